"""Review Q (session 48) of the live input path: the CRC64 of OpenIGTLink messages in _core
(crcmod held the GIL, ~15 ms per 1080p colour frame received and up to 0.39 s per 50 Mpixel
mosaic served), PLUS device names longer than the header's 20 bytes (and ``--transform
XToYTransform``), and refused-frame reasons holding the frame's size (a kind per size)."""

from __future__ import annotations

import json
import socket

import numpy as np
import pyigtl
import pytest
from _igtl_sender import T0, Sender, image_message, position_message, tracker_matrix

from fusedmosaic import _core, runner
from fusedmosaic.io.calibration import Camera
from fusedmosaic.io.igtl import (
    MAX_PROBLEM_KINDS,
    OTHER_PROBLEMS,
    IgtlImageServer,
    IgtlSource,
    igtl_image_bytes,
    igtl_image_message,
    mosaic_ijk_to_world,
)
from fusedmosaic.runner import run_igtl

# sockets and a sender on the wall clock: run alone (make test), not beside another worker
pytestmark = pytest.mark.realtime

LONG = "FetoscopeSensorToTracker"  # 24 characters: the header holds the first 20
POSE = tracker_matrix([12.5, -3.25, 150.0], [0.1, 0.2, 0.3, np.sqrt(0.86)])


def _plus_transform(matrix: np.ndarray, t: float, name: str, metadata: bool = True) -> bytes:
    """A TRANSFORM as PLUS packs it (vtkPlusIgtlMessageCommon::PackTransformMessage): header
    version 2, TransformStatus, the name's first 20 characters in the header and the whole
    name in the metadata IGTL_DEVICE_NAME; metadata False: header version 1, the name cut."""
    message = pyigtl.TransformMessage(matrix, timestamp=T0 + t, device_name=name[:20])
    if metadata:
        message.header_version = 2
        message.metadata = {"TransformStatus": "OK", "IGTL_DEVICE_NAME": name}
    return message.pack()


def _samples(events, transform_device: str) -> IgtlSource:
    """The (closed) IgtlSource that read `events` (images of 8x8 and the messages given)."""
    sender = Sender(events, delay=0.1)
    with IgtlSource(f":{sender.port}", transform_device=transform_device) as source:
        while source.next_frame(2.0) is not None:
            pass
    sender.join()
    return source


def _with_images(messages) -> list[tuple[float, bytes]]:
    image = np.zeros((8, 8), np.uint8)
    return [e for k, m in enumerate(messages)
            for e in ((0.04 * k, image_message(image, 0.04 * k)), (0.04 * k, m))]


def _check_poses(source: IgtlSource, expected: np.ndarray, n: int) -> None:
    assert source.valid_samples == n and not source.invalid_samples
    for sample in source.samples:
        np.testing.assert_allclose(sample.matrix, expected, atol=1e-4)


def test_a_long_plus_name_is_matched_by_its_metadata_and_others_named_whole():
    """PLUS sends 'FetoscopeSensorToTracker' as 'FetoscopeSensorToTra' with the whole name in
    IGTL_DEVICE_NAME: no sample was taken (review). Now the metadata name is the device's: it
    matches, and a device sharing the first 20 characters is ignored, listed whole."""
    other = np.eye(4)
    messages = [_plus_transform(POSE, 0.04 * k, LONG) for k in range(5)]
    messages += [_plus_transform(other, 0.2 + 0.04 * k, name) for k, name in
                 enumerate([LONG + "2", "NeedleTipSensorToTracker"])]
    source = _samples(_with_images(messages), LONG)
    _check_poses(source, POSE, 5)
    assert source.ignored_devices == {f"TRANSFORM {LONG}2", "TRANSFORM NeedleTipSensorToTracker"}


@pytest.mark.parametrize("metadata", [True, False])
def test_the_inverse_of_a_long_name_is_matched_with_or_without_metadata(metadata):
    """PLUS streaming TrackerToFetoscopeSensor (sent as 'TrackerToFetoscopeSe'): the inverse
    of the requested name never equalled the cut one, and no workaround existed (review)."""
    inverse = "TrackerToFetoscopeSensor"
    messages = [_plus_transform(np.linalg.inv(POSE), 0.04 * k, inverse, metadata)
                for k in range(5)]
    source = _samples(_with_images(messages), LONG)
    _check_poses(source, POSE, 5)
    assert not source.ignored_devices


