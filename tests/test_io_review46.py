"""Review 46, reading real inputs: a video's frames are the frames they are named (every seek's
landing checked by its stamp: MPEG transport and program streams, an AVI left by a killed
recorder); a frame lost inside a video leaves the others their stamps' times; hand_eye.txt
written with 4 decimals is read, and a refused one's message shows the figure compared; a long
tracking.csv of numbers is not held in memory as text.

The frames carry their number as 7 black / white blocks, which lossy codecs keep, so each
image read tells which frame it is."""

from __future__ import annotations

import fractions
import inspect
import re
import struct
import subprocess
import sys
import textwrap
import tracemalloc
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusedmosaic.io._table import read_number_table, read_table
from fusedmosaic.io.dataset import read_frame_times
from fusedmosaic.io.tracking import TRACKING_COLUMNS, read_hand_eye
from fusedmosaic.io.video import FrameSource

av = pytest.importorskip("av")

W, H = 64, 48
BITS = 7  # frame numbers 0-127


def _image(i: int, noise: np.ndarray | None = None) -> np.ndarray:
    """Frame i: its number's bits as blocks (white 1, black 0) across a grey gradient, or
    across ``noise`` (H, W, 3)."""
    image = np.empty((H, W, 3), np.uint8)
    image[:] = np.linspace(60, 190, W, dtype=np.uint8)[None, :, None] if noise is None else noise
    for b in range(BITS):
        image[14:34, 1 + 9 * b:8 + 9 * b] = 255 if (i >> b) & 1 else 0
    return image


def _number(image: np.ndarray) -> int:
    """The frame number an image shows (the centres of its blocks)."""
    grey = image if image.ndim == 2 else image.mean(axis=2)
    return sum(1 << b for b in range(BITS) if grey[20:28, 3 + 9 * b:6 + 9 * b].mean() > 128)


def _write(path: Path, n: int, codec: str, **options: str) -> None:
    """n frames at 25 fps with PyAV (FFmpeg picks the container from the suffix)."""
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=25)
        stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
        stream.options = options
        for i in range(n):
            container.mux(stream.encode(av.VideoFrame.from_ndarray(_image(i), format="bgr24")))
        container.mux(stream.encode())


def _wrong_frames(frames: FrameSource, order) -> list[tuple[int, int]]:
    """(asked, shown) for each frame of ``order`` that shows another."""
    return [(k, shown) for k in order if (shown := _number(frames[k])) != k]


def _orders(n: int) -> list[int]:
    """Frames read from a fresh source: the first ones, all in order, then random ones and
    backwards (seeks of every kind)."""
    rng = np.random.default_rng(0)
    return [0, 1, 2, *range(n), *map(int, rng.integers(0, n, 30)), *range(n - 1, -1, -7), 0]


def test_a_transport_stream_reads_every_frame_as_itself(tmp_path):
    """OpenCV reports the frame a seek asked for, not the one it reached: in an MPEG-TS every
    seek into the first GOP (frame 0 too, made by the first read after the end was probed)
    lands on the frame after the second keyframe, so frame i showed frame i + 30 throughout
    (e_M 354 px for 0.22, exit 0). Frame 0 is reached by opening the file again, every seek's
    landing is checked by its stamp, and a seek that misses leaves the frames before the one it
    reached to decoding from the start. The MP4 of the same encode keeps seeking."""
    n = 60
    for name in ("ts", "mp4"):
        root = tmp_path / name
        root.mkdir()
        _write(root / f"video.{name}", n, "libx264", bf="3", g="30")
        frames = FrameSource.open(root)
        assert len(frames) == n and frames.counted_by == "its header"
        assert _wrong_frames(frames, _orders(n)) == [], name
    assert frames._missed_landings == 0 and frames._seek_floor == 0  # (the MP4)


def test_a_program_stream_reads_every_frame_as_itself(tmp_path):
    """An MPEG-2 .mpg (older endoscopy recorders): its seeks landed elsewhere (15 of 20 random
    reads showed another frame); its last frame is stamped 0 (that stamp set aside, the
    others check the landings): after the second seek that lands elsewhere it is read by
    decoding forward."""
    _write(tmp_path / "video.mpg", 60, "mpeg2video", bf="2", g="15")
    frames = FrameSource.open(tmp_path)  # (its header: 59, an estimate)
    assert len(frames) == 60 and frames.counted_by == "decoding"
    assert _wrong_frames(frames, _orders(60)) == []  # (11 read as others)
    assert frames._seek_floor == 60


