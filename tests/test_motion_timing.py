"""The constant-velocity prior follows the frame timestamps (estimation/motion.py motion_timing):
frames dropped from a recording (or by a live source falling behind) no longer make the prior
predict half the motion across the gap."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fusedmosaic import _core
from fusedmosaic.estimation.bundle import BundleOptions, run_ba_emt
from fusedmosaic.estimation.motion import (
    CHI2_6_MEDIAN,
    MOTION_GATE_CHI2,
    RELEASED,
    estimate_motion_sigma,
    motion_departure_scale,
    motion_timing,
    tracker_motion_breaks,
    tracker_motion_departure,
)
from fusedmosaic.estimation.sequential import SequentialOptions, run_lba_emt
from fusedmosaic.evaluation import frame_errors
from fusedmosaic.io import read_dataset
from fusedmosaic.registration.features import FeatureOptions
from fusedmosaic.simulation import (
    PAPER_BLACK_FRAMES,
    FetoscopyOptions,
    generate_fetoscopy,
    plane_point_pairs,
    simulate_fetoscopy,
)

# Scenarios built on few keypoints (small or round frames) keep them: SIFT's low-contrast retry
# (FeatureOptions.sift_min_features) would detect such frames again at a lower threshold.
FEW = FeatureOptions(sift_min_features=0)


def test_motion_timing():
    assert motion_timing(0.0, 0.04, 0.08, 0.04) == (1.0, 1.0)  # evenly spaced: Eq. 16
    assert motion_timing(0.0, 0.04, 0.0801, 0.04) == (1.0, 1.0)  # clock jitter within 1 %
    ratio, scale = motion_timing(0.0, 0.04, 0.12, 0.04)  # one frame dropped before k
    assert ratio == pytest.approx(2.0) and scale == pytest.approx(np.sqrt(4 * 3 / 2))
    ratio, scale = motion_timing(0.0, 0.08, 0.12, 0.04)  # one frame dropped before k-1
    assert ratio == pytest.approx(0.5) and scale == pytest.approx(np.sqrt(1 * 3 / 2))
    for args in ((0.0, 0.04, 0.12, None), (0.0, np.nan, 0.12, 0.04), (0.0, 0.04, 0.04, 0.04)):
        assert motion_timing(*args) == (1.0, 1.0)  # unknown or not increasing: Eq. 16
    # close times: the prior is not made far stiffer, nor a short d1 extrapolated far
    assert motion_timing(0.0, 0.04, 0.046, 0.04) == (pytest.approx(0.15), 0.25)
    ratio, scale = motion_timing(0.0, 0.006, 0.046, 0.04)
    assert ratio == pytest.approx(40 / 6) and scale == pytest.approx(40 / 6 / 8)  # ratio / 8


def test_a_long_gap_breaks_the_motion_prior():
    """An interval more than 8 times the other, or above MOTION_MAX_GAP_S (1 s) and 8 nominal
    intervals, releases C_p: zero velocity, no term (an infinite sigma scale), before the gap
    (d2) and after it (d1)."""
    assert RELEASED == (0.0, np.inf)
    assert motion_timing(0.0, 0.04, 60.04, 0.04) == RELEASED  # the pause before frame k
    assert motion_timing(0.0, 60.0, 60.04, 0.04) == RELEASED  # and the frame after it
    assert motion_timing(0.0, 0.04, 0.36, 0.04)[0] == pytest.approx(8.0)  # 7 frames dropped
    assert motion_timing(0.0, 0.04, 0.37, 0.04) == RELEASED
    assert motion_timing(0.0, 0.33, 0.37, 0.04) == RELEASED
    assert motion_timing(0.0, 0.04, 0.04 + 1e-9, 0.04) == RELEASED  # a repeated frame
    assert motion_timing(0.0, 1e-9, 0.04, 0.04) == RELEASED
    # both intervals long: 1 s and 8 nominal intervals (1 s alone when it is unknown)
    assert motion_timing(0.0, 1.0, 2.0, 0.04)[0] == pytest.approx(1.0)
    assert motion_timing(0.0, 1.05, 2.1, 0.04) == RELEASED
    assert motion_timing(0.0, 1.05, 2.1, None) == RELEASED
    # a slow recording (one frame every 2 s) stays linked up to 8 of its intervals
    assert motion_timing(0.0, 2.0, 4.0, 2.0) == (1.0, 1.0)
    assert motion_timing(0.0, 2.0, 18.0, 2.0)[0] == pytest.approx(8.0)
    assert motion_timing(0.0, 2.0, 18.1, 2.0) == RELEASED
    assert motion_timing(0.0, 16.0, 32.0, 2.0)[0] == pytest.approx(1.0)
    assert motion_timing(0.0, 17.0, 34.0, 2.0) == RELEASED
    assert motion_timing(0.0, 17.0, 34.0, 2.0, max_gap_s=None)[0] == pytest.approx(1.0)


@pytest.mark.parametrize("solver", ["bundle", "window"])
def test_a_released_prior_adds_no_term_and_starts_at_the_previous_camera(solver):
    """A gap between frames 3 and 4 releases the C_p of frames 4 and 5 (motion_sigma_scale
    inf): the C++ problems leave those terms out, and frame 4, without a tracker sample, starts
    (and, with nothing else on it, stays) at frame 3's starting pose (ratio 0)."""
    scene = generate_fetoscopy(FetoscopyOptions(n_frames=6, width=200, height=200,
                                                laps=6 / 152, seed=3))
    K, poses = scene.camera_matrix, scene.poses

    def timing(k, gap):
        return RELEASED if gap and k in (4, 5) else (1.0, 1.0)

    def solve(gap):
        if solver == "bundle":
            ba = _core.BundleAdjuster(K, _core.BundleAdjusterOptions())
            for k in range(6):
                ba.add_frame(k, poses[k] if k != 4 else poses[3],
                             poses[k] if k != 4 else None, *timing(k, gap))
            ba.set_plane(scene.plane)
            summary = ba.solve()
            return summary.num_motion_blocks, summary.num_residuals, ba.pose(4)
        w = _core.SlidingWindow(K, _core.SlidingWindowOptions())
        w.set_plane(scene.plane)
        for k in range(6):
            w.add_frame(k, poses[k] if k < 3 else None, poses[k] if k != 4 else None,
                        fixed=k < 3, motion_ratio=timing(k, gap)[0],
                        motion_sigma_scale=timing(k, gap)[1])
        summary = w.step([])
        return None, summary.num_residuals, w.pose(4)

    motion, residuals, _ = solve(gap=False)
    motion_gap, residuals_gap, pose4 = solve(gap=True)
    assert residuals - residuals_gap == 2 * 6  # two 6-residual C_p terms fewer
    if solver == "bundle":
        assert (motion, motion_gap) == (4, 2)
    # frame 3's starting pose, its tracker sample (the solve then moves frame 3, not frame 4)
    np.testing.assert_allclose(pose4, poses[3], atol=1e-9)


