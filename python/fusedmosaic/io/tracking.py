"""External pose sources: EM tracker (``tracking.csv``, ``hand_eye.txt``) and robot
(``robot.csv``), and their interpolation to frame timestamps.

Quaternions are (x, y, z, w), scipy's order; angle-axis vectors are scipy's ``as_rotvec``, the
same convention as the C++ core (rotation angle = norm, right-handed about the axis).
"""

from __future__ import annotations

import numbers
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline, Slerp

from fusedmosaic.io._table import (
    check_increasing,
    format_float,
    parse_numbers,
    read_number_table,
    read_table,
    require_file,
    write_table,
)

TRACKING_COLUMNS = ["timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"]
ROBOT_COLUMNS = ["timestamp", "x", "y"]
QUATERNION_NORM_TOLERANCE = 1e-3
# hand_eye.txt's rotation block: |R^T R - I| (the squares of its column norms, their dot
# products) within this, as PLUS's tracker matrices (plus.RIGID_TOLERANCE) and tracking.csv's
# quaternion norms: a rotation printed with 4 decimals (MATLAB's format short, np.round(T, 4))
# is off by up to ~1.2e-4 there, and 1e-4 refused 22 % of them as "scaled" (review 46); the
# rotation is then projected onto the nearest one (a 1e-3 correction is 0.06 deg).
ROTATION_TOLERANCE = 1e-3
# Generous physical bound, not a tuned one: no tracker, robot or hand-eye offset spans a
# kilometre. Larger values are unit errors or corrupt rows, and squaring them (plane fit,
# distances) overflows.
MAX_TRANSLATION_MM = 1e6
MAX_ROBOT_UM = 1e3 * MAX_TRANSLATION_MM
# s; a timestamp above this is not in seconds (1e10 s is the year 2286 as Unix time; a Unix
# time in ms, µs or ns is 1e12 and above).
MAX_TIMESTAMP_S = 1e10
# s; frames of one sequence more than a day apart: a unit mix-up or a corrupt clock.
MAX_FRAME_GAP_S = 86_400.0
# s; the median frame spacing of a dataset (io.read_dataset): a video at 10-100 frames/s whose
# timestamps are in milliseconds has frames 10-100 "s" apart, below MAX_FRAME_GAP_S (which a
# single gap may reach: a paused recording), so the median is bounded too. Endoscope video runs
# at 25-60 frames/s and pCLE at ~10 (0.02-0.1 s apart); 10 s still takes a recording thinned
# to one frame in 100-250, whose consecutive frames would hardly overlap anyway.
MAX_FRAME_SPACING_S = 10.0


def check_stream_timestamp(index: int, timestamp, previous: float, *,
                           max_gap_s: float = MAX_FRAME_GAP_S,
                           gap_name: str = "MAX_FRAME_GAP_S") -> float:
    """The timestamp (s) of streamed frame `index` as a float, after the checks both streaming
    mosaickers make: a real number (a 0-d array is taken), finite, after `previous` (the last
    accepted frame's, -inf before the first), |t| <= MAX_TIMESTAMP_S and at most `max_gap_s`
    after `previous`. Raises TypeError / ValueError naming the frame; `gap_name` names the
    bound in the message (an option or a constant)."""
    if isinstance(timestamp, np.ndarray) and timestamp.ndim == 0:
        timestamp = timestamp[()]
    if isinstance(timestamp, bool | np.bool_) or not isinstance(timestamp, numbers.Real):
        raise TypeError(f"frame {index}: timestamp must be a real number (s), got "
                        f"{type(timestamp).__name__} {timestamp!r:.60}")
    try:
        t = float(timestamp)
    except OverflowError:  # a Python int beyond the float range
        t = float("inf")
    if not np.isfinite(t):
        raise ValueError(f"frame {index}: timestamp {timestamp!r:.60} is not finite")
    if not t > previous:
        raise ValueError(f"frame {index}: timestamp {t!r} does not increase (previous frame's "
                         f"{previous!r})")
    units = "timestamps are seconds: a unit mix-up (ms, µs or ns given as s)?"
    if abs(t) > MAX_TIMESTAMP_S:
        raise ValueError(f"frame {index}: timestamp {t!r} is beyond |t| <= {MAX_TIMESTAMP_S:g} s "
                         f"(the year 2286 as Unix time); {units}")
    if np.isfinite(previous) and t - previous > max_gap_s:
        raise ValueError(f"frame {index}: timestamp {t!r} is {t - previous:.3g} s after the "
                         f"previous frame's ({previous!r}), more than {gap_name} "
                         f"({max_gap_s:g} s); {units}")
    return t


