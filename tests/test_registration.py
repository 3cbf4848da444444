"""Feature registration (seed 000, Sec. 3.1), pair selection, and the PairVis chain."""

import cv2
import numpy as np
import pytest

from fusedmosaic import _core
from fusedmosaic.estimation.pairwise import chain_homographies
from fusedmosaic.evaluation import frame_errors
from fusedmosaic.registration.features import (
    FeatureExtractor,
    FeatureOptions,
    Features,
    fov_mask_from_image,
)
from fusedmosaic.registration.pair_selection import all_pairs, emt_guided_pairs, window_pairs
from fusedmosaic.registration.pairs import MatchOptions, degeneracy, match_pair, match_pairs
from fusedmosaic.simulation import FetoscopyOptions, generate_fetoscopy

SIZE = (320, 300)  # width, height


@pytest.fixture(scope="module")
def texture():
    rng = np.random.default_rng(11)
    noise = rng.normal(0, 1, (900, 900)).astype(np.float32)
    img = sum(cv2.GaussianBlur(noise, (0, 0), s) * s for s in (1.5, 4, 12))
    img = (img - img.min()) / (img.max() - img.min()) * 255
    return img.astype(np.uint8)


def view(texture, H_frame_from_tex):
    return cv2.warpPerspective(texture, H_frame_from_tex, SIZE, flags=cv2.INTER_LINEAR)


def similarity(angle_deg, scale, tx, ty):
    a = np.deg2rad(angle_deg)
    return np.array([[scale * np.cos(a), -scale * np.sin(a), tx],
                     [scale * np.sin(a), scale * np.cos(a), ty], [0, 0, 1.0]])


@pytest.mark.parametrize("detector", ["sift", "orb"])
def test_known_homography_recovered(texture, detector):
    A = similarity(0, 1, -250, -250)
    B = np.array([[1.02, 0.03, -270], [-0.02, 0.99, -236], [2e-5, -1e-5, 1.0]])
    img_m, img_l = view(texture, A), view(texture, B)
    ext = FeatureExtractor(FeatureOptions(detector=detector, max_features=1500))
    fm, fl = ext.extract(img_m, 0), ext.extract(img_l, 1)
    res = match_pair(fl, fm, SIZE, MatchOptions())
    assert res.ok, res.status
    true_lm = B @ np.linalg.inv(A)
    err = frame_errors(res.H_lm[None], (true_lm / true_lm[2, 2])[None], *SIZE)[0]
    assert err < 0.5  # px over the 100x100 grid
    assert res.n_inliers >= 50 and res.points_l.shape == res.points_m.shape
    moved = cv2.perspectiveTransform(res.points_m[None], true_lm)[0]
    assert np.median(np.linalg.norm(moved - res.points_l, axis=1)) < 1.0


def test_orb_fast_threshold_and_the_low_contrast_retry(texture):
    """FeatureOptions.orb_fast_threshold (default 5: OpenCV's ORB at that threshold exactly); a
    raised one keeps a contrasted frame's keypoints and detects a low-contrast frame that gives
    fewer than 90 % of max_features again at orb_fast_threshold_low."""
    def orb(image, threshold):
        return cv2.ORB_create(nfeatures=1000, fastThreshold=threshold).detectAndCompute(image,
                                                                                        None)

    image = view(texture, similarity(0, 1, -200, -200))
    low = (image.astype(float) * 0.3 + 100).astype(np.uint8)  # contrast 0.3
    counts = {t: len(orb(low, t)[0]) for t in (5, 10)}
    assert counts[10] < 0.9 * 1000 < counts[5]  # measured 93 and 935
    ext = {t: FeatureExtractor(FeatureOptions(detector="orb", orb_fast_threshold=t))
           for t in (5, 10)}
    np.testing.assert_array_equal(ext[5].extract(image).descriptors, orb(image, 5)[1])
    np.testing.assert_array_equal(ext[10].extract(image).descriptors, orb(image, 10)[1])
    np.testing.assert_array_equal(ext[10].extract(low).descriptors, orb(low, 5)[1])  # retried
    no_retry = FeatureExtractor(FeatureOptions(detector="orb", orb_fast_threshold=10,
                                               orb_fast_threshold_low=10))
    assert len(no_retry.extract(low)) == counts[10]
    for bad, message in (
            (dict(orb_fast_threshold=0), "orb_fast_threshold must be an integer in 1..255"),
            (dict(orb_fast_threshold=2.5), "orb_fast_threshold must be an integer in 1..255"),
            (dict(orb_fast_threshold_low=256), "orb_fast_threshold_low must be an integer")):
        with pytest.raises(ValueError, match=message):
            FeatureExtractor(FeatureOptions(detector="orb", **bad))


