"""Audit 20 (the rest): options that were accepted where they do nothing or spoil the output,
the robot's clock offset in offline runs, checkerboard options that blamed the lens, and a
misleading system message. Each test fails on the code before the fix."""

import json

import numpy as np
import pytest

from fusedmosaic.cli import main
from fusedmosaic.compositing import BlendOptions
from fusedmosaic.compositing.blending import FrameWarper
from fusedmosaic.io import read_dataset, read_homographies_csv
from fusedmosaic.io.tracking import RobotSamples, read_robot_csv, write_robot_csv
from fusedmosaic.simulation import CheckerboardOptions, PcleOptions, simulate_pcle

AHEAD_S = 0.06  # the robot's clock ahead of the video's (three robot periods at 50 Hz)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Eight fetoscopy frames of 160x120, a pCLE recording and its twin whose robot clock is
    AHEAD_S ahead (robot.csv stamped later by that much)."""
    root = tmp_path_factory.mktemp("audit20")
    assert main(["--quiet", "simulate", "fetoscopy", str(root / "feto"), "--n-frames", "8",
                 "--width", "160", "--height", "120", "--laps", "0.2"]) == 0
    assert main(["--quiet", "simulate", "fetoscopy", str(root / "lens"), "--n-frames", "8",
                 "--width", "320", "--height", "240", "--laps", "0.1", "--lens-distortion",
                 "0.5", "0", "0", "0"]) == 0
    options = PcleOptions(width=128, height=112, n_frames=20, contact_loss=False,
                          stick_slip=False)
    simulate_pcle(root / "pcle", options)
    import shutil

    shutil.copytree(root / "pcle", root / "ahead")
    robot = read_robot_csv(root / "pcle" / "robot.csv")
    write_robot_csv(root / "ahead" / "robot.csv",
                    RobotSamples(robot.timestamps + AHEAD_S, robot.xy_um))
    return root


def test_a_border_covering_the_frames_is_refused_before_the_estimation(data, tmp_path, capsys):
    """--border 1e9 gave an all-black mosaic without a word: the 160x120 frames' centre is 60 px
    from their edge. Through a lens the undistorted frames' valid pixels are measured (those
    the mosaic is drawn from): 114 px there against 120 raw, so 116 px is refused up front, not
    after the estimation."""
    out = tmp_path / "o"
    assert main(["run", str(data / "feto"), "--method", "emt", "--out", str(out),
                 "--border", "1e9"]) == 2
    assert ("border (border_px, --border) 1e+09 covers the whole field of view (its centre is "
            "60 px from the edge): the frames would be drawn all black; give at most 20.5 px (a "
            "border is a thin seam, e.g. 1.5)") \
        in capsys.readouterr().err
    assert main(["run", str(data / "lens"), "--method", "pairwise", "--out", str(out),
                 "--border", "116"]) == 2
    assert "border (border_px, --border) 116 covers the whole field of view (its centre is " \
           "114 px from the edge)" in capsys.readouterr().err
    assert not out.exists()
    with pytest.raises(ValueError, match=r"border \(border_px, --border\) 60 covers the whole "
                       r"field of view"):
        FrameWarper(160, 120, options=BlendOptions("linear", border_px=60.0))
    # Just below: a sliver of each frame left, the mosaic black all the same (before: accepted).
    # Accepted up to the median distance to the edge, where the border covers half the frame.
    with pytest.raises(ValueError, match=r"border \(border_px, --border\) 59 covers 99 % of the "
                       r"field of view \(its centre is 60 px from the edge\): the frames would be "
                       r"drawn mostly black; give at most 20\.5 px"):
        FrameWarper(160, 120, options=BlendOptions("linear", border_px=59.0))
    FrameWarper(160, 120, options=BlendOptions("linear", border_px=20.5))


def test_bands_apply_to_multiband_blending_only(data, tmp_path, capsys):
    for extra, what in ((["--bands", "3"], "the method's own blending"),
                        (["--blend", "linear", "--bands", "3"], "--blend linear")):
        assert main(["run", str(data / "feto"), "--method", "emt", "--out",
                     str(tmp_path / "o"), *extra]) == 2
        assert (f"--bands sets the pyramid levels of --blend multiband; it does not apply to "
                f"{what}") in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_robot_file_only_for_the_robot_methods_and_inside_the_dataset(data, tmp_path, capsys):
    assert main(["run", str(data / "pcle"), "--method", "ncc", "--out", str(tmp_path / "o"),
                 "--robot-file", "robot_noisy.csv"]) == 2
    assert ("--robot-file applies to the methods that use the robot (kalman-robot, robot), "
            "not ncc") in capsys.readouterr().err
    outside = tmp_path / "robot.csv"
    outside.write_text((data / "pcle" / "robot.csv").read_text())
    assert main(["run", str(data / "pcle"), "--method", "robot", "--out", str(tmp_path / "o"),
                 "--robot-file", ""]) == 2  # (was taken for robot.csv)
    assert "the robot file must be named relative to the dataset folder" in \
        capsys.readouterr().err
    for name in (str(outside), "../robot.csv", ""):
        with pytest.raises(ValueError, match=r"the robot file must be named relative to the "
                           r"dataset folder and stay inside it \(e.g. robot_noisy.csv\), got "):
            read_dataset(data / "pcle", robot_file=name)
    assert main(["run", str(data / "pcle"), "--method", "robot", "--out", str(tmp_path / "o"),
                 "--robot-file", str(outside)]) == 2
    assert f"got {str(outside)!r}" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_view_interval_without_a_view_is_refused(tmp_path, capsys):
    """--view-interval was checked only with --preview / --serve-mosaic (and ignored without)."""
    assert main(["live", "127.0.0.1:1", "--method", "kalman-robot", "--camera", "c.yaml",
                 "--transform", "RobotToBase",
                 "--record", str(tmp_path / "r"), "--out", str(tmp_path / "o"),
                 "--view-interval", "2"]) == 2
    assert ("--view-interval applies to --preview / --serve-mosaic (the mosaic as it grows); "
            "neither is given") in capsys.readouterr().err
    # calibrate's tracker figures are an EM tracker's: not for the robot stream
    assert main(["live", "127.0.0.1:1", "--method", "kalman-robot", "--camera", "c.yaml",
                 "--transform", "RobotToBase", "--record", str(tmp_path / "r"), "--out",
                 str(tmp_path / "o"), "--calibration", "calibration.json"]) == 2
    assert ("--calibration (an EM tracker's, from calibrate) applies to lba-emt, not "
            "kalman-robot") in capsys.readouterr().err
    assert not (tmp_path / "r").exists() and not (tmp_path / "o").exists()


def test_robot_clock_offset_in_offline_runs(data, tmp_path):
    """`live` took --tracker-time-offset for the robot stream while `run --method kalman-robot`
    refused it: given, the recording with the robot's clock ahead gives the synchronous
    recording's result (to the interpolation's rounding)."""
    for name, extra in (("pcle", []), ("ahead", ["--tracker-time-offset", str(AHEAD_S)]),
                        ("ignored", [])):
        dataset = data / ("pcle" if name == "pcle" else "ahead")
        assert main(["--quiet", "run", str(dataset), "--method", "kalman-robot", "--out",
                     str(tmp_path / name), "--no-report", *extra]) == 0
    _, synced = read_homographies_csv(tmp_path / "pcle" / "homographies.csv")
    _, given = read_homographies_csv(tmp_path / "ahead" / "homographies.csv")
    _, ignored = read_homographies_csv(tmp_path / "ignored" / "homographies.csv")
    np.testing.assert_allclose(given, synced, atol=1e-6)
    assert np.abs(ignored - synced).max() > 1.0  # px: the offset matters here
    report = json.loads((tmp_path / "ahead" / "report.json").read_text())
    assert report["tracker_time_offset_s"] == AHEAD_S
    with pytest.raises(ValueError, match=r"robot.csv \(timestamps shifted by -5 s, the clock "
                       r"offset\): none of the 20 frames lies in the robot's time span .*: check "
                       r"the clock offset given \(--tracker-time-offset; calibrate measures the "
                       r"tracker's\)$"):
        read_dataset(data / "pcle", robot_time_offset=5.0)


def test_checkerboard_options_name_themselves(tmp_path, capsys):
    """A principal point far outside the frame blamed the lens ('not invertible'); a focal
    factor of 1e-6 wrote frames where the board is a dot."""
    with pytest.raises(ValueError, match=r"CheckerboardOptions.principal_offset_px: the "
                       r"principal point must stay in the middle half of the 480x480 frame "
                       r"\(\|offset\| <= 150 px\), got 1000000000.0"):
        CheckerboardOptions(principal_offset_px=1e9).validate()
    CheckerboardOptions(principal_offset_px=-150).validate()
    assert main(["simulate", "checkerboard", str(tmp_path / "cb"), "--focal-factor",
                 "1e-6"]) == 2
    assert ("--focal-factor: a 2 mm square at the farthest views (36 mm) would be 2.67e-05 px "
            "wide with focal factor 1e-06, under the 6 px the corner finder needs: raise "
            "--focal-factor or --square-mm, or lower --distance-mm") in capsys.readouterr().err
    assert not (tmp_path / "cb").exists()


def test_a_file_system_taking_no_files_is_named(capsys):
    """/proc refuses new entries with ENOENT, which read 'No such file or directory' for a
    folder that exists."""
    assert main(["simulate", "fetoscopy", "/proc/fusedmosaic-test", "--n-frames", "3"]) == 2
    assert ("/proc/fusedmosaic-test: cannot write in /proc (the dataset folder is created "
            "there): the file system there takes no new files") in capsys.readouterr().err


def test_a_folder_where_an_input_file_belongs_is_named_as_such(data, tmp_path, capsys):
    """The table, hand-eye and evaluation inputs said 'file not found' for a folder there (the
    second read's io._table.require_file, now used by all of them)."""
    from fusedmosaic.io import read_hand_eye, read_tracking_csv

    (tmp_path / "hand_eye.txt").mkdir()
    (tmp_path / "tracking.csv").mkdir()
    for read, name in ((read_hand_eye, "hand_eye.txt"), (read_tracking_csv, "tracking.csv")):
        with pytest.raises(ValueError, match=rf"{name}: is a folder; expected a file$"):
            read(tmp_path / name)
    out = tmp_path / "out"
    (out / "homographies.csv").mkdir(parents=True)
    assert main(["evaluate", str(out), "--truth", str(data / "feto"), "--no-report"]) == 2
    assert f"{out / 'homographies.csv'}: is a folder; expected a file" in capsys.readouterr().err


def test_run_alpha_writes_the_coverage_as_alpha(data, tmp_path):
    """run --alpha: mosaic.png's alpha channel is report.json's covered_fraction."""
    import cv2

    out = tmp_path / "o"
    assert main(["--quiet", "run", str(data / "pcle"), "--method", "ncc", "--out", str(out),
                 "--alpha", "--no-report"]) == 0
    image = cv2.imread(str(out / "mosaic.png"), cv2.IMREAD_UNCHANGED)
    mosaic = json.loads((out / "report.json").read_text())["mosaic"]
    assert mosaic["alpha"] is True and image.shape[2] == 4
    assert set(np.unique(image[:, :, 3])) == {0, 255}
    assert (image[:, :, 3] == 255).mean() == pytest.approx(mosaic["covered_fraction"])
    assert (image[:, :, :3][image[:, :, 3] == 0] == 0).all()  # uncovered: black, transparent


def test_report_json_always_lists_warnings(data, tmp_path):
    """pairwise's report.json had no `warnings` key (every other method wrote [])."""
    out = tmp_path / "o"
    assert main(["--quiet", "run", str(data / "feto"), "--method", "pairwise", "--out",
                 str(out), "--no-report"]) == 0
    assert isinstance(json.loads((out / "report.json").read_text())["warnings"], list)


def test_live_lba_emt_without_hand_eye_is_warned(data, tmp_path, capsys):
    """live took the tracker's sensor as the camera without a word when --hand-eye was left
    out (the README's lines left it out: e_M 6.8 px against 0.37 on simulated data). Refused
    here before connecting (an existing recording folder); the warning comes first."""
    (tmp_path / "rec").mkdir()
    (tmp_path / "rec" / "notes.txt").write_text("mine")
    argv = ["live", "127.0.0.1:1", "--camera", str(data / "feto" / "camera.yaml"),
            "--transform", "SensorToTracker", "--record", str(tmp_path / "rec"), "--out",
            str(tmp_path / "out")]
    assert main(argv) == 2
    assert "live: no --hand-eye: the tracker's sensor is taken as the camera" in \
        capsys.readouterr().err
    assert main([*argv, "--hand-eye", str(data / "feto" / "hand_eye.txt")]) == 2
    assert "--hand-eye" not in capsys.readouterr().err
