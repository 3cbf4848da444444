"""Residual functors (cpp/fusedmosaic/residuals): zero at the truth, autodiff Jacobians equal to
central differences, weighting by the configured standard deviations, per-point robust loss."""

import numpy as np
import pytest

from fusedmosaic import _core

K = np.array([[450.0, 0.0, 200.0], [0.0, 450.0, 200.0], [0.0, 0.0, 1.0]])


def numeric_jacobian(f, x, h=1e-6):
    """Central differences of f at x, (len(f(x)), len(x))."""
    x = np.asarray(x, dtype=float)
    cols = []
    for j in range(x.size):
        e = np.zeros_like(x)
        e[j] = h
        cols.append((f(x + e) - f(x - e)) / (2 * h))
    return np.stack(cols, axis=1)


def assert_jacobian_close(analytic, numeric):
    scale = max(np.abs(numeric).max(), 1.0)
    np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-7 * scale)


def plane_at(depth=35.0, tilt=(0.08, -0.05)):
    n = np.array([tilt[0], tilt[1], 1.0])
    n /= np.linalg.norm(n)
    return n / (-depth * n[2])


def cam_from_world(center, angle_axis):
    R = _core.rotation_from_angle_axis(np.asarray(angle_axis, dtype=float))
    return np.r_[angle_axis, -R @ np.asarray(center, dtype=float)]


@pytest.fixture(scope="module")
def pair():
    rng = np.random.default_rng(3)
    plane = plane_at()
    pose_l = cam_from_world([2.0, -1.0, 0.3], [0.03, -0.02, 0.4])
    pose_m = cam_from_world([-1.5, 0.5, -0.2], [-0.02, 0.04, 0.1])
    points_m = rng.uniform(100, 300, (12, 2))
    points_l = _core.transfer_points(points_m, pose_l, pose_m, plane, K)
    return pose_l, pose_m, plane, points_l, points_m


# ---------------------------------------------------------------- visual transfer (Eq. 13, 18)


def test_visual_transfer_zero_at_truth(pair):
    pose_l, pose_m, plane, points_l, points_m = pair
    r, jac = _core.evaluate_visual_transfer(pose_l, pose_m, plane, points_l, points_m, K)
    assert r.shape == (24,)
    assert [j.shape for j in jac] == [(24, 6), (24, 6), (24, 3)]
    np.testing.assert_allclose(r, 0.0, atol=1e-9)


