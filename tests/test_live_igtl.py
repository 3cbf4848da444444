"""Live sessions on an OpenIGTLink source (io/igtl.py, io/recorder.py, `fusedmosaic live`): a
local sender streams a simulated tracked sequence as PLUS Server would; the session mosaics it
with lba-emt, records it as a dataset and writes the outputs."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
import warnings
from pathlib import Path

import cv2
import numpy as np
import pyigtl
import pytest
from _faults import signal_handler
from _igtl_sender import (
    T0,
    Sender,
    dataset_events,
    image_message,
    position_message,
    tracker_matrix,
    transform_message,
)
from scipy.spatial.transform import Rotation

from fusedmosaic.cli import main
from fusedmosaic.estimation.sequential import run_lba_emt
from fusedmosaic.evaluation import frame_errors, mosaic_error
from fusedmosaic.io import read_dataset, read_homographies_csv
from fusedmosaic.io.igtl import (
    IgtlImageServer,
    IgtlSource,
    inverse_device_name,
    parse_address,
    parse_listen_address,
)
from fusedmosaic.io.recorder import DatasetRecorder, recover_unfinished_recordings
from fusedmosaic.io.tracking import interpolate_camera_poses
from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

# sockets and a sender on the wall clock: run alone (make test), not beside another worker
pytestmark = pytest.mark.realtime

N = 60


@pytest.fixture(scope="module")
def syn(tmp_path_factory):
    options = FetoscopyOptions(n_frames=N, laps=N / 37.5, width=300, height=300)
    return read_dataset(simulate_fetoscopy(tmp_path_factory.mktemp("igtl") / "syn", options))


def _live(syn, tmp_path, sender, *extra, quiet=True):
    return main([*(["--quiet"] if quiet else []), "live", f"127.0.0.1:{sender.port}", "--camera",
                 str(syn.root / "camera.yaml"), "--hand-eye", str(syn.root / "hand_eye.txt"),
                 "--transform", "SensorToTracker", "--record", str(tmp_path / "rec"), "--out",
                 str(tmp_path / "out"), "--no-report", *extra])


def test_live_session_mosaics_records_and_reports(syn, tmp_path):
    # half the real rate (12.5 frames/s): room for a slower CI machine; drops are tested by
    # the live replay's schedule (test_live.py) and measured by bench/bench_live.py
    sender = Sender(dataset_events(syn), speed=0.5)
    assert _live(syn, tmp_path, sender) == 0
    sender.join()
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    live = report["live"]
    assert live["stopped_by"] == "the sender closed the stream"
    assert live["frames_recorded"] == N  # every frame is recorded, dropped or not
    assert live["frames_processed"] + live["frames_dropped"] <= N
    assert live["frames_processed"] >= N // 2
    assert live["frames_without_sample"] == []
    assert live["source"]["frames_refused"] == {}
    # the recording is a dataset: the frames as sent, timestamps on the sender's clock, and
    # the tracker samples at their own rate (float32 on the wire: 1e-4 mm, 1e-6 rad)
    rec = read_dataset(tmp_path / "rec", allow_untracked=True)
    assert len(rec) == N
    for k in (0, N // 2, N - 1):
        np.testing.assert_array_equal(rec.frames[k], syn.frames[k])
    np.testing.assert_allclose(rec.timestamps - T0, syn.timestamps, atol=1e-6)
    sent = syn.tracking.timestamps[syn.tracking.valid]
    sent = sent[sent <= syn.timestamps[-1]]
    np.testing.assert_allclose(rec.tracking.timestamps - T0, sent, atol=1e-6)
    np.testing.assert_allclose(rec.tracking.translations,
                               syn.tracking.translations[syn.tracking.valid][:sent.size],
                               atol=1e-4)
    np.testing.assert_allclose(np.loadtxt(tmp_path / "rec" / "hand_eye.txt"),
                               np.loadtxt(syn.root / "hand_eye.txt"), atol=1e-12)
    # the live mosaic against the simulator's truth: within 1 px on 300x300 frames (offline
    # lba-emt on the same sequence is the reference; live differs by the dropped frames)
    ids, G = read_homographies_csv(tmp_path / "out" / "homographies.csv")
    assert list(ids) == list(range(N))
    placed = np.isfinite(G).all(axis=(1, 2))
    assert placed.sum() == live["frames_processed"]
    e_live = mosaic_error(frame_errors(G, syn.ground_truth, 300, 300))
    e_offline = mosaic_error(frame_errors(run_lba_emt(syn, progress=False).homographies,
                                          syn.ground_truth, 200, 200))
    assert e_live < 1.0, (e_live, e_offline)
    status = report["frame_status"]
    for k in live["dropped"]:
        assert status[k].startswith("unplaced: dropped (live")


def test_pose_at_interpolates_between_samples_or_holds_the_newest(syn):
    """The pose at a frame time: SLERP + linear between the samples around it (as offline),
    the newest one held when no later sample has arrived; inverse device names inverted."""
    tr = syn.tracking
    i = np.flatnonzero(tr.valid)[:4]
    events = [(float(tr.timestamps[j]), _inverse(tr, j)) for j in i]
    sender = Sender(events, speed=100.0, delay=0.0)
    with IgtlSource(f":{sender.port}", transform_device="SensorToTracker") as source:
        sender.join()
        while source.next_frame(2.0) is not None:  # none sent: ends when the stream closes
            pass
        t = 0.5 * (tr.timestamps[i[1]] + tr.timestamps[i[2]])
        pose, age = source.pose_at(T0 + t, syn.hand_eye, wait_s=0.0)
        expected, _ = interpolate_camera_poses(tr, [t], syn.hand_eye)
        np.testing.assert_allclose(pose, expected[0], atol=1e-5)
        assert age == pytest.approx(t - tr.timestamps[i[1]], abs=1e-6)
        late = tr.timestamps[i[3]] + 0.01  # after the last sample: held
        pose, age = source.pose_at(T0 + late, syn.hand_eye, wait_s=0.0)
        held, _ = interpolate_camera_poses(tr, [tr.timestamps[i[3]]], syn.hand_eye)
        np.testing.assert_allclose(pose, held[0], atol=1e-5)
        assert age == pytest.approx(0.01, abs=1e-6)
        # older than 3 sample periods: no sample
        assert source.pose_at(T0 + late + 1.0, syn.hand_eye, wait_s=0.0)[0] is None
        assert source.pose_at(T0 + tr.timestamps[i[0]] - 0.01, wait_s=0.0) == (None, None)


def test_position_messages_are_poses_like_transforms(syn):
    """A POSITION (x, y, z and the quaternion ox, oy, oz, w: 28 bytes, or 24 with w implied;
    header version 2 with metadata too) is a sample as a TRANSFORM of the same pose is;
    unusable ones are counted invalid, with the reason, not fatal."""
    tr = syn.tracking
    i = np.flatnonzero(tr.valid)[:4]
    M = [tracker_matrix(tr.translations[j], tr.quaternions[j]) for j in i]
    t = [float(tr.timestamps[j]) for j in i]
    events = [(t[0], position_message(M[0], t[0])),
              (t[1], position_message(M[1], t[1], size=24)),
              (t[2], position_message(M[2], t[2], metadata={"TransformStatus": "OK"})),
              (t[3], position_message(M[3], t[3], size=24, metadata={"Note": "x"}))]
    bad = [position_message(M[3], t[3] + 0.001, size=12),  # no orientation: not a pose
           position_message(M[3], t[3] + 0.002, size=16),
           position_message(M[3], t[3] + 0.003, metadata={"TransformStatus": "MISSING"}),
           position_message(M[3] * [1, 1, 1, np.nan], t[3] + 0.004)]  # x, y, z NaN
    raw = bytearray(position_message(M[3], t[3] + 0.005))
    raw[-4:] = np.array([3.0], ">f4").tobytes()  # w = 3: not a unit quaternion
    bad.append(_with_crc(bytes(raw)))  # (as a sender would compute it)
    sender = Sender(events + [(t[3], m) for m in bad], speed=100.0, delay=0.0)
    with IgtlSource(f":{sender.port}", transform_device="SensorToTracker") as source:
        sender.join()
        while source.next_frame(2.0) is not None:
            pass
        assert source.valid_samples == 4
        for j in range(4):
            pose, _ = source.pose_at(T0 + t[j], syn.hand_eye, wait_s=0.0)
            expected, _ = interpolate_camera_poses(tr, [t[j]], syn.hand_eye)
            np.testing.assert_allclose(pose, expected[0], atol=1e-5)
        invalid = source.invalid_samples
    assert invalid.pop("POSITION without an orientation (a 6-DoF pose is needed)") == 1
    assert invalid.pop("POSITION content of 16 bytes (expected 12, 24 or 28)") == 1
    assert invalid.pop("status MISSING") == 1
    assert invalid.pop("not finite") == 1
    (why, n), = invalid.items()
    assert why == "quaternion not of unit norm (within 1e-3)" and n == 1
    assert source.invalid_sample_details == {why: "norm 3"}


def _inverse(tr, j):
    M = tracker_matrix(tr.translations[j], tr.quaternions[j])
    return transform_message(np.linalg.inv(M), float(tr.timestamps[j]), "TrackerToSensor")


def test_connection_refused_names_the_address(syn, tmp_path, capsys):
    with socket.create_server(("127.0.0.1", 0)) as s:
        port = s.getsockname()[1]  # closed again: nothing listens there
    assert main(["live", f"127.0.0.1:{port}", "--camera", str(syn.root / "camera.yaml"),
                 "--transform", "SensorToTracker", "--record", str(tmp_path / "rec"),
                 "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert f"OpenIGTLink 127.0.0.1:{port}: cannot connect" in err
    assert not (tmp_path / "rec").exists() and not (tmp_path / "out").exists()
    assert not list(tmp_path.iterdir())  # no temporary recording left either


@pytest.mark.parametrize("keep_open, stopped", [
    (False, "no frame was processed (the sender closed the stream)"),
    (True, "no frame from IMAGE device Video in 1 s")])
def test_frames_of_the_wrong_size_are_refused_with_the_reason(syn, tmp_path, capsys, keep_open,
                                                              stopped):
    small = np.zeros((100, 120), np.uint8)
    events = [(0.04 * k, image_message(small, 0.04 * k)) for k in range(5)]
    if keep_open:  # the sender stays connected (a final message 2 s later)
        events.append((2.0, image_message(small, 2.0)))
    sender = Sender(events, delay=0.0)
    code = _live(syn, tmp_path, sender, "--frame-timeout", "1")
    sender.join()
    assert code == 2
    err = capsys.readouterr().err
    assert stopped in err
    assert ("frames refused: 5 x an image of another size than camera.yaml's 300x300 (width x "
            "height) (first: received frame 0, a 120x100 image)" in err)
    assert not list(tmp_path.iterdir())


def test_stream_cut_inside_a_message(syn, tmp_path, capsys):
    message = image_message(syn.frames[0], 0.0)
    sender = Sender([(0.0, message[: len(message) // 2])], delay=0.0)
    code = _live(syn, tmp_path, sender)
    sender.join()
    assert code == 2
    assert "the connection closed inside a message" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_invalid_tracker_samples_are_skipped_not_fatal(syn, tmp_path):
    """A sample that is not a rigid transform (a corrupt message), goes back in time or is
    stamped an hour ahead (a glitch: it was taken, and every later sample then went 'back in
    time', the rest of the session untracked; review) is not used or recorded; the session
    goes on."""
    from fusedmosaic.io.igtl import STAMP_JUMP

    events = dataset_events(syn, n_frames=45)
    bad = np.eye(4)
    bad[:3, :3] *= 2.0  # scaled: not a rotation
    mid = len(events) // 2
    t = events[mid][0]
    events[mid:mid] = [(t, transform_message(bad, t + 1e-4)),  # after the previous sample
                       (t, transform_message(np.eye(4), t - 1.0)),  # back in time
                       (t, transform_message(np.eye(4), t + 3600.0))]  # an hour ahead
    sender = Sender(events)
    assert _live(syn, tmp_path, sender) == 0
    sender.join()
    live = json.loads((tmp_path / "out" / "report.json").read_text())["live"]
    assert live["source"]["tracker_samples_invalid"] == {
        "not rigid: scaled": 1, "timestamp not after the previous sample": 1, STAMP_JUMP: 1}
    assert live["source"]["tracker_samples_invalid_details"] == {}  # (none with figures)
    assert live["frames_without_sample"] == []
    rec = read_dataset(tmp_path / "rec", allow_untracked=True)
    # the non-rigid sample is recorded as a missing one (valid=0: the dropout stays visible
    # offline), the one going back in time is not recorded (tracking.csv is in time order)
    assert (~rec.tracking.valid).sum() == 1
    assert rec.tracking.timestamps[~rec.tracking.valid][0] == pytest.approx(T0 + t + 1e-4)
    R = Rotation.from_quat(rec.tracking.quaternions[rec.tracking.valid]).as_matrix()
    assert np.allclose(np.linalg.det(R), 1.0)


@pytest.mark.parametrize("address, message", [
    ("host:0", "port in 1..65535"), ("host:http", "port in 1..65535"),
    ("host:70000", "port in 1..65535")])
def test_bad_addresses(address, message):
    with pytest.raises(ValueError, match=message):
        parse_address(address)


def test_parse_address_defaults():
    assert parse_address("scanner") == ("scanner", 18944)
    assert parse_address(":1234") == ("127.0.0.1", 1234)


def test_ipv6_addresses_in_brackets():
    """[IPV6]:PORT as URLs write it; an IPv6 address without brackets is refused, not split at
    its last ':' (which read '::1' as host ':' port 1)."""
    assert parse_address("[::1]:1234") == ("::1", 1234)
    assert parse_address("[fe80::1%eth0]") == ("fe80::1%eth0", 18944)
    assert parse_listen_address("[::1]:0") == ("::1", 0)
    assert parse_listen_address("[::]:18945") == ("::", 18945)
    for address in ("::1", "::1:18944", "fe80::1"):
        with pytest.raises(ValueError, match=re.escape(
                f"OpenIGTLink address {address!r}: an IPv6 address goes in brackets: "
                "[ADDRESS]:PORT, e.g. [::1]:18944")):
            parse_address(address)
    with pytest.raises(ValueError, match=r"'\[::1': expected \[IPV6\]:PORT"):
        parse_address("[::1")
    with pytest.raises(ValueError, match=r"'\[::1\]': expected PORT, HOST:PORT or \[IPV6\]:PORT"):
        parse_listen_address("[::1]")  # a server needs its port


def _ipv6_loopback() -> bool:
    try:
        with socket.create_server(("::1", 0), family=socket.AF_INET6):
            return True
    except OSError:
        return False


@pytest.mark.skipif(not _ipv6_loopback(), reason="no IPv6 loopback on this machine")
def test_mosaic_server_and_source_over_ipv6():
    image = np.arange(24 * 32 * 3, dtype=np.uint8).reshape(24, 32, 3)
    with IgtlImageServer("[::1]:0") as server:
        assert server.address == f"[::1]:{server.port}" and server.port > 0
        with IgtlSource(server.address, transform_device="NoneToNone",
                        image_device="Mosaic") as client:
            for _ in range(200):  # until the server has accepted the client
                if server.num_clients:
                    break
                time.sleep(0.01)
            assert server.send(image) == 1
            frame = client.next_frame(5.0)
    np.testing.assert_array_equal(frame.image, image)


def test_a_frame_received_before_a_connection_reset_is_handed_over(syn):
    """The sender resets the connection after 3 frames (the newest waiting, the others
    replaced): next_frame hands over the waiting frame before reporting the failure (it was
    discarded, and its status said 'received after the session ended')."""
    events = [(0.01 * k, image_message(syn.frames[k], 0.01 * k)) for k in range(3)]
    sender = Sender(events, delay=0.0, reset=True)
    with IgtlSource(f":{sender.port}", transform_device="SensorToTracker") as source:
        sender.join()
        for _ in range(500):  # until the receiver has seen the reset
            if source._error is not None:
                break
            time.sleep(0.01)
        assert isinstance(source._error, ConnectionResetError)
        frame = source.next_frame(1.0)
        assert frame is not None and frame.index == 2 and source.dropped == [0, 1]
        np.testing.assert_array_equal(frame.image, syn.frames[2])
        with pytest.raises(ValueError, match="Connection reset by peer"):
            source.next_frame(1.0)


def test_existing_recording_folder_is_refused_before_connecting(syn, tmp_path, capsys):
    (tmp_path / "rec").mkdir()
    (tmp_path / "rec" / "notes.txt").write_text("mine")
    assert main(["live", "127.0.0.1:1", "--camera", str(syn.root / "camera.yaml"),
                 "--transform", "SensorToTracker", "--record", str(tmp_path / "rec"),
                 "--out", str(tmp_path / "out")]) == 2
    assert "rec: exists and is not empty" in capsys.readouterr().err
    assert (tmp_path / "rec" / "notes.txt").read_text() == "mine"


def test_lba_emt_flags_refused_for_kalman_robot_before_connecting(syn, tmp_path, capsys):
    assert main(["live", "127.0.0.1:1", "--camera", str(syn.root / "camera.yaml"),
                 "--transform", "SensorToTracker", "--record", str(tmp_path / "rec"),
                 "--out", str(tmp_path / "out"), "--method", "kalman-robot",
                 "--guided-sift"]) == 2
    assert ("--guided-sift / --motion-sigma-from / --tracker-*-sigma / --visual-sigma / feature "
            "flags apply to lba-emt, not kalman-robot") in capsys.readouterr().err
    assert not (tmp_path / "rec").exists() and not (tmp_path / "out").exists()


def test_inverse_device_names():
    assert inverse_device_name("SensorToTracker") == "TrackerToSensor"
    assert inverse_device_name("ToolToTracker") == "TrackerToTool"  # not 'olToTrackerTo'
    assert inverse_device_name("TouchProbeToTracker") == "TrackerToTouchProbe"
    assert inverse_device_name("ProbeToTooltip") == "TooltipToProbe"
    with pytest.raises(ValueError, match="'Tracker' should be named like PLUS's"):
        inverse_device_name("Tracker")


@pytest.mark.parametrize("cut", ["inside", "huge body"])
def test_a_stream_failing_mid_session_keeps_what_was_done(syn, tmp_path, cut):
    """After frames were processed, a stream that breaks (cut inside a message, a corrupt
    header) ends the session: the recording and the outputs are written, report.json says why.
    A gray frame among colour ones is refused (a recording is one or the other)."""
    events = dataset_events(syn, n_frames=45)
    t = events[-1][0] + 0.04
    events.insert(len(events) // 2, (events[len(events) // 2][0],
                                     image_message(np.zeros((300, 300), np.uint8), 0.95)))
    message = image_message(syn.frames[45], t)
    if cut == "inside":
        events.append((t, message[: len(message) // 2]))
        why = "the connection closed inside a message"
    else:  # a header announcing a 2**40-byte body
        events.append((t, message[:42] + (2**40).to_bytes(8, "big") + message[50:]))
        why = "malformed OpenIGTLink header: a IMAGE message of 1099511627776 bytes"
    sender = Sender(events)
    assert _live(syn, tmp_path, sender) == 0
    sender.join()
    live = json.loads((tmp_path / "out" / "report.json").read_text())["live"]
    assert live["stopped_by"].startswith("the stream failed: ") and why in live["stopped_by"]
    assert live["frames_recorded"] == 45
    assert list(live["source"]["frames_refused"].values()) == [1]
    assert "a gray image after colour ones" in next(iter(live["source"]["frames_refused"]))
    assert len(read_dataset(tmp_path / "rec", allow_untracked=True)) == 45


def test_out_inside_the_recording_is_refused_before_connecting(syn, tmp_path, capsys):
    assert main(["live", "127.0.0.1:1", "--camera", str(syn.root / "camera.yaml"),
                 "--transform", "SensorToTracker", "--record", str(tmp_path / "rec"),
                 "--out", str(tmp_path / "rec" / "out")]) == 2
    assert "must not be the recording folder or inside it" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_frame_synchronous_sender_transform_after_image(syn):
    """PLUS Server sends a frame's image and transform with one timestamp; when the transform
    comes second, pose_at waits for it (age 0: the frame's own sample, not the previous one)."""
    tr, times = syn.tracking, syn.timestamps[:8]
    poses, _ = interpolate_camera_poses(tr, times, syn.hand_eye)
    events = []
    for k, t in enumerate(times):
        M = _sensor_in_tracker(syn, float(t))
        events += [(float(t), image_message(syn.frames[k], float(t))),
                   (float(t) + 0.004, transform_message(M, float(t)))]
    sender = Sender(events, delay=0.1)
    ages = []
    with IgtlSource(f":{sender.port}", transform_device="SensorToTracker") as source:
        while (frame := source.next_frame(2.0)) is not None:
            pose, age = source.pose_at(frame.timestamp, syn.hand_eye)
            ages.append(age)
            k = int(np.argmin(np.abs(times + T0 - frame.timestamp)))
            np.testing.assert_allclose(pose, poses[k], atol=1e-4)
    sender.join()
    assert ages and all(a == 0.0 for a in ages)


def _sensor_in_tracker(syn, t: float) -> np.ndarray:
    """tracker_from_sensor at time t, interpolated from the dataset's samples."""
    cam_from_sensor, _ = interpolate_camera_poses(syn.tracking, [t])  # no hand-eye: the sensor
    R = Rotation.from_rotvec(cam_from_sensor[0, :3]).inv()
    M = np.eye(4)
    M[:3, :3] = R.as_matrix()
    M[:3, 3] = -R.apply(cam_from_sensor[0, 3:])
    return M


@pytest.mark.parametrize("position", [False, True], ids=["transform", "position"])
def test_live_kalman_robot_session(tmp_path, position):
    """pCLE live: frames and the robot's probe positions (a TRANSFORM's translation, mm, or a
    POSITION without orientation) over OpenIGTLink to kalman-robot; recorded as robot.csv in
    µm; the positions against the simulator's truth as accurate as the offline run (same
    filter, the robot extrapolated to the frame time instead of interpolated)."""
    from _igtl_sender import robot_events

    from fusedmosaic.estimation.translation import run_kalman_robot
    from fusedmosaic.evaluation import position_errors_um
    from fusedmosaic.simulation import PcleOptions, simulate_pcle

    ds = read_dataset(simulate_pcle(tmp_path / "pcle", PcleOptions(
        width=192, height=160, n_frames=40, speed_um_per_frame=12.0, radius_um=150.0,
        contact_loss=False, stick_slip=False)))
    sender = Sender(robot_events(ds, position=position), speed=2.0)
    assert main(["--quiet", "live", f"127.0.0.1:{sender.port}", "--method", "kalman-robot",
                 "--camera", str(ds.root / "camera.yaml"), "--transform", "RobotToBase",
                 "--record", str(tmp_path / "rec"), "--out", str(tmp_path / "out"),
                 "--no-report"]) == 0
    sender.join()
    live = json.loads((tmp_path / "out" / "report.json").read_text())["live"]
    assert live["frames_recorded"] == len(ds) and live["frames_without_sample"] == []
    rec = read_dataset(tmp_path / "rec", allow_untracked=True)  # last frame after the last sample
    sent = ds.robot.timestamps <= ds.timestamps[-1]
    np.testing.assert_allclose(rec.robot.timestamps - T0, ds.robot.timestamps[sent], atol=1e-6)
    np.testing.assert_allclose(rec.robot.xy_um, ds.robot.xy_um[sent], atol=1e-3)  # float32 mm
    _, G = read_homographies_csv(tmp_path / "out" / "homographies.csv")
    cam = ds.camera

    def mean_um(H):
        return float(np.nanmean(position_errors_um(H, ds.ground_truth, cam.width, cam.height,
                                                   cam.pixel_size_um)))

    e_live, e_offline = mean_um(G), mean_um(run_kalman_robot(ds, progress=False).homographies)
    placed = np.isfinite(G).all(axis=(1, 2)).sum()
    assert placed == live["frames_processed"]
    # against the truth: below 1 µm (one 1 µm pixel; measured 0.06, offline
    # 0.05: without contact loss both follow the accurate robot)
    assert e_live < 1.0, (e_live, e_offline)


def test_live_robot_session_without_a_sample_names_the_robot(tmp_path, capsys):
    """live --method robot whose robot transform never comes (sent under another name): it
    ended in the canvas's "no placed frame to compose a mosaic from"; now the robot and the
    cause are named, and the recording is kept."""
    from _igtl_sender import robot_events

    from fusedmosaic.simulation import PcleOptions, simulate_pcle

    ds = read_dataset(simulate_pcle(tmp_path / "pcle", PcleOptions(
        width=96, height=80, n_frames=10, speed_um_per_frame=6.0, radius_um=80.0,
        contact_loss=False, stick_slip=False)))
    sender = Sender(robot_events(ds, device="ProbeToBase"), speed=2.0)
    with warnings.catch_warnings():
        warnings.simplefilter("default")  # (the session warns: no RobotToBase heard)
        assert main(["--quiet", "live", f"127.0.0.1:{sender.port}", "--method", "robot",
                     "--camera", str(ds.root / "camera.yaml"), "--transform", "RobotToBase",
                     "--record", str(tmp_path / "rec"), "--out", str(tmp_path / "out"),
                     "--no-report"]) == 2
    sender.join()
    err = capsys.readouterr().err
    assert "no valid robot sample (TRANSFORM or POSITION) of RobotToBase" in err
    assert f"live session from 127.0.0.1:{sender.port}: none of the " in err
    assert "frames has a robot sample" in err and "ProbeToBase" in err
    assert f"the recording is kept in {tmp_path / 'rec'}" in err
    assert (tmp_path / "rec" / "frames.csv").is_file() and not (tmp_path / "out").exists()


@pytest.mark.parametrize("with_robot", [True, False], ids=["robot-streamed", "images-only"])
def test_live_ncc_session(tmp_path, with_robot):
    """A hand-held pCLE probe (no robot, no --transform) mosaicked live by ncc, the images
    only: no warning for the samples it does not take, every frame placed as the offline ncc
    run on the recording places it; a robot's stream (--transform given) is recorded as
    robot.csv (the recording re-runs with kalman-robot) but not used."""
    from _igtl_sender import robot_events

    from fusedmosaic.estimation.translation import run_ncc
    from fusedmosaic.simulation import PcleOptions, simulate_pcle

    ds = read_dataset(simulate_pcle(tmp_path / "pcle", PcleOptions(
        width=192, height=160, n_frames=30, speed_um_per_frame=12.0, radius_um=150.0,
        contact_loss=False, stick_slip=False)))
    events = robot_events(ds)
    if not with_robot:  # (the header's message type: bytes 2-14)
        events = [(t, m) for t, m in events if m[2:14].rstrip(b"\0") == b"IMAGE"]
    sender = Sender(events, speed=2.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (no "no valid robot sample" warning)
        assert main(["--quiet", "live", f"127.0.0.1:{sender.port}", "--method", "ncc",
                     "--camera", str(ds.root / "camera.yaml"),
                     *(["--transform", "RobotToBase"] if with_robot else []),
                     "--record", str(tmp_path / "rec"), "--out", str(tmp_path / "out"),
                     "--no-report"]) == 0
    sender.join()
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    live = report["live"]
    assert live["frames_recorded"] == len(ds) and live["frames_without_sample"] == []
    assert report["parameters"]["estimate"] == "image" and report["warnings"] == []
    rec = read_dataset(tmp_path / "rec", allow_untracked=True)
    assert (rec.robot is not None) == with_robot
    _, G = read_homographies_csv(tmp_path / "out" / "homographies.csv")
    processed = np.isfinite(G).all(axis=(1, 2))
    assert processed.sum() == live["frames_processed"] > len(ds) // 2
    # against the truth (clean scan): below 1 px (measured 0.13)
    assert mosaic_error(frame_errors(G[processed], ds.ground_truth[processed], 192, 160)) < 1.0
    if processed.all():  # (frames dropped while busy: the chain registers across them)
        np.testing.assert_allclose(G, run_ncc(rec, progress=False).homographies, atol=1e-6)


@pytest.mark.parametrize("method", ["lba-emt", "kalman-robot", "robot"])
def test_live_needs_the_transform_device_except_for_ncc(syn, tmp_path, capsys, method):
    assert main(["live", "127.0.0.1:1", "--method", method, "--camera",
                 str(syn.root / "camera.yaml"), "--record", str(tmp_path / "rec"), "--out",
                 str(tmp_path / "out")]) == 2
    device = "tracker" if method == "lba-emt" else "robot"
    assert (f"live session: {method} needs the device of the {device} (--transform)"
            in capsys.readouterr().err)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("method", ["kalman-robot", "robot"])
def test_live_kalman_robot_needs_pixel_size(syn, tmp_path, capsys, method):
    assert main(["live", "127.0.0.1:1", "--method", method, "--camera",
                 str(syn.root / "camera.yaml"), "--transform", "RobotToBase", "--record",
                 str(tmp_path / "rec"), "--out", str(tmp_path / "out")]) == 2
    assert f"camera.yaml: no pixel_size_um; method {method!r} needs" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())
    assert main(["live", "127.0.0.1:1", "--method", method, "--camera",
                 str(syn.root / "camera.yaml"), "--transform", "RobotToBase", "--record",
                 str(tmp_path / "rec"), "--out", str(tmp_path / "out"), "--preset", "phb"]) == 2
    assert f"apply to lba-emt, not {method}" in capsys.readouterr().err


@pytest.mark.parametrize("flag, value", [("--duration", "0"), ("--max-frames", "-3"),
                                         ("--frame-timeout", "nan")])
def test_live_limits_are_checked_before_connecting(syn, tmp_path, capsys, flag, value):
    assert main(["live", "127.0.0.1:1", "--camera", str(syn.root / "camera.yaml"),
                 "--transform", "SensorToTracker", "--record", str(tmp_path / "rec"),
                 "--out", str(tmp_path / "out"), flag, value]) == 2
    assert f"{flag} must be a number > 0, got {value}" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_live_with_a_tracker_clock_ahead(syn, tmp_path):
    """A tracker whose clock is 80 ms ahead of the video's (its samples stamped 80 ms late):
    given --tracker-time-offset 0.08, every frame gets a sample and the recording is written
    on the video's clock (re-runnable without the offset, as `import` writes it)."""
    offset = 0.08
    sender = Sender(dataset_events(syn, clock_ahead_s=offset), speed=0.5)
    assert _live(syn, tmp_path, sender, "--tracker-time-offset", str(offset)) == 0
    sender.join()
    live = json.loads((tmp_path / "out" / "report.json").read_text())["live"]
    assert live["source"]["tracker_time_offset_s"] == offset
    assert live["frames_without_sample"] == []
    rec = read_dataset(tmp_path / "rec", allow_untracked=True)
    sent = syn.tracking.timestamps[syn.tracking.valid]
    sent = sent[sent <= syn.timestamps[-1]]
    np.testing.assert_allclose(rec.tracking.timestamps - T0, sent, atol=1e-6)
    from fusedmosaic.io.plus import applied_tracker_time_offset

    assert applied_tracker_time_offset(tmp_path / "rec") == offset  # run --calibration: no 2nd
    _, G = read_homographies_csv(tmp_path / "out" / "homographies.csv")
    assert mosaic_error(frame_errors(G, syn.ground_truth, 300, 300)) < 1.0


def test_live_kalman_robot_with_a_robot_clock_ahead(tmp_path):
    """The robot's clock 80 ms ahead: given the offset, the live positions are as accurate as
    with synchronous clocks (< 1 µm against the truth, as test_live_kalman_robot_session;
    measured 0.06); ignored, each frame takes the robot's position of 80 ms earlier (24 µm at
    300 µm/s; positions relative to frame 0's, itself 80 ms late: measured 7.4 µm)."""
    from _igtl_sender import robot_events

    from fusedmosaic.evaluation import position_errors_um
    from fusedmosaic.simulation import PcleOptions, simulate_pcle

    ds = read_dataset(simulate_pcle(tmp_path / "pcle", PcleOptions(
        width=192, height=160, n_frames=40, speed_um_per_frame=12.0, radius_um=150.0,
        contact_loss=False, stick_slip=False)))
    cam = ds.camera
    errors = {}
    for given in (0.08, 0.0):
        out = tmp_path / f"out{given}"
        sender = Sender(robot_events(ds, clock_ahead_s=0.08), speed=2.0)
        assert main(["--quiet", "live", f"127.0.0.1:{sender.port}", "--method",
                     "kalman-robot", "--camera", str(ds.root / "camera.yaml"), "--transform",
                     "RobotToBase", "--record", str(tmp_path / f"rec{given}"), "--out",
                     str(out), "--no-report", "--tracker-time-offset", str(given)]) == 0
        sender.join()
        _, G = read_homographies_csv(out / "homographies.csv")
        errors[given] = float(np.nanmean(position_errors_um(G, ds.ground_truth, cam.width,
                                                            cam.height, cam.pixel_size_um)))
    assert errors[0.08] < 1.0 and errors[0.0] > 3.0, errors


def test_live_tracker_time_offset_is_checked_before_connecting(syn, tmp_path, capsys):
    assert main(["live", "127.0.0.1:1", "--camera", str(syn.root / "camera.yaml"),
                 "--transform", "SensorToTracker", "--record", str(tmp_path / "rec"),
                 "--out", str(tmp_path / "out"), "--tracker-time-offset", "11"]) == 2
    assert "--tracker-time-offset: expected seconds within +-10" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def _free_port() -> int:
    with socket.create_server(("127.0.0.1", 0)) as s:
        return s.getsockname()[1]


def test_live_view_preview_and_mosaic_server(syn, tmp_path):
    """The growing mosaic as a PNG and as OpenIGTLink IMAGE 'Mosaic' to a connected client
    (here our own IgtlSource, as 3D Slicer would connect): the last one sent is the preview,
    which is the linear blend of the session's final homographies (render_mosaic)."""
    import threading

    from fusedmosaic.compositing import BlendOptions, render_mosaic

    port = _free_port()
    received = []

    def viewer() -> None:
        for _ in range(200):  # until the session's server listens
            try:
                client = IgtlSource(f"127.0.0.1:{port}", transform_device="NoneToNone",
                                    image_device="Mosaic",
                                    on_frame=lambda f: received.append(f.image) or True)
                break
            except ValueError:
                time.sleep(0.05)
        with client:
            while client.next_frame(10) is not None:
                pass

    thread = threading.Thread(target=viewer, daemon=True)
    thread.start()
    sender = Sender(dataset_events(syn), speed=0.5)
    preview = tmp_path / "preview.png"
    assert _live(syn, tmp_path, sender, "--preview", str(preview), "--serve-mosaic", str(port),
                 "--view-interval", "0.5") == 0
    sender.join()
    thread.join(30)
    live = json.loads((tmp_path / "out" / "report.json").read_text())["live"]
    view = live["view"]
    assert view["frames_drawn"] == live["frames_processed"] and view["problems"] == {}
    assert view["server"]["clients"] == 1 and view["server"]["device"] == "Mosaic"
    assert len(received) == view["server"]["messages_sent"] == view["published"] >= 2
    shown = cv2.imread(str(preview))
    np.testing.assert_array_equal(received[-1], shown)  # the final view, both ways
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".preview")]  # no temp left
    ids, G = read_homographies_csv(tmp_path / "out" / "homographies.csv")
    rec = read_dataset(tmp_path / "rec", allow_untracked=True)
    ok = np.flatnonzero(np.isfinite(G).all(axis=(1, 2)))
    offline = render_mosaic([rec.frames[k] for k in ok], G[ok], 300, 300,
                            mask=rec.camera.fov_mask(), blend=BlendOptions("linear")).image
    # the same blend up to where each canvas starts (a whole pixel): measured 0.0 grey levels
    best = np.inf
    for dy in range(3):
        for dx in range(3):
            a = shown[dy:, dx:].astype(float)
            h, w = min(a.shape[0], offline.shape[0]), min(a.shape[1], offline.shape[1])
            a, b = a[:h, :w], offline[:h, :w].astype(float)
            both = (a.sum(axis=2) > 0) & (b.sum(axis=2) > 0)
            if both.mean() > 0.5:
                best = min(best, float(np.abs(a - b)[both].mean()))
    assert best < 0.5


