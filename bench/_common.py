"""Shared pieces of the issue-7 benchmarks (bench_table1, bench_latency, bench_peers, bench_cpp,
run_all): the paper's figures, the simulated sequences, machine facts, statistics, JSON output and
the problem logs replayed by the C++ solver benchmark (bench/cpp/solver_bench.cc); and for every
bench script, the shared command-line options (bench_args) and a run's start and end (BenchRun).

Scripts in bench/ import this as `_common` (python puts the script's folder on sys.path)."""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from fusedmosaic.evaluation.benchmark import (  # noqa: F401 (re-exported)
    load_average,
    machine_info,
)
from fusedmosaic.simulation.fetoscopy import SYN_FRAMES_PER_LAP

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
RESULTS = BENCH / "results"
DEFAULT_WORK = REPO / "build" / "bench_work"  # simulated datasets and saved problems (not in git)

# -- the papers' figures ---------------------------------------------------------------------

# Seed 000, Table 1 (MacBook Pro, Core i7 2.5 GHz, 4 cores, 16 GB; Matlab + VLFeat SIFT):
# (#images, #pairs, avg. correspondences, matching s, optimisation s). PHB is the hand-held
# phantom sequence; our phantom-like stand-in is the simulator's "handheld" motion.
PAPER_TABLE1 = {
    "syn": {
        "pairwise": (152, 151, 86, 49.811, 3.145),
        "lba-emt": (152, 350, 67, 178.766, 38.567),
        "ba": (152, 1094, 76, 4286.259, 521.819),
        "ba-emt": (152, 1094, 76, 4350.518, 321.928),
    },
    "handheld": {
        "pairwise": (155, 154, 222, 88.192, 3.333),
        "lba-emt": (155, 449, 184, 519.447, 50.638),
        "ba": (155, 2030, 105, 15064.135, 1488.251),
        "ba-emt": (155, 2030, 105, 15394.628, 1103.748),
    },
}
PAPER_MACHINE = "MacBook Pro, Intel Core i7 2.5 GHz, 4 cores, 16 GB; Matlab + VLFeat SIFT"
PAPER_NAMES = {
    "pairwise": "PairVis",
    "lba-emt": "LBAVis+EMT",
    "ba": "BAVis",
    "ba-emt": "BAVis+EMT",
    "ba-emt-guided": "BAVis+EMT, EMT-guided pairs",
    "emt": "EMT + plane",
}

# Seed 004, Tables I (circle) and II (spiral): mean, max, std, median in µm.
PAPER_PCLE = {
    "circle": {
        "#1": (274.3, 543.1, 190.2, 249.2),
        "#2": (116.5, 251.6, 73.3, 108.4),
        "#3": (142.3, 320.8, 86.8, 108.6),
        "#4": (489.1, 752.8, 201.8, 551.8),
        "#5": (226.8, 372.1, 86.4, 224.0),
    },
    "spiral": {
        "#1": (686.7, 800.2, 1080.8, 375.3),
        "#2": (139.4, 220.9, 51.3, 141.8),
        "#3": (135.7, 263.1, 70.7, 133.4),
        "#4": (291.0, 517.2, 134.9, 312.9),
        "#5": (100.8, 260.8, 63.9, 105.9),
    },
}
PCLE_CASES = {
    "#1": "X_m (Test #1)",
    "#2": "X_r (Test #2)",
    "#3": "X_f with X_r (Test #3)",
    "#4": "hat X_r (Test #4)",
    "#5": "X_f with hat X_r (Test #5)",
}

# -- the simulated sequences -----------------------------------------------------------------

FRAMES_PER_LAP = SYN_FRAMES_PER_LAP  # keep the SYN motion of the default 150 frames / 4 laps


@dataclass(frozen=True)
class Sequence:
    name: str  # "syn", "handheld", "syn-black", "handheld-black"
    base: str  # "syn" | "handheld": which Table 1 block it belongs to
    black: bool
    frames: int

    def options(self):
        from fusedmosaic.simulation import PAPER_BLACK_FRAMES, FetoscopyOptions

        o = FetoscopyOptions(motion=self.base, n_frames=self.frames)
        if self.base == "syn":
            o = replace(o, laps=self.frames / FRAMES_PER_LAP)
        if self.black:
            o = replace(o, black_frames=[k for k in PAPER_BLACK_FRAMES if k < self.frames])
        return o


