"""Keypoints and descriptors inside the field of view (seed 000, Sec. 3.1 and 4.1: SIFT).

Fetoscopic frames are low in contrast and circular: features are detected only inside the
field-of-view mask (from camera.yaml's fov_mask_radius, or found from the black border), a few
pixels away from its edge so the border itself never makes a corner, optionally after CLAHE.
"""

from __future__ import annotations

import threading
import warnings
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class FeatureOptions:
    detector: str = "sift"  # "sift" (paper Sec. 4.1, VLFeat SIFT) or "orb" (faster)
    # Strongest keypoints kept per frame, inside the mask. 1000 ORB keypoints keep lba-emt at
    # ~0.2 px on SYN where 500 gave ~0.55 px (bench/bench_sequential.py); ORB pairs are matched
    # in the C++ core (pairs.py) so this stays real-time. SIFT finds fewer on low-contrast
    # tissue anyway.
    max_features: int = 1000
    # SIFT peak threshold. OpenCV's default is 0.04; the paper used VLFeat SIFT whose default
    # peak threshold is 0, which matters on low-contrast placenta: lower keeps more keypoints.
    sift_contrast_threshold: float = 0.04
    # A frame where SIFT finds fewer than sift_min_features keypoints at that threshold is
    # detected again at sift_contrast_threshold_low (if lower). The threshold is on absolute
    # DoG contrast: the simulator's frames (grey std ~14) give 80-320 keypoints, but the same
    # frames at 70 % contrast gave 1-2 and lba-emt registered no pair at all (run failed); at
    # 0.01 they give 1000 (the cap) and register again. Never triggered on the simulator's
    # default sequences (fewest keypoints 79), so their figures are unchanged. A featureless
    # frame (noise alone: structure_to_noise < SIFT_RETRY_MIN_STRUCTURE) is not detected again.
    sift_min_features: int = 50
    sift_contrast_threshold_low: float = 0.01
    # ORB's FAST corner threshold (grey levels): the lower, the more candidate corners ORB
    # scores to keep its max_features best; better keypoints, slower. Measured on this 2-core
    # Xeon, 1000 keypoints kept either way: detection 400x400 SYN 10.6 ms at 5 vs 6.2 ms at 10,
    # 1280x720 53 vs 26 ms; lba-emt e_M hand-held (300 frames, 2 seeds) 0.293 / 0.273 px at 5
    # vs 0.364 / 0.294 px at 10, SYN (600 frames, 4 seeds) 0.318 vs 0.288 px mean. A raised
    # threshold trades accuracy for speed (e.g. live HD video). A frame where fewer than 90 %
    # of max_features are found (low contrast) is detected again at orb_fast_threshold_low, if
    # that is lower. Both passes are then paid for, so a threshold too high for the tissue is
    # slower than the default, for the default's keypoints: 400x400 ms per frame SYN 13.3 at
    # 5, 7.8 at 10, 16.3 at 20 (244 of 1000 found: every frame detected again), hand-held 17.0
    # at 5, 20.7 at 20 (381 found; review).
    orb_fast_threshold: int = 5
    orb_fast_threshold_low: int = 5
    clahe: bool = False  # contrast-limited histogram equalisation for low-texture tissue
    clahe_clip_limit: float = 2.0
    clahe_tiles: int = 8
    mask_margin_px: int = 6  # keep keypoints this far inside the field of view
    border_threshold: int = 12  # grey level below which a border pixel counts as black
    # Detect on a copy whose longer side is at most this many pixels (area-averaged), keypoints
    # mapped back to full-resolution pixels. None: full resolution. For live HD video: lba-emt
    # with ORB on 1280x720 frames ran at 17.0 frames/s (features 30 ms per frame), with 512 at
    # 26.6 frames/s, e_M 0.47 -> 1.25 px (bench/bench_detect_scale.py); the keypoints are only as
    # precise as the shrunk image's pixels.
    max_image_side: int | None = None
    # No keypoints on specular highlights (saturated white spots fixed to the camera, and their
    # glow: specular_mask); a frame without such pixels is unaffected. Judged on the grey image
    # the keypoints are detected in (after undistortion): grey >= 235, which only near-white
    # pixels reach (a saturated red channel alone gives ~76); the compositor judges the colour
    # frame, every channel >= 235, so a warm near-white spot (B 200, G 255, R 255: grey 249) is
    # kept from keypoints but pasted.
    mask_specular: bool = True

    def validate(self, names: dict[str, str] | None = None) -> None:
        """ValueError for a bad field; `names` maps fields to what the messages call them
        (e.g. the CLI's flags)."""
        name = (names or {}).get
        if self.detector not in ("sift", "orb"):
            raise ValueError(f"{name('detector', 'detector')} must be 'sift' or 'orb', got "
                             f"{self.detector!r}")
        n = self.max_features
        if (isinstance(n, bool) or not isinstance(n, int | np.integer)
                or not 1 <= n <= MAX_FEATURES):
            raise ValueError(f"{name('max_features', 'max_features')} must be an integer in "
                             f"1..{MAX_FEATURES} (keypoints per frame), got {n!r}")
        for field_name in ("clahe", "mask_specular"):
            v = getattr(self, field_name)
            if not isinstance(v, bool | np.bool_):  # ('no' is truthy: CLAHE applied; review)
                raise ValueError(f"{name(field_name, field_name)} must be True or False, got "
                                 f"{v!r}")
        for field_name in ("orb_fast_threshold", "orb_fast_threshold_low"):
            t = getattr(self, field_name)
            if isinstance(t, bool) or not isinstance(t, int | np.integer) or not 1 <= t <= 255:
                raise ValueError(f"{name(field_name, field_name)} must be an integer in 1..255 "
                                 f"(grey levels), got {t!r}")
        for field_name in ("sift_contrast_threshold", "sift_contrast_threshold_low"):
            t = getattr(self, field_name)
            if isinstance(t, bool) or not isinstance(t, REAL) or not 0 <= t < 1:
                raise ValueError(f"{name(field_name, field_name)} must be a number in [0, 1) "
                                 f"(SIFT's contrastThreshold), got {t!r}")
        m = self.sift_min_features
        if isinstance(m, bool) or not isinstance(m, int | np.integer) or m < 0:
            raise ValueError(f"{name('sift_min_features', 'sift_min_features')} must be an "
                             f"integer >= 0, got {m!r}")
        for field_name, low, high, unit in (("clahe_tiles", 1, 1024, "tiles per side"),
                                            ("mask_margin_px", 0, 10_000, "pixels"),
                                            ("border_threshold", 0, 255, "grey levels")):
            v = getattr(self, field_name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or not low <= v <= high:
                raise ValueError(f"{name(field_name, field_name)} must be an integer in "
                                 f"{low}..{high} ({unit}), got {v!r}")
        c = self.clahe_clip_limit
        if isinstance(c, bool) or not isinstance(c, REAL) or not 0 <= c < np.inf:
            raise ValueError(f"{name('clahe_clip_limit', 'clahe_clip_limit')} must be a finite "
                             f"number >= 0 (CLAHE's clipLimit; 0: not clipped), got {c!r}")
        side = self.max_image_side
        if side is not None and (isinstance(side, bool) or not isinstance(side, int | np.integer)
                                 or side < 32):
            # None (full resolution) is the Python default; a caller naming a flag has no None
            none = "" if names and "max_image_side" in names else ", or None"
            raise ValueError(f"{name('max_image_side', 'max_image_side')} must be >= 32 "
                             f"(pixels), an integer{none}; got {side!r}")
        if side is not None and self.detector == "orb" and side < ORB_MIN_IMAGE_SIDE:
            raise ValueError(f"{name('max_image_side', 'max_image_side')} must be >= "
                             f"{ORB_MIN_IMAGE_SIDE} (pixels) with {name('detector', 'detector')} "
                             f"'orb', whose 31 px patch border leaves a smaller copy (almost) no "
                             f"keypoints; got {side!r}")


C_INT_MAX = 2**31 - 1  # OpenCV's detectors take nfeatures as a C int
# max_features' bound. OpenCV's ORB reserves memory for nfeatures keypoints per pyramid level
# on every frame, whatever it finds: on this machine (21 GB free) 2^28 worked, 1e9 failed with
# std::bad_alloc mid-run (a raw traceback), and 1e8 took 8.7 s for 30 SYN frames instead of 2 s;
# 1e6 costs 0.08 s on a 400x400 noise frame (29 282 keypoints, all it has) and 1e7 1.0 s. No
# frame gives a million keypoints worth keeping (SIFT and ORB find 1e3-1e5 on HD frames).
MAX_FEATURES = 10**6
REAL = int | float | np.integer | np.floating  # (np.float32 is not a float)
# ORB detects nothing within edgeThreshold = patchSize = 31 px of the border: on a SYN frame
# shrunk to a longer side of 64 px it found 0 keypoints, 96 px 31, 128 px 209 (review).
ORB_MIN_IMAGE_SIDE = 128
MIN_FRAME_SIDE = 2  # px: ORB's pyramid fails on a side of 1 (SIFT finds nothing there either)
# The low-contrast SIFT retry keeps the strongest 4 x sift_min_features (200) keypoints, what
# the simulator's frames give at full contrast (80-320), not max_features: a thousand on every
# small frame (200-300 px, often under 50) made brute-force matching ~5x slower (a test file of
# such runs: 39 s without the retry, 182 s with 1000 keypoints).
SIFT_RETRY_FEATURES_PER_MIN = 4

# ... and is skipped on a featureless frame, pure noise or a black frame with sensor noise,
# where it doubled detection (400x400: 42 -> 97 ms) only to find noise: 0-200 keypoints that
# match nothing. Told apart by structure_to_noise (the DoG energy at SIFT's first scales over
# what the frame's own noise alone gives there), measured on 400x400 and 720x576 frames:
# white noise at grey levels 14, 40, 128 and sigma 0.5 to 32 (grey or colour, with or without
# a circular field of view) gave 0.99-1.01; three simulated sequences (syn, 2 x hand-held)
# faded to 1.0 ... 0.1 of their contrast (sensor noise sigma 2 added after fading, or the
# noisy frame faded) gave 1.71-13.9, and 2.97 the least of the frames whose pair (k, k + 2)
# the retry registered (syn faded to 0.2 with noise, 720x576: 35 inliers, none without it);
# below that, 1.71-2.92, pairs registered with neither. 1.5 lies between: half again the
# noise's own level, half the least helped texture's.
# A limitation: texture as sharp as the pixel grid (unblurred white-noise texture) is noise
# to this test (~1.01 at any contrast) and is not detected again (a review: faded to 0.3
# it registered with the retry, 153 inliers, and fails without); blurred by sigma 0.5 px,
# which any lens and sensor do, it scores 2.1 and keeps the retry.
SIFT_RETRY_MIN_STRUCTURE = 1.5
# The band: SIFT's base scale and the next in its octave (sigma 1.6 * 2^(1/3)), px of the
# image it detects in; small kernels (4 sigma each side), so a field-of-view mask's margin
# (mask_margin_px) keeps the black border, which would count as structure, out of all but
# their tails (noise in a circular field of view: 1.00-1.01).
_DOG_SIGMAS = (1.6, 1.6 * 2 ** (1 / 3))
_DOG_KSIZES = tuple(2 * int(np.ceil(4 * sigma)) + 1 for sigma in _DOG_SIGMAS)


def _white_noise_dog_gain() -> float:
    """std of the DoG band of white noise of std 1: the 2-D kernel's L2 norm (0.0511)."""
    a, b = (cv2.getGaussianKernel(k, sigma, cv2.CV_64F).ravel()
            for k, sigma in zip(_DOG_KSIZES, _DOG_SIGMAS, strict=True))
    a = np.pad(a, (len(b) - len(a)) // 2)
    # sum((a a^T - b b^T)^2) = (a.a)^2 + (b.b)^2 - 2 (a.b)^2
    return float(np.sqrt((a @ a) ** 2 + (b @ b) ** 2 - 2 * (a @ b) ** 2))


_WHITE_NOISE_DOG_GAIN = _white_noise_dog_gain()
_SECOND_DIFFERENCE = np.array([1, -2, 1], np.float32)


def structure_to_noise(gray: np.ndarray, mask: np.ndarray | None = None) -> float:
    """How much more a uint8 grey frame varies at SIFT's first scales than its noise alone
    would: the std of its difference of Gaussians (sigma 1.6 and 1.6 * 2^(1/3)) over that of
    white noise with the frame's noise std, which Immerkaer's estimator gives (J. Immerkaer,
    "Fast noise variance estimation", CVIU 1996: the mean absolute response to the 3x3 second
    difference [1 -2 1] x [1 -2 1], x sqrt(pi / 2) / 6). Both inside mask (uint8, non-zero:
    in; None: the whole frame). ~1 for noise alone whatever its level, far more for texture,
    whose DoG response adds to the noise's (SIFT_RETRY_MIN_STRUCTURE); 0 for a frame with no
    variation or an empty mask, inf for one without noise but with structure. ~1.5 ms on a
    400x400 frame."""
    if mask is not None and cv2.countNonZero(mask) == 0:
        return 0.0
    g = np.asarray(gray, np.float32)
    dog = cv2.GaussianBlur(g, (_DOG_KSIZES[0],) * 2, _DOG_SIGMAS[0])
    dog -= cv2.GaussianBlur(g, (_DOG_KSIZES[1],) * 2, _DOG_SIGMAS[1])
    structure = float(cv2.meanStdDev(dog, mask=mask)[1][0, 0])
    second = cv2.sepFilter2D(g, cv2.CV_32F, _SECOND_DIFFERENCE, _SECOND_DIFFERENCE)
    noise = np.sqrt(np.pi / 2) / 6 * cv2.mean(np.abs(second), mask=mask)[0]
    if noise <= 0:
        return np.inf if structure > 0 else 0.0
    return structure / (noise * _WHITE_NOISE_DOG_GAIN)


@dataclass
class Features:
    """Keypoints (N, 2) float64 pixel coordinates and descriptors (N, D) of one frame."""

    frame_id: int
    points: np.ndarray
    descriptors: np.ndarray | None
    binary: bool  # Hamming descriptors (ORB) vs float (SIFT)

    def __len__(self) -> int:
        return len(self.points)


def fov_mask_from_image(image: np.ndarray, threshold: int = 12) -> np.ndarray | None:
    """Finds a black border around a (circular) field of view: the largest connected non-black
    region, filled. Returns None when the frame has no black border (or no content at all)."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    bright = (gray > threshold).astype(np.uint8)
    ring = np.concatenate([bright[0], bright[-1], bright[:, 0], bright[:, -1]])
    if ring.mean() > 0.5 or not bright.any():  # the image border is not (mostly) black
        return None
    n, labels, stats, _ = cv2.connectedComponentsWithStats(bright, connectivity=8)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    region = (labels == largest).astype(np.uint8)
    contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    hull = cv2.convexHull(np.vstack(contours))
    mask = np.zeros_like(region)
    cv2.fillConvexPoly(mask, hull, 255)
    return mask


# Specular highlights (in-vivo fetoscopy: the light fibres at the scope tip mirrored in the wet
# tissue). A highlight is fixed to the camera, not the scene: its keypoints match across frames
# at the same pixel, and pasted into a mosaic it leaves a white trail along the path. Its core is
# saturated white (every channel near 255, which tissue under the scope's light is not: red
# saturates alone); the glow around the core falls off over about the core's own radius.
SPECULAR_THRESHOLD = 235  # grey level every channel of a core pixel reaches
SPECULAR_GROWTH = 1.0  # the masked glow: this many core radii beyond the core ...
SPECULAR_MARGIN_PX = 3  # ... plus this many pixels
# On a grey (monochrome) or over-exposed frame, bright tissue reaches the threshold too and is
# masked as highlights (review: a hand-held pair at gain 1.7, 8 % of pixels >= 235, lost 47 % of
# its field of view, SIFT keypoints 947 -> 347, inliers 489 -> 161). Not told apart from real
# highlights; FeatureExtractor warns when the mask takes more than this fraction of the field
# of view. The simulator's highlights took 2.2-2.9 % (3 lights, sigma 5 px), 3.1-3.5 % (6),
# 7.9-9.2 % (3, sigma 12), 11.9-12.8 % (8, sigma 12); that grey pair at gain 1.5 4-7 %, 1.6
# 22-28 %, 1.7 49-58 %.
SPECULAR_WARN_FRACTION = 0.2


def specular_mask(image: np.ndarray, *, threshold: int = SPECULAR_THRESHOLD,
                  growth: float = SPECULAR_GROWTH, margin_px: int = SPECULAR_MARGIN_PX,
                  gray: np.ndarray | None = None) -> np.ndarray | None:
    """(H, W) uint8, 255 on the specular highlights of a uint8 BGR or gray frame and around
    them, or None when it has none (no pixel with every channel >= threshold).

    Each highlight core (a connected set of such pixels, equivalent radius r = sqrt(area / pi))
    is grown by ``growth * r + margin_px`` pixels to cover its glow: on the simulator's
    highlights (``FetoscopyOptions.specular_lights``) the default covers the pixels the light
    brightens by 20 grey levels or more (tests/test_specular.py). gray: the frame's grey image
    if the caller has it (a quick test: no grey pixel reaches the threshold, no highlight).
    Costs ~0.05 ms on a 400x400 frame without highlights."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise ValueError(f"specular_mask: expected a uint8 (H, W) or (H, W, C) image, got "
                         f"{image.dtype} {image.shape}")
    # A core pixel's grey level (a mean of its channels) reaches the threshold too.
    if (image if gray is None else gray).max() < threshold:
        return None
    if image.ndim == 3 and image.shape[2] > 1:
        channels = image.shape[2]
        core = cv2.inRange(image, (threshold,) * channels, (255,) * channels)
    else:
        core = cv2.threshold(image.reshape(image.shape[:2]), threshold - 1, 255,
                             cv2.THRESH_BINARY)[1]
    contours, _ = cv2.findContours(core, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return None
    mask = core.copy()
    for contour in contours:
        # the core filled, and its outline drawn grow px thick on both sides: a dilation by a
        # disc of radius grow (thick lines have round joins)
        area = max(cv2.contourArea(contour), float(len(contour)), 1.0)
        grow = int(round(margin_px + growth * np.sqrt(area / np.pi)))
        cv2.drawContours(mask, [contour], -1, 255, thickness=cv2.FILLED)
        if grow > 0:
            cv2.drawContours(mask, [contour], -1, 255, thickness=2 * grow + 1)
    return mask


def _binary(mask: np.ndarray) -> np.ndarray:
    return np.where(np.asarray(mask) > 0, 255, 0).astype(np.uint8)


class FeatureExtractor:
    """Detects keypoints in frames of one camera; reusable and thread-safe per call."""

    def __init__(self, options: FeatureOptions | None = None, mask: np.ndarray | None = None,
                 undistortion=None):
        """mask: the raw frames' field of view (uint8 or bool), None: found per frame from a
        black border. undistortion: the camera's LensUndistortion (Camera.undistortion()):
        keypoints are detected in the undistorted frame (within its valid pixels), so they are
        in undistorted pixels, where the homographies of a planar scene hold; None: raw."""
        self.options = options or FeatureOptions()
        self.options.validate()
        self.undistortion = undistortion
        # OpenCV takes any non-zero mask value as inside; 255 is what the shrink below expects
        raw = None if mask is None else _binary(mask)
        if raw is not None and undistortion is not None:
            # (remap samples a mask of any size, unchecked: a smaller one kept keypoints to its
            # corner of the frame; review)
            if raw.shape != (undistortion.height, undistortion.width):
                raise ValueError(f"mask shape {raw.shape} differs from the camera's frames "
                                 f"({undistortion.height}, {undistortion.width})")
            raw = undistortion.valid(raw)  # the field of view on the undistorted frame
        self._mask = None if raw is None else self._shrink(raw)
        # without a fixed mask, frames with no black border are masked by the lens alone
        self._lens_mask = (self._shrink(undistortion.valid())
                           if undistortion is not None and raw is None else None)
        self._small_masks: dict[tuple, np.ndarray] = {}  # fixed mask at detection sizes
        self._specular_warned = False  # (_check_specular_area)
        self._specular_lock = threading.Lock()

    def _shrink(self, mask: np.ndarray) -> np.ndarray:
        m = self.options.mask_margin_px
        if m <= 0:
            return mask
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * m + 1, 2 * m + 1))
        return cv2.erode(mask, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)

    def _detector(self, fast_threshold: int | None = None, contrast_threshold: float | None = None,
                  max_features: int | None = None):
        o = self.options
        if o.detector == "sift":
            # Uncapped, the strongest inside the mask kept after (_CappedSift). OpenCV's SIFT
            # keeps its nfeatures strongest over the whole image and only then drops those
            # outside the mask, so keypoints on the black rim, the margin or a highlight spent
            # the cap: 1280x720 frames with 3 specular lights kept 892 / 919 of 1000 (477
            # inliers; 1000 / 1000 and 532 capped after the mask), fov_mask_radius 200 on them
            # 204 / 217 (103 inliers; 340 / 330 and 169; review). ORB masks first.
            return _CappedSift(cv2.SIFT_create(nfeatures=0, contrastThreshold=float(
                o.sift_contrast_threshold if contrast_threshold is None
                else contrast_threshold)), o.max_features if max_features is None
                else max_features)
        return cv2.ORB_create(nfeatures=o.max_features,
                              fastThreshold=fast_threshold or o.orb_fast_threshold)

    def extract(self, image: np.ndarray, frame_id: int = 0) -> Features:
        image = np.asarray(image)  # (a list: a bare AttributeError on .ndim; review)
        # (H, W, 1) / (H, W, 2) failed in cvtColor, a side of 1 px in ORB's pyramid (review)
        if (image.ndim not in (2, 3) or image.dtype != np.uint8
                or (image.ndim == 3 and image.shape[2] not in (1, 3, 4))
                or min(image.shape[:2]) < MIN_FRAME_SIDE):
            raise ValueError(f"frame {frame_id}: expected a uint8 (H, W), (H, W, 1), (H, W, 3) "
                             f"or (H, W, 4) image of at least {MIN_FRAME_SIDE}x{MIN_FRAME_SIDE} "
                             f"pixels, got {image.dtype} {image.shape}")
        if image.ndim == 2 or image.shape[2] == 1:
            gray = image.reshape(image.shape[:2])
        else:
            gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if image.shape[2] == 3
                                else cv2.COLOR_BGRA2GRAY)
        lens = self.undistortion
        if lens is not None and gray.shape != (lens.height, lens.width):
            raise ValueError(f"frame {frame_id}: image is {gray.shape[1]}x{gray.shape[0]}, the "
                             f"camera's is {lens.width}x{lens.height}")
        mask = self._mask
        if mask is None:  # the raw frame's black border, if it has one
            found = fov_mask_from_image(gray, self.options.border_threshold)
            if lens is None:
                mask = None if found is None else self._shrink(found)
            else:
                mask = self._lens_mask if found is None else self._shrink(lens.valid(found))
        if lens is not None:
            gray = lens.image(gray)  # detected here, the keypoints are in undistorted pixels
        if mask is not None and mask.shape != gray.shape:
            raise ValueError(f"frame {frame_id}: mask shape {mask.shape} differs from the image "
                             f"{gray.shape}")
        if self.options.mask_specular:
            highlights = specular_mask(gray)
            if highlights is not None:
                self._check_specular_area(highlights, mask, frame_id)
                mask = cv2.bitwise_not(highlights) if mask is None else cv2.bitwise_and(
                    mask, cv2.bitwise_not(highlights))
        binary = self.options.detector == "orb"
        if gray.max() <= self.options.border_threshold:  # no visual content (e.g. black frame)
            return Features(frame_id, np.zeros((0, 2)), None, binary)
        full_size = gray.shape[1], gray.shape[0]
        size = self._detection_size(full_size)
        if size != full_size:
            gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
            mask = None if mask is None else self._small_mask(mask, size, mask is self._mask)
        if self.options.clahe:
            clahe = cv2.createCLAHE(float(self.options.clahe_clip_limit),
                                    (self.options.clahe_tiles, self.options.clahe_tiles))
            gray = clahe.apply(gray)
        keypoints, descriptors = self._detect(self._detector(), gray, mask, frame_id)
        o = self.options
        if (binary and len(keypoints) < 0.9 * o.max_features
                and o.orb_fast_threshold_low < o.orb_fast_threshold):
            keypoints, descriptors = self._detect(self._detector(o.orb_fast_threshold_low),
                                                  gray, mask, frame_id)  # more candidate corners
        # Not when max_features itself is below sift_min_features and was reached: the cap, not
        # low contrast, kept the count down, and the retry (capped too) cannot give more; it ran
        # on every textured frame (400x400: 126 ms per frame at max_features 30, 74 at 50).
        if (not binary and len(keypoints) < min(o.sift_min_features, o.max_features)
                and o.sift_contrast_threshold_low < o.sift_contrast_threshold
                and structure_to_noise(gray, mask) >= SIFT_RETRY_MIN_STRUCTURE):
            keypoints, descriptors = self._detect(self._detector(
                contrast_threshold=o.sift_contrast_threshold_low,
                max_features=min(o.max_features, SIFT_RETRY_FEATURES_PER_MIN * max(
                    o.sift_min_features, 1))), gray, mask, frame_id)
        points = np.array([kp.pt for kp in keypoints], np.float64).reshape(-1, 2)
        if size != full_size:  # pixel centres: x_full + 0.5 = (x_small + 0.5) * W / w
            scale = np.array(full_size, np.float64) / np.array(size, np.float64)
            points = (points + 0.5) * scale - 0.5
        return Features(frame_id, points, descriptors, binary)

    def _check_specular_area(self, highlights: np.ndarray, mask: np.ndarray | None,
                             frame_id: int) -> None:
        """Warns (once per extractor, i.e. per run) when the specular mask takes more than
        SPECULAR_WARN_FRACTION of the field of view: bright tissue taken for highlights."""
        if self._specular_warned:
            return
        inside = highlights if mask is None else cv2.bitwise_and(highlights, mask)
        field = highlights.size if mask is None else cv2.countNonZero(mask)
        fraction = cv2.countNonZero(inside) / max(field, 1)
        if fraction <= SPECULAR_WARN_FRACTION or fraction >= 0.95:
            return  # (>= 95 %: a saturated or blank-white frame, textureless either way)
        with self._specular_lock:
            if self._specular_warned:
                return
            self._specular_warned = True
        warnings.warn(
            f"frame {frame_id}: the specular-highlight mask (pixels whose every channel reaches "
            f"grey {SPECULAR_THRESHOLD}, and their glow) keeps keypoints off {fraction:.0%} of "
            f"the field of view, more than highlights cover (the simulator's: 2-13 %): bright "
            f"tissue on a grey or over-exposed frame? Fewer keypoints there; mask_specular "
            f"(--keep-specular) turns the mask off (warned once)", stacklevel=3)

    def _detect(self, detector, gray: np.ndarray, mask: np.ndarray | None, frame_id: int):
        """detector.detectAndCompute, its cv2.error (e.g. std::bad_alloc: out of memory) a
        ValueError naming the frame and the options that set the memory it needs (a raw
        traceback with no "fusedmosaic: error:" line before; review)."""
        try:
            return detector.detectAndCompute(gray, mask)
        except cv2.error as e:
            o = self.options
            raise ValueError(
                f"frame {frame_id}: {o.detector.upper()} detection failed on the "
                f"{gray.shape[1]}x{gray.shape[0]} image ({str(e).strip()}) with max_features "
                f"(--max-features) {o.max_features}; fewer keypoints, or a smaller copy to "
                f"detect in (max_image_side, --detect-max-side), need less memory") from e

    def _detection_size(self, full_size: tuple[int, int]) -> tuple[int, int]:
        side = self.options.max_image_side
        if side is None or max(full_size) <= side:
            return full_size
        s = side / max(full_size)
        return (max(MIN_FRAME_SIDE, round(full_size[0] * s)),
                max(MIN_FRAME_SIDE, round(full_size[1] * s)))

    def _small_mask(self, mask: np.ndarray, size: tuple[int, int], fixed: bool) -> np.ndarray:
        """The mask at detection size: only pixels entirely inside the full-size mask."""
        if fixed and size in self._small_masks:
            return self._small_masks[size]
        small = cv2.resize(mask, size, interpolation=cv2.INTER_AREA)
        small = np.where(small >= 255, 255, 0).astype(np.uint8)
        if fixed:
            self._small_masks[size] = small
        return small


