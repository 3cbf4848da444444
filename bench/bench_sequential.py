"""Latency, throughput, long-sequence and linear-solver benchmark of LBAVis+EMT (seed 000,
Sec. 3.4 and 4.2; issue 4 items 4-6), on this machine, 400x400 frames.

One run, frames streamed from the SYN simulator (simulation/fetoscopy.py: circle of radius
15 mm, ~37 frames per lap as in the paper, so laps = n_frames / 37) into SequentialMosaicker
(estimation/sequential.py) with tracker poses interpolated from the simulated 40 Hz tracker through
the hand-eye transform (io.interpolate_camera_poses), as a live loop would:

1. Window solve per step: C++ step_time_s (assembly + Ceres) and Ceres' solve_time_s from the
   step summaries of the long ORB run (a gating redo's added to its step's), median and p95,
   also per new frame (/ chi_e).
   Budget (design.md, issue 4): per step median <= 5 ms, p95 <= 15 ms.
2. End to end per frame: wall time of add_frame (features, matching, window solve, keyframe
   selection) -> frames/s, with ORB (budget >= 25 frames/s) and with SIFT (reported).
3. Long sequence (Figs. 11-12): >= 3000 frames with ORB: drift ratio <= 1.3 and 0 unplaced
   against the simulator's true homographies (e_j, Eq. 28); p95 latency over frames 3000-3300
   <= 1.2 x p95 over frames 100-400 (wall time, the budget; the process CPU time's ratio is
   given beside it); RSS and the C++ window's state sizes at checkpoints (they must stop
   growing).
4. Linear solver of the window step: the window calls of the first frames of the long run are
   recorded and replayed into fresh C++ SlidingWindows with each configuration (solver x threads,
   and for reference the pairs' 2N residuals instead of the condensed blocks, and
   fold_fixed_cameras off), round-robin over repetitions so the load of other
   processes spreads evenly; median step time and Ceres' time split per configuration.

Memory: the simulator's scene (made before streaming) sets the process's peak on its own
(3300 frames: VmRSS 172 MB, VmHWM 204 MB before the first add_frame), so VmRSS is recorded
right before the first add_frame as the baseline and VmHWM is reset there ("5" to
/proc/self/clear_refs); the checkpoints give VmRSS and the peak since then, and both over the
baseline (what the mosaicker holds). Wall times are what the budgets name; process CPU times
are given beside them because the 2 cores may be shared with other processes (the load average
is recorded).

    python bench/bench_sequential.py [--frames 3300] [--sift-frames 300] [--solver-frames 400]
                                     [--repeats 3] [--out bench/results/sequential.json]

Writes the JSON and a markdown table beside it (sequential.md).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import time
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np

from fusedmosaic import _core
from fusedmosaic.estimation.consistency import starting_sigma_v
from fusedmosaic.estimation.sequential import SequentialMosaicker, SequentialOptions
from fusedmosaic.evaluation.benchmark import SYN_FRAMES_PER_LAP, syn_stream
from fusedmosaic.evaluation.metrics import drift_ratio, frame_errors
from fusedmosaic.registration.features import FeatureOptions

FRAMES_PER_LAP = SYN_FRAMES_PER_LAP  # paper 000 Sec. 4.2.4: the long sequence keeps SYN's motion
STEP_MEDIAN_MS, STEP_P95_MS = 5.0, 15.0  # design.md / issue 4, per window step
MIN_ORB_FPS = 25.0
MAX_DRIFT_RATIO = 1.3
MAX_LATENCY_GROWTH = 1.2  # p95 over frames 3000-3300 / p95 over frames 100-400
EARLY, LATE = (100, 400), (3000, 3300)
CHECKPOINTS = (500, 1000, 2000, 3000)
MEMORY_AT = (500, 3000)  # issue 4: peak RSS reported at 500 and 3000 frames
SOLVERS = ("dense_normal_cholesky", "dense_qr", "dense_schur", "sparse_normal_cholesky",
           "sparse_schur")
# --variants: ORB settings reachable through SequentialOptions, for the throughput discussion.
# (The defaults' label is built from the defaults: it read "max_features=500 (defaults)" once
# the default had become 1000.)
VARIANTS = {
    f"orb, max_features={FeatureOptions().max_features}, "
    f"loop_pairs={SequentialOptions().loop_pairs} (defaults)": SequentialOptions(
        features=FeatureOptions(detector="orb")),
    "orb, max_features=500": SequentialOptions(
        features=FeatureOptions(detector="orb", max_features=500)),
    "orb, loop_pairs=0 (the paper's temporal window only)": SequentialOptions(
        features=FeatureOptions(detector="orb"), loop_pairs=0),
}
# Calls of the C++ window that change its state; replayed for the solver comparison.
STATE_CALLS = ("add_frame", "add_pair", "set_plane", "step", "redo", "forget",
               "set_emt_sigma_scale", "drop_emt_measurement", "set_motion_timing",
               "set_sigma_v")
# The times of a step record that add up over its solves (a gating redo's to its step's).
SUMMED = ("step_ms", "solve_ms", "cpu_ms", "evaluation_ms", "linear_solver_ms",
          "preprocessor_ms", "iterations")


def proc_status_mb() -> dict:
    """VmRSS (current) and VmHWM (peak) of this process, MB."""
    out = {}
    with open("/proc/self/status") as f:
        for line in f:
            key = line.split(":")[0]
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(line.split()[1]) / 1024.0
    return {"rss_mb": out.get("VmRSS"), "peak_rss_mb": out.get("VmHWM")}


def reset_peak_rss() -> bool:
    """Sets this process's VmHWM to its current VmRSS ("5" to /proc/self/clear_refs, Linux >=
    4.0); False where that cannot be written, or the peak stayed above the current RSS."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        return False
    now = proc_status_mb()
    # (1 MB: RSS may grow between the reset and the read)
    return now["peak_rss_mb"] is not None and now["peak_rss_mb"] <= now["rss_mb"] + 1.0


