"""End to end through the command line: simulate -> evaluate (issue: Foundation, Done-when)."""

import json
import shutil

import cv2
import numpy as np
import pytest

from fusedmosaic.cli import main
from fusedmosaic.io import read_dataset, read_homographies_csv, write_homographies_csv


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    assert main(["--quiet", "simulate", "fetoscopy", str(root / "feto"), "--n-frames", "12"]) == 0
    assert main(["--quiet", "simulate", "pcle", str(root / "pcle"), "--n-frames", "12"]) == 0
    return root


@pytest.mark.parametrize("kind", ["feto", "pcle"])
def test_truth_scores_zero_and_a_two_pixel_shift_scores_two(datasets, kind, tmp_path):
    data = datasets / kind
    ids, G = read_homographies_csv(data / "ground_truth.csv")
    exact, shifted = tmp_path / "exact", tmp_path / "shifted"
    exact.mkdir()
    shifted.mkdir()
    write_homographies_csv(exact / "homographies.csv", ids, G)
    shift = np.array([[1.0, 0, 2.0], [0, 1, 0], [0, 0, 1]])
    write_homographies_csv(shifted / "homographies.csv", ids, np.einsum("ij,njk->nik", shift, G))
    assert main(["--quiet", "evaluate", str(exact), "--truth", str(data),
                 "--compare", str(shifted)]) == 0
    report = json.loads((exact / "evaluation.json").read_text())
    first, second = report["results"]
    assert first["e_M_px"] < 1e-6 and first["unplaced"] == 0
    assert second["e_M_px"] == pytest.approx(2.0, abs=0.01)
    if kind == "pcle":  # translation methods also get µm statistics and a Wilcoxon test
        assert first["position_all_um"]["mean"] < 1e-6
        pixel = read_dataset(data).camera.pixel_size_um
        assert second["position_all_um"]["mean"] == pytest.approx(2.0 * pixel, rel=1e-6)
        assert report["wilcoxon"][0]["n"] == 12


def test_simulate_black_frames_flag_uses_the_paper_list(tmp_path):
    out = tmp_path / "blk"
    assert main(["--quiet", "simulate", "fetoscopy", str(out), "--n-frames", "55",
                 "--black-frames"]) == 0
    ds = read_dataset(out)
    assert ds.frames[7].max() == 0 and ds.frames[11].max() == 0 and ds.frames[6].max() > 0


def test_evaluate_bad_input(datasets, tmp_path, capsys):
    assert main(["evaluate", str(tmp_path), "--truth", str(datasets / "feto")]) == 2
    assert "homographies.csv: file not found" in capsys.readouterr().err
    # frames of another sequence: how many, not only the first 5 (audit)
    write_homographies_csv(tmp_path / "homographies.csv", np.arange(40),
                           np.repeat(np.eye(3)[None], 40, axis=0))
    assert main(["evaluate", str(tmp_path), "--truth", str(datasets / "feto")]) == 2
    assert ("(missing 0 frames [], unexpected 28 frames [12, 13, 14, 15, 16, ...])"
            in capsys.readouterr().err)
    # a NaN is not an empty field
    rows = (tmp_path / "homographies.csv").read_text().splitlines()
    rows[1] = ",".join(["0", "nan", *rows[1].split(",")[2:]])
    (tmp_path / "homographies.csv").write_text("\n".join(rows) + "\n")
    assert main(["evaluate", str(tmp_path), "--truth", str(datasets / "feto")]) == 2
    assert "row 2: h00 empty or NaN; leave all of" in capsys.readouterr().err


