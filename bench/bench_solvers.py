"""Linear-solver and residual-block benchmark for BundleAdjuster (BA+EMT, seed 000 Eq. 17).

A SYN-like problem (seed 000, Sec. 4.1): a camera ~35 mm above a slightly tilted plane moves on
a circle in x-y (several laps, smooth small rotations), 400x400 frames with focal 450 px. Image
pairs are the ~1000 most overlapping frame pairs, each with ~70 correspondences made by exact
plane transfer plus sigma = 1 px noise; EMT measurements are the true poses plus 1 deg / 1 mm
noise (Sec. 4.1), and also initialise the poses. Every linear solver is run with per-pair and
per-point residual blocks; each configuration is solved 3 times from the same start and the
median time is reported (Ceres' total time and the wall time of solve(), which includes
building the ceres::Problem). Results go to bench/results/solvers.json.

The "auto" linear solver of BundleAdjusterOptions (cpp/fusedmosaic/problem/bundle_adjuster.cc)
is the fastest configuration measured here: sparse_schur with per-pair blocks.

Run: python bench/bench_solvers.py [--frames 150 --pairs 1000 --points 70 --runs 3]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from fusedmosaic import _core

K = np.array([[450.0, 0.0, 200.0], [0.0, 450.0, 200.0], [0.0, 0.0, 1.0]])
SIZE = 400
SOLVERS = [
    "sparse_normal_cholesky",
    "sparse_schur",
    "dense_schur",
    "iterative_schur",
    "dense_normal_cholesky",
    "dense_qr",
]
# Dense solvers build a dense (residuals x parameters) Jacobian; above this they are skipped on the
# full problem (140k x 903 doubles = 1 GB) and measured on a reduced one instead.
DENSE_JACOBIAN_LIMIT_BYTES = 64 * 2**20


def make_problem(n_frames, n_pairs, n_points, rng, laps=4, radius=10.0, depth=35.0):
    """Ground truth, EMT measurements and correspondences of a SYN-like sequence."""
    normal = np.array([0.06, -0.04, 1.0])
    normal /= np.linalg.norm(normal)
    plane = normal / (-depth * normal[2])
    theta = np.linspace(0.0, 2.0 * np.pi * laps, n_frames, endpoint=False)
    poses = np.zeros((n_frames, 6))
    for k, th in enumerate(theta):
        r = np.array([0.04 * np.sin(th), 0.04 * np.cos(th), 0.1 * np.sin(0.5 * th)])
        center = np.array([radius * np.cos(th), radius * np.sin(th), 0.5 * np.sin(3 * th)])
        poses[k] = np.r_[r, -_core.rotation_from_angle_axis(r) @ center]

    centers = np.array([-_core.rotation_from_angle_axis(p[:3]).T @ p[3:] for p in poses])
    dist = np.linalg.norm(centers[:, None, :2] - centers[None, :, :2], axis=2)
    candidates = sorted((dist[l, m], l, m) for m in range(n_frames) for l in range(m + 1, n_frames))
    pairs = []
    for _, l, m in candidates:
        pts_m = rng.uniform(0, SIZE, (6 * n_points, 2))
        pts_l = _core.transfer_points(pts_m, poses[l], poses[m], plane, K)
        inside = np.all((pts_l >= 0) & (pts_l < SIZE), axis=1)
        if inside.sum() < n_points:
            continue
        pts_m, pts_l = pts_m[inside][:n_points], pts_l[inside][:n_points]
        pairs.append((l, m, pts_l + rng.normal(0.0, 1.0, pts_l.shape), pts_m))
        if len(pairs) == n_pairs:
            break

    emt_sigma = np.r_[np.full(3, np.deg2rad(1.0)), np.full(3, 1.0)]
    emt = poses + rng.normal(0.0, 1.0, poses.shape) * emt_sigma
    plane_init = np.array([0.0, 0.0, -1.0 / 30.0])  # fronto-parallel guess, 5 mm off
    return dict(poses=poses, plane=plane, emt=emt, pairs=pairs, plane_init=plane_init)


def mosaic_error(poses_est, plane_est, poses_true, plane_true):
    """e_M (seed 000, Eq. 28-29): mean over frames of the mean grid displacement, pixels."""
    g = np.linspace(0, SIZE, 20)
    grid = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    grid_h = np.c_[grid, np.ones(len(grid))]
    G_est = _core.frame_to_reference(poses_est, plane_est, K)
    G_true = _core.frame_to_reference(poses_true, plane_true, K)
    p_est = np.einsum("kij,nj->kni", G_est, grid_h)
    p_true = np.einsum("kij,nj->kni", G_true, grid_h)
    diff = p_est[..., :2] / p_est[..., 2:] - p_true[..., :2] / p_true[..., 2:]
    return float(np.linalg.norm(diff, axis=2).mean())


def build(problem, **options):
    ba = _core.BundleAdjuster(K, _core.BundleAdjusterOptions(**options))
    for k, z in enumerate(problem["emt"]):
        ba.add_frame(k, z, z)
    for l, m, pts_l, pts_m in problem["pairs"]:
        ba.add_pair(l, m, pts_l, pts_m)
    ba.set_plane(problem["plane_init"])
    return ba


def run_config(problem, runs, **options):
    ceres_times, wall_times, summaries = [], [], []
    for _ in range(runs):
        ba = build(problem, **options)
        start = time.perf_counter()
        summary = ba.solve()
        wall_times.append(time.perf_counter() - start)
        ceres_times.append(summary.solve_time_s)
        summaries.append(summary)
    ids, est = ba.poses()
    s = summaries[-1]
    return dict(
        options=options,
        solve_time_s=statistics.median(ceres_times),
        wall_time_s=statistics.median(wall_times),
        solve_times_s=ceres_times,
        final_cost=s.final_cost,
        initial_cost=s.initial_cost,
        iterations=s.iterations,
        termination=s.termination,
        linear_solver=s.linear_solver,
        num_residual_blocks=s.num_residual_blocks,
        e_M_px=mosaic_error(est, ba.plane(), problem["poses"], problem["plane"]),
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--pairs", type=int, default=1000)
    parser.add_argument("--points", type=int, default=70)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).parent / "results" / "solvers.json"
    )
    args = parser.parse_args()

    rng = np.random.default_rng(args.seed)
    problem = make_problem(args.frames, args.pairs, args.points, rng)
    n_points = sum(len(p[2]) for p in problem["pairs"])
    emt_only = mosaic_error(problem["emt"], problem["plane"], problem["poses"], problem["plane"])
    print(
        f"problem: {args.frames} frames, {len(problem['pairs'])} pairs, {n_points} points; "
        f"e_M of EMT poses with the true plane: {emt_only:.2f} px"
    )
    # A reduced problem for the dense solvers (same scene, 10 points per pair).
    reduced = dict(problem, pairs=[(l, m, a[:10], b[:10]) for l, m, a, b in problem["pairs"]])
    n_params = 6 * args.frames + 3

    results = []
    for blocks in ("per_pair", "per_point"):
        for solver in SOLVERS:
            dense = solver.startswith("dense") and solver != "dense_schur"
            target, label = problem, "full"
            if dense and 2 * n_points * n_params * 8 > DENSE_JACOBIAN_LIMIT_BYTES:
                target, label = reduced, "reduced (10 points per pair)"
            row = run_config(
                target,
                args.runs,
                linear_solver=solver,
                residual_blocks=blocks,
                num_threads=args.threads,
            )
            row["problem"] = label
            results.append(row)
            print(
                f"{blocks:9s} {solver:23s} {label:8.8s} ceres {row['solve_time_s']:7.3f} s  "
                f"wall {row['wall_time_s']:7.3f} s  iters {row['iterations']:3d}  "
                f"cost {row['final_cost']:.6e}  e_M {row['e_M_px']:.3f} px  {row['termination']}"
            )
    # Robust loss: per-pair (in-block per-point kernel) vs per-point (ceres::LossFunction).
    for blocks in ("per_pair", "per_point"):
        row = run_config(
            problem, args.runs, loss="huber", residual_blocks=blocks, num_threads=args.threads
        )
        row["problem"] = "full"
        results.append(row)
        print(
            f"{blocks:9s} huber/auto              full     ceres {row['solve_time_s']:7.3f} s  "
            f"wall {row['wall_time_s']:7.3f} s  iters {row['iterations']:3d}  "
            f"cost {row['final_cost']:.6e}  e_M {row['e_M_px']:.3f} px  {row['termination']}"
        )

    full = [r for r in results if r["problem"] == "full" and "loss" not in r["options"]]
    best = min(full, key=lambda r: r["solve_time_s"])
    report = dict(
        problem=dict(
            frames=args.frames,
            pairs=len(problem["pairs"]),
            points=n_points,
            noise_px=1.0,
            emt_noise="1 deg, 1 mm",
            seed=args.seed,
            threads=args.threads,
            runs=args.runs,
            e_M_emt_only_px=emt_only,
        ),
        machine=dict(python=platform.python_version(), processor=platform.processor()),
        fastest=dict(
            linear_solver=best["options"]["linear_solver"],
            residual_blocks=best["options"]["residual_blocks"],
            solve_time_s=best["solve_time_s"],
        ),
        results=results,
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"fastest: {best['options']} {best['solve_time_s']:.3f} s -> {args.out}")


if __name__ == "__main__":
    main()