@dataclass(eq=False)
class TrackingSamples:
    """EM tracker samples of tracker_from_sensor at the tracker's own rate.

    timestamps : (M,) float64, s.  translations : (M, 3) float64, mm.
    quaternions : (M, 4) float64 unit, (x, y, z, w): a valid sample's norm must be within
    QUATERNION_NORM_TOLERANCE of 1 (then renormalised).  valid : (M,) bool, False = missing sample.
    """

    timestamps: np.ndarray
    translations: np.ndarray
    quaternions: np.ndarray
    valid: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        m = self.timestamps.size
        self.translations = np.asarray(self.translations, dtype=np.float64)
        self.quaternions = np.asarray(self.quaternions, dtype=np.float64)
        self.valid = np.ones(m, bool) if self.valid is None else np.asarray(self.valid, bool)
        for name, shape in [("translations", (m, 3)), ("quaternions", (m, 4)), ("valid", (m,))]:
            if getattr(self, name).shape != shape:
                raise ValueError(
                    f"TrackingSamples.{name}: expected shape {shape}, "
                    f"got {getattr(self, name).shape}"
                )
        # As read_tracking_csv: a valid sample's quaternion is a unit one to within
        # QUATERNION_NORM_TOLERANCE (rounding), and is renormalised; a norm further from 1 is
        # a wrong field order or a corrupt sample, which tracking.csv would refuse when read.
        norms = np.linalg.norm(self.quaternions, axis=1)
        bad = np.flatnonzero(self.valid & ~(np.abs(norms - 1.0) <= QUATERNION_NORM_TOLERANCE))
        if bad.size:
            raise ValueError(
                f"TrackingSamples.quaternions: sample {bad[0]} is valid but its quaternion "
                f"{self.quaternions[bad[0]].tolist()} has norm {norms[bad[0]]:g}, not 1 "
                f"(tolerance {QUATERNION_NORM_TOLERANCE:g})"
            )
        if self.valid.any():
            self.quaternions = self.quaternions.copy()
            self.quaternions[self.valid] /= norms[self.valid, None]
        bad = np.flatnonzero(self.valid & ~np.all(np.isfinite(self.translations), axis=1))
        if bad.size:
            raise ValueError(
                f"TrackingSamples.translations: sample {bad[0]} is valid but not finite"
            )
        bad = np.flatnonzero(self.valid & ~np.isfinite(self.timestamps))
        if bad.size:  # (it failed in SciPy: 'zero norm quaternions'; review)
            raise ValueError(f"TrackingSamples.timestamps: sample {bad[0]} is valid but its "
                             f"timestamp is {self.timestamps[bad[0]]}")

    def __len__(self) -> int:
        return self.timestamps.size


@dataclass(eq=False)
class RobotSamples:
    """Robot-reported probe positions in the image axes: timestamps (M,) s, xy_um (M, 2) µm.
    M = 0 is allowed (interpolate_robot then refuses it: "no samples")."""

    timestamps: np.ndarray
    xy_um: np.ndarray

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.xy_um = np.asarray(self.xy_um, dtype=np.float64)
        if self.xy_um.shape != (self.timestamps.size, 2):
            raise ValueError(
                f"RobotSamples.xy_um: expected shape ({self.timestamps.size}, 2), "
                f"got {self.xy_um.shape}"
            )
        # as robot.csv refuses them (a NaN sample was interpolated into frames marked valid)
        for name, values in (("timestamps", self.timestamps), ("xy_um", self.xy_um)):
            finite = np.isfinite(values)
            bad = np.flatnonzero(~(finite if finite.ndim == 1 else finite.all(1)))
            if bad.size:
                raise ValueError(f"RobotSamples.{name}: sample {bad[0]} is not finite "
                                 f"({values[bad[0]]}); leave a missing sample out")

    def __len__(self) -> int:
        return self.timestamps.size


def read_tracking_csv(path: str | Path) -> TrackingSamples:
    """Read ``timestamp,tx,ty,tz,qx,qy,qz,qw[,valid]`` (s, mm, quaternion x, y, z, w).

    ``valid`` (absent: every row valid) is 1 or 0, as any number (``1.0`` / ``0.0`` too), or
    ``true`` / ``false`` in any case (spreadsheets and tracker exports write those); anything
    else is refused. The pose fields of a row with valid=0 are not read: they may be empty or
    hold any text (NDI writes ``MISSING``); its timestamp still counts in the strictly
    increasing order. Timestamps must be within |t| <= MAX_TIMESTAMP_S. Quaternions of valid
    rows are checked (|q| within 1e-3 of 1; the error names the row) and renormalised (by
    TrackingSamples)."""
    numbers = read_number_table(path, TRACKING_COLUMNS, ["valid"])  # at numpy's speed
    if numbers is not None and "valid" in numbers[0] and not np.all(
            np.isin(numbers[0]["valid"], (0.0, 1.0))):
        numbers = None  # (read again as text: the message names the row)
    if numbers is None:
        text = [*TRACKING_COLUMNS[1:], "valid"]
        table, rows = read_table(path, TRACKING_COLUMNS, ["valid"], text=text)
    else:
        table, rows = numbers
    timestamps = table["timestamp"]
    check_increasing(path, rows, timestamps, "timestamp")
    check_timestamp_bound(path, rows, timestamps, "tracker")
    if numbers is not None:
        valid = (table["valid"] == 1.0 if "valid" in table
                 else np.ones(timestamps.size, bool))
        values = np.stack([table[c] for c in TRACKING_COLUMNS[1:]], axis=1).reshape(-1, 7)
    else:
        valid = (_valid_flags(path, rows, table["valid"]) if "valid" in table
                 else np.ones(timestamps.size, bool))
        values = np.stack([parse_numbers(path, rows, c, table[c], skip=~valid)
                           for c in TRACKING_COLUMNS[1:]], axis=1).reshape(-1, 7)
    _check_values(
        path,
        rows,
        values,
        TRACKING_COLUMNS[1:],
        valid,
        unit="mm",
        bound=MAX_TRANSLATION_MM,
        n_bounded=3,
    )
    quaternions = values[:, 3:]
    norms = np.linalg.norm(quaternions, axis=1)
    off = np.flatnonzero(valid & (np.abs(norms - 1.0) > QUATERNION_NORM_TOLERANCE))
    if off.size:
        raise ValueError(
            f"{path}: row {rows[off[0]]}: quaternion norm {norms[off[0]]:.6g} is "
            f"not 1 (tolerance {QUATERNION_NORM_TOLERANCE:g})"
        )
    return TrackingSamples(timestamps, values[:, :3], quaternions, valid)  # renormalised there


