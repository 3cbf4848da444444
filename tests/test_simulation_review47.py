"""Review 47 of the simulators: the lens's ideal pixel grid built in bounded blocks and only
after the cheap texture refusal; noisy frames rounded (not truncated) to grey levels; list and
bool options of the wrong type refused naming the option."""

from __future__ import annotations

import re
from dataclasses import fields

import cv2
import numpy as np
import pytest

import fusedmosaic.simulation._lens as lens_module
import fusedmosaic.simulation.fetoscopy as fetoscopy_module
from fusedmosaic.cli import main
from fusedmosaic.io.calibration import project_points
from fusedmosaic.simulation import (
    CheckerboardOptions,
    FetoscopyOptions,
    PcleOptions,
    generate_fetoscopy,
    generate_pcle,
)

BARREL = [-0.30, 0.10, 0.0008, -0.0005]  # a fetoscope's barrel lens (tests/test_lens.py's)
# 3000x3000 frames need a placenta texture that takes minutes and gigabytes to draw: refused
# from the frame's size alone; through this lens the grid cost 5 KB a pixel before that.
OVERSIZED = dict(width=3000, height=3000, n_frames=5)


def _one_shot_grid(K, d, lens_model, width, height, S):
    """The ideal pixel grid as it was built before review 47: every sub-pixel sample in one
    cv2.undistortPoints call (the values the blocks must reproduce)."""
    v, u = np.mgrid[0:height * S, 0:width * S].astype(np.float64)
    raw = np.stack([(u + 0.5) / S - 0.5, (v + 0.5) / S - 0.5], -1).reshape(-1, 1, 2)
    if lens_model == "fisheye":
        ideal = cv2.fisheye.undistortPoints(raw, K, d.reshape(4, 1), R=np.eye(3), P=K,
                                            criteria=lens_module._CRITERIA)
    else:
        ideal = cv2.undistortPoints(raw, K, d, P=K, criteria=lens_module._CRITERIA)
    return ideal.reshape(height * S, width * S, 2)


@pytest.mark.parametrize("lens_model, d", [
    ("pinhole", np.array(BARREL)),
    ("pinhole", np.array(BARREL + [0.01])),
    ("fisheye", np.array([0.05, -0.02, 0.01, 0.0])),
])
def test_blocked_grid_equals_the_one_shot_grid(monkeypatch, lens_model, d):
    """Blocks of 2 sub-pixel rows (250 samples // 120 per row) and a last, shorter block: the
    same values as one call over the whole grid, bit for bit (undistortion is per point)."""
    monkeypatch.setattr(lens_module, "GRID_BLOCK_SAMPLES", 250)
    width, height, S = 40, 31, 3
    K = np.array([[48.0, 0.0, 19.7], [0.0, 47.0, 15.2], [0.0, 0.0, 1.0]])
    grid = lens_module.ideal_pixel_grid(K, d, lens_model, width, height, S, "lens")
    assert grid.shape == (93, 120, 2)
    np.testing.assert_array_equal(grid, _one_shot_grid(K, d, lens_model, width, height, S))