def test_motion_sigma_from_a_recording_in_any_row_order_with_gaps(tmp_path):
    """--motion-sigma-from's truth_poses.csv: rows in frame order whatever the file's (before:
    shuffled rows gave second differences of unrelated poses), a gap in the frame ids is not
    one constant-velocity step, and a still recording is said, not floored silently."""
    from fusedmosaic.estimation.motion import (
        constant_velocity_residuals,
        motion_sigma_from_recording,
    )
    from fusedmosaic.estimation.world import poses_to_aligned, world_alignment
    from fusedmosaic.io import write_poses_csv

    poses = generate_fetoscopy(FetoscopyOptions(n_frames=40, seed=3)).poses
    ids = np.arange(40)
    write_poses_csv(tmp_path / "ordered.csv", ids, poses)
    expected = estimate_motion_sigma(poses)
    np.testing.assert_allclose(motion_sigma_from_recording(tmp_path / "ordered.csv"), expected,
                               rtol=1e-12)
    shuffled = np.random.default_rng(0).permutation(40)
    write_poses_csv(tmp_path / "shuffled.csv", ids[shuffled], poses[shuffled])
    np.testing.assert_allclose(motion_sigma_from_recording(tmp_path / "shuffled.csv"), expected,
                               rtol=1e-12)
    keep = np.r_[0:20, 25:40]  # frames 20-24 missing: the triples across the gap are left out
    write_poses_csv(tmp_path / "gap.csv", ids[keep], poses[keep])
    aligned = poses_to_aligned(poses[keep], world_alignment(poses[keep]))
    r = np.vstack([constant_velocity_residuals(aligned[:20]),
                   constant_velocity_residuals(aligned[20:])])
    halves = np.sqrt(np.mean(r**2, axis=0))
    gap = motion_sigma_from_recording(tmp_path / "gap.csv")
    # tx, ty (SYN moves in a plane at constant rotation: the others are floored)
    np.testing.assert_allclose(gap[3:5], halves[3:5], rtol=1e-9)
    assert not np.allclose(gap[3:5], estimate_motion_sigma(poses[keep])[3:5], rtol=1e-2)
    # every other frame (evenly spaced, but two frames a step): no triple is one frame's motion
    write_poses_csv(tmp_path / "stride2.csv", ids[::2], poses[::2])
    with pytest.raises(ValueError, match=r"stride2\.csv: poses: no three consecutive frames "
                       r"\(ids k-2, k-1, k\) with finite poses"):
        motion_sigma_from_recording(tmp_path / "stride2.csv")
    write_poses_csv(tmp_path / "still.csv", ids, np.repeat(poses[:1], 40, axis=0))
    with pytest.warns(UserWarning, match=r"still\.csv: the camera's translations depart from "
                      r"constant velocity by at most 0 mm RMS per frame \(a still or perfectly "
                      r"smooth recording\), so Sigma_p's translations are floored at 0\.01 mm"):
        motion_sigma_from_recording(tmp_path / "still.csv")


