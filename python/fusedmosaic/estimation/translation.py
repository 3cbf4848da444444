"""Translation-only pCLE mosaicking with a robot prior (Rosa et al. 2018, paper 004).

Three estimates of where frame i sits in the mosaic, relative to frame 0 (pixels, image axes:
x right, y down), each written as the frame -> reference translation ``G_i = [[1, 0, x],
[0, 1, y], [0, 0, 1]]``:

- ``X_m`` (method ``ncc``), Eq. 1-2: the image-only chain of forward/backward NCC registrations
  ``X_m(i) = X_m(i-1) + dX_{i-1}^i`` (:func:`fusedmosaic.registration.ncc.register_ncc`).
- ``X_r`` (method ``robot``), Eq. 3: the robot positions at the frame times, relative to frame 0,
  converted from µm with ``pixel_size_um``.
- ``X_f`` (method ``kalman-robot``), Eq. 4-18: the two fused per frame by
  :class:`fusedmosaic.estimation.kalman.RobotKalmanFilter`, with the confidences ``c_angle``,
  ``c_speed``, ``c_match`` (SSIM of the aligned overlap), ``c_img``, ``c_sp``, ``c_rob``.

Sign convention: frame i's pixel ``u`` shows the point ``u + X(i)`` of frame 0's pixel grid,
i.e. ``X`` is the position of the field of view over the tissue. The simulator's
``ground_truth.csv`` uses the same one (translation by ``(p_i - p_0) / pixel_size_um``).

:class:`RobotPriorMosaicker` is the streaming form (``add_frame(image, timestamp, robot_xy_um)``,
one call per acquired frame); ``run_ncc``, ``run_robot`` and ``run_kalman_robot`` feed it a
dataset frame by frame, so offline runs and live use share one code path. The mosaic is composed
by averaging every pixel landing on a canvas pixel (``blend="average"``, Sec. III-D).

Graceful degradation: a frame without a robot sample (NaN) follows the image (``c_rob = 0``); a
blank frame (constant image, e.g. a dropped frame) or a failed registration follows the robot
(``c_img = 0``) and is reported as ``prior-only``. The next textured frame is registered against
the last frame whose registration succeeded (the *anchor*), and the robot displacement is taken
from the last frame that had a robot sample, so a gap costs accuracy but never breaks the chain.

A registration whose forward and backward directions disagree even after the wide-range retry
(``NccResult.consistent`` False, e.g. a low-contrast frame where one direction locks on noise)
counts as failed for the fused estimate (``distrust_inconsistent``): the robot places the frame.
Without a robot sample at that frame it is the only information left, and is used as the image
chain uses it (a robot dropout must not leave the fused estimate worse than X_m).

Robot noise (``sigma_r0`` of Eq. 9). The paper gives no value for ``sigma_r0`` and ``sigma_i0``
("initial values", with ``sigma_r0(i)`` indexed by time in Eq. 9). The ratio decides everything:
with an accurate robot the filter should follow the robot wherever the image is doubtful, with a
noisy one (paper Sec. III-C: miniature mechanisms, noisy sensors) it should follow the image.
The robot's per-frame displacement error differs by orders of magnitude between setups (0.2 µm
resolution stage vs the paper's artificially noised input) and the user rarely knows it, so by
default (``adaptive_robot_sigma``) it is estimated online, as in innovation-based adaptive
Kalman filtering (Mehra 1970, IEEE TAC 15(2)): ``sigma_r0`` = the robust scale (1.4826 x median
absolute value) of the robot-minus-image displacement over the last ``robot_sigma_window``
frames whose image was trusted (``c_img >= 0.5``), floored at ``robot_sigma_floor_px``. Until
``robot_sigma_min_frames`` such frames exist the robot is uninformative (``sigma_r0 = inf``,
``robot_unknown_at_start``: the paper relies on the image at the start, Sec. II-B; else
``KalmanOptions.sigma_robot0`` is used), except on a frame whose registration the filter does
not trust (``c_img < robot_sigma_c_img``, e.g. a contact loss in the first frames): an infinite
``sigma_r0`` would let a registration of confidence ~0.1 place it, so the registration is left
out and the robot places the frame ("Image gating" below). Trust in the filter's warm-up: there
c_img is the initial ``c_img0 = 1`` of Sec. II-B, whatever the registration, so a registration
is trusted when its ``c_match`` reaches ``warmup_overlap_c_match`` or its SSIM gains at least
``warmup_ssim_margin`` over the same pair's SSIM at 0 px (the frames visibly overlap at the
shift found; a fibre-pattern lock lands at 0 px and gains nothing); this judgement decides the
``sigma_r0`` samples and both gates below. A recording starting inside a contact loss had its
lock placed 40 px off for good, all frames (e_M 38.8 px, robot 0.02). A robot sampled more
slowly than the frames
(``robot_xy_um`` None between samples) feeds the estimate with displacements spanning up to
``robot_sigma_max_span`` frames. With ``adaptive_robot_sigma=False`` the filter is the paper's
with fixed ``sigma_robot0``.

Robot gating (not in the paper). Eq. 17-18 bound the robot's confidence below by
``c_rob >= 1 - c_img`` (``c_sp`` compares speed *ratios*, so it saturates), whatever the size of
the disagreement: with an accurate robot (small ``sigma_r0``) one grossly wrong sample (a
glitch of +5 mm) still outweighs a confident image, and because the next robot displacement
was taken from that sample, the error went on into every later frame. So, as the fetoscopy
tracker is gated (``SequentialOptions.gate_chi2``): a robot displacement that disagrees with a
trusted registration (``c_img >= robot_sigma_c_img``) by more than ``robot_gate_sigmas x
sigma_r0`` and more than ``robot_gate_fraction`` of the frame's smaller side is left out of the
filter (the frame follows the image, ``c_rob = 0``), kept out of the ``sigma_r0`` estimate, and
the next robot displacement is taken from the last sample that was not gated; the frame is
flagged ``FrameResult.robot_gated``. After ``robot_gate_rebase`` gated frames in a row the robot
is taken to have a new offset and is re-anchored at the current frame. The bounds are per frame:
when the robot returns after frames without a sample (a dropout), its displacement spans those
frames too and differs from the registration by the image chain's drift over them, which the
returning robot is there to correct; so the bounds are allowed once per frame spanned (the
drift each frame would have been let through with), up to ``robot_gate_max_span`` times (a
larger jump stays a glitch however long the dropout), and a re-acquisition spanning more than
``robot_sigma_max_span`` frames is kept out of the ``sigma_r0`` estimate. While the filter is
in its warm-up (``c_img`` is the initial ``c_img0``, no judgement) and no registration has
agreed with the robot yet, a registration disagreeing beyond the bounds does not veto the
robot: the robot places the frame, as for an inconsistent registration (a fast scan whose
frames do not overlap, its registrations locking on the fibre pattern), unless the frames
visibly overlap (the warm-up's trust, above: the robot is gated, e.g. a glitch at frame 1).
Such a frame adds no image step to the filter's history, so the warm-up would never end: after
``robot_gate_rebase`` such registrations in a row (a robot disagreeing with every frame, e.g. in
the wrong units), they are believed over the robot, as ``robot_gate_rebase`` gated frames in a
row make the robot believed over them: the robot is judged (gated) from then on.

Unconfirmed robot steps (robot gating, not in the paper). On a frame the robot places alone (no
usable registration: inconsistent directions, failed, blank, unjudged, or image-gated) nothing
above judges the robot, and a glitch went through: the frame was placed at it, both anchors
moved there, the next trusted registrations chained from it and, disagreeing with the correct
robot, had it gated and, after ``robot_gate_rebase`` frames, re-anchored at the wrong X_f: the
offset was permanent (review 51; simulator 256x224 px, 60 frames, seed 0, mean error 7.1 µm
without a glitch: a +300 µm sample at frame 12, a contact loss, 332.6 µm; +5000 µm, 5650 µm;
+300 µm at frame 34, image-gated, 188 µm; no warning). A robot is a smooth actuator, so such a
step is judged against the robot's *own* recent motion (:meth:`RobotPriorMosaicker._robot_jump`):
its last anchor extrapolated at its velocity between its last two anchors (none before two, nor
across a rebase). A sample off that by more than ``robot_gate_sigmas`` x the robust scale of the
recent anchors' own deviations (per frame interval, once ``robot_sigma_min_frames`` of them
exist) and more than ``robot_gate_fraction`` of the frame's smaller side (allowed once more per
frame placed without a robot sample since the anchor, up to ``robot_gate_max_span`` times; not
by gated frames) is gated: the frame is placed at the extrapolation (``prior-only``, ``c_img =
c_rob = 0``, ``FrameResult.robot_gated``) and the robot anchor stays, so the next sample, back
on its course, is taken from the last good one. A run of ``robot_gate_rebase`` such samples is
accepted: one of about a constant deviation (a lasting offset, e.g. a re-homed robot) by the
rebase above (re-anchored at the extrapolated X_f), one moving steadily away from the
extrapolation (deviations on a line: the robot changed its velocity) by believing the robot at
its last sample. The three glitches above now give 7.2, 7.2 and 7.1 µm, the glitch frame alone
gated; a lasting +300 µm offset from frame 12 on, 332.7 -> 8.8 µm (frames 12-14 gated, the
next ones by the registrations, then re-anchored), with frames 12-17 blank 332.7 -> 17.7. Genuine
motion stays far inside the bound: on the simulator's circle and spiral (seeds 0-2, 512x448 and
256x224, robot.csv and robot_noisy.csv, with contact loss and stick-slip, where the image is
stuck while the robot moves), a robot at a third of the frame rate and 600 µm/frame scans whose
frames do not overlap, the robot's deviations reach 0.19 of the bound (0.52 on the 600
µm/frame circles, turning 0.2 rad/frame), none is gated and #1-#5 are unchanged to 0.01 µm. A
robot starting from rest deviates by its first step: below the floor whenever consecutive
frames overlap (sim0 held still 5 frames, the first moving frame blank: not gated). Starting at
600 µm/frame (512x448 px, frames not overlapping) it is gated for 2 frames, placed at rest,
then believed (3.7 -> 56.4 µm; rebased, it was 1459). The noisy robot on such a scan (velocity
noise 180 µm/frame, before the robot's own scale is measured): one of three scans gated twice
at frames 4-5, 1227 -> 1257 µm (the robot alone 1227), the two others unchanged.

Image gating (not in the paper), the converse: a registration the filter does not trust
(``c_img < robot_sigma_c_img``; in the warm-up, the trust of "Robot noise" above) that differs
from the robot displacement by more than ``image_gate_sigmas`` of the robot's standard
deviations (``sigma_r0 / sqrt(c_rob)``, Eq. 9, per axis) is left out: the robot places the frame
(``c_img = 0``, ``prior-only``, ``FrameResult.image_gated``). Eqs. 7-8 are a weighted mean, so
a confident robot of small ``sigma_r0`` already outweighs such a registration; a robot whose
``sigma_r0`` is of the order of ``sigma_i0`` (a robot sampled more slowly than the frames,
interpolated: its interpolation error) did not, and each registration locked on the fibre
pattern (contact loss) or on stuck tissue (stick-slip) pulled its frame several pixels off for
good. The bound needs a measured ``sigma_r0`` (or a fixed one, ``adaptive_robot_sigma=False``):
before that, with ``robot_unknown_at_start``, an untrusted registration is left out whatever its
disagreement (see "Robot noise"), and otherwise none is. (It was measured against the
placeholder ``KalmanOptions.sigma_robot0`` = 1 px, 3.2 px in the warm-up: with image noise
sigma 12-20 grey levels every correct registration of SSIM < 0.65 was gated, none fed the
filter, so no ``sigma_r0`` sample came and the warm-up never ended, and kalman-robot kept the
noisy robot's error, 91-165 µm against ncc's 0.3; review 47.) A registration left out in the
warm-up still enters the filter's histories (``RobotKalmanFilter.record``): the warm-up ends
after ``KalmanOptions.min_history`` image steps that are not still (a lock at 0 px is), and
c_img judges from then on. A run warns when the robot placed most frames that had a
registration (``MAX_UNUSED_FRACTION``); report.json keeps the ``c_match`` of a registration
left out.

Origin. Frame 0 is the reference (0, 0). When frame 0 is blank, X_m starts at the first
textured frame, put at frame 0's position, and X_f, when frame 0 is blank and has no robot
sample, at the first frame that is textured or has one (``RobotPriorMosaicker.origin_frames``;
the batch methods warn): every position then carries the unknown motion between the two frames,
the mosaic is consistent. When the robot has no sample at frame 0, X_r leaves it unplaced like
every frame before the first sample, which becomes the reference (0, 0) (frame 0, textured, was
drawn at that frame's position over it).

Input checks (streaming): timestamps are real numbers in seconds, below ``MAX_TIMESTAMP_S`` and
at most ``MAX_FRAME_GAP_S`` after the previous frame (a larger value is a unit mix-up: ms, µs or
ns given as s); robot positions are real numbers within the dataset reader's 1 km bound
(``fusedmosaic.io.tracking.MAX_ROBOT_UM``). A refused call raises (``TypeError`` for a wrong
type, ``ValueError`` otherwise, naming the frame and the argument) and changes nothing; so does
a call interrupted later (an exception or ``KeyboardInterrupt`` inside the registration, the
filter or the anchor updates): the state saved at its start is put back before it re-raises.
:meth:`RobotPriorMosaicker.add_frame` is not re-entrant: a call made while another thread is
inside it raises ``RuntimeError`` (serialise the calls); calls from different threads one after
the other are fine.
"""

