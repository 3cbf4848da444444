"""Simulators: geometry truth vs the C++ core, rendered images vs the truth, EMT noise statistics,
black frames, hand-held motion, pCLE contact events measured on the images, determinism, and the
written datasets read back through fusedmosaic.io."""

import dataclasses
import json
import re

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusedmosaic import _core
from fusedmosaic.cli import main
from fusedmosaic.io import TrackingSamples, interpolate_camera_poses, read_dataset
from fusedmosaic.simulation import (
    PAPER_BLACK_FRAMES,
    CheckerboardOptions,
    FetoscopyOptions,
    PcleOptions,
    cell_texture,
    fibre_bundle_pattern,
    generate_checkerboard,
    generate_fetoscopy,
    generate_pcle,
    placenta_texture,
    simulate_checkerboard,
    simulate_fetoscopy,
    simulate_pcle,
)
from fusedmosaic.simulation._lens import on_inner_branch

# Small scenes: 24 frames, laps scaled so consecutive frames keep the default ~40 px step.
SYN = FetoscopyOptions(n_frames=24, laps=24 / 150 * 4, seed=3)
HANDHELD = FetoscopyOptions(motion="handheld", n_frames=24, seed=5)
PCLE = PcleOptions(radius_um=250.0, seed=7)  # 40 frames: one contact loss, one stick-slip phase


@pytest.fixture(scope="session")
def syn():
    return generate_fetoscopy(SYN)


@pytest.fixture(scope="session")
def handheld():
    return generate_fetoscopy(HANDHELD)


@pytest.fixture(scope="session")
def pcle():
    return generate_pcle(PCLE)


