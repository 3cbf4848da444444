"""Review 44 (reviewer C) of the pCLE method of paper 004: NCC in forked workers, the trust of
warm-up registrations in the robot-prior filter, a header-only robot.csv, the Eq. 15 levels of
KalmanOptions and the one float32 conversion per frame."""

import csv
import multiprocessing
from dataclasses import asdict

import cv2
import numpy as np
import pytest

from fusedmosaic.estimation.kalman import KalmanOptions
from fusedmosaic.estimation.translation import RobotPriorMosaicker, RobotPriorOptions
from fusedmosaic.io import Camera, RobotSamples, read_dataset, write_dataset
from fusedmosaic.io.tracking import interpolate_robot, read_robot_csv
from fusedmosaic.registration.ncc import aligned_overlap_ssim, register_ncc
from fusedmosaic.runner import run_dataset
from fusedmosaic.simulation import PcleOptions, simulate_pcle


def _pair(shape=(224, 256), shift=(5, -7), seed=3):
    rng = np.random.default_rng(seed)
    a = cv2.GaussianBlur(rng.uniform(0, 255, shape), (0, 0), 2.0).astype(np.uint8)
    return a, np.roll(a, shift, axis=(0, 1))


# -- 1. the second thread of ncc.py in a forked process ---------------------------------------


def _register_in_worker(_):
    a, b = _pair()
    return register_ncc(a, b).dx.tolist(), aligned_overlap_ssim(a, b, np.array([7.0, -5.0]))


@pytest.mark.skipif("fork" not in multiprocessing.get_all_start_methods(), reason="no fork")
@pytest.mark.filterwarnings("ignore:This process.*multi-threaded:DeprecationWarning")
def test_register_ncc_works_in_a_process_forked_after_a_call_in_the_parent():
    """ncc.py's second thread is created on first use; a child forked after that inherited the
    executor without its thread, and register_ncc / SSIM waited for ever in the child (a
    multiprocessing Pool with the 'fork' start method, Linux's default before 3.14). The child
    now gets its own executor: the same numbers as in the parent, well within the timeout."""
    expected = _register_in_worker(None)  # starts the parent's second thread
    with multiprocessing.get_context("fork").Pool(2) as pool:
        got = pool.map_async(_register_in_worker, range(2)).get(timeout=60)
    assert got == [expected, expected]
    np.testing.assert_allclose(expected[0], [7.0, -5.0], atol=0.05)


# -- 2. warm-up registrations judged by c_match ------------------------------------------------

# Reviewer C's scenarios (simulator defaults at 256x224 px, no stick-slip): a recording that
# starts inside the simulator's contact loss (frames 6.. of a 3.2 s z period), and a fibre-
# pattern lock right after good frames (1.6 s period, 100 µm contact loss). Both lock on the
# fibre pattern at 0 px (c_match ~0.5) in the filter's warm-up, where c_img is the initial 1.
SCENARIOS = {
    "starts-in-contact-loss": (
        PcleOptions(width=256, height=224, n_frames=50, seed=0, z_period_s=3.2,
                    stick_slip=False, fibre_contrast=0.25), 6),
    "lock-after-good-frames": (
        PcleOptions(width=256, height=224, n_frames=40, seed=0, z_period_s=1.6,
                    stick_slip=False, fibre_contrast=0.8, contact_loss_um=100.0), 0),
}


def _stream_errors(dataset, first, options=None, estimate="fused"):
    """Per-frame position errors (px) of frames first.. streamed as a recording of their own
    (the truth rebased to its first frame)."""
    truth = dataset.ground_truth[first:, :2, 2] - dataset.ground_truth[first, :2, 2]
    m = RobotPriorMosaicker(dataset.camera, options, estimate=estimate)
    positions = np.array([
        m.add_frame(dataset.frames[k], dataset.timestamps[k], dataset.robot_xy_um[k]).position
        for k in range(first, len(dataset))])
    return np.hypot(*(positions - truth).T)


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_a_lock_in_the_warm_up_does_not_offset_the_fused_estimate(scenario, tmp_path):
    """kalman-robot within 2 px of the robot's e_M, no frame over 4 px off. Measured: e_M 0.35
    px (robot 0.02; 0.67 at fibre contrast 0.35) and 0.50 px (robot 0.01), largest frame error
    1.3 px; before, the lock was trusted (c_img = c_img0 = 1), placed 40 px off for good and,
    after good frames, fed its disagreement into sigma_r0: e_M 38.8 and 71.1 px, no warning.
    warmup_overlap_c_match=0 (every warm-up registration trusted) still gives that: the
    scenario holds a lock."""
    options, first = SCENARIOS[scenario]
    root = simulate_pcle(tmp_path / scenario, options)
    with open(root / "events.csv", newline="") as f:
        loss = [int(r["contact_loss"]) for r in csv.DictReader(f)][first:]
    assert (loss[0] == 1) == (scenario == "starts-in-contact-loss") and any(loss[:8])
    dataset = read_dataset(root)
    robot = _stream_errors(dataset, first, estimate="robot")
    fused = _stream_errors(dataset, first)
    assert fused.mean() <= robot.mean() + 2.0
    assert fused.max() <= 4.0
    trusted = _stream_errors(dataset, first, RobotPriorOptions(warmup_overlap_c_match=0.0))
    assert trusted.mean() > 10.0


