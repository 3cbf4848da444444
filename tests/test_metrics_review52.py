"""Review 52 of the evaluation (metrics, report, `evaluate`), findings F1 and F3-F5: a truth
without a row for the output's reference frame 0 refused (it was scored in whatever grid it is
in), frames placed at infinity ranked as the worst in the Wilcoxon test (they were dropped as
if unplaced), report.json's / report.md's max e_j and drift ratio consistent with e_M and
explained, and the drift note naming the reference frame when a quarter holds nothing else."""

import json
import shutil

import numpy as np
import pytest
from scipy import stats

from fusedmosaic.cli import main
from fusedmosaic.evaluation import compare_position_errors, drift_ratio, evaluate_output
from fusedmosaic.evaluation.metrics import (
    drift_note,
    frame_errors,
    run_metrics,
    scoring_truth,
    unscorable_reference,
)
from fusedmosaic.evaluation.report import RunRecord, TruthRecord, write_report
from fusedmosaic.io import read_homographies_csv, write_homographies_csv
from fusedmosaic.io.output import to_jsonable

N = 16  # frames of the simulated pCLE sequence
W, H = 128, 112


@pytest.fixture(scope="module")
def pcle(tmp_path_factory):
    """A 16-frame pCLE dataset with a robot run on it, and a 6-frame one run with its report
    (a quarter is one frame: no drift ratio)."""
    root = tmp_path_factory.mktemp("review52")
    for name, n in (("pcle", N), ("pcle6", 6)):
        assert main(["--quiet", "simulate", "pcle", str(root / name), "--n-frames", str(n),
                     "--width", str(W), "--height", str(H)]) == 0
    assert main(["--quiet", "run", str(root / "pcle"), "--method", "robot", "--out",
                 str(root / "robot"), "--no-report"]) == 0
    assert main(["--quiet", "run", str(root / "pcle6"), "--method", "robot", "--out",
                 str(root / "robot6")]) == 0
    return root


def _translations(n: int, x0: float = 0.0, y0: float = 0.0) -> np.ndarray:
    """Frame -> reference translations; (x0, y0): frame 0's offset in the reference."""
    G = np.tile(np.eye(3), (n, 1, 1))
    G[:, 0, 2] = x0 + 7.0 * np.arange(n)
    G[:, 1, 2] = y0 - 3.0 * np.arange(n)
    return G


def _strict(obj):
    """As report.json / evaluation.json write it: strict JSON (inf and NaN as null)."""
    return json.loads(json.dumps(to_jsonable(obj), allow_nan=False))


# ------------------------- F1: a truth without a row for the output's reference frame 0


def test_a_truth_in_another_grid_without_frame_0s_row_is_refused():
    """Truth in a microscope image's grid (frame 0 at (100, 50)), its frame-0 row missing, an
    exact estimate in frame 0's grid: before, scored as it was, e_M 111.8 px (frame 0's
    offset on every frame) and no word."""
    micro = _translations(8, 100.0, 50.0)
    G = np.linalg.inv(micro[0]) @ micro  # exact, frame 0's grid
    assert run_metrics(G, micro, 64, 48)["metrics"]["e_M_px"] < 1e-9  # with the row: exact
    sparse = micro.copy()
    sparse[0] = np.nan
    out = run_metrics(G, sparse, 64, 48, np.arange(10, 18))
    assert out["metrics"] is None
    assert out["metrics_note"] == (
        "not scored: the truth has no row for the output's reference frame 10 (the frame "
        "homographies.csv writes as the identity): which grid it is in cannot be checked (a "
        "truth in another grid, e.g. positions in a microscope image, is taken to the output's "
        "grid through that row); scored as it is every e_j would hold frame 10's offset in the "
        "truth's grid. Give the truth a row for frame 10 (the identity when the truth is in "
        "frame 10's grid)")
    G_ref, r, why = scoring_truth(G, sparse)
    assert G_ref is None and r == 0 and why.startswith(
        "the truth has no row for the output's reference frame 0 (the frame the output writes "
        "as the identity)")
    # a truth written with frame 3 as its identity (its grid is frame 3's): said so
    in3 = np.linalg.inv(micro[3]) @ micro
    in3[0] = np.nan
    assert ("its identity row is frame 3's, so it is in that frame's grid, not the output's"
            in unscorable_reference(G, in3))
    # nothing that would be scored (only frame 0 placed): no figure in a wrong grid, no refusal
    lone = np.full_like(G, np.nan)
    lone[0] = np.eye(3)
    assert unscorable_reference(lone, sparse) is None
    assert run_metrics(lone, sparse, 64, 48)["metrics"]["frames_scored"] == 0


