"""Session-52 review of the C++ priors and sliding window.

E1: the EMT pose prior (Eq. 19) and the constant-velocity prior (Eq. 20) took x - z as the plain
difference of angle-axis vectors, ~2 pi for two rotations near pi that are 0.02 rad apart (one
rotation, two vectors); now z's vector is the one of its rotation nearest x's.
E2: a refused SlidingWindow.redo left its frames pending without poses.
E3: a first frame with neither an initial pose nor a tracker sample was accepted, and dropping
the sample of a pending first frame dropped its initial pose too.
E4: forget dropped the cameras the first pending frame's constant-velocity prior links it to
when more than window_size - 2 frames were pending.
"""

from __future__ import annotations

import numpy as np
import pytest

from fusedmosaic import _core
from tests.test_residuals import numeric_jacobian

K = np.array([[450.0, 0, 199.5], [0, 450.0, 199.5], [0, 0, 1]])
PLANE = np.array([0.0, 0.0, -1 / 35.0])
AXIS = np.array([0.0, 0.6, 0.8])


def options():
    """The SYN preset (W = 5, chi_e = 3) on one thread: twin windows agree bit for bit."""
    return _core.SlidingWindowOptions(window_size=5, num_new=3,
                                      costs=_core.BundleAdjusterOptions(num_threads=1))


def geodesic(r_a, r_b):
    """log(R_a R_b^T) as an angle-axis vector."""
    return _core.angle_axis_from_rotation(_core.rotation_from_angle_axis(r_a)
                                          @ _core.rotation_from_angle_axis(r_b).T)


# --------------------------------------------------------------------------------- E1 priors
def test_pose_prior_across_the_pi_wrap_is_the_small_rotation():
    """(pi - 0.01) a and -(pi - 0.01) a are 0.02 rad apart: the residual was ~2 pi (6.26)."""
    theta = np.pi - 0.01
    x = np.r_[theta * AXIS, 1.0, 2.0, 3.0]
    z = np.r_[-theta * AXIS, 1.5, 2.0, 2.0]
    sigma = np.array([0.01, 0.02, 0.03, 0.5, 1.0, 2.0])
    r, (jac,) = _core.evaluate_pose_prior(x, z, sigma)
    np.testing.assert_allclose(r[:3] * sigma[:3], -0.02 * AXIS, atol=1e-12)
    np.testing.assert_allclose(r[:3] * sigma[:3], geodesic(x[:3], z[:3]), atol=1e-12)
    np.testing.assert_allclose(r[3:], (x[3:] - z[3:]) / sigma[3:], rtol=1e-12)
    np.testing.assert_allclose(jac, np.diag(1 / sigma), rtol=1e-12)  # still linear in x
    numeric = numeric_jacobian(lambda v: _core.evaluate_pose_prior(v, z, sigma)[0], x)
    np.testing.assert_allclose(jac, numeric, rtol=1e-6, atol=1e-6)
    # the other way round, and off the axis: within the chart's stretch of the geodesic angle
    # across the axis (<= pi / 2 at |r| = pi), never ~2 pi
    rng = np.random.default_rng(0)
    for _ in range(200):
        a = rng.normal(size=3)
        a /= np.linalg.norm(a)
        xr = (np.pi - rng.uniform(0, 0.05)) * a
        zr = _core.angle_axis_from_rotation(
            _core.rotation_from_angle_axis(rng.normal(0, 0.03, 3))
            @ _core.rotation_from_angle_axis(xr))
        r, _ = _core.evaluate_pose_prior(np.r_[xr, 0, 0, 0], np.r_[zr, 0, 0, 0], np.ones(6))
        angle = np.linalg.norm(geodesic(xr, zr))
        assert angle * (1 - 1e-9) <= np.linalg.norm(r[:3]) <= np.pi / 2 * angle + 1e-9


def test_pose_prior_away_from_the_wrap_is_the_papers_plain_difference():
    """Errors below pi along the measurement's axis: x - z bit for bit (Eq. 19 unchanged)."""
    rng = np.random.default_rng(1)
    for _ in range(500):
        z = np.r_[rng.uniform(-1.8, 1.8, 3), rng.uniform(-50, 50, 3)]
        x = z + np.r_[rng.normal(0, 0.3, 3), rng.normal(0, 5, 3)]
        r, (jac,) = _core.evaluate_pose_prior(x, z, np.ones(6))
        np.testing.assert_array_equal(r, x - z)
        np.testing.assert_array_equal(jac, np.eye(6))