def sequences(quick: bool) -> list[Sequence]:
    """SYN circular 152 frames and the hand-held phantom-like 155 frames (paper 000 Sec. 4.2.1),
    each also with the paper's black frames (Sec. 4.2.3). --quick: 60 frames each."""
    n = {"syn": 60, "handheld": 60} if quick else {"syn": 152, "handheld": 155}
    return [
        Sequence(base + ("-black" if black else ""), base, black, n[base])
        for black in (False, True)
        for base in ("syn", "handheld")
    ]


def ensure_dataset(work: Path, seq: Sequence) -> Path:
    """Simulates the sequence into work/<name>-<frames> unless an identical one is there."""
    from fusedmosaic.simulation import simulate_fetoscopy

    root = Path(work) / f"{seq.name}-{seq.frames}"
    options = asdict(seq.options())
    stamp = root / "bench_options.json"
    if stamp.is_file() and json.loads(stamp.read_text()) == options:
        return root
    simulate_fetoscopy(root, seq.options(), overwrite=True)
    stamp.write_text(json.dumps(options))
    return root


# -- machine, statistics, output -------------------------------------------------------------


def dist(values, scale: float = 1.0) -> dict:
    """median / p95 / p99 / mean / min / max / n of a sample (numpy's linear percentiles)."""
    x = np.asarray(values, float) * scale
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return {
            "median": None,
            "p95": None,
            "p99": None,
            "mean": None,
            "min": None,
            "max": None,
            "n": 0,
        }
    return {
        "median": float(np.median(x)),
        "p95": float(np.percentile(x, 95)),
        "p99": float(np.percentile(x, 99)),
        "mean": float(x.mean()),
        "min": float(x.min()),
        "max": float(x.max()),
        "n": int(len(x)),
    }


def jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_json(path: Path, obj) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(jsonable(obj), indent=1) + "\n")
    tmp.replace(path)


def work_folder(work: Path | None):
    """(folder, temporary directory or None): the --work folder if given, else a temporary one
    that finish_run removes."""
    if work is not None:
        return Path(work), None
    tmp = tempfile.TemporaryDirectory(prefix="fm_bench_")
    return Path(tmp.name), tmp


_OPTIONS = {  # the shared options of bench_args: name -> add_argument keywords from the value
    "quick": lambda text: {"action": "store_true", "help": text},
    "seeds": lambda default: {"type": int, "default": default},
    "frames": lambda default: {"type": int, "default": default},
    "out": lambda default: {"type": Path, "default": default},
    "work": lambda text: {"type": Path, "default": None, "help": None if text is True else text},
}


def add_options(ap: argparse.ArgumentParser, **options) -> argparse.ArgumentParser:
    """Adds the shared options named, in the order given: quick=HELP (--quick, a flag), seeds=N
    and frames=N (int, default N), out=PATH (--out, a Path, default PATH), work=True or HELP
    (--work, a Path, default None: a temporary folder, see BenchRun)."""
    for name, value in options.items():
        ap.add_argument(f"--{name}", **_OPTIONS[name](value))
    return ap


def bench_args(doc: str, **options) -> argparse.ArgumentParser:
    """A parser described by doc's first paragraph with the shared options named (add_options);
    a script adds its own to it (and more shared ones after those with add_options)."""
    return add_options(argparse.ArgumentParser(description=doc.split("\n\n")[0]), **options)


class BenchRun:
    """A bench script's run from its start: the clock (t_start), the load average (load_start)
    and, unless folder=False, the work folder (work): `work` if given, else a temporary one that
    cleanup(), write_results() and finish() remove."""

    def __init__(self, work: Path | None = None, folder: bool = True):
        self.t_start = time.perf_counter()
        self.load_start = load_average()
        self.work, self._tmp = work_folder(work) if folder else (None, None)

    def cleanup(self) -> None:
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def write_results(self, out: Path, markdown, **fields) -> dict:
        """write_results with this run's start, then cleanup()."""
        res = write_results(out, markdown, self.t_start, self.load_start, **fields)
        self.cleanup()
        return res

    def finish(self, result: dict, out: Path, markdown=None) -> dict:
        """finish_run with this run's start, then cleanup()."""
        finish_run(result, out, self.t_start, markdown=markdown)
        self.cleanup()
        return result


