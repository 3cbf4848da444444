"""The constant-velocity motion prior's covariance (seed 000, Eq. 14-16 and Sec. 4.2).

The paper estimates Sigma_p "through an independent dataset with similar motion characteristics"
(Sec. 4.2) and lists its values in the appendix (Eq. 30, read as standard deviations by the C++
core). `estimate_motion_sigma` does that estimation: given a pose sequence (cam_from_world,
e.g. ground truth of a calibration recording, or a simulated sequence of the same kind), it
returns the per-component standard deviation of x_k - mu_p(x_{k-1}, x_{k-2}).
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial.transform import Rotation

from fusedmosaic import _core
from fusedmosaic.estimation.world import poses_to_aligned, tracked_world

# Appendix Eq. 30 (std devs: rad x3, mm x3), the default when no motion data is given.
PAPER_MOTION_SIGMA = np.array([0.0044, 0.0044, 0.0044, 15.2178, 15.2178, 15.2178])


# Frame intervals within this relative tolerance of each other and of the nominal interval
# count as evenly spaced (camera clock jitter): the prior is then exactly Eq. 16.
EVEN_SPACING_TOLERANCE = 0.01

# motion_timing breaks the constant-velocity prior when one interval of the triple is more than
# GAP_INTERVALS times the other (a pause: the velocity before it says nothing about the motion
# after it), or longer than MOTION_MAX_GAP_S (s) and GAP_INTERVALS nominal intervals (a pause
# spanning both). Measured on the 24-frame test scene with the tracker lost over a pause:
# extrapolating 8.5 x the last motion (0.3 s) placed every frame within 0.8 px, 13.5 x (0.5 s)
# up to 18 890 px off, 21 x (0.8 s) 156 893 px. The nominal bound keeps slow recordings
# (1 frame/s) linked.
GAP_INTERVALS = 8.0
MOTION_MAX_GAP_S = 1.0

# The motion gate (not in the paper): C_p does not link a frame whose tracker samples over
# k-2, k-1, k depart from constant velocity by more than MOTION_GATE_CHI2 (chi2(6)'s 0.999
# quantile, as the tracker gate), each component's variance raised by max(1, its median /
# CHI2_1_MEDIAN) over the samples (a tracker noisier than Sigma_EMT). See
# tracker_motion_departure and breaks_constant_velocity.
MOTION_GATE_CHI2 = 22.46
CHI2_6_MEDIAN = 5.348120627447  # scipy.stats.chi2.median(6), the tracker gate's scale
CHI2_1_MEDIAN = 0.454936423119572  # scipy.stats.chi2.median(1)

# motion_timing's answer for a broken prior: zero velocity (the frame starts at the preceding
# camera when it has no tracker sample), no C_p term (an infinite sigma_p).
RELEASED = (0.0, float("inf"))


def motion_timing(t_km2: float, t_km1: float, t_k: float, nominal: float | None,
                  max_gap_s: float | None = MOTION_MAX_GAP_S,
                  max_ratio: float | None = GAP_INTERVALS) -> tuple[float, float]:
    """Timing of the constant-velocity prior over frames k-2, k-1, k (not in the paper, whose
    frames are evenly spaced): (motion_ratio, motion_sigma_scale) for the C++ add_frame.

    ratio = d2 / d1 with d1 = t_{k-1} - t_{k-2}, d2 = t_k - t_{k-1}: the last motion is
    repeated ratio times (a dropped frame between k-1 and k: ratio 2). The prediction error then
    grows with the gaps: for a velocity driven by white noise (a Wiener process),
    Var(x_k - mu_p) is proportional to d2^2 (d2 + d1), so in units of the nominal interval T
    (the spacing Sigma_p was estimated at) sigma_p is scaled by
    sqrt((d2/T)^2 (d2/T + d1/T) / 2), 1 for d1 = d2 = T. Returns (1, 1) (Eq. 16 exactly) when a
    time or the nominal interval is unknown, the times do not increase, or the spacing is even
    within EVEN_SPACING_TOLERANCE; RELEASED, (0, inf): no prior, zero velocity, when d1 or d2
    is more than max_ratio times the other (None: never), or exceeds max_gap_s (seconds;
    None: never) and GAP_INTERVALS nominal intervals. Extrapolating across such a gap moved
    frames 1e3-1e5 px off: a tracker lost at frame 12 of a sequence paused for 60 s at frame 15
    had the last motion repeated 1500 times."""
    times = np.array([t_km2, t_km1, t_k], np.float64)
    if not np.isfinite(times).all():
        return 1.0, 1.0
    d1, d2 = times[1] - times[0], times[2] - times[1]
    if d1 <= 0 or d2 <= 0:
        return 1.0, 1.0
    known = nominal is not None and bool(np.isfinite(nominal) and nominal > 0)
    if (max_ratio is not None and max(d1, d2) > max_ratio * min(d1, d2)) or (
            max_gap_s is not None
            and max(d1, d2) > max(max_gap_s, GAP_INTERVALS * nominal if known else 0.0)):
        return RELEASED
    if not known:
        return 1.0, 1.0
    u1, u2 = d1 / nominal, d2 / nominal
    tol = EVEN_SPACING_TOLERANCE
    if abs(u1 - 1.0) <= tol and abs(u2 - 1.0) <= tol:
        return 1.0, 1.0
    ratio = d2 / d1
    # Floors (not from the model): poses are not exact, so closely spaced timestamps must not
    # make the prior far stiffer than at the nominal spacing (d2 -> 0), and a velocity from a
    # short d1 extrapolated far (large ratio) is weak. Frames repeated 1 ns apart, ba-emt: e_M
    # 2.1 px and no convergence without, 0.2 px with (10 iterations; now released, above).
    scale = max(float(np.sqrt(u2 * u2 * (u2 + u1) / 2.0)), ratio / 8.0, 0.25)
    return float(ratio), scale


def tracker_motion_departure(z_km2: np.ndarray, z_km1: np.ndarray, z_k: np.ndarray,
                             motion_sigma: np.ndarray, emt_sigma: np.ndarray,
                             timing: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """How far three tracker samples (cam_from_world, frames k-2, k-1, k) depart from constant
    velocity (not in the paper), whitened per component (6,): the C_p residual x_k - mu_p
    (Eq. 15-16) at the samples over its standard deviation there, sigma_p^2 s^2 plus the
    samples' own noise propagated, (1 + (1 + rho)^2 + rho^2) Sigma_EMT (rho, s: motion_timing's
    ratio and sigma scale; 6 Sigma_EMT for even spacing). Each squared is chi2(1) or less when
    the motion keeps within Sigma_p and the tracker's noise is Sigma_EMT."""
    raw, variance = departure_parts(z_km2, z_km1, z_k, motion_sigma, emt_sigma, timing)
    return raw / np.sqrt(variance)