from __future__ import annotations

import copy
import numbers
import re
import threading
import time
from collections import deque
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from tqdm import tqdm

from fusedmosaic.estimation.consistency import add_robot_agreement
from fusedmosaic.estimation.guard import exclusive_call
from fusedmosaic.estimation.kalman import KalmanOptions, RobotKalmanFilter, normalize
from fusedmosaic.io.tracking import (  # noqa: F401  (MAX_FRAME_GAP_S, MAX_TIMESTAMP_S: API)
    MAX_FRAME_GAP_S,
    MAX_ROBOT_UM,
    MAX_TIMESTAMP_S,
    check_stream_timestamp,
    sample_spacing,
)
from fusedmosaic.methods import MethodResult, listed_ids, ms_stats
from fusedmosaic.registration.ncc import (
    aligned_overlap_ssim,
    fixed_pattern_gain,
    flat_field,
    gray_from_color,
    register_ncc,
    template_problem,
)

__all__ = [
    "ESTIMATES",
    "RobotPriorOptions",
    "FrameResult",
    "RobotPriorMosaicker",
    "translation_homography",
    "run_ncc",
    "run_robot",
    "run_kalman_robot",
]

# Streaming estimate -> (CLI method name, the paper's symbol).
ESTIMATES = {"image": ("ncc", "X_m"), "robot": ("robot", "X_r"), "fused": ("kalman-robot", "X_f")}
CONFIDENCES = ("c_img", "c_rob", "c_angle", "c_speed", "c_match", "c_sp")
STAGES = ("ncc", "ssim", "filter")


MAX_PRESMOOTH_SIGMA_PX = 512.0  # RobotPriorOptions.presmooth_sigma's sanity bound


@dataclass(frozen=True)
class RobotPriorOptions:
    """Options of :class:`RobotPriorMosaicker` (paper 004 values where the paper gives one)."""

    # Central template side as a fraction of the frame: 3/5, paper 004 Sec. III-D.
    template_fraction: float = 0.6
    # Coarse-to-fine NCC search (ncc.py), ~2.5x faster than the exhaustive one (0). Usually the
    # same peak; not always: on 76 of 490 consecutive pairs (simulator circle and spiral, seeds
    # 0-1, 256x224) the two differ by > 1 px, mostly in contact losses, where the exhaustive
    # search locks on the fibre pattern at 0 px more often (closer to the truth: levels 2 on
    # 53, levels 0 on 22; review 47).
    pyramid_levels: int = 2
    # Gaussian pre-blur (px) before NCC; 0 = raw frames, as the paper registers them.
    presmooth_sigma: float = 0.0
    # Largest displacement searched (px/axis); None = the template's full range (+-1/5 frame).
    max_displacement_px: float | None = None
    # c_match = SSIM of the aligned overlap at full resolution (Sec. II-C, ref. [17]); 2 = ~4x
    # cheaper SSIM on a 2x area-downsampled overlap.
    ssim_downsample: int = 1
    # Filter and confidence parameters (Eqs. 4-18), see kalman.KalmanOptions.
    kalman: KalmanOptions = field(default_factory=KalmanOptions)
    # Estimate sigma_r0 online from the robot-minus-image displacements (module docstring).
    adaptive_robot_sigma: bool = True
    # Frames in the estimate: 5 s at the pCLE's ~10 Hz (Sec. III-B), >= 100 pooled values, short
    # enough to follow a change of scanning speed.
    robot_sigma_window: int = 50
    # Trusted frames needed before the estimate replaces kalman.sigma_robot0: 3 frames (6
    # values), i.e. before the filter's own confidences start (kalman.min_history = 6) so that
    # the warm-up, where c_rob(0) = 10 favours the robot (Sec. II-B), uses a measured sigma_r0.
    robot_sigma_min_frames: int = 3
    # px; lower bound of the estimate: below ~0.1 px the sub-pixel NCC cannot tell the robot's
    # error from its own.
    robot_sigma_floor_px: float = 0.1
    # Frames with c_img at or above this feed the estimate: the 0.5 level of Eq. 15.
    robot_sigma_c_img: float = 0.5
    # A robot displacement spanning up to this many frames feeds the estimate: a robot sampled
    # more slowly than the frames (robot_xy_um None between its samples) spans 2 or 3 frames at
    # each sample, and its difference to the image chain over them is that of the displacement
    # the filter fuses at that step (a white robot error is span-independent). Spanning only one
    # frame, a robot at half the frame rate was never measured: sigma_r0 stayed inf, the robot
    # had no weight (seed 1, 60 frames: X_f 38.6 px mean vs 10.4 with a sample every frame).
    # Longer spans (a re-acquisition after a dropout) hold the image chain's drift.
    robot_sigma_max_span: int = 4
    # Forward/backward consistency and wide-range retry of register_ncc (ncc.py): the two
    # directions must agree within this (px; below the probe's 3.5 µm optical resolution,
    # Sec. III-B), else the 2/5 template retries over +-3/10 of the frame. None = no check.
    max_disagreement_px: float | None = 3.0
    fallback_template_fraction: float | None = 0.4
    # Fused estimate: a registration whose directions still disagree is a failed one (c_img = 0,
    # the robot places the frame), as a featureless frame. X_m (image only) keeps the average.
    distrust_inconsistent: bool = True
    # Until sigma_r0 has been measured (robot_sigma_min_frames trusted frames), the robot is
    # uninformative (sigma_r0 = inf): the paper "chose to rely more on the image data than on
    # the robot data at the start" (Sec. II-B). False: KalmanOptions.sigma_robot0 is used.
    robot_unknown_at_start: bool = True
    # c_match (Sec. II-C) is the raw SSIM: "as this score is by definition between 0 and 1, it
    # is not necessary to normalize" it. (k, x_r): c_match = normalize(1 - SSIM, k, x_r)
    # (Eq. 15) instead, a confidence that is 0.5 at SSIM = 1 - x_r. Measured in
    # bench/bench_pcle_cases.py ("ssim-normalized"): it flags low-contrast frames that still
    # register correctly, which then follow the (noisier) robot.
    c_match_normalize: tuple[float, float] | None = None
    # Not in the paper: divide every frame by the fibre bundle's fixed pattern, the mean of the
    # recording's frames (registration/ncc.py fixed_pattern_gain), before NCC and SSIM. For raw
    # fibre-bundle frames whose honeycomb NCC can lock on at low contrast. Batch methods only
    # (the mean needs the whole recording); RobotPriorMosaicker takes a pattern directly.
    # Measured in bench/bench_pcle_cases.py ("flat-field").
    flat_field: bool = False
    # Robot gating (module docstring), not in the paper: a robot displacement disagreeing with a
    # trusted registration (c_img >= robot_sigma_c_img) by more than both bounds is a glitch.
    # Measured on the simulator's circle and spiral, seeds 0-4, both robot files
    # (bench_pcle_cases.py): disagreements on trusted frames reach 115 px (stick-slip
    # catch-up, 0.26 of the 448 px side) and 13 x sigma_r0 (noisy robot); half the frame's
    # smaller side (the registration overlap of two frames is more than that) and 20 sigma_r0
    # leave all of them alone. None: no gating. Both are per frame: a robot sample returning
    # after k frames without one (a dropout) spans k + 1 frames and is allowed k + 1 times them,
    # up to robot_gate_max_span times. The same two (robot_gate_sigmas x the robot's own
    # deviation scale, not sigma_r0) bound a robot step that no registration confirms
    # (module docstring, "Unconfirmed robot steps").
    robot_gate_fraction: float | None = 0.5
    robot_gate_sigmas: float = 20.0
    # Gated frames in a row after which the robot is re-anchored (a lasting offset, e.g. the
    # robot re-homed, rather than a single bad sample).
    robot_gate_rebase: int = 3
    # After a robot dropout the bound is allowed once per frame the returning robot's displacement
    # spans (the image chain's drift it corrects), up to this many times: a drift of up to
    # 4 x the bound (2 frames' smaller side at the default fraction) is corrected, a larger jump
    # is gated as a glitch however long the dropout. Uncapped, a +5 mm glitch at the robot's
    # return passed after 22 missing frames at 512x448 px of 1 µm, the robot anchor moved to it
    # and the rebase locked the offset in (4529 px off to the end of a 110-frame scan).
    robot_gate_max_span: int = 4
    # Image gating (module docstring), not in the paper: a registration the filter does not
    # trust (c_img < robot_sigma_c_img) whose displacement differs from the robot's by more
    # than image_gate_sigmas x the robot's standard deviation sigma_r0 / sqrt(c_rob) (Eq. 9) on
    # an axis is left out (the robot places the frame). None: no gating. Measured on untrusted
    # frames (simulator circle and spiral, seeds 0-1 at 512x448, robot.csv and robot_noisy.csv;
    # 256x224 scans with the robot at a third of the frame rate): registrations off by 29-40
    # px (fibre-pattern locks in the contact loss) next to a robot within 2 px differ by >= 16.6
    # robot sigmas; correct registrations of a stick-slip release (wide-range retry, c_img
    # 0.40-0.43) next to the noisy robot (sigma_r0 ~13 px, 70-105 px off) by <= 7.6 and must
    # keep placing their frames (5 gated them: #5 spiral 33.6 -> 67.9 µm). Seed 0 third-rate
    # scan, 120 frames: X_f 41.5 -> 14.7 px (robot alone 11.5); without stick-slip 15.5 -> 2.6
    # (1.45).
    image_gate_sigmas: float | None = 10.0
    # In the warm-up, before any registration agreed with the robot, a registration disagreeing
    # with the robot beyond the gate is believed (the robot gated) when its c_match (SSIM of
    # the aligned overlap) is at least this: the two frames then visibly overlap, it is no
    # lock on the fibre pattern (module docstring, "Robot gating"). Measured: the consistent
    # registrations of fast scans whose frames do not overlap (600 µm/frame at 512x448 px,
    # seeds 3, 5, 8) have c_match <= 0.50 (fibre-pattern locks at 0 px: 0.48-0.50); frames
    # 1-3 of the simulator's scans 0.77-0.87 (circle seed 0, spiral seed 1, 256x224 seed 0).
    # Before, a +5 mm robot glitch at frame 1 placed frame 1 at the glitch (256x224, 120
    # frames: e_M 39.4 px, 10.5 without the glitch). > 1 and warmup_ssim_margin None: never
    # (the robot places the frame).
    # The same level judges every warm-up registration (RobotPriorMosaicker._trusted), with
    # warmup_ssim_margin: below both, it gives no sigma_r0 sample and can be image-gated; with
    # sigma_r0 still unknown it is left out (the robot places the frame). 0: every warm-up
    # registration trusted.
    warmup_overlap_c_match: float = 0.65
    # ... or when its SSIM (raw, at the NCC shift) exceeds the same pair's SSIM at 0 px by at
    # least this: the shift aligns the frames better than leaving them in place, where a
    # fibre-pattern lock lands. The absolute level alone is a noise level: with image noise
    # sigma 12-20 grey levels correct overlaps score 0.46-0.60, all were distrusted and
    # kalman-robot followed the noisy robot (256x224 px, 80 frames: 90.7-164.5 µm, ncc 0.3;
    # review 47). Measured on consecutive pairs of 23 simulated scans: the 253 registrations
    # more than 3 px off (contact losses, stick-slip, 600 µm/frame scans whose frames do not
    # overlap) gain at most 0 (a lock at 0 px exactly 0, the others lose); correct ones at
    # image noise sigma 12-28 gain >= 0.23 (0.43 at sigma 12). Now 6.8-7.1 µm at sigma 12-20
    # (6.6 at the default sigma 4), 2.1 at 512x448 and sigma 28 (before 293); the default circle
    # and spiral as before (0.1 or 0.3: the same to 0.2 µm). None: the absolute level alone.
    warmup_ssim_margin: float | None = 0.2

    def __post_init__(self) -> None:
        if not isinstance(self.kalman, KalmanOptions):
            raise ValueError(
                "RobotPriorOptions.kalman must be a KalmanOptions, got "
                f"{type(self.kalman).__name__}"
            )
        if not 0.0 < self.template_fraction < 1.0:
            raise ValueError(
                f"RobotPriorOptions.template_fraction must be in (0, 1), got "
                f"{self.template_fraction}"
            )
        for name in ("pyramid_levels", "ssim_downsample"):  # integers (a float failed at frame 1)
            value = getattr(self, name)
            if not isinstance(value, numbers.Integral) or isinstance(value, bool):
                raise ValueError(f"RobotPriorOptions.{name} must be an integer, got {value!r}")
        if self.pyramid_levels < 0:
            raise ValueError(
                f"RobotPriorOptions.pyramid_levels must be >= 0, got {self.pyramid_levels}"
            )
        # A Gaussian over more than ~a frame blurs it flat, and its cost grows with sigma
        # (1e4 px: 3 s a frame; 1e6: minutes, uninterruptible in cv2.GaussianBlur).
        if not 0.0 <= self.presmooth_sigma <= MAX_PRESMOOTH_SIGMA_PX:
            raise ValueError(
                f"RobotPriorOptions.presmooth_sigma must be in [0, {MAX_PRESMOOTH_SIGMA_PX:g}] "
                f"px, got {self.presmooth_sigma}"
            )
        if self.max_displacement_px is not None and not 0.0 < self.max_displacement_px < np.inf:
            raise ValueError(
                "RobotPriorOptions.max_displacement_px must be finite and > 0, or None, got "
                f"{self.max_displacement_px}"
            )
        if self.ssim_downsample < 1:
            raise ValueError(
                f"RobotPriorOptions.ssim_downsample must be >= 1, got {self.ssim_downsample}"
            )
        if self.fallback_template_fraction is not None and not (
                0.0 < self.fallback_template_fraction < 1.0):
            raise ValueError("RobotPriorOptions.fallback_template_fraction must be in (0, 1) or "
                             f"None, got {self.fallback_template_fraction}")
        if self.max_disagreement_px is not None and not 0.0 <= self.max_disagreement_px < np.inf:
            raise ValueError("RobotPriorOptions.max_disagreement_px must be finite and >= 0, or "
                             f"None, got {self.max_disagreement_px}")
        if self.robot_sigma_window < 1 or self.robot_sigma_min_frames < 1:
            raise ValueError(
                "RobotPriorOptions.robot_sigma_window and robot_sigma_min_frames must be >= 1, "
                f"got {self.robot_sigma_window} and {self.robot_sigma_min_frames}"
            )
        if not (isinstance(self.robot_sigma_max_span, int | np.integer)
                and self.robot_sigma_max_span >= 1):
            raise ValueError(
                "RobotPriorOptions.robot_sigma_max_span must be an integer >= 1, got "
                f"{self.robot_sigma_max_span!r}"
            )
        if self.robot_sigma_min_frames > self.robot_sigma_window:
            raise ValueError(
                "RobotPriorOptions.robot_sigma_min_frames must not exceed robot_sigma_window, "
                f"got {self.robot_sigma_min_frames} > {self.robot_sigma_window}"
            )
        if not (np.isfinite(self.robot_sigma_floor_px) and self.robot_sigma_floor_px > 0.0):
            raise ValueError(
                "RobotPriorOptions.robot_sigma_floor_px must be a finite number > 0, got "
                f"{self.robot_sigma_floor_px}"
            )
        if not 0.0 <= self.robot_sigma_c_img <= 1.0:
            raise ValueError(
                "RobotPriorOptions.robot_sigma_c_img must be in [0, 1], got "
                f"{self.robot_sigma_c_img}"
            )
        if self.robot_gate_fraction is not None and not (
            np.isfinite(self.robot_gate_fraction) and self.robot_gate_fraction > 0.0
        ):
            raise ValueError(
                "RobotPriorOptions.robot_gate_fraction must be a finite number > 0 or None, got "
                f"{self.robot_gate_fraction}"
            )
        if not self.robot_gate_sigmas > 0.0:
            raise ValueError(
                f"RobotPriorOptions.robot_gate_sigmas must be > 0, got {self.robot_gate_sigmas}"
            )
        if not (isinstance(self.robot_gate_max_span, int | np.integer)
                and self.robot_gate_max_span >= 1):
            raise ValueError(
                "RobotPriorOptions.robot_gate_max_span must be an integer >= 1, got "
                f"{self.robot_gate_max_span!r}"
            )
        if self.image_gate_sigmas is not None and not (
            np.isfinite(self.image_gate_sigmas) and self.image_gate_sigmas > 0.0
        ):
            raise ValueError(
                "RobotPriorOptions.image_gate_sigmas must be a finite number > 0 or None, got "
                f"{self.image_gate_sigmas}"
            )
        if not self.warmup_overlap_c_match >= 0.0:  # (NaN too)
            raise ValueError(
                "RobotPriorOptions.warmup_overlap_c_match must be a number >= 0, got "
                f"{self.warmup_overlap_c_match}"
            )
        if self.warmup_ssim_margin is not None and not (
                np.isfinite(self.warmup_ssim_margin) and self.warmup_ssim_margin > 0.0):
            # (0 would trust a lock at 0 px, whose two SSIMs are the same number)
            raise ValueError(
                "RobotPriorOptions.warmup_ssim_margin must be a finite number > 0 or None, got "
                f"{self.warmup_ssim_margin}"
            )
        if self.robot_gate_rebase < 1:
            raise ValueError(
                f"RobotPriorOptions.robot_gate_rebase must be >= 1, got {self.robot_gate_rebase}"
            )
        if self.c_match_normalize is not None:
            values = np.asarray(self.c_match_normalize, dtype=np.float64)
            if values.shape != (2,) or not np.isfinite(values).all() or not values[0] > 0.0:
                raise ValueError(
                    "RobotPriorOptions.c_match_normalize must be (k > 0, x_r) or None, got "
                    f"{self.c_match_normalize!r}"
                )