def test_visual_transfer_value_matches_geometry(pair):
    pose_l, pose_m, plane, points_l, points_m = pair
    observed = points_l + np.random.default_rng(0).normal(0, 3.0, points_l.shape)
    r, _ = _core.evaluate_visual_transfer(
        pose_l, pose_m, plane, observed, points_m, K, sigma_v_px=2.0
    )
    expected = (_core.transfer_points(points_m, pose_l, pose_m, plane, K) - observed) / 2.0
    np.testing.assert_allclose(r, expected.ravel(), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("loss", ["none", "huber", "cauchy"])
def test_visual_transfer_jacobian_matches_numeric(pair, loss):
    pose_l, pose_m, plane, points_l, points_m = pair
    # Off the solution, some points beyond the loss scale (2 px) and some inside it.
    observed = points_l + np.random.default_rng(1).normal(0, 2.5, points_l.shape)

    def residual(pl, pm, pi):
        return _core.evaluate_visual_transfer(pl, pm, pi, observed, points_m, K, loss=loss)[0]

    _, (j_l, j_m, j_plane) = _core.evaluate_visual_transfer(
        pose_l, pose_m, plane, observed, points_m, K, loss=loss
    )
    assert_jacobian_close(j_l, numeric_jacobian(lambda x: residual(x, pose_m, plane), pose_l))
    assert_jacobian_close(j_m, numeric_jacobian(lambda x: residual(pose_l, x, plane), pose_m))
    assert_jacobian_close(
        j_plane, numeric_jacobian(lambda x: residual(pose_l, pose_m, x), plane, h=1e-8)
    )


@pytest.mark.parametrize("loss", ["none", "huber", "cauchy"])
@pytest.mark.parametrize("n_points", [1, 12])
def test_visual_transfer_analytic_jacobian_equals_autodiff(pair, loss, n_points):
    """The solvers' analytic Jacobians (chain rule per point through dM/dtheta) against
    ceres::AutoDiffCostFunction of the same functor: equal to rounding."""
    pose_l, pose_m, plane, points_l, points_m = pair
    observed = points_l + np.random.default_rng(4).normal(0, 2.5, points_l.shape)
    args = (pose_l, pose_m, plane, observed[:n_points], points_m[:n_points], K)
    r_a, jac_a = _core.evaluate_visual_transfer(*args, loss=loss, jacobians="analytic")
    r_d, jac_d = _core.evaluate_visual_transfer(*args, loss=loss, jacobians="autodiff")
    np.testing.assert_allclose(r_a, r_d, rtol=1e-12, atol=1e-12)
    for a, d in zip(jac_a, jac_d, strict=True):
        np.testing.assert_allclose(a, d, rtol=1e-9, atol=1e-9 * np.abs(d).max())
    with pytest.raises(ValueError, match="jacobians: expected 'analytic', 'autodiff' or 'none'"):
        _core.evaluate_visual_transfer(*args, jacobians="numeric")


@pytest.mark.parametrize("loss", ["none", "cauchy"])
@pytest.mark.parametrize("fixed", ["none", "l", "m", "both"])
@pytest.mark.parametrize("repeat_points", [False, True])
def test_visual_transfer_condensed_form_keeps_normal_equations_and_cost(
        pair, loss, fixed, repeat_points):
    """The condensed block (P + 1 residuals) has the pair's J^T J, J^T r and cost, through the
    homography's Cholesky (one free camera or two), the plane's Cholesky (both fixed) and, for
    points that do not fix a homography (3 distinct points repeated), the QR fallback."""
    pose_l, pose_m, plane, points_l, points_m = pair
    observed = points_l + np.random.default_rng(5).normal(0, 2.5, points_l.shape)
    if repeat_points:
        observed, points_m = np.tile(observed[:3], (4, 1)), np.tile(points_m[:3], (4, 1))
    args = (pose_l, pose_m, plane, observed, points_m, K)
    kw = {"loss": loss, "fixed_cameras": fixed}
    r, jac = _core.evaluate_visual_transfer(*args, **kw)
    rc, jac_c = _core.evaluate_visual_transfer(*args, condense=True, **kw)
    J, Jc = np.hstack(jac), np.hstack(jac_c)
    n_free = J.shape[1]
    assert n_free == {"none": 15, "l": 9, "m": 9, "both": 3}[fixed]
    assert rc.shape == (n_free + 1,) and Jc.shape == (n_free + 1, n_free)
    np.testing.assert_allclose(rc @ rc, r @ r, rtol=1e-9)
    np.testing.assert_allclose(Jc.T @ rc, J.T @ r, rtol=1e-7, atol=1e-9 * np.abs(J.T @ r).max())
    JtJ = J.T @ J
    np.testing.assert_allclose(Jc.T @ Jc, JtJ, rtol=1e-7, atol=1e-9 * np.abs(JtJ).max())
    # without Jacobians, the same cost: [0, ..., 0, |r|]
    ro, none = _core.evaluate_visual_transfer(*args, condense=True, jacobians="none", **kw)
    assert none == () and ro.shape == rc.shape
    np.testing.assert_allclose(ro[-1], np.linalg.norm(r), rtol=1e-12)
    assert not ro[:-1].any()
    # too few points to save residuals: the block keeps its 2N
    r3, _ = _core.evaluate_visual_transfer(pose_l, pose_m, plane, observed[:1], points_m[:1], K,
                                           condense=True, **kw)
    assert r3.shape == (2,)


def test_visual_transfer_weighting_by_sigma(pair):
    pose_l, pose_m, plane, points_l, points_m = pair
    observed = points_l + 1.5
    r1, (j1, _, _) = _core.evaluate_visual_transfer(
        pose_l, pose_m, plane, observed, points_m, K, sigma_v_px=1.0
    )
    r4, (j4, _, _) = _core.evaluate_visual_transfer(
        pose_l, pose_m, plane, observed, points_m, K, sigma_v_px=4.0
    )
    np.testing.assert_allclose(r4, r1 / 4.0, rtol=1e-12)
    np.testing.assert_allclose(j4, j1 / 4.0, rtol=1e-12)


@pytest.mark.parametrize("loss", ["huber", "cauchy"])
def test_visual_transfer_loss_is_per_point(pair, loss):
    """Each point's squared residual equals rho(s_i) of its own plain squared residual."""
    pose_l, pose_m, plane, points_l, points_m = pair
    offsets = np.linspace(0.0, 12.0, len(points_l))  # from inliers to gross outliers
    observed = points_l + np.c_[offsets, np.zeros_like(offsets)]
    sigma, scale = 1.5, 3.0
    plain, _ = _core.evaluate_visual_transfer(
        pose_l, pose_m, plane, observed, points_m, K, sigma_v_px=sigma
    )
    robust, _ = _core.evaluate_visual_transfer(
        pose_l,
        pose_m,
        plane,
        observed,
        points_m,
        K,
        sigma_v_px=sigma,
        loss=loss,
        loss_scale_px=scale,
    )
    s = (plain.reshape(-1, 2) ** 2).sum(axis=1)
    a = scale / sigma  # kernel scale in units of sigma_v
    if loss == "huber":
        rho = np.where(s <= a**2, s, 2 * a * np.sqrt(s) - a**2)
    else:
        rho = a**2 * np.log1p(s / a**2)
    np.testing.assert_allclose((robust.reshape(-1, 2) ** 2).sum(axis=1), rho, rtol=1e-10)
    # Direction is kept; inliers (below the Huber scale) untouched.
    np.testing.assert_allclose(robust[1::2], 0.0, atol=1e-9)
    if loss == "huber":
        inlier = s <= a**2
        np.testing.assert_allclose(
            robust.reshape(-1, 2)[inlier], plain.reshape(-1, 2)[inlier], rtol=1e-12
        )


def test_visual_transfer_single_point_matches_block(pair):
    pose_l, pose_m, plane, points_l, points_m = pair
    observed = points_l + 0.7
    r_all, (jl_all, _, _) = _core.evaluate_visual_transfer(
        pose_l, pose_m, plane, observed, points_m, K
    )
    r_one, (jl_one, _, _) = _core.evaluate_visual_transfer(
        pose_l, pose_m, plane, observed[3:4], points_m[3:4], K
    )
    np.testing.assert_allclose(r_one, r_all[6:8], rtol=1e-12)
    np.testing.assert_allclose(jl_one, jl_all[6:8], rtol=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"points_m": np.zeros((3, 2))}, r"points_m: expected shape \(12, 2\), got \(3, 2\)"),
        ({"points_l": np.zeros((12, 3))}, r"points_l: expected shape \(N, 2\), got \(12, 3\)"),
        ({"plane": np.array([0.0, np.nan, 0.1])}, "plane: contains NaN"),
        ({"cam_l_from_world": np.zeros(5)}, "cam_l_from_world: expected 6 values, got 5"),
        ({"camera_matrix": np.zeros((3, 3))}, "camera_matrix: matrix is singular"),
        ({"loss": "l1"}, "loss: expected 'none', 'huber' or 'cauchy', got 'l1'"),
        ({"sigma_v_px": 0.0}, "sigma_v_px: must be > 0"),
    ],
)
def test_visual_transfer_bad_input(pair, kwargs, match):
    pose_l, pose_m, plane, points_l, points_m = pair
    args = dict(
        cam_l_from_world=pose_l,
        cam_m_from_world=pose_m,
        plane=plane,
        points_l=points_l,
        points_m=points_m,
        camera_matrix=K,
    )
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        _core.evaluate_visual_transfer(**args)


