"""The tracker-video clock offset `fusedmosaic calibrate` estimates (calibration.json
hand_eye.tracker_time_offset) against the checkerboard simulator's truth: is its standard error
(std_s) honest? Over simulator seeds, each with a true offset drawn uniformly in +-80 ms
(CheckerboardOptions.tracker_delay_s), the error estimate - truth against the reported std_s:
coverage of +-1.96 std_s (95 % when honest), RMS error over the median std_s, RMS of the
standardised errors (1 when honest) and the mean error (a bias no standard error covers).

The board corners are the simulator's projected with 0.05 px Gaussian noise (the board search's
~0.04 px; no rendering, as tests/test_calibration.py's _calibrated_from_projected_corners), and
calibrate_detections runs as `fusedmosaic calibrate` does after its board search (time offset
"auto", default bound +-0.5 s). Configurations: the simulator's EM tracker (40 Hz, 0.9 deg /
0.25 mm per axis), the same noise at 10 Hz, and bench_calibration's slow precise tracker (10 Hz,
0.1 deg / 0.03 mm), also with its samples half a period later against the frames (every seed
keeps the simulator's one phase, so the splines' interpolation error along the motions biases
all seeds alike; another phase, another bias). Where the report carries the curvature (i.i.d.)
figure beside the block bootstrap's, both are scored. Still views alone (the board lost while
the scope moves, or 2 frames per view) also score the standard error without its interpolation
term (std_interpolation_s: the cubic and the linear interpolation's estimates apart), as it was
before that term. (Not scored: 2 frames per view at 10 Hz, views 80 ms apart with 43 deg moves
in 40 ms, faster than the tracker samples: errors of 7.5-18 ms against std_s 1.9-3.7 ms, and on
one of 3 seeds the hand-eye fit failed.)

    python bench/bench_time_offset_se.py [--seeds 20] [--configs 0 1 2] [--jobs 2]
        [--out bench/results/time_offset_se.json]
"""

from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from _common import BenchRun, add_options, bench_args, fmt, md_table, run_note
from scipy.spatial.transform import Rotation

from fusedmosaic.estimation.calibration import (
    BoardDetections,
    CalibrationOptions,
    calibrate_detections,
)
from fusedmosaic.io import TrackingSamples
from fusedmosaic.simulation import CheckerboardOptions, generate_checkerboard

STILL_ONLY = "board_lost_while_moving"  # a configuration key, not a simulator option
CONFIGS = {
    "40 Hz, noise 0.9 deg / 0.25 mm": {},
    "10 Hz, noise 0.9 deg / 0.25 mm": {"tracker_rate_hz": 10.0},
    "10 Hz, noise 0.1 deg / 0.03 mm": {
        "tracker_rate_hz": 10.0, "rot_sigma_deg": 0.1, "trans_sigma_mm": 0.03},
    # the same with the tracker's samples half a period later against the frames and motions
    # (the simulator's default phase is 7.1 ms)
    "10 Hz, noise 0.1 deg / 0.03 mm, tracker phase 57.1 ms": {
        "tracker_rate_hz": 10.0, "rot_sigma_deg": 0.1, "trans_sigma_mm": 0.03,
        "tracker_offset_s": 0.0571},
    # Still views alone: the board found only while the scope rests (lost to motion blur during
    # the moves).
    "40 Hz, noise 0.9 deg / 0.25 mm, board lost while moving": {STILL_ONLY: True},
    "10 Hz, noise 0.9 deg / 0.25 mm, board lost while moving": {
        "tracker_rate_hz": 10.0, STILL_ONLY: True},
}
MAX_TRUE_OFFSET_S = 0.08
CORNER_NOISE_PX = 0.05
Z95 = 1.959964


def measure(seed: int, changes: dict) -> dict:
    truth = float(np.random.default_rng(1000 + seed).uniform(-MAX_TRUE_OFFSET_S,
                                                               MAX_TRUE_OFFSET_S))
    changes = dict(changes)
    still_only = changes.pop(STILL_ONLY, False)
    scene = generate_checkerboard(CheckerboardOptions(seed=seed, tracker_delay_s=truth,
                                                      **changes))
    T = scene.tracker_from_sensor
    tracking = TrackingSamples(scene.tracker_timestamps, T[:, :3, 3].copy(),
                               Rotation.from_matrix(T[:, :3, :3]).as_quat())
    detections = scene.projected_detections(CORNER_NOISE_PX, np.random.default_rng(seed))
    if still_only:
        keep = scene.resting[detections.frames]
        detections = BoardDetections(
            [p for p, k in zip(detections.points, keep, strict=True) if k],
            detections.frames[keep], detections.ids[keep], detections.times[keep],
            detections.size)
    t0 = time.perf_counter()
    result = calibrate_detections(detections, CalibrationOptions(), tracking=tracking)
    elapsed = time.perf_counter() - t0
    he = result.report["hand_eye"]
    if "tracker_time_offset" not in he:
        return {"seed": seed, "true_s": truth, "failed": he.get("failed", "no offset")}
    off = he["tracker_time_offset"]
    run = {"seed": seed, "true_s": truth, "estimate_s": off["estimate_s"],
           "error_s": off["estimate_s"] - truth, "std_s": off["std_s"],
           "applied_s": off["applied_s"], "views": off["views"], "calibrate_s": elapsed}
    for key in ("std_curvature_s", "std_bootstrap_s", "bootstrap_blocks",
                "std_interpolation_s", "estimate_linear_s", "frames_moving"):
        if key in off:
            run[key] = off[key]
    return run