def warp_onto_reference(scene, k, noise=True):
    """Frame k warped by the true G_k onto frame 0, frame 0, and their common valid pixels."""
    frame_k, frame_0 = scene.render(k, noise=noise), scene.render(0, noise=noise)
    warped = cv2.warpPerspective(frame_k, scene.homographies[k], scene.size)
    fov = scene.fov_mask()
    src = np.full(frame_k.shape[:2], 255, np.uint8) if fov is None else fov.astype(np.uint8) * 255
    overlap = (
        cv2.warpPerspective(src, scene.homographies[k], scene.size, flags=cv2.INTER_NEAREST) > 0
    )
    if fov is not None:
        overlap &= fov
    overlap = cv2.erode(overlap.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # edge pixels
    return warped, frame_0, overlap


# -- fetoscopy geometry ----------------------------------------------------------------------


@pytest.mark.parametrize("name", ["syn", "handheld"])
def test_truth_matches_core_frame_to_reference(name, request):
    scene = request.getfixturevalue(name)
    G = _core.frame_to_reference(scene.poses, scene.plane, scene.camera_matrix)
    np.testing.assert_allclose(scene.homographies, G, rtol=0, atol=1e-9)
    np.testing.assert_allclose(scene.homographies[0], np.eye(3), atol=1e-12)


@pytest.mark.parametrize("name", ["syn", "handheld"])
@pytest.mark.parametrize("k", [1, 3, 6])
def test_rendered_frame_warped_by_truth_matches_reference(name, k, request):
    # Tolerance: image noise sigma 2 gives a mean |difference| of ~2.3 gray levels; without
    # noise only the two bilinear resamplings remain (< 1 gray level).
    scene = request.getfixturevalue(name)
    warped, frame_0, overlap = warp_onto_reference(scene, k)
    assert overlap.mean() > 0.2
    a, b = warped[overlap].astype(float), frame_0[overlap].astype(float)
    assert np.abs(a - b).mean() < 3.5
    assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.97
    warped, frame_0, overlap = warp_onto_reference(scene, k, noise=False)
    assert np.abs(warped[overlap].astype(float) - frame_0[overlap]).mean() < 1.0


def test_syn_is_xy_translation_on_a_fronto_parallel_plane(syn):
    np.testing.assert_array_equal(syn.poses[:, :3], 0.0)
    np.testing.assert_array_equal(syn.poses[:, 5], 0.0)
    np.testing.assert_allclose(syn.plane, [0, 0, -1 / SYN.distance_mm], atol=1e-15)
    K = syn.camera_matrix
    assert 1.1 * SYN.width <= K[0, 0] <= 1.3 * SYN.width
    # Consecutive frames overlap by ~90 % (step ~40 px of 400).
    steps = np.linalg.norm(np.diff(syn.homographies[:, :2, 2], axis=0), axis=1)
    assert 0.05 * SYN.width < steps.min() and steps.max() < 0.15 * SYN.width


def test_syn_laps_revisit_the_same_area():
    scene = generate_fetoscopy(FetoscopyOptions(n_frames=60, laps=2.0))
    # Half-way through (one lap later) the camera is back over frame 0.
    np.testing.assert_allclose(scene.homographies[30, :2, 2], 0.0, atol=1e-9)


def test_handheld_has_rotations_tilted_plane_and_varying_distance(handheld):
    angles = np.rad2deg(np.linalg.norm(handheld.poses[:, :3], axis=1))
    assert angles.max() > 2.0
    # Roll/pitch (not only yaw): the optical axis direction changes in world.
    axes = Rotation.from_rotvec(handheld.poses[:, :3]).inv().apply([0, 0, 1])
    assert np.rad2deg(np.arccos(np.clip(axes @ axes[0], -1, 1))).max() > 1.0
    normal = handheld.plane / np.linalg.norm(handheld.plane)
    tilt = np.rad2deg(np.arccos(abs(normal[2])))
    assert tilt == pytest.approx(HANDHELD.tilt_deg, abs=1e-9)
    distances = [_core.camera_plane_distance(p, handheld.plane) for p in handheld.poses]
    assert np.ptp(distances) > 0.02 * HANDHELD.distance_mm
    assert not np.allclose(handheld.homographies[:, 2, :2], 0.0)  # perspective terms
    assert handheld.fov_mask_radius == pytest.approx(0.48 * 400)
    frame = handheld.render(2)
    assert not frame[~handheld.fov_mask()].any()
    assert frame[handheld.fov_mask()].mean() > 50


def test_handheld_consecutive_frames_overlap(handheld):
    for k in range(1, handheld.n_frames):
        G = np.linalg.inv(handheld.homographies[k - 1]) @ handheld.homographies[k]
        centre = G @ [199.5, 199.5, 1.0]
        assert np.linalg.norm(centre[:2] / centre[2] - 199.5) < 0.2 * 400


def test_sift_registers_consecutive_frames():
    # The texture gives SIFT enough, but not trivially many, features: pairwise homographies
    # from SIFT + RANSAC agree with the truth to < 1 px on average over the image.
    scene = generate_fetoscopy(FetoscopyOptions(n_frames=4, laps=4 / 150 * 4, seed=11))
    sift = cv2.SIFT_create()
    feats = [
        sift.detectAndCompute(cv2.cvtColor(scene.render(k), cv2.COLOR_BGR2GRAY), None)
        for k in (0, 1)
    ]
    assert 40 < len(feats[0][0]) < 2000
    matches = cv2.BFMatcher().knnMatch(feats[1][1], feats[0][1], k=2)
    good = [m for m, n in matches if m.distance < 0.8 * n.distance]
    p1 = np.float32([feats[1][0][m.queryIdx].pt for m in good])
    p0 = np.float32([feats[0][0][m.trainIdx].pt for m in good])
    H, inliers = cv2.findHomography(p1, p0, cv2.RANSAC, 3.0)
    assert inliers.sum() >= 20
    grid = np.stack(np.meshgrid(np.linspace(0, 399, 10), np.linspace(0, 399, 10)), -1)
    grid = grid.reshape(1, -1, 2)
    err = cv2.perspectiveTransform(grid, H) - cv2.perspectiveTransform(grid, scene.homographies[1])
    assert np.linalg.norm(err, axis=2).mean() < 1.0


# -- EM tracker ------------------------------------------------------------------------------


@pytest.mark.parametrize("nu", [0.5, 2.0])
def test_emt_noise_statistics_match_nu(nu):
    # ~1000 samples per component: the sample std is within ~2.2 % (1 sigma) of the true one,
    # so 10 % is a > 4 sigma tolerance; the mean within 4 standard errors of 0.
    scene = generate_fetoscopy(FetoscopyOptions(n_frames=600, noise_multiplier=nu, seed=1))
    d = scene.tracker_poses - scene.tracker_truth
    expected = nu * np.array([np.deg2rad(1.0)] * 3 + [1.0] * 3)
    np.testing.assert_allclose(d.std(axis=0), expected, rtol=0.10)
    assert np.all(np.abs(d.mean(axis=0)) < 4 * expected / np.sqrt(d.shape[0]))


def test_emt_noise_free_tracker_recovers_truth_through_hand_eye():
    scene = generate_fetoscopy(FetoscopyOptions(n_frames=20, laps=0.5, noise_multiplier=0.0))
    assert not np.allclose(scene.hand_eye, np.eye(4))
    np.testing.assert_allclose(scene.tracker_poses, scene.tracker_truth, atol=1e-12)
    samples = TrackingSamples(
        scene.tracker_timestamps, scene.tracker_translations, scene.tracker_quaternions
    )
    poses, valid = interpolate_camera_poses(samples, scene.timestamps, scene.hand_eye)
    assert valid.all()
    # SYN moves on a circle, so linear interpolation between 40 Hz samples is off by at most
    # the chord sagitta R (1 - cos(dtheta / 2)), dtheta the angle between samples (~0.018 mm).
    dtheta = 2 * np.pi * 0.5 * 25.0 / (20 * 40.0)
    sagitta = 15.0 * (1 - np.cos(dtheta / 2))
    np.testing.assert_allclose(poses[:, :3], 0.0, atol=1e-12)
    np.testing.assert_allclose(poses[:, 3:], scene.poses[:, 3:], atol=1.01 * sagitta)


def test_tracker_clock_is_not_frame_synchronous_and_spans_the_frames(syn):
    t = syn.tracker_timestamps
    assert t[0] < syn.timestamps[0] and t[-1] > syn.timestamps[-1]
    assert np.diff(t).mean() == pytest.approx(1 / 40.0)
    assert np.min(np.abs(t[:, None] - syn.timestamps[None, :])) > 1e-4


@pytest.mark.parametrize("gap", [[10, 14], [0, 4], [25, 29], [12, 14], [3, 26]])
def test_tracker_gap_flags_exactly_its_frames(gap):
    """The reader flags exactly frames first..last: frames first - 1 and last + 1 keep their
    tracker (a [10, 14] gap flagged frame 9 too, [5, 6] flagged 4..7; review 44)."""
    scene = generate_fetoscopy(FetoscopyOptions(n_frames=30, laps=0.8, tracker_gap=gap,
                                                width=64, height=64))
    dropped = ~scene.tracker_valid
    assert dropped.any() and np.isnan(scene.tracker_translations[dropped]).all()
    samples = TrackingSamples(
        scene.tracker_timestamps,
        scene.tracker_translations,
        scene.tracker_quaternions,
        scene.tracker_valid,
    )
    _, valid = interpolate_camera_poses(samples, scene.timestamps, scene.hand_eye,
                                        allow_outside=True)
    frames = np.arange(30)
    np.testing.assert_array_equal(~valid, (frames >= gap[0]) & (frames <= gap[1]))


# -- black frames, options -------------------------------------------------------------------


def test_black_frames_are_zero():
    scene = generate_fetoscopy(
        FetoscopyOptions(n_frames=60, laps=1.5, black_frames=PAPER_BLACK_FRAMES)
    )
    for k in range(scene.n_frames):
        assert scene.render(k).any() != (k in PAPER_BLACK_FRAMES)
    assert PAPER_BLACK_FRAMES == [7, 11, 12, 23, 24, 37, 38, 42, 43, 45, 51, 54]


@pytest.mark.parametrize(
    "options, match",
    [
        (FetoscopyOptions(n_frames=20, black_frames=[3, 20]), r"black_frames: frame 20 outside"),
        (FetoscopyOptions(motion="robot"), r"motion: expected one of"),
        (FetoscopyOptions(tracker_gap=[5]), r"tracker_gap: expected \[first, last\]"),
        (FetoscopyOptions(fps=0.0), r"fps: must be > 0"),
    ],
)
def test_bad_fetoscopy_options_raise(options, match):
    with pytest.raises(ValueError, match=match):
        generate_fetoscopy(options)


@pytest.mark.parametrize(
    "options, match",
    [
        (PcleOptions(trajectory="square"), r"trajectory: expected one of"),
        (
            PcleOptions(trajectory="spiral", spiral_inner_um=600.0),
            r"spiral_inner_um: must be below",
        ),
        (PcleOptions(speed_um_per_frame=-1.0), r"speed_um_per_frame: must be > 0"),
    ],
)
def test_bad_pcle_options_raise(options, match):
    with pytest.raises(ValueError, match=match):
        generate_pcle(options)


# Every float option of every simulator, NaN and +-inf: refused by name before any work.
_GENERATORS = {FetoscopyOptions: generate_fetoscopy, PcleOptions: generate_pcle,
               CheckerboardOptions: generate_checkerboard}
_FLOAT_OPTIONS = [(cls, f.name) for cls in _GENERATORS for f in dataclasses.fields(cls)
                  if isinstance(f.default, float)]


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
@pytest.mark.parametrize("cls, name", _FLOAT_OPTIONS,
                         ids=[f"{c.__name__}.{n}" for c, n in _FLOAT_OPTIONS])
def test_non_finite_float_options_are_refused_by_name(cls, name, value):
    with pytest.raises(ValueError, match=rf"^{cls.__name__}\.{name}: must be a finite number, "
                                         rf"got {value}$"):
        _GENERATORS[cls](cls(**{name: value}))


def test_float_options_cover_the_audited_ones():
    names = {f"{c.__name__}.{n}" for c, n in _FLOAT_OPTIONS}
    assert {"CheckerboardOptions.tracker_delay_s", "CheckerboardOptions.tracker_offset_s",
            "CheckerboardOptions.hand_eye_rot_deg", "CheckerboardOptions.hand_eye_offset_mm",
            "CheckerboardOptions.k1", "FetoscopyOptions.hand_eye_rot_deg",
            "FetoscopyOptions.hand_eye_offset_mm", "PcleOptions.robot_offset_s"} <= names
    assert len(_FLOAT_OPTIONS) > 60


@pytest.mark.parametrize(
    "kind, flags, message",
    [
        ("checkerboard", ["--tracker-delay-s", "nan"], "--tracker-delay-s: must be a finite num"),
        ("checkerboard", ["--tracker-offset-s", "nan"], "--tracker-offset-s: must be a finite "),
        ("checkerboard", ["--hand-eye-rot-deg", "nan"], "--hand-eye-rot-deg: must be a finite "),
        ("checkerboard", ["--k1", "nan"], "--k1: must be a finite number, got nan"),
        ("checkerboard", ["--k1", "-5"],
         r"--k1, --k2, --p1, --p2: \[-5\.0, 0\.1, 0\.0008, -0\.0005\] is not invertible over "
         r"the 480x480 frame \(the model folds over\)"),
        ("checkerboard", ["--fisheye", "-3", "0", "0", "0"],
         r"--fisheye: \[-3\.0, 0\.0, 0\.0, 0\.0\] is not invertible over the 480x480 frame"),
        ("checkerboard", ["--tracker-delay-s", "11"], r"--tracker-delay-s: must be within \+-10 s"),
        ("checkerboard", ["--hand-eye-rot-deg", "1e300"], r"--hand-eye-rot-deg: must be within"),
        ("checkerboard", ["--tracker-rate-hz", "1e300"],
         r"--tracker-rate-hz: 1e\+300 Hz over the 0\.92 s of the frames .* samples; at "
         r"most 1e\+07"),
        ("checkerboard", ["--fps", "1e-300"], r"--fps: 24 frames at 1e-300 fps span"),
        ("fetoscopy", ["--hand-eye-offset-mm", "nan"], "--hand-eye-offset-mm: must be a finite"),
        ("fetoscopy", ["--hand-eye-offset-mm", "2000"], r"--hand-eye-offset-mm: must be within"),
        ("fetoscopy", ["--tracker-offset-s", "1e6"], r"--tracker-offset-s: must be within"),
        ("pcle", ["--robot-rate-hz", "1e-300"], r"--robot-rate-hz: 1e-300 Hz .* beyond the "),
    ],
)
def test_simulate_refuses_bad_options_naming_the_flag_and_writes_nothing(
        kind, flags, message, tmp_path, capsys):
    out = tmp_path / "sim"
    size = {"checkerboard": ["--n-views", "3"], "fetoscopy": ["--n-frames", "3"],
            "pcle": ["--n-frames", "3"]}[kind]
    assert main(["simulate", kind, str(out), *size, *flags, "--quiet"]) == 2
    assert re.search(message, capsys.readouterr().err)
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_checkerboard_lens_gets_the_fetoscopy_invertibility_check(tmp_path):
    """The same lens is refused by both simulators with the same reason, through the API."""
    lens = [-3.0, 0.0, 0.0, 0.0]
    with pytest.raises(ValueError, match=r"^FetoscopyOptions\.lens_distortion: \[-3\.0, 0\.0, "
                                         r"0\.0, 0\.0\] is not invertible over the 400x400 frame"):
        generate_fetoscopy(FetoscopyOptions(n_frames=3, lens_distortion=lens))
    with pytest.raises(ValueError, match=r"^CheckerboardOptions\.k1, CheckerboardOptions\.k2, "
                                         r"CheckerboardOptions\.p1, CheckerboardOptions\.p2: "
                                         r"\[-3\.0, 0\.0, 0\.0, 0\.0\] is not invertible over "
                                         r"the 400x400 frame"):
        simulate_checkerboard(tmp_path / "cb", CheckerboardOptions(
            width=400, height=400, k1=-3.0, k2=0.0, p1=0.0, p2=0.0, n_views=3))
    assert not (tmp_path / "cb").exists()


def test_points_beyond_the_lens_fold_are_not_on_the_inner_branch():
    """k1 -0.5: r_d = r (1 - 0.5 r^2) peaks at r = 0.816; a point at r = 1.25 projects to
    r_d = 0.273, inside the frame, but the frame shows the ray at r = 0.29 there."""
    K = np.array([[480.0, 0, 150], [0, 480.0, 150], [0, 0, 1]])
    d = np.array([-0.5, 0.0, 0.0, 0.0])
    points = np.array([[0.3, 0.0, 1.0], [1.25, 0.0, 1.0]])
    uv = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, d)[0].reshape(-1, 2)
    assert 0 <= uv[1, 0] < 300  # both in a 300 x 300 frame
    assert on_inner_branch(uv[:1], points[:1], K, d, "pinhole")
    assert not on_inner_branch(uv[1:], points[1:], K, d, "pinhole")
    assert not on_inner_branch(uv, points, K, d, "pinhole")