def test_report_md_and_evaluate_refuse_it_alike(pcle, tmp_path, capsys):
    """report.md: no figures ("–") and the note; evaluate: exit 2, nothing written;
    evaluate_output: ValueError naming ground_truth.csv. With frame 0's row the same truth in
    the microscope's grid scores as the truth in frame 0's grid."""
    ids, G_true = read_homographies_csv(pcle / "pcle" / "ground_truth.csv")
    micro = np.array([[1.0, 0, 250.0], [0, 1.0, -80.0], [0, 0, 1.0]]) @ G_true
    truth = tmp_path / "truth"
    shutil.copytree(pcle / "pcle", truth)
    write_homographies_csv(truth / "ground_truth.csv", ids, micro)
    out = tmp_path / "out"
    shutil.copytree(pcle / "robot", out, ignore=shutil.ignore_patterns("evaluation*"))
    e_M = evaluate_output(out, pcle / "pcle")["e_M_px"]
    assert evaluate_output(out, truth)["e_M_px"] == pytest.approx(e_M, abs=1e-6)
    micro[0] = np.nan
    write_homographies_csv(truth / "ground_truth.csv", ids, micro)
    message = (f"{truth / 'ground_truth.csv'}: the truth has no row for the output's "
               f"reference frame {ids[0]} (the frame {out / 'homographies.csv'} writes as the "
               "identity): which grid it is in cannot be checked")
    with pytest.raises(ValueError) as info:
        evaluate_output(out, truth)
    assert str(info.value).startswith(message)
    capsys.readouterr()
    assert main(["--quiet", "evaluate", str(out), "--truth", str(truth)]) == 2
    assert f"fusedmosaic: error: {message}" in capsys.readouterr().err
    assert not (out / "evaluation.json").exists()
    _, G = read_homographies_csv(out / "homographies.csv")
    record = TruthRecord(W, H, ids, homographies=micro)
    md = write_report(tmp_path / "md", [RunRecord("robot", G, output=".")], record).read_text()
    row = next(line for line in md.splitlines() if line.startswith("| robot |"))
    assert row.split(" | ")[3:6] == ["–", "–", "–"], row
    assert ("**e_M (robot):** not scored: the truth has no row for the output's reference "
            f"frame {ids[0]}") in md


# ------------------------------------------- F3: frames placed at infinity in the Wilcoxon test


def test_frames_placed_at_infinity_rank_as_the_worst():
    """a better than b by 0.1-1.0 µm on 10 frames but at infinity on 3: before, those were
    dropped and a came out significantly better (p = 0.002, n = 10)."""
    b = np.arange(1.0, 14.0)
    a = b - np.r_[np.linspace(0.1, 1.0, 10), 0, 0, 0]
    a[10:] = np.inf
    res = compare_position_errors(a, b)
    assert res["n"] == 13 and res["n_ranked"] == 13
    assert res["at_infinity_a"] == 3 and res["at_infinity_b"] == 0
    assert res["unplaced_a"] == res["unplaced_b"] == 0
    # the three ranked 11-13, positive: W+ = 36, W- = 55
    d = np.r_[-np.linspace(0.1, 1.0, 10), 1e9, 1e9, 1e9]
    assert res["statistic"] == 36.0
    assert res["p_value"] == pytest.approx(stats.wilcoxon(d).pvalue)
    assert res["p_value"] > 0.4
    assert stats.wilcoxon(d[:10]).pvalue < 0.01  # what dropping them gave
    assert res["note"] == "3 frames placed at infinity by a, ranked as the largest differences"
    assert res["mean_a"] == np.inf  # (as position_stats': inf counted)
    # b at infinity instead: the sign follows, a better everywhere
    flipped = compare_position_errors(b, a)
    assert flipped["at_infinity_b"] == 3 and flipped["statistic"] == 36.0
    assert "placed at infinity by b" in flipped["note"]


def test_both_at_infinity_is_a_tie_and_unplaced_frames_are_counted():
    a = np.array([1.0, 2.0, 3.0, np.inf, np.nan, 5.0, np.nan])
    b = np.array([1.5, 2.5, 3.5, np.inf, 4.0, np.nan, np.nan])
    res = compare_position_errors(a, b)
    # frames 0-3 paired (3 both at infinity: no difference), 4 placed by b only, 5 by a only,
    # 6 by neither (no truth, say): not counted
    assert res["n"] == 4 and res["n_ranked"] == 3
    assert (res["at_infinity_a"], res["at_infinity_b"]) == (1, 1)
    assert (res["unplaced_a"], res["unplaced_b"]) == (1, 1)
    assert res["p_value"] == pytest.approx(stats.wilcoxon([-0.5, -0.5, -0.5]).pvalue)
    assert res["note"] == (
        "1 frame placed at infinity by a, ranked as the largest differences; 1 frame placed "
        "at infinity by b, ranked as the largest differences; 1 frame placed by b only (a "
        "left it unplaced), not paired; 1 frame placed by a only (b left it unplaced), not "
        "paired")
    every = compare_position_errors(np.full(4, np.inf), np.full(4, np.inf))
    assert every["n_ranked"] == 0 and every["p_value"] == 1.0
    assert every["note"].startswith("no paired difference above 1e-06: nothing to rank; 4 "
                                    "frames placed at infinity by a")
    plain = compare_position_errors(np.arange(5.0), np.arange(5.0) + 1.0)
    assert "note" not in plain and plain["at_infinity_a"] == 0  # nothing to say: no note


