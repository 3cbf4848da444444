"""Variable-frame-rate video: the frames are timed by the container's own stamps, not by its
nominal rate (a phone or screen recorder's MP4, a Matroska file), and a Matroska file's frame
count, which OpenCV estimates as duration x rate, is not trusted.

The videos are written with PyAV (FFmpeg) at chosen presentation times, which OpenCV's writer
cannot do."""

from __future__ import annotations

import fractions

import numpy as np
import pytest

from fusedmosaic.io import read_dataset
from fusedmosaic.io.calibration import Camera, write_camera_yaml
from fusedmosaic.io.video import FrameSource

av = pytest.importorskip("av")

W, H = 64, 48
# irregular intervals (ms), as a recorder dropping and repeating frames writes them
TIMES_MS = np.cumsum([0, 40, 40, 80, 33, 50, 40, 100, 40, 40, 67, 33])


def _frames(n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(1)
    return [rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8) for _ in range(n)]


def _write_vfr(path, images, times_ms, codec: str) -> None:
    base = fractions.Fraction(1, 1000)
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=1000)
        stream.width, stream.height = W, H
        stream.pix_fmt = "yuv444p" if codec == "ffv1" else "yuv420p"
        stream.codec_context.time_base = base
        for image, t in zip(images, times_ms, strict=True):
            frame = av.VideoFrame.from_ndarray(image, format="bgr24")
            frame.pts, frame.time_base = int(t), base
            container.mux(stream.encode(frame))
        container.mux(stream.encode())


@pytest.fixture
def mkv(tmp_path):
    root = tmp_path / "mkv"
    root.mkdir()
    images = _frames(len(TIMES_MS))
    _write_vfr(root / "video.mkv", images, TIMES_MS, "ffv1")  # lossless (yuv444p)
    write_camera_yaml(root / "camera.yaml", Camera(W, H))
    return root, images


def test_matroska_frames_are_counted_and_timed_by_the_file(mkv):
    root, images = mkv
    with pytest.warns(UserWarning, match=r"video\.mkv: its header counts \d+ frames but 12 "
                                         r"decode \(a count estimated from the duration"):
        frames = FrameSource.open(root)
    assert len(frames) == 12 and frames.counted_by == "decoding"  # was 464 (0.464 s x 1000)
    np.testing.assert_allclose(frames.presentation_times(), TIMES_MS / 1e3, atol=1e-6)
    # random access lands on the right frames (lossless: equal up to the colour conversion)
    for k in (11, 3, 7, 0, 9, 5, 10, 1):
        assert np.abs(frames[k].astype(int) - images[k]).max() <= 3, k


def test_a_variable_rate_video_is_timed_by_its_stamps(mkv):
    root, _ = mkv
    with pytest.warns(UserWarning, match="header counts"):
        ds = read_dataset(root)
    np.testing.assert_allclose(ds.timestamps, TIMES_MS / 1e3, atol=1e-6)
    assert ds.frame_times == ("the frame timestamps of video.mkv (variable frame rate: 33-100 ms "
                              "apart; no frames.csv)")
    with pytest.warns(UserWarning, match="header counts"):  # --fps still decides when given
        given = read_dataset(root, fps=25)
    np.testing.assert_allclose(given.timestamps, np.arange(12) / 25)


def test_mp4_stamps_and_constant_rate(tmp_path):
    """An MP4 (its count is exact) of variable rate is timed by its stamps; so is one of
    constant rate whose header's rate is off (FFmpeg's average over this short clip: 12 frames
    over 0.441 s); an OpenCV-written AVI keeps frame / rate (test_io)."""
    images = _frames(len(TIMES_MS))
    for name, times, expected in (("vfr", TIMES_MS, "the frame timestamps of video.mp4"),
                                  ("cfr", np.arange(12) * 40, "the frame timestamps of "
                                   "video.mp4 (every 40 ms; its header's rate: 27.2109 fps")):
        root = tmp_path / name
        root.mkdir()
        _write_vfr(root / "video.mp4", images, times, "libx264")
        write_camera_yaml(root / "camera.yaml", Camera(W, H))
        ds = read_dataset(root)
        assert len(ds.frames) == 12 and ds.frames.counted_by == "its header"
        np.testing.assert_allclose(ds.timestamps, times / 1e3, atol=1e-6)
        assert ds.frame_times.startswith(expected), ds.frame_times