def motion_departure_scale(history) -> np.ndarray:
    """Per component (6,): max(1, median of the squared departures in `history` (M, 6) /
    CHI2_1_MEDIAN), 1 with fewer than 3: a tracker noisier than Sigma_EMT raises the components
    its noise dominates, and only those."""
    if history is None or len(history) < 3:
        return np.ones(6)
    return np.maximum(1.0, np.median(np.asarray(history) ** 2, axis=0) / CHI2_1_MEDIAN)


# breaks_constant_velocity's explanations of a departure by bad samples: the frames left out,
# offsets from k, one or two of k-3 ... k+1 with one of k-2, k-1, k among them (else the
# triple k-2, k-1, k is kept); those after k once their samples are known (offline, or a
# frame judged again before its step). An explanation must also take away most of the
# departure: each triple of kept samples spanning a left-out one departs at most
# GLITCH_REMAINDER times as much as w_k (squared, at the variance of k-2, k-1, k): a turn or
# a jump of the motion departs alike over every triple across it (extrapolated from before
# it), only whitened by a larger variance where the samples are further apart; a +90 deg
# jump seen by a tracker 4x noisier than Sigma_EMT was "explained" by k-1 and k-2 left out
# (k-4, k-3, k: 11 against the gate's 22.5) without this.
GLITCH_SETS = ((-1,), (-2,), (0,), (-2, -1), (-3, -2), (-3, -1), (-1, 0), (-2, 0), (0, 1),
               (-1, 1), (-2, 1), (-3, 0))
GLITCH_REMAINDER = 1.0 / 3.0


