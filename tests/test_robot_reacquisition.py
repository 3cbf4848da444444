"""RobotPriorMosaicker (pCLE, paper 004) when the robot comes back after a dropout, and when a
call is interrupted half-way (review findings A and B).

A: the robot gate compares the robot displacement, taken from its last sample, with the image
registration. After a dropout the robot displacement spans every frame the image chain placed
alone, so their difference holds that chain's drift: the gate is widened once per frame spanned
and the returning robot corrects the drift instead of being gated and re-anchored at the drifted
position. A gross glitch is still gated. B: whatever interrupts a call after its input was
checked (even Ctrl-C between the filter update and the anchors), the state is put back.
"""

from dataclasses import replace

import numpy as np
import pytest
from _faults import raise_once

import fusedmosaic.estimation.translation as translation
from fusedmosaic.estimation.kalman import RobotKalmanFilter
from fusedmosaic.estimation.translation import RobotPriorMosaicker
from fusedmosaic.io import read_dataset
from fusedmosaic.simulation import PcleOptions, simulate_pcle

# A clean scan (no contact loss or stick-slip) with the perfect robot: without injected drift
# the image, the robot and the truth agree to a fraction of a pixel. 192x160 px: the gate's
# per-frame floor is half the smaller side, 80 px.
SCAN = PcleOptions(
    width=192,
    height=160,
    n_frames=64,
    speed_um_per_frame=12.0,
    radius_um=150.0,
    contact_loss=False,
    stick_slip=False,
)
FLOOR_PX = 80.0
DROPOUT = range(10, 50)  # robot samples missing (NaN): 40 frames placed by the image alone
RETURN = DROPOUT.stop  # the robot's first sample after the dropout
DRIFT_PX = 7.5  # x drift injected per registration during the dropout: 300 px in all
GLITCH_UM = 5000.0  # one grossly wrong robot sample (+5 mm, as in test_streaming_robustness)


@pytest.fixture(scope="module")
def pcle(tmp_path_factory):
    return read_dataset(simulate_pcle(tmp_path_factory.mktemp("pcle") / "scan", SCAN))


def _truth(pcle):
    return pcle.ground_truth[:, :2, 2]


def _feed(m, pcle, frames, robot, out=None):
    out = {} if out is None else out
    for k in frames:
        out[k] = m.add_frame(pcle.frames[k], pcle.timestamps[k], robot[k])
    return out


def _run(pcle, robot, monkeypatch=None, drift_frames=()):
    """The whole scan; registrations of `drift_frames` are biased by DRIFT_PX in x."""
    m = RobotPriorMosaicker(pcle.camera)
    if drift_frames:
        _drift_registrations(monkeypatch, m, drift_frames)
    return _feed(m, pcle, range(len(pcle)), robot)


def _drift_registrations(monkeypatch, m, frames):
    """An image chain drifting by DRIFT_PX per frame over `frames`, as a registration locking
    a little off would: NCC reports the biased displacement, while c_match (the SSIM of the
    overlap) is taken at the true one, so the frames stay trusted (c_img >= 0.5) and the bias
    is what the image chain accumulates, not a drop in confidence."""
    bias = np.array([DRIFT_PX, 0.0])
    register, ssim = translation.register_ncc, translation.aligned_overlap_ssim

    def biased_register(*args, **kwargs):
        result = register(*args, **kwargs)
        if m.frame_count in frames:  # the index of the frame being added
            return replace(result, dx=result.dx + bias)
        return result

    def true_ssim(previous, current, dx, **kwargs):
        if m.frame_count in frames:
            dx = dx - bias
        return ssim(previous, current, dx, **kwargs)

    monkeypatch.setattr(translation, "register_ncc", biased_register)
    monkeypatch.setattr(translation, "aligned_overlap_ssim", true_ssim)


def _errors(out, pcle, what="position"):
    """Per-frame distance (px) of FrameResult.<what> (position, position_robot, ...) from the
    truth, for `out` {frame: result} over every frame."""
    positions = np.stack([getattr(out[k], what) for k in sorted(out)])
    return np.linalg.norm(positions - _truth(pcle), axis=1)


