"""A pair keeps each correspondence once: SIFT's keypoints at one location with several
orientations pair up twice, and the bundle adjustment must not weigh that observation double."""

import cv2
import numpy as np

from fusedmosaic.registration.features import FeatureExtractor, FeatureOptions
from fusedmosaic.registration.pairs import MatchOptions, match_pair, unique_correspondences

SIZE = (320, 300)  # width, height


def _texture() -> np.ndarray:
    rng = np.random.default_rng(5)
    noise = rng.normal(0, 1, (700, 700)).astype(np.float32)
    img = sum(cv2.GaussianBlur(noise, (0, 0), s) * s for s in (1.5, 4, 12))
    return ((img - img.min()) / (img.max() - img.min()) * 255).astype(np.uint8)


def test_sift_pair_keeps_each_correspondence_once():
    tex = _texture()
    A = np.array([[1.0, 0, -150], [0, 1.0, -150], [0, 0, 1]])
    B = np.array([[1.01, 0.02, -170], [-0.02, 1.0, -140], [1e-5, 0, 1]])
    img_m = cv2.warpPerspective(tex, A, SIZE)
    img_l = cv2.warpPerspective(tex, B, SIZE)
    ext = FeatureExtractor(FeatureOptions(detector="sift", max_features=1500))
    f_m, f_l = ext.extract(img_m, 0), ext.extract(img_l, 1)
    # the texture gives SIFT locations with several orientations on both sides
    assert len(np.unique(f_m.points, axis=0)) < len(f_m)
    res = match_pair(f_l, f_m, SIZE, MatchOptions())
    assert res.ok, res.status
    rows = np.hstack([res.points_l, res.points_m])
    assert len(np.unique(rows, axis=0)) == len(rows) >= 50
    true_lm = B @ np.linalg.inv(A)
    moved = cv2.perspectiveTransform(res.points_m[None], true_lm)[0]
    assert np.median(np.linalg.norm(moved - res.points_l, axis=1)) < 1.0


def test_unique_correspondences_keeps_the_first_of_each_in_order():
    pl = np.array([[1.0, 2], [3, 4], [1, 2], [5, 6], [3, 4]])
    pm = np.array([[7.0, 8], [9, 1], [7, 8], [2, 3], [9, 2]])  # row 4 differs in m: kept
    ul, um = unique_correspondences(pl, pm)
    np.testing.assert_array_equal(ul, pl[[0, 1, 3, 4]])
    np.testing.assert_array_equal(um, pm[[0, 1, 3, 4]])
    same_l, same_m = unique_correspondences(pl[:2], pm[:2])
    assert np.array_equal(same_l, pl[:2])
    assert np.array_equal(same_m, pm[:2])
