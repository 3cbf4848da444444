"""Bad and awkward dataset input (audit 4): every problem is a ValueError naming the file, the
key or row/column and the problem; video frame sources are safe to read from several threads."""

from __future__ import annotations

import json
import re
import struct
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pytest

from fusedmosaic.io import (
    Camera,
    FrameSource,
    TrackingSamples,
    read_camera_yaml,
    read_dataset,
    read_hand_eye,
    read_robot_csv,
    read_tracking_csv,
    write_camera_yaml,
    write_dataset,
)
from fusedmosaic.io.tracking import write_tracking_csv
from fusedmosaic.io.video import (
    VIDEO_READ_AHEAD,
    VIDEO_RECENT_FRAMES,
    natural_key,
    sort_frame_names,
)

W, H = 32, 24
K_DATA = "[40.5, 0., 15.5, 0., 41.25, 11.5, 0., 0., 1.]"
TRACKING_HEADER = "timestamp,tx,ty,tz,qx,qy,qz,qw,valid\n"


def _write_video(path: Path, n: int, seed: int = 0) -> list[np.ndarray]:
    """MJPG video of n noise frames; returns the frames as decoded sequentially."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, (W, H))
    assert writer.isOpened()
    rng = np.random.default_rng(seed)
    for _ in range(n):
        writer.write(rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8))
    writer.release()
    capture = cv2.VideoCapture(str(path))
    decoded = [capture.read()[1] for _ in range(n)]
    capture.release()
    return decoded


def _camera_yaml(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "camera.yaml"
    path.write_text(f"%YAML:1.0\nimage_width: {W}\nimage_height: {H}\n{body}")
    return path


def _opencv_matrix(key: str, rows: int, cols: int, data: str, dt: str = "d") -> str:
    return f"{key}: !!opencv-matrix\n  rows: {rows}\n  cols: {cols}\n  dt: {dt}\n  data: {data}\n"


# ------------------------------------------------------------------------------ video


def test_video_frames_read_from_threads_match_sequential_reading(tmp_path):
    expected = _write_video(tmp_path / "video.avi", 24)
    frames = FrameSource.open(tmp_path, expected_size=(W, H))
    rng = np.random.default_rng(1)
    # In order (as feature extraction asks: two threads slightly out of order), then random.
    order = list(range(24)) * 2 + list(rng.permutation(24))
    with ThreadPoolExecutor(4) as pool:
        images = list(pool.map(frames.__getitem__, order))
    for k, image in zip(order, images, strict=True):
        np.testing.assert_array_equal(image, expected[k], err_msg=f"frame {k}")
    assert len(frames._recent) <= VIDEO_RECENT_FRAMES
    frames.close()


class _SeekCounter:
    """Wraps a cv2.VideoCapture and records its seeks."""

    def __init__(self, capture: cv2.VideoCapture) -> None:
        self.capture, self.seeks = capture, []

    def set(self, prop: int, value: float) -> bool:
        self.seeks.append(int(value))
        return self.capture.set(prop, value)

    def __getattr__(self, name: str):
        return getattr(self.capture, name)


def test_video_read_slightly_out_of_order_without_seeking(tmp_path):
    expected = _write_video(tmp_path / "video.avi", VIDEO_READ_AHEAD + 3)
    frames = FrameSource.open(tmp_path)
    frames[0]
    frames._capture = counter = _SeekCounter(frames._capture)
    for k in [2, 1, 3, 5, 4, 6]:  # skipped frames are kept, not decoded again after a seek
        np.testing.assert_array_equal(frames[k], expected[k])
    assert counter.seeks == []
    # backwards to frame 0: the file opened again, no seek (a seek to 0 landed on the next
    # keyframe in MPEG transport streams; review 46)
    np.testing.assert_array_equal(frames[0], expected[0])
    assert counter.seeks == [] and frames._capture is not counter
    frames._capture = counter = _SeekCounter(frames._capture)
    far = VIDEO_READ_AHEAD + 2
    np.testing.assert_array_equal(frames[far], expected[far])  # far ahead: one seek
    assert counter.seeks == [far]
    frames.close()


def _corrupt_avi_frames(path: Path, frames) -> None:
    """Zero the JPEG data of the given frames of an MJPG AVI (their '00dc' chunks in the movi
    list): those frames fail to decode, the others still do."""
    data = bytearray(path.read_bytes())
    at, k = data.find(b"movi") + 4, 0
    while (at := data.find(b"00dc", at)) >= 0 and k <= max(frames):
        size = struct.unpack_from("<I", data, at + 4)[0]
        if k in frames:
            data[at + 8:at + 8 + size] = bytes(size)
        at, k = at + 8 + size, k + 1
    path.write_bytes(bytes(data))


def test_undecodable_frame_is_named_and_the_others_read_right(tmp_path):
    """A frame in the middle that does not decode: OpenCV's seeks beyond it silently land on
    the frame after it (frame 9 asked, frame 7 given); the frames are counted by decoding and
    reached by decoding forward past it, and only it fails, named, from threads too."""
    root = tmp_path / "ds"
    root.mkdir()
    expected = _write_video(root / "video.avi", 12)
    _corrupt_avi_frames(root / "video.avi", {6})
    frames = FrameSource.open(root)
    assert len(frames) == 12 and frames.counted_by == "decoding"  # a seek to 11 lands on 7
    with (
        ThreadPoolExecutor(2) as pool,
        pytest.raises(ValueError, match=r"video\.avi frame 6: cannot read image \(video trunc"),
    ):
        list(pool.map(frames.__getitem__, range(12)))
    for k in (11, 2, 9, 0, 7, 5, 10, 8):  # backwards, far ahead, read ahead past frame 6
        np.testing.assert_array_equal(frames[k], expected[k])
    with pytest.raises(ValueError, match=r"video\.avi frame 6: cannot read image"):
        frames[6]
    np.testing.assert_array_equal(frames[7], expected[7])
    frames.close()
    # no stamp for frame 6 (unreadable): the others keep theirs, it is timed between them
    np.testing.assert_allclose(frames.presentation_times(), np.arange(12) / 25, atol=1e-9)


def test_a_run_of_undecodable_frames_is_not_the_end(tmp_path):
    root = tmp_path / "ds"
    root.mkdir()
    expected = _write_video(root / "video.avi", 12)
    _corrupt_avi_frames(root / "video.avi", {5, 6, 7})
    frames = FrameSource.open(root)
    assert len(frames) == 12
    for k in (11, 8, 0, 4, 9):
        np.testing.assert_array_equal(frames[k], expected[k])
    for k in (7, 5, 6):
        with pytest.raises(ValueError, match=rf"video\.avi frame {k}: cannot read image"):
            frames[k]
    frames.close()


def test_unreadable_frames_read_blank_when_asked(tmp_path):
    """blank_unreadable: an undecodable video frame or a damaged PNG is an all-zero image of the
    dataset's size and channels, recorded with the error it would have raised; the default
    still raises; frames of another size still raise (not damage)."""
    video = tmp_path / "video"
    video.mkdir()
    expected = _write_video(video / "video.avi", 12)
    _corrupt_avi_frames(video / "video.avi", {6})
    frames = FrameSource.open(video, expected_size=(W, H), blank_unreadable=True)
    with ThreadPoolExecutor(2) as pool:
        images = list(pool.map(frames.__getitem__, range(12)))
    for k, image in enumerate(images):
        if k == 6:
            assert image.shape == (H, W, 3) and image.dtype == np.uint8 and not image.any()
        else:
            np.testing.assert_array_equal(image, expected[k])
    assert list(frames.unreadable) == [6]
    assert frames.unreadable[6].endswith(
        "video.avi frame 6: cannot read image (video truncated or corrupt?)")
    frames.close()

    pngs = tmp_path / "pngs" / "frames"
    pngs.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for k in range(4):  # grey frames
        cv2.imwrite(str(pngs / f"{k:06d}.png"), rng.integers(1, 256, (H, W), dtype=np.uint8))
    (pngs / "000000.png").write_bytes(b"not a png")  # the first: its shape comes from another
    frames = FrameSource.open(pngs.parent, expected_size=(W, H), blank_unreadable=True)
    assert frames[0].shape == (H, W) and not frames[0].any()
    assert frames.unreadable == {0: f"{pngs / '000000.png'}: cannot read image"}
    assert frames[1].any() and frames.unreadable.keys() == {0}
    with pytest.raises(ValueError, match=r"000000\.png: cannot read image"):
        FrameSource.open(pngs.parent)[0]
    cv2.imwrite(str(pngs / "000002.png"), np.zeros((H, W - 4), np.uint8))
    with pytest.raises(ValueError, match=r"000002\.png: image is 28x24 but camera\.yaml says"):
        frames[2]

    for k in range(4):
        (pngs / f"{k:06d}.png").write_bytes(b"")
    frames = FrameSource.open(pngs.parent, blank_unreadable=True)
    with pytest.raises(ValueError, match=r"frames: none of its 4 frames can be read \(e\.g\. "
                                         r".*000000\.png: cannot read image\)"):
        frames[3]


def test_truncated_video_is_read_as_far_as_it_decodes(tmp_path):
    """A header counting frames the file no longer holds (cut short) used to fail when the
    first missing frame was read; the frames are counted by decoding, with a warning."""
    expected = _write_video(tmp_path / "full.avi", 12)
    data = (tmp_path / "full.avi").read_bytes()
    root = tmp_path / "ds"
    root.mkdir()
    (root / "video.avi").write_bytes(data[: len(data) * 6 // 10])
    with pytest.warns(UserWarning, match=r"video\.avi: its header counts 12 frames but \d+ "
                                         r"decode \(a truncated file, or .*\): the \d+ "
                                         r"(whole ones )?are read"):
        frames = FrameSource.open(root)
    assert 0 < len(frames) < 12 and frames.counted_by == "decoding"
    n = len(frames)  # (a last frame cut inside its chunk, decoded in part, is left out)
    for k in (n - 1, 0, n // 2, *range(n)):
        np.testing.assert_array_equal(frames[k], expected[k])


def _damage(path: Path, n: int, at: float, frames: int) -> None:
    """Zero about ``frames`` frames' worth of bytes of an n-frame video, from fraction ``at``
    of the file on (bytes lost in the middle)."""
    data = bytearray(path.read_bytes())
    start, size = int(len(data) * at), len(data) // n * frames
    data[start : start + size] = bytes(size)
    path.write_bytes(bytes(data))


def test_video_damaged_in_the_middle_is_refused(tmp_path):
    """Two frames' bytes zeroed 30 % into an AVI whose header count is confirmed at its end:
    the decoder passed the damaged frames without a failed grab, so every later frame was read
    as the one 2 after it (its number, time and tracker sample another frame's; 60 kB in a
    60-frame SYN AVI: e_M 155 px instead of 0.26, 'placed 60/60', review). Refused now, naming
    the file and both counts."""
    root = tmp_path / "ds"
    root.mkdir()
    _write_video(root / "video.avi", 30)
    _damage(root / "video.avi", 30, 0.3, 2)
    with pytest.raises(ValueError, match=r"video\.avi: its header counts 30 frames and its last "
                                         r"frame is there, but decoding it from the start gives "
                                         r"(2[0-9]): \d+ frames? (is|are) damaged and passed "
                                         r"without an error by the decoder, so every frame after "
                                         r"would be read under another frame's number"):
        FrameSource.open(root)


def test_video_cut_or_damaged_warned_as_either(tmp_path):
    """Damage nearer the end: the header's last frame no longer decodes either, so the frames
    are counted by decoding. An AVI whose index is whole at its end shows the loss inside and
    is refused (review 51: frames 7-11 were read as frames 4-8, with a warning only); one cut
    short, its index gone with its end, is warned of as either."""
    root = tmp_path / "ds"
    root.mkdir()
    _write_video(root / "video.avi", 12)
    whole = (root / "video.avi").read_bytes()
    _damage(root / "video.avi", 12, 0.5, 2)
    with pytest.raises(ValueError, match=r"video\.avi: its header counts 12 frames but decoding "
                                         r"it gives \d+, and the file is whole at its end: its "
                                         r"index \(idx1\) lists 12 frames"):
        FrameSource.open(root)
    (root / "video.avi").write_bytes(whole[: len(whole) * 3 // 4])  # cut short
    with pytest.warns(UserWarning, match=r"video\.avi: its header counts 12 frames but \d+ decode "
                                         r"\(a truncated file, or frames damaged in the middle, "
                                         r"which the decoder passes without a word: every frame "
                                         r"after them is then read under an earlier frame's "
                                         r"number"):
        FrameSource.open(root)


@pytest.mark.parametrize("content, message", [
    (b"", r"video\.mp4: cannot open video \(an empty file\)"),
    (b"not a video at all" * 100, r"video\.mp4: cannot open video \(not a video this OpenCV's "
                                  r"FFmpeg reads, or a recording that stopped before it was "
                                  r"finished: an MP4 / MOV without its index"),
], ids=["empty", "not a video"])
def test_video_that_cannot_be_opened_says_what_it_may_be(tmp_path, content, message):
    """'cannot open video' alone, for an empty file and for a recording stopped before its MP4
    index was written alike (review)."""
    root = tmp_path / "ds"
    root.mkdir()
    (root / "video.mp4").write_bytes(content)
    with pytest.raises(ValueError, match=message):
        FrameSource.open(root)


# ------------------------------------------------------------------------------ frames


def test_unpadded_frame_names_are_read_in_numeric_order(tmp_path):
    n = 12
    images = [np.full((H, W), 10 * k, np.uint8) for k in range(n)]
    root = write_dataset(
        tmp_path / "ds",
        camera=Camera(W, H),
        frames=iter(images),
        timestamps=None,
    )
    for k in range(n):  # frame_0.png ... frame_11.png
        (root / "frames" / f"{k:06d}.png").rename(root / "frames" / f"frame_{k}.png")
    (root / "frames" / "._frame_3.png").write_bytes(b"macOS metadata")  # hidden: not a frame
    ds = read_dataset(root)
    assert [p.name for p in ds.frames.paths] == [f"frame_{k}.png" for k in range(n)]
    assert [int(image[0, 0]) for image in ds.frames] == [10 * k for k in range(n)]


@pytest.mark.parametrize("fps", [float("inf"), float("nan"), 0.0])
def test_fps_must_be_finite_without_frames_csv(tmp_path, fps):
    root = write_dataset(
        tmp_path / "ds", camera=Camera(W, H), frames=[np.zeros((H, W), np.uint8)], timestamps=None
    )
    with pytest.raises(ValueError, match=r"fps must be positive and finite, got"):
        read_dataset(root, fps=fps)


def test_natural_order_equals_name_order_for_padded_names():
    names = [f"img{k:05d}_{j:03d}.png" for k in (0, 3, 10, 99, 100) for j in (0, 7, 12)]
    shuffled = list(np.random.default_rng(2).permutation(names))
    assert sorted(shuffled, key=natural_key) == sorted(shuffled)
    assert sort_frame_names(shuffled) == sorted(shuffled)
    # Padded decimal timestamps: name order, natural order and decimal order agree.
    stamps = [f"{1637000000 + k * 0.04:.3f}.png" for k in (0, 1, 2, 24, 25, 26, 250)]
    shuffled = list(np.random.default_rng(3).permutation(stamps))
    assert sort_frame_names(shuffled) == sorted(shuffled) == stamps
    assert sorted(["f10.png", "f9.png", "f010.png", "g1.png"], key=natural_key) == [
        "f9.png",
        "f010.png",
        "f10.png",
        "g1.png",
    ]


def test_natural_key_compares_any_two_names():
    # A name that is a prefix of another at a digit run used to compare int with str.
    assert sorted(["x.png1.png", "x.png"], key=natural_key) == ["x.png", "x.png1.png"]
    assert sorted(["a1b", "a1", "a", "a0b2", "1"], key=natural_key) == [
        "1",
        "a",
        "a0b2",
        "a1",
        "a1b",
    ]
    assert sort_frame_names(["x.png1.png", "x.png"]) == ["x.png", "x.png1.png"]


@pytest.mark.parametrize(
    ("names", "example"),
    [
        (  # str(float) timestamps: .5 < .25 < .125 as whole numbers
            ["1637000000.5.png", "1637000000.25.png", "1637000000.125.png", "1637000001.0.png"],
            r"'1637000000\.5\.png' and '1637000000\.125\.png'",
        ),
        (["t_0.1.png", "t_0.08.png", "t_0.040.png"], r"'t_0\.1\.png' and 't_0\.040\.png'"),
        (["v1.9.png", "v1.10.png"], r"'v1\.9\.png' and 'v1\.10\.png'"),  # or versions?
        (["f1.png", "f1.5.png", "f1.25.png"], r"'f1\.5\.png' and 'f1\.25\.png'"),
    ],
)
def test_ambiguous_decimal_frame_names_are_refused(tmp_path, names, example):
    frames_dir = tmp_path / "ds" / "frames"
    frames_dir.mkdir(parents=True)
    for name in names:
        cv2.imwrite(str(frames_dir / name), np.zeros((H, W), np.uint8))
    with pytest.raises(
        ValueError,
        match=r"ds/frames: frame names order differently when their numbers are read as decimals "
        rf"or as whole numbers \(e\.g\. {example}\); rename the frames with zero-padded frame "
        r"numbers",
    ):
        FrameSource.open(tmp_path / "ds")


def test_unambiguous_decimal_frame_names_keep_natural_order():
    # Decimals with the same digits in every name (a date), or fractions of equal length: the
    # whole-number and decimal readings agree, so the natural order stands.
    dated = [f"2023.11.21_frame_{k}.png" for k in (0, 1, 2, 10, 11)]
    assert sort_frame_names(reversed(dated)) == dated
    halves = ["t_1.5.png", "t_2.5.png", "t_10.5.png"]  # plain name order: 1.5, 10.5, 2.5
    assert sort_frame_names(reversed(halves)) == halves
    assert sort_frame_names(["f1.5.png", "f1.png", "f2.png"]) == ["f1.png", "f1.5.png", "f2.png"]


def test_grey_and_colour_frames_mixed(tmp_path):
    grey = np.zeros((H, W), np.uint8)
    root = write_dataset(
        tmp_path / "ds",
        camera=Camera(W, H),
        frames=[grey, grey, np.zeros((H, W, 3), np.uint8), grey],
        timestamps=None,
    )
    ds = read_dataset(root)  # frames are not all read up front
    ds.frames[1]
    with pytest.raises(
        ValueError,
        match=r"frames/000002\.png: 3 channel\(s\) \(BGR colour\) but .*frames/000000\.png has "
        r"1 channel\(s\) \(grey\); frames must be all grey or all colour",
    ):
        list(ds.frames)


# ------------------------------------------------------------------------------ camera.yaml


@pytest.mark.parametrize(
    ("body", "match"),
    [
        (
            _opencv_matrix("camera_matrix", 3, 3, "[480., 0., 199.5, 0., 480.]"),
            r"camera_matrix: matrix data has 5 values but rows x cols = 3 x 3",
        ),
        (
            _opencv_matrix("camera_matrix", 3, 3, "[a, 0, 1, 0, 1, 1, 0, 0, 1]"),
            r"camera_matrix: element 1 is not a number \('a'\)",
        ),
        (
            "camera_matrix: [40.5, 0, 15.5, 0, x, 11.5, 0, 0, 1]\n",
            r"camera_matrix: element 5 is not a number \('x'\)",
        ),
        (
            "camera_matrix: [40.5, 0, 15.5, 0, 41]\n",
            r"camera_matrix: expected a 3x3 matrix, got 1x5",
        ),
        ("camera_matrix: [1, 0, 0, 0, 1, 0, 0, 0, .inf]\n", r"camera_matrix: contains NaN or inf"),
        (
            "camera_matrix: {rows: 3, cols: 3}\n",
            r"camera_matrix: a matrix map needs rows, cols and data: \[\.\.\.\] \(!!opencv-matrix",
        ),
        (
            "distortion_coefficients: [0.1, 0.2, 0.3]\n",
            r"distortion_coefficients: 3 values; OpenCV takes 4, 5, 8, 12 or 14",
        ),
        (
            _opencv_matrix("distortion_coefficients", 1, 6, "[0, 0, 0, 0, 0.1, 0]"),
            r"distortion_coefficients: 6 values; OpenCV takes",
        ),
        ("distortion_coefficients: [0, .nan, 0, 0]\n", r"distortion_coefficients: contains NaN"),
        ("fov_mask_radius: 0.5\n", r"fov_mask_radius 0.5 px leaves the field-of-view mask empty"),
    ],
)
def test_bad_camera_yaml(tmp_path, body, match):
    path = _camera_yaml(tmp_path, body)
    with pytest.raises(ValueError, match=r"camera\.yaml: " + match):
        read_camera_yaml(path)


@pytest.mark.parametrize(
    ("data", "match"),
    [
        ("[480, 0, 199.5, 0, 480, 199.5, 0, 0, 0]", r"last row must be 0 0 1 .*got 0 0 0;"),
        ("[480, 0, 199.5, 0, 480, 199.5, 0, 0, -1]", r"last row must be 0 0 1 .*got 0 0 -1;"),
        ("[480, 0, 199.5, 0, 480, 199.5, 1e-5, 0, 1]", r"last row must be 0 0 1 .*got 1e-05 0 1;"),
        (  # transposed, also when scaled
            "[480, 0, 0, 0, 480, 0, 199.5, 199.5, 1]",
            r"last row must be 0 0 1 .*got 199\.5 199\.5 1 \(the matrix looks transposed\);",
        ),
        (
            "[960, 0, 0, 0, 960, 0, 399, 399, 2]",
            r"last row must be 0 0 1 .*got 399 399 2 \(the matrix looks transposed\);",
        ),
        (
            "[480, 0, 15, 0.0012345678, 480, 11, 0, 0, 1]",
            r"element \(1, 0\) must be 0 .*got 0\.0012345678;",
        ),
        ("[-480, 0, 15, 0, 480, 11, 0, 0, 1]", r"focal lengths must be positive, got fx=-480.0"),
        (
            "[1e12, 0, 15, 0, 1e12, 11, 0, 0, 1]",
            r"focal length fx=1e\+12, fy=1e\+12 px is over 320000 px",
        ),
        ("[1e-4, 0, 200, 0, 1e-4, 200, 0, 0, 1]",
         r"focal length fx=0\.0001, fy=0\.0001 px is under 0\.873 px.* A focal length in mm\?"),
        ("[480, 0, 1e9, 0, 480, 1e9, 0, 0, 1]", r"numerically singular \(fx=480"),
    ],
)
def test_camera_matrix_checked_when_a_pose_method_needs_it(tmp_path, data, match):
    # A placeholder K is fine for methods without K (pairwise, ncc, robot, kalman-robot): the
    # file loads, and the layout/bound/singularity checks run when a pose method asks for K.
    camera = read_camera_yaml(_camera_yaml(tmp_path, f"camera_matrix: {data}\n"))
    np.testing.assert_array_equal(camera.camera_matrix.ravel(), json.loads(data))
    with pytest.raises(
        ValueError,
        match=r"camera\.yaml: camera_matrix: " + match + r".* method 'ba-emt' needs the camera",
    ):
        camera.require_camera_matrix("ba-emt")


def test_placeholder_camera_matrix_loads_for_methods_without_k(tmp_path):
    camera = Camera(W, H, camera_matrix=np.zeros((3, 3)), pixel_size_um=1.0)
    root = write_dataset(
        tmp_path / "ds", camera=camera, frames=[np.zeros((H, W), np.uint8)] * 2, timestamps=None
    )
    ds = read_dataset(root)  # as for ncc / robot / kalman-robot
    assert ds.camera.camera_matrix.tolist() == np.zeros((3, 3)).tolist()
    assert ds.require_pixel_size("ncc") == 1.0
    with pytest.raises(
        ValueError, match=r"camera\.yaml: camera_matrix: last row must be .* method 'ba' needs"
    ):
        ds.require_camera_matrix("ba")


def test_camera_matrix_scaled_or_float32_is_normalised():
    K = np.array([[480.1, 0.5, 199.7], [0.0, 480.3, 199.3], [0.0, 0.0, 1.0]])
    for given in (2.0 * K, K.astype(np.float32), K / np.float32(1.0000001)):
        camera = Camera(400, 400, camera_matrix=given)
        np.testing.assert_allclose(camera.require_camera_matrix("ba"), K, rtol=1e-6)
        assert camera.camera_matrix[2].tolist() == [0.0, 0.0, 1.0]
        assert camera.camera_matrix[1, 0] == 0.0
    # float32 arithmetic: K[2, 2] = 0.99999994 (refused by the old absolute 1e-9 check)
    K32 = (K.astype(np.float32) * np.float32(3.0)) / np.float32(3.0)
    K32[2, 2] = np.float32(0.99999994)
    assert Camera(400, 400, camera_matrix=K32).require_camera_matrix("ba")[2, 2] == 1.0


def test_good_camera_yaml_variants(tmp_path):
    path = _camera_yaml(
        tmp_path,
        _opencv_matrix("camera_matrix", 3, 3, K_DATA)
        + _opencv_matrix("distortion_coefficients", 8, 1, "[0.1, 0, 0, 0, 0, 0, 0, 0]")
        + "fov_mask_radius: 0.71\n",  # reaches the 4 pixel centres 0.707 px from the centre
    )
    camera = read_camera_yaml(path)
    assert camera.camera_matrix[2].tolist() == [0, 0, 1] and camera.distortion.shape == (8,)
    assert np.count_nonzero(camera.fov_mask()) == 4
    # The numbers as written; the storage type dt is not used (OpenCV refused dt: q).
    for dt in ("f", "q"):
        path = _camera_yaml(tmp_path, _opencv_matrix("camera_matrix", 3, 3, K_DATA, dt=dt))
        K = read_camera_yaml(path).require_camera_matrix("ba")
        assert K.tolist() == [[40.5, 0, 15.5], [0, 41.25, 11.5], [0, 0, 1]]
    path = _camera_yaml(tmp_path, "camera_matrix: [81, 0, 31, 0, 82.5, 23, 0, 0, 2]\n")
    assert read_camera_yaml(path).camera_matrix[:2].tolist() == [[40.5, 0, 15.5], [0, 41.25, 11.5]]


@pytest.mark.parametrize(
    "body",
    [
        "distortion_coefficients: []\n",
        _opencv_matrix("distortion_coefficients", 0, 0, "[]"),
        "distortion_coefficients: [0, 0, 0]\n",  # any length: zeros are no distortion
        _opencv_matrix("distortion_coefficients", 1, 5, "[0., 0., 0., 0., 0.]"),
        "distortion_coefficients: {rows: 1, cols: 0, data: []}\n",  # ROS D: []
    ],
)
def test_empty_or_zero_distortion_means_none(tmp_path, body):
    camera = read_camera_yaml(_camera_yaml(tmp_path, body))
    assert camera.distortion is None
    assert Camera(W, H, distortion=[]).distortion is None
    assert Camera(W, H, distortion=np.zeros(8)).distortion is None


ROS_CAMERA_INFO = """\
image_width: 640
image_height: 480
camera_name: fetoscope
camera_matrix:
  rows: 3
  cols: 3
  data: [512.3417, 0, 321.2047, 0, 513.0261, 238.8652, 0, 0, 1]