@pytest.fixture(scope="module")
def black(tmp_path_factory):
    """Fig. 10's 62 frames with the paper's black frames, and Sigma_p estimated from an
    independent sequence of the same kind (Sec. 4.2)."""
    options = FetoscopyOptions(n_frames=62, laps=62 / 37.5, black_frames=list(PAPER_BLACK_FRAMES))
    root = simulate_fetoscopy(tmp_path_factory.mktemp("timing") / "black62", options)
    sigma = estimate_motion_sigma(generate_fetoscopy(replace(options, seed=100,
                                                             black_frames=None)).poses)
    return read_dataset(root), tuple(sigma)


def _without(ds, drop):
    keep = np.array([k for k in range(len(ds)) if k not in drop])
    return replace(ds, frames=[ds.frames[k] for k in keep], frame_ids=ds.frame_ids[keep],
                   timestamps=ds.timestamps[keep], cam_from_world=ds.cam_from_world[keep],
                   pose_valid=ds.pose_valid[keep], ground_truth=ds.ground_truth[keep]), keep


@pytest.mark.parametrize("drop", [[8, 13, 25, 39, 46], [8, 13, 25, 41]])
@pytest.mark.parametrize("method", ["ba-emt", "lba-emt"])
def test_dropped_frames_next_to_black_frames(black, method, drop):
    """Frames dropped next to black ones, which are placed from C_EMT + C_p. Measured, first
    list: black-frame e_M 0.86 (ba-emt) / 0.88 px (lba-emt); with the prior blind to the gaps
    (repeating one frame's motion over two) 14.3 / 14.1 px, worst 28 px; no frame dropped 0.53 /
    0.55 px. The second list ends lba-emt's 40-frame start-up on black frames 42-43, held for
    the next step (worst 27.9 px when that step re-solved them without the timing, 2.4 now)."""
    ds, sigma = black
    data, keep = _without(ds, drop)
    if method == "ba-emt":
        res = run_ba_emt(data, progress=False, options=BundleOptions(motion_sigma=sigma))
    else:
        res = run_lba_emt(data, progress=False, options=SequentialOptions(motion_sigma=sigma))
    e = frame_errors(res.homographies, data.ground_truth, ds.camera.width, ds.camera.height)
    is_black = np.isin(keep, PAPER_BLACK_FRAMES)
    assert np.mean(e[is_black]) < 2.0  # px
    assert np.max(e[is_black]) < 4.0
    assert np.mean(e[~is_black]) < 0.2


def test_nearly_coincident_timestamps(black):
    """Frames 22 and 36 repeated 1 ns after themselves (strictly increasing, so accepted): the
    floored timing keeps ba-emt converging (without the floor: no convergence, e_M 2.1 px)."""
    ds, sigma = black
    order = sorted([*range(len(ds)), 22, 36])
    data = replace(ds, frames=[ds.frames[k] for k in order], frame_ids=np.arange(len(order)),
                   timestamps=np.array([ds.timestamps[k] for k in order])
                   + np.r_[0, np.diff(order) == 0] * 1e-9,
                   cam_from_world=ds.cam_from_world[order], pose_valid=ds.pose_valid[order],
                   ground_truth=ds.ground_truth[order])
    assert np.all(np.diff(data.timestamps) > 0)
    res = run_ba_emt(data, progress=False, options=BundleOptions(motion_sigma=sigma))
    assert res.details["solver"]["termination"] == "CONVERGENCE"
    e = frame_errors(res.homographies, data.ground_truth, ds.camera.width, ds.camera.height)
    assert np.mean(e) < 0.5  # px (measured 0.215)


