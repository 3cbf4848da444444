"""Review 46 (F) of compositing (findings 1-9): the over-budget stray search stays O(N log N),
the live view keeps publishing past its budget (shrunk), the creation video keeps the options'
specular masking, writes that fail at their end are errors naming the file (mosaic.png, the
recording's frames, the streamed PNG, a video cut in its last atom), a thin footprint of
normal area is screened, the streamed PNG's memory is bounded by a chunk, and a 3-channel
field-of-view mask is named as such."""

from __future__ import annotations

import os
import re
import tracemalloc

import cv2
import numpy as np
import pytest
from _faults import file_size_limit

from fusedmosaic.compositing import (
    BlendOptions,
    CanvasOptions,
    IncrementalCanvas,
    live_view,
    plan_canvas,
    render_mosaic,
    write_creation_video,
)
from fusedmosaic.compositing import canvas as canvas_module
from fusedmosaic.compositing import video as video_module
from fusedmosaic.compositing.live_view import LiveMosaicView, shrink_step
from fusedmosaic.compositing.png import PngStreamWriter
from fusedmosaic.compositing.video import MosaicVideoWriter
from fusedmosaic.io.output import OutputWriter


def _shift(dx: float, dy: float = 0.0) -> np.ndarray:
    return np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]])


def _smooth(h: int, w: int, channels: int = 3, seed: int = 0) -> np.ndarray:
    """A smooth colour texture (compresses as an image does, not as noise)."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (max(1, h // 8), max(1, w // 8), channels)).astype(np.uint8)
    image = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    return image.reshape(h, w, channels)


# -- 1: the over-budget stray search -----------------------------------------------------------

def _groups_by_all_pairs(G: np.ndarray, width: int, height: int) -> list[list[int]]:
    """The groups from every pair of centres within the radius (the former quadratic way)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    fp = canvas_module.footprints(G, width, height)
    centres = fp.mean(axis=1)
    diagonal = float(np.median(np.maximum(np.linalg.norm(fp[:, 2] - fp[:, 0], axis=1),
                                          np.linalg.norm(fp[:, 3] - fp[:, 1], axis=1))))
    pairs = cKDTree(centres).query_pairs((canvas_module.STRAY_DIAGONALS + 1) * diagonal,
                                         output_type="ndarray").reshape(-1, 2)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(G),) * 2)
    _, labels = connected_components(graph, directed=False)
    return sorted(sorted(np.flatnonzero(labels == k).tolist()) for k in np.unique(labels))


def _layouts(rng: np.random.Generator):
    """(name, (N, 2) frame positions): scattered, clustered far apart, on one line (which Qhull
    refuses), with duplicates, and fewer than three frames."""
    for n in (1, 2, 3, 7, 40, 300):
        yield f"scattered {n}", rng.uniform(-3000, 3000, (n, 2))
    blobs = rng.integers(0, 4, 200)
    yield "clusters", rng.normal(0, 200, (200, 2)) + np.array([[0, 0], [5000, 0], [0, 9e5],
                                                                [2e4, 2e4]])[blobs]
    yield "row", np.c_[np.sort(rng.uniform(0, 20000, 150)), np.zeros(150)]
    yield "tilted line", np.outer(rng.uniform(0, 40000, 150), [0.6, 0.8])
    yield "two points on a line, apart", np.array([[0.0, 0], [1e5, 0]])
    grid = np.round(rng.uniform(0, 6, (120, 2))) * 900.0  # many at the same spot
    yield "duplicates", grid
    yield "one spot", np.zeros((5, 2))
    yield "duplicates on a line", np.c_[np.round(rng.uniform(0, 30, 80)) * 1000.0, np.zeros(80)]


def test_stray_groups_are_those_of_all_pairs():
    """The groups from the Delaunay edges (and the fallbacks) equal those of every pair within
    the radius, on layouts Qhull handles and those it refuses."""
    rng = np.random.default_rng(46)
    width = height = 100  # radius 11 x 141 px
    for name, xy in _layouts(rng):
        G = np.stack([_shift(x, y) for x, y in xy])
        use = np.ones(len(G), bool)
        groups = sorted(g.tolist() for g in canvas_module._proximity_groups(G, width, height,
                                                                            use))
        assert groups == _groups_by_all_pairs(G, width, height), name


