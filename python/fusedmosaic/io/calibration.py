"""Camera intrinsics: ``camera.yaml`` in OpenCV FileStorage format (dataset contract)."""

from __future__ import annotations

import difflib
import numbers
import re
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from fusedmosaic.io._table import require_file

DISTORTION_COUNTS = (4, 5, 8, 12, 14)  # lengths cv2.undistortPoints accepts
# Lens models: "pinhole", OpenCV's standard model (a perspective projection with radial and
# tangential distortion, 4-14 coefficients: cv2.calibrateCamera / undistortPoints); "fisheye",
# OpenCV's fisheye model (Kannala-Brandt: the equidistant projection r = f theta with theta
# distorted by k1..k4, exactly 4 coefficients: cv2.fisheye), for wide-angle scopes whose field
# of view the pinhole model's polynomial cannot follow.
LENS_MODELS = ("pinhole", "fisheye")
FISHEYE_COUNT = 4
# camera.yaml's distortion_model (ROS camera_info's names; OpenCV's own calibration sample
# writes a fisheye_model flag instead) -> lens model.
DISTORTION_MODELS = {"plumb_bob": "pinhole", "rational_polynomial": "pinhole",
                     "equidistant": "fisheye", "fisheye": "fisheye"}
# K's fixed entries (last row 0 0 c, K[1, 0] = 0), relative to the scale of their row: text
# rounding and float32 storage (K[2, 2] = 0.99999994) pass, a transposed K does not.
K_LAYOUT_TOLERANCE = 1e-6
# Generous sanity bound, not a tuned one: a focal length over 10^4 image sizes is a field of view
# under 0.006 degrees, i.e. a unit error (e.g. fx in µm or nm), not an endoscope.
MAX_FOCAL_IMAGE_SIZES = 1e4
# The opposite unit error, a focal length in mm (2.4 for a 480 px lens), is a focal length of a
# few px: a field of view no lens has. Bounds on the angle of the frame's corner rays from the
# optical axis (r = half the frame's diagonal, from the image centre): pinhole, tan(angle) =
# r / f, 87.5 deg (a 175 deg diagonal field of view; the fetoscopy simulator accepts corner rays
# up to 87.1 deg, so none of its cameras is refused); fisheye, angle = r / f (equidistant),
# 360 deg (a fisheye sees up to ~140 deg from the axis at its image circle's edge, a 280 deg
# lens; a wide frame's corners beyond the circle ~290 deg). A 4.8 mm focal length given for a
# 480 px lens (fx = 4.8) is refused by either: corner rays 89.2 deg (pinhole) or 4050 deg
# (fisheye) from the axis.
MAX_CORNER_ANGLE_DEG = {"pinhole": 87.5, "fisheye": 360.0}
# fx / fy: square pixels give 1; anamorphic lenses and video pixel aspects stay within ~3. Beyond
# this one axis of K is in other units than the other (or mistyped).
MAX_FOCAL_ASPECT = 5.0
_KEYS = "image_width, image_height[, camera_matrix, ...]"  # named in parse errors
# The keys read_camera_yaml reads (write_camera_yaml writes only these).
CAMERA_KEYS = ("image_width", "image_height", "camera_matrix", "distortion_coefficients",
               "distortion_model", "fisheye_model", "pixel_size_um", "fov_mask_radius")
# Keys that calibration tools write beside those and camera.yaml does not use: left unread
# without a word. OpenCV's calibration sample and tutorial (samples/cpp/calibration.cpp,
# camera_calibration.cpp), ROS camera_info (camera_calibration_parsers).
FOREIGN_CAMERA_KEYS = frozenset({
    "calibration_time", "calibration_Time", "nframes", "nr_of_frames", "board_width",
    "board_height", "square_size", "aspectRatio", "fix_aspect_ratio", "flags",
    "avg_reprojection_error", "per_view_reprojection_errors", "extrinsic_parameters",
    "image_points", "grid_points", "camera_name", "rectification_matrix", "projection_matrix",
    "marker_size", "dictionary",  # (the ChArUco-era tutorial)
})