@pytest.fixture(scope="module", params=["circle", "spiral"])
def default_scan(request, tmp_path_factory):
    root = simulate_pcle(tmp_path_factory.mktemp("pcle") / request.param,
                         PcleOptions(trajectory=request.param))
    return root


@pytest.mark.parametrize("robot_file", ["robot.csv", "robot_noisy.csv"])
def test_default_scans_are_not_worse_with_warm_up_judged_by_c_match(default_scan, robot_file):
    """The simulator's default circle and spiral (seed 0, 512x448 px), perfect and noisy robot:
    e_M with the warm-up judged by c_match not above that with every warm-up registration
    trusted (warmup_overlap_c_match=0, the judgement before) by more than 1 %. Measured: circle
    10.62 vs 10.66 px and 37.802 vs 37.801 px (a warm-up frame of c_match 0.57 in the contact
    loss no longer feeds sigma_r0), spiral 9.474 vs 9.476 and 32.936 vs 32.942 px."""
    dataset = read_dataset(default_scan, robot_file=robot_file)
    judged = _stream_errors(dataset, 0).mean()
    trusted = _stream_errors(dataset, 0, RobotPriorOptions(warmup_overlap_c_match=0.0)).mean()
    assert judged <= 1.01 * trusted


# -- 3. a header-only robot.csv ----------------------------------------------------------------


def test_a_header_only_robot_csv_is_refused_naming_the_file(tmp_path):
    rng = np.random.default_rng(0)
    data = write_dataset(
        tmp_path / "data", camera=Camera(64, 48, pixel_size_um=1.0),
        frames=[rng.integers(0, 255, (48, 64), dtype=np.uint8) for _ in range(3)],
        timestamps=np.arange(3) / 10.0,
        robot=RobotSamples(np.linspace(-0.1, 0.3, 5), np.zeros((5, 2))))
    (data / "robot.csv").write_text("timestamp,x,y\n")
    with pytest.raises(ValueError, match=r"robot\.csv: no samples \(header only\)"):
        read_robot_csv(data / "robot.csv")
    with pytest.raises(ValueError, match=r"robot\.csv: no samples \(header only\)"):
        run_dataset(data, "kalman-robot", tmp_path / "out", progress=False)


def test_robot_samples_may_be_empty_and_interpolation_says_so():
    empty = RobotSamples(np.zeros(0), np.zeros((0, 2)))
    assert len(empty) == 0 and empty.xy_um.shape == (0, 2)
    with pytest.raises(ValueError, match="robot.csv: no samples"):
        interpolate_robot(empty, [0.0, 0.1])
    with pytest.raises(ValueError, match=r"RobotSamples\.xy_um: sample 1 is not finite"):
        RobotSamples([0.0, 1.0], [[0.0, 0.0], [np.nan, 1.0]])
    with pytest.raises(ValueError, match=r"RobotSamples\.timestamps: sample 1 is not finite"):
        RobotSamples([0.0, np.nan], [[0.0, 0.0], [0.0, 1.0]])


# -- 4. the Eq. 15 levels of KalmanOptions -----------------------------------------------------


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"angle_x_r": np.nan}, r"KalmanOptions\.angle_x_r must be in \(0, 3\.142\)"),
    ({"angle_x_r": 4.0}, r"KalmanOptions\.angle_x_r must be in \(0, 3\.142\)"),
    ({"angle_x_r": 0.0}, r"KalmanOptions\.angle_x_r"),
    ({"speed_x_r": np.nan}, r"KalmanOptions\.speed_x_r must be in \(0, 1\)"),
    ({"speed_x_r": 1.5}, r"KalmanOptions\.speed_x_r must be in \(0, 1\) \(speed_deviation='ratio'"),
    ({"speed_x_r": np.inf, "speed_deviation": "relative"},
     r"KalmanOptions\.speed_x_r must be a finite number > 0 \(speed_deviation='relative'\)"),
    ({"speed_x_r": -2.0, "speed_deviation": "absolute"}, r"KalmanOptions\.speed_x_r"),
    ({"sp_x_r": np.inf}, r"KalmanOptions\.sp_x_r must be in \(0, 1\)"),
    ({"sp_x_r": np.nan}, r"KalmanOptions\.sp_x_r"),
])
def test_kalman_options_refuse_eq15_levels_that_switch_a_confidence_off(kwargs, message):
    """NaN / inf levels were accepted: angle_x_r NaN turned the angle check off (c_angle NaN,
    counted as 1), speed_x_r NaN made c_img NaN (every registration ignored), sp_x_r inf made
    c_rob always 1 (Eq. 18 off), all silently."""
    with pytest.raises(ValueError, match=message):
        KalmanOptions(**kwargs)