@pytest.mark.parametrize("extra, message", [
    (["--preview", "view.jpg"], "view.jpg: the preview is a PNG file (name it .png)"),
    (["--preview", "rec/view.png"], "the preview must not be inside the recording"),
    (["--serve-mosaic", "host:x"], "OpenIGTLink server address 'host:x': expected PORT, "
                                   "HOST:PORT or [IPV6]:PORT"),
    (["--serve-mosaic", "::1:18945"], "OpenIGTLink server address '::1:18945': an IPv6 address "
                                      "goes in brackets: [ADDRESS]:PORT"),
    (["--serve-mosaic", "0", "--view-interval", "-1"], "--view-interval): must be >= 0 s"),
])
def test_live_view_flags_are_checked_before_connecting(syn, tmp_path, capsys, monkeypatch,
                                                       extra, message):
    monkeypatch.chdir(tmp_path)
    assert main(["live", "127.0.0.1:1", "--camera", str(syn.root / "camera.yaml"),
                 "--transform", "SensorToTracker", "--record", "rec", "--out", "out",
                 *extra]) == 2
    err = capsys.readouterr().err
    assert message in err and "cannot connect" not in err
    assert not list(tmp_path.iterdir())


def test_mosaic_server_port_in_use_is_named(syn, tmp_path, capsys):
    with socket.create_server(("127.0.0.1", 0)) as busy:
        port = busy.getsockname()[1]
        assert main(["live", "127.0.0.1:1", "--camera", str(syn.root / "camera.yaml"),
                     "--transform", "SensorToTracker", "--record", str(tmp_path / "rec"),
                     "--out", str(tmp_path / "out"), "--serve-mosaic", str(port)]) == 2
    assert (f"OpenIGTLink server 127.0.0.1:{port}: cannot listen" in capsys.readouterr().err)
    assert not list(tmp_path.iterdir())


