"""`report.md` with PNG plots (matplotlib) for `fusedmosaic run` and `fusedmosaic evaluate`.

Plots, each when its data exist:
* errors.png — e_j per frame for each method (seed 000, Eq. 28; Fig. 8 style);
* poses.png — the six pose components per frame: estimate, EM tracker, truth (Fig. 10c);
* plane.png — the plane as azimuth / elevation / distance over time (appendix Eq. 31, Fig. 10b);
* distance.png — camera-to-plane distance per frame;
* trajectory.png — where each frame's centre lands in the reference (all methods, pCLE too);
* timing.png — seconds per pipeline stage.

Eq. 31 converts the Cartesian point (x, y, z) to tan(az) = y / z, tan(elev) = x / sqrt(z^2 + y^2),
d = sqrt(x^2 + y^2 + z^2) (the paper prints z^2 twice in d; the norm is meant). The point is the
foot of the perpendicular from the virtual camera to the plane, p = -d n = -pi / |pi|^2, so d is
the plane's distance and (az, elev) the direction of its normal.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fusedmosaic.io._table import require_file
from fusedmosaic.io.output import read_json_object, read_plane_json

PLOTS_DIR = "plots"
EVALUATION_TITLE = "fusedmosaic evaluation"  # `evaluate`'s report: its first line is "# " + it
# Methods in green first, then colours that differ from the tracker (blue) and the truth (red).
COLOURS = ["tab:green", "tab:orange", "tab:purple", "tab:brown", "tab:olive", "tab:cyan",
           "tab:pink", "tab:gray"]
TRUTH_COLOUR = "tab:red"
TRACKER_COLOUR = "tab:blue"


@dataclass
class RunRecord:
    """One method's output, from memory (`run`) or from an output folder (`evaluate`)."""

    label: str
    homographies: np.ndarray  # (N, 3, 3) frame -> reference, NaN = unplaced
    poses: np.ndarray | None = None  # (N, 6) cam_from_world
    plane: np.ndarray | None = None  # (3,) final pi = n / d
    plane_history: np.ndarray | None = None  # (N, 3) pi as estimated up to each frame
    timings: dict[str, float] = field(default_factory=dict)
    skipped: dict[int, str] = field(default_factory=dict)  # frames left out of the mosaic
    output: str | None = None


@dataclass
class TruthRecord:
    """What the dataset knows: ground truth (simulators) and the EM tracker's poses."""

    width: int
    height: int
    frame_ids: np.ndarray
    homographies: np.ndarray | None = None  # ground_truth.csv
    poses: np.ndarray | None = None  # truth_poses.csv (simulators)
    plane: np.ndarray | None = None  # truth_plane.json (simulators)
    tracker_poses: np.ndarray | None = None  # tracking.csv interpolated at the frames
    root: str | None = None


# ------------------------------------------------------------------------------------------
# Geometry for the plots
# ------------------------------------------------------------------------------------------


