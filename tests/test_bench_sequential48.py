"""Session 48's review of the bench scripts (report R): bench_sequential's window probe counts a
gating redo with its step and records the window calls its replays need; its peak RSS is the
mosaicker's, over a baseline taken before streaming; bench_cpp's replay reads held steps and
refuses records it does not know; run_all keeps the runs behind every stage and compares
cv2.Stitcher's registration with lba-emt's."""

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from fusedmosaic import _core
from fusedmosaic.estimation.sequential import SequentialOptions
from fusedmosaic.registration.features import FeatureOptions

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import bench_cpp  # noqa: E402
import bench_sequential as bs  # noqa: E402
import run_all  # noqa: E402
from _common import WindowRecorder  # noqa: E402


def _summary(step_s, frame_ids):
    return SimpleNamespace(
        step_time_s=step_s, solve_time_s=step_s / 2, evaluation_time_s=0.0,
        linear_solver_time_s=0.0, preprocessor_time_s=0.0, iterations=2,
        num_correspondences=10, num_window_correspondences=4, num_keyframe_correspondences=3,
        num_loop_correspondences=2, num_temporal_correspondences=1,
        num_fixed_pair_correspondences=0, num_residuals=20, final_cost=1.0,
        frame_ids=list(frame_ids))


class FakeWindow:
    """The SlidingWindow calls the probe and the recorder forward, with set step times."""

    def __init__(self, times=(0.003, 0.004, 0.005)):
        self.times = list(times)
        self.calls = []

    def add_frame(self, k, *args):
        self.calls.append(("add_frame", k))

    def set_emt_sigma_scale(self, k, scale):
        self.calls.append(("set_emt_sigma_scale", k))

    def drop_emt_measurement(self, k):
        self.calls.append(("drop_emt_measurement", k))

    def set_motion_timing(self, k, ratio, scale):
        self.calls.append(("set_motion_timing", k))

    def step(self, keyframe_ids=(), hold_plane=False):
        self.calls.append(("step", hold_plane))
        return _summary(self.times.pop(0), [1, 2, 3])

    def redo(self, frame_ids, keyframe_ids=(), hold_plane=False):
        self.calls.append(("redo", hold_plane))
        return _summary(self.times.pop(0), frame_ids)


# -- bench_sequential: the window probe ------------------------------------------------------


def test_probe_adds_a_gating_redo_to_its_step_and_a_redo_after_a_new_frame_is_a_step():
    probe = bs.WindowProbe(FakeWindow())
    probe.add_frame(3)
    probe.step([], False)
    probe.set_emt_sigma_scale(3, 4.0)
    probe.redo([1, 2, 3], [], False)  # the gating redo: same step
    probe.add_frame(4)
    probe.redo([3, 4], [], False)  # frames held back, re-estimated with the new one: a step
    assert len(probe.steps) == 2
    first, second = probe.steps
    assert first["step_ms"] == pytest.approx(7.0) and first["solves"] == 2
    assert first["solve_ms"] == pytest.approx(3.5) and first["iterations"] == 4
    assert second["step_ms"] == pytest.approx(5.0) and second["solves"] == 1
    assert bs.step_stats(probe.steps)["steps_with_a_redo"] == 1


def test_probe_records_the_calls_that_change_a_frames_priors_for_the_replays():
    probe = bs.WindowProbe(FakeWindow())
    probe.drop_emt_measurement(5)
    probe.set_motion_timing(5, 0.5, np.inf)
    assert [c[:2] for c in probe.calls] == [("drop_emt_measurement", (5,)),
                                            ("set_motion_timing", (5, 0.5, np.inf))]


def test_variants_label_the_defaults_with_the_defaults():
    defaults = [(name, o) for name, o in bs.VARIANTS.items() if "(defaults)" in name]
    assert len(defaults) == 1
    name, o = defaults[0]
    assert o.features.max_features == FeatureOptions().max_features
    assert o.loop_pairs == SequentialOptions().loop_pairs
    assert f"max_features={FeatureOptions().max_features}" in name
    assert f"loop_pairs={SequentialOptions().loop_pairs}" in name


# -- bench_sequential: memory ----------------------------------------------------------------


_MEMORY_CHILD = """
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[1])
import bench_sequential as bs
big = np.ones(160 * 2**20 // 8)  # 160 MB touched: a peak before "streaming"
del big
baseline = bs.memory_baseline()
after = bs.memory_at(baseline)
held = np.ones(40 * 2**20 // 8)
print(json.dumps({"baseline": baseline, "after": after, "now": bs.memory_at(baseline)}))
"""


