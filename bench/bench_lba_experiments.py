"""The paper's LBAVis+EMT experiments (seed 000, Sec. 4.2, Figs. 8-10), full versions, on the
simulator (issue 4, item 5). The suite runs short versions (tests/test_sequential.py).

1. Drift (Fig. 8): SYN circular, 152 frames, seeds 0..S-1. lba-emt, ba-emt (all pairs) and
   pairwise: e_M (Eq. 29), drift ratio (mean e_j of the last quarter / first quarter), with the
   paper's appendix Sigma_p and with Sigma_p estimated from an independent sequence of the same
   kind (seed + 100, ground-truth poses; the paper's Sec. 4.2 procedure). Also e_M after
   removing the best single homography common to all frames (cv2.findHomography over every
   frame's grid points): the part of e_M that is a global error of the reference frame.
   And a reference close to causal (paper Sigma_p): frames a..b-1 take their e_j from BA+EMT
   over the first b frames only, b every half lap from the start-up length on (so a frame sees
   at most half a lap ahead): roughly what a method that freezes each result after a full
   adjustment of everything seen so far would reach (the paper's assumption (ii) without LBA's
   window), against which lba-emt's e_M can be read.
2. EMT noise (Fig. 9): 17 frames (a 6-frame start-up bundle adjustment so most frames go through
   the window), noise multipliers nu = 0.25 ... 4: lba-emt vs the EMT poses with the true plane.
3. Loss of visual content (Fig. 10): 62 frames with the paper's 12 black frames. e_M on black
   and on textured frames for lba-emt with prior-only frames fixed at once (the paper's LBA) or
   held until two visual frames follow them (SequentialOptions.hold_prior_only_steps), each with
   the paper's and the estimated Sigma_p; ba-emt beside them; and the floor of C_EMT + C_p for
   these black frames: the true poses of all textured frames held constant and only the black
   ones estimated. The run's report (plane and pose components against truth and the tracker,
   the paper's Fig. 10b-c) is written to fig10/ beside the JSON (bench/results/fig10/).

    python bench/bench_lba_experiments.py [--seeds 4] [--quick]
                                          [--out bench/results/lba_experiments.json]
"""

from __future__ import annotations

import json
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from _common import (
    FRAMES_PER_LAP,
    RESULTS,
    BenchRun,
    bench_args,
    fmt,
    machine_info,
    md_table,
    ratio,
)

from fusedmosaic import _core
from fusedmosaic.estimation.bundle import BundleOptions, run_ba_emt, run_emt
from fusedmosaic.estimation.motion import estimate_motion_sigma
from fusedmosaic.estimation.pairwise import run_pairwise
from fusedmosaic.estimation.sequential import SequentialOptions, run_lba_emt
from fusedmosaic.evaluation import drift_ratio, frame_errors, mosaic_error
from fusedmosaic.io import read_dataset, read_poses_csv
from fusedmosaic.runner import run_dataset
from fusedmosaic.simulation import (
    PAPER_BLACK_FRAMES,
    FetoscopyOptions,
    generate_fetoscopy,
    simulate_fetoscopy,
)


def syn(n: int, seed: int, **kw) -> FetoscopyOptions:
    return FetoscopyOptions(n_frames=n, laps=n / FRAMES_PER_LAP, seed=seed, **kw)


def independent_sigma(n: int, seed: int) -> tuple:
    """Sigma_p from an independent SYN sequence (another seed), as the paper's Sec. 4.2."""
    return tuple(estimate_motion_sigma(generate_fetoscopy(syn(n, seed + 100)).poses))


def errors(ds, res) -> np.ndarray:
    return frame_errors(res.homographies, ds.ground_truth, ds.camera.width, ds.camera.height)


def global_part_removed(ds, res) -> float:
    """e_M after the best homography common to all frames (least squares on grid points)."""
    xs, ys = np.meshgrid(np.linspace(0, ds.camera.width - 1, 5),
                         np.linspace(0, ds.camera.height - 1, 5))
    grid = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)], 1)

    def project(G):
        q = grid @ G.T
        return q[:, :2] / q[:, 2:]

    ok = np.isfinite(res.homographies).all(axis=(1, 2))
    src = np.concatenate([project(G) for G in res.homographies[ok]])
    dst = np.concatenate([project(G) for G in ds.ground_truth[ok]])
    A, _ = cv2.findHomography(src, dst, 0)
    corrected = res.homographies.copy()
    corrected[ok] = np.einsum("ij,njk->nik", A, res.homographies[ok])
    return mosaic_error(frame_errors(corrected, ds.ground_truth, ds.camera.width,
                                     ds.camera.height))