def write_outputs(out: Path, res: dict, markdown=None, note: str = "") -> None:
    """res as JSON to `out` and, through markdown(res) if given, to its .md twin; says so."""
    write_json(out, res)
    if markdown is not None:
        Path(out).with_suffix(".md").write_text(markdown(res))
    print(f"wrote {out}{note}")


def finish_run(result: dict, out: Path, t_start: float, tmp=None, markdown=None) -> dict:
    """Common end of a bench script: runtime, end load, JSON (and markdown(result) beside it)
    out, temp work dir removed."""
    result["runtime_s"] = time.perf_counter() - t_start
    result["machine"]["load_average_end"] = load_average()
    write_outputs(out, result, markdown, f" ({result['runtime_s']:.0f} s)")
    if tmp is not None:
        tmp.cleanup()
    return result


def write_results(out: Path, markdown, t_start: float, load_start: list[float],
                  **fields) -> dict:
    """The end of a bench script whose markdown cites run_note: `fields` with the machine, the
    load averages at the start (load_start) and now, and the runtime since t_start, written to
    `out` (JSON) and, through markdown(result), to its .md twin. Returns the result."""
    res = {"machine": machine_info(), **fields, "load_average_start": load_start,
           "load_average_end": load_average(), "runtime_s": time.perf_counter() - t_start}
    write_outputs(out, res, markdown)
    return res


def run_note(res: dict, script: str, what: str = "") -> str:
    """The markdown line saying how a bench result was produced: the command, `what`, one run,
    its runtime and the load average at its start and end (res from a script that records
    load_average_start / load_average_end)."""
    return (f"`python bench/{script}`{what}, one run, {res['runtime_s']:.0f} s; load average "
            f"{res['load_average_start']} -> {res['load_average_end']} (2 cores).")


def fmt(x, digits: int = 2) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    if isinstance(x, int | np.integer):
        return str(int(x))
    return f"{x:.{digits}f}"


def ratio(a, b) -> float | None:
    if a is None or b is None or not b or not math.isfinite(a) or not math.isfinite(b):
        return None
    return float(a) / float(b)


def md_table(header: list[str], rows: list[list]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return out


# -- problem logs for the C++ replay ---------------------------------------------------------


def _pose(x) -> str:
    return " ".join(f"{v:.17g}" for v in np.asarray(x, float).ravel())


class ProblemLog:
    """The call log of one BundleAdjuster or SlidingWindow (format: solver_bench.cc). Records
    are kept in memory (points as array copies) and written by close(), so logging adds next to
    nothing to the timings of the run it records."""

    def __init__(self, path: Path, kind: str, K, costs, window=None):
        self.path = Path(path)
        self.records: list = []  # str lines, or (header, (N, 4) points) for add_pair
        self.closed = False
        c = costs
        self.line(f"fusedmosaic-problem 1 {kind}")
        self.line("K " + _pose(K))
        self.line(
            f"costs {c.sigma_v_px!r} {c.loss} {c.loss_scale_px!r} {c.linear_solver} "
            f"{c.residual_blocks} {c.max_iterations} {c.function_tolerance!r} "
            f"{c.gradient_tolerance!r} {c.parameter_tolerance!r} {c.num_threads} "
            f"{int(c.use_emt)} {int(c.use_motion_prior)}"
        )
        self.line("emt_sigma " + _pose(c.emt_sigma))
        self.line("motion_sigma " + _pose(c.motion_sigma))
        self.line(f"plane_std {int(c.plane_std)} {int(c.plane_std_paired_only)}")
        if window is not None:
            self.line(
                f"window {window.window_size} {window.num_new} {int(window.fold_fixed_cameras)}"
            )

    def line(self, text: str) -> None:
        self.records.append(text)

    def add_frame(self, k, initial, emt, fixed=False, motion_ratio=1.0,
                  motion_sigma_scale=1.0) -> None:
        a = "0" if initial is None else "1 " + _pose(initial)
        b = "0" if emt is None else "1 " + _pose(emt)
        self.line(f"add_frame {int(k)} {a} {b} {int(bool(fixed))} {motion_ratio!r} "
                  f"{motion_sigma_scale!r}")

    def add_pair(self, l, m, pl, pm) -> None:
        pts = np.hstack(
            [np.asarray(pl, float).reshape(-1, 2), np.asarray(pm, float).reshape(-1, 2)]
        )
        self.records.append((f"add_pair {int(l)} {int(m)} {len(pts)}", pts))

    def ids(self, ids) -> str:
        ids = [int(i) for i in ids]
        return " ".join([str(len(ids)), *map(str, ids)])

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "w") as f:
            for r in self.records:
                if isinstance(r, str):
                    f.write(r + "\n")
                else:
                    f.write(r[0] + "\n")
                    np.savetxt(f, r[1], fmt="%.17g")
            f.write("end\n")
        self.records = []


