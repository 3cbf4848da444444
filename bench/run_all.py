"""One entry for the benchmarks of issue 7 (`make bench`): the papers' tables, the peers and the
solver core, measured in one run on this machine; then bench/results/summary.md and the
"## Performance" section at the end of README.md.

Stages (each a script of bench/, run as a child process; the simulated sequences are shared
through --work):
  table1      bench_table1.py     seed 000 Table 1 + accuracy (SYN 152, hand-held 155, +black)
  latency     bench_latency.py    per-frame latency distributions of lba-emt and kalman-robot
  cpp         bench_cpp.py        C++ BundleAdjuster / SlidingWindow replays of saved problems
  pcle_cases  bench_pcle_cases.py seed 004 Tables I and II (the pCLE helper's benchmark)
  peers       bench_peers.py      cv2.Stitcher (SCANS) and a plain OpenCV SIFT chain, same frames
With --others, the other helpers' benchmarks run too (solvers, pcle_core, sequential,
compositing, offline, lba_experiments; minutes each); their latest results are linked from the
summary anyway.
With --only, the stages not run keep the record of the run that produced them (summary.json
"runs"), and summary.md says per stage which run that was.

    python bench/run_all.py            # full: <= 20 min on 2 cores; results in bench/results/
    python bench/run_all.py --quick    # smoke run (60-frame sequences), results in
                                       # build/bench_quick/results/, README untouched
    python bench/run_all.py --summary-only   # rebuild summary.md (+ README) from the JSON
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

from _common import (
    BENCH,
    DEFAULT_WORK,
    PAPER_MACHINE,
    PAPER_NAMES,
    PAPER_PCLE,
    PCLE_CASES,
    REPO,
    RESULTS,
    fmt,
    machine_info,
    md_table,
    ratio,
    write_json,
)

BUDGET_S = 20 * 60
QUICK_ROOT = REPO / "build" / "bench_quick"
# cpp replays what table1 and latency saved; peers (the stitcher, the longest) goes last.
MINE = ("table1", "latency", "cpp", "pcle_cases", "peers")
OTHERS = ("solvers", "pcle_core", "sequential", "compositing", "offline", "lba_experiments")


def stage_command(
    stage: str, results: Path, work: Path, quick: bool, stitcher_timeout: float
) -> list[str]:
    """The command line of one stage; quick runs pass smaller sizes."""
    w = ["--work", str(work)]
    q = ["--quick"] if quick else []
    args = {
        "table1": [*w, "--out", str(results / "table1.json"), *q],
        "latency": [*w, "--out", str(results / "latency.json"), *q],
        "cpp": [*w, "--repeats", "2" if quick else "3", "--out", str(results / "cpp_solvers.json")],
        "pcle_cases": ["--out", str(results)]
        + ("--seeds --timing-frames 50".split() if quick else []),
        "peers": [
            *w,
            "--out",
            str(results / "peers.json"),
            "--stitcher-timeout",
            f"{stitcher_timeout:.0f}",
            *q,
        ],
        "solvers": ["--out", str(results / "solvers.json")] + (["--runs", "2"] if quick else []),
        "pcle_core": ["--out", str(results / "pcle_core.json")]
        + (["--frames", "50"] if quick else []),
        "sequential": ["--out", str(results / "sequential.json")]
        + (
            "--frames 200 --sift-frames 60 --solver-frames 100 --repeats 1".split() if quick else []
        ),
        "compositing": ["--out", str(results / "compositing.json")]
        + ("--frames 200 --render-frames 150 --repeats 1".split() if quick else []),
        "offline": ["--out", str(results / "offline.json")] + (["--frames", "40"] if quick else []),
        "lba_experiments": ["--out", str(results / "lba_experiments.json")]
        + (["--quick"] if quick else []),
    }[stage]
    script = "bench_pcle_cases.py" if stage == "pcle_cases" else f"bench_{stage}.py"
    return [sys.executable, str(BENCH / script), *args]


def run_stage(name: str, cmd: list[str], log_dir: Path) -> dict:
    """Runs one stage, echoing its output and keeping it in log_dir/<name>.log."""
    print(
        f"\n=== {name}: {' '.join(Path(c).name if c.endswith('.py') else c for c in cmd[1:])}",
        flush=True,
    )
    log_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(log_dir / f"{name}.log", "w") as log:
        proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO
        )
        for line in proc.stdout:
            sys.stdout.write(line)
            log.write(line)
        rc = proc.wait()
    wall = time.perf_counter() - t0
    print(f"=== {name}: {'ok' if rc == 0 else f'FAILED (exit {rc})'} in {wall:.0f} s", flush=True)
    return {"stage": name, "exit_code": rc, "seconds": wall, "log": str(log_dir / f"{name}.log"),
            "finished": _now()}


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


# -- the runs behind the results -------------------------------------------------------------


def previous_runs(old: dict | None) -> list[dict]:
    """The run records of an earlier summary.json: its "runs", or the single "run" that
    summaries written before "runs" held."""
    if not old:
        return []
    if old.get("runs") is not None:
        return list(old["runs"])
    return [old["run"]] if old.get("run") else []


def merge_runs(previous: list[dict], run: dict) -> list[dict]:
    """The runs that produced the results folder's stages, oldest first: `run`'s stages replace
    the same stages of the earlier runs, whose other stages keep their run's record (with
    --only, the stages not rerun are still the earlier run's); a run left without stages, or of
    the other kind (quick or full), is dropped."""
    now = {st["stage"] for st in run["stages"]}
    out = []
    for r in previous:
        if bool(r.get("quick")) != bool(run.get("quick")):
            continue
        kept = [st for st in r.get("stages", []) if st["stage"] not in now]
        if kept:
            out.append({**r, "stages": kept})
    return out + [run]


def stage_runs(runs: list[dict]) -> dict[str, dict]:
    """stage -> the record of the run that produced it (the last one that ran it)."""
    return {st["stage"]: r for r in runs for st in r.get("stages", [])}


def from_other_runs(runs: list[dict], stages: dict[str, str],
                    unrecorded: dict[str, str] | None = None) -> str:
    """"" when the stages named ({label: stage}) come from one run, else a sentence saying
    which run (finished at) each label's figures come from (`unrecorded`: stages no run
    record names, unrecorded_stages)."""
    by = stage_runs(runs)
    found = {label: f"the run finished {by[st].get('finished')}" for label, st in stages.items()
             if st in by}
    # (which earlier run each unrecorded stage came from is not known: taken as one)
    found.update({label: "an earlier run with no record"
                  for label, st in stages.items() if st in (unrecorded or {})})
    if len(set(found.values())) <= 1:
        return ""
    return " Figures from different runs: " + "; ".join(
        f"{label} from {when}" for label, when in found.items()) + "."


# The JSON each stage of MINE writes (a stage without a run record is dated by it).
STAGE_JSON = {"table1": "table1.json", "latency": "latency.json", "cpp": "cpp_solvers.json",
              "pcle_cases": "pcle_cases.json", "peers": "peers.json"}


def unrecorded_stages(results: Path, runs: list[dict]) -> dict[str, str]:
    """The stages whose JSON is in `results` but in no run record (a run from before
    summary.json kept the earlier runs of --only): stage -> its JSON's date (written_at)."""
    by = stage_runs(runs)
    return {
        stage: f"{written_at(results / name):%Y-%m-%d %H:%M} UTC"
        for stage, name in STAGE_JSON.items()
        if stage not in by and (results / name).is_file()
    }