@dataclass(eq=False)
class Camera:
    """Image size and optional intrinsics of the endoscope camera.

    camera_matrix : (3, 3) float64 K = [fx s cx; 0 fy cy; 0 0 1] with fx, fy > 0, needed by the
        pose methods only. On entry it must only be a finite 3x3 matrix (methods that do not use
        it may carry a placeholder); its layout, focal bound and invertibility are checked by
        require_camera_matrix(). A valid K with last row 0 0 c (c > 0) is divided by c.
    distortion : (k,) OpenCV distortion coefficients (k = 4, 5, 8, 12 or 14), or None; an empty
        or all-zero vector (ROS ``D: []``) means no distortion and becomes None. OpenCV's
        undistortion ignores the skew K[0, 1] when distortion is given (negligible for
        endoscopes, whose skew is 0). With lens_model "fisheye": k1..k4 of OpenCV's fisheye
        model (None: zeros, the pure equidistant lens, which is not a pinhole; an empty vector
        is refused: "no distortion" does not exist for that model).
    lens_model : "pinhole" (OpenCV's standard model) or "fisheye" (cv2.fisheye); see
        LENS_MODELS.
    pixel_size_um : µm per pixel (pCLE robot methods convert robot µm to pixels with it).
    fov_mask_radius : px, radius of the circular field of view centred on the image centre.
    source : where the camera came from, used in error messages.
    """

    width: int
    height: int
    camera_matrix: np.ndarray | None = None
    distortion: np.ndarray | None = None
    pixel_size_um: float | None = None
    fov_mask_radius: float | None = None
    lens_model: str = "pinhole"
    source: str = field(default="Camera", compare=False, repr=False)

    def __post_init__(self) -> None:
        for key, value in (("image_width", self.width), ("image_height", self.height)):
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
                raise ValueError(f"{self.source}: {key}: expected a number, got {value!r}")
            if not float(value).is_integer():
                raise ValueError(f"{self.source}: {key} must be an integer, got {value!r}")
            if value <= 0:
                raise ValueError(f"{self.source}: {key} must be positive, got {value!r}")
        self.width, self.height = int(self.width), int(self.height)
        if self.camera_matrix is not None:
            self.camera_matrix = self._finite_camera_matrix(self.camera_matrix)
            try:  # a valid K is stored normalised; an invalid one fails in require_camera_matrix
                self.camera_matrix = self._checked_camera_matrix(self.camera_matrix)
            except ValueError:
                pass
            else:
                cx, cy = self.camera_matrix[:2, 2]
                if not (0 <= cx <= self.width and 0 <= cy <= self.height):
                    # accepted (a crop may move it off the frame), but rarely meant (review 54:
                    # cx 900 for a 200 px frame ran without a word)
                    warnings.warn(
                        f"{self.source}: camera_matrix: principal point ({cx:g}, {cy:g}) px "
                        f"lies outside the {self.width}x{self.height} frame: calibrated at "
                        "another resolution or crop, or cx and cy mistyped? (the frames are "
                        "used as they are)", stacklevel=3)
        if self.lens_model not in LENS_MODELS:
            raise ValueError(f"{self.source}: lens model {self.lens_model!r}: expected one of "
                             f"{', '.join(LENS_MODELS)}")
        if self.lens_model == "fisheye":
            d = (np.zeros(FISHEYE_COUNT) if self.distortion is None
                 else np.asarray(self.distortion, dtype=np.float64).reshape(-1))
            if d.size == 0:  # ROS's D: [] ("no distortion") has no fisheye meaning
                raise ValueError(
                    f"{self.source}: distortion_coefficients: empty, but the fisheye "
                    f"(equidistant) model takes {FISHEYE_COUNT} values k1 k2 k3 k4. An empty "
                    "list does not mean 'no distortion' here: with k1..k4 = 0 the equidistant "
                    "projection (r = f theta) still bends straight lines, unlike a pinhole "
                    "(r = f tan theta). Write [0, 0, 0, 0] for a pure equidistant lens, or "
                    "distortion_model plumb_bob for a pinhole without distortion")
            if d.size != FISHEYE_COUNT or not np.all(np.isfinite(d)):
                raise ValueError(
                    f"{self.source}: distortion_coefficients: the fisheye (equidistant) model "
                    f"takes {FISHEYE_COUNT} finite values k1 k2 k3 k4, got "
                    f"{_numbers(d) or 'none'}")
            self.distortion = d
        elif self.distortion is not None:
            d = np.asarray(self.distortion, dtype=np.float64).reshape(-1)
            if not np.all(np.isfinite(d)):
                raise ValueError(f"{self.source}: distortion_coefficients: contains NaN or inf")
            if d.size == 0 or not d.any():  # ROS D: [] or zeros: no distortion
                d = None
            elif d.size not in DISTORTION_COUNTS:
                raise ValueError(
                    f"{self.source}: distortion_coefficients: {d.size} values; OpenCV takes "
                    f"{', '.join(map(str, DISTORTION_COUNTS[:-1]))} or {DISTORTION_COUNTS[-1]}"
                )
            self.distortion = d
        for name in ("pixel_size_um", "fov_mask_radius"):
            value = getattr(self, name)
            if value is not None:
                try:
                    value = float(value)
                except (TypeError, ValueError):
                    raise ValueError(
                        f"{self.source}: {name}: expected a number, got {value!r}"
                    ) from None
                if not np.isfinite(value) or value <= 0:
                    raise ValueError(f"{self.source}: {name} must be positive, got {value!r}")
                setattr(self, name, value)
        if self.fov_mask_radius is not None:
            # The pixel centre nearest the image centre, tested as fov_mask() does.
            cx, cy = (self.width - 1) / 2.0, (self.height - 1) / 2.0
            nearest = (self.width // 2 - cx) ** 2 + (self.height // 2 - cy) ** 2
            if not nearest <= self.fov_mask_radius**2:
                raise ValueError(
                    f"{self.source}: fov_mask_radius {self.fov_mask_radius!r} px leaves the "
                    f"field-of-view mask empty (no pixel centre that close to the image centre; "
                    f"the nearest is {np.sqrt(nearest):.3g} px away)"
                )

    def _finite_camera_matrix(self, camera_matrix) -> np.ndarray:
        where = f"{self.source}: camera_matrix"
        try:
            K = np.array(camera_matrix, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: expected a 3x3 matrix of numbers") from None
        if K.shape != (3, 3):
            got = "x".join(map(str, K.shape)) if K.ndim == 2 else f"shape {K.shape}"
            raise ValueError(f"{where}: expected a 3x3 matrix, got {got}")
        if not np.all(np.isfinite(K)):
            raise ValueError(f"{where}: contains NaN or inf")
        return K

    def _checked_camera_matrix(self, K: np.ndarray) -> np.ndarray:
        """K (finite 3x3) checked as a pose method needs it, divided by K[2, 2]."""
        where = f"{self.source}: camera_matrix"
        c = K[2, 2]
        if not (c > 0 and np.abs(K[2, :2]).max() <= K_LAYOUT_TOLERANCE * c):
            transposed = c > 0 and np.abs(K[:2, 2]).max() <= K_LAYOUT_TOLERANCE * c
            hint = " (the matrix looks transposed)" if transposed else ""
            raise ValueError(
                f"{where}: last row must be 0 0 1 (K = [fx s cx; 0 fy cy; 0 0 1]; 0 0 c with "
                f"c > 0 is divided by c), got {_numbers(K[2])}{hint}"
            )
        K = K / c
        if abs(K[1, 0]) > K_LAYOUT_TOLERANCE * np.abs(K[1, 1:]).max():
            raise ValueError(
                f"{where}: element (1, 0) must be 0 (K = [fx s cx; 0 fy cy; 0 0 1]), "
                f"got {K[1, 0]:.10g}"
            )
        K[2], K[1, 0] = (0.0, 0.0, 1.0), 0.0
        fx, fy = float(K[0, 0]), float(K[1, 1])
        if fx <= 0 or fy <= 0:
            raise ValueError(f"{where}: focal lengths must be positive, got fx={fx!r}, fy={fy!r}")
        max_focal = MAX_FOCAL_IMAGE_SIZES * max(self.width, self.height)
        if max(fx, fy) > max_focal:
            raise ValueError(
                f"{where}: focal length fx={fx:g}, fy={fy:g} px is over {max_focal:g} px "
                f"({MAX_FOCAL_IMAGE_SIZES:g} image sizes, a field of view under 0.006 degrees)"
            )
        min_focal = self.min_focal_px()
        if min(fx, fy) < min_focal:
            angle = MAX_CORNER_ANGLE_DEG[self.lens_model]
            raise ValueError(
                f"{where}: focal length fx={fx:g}, fy={fy:g} px is under {min_focal:.3g} px, "
                f"which puts the {self.width}x{self.height} frame's corners over {angle:g} deg "
                f"from the optical axis (a field of view over {2 * angle:g} deg): beyond any "
                f"{self.lens_model} lens. A focal length in mm? camera.yaml wants pixels (fx = "
                "focal length / pixel pitch, both in mm)"
            )
        if max(fx / fy, fy / fx) > MAX_FOCAL_ASPECT:
            raise ValueError(
                f"{where}: fx={fx:g} and fy={fy:g} px differ by a factor "
                f"{max(fx, fy) / min(fx, fy):.3g} "
                f"(at most {MAX_FOCAL_ASPECT:g}: pixels that much taller than wide, or wider, "
                "are no camera's): one of them in other units (mm?) or mistyped; camera.yaml "
                "wants both in pixels"
            )
        # The C++ core's invertibility test (SlidingWindow): |det K| > 1e-12 |K|_F^3.
        if not abs(np.linalg.det(K)) > 1e-12 * np.linalg.norm(K) ** 3:
            raise ValueError(
                f"{where}: numerically singular (fx={fx:g}, fy={fy:g}, "
                f"cx={K[0, 2]:g}, cy={K[1, 2]:g})"
            )
        return K

    def min_focal_px(self) -> float:
        """The smallest focal length (px) _checked_camera_matrix accepts for this frame size and
        lens model (MAX_CORNER_ANGLE_DEG)."""
        corner = 0.5 * float(np.hypot(self.width, self.height))
        angle = np.deg2rad(MAX_CORNER_ANGLE_DEG[self.lens_model])
        return corner / (np.tan(angle) if self.lens_model == "pinhole" else angle)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.width, self.height

    def fov_mask(self) -> np.ndarray | None:
        """(H, W) uint8 mask, 255 inside the circular field of view; None without a radius."""
        if self.fov_mask_radius is None:
            return None
        y, x = np.ogrid[: self.height, : self.width]
        cx, cy = (self.width - 1) / 2.0, (self.height - 1) / 2.0
        inside = (x - cx) ** 2 + (y - cy) ** 2 <= self.fov_mask_radius**2
        return np.where(inside, np.uint8(255), np.uint8(0))

    def undistortion(self) -> LensUndistortion | None:
        """The lens undistortion of this camera, None without distortion coefficients; raises
        (naming the file) when the coefficients come without a valid camera matrix."""
        if self.distortion is None:
            return None
        if self.camera_matrix is None:
            raise ValueError(f"{self.source}: distortion_coefficients without a camera_matrix: "
                             "undistorting the frames needs the intrinsics")
        K = self._checked_camera_matrix(self.camera_matrix)
        return LensUndistortion(K, self.distortion, self.width, self.height,
                                self.fov_mask(), source=self.source, lens_model=self.lens_model)

    def require_camera_matrix(self, method: str) -> np.ndarray:
        """Return K = [fx s cx; 0 fy cy; 0 0 1], or raise naming the file, the problem and the
        method that needs it (layout, focal bound and invertibility are checked here, so that
        methods without K accept a placeholder)."""
        if self.camera_matrix is None:
            raise ValueError(
                f"{self.source}: no camera_matrix; method {method!r} needs the camera intrinsics"
            )
        try:
            return self._checked_camera_matrix(self._finite_camera_matrix(self.camera_matrix))
        except ValueError as e:
            raise ValueError(f"{e}; method {method!r} needs the camera intrinsics") from None

    def require_pixel_size(self, method: str) -> float:
        """Return pixel_size_um, or raise naming the file and the method that needs it."""
        if self.pixel_size_um is None:
            raise ValueError(
                f"{self.source}: no pixel_size_um; method {method!r} needs the "
                "pixel size to convert robot positions (µm) to pixels"
            )
        return self.pixel_size_um


# cv2.undistortPoints' default is 5 fixed-point iterations; a fetoscope's strong barrel lens
# (k1 ~ -0.3) needs more at the periphery. 40 iterations or 1e-10 (normalised units).
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)


def undistort_points(points, camera_matrix, distortion, lens_model: str = "pinhole",
                     P: np.ndarray | None = None, criteria=UNDISTORT_CRITERIA) -> np.ndarray:
    """(N, 2) raw pixels through the lens model -> (N, 2) undistorted: pixels of the camera
    matrix P (e.g. K itself), or normalised coordinates (x/z, y/z) when P is None (distortion
    None: a pinhole, as project_points)."""
    pts = np.asarray(points, np.float64).reshape(-1, 1, 2)
    if len(pts) == 0:
        return np.zeros((0, 2))
    K = np.asarray(camera_matrix, np.float64)
    d = np.zeros(4) if distortion is None else np.asarray(distortion, np.float64)
    if lens_model == "fisheye":
        out = cv2.fisheye.undistortPoints(pts, K, d.reshape(FISHEYE_COUNT, 1), R=np.eye(3),
                                          P=np.eye(3) if P is None else P, criteria=criteria)
    else:
        out = cv2.undistortPoints(pts, K, d, P=P, criteria=criteria)
    return out.reshape(-1, 2)


def project_points(points, camera_matrix, distortion, lens_model: str = "pinhole",
                   rvec=None, tvec=None) -> np.ndarray:
    """(N, 3) points (in the camera frame, or in a frame rvec / tvec take to it) -> (N, 2)
    pixels through the lens model (distortion None: a pinhole)."""
    obj = np.asarray(points, np.float64).reshape(-1, 1, 3)
    r = np.zeros(3) if rvec is None else np.asarray(rvec, np.float64).reshape(3)
    t = np.zeros(3) if tvec is None else np.asarray(tvec, np.float64).reshape(3)
    K = np.asarray(camera_matrix, np.float64)
    d = np.zeros(4) if distortion is None else np.asarray(distortion, np.float64)
    if lens_model == "fisheye":
        out = cv2.fisheye.projectPoints(obj, r.reshape(1, 1, 3), t.reshape(1, 1, 3), K,
                                        d.reshape(FISHEYE_COUNT, 1))[0]
    else:
        out = cv2.projectPoints(obj, r, t, K, d)[0]
    return out.reshape(-1, 2)


class LensFoldError(ValueError):
    """A lens model that folds over inside the frame (LensUndistortion): ``pixel`` (u, v) the
    first undistorted pixel found where it does, drawn from raw pixel ``raw`` (x, y)."""

    def __init__(self, message: str, *, pixel: tuple[int, int], raw: tuple[float, float]):
        super().__init__(message)
        self.pixel, self.raw = pixel, raw


class LensUndistortion:
    """Removes a camera's lens distortion (camera.yaml's distortion_coefficients, through
    OpenCV's standard model or, with lens_model "fisheye", its fisheye model) from keypoints
    and frames.

    The pose methods' homographies H = K (R - t pi^T) K^-1 hold between undistorted pixels, so
    features are detected in undistorted frames (`image`, within `mask`, their valid pixels)
    and the mosaic is composed from them; `points` undistorts raw pixel coordinates.
    Detecting in the raw frame and undistorting the keypoints instead was measured less
    accurate (SYN, 60 frames, k1 -0.3: lba-emt e_M 0.155 vs 0.090 px, ba-emt 0.204 vs 0.100;
    no distortion 0.059 / 0.061): a lens that compresses the periphery shifts blob detectors'
    keypoints systematically.
    Both use the raw frame's K and size (new camera matrix = K): homographies.csv keeps its
    pixel grid whether or not the lens is distorted. With a barrel lens (k1 < 0) the periphery
    that undistorts beyond the frame rectangle is cut from the mosaic; pixels with no source
    inside the raw frame (pincushion) or outside its field of view are outside `mask`.

    >>> lens = camera.undistortion()          # None when camera.yaml has no distortion
    >>> frame = lens.image(raw_frame)         # same size, same K
    >>> ideal = lens.points(raw_pixels)       # (N, 2) px
    """

    def __init__(self, camera_matrix: np.ndarray, distortion: np.ndarray, width: int,
                 height: int, fov_mask: np.ndarray | None = None, *,
                 source: str = "camera.yaml", lens_model: str = "pinhole") -> None:
        self.camera_matrix = np.asarray(camera_matrix, np.float64)
        self.distortion = np.asarray(distortion, np.float64).reshape(-1)
        self.width, self.height = int(width), int(height)
        self.lens_model = lens_model
        # For each undistorted pixel its source in the raw frame (fixed-point maps for remap).
        if lens_model == "fisheye":
            self._map1, self._map2 = cv2.fisheye.initUndistortRectifyMap(
                self.camera_matrix, self.distortion.reshape(FISHEYE_COUNT, 1), np.eye(3),
                self.camera_matrix, (self.width, self.height), cv2.CV_16SC2)
        else:
            self._map1, self._map2 = cv2.initUndistortRectifyMap(
                self.camera_matrix, self.distortion, None, self.camera_matrix,
                (self.width, self.height), cv2.CV_16SC2)
        self.mask = self.valid(fov_mask)
        if not self.mask.any():
            raise ValueError(f"{source}: distortion_coefficients leave no pixel of the "
                             "undistorted frame inside the raw frame")
        self._check_unfolded(source)

    def _check_unfolded(self, source: str) -> None:
        """Refuses coefficients whose model folds over where the undistorted frame is drawn from:
        the map undistorted pixel -> raw pixel (the lens's forward projection) must keep its
        orientation (Jacobian determinant > 0) over every pixel of `mask`; where it turns, two
        directions land on one raw pixel and the undistorted frame shows a mirrored double
        image. Only the pixels used are checked: a barrel lens whose raw corners lie beyond
        the fold, never sampled, passes. The projection needs no iteration (~0.05 s at
        1080p)."""
        size = (self.width, self.height)
        if self.lens_model == "fisheye":
            mx, my = cv2.fisheye.initUndistortRectifyMap(
                self.camera_matrix, self.distortion.reshape(FISHEYE_COUNT, 1), np.eye(3),
                self.camera_matrix, size, cv2.CV_32FC1)
        else:
            mx, my = cv2.initUndistortRectifyMap(self.camera_matrix, self.distortion, None,
                                                 self.camera_matrix, size, cv2.CV_32FC1)
        mx, my = mx.astype(np.float64), my.astype(np.float64)
        # forward differences at (v, u) towards (v, u + 1) and (v + 1, u), both in the mask
        det = ((mx[:-1, 1:] - mx[:-1, :-1]) * (my[1:, :-1] - my[:-1, :-1])
               - (mx[1:, :-1] - mx[:-1, :-1]) * (my[:-1, 1:] - my[:-1, :-1]))
        used = self.mask > 0
        used = used[:-1, :-1] & used[:-1, 1:] & used[1:, :-1]
        folded = used & ~(det > 0)
        if folded.any():
            v, u = np.argwhere(folded)[0]
            raise LensFoldError(
                f"{source}: distortion_coefficients: {self.distortion.tolist()} fold the "
                f"{self.lens_model} lens model over inside the {self.width}x{self.height} frame "
                f"(e.g. undistorted pixel ({u}, {v}) is drawn from raw pixel "
                f"({mx[v, u]:.0f}, {my[v, u]:.0f}), mirrored): the undistorted frames would "
                "show a double image; check the coefficients' order, sign and scale",
                pixel=(int(u), int(v)), raw=(float(mx[v, u]), float(my[v, u])))

    def valid(self, raw_mask: np.ndarray | None = None) -> np.ndarray:
        """(H, W) uint8, 255 where an undistorted pixel's whole bilinear support lies inside
        the raw frame and inside raw_mask (a field of view, non-zero = inside; None: all)."""
        if raw_mask is not None and np.shape(raw_mask) != (self.height, self.width):
            # remap samples any size, unchecked (a smaller mask, its corner of the frame; review)
            raise ValueError(f"mask shape {np.shape(raw_mask)} differs from the camera's "
                             f"undistortion maps ({self.height}, {self.width})")
        raw = (np.full((self.height, self.width), 255, np.uint8) if raw_mask is None
               else np.where(np.asarray(raw_mask) > 0, np.uint8(255), np.uint8(0)))
        valid = cv2.remap(raw, self._map1, self._map2, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return np.where(valid >= 255, np.uint8(255), np.uint8(0))

    def points(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) raw pixel coordinates -> undistorted pixel coordinates (same K)."""
        return undistort_points(points, self.camera_matrix, self.distortion, self.lens_model,
                                P=self.camera_matrix)

    def image(self, image: np.ndarray) -> np.ndarray:
        """The raw frame resampled on the undistorted pixel grid (bilinear; black outside)."""
        image = np.asarray(image)
        if image.shape[:2] != (self.height, self.width):
            raise ValueError(f"image is {image.shape[1]}x{image.shape[0]}, the camera's "
                             f"undistortion maps are {self.width}x{self.height}")
        return cv2.remap(image, self._map1, self._map2, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)


class UndistortedFrames(Sequence):
    """frames[k] undistorted on read (a view: nothing is kept in memory)."""

    def __init__(self, frames: Sequence, lens: LensUndistortion) -> None:
        self.frames, self.lens = frames, lens

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[j] for j in range(*k.indices(len(self)))]
        return self.lens.image(self.frames[k])


def read_camera_yaml(path: str | Path) -> Camera:
    """Read ``camera.yaml`` (keys: image_width, image_height, [camera_matrix,
    distortion_coefficients, pixel_size_um, fov_mask_radius]). Matrices may be
    ``!!opencv-matrix``, a plain list (9 numbers: row-major 3x3) or ROS camera_info's
    ``{rows, cols, data}``. The lens model: ``distortion_model`` (ROS camera_info: plumb_bob or
    rational_polynomial, OpenCV's standard model; equidistant or fisheye, OpenCV's fisheye
    model) or OpenCV's calibration sample's ``fisheye_model: 1``; default the standard model.
    A UTF-8 byte order mark (Windows editors write one) is skipped; a key given twice is refused.
    Tabs: between a line's tokens they are read as spaces (YAML allows them there; OpenCV does
    not); in indentation they are refused, naming the line (see _yaml_without_tabs).
    Every problem, including an OpenCV parse error, is a ValueError naming the file (and the
    key, or the line of a parse error)."""
    path = Path(path)
    require_file(path)
    data = path.read_bytes()
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise ValueError(f"{path}: UTF-16 text (a byte order mark FF FE / FE FF); save it as "
                         "UTF-8 (OpenCV FileStorage reads UTF-8 or ASCII)")
    bom = data.startswith(b"\xef\xbb\xbf")  # a UTF-8 BOM (Windows editors): OpenCV can't
    body = data[3 if bom else 0:]
    text = None  # the text as OpenCV is to parse it, when it is not the file's as it stands
    if bom:
        try:
            text = body.decode("utf-8")
        except UnicodeDecodeError as e:
            raise ValueError(f"{path}: starts with a UTF-8 byte order mark but is not UTF-8 "
                             f"(byte offset {e.start + 3})") from None
    if not body.strip():
        raise ValueError(f"{path}: empty file, expected OpenCV FileStorage YAML with {_KEYS}")
    yaml = _format_flag(body) == cv2.FILE_STORAGE_FORMAT_YAML
    if b"\t" in body and yaml:
        text = _yaml_without_tabs(text if text is not None else _decoded(body), path)
    if yaml and _FLUSH_ITEM.search(source := text if text is not None else _decoded(body)):
        indented = _yaml_lists_indented(source)
        if indented != source:
            text = indented
    fmt = _FORMAT_NAMES[_format_flag(body)]
    # parsed from memory, the file never opened by OpenCV: it crashed on a name that is not
    # UTF-8 (io._paths)
    try:
        fs = cv2.FileStorage(_decoded(body) if text is None else text,
                             cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY | _format_flag(body))
        opened = fs.isOpened() and fs.root().isMap()
    except (cv2.error, SystemError) as e:  # SystemError wraps a cv2.error from the constructor
        raise ValueError(f"{path}: cannot parse as OpenCV FileStorage {fmt}{_where(e)}") from None
    if not opened:
        raise ValueError(f"{path}: cannot parse as OpenCV FileStorage {fmt} with {_KEYS}")
    try:
        keys = list(fs.root().keys())
        if not set(keys) & (set(CAMERA_KEYS) | FOREIGN_CAMERA_KEYS):
            # OpenCV reads almost any text as a map ("this is : not : yaml [" is the key
            # "this is"): with none of camera.yaml's keys, it is not one
            shown = ", ".join(repr(k) for k in keys[:3]) + (", ..." if len(keys) > 3 else "")
            raise ValueError(
                f"{path}: cannot parse as OpenCV FileStorage {fmt} with {_KEYS}: none of "
                f"camera.yaml's keys in it (read {shown or 'nothing'} as "
                f"{'a key' if len(keys) == 1 else 'keys'})"
                + ("; expected e.g. '%YAML:1.0' then 'image_width: 640' and 'image_height: 480' "
                   "on lines of their own" if fmt == "YAML" else ""))
        unknown = [k for k in dict.fromkeys(keys)
                   if k not in CAMERA_KEYS and k not in FOREIGN_CAMERA_KEYS]
        camera = _read_camera(fs, path, unknown)
    except (cv2.error, SystemError) as e:
        raise ValueError(f"{path}: cannot read ({_reason(e)})") from None
    finally:
        fs.release()
    if unknown:  # after reading: a file refused for a missing key is refused, not warned about
        warnings.warn(_unknown_keys_message(path, unknown), stacklevel=2)
    return camera


def _close_key(key: str) -> str | None:
    """The camera.yaml key that ``key`` is likely a misspelling of, or None."""
    match = difflib.get_close_matches(key, CAMERA_KEYS, n=1, cutoff=0.7)
    return match[0] if match else None


def _unknown_keys_message(path: Path, unknown: list[str]) -> str:
    """Names camera.yaml's unknown keys (ignored), each with the known key it may misspell."""
    named = []
    for key in unknown:
        close = _close_key(key)
        named.append(f"{key!r}" + (f" (did you mean {close!r}?)" if close else ""))
    return (f"{path}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(named)} ignored; "
            f"camera.yaml's keys are {', '.join(CAMERA_KEYS)}")


def _yaml_without_tabs(text: str, path: Path) -> str:
    """YAML text with its tabs between tokens as spaces; ValueError naming the first line with a
    tab in its indentation.

    OpenCV's YAML reader refuses every tab outside a comment ("Tabs are prohibited in YAML!").
    YAML itself allows tabs as separation inside a line (``image_width:<TAB>400``, ``[1,<TAB>2]``,
    before a comment, trailing) but not in indentation, whose depth a tab would leave ambiguous.
    So: a tab before a line's first character that is not a comment is refused; a tab after it
    is a space. A line with a quote character before its tab keeps the tab (it may be inside a
    quoted string: OpenCV's error then names the line); lines holding only blanks or a comment
    lose their tabs."""
    lines = text.split("\n")
    indented = []
    for n, line in enumerate(lines):
        if "\t" not in line:
            continue
        content = line.lstrip(" \t")
        indent = line[: len(line) - len(content)]
        if "\t" in indent and content.strip() and not content.startswith("#"):
            indented.append(n + 1)
            continue
        quote = min((i for i in (line.find("'"), line.find('"')) if i >= 0), default=len(line))
        lines[n] = line[:quote].replace("\t", " ") + line[quote:]
    if indented:
        where = ("line " if len(indented) == 1 else "lines ") + ", ".join(
            map(str, indented[:3])) + (", ..." if len(indented) > 3 else "")
        raise ValueError(
            f"{path}: {where}: a tab character in the indentation; YAML does not allow tabs "
            "there (their width is ambiguous): indent with spaces")
    return "\n".join(lines)


_FLUSH_ITEM = re.compile(r"^[ ]*-( |\r?$)", re.MULTILINE)  # a block sequence's item line
_KEY_ONLY = re.compile(r"^([ ]*)[^\s#\-][^#]*:[ ]*(#.*)?\r?$")  # (CRLF files too)


def _yaml_lists_indented(text: str) -> str:
    """YAML text with block sequences written flush under their key (``key:`` then ``- 1`` at
    the key's indentation, as PyYAML's safe_dump and many emitters write them; valid YAML)
    indented by two spaces, which OpenCV's YAML reader needs ("Incorrect indentation" else;
    review). Every other line is left as it is."""
    lines = text.split("\n")
    for _ in range(len(lines)):  # one sequence per pass; nested ones in later passes
        for i, line in enumerate(lines):
            key = _KEY_ONLY.match(line)
            if key is None:
                continue
            k = len(key.group(1))
            j = next((j for j in range(i + 1, len(lines))
                      if lines[j].strip() and not lines[j].lstrip().startswith("#")), None)
            if j is None or _indent(lines[j]) != k or not _FLUSH_ITEM.match(lines[j]):
                continue
            while j < len(lines):
                content = lines[j].strip()
                if content and not content.startswith("#"):
                    if _indent(lines[j]) < k or (_indent(lines[j]) == k
                                                 and not _FLUSH_ITEM.match(lines[j])):
                        break
                lines[j] = "  " + lines[j] if content else lines[j]
                j += 1
            break
        else:
            break
    return "\n".join(lines)


def _decoded(body: bytes) -> str:
    """camera.yaml's bytes as text: UTF-8, else Latin-1 (e.g. Latin-1 comments: the keys and
    values are ASCII)."""
    try:
        return body.decode("utf-8")
    except UnicodeDecodeError:
        return body.decode("latin-1")


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip(" "))