def _real(value) -> bool:
    """A real number (int, float or NumPy's; not a bool or a string)."""
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value,
                                                                                       bool)


def translation_homography(position) -> np.ndarray:
    """(3, 3) frame -> reference translation by ``position`` (px); all-NaN if it is not finite."""
    p = np.asarray(position, dtype=np.float64)
    if not np.isfinite(p).all():
        return np.full((3, 3), np.nan)
    G = np.eye(3)
    G[:2, 2] = p
    return G


def _pixel_family(dtype: np.dtype):
    """What RobotPriorMosaicker requires every frame to share: floats of any width, else the
    integer type itself (either byte order)."""
    return "float" if dtype.kind == "f" else dtype.newbyteorder("=")


@dataclass(frozen=True)
class FrameResult:
    """What :meth:`RobotPriorMosaicker.add_frame` returns for one frame.

    index : frame number in the stream (0 = the reference); also as ``frame_id``, the name
        SequentialMosaicker's FrameResult uses.
    position : (2,) px, the chosen estimate (X_m, X_r or X_f) relative to frame 0; NaN when the
        frame could not be placed.
    homography : (3, 3) frame -> reference translation, all-NaN when unplaced.
    status : ``placed`` (image evidence used), ``prior-only`` (placed from the robot alone) or
        ``unplaced: <reason>``; frame 0, the reference, is ``placed`` (so with
        ``estimate="robot"`` every later frame is ``prior-only``), or ``prior-only`` when it is
        blank (image and fused estimates: placed at the origin, with no image content).
    c_img, c_rob, c_angle, c_speed, c_match, c_sp : the confidences of Eqs. 13-18 for the fused
        estimate (NaN when not computed: frame 0, other estimates, missing inputs); ``c_match``
        is also given for the image estimate. ``c_img`` and ``c_rob`` are the weights of Eqs.
        7-8: until enough frames give c_angle / c_speed / c_sp they hold the paper's initial
        values c_img = 1 and c_rob = 10 (KalmanOptions.c_img0 / c_rob0), which is why c_rob is
        not bounded by 1. ``c_rob`` is 0 whenever the robot sample had no weight: none, gated
        (``robot_gated``), or of unknown noise (``robot_noise_unknown``) on a frame the image
        placed (sigma_r0 inf gives the robot an infinite variance whatever c_rob; the filter's
        c_rob0 = 10 was reported there, read as a 10:1 weight of the robot; review 51). On a
        frame the robot places alone it is 1 (c_img 0), of unknown noise or not.
    ncc_score : mean forward/backward peak NCC (NaN without a registration).
    position_image, position_robot, position_fused : (2,) X_m, X_r, X_f where computed (NaN
        otherwise): the fused estimate also reports X_m and X_r for comparison.
    sigma_robot0 : px, the sigma_r0 of Eq. 9 used at this frame (NaN outside the fused estimate).
    displacement_image, displacement_robot : (2,) px, the dX of Eq. 5 and the V_r T_s of Eq. 4
        handed to the filter (relative to the previous placed position; NaN when missing).
    timings : seconds per stage: ``ncc`` (forward + backward), ``ssim`` (c_match), ``filter``
        (confidences + Eqs. 4-8), ``total`` (the whole call).
    robot_gated : True when the robot sample was left out as a glitch (module docstring): the
        frame follows the image (``c_rob = 0``, ``c_sp`` NaN), or, without a usable
        registration, the extrapolation of the robot's own recent motion (``prior-only``,
        ``c_img = c_rob = 0``; "Unconfirmed robot steps"); ``displacement_robot`` is the
        rejected robot displacement.
    robot_noise_unknown : True when sigma_r0 was not measured yet (``sigma_robot0`` inf:
        the robot's noise unknown, ``robot_unknown_at_start``): the robot had no weight next to
        a registration (``c_rob = 0``), and placed the frame only without one. report.json
        lists these frames (``robot_noise_unknown``) and writes their ``sigma_robot0_px`` as
        null.
    image_gated : True when the registration was left out by the image gate (module docstring,
        "Image gating"): the robot places the frame (``prior-only``, ``c_img = 0``);
        ``displacement_image`` is the rejected registration.
    ncc_consistent : whether the registration's forward and backward directions agreed (after
        the wide-range retry, ``RobotPriorOptions.max_disagreement_px``); None without one, or
        when it failed (a featureless template: no displacement, status ``unplaced`` or
        ``prior-only``).
    registered_against : the index of the frame it was registered against (the last placed
        textured one: ``index - 1`` unless blank or failed frames came between), None without
        a registration.
    """

    index: int
    timestamp: float
    position: np.ndarray
    homography: np.ndarray
    status: str
    c_img: float
    c_rob: float
    c_angle: float
    c_speed: float
    c_match: float
    c_sp: float
    ncc_score: float
    position_image: np.ndarray
    position_robot: np.ndarray
    position_fused: np.ndarray
    sigma_robot0: float
    displacement_image: np.ndarray
    displacement_robot: np.ndarray
    timings: dict[str, float]
    robot_gated: bool = False
    ncc_consistent: bool | None = None
    image_gated: bool = False
    registered_against: int | None = None
    robot_noise_unknown: bool = False

    @property
    def placed(self) -> bool:
        return bool(np.isfinite(self.position).all())

    @property
    def frame_id(self) -> int:
        return self.index


