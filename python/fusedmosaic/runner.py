"""`fusedmosaic run`: dataset -> method -> outputs, written atomically (design, output contract)."""

from __future__ import annotations

import dataclasses
import re
import signal
import threading
import time
import warnings
from pathlib import Path

import numpy as np

from fusedmosaic import methods
from fusedmosaic.io.dataset import check_fps
from fusedmosaic.io.output import (
    OutputsWrittenInterrupt,
    OutputWriter,
    is_under,
    missing_folders,
    read_json_object,
    read_manifest,
    remove_created_folders,
)
from fusedmosaic.io.tracking import MAX_TIME_OFFSET_S

# What each method needs from the dataset beyond frames and camera.yaml.
NEEDS_TRACKING = {"ba-emt", "lba-emt", "emt"}
NEEDS_CAMERA_MATRIX = {"ba", "ba-emt", "lba-emt", "emt"}
NEEDS_ROBOT = {"robot", "kalman-robot"}
# A live frame stamped further (s) from the tracker's latest sample, heard within the last
# second, than --tracker-time-offset can correct is on another clock.
CLOCK_MISMATCH_S = MAX_TIME_OFFSET_S
ONE_CLOCK = ("on another clock? The frames get no {0} sample near their time: the sender must "
             "stamp the images and the {0} on one clock (--tracker-time-offset corrects at most "
             f"+-{MAX_TIME_OFFSET_S:g} s, a calibrated latency)")
NEEDS_PIXEL_SIZE = NEEDS_ROBOT  # (ncc registers the images alone: no pixel size needed)
PCLE_METHODS = {"ncc", "robot", "kalman-robot"}  # translation-only: composed without undistortion
# Methods whose estimation reads no image: the frames are read once before compositing, so
# that unreadable ones are known (and left out) before the mosaic is drawn.
READS_NO_IMAGE = {"robot"}
# A frame whose every pixel is at or below this grey level shows nothing (not composed): the
# level below which features.py finds no visual content (FeatureOptions.border_threshold).
BLANK_LEVEL = 12
# --frame-timeout at most (s, 11.6 days: as good as none); a wait beyond threading.TIMEOUT_MAX
# (9.2e9 s) ended the session in OverflowError
MAX_FRAME_TIMEOUT_S = 1e6

def run_dataset(dataset_root: str | Path, method: str, out: str | Path, *,
                fps: float | None = None,
                robot_file: str = "robot.csv", allow_untracked: bool = False,
                progress: bool = True, blend=None, options=None, canvas=None,
                video: str | Path | None = None, report: bool = True, live: bool = False,
                result: methods.MethodResult | None = None,
                tracker_time_offset: float = 0.0, stop_on_unreadable: bool = False,
                shown_warnings=()) -> str:
    """Runs `method` on a dataset folder and writes the output contract into `out`.

    blend: a blend name ("linear", "multiband", "average", "last") or a
        compositing.BlendOptions (its blend None: the method's); by default the method's own
        preference (MethodResult.blend).
    options: the method's options dataclass (None: the method's defaults).
    canvas: compositing.CanvasOptions (pixel budget, tiling); None: defaults.
    video: path of an MP4 of the mosaic's sequential creation (None: no video).
    report: also write report.md with PNG plots (plots/).
    live: replay the recording as a live source through the method's streaming form (frames at
        their timestamps, the newest tracker / robot sample, frames dropped while busy; see
        estimation.live), for lba-emt and the pCLE methods (kalman-robot, ncc, robot).
    result: the method's result, already computed on this dataset (a live session, whose
        recording the dataset is): only the outputs are written.
    fps: the frame rate giving the frame times of a dataset without frames.csv (None: the
        video's own, else 25; io.read_dataset).
    tracker_time_offset: s, the tracker's clock ahead of the video's (io.read_dataset):
        calibrate's calibration.json "tracker_time_offset" / "applied_s"; for the methods that
        use the robot (NEEDS_ROBOT), the robot's clock (read_dataset's robot_time_offset), as
        run_igtl takes it for the sample stream.
    stop_on_unreadable: a frame that cannot be read (a damaged PNG, an undecodable video
        frame) stops the run with ValueError naming it. By default it is a frame without
        visual content (read as all zero: the pose methods place it from the tracker and
        motion priors, the translation methods from the robot, or leave it unplaced), flagged
        in report.json "unreadable_frames" and a warning, and left out of the mosaic.
    shown_warnings: texts of the result's warnings already shown (a live session's): in
        report.json, not repeated by the summary.
    Returns a short summary for the terminal."""
    from fusedmosaic.evaluation.provenance import dataset_fingerprint
    from fusedmosaic.io import read_dataset

    timings: dict[str, float] = {}
    run_method = methods.get(method)  # unknown method fails before any reading
    if live:
        from functools import partial

        from fusedmosaic.estimation.live import check_live_method, replay_live

        check_live_method(method)  # before any reading
        run_method = partial(replay_live, method=method)
    if result is not None:
        computed = result
        run_method = lambda dataset, **_: computed  # noqa: E731
    if fps is not None:
        check_fps(fps)
    out = Path(out)
    check_out_outside_dataset(out, Path(dataset_root))
    if video is not None:
        from fusedmosaic.compositing.video import check_video_suffix

        check_video_suffix(video)
        check_video_destination(Path(video), out, Path(dataset_root))
    check_compositing_options(blend, canvas)  # before minutes of estimation, not after
    t0 = time.perf_counter()
    # live replay uses the raw samples (frames without a recent one are listed, not refused);
    # a method that does not use the tracker / robot is not refused for their files: an
    # unusable one is left out with a warning (dataset.ignored says why)
    with HeardWarnings() as heard:  # for report.json (and not repeated by the summary)
        dataset = read_dataset(dataset_root, fps=fps, robot_file=robot_file,
                               allow_untracked=allow_untracked or live,
                               tracker_time_offset=(0.0 if method in NEEDS_ROBOT
                                                    else tracker_time_offset),
                               robot_time_offset=(tracker_time_offset if method in NEEDS_ROBOT
                                                  else 0.0),
                               strict_tracking=method in NEEDS_TRACKING,
                               strict_robot=method in NEEDS_ROBOT,
                               strict_truth=False,
                               blank_unreadable=not stop_on_unreadable)
        # a ground truth that does not fit the frames costs the run its scores, not its mosaic
        # (it blocked the run, exit 2; review 54): `fusedmosaic evaluate --truth` still refuses
        unused = {k: v for k, v in dataset.ignored.items() if k != "ground_truth.csv"}
        if unused:
            warnings.warn(f"{'; '.join(unused.values())} -- left out: method {method!r} "
                          f"does not use {'it' if len(unused) == 1 else 'them'}",
                          stacklevel=2)
        if "ground_truth.csv" in dataset.ignored:
            warnings.warn(f"{dataset.ignored['ground_truth.csv']} -- left out: the run is not "
                          "scored (report.json metrics null)", stacklevel=2)
        if method in NEEDS_TRACKING and result is None:  # a live session may have had none
            dataset.require_tracking(method)
            if not dataset.pose_valid.any():  # --allow-untracked: every frame flagged
                from fusedmosaic.io.tracking import no_overlap_message

                ts = dataset.tracking.timestamps[dataset.tracking.valid]
                raise ValueError(no_overlap_message(str(dataset.root / "tracking.csv"), "tracker",
                                                    dataset.timestamps, ts[0], ts[-1]))
        if method in NEEDS_CAMERA_MATRIX:
            dataset.camera.require_camera_matrix(method)
        check_compositing_options(blend, canvas, camera=dataset.camera, method=method)  # the border
        if method in NEEDS_ROBOT and result is None:
            dataset.require_robot(method)
        if method in NEEDS_PIXEL_SIZE:
            dataset.require_pixel_size(method)
        timings["read_dataset"] = time.perf_counter() - t0

        # OUT (and the video's folder) are checked before the computation; the outputs are
        # collected in a temporary folder and replace OUT's previous run at the end: the files that
        # run recorded (and evaluations of it), never files fusedmosaic did not write.
        if video is not None and not is_under(video, out):
            from fusedmosaic.io.output import check_output_dir

            # nothing created yet: a run that fails, is interrupted or skips the video leaves no
            # empty folder behind (OutputWriter.external_path creates it and removes it on failure)
            check_output_dir(Path(video).parent, "video's folder", create_parent=False)
        with run_output_writer(out, report=report, video=video) as w:
            w.check_ours(*run_output_names(report))
            result = run_method(dataset, progress=progress, options=options)
            add_streamed_checks(result, dataset, method, options)
            if method in READS_NO_IMAGE and not stop_on_unreadable:
                for k in range(len(dataset.frames)):
                    dataset.frames[k]
            unreadable = flag_unreadable_frames(result, dataset)
            flag_dead_reckoned_frames(result, dataset)
            reference = flag_reference_frame(result, dataset)
            timings.update(result.timings)
            G = result.homographies
            placed = np.isfinite(G).all(axis=(1, 2))

            report_json = {
                "method": method,
                "paper_name": methods.REGISTRY[method][1],
                "dataset": str(Path(dataset_root).resolve()),
                "dataset_fingerprint": dataset_fingerprint(dataset),
                "frames": len(G),
                "placed": int(placed.sum()),
                # the frame whose pixel grid homographies.csv maps to: frame 0 unless unplaced
                "reference_frame": reference,
                "parameters": result.parameters,
                "frame_times": dataset.frame_times,
                "tracker_time_offset_s": float(tracker_time_offset),
                "timings_s": timings,
                # the per-frame lists (frame_status, confidences, ...) are in frames.csv's
                # order; frame_ids names their frames (the other lists of frames hold IDs)
                "frame_ids": [int(i) for i in dataset.frame_ids],
                "frame_status": result.status,
                **result.details,
            }
            if dataset.ignored:  # files present but not usable, left out (the method does not
                # use them)
                report_json["inputs_ignored"] = dict(dataset.ignored)
            if unreadable:
                report_json["unreadable_frames"] = unreadable
            if dataset.frames.bits_in_use is not None:  # 16-bit frames, converted with one scale
                report_json["frame_bits_in_use"] = dataset.frames.bits_in_use
            if "ground_truth.csv" in dataset.ignored:
                report_json.update(metrics=None, metrics_note=(
                    "not scored: ground_truth.csv left out (inputs_ignored says why)"))
            if dataset.ground_truth is not None:
                from fusedmosaic.evaluation.metrics import run_metrics

                # {"metrics": {...}}, or metrics null and "metrics_note" when the truth has no
                # row for the output's reference frame (no figures in another grid: a robot
                # starting late on a sparse truth published 159.5 px for 0.46; review 46)
                report_json.update(run_metrics(G, dataset.ground_truth, dataset.camera.width,
                                               dataset.camera.height, dataset.frame_ids))
            w.write_homographies(dataset.frame_ids, G)
            if result.poses is not None:
                w.write_poses(dataset.frame_ids, result.poses)
            if result.plane is not None:
                from fusedmosaic import _core

                plane = np.asarray(result.plane, float)
                dist = [None if not np.isfinite(p).all() else _core.camera_plane_distance(p, plane)
                        for p in (result.poses if result.poses is not None else [])]
                # ba: no scale, lengths in the first camera's distance to the plane (review
                # 46), so its keys do not say mm (a script reading distance_mm got a plane 1 mm
                # away; review 47)
                unit = result.details.get("world", "mm")
                mm = "_mm" if unit == "mm" else ""
                w.write_json("plane.json", {"plane": plane.tolist(),
                                            "normal": (plane / np.linalg.norm(plane)).tolist(),
                                            f"distance{mm}": float(1.0 / np.linalg.norm(plane)),
                                            f"camera_plane_distance{mm}": dist,
                                            "unit": unit})
            outputs = compose_outputs(w, dataset, result, G, blend=blend, canvas=canvas,
                                      video=video, out=out, progress=progress, timings=timings)
            report_json["mosaic"] = outputs["mosaic"]
            heard.add_to(result.details)  # reading the dataset, the method, the compositing
            # (always a list: pairwise's details had none, so its report.json had no key)
            report_json["warnings"] = list(result.details.get("warnings", []))
            if report:
                t0 = time.perf_counter()
                with w.named_errors("report.md", "the report"):  # (matplotlib's, Python's)
                    write_run_report(w, dataset, method, result, G, outputs, timings)
                timings["report"] = time.perf_counter() - t0
            report_json["outputs"] = sorted({*w.written(), "report.json"})
            w.write_json("report.json", report_json)
    try:
        return _summary(method, G, out, report_json, outputs, report,
                        shown=[*shown_warnings, *heard.texts])
    except KeyboardInterrupt:  # (the outputs are in OUT: said, not 'interrupted' alone)
        raise OutputsWrittenInterrupt(out) from None