def memory_baseline() -> dict:
    """VmRSS right before streaming (the baseline) and the peak so far (the simulator's scene),
    then the peak reset, so that later VmHWM readings are the streaming's own peak."""
    gc.collect()
    before = proc_status_mb()
    return {"rss_mb": before["rss_mb"], "peak_rss_mb_before_streaming": before["peak_rss_mb"],
            "peak_reset": reset_peak_rss()}


def memory_at(baseline: dict) -> dict:
    """VmRSS and the peak since the baseline, also over the baseline's VmRSS (MB). Without the
    peak reset, the peak is the streaming's only once it exceeds the one before streaming;
    peak_rss_mb and its growth are None until then."""
    now = proc_status_mb()
    base = baseline["rss_mb"]
    peak = now["peak_rss_mb"]
    if not baseline["peak_reset"] and peak <= baseline["peak_rss_mb_before_streaming"]:
        peak = None
    return {"rss_mb": now["rss_mb"], "rss_over_baseline_mb": now["rss_mb"] - base,
            "peak_rss_mb": peak, "peak_rss_over_baseline_mb": None if peak is None else peak - base}


def summary_record(s, cpu_s: float) -> dict:
    return {
        "step_ms": s.step_time_s * 1e3, "solve_ms": s.solve_time_s * 1e3, "cpu_ms": cpu_s * 1e3,
        "evaluation_ms": s.evaluation_time_s * 1e3,
        "linear_solver_ms": s.linear_solver_time_s * 1e3,
        "preprocessor_ms": s.preprocessor_time_s * 1e3, "iterations": s.iterations,
        "correspondences": s.num_correspondences,
        "window_corr": s.num_window_correspondences,
        "keyframe_corr": s.num_keyframe_correspondences,
        "loop_corr": s.num_loop_correspondences,
        "temporal_corr": s.num_temporal_correspondences,
        "fixed_pair_corr": s.num_fixed_pair_correspondences,
        "residuals": s.num_residuals, "final_cost": s.final_cost,
    }


def add_solve(steps: list[dict], name: str, record: dict, opens_step: bool) -> None:
    """Adds one window solve (a summary_record) to the per-step records. A redo that does not
    open a step (the gating redo, or the redo after a failed solve's samples were dropped: no
    frame added since the last solve) is added to the step it redoes, so a step counts once
    with every solve's time (`solves` of them). A redo that opens one (frames held back by the
    last step re-estimated with the new ones, after an add_frame) is a step of its own."""
    if name == "redo" and steps and not opens_step:
        last = steps[-1]
        steps[-1] = {**last, **record, **{k: last[k] + record[k] for k in SUMMED},
                     "solves": last["solves"] + 1}
    else:
        steps.append({**record, "solves": 1})


