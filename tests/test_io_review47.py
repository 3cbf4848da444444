"""Review 47 (io): file names that are not UTF-8 crashed OpenCV (H1), two frame files with the
same number were read as two frames (L4), and a misnamed dataset file was dropped without a
word (L5).

H1's tests run the library in a child process: a segfault there fails the test instead of
ending pytest. The names are made of bytes (a Latin-1 'é', 0xE9), as a Windows share or an old
ZIP leaves them on Linux."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest

from fusedmosaic.estimation.consistency import add_tracker_agreement
from fusedmosaic.io import Camera, read_dataset, write_dataset
from fusedmosaic.io.video import FrameSource, sort_frame_names
from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

W = H = 32
LATIN1 = b"\xe9"  # 'é' in Latin-1: not UTF-8


def _bytes_name(folder: Path, name: bytes) -> Path:
    """folder / name, for a name of bytes that are not UTF-8 (skips where the file system
    refuses such names, as macOS's does)."""
    path = Path(os.fsdecode(os.fsencode(folder) + b"/" + name))
    try:
        path.mkdir()
        path.rmdir()
    except OSError:
        pytest.skip("this file system refuses names that are not UTF-8")
    return path


def _child(code: str, *paths: Path) -> str:
    """What `code` prints, run in a new Python with the paths in sys.argv[1:] (as bytes, as
    a shell passes them); a ValueError's message printed as 'ValueError: ...'."""
    script = ("import sys\ntry:\n" + textwrap.indent(textwrap.dedent(code), "    ")
              + "except ValueError as e:\n    print('ValueError:', e)\n")
    run = subprocess.run([sys.executable, "-c", script, *(os.fsencode(p) for p in paths)],
                         capture_output=True, timeout=120)
    assert run.returncode == 0, (f"exit {run.returncode} (-11: a segfault): "
                                 + run.stderr.decode(errors="replace")[-3000:])
    return run.stdout.decode()


def _images(n: int = 4) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(n)]


def _write(root: Path, **kw) -> Path:
    return write_dataset(root, camera=Camera(W, H, camera_matrix=np.diag([40.0, 40.0, 1.0])),
                         frames=_images(), timestamps=np.arange(4) / 25.0, **kw)


READ = """
from fusedmosaic.io import read_dataset
d = read_dataset(sys.argv[1])
print(len(d), d.camera.width, d.camera.camera_matrix[0, 0],
      [int(d.frames[k].astype(int).sum()) for k in range(len(d))])
"""


def _expected() -> str:
    return f"4 {W} 40.0 {[int(im.astype(int).sum()) for im in _images()]}\n"


def test_dataset_written_and_read_in_a_folder_named_in_latin1(tmp_path):
    # write_dataset: camera.yaml (FileStorage) and the frames (imwrite); read_dataset: both read
    # back (FileStorage, imread). Each crashed OpenCV.
    root = _bytes_name(tmp_path, b"data" + LATIN1) / "ds"
    write = """
    from fusedmosaic.io import Camera, write_dataset
    import numpy as np
    rng = np.random.default_rng(0)
    write_dataset(sys.argv[1], camera=Camera(32, 32, camera_matrix=np.diag([40.0, 40.0, 1.0])),
                  frames=[rng.integers(0, 256, (32, 32, 3), dtype=np.uint8) for _ in range(4)],
                  timestamps=np.arange(4) / 25.0)
    print("written")
    """
    assert _child(write, root) == "written\n"
    assert _child(READ, root) == _expected()
    # camera.yaml as OpenCV writes it to a file, byte for byte
    _write(tmp_path / "plain")
    assert (root / "camera.yaml").read_bytes() == (tmp_path / "plain" / "camera.yaml").read_bytes()


def test_frame_file_names_in_latin1_are_read(tmp_path):
    root = _write(tmp_path / "ds")
    frames = root / "frames"
    _bytes_name(frames, b"probe")
    for k in range(4):  # 000000.png -> \xe9000000.png: the same order, the same numbers
        os.rename(frames / f"{k:06d}.png", os.fsencode(frames) + b"/" + LATIN1 + b"%06d.png" % k)
    (root / "frames.csv").unlink()  # (numbered by the files' numbers, timed at 25 fps)
    assert _child(READ, root) == _expected()


def test_camera_yaml_in_a_folder_named_in_latin1(tmp_path):
    _write(tmp_path / "ds")
    folder = _bytes_name(tmp_path, b"calib" + LATIN1)
    shutil.copytree(tmp_path / "ds", folder)
    code = """
    from fusedmosaic.io import read_camera_yaml, write_camera_yaml
    from pathlib import Path
    camera = read_camera_yaml(Path(sys.argv[1]) / "camera.yaml")
    write_camera_yaml(Path(sys.argv[1]) / "copy.yaml", camera)
    print(camera.size, read_camera_yaml(Path(sys.argv[1]) / "copy.yaml").camera_matrix[1, 1])
    """
    assert _child(code, folder) == f"({W}, {H}) 40.0\n"