class BundleRecorder:
    """Stands in for a _core.BundleAdjuster: forwards every call, logs the problem for `path`,
    times solve() from Python and logs the solution as the replay's expected values."""

    def __init__(self, ba, K, path: Path):
        self._ba = ba
        self.log = ProblemLog(path, "ba", K, ba.options)
        self.python_solve_s = None
        self.summary = None
        self.solved_at = None  # perf_counter at the first solve()

    def __getattr__(self, name):
        return getattr(self._ba, name)

    def add_frame(self, k, pose, emt=None, motion_ratio=1.0, motion_sigma_scale=1.0):
        self.log.add_frame(k, pose, emt, False, motion_ratio, motion_sigma_scale)
        return self._ba.add_frame(k, pose, emt, motion_ratio, motion_sigma_scale)

    def add_pair(self, l, m, pl, pm):
        self.log.add_pair(l, m, pl, pm)
        return self._ba.add_pair(l, m, pl, pm)

    def set_plane(self, plane):
        self.log.line("set_plane " + _pose(plane))
        return self._ba.set_plane(plane)

    def set_pose(self, k, pose):
        self.log.line(f"set_pose {int(k)} " + _pose(pose))
        return self._ba.set_pose(k, pose)

    def set_constant_frame(self, k, constant=True):
        self.log.line(f"set_constant_frame {int(k)} {int(constant)}")
        return self._ba.set_constant_frame(k, constant)

    def solve(self):
        self.log.line("solve")
        t0 = time.perf_counter()
        if self.solved_at is None:
            self.solved_at = t0
        summary = self._ba.solve()
        self.python_solve_s = time.perf_counter() - t0
        self.summary = summary
        ids, poses = self._ba.poses()
        for k, x in zip(ids, poses, strict=True):
            self.log.line(f"expect {int(k)} " + _pose(x))
        self.log.line("expect_plane " + _pose(self._ba.plane()))
        return summary  # the log is written when record_bundle_problems() exits


@contextmanager
def record_bundle_problems(directory: Path, stem: str):
    """While active, every BundleAdjuster that estimation.bundle builds is recorded; those that
    solved are written to directory/<stem>-<i>.txt in the order they solved (an adjuster built
    only to check the options is not written), after the files of an earlier run of the same
    stem are removed. Hooks bundle._adjuster, the factory run_bundle uses, and
    bundle._rebuilt_adjuster, which solves an adjustment again (a dogleg continuation, sigma_v
    "auto"'s second solve: the one whose result ba-emt returns); if those private names change,
    nothing is recorded (the benchmark says so) and runs are unaffected."""
    from fusedmosaic.estimation import bundle

    directory = Path(directory)
    recorders: list[BundleRecorder] = []
    original = getattr(bundle, "_adjuster", None)
    rebuilt = getattr(bundle, "_rebuilt_adjuster", None)
    if original is None or rebuilt is None:
        yield recorders
        return
    for old in directory.glob(f"{stem}-*.txt"):
        if old.stem[len(stem) + 1 :].isdigit():
            old.unlink()

    def make(K, options, use_emt, *args, **kwargs):
        rec = BundleRecorder(original(K, options, use_emt, *args, **kwargs), K, directory / "_")
        recorders.append(rec)
        return rec

    def remake(K, costs):
        rec = BundleRecorder(rebuilt(K, costs), K, directory / "_")
        recorders.append(rec)
        return rec

    bundle._adjuster, bundle._rebuilt_adjuster = make, remake
    try:
        yield recorders
    finally:
        bundle._adjuster, bundle._rebuilt_adjuster = original, rebuilt
        solved = sorted((r for r in recorders if r.solved_at is not None),
                        key=lambda r: r.solved_at)
        for i, r in enumerate(solved):
            r.log.path = directory / f"{stem}-{i}.txt"
            r.log.close()


