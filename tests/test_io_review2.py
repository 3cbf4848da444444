"""A review of the input readers, its findings F1-F9: CSV parse errors as
ValueErrors, tracking.csv at numpy's speed, evaluate on a damaged first frame and a video read
once, camera.yaml as PyYAML / json write it, grey+alpha PNGs, hand_eye.txt layouts, README, and
the message hints."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

import fusedmosaic.io.video as video_module
from fusedmosaic.cli import main
from fusedmosaic.evaluation import evaluate_output
from fusedmosaic.io import (
    Camera,
    FrameSource,
    RobotSamples,
    TrackingSamples,
    read_camera_yaml,
    read_dataset,
    read_hand_eye,
    read_robot_csv,
    read_tracking_csv,
    write_dataset,
    write_homographies_csv,
)
from fusedmosaic.io.tracking import write_tracking_csv

W, H = 64, 48
README = Path(__file__).resolve().parents[1] / "README.md"


def _frames(n: int, seed: int = 0, colour: bool = False):
    rng = np.random.default_rng(seed)
    shape = (H, W, 3) if colour else (H, W)
    return [rng.integers(0, 256, shape, dtype=np.uint8) for _ in range(n)]


def _truth(n: int) -> np.ndarray:
    G = np.tile(np.eye(3), (n, 1, 1))
    G[:, 0, 2] = np.arange(n) * 2.0
    G[:, 1, 2] = np.arange(n) * 1.0
    return G


def _dataset(root: Path, n: int = 10, *, truth: bool = False, frames=None, **kw) -> Path:
    ts = np.arange(5 * n) / 100.0 - 0.05
    tracking = TrackingSamples(ts, np.c_[ts * 10, ts, 50 + 0 * ts],
                               np.tile([0, 0, 0, 1.0], (ts.size, 1)))
    robot = RobotSamples(ts, np.c_[ts * 100, ts * 50])
    cam = Camera(W, H, camera_matrix=np.array([[60, 0, W / 2], [0, 60, H / 2], [0, 0, 1.0]]),
                 pixel_size_um=1.0)
    return write_dataset(root, camera=cam, frames=_frames(n) if frames is None else frames,
                         timestamps=np.arange(n) / 25.0, tracking=tracking, robot=robot,
                         hand_eye=np.eye(4), ground_truth=_truth(n) if truth else None, **kw)


def _output(root: Path, G: np.ndarray) -> Path:
    root.mkdir(parents=True)
    write_homographies_csv(root / "homographies.csv", np.arange(len(G)), G)
    return root


def _tracking_lines(root: Path) -> list[str]:
    return (root / "tracking.csv").read_text().splitlines()


# ----------------------------------------------------------------------------------- F1


def test_f1_a_stray_quote_in_a_long_csv_is_a_value_error_naming_the_file_and_row(tmp_path):
    root = _dataset(tmp_path / "d")
    lines = _tracking_lines(root)
    (root / "tracking.csv").write_text(
        "\n".join(lines[:3] + ['"' + lines[3]] + lines[4:] * 3000) + "\n")
    with pytest.raises(ValueError, match=r"tracking\.csv: row 4: cannot be read as CSV \(field "
                                         r"larger than field limit.*unbalanced quote"):
        read_tracking_csv(root / "tracking.csv")


def test_f1_one_huge_field_is_a_value_error_in_every_table(tmp_path):
    root = _dataset(tmp_path / "d")
    frames = (root / "frames.csv").read_text().splitlines()
    (root / "frames.csv").write_text(
        "\n".join(frames[:2] + [frames[2].replace(",", "," + "9" * 200_000, 1)] + frames[3:]))
    with pytest.raises(ValueError, match=r"frames\.csv: row 3: cannot be read as CSV"):
        read_dataset(root)
    robot = (tmp_path / "robot.csv")
    robot.write_text('timestamp,x,y\n0,"1' + "1" * 200_000 + ",2\n")  # a stray quote
    with pytest.raises(ValueError, match=r"robot\.csv: row 2: cannot be read as CSV"):
        read_robot_csv(robot)


def test_f1_an_unreadable_csv_is_left_out_when_the_method_does_not_need_it(tmp_path, capsys):
    root = _dataset(tmp_path / "d")
    lines = _tracking_lines(root)
    (root / "tracking.csv").write_text(
        "\n".join(lines[:3] + ['"' + lines[3]] + lines[4:] * 3000) + "\n")
    (root / "robot.csv").write_text('timestamp,x,y\n0,"1' + "1" * 200_000 + ",2\n")
    ds = read_dataset(root, strict_tracking=False, strict_robot=False)
    assert ds.tracking is None and ds.robot is None
    assert "tracking.csv: row 4: cannot be read as CSV" in ds.ignored["tracking.csv"]
    assert "robot.csv: row 2: cannot be read as CSV" in ds.ignored["robot.csv"]
    # a method that needs it: refused with exit 2 and the message, not a traceback
    rc = main(["--quiet", "run", str(root), "--method", "emt", "--out", str(tmp_path / "o")])
    assert rc == 2
    assert "tracking.csv: row 4: cannot be read as CSV" in capsys.readouterr().err


# ----------------------------------------------------------------------------------- F2


def test_f2_files_of_numbers_take_the_fast_path(tmp_path, monkeypatch):
    """tracking.csv and robot.csv as written (numbers only) never reach the text reader."""
    import fusedmosaic.io.tracking as tracking

    rng = np.random.default_rng(2)
    ts = np.arange(50) / 40.0
    q = rng.normal(size=(50, 4))
    write_tracking_csv(tmp_path / "tracking.csv", TrackingSamples(
        ts, rng.normal(size=(50, 3)), q / np.linalg.norm(q, axis=1, keepdims=True),
        rng.random(50) > 0.2))
    tracking.write_robot_csv(tmp_path / "robot.csv", RobotSamples(ts, np.c_[ts, 2 * ts]))

    def text_reader(*args, **kwargs):
        raise AssertionError("read through the field-by-field text reader")

    monkeypatch.setattr(tracking, "read_table", text_reader)
    assert len(tracking.read_tracking_csv(tmp_path / "tracking.csv").timestamps) == 50
    np.testing.assert_array_equal(tracking.read_robot_csv(tmp_path / "robot.csv").xy_um[:, 1],
                                  2 * ts)


def test_f2_fast_and_text_paths_read_the_same_samples(tmp_path):
    rng = np.random.default_rng(1)
    m = 200
    ts = np.arange(m) / 40.0
    q = rng.normal(size=(m, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    valid = rng.random(m) > 0.1
    samples = TrackingSamples(ts, rng.normal(size=(m, 3)) * 50, q, valid)
    plain = tmp_path / "plain.csv"
    write_tracking_csv(plain, samples)
    a = read_tracking_csv(plain)
    # the same with MISSING in the invalid rows, true/false, a blank line: read as text
    lines = plain.read_text().splitlines()
    text = [lines[0]]
    for line, ok in zip(lines[1:], valid, strict=True):
        f = line.split(",")
        text.append(",".join([f[0], *f[1:8], "true"]) if ok else
                    ",".join([f[0]] + ["MISSING"] * 7 + ["false"]))
    text.insert(5, "")
    other = tmp_path / "text.csv"
    other.write_text("\n".join(text) + "\n")
    b = read_tracking_csv(other)
    for x, y in ((a.timestamps, b.timestamps), (a.valid, b.valid)):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.translations[valid], b.translations[valid])
    np.testing.assert_array_equal(a.quaternions[valid], b.quaternions[valid])
    assert np.isnan(b.translations[~valid]).all()
    # without the valid column, and as 1.0 / 0.0
    no_valid = tmp_path / "no_valid.csv"
    no_valid.write_text("\n".join([lines[0].rsplit(",", 1)[0]] + [
        line.rsplit(",", 1)[0] for line, ok in zip(lines[1:], valid, strict=True) if ok]))
    assert read_tracking_csv(no_valid).valid.all()
    floats = tmp_path / "floats.csv"
    floats.write_text("\n".join([lines[0]] + [line[:-1] + line[-1] + ".0" for line in lines[1:]]))
    np.testing.assert_array_equal(read_tracking_csv(floats).valid, valid)


def test_f2_messages_name_the_row_after_a_blank_line_and_in_the_fast_path(tmp_path):
    root = _dataset(tmp_path / "d")
    lines = _tracking_lines(root)
    path = root / "tracking.csv"
    bad = lines[6].split(",")
    bad[5] = "abc"
    path.write_text("\n".join(lines[:3] + [""] + lines[3:6] + [",".join(bad)] + lines[7:]))
    with pytest.raises(ValueError, match=r"tracking\.csv: row 8, column 'qy': cannot parse "
                                         r"'abc' as a number"):
        read_tracking_csv(path)
    zero = lines[4].split(",")
    zero[4:8] = ["0", "0", "0", "1"]
    zero[7] = "0"
    path.write_text("\n".join(lines[:4] + [",".join(zero)] + lines[5:]))  # numbers only
    with pytest.raises(ValueError, match=r"tracking\.csv: row 5: quaternion norm 0 is not 1"):
        read_tracking_csv(path)
    flag = lines[4].rsplit(",", 1)[0] + ",2"
    path.write_text("\n".join(lines[:4] + [flag] + lines[5:]))
    with pytest.raises(ValueError, match=r"tracking\.csv: row 5, column 'valid': expected 0 "
                                         r"or 1 .*got '2'"):
        read_tracking_csv(path)
    robot = root / "robot.csv"
    rows = robot.read_text().splitlines()
    robot.write_text("\n".join(rows[:3] + [rows[3].split(",")[0] + ",,1"] + rows[4:]))
    with pytest.raises(ValueError, match=r"robot\.csv: row 4, column 'x': NaN or empty"):
        read_robot_csv(robot)


# ----------------------------------------------------------------------------------- F3


def test_f3_evaluate_scores_a_dataset_whose_first_frame_is_damaged(tmp_path, capsys):
    root = _dataset(tmp_path / "d", truth=True)
    first = root / "frames" / "000000.png"
    first.write_bytes(first.read_bytes()[:200])
    out = _output(tmp_path / "out", _truth(10))
    result = evaluate_output(out, root)
    assert result["e_M_px"] == pytest.approx(0.0, abs=1e-9)
    assert main(["--quiet", "evaluate", str(out), "--truth", str(root)]) == 0, \
        capsys.readouterr().err


# ----------------------------------------------------------------------------------- F4


def _video_dataset(root: Path, n: int = 12) -> Path:
    _dataset(root, n, truth=True)
    writer = cv2.VideoWriter(str(root / "video.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 25,
                             (W, H))
    for k in range(n):
        writer.write(cv2.imread(str(root / "frames" / f"{k:06d}.png"), cv2.IMREAD_COLOR))
    writer.release()
    for p in (root / "frames").iterdir():
        p.unlink()
    (root / "frames").rmdir()
    return root


def test_f4_evaluate_decodes_a_video_dataset_at_most_once(tmp_path, monkeypatch):
    root = _video_dataset(tmp_path / "d")
    assert FrameSource.open(root).video is not None
    G = _truth(12)
    out = _output(tmp_path / "out", G)
    G2 = G.copy()
    G2[:, 0, 2] += 0.5 * np.arange(12)
    out2 = _output(tmp_path / "out2", G2)
    passes = []
    decode = video_module._decode_times

    def counted(capture, limit=None):
        times = decode(capture, limit)
        passes.append(len(times))
        return times

    monkeypatch.setattr(video_module, "_decode_times", counted)
    assert main(["--quiet", "evaluate", str(out), "--truth", str(root), "--compare",
                 str(out2), "--positions", "4"]) == 0
    assert len(passes) <= 1, passes
    assert (out / "evaluation.md").is_file()


# ----------------------------------------------------------------------------------- F5

K_ROWS = [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]


@pytest.mark.parametrize("text", [
    # yaml.safe_dump of a flat list and of K.tolist(): sequences flush under their key
    "camera_matrix:\n- 500.0\n- 0.0\n- 320.0\n- 0.0\n- 500.0\n- 240.0\n- 0.0\n- 0.0\n- 1.0\n"
    "image_height: 480\nimage_width: 640\n",
    "camera_matrix:\n- - 500.0\n  - 0.0\n  - 320.0\n- - 0.0\n  - 500.0\n  - 240.0\n- - 0.0\n"
    "  - 0.0\n  - 1.0\nimage_height: 480\nimage_width: 640\n",
    # nested flow lists, and json.dumps of K.tolist()
    "image_width: 640\nimage_height: 480\ncamera_matrix: [[500.0, 0.0, 320.0], "
    "[0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]\ndistortion_coefficients: [[-0.1, 0.01, 0, 0, 0]]\n",
    '{"image_width": 640, "image_height": 480, "camera_matrix": [[500.0, 0.0, 320.0], '
    '[0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]}',
    # ROS camera_info as yaml.safe_dump writes it (the data list flush under "data:")
    "camera_matrix:\n  cols: 3\n  data:\n  - 500.0\n  - 0.0\n  - 320.0\n  - 0.0\n  - 500.0\n"
    "  - 240.0\n  - 0.0\n  - 0.0\n  - 1.0\n  rows: 3\ndistortion_coefficients:\n  cols: 5\n"
    "  data:\n  - -0.1\n  - 0.01\n  - 0.0\n  - 0.0\n  - 0.0\n  rows: 1\n"
    "distortion_model: plumb_bob\nimage_height: 480\nimage_width: 640\n",
])
@pytest.mark.parametrize("newline", ["\n", "\r\n"])  # CRLF: safe_dump to a text file on Windows
def test_f5_camera_yaml_as_pyyaml_and_json_write_it(tmp_path, text, newline):
    path = tmp_path / "camera.yaml"
    path.write_bytes(text.replace("\n", newline).encode())
    camera = read_camera_yaml(path)
    assert (camera.width, camera.height) == (640, 480)
    np.testing.assert_array_equal(camera.camera_matrix, K_ROWS)
    if "distortion" in text:
        np.testing.assert_allclose(np.ravel(camera.distortion), [-0.1, 0.01, 0, 0, 0])


def test_f5_rows_of_different_lengths_or_a_list_among_numbers_are_named(tmp_path):
    path = tmp_path / "camera.yaml"
    path.write_text("image_width: 640\nimage_height: 480\n"
                    "camera_matrix: [[500.0, 0.0, 320.0], [0.0, 500.0], [0.0, 0.0, 1.0]]\n")
    with pytest.raises(ValueError, match=r"camera\.yaml: camera_matrix: rows of different "
                                         r"lengths \(3, 2, 3 numbers\)"):
        read_camera_yaml(path)
    path.write_text("image_width: 640\nimage_height: 480\n"
                    "camera_matrix: [500.0, [0.0, 320.0], 0, 500, 240, 0, 0, 1]\n")
    with pytest.raises(ValueError, match=r"camera\.yaml: camera_matrix: element 2 is a list, "
                                         r"not a number"):
        read_camera_yaml(path)


# ----------------------------------------------------------------------------------- F6


def _png_grey_alpha(path: Path, grey: np.ndarray) -> None:
    """A PNG of colour type 4 (grey + alpha, 8-bit), as PIL's mode LA writes it."""
    h, w = grey.shape
    pixels = np.dstack([grey, np.full_like(grey, 255)]).reshape(h, 2 * w)
    raw = b"".join(b"\x00" + row.tobytes() for row in pixels)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 4,
                                                                       0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def test_f6_grey_alpha_png_frames_read_as_grey(tmp_path):
    frames = _frames(6)
    root = _dataset(tmp_path / "d", 6, frames=frames)
    _png_grey_alpha(root / "frames" / "000003.png", frames[3])  # one among grey frames
    assert cv2.imread(str(root / "frames" / "000003.png"), cv2.IMREAD_UNCHANGED).shape[2] == 4
    ds = read_dataset(root)
    np.testing.assert_array_equal(ds.frames[3], frames[3])
    assert all(ds.frames[k].shape == (H, W) for k in range(6))
    for k in range(6):  # all of them grey+alpha: a grey recording
        _png_grey_alpha(root / "frames" / f"{k:06d}.png", frames[k])
    ds = read_dataset(root)
    for k in range(6):
        np.testing.assert_array_equal(ds.frames[k], frames[k])
    # a colour PNG with alpha (RGBA) stays colour
    rgba = np.dstack([_frames(1, colour=True)[0], np.full((H, W), 255, np.uint8)])
    cv2.imwrite(str(tmp_path / "rgba.png"), rgba)
    assert FrameSource([tmp_path / "rgba.png"])[0].shape == (H, W, 3)


