"""Offline methods of seed 000 on the simulated SYN sequence (issue: BA / BA+EMT).

Measures, in one run on this machine: e_M, drift ratio, pairs attempted / registered, mean
correspondences, matching and optimisation seconds for pairwise, ba, ba-emt (all pairs, the
paper's O(N^2)), ba-emt with EMT-guided pairs, and emt; then the EMT-guided / all-pairs matching
ratio. Writes bench/results/offline.json.

    python bench/bench_offline.py [--frames 150] [--out bench/results/offline.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

from _common import fmt

from fusedmosaic.estimation.bundle import BundleOptions
from fusedmosaic.evaluation import evaluate_output
from fusedmosaic.runner import run_dataset
from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

CASES = [
    ("pairwise", "pairwise", None),
    ("ba", "ba", None),
    ("ba-emt", "ba-emt", None),
    ("ba-emt (emt-guided)", "ba-emt", BundleOptions(pair_selection="emt-guided")),
    ("emt", "emt", None),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "offline.json"))
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        data = simulate_fetoscopy(Path(tmp) / "syn", FetoscopyOptions(n_frames=args.frames))
        for name, method, options in CASES:
            out = Path(tmp) / name.replace(" ", "_")
            t0 = time.perf_counter()
            run_dataset(data, method, out, progress=False, options=options)
            wall = time.perf_counter() - t0
            ev = evaluate_output(out, data)
            rep = json.loads((out / "report.json").read_text())
            t = rep["timings_s"]
            rows.append({
                "name": name, "method": method, "frames": ev["frames"],
                "placed": ev["placed"], "e_M_px": ev["e_M_px"], "max_e_j_px": ev["max_e_j_px"],
                "drift_ratio": ev["drift_ratio"], **{f"pairs_{k}": v for k, v in
                                                     rep.get("pairs", {}).items()},
                "features_s": t.get("features"), "matching_s": t.get("matching"),
                "optimisation_s": t.get("optimisation"), "wall_s": wall,
                "solver": rep.get("solver", {}).get("linear_solver"),
                "iterations": rep.get("solver", {}).get("iterations"),
            })
            print(f"{name:<22} e_M {ev['e_M_px']:8.3f} px  "
                  f"drift {fmt(ev['drift_ratio']):>5}  "
                  f"pairs {rep.get('pairs', {}).get('attempted', '-'):>6}  matching "
                  f"{t.get('matching', 0):6.2f} s  "
                  f"optimisation {t.get('optimisation') or 0:6.3f} s")
    by = {r["name"]: r for r in rows}
    full, guided = by["ba-emt"], by["ba-emt (emt-guided)"]
    summary = {
        "matching_speedup_emt_guided": full["matching_s"] / guided["matching_s"],
        "pairs_ratio_emt_guided": full["pairs_attempted"] / guided["pairs_attempted"],
        "e_M_ratio_emt_guided": guided["e_M_px"] / full["e_M_px"],
        "paper_ba_emt_optimisation_s": 321.928,  # seed 000 Table 1, SYN
        "ba_emt_optimisation_speedup_vs_paper": 321.928 / full["optimisation_s"],
    }
    print(json.dumps(summary, indent=1))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"machine": {"python": platform.python_version(),
                                           "cpus": __import__("os").cpu_count()},
                               "rows": rows, "summary": summary}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
