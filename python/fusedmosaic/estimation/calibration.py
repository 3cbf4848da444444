"""Camera intrinsics and the EM sensor's hand-eye transform from a tracked checkerboard recording.

Paper 000 (Sec. 4.1) pre-calibrates the fetoscope (intrinsics and lens distortion) and computes
the hand-eye transform "from a sequence of images of a checkerboard as well as synchronized
sensor poses". This module does both from one recording in the dataset layout (frames/ or a
video, frames.csv, tracking.csv; camera.yaml optional, its image size checked; everything
readable is read and checked before the board search):

1. The board's inner corners are found in every ``every``-th frame (OpenCV's
   findChessboardCorners + cornerSubPix, findChessboardCornersSB when that fails) and put in one
   order: board x along a row, y down the columns, z into the board, the square diagonally
   outside corner (0, 0) dark. That needs a board whose columns + rows (inner corners) is odd;
   otherwise it is symmetric under a half turn and only the intrinsics are computed.
2. Views: frames whose corners lie within 1 % of the image diagonal (RMS) of an earlier
   frame's show the same board pose (a still scope, a pause at a view, a return to it) and
   count as one view; fewer than MIN_VIEWS distinct views are refused.
3. Intrinsics: cv2.calibrateCameraExtended over one frame of each distinct view (at most
   ``max_views``, evenly spread over the recording), with 0 / 4 / 5 / 8 distortion
   coefficients (or, for a wide-angle scope, cv2.fisheye.calibrate: OpenCV's fisheye model, 0
   or 4 coefficients, its standard errors from cv2.fisheye.projectPoints' Jacobian, the
   extrinsics eliminated); views whose RMS reprojection error is over 3x the median (and over
   1 px) are dropped once and the calibration repeated. Then every detection's pose is solved
   with these intrinsics; views whose largest corner error is over 3x the median (and over 1
   px) are rejected (corners found off the squares' corners, e.g. where a circular field of
   view cuts the board) and the intrinsics computed again without them. A focal length with a
   standard error over 2 % is refused. How far the corners reach into the frame is reported
   (corner_reach: beyond it the model is extrapolated; warned below MIN_CORNER_REACH), and a
   model that folds over inside the frame, which `run` refuses, is named (_lens_fold).
4. Hand-eye: every detection gives cam_from_board C_k (solvePnP with the intrinsics) and the
   tracker gives tracker_from_sensor A_k, with A_k X C_k = B for the unknown X =
   sensor_from_camera and B = tracker_from_board. X starts from the relative motions
   (A_j^-1 A_i) X = X (C_j C_i^-1) (rotation axes aligned, Park & Martin's least squares; then
   the translations linearly), B from the mean of A_k X C_k; then X and B are refined together
   by SciPy least_squares on the tracker residuals A_k^-1 B C_k^-1 X^-1 (rotation in the
   sensor frame / rot_sigma_deg, translation in the tracker frame / trans_sigma_mm, Huber
   beyond 3 sigma): the maximum-likelihood estimate when the board poses from the images are
   much more precise than the tracker (tens of µm against the EM tracker's tenths of mm).
   - The clock offset (estimate_time_offset) from all frames, the tracker interpolated at the
     frame times by cubic splines (io.tracking, method "cubic"; the frames filmed while moving
     carry it); its standard error the larger of the cost's curvature's and a bootstrap over
     0.25 s blocks of frames (neighbouring frames' errors correlate: at 10 Hz the curvature's
     said 2.4-3x too little). With still views alone (the board lost to motion blur during the
     moves) the offset shows only at the rests' edges, where the interpolant decides: the
     standard error is then at least the distance to the linear interpolation's estimate.
   - The final fit uses the views held still (runs of frames whose corners move < 1 px), each
     paired with every raw tracker sample taken while it was filmed: no sample interpolated
     across a motion (a 10 Hz tracker's interpolation erred by 1-3 mm), each counted once, the
     noise seen the tracker's own. With fewer than MIN_STILL_VIEWS still views, all frames with
     the tracker interpolated (flagged in the report) by cubic splines: on the simulator's
     motions at 10 Hz (0.1 deg / 0.03 mm noise) the hand-eye translation errs 0.16-0.28 mm
     with them against 1.2-1.5 mm linear; at 40 Hz with 0.9 deg / 0.25 mm, 0.07-0.08 against
     0.11-0.18 mm. (Mosaicking keeps linear interpolation: with the EM tracker's noise, the
     spline through noisy samples placed emt's frames 6-25 % worse on SYN.)
   - The board's translations carry a free scale (tracker mm per board mm): a wrong
     --square-mm or a tracker not in mm shows as a scale off 1 and is refused (beyond 3 % and
     5 standard errors); a smaller significant one is kept in the fit.
   - Standard errors: a bootstrap over the distinct views (or 0.25 s blocks of frames),
     linearised (one Gauss-Newton step per replicate), beside the Jacobian's from the tracker
     noise; the larger RMS error magnitude is reported. Measured against the simulator: true /
     reported 0.9-1.5 over seeds (the Jacobian over interpolated frames said 4-10x too little).
"""

from __future__ import annotations

