"""C++ benchmark of the solver core, without Python in the loop (issue 7, item 6).

Builds bench/cpp/solver_bench.cc (std::chrono timing, links the same fusedmosaic_core sources
as the Python module; bench/CMakeLists.txt, standalone: needs Ceres and Eigen only) into
build/bench, then replays the problems saved from the simulator by bench_table1.py (BA and
BA+EMT, all pairs and EMT-guided pairs, SYN) and bench_latency.py (the LBAVis+EMT window call
log of the SYN stream): each BA problem is built and solved `--repeats` times; each window log
is replayed `--repeats` times, timing every step. The same files are also replayed through the
Python bindings (_core), round by round alternating with the C++ program, so the two columns
differ only by the Python layer. The replays report
their largest pose difference from the recorded run (same problem, same answer).

    python bench/bench_cpp.py [--work DIR] [--repeats 5] [--out bench/results/cpp_solvers.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _common import DEFAULT_WORK, REPO, RESULTS, dist, machine_info, write_json

BUILD = REPO / "build" / "bench"
PROGRAM = "fusedmosaic_solver_bench"


def build(build_dir: Path) -> dict:
    """Configures and builds the benchmark program; returns what happened (never raises)."""
    t0 = time.perf_counter()
    log = []
    steps = [
        ["cmake", "-S", str(REPO / "bench"), "-B", str(build_dir), "-DCMAKE_BUILD_TYPE=Release"],
        ["cmake", "--build", str(build_dir), "--target", PROGRAM, "-j", str(os.cpu_count() or 2)],
    ]
    for cmd in steps:
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True)
        except FileNotFoundError as e:
            return {
                "ok": False,
                "error": f"{cmd[0]} not found: {e}",
                "seconds": time.perf_counter() - t0,
            }
        log.append(proc.stdout[-2000:] + proc.stderr[-2000:])
        if proc.returncode != 0:
            return {
                "ok": False,
                "error": f"{' '.join(cmd)} failed:\n{log[-1][-1500:]}",
                "seconds": time.perf_counter() - t0,
            }
    return {"ok": True, "program": str(build_dir / PROGRAM), "seconds": time.perf_counter() - t0}


# -- the same files through the Python bindings ----------------------------------------------


def _ids_and_hold(path, line: int, name: str, rest: list[str], lists: int) -> tuple:
    """`lists` id lists ("n id1..idn" each), then the optional "hold" (the step holds pi,
    SlidingWindow.step's hold_plane), as solver_bench.cc reads them: (list, ..., hold)."""
    out, j = [], 0
    try:
        for _ in range(lists):
            n = int(rest[j])
            if n < 0 or len(rest) < j + 1 + n:
                raise ValueError
            out.append([int(x) for x in rest[j + 1 : j + 1 + n]])
            j += 1 + n
    except (ValueError, IndexError):
        raise ValueError(f"{path}:{line}: {name}: expected {lists} id list(s) 'n id1..idn', "
                         f"got {' '.join(rest)!r}") from None
    tail = rest[j:]
    if tail not in ([], ["hold"]):
        raise ValueError(f"{path}:{line}: {name}: expected 'hold' or the end of the line, got "
                         f"{' '.join(tail)!r}")
    return (*out, tail == ["hold"])


def load_problem(path: Path) -> dict:
    """Parses a problem log (format: bench/cpp/solver_bench.cc) into header + call list.
    Raises ValueError (file:line) on a record it does not know: a replay that skipped it would
    solve another problem than the recorded run did, silently."""
    lines = Path(path).read_text().splitlines()
    head = lines[0].split()
    if head[:2] != ["fusedmosaic-problem", "1"]:
        raise ValueError(f"{path}:1: not a fusedmosaic problem log: {lines[0]!r}")
    p: dict = {"kind": head[2], "calls": [], "expect": {}}
    i = 1
    while i < len(lines):
        tok = lines[i].split()
        i += 1
        if not tok:
            continue
        name, rest = tok[0], tok[1:]
        if name == "end":
            break
        if name == "K":
            p["K"] = np.array(rest, float).reshape(3, 3)
        elif name == "costs":
            p["costs"] = rest
        elif name in ("emt_sigma", "motion_sigma"):
            p[name] = np.array(rest, float)
        elif name == "plane_std":
            p["plane_std"] = [x == "1" for x in rest]
        elif name == "window":
            p["window"] = [int(x) for x in rest]
        elif name == "add_pair":
            n = int(rest[2])
            pts = np.array(" ".join(lines[i : i + n]).split(), float).reshape(n, 4)
            i += n
            p["calls"].append(
                (name, (int(rest[0]), int(rest[1]), pts[:, :2].copy(), pts[:, 2:].copy()))
            )
        elif name == "add_frame":
            k, j = int(rest[0]), 1
            init = None
            if rest[j] == "1":
                init = np.array(rest[j + 1 : j + 7], float)
                j += 6
            j += 1
            emt = None
            if rest[j] == "1":
                emt = np.array(rest[j + 1 : j + 7], float)
                j += 6
            # optional C_p timing (motion_ratio motion_sigma_scale; older logs: 1 1)
            timing = tuple(float(x) for x in rest[j + 2 : j + 4]) or (1.0, 1.0)
            p["calls"].append((name, (k, init, emt, rest[j + 1] == "1", *timing)))
        elif name == "step":  # (keyframe ids, hold)
            p["calls"].append((name, _ids_and_hold(path, i, name, rest, 1)))
        elif name == "redo":  # (frame ids, keyframe ids, hold)
            p["calls"].append((name, _ids_and_hold(path, i, name, rest, 2)))
        elif name == "forget":
            p["calls"].append((name, (_ids_and_hold(path, i, name, rest, 1)[0],)))
        elif name == "set_plane":
            p["calls"].append((name, (np.array(rest, float),)))
        elif name == "set_emt_sigma_scale":
            p["calls"].append((name, (int(rest[0]), float(rest[1]))))
        elif name == "set_sigma_v":
            p["calls"].append((name, (float(rest[0]),)))
        elif name == "expect" and p["kind"] == "ba":
            p["expect"][int(rest[0])] = np.array(rest[1:], float)
        elif name == "expect":
            p["calls"].append((name, (int(rest[0]), np.array(rest[1:], float))))
        elif name == "set_pose":
            p["calls"].append((name, (int(rest[0]), np.array(rest[1:], float))))
        elif name == "set_constant_frame":
            p["calls"].append((name, (int(rest[0]), rest[1] == "1")))
        elif name in ("solve", "expect_plane"):
            p["calls"].append((name, tuple(rest)))
        else:
            raise ValueError(
                f"{path}:{i}: unknown record {name!r}; a replay without it would solve "
                "another problem than the recorded run"
            )
    return p


def _costs(p: dict):
    from fusedmosaic import _core

    c = p["costs"]
    o = _core.BundleAdjusterOptions(
        sigma_v_px=float(c[0]),
        loss=c[1],
        loss_scale_px=float(c[2]),
        linear_solver=c[3],
        residual_blocks=c[4],
        max_iterations=int(c[5]),
        function_tolerance=float(c[6]),
        gradient_tolerance=float(c[7]),
        parameter_tolerance=float(c[8]),
        num_threads=int(c[9]),
        use_emt=c[10] == "1",
        use_motion_prior=c[11] == "1",
    )
    o.emt_sigma = p["emt_sigma"]
    o.motion_sigma = p["motion_sigma"]
    o.plane_std, o.plane_std_paired_only = p.get("plane_std", (False, False))
    return o


def python_replay(p: dict, repeats: int) -> dict:
    from fusedmosaic import _core

    costs = _costs(p)
    if p["kind"] == "ba":
        solve_wall, ceres, diff = [], [], 0.0
        for _ in range(repeats):
            ba = _core.BundleAdjuster(p["K"], costs)
            for name, a in p["calls"]:
                if name == "add_frame":
                    ba.add_frame(a[0], a[1], a[2], a[4], a[5])
                elif name == "add_pair":
                    ba.add_pair(*a)
                elif name == "set_plane":
                    ba.set_plane(a[0])
                elif name == "set_pose":
                    ba.set_pose(*a)
                elif name == "set_constant_frame":
                    ba.set_constant_frame(*a)
            t0 = time.perf_counter()
            s = ba.solve()
            solve_wall.append(time.perf_counter() - t0)
            ceres.append(s.solve_time_s)
            for k, x in p["expect"].items():
                diff = max(diff, float(np.abs(ba.pose(k) - x).max()))
        return {
            "solve_wall_s": solve_wall,
            "solve_ceres_s": ceres,
            "max_abs_diff_vs_recorded": diff,
        }
    w_size, num_new, fold = p["window"]
    wo = _core.SlidingWindowOptions(window_size=w_size, num_new=num_new, costs=costs)
    wo.fold_fixed_cameras = bool(fold)
    steps, per_frame, diff = [], [], 0.0
    for _ in range(repeats):
        w = _core.SlidingWindow(p["K"], wo)
        for name, a in p["calls"]:
            if name == "add_frame":
                w.add_frame(a[0], a[1], a[2], a[3], a[4], a[5])
            elif name == "add_pair":
                w.add_pair(*a)
            elif name == "set_plane":
                w.set_plane(a[0])
            elif name == "set_emt_sigma_scale":
                w.set_emt_sigma_scale(*a)
            elif name == "set_sigma_v":
                w.set_sigma_v(*a)
            elif name == "forget":
                w.forget(a[0])
            elif name == "expect":
                diff = max(diff, float(np.abs(w.pose(a[0]) - a[1]).max()))
            elif name in ("step", "redo"):
                t0 = time.perf_counter()
                s = w.step(*a) if name == "step" else w.redo(*a)
                dt = time.perf_counter() - t0
                if name == "redo":
                    steps[-1] += dt
                    per_frame[-1] = steps[-1] / max(len(s.frame_ids), 1)
                else:
                    steps.append(dt)
                    per_frame.append(dt / max(len(s.frame_ids), 1))
    return {
        "step_wall_ms": [1e3 * x for x in steps],
        "per_new_frame_ms": [1e3 * x for x in per_frame],
        "max_abs_diff_vs_recorded": diff,
    }


def pool_cpp(runs: list[dict]) -> dict | None:
    """One record per problem from the C++ program's single-repeat runs: the problem facts of
    the first run, the statistics over all runs' samples."""
    if not runs:
        return None
    out = {k: v for k, v in runs[0].items() if not isinstance(v, dict) and k != "repeats"}
    out["repeats"] = len(runs)
    for key in runs[0]["samples"]:
        out[key] = dist([x for r in runs for x in r["samples"][key]])
    out["max_abs_diff_vs_recorded"] = max(r["max_abs_diff_vs_recorded"] for r in runs)
    return out


def pool_py(runs: list[dict]) -> dict:
    out = {
        k: dist([x for r in runs for x in r[k]]) for k in runs[0] if k != "max_abs_diff_vs_recorded"
    }
    out["repeats"] = len(runs)
    out["max_abs_diff_vs_recorded"] = max(r["max_abs_diff_vs_recorded"] for r in runs)
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--work",
        type=Path,
        default=DEFAULT_WORK,
        help="where bench_table1 / bench_latency saved the problems",
    )
    ap.add_argument("--build-dir", type=Path, default=BUILD)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=RESULTS / "cpp_solvers.json")
    args = ap.parse_args(argv)
    t_start = time.perf_counter()
    files = sorted((args.work / "problems").glob("*.txt"))
    res: dict = {
        "benchmark": "C++ solver core replay (bench/bench_cpp.py, bench/cpp/)",
        "machine": machine_info(),
        "repeats": args.repeats,
        "problems": [],
    }
    if not files:
        res["error"] = (
            f"no saved problems in {args.work / 'problems'}: run bench_table1.py and "
            "bench_latency.py with the same --work first"
        )
        write_json(args.out, res)
        print(res["error"])
        return res
    b = build(args.build_dir)
    res["build"] = b
    if not b["ok"]:
        print(f"C++ benchmark not built: {b['error']}")
    problems = {f.name: load_problem(f) for f in files}
    # Rounds alternate the C++ program (one repeat of every file) and the Python replay of the
    # same files, so a change in the load of the shared cores hits both columns alike.
    cpp_runs: dict[str, list[dict]] = {f.name: [] for f in files}
    py_runs: dict[str, list[dict]] = {f.name: [] for f in files}
    for _ in range(args.repeats):
        if b["ok"] and "cpp_error" not in res:
            raw = args.build_dir / "solver_bench_raw.json"
            proc = subprocess.run(
                [b["program"], "--repeats", "1", "--out", str(raw), *map(str, files)],
                capture_output=True,
                text=True,
            )
            if proc.returncode == 0:
                for r in json.loads(raw.read_text())["results"]:
                    cpp_runs[Path(r["file"]).name].append(r)
            else:
                res["cpp_error"] = proc.stderr[-1500:]
        for f in files:
            py_runs[f.name].append(python_replay(problems[f.name], 1))
    for f in files:
        p = problems[f.name]
        entry = {
            "problem": f.stem,
            "kind": p["kind"],
            "file": str(f),
            "cpp": pool_cpp(cpp_runs[f.name]),
            "python_bindings": pool_py(py_runs[f.name]),
        }
        res["problems"].append(entry)
        c, py = entry["cpp"], entry["python_bindings"]
        if p["kind"] == "ba" and c:
            print(
                f"{f.stem:<22} C++ solve median {c['solve_wall_s']['median']:.3f} s "
                f"(Ceres {c['solve_ceres_s']['median']:.3f}); via Python "
                f"{py['solve_wall_s']['median']:.3f} s; {c['pairs']} pairs, "
                f"{c['correspondences']} correspondences",
                flush=True,
            )
        elif c:
            print(
                f"{f.stem:<22} C++ step median {c['step_wall_ms']['median']:.2f} p95 "
                f"{c['step_wall_ms']['p95']:.2f} p99 {c['step_wall_ms']['p99']:.2f} ms; via "
                f"Python median {py['step_wall_ms']['median']:.2f} ms",
                flush=True,
            )
    res["runtime_s"] = time.perf_counter() - t_start
    write_json(args.out, res)
    print(f"wrote {args.out} ({res['runtime_s']:.0f} s)")
    return res


if __name__ == "__main__":
    main(sys.argv[1:])
