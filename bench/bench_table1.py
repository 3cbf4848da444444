"""Seed 000 Table 1 and the accuracy table, reproduced on the simulator (issue 7, items 1-2).

Sequences (bench/_common.py): SYN circular, 152 frames (4 laps as in the paper's Fig. 1), and a
phantom-like hand-held sequence, 155 frames (tilted plane, rotations, circular FOV; the paper's
PHB), each also with the paper's black frames (Sec. 4.2.3). Every method runs through
`fusedmosaic.runner.run_dataset` (what `fusedmosaic run` does, mosaic included) and is scored
by `fusedmosaic.evaluation.evaluate_output` against the simulator's true homographies.

1. Table 1 (sequences without black frames): #images, #pairs (registered; the paper's "matched
   pairs"), pairs attempted, average correspondences per registered pair, matching s and
   optimisation s for pairwise (PairVis), lba-emt (LBAVis+EMT), ba (BAVis) and ba-emt
   (BAVis+EMT, all O(N^2) pairs as in the paper), plus ba-emt with EMT-guided pairs; the paper's
   figures beside ours and the ratios. lba-emt uses the paper's presets (Sec. 4.2: SYN W=5,
   chi_e=3, K=3x5; PHB W=3, chi_e=1, K=3x3); its pairs are counted by wrapping the matcher the
   sequential mosaicker calls.
2. Accuracy: e_M (Eq. 29), max e_j (Eq. 28), drift ratio (mean e_j over the last quarter / first
   quarter), unplaced frames, for pairwise, ba, ba-emt (all and EMT-guided pairs), emt and
   lba-emt on all four sequences.

The BA problems of the SYN runs are saved (work/problems/) for the C++ replay (bench_cpp.py).

    python bench/bench_table1.py [--quick] [--work DIR] [--out bench/results/table1.json]
"""

from __future__ import annotations

import json
import sys
import time
from contextlib import contextmanager
from pathlib import Path

from _common import (
    DEFAULT_WORK,
    PAPER_MACHINE,
    PAPER_NAMES,
    PAPER_TABLE1,
    RESULTS,
    BenchRun,
    bench_args,
    ensure_dataset,
    machine_info,
    ratio,
    record_bundle_problems,
    sequences,
)

# (row name, method, options factory (base sequence -> options or None))
METHODS = [
    ("pairwise", "pairwise", lambda base: None),
    ("lba-emt", "lba-emt", lambda base: _lba_options(base)),
    ("ba", "ba", lambda base: None),
    ("ba-emt", "ba-emt", lambda base: _bundle_options("all")),
    ("ba-emt-guided", "ba-emt", lambda base: _bundle_options("emt-guided")),
    ("emt", "emt", lambda base: None),
]
TABLE1_ROWS = ("pairwise", "lba-emt", "ba", "ba-emt", "ba-emt-guided")
RECORD = {("syn", "ba"), ("syn", "ba-emt"), ("syn", "ba-emt-guided")}  # problems for the C++ run


def _lba_options(base: str):
    from fusedmosaic.estimation.sequential import SequentialOptions

    return SequentialOptions.preset("phb" if base == "handheld" else "syn")


def _bundle_options(selection: str):
    from fusedmosaic.estimation.bundle import BundleOptions

    return BundleOptions(pair_selection=selection)


@contextmanager
def count_sequential_matches():
    """Counts the pair registrations of the sequential mosaicker (attempted, registered and
    their inliers) by wrapping the match_pair it calls; the wrapper only observes."""
    from fusedmosaic.estimation import sequential

    counts = {"attempted": 0, "registered": 0, "inliers": 0}
    original = getattr(sequential, "match_pair", None)
    if original is None:
        yield None
        return

    def counting(*args, **kwargs):
        m = original(*args, **kwargs)
        counts["attempted"] += 1
        if m.ok:
            counts["registered"] += 1
            counts["inliers"] += m.n_inliers
        return m

    sequential.match_pair = counting
    try:
        yield counts
    finally:
        sequential.match_pair = original


def run_one(
    data: Path, out: Path, name: str, method: str, options, *, problems: Path | None, stem: str
):
    from fusedmosaic.evaluation import evaluate_output
    from fusedmosaic.runner import run_dataset

    recorders = []
    with count_sequential_matches() as counts:
        if problems is not None:
            with record_bundle_problems(problems, stem) as recorders:
                t0 = time.perf_counter()
                run_dataset(data, method, out, progress=False, options=options, report=False)
                wall = time.perf_counter() - t0
        else:
            t0 = time.perf_counter()
            run_dataset(data, method, out, progress=False, options=options, report=False)
            wall = time.perf_counter() - t0
    ev = evaluate_output(out, data)
    rep = json.loads((out / "report.json").read_text())
    t = rep["timings_s"]
    pairs = dict(rep.get("pairs", {}))
    if method == "lba-emt" and counts is not None:
        pairs = {
            "attempted": counts["attempted"],
            "registered": counts["registered"],
            "mean_correspondences": counts["inliers"] / max(counts["registered"], 1),
        }
    row = {
        "name": name,
        "method": method,
        "paper_name": PAPER_NAMES[name],
        "frames": ev["frames"],
        "placed": ev["placed"],
        "unplaced": ev["unplaced"],
        "e_M_px": ev["e_M_px"],
        "max_e_j_px": ev["max_e_j_px"],
        "drift_ratio": ev["drift_ratio"],
        "e_j_px": ev["e_j_px"],
        "pairs_attempted": pairs.get("attempted"),
        "pairs_registered": pairs.get("registered"),
        "mean_correspondences": pairs.get("mean_correspondences"),
        "features_s": t.get("features"),
        "matching_s": t.get("matching"),
        "optimisation_s": t.get("optimisation"),
        "method_s": _method_seconds(t),
        "compose_s": t.get("compose_mosaic"),
        "wall_s": wall,
        "solver": {
            k: rep["solver"].get(k)
            for k in ("linear_solver", "iterations", "termination", "num_residual_blocks")
        }
        if "solver" in rep
        else None,
    }
    if method == "lba-emt":
        row["latency_ms"] = rep.get("latency_ms")
        row["window_step_ms"] = rep.get("window_step_ms")
    if recorders:
        row["saved_problems"] = [
            {
                "file": str(r.log.path),
                "python_solve_s": r.python_solve_s,
                "ceres_solve_s": r.summary.solve_time_s if r.summary else None,
            }
            for r in recorders
            if r.summary is not None
        ]
    return row