def reference_averaged_error(ds, res, stride: int = 4) -> float:
    """e_M with every stride-th frame in turn as the reference (homographies and truth
    re-expressed in frame r's grid, G_r^-1 G_k), averaged over r: e_M (Eq. 29) in frame 0's grid
    also carries the registration error of frame 0 itself, common to every other frame."""
    def rebase(G, r):
        out = np.linalg.inv(G[r]) @ G
        return out / out[:, 2:, 2:]

    G, T = res.homographies, ds.ground_truth
    w, h = ds.camera.width, ds.camera.height
    return float(np.mean([mosaic_error(frame_errors(rebase(G, r), rebase(T, r), w, h))
                          for r in range(0, len(G), stride) if np.isfinite(G[r]).all()]))


def causal_ba_emt(ds, start: int) -> float:
    """e_M where frames a..b-1 come from BA+EMT over the first b frames (b = start, then every
    half lap, then the sequence length): each block frozen after a full adjustment of
    everything seen up to its end."""
    n = len(ds.frames)
    ends = sorted({*range(start, n, round(FRAMES_PER_LAP / 2)), n})
    e = np.full(n, np.nan)
    a = 0
    for b in ends:
        prefix = replace(ds, frames=[ds.frames[k] for k in range(b)], frame_ids=ds.frame_ids[:b],
                         timestamps=ds.timestamps[:b], cam_from_world=ds.cam_from_world[:b],
                         pose_valid=ds.pose_valid[:b], ground_truth=ds.ground_truth[:b])
        e[a:b] = errors(prefix, run_ba_emt(prefix, progress=False))[a:b]
        a = b
    return mosaic_error(e)


def drift(work: Path, seeds: int, n: int) -> list[dict]:
    rows = []
    for seed in range(seeds):
        root = work / f"syn{n}_{seed}"
        simulate_fetoscopy(root, syn(n, seed), overwrite=True)
        ds = read_dataset(root)
        est = independent_sigma(n, seed)
        row: dict = {"seed": seed}
        e = errors(ds, run_pairwise(ds, progress=False))
        row["pairwise"] = {"e_M_px": mosaic_error(e), "drift_ratio": drift_ratio(e)}
        for label, sigma in (("paper", None), ("estimated", est)):
            for method, res in (
                ("lba-emt", run_lba_emt(ds, progress=False,
                                        options=SequentialOptions(motion_sigma=sigma))),
                ("ba-emt", run_ba_emt(ds, progress=False,
                                      options=BundleOptions(motion_sigma=sigma))),
            ):
                e = errors(ds, res)
                row[f"{method} {label}"] = {
                    "e_M_px": mosaic_error(e), "drift_ratio": drift_ratio(e),
                    "e_M_without_global_px": global_part_removed(ds, res)}
            row[f"ratio {label}"] = ratio(row[f"lba-emt {label}"]["e_M_px"],
                                          row[f"ba-emt {label}"]["e_M_px"])
        causal = causal_ba_emt(ds, SequentialOptions().bootstrap_frames)
        row["causal ba-emt paper"] = {"e_M_px": causal,
                                      "ratio_to_ba": ratio(causal, row["ba-emt paper"]["e_M_px"])}
        print(f"drift seed {seed}: lba/ba paper {row['ratio paper']:.2f}, "
              f"estimated {row['ratio estimated']:.2f}, causal ba/ba "
              f"{row['causal ba-emt paper']['ratio_to_ba']:.2f}", flush=True)
        rows.append(row)
    return rows


def emt_noise(work: Path) -> list[dict]:
    rows = []
    for nu in (0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0):
        root = work / f"nu{nu}"
        simulate_fetoscopy(root, syn(17, 11, noise_multiplier=nu), overwrite=True)
        ds = read_dataset(root)
        plane = np.array(json.loads((root / "truth_plane.json").read_text())["plane"])
        lba = errors(ds, run_lba_emt(ds, progress=False,
                                     options=SequentialOptions(bootstrap_frames=6)))
        emt = errors(ds, run_emt(ds, progress=False, plane=plane))
        rows.append({"nu": nu, "lba-emt e_M_px": mosaic_error(lba),
                     "emt true plane e_M_px": mosaic_error(emt)})
    return rows


