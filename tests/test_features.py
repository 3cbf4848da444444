"""SIFT's low-contrast retry (FeatureOptions.sift_min_features): taken on a faded textured
frame, where it registers pairs that the first pass cannot, and skipped on a featureless one
(noise alone: a black frame with sensor noise), where it only found noise
(registration.features.structure_to_noise, SIFT_RETRY_MIN_STRUCTURE)."""

import numpy as np
import pytest

from fusedmosaic.evaluation import frame_errors
from fusedmosaic.registration.features import FeatureExtractor, FeatureOptions
from fusedmosaic.registration.pairs import match_pair
from fusedmosaic.simulation import FetoscopyOptions, generate_fetoscopy

SIZE = 400


def _contrast_thresholds(monkeypatch) -> list:
    """The SIFT contrast threshold of each detector the extractor makes (None: the first
    pass's, sift_contrast_threshold)."""
    used, make = [], FeatureExtractor._detector

    def spy(self, fast_threshold=None, contrast_threshold=None, max_features=None):
        used.append(contrast_threshold)
        return make(self, fast_threshold, contrast_threshold, max_features)

    monkeypatch.setattr(FeatureExtractor, "_detector", spy)
    return used


def _noise(level: float, sigma: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(level + rng.normal(0, sigma, (SIZE, SIZE, 3)), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def syn():
    return generate_fetoscopy(FetoscopyOptions(n_frames=150, seed=0))  # ~40 px per frame


def _faded(scene, k: int, fade: float) -> np.ndarray:
    """Frame k at `fade` of its contrast, with the simulator's sensor noise (sigma 2) added
    after fading: the noise does not fade with the tissue."""
    image = scene.render(k, noise=False).astype(np.float64)
    mean = image.mean(axis=(0, 1))
    noise = np.random.default_rng([k, 9]).normal(0.0, 2.0, image.shape)
    return np.clip(mean + fade * (image - mean) + noise, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("level,sigma", [(14, 2), (128, 2), (40, 8)])
def test_sift_retry_skipped_on_a_featureless_noisy_frame(monkeypatch, level, sigma):
    """A black (or grey) frame with sensor noise: fewer than sift_min_features keypoints, but
    no retry, which doubled the detection time for 0-200 keypoints of noise (sigma 8)."""
    used = _contrast_thresholds(monkeypatch)
    features = FeatureExtractor(FeatureOptions()).extract(_noise(level, sigma), 0)
    assert len(features) < FeatureOptions().sift_min_features
    assert used == [None]  # the first pass only


@pytest.mark.parametrize("fade", [0.5, 0.25])
def test_sift_retry_kept_on_a_faded_textured_frame(monkeypatch, syn, fade):
    """Faded tissue with the same sensor noise: the retry is still taken, and registers the
    pair to the true homography (measured 119 / 93 inliers at fade 0.5 / 0.25; no keypoint at
    all without the retry)."""
    frames = [_faded(syn, k, fade) for k in (0, 2)]
    used = _contrast_thresholds(monkeypatch)
    options = FeatureOptions()
    f0, f2 = (FeatureExtractor(options).extract(image, k) for k, image in zip((0, 2), frames,
                                                                              strict=True))
    low = options.sift_contrast_threshold_low
    assert used == [None, low, None, low]
    assert min(len(f0), len(f2)) == 200  # the retry keeps 4 x sift_min_features
    res = match_pair(f2, f0, syn.size)
    assert res.ok, res.status
    assert res.n_inliers >= 50
    true = np.linalg.inv(syn.homographies[2]) @ syn.homographies[0]  # frame 0 -> frame 2
    assert frame_errors(res.H_lm[None], (true / true[2, 2])[None], *syn.size)[0] < 0.5


def test_structure_to_noise_of_noise_texture_and_flat_frames(syn):
    import cv2

    from fusedmosaic.registration.features import SIFT_RETRY_MIN_STRUCTURE, structure_to_noise

    for level, sigma in ((14, 1), (128, 4), (40, 16)):  # ~1 whatever the noise's level
        grey = cv2.cvtColor(_noise(level, sigma, seed=level), cv2.COLOR_BGR2GRAY)
        assert structure_to_noise(grey) == pytest.approx(1.0, abs=0.05)
    mask = np.zeros((SIZE, SIZE), np.uint8)
    cv2.circle(mask, (SIZE // 2, SIZE // 2), 180, 255, -1)
    grey[mask == 0] = 0  # a black border outside the field of view, kept out by the mask
    assert structure_to_noise(grey, cv2.erode(mask, np.ones((13, 13), np.uint8))) == (
        pytest.approx(1.0, abs=0.05))
    faded = cv2.cvtColor(_faded(syn, 0, 0.25), cv2.COLOR_BGR2GRAY)
    assert structure_to_noise(faded) > 2 * SIFT_RETRY_MIN_STRUCTURE  # measured 3.5
    clean = cv2.cvtColor(syn.render(0, noise=False), cv2.COLOR_BGR2GRAY)
    assert structure_to_noise(clean) > structure_to_noise(faded)
    flat = np.full((64, 64), 90, np.uint8)
    assert structure_to_noise(flat) == 0.0
    assert structure_to_noise(grey, np.zeros_like(mask)) == 0.0  # nothing inside the mask