def _format_flag(data: bytes) -> int:
    """The FileStorage format of a file's content, as OpenCV reads it whatever the file's name:
    ``<`` first XML, ``{`` first JSON, else YAML."""
    first = data.lstrip()[:1]
    if first == b"{":
        return cv2.FILE_STORAGE_FORMAT_JSON
    if first == b"<":
        return cv2.FILE_STORAGE_FORMAT_XML
    return cv2.FILE_STORAGE_FORMAT_YAML


_FORMAT_NAMES = {cv2.FILE_STORAGE_FORMAT_YAML: "YAML", cv2.FILE_STORAGE_FORMAT_JSON: "JSON",
                 cv2.FILE_STORAGE_FORMAT_XML: "XML"}


def _numbers(values) -> str:
    """Values as text with enough digits to show why a check failed (0.99999994 is not 1)."""
    return " ".join(f"{v:.10g}" for v in values)


def _cv_error(error: Exception) -> Exception:
    """The cv2.error behind a SystemError (a cv2.error raised in a constructor), else error."""
    context = error.__context__ if isinstance(error, SystemError) else None
    return context if isinstance(context, cv2.error) else error


def _reason(error: Exception) -> str:
    """OpenCV's own one-line reason, without its source location."""
    error = _cv_error(error)
    return str(getattr(error, "err", None) or error).strip()


