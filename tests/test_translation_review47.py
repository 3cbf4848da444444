"""Review 47 (reviewer J) of the pCLE translation path: kalman-robot's warm-up with noisy images
(H1), the step interval after an unplaced frame (L2) and a blank frame 0 in the mosaic (L1).

H1: in the filter's warm-up a registration was trusted only at an absolute SSIM (c_match >=
0.65), and an untrusted one was image-gated against a sigma_r0 never measured (the 1 px
placeholder: 3.2 px). With image noise sigma 12-20 grey levels every correct registration
scores 0.46-0.60, so all were gated, none fed the filter, the warm-up never ended and X_f
kept the noisy robot's error (126 µm at sigma 16, ncc 0.3), without a word.
"""

import json
import shutil
import warnings
from dataclasses import replace

import cv2
import numpy as np
import pytest

from fusedmosaic.cli import main
from fusedmosaic.estimation.kalman import KalmanOptions, RobotKalmanFilter
from fusedmosaic.estimation.translation import (
    RobotPriorMosaicker,
    RobotPriorOptions,
    run_kalman_robot,
    run_ncc,
    run_robot,
)
from fusedmosaic.evaluation import position_errors_um
from fusedmosaic.io import Camera, read_dataset
from fusedmosaic.simulation import PcleOptions, generate_pcle, simulate_pcle

# The review's case: a clean circle (no contact loss, no stick-slip), 256x224 px of 1 µm.
NOISY_IMAGES = PcleOptions(width=256, height=224, n_frames=80, speed_um_per_frame=20.0,
                           radius_um=250.0, image_noise_sigma=16.0, contact_loss=False,
                           stick_slip=False)
SMALL = PcleOptions(width=192, height=160, n_frames=14, speed_um_per_frame=12.0, radius_um=150.0,
                    contact_loss=False, stick_slip=False)


@pytest.fixture(scope="module")
def noisy_images(tmp_path_factory):
    root = simulate_pcle(tmp_path_factory.mktemp("pcle") / "sigma16", NOISY_IMAGES)
    return read_dataset(root, robot_file="robot_noisy.csv")


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return simulate_pcle(tmp_path_factory.mktemp("pcle") / "small", SMALL)


def _errors_um(result, dataset):
    cam = dataset.camera
    return position_errors_um(result.homographies, dataset.ground_truth, cam.width, cam.height,
                              cam.pixel_size_um)


def _robot_step_rms_um(dataset):
    """RMS over the frames of the noisy robot's per-frame displacement error, from the truth."""
    truth = dataset.ground_truth[:, :2, 2] * dataset.camera.pixel_size_um
    error = np.diff(dataset.robot_xy_um, axis=0) - np.diff(truth, axis=0)
    return float(np.sqrt(np.mean(np.sum(error**2, axis=1))))


# -- H1: noisy images in the warm-up -------------------------------------------------------------


def test_noisy_but_correct_registrations_are_used_from_the_start(noisy_images):
    """Image noise sigma 16: NCC registers every frame (X_m 0.3 µm), the noisy robot drifts
    (207 µm). The warm-up now trusts a registration whose SSIM gains over the pair's SSIM at 0
    px (0.35-0.51 here; a fibre-pattern lock gains 0), the filter measures sigma_r0 from the
    first frames and weighs the robot by it. Tolerance, from the truth: X_f within 2 of the
    robot's per-frame displacement errors (RMS 8.6 µm) of X_m: the robot's weight in the
    warm-up lets a few steps' noise in, not its drift. Measured 6.9 µm (before: 126.1 µm, 33
    correct registrations gated)."""
    fused = run_kalman_robot(noisy_images, progress=False)
    e_fused = _errors_um(fused, noisy_images)
    e_image = _errors_um(run_ncc(noisy_images, progress=False), noisy_images)
    e_robot = _errors_um(run_robot(noisy_images, progress=False), noisy_images)
    step = _robot_step_rms_um(noisy_images)
    assert e_image.max() < 1.0  # every registration correct (the premise) ...
    assert fused.details["image_gated"] == []  # ... so none is left out
    assert e_fused.mean() < e_image.mean() + 2.0 * step, (e_fused.mean(), e_image.mean(), step)
    assert e_fused.mean() < e_robot.mean() / 10.0, (e_fused.mean(), e_robot.mean())
    # sigma_r0 is measured in the warm-up (3 trusted frames), not left at the placeholder
    sigma = np.array(fused.details["sigma_robot0_px"][4:], dtype=float)
    assert np.isfinite(sigma).all() and (sigma > 2.0).all(), sigma[:8]


