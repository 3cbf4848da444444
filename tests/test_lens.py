"""Lens distortion end to end: camera.yaml's distortion_coefficients are removed before features
are detected and before frames are composed, so a distorted endoscope mosaics as a pinhole one.
Ground truth: the fetoscopy simulator rendering through OpenCV's lens model
(FetoscopyOptions.lens_distortion) against its pinhole truth."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from fusedmosaic.cli import main
from fusedmosaic.compositing import render_mosaic
from fusedmosaic.evaluation import evaluate_output, mosaic_difference
from fusedmosaic.io import Camera, UndistortedFrames, read_dataset
from fusedmosaic.io.calibration import project_points
from fusedmosaic.registration.features import FeatureExtractor
from fusedmosaic.runner import run_dataset
from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy
from fusedmosaic.simulation.fetoscopy import generate_fetoscopy

# A fetoscope's barrel lens (the checkerboard simulator's defaults).
LENS = [-0.30, 0.10, 0.0008, -0.0005]


def _camera(scene, fov=None) -> Camera:
    w, h = scene.size
    return Camera(w, h, camera_matrix=scene.camera_matrix, distortion=scene.distortion,
                  fov_mask_radius=fov)


@pytest.fixture(scope="module")
def scene():
    return generate_fetoscopy(FetoscopyOptions(n_frames=12, lens_distortion=LENS))


def test_undistorted_frame_is_the_pinhole_frame(scene):
    """Tolerance: 1.5 grey levels mean (two bilinear resamplings); the raw frame is > 4 off,
    so the lens matters at this size."""
    lens = _camera(scene).undistortion()
    inside = lens.mask > 0
    assert inside.mean() == 1.0  # barrel: every undistorted pixel has a source
    for k in (0, 3, 7):
        raw = scene.render(k, noise=False)
        ideal = scene.pinhole(k).astype(float)
        assert np.abs(lens.image(raw) - ideal)[inside].mean() < 1.5
        assert np.abs(raw - ideal)[inside].mean() > 4.0


def test_points_invert_the_lens_model_to_1e6_px(scene):
    """cv2.undistortPoints' default 5 iterations are ~0.007 px off at this lens's corners."""
    lens = _camera(scene).undistortion()
    K = scene.camera_matrix
    ideal = np.random.default_rng(0).uniform(-20, 420, (300, 2))
    rays = np.hstack([(ideal - K[:2, 2]) / K[0, 0], np.ones((300, 1))])
    raw, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, scene.distortion)
    np.testing.assert_allclose(lens.points(raw.reshape(-1, 2)), ideal, atol=1e-6)
    assert lens.points(np.zeros((0, 2))).shape == (0, 2)


def test_valid_mask_follows_the_lens_and_field_of_view(scene):
    w, h = scene.size
    K = scene.camera_matrix
    pincushion = Camera(w, h, camera_matrix=K, distortion=[0.3, 0, 0, 0]).undistortion()
    assert pincushion.mask[h // 2, w // 2] == 255
    assert pincushion.mask[0, 0] == 0 and pincushion.mask[h // 2, 0] == 0  # no source there
    # a circular field of view of radius 150 px: barrel undistortion widens it
    barrel = _camera(scene, fov=150.0).undistortion()
    y, x = np.nonzero(barrel.mask)
    r = np.hypot(x - (w - 1) / 2, y - (h - 1) / 2)
    assert 150.0 < r.max() < 200.0
    assert barrel.mask[h // 2, w // 2] == 255
    assert Camera(w, h, camera_matrix=K).undistortion() is None  # no distortion, nothing to do


def _matched_offsets(a, b) -> np.ndarray:
    m = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(a.descriptors, b.descriptors)
    pa = a.points[[x.queryIdx for x in m]]
    return np.linalg.norm(pa - b.points[[x.trainIdx for x in m]], axis=1)


def test_features_are_detected_in_undistorted_pixels(scene):
    """Keypoints of the distorted frame land where the pinhole frame's own keypoints are
    (measured: 86 of 87 mutual matches within 1 px, median 0.05 px); the raw frame's are
    pixels away (16 of 92 within 1 px, median 5 px)."""
    lens = _camera(scene).undistortion()
    raw = scene.render(3, noise=False)
    pinhole = FeatureExtractor().extract(scene.pinhole(3), 3)
    d = _matched_offsets(FeatureExtractor(undistortion=lens).extract(raw, 3), pinhole)
    assert len(d) > 50 and np.mean(d < 1.0) > 0.9
    assert np.median(d[d < 1.0]) < 0.1
    d_raw = _matched_offsets(FeatureExtractor().extract(raw, 3), pinhole)
    assert np.mean(d_raw < 1.0) < 0.5
    with pytest.raises(ValueError, match=r"frame 5: image is 399x400, the camera's is 400x400"):
        FeatureExtractor(undistortion=lens).extract(raw[:, :399], 5)


@pytest.fixture(scope="module")
def lens_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("lens")
    data = simulate_fetoscopy(root / "data", FetoscopyOptions(n_frames=40, lens_distortion=LENS))
    out = root / "lba"
    run_dataset(data, "lba-emt", out, progress=False)
    return data, out


def test_lba_emt_through_a_lens(lens_run):
    """e_M within 0.25 px of the pinhole truth (measured 0.094). On 60 frames: 0.096, without
    a lens 0.059; keypoints detected in the raw frames and undistorted for the adjustment
    only (before lens handling) 0.197."""
    data, out = lens_run
    result = evaluate_output(out, data)
    assert result["placed"] == 40
    assert result["e_M_px"] < 0.25


def test_mosaic_is_composed_from_undistorted_frames(lens_run):
    """mosaic.png against the mosaic of the pinhole frames at the TRUE homographies, on the
    pixels both show: mean difference under 3 grey levels (measured 0.82); the raw frames
    composed at the true homographies are > 5 off (measured 6.27)."""
    data, out = lens_run
    info = json.loads((out / "report.json").read_text())["mosaic"]
    assert info["lens_undistorted"] is True
    mosaic = cv2.imread(str(out / "mosaic.png"), cv2.IMREAD_COLOR)
    ds = read_dataset(data)
    scene = generate_fetoscopy(FetoscopyOptions(n_frames=40, lens_distortion=LENS))
    truth = render_mosaic([scene.pinhole(k) for k in range(40)], ds.ground_truth,
                          *scene.size)
    origin = (truth.plan.x0, truth.plan.y0)
    d = mosaic_difference(mosaic, info["origin_reference_px"], truth.image, origin,
                          truth.covered)
    assert d["compared_fraction"] > 0.9
    assert d["mean_abs_difference"] < 3.0
    raw = render_mosaic(ds.frames, ds.ground_truth, *scene.size)
    d_raw = mosaic_difference(raw.image, (raw.plan.x0, raw.plan.y0), truth.image, origin,
                              truth.covered)
    assert d_raw["mean_abs_difference"] > 5.0
    frames = UndistortedFrames(ds.frames, ds.camera.undistortion())
    assert len(frames) == 40 and frames[0].shape == (400, 400, 3)


def test_lens_distortion_flag_errors(tmp_path, capsys):
    assert main(["simulate", "fetoscopy", str(tmp_path / "a"), "--n-frames", "3",
                 "--lens-distortion", "-0.3", "0.1", "0"]) == 2
    assert "--lens-distortion: expected 4 or 5 finite numbers" in capsys.readouterr().err
    assert main(["simulate", "fetoscopy", str(tmp_path / "b"), "--n-frames", "3",
                 "--lens-distortion", "-3", "0", "0", "0"]) == 2
    assert "--lens-distortion: [-3.0, 0.0, 0.0, 0.0] is not invertible over the 400x400 " \
           "frame" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_distortion_without_camera_matrix_is_refused(tmp_path):
    """pairwise accepts a camera.yaml without K, but not one whose lens it cannot undo."""
    from fusedmosaic.io import write_dataset

    rng = np.random.default_rng(1)
    frames = [rng.integers(0, 255, (48, 64), dtype=np.uint8) for _ in range(3)]
    data = write_dataset(tmp_path / "data", camera=Camera(64, 48, distortion=LENS),
                         frames=frames, timestamps=np.arange(3) / 25.0)
    with pytest.raises(ValueError, match=r"camera\.yaml: distortion_coefficients without a "
                       r"camera_matrix: undistorting the frames needs the intrinsics"):
        run_dataset(data, "pairwise", tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


def test_folding_lens_in_camera_yaml_is_refused(tmp_path):
    """k1 = -5 at f = 480 px folds over: the distorted radius r (1 - 5 r^2) turns back at r =
    1 / sqrt(15), 124 px from the centre in undistorted pixels, so the undistorted frame
    beyond that shows the centre again, mirrored. A run refuses it naming camera.yaml and an
    undistorted pixel past the fold, leaving no output (before: accepted, e_M 305 px); a
    75 px field of view does not help (the mirrored pixels come from inside it). Lenses
    whose raw corners lie beyond their fold, never sampled by the undistorted frame, and a
    strong barrel lens that undistortPoints' iteration does not converge on in 60 steps, are
    accepted (refused by a first version of this check, a raw -> ray -> raw round trip)."""
    from fusedmosaic.io import write_dataset

    def K(f, w, h):
        return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])

    fold = [-5.0, 0.0, 0.0, 0.0, 0.0]
    rng = np.random.default_rng(2)
    frames = [rng.integers(0, 255, (400, 400), dtype=np.uint8) for _ in range(3)]
    data = write_dataset(tmp_path / "data", camera=Camera(400, 400, K(480, 400, 400),
                                                          distortion=fold),
                         frames=frames, timestamps=np.arange(3) / 25.0)
    message = (r"camera\.yaml: distortion_coefficients: \[-5\.0, 0\.0, 0\.0, 0\.0, 0\.0\] "
               r"fold the pinhole lens model over inside the 400x400 frame \(e\.g\. "
               r"undistorted pixel \((\d+), (\d+)\) is drawn from raw pixel \(\d+, \d+\), "
               r"mirrored\): the undistorted frames would show a double image")
    with pytest.raises(ValueError, match=message) as e:
        run_dataset(data, "pairwise", tmp_path / "out", progress=False)
    u, v = map(int, e.value.args[0].split("undistorted pixel (")[1].split(")")[0].split(", "))
    assert np.hypot(u - 199.5, v - 199.5) > 124
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match=message.replace(r"camera\.yaml", "Camera")):
        Camera(400, 400, K(480, 400, 400), distortion=fold, fov_mask_radius=75).undistortion()
    for w, h, f, d, model in ((640, 480, 480, [-0.4, 0, 0, 0, 0], "pinhole"),  # fold at 292 px
                              (640, 480, 200, [0.05, -0.02, 0.01, 0.0], "fisheye"),
                              (1920, 1080, 1000, [-0.4, 0.15, 0, 0, 0], "pinhole")):
        lens = Camera(w, h, K(f, w, h), distortion=d, lens_model=model).undistortion()
        assert lens.mask.mean() > 0.5


# A wide-angle scope (diagonal field of view ~100 deg) through OpenCV's fisheye model.
FISHEYE = dict(focal_factor=0.8, lens_model="fisheye", lens_distortion=[0.02, -0.01, 0.0, 0.0])


def test_fisheye_undistortion_is_the_pinhole_frame():
    """The fisheye model (cv2.fisheye maps and undistortPoints): the undistorted frame within
    1.5 grey levels of the pinhole render (measured 0.44-0.71; the raw frame 9.2-9.4 off), raw
    pixels projected through the model come back to 1e-6 px."""
    scene = generate_fetoscopy(FetoscopyOptions(n_frames=12, **FISHEYE))
    w, h = scene.size
    camera = Camera(w, h, camera_matrix=scene.camera_matrix, distortion=scene.distortion,
                    lens_model="fisheye")
    lens = camera.undistortion()
    inside = lens.mask > 0
    assert inside.mean() == 1.0
    for k in (0, 2, 7):
        raw = scene.render(k, noise=False)
        ideal = scene.pinhole(k).astype(float)
        assert np.abs(lens.image(raw) - ideal)[inside].mean() < 1.5
        assert np.abs(raw - ideal)[inside].mean() > 4.0
    K = scene.camera_matrix
    ideal = np.random.default_rng(0).uniform(-20, 420, (300, 2))
    rays = np.hstack([(ideal - K[:2, 2]) / K[0, 0], np.ones((300, 1))])
    raw = project_points(rays, K, scene.distortion, "fisheye")
    np.testing.assert_allclose(lens.points(raw), ideal, atol=1e-6)


def test_lba_emt_through_a_fisheye_lens(tmp_path):
    """A fisheye dataset (camera.yaml distortion_model: equidistant): lba-emt e_M within 0.25
    px (measured 0.117); the same frames with the lens ignored 29.6 px."""
    data = simulate_fetoscopy(tmp_path / "data", FetoscopyOptions(n_frames=40, **FISHEYE))
    assert "distortion_model: equidistant" in (data / "camera.yaml").read_text()
    run_dataset(data, "lba-emt", tmp_path / "lba", progress=False)
    result = evaluate_output(tmp_path / "lba", data)
    assert result["placed"] == 40 and result["e_M_px"] < 0.25
    info = json.loads((tmp_path / "lba" / "report.json").read_text())["mosaic"]
    assert info["lens_undistorted"] is True


def test_fisheye_flag_errors(tmp_path, capsys):
    assert main(["simulate", "fetoscopy", str(tmp_path / "a"), "--n-frames", "3",
                 "--lens-model", "fisheye", "--lens-distortion", "0.1", "0", "0", "0", "0"]) == 2
    assert ("--lens-distortion: expected 4 finite numbers (k1 k2 k3 k4) for the fisheye model"
            in capsys.readouterr().err)
    assert main(["simulate", "fetoscopy", str(tmp_path / "b"), "--n-frames", "3",
                 "--lens-model", "fisheye"]) == 2
    assert "--lens-model: 'fisheye' needs lens_distortion" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
