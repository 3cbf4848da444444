"""Review C of the evaluation (`evaluate`, metrics, provenance, evaluation.md), findings 1-9:
the truth taken to the estimate's reference grid always, an output reference without a truth
row refused, --positions chosen among the frames with a truth, the drift ratio without the
reference frame's exact 0, another dataset's truth refused unless allowed, Wilcoxon ties within
rounding, evaluation.md with the µm statistics / tests / drift notes, an infinite drift ratio
explained, and ground_truth.csv alone differing only a note."""

import json
import shutil

import numpy as np
import pytest
from scipy import stats

from fusedmosaic.cli import main
from fusedmosaic.evaluation import compare_position_errors, drift_ratio, evaluate_output
from fusedmosaic.evaluation.metrics import drift_note, evenly_spaced, truth_in_reference
from fusedmosaic.io import read_homographies_csv, write_homographies_csv

N = 16  # frames of the simulated pCLE sequence


@pytest.fixture(scope="module")
def pcle(tmp_path_factory):
    """A small pCLE dataset and a robot run on it (with its report.json and fingerprint)."""
    root = tmp_path_factory.mktemp("review_c")
    assert main(["--quiet", "simulate", "pcle", str(root / "pcle"), "--n-frames", str(N),
                 "--width", "128", "--height", "112"]) == 0
    assert main(["--quiet", "run", str(root / "pcle"), "--method", "robot", "--out",
                 str(root / "robot"), "--no-report"]) == 0
    return root


def _copy_dataset(pcle, tmp_path, name="truth"):
    dst = tmp_path / name
    shutil.copytree(pcle / "pcle", dst)
    return dst


def _copy_output(pcle, tmp_path, name="out"):
    dst = tmp_path / name
    shutil.copytree(pcle / "robot", dst, ignore=shutil.ignore_patterns("evaluation*"))
    return dst


def _output(tmp_path, name, ids, G):
    """An output folder holding homographies.csv alone."""
    out = tmp_path / name
    out.mkdir()
    write_homographies_csv(out / "homographies.csv", ids, G)
    return out


def _evaluate(out, truth, *extra):
    return main(["--quiet", "evaluate", str(out), "--truth", str(truth), *extra])


def _result(out, index=0):
    return json.loads((out / "evaluation.json").read_text())["results"][index]


# ------------------------------------------------------------- 1: truth given in another grid


def test_a_truth_in_another_grid_scores_as_one_in_frame_0s(pcle, tmp_path, capsys):
    """Frame 0's truth not the identity (positions in a microscope image, seed 004 IV-A): the
    truth is taken to the estimate's reference grid, as it was for a reference r != 0 only.
    Before: the whole offset (here 250, -120 px) counted as error, e_M 280 instead of 7 px."""
    ids, G_true = read_homographies_csv(pcle / "pcle" / "ground_truth.csv")
    T = np.array([[1.0, 0, 250.0], [0, 1, -120.0], [0, 0, 1]])
    rebased, r = truth_in_reference(G_true, T @ G_true)
    assert r == 0
    np.testing.assert_allclose(rebased, G_true, atol=1e-9)

    moved = _copy_dataset(pcle, tmp_path)
    write_homographies_csv(moved / "ground_truth.csv", ids, T @ G_true)
    out = _copy_output(pcle, tmp_path)
    assert _evaluate(out, pcle / "pcle", "--no-report") == 0
    before = _result(out)
    assert _evaluate(out, moved, "--no-report") == 0
    after = _result(out)
    assert after["e_M_px"] == pytest.approx(before["e_M_px"], rel=1e-9, abs=1e-9)
    assert after["position_all_um"]["mean"] == pytest.approx(before["position_all_um"]["mean"],
                                                             rel=1e-9, abs=1e-9)
    assert before["e_M_px"] < 50  # (the offset is 275 px)


# --------------------------------------------- 2: output reference without a truth row: refused


