"""Review 45 (B): a live session's recorder never holds up the OpenIGTLink receiver (H1): a
recorder whose writer is behind drops frames (counted, said, reported) instead of blocking
add_frame, stores frames uncompressed to catch up, and report.json measures how far reading fell
behind the sender's stamps; --frame-timeout is bounded (L3)."""

from __future__ import annotations

import json
import threading
import time

import cv2
import numpy as np
import pytest

from fusedmosaic.cli import main
from fusedmosaic.io import read_dataset
from fusedmosaic.io import recorder as recorder_module
from fusedmosaic.io.calibration import Camera
from fusedmosaic.io.recorder import RETRY_STORED, DatasetRecorder
from fusedmosaic.runner import (
    MAX_FRAME_TIMEOUT_S,
    _ReceiveBacklog,
    check_live_limits,
    run_igtl,
)

CAMERA = Camera(50, 40, camera_matrix=np.array([[60.0, 0, 25], [0, 60, 20], [0, 0, 1]]))


def _hold_writer(monkeypatch) -> tuple[threading.Event, threading.Event]:
    """(release, entered): the recorder's writer thread waits in cv2.imencode, once entered,
    until release is set (a writer far behind the stream, e.g. a slow encoder)."""
    release, entered = threading.Event(), threading.Event()
    write = cv2.imencode

    def held(path, *args):
        if threading.current_thread().name == "recorder":
            entered.set()
            release.wait(30)
        return write(path, *args)

    monkeypatch.setattr(cv2, "imencode", held)
    return release, entered


def test_add_frame_does_not_wait_for_a_writer_behind(tmp_path, monkeypatch):
    """Room for 3 frames, the writer held on the first: the next 7 are not recorded, at once
    (add_frame waited on a full queue, and the receiver calling it stopped reading the socket),
    counted; the 3 queued are written when the writer goes on."""
    release, _ = _hold_writer(monkeypatch)
    frame = np.full((40, 50), 7, np.uint8)
    recorder = DatasetRecorder(tmp_path / "rec", CAMERA, max_queued_bytes=3 * frame.nbytes)
    ids: list[int | None] = []
    adder = threading.Thread(target=lambda: ids.extend(
        recorder.add_frame(frame + k, 0.04 * k) for k in range(10)), daemon=True)
    adder.start()
    adder.join(10)
    held = adder.is_alive()
    release.set()
    assert not held, "add_frame waited for the writer"
    assert ids == [0, 1, 2, *[None] * 7]
    assert recorder.frames_not_recorded == 7
    assert recorder.finish() == tmp_path / "rec"
    ds = read_dataset(tmp_path / "rec", allow_untracked=True)
    assert np.allclose(ds.timestamps, [0.0, 0.04, 0.08])
    assert [int(ds.frames[k][0, 0]) for k in range(len(ds))] == [7, 8, 9]
    assert recorder.frames_written == 3


def test_frames_waiting_are_stored_uncompressed_and_lossless(tmp_path, monkeypatch):
    """Room for 16 frames: beyond 2 waiting (an eighth) the writer is behind the stream and
    stores frames uncompressed (PNG level 0) until it has caught up, then compresses again;
    every frame reads back as given."""
    release, entered = _hold_writer(monkeypatch)
    frames = [np.full((40, 50), 10 * k, np.uint8) for k in range(5)]
    recorder = DatasetRecorder(tmp_path / "rec", CAMERA, max_queued_bytes=16 * frames[0].nbytes)
    assert recorder.add_frame(frames[0], 0.0) == 0
    assert entered.wait(10)  # frame 0 chosen (compressed: nothing else waiting) and held
    for k in range(1, 5):
        assert recorder.add_frame(frames[k], 0.04 * k) == k
    time.sleep(0.3)  # (frame 0's compression, held, is measured slower than storing)
    release.set()
    recorder.finish()
    sizes = [(tmp_path / "rec" / "frames" / f"{k:06d}.png").stat().st_size for k in range(5)]
    stored = [k for k, size in enumerate(sizes) if size > frames[k].nbytes]
    assert stored == [1, 2]  # 4 then 3 waiting: behind; then 2 and 1: caught up
    assert max(sizes[k] for k in (0, 3, 4)) < frames[0].nbytes // 4  # compressed
    assert recorder.frames_uncompressed == 2
    ds = read_dataset(tmp_path / "rec", allow_untracked=True)
    for k in range(5):
        assert np.array_equal(ds.frames[k], frames[k])