def test_run_with_motion_sigma_from_an_independent_recording(datasets, tmp_path, capsys):
    # the SYN pace (the fixture's 12 frames over 4 laps are 120 degrees apart: no plane in
    # front of the cameras for lba-emt's start-up, ba-emt 277 px)
    feto = tmp_path / "feto"
    assert main(["--quiet", "simulate", "fetoscopy", str(feto), "--n-frames", "12",
                 "--laps", "0.32"]) == 0
    other = tmp_path / "calibration"
    assert main(["--quiet", "simulate", "fetoscopy", str(other), "--n-frames", "20",
                 "--seed", "7"]) == 0
    out = tmp_path / "lba"
    assert main(["--quiet", "run", str(feto), "--method", "lba-emt", "--out", str(out),
                 "--no-report", "--motion-sigma-from", str(other)]) == 0
    sigma = json.loads((out / "report.json").read_text())["parameters"]["motion_sigma"]
    truth = np.loadtxt(other / "truth_poses.csv", delimiter=",", skiprows=1)[:, 1:]
    second = truth[2:, 3:5] - 2 * truth[1:-1, 3:5] + truth[:-2, 3:5]  # SYN: no rotation
    np.testing.assert_allclose(sigma[3:5], np.sqrt((second**2).mean(axis=0)), rtol=1e-9)
    (other / "truth_poses.csv").unlink()
    assert main(["run", str(feto), "--method", "lba-emt", "--out", str(tmp_path / "x"),
                 "--motion-sigma-from", str(other)]) == 2
    assert "truth_poses.csv: no reference poses to estimate the motion prior" in (
        capsys.readouterr().err)
    assert main(["run", str(feto), "--method", "pairwise", "--out", str(tmp_path / "y"),
                 "--motion-sigma-from", str(other)]) == 2
    assert "--motion-sigma-from applies to ba-emt and lba-emt" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_run_feature_options(datasets, tmp_path, capsys):
    feto = tmp_path / "feto"  # a slower sweep than the fixture's: the frames overlap
    assert main(["--quiet", "simulate", "fetoscopy", str(feto), "--n-frames", "12",
                 "--laps", "0.3"]) == 0
    out = tmp_path / "orb"
    assert main(["--quiet", "run", str(feto), "--method", "ba-emt", "--out", str(out),
                 "--no-report", "--detector", "orb", "--max-features", "800",
                 "--detect-max-side", "300", "--clahe", "--orb-fast-threshold", "10"]) == 0
    features = json.loads((out / "report.json").read_text())["parameters"]["features"]
    assert features["detector"] == "orb" and features["max_features"] == 800
    assert features["orb_fast_threshold"] == 10
    assert features["max_image_side"] == 300 and features["clahe"] is True
    out = tmp_path / "emt"
    assert main(["--quiet", "run", str(feto), "--method", "emt", "--out", str(out),
                 "--no-report", "--detector", "orb"]) == 0
    parameters = json.loads((out / "report.json").read_text())["parameters"]
    assert parameters["pair_selection"] == "emt-guided"  # the EMT baseline's own default
    for method, extra in (("pairwise", []), ("lba-emt", ["--motion-sigma-from", str(feto)])):
        out = tmp_path / method
        assert main(["--quiet", "run", str(feto), "--method", method, "--out", str(out),
                     "--no-report", "--detector", "orb", *extra]) == 0
        parameters = json.loads((out / "report.json").read_text())["parameters"]
        assert parameters["features"]["detector"] == "orb"
        if extra:  # both overrides reach SequentialOptions
            assert parameters["motion_sigma"] is not None
    for extra, message in (
            (["--method", "ncc", "--detector", "orb"],
             "--detector / --max-features / --clahe / --detect-max-side / "
             "--orb-fast-threshold / --keep-specular apply to lba-emt"),
            (["--method", "lba-emt", "--detector", "orb", "--orb-fast-threshold", "300"],
             "--orb-fast-threshold must be an integer in 1..255 (grey levels), got 300"),
            (["--method", "pairwise", "--max-features", "0"],
             "--max-features must be an integer in 1..1000000 (keypoints per frame), got 0"),
            (["--method", "lba-emt", "--max-features", "5000000000"],
             "--max-features must be an integer in 1..1000000 (keypoints per frame), got "
             "5000000000"),
            (["--method", "pairwise", "--orb-fast-threshold", "10"],
             "--orb-fast-threshold applies to --detector orb (SIFT has no FAST threshold)"),
            (["--method", "lba-emt", "--detect-max-side", "16"],
             "--detect-max-side must be >= 32 (pixels), an integer; got 16"),
            (["--method", "pairwise", "--detect-max-side", "16"],
             "--detect-max-side must be >= 32")):
        _run_refused(feto, tmp_path, capsys, extra, message)