def test_fetoscopy_frame_lists_must_be_whole_numbers():
    for name, value in (("tracker_gap", [1, float("nan")]), ("black_frames", [2.5])):
        with pytest.raises(ValueError, match=rf"^FetoscopyOptions\.{name}: expected frame "
                                             r"indices \(whole numbers\)"):
            generate_fetoscopy(FetoscopyOptions(n_frames=5, **{name: value}))


# -- determinism -----------------------------------------------------------------------------


def test_fetoscopy_is_deterministic_with_a_seed(syn):
    again = generate_fetoscopy(SYN)
    np.testing.assert_array_equal(again.texture, syn.texture)
    np.testing.assert_array_equal(again.tracker_poses, syn.tracker_poses)
    np.testing.assert_array_equal(again.render(5), syn.render(5))
    other = generate_fetoscopy(FetoscopyOptions(n_frames=24, laps=SYN.laps, seed=4))
    assert not np.array_equal(other.texture, syn.texture)
    assert not np.array_equal(other.tracker_poses, syn.tracker_poses)


def test_pcle_is_deterministic_with_a_seed(pcle):
    again = generate_pcle(PCLE)
    np.testing.assert_array_equal(again.render(3), pcle.render(3))
    np.testing.assert_array_equal(again.robot_noisy_xy_um, pcle.robot_noisy_xy_um)
    other = generate_pcle(PcleOptions(radius_um=250.0, seed=8))
    assert not np.array_equal(other.render(3), pcle.render(3))