def test_constant_velocity_across_the_pi_wrap_is_the_small_rotation():
    """mu_p (from ToPose, |r| <= pi) and x_k on either side of pi: 0.02 rad, not ~2 pi."""
    theta = np.pi - 0.01
    x_km2 = np.r_[theta * AXIS, 0.0, 0.0, -30.0]
    x_km1 = np.r_[theta * AXIS, 1.0, 0.0, -30.0]
    x_k = np.r_[-theta * AXIS, 2.0, 0.0, -30.0]  # R((2 pi - theta) a): 0.02 rad from R(theta a)
    sigma = np.ones(6)
    r, (j2, j1, j0) = _core.evaluate_constant_velocity(x_km2, x_km1, x_k, sigma)
    np.testing.assert_allclose(r[:3], 0.02 * AXIS, atol=1e-9)
    np.testing.assert_allclose(r[3:], 0.0, atol=1e-9)
    mu = _core.compose_poses(_core.compose_poses(x_km1, _core.invert_pose(x_km2)), x_km1)
    np.testing.assert_allclose(r[:3], geodesic(x_k[:3], mu[:3]), atol=1e-9)
    np.testing.assert_allclose(j0, np.eye(6), atol=1e-12)
    for jac, i in ((j2, 0), (j1, 1), (j0, 2)):
        def f(v, i=i):
            args = [x_km2, x_km1, x_k]
            args[i] = v
            return _core.evaluate_constant_velocity(*args, sigma)[0]

        np.testing.assert_allclose(jac, numeric_jacobian(f, [x_km2, x_km1, x_k][i]),
                                   rtol=1e-5, atol=1e-5)


def _trajectory(n=12, rx0=-0.04, noise=(0.0, 0.0), seed=0):
    """Constant velocity (T_k = V T_{k-1}) whose rotation about x crosses 0 near frame 10, pairs
    of each frame with its 3 predecessors, and tracker samples with (rad, mm) noise."""
    rng = np.random.default_rng(seed)
    velocity = np.array([0.004, -0.003, 0.01, 0.9, 0.4, 0.05])
    poses = np.zeros((n, 6))
    poses[0] = [rx0, -0.01, 0.0, -4.0, -2.0, 0.0]
    for k in range(1, n):
        poses[k] = _core.compose_poses(velocity, poses[k - 1])
    samples = np.array([_core.compose_poses(np.r_[rng.normal(0, noise[0], 3),
                                                   rng.normal(0, noise[1], 3)], p)
                        for p in poses])
    pts = rng.uniform(40, 360, (60, 2))
    pairs = []
    for l in range(n):
        for m in range(max(0, l - 3), l):
            pl = _core.transfer_points(pts, poses[l], poses[m], PLANE, K)
            ok = (pl > 0).all(axis=1) & (pl < 400).all(axis=1)
            pairs.append((l, m, pl[ok] + rng.normal(0, 0.3, pl[ok].shape), pts[ok]))
    return poses, samples, pairs


def _rotated(pose, world):
    """cam_from_world' = cam_from_world * world'_from_world^-1 (canonical angle-axis)."""
    return _core.compose_poses(pose, _core.invert_pose(np.r_[world, 0, 0, 0]))


def _solve_window(poses, samples, pairs, plane, fixed=9):
    w = _core.SlidingWindow(K, options())
    w.set_plane(plane)
    for k in range(len(poses)):
        w.add_frame(k, poses[k] if k < fixed else None, samples[k], fixed=k < fixed)
    for l, m, pl, pm in pairs:
        w.add_pair(l, m, pl, pm)
    s = w.step([])
    return w, s


