"""Specular highlights (in-vivo fetoscopy: the scope's light fibres mirrored in wet tissue):
the simulator's highlights, their detection (registration.features.specular_mask), no keypoints
on them, and mosaics that do not paste them (BlendOptions.mask_specular), against the
simulator's truth: the same frames rendered without the lights."""

import json

import cv2
import numpy as np
import pytest

from fusedmosaic.cli import main
from fusedmosaic.compositing import BlendOptions, frame_gains, render_mosaic
from fusedmosaic.registration.features import FeatureExtractor, FeatureOptions, specular_mask
from fusedmosaic.simulation import FetoscopyOptions, generate_fetoscopy

SIZE = 240


def scenes(motion: str, seed: int, lights: int = 3, **kw):
    """The same sequence with and without highlights (same texture, path and noise); syn: an
    eighth of a lap, ~30 px between frames."""
    if motion == "syn":
        kw.setdefault("laps", 0.125)
    base = dict(motion=motion, n_frames=24, width=SIZE, height=SIZE, seed=seed, **kw)
    return (generate_fetoscopy(FetoscopyOptions(specular_lights=lights, **base)),
            generate_fetoscopy(FetoscopyOptions(**base)))


def test_highlight_sits_where_the_light_is_mirrored():
    """Camera looking straight down at the plane from h mm, a light l mm off the optical axis:
    its mirror image lies 2h below, so the highlight is the plane point halfway between, seen
    at f (l / 2) / h px from the principal point, in the light's direction."""
    s, _ = scenes("syn", 0, lights=1, light_offset_mm=2.0)
    f, cx, cy = s.camera_matrix[0, 0], s.camera_matrix[0, 2], s.camera_matrix[1, 2]
    h = s.options.distance_mm
    r = f * (2.0 / 2.0) / h
    expected = [cx + r * np.cos(np.pi / 4), cy + r * np.sin(np.pi / 4)]
    for k in (0, 11):
        np.testing.assert_allclose(s.highlight_centres(k), [expected], atol=1e-6)


@pytest.mark.parametrize("motion,seed", [("syn", 0), ("handheld", 1), ("handheld", 2)])
def test_specular_mask_covers_the_simulated_highlights(motion, seed):
    """Every pixel the lights brighten by >= 20 grey levels is masked (inside the field of
    view), and the mask is at most 4x that area; frames without lights have no mask."""
    lit, plain = scenes(motion, seed)
    fov = lit.fov_mask()
    seen = 0
    for k in range(0, lit.n_frames, 4):
        truth = lit.specular_light(k) >= 20.0
        if fov is not None:
            truth &= fov
        found = specular_mask(lit.render(k))
        assert specular_mask(plain.render(k)) is None
        if not truth.any():
            continue
        seen += 1
        assert found is not None, f"frame {k}: highlight not found"
        found = found > 0
        missed = int((truth & ~found).sum())
        assert missed <= 0.005 * truth.sum(), f"frame {k}: {missed} of {truth.sum()} px missed"
        assert found.sum() <= 4.0 * truth.sum(), f"frame {k}: {found.sum()} px masked"
    assert seen >= 3


def test_specular_mask_of_gray_frames_and_bad_input():
    gray = np.full((60, 80), 100, np.uint8)
    assert specular_mask(gray) is None
    cv2.circle(gray, (40, 30), 4, 255, -1)
    found = specular_mask(gray)
    assert found.shape == gray.shape and found[30, 40] == 255 and found[30, 52] == 0
    red = np.zeros((60, 80, 3), np.uint8)
    red[:, :, 2] = 255  # a saturated red channel is tissue, not a reflection
    assert specular_mask(red) is None
    with pytest.raises(ValueError, match=r"specular_mask: expected a uint8 .* float64"):
        specular_mask(gray.astype(np.float64))


