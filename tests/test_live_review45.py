"""Review 45 (B) of the live OpenIGTLink path: the tracker history as a span of time, big-endian
16-bit IMAGEs, stamps a few seconds ahead, extrapolation of a robot reporting in pairs, a slow
client of IgtlImageServer, a corrupt body size, and bounded problem counts."""

from __future__ import annotations

import json
import select
import socket
import threading
import time

import numpy as np
import pyigtl
import pytest
from _igtl_sender import (
    T0,
    Sender,
    dataset_events,
    image_message,
    position_message,
    tracker_matrix,
    transform_message,
)

from fusedmosaic.cli import main
from fusedmosaic.io import RobotSamples, igtl, read_dataset
from fusedmosaic.io.igtl import (
    STAMP_JUMP,
    STAMP_JUMP_CONFIRM,
    IgtlImageServer,
    IgtlSource,
    StampJumps,
    StreamTimeout,
)
from fusedmosaic.simulation import FetoscopyOptions, PcleOptions, simulate_fetoscopy, simulate_pcle

# sockets and a sender on the wall clock: run alone (make test), not beside another worker
pytestmark = pytest.mark.realtime


def _with_crc(message: bytes) -> bytes:
    """The message with its header's CRC64 computed again over its (edited) body."""
    import crcmod

    crc = crcmod.mkCrcFun(0x142F0E1EBA9EA3693, rev=False, initCrc=0, xorOut=0)(message[58:])
    return message[:50] + crc.to_bytes(8, "big") + message[58:]


def _drain(source: IgtlSource) -> None:
    while source.next_frame(5.0) is not None:  # ends when the sender closes
        pass


def _robot(t: float, x_mm: float, device: str = "RobotToBase") -> bytes:
    M = np.eye(4)
    M[0, 3] = x_mm
    return transform_message(M, t, device)


# -- M1: the history is the last HISTORY_S seconds, not 128 samples ----------------------------


def test_history_keeps_seconds_of_a_1_khz_robot():
    """A robot at 1 kHz: 128 samples were 0.128 s, and a frame arriving 200 ms after its
    capture found every sample of its time dropped (17 of 17 frames without a position;
    review). Now a frame 1.8 s behind the newest sample still gets its position."""
    times = np.arange(2000) * 1e-3
    sender = Sender([(float(t), _robot(float(t), float(t))) for t in times], speed=20.0,
                    delay=0.0)
    with IgtlSource(f":{sender.port}", transform_device="RobotToBase") as source:
        sender.join()
        _drain(source)
        assert source.valid_samples == 2000 and len(source.samples) == 2000
        position, age = source.position_at(T0 + 0.2005, wait_s=0.0)
        np.testing.assert_allclose(position, [0.2005, 0.0, 0.0], atol=1e-6)
        assert age == pytest.approx(0.0005, abs=1e-6)
        assert source.history_misses == 0


def test_a_frame_whose_samples_were_dropped_says_so(monkeypatch):
    """Samples older than HISTORY_S before the newest are dropped; a frame asking for their
    time gets none, counted in history_misses (a frame before the first sample is not)."""
    monkeypatch.setattr(igtl, "HISTORY_S", 0.5)
    times = np.arange(0.0, 2.0, 0.01)
    sender = Sender([(float(t), _robot(float(t), float(t))) for t in times], speed=20.0,
                    delay=0.0)
    with IgtlSource(f":{sender.port}", transform_device="RobotToBase") as source:
        sender.join()
        _drain(source)
        assert source.samples[0].timestamp >= T0 + 1.99 - 0.5 - 1e-6
        assert source.position_at(T0 + 0.205, wait_s=0.0) == (None, None)
        assert source.history_misses == 1
        assert source.position_at(T0 - 1.0, wait_s=0.0) == (None, None)  # before any sample
        assert source.history_misses == 1
    assert source.history_text.startswith("the samples of the last 0.5 s are kept, at most")