def test_window_step_in_a_world_where_the_cameras_sit_at_pi():
    """The same scene in a world rotated by pi about x: every camera's rotation is near pi and
    the pending frames' tracker samples (canonical vectors, |r| <= pi) flip between +-pi a.
    The step places them as in the original world (before: pulled ~2 pi / sigma apart)."""
    poses, samples, pairs = _trajectory(noise=(0.005, 0.3), seed=4)
    world = np.array([np.pi, 0.0, 0.0])
    poses_w = np.array([_rotated(p, world) for p in poses])
    samples_w = np.array([_rotated(z, world) for z in samples])
    plane_w = _core.rotation_from_angle_axis(world) @ PLANE
    assert (np.abs(np.linalg.norm(samples_w[:, :3], axis=1) - np.pi) < 0.05).all()
    flips = np.sign(samples_w[9:, 0])
    assert len(set(flips)) == 2, samples_w[9:, :3]  # the test crosses the wrap
    w0, s0 = _solve_window(poses, samples, pairs, PLANE)
    w1, s1 = _solve_window(poses_w, samples_w, pairs, plane_w)
    assert s0.termination == s1.termination == "CONVERGENCE"
    for k in (9, 10, 11):
        est = w1.pose(k)
        back = _core.compose_poses(est, np.r_[world, 0, 0, 0])  # to the original world
        err_rot = np.linalg.norm(geodesic(back[:3], poses[k][:3]))
        err_t = np.linalg.norm(back[3:] - poses[k][3:])
        ref_rot = np.linalg.norm(geodesic(w0.pose(k)[:3], poses[k][:3]))
        ref_t = np.linalg.norm(w0.pose(k)[3:] - poses[k][3:])
        assert err_rot < 2 * ref_rot + 1e-3 and err_t < 2 * ref_t + 0.05, (k, err_rot, err_t,
                                                                            ref_rot, ref_t)
    # (the plane as the original world's step estimates it, 1e-4 off the truth: 0.3 px noise)
    np.testing.assert_allclose(w1.plane(), _core.rotation_from_angle_axis(world) @ w0.plane(),
                               atol=2e-5)
    # the gate's distance takes the prior's difference: no tracker sample looks 2 pi off
    d2 = np.array(s1.emt_mahalanobis2)
    assert (d2 < 22.46).all(), d2
    np.testing.assert_allclose(d2, s0.emt_mahalanobis2, rtol=0.5, atol=1.0)


# --------------------------------------------------------------------------------- E2 redo
def _stepped(first_sample=False):
    """Frame 0 added with an initial pose (and a sample if first_sample), 1-5 with samples;
    stepped twice (0-2, then 3-5)."""
    poses, samples, pairs = _trajectory(n=6, noise=(0.003, 0.2), seed=2)
    w = _core.SlidingWindow(K, options())
    w.set_plane(PLANE * 1.02)
    for k in range(6):
        w.add_frame(k, poses[k] if k == 0 else None,
                    samples[k] if (k or first_sample) else None)
        if k in (2, 5):
            for l, m, pl, pm in pairs:
                if max(l, m) <= k and max(l, m) > k - 3:
                    w.add_pair(l, m, pl, pm)
            w.step([])
    return w


BAD_REDOS = [
    (([0, 1, 2, 3, 4, 5], []), ValueError,
     r"redo: frame 0 is the window's first frame and has no tracker sample: a redo starts each "
     r"frame again from its sample or the constant-velocity prediction of its predecessors "
     r"\(not from its initial pose or last estimate\), and it has neither"),
    (([3, 4, 5], [9]), IndexError, "redo keyframe: unknown frame id 9"),
    (([3, 4, 5], [4]), ValueError, "redo: keyframe 4 is among the frames this call estimates"),
    (([3, 4, 4, 5], []), ValueError, "redo: frame 4 appears more than once"),
    (([3, 4], []), ValueError, "redo: frame_ids must be the last frames, but frame 5"),
    (([3, 4, 5, 7], []), IndexError, "redo: unknown frame id 7"),
    (([], []), ValueError, "redo: frame_ids is empty"),
]


@pytest.mark.parametrize(("args", "error", "message"), BAD_REDOS)
def test_refused_redo_leaves_the_window_as_it_was(args, error, message):
    """Before, the first case made every frame pending without a pose (the window then refused
    every step); now each refusal comes before any change, and the window goes on exactly as
    one that never saw the call."""
    w, twin = _stepped(), _stepped()
    before = {k: w.pose(k) for k in range(6)}
    with pytest.raises(error, match=message):
        w.redo(*args)
    assert w.pending_ids() == [] and w.window_ids() == twin.window_ids() == [4, 5]
    for k in range(6):
        np.testing.assert_array_equal(w.pose(k), before[k])
    np.testing.assert_array_equal(w.plane(), twin.plane())
    s, t = w.redo([3, 4, 5], [0]), twin.redo([3, 4, 5], [0])
    assert s.termination == t.termination == "CONVERGENCE" and s.final_cost == t.final_cost
    for k in range(6):
        np.testing.assert_array_equal(w.pose(k), twin.pose(k))
    np.testing.assert_array_equal(w.plane(), twin.plane())


def test_redo_from_a_first_frame_with_a_sample_is_allowed():
    w = _stepped(first_sample=True)
    s = w.redo([0, 1, 2, 3, 4, 5])
    assert s.termination == "CONVERGENCE" and s.frame_ids == [0, 1, 2, 3, 4, 5]