def test_storing_measured_slower_is_tried_again_only_now_and_then(tmp_path):
    """On a disk slower than the encoder (storing measured slower per byte), frames waiting are
    compressed, but for one stored every RETRY_STORED (a disk stall may have made it look slow);
    not behind, none is stored."""
    recorder = DatasetRecorder(tmp_path / "rec", CAMERA, max_queued_bytes=1000)
    try:
        recorder._cost = [1e-9, 1e-8]  # s per byte, compressed / stored
        assert not recorder._store()  # nothing waiting
        recorder._queued_bytes = 1000
        choices = [recorder._store() for _ in range(RETRY_STORED)]
        assert choices == [False] * (RETRY_STORED - 1) + [True]
        recorder._cost = [1e-8, 1e-9]  # storing faster: every frame waiting
        recorder._since_stored = 0
        assert all(recorder._store() for _ in range(5))
    finally:
        recorder._queued_bytes = 0
        recorder.abort()


def test_max_queued_bytes_is_checked(tmp_path):
    with pytest.raises(ValueError, match=r"recorder: max_queued_bytes must be an integer > 0, "
                                         r"got 0"):
        DatasetRecorder(tmp_path / "rec", CAMERA, max_queued_bytes=0)
    assert not (tmp_path / "rec").exists()


def test_receive_backlog_is_the_growth_of_arrival_minus_stamp():
    """The sender's clock 1000 s ahead and 5-15 ms of transport: 0 while frames are read as
    sent; a receiver held up 2 s shows 2 s; a clock jump taken restarts the baseline."""
    backlog = _ReceiveBacklog()
    assert backlog.details() is None
    rng = np.random.default_rng(0)
    for k in range(35):
        stamp = 1000 + 0.04 * k
        backlog.add(stamp, stamp - 1000 + rng.uniform(0.005, 0.015))
    assert backlog.details()["max"] < 0.011
    for k in range(10):  # read 0.2 s later each frame
        stamp = 1001.4 + 0.04 * k
        backlog.add(stamp, stamp - 1000 + 0.01 + 0.2 * (k + 1))
    assert backlog.details() == pytest.approx({"end": 2.0, "max": 2.0}, abs=0.011)
    backlog.restart()  # the stamps jumped an hour ahead: arrival - stamp fell by 3600 s
    for k in range(5):
        stamp = 4600 + 0.04 * k
        backlog.add(stamp, stamp - 4600 + 2.01)
    assert backlog.details() == pytest.approx({"end": 0.0, "max": 2.0}, abs=0.011)