def test_an_output_reference_the_truth_has_no_row_for_is_refused(pcle, tmp_path, capsys):
    """Frame 0 unplaced, frame 3 written as the identity (a late start), and the truth has no
    row for frame 3: before, scored in frame 0's grid (every e_j held frame 3's offset) with
    reference_frame 0 and no word."""
    ids, G_true = read_homographies_csv(pcle / "pcle" / "ground_truth.csv")
    G = np.linalg.inv(G_true[3]) @ G_true
    G /= G[:, 2:3, 2:3]
    G[0] = np.nan
    out = _output(tmp_path, "late", ids, G)
    assert _evaluate(out, pcle / "pcle", "--no-report") == 0  # the full truth: frame 3's grid
    assert _result(out)["reference_frame"] == int(ids[3])
    assert _result(out)["e_M_px"] < 1e-6
    sparse = _copy_dataset(pcle, tmp_path)
    G_sparse = G_true.copy()
    G_sparse[3] = np.nan
    write_homographies_csv(sparse / "ground_truth.csv", ids, G_sparse)
    (out / "evaluation.json").unlink()
    capsys.readouterr()
    assert _evaluate(out, sparse, "--no-report") == 2
    err = capsys.readouterr().err
    assert (f"fusedmosaic: error: {sparse / 'ground_truth.csv'}: the truth has no row for the "
            f"output's reference frame {ids[3]}") in err
    assert not (out / "evaluation.json").exists()


# ------------------------------------------------ 3: --positions among the frames with a truth


def test_positions_are_chosen_among_the_frames_with_a_truth(pcle, tmp_path, capsys):
    """A sparse truth (seed 004: n images): the N evenly spaced frames are chosen among the
    frames that have one, the first of them included; fewer than N such frames are refused.
    Before: frames without a truth were sampled, the statistics over fewer frames (n: 1)."""
    ids, G_true = read_homographies_csv(pcle / "pcle" / "ground_truth.csv")
    keep = np.array([0, 2, 5, 9, 10, 14])
    sparse = _copy_dataset(pcle, tmp_path)
    G_sparse = np.full_like(G_true, np.nan)
    G_sparse[keep] = G_true[keep]
    write_homographies_csv(sparse / "ground_truth.csv", ids, G_sparse)
    exact = _output(tmp_path, "exact", ids, G_true)
    shifted_G = G_true.copy()
    shifted_G[:, 0, 2] += np.arange(N) + 1.0
    shifted = _output(tmp_path, "shifted", ids, shifted_G)
    argv = ["--no-report", "--compare", str(shifted), "--positions", "4"]
    assert _evaluate(exact, sparse, *argv) == 0
    expected = keep[evenly_spaced(len(keep), 4)]
    assert expected.tolist() == [0, 5, 9, 14]
    report = json.loads((exact / "evaluation.json").read_text())
    for r in report["results"]:
        assert r["position_sampled_frames"] == ids[expected].tolist()
        assert r["position_sampled_um"]["n"] == 4
    assert report["wilcoxon"][0]["n"] == 4
    pixel = report["results"][1]["position_errors_um"][5] / 6.0  # frame 5 is 6 px off
    assert report["results"][1]["position_sampled_um"]["max"] == pytest.approx(15 * pixel)
    (exact / "evaluation.json").unlink()
    capsys.readouterr()
    assert _evaluate(exact, sparse, "--no-report", "--positions", "7") == 2
    err = capsys.readouterr().err
    assert (f"fusedmosaic: error: {sparse / 'ground_truth.csv'}: 6 of the {N} frames have a "
            "ground-truth homography, fewer than the 7 evenly spaced frames asked for") in err
    assert "give at most 6" in err
    assert not (exact / "evaluation.json").exists()


# ------------------------------------------------------ 4: drift ratio without the reference


def test_the_drift_ratio_leaves_out_the_reference_frames_exact_zero():
    """A constant error of 1 px on every frame but the reference: no drift, ratio 1. Before:
    2.0 over 8 frames, 1.5 over 12 (the reference's 0 in the first quarter's mean)."""
    for n in (8, 12, 60):
        e = np.ones(n)
        e[0] = 0.0
        assert drift_ratio(e) == pytest.approx(1.0), n
        assert drift_note(e) is None
    e = np.ones(16)
    e[:2] = np.nan  # frames 0-1 unplaced, frame 2 the reference
    e[2] = 0.0
    assert drift_ratio(e, reference=2) == pytest.approx(1.0)
    assert drift_ratio(e, reference=None) == pytest.approx(2.0)  # (kept when asked)
    real = np.array([1e-3, 0.2, 0.4])  # frame 0 really off: a real error, kept
    assert drift_ratio(real) == pytest.approx(400.0)
    # a quarter holding only the reference has no ratio, as before
    assert np.isnan(drift_ratio(np.array([0.0, 1.0, 2.0])))
    assert drift_note(np.array([0.0, 1.0, 2.0])).startswith("the first quarter (frame 0) holds "
                                                            "only the reference frame")