def test_the_warm_up_ends_when_its_registrations_are_left_out(noisy_images):
    """No warm-up registration trusted (neither level can be reached): each is left out while
    sigma_r0 is unmeasured, the robot placing the frame, but its step enters the filter's
    histories, so after min_history steps c_img judges the registrations and they are used.
    Before, a registration left out added nothing: the warm-up (and the robot's noise) lasted
    the whole run. Tolerance: placed by the images from frame min_history + 1 on, and from
    there X_f's error grows by less than 2 of the robot's per-frame displacement errors (RMS
    8.6 µm; measured 12.0 µm, the robot alone 402)."""
    options = RobotPriorOptions(warmup_overlap_c_match=2.0, warmup_ssim_margin=None)
    fused = run_kalman_robot(noisy_images, progress=False, options=options)
    first = KalmanOptions().min_history + 1
    assert fused.status[1:first] == ["prior-only"] * (first - 1)
    assert fused.details["image_gated"] == list(range(1, first))
    assert all(s == "placed" for s in fused.status[first:]), fused.status
    c_speed = fused.details["confidences"]["c_speed"]
    assert all(np.isfinite(c) for c in c_speed[first:])  # out of the warm-up
    growth = _errors_um(fused, noisy_images)[first - 1:]
    growth -= growth[0]  # (the robot's error over the warm-up stays)
    assert growth.max() < 2.0 * _robot_step_rms_um(noisy_images), growth.round(1)