@pytest.mark.realtime
def test_live_session_counts_reports_and_tells_frames_not_recorded(tmp_path, monkeypatch):
    """A recorder with room for 3 frames whose writer is held until the session ends: the
    receiver goes on reading, the 27 other frames are neither recorded nor processed, said once,
    counted in report.json and the summary; the recording holds the 3 frames."""
    from _igtl_sender import Sender, robot_events

    from fusedmosaic.simulation import PcleOptions, simulate_pcle

    ds = read_dataset(simulate_pcle(tmp_path / "pcle", PcleOptions(
        width=192, height=160, n_frames=30, speed_um_per_frame=12.0, radius_um=150.0,
        contact_loss=False, stick_slip=False)))
    release, _ = _hold_writer(monkeypatch)
    room = 3 * ds.frames[0].nbytes

    class HeldRecorder(DatasetRecorder):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, max_queued_bytes=room, **kwargs)

        def finish(self):  # (after the session: every frame received)
            release.set()
            return super().finish()

    monkeypatch.setattr(recorder_module, "DatasetRecorder", HeldRecorder)
    events = [(t, m) for t, m in robot_events(ds) if m[2:14].rstrip(b"\0") == b"IMAGE"]
    sender = Sender(events, speed=2.0)
    told: list[str] = []
    try:
        summary = run_igtl(f"127.0.0.1:{sender.port}", tmp_path / "out", record=tmp_path / "rec",
                           camera=ds.root / "camera.yaml", transform_device=None, method="ncc",
                           progress=False, report=False, say=lambda text: None,
                           warn=told.append)
    finally:
        release.set()
    sender.join()
    not_recorded = [text for text in told if "neither recorded nor processed" in text]
    assert not_recorded == [
        f"live session: received frame 3 neither recorded nor processed: "
        f"{room / 2**20:.3g} MiB of frames wait to be written to the recording (writing cannot "
        "keep up with the stream: the disk, or the CPU the live session leaves it); the live "
        "view stays live, and such frames are counted (report.json live frames_not_recorded)"]
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    live = report["live"]
    assert live["frames_recorded"] == 3
    assert live["source"]["frames_received"] == 30
    assert live["source"]["frames_not_recorded"] == 27
    assert live["source"]["frames_not_recorded_first"] == 3
    # (each frame alone fills more than an eighth of the room: written as behind, stored)
    assert live["source"]["frames_recorded_uncompressed"] == 3
    assert set(live["source"]["receive_backlog_s"]) == {"end", "max"}
    assert not_recorded[0] in report["warnings"]
    assert (f"  frames  27 received frame(s) neither recorded nor processed: the recorder's "
            f"{room / 2**20:.3g} MiB queue was full, writing behind the stream (first: received "
            "frame 3; report.json live frames_not_recorded)") in summary.splitlines()
    assert len(read_dataset(tmp_path / "rec", allow_untracked=True)) == 3


def test_frame_timeout_above_the_bound_is_refused():
    names = {"frame_timeout_s": "--frame-timeout"}
    check_live_limits(None, None, MAX_FRAME_TIMEOUT_S, names)
    check_live_limits(None, 1e10, 5.0, names)  # (a duration only bounds the waits)
    with pytest.raises(ValueError, match=r"^--frame-timeout must be at most 1000000 s \(11\.6 "
                                         r"days, as good as no timeout\), got 1e\+10$"):
        check_live_limits(None, None, 1e10, names)


def test_cli_refuses_a_frame_timeout_beyond_the_bound(tmp_path, capsys):
    """--frame-timeout 1e10 ended a session in OverflowError (a wait beyond
    threading.TIMEOUT_MAX); now refused before connecting, nothing created."""
    (tmp_path / "camera.yaml").write_text("")  # (not read: the limits are checked first)
    assert main(["live", "127.0.0.1:1", "--camera", str(tmp_path / "camera.yaml"),
                 "--transform", "SensorToTracker", "--record", str(tmp_path / "rec"),
                 "--out", str(tmp_path / "out"), "--frame-timeout", "1e10"]) == 2
    assert ("--frame-timeout must be at most 1000000 s (11.6 days, as good as no timeout), got "
            "1e+10") in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["camera.yaml"]


def test_receive_backlog_is_not_hidden_by_a_connect_burst():
    """PLUS Server starts a new client at its oldest buffered frames, seconds old, read as fast
    as they come (2 ms apart here, 5 s of them), then live (50 ms of transport); then the
    receiver falls 3 s behind. The baseline was the least (arrival - stamp) of the first 25
    frames, those of the burst: the 3 s read {'end': -0.79, 'max': 0.0}. It is now the least
    so far."""
    backlog = _ReceiveBacklog()
    arrival = 0.0
    for k in range(125):  # the buffered burst: stamped 1000 - 5 .. 1000
        backlog.add(995 + 0.04 * k, arrival)
        arrival += 0.002
    assert backlog.details() == {"end": 0.0, "max": 0.0}  # (behind from the start: unseen)
    for k in range(250):  # live, 10 s
        stamp = 1000 + 0.04 * k
        backlog.add(stamp, stamp - 1000 + 0.3)
    assert backlog.details()["max"] < 0.02  # (the burst's last frame was read 12 ms sooner)
    for k in range(75):  # each frame read 80 ms after the one before: 3 s behind at the end
        stamp = 1010 + 0.04 * k
        backlog.add(stamp, stamp - 1000 + 0.3 + 0.04 * (k + 1))
    assert backlog.details() == pytest.approx({"end": 3.0, "max": 3.0}, abs=0.02)