class WindowProbe:
    """Stands in for SequentialMosaicker.window: forwards every call to the C++ SlidingWindow,
    times step/redo (wall from C++, process CPU around the call; a gating redo added to its
    step, add_solve) and, while `recording`, keeps copies of the state-changing calls so they
    can be replayed with other solver options."""

    def __init__(self, window):
        self._window = window
        self.steps: list[dict] = []
        self.calls: list[tuple[str, tuple, dict]] | None = []
        self.recording = True
        self.num_pairs = 0  # add_pair calls (registered pairs) so far
        self.bootstrap_pairs: int | None = None  # those before the first window step
        # The next solve opens a step: a frame was added since the last one (each add_frame
        # runs at most one mosaicker step), or the caller said so (flush's final step).
        self.opens_step = True

    def __getattr__(self, name):
        target = getattr(self._window, name)
        if name not in STATE_CALLS:
            return target

        def call(*args, **kwargs):
            if self.recording:
                self.calls.append((name, tuple(np.array(a) if isinstance(a, np.ndarray) else a
                                               for a in args), dict(kwargs)))
            if name == "add_pair":
                self.num_pairs += 1
            if name == "add_frame":
                self.opens_step = True
            if name == "step" and self.bootstrap_pairs is None:
                self.bootstrap_pairs = self.num_pairs
            c0 = time.process_time()
            result = target(*args, **kwargs)
            if name in ("step", "redo"):
                add_solve(self.steps, name, {**summary_record(result, time.process_time() - c0),
                                             "frame": int(max(result.frame_ids))},
                          self.opens_step)
                self.opens_step = False
            return result

        return call


def stats_ms(x) -> dict:
    x = np.asarray(x, float)
    return {"median": float(np.median(x)), "p95": float(np.percentile(x, 95)),
            "mean": float(np.mean(x)), "max": float(np.max(x)), "n": int(len(x))}


def make_scene(n_frames: int, size: tuple[int, int] = (400, 400)):
    """SYN circle (laps = n_frames / FRAMES_PER_LAP), camera, tracker poses at the frame times
    and their validity: the same stream `fusedmosaic bench` measures."""
    return syn_stream(n_frames, size)


def stream(scene, camera, poses, valid, n_frames: int, options: SequentialOptions, *,
           record_frames: int = 0, checkpoints=(), label: str = "") -> dict:
    """Feeds the first n_frames of the scene to a SequentialMosaicker; per-frame latency,
    per-stage timings, accuracy, step records, state at checkpoints."""
    mosaicker = SequentialMosaicker(camera, options)
    probe = WindowProbe(mosaicker.window)
    mosaicker.window = probe
    G = np.full((n_frames, 3, 3), np.nan)
    status = np.empty(n_frames, object)
    latency = np.zeros(n_frames)
    cpu = np.zeros(n_frames)
    stages = {s: np.zeros(n_frames) for s in
              ("features", "matching", "window_solve", "keyframe_selection")}
    state = {}
    recorded = None
    # after the scene is made, before the first add_frame: the simulator's peak stays out
    memory = memory_baseline() if checkpoints else None
    t_start = time.perf_counter()

    def collect(results):
        for r in results:
            G[r.frame_id] = r.homography
            status[r.frame_id] = r.status
            for s in stages:
                stages[s][r.frame_id] = r.timings.get(s, 0.0)

    for k in range(n_frames):
        image = scene.render(k)
        tracker = poses[k] if valid[k] else None
        t0, c0 = time.perf_counter(), time.process_time()
        mosaicker.add_frame(image, float(scene.timestamps[k]), tracker)
        latency[k] = time.perf_counter() - t0
        cpu[k] = time.process_time() - c0
        collect(mosaicker.finalized())
        if record_frames and k + 1 == record_frames:
            recorded, probe.calls, probe.recording = probe.calls, None, False
        if k + 1 in checkpoints:
            w = probe._window
            state[k + 1] = {"frames": k + 1, **memory_at(memory), "window_frames": w.num_frames,
                            "window_pairs": w.num_pairs,
                            "window_correspondences": w.num_correspondences,
                            "keyframe_blocks": len(mosaicker.keyframes),
                            "elapsed_s": time.perf_counter() - t_start}
            print(f"  {label} frame {k + 1}: {state[k + 1]}", flush=True)
    t0 = time.perf_counter()
    probe.opens_step = True  # (flush's step may start with a redo of held frames, no new frame)
    collect(mosaicker.flush())
    latency[-1] += time.perf_counter() - t0
    if not record_frames:
        probe.calls = None
    errors = frame_errors(G, scene.homographies[:n_frames], *scene.size)
    unplaced = int(np.sum(~np.isfinite(errors)))
    b = options.bootstrap_frames
    pairs = {"bootstrap_attempted": b * (b - 1) // 2, "bootstrap_registered": probe.bootstrap_pairs,
             "registered_per_frame_after_bootstrap":
                 (probe.num_pairs - (probe.bootstrap_pairs or 0)) / max(n_frames - b, 1)}
    return {"latency_s": latency, "cpu_s": cpu, "stages": stages, "errors": errors,
            "unplaced": unplaced, "status": status, "steps": probe.steps, "state": state,
            "memory_baseline": memory, "recorded": recorded, "bootstrap": b, "pairs": pairs}