@pytest.fixture(scope="module")
def pcle(tmp_path_factory):
    options = PcleOptions(width=96, height=80, n_frames=8, speed_um_per_frame=6.0,
                          radius_um=80.0, contact_loss=False, stick_slip=False)
    return read_dataset(simulate_pcle(tmp_path_factory.mktemp("r45") / "pcle", options))


class _Source:
    """live_session's source without a socket: the frames of `ds`; position_at gives none,
    and for frames from `dropped_from` on because their samples were dropped."""

    transform_device = "RobotToBase"
    history_text = "the samples of the last 15 s are kept, at most 20000: ..."

    def __init__(self, ds, dropped_from: int) -> None:
        self.ds, self.dropped_from = ds, dropped_from
        self.valid_samples, self.invalid_samples, self.ignored_devices = 100, {}, set()
        self.received = self.history_misses = 0

    def next_frame(self, timeout_s: float):
        if self.received == len(self.ds):
            return None
        k = self.received
        self.received += 1
        return igtl.LiveFrame(self.ds.frames[k], float(self.ds.timestamps[k]),
                              time.perf_counter(), k)

    def position_at(self, t, *, max_age_s=None):
        if self.received - 1 >= self.dropped_from:
            self.history_misses += 1
        return None, None


def test_live_session_names_frames_whose_samples_were_dropped(pcle):
    from fusedmosaic.estimation.live import live_session, session_result

    with pytest.warns(UserWarning) as said:
        session = live_session(_Source(pcle, 5), pcle.camera, method="kalman-robot")
    texts = [str(w.message) for w in said]
    dropped = [w for w in texts if "no longer kept" in w]
    assert dropped == ["live session: frame 5 got no robot sample: the samples of its time were "
                       f"no longer kept ({_Source.history_text}); such frames are listed in "
                       "report.json live frames_without_sample_dropped"], texts
    assert session.no_sample == list(range(len(pcle)))
    assert session.no_sample_dropped == list(range(5, len(pcle)))
    result = session_result(session, pcle.timestamps, [], source_details={},
                            method="kalman-robot")
    assert result.details["live"]["frames_without_sample_dropped"] == list(range(5, len(pcle)))
    assert any(f"for {len(pcle) - 5} of them, the samples of their time were no longer kept"
               in w for w in result.details["warnings"]), result.details["warnings"]


# -- M2: a 16-bit IMAGE sent big-endian -------------------------------------------------------


def _big_endian_image(image16: np.ndarray, t: float) -> bytes:
    """An IMAGE of a uint16 image with its pixels big-endian (the header's endian field 1),
    as the OpenIGTLink spec allows."""
    m = bytearray(pyigtl.ImageMessage(image16[None], timestamp=T0 + t,
                                      device_name="Video").pack())
    assert m[58 + 4] == 2  # little-endian, as pyigtl packs it
    m[58 + 4] = 1
    m[58 + 72:] = image16.astype(">u2").tobytes()
    return _with_crc(bytes(m))


def test_a_big_endian_16_bit_image_is_a_native_uint16_frame():
    """pyigtl kept the message's byte order: a '>u2' frame, refused by run_igtl as "a >u2
    image, expected 8- or 16-bit unsigned pixels (uint8, uint16)" (review)."""
    image = (np.arange(48, dtype=np.uint16).reshape(6, 8) * 1000 + 7).astype(np.uint16)
    sender = Sender([(0.0, _big_endian_image(image, 0.0))], delay=0.1)
    with IgtlSource(f":{sender.port}", transform_device=None) as source:
        frame = source.next_frame(5.0)
    sender.join()
    assert frame.image.dtype == np.dtype(np.uint16) and frame.image.dtype.isnative
    np.testing.assert_array_equal(frame.image, image)
    # (and the layout's conversions on one: a colour big-endian image too)
    rgb = np.arange(24, dtype=">u2").reshape(1, 2, 4, 3)
    bgr = igtl._frame_image(rgb, True)
    assert bgr.dtype == np.dtype(np.uint16)
    np.testing.assert_array_equal(bgr, rgb[0, :, :, ::-1].astype(np.uint16))


# -- M3: the lead bound relative to the stream -------------------------------------------------