UNREADABLE_STATUS = "unplaced: its image cannot be read"


def flag_unreadable_frames(result: methods.MethodResult, dataset) -> dict[str, str]:
    """Frames whose image could not be read (read as all zero, Dataset.frames.unreadable): a
    warning in the result's details counting and naming them, the status of those the method
    could not place says why (it would blame the featureless image), and {frame id: message}
    for report.json (empty when every frame was read). compose_outputs leaves them out."""
    found = dict(sorted(dataset.frames.unreadable.items()))
    if not found:
        return {}
    ids = dataset.frame_ids
    for k in found:
        if result.status[k].startswith("unplaced"):
            result.status[k] = UNREADABLE_STATUS
    placed = sum(not result.status[k].startswith("unplaced") for k in found)
    listed = methods.listed_ids(ids[k] for k in found)
    _warn_first(result, (
        f"{len(found)} of {len(ids)} frames could not be read (frames {listed}; first: "
        f"{next(iter(found.values()))}): taken as frames without visual content, {placed} "
        "placed from the priors, left out of the mosaic (report.json unreadable_frames)"))
    return {str(int(ids[k])): message for k, message in found.items()}


def _warn_first(result: methods.MethodResult, message: str) -> None:
    """`message` at the head of the result's details["warnings"]."""
    result.details["warnings"] = [message, *result.details.get("warnings", [])]


def flag_reference_frame(result: methods.MethodResult, dataset) -> int:
    """The id of the frame whose pixel grid the result's homographies map to (design.md: frame
    0's), with a warning in its details when that is not frame 0: frame 0 unplaced, the first
    placed frame is the reference (lba-emt's start-up handing frames out before its tracker
    came on, a pCLE chain starting at its first usable frame); frame 0 dead-reckoned (no
    anchor: its pose extrapolated by C_p alone), the homographies are re-expressed in the
    first anchored frame's grid (10 black frames at the start of a tracker gap: every frame
    150-224 px off in frame 0's grid, 0.5 px in frame 10's)."""
    from fusedmosaic.evaluation.metrics import reference_frame, rereferenced

    ids = dataset.frame_ids
    G = result.homographies
    status = result.status
    # the first placed frame: frame 0, or after unplaced ones (a late tracker's start-up)
    placed = np.flatnonzero(np.isfinite(G).all(axis=(1, 2)))
    first = int(placed[0]) if len(placed) and status else 0
    if status and status[first] == "dead-reckoned":
        anchored = [k for k, s in enumerate(status) if s in ("placed", "prior-only")
                    and np.isfinite(G[k]).all()]
        if anchored:
            r = anchored[0]
            result.homographies = rereferenced(G, r)  # (unplaced rows stay NaN)
            _warn_first(result, (
                f"frame {ids[first]} has no anchor ({status[first]}: placed by the motion "
                f"prior alone): homographies.csv maps the frames to frame {ids[r]}'s pixel "
                f"grid, the first frame placed with one, not frame {ids[first]}'s (report.json "
                "reference_frame; evaluate scores in that grid)"))
            return int(ids[r])
    if (status and status[first] == "prior-only" and result.poses is not None
            and "placed" in status):
        # (documented: the reference stays that frame; a black frame 0 with a tracker sample
        # put every frame 23 px off, 0.10 px from frame 1, without a word; helper fuzz 32)
        _warn_first(result, (
            f"frame {ids[first]}, the reference of homographies.csv, has no registered pair "
            "(prior-only): its pose comes from the tracker and the motion prior alone, so every "
            "homography carries its error (the mosaic itself is consistent)"))
    r = reference_frame(G)
    if r:
        _warn_first(result, (
            f"frame {ids[0]} was not placed ({status[0]}): homographies.csv maps the "
            f"frames to frame {ids[r]}'s pixel grid, the first placed frame, not frame "
            f"{ids[0]}'s (report.json reference_frame; evaluate scores in that grid)"))
    return int(ids[r])


def flag_dead_reckoned_frames(result: methods.MethodResult, dataset) -> None:
    """A warning in the result's details naming the frames placed with no anchor (status
    dead-reckoned: neither a tracker sample nor a registered pair chaining them to a frame with
    one), which compose_outputs leaves out: the constant-velocity prior alone puts them, and
    it drifts over a long stretch (16 black frames inside a 31-frame tracker gap: up to 170 px
    off, reported nowhere but in their status)."""
    dead = [k for k, s in enumerate(result.status) if s == "dead-reckoned"]
    if not dead:
        return
    runs, start = [], dead[0]
    for a, b in zip(dead, dead[1:] + [None], strict=True):
        if b != a + 1:
            runs.append((start, a))
            start = b
    ids = dataset.frame_ids
    listed = ", ".join(f"{ids[a]}-{ids[b]}" if b > a else f"{ids[a]}" for a, b in runs[:10])
    more = f", ... ({len(runs) - 10} more runs)" if len(runs) > 10 else ""
    longest = max(b - a + 1 for a, b in runs)
    _warn_first(result, (
        f"{len(dead)} of {len(ids)} frames had neither a tracker sample nor a registered pair "
        f"chaining them to a frame with one (frames {listed}{more}; the longest run "
        f"{longest} frames): placed by the constant-velocity prior alone (status "
        "dead-reckoned), they may lie far off; left out of the mosaic and the video, kept in "
        "homographies.csv"))


def playback_rate(timestamps: np.ndarray) -> float:
    """Frames/s of the creation video: the recording's own (its median frame interval), so it
    plays in real time, within [1, 60]; 25 for a single frame."""
    steps = np.diff(np.asarray(timestamps, float))
    if steps.size == 0 or not np.median(steps) > 0:
        return 25.0
    return float(f"{np.clip(1.0 / np.median(steps), 1.0, 60.0):.6g}")  # 25, not 24.99999999999998


def check_compositing_options(blend, canvas, names: dict[str, str] | None = None,
                              camera=None, method: str | None = None) -> None:
    """Raises ValueError for blend / canvas options compose_outputs cannot use; `names` maps
    option fields to what the messages call them (the CLI's flags). With the `camera` (and the
    `method`, which says whether the frames are composed undistorted), also a frame border
    that would cover the whole field of view the mosaic is drawn from."""
    from fusedmosaic.compositing import BlendOptions, CanvasOptions
    from fusedmosaic.compositing.blending import check_border, edge_distance, fov_mask_bool

    if isinstance(blend, str):
        BlendOptions(blend).validate(names)
    elif isinstance(blend, BlendOptions):  # its blend None: the method's, any is fine
        dataclasses.replace(blend, blend=blend.blend or "linear").validate(names)
        if camera is not None and blend.border_px > 0:
            _, mask = composing_lens(camera, undistorted=method not in PCLE_METHODS)
            mask = fov_mask_bool(mask, camera.width, camera.height)
            check_border(blend.border_px, edge_distance(mask))
    elif blend is not None:
        raise ValueError(f"blend must be a blend name or BlendOptions, got {type(blend).__name__}")
    (canvas or CanvasOptions()).validate(names)


def _in_dataset(path: Path, dataset_root: Path) -> str | None:
    """How `path` lies in the dataset ("is the dataset folder", "is inside ..."), or None:
    resolved (the dataset folder need not exist yet: a live recording's), and in the frames
    folder wherever it lies (a symlinked frames/ resolves elsewhere: --out DATA/frames wrote
    the outputs among the shared frames)."""
    root = dataset_root.resolve()
    frames = dataset_root / "frames"
    if path.resolve() == root:
        return "is the dataset folder"
    if is_under(path, root):
        return f"is inside the dataset folder {dataset_root}"
    if frames.is_dir() and is_under(path, frames, or_equal=True):
        return f"is (inside) the dataset's frames folder {frames} ({frames.resolve()})"
    return None


def check_out_outside_dataset(out: Path, dataset_root: Path) -> None:
    """OUT equal to the dataset folder or inside it (e.g. in frames/) would mix outputs into the
    dataset: mosaic.png among the frames, report.json beside camera.yaml."""
    where = _in_dataset(out, dataset_root)
    if where is not None:
        raise ValueError(f"{out}: the output folder {where}; writing there would corrupt the "
                         "dataset: choose --out outside it")


