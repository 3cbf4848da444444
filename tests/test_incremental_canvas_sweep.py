"""IncrementalCanvas budget on long sweeps (review: the bounds-skip dropped legitimate frames).

`max_pixels` bounds the allocated tiles and any one render() view, not the bounding box: a
diagonal sweep's bounding box grows with the square of its length while its tiles grow with the
length, so its frames are all kept and the whole-canvas render() raises with the sub-box hint.
Only a stray (a jump far from every placed frame that would take the bounds beyond the budget)
is left out.
"""

import math
import re

import numpy as np
import pytest

from fusedmosaic.compositing import CanvasTooLargeError, IncrementalCanvas

W = H = 64
TILE = 32
STEP = 20  # px per frame along both axes: a diagonal sweep
N = 300
BUDGET = 2_000_000  # canvas pixels; the sweep's bounding box reaches ~36.5 M, its tiles ~1.04 M


def _frame(k):
    return np.random.default_rng(k).integers(0, 256, (H, W, 3), dtype=np.uint8)


def _shift(x, y):
    return np.array([[1.0, 0, x], [0, 1, y], [0, 0, 1]])


def _area(box):
    return (box[2] - box[0]) * (box[3] - box[1])


def _sweep(n=N, **kwargs):
    canvas = IncrementalCanvas(W, H, tile_size=TILE, blend="last", **kwargs)
    for k in range(n):
        box = canvas.add(_frame(k), _shift(STEP * k, STEP * k))
        assert box == (STEP * k - 1, STEP * k - 1, STEP * k + W + 1, STEP * k + H + 1)
    return canvas


@pytest.fixture(scope="module")
def sweep():
    return _sweep(max_pixels=BUDGET)


def test_long_diagonal_sweep_keeps_every_frame(sweep):
    """Before the fix, frames 68..299 were skipped here (bounds 1405 x 1405 > 2 M pixels with
    0.24 M pixels of tiles)."""
    canvas = sweep
    assert canvas.skipped == [] and canvas.frames_added == N
    assert canvas.bounds == (-1, -1, STEP * (N - 1) + W + 1, STEP * (N - 1) + H + 1)
    assert _area(canvas.bounds) == 6046 * 6046 > 18 * BUDGET
    assert canvas.tile_pixels == 1_044_480 <= BUDGET
    assert canvas.nbytes == canvas.tile_pixels * 16  # BGR + weight, float32
    # late frames: with `last` blending, frame k keeps the STEP-wide strip its successor does
    # not cover, and the last frame is whole; integer shifts warp exactly
    for k in (150, 250, 298):
        x = y = STEP * k
        view = canvas.render((x + 1, y + 1, x + STEP - 1, y + STEP - 1))
        np.testing.assert_array_equal(view, _frame(k)[1:STEP - 1, 1:STEP - 1])
    x = y = STEP * (N - 1)
    view = canvas.render((x + 1, y + 1, x + W - 1, y + H - 1))
    np.testing.assert_array_equal(view, _frame(N - 1)[1:-1, 1:-1])


def test_whole_canvas_render_above_the_budget_asks_for_a_sub_box(sweep):
    with pytest.raises(CanvasTooLargeError, match=re.escape(
            "render: the view of x -1..6045, y -1..6045 is 6046 x 6046 pixels, above the budget "
            "of 2000000 pixels (max_pixels) (the whole canvas: its bounding box; the tiles hold "
            "1044480 pixels); render a smaller box, e.g. the one add() returned")):
        sweep.render()
    with pytest.raises(CanvasTooLargeError, match=r"above the budget of 2000000 pixels "
                       r"\(max_pixels\); render a smaller box"):
        sweep.render((0, 0, 2000, 2000))  # an explicit box: no whole-canvas note