def runs_phrase(runs: list[dict], unrecorded: dict[str, str] | None = None) -> str:
    """What produced the results, for the README line: one run's minutes, or per run its
    stages, command, end and minutes (and the stages no run record names, with their JSON's
    date)."""
    if len(runs) == 1 and not unrecorded:
        return f"{runs[0]['total_s'] / 60:.0f} min"
    parts = [
        f"{', '.join(st['stage'] for st in r['stages'])} from `{_command(r)}` finished "
        f"{r.get('finished')} ({r['total_s'] / 60:.1f} min)"
        for r in runs
    ]
    if unrecorded:
        dates = sorted(unrecorded.values())
        parts.append(
            f"{', '.join(unrecorded)} from earlier runs with no record (their JSON written or "
            f"committed {dates[0]}" + (f" to {dates[-1]})" if dates[-1] != dates[0] else ")")
        )
    return "stages from different runs: " + "; ".join(parts)


def _command(run: dict) -> str:
    return run.get("command") or "python bench/run_all.py"


def runs_markdown(runs: list[dict], unrecorded: dict[str, str] | None = None) -> list[str]:
    """summary.md's lines on the run(s) behind the figures: one run's stage times, or, when
    stages come from several runs (run_all --only), per stage the run that produced it;
    `unrecorded`: stages no run record names, with their JSON's date."""
    if not runs and not unrecorded:
        return []
    if len(runs) == 1 and not unrecorded:
        run = runs[0]
        return [
            f"Total run time {run['total_s'] / 60:.1f} min (budget {BUDGET_S // 60} min): "
            + ", ".join(
                f"{st['stage']} {st['seconds']:.0f} s"
                + ("" if st["exit_code"] == 0 else " **failed**")
                for st in run["stages"]
            )
            + ".",
            "",
        ]
    rows = [
        [
            st["stage"],
            st.get("finished") or r.get("finished"),
            f"`{_command(r)}` (finished {r.get('finished')}, {r['total_s'] / 60:.1f} min)",
            f"{st['seconds']:.0f}" + ("" if st["exit_code"] == 0 else " **failed**"),
        ]
        for r in runs
        for st in r["stages"]
    ] + [
        [stage, f"(its JSON written or committed {when})",
         "an earlier run, no record in summary.json", "–"]
        for stage, when in (unrecorded or {}).items()
    ]
    return (
        [
            "The stages come from different runs (each stage's figures from the last run "
            f"that ran it; budget {BUDGET_S // 60} min per run):",
            "",
        ]
        + md_table(["stage", "stage finished (UTC)", "run", "stage s"], rows)
        + [""]
    )


# -- summary ---------------------------------------------------------------------------------


def load(results: Path, name: str) -> dict | None:
    p = results / name
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError):
        return None


def _x(a) -> str:
    return "–" if a is None else (f"{a:.0f}x" if a >= 100 else f"{a:.1f}x")


def _mean(xs) -> float | None:
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return sum(xs) / len(xs) if xs else None


SEQ_TITLE = {
    "syn": "SYN circular",
    "handheld": "hand-held phantom-like (paper: PHB)",
    "syn-black": "SYN + 12 black frames",
    "handheld-black": "hand-held + 12 black frames",
}