def _image_sent_twice(events):
    """Each IMAGE message of `events` followed by a copy (same timestamp), as a sender whose
    capture repeats frames."""
    out = []
    for t, message in events:
        out.append((t, message))
        if message[2:14].rstrip(b"\0") == b"IMAGE":
            out.append((t, message))
    return out


def test_max_frames_records_that_many_and_refusals_count_per_reason(syn, tmp_path, capsys):
    """--max-frames 25: 25 frames recorded (none after: counted), the session stops once the
    last is processed, and says so truly (it recorded 54 of 50 while saying '50 frames
    received'). Every image sent twice: the repeats are refused under one reason, whatever
    their number (one key per frame before, the frame's number in it), with the first one."""
    sender = Sender(_image_sent_twice(dataset_events(syn, n_frames=40)), speed=0.5)
    assert _live(syn, tmp_path, sender, "--max-frames", "25", quiet=False) == 0
    sender.join()
    live = json.loads((tmp_path / "out" / "report.json").read_text())["live"]
    assert live["stopped_by"] == "25 frames recorded (--max-frames)"
    assert live["frames_recorded"] == 25 == len(read_dataset(tmp_path / "rec",
                                                              allow_untracked=True))
    assert live["frames_processed"] + live["frames_dropped"] == 25  # the last one processed
    source = live["source"]
    why = "timestamp does not increase (a repeated or earlier timestamp)"
    # the repeats of frames 0..23; frame 24's arrives after the limit
    assert source["frames_refused"] == {why: 24}
    assert source["frames_refused_first"] == {why: 1}  # the second message received
    assert source["frames_after_max_frames"] >= 1
    # said at the first refusal, and summed up (refused frames went without a word; audit)
    said = capsys.readouterr()
    text = said.out + said.err
    assert text.count(f"received frame 1 refused, neither processed nor recorded: {why}") == 1
    assert f"24 received frame(s) refused, neither processed nor recorded; 24 x {why}" in text


