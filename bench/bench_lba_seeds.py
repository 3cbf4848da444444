"""lba-emt against ba-emt over many SYN seeds (seed 000, Fig. 8 setting: circular, 152 frames),
and how the ratio depends on the start-up length (SequentialOptions.bootstrap_frames).

Issue 4 asks lba-emt e_M <= 1.25 x ba-emt e_M on the SYN sequence; bench_lba_experiments.py
measures it on seeds 0-3 with the full set of columns. This script repeats the two methods on
--seeds simulated sequences (paper Sigma_p, defaults otherwise) to show the spread of the ratio,
and runs lba-emt again with longer start-ups: the start-up BA+EMT fixes the plane and frame 0's
relation to its neighbours, which every later (fixed) frame inherits. Each e_M is also given
averaged over reference frames (every 4th frame in turn as the reference, see
bench_lba_experiments.reference_averaged_error): e_M in frame 0's grid includes frame 0's own
registration error, which the start-up fixes.

    python bench/bench_lba_seeds.py [--seeds 20] [--bootstrap 40,60,80]
                                    [--out bench/results/lba_seeds.json]

Writes the JSON and a markdown table beside it (lba_seeds.md).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from _common import BenchRun, add_options, bench_args, fmt, machine_info, md_table, write_outputs
from bench_lba_experiments import errors, reference_averaged_error, syn

from fusedmosaic.estimation.bundle import run_ba_emt
from fusedmosaic.estimation.sequential import SequentialOptions, run_lba_emt
from fusedmosaic.evaluation import mosaic_error
from fusedmosaic.io import read_dataset
from fusedmosaic.simulation import simulate_fetoscopy

FRAMES = 152


def main() -> None:
    ap = bench_args(__doc__, seeds=20)
    ap.add_argument("--bootstrap", default="40,60,80",
                    help="start-up lengths (frames), the first is the default's")
    args = add_options(ap, work=True, out=Path("bench/results/lba_seeds.json")).parse_args()
    boots = [int(b) for b in args.bootstrap.split(",")]
    bench = BenchRun(args.work)
    rows = []
    try:
        for seed in range(args.seeds):
            root = bench.work / f"syn{FRAMES}_{seed}"
            simulate_fetoscopy(root, syn(FRAMES, seed), overwrite=True)
            ds = read_dataset(root)
            ba = run_ba_emt(ds, progress=False)
            row = {"seed": seed, "ba-emt": mosaic_error(errors(ds, ba)),
                   "ba-emt all references": reference_averaged_error(ds, ba)}
            for b in boots:
                res = run_lba_emt(ds, progress=False,
                                  options=SequentialOptions(bootstrap_frames=b))
                row[f"lba-emt {b}"] = mosaic_error(errors(ds, res))
                row[f"lba-emt {b} all references"] = reference_averaged_error(ds, res)
            rows.append(row)
            print(seed, {k: round(v, 3) for k, v in row.items()}, flush=True)
    finally:
        bench.cleanup()
    summary = {}
    for b in boots:
        r = np.array([row[f"lba-emt {b}"] / row["ba-emt"] for row in rows])
        lba = np.mean([row[f"lba-emt {b}"] for row in rows])
        summary[b] = {"median_ratio": float(np.median(r)),
                      "geometric_mean_ratio": float(np.exp(np.log(r).mean())),
                      "ratio_of_means": float(lba / np.mean([row["ba-emt"] for row in rows])),
                      "fraction_within_1_25": float(np.mean(r <= 1.25)),
                      "seed_0_ratio": float(r[0])}
        ra = np.array([row[f"lba-emt {b} all references"] / row["ba-emt all references"]
                       for row in rows])
        summary[b]["all_references"] = {
            "median_ratio": float(np.median(ra)),
            "geometric_mean_ratio": float(np.exp(np.log(ra).mean())),
            "ratio_of_means": float(np.mean([row[f"lba-emt {b} all references"] for row in rows])
                                    / np.mean([row["ba-emt all references"] for row in rows])),
            "fraction_within_1_25": float(np.mean(ra <= 1.25)),
            "seed_0_ratio": float(ra[0])}
    res = {"machine": machine_info(), "frames": FRAMES, "seeds": args.seeds,
           "bootstrap_frames": boots, "runtime_s": time.perf_counter() - bench.t_start,
           "rows": rows, "summary": {str(b): s for b, s in summary.items()}}
    write_outputs(args.out, res, markdown)


def markdown(res: dict) -> str:
    boots = res["bootstrap_frames"]
    lines = [f"# lba-emt vs ba-emt over {res['seeds']} SYN seeds ({res['frames']} frames)", "",
             f"`python bench/bench_lba_seeds.py`, {res['runtime_s']:.0f} s. e_M in px (Eq. 29) "
             "against the simulator's truth; paper Sigma_p; lba-emt with start-ups of "
             f"{', '.join(map(str, boots))} frames (the default is "
             f"{SequentialOptions().bootstrap_frames}).", ""]
    rows = [[r["seed"], fmt(r["ba-emt"], 3)]
            + [f"{fmt(r[f'lba-emt {b}'], 3)} ({fmt(r[f'lba-emt {b}'] / r['ba-emt'])})"
               for b in boots] for r in res["rows"]]
    lines += md_table(["seed", "ba-emt e_M"] + [f"lba-emt e_M, start-up {b} (/ba)"
                                                  for b in boots], rows)
    lines += ["", "Averaged over reference frames (every 4th frame in turn as the reference), the "
              "same runs:", ""]
    rows = [[r["seed"], fmt(r["ba-emt all references"], 3)]
            + [f"{fmt(r[f'lba-emt {b} all references'], 3)} "
               f"({fmt(r[f'lba-emt {b} all references'] / r['ba-emt all references'])})"
               for b in boots] for r in res["rows"]]
    lines += md_table(["seed", "ba-emt"] + [f"lba-emt, start-up {b} (/ba)" for b in boots], rows)
    lines += ["", "| reference | start-up frames | median lba/ba | geometric mean | "
              "ratio of means | seeds with lba/ba <= 1.25 | seed 0 |",
              "|---|---|---|---|---|---|---|"]
    for label, key in (("frame 0 (Eq. 29)", None), ("all frames, averaged", "all_references")):
        for b in boots:
            s = res["summary"][str(b)]
            s = s[key] if key else s
            lines.append(f"| {label} | {b} | {s['median_ratio']:.2f} | "
                         f"{s['geometric_mean_ratio']:.2f} | {s['ratio_of_means']:.2f} | "
                         f"{100 * s['fraction_within_1_25']:.0f} % | {s['seed_0_ratio']:.2f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