@pytest.mark.parametrize(("a", "b", "message"), [
    (np.array([1.0, -np.inf, 2.0]), np.ones(3),
     r"Wilcoxon test: an error of -inf \(errors are distances, >= 0\)"),
    (np.ones(3), np.ones(4), r"Wilcoxon test needs two per-frame error lists of the same "
     r"length, got shapes \(3,\) and \(4,\)"),
    (np.array([1.0, np.inf, np.nan]), np.array([np.nan, 1.0, 2.0]),
     "Wilcoxon test needs at least 2 frames placed by both methods"),
])
def test_compare_position_errors_bad_input(a, b, message):
    with pytest.raises(ValueError, match=message):
        compare_position_errors(a, b)


def test_evaluate_compare_ranks_a_centre_at_infinity(pcle, tmp_path, capsys):
    """evaluate --compare: the output whose frame 5's centre lands at infinity (null in
    evaluation.json, listed in position_at_infinity) was compared on its 15 other frames."""
    ids, G_true = read_homographies_csv(pcle / "pcle" / "ground_truth.csv")
    G = G_true.copy()
    G[:, 0, 2] += 0.25  # 0.25 px off everywhere
    cx = (W - 1) / 2.0
    G[5, 2] = [0.002, 0.0, -0.002 * cx]  # frame 5's centre to infinity
    inf = tmp_path / "inf"
    inf.mkdir()
    write_homographies_csv(inf / "homographies.csv", ids, G)
    out = tmp_path / "out"
    shutil.copytree(pcle / "robot", out, ignore=shutil.ignore_patterns("evaluation*"))
    assert main(["evaluate", str(out), "--truth", str(pcle / "pcle"), "--compare",
                 str(inf)]) == 0
    printed = capsys.readouterr().out
    report = json.loads((out / "evaluation.json").read_text())
    assert report["results"][1]["position_at_infinity"] == [int(ids[5])]
    w = report["wilcoxon"][0]
    assert w["n"] == N and w["at_infinity_b"] == 1 and w["at_infinity_a"] == 0
    assert w["note"] == "1 frame placed at infinity by b, ranked as the largest differences"
    a = np.array(report["results"][0]["position_errors_um"], dtype=float)
    b = np.array([np.nan if e is None else e for e in report["results"][1][
        "position_errors_um"]])
    b[5] = np.inf
    assert w["p_value"] == compare_position_errors(a, b)["p_value"]
    assert f"(n = {N}" in printed and "1 frame placed at infinity by b" in printed
    md = (out / "evaluation.md").read_text()
    assert f"({w['note']})" in md and "a frame placed at infinity counts as the largest" in md


# ---------------------------------- F4: report.json's max e_j and drift beside an inf e_M


def test_run_metrics_at_infinity_and_drift_notes():
    """Every frame placed at infinity: before, max_e_j_px None beside an inf e_M (both null in
    report.json, one of them for no reason) and a null drift ratio without a note."""
    G_true = _translations(8)
    G = np.tile(np.eye(3), (8, 1, 1))
    G[:, 2] = [1.0, 0.0, 0.0]  # pixel (0, 0) of every frame to infinity (frame 0 too)
    assert np.isinf(frame_errors(G, G_true, 64, 48)).all()
    m = run_metrics(G, G_true, 64, 48, np.arange(10, 18))["metrics"]
    assert m["e_M_px"] == np.inf and m["max_e_j_px"] == np.inf
    assert m["placed_at_infinity"] == list(range(10, 18))
    assert m["drift_ratio"] is None
    assert m["drift_ratio_note"] == ("the first quarter (frames 10-11) holds a frame placed at "
                                     "infinity (e_j inf): no ratio to it")
    written = _strict(m)
    assert written["e_M_px"] is None and written["max_e_j_px"] is None  # alike, and why:
    assert written["placed_at_infinity"] == list(range(10, 18))
    # the last quarter at infinity: drift inf, null in the file, with its note
    last = np.linalg.inv(G_true[0]) @ G_true
    last[:, 0, 2] += np.arange(8) * 0.5
    last[7, 2] = [1.0, 0.0, 0.0]
    m = run_metrics(last, G_true, 64, 48)["metrics"]
    assert m["drift_ratio"] == np.inf and _strict(m)["drift_ratio"] is None
    assert m["drift_ratio_note"].startswith("the last quarter (frames 6-7) holds a frame placed "
                                            "at infinity")
    assert m["placed_at_infinity"] == [7] and m["e_M_px"] == np.inf
    # a finite ratio: no note, no list
    fine = np.linalg.inv(G_true[0]) @ G_true
    fine[:, 0, 2] += np.arange(8) * 0.5
    m = run_metrics(fine, G_true, 64, 48)["metrics"]
    assert m["drift_ratio"] == pytest.approx(drift_ratio(np.arange(8) * 0.5))
    assert "drift_ratio_note" not in m and "placed_at_infinity" not in m