def _gated(out):
    return [k for k, r in out.items() if r.robot_gated]


# -- A: the robot returning after a dropout corrects the image drift ----------------------------


def test_robot_returning_after_a_drifting_dropout_is_not_gated_and_corrects_the_drift(
    pcle, monkeypatch
):
    robot = pcle.robot_xy_um.copy()
    robot[DROPOUT] = np.nan
    out = _run(pcle, robot, monkeypatch, drift_frames=DROPOUT)
    err = _errors(out, pcle)
    drift = DRIFT_PX * len(DROPOUT)
    # through the dropout the frames follow the (drifting) image alone
    assert all(out[k].c_rob == 0.0 and out[k].status == "placed" for k in DROPOUT)
    assert err[RETURN - 1] == pytest.approx(drift, abs=2.0)
    # the robot's displacement at its return spans the dropout: it differs from the
    # registration by the whole drift, 3.75 times the per-frame gate (gated before the fix:
    # frames 50-52, then re-anchored at the drifted position, 300 px off for the rest of the run)
    r = out[RETURN]
    disagreement = np.abs(r.displacement_robot - r.displacement_image).max()
    assert disagreement == pytest.approx(drift, abs=2.0) and disagreement > 3.5 * FLOOR_PX
    assert r.c_img >= 0.5  # a trusted registration: the gate would look at this frame
    assert _gated(out) == []
    assert r.status == "placed" and r.c_rob > 0.0
    # Corrected: 300 -> 18 px measured, and it stays so. Not to 0: Eq. 17 compares the speed of
    # the robot's 41-frame displacement with the image's one-frame one (c_sp ~ 0), so Eq. 18
    # gives the robot c_rob ~ 1 - c_img ~ 0.13, and Eqs. 7-10 keep ~6 % of the drift.
    assert err[RETURN:].max() < 25.0, err[RETURN:]
    assert np.ptp(err[RETURN:]) < 0.5  # the robot is used again frame by frame, no new drift


@pytest.mark.parametrize(
    ("dropout", "glitch"),
    [(DROPOUT, RETURN + 6), (range(10, 15), 15), (DROPOUT, RETURN)],
    ids=["ordinary-frame", "return-after-5-frames", "return-after-40-frames"],
)
def test_a_gross_robot_glitch_is_still_gated(pcle, dropout, glitch):
    """+5 mm on one frame: after the robot came back, or at its return after a short or the
    long dropout (41 frames spanned; the bound is capped at 4 x 80 px)."""
    robot = pcle.robot_xy_um.copy()
    robot[dropout] = np.nan
    baseline = _run(pcle, robot)
    assert _gated(baseline) == []
    robot = robot.copy()
    robot[glitch, 0] += GLITCH_UM
    out = _run(pcle, robot)
    assert _gated(out) == [glitch]
    assert out[glitch].c_rob == 0.0 and out[glitch].displacement_robot[0] > 4000.0
    # the next sample is taken against the last good one: the run is the baseline again
    np.testing.assert_allclose(_errors(out, pcle), _errors(baseline, pcle), atol=0.5)


def test_the_widening_is_capped_so_a_glitch_after_a_long_dropout_is_gated(tmp_path):
    """Review 6 #1: widened once per missing frame without a cap, the bound passed 5 mm after 62
    missing frames here (63 x 80 px), the robot anchor moved to the glitch and the rebase locked
    it in: 4529 px off to the end of the scan. Capped at robot_gate_max_span (4) bounds, the
    glitch is gated after a 65-frame dropout, and the run is the one without it."""
    pcle = read_dataset(simulate_pcle(tmp_path / "long", replace(SCAN, n_frames=110)))
    robot = pcle.robot_xy_um.copy()
    robot[10:75] = np.nan
    baseline = _run(pcle, robot)
    assert _gated(baseline) == []
    robot[75, 0] += GLITCH_UM
    out = _run(pcle, robot)
    assert _gated(out) == [75]
    np.testing.assert_allclose(_errors(out, pcle), _errors(baseline, pcle), atol=0.5)
    assert _errors(out, pcle).max() < 5.0