def black_floor(ds, truth_poses, plane, black, sigma) -> float:
    """e_M of the black frames when every textured frame sits at its true pose: what C_EMT and
    C_p alone can do for them (BundleAdjuster, no pairs)."""
    o = _core.BundleAdjusterOptions()
    if sigma is not None:
        o.motion_sigma = np.asarray(sigma, np.float64)
    ba = _core.BundleAdjuster(ds.camera.camera_matrix, o)
    n = len(truth_poses)
    for k in range(n):
        z = ds.cam_from_world[k]
        ba.add_frame(k, z if k in black else truth_poses[k], z)
    ba.set_plane(plane)
    for k in range(n):
        if k not in black:
            ba.set_constant_frame(k)
    ba.solve()
    poses = np.array([ba.pose(k) for k in range(n)])
    G = _core.frame_to_reference(poses, plane, ds.camera.camera_matrix, 0)
    e = frame_errors(G, ds.ground_truth, ds.camera.width, ds.camera.height)
    return float(e[sorted(black)].mean())


def black_frames(work: Path, n: int, results: Path) -> dict:
    root = work / "black"
    black = [k for k in PAPER_BLACK_FRAMES if k < n]
    simulate_fetoscopy(root, syn(n, 0, black_frames=black), overwrite=True)
    ds = read_dataset(root)
    mask = np.zeros(n, bool)
    mask[black] = True
    est = independent_sigma(n, 0)
    _, truth = read_poses_csv(root / "truth_poses.csv")
    plane = np.array(json.loads((root / "truth_plane.json").read_text())["plane"])
    out: dict = {"frames": n, "black_frames": black, "estimated_sigma_p": list(est), "rows": []}
    for label, sigma in (("paper", None), ("estimated", est)):
        runs = [(f"lba-emt, fixed at once, {label} Sigma_p", run_lba_emt(
                    ds, progress=False, options=SequentialOptions(
                        motion_sigma=sigma, hold_prior_only_steps=0))),
                (f"lba-emt, held, {label} Sigma_p", run_lba_emt(
                    ds, progress=False, options=SequentialOptions(motion_sigma=sigma))),
                (f"ba-emt, {label} Sigma_p", run_ba_emt(
                    ds, progress=False, options=BundleOptions(motion_sigma=sigma)))]
        for name, res in runs:
            e = errors(ds, res)
            out["rows"].append({
                "run": name, "placed": int(np.isfinite(e).sum()),
                "black e_M_px": float(np.nanmean(e[mask])),
                "textured e_M_px": float(np.nanmean(e[~mask])),
                "ratio": ratio(float(np.nanmean(e[mask])), float(np.nanmean(e[~mask]))),
                "worst black e_j_px": float(np.nanmax(e[mask]))})
        out["rows"].append({"run": f"floor: C_EMT + C_p, true textured poses, {label} Sigma_p",
                            "black e_M_px": black_floor(ds, truth, plane, set(black), sigma)})
    # Fig. 10b-c: the run's report plots the plane and pose components against truth and EMT.
    report_dir = work / "fig10_run"
    run_dataset(root, "lba-emt", report_dir, progress=False,
                options=SequentialOptions(motion_sigma=est))
    dest = results / "fig10"
    shutil.rmtree(dest, ignore_errors=True)
    shutil.copytree(report_dir / "plots", dest)
    out["plots"] = sorted(str(p.relative_to(results)) for p in dest.iterdir())
    return out