def test_a_tracker_on_another_clock_is_told(syn, tmp_path, capsys):
    """TRANSFORMs stamped from the tracker's own start, IMAGEs in epoch seconds: no frame gets
    a pose. Said at the first frame, and the failure names the clocks (it said only that no
    pair 'could be registered with tracker poses'; audit)."""
    sender = Sender(dataset_events(syn, n_frames=30, clock_ahead_s=-T0), speed=0.5)
    assert _live(syn, tmp_path, sender) == 2  # (--quiet: warnings reach stderr all the same)
    sender.join()
    text = capsys.readouterr().err
    assert re.search(r"live session: frame \d+ \(recorded\) is stamped 17\d{8}\.\d{3} s, the "
                     r"tracker's latest sample \d+\.\d{3} s \(\+17\d{8}\.\d{3} s\): on another "
                     r"clock\? The frames get no tracker sample near their time: the sender must "
                     r"stamp the images and the tracker on one clock", text), text
    assert re.search(r"valid tracker samples are stamped \d+\.\d{3}-\d+\.\d{3} s, the frames "
                     r"17\d{8}\.\d{3}-17\d{8}\.\d{3} s: on another clock\?", text), text


def test_another_image_device_heard_first_is_named(syn, tmp_path, capsys):
    """An IMAGE of another device before the video's: the session takes it (the first heard)
    and refuses its frame; the error now names the video device it ignored and the option."""
    events = dataset_events(syn, n_frames=10)
    events.insert(0, (events[0][0] - 0.01, image_message(syn.frames[0][:50, :50], 0.0,
                                                         "Other")))
    sender = Sender(events, speed=0.5)
    assert _live(syn, tmp_path, sender) == 2
    sender.join()
    assert ("the session took the IMAGE device Other (the first heard) and ignored Video: "
            "choose one with --image-device" in capsys.readouterr().err)