def test_textures_are_seeded_and_shaped():
    a = placenta_texture((100, 120), np.random.default_rng(0))
    assert a.shape == (100, 120, 3) and a.dtype == np.uint8
    np.testing.assert_array_equal(a, placenta_texture((100, 120), np.random.default_rng(0)))
    assert a[..., 2].mean() > a[..., 1].mean() > a[..., 0].mean()  # reddish (BGR)
    c = cell_texture((90, 80), np.random.default_rng(0))
    assert c.shape == (90, 80) and c.dtype == np.uint8 and c.std() > 15
    f = fibre_bundle_pattern((96, 96), np.random.default_rng(0))
    assert f.dtype == np.float32 and f.max() == pytest.approx(1.0)
    # ~3 px hexagonal spacing: one core per 3^2 * sqrt(3)/2 ~ 7.8 px^2.
    peaks = (f == cv2.dilate(f, np.ones((3, 3), np.uint8))) & (f > 0.2)
    assert peaks.sum() == pytest.approx(96 * 96 / 7.8, rel=0.15)


# -- pCLE ------------------------------------------------------------------------------------


def _shift(a, b):
    """Integer translation of image b relative to image a (px) and its NCC score: a centred
    template of 3/5 of a (paper 004 Sec. III-D) matched in b, after a 1 px blur that removes
    most of the static fibre honeycomb."""
    a = cv2.GaussianBlur(a.astype(np.float32), (0, 0), 1.0)
    b = cv2.GaussianBlur(b.astype(np.float32), (0, 0), 1.0)
    h, w = a.shape
    th, tw = int(0.6 * h), int(0.6 * w)
    y0, x0 = (h - th) // 2, (w - tw) // 2
    score = cv2.matchTemplate(b, a[y0 : y0 + th, x0 : x0 + tw], cv2.TM_CCOEFF_NORMED)
    _, best, _, (x, y) = cv2.minMaxLoc(score)
    return np.array([x - x0, y - y0]), best