def plane_azimuth_elevation_distance(plane: np.ndarray) -> np.ndarray:
    """Seed 000 appendix Eq. 31 for pi (3,) or (N, 3): (..., 3) azimuth (deg), elevation (deg),
    distance (mm) of the plane's closest point p = -pi / |pi|^2 to the virtual camera."""
    plane = np.asarray(plane, np.float64)
    norm2 = np.sum(plane**2, axis=-1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y, z = np.moveaxis(-plane / norm2, -1, 0)
        az = np.degrees(np.arctan2(y, z))
        elev = np.degrees(np.arctan2(x, np.hypot(z, y)))
        dist = np.sqrt(x**2 + y**2 + z**2)
    return np.stack([az, elev, dist], axis=-1)


def camera_plane_distances(poses: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """(N,) distance (mm) from each camera centre to the plane; plane (3,) or per frame (N, 3)."""
    from scipy.spatial.transform import Rotation

    poses = np.asarray(poses, np.float64)
    out = np.full(len(poses), np.nan)
    plane = np.broadcast_to(np.asarray(plane, np.float64), (len(poses), 3))
    ok = np.isfinite(poses).all(axis=1) & np.isfinite(plane).all(axis=1)
    if ok.any():
        R = Rotation.from_rotvec(poses[ok, :3]).as_matrix()
        centres = -np.einsum("nji,nj->ni", R, poses[ok, 3:])  # C = -R^T t
        pi = plane[ok]
        out[ok] = np.abs(np.sum(pi * centres, axis=1) + 1.0) / np.linalg.norm(pi, axis=1)
    return out


def plane_history_per_frame(history, n: int) -> np.ndarray | None:
    """(N, 3) plane per frame from a method's `plane_history`, which is either already (N, 3),
    or one entry per estimation step: {"frame": k, "plane": pi} or [k, pi_x, pi_y, pi_z] rows
    (k = the frame's position in the sequence), each held until the next step (NaN before the
    first)."""
    if history is None or len(history) == 0:
        return None
    if isinstance(history[0], dict):
        steps = [(int(e["frame"]), e.get("plane")) for e in history]
    else:
        arr = np.array([[np.nan] * 3 if p is None else p for p in history], np.float64)
        if arr.shape == (n, 3):
            return arr
        if arr.ndim != 2 or arr.shape[1] != 4:
            return None
        steps = [(int(r[0]), r[1:]) for r in arr]
    out = np.full((n, 3), np.nan)
    for k, plane in sorted(steps, key=lambda e: e[0]):
        if 0 <= k < n and plane is not None:
            out[k:] = np.asarray(plane, np.float64)
    return out


def frame_centres(G: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N, 2) where each frame's centre lands in the reference, NaN for unplaced frames."""
    c = np.array([(width - 1) / 2.0, (height - 1) / 2.0, 1.0])
    p = np.asarray(G, np.float64) @ c
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[:, :2] / p[:, 2:]


# ------------------------------------------------------------------------------------------
# Loading
# ------------------------------------------------------------------------------------------


def load_truth(dataset_root: str | Path) -> TruthRecord:
    """Ground truth and tracker poses of a dataset folder (files that are absent are None)."""
    from fusedmosaic.evaluation.metrics import read_truth_dataset

    # the tracker poses are only plotted: an unusable tracking.csv / robot.csv is left out, and
    # unreadable frames read blank as `run` reads them
    return truth_from_dataset(read_truth_dataset(Path(dataset_root)))


def truth_from_dataset(ds) -> TruthRecord:
    from fusedmosaic.io import read_poses_csv

    root = Path(ds.root)
    truth = TruthRecord(ds.camera.width, ds.camera.height, np.asarray(ds.frame_ids),
                        homographies=ds.ground_truth, tracker_poses=ds.cam_from_world,
                        root=str(root))
    poses_path = root / "truth_poses.csv"
    if poses_path.is_file():
        ids, poses = read_poses_csv(poses_path)
        truth.poses = _align(ids, poses, truth.frame_ids)
    plane_path = root / "truth_plane.json"
    if plane_path.is_file():
        truth.plane = read_plane_json(plane_path)
    return truth


def _check_report(report: dict, path: Path) -> dict:
    """The parts of a run's report.json that evaluate reads, with their types checked."""
    expected = {"method": (str, "string"), "timings_s": (dict, "object"),
                "mosaic": (dict, "object"), "plane_history": (list, "array")}
    for key, (kind, name) in expected.items():
        if key in report and report[key] is not None and not isinstance(report[key], kind):
            raise ValueError(f"{path}: \"{key}\" must be a JSON {name}, got "
                             f"{type(report[key]).__name__}")
    skipped = (report.get("mosaic") or {}).get("skipped_frames")
    if skipped is not None and (not isinstance(skipped, dict)
                                or not all(k.lstrip("-").isdigit() for k in skipped)):
        raise ValueError(f"{path}: \"mosaic\".\"skipped_frames\" must map frame ids to reasons")
    return report


def _align(ids: np.ndarray, values: np.ndarray, frame_ids: np.ndarray) -> np.ndarray:
    out = np.full((len(frame_ids),) + values.shape[1:], np.nan)
    index = {int(f): i for i, f in enumerate(frame_ids)}
    for f, v in zip(ids, values, strict=True):
        if int(f) in index:
            out[index[int(f)]] = v
    return out


def load_run(out_dir: str | Path, frame_ids: np.ndarray | None = None) -> RunRecord:
    """A RunRecord from an output folder (homographies.csv, poses.csv, plane.json,
    report.json), rows aligned with `frame_ids` when given."""
    from fusedmosaic.io import read_homographies_csv, read_poses_csv

    out = Path(out_dir)
    path = out / "homographies.csv"
    require_file(path)
    ids, G = read_homographies_csv(path)
    order = np.argsort(ids)
    ids, G = ids[order], G[order]
    if frame_ids is not None:
        G = _align(ids, G.reshape(-1, 9), frame_ids).reshape(-1, 3, 3)
    report = {}
    if (out / "report.json").is_file():
        report = _check_report(read_json_object(out / "report.json"), out / "report.json")
    label = report.get("method") or out.name
    if (report.get("parameters") or {}).get("live") is True:
        label += " (live)"
    run = RunRecord(label, G, output=str(out),
                    timings={k: v for k, v in (report.get("timings_s") or {}).items()
                             if isinstance(v, (int, float))})
    if (report.get("mosaic") or {}).get("skipped_frames"):
        run.skipped = {int(k): str(v) for k, v in report["mosaic"]["skipped_frames"].items()}
    if (out / "poses.csv").is_file():
        pids, poses = read_poses_csv(out / "poses.csv")
        run.poses = _align(pids, poses, frame_ids if frame_ids is not None else ids)
    if (out / "plane.json").is_file():
        run.plane = read_plane_json(out / "plane.json")
    try:
        run.plane_history = plane_history_per_frame(report.get("plane_history"), len(G))
    except (TypeError, ValueError, KeyError, IndexError):
        raise ValueError(f"{out / 'report.json'}: \"plane_history\" is neither (N, 3) planes "
                         "nor steps of {\"frame\": k, \"plane\": [x, y, z]}") from None
    return run


# ------------------------------------------------------------------------------------------
# Plots
# ------------------------------------------------------------------------------------------


def _figure(rows: int = 1, cols: int = 1, size=(8.0, 3.6)):
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False)
    return fig, axes


def _x(truth: TruthRecord | None, n: int) -> np.ndarray:
    return truth.frame_ids if truth is not None and len(truth.frame_ids) == n else np.arange(n)


def plot_errors(path: Path, runs: list[RunRecord], errors: list[np.ndarray | None],
                truth: TruthRecord) -> None:
    """e_j per frame of each run; a run not scored (errors None) is left out."""
    fig, ax = _figure()
    ax = ax[0, 0]
    for i, (run, e) in enumerate(zip(runs, errors, strict=True)):
        if e is None:
            continue
        e_m = np.nanmean(e) if np.isfinite(e).any() else np.nan
        ax.plot(_x(truth, len(e)), e, color=COLOURS[i % len(COLOURS)], lw=1.2,
                label=f"{run.label} (e_M = {e_m:.2f} px)")
    ax.set_xlabel("frame")
    ax.set_ylabel("e_j (px, reference)")
    ax.set_title("Error per frame against the ground truth (seed 000, Eq. 28)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=100)


def plot_poses(path: Path, runs: list[RunRecord], truth: TruthRecord | None) -> None:
    fig, axes = _figure(2, 3, size=(11.0, 5.6))
    names = ["r_x (deg)", "r_y (deg)", "r_z (deg)", "t_x (mm)", "t_y (mm)", "t_z (mm)"]
    scale = np.array([np.degrees(1.0)] * 3 + [1.0] * 3)
    for c in range(6):
        ax = axes[c // 3, c % 3]
        if truth is not None and truth.tracker_poses is not None:
            tp = truth.tracker_poses
            ax.plot(_x(truth, len(tp)), tp[:, c] * scale[c], "x", color=TRACKER_COLOUR, ms=3,
                    mew=0.8, label="EM tracker")
        if truth is not None and truth.poses is not None:
            ax.plot(_x(truth, len(truth.poses)), truth.poses[:, c] * scale[c],
                    color=TRUTH_COLOUR, lw=1.2, label="truth")
        for i, run in enumerate(runs):
            if run.poses is not None:
                ax.plot(_x(truth, len(run.poses)), run.poses[:, c] * scale[c],
                        color=COLOURS[i % len(COLOURS)], lw=1.0, label=run.label)
        ax.set_title(names[c], fontsize=9)
        ax.grid(alpha=0.3)
        if c >= 3:
            ax.set_xlabel("frame")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Camera pose (cam_from_world): estimate, EM tracker and truth (seed 000 Fig. "
                 "10c)", fontsize=10)
    fig.savefig(path, dpi=100)


def _plane_series(run: RunRecord, n: int) -> np.ndarray | None:
    if run.plane_history is not None and len(run.plane_history) == n:
        return run.plane_history
    if run.plane is not None:
        return np.tile(np.asarray(run.plane, float), (n, 1))
    return None


def plot_plane(path: Path, runs: list[RunRecord], truth: TruthRecord | None, n: int) -> None:
    fig, axes = _figure(1, 3, size=(11.0, 3.4))
    names = ["azimuth (deg)", "elevation (deg)", "distance (mm)"]
    x = _x(truth, n)
    for i, run in enumerate(runs):
        series = _plane_series(run, n)
        if series is None:
            continue
        aed = plane_azimuth_elevation_distance(series)
        how = "per frame" if run.plane_history is not None else "final"
        for c in range(3):
            axes[0, c].plot(x, aed[:, c], color=COLOURS[i % len(COLOURS)], lw=1.2,
                            label=f"{run.label} ({how})")
    if truth is not None and truth.plane is not None:
        aed = plane_azimuth_elevation_distance(truth.plane)
        for c in range(3):
            axes[0, c].axhline(aed[c], color=TRUTH_COLOUR, lw=1.2, ls="--", label="truth")
    for c in range(3):
        axes[0, c].set_title(names[c], fontsize=9)
        axes[0, c].set_xlabel("frame")
        axes[0, c].grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Plane estimate (seed 000 appendix Eq. 31, Fig. 10b)", fontsize=10)
    fig.savefig(path, dpi=100)


def plot_distance(path: Path, runs: list[RunRecord], truth: TruthRecord | None, n: int) -> None:
    fig, ax = _figure()
    ax = ax[0, 0]
    x = _x(truth, n)
    for i, run in enumerate(runs):
        series = _plane_series(run, n)
        if run.poses is None or series is None:
            continue
        ax.plot(x, camera_plane_distances(run.poses, series), color=COLOURS[i % len(COLOURS)],
                lw=1.2, label=run.label)
    if truth is not None and truth.poses is not None and truth.plane is not None:
        ax.plot(x, camera_plane_distances(truth.poses, truth.plane), color=TRUTH_COLOUR, lw=1.0,
                ls="--", label="truth")
    ax.set_xlabel("frame")
    ax.set_ylabel("mm")
    ax.set_title("Camera-to-plane distance")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=100)


def plot_trajectory(path: Path, runs: list[RunRecord], truth: TruthRecord) -> None:
    fig, ax = _figure(size=(6.0, 5.4))
    ax = ax[0, 0]
    for i, run in enumerate(runs):
        c = frame_centres(run.homographies, truth.width, truth.height)
        ax.plot(c[:, 0], c[:, 1], color=COLOURS[i % len(COLOURS)], lw=1.6, marker=".", ms=3,
                label=run.label)
    if truth.homographies is not None:  # on top, dashed: visible where the estimate agrees
        c = frame_centres(truth.homographies, truth.width, truth.height)
        ax.plot(c[:, 0], c[:, 1], color=TRUTH_COLOUR, lw=0.9, ls="--", label="truth")
    ax.set_aspect("equal", adjustable="datalim")
    ax.invert_yaxis()  # image axes: y down
    ax.set_xlabel("x (reference px)")
    ax.set_ylabel("y (reference px)")
    ax.set_title("Frame centres in the reference (frame 0's pixels)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=100)


def plot_timing(path: Path, runs: list[RunRecord]) -> None:
    stages = []
    for run in runs:
        stages += [s for s in run.timings if s not in stages]
    fig, ax = _figure(size=(8.0, 0.9 + 0.32 * len(stages) * max(1, len(runs))))
    ax = ax[0, 0]
    height = 0.8 / max(1, len(runs))
    y = np.arange(len(stages))
    for i, run in enumerate(runs):
        vals = [run.timings.get(s, 0.0) for s in stages]
        ax.barh(y + i * height, vals, height=height, color=COLOURS[i % len(COLOURS)],
                label=run.label)
    ax.set_yticks(y + height * (len(runs) - 1) / 2, stages, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("seconds")
    ax.set_title("Time per stage")
    ax.grid(alpha=0.3, axis="x")
    if len(runs) > 1:
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=100)


# ------------------------------------------------------------------------------------------
# report.md
# ------------------------------------------------------------------------------------------


def _fmt(v, digits: int = 3) -> str:
    """A figure for the tables: "–" when there is none (None, NaN), "inf" for an infinite
    one (a frame placed at infinity scores e_j = inf: placed, unusably, not unscored)."""
    if v is None or np.isnan(v):
        return "–"
    return ("inf" if v > 0 else "-inf") if np.isinf(v) else f"{v:.{digits}f}"


def write_report(directory: str | Path, runs: list[RunRecord], truth: TruthRecord | None = None,
                 *, name: str = "report.md", title: str = "fusedmosaic report",
                 plots_dir: str = PLOTS_DIR, mosaic: str | None = None, video: str | None = None,
                 notes: list[str] | None = None) -> Path:
    """Writes `name` and its PNG plots (in `plots_dir`, relative to `directory`).

    mosaic / video: links relative to `directory` shown at the top. Returns the .md path."""
    from fusedmosaic.evaluation.metrics import (
        drift_note,
        drift_ratio,
        frame_errors,
        mosaic_error,
        scoring_truth,
    )

    directory = Path(directory)
    plots = directory / plots_dir
    plots.mkdir(parents=True, exist_ok=True)
    n = len(runs[0].homographies)
    lines = [f"# {title}", ""]
    if truth is not None and truth.root:
        lines += [f"Dataset: `{truth.root}`", ""]
    errors = None
    references = [0] * len(runs)  # each estimate's reference frame (left out of the drift)
    scoring = []  # what the table's figures are over, said below it
    if truth is not None and truth.homographies is not None:
        errors = []
        for i, r in enumerate(runs):
            G_true, references[i], why = scoring_truth(r.homographies, truth.homographies,
                                                       truth.frame_ids, "homographies.csv")
            if why is not None:  # no figures ("–"), not figures in another grid
                errors.append(None)
                scoring.append(f"**e_M ({r.label}):** not scored: {why}")
                continue
            e = frame_errors(r.homographies, G_true, truth.width, truth.height)
            errors.append(e)
            placed = np.isfinite(r.homographies).all(axis=(1, 2))
            scored = int((~np.isnan(e)).sum())
            if scored < len(e):  # e_M is over the frames placed and with a truth: say so
                without = int((placed & np.isnan(e)).sum())
                scoring.append(
                    f"**e_M ({r.label}):** over {scored} of the {len(e)} frames, those placed "
                    "and with a ground-truth homography"
                    + (f" ({without} placed without one)" if without else ""))
    header = ("| method | output | frames placed | e_M (px) | max e_j (px) | drift "
              "| sum of stage times (s) |")
    lines += [header, "|---|---|---|---|---|---|---|"]
    drift_notes = []  # why a drift ratio is "–" or inf (a caller's notes may hold them)
    for i, run in enumerate(runs):
        placed = int(np.isfinite(run.homographies).all(axis=(1, 2)).sum())
        e = errors[i] if errors is not None else None  # (None: not scored)
        em = mosaic_error(e) if e is not None else None
        # (inf when a scored frame is placed at infinity, as e_M: it was "–" beside e_M inf
        # when no scored frame had a finite e_j; review 52)
        mx = float(np.nanmax(e)) if e is not None and (~np.isnan(e)).any() else None
        dr = drift_ratio(e, references[i]) if e is not None else None
        why = drift_note(e, truth.frame_ids if len(truth.frame_ids) == len(e) else None,
                         references[i]) if e is not None else None
        if why is not None:
            drift_notes.append(f"**Drift ratio ({run.label}):** {why}")
        total = sum(run.timings.values()) if run.timings else None
        lines.append(f"| {run.label} | `{run.output or '.'}` | {placed}/{len(run.homographies)} "
                     f"| {_fmt(em)} | {_fmt(mx)} | {_fmt(dr, 2)} | {_fmt(total, 1)} |")
    lines.append("")
    for note in [*scoring, *(n for n in drift_notes if n not in (notes or [])), *(notes or [])]:
        lines += [note, ""]
    if mosaic:
        lines += ["## Mosaic", "", f"![mosaic]({mosaic})", ""]
    if video:
        lines += [f"Video of the sequential creation: [{video}]({video})", ""]

    def figure(fname: str, heading: str, caption: str) -> None:
        lines.extend([f"## {heading}", "", caption, "", f"![{heading}]({plots_dir}/{fname})", ""])

    if errors is not None and any(e is not None for e in errors):
        plot_errors(plots / "errors.png", runs, errors, truth)
        figure("errors.png", "Error per frame",
               "e_j: mean distance over a 100 x 100 grid between each frame's estimated and true "
               "placement in the reference (seed 000, Eq. 28); e_M is its mean (Eq. 29).")
    if any(r.poses is not None for r in runs):
        plot_poses(plots / "poses.png", runs, truth)
        figure("poses.png", "Camera poses",
               "Angle-axis rotation (deg) and translation (mm) of cam_from_world per frame: the "
               "estimate, the EM tracker's reading (hand-eye applied, interpolated at the frame "
               "times) and the truth when the dataset has it.")
    if any(_plane_series(r, n) is not None for r in runs):
        plot_plane(plots / "plane.png", runs, truth, n)
        rows = ["| plane | azimuth (deg) | elevation (deg) | distance (mm) |", "|---|---|---|---|"]
        for run in runs:
            if run.plane is not None:
                a, e, d = plane_azimuth_elevation_distance(run.plane)
                rows.append(f"| {run.label} | {a:.2f} | {e:.2f} | {d:.2f} |")
        if truth is not None and truth.plane is not None:
            a, e, d = plane_azimuth_elevation_distance(truth.plane)
            rows.append(f"| truth | {a:.2f} | {e:.2f} | {d:.2f} |")
        figure("plane.png", "Plane",
               "The plane as azimuth, elevation and distance of its closest point to the virtual "
               "camera (seed 000, appendix Eq. 31); a method estimating it per frame shows its "
               "history, others their final estimate.")
        lines += rows + [""]
        if any(r.poses is not None for r in runs):
            plot_distance(plots / "distance.png", runs, truth, n)
            figure("distance.png", "Camera-to-plane distance",
                   "Distance from each estimated camera centre to the estimated plane (mm).")
    if truth is not None:
        plot_trajectory(plots / "trajectory.png", runs, truth)
        figure("trajectory.png", "Trajectory in the mosaic",
               "Where each frame's centre lands in the reference frame's pixels.")
    if any(r.timings for r in runs):
        plot_timing(plots / "timing.png", runs)
        figure("timing.png", "Timing", "Wall-clock seconds per pipeline stage.")
        stages = []
        for run in runs:
            stages += [s for s in run.timings if s not in stages]
        lines += ["| stage | " + " | ".join(r.label for r in runs) + " |",
                  "|---|" + "---|" * len(runs)]
        for s in stages:
            lines.append(f"| {s} | " + " | ".join(_fmt(r.timings.get(s), 3) for r in runs) + " |")
        lines.append("")
    for run in runs:
        if run.skipped:
            lines += [f"## Frames left out of the mosaic ({run.label})", ""]
            lines += [f"- frame {k}: {why}" for k, why in sorted(run.skipped.items())] + [""]
    path = directory / name
    # (surrogateescape: a dataset folder whose name is not UTF-8 is written back as its bytes;
    # it raised UnicodeEncodeError, review 47)
    path.write_text("\n".join(lines), encoding="utf-8", errors="surrogateescape")
    return path