def headline(t1, lat, peers, cpp) -> dict:
    h: dict = {}
    if t1:
        for base, rows in t1["table1"].items():
            by = {r["method"]: r for r in rows}
            for m in ("lba-emt", "ba-emt"):
                if m in by and by[m].get("ratio"):
                    h[f"{m}_optimisation_speedup_vs_paper_{base}"] = by[m]["ratio"][
                        "optimisation_speedup"
                    ]
        acc = {(r["sequence"], r["name"]): r for r in t1["accuracy"]}
        for seq in ("syn", "handheld", "syn-black", "handheld-black"):
            a, b = acc.get((seq, "lba-emt")), acc.get((seq, "ba-emt"))
            if a and b:
                h[f"lba_emt_over_ba_emt_e_M_{seq}"] = ratio(a["e_M_px"], b["e_M_px"])
                h[f"e_M_px_{seq}"] = {"lba-emt": a["e_M_px"], "ba-emt": b["e_M_px"]}
    if lat and peers:
        # Like for like: registration against registration. lba-emt's time is add_frame's
        # (features, matching, window step, keyframes; it composes no mosaic), so the
        # Stitcher's is estimateTransform() alone, without composePanorama() (seams, blending:
        # 40 % of its stitch() on SYN; the whole stitch() made the ratio 17.9x, not 10.8x).
        for seq, r in lat.get("lba-emt", {}).items():
            st = [
                p
                for p in peers["rows"]
                if p["sequence"] == seq and p["peer"].startswith("cv2.Stitcher")
            ]
            if not st:
                continue
            st = st[0]
            out = {"lba_emt_ms_per_frame": 1e3 / r["frames_per_s"]["all"]}
            if st.get("success", True) and st.get("registration_s") is not None:
                n = st["frames"]
                out["stitcher_registration_ms_per_frame"] = 1e3 * st["registration_s"] / n
                if st.get("compositing_s") is not None:
                    out["stitcher_compositing_ms_per_frame"] = 1e3 * st["compositing_s"] / n
                out["ratio"] = out["stitcher_registration_ms_per_frame"] / out[
                    "lba_emt_ms_per_frame"
                ]
            else:
                out["stitcher"] = (
                    st.get("status") if not st.get("success", True)
                    else "no registration time recorded (peers.json older than its split)"
                )
            h[f"stitcher_registration_over_lba_emt_{seq}"] = out
    return h


def stitcher_headline(seq: str, s: dict) -> str:
    """The headline sentence comparing lba-emt's and cv2.Stitcher's registration time per
    frame (s: headline()'s stitcher_registration_over_lba_emt_<seq>)."""
    lba = (
        f"lba-emt {s['lba_emt_ms_per_frame']:.0f} ms (add_frame streamed, all frames: features, "
        "matching, window step; no mosaic)"
    )
    if "ratio" not in s:
        return f"Registration time per frame, {SEQ_TITLE[seq]}: {lba}; cv2.Stitcher SCANS: " \
            f"{s['stitcher']}."
    comp = s.get("stitcher_compositing_ms_per_frame")
    return (
        f"Registration time per frame, {SEQ_TITLE[seq]}: {lba} vs cv2.Stitcher SCANS "
        f"{s['stitcher_registration_ms_per_frame']:.0f} ms (estimateTransform: features, "
        f"all-pairs matching, bundle adjustment) -> lba-emt {_x(s['ratio'])} faster at "
        "registration"
        + (
            f"; compositing is left out on both sides (the Stitcher's composePanorama, seams "
            f"and blending: {comp:.0f} ms more per frame)."
            if comp is not None else "."
        )
    )


def textured_e_M(t1: dict, seq: str, name: str) -> float | None:
    """e_M over the frames that are not black (None on sequences without black frames)."""
    black = set(t1["sequences"].get(seq, {}).get("black_frames") or [])
    if not black:
        return None
    e = t1["e_j_px"].get(f"{seq}/{name}") or []
    return _mean([x for k, x in enumerate(e) if k not in black])


def sequential_budgets_line(seq: dict | None) -> str | None:
    """Issue 4's live budgets from bench_sequential.py's latest JSON (its own run, not this
    one's), or None without it."""
    b = (seq or {}).get("budgets") or {}
    try:
        v = {k: b[k]["value"] for k in ("step_median_ms", "step_p95_ms", "orb_frames_per_s",
                                        "drift_ratio", "unplaced", "latency_growth")}
    except (KeyError, TypeError):
        return None
    sift = ((seq.get("throughput") or {}).get("sift") or {}).get("frames_per_s_steady")
    # the wall time's p95 growth is the budget; the CPU time's beside it (less load-sensitive)
    cpu_growth = ((seq.get("long") or {}).get("p95_latency_growth") or {}).get(
        "process_cpu_time", (seq.get("cpu_diagnostics") or {}).get("latency_growth_cpu"))
    memory = ((seq.get("long") or {}).get("memory") or {}).get("at_frames") or {}
    peaks = [f"+{a['peak_rss_over_baseline_mb']:.0f} MB at {n} frames"
             for n, a in memory.items() if a.get("peak_rss_over_baseline_mb") is not None]
    return (
        f"lba-emt live budgets (`python bench/bench_sequential.py`, its own latest run: "
        f"[bench/results/sequential.md](bench/results/sequential.md)): window step median "
        f"{v['step_median_ms']:.2f} ms (<= 5), p95 {v['step_p95_ms']:.2f} ms (<= 15); end to end "
        f"ORB {v['orb_frames_per_s']:.1f} frames/s (>= 25)"
        + (f", SIFT {sift:.1f}" if sift else "")
        + f"; 3300 frames: drift ratio {v['drift_ratio']:.2f} (<= 1.3), {v['unplaced']} "
        f"unplaced, p95 latency growth {v['latency_growth']:.2f} (wall time, <= 1.2"
        + (f"; process CPU time {cpu_growth:.2f}" if cpu_growth is not None else "")
        + ")"
        + (f"; peak RSS over the baseline before streaming {', '.join(peaks)}" if peaks else "")
        + "."
    )


def written_at(path: Path) -> datetime:
    """When `path` was written: its last commit's time when it is committed unchanged (a
    checkout sets every file's mtime to the checkout's), else its mtime."""
    try:
        changed = subprocess.run(["git", "status", "--porcelain", "--", str(path)], cwd=REPO,
                                 capture_output=True, text=True, check=True).stdout.strip()
        stamp = subprocess.run(["git", "log", "-1", "--format=%ct", "--", str(path)], cwd=REPO,
                               capture_output=True, text=True, check=True).stdout.strip()
        if not changed and stamp:
            return datetime.fromtimestamp(int(stamp), timezone.utc)
    except (OSError, subprocess.CalledProcessError, ValueError):
        pass
    return datetime.fromtimestamp(path.stat().st_mtime, timezone.utc)


