"""IncrementalCanvas budget on long sweeps (review: the bounds-skip dropped legitimate frames).

`max_pixels` bounds the allocated tiles and any one render() view, not the bounding box: a
diagonal sweep's bounding box grows with the square of its length while its tiles grow with the
length, so its frames are all kept and the whole-canvas render() raises with the sub-box hint.
Only a stray (a jump far from every placed frame that would take the bounds beyond the budget)
is left out, unless it is the `stray_rebase`-th of a run of mutually consistent strays (review 6
#7: a genuine far jump): then the new place is accepted.
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


# -- a genuine far jump: accepted after `stray_rebase` consistent strays in a row (review 6 #7) --
JUMP = 8  # frames of the run at the new place, stepping STEP px along x


def _tiles(boxes):
    return {(ty, tx) for x0, y0, x1, y1 in boxes for ty in range(y0 // TILE, (y1 - 1) // TILE + 1)
            for tx in range(x0 // TILE, (x1 - 1) // TILE + 1)}


def _jump(place):
    """A sweep (bounds over the budget), then JUMP frames at a far place, STEP px apart."""
    canvas = _sweep(max_pixels=BUDGET)
    tiles = len(canvas.tiles)
    x, y = place
    boxes = [canvas.add(_frame(2000 + j), _shift(x + STEP * j, y)) for j in range(JUMP)]
    return canvas, tiles, boxes


@pytest.mark.parametrize("place", [(3000, -3000), (1_000_000, 1_000_000)])
def test_consistent_far_run_is_accepted_from_its_third_frame(place):
    """Before the fix every frame of the run was skipped (the last placed box never moved), and
    so would have been everything after it near the new place."""
    canvas, tiles, boxes = _jump(place)
    x, y = place
    assert boxes[:2] == [None, None]
    assert [k for k, _ in canvas.skipped] == [N, N + 1]
    assert canvas.skipped[0][1].endswith(
        f"(frame lands at x {x - 1}..{x + W + 1}, y {y - 1}..{y + H + 1}: a stray placement?)")
    assert boxes[2:] == [(x + STEP * j - 1, y - 1, x + STEP * j + W + 1, y + H + 1)
                         for j in range(2, JUMP)]
    assert canvas.rebased == [N + 2] and canvas.frames_added == N + JUMP - 2
    # only the placed frames' footprints cost tiles (21 or 24 of them), not the bounding box
    assert len(canvas.tiles) == tiles + len(_tiles(boxes[2:])) <= tiles + 24
    assert canvas.tile_pixels <= BUDGET
    # the bounding box spans both places: the whole render raises, sub-boxes work
    assert canvas.bounds == (-1, min(-1, y - 1), max(STEP * (N - 1) + W + 1, boxes[-1][2]),
                             max(STEP * (N - 1) + H + 1, y + H + 1))
    with pytest.raises(CanvasTooLargeError, match="the whole canvas"):
        canvas.render()
    for j in range(2, JUMP - 1):  # `last` blending: frame j keeps the strip its successor does not
        xj = x + STEP * j
        view = canvas.render((xj + 1, y + 1, xj + STEP - 1, y + H - 1))
        np.testing.assert_array_equal(view, _frame(2000 + j)[1:-1, 1:STEP - 1])
    xj = x + STEP * (JUMP - 1)
    np.testing.assert_array_equal(canvas.render((xj + 1, y + 1, xj + W - 1, y + H - 1)),
                                  _frame(2000 + JUMP - 1)[1:-1, 1:-1])
    # the two strays left out left nothing: left of frame 2's box the canvas is empty
    assert not canvas.render((x - 1, y - 1, x + 2 * STEP - 1, y + H + 1)).any()
    # the old place is still content (a return there is kept), and the new one stays accepted
    assert canvas.add(_frame(3000), _shift(STEP * 10, STEP * 10)) is not None
    assert canvas.add(_frame(3001), _shift(x + 200, y + 100)) is not None
    assert len(canvas.skipped) == 2 and canvas.rebased == [N + 2]


def test_isolated_strays_are_skipped_and_do_not_add_up():
    canvas = _sweep(max_pixels=BUDGET)
    tiles, bounds = len(canvas.tiles), canvas.bounds
    far, other = _shift(1e6, 1e6), _shift(-1e6, 3e5)
    # the same far place, again and again, with a frame near the content between: each stray
    # is alone in its run
    for k in range(6):
        assert canvas.add(_frame(2000 + k), far) is None
        assert canvas.add(_frame(k), _shift(STEP * k, STEP * k)) is not None
    # two far places in turn: each stray is far from the previous one
    for k in range(6):
        assert canvas.add(_frame(2100 + k), other if k % 2 else far) is None
    # two at one place, then a frame near the content ends the run
    assert canvas.add(_frame(2200), far) is None and canvas.add(_frame(2201), far) is None
    assert canvas.add(_frame(7), _shift(STEP * 7, STEP * 7)) is not None
    assert canvas.add(_frame(2202), far) is None and canvas.add(_frame(2203), far) is None
    assert canvas.rebased == [] and len(canvas.skipped) == 6 + 6 + 4
    assert len(canvas.tiles) == tiles and canvas.bounds == bounds
    # a frame without a position neither counts nor ends the run: the third one is accepted
    assert canvas.add(_frame(2204), np.full((3, 3), np.nan)) is None
    assert canvas.add(_frame(2205), far) == (999999, 999999, 1000065, 1000065)
    assert canvas.rebased == [N + 24] and len(canvas.skipped) == 6 + 6 + 4 + 1
    assert len(canvas.tiles) == tiles + len(_tiles([(999999, 999999, 1000065, 1000065)]))


def test_stray_rebase_none_never_accepts_a_far_place():
    canvas = _sweep(n=20, max_pixels=BUDGET, stray_rebase=None)
    tiles = len(canvas.tiles)
    for j in range(10):
        assert canvas.add(_frame(2000 + j), _shift(1e6 + STEP * j, 1e6)) is None
    assert len(canvas.skipped) == 10 and canvas.rebased == [] and len(canvas.tiles) == tiles
    # stray_rebase=1: a far place is accepted at once
    canvas = _sweep(n=20, max_pixels=BUDGET, stray_rebase=1)
    assert canvas.add(_frame(2000), _shift(1e6, 1e6)) is not None
    assert canvas.skipped == [] and canvas.rebased == [20]


def test_rebase_over_the_tile_budget_raises_and_changes_nothing():
    budget = 200_000  # the 55-frame sweep holds 193 tiles of 32 x 32; the far frame's 12 more
    # need 205 > 195
    canvas = _sweep(n=55, max_pixels=budget)
    far = _shift(5000.0, 0.0)
    assert canvas.add(_frame(2000), far) is None and canvas.add(_frame(2001), far) is None
    for _ in range(2):  # refused, and the run is where it was: the next one is refused too
        with pytest.raises(CanvasTooLargeError, match=re.escape(
                "live canvas would need 209920 pixels of tiles, above the budget of 200000 "
                "pixels (frame 57 lands at x 4999..5065, y -1..65)")):
            canvas.add(_frame(2002), far)
        assert [k for k, _ in canvas.skipped] == [55, 56] and canvas.rebased == []
        assert canvas.frames_added == 55 and canvas.tile_pixels == 193 * TILE**2
    assert canvas.add(_frame(1), _shift(STEP, STEP)) == (19, 19, 85, 85)  # frame 57
    assert canvas.add(_frame(2003), far) is None  # the run starts again
    assert [k for k, _ in canvas.skipped] == [55, 56, 58]


@pytest.mark.parametrize("value", [0, -1, 1.5, 3.0, True, "3", math.inf])
def test_stray_rebase_must_be_a_positive_integer_or_none(value):
    with pytest.raises(ValueError, match=re.escape(
            f"stray_rebase must be an integer >= 1 or None, got {value!r}")):
        IncrementalCanvas(W, H, stray_rebase=value)


def test_stray_rebase_accepts_numpy_integers():
    assert IncrementalCanvas(W, H, stray_rebase=np.int64(2)).stray_rebase == 2
    assert IncrementalCanvas(W, H, stray_rebase=None).stray_rebase is None
    assert IncrementalCanvas(W, H).stray_rebase == 3