def markdown(res: dict) -> str:
    lines = ["# LBAVis+EMT experiments (seed 000, Figs. 8-10), simulator", "",
             f"`python bench/bench_lba_experiments.py`, {res['runtime_s']:.0f} s.", "",
             f"## Drift (Fig. 8): SYN {res['drift_frames']} frames, per seed", ""]
    rows = []
    for r in res["drift"]:
        for label in ("paper", "estimated"):
            lba, ba = r[f"lba-emt {label}"], r[f"ba-emt {label}"]
            rows.append([r["seed"], label, fmt(lba["e_M_px"], 3), fmt(ba["e_M_px"], 3),
                         fmt(r[f"ratio {label}"]), fmt(lba["e_M_without_global_px"], 3),
                         fmt(ba["e_M_without_global_px"], 3), fmt(lba["drift_ratio"]),
                         fmt(r["pairwise"]["drift_ratio"])])
    lines += md_table(["seed", "Sigma_p", "lba-emt e_M", "ba-emt e_M", "lba/ba",
                       "lba e_M w/o global", "ba e_M w/o global", "lba drift",
                       "pairwise drift"], rows)
    lines += ["", "Causal reference, paper Sigma_p (frames a..b-1 from BA+EMT over the first b "
              "frames, b every half lap from the start-up length):", ""]
    lines += md_table(["seed", "causal ba-emt e_M", "ba-emt e_M", "causal/ba", "lba-emt e_M",
                       "lba/causal"],
                      [[r["seed"], fmt(r["causal ba-emt paper"]["e_M_px"], 3),
                        fmt(r["ba-emt paper"]["e_M_px"], 3),
                        fmt(r["causal ba-emt paper"]["ratio_to_ba"]),
                        fmt(r["lba-emt paper"]["e_M_px"], 3),
                        fmt(ratio(r["lba-emt paper"]["e_M_px"],
                                  r["causal ba-emt paper"]["e_M_px"]))] for r in res["drift"]])
    for label in ("paper", "estimated"):
        s = res["drift_summary"][label]
        lines.append(f"\nMean over seeds, {label} Sigma_p: lba-emt {s['lba']:.3f} px, ba-emt "
                     f"{s['ba']:.3f} px, ratio of means {s['ratio_of_means']:.2f}; without the "
                     f"global part {s['lba_wo']:.3f} vs {s['ba_wo']:.3f} px "
                     f"({s['ratio_wo']:.2f}).")
        if "causal" in s:
            lines.append(f"Causal reference: {s['causal']:.3f} px, "
                         f"{s['causal_ratio_of_means']:.2f} x ba-emt.")
    lines += ["", "## EMT noise (Fig. 9): 17 frames", ""]
    lines += md_table(["nu", "lba-emt e_M px", "EMT + true plane e_M px"],
                      [[r["nu"], fmt(r["lba-emt e_M_px"], 3), fmt(r["emt true plane e_M_px"])]
                       for r in res["emt_noise"]])
    b = res["black"]
    lines += ["", f"## Loss of visual content (Fig. 10): {b['frames']} frames, black "
              f"{b['black_frames']}", ""]
    lines += md_table(["run", "placed", "black e_M px", "textured e_M px", "black/textured",
                       "worst black px"],
                      [[r["run"], r.get("placed", "–"), fmt(r["black e_M_px"], 3),
                        fmt(r.get("textured e_M_px"), 3), fmt(r.get("ratio")),
                        fmt(r.get("worst black e_j_px"))] for r in b["rows"]])
    lines += ["", "Plots (plane and pose against truth and the tracker): "
              + ", ".join(b["plots"])]
    return "\n".join(lines) + "\n"


def main() -> None:
    args = bench_args(__doc__.splitlines()[0], seeds=4, quick="1 seed, 60 frames (smoke run)",
                      out=RESULTS / "lba_experiments.json").parse_args()
    bench = BenchRun()
    work = bench.work
    n = 60 if args.quick else 152
    seeds = 1 if args.quick else args.seeds
    res: dict = {"machine": machine_info(), "command": " ".join(sys.argv)}
    res["drift_frames"] = n
    res["drift"] = drift(work, seeds, n)
    res["drift_summary"] = {}
    for label in ("paper", "estimated"):
        mean = {k: float(np.mean([r[f"{m} {label}"][f] for r in res["drift"]]))
                for k, m, f in (("lba", "lba-emt", "e_M_px"), ("ba", "ba-emt", "e_M_px"),
                                ("lba_wo", "lba-emt", "e_M_without_global_px"),
                                ("ba_wo", "ba-emt", "e_M_without_global_px"))}
        mean["ratio_of_means"] = ratio(mean["lba"], mean["ba"])
        if label == "paper":
            mean["causal"] = float(np.mean([r["causal ba-emt paper"]["e_M_px"]
                                            for r in res["drift"]]))
            mean["causal_ratio_of_means"] = ratio(mean["causal"], mean["ba"])
        mean["ratio_wo"] = ratio(mean["lba_wo"], mean["ba_wo"])
        res["drift_summary"][label] = mean
    res["emt_noise"] = emt_noise(work)
    res["black"] = black_frames(work, 62, args.out.parent)
    bench.finish(res, args.out, markdown)
    print(args.out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
