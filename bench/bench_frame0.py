"""Frame 0's pose in lba-emt and ba-emt on SYN 152, for issue 4's 1.25x (missed on some
seeds): frame 0 is the reference every homography is expressed in (design.md).

e_M (seed 000 Eq. 29) maps each frame's grid into frame 0's pixels, so an error in frame 0's
own pose is common to every e_j. lba-emt fixes frame 0 after its start-up adjustment (BA+EMT
over the first SequentialOptions.bootstrap_frames = 40 frames, about one lap); ba-emt adjusts it
with all four laps. This script measures, per seed: frame 0's pose error (rotation deg,
translation mm, against truth_poses.csv) and the median over the other frames, for lba-emt,
ba-emt (all pairs, as bench_lba_experiments) and BA+EMT over only the first 40 frames (what
any method that freezes frame 0 after the start-up can know about it); and e_M of each.

    python bench/bench_frame0.py [--seeds 4] [--out bench/results/frame0.json]
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from _common import FRAMES_PER_LAP, RESULTS, BenchRun, bench_args, fmt, md_table, run_note

from fusedmosaic import _core
from fusedmosaic.estimation.bundle import run_ba_emt
from fusedmosaic.estimation.sequential import SequentialOptions, run_lba_emt
from fusedmosaic.evaluation import frame_errors, mosaic_error
from fusedmosaic.io import read_dataset, read_poses_csv
from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy


def pose_error(x: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(rotation deg, translation mm) of cam_from_world x against truth (6-vectors)."""
    R = _core.rotation_from_angle_axis(x[:3]) @ _core.rotation_from_angle_axis(truth[:3]).T
    return (float(np.degrees(np.linalg.norm(_core.angle_axis_from_rotation(R)))),
            float(np.linalg.norm(x[3:] - truth[3:])))


def first(ds, n: int):
    k = np.arange(n)
    return replace(ds, frames=[ds.frames[i] for i in k], frame_ids=ds.frame_ids[k],
                   timestamps=ds.timestamps[k], cam_from_world=ds.cam_from_world[k],
                   pose_valid=ds.pose_valid[k], ground_truth=ds.ground_truth[k])


def measure(ds, truth: np.ndarray, res) -> dict:
    n = len(res.homographies)
    e = frame_errors(res.homographies, ds.ground_truth[:n], ds.camera.width, ds.camera.height)
    others = np.array([pose_error(res.poses[k], truth[k]) for k in range(1, n)])
    rot0, trans0 = pose_error(res.poses[0], truth[0])
    return {"e_M_px": mosaic_error(e), "frame0_rot_deg": rot0, "frame0_trans_mm": trans0,
            "others_median_rot_deg": float(np.median(others[:, 0])),
            "others_median_trans_mm": float(np.median(others[:, 1]))}


def markdown(res: dict) -> str:
    lines = ["# Frame 0's pose: lba-emt vs ba-emt on SYN 152 (issue 4)", "",
             run_note(res, "bench_frame0.py", f", seeds 0-{res['seeds'] - 1}"), "",
             "Pose errors against truth_poses.csv: frame 0 (the reference of every homography) "
             "and the median over frames 1-151; `ba-emt first 40`: BA+EMT over the start-up's "
             "40 frames only, e_M over those frames.", ""]
    rows = []
    for r in res["rows"]:
        for name in ("lba-emt", "ba-emt", "ba-emt first 40"):
            m = r[name]
            rows.append([r["seed"], name, fmt(m["e_M_px"], 3), fmt(m["frame0_rot_deg"], 3),
                         fmt(m["frame0_trans_mm"], 3), fmt(m["others_median_rot_deg"], 3),
                         fmt(m["others_median_trans_mm"], 3)])
    lines += md_table(["seed", "method", "e_M px", "frame 0 deg", "frame 0 mm",
                       "others deg (median)", "others mm (median)"], rows)
    gap = np.array([[abs(r["lba-emt"][k] - r["ba-emt first 40"][k])
                     for k in ("frame0_rot_deg", "frame0_trans_mm")] for r in res["rows"]])
    lines += ["", f"lba-emt's frame 0 is BA+EMT's over the first 40 frames to within "
              f"{gap[:, 0].max():.3f} deg / {gap[:, 1].max():.3f} mm on every seed: its start-up "
              "places the reference as well as those frames allow, and ba-emt's lower frame-0 "
              "error comes from the later laps, which a causal method has not seen when it "
              "fixes it. Frame 0's pose error alone does not order e_M, though: on seed 2 "
              "lba-emt's frame 0 is further off than ba-emt's and its e_M lower, on seed 3 the "
              "two e_M are equal (e_M also depends on how the other frames' errors align with "
              "frame 0's)."]
    return "\n".join(lines) + "\n"


def main() -> None:
    args = bench_args(__doc__, seeds=4, work=True, out=RESULTS / "frame0.json").parse_args()
    bench = BenchRun(args.work)
    start = SequentialOptions().bootstrap_frames
    rows = []
    for seed in range(args.seeds):
        root = bench.work / f"syn152_{seed}"
        simulate_fetoscopy(root, FetoscopyOptions(n_frames=152, laps=152 / FRAMES_PER_LAP,
                                                  seed=seed), overwrite=True)
        ds = read_dataset(root)
        _, truth = read_poses_csv(root / "truth_poses.csv")
        row = {"seed": seed,
               "lba-emt": measure(ds, truth, run_lba_emt(ds, progress=False)),
               "ba-emt": measure(ds, truth, run_ba_emt(ds, progress=False)),
               "ba-emt first 40": measure(ds, truth,
                                          run_ba_emt(first(ds, start), progress=False))}
        print(f"seed {seed}: frame 0 deg / mm: " + ", ".join(
            f"{k} {row[k]['frame0_rot_deg']:.3f} / {row[k]['frame0_trans_mm']:.3f}"
            for k in ("lba-emt", "ba-emt", "ba-emt first 40")), flush=True)
        rows.append(row)
    bench.write_results(args.out, markdown, seeds=args.seeds, start_frames=start, rows=rows)


if __name__ == "__main__":
    main()