def test_unstamped_images_end_a_session_only_from_the_start(syn, tmp_path, capsys):
    """IMAGEs with timestamp 0 (the sender does not stamp them) are refused from the first;
    one unstamped frame mid-stream is refused and counted (it ended the session; audit)."""
    events = dataset_events(syn, n_frames=20)
    images = [i for i, (_, m) in enumerate(events) if m[2:7] == b"IMAGE"]
    t, _ = events[images[10]]
    events[images[10]] = (t, image_message(syn.frames[10], -T0))  # stamped 0
    sender = Sender(events, speed=0.5)
    assert _live(syn, tmp_path, sender) == 0
    sender.join()
    live = json.loads((tmp_path / "out" / "report.json").read_text())["live"]
    assert live["stopped_by"] == "the sender closed the stream"
    assert live["frames_recorded"] == 19
    assert live["source"]["frames_refused"] == {
        "no timestamp (0): the sender did not stamp it": 1}
    events = dataset_events(syn, n_frames=5)
    first = next(i for i, (_, m) in enumerate(events) if m[2:7] == b"IMAGE")
    events[first] = (events[first][0], image_message(syn.frames[0], -T0))
    sender = Sender(events, speed=0.5)
    assert _live(syn, tmp_path / "b", sender) == 2
    sender.join()
    assert "the IMAGE messages of 'Video' carry no timestamp (0)" in capsys.readouterr().err