def _run_refused(dataset, tmp_path, capsys, extra: list[str], message: str) -> None:
    """`fusedmosaic run DATASET --out bad EXTRA...` exits 2 with `message`, writing nothing."""
    assert main(["run", str(dataset), "--out", str(tmp_path / "bad"), *extra]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_simulate_warns_when_consecutive_frames_barely_overlap(tmp_path, capsys):
    assert main(["simulate", "fetoscopy", str(tmp_path / "a"), "--n-frames", "20"]) == 0
    err = capsys.readouterr().err
    assert ("warning: consecutive frames move by 282 px (median), more than half of the 400 "
            "px side") in err
    assert "(e.g. --laps 0.53 for 20 frames)" in err
    assert main(["simulate", "fetoscopy", str(tmp_path / "b"), "--n-frames", "20", "--laps",
                 "0.53"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_run_lba_emt_presets(datasets, tmp_path, capsys):
    feto = tmp_path / "feto"
    assert main(["--quiet", "simulate", "fetoscopy", str(feto), "--n-frames", "12",
                 "--laps", "0.3"]) == 0
    out = tmp_path / "phb"
    assert main(["--quiet", "run", str(feto), "--method", "lba-emt", "--out", str(out),
                 "--no-report", "--preset", "phb", "--loop-pairs", "1", "--detector",
                 "orb"]) == 0
    parameters = json.loads((out / "report.json").read_text())["parameters"]
    assert (parameters["window_size"], parameters["num_new"], parameters["num_clusters"],
            parameters["frames_per_cluster"]) == (3, 1, 3, 3)
    assert parameters["loop_pairs"] == 1 and parameters["features"]["detector"] == "orb"
    assert parameters["matching"]["guided_sift"] is False
    out = tmp_path / "guided"
    assert main(["--quiet", "run", str(feto), "--method", "lba-emt", "--out", str(out),
                 "--no-report", "--guided-sift"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["parameters"]["matching"]["guided_sift"] is True
    assert report["parameters"]["features"]["detector"] == "sift"
    assert report["placed"] == 12
    for extra, message in ((["--method", "ba-emt", "--preset", "phb"],
                            "--preset / --loop-pairs / --guided-sift apply to lba-emt, not "
                            "ba-emt"),
                           (["--method", "pairwise", "--guided-sift"],
                            "--guided-sift apply to lba-emt, not pairwise"),
                           (["--method", "lba-emt", "--loop-pairs", "-1"],
                            "--loop-pairs must be >= 0, got -1")):
        _run_refused(feto, tmp_path, capsys, extra, message)


def test_flags_are_named_in_errors(datasets, tmp_path, capsys):
    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0 and capsys.readouterr().out.startswith("fusedmosaic 0.")
    with pytest.raises(SystemExit):  # argparse choices: the help lists them, errors name them
        main(["simulate", "fetoscopy", str(tmp_path / "s"), "--motion", "circular"])
    assert "argument --motion: invalid choice: 'circular'" in capsys.readouterr().err
    assert main(["simulate", "fetoscopy", str(tmp_path / "s"), "--n-frames", "0"]) == 2
    assert "fusedmosaic: error: --n-frames: must be >= 1, got 0" in capsys.readouterr().err
    assert main(["demo", "--out", str(tmp_path / "s"), "--n-frames", "0"]) == 2
    assert "fusedmosaic: error: --frames must be >= 2, got 0" in capsys.readouterr().err
    feto = datasets / "feto"
    for extra, message in ((["--border", "-1"], "--border must be >= 0 (pixels), got -1.0"),
                           (["--blend", "multiband", "--bands", "0"],
                            "--bands must be in 1..10, got 0"),
                           (["--tile-size", "3"], "--tile-size must be in 64..8192 (pixels; a "
                            "tile's accumulator is tile size squared x 16 bytes for colour), "
                            "got 3"),
                           (["--max-canvas-pixels", "0"], "--max-canvas-pixels must be > 0")):
        assert main(["run", str(feto), "--method", "emt", "--out", str(tmp_path / "o"),
                     *extra]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "s").exists() and not (tmp_path / "o").exists()
    # position errors in µm need a pixel size: a fetoscopy truth is refused, not ignored
    out = tmp_path / "exact"
    out.mkdir()
    write_homographies_csv(out / "homographies.csv", *read_homographies_csv(
        feto / "ground_truth.csv"))
    assert main(["evaluate", str(out), "--truth", str(feto), "--positions", "3"]) == 2
    assert "camera.yaml: no pixel_size_um, so no position errors" in capsys.readouterr().err


def test_run_dataset_checks_compositing_options_before_estimating(datasets, tmp_path,
                                                                  monkeypatch):
    from fusedmosaic import runner
    from fusedmosaic.compositing import BlendOptions, CanvasOptions
    from fusedmosaic.runner import run_dataset

    def refuse(*args, **kwargs):
        raise AssertionError("the method ran")

    monkeypatch.setattr(runner.methods, "get", lambda name: refuse)

    for kwargs, message in (({"blend": BlendOptions(border_px=-2)}, "border_px must be >= 0"),
                            ({"blend": "mean"}, "blend must be one of"),
                            ({"canvas": CanvasOptions(tile_size=8)}, "tile_size must be in 64..")):
        with pytest.raises(ValueError, match=message):
            run_dataset(datasets / "feto", "pairwise", tmp_path / "o", progress=False, **kwargs)
    assert not (tmp_path / "o").exists()


def test_run_on_a_video_without_frames_csv_takes_its_frame_rate(tmp_path, capsys):
    """A 30 fps video without frames.csv: its frames are timed at frame / 30 (the container's
    rate), not the contract's 25 fps default, which would misplace every tracker sample."""
    data = tmp_path / "video30"
    assert main(["--quiet", "simulate", "fetoscopy", str(data), "--n-frames", "40",
                 "--fps", "30"]) == 0
    frames = sorted((data / "frames").glob("*.png"))
    first = cv2.imread(str(frames[0]))
    writer = cv2.VideoWriter(str(data / "video.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 30.0,
                             (first.shape[1], first.shape[0]))
    for path in frames:
        writer.write(cv2.imread(str(path)))
    writer.release()
    shutil.rmtree(data / "frames")
    (data / "frames.csv").unlink()
    capsys.readouterr()
    assert main(["run", str(data), "--method", "ba-emt", "--out", str(tmp_path / "o"),
                 "--no-report"]) == 0
    assert "times   frame / 30 fps (the frame rate of video.avi; no frames.csv)" in (
        capsys.readouterr().out)
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert report["frame_times"] == "frame / 30 fps (the frame rate of video.avi; no frames.csv)"
    assert report["placed"] == 40
    assert report["metrics"]["e_M_px"] < 0.2  # against the simulator's truth (PNGs: 0.06 px)
    # At 25 fps the 40 frames would span 1.56 s, past the tracker's 1.41 s: refused, saying so.
    assert main(["run", str(data), "--method", "ba-emt", "--out", str(tmp_path / "o25"),
                 "--fps", "25"]) == 2
    assert "tracking.csv: 4 frames outside the tracker's time span" in capsys.readouterr().err