# ---------------------------------------------------------------- EMT pose prior (Eq. 19)


def test_pose_prior_zero_at_truth_and_weighting():
    z = np.array([0.1, -0.2, 0.3, 1.0, 2.0, 30.0])
    r, (jac,) = _core.evaluate_pose_prior(z, z)
    np.testing.assert_array_equal(r, np.zeros(6))
    sigma = np.array([0.01, 0.02, 0.03, 0.5, 1.0, 2.0])
    x = z + np.array([0.01, 0.01, -0.03, 1.0, -1.0, 4.0])
    r, (jac,) = _core.evaluate_pose_prior(x, z, sigma)
    np.testing.assert_allclose(r, (x - z) / sigma, rtol=1e-12)
    np.testing.assert_allclose(jac, np.diag(1 / sigma), rtol=1e-12)
    assert_jacobian_close(
        jac, numeric_jacobian(lambda v: _core.evaluate_pose_prior(v, z, sigma)[0], x)
    )


def test_pose_prior_default_sigma_is_appendix():
    np.testing.assert_allclose(_core.DEFAULT_EMT_SIGMA, [0.017] * 3 + [1.0] * 3)
    z = np.zeros(6)
    r, _ = _core.evaluate_pose_prior(np.full(6, 0.017), z)
    np.testing.assert_allclose(r, [1.0] * 3 + [0.017] * 3)