def test_preview_folder_is_created_and_the_free_port_taken_is_told(syn, tmp_path, capsys):
    """--preview in a folder that does not exist yet: created, as --out is (the PNG was never
    written, only report.json said so); --serve-mosaic 0: the port taken is told when the
    server starts (it was only in report.json)."""
    preview = tmp_path / "views" / "today" / "view.png"
    sender = Sender(dataset_events(syn, n_frames=20))
    code = main(["live", f"127.0.0.1:{sender.port}", "--camera",  # not --quiet: it is told
                 str(syn.root / "camera.yaml"), "--hand-eye", str(syn.root / "hand_eye.txt"),
                 "--transform", "SensorToTracker", "--record", str(tmp_path / "rec"), "--out",
                 str(tmp_path / "out"), "--no-report", "--preview", str(preview),
                 "--serve-mosaic", "0"])
    sender.join()
    assert code == 0
    view = json.loads((tmp_path / "out" / "report.json").read_text())["live"]["view"]
    address = view["server"]["address"]
    assert re.fullmatch(r"127\.0\.0\.1:\d+", address) and not address.endswith(":0")
    assert (f"live: the mosaic is served on {address} (OpenIGTLink IMAGE "
            "'Mosaic'; --serve-mosaic 0 took this free port)") in capsys.readouterr().out
    assert view["problems"] == {} and view["published"] >= 1
    assert cv2.imread(str(preview)).shape[2] == 3
    # the next session into the same OUT replaces the preview its predecessor wrote
    before = preview.stat().st_mtime_ns
    sender = Sender(dataset_events(syn, n_frames=20))
    code = main(["live", f"127.0.0.1:{sender.port}", "--quiet", "--camera",
                 str(syn.root / "camera.yaml"), "--hand-eye", str(syn.root / "hand_eye.txt"),
                 "--transform", "SensorToTracker", "--record", str(tmp_path / "rec2"), "--out",
                 str(tmp_path / "out"), "--no-report", "--preview", str(preview)])
    sender.join()
    assert code == 0 and preview.stat().st_mtime_ns != before


def test_preview_never_replaces_an_image_it_did_not_write(syn, tmp_path, capsys):
    """--preview naming someone's PNG (e.g. a frame of another dataset): refused before
    connecting, the file untouched (before: replaced by the mosaic every second)."""
    mine = tmp_path / "frames" / "000005.png"
    mine.parent.mkdir()
    cv2.imwrite(str(mine), np.full((20, 30), 7, np.uint8))
    content = mine.read_bytes()
    assert main(["live", "127.0.0.1:1", "--camera", str(syn.root / "camera.yaml"),
                 "--hand-eye", str(syn.root / "hand_eye.txt"),
                 "--transform", "SensorToTracker", "--record", str(tmp_path / "rec"),
                 "--out", str(tmp_path / "out"), "--preview", str(mine)]) == 2
    err = capsys.readouterr().err
    assert err == (f"fusedmosaic: error: {mine}: exists and no earlier live session into "
                   f"{tmp_path / 'out'} wrote it; choose another preview path, or move that "
                   "file\n")
    assert mine.read_bytes() == content and sorted(os.listdir(tmp_path)) == ["frames"]


@pytest.mark.parametrize("fails", ["listen", "connect"])
def test_a_failed_start_leaves_no_folder_behind(syn, tmp_path, capsys, fails):
    """The folders made on the way to --record, --out and --preview are removed again when the
    session cannot start (a busy --serve-mosaic port, no sender): runs/busy/ was left empty."""
    with socket.create_server(("127.0.0.1", 0)) as busy:
        port = busy.getsockname()[1]
        serve = ["--serve-mosaic", str(port)] if fails == "listen" else []
        assert main(["live", "127.0.0.1:1", "--camera", str(syn.root / "camera.yaml"),
                     "--transform", "SensorToTracker", "--record",
                     str(tmp_path / "runs" / "busy" / "rec"), "--out",
                     str(tmp_path / "runs" / "busy" / "out"), "--preview",
                     str(tmp_path / "runs" / "views" / "v.png"), *serve]) == 2
    err = capsys.readouterr().err
    assert ("cannot listen" if fails == "listen" else "cannot connect") in err
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("stop", ["SIGTERM", "SIGHUP", "SIGINT", "SIGHUP ignored"])
def test_a_stop_signal_while_the_recording_is_finished_keeps_it(syn, tmp_path, monkeypatch,
                                                                  stop):
    """SIGTERM / SIGHUP (a launcher stopping the service, a closed terminal: the CLI turns them
    into Ctrl-C) arriving while the recording is moved into place is handled once it is there
    (exit 130): it deleted the recording. A first Ctrl-C once the session's loop is over is
    told and ignored (runner._EndingGuard): the outputs are written (exit 0). A SIGHUP that the
    session was started to ignore (`nohup fusedmosaic live ...`) stays ignored: the session
    ends normally (exit 0)."""
    from fusedmosaic.io import recorder

    move = recorder._replace_dir

    ignore = stop.endswith(" ignored")
    stop = stop.split()[0]
    sig = getattr(signal, stop)
    # the signal's usual handling (a process started by a non-interactive shell's `cmd &`
    # inherits SIGINT ignored: there Ctrl-C does nothing, and is rightly not deferred)
    handler = (signal.SIG_IGN if ignore else
               signal.default_int_handler if stop == "SIGINT" else signal.SIG_DFL)

    def stopped_meanwhile(src, dst):
        os.kill(os.getpid(), sig)
        time.sleep(0.05)  # delivered here, in the middle
        move(src, dst)

    monkeypatch.setattr(recorder, "_replace_dir", stopped_meanwhile)
    with signal_handler(sig, handler):
        sender = Sender(dataset_events(syn, n_frames=15))
        completes = ignore or stop == "SIGINT"
        assert _live(syn, tmp_path, sender) == (0 if completes else 130)
        assert signal.getsignal(sig) is handler
    sender.join()
    assert len(read_dataset(tmp_path / "rec", allow_untracked=True)) == 15
    assert sorted(p.name for p in tmp_path.iterdir()) == (["out", "rec"] if completes
                                                          else ["rec"])


@pytest.mark.parametrize("interrupts", [1, 2])
def test_ctrl_c_while_the_outputs_are_written(syn, tmp_path, monkeypatch, capsys, interrupts):
    """Once the session ended, a first Ctrl-C is told and ignored while the outputs are
    written; a second abandons them and names the kept recording (one Ctrl-C lost the whole
    live result; audit)."""
    from fusedmosaic import runner

    write = runner.run_dataset

    def interrupted_meanwhile(*args, **kwargs):
        for _ in range(interrupts):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)  # delivered here
        return write(*args, **kwargs)

    monkeypatch.setattr(runner, "run_dataset", interrupted_meanwhile)
    with signal_handler(signal.SIGINT, signal.default_int_handler):
        sender = Sender(dataset_events(syn, n_frames=15))
        assert _live(syn, tmp_path, sender, quiet=False) == (0 if interrupts == 1 else 130)
    sender.join()
    said = capsys.readouterr().out
    assert "live session: ending, writing the outputs; Ctrl-C again abandons them" in said
    assert (tmp_path / "out" / "homographies.csv").is_file() == (interrupts == 1)
    assert ("live session: outputs abandoned; the recording is kept in" in said) == (
        interrupts == 2)
    assert len(read_dataset(tmp_path / "rec", allow_untracked=True)) == 15


_KILLED = """
import sys, time
import numpy as np
from fusedmosaic.io.calibration import Camera
from fusedmosaic.io.recorder import DatasetRecorder
camera = Camera(64, 48, camera_matrix=np.array([[60.0, 0, 32], [0, 60, 24], [0, 0, 1]]))
recorder = DatasetRecorder(sys.argv[1], camera, np.eye(4))
rng = np.random.default_rng(0)
for k in range(5):
    pose = np.eye(4)
    pose[:3, 3] = [k, 0, 50]
    recorder.add_sample(10 + 0.04 * k, pose)
    recorder.add_frame(rng.integers(0, 255, (48, 64), np.uint8), 10 + 0.04 * k)
recorder.add_sample(10.19, None)
while recorder.frames_written < 5:
    time.sleep(0.01)
print(recorder.staging, flush=True)
time.sleep(60)
"""


