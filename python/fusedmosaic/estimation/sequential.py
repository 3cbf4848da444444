"""LBAVis+EMT, the sequential drift-free method of seed 000 (Sec. 3.4, Eqs. 21-27; Sec. 4.2).

`SequentialMosaicker` takes frames one at a time (a live loop or a recorded dataset):

    features -> match against the frames of the window -> C++ SlidingWindow step every chi_e
    frames (new cameras + plane, window and K-means keyframes fixed) -> tracker gating ->
    frame -> reference homographies G_k = H_0 H_k^-1 with the plane of that step (Sec. 3.4:
    "we compose the new homographies with the estimated set of cameras and plane obtained in
    every iteration by using Eq. (5)").

A frame is final once its step has run (every chi_e frames); until then `add_frame` returns a
provisional placement from its tracker pose (or the motion prediction) and the current plane.
The first `bootstrap_frames` (40) frames are final only after the start-up adjustment; until
then their provisional placements are chained through their registered pairs to frame 0 (a
frame without one: from the tracker poses and the plane of the start-up pairs so far).
State is bounded: features only for the frames the window matches against, images never, and
keyframe candidates in a bounded spatial reservoir (estimation/keyframes.py) whose evicted frames
are forgotten by the C++ window too.

Input contract of `add_frame` (checked before anything changes; a refused call raises and leaves
the mosaicker as it was, so the frame can be corrected and sent again with the same timestamp):
- image: numpy array, uint8, (H, W) gray, (H, W, 3) BGR or (H, W, 4) BGRA (alpha ignored), of
  the camera's size. Other dtypes (uint16, float, bool) are refused, not rescaled: the scaling
  of a 16-bit or float image is the caller's to choose (the dataset reader converts 16-bit
  frames with one scale for the whole dataset, io.video.FrameSource). None, lists and other
  shapes are refused (TypeError / ValueError).
- timestamp: a finite real number of seconds, increasing, |t| <= io.tracking.MAX_TIMESTAMP_S
  (1e10 s) and at most `SequentialOptions.max_timestamp_gap_s` (1 day) after the previous
  frame's: a larger value is taken for a unit mix-up (ms, µs or ns given as s) and refused,
  since it would block every later frame (the same checks as RobotPriorMosaicker,
  io.tracking.check_stream_timestamp).
- tracker_pose: None (or 6 NaN, as read_dataset writes a tracker gap) for a frame without a
  tracker sample, or 6 finite real numbers [r, t]: the CAMERA's pose cam_from_world
  (angle-axis rad, mm), i.e. the tracker sample composed with the hand-eye transform
  (io.camera_pose_from_sample does it for one live sample), with |t| within the dataset
  reader's 1 km bound (io.tracking.MAX_TRANSLATION_MM). The rotation vector is canonicalised
  to norm <= pi (the same rotation written with norm > pi, as a quaternion with w < 0 converts
  to, gives the same mosaic).
A tracker sample that jumps from the last trusted one faster than
`tracker_max_speed_mm_s` / `tracker_max_angular_speed` allow (plus a noise margin) is a glitch:
it is dropped before it reaches the window (the frame is placed from its images and the motion
prior, and flagged `tracker_gated`), since a window step initialised from it does not recover.
Smaller errors are gated by the window step (`gate_chi2`).

Failure safety: everything a call changes is staged; if anything raises inside the call
(including KeyboardInterrupt), the Python state is restored and the C++ window rebuilt from a
mirror of its frames, pairs and plane, so the next call continues as if the failed one had not
happened. Only if that restoration itself fails is the mosaicker marked unusable: every later
call then raises a RuntimeError saying why; `reset()` starts a new mosaic. The mosaicker is not
re-entrant: a second thread calling it while a call is running gets a RuntimeError.
"""

from __future__ import annotations

import copy
import numbers
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from tqdm import tqdm

from fusedmosaic import _core
from fusedmosaic.estimation.bundle import (
    chain_missing_poses,
    fill_missing_poses,
    subsample_inliers,
    unanchored_frames,
)
from fusedmosaic.estimation.consistency import (
    CONVENTIONS_AND_TIMING,
    MAX_NOISE_RATIO,
    SIGMA_V_AUTO,
    SIGMA_V_START_PX,
    TRACKER_NOISE_ADVICE,
    TransferResiduals,
    add_tracker_agreement,
    auto_sigma_v,
    check_emt_sigma,
    check_sigma_v,
    given_sigma_v_report,
    solver_warning,
    starting_sigma_v,
    tracker_agreement,
    visual_agreement,
)
from fusedmosaic.estimation.guard import exclusive_call
from fusedmosaic.estimation.keyframes import KeyframeIndex
from fusedmosaic.estimation.motion import (
    CHI2_6_MEDIAN,
    MOTION_GATE_CHI2,
    MOTION_MAX_GAP_S,
    RELEASED,
    motion_departure_scale,
    motion_timing,
    motion_verdict,
    predict_constant_velocity,
    tracker_motion_departure,
    triple_departures,
)
from fusedmosaic.estimation.plane import (
    MAX_NOMINAL_PARALLAX,
    MIN_BASELINE_RATIO,
    MIN_PAIR_BASELINE,
    baseline_ratio,
    camera_baseline_mm,
    estimate_plane,
    homography_parallax,
    plane_depths,
    plane_facing,
)
from fusedmosaic.estimation.world import (
    WorldAlignment,
    origin_near_plane,
    plane_from_aligned,
    plane_to_aligned,
    poses_from_aligned,
    poses_to_aligned,
    same_world,
    tracked_world,
    world_alignment,
)
from fusedmosaic.io.tracking import MAX_TRANSLATION_MM, check_stream_timestamp
from fusedmosaic.methods import MethodResult
from fusedmosaic.registration.features import FeatureExtractor, FeatureOptions
from fusedmosaic.registration.pair_selection import footprint_polygons, overlap_fraction
from fusedmosaic.registration.pairs import MatchOptions, guided_search, match_pair

# Paper presets (Sec. 4.2): (W, chi_e, K, frames per cluster).
PRESETS = {"syn": (5, 3, 3, 5), "phb": (3, 1, 3, 3), "ex": (12, 6, 3, 12)}
# FrameResult.status of a frame whose window step Ceres could not solve (FAILURE), even after
# dropping the samples that made its evaluation fail: it stays at its starting pose (its
# tracker sample, or the motion prediction).
SOLVER_FAILED_STATUS = "prior-only (solver failed)"
# Sigma_p scale of the constant-velocity term linking a tracked frame to frames placed without
# any anchor (see SequentialMosaicker._unanchored): the term is in effect released, the
# dead-reckoned motion before the tracker came back is no evidence for the frame.
RELEASED_MOTION_SIGMA_SCALE = 1e3
# The tracker samples and times kept for the motion checks, frames back from the newest: the
# held frames judged again before their step look 5 frames further back (_judge_motion_again).
SAMPLES_KEPT = 20
# Ceres' relative cost change that ends a solve, the window steps' and the start-up's (Ceres'
# default). The start-up had BundleAdjusterOptions' 1e-10 (the offline ba-emt's): ill-
# conditioned start-ups crawled to startup_max_iterations for nothing (a tracker on at frame
# 101, 81 frames held, 2 tracked: 300 iterations, 7.7 s, cost 1297.20; at 1e-6: 18, 0.5 s,
# 1297.33, e_M 0.115 -> 0.120 px; SYN 150 frames: 8 -> 6 iterations, e_M 0.1454 -> 0.1453).
FUNCTION_TOLERANCE = 1e-6
# Iterations each of the start-up's two initial planes is adjusted before the better one is
# taken (_initial_plane).
STARTUP_PROBE_ITERATIONS = 5
# Relative std of a start-up plane above which the start-up, made to decide, solves on to the
# offline tolerance to tell an unbounded plane from a finite one (see _bootstrap). Unbounded
# ones stopped at FUNCTION_TOLERANCE at 643-5500; late trackers' finite ones at 1.0-2.2,
# where solving on crawled along the valley their scale leaves for 300 iterations (7-8 s).
UNBOUNDED_CHECK_RELATIVE_STD = 10.0
# A start-up plane behind its cameras from at least this many registered pairs showing parallax
# is blamed on the tracker's poses, not on too few pairs or too short a baseline.
CONTRADICTING_PAIRS = 20
# A start-up refused with that many pairs while its tracked camera centres lie within this (mm)
# of each other says the tracker's translations may not be in mm (_units_hint): in metres an
# 80-frame SYN start-up's 33 mm read 0.033.
UNITS_BASELINE_MM = 1.0
# A window step whose evaluation failed (Ceres FAILURE) drops the tracker samples of its frames
# that put their camera nearer the plane than this fraction of the window cameras' median depth
# (or on or behind it), re-initialises those frames and is redone (_recover_failed_step).
UNUSABLE_DEPTH_RATIO = 0.05
# A start-up refused while it holds startup_wait_frames frames is tried again once this
# fraction of them came since (new tracked pairs, a quarter more, still try at once): every
# frame then hands its oldest out unplaced, so a start-up accepted k frames later places k
# frames fewer, at most 9 of 80.
STARTUP_RETRY_FRACTION = 0.125
# A start-up frame whose overlap with an older start-up frame the tracker cannot predict (either
# untracked) is matched, beyond the window's W - 1 frames, against at most this many older
# frames that the chain of registered pairs says overlap it most (_chained_candidates; 6 as
# ba-emt's EMT-guided pairs), and about STARTUP_STRIDE_PAIRS more in a stride over the rest.
# Before, against every frame the start-up held: a tracker off for the first 110 frames (SYN
# 400 px, ORB) cost 80 pairs and 371 ms a frame (median), now 12 and 22-32 ms. Placed after
# the tracker came on (e_j re-referenced to the first frame placed, median / max px): that run
# 0.11 / 0.34 and 0.19 / 0.48 before and after frame 110 (exhaustive 0.18 / 0.77, 0.26 /
# 0.78); recordings of 300 px, SIFT, tracker on at frame 85 or 100: SYN 0.16 / 0.39 and 0.10 /
# 0.19 (exhaustive 0.14 / 0.36, 0.12 / 0.18), hand-held 0.13 / 0.33, 0.47 / 1.35, 0.25 / 0.43
# (0.15 / 0.43, 0.33 / 1.01, 0.25 / 0.45). 10 instead of 6 gave 0.39 / 1.20 on the worst of
# these, 0.38 / 1.33 on the first: such start-ups, a few tracked frames, are ill-conditioned
# either way.
STARTUP_CHAINED_PAIRS = 6
STARTUP_STRIDE_PAIRS = 2
# The start-up refuses its tracker samples when the glitch filter dropped more than this
# fraction of them (_tracker_jumps). Measured at the start-up's first attempt: tracker_pose
# with rotations in degrees 4 of 8 samples dropped (the tests' 8-frame start-up) and 25 of 40
# (SYN, 200 px), given as [t, r] 4 of 8 and 18 of 40; the tests' glitches (a +10 m or +100 m
# sample, a bad first one, 4x the prior's noise) at most 1 of 8. A tracker re-based once (its
# reference changed mid-start-up) has 2 dropped (tracker_reanchor_after - 1): the samples a
# re-anchoring drops, those the old reference had accepted, are not counted (counted, 20 of
# them made a default start-up wait 40 frames more, 30 lost 10 frames). The tracker's
# disagreement with the adjusted poses (consistency.tracker_agreement's noise ratio) does not
# tell them apart: quaternions stored w first, which a 12-frame start-up takes and the run warns
# of, read 4.2 x the prior's noise (30 frames: 8.3), [t, r] from 4.4, 4x the noise 3.3-3.5.
STARTUP_MAX_DROPPED_FRACTION = 0.25
# The tracker disagrees with the images while more than TRACKER_WARNING_FRACTION of the tracker
# samples of the last TRACKER_WARNING_FRAMES final frames given one (at least
# TRACKER_WARNING_MIN) were gated or dropped. Measured over the last 100 of 200 frames (SYN 256
# px, ORB): consistent samples 0 %, 2x the prior's noise 56 %, 4x 98 %, rotations in degrees or
# [t, r] from frame 60 on (the start-up took the right ones) 100 %. 3/4 holds from ~2.5x the
# noise on, as the offline tracker_agreement check does (MAX_NOISE_RATIO: 2x read 1.65); over
# 50 frames, from a mix-up's 38th final frame on (after consistent samples). It is checked as
# frames are finalised: the first stretch where it held is kept (_tracker_episode: the frame
# where it began, and where it ended) and live_solver_warnings reports it at the session's end
# (tracker_warning), with the last 50 frames' count when it still holds (a stretch of 55 frames
# 4x as noisy mid-session, 75 % gated, went unreported when only the last 50 were looked at).
TRACKER_WARNING_FRACTION = 0.75
TRACKER_WARNING_FRAMES = 50
TRACKER_WARNING_MIN = 20


