"""Session 51 review of feature registration (features.py, pairs.py, pair_selection.py,
pairwise.py): SIFT's cap spent before the mask, the needless SIFT retry, option checks, the
RANSAC threshold at a shrunk detection scale, the circular footprint past the frame, inliers
spread too thin and the specular mask on bright grey frames."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest

from fusedmosaic.registration.features import FeatureExtractor, FeatureOptions, specular_mask


def _texture(size=(300, 300), seed=0, sigma=2.0, gain=4.0) -> np.ndarray:
    """Blurred-noise texture, uint8 grey, no black border nor highlight (SIFT finds ~1900
    keypoints on 300x300)."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.normal(128, 60, size).astype(np.float32), (0, 0), sigma)
    return np.clip((img - 128) * gain + 128, 30, 225).astype(np.uint8)


# --- finding 2: SIFT's max_features counted inside the mask -------------------------------------

def test_sift_max_features_counts_keypoints_inside_the_mask():
    img = _texture()
    mask = np.zeros_like(img)
    mask[:, :150] = 255  # ~960 candidates inside; OpenCV's cap kept 46 of its 100 there
    ex = FeatureExtractor(FeatureOptions(detector="sift", max_features=100, mask_margin_px=0),
                          mask)
    f = ex.extract(img)
    assert len(f) == 100
    assert (f.points[:, 0] < 150).all()
    assert f.descriptors.shape == (100, 128)


def test_sift_keeps_the_strongest_inside_the_mask():
    """The kept keypoints are the strongest of those inside the mask, each with its own
    descriptor (the same as OpenCV's own cap on a frame without a mask)."""
    img = _texture(seed=1)
    ex = FeatureExtractor(FeatureOptions(detector="sift", max_features=150, mask_margin_px=0))
    f = ex.extract(img)
    kp, desc = cv2.SIFT_create(nfeatures=150).detectAndCompute(img, None)
    ref = {(k.pt, tuple(d)) for k, d in zip(kp, desc, strict=True)}
    got = {(tuple(p), tuple(d)) for p, d in zip(f.points, f.descriptors, strict=True)}
    assert got == ref


def test_sift_under_the_cap_keeps_every_keypoint_in_the_mask():
    img = _texture(seed=2)
    mask = np.zeros_like(img)
    cv2.circle(mask, (150, 150), 100, 255, -1)  # ~750 keypoints, under the 1000
    ex = FeatureExtractor(FeatureOptions(detector="sift", mask_margin_px=0), mask)
    f = ex.extract(img)
    kp, desc = cv2.SIFT_create().detectAndCompute(img, mask)
    np.testing.assert_array_equal(f.points, np.array([k.pt for k in kp]))
    np.testing.assert_array_equal(f.descriptors, desc)


# --- finding 3: no SIFT retry when the cap, not low contrast, limits the count -------------------

def _count_detections(monkeypatch) -> list:
    """FeatureExtractor._detect's calls, counted in the list returned."""
    calls = []
    detect = FeatureExtractor._detect

    def counting(self, *args):
        calls.append(1)
        return detect(self, *args)

    monkeypatch.setattr(FeatureExtractor, "_detect", counting)
    return calls


@pytest.mark.parametrize("max_features", [30, 49])
def test_sift_no_retry_when_max_features_reached(monkeypatch, max_features):
    calls = _count_detections(monkeypatch)
    ex = FeatureExtractor(FeatureOptions(detector="sift", max_features=max_features))
    f = ex.extract(_texture())
    assert len(f) >= max_features
    assert len(calls) == 1


def test_sift_retry_still_runs_on_low_contrast(monkeypatch):
    calls = _count_detections(monkeypatch)
    img = _texture(gain=0.15)  # std ~1.3: few keypoints at contrastThreshold 0.04
    ex = FeatureExtractor(FeatureOptions(detector="sift", max_features=30))
    first = len(cv2.SIFT_create().detect(img, None))
    assert first < 30
    ex.extract(img)
    assert len(calls) == 2


# --- finding 7: option and input checks ---------------------------------------------------------

@pytest.mark.parametrize("value", ["no", 0, 1, None])
def test_guided_sift_must_be_a_bool(value):
    from fusedmosaic.registration.pairs import MatchOptions

    with pytest.raises(ValueError, match=r"guided_sift: expected True or False"):
        MatchOptions(guided_sift=value)
    options = MatchOptions()
    options.guided_sift = value  # set after construction: match_pair validates again
    with pytest.raises(ValueError, match=r"guided_sift"):
        options.validate()


def test_guided_sift_numpy_bool_accepted():
    from fusedmosaic.registration.pairs import MatchOptions

    assert MatchOptions(guided_sift=np.bool_(True)).guided_sift


