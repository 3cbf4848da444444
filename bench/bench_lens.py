"""Lens distortion: the SYN sequence filmed through a fetoscope's barrel lens (k1 -0.30, k2 0.10,
p1 0.0008, p2 -0.0005: FetoscopyOptions.lens_distortion) against the same trajectory through a
pinhole, and against the lens ignored (camera.yaml without its distortion_coefficients: the
baseline a pipeline without lens handling gives), in the same run: e_M / drift of lba-emt,
ba-emt and pairwise, the mosaic's difference from the pinhole frames composed at the true
homographies, and the per-frame time of lba-emt (the undistortion is one remap per frame).

    python bench/bench_lens.py [--seeds 3] [--frames 152] [--out bench/results/lens.json]
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import cv2
import numpy as np
from _common import BenchRun, bench_args, fmt, md_table, run_note

from fusedmosaic.compositing import render_mosaic
from fusedmosaic.evaluation import evaluate_output, mosaic_difference
from fusedmosaic.io import read_camera_yaml, read_dataset, write_camera_yaml
from fusedmosaic.runner import run_dataset
from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy
from fusedmosaic.simulation.fetoscopy import generate_fetoscopy

LENS = [-0.30, 0.10, 0.0008, -0.0005]
METHODS = ("lba-emt", "ba-emt", "pairwise")
CASES = ("pinhole", "lens", "lens ignored")


def pinhole_mosaic(options: FetoscopyOptions, G_true: np.ndarray):
    """The simulator's frames without lens or noise, composed at the true homographies."""
    scene = generate_fetoscopy(options)
    frames = [scene.pinhole(k) for k in range(scene.n_frames)]
    return render_mosaic(frames, G_true, *scene.size)


def measure(data: Path, out: Path, truth, options: dict | None = None, blend=None,
            extra=None) -> dict:
    """METHODS run on `data` (options: method -> its options, blend: run_dataset's), scored
    against the truth and `truth` (a RenderedMosaic); extra(mosaic, origin) -> more figures."""
    row = {}
    for method in METHODS:
        target = out / method
        shutil.rmtree(target, ignore_errors=True)
        t0 = time.perf_counter()
        run_dataset(data, method, target, progress=False,
                    options=None if options is None else options[method], blend=blend)
        elapsed = time.perf_counter() - t0
        ev = evaluate_output(target, data)
        report = json.loads((target / "report.json").read_text())
        entry = {"e_M_px": ev["e_M_px"], "drift_ratio": ev["drift_ratio"],
                 "placed": ev["placed"], "run_s": elapsed,
                 "features_s": report["timings_s"].get("features")}
        mosaic = cv2.imread(str(target / "mosaic.png"), cv2.IMREAD_COLOR)
        if mosaic is not None:
            d = mosaic_difference(mosaic, report["mosaic"]["origin_reference_px"], truth.image,
                                  (truth.plan.x0, truth.plan.y0), truth.covered)
            entry["mosaic_difference"] = d["mean_abs_difference"]
            entry["mosaic_compared_fraction"] = d["compared_fraction"]
            if extra is not None:
                entry.update(extra(mosaic, report["mosaic"]["origin_reference_px"]))
        if method == "lba-emt":
            entry["frame_ms_median"] = (report.get("latency_ms") or {}).get("median")
        row[method] = entry
        print(f"  {method}: e_M {entry['e_M_px']:.3f} px, drift {fmt(entry['drift_ratio'])}, "
              f"mosaic difference {entry.get('mosaic_difference', float('nan')):.2f}, "
              f"{elapsed:.1f} s", flush=True)
    return row


def case_medians(runs: list[dict], cases) -> dict:
    """{case: {method: {figure: median over the runs}}} of measure()'s rows (figures that are
    None in the first run are left out)."""
    return {case: {m: {k: float(np.median([r[case][m][k] for r in runs]))
                       for k in runs[0][case][m] if runs[0][case][m][k] is not None}
                   for m in METHODS} for case in cases}


def main() -> None:
    args = bench_args(__doc__, seeds=3, frames=152, out=Path("bench/results/lens.json"),
                      work=True).parse_args()
    bench = BenchRun(args.work)
    work = bench.work
    runs = []
    for seed in range(args.seeds):
        run = {"seed": seed}
        for case in CASES:
            print(f"seed {seed}, {case}", flush=True)
            lens = None if case == "pinhole" else LENS
            options = FetoscopyOptions(n_frames=args.frames, seed=seed, lens_distortion=lens)
            data = work / f"syn_{seed}_{case.replace(' ', '_')}"
            simulate_fetoscopy(data, options, overwrite=True)
            if case == "lens ignored":
                cam = read_camera_yaml(data / "camera.yaml")
                cam.distortion = None
                write_camera_yaml(data / "camera.yaml", cam)
            truth = pinhole_mosaic(options, read_dataset(data).ground_truth)
            run[case] = measure(data, work / f"out_{seed}_{case.replace(' ', '_')}", truth)
        runs.append(run)
    median = case_medians(runs, CASES)
    bench.write_results(args.out, markdown, seeds=args.seeds, frames=args.frames, lens=LENS,
                        runs=runs, median=median)


def markdown(res: dict) -> str:
    lines = ["# Lens distortion: SYN through a fetoscope's barrel lens", "",
             run_note(res, "bench_lens.py", f", {res['seeds']} seeds, {res['frames']} frames")
             + f" Lens k1 k2 p1 p2 = {res['lens']} (400x400, f = 480 px). Medians over the "
             "seeds. e_M and drift against the simulator's pinhole truth; mosaic difference: "
             "mean absolute grey-level difference of mosaic.png from the pinhole frames "
             "composed at the true homographies, where both show. 'lens ignored': the same "
             "frames with camera.yaml's distortion_coefficients removed (a pipeline without "
             "lens handling). The pinhole sequence has its own texture (the lens widens the "
             "area filmed), so it is a reference, not a pair.", ""]
    rows = []
    for case in CASES:
        for m in METHODS:
            e = res["median"][case][m]
            rows.append([case, m, fmt(e["e_M_px"], 3), fmt(e["drift_ratio"], 2),
                         fmt(e.get("mosaic_difference"), 2), fmt(e.get("features_s"), 2),
                         fmt(e.get("frame_ms_median"), 1)])
    lines += md_table(["case", "method", "e_M px", "drift ratio", "mosaic difference (grey)",
                       "features s", "lba-emt ms per frame (median)"], rows)
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