@dataclass
class SequentialOptions:
    """Options of :class:`SequentialMosaicker` (LBAVis+EMT); defaults are the paper's SYN preset.

    Window (Sec. 3.4, 4.2): ``window_size`` W cameras per step of which ``num_new`` (chi_e) are
    new; ``num_clusters`` K-means clusters of older frames, ``frames_per_cluster`` consecutive
    keyframes picked from each (``max_keyframe_blocks`` bounds the candidates kept); the other
    presets with :meth:`preset` ("syn", "phb", "ex").
    Registration: ``features`` (detector "sift" or "orb"), ``matching`` (ratio test, RANSAC,
    threads), ``max_points_per_pair`` inliers kept per pair.
    Costs: ``sigma_v_px`` (px), ``motion_sigma`` and ``emt_sigma`` (rad x3, mm x3; None = the
    paper's appendix values), ``loss``, ``linear_solver``, ``max_iterations``;
    ``motion_max_gap_s`` (s): a longer frame interval (or one 8 x its neighbour) breaks the
    motion prior.
    Start-up: the first ``bootstrap_frames`` frames are adjusted together (BA+EMT) before the
    window starts, matched by predicted overlap (``startup_min_overlap``, a fraction);
    ``startup_wait_frames`` bounds the wait for a tracker and for a plane in front of the
    cameras whose relative std is at most ``startup_max_plane_std``.
    Beyond the paper (0 disables each): ``loop_pairs`` spatial loop pairs per frame (at least
    ``loop_min_separation`` frames back), ``hold_prior_only_steps``,
    ``hold_unanchored_frames`` (frames without an anchor stay free until two follow), the
    plane observability gate ``plane_max_relative_std``.
    Tracker checks: ``gate_chi2`` / ``gate_sigma_scale`` down-weight a sample that disagrees
    with the images; ``motion_gate_chi2`` releases C_p where the tracker or a solve says the
    motion left constant velocity; ``tracker_max_speed_mm_s`` (mm/s),
    ``tracker_max_angular_speed`` (rad/s), ``tracker_jump_margin_mm`` / ``_rad``,
    ``tracker_max_gap_s`` (s) and
    ``tracker_reanchor_after`` drop glitches. ``max_timestamp_gap_s`` (s) refuses unit
    mix-ups. ``history_steps`` window step summaries are kept; ``seed`` seeds the keyframe
    picks. The comments at each field in the source give the measurements behind the values.
    """

    window_size: int = 5  # W (Sec. 4.2, SYN preset)
    num_new: int = 3  # chi_e, cameras estimated per step
    num_clusters: int = 3  # K of K-means
    frames_per_cluster: int = 5  # consecutive frames picked per cluster
    features: FeatureOptions = field(default_factory=FeatureOptions)
    # The new frame's pairs (window + loop, ~6) are matched on num_threads threads (2: the
    # cores of the target machine; the window step is single-threaded). ORB, 400x400 SYN, 700
    # frames, 1 and 2 threads interleaved in one run on a 2-core machine: 24.4-24.9 frames/s,
    # median 38.5-39.5 ms -> 32.1-32.3 frames/s, 29.9-30.7 ms; the mosaics are identical.
    matching: MatchOptions = field(default_factory=MatchOptions)
    max_points_per_pair: int = 100  # inliers kept per pair
    # px, the keypoints' noise per axis (Sec. 4.2's sigma_v, 1 px there, the default); "auto":
    # measured by the start-up (consistency.SIGMA_V_AUTO: its BA+EMT solved with 1 px, then
    # again with the transfer residuals' robust std, which the window keeps; visual_sigma says
    # what it took). Not the default: on weak texture (200 px SYN, ~19 inliers per pair, 3000
    # frames; bench/bench_plane_gate.py) it gave e_M 9.5 px and a frame 81 px off, against 7.6
    # and 30 with 1 px (the tracker alone with the true plane: 18.2 / 46 px).
    sigma_v_px: float | str = 1.0
    # Constant-velocity prior std devs (rad x3, mm x3); None = the paper's appendix values.
    # estimation/motion.py estimates them from an independent recording, as Sec. 4.2 did.
    motion_sigma: tuple[float, ...] | None = None
    # EMT prior std devs (rad x3, mm x3, Eq. 25): the tracker's noise; None = the paper's
    # appendix values (1 deg, 1 mm). The gate (gate_chi2) measures samples against them.
    emt_sigma: tuple[float, ...] | None = None
    loss: str = "none"
    linear_solver: str = "auto"
    max_iterations: int = 20
    # Tracker gating: a sample whose whitened distance to the fused pose exceeds the 99.9 %
    # chi-square quantile for 6 dof (22.46) is down-weighted (sigma x gate_sigma_scale) and the
    # step redone, when the frame has visual evidence to judge it by.
    gate_chi2: float = 22.46
    gate_sigma_scale: float = 10.0
    # Motion gate (not in the paper): C_p does not link a frame whose tracker samples over
    # frames k-2, k-1, k depart from constant velocity by more than this (Mahalanobis^2 with
    # Sigma_p and their own noise, each component scaled by its median; not where one or two
    # bad samples explain it, which are then gated, nor where no explanation can be tested,
    # e.g. just after a pause: motion.motion_verdict, judged again before each step with the
    # later samples), nor a frame with pairs and a
    # triple missing a tracker sample whose C_p block a solve leaves above it
    # (BundleAdjusterOptions.motion_gate_chi2). Black frames tracked while the scope spun in at
    # 30 deg per frame (120 sigma_p) and stopped: their C_p turned the textured frames of the
    # start-up with it, e_M 12 to 263 px on the 24-frame test scene (0.47 px without them),
    # 0.45-0.88 px with the gate. Simulated sequences (SYN, hand-held, black frames, a tracker
    # 4x noisier than Sigma_EMT) are left alone (identical e_M). inf: off.
    motion_gate_chi2: float = MOTION_GATE_CHI2
    max_keyframe_blocks: int = 200  # bound on retained keyframe candidates (memory, per-step cost)
    # Initialisation: the first frames are bundle-adjusted together (all pairs, BA+EMT) to get the
    # plane and their poses before the window starts. A plane from the first chi_e frames alone
    # (1-3 mm baselines against 1 mm tracker noise) was 11 % off in depth on SYN, and the window
    # cannot repair it later: pairs between fixed cameras pin pi to their scale.
    # Measured on SYN-150: 15 frames -> e_M 0.30 px (plane 2.4 % deep), 25 -> 0.30, 40 -> 0.14.
    bootstrap_frames: int = 40
    # Start-up frames are matched against the window and every earlier start-up frame whose
    # footprint, predicted from the tracker poses and a provisional plane (from the start-up
    # pairs registered so far), overlaps theirs by >= this fraction of the smaller one (as
    # ba-emt's EMT-guided pairs); 0 = all earlier start-up frames. Where either frame has no
    # tracker sample, the start-up's chain of registered pairs predicts the overlap, and at most
    # STARTUP_CHAINED_PAIRS + STARTUP_STRIDE_PAIRS such older frames are tried (a start-up
    # waiting for its tracker matched each frame against all it held). The start-up adjustment
    # is then ba-emt over the first frames with (nearly) all pairs that can register: every
    # later frame is tied to it. On SYN 152 (bench/bench_sequential.py,
    # bench_lba_experiments.py) all pairs gave e_M 0.136 px where a sparse stride-4 subset gave
    # 0.152 (lba/ba 1.42 vs 1.59), but cost ORB 13 s over the 40 frames; this overlap test:
    # 0.144 px, ORB 1.7 s (stride 4: 4.1 s). On slow hand-held motion every start-up frame
    # overlaps, so the start-up gets all 780 pairs (start-up frames up to ~67 ms instead of
    # ~30). Keeping only the 6 best-overlapping older frames per frame, as ba-emt's EMT-guided
    # selection does, was measured too: cheaper, but e_M 0.145 / 0.135 / 0.042 / 0.077 px on
    # SYN seeds 0-3 against 0.144 / 0.123 / 0.034 / 0.064.
    startup_min_overlap: float = 0.3
    # Spatial loop pairs (beyond the paper's Eq. 25 window; its Sec. 5 proposes such a
    # spatio-temporal window): each new frame is also matched against up to this many retained
    # older frames whose footprint, predicted from the drift-free tracker pose, overlaps it.
    # Measured in bench/bench_sequential.py. 0: no loop pairs, only the temporal ones, which is
    # close to the paper's LBA but not exactly its Eq. 25 window: each new frame is matched
    # against its W - 1 predecessors, so a step's later frames reach up to W - 2 frames behind
    # the window's W - chi_e fixed ones (SYN: the step 115-117 has pairs to 111 and 112, outside
    # 113-117). The C++ step joins every fixed camera paired with a free one as a constant, so
    # those pairs, and the pairs among those cameras (which constrain pi alone), enter C_v; the
    # step summary counts them as loop correspondences (SYN: 800 of a step's 1800, no loop pair).
    loop_pairs: int = 2
    loop_min_separation: int = 10  # frames between a new frame and its loop candidates
    # Pair consistency (not in the paper, 0 disables): a new frame's registered pairs are
    # checked against each other before they enter C_v, with a limit of this fraction of the
    # frame's diagonal (at least PAIR_CONSISTENCY_MIN_PX) on the mean corner distance. Two
    # partners registered to each other predict one pair from the other (a triangle); a pair
    # that two or more triangles contradict, and more than confirm it, is left out. The
    # start-up then leaves out, one at a time, a pair its adjustment leaves over the limit and
    # 5 x the pairs' median RMS (a group of wrong pairs that agree with each other: triangles
    # miss it). Counted in pair_counts["inconsistent"]. A frame decoded in part (an MJPG
    # frame's top, another view below) registered 3 of its pairs to that other view, 66 px off;
    # under C_v's squares they moved a 27-frame run's e_M 0.14 -> 5.5 px (0.140 with the
    # check); the same splice at frame 60 of 90 took frames 64-83 6-19 px off, e_M 1.41 (0.188;
    # 0.187 unspliced).
    pair_consistency_fraction: float = 0.05
    # A frame without visual evidence (Sec. 4.2.3) is placed by C_EMT and C_p alone. Fixed at the
    # end of its step it would be extrapolated from its predecessors only; instead it stays free
    # (with the frames after it) for up to this many more steps, until two frames with visual
    # evidence follow it, so C_p ties it to both sides. 0 fixes it at once (the paper's LBA).
    hold_prior_only_steps: int = 2
    # A frame without an anchor (no tracker sample used, no registered pair leading to an
    # anchored frame: black frames in a tracker dropout, and the visual chain after them) stays
    # free too, with the frames after it, until two frames with an anchor follow them (the
    # tracker returns, or a pair to an anchored older frame; two, so that C_p ties the far side's
    # velocity as well as its position: _held_tail), for up to this many frames; then C_p and
    # the pairs tie the lost frames to anchors on both sides. 0 finalises them at once,
    # extrapolated ("dead-reckoned"). 12 black frames in a 26-frame dropout (SYN, 110 frames):
    # black e_M / worst 165 / 338 px -> 10.2 / 16.6, the 4 textured frames chained to them
    # 352 px -> 0.1; held steps (up to ~28 free frames) p95 5.4 ms where 3.8 before.
    hold_unanchored_frames: int = 25
    # Plane observability gate (not from the paper): after each step the marginal covariance of
    # pi given the step's costs is computed; if its relative standard deviation
    # sqrt(trace(Cov_pi)) / |pi| exceeds this, the step cannot tell where the plane is and is
    # solved again with pi held at its previous value (step summary plane_held). Normal
    # operation measured 0.0004-0.0104 (SYN and hand-held presets, with and without black
    # frames); 0.02 leaves it alone. On weak texture (200x200 SYN, SIFT, ~19 inliers per pair,
    # 65 % of frames without a registered pair) a step whose only visual evidence was one pair
    # between tracker-placed cameras moved pi to infinity: frames at 238 px, e_M 13.2 px; gated:
    # max 24.9 px, e_M 7.3 px (the tracker alone with the true plane: max 34.3, e_M 17.2 px).
    # The std costs one more Jacobian evaluation per step (~0.6 ms on SYN, bench_plane_gate);
    # 0 disables the gate and that cost. The value is for sigma_v = 1 px, with which it was
    # measured; the window compares with it x sigma_v_px / 1 px (pi is observed through C_v
    # alone: its std scales with sigma_v; _core.SlidingWindowOptions), and reports the steps'
    # std at 1 px (report.json plane_gate, plane_relative_std).
    plane_max_relative_std: float = 0.02
    history_steps: int = 1000  # window step summaries kept (diagnostics, bounded)
    # Input guards (not from the paper). A timestamp more than this after the previous frame's
    # is refused as a unit mix-up (e.g. ns as s): accepted, it would block every later frame.
    max_timestamp_gap_s: float = 86400.0  # 1 day
    # A tracker sample whose camera centre moved from the last trusted sample's by more than
    # tracker_max_speed_mm_s * dt + tracker_jump_margin_mm (or rotated more than
    # tracker_max_angular_speed * dt + tracker_jump_margin_rad) is a glitch and dropped before
    # the window sees it. Generous physical bounds for a hand-held endoscope (1 m/s, 1 turn/s)
    # plus a margin far above tracker noise (~1 mm, ~1 deg): gross errors within them are
    # gated by the window step (+5 to +20 mm, +10 to +30 deg measured), larger ones made the
    # step diverge from the sample (a +10 m glitch on one frame: e_M 1131 px on 30 frames).
    tracker_max_speed_mm_s: float = 1000.0
    tracker_max_angular_speed: float = 2 * np.pi  # rad/s
    tracker_jump_margin_mm: float = 50.0
    tracker_jump_margin_rad: float = 0.5
    # dt in those bounds is capped at this (s), so that a glitch after a tracker dropout is
    # still caught; and after this many dropped samples in a row the newest becomes the
    # reference (the reference itself was the glitch, e.g. a bad first sample, or the tracker
    # moved for good), as the pCLE robot gate re-anchors.
    tracker_max_gap_s: float = 1.0
    tracker_reanchor_after: int = 3
    # A frame interval longer than this (s) and than 8 nominal intervals, or 8 times the one
    # before or after it, breaks the constant-velocity prior (motion.motion_timing): no C_p
    # across it, zero velocity after it. Extrapolated across a pause of 0.5-60 s with the
    # tracker lost, frames were 1e3-1e5 px off.
    motion_max_gap_s: float = MOTION_MAX_GAP_S
    # Frames the start-up keeps while it waits for a registered pair with tracker poses (the
    # tracker switched on late); older ones are handed out unplaced. 2 x bootstrap_frames.
    startup_wait_frames: int = 80
    # The start-up also waits while its plane's relative standard deviation (the marginal
    # covariance of pi given the start-up's costs, over |pi|) is above this (0: never), until
    # it holds startup_wait_frames frames. The simulated start-ups give 0.012-0.025 (40
    # frames, 400 px; 0.07 with 8 frames of 200 px), a weakly textured one with 3 registered
    # pairs 1.8 (frames then ~1000 px off; waiting: 5 pairs, 0.17, 23 px). 0.05 or 0.1 made
    # it wait longer, but not better on other weakly textured scenes (seeds 0-9 of the tests'
    # 60-frame scene: 0.1 gave 5.6 / 19.5 px where 0.25 gives 4.4 / 10.6 on seeds 3 / 5);
    # 0.25 leaves every simulated start-up alone (up to 0.11 with 8 frames).
    startup_max_plane_std: float = 0.25
    # A start-up camera that did not translate (held still, or turning about its axis) shows
    # no parallax: its plane comes out anywhere, near infinity, on either side of the cameras
    # (relative std 2.1 over 50 still frames; behind them after 80). When the start-up must
    # decide (the sequence ends, or it holds startup_wait_frames frames) and its cameras'
    # spread is below MIN_BASELINE_RATIO of the plane's depth, the plane is put facing them at
    # this distance and held while their poses are adjusted: the images tie their centres
    # together, so the homographies do not depend on it, and the window measures pi once the
    # camera translates (fetoscopes view the placenta from 10-50 mm).
    nominal_plane_distance_mm: float = 30.0
    # The start-up adjustment starts from the tracker's poses, far from its solution when the
    # tracker's noise is large against the scene (5 mm from the plane: initial cost 1.3e8, 187
    # iterations to converge; a SYN circle of 0.3 mm hovering: 128-200; a hand-held one at 30
    # mm: 11). Ceres' default 100 stopped those short, with a warning, at the same e_M.
    startup_max_iterations: int = 300
    # A start-up whose frames mostly lack tracker samples (a tracker switched on late: 2 of 73
    # tracked) is solved first with at most this many iterations while a refusal would only
    # make it wait: its poor conditioning kept Ceres crawling for 300 iterations (6 s each
    # time, 16 s over 4 frames streamed) towards a plane refused anyway. Refused for its
    # plane's std there, it waits; else it is solved on to startup_max_iterations from there
    # (e_M 0.0586 -> 0.0561 px; measured before FUNCTION_TOLERANCE, which shortens both).
    startup_trial_iterations: int = 40
    # Ceres' trust region strategy for the adjustment of a start-up whose frames are not all
    # tracked ("dogleg" or "levenberg_marquardt"). A late tracker's start-up (80 frames, the
    # last 2-3 tracked) ties a visual structure that converges in ~5 iterations to a few
    # samples; Levenberg-Marquardt's damping left it crawling onto them for 110-210 iterations
    # (2-4 s, holding a live frame), Powell's dogleg took 7-58 to the same cost (live replays of
    # the tests' late-tracker scene). Fully tracked start-ups keep Levenberg-Marquardt: dogleg
    # converged faster there too (a scope 5 mm from the plane: 13 iterations against 167, same
    # e_M), but a tracker garbled by w-first quaternions then ended at a point whose plane std
    # came out unbounded and the run was refused (Levenberg-Marquardt: std 0.039, taken, with
    # the tracker's disagreement warned of). The window and ba-emt keep Levenberg-Marquardt.
    startup_trust_region: str = "dogleg"
    seed: int = 0

    @classmethod
    def preset(cls, name: str, **overrides) -> SequentialOptions:
        if name not in PRESETS:
            raise ValueError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}")
        w, chi, k, per = PRESETS[name]
        return cls(window_size=w, num_new=chi, num_clusters=k, frames_per_cluster=per,
                   **overrides)


@dataclass
class FrameResult:
    """What :meth:`SequentialMosaicker.add_frame` returns for a frame (and ``finalized()`` /
    ``flush()`` once it is final).

    frame_id: 0-based count of accepted frames. timestamp: s, as given. homography: (3, 3)
    frame -> reference (frame 0's pixel grid; the first placed frame's when frame 0 is
    unplaced: SequentialMosaicker.reference_frame), NaN when unplaced. pose: (6,) cam_from_world
    [angle-axis rad, t mm] in the tracker's world (NaN when unknown). status: "placed" (final,
    with visual evidence), "prior-only" (final, from the tracker and motion priors alone: no
    registered pair), "dead-reckoned" (final, with no anchor at all: neither a tracker sample
    nor a registered pair to a frame that had one, e.g. black frames inside a tracker dropout;
    placed by the constant-velocity prior between the anchored frames around it when two follow
    within hold_unanchored_frames, else extrapolated, its error growing with the gap),
    "prior-only (solver failed)" (final, its window step could not be solved, Ceres FAILURE, even
    after dropping the tracker samples that made it fail: left at its starting pose, the tracker
    sample or the motion prediction), "provisional"
    (not final yet) or "unplaced: <why>". final: whether the
    estimate will not change. tracker_gated: its tracker sample was down-weighted by the
    window step (gate_chi2) or dropped as a glitch; tracker_dropped: dropped (never used).
    timings: seconds per stage (features, matching, window_solve, keyframe_selection). plane:
    (3,) pi = n / d of the step that made the frame final. motion_released: the motion gate
    (motion_gate_chi2) released its constant-velocity term (over frames k-2, k-1, k): the
    tracker samples, or the solve, said the camera left constant velocity there.
    """

    frame_id: int
    timestamp: float
    homography: np.ndarray  # (3, 3) frame -> reference (NaN when unplaced)
    pose: np.ndarray  # (6,) cam_from_world
    # "placed" | "prior-only" | "dead-reckoned" | "prior-only (solver failed)" | "provisional"
    # | "unplaced: ..."
    status: str
    final: bool
    # its tracker sample was down-weighted by the window step (gate_chi2) or dropped as a
    # glitch (tracker_max_speed_mm_s ...) before reaching the window; tracker_dropped tells which
    tracker_gated: bool = False
    timings: dict[str, float] = field(default_factory=dict)
    plane: np.ndarray | None = None  # (3,) pi of the step that made the frame final
    # its tracker sample was dropped as a glitch and never used (implies tracker_gated)
    tracker_dropped: bool = False
    # its C_p term was released by the motion gate (SequentialOptions.motion_gate_chi2)
    motion_released: bool = False


def canonical_rotation_vector(r: np.ndarray) -> np.ndarray:
    """The angle-axis vector of norm <= pi for the rotation r (any norm) stands for: the pose
    prior compares angle-axis components, so the same rotation must have one vector (e.g.
    -axis * (2 pi - theta), from a quaternion with w < 0, becomes axis * theta)."""
    theta = float(np.linalg.norm(r))
    if theta <= np.pi:
        return r
    wrapped = np.remainder(theta + np.pi, 2 * np.pi) - np.pi  # in [-pi, pi)
    return r * (wrapped / theta)


# tracker_pose's rotation vector: components up to 1e6 rad (any wrap of a real angle); beyond,
# refused. Degrees passed by mistake are within it, and not refused here: a probe turning faster
# than ~0.3 rad/s at 25 frames/s (its degrees then jump ~57x as far) has most of its samples
# dropped by the glitch filter, which the start-up refuses (_tracker_jumps) and, after it (the
# start-up took the right samples), live_solver_warnings reports at the session's end
# (tracker_warning, from the frame where it was first seen); a slower one's pass the filter, and
# only the window's gate (tracker_warning again) and, offline, the run's tracker_agreement
# check tell.
MAX_ROTATION_VECTOR_RAD = 1e6

# mm: the largest SequentialOptions.nominal_plane_distance_mm (1 km; endoscopes see their plane
# tens of mm away). The C++ core refuses a plane with |pi| <= 1e-12 (the plane at infinity):
# 1e12 mm jammed a start-up whose camera did not translate (review 51); 1e6 is far inside.
MAX_NOMINAL_PLANE_DISTANCE_MM = 1e6
PAIR_CONSISTENCY_MIN_PX = 10.0  # (SequentialOptions.pair_consistency_fraction's floor)