@pytest.mark.parametrize("detector", ["sift", "orb"])
def test_extract_of_a_list_is_a_clear_error(detector):
    """A list is an array like any other: refused for its dtype, naming the frame (it was a bare
    AttributeError: 'list' object has no attribute 'ndim')."""
    ex = FeatureExtractor(FeatureOptions(detector=detector))
    with pytest.raises(ValueError, match=r"frame 3: expected a uint8 .* got int64"):
        ex.extract(_texture((200, 200)).tolist(), 3)


# --- finding 4: a circular field of view larger than the frame is clipped to it -------------

def _shifted(dy: float) -> np.ndarray:
    return np.stack([np.eye(3), np.array([[1, 0, 0], [0, 1, dy], [0, 0, 1.0]])])


def _true_overlap(w: int, h: int, r: float, dy: int) -> float:
    """Circle & frame, rasterised: intersection over the smaller."""
    yy, xx = np.mgrid[-200:h + dy + 200, -200:w + 200]

    def region(oy):
        return (((xx - (w - 1) / 2) ** 2 + (yy - oy - (h - 1) / 2) ** 2 <= r * r)
                & (xx >= 0) & (xx < w) & (yy - oy >= 0) & (yy - oy < h))

    a, b = region(0), region(dy)
    return (a & b).sum() / min(a.sum(), b.sum())


@pytest.mark.parametrize("dy", [200, 400, 500])
def test_footprint_circle_clipped_to_the_frame(dy):
    from fusedmosaic.registration.pair_selection import footprint_polygons, overlap_fraction

    w, h, r = 720, 576, 400
    a, b = footprint_polygons(_shifted(dy), w, h, fov_radius=r, n_vertices=96)
    # whole circle: 0.68 / 0.39 / 0.26 against 0.64 / 0.28 / 0.11
    assert overlap_fraction(a, b) == pytest.approx(_true_overlap(w, h, r, dy), abs=0.01)
    assert a[:, 0].min() >= 0 and a[:, 0].max() <= w and a[:, 1].min() >= 0
    assert a[:, 1].max() <= h


def test_footprint_circle_inside_the_frame_unchanged():
    from fusedmosaic.registration.pair_selection import footprint_polygons

    a = footprint_polygons(np.eye(3)[None], 400, 400, fov_radius=190, n_vertices=24)[0]
    t = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    expected = np.stack([199.5 + 190 * np.cos(t), 199.5 + 190 * np.sin(t)], 1)
    np.testing.assert_allclose(a, expected, atol=1e-4)


def test_emt_guided_pairs_respect_min_overlap_with_a_cropped_circle():
    from fusedmosaic.registration.pair_selection import emt_guided_pairs

    # frame 1 shifted 400 px: circle & frame overlap 0.28 < min_overlap 0.3 (0.39 as circles)
    pairs = emt_guided_pairs(_shifted(400), 720, 576, fov_radius=400, min_overlap=0.3)
    assert pairs == []
    assert emt_guided_pairs(_shifted(200), 720, 576, fov_radius=400, min_overlap=0.3) == [(1, 0)]


# --- finding 6: the specular mask taking much of a (grey) frame is reported ------------------

def _bright(seed=0) -> np.ndarray:
    """Grey texture over-exposed: ~30 % of pixels reach 235, the mask takes most of it."""
    img = _texture((240, 240), seed=seed).astype(np.float64)
    return np.clip(img * 1.45, 30, 255).astype(np.uint8)


def test_specular_mask_over_much_of_the_frame_warns_once():
    ex = FeatureExtractor(FeatureOptions(detector="orb", mask_margin_px=0))
    assert (specular_mask(_bright()) > 0).mean() > 0.3
    with warnings.catch_warnings(record=True) as heard:
        warnings.simplefilter("always")
        for k in range(3):
            ex.extract(_bright(k), k)
    texts = [str(w.message) for w in heard]
    assert len(texts) == 1
    assert texts[0].startswith("frame 0: the specular-highlight mask")
    assert "of the field of view" in texts[0] and "--keep-specular" in texts[0]
    # turned off: no mask, no warning
    off = FeatureExtractor(FeatureOptions(detector="orb", mask_margin_px=0, mask_specular=False))
    with warnings.catch_warnings(record=True) as heard:
        warnings.simplefilter("always")
        off.extract(_bright(), 0)
    assert heard == []


def test_simulated_highlights_do_not_warn():
    from fusedmosaic.simulation import FetoscopyOptions, generate_fetoscopy

    scene = generate_fetoscopy(FetoscopyOptions(n_frames=2, seed=0, motion="handheld",
                                                specular_lights=3))
    image = scene.render(0)
    covered = (specular_mask(image) > 0)[scene.fov_mask() > 0].mean()
    assert 0.01 < covered < 0.05  # measured 2.2-2.6 %
    ex = FeatureExtractor(FeatureOptions(detector="orb"), scene.fov_mask())
    with warnings.catch_warnings(record=True) as heard:
        warnings.simplefilter("always")
        f = ex.extract(image, 0)
    assert heard == [] and len(f) > 100