@pytest.mark.parametrize("detector", ["sift", "orb"])
def test_no_keypoints_on_highlights(detector):
    lit, _ = scenes("syn", 0)
    k = 5
    truth = lit.specular_light(k) >= 20.0
    image = lit.render(k)
    masked = FeatureExtractor(FeatureOptions(detector=detector)).extract(image, k)
    kept = FeatureExtractor(FeatureOptions(detector=detector, mask_specular=False)).extract(
        image, k)

    def on_highlight(features):
        p = np.rint(features.points).astype(int)
        return int(truth[p[:, 1], p[:, 0]].sum())

    assert on_highlight(kept) >= 1  # the highlight does make keypoints ...
    assert on_highlight(masked) == 0  # ... which the default leaves out
    assert len(masked) >= 0.8 * len(kept)


@pytest.mark.parametrize("blend", ["linear", "multiband", "average", "last"])
def test_mosaic_leaves_the_highlights_out(blend):
    """Composed with the true homographies, the mosaic of lit frames is the mosaic of the same
    frames without lights to within a few grey levels where the highlights were (other frames
    see the tissue there); kept, they leave a white trail."""
    lit, plain = scenes("syn", 0)
    frames = [lit.render(k, noise=False) for k in range(lit.n_frames)]
    truth = render_mosaic([plain.render(k, noise=False) for k in range(plain.n_frames)],
                          plain.homographies, SIZE, SIZE, blend=blend)
    masked = render_mosaic(frames, lit.homographies, SIZE, SIZE,
                           blend=BlendOptions(blend, mask_specular=True))
    kept = render_mosaic(frames, lit.homographies, SIZE, SIZE, blend=blend)
    assert masked.image.shape == truth.image.shape == kept.image.shape
    where = truth.covered & masked.covered
    excess_kept = kept.image.astype(float) - truth.image
    trail = where & (excess_kept.min(axis=2) > 20)  # where the kept highlights show
    assert trail.sum() > 200
    excess = np.abs(masked.image.astype(float) - truth.image)[trail]
    # measured p99 1-2 grey levels; multiband 7 (its low bands reach past the seams)
    tolerance = 10.0 if blend == "multiband" else 3.0
    assert np.percentile(excess, 99) <= tolerance, f"{blend}: p99 {np.percentile(excess, 99)}"
    assert excess.mean() <= tolerance / 3


@pytest.mark.parametrize("seed", [1, 2])
def test_gain_compensation_leaves_the_highlights_out(seed):
    """Gain compensation (Brown & Lowe) on a lit hand-held sequence: the highlights move with
    the camera, so kept in the overlap means they make each frame look brighter than its
    neighbours see it there and bias its gain (measured up to 0.030 / 0.038 off the gains of
    the same frames without lights, seeds 1 / 2); masked as the blend masks them, the gains are
    those without lights (measured 0.0006 / 0.0004), and a frame without highlights gives the
    same gains either way."""
    lit, plain = scenes("handheld", seed)
    fov = lit.fov_mask()

    def gains(s, mask_specular):
        return frame_gains([s.render(k) for k in range(s.n_frames)], s.homographies, SIZE, SIZE,
                           mask=fov, mask_specular=mask_specular)

    truth = gains(plain, False)
    np.testing.assert_array_equal(gains(plain, True), truth)
    kept = np.abs(gains(lit, False) - truth).max()
    masked = np.abs(gains(lit, True) - truth).max()
    assert kept > 0.01  # the defect the masking removes
    assert masked <= 0.003, f"masked highlights: gains {masked:.4f} off (kept: {kept:.4f})"


def test_one_pass_multiband_keeps_the_highlights():
    """A one-pass iterable cannot be read for the seams first: documented fallback, no crash."""
    lit, _ = scenes("syn", 0)
    frames = [lit.render(k, noise=False) for k in range(8)]
    G = lit.homographies[:8]
    options = BlendOptions("multiband", mask_specular=True)
    once = render_mosaic(((k, f) for k, f in enumerate(frames)), G, SIZE, SIZE, blend=options)
    plain = render_mosaic(frames, G, SIZE, SIZE, blend="multiband")
    np.testing.assert_array_equal(once.image, plain.image)


