"""Fisheye lenses: a wide-angle scope (400x400, f = 240 px, diagonal field of view ~135 deg)
through OpenCV's fisheye model (k1..k4 = LENS), from calibration to mosaic, in one run:

1. Calibration: a tracked checkerboard recording with that lens (simulate checkerboard
   --fisheye, the same K), calibrated with `--lens-model fisheye` and, as the baseline a
   pipeline without the fisheye model gives, with OpenCV's standard model (5 and 8
   coefficients): the largest distance between the calibrated and the true camera's pixels
   over the central 50 / 80 / 100 % of the image (camera_model_difference), the corner RMS, the
   focal length's error against its standard error.
2. Mosaicking: the SYN sequence filmed through that lens, run with camera.yaml's lens as
   simulated (true fisheye), as calibrated in 1 (fisheye model / standard model with 5
   coefficients), and with the lens ignored: e_M, drift and the mosaic's difference from the
   pinhole frames composed at the true homographies, for lba-emt, ba-emt and pairwise.

    python bench/bench_fisheye.py [--seeds 3] [--frames 152] [--out bench/results/fisheye.json]
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np
from _common import BenchRun, bench_args, fmt, md_table, run_note
from bench_lens import METHODS, case_medians, measure, pinhole_mosaic

from fusedmosaic.estimation.calibration import (
    CalibrationOptions,
    calibrate_recording,
    camera_model_difference,
)
from fusedmosaic.io import Camera, read_camera_yaml, read_dataset, write_camera_yaml
from fusedmosaic.simulation import (
    CheckerboardOptions,
    FetoscopyOptions,
    simulate_checkerboard,
    simulate_fetoscopy,
)

LENS = [0.05, -0.02, 0.01, 0.0]
FOCAL_FACTOR = 0.6
SIZE = 400
BOARD_DISTANCE_MM = 15.0  # the board reaches the periphery (where the models differ)
MODELS = {"fisheye": ("fisheye", None), "standard, 5": ("pinhole", 5),
          "standard, 8": ("pinhole", 8)}
CASES = ("true fisheye", "calibrated fisheye", "calibrated standard, 5", "lens ignored")
REGIONS = (0.5, 0.8, 1.0)


def calibrate(work: Path, seed: int) -> tuple[dict, dict]:
    """The calibration stage: {model: figures}, {model: Camera}."""
    rec = work / f"board_{seed}"
    simulate_checkerboard(rec, CheckerboardOptions(
        width=SIZE, height=SIZE, focal_factor=FOCAL_FACTOR, principal_offset_px=0.0,
        fisheye=LENS, distance_mm=BOARD_DISTANCE_MM, seed=seed), overwrite=True)
    truth = read_camera_yaml(rec / "truth_camera.yaml")
    figures, cameras = {}, {}
    for name, (model, coefficients) in MODELS.items():
        t0 = time.perf_counter()
        result = calibrate_recording(rec, CalibrationOptions(lens_model=model,
                                                             distortion=coefficients))
        intr = result.report["intrinsics"]
        K, K0 = result.camera.camera_matrix, truth.camera_matrix
        figures[name] = {
            **{f"difference_{int(100 * r)}_px": camera_model_difference(truth, result.camera, r)
               for r in REGIONS},
            "rms_px": intr["rms_px"], "views": intr["views"],
            "fx_error_px": float(K[0, 0] - K0[0, 0]), "fx_std_px": intr["std_fx_fy_cx_cy_px"][0],
            "calibrate_s": time.perf_counter() - t0}
        cameras[name] = result.camera
        f = figures[name]
        print(f"  calibrated {name}: {f['difference_80_px']:.3f} px over 80 % "
              f"({f['difference_100_px']:.2f} over all), RMS {f['rms_px']:.3f} px", flush=True)
    return figures, cameras


def with_camera(source: Path, target: Path, camera: Camera | None) -> Path:
    """A copy of dataset `source` whose camera.yaml has `camera`'s lens (None: no lens)."""
    shutil.rmtree(target, ignore_errors=True)
    shutil.copytree(source, target)
    given = read_camera_yaml(source / "camera.yaml")
    write_camera_yaml(target / "camera.yaml", Camera(
        given.width, given.height, camera_matrix=given.camera_matrix if camera is None
        else camera.camera_matrix, distortion=None if camera is None else camera.distortion,
        lens_model="pinhole" if camera is None else camera.lens_model,
        fov_mask_radius=given.fov_mask_radius))
    return target


