"""Robot-prior Kalman filter for online pCLE topology inference (Rosa et al. 2018, paper 004).

Per frame i the filter fuses two estimates of the displacement since frame i-1, independently
for x and y (Sec. II-A):

- the robot's ``dX_r(i) = V_r(i) T_s`` (the prior, Eq. 4), with variance
  ``sigma_rob^2 = sigma_r0^2 / c_rob`` (Eq. 9);
- the image registration ``dX_{i-1}^i`` (the likelihood, Eq. 5), with variance
  ``sigma_img^2 = sigma_i0^2 / c_img`` (Eq. 10);

by the product of the two Gaussians (Eqs. 6-8). The confidences come from the smoothness of the
image displacement's direction and norm (``c_angle``, ``c_speed``, Eqs. 11-15), the structural
similarity of the aligned frames (``c_match``, Sec. II-C), their geometric mean ``c_img``
(Eq. 16), the robot/image speed agreement ``c_sp`` (Eq. 17) and ``c_rob`` (Eq. 18).

Units: displacements are in pixels of the image axes (x right, y down), the robot's already
converted to pixels by the caller (robot positions interpolated at the frame times, then
differenced). Angles are in radians. Positions are relative to frame 0 (Eq. 3).

Reading choices where the paper leaves room (all configurable in :class:`KalmanOptions`):

- Eq. 13-14: ``normalize`` decreases, so it is applied to the absolute deviation. The angle
  deviation ``alpha(i) - f(h_alpha)`` is wrapped to (-pi, pi] before taking its absolute value,
  and the angle history is unwrapped (``numpy.unwrap``) before filtering so that a trajectory
  crossing +-pi (a circle, a spiral) stays smooth.
- The history ``h(i, n) = [x(i-n), ..., x(i)]`` holds the n preceding values and the current
  one, as Eq. 13-14 write it, and ``f`` (median filter, then a 3rd-order least-squares
  polynomial) is read at i. The median filter mirrors the sequence at its end, so an outlier at
  i is removed from its own reference (the text's "n time-steps directly preceding i" reading,
  with ``f`` extrapolated one step, is ``include_current=False``; it is about twice as noisy).
  The cost: the mirrored end lags a steady trend by ~0.9 step (a ramp 0..10 gives 9.13), so a
  smooth turn of w rad/frame reads as a deviation of ~0.87 w (c_angle 0.91 at 0.3 rad/frame,
  0.64 at 0.5). A median of the residuals about a least-squares line (the line added back) has
  no lag, but the line follows an outlier at i, which then pulls its own reference (c_speed of
  a speed doubling 0.50 -> 0.61, c_angle of a 0.7 rad turn 0.13 -> 0.22), and on the
  simulator's circle / spiral it made #3 worse (10.2 -> 12.8 / 10.8 -> 13.5 µm at the paper's
  n frames) and flagged fewer event frames (c_img < 0.5: 53 -> 50 % / 60 -> 56 %): not used.
  Histories keep the last n *valid* samples with their step indices (failed registrations are
  skipped; a caller adds one it left out of the fusion with ``RobotKalmanFilter.record``) and
  the angle history skips displacements too short to have a direction.
- Eq. 14 compares N(i) with f(h_N) scale-free, as Eq. 17 compares the image and robot speeds:
  deviation ``1 - min(N', f') / max(N', f')`` (``N' = N + speed_floor``), so one ``(k, x_r)``
  works across scanning speeds and a stop is as unusual as a jump (the relative deviation
  ``|N - f| / f``, ``speed_deviation="relative"``, caps a stop at 1, a mere doubling). It is
  bounded, so c_speed >= normalize(1) ~ 0.002 and c_img (Eq. 16) >= ~0.13 (c_angle c_match)^(1/3):
  at a stick-slip release (Sec. III-C) a correct registration (high c_match, consistent
  direction) keeps c_img ~0.1-0.4, flagged (< 0.5) but still the better estimate of the jump
  than the robot increment, which never contains the catch-up of the lag.
- Still displacements (< ``angle_min_norm``) stay out of both histories
  (``speed_history_skips_still``), so a stuck image keeps a low c_speed for the whole stick.
- Eq. 17: ``r = min(n_I/n_r, n_r/n_I)`` is 1 when the speeds agree, and ``normalize`` decreases,
  so ``c_sp = normalize(1 - r)``: high for agreement, as the text below Eq. 17 requires ("tend
  to 1 if both displacements get close"). ``speed_floor`` is added to both norms so two
  near-zero displacements count as agreeing.
- Until the history holds ``min_history`` values the confidences cannot be computed; the
  initial values ``c_rob(0) = 10`` and ``c_img(0) = 1`` (Sec. II-B) are used. Note that with
  Eq. 9-10 taken literally and equal ``sigma_r0 = sigma_i0`` this favours the *robot* 10:1,
  whereas the paper's prose says it relies more on the image at the start; set ``c_rob0 < 1``
  (or ``sigma_robot0 > sqrt(10) sigma_image0``) to follow the prose.
- ``c_angle`` is undefined for a displacement shorter than ``angle_min_norm`` (its direction is
  noise, e.g. a stuck probe): it is reported as NaN and counts as 1 in Eq. 16 (``c_speed``
  already judges such a step), and such directions are kept out of the angle history.
- A missing image displacement (NaN, e.g. a featureless frame) sets ``c_img = 0`` (follow the
  robot); a missing robot displacement sets ``c_rob = 0`` (follow the image).
- The paper's frames come at a constant rate (T_s, Eq. 3). A live stream drops frames: the
  step after a drop spans ``intervals`` > 1 frame intervals (``update(..., intervals=2)``, as
  RobotPriorMosaicker gives from the timestamps), and its norm divided by that is what Eq. 14
  judges and the speed history keeps (a correct 2-interval step, 77 px against 40 px steps,
  had c_speed 0.55 and c_img 0.46 < 0.5: untrusted; review). With ``intervals = 1`` (evenly
  spaced frames) nothing changes. The angle (Eq. 11) and Eq. 17, which compares two
  displacements over the same time, are unchanged.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from scipy import ndimage
from scipy.special import erf

__all__ = [
    "KalmanOptions",
    "FilterStep",
    "FilterTrajectory",
    "RobotKalmanFilter",
    "normalize",
    "smoothed_prediction",
    "angle_confidence",
    "speed_confidence",
    "speed_agreement_confidence",
    "image_confidence",
    "robot_confidence",
    "fuse_gaussians",
    "filter_trajectory",
    "integrate_displacements",
]


def normalize(x, k: float, x_r: float):
    """Eq. 15: ``(1 - erf(k (x - x_r))) / 2``, decreasing from ~1 to ~0, 0.5 at ``x = x_r``.

    ``k`` sets the slope (the transition spans about ``x_r +- 2/k``). Works on scalars and arrays.
    """
    out = 0.5 * (1.0 - erf(k * (np.asarray(x, dtype=np.float64) - x_r)))
    return float(out) if np.ndim(out) == 0 else out


@dataclass(frozen=True)
class KalmanOptions:
    """Parameters of :class:`RobotKalmanFilter`. The paper gives no numeric values except
    ``c_rob0``, ``c_img0`` and the polynomial order; the rest are chosen so that a confidence is
    ~1 for smooth motion and ~0 for a clear outlier (see the module docstring)."""

    # Eq. 9-10 base standard deviations of the robot and image displacements, px per frame
    # (sigma_robot0 = inf: the robot's noise is unknown, the prior carries no information).
    sigma_robot0: float = 1.0
    sigma_image0: float = 1.0
    # Initial confidences, Sec. II-B: c_rob(0) = 10, c_img(0) = 1.
    c_rob0: float = 10.0
    c_img0: float = 1.0
    # Eq. 13-14 history length n (paper: no value; ~1 s at the pCLE's 9-12 Hz).
    history_length: int = 10
    # Fewest past values for which confidences are computed (needs > poly_degree).
    min_history: int = 6
    # True: h(i, n) = [x(i-n), ..., x(i)] includes the current value (Eq. 13-14 as written) and
    # f is the smoothed value at i. False: only the n preceding values, f extrapolated to i
    # (noisier: a cubic extrapolated one step amplifies noise ~2x at n = 10).
    include_current: bool = True
    # f(.) of Eq. 13-14: median filter (odd kernel, removes isolated peaks) ...
    median_kernel: int = 5
    # ... then a 3rd-order polynomial fit, Sec. II-C.
    poly_degree: int = 3
    # c_angle = normalize(|wrap(alpha - f(h_alpha))|, k, x_r): 0.5 at 0.5 rad (~29 deg).
    angle_k: float = 4.0  # 1/rad
    angle_x_r: float = 0.5  # rad
    # Displacements shorter than this (px/frame) have no usable direction: no c_angle, and
    # they are left out of the angle history.
    angle_min_norm: float = 0.25
    # c_speed = normalize(1 - min(N', f') / max(N', f'), k, x_r) (speed_deviation="ratio"):
    # 0.5 when the speed halves or doubles, ~0.002 for a stop or an unbounded jump (never 0:
    # a speed change alone cannot veto a registration that c_match and c_angle accept).
    speed_k: float = 4.0
    speed_x_r: float = 0.5
    # "ratio" (above), "relative" |N - f| / max(f, speed_floor) (0.5 at a 50 % change; a stop
    # counts like a doubling) or "absolute" |N - f| in px/frame (then set speed_x_r in px).
    speed_deviation: str = "ratio"
    # Keep displacements shorter than angle_min_norm (a still image) out of the speed history,
    # as they are kept out of the angle history: a still image while the scan goes on
    # (stick-slip, Sec. III-C) stays unusual for as long as it lasts instead of becoming the
    # reference after median_kernel // 2 frames. A deliberate stop is unaffected in effect:
    # the robot stops too, so both estimates say ~0.
    speed_history_skips_still: bool = True
    # px/frame; guards the relative speed and the Eq. 17 ratio against near-zero norms.
    speed_floor: float = 0.25
    # c_sp = normalize(1 - min(n_I/n_r, n_r/n_I), k, x_r): 0.5 when one norm is half the other.
    sp_k: float = 4.0
    sp_x_r: float = 0.5
    # False: Eqs. 7-8 as written (the state variance is not carried over).
    # True: the state variance carried over, a Kalman-filter form compared in
    # bench/bench_pcle_cases.py; not the optimal update for these relative measurements (it
    # over-weights the image), see RobotKalmanFilter.
    propagate_variance: bool = False
    # Variance of X_f(0) for propagate_variance=True, px^2 (frame 0 defines the origin).
    initial_variance: float = 0.0

    def __post_init__(self) -> None:
        if not self.sigma_robot0 > 0:  # inf allowed: robot noise unknown, no robot information
            raise ValueError(f"KalmanOptions.sigma_robot0 must be > 0, got {self.sigma_robot0}")
        positive = ("sigma_image0", "angle_k", "speed_k", "sp_k")
        for name in positive:
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"KalmanOptions.{name} must be a finite number > 0, got {value}")
        for name in ("c_rob0", "c_img0", "speed_floor", "angle_min_norm", "initial_variance"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"KalmanOptions.{name} must be a finite number >= 0, got {value}")
        # The Eq. 15 levels x_r: where a confidence is 0.5. Not finite, a confidence is NaN or
        # constant and silently drops out (angle_x_r NaN: c_angle NaN, counted as 1 in Eq. 16;
        # speed_x_r NaN: c_img NaN, every registration ignored; sp_x_r inf: c_rob always 1).
        # Each must lie inside its deviation's range: beyond it the confidence never falls to
        # 0.5 (the check is off), at or below 0 it never rises above 0.5.
        upper = {
            "angle_x_r": (np.pi, "rad: |wrapped angle deviation| <= pi"),
            "sp_x_r": (1.0, "Eq. 17's 1 - min(n_I/n_r, n_r/n_I) < 1"),
            "speed_x_r": (1.0, "speed_deviation='ratio': 1 - min(N', f') / max(N', f') < 1")
            if self.speed_deviation == "ratio" else (np.inf, f"speed_deviation="
                                                     f"{self.speed_deviation!r}"),
        }
        for name, (high, why) in upper.items():
            value = getattr(self, name)
            if not (np.isfinite(value) and 0.0 < value < high):
                bound = "a finite number > 0" if high == np.inf else f"in (0, {high:.4g})"
                raise ValueError(f"KalmanOptions.{name} must be {bound} ({why}), got {value}")
        if self.c_rob0 == 0 and self.c_img0 == 0:
            raise ValueError("KalmanOptions: c_rob0 and c_img0 cannot both be 0")
        if self.speed_deviation not in ("ratio", "relative", "absolute"):
            raise ValueError(
                "KalmanOptions.speed_deviation must be 'ratio', 'relative' or 'absolute', got "
                f"{self.speed_deviation!r}"
            )
        if self.poly_degree < 0:
            raise ValueError(f"KalmanOptions.poly_degree must be >= 0, got {self.poly_degree}")
        if self.median_kernel < 1 or self.median_kernel % 2 == 0:
            raise ValueError(
                f"KalmanOptions.median_kernel must be a positive odd integer, "
                f"got {self.median_kernel}"
            )
        if not self.poly_degree < self.min_history <= self.history_length:
            raise ValueError(
                f"KalmanOptions: need poly_degree < min_history <= history_length, got "
                f"poly_degree={self.poly_degree}, min_history={self.min_history}, "
                f"history_length={self.history_length}"
            )


@lru_cache(maxsize=256)
def _extrapolation_weights(offsets: tuple[int, ...], degree: int) -> np.ndarray:
    """Weights w with ``w @ h`` = least-squares polynomial of ``degree`` through samples ``h``
    taken at integer step ``offsets`` (<= 0) relative to the current step, evaluated at 0. Same
    value as ``numpy.polynomial.Polynomial.fit(offsets, h, degree)(0)``, computed once per
    pattern of offsets (in a steady stream there is one pattern)."""
    t = np.asarray(offsets, dtype=np.float64)
    t = t / max(1.0, float(-t.min()))  # scaled to [-1, 0] for conditioning
    vander = np.polynomial.polynomial.polyvander(t, degree)
    weights = np.linalg.pinv(vander)[0]  # coefficient of t^0 = value at t = 0
    weights.setflags(write=False)
    return weights


def smoothed_prediction(
    history, offsets=None, *, median_kernel: int = 5, poly_degree: int = 3
) -> float:
    """The low-pass operator ``f(h)`` of Eq. 13-14, evaluated at the current step.

    ``history`` holds values oldest first; ``offsets`` their step offsets from the current step
    (increasing integers <= 0), by default ``-len(history)+1, ..., 0``: the last sample is the
    current step, the paper's ``h(i, n) = [x(i-n), ..., x(i)]``. A median filter of
    ``median_kernel`` samples (``scipy.ndimage.median_filter``, mirrored edges, so a peak in the
    last sample is removed too) suppresses isolated peaks, then a least-squares polynomial of
    ``poly_degree`` (3 in the paper) is evaluated at offset 0 (an extrapolation when the history
    stops before the current step).
    """
    h = np.asarray(history, dtype=np.float64)
    if h.ndim != 1 or h.size <= poly_degree:
        raise ValueError(
            f"smoothed_prediction: need a 1-D history longer than poly_degree={poly_degree}, "
            f"got shape {h.shape}"
        )
    if offsets is None:
        offsets = tuple(range(-h.size + 1, 1))
    else:
        offsets = tuple(int(o) for o in offsets)
        if (
            len(offsets) != h.size
            or offsets[-1] > 0
            or any(b <= a for a, b in zip(offsets[:-1], offsets[1:], strict=True))
        ):
            raise ValueError(
                f"smoothed_prediction: offsets must be {h.size} increasing step offsets <= 0, "
                f"got {offsets}"
            )
    if median_kernel > 1 and h.size > 1:
        h = ndimage.median_filter(h, size=min(median_kernel, 2 * h.size - 1), mode="mirror")
    return float(_extrapolation_weights(offsets, poly_degree) @ h)


def _wrap_angle(a: float) -> float:
    """Wrap to (-pi, pi]."""
    w = float(np.mod(a + np.pi, 2.0 * np.pi) - np.pi)
    return np.pi if w == -np.pi else w


def angle_confidence(
    alpha: float,
    alpha_history,
    offsets=None,
    *,
    k: float = 4.0,
    x_r: float = 0.5,
    median_kernel: int = 5,
    poly_degree: int = 3,
) -> float:
    """Eq. 13: ``normalize(|wrap(alpha - f(unwrap(h_alpha)))|)``, angles in radians.

    ``offsets``: step offsets of the history samples, see :func:`smoothed_prediction`."""
    reference = smoothed_prediction(
        np.unwrap(np.asarray(alpha_history, dtype=np.float64)),
        offsets,
        median_kernel=median_kernel,
        poly_degree=poly_degree,
    )
    return normalize(abs(_wrap_angle(alpha - reference)), k, x_r)


def speed_confidence(
    norm: float,
    norm_history,
    offsets=None,
    *,
    k: float = 4.0,
    x_r: float = 0.5,
    deviation: str = "ratio",
    floor: float = 0.25,
    median_kernel: int = 5,
    poly_degree: int = 3,
) -> float:
    """Eq. 14: ``normalize(deviation(N, f(h_N)))``. ``deviation``: ``"ratio"`` (default)
    ``1 - min(N', f') / max(N', f')`` with ``N' = N + floor``, ``f' = max(f, 0) + floor``;
    ``"relative"`` ``|N - f| / max(f, floor)``; ``"absolute"`` ``|N - f|`` (px/frame).

    ``offsets``: step offsets of the history samples, see :func:`smoothed_prediction`."""
    reference = smoothed_prediction(
        norm_history, offsets, median_kernel=median_kernel, poly_degree=poly_degree
    )
    if deviation == "ratio":
        # Eq. 17's comparison of two speeds applied to N(i) and f(h_N): 0 when equal, -> 1 when
        # one is much smaller, the same for a stop as for a jump (a speed change by a factor rho
        # either way gives 1 - 1/rho).
        a, b = norm + floor, max(reference, 0.0) + floor
        dev = 1.0 - min(a, b) / max(a, b)
    elif deviation == "relative":
        dev = abs(norm - reference) / max(reference, floor, np.finfo(np.float64).tiny)
    elif deviation == "absolute":
        dev = abs(norm - reference)
    else:
        raise ValueError(
            f"speed deviation must be 'ratio', 'relative' or 'absolute', got {deviation!r}"
        )
    return normalize(dev, k, x_r)


def speed_agreement_confidence(
    norm_image: float, norm_robot: float, *, k: float = 4.0, x_r: float = 0.5, floor: float = 0.25
) -> float:
    """Eq. 17 read as ``normalize(1 - min(n_I/n_r, n_r/n_I))``: ~1 when the image and robot
    displacement norms agree, ~0 when one is much smaller. ``floor`` (px/frame) is added to both
    norms (two still frames agree); both zero with ``floor = 0`` counts as agreement."""
    a, b = norm_image + floor, norm_robot + floor
    ratio = 1.0 if max(a, b) == 0.0 else min(a, b) / max(a, b)
    return normalize(1.0 - ratio, k, x_r)


def image_confidence(c_angle: float, c_speed: float, c_match: float) -> float:
    """Eq. 16: geometric mean of the three image confidences."""
    return float(np.cbrt(c_angle * c_speed * c_match))


def robot_confidence(c_sp: float, c_img: float) -> float:
    """Eq. 18: ``c_rob = c_sp c_img - c_img + 1``: 0 when the image is trusted (c_img = 1) and
    disagrees with the robot (c_sp = 0); 1 when they agree or the image is not trusted."""
    return c_sp * c_img - c_img + 1.0


def fuse_gaussians(
    mean_prior: np.ndarray, var_prior: float, mean_like: np.ndarray, var_like: float
) -> tuple[np.ndarray, float]:
    """Eqs. 7-8, product of two Gaussians; an infinite variance means "ignore this one"."""
    if np.isinf(var_prior) and np.isinf(var_like):
        raise ValueError("fuse_gaussians: both variances are infinite (no information)")
    if np.isinf(var_prior):
        return np.asarray(mean_like, dtype=np.float64), float(var_like)
    if np.isinf(var_like):
        return np.asarray(mean_prior, dtype=np.float64), float(var_prior)
    total = var_prior + var_like
    if total == 0.0:  # both exact: Eq. 7 is 0/0; take the midpoint
        return 0.5 * (np.asarray(mean_prior) + np.asarray(mean_like)), 0.0
    mean = (var_prior * np.asarray(mean_like) + var_like * np.asarray(mean_prior)) / total
    return mean, var_prior * var_like / total


@dataclass(frozen=True)
class FilterStep:
    """One :meth:`RobotKalmanFilter.update`.

    position : (2,) filtered position X_f(i) (px, relative to frame 0).
    displacement : (2,) X_f(i) - X_f(i-1).
    variance : (2,) state variance per axis: sigma_est^2 of Eq. 8, or the propagated P(i)
        (with ``propagate_variance``: not X_f's error variance, see RobotKalmanFilter).
    prior_variance, likelihood_variance : the robot and image variances used (Eq. 9-10;
        inf for a confidence of 0). With ``propagate_variance`` the prior one includes P(i-1).
    c_angle, c_speed, c_match, c_sp : the confidences (NaN when not computed: warm-up, missing
        input).
    c_img, c_rob : the confidences used for the variances (Eq. 16, 18 or the initial values).
    warmup : True while the initial confidences of Sec. II-B are in use.
    """

    position: np.ndarray
    displacement: np.ndarray
    variance: np.ndarray
    prior_variance: float
    likelihood_variance: float
    c_angle: float
    c_speed: float
    c_match: float
    c_img: float
    c_sp: float
    c_rob: float
    warmup: bool


def _as_vector2(value, name: str, step: int) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.shape != (2,):
        raise ValueError(f"step {step}: {name} must have shape (2,), got {v.shape}")
    if np.isinf(v).any():
        raise ValueError(f"step {step}: {name} is infinite: {v}")
    return v


@dataclass
class RobotKalmanFilter:
    """Streaming robot-prior filter (paper 004, Sec. II), one :meth:`update` per new frame.

    With ``options.propagate_variance = False`` (default, the paper as written) each step fuses

    - prior ``N(X_f(i-1) + dX_r(i), sigma_r0^2 / c_rob(i))`` (Eq. 4, 9) and
    - likelihood ``N(X_f(i-1) + dX(i), sigma_i0^2 / c_img(i))`` (Eq. 5, 10)

    by Eqs. 7-8; ``sigma_est^2`` is reported but not carried to the next step. Because both
    Gaussians are centred on the same X_f(i-1), this is also the exact Kalman mean for relative
    measurements (a two-state "stochastic cloning" filter gives the same X_f, with the position
    variance growing by sigma_est^2 per step).

    With ``propagate_variance = True`` the state variance is carried over, as a Kalman filter on
    the position would, the robot displacement as the control input and the image registration
    read as a position measurement in the mosaic (the "standard Kalman filter" variant the
    project compares in bench/bench_pcle_cases.py):

    - predict: ``x- = X_f(i-1) + dX_r(i)``, ``P- = P(i-1) + sigma_r0^2 / c_rob(i)``
    - measure: ``z = X_f(i-1) + dX(i)`` with ``R = sigma_i0^2 / c_img(i)``
    - update: ``K = P- / (P- + R)``, ``X_f(i) = x- + K (z - x-)``, ``P(i) = (1 - K) P-``,
      with ``P(0) = options.initial_variance``.

    This is *not* the optimal (or a consistent) Kalman update for these measurements: the prior
    mean and the "measurement" both contain X_f(i-1), hence the same error e(i-1), so the
    innovation ``z - x-`` is the difference of the two displacement noises, of variance
    ``Q + R`` (Q = sigma_r0^2 / c_rob), not ``P- + R``. The optimal weight of the image is
    ``Q / (Q + R)``, Eqs. 7-8, the default mode; with P carried over ``K > Q / (Q + R)``: the
    image is over-weighted, and the reported P(i) converges to a constant while the true
    position error is a random walk of the step errors. (Read as "registered against frame i-1
    as already placed", X_f(i-1) would be exact and P(i-1) should be 0; read as uncertain, z
    carries the same error: either way the carried-over P is not the state's.) Measured under
    the filter's own model (independent white displacement noise, 200 runs of 100 steps;
    review 51): with sigma_r0 = sigma_i0 = 1 px the step error variance is 0.535 against the
    optimal 0.500; with sigma_r0 = 0.1 px (an accurate robot at the online estimate's floor)
    and sigma_i0 = 1 px, 0.0169 against 0.0099 (+70 %), the error variance of X_f after 100
    steps 1.67 against 1.03, and the reported variance 0.098 against a true 1.67 (17x too
    small). A heuristic kept for that comparison, not a better filter: the default mode is the
    paper's, and the optimal one under that model. Both modes coincide on the first step when
    P(0) = 0.
    """

    options: KalmanOptions = field(default_factory=KalmanOptions)
    start: np.ndarray = field(default_factory=lambda: np.zeros(2))

    def __post_init__(self) -> None:
        if not isinstance(self.options, KalmanOptions):
            raise ValueError(f"options must be a KalmanOptions, got {type(self.options).__name__}")
        self.start = _as_vector2(self.start, "start", 0).copy()
        if np.isnan(self.start).any():
            raise ValueError(f"start must be finite, got {self.start}")
        self.reset()

    def reset(self) -> None:
        """Forget the history and go back to ``start`` (frame 0)."""
        n = self.options.history_length
        # (step, value) of the last n valid image displacements; the angle history skips
        # displacements shorter than angle_min_norm (their direction is noise).
        self._alpha: deque[tuple[int, float]] = deque(maxlen=n)
        self._norm: deque[tuple[int, float]] = deque(maxlen=n)
        self._position = self.start.copy()
        self._variance = np.full(2, self.options.initial_variance)
        self._step = 0

    def snapshot(self) -> tuple:
        """The state an update changes, for :meth:`restore` (the histories' entries are
        immutable tuples: copying the deques is enough; ~20x cheaper than copy.deepcopy)."""
        return (deque(self._alpha, self._alpha.maxlen), deque(self._norm, self._norm.maxlen),
                self._position.copy(), self._variance.copy(), self._step)

    def restore(self, snapshot: tuple) -> None:
        """Back to a :meth:`snapshot` of this filter."""
        alpha, norm, position, variance, self._step = snapshot
        self._alpha, self._norm = deque(alpha, alpha.maxlen), deque(norm, norm.maxlen)
        self._position, self._variance = position.copy(), variance.copy()

    @property
    def position(self) -> np.ndarray:
        """Current filtered position X_f (2,), a copy."""
        return self._position.copy()

    @property
    def step(self) -> int:
        """Number of updates so far (the index of the last frame placed)."""
        return self._step

    @property
    def warming_up(self) -> bool:
        """True while the next update with an image displacement uses the initial confidences
        of Sec. II-B (its FilterStep.warmup): the history holds fewer than min_history values."""
        return len(self._norm) < self.options.min_history

    def _history(
        self, stored: deque[tuple[int, float]], current: float, step: int
    ) -> tuple[list[int], list[float]]:
        """Offsets and values of h(i, n) for Eq. 13-14 (with the current value when
        ``include_current``)."""
        offsets = [s - step for s, _ in stored]
        values = [v for _, v in stored]
        if self.options.include_current:
            offsets.append(0)
            values.append(current)
        return offsets, values

    def record(self, dx_image, intervals: float = 1.0) -> None:
        """Add the image displacement of the last :meth:`update`'s step, made without it (a
        registration the caller left out), to the histories of Eq. 13-14, as that update would
        have (still ones left out with ``speed_history_skips_still``); nothing else changes."""
        opt = self.options
        step = self._step
        dx = _as_vector2(dx_image, "dx_image", step)
        if not np.isfinite(dx).all():
            return
        if not (np.isfinite(intervals) and intervals > 0):
            raise ValueError(f"intervals must be a number > 0, got {intervals}")
        norm = float(np.hypot(dx[0], dx[1]))
        if step == 0 or (self._norm and self._norm[-1][0] == step) or (
                opt.speed_history_skips_still and norm < opt.angle_min_norm):
            return  # (no step yet, its update had the image, or a still step)
        self._norm.append((step, norm / intervals))
        if norm >= opt.angle_min_norm:
            self._alpha.append((step, float(np.arctan2(dx[1], dx[0]))))

    def update(self, dx_image, dx_robot, c_match: float, intervals: float = 1.0) -> FilterStep:
        """Place the next frame.

        Parameters
        ----------
        dx_image : (2,) image registration dX_{i-1}^i in px (``register_ncc(...).dx``); NaN if
            the registration failed.
        dx_robot : (2,) robot displacement dX_r(i) = V_r(i) T_s in px, image axes; NaN if
            unavailable.
        c_match : SSIM of the aligned overlap in [0, 1] (``aligned_overlap_ssim``); ignored when
            ``dx_image`` is NaN.
        intervals : frame intervals the step spans (> 1 after a dropped frame, see the module
            docstring); the norm per interval enters Eq. 14 and the speed history.
        """
        opt = self.options
        step = self._step + 1
        dx_img = _as_vector2(dx_image, "dx_image", step)
        dx_rob = _as_vector2(dx_robot, "dx_robot", step)
        image_ok = bool(np.isfinite(dx_img).all())
        robot_ok = bool(np.isfinite(dx_rob).all())
        if not image_ok and not robot_ok:
            raise ValueError(
                f"step {step}: both dx_image and dx_robot are missing (NaN); cannot place the frame"
            )
        c_match = float(c_match)
        if not (np.isfinite(intervals) and intervals > 0):
            raise ValueError(f"step {step}: intervals must be a number > 0, got {intervals}")
        if image_ok and not 0.0 <= c_match <= 1.0:
            raise ValueError(f"step {step}: c_match must be in [0, 1], got {c_match}")

        nan = float("nan")
        c_angle = c_speed = c_sp = nan
        if image_ok:
            alpha = float(np.arctan2(dx_img[1], dx_img[0]))  # Eq. 11
            norm = float(np.hypot(dx_img[0], dx_img[1]))  # Eq. 12
            speed = norm / intervals  # per frame interval (norm itself at 1: x / 1.0 is x)
        warmup = len(self._norm) < opt.min_history
        if robot_ok and image_ok:
            c_sp = speed_agreement_confidence(
                norm, float(np.hypot(*dx_rob)), k=opt.sp_k, x_r=opt.sp_x_r, floor=opt.speed_floor
            )
        if not image_ok:
            c_img, c_rob = 0.0, 1.0
            warmup = False
        elif warmup:
            c_img, c_rob = opt.c_img0, opt.c_rob0
        else:
            smooth = {"median_kernel": opt.median_kernel, "poly_degree": opt.poly_degree}
            if norm >= opt.angle_min_norm and len(self._alpha) >= opt.min_history:
                offsets, values = self._history(self._alpha, alpha, step)
                c_angle = angle_confidence(
                    alpha, values, offsets, k=opt.angle_k, x_r=opt.angle_x_r, **smooth
                )
            offsets, values = self._history(self._norm, speed, step)
            c_speed = speed_confidence(
                speed,
                values,
                offsets,
                k=opt.speed_k,
                x_r=opt.speed_x_r,
                deviation=opt.speed_deviation,
                floor=opt.speed_floor,
                **smooth,
            )
            # An undefined c_angle (too short a displacement, or too few directions yet) is
            # uninformative: 1 in Eq. 16.
            c_img = image_confidence(1.0 if np.isnan(c_angle) else c_angle, c_speed, c_match)
            c_rob = robot_confidence(c_sp, c_img) if robot_ok else 0.0
        if not robot_ok:
            c_rob = 0.0
        if image_ok and not (opt.speed_history_skips_still and norm < opt.angle_min_norm):
            self._norm.append((step, speed))
            if norm >= opt.angle_min_norm:
                self._alpha.append((step, alpha))

        var_rob = opt.sigma_robot0**2 / c_rob if c_rob > 0 else np.inf  # Eq. 9
        var_img = opt.sigma_image0**2 / c_img if c_img > 0 else np.inf  # Eq. 10
        mu_prior = self._position + (dx_rob if robot_ok else 0.0)  # Eq. 4
        mu_like = self._position + (dx_img if image_ok else 0.0)  # Eq. 5
        previous = self._position
        if np.isinf(var_rob) and np.isinf(var_img):
            # Neither variance is finite: the image is missing or has c_img = 0, and the robot is
            # missing or its sigma_r0 is not known yet (e.g. the first frames blank). A robot
            # displacement, even of unknown noise, beats an image judged worthless; without one,
            # the image's is the only information left.
            position = mu_prior if robot_ok else mu_like
            variance = np.full(2, np.inf)
            prior_variance = float("inf")
        elif opt.propagate_variance:
            var_prior = self._variance + var_rob  # (2,), P- = P(i-1) + Q
            if np.isinf(var_img):
                position, variance = mu_prior, var_prior
            elif np.isinf(var_prior).any():  # no robot now, or no information carried over
                position, variance = mu_like, np.full(2, var_img)
            else:
                gain = var_prior / (var_prior + var_img)  # var_img > 0: sigma_image0 > 0
                position = mu_prior + gain * (mu_like - mu_prior)
                variance = (1.0 - gain) * var_prior
            prior_variance = float(var_prior[0])
        else:
            position, var_est = fuse_gaussians(mu_prior, var_rob, mu_like, var_img)  # Eq. 7-8
            variance = np.full(2, var_est)
            prior_variance = float(var_rob)
        self._position = np.asarray(position, dtype=np.float64).copy()
        self._variance = np.asarray(variance, dtype=np.float64).copy()
        self._step = step
        return FilterStep(
            position=self._position.copy(),
            displacement=self._position - previous,
            variance=self._variance.copy(),
            prior_variance=prior_variance,
            likelihood_variance=float(var_img),
            c_angle=c_angle,
            c_speed=c_speed,
            c_match=c_match if image_ok else nan,
            c_img=float(c_img),
            c_sp=c_sp,
            c_rob=float(c_rob),
            warmup=warmup,
        )


@dataclass(frozen=True)
class FilterTrajectory:
    """Result of :func:`filter_trajectory` for N displacements (N + 1 frames).

    positions : (N + 1, 2) X_f of frames 0..N, positions[0] = start (frame 0).
    variances : (N, 2) state variance after each step (frames 1..N).
    c_angle, c_speed, c_match, c_img, c_sp, c_rob : (N,) per-step confidences (NaN = not
        computed).
    warmup : (N,) bool, True where the initial confidences were used.
    """

    positions: np.ndarray
    variances: np.ndarray
    c_angle: np.ndarray
    c_speed: np.ndarray
    c_match: np.ndarray
    c_img: np.ndarray
    c_sp: np.ndarray
    c_rob: np.ndarray
    warmup: np.ndarray


def filter_trajectory(
    dx_images,
    dx_robots,
    c_match,
    options: KalmanOptions | None = None,
    *,
    start=(0.0, 0.0),
) -> FilterTrajectory:
    """Run :class:`RobotKalmanFilter` over a whole sequence.

    Parameters
    ----------
    dx_images : (N, 2) image registrations, row i-1 = dX between frames i-1 and i (px); NaN rows
        are failed registrations.
    dx_robots : (N, 2) robot displacements over the same frame pairs (px); NaN rows = missing.
    c_match : (N,) SSIM confidences in [0, 1].
    options : KalmanOptions, default paper settings.
    start : (2,) position of frame 0.
    """
    dx_images = np.asarray(dx_images, dtype=np.float64)
    dx_robots = np.asarray(dx_robots, dtype=np.float64)
    c_match = np.asarray(c_match, dtype=np.float64)
    if dx_images.ndim != 2 or dx_images.shape[1] != 2:
        raise ValueError(f"dx_images must have shape (N, 2), got {dx_images.shape}")
    n = dx_images.shape[0]
    if dx_robots.shape != (n, 2):
        raise ValueError(
            f"dx_robots must have shape ({n}, 2) like dx_images, got {dx_robots.shape}"
        )
    if c_match.shape != (n,):
        raise ValueError(f"c_match must have shape ({n},) like dx_images, got {c_match.shape}")
    kf = RobotKalmanFilter(options if options is not None else KalmanOptions(), np.asarray(start))
    positions = np.empty((n + 1, 2))
    positions[0] = kf.position
    variances = np.empty((n, 2))
    conf = {
        name: np.empty(n) for name in ("c_angle", "c_speed", "c_match", "c_img", "c_sp", "c_rob")
    }
    warmup = np.empty(n, dtype=bool)
    for i in range(n):
        s = kf.update(dx_images[i], dx_robots[i], c_match[i])
        positions[i + 1] = s.position
        variances[i] = s.variance
        for name, values in conf.items():
            values[i] = getattr(s, name)
        warmup[i] = s.warmup
    return FilterTrajectory(positions=positions, variances=variances, warmup=warmup, **conf)


def integrate_displacements(displacements, start=(0.0, 0.0)) -> np.ndarray:
    """Eq. 2-3: chain (N, 2) per-frame displacements into (N + 1, 2) positions from ``start``
    (X_m for image registrations, X_r for robot displacements). NaN rows propagate."""
    d = np.asarray(displacements, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 2:
        raise ValueError(f"displacements must have shape (N, 2), got {d.shape}")
    out = np.empty((d.shape[0] + 1, 2))
    out[0] = np.asarray(start, dtype=np.float64)
    out[1:] = out[0] + np.cumsum(d, axis=0)
    return out
