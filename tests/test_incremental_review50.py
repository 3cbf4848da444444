"""Review 50 (compositing path): IncrementalCanvas and LiveMosaicView.

- MEDIUM 1: a near-singular first frame's footprint listed every tile under its bounding box
  before the budget check (diag(1, 1, 1e-5): a MemoryError under a 2 GB cap, the live session
  OOM-killed without it).
- MEDIUM 2: a collapsed first frame seeded the recent median, every later frame was left out
  as "1000000 x the recent median", and the live view said nothing.
- LOW 4: `skipped` grew by an entry per frame left out (9.1 MB after 100 000).
- LOW 5: render(step=...) summed a whole view row at a time (592 MB for a 24.7 Mpx wide row).
"""

import tracemalloc

import cv2
import numpy as np
import pytest

from fusedmosaic.compositing import IncrementalCanvas, incremental
from fusedmosaic.compositing.canvas import CanvasTooLargeError
from fusedmosaic.compositing.live_view import LiveMosaicView

W, H = 64, 48
COLLAPSED = ("footprint area 0.00307 pixels, below 0.001 x the frame's own 3072 (a collapsed "
             "placement: a near-singular homography)")


def _shift(x: float, y: float = 0.0) -> np.ndarray:
    return np.array([[1.0, 0, x], [0, 1, y], [0, 0, 1]])


def _frames(n: int, seed: int = 0) -> list[np.ndarray]:
    """Frames of a smooth texture, frame k cut at (5 k, 0), as _shift(5 k) places it."""
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.integers(0, 255, (H, W + 5 * n), np.uint8), (0, 0), 2)
    return [texture[:, 5 * k:5 * k + W].copy() for k in range(n)]


def test_over_budget_footprint_refused_before_listing_its_tiles():
    """Before the fix: the 1.2 M tiles under the box listed first (peak ~100 MB, 0.2 s); at
    diag(1, 1, 1e-5), 4.7e8 of them (MemoryError under a 2 GB cap)."""
    image = np.full((H, W), 128, np.uint8)
    canvas = IncrementalCanvas(W, H, max_pixels=10_000_000)
    tracemalloc.start()
    try:
        with pytest.raises(CanvasTooLargeError, match=(
                r"^live canvas would need at least \d+ pixels of tiles, above the budget of "
                r"10000000 pixels \(frame 0 lands at x -\d+\.\.\d+, y -\d+\.\.\d+\); raise "
                "max_pixels")):
            canvas.add(image, np.diag([1.0, 1.0, 2e-4]))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20, peak
    # nothing changed: the next frame is frame 0 and is placed
    assert canvas.tiles == {} and canvas.skipped == []
    assert canvas.add(image, np.eye(3)) == (-1, -1, W + 1, H + 1) and canvas.frames_added == 1
    first = IncrementalCanvas(W, H, max_pixels=10_000_000)
    with pytest.raises(CanvasTooLargeError, match="frame 0 lands"):  # (6.4e10 px a side)
        first.add(image, np.diag([1.0, 1.0, 1e-9]))


def test_collapsed_first_frame_is_left_out_not_the_median():
    """Before the fix 1 frame of 40 was placed (the collapsed one)."""
    frames = _frames(40)
    Gs = [np.diag([1e-3, 1e-3, 1.0])] + [_shift(5.0 * k) for k in range(1, 40)]
    canvas = IncrementalCanvas(W, H)
    for image, G in zip(frames, Gs, strict=True):
        canvas.add(image, G)
    assert canvas.skipped == [(0, COLLAPSED)] and canvas.frames_added == 39
    reference = IncrementalCanvas(W, H)
    for image, G in zip(frames[1:], Gs[1:], strict=True):
        reference.add(image, G)
    np.testing.assert_array_equal(canvas.render(), reference.render())
    assert canvas.bounds == reference.bounds == (4, -1, 5 * 39 + W + 1, H + 1)


