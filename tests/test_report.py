"""report.md and plots (evaluation/report.py), and the CLI around them: run with --video and
the report, evaluate --compare, --quiet, the end summary."""

import json
import re
import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from fusedmosaic import _core
from fusedmosaic.cli import main
from fusedmosaic.evaluation.report import (
    RunRecord,
    camera_plane_distances,
    load_run,
    load_truth,
    plane_azimuth_elevation_distance,
    plane_history_per_frame,
    write_report,
)
from fusedmosaic.io import read_homographies_csv, write_homographies_csv
from fusedmosaic.runner import playback_rate
from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

SIM = FetoscopyOptions(motion="handheld", n_frames=24, width=200, height=200, seed=4)


@pytest.fixture(scope="session")
def dataset(tmp_path_factory):
    return simulate_fetoscopy(tmp_path_factory.mktemp("report") / "data", SIM)


@pytest.fixture(scope="session")
def emt_run(dataset, tmp_path_factory):
    """`fusedmosaic run` with every output on (the fastest pose method)."""
    out = tmp_path_factory.mktemp("runs") / "emt"
    argv = ["run", str(dataset), "--method", "emt", "--out", str(out), "--blend", "multiband",
            "--border", "1.5", "--video", str(out / "creation.mp4")]
    return out, argv


def linked_files(md: Path) -> list[Path]:
    links = re.findall(r"\]\(([^)]+)\)", md.read_text())
    return [md.parent / link for link in links]


# -- geometry of the plots ---------------------------------------------------------------------


def test_plane_azimuth_elevation_distance_eq31():
    # SYN: the plane z = 30 mm facing the virtual camera, pi = n / d = (0, 0, -1/30)
    np.testing.assert_allclose(plane_azimuth_elevation_distance([0, 0, -1 / 30]), [0, 0, 30],
                               atol=1e-12)
    p = np.array([1.0, 2.0, 10.0])  # the plane's closest point to the camera
    pi = -p / (p @ p)  # n.X + d = 0 through p with normal along p
    az, elev, dist = plane_azimuth_elevation_distance(pi)
    assert az == pytest.approx(np.degrees(np.arctan2(2.0, 10.0)))
    assert elev == pytest.approx(np.degrees(np.arctan2(1.0, np.hypot(10.0, 2.0))))
    assert dist == pytest.approx(np.sqrt(105.0))
    assert plane_azimuth_elevation_distance(np.tile(pi, (4, 1))).shape == (4, 3)


def test_camera_plane_distance_matches_core():
    rng = np.random.default_rng(0)
    poses = np.hstack([rng.normal(0, 0.2, (20, 3)), rng.normal(0, 5, (20, 3))])
    poses[3] = np.nan
    plane = np.array([0.001, -0.002, -1 / 30])
    d = camera_plane_distances(poses, plane)
    assert np.isnan(d[3])
    expected = [_core.camera_plane_distance(p, plane) for k, p in enumerate(poses) if k != 3]
    np.testing.assert_allclose(np.delete(d, 3), expected, rtol=1e-10)


def test_plane_history_formats():
    rows = [[2, 0.0, 0.0, -0.05], [4, 0.0, 0.0, -0.04]]
    per_frame = plane_history_per_frame(rows, 6)
    assert np.isnan(per_frame[:2]).all()
    np.testing.assert_array_equal(per_frame[2:4, 2], [-0.05, -0.05])
    np.testing.assert_array_equal(per_frame[4:, 2], [-0.04, -0.04])
    dicts = [{"frame": 2, "plane": [0.0, 0.0, -0.05]}, {"frame": 4, "plane": [0.0, 0.0, -0.04]}]
    np.testing.assert_array_equal(plane_history_per_frame(dicts, 6), per_frame)
    full = np.tile([0.0, 0.0, -0.05], (6, 1))
    np.testing.assert_array_equal(plane_history_per_frame(full.tolist(), 6), full)
    assert plane_history_per_frame(None, 6) is None