@dataclass
class _Anchor:
    """The last frame registered successfully: its image (float32, as NCC and SSIM read it:
    converted once, when it was the current frame), whether that was uint8 (SSIM's data range
    is then 255) and its positions in the mosaic."""

    index: int
    image: np.ndarray
    uint8: bool
    x_m: np.ndarray
    x_f: np.ndarray


_NAN2 = np.full(2, np.nan)
# Recent frame spacings whose median is the nominal frame interval (_frame_intervals).
_SPACING_WINDOW = 32
_NOT_YET = object()  # (RobotPriorMosaicker._place: a value not computed yet)


def field_boxes(width: int, height: int, radius: float | None
                ) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """Where pCLE frames are registered, as (rows, cols) slices: the bounding box of a circular
    field of view of `radius` px centred on the frame (camera.yaml's fov_mask_radius, as
    Camera.fov_mask), for NCC, and the largest square inside it, for c_match. The paper's
    frames fill their rectangle, so its central 3/5 template holds tissue only; in a circular
    field the template is 3/5 of the field's box and lies inside the circle (its corners at
    0.85 x the radius), and SSIM compares tissue only. Registered on the whole frame, a field
    of radius 160 in 512x448 frames locked on its fixed black border (shift 0 for a true 40 px:
    ncc e_M 53 px, kalman-robot 39). The whole frame for both without a radius."""
    whole = (slice(0, height), slice(0, width))
    if radius is None:
        return whole, whole
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0

    def box(half: float) -> tuple[slice, slice]:
        return (slice(max(0, int(np.ceil(cy - half))), min(height, int(np.floor(cy + half)) + 1)),
                slice(max(0, int(np.ceil(cx - half))), min(width, int(np.floor(cx + half)) + 1)))

    return box(float(radius)), box(float(radius) / np.sqrt(2.0))