import time
import warnings
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
# RMS reprojection error (px) above which the camera model is suspect (a warning, and named in
# the hand-eye's disagreement): cornerSubPix finds a clear board's corners to ~0.05-0.2 px, so a
# model that fits the lens leaves about that (the simulator: 0.045 px; 0.34-0.43 px at 320x320
# with a strong pincushion), while a lens model lacking coefficients leaves a systematic error
# several times larger (--distortion 0 on the simulator's k1 = -0.3 lens: 10 views x 6 frames at
# 320x320, 0.87 px, cx 12 px off for a reported standard error of 0.75 px; its default 480x480
# recording, 1.23 px, cx 16.6 px off for 0.78 px). 0.5 px: above any fitting model's, below that.
MAX_REPROJECTION_RMS_PX = 0.5
# The board's corners reaching less than this fraction of the frame's radius (from the principal
# point: corner_reach) leave the lens model extrapolated over the periphery: a warning. Measured
# (simulate checkerboard's views at 20-70 mm, 20 views at 480x480, corners projected with 0.05
# px noise, the default k1 -0.3 lens and a fisheye one, 3-4 seeds each; the model's largest
# error against the truth within 0.9 of the frame's radius, every fit's RMS 0.07 px): reach
# 0.72-0.78, 0.29-0.59 px; 0.60-0.70, 0.41-23 px (mostly 0.5-2); below 0.60, 1.6-3570 px
# (median ~20; some models fold over). So below 60 % the periphery is wrong on every seed, and
# 70 % is the advice (README; the simulator's default views reach 68-73 %).
MIN_CORNER_REACH = 0.6
# Board normals (in the camera frame) of the intrinsics' views spreading less than this (RMS
# angle about their mean) are Zhang's degenerate case, parallel views: the focal length is not
# determined and OpenCV's standard error says nothing of it. Measured on the simulator (60 views
# at 480x480, corners with 0.02 px noise, the best a recording gives): at 0.35 deg RMS the
# standard error read 0.001 % for a focal length 9-14 % off (all views facing the board: 0.00
# deg, 2-46 % off over seeds, exit 0 before); at 0.66-1.05 deg it read 2.3-5.9 % (refused by
# MAX_FOCAL_RELATIVE_STD), at 1.3-1.4 deg 1.3-1.5 % with the error within it. So below 1 deg no
# recording calibrates honestly. `simulate checkerboard`'s default recording (tilts up to 35 deg)
# spreads 20.1 deg, its --tilt-deg 0 (all views facing the board) 0.03.
MIN_NORMAL_SPREAD_DEG = 1.0
# Tracker noise beyond which the fit is not a tracker's noise but a wrong input (an EM tracker:
# ~1 deg / 1 mm at worst, paper 000's Sigma_EMT).
MAX_TRACKER_SIGMA = (5.0, 5.0)
HUBER_SIGMAS = 3.0
# RMS of a standard normal within +-3: sqrt(1 - 6 phi(3) / (2 Phi(3) - 1)) (the noise seen from
# the inliers at HUBER_SIGMAS is divided by it)
TRUNCATED_RMS = 0.98658
# Frames whose corners lie within 1 % of the image diagonal (RMS) of an earlier frame's show
# the same view (a still scope, a pause): one view, not several independent ones.
REPEATED_VIEW_FRACTION = 0.01
# Consecutive frames whose corners move less than this (RMS, px) are a still view: the tracker
# samples taken meanwhile all measure its pose (at 30 mm and f = 480 px, 1 px is ~0.06 mm).
STILL_PX = 1.0
MIN_STILL_VIEWS = 6  # fewer distinct still views: the hand-eye from all frames, interpolated
# Independent groups of measurements (distinct still views, or blocks of frames) the hand-eye
# needs: fewer determine it poorly and leave its error unknown (the bootstrap needs them).
# More than this fraction of the still views with a tracker sample beyond 3 sigma: a warning.
# Measured (simulate checkerboard, 16 views x 6 frames, 320x320): tracker 80 ms late, the
# offset estimated: 1 of 16; --time-offset 0: 15 of 16 (the hand-eye 2.8 mm off for an
# expected 1.27 mm, the noise seen 0.75 mm for the tracker's 0.25); no delay, --time-offset
# 0.05: 15 of 16; no delay, estimated: 1 of 16.
STILL_VIEWS_BEYOND_FRACTION = 0.5
MIN_HAND_EYE_GROUPS = 6
BOOTSTRAP_REPLICATES = 400
BOOTSTRAP_BLOCK_S = 0.25  # without still views, the bootstrap resamples blocks of frames
# The clock offset shows where the pose changes while filmed: when the frames filmed while moving
# would determine it to no better than this standard error (filmed_motion_std), the recording is
# taken as still views alone and estimate_time_offset also weighs the interpolant's shape.
# Measured on the simulator (20 views, corners projected; 40 Hz and 10 Hz at 0.9 deg / 0.25 mm,
# 10 Hz at 0.1 / 0.03): every move filmed, 0.18-0.40 ms; the board kept through one or two of
# the 19 moves (3-6 moving frames), 0.46-2.3 ms; still views alone, inf. 2 ms: about one move
# filmed at the simulator's pace (its moves turn 43 deg and travel 20 mm (medians) in 0.16 s).
MAX_FILMED_MOTION_STD_S = 0.002
# estimate_time_offset's coarse scan picks the basin only when its least lies this many times
# below its median. Measured (checkerboard simulator, 40 Hz, 0.9 deg / 0.25 mm, roll 0, clocks
# agreeing): the turns' scan 11-85 x on bench_time_offset_se's configurations (6 x 6 seeds),
# 2.1-2.6 at tilt 12, 1.4-1.6 at tilt 8 and 1.09-1.38 at tilt 4-6, where its least lay 280-400
# ms off on 12 of 27 seeds (the search stayed there: +288 / -302 ms applied, the board scale
# then negative); the hand-eye cost's scan 25-44 x at tilt 4-8, every estimate within 0.6 ms
# of 0 (std 0.3-0.5 ms), none applied (31 seeds).
SCAN_CONTRAST = 2.0
# ... over a search range of at least +-this: a narrower one holds a single basin (the hand-eye
# cost's is ~25 ms wide at tilt 4, 3.5x its least at +-25 ms), so its scan is flat whatever the
# motion (+-4 ms: 3 steps) and the search cannot stray far.
SCAN_MIN_BOUND_S = 0.1
# Basins of the scan compared by the hand-eye's cost: the lowest ones, more than
# SCAN_BASIN_STEPS steps of 5 ms apart, and offset 0, those within SCAN_CONTRAST of its least.
SCAN_CANDIDATES = 3
SCAN_BASIN_STEPS = 3
# The hand-eye's cost scanned over SCAN_VIEWS views (evenly spread; the search after it uses
# all), each fit stopped after SCAN_NFEV evaluations (far from the offset a fit from the closed
# form took ~30 iterations; stopped early its cost stays higher, further above the least; at the
# offset it converges from the closed form): on the tilt 4-8 recordings above (140 views) the same
# estimates as 60 views fully fitted, for a third of the estimate's work (residuals of 0.38 M
# views evaluated against 1.13 M): the scan only picks the basin.
SCAN_VIEWS = 30
SCAN_NFEV = 10
# The board's scale against the tracker's (tracker mm per board mm) refused when off by more
# than this and by more than SCALE_SIGMAS standard errors: a wrong --square-mm, a board
# printed scaled, or a tracker not in mm.
MAX_SCALE_DEVIATION = 0.03
SCALE_SIGMAS = 5.0


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
    max_time_offset_s : the largest offset "auto" considers (an estimate at it is refused:
        the clocks may differ by more). Video capture lags by up to a few hundred ms; the search
        costs the same at any bound, but views within it of the tracker's ends or of a dropout
        (valid=0 samples) do not take part.
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
    max_time_offset_s: float = 0.5
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
        from fusedmosaic.io.tracking import MAX_TIME_OFFSET_S

        if self.time_offset != "auto" and not (
                isinstance(self.time_offset, (int, float)) and np.isfinite(self.time_offset)
                and abs(self.time_offset) <= MAX_TIME_OFFSET_S):
            raise ValueError(f"{name('time_offset')}: expected 'auto' or seconds within "
                             f"+-{MAX_TIME_OFFSET_S:g}, got {self.time_offset!r}")
        for key in ("square_mm", "rot_sigma_deg", "trans_sigma_mm", "max_time_offset_s"):
            value = getattr(self, key)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name(key)}: must be a number > 0, got {value!r}")
        # run / import / live correct offsets up to MAX_TIME_OFFSET_S: a larger bound could
        # only find one they refuse (--max-time-offset 20 was accepted).
        if self.max_time_offset_s > MAX_TIME_OFFSET_S:
            raise ValueError(f"{name('max_time_offset_s')}: must be at most "
                             f"{MAX_TIME_OFFSET_S:g} s (the clock offset run, import and live "
                             f"correct), got {self.max_time_offset_s!r}")

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
    (deg) and translation (mm), the largest over directions, and the RMS error magnitudes, from
    the tracker noise alone (views taken as independent, the board poses as exact: errors of
    the intrinsics add to them; bootstrap_hand_eye resamples groups of views instead)."""

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
    scale: float = 1.0  # board translations' scale (fit_scale), tracker mm per board mm
    scale_std: float = 0.0  # its standard error from the tracker noise (0: not fitted)
    rotation_rms_deg: float = 0.0  # sqrt(trace(covariance)): the RMS error magnitude
    translation_rms_mm: float = 0.0
    # (Jacobian (6N, P) of the residuals / sigma, those residuals (6N,), Huber weights (6N,))
    # at the solution: what bootstrap_hand_eye resamples.
    linearisation: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


@dataclass
class CalibrationResult:
    """What calibrate_recording found: the camera (intrinsics + distortion) for camera.yaml,
    the hand-eye (None without tracking, with a symmetric board, or when it failed:
    hand_eye_error says why) and a JSON-able report."""

    camera: Camera
    hand_eye: np.ndarray | None
    report: dict = field(default_factory=dict)
    hand_eye_error: str | None = None  # why the hand-eye failed (the intrinsics stand)
    # why `run` would refuse the camera (its lens model folds over inside the frame: _lens_fold)
    camera_error: str | None = None


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
    fit_scale: bool = False,
    start: HandEyeResult | None = None,
    linearise: bool = True,
    max_nfev: int | None = None,
) -> HandEyeResult:
    """X = sensor_from_camera and B = tracker_from_board from A_k X C_k = B over views k (module
    doc). With ``reweight`` the fits after the first weight by the noise the residuals show
    (HandEyeResult.tracker_sigma, iterated to agree with its inliers' within 5 %), otherwise
    the one fit by the given noise. With ``fit_scale`` the board's translations are scaled
    by a free factor (HandEyeResult.scale: tracker mm per board mm, 1 when the square size and
    the tracker's unit are right). ``start``: begin from that solution instead of the closed
    form. ``linearise``: keep what bootstrap_hand_eye needs (False: only the fit, e.g. to
    compare costs). ValueError when the views do not determine X (fewer than 3, or rotations
    about fewer than two distinct axes)."""
    A = np.asarray(tracker_from_sensor, np.float64)
    C = np.asarray(cam_from_board, np.float64)
    if A.shape != C.shape or A.ndim != 3 or A.shape[1:] != (4, 4):
        raise ValueError(f"hand-eye: expected two (N, 4, 4) stacks, got {A.shape} and {C.shape}")
    n = A.shape[0]
    if n < MIN_HAND_EYE_VIEWS:
        raise ValueError(f"hand-eye: {n} views with a tracker sample; at least "
                         f"{MIN_HAND_EYE_VIEWS} are needed (and more, rotated about different "
                         "axes, for a precise result)")
    if start is None:
        X0, scale0 = _hand_eye_from_motions(A, C, fit_scale=fit_scale)
        closed_form = X0
        B0 = _mean_transform(A @ X0 @ _scaled(C, scale0))
    else:
        X0, B0, closed_form = start.sensor_from_camera, start.tracker_from_board, start.closed_form
        scale0 = start.scale if fit_scale else 1.0
    Ainv = np.linalg.inv(A)
    Cinv = np.linalg.inv(C)
    n_par = 13 if fit_scale else 12

    def unpack(p):
        X, B = X0.copy(), B0.copy()
        X[:3, :3] = X0[:3, :3] @ Rotation.from_rotvec(p[0:3]).as_matrix()
        X[:3, 3] = X0[:3, 3] + p[3:6]
        B[:3, :3] = B0[:3, :3] @ Rotation.from_rotvec(p[6:9]).as_matrix()
        B[:3, 3] = B0[:3, 3] + p[9:12]
        return X, B, scale0 * (1.0 + p[12]) if fit_scale else 1.0

    def residuals(p, sigma=None):
        r = _tracker_residuals(A, Ainv, Cinv, *unpack(p))
        return r if sigma is None else (r / sigma).ravel()

    # The given noise weights the first fit; the noise the residuals show weights the next
    # (rotation against translation matters, and users rarely know their tracker's). Inliers
    # picked at 3x the given noise bias that low when the real noise is larger (3 deg / 1.5 mm
    # seen as 1.73 / 1.42 under the default 1 / 1, 0.5 / 3 as 0.48 / 1.60), so the first
    # reweighting takes the residuals' MAD (robust to up to half outliers, unbiased for
    # Gaussian noise), the next ones the RMS of the inliers at 3x the current noise, until it
    # agrees with the weights within 5 % (2-3 fits).
    sigma = np.array([np.deg2rad(rot_sigma_deg)] * 3 + [trans_sigma_mm] * 3)
    p = np.zeros(n_par)
    for attempt in range(6):
        fit = least_squares(residuals, p, args=(sigma,), method="trf", loss="huber",
                            f_scale=HUBER_SIGMAS, x_scale="jac", max_nfev=max_nfev)
        p = fit.x
        r = residuals(p)
        inlier = np.abs(r / sigma).max(axis=1) <= HUBER_SIGMAS
        if attempt == 5 or not reweight or inlier.sum() < MIN_HAND_EYE_VIEWS:
            break
        if attempt == 0:
            mad = 1.4826 * np.median(np.abs(r - np.median(r, axis=0)), axis=0)
            seen = np.array([mad[:3].mean(), mad[3:].mean()])
        else:
            # RMS of the inliers, made unbiased for Gaussian noise: the residuals' degrees of
            # freedom (the fit's parameters taken out) and the 3 sigma cut (TRUNCATED_RMS)
            rms = np.sqrt(np.sum(r[inlier] ** 2, axis=0) / (inlier.sum() - n_par / 6))
            seen = np.array([rms[:3].mean(), rms[3:].mean()]) / TRUNCATED_RMS
            if np.all(np.abs(seen / sigma[[0, 3]] - 1) < 0.05):
                break
        # Floors: absolute, and 1e-3 of the other's at a 100 mm lever (noise-free rotations
        # beside noisy translations weighted 1e8 to 5 left the fit's curvature singular).
        rot = max(seen[0], 1e-8, 1e-5 * seen[1])
        sigma = np.repeat([rot, max(seen[1], 1e-6, 0.1 * rot)], 3)
    X, B, scale = unpack(p)
    JtJ = fit.jac.T @ fit.jac
    eig = np.linalg.eigvalsh(JtJ)
    if eig[0] <= 1e-12 * eig[-1]:
        raise ValueError("hand-eye: the views do not determine it (rotate the scope about at "
                         "least two different axes between views)")
    dof = max(r.size - n_par, 1)
    cov = np.linalg.inv(JtJ) * (2.0 * fit.cost / dof)
    # The linearisation the bootstrap resamples: the Jacobian of the weighted residuals at the
    # solution (forward differences) and each residual's Huber weight there.
    linearisation = None
    if linearise:
        scaled_r = (r / sigma).ravel()
        J = np.empty((scaled_r.size, n_par))
        for i in range(n_par):
            step = np.zeros(n_par)
            step[i] = 1e-7
            J[:, i] = (residuals(p + step, sigma) - scaled_r) / 1e-7
        huber = np.minimum(1.0, HUBER_SIGMAS / np.maximum(np.abs(scaled_r), 1e-300))
        linearisation = (J, scaled_r, huber)
    return HandEyeResult(
        sensor_from_camera=X,
        tracker_from_board=B,
        rotation_residual_deg=np.rad2deg(np.linalg.norm(r[:, :3], axis=1)),
        translation_residual_mm=np.linalg.norm(r[:, 3:], axis=1),
        inlier=inlier,
        rotation_std_deg=float(np.rad2deg(np.sqrt(np.linalg.eigvalsh(cov[0:3, 0:3])[-1]))),
        translation_std_mm=float(np.sqrt(np.linalg.eigvalsh(cov[3:6, 3:6])[-1])),
        rotation_rms_deg=float(np.rad2deg(np.sqrt(np.trace(cov[0:3, 0:3])))),
        translation_rms_mm=float(np.sqrt(np.trace(cov[3:6, 3:6]))),
        tracker_sigma=(float(np.rad2deg(sigma[0])), float(sigma[3])),
        closed_form=closed_form,
        cost=float(fit.cost),
        scale=float(scale),
        scale_std=float(scale0 * np.sqrt(cov[12, 12])) if fit_scale else 0.0,
        linearisation=linearisation,
    )


def bootstrap_hand_eye(he: HandEyeResult, clusters: np.ndarray, *, replicates: int = 400,
                       seed: int = 0) -> dict:
    """Standard errors of a calibrate_hand_eye result from a bootstrap over clusters of views
    (``clusters``: (N,) label of each view; views of one label are resampled together: the
    frames or tracker samples of one board pose, whose errors are not independent). Each
    replicate draws the clusters with replacement and takes one Gauss-Newton step (Huber
    weights of the solution) from the solution on the drawn views: the refit, linearised, as
    the errors are small against the fit's curvature. Returns the per-axis standard errors (the
    largest over directions) and the RMS error magnitude (sqrt of the covariance's trace) of
    the rotation (deg) and the translation (mm), and of the scale when it was fitted; seeded
    (numpy Generator)."""
    J, r, huber = he.linearisation
    cov, g, kept = _linearised_bootstrap(J, r, huber, clusters, replicates, seed)
    n_par = J.shape[1]

    def stds(block: slice, unit: float) -> tuple[float, float]:
        c = cov[block, block] * unit ** 2
        return float(np.sqrt(np.linalg.eigvalsh(c)[-1])), float(np.sqrt(np.trace(c)))

    rot_axis, rot_rms = stds(slice(0, 3), np.rad2deg(1.0))
    trans_axis, trans_rms = stds(slice(3, 6), 1.0)
    out = {"clusters": int(g), "replicates": int(kept),
           "replicates_left_out": int(replicates - kept),
           "rotation_std_deg": rot_axis, "rotation_rms_deg": rot_rms,
           "translation_std_mm": trans_axis, "translation_rms_mm": trans_rms}
    if n_par == 13:
        out["scale_std"] = float(np.sqrt(cov[12, 12]) * he.scale)
    return out


def _linearised_bootstrap(J: np.ndarray, r: np.ndarray, huber: np.ndarray, clusters,
                          replicates: int, seed: int) -> tuple[np.ndarray, int, int]:
    """The bootstrap of bootstrap_hand_eye on a linearisation (J (6N, P), r (6N,), Huber
    weights (6N,): 6 residuals per view) with views of one ``clusters`` label resampled
    together. Returns (the replicates' covariance (P, P) times g / (g - 1), the number of
    clusters g, the replicates kept)."""
    labels, index = np.unique(np.asarray(clusters), return_inverse=True)
    n_views = r.size // 6
    if index.size != n_views:
        raise ValueError(f"bootstrap: {index.size} cluster labels for {n_views} views")
    g = labels.size
    n_par = J.shape[1]
    per_residual = np.repeat(index, 6)
    Jw = J * huber[:, None]
    H = np.zeros((g, n_par, n_par))
    grad = np.zeros((g, n_par))
    np.add.at(H, per_residual, Jw[:, :, None] * J[:, None, :])
    np.add.at(grad, per_residual, Jw * r[:, None])
    rng = np.random.default_rng(seed)
    counts = rng.multinomial(g, np.full(g, 1.0 / g), size=replicates).astype(np.float64)
    Hb = np.einsum("bg,gij->bij", counts, H)
    gb = counts @ grad
    # A draw of views that barely determines the fit (e.g. all rotating about one axis) has no
    # refit (calibrate_hand_eye refuses it): left out, and counted.
    floor = 1e-2 * np.linalg.eigvalsh(H.sum(axis=0))[0]
    keep = np.linalg.eigvalsh(Hb)[:, 0] > floor
    steps = -np.linalg.solve(Hb[keep], gb[keep][..., None])[..., 0]
    cov = np.atleast_2d(np.cov(steps, rowvar=False)) * g / max(g - 1, 1)
    return cov, int(g), int(keep.sum())


def tracked_at_every_offset(tracker_at, bound: float, gap_s: float | None = None) -> np.ndarray:
    """(N,) bool: the views ``tracker_at(d, method)`` -> (poses, covered (N,)) covers at every
    offset d in [-bound, bound]. A view is uncovered where t + d falls outside the tracker's
    span (checked at both ends) or inside a dropout, an open interval longer than ``gap_s``
    (io.tracking: GAP_SPACINGS sample spacings; None: 5 ms, every dropout of a tracker below
    600 Hz): each view's uncovering offsets are then such an interval, which a grid of offsets
    at most half of it apart always meets. The grid interpolates linearly (the same coverage as
    cubic, for less)."""
    step = 0.005 if gap_s is None else min(0.005, 0.5 * float(gap_s))
    grid = np.linspace(-bound, bound, max(int(np.ceil(2 * bound / step)), 1) + 1)
    covered = np.asarray(tracker_at(grid[0], "linear")[1], bool).copy()
    for d in grid[1:]:
        covered &= tracker_at(d, "linear")[1]
    return covered


def estimate_time_offset(tracker_at, cam_from_board: np.ndarray, first: HandEyeResult,
                         max_offset_s: float, times: np.ndarray, *,
                         still: np.ndarray | None = None, gap_s: float | None = None) -> dict:
    """The offset d (s) such that the tracker sample interpolated at t + d belongs to the frame
    at t: the d whose hand-eye fit leaves the smallest cost, over the views the tracker covers
    at every d in [-max_offset_s, max_offset_s] and with the noise of the first fit held (so the
    costs compare; the board's scale free as in ``first``). The range is scanned in ~5 ms steps
    (at least -bound, 0 and +bound) comparing the angles the scope turns between consecutive
    views by the board and by the tracker (no hand-eye: cheap over any range). When that scan's
    least is not SCAN_CONTRAST times below its median (views that barely turn against the
    tracker noise: its least falls on noise; a bound of SCAN_MIN_BOUND_S at least) the
    hand-eye's cost is scanned instead, in 25 ms steps; when that is flat too, the offset is not
    determined ("estimated" False, "reason" says so, 0 applied). The scan's lowest basins
    (SCAN_CANDIDATES) and offset 0 that lie within SCAN_CONTRAST of its least are compared by
    the hand-eye's cost, each fitted from its closed form ("scan_candidates" when more than
    one; "scan" and "scan_contrast" say which scan and how clear its least), and the lowest is
    searched: the hand-eye refitted there when it is not 0, the fit's cost compared in 5 ms
    steps around it (widened while the best lies at its edge) and minimised by a bounded
    search. An estimate within min(5 ms, a tenth of the bound) of
    the bound lies at it.
    Standard error ("std_s"): the larger of the cost's curvature's (cost = chi^2 / 2: views
    independent, "std_curvature_s") and a bootstrap over BOOTSTRAP_BLOCK_S blocks of views by
    their frame ``times`` (s), linearised as bootstrap_hand_eye's with the offset a parameter
    beside the hand-eye ("std_bootstrap_s"): the errors of neighbouring views correlate (a
    tracker sample interpolated to several frames, the interpolation's error along a motion),
    which the curvature counts as independent. Measured on the simulator
    (bench/bench_time_offset_se.py, 20 seeds, true offsets within +-80 ms; errors within +-1.96
    standard errors, RMS error / median standard error): a 40 Hz tracker (0.9 deg / 0.25 mm) 20
    / 20, 0.84 (the curvature's 19 / 20, 0.85); at 10 Hz 19 / 20, 0.88 (curvature 12 / 20,
    2.43); at 10 Hz with 0.1 deg / 0.03 mm 20 / 20, 0.87 (curvature 7 / 20, 3.02; its samples
    half a period later against the frames: 20 / 20, 0.77 against 6 / 20, 2.94). At 10 Hz the
    errors share a bias (-0.6 ms; +0.5 at the other phase): the splines' error along the
    simulator's motions, which the standard error covers but does not remove.
    Still views alone (the board found only while the scope rests, e.g. lost to motion blur
    during the moves; ``still`` (N,) marks the views held still, filmed_motion_std) show the
    offset only where the tracker interpolated across a rest's edge runs into a move: there the
    interpolant's shape decides, which neither figure above sees. The estimate is then also
    made with linear interpolation and the standard error is at least the distance between the
    two ("std_interpolation_s"). Measured (bench_time_offset_se, the board lost while moving,
    0.9 deg / 0.25 mm, 20 seeds, true offsets within +-80 ms): at 10 Hz 18 / 20 within 1.96
    std_s, RMS error / median std 1.26 (without the term 4 / 20, 2.43; the clocks agreeing it
    applied +6.4 to +7.1 ms, now not); at 40 Hz 13 / 20, 2.53 (5 / 20, 3.88): still too small
    there, where the cubic and the linear estimates err alike by 4-11 ms on a quarter of the
    seeds, a cost sharply curved at the wrong place (not flat), which neither a leave-one-block-
    out jackknife (z up to 4.7) nor a profile of the cost caught. The report says so
    ("interpolation_note").
    Applied only when it is determined (the scope moved while filmed: error < 10 ms) and
    differs from 0 by more than two standard errors; an estimate at the bound is flagged
    ("at_bound": the clocks may differ by more). `tracker_at(d, method)` -> (tracker_from_sensor
    of the views it covers, mask), interpolated by io.tracking's ``method`` ("cubic" or
    "linear"); ``gap_s`` the shortest dropout that uncovers a view (tracked_at_every_offset)."""
    from scipy.optimize import minimize_scalar

    times = np.asarray(times, np.float64).reshape(-1)
    if times.size != len(cam_from_board):
        raise ValueError(f"time offset: {times.size} frame times for {len(cam_from_board)} "
                         "views")
    h = 0.002  # curvature step; the views must be covered there too
    # The views tracked at every offset the search may try (the curvature's and the bootstrap's
    # steps beyond the bound included): one set of views for every cost, so the costs compare
    # and their curvature is a chi^2's. Both ends alone missed the views a dropout mid-recording
    # uncovers at offsets between them (4 invalid samples at 40 Hz: a numpy broadcast error,
    # reported as a bound too wide).
    common = tracked_at_every_offset(tracker_at, max_offset_s + 2 * h, gap_s)
    sigma = first.tracker_sigma
    fit_scale = first.scale_std > 0
    C = cam_from_board[common]

    def tracked(d: float, method: str = "cubic") -> np.ndarray:
        A, ok = tracker_at(d, method)
        if not ok[common].all():  # (a tracker_at whose gaps are shorter than gap_s)
            raise ValueError(f"the tracker does not cover {int((~ok & common).sum())} of the "
                             f"views tracked at every offset at {d:+.4f} s")
        return A[common[ok]]

    def cost(d: float, method: str = "cubic") -> float:
        return calibrate_hand_eye(tracked(d, method), C, rot_sigma_deg=sigma[0],
                                  trans_sigma_mm=sigma[1], reweight=False, fit_scale=fit_scale,
                                  start=first, linearise=False).cost

    if common.sum() < MIN_HAND_EYE_VIEWS:
        return {"estimated": False, "applied_s": 0.0, "at_bound": False,
                "views": int(common.sum()),
                "reason": f"fewer than {MIN_HAND_EYE_VIEWS} views tracked at every offset"}
    fine = 0.005
    # Steps of about `fine`, an odd count: 0 and both bounds are always on the grid (a bound
    # under 2.5 ms made it the single point -bound, and the estimate was forced there).
    half = max(int(round(max_offset_s / fine)), 1)
    grid = np.linspace(-max_offset_s, max_offset_s, 2 * half + 1)
    # An estimate this close to the bound lies at it (the minimiser ends within xatol of it
    # when the cost still falls beyond): both scale with a bound below `fine` (a 5 ms
    # tolerance put every estimate at a 4 ms bound, 0 included).
    at_bound_tolerance = min(fine, 0.1 * max_offset_s)
    xatol = min(1e-4, 0.02 * max_offset_s)
    # The coarse scan compares how far the scope turns between consecutive views, by the board
    # and by the tracker: angle(A_k^-1 A_k+1) = angle(C_k C_k+1^-1) whatever the hand-eye, so
    # it needs none (holding the one fitted at offset 0 found -53 ms for clocks 0.6 s apart).
    turned = _rotation_angles(C[:-1, :3, :3] @ np.swapaxes(C[1:, :3, :3], 1, 2))

    def mismatch(d: float) -> float:
        R = tracked(d)[:, :3, :3]
        return float(np.sum((_rotation_angles(np.swapaxes(R[:-1], 1, 2) @ R[1:]) - turned) ** 2))

    scan = np.array([mismatch(d) for d in grid])
    zero = half  # grid[half] = 0
    scanned = {"scan": "turns between views",
               "scan_contrast": _contrast(scan)}

    def fitted(k: int, views=slice(None), max_nfev=None) -> HandEyeResult | None:
        # The hand-eye at grid[k] from its closed form, the noise of the fit at 0 held: costs
        # that compare across offsets (from the fit at 0 instead, +400 ms ended at 15436, the
        # closed form's 14843), None where the views do not determine it.
        try:
            return calibrate_hand_eye(tracked(grid[k])[views], C[views], rot_sigma_deg=sigma[0],
                                      trans_sigma_mm=sigma[1], reweight=False,
                                      fit_scale=fit_scale, linearise=False, max_nfev=max_nfev)
        except ValueError:
            return None

    def refuse() -> None:  # no offset's views determine the hand-eye: its own refusal
        calibrate_hand_eye(tracked(0.0), C, rot_sigma_deg=sigma[0], trans_sigma_mm=sigma[1],
                           reweight=False, fit_scale=fit_scale, linearise=False)

    if max_offset_s >= SCAN_MIN_BOUND_S and not scanned["scan_contrast"] >= SCAN_CONTRAST:
        # The views turn too little against the tracker's noise for the scan to pick a basin
        # (SCAN_CONTRAST): the hand-eye's cost in steps of 5 `fine` (25 ms; at tilt 4 its basin
        # is 25 ms wide, 3.5x its least at +-25 ms) instead, which sees the translations too.
        # Over SCAN_VIEWS views (all when those determine no hand-eye), SCAN_NFEV evaluations.
        coarse = np.unique(np.r_[np.arange(zero % 5, grid.size, 5), 0, grid.size - 1])
        views = np.unique(np.linspace(0, len(C) - 1, min(len(C), SCAN_VIEWS)).round().astype(int))
        fits = {int(k): fitted(int(k), views, SCAN_NFEV) for k in coarse}
        if all(f is None for f in fits.values()) and len(views) < len(C):
            fits = {int(k): fitted(int(k)) for k in coarse}
        costs = {k: f.cost for k, f in fits.items() if f is not None}
        if not costs:
            refuse()
        keys = np.array(sorted(costs))
        scan = np.array([costs[k] for k in keys])
        scanned.update(scan="hand-eye cost (the turns' scan flat: least "
                            f"{scanned['scan_contrast']:.2f} x below its median)",
                       scan_contrast=_contrast(scan))
        if not scanned["scan_contrast"] >= SCAN_CONTRAST:
            return {"estimated": False, "applied_s": 0.0, "at_bound": False,
                    "views": int(common.sum()), **scanned,
                    "reason": (
                        "not determined: over the search range neither how far the views turn "
                        "nor the hand-eye's cost has a clear least (the scope barely moved "
                        "against the tracker's noise); 0 applied. Film slow motion with the "
                        "scope tilted and rolled over the board, or give the offset with "
                        "--time-offset S")}
        low = [int(keys[j]) for j in _low_points(scan, SCAN_CANDIDATES, 1)]
        values = dict(zip(keys.tolist(), scan, strict=True))
    else:
        low = [int(k) for k in _low_points(scan, SCAN_CANDIDATES, SCAN_BASIN_STEPS)]
        values = dict(enumerate(scan))
    # The scan's basins it cannot tell from its best (within SCAN_CONTRAST of its least), offset
    # 0 among them, are compared by the hand-eye's cost over all views and the lowest searched
    # (a scan's least on noise: 14001 at +288 ms against 424 at 0). Basins the scan rules out
    # are not fitted: the defaults' estimates as they were, at no cost.
    if all(abs(k - zero) > SCAN_BASIN_STEPS for k in low):
        low.append(zero)
    candidates = [k for k in low if k in values and values[k] <= SCAN_CONTRAST * values[low[0]]]
    costs = {}
    if len(candidates) == 1:
        costs[candidates[0]] = float(values[candidates[0]])  # (the scan's least: no rival)
    else:
        for k in candidates:
            fit = fitted(k)
            if fit is not None:
                costs[k] = fit.cost
        if not costs:
            refuse()
    i = min(costs, key=costs.get)
    if len(costs) > 1:
        scanned["scan_candidates"] = [{"offset_s": float(grid[k]), "cost": float(c)}
                                      for k, c in sorted(costs.items())]
    if abs(grid[i]) > 2 * fine:  # the fits below start from a hand-eye fitted there
        first = calibrate_hand_eye(tracked(grid[i]), C, rot_sigma_deg=sigma[0],
                                   trans_sigma_mm=sigma[1], fit_scale=fit_scale,
                                   linearise=False)
        sigma = first.tracker_sigma

    def minimise(i: int, method: str = "cubic"):
        # The cost in 5 ms steps from grid[i], widened while the least lies at the edge, then
        # a bounded search between that least's neighbours.
        costs: dict[int, float] = {}
        lo, hi = max(i - 3, 0), min(i + 3, grid.size - 1)
        while True:
            for k in range(lo, hi + 1):
                if k not in costs:
                    costs[k] = cost(grid[k], method)
            i = min(costs, key=costs.get)
            if (i > lo or lo == 0) and (i < hi or hi == grid.size - 1):
                break
            lo, hi = max(min(lo, i - 2), 0), min(max(hi, i + 2), grid.size - 1)
        lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
        return minimize_scalar(cost, bounds=(lo, hi), args=(method,), method="bounded",
                               options={"xatol": xatol})

    search = minimise(i)
    best = float(search.x)
    curvature = (cost(best + h) + cost(best - h) - 2 * search.fun) / h ** 2
    std = float(1 / np.sqrt(curvature)) if curvature > 0 else float("inf")
    at_bound = abs(abs(best) - max_offset_s) < at_bound_tolerance
    out = {"estimated": True, "estimate_s": float(best), "std_s": std,
           "std_curvature_s": std, "views": int(common.sum()), "applied_s": 0.0,
           "at_bound": bool(at_bound), "search_bound_s": float(max_offset_s), **scanned}
    motion_std, moving = filmed_motion_std(C, times[common], first.sensor_from_camera, sigma,
                                           None if still is None else still[common])
    out.update(std_filmed_motion_s=motion_std, frames_moving=moving)
    spread = 0.0
    if not motion_std <= MAX_FILMED_MOTION_STD_S and np.isfinite(std):
        linear = float(minimise(int(np.argmin(np.abs(grid - best))), "linear").x)
        spread = abs(linear - best)
        out.update(estimate_linear_s=linear, std_interpolation_s=spread,
                   interpolation_note=(
                       "still views: the frames filmed while moving do not determine the "
                       "offset, which shows only where the tracker interpolated across a "
                       "rest's edge runs into a move; the standard error is at least the "
                       "distance between the cubic and the linear interpolation's estimates, "
                       "and may still understate the error (simulator, 40 Hz: errors up to "
                       "11 ms against 1.2-7.5 ms). To measure the offset, film a few seconds "
                       "of slow continuous motion over the board (the whole board in view)"))
    if np.isfinite(std):
        t = times[common]
        blocks = np.floor((t - t[0]) / BOOTSTRAP_BLOCK_S)
        g = int(np.unique(blocks).size)
        if g < MIN_HAND_EYE_GROUPS:
            # A bootstrap over so few blocks says nothing (2 blocks: 0.08 ms for a 0.9 ms
            # error's spread; 1 block: 0): not computed, the curvature's figure alone.
            out.update(std_bootstrap_s=None, bootstrap_blocks=g,
                       bootstrap_note=f"not computed: {g} block(s) of {BOOTSTRAP_BLOCK_S:g} s "
                                      f"(needs {MIN_HAND_EYE_GROUPS})")
        else:
            # The fit at the estimate, linearised (Jacobian of the weighted residuals in the
            # hand-eye's parameters), with one more column: the residuals' derivative in the
            # offset (central differences, the hand-eye held).
            he = calibrate_hand_eye(tracked(best), C, rot_sigma_deg=sigma[0],
                                    trans_sigma_mm=sigma[1], reweight=False,
                                    fit_scale=fit_scale, start=first)
            J, r, huber = he.linearisation
            weight = np.repeat([np.deg2rad(sigma[0]), sigma[1]], 3)
            Cinv = np.linalg.inv(C)

            def weighted(d: float) -> np.ndarray:
                A = tracked(d)
                return (_tracker_residuals(A, np.linalg.inv(A), Cinv, he.sensor_from_camera,
                                           he.tracker_from_board, he.scale) / weight).ravel()

            dr = (weighted(best + h) - weighted(best - h)) / (2 * h)
            cov, g, kept = _linearised_bootstrap(np.column_stack([J, dr]), r, huber, blocks,
                                                 BOOTSTRAP_REPLICATES, 0)
            boot = float(np.sqrt(cov[-1, -1]))
            out.update(std_s=max(std, boot), std_bootstrap_s=boot, bootstrap_blocks=g,
                       bootstrap_replicates=kept,
                       bootstrap_replicates_left_out=BOOTSTRAP_REPLICATES - kept,
                       bootstrap_seed=0)
            std = out["std_s"]
    if spread > std:
        std = out["std_s"] = spread
    if not np.isfinite(std) or std > 0.01:
        out["reason"] = "not determined: the scope must move while filmed"
    elif at_bound:
        out["reason"] = f"at the search bound +-{max_offset_s:g} s"
    elif abs(best) > 2 * std:
        out["applied_s"] = float(best)
    return out


def filmed_motion_std(cam_from_board: np.ndarray, times: np.ndarray,
                      sensor_from_camera: np.ndarray, tracker_sigma: tuple[float, float],
                      still: np.ndarray | None = None) -> tuple[float, int]:
    """The standard error (s) of the tracker clock offset that the frames filmed while moving
    would give, and how many such frames there are: a shift d of the tracker's clock moves
    the frame's tracked pose by its velocity times d, so a frame informs the offset with its
    squared speed over the tracker noise ``tracker_sigma`` (deg, mm per axis): (rotation rate
    / sigma_deg)^2 + (sensor speed / sigma_mm)^2, the speeds from the board poses
    ``cam_from_board`` (N, 4, 4) at ``times`` (s) through ``sensor_from_camera`` (no tracker
    sample, so no spline or noise enters). A frame's speed is the smaller of those to its
    neighbours (within 1.5 median frame spacings; none at a gap), so a frame at rest beside a
    move counts 0; frames ``still`` (N,) (held still: still_groups) count 0 whatever their
    corners' noise. 1 / sqrt(the summed information): inf when no frame was filmed moving. The
    frames' errors taken as independent, the tracker as following the motion exactly: a floor
    on what estimate_time_offset can reach."""
    P = np.linalg.inv(cam_from_board) @ np.linalg.inv(sensor_from_camera)  # board_from_sensor
    if len(P) < 2:
        return float("inf"), 0
    dt = np.diff(np.asarray(times, np.float64))
    near = (dt > 0) & (dt <= 1.5 * np.median(dt[dt > 0])) if (dt > 0).any() else dt > 0
    turn = _rotation_angles(np.swapaxes(P[:-1, :3, :3], 1, 2) @ P[1:, :3, :3])
    step = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
    speed2 = np.zeros(dt.size)
    speed2[near] = ((turn[near] / np.deg2rad(tracker_sigma[0])) ** 2
                    + (step[near] / tracker_sigma[1]) ** 2) / dt[near] ** 2
    per_frame = np.minimum(np.r_[0.0, speed2], np.r_[speed2, 0.0])
    if still is not None:
        per_frame[np.asarray(still, bool)] = 0.0
    info = float(per_frame.sum())
    return float(1.0 / np.sqrt(info) if info > 0 else np.inf), int(np.sum(per_frame > 0))



def _contrast(values: np.ndarray) -> float:
    """How far a scan's least lies below its median: median / least (inf for a least of 0
    below a positive median)."""
    least, median = float(np.min(values)), float(np.median(values))
    if least > 0:
        return median / least
    return float("inf") if median > least else 1.0


def _low_points(values: np.ndarray, count: int, apart: int) -> list[int]:
    """Indices of up to ``count`` local minima of ``values`` (an end counts when below its
    neighbour), lowest first, each more than ``apart`` indices from a lower one kept."""
    v = np.asarray(values, np.float64)
    minima = np.flatnonzero((v <= np.r_[np.inf, v[:-1]]) & (v <= np.r_[v[1:], np.inf]))
    kept: list[int] = []
    for k in minima[np.argsort(v[minima], kind="stable")]:
        if all(abs(int(k) - j) > apart for j in kept):
            kept.append(int(k))
        if len(kept) == count:
            break
    return kept


def _offset_bound_note(samples, times: np.ndarray, gap_s: float | None = None) -> str:
    """What the refusals of the clock offset search add: both time spans, the recording's
    length and the bound that keeps half the views (from the valid samples' span and, with
    ``gap_s``, their dropouts: intervals longer than it between valid samples)."""
    from fusedmosaic.io.tracking import _time

    ts = samples.timestamps[samples.valid]
    margin = np.minimum(times - ts[0], ts[-1] - times)
    if gap_s is not None:  # each view's distance to the nearest dropout (0 inside one)
        dropout = np.diff(ts) > gap_s * (1 + 1e-9)
        for start, end in zip(ts[:-1][dropout], ts[1:][dropout], strict=True):
            inside = (times > start) & (times < end)
            near = np.where(times <= start, start - times, times - end)
            margin = np.minimum(margin, np.where(inside, 0.0, near))
    margin = np.sort(margin)[::-1]
    # estimate_time_offset looks 4 ms beyond the bound
    half = np.floor(100 * (margin[max(times.size // 2 - 1, 0)] - 0.004)) / 100
    return (
        f"the tracker spans [{_time(ts[0])}, {_time(ts[-1])}] s, the views [{_time(times[0])}, "
        f"{_time(times[-1])}] s, a {times[-1] - times[0]:.3g} s recording"
        + (f"; +-{half:g} s keeps half the views" if half > 0 else ""))


def _rotation_angles(R: np.ndarray) -> np.ndarray:
    """Angles (rad) of rotation matrices (N, 3, 3), from their traces."""
    return np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0))


def _hand_eye_from_motions(A: np.ndarray, C: np.ndarray, max_views: int = 60,
                           fit_scale: bool = False) -> tuple[np.ndarray, float]:
    """Closed-form X from pairs of views: (A_j^-1 A_i) X = X (C_j C_i^-1). Rotation: the
    rotation vectors satisfy alpha = R_X beta (aligned by SciPy's align_vectors, the least
    squares solution); translation: (R_A - I) t_X = R_X s t_B - t_A, stacked (least squares),
    with the board's scale s = 1 or, with fit_scale, solved for with t_X. Returns (X, s)."""
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
    board = np.einsum("ij,njk->nik", R, MB[use, :3, 3:4])[..., 0].reshape(-1)
    tracker = MA[use, :3, 3].reshape(-1)
    scale = 1.0
    if fit_scale:
        t_s = np.linalg.lstsq(np.hstack([lhs, -board[:, None]]), -tracker, rcond=None)[0]
        t, scale = t_s[:3], float(t_s[3])
        if not np.isfinite(scale) or scale <= 0:  # not determined (or a mirrored input): none
            t, scale = np.linalg.lstsq(lhs, board - tracker, rcond=None)[0], 1.0
    else:
        t = np.linalg.lstsq(lhs, board - tracker, rcond=None)[0]
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = R, t
    return X, scale


def _normal_spread_deg(cam_from_board: np.ndarray) -> float:
    """RMS angle (deg) of the board normals (the board's z axis in the camera frame) of the
    poses (N, 4, 4) about their mean direction: 0 for parallel views (MIN_NORMAL_SPREAD_DEG)."""
    normals = cam_from_board[:, :3, 2]
    mean = normals.mean(axis=0)
    mean /= np.linalg.norm(mean)
    return float(np.rad2deg(np.sqrt(np.mean(np.arccos(np.clip(normals @ mean, -1, 1)) ** 2))))


def _tracker_residuals(A: np.ndarray, Ainv: np.ndarray, Cinv: np.ndarray, X: np.ndarray,
                       B: np.ndarray, scale: float) -> np.ndarray:
    """calibrate_hand_eye's residuals (N, 6): the rotation vector (rad, sensor frame) and the
    translation (mm, tracker frame) from the tracked tracker_from_sensor A (its inverse Ainv)
    to the one the board gives, B (C scaled)^-1 X^-1 (Cinv: board_from_cam)."""
    board_from_cam = Cinv if scale == 1.0 else _scaled(Cinv, scale)
    predicted = B @ board_from_cam @ np.linalg.inv(X)  # tracker_from_sensor via the board
    rot = Rotation.from_matrix((Ainv @ predicted)[:, :3, :3]).as_rotvec()
    return np.hstack([rot, predicted[:, :3, 3] - A[:, :3, 3]])


def _scaled(T: np.ndarray, scale: float) -> np.ndarray:
    """Rigid transforms (N, 4, 4) with their translations times ``scale``."""
    out = T.copy()
    out[..., :3, 3] *= scale
    return out


def _tracker_from_sensor(sensor_from_tracker: np.ndarray) -> np.ndarray:
    """(N, 4, 4) inverses of (N, 6) [angle-axis, t] poses."""
    R = Rotation.from_rotvec(sensor_from_tracker[:, :3]).inv()
    T = np.tile(np.eye(4), (sensor_from_tracker.shape[0], 1, 1))
    T[:, :3, :3] = R.as_matrix()
    T[:, :3, 3] = -R.apply(sensor_from_tracker[:, 3:])
    return T


def _tracker_samples(samples, index: np.ndarray) -> np.ndarray:
    """tracker_from_sensor (len(index), 4, 4) of raw samples (indices into samples)."""
    T = np.tile(np.eye(4), (index.size, 1, 1))
    T[:, :3, :3] = Rotation.from_quat(samples.quaternions[index]).as_matrix()
    T[:, :3, 3] = samples.translations[index]
    return T


def _mean_transform(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = Rotation.from_matrix(T[:, :3, :3]).mean().as_matrix()
    out[:3, 3] = T[:, :3, 3].mean(0)
    return out


# ------------------------------------------------------------------------------------------------
# Views
# ------------------------------------------------------------------------------------------------


def _corner_distance(points: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """RMS distance (px) between the corners of each of ``points`` (K, M, 2) and ``reference``
    (M, 2)."""
    return np.sqrt(np.mean(np.sum((points - reference) ** 2, axis=-1), axis=-1))


def repeated_views(points: list[np.ndarray], min_px: float) -> np.ndarray:
    """For each detection (in recording order), the index of the first earlier distinct view
    whose corners lie within ``min_px`` (RMS) of its own, else its own index: detections of one
    label show one board pose (a still scope, a pause, a return to a view), and count as one
    view."""
    label = np.arange(len(points))
    if not points:
        return label
    corners = np.stack(points)
    chosen = [0]
    for k in range(1, len(points)):
        d = _corner_distance(corners[chosen], corners[k])
        j = int(np.argmin(d))
        if d[j] < min_px:
            label[k] = chosen[j]
        else:
            chosen.append(k)
    return label


def still_groups(points: list[np.ndarray], frames: np.ndarray, step: int = 1,
                 max_px: float = None) -> list[np.ndarray]:
    """Runs (index arrays, two detections or more) of detections of consecutive searched frames
    (``frames`` index the recording, searched every ``step``) whose corners stay within
    ``max_px`` (RMS; STILL_PX) of the run's first: the scope held still over the run."""
    max_px = STILL_PX if max_px is None else max_px
    runs: list[list[int]] = []
    for k in range(len(points)):
        if (runs and frames[k] - frames[runs[-1][-1]] <= step
                and _corner_distance(points[k][None], points[runs[-1][0]])[0] < max_px):
            runs[-1].append(k)
        else:
            runs.append([k])
    return [np.array(r) for r in runs if len(r) >= 2]


# ------------------------------------------------------------------------------------------------
# A recording
# ------------------------------------------------------------------------------------------------


@dataclass
class BoardDetections:
    """The board's corners found in a recording: points[k] (rows * cols, 2) px in the canonical
    order, found in frame frames[k] (index into the recording, searched every ``step`` frames)
    of id ids[k] at time times[k] (s); frames of ``size`` (width, height)."""

    points: list[np.ndarray]
    frames: np.ndarray
    ids: np.ndarray
    times: np.ndarray
    size: tuple[int, int]
    step: int = 1


def calibrate_recording(
    root: str | Path,
    options: CalibrationOptions | None = None,
    *,
    fps: float | None = None,
    progress: bool = False,
) -> CalibrationResult:
    """Calibrate from a recording folder (module doc). Everything readable is read and checked
    first (camera.yaml, frame times, tracking.csv and its time span), before the board search.
    ValueError naming the folder or file for a missing or malformed input, a board found in too
    few frames or too few distinct views; a hand-eye that fails is reported in the result
    (hand_eye_error), the intrinsics kept."""
    from fusedmosaic.io.calibration import read_camera_yaml
    from fusedmosaic.io.dataset import read_frame_times
    from fusedmosaic.io.video import FrameSource

    o = CalibrationOptions() if options is None else options
    o.validate()
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"{root}: recording folder not found")
    t_start = time.perf_counter()
    given = read_camera_yaml(root / "camera.yaml") if (root / "camera.yaml").exists() else None
    # a damaged frame is one without the board (counted in the report), not the end of it
    frames = FrameSource.open(root, expected_size=None if given is None else given.size,
                              blank_unreadable=True)
    first = frames[0]
    size = (first.shape[1], first.shape[0])
    if given is None:  # every frame the size of the first
        frames.expected_size, frames.size_source = size, f"its first frame {size}"
    frame_ids, timestamps, frame_times = read_frame_times(root, frames, fps)
    tracking, skipped = _read_tracking(root, timestamps, o)
    # a tracker time offset import already applied to tracking.csv (import / live --record
    # --tracker-time-offset S): what calibrate measures is then what remains of the offset
    import_shift = 0.0
    if tracking is not None:
        from fusedmosaic.io.plus import applied_tracker_time_offset

        import_shift = applied_tracker_time_offset(root) or 0.0
    detections, searched = find_board_views(frames, frame_ids, timestamps, o, size=size,
                                            progress=progress)
    t_detect = time.perf_counter() - t_start
    result = calibrate_detections(detections, o, tracking=tracking,
                                  tracking_source=str(root / "tracking.csv"),
                                  hand_eye_skipped=skipped, given=given, source=str(root),
                                  searched=searched, import_shift_s=import_shift)
    result.report = {"recording": str(root.resolve()), **result.report,
                     "frames": len(frames), "frame_times": frame_times,
                     "frames_searched": searched}
    if frames.unreadable:
        ids = [int(frame_ids[k]) for k in sorted(frames.unreadable)]
        result.report["unreadable_frames"] = {
            str(i): frames.unreadable[k] for i, k in zip(ids, sorted(frames.unreadable),
                                                         strict=True)}
        warnings.warn(f"{len(ids)} of the {searched} frames searched could not be read "
                      f"(frames {', '.join(map(str, ids[:10]))}{', ...' if len(ids) > 10 else ''}"
                      f"; first: {frames.unreadable[min(frames.unreadable)]}): searched as "
                      "frames without the board (calibration.json unreadable_frames)",
                      stacklevel=2)
    timings = result.report.setdefault("timings_s", {})
    timings["board_search"] = t_detect
    timings["total"] = time.perf_counter() - t_start
    return result


def find_board_views(frames, frame_ids: np.ndarray, timestamps: np.ndarray,
                     options: CalibrationOptions, *, size: tuple[int, int] | None = None,
                     progress: bool = False) -> tuple[BoardDetections, int]:
    """The board searched in every options.every-th of `frames` (frames[k]: an image) on
    options.threads threads: its detections (frame ids and times from `frame_ids` /
    `timestamps`; size: the frames' (width, height), None: the first frame's) and the number
    of frames searched."""
    if size is None:
        size = (frames[0].shape[1], frames[0].shape[0])
    tried = np.arange(0, len(frames), options.every)

    def detect(k: int):
        return detect_board(frames[int(k)], options)

    with ThreadPoolExecutor(max_workers=options.threads) as pool:
        results = pool.map(detect, tried)
        if progress:
            from tqdm import tqdm
            results = tqdm(results, total=tried.size, desc="board search", unit="frame")
        found = list(results)
    views = np.array([k for k, c in zip(tried, found, strict=True) if c is not None], int)
    detections = BoardDetections([c for c in found if c is not None], views, frame_ids[views],
                                 timestamps[views], size, options.every)
    return detections, int(tried.size)


def _read_tracking(root: Path, timestamps: np.ndarray, o: CalibrationOptions):
    """(tracking samples or None, why the hand-eye is skipped or None), read and checked before
    any work: ValueError naming tracking.csv when it is malformed or covers too few frames."""
    from fusedmosaic.io.tracking import interpolate_camera_poses, read_tracking_csv

    path = root / "tracking.csv"
    if not path.exists():
        return None, f"no tracking.csv in {root}"
    if not o.oriented:
        return None, (f"the {o.board_cols}x{o.board_rows} board looks the same after a half "
                      "turn (columns + rows even), so its pose is ambiguous; use a board with "
                      "an odd sum, e.g. 9x6")
    samples = read_tracking_csv(path)
    shift = 0.0 if o.time_offset == "auto" else float(o.time_offset)
    _, covered = interpolate_camera_poses(samples, timestamps + shift, None, allow_outside=True,
                                          source=str(path))
    _check_tracker_covers(samples, covered, timestamps + shift, str(path), "frames",
                          shift_note=(f", the frames' shifted by the time offset {shift:g} s"
                                      if shift else ""))
    return samples, None


def _check_tracker_covers(samples, covered: np.ndarray, times: np.ndarray, source: str,
                          what: str, shift_note: str = "") -> None:
    """ValueError naming ``source`` when fewer than MIN_HAND_EYE_VIEWS of the ``what`` (frames
    or views, at their tracker-clock ``times``) have a tracker sample, with both time spans."""
    from fusedmosaic.io.tracking import _time

    if covered.sum() >= MIN_HAND_EYE_VIEWS:
        return
    ts = samples.timestamps[samples.valid]
    raise ValueError(
        f"{source}: {int(covered.sum())} of {len(times)} {what} have a tracker sample; "
        f"the tracker spans [{_time(ts[0])}, {_time(ts[-1])}] s, the {what} "
        f"[{_time(times[0])}, {_time(times[-1])}] s (frame times come from frames.csv, or "
        f"frame / fps without it (--fps, else the video's frame rate, else 25); both clocks "
        f"in seconds{shift_note})")


def calibrate_detections(
    detections: BoardDetections,
    options: CalibrationOptions | None = None,
    *,
    tracking=None,
    tracking_source: str = "tracking.csv",
    hand_eye_skipped: str | None = None,
    given: Camera | None = None,
    source: str = "the recording",
    searched: int | None = None,
    import_shift_s: float = 0.0,
) -> CalibrationResult:
    """Intrinsics and hand-eye from board detections (calibrate_recording's stages after the
    board search): ``tracking`` the TrackingSamples (None: the hand-eye skipped, for the reason
    ``hand_eye_skipped``), ``given`` the recording's camera.yaml (its field-of-view mask and
    pixel size carried over), ``source`` and ``tracking_source`` name them in messages.
    ``import_shift_s``: the tracker time offset already applied to the tracking at import
    (io.plus.applied_tracker_time_offset); the report's tracker_time_offset then gives it
    ("import_shift_s") and the offset against the video, it plus the one applied here
    ("total_s": what recordings of the set-up need)."""
    o = CalibrationOptions() if options is None else options
    o.validate()
    t0 = time.perf_counter()
    points, size = detections.points, detections.size
    pattern = f"{o.board_cols}x{o.board_rows}"
    searched = len(points) if searched is None else searched
    if len(points) < MIN_VIEWS:
        if points and len(points) == searched:
            # found in every frame searched: too few frames were searched, not a wrong board
            advice = (f"lower --every (now {o.every}: one frame in {o.every} searched)"
                      if o.every > 1 else "record more views")
            advice = f"The board was found in every frame searched: {advice}"
        else:
            advice = ("Check the board size (inner corners, not squares) and that the whole "
                      "board is in view")
        raise ValueError(
            f"{source}: the {pattern} board (inner corners, columns x rows) was found in "
            f"{len(points)} of {searched} frames searched; calibration needs at least "
            f"{MIN_VIEWS} views (15-30 at varied angles are advised). {advice}")
    # Frames of one board pose (a still scope, a pause at each view) are one view: the
    # intrinsics take one frame of each distinct pose, the hand-eye's errors are resampled by
    # pose.
    repeat_px = max(REPEATED_VIEW_FRACTION * float(np.hypot(*size)), 1.0)
    label = repeated_views(points, repeat_px)
    distinct = np.flatnonzero(label == np.arange(len(points)))
    if distinct.size < MIN_VIEWS:
        raise ValueError(
            f"{source}: the {pattern} board was found in {len(points)} frames, but they show "
            f"{distinct.size} distinct view(s) (frames whose corners lie within "
            f"{repeat_px:.1f} px RMS of an earlier frame's repeat its view: a still scope or a "
            f"pause); calibration needs at least {MIN_VIEWS} distinct views (15-30 at varied "
            "angles are advised): film the board from more, different angles")
    chosen = distinct[np.unique(np.linspace(0, distinct.size - 1, min(distinct.size, o.max_views))
                                .round().astype(int))]
    # Views whose corners the camera cannot explain (corners found off the squares' corners,
    # e.g. where a circular field of view cuts the board; outliers of the intrinsics) give
    # neither intrinsics nor hand-eye: rejected, and the intrinsics computed again without them.
    usable = np.ones(len(points), bool)
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
    normal_spread = _normal_spread_deg(poses[np.delete(chosen, dropped)])
    if normal_spread < MIN_NORMAL_SPREAD_DEG:
        raise ValueError(
            f"{source}: the board faces the camera at nearly the same angle in all "
            f"{len(chosen) - len(dropped)} views (their board normals spread "
            f"{normal_spread:.2f} deg RMS about their mean; at least {MIN_NORMAL_SPREAD_DEG:g} "
            "deg is needed): parallel views do not determine the focal length. Film the board "
            "from more, different angles (tilted by 20-40 degrees in different directions, at "
            "different distances)")
    focal_std = float(max(std[0] / K[0, 0], std[1] / K[1, 1]))
    if not np.isfinite(focal_std) or focal_std > MAX_FOCAL_RELATIVE_STD:
        # The board in under half the frames searched: a wrong --board finds a part of the board
        # in a few (8x6 on a 9x6 board: 4 views), and more angles would not help.
        board = "" if 2 * len(points) >= searched else (
            f"; the {pattern} board was found in only {len(points)} of {searched} frames "
            "searched: check --board (inner corners, columns x rows: a board of 10x7 squares "
            "is 9x6; a wrong size can match a part of the board)")
        raise ValueError(
            f"{source}: the {len(chosen)} distinct views do not determine the focal length "
            f"(standard error {100 * focal_std:.1f} %): film the board from more, different "
            "angles (tilted by 20-40 degrees in different directions, at different distances)"
            f"{board}")
    usable &= pnp_max <= limit
    usable[chosen[dropped]] = False
    camera = Camera(size[0], size[1], camera_matrix=K,
                    distortion=None if o.coefficients == 0 else dist, lens_model=o.lens_model,
                    pixel_size_um=None if given is None else given.pixel_size_um,
                    fov_mask_radius=None if given is None else given.fov_mask_radius)
    ids = detections.ids
    fitted = [points[i] for k, i in enumerate(chosen) if k not in dropped]
    reach = corner_reach(fitted, camera)
    fold = _lens_fold(camera, reach, fitted)
    report: dict = {
        "board": {"inner_corners": [o.board_cols, o.board_rows], "square_mm": o.square_mm},
        "image_size": list(size),
        "board_found": len(points),
        "distinct_views": int(distinct.size),
        "repeated_view_px": repeat_px,
        "board_normal_spread_deg": normal_spread,
        "frames_with_board": [int(v) for v in ids],
        "frames_rejected": {"corner_reprojection_px_over": limit,
                            "frames": [int(v) for v in ids[~usable]]},
        "intrinsics": {
            "views": int(len(chosen) - len(dropped)),
            "frames": [int(ids[i]) for k, i in enumerate(chosen) if k not in dropped],
            "views_dropped_as_outliers": [int(ids[chosen[i]]) for i in dropped],
            "rms_px": float(np.sqrt(np.mean(rms ** 2))),
            "view_rms_px_max": float(rms.max()),
            "camera_matrix": K.tolist(),
            "std_fx_fy_cx_cy_px": [float(v) for v in std],
            "lens_model": o.lens_model,
            "distortion": [float(v) for v in dist],
            "distortion_coefficients": o.coefficients,
            "corner_reach": reach,
            "undistortion": fold,
        },
        "timings_s": {"intrinsics": time.perf_counter() - t0},
    }

    model_warning = _camera_model_warning(report["intrinsics"]["rms_px"], o)
    if model_warning:
        report["intrinsics"]["warning"] = model_warning
        warnings.warn(f"{source}: {model_warning}", stacklevel=2)
    if reach.get("warning"):
        warnings.warn(f"{source}: {reach['warning']}", stacklevel=2)
    camera_error = fold.get("error")
    if camera_error:
        warnings.warn(f"{source}: {camera_error}", stacklevel=2)
    hand_eye, error = None, None
    if tracking is None:
        report["hand_eye"] = {"skipped": hand_eye_skipped or "no tracker samples"}
    else:
        t0 = time.perf_counter()
        keep = np.flatnonzero(usable)
        views = _Views(detections.times[keep], ids[keep], detections.frames[keep],
                       poses[keep], [points[i] for i in keep], label[keep], detections.step)
        try:
            hand_eye, report["hand_eye"] = _hand_eye_stage(tracking, tracking_source, views, K,
                                                           dist, o, model_warning=model_warning)
            offset = report["hand_eye"]["tracker_time_offset"]
            offset.update(import_shift_s=float(import_shift_s),
                          total_s=float(import_shift_s + offset["applied_s"]))
        except ValueError as exc:
            error = str(exc)
            report["hand_eye"] = {"failed": error}
        report["timings_s"]["hand_eye"] = time.perf_counter() - t0
    return CalibrationResult(camera, hand_eye, report, error, camera_error)


def corner_reach(points: list[np.ndarray], camera: Camera) -> dict:
    """How far into the frame the board's corners ``points`` (the intrinsics' views) reach: the
    largest corner radius from the principal point over the largest radius of a pixel the
    frames show (within the field-of-view mask, if any), "fraction"; with a "warning" below
    MIN_CORNER_REACH. The lens model is fitted to the corners alone: beyond their reach it is
    extrapolated, and `run` undistorts whole frames with it."""
    c = camera.camera_matrix[:2, 2]
    corner = max(float(np.linalg.norm(p - c, axis=1).max()) for p in points)
    mask = camera.fov_mask()
    if mask is None:
        used = np.array([[0, 0], [camera.width - 1, 0], [0, camera.height - 1],
                         [camera.width - 1, camera.height - 1]], np.float64)
    else:
        v, u = np.nonzero(mask)
        used = np.stack([u, v], 1).astype(np.float64)
    frame = float(np.linalg.norm(used - c, axis=1).max())
    out = {"fraction": corner / frame, "corner_radius_px": corner, "frame_radius_px": frame,
           "what": ("the board corners' largest radius from the principal point over the "
                    "frame's (its farthest pixel" + (" inside the field-of-view mask" if mask
                                                     is not None else "") + "): beyond it "
                    "the lens model is extrapolated")}
    if out["fraction"] < MIN_CORNER_REACH:
        out["warning"] = (
            f"the board's corners reach {100 * out['fraction']:.0f} % of the frame's radius "
            f"from the principal point ({corner:.0f} of {frame:.0f} px; "
            "70 % advised): beyond it, over the frame's periphery, "
            "the lens model is extrapolated and may err by pixels to tens of pixels, whatever "
            "the RMS reprojection error and the standard errors say (they see the corners "
            "only). Film views with the board near the frame's edges and corners")
    return out


def _lens_fold(camera: Camera, reach: dict, points: list[np.ndarray]) -> dict:
    """What calibration.json says of undistorting whole frames with ``camera`` (as `run`
    does: io.calibration.LensUndistortion, within the field-of-view mask): {"folds_over":
    False}, or True with the fold's pixel and an "error" (run refuses the camera.yaml), which
    compares its radius with the board's corners' ``points`` in its direction (within 22.5
    deg). A model with many coefficients (--distortion 8) can fit the corners to 0.04 px and
    fold over beyond them (review: `simulate checkerboard`, seed 0: at 64 % of the frame's
    radius, near the top edge, where the corners reached 62 %; 70 % at most)."""
    from fusedmosaic.io.calibration import LensFoldError

    out: dict = {"folds_over": False, "fov_mask_radius": camera.fov_mask_radius}
    try:
        camera.undistortion()
    except LensFoldError as exc:
        (u, v), (x, y) = exc.pixel, exc.raw
        c = camera.camera_matrix[:2, 2]
        radius = float(np.hypot(x - c[0], y - c[1]) / reach["frame_radius_px"])
        d = np.concatenate(points) - c
        # each corner's direction from the principal point against the fold's, within +-pi
        turn = np.angle(np.exp(1j * (np.arctan2(d[:, 1], d[:, 0])
                                     - np.arctan2(y - c[1], x - c[0]))))
        along = np.linalg.norm(d[np.abs(turn) <= np.pi / 8], axis=1)
        there = float(along.max() if along.size else 0.0) / reach["frame_radius_px"]
        n = 0 if camera.distortion is None else camera.distortion.size
        out.update(folds_over=True, pixel=[u, v], raw_pixel=[x, y], radius_fraction=radius,
                   corner_reach_that_way=there, error=(
                       f"the {camera.lens_model} lens model with {n} distortion coefficients "
                       f"folds over inside the {camera.width}x{camera.height} frame: undistorted "
                       f"pixel ({u}, {v}) is drawn from raw pixel ({x:.0f}, {y:.0f}), mirrored, "
                       f"at {100 * radius:.0f} % of the frame's radius from the principal point "
                       f"(the board's corners reach {100 * there:.0f} % that way, "
                       f"{100 * reach['fraction']:.0f} % at most): it fits the corners but not "
                       "the frame beyond them, and run refuses this "
                       "camera.yaml (its undistorted frames would show a double image). "
                       "Calibrate with fewer distortion coefficients (--distortion 5 or 4), or "
                       "with views that bring the board to the frame's edges and corners"))
    except ValueError as exc:  # no undistorted pixel inside the raw frame
        out.update(folds_over=True, error=str(exc))
    return out


def _camera_model_warning(rms_px: float, o: CalibrationOptions) -> str:
    """What to say of an RMS reprojection error above MAX_REPROJECTION_RMS_PX ("" below): the
    lens model and what to try instead."""
    if not rms_px > MAX_REPROJECTION_RMS_PX:
        return ""
    n = o.coefficients
    if o.lens_model == "fisheye":
        hint = ("estimate the fisheye's k1..k4 (--distortion 4)" if n < FISHEYE_COUNT else
                "the pinhole model with more coefficients (--lens-model pinhole --distortion 8)")
    elif n < 5:
        hint = ("more distortion coefficients (--distortion 5) or, for a wide-angle scope, "
                "--lens-model fisheye")
    elif n < 8:
        # (calibrate checks that the rational model does not fold over beyond the corners:
        # _lens_fold; it did on the simulator's default recording, seed 0)
        hint = ("--distortion 8 (the rational model: calibrate then checks that it does not "
                "fold over inside the frame) or, for a wide-angle scope, --lens-model fisheye")
    else:
        hint = "--lens-model fisheye"
    model = f"{o.lens_model} model with {n} distortion coefficient{'s' * (n != 1)}"
    return (f"the RMS reprojection error is {rms_px:.3f} px, above the "
            f"{MAX_REPROJECTION_RMS_PX:g} px a camera model fitting the lens leaves (corners on "
            f"a clear board are found to ~0.05-0.2 px): the {model} may not describe this lens, "
            f"and its intrinsics and their standard errors are then biased; try {hint} (or check "
            "the frames for motion blur and an out-of-focus board)")


@dataclass
class _Views:
    """The usable detections the hand-eye works on (calibrate_detections)."""

    times: np.ndarray
    ids: np.ndarray
    frames: np.ndarray
    poses: np.ndarray  # cam_from_board (N, 4, 4)
    points: list[np.ndarray]
    label: np.ndarray  # repeated_views label: one per distinct board pose
    step: int


def _still_view_samples(samples, views: _Views, offset: float, K, dist, o):
    """The hand-eye's measurements from the views where the scope was held still: each still
    group's board pose (from its frames' mean corners) paired with every raw tracker sample
    taken while it was filmed (stamped within its first and last frame's times + offset), so
    that no sample is interpolated across a motion and each enters once. Returns
    (tracker_from_sensor (S, 4, 4), cam_from_board (S, 4, 4), cluster label (S,), sample
    index (S,), frame id of each group's first frame (S,), groups with a sample)."""
    groups = still_groups(views.points, views.frames, views.step)
    valid = np.flatnonzero(samples.valid)
    ts = samples.timestamps[valid]
    mean_corners = [np.mean([views.points[k] for k in g], axis=0) for g in groups]
    poses, _ = board_poses(mean_corners, K, dist, o) if groups else (np.empty((0, 4, 4)), None)
    A, C, cluster, index, first = [], [], [], [], []
    used = 0
    for g, pose in zip(groups, poses, strict=True):
        inside = valid[(ts >= views.times[g[0]] + offset) & (ts <= views.times[g[-1]] + offset)]
        if inside.size == 0:
            continue
        used += 1
        A.append(_tracker_samples(samples, inside))
        C.append(np.repeat(pose[None], inside.size, axis=0))
        cluster.append(np.full(inside.size, views.label[g[0]]))
        index.append(inside)
        first.append(np.full(inside.size, views.ids[g[0]]))
    if not A:
        return None
    return (np.concatenate(A), np.concatenate(C), np.concatenate(cluster),
            np.concatenate(index), np.concatenate(first), used)


def _check_hand_eye_groups(source: str, still_views: int, blocks: np.ndarray,
                           coverage: str = "") -> None:
    """ValueError unless the hand-eye has MIN_HAND_EYE_GROUPS independent groups of
    measurements: distinct still views with a tracker sample, or BOOTSTRAP_BLOCK_S blocks of
    tracked frames; ``coverage`` says how much of the recording the tracker covers."""
    n_blocks = len(np.unique(blocks))
    if max(still_views, n_blocks) < MIN_HAND_EYE_GROUPS:
        raise ValueError(
            f"{source}: the hand-eye needs at least {MIN_HAND_EYE_GROUPS} distinct views held "
            f"still (or {MIN_HAND_EYE_GROUPS * BOOTSTRAP_BLOCK_S:g} s of tracked frames filmed "
            f"while moving); this recording has {still_views} still view(s) and "
            f"{n_blocks * BOOTSTRAP_BLOCK_S:g} s of frames with a tracker sample{coverage}: film "
            "the board from more angles, pausing at each, with the tracker on throughout")


def _hand_eye_stage(samples, source: str, views: _Views, K: np.ndarray, dist: np.ndarray,
                    o: CalibrationOptions, *,
                    model_warning: str = "") -> tuple[np.ndarray, dict]:
    """The hand-eye of calibrate_detections from the usable views and its report; ValueError
    naming tracking.csv (``source``) when it fails or the result is implausible: the tracker
    and the board disagree (naming the camera model as a suspect when ``model_warning``, its
    RMS reprojection error high: _camera_model_warning), the board's scale against the
    tracker's is not 1 (--square-mm, the tracker's unit), or the clock offset lies at the
    search bound."""
    from fusedmosaic.io.tracking import GAP_SPACINGS, interpolate_camera_poses, sample_spacing

    times, poses = views.times, views.poses

    def tracker_at(delta: float, method: str = "cubic") -> tuple[np.ndarray, np.ndarray]:
        # interpolate_camera_poses with no hand-eye gives sensor_from_tracker as [r, t].
        pose, ok = interpolate_camera_poses(samples, times + delta, None, allow_outside=True,
                                            source=source, method=method)
        return _tracker_from_sensor(pose[ok]), ok

    shift = 0.0 if o.time_offset == "auto" else float(o.time_offset)
    A, valid = tracker_at(shift)
    _check_tracker_covers(samples, valid, times + shift, source, "views")
    blocks = np.floor((times[valid] - times[valid][0]) / BOOTSTRAP_BLOCK_S)
    # Only still views the tracker covers count (a tracker on for a part of the recording had
    # the untracked ones counted, and the fit then failed as 'rotate about two axes').
    groups = still_groups(views.points, views.frames, views.step)
    still_views = len({int(views.label[g[0]]) for g in groups if valid[g].all()})
    held = np.zeros(times.size, bool)  # views held still: they show no clock offset
    for g in groups:
        held[g] = True
    coverage = ""
    if not valid.all():
        from fusedmosaic.io.tracking import _time

        coverage = (f" (the tracker covers {int(valid.sum())} of the {valid.size} views, "
                    f"[{_time(times[valid][0])}, {_time(times[valid][-1])}] s of the frames' "
                    f"[{_time(times[0])}, {_time(times[-1])}] s)")
    _check_hand_eye_groups(source, still_views, blocks, coverage)
    bound_hint = ""
    try:
        # All frames, the tracker interpolated at their times: the clock offset (it needs the
        # frames filmed while moving) and the start of the fits below.
        first = calibrate_hand_eye(A, poses[valid], rot_sigma_deg=o.rot_sigma_deg,
                                   trans_sigma_mm=o.trans_sigma_mm, fit_scale=True)
        offset = {"estimated": False, "applied_s": shift}
        if o.time_offset == "auto":
            # A bound leaving too few views tracked at every offset within it skipped the
            # estimate (--max-time-offset 4 on a 6.4 s recording; the reason only in
            # calibration.json) or failed its fits: refused, naming the recording's length.
            # the shortest dropout that uncovers a frame (io.tracking.interpolate_camera_poses)
            # (the coverage's 5 ms steps meet every dropout of a tracker up to 300 Hz; a faster
            # one's are checked in finer steps: tracked_at_every_offset)
            gap_s = GAP_SPACINGS * sample_spacing(samples.timestamps[samples.valid])
            try:
                offset = estimate_time_offset(tracker_at, poses, first, o.max_time_offset_s,
                                              times, still=held, gap_s=gap_s)
                # (a scan without a clear least is no failure: the offset not determined, 0)
                failed = "" if offset["estimated"] or "scan" in offset else (
                    f"at least {MIN_HAND_EYE_VIEWS} views tracked at every offset are needed")
            except ValueError as exc:
                failed = f"over them {exc}"
            if failed:
                bound = o.max_time_offset_s + 0.004  # as estimate_time_offset looks
                ends = tracker_at(-bound)[1] & tracker_at(bound)[1]
                covered = tracked_at_every_offset(tracker_at, bound, gap_s)
                note = _offset_bound_note(samples, times, gap_s)
                dropouts = int(ends.sum() - covered.sum())
                if dropouts:
                    note += (f"; the tracker's dropouts (over {1e3 * gap_s:.0f} ms between valid "
                             f"samples) leave {dropouts} more views untracked at some offset "
                             "within it")
                raise ValueError(
                    f"the clock offset search within +-{o.max_time_offset_s:g} s "
                    f"(--max-time-offset) covers {int(covered.sum())} of the {times.size} views "
                    f"(those tracked at every offset within it): {failed}; {note}. Lower "
                    "--max-time-offset, or give the offset with --time-offset S")
            # A fit failing after an estimated offset may be the offset's fault: the coarse
            # scan holds the hand-eye fitted at 0, so clocks >= ~0.6 s apart were estimated
            # wrongly (0.6 s: -53 +- 1 ms) and the tracker and the board then disagreed.
            bound_hint = (
                f"; the clock offset was estimated at {1e3 * offset['estimate_s']:+.0f} +- "
                f"{1e3 * offset['std_s']:.1f} ms (within +-{o.max_time_offset_s:g} s): if the "
                "clocks differ by more or that is wrong, give the offset with --time-offset S "
                "(or raise --max-time-offset)") if offset["estimated"] else (
                f"; the clock offset was {offset['reason']}")
            if offset["at_bound"]:
                bound_hint = (
                    f"; the clock offset estimate ({1e3 * offset['estimate_s']:+.0f} ms) lies at "
                    f"the search bound +-{o.max_time_offset_s:g} s: the clocks may differ by "
                    "more (raise --max-time-offset, or give --time-offset S)")
                if offset["std_s"] <= 0.01:
                    bound_hint = ""
                    raise ValueError(
                        f"the tracker's clock offset against the frames' is not within the "
                        f"search bound: the estimate ({1e3 * offset['estimate_s']:+.0f} +- "
                        f"{1e3 * offset['std_s']:.1f} ms) lies at +-{o.max_time_offset_s:g} s "
                        "and the fit still improves beyond it; raise --max-time-offset (e.g. "
                        f"{2 * o.max_time_offset_s:g}) or give the offset with --time-offset S")
        unshifted = first  # (the fit without the estimated offset: the refusals compare it)
        if offset["applied_s"] != shift:  # from the closed form: the fit at 0 may be far off
            A, valid = tracker_at(offset["applied_s"])
            first = calibrate_hand_eye(A, poses[valid], rot_sigma_deg=first.tracker_sigma[0],
                                       trans_sigma_mm=first.tracker_sigma[1], fit_scale=True)
        still = _still_view_samples(samples, views, offset["applied_s"], K, dist, o)
        mode = "still"
        if still is None or len(np.unique(still[2])) < MIN_STILL_VIEWS:
            mode = "interpolated"
        else:
            try:
                free = calibrate_hand_eye(still[0], still[1], rot_sigma_deg=o.rot_sigma_deg,
                                          trans_sigma_mm=o.trans_sigma_mm, fit_scale=True)
            except ValueError:  # the still views alone do not determine it: all frames
                mode = "interpolated"
        if mode == "still":
            A_fit, C_fit, clusters = still[0], still[1], still[2]
        else:
            free, A_fit, C_fit = first, A, poses[valid]
            clusters = np.floor((times[valid] - times[valid][0]) / BOOTSTRAP_BLOCK_S)
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}{bound_hint}") from None
    if mode == "interpolated":
        _check_hand_eye_groups(source, 0 if still is None else len(np.unique(still[2])),
                               clusters)
    n = len(A_fit)

    def without_offset() -> HandEyeResult | None:
        # The fit of the refused one's kind (still views' samples, or all frames interpolated)
        # without the estimated offset applied; None without one applied or when it fails.
        if not (offset.get("estimated") and offset["applied_s"]):
            return None
        if mode == "interpolated":
            return unshifted
        at_zero = _still_view_samples(samples, views, shift, K, dist, o)
        try:
            return None if at_zero is None else calibrate_hand_eye(
                at_zero[0], at_zero[1], rot_sigma_deg=o.rot_sigma_deg,
                trans_sigma_mm=o.trans_sigma_mm, fit_scale=True)
        except ValueError:
            return None

    def offset_suspect(without: str) -> str:
        # An estimated offset applied pairs each view with the tracker at another time: a wrong
        # one (a scan's least on noise: +288 ms for clocks that agree) makes the tracker and
        # the board disagree or the scale come out wrong (-0.056 against 1.013 without it), so
        # the refusals name it first when the same fit without it has no such fault (`without`
        # says what it has; "" when it has the fault too: quaternions w, x, y, z with +7 ms
        # applied).
        if not without:
            return ""
        return (f"the clock offset applied ({1e3 * offset['estimate_s']:+.0f} +- "
                f"{1e3 * offset['std_s']:.1f} ms, estimated within +-{o.max_time_offset_s:g} "
                f"s): without it {without}; calibrate again with --time-offset 0 (or the "
                "offset, if known)")

    def agrees(fit: HandEyeResult) -> bool:
        return (fit.inlier.size - int(fit.inlier.sum()) <= 0.5 * fit.inlier.size
                and fit.tracker_sigma[0] <= MAX_TRACKER_SIGMA[0]
                and fit.tracker_sigma[1] <= MAX_TRACKER_SIGMA[1])

    def check_agreement(fit: HandEyeResult) -> None:
        outliers = n - int(fit.inlier.sum())
        if agrees(fit):
            return
        # The residuals, not fit.tracker_sigma: with most samples beyond 3 sigma that stays
        # the prior (--rot-sigma / --trans-sigma; it read 1.00 deg / 1.00 mm).
        rms = [float(np.sqrt(np.mean(r ** 2) / 3)) for r in (fit.rotation_residual_deg,
                                                               fit.translation_residual_mm)]
        alt = without_offset()
        clock = offset_suspect(
            f"they agree (the tracker's noise seen {alt.tracker_sigma[0]:.2f} deg / "
            f"{alt.tracker_sigma[1]:.2f} mm per axis)" if alt is not None and agrees(alt)
            else "")
        # A lens model that does not fit biases every board pose: the first suspect then
        suspect = "" if not model_warning else (
            f"Suspect the camera model first: {model_warning}"
            + (f"; then {clock}" if clock else "") + ". Otherwise check")
        if clock and not suspect:
            suspect = f"Suspect first {clock}. Otherwise check"
        raise ValueError(
            f"{source}: the tracker and the board disagree: {outliers} of {n} "
            f"{'tracker samples' if mode == 'still' else 'views'} beyond 3 sigma, RMS "
            f"residuals {rms[0]:.2f} deg / {rms[1]:.2f} mm per axis (an EM tracker: tenths). "
            f"{suspect or 'Check'} that tracking.csv holds tracker_from_sensor (not its "
            "inverse) with quaternions x, y, z, w and translations in mm, the board's "
            "--square-mm, and the "
            f"frame times (frames.csv, or --fps without it){'' if clock else bound_hint}")

    check_agreement(free)
    scale_boot = bootstrap_hand_eye(free, clusters, replicates=BOOTSTRAP_REPLICATES)
    scale_std = max(free.scale_std, scale_boot["scale_std"])
    significant = abs(free.scale - 1) > SCALE_SIGMAS * scale_std
    scale = {"ratio": free.scale, "std": scale_std, "square_mm_implied": o.square_mm * free.scale,
             "applied": bool(significant)}
    if significant and abs(free.scale - 1) > MAX_SCALE_DEVIATION:
        alt = without_offset()
        suspect = offset_suspect(
            f"the tracker's motions are {alt.scale:.4g} x the board's"
            if alt is not None and abs(alt.scale - 1) <= MAX_SCALE_DEVIATION else "")
        unit = (" (x 0.001: metres?)" if 0.0005 < free.scale < 0.002 else
                " (x 0.1: cm?)" if 0.05 < free.scale < 0.2 else "")
        raise ValueError(
            f"{source}: the tracker's motions are {free.scale:.4g} +- {scale_std:.2g} x those "
            f"the board gives{unit}, where 1 is expected: by the tracker the board's squares "
            f"measure {o.square_mm * free.scale:.3g} mm, not {o.square_mm:g} mm. "
            + (f"Suspect first {suspect}. Otherwise check" if suspect else "Check")
            + " the square size (--square-mm, a printed board's scaling) and that "
            f"tracking.csv's translations are in mm{'' if suspect else bound_hint}")
    # A scale that differs from 1 by a little, but significantly (a board printed scaled by
    # 1-3 %, a tracker's own scale error), is kept: the hand-eye is then in the tracker's mm,
    # which is what the tracked poses are composed with.
    try:
        he = calibrate_hand_eye(A_fit, C_fit, rot_sigma_deg=free.tracker_sigma[0],
                                trans_sigma_mm=free.tracker_sigma[1], start=free,
                                fit_scale=significant)
    except ValueError as exc:
        raise ValueError(f"{source}: {exc}{bound_hint}") from None
    # The noise seen follows the residuals (calibrate_hand_eye): a wrong input's too, so the
    # final fit's is checked as well (quaternions w, x, y, z on a 12-view recording: 3.4 deg /
    # 5.5 mm seen there, beyond MAX_TRACKER_SIGMA).
    check_agreement(he)
    boot = bootstrap_hand_eye(he, clusters, replicates=BOOTSTRAP_REPLICATES)
    # What the tracker alone places: board corners through the tracked camera pose (the board
    # in the tracker's mm when a scale was applied).
    predicted = np.linalg.inv(he.sensor_from_camera) @ np.linalg.inv(A) @ he.tracker_from_board
    obj = o.board_points() * he.scale
    through_tracker = np.array([
        np.mean(np.linalg.norm(project_points(
            obj, K, dist, o.lens_model, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3]) - views.points[k],
            axis=1))
        for T, k in zip(predicted, np.flatnonzero(valid), strict=True)])
    used = views.ids[valid]
    if mode == "still":
        beyond = sorted({int(v) for v in still[4][~he.inlier]})
        measurements = {"mode": "still views: raw tracker samples while the board pose held",
                        "still_views": int(still[5]), "tracker_samples": n,
                        "distinct_views": int(len(np.unique(clusters)))}
        noise_from = "raw tracker samples of the still views (the tracker's own noise)"
        distinct = int(len(np.unique(clusters)))
        if len(beyond) > STILL_VIEWS_BEYOND_FRACTION * distinct:
            applied = offset["applied_s"] * 1e3
            how = ("as estimated" if offset.get("estimated") else
                   "as given with --time-offset; --time-offset auto estimates it")
            measurements["warning"] = (
                f"{len(beyond)} of {distinct} still views have tracker samples beyond 3 sigma: "
                "within a view held still the samples agree to the tracker's noise, so the "
                "tracker moved within these views as the time offset applied puts them "
                f"({applied:+.1f} ms, {how}): a wrong time offset, or views not held still. "
                "The noise seen is then not the tracker's own (run --calibration would weigh "
                "the tracker by it) and the hand-eye may err beyond the expected error")
            noise_from += " (suspect: see warning)"
    else:
        beyond = [int(v) for v in used[~he.inlier]]
        measurements = {"mode": "all frames: the tracker interpolated at the frame times",
                        "distinct_views": int(len(np.unique(views.label[valid]))),
                        "warning": (
                            f"fewer than {MIN_STILL_VIEWS} views held still: the hand-eye comes "
                            "from frames filmed while moving, where the tracker interpolated "
                            "between samples errs systematically (more at low tracker rates) "
                            "and the error may exceed the estimate; pause at each view")}
        noise_from = ("the tracker interpolated at the frame times: between two samples the "
                      "noise averages, so this is below a sample's noise")
    per_view = {"frame": used.tolist(),
                "board_through_tracker_px": through_tracker.round(3).tolist()}
    if mode == "interpolated":
        per_view["rotation_residual_deg"] = he.rotation_residual_deg.round(4).tolist()
        per_view["translation_residual_mm"] = he.translation_residual_mm.round(4).tolist()
    rotation_rms = max(boot["rotation_rms_deg"], he.rotation_rms_deg)
    translation_rms = max(boot["translation_rms_mm"], he.translation_rms_mm)
    return he.sensor_from_camera, {
        "views": int(valid.sum()),
        **measurements,
        "tracker_time_offset": offset,
        "views_without_tracker_sample": [int(v) for v in views.ids[~valid]],
        "views_beyond_3_sigma": beyond,
        "sensor_from_camera": he.sensor_from_camera.tolist(),
        "tracker_from_board": he.tracker_from_board.tolist(),
        "sensor_from_camera_closed_form": first.closed_form.tolist(),
        "rotation_error_rms_deg": rotation_rms,
        "translation_error_rms_mm": translation_rms,
        "standard_errors": {
            "what": ("1 sigma: per axis (the largest over directions) and the RMS error "
                     "magnitude (sqrt of the covariance's trace); the larger of the bootstrap "
                     "and the tracker-noise figure is reported as rotation_error_rms_deg / "
                     "translation_error_rms_mm"),
            "bootstrap": {**boot, "over": (
                "distinct board poses (still views)" if mode == "still" else
                f"blocks of {BOOTSTRAP_BLOCK_S:g} s of frames"), "seed": 0},
            "from_tracker_noise": {
                "rotation_std_deg": he.rotation_std_deg,
                "rotation_rms_deg": he.rotation_rms_deg,
                "translation_std_mm": he.translation_std_mm,
                "translation_rms_mm": he.translation_rms_mm},
        },
        "board_scale": scale,
        "tracker_sigma_deg": he.tracker_sigma[0],
        "tracker_sigma_mm": he.tracker_sigma[1],
        "tracker_sigma_from": noise_from,
        "tracker_residual_rotation_deg_rms": float(np.sqrt(np.mean(
            he.rotation_residual_deg ** 2))),
        "tracker_residual_translation_mm_rms": float(np.sqrt(np.mean(
            he.translation_residual_mm ** 2))),
        "per_view": per_view,
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


@dataclass(frozen=True)
class TrackerCalibration:
    """What calibrate measured of the tracker, for runs of recordings from the same set-up:
    time_offset_s, the shift to apply to the dataset's tracking.csv (the tracker's clock ahead
    of the video's as calibrate measured it, 0 where not significant, less any shift the
    dataset's tracking.csv had at import); rot_sigma_deg / trans_sigma_mm, its noise per axis
    as seen against the board (tracker_sigma_from says which samples: a still view's raw
    samples, or samples interpolated at moving frames' times, below a raw sample's);
    time_offset_note: why the offset is 0 or where it came from ("" when calibrate measured
    and applied it)."""

    time_offset_s: float
    rot_sigma_deg: float
    trans_sigma_mm: float
    sigma_from: str
    time_offset_note: str = ""


def read_tracker_calibration(path: str | Path,
                             dataset: str | Path | None = None) -> TrackerCalibration:
    """The tracker's time offset and noise from a calibration.json calibrate wrote (its
    "hand_eye" entry); ValueError naming the file when it has no hand-eye calibration or a
    value is missing or out of range. The offset is calibrate's total against the video (the
    shift its recording's tracking.csv had at import, "import_shift_s", plus the one calibrate
    applied, "applied_s"; "total_s" says the sum). ``dataset``: the dataset the calibration is
    for (run's); when its tracking.csv was already shifted at import
    (io.plus.applied_tracker_time_offset), only the difference is applied, with a warning when
    there is one (the two disagree). A calibration.json without "import_shift_s" (calibrate
    before it) gives its "applied_s", and a dataset shifted at import none (time_offset_s 0,
    with a warning). Warns when calibrate warned of the hand-eye or of the intrinsics (a lens
    model that misfits inflates the tracker noise seen)."""
    from fusedmosaic.io.output import read_json_object
    from fusedmosaic.io.tracking import check_time_offset

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: {'is a folder; expected' if path.is_dir() else 'not found:'} "
                         "a calibration.json written by fusedmosaic calibrate")
    data = read_json_object(path)
    he = data.get("hand_eye")
    why = (he.get("skipped") or he.get("failed")) if isinstance(he, dict) else \
        'no "hand_eye" entry'
    if why:
        # "calibrate a recording with tracking.csv" only where it had none: a failed hand-eye
        # had one (a wrong --square-mm, a tracker in another convention)
        advice = ("the hand-eye failed at calibrate: correct what its message names and "
                  "calibrate again" if isinstance(he, dict) and not he.get("skipped") else
                  "calibrate a recording with tracking.csv")
        raise ValueError(f"{path}: holds no hand-eye calibration ({why}), so no tracker time "
                         f"offset or noise: {advice}")
    try:
        entry = he["tracker_time_offset"]
        offset = entry["applied_s"]
        sigma = (he["tracker_sigma_deg"], he["tracker_sigma_mm"])
    except (KeyError, TypeError):
        raise ValueError(f"{path}: its hand_eye lacks tracker_time_offset.applied_s, "
                         "tracker_sigma_deg or tracker_sigma_mm (written by an older "
                         "calibrate? calibrate the recording again)") from None
    offset = check_time_offset(offset, f"{path}: hand_eye.tracker_time_offset.applied_s")
    import_shift = entry.get("import_shift_s")  # None: written before calibrate read import.json
    if import_shift is not None:  # (its total_s, for the reader, is this sum)
        import_shift = check_time_offset(
            import_shift, f"{path}: hand_eye.tracker_time_offset.import_shift_s")
        total = check_time_offset(import_shift + offset,
                                  f"{path}: hand_eye.tracker_time_offset.total_s")
    for key, value, bound in zip(("tracker_sigma_deg", "tracker_sigma_mm"), sigma,
                                 MAX_TRACKER_SIGMA, strict=True):
        if (isinstance(value, bool) or not isinstance(value, (int, float))
                or not 0 < value <= bound):
            raise ValueError(f"{path}: hand_eye.{key} must be a number in (0, {bound:g}], got "
                             f"{value!r}")
    if he.get("warning"):  # what calibrate said of it holds for its noise figure too
        warnings.warn(f"{path}: calibrate warned of this calibration: {he['warning']}",
                      stacklevel=2)
    intrinsics = data.get("intrinsics")
    if isinstance(intrinsics, dict) and intrinsics.get("warning"):
        # A lens model that misfits biases every board pose, and the tracker's disagreement
        # with them is taken for its noise: review, --distortion 0 on the simulator's k1 -0.3
        # lens, 1.52 deg / 0.80 mm seen for a true 0.9 / 0.25 (ba-emt / lba-emt weigh the
        # tracker by it)
        warnings.warn(f"{path}: calibrate warned of its intrinsics, so the tracker noise it "
                      f"saw ({float(sigma[0]):.3g} deg / {float(sigma[1]):.3g} mm) may be "
                      f"inflated by the lens model's misfit: {intrinsics['warning']}",
                      stacklevel=2)
    if entry.get("estimated") and offset == 0:
        note = f"calibrate did not apply one: {entry.get('reason', 'not significant')}"
    elif not entry.get("estimated"):
        note = (f"not estimated by calibrate: {entry['reason']}" if "reason" in entry
                else "as given to calibrate")
    else:
        note = ""
    if import_shift:  # the calibration recording's tracking.csv was shifted at import
        note = "; ".join(filter(None, [
            note, f"calibrate's recording was shifted by {import_shift:+g} s at import: "
                  f"{total:+g} s in all"]))
    from fusedmosaic.io.plus import IMPORT_RECORD, applied_tracker_time_offset

    done = None if dataset is None else applied_tracker_time_offset(dataset)
    record = None if dataset is None else Path(dataset) / IMPORT_RECORD
    if import_shift is None:  # (an older calibration.json: its offset against its recording)
        if done and offset:  # tracking.csv is on the video's clock already: not again
            warnings.warn(
                f"{Path(dataset) / 'tracking.csv'} was already shifted by the tracker time "
                f"offset {done:+g} s at import ({record}); {path}'s offset {offset:+g} s not "
                "applied again", stacklevel=2)
            offset, note = 0.0, (f"not applied: tracking.csv was shifted by {done:+g} s at "
                                 "import")
    else:
        offset = total
        if done:  # tracking.csv shifted by `done` already: what remains of calibrate's total
            offset = check_time_offset(total - done, f"{path}: its offset {total:+g} s less "
                                                     f"the shift at import ({record})")
            if abs(offset) > 1e-9:
                warnings.warn(
                    f"{Path(dataset) / 'tracking.csv'} was shifted by the tracker time offset "
                    f"{done:+g} s at import ({record}), {path} measured {total:+g} s: the "
                    f"difference {offset:+g} s applied", stacklevel=2)
                note = (f"tracking.csv was shifted by {done:+g} s at import, calibrate measured "
                        f"{total:+g} s: the difference applied")
            else:
                offset, note = 0.0, (f"tracking.csv was shifted by {done:+g} s at import, the "
                                     "offset calibrate measured")
    return TrackerCalibration(offset, float(sigma[0]), float(sigma[1]),
                              str(he.get("tracker_sigma_from", "")), note)


