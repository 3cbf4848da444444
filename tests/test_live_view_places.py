"""The live view after frames placed far apart (review 50 LOW 5, second half): it showed the
whole bounding box shrunk to its budget, the latest frames a line 2 pixels high; it now shows
the place of the latest frames (IncrementalCanvas.view_bounds)."""

import cv2
import numpy as np
from test_incremental_review50 import H, W, _frames, _shift  # 64 x 48 frames of one texture

from fusedmosaic.compositing import IncrementalCanvas
from fusedmosaic.compositing.live_view import LiveMosaicView

FAR = 50_000.0  # px: 625 frame diagonals


def test_view_follows_a_far_re_localisation(tmp_path):
    """20 frames at the origin, then 10 placed 50000 px away (the canvas budget makes the first
    two strays and accepts the third as a new place). The preview shows the new place: 101 x
    50 pixels (its 8 frames span 35 px, plus a frame and the outward rounding), not 50109 x 50
    shrunk; the summary says there are 2 places."""
    frames = _frames(30)
    told = []
    preview = tmp_path / "view.png"
    view = LiveMosaicView(W, H, preview=preview, interval_s=0.0, max_pixels=1_000_000,
                          notify=told.append)
    for k in range(20):
        view.add(frames[k], _shift(5.0 * k))
    for k in range(20, 30):
        view.add(frames[k], _shift(FAR + 5.0 * (k - 20)))
    view.close()
    summary = view.summary()
    assert view.canvas.rebased == [22] and summary["places"] == 2
    assert summary["frames_drawn"] == 28  # the first two far frames were strays
    image = cv2.imread(str(preview), cv2.IMREAD_UNCHANGED)
    assert image.shape[:2] == (summary["height"], summary["width"]) == (50, 7 * 5 + W + 2)
    assert summary["origin_reference_px"][0] > FAR - 1 and summary["reduced"] == 0
    assert any("2 places far apart" in text for text in told)
    # the new place's frames as the canvas holds them (the view is the canvas at that box)
    np.testing.assert_array_equal(image, view.canvas.render(view.canvas.view_bounds))


def test_lone_far_frame_does_not_move_the_view():
    """A frame placed far away within the budget (no stray rule) is a place of its own, but the
    view stays on the frames' place until the far place holds MIN_VIEW_PLACE_FRAMES frames, and
    comes back with the next frame near the first place."""
    frames = _frames(25)
    canvas = IncrementalCanvas(W, H)
    for k in range(20):
        canvas.add(frames[k], _shift(5.0 * k))
    home = canvas.view_bounds
    assert canvas.places == 1 and home == canvas.bounds
    canvas.add(frames[20], _shift(FAR))
    assert canvas.places == 2 and canvas.view_bounds == home and canvas.bounds != home
    canvas.add(frames[21], _shift(100.0))  # back home: the view's place grows
    assert canvas.places == 2 and canvas.view_bounds == (*home[:2], 100 + W + 1, home[3])
    for k in range(22, 25):  # three more far: the far place is now shown
        canvas.add(frames[k], _shift(FAR + 5.0 * (k - 21)))
    assert canvas.view_bounds[0] >= FAR - 2


def test_one_place_views_the_whole_canvas():
    """A normal sweep is one place: view_bounds is bounds (the view unchanged)."""
    frames = _frames(40)
    canvas = IncrementalCanvas(W, H, tile_size=16)
    for k in range(40):
        canvas.add(frames[k], _shift(5.0 * k, 2.0 * k))
    assert canvas.places == 1 and canvas.view_bounds == canvas.bounds