def check_video_destination(video: Path, out: Path, dataset_root: Path) -> None:
    """The creation video replaces a file only when a run into ``out`` wrote it (its report.json
    names that path), never a file of the user's (a recording, another clip) nor anything in the
    dataset folder: ValueError naming the path, before any work."""
    where = _in_dataset(video, dataset_root)
    if where is not None:
        raise ValueError(f"{video}: the video would be written inside the dataset: its path "
                         f"{where}; choose a path outside it (e.g. in the output folder)")
    if not (video.exists() or video.is_symlink()) or video.is_dir():
        return  # absent; a folder there is refused by the writer
    if not _named_by_earlier_run(video, out, lambda report: (
            report["mosaic"]["video"].get("path") or report["mosaic"]["video"]["file"])):
        raise ValueError(f"{video}: exists and no earlier run into {out} wrote it; choose another "
                         "video path, or move that file")


def check_preview_destination(preview: Path, out: Path) -> None:
    """live's --preview (replaced every second) replaces a file only when a live session into
    ``out`` wrote it (its report.json names that path), never an image of the user's: ValueError
    naming the path, before connecting."""
    if not (preview.is_file() or preview.is_symlink()):
        return  # absent (a folder there is refused by the live view)
    if not _named_by_earlier_run(preview, out,
                                 lambda report: report["live"]["view"]["preview"]):
        raise ValueError(f"{preview}: exists and no earlier live session into {out} wrote it; "
                         "choose another preview path, or move that file")


def _named_by_earlier_run(path: Path, out: Path, lookup) -> bool:
    """Whether an earlier run into ``out`` (recognisably fusedmosaic's) names ``path`` in its
    report.json, as lookup(report) gives it."""
    if not (older_run_outputs(out) or "run" in (read_manifest(out) or {})):
        return False
    try:
        earlier = lookup(read_json_object(out / "report.json"))
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return False
    return isinstance(earlier, str) and Path(earlier).resolve() == path.resolve()


# What a run may write in OUT besides plots/ and a creation video inside it.
RUN_FILES = ("homographies.csv", "poses.csv", "plane.json", "mosaic.png", "report.json",
             "report.md")
# The plots a run's report.md may show (evaluation.report.write_report's names, in its
# PLOTS_DIR): checked for a user's file before the computation, as RUN_FILES (one was first
# refused when the outputs were moved in, after the whole computation; review 47).
RUN_PLOTS = ("errors.png", "poses.png", "plane.png", "distance.png", "trajectory.png",
             "timing.png")


def run_output_names(report: bool = True) -> list[str]:
    """The files (relative to OUT) a run may write there, besides a creation video."""
    if not report:
        return [f for f in RUN_FILES if f != "report.md"]
    return [*RUN_FILES, *(f"plots/{name}" for name in RUN_PLOTS)]


def run_output_writer(out: str | Path, *, report: bool = True,
                      video: str | Path | None = None) -> OutputWriter:
    """The OutputWriter of a run's outputs in `out`: it records them as the "run" set, replaces
    the earlier run's (and the evaluations of it), and refuses a file of a run's name that no
    fusedmosaic run wrote (the user's) rather than replace it."""
    out = Path(out)
    expects = ["homographies.csv", "mosaic.png", "report.json"]
    if report:
        expects += ["report.md", "plots/"]
    if video is not None and is_under(video, out):
        expects.append(Path(video).resolve().relative_to(out.resolve()).as_posix())
    older = older_run_outputs(out)
    return OutputWriter(out, record="run", stale_after_run=True, new_run=True, expects=expects,
                        replaces=older, foreign="refuse",
                        older=[*RUN_FILES, "plots/"] if older else [])


def check_run_destination(out: str | Path, *, report: bool = True,
                          video: str | Path | None = None) -> None:
    """What run_dataset checks in `out` before its computation (a folder or a user's file where
    one of its outputs goes), creating nothing: for a live session, before it connects (a
    user's report.md in OUT refused the outputs once the session was over; review 47)."""
    w = run_output_writer(out, report=report, video=video)
    w.check_expected()
    w.check_ours(*run_output_names(report))


def older_run_outputs(out: Path) -> list[str]:
    """What a run of an older fusedmosaic (no "run" record in OUT's manifest) left in OUT and
    a new run replaces; only when OUT's report.json is recognisably ours (method registered):
    the files it lists under "outputs" when it also records a dataset fingerprint, else the
    method-dependent plane.json and poses.csv (an emt run's plane beside a pairwise run's
    homographies would be read as pairwise's). Nothing for a foreign or absent report.json."""
    try:
        report = read_json_object(out / "report.json")
    except (OSError, ValueError):
        return []
    if not isinstance(report.get("method"), str) or report["method"] not in methods.REGISTRY:
        return []
    listed = report.get("outputs")
    if isinstance(report.get("dataset_fingerprint"), dict) and isinstance(listed, list):
        return [name for name in listed if isinstance(name, str)]
    return ["plane.json", "poses.csv"]


def frames_to_compose(dataset, undistorted: bool = True):
    """(frames, field-of-view mask) the mosaic is composed from: with lens distortion in
    camera.yaml and homographies between undistorted pixels (MethodResult.undistorted), the
    frames undistorted on read and the mask of their valid pixels (see LensUndistortion);
    otherwise the frames and the camera's field-of-view mask as they are."""
    from fusedmosaic.io import UndistortedFrames

    lens, mask = composing_lens(dataset.camera, undistorted)
    return (dataset.frames if lens is None else UndistortedFrames(dataset.frames, lens)), mask


def composing_lens(camera, undistorted: bool):
    """(LensUndistortion or None, field-of-view mask) of frames composed undistorted or raw:
    the lens and the mask of its valid pixels when camera.yaml has distortion and the
    homographies hold between undistorted pixels, else None and the camera's own mask."""
    lens = camera.undistortion() if undistorted else None
    return lens, (camera.fov_mask() if lens is None else lens.mask)


def is_blank(image, status: str | None = None, mask=None) -> bool:
    """A frame with no visual content: placed, not composed (blank_reason says why). A frame
    its method calls "placed" was registered, so has content: not read."""
    return status != "placed" and blank_reason(image, mask) is not None


def blank_reason(image, mask=None) -> str | None:
    """Why a frame has no visual content, for report.json's mosaic.skipped_frames; None when
    it has. Black (every pixel <= BLANK_LEVEL), or, 8-bit, textureless inside the field of
    view ``mask`` (each channel's 1st-99th percentile range <= BLANK_LEVEL levels: a capture
    card's uniform "no signal" frame, a lens in turbid fluid; 10 grey frames of 45 pasted a
    grey veil over the tissue, review 54). Without a mask (no fov_mask_radius) a grey frame
    inside the scope's black circle is not judged textureless."""
    image = np.asarray(image)
    if image.max() <= BLANK_LEVEL:
        return f"no visual content (every pixel <= {BLANK_LEVEL}): not composed"
    if image.dtype != np.uint8:
        return None
    if mask is not None and np.shape(mask) == image.shape[:2]:
        image = image[np.asarray(mask) > 0]
    if image.size == 0:
        return None
    values = image.reshape(-1, image.shape[-1]) if image.ndim == 3 else image.reshape(-1, 1)
    low, high = np.percentile(values, (1, 99), axis=0)  # per channel (a blue "no signal")
    if (high - low).max() > BLANK_LEVEL:
        return None
    return (f"no visual content (textureless: 98 % of its pixels within {BLANK_LEVEL} grey "
            "levels): not composed")