def _avi(path: Path, n: int = 5) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (W, H))
    for image in _images(n):
        writer.write(image)
    writer.release()


def test_video_named_in_latin1_is_refused_by_name(tmp_path):
    # Only OpenCV reads and writes videos: such a name is refused, naming the file and the byte.
    plain = tmp_path / "ds"
    plain.mkdir()
    (plain / "camera.yaml").write_text(f"%YAML:1.0\nimage_width: {W}\nimage_height: {H}\n")
    _avi(plain / "video.avi")
    root = _bytes_name(tmp_path, b"data" + LATIN1)
    plain.rename(root)
    videos = _bytes_name(tmp_path, b"vid" + LATIN1)
    out = _bytes_name(tmp_path, b"out" + LATIN1)
    code = """
    from fusedmosaic.io import read_dataset
    from fusedmosaic.io.video import FrameSource
    from fusedmosaic.compositing.video import MosaicVideoWriter
    from pathlib import Path
    for step in (lambda: read_dataset(sys.argv[1]),
                 lambda: FrameSource(video=Path(sys.argv[2]) / "v.avi"),
                 lambda: MosaicVideoWriter(Path(sys.argv[3]) / "mosaic.mp4", (0, 0, 64, 64), 32,
                                           32)):
        try:
            step()
            print("no error")
        except ValueError as e:
            print('ValueError:', e)
    """
    videos.mkdir()
    shown = str(tmp_path)
    assert _child(code, root, videos, out).splitlines() == [
        f"ValueError: {shown}/data\\xe9/video.avi: the folder name 'data\\xe9' is not UTF-8 (the "
        "byte \\xe9: Latin-1 or another legacy encoding?), and OpenCV cannot read a video by "
        "such a name; rename it",
        f"ValueError: {shown}/vid\\xe9/v.avi: the folder name 'vid\\xe9' is not UTF-8 (the byte "
        "\\xe9: Latin-1 or another legacy encoding?), and OpenCV cannot read a video by such a "
        "name; rename it",
        f"ValueError: {shown}/out\\xe9/mosaic.mp4: the folder name 'out\\xe9' is not UTF-8 (the "
        "byte \\xe9: Latin-1 or another legacy encoding?), and OpenCV cannot write a video by "
        "such a name; rename it"]
    assert not out.exists()  # refused before its folder was made


def test_video_file_name_in_latin1_is_refused(tmp_path):
    _avi(tmp_path / "v.avi")
    name = os.fsencode(tmp_path) + b"/v" + LATIN1 + b"\xe8.avi"
    try:
        os.rename(tmp_path / "v.avi", name)
    except OSError:
        pytest.skip("this file system refuses names that are not UTF-8")
    assert _child("from fusedmosaic.io.video import FrameSource\nFrameSource(video=sys.argv[1])\n",
                  Path(os.fsdecode(name))) == (
        f"ValueError: {tmp_path}/v\\xe9\\xe8.avi: the file name 'v\\xe9\\xe8.avi' is not UTF-8 "
        "(the bytes \\xe9, \\xe8: Latin-1 or another legacy encoding?), and OpenCV cannot read a "
        "video by such a name; rename it\n")


# --- L4: two files for one frame number


def test_two_files_for_one_frame_number_are_refused(tmp_path):
    frames = tmp_path / "ds" / "frames"
    frames.mkdir(parents=True)
    for name in [f"{k}.png" for k in range(8)] + ["05.png"]:
        cv2.imwrite(str(frames / name), np.zeros((H, W), np.uint8))
    with pytest.raises(ValueError) as info:
        FrameSource.open(tmp_path / "ds")
    assert str(info.value) == (
        f"{frames}: two files for frame 5: 05.png and 5.png (the frames are ordered by the "
        "numbers in their names, and theirs are equal); remove the one that is not a frame, or "
        "rename it")
    # different numbers stay apart: 1.05 and 1.5 are other decimals; f10 and f010 equal only in
    # one of their two numbers
    assert sort_frame_names(["t_1.5.png", "t_1.05.png"]) == ["t_1.05.png", "t_1.5.png"]
    assert sort_frame_names(["a1_f10.png", "a2_f010.png"]) == ["a1_f10.png", "a2_f010.png"]


@pytest.mark.parametrize(("names", "message"), [
    (["f_001.png", "f_1.png", "f_2.png"], "two files for frame 1: f_001.png and f_1.png"),
    (["cam1_f2.png", "cam01_f2.png"], "two files for the same frame: cam01_f2.png and cam1_f2.png"),
    (["t_1.5.png", "t_1.50.png"], "two files for the same frame: t_1.5.png and t_1.50.png"),
    (["7.png", "7.PNG"], "two files for frame 7: 7.PNG and 7.png"),
])
def test_equal_frame_numbers_written_differently_are_refused(names, message):
    with pytest.raises(ValueError, match=rf"^frames: {message} \(the frames are ordered"):
        sort_frame_names(names)