def test_mosaic_png_leaves_out_the_collapsed_frame_as_the_live_view():
    """The floor is canvas.footprint_problem's, shared: plan_canvas (mosaic.png) leaves the
    collapsed frame out with the same reason, and its canvas is that of the other 39 frames.
    Before (session 51) only IncrementalCanvas had the floor: mosaic.png drew the frame (a dot
    at the reference's origin) and its canvas reached x = 0, 5 px beyond the others'."""
    from fusedmosaic.compositing.canvas import plan_canvas

    Gs = np.stack([np.diag([1e-3, 1e-3, 1.0])] + [_shift(5.0 * k) for k in range(1, 40)])
    plan, others = plan_canvas(Gs, W, H), plan_canvas(Gs[1:], W, H)
    assert plan.skipped == {0: COLLAPSED} and plan.use.sum() == 39
    assert (plan.x0, plan.y0, plan.x1, plan.y1) == (others.x0, others.y0, others.x1, others.y1)
    assert plan.x0 == 5  # (the collapsed frame's dot at 0 is not on it)


def test_live_view_reports_the_frames_the_canvas_leaves_out():
    """Before the fix: frames_drawn 1, a 3 x 3 px view and problems {}."""
    frames = _frames(40)
    view = LiveMosaicView(W, H, interval_s=0.0)
    view.add(frames[0], np.diag([1e-3, 1e-3, 1.0]))
    for k in range(1, 40):
        view.add(frames[k], _shift(5.0 * k))
    view.add(frames[0], np.diag([-1.0, 1.0, 1.0]) @ _shift(7.0))  # mirrored
    view.add(frames[0], np.diag([-1.0, 1.0, 1.0]) @ _shift(9.0))
    view.close()
    summary = view.summary()
    assert summary["frames_drawn"] == 39 and (summary["width"], summary["height"]) == (256, 50)
    collapsed = ("frame left out of the view: footprint area N pixels, below N x the frame's "
                 "own N (a collapsed placement: a near-singular homography)")
    mirrored = ("frame left out of the view: mirrored footprint (the homography flips the "
                "frame)")
    assert summary["problems"] == {collapsed: 1, mirrored: 2}
    assert summary["problem_details"][collapsed] == {"frame": 0, "message": COLLAPSED}
    assert summary["problem_details"][mirrored]["frame"] == 40


def test_median_recovers_from_a_bad_seed_not_from_a_short_glitch():
    """A first frame of 1 / 100 of the area (above the collapse floor) seeds the median: the
    next frame is left out, the second re-bases it (before the fix every later frame was left
    out). An established median is kept through a short run of odd sizes, either way, and a run
    of sizes that disagree with each other never re-bases it."""
    frames = _frames(80)
    canvas = IncrementalCanvas(W, H)
    canvas.add(frames[0], np.diag([0.1, 0.1, 1.0]))
    assert canvas.add(frames[1], _shift(5.0)) is None
    assert canvas.skipped == [(1, "footprint area 100 x the recent median")]
    assert canvas.add(frames[2], _shift(10.0)) is not None
    assert canvas.median_rebased == [2] and canvas.median_rebases == 1
    for k in range(3, 40):
        assert canvas.add(frames[k], _shift(5.0 * k)) is not None
    for k in range(40, 45):  # 100 x the area, then 1 / 100 of it: 5 frames each
        assert canvas.add(frames[k], _shift(5.0 * k) @ np.diag([10.0, 10.0, 1.0])) is None
    for k in range(45, 50):
        assert canvas.add(frames[k], _shift(5.0 * k) @ np.diag([0.1, 0.1, 1.0])) is None
    assert canvas.skipped[-6:] == [(44, "footprint area 100 x the recent median")] + [
        (k, "footprint area 1 / 100 of the recent median") for k in range(45, 50)]
    for k in range(50, 60):
        assert canvas.add(frames[k], _shift(5.0 * k)) is not None
    assert canvas.median_rebases == 1 and canvas.frames_added == 1 + 38 + 10
    # a bad seed followed by sizes alternating 16 x apart: none agrees with the previous one
    odd = IncrementalCanvas(W, H)
    odd.add(frames[0], np.diag([0.1, 0.1, 1.0]))
    for k in range(1, 20):
        zoom = 1.0 if k % 2 else 4.0
        assert odd.add(frames[k], _shift(5.0 * k) @ np.diag([zoom, zoom, 1.0])) is None
    assert odd.median_rebases == 0 and odd.frames_added == 1