def _stream(jumps: StampJumps, n: int, interval: float, t0: float = 100.0) -> float:
    for k in range(n):
        assert jumps.check(t0 + interval * k, interval * k) is None
        jumps.accepted(t0 + interval * k, interval * k)
    return interval * (n - 1)


def test_a_stamp_3_s_ahead_of_a_25_fps_stream_is_refused_alone():
    """A fixed 10 s bound let a frame stamped 3 s ahead in, and every frame of the next 3 s
    was refused as not increasing (75 of 100; review). Now the bound is the longer of
    MIN_STAMP_LEAD_S and STAMP_LEAD_SPACINGS intervals of the stream's stamps."""
    jumps = StampJumps()
    assert jumps.lead_bound() == igtl.MIN_STAMP_LEAD_S  # (no interval yet)
    last = _stream(jumps, 20, 0.04)
    assert jumps.lead_bound() == pytest.approx(0.5)  # 10 x 40 ms = 0.4: the 0.5 s floor
    assert jumps.check(100.0 + last + 3.04, last + 0.04) == STAMP_JUMP
    assert jumps.check(100.0 + last + 0.08, last + 0.08) is None  # the stream goes on
    jumps.accepted(100.0 + last + 0.08, last + 0.08)
    # a slower stream's bound is longer (10 Hz: 1 s), at most MAX_STAMP_LEAD_S (0.5 Hz)
    slow = StampJumps()
    last = _stream(slow, 10, 0.1)
    assert slow.lead_bound() == pytest.approx(1.0)
    assert slow.check(100.0 + last + 0.9, last + 0.1) is None  # 0.8 s ahead: within
    very_slow = StampJumps()
    _stream(very_slow, 5, 2.0)
    assert very_slow.lead_bound() == igtl.MAX_STAMP_LEAD_S


def test_a_clock_jumping_3_s_is_taken_after_the_confirming_stamps():
    jumps = StampJumps()
    last = _stream(jumps, 20, 0.04)
    for k in range(1, STAMP_JUMP_CONFIRM + 1):
        t = last + 0.04 * k
        assert jumps.check(100.0 + t + 3.0, t) == (STAMP_JUMP if k < STAMP_JUMP_CONFIRM
                                                    else None)
    assert jumps.jumps == [pytest.approx(3.0)]
    jumps.accepted(100.0 + t + 3.0, t)
    assert jumps.check(100.0 + t + 3.04, t + 0.04) is None  # the stream on its new clock
    assert jumps.lead_bound() == igtl.MIN_STAMP_LEAD_S  # (its intervals start again)


def test_a_sample_3_s_ahead_is_refused_alone():
    """40 Hz samples, one stamped 3 s ahead: it was taken, and every sample of the next 3 s
    refused as 'timestamp not after the previous sample' (frames without pose 74 of 125;
    review)."""
    times = np.arange(60) / 40
    events = [(float(t), _robot(float(t) + (3.0 if k == 20 else 0.0), float(t)))
              for k, t in enumerate(times)]
    sender = Sender(events, speed=4.0, delay=0.0)
    with IgtlSource(f":{sender.port}", transform_device="RobotToBase") as source:
        sender.join()
        _drain(source)
    assert source.invalid_samples == {STAMP_JUMP: 1}
    assert source.valid_samples == 59


@pytest.fixture(scope="module")
def syn(tmp_path_factory):
    options = FetoscopyOptions(n_frames=30, laps=30 / 37.5, width=200, height=200)
    return read_dataset(simulate_fetoscopy(tmp_path_factory.mktemp("r45") / "syn", options))