def compose_outputs(w, dataset, result, G: np.ndarray, *, blend=None, canvas=None, video=None,
                    out: Path, progress: bool, timings: dict[str, float]) -> dict:
    """mosaic.png (one piece, or tile by tile above CanvasOptions.in_memory_pixels), and the
    creation video if asked; fills `timings`; returns what report.json says about them.
    The options were checked by run_dataset (check_compositing_options).

    A canvas above the pixel budget (CanvasTooLargeError, raised before anything is allocated)
    or no frame left to show (NoFrameToComposeError: every placed frame left out, e.g. all
    black) skips the mosaic and the video with a warning; the estimates are still written."""
    from fusedmosaic.compositing import (
        BlendOptions,
        CanvasOptions,
        CanvasTooLargeError,
        NoFrameToComposeError,
        SpecularMasks,
        frame_gains,
        plan_canvas,
        render_mosaic,
        screen_frames,
        write_creation_video,
        write_mosaic_png,
    )
    from fusedmosaic.compositing.png import write_png

    cam = dataset.camera
    frames, mask = frames_to_compose(dataset, result.undistorted)
    # Frames lba-emt placed with no anchor at all (black frames inside a tracker dropout, and
    # the frames chained only to them) can lie hundreds of px off: not pasted into the mosaic
    # or the video (homographies.csv still has them, flagged in frame_status).
    dead = np.array([s == "dead-reckoned" for s in result.status], dtype=bool)
    # Frames whose image could not be read are placed (from the priors) but have nothing to
    # show: their all-zero stand-in would paint a black hole into the mosaic.
    unreadable = np.zeros(len(G), dtype=bool)
    unreadable[list(dataset.frames.unreadable)] = True
    # Black frames (no visual content, e.g. the light off: paper 000 Sec. 4.2.3) are placed from
    # the priors but show nothing: pasted, they blacked out or darkened the tissue under them
    # (12 black frames of 60: 363k of 694k mosaic pixels > 20 grey levels darker, linear).
    # Only frames the method placed without looking are read here (it judged the others).
    blank = np.zeros(len(G), dtype=bool)
    blank_why: dict[int, str] = {}
    for k in np.flatnonzero(np.isfinite(G).all(axis=(1, 2)) & ~dead & ~unreadable):
        if not (result.images_seen and result.status[k] == "placed"):
            why = blank_reason(frames[k], mask)
            if why is not None:
                blank[k] = True
                blank_why[int(k)] = why
    if (dead | unreadable | blank).any():
        G = np.where((dead | unreadable | blank)[:, None, None], np.nan, G)
    if blend is None:
        blend = BlendOptions(result.blend)
    elif isinstance(blend, str):
        blend = BlendOptions(blend)
    elif blend.blend is None:  # options given, blend left to the method
        blend = dataclasses.replace(blend, blend=result.blend)
    if blend.mask_specular is None:  # the method's choice
        blend = dataclasses.replace(blend, mask_specular=result.mask_specular)
    canvas = canvas or CanvasOptions()
    t0 = time.perf_counter()
    ids = dataset.frame_ids

    def skipped_frames(reasons: dict[int, str]) -> dict[str, str]:
        return {str(int(ids[k])): why for k, why in sorted(
            {**reasons, **{int(k): "dead-reckoned (no anchor): not composed"
                           for k in np.flatnonzero(dead)},
             **{int(k): "image unreadable: not composed"
                for k in np.flatnonzero(unreadable)},
             **blank_why}.items())}

    plan, none_left = None, None
    try:
        plan = plan_canvas(G, cam.width, cam.height, max_pixels=canvas.max_pixels,
                           absurd_area_factor=canvas.absurd_area_factor)
    except NoFrameToComposeError:
        # every placed frame left out (black, unreadable, dead-reckoned or screened): as a
        # canvas too large, the mosaic is skipped and the estimates kept
        none_left = skipped_frames(
            screen_frames(G, cam.width, cam.height, canvas.absurd_area_factor)[1])
        why = ("no frame to compose a mosaic from: " + (
            f"the {len(none_left)} placed frame(s) are all left out (report.json "
            "mosaic.skipped_frames says why)" if none_left else "no frame is placed"))
    except CanvasTooLargeError as exc:
        why = str(exc)
    if plan is None:
        skipped = ["mosaic.png"] + ([str(video)] if video is not None else [])
        kept = (" (an earlier file at the video's path is left as it was)"
                if video is not None and not is_under(video, out) else "")
        warnings.warn(f"{out}: {' and '.join(skipped)} not written{kept}: {why}. The "
                      "estimates (homographies.csv, report.json, ...) are written.", stacklevel=3)
        info = {"file": None, "skipped": why}
        if none_left is not None:
            info["skipped_frames"] = none_left
        if video is not None:
            info["video"] = {"file": None, "skipped": why}
        return {"mosaic": info, "plan": None, "video": None}
    strays = [k for k, why in sorted(plan.skipped.items()) if why.startswith("stray")]
    if strays:
        warnings.warn(
            f"{out}: frame(s) {methods.listed_ids(dataset.frame_ids[strays])} left out of "
            f"mosaic.png{' and the video' if video is not None else ''}: each lands far from "
            "all the other frames (more than 10 footprint diagonals: a placement glitch?); "
            "homographies.csv has it as estimated (report.json mosaic.skipped_frames)",
            stacklevel=3)
    gains = None
    # Each frame's specular highlights found once for the gains and the mosaic, not twice
    # (SpecularMasks: ~0.5 kB per simulated frame with highlights, at most 64 MB, freed below).
    highlights = (SpecularMasks() if blend.mask_specular and blend.gain_compensation
                  else None)
    if blend.gain_compensation:
        gains = frame_gains(frames, G, cam.width, cam.height, mask=mask, use=plan.use,
                            progress=progress, mask_specular=blend.mask_specular,
                            highlights=highlights)
        timings["gain_compensation"] = time.perf_counter() - t0
        t0 = time.perf_counter()
    tiled = plan.pixels > canvas.in_memory_pixels
    # a write error names OUT's mosaic.png, not the staging copy the streamed writers write
    # (review 46); an OSError exits 1, as every output the file system refuses (review 47)
    with w.named_errors("mosaic.png", "the image") as staged:
        if tiled:
            _, covered = write_mosaic_png(staged, frames, G, cam.width, cam.height, mask=mask,
                                          blend=blend, canvas=canvas, gains=gains, plan=plan,
                                          progress=progress, highlights=highlights)
        else:
            rendered = render_mosaic(frames, G, cam.width, cam.height, mask=mask,
                                     blend=blend, max_pixels=canvas.max_pixels, gains=gains,
                                     plan=plan, progress=progress, highlights=highlights)
            if canvas.alpha:  # (OpenCV's PNG encoder takes no grey + alpha)
                write_png(staged, np.dstack(
                    [rendered.image, rendered.covered.view(np.uint8) * np.uint8(255)]))
            else:
                w.write_image("mosaic.png", rendered.image)
            covered = float(rendered.covered.mean())
    highlights = None  # (not shared with the video's incremental canvas)
    timings["compose_mosaic"] = time.perf_counter() - t0
    info = {
        "file": "mosaic.png",
        "blend": blend.blend,
        "border_px": blend.border_px,
        "gain_compensation": blend.gain_compensation,
        "mask_specular": bool(blend.mask_specular),
        # frames undistorted first (camera.yaml's distortion_coefficients)
        "lens_undistorted": frames is not dataset.frames,
        "width": plan.width,
        "height": plan.height,
        "origin_reference_px": [plan.x0, plan.y0],  # mosaic pixel (0, 0) in frame 0's pixels
        "tiled": tiled,
        "covered_fraction": covered,
        "alpha": bool(canvas.alpha),  # an alpha channel: 255 where covered
        "frames_shown": int(plan.use.sum()),
        "skipped_frames": skipped_frames(plan.skipped),
    }
    if gains is not None:
        info["gains"] = gains.tolist()
    outputs = {"mosaic": info, "plan": plan, "video": None}
    if video is not None:
        t0 = time.perf_counter()
        target = Path(video)
        # Inside OUT or not, the video goes through the atomic writer with everything else.
        if is_under(target, out):
            path = w.path(str(target.resolve().relative_to(out.resolve())))
        else:
            path = w.external_path(target)
        fps = playback_rate(dataset.timestamps)
        try:
            n = write_creation_video(path, frames, G, cam.width, cam.height,
                                     (plan.x0, plan.y0, plan.x1, plan.y1), use=plan.use,
                                     mask=mask, blend=blend, fps=fps, gains=gains,
                                     frame_ids=ids, progress=progress)
        except OSError as exc:  # named by the user's path, not the staged one
            if exc.filename != str(path):
                raise
            raise OSError(exc.errno, exc.strerror, str(target)) from None
        timings["video"] = time.perf_counter() - t0
        outputs["video"] = str(target)
        info["video"] = {"file": str(target), "path": str(target.resolve()), "frames": n,
                         "fps": fps,
                         # multiband needs every frame: the video shows the growing linear blend
                         "blend": "linear" if blend.blend == "multiband" else blend.blend}
    return outputs


def write_run_report(w, dataset, method: str, result, G: np.ndarray, outputs: dict,
                     timings: dict[str, float]) -> None:
    """report.md + plots/ for one run (see evaluation.report)."""
    from fusedmosaic.evaluation.report import (
        RunRecord,
        plane_history_per_frame,
        truth_from_dataset,
        write_report,
    )

    plan, mosaic = outputs["plan"], outputs["mosaic"]
    if plan is None:
        note = f"Mosaic not written: {mosaic['skipped']}"
    else:
        note = (f"Mosaic: {mosaic['width']} x {mosaic['height']} px, {mosaic['blend']} blending"
                f"{', tiled' if mosaic['tiled'] else ''}; its pixel (0, 0) is reference pixel "
                f"{tuple(mosaic['origin_reference_px'])}.")
    run = RunRecord(method, G, poses=result.poses,
                    plane=None if result.plane is None else np.asarray(result.plane, float),
                    plane_history=plane_history_per_frame(result.details.get("plane_history"),
                                                          len(G)),
                    timings=dict(timings),
                    # every frame left out (black, dead-reckoned, unreadable ones too, as
                    # report.json lists them; the canvas's own screening alone left report.md
                    # silent on 4 black frames; review)
                    skipped={} if plan is None else {int(k): why for k, why in
                                                    mosaic["skipped_frames"].items()},
                    output=".")
    directory = w.path("report.md").parent
    video = outputs.get("video")
    if video is not None:
        try:
            video = str(Path(video).resolve().relative_to(Path(w.out_dir).resolve()))
        except ValueError:
            video = str(Path(video).resolve())
    notes = [f"**Warning:** {text}" for text in result.details.get("warnings", [])] + [note]
    write_report(directory, [run], truth_from_dataset(dataset),
                 title=f"fusedmosaic run: {method} ({methods.REGISTRY[method][1]})",
                 mosaic=None if plan is None else "mosaic.png", video=video, notes=notes)


WARNING_LINE = "  warning "  # the summary's lines of the checks after the fusion


def _summary(method: str, G: np.ndarray, out: Path, report_json: dict, outputs: dict,
             report: bool, shown: list[str] = ()) -> str:
    """The terminal's summary of a run; report.json's warnings among its lines, but for those in
    `shown` (already shown as Python warnings while the run went on)."""
    placed = int(np.isfinite(G).all(axis=(1, 2)).sum())
    dead = sum(s == "dead-reckoned" for s in report_json.get("frame_status", []))
    # (dead-reckoned frames have homographies but no anchor: said apart; 'placed 100/100'
    # then '48 frame(s) left out' read as a contradiction; audit)
    msg = (f"{method}: placed {placed}/{len(G)} frames"
           + (f" ({dead} of them dead-reckoned)" if dead else "") + f" -> {out}")
    if report_json.get("metrics_note"):  # (metrics null: not scored, and why)
        msg += f" (e_M {report_json['metrics_note']})"
    elif "metrics" in report_json:
        e_M = report_json["metrics"]["e_M_px"]
        scored = report_json["metrics"]["frames_scored"]
        if scored == 0:
            msg += " (e_M undefined: no placed frame has a ground-truth homography)"
        elif scored < len(G):  # e_M is over the frames placed and with a ground truth: say
            # so, e.g. 0.000 for the reference alone when a pairwise chain breaks at frame 1
            msg += f" (e_M = {e_M:.3f} px over {scored} of {len(G)} frames)"
        else:
            msg += f" (e_M = {e_M:.3f} px)"
    m = outputs["mosaic"]
    if outputs["plan"] is None:  # (the canvas budget, or no frame left to compose: review 51
        # found the latter summed up as the former, sending the user to --max-canvas-pixels)
        lines = [msg, "  mosaic  not written" + (
            f": {m['skipped']}" if "skipped_frames" in m
            else " (above the canvas budget: see report.json)")]
    else:
        detail = f"{m['width']} x {m['height']} px, {m['blend']}"
        if m["tiled"]:
            detail += ", tiled"
        if m["skipped_frames"]:
            detail += f", {len(m['skipped_frames'])} frame(s) left out: see report.json"
        lines = [msg, f"  mosaic  {out / 'mosaic.png'}  ({detail})"]
    if report:
        lines.append(f"  report  {out / 'report.md'}  (plots in {out / 'plots'})")
    if report_json["frame_times"] != "frames.csv":  # where the tracker / robot times meet
        lines.append(f"  times   {report_json['frame_times']}")
    if "live" in report_json:
        live = report_json["live"]
        interval = live.get("frame_interval_ms")
        lines.append(f"  live    {live['frames_dropped']} frame(s) dropped; latency median "
                     f"{live['latency_ms']['median']:.1f} ms, p95 {live['latency_ms']['p95']:.1f}"
                     f" ms (frame interval "
                     f"{'n/a' if interval is None else f'{interval:.1f} ms'})")
        if "stopped_by" in live:
            lines.append(f"  session {live['frames_recorded']} frame(s) recorded, "
                         f"{live['frames_processed']} processed; stopped: {live['stopped_by']}")
    if outputs["video"] is not None:
        lines.append(f"  video   {outputs['video']}")
    lines += [f"{WARNING_LINE}{text}" for text in report_json.get("warnings", [])
              if text not in shown]
    return "\n".join(lines)