def _valid_flags(path, rows: np.ndarray, fields: np.ndarray) -> np.ndarray:
    """tracking.csv's ``valid`` column as booleans: 1 / 0 as numbers (1, 1.0, ...) or true /
    false in any case; ValueError naming the row of the first other value and listing what is
    accepted."""
    fields = np.asarray(fields, dtype=object).reshape(-1)
    ones = fields == "1"
    if np.all(ones | (fields == "0")):  # as written by write_tracking_csv: at once
        return np.asarray(ones, bool)
    flags = np.empty(len(fields), bool)
    for i, field in enumerate(fields):
        word = str(field).lower()
        if word in ("true", "false"):
            flag = word == "true"
        else:
            try:
                flag = {1.0: True, 0.0: False}.get(float(word))
            except ValueError:
                flag = None
        if flag is None:
            raise ValueError(
                f"{path}: row {rows[i]}, column 'valid': expected 0 or 1 (also accepted: true / "
                f"false in any case, 1.0 / 0.0), got {str(field)!r}"
            )
        flags[i] = flag
    return flags


def check_timestamp_bound(path, rows: np.ndarray, timestamps: np.ndarray, what: str) -> None:
    """Refuses a timestamp beyond |t| <= MAX_TIMESTAMP_S (as the streaming mosaickers do,
    check_stream_timestamp), naming the file and the row: such times are not seconds."""
    beyond = np.flatnonzero(np.abs(timestamps) > MAX_TIMESTAMP_S)
    if beyond.size:
        i = beyond[0]
        raise ValueError(
            f"{path}: row {rows[i]}, column 'timestamp': {timestamps[i].item()!r} is beyond "
            f"|t| <= {MAX_TIMESTAMP_S:g} s (the year 2286 as UNIX time): {what} timestamps "
            "are in seconds; are these milliseconds (or µs, ns)?"
        )


def _check_values(
    path, rows, values, columns, valid, *, unit: str, bound: float, n_bounded: int
) -> None:
    """Raise naming the row and column of the first NaN/empty value, infinite value, or value
    beyond ``bound`` (first ``n_bounded`` columns only); rows with ``valid`` False are skipped."""
    checked = np.ones(len(values), bool) if valid is None else valid
    beyond = np.zeros(values.shape, bool)
    beyond[:, :n_bounded] = np.abs(values[:, :n_bounded]) > bound
    in_valid_row = "" if valid is None else " in a valid row"
    for mask, problem in (
        (np.isnan(values), f"NaN or empty value{in_valid_row}"),
        (np.isinf(values), f"infinite value{in_valid_row}"),
        (beyond, f"beyond the {bound:g} {unit} bound (1 km), not physical"),
    ):
        row, col = np.nonzero(mask & checked[:, None])
        if row.size:
            value = values[row[0], col[0]].item()
            shown = "" if np.isnan(value) else f" ({value:g})"
            raise ValueError(
                f"{path}: row {rows[row[0]]}, column {columns[col[0]]!r}: {problem}{shown}"
            )


# The largest tracker-video clock offset taken (as calibrate's --time-offset): endoscope video
# and EM tracker latencies are tens of milliseconds; seconds mean clocks that were never synced.
MAX_TIME_OFFSET_S = 10.0


def check_time_offset(offset, what: str = "tracker_time_offset") -> float:
    """A tracker-video clock offset: a finite number of seconds within +-MAX_TIME_OFFSET_S."""
    if (isinstance(offset, bool) or not isinstance(offset, numbers.Real)
            or not abs(float(offset)) <= MAX_TIME_OFFSET_S):
        raise ValueError(f"{what}: expected seconds within +-{MAX_TIME_OFFSET_S:g}, "
                         f"got {offset!r}")
    return float(offset)