def test_memory_baseline_resets_the_peak_so_growth_is_the_streamings():
    # (in a fresh interpreter: in a test worker, memory other tests freed but the allocator
    # kept can take the 40 MB without any growth of RSS)
    import subprocess

    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pytest.skip("VmHWM cannot be reset here (/proc/self/clear_refs)")
    bench = str(Path(__file__).resolve().parents[1] / "bench")
    out = subprocess.run([sys.executable, "-c", _MEMORY_CHILD, bench], capture_output=True,
                         text=True, check=True, timeout=120).stdout
    m = json.loads(out.strip().splitlines()[-1])
    baseline, after, now = m["baseline"], m["after"], m["now"]
    assert baseline["peak_reset"]
    assert baseline["peak_rss_mb_before_streaming"] - baseline["rss_mb"] > 100
    assert after["peak_rss_over_baseline_mb"] < 20  # the earlier 160 MB is not counted
    assert now["rss_over_baseline_mb"] > 30 and now["peak_rss_over_baseline_mb"] > 30


def test_memory_at_without_a_reset_gives_no_peak_below_the_earlier_one(monkeypatch):
    status = {"rss_mb": 190.0, "peak_rss_mb": 204.0}
    monkeypatch.setattr(bs, "proc_status_mb", lambda: dict(status))
    baseline = {"rss_mb": 172.0, "peak_rss_mb_before_streaming": 204.0, "peak_reset": False}
    m = bs.memory_at(baseline)
    assert m["peak_rss_mb"] is None and m["peak_rss_over_baseline_mb"] is None
    assert m["rss_over_baseline_mb"] == pytest.approx(18.0)
    status.update(rss_mb=230.0, peak_rss_mb=231.0)  # above the earlier peak: the streaming's
    assert bs.memory_at(baseline)["peak_rss_over_baseline_mb"] == pytest.approx(59.0)


def test_memory_sentence_names_the_baseline_and_the_growth():
    m = {"rss_baseline_mb": 172.4, "peak_rss_before_streaming_mb": 203.8,
         "peak_reset_at_baseline": True,
         "at_frames": {"500": {"peak_rss_mb": 194.0, "peak_rss_over_baseline_mb": 21.6,
                               "rss_mb": 193.0, "rss_over_baseline_mb": 20.6},
                       "3000": {"peak_rss_mb": 225.0, "peak_rss_over_baseline_mb": 52.6,
                                "rss_mb": 224.0, "rss_over_baseline_mb": 51.6}}}
    text = bs.memory_sentence(m)
    assert "VmRSS 172 MB (the baseline), peak so far 204 MB (the simulator's)" in text
    assert "500 frames: peak 194 MB (+22 MB), VmRSS 193 MB (+21 MB)" in text
    assert "3000 frames: peak 225 MB (+53 MB)" in text


# -- bench_cpp / _common: held steps and calls the log cannot hold ---------------------------


HEADER = """fusedmosaic-problem 1 window
K 400 0 200 0 400 200 0 0 1
costs 1.0 huber 1.0 sparse_normal_cholesky per_pair 50 1e-06 1e-10 1e-08 1 1 1
emt_sigma 0.01 0.01 0.01 0.5 0.5 0.5
motion_sigma 0.01 0.01 0.01 0.5 0.5 0.5
plane_std 0 0
window 5 3 1
"""


def test_load_problem_reads_held_steps_and_redos(tmp_path):
    path = tmp_path / "w.txt"
    path.write_text(HEADER + "step 2 5 6 hold\nstep 0\nredo 2 7 8 1 5 hold\nredo 1 9 0\n"
                    "forget 2 1 2\nend\n")
    calls = bench_cpp.load_problem(path)["calls"]
    assert calls == [("step", ([5, 6], True)), ("step", ([], False)),
                     ("redo", ([7, 8], [5], True)), ("redo", ([9], [], False)),
                     ("forget", ([1, 2],))]


@pytest.mark.parametrize("record, message", [
    ("step 1 5 held", r"w.txt:8: step: expected 'hold' or the end of the line, got 'held'"),
    ("redo 2 7", r"w.txt:8: redo: expected 2 id list\(s\)"),
    ("drop_emt_measurement 4", r"w.txt:8: unknown record 'drop_emt_measurement'; a replay "
                               "without it would solve another problem"),
])
def test_load_problem_refuses_what_it_cannot_replay(tmp_path, record, message):
    path = tmp_path / "w.txt"
    path.write_text(HEADER + record + "\nend\n")
    with pytest.raises(ValueError, match=message):
        bench_cpp.load_problem(path)