class RobotPriorMosaicker:
    """Streaming pCLE topology inference (paper 004, Sec. II): one :meth:`add_frame` per frame.

    Parameters
    ----------
    camera : :class:`fusedmosaic.io.Camera` (or any object with ``width``, ``height`` and
        ``pixel_size_um``): frames must be ``height x width``; ``pixel_size_um`` (µm/px)
        converts robot positions and is required by the ``robot`` and ``fused`` estimates.
    options : :class:`RobotPriorOptions`, default paper settings.
    estimate : ``"fused"`` (X_f, default), ``"image"`` (X_m) or ``"robot"`` (X_r).
    fixed_pattern : optional (H, W) gain image of the fibre bundle's fixed pattern (e.g.
        ``registration.ncc.fixed_pattern_gain`` of a calibration recording), scaled here to mean
        1 over its non-zero pixels; every frame is divided by it before registration, pixels of
        gain 0 (no signal, e.g. outside the field of view) become 0.

    Memory is bounded: only the anchor frame's image is kept. Not re-entrant: concurrent
    :meth:`add_frame` / :meth:`reset` calls raise ``RuntimeError``; serialise them.
    """

    def __init__(
        self,
        camera,
        options: RobotPriorOptions | None = None,
        *,
        estimate: str = "fused",
        fixed_pattern: np.ndarray | None = None,
    ) -> None:
        if estimate not in ESTIMATES:
            raise ValueError(f"estimate must be one of {tuple(ESTIMATES)}, got {estimate!r}")
        self.options = RobotPriorOptions() if options is None else options
        if not isinstance(self.options, RobotPriorOptions):
            raise ValueError(
                f"options must be a RobotPriorOptions, got {type(self.options).__name__}"
            )
        self.estimate = estimate
        pixel_size = getattr(camera, "pixel_size_um", None)
        source = getattr(camera, "source", "camera")
        for name in ("width", "height"):  # (256.7 was cut to 256; review)
            value = getattr(camera, name, None)
            if not (_real(value) and float(value).is_integer() and value > 0):
                raise ValueError(f"{source}: {name} must be a positive whole number of pixels, "
                                 f"got {value!r}")
        self.width, self.height = int(camera.width), int(camera.height)
        if pixel_size is not None and not _real(pixel_size):  # ("1.0": a TypeError from numpy)
            raise ValueError(f"{source}: pixel_size_um must be a positive number, got "
                             f"{pixel_size!r}")
        if estimate != "image" and pixel_size is None:
            raise ValueError(
                f"{source}: no pixel_size_um; the {estimate!r} estimate "
                f"(method {ESTIMATES[estimate][0]!r}) needs it to convert robot µm to pixels"
            )
        if pixel_size is not None and not (np.isfinite(pixel_size) and pixel_size > 0):
            raise ValueError(f"{source}: pixel_size_um must be a positive number, got {pixel_size}")
        self.pixel_size_um = None if pixel_size is None else float(pixel_size)
        radius = getattr(camera, "fov_mask_radius", None)
        self._field = field_boxes(self.width, self.height, radius)
        if estimate != "robot":  # before frame 1 (or a wide-range retry mid-run) finds out
            rows, cols = self._field[0]
            for name in ("template_fraction", "fallback_template_fraction"):
                fraction = getattr(self.options, name)
                problem = None if fraction is None else template_problem(
                    (rows.stop - rows.start, cols.stop - cols.start), fraction,
                    f"RobotPriorOptions.{name}")
                if problem is not None:
                    field = ("" if radius is None else
                             f" (their field of view: fov_mask_radius {radius:g} px)")
                    raise ValueError(f"{source}: frames of {self.width}x{self.height} px{field} "
                                     f"are too small to register by NCC: {problem}")
        self.fixed_pattern = None
        if fixed_pattern is not None:
            gain = np.asarray(fixed_pattern, dtype=np.float32)
            if gain.shape != (self.height, self.width):
                raise ValueError(
                    f"fixed_pattern: expected a ({self.height}, {self.width}) gain image (the "
                    f"camera's size), got shape {gain.shape}"
                )
            if not (np.isfinite(gain).all() and (gain >= 0).all() and gain.max() > 0):
                raise ValueError("fixed_pattern: gains must be finite, >= 0 and not all 0")
            self.fixed_pattern = gain / float(gain[gain > 0].mean())  # mean 1 where it has signal
        # Largest robot-image disagreement (px) that is never gated, whatever sigma_r0.
        fraction = self.options.robot_gate_fraction
        self._gate_floor_px = (
            np.inf if fraction is None else fraction * min(self.width, self.height)
        )
        self._busy = threading.Lock()
        self._reset()

    def reset(self) -> None:
        """Start a new sequence: the next frame becomes the reference (frame 0)."""
        with exclusive_call(self._busy, "RobotPriorMosaicker", "reset"):
            self._reset()

    def _reset(self) -> None:
        self._count = 0
        self._last_timestamp = -np.inf
        self._pixel_type: np.dtype | None = None  # the first image's, which every image keeps
        self._intensity: tuple[float, float] | None = None  # _common_scale's (offset, factor)
        self._anchor: _Anchor | None = None
        self._robot_origin_um = _NAN2  # robot position at frame 0
        # The frames whose X_m / X_r are the origin (0, 0): frame 0, or when frame 0 is blank
        # (no robot sample) the first textured frame (the first robot sample), see origin_frames.
        self._image_origin: int | None = None
        self._robot_origin: int | None = None
        # X_f's: frame 0, or when frame 0 is blank and has no robot sample the first frame that
        # is textured or has one.
        self._fused_origin: int | None = None
        # (robot µm, X_f, timestamp s) of the last robot sample taken as an anchor
        self._robot_anchor: tuple[np.ndarray, np.ndarray, float] | None = None
        # µm/s, the robot's own velocity between its last two anchors (not across a rebase):
        # what an unconfirmed robot step is judged against (_robot_jump)
        self._robot_velocity: np.ndarray | None = None
        # |deviation| (px per frame interval, both axes) of the recent anchors from that
        # extrapolation: the robot's own jerkiness, _robot_jump's scale
        self._robot_jumps: deque[np.ndarray] = deque(maxlen=self.options.robot_sigma_window)
        # the signed deviations (px) of the samples gated so in a row since the anchor
        self._jump_run: list[np.ndarray] = []
        # Frames placed from the image alone, for want of a robot sample, since the robot anchor:
        # the robot displacement spans that many more image steps than the image displacement.
        self._steps_without_robot = 0
        self._gated_in_a_row = 0
        # Registrations left "unjudged" in a row (_robot_glitch); once robot_gate_rebase, the
        # warm-up exception is over for the sequence (kept at that count).
        self._unjudged_in_a_row = 0
        self._innovations: deque[np.ndarray] = deque(maxlen=self.options.robot_sigma_window)
        self._spacings: deque[float] = deque(maxlen=_SPACING_WINDOW)  # recent frame spacings, s
        # The timestamp of the last frame the fused estimate placed: X_f(i-1) of the next step.
        self._placed_timestamp = -np.inf
        self._kf = RobotKalmanFilter(self.options.kalman) if self.estimate == "fused" else None

    @property
    def frame_count(self) -> int:
        """Frames added since the last :meth:`reset`."""
        return self._count

    @property
    def origin_frames(self) -> dict:
        """{"image": k, "robot": k, "fused": k}: the frame whose X_m (X_r, X_f) is the origin
        (0, 0), None before there is one. Frame 0 normally; when frame 0 is blank nothing places
        its image, so the first textured frame is put at frame 0's position: X_m is then
        relative to that frame, a consistent mosaic offset by the unknown motion between the two
        (reported by the batch methods as a warning). X_r: the first frame with a robot sample;
        the frames before it, frame 0 included, are unplaced (it is the reference of the
        homographies). X_f needs either: it starts after frame 0 only when frame 0 is
        blank and has no robot sample, at the first frame that is textured or has one (only with
        ``estimate="fused"``)."""
        return {"image": self._image_origin, "robot": self._robot_origin,
                "fused": self._fused_origin}

    @property
    def sigma_robot0(self) -> float:
        """The sigma_r0 (px) the next fused step will use (Eq. 9)."""
        o = self.options
        if (
            o.robot_unknown_at_start
            and o.adaptive_robot_sigma
            and len(self._innovations) < o.robot_sigma_min_frames
        ):
            return float("inf")
        if not o.adaptive_robot_sigma or len(self._innovations) < o.robot_sigma_min_frames:
            return o.kalman.sigma_robot0
        d = np.abs(np.concatenate(self._innovations))
        return max(1.4826 * float(np.median(d)), o.robot_sigma_floor_px)

    # -- input checks --------------------------------------------------------------------------

    def _prepare_image(self, image, index: int) -> np.ndarray:
        # the pixel type checked before a colour image is converted (before: BGR bool / complex
        # / object arrays were cast to grey silently, or failed inside the conversion)
        if not isinstance(image, np.ndarray):
            raise TypeError(f"frame {index}: image must be a numpy array, got "
                            f"{type(image).__name__}")
        if image.dtype.kind not in "uif":
            raise ValueError(f"frame {index}: unsupported pixel type {image.dtype}")
        if (self._pixel_type is not None and self.estimate != "robot"
                and _pixel_family(image.dtype) != _pixel_family(self._pixel_type)):
            # c_match's SSIM range follows the type (uint8: 0-255, others: the overlap's own
            # range): a float 0-1 frame after uint8 ones scored c_match ~0.001. Floats of any
            # width, and either byte order, are alike
            raise ValueError(
                f"frame {index}: pixel type {image.dtype} differs from the first frame's "
                f"{self._pixel_type}; all frames of a sequence must have one pixel type")
        image = gray_from_color(image)
        if image.ndim != 2:
            raise ValueError(
                f"frame {index}: expected a (H, W) gray or (H, W, 3) BGR image, got an array of "
                f"shape {image.shape}"
            )
        if image.shape != (self.height, self.width):
            raise ValueError(
                f"frame {index}: image is {image.shape[1]}x{image.shape[0]} but the camera (and "
                f"frame 0) is {self.width}x{self.height}; all frames must have one size"
            )
        if image.dtype != np.uint8:  # (integer or float: checked above)
            image = np.ascontiguousarray(image, dtype=np.float32)
            if not np.isfinite(image).all():
                raise ValueError(f"frame {index}: image contains NaN or infinite pixels")
        return image

    def _common_scale(self, gray: np.ndarray) -> np.ndarray:
        """A frame not of uint8 (float, or integers wider than 8 bits) on one intensity scale
        for the sequence, set by its first textured such frame: (v - that frame's minimum) *
        255 / its range. NCC and the SSIM of c_match (on the overlap's own range) do not depend
        on an affine map of the intensities that all frames share, but their float32
        arithmetic does: frames on a pedestal of 1e5 placed twice as far off, frames scaled by
        1e12 failed with c_match NaN, by 1e-12 every one fell back to the robot (review)."""
        if self._intensity is None:
            low, high = float(gray.min()), float(gray.max())
            self._intensity = (low, 255.0 / (high - low))  # (textured: high > low)
        low, factor = self._intensity
        out = (gray.astype(np.float64) - low) * factor
        with np.errstate(over="ignore"):  # beyond float32: refused by _place, naming the frame
            return out.astype(np.float32)

    def _prepare_timestamp(self, timestamp, index: int) -> float:
        return check_stream_timestamp(index, timestamp, self._last_timestamp)

    def _prepare_robot(self, robot_xy_um, index: int) -> np.ndarray:
        if robot_xy_um is None:
            return _NAN2
        r = np.asarray(robot_xy_um)
        if r.dtype.kind == "O":  # e.g. a list holding None or complex numbers
            try:
                r = r.astype(np.float64)
            except (TypeError, ValueError):
                pass  # still object: refused below
        if r.dtype.kind not in "iuf":
            kind = {"c": "complex", "b": "bool", "U": "str", "S": "bytes"}.get(r.dtype.kind)
            raise TypeError(
                f"frame {index}: robot_xy_um must be two real numbers (µm), got "
                f"{kind or 'non-numeric'} values {robot_xy_um!r:.60}"
            )
        r = r.astype(np.float64)
        if r.shape != (2,):
            raise ValueError(f"frame {index}: robot_xy_um must have shape (2,), got {r.shape}")
        if np.isinf(r).any():
            raise ValueError(f"frame {index}: robot_xy_um is infinite: {r}")
        if (np.abs(r) > MAX_ROBOT_UM).any():  # NaN compares False: a missing sample passes
            raise ValueError(
                f"frame {index}: robot_xy_um {r} is beyond the {MAX_ROBOT_UM:g} µm bound (1 km), "
                "not a physical position (a unit mix-up? µm expected)"
            )
        if np.isnan(r).all():
            return _NAN2  # no sample for this frame
        if np.isnan(r).any():  # one axis measured, the other not: a caller's bug, not a dropout
            raise ValueError(f"frame {index}: robot_xy_um has one NaN coordinate ({r}); give "
                             "both, or None / both NaN when the robot has no sample")
        return r

    # -- the streaming step --------------------------------------------------------------------

    def add_frame(self, image, timestamp: float, robot_xy_um=None) -> FrameResult:
        """Place the next frame.

        Parameters
        ----------
        image : (H, W) uint8/float gray or (H, W, 3) BGR, the camera's size and the first
            image's pixel type; may be None for the ``robot`` estimate (which does not look at
            images). Float or wider integer pixels may have any offset and scale: they are
            mapped onto one scale, the first textured frame's range to 0-255.
        timestamp : s, strictly increasing.
        robot_xy_um : (2,) robot position at the frame time (µm, image axes), or None / both
            NaN when the robot has no sample for this frame.

        Raises
        ------
        ValueError
            Naming the frame: a size differing from the camera's, a pixel type differing from
            the first image's, bad pixel values or shapes, a timestamp not after the previous
            one or beyond the bounds (``MAX_TIMESTAMP_S``, ``MAX_FRAME_GAP_S``), a robot
            position beyond ``MAX_ROBOT_UM`` or with one NaN coordinate.
        TypeError
            Naming the frame and the argument: a timestamp or robot position that is not real
            numbers (a string, None, complex).
        RuntimeError
            When another thread is inside ``add_frame`` on this mosaicker (not re-entrant).

        A call that raises changes nothing: the next call is frame ``frame_count`` again. The
        input is checked before anything changes, and any exception after that (including
        ``KeyboardInterrupt``) puts back the state saved at the start of the call.
        """
        t_start = time.perf_counter()
        with exclusive_call(self._busy, "RobotPriorMosaicker", "add_frame"):
            return self._add_frame(image, timestamp, robot_xy_um, t_start)

    def _add_frame(self, image, timestamp, robot_xy_um, t_start: float) -> FrameResult:
        i = self._count
        t = self._prepare_timestamp(timestamp, i)
        robot = self._prepare_robot(robot_xy_um, i)
        gray = None
        if image is not None:
            gray = self._prepare_image(image, i)
        elif self.estimate != "robot":
            raise ValueError(f"frame {i}: an image is needed for the {self.estimate!r} estimate")
        # The input is valid; from here on the state changes. Whatever interrupts it (an
        # exception in a registration, Ctrl-C between the filter update and the anchors), the
        # state is put back as it was, so the caller can give the frame again or go on.
        saved = self._state()
        try:
            result = self._place(i, t, robot, gray, t_start)
        except BaseException:
            self._restore(saved)
            raise
        if image is not None and self._pixel_type is None:
            self._pixel_type = np.asarray(image).dtype
        return result

    # Everything _place changes, for _restore. Copied shallowly (the values are replaced, the
    # innovations deque is appended to); the filter, changed in place, by its snapshot (a
    # deepcopy took ~0.5 ms, 5 % of a 512x448 frame).
    _STATE = ("_count", "_last_timestamp", "_anchor", "_robot_origin_um", "_image_origin",
              "_robot_origin", "_fused_origin", "_robot_anchor", "_robot_velocity",
              "_robot_jumps", "_jump_run",
              "_steps_without_robot", "_gated_in_a_row", "_unjudged_in_a_row", "_innovations",
              "_intensity", "_spacings", "_placed_timestamp")

    def _state(self) -> dict:
        state = {name: copy.copy(getattr(self, name)) for name in self._STATE}
        state["_kf"] = None if self._kf is None else (self._kf, self._kf.snapshot())
        return state

    def _restore(self, state: dict) -> None:
        for name, value in state.items():
            if name == "_kf" and value is not None:
                self._kf = value[0]
                self._kf.restore(value[1])
            else:
                setattr(self, name, value)

    def _place(self, i: int, t: float, robot: np.ndarray, gray, t_start: float) -> FrameResult:
        """Frame i, validated: register, fuse, move the anchors (changes the state)."""
        blank = gray is not None and float(np.ptp(gray)) == 0.0  # before any flat-field
        if gray is not None and self.fixed_pattern is not None:
            gray = flat_field(gray, self.fixed_pattern)
        if gray is not None and gray.dtype != np.uint8 and not blank:
            gray = self._common_scale(gray)
        # The frame as NCC and SSIM read it, converted once (a fresh array: it may become the
        # anchor, and a live caller may reuse its capture buffer for the next frame).
        image32 = None if gray is None or blank else gray.astype(np.float32)
        if (image32 is not None and gray.dtype != np.uint8 and self.estimate != "robot"
                and not np.isfinite(image32).all()):  # (register_ncc no longer checks it)
            raise ValueError(f"frame {i}: pixel values overflow float32 on the sequence's "
                             "intensity scale (the first textured frame's range mapped to 0-255)")
        timings = dict.fromkeys(STAGES, 0.0)
        motion = _NOT_YET  # the robot's extrapolation at t (_robot_extrapolation), once a frame
        nan = float("nan")
        conf = dict.fromkeys(CONFIDENCES, nan)
        score, sigma_r = nan, nan
        ssim_gain = nan  # (SSIM at the NCC shift) - (at 0 px), computed in the warm-up only
        dx_img_f, dx_rob_f = _NAN2, _NAN2
        robot_gated = image_gated = False
        jumped = False  # robot_gated as an unconfirmed robot step (_robot_jump)

        # Robot position X_r (Eq. 3), relative to frame 0.
        if self._robot_origin is None and np.isfinite(robot).all():
            self._robot_origin_um, self._robot_origin = robot, i
        x_r = _NAN2
        if self.pixel_size_um is not None:
            x_r = (robot - self._robot_origin_um) / self.pixel_size_um

        # Image registration against the anchor (frame i-1 unless it was blank or failed).
        dx, why_no_image = _NAN2, None
        inconsistent, consistent = False, None
        against = None
        if i > 0 and self.estimate != "robot":
            if blank:
                why_no_image = "blank frame (constant image)"
            elif self._anchor is None:
                why_no_image = "no textured frame placed before it to register against"
            else:
                t0 = time.perf_counter()
                box, square = self._field
                against = self._anchor.index
                reg = register_ncc(
                    self._anchor.image[box],
                    image32[box],
                    template_fraction=self.options.template_fraction,
                    max_displacement=self.options.max_displacement_px,
                    pyramid_levels=self.options.pyramid_levels,
                    presmooth_sigma=self.options.presmooth_sigma,
                    max_disagreement=self.options.max_disagreement_px,
                    fallback_template_fraction=self.options.fallback_template_fraction,
                    prepared=True,
                )
                t1 = time.perf_counter()
                timings["ncc"] = t1 - t0
                dx, score = reg.dx, reg.score
                # a failed registration (featureless template: dx NaN, reported inconsistent)
                # has no directions to disagree: None, not counted by add_inconsistency
                failed = not np.isfinite(dx).all()
                consistent = None if failed else bool(reg.consistent)
                inconsistent = (self.options.distrust_inconsistent and not failed
                                and not reg.consistent)
                if inconsistent:
                    why_no_image = (f"NCC registration against frame {self._anchor.index}: "
                                    "forward and backward directions disagree")
                if np.isfinite(dx).all():
                    pair = (self._anchor.image[square], image32[square])
                    ssim_options = {
                        # 8-bit frames: SSIM's constants for the 0-255 range, as for uint8 input
                        "data_range": (255.0 if self._anchor.uint8 and gray.dtype == np.uint8
                                       else None),
                        "downsample": self.options.ssim_downsample,
                        "prepared": True,
                    }
                    ssim = aligned_overlap_ssim(*pair, dx, **ssim_options)
                    conf["c_match"] = ssim
                    if self.options.c_match_normalize is not None:
                        slope, level = self.options.c_match_normalize
                        conf["c_match"] = normalize(1.0 - conf["c_match"], slope, level)
                    if (self._kf is not None and self._kf.warming_up
                            and self.options.warmup_ssim_margin is not None
                            and not conf["c_match"] >= self.options.warmup_overlap_c_match):
                        # what the shift gains over leaving the frames in place (_trusted):
                        # only in the warm-up, where c_img judges nothing
                        ssim_gain = ssim - aligned_overlap_ssim(*pair, np.zeros(2),
                                                                **ssim_options)
                    timings["ssim"] = time.perf_counter() - t1
                else:
                    why_no_image = (
                        f"NCC registration against frame {self._anchor.index} failed "
                        "(featureless template)"
                    )
        if i == 0:
            x_m = x_f = np.zeros(2)
        else:
            x_m = self._anchor.x_m + dx if self._anchor is not None else _NAN2
            x_f = _NAN2
            if self._image_origin is None and gray is not None and not blank:
                x_m = np.zeros(2)  # the first textured frame after a blank frame 0
        if self._image_origin is None and gray is not None and not blank:
            self._image_origin = i

        # The chosen estimate.
        textured = gray is not None and not blank
        usable = textured or bool(np.isfinite(robot).all())  # something X_f can start from
        if i == 0 and self.estimate == "robot" and not np.isfinite(x_r).all():
            # X_r has no position for it: put at the origin it was drawn over the first frame
            # with a robot sample, put there too (a ghost of tissue 840 µm away; review). Left
            # unplaced as the frames up to that one: it is the reference (runner warns).
            position, status = _NAN2, "unplaced: no robot sample at this frame"
        elif i == 0:
            # The reference defines the origin. Blank, it is placed without having been seen:
            # prior-only, as every later blank frame, so that run reads it and leaves a black
            # one out of the mosaic ("placed" told run it had content: a black frame 0 was
            # pasted, 8 % darker tissue under it; every frame black, a black mosaic.png; review
            # 47). (X_r's frame 0 is "placed": run knows that method sees no image.)
            status = "prior-only" if self.estimate != "robot" and not textured else "placed"
            position = np.zeros(2)
            if self.estimate == "fused" and usable:
                self._fused_origin = 0
        elif self.estimate == "image":
            position = x_m
            status = "placed" if np.isfinite(x_m).all() else f"unplaced: {why_no_image}"
        elif self.estimate == "robot":
            position = x_r
            if np.isfinite(x_r).all():
                status = "prior-only"
            else:
                status = "unplaced: no robot sample at this frame"
        else:
            t0 = time.perf_counter()
            kf = self._kf
            intervals = self._frame_intervals(t)
            previous = kf.position
            if self._robot_anchor is not None and np.isfinite(robot).all():
                r_um, r_xf, _ = self._robot_anchor
                dx_rob_f = r_xf + (robot - r_um) / self.pixel_size_um - previous  # Eq. 4
            if self._anchor is not None and not (inconsistent and np.isfinite(dx_rob_f).all()):
                # an inconsistent registration only when no robot sample can place the frame
                dx_img_f = self._anchor.x_f + dx - previous  # likelihood mean - X_f(i-1), Eq. 5
            image_ok = bool(np.isfinite(dx_img_f).all())
            robot_ok = bool(np.isfinite(dx_rob_f).all())
            if not image_ok and not robot_ok and self._fused_origin is None and usable:
                # Frame 0 blank and without a robot sample: nothing relates it to later frames,
                # and neither anchor could ever be set (they need a placed textured frame, a
                # placed frame with a robot sample). As X_m and X_r do, the first frame that is
                # textured or has a robot sample is put at frame 0's position and the chain goes
                # on from it (both anchors are set below); the batch method warns.
                x_f = position = previous
                status = "placed" if textured else "prior-only"
                self._fused_origin = i
            elif not image_ok and not robot_ok:
                position = _NAN2
                if not np.isfinite(robot).all():
                    no_robot = "no robot sample"
                else:  # a sample, but no earlier placed one to take the displacement from
                    no_robot = "no robot sample at a placed frame before it"
                status = f"unplaced: no image registration ({why_no_image}) and {no_robot}"
            else:
                sigma_r = self.sigma_robot0
                if sigma_r != kf.options.sigma_robot0:
                    kf.options = replace(kf.options, sigma_robot0=sigma_r)
                # where the robot's own recent motion puts the frame, when this sample jumps
                # off it (None otherwise): used if the robot would place the frame alone
                if robot_ok:
                    motion = self._robot_extrapolation(robot, t)
                extrapolated = self._robot_jump(robot, t, previous, motion) if robot_ok else None
                c_match = conf["c_match"] if image_ok else 0.0
                verdict = None
                if image_ok and robot_ok:
                    verdict = self._robot_glitch(kf, dx_img_f, dx_rob_f, c_match, sigma_r,
                                                 intervals, ssim_gain)
                    robot_gated = verdict == "glitch"
                    if verdict == "unjudged":  # as an inconsistent registration: the robot
                        image_ok, dx_img_f, c_match = False, _NAN2, 0.0  # places the frame
                if verdict == "unjudged":
                    self._unjudged_in_a_row += 1
                elif not self._streak_judged():
                    self._unjudged_in_a_row = 0
                dx_rob_used = _NAN2 if robot_gated else dx_rob_f
                if not image_ok and extrapolated is not None:
                    # the robot alone would place it, at a jump of its own signal: a glitch
                    # nothing can check ("Robot gating": unconfirmed robot steps)
                    robot_gated = jumped = True
                    dx_rob_used = extrapolated
                before = kf.snapshot() if image_ok and robot_ok and not robot_gated else None
                warm = kf.warming_up
                step = kf.update(dx_img_f, dx_rob_used, c_match, intervals)
                if before is not None and self._left_out(step, c_match, dx_img_f, dx_rob_used,
                                                         sigma_r, ssim_gain):
                    kf.restore(before)  # the robot places the frame (c_img = 0)
                    image_ok, c_match, image_gated = False, 0.0, True
                    if extrapolated is not None:  # as above: the robot alone, at a jump
                        robot_gated = jumped = True
                        dx_rob_used = extrapolated
                    step = kf.update(_NAN2, dx_rob_used, c_match, intervals)
                    if warm:
                        # Its step still enters the histories of Eq. 13-14: the warm-up ends
                        # after min_history steps whatever their fate, and c_img judges from
                        # then on. Left out of them, gated registrations kept the filter in
                        # its warm-up for good, where nothing could trust them (review 47).
                        kf.record(dx_img_f, intervals)
                computed = conf["c_match"]
                for name in CONFIDENCES:
                    conf[name] = float(getattr(step, name))
                if robot_gated or (image_ok and np.isinf(sigma_r)):
                    # the robot sample had no weight: left out, or of unknown noise (sigma_r0
                    # inf: Eq. 9's variance is inf whatever c_rob; the filter's c_rob, 10 in
                    # its warm-up, read as a 10:1 weight of the robot; review 51)
                    conf["c_rob"] = 0.0
                if np.isnan(conf["c_match"]):
                    # a registration left out (gated, unjudged, inconsistent): its SSIM, when
                    # computed, still says why (report.json had null for every gated frame)
                    conf["c_match"] = computed
                x_f = position = step.position
                status = "placed" if image_ok else "prior-only"
                if (
                    image_ok
                    and robot_ok
                    and not robot_gated
                    # a re-acquisition after a dropout spans many steps, and their drift
                    and self._steps_without_robot < self.options.robot_sigma_max_span
                    and self._trusted(step, c_match, ssim_gain)
                ):
                    self._innovations.append(dx_rob_f - dx_img_f)
            timings["filter"] = time.perf_counter() - t0

        placed = bool(np.isfinite(position).all())
        if self.estimate == "fused" and placed:
            self._placed_timestamp = t  # X_f(i-1) of the next step (_frame_intervals)
        if (
            placed
            and gray is not None
            and not blank
            and (i == 0 or self._anchor is None or np.isfinite(dx).all())
        ):
            # image32 is a fresh float32 array (not a live caller's capture buffer)
            self._anchor = _Anchor(i, image32, gray.dtype == np.uint8, x_m.copy(), x_f.copy())
        if self.estimate == "fused" and placed and np.isfinite(robot).all():
            # A gated sample is not an anchor: the next robot displacement is taken from the
            # last good one, unless the robot has been gated so often in a row that it more
            # likely moved its origin than glitched.
            self._gated_in_a_row = self._gated_in_a_row + 1 if robot_gated else 0
            if motion is _NOT_YET:  # (the anchor and velocity have not moved since)
                motion = self._robot_extrapolation(robot, t)
            self._jump_run = [*self._jump_run, motion[1]] if jumped else []
            if not robot_gated or self._gated_in_a_row >= self.options.robot_gate_rebase:
                if robot_gated:  # a rebase: the offset is no motion, the velocity unknown
                    self._robot_velocity = None
                elif self._robot_anchor is not None:  # the robot's own velocity
                    if motion is not None and motion[2] == 1.0:  # (not a run believed)
                        self._robot_jumps.append(np.abs(motion[1]))
                    r_um, _, r_t = self._robot_anchor
                    self._robot_velocity = (robot - r_um) / (t - r_t)
                self._robot_anchor = (robot.copy(), x_f.copy(), t)
                self._jump_run = []
                self._steps_without_robot = 0
                self._gated_in_a_row = 0
        elif self.estimate == "fused" and placed and self._robot_anchor is not None:
            # No robot sample: the frame was placed by the image alone, one more step of image
            # drift the next robot displacement spans. (An unplaced frame is no step: the next
            # registration spans it, against the same anchor.)
            self._steps_without_robot += 1
        self._count += 1
        self._last_timestamp = t
        timings["total"] = time.perf_counter() - t_start
        position = np.asarray(position, dtype=np.float64).copy()
        return FrameResult(
            index=i,
            timestamp=t,
            position=position,
            homography=translation_homography(position),
            status=status,
            ncc_score=float(score),
            position_image=np.array(x_m, dtype=np.float64),
            position_robot=np.array(x_r, dtype=np.float64),
            position_fused=np.array(x_f, dtype=np.float64),
            sigma_robot0=float(sigma_r),
            displacement_image=np.array(dx_img_f),
            displacement_robot=np.array(dx_rob_f),
            timings=timings,
            robot_gated=robot_gated,
            ncc_consistent=consistent,
            image_gated=image_gated,
            registered_against=against,
            robot_noise_unknown=bool(np.isinf(sigma_r)),
            **conf,
        )

    def _frame_intervals(self, t: float) -> float:
        """Frame intervals since the last frame the filter placed (X_f(i-1), which the image
        and robot steps are taken against: 2 after an unplaced frame), in whole ones of the
        median spacing of the recent frames (1 for the first two and for timing jitter; 2 after
        a frame a live stream dropped): the Kalman filter judges the image step per interval
        (kalman.py)."""
        if not np.isfinite(self._last_timestamp):
            return 1.0
        spacing = t - self._last_timestamp
        since = t - self._placed_timestamp if np.isfinite(self._placed_timestamp) else spacing
        intervals = 1.0
        if self._spacings:
            intervals = max(1.0, float(round(since / float(np.median(self._spacings)))))
        self._spacings.append(spacing)
        return intervals

    def _trusted(self, step, c_match: float, ssim_gain: float = float("nan")) -> bool:
        """Whether the registration of `step` (a filter update) is trusted: the judgement behind
        the sigma_r0 samples and both gates. Once the filter computes its confidences, c_img >=
        robot_sigma_c_img (the 0.5 level of Eq. 15). In its warm-up c_img is the initial
        c_img0 of Sec. II-B, which judges nothing (it is 1 whatever the registration), so the
        one confidence that is computed judges it (_overlaps): its c_match (SSIM of the aligned
        overlap) must reach warmup_overlap_c_match, the level at which the frames visibly
        overlap, as for robot gating in the warm-up (a fibre-pattern lock at 0 px scores
        0.48-0.50), or gain warmup_ssim_margin over the pair's SSIM at 0 px (ssim_gain, NaN
        when not computed). Taken as trusted, a lock in the first frames of a recording that
        starts in a contact loss was placed 40 px off (sigma_r0 still inf), an offset every
        later position kept (44 frames: e_M 38.8 px, the robot's 0.02), and locks after good
        frames fed their 40 px disagreement into the sigma_r0 estimate (e_M 71 px).
        """
        if step.warmup:
            return self._overlaps(c_match, ssim_gain)
        return step.c_img >= self.options.robot_sigma_c_img

    def _overlaps(self, c_match: float, ssim_gain: float) -> bool:
        """The warm-up's judgement of a registration (_trusted): its c_match reaches
        warmup_overlap_c_match, or its SSIM gains at least warmup_ssim_margin over the same
        pair's at 0 px (ssim_gain; NaN when not computed)."""
        margin = self.options.warmup_ssim_margin
        return bool(c_match >= self.options.warmup_overlap_c_match
                    or (margin is not None and ssim_gain >= margin))

    def _sigma_measured(self) -> bool:
        """sigma_r0 is the online estimate (robot_sigma_min_frames samples), or fixed by the
        user (adaptive_robot_sigma False), not a placeholder."""
        o = self.options
        return not o.adaptive_robot_sigma or len(self._innovations) >= o.robot_sigma_min_frames

    def _left_out(self, step, c_match: float, dx_image, dx_robot, sigma_r: float,
                  ssim_gain: float) -> bool:
        """Whether the registration of `step` (a filter update with both displacements) is
        left out, the robot placing the frame (module docstring, "Image gating"): before
        sigma_r0 is measured (sigma_r inf, robot_unknown_at_start) when the filter does not
        trust it (:meth:`_trusted`), after that when it is an outlier (:meth:`_image_outlier`).
        The first was a fallback to KalmanOptions.sigma_robot0, a guess the image gate then
        measured the registration against (1 px: gated beyond 3.2 px), whatever the robot's
        noise (review 47)."""
        if np.isinf(sigma_r) and np.isfinite(self.options.kalman.sigma_robot0):
            # relying on the image (sigma_r0 = inf) would let an untrusted registration (a
            # contact loss in the first frames) place the frame, and the robot anchor and every
            # later position would keep its error for good
            return not self._trusted(step, c_match, ssim_gain)
        return self._image_outlier(step, c_match, dx_image, dx_robot, ssim_gain)

    def _image_outlier(self, step, c_match: float, dx_image, dx_robot,
                       ssim_gain: float = float("nan")) -> bool:
        """True when the registration of `step` (a filter update with both displacements) is
        not trusted (:meth:`_trusted`) and differs from the robot displacement on an axis by
        more than image_gate_sigmas x the robot's standard deviation under Eq. 9,
        sigma_r0 / sqrt(c_rob) (module docstring, "Image gating"). Never before sigma_r0 is
        measured (_sigma_measured), nor with an infinite prior variance."""
        k = self.options.image_gate_sigmas
        if k is None or not self._sigma_measured() or self._trusted(step, c_match, ssim_gain):
            return False
        if not np.isfinite(step.prior_variance):
            return False
        limit = k * np.sqrt(step.prior_variance)
        return bool(np.abs(np.asarray(dx_robot) - np.asarray(dx_image)).max() > limit)

    def _robot_extrapolation(self, robot: np.ndarray, t: float):
        """(where the robot's own recent motion puts it at ``t``, µm; the robot sample
        ``robot``'s deviation from that, px, signed; the frame intervals spanned since its
        anchor), or None without a velocity. The motion: the last robot anchor extrapolated at
        the velocity between the last two (``_robot_velocity``; None before there are two, and
        after a rebase until the next)."""
        if self._robot_velocity is None or self._robot_anchor is None:
            return None
        r_um, _, r_t = self._robot_anchor
        expected = r_um + self._robot_velocity * (t - r_t)
        spacing = float(np.median(self._spacings)) if self._spacings else t - r_t
        span = max(1.0, float(round((t - r_t) / spacing)))
        return expected, (robot - expected) / self.pixel_size_um, span

    def _robot_jump(self, robot: np.ndarray, t: float, previous: np.ndarray, motion
                    ) -> np.ndarray | None:
        """The displacement from X_f(i-1) (``previous``) to where the robot's own recent motion
        puts frame i (_robot_extrapolation), when the robot sample ``robot`` (µm, at ``t``)
        jumps off it; else None (also without a velocity). A robot is a smooth actuator: a gross
        jump of its own signal is a glitch (module docstring, "Robot gating": unconfirmed robot
        steps). The bound: ``robot_gate_sigmas`` x the robust scale (1.4826 x median) of the
        recent anchors' own deviations (per frame interval; once robot_sigma_min_frames of them
        exist), at least ``robot_gate_fraction`` of the frame's smaller side; allowed once per
        frame placed without a robot sample since the anchor, plus one, up to
        ``robot_gate_max_span`` times (the extrapolation's error grows with the span; gated
        frames do not widen it: a lasting offset of 1.3 x the bound passed at the third,
        review 51). ``robot_gate_fraction`` None: never.

        Also None (the robot believed) for the ``robot_gate_rebase``-th such sample in a row
        when the run moves steadily away from the extrapolation (its deviations on a line, of a
        slope beyond the bound: the robot changed its velocity, e.g. started from rest faster
        than half a frame per frame); a run of about one deviation (a lasting offset) is
        re-anchored as a gated run is (the rebase). ``motion``: _robot_extrapolation(robot, t),
        which _place reuses."""
        if motion is None:
            return None
        expected, deviation, span = motion
        floor = self._gate_floor_px
        if len(self._robot_jumps) >= self.options.robot_sigma_min_frames:
            scale = 1.4826 * float(np.median(np.concatenate(self._robot_jumps)))
            floor = max(self.options.robot_gate_sigmas * scale, floor)
        # frames placed without a robot sample since the anchor widen it; gated ones do not (a
        # lasting offset then stays gated until the rebase, as in _robot_glitch)
        bound = floor * min(1 + self._steps_without_robot, self.options.robot_gate_max_span)
        if not float(np.abs(deviation).max()) > bound:  # (also for bound = inf)
            return None
        run = [*self._jump_run, deviation]
        if len(run) >= self.options.robot_gate_rebase and len(run) >= 2:
            steps = np.diff(np.asarray(run), axis=0)  # the run's velocity off the extrapolation
            steady = len(run) < 3 or np.abs(np.diff(steps, axis=0)).max() <= floor
            if steady and np.abs(run[-1] - run[0]).max() > floor:
                return None
        r_um, r_xf, _ = self._robot_anchor
        return r_xf + (expected - r_um) / self.pixel_size_um - previous

    def _streak_judged(self) -> bool:
        """True once robot_gate_rebase registrations in a row were left unjudged: they are
        then believed over the robot (_robot_glitch)."""
        return self._unjudged_in_a_row >= self.options.robot_gate_rebase

    def _robot_glitch(self, kf, dx_image, dx_robot, c_match: float, sigma_r: float,
                      intervals: float = 1.0, ssim_gain: float = float("nan")):
        """"glitch" when the robot displacement is a gross outlier next to a trusted
        registration (module docstring, "Robot gating"), else None. The image confidence c_img
        (Eq. 16) does not depend on the robot; it is read from a trial update of a copy of the
        filter. "unjudged" when they disagree beyond the bound while the filter is still in its
        warm-up (c_img is the initial c_img0 of Sec. II-B, no judgement of this registration)
        and no registration has agreed with the robot yet (no sigma_r0 sample): nothing says
        the image is the one to believe, and it must not veto the robot. A fast scan whose
        frames do not overlap keeps the filter in warm-up (its registrations fail or lock on the
        fibre pattern at ~0 px); such locks vetoed the correct robot and placed 4 of 30 frames
        550-670 px off (seed 8, 600 µm/frame: 84.6 px mean, the robot alone 4.2). The frame is
        then placed by the robot, as for an inconsistent registration; unless the frames
        visibly overlap (_overlaps: c_match at least warmup_overlap_c_match, a fibre-pattern
        lock scores ~0.5, or the SSIM gain over 0 px at least warmup_ssim_margin), so the
        registration is believed and the robot gated (a +5 mm robot glitch at frame 1 placed
        that frame at the glitch).
        Only up to robot_gate_rebase such frames in a row (_streak_judged): an unjudged frame
        adds no image step to the filter's history, so a robot that disagrees on every frame
        (in the wrong units: 10 x the image steps) kept the filter in warm-up for good and
        placed every frame alone, with no units warning (robot_agreement had no confident
        step; 256x224 px circle, 60 frames, robot x 10: 59 prior-only, e_M 6467 px; now 3
        prior-only, 42 gated, 2639 px and the warning). The fast scan's locks come one at a
        time between failed registrations, which end a streak.

        ``_steps_without_robot``: frames placed from the image alone since the robot anchor,
        for want of a robot sample. The robot displacement then spans 1 + that many image steps
        while the registration spans one, and their difference holds the image chain's drift
        over those steps (a re-acquisition after a robot dropout). The bound is per step, so it
        is allowed once per step spanned: a drift that each step would have been let through
        with is let through over the span, and the returning robot corrects it (gated, it would
        be re-anchored at the drifted X_f after robot_gate_rebase frames, its correction lost
        for good), up to robot_gate_max_span times: not gating after a dropout, or widening
        without a cap, would let a gross glitch at the robot's return through, and the anchor
        would move to it for good. Gated frames do not widen it: a lasting offset keeps being
        gated until the rebase, whatever its size."""
        bound = self._gate_floor_px  # sigma_r0 not known yet (inf): the floor alone
        if np.isfinite(sigma_r):
            bound = max(self.options.robot_gate_sigmas * sigma_r, bound)
        bound *= min(1 + self._steps_without_robot, self.options.robot_gate_max_span)
        if not np.abs(dx_robot - dx_image).max() > bound:  # also False for bound = inf
            return None
        trial = copy.deepcopy(kf).update(dx_image, _NAN2, c_match, intervals)
        if trial.warmup and not self._innovations and not self._streak_judged():
            if self._overlaps(c_match, ssim_gain):
                return "glitch"  # the frames overlap: the registration is no lock
            return "unjudged"
        if trial.warmup and not self._innovations:  # a streak: believed over the robot
            return "glitch"
        return "glitch" if self._trusted(trial, c_match, ssim_gain) else None


