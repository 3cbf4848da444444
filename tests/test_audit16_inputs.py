"""Audit 16 items 5, 8 and 9 (tracker exports): a method is not refused for a file it does not
use; frame / sample times in the wrong unit are refused at read time naming the file and the
row; tracking.csv's valid flags as exports write them; which rigidity check hand_eye.txt fails."""

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from fusedmosaic.cli import main
from fusedmosaic.evaluation.report import load_truth
from fusedmosaic.io import read_dataset, read_hand_eye, read_robot_csv, read_tracking_csv
from fusedmosaic.io.tracking import (
    MAX_FRAME_SPACING_S,
    check_stream_timestamp,
    hand_eye_matrix,
    rigid_defects,
)
from fusedmosaic.runner import run_dataset


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A tiny fetoscopy dataset (8 frames at 25 fps, tracker at 40 Hz) and a pCLE one (10 fps)."""
    root = tmp_path_factory.mktemp("inputs16")
    assert main(["--quiet", "simulate", "fetoscopy", str(root / "feto"), "--n-frames", "8",
                 "--laps", "0.1"]) == 0
    assert main(["--quiet", "simulate", "pcle", str(root / "pcle"), "--n-frames", "8",
                 "--width", "128", "--height", "112"]) == 0
    return root


def copy(data: Path, name: str, tmp_path: Path) -> Path:
    return Path(shutil.copytree(data / name, tmp_path / name))


def edit_column(path: Path, column: int, change) -> None:
    """Applies `change` (str -> str) to one column of every data row of a CSV."""
    lines = path.read_text().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    for row in rows:
        row[column] = change(row[column])
    path.write_text("\n".join([lines[0], *(",".join(r) for r in rows)]) + "\n")


def in_ms(text: str) -> str:
    return repr(float(text) * 1000.0)


# --------------------------------------------------------------------------- item 5

# tracking.csv / hand_eye.txt a tracker method refuses, and what the refusal says
BAD_TRACKER = {
    "unix clock": ("tracking.csv", lambda p: edit_column(p, 0, lambda t: repr(float(t) + 1.7e9)),
                   r"tracking\.csv: none of the 8 frames lies in the tracker's time span"),
    "short row": ("tracking.csv", lambda p: p.write_text(p.read_text() + "1e3,1,2\n"),
                  r"tracking\.csv: row 23: 3 fields, expected 9"),
    "reflection": ("hand_eye.txt",
                   lambda p: np.savetxt(p, np.diag([1.0, 1.0, -1.0, 1.0])),
                   r"hand_eye\.txt: not a rigid transform: .*a reflection"),
}


@pytest.mark.parametrize("case", sorted(BAD_TRACKER))
def test_image_only_methods_run_despite_an_unusable_tracker(data, tmp_path, case):
    """pairwise / ba do not use the EM tracker: an unusable tracking.csv or hand_eye.txt is
    left out with a warning naming the file and the problem; the tracker methods still get
    the same refusal as before."""
    name, spoil, problem = BAD_TRACKER[case]
    root = copy(data, "feto", tmp_path)
    spoil(root / name)
    with pytest.raises(ValueError, match=problem):
        run_dataset(root, "emt", tmp_path / "emt", progress=False, report=False)
    assert not (tmp_path / "emt").exists()
    with pytest.raises(ValueError, match=problem):
        read_dataset(root)
    for method in ("pairwise", "ba"):
        with pytest.warns(UserWarning, match=problem + r".* -- left out: method "
                          f"'{method}' does not use"):
            run_dataset(root, method, tmp_path / method, progress=False, report=False)
        report = json.loads((tmp_path / method / "report.json").read_text())
        assert report["frames"] == 8 and report["placed"] >= 2


def test_lenient_read_records_why_and_requirements_say_it(data, tmp_path):
    root = copy(data, "feto", tmp_path)
    (root / "tracking.csv").write_text("timestamp;tx;ty;tz;qx;qy;qz;qw\n")
    ds = read_dataset(root, strict_tracking=False)
    assert ds.tracking is None and ds.cam_from_world is None and ds.pose_valid is None
    assert list(ds.ignored) == ["tracking.csv"]
    assert "row 1: header is" in ds.ignored["tracking.csv"]
    with pytest.raises(ValueError, match=r"tracking\.csv: row 1: header is .* \(method 'emt' "
                                         r"needs EM tracker poses\)"):
        ds.require_tracking("emt")
    # hand_eye.txt unusable: both files left out, each with its reason
    root = copy(data, "feto", tmp_path / "b")
    np.savetxt(root / "hand_eye.txt", np.diag([1.01, 1.01, 1.01, 1.0]))
    ds = read_dataset(root, strict_tracking=False)
    assert ds.tracking is None and np.array_equal(ds.hand_eye, np.eye(4))
    assert "norms 1.01, 1.01, 1.01, not 1 (scaled)" in ds.ignored["hand_eye.txt"]
    assert "left out with hand_eye.txt" in ds.ignored["tracking.csv"]


def test_lenient_read_keeps_a_usable_tracker_for_the_plots(data, tmp_path):
    """A well-formed tracking.csv is still read for a method that does not use it (the report
    plots the EM tracker); frames outside its span are flagged, not refused."""
    root = copy(data, "feto", tmp_path)
    lines = (root / "tracking.csv").read_text().splitlines()
    (root / "tracking.csv").write_text("\n".join(lines[:-8]) + "\n")  # ends before the frames
    with pytest.raises(ValueError, match=r"frames outside the tracker's time span"):
        read_dataset(root)
    ds = read_dataset(root, strict_tracking=False)
    assert ds.ignored == {} and ds.tracking is not None
    assert ds.pose_valid.any() and not ds.pose_valid.all()
    assert np.isnan(ds.cam_from_world[~ds.pose_valid]).all()
    assert load_truth(root).tracker_poses is not None


def test_evaluate_report_reads_the_truth_despite_an_unusable_tracker(data, tmp_path):
    root = copy(data, "feto", tmp_path)
    edit_column(root / "tracking.csv", 8, lambda v: "OK")
    truth = load_truth(root)
    assert truth.tracker_poses is None and truth.homographies is not None


def test_ncc_runs_despite_a_malformed_robot_csv(data, tmp_path):
    root = copy(data, "pcle", tmp_path)
    (root / "robot.csv").write_text("timestamp,x,y\n0,1\n")
    problem = r"robot\.csv: row 2: 2 fields, expected 3"
    with pytest.raises(ValueError, match=problem):
        run_dataset(root, "kalman-robot", tmp_path / "k", progress=False, report=False)
    with pytest.warns(UserWarning, match=problem + r".* left out: method 'ncc' does not use it"):
        run_dataset(root, "ncc", tmp_path / "ncc", progress=False, report=False)
    assert json.loads((tmp_path / "ncc" / "report.json").read_text())["placed"] == 8
    from fusedmosaic.evaluation import evaluate_output

    assert evaluate_output(tmp_path / "ncc", root)["placed"] == 8  # scored without the robot
    # the robot file given by name is the one read leniently
    ds = read_dataset(root, robot_file="robot.csv", strict_robot=False)
    assert ds.robot is None and problem.replace("\\", "") in ds.ignored["robot.csv"]
    ds = read_dataset(root, robot_file="robot_noisy.csv", strict_robot=False)
    assert ds.robot is not None and ds.ignored == {}


def test_cli_prints_the_left_out_file_as_a_warning(data, tmp_path, capsys):
    root = copy(data, "feto", tmp_path)
    edit_column(root / "tracking.csv", 0, lambda t: repr(float(t) + 1.7e9))
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        assert main(["--quiet", "run", str(root), "--method", "pairwise", "--out",
                     str(tmp_path / "o"), "--no-report"]) == 0
    err = capsys.readouterr().err
    assert "fusedmosaic: warning: " in err and "tracking.csv: none of the 8 frames" in err
    assert "left out: method 'pairwise' does not use it" in err
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert "none of the 8 frames" in report["inputs_ignored"]["tracking.csv"]


# --------------------------------------------------------------------------- item 8


def test_frame_times_in_unix_milliseconds_are_refused_naming_the_row(data, tmp_path):
    root = copy(data, "feto", tmp_path)
    edit_column(root / "frames.csv", 1, lambda t: repr((float(t) + 1714560000.123) * 1000))
    problem = (r"frames\.csv: row 2, column 'timestamp': 1714560000123\.0 is beyond "
               r"\|t\| <= 1e\+10 s .*milliseconds")
    with pytest.raises(ValueError, match=problem):
        read_dataset(root)
    for method in ("pairwise", "lba-emt"):  # every method, at read time
        with pytest.raises(ValueError, match=problem):
            run_dataset(root, method, tmp_path / method, progress=False, report=False)
        assert not (tmp_path / method).exists()


def test_frame_times_in_milliseconds_are_refused_by_their_spacing(data, tmp_path):
    """Frames at 25 fps stamped in ms (0, 40, 80, ...) stay below |t| <= 1e10 s: their median
    spacing (40 s) gives them away; tracking.csv in ms as well (consistent) does not help."""
    root = copy(data, "feto", tmp_path)
    edit_column(root / "frames.csv", 1, in_ms)
    edit_column(root / "tracking.csv", 0, in_ms)
    with pytest.raises(ValueError, match=r"frames\.csv: frames come every 40 s \(median spacing; "
                       r"e\.g\. rows 2 and 3 are 40 s apart\), more than MAX_FRAME_SPACING_S "
                       r"\(10 s\).*milliseconds\?"):
        read_dataset(root)
    root = copy(data, "pcle", tmp_path)  # 10 fps: 100 "s"
    edit_column(root / "frames.csv", 1, in_ms)
    with pytest.raises(ValueError, match=r"frames\.csv: frames come every 100 s"):
        run_dataset(root, "ncc", tmp_path / "ncc", progress=False, report=False)


def test_a_gap_of_more_than_a_day_is_refused_a_long_pause_is_not(data, tmp_path):
    root = copy(data, "feto", tmp_path)
    edit_column(root / "frames.csv", 1, lambda t: repr(float(t) + (2e5 if float(t) > 0.1 else 0)))
    with pytest.raises(ValueError, match=r"frames\.csv: row 5: timestamp 200000\.12 is "
                       r"200000\.040 s after the previous row's, more than MAX_FRAME_GAP_S "
                       r"\(86400 s, a day\)"):
        read_dataset(root, strict_tracking=False)
    root = copy(data, "feto", tmp_path / "pause")
    edit_column(root / "frames.csv", 1, lambda t: repr(float(t) + (3600 if float(t) > 0.1 else 0)))
    ds = read_dataset(root, strict_tracking=False)  # an hour's pause: frames in s, accepted
    assert ds.timestamps[-1] > 3600
    previous = -np.inf
    for k, t in enumerate(ds.timestamps):  # and the streaming mosaickers accept them too
        previous = check_stream_timestamp(k, t, previous)


def test_frame_rate_giving_frames_far_apart_is_refused(data, tmp_path):
    root = copy(data, "feto", tmp_path)
    (root / "frames.csv").unlink()
    with pytest.raises(ValueError, match=r"frame / 0\.05 fps \(given; no frames\.csv\) put "
                       r"frames 20 s apart.*MAX_FRAME_SPACING_S"):
        read_dataset(root, fps=0.05, strict_tracking=False)
    with pytest.raises(ValueError, match=r"frame / 1e-300 fps .* put frames 1e\+300 s apart"):
        read_dataset(root, fps=1e-300, strict_tracking=False)
    assert read_dataset(root, fps=1.0 / MAX_FRAME_SPACING_S, strict_tracking=False)


def test_the_usual_frame_rates_pass(data):
    for name, step in (("feto", 0.04), ("pcle", 0.1)):
        ds = read_dataset(data / name)
        assert np.allclose(np.diff(ds.timestamps), step)


@pytest.mark.parametrize("name, reader, what", [
    ("tracking.csv", read_tracking_csv, "tracker"),
    ("robot.csv", read_robot_csv, "robot"),
])
def test_sample_times_beyond_the_bound_name_the_file_and_row(data, tmp_path, name, reader, what):
    root = copy(data, "feto" if name == "tracking.csv" else "pcle", tmp_path)
    edit_column(root / name, 0, lambda t: repr((float(t) + 1714560000.0) * 1000))
    with pytest.raises(ValueError, match=rf"{name}: row 2, column 'timestamp': 1714559999\d*\.\d+ "
                       rf"is beyond \|t\| <= 1e\+10 s .*{what} timestamps are in seconds; are "
                       r"these milliseconds"):
        reader(root / name)


# --------------------------------------------------------------------------- item 9


HEADER = "timestamp,tx,ty,tz,qx,qy,qz,qw,valid\n"
ROW = "{t},1,2,3,0,0,0,1,{v}\n"


@pytest.mark.parametrize("flags, expected", [
    (("true", "false", "TRUE", "False"), [True, False, True, False]),
    (("1.0", "0.0", "1", "0"), [True, False, True, False]),
    ((" 1.00", "0.", "+1", "1e0"), [True, False, True, True]),
])
def test_valid_flags_as_exports_write_them(tmp_path, flags, expected):
    path = tmp_path / "tracking.csv"
    path.write_text(HEADER + "".join(ROW.format(t=k, v=f) for k, f in enumerate(flags)))
    assert read_tracking_csv(path).valid.tolist() == expected


@pytest.mark.parametrize("flag", ["OK", "yes", "", "2", "0.5", "nan", "-1"])
def test_other_valid_flags_are_refused_listing_the_accepted_ones(tmp_path, flag):
    path = tmp_path / "tracking.csv"
    path.write_text(HEADER + ROW.format(t=0, v=1) + ROW.format(t=1, v=flag))
    with pytest.raises(ValueError, match=r"tracking\.csv: row 3, column 'valid': expected 0 or "
                       r"1 \(also accepted: true / false in any case, 1\.0 / 0\.0\), got "
                       f"'{flag}'"):
        read_tracking_csv(path)


def test_an_invalid_rows_pose_text_is_ignored(tmp_path):
    """NDI exports write MISSING in the pose fields of a missing sample: with valid=0 its
    content is not read; in a valid row it is still refused."""
    path = tmp_path / "tracking.csv"
    missing = "2,MISSING,MISSING,MISSING,MISSING,MISSING,MISSING,MISSING,{v}\n"
    path.write_text(HEADER + ROW.format(t=1, v=1) + missing.format(v=0) + ROW.format(t=3, v=1))
    samples = read_tracking_csv(path)
    assert samples.valid.tolist() == [True, False, True]
    assert np.isnan(samples.translations[1]).all() and np.isnan(samples.quaternions[1]).all()
    assert np.array_equal(samples.translations[0], [1, 2, 3])
    path.write_text(HEADER + ROW.format(t=1, v=1) + missing.format(v="true"))
    with pytest.raises(ValueError, match=r"row 3, column 'tx': cannot parse 'MISSING' as a "
                                         "number"):
        read_tracking_csv(path)
    # the timestamp of an invalid row still has to be a number, in order
    path.write_text(HEADER + ROW.format(t=1, v=1) + ROW.format(t="MISSING", v=0))
    with pytest.raises(ValueError, match=r"row 3, column 'timestamp': cannot parse 'MISSING'"):
        read_tracking_csv(path)


def _rotation() -> np.ndarray:
    c, s = np.cos(0.3), np.sin(0.3)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [1.0, 2.0, 3.0]
    return T


def _spoiled(change) -> np.ndarray:
    T = _rotation()
    change(T)
    return T


@pytest.mark.parametrize("T, problem", [
    (_spoiled(lambda T: T.__setitem__((slice(0, 3), slice(0, 3)), T[:3, :3] * 1.01)),
     r"columns have norms 1\.01, 1\.01, 1\.01, not 1 \(scaled\)"),
    (_spoiled(lambda T: T.__setitem__((slice(0, 3), 2), -T[:3, 2])),
     r"determinant is -1, not \+1: a reflection \(a left-handed frame"),
    (_spoiled(lambda T: T.__setitem__((0, 1), T[0, 1] + 0.01)),
     r"columns are not orthogonal \(\|cos\| up to 0\.0\d+ between two: sheared\)"),
    (_spoiled(lambda T: T.__setitem__((3, 2), 0.5)), r"the last row is 0 0 0\.5 1, not 0 0 0 1"),
])
def test_hand_eye_says_which_rigidity_check_fails(tmp_path, T, problem):
    path = tmp_path / "hand_eye.txt"
    np.savetxt(path, T)
    with pytest.raises(ValueError, match=r"hand_eye\.txt: not a rigid transform: .*" + problem):
        read_hand_eye(path)
    with pytest.raises(ValueError, match=r"hand_eye: not a rigid transform: .*" + problem):
        hand_eye_matrix(T)


@pytest.mark.parametrize("T, kind", [
    (_spoiled(lambda T: T.__setitem__((slice(0, 3), slice(0, 3)), T[:3, :3] * 1.01)), "scaled"),
    (_spoiled(lambda T: T.__setitem__((slice(0, 3), 2), -T[:3, 2])), "a reflection (det -1)"),
    (_spoiled(lambda T: T.__setitem__((0, 1), T[0, 1] + 0.01)), "sheared"),
    (_spoiled(lambda T: T.__setitem__((3, 2), 0.5)), "last row not 0 0 0 1"),
])
def test_a_live_sample_says_which_rigidity_check_fails(T, kind):
    """OpenIGTLink counts its invalid samples by problem: the kind, without the figures."""
    from fusedmosaic.io.igtl import _rigid_problem

    assert _rigid_problem(T) == f"not rigid: {kind}"
    assert _rigid_problem(_rotation()) is None


def test_a_shear_is_not_also_called_a_scale():
    message = rigid_defects(_spoiled(lambda T: T.__setitem__((0, 1), T[0, 1] + 0.01)), 1e-4)
    assert "sheared" in message and "scaled" not in message
    assert rigid_defects(_rotation(), 1e-4) == ""