def throughput(run: dict, lo: int | None = None) -> dict:
    """Frames/s from add_frame wall time over all frames and after `lo` (steady state)."""
    lat, cpu = run["latency_s"], run["cpu_s"]
    lo = run["bootstrap"] + 10 if lo is None else lo
    if len(lat) <= lo:  # (numpy's empty-slice warnings and a division by zero otherwise)
        raise SystemExit(f"{len(lat)} frames streamed: no steady state, which starts at frame "
                         f"{lo} (the start-up's {run['bootstrap']} frames + 10); give more "
                         "--frames")
    stages = {s: float(np.mean(v[lo:]) * 1e3) for s, v in run["stages"].items()}
    return {
        "frames": len(lat),
        "frames_per_s_all": len(lat) / float(lat.sum()),
        "frames_per_s_steady": 1.0 / float(lat[lo:].mean()),
        "steady_from_frame": lo,
        "cpu_frames_per_s_steady": 1.0 / float(cpu[lo:].mean()),
        "latency_ms_steady": stats_ms(lat[lo:] * 1e3),
        "bootstrap_s": float(lat[: run["bootstrap"]].sum()),
        "stage_ms_per_frame_steady": stages,
        "pairs": run["pairs"],
    }


def accuracy(run: dict) -> dict:
    e = run["errors"]
    n = len(e)
    segments = np.array_split(np.arange(n), min(11, n))
    return {"e_M_px": float(np.nanmean(e)), "e_j_max_px": float(np.nanmax(e)),
            "drift_ratio": drift_ratio(e), "unplaced": run["unplaced"],
            "status_counts": {s: int(np.sum(run["status"] == s)) for s in set(run["status"])},
            "e_M_by_segment": [{"frames": [int(s[0]), int(s[-1])],
                                "e_M_px": float(np.nanmean(e[s]))} for s in segments]}


def step_stats(steps: list[dict]) -> dict:
    out = {key: stats_ms([s[key] for s in steps]) for key in
           ("step_ms", "solve_ms", "cpu_ms", "evaluation_ms", "linear_solver_ms",
            "preprocessor_ms")}
    for key in ("iterations", "correspondences", "window_corr", "keyframe_corr", "loop_corr",
                "temporal_corr", "fixed_pair_corr", "residuals"):
        out[key] = {"median": float(np.median([s[key] for s in steps])),
                    "max": float(np.max([s[key] for s in steps]))}
    out["steps"] = len(steps)
    out["steps_with_a_redo"] = sum(s["solves"] > 1 for s in steps)
    return out


# --------------------------------------------------------------------------------------------
def replay(camera_matrix, calls, options: SequentialOptions, *, solver: str, threads: int,
           fold: bool, condense: bool = True) -> tuple[list[dict], dict, np.ndarray]:
    """Re-runs recorded window calls on a fresh SlidingWindow configured like the mosaicker's,
    with the given linear solver, Ceres threads, fold_fixed_cameras and condense_pairs."""
    o = options
    costs = _core.BundleAdjusterOptions(  # (sigma_v "auto": the recorded set_sigma_v sets it)
        sigma_v_px=starting_sigma_v(o.sigma_v_px), loss=o.loss, linear_solver=solver,
        max_iterations=o.max_iterations, function_tolerance=1e-6, num_threads=threads,
        condense_pairs=condense)
    if getattr(o, "motion_sigma", None) is not None:
        costs.motion_sigma = np.asarray(o.motion_sigma, np.float64)
    wo = _core.SlidingWindowOptions(window_size=o.window_size, num_new=o.num_new, costs=costs)
    wo.fold_fixed_cameras = fold
    window = _core.SlidingWindow(camera_matrix, wo)
    steps, poses = [], {}
    opens_step = True
    for name, args, kwargs in calls:
        opens_step = opens_step or name == "add_frame"
        c0 = time.process_time()
        result = getattr(window, name)(*args, **kwargs)
        if name in ("step", "redo"):
            add_solve(steps, name, summary_record(result, time.process_time() - c0), opens_step)
            opens_step = False
            for k in result.frame_ids:
                poses[k] = np.asarray(window.pose(k))
    return steps, poses, np.asarray(window.plane())


