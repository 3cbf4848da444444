"""The machine check behind ``fusedmosaic bench``: design.md's live budgets, measured on this
machine on simulated data (nothing to download or prepare).

- Sequential (seed 000, LBAVis+EMT): a SYN circle (~37 frames per lap, as the paper's 152-frame
  sequence) at 400x400 px streamed into :class:`~fusedmosaic.SequentialMosaicker` with tracker
  poses interpolated from the simulated 40 Hz tracker through the hand-eye transform, as a live
  loop calls it. Budgets: window step median <= 5 ms and p95 <= 15 ms (C++ assembly + solve),
  >= 25 frames/s end to end (features, matching, window step, keyframe selection) after the
  start-up adjustment.
- pCLE (seed 004, kalman-robot): a simulated circle at 512x448 px with contact loss, stick-slip
  and a noisy robot streamed into :class:`~fusedmosaic.RobotPriorMosaicker`. Budget: >= 100
  frames/s (NCC forward and backward, SSIM, confidences, filter).
- Offline (optional): BA+EMT over 150 SYN frames with EMT-guided pairs (~1000 pairs, the
  budget's size), optimisation <= 1 s.

Frames are rendered before each call and not timed; frames/s is frames / summed call time over
the steady part. Accuracy against the simulator's truth is reported beside the speed, so that a
fast but wrong run does not pass unnoticed. The repository's bench/ scripts measure more (long
sequences, memory growth, solver comparison) and write the figures quoted in the issues.
"""

from __future__ import annotations

import math
import os
import platform
import resource
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from fusedmosaic.methods import ms_stats

# design.md "Performance budgets"
BUDGETS = {
    "window_step_median_ms": ("<=", 5.0),
    "window_step_p95_ms": ("<=", 15.0),
    "sequential_frames_per_s": (">=", 25.0),
    "pcle_frames_per_s": (">=", 100.0),
    "ba_emt_optimisation_s": ("<=", 1.0),
}
SYN_SIZE = (400, 400)  # the sequential budget's frame size
SYN_FRAMES_PER_LAP = 37  # paper 000 Sec. 4.2: 152 frames, 4 laps
OFFLINE_FRAMES = 150  # design.md: BA+EMT over ~150 frames
STEADY_AFTER_STARTUP = 10  # frames after the start-up adjustment excluded from the steady part
MIN_PCLE_FRAMES = 10


def _bench_pcle_options(frames: int, seed: int = 0):
    """The pCLE simulation measure_pcle streams: the simulator's circle, lapped as often as
    the frames need (one lap is 79 frames: past its end the probe went straight on, where the
    stick-slip releases jump beyond NCC's search and the printed accuracy was that of the
    run-out, 209 µm at 200 frames against 38 on the circle)."""
    from fusedmosaic.simulation.pcle import PcleOptions

    o = PcleOptions(n_frames=frames, seed=seed)
    lap = 2 * math.pi * o.radius_um / o.speed_um_per_frame  # frames per lap
    return replace(o, laps=float(max(1, math.ceil((frames - 1) / lap))))


def max_pcle_frames() -> int:
    """The most pCLE frames the bench's simulation takes (the simulator's bounds)."""
    from fusedmosaic.simulation.pcle import max_n_frames

    return max_n_frames(_bench_pcle_options, least=MIN_PCLE_FRAMES)


@dataclass
class BenchOptions:
    """What ``fusedmosaic bench`` measures. frames: SYN frames streamed (the steady part starts
    ``STEADY_AFTER_STARTUP`` frames after the start-up adjustment's 40, so at least 60);
    detector: "orb" (the live choice) or "sift"; pcle_frames: pCLE frames (MIN_PCLE_FRAMES ..
    max_pcle_frames()); offline:
    also time BA+EMT over 150 frames (~10 s more: features and matching of the 150
    frames, then the optimisation); seed: the simulations' seed."""

    frames: int = 300
    detector: str = "orb"
    pcle_frames: int = 200
    offline: bool = False
    seed: int = 0

    def check(self) -> None:
        """Raise ValueError naming the first bad field (the CLI names it as its flag), before
        anything is measured: the simulations' own bounds included."""
        from fusedmosaic.estimation.sequential import SequentialOptions
        from fusedmosaic.simulation._options import MAX_FRAMES

        least = SequentialOptions().bootstrap_frames + 2 * STEADY_AFTER_STARTUP
        if not isinstance(self.frames, int) or self.frames < least:
            raise ValueError(f"frames: must be >= {least} (the start-up adjustment takes the "
                             f"first {least - 2 * STEADY_AFTER_STARTUP}), got {self.frames}")
        if self.frames > MAX_FRAMES:
            raise ValueError(f"frames: at most {MAX_FRAMES} (the simulator's bound), got "
                             f"{self.frames}")
        if self.detector not in ("orb", "sift"):
            raise ValueError(f"detector: must be 'orb' or 'sift', got {self.detector!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed: must be an integer >= 0, got {self.seed}")
        if not isinstance(self.pcle_frames, int) or self.pcle_frames < MIN_PCLE_FRAMES:
            raise ValueError(f"pcle_frames: must be >= {MIN_PCLE_FRAMES}, got "
                             f"{self.pcle_frames}")
        try:
            _bench_pcle_options(self.pcle_frames, self.seed).validate()
        except ValueError:
            raise ValueError(
                f"pcle_frames: at most {max_pcle_frames()} (the simulator's bounds), got "
                f"{self.pcle_frames}"
            ) from None