def test_a_registration_left_out_keeps_its_c_match_and_most_left_out_warns(tmp_path):
    """The probe lifted off the tissue after frame 0 (a contact loss for the whole recording):
    every registration locks on the fibre pattern or disagrees between directions, and the
    robot places every frame. report.json showed c_match null for those frames and no warning
    said that X_f was the robot's chain. Now the SSIM computed stays, and a run warns when the
    robot placed most frames that had a registration."""
    root = simulate_pcle(tmp_path / "lifted", replace(
        SMALL, width=256, height=224, n_frames=30, speed_um_per_frame=20.0, radius_um=250.0,
        contact_loss=True, z_period_s=20.0, contact_loss_um=0.0, contact_fade_um=5.0))
    dataset = read_dataset(root)
    result = run_kalman_robot(dataset, progress=False)
    assert result.status[1:] == ["prior-only"] * 29
    gated = result.details["image_gated"]
    assert gated
    c_match = result.details["confidences"]["c_match"]
    assert all(c_match[k] is not None and np.isfinite(c_match[k]) for k in gated)
    (warning,) = result.details["warnings"]
    assert warning.startswith(
        "29 of 29 NCC registrations were not used, the robot placing their frames (frames 1, "
        f"2, 3, 4, 5, 6, 7, 8, 9, 10, ... (19 more)): {len(gated)} left out by the image gate "
        "(report.json image_gated), "), warning
    assert "X_f is mostly the robot's chain" in warning
    # the same warning streamed (run --live)
    out = tmp_path / "live"
    assert main(["run", str(root), "--method", "kalman-robot", "--live", "--quiet",
                 "--no-report", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert [w for w in report["warnings"] if w.startswith("29 of 29 NCC registrations were "
                                                          "not used")], report["warnings"]


def test_kalman_filter_record_adds_a_left_out_step_to_the_histories():
    """RobotKalmanFilter.record: the step of the last update, made without the image, enters
    the histories (the warm-up counts it); a still step, a second record, or one after an
    update that had the image add nothing; the position does not move."""
    kf = RobotKalmanFilter(KalmanOptions())
    for k in range(KalmanOptions().min_history):
        assert kf.warming_up
        step = kf.update([np.nan, np.nan], [4.0, 0.0], 0.0)
        kf.record([4.0, 0.1])
        kf.record([4.0, 0.1])  # the same step: once
        np.testing.assert_allclose(step.position, [4.0 * (k + 1), 0.0])
    assert not kf.warming_up
    kf = RobotKalmanFilter(KalmanOptions())
    kf.update([np.nan, np.nan], [4.0, 0.0], 0.0)
    kf.record([0.1, 0.0])  # still (< angle_min_norm): no speed history either
    kf.update([4.0, 0.0], [4.0, 0.0], 0.9)
    kf.record([4.0, 0.0])  # the update had it
    assert list(kf.snapshot()[1]) == [(2, 4.0)]  # (step, speed): the update's only


# -- L2: the interval after an unplaced frame ----------------------------------------------------


def test_the_step_after_an_unplaced_frame_spans_two_intervals():
    """Frame 15 blank and without a robot sample: unplaced, so frame 16's step spans frames
    14-16, two intervals, but the filter was told one and read a speed doubling (c_speed 0.513
    against 0.998 without the gap). Tolerance: c_speed of frame 16 within 0.01 of the run
    without the gap."""
    scene = generate_pcle(replace(SMALL, width=256, height=224, n_frames=20,
                                  speed_um_per_frame=15.0, radius_um=250.0))
    camera = Camera(256, 224, pixel_size_um=1.0)
    robot = np.stack([np.interp(scene.timestamps, scene.robot_timestamps, scene.robot_xy_um[:, j])
                      for j in range(2)], axis=1)
    c_speed = {}
    for gap in (None, 15):
        m = RobotPriorMosaicker(camera)
        for k in range(17):
            image, sample = scene.render(k), robot[k]
            if k == gap:
                image, sample = np.zeros_like(image), None
            out = m.add_frame(image, scene.timestamps[k], sample)
        assert out.status == "placed" and out.registered_against == (14 if gap else 15)
        c_speed[gap] = out.c_speed
    assert c_speed[None] > 0.9
    assert abs(c_speed[15] - c_speed[None]) < 0.01, c_speed


# -- L1: a blank frame 0 ------------------------------------------------------------------------


def _black_frame0(small, tmp_path, every=False):
    root = shutil.copytree(small, tmp_path / ("black" if every else "black0"))
    frames = sorted((root / "frames").iterdir())
    for path in frames if every else frames[:1]:
        cv2.imwrite(str(path), np.zeros_like(cv2.imread(str(path), cv2.IMREAD_UNCHANGED)))
    return root


@pytest.mark.parametrize(("method", "live"), [
    ("ncc", False), ("ncc", True), ("kalman-robot", False), ("kalman-robot", True),
    ("robot", True)])
def test_a_black_frame0_is_placed_but_not_composed(small, tmp_path, method, live):
    """A black frame 0 was "placed" by ncc and kalman-robot (offline and --live) and by robot
    --live, which told run that the method had seen its content: it was pasted into the
    mosaic (8 % darker tissue under it). Now it is placed (the reference, homographies.csv
    identity) but left out of the mosaic, as every black frame is (as robot offline did)."""
    root = _black_frame0(small, tmp_path)
    out = tmp_path / "out"
    assert main(["run", str(root), "--method", method, *(["--live"] if live else []),
                 "--quiet", "--no-report", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["frame_status"][0] == ("placed" if method == "robot" else "prior-only")
    assert report["mosaic"]["skipped_frames"] == {
        "0": "no visual content (every pixel <= 12): not composed"}
    H = np.loadtxt(out / "homographies.csv", delimiter=",", skiprows=1)[:, 1:]
    np.testing.assert_array_equal(H[0], np.eye(3).ravel())


def test_every_frame_black_writes_no_black_mosaic(small, tmp_path, capsys):
    """kalman-robot on a recording of black frames wrote a black mosaic.png (frame 0 "placed"),
    where robot says the mosaic was not written; now both say so."""
    root = _black_frame0(small, tmp_path, every=True)
    out = tmp_path / "out"
    with warnings.catch_warnings():  # as on a terminal: run shows it (on stderr), and goes on
        warnings.simplefilter("default", UserWarning)
        assert main(["run", str(root), "--method", "kalman-robot", "--quiet", "--no-report",
                     "--out", str(out)]) == 0
    assert not (out / "mosaic.png").exists()
    assert ("mosaic.png not written: no frame to compose a mosaic from: the 14 placed frame(s) "
            "are all left out") in capsys.readouterr().err


def test_a_streamed_blank_frame0_is_prior_only_and_a_textured_one_placed(small):
    dataset = read_dataset(small)
    blank = np.zeros_like(dataset.frames[0])
    for estimate in ("image", "fused"):
        m = RobotPriorMosaicker(dataset.camera, estimate=estimate)
        assert m.add_frame(blank, 0.0, dataset.robot_xy_um[0]).status == "prior-only"
        m = RobotPriorMosaicker(dataset.camera, estimate=estimate)
        assert m.add_frame(dataset.frames[0], 0.0, dataset.robot_xy_um[0]).status == "placed"
    m = RobotPriorMosaicker(dataset.camera, estimate="robot")
    assert m.add_frame(None, 0.0, dataset.robot_xy_um[0]).status == "placed"


def test_bad_warmup_ssim_margin_is_refused():
    for value in (0.0, -0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="warmup_ssim_margin must be a finite number > 0 "
                                             "or None"):
            RobotPriorOptions(warmup_ssim_margin=value)
