"""Review 50 (compositing), canvas.py: multiband's per-frame cut (LOW 3) and the canvas bounds
of magnified frames (LOW 7)."""

import cv2
import numpy as np
import pytest

import fusedmosaic.compositing.canvas as canvas_module
from fusedmosaic.compositing import (
    BlendOptions,
    CanvasOptions,
    IncrementalCanvas,
    canvas_bounds,
    plan_canvas,
    render_mosaic,
    write_mosaic_png,
)

W, H = 160, 120


def rectangular_scene(seed: int, n: int = 13) -> tuple[list[np.ndarray], np.ndarray]:
    """n frames W x H cut from a smooth random texture by known frame -> reference homographies
    (frame 0 the reference; the others shifted by up to 250 px, turned by up to 0.1 rad, a
    little perspective). No field-of-view mask: the frames are tissue up to their edges, as
    SYN's (fetoscopy without fov_mask_radius)."""
    rng = np.random.default_rng(seed)
    coarse = rng.random((90, 90, 3), dtype=np.float32)
    texture = cv2.GaussianBlur(cv2.resize(coarse, (720, 720), interpolation=cv2.INTER_CUBIC),
                               (0, 0), 2.0)
    texture = (texture - texture.min()) / np.ptp(texture) * 200 + 30
    texture = texture.astype(np.uint8)
    G = [np.eye(3)]
    for _ in range(n - 1):
        angle = rng.uniform(-0.1, 0.1)
        g = np.array([[np.cos(angle), -np.sin(angle), 0.0],
                      [np.sin(angle), np.cos(angle), 0.0],
                      [rng.normal(0, 2e-5), 0.0, 1.0]])
        g[:2, 2] = rng.uniform(-150, 250, 2)
        G.append(g)
    G = np.array(G)
    to_texture = np.array([[1.0, 0, 250], [0, 1.0, 250], [0, 0, 1.0]])  # reference -> texture
    frames = [cv2.warpPerspective(texture, to_texture @ g, (W, H),
                                  flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP) for g in G]
    return frames, G


# -- LOW 3: multiband's cut ---------------------------------------------------------------------


def test_multiband_cut_stays_within_a_grey_level_of_the_uncut_blend(monkeypatch):
    """Each frame enters the pyramids cut to the pixels it owns plus MULTIBAND_REACH x 2^bands
    px. The cut part was filled outside the frame's footprint on its own, and this scene came
    out up to 4 grey levels off the blend of the uncut patches (45 pixels > 2); filled as the
    whole patch is, 1."""
    frames, G = rectangular_scene(1)
    options = BlendOptions("multiband", bands=5)
    cut = render_mosaic(frames, G, W, H, blend=options)
    monkeypatch.setattr(canvas_module, "MULTIBAND_REACH", 10**6)
    whole = render_mosaic(frames, G, W, H, blend=options)
    assert cut.plan.width > 400 and cut.plan.height > 400  # the frames spread out
    diff = np.abs(cut.image.astype(int) - whole.image).max(axis=2)
    assert diff.max() <= 1, (diff.max(), int((diff > 1).sum()))


@pytest.mark.parametrize("seed", [4, 5])
@pytest.mark.parametrize("tile", [64, 128])
def test_tiled_multiband_without_mask_close_to_one_piece(tmp_path, seed, tile):
    """No field-of-view mask, bands 5 (the default): tiled against one piece differed by up to
    6 / 4 grey levels (seeds 4 / 5: 405 / 92 pixels > 2, tile 64 or 128), where the test with a
    circular mask (test_compositing) stayed within 2: each tile filled the frames' parts outside
    their footprints from what it cut of them. Now 0."""
    frames, G = rectangular_scene(seed)
    options = BlendOptions("multiband", bands=5)
    one = render_mosaic(frames, G, W, H, blend=options)
    path = tmp_path / "tiled.png"
    plan, covered = write_mosaic_png(path, frames, G, W, H, blend=options,
                                     canvas=CanvasOptions(tile_size=tile))
    assert (plan.x0, plan.y0, plan.x1, plan.y1) == (one.plan.x0, one.plan.y0, one.plan.x1,
                                                    one.plan.y1)
    assert plan.width > 3 * tile or plan.height > 3 * tile
    diff = np.abs(cv2.imread(str(path)).astype(int) - one.image).max(axis=2)
    assert diff.max() <= 2, (diff.max(), int((diff > 2).sum()))
    assert diff.mean() < 0.05
    assert covered == pytest.approx(one.covered.mean())


# -- LOW 7: the canvas holds the whole pixel extent -------------------------------------------


@pytest.mark.parametrize("blend", ["linear", "last"])
def test_magnified_frame_keeps_its_rim_as_the_live_canvas(blend):
    """A frame zoomed 2x at frame 0 covers reference pixels -1 .. 2W - 1 (its pixel extent
    -0.5 .. W - 0.5). The bounds came from the pixel centres, (0, 0, 319, 239): mosaic.png lost
    the covered first row and column and the last ones, which IncrementalCanvas (the live
    view, the video) shows. Now both have (-1, -1, 320, 240) and the same pixels."""
    rng = np.random.default_rng(0)
    image = cv2.GaussianBlur(rng.integers(30, 230, (H, W, 3), np.uint8), (0, 0), 1.5)
    zoom = np.diag([2.0, 2.0, 1.0])[None]
    rendered = render_mosaic([image], zoom, W, H, blend=blend)
    live = IncrementalCanvas(W, H, blend=blend)
    live.add(image, zoom[0])
    box = (rendered.plan.x0, rendered.plan.y0, rendered.plan.x1, rendered.plan.y1)
    assert box == live.bounds == (-1, -1, 2 * W, 2 * H)
    assert rendered.covered.all()  # every row and column of the canvas is covered
    np.testing.assert_array_equal(live.render(box), rendered.image)
    # frames not magnified keep their bounds: at the origin, and a fractional shift keeps the
    # partly covered column and row it reaches
    shift = np.array([[1.0, 0, 0.3], [0, 1.0, -0.3], [0, 0, 1.0]])
    assert canvas_bounds(np.eye(3)[None], W, H) == (0, 0, W, H)
    assert canvas_bounds(shift[None], W, H) == (0, -1, W + 1, H)
    assert render_mosaic([image], shift[None], W, H, blend=blend).covered.all()
    plan = plan_canvas(np.stack([np.eye(3), zoom[0]]), W, H)
    assert (plan.x0, plan.y0, plan.x1, plan.y1) == box