# ----------------------------------------------------------------------------------- F7


def _rigid() -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(0.3), np.sin(0.3)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [1.5, -2.0, 6.0]
    return T


@pytest.mark.parametrize("layout", ["comma", "semicolon", "print", "matlab", "one line", "3x4"])
def test_f7_hand_eye_layouts(tmp_path, layout):
    T = _rigid()
    rows = [[repr(float(v)) for v in row] for row in T]
    text = {
        "comma": "\n".join(",".join(r) for r in rows),
        "semicolon": "\n".join(";".join(r) for r in rows),
        "print": "[" + "\n ".join("[" + " ".join(r) + "]" for r in rows) + "]",
        "matlab": "[" + "; ".join(", ".join(r) for r in rows) + "]",
        "one line": " ".join(v for r in rows for v in r),
        "3x4": "\n".join(" ".join(r) for r in rows[:3]),
    }[layout]
    path = tmp_path / "hand_eye.txt"
    path.write_text(text + "\n")
    np.testing.assert_allclose(read_hand_eye(path), T, atol=1e-12)


def test_f7_the_rigidity_check_and_the_shape_message_still_apply(tmp_path):
    path = tmp_path / "hand_eye.txt"
    path.write_text("2,0,0,1\n0,1,0,2\n0,0,1,3\n")  # a 3x4 that scales
    with pytest.raises(ValueError, match=r"hand_eye\.txt: not a rigid transform"):
        read_hand_eye(path)
    path.write_text("1 0 0\n0 1 0\n0 0 1\n")
    with pytest.raises(ValueError, match=r"hand_eye\.txt: expected a 4x4 matrix, got 3x3 "
                                         r"\(also accepted: its 16 numbers"):
        read_hand_eye(path)
    path.write_text("1, 0, 0, 1\n0, 1, x, 2\n")
    with pytest.raises(ValueError, match=r"hand_eye\.txt: cannot parse as a 4x4 matrix of "
                                         r"numbers"):
        read_hand_eye(path)