def shift_tracking(samples: TrackingSamples, offset_s: float) -> TrackingSamples:
    """The samples on the video's clock when the tracker's clock is offset_s ahead: the
    sample for the frame at time t is the one stamped t + offset_s (calibrate's
    calibration.json "tracker_time_offset" / "applied_s"), so every timestamp moves by
    -offset_s."""
    offset_s = check_time_offset(offset_s)
    return TrackingSamples(samples.timestamps - offset_s, samples.translations.copy(),
                           samples.quaternions.copy(), samples.valid.copy())


def write_tracking_csv(path: str | Path, samples: TrackingSamples) -> None:
    """Write all samples with a ``valid`` column; NaN fields are written empty."""
    values = np.concatenate([samples.translations, samples.quaternions], axis=1)
    rows = (
        [format_float(t), *map(format_float, v), str(int(ok))]
        for t, v, ok in zip(samples.timestamps, values, samples.valid, strict=True)
    )
    write_table(path, [*TRACKING_COLUMNS, "valid"], rows)


def rigid_problems(transforms, tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Masks over (N, 4, 4) transforms (or one 4x4): not finite; finite but not rigid (rotation
    block not orthonormal with det +1 to `tolerance`, or last row not 0 0 0 1); finite with a
    translation beyond MAX_TRANSLATION_MM. Callers word the problem for their input."""
    T = np.asarray(transforms, dtype=np.float64).reshape(-1, 4, 4)
    finite = np.isfinite(T).all(axis=(1, 2))
    M = np.where(finite[:, None, None], T, np.eye(4))
    R = M[:, :3, :3]
    off = np.abs(np.einsum("nki,nkj->nij", R, R) - np.eye(3)).max(axis=(1, 2))
    last = np.abs(M[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1)
    rigid = (off <= tolerance) & (np.linalg.det(R) > 0) & (last <= tolerance)
    far = np.abs(M[:, :3, 3]).max(axis=1) > MAX_TRANSLATION_MM
    return ~finite, finite & ~rigid, finite & far


def rigid_defects(T, tolerance: float, brief: bool = False) -> str:
    """Which checks of rigid_problems a finite 4x4 ``T`` fails, in words: a reflection (det -1),
    a scale (column norms not 1), a shear (columns not orthogonal), a last row other than
    0 0 0 1; "" when it is rigid to ``tolerance``. ``brief``: the kinds alone, without the
    figures (a live source counts its invalid samples by this text)."""
    T = np.asarray(T, dtype=np.float64).reshape(4, 4)
    R = T[:3, :3]
    gram = R.T @ R  # the identity for a rotation (rigid_problems compares it)
    norms = np.sqrt(np.abs(np.diag(gram)))
    found = []
    det = np.linalg.det(R)
    if det < 0:
        found.append("a reflection (det -1)" if brief else
                     f"the rotation block's determinant is {det:.6g}, not +1: a reflection (a "
                     "left-handed frame, or an axis flipped?)")
    # (the figures shown are those compared with the tolerance: the squared norms' distance
    # from 1 was compared, the norms shown; 1.00006 was refused at tolerance 1e-4; review 46)
    off_diagonal = np.abs(gram - np.diag(np.diag(gram))).max()
    squares = np.abs(np.diag(gram) - 1.0).max()
    if off_diagonal > tolerance:  # a shear changes the norms too: named as a shear only
        with np.errstate(divide="ignore", invalid="ignore"):  # a zero column: no angle
            cosine = np.nanmax(np.abs(gram / np.outer(norms, norms) - np.eye(3)))
        found.append("sheared" if brief else
                     f"the rotation block's columns are not orthogonal (|cos| up to "
                     f"{cosine:.3g} between two: sheared): their dot products up to "
                     f"{off_diagonal:.3g}")
    elif squares > tolerance:
        shown = ", ".join(f"{n:.6g}" for n in norms)
        found.append("scaled" if brief else
                     f"the rotation block's columns have norms {shown}, not 1 (scaled): their "
                     f"squares up to {squares:.3g} from 1")
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > tolerance:
        found.append("last row not 0 0 0 1" if brief else
                     f"the last row is {' '.join(f'{v:g}' for v in T[3])}, not 0 0 0 1")
    if not found and not rigid_problems(T, tolerance)[1][0]:
        return ""
    return "; ".join(found or ["not orthonormal"]) + ("" if brief else
                                                      f" (tolerance {tolerance:g})")


def read_hand_eye(path: str | Path) -> np.ndarray:
    """Read the 4x4 rigid sensor_from_camera transform (text: numbers separated by blanks, or
    by commas or semicolons, brackets ignored, as np.savetxt, MATLAB's writematrix and print(T)
    write them; '#' starts a comment). Also accepted: the 16 numbers in another layout (read
    row by row) and a 3x4 [R | t] without its last row (0 0 0 1 added). Checked and projected
    as `hand_eye_matrix` does."""
    path = Path(path)
    require_file(path)
    data = path.read_bytes()
    if not data.strip():
        raise ValueError(f"{path}: empty file, expected a 4x4 matrix")
    try:
        text = data.decode("utf-8-sig")  # a byte order mark skipped
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not UTF-8 text; expected a 4x4 matrix of numbers") from None
    rows = []
    for line in text.splitlines():
        tokens = _HAND_EYE_SEPARATORS.sub(" ", line.split("#", 1)[0]).split()
        if tokens:
            try:
                rows.append([float(t) for t in tokens])
            except ValueError as e:
                raise ValueError(f"{path}: cannot parse as a 4x4 matrix of numbers ({e})") from None
    widths = sorted({len(row) for row in rows})
    flat = [v for row in rows for v in row]
    if len(rows) == 3 and widths == [4]:  # [R | t]
        T = np.array([*rows, [0.0, 0.0, 0.0, 1.0]])
    elif len(flat) == 16:
        T = np.array(flat, dtype=np.float64).reshape(4, 4)
    else:
        shape = (f"{len(rows)}x{widths[0]}" if len(widths) == 1 else
                 f"{len(rows)} rows of {', '.join(map(str, widths))} numbers" if rows else
                 "no numbers")
        raise ValueError(f"{path}: expected a 4x4 matrix, got {shape} (also accepted: its 16 "
                         "numbers in another layout, read row by row; a 3x4 [R | t])")
    return _checked_hand_eye(T, str(path))


_HAND_EYE_SEPARATORS = re.compile(r"[,;\[\]]")  # read as blanks in hand_eye.txt


def hand_eye_matrix(hand_eye) -> np.ndarray:
    """A 4x4 sensor_from_camera from a hand_eye.txt path (read_hand_eye) or a matrix, checked
    the same way (ValueError naming the file, or "hand_eye")."""
    if isinstance(hand_eye, (str, os.PathLike)):
        return read_hand_eye(hand_eye)
    try:
        T = np.array(hand_eye, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError("hand_eye: expected a 4x4 matrix of numbers or a path") from None
    if T.shape != (4, 4):
        raise ValueError(f"hand_eye: expected a 4x4 matrix, got shape {T.shape}")
    return _checked_hand_eye(T, "hand_eye")


def _checked_hand_eye(T: np.ndarray, source: str) -> np.ndarray:
    """T checked (finite, within 1 km, rigid to ROTATION_TOLERANCE), its rotation block
    projected onto the nearest rotation so text rounding does not leak a scale."""
    not_finite, not_rigid, far = rigid_problems(T, ROTATION_TOLERANCE)
    if not_finite[0]:
        raise ValueError(f"{source}: NaN or inf in the matrix")
    if far[0]:
        raise ValueError(
            f"{source}: translation {T[:3, 3].tolist()} mm is beyond the "
            f"{MAX_TRANSLATION_MM:g} mm bound (1 km), not physical"
        )
    if not_rigid[0]:
        raise ValueError(f"{source}: not a rigid transform: {rigid_defects(T, ROTATION_TOLERANCE)}")
    T = T.copy()
    u, _, vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = u @ vt
    T[3] = [0, 0, 0, 1]
    return T


def write_hand_eye(path: str | Path, T) -> None:
    """Write a 4x4 transform as text, 17 significant digits (exact round trip)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"{path}: hand-eye transform must be 4x4, got {T.shape}")
    np.savetxt(path, T, fmt="%.17g")