# ------------------------------------------------------------------ the motion gate


def test_tracker_motion_departure_on_a_smooth_motion_and_a_noisy_tracker():
    """tracker_motion_departure at samples with Sigma_EMT noise (1 deg, 1 mm) on a SYN motion,
    whose translations depart from constant velocity far less than Sigma_p's 15 mm: squared
    norm at most chi2(6) (median 2.3 against 5.35: the rotations' chi2(3) and small translation
    terms), the gate (chi2(6)'s 0.999 quantile) exceeded by <= 1 % of 298 triples. A jump of the
    motion breaks the triple at the jump; one sample turned 30 deg makes three triples depart
    (d, -2 d, d), the sample's doing, not the motion's (two consecutive ones four): with the
    samples after it known none breaks, without them only the first."""
    poses = generate_fetoscopy(FetoscopyOptions(n_frames=300, width=200, height=200,
                                                laps=8, seed=0)).poses
    emt = np.r_[[np.deg2rad(1.0)] * 3, [1.0] * 3]
    rng = np.random.default_rng(1)
    z = poses + rng.normal(0.0, 1.0, poses.shape) * emt
    sigma_p = _core.DEFAULT_MOTION_SIGMA
    even = None  # evenly spaced frames
    w = np.array([tracker_motion_departure(z[k - 2], z[k - 1], z[k], sigma_p, emt)
                  for k in range(2, len(z))])
    m2 = np.sum(w ** 2, axis=1)
    assert 0.3 * CHI2_6_MEDIAN < np.median(m2) < CHI2_6_MEDIAN
    assert np.mean(m2 > MOTION_GATE_CHI2) <= 0.01
    np.testing.assert_allclose(motion_departure_scale(w), 1.0, atol=0.2)  # nominal noise
    assert len(tracker_motion_breaks(z, even, sigma_p, emt)) <= 3

    def turn(poses, k, degrees):
        out = poses.copy()
        R = _core.rotation_from_angle_axis(np.array([np.deg2rad(degrees), 0.0, 0.0]))
        for j in range(k, len(out)) if k >= 0 else [-k]:
            out[j, :3] = _core.angle_axis_from_rotation(
                R @ _core.rotation_from_angle_axis(out[j, :3]))
        return out

    jumped = turn(z, 150, 30.0)  # from frame 150 on, turned 30 deg: the motion jumped
    assert {150, 151} <= set(tracker_motion_breaks(jumped, even, sigma_p, emt)) - {
        k for k in tracker_motion_breaks(z, even, sigma_p, emt)}
    glitch = turn(z, -150, 30.0)  # frame 150's sample alone
    assert tracker_motion_departure(*glitch[148:151], sigma_p, emt) @ tracker_motion_departure(
        *glitch[148:151], sigma_p, emt) > 3 * MOTION_GATE_CHI2
    # offline the samples after it are known: all three triples are the sample's doing
    assert not {150, 151, 152} & set(tracker_motion_breaks(glitch, even, sigma_p, emt))
    # two consecutive samples turned 30 deg: four triples depart, none breaks
    glitch2 = turn(turn(z, -150, 30.0), -151, 30.0)
    assert not set(range(150, 154)) & set(tracker_motion_breaks(glitch2, even, sigma_p, emt))
    # without the samples after it, frame 150 alone breaks (a turn and a bad sample look the
    # same at 150)
    assert tracker_motion_breaks(glitch[:151], even, sigma_p, emt) == [150]
    # a tracker 4x noisier than Sigma_EMT: the components its noise dominates (the rotations)
    # are scaled by their medians, so no more triples break than with the nominal noise
    noisy = poses + rng.normal(0.0, 4.0, poses.shape) * emt
    assert len(tracker_motion_breaks(noisy, even, sigma_p, emt)) <= 3
    assert 150 in tracker_motion_breaks(turn(noisy, 150, 90.0), even, sigma_p, emt)
    # a released triple (a pause) is not judged
    paused = np.arange(len(z), dtype=np.float64)
    paused[150:] += 20.0  # 20 frame intervals before frame 150
    assert 150 not in tracker_motion_breaks(glitch, paused, sigma_p, emt, nominal=1.0)