def compare_solvers(camera_matrix, calls, options: SequentialOptions, repeats: int) -> list:
    configs = [{"solver": s, "threads": t, "fold_fixed_cameras": True, "condense_pairs": True}
               for s in SOLVERS for t in (1, 2)]
    # references: the pairs' 2N residuals (as before the condensed blocks), and also unfolded
    configs += [{"solver": s, "threads": 1, "fold_fixed_cameras": True, "condense_pairs": False}
                for s in ("dense_schur", "sparse_normal_cholesky")]
    configs += [{"solver": s, "threads": 1, "fold_fixed_cameras": False, "condense_pairs": False}
                for s in ("dense_normal_cholesky", "sparse_normal_cholesky")]
    runs: list[list[list[dict]]] = [[] for _ in configs]
    reference = None
    max_pose_diff = [0.0] * len(configs)
    for _ in range(repeats):
        for i, c in enumerate(configs):
            steps, poses, plane = replay(camera_matrix, calls, options, solver=c["solver"],
                                         threads=c["threads"], fold=c["fold_fixed_cameras"],
                                         condense=c["condense_pairs"])
            runs[i].append(steps)
            if reference is None:
                reference = (poses, plane)
            diff = max(float(np.abs(poses[k] - reference[0][k]).max()) for k in poses)
            max_pose_diff[i] = max(max_pose_diff[i], diff,
                                   float(np.abs(plane - reference[1]).max()))
    out = []
    for c, rs, diff in zip(configs, runs, max_pose_diff, strict=True):
        pooled = [s for r in rs for s in r]
        st = step_stats(pooled)
        out.append({**c, "steps": len(rs[0]), "repeats": repeats,
                    "step_ms": st["step_ms"], "cpu_ms": st["cpu_ms"],
                    "evaluation_ms_median": st["evaluation_ms"]["median"],
                    "linear_solver_ms_median": st["linear_solver_ms"]["median"],
                    "preprocessor_ms_median": st["preprocessor_ms"]["median"],
                    "iterations_median": st["iterations"]["median"],
                    "max_abs_diff_vs_first": diff})
    return out


# --------------------------------------------------------------------------------------------
def check(value: float, budget: float, *, at_most: bool) -> dict:
    met = value <= budget if at_most else value >= budget
    return {"value": value, "budget": budget, "at_most": at_most, "met": bool(met)}


def _mb(x, sign: str = "") -> str:
    return "–" if x is None else f"{x:{sign}.0f}"


def memory_sentence(m: dict | None) -> str:
    """The markdown sentence on the memory baseline of the long run (JSON long.memory)."""
    if not m:
        return "(no memory baseline recorded: the peak RSS includes the simulator's)"
    peak = ("VmHWM was reset there, so peak RSS is the streaming's own"
            if m["peak_reset_at_baseline"] else
            "VmHWM could not be reset there: peak RSS is given only once it exceeds that peak")
    at = "; ".join(f"{n} frames: peak {_mb(a['peak_rss_mb'])} MB "
                   f"({_mb(a['peak_rss_over_baseline_mb'], '+')} MB), VmRSS {_mb(a['rss_mb'])} MB "
                   f"({_mb(a['rss_over_baseline_mb'], '+')} MB)"
                   for n, a in m["at_frames"].items())
    return (f"Memory: before the first add_frame (the simulator's scene made) VmRSS "
            f"{m['rss_baseline_mb']:.0f} MB (the baseline), peak so far "
            f"{m['peak_rss_before_streaming_mb']:.0f} MB (the simulator's); {peak}. "
            f"{at}.")


