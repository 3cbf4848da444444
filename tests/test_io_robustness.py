"""Bad and awkward dataset input (audit 4): every problem is a ValueError naming the file, the
key or row/column and the problem; video frame sources are safe to read from several threads."""

from __future__ import annotations

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
    write_dataset,
)
from fusedmosaic.io.video import VIDEO_READ_AHEAD, VIDEO_RECENT_FRAMES, natural_key

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
    np.testing.assert_array_equal(frames[0], expected[0])  # backwards: one seek
    far = VIDEO_READ_AHEAD + 2
    np.testing.assert_array_equal(frames[far], expected[far])  # far ahead: one seek
    assert counter.seeks == [0, far]
    frames.close()


def test_truncated_video_names_file_and_frame_from_threads(tmp_path):
    expected = _write_video(tmp_path / "full.avi", 12)
    data = (tmp_path / "full.avi").read_bytes()
    root = tmp_path / "ds"
    root.mkdir()
    (root / "video.avi").write_bytes(data[: len(data) * 6 // 10])
    frames = FrameSource.open(root)
    assert len(frames) == 12  # the header still claims 12 frames
    with (
        ThreadPoolExecutor(2) as pool,
        pytest.raises(ValueError, match=r"video\.avi frame \d+: cannot read image \(video trunc"),
    ):
        list(pool.map(frames.__getitem__, range(12)))
    for k in (2, 0):  # after the failed decode the position is unknown: seek, do not guess
        np.testing.assert_array_equal(frames[k], expected[k])
    frames.close()


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
    assert sorted(["f10.png", "f9.png", "f010.png", "g1.png"], key=natural_key) == [
        "f9.png",
        "f010.png",
        "f10.png",
        "g1.png",
    ]


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
            r"camera_matrix: !!opencv-matrix data has 5 values but rows x cols = 3 x 3",
        ),
        (
            _opencv_matrix("camera_matrix", 3, 3, "[a, 0, 1, 0, 1, 1, 0, 0, 1]"),
            r"camera_matrix: element 1 is not a number \('a'\)",
        ),
        (
            _opencv_matrix("camera_matrix", 3, 3, K_DATA, dt="q"),  # cv2.error inside OpenCV
            r"camera_matrix: cannot read the !!opencv-matrix \(Invalid data type",
        ),
        (
            "camera_matrix: [40.5, 0, 15.5, 0, x, 11.5, 0, 0, 1]\n",
            r"camera_matrix: element 5 is not a number \('x'\)",
        ),
        (
            "camera_matrix: [480, 0, 199.5, 0, 480, 199.5, 0, 0, 0]\n",
            r"camera_matrix: last row must be 0 0 1 .*got 0 0 0$",
        ),
        (
            "camera_matrix: [480, 0, 0, 0, 480, 0, 199.5, 199.5, 1]\n",
            r"camera_matrix: last row must be 0 0 1 .*got 199.5 199.5 1 \(the matrix looks "
            r"transposed\)",
        ),
        (
            "camera_matrix: [480, 0, 15, 2, 480, 11, 0, 0, 1]\n",
            r"camera_matrix: element \(1, 0\) must be 0",
        ),
        (
            "camera_matrix: [-480, 0, 15, 0, 480, 11, 0, 0, 1]\n",
            r"camera_matrix: focal lengths must be positive, got fx=-480.0",
        ),
        (
            "camera_matrix: [1e12, 0, 15, 0, 1e12, 11, 0, 0, 1]\n",
            r"camera_matrix: focal length fx=1e\+12, fy=1e\+12 px is over 320000 px",
        ),
        (
            "camera_matrix: [1e-4, 0, 200, 0, 1e-4, 200, 0, 0, 1]\n",
            r"camera_matrix: numerically singular \(fx=0.0001",
        ),
        (
            "distortion_coefficients: [0.1, 0.2, 0.3]\n",
            r"distortion_coefficients: 3 values; OpenCV takes 4, 5, 8, 12 or 14",
        ),
        (
            _opencv_matrix("distortion_coefficients", 1, 6, "[0, 0, 0, 0, 0, 0]"),
            r"distortion_coefficients: 6 values; OpenCV takes",
        ),
        ("fov_mask_radius: 0.5\n", r"fov_mask_radius 0.5 px leaves the field-of-view mask empty"),
    ],
)
def test_bad_camera_yaml(tmp_path, body, match):
    path = _camera_yaml(tmp_path, body)
    with pytest.raises(ValueError, match=r"camera\.yaml: " + match):
        read_camera_yaml(path)


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
