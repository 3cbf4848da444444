"""Per-frame latency distributions of the streaming methods (issue 7, item 4): lba-emt
(LBAVis+EMT, seed 000) and kalman-robot (X_f, seed 004); median, p95, p99.

Frames are read from the simulated datasets into memory first (no disk I/O in the timings) and
fed one by one, as a live loop would:
* lba-emt, SequentialMosaicker.add_frame on the SYN (152 frames) and hand-held (155 frames)
  sequences of bench_table1 with the paper's presets. End to end = wall time of add_frame
  (features, matching, window step, keyframe selection), per frame; "steady" leaves out the
  bootstrap frames (the first 40 are bundle-adjusted together when the 40th arrives, one long
  frame). Solve only = the C++ window step (assembly + Ceres; a gating redo counted with its
  step), per step and per new frame (step / chi_e), also as seen from Python (binding call).
  The SYN run's window calls are saved (work/problems/) for the C++ replay (bench_cpp.py).
* kalman-robot, RobotPriorMosaicker.add_frame (NCC fwd+bwd, SSIM c_match, confidences, Kalman
  update) with the noisy robot (Test #5) on the pCLE circle and spiral, 512x448. End to end =
  wall time of add_frame; solve only = the Kalman filter stage (its `filter` timing); the NCC
  registration stage beside it.

    python bench/bench_latency.py [--quick] [--work DIR] [--out bench/results/latency.json]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from _common import (
    DEFAULT_WORK,
    RESULTS,
    BenchRun,
    WindowRecorder,
    bench_args,
    dist,
    ensure_dataset,
    machine_info,
    sequences,
)


def lba_latency(data: Path, base: str, log: Path | None) -> dict:
    from fusedmosaic import _core
    from fusedmosaic.estimation.sequential import SequentialMosaicker, SequentialOptions
    from fusedmosaic.evaluation import drift_ratio, frame_errors, mosaic_error
    from fusedmosaic.io import read_dataset

    ds = read_dataset(data)
    options = SequentialOptions.preset("phb" if base == "handheld" else "syn")
    frames = [np.asarray(ds.frames[k]) for k in range(len(ds))]
    n = len(frames)
    m = SequentialMosaicker(ds.camera, options)
    # The costs the window was built with, for the saved log (private: if it goes, no log).
    costs = getattr(m, "_costs", None)
    wopts = _core.SlidingWindowOptions(
        window_size=options.window_size, num_new=options.num_new, costs=costs
    )
    rec = WindowRecorder(m.window, m.K, costs, wopts, log if costs is not None else None)
    m.window = rec
    latency = np.zeros(n)
    G = np.full((n, 3, 3), np.nan)
    stage = {s: np.zeros(n) for s in ("features", "matching", "window_solve", "keyframe_selection")}

    def collect(results):
        for r in results:
            G[r.frame_id] = r.homography
            for s in stage:
                stage[s][r.frame_id] = r.timings.get(s, 0.0)

    t_all = time.perf_counter()
    for k in range(n):
        z = ds.cam_from_world[k] if ds.pose_valid[k] else None
        t0 = time.perf_counter()
        m.add_frame(frames[k], float(ds.timestamps[k]), z)
        latency[k] = time.perf_counter() - t0
        collect(m.finalized())
    t0 = time.perf_counter()
    collect(m.flush())
    flush_s = time.perf_counter() - t0
    total = time.perf_counter() - t_all
    rec.close()
    boot = min(options.bootstrap_frames, n)
    steady = latency[boot:]
    per_new = np.array(rec.step_cpp_s) / np.maximum(np.array(rec.step_frames), 1)
    e = frame_errors(G, ds.ground_truth, ds.camera.width, ds.camera.height)
    return {
        "method": "lba-emt",
        "frames": n,
        "options": {
            "window_size": options.window_size,
            "num_new": options.num_new,
            "num_clusters": options.num_clusters,
            "frames_per_cluster": options.frames_per_cluster,
            "bootstrap_frames": options.bootstrap_frames,
            "detector": options.features.detector,
        },
        "end_to_end_ms": {
            "all": dist(latency, 1e3),
            "steady": dist(steady, 1e3),
            "bootstrap_frame_ms": float(latency[boot - 1] * 1e3) if boot else None,
            "flush_ms": flush_s * 1e3,
        },
        "frames_per_s": {
            "all": n / total,
            "steady": 1.0 / float(steady.mean()) if len(steady) else None,
        },
        "solve_only_ms": {
            "per_step_cpp": dist(rec.step_cpp_s, 1e3),
            "per_step_python_call": dist(rec.step_wall_s, 1e3),
            "per_new_frame_cpp": dist(per_new, 1e3),
            "steps": len(rec.step_cpp_s),
        },
        "stage_mean_ms_steady": {
            s: float(v[boot:].mean() * 1e3) if n > boot else None for s, v in stage.items()
        },
        "accuracy": {
            "e_M_px": mosaic_error(e),
            "drift_ratio": drift_ratio(e),
            "unplaced": int((~np.isfinite(e)).sum()),
        },
        "window_log": (str(log) if (log is not None and costs is not None
                                    and rec.not_logged is None) else None),
        # why no log was written (calls the replays cannot reproduce), else None
        "window_log_not_written": rec.not_logged,
    }


def kalman_latency(root: Path) -> dict:
    from fusedmosaic.estimation.translation import RobotPriorMosaicker
    from fusedmosaic.io import read_dataset

    ds = read_dataset(root, robot_file="robot_noisy.csv")
    frames = [np.asarray(ds.frames[k]) for k in range(len(ds))]
    n = len(frames)

    def once():
        m = RobotPriorMosaicker(ds.camera)
        lat = np.zeros(n)
        results = []
        for k in range(n):
            t0 = time.perf_counter()
            results.append(m.add_frame(frames[k], ds.timestamps[k], ds.robot_xy_um[k]))
            lat[k] = time.perf_counter() - t0
        return lat, results

    once()  # warm-up: OpenCV DFT plans, imports
    lat, results = once()
    lat, results = lat[1:], results[1:]  # frame 0 only sets the origin
    stage = {
        s: np.array([r.timings.get(s, 0.0) for r in results]) for s in ("ncc", "ssim", "filter")
    }
    return {
        "method": "kalman-robot",
        "frames": n,
        "frame_size": [ds.camera.width, ds.camera.height],
        "robot": "robot_noisy.csv (Test #5)",
        "end_to_end_ms": {"all": dist(lat, 1e3)},
        "frames_per_s": {"all": len(lat) / float(lat.sum())},
        "solve_only_ms": {"kalman_filter": dist(stage["filter"], 1e3)},
        "stage_ms": {"ncc_fwd_bwd": dist(stage["ncc"], 1e3), "ssim": dist(stage["ssim"], 1e3)},
    }


def main(argv=None) -> dict:
    args = bench_args(
        __doc__,
        quick="60-frame fetoscopy, short pCLE paths",
        work=f"datasets and saved problems (run_all uses {DEFAULT_WORK})",
        out=RESULTS / "latency.json",
    ).parse_args(argv)
    bench = BenchRun(args.work)
    args.work = bench.work
    from dataclasses import replace

    from fusedmosaic.simulation import PcleOptions, simulate_pcle

    res: dict = {
        "benchmark": "streaming latency (bench/bench_latency.py)",
        "quick": args.quick,
        "machine": machine_info(),
        "lba-emt": {},
        "kalman-robot": {},
    }
    for seq in sequences(args.quick):
        if seq.black:
            continue
        data = ensure_dataset(args.work, seq)
        log = args.work / "problems" / f"window-{seq.name}.txt" if seq.base == "syn" else None
        r = lba_latency(data, seq.base, log)
        res["lba-emt"][seq.name] = r
        e2e, solve = r["end_to_end_ms"], r["solve_only_ms"]
        print(
            f"lba-emt {seq.name:<9} end to end (steady) median {e2e['steady']['median']:.1f} "
            f"p95 {e2e['steady']['p95']:.1f} p99 {e2e['steady']['p99']:.1f} ms; window step "
            f"median {solve['per_step_cpp']['median']:.2f} p95 {solve['per_step_cpp']['p95']:.2f}"
            f" p99 {solve['per_step_cpp']['p99']:.2f} ms",
            flush=True,
        )
    for trajectory in ("circle", "spiral"):
        o = PcleOptions(trajectory=trajectory)
        if args.quick:
            o = replace(o, n_frames=40)
        root = simulate_pcle(args.work / f"pcle-{trajectory}-{o.n_frames}", o, overwrite=True)
        r = kalman_latency(root)
        res["kalman-robot"][trajectory] = r
        e2e = r["end_to_end_ms"]["all"]
        kf = r["solve_only_ms"]["kalman_filter"]
        print(
            f"kalman-robot {trajectory:<6} end to end median {e2e['median']:.2f} p95 "
            f"{e2e['p95']:.2f} p99 {e2e['p99']:.2f} ms; filter median {kf['median']:.4f} p99 "
            f"{kf['p99']:.4f} ms",
            flush=True,
        )
    return bench.finish(res, args.out)


if __name__ == "__main__":
    main(sys.argv[1:])