@pytest.mark.parametrize("solver", ["bundle", "window"])
@pytest.mark.parametrize("gate", [MOTION_GATE_CHI2, np.inf])
def test_a_solve_releases_a_motion_prior_its_solution_contradicts(solver, gate):
    """Frames 0 and 1 held at the same pose, frame 2 (no tracker sample) turned 10 deg about its
    optical axis, which its pairs show: C_p (0.25 deg) holds it back (at 7.5 deg: whitened
    squared norm 888 > 22.46), so the gate releases it and frame 2 follows its images; with the
    gate off (inf) it stays held back. A frame with a tracker sample at each of k-2, k-1, k
    (the tracker has judged the motion there), or without pairs, is not judged."""
    scene = generate_fetoscopy(FetoscopyOptions(n_frames=3, width=200, height=200, seed=3))
    K, pose = scene.camera_matrix, scene.poses[0]
    turned = pose.copy()
    R = _core.rotation_from_angle_axis(np.array([0.0, 0.0, np.deg2rad(10.0)]))
    turned[:3] = _core.angle_axis_from_rotation(R @ _core.rotation_from_angle_axis(pose[:3]))
    turned[3:] = R @ pose[3:]  # the same centre
    poses = np.stack([pose, pose, turned])
    pairs = plane_point_pairs(poses, scene.plane, K, 200, np.random.default_rng(0),
                              noise_px=0.5)
    costs = _core.BundleAdjusterOptions(motion_gate_chi2=gate)
    if solver == "bundle":
        ba = _core.BundleAdjuster(K, costs)
        for k in range(3):
            ba.add_frame(k, pose, pose if k < 2 else None)
            ba.set_constant_frame(k, k < 2)
        for pair in pairs:
            ba.add_pair(*pair)
        ba.set_plane(scene.plane)
        released = ba.solve().motion_released_ids
        got = ba.pose(2)
    else:
        w = _core.SlidingWindow(K, _core.SlidingWindowOptions(costs=costs))
        w.set_plane(scene.plane)
        for k in range(3):
            w.add_frame(k, pose if k < 2 else None, pose if k < 2 else None, fixed=k < 2)
        for pair in pairs:
            w.add_pair(*pair)
        released = w.step([]).motion_released_ids
        got = w.pose(2)
    turn = np.rad2deg(np.linalg.norm(_core.angle_axis_from_rotation(
        _core.rotation_from_angle_axis(got[:3])
        @ _core.rotation_from_angle_axis(pose[:3]).T)))
    if np.isfinite(gate):
        assert released == [2]
        assert turn == pytest.approx(10.0, abs=0.05)
    else:
        assert released == []
        assert 5.0 < turn < 9.9


def _spun_in(ds, lead_deg):
    """ds with black frames before it, tracked while the scope turned about x into frame 0's
    pose (lead_deg, the angles from frame 0's orientation, one frame apart)."""
    z0 = ds.cam_from_world[0]
    R0 = _core.rotation_from_angle_axis(z0[:3])
    dt = ds.timestamps[1] - ds.timestamps[0]
    lead = len(lead_deg)
    samples = []
    for a in lead_deg:
        R = _core.rotation_from_angle_axis(np.array([np.deg2rad(a), 0.0, 0.0])) @ R0
        samples.append(np.r_[_core.angle_axis_from_rotation(R), R @ R0.T @ z0[3:]])
    n = lead + len(ds.frames)
    return replace(
        ds, frames=[np.zeros_like(ds.frames[0])] * lead + list(ds.frames),
        frame_ids=np.arange(n), timestamps=np.r_[ds.timestamps[0] - dt * np.arange(lead, 0, -1),
                                                 ds.timestamps],
        cam_from_world=np.concatenate([np.reshape(samples, (-1, 6)), ds.cam_from_world]),
        pose_valid=np.r_[np.ones(lead, bool), ds.pose_valid],
        ground_truth=np.concatenate([np.repeat(np.eye(3)[None], lead, 0), ds.ground_truth]))


