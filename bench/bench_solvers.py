"""Linear-solver and residual-block benchmark for BundleAdjuster (BA+EMT, seed 000 Eq. 17).

A SYN-like problem (seed 000, Sec. 4.1): a camera ~35 mm above a slightly tilted plane moves on
a circle in x-y (several laps, smooth small rotations), 400x400 frames with focal 450 px. Image
pairs are the ~1000 most overlapping frame pairs, each with ~70 correspondences made by exact
plane transfer plus sigma = 1 px noise; EMT measurements are the true poses plus 1 deg / 1 mm
noise (Sec. 4.1), and also initialise the poses. Every linear solver is run with per-pair and
per-point residual blocks; each configuration is solved 5 times from the same start, the runs
interleaved round-robin across configurations (the cores are shared with other processes), and
the median of Ceres' total time is reported, with the process CPU time and the wall time of
solve() (which includes building the ceres::Problem). dense_qr and dense_normal_cholesky need
the dense 140k x 903 Jacobian (1 GB); they run once, on the same scene with 10 points per pair.
The robust losses are compared on the problem with 10% outliers, per-pair (kernel applied per
point inside the block) against per-point blocks (ceres::LossFunction). Results go to
bench/results/solvers.json, the default configuration checked against the design budget
(BA+EMT <= 1 s).

The "auto" linear solver of BundleAdjusterOptions (cpp/fusedmosaic/problem/bundle_adjuster.cc)
is the fastest configuration measured here: sparse_schur with per-pair blocks.

Run: python bench/bench_solvers.py [--frames 150 --pairs 1000 --points 70 --runs 5]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from fusedmosaic import _core
from fusedmosaic.simulation import circle_scene, plane_point_pairs

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
BUDGET_S = 1.0  # design.md: BA+EMT over ~150 frames / ~1000 pairs, optimisation <= 1 s


def make_problem(n_frames, n_pairs, n_points, rng, laps=4, radius=10.0, depth=35.0):
    """Ground truth, EMT measurements and correspondences of a SYN-like sequence."""
    poses, plane = circle_scene(n_frames, rng, laps=laps, radius=radius, depth=depth,
                                normal=(0.06, -0.04, 1.0), rotation_jitter=0.0,
                                height_jitter=0.5)
    pairs = plane_point_pairs(poses, plane, K, SIZE, rng, n_points=n_points, noise_px=1.0,
                              max_pairs=n_pairs)
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


def with_outliers(pair, rng, fraction=0.1):
    """Moves a fraction of a pair's points in frame l by 15-40 px in a random direction."""
    l, m, pts_l, pts_m = pair
    pts_l = pts_l.copy()
    bad = rng.random(len(pts_l)) < fraction
    angle = rng.uniform(0.0, 2.0 * np.pi, bad.sum())
    pts_l[bad] += rng.uniform(15, 40, bad.sum())[:, None] * np.c_[np.cos(angle), np.sin(angle)]
    return l, m, pts_l, pts_m


def build(problem, **options):
    ba = _core.BundleAdjuster(K, _core.BundleAdjusterOptions(**options))
    for k, z in enumerate(problem["emt"]):
        ba.add_frame(k, z, z)
    for l, m, pts_l, pts_m in problem["pairs"]:
        ba.add_pair(l, m, pts_l, pts_m)
    ba.set_plane(problem["plane_init"])
    return ba


def solve_once(problem, **options):
    """One solve from the problem's start; (summary, wall s, process CPU s, adjuster)."""
    ba = build(problem, **options)
    wall, cpu = time.perf_counter(), time.process_time()
    summary = ba.solve()
    return summary, time.perf_counter() - wall, time.process_time() - cpu, ba


def run_configs(configs, runs):
    """Solves every (label, problem, options) config `runs` times, interleaved round-robin so
    that load drift on a shared machine affects all configs alike; medians per config."""
    samples = {i: [] for i in range(len(configs))}
    for _ in range(runs):
        for i, (_, problem, options) in enumerate(configs):
            samples[i].append(solve_once(problem, **options))
    rows = []
    for i, (label, problem, options) in enumerate(configs):
        summary, _, _, ba = samples[i][-1]
        _, est = ba.poses()
        ceres_s = [x[0].solve_time_s for x in samples[i]]
        rows.append(
            dict(
                problem=label,
                options=options,
                solve_time_s=statistics.median(ceres_s),
                solve_time_min_s=min(ceres_s),
                wall_time_s=statistics.median(x[1] for x in samples[i]),
                cpu_time_s=statistics.median(x[2] for x in samples[i]),
                solve_times_s=ceres_s,
                runs=len(ceres_s),
                final_cost=summary.final_cost,
                initial_cost=summary.initial_cost,
                iterations=summary.iterations,
                termination=summary.termination,
                linear_solver=summary.linear_solver,
                num_residual_blocks=summary.num_residual_blocks,
                e_M_px=mosaic_error(est, ba.plane(), problem["poses"], problem["plane"]),
            )
        )
    return rows