def test_evaluate_reports_drift_1_for_a_constant_error(pcle, tmp_path):
    ids, G_true = read_homographies_csv(pcle / "pcle" / "ground_truth.csv")
    G = G_true.copy()
    G[1:, 0, 2] += 1.0  # every frame but the reference 1 px off
    out = _output(tmp_path, "constant", ids, G)
    assert _evaluate(out, pcle / "pcle", "--no-report") == 0
    result = _result(out)
    assert result["drift_ratio"] == pytest.approx(1.0)
    assert result["e_j_px"][0] == 0.0 and result["e_j_px"][1] == pytest.approx(1.0)


# --------------------------------------------------------- 5: another dataset's truth refused


def test_another_datasets_truth_is_refused_unless_allowed(pcle, tmp_path, capsys):
    """camera.yaml or the frames' pixels differ: another dataset, refused (exit 2, nothing
    written) naming what differs; --allow-other-dataset scores it with the warning. A moved
    copy is fine. Without report.json a note says the provenance was not checked. Before:
    scored with a warning (none without report.json), exit 0."""
    out = _copy_output(pcle, tmp_path)
    other = tmp_path / "other"
    assert main(["--quiet", "simulate", "pcle", str(other), "--n-frames", str(N), "--width",
                 "128", "--height", "112", "--trajectory", "spiral"]) == 0
    capsys.readouterr()
    assert _evaluate(out, other, "--no-report") == 2
    err = capsys.readouterr().err
    assert err.startswith(f"fusedmosaic: error: {out / 'report.json'} records the dataset ")
    assert f"but {other} differs from it (pixels of the first, middle and last frame)" in err
    assert "--allow-other-dataset" in err and "\n" not in err.rstrip("\n")
    assert not (out / "evaluation.json").exists()
    with pytest.raises(ValueError, match="it is another dataset"):
        evaluate_output(out, other)

    assert _evaluate(out, other, "--no-report", "--allow-other-dataset") == 0
    err = capsys.readouterr().err
    assert err.startswith("fusedmosaic: warning: ") and "differs from it (pixels" in err
    assert "pixels of the first" in _result(out)["dataset_warning"]

    camera = _copy_dataset(pcle, tmp_path, "camera")
    (camera / "camera.yaml").write_text((camera / "camera.yaml").read_text() + "# edited\n")
    (out / "evaluation.json").unlink()
    assert _evaluate(out, camera, "--no-report") == 2
    assert "differs from it (camera.yaml)" in capsys.readouterr().err

    moved = _copy_dataset(pcle, tmp_path, "moved")  # the same dataset elsewhere: no word
    assert _evaluate(out, moved, "--no-report") == 0
    assert capsys.readouterr().err == ""
    assert not {"dataset_warning", "truth_note", "provenance_note"} & set(_result(out))

    bare = tmp_path / "bare"  # homographies.csv alone: nothing to check against
    bare.mkdir()
    shutil.copy(out / "homographies.csv", bare)
    assert _evaluate(bare, other, "--no-report") == 0
    assert capsys.readouterr().err == (
        f"fusedmosaic: note: {bare} has no report.json: which dataset the output was computed "
        f"from could not be checked against {other}\n")
    assert "could not be checked" in _result(bare)["provenance_note"]


# ------------------------------------------------------------- 6: Wilcoxon ties within rounding


def test_wilcoxon_counts_differences_within_rounding_as_ties():
    """Errors equal up to rounding (6e-8 µm) were 'significantly' different (p 0.0026); n
    counted the reference's 0 vs 0, which scipy does not rank."""
    rng = np.random.default_rng(3)
    a = rng.uniform(1, 10, 60)
    same = compare_position_errors(a, a + rng.uniform(-6e-8, 6e-8, 60))
    assert same["p_value"] == 1.0 and same["n"] == 60 and same["n_ranked"] == 0
    assert same["statistic"] == 0.0 and "nothing to rank" in same["note"]
    a = np.concatenate([[0.0], rng.uniform(1, 10, 12)])
    b = a + np.concatenate([[0.0], rng.uniform(0.5, 1, 12)])  # frame 0: the reference, 0 vs 0
    res = compare_position_errors(a, b)
    assert res["n"] == 13 and res["n_ranked"] == 12 and "note" not in res
    assert res["p_value"] == pytest.approx(stats.wilcoxon(a[1:], b[1:]).pvalue)
    assert res["p_value"] == pytest.approx(2 / 2**12)


