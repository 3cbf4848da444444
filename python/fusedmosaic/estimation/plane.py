"""Plane initialisation for the EMT methods (seed 000, Sec. 3.3-3.4).

A registered pair gives a homography H_lm (pixels, m -> l). In normalised coordinates and in
camera m's frame it factorises as s Hn = R - t pi_m^T, with (R, t) = l_from_m known from the tracker
poses: 9 linear equations in the 4 unknowns (s, pi_m). The plane in camera m is moved to the world
(virtual camera): for X_m = R_m X + t_m, the condition -pi_m^T X_m = 1 becomes
-(R_m^T pi_m)^T X = 1 + pi_m^T t_m, so pi = R_m^T pi_m / (1 + pi_m^T t_m).
Each pair is noisy (tracker noise enters through (R, t)), so pairs with the widest baselines are
used and combined robustly (median normal direction and median inverse depth). A refinement of the
point-transfer error with the noisy tracker poses held fixed was tried and removed: it fits the
plane to the pose noise (4-6 deg normal error on SYN-150 against 0.24 deg for the median).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.distance import cdist

from fusedmosaic import _core


def plane_depths(poses: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """(N,) distance along each camera's optical axis to the plane pi (pi . X + 1 = 0), for
    (N, 6) cam_from_world poses: > 0 when the plane is in front of the camera, <= 0 or inf when
    it is behind it or parallel to the axis."""
    poses = np.atleast_2d(np.asarray(poses, np.float64))
    plane = np.asarray(plane, np.float64)
    out = np.empty(len(poses))
    for i, pose in enumerate(poses):
        R = _core.rotation_from_angle_axis(pose[:3])
        centre, axis = -R.T @ pose[3:], R[2]  # the optical axis (camera z) in the world
        along = float(plane @ axis)
        out[i] = -(plane @ centre + 1.0) / along if along != 0.0 else np.inf
    return out


def camera_baseline_mm(poses: np.ndarray) -> float:
    """The largest distance between the centres of (N, 6) cam_from_world poses (world units,
    mm): how far the cameras moved, which is what makes the plane's distance observable (0
    for fewer than two)."""
    poses = np.atleast_2d(np.asarray(poses, np.float64))
    centres = np.array([-_core.rotation_from_angle_axis(p[:3]).T @ p[3:] for p in poses])
    if len(centres) < 2:
        return 0.0
    return point_set_diameter(centres)


# Rows compared per block by _max_distance: 512 x N distances (4 MB at 1000 points, 60 MB
# at 15 000; the whole N x N x 3 difference array of a 6000-frame run took 2.3 GB; review).
_DISTANCE_BLOCK = 512


def _max_distance(points: np.ndarray) -> float:
    """The largest Euclidean distance between two rows of (N, d) `points`, by blocks of rows:
    exact, in memory O(_DISTANCE_BLOCK * N)."""
    best = 0.0
    for i in range(0, len(points), _DISTANCE_BLOCK):
        best = max(best, float(cdist(points[i:i + _DISTANCE_BLOCK], points[i:]).max()))
    return best


def _hull_points(points: np.ndarray) -> np.ndarray | None:
    """Indices of the points on the convex hull of (N, d) points (its vertices, and the points
    qhull found coplanar with a facet, which rounding may have kept off the vertex list); None
    when the points span fewer than d dimensions (qhull cannot build the hull)."""
    try:
        hull = ConvexHull(points)
    except QhullError:
        return None
    return np.union1d(hull.vertices, hull.coplanar[:, 0] if len(hull.coplanar) else [])


def point_set_diameter(points: np.ndarray) -> float:
    """The largest distance between two of the (N, d) points, exactly as over all pairs: the two
    farthest points are vertices of their convex hull, so only the hull's points are compared
    (a few dozen for a camera path in 3-D). Flat or collinear sets (qhull needs a full-
    dimensional hull) are projected on their own span (SVD; distances kept) and the hull of the
    projection taken; a set too thin for that, or a hull of many points, is compared by
    blocks (_max_distance), exact too."""
    points = np.asarray(points, np.float64)
    if not np.isfinite(points).all():  # NaN, as over all pairs (not qhull's error or a max of 0)
        return float("nan")
    points = np.unique(points, axis=0)
    if len(points) < 2:
        return 0.0
    if len(points) <= points.shape[1] + 1:
        return _max_distance(points)
    on_hull = _hull_points(points)
    if on_hull is None:  # flat or collinear: the hull of the points in their own span
        centred = points - points.mean(axis=0)
        _, s, vt = np.linalg.svd(centred, full_matrices=False)
        rank = int(np.sum(s > s[0] * 1e-9)) if s[0] > 0 else 0
        if rank >= 2:
            on_hull = _hull_points(centred @ vt[:rank].T)
        elif rank == 1:  # along a line: the points at (or within rounding of) its two ends
            t = centred @ vt[0]
            tie = 1e-9 * (t.max() - t.min())
            on_hull = np.flatnonzero((t <= t.min() + tie) | (t >= t.max() - tie))
    if on_hull is None:
        return _max_distance(points)
    return _max_distance(points[on_hull.astype(int)])


# Below this ratio of the cameras' spread (camera_baseline_mm) to their distance from the plane
# the images show no parallax the plane could be measured by: at a focal length of ~300 px, 1 %
# moves a point by ~3 px across the frame. A camera held still (50 frames, centres within 3.9
# mm by the tracker's noise) gave a plane 3.7e4 mm away (truth 35 mm), 1e-4; hand-held and SYN
# sequences 0.2-0.5; translations in metres or micrometres keep it (both shrink or grow).
MIN_BASELINE_RATIO = 0.01


def baseline_ratio(poses: np.ndarray, plane: np.ndarray) -> float:
    """camera_baseline_mm of (N, 6) cam_from_world poses over their median distance along the
    optical axis to the plane pi (its absolute value: a plane behind them counts as well): below
    MIN_BASELINE_RATIO the images cannot tell where the plane is, and the mosaic does not
    depend on it (0 for a plane at infinity or parallel to the axes; NaN for fewer than two
    poses)."""
    depths = np.abs(plane_depths(poses, plane))
    if len(depths) < 2:
        return float("nan")
    return camera_baseline_mm(poses) / float(np.median(depths))


# The registered homographies' own parallax (homography_parallax) above which a start-up is not
# taken for one without parallax, whatever its cameras' spread against its plane says: a plane
# fitted to 2 pairs of a moving camera behind a 55 px field stop lay so far away that the
# spread looked like 0.01 of its depth while the pairs showed 2.5. Measured: a camera held
# still 0.0016, turning about its axis (with the hand-eye offset) 0.02-0.027, a 0.3 mm hover
# 0.02, hand-held 0.56 (90th percentiles over the start-up's pairs).
MAX_NOMINAL_PARALLAX = 0.1


def homography_parallax(pairs, K: np.ndarray) -> float:
    """The 90th percentile over registered pairs (PairMatch) of s_max / s_min - 1 for the
    singular values of K^-1 H_lm K: 0 for a camera that only rotated (the normalised
    homography is then a rotation), ~ baseline / depth for one that translated; NaN without
    pairs."""
    Kinv = np.linalg.inv(K)
    spread = []
    for p in pairs:
        s = np.linalg.svd(Kinv @ p.H_lm @ K, compute_uv=False)
        spread.append(s[0] / s[2] - 1.0 if s[2] > 0 else np.inf)
    return float(np.percentile(spread, 90)) if spread else float("nan")


def plane_facing(poses: np.ndarray, distance_mm: float) -> np.ndarray:
    """pi of the plane perpendicular to the (N, 6) cam_from_world poses' mean optical axis,
    distance_mm in front of their mean centre: a nominal plane for cameras that did not
    translate (its distance cannot be measured; the homographies between such cameras do not
    depend on it)."""
    poses = np.atleast_2d(np.asarray(poses, np.float64))
    Rs = [_core.rotation_from_angle_axis(p[:3]) for p in poses]
    centre = np.mean([-R.T @ p[3:] for R, p in zip(Rs, poses, strict=True)], axis=0)
    axis = np.sum([R[2] for R in Rs], axis=0)
    axis /= np.linalg.norm(axis)
    point = centre + distance_mm * axis  # pi . X + 1 = 0 through it, normal along the axis
    return -axis / float(axis @ point)


# World units (mm): two cameras' centres nearer than this give plane_from_pair no baseline (|t| of
# l_from_m is the distance between the centres): their homography does not depend on the plane.
MIN_PAIR_BASELINE = 1e-9


def plane_from_pair(H_lm: np.ndarray, K: np.ndarray, cam_l: np.ndarray,
                    cam_m: np.ndarray) -> np.ndarray | None:
    """pi (world) from one homography and two cam_from_world poses; None if ill-posed: the
    centres within MIN_PAIR_BASELINE, or a plane through the world's origin (no pi = n / d)."""
    Kinv = np.linalg.inv(K)
    Hn = Kinv @ H_lm @ K
    rel = _core.compose_poses(cam_l, _core.invert_pose(cam_m))  # l_from_m
    R = _core.rotation_from_angle_axis(rel[:3])
    t = rel[3:]
    if np.linalg.norm(t) < MIN_PAIR_BASELINE:
        return None
    # Unknowns u = [s, pi_x, pi_y, pi_z]: s Hn_ij + t_i pi_j = R_ij.
    A = np.zeros((9, 4))
    b = R.ravel()
    for i in range(3):
        for j in range(3):
            A[3 * i + j, 0] = Hn[i, j]
            A[3 * i + j, 1 + j] = t[i]
    u, *_ = np.linalg.lstsq(A, b, rcond=None)
    pi_m = u[1:]
    denom = 1.0 + pi_m @ cam_m[3:]
    if abs(denom) < 1e-9 or not np.isfinite(u).all():
        return None
    return _core.rotation_from_angle_axis(cam_m[:3]).T @ pi_m / denom


