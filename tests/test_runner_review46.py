"""Review 46 (lead): the run's outputs as the CLI reports them."""

import pytest
from _faults import file_size_limit

from fusedmosaic.cli import main
from fusedmosaic.simulation import PcleOptions, simulate_pcle


@pytest.fixture(scope="module")
def pcle(tmp_path_factory):
    root = tmp_path_factory.mktemp("runner46") / "pcle"
    simulate_pcle(root, PcleOptions(width=128, height=112, n_frames=20, contact_loss=False,
                                    stick_slip=False))
    return root


def test_a_streamed_mosaic_that_cannot_be_written_names_outs_mosaic_png(pcle, tmp_path,
                                                                           capsys):
    """run --alpha (as a tiled mosaic) streams mosaic.png into the output folder's staging
    copy: a write error named that hidden path (".o.fusedmosaic.tmp-.../mosaic.png: File too
    large"). It names OUT's mosaic.png, and nothing is left behind."""
    out = tmp_path / "o"
    with file_size_limit(20_000):
        code = main(["--quiet", "run", str(pcle), "--method", "robot", "--out", str(out),
                     "--alpha", "--no-report"])
    err = capsys.readouterr().err
    assert code != 0
    assert f"{out / 'mosaic.png'}: the image could not be written (File too large" in err, err
    assert "fusedmosaic.tmp" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def feto(tmp_path_factory):
    root = tmp_path_factory.mktemp("runner46") / "feto"
    assert main(["--quiet", "simulate", "fetoscopy", str(root), "--n-frames", "8",
                 "--width", "160", "--height", "120", "--laps", "0.2"]) == 0
    return root


def test_plane_json_says_its_unit(feto, tmp_path):
    """ba fixes no scale: plane.json's distance_mm was 1.0, in units of the first camera's
    distance to the plane, with nothing saying so. Its "unit" says it (mm for ba-emt)."""
    import json

    units, keys = {}, {}
    for method in ("ba", "ba-emt"):
        out = tmp_path / method
        assert main(["--quiet", "run", str(feto), "--method", method, "--out", str(out),
                     "--no-report"]) == 0
        plane = json.loads((out / "plane.json").read_text())
        units[method], keys[method] = plane["unit"], sorted(plane)
    assert units["ba-emt"] == "mm"
    # (review 47: ba's keys said mm beside a unit saying not mm)
    assert keys["ba-emt"] == ["camera_plane_distance_mm", "distance_mm", "normal", "plane", "unit"]
    assert keys["ba"] == ["camera_plane_distance", "distance", "normal", "plane", "unit"]
    assert units["ba"].startswith("the first frame's camera frame, lengths in units of that "
                                  "camera's distance to the plane") and "not mm" in units["ba"]


def test_run_does_not_score_in_another_grid(pcle, tmp_path, capsys):
    """The robot starting late leaves frames 0-3 unplaced: frame 4 is the reference. With no
    truth row for it, run scored its frame-4-grid output against the truth in frame 0's grid
    (every e_j holding frame 4's offset: e_M 159.5 px for 0.46 on the review's data), where
    evaluate refuses. report.json now has no figures and says why; so does the summary."""
    import json
    import shutil

    import numpy as np

    data = tmp_path / "late"
    shutil.copytree(pcle, data)
    frame_times = np.loadtxt(data / "frames.csv", delimiter=",", skiprows=1)[:, 1]
    robot = (data / "robot.csv").read_text().splitlines()
    (data / "robot.csv").write_text("\n".join(
        [robot[0], *(r for r in robot[1:] if float(r.split(",")[0]) > frame_times[3] + 1e-3)])
        + "\n")
    truth = (data / "ground_truth.csv").read_text().splitlines()
    (data / "ground_truth.csv").write_text("\n".join(  # (empty fields: no truth there)
        [truth[0], *(r.split(",")[0] + "," * 9 if r.split(",")[0] in ("1", "2", "3", "4")
                     else r for r in truth[1:])]) + "\n")
    out = tmp_path / "o"
    assert main(["run", str(data), "--method", "robot", "--out", str(out), "--no-report",
                 "--allow-untracked"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["reference_frame"] == 4 and report["metrics"] is None
    assert report["metrics_note"].startswith("not scored: the truth has no row for the "
                                             "output's reference frame 4")
    assert "(e_M not scored: the truth has no row" in capsys.readouterr().out