def test_a_killed_session_leaves_a_dataset_that_the_next_one_recovers(tmp_path):
    """A session killed outright (SIGKILL: no clean-up runs) left frames/*.png alone in a
    hidden folder, never cleaned. The staging folder is a dataset as it grows; the next
    recorder in that folder recovers it as NAME.recovered-START (the last, incomplete row and
    frame dropped) and says where."""
    child = subprocess.Popen([sys.executable, "-c", _KILLED, str(tmp_path / "rec")],
                             stdout=subprocess.PIPE, text=True)
    try:
        staging = Path(child.stdout.readline().strip())
        grown = read_dataset(staging, allow_untracked=True)  # while it runs: a dataset
        assert len(grown) == 5 and grown.tracking.valid.tolist() == [True] * 5 + [False]
        assert recover_unfinished_recordings(tmp_path) == []  # its session is alive: untouched
    finally:
        child.kill()
        child.wait()
        child.stdout.close()
    assert child.returncode == -signal.SIGKILL
    # as if killed while frame 5 was written and renamed, its row and a sample half written
    (staging / "frames" / ".000005.part.png").write_bytes(b"\x89PNG")
    (staging / "frames" / "000005.png").write_bytes(b"\x89PNG")
    with (staging / "frames.csv").open("a") as f:
        f.write("5,10.2")
    with (staging / "tracking.csv").open("a") as f:
        f.write("10.23,1.0,")
    # an earlier version's leftover of the same recording (frames only) and an empty one
    (tmp_path / ".rec.tmp-older" / "frames").mkdir(parents=True)
    empty = tmp_path / ".other.tmp-x"
    empty.mkdir()
    (empty / ".fusedmosaic-recording.json").write_text('{"name": "other"}')
    (empty / "frames.csv").write_text("frame,timestamp\n")
    camera = grown.camera
    with pytest.warns(UserWarning) as said:
        DatasetRecorder(tmp_path / "rec", camera).abort()
    notes = sorted((str(w.message) for w in said), key=lambda note: (
        note.startswith("/"), "without a frame" in note))
    recovered = sorted(tmp_path.glob("rec.recovered-*"))
    assert len(notes) == 3 and len(recovered) == 1
    assert re.fullmatch(
        rf"a live session recording into {re.escape(str(tmp_path / 'rec'))} \(process "
        rf"{child.pid}, started [-0-9: ]+\) ended without finishing \(killed or crashed\); "
        rf"its 5 frame\(s\) are recovered as the dataset {re.escape(str(recovered[0]))} "
        rf"\(re-run it offline: fusedmosaic run .* --method ba-emt --out OUT "
        rf"--allow-untracked\)", notes[0])
    assert notes[1].startswith(f"a live session recording into {tmp_path / 'other'} ended "
                               f"without finishing and without a frame; removed its {empty}")
    assert notes[2].startswith(f"{tmp_path / '.rec.tmp-older'}: frames of an earlier recording "
                               f"into {tmp_path / 'rec'} that never finished")
    ds = read_dataset(recovered[0], allow_untracked=True)
    assert len(ds) == 5 and ds.tracking.timestamps.tolist() == [10, 10.04, 10.08, 10.12,
                                                                 10.16, 10.19]
    np.testing.assert_array_equal(ds.tracking.translations[:5, 0], np.arange(5.0))
    np.testing.assert_array_equal(ds.hand_eye, np.eye(4))
    assert sorted(p.name for p in recovered[0].iterdir()) == [
        "camera.yaml", "frames", "frames.csv", "hand_eye.txt", "tracking.csv"]
    assert sorted(p.name for p in (recovered[0] / "frames").iterdir()) == [
        f"{k:06d}.png" for k in range(5)]
    assert sorted(p.name for p in tmp_path.iterdir()) == [".rec.tmp-older",
                                                          recovered[0].name]


def test_a_recording_that_cannot_be_written_further_keeps_its_frames(tmp_path, monkeypatch):
    """A frame that cannot be written (a full disk): the recording stops growing there and the
    frames written before are kept as a dataset, the error saying so (finish deleted them)."""
    from fusedmosaic.io import recorder as module
    from fusedmosaic.io.calibration import Camera

    write = module._write_png

    def full(path, *args):
        if "000003" in str(path):
            raise OSError(f"{path}: cv2.imwrite failed")
        write(path, *args)

    monkeypatch.setattr(module, "_write_png", full)
    camera = Camera(64, 48, camera_matrix=np.array([[60.0, 0, 32], [0, 60, 24], [0, 0, 1]]))
    recorder = DatasetRecorder(tmp_path / "rec", camera)
    for k in range(6):
        recorder.add_sample(0.04 * k, np.eye(4))
        try:
            recorder.add_frame(np.full((48, 64), 10 * k, np.uint8), 0.04 * k)
        except OSError:  # once the writer failed, the next frame is refused at once
            break
    with pytest.raises(ValueError, match=r"rec: stopped after 3 frame\(s\) \(.*000003\.part\.png: "
                                         r"cv2\.imwrite failed\); those are kept there"):
        recorder.finish()
    ds = read_dataset(tmp_path / "rec", allow_untracked=True)
    assert len(ds) == 3 and ds.frames[2][0, 0] == 20
    assert recorder.finish() == tmp_path / "rec"  # done: again returns the folder
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]


def _first_pixels(events) -> tuple[list[int], IgtlSource]:
    """The first pixel of each frame an IgtlSource offers from the sent `events`, and the
    source (closed) for its counters."""
    sender = Sender(events, delay=0.1)
    seen = []
    with IgtlSource(f":{sender.port}", transform_device="SensorToTracker") as source:
        while (frame := source.next_frame(2.0)) is not None:
            seen.append(int(frame.image.reshape(-1)[0]))
    sender.join()
    return seen, source


def _with_crc(message: bytes) -> bytes:
    """The message with its header's CRC64 computed again over its (edited) body."""
    import crcmod

    crc = crcmod.mkCrcFun(0x142F0E1EBA9EA3693, rev=False, initCrc=0, xorOut=0)(message[58:])
    return message[:50] + crc.to_bytes(8, "big") + message[58:]


def test_corrupted_undecodable_and_unread_tracker_messages_are_named():
    """Review of the OpenIGTLink reader against the spec (openigtlink/OpenIGTLink Documents/
    Protocol): a body that fails its CRC64 was taken as a pose (one bit flipped: ty 3.25 mm ->
    -7e-39); metadata in ISO-8859-1 (legal, pyigtl reads only ASCII / UTF-8) ended the session
    with "exceptions must derive from BaseException"; a timestamp of 0 (the spec's "unused")
    read as "not after the previous sample"; TDATA / QTRANS were dropped unheard. Now invalid
    samples with their reason, and the devices of unread types listed."""
    pose = tracker_matrix([12.5, -3.25, 150.0], [0.1, 0.2, 0.3, np.sqrt(0.86)])
    good = transform_message(pose, 0.00)
    flipped = bytearray(transform_message(pose, 0.04))
    flipped[58 + 40] ^= 0x01  # a bit of ty, the header's CRC kept
    latin = pyigtl.TransformMessage(pose, timestamp=T0 + 0.08, device_name="SensorToTracker")
    latin.header_version, latin.metadata = 2, {"Note": "ok"}
    raw = bytearray(latin.pack())
    meta = raw[-(2 + 8 + len("Note") + len("ok")):]  # index count, then key size, encoding
    assert meta[:2] == b"\x00\x01" and meta[4:6] == (3).to_bytes(2, "big")  # US-ASCII
    raw[len(raw) - len(meta) + 4: len(raw) - len(meta) + 6] = (4).to_bytes(2, "big")
    unstamped = pyigtl.TransformMessage(pose, timestamp=0.0, device_name="SensorToTracker")
    tdata = pyigtl.MessageBase(timestamp=T0 + 0.1, device_name="Tracker")
    tdata._message_type = "TDATA"
    image = np.zeros((8, 8), np.uint8)
    events = [(0.0, image_message(image, 0.0)), (0.0, good), (0.04, bytes(flipped)),
              (0.08, _with_crc(bytes(raw))), (0.1, unstamped.pack()), (0.1, tdata.pack()),
              (0.12, transform_message(pose, 0.12)), (0.12, image_message(image, 0.12))]
    sender = Sender(events, delay=0.1)
    with IgtlSource(f":{sender.port}", transform_device="SensorToTracker") as source:
        while source.next_frame(2.0) is not None:
            pass
    sender.join()
    assert source.valid_samples == 2
    assert source.invalid_samples == {
        "CRC64 of the body differs from the header's (corrupted message)": 1,
        "its metadata is in a text encoding other than ASCII or UTF-8": 1,
        "no timestamp (0): the sender does not stamp its samples": 1}
    assert source.ignored_devices == {"TDATA Tracker (type not read)"}


def test_an_image_failing_its_crc_is_dropped_and_counted():
    """An IMAGE whose body fails its CRC64 (one pixel bit flipped in transit, the header's CRC
    kept) was offered as a frame; now it is dropped and counted, the session goes on."""
    images = [np.full((8, 8), 10 * (k + 1), np.uint8) for k in range(3)]
    corrupted = bytearray(image_message(images[1], 0.04))
    corrupted[-1] ^= 0x01
    events = [(0.0, image_message(images[0], 0.0)), (0.04, bytes(corrupted)),
              (0.08, image_message(images[2], 0.08))]
    seen, source = _first_pixels(events)
    assert 30 in seen and 20 not in seen, seen  # (frame 10 may be replaced before taken)
    assert source.corrupted_frames == 1 and source.received == 2