def test_pose_prior_bad_sigma():
    with pytest.raises(ValueError, match=r"sigma\[3\]: standard deviations must be > 0"):
        _core.evaluate_pose_prior(np.zeros(6), np.zeros(6), np.array([1, 1, 1, 0, 1, 1.0]))


# ---------------------------------------------------------------- constant velocity (Eq. 15-20)


def predicted(x_km2, x_km1):
    """mu_p = T_{k-1} T_{k-2}^-1 T_{k-1}, through the geometry bindings."""
    velocity = _core.compose_poses(x_km1, _core.invert_pose(x_km2))
    return _core.compose_poses(velocity, x_km1)


@pytest.fixture(scope="module")
def triple():
    x_km2 = np.array([0.05, -0.1, 0.3, 1.0, -2.0, -33.0])
    x_km1 = np.array([0.07, -0.08, 0.35, 1.4, -1.7, -33.2])
    return x_km2, x_km1


def test_constant_velocity_zero_at_truth(triple):
    x_km2, x_km1 = triple
    r, jac = _core.evaluate_constant_velocity(x_km2, x_km1, predicted(x_km2, x_km1))
    np.testing.assert_allclose(r, 0.0, atol=1e-10)
    assert [j.shape for j in jac] == [(6, 6)] * 3


def test_constant_velocity_zero_on_screw_motion():
    """Poses T_k = D^k T_0 (constant body velocity D) are predicted exactly."""
    step = np.array([0.02, -0.01, 0.05, 0.3, 0.1, -0.05])
    poses = [np.array([0.1, 0.2, -0.1, 1.0, 2.0, -30.0])]
    for _ in range(3):
        poses.append(_core.compose_poses(step, poses[-1]))
    for k in (2, 3):
        r, _ = _core.evaluate_constant_velocity(poses[k - 2], poses[k - 1], poses[k])
        np.testing.assert_allclose(r, 0.0, atol=1e-10)


def test_constant_velocity_value_and_weighting(triple):
    x_km2, x_km1 = triple
    x_k = predicted(x_km2, x_km1) + np.array([0.01, -0.02, 0.005, 0.5, -0.25, 1.0])
    sigma = np.array([0.01, 0.01, 0.02, 0.5, 0.5, 2.0])
    r, _ = _core.evaluate_constant_velocity(x_km2, x_km1, x_k, sigma)
    np.testing.assert_allclose(r, (x_k - predicted(x_km2, x_km1)) / sigma, rtol=1e-9)
    r_default, _ = _core.evaluate_constant_velocity(x_km2, x_km1, x_k)
    np.testing.assert_allclose(r_default * _core.DEFAULT_MOTION_SIGMA, r * sigma, rtol=1e-9)
    np.testing.assert_allclose(_core.DEFAULT_MOTION_SIGMA, [0.0044] * 3 + [15.2178] * 3)