def test_pcle_shape_rates_and_events(pcle):
    assert pcle.size == (512, 448)
    assert pcle.render(0).shape == (448, 512) and pcle.render(0).dtype == np.uint8
    assert np.diff(pcle.timestamps).mean() == pytest.approx(0.1)
    assert np.diff(pcle.robot_timestamps).mean() == pytest.approx(0.02)
    assert pcle.robot_timestamps[0] < 0 < pcle.timestamps[-1] < pcle.robot_timestamps[-1]
    assert pcle.contact_loss.any() and pcle.stick_slip.any()
    assert not pcle.contact_loss[0] and not pcle.stick_slip[0]
    assert not (pcle.contact_loss & pcle.stick_slip).any()


def test_pcle_ground_truth_is_the_image_translation(pcle):
    # Frame k shows tissue p_k + u, so content at pixel u of frame k-1 is at u + p_{k-1} - p_k
    # in frame k. Checked on pairs in good contact, with steps inside the template's reach.
    good = pcle.contrast > 0.5
    checked = 0
    for k in range(1, pcle.n_frames):
        truth = (pcle.positions_um[k - 1] - pcle.positions_um[k]) / PCLE.pixel_size_um
        if good[k - 1] and good[k] and np.abs(truth).max() < 80:
            measured, score = _shift(pcle.render(k - 1), pcle.render(k))
            assert np.abs(measured - truth).max() <= 1.0, k
            assert score > 0.9
            checked += 1
    assert checked > pcle.n_frames // 2
    np.testing.assert_allclose(pcle.homographies[:, :2, 2], pcle.positions_um / 1.0)


