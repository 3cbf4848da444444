"""The lens shared by the simulators' renderers (fetoscopy --lens-distortion, checkerboard): the
ideal pixel behind every raw sub-pixel sample, with the check that the lens model is invertible
over the frame."""

from __future__ import annotations

import cv2
import numpy as np

from fusedmosaic.io.calibration import undistort_points

# Iterated to convergence: a fetoscope's strong barrel lens needs more than io's default.
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-12)
ROUND_TRIP_TOLERANCE_PX = 1e-3
# Sub-pixel samples undistorted and checked at a time (whole rows of them), so that the
# temporaries stay near 0.2 GB whatever the frame size. A 1920x1080 grid at 3x3 samples (0.30
# GB itself) took 9.3 s and 0.52 GB peak RSS (blocks of 2^16: 13.2 s, 2^18: 10.0 s, 2^22:
# 11.6 s and 0.86 GB); in one go, checked through cv2.projectPoints and the (2N, 14) Jacobian
# its Python binding always returns, 37 s and 11 GB (review 47).
GRID_BLOCK_SAMPLES = 2**20


def ideal_pixel_grid(camera_matrix: np.ndarray, distortion: np.ndarray, lens_model: str,
                     width: int, height: int, supersample: int, what: str) -> np.ndarray:
    """(S H, S W, 2) ideal (undistorted, pinhole) pixel in camera_matrix's grid of every raw
    sub-pixel sample of a width x height frame (S = supersample; sample (i, j) of pixel (u, v)
    at (u + (i + 0.5) / S - 0.5, ...)) through the lens (OpenCV's standard model with 4, 5, 8
    or 12 coefficients, or its fisheye model), computed GRID_BLOCK_SAMPLES at a time.

    Raises ValueError naming ``what`` (the option that set the coefficients) when the model
    folds over within the frame: a raw sample whose undistortion does not project back onto
    it (within ROUND_TRIP_TOLERANCE_PX) has no ray, or two, and would render garbage or a
    double image."""
    K = np.asarray(camera_matrix, np.float64)
    d = np.asarray(distortion, np.float64)
    S = supersample
    out = np.empty((height * S, width * S, 2))
    u = (np.arange(width * S, dtype=np.float64) + 0.5) / S - 0.5
    rows = max(1, GRID_BLOCK_SAMPLES // (width * S))
    for top in range(0, height * S, rows):
        v = (np.arange(top, min(top + rows, height * S), dtype=np.float64) + 0.5) / S - 0.5
        raw = np.stack(np.broadcast_arrays(u[None, :], v[:, None]), -1).reshape(-1, 2)
        out[top:top + len(v)] = _undistort_checked(raw, K, d, lens_model, width, height,
                                                   what).reshape(len(v), width * S, 2)
    return out


def _undistort_checked(raw: np.ndarray, K: np.ndarray, d: np.ndarray, lens_model: str,
                       width: int, height: int, what: str) -> np.ndarray:
    """(N, 2) ideal pixels of raw pixels ``raw`` (N, 2), or ideal_pixel_grid's ValueError when
    one does not project back onto its raw pixel."""
    ideal = undistort_points(raw, K, d, lens_model, P=K, criteria=_CRITERIA)
    rays = np.linalg.solve(K, np.hstack([ideal, np.ones((len(ideal), 1))]).T).T
    back = distort_rays(rays, K, d, lens_model)
    if not np.all(np.abs(back - raw) < ROUND_TRIP_TOLERANCE_PX):  # NaN fails too
        raise ValueError(
            f"{what}: {d.tolist()} is not invertible over the {width}x{height} frame (the "
            "model folds over); use a milder lens"
        )
    return ideal


def distort_rays(rays: np.ndarray, camera_matrix: np.ndarray, distortion: np.ndarray,
                 lens_model: str) -> np.ndarray:
    """(N, 2) raw pixels of camera-frame rays (N, 3) through the lens: cv2.projectPoints (or
    cv2.fisheye.projectPoints) at the identity pose, in NumPy, without the Jacobian the Python
    bindings always compute (2N x 14 float64). Standard model: 4, 5, 8 or 12 coefficients
    (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4]]]); fisheye: k1 k2 k3 k4. Skew (K[0, 1]) is left
    out, as cv2.projectPoints does."""
    K = np.asarray(camera_matrix, np.float64)
    d = np.asarray(distortion, np.float64).ravel()
    x, y = rays[:, 0] / rays[:, 2], rays[:, 1] / rays[:, 2]
    r2 = x * x + y * y
    if lens_model == "fisheye":
        if d.size != 4:
            raise ValueError(f"fisheye lens: expected 4 coefficients, got {d.size}")
        r = np.sqrt(r2)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (d[0] + t2 * (d[1] + t2 * (d[2] + t2 * d[3]))))
        # theta_d / r -> 1 on the axis (cv2: scale 1 at r < 1e-8)
        scale = np.divide(theta_d, r, out=np.ones_like(r), where=r >= 1e-8)
        xd, yd = x * scale, y * scale
    else:
        if d.size not in (4, 5, 8, 12):
            raise ValueError(f"standard lens: expected 4, 5, 8 or 12 coefficients, got {d.size}")
        c = np.zeros(12)
        c[:d.size] = d
        k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = c
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + r2 * (s1 + s2 * r2)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + r2 * (s3 + s4 * r2)
    return np.stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]], -1)


def ideal_border(camera_matrix: np.ndarray, distortion: np.ndarray, lens_model: str,
                 width: int, height: int, what: str | None = None) -> np.ndarray:
    """(P, 2) ideal pixels of the centres of a width x height frame's border pixels through the
    lens: an estimate of what the frame shows, without ideal_pixel_grid's cost. Given ``what``,
    with ideal_pixel_grid's fold check on them (the pixel centres are samples of its grid for
    an odd supersample: the grid would fail it too); without, none."""
    u, v = np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64)
    raw = np.concatenate([np.stack([u, 0 * u], 1), np.stack([u, 0 * u + height - 1], 1),
                          np.stack([0 * v, v], 1), np.stack([0 * v + width - 1, v], 1)])
    K, d = np.asarray(camera_matrix, np.float64), np.asarray(distortion, np.float64)
    if what is not None:
        return _undistort_checked(raw, K, d, lens_model, width, height, what)
    return undistort_points(raw, K, d, lens_model, P=K, criteria=_CRITERIA)


def on_inner_branch(pixels: np.ndarray, cam_points: np.ndarray, camera_matrix: np.ndarray,
                    distortion: np.ndarray, lens_model: str) -> bool:
    """Whether camera-frame points cam_points (N, 3) that project to pixels (N, 2) are what
    the frame shows there: their undistortion is their own direction, not a ray beyond the
    lens model's fold (whose projection also lands in the frame, but which the renderer, going
    from pixels to rays, never shows)."""
    x = undistort_points(pixels, camera_matrix, distortion, lens_model, criteria=_CRITERIA)
    z = cam_points[:, 2:3]
    return bool(np.all(z > 0)) and bool(
        np.all(np.abs(x - cam_points[:, :2] / z) < 1e-6 * (1 + np.abs(x))))