class _CappedSift:
    """An uncapped SIFT detector whose detectAndCompute keeps the n strongest keypoints inside
    the mask by response, with their descriptors, in their order; ties at the n-th response all
    kept, as OpenCV's KeyPointsFilter::retainBest (SIFT's own cap, which it applies before the
    mask). All described, then selected: on this 2-core Xeon, SIFT per frame (median of 21, one
    thread) 400x400 SYN 56.7 ms capped by OpenCV, 57.3 ms so (under the cap: the same
    keypoints); 1280x720 with specular lights 323 -> 341 ms (+5 %, ~900 -> 1000 keypoints
    described); detecting uncapped and describing only the kept ones took 1.6x (SIFT's compute
    builds the pyramid again)."""

    def __init__(self, sift, n: int):
        self.sift, self.n = sift, n

    def detectAndCompute(self, gray: np.ndarray, mask: np.ndarray | None):  # noqa: N802
        keypoints, descriptors = self.sift.detectAndCompute(gray, mask)
        n = self.n
        if len(keypoints) <= n:
            return keypoints, descriptors
        response = np.array([k.response for k in keypoints], np.float32)
        keep = np.flatnonzero(response >= np.partition(response, len(response) - n)[-n])
        return [keypoints[i] for i in keep], descriptors[keep]


def extract_features(frames, frame_indices, camera_mask: np.ndarray | None,
                     options: FeatureOptions | None = None, progress: bool = False,
                     num_threads: int = 2, undistortion=None) -> dict[int, Features]:
    """Features of frames[k] for k in frame_indices, keyed by k; threads share the work.
    undistortion: see FeatureExtractor."""
    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    extractor = FeatureExtractor(options, camera_mask, undistortion)
    indices = list(frame_indices)

    def one(k):
        return extractor.extract(frames[k], int(k))

    out: dict[int, Features] = {}
    with ThreadPoolExecutor(max(1, num_threads)) as pool, tqdm(
            total=len(indices), desc="features", disable=not progress, leave=False) as bar:
        for f in pool.map(one, indices):
            out[f.frame_id] = f
            bar.update(1)
    return out