def summary_markdown(results: Path, runs: list[dict] | dict | None) -> tuple[str, str, dict]:
    """(summary.md text, README section text, headline dict) from the JSON in `results`;
    `runs`: the run records behind them (merge_runs; one run's record is taken as a list)."""
    runs = [runs] if isinstance(runs, dict) else list(runs or [])
    t1 = load(results, "table1.json")
    lat = load(results, "latency.json")
    peers = load(results, "peers.json")
    cpp = load(results, "cpp_solvers.json")
    pcle = load(results, "pcle_cases.json")
    m = (t1 or lat or peers or {}).get("machine") or machine_info()
    quick = bool((t1 or {}).get("quick"))
    h = headline(t1, lat, peers, cpp)
    machine_line = (
        f"{m.get('cpu')}, {m.get('cores')} cores, {m.get('ram_gb')} GB RAM; "
        f"{m.get('platform')}; Python {m.get('python')}, numpy {m.get('numpy')}, "
        f"OpenCV {m.get('opencv')}"
    )
    L: list[str] = ["# fusedmosaic benchmarks (issue 7)", ""]
    when = runs[-1].get("finished") if runs else None
    unrecorded = unrecorded_stages(results, runs)
    one = (
        "every figure is one measurement of this run"
        if len(runs) <= 1 and not unrecorded
        else "every figure is one measurement of the run its stage names below"
    )
    L += [
        f"Generated by `python bench/run_all.py{' --quick' if quick else ''}`"
        + (f"; latest run finished {when}." if when else f" on {_now()}."),
        "",
        f"**Machine**: {machine_line}. Load average at the start of table1: "
        f"{m.get('load_average')} (other processes share the 2 cores; {one}, nothing copied "
        "or estimated).",
        "",
    ]
    if quick:
        L += [
            "**Quick smoke run** (60-frame sequences, fewer repeats): the figures check that "
            "everything runs, they are not the benchmark.",
            "",
        ]
    L += runs_markdown(runs, unrecorded)

    # headline
    L += ["## Headline", ""]
    hl = []
    for base, title in (("syn", "SYN"), ("handheld", "hand-held")):
        a = h.get(f"lba-emt_optimisation_speedup_vs_paper_{base}")
        b = h.get(f"ba-emt_optimisation_speedup_vs_paper_{base}")
        if a or b:
            hl.append(
                f"Optimisation vs the paper's Table 1 ({title}): lba-emt {_x(a)} faster, "
                f"ba-emt {_x(b)} faster (different machine and language: "
                f"{PAPER_MACHINE})."
            )
    for seq in ("syn", "handheld"):
        s = h.get(f"stitcher_registration_over_lba_emt_{seq}")
        if s:
            hl.append(
                stitcher_headline(seq, s)
                + from_other_runs(runs, {"lba-emt": "latency", "cv2.Stitcher": "peers"},
                                  unrecorded)
            )
    for seq in ("syn", "handheld", "syn-black", "handheld-black"):
        r = h.get(f"lba_emt_over_ba_emt_e_M_{seq}")
        e = h.get(f"e_M_px_{seq}")
        if r is not None:
            hl.append(
                f"e_M {SEQ_TITLE[seq]}: lba-emt {e['lba-emt']:.3f} px vs ba-emt "
                f"{e['ba-emt']:.3f} px (ratio {r:.2f})."
            )
    seq_line = sequential_budgets_line(load(results, "sequential.json"))
    if seq_line:
        hl.append(seq_line)
    L += [f"- {x}" for x in hl] + [""]

    # Table 1
    t1_md: list[str] = []
    if t1:
        for base, rows in t1["table1"].items():
            n = rows[0]["images"] if rows else "?"
            t1_md += [f"### Table 1, {SEQ_TITLE[base]} ({n} frames): ours / paper", ""]
            body = []
            for r in rows:
                p = r.get("paper") or {}
                q = r.get("ratio") or {}
                body.append(
                    [
                        f"{r['method']} ({r['paper_name']})",
                        r["images"],
                        f"{fmt(r['pairs'])} / {fmt(p.get('pairs'))}",
                        fmt(r["pairs_attempted"]),
                        f"{fmt(r['avg_correspondences'], 0)} / "
                        f"{fmt(p.get('avg_correspondences'), 0)}",
                        f"{fmt(r['matching_s'], 2)} / {fmt(p.get('matching_s'), 1)}",
                        _x(q.get("matching_speedup")),
                        f"{fmt(r['optimisation_s'], 3)} / {fmt(p.get('optimisation_s'), 1)}",
                        _x(q.get("optimisation_speedup")),
                        fmt(r["features_s"], 2),
                    ]
                )
            t1_md += md_table(
                [
                    "method",
                    "#images",
                    "#pairs",
                    "attempted",
                    "avg corr.",
                    "matching s",
                    "speed-up",
                    "optimisation s",
                    "speed-up",
                    "features s",
                ],
                body,
            ) + [""]
        t1_md += [
            "#pairs = registered pairs (the paper's matched pairs); attempted includes "
            "failed ones. Matching = descriptor matching + RANSAC of all attempted pairs "
            "(feature extraction separate, last column); optimisation = Ceres time "
            "(lba-emt: all window steps + the bootstrap BA over the first 40 frames). "
            "Speed-up = paper / ours. lba-emt runs the paper's presets (SYN: W=5, "
            "chi_e=3, K=3x5; PHB: W=3, chi_e=1, K=3x3) plus 2 EMT-predicted loop pairs "
            "per frame; its attempted pairs include the bootstrap's all-pairs matching of the "
            "first 40 frames (780). ba-emt-guided is ours only (pairs predicted from the "
            "tracker).",
            "",
        ]
    L += ["## Seed 000 Table 1 reproduced", ""] + (t1_md or ["(table1.json missing)", ""])

    # accuracy
    acc_md: list[str] = []
    if t1:
        body = []
        for r in t1["accuracy"]:
            textured = textured_e_M(t1, r["sequence"], r["name"])
            body.append(
                [
                    r["sequence"],
                    f"{r['name']} ({r['paper_name']})",
                    fmt(r["e_M_px"], 3),
                    fmt(r["max_e_j_px"], 3),
                    fmt(r["drift_ratio"], 2),
                    r["unplaced"],
                    fmt(textured, 3),
                    fmt(r["method_s"], 1),
                ]
            )
        acc_md = md_table(
            [
                "sequence",
                "method",
                "e_M px",
                "max e_j px",
                "drift ratio",
                "unplaced",
                "e_M textured frames px",
                "method s",
            ],
            body,
        ) + [
            "",
            "e_j (Eq. 28): mean distance over a 100x100 grid between estimated and true "
            "frame -> reference mappings, reference pixels; e_M (Eq. 29) its mean over placed "
            "frames. Drift ratio = mean e_j of the last quarter / first quarter. On the black-"
            "frame sequences the black frames are placed from the tracker alone (prior-only); "
            "'textured frames' leaves them out; all 12 lie in the first quarter (frames 7-54), "
            "so there the drift ratio compares the last quarter with tracker-only errors and is "
            "small. Pairwise stops at the first black frame (its chain has no way across). "
            "Method s = the method's own stages (no reading, no compositing).",
            "",
        ]
    L += ["## Accuracy, every method, both sequences, with and without black frames", ""]
    L += acc_md or ["(table1.json missing)", ""]

    # peers
    peer_md: list[str] = []
    if peers:
        v = peers["versions"]
        body = []
        ours = {(r["sequence"], r["name"]): r for r in (t1 or {}).get("accuracy", [])}
        lat_rows = (lat or {}).get("lba-emt", {})
        for r in peers["rows"]:
            body.append(
                [
                    r["sequence"],
                    r["peer"],
                    "yes" if r.get("success", True) else f"no: {r.get('status')}",
                    fmt(r.get("time_s"), 1),
                    fmt(r.get("registration_s"), 1),
                    fmt(r.get("time_per_frame_ms"), 0),
                    fmt(r.get("e_M_px"), 3),
                    fmt(r.get("max_e_j_px"), 3),
                    fmt(r.get("drift_ratio"), 2),
                    fmt(r.get("unplaced")),
                    _pano_check(r.get("panorama_check")),
                ]
            )
        for seq in ("syn", "handheld", "syn-black", "handheld-black"):
            for name in ("lba-emt", "ba-emt-guided"):
                o = ours.get((seq, name))
                if not o:
                    continue
                ms = 1e3 * o["method_s"] / o["frames"]
                label = f"fusedmosaic {name}"
                if name == "lba-emt" and seq in lat_rows:
                    ms = 1e3 / lat_rows[seq]["frames_per_s"]["all"]
                    label += " (streamed)"
                body.append(
                    [
                        seq,
                        label,
                        "yes",
                        fmt(ms * o["frames"] / 1e3, 1),
                        "",
                        fmt(ms, 0),
                        fmt(o["e_M_px"], 3),
                        fmt(o["max_e_j_px"], 3),
                        fmt(o["drift_ratio"], 2),
                        o["unplaced"],
                        "",
                    ]
                )
        peer_md = [f"OpenCV {v['opencv']}, numpy {v['numpy']}; same frames, in memory.", ""]
        peer_md += md_table(
            [
                "sequence",
                "method",
                "success",
                "time s",
                "of which registration s",
                "ms / frame",
                "e_M px",
                "max e_j px",
                "drift ratio",
                "unplaced",
                "e_j via the panorama image px",
            ],
            body,
        )
        peer_md += [
            "",
            "cv2.Stitcher: `Stitcher.create(SCANS)` defaults (affine, all pairs, "
            "seams, multi-band), FOV masks passed; time = estimateTransform() (registration) "
            "+ composePanorama() (seams, blending), i.e. stitch(); its e_j comes from its "
            "camera parameters (frame -> panorama "
            "affine A_k = R_k^-1, G_k = A_0^-1 A_k); last column: mean e_j of 5 evenly "
            "spaced frames registered into the returned panorama image with SIFT + RANSAC, "
            "frame 0 as the reference (independent of that convention; it includes the "
            "panorama's resampling and blending). OpenCV chain: SIFT + BFMatcher ratio "
            "0.75 + findHomography RANSAC 3 px, chained to the last placed frame. "
            "Ours: lba-emt time per frame from the streamed run (latency stage), "
            "ba-emt-guided from its method stages."
            + from_other_runs(
                runs,
                {"the peers": "peers", "lba-emt (streamed)": "latency",
                 "ba-emt-guided and the e_M of ours": "table1"},
                unrecorded,
            ),
            "",
        ]
    L += ["## Peers on the same frames", ""] + (peer_md or ["(peers.json missing)", ""])

    # latency
    lat_md: list[str] = []
    if lat:
        body = []
        for seq, r in lat.get("lba-emt", {}).items():
            e, s = r["end_to_end_ms"], r["solve_only_ms"]
            body.append(
                [
                    f"lba-emt, {seq} ({e['steady']['n']} frames after the bootstrap, "
                    f"{s['steps']} steps)",
                    _dist(e["steady"]),
                    fmt(e["all"]["p99"], 1),
                    f"step: {_dist(s['per_step_cpp'])}; per new frame: "
                    f"{_dist(s['per_new_frame_cpp'])}",
                    fmt(r["frames_per_s"]["steady"], 1),
                ]
            )
        for traj, r in lat.get("kalman-robot", {}).items():
            e, s = r["end_to_end_ms"], r["solve_only_ms"]
            body.append(
                [
                    f"kalman-robot, pCLE {traj} ({e['all']['n']} frames)",
                    _dist(e["all"]),
                    fmt(e["all"]["p99"], 1),
                    f"filter: {_dist(s['kalman_filter'], 3)}",
                    fmt(r["frames_per_s"]["all"], 0),
                ]
            )
        lat_md = md_table(
            [
                "method",
                "end to end median / p95 / p99 ms (steady)",
                "p99 all frames ms",
                "solve only median / p95 / p99 ms",
                "frames/s",
            ],
            body,
        )
        boot = [
            f"{seq}: {r['end_to_end_ms']['bootstrap_frame_ms']:.0f} ms"
            for seq, r in lat.get("lba-emt", {}).items()
            if r["end_to_end_ms"].get("bootstrap_frame_ms")
        ]
        lat_md += [
            "",
            "End to end = wall time of add_frame with the frame in memory. lba-emt "
            "steady = after the bootstrap (the first 40 frames are bundle-adjusted "
            f"together when the 40th arrives; that frame took {', '.join(boot)}); solve "
            "only = the C++ window step (assembly + Ceres, gating redo included), per "
            "step and per new frame (step / chi_e). kalman-robot: NCC fwd/bwd + SSIM + "
            "Kalman update per 512x448 frame with the noisy robot (Test #5); solve only = "
            "the filter update.",
            "",
        ]
    L += ["## Latency distributions", ""] + (lat_md or ["(latency.json missing)", ""])

    # C++
    cpp_md: list[str] = []
    if cpp:
        b = cpp.get("build") or {}
        if not b.get("ok", False):
            cpp_md += [f"C++ program not built: {b.get('error') or cpp.get('error')}", ""]
        recorded = {}
        for r in (t1 or {}).get("accuracy", []):
            for sp in r.get("saved_problems") or []:
                recorded[Path(sp["file"]).stem] = sp.get("ceres_solve_s")
        ba_rows, win_rows = [], []
        for p in cpp.get("problems", []):
            c, py = p.get("cpp"), p["python_bindings"]
            if p["kind"] == "ba":
                ba_rows.append(
                    [
                        p["problem"],
                        c and c["frames"],
                        c and c["pairs"],
                        c and c["correspondences"],
                        c and c.get("linear_solver"),
                        c and c.get("iterations"),
                        _dist_s(c["solve_wall_s"]) if c else "–",
                        _dist_s(py["solve_wall_s"]),
                        fmt(recorded.get(p["problem"]), 3),
                        f"{c['max_abs_diff_vs_recorded']:.1e}" if c else "–",
                    ]
                )
            else:
                win_rows.append(
                    [
                        p["problem"],
                        c and c["frames"],
                        c and c["steps"],
                        _dist(c["step_wall_ms"], 2) if c else "–",
                        _dist(py["step_wall_ms"], 2),
                        _dist(c["per_new_frame_ms"], 2) if c else "–",
                        f"{c['max_abs_diff_vs_recorded']:.1e}" if c else "–",
                    ]
                )
        cpp_md += md_table(
            [
                "problem",
                "frames",
                "pairs",
                "correspondences",
                "linear solver",
                "iterations",
                "C++ solve s median (min-max)",
                "via Python s median (min-max)",
                "in the pipeline run s",
                "max pose diff",
            ],
            ba_rows,
        ) + [""]
        cpp_md += md_table(
            [
                "window log",
                "frames",
                "steps",
                "C++ step ms median / p95 / p99",
                "via Python ms",
                "C++ per new frame ms",
                "max pose diff",
            ],
            win_rows,
        )
        built = f" The C++ program was built in {b['seconds']:.0f} s." if b.get("ok") else ""
        cpp_md += [
            "",
            "Problems saved from the simulator runs above (SYN; ba, ba-emt all pairs, "
            "ba-emt EMT-guided; the lba-emt window call log) and replayed by "
            "bench/cpp/solver_bench.cc (std::chrono, links fusedmosaic_core) and through "
            f"the Python bindings, alternating, {cpp.get('repeats')} rounds. Max pose "
            "diff = largest difference from the poses of the recorded run." + built
            + from_other_runs(
                runs,
                {"the replays (of the problem files there were then)": "cpp",
                 "'in the pipeline run s'": "table1"},
                unrecorded,
            ),
            "",
        ]
    L += ["## C++ solver core (no Python in the loop)", ""] + (
        cpp_md or ["(cpp_solvers.json missing)", ""]
    )

    # seed 004
    pc_md: list[str] = []
    if pcle:
        for traj, table in (("circle", "I"), ("spiral", "II")):
            t = pcle["trajectories"].get(traj)
            if not t:
                continue
            n = len(t["evenly_spaced_frames"])
            pc_md += [
                f"### Table {table}, {traj} ({t['frames']} frames; statistics at the "
                f"paper's {n} evenly spaced frames): ours / paper, µm",
                "",
            ]
            body = []
            for case, label in PCLE_CASES.items():
                s = t["stats_um"][case]["even"]
                pp = PAPER_PCLE[traj][case]
                body.append(
                    [label]
                    + [
                        f"{s[k]:.1f} / {pv:.1f}"
                        for k, pv in zip(("mean", "max", "std", "median"), pp, strict=True)
                    ]
                )
            pc_md += md_table(
                ["errors w.r.t. ground truth", "mean", "max", "std", "median"], body
            ) + [""]
            w = t.get("wilcoxon", {})
            if "#4 vs #5" in w and "#2 vs #3" in w:
                pc_md += [
                    f"Wilcoxon signed-rank at those frames: #4 vs #5 p = "
                    f"{w['#4 vs #5']['even'].get('p_value', float('nan')):.2g}, #2 vs #3 "
                    f"p = {w['#2 vs #3']['even'].get('p_value', float('nan')):.2g}.",
                    "",
                ]
        pc_md += [
            "From bench/bench_pcle_cases.py (pcle_cases.md has the variants, the c_img "
            "analysis and other seeds). The simulator is not the paper's phantom: absolute "
            "values differ; the ordering of the tests is the comparison.",
            "",
        ]
    L += ["## Seed 004 Tables I and II reproduced", ""] + (
        pc_md or ["(pcle_cases.json missing)", ""]
    )

    others = []
    for name in OTHERS:
        p = results / f"{name}.json"
        if p.is_file():
            md = p.with_suffix(".md")
            stamp = written_at(p)
            others.append(
                f"- bench_{name}.py -> [{p.name}]({p.name})"
                + (f", [{md.name}]({md.name})" if md.is_file() else "")
                + f" (written {stamp:%Y-%m-%d %H:%M} UTC)"
            )
    if others:
        L += ["## Other benchmarks (their own scripts; run with --others)", ""] + others + [""]
    summary = "\n".join(L)

    # README section: the current table, short
    R = [
        "## Performance",
        "",
        f"Measured by `python bench/run_all.py` (what `make bench` runs; "
        f"{'QUICK smoke run, ' if quick else ''}"
        f"{runs_phrase(runs, unrecorded) if runs else 'run time not recorded'}) on "
        f"{machine_line}. "
        "Full tables, the "
        "paper's figures beside ours and the method notes: "
        "[bench/results/summary.md](bench/results/summary.md).",
        "",
    ]
    R += [f"- {x}" for x in hl] + [""]
    if t1:
        body = []
        for base, rows in t1["table1"].items():
            for r in rows:
                p = r.get("paper") or {}
                q = r.get("ratio") or {}
                body.append(
                    [
                        base,
                        r["method"],
                        f"{fmt(r['pairs'])} / {fmt(p.get('pairs'))}",
                        f"{fmt(r['matching_s'], 2)} / {fmt(p.get('matching_s'), 1)}",
                        f"{fmt(r['optimisation_s'], 3)} / {fmt(p.get('optimisation_s'), 1)}",
                        _x(q.get("optimisation_speedup")),
                    ]
                )
        R += ["Seed 000 Table 1 (ours / paper):", ""]
        R += md_table(
            ["sequence", "method", "#pairs", "matching s", "optimisation s", "speed-up"], body
        ) + [""]
        seqs = list(t1["sequences"])
        acc = {(r["sequence"], r["name"]): r for r in t1["accuracy"]}
        names = []
        for r in t1["accuracy"]:
            if r["name"] not in names:
                names.append(r["name"])
        body = [
            [f"{n} ({PAPER_NAMES.get(n, n)})"]
            + [
                _acc_cell(acc[(s, n)], textured_e_M(t1, s, n)) if (s, n) in acc else "–"
                for s in seqs
            ]
            for n in names
        ]
        if peers:
            for peer in ("opencv-chain", "cv2.Stitcher SCANS"):
                cells = []
                for s in seqs:
                    pr = [r for r in peers["rows"] if r["sequence"] == s and r["peer"] == peer]
                    if not pr:
                        cells.append("–")
                    elif not pr[0].get("success", True) or pr[0].get("e_M_px") is None:
                        cells.append(f"failed ({pr[0].get('status')})")
                    else:
                        cells.append(
                            fmt(pr[0]["e_M_px"], 3)
                            + (f" ({pr[0]['unplaced']} unplaced)" if pr[0]["unplaced"] else "")
                        )
                body.append([peer] + cells)
        R += [
            "e_M (px, Eq. 29) against the simulator's ground truth (textured = without the "
            "12 black frames, which only the tracker can place):",
            "",
        ]
        R += md_table(["method"] + seqs, body) + [""]
    if lat:
        body = []
        for seq, r in lat.get("lba-emt", {}).items():
            body.append(
                [
                    f"lba-emt {seq}",
                    _dist(r["end_to_end_ms"]["steady"]),
                    _dist(r["solve_only_ms"]["per_step_cpp"], 2),
                ]
            )
        for traj, r in lat.get("kalman-robot", {}).items():
            body.append(
                [
                    f"kalman-robot {traj}",
                    _dist(r["end_to_end_ms"]["all"]),
                    _dist(r["solve_only_ms"]["kalman_filter"], 3),
                ]
            )
        R += ["Per-frame latency, ms (median / p95 / p99):", ""]
        R += md_table(["method", "end to end", "solve only"], body) + [""]
    if cpp and cpp.get("problems"):
        lines = []
        for p in cpp["problems"]:
            c, py = p.get("cpp"), p["python_bindings"]
            if not c:
                continue
            if p["kind"] == "ba":
                lines.append(
                    f"{p['problem']}: {c['frames']} frames, {c['pairs']} pairs, "
                    f"{c['correspondences']} correspondences, solve "
                    f"{c['solve_wall_s']['median']:.3f} s in C++ "
                    f"({py['solve_wall_s']['median']:.3f} s via Python)"
                )
            else:
                lines.append(
                    f"{p['problem']}: window step {_dist(c['step_wall_ms'], 2)} ms "
                    f"(median / p95 / p99) in C++, "
                    f"{py['step_wall_ms']['median']:.2f} ms median via Python"
                )
        if lines:
            R += (
                [
                    "Solver core replayed from saved problems by the C++ benchmark "
                    "(bench/cpp/solver_bench.cc):",
                    "",
                ]
                + [f"- {x}" for x in lines]
                + [""]
            )
    readme = "\n".join(R)
    return summary, readme, h