class HeardWarnings:
    """While entered, records the text of each UserWarning shown (each is still shown as
    before), for report.json: what a warning says about the inputs or their processing (a
    dataset numbered around a gap, 16-bit frames clipped, a camera.yaml key not known, a
    tracker file left out) qualifies the results, so it is kept with them, not only on a
    terminal. A warning that the filters make an error or ignore is not shown, so not
    recorded. Restores warnings.showwarning (and the filters) on exit."""

    def __init__(self):
        self.texts: list[str] = []
        self._state = warnings.catch_warnings()

    def __enter__(self) -> HeardWarnings:
        self._state.__enter__()
        show = warnings.showwarning

        def record(message, category, filename, lineno, file=None, line=None):
            if issubclass(category, UserWarning) and str(message) not in self.texts:
                self.texts.append(str(message))
            show(message, category, filename, lineno, file, line)

        warnings.showwarning = record
        return self

    def __exit__(self, *exc) -> None:
        self._state.__exit__(*exc)

    def add_to(self, details: dict) -> None:
        """The warnings heard so far at the head of details["warnings"] (those it has not)."""
        add_warnings(details, self.texts)


def add_warnings(details: dict, texts) -> None:
    """`texts` at the head of details["warnings"], but those it has (once each)."""
    known = details.get("warnings", [])
    new = [t for t in dict.fromkeys(texts) if t not in known]
    if new:
        details["warnings"] = new + known


def add_streamed_checks(result: methods.MethodResult, dataset, method: str, options) -> None:
    """The checks after the fusion (estimation.consistency) for a result that has not had
    them: lba-emt (tracker) and kalman-robot (robot) streamed live or replayed (the offline
    methods add them themselves)."""
    details = result.details
    if method == "kalman-robot" and "robot_agreement" not in details \
            and "trajectories_px" in details and dataset.robot is not None:
        from fusedmosaic.estimation.consistency import add_robot_agreement

        add_robot_agreement(details, str(dataset.root / dataset.robot_file),
                            result.parameters.get("pixel_size_um"), dataset.frame_times)
        return
    if (method != "lba-emt" or "tracker_agreement" in details or result.poses is None
            or dataset.cam_from_world is None):
        return
    from fusedmosaic.estimation.consistency import add_tracker_agreement

    add_tracker_agreement(details, result.poses, dataset, result.plane,
                          getattr(options, "emt_sigma", None),
                          getattr(options, "motion_sigma", None))


class _EndingGuard:
    """From start() (a live session's loop over) until stop(): a first SIGINT calls tell()
    and is otherwise ignored, a second raises KeyboardInterrupt: the session's estimates exist
    nowhere else (an offline re-run drops no frame), and one Ctrl-C after the sender closed lost
    them with 'interrupted' and nothing more (audit). Only in the main thread; a SIGINT the
    process ignores (nohup, a background job) stays ignored."""

    def __init__(self, tell) -> None:
        self.tell, self.heard, self.previous, self.active = tell, 0, None, False

    def start(self) -> None:
        if self.active or threading.current_thread() is not threading.main_thread():
            return
        current = signal.getsignal(signal.SIGINT)
        if current in (signal.SIG_IGN, None):
            return
        self.previous, self.active = current, True
        signal.signal(signal.SIGINT, self._handler)

    def _handler(self, signum, frame) -> None:
        self.heard += 1
        if self.heard > 1:
            raise KeyboardInterrupt
        try:  # (a caller's say, or warnings made errors, must not interrupt instead)
            self.tell()
        except Exception:  # noqa: BLE001
            pass

    def stop(self) -> None:
        if self.active:
            signal.signal(signal.SIGINT, self.previous)
            self.active = False


def check_live_limits(max_frames, duration_s, frame_timeout_s,
                      names: dict[str, str] | None = None) -> None:
    """ValueError unless each limit of a live session is None or a number > 0, and
    frame_timeout_s at most MAX_FRAME_TIMEOUT_S; `names` maps the parameters to what the message
    calls them (the CLI's flags)."""
    names = names or {}
    for name, value in (("max_frames", max_frames), ("duration_s", duration_s),
                        ("frame_timeout_s", frame_timeout_s)):
        what = names.get(name, f"live session: {name}")
        if value is not None and not (np.isfinite(value) and value > 0):
            raise ValueError(f"{what} must be a number > 0, got {value}")
        if name == "frame_timeout_s" and value is not None and value > MAX_FRAME_TIMEOUT_S:
            raise ValueError(f"{what} must be at most {MAX_FRAME_TIMEOUT_S:.0f} s (11.6 days, "
                             f"as good as no timeout), got {value:g}")


def _live_view(camera, method: str, record: Path, preview, serve_mosaic,
               interval_s: float, say, blend=None, max_pixels: int | None = None, warn=None):
    """(LiveMosaicView, IgtlImageServer or None) for run_igtl, checked before connecting; the
    preview's folder is created (as an output folder is); say(text) is told a free port taken
    (--serve-mosaic 0). blend: run_igtl's, for its mask_specular (None: the method's).
    max_pixels: the view's canvas budget, run_igtl's canvas's (--max-canvas-pixels; None:
    CanvasOptions'), as the final mosaic's; a published image is shrunk above
    live_view.VIEW_MAX_PIXELS. warn(text): told once if the view is published shrunk."""
    from fusedmosaic.compositing import CanvasOptions
    from fusedmosaic.compositing.live_view import LiveMosaicView
    from fusedmosaic.io.igtl import IgtlImageServer
    from fusedmosaic.io.output import check_output_dir

    if preview is not None:
        preview = Path(preview)
        if preview.is_dir():
            raise ValueError(f"{preview}: is a folder; the preview is a PNG file")
        if is_under(preview, record):
            raise ValueError(f"{preview}: the preview must not be inside the recording {record}")
    LiveMosaicView.check_preview(preview)
    if preview is not None:
        check_output_dir(preview.parent, "preview's folder")
        try:
            preview.parent.mkdir(exist_ok=True)
        except OSError as exc:
            raise ValueError(f"{preview}: cannot create the preview's folder "
                             f"({exc.strerror or exc})") from None
    lens, mask = composing_lens(camera, undistorted=method == "lba-emt")
    server = None if serve_mosaic is None else IgtlImageServer(serve_mosaic)
    try:
        chosen = None if blend is None or isinstance(blend, str) else blend.mask_specular
        # a pCLE frame's pixel is a known size on the tissue (translation methods): the
        # mosaic served to Slicer is then in true mm; else 1 mm per reference pixel
        size_um = camera.pixel_size_um if method != "lba-emt" else None
        view = LiveMosaicView(camera.width, camera.height, mask=mask, lens=lens,
                              preview=preview, server=server, interval_s=interval_s,
                              mask_specular=method == "lba-emt" if chosen is None else chosen,
                              pixel_size_mm=None if size_um is None else size_um / 1000.0,
                              # (a fixed 50 Mpx stopped the view's publications for the rest
                              # of a session whose bounding box passed it; review 46)
                              max_pixels=(CanvasOptions().max_pixels if max_pixels is None
                                          else max_pixels),
                              notify=warn)
    except BaseException:
        if server is not None:
            server.close()
        raise
    if server is not None and server.requested_port == 0:
        say(f"live: the mosaic is served on {server.address} (OpenIGTLink IMAGE "
            f"'{server.device_name}'; --serve-mosaic 0 took this free port)")
    return view, server


def _refusal_reason(message: str) -> str:
    """A refused frame's problem without what changes from frame to frame (its number, its
    timestamps), so that report.json counts frames per reason (bounded however long the
    session)."""
    reason = re.sub(r"^frame \d+: ", "", message)
    if reason.startswith("timestamp "):
        reason = re.sub(r"^timestamp \S+ ", "timestamp ", reason)
        reason = re.sub(r" \(previous frame's [^)]*\)", " (a repeated or earlier timestamp)",
                        reason)
        reason = re.sub(r"is \S+ s after the previous frame's \([^)]*\), more than ([^;]*)",
                        r"more than \1 after the previous frame's", reason)
    return reason


def _pixels(dtype) -> str:
    """'8-bit' / '16-bit' for a live frame's pixel type."""
    return f"{np.dtype(dtype).itemsize * 8}-bit"


def _live_image_problem(image: np.ndarray, camera,
                        first: tuple | None) -> tuple[str, str | None] | None:
    """Why a received frame (io.igtl: alpha dropped) is refused, None if it is not: its pixel
    type, layout, size against camera.yaml's, or its kind (gray / colour, 8 / 16-bit) against
    the first frame accepted, `first` (ndim, dtype): a recording is all one kind. Returned as
    (the kind of problem, this frame's figures or None): report.json counts frames per kind,
    and a kind holds nothing that changes from frame to frame. A stream changing size made a
    kind per size, each told and counted apart: 100 in 100 frames (review). (A pixel type
    stays in its kind's text: pyigtl decodes eight.)"""
    if image.dtype not in (np.uint8, np.uint16):
        return (f"a {image.dtype} image, expected 8- or 16-bit unsigned pixels (uint8, uint16)",
                None)
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        return ("an image neither gray (rows x columns) nor colour (rows x columns x 3, or 4 "
                "with alpha)", f"shape {'x'.join(map(str, image.shape))}")
    if image.shape[:2] != (camera.height, camera.width):
        return (f"an image of another size than camera.yaml's {camera.width}x{camera.height} "
                "(width x height)", f"a {image.shape[1]}x{image.shape[0]} image")
    if first is None:
        return None
    ndim, dtype = first
    if image.ndim != ndim:
        return (f"a {'colour' if image.ndim == 3 else 'gray'} image after "
                f"{'colour' if ndim == 3 else 'gray'} ones (a recording is one or the other)",
                None)
    if image.dtype != dtype:
        return (f"a {_pixels(image.dtype)} image after {_pixels(dtype)} ones (a "
                "recording is all 8-bit or all 16-bit)", None)
    return None