def _method_seconds(t: dict) -> float:
    """Time of the method itself (everything but reading, composing and reporting)."""
    skip = {"read_dataset", "compose_mosaic", "gain_compensation", "report", "video"}
    return float(sum(v for k, v in t.items() if k not in skip and isinstance(v, int | float)))


def table1(rows_by_seq: dict) -> dict:
    out = {}
    for base in ("syn", "handheld"):
        rows = rows_by_seq.get(base)
        if not rows:
            continue
        block = []
        for name in TABLE1_ROWS:
            r = rows.get(name)
            if r is None:
                continue
            paper = PAPER_TABLE1[base].get(name)
            entry = {
                "method": name,
                "paper_name": PAPER_NAMES[name],
                "images": r["frames"],
                "pairs": r["pairs_registered"],
                "pairs_attempted": r["pairs_attempted"],
                "avg_correspondences": r["mean_correspondences"],
                "features_s": r["features_s"],
                "matching_s": r["matching_s"],
                "optimisation_s": r["optimisation_s"],
            }
            if paper:
                p = dict(
                    zip(
                        ("images", "pairs", "avg_correspondences", "matching_s", "optimisation_s"),
                        paper,
                        strict=True,
                    )
                )
                entry["paper"] = p
                entry["ratio"] = {
                    "pairs_ours_over_paper": ratio(r["pairs_registered"], p["pairs"]),
                    "corr_ours_over_paper": ratio(
                        r["mean_correspondences"], p["avg_correspondences"]
                    ),
                    "matching_speedup": ratio(p["matching_s"], r["matching_s"]),
                    "optimisation_speedup": ratio(p["optimisation_s"], r["optimisation_s"]),
                }
            block.append(entry)
        out[base] = block
    return out


def main(argv=None) -> dict:
    ap = bench_args(
        __doc__,
        quick="60-frame sequences (smoke run)",
        work=f"datasets and saved problems (default: a temporary folder; run_all "
        f"uses {DEFAULT_WORK})",
        out=RESULTS / "table1.json",
    )
    ap.add_argument("--sequences", nargs="*", default=None, help="subset, e.g. syn handheld")
    ap.add_argument("--methods", nargs="*", default=None, help="subset of row names")
    args = ap.parse_args(argv)
    bench = BenchRun(args.work)
    args.work = bench.work
    problems = args.work / "problems"
    machine = machine_info()
    rows_by_seq: dict[str, dict] = {}
    accuracy = []
    for seq in sequences(args.quick):
        if args.sequences and seq.name not in args.sequences:
            continue
        data = ensure_dataset(args.work, seq)
        rows: dict[str, dict] = {}
        for name, method, make_options in METHODS:
            if args.methods and name not in args.methods:
                continue
            record = problems if (seq.name, name) in RECORD else None
            r = run_one(
                data,
                args.work / "runs" / seq.name / name,
                name,
                method,
                make_options(seq.base),
                problems=record,
                stem=f"{seq.name}-{name}",
            )
            r["sequence"] = seq.name
            rows[name] = r
            print(
                f"{seq.name:<15} {name:<14} e_M {r['e_M_px']:8.3f} px  max {r['max_e_j_px']:8.3f}"
                f"  drift {r['drift_ratio'] or float('nan'):5.2f}  unplaced {r['unplaced']:3d}  "
                f"pairs {r['pairs_registered'] or 0:>5}/{r['pairs_attempted'] or 0:<6} matching "
                f"{r['matching_s'] or 0:6.2f} s  optimisation {r['optimisation_s'] or 0:7.3f} s"
                f"  wall {r['wall_s']:6.1f} s",
                flush=True,
            )
            accuracy.append({k: v for k, v in r.items() if k != "e_j_px"})
        rows_by_seq[seq.name] = rows
    result = {
        "benchmark": "seed 000 Table 1 + accuracy on the simulator (bench/bench_table1.py)",
        "quick": args.quick,
        "machine": machine,
        "paper_machine": PAPER_MACHINE,
        "sequences": {
            s.name: {"frames": s.frames, "black_frames": s.options().black_frames, "motion": s.base}
            for s in sequences(args.quick)
        },
        "table1": table1(rows_by_seq),
        "accuracy": accuracy,
        "e_j_px": {
            f"{s}/{n}": r["e_j_px"] for s, rows in rows_by_seq.items() for n, r in rows.items()
        },
    }
    return bench.finish(result, args.out)


if __name__ == "__main__":
    main(sys.argv[1:])