def score(errors: np.ndarray, stds: np.ndarray) -> dict:
    z = errors / stds
    covered = int(np.sum(np.abs(z) <= Z95))
    return {"n": int(errors.size), "covered_1.96": covered,
            "coverage_1.96": covered / errors.size,
            "rms_error_ms": float(1e3 * np.sqrt(np.mean(errors ** 2))),
            "mean_error_ms": float(1e3 * errors.mean()),
            "sd_error_ms": float(1e3 * errors.std(ddof=1)),
            "median_std_ms": float(1e3 * np.median(stds)),
            "rms_error_over_median_std": float(np.sqrt(np.mean(errors ** 2)) / np.median(stds)),
            "rms_z": float(np.sqrt(np.mean(z ** 2))),
            "max_abs_z": float(np.abs(z).max())}


def main() -> None:
    ap = bench_args(__doc__, seeds=20)
    ap.add_argument("--configs", type=int, nargs="+", default=list(range(len(CONFIGS))),
                    help="indices into CONFIGS")
    ap.add_argument("--jobs", type=int, default=1, help="processes (seeds run in parallel)")
    args = add_options(ap, out=Path("bench/results/time_offset_se.json")).parse_args()
    bench = BenchRun(folder=False)
    labels = list(CONFIGS)
    tasks = [(c, seed) for c in args.configs for seed in range(args.seeds)]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        done = dict(zip(tasks, pool.map(measure, [s for _, s in tasks],
                                        [CONFIGS[labels[c]] for c, _ in tasks]), strict=True))
    configs = []
    for c in args.configs:
        label, changes = labels[c], CONFIGS[labels[c]]
        runs = []
        for seed in range(args.seeds):
            run = done[c, seed]
            runs.append(run)
            if "failed" in run:
                print(f"{label}, seed {seed}: failed: {run['failed']}", flush=True)
                continue
            print(f"{label}, seed {seed}: true {1e3 * run['true_s']:+.2f} ms, error "
                  f"{1e3 * run['error_s']:+.3f} ms, std {1e3 * run['std_s']:.3f} ms"
                  + (f" (curvature {1e3 * run['std_curvature_s']:.3f})"
                     if "std_curvature_s" in run else "")
                  + f", {run['calibrate_s']:.1f} s", flush=True)
        ok = [r for r in runs if "failed" not in r]
        errors = np.array([r["error_s"] for r in ok])
        summary = {"reported": score(errors, np.array([r["std_s"] for r in ok])),
                   "failed": len(runs) - len(ok)}
        if ok and all("std_curvature_s" in r for r in ok):
            summary["curvature_only"] = score(errors,
                                              np.array([r["std_curvature_s"] for r in ok]))
        if ok and any("std_interpolation_s" in r for r in ok):  # still views: as before it
            summary["without_interpolation"] = score(errors, np.array(
                [max(r["std_curvature_s"], r.get("std_bootstrap_s") or 0.0) for r in ok]))
        configs.append({"configuration": label, "options": changes, "runs": runs,
                        "summary": summary})
        print(f"{label}: {summary}", flush=True)
    bench.write_results(args.out, markdown, seeds=args.seeds, jobs=args.jobs,
                        max_true_offset_s=MAX_TRUE_OFFSET_S, corner_noise_px=CORNER_NOISE_PX,
                        configurations=configs)


def markdown(res: dict) -> str:
    lines = ["# Standard error of calibrate's tracker time offset against the simulator's truth",
             "", run_note(res, f"bench_time_offset_se.py --jobs {res['jobs']}",
                          f", {res['seeds']} seeds per "
                          "configuration") + " Simulator defaults (20 views at 480x480, 8 "
                          "frames per view at 25 frames/s, half resting), the true offset "
                          f"uniform in +-{1e3 * res['max_true_offset_s']:g} ms per seed, corners "
                          f"projected with {res['corner_noise_px']:g} px noise; time offset "
                          "'auto'. Coverage: the share of seeds whose error lies within +-1.96 "
                          "reported standard errors (95 % when honest); RMS z: RMS of error / "
                          "std (1 when honest). 'curvature' is the i.i.d. figure from the cost's "
                          "curvature alone (before the block bootstrap it was std_s). Mean "
                          "error: a bias shared by the seeds, which keep the simulator's one "
                          "tracker phase against the frames and motions (7.1 ms unless named): "
                          "the splines' interpolation error, which the standard error covers but "
                          "does not remove. 'without the interpolation term': the still-views "
                          "configurations' std_s before it was at least the distance between "
                          "the cubic and the linear interpolation's estimates.", ""]
    rows = []
    for c in res["configurations"]:
        s = c["summary"]
        for what, key in (("reported std_s", "reported"),
                          ("without the interpolation term", "without_interpolation"),
                          ("curvature only", "curvature_only")):
            if key not in s:
                continue
            m = s[key]
            rows.append([c["configuration"], what, f"{m['covered_1.96']}/{m['n']}",
                         fmt(m["rms_error_ms"], 3), fmt(m["mean_error_ms"], 3),
                         fmt(m["sd_error_ms"], 3), fmt(m["median_std_ms"], 3),
                         fmt(m["rms_error_over_median_std"], 2), fmt(m["rms_z"], 2),
                         fmt(m["max_abs_z"], 2), str(s["failed"])])
    lines += md_table(["configuration", "standard error", "within +-1.96 std", "RMS error ms",
                       "mean error ms", "SD of errors ms", "median std ms",
                       "RMS error / median std", "RMS z", "max abs z", "failed"], rows)
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