def test_live_refuses_a_frame_stamped_3_s_ahead_alone(syn, tmp_path):
    """`fusedmosaic live` (run_igtl's frame StampJumps): frame 10 stamped 3 s ahead is refused
    alone, the others recorded (25 of 100 were, the rest refused as not increasing)."""
    events = dataset_events(syn, n_frames=30)
    images = [i for i, (_, m) in enumerate(events) if m[2:7] == b"IMAGE"]
    i = images[10]
    t = events[i][0]
    events[i] = (t, image_message(syn.frames[10], t + 3.0))
    sender = Sender(events)
    assert main(["--quiet", "live", f"127.0.0.1:{sender.port}", "--camera",
                 str(syn.root / "camera.yaml"), "--hand-eye", str(syn.root / "hand_eye.txt"),
                 "--transform", "SensorToTracker", "--record", str(tmp_path / "rec"), "--out",
                 str(tmp_path / "out"), "--no-report"]) == 0
    sender.join()
    live = json.loads((tmp_path / "out" / "report.json").read_text())["live"]
    assert live["source"]["frames_refused"] == {STAMP_JUMP: 1}
    assert live["frames_recorded"] == 29


# -- M4: extrapolation over a baseline of a typical spacing -----------------------------------


def _pairs(n: int) -> np.ndarray:
    """Times of a robot reporting in pairs, 1 ms then 19 ms apart (50 Hz)."""
    return np.sort(np.r_[np.arange(n) * 0.02, np.arange(n) * 0.02 + 0.001])


def test_replay_extrapolates_pairs_over_a_spacing():
    """estimation.live.extrapolated_robot: along samples i-1 and i, 1 ms apart, a 1 µm error
    of the newest became 20 µm 19 ms later; now the base is the newest sample at least half a
    typical spacing (19 ms) before: under 2 µm. Evenly spaced samples: as before."""
    from fusedmosaic.estimation.live import extrapolated_robot

    times = _pairs(10)
    v = 400.0  # µm/s
    xy = np.stack([v * times, np.zeros_like(times)], axis=1)
    xy[-1, 0] += 1.0  # the newest sample 1 µm off
    robot = RobotSamples(times, xy)
    t = times[-1] + 0.019
    error = abs(extrapolated_robot(robot, len(times) - 1, t, 0.057)[0] - v * t)
    assert error < 2.0, error
    assert igtl.extrapolation_base(times, len(times) - 1, 0.019) == len(times) - 3
    assert igtl.extrapolation_base(times, 1, 0.019) is None  # none 9.5 ms before: held
    np.testing.assert_allclose(extrapolated_robot(robot, 1, times[1] + 0.01, 0.057), xy[1])


def test_live_position_of_pairs_extrapolates_over_a_spacing():
    """IgtlSource.position_at as the replay: the same base."""
    times = _pairs(15)
    v = 0.4  # mm/s
    x = v * times
    x[-1] += 1e-3  # the newest sample 1 µm off
    events = [(float(t), _robot(float(t), float(p))) for t, p in zip(times, x, strict=True)]
    sender = Sender(events, speed=10.0, delay=0.0)
    with IgtlSource(f":{sender.port}", transform_device="RobotToBase") as source:
        sender.join()
        _drain(source)
        t = times[-1] + 0.019
        position, age = source.position_at(T0 + t, wait_s=0.0)
    assert age == pytest.approx(0.019, abs=1e-6)
    assert abs(position[0] - v * t) < 2e-3, position[0] - v * t  # (before: 20 µm off)


# -- M5: IgtlImageServer and a slow client -----------------------------------------------------


def _client(port: int) -> socket.socket:
    client = socket.socket()
    client.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 64 * 1024)  # a slow link's window
    client.connect(("127.0.0.1", port))
    return client


def _read(client: socket.socket, size: int, chunk: int, pause_s: float) -> int:
    got = 0
    client.settimeout(5.0)
    while got < size:
        data = client.recv(min(chunk, size - got))
        if not data:
            break
        got += len(data)
        time.sleep(pause_s)
    return got


def _wait_clients(server: IgtlImageServer, n: int) -> None:
    deadline = time.monotonic() + 5.0
    while server.num_clients < n and time.monotonic() < deadline:
        time.sleep(0.01)
    assert server.num_clients == n


