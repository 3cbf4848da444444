"""Registration review (session 44, review A): the degeneracy test's area scale, mask / frame /
option checks, and emt_guided_pairs' vectorised pre-filter."""

import re

import cv2
import numpy as np
import pytest

from fusedmosaic.io.calibration import Camera
from fusedmosaic.registration.features import FeatureExtractor, FeatureOptions
from fusedmosaic.registration.pair_selection import (
    emt_guided_pairs,
    footprint_polygons,
    kept_pairs,
    overlap_fraction,
)
from fusedmosaic.registration.pairs import (
    MatchOptions,
    degeneracy,
)

W = H = 400


@pytest.fixture(scope="module")
def texture():
    """A 900x1200 blurred-noise texture."""
    rng = np.random.default_rng(1)
    big = cv2.GaussianBlur(rng.normal(128, 40, (900, 1200)).astype(np.float32), (0, 0), 2)
    return cv2.normalize(big, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def _rotation_y(deg: float) -> np.ndarray:
    """The homography of a camera turned about its y axis, principal point at the frame's
    centre (f = 300 px): frame areas change alike for either sign."""
    K = np.array([[300.0, 0, W / 2], [0, 300.0, H / 2], [0, 0, 1]])
    a = np.deg2rad(deg)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    G = K @ R @ np.linalg.inv(K)
    return G / G[2, 2]


# ---- 1: the area scale is the frame's, whichever way the camera turns -------------------------

@pytest.mark.parametrize("deg", [30.0, -30.0, 35.0, -35.0])
def test_turned_camera_accepted_for_either_sign(deg):
    """det of the affine part (the scale at pixel (0, 0)) was 0.37 at +30 deg and 4.2 at -30:
    the -30 deg pair was rejected. The frame's area changes by ~2.1 either way."""
    assert degeneracy(_rotation_y(deg), W, H, 4.0) is None


@pytest.mark.parametrize("deg, scale", [(40.0, "4.71"), (-40.0, "4.71"), (45.0, "9.16"),
                                        (-45.0, "9.16")])
def test_turned_camera_past_the_limit_rejected_for_either_sign(deg, scale):
    message = ("degenerate homography (area scale " + scale + ": the warped frame's area over "
               "the frame's, outside (1/4, 4) for max_scale_change 4)")
    assert degeneracy(_rotation_y(deg), W, H, 4.0) == message


def test_zoom_past_the_limit_with_perspective_rejected():
    """A zoom to 0.45 (area 0.2) about the centre with a perspective term had det 0.69 at
    pixel (0, 0) and passed; its frame area is 0.245 of the frame's."""
    C = np.array([[1, 0, W / 2], [0, 1, H / 2], [0, 0, 1.0]])
    G = C @ np.array([[0.45, 0, 0], [0, 0.45, 0], [0.0015, 0, 1]]) @ np.linalg.inv(C)
    reason = degeneracy(G / G[2, 2], W, H, 4.0)
    assert reason is not None and reason.startswith("degenerate homography (area scale 0.245:")
    C2 = C @ np.diag([0.55, 0.55, 1.0]) @ np.linalg.inv(C)  # area 0.30: within (1/4, 4)
    assert degeneracy(C2, W, H, 4.0) is None


def test_mirrored_frame_rejected():
    mirror = np.array([[-1.0, 0, W], [0, 1, 0], [0, 0, 1]])  # convex, same area, mirrored
    assert degeneracy(mirror, W, H, 4.0) == (
        "degenerate homography (mirrored: the warped frame's signed area is -1 x the frame's)")
    assert degeneracy(np.diag([1.9, 1.9, 1.0]), W, H, 4.0) is None  # area x 3.61
    assert degeneracy(np.diag([2.1, 2.1, 1.0]), W, H, 4.0).startswith(
        "degenerate homography (area scale 4.41:")


# ---- 4: a mask of the wrong size with a lens -------------------------------------------------

def test_wrong_size_mask_refused_with_a_lens():
    K = np.array([[480.0, 0, 199.5], [0, 480, 199.5], [0, 0, 1]])
    lens = Camera(width=400, height=400, camera_matrix=K,
                  distortion=np.array([-0.3, 0.1, 0, 0, 0])).undistortion()
    for shape in ((200, 200), (400, 300), (400, 400, 3)):
        with pytest.raises(ValueError, match=re.escape(
                f"mask shape {shape} differs from the camera's frames (400, 400)")):
            FeatureExtractor(FeatureOptions(), mask=np.full(shape, 255, np.uint8),
                             undistortion=lens)
        with pytest.raises(ValueError, match=re.escape(
                f"mask shape {shape} differs from the camera's undistortion maps (400, 400)")):
            lens.valid(np.full(shape, 255, np.uint8))
    FeatureExtractor(FeatureOptions(), mask=np.full((400, 400), 255, np.uint8),
                     undistortion=lens)


# ---- 5: emt_guided_pairs' pre-filter -----------------------------------------------------------

def _reference_emt_guided_pairs(predicted, width, height, *, min_overlap=0.3, max_per_frame=20,
                                fov_radius=None, temporal_window=2, min_separation=4):
    """The loop before the review: every (l, m) in Python, overlap_fraction per pair (the
    choice among the overlapping frames, kept_pairs, is shared: the pre-filter is under test)."""
    polys = footprint_polygons(predicted, width, height, fov_radius)
    n = len(polys)
    areas = np.array([cv2.contourArea(p) if p is not None else 0.0 for p in polys])
    centres = np.array([p.mean(axis=0) if p is not None else (np.nan, np.nan) for p in polys])
    radii = np.array([np.linalg.norm(p - p.mean(axis=0), axis=1).max() if p is not None else 0
                      for p in polys])
    pairs = []
    for l in range(n):
        if polys[l] is None:
            pairs += [(l, m) for m in (l - 1,) if m >= 0]
            continue
        candidates = []
        for m in range(l):
            if polys[m] is None:
                if m == l - 1:
                    pairs.append((l, m))
                continue
            if np.linalg.norm(centres[l] - centres[m]) > radii[l] + radii[m]:
                continue
            frac = overlap_fraction(polys[l], polys[m], areas[l], areas[m])
            if frac >= min_overlap:
                candidates.append((frac, m))
        pairs += kept_pairs(l, candidates, temporal_window, max_per_frame, min_separation)
    return pairs


@pytest.mark.parametrize("seed", range(12))
def test_emt_guided_pairs_equal_the_per_pair_loop(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 120))
    G = np.tile(np.eye(3), (n, 1, 1))
    G[:, :2, 2] = np.cumsum(rng.normal(0, 40, (n, 2)), axis=0)  # a random walk that revisits
    G[:, 0, 0] = G[:, 1, 1] = rng.uniform(0.7, 1.3, n)
    G[:, 2, :2] = rng.normal(0, 2e-4, (n, 2))
    G[rng.random(n) < 0.1] = np.nan  # unplaced frames
    kw = dict(min_overlap=float(rng.choice([0.0, 0.1, 0.3, 0.6])),
              max_per_frame=[None, 0, 3, 20][seed % 4], fov_radius=[None, 150.0][seed % 2],
              temporal_window=int(rng.integers(0, 4)), min_separation=int(rng.integers(1, 6)))
    expected = _reference_emt_guided_pairs(G, 320, 240, **kw)
    assert len(expected) > n // 2
    assert emt_guided_pairs(G, 320, 240, **kw) == expected