def read_robot_csv(path: str | Path) -> RobotSamples:
    """Read ``timestamp,x,y`` (s, µm; every field filled, |timestamp| <= MAX_TIMESTAMP_S)."""
    table, rows = read_number_table(path, ROBOT_COLUMNS) or read_table(path, ROBOT_COLUMNS)
    if table["timestamp"].size == 0:  # a logger that wrote its header only
        raise ValueError(
            f"{path}: no samples (header only): need rows of {','.join(ROBOT_COLUMNS)}")
    check_increasing(path, rows, table["timestamp"], "timestamp")
    check_timestamp_bound(path, rows, table["timestamp"], "robot")
    xy = np.stack([table["x"], table["y"]], axis=1)
    _check_values(
        path, rows, xy, ROBOT_COLUMNS[1:], None, unit="µm", bound=MAX_ROBOT_UM, n_bounded=2
    )
    return RobotSamples(table["timestamp"], xy)


def write_robot_csv(path: str | Path, samples: RobotSamples) -> None:
    rows = (
        [format_float(t), format_float(x), format_float(y)]
        for t, (x, y) in zip(samples.timestamps, samples.xy_um, strict=True)
    )
    write_table(path, ROBOT_COLUMNS, rows)


def _time(t: float) -> str:
    """Seconds readable at any magnitude: times from 1 s to Unix times (in s or ms) keep their
    milliseconds (1.7e+09 and 1000.2 for 1000.215 do not); beyond those, exponent form (not
    300 digits for a time of 1e300)."""
    return f"{t:.3f}" if 1e3 <= abs(t) < 1e15 else f"{t:.6g}"


# Samples this many times sparser than the frames (median spacings) are taken for a unit
# mistake (a tracker at 40 Hz stamped in ms against frames in s is 1000x), not a real rate: an
# EM tracker runs at 20-100 Hz, a robot faster, the video at 10-60 frames/s.
MAX_SAMPLE_TO_FRAME_SPACING = 50.0