# ----------------------------------------------------------------------------------- F8


def test_f8_readme_says_untracked_frames_are_refused_and_how_to_flag_them():
    text = " ".join(README.read_text().split())
    assert "refused by default" in text and "`run --allow-untracked` flags them" in text


# ----------------------------------------------------------------------------------- F9


def test_f9_frames_that_are_not_png_are_named(tmp_path):
    root = _dataset(tmp_path / "d", 4)
    for p in sorted((root / "frames").iterdir()):
        p.rename(p.with_suffix(".jpg"))
    with pytest.raises(ValueError, match=r"frames: no frames \(\*\.png\): it holds 4 \.jpg "
                                         r"file\(s\) \(000000\.jpg, .*only PNG frames are read"):
        read_dataset(root)
    (root / "frames" / "000000.jpg").rename(root / "frames" / "000000.png")
    for k in (1, 2, 3):  # one stray JPEG among PNGs: warned of
        (root / "frames" / f"{k:06d}.jpg").rename(root / "frames" / f"{k:06d}.png")
    (root / "frames" / "extra.jpg").write_bytes(b"")
    with pytest.warns(UserWarning, match=r"frames: 1 image file\(s\) that are not PNG left out "
                                         r"\(extra\.jpg\)"):
        read_dataset(root)


def test_f9_a_capitalised_video_name_is_named(tmp_path):
    root = _video_dataset(tmp_path / "d", 4)
    (root / "video.avi").rename(root / "Video.AVI")
    with pytest.raises(ValueError, match=r"no frames \(neither frames/\*\.png nor a video\.\* "
                                         r"file\); found Video\.AVI: the names are "
                                         r"case-sensitive"):
        read_dataset(root)
    (root / "Video.AVI").rename(root / "video")  # the case right: the real problem is named
    with pytest.raises(ValueError, match=r"; video has no extension: name it video\.<ext>"):
        read_dataset(root)
    (root / "video").rename(root / "frames")
    with pytest.raises(ValueError, match=r"; frames is a file, not a folder of PNG frames$"):
        read_dataset(root)


def test_f9_comment_and_pandas_index_headers_get_a_hint(tmp_path):
    root = _dataset(tmp_path / "d")
    lines = _tracking_lines(root)
    path = root / "tracking.csv"
    path.write_text("# NDI Aurora export\n" + "\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"tracking\.csv: row 1: header is .*comment lines are "
                                         r"not allowed"):
        read_tracking_csv(path)
    path.write_text("\n".join(lines[:5] + ["# pause"] + lines[5:]) + "\n")
    with pytest.raises(ValueError, match=r"tracking\.csv: row 6: 1 fields, expected 9 .*comment "
                                         r"lines are not allowed"):
        read_tracking_csv(path)
    frames = (root / "frames.csv").read_text().splitlines()
    (root / "frames.csv").write_text("\n".join(
        ["," + frames[0]] + [f"{i},{line}" for i, line in enumerate(frames[1:])]) + "\n")
    with pytest.raises(ValueError, match=r"frames\.csv: row 1: header is ',frame,timestamp'.*"
                                         r"pandas' index\? write the file with "
                                         r"to_csv\(\.\.\., index=False\)"):
        read_dataset(root)