# -- batch methods (`fusedmosaic run --method ncc|robot|kalman-robot`) ---------------------------


def frame_columns(results: list, ids) -> dict:
    """report.json's per-frame "confidences", "ncc_score", "sigma_robot0_px",
    "trajectories_px" (X_m, X_r, X_f), "robot_gated", "image_gated" and "robot_noise_unknown"
    (the IDs of the frames whose robot sample, whose registration was left out, whose robot
    noise sigma_r0 was not measured yet, as every other frame list of report.json names them)
    of a run's FrameResults, one per frame with ``ids`` its frame IDs, None for a frame not
    processed (a live run's dropped frames: confidences, scores None, positions NaN); and
    "per_frame_ms", the time of add_frame per processed frame after the first. Offline runs
    and streamed ones (estimation/live.py) both write these."""
    def values(name: str) -> list:
        return [None if r is None else float(getattr(r, name)) for r in results]

    return {
        "confidences": {name: values(name) for name in CONFIDENCES},
        "ncc_score": values("ncc_score"),
        "sigma_robot0_px": values("sigma_robot0"),
        "per_frame_ms": ms_stats(np.array([r.timings["total"] for r in results
                                           if r is not None and r.index > 0] or [0.0]) * 1e3),
        "trajectories_px": {
            key: np.stack([np.full(2, np.nan) if r is None else getattr(r, field)
                           for r in results])
            for key, field in (("X_m", "position_image"), ("X_r", "position_robot"),
                               ("X_f", "position_fused"))},
        "robot_gated": [int(ids[k]) for k, r in enumerate(results)
                        if r is not None and r.robot_gated],
        "image_gated": [int(ids[k]) for k, r in enumerate(results)
                        if r is not None and r.image_gated],
        "robot_noise_unknown": [int(ids[k]) for k, r in enumerate(results)
                                if r is not None and r.robot_noise_unknown],
    }