def test_images_without_timestamps_end_the_session_with_the_reason():
    sender = Sender([(0.0, pyigtl.ImageMessage(np.zeros((1, 8, 8), np.uint8), timestamp=0.0,
                                               device_name="Video").pack())], delay=0.1)
    with IgtlSource(f":{sender.port}", transform_device="SensorToTracker") as source:
        with pytest.raises(ValueError, match=r"the IMAGE messages of 'Video' carry no "
                                             r"timestamp \(0\)"):
            source.next_frame(2.0)
    sender.join()


def _undecodable(image: np.ndarray, t: float) -> bytes:
    """An IMAGE whose header's size is image's but whose body holds a quarter of its pixels
    (CRC recomputed, as a buggy sender would)."""
    good = image_message(image, t)
    small = image_message(image[: image.shape[0] // 2, : image.shape[1] // 2], t)
    body = good[58:58 + 72] + small[58 + 72:]
    return _with_crc(good[:42] + len(body).to_bytes(8, "big") + good[50:58] + body)


def test_an_undecodable_image_is_dropped_and_counted():
    """One IMAGE that cannot be decoded mid-stream ended the session (every later frame lost;
    review): now it is dropped and counted per reason, the frames after it arrive. Images that
    never decode (the first UNDECODABLE_LIMIT) still end it, naming why."""
    from fusedmosaic.io import igtl

    images = [np.full((8, 8), 10 * (k + 1), np.uint8) for k in range(3)]
    events = [(0.0, image_message(images[0], 0.0)), (0.04, _undecodable(images[1], 0.04)),
              (0.08, image_message(images[2], 0.08))]
    seen, source = _first_pixels(events)
    assert 30 in seen and 20 not in seen, seen
    assert source.received == 2 and sum(source.undecodable_frames.values()) == 1
    (why,) = source.undecodable_frames
    assert "cannot reshape" in why, why
    bad = [(0.04 * k, _undecodable(images[0], 0.04 * k)) for k in range(igtl.UNDECODABLE_LIMIT)]
    sender = Sender(bad, delay=0.1)
    with IgtlSource(f":{sender.port}", transform_device="SensorToTracker") as source:
        with pytest.raises(ValueError, match=rf"the IMAGE messages of 'Video' cannot be decoded "
                                             rf"\(the first {igtl.UNDECODABLE_LIMIT}, none "
                                             r"decoded\): .*cannot reshape"):
            while source.next_frame(2.0) is not None:
                pass
    sender.join()


def test_a_sender_dying_after_a_header_is_a_cut_not_a_close():
    """Only a message's header arrived, then the socket closed: it was told as 'the sender
    closed the stream' and the lost frame never mentioned (review)."""
    message = image_message(np.zeros((8, 8), np.uint8), 0.0)
    sender = Sender([(0.0, message[:58])], delay=0.1)
    with IgtlSource(f":{sender.port}", transform_device="SensorToTracker") as source:
        with pytest.raises(ValueError, match=r"the connection closed inside a message "
                                             r"\(after the header of a message of type "
                                             r"IMAGE, none of its \d+ body bytes\)$"):
            while source.next_frame(2.0) is not None:
                pass
    sender.join()


def test_stamp_jumps_refuse_a_glitch_and_follow_a_new_clock():
    """StampJumps (frames in run_igtl, samples in IgtlSource): a stamp more than its lead bound
    (StampJumps.lead_bound) ahead of the time since the last accepted one arrived is refused, and
    the stream goes on from the last accepted one; STAMP_JUMP_CONFIRM such stamps in a row,
    consistent among themselves, are a clock jump: the last is accepted."""
    from fusedmosaic.io.igtl import STAMP_JUMP, STAMP_JUMP_CONFIRM, StampJumps

    jumps = StampJumps()
    assert jumps.check(100.0, 0.0) is None
    jumps.accepted(100.0, 0.0)
    assert jumps.check(3700.04, 0.04) == STAMP_JUMP  # an hour ahead, 40 ms later: a glitch
    assert jumps.check(100.08, 0.08) is None  # the stream goes on
    jumps.accepted(100.08, 0.08)
    assert jumps.check(100.08 + 3.0, 0.12) == STAMP_JUMP  # 3 s ahead of an 80 ms stream too
    assert jumps.check(100.08 + 0.7, 0.12) is None  # 0.66 s ahead: within 10 intervals
    jumps.accepted(100.08 + 0.7, 0.12)
    for k in range(1, STAMP_JUMP_CONFIRM):  # the clock jumps an hour and stays there
        assert jumps.check(3709.0 + 0.04 * k, 0.12 + 0.04 * k) == STAMP_JUMP
    k = STAMP_JUMP_CONFIRM
    assert jumps.check(3709.0 + 0.04 * k, 0.12 + 0.04 * k) is None
    assert jumps.jumps == [pytest.approx(3709.0 + 0.04 * k - 100.78 - 0.04 * k)]


def test_a_frame_stamped_an_hour_ahead_is_refused_alone(syn, tmp_path):
    """One frame stamped an hour ahead mid-stream was accepted and recorded, and every later
    frame refused as not increasing (24 of 40; review): now that frame alone is refused,
    counted, and the rest recorded."""
    from fusedmosaic.io.igtl import STAMP_JUMP

    events = dataset_events(syn, n_frames=30)
    images = [i for i, (_, m) in enumerate(events) if m[2:7] == b"IMAGE"]
    i = images[15]
    t = events[i][0]
    events[i] = (t, image_message(syn.frames[15], t + 3600.0))
    sender = Sender(events)
    assert _live(syn, tmp_path, sender) == 0
    sender.join()
    live = json.loads((tmp_path / "out" / "report.json").read_text())["live"]
    assert live["source"]["frames_refused"] == {STAMP_JUMP: 1}
    assert live["source"]["frames_refused_first"] == {STAMP_JUMP: 15}
    assert live["frames_recorded"] == 29


def test_sender_clock_jump_taken_and_reported(syn, tmp_path, capsys):
    """The sender's clock jumping an hour ahead mid-session, frames and tracker alike: the
    first STAMP_JUMP_CONFIRM - 1 of each after it are refused as glitches, then the jump is
    taken; both jumps are warned of (the samples' was taken silently) and kept in report.json:
    live source frame_clock_jumps_s / sample_clock_jumps_s and warnings."""
    from fusedmosaic.io.igtl import STAMP_JUMP, STAMP_JUMP_CONFIRM

    jump_at = float(syn.timestamps[20])
    sender = Sender(dataset_events(syn, n_frames=40,
                                   stamp=lambda t: t + (3600.0 if t >= jump_at else 0.0)))
    assert _live(syn, tmp_path, sender) == 0
    sender.join()
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    source = report["live"]["source"]
    assert source["frames_refused"] == {STAMP_JUMP: STAMP_JUMP_CONFIRM - 1}
    assert source["tracker_samples_invalid"] == {STAMP_JUMP: STAMP_JUMP_CONFIRM - 1}
    assert source["frame_clock_jumps_s"] == [pytest.approx(3600.0, abs=0.5)]
    assert source["sample_clock_jumps_s"] == [pytest.approx(3600.0, abs=0.5)]
    said = [w for w in report["warnings"] if "jumped" in w]
    assert len(said) == 2 and "frame stamps jumped" in said[0] + said[1]
    assert "tracker stamps jumped ahead of the stream 1 time(s) (by 3.6e+03 s)" in said[0] + said[1]
    err = capsys.readouterr().err
    assert all(text in err for text in said)


def test_sender_clock_set_back_is_named(syn, tmp_path):
    """The sender's clock set back an hour mid-session: the frames and samples after it cannot
    be recorded after the earlier ones (refused, as before), and the session says why instead
    of 'timestamp does not increase' frame after frame: warnings naming the step, report.json
    live source frame_clock_steps_back_s / sample_clock_steps_back_s."""
    back_at = float(syn.timestamps[20])
    sender = Sender(dataset_events(syn, n_frames=30,
                                   stamp=lambda t: t - (3600.0 if t >= back_at else 0.0)))
    assert _live(syn, tmp_path, sender) == 0
    sender.join()
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    source = report["live"]["source"]
    assert report["live"]["frames_recorded"] == 20
    assert source["frame_clock_steps_back_s"] == [pytest.approx(3600.0, abs=0.5)]
    assert source["sample_clock_steps_back_s"] == [pytest.approx(3600.0, abs=0.5)]
    said = " ".join(report["warnings"])
    assert ("the sender's frame stamps stepped 3.6e+03 s back at received frame 20 (3 frames "
            "in a row): its clock was set back?") in said
    assert "the sender's tracker stamps stepped back 1 time(s) (by 3.6e+03 s)" in said