def test_bad_span_cap_is_refused():
    with pytest.raises(ValueError, match="robot_gate_max_span must be an integer >= 1, got 0"):
        translation.RobotPriorOptions(robot_gate_max_span=0)


def _scan(tmp_path_factory, **options):
    """The simulator's default scan (512x448 px, contact loss in frames ~7-13), 60 frames: the
    image chain drifts (X_m 53-127 px mean off), the perfect robot does not."""
    root = simulate_pcle(tmp_path_factory.mktemp("pcle") / "scan",
                         PcleOptions(n_frames=60, **options))
    return read_dataset(root)


def _fused_errors(pcle, every):
    """X_f and X_m errors (px) with a robot sample on every `every`-th frame only, None between."""
    robot = pcle.robot_xy_um.copy()
    robot[np.arange(len(pcle)) % every != 0] = np.nan
    m = RobotPriorMosaicker(pcle.camera)
    out = [m.add_frame(pcle.frames[k], pcle.timestamps[k], robot[k]) for k in range(len(pcle))]
    err = np.hypot(*(np.stack([r.position for r in out]) - _truth(pcle)).T)
    image = np.hypot(*(np.stack([r.position_image for r in out]) - _truth(pcle)).T)
    return out, err, image


def test_a_robot_at_half_the_frame_rate_is_measured_and_weighed(tmp_path_factory):
    """Each sample's displacement spans 2 frames and feeds the sigma_r0 estimate
    (robot_sigma_max_span). Before, only one-frame spans did: sigma_r0 stayed inf for the whole
    scan, the robot had no weight and X_f was the drifting image chain (seed 1, with stick-slip:
    38.6 px mean vs 10.4 with a sample every frame; then 7.0, 5.6 with image gating, 7.2 with a
    sample every frame). Tolerance: within 1.5x of the same
    scan with a sample every frame, and under a third of the image chain's error."""
    pcle = _scan(tmp_path_factory, seed=1)
    _, every_frame, _ = _fused_errors(pcle, 1)
    out, err, image = _fused_errors(pcle, 2)
    assert np.isfinite(out[-1].sigma_robot0)
    assert err.mean() <= 1.5 * every_frame.mean(), (err.mean(), every_frame.mean())
    assert err.mean() < image.mean() / 3, (err.mean(), image.mean())


def test_the_robot_places_untrusted_frames_before_its_noise_is_measured(tmp_path_factory):
    """Seed 2, a robot sample every 3rd frame: the contact loss (frames 9-13) comes before
    sigma_r0 is measured (3 trusted samples). A sigma_r0 of inf there let registrations of
    confidence c_img ~0.1 place the frames, and the robot anchor kept their ~170 px error for
    good (X_f 138 px mean, worse than X_m's 127); then such a frame used KalmanOptions.sigma_robot0
    (18 px mean: at c_img 0.11 the paper's weighing leaves ~11 % of the correction out; 7.9
    since such registrations, far from the robot, were gated); now (review 47) a registration
    the filter does not trust before sigma_r0 is measured is left out, the robot placing the
    frame (6.7 px).
    Tolerance: under a third of the image chain's error."""
    pcle = _scan(tmp_path_factory, seed=2, stick_slip=False)
    out, err, image = _fused_errors(pcle, 3)
    assert any(r.c_img < 0.5 and np.isfinite(r.displacement_robot).all() for r in out[5:15])
    assert err.mean() < image.mean() / 3, (err.mean(), image.mean())