class SequentialMosaicker:
    """Frame-by-frame LBAVis+EMT. `camera` is an io.Camera with a camera_matrix."""

    def __init__(self, camera, options: SequentialOptions | None = None):
        self.options = o = options or SequentialOptions()
        if not isinstance(o, SequentialOptions):
            raise ValueError("options must be a SequentialOptions, got "
                             f"{type(options).__name__}")
        # Counts: integers within range, checked here (before: some failed only at the first
        # window step, on every frame after it, e.g. max_points_per_pair = 0).
        for name, low in (("window_size", 1), ("num_new", 1), ("frames_per_cluster", 1),
                          ("max_points_per_pair", 1), ("bootstrap_frames", 1),
                          ("num_clusters", 0), ("loop_pairs", 0), ("loop_min_separation", 0),
                          ("hold_prior_only_steps", 0), ("hold_unanchored_frames", 0),
                          ("history_steps", 0),
                          ("max_keyframe_blocks", 1), ("tracker_reanchor_after", 1),
                          ("startup_wait_frames", 1), ("max_iterations", 1),
                          ("startup_max_iterations", 1),
                          ("startup_trial_iterations", 1),
                          ("seed", 0)):
            value = getattr(o, name)
            if (not isinstance(value, numbers.Integral) or isinstance(value, bool | np.bool_)
                    or value < low):
                raise ValueError(f"SequentialOptions.{name} must be an integer >= {low}, got "
                                 f"{value!r}")
        if not (isinstance(o.gate_sigma_scale, numbers.Real) and 1.0 <= o.gate_sigma_scale
                < np.inf):
            raise ValueError("SequentialOptions.gate_sigma_scale must be finite and >= 1 (the "
                             f"factor on a gated sample's sigma), got {o.gate_sigma_scale!r}")
        for name in ("gate_chi2", "motion_gate_chi2"):
            value = getattr(o, name)
            if not (isinstance(value, numbers.Real) and 0.0 < value):
                raise ValueError(f"SequentialOptions.{name} must be > 0 (inf: no gate), got "
                                 f"{value!r}")
        value = o.pair_consistency_fraction
        if not (isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_)
                and 0 <= value < np.inf):
            raise ValueError("SequentialOptions.pair_consistency_fraction must be finite and "
                             f">= 0 (0 disables the check), got {value!r}")
        if not 0.0 <= o.startup_min_overlap <= 1.0:
            raise ValueError("SequentialOptions.startup_min_overlap must be a fraction in [0, 1], "
                             f"got {o.startup_min_overlap}")
        for name in ("max_timestamp_gap_s", "tracker_max_speed_mm_s", "tracker_max_angular_speed",
                     "tracker_jump_margin_mm", "tracker_jump_margin_rad", "tracker_max_gap_s",
                     "motion_max_gap_s"):
            value = getattr(o, name)
            if not (isinstance(value, numbers.Real) and value > 0):
                raise ValueError(f"SequentialOptions.{name} must be > 0, got {value!r}")
        # a distance, never "off": inf (or 1e12) gave a start-up without translation pi = 0 (or
        # |pi| <= 1e-12), which SetPlane refuses; the call was rolled back and every later
        # add_frame and flush raised the same error, naming no option (review 51)
        value = o.nominal_plane_distance_mm
        if not (isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_)
                and 0 < value <= MAX_NOMINAL_PLANE_DISTANCE_MM):
            raise ValueError("SequentialOptions.nominal_plane_distance_mm must be finite, > 0 "
                             f"and <= {MAX_NOMINAL_PLANE_DISTANCE_MM:g} (mm), got {value!r}")
        for name in ("plane_max_relative_std", "startup_max_plane_std"):
            value = getattr(o, name)
            if not (isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_)
                    and 0 <= value < np.inf):
                raise ValueError(f"SequentialOptions.{name} must be finite and >= 0 (0 disables "
                                 f"the check), got {value!r}")
        if o.window_size < o.num_new + 2:
            # C_p (Eq. 27) links each new camera to its two predecessors, which only the
            # window's W - chi_e fixed cameras keep from being forgotten
            raise ValueError("SequentialOptions.window_size must be >= num_new + 2 (the "
                             "constant-velocity prior links each new camera to its two "
                             "predecessors, which the window holds fixed), got window_size "
                             f"{o.window_size}, num_new {o.num_new}")
        if o.frames_per_cluster < o.window_size - 1:
            # a keyframe block shorter than the fixed part of the window can be evicted while
            # its frames are still in the window (every preset has frames_per_cluster >= W)
            raise ValueError("SequentialOptions.frames_per_cluster must be >= window_size - 1, "
                             f"got {o.frames_per_cluster} < {o.window_size} - 1")
        if o.startup_trust_region not in ("dogleg", "levenberg_marquardt"):
            raise ValueError("SequentialOptions.startup_trust_region must be 'dogleg' or "
                             f"'levenberg_marquardt', got {o.startup_trust_region!r}")
        if o.startup_wait_frames < o.bootstrap_frames:
            raise ValueError("SequentialOptions.startup_wait_frames must be >= bootstrap_frames, "
                             f"got {o.startup_wait_frames} < {o.bootstrap_frames}")
        self._camera = camera
        self.K = camera.require_camera_matrix("lba-emt")
        self.size = (camera.width, camera.height)
        self._outline = self._frame_outline(camera)
        self._fov_radius = camera.fov_mask_radius
        # this frame's own footprint in its pixels (start-up pair selection)
        self._own_footprint = footprint_polygons(np.eye(3)[None], *self.size,
                                                 self._fov_radius)[0]
        check_sigma_v(o.sigma_v_px, "SequentialOptions.sigma_v_px")
        # the visual cost's sigma_v now (see sigma_v_px), and how it was decided
        self._sigma_v = starting_sigma_v(o.sigma_v_px)
        self.visual_sigma: dict = given_sigma_v_report(o.sigma_v_px)
        costs = _core.BundleAdjusterOptions(
            sigma_v_px=self._sigma_v, loss=o.loss, linear_solver=o.linear_solver,
            max_iterations=o.max_iterations, function_tolerance=FUNCTION_TOLERANCE, num_threads=1,
            motion_gate_chi2=o.motion_gate_chi2)
        if o.motion_sigma is not None:
            costs.motion_sigma = np.asarray(o.motion_sigma, np.float64)
        if o.emt_sigma is not None:
            costs.emt_sigma = np.asarray(check_emt_sigma(o.emt_sigma,
                                                         "SequentialOptions.emt_sigma"))
        self._costs = costs
        self._window_options = _core.SlidingWindowOptions(
            window_size=o.window_size, num_new=o.num_new, costs=costs)
        self._window_options.plane_max_relative_std = o.plane_max_relative_std
        self.window = _core.SlidingWindow(self.K, self._window_options)
        # What the C++ window holds, to rebuild it when a call fails half-way (_transaction):
        # frame id -> (pose or None while pending, tracker sample, sigma scale, fixed, C_p
        # timing), the pairs by (frame_l, frame_m) -> (points_l, points_m), the plane.
        self._mirror_frames: dict[int, tuple] = {}
        self._mirror_pairs: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        # frame id -> the keys of its pairs in _mirror_pairs (tuples, replaced, never mutated:
        # _save copies shallowly), so that forgetting frames touches only their pairs
        self._mirror_pair_index: dict[int, tuple[tuple[int, int], ...]] = {}
        self._mirror_plane: np.ndarray | None = None
        # the transfer residuals of the pairs the window has forgotten, at their final poses
        # (visual_agreement: the keypoints' noise, for sigma_v_px)
        self._forgotten_residuals = TransferResiduals()
        self._window_touched = False
        self._lock = getattr(self, "_lock", None) or threading.Lock()  # reset() keeps it
        self._broken: str | None = None  # why the mosaicker is unusable (failed restoration)
        # matching threads, made on first use; reset() keeps them
        self._pool = getattr(self, "_pool", None)
        # keypoints in undistorted pixels (camera.yaml's lens distortion removed)
        self.extractor = FeatureExtractor(o.features, camera.fov_mask(), camera.undistortion())
        self.keyframes = KeyframeIndex(o.frames_per_cluster, max_blocks=o.max_keyframe_blocks,
                                       cell_size_px=0.5 * max(self.size),
                                       rng=np.random.default_rng(o.seed))
        self.rng = np.random.default_rng(o.seed)
        self._recent: deque = deque(maxlen=max(o.window_size - 1, 1))  # (id, Features)
        self._pending: list[dict] = []
        self._finalized: list[FrameResult] = []
        self._boot_feats: list = []  # bootstrap: features and pairs of the first frames
        self._boot_matches: list = []
        self._startup_left_out: list = []  # (_bootstrap: pairs its try left out)
        self._loop_feats: dict = {}  # one frame per retained keyframe block: its features
        self._loop_centroids: dict = {}
        self._loop_G: dict = {}  # their reference homographies (guided matching predictions)
        # Guided matching (MatchOptions.guided_radius_px): the registered pairs of the recent
        # frames, id -> {older id: H (older -> id pixels)}, and the reference homographies of
        # the recent frames already final, id -> G.
        self._pair_H: dict[int, dict[int, np.ndarray]] = {}
        self._recent_G: dict[int, np.ndarray] = {}
        self._loop_radius = 0.6 * float(np.hypot(*self.size))  # centroid distance for overlap
        # last two estimated poses and their frames' times, for prediction: id -> (pose, time)
        self._poses: dict[int, tuple[np.ndarray, float]] = {}
        # Frame times: the last three frames given (the constant-velocity prior's timing,
        # motion.motion_timing) and the recent intervals, whose median is the nominal spacing.
        self._times: dict[int, float] = {}
        self._intervals: deque = deque(maxlen=200)
        # The tracker's motion check (_judge_motion_again): the last SAMPLES_KEPT frames'
        # samples used (id -> pose) and the recent departures from constant velocity.
        self._samples: dict[int, np.ndarray] = {}
        self._motion_history: deque = deque(maxlen=200)
        # Of the last TRACKER_WARNING_FRAMES final frames given a tracker sample, (frame,
        # whether it was gated or dropped); the first stretch of final frames where most were
        # (_note_tracker_verdict), None while none was: live_solver_warnings' tracker warning.
        self._tracker_verdicts: deque = deque(maxlen=TRACKER_WARNING_FRAMES)
        self._tracker_episode: TrackerEpisode | None = None
        self._reference_pose: np.ndarray | None = None
        self._reference_id: int | None = None  # the frame whose pose it is
        self._plane: np.ndarray | None = None
        # Provisional placements in the start-up, until its adjustment gives self._plane: start-up
        # frame -> reference homographies chained through each frame's best registered pair
        # (PairVis over <= bootstrap_frames frames), else from the tracker poses and the plane of
        # the start-up pairs registered so far.
        self._startup_G: dict[int, np.ndarray] = {}
        self._startup_plane: np.ndarray | None = None
        self._startup_problem: str | None = None  # why the last start-up adjustment was refused
        self._startup_refused = (0, 0, 0)  # its registered pairs with tracker poses, frames
        # Frames finalised without an anchor: no tracker sample used and no registered pair
        # leading to an anchored camera (e.g. black frames in a tracker dropout, and the visual
        # chain after them). Kept while the window or the keyframe reservoir may hold them;
        # they never become keyframes or loop frames, and a tracked frame is not tied to them.
        self._unanchored: set[int] = set()
        self._next_id = 0
        self._last_timestamp = -np.inf
        self._trusted: tuple | None = None  # last tracker sample kept: (time, centre, R)
        self._implausible_run = 0  # tracker samples dropped in a row (re-anchor after 3)
        # The world the window works in (estimation/world.py): decided by the first tracker
        # sample, rotated when that camera is near a rotation of pi in the tracker's frame and
        # centred on it when it is far from the tracker's origin.
        self._world: WorldAlignment | None = None
        # C++ summaries of the last history_steps window steps (each frame's plane is in its
        # FrameResult).
        self.step_summaries: deque = deque(maxlen=o.history_steps)
        # the last window step's summary, kept whatever history_steps (0 keeps none above)
        self.last_step_summary = None
        # the last window step's solve time (s): the C++ step_time_s of each of its solves
        # summed, the first and any redo (a gated sample's, a failed step's recovery); its
        # summary has the last one's only
        self.last_step_solve_s = 0.0
        self._step_solve_s = 0.0  # (the step's so far)
        self.num_steps = 0
        # Frames handed out unplaced because the plane passes through their camera centre:
        # they never join the keyframe reservoir, so they are forgotten by the C++ window once
        # neither the window nor the recent frames' matching can use them (_forget_orphans).
        self._orphans: set[int] = set()
        self.bootstrap_summary: dict | None = None  # the start-up BA+EMT solve, once it ran
        # Pair registrations (window / start-up and spatial loop pairs): attempted, registered,
        # correspondences of the registered ones.
        self.pair_counts = {"attempted": 0, "registered": 0, "correspondences": 0,
                            "loop_attempted": 0, "loop_registered": 0,
                            "guided": 0, "guided_fallback": 0, "inconsistent": 0}

    @property
    def frame_count(self) -> int:
        """Frames accepted since the last :meth:`reset`: the id the next frame will get."""
        return self._next_id

    @property
    def reference_frame(self) -> int | None:
        """The id of the frame whose pixel grid the final homographies map to: frame 0, or
        when frame 0 was handed out unplaced (e.g. a tracker that came on late: the start-up
        cannot wait for it beyond its bound) the first frame placed; None before a frame is
        final and placed."""
        return self._reference_id

    @property
    def plane(self) -> np.ndarray | None:
        """The current plane pi = n / d in the tracker's world (None before the start-up)."""
        if self._plane is None:
            return None
        return plane_from_aligned(self._plane, self._world)

    @staticmethod
    def _frame_outline(camera) -> np.ndarray:
        w, h = camera.width, camera.height
        if camera.fov_mask_radius:
            a = np.linspace(0, 2 * np.pi, 16, endpoint=False)
            r = camera.fov_mask_radius
            return np.stack([(w - 1) / 2 + r * np.cos(a), (h - 1) / 2 + r * np.sin(a)], axis=1)
        return np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float64)

    # ----------------------------------------------------------------------------------------
    def add_frame(self, image: np.ndarray, timestamp: float,
                  tracker_pose: np.ndarray | None = None) -> FrameResult:
        """Adds the next frame. tracker_pose: (6,) cam_from_world from the EM tracker after
        hand-eye (None when there is no valid sample). Returns this frame's result, final if
        its step ran now, else provisional; `finalized()` hands out the frames made final.

        Raises TypeError / ValueError, naming the frame id and the argument, for a call it
        refuses (see the module docstring for the input contract); the state is then unchanged.
        A frame it keeps never raises: while the start-up cannot initialise the plane yet (no
        registered pair with tracker poses), it is returned with an "unplaced: ..." status."""
        with self._exclusive("add_frame"):
            self._finalized = []  # a refused or failed call makes no frame final
            k = self._next_id
            image = self._check_image(k, image)
            timestamp = self._check_timestamp(k, timestamp)
            tracker_pose = self._check_tracker_pose(k, tracker_pose)
            return self._transaction(self._add_frame, k, image, timestamp, tracker_pose)

    def finalized(self) -> list[FrameResult]:
        """Frames made final by the last add_frame / flush call (in order; none after a call
        that raised)."""
        return list(self._finalized)

    def flush(self) -> list[FrameResult]:
        """Estimates any pending frames (end of sequence) and returns their final results.
        Raises ValueError (state unchanged) if the start-up frames still have no registered
        pair with tracker poses to initialise the plane."""
        with self._exclusive("flush"):
            self._finalized = []
            return self._transaction(self._flush)

    def reset(self) -> None:
        """Forgets everything: a new mosaic with the same camera and options (also the way out
        of the unusable state that a failed restoration leaves, see the module docstring)."""
        with self._exclusive("reset", check_usable=False):
            lock = self._lock
            self.__init__(self._camera, self.options)
            self._lock = lock

    # ------------------------------------------------------------- call guards and rollback
    @contextmanager
    def _exclusive(self, what: str, check_usable: bool = True):
        with exclusive_call(self._lock, "SequentialMosaicker", what):
            if check_usable and self._broken is not None:
                raise RuntimeError(f"SequentialMosaicker is unusable: {self._broken}; call "
                                   "reset() to start a new mosaic")
            yield

    def _check_image(self, k: int, image) -> np.ndarray:
        if not isinstance(image, np.ndarray):
            raise TypeError(f"frame {k}: image must be a numpy array (H, W) or (H, W, 3) uint8, "
                            f"got {type(image).__name__}")
        if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (3, 4))):
            raise ValueError(f"frame {k}: image shape {image.shape} is not (H, W) gray, "
                             "(H, W, 3) BGR or (H, W, 4) BGRA")
        if image.dtype != np.uint8:
            raise ValueError(f"frame {k}: image dtype {image.dtype} is not supported, expected "
                             "uint8 (8-bit gray or BGR); scale and convert the image first, "
                             "with one scale for the whole sequence")
        if image.shape[1::-1] != self.size:
            raise ValueError(f"frame {k}: image size {image.shape[1]}x{image.shape[0]} differs "
                             f"from the camera's {self.size[0]}x{self.size[1]}")
        return image

    def _check_timestamp(self, k: int, timestamp) -> float:
        return check_stream_timestamp(k, timestamp, self._last_timestamp,
                                      max_gap_s=self.options.max_timestamp_gap_s,
                                      gap_name="max_timestamp_gap_s")

    def _check_tracker_pose(self, k: int, tracker_pose) -> np.ndarray | None:
        if tracker_pose is None:
            return None
        pose = np.asarray(tracker_pose)
        if pose.dtype.kind not in "iuf":
            raise TypeError(f"frame {k}: tracker_pose must be 6 real numbers [r, t] "
                            f"(cam_from_world), got dtype {pose.dtype}: {tracker_pose!r}")
        pose = pose.astype(np.float64)  # a copy: the caller's array is never kept
        if pose.shape == (6,) and np.isnan(pose).all():
            return None  # no sample, as read_dataset writes a tracker gap (Dataset.cam_from_world)
        if pose.shape != (6,):
            hint = ("; a (4, 4) matrix is the pose's matrix form: give its [angle-axis r, t] "
                    "(io.camera_pose_from_sample converts a tracker sample)"
                    if pose.shape == (4, 4) else "")
            raise ValueError(f"frame {k}: tracker_pose must be 6 finite values [r, t] "
                             f"(cam_from_world) of shape (6,), got shape {pose.shape}{hint}")
        if not np.isfinite(pose).all():
            raise ValueError(f"frame {k}: tracker_pose must be 6 finite values "
                             f"[r, t] (cam_from_world), got {tracker_pose!r}")
        # |t| is the camera's distance from the tracker origin (t = -R c); the max first, so
        # that the norm of a huge vector cannot overflow
        if (np.abs(pose[3:]).max() > MAX_TRANSLATION_MM
                or np.linalg.norm(pose[3:]) > MAX_TRANSLATION_MM):
            raise ValueError(f"frame {k}: tracker_pose translation {pose[3:].tolist()} mm puts "
                             "the camera beyond the dataset reader's bound of "
                             f"{MAX_TRANSLATION_MM:g} mm (1 km) from the tracker origin, not "
                             "physical")
        # a rotation vector's norm is its angle: beyond ~1e150 it overflows (then NaN inside
        # the window); any real angle is far below this bound before its wrap to [-pi, pi)
        if np.abs(pose[:3]).max() > MAX_ROTATION_VECTOR_RAD:
            raise ValueError(f"frame {k}: tracker_pose rotation vector {pose[:3].tolist()} has "
                             f"a component beyond {MAX_ROTATION_VECTOR_RAD:g} rad: not an "
                             "angle-axis rotation (degrees? a quaternion or matrix?)")
        pose[:3] = canonical_rotation_vector(pose[:3])
        return pose

    def _transaction(self, call, *args):
        """Runs call(*args); if it raises (anything, KeyboardInterrupt too), restores the state
        from before it and re-raises."""
        saved = self._save()
        self._window_touched = False
        try:
            return call(*args)
        except BaseException as exc:
            try:
                self._restore(saved)
            except BaseException as failure:
                self._broken = (f"restoring the state after {type(exc).__name__} ({exc}) failed "
                                f"with {type(failure).__name__} ({failure})")
                raise RuntimeError(f"SequentialMosaicker is unusable: {self._broken}; call "
                                   "reset() to start a new mosaic") from exc
            raise

    _SAVED = ("_next_id", "_last_timestamp", "_trusted", "_reference_pose", "_reference_id",
              "_plane",
              "_startup_G", "_startup_plane", "_startup_problem", "_startup_refused",
              "num_steps", "_orphans", "_finalized", "_boot_feats",
              "_boot_matches", "_startup_left_out", "_loop_feats",
              "_loop_centroids", "_loop_G", "_pair_H", "_recent_G", "_poses", "pair_counts",
              "_mirror_frames", "_mirror_pairs", "_mirror_pair_index", "_mirror_plane",
              "_forgotten_residuals", "_sigma_v", "visual_sigma",
              "_implausible_run",
              "_world", "_times", "_intervals", "_unanchored", "bootstrap_summary",
              "_samples", "_motion_history", "_tracker_verdicts", "_tracker_episode")

    def _save(self) -> dict:
        """What a call may change, copied (shallowly: the values it replaces, never mutates)."""
        saved = {name: copy.copy(getattr(self, name)) for name in self._SAVED}
        saved["_recent"] = deque(self._recent, maxlen=self._recent.maxlen)
        saved["step_summaries"] = deque(self.step_summaries, maxlen=self.step_summaries.maxlen)
        saved["last_step_summary"] = self.last_step_summary  # (read-only: never mutated)
        saved["last_step_solve_s"] = self.last_step_solve_s
        saved["_pending"] = [dict(p, timings=dict(p["timings"])) for p in self._pending]
        saved["rng"] = self.rng.bit_generator.state
        saved["keyframes"] = self.keyframes.snapshot()
        return saved

    def _restore(self, saved: dict) -> None:
        self.rng.bit_generator.state = saved.pop("rng")
        self.keyframes.restore(saved.pop("keyframes"))
        for name, value in saved.items():
            setattr(self, name, value)
        if self._window_touched:
            self._rebuild_window()

    def _rebuild_window(self) -> None:
        """A new C++ window holding what the mirror says the old one held."""
        window = _core.SlidingWindow(self.K, self._window_options)
        if self._sigma_v != self._window_options.costs.sigma_v_px:  # (measured by the start-up)
            window.set_sigma_v(self._sigma_v)
        if self._mirror_plane is not None:
            window.set_plane(self._mirror_plane)
        for k, (pose, emt, scale, fixed, timing) in self._mirror_frames.items():
            window.add_frame(k, pose, emt, fixed, *timing)
            if scale != 1.0:
                window.set_emt_sigma_scale(k, scale)
        for (l, m), (pl, pm) in self._mirror_pairs.items():
            window.add_pair(l, m, pl, pm)
        self.window = window
        self._window_touched = False

    # C++ window updates go through these, which keep the mirror (for _rebuild_window).
    def _win_add_frame(self, k, initial, emt, fixed=False, timing=(1.0, 1.0)) -> None:
        self._window_touched = True
        self.window.add_frame(k, initial, emt, fixed, *timing)
        self._mirror_frames[k] = (initial, emt, 1.0, fixed, timing)

    def _win_add_pair(self, l, m, pl, pm) -> None:
        self._window_touched = True
        self.window.add_pair(l, m, pl, pm)
        key = (l, m)
        if key not in self._mirror_pairs:
            index = self._mirror_pair_index
            for k in key:
                index[k] = index.get(k, ()) + (key,)
        self._mirror_pairs[key] = (pl, pm)

    def _win_set_plane(self, plane) -> None:
        self._window_touched = True
        self.window.set_plane(plane)
        self._mirror_plane = np.array(plane, np.float64)

    def _win_set_sigma_v(self, sigma_v_px: float) -> None:
        self._window_touched = True
        self.window.set_sigma_v(sigma_v_px)
        self._sigma_v = sigma_v_px

    def _win_set_scale(self, k, scale) -> None:
        self._window_touched = True
        self.window.set_emt_sigma_scale(k, scale)
        initial, emt, _, fixed, timing = self._mirror_frames[k]
        self._mirror_frames[k] = (initial, emt, scale, fixed, timing)

    def _win_drop_sample(self, k) -> None:
        self._window_touched = True
        self.window.drop_emt_measurement(k)
        initial, _, _, fixed, timing = self._mirror_frames[k]
        self._mirror_frames[k] = (initial, None, 1.0, fixed, timing)

    def _win_set_timing(self, k, timing) -> None:
        self._window_touched = True
        self.window.set_motion_timing(k, *timing)
        initial, emt, scale, fixed, _ = self._mirror_frames[k]
        self._mirror_frames[k] = (initial, emt, scale, fixed, timing)

    def _win_solved(self, ids, summary_call, *args):
        """window.step / redo; afterwards the solved frames are fixed at their new poses."""
        self._window_touched = True
        summary = summary_call(*args)
        self._step_solve_s += summary.step_time_s
        self._mark_motion_gated(ids, summary.motion_released_ids)
        for k in ids:
            _, emt, scale, _, timing = self._mirror_frames[k]
            self._mirror_frames[k] = (np.asarray(self.window.pose(k)), emt, scale, True, timing)
        self._mirror_plane = np.asarray(self.window.plane())
        return summary

    def _mark_motion_gated(self, solved, released) -> None:
        """Of the pending frames `solved`, those whose C_p term the solve left out (the C++
        motion gate): the last solve of a frame decides its flag."""
        solved, released = set(solved), set(released)
        for p in self._pending:
            if p["id"] in solved:
                p["motion_gated"] = p["id"] in released

    def _win_forget(self, ids) -> None:
        self._window_touched = True
        self.window.forget(ids)
        gone = set(ids)
        index = self._mirror_pair_index
        # (through the index: rebuilding _mirror_pairs without the forgotten frames' pairs cost
        # 0.49 ms an eviction at ~5000 pairs, every 5 frames once the window is full; review)
        # (each pair once: the keyframe index forgets a block of consecutive frames, whose
        # pairs among themselves appear under both frames; 8940 counted for 8340 pairs. add()
        # replaces the accumulator's arrays, so _save's shallow copy stays the snapshot)
        for key in {key for k in gone for key in index.get(k, ()) if key in self._mirror_pairs}:
            self._add_residuals(self._forgotten_residuals, key)
        for k in gone:
            self._mirror_frames.pop(k, None)
            for key in index.pop(k, ()):
                self._mirror_pairs.pop(key, None)
                other = key[0] if key[1] == k else key[1]
                if other in index:
                    index[other] = tuple(x for x in index[other] if x != key)

    def _add_residuals(self, residuals: TransferResiduals, key: tuple[int, int]) -> None:
        """The pair `key`'s transfer residuals into `residuals` when both its frames are fixed
        (solved; a pending frame sits at its starting pose)."""
        frames = self._mirror_frames
        if self._mirror_plane is None or not all(k in frames and frames[k][3] for k in key):
            return
        pl, pm = self._mirror_pairs[key]
        residuals.add(frames[key[0]][0], frames[key[1]][0], self._mirror_plane, pl, pm, self.K)

    @property
    def sigma_v_px(self) -> float:
        """The visual cost's sigma_v (px): the given one, or measured by the start-up ("auto";
        SIGMA_V_START_PX until then)."""
        return self._sigma_v

    def visual_agreement(self, *, source: str = "the stream") -> dict:
        """consistency.visual_agreement of the registered pairs' transfer residuals (Eq. 13)
        at their final poses: those the window forgot, and those it holds between solved
        frames; each pair counted once. Its "robust_std_px" measures the keypoints' noise
        (SequentialOptions.sigma_v_px); a warning when it is over MAX_NOISE_RATIO x the sigma_v
        the window used."""
        residuals = self._forgotten_residuals.copy()
        for key in self._mirror_pairs:
            self._add_residuals(residuals, key)
        return visual_agreement(residuals, self._sigma_v, source=source,
                                knob="--visual-sigma")

    # ------------------------------------------------------------------------- the frame step
    def _plausible(self, timestamp: float, pose: np.ndarray) -> str:
        """Whether a tracker sample is within the speed bounds of the last trusted one: "ok",
        "drop", or "reanchor" (the tracker_reanchor_after-th disagreeing sample in a row,
        which becomes the new reference)."""
        R = _core.rotation_from_angle_axis(pose[:3])
        centre = -R.T @ pose[3:]
        if self._trusted is not None:
            o = self.options
            t0, centre0, R0 = self._trusted
            # a long gap allows at most tracker_max_gap_s of motion, so that a glitch after a
            # dropout is still caught
            dt = min(timestamp - t0, o.tracker_max_gap_s)
            moved = float(np.linalg.norm(centre - centre0))
            turned = float(np.arccos(np.clip((np.trace(R0.T @ R) - 1) / 2, -1.0, 1.0)))
            if (moved > o.tracker_max_speed_mm_s * dt + o.tracker_jump_margin_mm
                    or turned > o.tracker_max_angular_speed * dt + o.tracker_jump_margin_rad):
                self._implausible_run += 1
                if self._implausible_run < self.options.tracker_reanchor_after:
                    return "drop"
                # that many samples in a row disagree with the reference: the reference was the
                # glitch (e.g. a bad first sample) or the tracker moved for good; start again
                self._implausible_run = 0
                self._trusted = (timestamp, centre, R)
                return "reanchor"
        self._implausible_run = 0
        self._trusted = (timestamp, centre, R)
        return "ok"

    def _reanchor_startup(self) -> None:
        """During the start-up (nothing in the window yet): the samples dropped in the run that
        made the tracker re-anchor agree with the new reference and are restored; those the
        old reference had accepted (e.g. a bad first sample) are dropped instead. In the
        start-up every pending sample still kept was accepted by the current reference (a
        re-anchoring drops the others), so those are the old reference's."""
        old = {p["id"] for p in self._pending if p["tracker"] is not None}
        self._startup_refused = (0, 0, 0)  # (its pairs counted with the old samples)
        pending = []
        for p in self._pending:
            if p["id"] in old and p["tracker"] is not None:
                p = dict(p, tracker=None, dropped=True)
            elif p["dropped"] and p.get("sample") is not None and p["id"] > max(old, default=-1):
                p = dict(p, tracker=p["sample"], dropped=False)
            pending.append(dict(p, departure=None))  # (from the old reference's samples)
        self._pending = pending
        self._samples = {}  # the old reference's: no motion to judge against the new one

    def _realign_startup(self, sample: np.ndarray, timestamp: float) -> np.ndarray:
        """During the start-up, after a re-anchoring on `sample` (aligned in the current
        world): the world decided again from it, the pending samples and the reference moved
        into it; returns `sample` in the new world."""
        raw = poses_from_aligned(sample, self._world)
        world = world_alignment(raw)
        if world is None and self._world is None:
            return sample
        self._move_startup(world)
        sample = poses_to_aligned(raw, world)
        R = _core.rotation_from_angle_axis(sample[:3])
        self._trusted = (timestamp, -R.T @ sample[3:], R)
        return sample

    def _move_startup(self, world: WorldAlignment | None) -> None:
        """During the start-up: its samples (pending, the glitch filter's reference and the
        recent ones) moved from the current world into `world`, which becomes the current one.
        The provisional plane and the samples' departures, of the old world, are dropped."""

        def move(pose):
            return None if pose is None else poses_to_aligned(
                poses_from_aligned(pose, self._world), world)

        self._pending = [dict(p, tracker=move(p["tracker"]), sample=move(p.get("sample")),
                              departure=None)  # (from samples in the old world)
                         for p in self._pending]
        self._samples = {i: move(z) for i, z in self._samples.items()}
        if self._trusted is not None:
            t0, centre, R = self._trusted
            pose = move(np.concatenate([_core.angle_axis_from_rotation(R), -R @ centre]))
            R = _core.rotation_from_angle_axis(pose[:3])
            self._trusted = (t0, -R.T @ pose[3:], R)
        self._world, self._startup_plane = world, None

    def _recentre_near_plane(self, usable: list) -> bool:
        """Before the start-up adjusts: when the plane of its registered pairs with tracker
        poses (`usable`) lies near the world's origin (world.origin_near_plane: pi = n / d is
        then ill-conditioned), the world becomes tracked_world's of the start-up's tracked
        cameras, centred on one (as ba-emt's), and the start-up's samples move into it, their
        departures from constant velocity judged again there; True then. The world was
        decided by the first tracker sample, before any plane (module world.py). The plane is
        estimated in that centred world, where it is well-conditioned whatever the tracker's
        origin (in the tracker's a plane through its origin has no pi)."""
        _, table = self._pending_tracker_poses()
        raw = poses_from_aligned(table, self._world)
        centred = tracked_world(raw, recentre=True)
        if same_world(centred, self._world):
            return False
        aligned = poses_to_aligned(raw, centred)
        try:
            plane = estimate_plane(self._renumbered(usable), aligned, self.K)
        except ValueError:  # no pair has a baseline: the plane the start-up will assume
            plane = plane_facing(aligned[np.isfinite(aligned).all(axis=1)],
                                 self.options.nominal_plane_distance_mm)
        with np.errstate(divide="ignore", invalid="ignore"):  # (not finite: through it)
            here = plane_to_aligned(plane_from_aligned(plane, centred), self._world)
        if not origin_near_plane(table, here):
            return False
        self._move_startup(centred)
        samples = {p["id"]: p["tracker"] for p in self._pending if p["tracker"] is not None}
        times = {p["id"]: p["timestamp"] for p in self._pending}
        for p in self._pending:  # (new dicts, from _move_startup)
            k = p["id"]
            if k in samples and k - 1 in samples and k - 2 in samples:
                timing = self._timing(k, times)
                if np.isfinite(timing[1]):
                    p["departure"] = tracker_motion_departure(
                        samples[k - 2], samples[k - 1], samples[k], self._costs.motion_sigma,
                        self._costs.emt_sigma, timing)
        return True

    def _add_frame(self, k, image, timestamp, tracker_pose) -> FrameResult:
        self._next_id += 1
        if k - 1 in self._times:
            self._intervals.append(timestamp - self._times[k - 1])
        self._times = {i: t for i, t in self._times.items()
                       if i >= k - SAMPLES_KEPT} | {k: timestamp}
        self._last_timestamp = timestamp
        if tracker_pose is not None:
            if self._trusted is None:  # the first tracker sample decides the world
                self._world = world_alignment(tracker_pose)
            tracker_pose = poses_to_aligned(tracker_pose, self._world)
        verdict = None if tracker_pose is None else self._plausible(timestamp, tracker_pose)
        dropped = verdict == "drop"
        sample = tracker_pose  # kept with a dropped frame: a re-anchoring may restore it
        if dropped:
            tracker_pose = None
        if verdict == "reanchor" and self._plane is None:
            self._reanchor_startup()
            # the world was decided by the old reference (e.g. a bad first sample 10 m off,
            # which made a far origin of its own): decided again by the new one
            tracker_pose = sample = self._realign_startup(sample, timestamp)
        departure = self._tracker_departure(k, tracker_pose)
        timings: dict[str, float] = {}

        t0 = time.perf_counter()
        feats = self.extractor.extract(image, k)
        timings["features"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        if self._plane is None:  # start-up: the window and the older frames that overlap
            against = self._startup_candidates(k, tracker_pose)
            matches = self._match(feats, against)
        else:
            matches = self._match_recent(feats, [f for _, f in self._recent])
        self._recent.append((k, feats))
        timings["matching"] = time.perf_counter() - t0
        ok = [m for m in matches if m.ok]
        known = None  # (the recent pairs; in the start-up, all of its pairs)
        if self._plane is None:
            known = {}
            for m in self._boot_matches:
                known.setdefault(m.frame_l, {})[m.frame_m] = m.H_lm
        outliers = self._inconsistent_pairs(ok, known)
        if outliers:  # (before any frame counts them as its visual evidence)
            ok = [m for m in ok if m.frame_m not in outliers]
            self.pair_counts["inconsistent"] += len(outliers)
        recent = {i for i, _ in self._recent}
        self._pair_H = {i: v for i, v in self._pair_H.items() if i in recent} | {
            k: {m.frame_m: m.H_lm for m in ok}}
        self._recent_G = {i: G for i, G in self._recent_G.items() if i in recent}
        self._count_pairs(matches, ok)
        self._pending = [dict(p, visual=True) if any(m.frame_m == p["id"] for m in ok) else p
                         for p in self._pending]  # a registered pair: evidence for both frames
        self._pending.append({"id": k, "timestamp": timestamp, "tracker": tracker_pose,
                              "visual": bool(ok), "timings": timings, "features": feats,
                              "held": 0, "dropped": dropped, "sample": sample,
                              # dropped by the glitch filter itself, as a jump from the sample
                              # before (a re-anchoring's drops and restorings leave it as it is)
                              "jump": dropped,
                              "departure": departure, "motion_break": False})
        self._finalized = []
        waiting = False
        if self._plane is None:  # bootstrap: keep everything until the initial adjustment
            self._boot_feats.append(feats)
            self._boot_matches += ok
            self._chain_startup(k, ok)
            if len(self._pending) >= self.options.bootstrap_frames:
                waiting = not (self._startup_due() and self._bootstrap())
                if waiting:
                    self._restore_startup_pairs()
            if waiting:
                self._drop_oldest_startup_frames()
        else:
            t0 = time.perf_counter()
            loop_matches = self._match_loops(k, feats, tracker_pose, ok)
            loops = [m for m in loop_matches if m.ok]
            self._count_pairs(loop_matches, loops, "loop_")
            # After a loss (frames placed with no anchor, see _unanchored), a frame with an
            # anchor of its own (its tracker sample, or a registered pair to an anchored frame)
            # is not tied to the lost frames by pairs or the constant-velocity term: they would
            # pull it off. A frame without one keeps chaining through them.
            if departure is not None:  # (the motion checks scale by these)
                self._motion_history.append(departure)
            unbroken = self._timing(k)
            lost = self._lost_ids()
            anchored = tracker_pose is not None or any(m.frame_m not in lost for m in ok + loops)
            # (lost frames still pending are free: tied to this anchor, they are placed by it)
            if anchored and self._unanchored:
                ok = [m for m in ok if m.frame_m not in self._unanchored]
                loops = [m for m in loops if m.frame_m not in self._unanchored]
                if self._unanchored & {k - 1, k - 2}:  # (released by motion_timing stays so)
                    unbroken = (unbroken[0], max(unbroken[1], RELEASED_MOTION_SIGMA_SCALE))
            # C_p as timed; the motion check decides before the frame's step
            self._pending[-1]["cv_timing"] = unbroken
            pairs = [(m.frame_l, m.frame_m, *self._subsample(m)) for m in ok + loops]
            timings["matching"] += time.perf_counter() - t0
            self._win_add_frame(k, None, tracker_pose, timing=unbroken)
            for pair in pairs:
                self._win_add_pair(*pair)
            self._pending[-1]["visual"] = bool(ok or loops)
            self._pending[-1]["links"] = {m.frame_m for m in ok + loops}
            self._pending[-1]["anchored"] = anchored
            for p in self._pending[:-1]:
                if any(m.frame_m == p["id"] for m in ok):
                    p["links"] = p.get("links", set()) | {k}
            if sum(p["held"] == 0 for p in self._pending) >= self.options.num_new:
                self._step()
        for r in self._finalized:
            if r.frame_id == k:
                return r
        result = self._provisional(k, timestamp, tracker_pose, timings)
        result.tracker_gated = result.tracker_dropped = dropped
        if waiting:
            result.status = ("unplaced: " + (
                f"the start-up waits: {self._startup_problem}" if self._startup_problem else
                "waiting for a registered pair with tracker poses to initialise the plane"))
        return result

    def _drop_oldest_startup_frames(self) -> None:
        """While the start-up waits for a registered pair with tracker poses (e.g. the tracker
        switched on late), keep at most startup_wait_frames frames: the oldest are handed out
        as final and unplaced, with their features and pairs, so that the per-frame cost
        (matching against the kept frames) and the memory stay bounded. The first frame placed
        later becomes the reference."""
        excess = len(self._pending) - self.options.startup_wait_frames
        if excess <= 0:
            return
        gone, self._pending = self._pending[:excess], self._pending[excess:]
        ids = {p["id"] for p in gone}
        self._boot_feats = [f for f in self._boot_feats if f.frame_id not in ids]
        self._boot_matches = [m for m in self._boot_matches
                              if m.frame_l not in ids and m.frame_m not in ids]
        # (the chain's homographies too: they grew by one a frame while no tracker came)
        self._startup_G = {i: G for i, G in self._startup_G.items() if i not in ids}
        status = (f"unplaced: {self._startup_problem}" if self._startup_problem else
                  "unplaced: no registered pair with tracker poses within the start-up's "
                  f"{self.options.startup_wait_frames} frames")
        self._finalized = self._finalized + [
            FrameResult(p["id"], p["timestamp"], np.full((3, 3), np.nan), np.full(6, np.nan),
                        status, True, p["dropped"], p["timings"],
                        tracker_dropped=p["dropped"]) for p in gone]

    def _flush(self) -> list[FrameResult]:
        self._finalized = []
        if self._pending:
            if self._plane is None:
                if len(self._pending) < 2:  # (a pair was blamed on tracking; review)
                    raise ValueError(
                        "the sequence ended with 1 frame in the start-up: the plane needs a "
                        "registered pair, at least 2 frames with tracker poses")
                if not self._bootstrap(final_step=True):
                    self._restore_startup_pairs()
                    raise ValueError(self._startup_problem or (
                        f"no pair among the first {len(self._pending)} frames could be "
                        "registered with tracker poses: the plane cannot be initialised"))
            else:
                self._step(final_step=True)
        return list(self._finalized)

    # ----------------------------------------------------------------------------------------
    def _count_pairs(self, attempted, registered, kind: str = "") -> None:
        c = self.pair_counts
        c[kind + "attempted"] += len(attempted)
        c[kind + "registered"] += len(registered)
        if not kind:
            c["correspondences"] += sum(m.n_inliers for m in registered)

    def _subsample(self, m):
        """At most max_points_per_pair inliers of a pair (undistorted pixels, as extracted)."""
        return subsample_inliers(m, self.options.max_points_per_pair, self.rng)

    def _match_loops(self, k: int, feats, tracker_pose, recent_ok: list) -> list:
        """Matches frame k against retained older frames its predicted footprint overlaps
        (guided through frame k's registered pairs to recent final frames, recent_ok)."""
        o = self.options
        if o.loop_pairs <= 0 or not self._loop_feats:
            return []
        pose = tracker_pose if tracker_pose is not None else self._predict_pose(
            self._times.get(k))
        if pose is None:
            return []
        try:
            centre = self._centroid(self._to_reference(pose))
        except ValueError:  # the plane through the reference camera or this one: no prediction
            return []
        ids = np.array([i for i in self._loop_feats if k - i >= o.loop_min_separation], int)
        if len(ids) == 0:
            return []
        dist = np.linalg.norm(np.array([self._loop_centroids[i] for i in ids]) - centre, axis=1)
        near = ids[np.argsort(dist)][: o.loop_pairs]
        near = [i for i in near if np.linalg.norm(self._loop_centroids[i] - centre)
                < self._loop_radius]
        guided = guided_search(feats, self.options.matching)
        G_k = self._predict_reference(recent_ok) if guided else None
        predicted = [None if G_k is None else np.linalg.solve(G_k, self._loop_G[i])
                     for i in near]  # loop frame i -> frame k pixels
        return self._match(feats, [self._loop_feats[i] for i in near], predicted)

    def _restore_startup_pairs(self) -> None:
        """A start-up try that refused its plane (the start-up waits) gives back the pairs it
        left out: its adjustment, refused, does not judge them."""
        for pair in self._startup_left_out:  # (replaced, never mutated: _save)
            self._boot_matches = [*self._boot_matches, pair]
            if pair.frame_l in self._pair_H:
                self._pair_H = {**self._pair_H, pair.frame_l: {
                    **self._pair_H[pair.frame_l], pair.frame_m: pair.H_lm}}
            for p in self._pending:
                if p["id"] in (pair.frame_l, pair.frame_m):
                    p["visual"] = True
        self.pair_counts["inconsistent"] -= len(self._startup_left_out)
        self._startup_left_out = []

    def _pair_consistency_limit(self) -> float:
        """px, the pair consistency checks' limit (SequentialOptions.pair_consistency_fraction
        of the frame's diagonal, at least PAIR_CONSISTENCY_MIN_PX)."""
        w, h = self.size
        return max(PAIR_CONSISTENCY_MIN_PX,
                   self.options.pair_consistency_fraction * np.hypot(w, h))

    def _startup_pair_outlier(self, ba):
        """The start-up pair whose transfer residuals (RMS, px) at the adjustment ``ba`` are
        the largest, when above the pair consistency limit and 5 x the pairs' median; else
        None."""
        fraction = self.options.pair_consistency_fraction
        if fraction <= 0 or len(self._boot_matches) < 3:
            return None
        limit = self._pair_consistency_limit()
        plane = np.asarray(ba.plane(), np.float64)
        poses = {}
        rms = np.zeros(len(self._boot_matches))
        for i, m in enumerate(self._boot_matches):
            for k in (m.frame_l, m.frame_m):
                if k not in poses:
                    poses[k] = np.asarray(ba.pose(k), np.float64)
            d = _core.transfer_points(np.asarray(m.points_m, np.float64), poses[m.frame_l],
                                      poses[m.frame_m], plane, self.K) - m.points_l
            d = d[np.isfinite(d).all(axis=1)]
            rms[i] = np.sqrt(np.mean(d**2)) if len(d) else 0.0
        worst = int(np.argmax(rms))
        if rms[worst] > limit and rms[worst] > 5 * np.median(rms):
            return self._boot_matches[worst]
        return None

    def _inconsistent_pairs(self, matches: list, known: dict | None = None) -> set[int]:
        """The partners of the new frame's pairs (``matches``, frame_l the new frame) that the
        others contradict (SequentialOptions.pair_consistency_fraction), by triangles through
        the pairs ``known`` among the partners ({a: {b: H_ab}}, default the recent ones). Not by
        where pairs to final frames place it: a loop pair that disagrees with the recent
        frames' estimates may be the one correcting their drift. Fewer than 3 pairs: none."""
        fraction = self.options.pair_consistency_fraction
        if fraction <= 0 or len(matches) < 3:
            return set()
        w, h = self.size
        corners = np.array([[0, 0, 1], [w, 0, 1], [w, h, 1], [0, h, 1]], float)
        limit = self._pair_consistency_limit()

        def apart(A, B) -> float:  # mean corner distance of two homographies into frame k
            with np.errstate(divide="ignore", invalid="ignore"):
                a, b = corners @ A.T, corners @ B.T
                return float(np.linalg.norm(a[:, :2] / a[:, 2:] - b[:, :2] / b[:, 2:],
                                            axis=1).mean())

        known = self._pair_H if known is None else known  # {a: {b: H (b -> a pixels)}}
        # triangles: two partners a, b registered to each other (a recent pair) predict the
        # pair k-b as k-a times a-b; a pair contradicted by two or more triangles and by more
        # than confirm it is an outlier
        H = {m.frame_m: m.H_lm for m in matches}  # partner pixels -> frame k pixels
        good, bad = dict.fromkeys(H, 0), dict.fromkeys(H, 0)
        ids = list(H)
        for i, a in enumerate(ids):
            for b in ids[i + 1:]:
                if b in known.get(a, {}):
                    d = apart(H[a] @ known[a][b], H[b])
                elif a in known.get(b, {}):
                    d = apart(H[b] @ known[b][a], H[a])
                else:
                    continue
                for x in (a, b):
                    if d <= limit:
                        good[x] += 1
                    else:  # (NaN: at infinity, not agreeing)
                        bad[x] += 1
        return {x for x in ids if bad[x] >= 2 and bad[x] > good[x]}

    def _predict_reference(self, ok: list) -> np.ndarray | None:
        """Frame k's reference homography from a registered pair to a recent final frame."""
        for m in reversed(ok):
            if m.frame_m in self._recent_G:
                return self._recent_G[m.frame_m] @ np.linalg.inv(m.H_lm)
        return None

    def _match_recent(self, feats, others: list) -> list:
        """The new frame against the recent frames, guided: the newest frame's registration to
        the one before it, repeated (constant velocity: on SYN 6.7 px off at the corners, on the
        hand-held sequence 7 px median, 17 px at most), chained with the newest frame's pairs to
        the others, predicts each pair. Without that registration the newest is matched
        exhaustively first and its result chained instead."""
        if not others or not guided_search(feats, self.options.matching):
            return self._match(feats, others)
        newest = others[-1]
        chained = self._pair_H.get(newest.frame_id, {})
        step = chained.get(others[-2].frame_id) if len(others) > 1 else None
        if step is not None:  # newest -> new frame predicted as previous -> newest
            predicted = [step if f is newest else
                         step @ chained[f.frame_id] if f.frame_id in chained else None
                         for f in others]
            return self._match(feats, others, predicted)
        first = self._match(feats, [newest])[0]
        predicted = [first.H_lm @ chained[f.frame_id]
                     if first.ok and f.frame_id in chained else None for f in others[:-1]]
        return [*self._match(feats, others[:-1], predicted), first]

    def _match(self, feats, others: list, predicted: list | None = None) -> list:
        """match_pair of the new frame against each of `others`, in order (guided where
        `predicted` gives that pair's homography); with matching.num_threads > 1 on a thread
        pool (OpenCV's matcher and RANSAC release the GIL, and the pair results do not depend
        on the thread: RANSAC seeds its own generator)."""
        o = self.options.matching
        predicted = predicted or [None] * len(others)
        jobs = list(zip(others, predicted, strict=True))

        def one(job):
            return match_pair(feats, job[0], self.size, o, predicted=job[1])

        if o.num_threads <= 1 or len(others) <= 1:
            out = [one(job) for job in jobs]
        else:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(o.num_threads,
                                                thread_name_prefix="fusedmosaic-match")
            out = list(self._pool.map(one, jobs))
        tried = [h is not None for h in predicted]
        self.pair_counts["guided"] += sum(m.guided for m in out)
        self.pair_counts["guided_fallback"] += sum(t and not m.guided for t, m in
                                                   zip(tried, out, strict=True))
        return out

    def _startup_rows(self) -> dict[int, int]:
        """The start-up's frames (pending) by their row in its tables: {id: position}. The
        tables are sized by the frames the start-up holds (at most startup_wait_frames), not by
        the frame count: indexed by frame id they grew with every frame a start-up waiting for
        its tracker saw (0.9 of 2 s over 10 frames after 3e6 frames)."""
        return {p["id"]: i for i, p in enumerate(self._pending)}

    def _pending_tracker_poses(self) -> tuple[dict, np.ndarray]:
        """Tracker poses of the pending frames: {id: pose} and an (n, 6) table by row of
        _startup_rows (use _renumbered matches with it), NaN where a frame has none."""
        tracked, table = {}, np.full((len(self._pending), 6), np.nan)
        for i, p in enumerate(self._pending):
            if p["tracker"] is not None:
                tracked[p["id"]] = table[i] = p["tracker"]
        return tracked, table

    def _renumbered(self, matches: list) -> list:
        """The start-up's pair matches with their frame ids replaced by _startup_rows' rows
        (the ids the tables of _pending_tracker_poses are indexed by)."""
        rows = self._startup_rows()
        return [replace(m, frame_l=rows[m.frame_l], frame_m=rows[m.frame_m])
                for m in matches]  # (the arrays are shared, not copied)

    def _startup_candidates(self, k: int, tracker_pose) -> list:
        """Earlier start-up frames to match frame k against: those of the window (the last
        W - 1), the others whose footprint, predicted from the tracker poses and a provisional
        plane, overlaps frame k's by >= startup_min_overlap, and among those without that
        prediction (frame k or they untracked, or no plane yet) the ones _chained_candidates
        picks. An older tracked frame without a predicted footprint is always tried;
        startup_min_overlap 0: every earlier start-up frame."""
        o = self.options
        if o.startup_min_overlap <= 0:
            return list(self._boot_feats)
        recent = {i for i, _ in self._recent}
        older = [f.frame_id for f in self._boot_feats if f.frame_id not in recent]
        tracked, plane = {}, None
        if tracker_pose is not None:
            tracked, table = self._pending_tracker_poses()
            try:
                plane = estimate_plane(self._renumbered(self._boot_matches), table, self.K)
            except ValueError:  # no registered start-up pair with tracker poses yet
                tracked = {}
            else:
                self._startup_plane = plane
        predicted = [i for i in older if i in tracked]
        G = np.array([_transfer_or_nan(tracker_pose, tracked[i], plane, self.K)
                      for i in predicted]).reshape(-1, 3, 3)
        polys = footprint_polygons(G, *self.size, self._fov_radius)
        # poly None: the provisional plane puts the footprint behind the camera (or a camera on
        # it); no prediction, so the frame is tried
        skip = {i for i, poly in zip(predicted, polys, strict=True) if poly is not None
                and overlap_fraction(self._own_footprint, poly) < o.startup_min_overlap}
        unpredicted = [i for i in older if i not in tracked]
        skip |= set(unpredicted) - self._chained_candidates(k, unpredicted)
        return [f for f in self._boot_feats if f.frame_id not in skip]

    def _chained_candidates(self, k: int, ids: list[int]) -> set[int]:
        """Of the older start-up frames `ids`, whose overlap with frame k the tracker cannot
        predict, those frame k is matched against: the STARTUP_CHAINED_PAIRS whose footprints,
        chained through the start-up's registered pairs (_startup_G), overlap most, by >=
        startup_min_overlap, the footprint of the newest chained frame of the window (frame
        k's, predicted: it is not matched yet), and a stride over the others that tries each
        of them every few frames (STARTUP_STRIDE_PAIRS a frame: frames the chain does not
        reach, e.g. after black frames, or whose chain drifted). Before, a frame without a
        tracker sample was matched against every frame the start-up holds, up to
        startup_wait_frames: 80 pairs, ~370 ms a frame at 400x400 (ORB) for as long as the
        tracker stayed off (review)."""
        if not ids:
            return set()
        overlaps = {}
        newest = next((i for i, _ in reversed(self._recent) if i in self._startup_G), None)
        chained = [i for i in ids if i in self._startup_G]
        if newest is not None and chained:
            # older frame -> the newest chained frame's pixels
            G = np.linalg.solve(self._startup_G[newest],
                                np.array([self._startup_G[i] for i in chained]))
            polys = footprint_polygons(G, *self.size, self._fov_radius)
            for i, poly in zip(chained, polys, strict=True):
                overlap = overlap_fraction(self._own_footprint, poly)
                if overlap >= self.options.startup_min_overlap:
                    overlaps[i] = overlap
        best = set(sorted(overlaps, key=overlaps.get, reverse=True)[:STARTUP_CHAINED_PAIRS])
        others = [i for i in ids if i not in best]
        stride = -(-len(others) // STARTUP_STRIDE_PAIRS)  # (ceil; others empty: 0, unused)
        return best | {i for i in others if (k - i) % stride == 0}

    def _timing(self, k: int, times: dict | None = None) -> tuple[float, float]:
        """C_p timing of frame k over the frames k-2, k-1 given before it (motion_timing);
        nominal spacing: the median of the recent frame intervals."""
        times = self._times if times is None else times
        if k - 2 not in times or k - 1 not in times or k not in times:
            return 1.0, 1.0
        nominal = float(np.median(self._intervals)) if self._intervals else None
        return motion_timing(times[k - 2], times[k - 1], times[k], nominal,
                             self.options.motion_max_gap_s)

    def _tracker_departure(self, k: int, sample: np.ndarray | None) -> np.ndarray | None:
        """How far the tracker samples of frames k-2, k-1, k (those kept: none dropped as a
        glitch) depart from constant velocity, whitened (motion.tracker_motion_departure);
        None without three samples or across a pause (C_p released already)."""
        self._samples = {i: z for i, z in self._samples.items() if i >= k - SAMPLES_KEPT}
        if sample is not None:
            self._samples[k] = sample
        if sample is None or k - 1 not in self._samples or k - 2 not in self._samples:
            return None
        timing = self._timing(k)
        if not np.isfinite(timing[1]):
            return None
        return tracker_motion_departure(self._samples[k - 2], self._samples[k - 1], sample,
                                        self._costs.motion_sigma, self._costs.emt_sigma, timing)

    def _departure_of(self, samples: dict, times: dict):
        """motion.triple_departures over these samples and times, the nominal interval and
        the motion's and tracker's sigmas of the C_p terms."""
        nominal = float(np.median(self._intervals)) if self._intervals else None
        return triple_departures(samples, times, nominal, motion_sigma=self._costs.motion_sigma,
                                 emt_sigma=self._costs.emt_sigma,
                                 max_gap_s=self.options.motion_max_gap_s)

    def _predict_pose(self, timestamp: float | None = None) -> np.ndarray | None:
        """Constant-velocity prediction from the last two estimated poses, the motion scaled by
        the time since the last one (when the times are known)."""
        if len(self._poses) < 2:
            return None
        (pose_a, ta), (pose_b, tb) = (self._poses[i] for i in sorted(self._poses)[-2:])
        # the ratio of motion_timing with b's interval as the nominal one (1 when within 1 %);
        # a frame many frames ahead of the last estimated one (a step's pending frames) is no
        # pause: only the long-pause rule applies
        nominal = float(np.median(self._intervals)) if self._intervals else tb - ta
        ratio = 1.0 if timestamp is None else motion_timing(
            ta, tb, timestamp, nominal, self.options.motion_max_gap_s, max_ratio=None)[0]
        return predict_constant_velocity(pose_a, pose_b, ratio)

    def _solve_startup(self, ids, tracked, table, timing, max_iterations=None, start=None,
                       function_tolerance=FUNCTION_TOLERANCE, constant_plane=False,
                       plane_std=True):
        """The start-up's BA+EMT over frames ids with the samples `tracked` (id -> z): the
        adjuster and its summary (a dict). At most `max_iterations` (None:
        startup_max_iterations); `start`: an adjuster of these frames to start from (its poses
        and plane), else the tracker's poses and _initial_plane's plane."""
        o = self.options
        pairs = [(m.frame_l, m.frame_m, *self._subsample(m)) for m in self._boot_matches]
        if start is None:
            plane, initial = self._initial_plane(ids, tracked, table, timing, pairs)
        else:
            plane, initial = start.plane(), [start.pose(k) for k in ids]
        ba = self._startup_adjuster(ids, tracked, timing, pairs, plane, initial,
                                    max_iterations=(o.startup_max_iterations
                                                    if max_iterations is None
                                                    else max_iterations),
                                    function_tolerance=function_tolerance,
                                    plane_std=plane_std and o.startup_max_plane_std > 0)
        if constant_plane:
            ba.set_constant_plane(True)
        return ba, ba.solve().as_dict()

    def _startup_sigma_v(self, ba, summary, ids, tracked, table, timing, nominal):
        """sigma_v "auto" (consistency.auto_sigma_v): the start-up adjustment `ba` (its
        `summary`) solved again with the keypoints' noise its pairs' transfer residuals (every
        inlier) show at its estimate, which the window keeps (visual_sigma reports it).
        `nominal`: the plane was given (held constant), not estimated. As ba-emt's
        (bundle._with_measured_sigma_v), `ba` and `summary` with the paper's value where
        auto_sigma_v measures nothing to solve again with, or when the second solve does not
        converge."""
        start = self._sigma_v
        plane = np.asarray(ba.plane())
        sigma, report = auto_sigma_v(
            start, summary["termination"], np.nan if nominal else summary["plane_relative_std"],
            lambda: TransferResiduals.of(
                [(m.frame_l, m.frame_m, m.points_l, m.points_m) for m in self._boot_matches],
                lambda k: np.asarray(ba.pose(k)), plane, self.K),
            "the start-up adjustment")
        if sigma != start:
            self._sigma_v = sigma  # (read by _startup_adjuster)
            # (pi's std not computed again: the first solve's, at the paper's sigma_v, stands)
            second, again = self._solve_startup(ids, tracked, table, timing, start=ba,
                                                constant_plane=nominal, plane_std=False)
            if again["termination"] != "CONVERGENCE":
                self._sigma_v, sigma = start, start
                report |= {"sigma_v_px": start,
                           "note": f"the start-up solved again with the measured sigma_v ended "
                                   f"{again['termination']} ({again['message']}); its first "
                                   f"solve, with the paper's {start:g} px, kept"}
            else:
                again["sigma_v_from"] = {key: summary[key] for key in (
                    "termination", "iterations", "final_cost")} | {"sigma_v_px": start}
                again["iterations"] += summary["iterations"]
                again["solve_time_s"] += summary["solve_time_s"]
                # the first solve's, at the paper's sigma_v, as the start-up's checks judged it
                # (and the gate's limit is stated: see plane_max_relative_std)
                again["plane_relative_std"] = summary["plane_relative_std"]
                ba, summary = second, again
        self._win_set_sigma_v(sigma)
        self.visual_sigma = report
        return ba, summary

    def _startup_adjuster(self, ids, tracked, timing, pairs, plane, initial, **options):
        """A BundleAdjuster of the start-up's frames (ids, from the poses `initial`, with the
        samples `tracked`), its pairs (frame_l, frame_m, points_l, points_m) and `plane`;
        `options`: BundleAdjusterOptions fields (motion_gate_chi2: the options' by default)."""
        o = self.options
        options.setdefault("motion_gate_chi2", o.motion_gate_chi2)
        ba_options = _core.BundleAdjusterOptions(
            sigma_v_px=self._sigma_v, loss=o.loss, num_threads=1,
            trust_region=(o.startup_trust_region if self._startup_untracked()
                          else "levenberg_marquardt"), **options)
        ba_options.motion_sigma = self._costs.motion_sigma
        ba_options.emt_sigma = self._costs.emt_sigma
        ba = _core.BundleAdjuster(self.K, ba_options)
        for i, k in enumerate(ids):
            ba.add_frame(k, initial[i], tracked.get(k), *timing[k])
        for pair in pairs:
            ba.add_pair(*pair)
        ba.set_plane(plane)
        return ba

    def _startup_untracked(self) -> bool:
        """Whether a start-up frame came without a tracker sample (a sample gated by the
        start-up's checks does not count: its frame is tracked)."""
        return any(p["tracker"] is None for p in self._pending)

    def _initial_plane(self, ids, tracked, table, timing, pairs):
        """The plane the start-up's adjustment starts from, and its frames' initial poses: the
        tracker's, frames without a sample chained from them through the registered pairs and
        the plane of the registered pairs between tracked frames. When some frames have no sample,
        that start and the one from the plane facing the tracked cameras at
        nominal_plane_distance_mm are each adjusted STARTUP_PROBE_ITERATIONS times and the
        lower cost's state returned. A tracker that came on at the start-up's last 2-3 frames
        has 1-2 such pairs, ~1 mm apart: their plane came out tilted or behind the cameras (live
        replays of the tests' late-tracker scene: the adjustment settled at cost 1e6-5e6, 7-19
        motion terms released, and was refused, then solved again at the next frame), or 48 mm
        away where the solution is at 31: 192 iterations along the valley that the scale of a
        structure tied to 2 samples leaves (the homographies within 0.02 px after 12); the
        nominal start converged in 4-23 to the ~1300 of the visual noise."""
        usable = [m for m in self._boot_matches if m.frame_l in tracked and m.frame_m in tracked]
        degenerate = None
        try:
            planes = [estimate_plane(self._renumbered(usable), table, self.K)]
        except ValueError as exc:
            # No pair has a baseline, and the images show no parallax (else _stuck_tracker
            # refused the start-up): a camera held still, or a frozen tracker on one, given the
            # nominal plane below as a camera held still with a noisy tracker gets it.
            planes, degenerate = [], exc
        if not planes or self._startup_untracked():  # (all tracked: nothing is chained)
            samples = np.array([tracked[k] for k in ids if k in tracked])
            with np.errstate(divide="ignore", invalid="ignore"):  # (checked below)
                nominal = plane_facing(samples, self.options.nominal_plane_distance_mm)
            if np.isfinite(nominal).all():  # (not through the world's origin)
                planes.append(nominal)
        if not planes:  # (the nominal plane through the origin: _recentre_near_plane moves it)
            raise degenerate
        rows = self._startup_rows()
        boot = self._renumbered(self._boot_matches)
        starts = [(plane, fill_missing_poses(chain_missing_poses(
            table, boot, plane, self.K, fill=False)[[rows[k] for k in ids]]))
            for plane in planes]
        if len(starts) == 1:
            return starts[0]
        best = (np.inf, *starts[0])  # (taken if no probe succeeds)
        for plane, initial in starts:
            probe = self._startup_adjuster(ids, tracked, timing, pairs, plane, initial,
                                           max_iterations=STARTUP_PROBE_ITERATIONS,
                                           function_tolerance=FUNCTION_TOLERANCE,
                                           motion_gate_chi2=np.inf)
            summary = probe.solve()
            # (a failed evaluation reports final_cost NaN and leaves the state at the start)
            if (summary.termination != "FAILURE" and 0 <= summary.final_cost < best[0]):
                best = (summary.final_cost, np.asarray(probe.plane()),
                        [probe.pose(k) for k in ids])
        return best[1], best[2]

    def _stuck_tracker(self, usable: list, tracked: dict) -> str | None:
        """Why the start-up refuses its tracker samples, or None: when the two samples of every
        registered pair with tracker poses (`usable`) lie at one position (no pair has a
        baseline, plane.MIN_PAIR_BASELINE) while the images show parallax
        (homography_parallax above MAX_NOMINAL_PARALLAX): the camera moved, the tracker did
        not. Without parallax either, it is a camera held still, given the nominal plane
        (_initial_plane, _bootstrap). Before, both raised "cannot estimate the plane: every
        pair was degenerate" out of add_frame at every frame from the start-up's on."""
        centres = {k: -_core.rotation_from_angle_axis(z[:3]).T @ z[3:]
                   for k, z in tracked.items()}
        if any(np.linalg.norm(centres[m.frame_l] - centres[m.frame_m]) >= MIN_PAIR_BASELINE
               for m in usable):
            return None
        parallax = homography_parallax(usable, self.K)
        if not parallax > MAX_NOMINAL_PARALLAX:
            return None
        frames = sorted({k for m in usable for k in (m.frame_l, m.frame_m)})
        return (f"the tracker did not move while the camera did: the tracker samples of the "
                f"{len(frames)} start-up frames of its {len(usable)} registered pairs put "
                "every pair's two cameras at the same position, yet the images show parallax "
                f"({parallax:.2g} of the depth, 90th percentile; a camera held still shows "
                "none). The tracker is frozen: it resends its last pose (a stalled stream, or "
                "a sensor it no longer sees); check that tracker_pose is a live sample for "
                "each frame")

    def _std_refusal(self, std: float, usable: list, tracked: dict) -> str:
        """Why a start-up plane of relative std `std` from the registered pairs `usable` is
        refused (`tracked`: the samples it used, for _units_hint)."""
        return (f"the plane the start-up estimated from {len(usable)} registered pairs has a "
                + ("relative standard deviation that the images leave unbounded (too few "
                   "pairs, or pairs that do not see it)" if np.isinf(std) else
                   f"relative standard deviation of {std:.2g}")
                + f" (startup_max_plane_std {self.options.startup_max_plane_std:g})"
                + self._units_hint(usable, tracked))

    def _units_hint(self, usable: list, tracked: dict, still: bool = True) -> str:
        """For a refused start-up: "; ... in mm?" when at least CONTRADICTING_PAIRS pairs
        (`usable`) registered but the tracked camera centres lie within UNITS_BASELINE_MM of
        each other (a tracker in metres: an 80-frame start-up on the SYN circle, 1131 pairs, was
        refused as "too few pairs, or pairs that do not see it", its 33 mm of baseline read
        0.033), and the images show parallax. Without (homography_parallax at most
        MAX_NOMINAL_PARALLAX) the camera was held still, which it says instead when `still`
        (a still camera's noise-free samples, 0 mm apart, were asked whether they were in mm)."""
        if len(usable) < CONTRADICTING_PAIRS or len(tracked) < 2:
            return ""
        spread = camera_baseline_mm(np.array(list(tracked.values())))
        if not spread < UNITS_BASELINE_MM:
            return ""
        if not homography_parallax(usable, self.K) > MAX_NOMINAL_PARALLAX:
            return (f"; its tracked camera centres lie within {spread:.2g} mm of each other "
                    "and the images show no parallax: a camera held still, whose plane the "
                    "images cannot place (assumed nominal_plane_distance_mm away once the "
                    "start-up holds startup_wait_frames frames or the sequence ends)"
                    if still else "")
        return (f"; yet its tracked camera centres lie within {spread:.2g} mm of each other: "
                "are the tracker's translations in mm? (metres give a 1000x smaller baseline)")

    def _disagreement(self, ba, tracked: dict, conventions: bool = True) -> str:
        """For a refused start-up: "; its tracker samples disagree ..." when the adjusted poses
        lie further from the samples than MAX_NOISE_RATIO x the EMT prior's noise (as the run's
        tracker_agreement check), else "". A tracker in another convention is the likelier cause
        then than the images: quaternions stored w first made SYN start-ups of 30-40 frames
        refused as "unbounded" or "not in front of frames" (ratios 6.9-9.3), with nothing to
        say why."""
        if not tracked:
            return ""
        ids = sorted(tracked)
        agreement = tracker_agreement(np.array([ba.pose(k) for k in ids]),
                                      np.array([tracked[k] for k in ids]),
                                      np.ones(len(ids), bool), None, self._costs.emt_sigma)
        ratio = agreement.get("noise_ratio", 0.0)
        if not ratio > MAX_NOISE_RATIO:
            return ""
        noise = "emt_sigma; --tracker-rot-sigma / --tracker-trans-sigma"
        return (f"; its {agreement['frames']} tracker samples disagree with the images: the "
                f"adjusted poses differ from them by {agreement['rotation_rms_deg']:.2f} deg / "
                f"{agreement['translation_rms_mm']:.2f} mm per axis (median), {ratio:.1f} x the "
                "noise the EMT prior assumes. " + (
                    TRACKER_NOISE_ADVICE.format(noise) if conventions else
                    f"If the tracker is that noisy, give its noise ({noise})"))

    def _startup_outlier(self, ba, tracked: dict, seen: set) -> int | None:
        """Among the tracked start-up frames with a registered pair (`seen`: the images can
        contradict their samples, as the window gates only frames with visual evidence), the
        one whose sample disagrees most with the adjustment, if its Mahalanobis^2 exceeds
        gate_chi2 x max(1, median / chi2(6)'s median); else None."""
        ids = sorted(k for k in tracked if k in seen)
        if len(ids) < 4 or not np.isfinite(self.options.gate_chi2):
            return None
        sigma = self._costs.emt_sigma  # the C_EMT residual, whitened, squared
        m2 = np.array([np.sum(_core.evaluate_pose_prior(ba.pose(k), tracked[k], sigma)[0] ** 2)
                       for k in ids])
        limit = self.options.gate_chi2 * max(1.0, float(np.median(m2)) / CHI2_6_MEDIAN)
        worst = int(np.argmax(m2))
        return ids[worst] if m2[worst] > limit else None

    def _startup_due(self) -> bool:
        """Whether to try the start-up adjustment (again): its plane was not refused yet, or
        since then its registered pairs with tracker poses grew by a quarter (at least one) or
        its frames by a quarter; holding startup_wait_frames frames, once
        STARTUP_RETRY_FRACTION of them came since the refusal. A weakly textured scene's
        start-up was solved again at every frame while it waited (up to ~46 ms a frame at 60
        frames of 200 px), though only new pairs see the plane much better. At the bound the
        plane's uncertainty is no longer refused (it must decide): a refusal there is a plane
        behind the cameras (the tracker contradicting the images: an inverted hand-eye), which
        one more frame does not change, and each attempt over 80 frames and ~1500 pairs took
        4-8 s: tried at every frame, 150 frames of 240 px took 5.6 min (review)."""
        pairs, frames, refused_at = self._startup_refused
        wait = self.options.startup_wait_frames
        if not pairs:
            return True
        if len(self._pending) >= wait:
            if self._next_id - refused_at >= max(1, round(STARTUP_RETRY_FRACTION * wait)):
                return True
        elif len(self._pending) >= 1.25 * frames:
            return True
        tracked = {p["id"] for p in self._pending if p["tracker"] is not None}
        usable = sum(m.frame_l in tracked and m.frame_m in tracked for m in self._boot_matches)
        return usable >= max(pairs + 1, 1.25 * pairs)

    def _tracker_jumps(self) -> str | None:
        """Why the start-up refuses its tracker samples, or None: when the glitch filter
        (_plausible) dropped more than STARTUP_MAX_DROPPED_FRACTION of them (and at least
        tracker_reanchor_after), they jump between frames as no probe moves: a convention mix-up
        (rotations in degrees, [t, r] order), not glitches. The start-up adjustment took such
        samples and frames came out "placed" 50-2000 px off (median). Counted: the samples the
        filter dropped on arrival ("jump"), whether a re-anchoring restored them since; not
        those a re-anchoring dropped (the old reference's: a tracker re-based once is no
        convention mix-up, which re-anchors again and again)."""
        given = sum(p.get("sample") is not None for p in self._pending)
        dropped = sum(bool(p["jump"]) for p in self._pending)
        if not (dropped > STARTUP_MAX_DROPPED_FRACTION * given
                and dropped >= self.options.tracker_reanchor_after):
            return None
        return (f"the glitch filter dropped {dropped} of the start-up's {given} tracker samples "
                "as jumps from the sample before faster than tracker_max_speed_mm_s / "
                "tracker_max_angular_speed allow: the tracker evidently disagrees with the "
                "images. Check that tracker_pose is the camera's cam_from_world as [angle-axis "
                "r in rad, t in mm] (rotations in degrees, or [t, r] for [r, t], make samples "
                "jump so), and that "
                + CONVENTIONS_AND_TIMING)

    def _bootstrap(self, final_step: bool = False) -> bool:
        """BA+EMT over the first frames (all their pairs): plane and poses to start from.
        False (nothing done) while no registered pair has tracker poses for both frames, or
        when the plane it gives is not in front of every start-up camera."""
        t0 = time.perf_counter()
        self._startup_left_out = []  # (pairs this try leaves out: restored if it refuses)
        self._startup_refused = (0, 0, 0)
        self._startup_problem = self._tracker_jumps()  # (None: not refused for this)
        if self._startup_problem:  # (checked again at the next frame: a count, no solve)
            return False
        tracked, table = self._pending_tracker_poses()
        usable = [m for m in self._boot_matches if m.frame_l in tracked and m.frame_m in tracked]
        if not usable:
            return False
        refused_pairs = len(usable)  # (counted as _startup_due counts them)
        self._startup_problem = self._stuck_tracker(usable, tracked)
        if self._startup_problem:  # (no solve: tried again when the pairs grow)
            self._startup_refused = (refused_pairs, len(self._pending), self._next_id)
            return False
        if self._recentre_near_plane(usable):
            tracked, table = self._pending_tracker_poses()
        o = self.options
        # frames with a registered pair: the checks below look at these only (a black frame
        # or one looking away while the scope goes in sees no plane, and proves nothing)
        seen = {i for m in self._boot_matches for i in (m.frame_l, m.frame_m)}
        ids = [p["id"] for p in self._pending]
        times = {p["id"]: p["timestamp"] for p in self._pending}
        # The tracker's motion check over the start-up (see _judge_motion_again), each
        # component scaled by its median over all the start-up's triples (its first ones have no
        # earlier ones: a tracker 4x noisier than Sigma_EMT broke them, e_M 1.6 -> 3.9 px)
        w = {p["id"]: p["departure"] for p in self._pending if p["departure"] is not None}
        scale = motion_departure_scale(list(w.values()))
        departure = self._departure_of(
            {p["id"]: p["tracker"] for p in self._pending if p["tracker"] is not None}, times)
        bad: set[int] = set()
        for p in self._pending:
            k = p["id"]
            p["motion_break"], samples = (
                motion_verdict(w[k], k, departure, scale, o.motion_gate_chi2) if k in w
                else (False, frozenset()))
            bad |= samples
            p["cv_timing"] = self._timing(k, times)
        timing = {p["id"]: RELEASED if p["motion_break"] else p["cv_timing"]
                  for p in self._pending}
        # The samples that explained a departure are left out, as the window gates them: no
        # registered pair contradicts a black frame's (+20 deg glitches on black frames 9, 10 of
        # a 16-frame start-up: e_M / worst 2.74 / 23.3 px kept, 0.50 / 0.9 px left out). A
        # start-up of 8 frames has too few triples for the scale to stand out of its glitches.
        gated = [k for k in sorted(bad) if k in tracked]
        rest = {k: z for k, z in tracked.items() if k not in bad}
        rows = self._startup_rows()
        if gated and any(m.frame_l in rest and m.frame_m in rest for m in usable):
            tracked, table = rest, table.copy()
            table[[rows[k] for k in gated]] = np.nan
        else:
            gated = []
        for p in self._pending:  # (decided again while the start-up waits)
            p["motion_glitch"] = p["id"] in gated
        # Tracker samples that disagree with the adjustment are gated as the window's are, one
        # at a time (the worst), at most a quarter of them: Mahalanobis^2 above gate_chi2
        # scaled by the samples' own median over chi2(6)'s (noisier samples than Sigma_EMT,
        # Fig. 9's nu = 4: median 57, every sample above 22.5, none an outlier). A glitch on
        # the first sample (+100 mm: 328 against a median of 50) was the glitch filter's
        # reference and was kept: frames up to 144 px off.
        most = len(tracked) // 4 + len(gated)
        limit = o.startup_max_plane_std
        # the plane is taken or refused for good (else a refusal makes the start-up wait)
        must_decide = final_step or len(ids) >= o.startup_wait_frames
        # (see startup_trial_iterations)
        trial = limit > 0 and not must_decide and len(tracked) < len(ids) / 2
        while True:
            if trial:
                ba, summary = self._solve_startup(ids, tracked, table, timing,
                                                  o.startup_trial_iterations)
                trial = False  # (once)
                if summary["termination"] == "NO_CONVERGENCE":
                    if not summary["plane_relative_std"] <= limit:
                        self._startup_refused = (refused_pairs, len(ids), self._next_id)
                        self._startup_problem = self._std_refusal(
                            summary["plane_relative_std"], usable, tracked
                        ) + self._disagreement(ba, tracked)
                        return False
                    ba, summary = self._solve_startup(ids, tracked, table, timing, start=ba)
            else:
                ba, summary = self._solve_startup(ids, tracked, table, timing)
            # a registered pair the adjustment leaves grossly off is left out and the start-up
            # solved again (one at a time, the worst; at most a quarter of the pairs): see
            # pair_consistency_fraction, whose triangles miss a group of wrong pairs that agree
            # with each other (a frame's lower half from another view, 4 of its 11 pairs there)
            pair = (self._startup_pair_outlier(ba)
                    if len(self._startup_left_out) < len(usable) // 4 else None)
            if pair is not None and any(m is not pair for m in usable):
                self._startup_left_out = [*self._startup_left_out, pair]  # (replaced: _save)
                if pair.frame_m in self._pair_H.get(pair.frame_l, {}):  # (replaced: _save)
                    self._pair_H = {**self._pair_H, pair.frame_l: {
                        i: H for i, H in self._pair_H[pair.frame_l].items()
                        if i != pair.frame_m}}
                self._boot_matches = [m for m in self._boot_matches if m is not pair]
                usable = [m for m in usable if m is not pair]
                self.pair_counts["inconsistent"] += 1
                seen = {i for m in self._boot_matches for i in (m.frame_l, m.frame_m)}
                for p in self._pending:  # (its visual evidence: the pairs left)
                    if p["id"] in (pair.frame_l, pair.frame_m) and p["id"] not in seen:
                        p["visual"] = False
                continue
            worst = self._startup_outlier(ba, tracked, seen) if len(gated) < most else None
            rest = {k: z for k, z in tracked.items() if k != worst}
            if worst is None or not any(m.frame_l in rest and m.frame_m in rest
                                        for m in usable):
                break  # (a gate that would leave no registered pair with samples: not applied)
            gated.append(worst)
            tracked = rest
            table = table.copy()
            table[rows[worst]] = np.nan
        usable = [m for m in usable if m.frame_l in tracked and m.frame_m in tracked]
        if (limit > 0 and not summary["plane_relative_std"] < UNBOUNDED_CHECK_RELATIVE_STD
                and must_decide):
            # Taken or refused below for good: solved on to the offline adjustment's tolerance
            # first. Stopped at FUNCTION_TOLERANCE, a plane the images leave unbounded came out
            # finite (2 pairs behind a 55 px field stop: relative std 643, |pi| 97 / mm; taken,
            # frames up to 9780 px off); solved on, it is told unbounded (inf) and refused.
            ba, summary = self._solve_startup(
                ids, tracked, table, timing, start=ba,
                function_tolerance=_core.BundleAdjusterOptions().function_tolerance)
        # A plane behind a start-up camera is no plane it sees: too few registered pairs, or
        # too short a baseline, for the start-up to tell (60 untextured frames, one start-up
        # pair with a 2.5 mm baseline: pi behind every camera, then frames 182 px to 3.4e6 px
        # off). The start-up waits for more frames instead.
        checked = [k for k in ids if k in seen]
        checked_poses = np.array([ba.pose(k) for k in checked]).reshape(-1, 6)

        def not_in_front(poses):
            depths = plane_depths(poses, np.asarray(ba.plane()))
            return [k for k, d in zip(checked, depths, strict=True)
                    if not (np.isfinite(d) and d > 0)]

        behind = not_in_front(checked_poses)
        std = summary["plane_relative_std"]
        nominal = False  # (the plane given, not estimated)
        # (the spread of every tracked start-up camera: those of a few pairs may be neighbours
        # of a camera that moved; 1 pair, 0.009 of the depth, the cameras' 0.6)
        spread = np.array([ba.pose(k) for k in ids if k in tracked]).reshape(-1, 6)
        if ((behind or (limit > 0 and not std <= limit))
                and must_decide
                and baseline_ratio(spread, np.asarray(ba.plane())) < MIN_BASELINE_RATIO
                and not homography_parallax(usable, self.K) > MAX_NOMINAL_PARALLAX):
            # No parallax: nominal_plane_distance_mm. Before, 80 frames held still were handed
            # out unplaced and the sequence refused (ba-emt: e_M 0.027 px), 50 gave a plane
            # 3.7e4 mm away.
            ba.set_plane(plane_facing(spread, o.nominal_plane_distance_mm))
            ba.set_constant_plane(True)
            nominal = True
            summary = ba.solve().as_dict()
            checked_poses = np.array([ba.pose(k) for k in checked]).reshape(-1, 6)
            behind = not_in_front(checked_poses)
            std = 0.0  # (given: not refused for its std)
            # but not measured: the run's plane check says so unless the window measures it
            summary["plane_relative_std"] = np.inf
        if behind:
            self._startup_refused = (refused_pairs, len(ids), self._next_id)
            parallax = homography_parallax(usable, self.K)
            if len(usable) >= CONTRADICTING_PAIRS and parallax > MAX_NOMINAL_PARALLAX:
                # Many pairs with parallax: neither few nor short. (An inverted tracking.csv
                # on the SYN circle, 271 pairs, centres 28.7 mm apart, was told "too few pairs
                # or too short a baseline".)
                why = (f"the images show parallax ({parallax:.2g} of the depth, 90th "
                       "percentile), so the tracker's poses likely contradict them: check that "
                       f"{CONVENTIONS_AND_TIMING}")
            else:
                held = (baseline_ratio(checked_poses, np.asarray(ba.plane()))
                        < MIN_BASELINE_RATIO)
                why = ("too few pairs or too short a baseline to initialise it (the start-up "
                       "cameras' centres lie within "
                       f"{camera_baseline_mm(checked_poses):.3g} mm of each other" + (
                           "; a camera held still or only turning about its axis gives the "
                           "images no parallax" if held else "") + ")"
                       + self._units_hint(usable, tracked, still=not held))
            self._startup_problem = (
                f"the plane the start-up estimated from {len(usable)} registered pairs is not "
                f"in front of frames {behind[:5]}{' ...' if len(behind) > 5 else ''}: {why}"
                + self._disagreement(ba, tracked, conventions=CONVENTIONS_AND_TIMING not in why))
            return False
        # Nor is a plane the start-up cannot tell (the same 60 frames, 3 pairs after 20 frames:
        # relative std 1.8, depth 4 mm for 30, frames ~1000 px off), unless the sequence ends
        # or the start-up holds startup_wait_frames frames: then the best it has is taken.
        # An unbounded one is no plane at all, even then (2 pairs behind a 55 px field stop,
        # streamed: pi 6e-5 mm from the world's origin, frames' homographies singular, the
        # run crashed): refused as a plane behind the cameras is.
        if limit > 0 and not std <= limit and (
                np.isinf(std) or not must_decide):
            self._startup_refused = (refused_pairs, len(ids), self._next_id)
            self._startup_problem = (self._std_refusal(std, usable, tracked)
                                     + self._disagreement(ba, tracked))
            return False
        if o.sigma_v_px == SIGMA_V_AUTO:
            ba, summary = self._startup_sigma_v(ba, summary, ids, tracked, table, timing, nominal)
        self.bootstrap_summary = summary
        self._mark_motion_gated(ids, summary["motion_released_ids"])
        self._motion_history.extend(w.values())  # the window's checks scale by these too
        self._plane = np.asarray(ba.plane())
        self._startup_G, self._startup_plane = {}, None
        self._win_set_plane(self._plane)
        for k in ids:
            # held prior-only frames of the start-up's tail are solved again by the next step
            self._win_add_frame(k, np.asarray(ba.pose(k)), tracked.get(k), fixed=True,
                                timing=timing[k])
        for m in self._boot_matches:
            self._win_add_pair(m.frame_l, m.frame_m, *self._subsample(m))
        # frames with no anchor (no tracker sample, no pairs chaining them to a frame with
        # one), as the window's: 6 black frames in a tracker gap of a 30-frame start-up were
        # "prior-only" here and "dead-reckoned" after it (and in ba-emt)
        # (by row of the start-up's frames: sized by them, not by the frame count)
        has_sample = np.zeros(len(ids), bool)
        has_sample[[rows[k] for k in tracked]] = True
        lost = unanchored_frames(len(ids), self._renumbered(self._boot_matches), has_sample)
        anchored = {k for k in ids if not lost[rows[k]]}
        # the start-up's pairs, for the frames its tail holds back to the next step: what
        # links them to the start-up frames placed now (_fixed_partners, _linked)
        for p in self._pending:
            p["links"] = {m.frame_l if m.frame_m == p["id"] else m.frame_m
                          for m in self._boot_matches if p["id"] in (m.frame_l, m.frame_m)}
        self._boot_feats, self._boot_matches = [], []
        elapsed = (time.perf_counter() - t0) / len(ids)
        self._finalize(ids, [ba.pose(k) for k in ids], gated, elapsed, 0.0, final_step,
                       anchored)
        return True

    def _judge_motion_again(self) -> None:
        """After the start-up, before each step: whether the pending frames' tracker samples
        say the camera left constant velocity (not in the paper), so that C_p does not link
        them, as after a pause (motion.motion_verdict: a departure above motion_gate_chi2, each
        component scaled by its median over the frames so far, and not bad samples' doing),
        with every sample given so far: a bad sample shows as such once later ones return to
        the motion (judged on arrival, two consecutive +20 deg glitches on black frames released
        both frames' C_p, and the held frames followed their samples: 116 px). The scope spun in
        at 30 deg per frame (120 sigma_p) and stopped: C_p turned the textured frames with it
        (e_M 12-263 px, 0.5 px with this; the start-up decides its frames in _bootstrap)."""
        if not np.isfinite(self.options.motion_gate_chi2):
            return
        scale = motion_departure_scale(self._motion_history)
        departure = self._departure_of(self._samples, self._times)
        bad: set[int] = set()
        for p in self._pending:
            if p.get("departure") is None or "cv_timing" not in p:
                continue
            broken, samples = motion_verdict(p["departure"], p["id"], departure, scale,
                                             self.options.motion_gate_chi2)
            bad |= samples
            if broken != p["motion_break"]:
                p["motion_break"] = broken
                self._win_set_timing(p["id"], RELEASED if broken else p["cv_timing"])
        # The samples that explained a departure are bad: gated as the window gates a sample
        # its visual evidence contradicts (black frames have none to contradict them). A
        # +20 deg glitch on a black frame: e_M / worst 1.13 / 14.2 px with its C_p, 0.60 / 3.9
        # px with the sample gated too.
        for p in self._pending:
            if p["id"] in bad and p["tracker"] is not None and not p.get("motion_glitch"):
                p["motion_glitch"] = True
                self._win_set_scale(p["id"], self.options.gate_sigma_scale)

    def _step(self, final_step: bool = False) -> None:
        t0 = time.perf_counter()
        self._judge_motion_again()
        ids = [p["id"] for p in self._pending]
        window_ids = set(self.window.window_ids())
        keyframe_ids = self.keyframes.select(self.options.num_clusters,
                                             set(ids) | window_ids | self._unanchored)
        t_kf = time.perf_counter() - t0
        # Anchors: fixed cameras placed with one, the frames' own tracker samples, and
        # registered pairs (visual: linked to an anchored fixed camera through pairs alone).
        # A step with none cannot inform pi: it is held.
        fixed = self._fixed_partners(ids)
        visual = self._linked(fixed - self._unanchored, set())
        glitched = [p["id"] for p in self._pending if p.get("motion_glitch")]
        tracked = {p["id"] for p in self._pending if p["tracker"] is not None} - set(glitched)
        hold = not (visual or tracked)
        self._step_solve_s = 0.0  # (every solve of the step: _win_solved adds each)
        if any(p["held"] for p in self._pending):  # frames held back by the last step
            summary = self._win_solved(ids, self.window.redo, ids, keyframe_ids, hold)
        else:
            summary = self._win_solved(ids, self.window.step, keyframe_ids, hold)
        failed: set[int] = set()
        if summary.termination == "FAILURE":
            summary, failed = self._recover_failed_step(ids, keyframe_ids, hold, summary)
            tracked = {p["id"] for p in self._pending if p["tracker"] is not None} - set(glitched)
        # a tracker sample is gated only against visual evidence that is itself anchored
        gated = [p["id"] for p, d2 in zip(self._pending, summary.emt_mahalanobis2, strict=True)
                 if np.isfinite(d2) and d2 > self.options.gate_chi2 and p["id"] in visual
                 and not failed]
        if gated:
            for k in gated:
                self._win_set_scale(k, self.options.gate_sigma_scale)
            summary = self._win_solved(ids, self.window.redo, ids, keyframe_ids, hold)
            if summary.termination == "FAILURE":  # (the gated redo too: never "placed")
                summary, failed = self._recover_failed_step(ids, keyframe_ids, hold, summary)
        anchored = self._linked(fixed - self._unanchored, tracked - set(gated))
        self._trust_the_estimate(gated)
        self.step_summaries.append(summary)
        self.last_step_summary = summary
        # Each frame's window_solve: its share of all the step's solves. The last summary's
        # time alone left out the first solve of every step redone for a gated sample (SYN
        # 200 frames, tracker noise x 4: 54 of 54 steps redone, the frames' window_solve
        # summed to 136 of the 292 ms solved; review).
        self.last_step_solve_s = self._step_solve_s
        self.num_steps += 1
        self._plane = np.asarray(self.window.plane())
        gated += [k for k in glitched if k not in gated]
        self._finalize(ids, [self.window.pose(k) for k in ids], gated,
                       self._step_solve_s / len(ids), t_kf / len(ids), final_step, anchored,
                       failed)

    def _trust_the_estimate(self, gated) -> None:
        """When the glitch filter's reference (the last sample it kept) is a sample the window
        step just gated against anchored visual evidence, the reference becomes that frame's
        estimate: later samples are judged against where the images put the camera, not
        against the sample they contradict. Before, after a stretch of samples with rotations
        in degrees (frames 20-24 of a 110-frame scan, 37-132 deg off) re-anchored the filter on
        sample 24 (the third disagreeing sample in a row), the right samples after it were
        dropped until the third of them re-anchored it again (sample 26 of that scan)."""
        if self._trusted is None or not gated:
            return
        t0 = self._trusted[0]
        for p in self._pending:
            if p["id"] in gated and p["timestamp"] == t0:
                pose = np.asarray(self.window.pose(p["id"]))
                if np.all(np.isfinite(pose)):
                    R = _core.rotation_from_angle_axis(pose[:3])
                    self._trusted = (t0, -R.T @ pose[3:], R)
                return

    def _recover_failed_step(self, ids, keyframe_ids, hold, summary):
        """A step Ceres ended in FAILURE: its costs could not be evaluated at the starting
        poses (a camera centre on the plane makes the plane-induced homography singular), and
        the C++ window fixed its frames where they started, at their raw tracker samples.
        A tracker sample that puts its camera on or behind the plane, or much nearer it than
        the window's cameras (_unusable_samples), is no pose the images can come from: it is
        dropped (the frame flagged tracker_dropped), its frame re-initialised from the
        constant-velocity prediction, and the step redone. Before, one such sample within the
        glitch filter's bound failed that step and every later step pairing a frame with it,
        leaving 6 neighbours 4-25 px off, all reported "placed".
        Returns the summary and the frames the redo could not place either (the step's, all
        of them: they are finalised at their starting poses as "prior-only (solver failed)"),
        else none."""
        bad = self._unusable_samples(ids)
        if bad:
            for p in self._pending:
                if p["id"] in bad:
                    p["tracker"], p["dropped"], p["motion_glitch"] = None, True, False
                    self._samples.pop(p["id"], None)
                    self._win_drop_sample(p["id"])
                elif p["tracker"] is None and p["id"] > min(bad):
                    # (started from the dropped sample's prediction: predicted again)
                    self._win_drop_sample(p["id"])
            summary = self._win_solved(ids, self.window.redo, ids, keyframe_ids, hold)
        if summary.termination == "FAILURE":
            return summary, set(ids)
        return summary, set()

    def _unusable_samples(self, ids) -> set[int]:
        """Pending frames whose tracker sample puts the camera on or behind the current plane,
        or nearer it than UNUSABLE_DEPTH_RATIO x the median depth of the last window_size fixed
        cameras before the step's frames `ids` (their plane-induced homographies degenerate:
        the step cannot be evaluated)."""
        samples = {p["id"]: p["tracker"] for p in self._pending if p["tracker"] is not None}
        if self._plane is None or not samples:
            return set()
        depths = plane_depths(np.array(list(samples.values())), self._plane)
        frames, step = self._mirror_frames, set(ids)
        before = sorted(k for k, v in frames.items() if v[3] and v[0] is not None
                        and k not in step)[-self.options.window_size:]
        fixed = [frames[k][0] for k in before]
        reference = (np.median(plane_depths(np.array(fixed), self._plane)) if fixed
                     else np.nan)
        floor = UNUSABLE_DEPTH_RATIO * reference if np.isfinite(reference) and reference > 0 \
            else 0.0
        return {k for k, d in zip(samples, depths, strict=True)
                if not (np.isfinite(d) and d > floor)}

    def _fixed_partners(self, ids) -> set[int]:
        """The fixed cameras a step of the pending frames `ids` holds constant through their
        pairs: every fixed frame the C++ window still holds that a pending frame has a stored
        pair with (the step joins each such camera, sliding_window.cc SolveStep). Not
        window_ids(): those are the last W - chi_e frames the window fixed, which after a step
        that held its last frames back (_held_tail) are those held frames themselves, pending
        again; the frames placed before them, which the new frames' pairs point to, were then
        no anchor (review: textured frames chained to placed ones came out "dead-reckoned", the
        plane held for 17 steps, steps of up to 28 free frames)."""
        frames, step = self._mirror_frames, set(ids)
        linked = set().union(*(p.get("links", ()) for p in self._pending))
        return {i for i in linked - step if i in frames and frames[i][3]}

    def _linked(self, anchors: set[int], seeds: set[int]) -> set[int]:
        """Pending frames anchored: the seeds, and those linked by registered pairs to an
        anchor or to an anchored pending frame."""
        found = set(seeds)
        grew = True
        while grew:
            grew = False
            for p in self._pending:
                if p["id"] not in found and p.get("links", set()) & (anchors | found):
                    found.add(p["id"])
                    grew = True
        return found

    def _lost_ids(self) -> set[int]:
        """Frames placed, or being placed, without an anchor: finalised unanchored ones and
        pending ones that had neither a tracker sample nor a pair to a frame not lost."""
        return self._unanchored | {p["id"] for p in self._pending
                                   if not p.get("anchored", True)}

    def _held_tail(self, final_step: bool, anchored: set[int] | None) -> int:
        """Index into the pending frames from which they stay free for the next step: the first
        prior-only frame followed by fewer than two frames with visual evidence (Sec. 4.2.3),
        or the first frame without an anchor (`anchored`: the step's anchored frames) followed
        by fewer than two anchored frames, within hold_unanchored_frames of the newest.

        Two on the far side, not one: one anchored frame fixes the lost stretch's far end but
        not its velocity there (the C_p term of the frame after it comes in a later step), so
        with one step per frame (PHB preset, chi_e = 1) the stretch was fixed as soon as the
        first anchored frame came and bent away from the motion (review 51, 300 px SYN, 6
        black frames in a 12-frame tracker gap: black e_j mean / worst 21.2 / 31.6 px -> 4.7 /
        6.7, as with the SYN preset, 4.8 / 6.8, whose 3-frame steps held two anchored frames
        already; 250 px, 8 black: 11.6 / 17.8 -> 2.0 / 3.0). They are final one step later when
        the first anchored frame ends its step: one frame with chi_e = 1."""
        n = len(self._pending)
        if final_step:
            return n
        o = self.options
        newest = self._pending[-1]["id"] if self._pending else 0
        for i, p in enumerate(self._pending):
            if (not p["visual"] and p["held"] < o.hold_prior_only_steps
                    and sum(q["visual"] for q in self._pending[i + 1:]) < 2):
                return i
            if (anchored is not None and p["id"] not in anchored
                    and newest - p["id"] < o.hold_unanchored_frames
                    and sum(q["id"] in anchored for q in self._pending[i + 1:]) < 2):
                return i
        return n

    def _finalize(self, ids, poses, gated, solve_per_frame, keyframe_per_frame,
                  final_step: bool = False, anchored: set[int] | None = None,
                  failed: set[int] | frozenset = frozenset()) -> None:
        """Hands out the pending frames before the held tail (_held_tail) as final. `failed`:
        frames whose step Ceres could not solve (FAILURE, also after _recover_failed_step):
        finalised at their starting poses as "prior-only (solver failed)", and, like frames
        without an anchor, never keyframes, loop frames or anchors of later frames."""
        forget: list[int] = []
        cut = self._held_tail(final_step, anchored)
        held = self._pending[cut:]
        for p, pose in zip(self._pending[:cut], poses[:cut], strict=True):
            k = p["id"]
            pose = np.asarray(pose)
            if p.get("sample") is not None:
                self._note_tracker_verdict(k, k in gated or bool(p["dropped"]))
            self._poses[k] = (pose, p["timestamp"])
            reference = pose if self._reference_pose is None else self._reference_pose
            try:
                G = _core.transfer_homography(reference, pose, self._plane, self.K)
            except ValueError:
                # the plane passes through the camera (or the reference's): a frame without
                # registered pairs the start-up's plane checks did not see, placed from its
                # priors alone (a 55 px field stop, live: crashed the run, nothing written)
                self._finalized.append(FrameResult(
                    k, p["timestamp"], np.full((3, 3), np.nan),
                    poses_from_aligned(pose, self._world),
                    "unplaced: the estimated plane passes through its camera centre", True,
                    k in gated or p["dropped"], p["timings"], self.plane,
                    tracker_dropped=p["dropped"]))
                # forgotten by _forget_orphans; no anchor for later frames meanwhile (its pose
                # is on the plane: a pair to it cannot be evaluated)
                self._orphans = self._orphans | {k}
                self._unanchored = self._unanchored | {k}
                continue
            if self._reference_pose is None:
                self._reference_pose, self._reference_id = reference, k
            centroid = self._centroid(G)
            # (KeyframeIndex.add skips a centroid that is not finite: an outline point that G
            # sends to infinity; stored, it made every later K-means raise; review. Such a frame
            # belongs to no block, which is how frames leave the window: it is forgotten as an
            # orphan once nothing uses it, else it stayed to the end; review Z)
            forget += self.keyframes.add(k, centroid)
            if not np.isfinite(centroid).all():
                self._orphans = self._orphans | {k}
            dead_reckoned = anchored is not None and k not in anchored
            solver_failed = k in failed
            if dead_reckoned or solver_failed:
                self._unanchored = self._unanchored | {k}
            elif (k % self.options.frames_per_cluster == self.options.frames_per_cluster // 2
                  and np.isfinite(centroid).all()):
                feats = p.pop("features", None)
                if feats is not None and len(feats):
                    self._loop_feats[k] = feats
                    self._loop_centroids[k] = centroid
                    self._loop_G[k] = G
            if not (dead_reckoned or solver_failed):
                self._recent_G[k] = G
            p["timings"]["window_solve"] = solve_per_frame
            p["timings"]["keyframe_selection"] = keyframe_per_frame
            status = (SOLVER_FAILED_STATUS if solver_failed else
                      "dead-reckoned" if dead_reckoned else
                      "placed" if p["visual"] else "prior-only")
            self._finalized.append(FrameResult(
                k, p["timestamp"], G, poses_from_aligned(pose, self._world), status,
                True, k in gated or p["dropped"], p["timings"], self.plane,
                tracker_dropped=p["dropped"],
                motion_released=p["motion_break"] or p.get("motion_gated", False)))
        for old in sorted(self._poses)[:-2]:
            del self._poses[old]  # keep only what the motion prediction needs
        if forget:
            self._unanchored = self._unanchored - set(forget)
            self._win_forget(forget)
            for i in forget:
                self._loop_feats.pop(i, None)
                self._loop_centroids.pop(i, None)
                self._loop_G.pop(i, None)
        for p in held:
            p["held"] += 1
        self._pending = held
        self._forget_orphans()

    @property
    def tracker_episode(self) -> TrackerEpisode | None:
        """The first stretch of final frames where most tracker samples were gated or dropped
        (tracker_warning words it), or None."""
        return self._tracker_episode

    def _note_tracker_verdict(self, k: int, bad: bool) -> None:
        """Final frame k's tracker sample was gated or dropped (`bad`) or not: the verdicts of
        the last TRACKER_WARNING_FRAMES, and the first stretch where most of them were bad
        (begun at the frame where that first held, ended at the last where it still did)."""
        self._tracker_verdicts.append((k, bad))
        count = _tracker_disagreement(self._tracker_verdicts)
        episode = self._tracker_episode
        if episode is None:
            if count is not None:
                self._tracker_episode = TrackerEpisode(
                    self._tracker_verdicts[0][0], k, *count, last=k, holds=True)
        elif episode.holds:  # (replaced, never mutated: the rollback copies it shallowly)
            self._tracker_episode = replace(
                episode, last=k if count is not None else episode.last, holds=count is not None)

    def _forget_orphans(self) -> None:
        """Forgets, in the C++ window, the frames handed out unplaced for a plane through
        their camera centre (_orphans) once nothing can use them: not pending, not among the
        recent frames new ones are matched against, not in the window Forget keeps, nor one
        of the two fixed predecessors of the first pending frame (its C_p)."""
        if not self._orphans:
            return
        frames = self._mirror_frames
        fixed = sorted(k for k, v in frames.items() if v[3])
        pending_cpp = len(frames) - len(fixed)
        keep = max(0, self.options.window_size - max(1, pending_cpp))
        protected = set(fixed[-keep:]) if keep else set()
        first = min((p["id"] for p in self._pending), default=None)
        if first is not None:
            protected |= set([k for k in fixed if k < first][-2:])
        protected |= {i for i, _ in self._recent} | {p["id"] for p in self._pending}
        gone = sorted(k for k in self._orphans if k not in protected)
        if gone:
            self._orphans = self._orphans - set(gone)
            self._unanchored = self._unanchored - set(gone)
            self._win_forget([k for k in gone if k in frames])

    def _to_reference(self, pose: np.ndarray) -> np.ndarray:
        return _core.transfer_homography(self._reference_pose, pose, self._plane, self.K)

    def _centroid(self, G: np.ndarray) -> np.ndarray:
        q = np.hstack([self._outline, np.ones((len(self._outline), 1))]) @ G.T
        return (q[:, :2] / q[:, 2:]).mean(axis=0)

    def _chain_startup(self, k: int, ok: list) -> None:
        """Start-up frame k's provisional homography: frame 0 is the reference; a later frame
        is chained through its registered pair with the most inliers to a chained frame."""
        if k == 0:
            self._startup_G[k] = np.eye(3)
            return
        chained = [m for m in ok if m.frame_m in self._startup_G]
        if chained:
            best = max(chained, key=lambda m: m.n_inliers)
            G = self._startup_G[best.frame_m] @ np.linalg.inv(best.H_lm)  # H_lm: old -> new
            self._startup_G[k] = G / G[2, 2]

    def _provisional(self, k, timestamp, tracker_pose, timings) -> FrameResult:
        """Frame k before its step: placed from its tracker pose (else the motion prediction)
        and the current plane. In the start-up, before any step: chained through its registered
        pairs to frame 0 (_chain_startup), else from its tracker pose, frame 0's and the
        start-up plane (the tracker's accuracy, tens of pixels: a live preview)."""
        pose = tracker_pose if tracker_pose is not None else self._predict_pose(timestamp)
        plane, reference = self._plane, self._reference_pose
        if plane is None and k in self._startup_G:
            reported = (np.full(6, np.nan) if pose is None
                        else poses_from_aligned(pose, self._world))
            return FrameResult(k, timestamp, self._startup_G[k].copy(), reported, "provisional",
                               False, timings=timings)
        if plane is None:
            first = self._pending[0] if self._pending else None
            plane = self._startup_plane
            reference = first["tracker"] if first is not None and first["id"] == 0 else None
        if pose is None or plane is None or reference is None:
            nan = np.full((3, 3), np.nan)
            return FrameResult(k, timestamp, nan, np.full(6, np.nan),
                               "unplaced: waiting for the first window step", False,
                               timings=timings)
        # (NaN: the plane passes through either camera, which transfer_homography refuses)
        G = _transfer_or_nan(reference, pose, plane, self.K)
        return FrameResult(k, timestamp, G, poses_from_aligned(pose, self._world),
                           "provisional", False, timings=timings)


def _transfer_or_nan(cam_l, cam_m, plane, K) -> np.ndarray:
    """transfer_homography, NaN where the plane passes through either camera centre (a
    prediction that has none; the homography was inf / NaN there for camera l)."""
    try:
        return _core.transfer_homography(cam_l, cam_m, plane, K)
    except ValueError:
        return np.full((3, 3), np.nan)


def _plane_gate_details(steps: list[tuple[float, bool]], sigma_v_px: float) -> dict:
    """Steps whose costs saw pi (a std, NaN without visual cost or with the gate disabled),
    how many of them the gate held, and the median relative std of the others, at the paper's
    sigma_v as the gate's limit (x SIGMA_V_START_PX / sigma_v_px, the window's sigma_v: see
    SequentialOptions.plane_max_relative_std)."""
    seen = [(std, held) for std, held in steps if not np.isnan(std)]
    kept = [std * SIGMA_V_START_PX / sigma_v_px for std, held in seen if not held]
    return {"steps_seeing_plane": len(seen), "held": sum(held for _, held in seen),
            "median_relative_std": float(np.median(kept)) if kept else None}


def observed_plane_std(mosaicker: SequentialMosaicker,
                       plane_steps: list[tuple[float, bool]] | None = None) -> float | None:
    """Whether the images observe the plane (consistency.MAX_PLANE_RELATIVE_STD): the median
    relative std of the window steps that measured it (plane_steps: every step's (std,
    held); default the mosaicker's step_summaries), else the start-up's (taken when the
    sequence ended or startup_wait_frames was reached); None when none was computed."""
    if plane_steps is None:
        plane_steps = [(s.plane_relative_std, s.plane_held) for s in mosaicker.step_summaries]
    std = _plane_gate_details(plane_steps, mosaicker.sigma_v_px)["median_relative_std"]
    if std is None:
        std = (mosaicker.bootstrap_summary or {}).get("plane_relative_std")
    return None if std is None or np.isnan(std) else float(std)


def live_solver_warnings(mosaicker: SequentialMosaicker,
                         frame_name: Callable[[int], int] | None = None) -> list[str]:
    """_solver_warnings of a streamed run, from the mosaicker's start-up summary and its kept
    step summaries (the last history_steps), and tracker_warning's (the offline run's
    tracker_agreement compares the whole run's poses with the recording's samples instead;
    frame_name: see tracker_warning)."""
    o = mosaicker.options
    steps = mosaicker.step_summaries
    unconverged = [s.termination for s in steps if solver_warning(s, o.max_iterations)]
    out = _solver_warnings(mosaicker.bootstrap_summary, unconverged, len(steps),
                           o.max_iterations, o.startup_max_iterations)
    tracker = tracker_warning(mosaicker, frame_name)
    return out + [tracker] if tracker else out


@dataclass(frozen=True)
class TrackerEpisode:
    """The first stretch of a run where most recent tracker samples were gated or dropped: at
    final frame `began` first, then `bad` of the `of` samples of the final frames `first` to
    `began` given one were; it last held at final frame `last`, and `holds` still (the run's
    last final frame)."""

    first: int
    began: int
    bad: int
    of: int
    last: int
    holds: bool


def _tracker_disagreement(verdicts) -> tuple[int, int] | None:
    """(bad, count) when more than TRACKER_WARNING_FRACTION of the (frame, bad) `verdicts` (at
    least TRACKER_WARNING_MIN of them) are bad, else None."""
    bad = sum(b for _, b in verdicts)
    if len(verdicts) < TRACKER_WARNING_MIN or not bad > TRACKER_WARNING_FRACTION * len(verdicts):
        return None
    return bad, len(verdicts)


def tracker_warning(mosaicker: SequentialMosaicker,
                    frame_name: Callable[[int], int] | None = None) -> str | None:
    """A warning when, at some final frame, more than TRACKER_WARNING_FRACTION of the last
    TRACKER_WARNING_FRAMES final frames given a tracker sample (at least TRACKER_WARNING_MIN of
    them) had it gated or dropped: the tracker disagrees with the images, as tracker_pose in
    another convention does once the start-up took it (frames then "placed" hundreds of px off
    with at most a solver warning before), a tracker noisier than emt_sigma says, or one
    distorted for a while (near metal). It names the first such stretch (where it began and
    ended) and says whether it held at the last final frame. frame_name: the mosaicker's frame
    number -> the frame's name in the messages (a live session's recorded frame), else itself."""
    episode = mosaicker.tracker_episode
    if episode is None:
        return None
    name = (lambda k: k) if frame_name is None else frame_name
    first, began, last = name(episode.first), name(episode.began), name(episode.last)
    at_first = f"{episode.bad} of the {episode.of} of frames {first}-{began}"
    gated = ("gated (down-weighted: they disagree with the images, gate_chi2) or dropped as "
             "glitches")
    now = _tracker_disagreement(mosaicker._tracker_verdicts)
    if now is not None:
        bad, count = now
        when = (f"have been since frame {began}" if episode.holds else
                f"were from frame {began} to frame {last} before")
        head = (f"{bad} of the last {count} tracker samples of final frames were {gated}, and "
                f"most {when} ({at_first}): the tracker disagrees")
    else:
        head = (f"from frame {began} to frame {last}, most tracker samples of final frames were "
                f"{gated} ({at_first} at first; no longer at the end): the tracker disagreed")
    return (head + " with the images by more than the EMT prior's noise. "
            + TRACKER_NOISE_ADVICE.format("emt_sigma; --tracker-rot-sigma / "
                                          "--tracker-trans-sigma")
            + "; tracker_pose is the camera's cam_from_world, [angle-axis r in rad, t in mm]")


def _solver_warnings(bootstrap, unconverged: list[str], steps: int, max_iterations: int,
                     startup_max_iterations: int) -> list[str]:
    """Messages for a start-up adjustment and window steps that did not converge."""
    out = ([solver_warning(bootstrap, startup_max_iterations, "the start-up adjustment",
                           knob="SequentialOptions.startup_max_iterations")]
           if bootstrap else [])
    if unconverged:
        kinds = ", ".join(sorted(set(unconverged)))
        out.append(f"{len(unconverged)} of {steps} window steps did not converge (Ceres "
                   f"{kinds}; max_iterations {max_iterations}): their frames' estimates are not "
                   "at the cost's minimum (a tracker disagreeing with the images is a common "
                   "cause)")
    return [w for w in out if w]


def run_lba_emt(dataset, *, progress: bool = True,
                options: SequentialOptions | None = None) -> MethodResult:
    """LBAVis+EMT over a recorded dataset, frame by frame through SequentialMosaicker."""
    o = options or SequentialOptions()
    n = len(dataset.frames)
    mosaicker = SequentialMosaicker(dataset.camera, o)
    results: dict[int, FrameResult] = {}
    latency = np.zeros(n)
    step_times: list[float] = []  # every step's (the mosaicker keeps the last history_steps)
    plane_steps: list[tuple[float, bool]] = []  # every step's (plane_relative_std, plane_held)
    unconverged: list[str] = []  # every step's solver message when it did not converge

    def take(finals: list[FrameResult]) -> None:
        """Results made final by the last call, and the time of its step (at most one)."""
        if mosaicker.num_steps > len(step_times):
            summary = mosaicker.last_step_summary  # (step_summaries may keep none)
            step_times.append(mosaicker.last_step_solve_s)  # (with its redo, if any)
            plane_steps.append((summary.plane_relative_std, summary.plane_held))
            if solver_warning(summary, o.max_iterations):
                unconverged.append(summary.termination)
        results.update({r.frame_id: r for r in finals})

    t_start = time.perf_counter()
    for k in tqdm(range(n), desc="lba-emt", disable=not progress, leave=False):
        image = dataset.frames[k]
        t0 = time.perf_counter()
        valid = dataset.pose_valid is not None and dataset.pose_valid[k]
        mosaicker.add_frame(image, float(dataset.timestamps[k]),
                            dataset.cam_from_world[k] if valid else None)
        latency[k] = time.perf_counter() - t0
        take(mosaicker.finalized())
    take(mosaicker.flush())
    total = time.perf_counter() - t_start
    G = np.stack([results[k].homography for k in range(n)])
    poses = np.stack([results[k].pose for k in range(n)])
    # "optimisation" is the window solve (incl. the bootstrap adjustment), as in the BA report
    stages = {"features": "features", "matching": "matching", "optimisation": "window_solve",
              "keyframe_selection": "keyframe_selection"}
    timings = {name: float(sum(results[k].timings.get(key, 0.0) for k in range(n)))
               for name, key in stages.items()}
    solve = np.array(step_times) if step_times else np.full(1, np.nan)
    c = mosaicker.pair_counts
    details = {
        "latency_ms": {"median": float(np.median(latency) * 1e3),
                       "p95": float(np.percentile(latency, 95) * 1e3),
                       "p99": float(np.percentile(latency, 99) * 1e3),
                       "frames_per_s": n / total},
        "window_step_ms": {"median": float(np.median(solve) * 1e3),
                           "p95": float(np.percentile(solve, 95) * 1e3),
                           "p99": float(np.percentile(solve, 99) * 1e3),
                           "steps": len(step_times)},
        "pairs": {"attempted": c["attempted"], "registered": c["registered"],
                  "mean_correspondences": c["correspondences"] / max(c["registered"], 1),
                  "loop_attempted": c["loop_attempted"],
                  "loop_registered": c["loop_registered"],
                  # registered pairs left out by the consistency check (pair_consistency_fraction)
                  "inconsistent": c["inconsistent"]},
        "tracker_gated": [k for k in range(n) if results[k].tracker_gated],
        "tracker_dropped": [k for k in range(n) if results[k].tracker_dropped],
        # C_p released by the motion gate (SequentialOptions.motion_gate_chi2)
        "motion_released": [k for k in range(n) if results[k].motion_released],
        # frames whose window step Ceres could not solve, left at their starting poses
        "solver_failed": [k for k in range(n) if results[k].status == SOLVER_FAILED_STATUS],
        # the plane observability gate (SequentialOptions.plane_max_relative_std)
        "plane_gate": _plane_gate_details(plane_steps, mosaicker.sigma_v_px),
        # per frame: the plane of the step that made the frame final
        # (None for a frame handed out before any plane: dropped from a waiting start-up)
        "plane_history": [None if results[k].plane is None else
                          np.asarray(results[k].plane).tolist() for k in range(n)],
    }
    details["plane_relative_std"] = observed_plane_std(mosaicker, plane_steps)
    details["warnings"] = _solver_warnings(mosaicker.bootstrap_summary, unconverged,
                                           len(step_times), o.max_iterations,
                                           o.startup_max_iterations)
    agreement = mosaicker.visual_agreement(source=str(getattr(dataset, "root", "the frames")))
    details["warnings"] += agreement.pop("warnings")
    details["visual_agreement"] = agreement
    details["visual_sigma"] = mosaicker.visual_sigma
    if dataset.cam_from_world is not None:
        add_tracker_agreement(details, poses, dataset, mosaicker.plane, o.emt_sigma,
                              o.motion_sigma)
    status = [results[k].status for k in range(n)]
    return MethodResult(G, status, poses=poses, plane=mosaicker.plane, timings=timings,
                        parameters=asdict(o), details=details)