def _pano_check(c: dict | None) -> str:
    if not c:
        return "–"
    n = len(c["frames"])
    if c.get("mean_e_j_px") is None:
        return f"none of {n} frames registered into it"
    return f"{c['mean_e_j_px']:.3f} ({c['registered']}/{n} frames registered)"


def _acc_cell(r: dict, textured: float | None) -> str:
    cell = fmt(r["e_M_px"], 3)
    notes = []
    if textured is not None and r["unplaced"] == 0:
        notes.append(f"textured {fmt(textured, 3)}")
    if r["unplaced"]:
        notes.append(f"{r['unplaced']} unplaced")
    return cell + (f" ({', '.join(notes)})" if notes else "")


def _dist(d: dict, digits: int = 1) -> str:
    if not d or d.get("median") is None:
        return "–"
    return f"{d['median']:.{digits}f} / {d['p95']:.{digits}f} / {d['p99']:.{digits}f}"


def _dist_s(d: dict) -> str:
    if not d or d.get("median") is None:
        return "–"
    return f"{d['median']:.3f} ({d.get('min', d['median']):.3f}-{d['max']:.3f})"


def update_readme(section: str, readme: Path = REPO / "README.md") -> None:
    """Replaces the "## Performance" section (up to the next "## " heading) or appends it at
    the end; nothing else in README.md changes."""
    text = readme.read_text()
    lines = text.splitlines()
    start = next((i for i, x in enumerate(lines) if x.strip() == "## Performance"), None)
    if start is None:
        new = text.rstrip("\n") + "\n\n" + section.rstrip("\n") + "\n"
    else:
        end = next(
            (i for i in range(start + 1, len(lines)) if lines[i].startswith("## ")), len(lines)
        )
        rest = lines[end:]
        new = (
            "\n".join(
                lines[:start] + section.rstrip("\n").splitlines() + ([""] + rest if rest else [])
            )
            + "\n"
        )
    readme.write_text(new)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run (minutes), README untouched")
    ap.add_argument(
        "--results",
        type=Path,
        default=None,
        help="results folder (default bench/results; --quick: build/bench_quick/results)",
    )
    ap.add_argument(
        "--work",
        type=Path,
        default=None,
        help=f"simulated datasets and saved problems (default {DEFAULT_WORK})",
    )
    ap.add_argument("--only", nargs="*", choices=MINE + OTHERS, default=None)
    ap.add_argument("--skip", nargs="*", choices=MINE + OTHERS, default=[])
    ap.add_argument(
        "--others",
        action="store_true",
        help="also run the other helpers' benchmarks: " + ", ".join(OTHERS),
    )
    ap.add_argument(
        "--stitcher-timeout",
        type=float,
        default=None,
        help="seconds per cv2.Stitcher run (default: the budget left - 150 s, 300-600 s)",
    )
    ap.add_argument(
        "--summary-only",
        action="store_true",
        help="only rebuild summary.md (and README unless --quick) from the JSON",
    )
    ap.add_argument("--no-readme", action="store_true")
    argv = sys.argv[1:] if argv is None else list(argv)
    args = ap.parse_args(argv)
    results = args.results or (QUICK_ROOT / "results" if args.quick else RESULTS)
    work = args.work or (QUICK_ROOT / "work" if args.quick else DEFAULT_WORK)
    # Each stitcher run may use what is left of the budget after ~2.5 min for the rest of the
    # peers stage (SYN's run takes a fraction of the hand-held one), at least 5 and at most
    # 10 min; a run that does not finish is killed and reported as such.
    results.mkdir(parents=True, exist_ok=True)
    run = None
    runs = previous_runs(load(results, "summary.json"))
    if not args.summary_only:
        stages = (
            list(args.only) if args.only else list(MINE) + (list(OTHERS) if args.others else [])
        )
        stages = [s for s in stages if s not in args.skip]
        t0 = time.perf_counter()
        done = []
        for s in stages:
            left = BUDGET_S - (time.perf_counter() - t0)
            timeout = args.stitcher_timeout or min(max(left - 150.0, 300.0), 600.0)
            done.append(
                run_stage(s, stage_command(s, results, work, args.quick, timeout), work / "logs")
            )
            elapsed = time.perf_counter() - t0
            print(
                f"    elapsed {elapsed / 60:.1f} min of the {BUDGET_S // 60} min budget", flush=True
            )
        run = {
            "quick": args.quick,
            "stages": done,
            "total_s": time.perf_counter() - t0,
            "finished": _now(),
            "command": " ".join(["python bench/run_all.py", *argv]),
            "machine": machine_info(),
        }
        runs = merge_runs(runs, run)
    summary, readme, h = summary_markdown(results, runs)
    (results / "summary.md").write_text(summary)
    write_json(results / "summary.json", {"runs": runs, "headline": h})
    print(f"\nwrote {results / 'summary.md'}")
    if not args.quick and not args.no_readme:
        update_readme(readme)
        print(f"updated the '## Performance' section of {REPO / 'README.md'}")
    print("\nHeadline:")
    for line in summary.split("## Headline", 1)[-1].split("\n## ", 1)[0].strip().splitlines():
        print("  " + line)
    if run:
        print(f"\ntotal {run['total_s'] / 60:.1f} min (budget {BUDGET_S // 60} min)")
        failed = [s["stage"] for s in run["stages"] if s["exit_code"] != 0]
        if failed:
            print(f"FAILED stages: {', '.join(failed)} (logs in {work / 'logs'})")
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