@pytest.mark.parametrize("stick_slip", [False, True])
def test_an_untrusted_registration_far_from_the_robot_is_left_out(tmp_path_factory, stick_slip):
    """A robot sampled at a third of the frame rate, interpolated to the frames (as `run`
    reads robot.csv): sigma_r0 measures its interpolation error, ~1.6 px, not the ~0.1 px of a
    robot sampled every frame. During the contact loss the registrations lock on the fibre
    pattern (0 px while the robot says ~40 px, c_img 0.11) and during stick-slip NCC sees the
    stuck tissue; the Eq. 9-10 weighing (sigma_img^2 = 1 / 0.11 against sigma_rob^2 = 1.6^2)
    let each such registration pull the frame ~7 px off the robot, for good in the chain.
    Image gating leaves them out. 256x224 px, 60 frames, seed 0: X_f 7.6 px mean without
    stick-slip, 40.3 with (robot alone 2.2 and 8.8); now 2.6 and 12.5. Tolerance: within 2x
    the robot alone."""
    root = simulate_pcle(tmp_path_factory.mktemp("pcle") / "third", PcleOptions(
        width=256, height=224, n_frames=60, robot_rate_hz=10.0 / 3.0, stick_slip=stick_slip))
    pcle = read_dataset(root)
    out = _run(pcle, pcle.robot_xy_um)
    err, robot = _errors(out, pcle), _errors(out, pcle, "position_robot")
    assert err.mean() < 2.0 * robot.mean(), (err.mean(), robot.mean())
    # registered consistently, yet placed by the robot alone, and flagged so
    gated = [k for k, r in out.items() if r.image_gated]
    assert any(out[k].ncc_consistent for k in gated)
    assert all(out[k].status == "prior-only" and out[k].c_img == 0.0
               and np.isfinite(out[k].displacement_image).all() for k in gated)
    # (what else is prior-only had no registration to gate)
    assert all(r.image_gated or not np.isfinite(r.displacement_image).all()
               for r in out.values() if r.status == "prior-only" and r.index > 0)
    batch = translation.run_kalman_robot(pcle, progress=False)
    assert batch.details["image_gated"] == gated


@pytest.mark.xfail(strict=True, reason=(
    "known limitation: Eq. 4 re-anchors the robot at X_f on every sample, reading a sparse "
    "robot's bounded interpolation error as drift (X_f 14.7 / 15.0 px vs the robot alone's "
    "11.5 / 13.2); a filtered robot offset fixed this case (212c674) but froze the offset after "
    "the warm-up and followed slowly drifting robots and offset steps (2-8x worse), reverted"))
@pytest.mark.parametrize("trajectory", ["circle", "spiral"])
def test_a_sparse_robot_through_stick_slip_is_not_worse_than_the_robot_alone(
        tmp_path_factory, trajectory):
    """A robot sampled at a third of the frame rate, interpolated to the frames (as `run` reads
    robot.csv), with stick-slip: 256x224 px, 120 frames, seed 0. Each trusted registration of a
    frame between two stuck ones (the tissue sticking again after a slip, c_img ~0.6, 20 px from
    the lagging robot) is partly fused and kept for good once the robot places the rest of the
    event. Tolerance: the robot alone's mean within 5 % (the fusion no worse than the better of
    its inputs; the image chain is 185 / 140 px off)."""
    root = simulate_pcle(tmp_path_factory.mktemp("pcle") / "sparse", PcleOptions(
        trajectory=trajectory, width=256, height=224, n_frames=120, robot_rate_hz=10.0 / 3.0))
    pcle = read_dataset(root)
    m = RobotPriorMosaicker(pcle.camera)
    out = _feed(m, pcle, range(len(pcle)), pcle.robot_xy_um)
    err, robot = _errors(out, pcle), _errors(out, pcle, "position_robot")
    assert err.mean() <= 1.05 * robot.mean(), (err.mean(), robot.mean())


def test_bad_image_gate_is_refused():
    with pytest.raises(ValueError, match="image_gate_sigmas must be a finite number > 0"):
        translation.RobotPriorOptions(image_gate_sigmas=0.0)


