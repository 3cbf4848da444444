"""NCC forward/backward registration and aligned-overlap SSIM (paper 004, Sec. II-C, III-D)."""

import cv2
import numpy as np
import pytest
from scipy import ndimage
from skimage.metrics import structural_similarity as skimage_ssim

from fusedmosaic.registration.ncc import (
    NccResult,
    aligned_overlap_ssim,
    register_ncc,
    structural_similarity,
)

H, W = 224, 256  # half the pCLE export size (448x512), keeps the tests fast
SUBPIXEL_TOL = 0.1  # px


def smooth_texture(shape, sigma, seed):
    """Periodic, band-limited random texture in [0, 255] (cell-scale blobs of ~sigma px)."""
    rng = np.random.default_rng(seed)
    t = ndimage.gaussian_filter(rng.standard_normal(shape), sigma, mode="wrap")
    return (t - t.min()) / (t.max() - t.min()) * 255.0


def fourier_shift(image, d):
    """Exact sub-pixel shift of a periodic image: out(p) = image(p + d), d = (dx, dy)."""
    spectrum = ndimage.fourier_shift(np.fft.fft2(image), (-d[1], -d[0]))
    return np.fft.ifft2(spectrum).real


@pytest.fixture(scope="module")
def scene():
    """A large periodic scene; frames are crops of it."""
    return smooth_texture((H + 128, W + 128), 3.0, seed=11)


def frame_pair(scene, d, noise=0.0, seed=0):
    """Frame i-1 at the scene origin and frame i with the probe moved by d (mosaic convention:
    mosaic pixel = frame pixel + X, so frame i shows the content moved by -d)."""
    rng = np.random.default_rng(seed)
    shifted = fourier_shift(scene, d)
    previous = scene[64 : 64 + H, 64 : 64 + W]
    current = shifted[64 : 64 + H, 64 : 64 + W]
    if noise:
        previous = previous + rng.normal(0, noise, previous.shape)
        current = current + rng.normal(0, noise, current.shape)
    return previous.astype(np.float32), current.astype(np.float32)


@pytest.mark.parametrize("d", [(0, 0), (7, -4), (-12, 9), (25, 18), (-30, -20), (3, 0)])
@pytest.mark.parametrize("levels", [0, 2])
def test_integer_shifts_recovered(scene, d, levels):
    prev, curr = frame_pair(scene, d)
    res = register_ncc(prev, curr, pyramid_levels=levels)
    assert isinstance(res, NccResult)
    assert res.dx.shape == (2,) and res.dx.dtype == np.float64
    np.testing.assert_allclose(res.dx, d, atol=0.02)
    assert res.score > 0.99


def test_subpixel_shifts_both_signs(scene):
    rng = np.random.default_rng(5)
    shifts = rng.uniform(-25, 25, (8, 2))
    shifts[0] = (0.5, -0.5)
    shifts[1] = (-0.25, 0.75)
    errors = []
    for d in shifts:
        res = register_ncc(*frame_pair(scene, d, noise=2.0))
        errors.append(np.abs(res.dx - d).max())
    assert max(errors) < SUBPIXEL_TOL, errors