def departure_parts(z_km2: np.ndarray, z_km1: np.ndarray, z_k: np.ndarray,
                    motion_sigma: np.ndarray, emt_sigma: np.ndarray,
                    timing: tuple[float, float] = (1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """tracker_motion_departure's raw C_p residual at the samples and its variance, (6,)
    each."""
    ratio, scale = timing
    raw, _ = _core.evaluate_constant_velocity(z_km2, z_km1, z_k, np.ones(6), ratio)
    variance = (np.asarray(motion_sigma, np.float64) * scale) ** 2 + (
        1.0 + (1.0 + ratio) ** 2 + ratio ** 2) * np.asarray(emt_sigma, np.float64) ** 2
    return np.asarray(raw), variance


def triple_departures(samples, times=None, nominal: float | None = None, *,
                      motion_sigma: np.ndarray, emt_sigma: np.ndarray,
                      max_gap_s: float | None = MOTION_MAX_GAP_S):
    """departure(a, b, c): the samples of frames a < b < c (`samples`: frame id ->
    cam_from_world, or an (N, 6) array with NaN rows where a frame has none) as
    (tracker_motion_departure, its variance before whitening), timed by motion_timing over
    their `times` (a mapping or sequence by frame id; None or a time missing: the frame ids,
    evenly spaced) and nominal interval (None: the triple's mean interval per frame); None
    where a sample is missing or the triple spans a pause (motion_timing releases it)."""
    def get(table, i):
        if table is None:
            return None
        if isinstance(table, dict):
            return table.get(i)
        return table[i] if 0 <= i < len(table) else None

    def departure(a: int, b: int, c: int) -> tuple[np.ndarray, np.ndarray] | None:
        z = [get(samples, i) for i in (a, b, c)]
        if any(v is None or not np.isfinite(v).all() for v in z):
            return None
        t = [get(times, i) for i in (a, b, c)]
        if all(v is not None and np.isfinite(v) for v in t):
            unit = nominal if nominal is not None else (t[2] - t[0]) / (c - a)
            timing = motion_timing(*t, unit, max_gap_s)
        else:
            timing = motion_timing(a, b, c, 1.0, None)
        if not np.isfinite(timing[1]):
            return None
        raw, variance = departure_parts(*z, motion_sigma, emt_sigma, timing)
        return raw / np.sqrt(variance), variance
    return departure


def motion_verdict(w_k: np.ndarray, k: int, departure, scale: np.ndarray,
                   gate_chi2: float = MOTION_GATE_CHI2) -> tuple[bool, frozenset[int]]:
    """(breaks, bad samples): whether frame k's departure w_k (tracker_motion_departure over k-2,
    k-1, k; each component divided by sqrt(scale) here) says the camera left constant velocity:
    its squared norm above gate_chi2, and not explained by bad samples. A sample off at frame j
    makes the triples ending at j, j + 1, j + 2 depart (d, -2 d, d when evenly spaced), two
    consecutive ones four triples; a turn between k-1 and k makes every triple across it depart,
    from the velocity before it. So for each GLITCH_SETS of frames left out, the triples of
    consecutive kept samples over k-5 ... k+3 that span one left out (`departure(a, b, c)`, see
    triple_departures; None: unknown, a sample missing, not yet given, or a pause between) must
    keep within the gate and depart at most GLITCH_REMAINDER times as much as w_k, every frame
    left out spanned by one known (samples on both sides pass it by; a spin from a sequence's
    first frame was "frame 0's sample off" without): then the departure is the samples' doing
    and C_p holds frame k. Nor does it break where no left-out set has a triple known (e.g. the
    first triples after a pause): a +20 deg glitch on a black frame just after a 2 s pause then
    released the next frame's C_p, and the frame followed its sample (lba-emt 76 px, 16 px with
    C_p). Frame k's own sample is left out only with a later one known: at k a bad sample and a
    turn look the same. Bad samples: the frames left out by the explanation found (empty when it
    breaks or none is needed)."""
    root = np.sqrt(scale)
    w = np.asarray(w_k) / root
    m2 = float(w @ w)
    if not m2 > gate_chi2:
        return False, frozenset()
    base = departure(k - 2, k - 1, k)
    judged = False
    single: dict[tuple[int, ...], bool] = {}
    found: frozenset[int] | None = None
    for left_out in GLITCH_SETS:
        out = {k + i for i in left_out}
        kept = [j for j in range(k - 5, k + 4) if j not in out]
        spanned: set[int] = set()
        explained = False
        for a, b, c in zip(kept, kept[1:], kept[2:], strict=False):
            if not any(a < j < c for j in out) or (d := departure(a, b, c)) is None:
                continue
            e = d[0] / root
            spanned |= {j for j in out if a < j < c}
            explained = float(e @ e) <= gate_chi2
            if explained and base is not None:
                e = e * np.sqrt(d[1] / base[1])  # at the variance of k-2, k-1, k
                explained = float(e @ e) <= GLITCH_REMAINDER * m2
            if not explained:
                break
        known = spanned == out
        judged |= known
        single[left_out] = known
        if known and explained and found is None:
            found = frozenset(out)
    if found is None:
        return judged, frozenset()
    # the samples are named bad only where each of k-2, k-1, k alone was put to the test
    # (a +20 deg glitch on the first frame after a pause, with no sample before it in reach,
    # was taken for its successor's: the one there to test)
    return False, found if all(single.get((i,), False) for i in (-2, -1, 0)) else frozenset()


def breaks_constant_velocity(w_k: np.ndarray, k: int, departure, scale: np.ndarray,
                             gate_chi2: float = MOTION_GATE_CHI2) -> bool:
    """motion_verdict's first answer: whether C_p should not link frame k."""
    return motion_verdict(w_k, k, departure, scale, gate_chi2)[0]


def tracker_motion_verdicts(samples: np.ndarray, times, motion_sigma: np.ndarray,
                            emt_sigma: np.ndarray, gate_chi2: float = MOTION_GATE_CHI2,
                            nominal: float | None = None,
                            max_gap_s: float | None = MOTION_MAX_GAP_S
                            ) -> tuple[list[int], list[int]]:
    """Offline (breaks, bad samples): the frames k whose tracker samples over k-2, k-1, k
    (rows of `samples`, NaN where a frame has none) break constant velocity, and the samples
    that explained other departures (motion_verdict over the sequence's `times`, None: evenly
    spaced, and nominal interval, each component scaled by the whole sequence's medians;
    triples across a pause, released, are not judged)."""
    samples = np.asarray(samples, np.float64)
    departure = triple_departures(samples, times, nominal, motion_sigma=motion_sigma,
                                  emt_sigma=emt_sigma, max_gap_s=max_gap_s)
    w = {k: d[0] for k in range(2, len(samples))
         if (d := departure(k - 2, k - 1, k)) is not None}
    if not w or not np.isfinite(gate_chi2):
        return [], []
    scale = motion_departure_scale(list(w.values()))
    verdicts = {k: motion_verdict(w[k], k, departure, scale, gate_chi2) for k in w}
    return ([k for k, (broken, _) in verdicts.items() if broken],
            sorted(set().union(*(bad for _, bad in verdicts.values()))))


def tracker_motion_breaks(samples: np.ndarray, times, motion_sigma: np.ndarray,
                          emt_sigma: np.ndarray, gate_chi2: float = MOTION_GATE_CHI2,
                          nominal: float | None = None,
                          max_gap_s: float | None = MOTION_MAX_GAP_S) -> list[int]:
    """tracker_motion_verdicts' breaks."""
    return tracker_motion_verdicts(samples, times, motion_sigma, emt_sigma, gate_chi2, nominal,
                                   max_gap_s)[0]


def predict_constant_velocity(pose_km2: np.ndarray, pose_km1: np.ndarray,
                              ratio: float = 1.0) -> np.ndarray:
    """mu_p of Eq. 16 with the last motion repeated `ratio` times (see motion_timing), as the
    C++ prior computes it: the motion's 6-vector scaled."""
    motion = np.asarray(_core.compose_poses(pose_km1, _core.invert_pose(pose_km2)), np.float64)
    return np.asarray(_core.compose_poses(motion * ratio, pose_km1))


def constant_velocity_residuals(poses: np.ndarray, frame_ids=None, *,
                                geodesic: bool = False) -> np.ndarray:
    """(M, 6) x_k - mu_p(x_{k-1}, x_{k-2}) with mu_p = T_{k-1} T_{k-2}^-1 T_{k-1} (Eq. 16), over
    the triples of consecutive finite rows; with frame_ids (N,), only triples of consecutive
    frame ids (k-2, k-1, k): across a gap, e.g. dropped frames, the step is not one frame's,
    and a second difference over s frames is ~s^2 times a frame's.

    The rotation part is the plain difference of angle-axis vectors (paper Eq. 20; the C++
    prior's too away from a rotation of pi, where it takes the prediction's angle-axis vector
    nearest the pose's: geometry/pose.h PoseDifference), or with ``geodesic`` the rotation
    from the prediction to the pose,
    log(R_k R_bar_k^T) as an angle-axis vector: the same to first order near the identity, but
    a difference of angle-axis vectors wraps by ~2 pi where the two rotations straddle a
    rotation of pi (r and -r' for two rotations 0.002 rad apart), and is distorted near it."""
    poses = np.asarray(poses, np.float64)
    if poses.ndim != 2 or poses.shape[1] != 6 or len(poses) < 3:
        raise ValueError(f"poses: expected shape (N >= 3, 6), got {poses.shape}")
    ids = None if frame_ids is None else np.asarray(frame_ids, np.int64)
    out = []
    for k in range(2, len(poses)):
        a, b, c = poses[k - 2], poses[k - 1], poses[k]
        if not (np.isfinite(a).all() and np.isfinite(b).all() and np.isfinite(c).all()):
            continue
        if ids is not None and not ids[k] - ids[k - 1] == ids[k - 1] - ids[k - 2] == 1:
            continue
        mu = np.asarray(_core.compose_poses(_core.compose_poses(b, _core.invert_pose(a)), b))
        residual = c - mu
        if geodesic:
            residual[:3] = (Rotation.from_rotvec(c[:3])
                            * Rotation.from_rotvec(mu[:3]).inv()).as_rotvec()
        out.append(residual)
    if not out:
        raise ValueError("poses: no three consecutive finite poses" if ids is None else
                         "poses: no three consecutive frames (ids k-2, k-1, k) with finite "
                         "poses")
    return np.array(out)


# Sigma_p's floor (rad, mm): a perfectly smooth recording must not give a zero deviation.
MOTION_SIGMA_FLOOR = (1e-4, 0.01)


def _motion_rms(poses: np.ndarray, frame_ids=None) -> np.ndarray:
    poses = np.asarray(poses, np.float64)
    if poses.ndim == 2 and poses.shape[1:] == (6,):
        poses = poses_to_aligned(poses, tracked_world(poses))
    r = constant_velocity_residuals(poses, frame_ids, geodesic=True)
    return np.sqrt(np.mean(r**2, axis=0))


def _floored(sigma: np.ndarray, floor: tuple[float, float]) -> np.ndarray:
    return np.concatenate([np.maximum(sigma[:3], floor[0]), np.maximum(sigma[3:], floor[1])])


def estimate_motion_sigma(poses: np.ndarray, *,
                          floor: tuple[float, float] = MOTION_SIGMA_FLOOR) -> np.ndarray:
    """Per-component RMS of the constant-velocity residual (6,), rotations then translations,
    floored at (rad, mm) so a perfectly smooth recording does not give a zero deviation. The
    residuals are taken in the world the pose methods work in (estimation/world.py), the
    rotation's as the geodesic log(R_k R_bar_k^T) (constant_velocity_residuals, geodesic): a
    difference of angle-axis vectors wraps by ~2 pi where the pose and its prediction straddle
    a rotation of pi, which the world's alignment cannot avoid once the camera turns by more
    than pi over the recording (a spin about the optical axis: rz 1.0 rad for 0.0025; review
    52). RMS, as Sigma_p is the residual's standard deviation (Eq. 14), not a robust scale:
    the recording should hold the motion to be mosaicked, not outliers."""
    return _floored(_motion_rms(poses), floor)


def motion_sigma_from_recording(path) -> np.ndarray:
    """Sigma_p estimated from an independent recording with reference poses (Sec. 4.2): a file
    or a dataset folder holding truth_poses.csv (frame,rx,ry,rz,tx,ty,tz, cam_from_world), e.g.
    a calibration recording with an optical tracker, or a simulated sequence of the same kind.
    Tracker poses are not used: their noise (Sigma_EMT) would dominate the second differences."""
    from pathlib import Path

    from fusedmosaic.io import read_poses_csv

    path = Path(path)
    csv = path / "truth_poses.csv" if path.is_dir() else path
    if not csv.is_file():
        raise ValueError(f"{csv}: no reference poses to estimate the motion prior from "
                         "(expected truth_poses.csv: frame,rx,ry,rz,tx,ty,tz)")
    ids, poses = read_poses_csv(csv)
    order = np.argsort(ids, kind="stable")  # the rows in frame order, whatever the file's
    try:
        rms = _motion_rms(poses[order], ids[order])
    except ValueError as e:
        raise ValueError(f"{csv}: {e}") from None
    sigma = _floored(rms, MOTION_SIGMA_FLOOR)
    if (rms[3:] < MOTION_SIGMA_FLOOR[1]).all():  # e.g. a still recording. (A constant
        # rotation alone, as SYN's, is a motion the prior should hold stiffly: not said.)
        warnings.warn(
            f"{csv}: the camera's translations depart from constant velocity by at most "
            f"{rms[3:].max():.2g} mm RMS per frame (a still or perfectly smooth recording), so "
            f"Sigma_p's translations are floored at {MOTION_SIGMA_FLOOR[1]:g} mm and the motion "
            "prior will be stiff; estimate it from a recording of the motion to be mosaicked",
            stacklevel=2)
    return sigma