def test_one_stamp_out_of_order_does_not_stop_the_seeks(tmp_path):
    """An MPEG-4 AVI with B-frames stamps its last frame 0: that one stamp made every stamp
    unusable and stopped all seeking (20 random reads of 1500 frames: 0.95 s, where seeking
    took 0.04 s; review 46). It is set aside; the other frames are sought, their landings
    checked, and every frame is read as itself."""
    _write(tmp_path / "video.avi", 60, "mpeg4", bf="2", g="25")
    frames = FrameSource.open(tmp_path)
    assert len(frames) == 60 and frames._decoded_times()[-1] == 0.0  # (out of order)
    assert _wrong_frames(frames, _orders(60)) == []
    assert frames._seek_floor == 0 and frames._missed_landings == 0


def test_an_avi_left_by_a_killed_recorder_reads_every_frame_as_itself(tmp_path):
    """An MJPG AVI whose recorder was killed before release(): no frame count, no index; its
    frames are counted by decoding, and its seeks land elsewhere (12 of 20 random reads showed
    another frame, and two runs on it read different images): such landings are caught, and
    after the second, every frame is reached by decoding from the start."""
    # (OpenCV's AVI writer writes 256 kB at a time: noisy frames, 4 kB each, fill that)
    script = textwrap.dedent(f"""
        import os
        import cv2
        import numpy as np
        W, H, BITS = {W}, {H}, {BITS}
        """) + inspect.getsource(_image) + textwrap.dedent(f"""
        writer = cv2.VideoWriter({str(tmp_path / "video.avi")!r},
                                 cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (W, H))
        rng = np.random.default_rng(0)
        for i in range(120):
            writer.write(_image(i, rng.integers(0, 256, (H, W, 3), dtype=np.uint8)))
        os._exit(0)  # killed: neither the index nor the header's count is written
        """)
    subprocess.run([sys.executable, "-c", script], check=True, timeout=60)
    assert cv2.VideoCapture(str(tmp_path / "video.avi")).get(cv2.CAP_PROP_FRAME_COUNT) == 0
    with warnings.catch_warnings():  # (the kill may cut a frame's chunk: it is left out)
        warnings.filterwarnings("ignore", r".*video\.avi: the file ends inside frame \d+'s "
                                r"chunk", UserWarning)
        frames = FrameSource.open(tmp_path)
    n = len(frames)
    assert 30 <= n < 120 and frames.counted_by == "decoding"
    assert _wrong_frames(frames, [k for k in _orders(n) if k < n]) == []
    assert frames._missed_landings >= 1  # (caught; where they land varies)


def _write_mkv_with_a_loss(path: Path) -> None:
    """30 MJPEG frames at 25 fps in Matroska, frames 15-23 lost and frame 14 damaged (its
    packet zeroed: it does not decode), as a file damaged in the middle decodes."""
    base = fractions.Fraction(1, 25)
    with av.open(str(path), "w") as container:
        stream = container.add_stream("mjpeg", rate=25)
        stream.width, stream.height, stream.pix_fmt = W, H, "yuvj420p"
        for i in range(30):
            frame = av.VideoFrame.from_ndarray(_image(i), format="bgr24")
            frame.pts, frame.time_base = i, base
            for packet in stream.encode(frame):
                if 15 <= i < 24:
                    continue
                if i == 14:
                    damaged = av.Packet(bytes(packet.size))
                    damaged.pts, damaged.dts = packet.pts, packet.dts
                    damaged.time_base, damaged.stream = packet.time_base, packet.stream
                    packet = damaged
                container.mux(packet)
        container.mux(stream.encode())


def test_frames_after_a_loss_inside_a_matroska_file_keep_their_stamps(tmp_path):
    """One frame that does not decode (no stamp) made all the stamps unusable: the frames after
    the loss were timed at frame / rate, frame 15 (showing frame 24, 0.96 s) at 0.60 s with
    frame 15's tracker sample, 15 mm away. The frames that decode keep their stamps; the
    warning names the loss in the middle (it blamed the duration estimate or a truncation)."""
    _write_mkv_with_a_loss(tmp_path / "video.mkv")
    with pytest.warns(UserWarning, match=re.escape(
            "its header counts 30 frames but 21 decode (a count estimated from the duration, as "
            "Matroska's and MPEG streams' are, a truncated file, or frames lost in the middle: "
            "its stamps jump from 520 ms (frame 13) to 960 ms (frame 15), frames lost there; "
            "timed by its stamps")):
        frames = FrameSource.open(tmp_path, blank_unreadable=True)
    ids, times, how = read_frame_times(tmp_path, frames)
    assert how.startswith("the frame timestamps of video.mkv")
    shown = [_number(frames[k]) for k in range(21)]
    assert list(frames.unreadable) == [14]
    assert shown[:14] == list(range(14)) and shown[15:] == list(range(24, 30))
    np.testing.assert_allclose(times[15:], np.arange(24, 30) / 25, atol=1e-6)
    np.testing.assert_allclose(times[:14], np.arange(14) / 25, atol=1e-6)
    assert times[13] < times[14] < times[15]  # the unreadable frame: between its neighbours