@pytest.mark.parametrize("bad, message", [
    (dict(clahe=True, clahe_tiles=0), r"clahe_tiles must be an integer in 1\.\.1024"),
    (dict(clahe_tiles=2.5), "clahe_tiles must be an integer"),
    (dict(clahe_clip_limit=float("nan")), "clahe_clip_limit must be a finite number >= 0"),
    (dict(clahe_clip_limit=-1.0), "clahe_clip_limit must be a finite number >= 0"),
    (dict(mask_margin_px=-3), "mask_margin_px must be an integer in 0..10000"),
    (dict(border_threshold=300), "border_threshold must be an integer in 0..255")])
def test_feature_options_refused_before_any_frame(bad, message):
    """clahe_tiles=0 was accepted and the first add_frame killed the interpreter (SIGFPE in
    OpenCV's CLAHE); other bad values failed inside OpenCV (review)."""
    from fusedmosaic.estimation.sequential import SequentialMosaicker, SequentialOptions
    from fusedmosaic.io import Camera

    with pytest.raises(ValueError, match=message):
        SequentialMosaicker(Camera(64, 64, np.array([[60.0, 0, 32], [0, 60, 32], [0, 0, 1]])),
                            SequentialOptions(features=FeatureOptions(**bad)))


@pytest.mark.parametrize("bad, message", [
    (dict(min_inliers=3), r"min_inliers: expected an integer >= 4, got 3"),
    (dict(ratio=1.5), r"ratio: expected a value in \(0, 1\], got 1\.5"),
    (dict(ransac_threshold_px=-1.0), r"ransac_threshold_px: expected pixels > 0"),
    (dict(ransac_confidence=1.0), r"ransac_confidence: expected a value in \(0, 1\)"),
    (dict(max_scale_change=0.5), r"max_scale_change: expected a factor > 1 \(1 refuses every "
                                 r"pair\)"),
    (dict(max_scale_change=1.0), r"max_scale_change: expected a factor > 1"),
    (dict(num_threads=0), r"num_threads: expected an integer >= 1"),
    (dict(binary_matcher="flann"), r"binary_matcher: expected one of \('exact', 'lsh'\)")])
def test_match_options_refused(bad, message):
    """min_inliers=3 failed in findHomography on whichever pair had exactly 3 matches, a
    random frame of a live loop (review): refused when built, and when set afterwards, by the
    first match."""
    with pytest.raises(ValueError, match=message):
        MatchOptions(**bad)
    options = MatchOptions()
    for name, value in bad.items():
        setattr(options, name, value)
    feats = Features(0, np.zeros((0, 2)), np.zeros((0, 128), np.float32), binary=False)
    with pytest.raises(ValueError, match=message):
        match_pair(feats, feats, SIZE, options)


def test_sift_low_contrast_retry_registers_faded_frames():
    """SIFT's threshold is on absolute contrast: the simulator's frames at 70 % contrast gave
    1-2 keypoints and no pair registered. A frame with fewer than sift_min_features is detected
    again at sift_contrast_threshold_low: the pair then registers to the true homography."""
    s = generate_fetoscopy(FetoscopyOptions(n_frames=150, seed=0))  # ~40 px per frame
    frames = []
    for k in (0, 2):
        image = s.render(k).astype(np.float32)
        mean = image.mean(axis=(0, 1))
        frames.append(np.clip(mean + 0.6 * (image - mean), 0, 255).astype(np.uint8))
    size = s.size
    no_retry = FeatureExtractor(FeatureOptions(sift_min_features=0))
    assert max(len(no_retry.extract(f, k)) for k, f in enumerate(frames)) < 20
    ext = FeatureExtractor(FeatureOptions())
    f0, f2 = ext.extract(frames[0], 0), ext.extract(frames[1], 2)
    assert min(len(f0), len(f2)) == 200  # the retry keeps the strongest 4 x sift_min_features
    # 0 (VLFeat's default peak threshold) is a threshold too, not "use the first one"
    zero = FeatureExtractor(FeatureOptions(sift_contrast_threshold_low=0.0))
    assert len(zero.extract(frames[0], 0)) == 200
    res = match_pair(f2, f0, size, MatchOptions())
    assert res.ok, res.status
    true = np.linalg.inv(s.homographies[2]) @ s.homographies[0]  # frame 0 -> frame 2
    err = frame_errors(res.H_lm[None], (true / true[2, 2])[None], *size)[0]
    assert err < 0.5  # px over the 100x100 grid
    for bad, message in (
            (dict(sift_contrast_threshold_low=-0.1), "sift_contrast_threshold_low must be a "
             r"number in \[0, 1\)"),
            (dict(sift_min_features=2.5), "sift_min_features must be an integer >= 0")):
        with pytest.raises(ValueError, match=message):
            FeatureExtractor(FeatureOptions(**bad))


