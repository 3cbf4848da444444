"""C++ geometry (seed 000, Eqs. 1-5, 13) against independent numpy constructions."""

import cv2
import numpy as np
import pytest

from fusedmosaic import _core

TOL = 1e-10


def rodrigues(r: np.ndarray) -> np.ndarray:
    """R = exp([r]_x) by the closed-form Rodrigues formula (independent of the C++ code)."""
    theta = np.linalg.norm(r)
    if theta < 1e-15:
        return np.eye(3)
    k = r / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * kx @ kx


def induced(pose: np.ndarray, plane: np.ndarray, K: np.ndarray | None = None) -> np.ndarray:
    H = rodrigues(pose[:3]) - np.outer(pose[3:], plane)
    return H if K is None else K @ H @ np.linalg.inv(K)


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(7)
    poses = np.hstack([rng.normal(0, 0.2, (12, 3)), rng.normal(0, 5.0, (12, 3))])
    normal = np.array([0.1, -0.2, 1.0])
    normal /= np.linalg.norm(normal)
    plane = normal / -35.0  # plane n.X + d = 0 with d = -35 mm
    K = np.array([[450.0, 0.5, 201.0], [0.0, 440.0, 198.0], [0.0, 0.0, 1.0]])
    return poses, plane, K


def test_rotation_matches_rodrigues_and_round_trips(scene):
    poses, _, _ = scene
    for r in poses[:, :3]:
        R = _core.rotation_from_angle_axis(r)
        np.testing.assert_allclose(R, rodrigues(r), atol=TOL)
        np.testing.assert_allclose(R, cv2.Rodrigues(r)[0], atol=1e-9)
        np.testing.assert_allclose(_core.angle_axis_from_rotation(R), r, atol=TOL)


def test_induced_homography_matches_numpy(scene):
    poses, plane, K = scene
    for pose in poses:
        np.testing.assert_allclose(_core.induced_homography(pose, plane), induced(pose, plane),
                                   atol=TOL)
        np.testing.assert_allclose(
            _core.induced_homography(pose, plane, camera_matrix=K), induced(pose, plane, K),
            rtol=TOL, atol=TOL * 1e3)