def test_a_slow_client_gets_a_large_image_in_full():
    """send_timeout_s covered the whole sendall: a client taking a 27 MB mosaic at 4 MB/s was
    dropped mid-message (review). Now only a client taking no byte for send_timeout_s is."""
    image = np.zeros((2000, 2000, 3), np.uint8)  # 12 MB: 3x the socket's buffer (4 MB)
    size = len(igtl.igtl_image_message(image, device_name="Mosaic", timestamp=T0).pack())
    with IgtlImageServer("0", send_timeout_s=0.4) as server, _client(server.port) as client:
        _wait_clients(server, 1)
        got = []
        reader = threading.Thread(target=lambda: got.append(_read(client, size, 1 << 16, 0.01)))
        reader.start()  # ~6 MB/s, 64 KB every 10 ms: ~2 s for 12 MB, in steps of 10 ms
        assert server.send(image, T0) == 1
        reader.join(10.0)
        assert got == [size] and server.num_clients == 1


def test_a_client_connects_while_a_send_waits_on_another():
    """The server held its lock for the whole send: a client connecting meanwhile waited,
    and so did num_clients. Now it is accepted during the send, and gets the next message
    (not the rest of the one under way)."""
    image = np.zeros((2000, 2000, 3), np.uint8)  # 12 MB: more than the socket buffers
    size = len(igtl.igtl_image_message(image, device_name="Mosaic", timestamp=T0).pack())
    with IgtlImageServer("0", send_timeout_s=3.0) as server, _client(server.port) as slow:
        _wait_clients(server, 1)
        sent = []
        sender = threading.Thread(target=lambda: sent.append(server.send(image, T0)))
        sender.start()
        assert select.select([slow], [], [], 5.0)[0]  # the send is under way
        time.sleep(0.1)  # (and fills slow's window, then waits)
        assert sender.is_alive()
        with _client(server.port) as late:
            _wait_clients(server, 2)  # (before: blocked until the send ended)
            assert sender.is_alive()
            assert _read(slow, size, 1 << 20, 0.0) == size
            sender.join(5.0)
            assert sent == [1]
            late.setblocking(False)
            with pytest.raises(BlockingIOError):  # nothing of the message under way
                late.recv(1)
            got = []
            readers = [threading.Thread(target=lambda c=c: got.append(
                _read(c, size, 1 << 20, 0.0))) for c in (slow, late)]
            for reader in readers:
                reader.start()
            assert server.send(image, T0) == 2
            for reader in readers:
                reader.join(5.0)
            assert got == [size, size]


# -- L1: a corrupt size on a small message; a message partly received --------------------------


def test_a_transform_declaring_200_mb_is_a_malformed_header():
    """A TRANSFORM whose header declares 200 MB swallowed the IMAGEs after it, and the session
    ended with 'no frame ... in 5 s' (review)."""
    frame = np.zeros((8, 8), np.uint8)
    corrupt = transform_message(np.eye(4), 0.02)
    corrupt = corrupt[:42] + (200 * 2**20).to_bytes(8, "big") + corrupt[50:]
    events = [(0.0, image_message(frame, 0.0)), (0.02, corrupt)]
    events += [(0.04 * k, image_message(frame, 0.04 * k)) for k in range(1, 10)]
    sender = Sender(events, delay=0.1)
    with IgtlSource(f":{sender.port}", transform_device="SensorToTracker") as source:
        assert source.next_frame(5.0).timestamp == T0
        with pytest.raises(ValueError, match=r"malformed OpenIGTLink header: a TRANSFORM message "
                                             r"of 209715200 bytes \(more than 65536 bytes for "
                                             r"its type\): a corrupt size field"):
            source.next_frame(5.0)
    sender.join()


def test_the_timeout_says_a_message_is_partly_received():
    message = image_message(np.zeros((100, 100), np.uint8), 0.0)
    half = len(message) // 2
    sender = Sender([(0.0, message[:half]), (3.0, message[half:])], delay=0.0)
    with IgtlSource(f":{sender.port}", transform_device=None) as source:
        with pytest.raises(StreamTimeout) as raised:
            source.next_frame(1.0)
        assert source.next_frame(5.0) is not None  # (the rest arrives: the frame)
    sender.join()
    text = str(raised.value)
    assert text.startswith(f"OpenIGTLink 127.0.0.1:{sender.port}: no frame from any IMAGE "
                           f"device in 1 s (inside a IMAGE message of 'Video': "), text
    assert text.endswith(f" of {(len(message) - 58) / 1e3:.3g} KB received; a sender stalled "
                         "mid-message, or a corrupt size in its header?)"), text


