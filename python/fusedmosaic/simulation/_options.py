"""Pieces shared by the simulators' option dataclasses (FetoscopyOptions, PcleOptions,
CheckerboardOptions)."""

from __future__ import annotations

import math
import numbers
from dataclasses import field, fields

import numpy as np

from fusedmosaic.io.tracking import (
    MAX_FRAME_SPACING_S,
    MAX_SAMPLE_TO_FRAME_SPACING,
    MAX_TIME_OFFSET_S,
    MAX_TIMESTAMP_S,
    MAX_TRANSLATION_MM,
)

# Tracker / robot samples of one simulated recording (a 40 Hz tracker over 70 hours): more is a
# rate, margin or frame rate off by orders of magnitude, not a recording.
MAX_SAMPLES = 10_000_000
# Frames of one simulated sequence: over an hour of video at 25 frames/s (tens of GB of PNGs at
# 400x400; the papers' sequences have ~100-300 frames). Checked before anything is computed.
MAX_FRAMES = 100_000
# Tracker / robot samples per frame beyond which the rate, not the frame count, is taken for
# the cause of too many samples (a 40 Hz tracker at 25 frames/s takes 1.6).
_SAMPLES_PER_FRAME_IS_THE_RATE = 1000.0
# mm, |sensor_from_camera translation|: a sensor mounted on the scope, not across the room.
MAX_HAND_EYE_OFFSET_MM = 1000.0
# The smallest circular field of view (radius, px) a simulator renders (0: none).
MIN_FOV_RADIUS_PX = 16.0
# Standard deviations of Gaussian noise no draw of a simulation reaches (P(|z| > 10) ~ 1e-23,
# against at most 3e7 draws): the bound on where noisy tracker / robot positions can land.
NOISE_REACH_SIGMAS = 10.0
# deg, rotation noise std of a simulated tracker: beyond half a turn its orientation is random.
MAX_ROTATION_SIGMA_DEG = 180.0


def option(default, help_text: str, choices: tuple | None = None):
    """A dataclass field whose default, one-line help and allowed values (used by the CLI) sit
    together."""
    metadata = {"help": help_text}
    if choices is not None:
        metadata["choices"] = choices
    return field(default=default, metadata=metadata)


def check_types(options, whole: tuple[str, ...] = ()) -> None:
    """Raise ValueError naming the first field of ``options`` that is not of its type: each
    field of ``whole`` (frame counts, sizes) must be a whole number, and an integral float
    there (200.0 from a config file or W / 2) is converted to int in place; every field
    declared float must be a real number; bool fields True or False; list fields a list (or
    tuple, or 1-D array; None where the field allows it), of real numbers for list[float]
    (list[int] fields hold frame indices, which check_frame_list checks). bools are refused as
    numbers (True is 1 to Python, not a size). Run first by validate, before any comparison:
    text or 200.5 gave TypeErrors or cv2.error deep inside rendering (review 44); a scalar for
    a list, "'int' object is not iterable", and contact_loss="no" simulated contact loss
    (review 47)."""
    cls = type(options).__name__
    for f in fields(options):
        value = getattr(options, f.name)
        # "float", "bool", "list[int] | None", as written (a string under postponed
        # annotations, else the class or the typing expression)
        declared = (f.type if isinstance(f.type, str) else f.type.__name__
                    if f.type in (bool, float, int, str) else str(f.type))
        number = _is_number(value)
        if f.name in whole:
            if not (number and math.isfinite(value) and value == int(value)):
                raise ValueError(f"{cls}.{f.name}: must be a whole number, got {value!r}")
            setattr(options, f.name, int(value))
        elif declared == "float" and not number:
            raise ValueError(f"{cls}.{f.name}: must be a number, got {value!r}")
        elif declared == "bool" and not isinstance(value, (bool, np.bool_)):
            raise ValueError(f"{cls}.{f.name}: must be True or False, got {value!r}")
        elif declared.startswith("list[") and not (value is None and "None" in declared):
            of = "numbers" if declared.startswith("list[float]") else "frame indices"
            if not (isinstance(value, (list, tuple))
                    or (isinstance(value, np.ndarray) and value.ndim == 1)) or (
                    of == "numbers" and not all(_is_number(v) for v in value)):
                raise ValueError(f"{cls}.{f.name}: expected a list of {of}, got {value!r}")