_ANCHOR_FRAME = re.compile(r"against frame (\d+)")  # (RobotPriorMosaicker's statuses)


def name_anchor(status: str, id_of) -> str:
    """A RobotPriorMosaicker status with the frame it registered against ("against frame
    N", N its count of frames added) named by ``id_of(N)``: the frame's id in a dataset, or
    in a live session's recording (which holds the dropped frames too)."""
    return _ANCHOR_FRAME.sub(lambda m: f"against frame {id_of(int(m.group(1)))}", status)


def _run(
    dataset, estimate: str, *, progress: bool, options: RobotPriorOptions | None
) -> MethodResult:
    method, symbol = ESTIMATES[estimate]
    if estimate != "image":
        dataset.require_robot(method)
        dataset.require_pixel_size(method)
    options = RobotPriorOptions() if options is None else options
    n = len(dataset)
    pattern = None
    if options.flat_field and estimate != "robot" and n > 1:  # one frame: nothing to register
        try:
            pattern = fixed_pattern_gain(dataset.frames[k] for k in range(n))
        except ValueError as error:
            raise ValueError(f"{dataset.root}: flat field: {error}") from None
    mosaicker = RobotPriorMosaicker(dataset.camera, options, estimate=estimate,
                                    fixed_pattern=pattern)
    robot = dataset.robot_xy_um
    if estimate == "robot" and robot is not None and not np.isfinite(robot).all(axis=1).any():
        ts = dataset.robot.timestamps
        spacing = f" ({sample_spacing(ts) * 1e3:.3g} ms)" if ts.size > 1 else ""
        raise no_robot_sample_error(
            str(dataset.root / dataset.robot_file), n,
            f"each lies outside its time span or in a gap between samples longer than 3x "
            f"their typical spacing{spacing}")
    results: list[FrameResult] = []
    read_s = 0.0
    for k in tqdm(range(n), desc=method, disable=not progress, leave=False):
        t0 = time.perf_counter()
        image = None if estimate == "robot" else dataset.frames[k]
        read_s += time.perf_counter() - t0
        results.append(
            mosaicker.add_frame(image, dataset.timestamps[k], None if robot is None else robot[k])
        )

    G = np.stack([r.homography for r in results])
    timings = {"read_frames": read_s}
    for stage in (*STAGES, "total"):
        timings[f"{stage}_per_frame_sum" if stage == "total" else stage] = float(
            sum(r.timings[stage] for r in results)
        )

    def column(name: str) -> list:
        return [getattr(r, name) for r in results]

    details = {
        "estimate": symbol,
        **frame_columns(results, dataset.frame_ids),
        "warnings": _origin_warnings(dataset, mosaicker, estimate),
    }
    if estimate != "robot":
        add_inconsistency(details, results, dataset.frame_ids, estimate)
    if estimate != "image":
        add_frames_without_robot_sample(
            details, dataset.frame_ids[~np.isfinite(robot).all(axis=1)].tolist(), n, estimate,
            dataset.robot_file, "outside its time span, or in a gap longer than 3x its typical "
            "sample spacing")
    if estimate == "fused":  # robot and images both seen: do they move alike?
        add_unused_registrations(details, results, dataset.frame_ids)
        add_robot_agreement(details, str(dataset.root / dataset.robot_file),
                            mosaicker.pixel_size_um, dataset.frame_times)
    parameters = {
        "estimate": estimate,
        "pixel_size_um": mosaicker.pixel_size_um,
        "robot_file": dataset.robot_file if estimate != "image" else None,
        **asdict(options),
    }
    # the streaming statuses count frames ("against frame 9"); report.json names frame ids
    # (a dataset with files missing: frame 9 was id 12)
    ids = dataset.frame_ids
    status = [name_anchor(text, lambda count: int(ids[count])) for text in column("status")]
    return MethodResult(
        homographies=G,
        status=status,
        timings=timings,
        parameters=parameters,
        details=details,
        blend="average",
        undistorted=False,  # NCC on the raw frames
        mask_specular=False,  # confocal frames: bright is fluorescence, not a reflection
        # robot places every frame from the robot alone, frame 0 ("placed") too: run checks
        # them all for a black image (a black frame 0 was pasted into mosaic.png)
        images_seen=estimate != "robot",
    )


