"""The dataset contract (design.md, "Dataset contract"): reader and writer.

A dataset is a folder with ``frames/*.png`` or ``video.*``, ``camera.yaml`` and optionally
``frames.csv``, ``tracking.csv``, ``hand_eye.txt``, ``robot.csv`` and ``ground_truth.csv``.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import tempfile
import warnings
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path, PurePath

import numpy as np

from fusedmosaic.io._table import check_increasing, format_float, read_table, write_table
from fusedmosaic.io.calibration import Camera, read_camera_yaml, write_camera_yaml
from fusedmosaic.io.homographies import read_homographies_csv, write_homographies_csv
from fusedmosaic.io.tracking import (
    MAX_FRAME_GAP_S,
    MAX_FRAME_SPACING_S,
    MAX_TIMESTAMP_S,
    SHIFTED,
    RobotSamples,
    TrackingSamples,
    _time,
    check_time_offset,
    check_timestamp_bound,
    interpolate_camera_poses,
    interpolate_robot,
    no_overlap_message,
    read_hand_eye,
    read_robot_csv,
    read_tracking_csv,
    shift_tracking,
    write_hand_eye,
    write_robot_csv,
    write_tracking_csv,
)
from fusedmosaic.io.video import FrameSource, write_frames


@dataclass(eq=False)
class Dataset:
    """A dataset read from disk; per-frame arrays are aligned with ``frame_ids``.

    hand_eye : (4, 4) sensor_from_camera (identity when hand_eye.txt is absent or left out).
    hand_eye_file : the hand_eye.txt read; None when absent or left out (hand_eye the identity).
    cam_from_world, pose_valid : EM-tracker camera poses interpolated at the frame times (N, 6)
        and their validity (N,); None without tracking.csv. Invalid frames have NaN poses.
    robot_xy_um, robot_valid : robot positions at the frame times (N, 2) µm and validity (N,).
    ground_truth : (N, 3, 3) frame -> reference homographies, NaN for unplaced frames.
    frame_times : where ``timestamps`` come from, for reports: "frames.csv", or without it
        "frame / R fps" and whose rate R is (given, the video's, the default).
    ignored : {file name: why it was left out} for files present but not read, only for a
        source the caller does not need (read_dataset's strict_tracking / strict_robot /
        strict_truth False): e.g. {"tracking.csv": "<path>: row 1: header is ..."}.
    """

    root: Path
    camera: Camera
    frames: FrameSource
    frame_ids: np.ndarray
    timestamps: np.ndarray
    hand_eye: np.ndarray
    tracking: TrackingSamples | None = None
    cam_from_world: np.ndarray | None = None
    pose_valid: np.ndarray | None = None
    robot: RobotSamples | None = None
    robot_xy_um: np.ndarray | None = None
    robot_valid: np.ndarray | None = None
    ground_truth: np.ndarray | None = None
    robot_file: str = "robot.csv"
    frame_times: str = "frames.csv"
    ignored: dict[str, str] = field(default_factory=dict)
    hand_eye_file: Path | None = None

    def __len__(self) -> int:
        return self.frame_ids.size

    def require_tracking(self, method: str) -> None:
        if self.tracking is None:
            raise ValueError(self._missing("tracking.csv", method, "EM tracker poses"))

    def require_robot(self, method: str) -> None:
        if self.robot is None:
            raise ValueError(self._missing(self.robot_file, method, "robot positions"))

    def _missing(self, name: str, method: str, what: str) -> str:
        needs = f"method {method!r} needs {what}"
        if name in self.ignored:  # read leniently and left out: the reason
            return f"{self.ignored[name]} ({needs})"
        return f"{self.root / name}: file not found; {needs}"

    def require_pixel_size(self, method: str) -> float:
        return self.camera.require_pixel_size(method)

    def require_camera_matrix(self, method: str) -> np.ndarray:
        return self.camera.require_camera_matrix(method)


def read_dataset(
    root: str | Path,
    *,
    fps: float | None = None,
    robot_file: str | None = "robot.csv",
    allow_untracked: bool = False,
    tracker_time_offset: float = 0.0,
    robot_time_offset: float = 0.0,
    strict_tracking: bool = True,
    strict_robot: bool = True,
    strict_truth: bool = True,
    blank_unreadable: bool = False,
) -> Dataset:
    """Read and check a dataset folder. Images are not loaded (only the first, to check its size).

    Row i of frames.csv (``frame,timestamp``, both strictly increasing) describes the i-th image
    in name order; without frames.csv, frame ids are 0..N-1, or for frame files numbered with
    gaps (missing files) their numbers from the first one's, over their step (see
    read_frame_times).

    fps : frame rate giving the timestamps when frames.csv is absent (timestamp = frame / fps);
        None: the video's own frame rate (FrameSource.frame_rate), else DEFAULT_FPS. A dataset
        with frames.csv takes its times from it: an fps given as well is refused (ValueError).
    robot_file : name of the robot positions file (e.g. robot_noisy.csv), inside the dataset
        folder; None: robot.csv.
    allow_untracked : flag frames outside the tracker's / robot's time span as invalid instead of
        raising.
    tracker_time_offset : s, the tracker's clock ahead of the video's: the sample for the frame
        at time t is the one tracking.csv stamps t + tracker_time_offset (calibrate measures
        it: calibration.json "tracker_time_offset"); Dataset.tracking is then on the video's
        clock.
    robot_time_offset : s, the robot's clock ahead of the video's, likewise for robot_file
        (Dataset.robot is then on the video's clock).
    strict_tracking, strict_robot : the caller uses the EM tracker (tracking.csv with
        hand_eye.txt) / the robot (robot_file): a present file that cannot be read, or whose
        times do not fit the frames', raises ValueError (the default). False, for a method that
        does not use it: such a file is left out (Dataset.tracking / .robot None) and the
        reason recorded in Dataset.ignored; a usable one is still read (reports plot it), its
        frames outside the samples' time span flagged invalid.
    strict_truth : a ground_truth.csv that cannot be read, or that lacks a row for a frame,
        raises ValueError (the default: the caller evaluates against it). False (run, whose
        scoring is a by-product): it is left out (Dataset.ground_truth None) and the reason
        recorded in Dataset.ignored.
    blank_unreadable : a frame that cannot be read (damaged PNG, undecodable video frame) is
        read as an all-zero image and recorded in Dataset.frames.unreadable instead of raising
        ValueError when read (FrameSource).

    The frame times are checked (read_frame_times): within |t| <= MAX_TIMESTAMP_S, at most
    MAX_FRAME_GAP_S apart, and MAX_FRAME_SPACING_S apart at most in the median (a video's
    timestamps in milliseconds otherwise pass for seconds).
    """
    root = Path(root)
    tracker_time_offset = check_time_offset(tracker_time_offset)
    robot_time_offset = check_time_offset(robot_time_offset, "robot_time_offset")
    if not root.is_dir():
        raise ValueError(f"{root}: dataset folder not found")
    robot_file = "robot.csv" if robot_file is None else robot_file
    check_robot_file_name(robot_file, root)
    _check_near_names(root, robot_file)
    camera = read_camera_yaml(root / "camera.yaml")
    frames = FrameSource.open(root, expected_size=camera.size, size_source=camera.source,
                              blank_unreadable=blank_unreadable)
    frames[0]  # size check of the first image; the rest are checked as they are read

    frame_ids, timestamps, frame_times = read_frame_times(
        root, frames, fps, max_spacing=MAX_FRAME_SPACING_S)
    dataset = Dataset(root, camera, frames, frame_ids, timestamps, np.eye(4),
                      robot_file=robot_file, frame_times=frame_times)
    _read_tracking(dataset, allow_untracked, tracker_time_offset, lenient=not strict_tracking)
    _read_robot(dataset, allow_untracked, robot_time_offset, lenient=not strict_robot)
    truth_path = root / "ground_truth.csv"
    if truth_path.exists():
        try:
            dataset.ground_truth = _align_ground_truth(truth_path, frame_ids,
                                                       explicit=frame_times == "frames.csv")
        except ValueError as error:
            if strict_truth:
                raise
            dataset.ignored[truth_path.name] = str(error)
    return dataset


def _read_tracking(dataset: Dataset, allow_untracked: bool, tracker_time_offset: float, *,
                   lenient: bool) -> None:
    """hand_eye.txt and tracking.csv, if present, into ``dataset`` (camera poses at its frame
    times); ValueError naming the file, or with ``lenient`` the file left out and the reason
    in dataset.ignored (read_dataset's strict_tracking False)."""
    root = dataset.root
    hand_eye_path, tracking_path = root / "hand_eye.txt", root / "tracking.csv"
    try:
        hand_eye = read_hand_eye(hand_eye_path) if hand_eye_path.exists() else None
    except ValueError as error:
        if not lenient:
            raise
        dataset.ignored["hand_eye.txt"] = str(error)
        if tracking_path.exists():
            dataset.ignored["tracking.csv"] = (f"{tracking_path}: left out with hand_eye.txt "
                                               "(the camera poses need both)")
        return
    if hand_eye is not None:
        dataset.hand_eye, dataset.hand_eye_file = hand_eye, hand_eye_path
    hand_eye = dataset.hand_eye
    if not tracking_path.exists():
        return
    try:
        tracking = read_tracking_csv(tracking_path)
        source = str(tracking_path)
        if tracker_time_offset:
            tracking = shift_tracking(tracking, tracker_time_offset)
            source += SHIFTED.format(-tracker_time_offset)
        poses, valid = interpolate_camera_poses(tracking, dataset.timestamps, hand_eye,
                                                allow_outside=allow_untracked or lenient,
                                                source=source)
        if lenient:
            _check_overlap(dataset.timestamps, tracking.timestamps[tracking.valid], source,
                           "tracker")
    except ValueError as error:
        if not lenient:
            raise
        dataset.ignored["tracking.csv"] = str(error)
        return
    dataset.tracking, dataset.cam_from_world, dataset.pose_valid = tracking, poses, valid


# The dataset's files read when present, and what reading it without one means: a file there
# with a near name (another case, '-' or ' ' for '_', an extension more: Windows hides a known
# one, hand_eye.txt.txt) is named in a warning (a misnamed hand_eye.txt was dropped without a
# word: poses.csv shifted by the hand-eye, the tracker warning blaming a file not there;
# review 47). frames/ and video.* get the same hint in FrameSource.open's error.
OPTIONAL_FILES = {
    "frames.csv": "the frames are timed by their number and a frame rate",
    "tracking.csv": "the dataset has no tracker poses",
    "hand_eye.txt": "the hand-eye transform is the identity (the camera at the tracker's sensor)",
}


def near_names(folder: Path, name: str) -> list[str]:
    """The files in ``folder`` (not hidden) whose name is nearly ``name``: the same but for the
    case, '-', ' ' or nothing for '_', a further extension or none, .yml for .yaml."""
    def plain(text: str) -> str:
        return re.sub(r"[-_ ]", "", text.lower())
    full, stem = plain(name), plain(PurePath(name).stem)
    alike = {full, stem} | ({stem + ".yml"} if full.endswith(".yaml") else set())
    try:
        entries = sorted(folder.iterdir())
    except OSError:
        return []
    return [p.name for p in entries if p.name != name and not p.name.startswith(".")
            and (plain(p.name) in alike or plain(p.name).startswith(full + "."))
            and p.is_file()]


def _check_near_names(root: Path, robot_file: str) -> None:
    """camera.yaml absent but a near name present: ValueError naming it; for the optional
    files and the robot file, a warning."""
    near = near_names(root, "camera.yaml") if not (root / "camera.yaml").exists() else []
    if near:
        raise ValueError(f"{root / 'camera.yaml'}: file not found, but {_named_files(near)} "
                         f"{_is_there(near)}: {_rename(near, 'camera.yaml')} (the names are "
                         "exact and case-sensitive)")
    optional = {**OPTIONAL_FILES, robot_file: "the dataset has no robot positions"}
    for name, without in optional.items():
        path = root / name
        near = [] if path.exists() else near_names(path.parent, path.name)
        if near:
            shown = [str(PurePath(name).with_name(n)) for n in near]  # (robot file: sub/...)
            warnings.warn(
                f"{path}: not found, but {_named_files(shown)} {_is_there(near)}; without "
                f"{name}, {without}: if {'it is' if len(near) == 1 else 'one of them is'} that "
                f"file, {_rename(near, name)} (the names are exact and case-sensitive)",
                stacklevel=3)


def _named_files(names: list[str]) -> str:
    return " and ".join(names) if len(names) <= 2 else f"{', '.join(names[:-1])} and {names[-1]}"


def _is_there(names: list[str]) -> str:
    return "is there" if len(names) == 1 else "are there"


def _rename(names: list[str], name: str) -> str:
    return f"rename {'it' if len(names) == 1 else 'that one'} to {name}"


def check_robot_file_name(robot_file: str, root: str | Path) -> None:
    """The robot file is named relative to the dataset folder and stays inside it (a dataset is
    one folder: reports and later runs find the file there): ValueError otherwise."""
    name = PurePath(robot_file) if isinstance(robot_file, (str, PurePath)) else None
    if name is None or not name.parts or name.is_absolute() or ".." in name.parts:
        raise ValueError(f"{root}: the robot file must be named relative to the dataset folder "
                         f"and stay inside it (e.g. robot_noisy.csv), got {robot_file!r}")


def _read_robot(dataset: Dataset, allow_untracked: bool, time_offset: float, *,
                lenient: bool) -> None:
    """The robot file, if present, into ``dataset`` (positions at its frame times, its clock
    time_offset s ahead of the video's); ValueError naming it, or with ``lenient`` the file
    left out and the reason in dataset.ignored."""
    path = dataset.root / dataset.robot_file
    if not path.exists():
        return
    try:
        robot = read_robot_csv(path)
        source = str(path)
        if time_offset:
            robot = RobotSamples(robot.timestamps - time_offset, robot.xy_um.copy())
            source += SHIFTED.format(-time_offset)
        xy, valid = interpolate_robot(robot, dataset.timestamps,
                                      allow_outside=allow_untracked or lenient, source=source)
        if lenient:
            _check_overlap(dataset.timestamps, robot.timestamps, source, "robot")
    except ValueError as error:
        if not lenient:
            raise
        dataset.ignored[dataset.robot_file] = str(error)
        return
    dataset.robot, dataset.robot_xy_um, dataset.robot_valid = robot, xy, valid


def _check_overlap(frame_times: np.ndarray, sample_times: np.ndarray, source: str,
                   what: str) -> None:
    """ValueError when no frame lies in the samples' time span (the clocks differ)."""
    t0, t1 = sample_times[0], sample_times[-1]
    if np.all((frame_times < t0) | (frame_times > t1)):
        raise ValueError(no_overlap_message(source, what, frame_times, t0, t1))


DEFAULT_FPS = 25.0  # frame rate of a dataset without frames.csv whose frames give none (PNGs)


def check_fps(fps, what: str = "fps") -> float:
    """The frame rate that gives timestamps without frames.csv: a finite number > 0 (inf would
    give every frame timestamp 0). ``what`` names it in the message (e.g. "--fps")."""
    if (
        isinstance(fps, bool)
        or not isinstance(fps, (int, float, np.number))
        or not (math.isfinite(fps) and fps > 0)
    ):
        raise ValueError(f"{what} must be positive and finite, got {fps}")
    return float(fps)


_NUMBERED_NAME = re.compile(r"^(\D*)(\d+)(\D*)$")  # one digit run: frame_000010.png


def _file_numbers(frames: FrameSource) -> np.ndarray | None:
    """The numbers of PNG frame files named with one number each and the same text around it
    (in name order), else None."""
    paths = frames.paths
    if paths is None or len(paths) < 2 or any(p.suffix.lower() != ".png" for p in paths):
        return None
    parts = [_NUMBERED_NAME.match(p.name[:-4]) for p in paths]  # (*.png, any case)
    if not all(parts) or len({(m.group(1), m.group(3)) for m in parts}) != 1:
        return None
    numbers = [int(m.group(2)) for m in parts]
    if max(numbers) >= 2**53:  # not frame numbers (and not exact as floats)
        return None
    return np.array(numbers, dtype=np.int64)


@dataclass(frozen=True, eq=False)
class FileNumbers:
    """The numbers of frame files named with one number each (``000010.png``,
    ``frame_10.png``: the same text around it in every name) that count frames in steps of
    ``step`` (k: every step a multiple of k, and k the median step, so that at least half the
    files are k apart; 1 for files numbered frame by frame, k > 1 for every k-th frame of a
    video named by its frame number), in name order; a step over k is a gap, files missing.
    Names without such numbers (img_a.png, timestamps whose steps vary) have none
    (FileNumbers.of: None).

    A dataset without frames.csv is timed by the numbers (read_frame_times: frame id = (file
    number - the first one's) / k, so one step of k is one frame interval and the frames after
    a gap keep their own times); with frames.csv and gaps, its frame ids must skip what the
    files skip (check_frame_ids)."""

    folder: Path
    names: tuple[str, ...]
    numbers: np.ndarray  # (N,) int64, strictly increasing
    gaps: tuple[int, ...]  # i: files missing between names[i - 1] and names[i]
    step: int = 1  # k: the numbers' step between consecutive frames

    @classmethod
    def of(cls, frames: FrameSource) -> FileNumbers | None:
        numbers = _file_numbers(frames)
        if numbers is None:
            return None
        steps = np.diff(numbers)
        # (equal numbers, f01.png and f1.png, FrameSource.open refuses; FrameSource(paths)
        # may hold them)
        if np.any(steps <= 0):
            return None
        # k: the steps' gcd, and their median, so the dominant step (a step of 2 with one of 4
        # where a file is missing: k 2, one gap; review 51 found it read as consecutive frames
        # without a word). Timestamps as names (steps of 33 and 34 ms) have gcd 1, median 33:
        # none.
        k = int(np.gcd.reduce(steps))
        if np.median(steps) != k:
            return None
        gaps = tuple(int(i) + 1 for i in np.flatnonzero(steps > k))
        paths = frames.paths
        return cls(paths[0].parent, tuple(p.name for p in paths), numbers, gaps, k)

    @property
    def frames(self) -> np.ndarray:
        """The frame ids the numbers give: (number - the first one's) / step."""
        return (self.numbers - self.numbers[0]) // self.step

    @property
    def missing(self) -> int:
        """The number of files missing in the gaps."""
        k = self.step
        return int(sum((self.numbers[i] - self.numbers[i - 1]) // k - 1 for i in self.gaps))

    def _name(self, number: int, like: str) -> str:
        """The file name ``number`` would have, written as ``like``."""
        m = _NUMBERED_NAME.match(like[:-4])
        digits = m.group(2)
        width = len(digits) if digits.startswith("0") or len(digits) > len(str(number)) else 0
        return f"{m.group(1)}{number:0{width}d}{m.group(3)}{like[-4:]}"

    def describe_gaps(self, limit: int = 3) -> str:
        """E.g. "000010.png missing between 000009.png and 000011.png"."""
        texts = []
        for i in self.gaps[:limit]:
            before, after = self.names[i - 1], self.names[i]
            k = self.step
            a, b = int(self.numbers[i - 1]) + k, int(self.numbers[i]) - k
            missing = (self._name(a, before) if a == b else
                       f"{self._name(a, before)}-{self._name(b, before)} "
                       f"({(b - a) // k + 1} files)")
            texts.append(f"{missing} missing between {before} and {after}")
        more = len(self.gaps) - limit
        if more > 0:
            texts.append(f"and {more} more gap{'s' if more > 1 else ''} ({self.missing} files "
                         "missing in all)")
        return "; ".join(texts)

    def check_frame_ids(self, path: Path, rows: np.ndarray, ids: np.ndarray) -> None:
        """frames.csv's rows pair with the files by position: with files missing, its frame
        ids that do not step as the files' numbers do may mean a frame file and a row went
        missing at different places (every row after pairs with the wrong image), or nothing
        (ids renumbered, a counter of its own): a warning naming frames.csv's row and the file
        (a review found such valid datasets refused)."""
        # files numbered in steps of k: ids stepping as the numbers (the video's frame numbers)
        # or as the frames (renumbered 0, 1, 2, ...) both skip what the files skip
        candidates = [ids[0] + (self.numbers - self.numbers[0])]
        if self.step > 1:
            candidates.insert(0, ids[0] + self.frames)
        expected = min(candidates, key=lambda e: int(np.count_nonzero(ids != e)))
        wrong = np.flatnonzero(ids != expected)
        if not wrong.size:
            return
        i = int(wrong[0])
        warnings.warn(
            f"{path}: row {rows[i]}: frame {ids[i]} goes with {self.folder / self.names[i]} "
            "(the rows go with the frame files in name order), but after frame "
            f"{ids[i - 1]} ({self.names[i - 1]}) that file's number would make it frame "
            f"{expected[i]}: the file numbers and frames.csv's frame ids do not skip the same "
            f"frames ({self.folder}: {self.describe_gaps()}); if a frame file or a row of "
            "frames.csv is missing, every later row is paired with the wrong image",
            stacklevel=3)


def read_frame_times(root: Path, frames: FrameSource, fps: float | None = None, *,
                     max_spacing: float | None = None) -> tuple[np.ndarray, np.ndarray, str]:
    """(frame ids, timestamps s, where they come from) of the images ``frames`` of the dataset
    or recording folder ``root``: from frames.csv (``frame,timestamp``, both strictly
    increasing, one row per image), else ids 0..N-1 (for frame files numbered with gaps,
    FileNumbers, their numbers less the first one's, divided by their step k, with a warning
    naming the missing files; files numbered in steps of k > 1, with gaps or none, are warned
    of) at timestamp = id / rate, the rate being
    ``fps`` if given, else the video's (frames.frame_rate), else DEFAULT_FPS; a video whose
    own stamps leave its nominal rate (variable frame rate; FrameSource.presentation_times) is
    timed by its stamps unless ``fps`` is given. ValueError naming
    frames.csv when it is malformed, or when ``fps`` is given as well (it would be ignored), or
    when the frame files have gaps its frame ids do not have (FileNumbers.check_frame_ids).

    The times are seconds, checked as the streaming mosaickers check theirs
    (io.tracking.check_stream_timestamp): |t| <= MAX_TIMESTAMP_S and consecutive frames at most
    MAX_FRAME_GAP_S apart; with ``max_spacing`` (s; read_dataset: MAX_FRAME_SPACING_S) also at
    most that far apart in the median, which a video's times in milliseconds exceed."""
    path = root / "frames.csv"
    numbered = FileNumbers.of(frames)
    if path.exists():
        if fps is not None:
            raise ValueError(f"{path}: gives the frame times; the frame rate given ({fps:g} fps) "
                             "applies only to a dataset without frames.csv")
        table, rows = read_table(path, ["frame", "timestamp"], integer=["frame"])
        if rows.size != len(frames):
            what = ("images" if frames.video is None
                    else f"frames in {frames.video.name} (as {frames.counted_by} counts them)")
            gaps = "" if numbered is None or not numbered.gaps else (
                f" ({numbered.folder}: {numbered.describe_gaps()})")
            raise ValueError(f"{path}: {rows.size} rows but the dataset has {len(frames)} "
                             f"{what}{gaps}")
        check_increasing(path, rows, table["frame"], "frame")
        if numbered is not None and numbered.gaps:
            numbered.check_frame_ids(path, rows, table["frame"])
        check_increasing(path, rows, table["timestamp"], "timestamp")
        _check_frame_times(path, rows, table["timestamp"], max_spacing)
        return table["frame"], table["timestamp"], "frames.csv"
    video = None if frames.video is None else frames.video.name
    variable = None if fps is not None else _variable_frame_times(frames, max_spacing)
    if variable is not None:
        return np.arange(len(frames), dtype=np.int64), *variable
    if fps is not None:
        rate = check_fps(fps)
        source = "given"
        if frames.frame_rate is not None and abs(rate / frames.frame_rate - 1.0) > 1e-3:
            source += f"; {video} says {frames.frame_rate:.6g} fps"
    elif frames.frame_rate is not None:
        rate, source = frames.frame_rate, f"the frame rate of {video}"
    else:
        rate = DEFAULT_FPS
        source = "the default: " + ("no frame rate in " + video if video else "PNG frames")
    frame_ids = np.arange(len(frames), dtype=np.int64)
    described = f"frame / {rate:.6g} fps ({source}; no frames.csv)"
    k = 1 if numbered is None else numbered.step
    if numbered is not None and numbered.gaps:  # missing files: the numbers time the frames
        frame_ids = numbered.frames
        first = numbered.numbers[0]
        number = "number" + (f" - {first}" if first else "")
        if k > 1:
            number = f"({number}) / {k}" if first else f"{number} / {k}"
        described = (f"frame / {rate:.6g} fps ({source}; no frames.csv; frame = file {number}, "
                     f"{numbered.missing} missing)")
        gap = int(np.diff(frame_ids).max()) / rate
        if gap > MAX_FRAME_GAP_S:
            raise ValueError(f"{numbered.folder}: {numbered.describe_gaps()}: no frames.csv, so "
                             f"the frames are timed by their numbers, which puts frames "
                             f"{_time(gap)} s apart, more than MAX_FRAME_GAP_S "
                             f"({MAX_FRAME_GAP_S:g} s): give frames.csv with their times")
        if k == 1:
            warnings.warn(
                f"{numbered.folder}: {numbered.describe_gaps()}: no frames.csv, so the frames "
                f"are numbered and timed by their file numbers (frame id = file {number}, "
                f"timestamp = id / {rate:.6g} fps): the frames after a gap keep their own times, "
                "and the missing frames are left out; give frames.csv if the file numbers are "
                "not frame numbers", stacklevel=2)
    if k > 1:  # every k-th frame kept, named by its number? (a step of k: one frame interval)
        names = [p.name for p in frames.paths[:2]]
        kept = (f"--fps {rate / k:.6g}" if fps is None else
                f"--fps the kept frames' rate (the video's / {k}; the {rate:.6g} given is taken "
                "as such)")
        if numbered.gaps:  # (as for files numbered frame by frame: the numbers time them)
            taken = (f"a step of {k} is taken as one frame interval and the frames are timed "
                     f"by their numbers, {described}: {numbered.describe_gaps()}: the frames "
                     "after a gap keep their own times, and the missing frames are left out")
        else:
            taken = f"they are taken as consecutive frames, timed {described}"
        warnings.warn(
            f"{frames.paths[0].parent}: the frame files are numbered in steps of {k} "
            f"({names[0]}, {names[1]}, ...): no frames.csv, so {taken}; if the numbers are the "
            f"video's frame numbers (every {_ordinal(k)} frame kept), give frames.csv with their "
            f"times, or {kept}", stacklevel=2)
    if len(frames) > 1:
        step = 1.0 / rate
        bound, name = min((MAX_FRAME_GAP_S, "MAX_FRAME_GAP_S"),
                          (max_spacing or math.inf, "MAX_FRAME_SPACING_S"))
        last = int(frame_ids[-1]) / rate
        if step > bound or abs(last) > MAX_TIMESTAMP_S:
            raise ValueError(
                f"{root}: the frame times {described} put frames {_time(step)} s apart, up to "
                f"t={_time(last)} s (bounds: {bound:g} s apart, {name}; |t| <= "
                f"{MAX_TIMESTAMP_S:g} s): no endoscope or pCLE video is that slow; check the "
                "frame rate (fusedmosaic run: --fps)")
    return frame_ids, frame_ids / rate, described


def _ordinal(k: int) -> str:
    """2nd, 3rd, 5th, 11th, 21st."""
    suffix = "th" if 10 <= k % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(k % 10, "th")
    return f"{k}{suffix}"


# A video whose stamps stay within this fraction of a frame interval of frame / rate is timed at
# frame / rate (its nominal rate); beyond, by its stamps, described as constant ("every 40 ms")
# when their intervals differ by at most this fraction of the median one, else as variable.
VARIABLE_RATE_TOLERANCE = 0.25


def _variable_frame_times(frames: FrameSource, max_spacing: float | None
                          ) -> tuple[np.ndarray, str] | None:
    """(times s, description) of a video whose container's stamps leave its nominal rate (a
    variable frame rate, or a header's rate that is an estimate; or it gives none); None for
    PNG frames and video whose stamps keep its rate. Stamps that cannot time the frames (not
    increasing, or beyond read_frame_times's bounds) are named in a warning, and the nominal
    rate serves."""
    if frames.video is None:
        return None
    times = frames.presentation_times()
    n, rate, name = len(frames), frames.frame_rate, frames.video.name
    if times is None:
        if n > 1:
            warnings.warn(f"{frames.video}: its frame timestamps are not usable (not one "
                          "increasing stamp per frame): the frames are timed at its frame "
                          "rate; give frames.csv for their true times", stacklevel=3)
        return None
    if n < 2 or (rate is not None and np.abs(times - np.arange(n) / rate).max()
                 <= VARIABLE_RATE_TOLERANCE / rate):
        return None
    steps = np.diff(times)
    if (np.median(steps) > (max_spacing or math.inf) or steps.max() > MAX_FRAME_GAP_S
            or times[-1] > MAX_TIMESTAMP_S):
        warnings.warn(f"{frames.video}: its frame timestamps put frames {np.median(steps):.6g} "
                      f"s apart (median), up to {steps.max():.6g} s: not used (the frames are "
                      "timed at its frame rate); give frames.csv for their true times",
                      stacklevel=3)
        return None
    if steps.max() - steps.min() <= VARIABLE_RATE_TOLERANCE * np.median(steps):
        header = "none" if rate is None else f"{rate:.6g} fps"
        spacing = f"every {np.median(steps) * 1e3:.4g} ms; its header's rate: {header}"
    else:
        spacing = (f"variable frame rate: {steps.min() * 1e3:.4g}-{steps.max() * 1e3:.4g} ms "
                   "apart")
    return times, f"the frame timestamps of {name} ({spacing}; no frames.csv)"


def _check_frame_times(path: Path, rows: np.ndarray, times: np.ndarray,
                       max_spacing: float | None) -> None:
    """frames.csv's timestamps (finite, increasing) within the bounds of read_frame_times;
    ValueError naming the file, the row and the likely unit mistake."""
    check_timestamp_bound(path, rows, times, "frame")
    ms = "frames.csv's timestamps must be seconds: are these milliseconds"
    steps = np.diff(times)
    far = np.flatnonzero(steps > MAX_FRAME_GAP_S)
    if far.size:
        i = far[0] + 1
        raise ValueError(f"{path}: row {rows[i]}: timestamp {times[i].item()!r} is "
                         f"{_time(steps[i - 1])} s after the previous row's, more than "
                         f"MAX_FRAME_GAP_S ({MAX_FRAME_GAP_S:g} s, a day): {ms}?")
    if max_spacing is not None and steps.size and np.median(steps) > max_spacing:
        i = int(np.flatnonzero(steps > max_spacing)[0]) + 1
        raise ValueError(
            f"{path}: frames come every {_time(float(np.median(steps)))} s (median spacing; "
            f"e.g. rows {rows[i - 1]} and {rows[i]} are {_time(steps[i - 1])} s apart), more "
            f"than MAX_FRAME_SPACING_S ({max_spacing:g} s): an endoscope or pCLE video gives "
            f"10-60 frames/s; {ms}?")


def _align_ground_truth(path: Path, frame_ids: np.ndarray, *, explicit: bool) -> np.ndarray:
    """ground_truth.csv's homographies in the order of ``frame_ids``. With ``explicit`` ids
    (frames.csv's), rows for frames not in the dataset (e.g. frames removed from it) are left
    out with a warning naming them (the truth is for scoring only: the frames present are
    scored), and when they include the truth's reference (frames before the dataset's first)
    the truth is re-referenced to the dataset's first frame, as the output is. Without (ids by
    position, or by file number less the first one's) such rows are a ValueError: the ids may
    have shifted (a first file removed made every frame scored against its neighbour's truth,
    e_M 251 px for 0.06; review). A frame without a row is a ValueError."""
    truth_ids, H = read_homographies_csv(path)
    unknown = np.setdiff1d(truth_ids, frame_ids)
    if unknown.size and not explicit:
        raise ValueError(
            f"{path}: frame {unknown[0]} is not in the dataset ({unknown.size} unknown frame "
            "ids): without frames.csv the frames are numbered by position (or, numbered files "
            "with gaps, by their numbers less the first one's), so a removed frame shifts the "
            "ids; give frames.csv with the ids ground_truth.csv uses")
    if unknown.size:
        shown = ", ".join(map(str, unknown[:5])) + (", ..." if unknown.size > 5 else "")
        keep = np.isin(truth_ids, frame_ids)
        truth_ids, H = truth_ids[keep], H[keep]
        rebased = ""
        first = np.flatnonzero(truth_ids == frame_ids[0])
        if unknown[0] < frame_ids[0] and first.size and np.isfinite(H[first[0]]).all():
            # the truth's reference (its first frame) is gone: the dataset's first frame is
            # the reference of its output, so of its truth too
            with np.errstate(divide="ignore", invalid="ignore"):
                try:
                    H = np.linalg.inv(H[first[0]]) @ H
                    H /= H[:, 2:3, 2:3]
                    rebased = (f"; the truth is taken relative to frame {frame_ids[0]}, the "
                               "dataset's first")
                except np.linalg.LinAlgError:  # a singular truth: scored as it is
                    pass
        rows = "1 row for a frame" if unknown.size == 1 else f"{unknown.size} rows for frames"
        warnings.warn(
            f"{path}: {rows} not in the dataset ignored (frame{'s' if unknown.size > 1 else ''} "
            f"{shown}): only the dataset's frames are scored{rebased}", stacklevel=3)
    missing = np.setdiff1d(frame_ids, truth_ids)
    if missing.size:
        raise ValueError(
            f"{path}: no row for frame {missing[0]} ({missing.size} frames missing; "
            "write empty fields for unplaced frames)"
        )
    order = np.argsort(truth_ids)
    return H[order][np.searchsorted(truth_ids[order], frame_ids)]


def write_dataset(
    root: str | Path,
    *,
    camera: Camera,
    frames: Iterable[np.ndarray],
    timestamps,
    frame_ids=None,
    tracking: TrackingSamples | None = None,
    hand_eye=None,
    robot: RobotSamples | None = None,
    ground_truth=None,
    extra_files: dict[str, bytes | str] | None = None,
    robot_files: dict[str, RobotSamples] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a dataset folder atomically: it is built in a temporary folder next to ``root`` and
    renamed into place, so a failure leaves no ``root`` (or the previous one, with overwrite).

    frames are streamed to ``frames/000000.png``…; timestamps (N,) go to frames.csv (None: no
    frames.csv) with ``frame_ids`` (N,) strictly increasing integers (None: 0..N-1; e.g. a
    recording's own numbers, with gaps where frames were left out); ground_truth (N, 3, 3) is
    written with the same ids.
    robot goes to robot.csv; robot_files maps further file names to samples. extra_files are
    written last, verbatim (they may replace a generated file, e.g. to build a bad dataset).
    """
    root = Path(root)
    if frame_ids is not None:
        ids = np.asarray(frame_ids)
        if timestamps is None:
            raise ValueError(f"{root}: frame_ids need timestamps (frames.csv holds both)")
        if (ids.ndim != 1 or not np.issubdtype(ids.dtype, np.integer)
                or (ids.size > 1 and np.any(np.diff(ids) <= 0))):
            raise ValueError(f"{root}: frame_ids must be strictly increasing integers (N,)")
    tmp = staging_folder(root, overwrite)
    try:
        write_camera_yaml(tmp / "camera.yaml", camera)
        n = write_frames(tmp / "frames", frames)
        ids = np.arange(n) if frame_ids is None else np.asarray(frame_ids, np.int64)
        if ids.size != n:
            raise ValueError(f"{root}: {ids.size} frame ids for {n} frames")
        if timestamps is not None:
            timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
            if timestamps.size != n:
                raise ValueError(f"{root}: {timestamps.size} timestamps for {n} frames")
            write_table(
                tmp / "frames.csv",
                ["frame", "timestamp"],
                ([str(i), format_float(t)] for i, t in zip(ids, timestamps, strict=True)),
            )
        if tracking is not None:
            write_tracking_csv(tmp / "tracking.csv", tracking)
        if hand_eye is not None:
            write_hand_eye(tmp / "hand_eye.txt", hand_eye)
        robot_files = dict(robot_files or {})
        if robot is not None:
            robot_files.setdefault("robot.csv", robot)
        for name, samples in robot_files.items():
            write_robot_csv(tmp / name, samples)
        if ground_truth is not None:
            ground_truth = np.asarray(ground_truth, dtype=np.float64)
            if ground_truth.shape[0] != n:
                raise ValueError(
                    f"{root}: ground truth has {ground_truth.shape[0]} homographies for {n} frames"
                )
            write_homographies_csv(tmp / "ground_truth.csv", ids, ground_truth)
        for name, content in (extra_files or {}).items():
            path = tmp / name
            path.parent.mkdir(parents=True, exist_ok=True)
            if isinstance(content, str):
                path.write_text(content)
            else:
                path.write_bytes(content)
        _replace_dir(tmp, root)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return root


def staging_folder(root: Path, overwrite: bool,
                   hint: str = "pass overwrite=True to replace it") -> Path:
    """Checks that `root` can receive a dataset (absent or empty; with overwrite, an earlier
    dataset: check_replaceable_dataset) and returns a new empty folder beside it to build the
    dataset in, for _replace_dir to rename into place; with a folder's usual mode (mkdtemp
    makes it 0700, which the renamed dataset would keep). ValueError otherwise (`hint` says
    how to replace)."""
    if root.exists() and not root.is_dir():  # (was 'exists and is not empty'; review)
        raise ValueError(f"{root}: exists and is a file, not a folder (name a new folder for "
                         "the dataset)")
    if root.exists() and any(root.iterdir()):
        if not overwrite:
            raise ValueError(f"{root}: exists and is not empty ({hint})")
        check_replaceable_dataset(root)
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{root.name}.tmp-", dir=root.parent))
    os.chmod(tmp, created_mode(0o777))
    return tmp


def created_mode(bits: int) -> int:
    """`bits` (0o666 for a file, 0o777 for a folder) as the umask leaves them on a newly
    created one: the mode to give what mkstemp / mkdtemp made (0600 / 0700)."""
    umask = os.umask(0)
    os.umask(umask)
    return bits & ~umask


def check_not_current_folder(root: str | Path) -> None:
    """A dataset is written beside its folder and renamed over it: ValueError naming `root`
    when that folder is the current one or holds it (the shell would be left in a deleted
    folder)."""
    here, target = Path.cwd().resolve(), Path(root).resolve()
    if target == here or target in here.parents:
        what = "is the current folder" if target == here else f"holds the current folder {here}"
        raise ValueError(f"{root}: refusing to overwrite: it {what}; choose a new folder")


def check_replaceable_dataset(root: str | Path) -> None:
    """overwrite replaces a whole folder, so only an earlier dataset: never the current folder
    or one that holds it, nor a folder without camera.yaml or simulation.json (the user's files,
    a project, a home folder). ValueError naming the folder otherwise."""
    root = Path(root)
    check_not_current_folder(root)
    if not root.is_dir() or not any(
        (root / n).is_file() for n in ("camera.yaml", "simulation.json")
    ):
        raise ValueError(
            f"{root}: refusing to overwrite: it does not look like a dataset (no camera.yaml or "
            "simulation.json), and overwriting would delete everything in it; choose a new "
            "folder, or empty it yourself"
        )


def _replace_dir(src: Path, dst: Path) -> None:
    """Rename ``src`` to ``dst``, replacing an existing ``dst`` (moved aside first, and put back
    if the rename fails; kept in ``.NAME.old-*`` if even that fails)."""
    dst = Path(os.path.abspath(dst))  # "a/.." -> its real name, without following symlinks
    if not dst.exists() and not dst.is_symlink():
        os.replace(src, dst)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{dst.name}.old-", dir=dst.parent))
    try:
        os.replace(dst, old / dst.name)
    except BaseException:
        old.rmdir()
        raise
    try:
        os.replace(src, dst)
    except BaseException:
        os.replace(old / dst.name, dst)
        old.rmdir()
        raise
    shutil.rmtree(old, ignore_errors=True)
