"""Review B of compositing (findings F1-F13): frames that cannot be composed are left out with a
reason rather than breaking the mosaic, the live view's worker survives its failures, partial
files are never left behind, and the options' costs stay bounded."""

from __future__ import annotations

import json
import time
import warnings

import cv2
import numpy as np
import pytest

from fusedmosaic.compositing import (
    BlendOptions,
    CanvasOptions,
    IncrementalCanvas,
    NoFrameToComposeError,
    live_view,
    plan_canvas,
    render_mosaic,
    screen_frames,
    write_mosaic_png,
)
from fusedmosaic.compositing import canvas as canvas_module
from fusedmosaic.compositing import video as video_module
from fusedmosaic.compositing.blending import FrameWarper, max_bands
from fusedmosaic.compositing.live_view import LiveMosaicView


def _shift(dx: float, dy: float = 0.0) -> np.ndarray:
    return np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]])


def _row(n: int, step: float) -> np.ndarray:
    return np.stack([_shift(step * k) for k in range(n)])


def _textured(h: int, w: int, channels: int = 1, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    shape = (h, w) if channels == 1 else (h, w, channels)
    return cv2.GaussianBlur(rng.integers(40, 220, shape, np.uint8), (0, 0), 1.5)


class _Recorder:
    """A server stand-in keeping what LiveMosaicView sends (pyigtl's uint16 size check too)."""
    address, device_name, clients_served, messages_sent = "-", "Mosaic", 0, 0

    def __init__(self) -> None:
        self.sent: list[tuple[np.ndarray, np.ndarray]] = []

    def send(self, image, timestamp=None, *, ijk_to_world=None):
        if max(image.shape[:2]) > 65535:
            import struct

            struct.pack(">H", max(image.shape[:2]))  # raises as pyigtl's pack did
        self.sent.append((image.copy(), ijk_to_world))
        return 0


# -- F1: the robot method's frames are all checked for a black image ---------------------------

def _pcle(tmp_path, name: str, black) -> object:
    from fusedmosaic.simulation import PcleOptions, simulate_pcle

    root = simulate_pcle(tmp_path / name, PcleOptions(width=128, height=112, n_frames=12))
    paths = sorted((root / "frames").glob("*.png"))
    for k in (range(len(paths)) if black == "all" else black):
        image = cv2.imread(str(paths[k]), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(paths[k]), np.zeros_like(image))
    return root


def test_robot_black_frame_0_is_not_composed(tmp_path):
    """robot places every frame from the robot alone and calls frame 0 "placed": a black frame 0
    was pasted into mosaic.png (frame 5, black too, was left out), darkening the tissue under it
    from 79 to 25 grey levels."""
    from fusedmosaic.runner import run_dataset

    root = _pcle(tmp_path, "data", black=[0, 5])
    out = tmp_path / "out"
    run_dataset(root, "robot", out, progress=False, report=False)
    mosaic = json.loads((out / "report.json").read_text())["mosaic"]
    assert set(mosaic["skipped_frames"]) == {"0", "5"}, mosaic["skipped_frames"]
    assert mosaic["skipped_frames"]["0"].startswith("no visual content")
    assert mosaic["frames_shown"] == 10


def test_robot_all_frames_black_skips_the_mosaic_and_keeps_the_estimates(tmp_path):
    """Every frame black: no frame is left to compose. The run skipped nothing and wrote a
    mosaic of black frame 0 (F1); once frame 0 was judged, plan_canvas's ValueError would
    have failed the run and lost the estimates. The mosaic is skipped with a warning."""
    from fusedmosaic.runner import run_dataset

    root = _pcle(tmp_path, "black", black="all")
    out = tmp_path / "out"
    with pytest.warns(UserWarning, match=r"mosaic\.png not written: no frame to compose a mosaic "
                                         r"from: the 12 placed frame\(s\) are all left out"):
        run_dataset(root, "robot", out, progress=False, report=False)
    assert (out / "homographies.csv").is_file() and not (out / "mosaic.png").exists()
    mosaic = json.loads((out / "report.json").read_text())["mosaic"]
    assert mosaic["file"] is None and mosaic["skipped"].startswith("no frame to compose")
    assert len(mosaic["skipped_frames"]) == 12


def test_no_frame_error_is_a_value_error():
    with pytest.raises(NoFrameToComposeError, match="no placed frame to compose a mosaic from"):
        plan_canvas(np.full((2, 3, 3), np.nan), 32, 32)
    assert issubclass(NoFrameToComposeError, ValueError)


# -- F2: a footprint beyond int64 ---------------------------------------------------------------

def test_footprint_beyond_the_canvas_range_is_left_out():
    """diag(2e17, 5e-18, 1): det 1, a normal area, an x extent of 2e19 px. The canvas bounds
    overflowed int64 into a negative width that passed the pixel budget, and render_mosaic
    failed ("negative dimensions")."""
    G = _row(10, 20.0)
    G[9] = np.diag([2e17, 5e-18, 1.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (the overflow was a RuntimeWarning too)
        plan = plan_canvas(G, 100, 100)
        assert plan.use.tolist() == [True] * 9 + [False]
        assert plan.skipped[9].startswith("footprint beyond the canvas range")
        assert (plan.width, plan.height) == (260, 100)
        frames = [np.full((100, 100), 100, np.uint8)] * 10
        assert render_mosaic(frames, G, 100, 100).image.shape == (100, 260)
        canvas = IncrementalCanvas(100, 100)
        for k in range(10):
            canvas.add(frames[k], G[k])
        assert canvas.skipped[0][0] == 9
        assert canvas.skipped[0][1].startswith("footprint beyond the canvas range")


# -- F3: screening and warping test the same pixel extent --------------------------------------

def test_frame_whose_pixel_extent_crosses_the_horizon_is_left_out():
    """The horizon between pixel corner (-0.5, -0.5) and (0, 0): plan_canvas kept the frame
    (corners 0..W), its warp box (corners -0.5..W-0.5) was None and render_mosaic raised
    "homography has no valid footprint" for the whole mosaic."""
    G = _row(5, 30.0)
    G[4] = np.array([[1.0, 0, 0], [0, 1.0, 0], [0.01, 0.01, 0.002]])
    plan = plan_canvas(G, 100, 100)
    assert plan.skipped == {4: "footprint behind the camera"}
    frames = [np.full((100, 100), 100, np.uint8)] * 5
    render_mosaic(frames, G, 100, 100)  # no longer raises


# -- F4 / F10 / F11: the live view -------------------------------------------------------------

def test_live_view_worker_survives_a_canvas_wider_than_openigtlink_takes():
    """A view 70000 px wide (1.1 Mpx of bounding box, within max_pixels): the IMAGE message's
    size is uint16, the send raised struct.error, the worker died and every later frame was
    lost without a problem recorded. The image is now sent shrunk by a whole factor, its
    geometry saying so. (Frames every 200 px, one place: two frames 70000 px apart are two
    places since session 51, and the view shows the latest frames' one.)"""
    server = _Recorder()
    view = LiveMosaicView(16, 16, server=server, interval_s=0.0)
    image = np.full((16, 16), 200, np.uint8)
    for x in range(0, 70001, 200):
        view.add(image, _shift(x))
        while view._queue.qsize() > 10:  # (not beyond the worker's MAX_QUEUED)
            time.sleep(0.001)
    for k in range(1, 6):
        view.add(image, _shift(16 * k))
    view.close(timeout_s=30)
    assert view.frames_added == 356 and view.problems == {}, view.problems
    assert view.summary()["places"] == 1
    sent, matrix = server.sent[-1]
    summary = view.summary()
    width, height = summary["width"], summary["height"]
    assert width > 70000 and height < 20
    assert sent.shape == (-(-height // 2), -(-width // 2))  # shrunk twice
    assert summary["server"]["downscaled"] >= 1 and summary["server"]["scale"] == 0.5
    # image pixel (0, 0) is the mean of canvas pixels 0 and 1: its centre half a pixel on
    x0, y0 = summary["origin_reference_px"]
    assert matrix[0, 0] == 2.0 and matrix[:2, 3] == pytest.approx([x0 + 0.5, y0 + 0.5])
    assert sent[4, 0] == 100  # area averaged: canvas column -1 empty, column 0 at 200
    assert sent.dtype == np.uint8


def test_live_view_worker_records_any_error_and_goes_on(monkeypatch):
    """Only ValueError and cv2.error were caught: any other error (here the canvas's add, then
    the server's send) killed the worker."""
    view = LiveMosaicView(16, 16, interval_s=0.0, server=_Recorder())
    calls = []
    real_add = view.canvas.add

    def flaky(image, G):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("something unforeseen at frame 1")
        return real_add(image, G)

    monkeypatch.setattr(view.canvas, "add", flaky)

    def broken_send(*args, **kwargs):
        raise ConnectionError("send failed")

    image = np.full((16, 16), 100, np.uint8)
    for k in range(3):
        view.add(image, _shift(8 * k))
    time.sleep(0.5)
    monkeypatch.setattr(view.server, "send", broken_send)
    view.add(image, _shift(30))
    view.close(timeout_s=30)
    assert not view._thread.is_alive()
    assert view.frames_added == 3
    kinds = view.summary()["problems"]
    assert kinds["frame left out of the view: RuntimeError: something unforeseen at frame N"] == 1
    assert kinds["not published: ConnectionError: send failed"] >= 1
    details = view.summary()["problem_details"]
    first = details["frame left out of the view: RuntimeError: something unforeseen at frame N"]
    assert first == {"frame": 1, "message": "RuntimeError: something unforeseen at frame 1"}


def test_live_view_problems_have_one_key_per_kind():
    """Keys were the exception's text, naming the frame and where it landed: once the tile
    budget was spent, every frame added a key (94 keys for 300 frames)."""
    view = LiveMosaicView(64, 64, interval_s=1e9, max_pixels=256 * 256 * 4)
    image = np.full((64, 64), 150, np.uint8)
    for k in range(40):
        view.add(image, _shift(40.0 * k))
        time.sleep(0.002)  # (the worker keeps up: no "frames were waiting")
    view.close()
    problems = view.summary()["problems"]
    assert list(problems) == ["frame left out of the view: the live canvas's tiles would exceed "
                              "max_pixels"], problems
    assert sum(problems.values()) == 40 - view.frames_added
    detail = view.summary()["problem_details"][next(iter(problems))]
    assert detail["frame"] == view.frames_added and "live canvas would need" in detail["message"]


def test_live_view_problem_kinds_are_bounded():
    view = LiveMosaicView(16, 16, interval_s=0.0)
    for k in range(live_view.MAX_PROBLEM_KINDS + 10):
        view._problem(f"kind {k}")
    view.close()
    assert len(view.problems) == live_view.MAX_PROBLEM_KINDS + 1


@pytest.mark.realtime  # (wall-clock pacing: run alone, not beside another worker)
def test_live_view_publication_interval_follows_its_cost(monkeypatch):
    """Each publication renders and encodes the whole canvas (4096 x 4096: ~1.8 s); at the
    1 s interval the worker ate a whole core. The next publication now waits PUBLISH_DUTY x
    the last one's cost."""
    view = LiveMosaicView(16, 16, interval_s=0.0)
    real_render = view.canvas.render

    def slow_render(*args, **kwargs):
        time.sleep(0.1)
        return real_render(*args, **kwargs)

    monkeypatch.setattr(view.canvas, "render", slow_render)
    image = np.full((16, 16), 100, np.uint8)
    for k in range(20):
        view.add(image, _shift(4 * k))
        time.sleep(0.01)
    view.close(timeout_s=30)
    summary = view.summary()
    assert summary["publish_s"]["last"] >= 0.1
    assert summary["effective_interval_s"] >= live_view.PUBLISH_DUTY * 0.1
    assert view.frames_added == 20
    assert view.published <= 3  # the first, at most one more within ~0.4 s, and the last


# -- F5: IncrementalCanvas with a per-frame mask -----------------------------------------------

def test_incremental_canvas_checks_channels_with_a_frame_mask():
    """Each mask has its own FrameWarper and channel count: a colour frame with its own mask
    after grey frames passed the check, broke the tiles (an opaque broadcast error after the
    call number had advanced) or, on new tiles, every later render()."""
    grey = np.full((64, 64), 100, np.uint8)
    colour = np.full((64, 64, 3), 200, np.uint8)
    mask = np.full((64, 64), 255, np.uint8)
    mask[:2] = 0
    for dx in (48, 200):  # over the existing tiles, then on new tiles only
        canvas = IncrementalCanvas(64, 64, tile_size=32)
        canvas.add(grey, _shift(0))
        tiles = len(canvas.tiles)
        with pytest.raises(ValueError, match=r"^frame 1: 3 channel\(s\), earlier frames have 1$"):
            canvas.add(colour, _shift(dx), mask=mask)
        assert len(canvas.tiles) == tiles and canvas._calls == 1 and canvas.frames_added == 1
        assert canvas.render().ndim == 2  # (grey)
        # a grey frame with that mask is still taken, as frame 1
        assert canvas.add(grey, _shift(dx), mask=mask) is not None
        assert canvas.frames_added == 2 and canvas.skipped == []


# -- F6: bands capped at what the frames support -----------------------------------------------

def test_bands_are_capped_at_what_the_frame_size_supports():
    """--bands 10 padded each 64 x 64 frame to ~7000 x 7000 float32 (3.4 s, 1.5 GB for two
    frames); it is lowered to log2 of the smaller side, with a warning."""
    frames = [_textured(64, 64, seed=k) for k in range(2)]
    G = np.stack([np.eye(3), _shift(40)])
    assert max_bands(64, 64) == 6 and max_bands(64, 48) == 5
    with pytest.warns(UserWarning, match=r"multiband bands \(--bands\) 10 is more than 64x64 "
                                         r"frames support \(log2 of the smaller side: 6\)"):
        capped = render_mosaic(frames, G, 64, 64, blend=BlendOptions("multiband", bands=10))
    six = render_mosaic(frames, G, 64, 64, blend=BlendOptions("multiband", bands=6))
    np.testing.assert_array_equal(capped.image, six.image)


def test_default_bands_unchanged_for_ordinary_frames():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        frames = [_textured(48, 64, seed=k) for k in range(2)]
        render_mosaic(frames, np.stack([np.eye(3), _shift(30)]), 64, 48, blend="multiband")


# -- F7: tiles warp only the part of a frame they need -----------------------------------------

def test_tiles_warp_only_the_part_of_a_large_frame_they_need(tmp_path, monkeypatch):
    """A thin diagonal footprint (16 x the median area: kept) has a ~6000 x 6000 box; each of
    the 36 tiles it touches warped the whole box (497 MB, 10 s). Now a patch too large for the
    cache is warped over the tile's region only; the mosaic is the same. (Its extent, ~60 x the
    median's, is screened by default since review 46: a factor of 100 keeps it here.)"""
    frames = [np.full((100, 100), 120, np.uint8) for _ in range(6)]
    G = _row(6, 60.0)
    G[5] = np.array([[60.0, -0.1, 0], [60.0, 0.1, 0], [0, 0, 1]])
    warped = []
    real = canvas_module.FrameWarper.warp

    def counting(self, image, G, **kwargs):
        patch = real(self, image, G, **kwargs)
        warped.append(patch.data.shape[0] * patch.data.shape[1])
        return patch

    monkeypatch.setattr(canvas_module.FrameWarper, "warp", counting)
    plan, covered = write_mosaic_png(tmp_path / "m.png", frames, G, 100, 100,
                                     canvas=CanvasOptions(absurd_area_factor=100.0))
    # (the frame's pixel extent -0.5 .. W - 0.5, magnified 60 x: 5951 from pixel centres)
    assert (plan.width, plan.height) == (6011, 6011) and plan.use.all()
    assert max(warped) <= (1024 + 1) ** 2  # a tile's region, not the 6011^2 box
    mosaic = cv2.imread(str(tmp_path / "m.png"), cv2.IMREAD_UNCHANGED)
    # the sliver's pixels: the one-piece warp of the same frame (whole box, no clipping)
    alone = render_mosaic([frames[5]], G[5:6], 100, 100)
    box = alone.plan
    sub = mosaic[box.y0 - plan.y0:box.y1 - plan.y0, box.x0 - plan.x0:box.x1 - plan.x0]
    only5 = alone.covered.copy()
    first = render_mosaic(frames[:5], G[:5], 100, 100).plan
    only5[first.y0 - box.y0:first.y1 - box.y0, first.x0 - box.x0:first.x1 - box.x0] = False
    assert np.abs(sub[only5].astype(int) - alone.image[only5]).max() <= 1


def test_tiled_output_unchanged_when_patches_fit_the_cache(tmp_path, monkeypatch):
    """Ordinary frames: every patch fits the cache and is warped whole, as before, so the tiled
    mosaic is the one-piece one exactly (linear)."""
    frames = [_textured(80, 96, 3, seed=k) for k in range(8)]
    G = np.stack([_shift(30.0 * k, 7.0 * (k % 3)) for k in range(8)])
    one = render_mosaic(frames, G, 96, 80)
    write_mosaic_png(tmp_path / "t.png", frames, G, 96, 80, canvas=CanvasOptions(tile_size=64))
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "t.png")), one.image)


# -- F8: an interrupt in MosaicVideoWriter.close() ---------------------------------------------

def test_interrupt_while_closing_the_video_leaves_nothing(tmp_path, monkeypatch):
    frames = [np.full((64, 64, 3), 100, np.uint8)] * 3

    class Interrupted:
        def __init__(self, *args):
            raise KeyboardInterrupt

    monkeypatch.setattr(video_module.cv2, "VideoCapture", Interrupted)
    with pytest.raises(KeyboardInterrupt):
        video_module.write_creation_video(tmp_path / "creation.mp4", frames, _row(3, 20.0), 64,
                                          64, (0, 0, 104, 64))
    assert list(tmp_path.iterdir()) == []


# -- F9: write_mosaic_png keeps an earlier file on failure -------------------------------------

def test_failed_write_mosaic_png_keeps_the_earlier_file(tmp_path):
    path = tmp_path / "mosaic.png"
    cv2.imwrite(str(path), np.full((50, 50, 3), 128, np.uint8))
    before = path.read_bytes()
    frames = [_textured(64, 64, 3, seed=k) for k in range(40)]

    class Failing(list):
        def __getitem__(self, k):
            if k == 30:
                raise OSError("disk read error on frame 30")
            return list.__getitem__(self, k)

    with pytest.raises(OSError, match="disk read error on frame 30"):
        write_mosaic_png(path, Failing(frames), _row(40, 40.0), 64, 64,
                         canvas=CanvasOptions(tile_size=64))
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["mosaic.png"]
    write_mosaic_png(path, frames, _row(40, 40.0), 64, 64, canvas=CanvasOptions(tile_size=64))
    assert cv2.imread(str(path)).shape == (64, 1624, 3)
    assert [p.name for p in tmp_path.iterdir()] == ["mosaic.png"]


# -- F12: mirrored footprints ------------------------------------------------------------------

def test_mirrored_footprint_is_left_out():
    G = _row(6, 30.0)
    G[5] = np.array([[-1.0, 0, 250], [0, 1, 0], [0, 0, 1]])
    use, reasons = screen_frames(G, 100, 100)
    assert use.tolist() == [True] * 5 + [False]
    assert reasons == {5: "mirrored footprint (the homography flips the frame)"}
    canvas = IncrementalCanvas(100, 100)
    frames = [np.full((100, 100), 100, np.uint8)] * 6
    for k in range(6):
        canvas.add(frames[k], G[k])
    assert canvas.skipped == [(5, "mirrored footprint (the homography flips the frame)")]
    # a rotation by 180 degrees is no mirror
    G[5] = np.array([[-1.0, 0, 250], [0, -1, 100], [0, 0, 1]])
    assert screen_frames(G, 100, 100)[0].all()


# -- F13: 16-bit frames ------------------------------------------------------------------------

def test_render_mosaic_refuses_16_bit_frames():
    """A mid-grey 16-bit frame rendered pure white, silently."""
    frame = np.full((64, 64), 12000, np.uint16)
    with pytest.raises(ValueError, match=r"frame 0: image is uint16, expected uint8: .*16-bit: "
                                         r"\(image >> 8\)\.astype\(np\.uint8\)"):
        render_mosaic([frame], np.eye(3)[None], 64, 64)
    with pytest.raises(ValueError, match=r"image is float64, expected uint8: .*0\.\.1 floats"):
        FrameWarper(64, 64).warp(np.zeros((64, 64)), np.eye(3), name=0)


# -- --tile-size upper bound -------------------------------------------------------------------

def test_tile_size_has_an_upper_bound():
    with pytest.raises(ValueError, match=r"--tile-size must be in 64\.\.8192 \(pixels; "):
        CanvasOptions(tile_size=50_000).validate({"tile_size": "--tile-size"})
    CanvasOptions(tile_size=8192).validate()