def _check_rates(frame_times: np.ndarray, ts: np.ndarray, source: str, what: str) -> None:
    """Refuses samples far sparser than the frames: timestamps in other units than the
    frames' (all frames would fall between two samples and be interpolated from them)."""
    if frame_times.size < 3 or ts.size < 2 or not np.all(np.isfinite(frame_times)):
        return  # (non-finite frame times: refused by _outside_span)
    frame_step = float(np.median(np.diff(np.sort(frame_times))))
    sample_step = float(np.median(np.diff(ts)))
    if frame_step > 0 and sample_step > MAX_SAMPLE_TO_FRAME_SPACING * frame_step:
        raise ValueError(
            f"{source}: {what} samples every {_time(sample_step)} s (median) while frames come "
            f"every {_time(frame_step)} s: are the {what}'s timestamps in another unit (ms?) "
            "than the frames'? Both must be in seconds, on one clock")


def no_overlap_message(source: str, what: str, frame_times: np.ndarray, t0: float,
                       t1: float) -> str:
    """No frame time lies in the samples' span [t0, t1]: the two files' clocks differ (or the
    clock offset given, named in `source` as SHIFTED says, moved the samples away)."""
    hint = ("check the clock offset given (--tracker-time-offset; calibrate measures the "
            "tracker's)" if SHIFTED_MARK in source else
            f"the {what}'s timestamps and the frames' must be on one clock, in seconds (e.g. "
            "both UNIX time: write frames.csv with the frames' own times)")
    return (f"{source}: none of the {frame_times.size} frames lies in the {what}'s time span "
            f"[{_time(t0)}, {_time(t1)}] s (the frames span [{_time(np.min(frame_times))}, "
            f"{_time(np.max(frame_times))}] s): {hint}")


SHIFTED_MARK = "the clock offset)"
SHIFTED = " (timestamps shifted by {:+g} s, " + SHIFTED_MARK  # a source read with an offset


def _outside_span(
    frame_times: np.ndarray, t0: float, t1: float, source: str, what: str, allow_outside: bool,
    span: str = "",
) -> np.ndarray:
    """Boolean mask of frames outside [t0, t1]; raises on the first unless allow_outside.
    ``span`` says what the span is, after it in the message (e.g. which samples it counts)."""
    if not np.all(np.isfinite(frame_times)):
        raise ValueError(f"{source}: frame times must be finite")
    outside = (frame_times < t0) | (frame_times > t1)
    if outside.all() and not allow_outside:
        raise ValueError(no_overlap_message(source, what, frame_times, t0, t1))
    if outside.any() and not allow_outside:
        i = int(np.flatnonzero(outside)[0])
        raise ValueError(
            f"{source}: {int(outside.sum())} frames outside the {what}'s time span "
            f"[{_time(t0)}, {_time(t1)}] s{span}; first offending frame index {i} at "
            f"t={_time(frame_times[i])} s"
            " (fusedmosaic run: --allow-untracked flags such frames instead; without frames.csv "
            "the frame times are frame / fps: --fps, else the video's frame rate, else 25)"
        )
    return outside


# A gap between samples longer than this many typical sample spacings (sample_spacing) is a
# dropout: the frames inside it get no sample (offline) and a newest sample older than this is
# none (live).
GAP_SPACINGS = 3.0


def sample_spacing(times) -> float:
    """The typical spacing (s) of the samples at increasing ``times`` (at least 2), for telling
    a dropout (a gap over GAP_SPACINGS of it) from the normal sampling: the larger of the median
    spacing and the smaller of two robust spacings, the time-weighted lower quartile (the
    spacing s such that 25 % of the samples' span lies in intervals <= s) and the 95th
    percentile of the spacings.

    Evenly spaced samples: their spacing (the median). Samples that come unevenly spaced,
    e.g. in pairs (a controller reporting twice per cycle, 1 ms then 19 ms) or in bursts
    (receipt times batched by TCP, a logger at 1 kHz bunching ~15 samples per 15.6 ms tick):
    the median is the short spacing, and 3x it flagged every long one, the sampling itself, as
    a dropout (a 50 Hz robot in pairs was discarded for every 100 ms frame: kalman-robot fell
    back to NCC alone, e_M 10.5 -> 117.9 px; review). The short spacings there hold little of
    the time and the long ones are over 5 % of the spacings (one per burst of up to 20), so
    both robust spacings are the long one. A dropout is a long interval holding much of the
    time but few of the spacings: it raises the quartile only when it holds over 75 % of the
    span (a tracker off for frames 0-85 of 110), the percentile only when dropouts are over 5 %
    of the spacings, so the smaller of the two stays the sampling's."""
    spacing = np.sort(np.diff(np.asarray(times, dtype=np.float64)))
    if spacing.size == 0:
        raise ValueError("sample_spacing: needs at least 2 sample times")
    cumulative = np.cumsum(spacing)
    quartile = spacing[min(int(np.searchsorted(cumulative, 0.25 * cumulative[-1])),
                           spacing.size - 1)]
    return max(float(np.median(spacing)),
               min(float(quartile), float(np.percentile(spacing, 95, method="lower"))))