# --- L5: a misnamed dataset file


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    return simulate_fetoscopy(tmp_path_factory.mktemp("l5") / "sim",
                              FetoscopyOptions(n_frames=8, width=64, height=64, laps=0.2))


@pytest.mark.parametrize(("name", "variant", "without"), [
    ("hand_eye.txt", "hand_eye.txt.txt", "the hand-eye transform is the identity (the camera at "
                                         "the tracker's sensor)"),
    ("hand_eye.txt", "Hand_Eye.txt", "the hand-eye transform is the identity"),
    ("hand_eye.txt", "hand-eye.txt", "the hand-eye transform is the identity"),
    ("tracking.csv", "Tracking.CSV", "the dataset has no tracker poses"),
    ("frames.csv", "frames.csv.txt", "the frames are timed by their number and a frame rate"),
])
def test_a_missing_file_with_a_near_name_there_is_named(simulated, tmp_path, name, variant,
                                                        without):
    root = shutil.copytree(simulated, tmp_path / "ds")
    (root / name).rename(root / variant)
    with pytest.warns(UserWarning) as record:
        read_dataset(root)
    texts = [str(w.message) for w in record]
    assert texts[0].startswith(
        f"{root / name}: not found, but {variant} is there; without {name}, {without}"), texts
    assert texts[0].endswith(f": if it is that file, rename it to {name} (the names are exact "
                             "and case-sensitive)"), texts


def test_a_missing_camera_yaml_with_a_near_name_there_is_named(simulated, tmp_path):
    root = shutil.copytree(simulated, tmp_path / "ds")
    (root / "camera.yaml").rename(root / "camera.yml")
    with pytest.raises(ValueError) as info:
        read_dataset(root)
    assert str(info.value) == (f"{root / 'camera.yaml'}: file not found, but camera.yml is "
                               "there: rename it to camera.yaml (the names are exact and "
                               "case-sensitive)")


def test_tracker_disagreement_without_hand_eye_says_the_identity_was_used(simulated, tmp_path):
    root = shutil.copytree(simulated, tmp_path / "ds")
    (root / "hand_eye.txt").unlink()
    dataset = read_dataset(root)
    assert dataset.hand_eye_file is None and np.array_equal(dataset.hand_eye, np.eye(4))
    poses = dataset.cam_from_world + [0, 0, 0, 20.0, 0, 0]  # 20 mm off: far beyond the noise
    details: dict = {}
    add_tracker_agreement(details, poses, dataset, None)
    (warning,) = details["warnings"]
    assert warning.startswith(f"{root / 'tracking.csv'}: the tracker disagrees with the images")
    assert ("There is no hand_eye.txt: the hand-eye transform was taken as the identity (the "
            "camera at the tracker's sensor); if the camera is not there, give "
            "sensor_from_camera as hand_eye.txt (calibrate measures it)") in warning
    assert "hand_eye.txt holds" not in warning
    # with hand_eye.txt, the advice names its convention
    with_file = read_dataset(simulated)
    assert with_file.hand_eye_file == simulated / "hand_eye.txt"
    details = {}
    add_tracker_agreement(details, with_file.cam_from_world + [0, 0, 0, 20.0, 0, 0], with_file,
                          None)
    assert "hand_eye.txt holds sensor_from_camera (not its inverse)" in details["warnings"][0]
    assert "There is no hand_eye.txt" not in details["warnings"][0]


CLI = [sys.executable, "-c", "import sys; from fusedmosaic.cli import main; sys.exit(main())"]


def test_run_with_its_report_on_a_dataset_folder_named_in_latin1(tmp_path):
    """report.md (it names the dataset) raised UnicodeEncodeError: exit 2 for every run with a
    report; a --video named so was refused only after the computation, naming the staging
    copy. Now the run writes its report, and the video name is refused before any work."""
    simulated = simulate_fetoscopy(tmp_path / "src", FetoscopyOptions(
        n_frames=8, width=120, height=120, laps=0.2))
    data = _bytes_name(tmp_path, b"data" + LATIN1)
    shutil.copytree(simulated, data)
    out = tmp_path / "out"
    run = subprocess.run([*CLI, "--quiet", "run",
                          os.fsencode(data), "--method", "emt", "--out", os.fsencode(out)],
                         capture_output=True, timeout=300)
    assert run.returncode == 0, run.stderr.decode(errors="replace")[-2000:]
    assert os.fsencode(data) in (out / "report.md").read_bytes()
    video = os.fsencode(tmp_path) + b"/v" + LATIN1 + b".mp4"
    run = subprocess.run([*CLI, "run", os.fsencode(data),
                          "--method", "emt", "--out", os.fsencode(tmp_path / "o2"),
                          "--video", video], capture_output=True, timeout=300)
    assert run.returncode == 2
    assert run.stderr.decode(errors="replace").strip().endswith(
        "v\\xe9.mp4: the file name 'v\\xe9.mp4' is not UTF-8 (the byte \\xe9: Latin-1 or another "
        "legacy encoding?), and OpenCV cannot write a video by such a name; rename it")
    assert not (tmp_path / "o2").exists()
