"""Review 48 (Q, HIGH 1): a live recording kept after a write failure (a full disk; here a file
size limit, RLIMIT_FSIZE, which like a full disk lets a write take part of a row and fails the
next) is a readable dataset: each CSV row is written whole or not at all, a frame's PNG and its
frames.csv row go together, finish says the number of frames kept, and a tracker sample that
cannot be written no longer throws away the frames waiting to be written."""

from __future__ import annotations

import signal
import threading
import time

import cv2
import numpy as np
import pytest
from _faults import file_size_limit, signal_handler

from fusedmosaic.io import read_dataset
from fusedmosaic.io._table import format_float
from fusedmosaic.io.calibration import Camera
from fusedmosaic.io.recorder import DatasetRecorder

CAMERA = Camera(64, 48, camera_matrix=np.array([[60.0, 0, 32], [0, 60, 24], [0, 0, 1]]))
T0 = 1.7e9
POSE = np.eye(4)
POSE[:3, 3] = [10.5, -3.25, 120.0]


def _frame(k: int) -> np.ndarray:
    return np.full((48, 64), k, np.uint8)  # (a PNG of 140 bytes: below every limit here)


def _rows_that_fit(header: str, rows: list[str], limit: int) -> int:
    """How many of `rows` fit whole in a table of at most `limit` bytes; checks that the next
    one is cut by the limit in its middle (what a full disk does, and what this tests)."""
    size = len(header)
    for n, row in enumerate(rows):
        if size + len(row) > limit:
            assert size < limit, "the limit falls between two rows: choose another"
            return n
        size += len(row)
    raise AssertionError("the limit is not reached")


def _add_frames_until_refused(recorder: DatasetRecorder) -> None:
    """Frames 0, 1, ... until add_frame raises the writer's error (or 20 s have passed)."""
    deadline = time.monotonic() + 20
    k = 0
    while time.monotonic() < deadline:
        recorder.add_frame(_frame(k % 256), T0 + 0.04 * k)
        k += 1
        time.sleep(0.002)


def _pngs(folder) -> list[str]:
    return sorted(p.name for p in (folder / "frames").iterdir())


def test_frames_csv_cut_by_a_full_disk_keeps_a_dataset_and_says_its_frames(tmp_path):
    """frames.csv ended in half a row ('41,170'), frame 42's PNG was left without its row, and
    finish said 42 frames kept, 41 were: read_dataset refused the recording kept. Now the
    staging folder stays a dataset when the row fails, and so is the folder kept, with the
    number of frames said."""
    rows = [f"{k},{format_float(T0 + 0.04 * k)}\n" for k in range(100)]
    kept = _rows_that_fit("frame,timestamp\n", rows, 700)
    assert kept == 41  # (the review's run)
    recorder = DatasetRecorder(tmp_path / "rec", CAMERA)
    with signal_handler(signal.SIGXFSZ, signal.SIG_IGN), file_size_limit(700):
        with pytest.raises(OSError, match=r"^\[Errno 27\] frames\.csv: File too large$"):
            _add_frames_until_refused(recorder)
        staging = recorder.staging  # as it grows: a dataset (nothing of frame 41 left)
        assert len(read_dataset(staging, allow_untracked=True)) == kept
        assert _pngs(staging) == [f"{k:06d}.png" for k in range(kept)]
        with pytest.raises(ValueError) as said:
            recorder.finish()
    assert str(said.value) == (f"recording {tmp_path / 'rec'}: stopped after {kept} frame(s) "
                               "(frames.csv: File too large); those are kept there")
    ds = read_dataset(tmp_path / "rec", allow_untracked=True)
    assert len(ds) == kept == recorder.frames_written
    assert (tmp_path / "rec" / "frames.csv").read_text() == "frame,timestamp\n" + "".join(
        rows[:kept])
    assert _pngs(tmp_path / "rec") == [f"{k:06d}.png" for k in range(kept)]
    assert int(ds.frames[kept - 1][0, 0]) == kept - 1


def _hold_writer(monkeypatch) -> threading.Event:
    """release: the recorder's writer thread waits in cv2.imencode until it is set (frames
    wait to be written meanwhile)."""
    release = threading.Event()
    encode = cv2.imencode

    def held(*args):
        if threading.current_thread().name == "recorder":
            release.wait(30)
        return encode(*args)

    monkeypatch.setattr(cv2, "imencode", held)
    return release