# Registrations whose directions disagree, of those made, above which an ncc run warns: the
# simulator's scans with contact loss and stick-slip have 1-7 % (circle and spiral, seeds 0-3),
# a scan too fast for its frames to overlap (600 µm/frame, 512x448 px of 1 µm) 86 %.
MAX_INCONSISTENT_FRACTION = 0.25


def add_inconsistency(details: dict, results: list, ids, estimate: str) -> None:
    """details["ncc_inconsistent"]: frame IDs (ids[r.index]: the id of the mosaicker's r.index-th
    frame) whose registration's directions disagreed; for X_m a warning (appended to
    details["warnings"]) when they exceed MAX_INCONSISTENT_FRACTION of the registrations (the
    fused estimate places such frames by the robot). Failed registrations (ncc_consistent
    None: no displacement, the frame not placed by them) are not counted."""
    made = [r for r in results if r.ncc_consistent is not None]
    bad = [int(ids[r.index]) for r in made if not r.ncc_consistent]
    details["ncc_inconsistent"] = bad
    # X_m across frames without a registration (blank, failed): an inconsistent one there is
    # a jump of the whole chain after it (3 blank frames of 60: frame 23 put on frame 19, 158
    # px off, every later frame with it, e_M 151 -> 250 px, without a word; review)
    bridged = [r for r in made if not r.ncc_consistent and r.registered_against is not None
               and r.registered_against < r.index - 1]
    if estimate == "image" and bridged:
        details["warnings"].append(
            "NCC registered " + "; ".join(
                f"frame {int(ids[r.index])} against frame {int(ids[r.registered_against])}"
                for r in bridged[:5]) + (f" and {len(bridged) - 5} more" if len(bridged) > 5
                                         else "")
            + " across frames without a registration (blank or failed), with forward and "
            "backward directions that disagree: X_m likely jumped there, and every frame after "
            "carries the jump (kalman-robot places such frames by the robot; report.json "
            "ncc_inconsistent)")
    if estimate == "image" and made and len(bad) > MAX_INCONSISTENT_FRACTION * len(made):
        listed = listed_ids(bad)
        details["warnings"].append(
            f"{len(bad)} of {len(made)} NCC registrations have forward and backward directions "
            f"that disagree even after the wide-range retry (frames {listed}): consecutive "
            "frames likely do not overlap (a scan too fast for the frame rate) or lack texture; "
            "X_m places them anyway and is unreliable (kalman-robot places them by the robot; "
            "report.json ncc_inconsistent)")


# Registrations the fused estimate did not use (the robot placed their frames: left out by the
# image gate, directions that disagree, or unjudged in the warm-up), of those made, above which
# a kalman-robot run warns: X_f is then mostly the robot's chain. The simulator's scans with
# robot.csv (contact loss, stick-slip; circle and spiral, seeds 0-3, 512x448 and 256x224) have
# 22-34 %, with robot_noisy.csv 3-6 %; a 256x224 scan whose probe is lifted after frame 0 100 %,
# a scan too fast for its frames to overlap (600 µm/frame) 100 %. Before review 47, image noise
# sigma 20 had 42 of 79 correct registrations image-gated (the robot's 165 µm kept, ncc 0.3),
# at 512x448 all 59, without a word.
MAX_UNUSED_FRACTION = 0.5


def add_unused_registrations(details: dict, results: list, ids) -> None:
    """A warning (appended to details["warnings"]) when the robot placed more than
    MAX_UNUSED_FRACTION of the frames whose registration was made (ncc_consistent not None)
    in `results` (FrameResults of the fused estimate, None for a frame not processed;
    ids[r.index]: a frame's id), with why."""
    made = [r for r in results if r is not None and r.ncc_consistent is not None]
    unused = [r for r in made if r.status == "prior-only"]
    if not made or not len(unused) > MAX_UNUSED_FRACTION * len(made):
        return
    gated = sum(r.image_gated for r in unused)
    inconsistent = sum(not r.ncc_consistent and not r.image_gated for r in unused)
    why = [f"{n} {what}" for n, what in (
        (gated, "left out by the image gate (report.json image_gated)"),
        (inconsistent, "with forward and backward directions that disagree (ncc_inconsistent)"),
        (len(unused) - gated - inconsistent, "disagreeing with the robot in the filter's "
         "warm-up, before anything could judge them")) if n]
    details["warnings"].append(
        f"{len(unused)} of {len(made)} NCC registrations were not used, the robot placing their "
        f"frames (frames {listed_ids(int(ids[r.index]) for r in unused)}): {', '.join(why)}. "
        "Consecutive frames likely do not overlap or lack texture (a contact loss, a scan too "
        "fast for the frame rate): X_f is mostly the robot's chain (compare --method ncc; "
        "report.json confidences c_match)")


def no_robot_sample_error(source: str, n: int, why: str) -> ValueError:
    """The error of the robot method when none of the n frames has a robot sample (``why``):
    it places frames by their samples alone, and failed later with "no placed frame to compose
    a mosaic from", naming neither the file nor the cause (review)."""
    return ValueError(f"{source}: none of the {n} frames has a robot sample ({why}): method "
                      "'robot' places frames by their robot samples alone and has none to place")


def add_frames_without_robot_sample(details: dict, missing: list[int], n: int, estimate: str,
                                    source: str, why: str) -> None:
    """details["frames_without_robot_sample"]: ``missing``, the IDs of the frames (of ``n``) that
    had no robot position in ``source`` (``why``: e.g. outside the robot file's time span with
    --allow-untracked, or in a gap of its samples), and a warning when there are any: X_f
    placed them by the NCC registrations alone, X_r left them unplaced. (Before, a
    kalman-robot run over a 2 s gap in robot.csv said nothing: every frame 'placed', e_M 55 px
    against 7.1; review.)"""
    details["frames_without_robot_sample"] = [int(k) for k in missing]
    if missing:
        listed = listed_ids(missing)
        how = ("kalman-robot placed them by the NCC registrations alone, whose drift the robot "
               "does not correct there" if estimate == "fused" else "they are unplaced")
        details["warnings"].append(
            f"{len(missing)} of {n} frames have no robot sample in {source} ({why}; "
            f"frame{'s' if len(missing) > 1 else ''} {listed}): {how} (report.json "
            "frames_without_robot_sample)")


def _origin_warnings(dataset, mosaicker: RobotPriorMosaicker, estimate: str) -> list[str]:
    """origin_warnings of a batch run: the mosaicker was given every frame of `dataset`."""
    return origin_warnings(mosaicker.origin_frames, dataset.frame_ids, len(dataset), estimate,
                           dataset.robot_file)


def origin_warnings(origin_frames: dict, ids, n: int, estimate: str,
                    robot_name: str) -> list[str]:
    """A run whose X_m (X_r, X_f) starts after frame 0 (RobotPriorMosaicker.origin_frames):
    every position carries the unknown motion between frame 0 and that frame; or never starts.
    ids[k]: the id of the k-th frame the mosaicker was given (a streamed run's processed
    frames); n: the frames of the run; robot_name: where the robot positions come from (the
    robot file, or a live session's stream)."""
    warnings = []
    wanted = {"image": ("image",), "robot": ("robot",), "fused": ()}[estimate]
    first = int(ids[0])
    for source in wanted:
        k = origin_frames[source]
        what = (f"frame {first} is blank (a constant image)" if source == "image" else
                f"{robot_name} has no sample at frame {first}")
        if k is None and source == "robot":
            warnings.append(f"{robot_name} has no sample at any of the {n} frame(s): none is "
                            "placed")
        elif k is None and n > 1:
            warnings.append(f"{what} and no frame is textured: only frame {first}, the "
                            "reference, is placed")
        elif k is not None and k > 0 and source == "image":
            # (X_r leaves the frames before its first sample unplaced, frame 0 included: that
            # frame is the reference, which runner.flag_reference_frame warns of)
            warnings.append(
                f"{what}: the NCC chain starts at frame {int(ids[k])}, put at frame {first}'s "
                f"position, so every frame is offset by the (unknown) motion between frames "
                f"{first} and {int(ids[k])}; the mosaic itself is consistent")
    if estimate == "fused":  # needs frame 0 textured or with a robot sample
        k = origin_frames["fused"]
        what = (f"frame {first} is blank (a constant image) and {robot_name} has no "
                f"sample at frame {first}")
        if k is None and n > 1:
            warnings.append(f"{what}, and no frame is textured or has a robot sample: only frame "
                            f"{first}, the reference, is placed")
        elif k is not None and k > 0:
            warnings.append(
                f"{what}: the fused chain starts at frame {int(ids[k])}, put at frame {first}'s "
                f"position, so every frame is offset by the (unknown) motion between frames "
                f"{first} and {int(ids[k])}; the mosaic itself is consistent")
    return warnings


def run_ncc(
    dataset, *, progress: bool = True, options: RobotPriorOptions | None = None
) -> MethodResult:
    """X_m: the image-only chain of NCC registrations (paper 004, Eq. 1-2)."""
    return _run(dataset, "image", progress=progress, options=options)


def run_robot(
    dataset, *, progress: bool = True, options: RobotPriorOptions | None = None
) -> MethodResult:
    """X_r: robot positions at the frame times, relative to frame 0 (paper 004, Eq. 3)."""
    return _run(dataset, "robot", progress=progress, options=options)


def run_kalman_robot(
    dataset, *, progress: bool = True, options: RobotPriorOptions | None = None
) -> MethodResult:
    """X_f: image registrations fused with the robot prior (paper 004, Eqs. 4-18)."""
    return _run(dataset, "fused", progress=progress, options=options)