def test_python_replay_passes_the_hold_flag(tmp_path, monkeypatch):
    path = tmp_path / "w.txt"
    path.write_text(HEADER + "step 0 hold\nredo 3 1 2 3 0 hold\nstep 0\nend\n")
    p = bench_cpp.load_problem(path)
    windows = []

    class Window(FakeWindow):
        def __init__(self, K, options):
            super().__init__()
            windows.append(self)

    monkeypatch.setattr(_core, "SlidingWindow", Window)
    out = bench_cpp.python_replay(p, 1)
    assert windows[0].calls == [("step", True), ("redo", True), ("step", False)]
    assert len(out["step_wall_ms"]) == 2  # the redo is added to its step, as in the C++ replay


def _recorder(window, path):
    costs = _core.BundleAdjusterOptions()
    wopts = _core.SlidingWindowOptions(window_size=5, num_new=3, costs=costs)
    return WindowRecorder(window, np.eye(3), costs, wopts, path)


def test_window_recorder_writes_no_log_the_replays_would_misread(tmp_path):
    path = tmp_path / "window-syn.txt"
    path.write_text("an older run's log\n")
    window = FakeWindow()
    rec = _recorder(window, path)
    rec.add_frame(1)
    rec.drop_emt_measurement(1)
    rec.set_motion_timing(1, 1.0, 2.0)
    rec.step([], True)
    rec.close()
    assert window.calls[1:3] == [("drop_emt_measurement", 1), ("set_motion_timing", 1)]
    assert not path.exists()  # (not the older log either: it would be replayed instead)
    assert rec.not_logged == (f"{path} not written: the run called 1 x drop_emt_measurement, "
                              "1 x set_motion_timing, which the replays' log format has no "
                              "record for")

    rec = _recorder(FakeWindow(), path)  # without them: written, and read back
    rec.add_frame(1)
    rec.step([], True)
    rec.close()
    assert rec.not_logged is None
    assert ("step", ([], True)) in bench_cpp.load_problem(path)["calls"]


# -- run_all: the runs behind the stages, the headline ---------------------------------------


def _run(finished, stages, total=60.0, command="python bench/run_all.py"):
    return {"quick": False, "finished": finished, "total_s": total, "command": command,
            "stages": [{"stage": s, "exit_code": 0, "seconds": 10.0, "log": "-",
                        "finished": finished} for s in stages]}


def test_merge_runs_keeps_the_stages_an_only_run_did_not_rerun():
    full = _run("2026-11-30T22:33:00+00:00", ["table1", "latency", "cpp"], 828.0)
    only = _run("2026-11-30T22:45:00+00:00", ["table1"], 154.0,
                "python bench/run_all.py --only table1")
    runs = run_all.merge_runs(run_all.previous_runs({"run": full}), only)
    assert [[s["stage"] for s in r["stages"]] for r in runs] == [["latency", "cpp"], ["table1"]]
    assert runs[0]["finished"] == full["finished"] and runs[0]["total_s"] == 828.0
    assert run_all.merge_runs(runs, _run("2026-12-01T10:00:00+00:00",
                                         ["table1", "latency", "cpp"]))[0]["stages"][0][
        "stage"] == "table1"  # a full rerun leaves one run
    quick = dict(_run("2026-12-01T11:00:00+00:00", ["table1"]), quick=True)
    assert run_all.merge_runs(runs, quick) == [quick]


def test_summary_says_per_stage_which_run_produced_it(tmp_path):
    runs = [_run("2026-11-30T22:33:00+00:00", ["latency", "peers"], 828.0),
            _run("2026-11-30T22:45:00+00:00", ["table1"], 154.0,
                 "python bench/run_all.py --only table1")]
    summary, readme, _ = run_all.summary_markdown(tmp_path, runs)
    assert "every figure is one measurement of this run" not in summary
    assert "one measurement of the run its stage names below" in summary
    assert ("| table1 | 2026-11-30T22:45:00+00:00 | `python bench/run_all.py --only table1` "
            "(finished 2026-11-30T22:45:00+00:00, 2.6 min) | 10 |") in summary
    assert "| latency | 2026-11-30T22:33:00+00:00 |" in summary
    assert ("table1 from `python bench/run_all.py --only table1` finished "
            "2026-11-30T22:45:00+00:00 (2.6 min)") in readme
    one, _, _ = run_all.summary_markdown(tmp_path, runs[:1])
    assert "every figure is one measurement of this run" in one


