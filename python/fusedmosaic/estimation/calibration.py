"""Camera intrinsics and the EM sensor's hand-eye transform from a tracked checkerboard recording.

Paper 000 (Sec. 4.1) pre-calibrates the fetoscope (intrinsics and lens distortion) and computes
the hand-eye transform "from a sequence of images of a checkerboard as well as synchronized
sensor poses". This module does both from one recording in the dataset layout (frames/ or a
video, frames.csv, tracking.csv; camera.yaml optional, its image size checked):

1. The board's inner corners are found in every ``every``-th frame (OpenCV's
   findChessboardCorners + cornerSubPix, findChessboardCornersSB when that fails) and put in one
   order: board x along a row, y down the columns, z into the board, the square diagonally
   outside corner (0, 0) dark. That needs a board whose columns + rows (inner corners) is odd;
   otherwise it is symmetric under a half turn and only the intrinsics are computed.
2. Intrinsics: cv2.calibrateCameraExtended over at most ``max_views`` detections spread over
   the recording, with 0 / 4 / 5 / 8 distortion coefficients (or, for a wide-angle scope,
   cv2.fisheye.calibrate: OpenCV's fisheye model, 0 or 4 coefficients, its standard errors
   from cv2.fisheye.projectPoints' Jacobian, the extrinsics eliminated); views whose RMS
   reprojection error is over 3x the median (and over 1 px) are dropped once and the
   calibration repeated. Then every detection's pose is solved with these intrinsics; views
   whose largest corner error is over 3x the median (and over 1 px) are rejected (corners
   found off the squares' corners, e.g. where a circular field of view cuts the board) and
   the intrinsics computed
   again without them. A focal length with a standard error over 2 % is refused.
3. Hand-eye: every detection gives cam_from_board C_k (solvePnP with the intrinsics) and the
   tracker gives tracker_from_sensor A_k at the frame time (interpolated as the datasets are),
   with A_k X C_k = B for the unknown X = sensor_from_camera and B = tracker_from_board. X starts
   from the relative motions (A_j^-1 A_i) X = X (C_j C_i^-1) (rotation axes aligned, Park &
   Martin's least squares; then the translations linearly), B from the mean of A_k X C_k; then
   X and B are refined together by SciPy least_squares on the tracker residuals
   A_k^-1 B C_k^-1 X^-1 (rotation in the sensor frame / rot_sigma_deg, translation in the tracker
   frame / trans_sigma_mm, Huber beyond 3 sigma): the maximum-likelihood estimate when the
   board poses from the images are much more precise than the tracker (tens of µm against the
   EM tracker's tenths of mm). Standard errors come from the Jacobian at the solution.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from fusedmosaic.io.calibration import (
    FISHEYE_COUNT,
    LENS_MODELS,
    Camera,
    project_points,
    undistort_points,
)

DISTORTION_FLAGS = {
    0: cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    4: cv2.CALIB_FIX_K3,
    5: 0,
    8: cv2.CALIB_RATIONAL_MODEL,
}


def _fisheye_flag(name: str) -> int:
    """cv2.fisheye.calibrate's flag: OpenCV 4 numbers them apart (cv2.fisheye.CALIB_*), OpenCV
    5 shares cv2.CALIB_* with calibrateCamera."""
    return int(getattr(cv2.fisheye, name, None) or getattr(cv2, name))


FISHEYE_FLAGS = {  # the fisheye model: k1..k4, or none (the pure equidistant projection)
    0: sum(_fisheye_flag(f"CALIB_FIX_K{i}") for i in range(1, 5)),
    4: 0,
}
MIN_VIEWS = 4  # calibrateCamera's minimum for K + distortion is lower; 4 keeps it determined
MIN_HAND_EYE_VIEWS = 3
MIN_RELATIVE_ROTATION_DEG = 5.0  # pairs of views rotating less say little about X's rotation
OUTLIER_VIEW_FACTOR = 3.0
MAX_FOCAL_RELATIVE_STD = 0.02  # above it the views are too alike to calibrate from
# Tracker noise beyond which the fit is not a tracker's noise but a wrong input (an EM tracker:
# ~1 deg / 1 mm at worst, paper 000's Sigma_EMT).
MAX_TRACKER_SIGMA = (5.0, 5.0)
HUBER_SIGMAS = 3.0


@dataclass
class CalibrationOptions:
    """board_cols x board_rows inner corners (OpenCV's pattern size), squares of square_mm.

    lens_model : "pinhole" (OpenCV's standard model) or "fisheye" (OpenCV's fisheye model, for
        wide-angle lenses); see io.calibration.LENS_MODELS.
    distortion : number of OpenCV distortion coefficients estimated (0, 4: k1 k2 p1 p2, 5: + k3,
        8: rational model; fisheye: 0 or 4, k1..k4; None: 5, fisheye 4).
    every : detect the board in every n-th frame only.
    max_views : at most this many detections (evenly spread) enter the intrinsics; all enter
        the hand-eye.
    rot_sigma_deg, trans_sigma_mm : the EM tracker's noise, weighting its rotation against its
        translation in the hand-eye fit (paper 000's Sigma_EMT defaults: 1 deg, 1 mm).
    time_offset : "auto" (estimated: estimate_time_offset), or seconds: the tracker sample of
        the frame at time t is the one at t + time_offset (0: the clocks agree).
    max_time_offset_s : the largest offset "auto" considers.
    threads : frames searched for the board in parallel.
    """

    board_cols: int = 9
    board_rows: int = 6
    square_mm: float = 2.0
    distortion: int | None = None
    lens_model: str = "pinhole"
    every: int = 1
    max_views: int = 60
    rot_sigma_deg: float = 1.0
    trans_sigma_mm: float = 1.0
    time_offset: float | str = "auto"
    max_time_offset_s: float = 0.1
    threads: int = 2

    def validate(self, names: dict[str, str] | None = None) -> None:
        """ValueError for a bad field; `names` maps fields to what the messages call them
        (e.g. the CLI's flags)."""
        def name(key: str) -> str:
            return (names or {}).get(key, key)

        for key in ("board_cols", "board_rows"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 2:
                raise ValueError(f"{name(key)}: expected an integer >= 2 (inner corners), got "
                                 f"{value!r}")
        if self.lens_model not in LENS_MODELS:
            raise ValueError(f"{name('lens_model')}: expected one of {', '.join(LENS_MODELS)}, "
                             f"got {self.lens_model!r}")
        allowed = FISHEYE_FLAGS if self.lens_model == "fisheye" else DISTORTION_FLAGS
        if self.distortion is not None and self.distortion not in allowed:
            raise ValueError(f"{name('distortion')}: the {self.lens_model} model takes one of "
                             f"{sorted(allowed)} coefficients, got {self.distortion!r}")
        for key in ("every", "max_views", "threads"):
            if int(getattr(self, key)) != getattr(self, key) or getattr(self, key) < 1:
                raise ValueError(f"{name(key)}: expected an integer >= 1, got "
                                 f"{getattr(self, key)!r}")
        if self.max_views < MIN_VIEWS:
            raise ValueError(f"{name('max_views')}: must be >= {MIN_VIEWS}, got {self.max_views}")
        if self.time_offset != "auto" and not (
                isinstance(self.time_offset, (int, float)) and np.isfinite(self.time_offset)
                and abs(self.time_offset) <= 10.0):
            raise ValueError(f"{name('time_offset')}: expected 'auto' or seconds within +-10, "
                             f"got {self.time_offset!r}")
        for key in ("square_mm", "rot_sigma_deg", "trans_sigma_mm", "max_time_offset_s"):
            value = getattr(self, key)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name(key)}: must be a number > 0, got {value!r}")

    @property
    def coefficients(self) -> int:
        """Distortion coefficients estimated (the default: 5, fisheye 4)."""
        if self.distortion is not None:
            return int(self.distortion)
        return FISHEYE_COUNT if self.lens_model == "fisheye" else 5

    @property
    def pattern(self) -> tuple[int, int]:
        return (int(self.board_cols), int(self.board_rows))

    @property
    def oriented(self) -> bool:
        """A board whose orientation the corners fix (columns + rows odd)."""
        return (self.board_cols + self.board_rows) % 2 == 1

    def board_points(self) -> np.ndarray:
        """(rows * cols, 3) float32 inner corners in the board frame (mm), row by row."""
        j, i = np.mgrid[0:self.board_rows, 0:self.board_cols]
        return (np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], 1)
                * self.square_mm).astype(np.float32)


@dataclass
class HandEyeResult:
    """sensor_from_camera and tracker_from_board (4, 4); per-view tracker residuals
    (rotation deg, translation mm) and inlier flags; standard errors of the hand-eye rotation
    (deg) and translation (mm), the largest over directions, from the tracker noise alone (views
    taken as independent, the board poses as exact: errors of the intrinsics add to them; see
    bench/bench_calibration.py for measured errors)."""

    sensor_from_camera: np.ndarray
    tracker_from_board: np.ndarray
    rotation_residual_deg: np.ndarray
    translation_residual_mm: np.ndarray
    inlier: np.ndarray
    rotation_std_deg: float
    translation_std_mm: float
    tracker_sigma: tuple[float, float] = (0.0, 0.0)
    closed_form: np.ndarray | None = None  # X from the relative motions, before refinement
    cost: float = 0.0  # 0.5 * sum of Huber(residual / sigma)^2 at the solution


@dataclass
class CalibrationResult:
    """What calibrate_recording found: the camera (intrinsics + distortion) for camera.yaml,
    the hand-eye (None without tracking, with a symmetric board, or when it failed:
    hand_eye_error says why) and a JSON-able report."""

    camera: Camera
    hand_eye: np.ndarray | None
    report: dict = field(default_factory=dict)
    hand_eye_error: str | None = None  # why the hand-eye failed (the intrinsics stand)


# ------------------------------------------------------------------------------------------------
# Board detection
# ------------------------------------------------------------------------------------------------


def detect_board(image: np.ndarray, options: CalibrationOptions) -> np.ndarray | None:
    """The board's inner corners (rows * cols, 2) float64 in the canonical order (module doc),
    sub-pixel; None when the whole board is not found."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    pattern = options.pattern
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    found, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
    if not found:  # the sector-based detector finds boards the classic one misses (blur, noise)
        found, corners = cv2.findChessboardCornersSB(gray, pattern,
                                                     flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not found:
            return None
    c = corners.reshape(-1, 2)
    spacing = np.median(np.linalg.norm(np.diff(c.reshape(pattern[1], pattern[0], 2), axis=1),
                                       axis=2))
    half = int(np.clip(0.4 * spacing, 2, 11))
    corners = cv2.cornerSubPix(gray, np.ascontiguousarray(corners, np.float32), (half, half),
                               (-1, -1), (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50,
                                          1e-3))
    return _canonical_order(gray, corners.reshape(-1, 2).astype(np.float64), pattern)


def _canonical_order(gray: np.ndarray, c: np.ndarray,
                     pattern: tuple[int, int]) -> np.ndarray | None:
    """Reorder detected corners so that board x runs along a row and y down the columns as a
    right-handed frame seen from the front (z into the board), and the interior squares whose
    corner indices i + j are even are the dark ones (so the square diagonally outside corner
    (0, 0) is dark too): this decides between the two half-turn orders when cols + rows is odd.
    The colours are read at the centres of all interior squares (not the outer ones, which a
    circular field of view may hide); None when they do not tell dark from light."""
    cols, rows = pattern
    grid = c.reshape(rows, cols, 2)
    a, b = grid[0, 1] - grid[0, 0], grid[1, 0] - grid[0, 0]
    if a[0] * b[1] - a[1] * b[0] < 0:  # mirrored: image y points down, so det > 0 is right
        grid = grid[:, ::-1]
    centres = 0.25 * (grid[:-1, :-1] + grid[:-1, 1:] + grid[1:, :-1] + grid[1:, 1:])
    spacing = float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2)))
    radius = max(int(0.15 * spacing), 1)
    values = np.array([[_mean_intensity(gray, p, radius) for p in row] for row in centres])
    jj, ii = np.mgrid[0:rows - 1, 0:cols - 1]
    even, odd = values[(ii + jj) % 2 == 0], values[(ii + jj) % 2 == 1]
    # Each class must be one colour, apart from the other: its spread well under the gap.
    gap = abs(float(np.median(even)) - float(np.median(odd)))
    spread = max(np.percentile(np.abs(even - np.median(even)), 90),
                 np.percentile(np.abs(odd - np.median(odd)), 90)) if odd.size else 0.0
    if odd.size == 0 or gap < 10.0 or spread > 0.5 * gap:
        return None
    if np.median(even) > np.median(odd):
        grid = grid[::-1, ::-1]
    return grid.reshape(-1, 2)


def _mean_intensity(gray: np.ndarray, p: np.ndarray, radius: int) -> float:
    x, y = (int(round(v)) for v in p)
    h, w = gray.shape
    patch = gray[max(y - radius, 0):min(y + radius + 1, h), max(x - radius, 0):min(x + radius + 1,
                                                                                     w)]
    return float(patch.mean()) if patch.size else 128.0


# ------------------------------------------------------------------------------------------------
# Intrinsics
# ------------------------------------------------------------------------------------------------


def calibrate_intrinsics(
    image_points: list[np.ndarray], size: tuple[int, int], options: CalibrationOptions
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int], np.ndarray]:
    """K (3, 3), distortion (options.coefficients,), per-view RMS reprojection error (px) of the
    views kept, the indices (into image_points) of the views dropped as outliers, and the
    standard errors of fx, fy, cx, cy (px; OpenCV's, from the Jacobian)."""
    obj = options.board_points()
    keep = list(range(len(image_points)))
    dropped: list[int] = []
    for attempt in range(2):
        K, dist, rms, std = _calibrate(obj, [image_points[i] for i in keep], size, options)
        if attempt == 1:
            break
        limit = max(OUTLIER_VIEW_FACTOR * float(np.median(rms)), 1.0)
        bad = [i for i, r in zip(keep, rms, strict=True) if r > limit]
        if not bad or len(keep) - len(bad) < MIN_VIEWS:
            break
        dropped = bad
        keep = [i for i in keep if i not in bad]
    return K, dist, rms, dropped, std


def _calibrate(obj, points, size, options):
    if options.lens_model == "fisheye":
        return _calibrate_fisheye(obj, points, size, options)
    n = options.coefficients
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    _, K, dist, _, _, std, _, rms = cv2.calibrateCameraExtended(
        [obj] * len(points), [p.astype(np.float32).reshape(-1, 1, 2) for p in points], size,
        None, None, flags=DISTORTION_FLAGS[n], criteria=criteria)
    dist = dist.reshape(-1)[:max(n, 4)]
    if n == 0:
        dist = np.zeros(4)
    return K, dist, rms.reshape(-1), std.reshape(-1)[:4]


def _calibrate_fisheye(obj, points, size, options):
    """cv2.fisheye.calibrate (skew fixed at 0), with what calibrateCameraExtended gives and it
    does not: per-view RMS errors, and the standard errors of fx, fy, cx, cy from the
    Jacobian of cv2.fisheye.projectPoints (columns fx fy cx cy k1..k4 rvec tvec skew), each
    view's extrinsics eliminated (Schur complement), scaled by the residual variance."""
    n = options.coefficients
    flags = (_fisheye_flag("CALIB_RECOMPUTE_EXTRINSIC") | _fisheye_flag("CALIB_FIX_SKEW")
             | FISHEYE_FLAGS[n])
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    obj = np.asarray(obj, np.float64).reshape(1, -1, 3)
    image = [np.asarray(p, np.float64).reshape(1, -1, 2) for p in points]
    try:
        _, K, D, rvecs, tvecs = cv2.fisheye.calibrate([obj] * len(image), image, size, None,
                                                      None, flags=flags, criteria=criteria)
    except cv2.error as exc:
        raise ValueError(f"OpenCV's fisheye calibration failed on these views "
                         f"({str(exc.err).strip()})") from None
    free = 4 + n  # fx fy cx cy (+ k1..k4)
    normal = np.zeros((free, free))
    squares, rms = 0.0, []
    for p, r, t in zip(image, rvecs, tvecs, strict=True):
        proj, J = cv2.fisheye.projectPoints(obj, np.reshape(r, (1, 1, 3)),
                                            np.reshape(t, (1, 1, 3)), K, D)
        e = proj.reshape(-1) - p.reshape(-1)
        A, B = J[:, :free], J[:, 8:14]
        W = A.T @ B
        normal += A.T @ A - W @ np.linalg.solve(B.T @ B, W.T)
        squares += float(e @ e)
        rms.append(np.sqrt(float(e @ e) / (e.size / 2)))
    dof = max(sum(p.size for p in image) - free - 6 * len(image), 1)
    std = np.sqrt(np.abs(np.diag(np.linalg.pinv(normal))) * squares / dof)[:4]
    return K, D.reshape(-1), np.array(rms), std


def board_poses(image_points: list[np.ndarray], K: np.ndarray, dist: np.ndarray,
                options: CalibrationOptions) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_board (N, 4, 4) of each detection (solvePnP, iterative; a fisheye lens's
    corners undistorted to normalised coordinates first) and its largest corner reprojection
    error (px)."""
    obj = options.board_points()
    poses = np.tile(np.eye(4), (len(image_points), 1, 1))
    worst = np.zeros(len(image_points))
    model = options.lens_model
    for k, p in enumerate(image_points):
        if model == "fisheye":
            ok, r, t = cv2.solvePnP(obj, undistort_points(p, K, dist, model).reshape(-1, 1, 2),
                                    np.eye(3), None, flags=cv2.SOLVEPNP_ITERATIVE)
        else:
            ok, r, t = cv2.solvePnP(obj, p.reshape(-1, 1, 2), K, dist,
                                    flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:  # pragma: no cover - a detected planar board always has a pose
            raise ValueError("solvePnP failed on a detected board")
        poses[k, :3, :3] = cv2.Rodrigues(r)[0]
        poses[k, :3, 3] = t.reshape(3)
        proj = project_points(obj, K, dist, model, r, t)
        worst[k] = np.linalg.norm(proj - p, axis=1).max()
    return poses, worst


# ------------------------------------------------------------------------------------------------
# Hand-eye
# ------------------------------------------------------------------------------------------------


def calibrate_hand_eye(
    tracker_from_sensor: np.ndarray,
    cam_from_board: np.ndarray,
    *,
    rot_sigma_deg: float = 1.0,
    trans_sigma_mm: float = 1.0,
    reweight: bool = True,
) -> HandEyeResult:
    """X = sensor_from_camera and B = tracker_from_board from A_k X C_k = B over views k (module
    doc). With ``reweight`` the second fit weights by the noise the first one's inliers show,
    otherwise both by the given noise. ValueError when the views do not determine X (fewer than
    3, or rotations about fewer than two distinct axes)."""
    A = np.asarray(tracker_from_sensor, np.float64)
    C = np.asarray(cam_from_board, np.float64)
    if A.shape != C.shape or A.ndim != 3 or A.shape[1:] != (4, 4):
        raise ValueError(f"hand-eye: expected two (N, 4, 4) stacks, got {A.shape} and {C.shape}")
    n = A.shape[0]
    if n < MIN_HAND_EYE_VIEWS:
        raise ValueError(f"hand-eye: {n} views with a tracker sample; at least "
                         f"{MIN_HAND_EYE_VIEWS} are needed (and more, rotated about different "
                         "axes, for a precise result)")
    X0 = _hand_eye_from_motions(A, C)
    B0 = _mean_transform(A @ X0 @ C)
    Ainv = np.linalg.inv(A)
    Cinv = np.linalg.inv(C)

    def unpack(p):
        X, B = X0.copy(), B0.copy()
        X[:3, :3] = X0[:3, :3] @ Rotation.from_rotvec(p[0:3]).as_matrix()
        X[:3, 3] = X0[:3, 3] + p[3:6]
        B[:3, :3] = B0[:3, :3] @ Rotation.from_rotvec(p[6:9]).as_matrix()
        B[:3, 3] = B0[:3, 3] + p[9:12]
        return X, B

    def residuals(p, sigma=None):
        X, B = unpack(p)
        predicted = B @ Cinv @ np.linalg.inv(X)  # tracker_from_sensor seen through the board
        rot = Rotation.from_matrix((Ainv @ predicted)[:, :3, :3]).as_rotvec()
        r = np.hstack([rot, predicted[:, :3, 3] - A[:, :3, 3]])
        return r if sigma is None else (r / sigma).ravel()

    # The given noise weights the first fit; the noise its inliers show weights the second
    # (rotation against translation matters, and users rarely know their tracker's).
    sigma = np.array([np.deg2rad(rot_sigma_deg)] * 3 + [trans_sigma_mm] * 3)
    p = np.zeros(12)
    for attempt in range(2):
        fit = least_squares(residuals, p, args=(sigma,), method="trf", loss="huber",
                            f_scale=HUBER_SIGMAS, x_scale="jac")
        p = fit.x
        r = residuals(p)
        inlier = np.abs(r / sigma).max(axis=1) <= HUBER_SIGMAS
        if attempt == 1 or not reweight or inlier.sum() < MIN_HAND_EYE_VIEWS:
            break
        seen = np.sqrt(np.mean(r[inlier] ** 2, axis=0))
        sigma = np.repeat([max(seen[:3].mean(), 1e-9), max(seen[3:].mean(), 1e-12)], 3)
    X, B = unpack(p)
    JtJ = fit.jac.T @ fit.jac
    eig = np.linalg.eigvalsh(JtJ)
    if eig[0] <= 1e-12 * eig[-1]:
        raise ValueError("hand-eye: the views do not determine it (rotate the scope about at "
                         "least two different axes between views)")
    dof = max(r.size - 12, 1)
    cov = np.linalg.inv(JtJ) * (2.0 * fit.cost / dof)
    return HandEyeResult(
        sensor_from_camera=X,
        tracker_from_board=B,
        rotation_residual_deg=np.rad2deg(np.linalg.norm(r[:, :3], axis=1)),
        translation_residual_mm=np.linalg.norm(r[:, 3:], axis=1),
        inlier=inlier,
        rotation_std_deg=float(np.rad2deg(np.sqrt(np.linalg.eigvalsh(cov[0:3, 0:3])[-1]))),
        translation_std_mm=float(np.sqrt(np.linalg.eigvalsh(cov[3:6, 3:6])[-1])),
        tracker_sigma=(float(np.rad2deg(sigma[0])), float(sigma[3])),
        closed_form=X0,
        cost=float(fit.cost),
    )


def estimate_time_offset(tracker_at, cam_from_board: np.ndarray, first: HandEyeResult,
                         max_offset_s: float) -> dict:
    """The offset d (s) such that the tracker sample interpolated at t + d belongs to the frame
    at t: the d whose hand-eye fit leaves the smallest cost, over the views the tracker covers
    at every d in [-max_offset_s, max_offset_s] and with the noise of the first fit held (so the
    costs compare). A grid of 5 ms steps, then a bounded search around its best; the standard
    error from the cost's curvature (cost = chi^2 / 2). Applied only when it is determined (the
    scope moved while filmed: error < 10 ms, not at the bound) and differs from 0 by more than
    two standard errors. `tracker_at(d)` -> (tracker_from_sensor of the views it covers, mask).
    """
    from scipy.optimize import minimize_scalar

    _, low = tracker_at(-max_offset_s)
    _, high = tracker_at(max_offset_s)
    common = low & high
    sigma = first.tracker_sigma

    def cost(d: float) -> float:
        A, ok = tracker_at(d)
        keep = common[ok]
        return calibrate_hand_eye(A[keep], cam_from_board[common], rot_sigma_deg=sigma[0],
                                  trans_sigma_mm=sigma[1], reweight=False).cost

    if common.sum() < MIN_HAND_EYE_VIEWS:
        return {"estimated": False, "applied_s": 0.0,
                "reason": f"fewer than {MIN_HAND_EYE_VIEWS} views tracked at every offset"}
    grid = np.arange(-max_offset_s, max_offset_s + 1e-9, 0.005)
    costs = np.array([cost(d) for d in grid])
    i = int(np.argmin(costs))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    search = minimize_scalar(cost, bounds=(lo, hi), method="bounded", options={"xatol": 1e-4})
    best = float(search.x)
    h = 0.002
    curvature = (cost(best + h) + cost(best - h) - 2 * search.fun) / h ** 2
    std = float(1 / np.sqrt(curvature)) if curvature > 0 else float("inf")
    out = {"estimated": True, "estimate_s": float(best), "std_s": std,
           "views": int(common.sum()), "applied_s": 0.0}
    at_bound = abs(abs(best) - max_offset_s) < 0.005
    if not np.isfinite(std) or std > 0.01 or at_bound:
        out["reason"] = ("not determined: the scope must move while filmed" if not at_bound
                         else f"at the search bound +-{max_offset_s:g} s")
    elif abs(best) > 2 * std:
        out["applied_s"] = float(best)
    return out


def _hand_eye_from_motions(A: np.ndarray, C: np.ndarray, max_views: int = 60) -> np.ndarray:
    """Closed-form X from pairs of views: (A_j^-1 A_i) X = X (C_j C_i^-1). Rotation: the
    rotation vectors satisfy alpha = R_X beta (aligned by SciPy's align_vectors, the least
    squares solution); translation: (R_A - I) t_X = R_X t_B - t_A, stacked (least squares)."""
    idx = np.linspace(0, A.shape[0] - 1, min(A.shape[0], max_views)).round().astype(int)
    idx = np.unique(idx)
    i, j = np.triu_indices(idx.size, 1)
    i, j = idx[i], idx[j]
    MA = np.linalg.inv(A[j]) @ A[i]
    MB = C[j] @ np.linalg.inv(C[i])
    alpha = Rotation.from_matrix(MA[:, :3, :3]).as_rotvec()
    beta = Rotation.from_matrix(MB[:, :3, :3]).as_rotvec()
    use = np.linalg.norm(beta, axis=1) > np.deg2rad(MIN_RELATIVE_ROTATION_DEG)
    axes = beta[use] / np.linalg.norm(beta[use], axis=1, keepdims=True) if use.any() else beta[:0]
    spread = np.linalg.svd(axes, compute_uv=False) if len(axes) >= 2 else np.zeros(2)
    if len(axes) < 2 or spread[1] < 0.1 * spread[0]:
        raise ValueError(
            "hand-eye: the views do not determine it: between views the scope must rotate by "
            f"more than {MIN_RELATIVE_ROTATION_DEG:g} deg about at least two different axes "
            f"({int(use.sum())} pairs of views rotate that much"
            + (", all about nearly one axis)" if len(axes) >= 2 else ")"))
    R_X, _ = Rotation.align_vectors(alpha[use], beta[use])
    R = R_X.as_matrix()
    lhs = (MA[use, :3, :3] - np.eye(3)).reshape(-1, 3)
    rhs = (np.einsum("ij,njk->nik", R, MB[use, :3, 3:4])[..., 0] - MA[use, :3, 3]).reshape(-1)
    t = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = R, t
    return X


def _tracker_from_sensor(sensor_from_tracker: np.ndarray) -> np.ndarray:
    """(N, 4, 4) inverses of (N, 6) [angle-axis, t] poses."""
    R = Rotation.from_rotvec(sensor_from_tracker[:, :3]).inv()
    T = np.tile(np.eye(4), (sensor_from_tracker.shape[0], 1, 1))
    T[:, :3, :3] = R.as_matrix()
    T[:, :3, 3] = -R.apply(sensor_from_tracker[:, 3:])
    return T


def _mean_transform(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = Rotation.from_matrix(T[:, :3, :3]).mean().as_matrix()
    out[:3, 3] = T[:, :3, 3].mean(0)
    return out


# ------------------------------------------------------------------------------------------------
# A recording
# ------------------------------------------------------------------------------------------------


def calibrate_recording(
    root: str | Path,
    options: CalibrationOptions | None = None,
    *,
    fps: float = 25.0,
    progress: bool = False,
) -> CalibrationResult:
    """Calibrate from a recording folder (module doc). ValueError naming the folder or file for
    a missing recording, a board found in too few frames, or views that cannot give the
    hand-eye."""
    from fusedmosaic.io.calibration import read_camera_yaml
    from fusedmosaic.io.dataset import _read_frame_times
    from fusedmosaic.io.video import FrameSource

    o = CalibrationOptions() if options is None else options
    o.validate()
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"{root}: recording folder not found")
    t_start = time.perf_counter()
    given = read_camera_yaml(root / "camera.yaml") if (root / "camera.yaml").exists() else None
    frames = FrameSource.open(root, expected_size=None if given is None else given.size)
    first = frames[0]
    size = (first.shape[1], first.shape[0])
    if given is None:  # every frame the size of the first
        frames.expected_size, frames.size_source = size, f"its first frame {size}"
    frame_ids, timestamps = _read_frame_times(root, len(frames), fps)
    tried = np.arange(0, len(frames), o.every)

    def detect(k: int):
        return detect_board(frames[int(k)], o)

    with ThreadPoolExecutor(max_workers=o.threads) as pool:
        results = pool.map(detect, tried)
        if progress:
            from tqdm import tqdm
            results = tqdm(results, total=tried.size, desc="board search", unit="frame")
        found = list(results)
    views = np.array([k for k, c in zip(tried, found, strict=True) if c is not None], int)
    points = [c for c in found if c is not None]
    t_detect = time.perf_counter() - t_start
    pattern = f"{o.board_cols}x{o.board_rows}"
    if len(views) < MIN_VIEWS:
        raise ValueError(
            f"{root}: the {pattern} board (inner corners, columns x rows) was found in "
            f"{len(views)} of {tried.size} frames searched; calibration needs at least "
            f"{MIN_VIEWS} views (15-30 at varied angles are advised). Check the board size "
            "(inner corners, not squares) and that the whole board is in view")

    chosen = np.unique(np.linspace(0, len(views) - 1, min(len(views), o.max_views))
                       .round().astype(int))
    # Views whose corners the camera cannot explain (corners found off the squares' corners,
    # e.g. where a circular field of view cuts the board; outliers of the intrinsics) give
    # neither intrinsics nor hand-eye: rejected, and the intrinsics computed again without them.
    usable = np.ones(len(views), bool)
    for _ in range(2):
        use = chosen[usable[chosen]]
        K, dist, rms, dropped, std = calibrate_intrinsics([points[i] for i in use], size, o)
        poses, pnp_max = board_poses(points, K, dist, o)
        limit = max(OUTLIER_VIEW_FACTOR * float(np.median(pnp_max)), 1.0)
        rejected = (pnp_max > limit) & usable
        rejected[use[dropped]] = True
        if not rejected.any():
            break
        usable &= ~rejected
        if usable[chosen].sum() < MIN_VIEWS:
            break
    chosen, dropped = use, [int(i) for i in dropped]
    focal_std = float(max(std[0] / K[0, 0], std[1] / K[1, 1]))
    if not np.isfinite(focal_std) or focal_std > MAX_FOCAL_RELATIVE_STD:
        raise ValueError(
            f"{root}: the {len(chosen)} views do not determine the focal length (standard error "
            f"{100 * focal_std:.1f} %): film the board from more, different angles (tilted by "
            "20-40 degrees in different directions, at different distances)")
    usable &= pnp_max <= limit
    usable[chosen[dropped]] = False
    camera = Camera(size[0], size[1], camera_matrix=K,
                    distortion=None if o.coefficients == 0 else dist, lens_model=o.lens_model,
                    pixel_size_um=None if given is None else given.pixel_size_um,
                    fov_mask_radius=None if given is None else given.fov_mask_radius)
    report: dict = {
        "recording": str(root.resolve()),
        "board": {"inner_corners": [o.board_cols, o.board_rows], "square_mm": o.square_mm},
        "image_size": list(size),
        "frames": len(frames),
        "frames_searched": int(tried.size),
        "board_found": int(len(views)),
        "frames_with_board": [int(frame_ids[v]) for v in views],
        "frames_rejected": {"corner_reprojection_px_over": limit, "frames": [
            int(frame_ids[v]) for v in views[~usable]]},
        "intrinsics": {
            "views": int(len(chosen) - len(dropped)),
            "frames": [int(frame_ids[views[i]]) for k, i in enumerate(chosen)
                       if k not in dropped],
            "views_dropped_as_outliers": [int(frame_ids[views[chosen[i]]]) for i in dropped],
            "rms_px": float(np.sqrt(np.mean(rms ** 2))),
            "view_rms_px_max": float(rms.max()),
            "camera_matrix": K.tolist(),
            "std_fx_fy_cx_cy_px": [float(v) for v in std],
            "lens_model": o.lens_model,
            "distortion": [float(v) for v in dist],
            "distortion_coefficients": o.coefficients,
        },
        "timings_s": {"board_search": t_detect},
    }

    hand_eye, error = None, None
    tracking_path = root / "tracking.csv"
    if not tracking_path.exists():
        report["hand_eye"] = {"skipped": f"no tracking.csv in {root}"}
    elif not o.oriented:
        report["hand_eye"] = {"skipped": (
            f"the {pattern} board looks the same after a half turn (columns + rows even), so "
            "its pose is ambiguous; use a board with an odd sum, e.g. 9x6")}
    else:
        t0 = time.perf_counter()
        try:
            hand_eye, report["hand_eye"] = _hand_eye_stage(
                tracking_path, timestamps[views[usable]], frame_ids[views[usable]],
                poses[usable], [p for p, u in zip(points, usable, strict=True) if u], K, dist, o)
        except ValueError as exc:
            error = str(exc)
            report["hand_eye"] = {"failed": error}
        report["timings_s"]["hand_eye"] = time.perf_counter() - t0
    report["timings_s"]["total"] = time.perf_counter() - t_start
    return CalibrationResult(camera, hand_eye, report, error)


def _hand_eye_stage(tracking_path: Path, times: np.ndarray, ids: np.ndarray, poses: np.ndarray,
                    points: list[np.ndarray], K: np.ndarray, dist: np.ndarray,
                    o: CalibrationOptions) -> tuple[np.ndarray, dict]:
    """The hand-eye of calibrate_recording from the usable views (frame times, ids, board
    poses, corners) and its report; ValueError naming tracking.csv when it fails or the result
    is implausible."""
    from fusedmosaic.io.tracking import _time, interpolate_camera_poses, read_tracking_csv

    samples = read_tracking_csv(tracking_path)

    def tracker_at(delta: float) -> tuple[np.ndarray, np.ndarray]:
        # interpolate_camera_poses with no hand-eye gives sensor_from_tracker as [r, t].
        pose, ok = interpolate_camera_poses(samples, times + delta, None, allow_outside=True,
                                            source=str(tracking_path))
        return _tracker_from_sensor(pose[ok]), ok

    A, valid = tracker_at(0.0)
    if valid.sum() < MIN_HAND_EYE_VIEWS:
        ts = samples.timestamps[samples.valid]
        span = f"[{_time(ts[0])}, {_time(ts[-1])}] s" if ts.size else "(no valid sample)"
        raise ValueError(
            f"{tracking_path}: {int(valid.sum())} of {len(times)} views have a tracker sample; "
            f"the tracker spans {span}, the views [{_time(times[0])}, {_time(times[-1])}] s "
            "(frame times come from frames.csv, or --fps without it; both clocks in seconds)")
    try:
        he = calibrate_hand_eye(A, poses[valid], rot_sigma_deg=o.rot_sigma_deg,
                                trans_sigma_mm=o.trans_sigma_mm)
        offset = {"estimated": False, "applied_s": 0.0}
        if o.time_offset == "auto":
            offset = estimate_time_offset(tracker_at, poses, he, o.max_time_offset_s)
        elif o.time_offset != 0:
            offset = {"estimated": False, "applied_s": float(o.time_offset)}
        if offset["applied_s"] != 0.0:
            A, valid = tracker_at(offset["applied_s"])
            he = calibrate_hand_eye(A, poses[valid], rot_sigma_deg=he.tracker_sigma[0],
                                    trans_sigma_mm=he.tracker_sigma[1])
    except ValueError as exc:
        raise ValueError(f"{tracking_path}: {exc}") from None
    n = int(valid.sum())
    outliers = n - int(he.inlier.sum())
    if (outliers > 0.5 * n or he.tracker_sigma[0] > MAX_TRACKER_SIGMA[0]
            or he.tracker_sigma[1] > MAX_TRACKER_SIGMA[1]):
        raise ValueError(
            f"{tracking_path}: the tracker and the board disagree: {outliers} of {n} views "
            f"beyond 3 sigma, noise seen {he.tracker_sigma[0]:.2f} deg / "
            f"{he.tracker_sigma[1]:.2f} mm per axis (an EM tracker: tenths). Check that "
            "tracking.csv holds tracker_from_sensor (not its inverse) with quaternions x, y, z, "
            "w and translations in mm, the board's --square-mm, and the frame times (frames.csv "
            "or --fps)")
    # What the tracker alone places: board corners through the tracked camera pose.
    predicted = np.linalg.inv(he.sensor_from_camera) @ np.linalg.inv(A) @ he.tracker_from_board
    obj = o.board_points()
    through_tracker = np.array([
        np.mean(np.linalg.norm(project_points(
            obj, K, dist, o.lens_model, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3]) - points[k],
            axis=1))
        for T, k in zip(predicted, np.flatnonzero(valid), strict=True)])
    used = ids[valid]
    return he.sensor_from_camera, {
        "views": n,
        "tracker_time_offset": offset,
        "views_without_tracker_sample": [int(v) for v in ids[~valid]],
        "views_beyond_3_sigma": [int(v) for v in used[~he.inlier]],
        "sensor_from_camera": he.sensor_from_camera.tolist(),
        "tracker_from_board": he.tracker_from_board.tolist(),
        "sensor_from_camera_closed_form": he.closed_form.tolist(),
        "rotation_std_from_tracker_noise_deg": he.rotation_std_deg,
        "translation_std_from_tracker_noise_mm": he.translation_std_mm,
        "tracker_sigma_deg": he.tracker_sigma[0],
        "tracker_sigma_mm": he.tracker_sigma[1],
        "tracker_residual_rotation_deg_rms": float(np.sqrt(np.mean(
            he.rotation_residual_deg ** 2))),
        "tracker_residual_translation_mm_rms": float(np.sqrt(np.mean(
            he.translation_residual_mm ** 2))),
        "per_view": {"frame": used.tolist(),
                     "rotation_residual_deg": he.rotation_residual_deg.round(4).tolist(),
                     "translation_residual_mm": he.translation_residual_mm.round(4).tolist(),
                     "board_through_tracker_px": through_tracker.round(3).tolist()},
        "board_through_tracker_px_median": float(np.median(through_tracker)),
        "first_fit_noise": {"rot_sigma_deg": o.rot_sigma_deg,
                            "trans_sigma_mm": o.trans_sigma_mm},
    }


def camera_model_difference(a: Camera, b: Camera, region: float = 0.8) -> float:
    """Largest distance (px) between where cameras a and b put the same rays, over a 17x17 grid
    spanning the central ``region`` of a's image: how far apart two calibrations of one camera
    are, whatever the split between focal length, principal point and distortion."""
    lo, hi = (1 - region) / 2, (1 + region) / 2
    u, v = np.meshgrid(np.linspace(lo, hi, 17) * (a.width - 1),
                       np.linspace(lo, hi, 17) * (a.height - 1))
    px = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
    rays = undistort_points(px, a.camera_matrix, a.distortion, a.lens_model, criteria=(
        cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12))
    rays = np.hstack([rays, np.ones((rays.shape[0], 1))])
    back = project_points(rays, b.camera_matrix, b.distortion, b.lens_model)
    return float(np.linalg.norm(back - px.reshape(-1, 2), axis=1).max())


def write_calibration(out: str | Path, result: CalibrationResult) -> list[str]:
    """camera.yaml, hand_eye.txt (when found) and calibration.json into ``out``, atomically
    (io.OutputWriter); returns the names written."""
    from fusedmosaic.io.calibration import write_camera_yaml
    from fusedmosaic.io.output import OutputWriter
    from fusedmosaic.io.tracking import write_hand_eye

    with OutputWriter(out, record="calibrate") as w:
        write_camera_yaml(w.path("camera.yaml"), result.camera)
        if result.hand_eye is not None:
            write_hand_eye(w.path("hand_eye.txt"), result.hand_eye)
        w.write_json("calibration.json", result.report)
        return w.written()