# ---- 6, 7, 9: options --------------------------------------------------------------------------

def test_ransac_max_iters_bounded_by_a_c_int():
    with pytest.raises(ValueError, match=re.escape(
            "ransac_max_iters: expected an integer in 1..2147483647 (OpenCV's int), got "
            "2147483648")):
        MatchOptions(ransac_max_iters=2**31)
    with pytest.raises(ValueError, match=re.escape(
            "ransac_max_iters: expected an integer in 1..2147483647 (OpenCV's int), got 0")):
        MatchOptions(ransac_max_iters=0)
    MatchOptions(ransac_max_iters=2**31 - 1)
    with pytest.raises(ValueError, match=re.escape(
            "min_inliers: expected an integer >= 4, got 3")):  # (unbounded fields unchanged)
        MatchOptions(min_inliers=3)


def test_numpy_float32_feature_options_accepted(texture):
    frame = texture[:300, :300].copy()
    as_float = FeatureExtractor(FeatureOptions(sift_contrast_threshold=0.02, clahe=True,
                                               clahe_clip_limit=2.0)).extract(frame)
    as_f32 = FeatureExtractor(FeatureOptions(
        sift_contrast_threshold=np.float32(0.02), clahe=True,
        clahe_clip_limit=np.float32(2.0))).extract(frame)
    assert len(as_f32) > 100
    np.testing.assert_allclose(as_f32.points, as_float.points, atol=1e-3)
    with pytest.raises(ValueError, match=re.escape(
            "sift_contrast_threshold must be a number in [0, 1) (SIFT's contrastThreshold), "
            "got np.float32(nan)")):
        FeatureExtractor(FeatureOptions(sift_contrast_threshold=np.float32("nan")))
    with pytest.raises(ValueError, match=re.escape(
            "clahe_clip_limit must be a finite number >= 0 (CLAHE's clipLimit; 0: not "
            "clipped), got np.float32(-1.0)")):
        FeatureExtractor(FeatureOptions(clahe_clip_limit=np.float32(-1.0)))