# OpenCV's parse errors (cv::Error::StsParseError) carry "<file>(<line>): <message>" where other
# errors carry the function name (and the parsing function's name where others the message).
_PARSE_ERROR = re.compile(r"^.*\((\d+)\): (.+)$", re.DOTALL)
_OPENCV_MESSAGES = {  # OpenCV's wording -> what to do about it
    "Tabs are prohibited in YAML!": "a tab character, which OpenCV's YAML reader does not "
                                    "accept here: replace it with spaces",
}


def _where(error: Exception) -> str:
    """", line N: <problem>" for an OpenCV parse error, else " (<OpenCV's reason>)"."""
    error = _cv_error(error)
    match = _PARSE_ERROR.match(str(getattr(error, "func", "") or ""))
    if getattr(error, "code", None) == cv2.Error.StsParseError and match:
        message = match.group(2).strip()
        return f", line {match.group(1)}: {_OPENCV_MESSAGES.get(message, message)}"
    return f" ({_reason(error)})"


def _read_camera(fs: cv2.FileStorage, path: Path, unknown: Sequence[str] = ()) -> Camera:
    """The Camera in ``fs``; ``unknown`` (its keys camera.yaml does not know) name a likely
    misspelling when a required key is missing."""
    keys = list(fs.root().keys())
    repeated = sorted({k for k in keys if keys.count(k) > 1})
    if repeated:  # OpenCV would silently keep the first value of each
        raise ValueError(f"{path}: key {repeated[0]!r} appears {keys.count(repeated[0])} times; "
                         "keep one (OpenCV would read only the first)")

    def number(key: str, required: bool = False) -> float | None:
        node = fs.getNode(key)
        if node.empty() or node.isNone():
            if required:
                misspelt = [k for k in unknown if _close_key(k) == key]
                hint = f" ({misspelt[0]!r} is not a camera.yaml key: misspelt?)" if misspelt else ""
                raise ValueError(f"{path}: missing key {key!r}{hint}")
            return None
        if not (node.isInt() or node.isReal()):
            raise ValueError(f"{path}: {key}: expected a number")
        value = node.real()
        if np.isnan(value):
            raise ValueError(f"{path}: {key} is NaN")
        return value

    def numbers_of(key: str, node: cv2.FileNode) -> list[float]:
        values = []
        for i in range(node.size()):
            item = node.at(i)
            if not (item.isInt() or item.isReal()):
                if item.isSeq() or item.isMap():
                    raise ValueError(
                        f"{path}: {key}: element {i + 1} is a {'list' if item.isSeq() else 'map'}"
                        ", not a number: give the numbers in one list, or every row as a list of "
                        "numbers ([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])")
                text = item.string() if item.isString() else "not a number"
                raise ValueError(f"{path}: {key}: element {i + 1} is not a number ({text!r})")
            values.append(item.real())
        return values

    def matrix(key: str) -> np.ndarray | None:
        node = fs.getNode(key)
        if node.empty() or node.isNone():
            return None
        if node.isSeq() and node.size() and all(node.at(i).isSeq() for i in range(node.size())):
            # a list of rows (K.tolist(), [[k1, k2, p1, p2, k3]]): a matrix of their numbers
            rows = [numbers_of(f"{key} row {i + 1}", node.at(i)) for i in range(node.size())]
            if len({len(row) for row in rows}) != 1:
                raise ValueError(f"{path}: {key}: rows of different lengths "
                                 f"({', '.join(str(len(row)) for row in rows)} numbers)")
            return np.array(rows, dtype=np.float64)
        if node.isSeq():  # plain YAML list; 9 numbers are read as a row-major 3x3
            values = np.array(numbers_of(key, node), dtype=np.float64)
            return values.reshape(3, 3) if values.size == 9 else values[None, :]
        if not node.isMap():
            raise ValueError(f"{path}: {key}: expected an !!opencv-matrix or a list")
        # An !!opencv-matrix, or ROS camera_info's untagged {rows, cols, data} without dt: the
        # matrix is built from the numbers as written (dt, the storage type, is not needed).
        rows, cols, data = (node.getNode(k) for k in ("rows", "cols", "data"))
        if not (rows.isInt() and cols.isInt() and data.isSeq()):
            raise ValueError(
                f"{path}: {key}: a matrix map needs rows, cols and data: [...] "
                "(!!opencv-matrix or ROS camera_info)"
            )
        r, c = int(rows.real()), int(cols.real())
        values = numbers_of(key, data)
        if r < 0 or c < 0 or len(values) != r * c:
            raise ValueError(
                f"{path}: {key}: matrix data has {len(values)} values but rows x cols = {r} x {c}"
            )
        return np.array(values, dtype=np.float64).reshape(r, c)

    lens_model = "pinhole"
    model = fs.getNode("distortion_model")  # ROS camera_info; OpenCV's files have none
    if not (model.empty() or model.isNone()):
        name = model.string().strip() if model.isString() else None
        if name not in DISTORTION_MODELS:
            shown = repr(name) if name is not None else "not a string"
            raise ValueError(
                f"{path}: distortion_model: {shown} is not supported; expected one of "
                f"{', '.join(DISTORTION_MODELS)} (OpenCV's standard model: plumb_bob, "
                "rational_polynomial; its fisheye model: equidistant)"
            )
        lens_model = DISTORTION_MODELS[name]
    flag = number("fisheye_model")  # OpenCV's calibration sample: 1 for its fisheye model
    if flag is not None:
        if flag not in (0, 1):
            raise ValueError(f"{path}: fisheye_model: expected 0 or 1, got {flag:g}")
        if not model.empty() and not model.isNone() and (flag == 1) != (lens_model == "fisheye"):
            raise ValueError(f"{path}: fisheye_model {flag:g} contradicts distortion_model "
                             f"{model.string()!r}")
        lens_model = "fisheye" if flag == 1 else lens_model

    return Camera(
        width=number("image_width", required=True),
        height=number("image_height", required=True),
        camera_matrix=matrix("camera_matrix"),
        distortion=matrix("distortion_coefficients"),
        pixel_size_um=number("pixel_size_um"),
        fov_mask_radius=number("fov_mask_radius"),
        lens_model=lens_model,
        source=str(path),
    )


