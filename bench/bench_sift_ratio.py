"""SIFT's ratio test (MatchOptions.ratio) on SYN 152, over seeds: lba-emt and ba-emt e_M and
their ratio for each ratio-test threshold, exhaustive matching (run's default).

Why: SYN frames give ~100 SIFT keypoints each, and a match a pixel or two off that passes
Lowe's 0.8 is kept by RANSAC's 3 px threshold; a stricter test trades matches for precision.
The default (0.8) is not changed by this script: it measures, and the choice is recorded in
the closing notes.

    python bench/bench_sift_ratio.py [--seeds 12] [--ratios 0.8 0.6]
                                     [--out bench/results/sift_ratio.json]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from _common import RESULTS, BenchRun, add_options, bench_args, fmt, machine_info, md_table
from bench_lba_experiments import errors, syn

from fusedmosaic.estimation.bundle import BundleOptions, run_ba_emt
from fusedmosaic.estimation.sequential import SequentialOptions, run_lba_emt
from fusedmosaic.evaluation import mosaic_error
from fusedmosaic.io import read_dataset
from fusedmosaic.registration.pairs import MatchOptions
from fusedmosaic.simulation import simulate_fetoscopy


def measure(work: Path, seeds: int, ratios: list[float], n: int) -> list[dict]:
    rows = []
    for seed in range(seeds):
        root = work / f"syn{n}_{seed}"
        simulate_fetoscopy(root, syn(n, seed), overwrite=True)
        ds = read_dataset(root)
        row: dict = {"seed": seed}
        for r in ratios:
            m = MatchOptions(ratio=r)
            lba = mosaic_error(errors(ds, run_lba_emt(
                ds, progress=False, options=SequentialOptions(matching=m))))
            ba = mosaic_error(errors(ds, run_ba_emt(
                ds, progress=False, options=BundleOptions(matching=m))))
            row[str(r)] = {"lba-emt": lba, "ba-emt": ba, "lba/ba": lba / ba}
        print(seed, {k: {m: round(v, 3) for m, v in x.items()} for k, x in row.items()
                     if k != "seed"}, flush=True)
        rows.append(row)
    return rows


def summary(rows: list[dict], ratios: list[float]) -> dict:
    out = {}
    base = str(ratios[0])
    for r in map(str, ratios):
        lba = np.array([x[r]["lba-emt"] for x in rows])
        ba = np.array([x[r]["ba-emt"] for x in rows])
        q = lba / ba
        out[r] = {"lba-emt median": float(np.median(lba)), "ba-emt median": float(np.median(ba)),
                  "lba/ba median": float(np.median(q)),
                  "seeds lba/ba <= 1.25": int((q <= 1.25).sum()),
                  "lba-emt lower than at " + base: int(
                      (lba < np.array([x[base]["lba-emt"] for x in rows])).sum()),
                  "ba-emt lower than at " + base: int(
                      (ba < np.array([x[base]["ba-emt"] for x in rows])).sum())}
    return out


def markdown(res: dict) -> str:
    ratios = list(res["summary"])
    base = ratios[0]
    L = [f"# SIFT ratio test on SYN {res['frames']} (bench/bench_sift_ratio.py)", "",
         f"`{res['command']}`, {res['runtime_s']:.0f} s; exhaustive matching, paper Sigma_p.", "",
         "| seed | " + " | ".join(f"lba-emt / ba-emt / lba/ba at {r}" for r in ratios) + " |",
         "|---|" + "---|" * len(ratios)]
    for x in res["seeds"]:
        L.append(f"| {x['seed']} | " + " | ".join(
            f"{fmt(x[r]['lba-emt'], 3)} / {fmt(x[r]['ba-emt'], 3)} / {fmt(x[r]['lba/ba'])}"
            for r in ratios) + " |")
    L += ["", f"Over {len(res['seeds'])} seeds:", ""]
    L += md_table(["ratio", "lba-emt e_M median", "ba-emt e_M median", "lba/ba median",
                   "seeds lba/ba <= 1.25", f"lba-emt lower than at {base}",
                   f"ba-emt lower than at {base}"],
                  [[r, fmt(s["lba-emt median"], 3), fmt(s["ba-emt median"], 3),
                    fmt(s["lba/ba median"]), s["seeds lba/ba <= 1.25"],
                    s[f"lba-emt lower than at {base}"], s[f"ba-emt lower than at {base}"]]
                   for r, s in res["summary"].items()])
    return "\n".join(L) + "\n"


def main() -> None:
    p = bench_args(__doc__.splitlines()[0], seeds=12)
    p.add_argument("--ratios", type=float, nargs="+", default=[0.8, 0.6])
    default_out = RESULTS / "sift_ratio.json"
    args = add_options(p, frames=152, out=default_out).parse_args()
    bench = BenchRun()
    res: dict = {"machine": machine_info(), "command": "python bench/bench_sift_ratio.py "
                 f"--seeds {args.seeds} --ratios {' '.join(map(str, args.ratios))} "
                 f"--frames {args.frames}"
                 + ("" if args.out == default_out else f" --out {args.out}"), "frames": args.frames}
    res["seeds"] = measure(bench.work, args.seeds, args.ratios, args.frames)
    res["summary"] = summary(res["seeds"], args.ratios)
    bench.finish(res, args.out, markdown)
    print(args.out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