def markdown(res: dict) -> str:
    b = res["budgets"]
    lines = ["# LBAVis+EMT sequential benchmark (bench/bench_sequential.py)", "",
             f"Machine: {res['machine']['cpus']} CPUs, load average at start / end "
             f"{res['machine']['load_start']} / {res['machine']['load_end']}; "
             f"total bench time {res['total_s']:.0f} s. 400x400 SYN frames, "
             f"{FRAMES_PER_LAP} frames per lap, preset SYN (W=5, chi_e=3, K=3x5).", "",
             "## Budgets", "", "Budgets are on wall time.", "",
             "| figure | value | budget | met |", "|---|---|---|---|"]
    names = {"step_median_ms": "window step, median (ms)", "step_p95_ms": "window step, p95 (ms)",
             "orb_frames_per_s": "end to end ORB, frames/s (steady state)",
             "orb_frames_per_s_all": "end to end ORB, frames/s (all frames, incl. bootstrap)",
             "drift_ratio": "long run drift ratio", "unplaced": "long run unplaced frames",
             "latency_growth": "p95 latency (wall time) 3000-3300 / 100-400"}
    for key, name in names.items():
        c = b[key]
        op = "<=" if c["at_most"] else ">="
        lines.append(f"| {name} | {c['value']:.3g} | {op} {c['budget']:g} | "
                     f"{'yes' if c['met'] else '**no**'} |")
    g = res["long"].get("p95_latency_growth")
    if g:  # (the wall time's is the one judged; CPU time is less sensitive to other load)
        lines.append(f"| p95 process CPU time per frame 3000-3300 / 100-400 (beside the wall "
                     f"time's, not judged) | {g['process_cpu_time'] or float('nan'):.3g} | – | – |")
    d = res["cpu_diagnostics"]
    lines += ["", "Process CPU time (diagnostic, not a budget: other processes' load does not "
              "inflate it, but it sums every thread, so with the new frame's pairs matched on "
              f"{res['matching_threads']} threads 1 / CPU time per frame is not a frame rate): "
              f"end to end ORB {d['orb_cpu_frames_per_s']:.3g} frames of CPU time per s; "
              f"p95 CPU per frame 3000-3300 / 100-400 {d['latency_growth_cpu']:.3g}."]
    s = res["window_step"]
    lines += ["", "## Window step (long ORB run, all steps)", "",
              f"{s['steps']} steps, {s['steps_with_a_redo']} of them with a redo (the gating "
              "redo, or the redo after a failed solve's dropped samples), whose time is added "
              "to its step's.", "",
              "| | median | p95 |", "|---|---|---|"]
    for key, name in (("step_ms", "C++ step (assembly + Ceres), ms"),
                      ("solve_ms", "Ceres solve, ms"), ("cpu_ms", "process CPU per step, ms"),
                      ("evaluation_ms", "Ceres residual + Jacobian evaluation, ms"),
                      ("linear_solver_ms", "Ceres linear solves, ms")):
        lines.append(f"| {name} | {s[key]['median']:.2f} | {s[key]['p95']:.2f} |")
    chi = res["options"]["num_new"]
    lines.append(f"| per new frame (step / chi_e={chi}), ms | "
                 f"{s['step_ms']['median'] / chi:.2f} | {s['step_ms']['p95'] / chi:.2f} |")
    lines += ["", "Correspondences per step (median): "
              f"{s['correspondences']['median']:.0f} = window {s['window_corr']['median']:.0f} + "
              f"keyframe {s['keyframe_corr']['median']:.0f} + "
              f"loop {s['loop_corr']['median']:.0f} + "
              f"temporal {s['temporal_corr']['median']:.0f} (pairs with the W - 1 frames before "
              "the first new one, outside the window; medians, so the sum differs);"
              f" of these {s['fixed_pair_corr']['median']:.0f} in pairs of two fixed cameras "
              "(they constrain pi only).", "",
              "## End to end per frame (add_frame wall time, steady state)", "",
              "| detector | frames/s | frames/s all | CPU frames/s | latency median / p95 ms | "
              "features | matching | window solve | keyframes | bootstrap s |",
              "|---" * 10 + "|"]
    for det in ("orb", "sift"):
        t = res["throughput"][det]
        st = t["stage_ms_per_frame_steady"]
        lines.append(f"| {det} ({t['frames']} frames) | {t['frames_per_s_steady']:.1f} | "
                     f"{t['frames_per_s_all']:.1f} | {t['cpu_frames_per_s_steady']:.1f} | "
                     f"{t['latency_ms_steady']['median']:.1f} / "
                     f"{t['latency_ms_steady']['p95']:.1f} | {st['features']:.1f} | "
                     f"{st['matching']:.1f} | {st['window_solve']:.2f} | "
                     f"{st['keyframe_selection']:.2f} | {t['bootstrap_s']:.1f} |")
    p = res["throughput"]["orb"]["pairs"]
    lines += ["", "Stage times in ms per frame. CPU frames/s = 1 / process CPU time per frame "
              "(insensitive to other processes' load). ORB: "
              f"{p['registered_per_frame_after_bootstrap']:.1f} registered pairs per frame after "
              f"the bootstrap; the bootstrap tried {p['bootstrap_attempted']} pairs and "
              f"registered {p['bootstrap_registered']}."]
    if res.get("variants"):
        lines += ["", "ORB variants (options only, short runs, steady state):", "",
                  "| variant | frames | frames/s | CPU frames/s | matching ms | e_M px | drift |",
                  "|---" * 7 + "|"]
        for v in res["variants"]:
            lines.append(f"| {v['name']} | {v['frames']} | {v['frames_per_s_steady']:.1f} | "
                         f"{v['cpu_frames_per_s_steady']:.1f} | {v['matching_ms']:.1f} | "
                         f"{v['e_M_px']:.3f} | {v['drift_ratio']:.2f} |")
    L = res["long"]
    a = L["accuracy"]
    lines += ["", f"## Long sequence ({L['frames']} frames, ORB)", "",
              f"e_M {a['e_M_px']:.3f} px, max e_j {a['e_j_max_px']:.3f} px, drift ratio "
              f"{a['drift_ratio']:.3f}, unplaced {a['unplaced']}; p95 latency frames "
              f"{EARLY[0]}-{EARLY[1]} {L['latency_p95_early_ms']:.1f} ms, {LATE[0]}-{LATE[1]} "
              f"{L['latency_p95_late_ms'] or float('nan'):.1f} ms (process CPU per frame: "
              f"{L['cpu_p95_early_ms']:.1f} and {L['cpu_p95_late_ms'] or float('nan'):.1f} ms); "
              f"window step CPU median {L['step_cpu_ms_early']['median']:.2f} ms over frames "
              f"{EARLY[0]}-{EARLY[1]}, "
              f"{(L['step_cpu_ms_late'] or {'median': float('nan')})['median']:.2f} ms from "
              f"{LATE[0]}.", "",
              "Mean stage times per frame (ms): " + "; ".join(
                  f"frames {span}: " + ", ".join(f"{k} {v:.2f}" for k, v in st.items())
                  for span, st in L["stage_ms_per_frame"].items()) + ".", "",
              memory_sentence(L.get("memory")), "",
              "| frames | VmRSS MB | over baseline MB | peak RSS MB | peak over baseline MB | "
              "window frames | pairs | correspondences | keyframe blocks |",
              "|---|---|---|---|---|---|---|---|---|"]
    for st in L["checkpoints"]:
        lines.append(f"| {st['frames']} | {st['rss_mb']:.0f} | "
                     f"{_mb(st.get('rss_over_baseline_mb'), '+')} | "
                     f"{_mb(st.get('peak_rss_mb'))} | "
                     f"{_mb(st.get('peak_rss_over_baseline_mb'), '+')} | "
                     f"{st['window_frames']} | {st['window_pairs']} | "
                     f"{st['window_correspondences']} | {st['keyframe_blocks']} |")
    lines += ["", "## Linear solver of the window step (replay of the first "
              f"{res['solvers']['frames']} frames' window calls, pooled over "
              f"{res['solvers']['configs'][0]['repeats']} round-robin repeats)", "",
              "linear_solver \"auto\" = sparse_normal_cholesky; max abs diff = largest pose / "
              "plane difference to the first configuration (same solution).", "",
              "| solver | threads | fold fixed cameras | condensed pairs | step median ms | p95 | "
              "CPU median ms | evaluation | linear solve | max abs diff |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["solvers"]["configs"]:
        lines.append(f"| {r['solver']} | {r['threads']} | {r['fold_fixed_cameras']} | "
                     f"{r['condense_pairs']} | "
                     f"{r['step_ms']['median']:.2f} | {r['step_ms']['p95']:.2f} | "
                     f"{r['cpu_ms']['median']:.2f} | {r['evaluation_ms_median']:.2f} | "
                     f"{r['linear_solver_ms_median']:.2f} | {r['max_abs_diff_vs_first']:.1e} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=3300, help="long ORB run (>= 3300 for items 3)")
    ap.add_argument("--sift-frames", type=int, default=300)
    ap.add_argument("--solver-frames", type=int, default=400,
                    help="frames whose window calls are replayed per solver configuration")
    ap.add_argument("--repeats", type=int, default=3, help="replays per solver configuration")
    ap.add_argument("--variants", type=int, default=0, metavar="N",
                    help="also run ORB option variants over N frames each (not by default)")
    ap.add_argument("--out", type=Path, default=Path("bench/results/sequential.json"))
    args = ap.parse_args()
    t_bench = time.perf_counter()
    load_start = [round(x, 2) for x in os.getloadavg()]

    scene, camera, poses, valid = make_scene(args.frames)
    orb = SequentialOptions(features=FeatureOptions(detector="orb"))
    print(f"long ORB run: {args.frames} frames", flush=True)
    long_run = stream(scene, camera, poses, valid, args.frames, orb,
                      record_frames=min(args.solver_frames, args.frames),
                      checkpoints=(*CHECKPOINTS, args.frames), label="orb")
    print(f"SIFT run: {args.sift_frames} frames", flush=True)
    sift = SequentialOptions(features=FeatureOptions(detector="sift"))
    sift_run = stream(scene, camera, poses, valid, min(args.sift_frames, args.frames), sift)
    print(f"solver replays: {args.repeats} x {len(SOLVERS) * 2 + 2} configurations", flush=True)
    solvers = compare_solvers(scene.camera_matrix, long_run["recorded"], orb, args.repeats)

    variants = []
    for name, opts in VARIANTS.items() if args.variants else ():
        print(f"variant {name}: {args.variants} frames", flush=True)
        run = stream(scene, camera, poses, valid, min(args.variants, args.frames), opts)
        t, a = throughput(run), accuracy(run)
        variants.append({"name": name, "frames": t["frames"],
                         "frames_per_s_steady": t["frames_per_s_steady"],
                         "cpu_frames_per_s_steady": t["cpu_frames_per_s_steady"],
                         "matching_ms": t["stage_ms_per_frame_steady"]["matching"],
                         "e_M_px": a["e_M_px"], "drift_ratio": a["drift_ratio"],
                         "unplaced": a["unplaced"]})

    lat, cpu = long_run["latency_s"] * 1e3, long_run["cpu_s"] * 1e3
    base = long_run["memory_baseline"]
    has_late = args.frames >= LATE[1]
    early = float(np.percentile(lat[EARLY[0]:EARLY[1]], 95))
    late = float(np.percentile(lat[LATE[0]:LATE[1]], 95)) if has_late else None
    cpu_early = float(np.percentile(cpu[EARLY[0]:EARLY[1]], 95))
    cpu_late = float(np.percentile(cpu[LATE[0]:LATE[1]], 95)) if has_late else None
    step_cpu = np.array([s["cpu_ms"] for s in long_run["steps"]])
    step_frame = np.array([s["frame"] for s in long_run["steps"]])
    steps = step_stats(long_run["steps"])
    tp = {"orb": throughput(long_run), "sift": throughput(sift_run)}
    acc = accuracy(long_run)
    res = {
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "python": platform.python_version(), "opencv": cv2.__version__,
                    "load_start": load_start, "load_end": [round(x, 2) for x in os.getloadavg()]},
        "options": {k: v for k, v in asdict(orb).items() if k != "features"},
        "features": {"orb": asdict(orb.features), "sift": asdict(sift.features)},
        "window_step": steps,
        "window_step_per_new_frame_ms": {"median": steps["step_ms"]["median"] / orb.num_new,
                                         "p95": steps["step_ms"]["p95"] / orb.num_new},
        "throughput": tp,
        "long": {"frames": args.frames, "laps": args.frames / FRAMES_PER_LAP, "accuracy": acc,
                 "latency_p95_early_ms": early, "latency_p95_late_ms": late,
                 "cpu_p95_early_ms": cpu_early, "cpu_p95_late_ms": cpu_late,
                 "stage_ms_per_frame": {
                     f"{a}-{b}": {st: float(np.mean(v[a:b]) * 1e3)
                                  for st, v in long_run["stages"].items()}
                     for a, b in (EARLY, LATE) if b <= args.frames},
                 "step_cpu_ms_early": stats_ms(step_cpu[(step_frame >= EARLY[0])
                                                        & (step_frame < EARLY[1])]),
                 "step_cpu_ms_late": stats_ms(step_cpu[step_frame >= LATE[0]])
                 if has_late else None,
                 "latency_ms_by_segment": [
                     {"frames": [int(s[0]), int(s[-1])], **stats_ms(lat[s])}
                     for s in np.array_split(np.arange(args.frames), 11)],
                 "p95_latency_growth": {
                     "wall_time": late / early if late else None,
                     "process_cpu_time": cpu_late / cpu_early if cpu_late else None,
                     "judged": "wall_time", "budget": MAX_LATENCY_GROWTH},
                 "memory": {
                     "rss_baseline_mb": base["rss_mb"],
                     "peak_rss_before_streaming_mb": base["peak_rss_mb_before_streaming"],
                     "peak_reset_at_baseline": base["peak_reset"],
                     "at_frames": {str(n): {k: long_run["state"][n][k] for k in (
                         "peak_rss_mb", "peak_rss_over_baseline_mb", "rss_mb",
                         "rss_over_baseline_mb")}
                                   for n in MEMORY_AT if n in long_run["state"]}},
                 "checkpoints": [long_run["state"][k] for k in sorted(long_run["state"])]},
        "solvers": {"frames": min(args.solver_frames, args.frames),
                    "auto": "sparse_normal_cholesky", "configs": solvers},
        "variants": variants,
    }
    res["budgets"] = {
        "step_median_ms": check(steps["step_ms"]["median"], STEP_MEDIAN_MS, at_most=True),
        "step_p95_ms": check(steps["step_ms"]["p95"], STEP_P95_MS, at_most=True),
        "orb_frames_per_s": check(tp["orb"]["frames_per_s_steady"], MIN_ORB_FPS, at_most=False),
        "orb_frames_per_s_all": check(tp["orb"]["frames_per_s_all"], MIN_ORB_FPS,
                                      at_most=False),
        "drift_ratio": check(acc["drift_ratio"], MAX_DRIFT_RATIO, at_most=True),
        "unplaced": check(acc["unplaced"], 0, at_most=True),
        "latency_growth": check(late / early if late else float("nan"), MAX_LATENCY_GROWTH,
                                at_most=True),
    }
    res["cpu_diagnostics"] = {
        "latency_growth_cpu": cpu_late / cpu_early if cpu_late else float("nan"),
        "orb_cpu_frames_per_s": tp["orb"]["cpu_frames_per_s_steady"],
    }
    res["matching_threads"] = SequentialOptions().matching.num_threads
    res["total_s"] = time.perf_counter() - t_bench
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=2) + "\n")
    md = markdown(res)
    args.out.with_suffix(".md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