def test_kalman_options_accept_eq15_levels_in_range():
    KalmanOptions(angle_x_r=3.0, speed_x_r=0.9, sp_x_r=0.1)
    KalmanOptions(speed_x_r=1.5, speed_deviation="relative")  # |N - f| / f: any level > 0
    KalmanOptions(speed_x_r=20.0, speed_deviation="absolute")  # px / frame


# -- 6. one float32 conversion per frame -------------------------------------------------------


def test_prepared_float32_frames_give_the_same_numbers_to_the_bit():
    """register_ncc / aligned_overlap_ssim with frames converted once (prepared=True; SSIM's
    8-bit range given) equal the calls on the uint8 frames, presmoothing and the wide-range
    retry included, and on slices (a circular field of view's box)."""
    rng = np.random.default_rng(5)
    scene = cv2.GaussianBlur(rng.uniform(0, 255, (400, 420)), (0, 0), 2.0).astype(np.uint8)
    # dx = (70, -55): beyond the 3/5 template's +-51 x 44 px range, the wide-range retry runs
    a, b = scene[100:324, 80:336], scene[45:269, 150:406]
    fa, fb = a.astype(np.float32), b.astype(np.float32)
    for kwargs in ({}, {"presmooth_sigma": 1.5}, {"pyramid_levels": 0}):
        plain, prepared = register_ncc(a, b, **kwargs), register_ncc(fa, fb, prepared=True,
                                                                     **kwargs)
        for name, value in asdict(plain).items():
            np.testing.assert_array_equal(value, asdict(prepared)[name], err_msg=name)
    assert register_ncc(a, b).fallback
    np.testing.assert_allclose(register_ncc(a, b).dx, [70.0, -55.0], atol=0.1)
    box = (slice(10, 200), slice(20, 230))
    np.testing.assert_array_equal(register_ncc(a[box], b[box]).dx,
                                  register_ncc(fa[box], fb[box], prepared=True).dx)
    dx = np.array([70.0, -55.0])
    for downsample in (1, 2):
        plain = aligned_overlap_ssim(a, b, dx, downsample=downsample)
        assert plain > 0.9
        assert plain == aligned_overlap_ssim(fa, fb, dx, data_range=255.0,
                                             downsample=downsample, prepared=True)
    with pytest.raises(ValueError, match="previous: prepared=True needs a 2-D float32 image"):
        register_ncc(a, fb, prepared=True)


@pytest.mark.parametrize("to_float", [False, True], ids=["uint8", "float"])
def test_streaming_equals_the_public_calls_on_the_frames(to_float, tmp_path):
    """The mosaicker converts each frame once and keeps its anchor's float copy: X_m and
    c_match equal a chain of register_ncc / aligned_overlap_ssim calls on the frames, to the
    bit (uint8 frames as given; float frames as the mosaicker scales them: float32, the first
    frame's range mapped to 0-255)."""
    root = simulate_pcle(tmp_path / "s", PcleOptions(width=192, height=160, n_frames=12,
                                                     speed_um_per_frame=12.0, radius_um=150.0,
                                                     contact_loss=False, stick_slip=False))
    dataset = read_dataset(root)
    given = [f / 255.0 + 7.0 if to_float else f for f in dataset.frames]
    frames = given
    if to_float:
        frames = [g.astype(np.float32) for g in given]
        low, high = float(frames[0].min()), float(frames[0].max())
        frames = [((f.astype(np.float64) - low) * (255.0 / (high - low))).astype(np.float32)
                  for f in frames]
    m = RobotPriorMosaicker(dataset.camera, estimate="image")
    position = np.zeros(2)
    for k in range(len(frames)):
        result = m.add_frame(given[k], dataset.timestamps[k])
        if k:
            dx = register_ncc(frames[k - 1], frames[k]).dx
            position = position + dx
            assert result.c_match == aligned_overlap_ssim(frames[k - 1], frames[k], dx) > 0.5
        np.testing.assert_array_equal(result.position, position)


def test_float_frames_overflowing_float32_on_the_common_scale_are_refused():
    """Frames are put on the first textured frame's intensity scale; a later frame whose values
    overflow float32 there is refused naming the frame (register_ncc checked it before, now
    that it reads the mosaicker's converted frames unchecked, the mosaicker does)."""
    rng = np.random.default_rng(0)
    m = RobotPriorMosaicker(Camera(64, 48, pixel_size_um=1.0), estimate="image")
    m.add_frame((rng.random((48, 64)) * 1e-30).astype(np.float32), 0.0)
    with pytest.raises(ValueError, match="frame 1: pixel values overflow float32"):
        m.add_frame((rng.random((48, 64)) * 1e30).astype(np.float32), 0.1)
    assert m.frame_count == 1