def write_camera_yaml(path: str | Path, camera: Camera) -> None:
    """Write ``camera`` as OpenCV FileStorage YAML (readable by cv2 and read_camera_yaml).
    OSError naming ``path`` when it cannot be written (OpenCV said only 'Emitter is not
    available'). The text is composed in memory (byte for byte what OpenCV writes to a file)
    and written by Python: OpenCV crashed on a name that is not UTF-8 (io._paths)."""
    fs = cv2.FileStorage("", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY
                         | cv2.FILE_STORAGE_FORMAT_YAML)
    try:
        fs.write("image_width", int(camera.width))
        fs.write("image_height", int(camera.height))
        if camera.camera_matrix is not None:
            fs.write("camera_matrix", np.asarray(camera.camera_matrix, dtype=np.float64))
        if camera.lens_model == "fisheye":  # ROS camera_info's name of OpenCV's fisheye
            fs.write("distortion_model", "equidistant")
        if camera.distortion is not None:
            fs.write(
                "distortion_coefficients",
                np.asarray(camera.distortion, dtype=np.float64).reshape(1, -1),
            )
        if camera.pixel_size_um is not None:
            fs.write("pixel_size_um", float(camera.pixel_size_um))
        if camera.fov_mask_radius is not None:
            fs.write("fov_mask_radius", float(camera.fov_mask_radius))
        text = fs.releaseAndGetString()
    finally:
        fs.release()
    try:
        Path(path).write_bytes(text.encode("utf-8"))
    except OSError as error:  # (a failed write or close carries no file name)
        raise OSError(error.errno, error.strerror or str(error), str(path)) from None
