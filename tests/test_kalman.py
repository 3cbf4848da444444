"""Robot-prior Kalman filter and its confidences (paper 004, Sec. II, Eqs. 1-18)."""

import numpy as np
import pytest
from numpy.polynomial import Polynomial
from scipy import ndimage
from scipy.special import erf

from fusedmosaic.estimation.kalman import (
    FilterStep,
    KalmanOptions,
    RobotKalmanFilter,
    angle_confidence,
    filter_trajectory,
    fuse_gaussians,
    image_confidence,
    integrate_displacements,
    normalize,
    robot_confidence,
    smoothed_prediction,
    speed_agreement_confidence,
    speed_confidence,
)


def circle_displacements(n, radius=80.0, period=120, noise=0.05, seed=0):
    """Per-frame displacements of a circular scan (crosses the +-pi direction twice per turn)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n + 1)
    pos = radius * np.stack([np.cos(2 * np.pi * t / period), np.sin(2 * np.pi * t / period)], 1)
    d = np.diff(pos, axis=0)
    return d, d + rng.normal(0.0, noise, d.shape)


# --- normalize (Eq. 15) -----------------------------------------------------------------------


def test_normalize_orientation_and_values():
    assert normalize(0.7, 3.0, 0.7) == pytest.approx(0.5)
    assert normalize(0.7 + 1 / 3.0, 3.0, 0.7) == pytest.approx((1 - erf(1.0)) / 2)
    xs = np.linspace(0.0, 2.0, 50)
    ys = normalize(xs, 4.0, 1.0)
    assert isinstance(ys, np.ndarray) and ys.shape == (50,)
    assert np.all(np.diff(ys) < 0)  # decreasing: small deviation = high confidence
    assert ys[0] > 0.999 and ys[-1] < 1e-3
    assert isinstance(normalize(0.1, 4.0, 0.5), float)


# --- f(.) and the image confidences (Eq. 11-16) ------------------------------------------------


def test_smoothed_prediction_is_median_then_cubic_fit():
    rng = np.random.default_rng(1)
    h = np.cumsum(rng.normal(1.0, 0.3, 11))
    offsets = np.arange(-10, 1)
    expected = Polynomial.fit(offsets, ndimage.median_filter(h, 5, mode="mirror"), 3)(0.0)
    assert smoothed_prediction(h) == pytest.approx(expected, abs=1e-9)
    # irregular offsets (skipped samples) and extrapolation past the last sample
    offs = [-12, -11, -9, -8, -7, -5, -4, -3, -2]
    expected = Polynomial.fit(offs, ndimage.median_filter(h[:9], 5, mode="mirror"), 3)(0.0)
    assert smoothed_prediction(h[:9], offs) == pytest.approx(expected, abs=1e-9)


def test_smoothed_prediction_removes_a_peak_in_the_current_sample():
    h = np.full(11, 3.0)
    h[-1] = 40.0
    assert smoothed_prediction(h) == pytest.approx(3.0, abs=1e-9)


def test_smoothed_prediction_bad_inputs():
    with pytest.raises(ValueError, match=r"longer than poly_degree=3"):
        smoothed_prediction([1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match=r"increasing step offsets <= 0"):
        smoothed_prediction([1.0, 2.0, 3.0, 4.0, 5.0], [-4, -3, -2, -1, 1])


def test_angle_confidence_wraps_across_pi():
    # direction turning smoothly through +-pi: unwrapped, the history is a straight ramp
    history = np.angle(np.exp(1j * (np.pi - 0.25 + 0.05 * np.arange(10))))
    alpha_next = float(np.angle(np.exp(1j * (np.pi - 0.25 + 0.5))))
    assert angle_confidence(alpha_next, np.append(history, alpha_next)) > 0.99
    reverse = float(np.angle(np.exp(1j * (np.pi + 0.25))) - np.pi)  # opposite direction
    assert angle_confidence(reverse, np.append(history, reverse)) < 1e-6


def test_speed_confidence_ratio_relative_and_absolute():
    history = np.full(10, 10.0)
    # +20 %: scale-free deviations ~0.2 -> high; absolute deviation 2 px -> low with x_r = 0.5 px
    assert speed_confidence(12.0, np.append(history, 12.0)) > 0.9
    assert speed_confidence(12.0, np.append(history, 12.0), deviation="relative") > 0.9
    assert speed_confidence(12.0, np.append(history, 12.0), deviation="absolute") < 1e-3
    # ratio (default, Eq. 17's comparison): halving and doubling are alike, ~0.5 at x_r = 0.5
    doubled = speed_confidence(20.0, np.append(history, 20.0))
    halved = speed_confidence(5.0, np.append(history, 5.0))
    assert 0.4 < doubled < 0.6 and abs(doubled - halved) < 0.05
    # relative: a doubling is as bad as a stop
    assert speed_confidence(20.0, np.append(history, 20.0), deviation="relative") < 0.01
    # a stop and a large jump: low but bounded below by normalize(1) (~0.0023)
    stuck = speed_confidence(0.0, np.append(history, 0.0))
    jump = speed_confidence(1e4, np.append(history, 1e4))
    for c in (stuck, jump):
        assert 0.002 < c < 0.01
    with pytest.raises(ValueError, match="speed deviation must be"):
        speed_confidence(1.0, np.append(history, 1.0), deviation="log")


def test_speed_agreement_confidence_orientation():
    equal = speed_agreement_confidence(4.0, 4.0)
    assert equal == pytest.approx(normalize(0.0, 4.0, 0.5))
    assert equal > 0.99
    assert speed_agreement_confidence(0.0, 5.0) < 0.01  # image stuck, robot moving
    assert speed_agreement_confidence(5.0, 0.0) == speed_agreement_confidence(0.0, 5.0)
    assert speed_agreement_confidence(2.0, 4.0, floor=0.0) == pytest.approx(0.5)  # ratio 0.5
    assert speed_agreement_confidence(0.0, 0.0, floor=0.0) == pytest.approx(equal)
    # sub-pixel noise of a still image does not count as disagreement with a still robot
    assert speed_agreement_confidence(0.05, 0.0) > 0.9


def test_image_and_robot_confidence_formulas():
    assert image_confidence(1.0, 1.0, 1.0) == pytest.approx(1.0)
    assert image_confidence(0.125, 1.0, 1.0) == pytest.approx(0.5)
    assert image_confidence(0.5, 0.25, 0.5) == pytest.approx(0.5 ** (4 / 3))
    assert image_confidence(0.9, 0.9, 0.0) == 0.0
    # Eq. 18 edge cases
    assert robot_confidence(c_sp=1.0, c_img=0.7) == pytest.approx(1.0)
    assert robot_confidence(c_sp=0.3, c_img=0.0) == pytest.approx(1.0)
    assert robot_confidence(c_sp=0.0, c_img=1.0) == pytest.approx(0.0)
    assert robot_confidence(c_sp=0.5, c_img=0.5) == pytest.approx(0.75)


def test_confidences_drop_on_outlier_and_stay_high_otherwise():
    _, measured = circle_displacements(150)
    measured[60] = measured[60] @ np.array([[0.0, 1.0], [-1.0, 0.0]])  # turned 90 deg
    measured[100] *= 4.0  # sudden slip
    result = filter_trajectory(measured, measured.copy(), np.full(150, 0.9))
    assert result.c_angle[60] < 0.01 and result.c_speed[60] > 0.9
    # speed_deviation="ratio": a 4x jump deviates by 0.75 -> c_speed ~0.1 (bounded below, Eq. 17
    # form); with "relative" it would be ~1e-20
    assert result.c_speed[100] < 0.15 and result.c_angle[100] > 0.9
    assert result.c_img[60] < 0.2 and result.c_img[100] < 0.5
    normal = ~result.warmup
    normal[[60, 100]] = False
    assert np.nanmin(result.c_angle[normal]) > 0.9  # includes the two crossings of +-pi
    assert np.nanmin(result.c_speed[normal]) > 0.9
    assert np.nanmin(result.c_img[normal]) > 0.9 ** (1 / 3) * 0.9
    # the outliers do not poison the following steps' references
    assert min(result.c_angle[61], result.c_speed[61], result.c_speed[101]) > 0.9


# --- the filter (Eqs. 4-10, 17-18) ------------------------------------------------------------


def test_fuse_gaussians_product():
    mean, var = fuse_gaussians(np.array([0.0, 2.0]), 1.0, np.array([4.0, 2.0]), 1.0)
    np.testing.assert_allclose(mean, [2.0, 2.0])
    assert var == pytest.approx(0.5)
    mean, var = fuse_gaussians(np.array([0.0]), 1.0, np.array([4.0]), 3.0)
    np.testing.assert_allclose(mean, [1.0])  # (3 * 0 + 1 * 4) / 4
    assert var == pytest.approx(0.75)
    mean, var = fuse_gaussians(np.array([0.0]), np.inf, np.array([4.0]), 3.0)
    np.testing.assert_allclose(mean, [4.0])
    with pytest.raises(ValueError, match="both variances are infinite"):
        fuse_gaussians(np.array([0.0]), np.inf, np.array([4.0]), np.inf)


def test_equal_variances_and_unit_confidences_average():
    kf = RobotKalmanFilter(KalmanOptions(c_rob0=1.0, c_img0=1.0))
    step = kf.update((4.0, -2.0), (2.0, 0.0), c_match=0.8)
    assert isinstance(step, FilterStep) and step.warmup
    np.testing.assert_allclose(step.position, [3.0, -1.0])
    np.testing.assert_allclose(step.variance, [0.5, 0.5])  # Eq. 8
    assert step.c_img == 1.0 and step.c_rob == 1.0


def test_initial_confidences_follow_eq_9_10():
    """c_rob(0) = 10, c_img(0) = 1 (Sec. II-B): robot variance sigma_r0^2 / 10."""
    step = RobotKalmanFilter().update((11.0, 0.0), (0.0, 0.0), c_match=1.0)
    np.testing.assert_allclose(step.position, [11.0 * 0.1 / 1.1, 0.0])
    assert step.prior_variance == pytest.approx(0.1)
    assert step.likelihood_variance == pytest.approx(1.0)


def test_outlier_image_measurement_follows_robot():
    truth, measured = circle_displacements(80, noise=0.02)
    robot = truth + np.random.default_rng(7).normal(0.0, 0.02, truth.shape)
    measured[40] += (12.0, 8.0)
    c_match = np.full(80, 0.9)
    c_match[40] = 0.3
    result = filter_trajectory(measured, robot, c_match)
    assert result.c_img[40] < 0.05 and result.c_rob[40] > 0.95
    step_40 = result.positions[41] - result.positions[40]
    np.testing.assert_allclose(step_40, robot[40], atol=0.1)
    chained = integrate_displacements(measured)
    assert np.abs(chained[-1] - integrate_displacements(truth)[-1]).max() > 10.0
    assert np.abs(result.positions[-1] - integrate_displacements(truth)[-1]).max() < 1.0


def test_trusted_image_disagreeing_robot_follows_image():
    """c_img high and c_sp low give c_rob ~ 0 (Eq. 18): the image wins."""
    truth, measured = circle_displacements(60, noise=0.02)
    robot = truth.copy()
    robot[45] = 0.0  # robot reports no motion (e.g. a dropped sample) while the image moves
    result = filter_trajectory(measured, robot, np.full(60, 1.0))
    assert result.c_img[45] > 0.95 and result.c_sp[45] < 0.01 and result.c_rob[45] < 0.05
    step_45 = result.positions[46] - result.positions[45]
    np.testing.assert_allclose(step_45, measured[45], atol=0.1)


def test_propagated_variance_two_steps_by_hand():
    opts = KalmanOptions(
        propagate_variance=True, c_rob0=1.0, c_img0=1.0, sigma_robot0=1.0, sigma_image0=2.0
    )
    kf = RobotKalmanFilter(opts)
    d_img1, d_rob1 = np.array([2.0, 1.0]), np.array([1.0, 1.0])
    d_img2, d_rob2 = np.array([3.0, -1.0]), np.array([1.0, 0.0])
    # step 1: P- = 0 + 1, R = 4, K = 0.2
    s1 = kf.update(d_img1, d_rob1, c_match=1.0)
    x1 = d_rob1 + 0.2 * (d_img1 - d_rob1)
    np.testing.assert_allclose(s1.position, x1)
    np.testing.assert_allclose(s1.variance, [0.8, 0.8])
    # step 2: P- = 0.8 + 1 = 1.8, K = 1.8 / 5.8, P = (1 - K) 1.8
    s2 = kf.update(d_img2, d_rob2, c_match=1.0)
    gain = 1.8 / 5.8
    np.testing.assert_allclose(s2.position, x1 + d_rob2 + gain * (d_img2 - d_rob2))
    np.testing.assert_allclose(s2.variance, [1.8 * 4.0 / 5.8] * 2)
    assert s2.prior_variance == pytest.approx(1.8)
    # the paper's form keeps K = 0.2 at every step
    paper = RobotKalmanFilter(KalmanOptions(c_rob0=1.0, c_img0=1.0, sigma_image0=2.0))
    paper.update(d_img1, d_rob1, c_match=1.0)
    p2 = paper.update(d_img2, d_rob2, c_match=1.0)
    np.testing.assert_allclose(p2.position, x1 + d_rob2 + 0.2 * (d_img2 - d_rob2))
    np.testing.assert_allclose(p2.variance, [0.8, 0.8])


def test_missing_inputs():
    kf = RobotKalmanFilter(KalmanOptions(c_rob0=1.0))
    s = kf.update((np.nan, np.nan), (1.0, 2.0), c_match=np.nan)
    np.testing.assert_allclose(s.position, [1.0, 2.0])
    assert s.c_img == 0.0 and np.isinf(s.likelihood_variance)
    s = kf.update((3.0, 0.0), (np.nan, np.nan), c_match=0.9)
    np.testing.assert_allclose(s.position, [4.0, 2.0])
    assert s.c_rob == 0.0
    with pytest.raises(ValueError, match=r"step 3: both dx_image and dx_robot are missing"):
        kf.update((np.nan, 0.0), (np.nan, 0.0), c_match=0.5)


@pytest.mark.parametrize("propagate", [False, True])
def test_unknown_robot_noise_without_usable_image_follows_the_robot(propagate):
    """sigma_r0 = inf (robot noise not measured yet): a missing image, or one with c_img = 0,
    leaves the robot displacement as the information to follow, not a standstill."""
    kf = RobotKalmanFilter(KalmanOptions(sigma_robot0=np.inf, propagate_variance=propagate))
    d, _ = circle_displacements(12)
    for k in range(8):  # past the warm-up: c_img comes from Eq. 16
        s = kf.update(d[k], d[k] + 5.0, c_match=0.9)
        np.testing.assert_allclose(s.displacement, d[k], atol=1e-12)  # image only: robot inf
    s = kf.update((np.nan, np.nan), d[8], c_match=np.nan)
    np.testing.assert_allclose(s.displacement, d[8], atol=1e-12)
    s = kf.update(d[9] + 40.0, d[9], c_match=0.0)  # an image judged worthless: c_img = 0
    assert s.c_img == 0.0
    np.testing.assert_allclose(s.displacement, d[9], atol=1e-12)


def test_missing_inputs_with_propagated_variance():
    kf = RobotKalmanFilter(KalmanOptions(propagate_variance=True, c_rob0=1.0))
    s = kf.update((np.nan, np.nan), (1.0, 0.0), c_match=np.nan)  # predict only: P = 0 + 1
    np.testing.assert_allclose(s.variance, [1.0, 1.0])
    s = kf.update((2.0, 0.0), (np.nan, np.nan), c_match=0.0)  # c_img = 1 (warm-up), no robot
    np.testing.assert_allclose(s.position, [3.0, 0.0])
    np.testing.assert_allclose(s.variance, [1.0, 1.0])
    s = kf.update((1.0, 1.0), (1.0, 1.0), c_match=0.5)
    assert np.isfinite(s.position).all() and np.isfinite(s.variance).all()


def test_streaming_equals_batch_and_warmup():
    truth, measured = circle_displacements(40, seed=3)
    c_match = np.linspace(0.6, 0.95, 40)
    opts = KalmanOptions(min_history=5)
    batch = filter_trajectory(measured, truth, c_match, opts, start=(5.0, -5.0))
    assert batch.positions.shape == (41, 2) and batch.variances.shape == (40, 2)
    np.testing.assert_allclose(batch.positions[0], [5.0, -5.0])
    kf = RobotKalmanFilter(opts, start=np.array([5.0, -5.0]))
    for i in range(40):
        s = kf.update(measured[i], truth[i], c_match[i])
        np.testing.assert_allclose(s.position, batch.positions[i + 1], atol=1e-12)
        assert s.c_rob == batch.c_rob[i]
    assert kf.step == 40
    assert batch.warmup[:5].all() and not batch.warmup[5:].any()
    assert (batch.c_rob[:5] == 10.0).all() and np.isnan(batch.c_angle[:5]).all()


def test_integrate_displacements():
    d = np.array([[1.0, 2.0], [3.0, -1.0]])
    np.testing.assert_allclose(integrate_displacements(d, (1.0, 1.0)), [[1, 1], [2, 3], [5, 2]])
    with pytest.raises(ValueError, match=r"displacements must have shape \(N, 2\)"):
        integrate_displacements(np.zeros(3))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"sigma_robot0": 0.0}, r"KalmanOptions.sigma_robot0 must be > 0"),
        ({"speed_deviation": "log"}, r"KalmanOptions.speed_deviation must be 'ratio'"),
        ({"median_kernel": 4}, r"median_kernel must be a positive odd integer, got 4"),
        ({"min_history": 3}, r"need poly_degree < min_history <= history_length"),
        ({"min_history": 12}, r"need poly_degree < min_history <= history_length"),
        ({"c_rob0": -1.0}, r"KalmanOptions.c_rob0 must be a finite number >= 0"),
        ({"c_rob0": 0.0, "c_img0": 0.0}, r"cannot both be 0"),
    ],
)
def test_bad_options(kwargs, message):
    with pytest.raises(ValueError, match=message):
        KalmanOptions(**kwargs)


def test_bad_update_and_batch_inputs():
    kf = RobotKalmanFilter()
    with pytest.raises(ValueError, match=r"step 1: dx_image must have shape \(2,\), got \(3,\)"):
        kf.update((1.0, 2.0, 3.0), (0.0, 0.0), 0.5)
    with pytest.raises(ValueError, match=r"step 1: c_match must be in \[0, 1\], got 1.5"):
        kf.update((1.0, 2.0), (0.0, 0.0), 1.5)
    with pytest.raises(ValueError, match=r"step 1: dx_robot is infinite"):
        kf.update((1.0, 2.0), (np.inf, 0.0), 0.5)
    assert kf.step == 0  # rejected updates leave the state untouched
    with pytest.raises(ValueError, match=r"dx_robots must have shape \(4, 2\) like dx_images"):
        filter_trajectory(np.zeros((4, 2)), np.zeros((3, 2)), np.zeros(4))
    with pytest.raises(ValueError, match=r"c_match must have shape \(4,\)"):
        filter_trajectory(np.zeros((4, 2)), np.zeros((4, 2)), np.zeros(5))
    with pytest.raises(ValueError, match=r"dx_images must have shape \(N, 2\)"):
        filter_trajectory(np.zeros(4), np.zeros((4, 2)), np.zeros(4))
    with pytest.raises(ValueError, match=r"options must be a KalmanOptions"):
        RobotKalmanFilter(options={"sigma_robot0": 1.0})
