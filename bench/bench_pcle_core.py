"""Throughput of the pCLE online core (paper 004): NCC forward+backward, SSIM c_match,
confidences and the Kalman update, per frame, on synthetic 512x448 frames.

Budget (design.md): >= 100 frames/s on 2 cores. Writes bench/results/pcle_core.json.

    python bench/bench_pcle_core.py [--frames 200] [--out bench/results/pcle_core.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from fusedmosaic.estimation.kalman import KalmanOptions, RobotKalmanFilter
from fusedmosaic.registration.ncc import aligned_overlap_ssim, register_ncc

H, W = 448, 512  # CellVizio export size, paper 004 Sec. III-B


def make_sequence(n_frames: int, seed: int = 0) -> tuple[list[np.ndarray], np.ndarray]:
    """Frames cropped (sub-pixel, bilinear) along a circle of radius 120 px, 4 px/frame, from a
    cell-like texture, with sensor noise. Returns uint8 frames and the true positions (N, 2)."""
    rng = np.random.default_rng(seed)
    radius, speed = 120.0, 4.0
    theta = np.arange(n_frames) * speed / radius
    pos = radius * np.stack([np.cos(theta), np.sin(theta)], axis=1)
    pos -= pos[0]
    margin = 2 * int(radius) + 40
    scene = ndimage.gaussian_filter(rng.standard_normal((H + margin, W + margin)), 3.0)
    scene = ((scene - scene.min()) / np.ptp(scene) * 255.0).astype(np.float32)
    frames = []
    for x, y in pos:
        center = (W / 2 + margin / 2 + x, H / 2 + margin / 2 + y)
        crop = cv2.getRectSubPix(scene, (W, H), center)
        crop = crop + rng.normal(0.0, 4.0, crop.shape).astype(np.float32)
        frames.append(np.clip(crop, 0, 255).astype(np.uint8))
    return frames, pos


def run(frames, robot_dx, *, pyramid_levels: int, ssim_downsample: int) -> dict:
    kf = RobotKalmanFilter(KalmanOptions())
    per_stage = {"ncc": [], "ssim": [], "filter": [], "total": []}
    dxs = []
    for i in range(1, len(frames)):
        t0 = time.perf_counter()
        reg = register_ncc(frames[i - 1], frames[i], pyramid_levels=pyramid_levels)
        t1 = time.perf_counter()
        c_match = aligned_overlap_ssim(frames[i - 1], frames[i], reg.dx, downsample=ssim_downsample)
        t2 = time.perf_counter()
        kf.update(reg.dx, robot_dx[i - 1], c_match)
        t3 = time.perf_counter()
        per_stage["ncc"].append(t1 - t0)
        per_stage["ssim"].append(t2 - t1)
        per_stage["filter"].append(t3 - t2)
        per_stage["total"].append(t3 - t0)
        dxs.append(reg.dx)
    medians_ms = {k: 1e3 * float(np.median(v)) for k, v in per_stage.items()}
    return {
        "pyramid_levels": pyramid_levels,
        "ssim_downsample": ssim_downsample,
        "median_ms": medians_ms,
        "p95_total_ms": 1e3 * float(np.percentile(per_stage["total"], 95)),
        "frames_per_s_median": 1e3 / medians_ms["total"],
        "ncc_max_abs_error_px": float(np.abs(np.array(dxs) - robot_dx).max()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "pcle_core.json"))
    args = parser.parse_args()

    frames, pos = make_sequence(args.frames + 1)
    robot_dx = np.diff(pos, axis=0)  # a perfect robot; accuracy is not the point here
    # warm-up (imports, OpenCV DFT plans, caches)
    run(frames[:12], robot_dx[:11], pyramid_levels=2, ssim_downsample=1)

    configs = [
        {"pyramid_levels": 2, "ssim_downsample": 1},  # library defaults
        {"pyramid_levels": 0, "ssim_downsample": 1},  # exhaustive full-resolution NCC
        {"pyramid_levels": 2, "ssim_downsample": 2},
    ]
    results = [run(frames, robot_dx, **cfg) for cfg in configs]
    report = {
        "benchmark": "pcle_core: NCC fwd+bwd + SSIM c_match + confidences + Kalman update",
        "frame_size": [W, H],
        "frames": args.frames,
        "budget_frames_per_s": 100,
        "cpu_count": os.cpu_count(),
        "opencv_threads": cv2.getNumThreads(),
        "python": platform.python_version(),
        "opencv": cv2.__version__,
        "numpy": np.__version__,
        "results": results,
        "default_meets_budget": results[0]["frames_per_s_median"] >= 100,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    for r in results:
        print(
            f"levels={r['pyramid_levels']} ssim_ds={r['ssim_downsample']}: "
            f"{r['frames_per_s_median']:.0f} frames/s (median {r['median_ms']['total']:.2f} ms: "
            f"ncc {r['median_ms']['ncc']:.2f}, ssim {r['median_ms']['ssim']:.2f}, "
            f"filter {r['median_ms']['filter']:.3f}; p95 {r['p95_total_ms']:.2f} ms), "
            f"max |dx error| {r['ncc_max_abs_error_px']:.3f} px"
        )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