def test_a_cut_name_without_metadata_matches_the_name_it_begins():
    """Header version 1 (no metadata): a header name of 20 bytes is the start of a longer
    name; POSITION messages too. One of fewer bytes is matched whole, as before."""
    messages = [_plus_transform(POSE, 0.0, LONG, metadata=False),
                position_message(POSE, 0.04, LONG[:20], size=28),
                position_message(POSE, 0.08, LONG[:19], size=28)]
    source = _samples(_with_images(messages), LONG)
    _check_poses(source, POSE, 2)
    assert source.ignored_devices == {f"POSITION {LONG[:19]}"}


def test_a_long_position_device_is_matched_by_its_metadata():
    messages = [position_message(POSE, 0.04 * k, LONG[:20], metadata={"IGTL_DEVICE_NAME": LONG})
                for k in range(3)]
    source = _samples(_with_images(messages), LONG)
    _check_poses(source, POSE, 3)


def test_transform_given_as_the_mha_field_name():
    """`import --transform SensorToTrackerTransform` takes the .mha field name; `live` with it
    silently matched nothing (review). Now its device is the name without 'Transform', and
    the inverse device answers it too."""
    messages = [_plus_transform(POSE, 0.0, "SensorToTracker"),
                _plus_transform(np.linalg.inv(POSE), 0.04, "TrackerToSensor")]
    source = _samples(_with_images(messages), "SensorToTrackerTransform")
    _check_poses(source, POSE, 2)
    assert not source.ignored_devices


def test_a_device_really_named_with_the_transform_suffix_stays_reachable():
    """Stripping 'Transform' always (as first done) left a device really named so, as Slicer
    names devices after its transform nodes, with no sample (review Z)."""
    messages = [_plus_transform(POSE, 0.04 * k, "NeedleToRefTransform") for k in range(2)]
    source = _samples(_with_images(messages), "NeedleToRefTransform")
    _check_poses(source, POSE, 2)
    assert not source.ignored_devices


# -- MEDIUM 2: the CRC64 in _core, the GIL released ---------------------------------------------


@pytest.fixture()
def crc_calls(monkeypatch):
    """The sizes of the buffers _core.crc64 computes (its result unchanged)."""
    calls = []
    real = _core.crc64

    def spy(data):
        calls.append(memoryview(data).nbytes)
        return real(data)

    monkeypatch.setattr(_core, "crc64", spy)
    return calls


def test_images_are_checked_with_the_core_crc_and_a_corrupted_one_dropped(crc_calls):
    """The IMAGE check was crcmod's C extension (holding the GIL: frames arrived a median
    150-300 ms late at 1080p30), and no check at all without it (frames_crc_checked False).
    Now _core.crc64, always; a corrupted IMAGE is still dropped and counted."""
    images = [np.full((48, 64, 3), 10 * (k + 1), np.uint8) for k in range(3)]
    messages = [image_message(image, 0.04 * k) for k, image in enumerate(images)]
    corrupted = bytearray(messages[1])
    corrupted[-1] ^= 0x01  # a pixel bit flipped in transit, the header's CRC kept
    sender = Sender([(0.0, messages[0]), (0.04, bytes(corrupted)), (0.08, messages[2])],
                    delay=0.1)
    seen = []
    with IgtlSource(f":{sender.port}", transform_device=None) as source:
        assert source.frames_crc_checked
        while (frame := source.next_frame(2.0)) is not None:
            seen.append(int(frame.image[0, 0, 0]))
    sender.join()
    assert 30 in seen and 20 not in seen, seen
    assert source.corrupted_frames == 1 and source.received == 2
    body = len(messages[0]) - 58
    assert crc_calls.count(body) == 3  # every IMAGE body, by _core


def _receive_message(client: socket.socket) -> bytes:
    header = b""
    while len(header) < 58:
        header += client.recv(58 - len(header))
    size = pyigtl.MessageBase.parse_header(header)["body_size"]
    body = bytearray()
    while len(body) < size:
        body += client.recv(size - len(body))
    return header + bytes(body)