def machine_info() -> dict:
    """CPU, cores, memory, platform and library versions, and the load averages (the 2 cores
    may be shared: a loaded machine measures slower)."""
    import cv2
    import scipy

    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    ram_gb = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                ram_gb = round(int(line.split()[1]) / 1024**2, 1)
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "ram_gb": ram_gb,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "opencv": cv2.__version__,
        "load_average": load_average(),
    }


def load_average() -> list[float] | None:
    """The 1/5/15-minute load averages, rounded (None where the system has none)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def syn_stream(n_frames: int, size: tuple[int, int] = SYN_SIZE, seed: int = 0):
    """A SYN circle of n_frames (laps = n_frames / 37) and what a live loop would feed:
    (scene, camera, tracker camera poses at the frame times (N, 6), valid (N,))."""
    from fusedmosaic.io import Camera, TrackingSamples, interpolate_camera_poses
    from fusedmosaic.simulation.fetoscopy import FetoscopyOptions, generate_fetoscopy

    scene = generate_fetoscopy(FetoscopyOptions(
        n_frames=n_frames, laps=n_frames / SYN_FRAMES_PER_LAP, width=size[0], height=size[1],
        seed=seed))
    camera = Camera(*scene.size, camera_matrix=scene.camera_matrix,
                    fov_mask_radius=scene.fov_mask_radius)
    samples = TrackingSamples(scene.tracker_timestamps, scene.tracker_translations,
                              scene.tracker_quaternions, scene.tracker_valid)
    poses, valid = interpolate_camera_poses(samples, scene.timestamps, scene.hand_eye)
    return scene, camera, poses, valid


def _ms(seconds) -> dict:
    """report.json's per-frame time statistics (ms) and how many values they cover."""
    seconds = np.asarray(seconds, float)
    return {**ms_stats(seconds * 1e3), "n": int(seconds.size)}


def measure_sequential(frames: int, detector: str = "orb", seed: int = 0) -> dict:
    """Streams a SYN circle through SequentialMosaicker; latency, window steps, accuracy."""
    from fusedmosaic.estimation.sequential import SequentialMosaicker, SequentialOptions
    from fusedmosaic.evaluation.metrics import frame_errors
    from fusedmosaic.registration.features import FeatureOptions

    t0 = time.perf_counter()
    scene, camera, poses, valid = syn_stream(frames, seed=seed)
    setup_s = time.perf_counter() - t0
    options = SequentialOptions(features=FeatureOptions(detector=detector), seed=seed,
                                history_steps=frames)
    mosaicker = SequentialMosaicker(camera, options)
    latency = np.zeros(frames)
    G = np.full((frames, 3, 3), np.nan)

    steps: list[float] = []  # each window step's solve time, with its redo if any

    def collect(results) -> None:
        if mosaicker.num_steps > len(steps):  # (step_summaries keep the last solve only)
            steps.append(mosaicker.last_step_solve_s)
        for r in results:
            G[r.frame_id] = r.homography

    for k in range(frames):
        image = scene.render(k)
        t = time.perf_counter()
        mosaicker.add_frame(image, float(scene.timestamps[k]), poses[k] if valid[k] else None)
        latency[k] = time.perf_counter() - t
        collect(mosaicker.finalized())
    t = time.perf_counter()
    collect(mosaicker.flush())
    latency[-1] += time.perf_counter() - t
    steady = latency[options.bootstrap_frames + STEADY_AFTER_STARTUP:]
    errors = frame_errors(G, scene.homographies, *scene.size)
    return {
        "frames": frames, "size": list(scene.size), "detector": detector,
        "steady_from_frame": options.bootstrap_frames + STEADY_AFTER_STARTUP,
        "frames_per_s_steady": steady.size / float(steady.sum()),
        "frames_per_s_all": frames / float(latency.sum()),
        "latency_ms_steady": _ms(steady),
        "startup_s": float(latency[:options.bootstrap_frames].sum()),
        "window_step_ms": _ms(steps),
        "e_M_px": float(np.nanmean(errors)),
        "unplaced": int(np.sum(~np.isfinite(errors))),
        "simulation_s": setup_s,
    }