# -- L2: invalid samples by kind, bounded; ignored devices bounded -----------------------------


def test_invalid_samples_are_counted_by_kind_with_the_first_figures():
    """POSITIONs with quaternion norms 1.01, 1.011, ...: one key per sample (500 for 500;
    review). Now one kind, the first norm kept as its detail."""
    pose = tracker_matrix([1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0])
    events = []
    for k in range(20):
        raw = bytearray(position_message(pose, 0.01 * k))
        raw[-4:] = np.array([1.01 + 0.001 * k], ">f4").tobytes()  # w: not a unit quaternion
        events.append((0.01 * k, _with_crc(bytes(raw))))
    sender = Sender(events, speed=10.0, delay=0.0)
    with IgtlSource(f":{sender.port}", transform_device="SensorToTracker") as source:
        sender.join()
        _drain(source)
    assert source.invalid_samples == {igtl.QUATERNION_NOT_UNIT: 20}
    assert source.invalid_sample_details == {igtl.QUATERNION_NOT_UNIT: "norm 1.01"}
    matrix, problem = igtl.position_message_matrix(bytes(raw[-28:]))
    assert problem == igtl.QUATERNION_NOT_UNIT


def test_problem_kinds_and_ignored_devices_are_bounded():
    """A sender's status texts and device names are the sender's: one entry each grew
    without bound. At most MAX_PROBLEM_KINDS, the rest counted together."""
    n = igtl.MAX_PROBLEM_KINDS + 8
    events = []
    for k in range(n):
        status = pyigtl.TransformMessage(np.eye(4), timestamp=T0 + 0.01 * k,
                                         device_name="SensorToTracker")
        status.header_version, status.metadata = 2, {"TransformStatus": f"LOST{k}"}
        events.append((0.01 * k, status.pack()))
        events.append((0.01 * k, transform_message(np.eye(4), 0.01 * k, f"Tool{k}ToTracker")))
    sender = Sender(events, speed=10.0, delay=0.0)
    with IgtlSource(f":{sender.port}", transform_device="SensorToTracker") as source:
        sender.join()
        _drain(source)
    invalid = source.invalid_samples
    assert len(invalid) == igtl.MAX_PROBLEM_KINDS + 1 and invalid[igtl.OTHER_PROBLEMS] == 8
    assert sum(invalid.values()) == n and invalid["status LOST0"] == 1
    assert len(source.ignored_devices) == igtl.MAX_PROBLEM_KINDS + 1
    assert igtl.MORE_DEVICES in source.ignored_devices
    assert "TRANSFORM Tool0ToTracker" in source.ignored_devices


def test_a_robot_position_stands_with_a_bad_quaternion():
    """A POSITION whose quaternion is not of unit norm voided its position too; for a source
    that needs no orientation (a robot: kalman-robot, robot) the position is now taken."""
    pose = tracker_matrix([1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0])
    raw = bytearray(position_message(pose, 0.0))
    raw[-4:] = np.array([1.2], ">f4").tobytes()  # w: not a unit quaternion
    events = [(0.0, _with_crc(bytes(raw)))]
    for required, valid in ((True, 0), (False, 1)):
        sender = Sender(events, speed=10.0, delay=0.0)
        with IgtlSource(f":{sender.port}", transform_device="SensorToTracker",
                        orientation_required=required) as source:
            sender.join()
            _drain(source)
        assert source.valid_samples == valid
        if valid:
            assert source.invalid_samples == {}
            np.testing.assert_allclose(source.samples[0].matrix[:3, 3], [1.0, 2.0, 3.0])
        else:
            assert source.invalid_samples == {igtl.QUATERNION_NOT_UNIT: 1}