def test_return_near_earlier_content_is_kept_a_jump_away_from_it_is_not():
    """Once the bounding box is over the budget, a frame growing it is judged by its distance
    to every placed frame (the tiles), not only to the last one."""
    canvas = _sweep(max_pixels=BUDGET)
    bounds = canvas.bounds
    # back to the start, just outside the bounds: ~5900 px from the last frame, near frame 0
    assert canvas.add(_frame(1000), _shift(-200.0, 40.0)) == (-201, 39, -135, 105)
    assert canvas.skipped == [] and canvas.bounds == (-201, -1, bounds[2], bounds[3])
    # off the diagonal: ~4200 px from any content, > 10 diagonals (10 x 93 px)
    tiles = len(canvas.tiles)
    assert canvas.add(_frame(1001), _shift(3000.0, -3000.0)) is None
    assert canvas.skipped == [(N + 1, (
        "would grow the canvas bounds to 6246 x 9046 pixels, above max_pixels 2000000 (frame "
        "lands at x 2999..3065, y -3001..-2935: a stray placement?)"))]
    assert len(canvas.tiles) == tiles and canvas.frames_added == N + 1
    # the same jump with the stray check off is kept; it costs its 9 tiles, not the box
    loose = _sweep(max_pixels=BUDGET, stray_diagonals=math.inf)
    tiles = len(loose.tiles)
    assert loose.add(_frame(1001), _shift(3000.0, -3000.0)) is not None
    assert len(loose.tiles) == tiles + 9 and loose.skipped == []


@pytest.mark.parametrize("max_pixels", [BUDGET, 400_000_000])  # lowered, default
def test_stray_far_frame_is_skipped_and_costs_nothing(max_pixels):
    canvas = _sweep(n=20, max_pixels=max_pixels)
    bounds, tiles, nbytes = canvas.bounds, len(canvas.tiles), canvas.nbytes
    assert canvas.add(_frame(99), _shift(1e6, 1e6)) is None
    assert canvas.skipped == [(20, (
        f"would grow the canvas bounds to 1000066 x 1000066 pixels, above max_pixels "
        f"{max_pixels} (frame lands at x 999999..1000065, y 999999..1000065: a stray "
        "placement?)"))]
    assert canvas.bounds == bounds and len(canvas.tiles) == tiles and canvas.nbytes == nbytes
    assert canvas.render().shape == (bounds[3] - bounds[1], bounds[2] - bounds[0], 3)
    # the sweep goes on, numbering included
    assert canvas.add(_frame(20), _shift(STEP * 20, STEP * 20)) is not None
    assert canvas.add(_frame(21), np.full((3, 3), np.nan)) is None
    assert [k for k, _ in canvas.skipped] == [20, 22] and canvas.frames_added == 21


def test_stray_after_the_sweep_is_skipped():
    canvas = _sweep(max_pixels=BUDGET)  # bounds already over the budget
    tiles = len(canvas.tiles)
    assert canvas.add(_frame(99), _shift(1e6, 1e6)) is None
    assert [k for k, _ in canvas.skipped] == [N] and len(canvas.tiles) == tiles


def test_tiles_over_the_budget_raise_and_change_nothing():
    budget = 200_000  # 195 tiles of 32 x 32; the sweep's 56th frame would need 198
    canvas = IncrementalCanvas(W, H, tile_size=TILE, blend="last", max_pixels=budget)
    k = 0
    with pytest.raises(CanvasTooLargeError) as error:
        for k in range(N):  # noqa: B007 - k is the frame that failed
            canvas.add(_frame(k), _shift(STEP * k, STEP * k))
    assert k == 55
    assert str(error.value) == (
        "live canvas would need 202752 pixels of tiles, above the budget of 200000 pixels "
        "(frame 55 lands at x 1099..1165, y 1099..1165); raise max_pixels, lower scale, or "
        "start a new canvas")
    assert canvas.frames_added == 55 and canvas.skipped == []
    assert canvas.tile_pixels == 193 * TILE**2 == 197_632 <= budget  # the 55 frames' tiles
    # the refused call changed nothing: same frame number next, frames on existing tiles fit
    assert canvas.add(_frame(1), _shift(STEP, STEP)) is not None
    assert canvas.add(_frame(2), np.full((3, 3), np.nan)) is None
    assert canvas.skipped == [(56, "not placed")]


def test_stray_diagonals_must_be_positive():
    with pytest.raises(ValueError, match="stray_diagonals must be > 0, got 0"):
        IncrementalCanvas(W, H, stray_diagonals=0)
    with pytest.raises(ValueError, match="stray_diagonals must be > 0, got nan"):
        IncrementalCanvas(W, H, stray_diagonals=math.nan)