def measure_pcle(frames: int, seed: int = 0) -> dict:
    """Streams a simulated pCLE circle (512x448, contact loss, stick-slip, noisy robot) through
    RobotPriorMosaicker (kalman-robot); per-frame time and position error against the truth."""
    from fusedmosaic.estimation.translation import RobotPriorMosaicker
    from fusedmosaic.evaluation.metrics import position_errors_um
    from fusedmosaic.io import Camera
    from fusedmosaic.io.tracking import RobotSamples, interpolate_robot
    from fusedmosaic.simulation.pcle import generate_pcle

    t0 = time.perf_counter()
    scene = generate_pcle(_bench_pcle_options(frames, seed))
    setup_s = time.perf_counter() - t0
    o = scene.options
    robot, robot_valid = interpolate_robot(
        RobotSamples(scene.robot_timestamps, scene.robot_noisy_xy_um), scene.timestamps,
        allow_outside=True)
    camera = Camera(o.width, o.height, pixel_size_um=o.pixel_size_um)
    mosaicker = RobotPriorMosaicker(camera)
    latency = np.zeros(scene.n_frames)
    G = np.full((scene.n_frames, 3, 3), np.nan)
    for k in range(scene.n_frames):
        image = scene.render(k)
        t = time.perf_counter()
        r = mosaicker.add_frame(image, float(scene.timestamps[k]),
                                robot[k] if robot_valid[k] else None)
        latency[k] = time.perf_counter() - t
        G[k] = r.homography
    steady = latency[1:]  # frame 0 only starts the chain
    errors = position_errors_um(G, scene.homographies, o.width, o.height, o.pixel_size_um)
    return {
        "frames": int(scene.n_frames), "size": [o.width, o.height],
        "frames_per_s": steady.size / float(steady.sum()),
        "latency_ms": _ms(steady),
        "mean_error_um": float(np.nanmean(errors)),
        "robot_mean_error_um": _robot_error(scene, robot),
        "simulation_s": setup_s,
    }


def _robot_error(scene, robot: np.ndarray) -> float:
    """Mean distance (µm) of the noisy robot alone (X_r, relative to frame 0) from the truth:
    the filter should be well below it."""
    rel = robot - robot[0]
    return float(np.nanmean(np.linalg.norm(rel - scene.positions_um, axis=1)))


def measure_offline(seed: int = 0, frames: int = OFFLINE_FRAMES) -> dict:
    """BA+EMT with EMT-guided pairs (design.md's "~150 frames / ~1000 pairs"; all pairs would
    be ~5000 registered) over a simulated SYN sequence written to a temporary folder: Ceres'
    optimisation time (the budget) and the whole run's stages."""
    from fusedmosaic.estimation.bundle import BundleOptions, run_ba_emt
    from fusedmosaic.evaluation.metrics import frame_errors
    from fusedmosaic.io import read_dataset
    from fusedmosaic.simulation.fetoscopy import FetoscopyOptions, simulate_fetoscopy

    with tempfile.TemporaryDirectory(prefix="fusedmosaic_bench_") as tmp:
        root = simulate_fetoscopy(Path(tmp) / "syn", FetoscopyOptions(n_frames=frames,
                                                                      seed=seed))
        dataset = read_dataset(root)
        t0 = time.perf_counter()
        result = run_ba_emt(dataset, progress=False,
                            options=BundleOptions(pair_selection="emt-guided"))
        total = time.perf_counter() - t0
        errors = frame_errors(result.homographies, dataset.ground_truth, dataset.camera.width,
                              dataset.camera.height)
    return {"frames": frames, "pairs_registered": result.details["pairs"]["registered"],
            "optimisation_s": float(result.timings["optimisation"]),
            "total_s": total, "timings_s": {k: float(v) for k, v in result.timings.items()},
            "e_M_px": float(np.nanmean(errors))}


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def run_benchmark(options: BenchOptions | None = None, *, say=None) -> dict:
    """Measures the budgets; returns machine facts, per-part measurements and ``checks`` (one
    per budget: measured, limit, ok). ``say(text)`` reports progress."""
    o = options or BenchOptions()
    o.check()
    say = say or (lambda text: None)
    t_start = time.perf_counter()
    result: dict = {"options": asdict(o), "machine": machine_info()}
    say(f"[bench] sequential lba-emt, {o.frames} SYN frames at {SYN_SIZE[0]}x{SYN_SIZE[1]}, "
        f"{o.detector.upper()} ...")
    seq = result["sequential"] = measure_sequential(o.frames, o.detector, o.seed)
    say(f"[bench] pCLE kalman-robot, {o.pcle_frames} frames at 512x448 ...")
    pcle = result["pcle"] = measure_pcle(o.pcle_frames, o.seed)
    measured = {
        "window_step_median_ms": seq["window_step_ms"]["median"],
        "window_step_p95_ms": seq["window_step_ms"]["p95"],
        "sequential_frames_per_s": seq["frames_per_s_steady"],
        "pcle_frames_per_s": pcle["frames_per_s"],
    }
    if o.offline:
        say(f"[bench] offline ba-emt, {OFFLINE_FRAMES} SYN frames ...")
        result["offline"] = measure_offline(o.seed)
        measured["ba_emt_optimisation_s"] = result["offline"]["optimisation_s"]
    checks = []
    for name, value in measured.items():
        op, limit = BUDGETS[name]
        ok = value <= limit if op == "<=" else value >= limit
        checks.append({"name": name, "measured": value, "budget": f"{op} {limit:g}", "ok": ok})
    result["checks"] = checks
    result["all_ok"] = all(c["ok"] for c in checks)
    result["peak_rss_mb"] = _peak_rss_mb()
    result["load_average_end"] = load_average()
    result["runtime_s"] = time.perf_counter() - t_start
    return result