def check_bit_depth(bits, name: str = "bit depth (--bit-depth)") -> int | None:
    """None, or the bit depth in use a live session's 16-bit frames are taken as: an integer
    8..16 (ValueError otherwise)."""
    if bits is None:
        return None
    if isinstance(bits, bool) or not isinstance(bits, (int, np.integer)) or not 8 <= bits <= 16:
        raise ValueError(f"{name}: must be an integer in 8..16 (the bits the 16-bit frames' "
                         f"data uses, e.g. 12 for a 12-bit sensor), got {bits!r}")
    return int(bits)


class _LiveScale:
    """A live session's 16-bit frames in 8 bits on one scale (as offline, io.video.FrameSource:
    no flicker, the registrations see one contrast): v -> round(v * 255 / (2^b - 1)), b the bit
    depth given (--bit-depth; a frame above 2^b - 1 is clipped to 255, told once, counted in
    `clipped`), else the smallest in 8..16 holding the largest value seen so far: a stream
    cannot be sampled ahead, so b starts from the first 16-bit frame and is raised, told once,
    when a frame exceeds it (a dim first frame, the probe not yet in contact, took 8 bits and
    clipped 19 of 20 12-bit frames for the whole session; review). NCC is insensitive to the
    step in contrast; the final outputs are composed on the recording's sampled scale."""

    def __init__(self, bits: int | None) -> None:
        self.bits, self.given = bits, bits is not None
        self.chosen_by = "--bit-depth" if self.given else None
        self.clipped = 0  # 16-bit frames with values above the range (clipped; --bit-depth)
        self.raised: list[tuple[int, int]] = []  # (received frame, bits) where b was raised
        self.converted = 0  # 16-bit frames converted

    def convert(self, image: np.ndarray, received: int, recorded: int, warn) -> np.ndarray:
        from fusedmosaic.io.video import bits_holding, to_8_bits

        peak = int(image.max())
        if self.bits is None:
            self.bits = bits_holding(peak)
            self.chosen_by = f"the first 16-bit frame, received frame {received}"
        self.converted += 1
        full = (1 << self.bits) - 1
        if peak > full and not self.given:
            if not self.raised:
                warn(f"live session: received frame {received} (recorded as frame {recorded}) "
                     f"has 16-bit values up to {peak}, above the {self.bits}-bit range (0-"
                     f"{full}) taken from {self.chosen_by}: the live scale is raised to "
                     f"{bits_holding(peak)} bits from this frame on (the frames before look "
                     "brighter in the live view; the final outputs are composed on one scale "
                     "sampled over the recording; further raises are counted, report.json live "
                     "frame_bits_raised). Give --bit-depth B (the bits the sensor's data uses) "
                     "to fix the scale from the start")
            self.bits = bits_holding(peak)
            self.raised.append((received, self.bits))
        elif peak > full:
            self.clipped += 1
            if self.clipped == 1:
                warn(f"live session: received frame {received} (recorded as frame {recorded}) "
                     f"has 16-bit values up to {peak}, above the {self.bits}-bit range "
                     f"(0-{full}) given by --bit-depth: clipped to 255 in the live mosaic (the "
                     "recording keeps the frames as received); further such frames are clipped "
                     "without a warning (report.json live frames_clipped). Give --bit-depth "
                     f"{bits_holding(peak)} (the bits the sensor's data uses, 16 at most)")
        return to_8_bits(image, self.bits)

    def details(self) -> dict:
        """report.json live "source": the scale of the 16-bit frames (none: {})."""
        if not self.converted:
            return {}
        return {"frame_bits_in_use": self.bits, "frame_bits_chosen_by": self.chosen_by,
                "frame_bits_raised": [{"received_frame": k, "bits": b} for k, b in self.raised],
                "frames_clipped": self.clipped}


class _ReceiveBacklog:
    """How far a live session's receiver fell behind the sender: each accepted frame's
    (arrival - stamp) less the least one so far (since the session began, or the sender's clock
    last jumped), which takes out the clocks' offset and the transport's delay: about 0 while
    frames are read as they are sent; it grows while they wait in the socket or the sender (a
    receiver held up), by the clocks' relative drift too (ppm), and for a sender stamping at
    another pace than real time (a replay). The latency figures start at arrival and cannot
    show it. The least so far, not that of the first frames: PLUS Server starts a new client at
    its oldest buffered frames, seconds old, sent as fast as it can (vtkPlusOpenIGTLinkServer's
    SendLatestFramesToClients), and a baseline taken from them hid a later backlog as long
    (review: a real 3 s backlog read max 0.0, end -0.79; now 3.0). Frames read behind from the
    start (that burst) read 0 until a frame comes sooner.
    report.json live source receive_backlog_s (end: the last frame's, max)."""

    def __init__(self) -> None:
        self.base, self.end, self.max = np.inf, 0.0, 0.0
        self.frames = 0

    def add(self, stamp: float, arrival: float) -> None:
        lag = arrival - stamp
        self.base = min(self.base, lag)
        self.frames += 1
        self.end = lag - self.base
        self.max = max(self.max, self.end)

    def restart(self) -> None:
        """The sender's clock jumped (taken as its clock from there): a new baseline."""
        self.base = np.inf

    def details(self) -> dict | None:
        return (None if not self.frames else
                {"end": round(self.end, 3), "max": round(self.max, 3)})