def test_report_from_records(dataset, tmp_path):
    truth = load_truth(dataset)
    assert truth.poses is not None and truth.plane is not None and truth.tracker_poses is not None
    shift = np.tile(np.eye(3), (len(truth.homographies), 1, 1))
    shift[:, 0, 2] = np.linspace(0, 6, len(shift))  # drifts to 6 px in the reference
    noisy = shift @ truth.homographies
    runs = [RunRecord("exact", truth.homographies, poses=truth.poses, plane=truth.plane,
                      timings={"features": 1.0, "optimisation": 0.5}),
            RunRecord("drifting", noisy, skipped={3: "non-convex footprint"},
                      timings={"features": 2.0})]
    md = write_report(tmp_path, runs, truth, title="two methods")
    text = md.read_text()
    for name in ("errors", "poses", "plane", "distance", "trajectory", "timing"):
        assert f"plots/{name}.png" in text
    for path in linked_files(md):
        image = cv2.imread(str(path))
        assert image is not None and image.shape[0] > 200, path
    rows = [line for line in text.splitlines() if line.startswith("| exact")
            or line.startswith("| drifting")]
    e_exact, e_drift = (float(r.split("|")[4]) for r in rows[:2])
    assert e_exact == 0.0 and e_drift == pytest.approx(3.0, abs=0.01)  # mean of 0..6 px
    assert "- frame 3: non-convex footprint" in text
    assert "| truth | " in text  # plane table row (Eq. 31)


# -- through the CLI ---------------------------------------------------------------------------