_LABELS = {
    "window_step_median_ms": "LBA window step, median (ms)",
    "window_step_p95_ms": "LBA window step, p95 (ms)",
    "sequential_frames_per_s": "lba-emt end to end (frames/s)",
    "pcle_frames_per_s": "kalman-robot end to end (frames/s)",
    "ba_emt_optimisation_s": "ba-emt optimisation, 150 frames (s)",
}


def json_record(path: str | Path) -> str:
    """The output-manifest key under which `write_json` records ``path`` in its folder."""
    return f"bench:{Path(path).name}"


def check_json_destination(path: str | Path) -> Path:
    """Where ``fusedmosaic bench --json PATH`` writes, checked before measuring: a file name in
    a folder that exists and can be written, and not a file fusedmosaic did not write there: an
    existing file is replaced only when the folder's output manifest (io.output) records it as
    a bench result, or it is one from a version before that record (a JSON object with
    "checks" and "machine"). ValueError starting with the path otherwise."""
    from fusedmosaic.io.output import check_output_dir, read_json_object, read_manifest

    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder; give a file name, e.g. {path / 'bench.json'}")
    try:
        check_output_dir(path.parent, "folder of the bench JSON", create_parent=False)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    if not (path.exists() or path.is_symlink()):
        return path
    entry = (read_manifest(path.parent) or {}).get(json_record(path))
    if entry is not None and path.name in entry["files"]:
        return path
    try:
        older = read_json_object(path)
    except (OSError, ValueError):
        older = {}
    if not (isinstance(older.get("checks"), list) and isinstance(older.get("machine"), dict)):
        raise ValueError(f"{path}: exists and is not a bench result fusedmosaic wrote; choose "
                         "another file name, or move that file")
    return path


def write_json(path: str | Path, result: dict) -> Path:
    """Writes run_benchmark's result to ``path`` atomically, recorded in the folder's output
    manifest so that a later write replaces it and nothing else (check_json_destination: call
    it before measuring too)."""
    from fusedmosaic.io.output import OutputWriter

    path = check_json_destination(path)
    with OutputWriter(path.parent, record=json_record(path)) as w:
        w.write_json(path.name, result)  # strict JSON: a NaN figure (none measured) is null
    return path


def format_benchmark(result: dict) -> str:
    """The checks as a table, then the accuracy beside them and the machine."""
    rows = [("budget (README, Performance)", "measured", "limit", ""), ("---", "---", "---", "---")]
    for c in result["checks"]:
        rows.append((_LABELS[c["name"]], f"{c['measured']:.3g}", c["budget"],
                     "ok" if c["ok"] else "MISSED"))
    width = [max(len(r[i]) for r in rows) for i in range(4)]
    lines = ["| " + " | ".join(r[i].ljust(width[i]) for i in range(4)) + " |" for r in rows]
    seq, pcle, m = result["sequential"], result["pcle"], result["machine"]
    lines.append(
        f"accuracy: lba-emt e_M {seq['e_M_px']:.3f} px over {seq['frames']} frames "
        f"({seq['unplaced']} unplaced); kalman-robot mean error {pcle['mean_error_um']:.1f} µm "
        f"(robot alone {pcle['robot_mean_error_um']:.1f} µm)")
    if "offline" in result:
        off = result["offline"]
        lines.append(f"ba-emt: e_M {off['e_M_px']:.3f} px over {off['pairs_registered']} "
                     f"registered pairs, whole run {off['total_s']:.1f} s")
    lines.append(f"machine: {m['cpu']}, {m['cores']} cores, load average {m['load_average']}; "
                 f"peak RSS {result['peak_rss_mb']:.0f} MB; {result['runtime_s']:.0f} s")
    lines.append("all budgets met" if result["all_ok"] else
                 "some budgets MISSED (a loaded machine measures slower: see the load average)")
    return "\n".join(lines)
