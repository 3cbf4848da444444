"""compositing/live_view.py: the live session's growing mosaic (published to a PNG / an
OpenIGTLink server; end to end in test_live_igtl.py)."""

import shutil

import cv2
import numpy as np
import pytest

from fusedmosaic.compositing import IncrementalCanvas, live_view
from fusedmosaic.compositing.live_view import LiveMosaicView


def _frames(n: int = 6):
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.integers(0, 255, (200, 400, 3), np.uint8), (0, 0), 2)
    for k in range(n):
        G = np.array([[1.0, 0, 20.0 * k], [0, 1, 0], [0, 0, 1]])
        yield texture[:120, 20 * k:20 * k + 160].copy(), G


def test_view_is_the_incremental_canvas_of_the_frames(tmp_path):
    preview = tmp_path / "v.png"
    view = LiveMosaicView(160, 120, preview=preview, interval_s=0.0)
    reference = IncrementalCanvas(160, 120, blend="linear")
    for image, G in _frames():
        view.add(image, G)
        reference.add(image, G)
    view.close()
    assert view.frames_added == 6 and view.published >= 1 and view.problems == {}
    np.testing.assert_array_equal(cv2.imread(str(preview)), reference.render())
    assert [p.name for p in tmp_path.iterdir()] == ["v.png"]  # no temporary file left


def test_problems_are_recorded_not_raised(tmp_path, monkeypatch):
    folder = tmp_path / "gone"
    folder.mkdir()
    view = LiveMosaicView(160, 120, preview=folder / "v.png", interval_s=0.0)
    shutil.rmtree(folder)  # the preview's folder disappears during the session
    frames = list(_frames(2))
    view.add(*frames[0])
    view.add(frames[1][0], np.full((3, 3), np.nan))  # not placed: left out by the canvas
    view.close()
    assert view.frames_added == 1
    assert any("v.png: not written" in p for p in view.problems)
    monkeypatch.setattr(live_view, "MAX_QUEUED", 0)  # a worker that cannot keep up
    behind = LiveMosaicView(160, 120, interval_s=0.0)
    behind.add(*frames[0])
    behind.close()
    assert behind.frames_added == 0
    assert behind.problems == {"frame left out of the view: 0 frames were waiting": 1}


def test_bad_arguments():
    with pytest.raises(ValueError, match=r"v\.jpg: the preview is a PNG file"):
        LiveMosaicView(160, 120, preview="v.jpg")
    with pytest.raises(ValueError, match="interval_s must be >= 0"):
        LiveMosaicView(160, 120, interval_s=-1.0)