OUTPUT_FILES = ("camera.yaml", "hand_eye.txt", "calibration.json")
OUTPUT_RECORD = "calibrate"  # the output set's key in the folder's manifest (io.output)


def check_calibration_output(out: str | Path) -> None:
    """ValueError naming the file when ``out`` holds a camera.yaml, hand_eye.txt or
    calibration.json that no fusedmosaic calibrate wrote (not recorded in the folder's
    manifest, io.output.MANIFEST): a user's own files are never replaced (the output contract
    of ``run``). Call it before the work; write_calibration checks again."""
    from fusedmosaic.io.output import MANIFEST, read_manifest

    out = Path(out)
    if not out.is_dir():
        return
    recorded = set((read_manifest(out) or {}).get(OUTPUT_RECORD, {}).get("files", []))
    for name in OUTPUT_FILES:
        path = out / name
        if (path.exists() or path.is_symlink()) and name not in recorded:
            raise ValueError(
                f"{path}: exists and no fusedmosaic calibrate wrote it (it is not listed in "
                f"{out / MANIFEST}); calibrate replaces only its own outputs: choose another "
                "output folder (--out), or move the file away")


def write_calibration(out: str | Path, result: CalibrationResult) -> list[str]:
    """camera.yaml, hand_eye.txt (when found) and calibration.json into ``out``, atomically
    (io.OutputWriter), recorded in the folder's manifest; a previous calibration's files there
    are replaced (its hand_eye.txt removed when none is found now), anyone else's refused
    (check_calibration_output). Returns the names written."""
    from fusedmosaic.io.calibration import write_camera_yaml
    from fusedmosaic.io.output import OutputWriter
    from fusedmosaic.io.tracking import write_hand_eye

    check_calibration_output(out)
    with OutputWriter(out, record=OUTPUT_RECORD, expects=OUTPUT_FILES) as w:
        write_camera_yaml(w.path("camera.yaml"), result.camera)
        if result.hand_eye is not None:
            write_hand_eye(w.path("hand_eye.txt"), result.hand_eye)
        w.write_json("calibration.json", result.report)
        return w.written()
