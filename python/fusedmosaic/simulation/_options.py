"""Pieces shared by the simulators' option dataclasses (FetoscopyOptions, PcleOptions,
CheckerboardOptions)."""

from __future__ import annotations

import math
import numbers
from dataclasses import field, fields

import numpy as np

from fusedmosaic.io.tracking import MAX_TIME_OFFSET_S, MAX_TIMESTAMP_S

# Tracker / robot samples of one simulated recording (a 40 Hz tracker over 70 hours): more is a
# rate, margin or frame rate off by orders of magnitude, not a recording.
MAX_SAMPLES = 10_000_000
# mm, |sensor_from_camera translation|: a sensor mounted on the scope, not across the room.
MAX_HAND_EYE_OFFSET_MM = 1000.0


def option(default, help_text: str, choices: tuple | None = None):
    """A dataclass field whose default, one-line help and allowed values (used by the CLI) sit
    together."""
    metadata = {"help": help_text}
    if choices is not None:
        metadata["choices"] = choices
    return field(default=default, metadata=metadata)


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
    t_last = (n_frames - 1) / options.fps
    if not t_last <= MAX_TIMESTAMP_S:
        raise ValueError(f"{type(options).__name__}.fps: {n_frames} frames at {options.fps:g} "
                         f"fps span {t_last:.3g} s, beyond the {MAX_TIMESTAMP_S:g} s a "
                         "timestamp may hold")
    return np.arange(n_frames) / options.fps


def sample_times(options, prefix: str, t_last: float) -> np.ndarray:
    """Sample times of the tracker (prefix "tracker") or robot ("robot") on its own clock:
    period 1 / <prefix>_rate_hz, phase <prefix>_offset_s, covering [-<prefix>_margin_s,
    t_last + <prefix>_margin_s]. ValueError naming the rate when that is over MAX_SAMPLES
    samples or reaches beyond io.tracking.MAX_TIMESTAMP_S."""
    rate = getattr(options, f"{prefix}_rate_hz")
    offset = getattr(options, f"{prefix}_offset_s")
    margin = getattr(options, f"{prefix}_margin_s")
    period = 1.0 / rate
    j0 = np.floor((-margin - offset) / period)
    j1 = np.ceil((t_last + margin - offset) / period)
    where = (f"{type(options).__name__}.{prefix}_rate_hz: {rate:g} Hz over the {t_last:.3g} s "
             f"of the frames and {prefix}_margin_s ({margin:g} s) on both sides")
    count = j1 - j0 + 1
    if not count <= MAX_SAMPLES:
        raise ValueError(f"{where} is {count:.3g} samples; at most {MAX_SAMPLES:.3g}")
    times = offset + np.arange(j0, j1 + 1) * period
    if not np.abs(times).max() <= MAX_TIMESTAMP_S:
        raise ValueError(f"{where} puts samples at {np.abs(times).max():.3g} s, beyond the "
                         f"{MAX_TIMESTAMP_S:g} s a timestamp may hold")
    return times