def test_run_report_json_and_md_say_why_the_drift_is_null(pcle):
    """A 6-frame run: a quarter is frame 0 alone, the reference: drift null; before, with no
    note in report.json nor in report.md."""
    report = json.loads((pcle / "robot6" / "report.json").read_text())
    m = report["metrics"]
    note = ("the first quarter (frame 0) holds only the reference frame, whose e_j is 0 by "
            "construction and left out (with under 8 frames a quarter is one frame): no ratio "
            "to it")
    assert m["drift_ratio"] is None and m["drift_ratio_note"] == note
    assert m["frames_scored"] == 6 and m["max_e_j_px"] >= m["e_M_px"] > 0
    md = (pcle / "robot6" / "report.md").read_text()
    assert f"**Drift ratio (robot):** {note}" in md
    # evaluate's evaluation.md has it once (its own notes hold it already)
    assert main(["--quiet", "evaluate", str(pcle / "robot6"), "--truth",
                 str(pcle / "pcle6")]) == 0
    assert (pcle / "robot6" / "evaluation.md").read_text().count(note) == 1


def test_report_md_max_e_j_is_inf_beside_an_inf_e_m(tmp_path):
    G_true = _translations(8)
    G = np.tile(np.eye(3), (8, 1, 1))
    G[:, 2] = [1.0, 0.0, 0.0]
    md = write_report(tmp_path, [RunRecord("bad", G, output=".")],
                      TruthRecord(64, 48, np.arange(8), homographies=G_true)).read_text()
    row = next(line for line in md.splitlines() if line.startswith("| bad |"))
    assert row.split(" | ")[3:6] == ["inf", "inf", "–"], row  # max e_j was "–"
    assert ("**Drift ratio (bad):** the first quarter (frames 0-1) holds a frame placed at "
            "infinity (e_j inf): no ratio to it") in md


# ----------------------------------------- F5: the drift note of a quarter holding the reference


def test_the_drift_note_names_the_reference_frame():
    """A first quarter with no scored frame but the reference said "has mean e_j 0", as if
    frames had been scored exact."""
    nan = np.nan
    assert drift_note(np.array([0.0, 1.0, 2.0])) == (
        "the first quarter (frame 0) holds only the reference frame, whose e_j is 0 by "
        "construction and left out (with under 8 frames a quarter is one frame): no ratio to "
        "it")
    # 8 frames: the quarter is frames 0-1, frame 1 unplaced
    e = np.array([0.0, nan, 1, 1, 1, 1, 1, 1])
    assert np.isnan(drift_ratio(e))
    assert drift_note(e, frame_ids=np.arange(20, 28)) == (
        "the first quarter (frames 20-21) has no scored frame but the reference frame, whose "
        "e_j is 0 by construction and left out (the others are unplaced or have no ground-truth "
        "homography): no ratio to it")
    # the reference last (a late start written backwards): the last quarter's alike
    e = np.array([1.0, 1, 1, 1, 1, 1, nan, 0.0])
    assert drift_note(e, reference=7).startswith(
        "the last quarter (frames 6-7) has no scored frame but the reference frame")
    # frames scored exactly 0 (an exact estimate): that is a mean e_j of 0
    e = np.r_[0.0, 0.0, np.ones(6)]
    assert drift_note(e) == ("the first quarter (frames 0-1) has mean e_j 0 (up to 1e-09 px) "
                             "over its scored frames: no ratio to it")
    # one scored frame beside the reference: a ratio
    e = np.array([0.0, 0.5, 1, 1, 1, 1, 1, 1])
    assert drift_ratio(e) == pytest.approx(2.0) and drift_note(e) is None