def test_constant_velocity_jacobian_matches_numeric(triple):
    x_km2, x_km1 = triple
    x_k = predicted(x_km2, x_km1) + np.array([0.03, -0.02, 0.01, 0.5, -0.5, 1.0])
    sigma = np.array([0.01, 0.01, 0.02, 0.5, 0.5, 2.0])
    _, (j2, j1, j0) = _core.evaluate_constant_velocity(x_km2, x_km1, x_k, sigma)

    def f(a, b, c):
        return _core.evaluate_constant_velocity(a, b, c, sigma)[0]

    assert_jacobian_close(j2, numeric_jacobian(lambda x: f(x, x_km1, x_k), x_km2))
    assert_jacobian_close(j1, numeric_jacobian(lambda x: f(x_km2, x, x_k), x_km1))
    assert_jacobian_close(j0, numeric_jacobian(lambda x: f(x_km2, x_km1, x), x_k))
    np.testing.assert_allclose(j0, np.diag(1 / sigma), rtol=1e-12)


def test_constant_velocity_ratio_repeats_the_motion(triple):
    """ratio 2 (one dropped frame): the last motion twice; ratio 1 is Eq. 16 bit for bit; the
    same prediction as motion.predict_constant_velocity; a non-positive ratio is refused."""
    from fusedmosaic.estimation.motion import predict_constant_velocity

    step = np.array([0.0, 0.0, 0.05, 0.3, 0.1, -0.05])  # rotation about one axis: exact power
    x0 = np.array([0.0, 0.0, 0.1, 1.0, 2.0, -30.0])
    x1 = _core.compose_poses(step, x0)
    x3 = _core.compose_poses(step, _core.compose_poses(step, x1))
    r, _ = _core.evaluate_constant_velocity(x0, x1, x3, np.ones(6), ratio=2.0)
    np.testing.assert_allclose(r[:3], 0.0, atol=1e-12)  # the rotation exactly
    # the translation to first order: |(R - I) t| <= angle x |t| per repeated step
    assert np.linalg.norm(r[3:]) <= 0.05 * np.linalg.norm(step[3:]) * 1.01
    pure = np.array([0.0, 0.0, 0.0, 0.3, 0.1, -0.05])  # no rotation: exact
    y1 = _core.compose_poses(pure, x0)
    y3 = _core.compose_poses(pure, _core.compose_poses(pure, y1))
    np.testing.assert_allclose(_core.evaluate_constant_velocity(x0, y1, y3, ratio=2.0)[0], 0.0,
                               atol=1e-12)
    x_km2, x_km1 = triple
    x_k = predicted(x_km2, x_km1) + 0.01
    np.testing.assert_array_equal(_core.evaluate_constant_velocity(x_km2, x_km1, x_k)[0],
                                  _core.evaluate_constant_velocity(x_km2, x_km1, x_k,
                                                                   ratio=1.0)[0])
    sigma = np.ones(6)
    r, _ = _core.evaluate_constant_velocity(x_km2, x_km1, x_k, sigma, ratio=0.5)
    np.testing.assert_allclose(r, x_k - predict_constant_velocity(x_km2, x_km1, 0.5),
                               atol=1e-12)
    # ratio 0 (after a gap that breaks the prior: zero velocity) predicts frame k-1's pose
    r, _ = _core.evaluate_constant_velocity(x_km2, x_km1, x_k, sigma, ratio=0.0)
    np.testing.assert_allclose(r, x_k - x_km1, atol=1e-12)
    for bad in (-0.5, np.inf, np.nan):
        with pytest.raises(ValueError, match=r"evaluate_constant_velocity: motion_ratio must be "
                           r"finite and >= 0 and motion_sigma_scale > 0 \(inf: no motion "
                           r"prior\), got"):
            _core.evaluate_constant_velocity(x_km2, x_km1, x_k, ratio=bad)


def test_constant_velocity_bad_input(triple):
    x_km2, x_km1 = triple
    with pytest.raises(ValueError, match="cam_k_from_world: expected 6 values, got 3"):
        _core.evaluate_constant_velocity(x_km2, x_km1, np.zeros(3))