def test_orb_max_image_side_below_its_patch_refused(texture):
    """ORB found no keypoint on a copy of 64 px (31 px border), and every pair failed."""
    with pytest.raises(ValueError, match=re.escape(
            "max_image_side must be >= 128 (pixels) with detector 'orb', whose 31 px patch "
            "border leaves a smaller copy (almost) no keypoints; got 127")):
        FeatureExtractor(FeatureOptions(detector="orb", max_image_side=127))
    with pytest.raises(ValueError, match=re.escape(
            "--detect-max-side must be >= 128 (pixels) with --detector 'orb'")):
        FeatureOptions(detector="orb", max_image_side=64).validate(
            names={"max_image_side": "--detect-max-side", "detector": "--detector"})
    assert len(FeatureExtractor(FeatureOptions(detector="orb", max_image_side=128))
               .extract(texture[:400, :400])) > 100
    FeatureExtractor(FeatureOptions(detector="sift", max_image_side=64))  # SIFT: from 32


# ---- 8: frame shapes ---------------------------------------------------------------------------

@pytest.mark.parametrize("detector", ["sift", "orb"])
def test_single_and_four_channel_frames(texture, detector):
    gray = texture[:300, :300].copy()
    bgr = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    ext = FeatureExtractor(FeatureOptions(detector=detector))
    ref = ext.extract(gray)
    assert len(ref) > 100
    np.testing.assert_array_equal(ext.extract(gray[:, :, None]).points, ref.points)
    np.testing.assert_array_equal(ext.extract(np.dstack([bgr, gray])).points,
                                  ext.extract(bgr).points)


@pytest.mark.parametrize("detector", ["sift", "orb"])
@pytest.mark.parametrize("shape", [(300, 300, 2), (300, 300, 5), (1, 400), (400, 1),
                                   (0, 0), (1, 1, 3)])
def test_bad_frame_shapes_refused(detector, shape):
    ext = FeatureExtractor(FeatureOptions(detector=detector))
    with pytest.raises(ValueError, match=re.escape(
            f"frame 3: expected a uint8 (H, W), (H, W, 1), (H, W, 3) or (H, W, 4) image of at "
            f"least 2x2 pixels, got uint8 {shape}")):
        ext.extract(np.full(shape, 128, np.uint8), 3)


def test_thin_frames_and_thin_detection_copies_give_no_keypoints(texture):
    """ORB's pyramid failed on a side of 1 px, also on a copy shrunk to it (max_image_side)."""
    for detector in ("sift", "orb"):
        assert len(FeatureExtractor(FeatureOptions(detector=detector))
                   .extract(texture[:2, :400].copy())) == 0
    thin = np.ascontiguousarray(np.tile(texture[:3], (1, 2)))  # 3 x 2400 -> 0.16 x 128
    assert len(FeatureExtractor(FeatureOptions(detector="orb", max_image_side=128))
               .extract(thin)) == 0