def test_induced_homography_maps_plane_points(scene):
    """Eq. 5 from first principles: project a 3D plane point in the virtual and the real camera."""
    poses, plane, K = scene
    rng = np.random.default_rng(1)
    # Points on n.X + d = 0: X = X0 + a e1 + b e2, with X0 = -n d = n / |pi|^2 * (-1) ...
    n = plane / np.linalg.norm(plane)
    d = 1.0 / np.dot(plane, n)
    x0 = -d * n
    e1 = np.cross(n, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    pts3d = x0 + rng.uniform(-10, 10, (50, 1)) * e1 + rng.uniform(-10, 10, (50, 1)) * e2
    np.testing.assert_allclose(pts3d @ n + d, 0, atol=1e-9)
    virtual_px = (K @ pts3d.T).T
    virtual_px = virtual_px[:, :2] / virtual_px[:, 2:]
    for pose in poses:
        cam = (rodrigues(pose[:3]) @ pts3d.T).T + pose[3:]
        frame_px = (K @ cam.T).T
        frame_px = frame_px[:, :2] / frame_px[:, 2:]
        H = _core.induced_homography(pose, plane, camera_matrix=K)
        mapped = cv2.perspectiveTransform(virtual_px[None], H)[0]
        np.testing.assert_allclose(mapped, frame_px, atol=1e-8)


def test_transfer_and_frame_to_reference_match_numpy(scene):
    poses, plane, K = scene
    rng = np.random.default_rng(2)
    pts = rng.uniform(0, 400, (30, 2))
    for pl, pm in zip(poses[1:], poses[:-1], strict=True):
        expected = induced(pl, plane, K) @ np.linalg.inv(induced(pm, plane, K))
        expected /= expected[2, 2]
        got = _core.transfer_homography(pl, pm, plane, camera_matrix=K)
        np.testing.assert_allclose(got, expected, rtol=TOL, atol=TOL)
        mapped = _core.transfer_points(pts, pl, pm, plane, camera_matrix=K)
        np.testing.assert_allclose(mapped, cv2.perspectiveTransform(pts[None], expected)[0],
                                   atol=1e-8)
    G = _core.frame_to_reference(poses, plane, K)
    assert G.shape == (len(poses), 3, 3)
    np.testing.assert_allclose(G[0], np.eye(3), atol=TOL)
    for k, pose in enumerate(poses):
        expected = induced(poses[0], plane, K) @ np.linalg.inv(induced(pose, plane, K))
        np.testing.assert_allclose(G[k], expected / expected[2, 2], rtol=TOL, atol=TOL)


def test_pose_algebra_and_distance(scene):
    poses, plane, _ = scene

    def matrix(p):
        T = np.eye(4)
        T[:3, :3] = rodrigues(p[:3])
        T[:3, 3] = p[3:]
        return T

    a, b = poses[0], poses[1]
    np.testing.assert_allclose(matrix(_core.compose_poses(a, b)), matrix(a) @ matrix(b), atol=TOL)
    np.testing.assert_allclose(matrix(_core.invert_pose(a)), np.linalg.inv(matrix(a)), atol=TOL)
    n = plane / np.linalg.norm(plane)
    d = 1.0 / np.dot(plane, n)
    for pose in poses:
        centre = -rodrigues(pose[:3]).T @ pose[3:]
        assert _core.camera_plane_distance(pose, plane) == pytest.approx(abs(n @ centre + d),
                                                                        abs=1e-10)


def analytic_texture(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A smooth texture defined on plane coordinates (mm), evaluated exactly at any point."""
    return (128 + 50 * np.sin(0.9 * u) * np.cos(0.7 * v) + 40 * np.sin(0.31 * u + 0.53 * v)
            + 25 * np.cos(1.7 * v - 0.4 * u))


def render(pose: np.ndarray, K: np.ndarray, depth: float, size=(160, 160)) -> np.ndarray:
    """Ray-cast a camera onto the plane Z = depth (world), texture sampled analytically."""
    h, w = size
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    rays_cam = np.linalg.inv(K) @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    R = rodrigues(pose[:3])
    centre = -R.T @ pose[3:]
    rays_world = R.T @ rays_cam
    s = (depth - centre[2]) / rays_world[2]
    X = centre[:, None] + s * rays_world
    return analytic_texture(X[0], X[1]).reshape(h, w)


def test_rendered_frame_reproduced_by_transfer_warp():
    """A frame ray-cast from a known plane and pose equals frame 0 warped by H_k H_0^-1."""
    K = np.array([[150.0, 0, 79.5], [0, 150.0, 79.5], [0, 0, 1]])
    depth = 30.0
    plane = np.array([0.0, 0.0, -1.0 / depth])  # n = (0,0,1), d = -30: the plane Z = 30
    pose0 = np.array([0.02, -0.01, 0.0, 0.0, 0.0, 0.0])
    posek = np.array([0.05, 0.03, 0.1, 1.5, -1.0, 2.0])
    frame0 = render(pose0, K, depth)
    framek = render(posek, K, depth)
    H = _core.transfer_homography(posek, pose0, plane, camera_matrix=K)  # frame 0 -> frame k
    warped = cv2.warpPerspective(frame0.astype(np.float32), H, (160, 160),
                                 flags=cv2.INTER_CUBIC, borderValue=-1)
    valid = cv2.warpPerspective(np.ones((160, 160), np.float32), H, (160, 160),
                                flags=cv2.INTER_NEAREST) > 0
    valid = cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8),
                      borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    assert valid.mean() > 0.5
    err = np.abs(warped[valid] - framek[valid])
    # Interpolation error only: texture range ~230 grey levels, cubic resampling.
    assert err.mean() < 0.5
    assert err.max() < 5.0


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: _core.induced_homography(np.zeros(5), np.array([0, 0, -0.03])),
         "cam_from_world: expected 6 values, got 5"),
        (lambda: _core.induced_homography(np.full(6, np.nan), np.array([0, 0, -0.03])),
         "cam_from_world: contains NaN"),
        (lambda: _core.induced_homography(np.zeros(6), np.zeros(3)), "plane: pi = n/d must be"),
        (lambda: _core.frame_to_reference(np.zeros((3, 5)), np.array([0, 0, -0.03]), np.eye(3)),
         r"cams_from_world: expected shape \(N, 6\), got \(3, 5\)"),
        (lambda: _core.frame_to_reference(np.zeros((3, 6)), np.array([0, 0, -0.03]),
                                          np.zeros((3, 3))),
         "camera_matrix: matrix is singular"),
        (lambda: _core.angle_axis_from_rotation(np.ones((3, 3))), "not a rotation matrix"),
    ],
)
def test_bad_input_messages(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_reference_index_out_of_range():
    with pytest.raises(IndexError, match="reference: index 5 outside"):
        _core.frame_to_reference(np.zeros((3, 6)), np.array([0, 0, -0.03]), np.eye(3),
                                 reference=5)


def test_a_pose_through_a_registered_pair_and_the_plane_is_exact():
    """estimation.bundle.pose_through_pair: the other frame of a pair from one frame's pose,
    the pair's homography (any scale or sign) and the plane, in either direction."""
    from fusedmosaic.estimation.bundle import pose_through_pair

    K = np.array([[300.0, 0, 150], [0, 300.0, 150], [0, 0, 1]])
    plane = np.array([0.01, -0.005, -1 / 30])
    rng = np.random.default_rng(0)

    def H(p):
        R = _core.rotation_from_angle_axis(p[:3])
        return K @ (R - np.outer(p[3:], plane)) @ np.linalg.inv(K)

    for _ in range(5):
        pose_l, pose_m = (np.r_[rng.normal(0, 0.1, 3), rng.normal(0, 3, 3)] for _ in range(2))
        H_lm = H(pose_l) @ np.linalg.inv(H(pose_m))
        assert np.allclose(pose_through_pair(2.7 * H_lm, pose_l, True, plane, K), pose_m,
                           atol=1e-9)
        assert np.allclose(pose_through_pair(-1.3 * H_lm, pose_m, False, plane, K), pose_l,
                           atol=1e-9)
    # a degenerate homography gives no pose
    for known_is_l in (True, False):
        assert pose_through_pair(np.zeros((3, 3)), np.zeros(6), known_is_l, plane, K) is None


def test_homography_parallax_tells_rotation_from_translation():
    """estimation.plane.homography_parallax: 0 for pairs of a camera that only rotated, about
    baseline / depth for one that translated (the start-up's no-parallax test)."""
    from types import SimpleNamespace

    from fusedmosaic.estimation.plane import homography_parallax

    K = np.array([[300.0, 0, 150], [0, 300.0, 150], [0, 0, 1]])
    plane = np.array([0.0, 0.0, -1 / 30])  # 30 mm in front of the world's camera

    def pair(pose):  # frame l = the world's camera, frame m at `pose`
        R = _core.rotation_from_angle_axis(pose[:3])
        H_m = K @ (R - np.outer(pose[3:], plane)) @ np.linalg.inv(K)
        return SimpleNamespace(H_lm=np.linalg.inv(H_m))

    turned = [pair(np.r_[0.0, 0.0, a, 0.0, 0.0, 0.0]) for a in (0.1, 0.5, 1.0)]
    moved = [pair(np.r_[0.0, 0.0, 0.1, t, 0.0, 0.0]) for t in (1.5, 3.0, 6.0)]  # mm
    assert homography_parallax(turned, K) < 1e-9
    assert homography_parallax(moved, K) == pytest.approx(6.0 / 30, rel=0.1)
    assert np.isnan(homography_parallax([], K))