def _is_number(value) -> bool:
    """A real number, not a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def check_finite(options) -> None:
    """Raise ValueError naming the first numeric field (in declaration order) that is NaN or
    infinite: no simulator option means anything there (NaN also slips past comparisons, so a
    bound check alone lets it through). List fields are checked by their own validators."""
    cls = type(options).__name__
    for f in fields(options):
        value = getattr(options, f.name)
        if isinstance(value, numbers.Real) and not isinstance(value, bool) \
                and not math.isfinite(value):
            raise ValueError(f"{cls}.{f.name}: must be a finite number, got {value}")


def check_signs(options, *, positive=(), non_negative=()) -> None:
    """Raise ValueError naming the first numeric field of ``options`` that is not finite
    (check_finite), then the first field of `positive` not > 0, then of `non_negative`
    not >= 0."""
    check_finite(options)
    cls = type(options).__name__
    seed = getattr(options, "seed", 0)  # numpy's seeds are integers >= 0
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise ValueError(f"{cls}.seed: must be an integer >= 0, got {seed}")
    for names, ok, rule in ((positive, lambda v: v > 0, "> 0"),
                            (non_negative, lambda v: v >= 0, ">= 0")):
        for name in names:
            value = getattr(options, name)
            if not ok(value):
                raise ValueError(f"{cls}.{name}: must be {rule}, got {value}")


def check_frame_list(options, name: str, n_frames: int | None = None) -> list[int]:
    """The list field ``name`` as ints, or ValueError naming it when an entry is not a whole
    number (NaN, inf, 2.5, text) or, given n_frames, outside 0..n_frames - 1."""
    values = getattr(options, name)
    bad = [v for v in values if isinstance(v, bool) or not isinstance(v, numbers.Real)
           or not math.isfinite(v) or v != int(v)]
    if bad:
        raise ValueError(f"{type(options).__name__}.{name}: expected frame indices (whole "
                         f"numbers), got {values}")
    frames = [int(v) for v in values]
    outside = [k for k in frames if n_frames is not None and not 0 <= k < n_frames]
    if outside:
        raise ValueError(f"{type(options).__name__}.{name}: frame {outside[0]} outside "
                         f"0..{n_frames - 1}")
    return frames


def check_time_offsets(options, *names: str) -> None:
    """Raise ValueError naming the first of ``names`` (clock offsets or delays, s) beyond
    io.tracking.MAX_TIME_OFFSET_S, the bound run / import / calibrate put on a clock offset."""
    for name in names:
        value = getattr(options, name)
        if not abs(value) <= MAX_TIME_OFFSET_S:
            raise ValueError(f"{type(options).__name__}.{name}: must be within "
                             f"+-{MAX_TIME_OFFSET_S:g} s, got {value}")


def check_tracker_reach(options, camera_mm: float, camera: str, camera_fields: tuple[str, ...],
                        noise_mm: float, noise_fields: tuple[str, ...]) -> None:
    """tracking.csv's positions within what run reads (io.tracking.MAX_TRANSLATION_MM of the
    tracker's origin): the camera's reach ``camera_mm`` ("{camera} N mm from the tracker's
    origin", made of ``camera_fields``), then with the hand-eye offset and NOISE_REACH_SIGMAS
    of the translation noise std ``noise_mm`` (the product of ``noise_fields``). Each error
    names the field furthest from its default (most_changed)."""
    cls = type(options).__name__
    beyond = (f"beyond the {MAX_TRANSLATION_MM:g} mm a tracker position may hold "
              "(io.tracking.MAX_TRANSLATION_MM)")
    if not camera_mm <= MAX_TRANSLATION_MM:
        named = ", ".join(f"{cls}.{name}" for name in camera_fields)
        raise ValueError(f"{cls}.{most_changed(options, *camera_fields)}: {camera} "
                         f"{camera_mm:.3g} mm from the tracker's origin ({named}), {beyond}")
    reach = (camera_mm + abs(options.hand_eye_offset_mm)
             + NOISE_REACH_SIGMAS * np.sqrt(3.0) * noise_mm)
    if not reach <= MAX_TRANSLATION_MM:
        made = ("" if len(noise_fields) == 1
                else " (" + " x ".join(f"{cls}.{name}" for name in noise_fields) + ")")
        raise ValueError(f"{cls}.{most_changed(options, *noise_fields)}: a tracker translation "
                         f"noise of {noise_mm:.3g} mm{made} puts tracker positions up to "
                         f"{reach:.3g} mm from its origin, {beyond}")


def most_changed(options, *names: str) -> str:
    """Of the numeric fields ``names``, the one furthest (by ratio) from its default: what an
    error about a product of them names first, as its likely cause. Ties: the first."""
    defaults = {f.name: f.default for f in fields(options)}

    def deviation(name: str) -> float:
        value, default = abs(getattr(options, name)), abs(defaults[name])
        if value == default:
            return 0.0
        if value == 0 or default == 0:
            return math.inf
        return abs(math.log(value / default))

    return max(names, key=deviation)


def check_fov_radius(options, auto: bool = False) -> None:
    """fov_mask_radius: 0 (none) or at least MIN_FOV_RADIUS_PX; with ``auto`` also -1 (the
    simulator's own choice)."""
    r = options.fov_mask_radius
    if (0 < r < MIN_FOV_RADIUS_PX) or (r < 0 and not (auto and r == -1)):
        choices = "0: the whole frame, -1: auto" if auto else "0: the whole frame"
        raise ValueError(f"{type(options).__name__}.fov_mask_radius: a field of at least "
                         f"{MIN_FOV_RADIUS_PX:g} px ({choices}), got {r}")


def check_frame_count(options, n_frames, frames_name: str) -> None:
    """At most MAX_FRAMES frames; ``frames_name`` names the option(s) that set the count."""
    if not n_frames <= MAX_FRAMES:
        raise ValueError(f"{frames_name}: {n_frames:.6g} frames; at most {MAX_FRAMES} (over an "
                         "hour of video at 25 frames/s)")


def check_recording(options, n_frames: int, frames_name: str, prefix: str) -> None:
    """Before anything is computed, what frame_times and sample_times would give, against the
    bounds io.read_dataset / io.tracking put on a dataset (so that what simulate writes, run
    reads): at most MAX_FRAMES frames (check_frame_count), timestamps within MAX_TIMESTAMP_S,
    frames at most MAX_FRAME_SPACING_S apart, the tracker's (prefix "tracker") or robot's
    ("robot") samples as check_samples wants them, and at most MAX_SAMPLE_TO_FRAME_SPACING
    frames apart (sparser, run takes them for timestamps in another unit). ``frames_name``
    names the option(s) that set n_frames; ValueError naming the likely cause."""
    cls = type(options).__name__
    check_frame_count(options, n_frames, frames_name)
    fps = options.fps
    t_last = (n_frames - 1) / fps
    _check_span(options, n_frames, t_last)
    if n_frames >= 2 and not 1.0 / fps <= MAX_FRAME_SPACING_S:
        raise ValueError(f"{cls}.fps: frames {1.0 / fps:.3g} s apart ({fps:g} fps), more than "
                         f"the {MAX_FRAME_SPACING_S:g} s run accepts between frames "
                         "(io.tracking.MAX_FRAME_SPACING_S): at least "
                         f"{1.0 / MAX_FRAME_SPACING_S:g} fps")
    check_samples(options, prefix, t_last, n_frames, frames_name)
    rate = getattr(options, f"{prefix}_rate_hz")
    if n_frames >= 3 and not fps <= MAX_SAMPLE_TO_FRAME_SPACING * rate:
        lead = most_changed(options, "fps", f"{prefix}_rate_hz")
        raise ValueError(
            f"{cls}.{lead}: a {prefix} at {rate:g} Hz ({cls}.{prefix}_rate_hz) against frames "
            f"at {fps:g} fps ({cls}.fps) samples every {fps / rate:.3g} frames, more than the "
            f"{MAX_SAMPLE_TO_FRAME_SPACING:g} frames apart run accepts (io.tracking."
            "MAX_SAMPLE_TO_FRAME_SPACING: sparser, it takes the timestamps for another unit): "
            f"at most {MAX_SAMPLE_TO_FRAME_SPACING * rate:g} fps at {rate:g} Hz")


def _check_span(options, n_frames: int, t_last: float) -> None:
    if not t_last <= MAX_TIMESTAMP_S:
        raise ValueError(f"{type(options).__name__}.fps: {n_frames} frames at {options.fps:g} "
                         f"fps span {t_last:.3g} s, beyond the {MAX_TIMESTAMP_S:g} s a "
                         "timestamp may hold")


def _sample_range(options, prefix: str, t_last: float) -> tuple[float, float, float]:
    """(j0, j1, period): sample_times' samples are offset + j period, j = j0..j1."""
    period = 1.0 / getattr(options, f"{prefix}_rate_hz")
    offset = getattr(options, f"{prefix}_offset_s")
    margin = getattr(options, f"{prefix}_margin_s")
    return (float(np.floor((-margin - offset) / period)),
            float(np.ceil((t_last + margin - offset) / period)), period)


def check_samples(options, prefix: str, t_last: float, n_frames: int | None = None,
                  frames_name: str | None = None) -> None:
    """The samples sample_times would make: at most MAX_SAMPLES, within MAX_TIMESTAMP_S.
    ValueError naming the rate when it takes over _SAMPLES_PER_FRAME_IS_THE_RATE samples per
    frame, the margin when the margins make most of the samples, and otherwise the frame count
    (``frames_name``; the rate when none is given) and the frame rate."""
    cls = type(options).__name__
    rate = getattr(options, f"{prefix}_rate_hz")
    offset = getattr(options, f"{prefix}_offset_s")
    margin = getattr(options, f"{prefix}_margin_s")
    j0, j1, period = _sample_range(options, prefix, t_last)
    count = j1 - j0 + 1
    rate_name, margin_name = f"{cls}.{prefix}_rate_hz", f"{cls}.{prefix}_margin_s"
    where = (f"{rate_name}: {rate:g} Hz over the {t_last:.3g} s of the frames and "
             f"{margin_name} ({margin:g} s) on both sides")
    if not count <= MAX_SAMPLES:
        if rate / options.fps > _SAMPLES_PER_FRAME_IS_THE_RATE or (
                n_frames is None and 2 * margin < t_last):
            raise ValueError(f"{where} is {count:.3g} samples; at most {MAX_SAMPLES:.3g}")
        if 2 * margin >= t_last:
            raise ValueError(f"{margin_name}: {margin:g} s on both sides of the {t_last:.3g} s "
                             f"of the frames at {rate:g} Hz ({rate_name}) is {count:.3g} "
                             f"{prefix} samples; at most {MAX_SAMPLES:.3g}")
        raise ValueError(f"{frames_name}: {n_frames} frames at {options.fps:g} fps ({cls}.fps) "
                         f"last {t_last:.3g} s, over which the {prefix} at {rate:g} Hz "
                         f"({rate_name}) takes {count:.3g} samples; at most "
                         f"{MAX_SAMPLES:.3g}: fewer frames or a higher frame rate")
    reach = max(abs(offset + j0 * period), abs(offset + j1 * period))
    if not reach <= MAX_TIMESTAMP_S:
        lead = where if margin <= MAX_TIMESTAMP_S / 2 else (
            f"{margin_name}: {margin:g} s on both sides of the frames at {rate:g} Hz "
            f"({rate_name})")
        raise ValueError(f"{lead} puts samples at {reach:.3g} s, beyond the "
                         f"{MAX_TIMESTAMP_S:g} s a timestamp may hold")


def check_hand_eye(options) -> None:
    """hand_eye_rot_deg within one turn, hand_eye_offset_mm within MAX_HAND_EYE_OFFSET_MM."""
    cls = type(options).__name__
    if not abs(options.hand_eye_rot_deg) <= 360.0:
        raise ValueError(f"{cls}.hand_eye_rot_deg: must be within +-360 deg, got "
                         f"{options.hand_eye_rot_deg}")
    if not abs(options.hand_eye_offset_mm) <= MAX_HAND_EYE_OFFSET_MM:
        raise ValueError(f"{cls}.hand_eye_offset_mm: must be within "
                         f"+-{MAX_HAND_EYE_OFFSET_MM:g} mm (a sensor on the scope), got "
                         f"{options.hand_eye_offset_mm}")


def frame_times(options, n_frames: int) -> np.ndarray:
    """(n_frames,) frame times k / options.fps, s; ValueError naming fps when they run beyond
    io.tracking.MAX_TIMESTAMP_S (what a dataset's timestamps may hold)."""
    _check_span(options, n_frames, (n_frames - 1) / options.fps)
    return np.arange(n_frames) / options.fps


def sample_times(options, prefix: str, t_last: float) -> np.ndarray:
    """Sample times of the tracker (prefix "tracker") or robot ("robot") on its own clock:
    period 1 / <prefix>_rate_hz, phase <prefix>_offset_s, covering [-<prefix>_margin_s,
    t_last + <prefix>_margin_s]. ValueError (check_samples) when that is over MAX_SAMPLES
    samples or reaches beyond io.tracking.MAX_TIMESTAMP_S (the validators check this first,
    with the frame count)."""
    check_samples(options, prefix, t_last)
    j0, j1, _ = _sample_range(options, prefix, t_last)
    # j / rate, as frame_times' k / fps: a sampler at the frame rate with offset 0 stamps the
    # frame times exactly (j * (1 / rate) gave 0.30000000000000004 for frame 3 at 0.3 s, and
    # a live replay took the sample 100 ms older; review)
    rate = getattr(options, f"{prefix}_rate_hz")
    return getattr(options, f"{prefix}_offset_s") + np.arange(j0, j1 + 1) / rate