@pytest.mark.parametrize("detector", ["sift", "orb"])
def test_detection_on_a_shrunk_copy_maps_keypoints_to_full_resolution(texture, detector):
    # Frames at twice the size, detected at half size (max_image_side): the keypoints are in
    # full-resolution pixels, so the recovered homography is the full-resolution one.
    S = np.diag([2.0, 2.0, 1.0])
    A = S @ similarity(0, 1, -250, -250)
    B = S @ np.array([[1.02, 0.03, -270], [-0.02, 0.99, -236], [2e-5, -1e-5, 1.0]])
    size = (2 * SIZE[0], 2 * SIZE[1])
    img_m, img_l = (cv2.warpPerspective(texture, H, size, flags=cv2.INTER_LINEAR) for H in (A, B))
    mask = np.zeros((size[1], size[0]), np.uint8)
    cv2.circle(mask, (size[0] // 2, size[1] // 2), 280, 255, -1)
    ext = FeatureExtractor(FeatureOptions(detector=detector, max_features=1500,
                                          max_image_side=SIZE[0]), mask)
    fm, fl = ext.extract(img_m, 0), ext.extract(img_l, 1)
    inside = mask[np.round(fm.points[:, 1]).astype(int), np.round(fm.points[:, 0]).astype(int)]
    assert len(fm) > 100 and (inside > 0).all()  # the mask applies at the shrunk size too
    assert fm.points[:, 0].max() > SIZE[0] and fm.points[:, 1].max() > SIZE[1]
    res = match_pair(fl, fm, size, MatchOptions())
    assert res.ok, res.status
    true_lm = B @ np.linalg.inv(A)
    err = frame_errors(res.H_lm[None], (true_lm / true_lm[2, 2])[None], *size)[0]
    assert err < 1.0  # px at full resolution (0.5 px at the detection scale)
    moved = cv2.perspectiveTransform(res.points_m[None], true_lm)[0]
    assert np.median(np.linalg.norm(moved - res.points_l, axis=1)) < 2.0


def test_shrunk_detection_keypoints_sit_where_full_resolution_ones_do(texture):
    # An image made by doubling every pixel of `small`: ORB on it shrunk back by 2 finds the
    # keypoints of `small`, which in full-resolution pixels ((x + 0.5) * 2 - 0.5) must coincide
    # with ORB's on the full image at the same corners, to well under a pixel. A 0/1 mask is
    # taken as 0/255.
    small = view(texture, similarity(0, 1, -250, -250))
    full = cv2.resize(small, (2 * SIZE[0], 2 * SIZE[1]), interpolation=cv2.INTER_NEAREST)
    mask = np.zeros(full.shape, np.uint8)
    mask[40:-40, 40:-40] = 1
    shrunk = FeatureExtractor(FeatureOptions(detector="orb", max_image_side=SIZE[0]),
                              mask).extract(full)
    ref = FeatureExtractor(FeatureOptions(detector="orb")).extract(small)
    assert len(shrunk) > 300
    expected = (ref.points + 0.5) * 2 - 0.5
    d = np.linalg.norm(shrunk.points[:, None] - expected[None], axis=2).min(axis=1)
    assert np.median(d) < 0.1


@pytest.mark.parametrize("side", [0, 31, 400.0, True])
def test_bad_max_image_side_is_refused(side):
    with pytest.raises(ValueError, match=r"max_image_side must be >= 32 \(pixels\), an integer, or "
                                         "None"):
        FeatureExtractor(FeatureOptions(max_image_side=side))


def test_black_frame_and_unrelated_frames_are_reported(texture):
    ext = FeatureExtractor()
    f0 = ext.extract(view(texture, similarity(0, 1, -100, -100)), 0)
    black = ext.extract(np.zeros((SIZE[1], SIZE[0]), np.uint8), 1)
    assert len(black) == 0
    res = match_pair(black, f0, SIZE)
    assert not res.ok and res.status.startswith("too few features")
    rng = np.random.default_rng(5)
    other = cv2.GaussianBlur(rng.integers(0, 255, (SIZE[1], SIZE[0])).astype(np.uint8), (0, 0), 2)
    res = match_pair(ext.extract(other, 2), f0, SIZE)
    assert not res.ok and res.H_lm is None


def test_degenerate_homographies_rejected():
    assert degeneracy(np.eye(3), *SIZE, 4.0) is None
    assert "area scale" in degeneracy(np.diag([10.0, 10.0, 1.0]), *SIZE, 4.0)
    flip = np.array([[1.0, 0, 0], [0, 1, 0], [-0.01, 0, 1]])
    assert "behind the camera" in degeneracy(flip, *SIZE, 4.0)


def test_fov_mask_detected_from_black_border(texture):
    img = view(texture, similarity(0, 1, -100, -100))
    circle = np.zeros_like(img)
    cv2.circle(circle, (SIZE[0] // 2, SIZE[1] // 2), 120, 255, -1)
    img[circle == 0] = 0
    mask = fov_mask_from_image(img)
    assert mask is not None
    assert (mask > 0).sum() == pytest.approx((circle > 0).sum(), rel=0.03)
    feats = FeatureExtractor(FeatureOptions(mask_margin_px=6)).extract(img)
    r = np.linalg.norm(feats.points - [SIZE[0] // 2, SIZE[1] // 2], axis=1)
    assert len(feats) > 50 and r.max() < 120 - 4
    assert fov_mask_from_image(view(texture, np.eye(3))) is None


def test_parallel_matching_equals_serial(texture):
    ext = FeatureExtractor(FeatureOptions(detector="orb"))
    feats = {k: ext.extract(view(texture, similarity(2 * k, 1, -200 - 9 * k, -200 + 4 * k)), k)
             for k in range(4)}
    pairs = window_pairs(4, 2)
    serial = match_pairs(feats, pairs, SIZE, MatchOptions(num_threads=1))
    parallel = match_pairs(feats, pairs, SIZE, MatchOptions(num_threads=2))
    assert [(r.frame_l, r.frame_m, r.n_inliers) for r in serial] == \
        [(r.frame_l, r.frame_m, r.n_inliers) for r in parallel]
    with pytest.raises(ValueError, match="no features for frame 9"):
        match_pairs(feats, [(9, 0)], SIZE)


def _bf_ratio_matches(query, train, ratio, norm=cv2.NORM_HAMMING):
    """The reference: OpenCV's brute-force 2-NN, the ratio test, one query per train."""
    knn = cv2.BFMatcher(norm).knnMatch(query, train, k=2)
    best = {}
    for p in knn:
        if len(p) == 2 and p[0].distance < ratio * p[1].distance:
            m = p[0]
            if m.trainIdx not in best or m.distance < best[m.trainIdx].distance:
                best[m.trainIdx] = m
    return sorted((m.queryIdx, m.trainIdx, m.distance) for m in best.values())


@pytest.mark.parametrize("ratio", [0.6, 0.8, 1.0])
def test_hamming_matcher_equals_opencv_brute_force(texture, ratio):
    ext = FeatureExtractor(FeatureOptions(detector="orb"))
    f0 = ext.extract(view(texture, similarity(0, 1, -200, -200)), 0)
    f1 = ext.extract(view(texture, similarity(5, 1.05, -215, -190)), 1)
    q, t, d = _core.match_hamming(f0.descriptors, f1.descriptors, ratio)
    assert list(zip(q.tolist(), t.tolist(), d.tolist(), strict=True)) == \
        _bf_ratio_matches(f0.descriptors, f1.descriptors, ratio)
    assert len(q) > 100 and len(set(t.tolist())) == len(t)
    # any length, not only ORB's 32 bytes (the word loop plus a byte tail)
    rng = np.random.default_rng(3)
    a, b = rng.integers(0, 256, (300, 13), np.uint8), rng.integers(0, 256, (250, 13), np.uint8)
    b[:100] = a[:100] ^ (rng.random((100, 13)) < 0.05).astype(np.uint8)  # near copies
    q, t, d = _core.match_hamming(a, b, ratio)
    assert list(zip(q.tolist(), t.tolist(), d.tolist(), strict=True)) == \
        _bf_ratio_matches(a, b, ratio)


def test_lsh_binary_matcher_still_available(texture):
    """MatchOptions(binary_matcher="lsh"): FLANN's approximate index, as before the C++ matcher;
    it registers the pair as well, its matches mostly those of the exact search."""
    A = similarity(0, 1, -250, -250)
    B = np.array([[1.02, 0.03, -270], [-0.02, 0.99, -236], [2e-5, -1e-5, 1.0]])
    ext = FeatureExtractor(FeatureOptions(detector="orb", max_features=1500))
    fm, fl = ext.extract(view(texture, A), 0), ext.extract(view(texture, B), 1)
    true_lm = B @ np.linalg.inv(A)
    results = {m: match_pair(fl, fm, SIZE, MatchOptions(binary_matcher=m))
               for m in ("exact", "lsh")}
    for r in results.values():
        assert r.ok, r.status
        err = frame_errors(r.H_lm[None], (true_lm / true_lm[2, 2])[None], *SIZE)[0]
        assert err < 0.5
    exact = {tuple(p) for p in np.c_[results["exact"].points_m, results["exact"].points_l]}
    lsh = [tuple(p) for p in np.c_[results["lsh"].points_m, results["lsh"].points_l]]
    assert np.mean([p in exact for p in lsh]) > 0.8
    with pytest.raises(ValueError, match="binary_matcher: expected one of"):
        match_pair(fl, fm, SIZE, MatchOptions(binary_matcher="flann"))


def test_hamming_matcher_bad_input():
    a = np.zeros((10, 32), np.uint8)
    with pytest.raises(ValueError, match="differ in length: 32 and 16 bytes"):
        _core.match_hamming(a, np.zeros((10, 16), np.uint8), 0.8)
    with pytest.raises(ValueError, match="query: expected a 2-D"):
        _core.match_hamming(a[0], a, 0.8)
    with pytest.raises(ValueError, match=r"ratio: expected a value in \(0, 1\]"):
        _core.match_hamming(a, a, 1.5)
    q, t, d = _core.match_hamming(a, a[:1], 0.8)  # one train descriptor: no second nearest
    assert len(q) == len(t) == len(d) == 0


def _guided_reference(query, query_xy, train, train_xy, radius, ratio, max_distance):
    """The guided search written out: distances (Hamming for uint8 descriptors, Euclidean in
    float64 for float ones) to every train keypoint within the radius of the prediction, the
    two nearest of those, the ratio test (a single candidate: within max_distance >= 0, or
    else the ratio test against the nearest other train descriptor of all), one query per
    train (the first on a tie)."""
    if query.dtype == np.uint8:
        dist = np.unpackbits(query[:, None, :] ^ train[None, :, :], axis=2).sum(axis=2)
    else:
        diff = query[:, None, :].astype(np.float64) - train[None, :, :]
        dist = np.sqrt((diff ** 2).sum(axis=2))
    d2 = ((query_xy[:, None, :] - train_xy[None, :, :]) ** 2).sum(axis=2)
    best = {}
    for i in range(len(query)):
        if not np.isfinite(query_xy[i]).all():
            continue
        near = np.flatnonzero(d2[i] <= radius * radius)
        if len(near) == 0:
            continue
        order = np.argsort(dist[i, near], kind="stable")
        j, d = int(near[order[0]]), dist[i, near[order[0]]]
        if len(near) == 1 and max_distance >= 0:
            if not d <= max_distance:
                continue
        else:  # a lone candidate against the nearest of all the other train descriptors
            second = (dist[i, near[order[1]]] if len(near) > 1
                      else np.delete(dist[i], j).astype(float).min(initial=np.inf))
            if not d < ratio * second:
                continue
        if j not in best or d < best[j][1]:
            best[j] = (i, d)
    return sorted((i, j, d) for j, (i, d) in best.items())


def test_guided_hamming_matcher(texture):
    """match_hamming_guided compares only train keypoints within the radius of each query's
    predicted position: the same matches as that search written out in numpy, for small to
    large radii, with and without accepting a lone candidate, and unpredictable queries (NaN,
    far outside the image) unmatched; a radius covering everything is match_hamming."""
    A, B = similarity(0, 1, -200, -200), similarity(5, 1.05, -215, -190)
    ext = FeatureExtractor(FeatureOptions(detector="orb"))
    f0, f1 = ext.extract(view(texture, A), 0), ext.extract(view(texture, B), 1)
    H = B @ np.linalg.inv(A)  # frame 0 -> frame 1 pixels
    predicted = cv2.perspectiveTransform(f0.points[None], H)[0]
    predicted += np.random.default_rng(0).normal(0, 1.0, predicted.shape)  # a noisy prediction
    predicted[:7] = np.nan
    predicted[7:9] = 1e12
    for radius in (3.0, 12.0, 40.0):
        for max_distance in (-1, 40):
            q, t, d = _core.match_hamming_guided(f0.descriptors, predicted, f1.descriptors,
                                                 f1.points, radius, 0.8, max_distance)
            got = list(zip(q.tolist(), t.tolist(), d.tolist(), strict=True))
            assert got == _guided_reference(f0.descriptors, predicted, f1.descriptors,
                                            f1.points, radius, 0.8, max_distance)
            assert len(got) > 50 and not {0, 1, 2, 3, 4, 5, 6, 7, 8} & set(q.tolist())
    everywhere = np.zeros_like(f0.points)
    for a, b in zip(_core.match_hamming_guided(f0.descriptors, everywhere, f1.descriptors,
                                               f1.points, 1e4, 0.8),
                    _core.match_hamming(f0.descriptors, f1.descriptors, 0.8), strict=True):
        np.testing.assert_array_equal(a, b)
    # far-flung keypoints and a tiny radius (the grid's cells stay at most ~4 per keypoint): a
    # query predicted onto one train keypoint finds exactly that one
    far = f1.points * 1e6
    q, t, _ = _core.match_hamming_guided(f0.descriptors[:1], far[5:6], f1.descriptors, far,
                                         1e-3, 0.8, 256)
    assert q.tolist() == [0] and t.tolist() == [5]


def test_guided_hamming_matcher_bad_input():
    a, xy = np.zeros((10, 32), np.uint8), np.zeros((10, 2))
    with pytest.raises(ValueError, match=r"query_xy: expected \(10, 2\) positions, one per "
                                         r"query descriptor, got \(9, 2\)"):
        _core.match_hamming_guided(a, xy[:9], a, xy, 5.0)
    with pytest.raises(ValueError, match=r"train_xy: expected \(10, 2\) positions, one per "
                                         r"train descriptor, got \(10, 3\)"):
        _core.match_hamming_guided(a, xy, a, np.zeros((10, 3)), 5.0)
    for radius in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="radius: expected a positive finite number"):
            _core.match_hamming_guided(a, xy, a, xy, radius)
    with pytest.raises(ValueError, match="differ in length: 32 and 16 bytes"):
        _core.match_hamming_guided(a, xy, np.zeros((10, 16), np.uint8), xy, 5.0)
    huge = xy.copy()
    huge[0], huge[1] = -1e308, 1e308
    with pytest.raises(ValueError, match="train_xy: the keypoints span more than a double"):
        _core.match_hamming_guided(a, xy, a, huge, 5.0)
    # queries predicted near 1e308 find nothing; the others their one candidate each
    desc = np.random.default_rng(5).integers(0, 256, (10, 32), np.uint8)
    spaced = np.c_[10.0 * np.arange(10), np.zeros(10)]
    pred = spaced.copy()
    pred[0], pred[1] = -1e308, 1e308
    q, t, d = _core.match_hamming_guided(desc, pred, desc, spaced, 5.0, 0.8, 256)
    assert q.tolist() == t.tolist() == list(range(2, 10)) and d.tolist() == [0] * 8


def _assert_same_matches(got, expected):
    """The same (query, train) pairs and, to float32 rounding, the same distances."""
    q, t, d = got
    assert list(zip(q.tolist(), t.tolist(), strict=True)) == [(i, j) for i, j, _ in expected]
    np.testing.assert_allclose(d, [e[2] for e in expected], rtol=1e-5)


def test_guided_l2_matcher(texture):
    """match_l2_guided, the guided search for float descriptors (SIFT) under the Euclidean
    distance: the numpy statement of the search for small to large radii, with and without
    accepting a lone candidate; unpredictable queries unmatched; a radius covering everything is
    OpenCV's brute-force L2 matcher with the ratio test and the one-to-one filter."""
    A, B = similarity(0, 1, -200, -200), similarity(5, 1.05, -215, -190)
    ext = FeatureExtractor(FeatureOptions(detector="sift"))
    f0, f1 = ext.extract(view(texture, A), 0), ext.extract(view(texture, B), 1)
    assert f0.descriptors.dtype == np.float32 and f0.descriptors.shape[1] == 128
    predicted = cv2.perspectiveTransform(f0.points[None], B @ np.linalg.inv(A))[0]
    predicted += np.random.default_rng(0).normal(0, 1.0, predicted.shape)
    predicted[:7] = np.nan
    predicted[7:9] = 1e12
    for radius in (3.0, 12.0, 40.0):
        for max_distance in (-1.0, 150.0):
            got = _core.match_l2_guided(f0.descriptors, predicted, f1.descriptors, f1.points,
                                        radius, 0.8, max_distance)
            _assert_same_matches(got, _guided_reference(
                f0.descriptors, predicted, f1.descriptors, f1.points, radius, 0.8, max_distance))
            assert len(got[0]) > 50 and not set(range(9)) & set(got[0].tolist())
    for ratio in (0.6, 0.8, 1.0):
        _assert_same_matches(
            _core.match_l2_guided(f0.descriptors, np.zeros_like(f0.points), f1.descriptors,
                                  f1.points, 1e4, ratio),
            _bf_ratio_matches(f0.descriptors, f1.descriptors, ratio, cv2.NORM_L2))
    # any length, not only SIFT's 128 (the 8-lane loop plus a tail): 13 floats
    rng = np.random.default_rng(3)
    a, b = rng.random((300, 13), np.float32), rng.random((250, 13), np.float32)
    b[:100] = a[:100] + rng.normal(0, 0.01, (100, 13)).astype(np.float32)  # near copies
    _assert_same_matches(_core.match_l2_guided(a, np.zeros((300, 2)), b, np.zeros((250, 2)),
                                               1.0, 0.8),
                         _bf_ratio_matches(a, b, 0.8, cv2.NORM_L2))


def test_guided_l2_matcher_bad_input():
    a, xy = np.zeros((10, 128), np.float32), np.zeros((10, 2))
    with pytest.raises(ValueError, match="differ in length: 128 and 64 floats"):
        _core.match_l2_guided(a, xy, np.zeros((10, 64), np.float32), xy, 5.0)
    with pytest.raises(ValueError, match=r"query: expected a 2-D \(N, dims\) float32 array"):
        _core.match_l2_guided(a[0], xy, a, xy, 5.0)
    with pytest.raises(ValueError, match=r"train_xy: expected \(10, 2\) positions"):
        _core.match_l2_guided(a, xy, a, xy[:3], 5.0)
    with pytest.raises(ValueError, match="descriptors: expected at least one float"):
        _core.match_l2_guided(np.zeros((10, 0), np.float32), xy, np.zeros((10, 0), np.float32),
                              xy, 5.0)
    for radius in (0.0, float("inf")):
        with pytest.raises(ValueError, match="radius: expected a positive finite number"):
            _core.match_l2_guided(a, xy, a, xy, radius)
    with pytest.raises(ValueError, match=r"ratio: expected a value in \(0, 1\]"):
        _core.match_l2_guided(a, xy, a, xy, 5.0, 0.0)
    with pytest.raises(ValueError, match="max_distance: expected a number"):
        _core.match_l2_guided(a, xy, a, xy, 5.0, 0.8, float("nan"))
    # a descriptor with a non-finite element matches nothing; the others their copy
    desc = np.random.default_rng(5).random((10, 128), np.float32)
    spaced = np.c_[10.0 * np.arange(10), np.zeros(10)]
    bad = desc.copy()
    bad[0, 3], bad[1, 100] = np.nan, np.inf
    q, t, d = _core.match_l2_guided(bad, spaced, desc, spaced, 5.0, 0.8, 1.0)
    assert q.tolist() == t.tolist() == list(range(2, 10)) and d.tolist() == [0.0] * 8
    q, t, d = _core.match_l2_guided(desc, spaced, bad, spaced, 5.0, 0.8, 1.0)
    assert q.tolist() == t.tolist() == list(range(2, 10))


@pytest.mark.parametrize("detector", ["orb", "sift"])
def test_match_pair_guided_by_a_prediction(texture, detector):
    """With a predicted homography (ORB with the exact matcher; SIFT with guided_sift)
    match_pair searches near the prediction and registers the pair as exhaustively; a wrong
    prediction falls back to the exhaustive search, which registers it too. SIFT without
    guided_sift ignores the prediction."""
    A = similarity(0, 1, -250, -250)
    B = np.array([[1.02, 0.03, -270], [-0.02, 0.99, -236], [2e-5, -1e-5, 1.0]])
    ext = FeatureExtractor(FeatureOptions(detector=detector, max_features=1500))
    fm, fl = ext.extract(view(texture, A), 0), ext.extract(view(texture, B), 1)
    true_lm = B @ np.linalg.inv(A)
    nearly = similarity(0.5, 1.0, 3, -2) @ true_lm  # a few px off
    on = MatchOptions(guided_sift=True)
    results = {
        "exhaustive": match_pair(fl, fm, SIZE, on),
        "guided": match_pair(fl, fm, SIZE, on, predicted=nearly),
        "wrong": match_pair(fl, fm, SIZE, on, predicted=similarity(0, 1, 150, 0)),
        "off": match_pair(fl, fm, SIZE, MatchOptions(guided_radius_px=0, guided_sift=True),
                          predicted=nearly),
        "default": match_pair(fl, fm, SIZE, MatchOptions(), predicted=nearly),
    }
    for r in results.values():
        assert r.ok, r.status
        err = frame_errors(r.H_lm[None], (true_lm / true_lm[2, 2])[None], *SIZE)[0]
        assert err < 0.5  # px over the 100x100 grid
    assert [r.guided for r in results.values()] == [False, True, False, False,
                                                    detector == "orb"]
    for bad, message in ((dict(guided_radius_px=-1.0), "guided_radius_px: expected pixels >= 0"),
                         (dict(guided_radius_px=float("nan")), "guided_radius_px"),
                         (dict(guided_ratio=0.0), r"guided_ratio: expected a value in \(0, 1\]"),
                         (dict(guided_sift_ratio=1.5),
                          r"guided_sift_ratio: expected a value in \(0, 1\]")):
        with pytest.raises(ValueError, match=message):
            match_pair(fl, fm, SIZE, MatchOptions(**bad), predicted=nearly)
    # among the neighbours only, with a stricter ratio (ORB 0.7, SIFT 0.5): about as many
    # inliers (measured ORB 940 vs 962, SIFT 593 vs 599)
    assert results["guided"].n_inliers > 0.8 * results["exhaustive"].n_inliers


def test_pair_selection_counts():
    assert len(all_pairs(10)) == 45
    assert window_pairs(4, 1) == [(1, 0), (2, 1), (3, 2)]
    # Frames on a line, 40 px apart, 100 px wide: only neighbours within 2 steps overlap >= 30 %.
    G = np.stack([np.array([[1.0, 0, 40 * k], [0, 1, 0], [0, 0, 1]]) for k in range(8)])
    pairs = emt_guided_pairs(G, 100, 100, min_overlap=0.3)
    assert set(pairs) == {(l, m) for l in range(8) for m in range(l) if l - m <= 1}
    G[3] = np.nan  # no prediction: keeps its temporal neighbours
    pairs = emt_guided_pairs(G, 100, 100, min_overlap=0.15)
    assert (3, 2) in pairs and (4, 3) in pairs and (3, 1) not in pairs and (5, 3) not in pairs


def test_chain_breaks_at_first_failure():
    step = np.array([[1.0, 0, 5], [0, 1, 0], [0, 0, 1]])
    G = chain_homographies([step, step, None, step])
    np.testing.assert_allclose(G[2][:2, 2], [10, 0])
    assert np.isnan(G[3:]).all() and np.isfinite(G[:3]).all()