def _beyond(spacing, max_gap: float):
    """spacing > max_gap beyond rounding: a dropout of two samples at 40 Hz spans 3 x 25 ms,
    which the sums of float timestamps give as 0.07500000000000007 in one place and
    0.07499999999999998 in another; the same dropout is flagged or not the same everywhere."""
    return np.asarray(spacing) > max_gap * (1.0 + 1e-9)


def interpolate_camera_poses(
    samples: TrackingSamples,
    frame_times,
    sensor_from_camera=None,
    *,
    max_gap: float | None = None,
    allow_outside: bool = False,
    source: str = "tracking.csv",
    method: str = "linear",
) -> tuple[np.ndarray, np.ndarray]:
    """Camera poses at frame times from tracker samples (paper 000, Sec. 3: tracker poses are
    interpolated to the frames, then composed with the hand-eye transform).

    tracker_from_sensor is interpolated between the valid samples around each frame time:
    ``method="linear"`` SLERPs the rotation and interpolates the translation linearly;
    ``"cubic"`` passes SciPy's RotationSpline and a not-a-knot CubicSpline through the samples
    of each stretch without a gap (for a sparse tracker, e.g. 10 Hz, on a curved motion, where
    the chord between two samples cuts the curve by millimetres). world_from_cam =
    tracker_from_sensor @ sensor_from_camera; returns cam_from_world (N, 6) = [angle-axis, t]
    and valid (N,) bool.

    Frames outside the tracker's time span, its first to last sample (missing ones included:
    the tracker was running), raise ValueError, or with ``allow_outside`` are flagged invalid.
    Frames inside a gap between valid samples longer than ``max_gap`` (default 3x the valid
    samples' typical spacing, sample_spacing) are flagged invalid, and so are frames before the
    first valid sample or after the last one among missing samples (a sensor that enters the
    field after the recording starts): a gap of invalid samples at an end. Invalid frames get
    NaN poses.
    """
    if method not in ("linear", "cubic"):
        raise ValueError(f"interpolation method must be 'linear' or 'cubic', got {method!r}")
    frame_times = np.asarray(frame_times, dtype=np.float64).reshape(-1)
    X = np.eye(4) if sensor_from_camera is None else np.asarray(sensor_from_camera, np.float64)
    if X.shape != (4, 4):
        raise ValueError(f"sensor_from_camera must be 4x4, got {X.shape}")
    if sensor_from_camera is not None:  # (a sheared one was projected: poses 0.26 rad off)
        X = _checked_hand_eye(X, "hand-eye (sensor_from_camera)")
    ts = samples.timestamps[samples.valid]
    if ts.size < 2:
        raise ValueError(f"{source}: {ts.size} valid samples; interpolation needs at least 2")
    if np.any(np.diff(ts) <= 0):
        raise ValueError(f"{source}: timestamps must be strictly increasing")
    _check_rates(frame_times, ts, source, "tracker")
    rows = samples.timestamps[np.isfinite(samples.timestamps)]
    outside = _outside_span(frame_times, min(rows.min(), ts[0]), max(rows.max(), ts[-1]),
                            source, "tracker", allow_outside, span=" (its first to last "
                            "sample, missing ones included)")
    unsampled = (frame_times < ts[0]) | (frame_times > ts[-1])  # among missing samples

    if max_gap is None:
        max_gap = GAP_SPACINGS * sample_spacing(ts)
    # Interval [ts[k], ts[k+1]] holding each frame; a frame exactly on a sample is measured.
    k = np.clip(np.searchsorted(ts, frame_times, side="right") - 1, 0, ts.size - 2)
    on_sample = (frame_times == ts[k]) | (frame_times == ts[k + 1])
    in_gap = _beyond(ts[k + 1] - ts[k], max_gap) & ~on_sample
    valid = ~outside & ~in_gap & ~unsampled

    cam_from_world = np.full((frame_times.size, 6), np.nan)
    if valid.any():
        t = frame_times[valid]
        rotations = Rotation.from_quat(samples.quaternions[samples.valid])
        translations = samples.translations[samples.valid]
        if method == "cubic":
            R_ts, t_ts = _cubic(ts, rotations, translations, t, max_gap)
        else:
            R_ts = Slerp(ts, rotations)(t)
            t_ts = np.stack([np.interp(t, ts, translations[:, j]) for j in range(3)], axis=1)
        cam_from_world[valid] = _cam_from_world(R_ts, t_ts, X)
    return cam_from_world, valid


def _cubic(ts: np.ndarray, rotations: Rotation, translations: np.ndarray, t: np.ndarray,
           max_gap: float) -> tuple[Rotation, np.ndarray]:
    """tracker_from_sensor at times t (inside the samples' span, not inside a gap) from splines
    through the samples of each stretch whose spacing stays <= max_gap: a gap (a dropout)
    starts a new spline, so samples across it do not bend the curve on either side."""
    breaks = np.flatnonzero(_beyond(np.diff(ts), max_gap)) + 1
    last = np.searchsorted(ts, t, side="right") - 1  # the latest sample at or before t
    stretch = np.searchsorted(breaks, last, side="right")
    quats = np.empty((t.size, 4))
    out = np.empty((t.size, 3))
    bounds = np.concatenate([[0], breaks, [ts.size]])
    for s in np.unique(stretch):
        a, b = bounds[s], bounds[s + 1]
        m = stretch == s
        if b - a < 2:  # a lone sample: only a frame exactly on it is valid
            quats[m] = rotations[a].as_quat()
            out[m] = translations[a]
            continue
        tt = np.clip(t[m], ts[a], ts[b - 1])
        quats[m] = RotationSpline(ts[a:b], rotations[a:b])(tt).as_quat()
        # not-a-knot: through two samples a straight line, through three a parabola
        out[m] = CubicSpline(ts[a:b], translations[a:b], axis=0)(tt)
    return Rotation.from_quat(quats), out