def test_served_images_are_pyigtls_bytes_with_the_core_crc(crc_calls):
    """IgtlImageServer.send packed with pyigtl (four copies of a 50 Mpixel mosaic, and
    crcmod's CRC holding the GIL up to 0.39 s; review). Now igtl_image_bytes: the same bytes,
    colour and gray, placed or not, the CRC from _core."""
    rng = np.random.default_rng(0)
    colour = rng.integers(0, 256, (37, 53, 3), np.uint8)
    for image in (colour, colour[:, ::2], colour[:, :, 0]):
        for where in (None, mosaic_ijk_to_world((-12.3, 45.6), 0.37, 0.0123)):
            ours = igtl_image_bytes(image, device_name="Mosaic", timestamp=T0,
                                    ijk_to_world=where)
            theirs = igtl_image_message(image, device_name="Mosaic", timestamp=T0,
                                        ijk_to_world=where).pack()
            assert ours.tobytes() == theirs
    crc_calls.clear()
    with IgtlImageServer("127.0.0.1:0") as server:
        with socket.create_connection(("127.0.0.1", server.port), timeout=5.0) as client:
            while server.num_clients == 0:
                pass
            assert server.send(colour, T0 + 0.25) == 1
            received = _receive_message(client)
    assert crc_calls == [len(received) - 58]
    message = pyigtl.ImageMessage()
    message.unpack(pyigtl.MessageBase.parse_header(received[:58]), received[58:])
    assert message.timestamp == pytest.approx(T0 + 0.25, abs=1e-6)
    np.testing.assert_array_equal(message.image[0], colour[:, :, ::-1])


def test_an_image_of_an_unsupported_type_is_refused_by_name():
    with pytest.raises(ValueError, match=r"an IMAGE message holds a \(rows x columns\[ x "
                                         r"components\]\) array of int8, .*got bool 4x4"):
        igtl_image_bytes(np.zeros((4, 4), bool), device_name="Mosaic", timestamp=T0)


# -- LOW 4: refused frames counted per kind ------------------------------------------------------


def _size_changing_stream() -> Sender:
    """30 frames of 64x48, then 40 whose width grows by 1 px each (a sender cropping)."""
    texture = np.random.default_rng(0).integers(0, 255, (200, 200), np.uint8)
    events = [(0.04 * k, image_message(np.ascontiguousarray(texture[50:98, k:64 + k]),
                                       0.04 * k)) for k in range(30)]
    events += [(0.04 * k, image_message(np.ascontiguousarray(texture[50:98, :64 + k]),
                                        0.04 * k)) for k in range(30, 70)]
    return Sender(events, delay=0.1, speed=4)


def _run(tmp_path, sender) -> tuple[dict, list[str]]:
    said = []
    run_igtl(f":{sender.port}", tmp_path / "out", record=tmp_path / "rec",
             camera=Camera(64, 48), transform_device=None, method="ncc", progress=False,
             warn=said.append, say=lambda text: None, frame_timeout_s=3)
    sender.join()
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    return report["live"]["source"], said


def test_a_stream_changing_size_is_one_refusal_kind(tmp_path):
    """Each new size was a new reason: told on stderr and a key of report.json, one per frame
    of a cropping sender (100 in 100 frames; review). Now one kind, the first size kept."""
    source, said = _run(tmp_path, _size_changing_stream())
    why = "an image of another size than camera.yaml's 64x48 (width x height)"
    assert source["frames_refused"] == {why: 40}
    assert source["frames_refused_first"] == {why: 30}
    assert source["frames_refused_details"] == {why: "a 94x48 image"}
    refusals = [text for text in said if "refused" in text]
    assert refusals == [f"live session: received frame 30 refused, neither processed nor "
                        f"recorded: {why}: a 94x48 image; such frames are counted (report.json "
                        "live frames_refused)"]


def test_refusal_kinds_are_bounded(tmp_path, monkeypatch):
    """Beyond MAX_PROBLEM_KINDS kinds, further ones are counted together (OTHER_PROBLEMS), as
    io.igtl counts its problems, with the first one's reason."""
    real = runner._live_image_problem

    def a_kind_per_width(image, camera, first):
        if image.shape[1] == 64:
            return real(image, camera, first)
        return f"kind {image.shape[1]}", None

    monkeypatch.setattr(runner, "_live_image_problem", a_kind_per_width)
    source, said = _run(tmp_path, _size_changing_stream())
    kinds = source["frames_refused"]
    assert len(kinds) == MAX_PROBLEM_KINDS + 1 and sum(kinds.values()) == 40
    assert kinds[OTHER_PROBLEMS] == 40 - MAX_PROBLEM_KINDS
    first_other = 30 + MAX_PROBLEM_KINDS
    assert source["frames_refused_first"][OTHER_PROBLEMS] == first_other
    assert source["frames_refused_details"] == {OTHER_PROBLEMS: f"kind {64 + first_other}"}
    assert len([text for text in said if "refused" in text]) == MAX_PROBLEM_KINDS + 1