def test_run_writes_mosaic_video_and_report(emt_run, dataset, capsys):
    out, argv = emt_run
    assert main(argv) == 0
    said = capsys.readouterr().out
    assert re.search(rf"emt: placed {SIM.n_frames}/{SIM.n_frames} frames -> .* \(e_M = ", said)
    for name in ("mosaic.png", "report.md", "creation.mp4"):
        assert str(out / name) in said
    report = json.loads((out / "report.json").read_text())
    mosaic = report["mosaic"]
    assert mosaic["blend"] == "multiband" and mosaic["border_px"] == 1.5
    image = cv2.imread(str(out / "mosaic.png"))
    assert image.shape[:2] == (mosaic["height"], mosaic["width"])
    assert mosaic["video"]["frames"] == SIM.n_frames
    assert mosaic["video"]["blend"] == "linear"  # multiband needs every frame: said so
    capture = cv2.VideoCapture(str(out / "creation.mp4"))  # plays at the recording's rate
    assert capture.get(cv2.CAP_PROP_FPS) == pytest.approx(SIM.fps) == mosaic["video"]["fps"]
    capture.release()
    for stage in ("features", "compose_mosaic", "video", "report"):
        assert stage in report["timings_s"]
    md = out / "report.md"
    links = linked_files(md)
    assert {p.name for p in links} >= {"mosaic.png", "creation.mp4", "errors.png", "poses.png",
                                       "plane.png", "distance.png", "timing.png"}
    assert all(p.is_file() and p.stat().st_size > 1000 for p in links)
    cap = cv2.VideoCapture(str(out / "creation.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == SIM.n_frames
    assert not [p for p in out.parent.iterdir() if ".tmp" in p.name]


def test_evaluate_compare_writes_report(emt_run, dataset, tmp_path, capsys):
    out, argv = emt_run
    if not (out / "homographies.csv").is_file():
        assert main(argv + ["--quiet"]) == 0
    other = tmp_path / "shifted"
    shutil.copytree(out, other)
    ids, G = read_homographies_csv(other / "homographies.csv")
    G = np.array([[1.0, 0, 2], [0, 1, 2], [0, 0, 1]]) @ G
    write_homographies_csv(other / "homographies.csv", ids, G)
    capsys.readouterr()
    assert main(["evaluate", str(out), "--truth", str(dataset), "--compare", str(other)]) == 0
    said = capsys.readouterr().out
    md = out / "evaluation.md"
    assert f"wrote {md}" in said
    text = md.read_text()
    assert "| emt (emt) |" in text and "| emt (shifted) |" in text  # same method, two folders
    assert (out / "evaluation_plots" / "errors.png").is_file()
    run = load_run(other, load_truth(dataset).frame_ids)
    assert run.label == "emt" and run.poses is not None and run.plane is not None


def test_quiet_prints_nothing(dataset, tmp_path, capsys):
    out = tmp_path / "q"
    assert main(["run", str(dataset), "--method", "emt", "--out", str(out), "--quiet",
                 "--no-report", "--blend", "average"]) == 0
    assert capsys.readouterr().out == ""
    assert (out / "mosaic.png").is_file() and not (out / "report.md").exists()


def test_canvas_budget_skips_the_mosaic_but_keeps_the_estimates(dataset, tmp_path, capsys):
    out = tmp_path / "b"
    with warnings.catch_warnings():
        warnings.simplefilter("default")  # as outside pytest: the CLI prints it
        code = main(["run", str(dataset), "--method", "emt", "--out", str(out),
                     "--max-canvas-pixels", "1000", "--video", str(out / "v.mp4")])
    assert code == 0
    captured = capsys.readouterr()
    assert re.search(r"fusedmosaic: warning: .*b: mosaic.png and .*v.mp4 not written: mosaic "
                     r"canvas of \d+ x \d+ pixels .* exceeds the budget of 1000 pixels .* The "
                     r"estimates \(homographies.csv, report.json, ...\) are written.",
                     captured.err)
    assert "mosaic  not written (above the canvas budget: see report.json)" in captured.out
    assert not (out / "mosaic.png").exists() and not (out / "v.mp4").exists()
    report = json.loads((out / "report.json").read_text())
    assert "exceeds the budget of 1000 pixels" in report["mosaic"]["skipped"]
    assert report["mosaic"]["file"] is None and report["mosaic"]["video"]["file"] is None
    assert "mosaic.png" not in report["outputs"]
    ids, G = read_homographies_csv(out / "homographies.csv")
    assert len(G) == report["frames"] and np.isfinite(G).all()
    assert "Mosaic not written: mosaic canvas of" in (out / "report.md").read_text()


def test_demo_says_where_to_look(tmp_path, capsys):
    """`fusedmosaic demo` end to end on a short sequence: every file it points at exists."""
    assert main(["demo", "--out", str(tmp_path / "demo"), "--frames", "50"]) == 0
    said = capsys.readouterr().out
    pointed = re.findall(r"^  (\S+)  ", said, flags=re.MULTILINE)
    names = {Path(p).name for p in pointed}
    assert names == {"report.md", "mosaic.png", "mosaic_seams.png", "creation.mp4"}
    assert all(Path(p).is_file() and Path(p).stat().st_size > 1000 for p in pointed)
    assert re.search(r"50/50 frames placed, e_M = \d+\.\d+ px", said)


def test_creation_video_plays_at_the_recordings_frame_rate():
    times = np.arange(20) / 10.0  # a 10 frames/s pCLE recording, one frame dropped
    assert playback_rate(np.delete(times, 7)) == pytest.approx(10.0)
    assert playback_rate(np.arange(5) / 1000.0) == 60.0  # bounded for players
    assert playback_rate(np.array([3.0])) == 25.0


def test_video_never_replaces_a_file_no_run_wrote(dataset, tmp_path, capsys):
    """--video onto the dataset's own files or a user's clip is refused before any work; a
    later run into the same OUT replaces the video its earlier run wrote."""
    dataset_video = dataset / "frames" / "clip.mp4"
    clip = tmp_path / "clip.mp4"
    clip.write_bytes(b"the user's own clip")
    run = ["run", str(dataset), "--method", "emt", "--no-report", "--out"]
    assert main([*run, str(tmp_path / "a"), "--video", str(dataset_video)]) == 2
    assert ("the video would be written inside the dataset: its path is inside the dataset "
            "folder" in capsys.readouterr().err)
    assert main([*run, str(tmp_path / "a"), "--video", str(clip)]) == 2
    assert (f"{clip}: exists and no earlier run into {tmp_path / 'a'} wrote it"
            in capsys.readouterr().err)
    assert clip.read_bytes() == b"the user's own clip" and not (tmp_path / "a").exists()
    mine = tmp_path / "videos" / "creation.mp4"
    mine.parent.mkdir()
    for _ in range(2):  # written, then replaced by the next run into the same OUT
        assert main([*run, str(tmp_path / "b"), "--video", str(mine), "--quiet"]) == 0
        assert cv2.VideoCapture(str(mine)).get(cv2.CAP_PROP_FRAME_COUNT) == SIM.n_frames
    assert main([*run, str(tmp_path / "c"), "--video", str(mine)]) == 2  # another OUT's video
    assert "exists and no earlier run into" in capsys.readouterr().err


def test_run_report_lists_every_frame_left_out_of_the_mosaic(tmp_path):
    """Black frames placed from the tracker are left out of the mosaic (report.json
    mosaic.skipped_frames, the summary's 'N frame(s) left out'), but report.md listed only the
    canvas's own screening and said nothing of them (review)."""
    from fusedmosaic.runner import run_dataset
    from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

    root = simulate_fetoscopy(tmp_path / "d", FetoscopyOptions(
        n_frames=12, laps=12 / 37.5, width=160, height=160, black_frames=[5, 6]))
    run_dataset(root, "emt", tmp_path / "out", progress=False)
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert sorted(report["mosaic"]["skipped_frames"]) == ["5", "6"]
    md = (tmp_path / "out" / "report.md").read_text()
    assert "## Frames left out of the mosaic (emt)" in md
    for k in (5, 6):
        assert f"- frame {k}: {report['mosaic']['skipped_frames'][str(k)]}" in md