def test_skipped_is_bounded():
    """Before the fix `skipped` held every entry (and had no skipped_total)."""
    image = np.full((H, W), 128, np.uint8)
    canvas = IncrementalCanvas(W, H)
    canvas.add(image, np.eye(3))
    mirrored = "mirrored footprint (the homography flips the frame)"
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for k in range(1, 1001):
            canvas.add(image, np.diag([-1.0, 1.0, 1.0]) @ _shift(k / 10))
        for k in range(1001, 2001):  # a reason with figures: one kind
            canvas.add(image, _shift(1e15 + 1e12 * k))
        held = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert held < 100_000, held  # (before the fix ~200 kB here, ~9 MB after 100 000)
    assert canvas.skipped_total == 2000
    assert canvas.skipped_counts == {
        mirrored: 1000,
        "footprint beyond the canvas range (a corner N px from the reference, more than N)":
            1000}
    kept = incremental.SKIPPED_KEPT
    assert len(canvas.skipped) == 2 * kept
    assert [k for k, _ in canvas.skipped] == [*range(1, kept + 1), *range(2001 - kept, 2001)]
    assert canvas.skipped[0] == (1, mirrored)
    assert canvas.skipped[-1] == (2000, "footprint beyond the canvas range (a corner 3e+15 px "
                                        "from the reference, more than 1e+15)")


def _sweep_canvas(colour: bool, tile: int) -> IncrementalCanvas:
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.integers(0, 255, (400, 600, 3), np.uint8), (0, 0), 2)
    canvas = IncrementalCanvas(160, 120, tile_size=tile)
    for k in range(12):
        x, y, a = 30.0 * k, 15.0 * (k % 4), 0.05 * (k % 3 - 1)
        G = np.array([[np.cos(a), -np.sin(a), x], [np.sin(a), np.cos(a), y], [0, 0, 1]])
        image = texture[int(y):int(y) + 120, int(x):int(x) + 160]
        canvas.add(image if colour else image[:, :, 0].copy(), G)
    return canvas


@pytest.mark.parametrize("colour", [True, False])
def test_shrunk_render_by_column_blocks_is_unchanged(monkeypatch, colour):
    """A normal view is one block of whole rows, as before (checked against the pre-fix code in
    108 cases when fixed); blocks of a few columns give the same view."""
    canvas = _sweep_canvas(colour, 64)
    x0, y0, x1, y1 = canvas.bounds
    boxes = (canvas.bounds, (x0 + 7, y0 + 13, x1 - 5, y1 - 29))
    views = {(b, s): canvas.render(b, step=s) for b in boxes for s in (2, 3, 7, 81)}
    monkeypatch.setattr(incremental, "SHRUNK_BLOCK_BYTES", 96)  # 8 or 24 view columns a block
    for (box, step), view in views.items():
        np.testing.assert_array_equal(canvas.render(box, step=step), view)


def test_shrunk_render_of_a_wide_view_holds_one_block(monkeypatch):
    """A canvas spanning two places 3e6 px apart, shrunk 8 times: 14 x 375 010 view px, a view
    row of 1.5 MB. Before the fix a strip of 8 whole rows (12 MB) whatever the block size."""
    monkeypatch.setattr(incremental, "SHRUNK_BLOCK_BYTES", 1 << 16)
    canvas = IncrementalCanvas(W, H, tile_size=64)
    frames = _frames(6)
    for k in range(3):
        canvas.add(frames[k], _shift(5.0 * k, 60.0))
        canvas.add(frames[3 + k], _shift(3e6 + 5.0 * k))
    x0, y0, x1, y1 = canvas.bounds
    tracemalloc.start()
    try:
        view = canvas.render(step=8)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert view.shape == (-(-(y1 - y0) // 8), -(-(x1 - x0) // 8)) == (14, 375_010)
    assert peak - view.nbytes < 1 << 20, peak - view.nbytes
    # the two places as render gives each at full resolution, shrunk
    for j in (0, view.shape[1] - 40):  # (the right one padded with black past x1, as view)
        part = canvas.render((x0 + 8 * j, y0, x0 + 8 * j + 8 * 40, y1), step=8)
        np.testing.assert_array_equal(view[:, j:j + 40], part)
        assert part.max() > 0
    assert not view[:, 40:-40].any()
