"""Image-free scenes for the solver core: cameras on a circle above a tilted plane and point
correspondences made by exact plane transfer (plus seeded pixel noise).

The fetoscopy simulator (fetoscopy.py) renders images and goes through feature matching; these
scenes skip both, so the C++ BundleAdjuster and SlidingWindow can be checked against an exact
optimum (tests/test_bundle_adjuster.py) and timed on problems of a chosen size
(bench/bench_solvers.py). Poses are cam_from_world [r, t] and the plane pi = n / d as in design.md.
"""

from __future__ import annotations

import numpy as np

from fusedmosaic import _core


def circle_scene(
    n_frames: int,
    rng: np.random.Generator,
    *,
    laps: float = 1.0,
    radius: float = 8.0,
    depth: float = 35.0,
    normal: tuple[float, float, float] = (0.08, -0.05, 1.0),
    rotation_jitter: float = 0.002,
    height_jitter: float = 0.3,
) -> tuple[np.ndarray, np.ndarray]:
    """True poses (N, 6) of a camera circling `laps` times (radius mm) `depth` mm above the plane
    with unit normal along `normal`, and that plane pi (3,). The camera rocks smoothly (0.04 rad
    about x and y, 0.1 rad about z over two laps); rotation_jitter (rad) and height_jitter (mm)
    add seeded Gaussian noise per frame."""
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    plane = n / (-depth * n[2])
    theta = np.linspace(0.0, 2.0 * np.pi * laps, n_frames, endpoint=False)
    poses = np.zeros((n_frames, 6))
    for k, th in enumerate(theta):
        r = np.array([0.04 * np.sin(th), 0.04 * np.cos(th), 0.1 * np.sin(0.5 * th)])
        r += rng.normal(0.0, rotation_jitter, 3)
        center = np.array([radius * np.cos(th), radius * np.sin(th),
                           rng.normal(0.0, height_jitter)])
        poses[k] = np.r_[r, -_core.rotation_from_angle_axis(r) @ center]
    return poses, plane


def plane_point_pairs(
    poses: np.ndarray,
    plane: np.ndarray,
    camera_matrix: np.ndarray,
    size: int,
    rng: np.random.Generator,
    *,
    n_points: int = 30,
    noise_px: float = 0.0,
    max_distance: float | None = None,
    max_pairs: int | None = None,
) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """Pairs (l, m, points_l, points_m), l > m, nearest camera centres first: points uniform in
    frame m (size x size pixels) transferred through the plane into frame l, n_points of those
    that land inside it, points_l with seeded Gaussian noise (noise_px). A pair with fewer
    inside is skipped; pairs farther apart than max_distance (mm) are not tried; at most
    max_pairs are returned."""
    centers = np.array([-_core.rotation_from_angle_axis(p[:3]).T @ p[3:] for p in poses])
    candidates = sorted(
        (float(np.linalg.norm(centers[l] - centers[m])), l, m)
        for m in range(len(poses)) for l in range(m + 1, len(poses))
    )
    pairs = []
    for distance, l, m in candidates:
        if max_distance is not None and distance > max_distance:
            break
        pts_m = rng.uniform(0, size, (8 * n_points, 2))
        pts_l = _core.transfer_points(pts_m, poses[l], poses[m], plane, camera_matrix)
        inside = np.all((pts_l >= 0) & (pts_l < size), axis=1)
        if inside.sum() < n_points:
            continue
        pts_m, pts_l = pts_m[inside][:n_points], pts_l[inside][:n_points]
        pairs.append((l, m, pts_l + rng.normal(0.0, noise_px, pts_l.shape), pts_m))
        if max_pairs is not None and len(pairs) == max_pairs:
            break
    return pairs