def test_an_undecodable_frame_does_not_make_the_stamps_unusable(tmp_path):
    """The same in a file of constant rate: one frame that does not decode warned that the
    stamps were not usable (they are: the others are read and timed right)."""
    path = tmp_path / "video.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, (W, H))
    for i in range(12):
        writer.write(_image(i))
    writer.release()
    data = bytearray(path.read_bytes())  # frame 6's JPEG data zeroed ('00dc' chunks)
    at = data.find(b"movi") + 4
    for _ in range(7):
        at = data.find(b"00dc", at)
        size = struct.unpack_from("<I", data, at + 4)[0]
        start, at = at + 8, at + 8 + size
    data[start:at] = bytes(size)
    path.write_bytes(bytes(data))
    frames = FrameSource.open(tmp_path, blank_unreadable=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ids, times, how = read_frame_times(tmp_path, frames)
    assert how.startswith("frame / 25 fps")
    np.testing.assert_allclose(frames.presentation_times(), np.arange(12) / 25, atol=1e-9)
    assert [_number(frames[k]) for k in range(12)] == [*range(6), 0, *range(7, 12)]
    assert list(frames.unreadable) == [6]  # (read blank)


def test_hand_eye_with_4_decimals_is_read(tmp_path):
    """A rotation printed with 4 decimals (MATLAB's format short, np.round(T, 4)) has squared
    column norms up to ~1.2e-4 off: refused about 1 time in 5 as "scaled" at 1e-4, with norms
    shown within it (1, 1.00006, 1.00003). The tolerance is PLUS's and the quaternions' (1e-3),
    and a refusal shows the figure compared, beyond the tolerance it names."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [20, -35, 10], degrees=True).as_matrix()
    T[:3, 3] = [1.5, -2.0, 12.0]
    path = tmp_path / "hand_eye.txt"
    np.savetxt(path, T, fmt="%.4f")
    read = read_hand_eye(path)
    np.testing.assert_allclose(read, T, atol=1e-4)
    np.testing.assert_allclose(read[:3, :3].T @ read[:3, :3], np.eye(3), atol=1e-12)

    T[:3, :3] *= 1.0006  # squares 1.0012
    np.savetxt(path, T)
    with pytest.raises(ValueError, match=r"hand_eye\.txt: not a rigid transform: the rotation "
                                         r"block's columns have norms 1\.0006, 1\.0006, 1\.0006, "
                                         r"not 1 \(scaled\): their squares up to 0\.0012 from 1 "
                                         r"\(tolerance 0\.001\)"):
        read_hand_eye(path)


def test_a_long_tracking_csv_is_not_held_as_text(tmp_path):
    """A file of numbers was read whole, then parsed from an io.StringIO (4 bytes a character):
    peak memory 5.5x the file (500 000 rows, 74 MB: 546 MB). It is parsed as it is read; the
    columns are the same."""
    n = 20_000
    rng = np.random.default_rng(0)
    values = np.column_stack([np.arange(n) * 0.025, rng.normal(0, 50, (n, 7)), np.ones(n)])
    path = tmp_path / "tracking.csv"
    np.savetxt(path, values, delimiter=",", fmt="%.17g", comments="",
               header=",".join([*TRACKING_COLUMNS, "valid"]))
    size = path.stat().st_size
    tracemalloc.start()
    try:
        table, rows = read_number_table(path, TRACKING_COLUMNS, ["valid"])
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 3 * size, (peak, size)  # (the columns alone: 1x)
    expected, expected_rows = read_table(path, TRACKING_COLUMNS, ["valid"])
    np.testing.assert_array_equal(rows, expected_rows)
    for name, column in expected.items():
        np.testing.assert_array_equal(table[name], column)