def print_row(row):
    o = row["options"]
    name = o.get("linear_solver", "auto") + ("" if "loss" not in o else f" + {o['loss']}")
    print(
        f"{o.get('residual_blocks', 'per_pair'):9s} {name:29s} {row['problem'][:14]:14s} "
        f"ceres {row['solve_time_s']:7.3f} s (min {row['solve_time_min_s']:6.3f})  "
        f"cpu {row['cpu_time_s']:7.3f} s  iters {row['iterations']:3d}  "
        f"cost {row['final_cost']:.6e}  e_M {row['e_M_px']:.3f} px  {row['termination']}"
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--pairs", type=int, default=1000)
    parser.add_argument("--points", type=int, default=70)
    parser.add_argument("--runs", type=int, default=5)
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

    threads = dict(num_threads=args.threads)
    full, dense = [], []
    for blocks in ("per_pair", "per_point"):
        for solver in SOLVERS:
            options = dict(linear_solver=solver, residual_blocks=blocks, **threads)
            is_dense = solver in ("dense_qr", "dense_normal_cholesky")
            if is_dense and 2 * n_points * n_params * 8 > DENSE_JACOBIAN_LIMIT_BYTES:
                dense.append(("reduced: 10 points per pair", reduced, options))
            else:
                full.append(("full", problem, options))
    # The default configuration (linear_solver="auto", per-pair blocks), checked against budget.
    full.append(("full", problem, dict(threads)))
    # Robust loss, per point: per-pair blocks (kernel inside the block) vs per-point blocks
    # (ceres::LossFunction), on the problem with 10% of the points in frame l moved 15-40 px.
    outliers = dict(problem, pairs=[with_outliers(p, rng) for p in problem["pairs"]])
    robust = [("10% outliers", outliers, dict(loss="none", **threads))]
    for loss in ("huber", "cauchy"):
        for blocks in ("per_pair", "per_point"):
            robust.append(
                ("10% outliers", outliers, dict(loss=loss, residual_blocks=blocks, **threads))
            )

    results = run_configs(full, args.runs)
    results += run_configs(dense, 1)  # far off the pace (> 6 s): one run suffices
    results += run_configs(robust, args.runs)
    for row in results:
        print_row(row)
    default = results[len(full) - 1]
    print(
        f"default (auto -> {default['linear_solver']}, per_pair): "
        f"ceres {default['solve_time_s']:.3f} s, wall {default['wall_time_s']:.3f} s "
        f"(budget {BUDGET_S} s)"
    )

    # Per (residual blocks, linear solver) on the full problem, the "auto" runs pooled with the
    # solver they resolved to; the fastest median is the candidate for "auto".
    pooled = {}
    for row in results[: len(full)]:
        key = (row["options"].get("residual_blocks", "per_pair"), row["linear_solver"])
        pooled.setdefault(key, []).extend(row["solve_times_s"])
    table = [
        dict(residual_blocks=b, linear_solver=ls, median_s=statistics.median(t), runs=len(t))
        for (b, ls), t in sorted(pooled.items(), key=lambda kv: statistics.median(kv[1]))
    ]
    best = table[0]
    for row in table:
        print(f"  {row['residual_blocks']:9s} {row['linear_solver']:23s} {row['median_s']:.3f} s")
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
        machine=dict(
            python=platform.python_version(),
            cpus=os.cpu_count(),
            load_average_1min=os.getloadavg()[0],  # other processes share the cores
        ),
        default=dict(
            linear_solver=default["linear_solver"],
            solve_time_s=default["solve_time_s"],
            wall_time_s=default["wall_time_s"],
            budget_s=BUDGET_S,
            within_budget=default["wall_time_s"] <= BUDGET_S,
        ),
        fastest=best,
        by_solver=table,
        results=results,
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"fastest: {best} -> {args.out}")


if __name__ == "__main__":
    main()