def run_igtl(address: str, out: str | Path, *, record: str | Path, camera,
             transform_device: str | None, image_device: str | None = None, hand_eye=None,
             rgb: bool = True, options=None, max_frames: int | None = None,
             duration_s: float | None = None, frame_timeout_s: float = 5.0,
             overwrite_record: bool = False, progress: bool = True, blend=None, canvas=None,
             video: str | Path | None = None, report: bool = True,
             method: str = "lba-emt", tracker_time_offset: float = 0.0,
             preview: str | Path | None = None, serve_mosaic: str | None = None,
             view_interval_s: float = 1.0, say=None, warn=None,
             bit_depth: int | None = None) -> str:
    """A live session on an OpenIGTLink source (io.igtl: e.g. PLUS Server streaming a tracked
    endoscope), lba-emt, or kalman-robot with a robot streaming the probe position (the
    transform's translation, mm, in the image axes; the camera needs pixel_size_um; recorded
    into robot.csv), or the pCLE baselines ncc (the images alone: samples recorded, not used)
    and robot: frames and tracker poses are received as they come, each frame is
    mosaicked as soon as the previous one is done (frames arriving meanwhile are dropped but
    recorded), until the sender closes the stream, max_frames frames were recorded (no more are),
    duration_s passed or Ctrl-C. Every received frame and tracker sample is recorded into the
    dataset folder `record` (re-runnable offline with any method; it grows as a readable dataset
    in a staging folder, and a session killed outright is recovered by the next one in that
    folder: io.recorder), but for frames arriving while the recorder's queue is full (writing
    behind the stream): those are neither recorded nor processed, so that the receiver never
    waits for the disk (told at the first, counted: report.json live frames_not_recorded);
    then the outputs of the live estimates go to `out` as `run` writes
    them (report.json "live": drops, latency, why the session stopped). camera / hand_eye: a
    Camera / 4x4 or the path of camera.yaml / hand_eye.txt. tracker_time_offset: s, the
    tracker's (robot's) clock ahead of the video's (calibrate's calibration.json
    "tracker_time_offset"): the frame at t takes the sample at t + offset, and the samples are
    recorded on the video's clock (stamped - offset), as `import` writes them, so that the
    recording re-runs without it. preview (a .png path; its folder is created) / serve_mosaic
    ([HOST:]PORT, [IPV6]:PORT): the mosaic as it grows, from each frame's final placement
    (compositing.live_view), replaced atomically in that file and / or sent as OpenIGTLink IMAGE
    "Mosaic" to every client of a server listening there (e.g. 3D Slicer), at most every
    view_interval_s; report.json "live" "view". say(text): tells the user what they need during
    the session (the port --serve-mosaic 0 took); None: as a warning. warn(text): what went
    wrong during it (frames refused, a tracker on another clock); None: say. Progress notes
    (the session ended, the outputs being written) go to a given say only. A start that fails
    leaves no folder behind. Frames are 8- or 16-bit, gray or colour (an alpha channel is
    dropped), all alike (a frame of another kind than the first accepted is refused, as one of
    another size than camera.yaml's). 16-bit frames are recorded as received (16-bit PNG) and
    mosaicked live in 8 bits (_LiveScale): as data of bit_depth bits (8..16; e.g. 12 for a
    12-bit sensor; values above clipped, told once), by default of the bits the largest value
    so far needs (raised when a frame exceeds it, told once); report.json live "source". The
    final outputs are composed as offline, on the recording's sampled scale
    ("frame_bits_in_use"). Returns the terminal summary."""
    from fusedmosaic.estimation.live import (
        check_live_method,
        live_session,
        session_result,
        takes_samples,
    )
    from fusedmosaic.io.calibration import Camera, read_camera_yaml
    from fusedmosaic.io.igtl import (
        MAX_PROBLEM_KINDS,
        OTHER_PROBLEMS,
        STAMP_JUMP_CONFIRM,
        IgtlSource,
        StampJumps,
        format_address,
    )
    from fusedmosaic.io.recorder import DatasetRecorder
    from fusedmosaic.io.tracking import check_stream_timestamp, check_time_offset, hand_eye_matrix

    check_live_method(method)
    if transform_device is None and takes_samples(method):
        raise ValueError(f"live session: {method} needs the device of the "
                         f"{'tracker' if method == 'lba-emt' else 'robot'} (--transform)")
    offset = check_time_offset(tracker_time_offset)
    inform = say if say is not None else (lambda text: None)
    if say is None:
        say = lambda text: warnings.warn(text, stacklevel=3)  # noqa: E731
    tell = say if warn is None else warn
    told: list[str] = []  # what went wrong during the session: report.json warnings too

    def warn(text: str) -> None:
        if text not in told:
            told.append(text)
        tell(text)

    if not isinstance(camera, Camera):
        camera = read_camera_yaml(camera)
    if method == "lba-emt":
        camera.require_camera_matrix(method)
    else:
        if method in NEEDS_ROBOT:  # (ncc, as offline, needs no pixel size)
            camera.require_pixel_size(method)
        if hand_eye is not None:
            raise ValueError("live session: a hand-eye applies to lba-emt (a tracked camera), "
                             f"not to {method}")
    if hand_eye is not None:
        hand_eye = hand_eye_matrix(hand_eye)
    check_live_limits(max_frames, duration_s, frame_timeout_s)
    scale = _LiveScale(check_bit_depth(bit_depth))
    if not (isinstance(view_interval_s, (int, float)) and np.isfinite(view_interval_s)
            and view_interval_s >= 0):  # with or without a view
        raise ValueError(f"view interval (--view-interval): must be >= 0 s, got "
                         f"{view_interval_s}")
    out, record = Path(out), Path(record)
    if is_under(out, record, or_equal=True):  # the recording does not exist yet
        raise ValueError(f"{out}: the output folder must not be the recording folder or inside "
                         f"it ({record})")
    if is_under(record, out, or_equal=True):
        raise ValueError(f"{record}: the recording must not be inside the output folder {out}")
    if video is not None:
        from fusedmosaic.compositing.video import check_video_suffix

        check_video_suffix(video)
        check_video_destination(Path(video), out, record)
    if preview is not None:
        check_preview_destination(Path(preview), out)
    check_compositing_options(blend, canvas, camera=camera, method=method)
    from fusedmosaic.io.output import check_output_dir

    # what a failed start removes again (run_igtl leaves nothing behind)
    created = [folder for path in (out, record, *(() if preview is None else (Path(preview),)))
               for folder in missing_folders(path)]
    view, server, recorder, src = None, None, None, None
    fov = camera.fov_mask()  # (is_blank: the frames arrive raw)

    def on_final(index, image, r) -> None:  # given to the session only with a view
        if (image is not None and np.isfinite(r.homography).all()
                and r.status != "dead-reckoned"  # as compose_outputs: not drawn
                and not is_blank(image, r.status, fov)):
            view.add(image, r.homography)

    rejected: dict[str, int] = {}  # why (its kind) -> frames refused
    first_refused: dict[str, int] = {}  # why -> the first such frame (the source's count)
    refused_details: dict[str, str] = {}  # why -> the first such frame's figures (its size)
    after_limit = 0  # frames received once max_frames were recorded (not recorded)
    not_recorded: list[int] = []  # received frames the recorder had no room for (the first)
    backlog = _ReceiveBacklog()
    accepting, first, last_time = True, None, -np.inf  # first: (ndim, dtype) of the first frame
    frame_jumps = StampJumps()  # frames stamped far ahead of the stream: refused as glitches
    device = "tracker" if method == "lba-emt" else "robot"
    latest_sample: list[float] = []  # [stamp on the video's clock, time.monotonic() heard]
    clocks_told = False

    def warn_from_receiver(text: str) -> None:
        """warn(text) on the receiver thread: a caller's warn, or warnings made errors, must
        not end the stream (what it says is counted in report.json whatever happens)."""
        try:
            warn(text)
        except Exception:  # noqa: BLE001
            pass

    def on_frame(frame) -> bool:  # receiver thread: what is recorded and offered to the loop
        nonlocal first, last_time, after_limit
        image = frame.image
        if not accepting:
            return False
        if max_frames is not None and len(recorder.timestamps) >= max_frames:
            after_limit += 1
            return False
        # pixel type, layout, size, kind against the first frame's
        problem, detail = _live_image_problem(image, camera, first) or (None, None)
        if problem is None and frame.timestamp == 0:  # (after stamped ones: io.igtl passes
            # it on; accepted after refused ones, it made every later frame 'a day after' it)
            problem = "no timestamp (0): the sender did not stamp it"
        elif problem is None:
            try:
                t = check_stream_timestamp(frame.index, frame.timestamp, last_time)
                jumped = len(frame_jumps.jumps)
                problem = frame_jumps.check(t, frame.arrival)
                if problem is None:
                    last_time = t
                    frame_jumps.accepted(t, frame.arrival)
                    if len(frame_jumps.jumps) > jumped:
                        backlog.restart()
                        warn_from_receiver(
                            f"live session: the sender's frame stamps jumped "
                            f"{frame_jumps.jumps[-1]:.3g} s ahead of the stream at received "
                            f"frame {frame.index}, {STAMP_JUMP_CONFIRM} frames in a row: taken "
                            "as its clock from there (the frames before it in the jump were "
                            "refused)")
            except ValueError as exc:
                problem = _refusal_reason(str(exc))
                if "does not increase" in problem and (
                        back := frame_jumps.behind(float(frame.timestamp), frame.arrival)):
                    warn_from_receiver(
                        f"live session: the sender's frame stamps stepped {back:.3g} s back at "
                        f"received frame {frame.index - STAMP_JUMP_CONFIRM + 1} "
                        f"({STAMP_JUMP_CONFIRM} frames in a row): its clock was set back? A "
                        "recording is in time order, so every frame stamped before the last "
                        "one recorded is refused: end the session and start a new one (another "
                        "--record) to go on")
        if problem is not None:
            if problem not in rejected and len(rejected) >= MAX_PROBLEM_KINDS:
                # (bounded however long the session, as io.igtl counts its problems)
                problem, detail = OTHER_PROBLEMS, problem + (f": {detail}" if detail else "")
            rejected[problem] = rejected.get(problem, 0) + 1
            if problem not in first_refused:  # told once per reason, then counted (a stream
                # changing size was refused frame after frame without a word; audit)
                first_refused[problem] = frame.index
                if detail is not None:
                    refused_details[problem] = detail
                warn_from_receiver(f"live session: received frame {frame.index} refused, "
                                   f"neither processed nor recorded: {problem}"
                                   f"{f': {detail}' if detail else ''}; such frames are "
                                   "counted (report.json live frames_refused)")
            return False
        if first is None and scale.given and image.dtype == np.uint8:
            warn_from_receiver(f"live session: --bit-depth {scale.bits} applies to 16-bit "
                               f"frames; received frame {frame.index} is 8-bit: the frames are "
                               "taken as they are")
        first = (image.ndim, image.dtype)
        received = frame.index
        backlog.add(frame.timestamp, frame.arrival)
        k = recorder.add_frame(image, frame.timestamp)  # as received (16-bit PNG); never waits
        if k is None:  # the recorder's queue is full: not processed either (the outputs are
            # composed on the recording), and the socket goes on being read (a receiver that
            # waited for the disk let the live view fall a minute behind; review)
            if not not_recorded:
                not_recorded.append(received)
                warn_from_receiver(
                    f"live session: received frame {received} neither recorded nor processed: "
                    f"{recorder.max_queued_bytes / 2**20:.3g} MiB of frames wait to be written "
                    "to the recording (writing cannot keep up with the stream: the disk, or the "
                    "CPU the live session leaves it); the live view stays live, and such frames "
                    "are counted (report.json live frames_not_recorded)")
            return False
        frame.index = k
        if image.dtype == np.uint16:  # the session mosaics 8 bits, on one scale
            frame.image = scale.convert(image, received, frame.index, warn_from_receiver)
        check_clocks(frame)
        return True

    def on_sample(sample) -> None:  # receiver thread
        recorder.add_sample(sample.timestamp - offset, sample.matrix if sample.valid else None)
        if sample.valid:
            latest_sample[:] = [sample.timestamp - offset, time.monotonic()]

    def check_clocks(frame) -> None:
        """Once: a frame stamped far from the tracker's samples still arriving (within 1 s)
        is on another clock, and gets no tracker pose (a tracker stamped from its own start,
        frames in epoch seconds: no word until the start-up failed 'to register pairs')."""
        nonlocal clocks_told
        if clocks_told or not latest_sample or time.monotonic() - latest_sample[1] > 1.0:
            return
        gap = frame.timestamp - latest_sample[0]
        if abs(gap) > CLOCK_MISMATCH_S and method != "ncc":  # (ncc uses no sample)
            clocks_told = True
            warn_from_receiver(f"live session: frame {frame.index} (recorded) is stamped "
                               f"{frame.timestamp:.3f} s, the {device}'s latest sample "
                               f"{latest_sample[0]:.3f} s ({gap:+.3f} s): "
                               f"{ONE_CLOCK.format(device)}")

    def other_images() -> str:
        """With refused frames: the other IMAGE devices heard (one heard first took the
        session, and the video's frames were ignored without a word; audit)."""
        others = sorted(d[len("IMAGE "):] for d in (src.ignored_devices if src else ())
                        if d.startswith("IMAGE "))
        if not rejected or not others:
            return ""
        how = "--image-device" if image_device is not None else "the first heard"
        return (f"; the session took the IMAGE device {src.image_device} ({how}) and ignored "
                f"{', '.join(others)}" + ("" if image_device is not None
                                          else ": choose one with --image-device"))

    def refused() -> str:
        return "".join(f"; frames refused: {n} x {why} ({first_text(why)})"
                       for why, n in rejected.items()) + other_images()

    def first_text(why: str) -> str:
        """'first: received frame 3, a 120x100 image': a refusal kind's first frame."""
        detail = refused_details.get(why)
        return f"first: received frame {first_refused[why]}" + (f", {detail}" if detail else "")

    def samples_heard(src) -> str:
        if src is None or transform_device is None:
            return ""
        span = recorder.valid_sample_span() if recorder is not None else None
        frames = list(recorder.timestamps) if recorder is not None else []
        if span is not None and frames and (span[0] > frames[-1] + CLOCK_MISMATCH_S
                                            or span[1] < frames[0] - CLOCK_MISMATCH_S):
            return (f"; the {src.valid_samples} valid {device} samples are stamped "
                    f"{span[0]:.3f}-{span[1]:.3f} s, the frames {frames[0]:.3f}-"
                    f"{frames[-1]:.3f} s: {ONE_CLOCK.format(device)}")
        if src.valid_samples:
            return ""
        heard = ", ".join(sorted(src.ignored_devices)) or "none"
        return (f"; no valid TRANSFORM or POSITION sample of {transform_device} arrived (other "
                f"devices heard: {heard}; see --transform)")

    guard = _EndingGuard(lambda: inform(
        "live session: ending, writing the outputs; Ctrl-C again abandons them"))
    try:
        try:
            check_output_dir(out, "output folder")
            # a user's file where an output goes is refused now, not once the session is over
            check_run_destination(out, report=report, video=video)
            if preview is not None or serve_mosaic is not None:  # before connecting
                view, server = _live_view(camera, method, record, preview, serve_mosaic,
                                          view_interval_s, say, blend,
                                          None if canvas is None else canvas.max_pixels,
                                          warn_from_receiver)
            # (the pCLE methods record the samples as robot positions: ncc's recording re-runs
            # with kalman-robot when a robot streamed)
            recorder = DatasetRecorder(record, camera, hand_eye, overwrite=overwrite_record,
                                       robot=method != "lba-emt", tracker_time_offset=offset,
                                       source=f"live session from {address}")
            # (said once OUT, the recording and the view are usable: before, it read as if a
            # refused OUT had connected; review 47)
            inform(f"live: connecting to {address} (Ctrl-C ends the session and writes the "
                   "outputs)")
            with IgtlSource(address, transform_device=transform_device, image_device=image_device,
                            rgb=rgb, orientation_required=method == "lba-emt",
                            on_frame=on_frame, on_sample=on_sample) as src:
                try:
                    with HeardWarnings() as heard:  # the estimation's, for report.json
                        session = live_session(src, camera, method=method, hand_eye=hand_eye,
                                               options=options,
                                               max_frames=max_frames, duration_s=duration_s,
                                               frame_timeout_s=frame_timeout_s,
                                               tracker_time_offset=offset,
                                               on_final=on_final if view is not None else None,
                                               on_loop_end=guard.start)
                finally:
                    accepting = False
                    if view is not None:  # the last frames drawn and published, then no more
                        view.close()
                    if server is not None:
                        server.close()
                dropped = [k for k in src.dropped if k not in session.finals]
                details = {"address": format_address(src.host, src.port),
                           "image_device": src.image_device,
                           "transform_device": transform_device,
                           # the recording's samples are on the video's clock (stamped - offset)
                           "tracker_time_offset_s": offset,
                           "frames_received": src.received,
                           # IMAGE messages failing their CRC64, dropped
                           "frames_corrupted": src.corrupted_frames,
                           # IMAGE messages that could not be decoded, dropped (why -> count)
                           "frames_undecodable": dict(src.undecodable_frames),
                           "frames_refused": dict(rejected),
                           "frames_refused_first": dict(first_refused),
                           # why -> the first such frame's figures (e.g. its size), where any
                           "frames_refused_details": dict(refused_details),
                           # frames the recorder had no room for: neither recorded nor processed
                           "frames_not_recorded": recorder.frames_not_recorded,
                           "frames_not_recorded_first": not_recorded[0] if not_recorded else None,
                           # s: how far reading fell behind the sender's stamps (_ReceiveBacklog)
                           "receive_backlog_s": backlog.details(),
                           # 16-bit frames: the session's 8-bit scale, frames clipped by it
                           **scale.details(),
                           "tracker_samples_valid": src.valid_samples,
                           "tracker_samples_invalid": dict(src.invalid_samples),
                           # kind -> the figures of its first sample (e.g. a quaternion's norm)
                           "tracker_samples_invalid_details": dict(src.invalid_sample_details),
                           # the sender's clock jumping ahead (s), taken (io.igtl.StampJumps)
                           "frame_clock_jumps_s": list(frame_jumps.jumps),
                           "sample_clock_jumps_s": src.sample_clock_jumps,
                           # ... and stepping back (s): the frames / samples after it refused
                           "frame_clock_steps_back_s": list(frame_jumps.steps_back),
                           "sample_clock_steps_back_s": src.sample_clock_steps_back,
                           "ignored_devices": sorted(src.ignored_devices)}
                if max_frames is not None:
                    details["frames_after_max_frames"] = after_limit
            if not session.processed:
                if session.stopped_by.startswith("interrupted"):  # the user's stop, not an input
                    raise KeyboardInterrupt  # error (it ended with exit 2, 'error: ...'; audit)
                raise ValueError(f"live session: no frame was processed ({session.stopped_by})")
            timestamps = list(recorder.timestamps)
            recorder.finish()  # SIGINT / SIGTERM / SIGHUP wait until the recording is in place
            details["frames_not_recorded"] = recorder.frames_not_recorded  # (final)
            # frames written as stored PNG while the compression was behind (lossless, larger)
            details["frames_recorded_uncompressed"] = recorder.frames_uncompressed
        except BaseException as exc:
            # the recording is the session's safety net: kept whenever it holds a frame (first:
            # closing the view may take a while)
            note = ""
            if recorder is not None and recorder.timestamps:
                said = recorder.finished  # exc is finish's own error, which says where
                try:
                    recorder.finish()  # (again: returns at once when done)
                    note = "" if said else (f"; the {recorder.frames_written} frame(s) received "
                                            f"are recorded in {record}")
                except ValueError as kept:  # kept all the same: the message says where
                    note = f"; {kept}"
            elif recorder is not None:
                recorder.abort()
            if view is not None:
                view.close()
            if server is not None:
                server.close()
            remove_created_folders(created)
            if isinstance(exc, (ValueError, OSError)):
                raise ValueError(f"{exc}{refused()}{samples_heard(src)}{note}") from None
            if note and isinstance(exc, KeyboardInterrupt):  # where the frames went
                inform(f"live session interrupted{note}")
            raise
        if jumps := details["sample_clock_jumps_s"]:
            warn(f"live session: the sender's {device} stamps jumped ahead of the stream "
                 f"{len(jumps)} time(s) (by {', '.join(f'{j:.3g}' for j in jumps[:5])} s), "
                 f"{STAMP_JUMP_CONFIRM} samples in a row each time: taken as its clock from "
                 "there (the samples before it in a jump were refused, report.json live "
                 "tracker_samples_invalid); the frames are paired with the samples by their "
                 "stamps, so check that the frames' stamps jumped alike")
        if steps := details["sample_clock_steps_back_s"]:
            warn(f"live session: the sender's {device} stamps stepped back {len(steps)} "
                 f"time(s) (by {', '.join(f'{b:.3g}' for b in steps[:5])} s): the samples "
                 "after a step are refused as going back in time (report.json live "
                 "tracker_samples_invalid)")
        result = session_result(session, timestamps, dropped, source_details=details,
                                method=method)
        add_warnings(result.details, [*told, *heard.texts])
        if view is not None:
            result.details["live"]["view"] = view.summary()
        if method == "robot" and not np.isfinite(result.homographies).all(axis=(1, 2)).any():
            # (robot places frames by their samples alone: it ended in the canvas's "no placed
            # frame to compose a mosaic from", naming neither the robot nor the cause)
            from fusedmosaic.estimation.translation import no_robot_sample_error

            raise no_robot_sample_error(
                f"live session from {address}", len(timestamps),
                f"none heard at or shortly before each frame{samples_heard(src)}; the "
                f"recording is kept in {record}")
        inform(f"live session ended ({session.stopped_by}): writing the outputs to {out} "
               "(Ctrl-C twice abandons them)")

        def rerun(where) -> str:
            return f"fusedmosaic run {record} --method {method} --out {where} --allow-untracked"

        try:
            summary = run_dataset(record, method, out, result=result, allow_untracked=True,
                                  progress=progress, blend=blend, canvas=canvas, video=video,
                                  report=report, shown_warnings=[*told, *heard.texts])
        except OutputsWrittenInterrupt:  # (the commit holds a Ctrl-C until it is done)
            inform(f"live session: interrupted once the outputs were in {out}")
            raise
        except KeyboardInterrupt:
            inform(f"live session: outputs abandoned; the recording is kept in {record} "
                   f"({rerun(out)})")
            raise
        except ValueError as exc:  # (e.g. a user's file put in OUT during the session)
            # another OUT helps only when OUT refused (the data refused: run it as it is)
            where = "OUT2" if str(exc).startswith((f"{out}/", f"{out}:")) else out
            raise ValueError(f"{exc}; the live outputs are not written, the recording is kept "
                             f"in {record} ({rerun(where)})") from None
        except OSError as exc:  # the file system refused: OSError still (exit 1), named
            kept = f"the recording is kept in {record} ({rerun(out)})"
            raise OSError(exc.errno, f"{exc.strerror or exc}; the live outputs are not "
                                     f"written, {kept}", exc.filename) from None
    finally:
        guard.stop()
    span = recorder.valid_sample_span()
    outside = span is None or timestamps[0] < span[0] or timestamps[-1] > span[1]
    stored = (f", {recorder.frames_uncompressed} of them stored uncompressed, the compression "
              "behind the stream" if recorder.frames_uncompressed else "")
    lines = [summary, f"  record  {record}  ({len(timestamps)} frames{stored}; re-run offline: "
                      f"fusedmosaic run {record} --method "
                      f"{'ba-emt' if method == 'lba-emt' else method} --out OUT2"
                      f"{' --allow-untracked' if outside else ''})"]
    if session.no_sample:
        lines.append(f"  {device:<7} {len(session.no_sample)} frame(s) without a usable sample"
                     f"{samples_heard(src)}")
    if recorder.frames_not_recorded:
        lines.append(f"  frames  {recorder.frames_not_recorded} received frame(s) neither "
                     "recorded nor processed: the recorder's "
                     f"{recorder.max_queued_bytes / 2**20:.3g} MiB queue was full, writing "
                     "behind the stream (first: received frame "
                     f"{not_recorded[0]}; report.json live frames_not_recorded)")
    if (lag := backlog.details()) is not None and lag["max"] >= 1.0:  # (below: jitter)
        lines.append(f"  frames  received up to {lag['max']:.1f} s later than their stamps "
                     f"say, against the first frames ({lag['end']:.1f} s at the end): read "
                     "behind the sender, or stamped at another pace than real time (the latency "
                     "figures count from receipt; report.json live receive_backlog_s)")
    if rejected:
        lines.append(f"  frames  {sum(rejected.values())} received frame(s) refused, neither "
                     "processed nor recorded" + "".join(
                         f"; {n} x {why} ({first_text(why)})"
                         for why, n in rejected.items()) + other_images())
    if scale.converted:
        lines.append(f"  frames  16-bit, mosaicked live as {scale.bits}-bit data (from "
                     f"{scale.chosen_by}"
                     + (f", raised {len(scale.raised)} time(s)" if scale.raised else "")
                     + "; report.json live source)"
                     + (f"; {scale.clipped} frame(s) above it clipped (--bit-depth sets it)"
                        if scale.clipped else ""))
    if src.corrupted_frames:
        lines.append(f"  frames  {src.corrupted_frames} IMAGE message(s) failed their CRC64 "
                     "(corrupted in transit) and were dropped (report.json live "
                     "frames_corrupted)")
    if src.undecodable_frames:
        lines.append(f"  frames  {sum(src.undecodable_frames.values())} IMAGE message(s) could "
                     "not be decoded and were dropped (" + "; ".join(
                         f"{n} x {why}" for why, n in src.undecodable_frames.items())
                     + "; report.json live frames_undecodable)")
    return "\n".join(lines)