@pytest.mark.parametrize("method", ["ba-emt", "lba-emt"])
def test_a_scope_spun_in_does_not_turn_the_mosaic(tmp_path, method):
    """Five black frames tracked while the scope turned in at 30 deg per frame (150 ... 30 deg)
    and stopped at the first textured frame (24 textured frames, 200 px): C_p, 120 sigma_p off
    at the stop, pulled the textured frames: ba-emt 15.8 px e_M (43 px worst), lba-emt 584 px,
    against 1.43 / 1.71 px with five black frames tracked still at frame 0's pose (0.92 / 0.61
    without any: they take start-up places). The motion gate releases it: within 0.5 px of the
    still ones (measured ba-emt 1.44, lba-emt 1.69 px). (Measured with the paper's sigma_v of 1
    px; with the one measured on the recording (sigma_v_px "auto", session 49), the images
    resist C_p 120 x more: ba-emt 3.4 px without the gate. The scenario's check is made at 1 px.)"""
    root = simulate_fetoscopy(tmp_path / "syn", FetoscopyOptions(
        n_frames=24, width=200, height=200, laps=24 / 37.5, seed=3))
    ds = read_dataset(root)

    def e_M(lead, gate, sigma_v="auto"):
        data = _spun_in(ds, lead)
        if method == "ba-emt":
            res = run_ba_emt(data, progress=False, options=BundleOptions(
                motion_gate_chi2=gate, features=FEW, sigma_v_px=sigma_v))
        else:
            res = run_lba_emt(data, progress=False, options=SequentialOptions(
                bootstrap_frames=8, motion_gate_chi2=gate, features=FEW, sigma_v_px=sigma_v))
        released = res.details["motion_released"]  # in the report: the frames at the stop
        assert (released and max(released) <= len(lead) + 1) if np.isfinite(gate) and any(
            lead) else released == []
        G = res.homographies[len(lead):]
        return frame_errors(np.linalg.inv(G[0]) @ G, ds.ground_truth, 200, 200).mean()

    still = e_M([0] * 5, MOTION_GATE_CHI2)
    assert e_M([150, 120, 90, 60, 30], MOTION_GATE_CHI2) < still + 0.5
    # the gate is what does it (at the paper's sigma_v, where C_p pulls the images hardest)
    paper_still = e_M([0] * 5, MOTION_GATE_CHI2, 1.0)
    assert e_M([150, 120, 90, 60, 30], MOTION_GATE_CHI2, 1.0) < paper_still + 0.5
    assert e_M([150, 120, 90, 60, 30], np.inf, 1.0) > paper_still + 10.0


@pytest.mark.parametrize("glitched", [[13], [13, 14]])
def test_ba_emt_leaves_out_glitched_samples_on_black_frames(tmp_path, glitched):
    """ba-emt, 24 textured frames (200 px) with frames 13 (and 14) black and their tracker
    samples turned 20 deg: the samples on both sides show the motion passing them by
    (motion.motion_verdict), so C_p keeps linking every frame and the glitched samples are
    left out (details tracker_glitches). Measured e_M / worst: 0.99 / 2.2 px against 1.93 /
    13.5 px without the gate ([13]); 0.98 / 2.2 against 3.04 / 20.1 px ([13, 14])."""
    root = simulate_fetoscopy(tmp_path / "syn", FetoscopyOptions(
        n_frames=24, width=200, height=200, laps=24 / 37.5, seed=3))
    ds = read_dataset(root)
    frames, samples = list(ds.frames), ds.cam_from_world.copy()
    R = _core.rotation_from_angle_axis(np.array([np.deg2rad(20.0), 0.0, 0.0]))
    for k in glitched:
        frames[k] = np.zeros_like(frames[0])
        samples[k, :3] = _core.angle_axis_from_rotation(
            R @ _core.rotation_from_angle_axis(samples[k, :3]))
    data = replace(ds, frames=frames, cam_from_world=samples)
    errors = {}
    for gate in (MOTION_GATE_CHI2, np.inf):
        res = run_ba_emt(data, progress=False, options=BundleOptions(motion_gate_chi2=gate))
        assert res.details["motion_released"] == []
        assert res.details["tracker_glitches"] == (glitched if np.isfinite(gate) else [])
        errors[gate] = frame_errors(res.homographies, ds.ground_truth, 200, 200)
    on, off = errors[MOTION_GATE_CHI2], errors[np.inf]
    assert on.max() < 5.0 and on.max() < 0.5 * off.max()  # px
    assert on.mean() < off.mean()
