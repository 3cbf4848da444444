"""The lens shared by the simulators' renderers (fetoscopy --lens-distortion, checkerboard): the
ideal pixel behind every raw sub-pixel sample, with the check that the lens model is invertible
over the frame."""

from __future__ import annotations

import cv2
import numpy as np

from fusedmosaic.io.calibration import project_points, undistort_points

# Iterated to convergence: a fetoscope's strong barrel lens needs more than io's default.
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-12)
ROUND_TRIP_TOLERANCE_PX = 1e-3


def ideal_pixel_grid(camera_matrix: np.ndarray, distortion: np.ndarray, lens_model: str,
                     width: int, height: int, supersample: int, what: str) -> np.ndarray:
    """(S H, S W, 2) ideal (undistorted, pinhole) pixel in camera_matrix's grid of every raw
    sub-pixel sample of a width x height frame (S = supersample; sample (i, j) of pixel (u, v)
    at (u + (i + 0.5) / S - 0.5, ...)) through the lens (OpenCV's standard or fisheye model).

    Raises ValueError naming ``what`` (the option that set the coefficients) when the model
    folds over within the frame: a raw sample whose undistortion does not project back onto
    it (within ROUND_TRIP_TOLERANCE_PX) has no ray, or two, and would render garbage or a
    double image."""
    K = np.asarray(camera_matrix, np.float64)
    d = np.asarray(distortion, np.float64)
    S = supersample
    v, u = np.mgrid[0:height * S, 0:width * S].astype(np.float64)
    raw = np.stack([(u + 0.5) / S - 0.5, (v + 0.5) / S - 0.5], -1).reshape(-1, 2)
    ideal = undistort_points(raw, K, d, lens_model, P=K, criteria=_CRITERIA)
    rays = np.linalg.solve(K, np.hstack([ideal, np.ones((len(ideal), 1))]).T).T
    back = project_points(rays, K, d, lens_model)
    if not np.all(np.abs(back - raw) < ROUND_TRIP_TOLERANCE_PX):  # NaN fails too
        raise ValueError(
            f"{what}: {d.tolist()} is not invertible over the {width}x{height} frame (the "
            "model folds over); use a milder lens"
        )
    return ideal.reshape(height * S, width * S, 2)


def ideal_border(camera_matrix: np.ndarray, distortion: np.ndarray, lens_model: str,
                 width: int, height: int) -> np.ndarray:
    """(P, 2) ideal pixels of the centres of a width x height frame's border pixels through the
    lens (no fold check: an estimate of what the frame shows, for ideal_pixel_grid's cost)."""
    u, v = np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64)
    raw = np.concatenate([np.stack([u, 0 * u], 1), np.stack([u, 0 * u + height - 1], 1),
                          np.stack([0 * v, v], 1), np.stack([0 * v + width - 1, v], 1)])
    return undistort_points(raw, np.asarray(camera_matrix, np.float64),
                            np.asarray(distortion, np.float64), lens_model,
                            P=np.asarray(camera_matrix, np.float64), criteria=_CRITERIA)


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