def test_pcle_frames_freeze_during_stick_slip(pcle):
    robot_at_frames = np.stack(
        [
            np.interp(pcle.timestamps, pcle.robot_timestamps, pcle.robot_xy_um[:, j])
            for j in range(2)
        ],
        1,
    )
    frozen = 0
    for k in np.flatnonzero(pcle.stick_slip[1:] & pcle.stick_slip[:-1]) + 1:
        robot_step = np.linalg.norm(robot_at_frames[k] - robot_at_frames[k - 1])
        shift, score = _shift(pcle.render(k - 1), pcle.render(k))
        assert robot_step > 30.0
        if not shift.any() and score > 0.99:
            frozen += 1
    assert frozen >= 2
    # Outside the events the image follows the robot to < 1 µm.
    ok = ~pcle.stick_slip
    np.testing.assert_allclose(pcle.positions_um[ok], robot_at_frames[ok], atol=1.0)
    # ... and the slip jump catches up: the image moves more than the robot in some frame.
    steps = np.linalg.norm(np.diff(pcle.positions_um, axis=0), axis=1)
    assert steps.max() > 2.5 * PCLE.speed_um_per_frame


def test_pcle_frames_lose_contrast_during_contact_loss(pcle):
    # Tissue structure (cells ~12 um) survives a sigma-2 px blur, the fibre honeycomb (3 px)
    # and pixel noise do not: the blurred std measures the tissue contrast.
    contrast = np.array(
        [
            cv2.GaussianBlur(pcle.render(k).astype(np.float32), (0, 0), 2.0).std()
            for k in range(pcle.n_frames)
        ]
    )
    lost = pcle.contrast < 0.2
    assert lost.any()
    assert contrast[lost].max() < 0.4 * np.median(contrast[~pcle.contact_loss])
    # ... the fade is smooth: frames with 0.2 <= c < 0.8 sit in between.
    mid = (pcle.contrast >= 0.2) & (pcle.contrast < 0.8)
    assert np.all(contrast[mid] > contrast[lost].max())
    # ... and what remains is fibre-bundle noise: the unblurred image still has texture.
    k = int(np.argmin(pcle.contrast))
    assert pcle.render(k).std() > 5