# -------------------------------------------------------------------- 7 and 8: evaluation.md


def test_evaluation_md_holds_the_position_statistics_the_tests_and_the_drift_notes(
        pcle, tmp_path, capsys):
    """evaluation.md had neither the µm statistics nor the Wilcoxon p-values (seed 004's
    results), nor why a drift ratio is undefined."""
    ids, G_true = read_homographies_csv(pcle / "pcle" / "ground_truth.csv")
    out = _copy_output(pcle, tmp_path)
    early_G = G_true.copy()
    early_G[:, 0, 2] += np.arange(N) * 0.5
    early_G[N // 2:] = np.nan  # none placed in the last quarter: drift undefined
    early = _output(tmp_path, "early", ids, early_G)
    assert _evaluate(out, pcle / "pcle", "--compare", str(early), "--positions", "5") == 0
    md = (out / "evaluation.md").read_text()
    report = json.loads((out / "evaluation.json").read_text())
    first, second = report["results"]
    assert "## Position errors (µm)" in md and "## Wilcoxon signed-rank tests" in md
    s = first["position_sampled_um"]
    assert f"| robot | evenly spaced | {s['n']} | {s['mean']:.2f} | {s['max']:.2f} |" in md
    s = second["position_all_um"]
    assert f"| early | all | {s['n']} | {s['mean']:.2f} |" in md
    w = report["wilcoxon"][0]
    assert f"| robot | early | 5 evenly spaced | {w['n']} | {w['n_ranked']} |" in md
    assert f"{w['p_value']:.3g} |" in md
    assert second["drift_ratio"] is None
    assert f"**Drift ratio (early):** {second['drift_ratio_note']}" in md


def test_an_infinite_drift_ratio_has_a_note(pcle, tmp_path, capsys):
    """A frame of the last quarter placed at infinity: the ratio is inf (null in the JSON);
    before, without a drift_ratio_note."""
    e = np.ones(8)
    e[-1] = np.inf
    assert drift_ratio(e) == np.inf
    assert drift_note(e) == ("the last quarter (frames 6-7) holds a frame placed at infinity "
                             "(e_j inf): the ratio is infinite")
    out = _copy_output(pcle, tmp_path)
    text = (out / "homographies.csv").read_text().splitlines()
    text[-1] = f"{text[-1].split(',')[0]},0,0,1,0,1,0,1,0,0"  # w = 0 at pixel (0, 0)
    (out / "homographies.csv").write_text("\n".join(text) + "\n")
    assert main(["evaluate", str(out), "--truth", str(pcle / "pcle")]) == 0
    printed = capsys.readouterr().out
    assert "  drift inf: the last quarter" in printed
    result = _result(out)
    assert result["drift_ratio"] is None and "placed at infinity" in result["drift_ratio_note"]
    assert "placed at infinity" in (out / "evaluation.md").read_text()


# ------------------------------------------------------------ 9: ground_truth.csv alone changed


def test_a_changed_truth_file_alone_is_a_note_not_another_dataset(pcle, tmp_path, capsys):
    """Only ground_truth.csv differing (a corrected, extended or sparse truth for the same
    frames) warned "another dataset's ground truth"; now a note that the truth changed."""
    ids, G_true = read_homographies_csv(pcle / "pcle" / "ground_truth.csv")
    edited = _copy_dataset(pcle, tmp_path)
    G = G_true.copy()
    G[7] = np.nan  # a sparser truth
    write_homographies_csv(edited / "ground_truth.csv", ids, G)
    out = _copy_output(pcle, tmp_path)
    assert _evaluate(out, edited) == 0
    err = capsys.readouterr().err
    assert "warning" not in err and "another dataset" not in err
    assert err == (f"fusedmosaic: note: {edited / 'ground_truth.csv'} differs from the "
                   "ground_truth.csv of the dataset the output was computed from "
                   f"({out / 'report.json'}): the truth changed since the run\n")
    result = _result(out)
    assert "dataset_warning" not in result and "the truth changed" in result["truth_note"]
    assert "**Note:** " in (out / "evaluation.md").read_text()