# --------------------------------------------------------------------------------- E3 anchor
def test_first_frame_without_a_pose_or_a_sample_is_refused():
    w = _core.SlidingWindow(K)
    with pytest.raises(ValueError, match=r"add_frame: frame 7 is the window's first frame and "
                       r"has neither an initial pose nor a tracker sample \(emt_measurement\): "
                       r"it has no predecessors to be predicted from, so nothing would place "
                       r"it; give it one of them"):
        w.add_frame(7, None, None)
    assert w.num_frames == 0
    w.add_frame(7, None, np.zeros(6))  # either anchors it
    w.add_frame(8, None, None)  # later frames are predicted from their predecessors
    assert w.pending_ids() == [7, 8]
    v = _core.SlidingWindow(K)
    v.add_frame(3, np.zeros(6), None)
    assert v.pending_ids() == [3]


@pytest.mark.parametrize("initial", [None, np.zeros(6)])
def test_dropping_the_sample_of_a_pending_first_frame_is_refused(initial):
    """It dropped the frame's initial pose too, leaving it nothing to start from."""
    w = _core.SlidingWindow(K)
    w.set_plane(PLANE)
    w.add_frame(4, initial, np.r_[0, 0, 0, 0.1, 0, 0])
    w.add_frame(5, None, None)
    with pytest.raises(ValueError, match=r"drop_emt_measurement: frame 4 is the window's first "
                       r"frame and still pending: without its tracker sample it would have no "
                       r"starting pose \(no predecessors to predict it from, and its initial "
                       r"pose is not kept\)"):
        w.drop_emt_measurement(4)
    w.drop_emt_measurement(5)  # a later frame: predicted from its predecessors
    if initial is not None:
        np.testing.assert_array_equal(w.pose(4), initial)
    s = w.step([])
    assert s.frame_ids == [4, 5] and s.termination != "FAILURE"
    np.testing.assert_allclose(w.pose(4)[3:], [0.1, 0, 0], atol=1e-6)  # at its sample
    w.drop_emt_measurement(4)  # fixed now: keeps its estimate (test_window_review45)
    np.testing.assert_allclose(w.pose(4)[3:], [0.1, 0, 0], atol=1e-6)


# --------------------------------------------------------------------------------- E4 forget
def _many_pending():
    """W = 5: frames 0-5 fixed, 6-10 pending (5 > W - 2): the window holds none of 0-5."""
    poses, samples, pairs = _trajectory(n=11, noise=(0.002, 0.1), seed=3)
    w = _core.SlidingWindow(K, options())
    w.set_plane(PLANE)
    for k in range(11):
        w.add_frame(k, poses[k] if k < 6 else None, samples[k], fixed=k < 6)
    for l, m, pl, pm in pairs:
        w.add_pair(l, m, pl, pm)
    return w


def test_forget_keeps_the_predecessors_of_the_first_pending_frame():
    """Before, frame 4 went and frame 6's C_p took frames 3 and 5 as its k-2, k-1."""
    w = _many_pending()
    assert w.pending_ids() == [6, 7, 8, 9, 10]
    n = (w.num_frames, w.num_pairs, w.num_correspondences)
    for ids, frame in (([4], 4), ([0, 1, 5], 5), ([2, 4, 3], 4)):
        with pytest.raises(ValueError, match=(
                rf"forget: frame {frame} is one of the two cameras before the first pending "
                r"frame 6, which its constant-velocity prior links it to \(the window keeps "
                r"them only while at most window_size - 2 = 3 frames are pending; 5 are\)")):
            w.forget(ids)
        assert (w.num_frames, w.num_pairs, w.num_correspondences) == n  # nothing dropped
    with pytest.raises(ValueError, match="forget: frame 7 is pending or in the window"):
        w.forget([0, 7])
    assert w.num_frames == n[0]
    w.forget([0, 1, 2, 3, 99])  # the others may go (an unknown id is ignored)
    assert w.num_frames == n[0] - 4
    twin = _many_pending()
    twin.forget([0, 1, 2, 3])
    s, t = w.step([]), twin.step([])
    assert s.frame_ids == [6, 7, 8, 9, 10] and s.fixed_ids == []  # 5 pending: no window
    assert s.termination == "CONVERGENCE" and s.final_cost == t.final_cost
    for k in range(6, 11):
        np.testing.assert_array_equal(w.pose(k), twin.pose(k))
    # once stepped, the usual window: the last W - 1 fixed frames stay
    w.forget([4, 5, 6])
    with pytest.raises(ValueError, match="forget: frame 7 is pending or in the window"):
        w.forget([7])