def test_pcle_noisy_robot_drifts_from_the_robot(pcle):
    err = np.linalg.norm(pcle.robot_noisy_xy_um - pcle.robot_xy_um, axis=1)
    assert err[0] == 0.0 and err.max() > 20.0
    # Noise is on velocities, integrated: the error is a smooth random walk, not jitter.
    assert np.abs(np.diff(err)).max() < 0.1 * err.max()


def test_pcle_spiral_has_lines_at_both_ends():
    scene = generate_pcle(
        PcleOptions(
            trajectory="spiral",
            radius_um=300.0,
            spiral_turns=1.0,
            line_um=200.0,
            n_frames=0,
            contact_loss=False,
            stick_slip=False,
        )
    )
    xy = scene.robot_xy_um[(scene.robot_timestamps >= 0)]
    v = np.diff(xy, axis=0)
    heading = np.unwrap(np.arctan2(v[:, 1], v[:, 0]))
    n_line = int(200.0 / (40.0 * 10.0) * 50.0) - 2
    assert np.ptp(heading[:n_line]) < 1e-6 and np.ptp(heading[-n_line:]) < 1e-6
    assert np.ptp(heading) > 2 * np.pi * 0.9


# -- datasets on disk ------------------------------------------------------------------------


def test_simulate_fetoscopy_writes_a_readable_dataset(tmp_path):
    opts = FetoscopyOptions(motion="handheld", n_frames=8, black_frames=[2], seed=2)
    root = simulate_fetoscopy(tmp_path / "feto", opts)
    scene = generate_fetoscopy(opts)
    ds = read_dataset(root)
    assert len(ds) == 8 and ds.camera.fov_mask_radius == pytest.approx(192.0)
    np.testing.assert_allclose(ds.camera.camera_matrix, scene.camera_matrix)
    np.testing.assert_allclose(ds.ground_truth, scene.homographies, atol=1e-12)
    np.testing.assert_allclose(ds.hand_eye, scene.hand_eye, atol=1e-12)
    np.testing.assert_array_equal(ds.frames[3], scene.render(3))
    assert not ds.frames[2].any()
    # EMT poses read back through the hand-eye: truth + noise of the configured size.
    assert ds.pose_valid.all()
    err = np.abs(ds.cam_from_world - scene.poses)
    assert 0.05 < err[:, 3:].mean() < 3.0
    poses = np.loadtxt(root / "truth_poses.csv", delimiter=",", skiprows=1)
    np.testing.assert_array_equal(poses[:, 0], np.arange(8))
    np.testing.assert_allclose(poses[:, 1:], scene.poses, atol=1e-12)
    plane = json.loads((root / "truth_plane.json").read_text())
    np.testing.assert_allclose(plane["plane"], scene.plane)
    np.testing.assert_allclose(np.asarray(plane["normal"]) / plane["distance_mm"], scene.plane)
    assert plane["distance_mm"] > 0
    with pytest.raises(ValueError, match="exists and is not empty"):
        simulate_fetoscopy(root, opts)