class WindowRecorder:
    """Stands in for SequentialMosaicker.window (a _core.SlidingWindow): forwards every call,
    times step()/redo() from Python (a gating redo is added to its step, one latency per step)
    and, when `path` is given, logs the calls with the poses Python read back as expected
    values.

    drop_emt_measurement and set_motion_timing have no record in the log format that the C++
    replay reads (solver_bench.cc stops at an unknown record, and with it every replay of the
    bench_cpp run). A run that makes either call therefore writes no log (close() removes an
    older one at `path`, so no stale log is replayed in its place) and says why in
    `not_logged`: a replay without those calls would solve another problem."""

    def __init__(self, window, K, costs, window_options, path: Path | None = None):
        self._window = window
        self.log = ProblemLog(path, "window", K, costs, window_options) if path else None
        self.step_wall_s: list[float] = []
        self.step_cpp_s: list[float] = []
        self.step_frames: list[int] = []
        self.summaries: list = []
        self.unloggable: dict[str, int] = {}  # calls the log format cannot hold: name -> count
        self.not_logged: str | None = None  # why close() wrote no log

    def __getattr__(self, name):
        return getattr(self._window, name)

    def add_frame(self, k, initial=None, emt=None, fixed=False, motion_ratio=1.0,
                  motion_sigma_scale=1.0):
        if self.log:
            self.log.add_frame(k, initial, emt, fixed, motion_ratio, motion_sigma_scale)
        return self._window.add_frame(k, initial, emt, fixed, motion_ratio, motion_sigma_scale)

    def add_pair(self, l, m, pl, pm):
        if self.log:
            self.log.add_pair(l, m, pl, pm)
        return self._window.add_pair(l, m, pl, pm)

    def set_plane(self, plane):
        if self.log:
            self.log.line("set_plane " + _pose(plane))
        return self._window.set_plane(plane)

    def set_sigma_v(self, sigma_v_px):
        if self.log:
            self.log.line(f"set_sigma_v {float(sigma_v_px)!r}")
        return self._window.set_sigma_v(sigma_v_px)

    def set_emt_sigma_scale(self, k, scale):
        if self.log:
            self.log.line(f"set_emt_sigma_scale {int(k)} {float(scale)!r}")
        return self._window.set_emt_sigma_scale(k, scale)

    def drop_emt_measurement(self, k):
        self.unloggable["drop_emt_measurement"] = self.unloggable.get("drop_emt_measurement", 0) + 1
        return self._window.drop_emt_measurement(k)

    def set_motion_timing(self, k, motion_ratio, motion_sigma_scale):
        self.unloggable["set_motion_timing"] = self.unloggable.get("set_motion_timing", 0) + 1
        return self._window.set_motion_timing(k, motion_ratio, motion_sigma_scale)

    def forget(self, ids):
        if self.log:
            self.log.line("forget " + self.log.ids(ids))
        return self._window.forget(ids)

    def step(self, keyframe_ids=(), hold_plane=False):
        if self.log:
            self.log.line("step " + self.log.ids(keyframe_ids) + (" hold" if hold_plane else ""))
        t0 = time.perf_counter()
        s = self._window.step(list(keyframe_ids), hold_plane)
        self.step_wall_s.append(time.perf_counter() - t0)
        self.step_cpp_s.append(s.step_time_s)
        self.step_frames.append(len(s.frame_ids))
        self.summaries.append(s)
        return s

    def redo(self, frame_ids, keyframe_ids=(), hold_plane=False):
        if self.log:
            self.log.line("redo " + self.log.ids(frame_ids) + " " + self.log.ids(keyframe_ids)
                          + (" hold" if hold_plane else ""))
        t0 = time.perf_counter()
        s = self._window.redo(list(frame_ids), list(keyframe_ids), hold_plane)
        self.step_wall_s[-1] += time.perf_counter() - t0
        self.step_cpp_s[-1] += s.step_time_s
        return s

    def pose(self, k):
        x = self._window.pose(k)
        if self.log:
            self.log.line(f"expect {int(k)} " + _pose(x))
        return x

    def close(self) -> None:
        if not self.log or self.log.closed:
            return
        if not self.unloggable:
            self.log.close()
            return
        self.log.closed, self.log.records = True, []
        self.log.path.unlink(missing_ok=True)
        calls = ", ".join(f"{n} x {name}" for name, n in self.unloggable.items())
        self.not_logged = (f"{self.log.path} not written: the run called {calls}, which the "
                           "replays' log format has no record for")
        print(self.not_logged, flush=True)