distortion_model: {model}
distortion_coefficients:
  rows: 1
  cols: {n}
  data: [{d}]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [508.1169, 0, 322.0891, 0, 0, 510.3952, 239.5573, 0, 0, 0, 1, 0]
"""
ROS_D = "-0.3412, 0.1265, 0.000413, -0.000788, 0"


@pytest.mark.parametrize("header", ["", "%YAML:1.0\n---\n"])
def test_ros_camera_info_yaml(tmp_path, header):
    # As written by ROS camera_calibration_parsers: untagged {rows, cols, data} maps, no dt.
    path = tmp_path / "camera.yaml"
    path.write_text(header + ROS_CAMERA_INFO.format(model="plumb_bob", n=5, d=ROS_D))
    camera = read_camera_yaml(path)
    assert camera.size == (640, 480)
    assert camera.require_camera_matrix("ba").tolist() == [
        [512.3417, 0, 321.2047],
        [0, 513.0261, 238.8652],
        [0, 0, 1],
    ]
    assert camera.distortion.tolist() == [-0.3412, 0.1265, 0.000413, -0.000788, 0]
    d8 = ROS_D + ", 0.01, 0, 0"
    path.write_text(ROS_CAMERA_INFO.format(model="rational_polynomial", n=8, d=d8))
    assert read_camera_yaml(path).distortion.shape == (8,)
    path.write_text(ROS_CAMERA_INFO.format(model="plumb_bob", n=0, d=""))  # ROS D: []
    assert read_camera_yaml(path).distortion is None


@pytest.mark.parametrize(("model", "shown"), [("fov", "'fov'"), ("3", "not a string")])
def test_unknown_distortion_model_refused(tmp_path, model, shown):
    path = tmp_path / "camera.yaml"
    path.write_text(ROS_CAMERA_INFO.format(model=model, n=4, d="0.1, 0.01, 0.001, 0.0001"))
    with pytest.raises(
        ValueError,
        match=rf"camera\.yaml: distortion_model: {shown} is not supported; expected one of "
        r"plumb_bob, rational_polynomial, equidistant, fisheye",
    ):
        read_camera_yaml(path)


def test_fisheye_camera_yaml(tmp_path):
    """ROS camera_info's equidistant model and OpenCV's calibration sample's fisheye_model: 1
    are OpenCV's fisheye model (4 coefficients, all-zero ones kept: the equidistant lens is not
    a pinhole); written back as distortion_model: equidistant."""
    path = tmp_path / "camera.yaml"
    path.write_text(ROS_CAMERA_INFO.format(model="equidistant", n=4, d="0.1, 0.01, 0.001, 0"))
    camera = read_camera_yaml(path)
    assert camera.lens_model == "fisheye"
    assert camera.distortion.tolist() == [0.1, 0.01, 0.001, 0]
    write_camera_yaml(tmp_path / "back.yaml", camera)
    assert "distortion_model: equidistant" in (tmp_path / "back.yaml").read_text()
    back = read_camera_yaml(tmp_path / "back.yaml")
    assert back.lens_model == "fisheye" and back.distortion.tolist() == [0.1, 0.01, 0.001, 0]
    path.write_text(ROS_CAMERA_INFO.format(model="equidistant", n=4, d="0, 0, 0, 0"))
    assert read_camera_yaml(path).distortion.tolist() == [0, 0, 0, 0]
    opencv = ROS_CAMERA_INFO.format(model="plumb_bob", n=4, d="0.1, 0.01, 0.001, 0")
    opencv = opencv.replace("distortion_model: plumb_bob\n", "fisheye_model: 1\n")
    path.write_text(opencv)
    assert read_camera_yaml(path).lens_model == "fisheye"
    path.write_text(opencv.replace("fisheye_model: 1", "fisheye_model: 0"))
    assert read_camera_yaml(path).lens_model == "pinhole"


@pytest.mark.parametrize(("model", "n", "d", "message"), [
    ("equidistant", 5, "0.1, 0.01, 0.001, 0, 0",
     r"distortion_coefficients: the fisheye \(equidistant\) model takes 4 finite values k1 k2 "
     r"k3 k4, got 0.1 0.01 0.001 0 0"),
    ("equidistant\nfisheye_model: 0", 4, "0.1, 0, 0, 0",
     r"fisheye_model 0 contradicts distortion_model 'equidistant'"),
    ("plumb_bob\nfisheye_model: 2", 4, "0.1, 0, 0, 0", r"fisheye_model: expected 0 or 1, got 2"),
])
def test_bad_fisheye_camera_yaml_named(tmp_path, model, n, d, message):
    path = tmp_path / "camera.yaml"
    path.write_text(ROS_CAMERA_INFO.format(model=model, n=n, d=d))
    with pytest.raises(ValueError, match=r"camera\.yaml: " + message):
        read_camera_yaml(path)


def test_empty_camera_yaml(tmp_path):
    path = tmp_path / "camera.yaml"
    path.write_text("")
    with pytest.raises(ValueError, match=r"camera\.yaml: empty file, expected OpenCV FileStorage"):
        read_camera_yaml(path)
    path.write_text("%YAML:1.0\n---\n")
    with pytest.raises(ValueError, match=r"camera\.yaml: cannot parse .* with image_width"):
        read_camera_yaml(path)


def test_camera_api_size_messages():
    with pytest.raises(ValueError, match=r"image_width: expected a number, got '400'"):
        Camera("400", 400)
    with pytest.raises(ValueError, match=r"image_height must be an integer, got 24.5"):
        Camera(W, 24.5)
    with pytest.raises(ValueError, match=r"cam\.yaml: camera_matrix: expected a 3x3 matrix of"):
        Camera(W, H, camera_matrix=[["a", 0, 0], [0, 1, 0], [0, 0, 1]], source="cam.yaml")


# ------------------------------------------------------------------- tracking, robot, hand-eye


@pytest.mark.parametrize(
    ("row", "match"),
    [
        (
            "0.1,1e300,0,0,0,0,0,1,1",
            r"row 3, column 'tx': beyond the 1e\+06 mm bound \(1 km\), not physical \(1e\+300\)",
        ),
        ("0.1,0,-2e6,0,0,0,0,1,1", r"row 3, column 'ty': beyond the 1e\+06 mm bound"),
        ("0.1,0,0,inf,0,0,0,1,1", r"row 3, column 'tz': infinite value in a valid row \(inf\)"),
        ("0.1,0,0,0,0,-inf,0,1,1", r"row 3, column 'qy': infinite value"),
    ],
)
def test_tracking_csv_non_physical_values(tmp_path, row, match):
    path = tmp_path / "tracking.csv"
    path.write_text(TRACKING_HEADER + f"0,0,0,0,0,0,0,1,1\n{row}\n0.2,0,0,0,0,0,0,1,1\n")
    with pytest.raises(ValueError, match=r"tracking\.csv: " + match):
        read_tracking_csv(path)
    path.write_text(TRACKING_HEADER + "0,0,0,0,0,0,0,1,1\n" + row[:-1] + "0\n")  # valid=0
    assert read_tracking_csv(path).valid.tolist() == [True, False]


def test_robot_csv_non_physical_values(tmp_path):
    path = tmp_path / "robot.csv"
    path.write_text("timestamp,x,y\n0,0,0\n0.1,1e9,0\n")  # 1 km: still accepted
    assert read_robot_csv(path).xy_um[1, 0] == 1e9
    path.write_text("timestamp,x,y\n0,0,0\n0.1,0,-1e300\n")
    with pytest.raises(ValueError, match=r"robot\.csv: row 3, column 'y': beyond the 1e\+09 µm"):
        read_robot_csv(path)
    path.write_text("timestamp,x,y\n0,inf,0\n")
    with pytest.raises(ValueError, match=r"robot\.csv: row 2, column 'x': infinite value \(inf"):
        read_robot_csv(path)


def test_hand_eye_empty_or_far(tmp_path):
    path = tmp_path / "hand_eye.txt"
    path.write_text("\n")
    with pytest.raises(ValueError, match=r"hand_eye\.txt: empty file, expected a 4x4 matrix"):
        read_hand_eye(path)  # and no numpy UserWarning (warnings are errors in the tests)
    T = np.eye(4)
    T[0, 3] = 1e7
    np.savetxt(path, T)
    with pytest.raises(ValueError, match=r"hand_eye\.txt: translation .* beyond the 1e\+06 mm"):
        read_hand_eye(path)


def test_tracking_samples_zero_quaternion():
    q = [[0, 0, 0, 1], [0, 0, 0, 0]]
    with pytest.raises(ValueError, match=r"quaternions: sample 1 is valid but .* has norm 0"):
        TrackingSamples([0.0, 1.0], np.zeros((2, 3)), q)
    TrackingSamples([0.0, 1.0], np.zeros((2, 3)), q, valid=[True, False])  # missing sample


def test_tracking_samples_refuse_what_tracking_csv_refuses(tmp_path):
    """A non-unit quaternion (here w, x, y, z read as x, y, z, w and scaled) is refused by the
    Python API as by read_tracking_csv; within the tolerance it is renormalised, and what is
    written reads back."""
    q = np.array([[0.0, 0.0, 0.0, 1.0], [2.0, 0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match=r"quaternions: sample 1 is valid but .* has norm 2, "
                                         r"not 1 \(tolerance 0\.001\)"):
        TrackingSamples([0.0, 1.0], np.zeros((2, 3)), q)
    q[1] = [0.0, 0.0, 0.0, 1.0005]
    samples = TrackingSamples([0.0, 1.0], np.zeros((2, 3)), q)
    np.testing.assert_allclose(np.linalg.norm(samples.quaternions, axis=1), 1.0, atol=1e-15)
    assert q[1, 3] == 1.0005  # the caller's array is not changed
    write_tracking_csv(tmp_path / "tracking.csv", samples)
    np.testing.assert_allclose(read_tracking_csv(tmp_path / "tracking.csv").quaternions,
                               samples.quaternions, atol=1e-9)


def test_samples_in_milliseconds_against_frames_in_seconds_are_refused():
    """A tracker (or robot) stamped in ms against frames in s: every frame would fall between
    two samples 25 s apart and be interpolated from them; refused, naming the rates."""
    from fusedmosaic.io.tracking import (
        RobotSamples,
        TrackingSamples,
        interpolate_camera_poses,
        interpolate_robot,
    )

    frames = np.arange(60) / 25.0
    t_s = np.arange(0.0, 2.5, 0.025)  # 40 Hz over the frames' span
    q = np.tile([0.0, 0.0, 0.0, 1.0], (t_s.size, 1))
    tracker_s = TrackingSamples(t_s, np.zeros((t_s.size, 3)), q)
    assert interpolate_camera_poses(tracker_s, frames)[1].all()
    with pytest.raises(ValueError, match=r"tracking\.csv: tracker samples every 25 s \(median\) "
                                         r"while frames come every 0\.04 s: are the tracker's "
                                         r"timestamps in another unit \(ms\?\)"):
        interpolate_camera_poses(TrackingSamples(t_s * 1000, tracker_s.translations, q), frames)
    robot = RobotSamples(t_s * 1000, np.zeros((t_s.size, 2)))
    with pytest.raises(ValueError, match=r"robot\.csv: robot samples every 25 s"):
        interpolate_robot(robot, frames)
    # a single frame time (a live pose lookup) or sample is not judged
    assert interpolate_robot(robot, frames[:1])[1].all()


def test_upper_case_png_frames_are_frames_and_two_sources_are_refused(tmp_path):
    """frames/*.PNG (a Windows export) were "no frames", mixed with .png silently dropped;
    a frames/ folder beside a video.* silently hid the video."""
    images = [np.full((H, W), 10 * k, np.uint8) for k in range(4)]
    root = write_dataset(tmp_path / "ds", camera=Camera(W, H), frames=iter(images),
                         timestamps=None)
    for k in (1, 3):
        (root / "frames" / f"{k:06d}.png").rename(root / "frames" / f"{k:06d}.PNG")
    ds = read_dataset(root)
    assert [int(image[0, 0]) for image in ds.frames] == [0, 10, 20, 30]
    _write_video(root / "video.avi", 4)
    with pytest.raises(ValueError, match=r"ds: both frames/ and video\.avi; a dataset holds its "
                                         r"frames one way"):
        read_dataset(root)


def _patch_avi_frame_count(path: Path, n: int) -> None:
    """Rewrite the AVI header's frame counts (avih.dwTotalFrames, strh.dwLength) to n."""
    data = bytearray(path.read_bytes())
    struct.pack_into("<I", data, data.find(b"avih") + 8 + 16, n)
    struct.pack_into("<I", data, data.find(b"strh") + 8 + 32, n)
    path.write_bytes(bytes(data))


def test_video_header_counting_too_few_frames_is_not_trusted(tmp_path):
    """A header saying 7 of 12 frames (a recorder that crashed before updating it) silently cut
    the last 5; frames decoding past the count are counted by decoding. A header counting too
    many (its last frame does not decode) is not trusted either; frames.csv disagreeing with
    the count says how the video's frames were counted (not frames.csv blamed alone)."""
    root = tmp_path / "ds"
    root.mkdir()
    expected = _write_video(root / "video.avi", 12)
    _patch_avi_frame_count(root / "video.avi", 7)
    assert cv2.VideoCapture(str(root / "video.avi")).get(cv2.CAP_PROP_FRAME_COUNT) == 7
    frames = FrameSource.open(root)
    assert len(frames) == 12
    # OpenCV's seeks stop at the header's last frame (6): frames past it are decoded forward
    for k in (11, 3, 9, 0, 8, 10, 7, 6):
        np.testing.assert_array_equal(frames[k], expected[k])
    for image, truth in zip(frames, expected, strict=True):
        np.testing.assert_array_equal(image, truth)
    _patch_avi_frame_count(root / "video.avi", 15)
    write_camera_yaml(root / "camera.yaml", Camera(W, H))
    (root / "frames.csv").write_text("frame,timestamp\n" + "".join(
        f"{k},{k / 25}\n" for k in range(12)))
    with pytest.warns(UserWarning, match=r"header counts 15 frames but 12 decode"):
        ds = read_dataset(root)
    assert len(ds.frames) == 12
    (root / "frames.csv").write_text("frame,timestamp\n" + "".join(
        f"{k},{k / 25}\n" for k in range(11)))
    with pytest.warns(UserWarning, match=r"header counts 15"), \
            pytest.raises(ValueError, match=r"frames\.csv: 11 rows but the dataset has 12 frames "
                                            r"in video\.avi \(as decoding counts them\)"):
        read_dataset(root)
    _patch_avi_frame_count(root / "video.avi", 12)
    with pytest.raises(ValueError, match=r"frames\.csv: 11 rows but the dataset has 12 frames "
                                         r"in video\.avi \(as its header counts them\)"):
        read_dataset(root)


@pytest.mark.parametrize("defect, message", [
    ("shear", "columns are not orthogonal"), ("scale", r"have norms 2, 2, 2, not 1 \(scaled\)"),
    ("reflection", "a reflection"), ("last row", "the last row is 1 2 3 4, not 0 0 0 1")])
def test_interpolate_camera_poses_checks_the_hand_eye(defect, message):
    """A sheared hand-eye was projected onto a rotation silently (poses 0.26 rad off), a
    reflection failed inside SciPy (review): refused as camera_pose_from_sample refuses it."""
    from fusedmosaic.io.tracking import TrackingSamples, interpolate_camera_poses

    X = np.eye(4)
    if defect == "shear":
        X[0, 1] = 0.5
    elif defect == "scale":
        X[:3, :3] *= 2
    elif defect == "reflection":
        X[2, 2] = -1
    else:
        X[3] = [1, 2, 3, 4]
    samples = TrackingSamples(np.arange(5) * 0.025, np.zeros((5, 3)),
                              np.tile([0.0, 0.0, 0.0, 1.0], (5, 1)))
    with pytest.raises(ValueError, match=rf"hand-eye \(sensor_from_camera\): not a rigid "
                                         rf"transform: .*{message}"):
        interpolate_camera_poses(samples, [0.03, 0.05], X)


def test_non_finite_samples_refused():
    """A NaN robot sample was interpolated into frames marked valid, and written to a robot.csv
    the reader refuses; a NaN tracker timestamp failed in SciPy (review)."""
    from fusedmosaic.io.tracking import RobotSamples, TrackingSamples

    with pytest.raises(ValueError, match=r"RobotSamples\.xy_um: sample 1 is not finite "
                                         r"\(\[nan nan\]\); leave a missing sample out"):
        RobotSamples([0.0, 0.1, 0.2], [[0, 0], [np.nan, np.nan], [2, 2]])
    with pytest.raises(ValueError, match=r"RobotSamples\.timestamps: sample 2 is not finite"):
        RobotSamples([0.0, 0.1, np.inf], np.zeros((3, 2)))
    q = np.tile([0.0, 0.0, 0.0, 1.0], (3, 1))
    with pytest.raises(ValueError, match=r"TrackingSamples\.timestamps: sample 1 is valid but "
                                         r"its timestamp is nan"):
        TrackingSamples([0.0, np.nan, 0.2], np.zeros((3, 3)), q)
    TrackingSamples([0.0, np.nan, 0.2], np.zeros((3, 3)), q, [True, False, True])  # missing


@pytest.mark.parametrize("where", ["missing folder", "a folder"])
def test_write_camera_yaml_names_the_path(tmp_path, where):
    """OpenCV said 'Emitter is not available' (review)."""
    from fusedmosaic.io import Camera, write_camera_yaml

    path = tmp_path / "none" / "camera.yaml" if where == "missing folder" else tmp_path
    with pytest.raises(OSError, match=re.escape(str(path))):
        write_camera_yaml(path, Camera(32, 24))