def test_simulate_pcle_writes_a_readable_dataset(tmp_path):
    opts = PcleOptions(n_frames=6, seed=9)
    root = simulate_pcle(tmp_path / "pcle", opts)
    scene = generate_pcle(opts)
    ds = read_dataset(root)
    assert len(ds) == 6 and ds.camera.pixel_size_um == 1.0 and ds.camera.camera_matrix is None
    np.testing.assert_allclose(ds.ground_truth, scene.homographies, atol=1e-12)
    np.testing.assert_array_equal(ds.frames[4], scene.render(4))
    assert ds.robot_valid.all()
    # Linear interpolation of the 50 Hz robot samples on a 500 um circle: chord error < 0.1 um.
    np.testing.assert_allclose(ds.robot_xy_um - ds.robot_xy_um[0], scene.positions_um, atol=0.1)
    noisy = read_dataset(root, robot_file="robot_noisy.csv")
    assert not np.allclose(noisy.robot_xy_um, ds.robot_xy_um)
    events = np.loadtxt(root / "events.csv", delimiter=",", skiprows=1)
    assert (root / "events.csv").read_text().startswith("frame,contact_loss,stick_slip")
    np.testing.assert_array_equal(events[:, 1], scene.contact_loss)
    np.testing.assert_array_equal(events[:, 2], scene.stick_slip)
    positions = np.loadtxt(root / "truth_positions.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(positions[:, 2:], scene.positions_um)


def test_pcle_circular_field_of_view(tmp_path):
    """--fov-mask-radius: frames black outside the circle, camera.yaml carries the radius."""
    from fusedmosaic.io import read_dataset
    from fusedmosaic.simulation import PcleOptions, generate_pcle, simulate_pcle

    options = PcleOptions(n_frames=3, width=96, height=80, fov_mask_radius=30.0)
    scene = generate_pcle(options)
    frame, inside = scene.render(1), scene.fov_mask()
    assert inside.sum() == pytest.approx(np.pi * 30**2, rel=0.05)
    assert not frame[~inside].any() and frame[inside].mean() > 20
    ds = read_dataset(simulate_pcle(tmp_path / "d", options), robot_file="robot.csv")
    assert ds.camera.fov_mask_radius == pytest.approx(30.0)
    np.testing.assert_array_equal(ds.camera.fov_mask() > 0, inside)
    with pytest.raises(ValueError, match="fov_mask_radius: a field of at least 16 px"):
        PcleOptions(fov_mask_radius=5.0).validate()