def main() -> None:
    args = bench_args(__doc__, seeds=3, frames=152, out=Path("bench/results/fisheye.json"),
                      work=True).parse_args()
    bench = BenchRun(args.work)
    work = bench.work
    runs = []
    for seed in range(args.seeds):
        print(f"seed {seed}: calibration", flush=True)
        calibration, cameras = calibrate(work, seed)
        run = {"seed": seed, "calibration": calibration}
        options = FetoscopyOptions(n_frames=args.frames, seed=seed, focal_factor=FOCAL_FACTOR,
                                   width=SIZE, height=SIZE, lens_model="fisheye",
                                   lens_distortion=LENS)
        data = simulate_fetoscopy(work / f"syn_{seed}", options, overwrite=True)
        truth = pinhole_mosaic(options, read_dataset(data).ground_truth)
        lens_of = {"true fisheye": read_camera_yaml(data / "camera.yaml"),
                   "calibrated fisheye": cameras["fisheye"],
                   "calibrated standard, 5": cameras["standard, 5"], "lens ignored": None}
        for case in CASES:
            print(f"seed {seed}, {case}", flush=True)
            slug = case.replace(" ", "_").replace(",", "")
            case_data = with_camera(data, work / f"syn_{seed}_{slug}", lens_of[case])
            run[case] = measure(case_data, work / f"out_{seed}_{slug}", truth)
        runs.append(run)
    median = {
        "calibration": {m: {k: float(np.median([r["calibration"][m][k] for r in runs]))
                            for k in runs[0]["calibration"][m]} for m in MODELS},
        **case_medians(runs, CASES)}
    bench.write_results(args.out, markdown, seeds=args.seeds, frames=args.frames, lens=LENS,
                        focal_px=FOCAL_FACTOR * SIZE, runs=runs, median=median)


def markdown(res: dict) -> str:
    lines = ["# Fisheye lenses: calibration and mosaicking through OpenCV's fisheye model", "",
             run_note(res, "bench_fisheye.py", f", {res['seeds']} seeds, {res['frames']} frames")
             + f" Lens k1..k4 = {res['lens']} (fisheye model), 400x400, f = "
             f"{res['focal_px']:g} px. Medians over the seeds.", "",
             "## Calibration (checkerboard recording through the lens, 20 views)", "",
             "Largest pixel distance between the calibrated and the true camera over the central "
             "50 / 80 / 100 % of the image; fx error against its standard error.", ""]
    rows = []
    for m in MODELS:
        c = res["median"]["calibration"][m]
        rows.append([m, fmt(c["difference_50_px"], 3), fmt(c["difference_80_px"], 3),
                     fmt(c["difference_100_px"], 2), fmt(c["rms_px"], 4),
                     fmt(c["fx_error_px"], 3), fmt(c["fx_std_px"], 3)])
    lines += md_table(["model", "50 % px", "80 % px", "100 % px", "corner RMS px",
                       "fx error px", "fx std px"], rows)
    lines += ["", "## Mosaicking (SYN through the lens)", "",
              "camera.yaml's lens: as simulated, as calibrated above (fisheye model / standard "
              "model with 5 coefficients), or none. e_M and drift against the simulator's "
              "pinhole truth; mosaic difference: mean absolute grey-level difference of "
              "mosaic.png from the pinhole frames composed at the true homographies.", ""]
    rows = []
    for case in CASES:
        for m in METHODS:
            e = res["median"][case][m]
            rows.append([case, m, fmt(e["e_M_px"], 3), fmt(e["drift_ratio"], 2),
                         fmt(e.get("mosaic_difference"), 2)])
    lines += md_table(["camera.yaml lens", "method", "e_M px", "drift ratio",
                       "mosaic difference (grey)"], rows)
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