def test_over_budget_stray_search_is_not_quadratic():
    """20 000 frames of a compact sweep, one sent 1e6 px away: every pair lies within the
    search radius, and listing the pairs took 2.8 GB at 10 000 frames (16.6 s; ~11 GB at
    20 000). Now the stray is found with memory linear in the frames (12 MB traced here)."""
    n, rng = 20_000, np.random.default_rng(0)
    G = np.tile(np.eye(3), (n, 1, 1))
    G[:, 0, 2] = rng.uniform(-2000, 2000, n)
    G[:, 1, 2] = rng.uniform(-2000, 2000, n)
    G[n // 2, 0, 2] = 1e6
    tracemalloc.start()
    try:
        groups = canvas_module._proximity_groups(G, 512, 448, np.ones(n, bool))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert sorted(len(g) for g in groups) == [1, n - 1]
    plan = plan_canvas(G, 512, 448, max_pixels=400_000_000)
    assert list(plan.skipped) == [n // 2]
    assert plan.skipped[n // 2].startswith("stray: lands 9.98e+05 px from the other frames")
    assert plan.width < 5000 and plan.use.sum() == n - 1
    assert peak < 64 * 2**20, f"{peak / 2**20:.0f} MB traced"


# -- 2: the live view past its budget ----------------------------------------------------------

def test_shrunk_render_is_the_area_mean_of_the_full_one():
    rng = np.random.default_rng(3)
    for channels in (1, 3):
        canvas = IncrementalCanvas(60, 60, tile_size=16)
        for k in range(12):
            image = rng.integers(0, 256, (60, 60, channels)).astype(np.uint8)
            canvas.add(image[:, :, 0] if channels == 1 else image, _shift(37 * k, 23 * k - 50))
        x0, y0, x1, y1 = canvas.bounds
        for box in (None, (x0 + 13, y0 + 5, x1 - 20, y1 - 7)):
            full = canvas.render(box).astype(np.float64)
            for step in (2, 3, 16, 1000):
                h, w = full.shape[:2]
                padded = np.zeros((-(-h // step) * step, -(-w // step) * step) + full.shape[2:])
                padded[:h, :w] = full
                mean = padded.reshape(padded.shape[0] // step, step, padded.shape[1] // step,
                                      step, *full.shape[2:]).mean(axis=(1, 3))
                shrunk = canvas.render(box, step=step)
                assert shrunk.shape == mean.shape and shrunk.dtype == np.uint8
                assert np.abs(shrunk - mean).max() <= 0.5 + 1e-3, (channels, box, step)
    with pytest.raises(ValueError, match=r"render: step must be an integer >= 1, got 0"):
        canvas.render(step=0)
    small = IncrementalCanvas(60, 60, tile_size=16, max_pixels=14_000)
    small.add(np.zeros((60, 60), np.uint8), _shift(0))
    small.add(np.zeros((60, 60), np.uint8), _shift(200, 200))  # tiles: 12 800 pixels
    assert small.bounds == (-1, -1, 261, 261)
    with pytest.raises(live_view.CanvasTooLargeError,
                       match=r"render: the view of x -1..261, y -1..261 shrunk 2 times is 131 x "
                             r"131 pixels, above the budget of 14000 pixels"):
        small.render(step=2)
    assert small.render(step=3).shape == (88, 88)


def test_shrink_step_is_the_least_that_fits():
    for width, height, budget in ((6302, 6302, 50_000_000), (10052, 10052, 50_000_000),
                                  (1000, 1, 7), (99, 4999, 100), (10**15, 3, 50_000_000)):
        step = shrink_step(width, height, budget)
        assert -(-width // step) * -(-height // step) <= budget
        assert step == 1 or -(-width // (step - 1)) * -(-height // (step - 1)) > budget
    assert shrink_step(6302, 6302, 50_000_000) == 1 and shrink_step(10052, 10052, 50_000_000) == 2


def test_live_view_keeps_publishing_past_its_budget(tmp_path):
    """A diagonal sweep whose bounding box passes the budget while its tiles stay far below:
    publishing stopped there for the rest of the session (problems 'not published: the
    canvas's bounding box is above max_pixels'; the last view showed ~125 of 200 frames). Now
    the view is published shrunk, told once, and shows the last frame."""
    told: list[str] = []
    preview = tmp_path / "view.png"
    view = LiveMosaicView(100, 100, preview=preview, interval_s=0.0, max_pixels=3_000_000,
                          notify=told.append)
    image = np.full((100, 100), 128, np.uint8)
    for k in range(40):
        view.add(image, _shift(50 * k, 50 * k))
    view.close(timeout_s=60)
    summary = view.summary()
    assert summary["problems"] == {} and summary["frames_drawn"] == 40
    x0, y0, x1, y1 = view.canvas.bounds  # 2052 x 2052: 4.2 Mpx, shrunk twice
    assert (x1 - x0, y1 - y0) == (2052, 2052) and view.canvas.tile_pixels < 3_000_000
    assert summary["reduced"] >= 1 and summary["view_max_pixels"] == 3_000_000
    assert (summary["width"], summary["height"]) == (1026, 1026)
    assert summary["scale"] == 0.5
    assert summary["origin_reference_px"] == pytest.approx([x0 + 0.5, y0 + 0.5])
    shown = cv2.imread(str(preview), cv2.IMREAD_UNCHANGED)
    assert shown.shape == (1026, 1026)
    # the last frame (reference 1950..2049) is shown, the middle of its footprint at 128
    assert shown[(2000 - y0) // 2, (2000 - x0) // 2] == 128
    assert shown[(1900 - y0) // 2, (2040 - x0) // 2] == 0  # (beside the sweep: empty)
    assert len(told) == 1 and re.match(
        r"live view: the mosaic's bounding box \(\d+ x \d+ pixels\) is above the view's budget "
        r"of 3000000 pixels: it is published shrunk 2 times \(area averaged\)", told[0])


def test_live_view_budget_follows_the_canvas_options(tmp_path):
    """run_igtl's view took a fixed 50 Mpx, not --max-canvas-pixels."""
    from fusedmosaic.io.calibration import Camera
    from fusedmosaic.runner import _live_view

    camera = Camera(64, 48, camera_matrix=np.array([[60.0, 0, 32], [0, 60, 24], [0, 0, 1]]))
    told: list[str] = []
    view, server = _live_view(camera, "ncc", tmp_path / "rec", tmp_path / "v.png", None, 1.0,
                              told.append, None, 3_000_000, told.append)
    try:
        assert server is None and view.canvas.max_pixels == 3_000_000
        assert view.view_max_pixels == 3_000_000 and view._notify == told.append
    finally:
        view.close()
    view, _ = _live_view(camera, "ncc", tmp_path / "rec", tmp_path / "v.png", None, 1.0,
                         told.append)
    try:  # run_igtl without canvas options: CanvasOptions' budget, views of 50 Mpx at most
        assert view.canvas.max_pixels == CanvasOptions().max_pixels
        assert view.view_max_pixels == live_view.VIEW_MAX_PIXELS == 50_000_000
    finally:
        view.close()


# -- 3: the creation video's options -----------------------------------------------------------

def test_video_of_a_multiband_run_keeps_specular_masking(tmp_path):
    """--blend multiband's video is drawn linear; the options were rebuilt without
    mask_specular, and each frame's highlight left a trail along the path in lba-emt's video
    (the demo's) while mosaic.png had none. Now its canvas is the linear one's."""
    W = H = 160
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.integers(60, 160, (300, 400, 3)).astype(np.uint8), (0, 0), 2)
    frames, G = [], np.stack([_shift(12 * k) for k in range(8)])
    for k in range(8):
        frame = texture[50:50 + H, 50 + 12 * k:50 + 12 * k + W].copy()
        cv2.circle(frame, (80, 80), 6, (255, 255, 255), -1)  # a highlight fixed to the camera
        frames.append(frame)
    bounds = (0, 0, 12 * 7 + W, H)
    views = {}
    for blend in ("linear", "multiband"):
        options = BlendOptions(blend, mask_specular=True, border_px=2.0)
        with MosaicVideoWriter(tmp_path / f"{blend}.mp4", bounds, W, H, blend=options,
                               outline=False) as video:
            assert video.canvas.options == BlendOptions("linear", mask_specular=True,
                                                        border_px=2.0)
            for frame, g in zip(frames, G, strict=True):
                video.add(frame, g)
            views[blend] = video.canvas.render()
    np.testing.assert_array_equal(views["multiband"], views["linear"])
    assert views["multiband"][80, 80:165].max() < 140  # no trail of 255s along row 80


# -- 4: an image write that fails at its end ---------------------------------------------------

def test_write_image_cut_short_is_an_error_naming_the_file(tmp_path):
    """cv2.imwrite does not check its last write: a mosaic.png 300 bytes short of its size (a
    file size limit, as a full disk) was committed, unreadable, with exit 0."""
    image = _smooth(300, 400)
    size = len(cv2.imencode(".png", image)[1])
    out = tmp_path / "out"
    with file_size_limit(size - 300), pytest.raises(OSError) as caught:  # (exit 1: review 47)
        with OutputWriter(out, record="review") as w:
            w.write_image("mosaic.png", image)
    assert caught.value.filename == str(out / "mosaic.png")
    assert caught.value.strerror.startswith("the image could not be written (File too large: a "
                                            "full disk, or no write permission in ")
    assert not out.exists()
    with OutputWriter(out, record="review") as w:  # without the limit, as before
        w.write_image("mosaic.png", image)
    np.testing.assert_array_equal(cv2.imread(str(out / "mosaic.png")), image)


def test_recorded_frame_cut_short_is_an_error(tmp_path):
    """The recording's frames (the only copy) went through cv2.imwrite too."""
    from fusedmosaic.io.calibration import Camera
    from fusedmosaic.io.recorder import PNG_COMPRESSED, DatasetRecorder

    camera = Camera(200, 150, camera_matrix=np.array([[60.0, 0, 100], [0, 60, 75], [0, 0, 1]]))
    image = _smooth(150, 200)
    size = len(cv2.imencode(".png", image, PNG_COMPRESSED)[1])
    recorder = DatasetRecorder(tmp_path / "rec", camera)
    with file_size_limit(size - 300):
        recorder.add_sample(0.0, np.eye(4))
        recorder.add_frame(image, 0.0)
        with pytest.raises(ValueError, match=r"rec: no frame could be written: .*"
                                             r"\.000000\.part\.png: File too large"):
            recorder.finish()
    assert not (tmp_path / "rec").exists()


# -- 5: a thin footprint of normal area --------------------------------------------------------

def _sliver(s: float) -> np.ndarray:
    """50 frames 100 x 100 along 590 px; frame 25 stretched s times and squeezed as much: its
    area is the others', its centre among theirs."""
    G = np.stack([_shift(10 * k) for k in range(50)])
    G[25] = np.array([[s, 0, 250 - s * 50], [0, 1 / s, 50 - 50 / s], [0, 0, 1.0]])
    return G


def test_thin_footprint_of_normal_area_is_left_out():
    """It passed the area screen and the stray rule: a 990001 x 100 canvas 99 % black
    (s = 1e4), or the whole mosaic refused (s = 1e5)."""
    for s in (1e4, 1e5):
        plan = plan_canvas(_sliver(s), 100, 100)
        assert (plan.width, plan.height) == (590, 100)
        assert plan.skipped == {25: f"footprint extent {int(round(s / np.sqrt(2))):d} x the "
                                    "median (its bounding box's diagonal; limit 20)"}
    assert plan_canvas(_sliver(4.0), 100, 100).skipped == {}  # (extent 2.9 x: kept)
    canvas = IncrementalCanvas(100, 100, blend="last")
    image = np.full((100, 100), 90, np.uint8)
    G = _sliver(1e4)
    assert all(canvas.add(image, G[k]) is not None for k in range(25))
    assert canvas.add(image, G[25]) is None
    assert canvas.skipped == [(25, "footprint extent 7071 x the recent median (its bounding "
                                   "box's diagonal)")]


# -- 6 and 7: the streamed PNG -----------------------------------------------------------------

def test_streamed_png_memory_is_bounded_by_a_chunk(tmp_path):
    """write_rows made four copies of the band (286 MB -> 1148 MB more); the encoding now takes
    about 9 chunks of 1 MiB, whatever the band (before: ~4 x its 47 MB here)."""
    band = _smooth(512, 10_000)
    path = tmp_path / "band.png"
    tracemalloc.start()
    try:
        with PngStreamWriter(path, band.shape[1], 2 * band.shape[0], 3) as png:
            png.write_rows(band[:301])  # row counts that split chunks
            png.write_rows(band[301:])
            png.write_rows(band[::-1])
            peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 * 2**20, f"{peak / 2**20:.0f} MB traced beyond the band"
    np.testing.assert_array_equal(cv2.imread(str(path)), np.concatenate([band, band[::-1]]))
    for channels in (1, 2, 4):  # grey, grey + alpha (read back by PIL), BGRA
        image = _smooth(300, 2000, channels, seed=channels)
        with PngStreamWriter(tmp_path / f"c{channels}.png", 2000, 300, channels) as png:
            png.write_rows(image[:150])
            png.write_rows(image[150:])
        if channels == 2:
            from PIL import Image

            back = np.asarray(Image.open(tmp_path / "c2.png"))
        else:
            back = cv2.imread(str(tmp_path / f"c{channels}.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(back.reshape(image.shape), image)


@pytest.mark.parametrize("where", ["write_rows", "close"])
def test_streamed_png_write_error_names_the_file(tmp_path, where):
    """The path was named only for errors in open(): `fusedmosaic run --alpha` under a file
    size limit said only 'error: File too large'."""
    path = tmp_path / "mosaic.png"
    if where == "write_rows":  # an incompressible band: a 1 MiB IDAT chunk written at once
        image = np.random.default_rng(0).integers(0, 256, (700, 700, 3)).astype(np.uint8)
    else:  # a small image, written at close()
        image = np.full((100, 100, 3), 7, np.uint8)
    with file_size_limit(40), pytest.raises(OSError) as caught:
        with PngStreamWriter(path, image.shape[1], image.shape[0], 3) as png:
            png.write_rows(image)
            assert where == "close"  # (write_rows raised otherwise)
    assert caught.value.filename == str(path) and caught.value.strerror == "File too large"
    assert os.listdir(tmp_path) == []  # no temporary file left


# -- 8: a video cut in its last atom -----------------------------------------------------------

def _frames(n: int = 60, size: int = 120) -> tuple[list[np.ndarray], np.ndarray]:
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (size, size, 3)).astype(np.uint8) for _ in range(n)]
    return frames, np.stack([_shift(7 * k, 3 * k) for k in range(n)])


def test_video_cut_in_its_last_atom_is_refused(tmp_path, monkeypatch):
    """A video 71 bytes short (the end of its moov atom, its metadata) still decoded its 60
    frames, and was committed; the atoms' sizes must now add up to the file's."""
    real = cv2.VideoWriter

    class CutShort:  # the writer's last write lost, as on a full disk
        def __init__(self, path, *args):
            self.path, self.writer = path, real(path, *args)

        def isOpened(self):  # noqa: N802 (OpenCV's name)
            return self.writer.isOpened()

        def write(self, frame):
            self.writer.write(frame)

        def release(self):
            self.writer.release()
            os.truncate(self.path, os.path.getsize(self.path) - 71)

    frames, G = _frames()
    plan = plan_canvas(G, 120, 120)
    bounds = (plan.x0, plan.y0, plan.x1, plan.y1)
    monkeypatch.setattr(video_module.cv2, "VideoWriter", CutShort)
    with pytest.raises(OSError, match=r"the video is incomplete \(the atom 'moov' at byte \d+ "
                                      r"declares \d+ bytes, 71 beyond the file's end at \d+; a "
                                      r"full disk\?\): no video written: '.*c\.mp4'"):
        write_creation_video(tmp_path / "c.mp4", frames, G, 120, 120, bounds)
    assert os.listdir(tmp_path) == []
    monkeypatch.setattr(video_module.cv2, "VideoWriter", real)
    for name in ("c.mp4", "c.mov", "c.m4v"):  # whole: read back, atoms adding up
        assert write_creation_video(tmp_path / name, frames[:5], G[:5], 120, 120, bounds) == 5
        assert video_module._atoms_problem(tmp_path / name) is None
    with open(tmp_path / "c.mov", "ab") as f:
        f.write(b"\0\0\0")
    assert video_module._atoms_problem(tmp_path / "c.mov") == "3 stray bytes at its end"


# -- 9: a 3-channel field-of-view mask ---------------------------------------------------------

def test_three_channel_mask_is_named_as_such():
    """'field-of-view mask is 40x30 but the frames are 40x30'."""
    mask = np.full((30, 40, 3), 255, np.uint8)
    message = (r"field-of-view mask must be one channel \(H, W\), got shape \(30, 40, 3\); the "
               r"frames are 40x30")
    with pytest.raises(ValueError, match=message):
        render_mosaic([np.zeros((30, 40), np.uint8)], np.eye(3)[None], 40, 30, mask=mask)
    with pytest.raises(ValueError, match=message):
        IncrementalCanvas(40, 30, mask=mask)
