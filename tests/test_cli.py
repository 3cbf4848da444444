"""End to end through the command line: simulate -> evaluate (issue: Foundation, Done-when)."""

import json

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


def test_run_with_motion_sigma_from_an_independent_recording(datasets, tmp_path, capsys):
    feto = datasets / "feto"
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