# --- finding 1: inliers spread too thin are refused --------------------------------------------

def _synthetic_pair(points_m: np.ndarray, seed: int = 1):
    """Features of frame m at points_m and of frame l at the same points shifted by (+5, +3)
    with 0.3 px noise, the descriptors matching one to one (the true motion: a pure shift)."""
    from fusedmosaic.registration.features import Features

    rng = np.random.default_rng(seed)
    n = len(points_m)
    desc = rng.random((n, 128)).astype(np.float32)
    points_l = points_m + np.array([5.0, 3.0]) + rng.normal(0, 0.3, points_m.shape)
    f_m = Features(1, points_m, desc, False)
    f_l = Features(0, points_l, desc + rng.normal(0, 0.01, desc.shape).astype(np.float32), False)
    return f_l, f_m


def _cases():
    rng = np.random.default_rng(1)
    n = 60
    t = rng.uniform(0, 1, n)
    return {"two lines 10 px apart": np.c_[50 + 300 * t, np.where(np.arange(n) % 2, 100.0, 110.0)],
            "20 px cluster": 200 + rng.uniform(0, 20, (n, 2)),
            "spread": rng.uniform(40, 360, (n, 2))}


@pytest.mark.parametrize("case", ["two lines 10 px apart", "20 px cluster"])
def test_thinly_spread_inliers_are_refused(case):
    from fusedmosaic.registration.pairs import MatchOptions, match_pair

    f_l, f_m = _synthetic_pair(_cases()[case])
    r = match_pair(f_l, f_m, (400, 400))
    # accepted before, the frame's corners 9 / 26 px off the true shift
    assert not r.ok and r.H_lm is None and r.n_inliers == 0
    assert r.status.startswith("inliers too thinly spread (60 inliers span ")
    assert "min_inlier_spread 0.015 x the frame's shorter side = 6.0 px" in r.status
    # the check off: registered (as before)
    assert match_pair(f_l, f_m, (400, 400), MatchOptions(min_inlier_spread=0)).ok


def test_spread_inliers_are_accepted_and_accurate():
    from fusedmosaic.registration.pairs import match_pair

    f_l, f_m = _synthetic_pair(_cases()["spread"])
    r = match_pair(f_l, f_m, (400, 400))
    assert r.ok, r.status
    corners = np.array([[0, 0, 1], [400, 0, 1], [400, 400, 1], [0, 400, 1.0]])
    q = corners @ r.H_lm.T
    np.testing.assert_allclose(q[:, :2] / q[:, 2:], corners[:, :2] + [5, 3], atol=1.0)


def test_thin_band_of_texture_refused_on_a_simulated_pair():
    """Frame m textured only in a 40 px band (one vessel over smooth tissue): ORB registered it
    22 inliers 3.6 px across, 11.5 px off over the field of view on average."""
    from fusedmosaic.registration.pairs import match_pair
    from fusedmosaic.simulation import FetoscopyOptions, generate_fetoscopy

    scene = generate_fetoscopy(FetoscopyOptions(n_frames=2, seed=0, motion="handheld"))
    ex = FeatureExtractor(FeatureOptions(detector="orb"), scene.fov_mask())
    image = scene.render(1)
    keep = np.zeros(image.shape[:2], bool)
    keep[180:220] = True
    image[~keep] = int(image[keep].mean())
    r = match_pair(ex.extract(scene.render(0), 0), ex.extract(image, 1), scene.size)
    assert r.status.startswith("inliers too thinly spread") or not r.ok
    assert r.H_lm is None


@pytest.mark.parametrize("value", [-0.1, 0.5, float("nan"), True, "0.1"])
def test_min_inlier_spread_is_checked(value):
    from fusedmosaic.registration.pairs import MatchOptions

    with pytest.raises(ValueError, match=r"min_inlier_spread: expected a fraction in \[0, 0.5\)"):
        MatchOptions(min_inlier_spread=value)


def test_pairwise_reports_a_pair_refused_for_thin_inliers(tmp_path):
    """PairVis treats the refusal as any failed pair: the reason reaches the error / status."""
    from fusedmosaic.estimation.pairwise import PairwiseOptions, run_pairwise
    from fusedmosaic.io.dataset import read_dataset
    from fusedmosaic.registration.pairs import MatchOptions
    from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

    root = simulate_fetoscopy(tmp_path / "d", FetoscopyOptions(n_frames=3, laps=3 / 37,
                                                               seed=0))
    options = PairwiseOptions(features=FeatureOptions(detector="orb"),
                              matching=MatchOptions(min_inlier_spread=0.45))  # refuses all
    with pytest.raises(ValueError, match=r"no consecutive pair .* inliers too thinly spread"):
        run_pairwise(read_dataset(root), progress=False, options=options)