def _robust_combine(planes: np.ndarray) -> np.ndarray:
    inv_depth = np.median(np.linalg.norm(planes, axis=1))
    normals = planes / np.linalg.norm(planes, axis=1, keepdims=True)
    ref = np.median(normals, axis=0)
    normals *= np.sign(normals @ ref)[:, None]  # pi and -pi are different planes; align anyway
    n = np.median(normals, axis=0)
    return n / np.linalg.norm(n) * inv_depth


def estimate_plane(pairs, poses: np.ndarray, K: np.ndarray, *, max_pairs: int = 60,
                   source: str | None = None) -> np.ndarray:
    """Plane pi from registered pairs (PairMatch, frame ids index `poses`) and tracker poses.

    Raises ValueError when no registered pair with valid poses is available, or when none of
    them gives a plane, with why (the message starts with `source`, e.g. the dataset's folder,
    when given)."""
    where = f"{source}: " if source else ""
    usable = [p for p in pairs if p.ok and np.isfinite(poses[p.frame_l]).all()
              and np.isfinite(poses[p.frame_m]).all()]
    if not usable:
        ok = sum(1 for p in pairs if p.ok)
        raise ValueError(f"{where}cannot estimate the plane: no registered pair of frames with "
                         f"valid tracker poses ({ok} of {len(pairs)} pairs registered)")
    centres = {k: -(_core.rotation_from_angle_axis(poses[k][:3]).T @ poses[k][3:])
               for p in usable for k in (p.frame_l, p.frame_m)}
    baseline = np.array([np.linalg.norm(centres[p.frame_l] - centres[p.frame_m])
                         for p in usable])
    widest = np.argsort(-baseline)[:max_pairs]
    chosen = [usable[i] for i in widest]
    estimates = [plane_from_pair(p.H_lm, K, poses[p.frame_l], poses[p.frame_m]) for p in chosen]
    estimates = np.array([e for e in estimates if e is not None and np.isfinite(e).all()])
    if len(estimates) == 0:
        # Why, which the caller cannot tell: a tracker that froze (resending its last pose) put
        # every pair's cameras at one position, and this said only "every pair was degenerate"
        # (lba-emt then named no file either; review).
        still = int(np.sum(baseline[widest] < MIN_PAIR_BASELINE))
        if still == len(chosen):
            why = (f"the tracker poses of every registered pair ({len(usable)}) put its two "
                   "cameras at the same position, so no pair has a baseline the plane's "
                   "distance could be measured by (a frozen tracker resending one pose, or a "
                   "camera held perfectly still)")
        else:
            why = (f"of the {len(chosen)} registered pairs with the widest baselines, "
                   f"{still} have their two tracker poses at the same position and "
                   f"{len(chosen) - still} give no finite plane (a plane through the world's "
                   "origin, or non-finite poses or homographies)")
        raise ValueError(f"{where}cannot estimate the plane: {why}")
    return _robust_combine(estimates)