@pytest.mark.parametrize("value,match", [(-1, "0..8"), (9, "0..8"), (1.5, "0..8")])
def test_bad_specular_options(value, match):
    with pytest.raises(ValueError, match=rf"FetoscopyOptions.specular_lights: .*{match}"):
        generate_fetoscopy(FetoscopyOptions(n_frames=3, specular_lights=value))
    with pytest.raises(ValueError, match="FetoscopyOptions.specular_sigma_px: must be > 0"):
        generate_fetoscopy(FetoscopyOptions(n_frames=3, specular_sigma_px=0.0))


@pytest.mark.slow
def test_run_with_highlights(tmp_path, capsys):
    """lba-emt on a lit hand-held sequence: accurate, the highlights masked and reported;
    --keep-specular turns both off; the pCLE methods refuse it (no feature detection)."""
    data, out, kept = tmp_path / "data", tmp_path / "out", tmp_path / "kept"
    assert main(["--quiet", "simulate", "fetoscopy", str(data), "--motion", "handheld",
                 "--n-frames", "50", "--specular-lights", "3", "--seed", "4"]) == 0
    assert main(["--quiet", "run", str(data), "--method", "lba-emt", "--out", str(out)]) == 0
    assert main(["--quiet", "run", str(data), "--method", "lba-emt", "--out", str(kept),
                 "--keep-specular"]) == 0
    assert main(["--quiet", "evaluate", str(out), "--truth", str(data)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["mosaic"]["mask_specular"] is True
    assert report["parameters"]["features"]["mask_specular"] is True
    kept_report = json.loads((kept / "report.json").read_text())
    assert kept_report["mosaic"]["mask_specular"] is False
    assert kept_report["parameters"]["features"]["mask_specular"] is False
    e_M = json.loads((out / "evaluation.json").read_text())["results"][0]["e_M_px"]
    assert e_M <= 0.6  # px against the simulator's truth (0.12 px on the 150-frame sequence)
    pcle = tmp_path / "pcle"
    assert main(["--quiet", "simulate", "pcle", str(pcle), "--n-frames", "5"]) == 0
    assert main(["--quiet", "run", str(pcle), "--method", "ncc", "--out", str(tmp_path / "o2"),
                 "--keep-specular"]) == 2
    assert "--keep-specular apply to lba-emt, ba-emt, ba, emt, pairwise, not ncc" in (
        capsys.readouterr().err)
    assert not (tmp_path / "o2").exists()


@pytest.mark.parametrize("blend", ["linear", "multiband", "average", "last"])
def test_a_highlight_no_other_frame_sees_is_no_hole(blend):
    """One frame, a highlight 14 px from its edge (where the feathering weight is small): the
    mosaic shows it (filled from the tissue around), it leaves no empty pixel."""
    rng = np.random.default_rng(0)
    frame = np.clip(rng.normal(120, 20, (120, 160, 3)), 0, 255).astype(np.uint8)
    cv2.circle(frame, (14, 60), 6, (255, 255, 255), -1)
    plain = render_mosaic([frame], np.eye(3)[None], 160, 120, blend=blend)
    masked = render_mosaic([frame], np.eye(3)[None], 160, 120,
                           blend=BlendOptions(blend, mask_specular=True))
    assert (plain.covered & ~masked.covered).sum() == 0
    assert masked.image[60, 14].max() < 200  # not the white spot: the tissue around


def _count_specular_masks(monkeypatch) -> list:
    """Spies on registration.features.specular_mask (the compositor imports it when called):
    the list of the images it was called with."""
    import fusedmosaic.registration.features as features

    calls, found = [], features.specular_mask

    def spy(image, **kw):
        calls.append(image)
        return found(image, **kw)

    monkeypatch.setattr(features, "specular_mask", spy)
    return calls


def test_specular_masks_keep_each_frames_mask():
    """SpecularMasks gives specular_mask's own mask, kept packed (bounding box, 1 bit per
    pixel) within its byte budget; over budget it finds the mask again."""
    from fusedmosaic.compositing import SpecularMasks

    lit, plain = scenes("handheld", 1)
    masks = SpecularMasks()
    lit_frames = [lit.render(k) for k in range(0, lit.n_frames, 4)]
    for k, image in enumerate(lit_frames):
        for _ in range(2):  # found, then kept
            found = masks.get(k, image)
            expected = specular_mask(image)
            assert (found is None) == (expected is None)
            if expected is not None:
                np.testing.assert_array_equal(found, expected)
    assert masks.get(99, plain.render(0)) is None and masks.get(99, plain.render(0)) is None
    assert len(masks) == len(lit_frames) + 1
    assert 0 < masks.nbytes <= len(lit_frames) * SIZE * SIZE / 8
    none_kept = SpecularMasks(max_bytes=0)
    np.testing.assert_array_equal(none_kept.get(0, lit_frames[1]), specular_mask(lit_frames[1]))
    assert none_kept.nbytes == 0


@pytest.mark.parametrize("blend", ["linear", "multiband"])
def test_gains_and_mosaic_find_each_frames_highlights_once(monkeypatch, tmp_path, blend):
    """With gain compensation the thumbnails and the warper need every frame's highlights:
    found once per frame (a shared SpecularMasks), not once for the gains and again for the
    mosaic (multiband: again for its seams), and the same mosaic as finding them each time."""
    from fusedmosaic.compositing import SpecularMasks, write_mosaic_png
    from fusedmosaic.compositing.canvas import CanvasOptions

    lit, _ = scenes("handheld", 1)
    frames = [lit.render(k) for k in range(12)]
    G, fov = lit.homographies[:12], lit.fov_mask()
    options = BlendOptions(blend, mask_specular=True, gain_compensation=True)
    kept_none = SpecularMasks(max_bytes=0)  # found every time they are needed, as before
    gains = frame_gains(frames, G, SIZE, SIZE, mask=fov, mask_specular=True,
                        highlights=kept_none)
    expected = render_mosaic(frames, G, SIZE, SIZE, mask=fov, blend=options, gains=gains,
                             highlights=kept_none)

    calls = _count_specular_masks(monkeypatch)
    masks = SpecularMasks()
    shared_gains = frame_gains(frames, G, SIZE, SIZE, mask=fov, mask_specular=True,
                               highlights=masks)
    mosaic = render_mosaic(frames, G, SIZE, SIZE, mask=fov, blend=options, gains=shared_gains,
                           highlights=masks)
    assert len(calls) == len(frames)
    np.testing.assert_array_equal(shared_gains, gains)
    np.testing.assert_array_equal(mosaic.image, expected.image)
    # tile by tile (frames warped again for neighbouring tiles): still once per frame
    canvas = CanvasOptions(tile_size=64, cache_mb=0.0)
    paths = tmp_path / "each_time.png", tmp_path / "tiled.png"
    write_mosaic_png(paths[0], frames, G, SIZE, SIZE, mask=fov, blend=options, gains=gains,
                     canvas=canvas, highlights=kept_none)
    calls.clear()
    write_mosaic_png(paths[1], frames, G, SIZE, SIZE, mask=fov, blend=options, gains=gains,
                     canvas=canvas)
    assert len(calls) == len(frames)
    np.testing.assert_array_equal(*(cv2.imread(str(path)) for path in paths))


def test_run_with_gain_compensation_finds_each_frames_highlights_once(monkeypatch, tmp_path):
    """`fusedmosaic run --gain-compensation`: each shown frame's highlights are found once for
    the gains and the mosaic together (the colour frames; emt's plane estimation finds them
    in its grey frames, apart)."""
    data, out = tmp_path / "data", tmp_path / "out"
    assert main(["--quiet", "simulate", "fetoscopy", str(data), "--motion", "handheld",
                 "--n-frames", "12", "--width", "160", "--height", "160",
                 "--specular-lights", "3", "--seed", "1"]) == 0
    calls = _count_specular_masks(monkeypatch)
    assert main(["--quiet", "run", str(data), "--method", "emt", "--gain-compensation",
                 "--no-report", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["mosaic"]["mask_specular"] is True
    colour = [image for image in calls if image.ndim == 3]
    assert len(colour) == report["mosaic"]["frames_shown"] == 12