def test_an_unjudged_registration_does_not_veto_the_robot(tmp_path_factory):
    """A fast scan (600 µm/frame at 1 µm/px, 512x448 px frames: no two frames overlap): the
    registrations fail or lock on the fibre pattern at ~0 px, so the filter never leaves its
    warm-up and such a lock came with c_img = c_img0 = 1; the gate took it as trusted and vetoed
    the correct robot: 4 of 30 frames 550-670 px off (84.6 px mean vs 4.2 for the robot alone).
    Tolerance: within 1 px of the robot alone (the perfect robot is the only information)."""
    root = simulate_pcle(tmp_path_factory.mktemp("pcle") / "fast", PcleOptions(
        n_frames=30, speed_um_per_frame=600.0, radius_um=3000.0, seed=8))
    pcle = read_dataset(root)
    out = _run(pcle, pcle.robot_xy_um)
    err, robot = _errors(out, pcle), _errors(out, pcle, "position_robot")
    assert not _gated(out)
    assert err.max() < robot.max() + 1.0, (err.round(0), robot.round(0))
    # registered (an NCC score) but placed by the robot alone
    unjudged = [r for r in out.values() if np.isfinite(r.ncc_score) and r.status == "prior-only"]
    assert unjudged and all(r.c_img == 0.0 and r.c_rob == 1.0 for r in unjudged)


def test_a_glitch_after_the_first_agreement_is_still_gated_in_the_warm_up(pcle):
    """The warm-up exception needs no registration to have agreed with the robot yet: a +5 mm
    glitch at frame 3 (the filter's history not full, two agreements measured) is gated."""
    robot = pcle.robot_xy_um.copy()
    robot[3, 0] += GLITCH_UM
    out = _run(pcle, robot)
    assert _gated(out) == [3]
    assert _errors(out, pcle).max() < 5.0


def test_a_glitch_at_frame_1_is_gated_when_the_frames_overlap(pcle):
    """Nothing agreed with the robot before frame 1, so its registration was "unjudged" and the
    robot placed the frame at a +5 mm glitch (5000 px off). Frames 0 and 1 overlap (c_match
    ~0.8, a fibre-pattern lock scores ~0.5): the registration is believed, the robot gated
    (warmup_overlap_c_match). 256x224 px, 120 frames, the glitch interpolated to 3425 px at
    frame 1: e_M 39.4 -> 10.5 px (10.5 without the glitch)."""
    robot = pcle.robot_xy_um.copy()
    robot[1, 0] += GLITCH_UM
    out = _run(pcle, robot)
    assert _gated(out) == [1]
    assert _errors(out, pcle).max() < 5.0
    # never: the robot places the frame, as before
    never = replace(translation.RobotPriorOptions(), warmup_overlap_c_match=2.0,
                    warmup_ssim_margin=None)
    m = RobotPriorMosaicker(pcle.camera, never)
    first = _feed(m, pcle, range(3), robot)
    assert first[1].status == "prior-only" and not first[1].robot_gated


def test_bad_warmup_overlap_is_refused():
    with pytest.raises(ValueError, match="warmup_overlap_c_match must be a number >= 0"):
        translation.RobotPriorOptions(warmup_overlap_c_match=float("nan"))


def test_bad_sigma_span_is_refused():
    with pytest.raises(ValueError, match="robot_sigma_max_span must be an integer >= 1, got 0"):
        translation.RobotPriorOptions(robot_sigma_max_span=0)


@pytest.mark.parametrize("dropout", [range(0), DROPOUT], ids=["no-dropout", "at-the-return"])
def test_a_lasting_robot_offset_is_gated_until_the_rebase(pcle, dropout):
    """Gated frames do not widen the gate: a robot re-homed (its samples offset from frame
    `start` on) by (k + 2) x 80 px, k the frames it was missing before, is gated
    robot_gate_rebase = 3 times (were the gated frames counted, the third would pass and drag
    the frame), then re-anchored; the frames follow the image meanwhile."""
    start = dropout.stop if len(dropout) else RETURN
    robot = pcle.robot_xy_um.copy()
    robot[dropout] = np.nan
    baseline = _run(pcle, robot)
    robot[start:, 1] -= (len(dropout) + 2) * FLOOR_PX * pcle.camera.pixel_size_um
    out = _run(pcle, robot)
    assert _gated(out) == [start, start + 1, start + 2]
    np.testing.assert_allclose(_errors(out, pcle), _errors(baseline, pcle), atol=0.5)


# -- B: an interrupted call changes nothing ------------------------------------------------------


