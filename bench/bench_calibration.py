"""Calibration from a tracked checkerboard recording (`fusedmosaic calibrate`) against the
checkerboard simulator's truth: intrinsics (focal, principal point, camera-model difference over
the central 80 % of the image) and the hand-eye transform, the maximum-likelihood refinement
against its closed-form start from relative motions (the baseline, same run, same views), over
seeds, EM-tracker noise levels and numbers of views; with the time calibration takes.

    python bench/bench_calibration.py [--seeds 5] [--out bench/results/calibration.json]
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from _common import BenchRun, bench_args, fmt, md_table, ratio, run_note
from scipy.spatial.transform import Rotation

from fusedmosaic.estimation.calibration import calibrate_recording, camera_model_difference
from fusedmosaic.io import read_camera_yaml, read_hand_eye
from fusedmosaic.simulation import CheckerboardOptions, simulate_checkerboard

# (label, simulator options): the default recording (20 views, Aurora-in-the-laboratory noise
# 0.9 deg / 0.25 mm), twice that noise, a short recording of 8 views, and a slow precise tracker
# (10 Hz, 0.1 deg / 0.03 mm: interpolating it across a motion errs by millimetres).
CONFIGS = {
    "20 views, noise 0.9 deg / 0.25 mm": {},
    "20 views, noise 1.8 deg / 0.5 mm": {"rot_sigma_deg": 1.8, "trans_sigma_mm": 0.5},
    "8 views, noise 0.9 deg / 0.25 mm": {"n_views": 8},
    "20 views, 10 Hz tracker, noise 0.1 deg / 0.03 mm": {
        "tracker_rate_hz": 10.0, "rot_sigma_deg": 0.1, "trans_sigma_mm": 0.03},
}


def hand_eye_errors(X, X0) -> tuple[float, float]:
    E = np.linalg.inv(X0) @ np.asarray(X)
    return (float(np.rad2deg(Rotation.from_matrix(E[:3, :3]).magnitude())),
            float(np.linalg.norm(np.asarray(X)[:3, 3] - X0[:3, 3])))


def measure(root: Path) -> dict:
    t0 = time.perf_counter()
    result = calibrate_recording(root)
    elapsed = time.perf_counter() - t0
    truth = read_camera_yaml(root / "truth_camera.yaml")
    X0 = read_hand_eye(root / "truth_hand_eye.txt")
    K, Kt = result.camera.camera_matrix, truth.camera_matrix
    he = result.report["hand_eye"]
    rot, trans = hand_eye_errors(result.hand_eye, X0)
    rot_cf, trans_cf = hand_eye_errors(he["sensor_from_camera_closed_form"], X0)
    return {
        "frames": result.report["frames"], "board_found": result.report["board_found"],
        "intrinsics_views": result.report["intrinsics"]["views"],
        "rms_px": result.report["intrinsics"]["rms_px"],
        "focal_error_percent": float(100 * max(abs(K[0, 0] / Kt[0, 0] - 1),
                                               abs(K[1, 1] / Kt[1, 1] - 1))),
        "principal_point_error_px": float(np.linalg.norm(K[:2, 2] - Kt[:2, 2])),
        "camera_model_difference_px": camera_model_difference(truth, result.camera),
        "hand_eye_views": he["views"],
        "hand_eye_rotation_error_deg": rot, "hand_eye_translation_error_mm": trans,
        "closed_form_rotation_error_deg": rot_cf, "closed_form_translation_error_mm": trans_cf,
        # calibrate's expected error (RMS magnitude: bootstrap, or the tracker noise if larger)
        # against the true error; the Jacobian's from the tracker noise alone beside it.
        "reported_rotation_rms_deg": he["rotation_error_rms_deg"],
        "reported_translation_rms_mm": he["translation_error_rms_mm"],
        "tracker_noise_rotation_rms_deg":
            he["standard_errors"]["from_tracker_noise"]["rotation_rms_deg"],
        "tracker_noise_translation_rms_mm":
            he["standard_errors"]["from_tracker_noise"]["translation_rms_mm"],
        "hand_eye_mode": he["mode"],
        "still_views": he.get("still_views", 0),
        "distinct_views": result.report["distinct_views"],
        "board_scale": he["board_scale"]["ratio"],
        "board_scale_std": he["board_scale"]["std"],
        "tracker_sigma_seen_deg": he["tracker_sigma_deg"],
        "tracker_sigma_seen_mm": he["tracker_sigma_mm"],
        "board_through_tracker_px_median": he["board_through_tracker_px_median"],
        "calibrate_s": elapsed, "board_search_s": result.report["timings_s"]["board_search"],
    }


def main() -> None:
    args = bench_args(__doc__, seeds=5, out=Path("bench/results/calibration.json"),
                      work=True).parse_args()
    bench = BenchRun(args.work)
    configs = []
    for label, changes in CONFIGS.items():
        runs = []
        for seed in range(args.seeds):
            root = bench.work / f"board_{len(configs)}_{seed}"
            simulate_checkerboard(root, CheckerboardOptions(seed=seed, **changes),
                                  overwrite=True)
            run = measure(root)
            runs.append(run)
            print(f"{label}, seed {seed}: focal {run['focal_error_percent']:.3f} %, model "
                  f"{run['camera_model_difference_px']:.3f} px, hand-eye "
                  f"{run['hand_eye_rotation_error_deg']:.3f} deg / "
                  f"{run['hand_eye_translation_error_mm']:.3f} mm (closed form "
                  f"{run['closed_form_rotation_error_deg']:.3f} / "
                  f"{run['closed_form_translation_error_mm']:.3f}), {run['calibrate_s']:.2f} s",
                  flush=True)
        median = {k: float(np.median([r[k] for r in runs])) for k in runs[0]
                  if isinstance(runs[0][k], float | int)}
        # True error against the reported one over the seeds (RMS / mean; 1 = honest).
        for q, unit in (("rotation", "deg"), ("translation", "mm")):
            true = np.array([r[f"hand_eye_{q}_error_{unit}"] for r in runs])
            told = np.array([r[f"reported_{q}_rms_{unit}"] for r in runs])
            median[f"{q}_true_over_reported"] = float(np.sqrt(np.mean(true ** 2)) / told.mean())
        configs.append({"configuration": label, "options": changes, "runs": runs,
                        "median": median})
    bench.write_results(args.out, markdown, seeds=args.seeds, configurations=configs)


def markdown(res: dict) -> str:
    lines = ["# Calibration from a tracked checkerboard recording against the simulator's truth",
             "", run_note(res, "bench_calibration.py", f", {res['seeds']} seeds per "
                          "configuration") + " Simulator defaults: 480x480, f = 480 px, "
             "k1 = -0.30, k2 = 0.10, 9x6 inner corners of 2 mm, 8 frames per view at 25 "
             "frames/s (half of them resting), tracker at 40 Hz. Medians over the seeds; "
             "hand-eye errors are the rotation angle and translation distance to the true "
             "sensor_from_camera; the closed form (relative motions, all frames) is the "
             "refinement's start. 'reported' is calibrate's expected error (RMS magnitude); "
             "'true / reported' is the RMS of the true errors over the seeds over the mean "
             "reported (1: honest). Noise seen: the tracker noise the fit finds (simulated "
             "in the configuration's name).", ""]
    rows = []
    for c in res["configurations"]:
        m = c["median"]
        rows.append([c["configuration"], fmt(m["board_found"], 0), fmt(m["rms_px"], 3),
                     fmt(m["focal_error_percent"], 3), fmt(m["principal_point_error_px"], 2),
                     fmt(m["camera_model_difference_px"], 3),
                     f"{fmt(m['hand_eye_rotation_error_deg'], 3)} / "
                     f"{fmt(m['closed_form_rotation_error_deg'], 3)}",
                     f"{fmt(m['hand_eye_translation_error_mm'], 3)} / "
                     f"{fmt(m['closed_form_translation_error_mm'], 3)}",
                     " / ".join(fmt(ratio(m[f"closed_form_{q}"], m[f"hand_eye_{q}"]), 1)
                                for q in ("rotation_error_deg", "translation_error_mm")),
                     f"{fmt(m['reported_rotation_rms_deg'], 3)} / "
                     f"{fmt(m['reported_translation_rms_mm'], 3)}",
                     f"{fmt(m['rotation_true_over_reported'], 2)} / "
                     f"{fmt(m['translation_true_over_reported'], 2)}",
                     f"{fmt(m['tracker_sigma_seen_deg'], 2)} / "
                     f"{fmt(m['tracker_sigma_seen_mm'], 3)}",
                     fmt(m["distinct_views"], 0), fmt(m["still_views"], 0),
                     fmt(m["board_scale"], 4),
                     fmt(m["board_through_tracker_px_median"], 1), fmt(m["calibrate_s"], 2)])
    lines += md_table(["configuration", "views found", "RMS px", "focal error %",
                       "principal point error px", "camera model difference px",
                       "hand-eye rotation error deg (ML / closed form)",
                       "translation error mm (ML / closed form)",
                       "closed form / ML error (rotation / translation)",
                       "reported error deg / mm", "true / reported (rotation / translation)",
                       "noise seen deg / mm", "distinct views", "still views",
                       "board / tracker scale", "board through tracker px", "calibrate s"], rows)
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