def _cam_from_world(R_ts: Rotation, t_ts: np.ndarray, X: np.ndarray) -> np.ndarray:
    """[angle-axis, t] (N, 6) of cam_from_world from tracker_from_sensor and sensor_from_camera
    X: world_from_cam = [R_ts | t_ts] @ X."""
    R_wc = R_ts * Rotation.from_matrix(X[:3, :3])
    t_wc = R_ts.apply(X[:3, 3]) + t_ts
    R_cw = R_wc.inv()
    return np.hstack([R_cw.as_rotvec().reshape(-1, 3), -R_cw.apply(t_wc).reshape(-1, 3)])


def camera_pose_from_sample(translation, quaternion, sensor_from_camera=None) -> np.ndarray:
    """The camera pose cam_from_world [angle-axis (rad), t (mm)] of ONE tracker sample
    (tracker_from_sensor: translation in mm, quaternion x, y, z, w as in tracking.csv) through
    the hand-eye transform sensor_from_camera (4x4, identity if None): what
    ``SequentialMosaicker.add_frame`` takes as ``tracker_pose`` in a live loop, where the sample
    after the frame time is not there yet to interpolate (interpolate_camera_poses does that
    for recorded samples). Checked as tracking.csv and hand_eye.txt are: ValueError for
    non-finite values, a quaternion whose norm is not 1 (to QUATERNION_NORM_TOLERANCE: another
    field order, or a corrupt sample) and a hand-eye that is not a rigid transform."""
    t = np.asarray(translation, dtype=np.float64)
    q = np.asarray(quaternion, dtype=np.float64)
    X = np.eye(4) if sensor_from_camera is None else np.asarray(sensor_from_camera, np.float64)
    if t.shape != (3,) or q.shape != (4,) or X.shape != (4, 4):
        raise ValueError(f"tracker sample: expected translation (3,), quaternion (4,) and a 4x4 "
                         f"hand-eye, got {t.shape}, {q.shape}, {X.shape}")
    if not (np.isfinite(t).all() and np.isfinite(q).all() and np.isfinite(X).all()):
        raise ValueError("tracker sample: translation, quaternion and hand-eye must be finite")
    norm = float(np.linalg.norm(q))
    if not abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE:
        raise ValueError(f"tracker sample: quaternion {q.tolist()} has norm {norm:.6g}, not 1 "
                         f"(tolerance {QUATERNION_NORM_TOLERANCE:g}): x, y, z, w of a rotation")
    if sensor_from_camera is not None:
        X = _checked_hand_eye(X, "hand-eye (sensor_from_camera)")
    return _cam_from_world(Rotation.from_quat(q), t, X)[0]


def interpolate_robot(
    samples: RobotSamples,
    frame_times,
    *,
    allow_outside: bool = False,
    source: str = "robot.csv",
) -> tuple[np.ndarray, np.ndarray]:
    """Robot positions (N, 2) µm at frame times, linear between samples, and valid (N,) bool.
    Frames outside the robot's time span raise, or with ``allow_outside`` get NaN/invalid;
    frames in a gap between samples (longer than 3x their typical spacing, sample_spacing: a
    robot sampled in pairs or bursts is not in a gap between them) are flagged invalid,
    as interpolate_camera_poses does (a 2 s gap was bridged by a straight line: kalman-robot
    103 px off to the end, worse than ncc alone)."""
    frame_times = np.asarray(frame_times, dtype=np.float64).reshape(-1)
    ts = samples.timestamps
    if ts.size == 0:
        raise ValueError(f"{source}: no samples")
    if np.any(np.diff(ts) <= 0):
        raise ValueError(f"{source}: timestamps must be strictly increasing")
    _check_rates(frame_times, ts, source, "robot")
    outside = _outside_span(frame_times, ts[0], ts[-1], source, "robot", allow_outside)
    xy = np.stack([np.interp(frame_times, ts, samples.xy_um[:, j]) for j in range(2)], axis=1)
    invalid = outside.copy()
    if ts.size >= 2:
        k = np.clip(np.searchsorted(ts, frame_times, side="right") - 1, 0, ts.size - 2)
        on_sample = (frame_times == ts[k]) | (frame_times == ts[k + 1])
        invalid |= _beyond(ts[k + 1] - ts[k], GAP_SPACINGS * sample_spacing(ts)) & ~on_sample
    xy[invalid] = np.nan
    return xy, ~invalid