def test_blocked_grid_fold_check_in_a_later_block(monkeypatch):
    """The fold check runs in every block: a lens folding at the frame's corners (the last
    block's rows) is refused as before."""
    monkeypatch.setattr(lens_module, "GRID_BLOCK_SAMPLES", 250)
    K = np.array([[48.0, 0.0, 19.5], [0.0, 48.0, 15.0], [0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match=r"^lens: \[-3\.0, 0\.0, 0\.0, 0\.0\] is not "
                                         r"invertible over the 40x31 frame \(the model folds "
                                         r"over\); use a milder lens$"):
        lens_module.ideal_pixel_grid(K, np.array([-3.0, 0, 0, 0]), "pinhole", 40, 31, 3, "lens")


@pytest.mark.parametrize("lens_model, d", [
    ("pinhole", [-0.3, 0.1, 0.001, -0.002]),
    ("pinhole", [-0.3, 0.1, 0.001, -0.002, 0.05]),
    ("pinhole", [-0.3, 0.1, 0.001, -0.002, 0.05, 0.1, -0.02, 0.01]),
    ("pinhole", [-0.3, 0.1, 0.001, -0.002, 0.05, 0.1, -0.02, 0.01, 1e-3, -2e-3, 3e-3, 1e-4]),
    ("fisheye", [-0.05, 0.01, 0.002, -0.001]),
])
def test_distort_rays_is_opencvs_projection(lens_model, d):
    """The fold check's Jacobian-free projection equals cv2.projectPoints /
    cv2.fisheye.projectPoints to 1e-9 px, on the optical axis too."""
    rng = np.random.default_rng(1)
    K = np.array([[500.0, 0.0, 210.3], [0.0, 470.0, 190.7], [0.0, 0.0, 1.0]])
    rays = np.hstack([rng.uniform(-0.8, 0.8, (2000, 2)), np.ones((2000, 1))])
    rays[0, :2], rays[1, :2] = 0.0, (1e-9, 0.0)
    d = np.array(d)
    np.testing.assert_allclose(lens_module.distort_rays(rays, K, d, lens_model),
                               project_points(rays, K, d, lens_model), rtol=0, atol=1e-9)


def _no_grid(*args, **kwargs):
    raise AssertionError("the ideal pixel grid was built for a refused request")


def test_oversized_lens_request_refused_before_the_grid(monkeypatch):
    """With --lens-distortion, a request whose texture is refused gets the texture's --width
    error without the grid being built (it took a minute and then failed with a MemoryError
    traceback at 3000x3000), as without a lens."""
    monkeypatch.setattr(fetoscopy_module, "ideal_pixel_grid", _no_grid)
    expected = (r"^FetoscopyOptions\.width: the camera path needs a \d+x\d+ px texture with "
                r"[\d.]+ px vessels .* which takes about \d+ s and [\d.]+ GB to draw; at most "
                r"60 s and 3 GB \(textures\.placenta_texture_cost\): lower "
                r"FetoscopyOptions\.focal_factor, FetoscopyOptions\.width or "
                r"FetoscopyOptions\.radius_mm, or raise FetoscopyOptions\.distance_mm$")
    with pytest.raises(ValueError, match=expected):
        generate_fetoscopy(FetoscopyOptions(**OVERSIZED))
    with pytest.raises(ValueError, match=expected):
        generate_fetoscopy(FetoscopyOptions(**OVERSIZED, lens_distortion=BARREL))


def test_oversized_lens_request_refused_by_the_cli(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(fetoscopy_module, "ideal_pixel_grid", _no_grid)
    out = tmp_path / "big"
    assert main(["simulate", "fetoscopy", str(out), "--width", "3000", "--height", "3000",
                 "--n-frames", "5", "--lens-distortion", *map(str, BARREL)]) == 2
    err = capsys.readouterr().err
    assert re.search(r"error: --width: the camera path needs a \d+x\d+ px texture", err), err
    assert not out.exists()


def test_folding_lens_refused_from_the_border_before_the_view(monkeypatch):
    """The border's fold check comes first: a lens folding at the frame's edge is blamed as
    before (not on the view its garbage undistortion would give), without building the grid."""
    monkeypatch.setattr(fetoscopy_module, "ideal_pixel_grid", _no_grid)
    with pytest.raises(ValueError, match=r"^FetoscopyOptions\.lens_distortion: \[-3\.0, 0\.0, "
                                         r"0\.0, 0\.0\] is not invertible over the 400x400 "
                                         r"frame"):
        generate_fetoscopy(FetoscopyOptions(n_frames=3, lens_distortion=[-3.0, 0, 0, 0]))


# ------------------------------------------------------------------------------------------
# Finding 2: noisy frames rounded to grey levels
# ------------------------------------------------------------------------------------------


def test_fetoscopy_noise_has_no_bias():
    """Noise of std 2 rounded: the noisy frame's mean is the noise-free frame's (0.007 grey
    levels is its standard error over 160x160x3 values); truncated, it was 0.5 darker."""
    scene = generate_fetoscopy(FetoscopyOptions(n_frames=3, width=160, height=160, seed=0))
    diff = scene.render(1).astype(np.float64) - scene.render(1, noise=False)
    assert abs(diff.mean()) < 0.1


def test_fetoscopy_specular_highlights_rounded():
    """Noise-free frames with highlights: rounded, within 0.1 grey levels of the unrounded sum
    where the glow adds something and nothing saturates (truncated: 0.5 darker there)."""
    scene = generate_fetoscopy(FetoscopyOptions(n_frames=3, width=160, height=160, seed=0,
                                                specular_lights=2, fov_mask_radius=0))
    light = scene.specular_light(1)
    exact = scene.pinhole(1).astype(np.float64) + light[:, :, None]
    inside = np.broadcast_to((light > 0.01)[:, :, None], exact.shape) & (exact < 255)
    assert inside.sum() > 1000
    diff = scene.render(1, noise=False) - exact
    assert abs(diff[inside].mean()) < 0.1


def test_pcle_frames_rounded():
    """pCLE frames are the grey levels rounded: the same mean within 0.1 (truncated: 0.5
    darker)."""
    scene = generate_pcle(PcleOptions(n_frames=4, width=96, height=96, seed=0))
    for k in range(scene.n_frames):
        exact = np.clip(scene.grey_levels(k).astype(np.float64), 0, 255)
        assert abs((scene.render(k) - exact).mean()) < 0.1


# ------------------------------------------------------------------------------------------
# Finding 3: list and bool options of the wrong type
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("options, message", [
    (FetoscopyOptions(n_frames=20, black_frames=7),
     "FetoscopyOptions.black_frames: expected a list of frame indices, got 7"),
    (FetoscopyOptions(n_frames=20, tracker_gap=5),
     "FetoscopyOptions.tracker_gap: expected a list of frame indices, got 5"),
    (FetoscopyOptions(n_frames=20, black_frames="12"),
     "FetoscopyOptions.black_frames: expected a list of frame indices, got '12'"),
    (FetoscopyOptions(lens_distortion=["a", 0, 0, 0]),
     "FetoscopyOptions.lens_distortion: expected a list of numbers, got ['a', 0, 0, 0]"),
    (CheckerboardOptions(fisheye=0.1),
     "CheckerboardOptions.fisheye: expected a list of numbers, got 0.1"),
    (PcleOptions(n_frames=40, contact_loss="no"),
     "PcleOptions.contact_loss: must be True or False, got 'no'"),
    (PcleOptions(n_frames=40, stick_slip=0.0),
     "PcleOptions.stick_slip: must be True or False, got 0.0"),
])
def test_list_and_bool_options_of_the_wrong_type(options, message):
    with pytest.raises(ValueError, match="^" + re.escape(message) + "$"):
        options.validate()


def test_lists_may_be_tuples_or_arrays_and_bools_numpy_bools():
    """The type checks take what a caller may pass for these (tuples, arrays, NumPy bools)."""
    FetoscopyOptions(n_frames=20, black_frames=(3, 4), tracker_gap=np.array([8, 12]),
                     lens_distortion=np.array(BARREL)).validate()
    PcleOptions(n_frames=40, contact_loss=np.False_).validate()
    with pytest.raises(ValueError, match=r"^FetoscopyOptions\.black_frames: expected a list of "
                                         r"frame indices, got array\(\[\[3\]\]\)$"):
        FetoscopyOptions(n_frames=20, black_frames=np.array([[3]])).validate()
    with pytest.raises(ValueError, match=r"^PcleOptions\.contact_loss: must be True or False, "
                                         r"got 1$"):
        PcleOptions(n_frames=40, contact_loss=1).validate()


def test_negative_laps_circle_the_other_way():
    """laps < 0 is documented as the same circle the other way round, and is: the camera's
    path mirrored across the circle's x axis, the ground truth mirrored with it."""
    help_text = {f.name: f.metadata["help"] for f in fields(FetoscopyOptions)}["laps"]
    assert "negative: the same circle the other way round, 0: the camera rests" in help_text
    size = dict(n_frames=10, width=96, height=96)
    ahead = generate_fetoscopy(FetoscopyOptions(**size, laps=1.0))
    back = generate_fetoscopy(FetoscopyOptions(**size, laps=-1.0))
    np.testing.assert_array_equal(back.poses[:, 3:], ahead.poses[:, 3:] * [1, -1, 1])
    np.testing.assert_allclose(back.homographies, ahead.homographies * [[1, 1, 1],
                                                                         [1, 1, -1],
                                                                         [1, 1, 1]], atol=1e-9)