def test_subpixel_shift_made_with_warp_affine():
    img = smooth_texture((H, W), 3.0, seed=2).astype(np.float32)
    d = np.array([4.3, -6.7])
    m = np.float32([[1, 0, -d[0]], [0, 1, -d[1]]])  # dst(p) = img(p + d)
    moved = cv2.warpAffine(img, m, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    res = register_ncc(img, moved)
    np.testing.assert_allclose(res.dx, d, atol=SUBPIXEL_TOL)


def test_position_convention_matches_eq1(scene):
    """Frames cropped at probe positions X(i) satisfy X(i) = X(i-1) + dx (Eq. 1)."""
    positions = np.array([[10, 20], [17, 14], [9, 25], [30, 31]])
    frames = [scene[y : y + H, x : x + W].astype(np.uint8) for x, y in positions]
    for i in range(1, len(frames)):
        res = register_ncc(frames[i - 1], frames[i])
        np.testing.assert_allclose(res.dx, positions[i] - positions[i - 1], atol=0.05)


def test_forward_backward_average_and_antisymmetry(scene):
    d = np.array([6.4, -3.3])
    prev, curr = frame_pair(scene, d, noise=4.0, seed=1)
    res = register_ncc(prev, curr)
    np.testing.assert_allclose(res.dx, 0.5 * (res.dx_forward + res.dx_backward), atol=1e-12)
    np.testing.assert_allclose(res.dx_forward, d, atol=SUBPIXEL_TOL)
    np.testing.assert_allclose(res.dx_backward, d, atol=SUBPIXEL_TOL)
    assert res.disagreement < SUBPIXEL_TOL
    assert res.score == pytest.approx(0.5 * (res.score_forward + res.score_backward))
    swapped = register_ncc(curr, prev)
    np.testing.assert_allclose(swapped.dx, -res.dx, atol=1e-6)


def test_uint8_and_float_agree(scene):
    prev, curr = frame_pair(scene, (5.5, 2.25))
    a = register_ncc(prev, curr).dx
    b = register_ncc(np.rint(prev).astype(np.uint8), np.rint(curr).astype(np.uint8)).dx
    c = register_ncc(prev.astype(np.float64) / 255.0, curr.astype(np.float64) / 255.0).dx
    np.testing.assert_allclose(b, a, atol=0.02)
    np.testing.assert_allclose(c, a, atol=1e-3)


def test_pyramid_and_exhaustive_agree(scene):
    prev, curr = frame_pair(scene, (-18.3, 11.6), noise=3.0)
    np.testing.assert_allclose(
        register_ncc(prev, curr, pyramid_levels=2).dx,
        register_ncc(prev, curr, pyramid_levels=0).dx,
        atol=1e-9,
    )


def test_presmoothing_keeps_accuracy_on_noisy_frames(scene):
    d = np.array([-9.6, 4.2])
    prev, curr = frame_pair(scene, d, noise=25.0, seed=2)
    np.testing.assert_allclose(register_ncc(prev, curr, presmooth_sigma=1.5).dx, d, atol=0.15)


def test_max_displacement_bounds_the_search(scene):
    prev, curr = frame_pair(scene, (8.0, -5.0))
    np.testing.assert_allclose(register_ncc(prev, curr, max_displacement=10).dx, (8, -5), atol=0.02)
    far_prev, far_curr = frame_pair(scene, (30.0, 0.0))
    res = register_ncc(far_prev, far_curr, max_displacement=10)
    assert np.all(np.abs(res.dx) <= 10.0)
    assert np.abs(res.dx - (30.0, 0.0)).max() > 15.0


def test_noise_frame_gives_low_score(scene):
    prev, _ = frame_pair(scene, (0, 0))
    noise = np.random.default_rng(4).uniform(0, 255, prev.shape).astype(np.float32)
    assert register_ncc(prev, noise).score < 0.3


def test_featureless_frame_fails_softly(scene):
    prev, _ = frame_pair(scene, (0, 0))
    flat = np.full_like(prev, 100.0)
    res = register_ncc(prev, flat)
    assert np.isnan(res.dx).all() and res.score == 0.0


def test_different_sizes_name_both_shapes():
    with pytest.raises(ValueError, match=r"previous has shape \(40, 50\).*current has shape"):
        register_ncc(np.zeros((40, 50), np.uint8), np.zeros((40, 60), np.uint8))


@pytest.mark.parametrize(
    ("previous", "kwargs", "message"),
    [
        (np.zeros((40, 50, 3), np.uint8), {}, r"previous: expected a 2-D grayscale image"),
        (np.full((40, 50), np.nan), {}, r"previous: image contains NaN"),
        (np.zeros((40, 50), np.float32), {"template_fraction": 1.2}, r"template_fraction"),
        (np.zeros((40, 50), np.float32), {"pyramid_levels": -1}, r"pyramid_levels"),
        (np.zeros((40, 50), np.float32), {"max_displacement": -2}, r"max_displacement"),
        (np.zeros((40, 50), np.float32), {"presmooth_sigma": -1.0}, r"presmooth_sigma must be"),
        (np.zeros((40, 50), np.float32), {"template_fraction": 0.02}, r"gives a 0x1 template"),
    ],
)
def test_bad_inputs(previous, kwargs, message):
    current = np.zeros(previous.shape[:2], np.float32)
    if previous.ndim == 3:
        current = previous.copy()
    with pytest.raises(ValueError, match=message):
        register_ncc(previous, current, **kwargs)


# --- c_match: SSIM of the aligned overlap ---------------------------------------------------


def test_ssim_matches_skimage():
    rng = np.random.default_rng(8)
    a = smooth_texture((90, 110), 2.0, seed=3).astype(np.float32)
    b = np.clip(a + rng.normal(0, 20, a.shape), 0, 255).astype(np.float32)
    expected = skimage_ssim(a.astype(np.float64), b.astype(np.float64), data_range=255.0)
    assert structural_similarity(a, b, data_range=255.0) == pytest.approx(expected, abs=1e-5)


def test_ssim_high_for_aligned_identical_content(scene):
    d = np.array([12.0, -7.0])
    prev, curr = frame_pair(scene, d)
    prev8, curr8 = np.rint(prev).astype(np.uint8), np.rint(curr).astype(np.uint8)
    assert aligned_overlap_ssim(prev8, curr8, d) > 0.98
    # wrongly aligned content scores much lower
    assert aligned_overlap_ssim(prev8, curr8, d + (6, 6)) < 0.5


def test_ssim_low_for_noise(scene):
    prev, _ = frame_pair(scene, (0, 0))
    noise = np.random.default_rng(9).uniform(0, 255, prev.shape).astype(np.uint8)
    value = aligned_overlap_ssim(prev.astype(np.uint8), noise, (0.0, 0.0))
    assert 0.0 <= value < 0.1


def test_ssim_downsampled_and_degenerate_cases(scene):
    d = np.array([3.0, 4.0])
    prev, curr = frame_pair(scene, d)
    assert aligned_overlap_ssim(prev, curr, d, downsample=2) > 0.98
    assert aligned_overlap_ssim(prev, curr, (np.nan, 0.0)) == 0.0
    assert aligned_overlap_ssim(prev, curr, (W - 5.0, 0.0)) == 0.0  # no usable overlap
    anti = 255.0 - prev  # negative correlation is clipped to 0
    assert aligned_overlap_ssim(prev, anti, (0.0, 0.0)) == 0.0


def test_ssim_bad_inputs():
    a = np.zeros((40, 50), np.uint8)
    with pytest.raises(ValueError, match=r"previous has shape \(40, 50\), current has shape"):
        aligned_overlap_ssim(a, np.zeros((41, 50), np.uint8), (0, 0))
    with pytest.raises(ValueError, match=r"dx: expected shape \(2,\)"):
        aligned_overlap_ssim(a, a, (0, 0, 0))
    with pytest.raises(ValueError, match=r"downsample must be >= 1"):
        aligned_overlap_ssim(a, a, (0, 0), downsample=0)


def test_wide_range_fallback_beyond_the_primary_search(scene):
    """A jump beyond the 3/5 template's +-1/5 frame (a stick-slip release) is clipped by the
    primary search; the 2/5 retry (+-3/10 frame) recovers it, flagged as a fallback."""
    d = (65.0, -55.0)  # primary range at 256x224: +-51 x, +-45 y; retry: +-77 x, +-67 y
    prev, curr = frame_pair(scene, d, noise=2.0)
    paper = register_ncc(prev, curr, fallback_template_fraction=None)
    assert np.abs(paper.dx - d).max() > 5.0  # clipped at the primary range
    res = register_ncc(prev, curr)
    assert res.fallback and res.consistent
    np.testing.assert_allclose(res.dx, d, atol=SUBPIXEL_TOL)
    # ordinary shifts never trigger the retry
    small = register_ncc(*frame_pair(scene, (12.0, -7.0), noise=2.0))
    assert not small.fallback and small.consistent


def test_inconsistent_directions_are_flagged():
    """Forward and backward peaks far apart (pure noise, no common content): not consistent."""
    rng = np.random.default_rng(2)
    a, b = (rng.normal(128, 40, (H, W)).astype(np.float32) for _ in range(2))
    res = register_ncc(a, b)
    if res.disagreement > 3.0:
        assert not res.consistent
    assert register_ncc(a, b, max_disagreement=None).consistent
    with pytest.raises(ValueError, match="max_disagreement"):
        register_ncc(a, b, max_disagreement=-1.0)
    with pytest.raises(ValueError, match="fallback_template_fraction"):
        register_ncc(a, b, fallback_template_fraction=1.5)


@pytest.mark.parametrize("shape", [(448, 512), (101, 77)])
def test_second_thread_gives_the_same_numbers(shape, monkeypatch):
    """The backward search and half of the SSIM run on a second thread (ncc._SECOND): the same
    displacements, scores and SSIM as on one thread, to the last bit."""
    from fusedmosaic.registration import ncc

    rng = np.random.default_rng(3)
    a = cv2.GaussianBlur(rng.uniform(0, 255, shape), (0, 0), 2.0).astype(np.uint8)
    b = np.roll(a, (5, -7), axis=(0, 1))
    if ncc._SECOND is None:
        pytest.skip("one core: no second thread")
    threaded = (ncc.register_ncc(a, b), ncc.aligned_overlap_ssim(a, b, np.array([7.0, -5.0])))
    monkeypatch.setattr(ncc, "_SECOND", None)
    serial = (ncc.register_ncc(a, b), ncc.aligned_overlap_ssim(a, b, np.array([7.0, -5.0])))
    from dataclasses import asdict

    for name, value in asdict(threaded[0]).items():
        np.testing.assert_array_equal(value, asdict(serial[0])[name], err_msg=name)
    assert threaded[1] == serial[1] > 0.9
    np.testing.assert_allclose(threaded[0].dx, [7.0, -5.0], atol=0.05)