def test_summary_names_stages_no_run_record_covers(tmp_path):
    # summary.json from before "runs" kept only the --only rerun; the other stages' JSON is there
    (tmp_path / "latency.json").write_text("{}")
    runs = [_run("2026-11-30T22:45:00+00:00", ["table1"], 154.0)]
    summary, readme, _ = run_all.summary_markdown(tmp_path, runs)
    assert "every figure is one measurement of this run" not in summary
    assert "| latency | (its JSON written or committed 20" in summary
    assert "latency from earlier runs with no record (their JSON written or committed" in readme


def test_run_all_only_keeps_the_earlier_runs_stages_in_summary_json(tmp_path, monkeypatch):
    results = tmp_path / "results"
    results.mkdir()
    earlier = _run("2026-11-30T22:33:00+00:00", ["table1", "latency", "cpp"], 828.0)
    (results / "summary.json").write_text(json.dumps({"run": earlier, "headline": {}}))
    monkeypatch.setattr(run_all, "run_stage", lambda name, cmd, log_dir: {
        "stage": name, "exit_code": 0, "seconds": 1.0, "log": "-", "finished": "now"})
    assert run_all.main(["--only", "table1", "--results", str(results), "--work",
                         str(tmp_path / "work"), "--no-readme"]) == 0
    runs = json.loads((results / "summary.json").read_text())["runs"]
    assert [[s["stage"] for s in r["stages"]] for r in runs] == [["latency", "cpp"], ["table1"]]
    assert "run_all.py --only table1 --results" in runs[1]["command"]
    assert "| latency | 2026-11-30T22:33:00+00:00 |" in (results / "summary.md").read_text()


def _peers(**stitcher):
    row = {"peer": "cv2.Stitcher SCANS", "sequence": "syn", "frames": 100, "success": True,
           "status": "OK", "time_s": 15.0, "time_per_frame_ms": 150.0, "registration_s": 10.0,
           "compositing_s": 5.0}
    return {"rows": [{**row, **stitcher}]}


def test_headline_compares_registration_with_registration():
    lat = {"lba-emt": {"syn": {"frames_per_s": {"all": 25.0}}}}  # 40 ms per frame
    s = run_all.headline(None, lat, _peers(), None)["stitcher_registration_over_lba_emt_syn"]
    assert s["ratio"] == pytest.approx(2.5)  # 100 / 40 ms, not stitch()'s 150 / 40
    assert run_all.stitcher_headline("syn", s) == (
        "Registration time per frame, SYN circular: lba-emt 40 ms (add_frame streamed, all "
        "frames: features, matching, window step; no mosaic) vs cv2.Stitcher SCANS 100 ms "
        "(estimateTransform: features, all-pairs matching, bundle adjustment) -> lba-emt 2.5x "
        "faster at registration; compositing is left out on both sides (the Stitcher's "
        "composePanorama, seams and blending: 50 ms more per frame).")
    failed = run_all.headline(None, lat, _peers(success=False, status="ERR_NEED_MORE_IMGS"),
                              None)["stitcher_registration_over_lba_emt_syn"]
    assert "ratio" not in failed
    assert run_all.stitcher_headline("syn", failed).endswith(
        "cv2.Stitcher SCANS: ERR_NEED_MORE_IMGS.")


def test_sequential_line_shows_the_cpu_growth_beside_the_judged_wall_time():
    budgets = {k: {"value": v} for k, v in (
        ("step_median_ms", 2.3), ("step_p95_ms", 2.6), ("orb_frames_per_s", 55.2),
        ("drift_ratio", 1.1), ("unplaced", 0), ("latency_growth", 1.13))}
    seq = {"budgets": budgets, "long": {
        "p95_latency_growth": {"wall_time": 1.13, "process_cpu_time": 1.14},
        "memory": {"at_frames": {"500": {"peak_rss_over_baseline_mb": 21.0},
                                 "3000": {"peak_rss_over_baseline_mb": 52.0}}}}}
    line = run_all.sequential_budgets_line(seq)
    assert ("p95 latency growth 1.13 (wall time, <= 1.2; process CPU time 1.14); peak RSS over "
            "the baseline before streaming +21 MB at 500 frames, +52 MB at 3000 frames.") in line
