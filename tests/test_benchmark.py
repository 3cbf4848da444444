"""`fusedmosaic bench`: design.md's budgets measured on the machine it runs on. Speeds are not
asserted here (no timed tests); the runs' accuracy against the simulator's truth, the budget
checks' logic and the refusals are."""

import json

import numpy as np
import pytest

from fusedmosaic.cli import main
from fusedmosaic.evaluation import benchmark


def test_bench_measures_every_budget_on_runs_that_are_right(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert main(["bench", "--frames", "60", "--pcle-frames", "12", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    result = json.loads(out.read_text())
    names = [c["name"] for c in result["checks"]]
    assert names == ["window_step_median_ms", "window_step_p95_ms", "sequential_frames_per_s",
                     "pcle_frames_per_s"]  # the offline one only with --offline
    for c in result["checks"]:
        assert np.isfinite(c["measured"]) and c["measured"] > 0
        assert ("ok" if c["ok"] else "MISSED") in printed
    seq, pcle = result["sequential"], result["pcle"]
    # 60 frames, the last 10 after the start-up's 40 + 10 steady; every window step timed
    assert seq["latency_ms_steady"]["n"] == 10 and seq["window_step_ms"]["n"] >= 6
    # the measured runs are correct, not only fast: against the simulator's truth
    assert seq["unplaced"] == 0 and seq["e_M_px"] < 0.5  # measured 0.22
    assert pcle["frames"] == 12 and pcle["mean_error_um"] < pcle["robot_mean_error_um"]
    assert result["machine"]["cores"] >= 1 and result["peak_rss_mb"] > 0
    assert f"wrote {out}" in printed


def _fake_measurements(monkeypatch, *, fps: float) -> None:
    monkeypatch.setattr(benchmark, "measure_sequential", lambda frames, detector, seed: {
        "frames": frames, "window_step_ms": {"median": 4.0, "p95": 20.0},
        "frames_per_s_steady": fps, "e_M_px": 0.2, "unplaced": 0})
    monkeypatch.setattr(benchmark, "measure_pcle", lambda frames, seed: {
        "frames_per_s": 150.0, "mean_error_um": 30.0, "robot_mean_error_um": 300.0})
    monkeypatch.setattr(benchmark, "measure_offline", lambda seed: {
        "optimisation_s": 0.3, "e_M_px": 0.09, "pairs_registered": 1000, "total_s": 3.0})


def test_budget_checks_and_strict_exit_status(monkeypatch, capsys):
    _fake_measurements(monkeypatch, fps=30.0)
    result = benchmark.run_benchmark(benchmark.BenchOptions(offline=True))
    verdict = {c["name"]: c["ok"] for c in result["checks"]}
    assert verdict == {"window_step_median_ms": True, "window_step_p95_ms": False,  # 20 > 15
                       "sequential_frames_per_s": True, "pcle_frames_per_s": True,
                       "ba_emt_optimisation_s": True}
    assert not result["all_ok"]
    assert main(["bench"]) == 0  # a missed budget is reported ...
    assert "| LBA window step, p95 (ms)" in capsys.readouterr().out
    assert main(["bench", "--strict"]) == 1  # ... and fails the command only with --strict
    assert "some budgets MISSED" in capsys.readouterr().out


@pytest.mark.parametrize("extra, message", [
    (["--frames", "59"], "--frames: must be >= 60 (the start-up adjustment takes the first 40)"),
    (["--pcle-frames", "5"], "--pcle-frames: must be >= 10, got 5"),
])
def test_bad_counts_are_refused_by_flag(monkeypatch, capsys, extra, message):
    _fake_measurements(monkeypatch, fps=30.0)
    assert main(["bench", *extra]) == 2
    assert message in capsys.readouterr().err


def test_bad_json_destination_is_refused_before_measuring(monkeypatch, tmp_path, capsys):
    def never(*args, **kwargs):
        raise AssertionError("measured before checking --json")

    monkeypatch.setattr(benchmark, "measure_sequential", never)
    assert main(["bench", "--json", str(tmp_path)]) == 2
    assert f"--json {tmp_path}: is a folder; give a file name" in capsys.readouterr().err
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["bench", "--json", str(blocker / "b.json")]) == 2
    assert f"{blocker}: exists and is not a folder" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
    notes = tmp_path / "notes.json"  # a user's file of that name is not replaced
    notes.write_text('{"my": "notes"}')
    assert main(["bench", "--json", str(notes)]) == 2
    assert f"--json {notes}: exists and is not a bench result" in capsys.readouterr().err
    assert json.loads(notes.read_text()) == {"my": "notes"}


def test_json_replaces_only_a_bench_result(tmp_path):
    """`bench --json FILE` replaced any file of that name (a user's notes included): only a
    bench result fusedmosaic wrote (recorded in the folder's output manifest, or an older
    version's, recognised by its content) is replaced now."""
    result = {"checks": [{"name": "pcle_frames_per_s", "ok": True}], "machine": {"cores": 2},
              "all_ok": True}
    mine = tmp_path / "notes.json"
    mine.write_text('{"my": "notes"}')
    with pytest.raises(ValueError, match=r"notes\.json: exists and is not a bench result "
                                         r"fusedmosaic wrote; choose another file name"):
        benchmark.check_json_destination(mine)
    with pytest.raises(ValueError, match=r"notes\.json: exists and is not a bench result"):
        benchmark.write_json(mine, result)
    assert json.loads(mine.read_text()) == {"my": "notes"}
    out = benchmark.write_json(tmp_path / "bench.json", result)  # new: written and recorded
    assert json.loads(out.read_text()) == result
    result["all_ok"] = False
    benchmark.write_json(out, result)  # recorded: replaced
    assert json.loads(out.read_text())["all_ok"] is False
    older = tmp_path / "old_bench.json"  # a result written before the record existed
    older.write_text(json.dumps(result))
    assert benchmark.check_json_destination(older) == older
    with pytest.raises(ValueError, match=r": is a folder; give a file name"):
        benchmark.check_json_destination(tmp_path)
    with pytest.raises(ValueError, match=r"b\.json: .*notes\.json: exists and is not a folder"):
        benchmark.check_json_destination(mine / "b.json")