def _once(original, exception, *, call_through=False):
    """A stand-in for `original` that raises `exception` at its first call once armed
    (``state["armed"] = True``), after running the original when `call_through`, then behaves
    as the original again."""
    return raise_once(original, exception, call_through=call_through, armed=False)


INTERRUPTS = {
    # before the filter: only the registration ran
    "register_ncc": (translation, "register_ncc", False),
    # the filter has stepped (position, histories), the anchors and the count not yet (at a
    # gated frame the first update is the gate's trial on a copy)
    "filter update, after it ran": (RobotKalmanFilter, "update", True),
    # everything is updated (anchors, count, timestamp), the result is not returned yet
    "translation_homography": (translation, "translation_homography", False),
}
# Frames interrupted: ordinary, the robot's return after a dropout, a gated glitch, the frame
# after it (the robot anchor and the gated count move there).
SHORT_DROPOUT, GLITCH = range(20, 25), 30


@pytest.fixture(scope="module")
def interrupted_robot(pcle):
    robot = pcle.robot_xy_um.copy()
    robot[SHORT_DROPOUT] = np.nan
    robot[GLITCH, 0] += GLITCH_UM
    return robot


@pytest.fixture(scope="module")
def uninterrupted(pcle, interrupted_robot):
    out = _run(pcle, interrupted_robot)
    assert _gated(out) == [GLITCH]
    return out


def _table(out):
    """Every number a frame result reports (timings aside), one row per frame."""
    rows = []
    for k in sorted(out):
        r = out[k]
        rows.append(
            np.concatenate(
                [
                    r.position,
                    r.position_image,
                    r.position_fused,
                    r.displacement_image,
                    r.displacement_robot,
                    [r.c_img, r.c_rob, r.c_angle, r.c_speed, r.c_match, r.c_sp],
                    [r.sigma_robot0, r.ncc_score, float(r.robot_gated), r.index],
                ]
            )
        )
    return np.stack(rows)


@pytest.mark.parametrize("frame", [10, SHORT_DROPOUT.stop, GLITCH, GLITCH + 1])
@pytest.mark.parametrize("where", list(INTERRUPTS))
def test_an_interrupted_call_changes_nothing(
    pcle, interrupted_robot, uninterrupted, monkeypatch, where, frame
):
    target, name, call_through = INTERRUPTS[where]
    original = getattr(target, name)
    replacement, state = _once(original, KeyboardInterrupt(), call_through=call_through)
    monkeypatch.setattr(target, name, replacement)
    m = RobotPriorMosaicker(pcle.camera)
    out = _feed(m, pcle, range(frame), interrupted_robot)
    state["armed"] = True
    with pytest.raises(KeyboardInterrupt):
        m.add_frame(pcle.frames[frame], pcle.timestamps[frame], interrupted_robot[frame])
    assert not state["armed"]  # the interrupt did happen, inside the call
    assert m.frame_count == frame
    # the frame given again, and the rest of the run: as if never interrupted
    _feed(m, pcle, range(frame, len(pcle)), interrupted_robot, out)
    np.testing.assert_array_equal(_table(out), _table(uninterrupted))
    assert [out[k].status for k in sorted(out)] == [r.status for r in uninterrupted.values()]


def test_an_interrupted_first_frame_leaves_no_origin_behind(pcle, monkeypatch):
    """Interrupted at frame 0, where the robot origin is set (to a wrong sample here): frame 0
    given again starts the sequence as if the first call never happened."""
    replacement, state = _once(translation.translation_homography, KeyboardInterrupt())
    monkeypatch.setattr(translation, "translation_homography", replacement)
    m = RobotPriorMosaicker(pcle.camera)
    state["armed"] = True
    with pytest.raises(KeyboardInterrupt):
        m.add_frame(pcle.frames[0], pcle.timestamps[0], pcle.robot_xy_um[0] + 100.0)
    assert m.frame_count == 0
    out = _feed(m, pcle, range(len(pcle)), pcle.robot_xy_um)
    np.testing.assert_array_equal(_table(out), _table(_run(pcle, pcle.robot_xy_um)))