@pytest.mark.parametrize("robot", [False, True])
def test_a_sample_that_cannot_be_written_keeps_the_frames_waiting(tmp_path, monkeypatch, robot):
    """tracking.csv (robot.csv), appended at the tracker's rate, is where a full disk shows
    first: its last row was cut in half, and its error stopped the writer, so that the 4 frames
    waiting were never tried and the recording was deleted, 'no frame could be written'. Now the
    samples stop at their last whole row, the frames waiting are written, and finish says what
    failed; the frames received after it are refused (add_frame names the file)."""
    name = "robot.csv" if robot else "tracking.csv"
    header = "timestamp,x,y\n" if robot else "timestamp,tx,ty,tz,qx,qy,qz,qw,valid\n"
    times = [T0 + 0.01 * j for j in range(100)]
    if robot:
        rows = [f"{format_float(t)},10500.0,-3250.0\n" for t in times]
        limit = 300
    else:
        rows = [f"{format_float(t)},10.5,-3.25,120.0,0.0,0.0,0.0,1.0,1\n" for t in times]
        limit = 450
    fit = _rows_that_fit(header, rows, limit)
    release = _hold_writer(monkeypatch)
    recorder = DatasetRecorder(tmp_path / "rec", CAMERA, robot=robot)
    try:
        with signal_handler(signal.SIGXFSZ, signal.SIG_IGN), file_size_limit(limit):
            for k in range(4):
                assert recorder.add_frame(_frame(k), T0 + 0.04 * k) == k
            for t in times:
                recorder.add_sample(t, POSE)
            with pytest.raises(OSError, match=rf"^\[Errno 27\] {name}: File too large$"):
                recorder.add_frame(_frame(4), T0 + 0.16)
            # as it grows: the samples end at their last whole row
            assert (recorder.staging / name).read_text() == header + "".join(rows[:fit])
            release.set()
            with pytest.raises(ValueError) as said:
                recorder.finish()
    finally:
        release.set()
    assert str(said.value) == (f"recording {tmp_path / 'rec'}: stopped after 4 frame(s) "
                               f"({name}: File too large); those are kept there")
    assert (tmp_path / "rec" / name).read_text() == header + "".join(rows[:fit])
    ds = read_dataset(tmp_path / "rec", allow_untracked=True)
    assert len(ds) == 4 == recorder.frames_written
    assert [int(ds.frames[k][0, 0]) for k in range(4)] == [0, 1, 2, 3]
    samples = ds.robot if robot else ds.tracking
    np.testing.assert_array_equal(samples.timestamps, times[:fit])


def test_a_sample_failing_before_any_frame_says_so(tmp_path):
    """Nothing to keep: said as what failed (it read 'no frame could be written', of frames
    never received)."""
    recorder = DatasetRecorder(tmp_path / "rec", CAMERA)
    with signal_handler(signal.SIGXFSZ, signal.SIG_IGN), file_size_limit(200):
        for j in range(10):
            recorder.add_sample(T0 + 0.01 * j, POSE)
        with pytest.raises(ValueError) as said:
            recorder.finish()
    assert str(said.value) == (f"recording {tmp_path / 'rec'}: tracking.csv: File too large, "
                               "before a frame was received; nothing is kept")
    assert list(tmp_path.iterdir()) == []


def test_a_row_that_cannot_be_taken_back_is_cut_by_finish(tmp_path, monkeypatch):
    """Should cutting the table back fail as well, finish checks the folder it keeps (as the
    recovery of a killed session does): its last, partial row is dropped."""
    import os

    def refused(fd, length):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "ftruncate", refused)
    recorder = DatasetRecorder(tmp_path / "rec", CAMERA)
    with signal_handler(signal.SIGXFSZ, signal.SIG_IGN), file_size_limit(700):
        with pytest.raises(OSError, match=r"frames\.csv: File too large$"):
            _add_frames_until_refused(recorder)
        assert (recorder.staging / "frames.csv").read_bytes().endswith(b"\n41,170")
        with pytest.raises(ValueError, match=r"stopped after 41 frame\(s\) \(frames\.csv: File "
                                             r"too large\); those are kept there$"):
            recorder.finish()
    assert len(read_dataset(tmp_path / "rec", allow_untracked=True)) == 41
    assert recorder.frames_written == 41
