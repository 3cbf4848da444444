"""SequentialMosaicker as a live API (audit 5, items 1-8 and 15): refused calls leave the state
unchanged, the same rotation gives the same mosaic, a tracker glitch is dropped, a failure inside
a call is rolled back, the start-up waits for the tracker without raising, and concurrent calls
are refused. "Unchanged" is checked by continuing the run and comparing with an uninterrupted
one. Small frames (200x200) and a short start-up keep every run under a second."""

import threading

import numpy as np
import pytest
from _faults import raise_once

import fusedmosaic.estimation.sequential as sequential
from fusedmosaic import _core
from fusedmosaic.estimation.sequential import (
    SequentialMosaicker,
    SequentialOptions,
    canonical_rotation_vector,
)
from fusedmosaic.evaluation import frame_errors
from fusedmosaic.io import Camera
from fusedmosaic.registration.features import FeatureOptions
from fusedmosaic.registration.pairs import MatchOptions
from fusedmosaic.simulation import FetoscopyOptions, generate_fetoscopy

# Scenarios built on few keypoints (small or round frames) keep them: SIFT's low-contrast retry
# (FeatureOptions.sift_min_features) would detect such frames again at a lower threshold.
FEW = FeatureOptions(sift_min_features=0)

N, SIZE, AT = 24, 200, 13  # frames, image size, the frame where things go wrong


class Scene:
    def __init__(self, n=N, seed=3):
        scene = generate_fetoscopy(FetoscopyOptions(n_frames=n, width=SIZE, height=SIZE,
                                                    laps=n / 37.5, seed=seed))
        rng = np.random.default_rng(0)  # tracker noise 1 deg, 1 mm (paper 000 appendix)
        self.n = n
        self.tracker = scene.poses + np.hstack([rng.normal(0, np.deg2rad(1.0), (n, 3)),
                                                rng.normal(0, 1.0, (n, 3))])
        self.frames = [scene.render(k) for k in range(n)]
        self.timestamps = scene.timestamps
        self.truth = scene.homographies
        self.poses, self.plane = scene.poses, scene.plane  # true cam_from_world and pi
        self.camera = Camera(SIZE, SIZE, camera_matrix=scene.camera_matrix)

    def mosaicker(self):
        return SequentialMosaicker(self.camera, SequentialOptions(bootstrap_frames=8))

    def feed(self, m, ks, results, tracker=None):
        tracker = self.tracker if tracker is None else tracker
        for k in ks:
            r = m.add_frame(self.frames[k], self.timestamps[k], tracker[k])
            assert r.frame_id == k
            results.update({f.frame_id: f for f in m.finalized()})
        return results

    def finish(self, m, results):
        results.update({f.frame_id: f for f in m.flush()})
        assert sorted(results) == list(range(self.n))
        return np.stack([results[k].homography for k in range(self.n)])

    def run(self, tracker=None):
        m = self.mosaicker()
        return self.finish(m, self.feed(m, range(N), {}, tracker))


@pytest.fixture(scope="module")
def scene():
    return Scene()


@pytest.fixture(scope="module")
def baseline(scene):
    G = scene.run()
    errors = frame_errors(G, scene.truth, SIZE, SIZE)
    assert errors.mean() < 1.0
    return G, errors


def assert_same(G, G_ref, tol_px=1e-6):
    """Frame -> reference homographies equal within tol_px over the image (the e_j grid)."""
    assert frame_errors(G, G_ref, SIZE, SIZE).max() < tol_px


# ------------------------------------------------------------- items 1-3, 5, 15: bad calls
def bad_calls(scene):
    k = AT
    image, t, pose = scene.frames[k], scene.timestamps[k], scene.tracker[k]
    far = pose.copy()
    far[3] = 1e9
    huge = pose.copy()
    huge[3] = 1e200
    return [
        ((None, t, pose), TypeError, "frame 13: image must be a numpy array.*NoneType"),
        ((image.tolist(), t, pose), TypeError, "frame 13: image must be a numpy array.*list"),
        ((image.astype(np.float32) / 255, t, pose), ValueError,
         "frame 13: image dtype float32 is not supported, expected uint8"),
        ((image.astype(np.uint16) * 256, t, pose), ValueError, "image dtype uint16 is not"),
        ((image > 0, t, pose), ValueError, "image dtype bool is not supported"),
        ((image[:, :, :2], t, pose), ValueError,
         r"frame 13: image shape \(200, 200, 2\) is not \(H, W\) gray"),
        ((image[:, :, :1], t, pose), ValueError, r"image shape \(200, 200, 1\) is not"),
        ((image[None], t, pose), ValueError, r"image shape \(1, 200, 200, 3\) is not"),
        ((image[:100], t, pose), ValueError, "frame 13: image size 200x100 differs"),
        ((image, "0.6", pose), TypeError, "frame 13: timestamp must be a real number.*str"),
        ((image, None, pose), TypeError, "timestamp must be a real number.*NoneType"),
        ((image, complex(t), pose), TypeError, "timestamp must be a real number.*complex"),
        ((image, True, pose), TypeError, "timestamp must be a real number.*bool"),
        ((image, np.nan, pose), ValueError, "frame 13: timestamp nan is not finite"),
        ((image, np.inf, pose), ValueError, "frame 13: timestamp inf is not finite"),
        ((image, scene.timestamps[k - 1], pose), ValueError, "timestamp .* does not increase"),
        ((image, 1e300, pose), ValueError,
         r"frame 13: timestamp 1e\+300 is beyond \|t\| <= 1e\+10 s .*ms, µs or ns"),
        ((image, t * 1e9, pose), ValueError, "more than max_timestamp_gap_s"),
        ((image, t, "abc"), TypeError, "frame 13: tracker_pose must be 6 real numbers"),
        ((image, t, pose.astype(complex)), TypeError, "tracker_pose .* dtype complex128"),
        ((image, t, [0, 0, 0, None, 0, 0]), TypeError, "tracker_pose .* dtype object"),
        ((image, t, pose[:5]), ValueError, "frame 13: tracker_pose must be 6 finite values"),
        ((image, t, np.r_[np.full(5, np.nan), 1.0]), ValueError,
         "tracker_pose must be 6 finite values"),
        ((image, t, far), ValueError, r"frame 13: tracker_pose translation .* bound .* \(1 km\)"),
        ((image, t, huge), ValueError, r"tracker_pose translation .* bound .* \(1 km\)"),
    ]


def test_refused_calls_leave_the_state_unchanged(scene, baseline):
    m = scene.mosaicker()
    results = scene.feed(m, range(AT), {})
    before = (m._next_id, m._last_timestamp, len(m._pending), m.window.pending_ids())
    for args, error, message in bad_calls(scene):
        with pytest.raises(error, match=message):
            m.add_frame(*args)
        assert (m._next_id, m._last_timestamp, len(m._pending),
                m.window.pending_ids()) == before
        assert m.finalized() == []
    scene.feed(m, range(AT, N), results)
    assert_same(scene.finish(m, results), baseline[0])


def test_a_refused_call_hands_out_no_final_frames_again(scene):
    """finalized() is what the last call made final: after a call that raised, none (a live
    loop collecting it after every call, refused ones too, gets each frame once)."""
    m = scene.mosaicker()
    scene.feed(m, range(AT - 2), {})
    assert m.finalized()  # the window step of frame AT - 3's call
    with pytest.raises(ValueError, match="image size 200x100 differs"):
        m.add_frame(scene.frames[AT - 2][:100], scene.timestamps[AT - 2], None)
    assert m.finalized() == []


def test_timestamp_gap_bound_is_an_option(scene):
    m = SequentialMosaicker(scene.camera, SequentialOptions(bootstrap_frames=8,
                                                            max_timestamp_gap_s=1.0))
    m.add_frame(scene.frames[0], 0.0, scene.tracker[0])
    with pytest.raises(ValueError, match=r"frame 1: timestamp 2.0 is 2 s after .* \(1 s\)"):
        m.add_frame(scene.frames[1], 2.0, scene.tracker[1])
    assert m.add_frame(scene.frames[1], 1.0, scene.tracker[1]).frame_id == 1
    with pytest.raises(ValueError, match="max_timestamp_gap_s must be > 0, got -1"):
        SequentialMosaicker(scene.camera, SequentialOptions(max_timestamp_gap_s=-1))


@pytest.mark.parametrize("gap_s", [0.5, 60.0, 3600.0])
def test_a_pause_while_the_tracker_is_lost_breaks_the_motion_prior(scene, gap_s):
    """The recording paused gap_s before frame 9 and the tracker lost for frames 9-13: the
    constant-velocity prior is released across the pause (motion.motion_timing), so frame 9
    starts at frame 8's pose and the images place it. Before, the last motion was repeated
    gap_s / 0.04 times: frames 9-23 up to 18 890 px off (0.5 s), 156 893 px (0.8 s); with the
    tracker lost from frame 12 and a 60 s pause at 15, 1e3-1e5 px, and 'induced homography is
    singular' raised at frame 25 of a longer run (3600 s). Measured: within 0.17 px of the
    same run without the pause (worst frame 0.66 px, 0.83 px without the pause)."""
    tracker = [None if 9 <= k <= 13 else scene.tracker[k] for k in range(N)]

    def run(gap):
        m = scene.mosaicker()
        times = np.asarray(scene.timestamps, float) + np.where(np.arange(N) >= 9, gap, 0.0)
        out = {}
        for k in range(N):
            m.add_frame(scene.frames[k], times[k], tracker[k])
            out.update({f.frame_id: f for f in m.finalized()})
        out.update({f.frame_id: f for f in m.flush()})
        return frame_errors(np.stack([out[k].homography for k in range(N)]), scene.truth,
                            SIZE, SIZE)

    paused, steady = run(gap_s), run(0.0)
    assert paused.max() < 2.0  # px
    np.testing.assert_allclose(paused, steady, atol=0.5)


@pytest.mark.parametrize("lead", [[30] * 5, [120, 120, 90, 60, 30], [100] * 4 + [60, 30]])
def test_black_frames_tracked_while_the_scope_turned_in(scene, baseline, lead):
    """Black frames tracked while the scope turned about x (lead: degrees from frame 0's
    orientation, one frame apart) before the textured ones: C_p over the stop (30 deg, 120
    sigma_p) turned the textured frames of the start-up with it. Measured without the motion
    gate (motion_gate_chi2 inf), e_M / worst: 12.3 / 32 px (one 30 deg step), 26.0 / 83 px (a
    spin from the first frame, whose departure has no earlier ones to be scaled by), 25.6 /
    77 px (a spin after four still frames); 0.47 / 1.3 px without black frames. With it:
    0.52 / 1.1, 0.53 / 1.3, 0.88 / 2.2 px."""
    R0 = _core.rotation_from_angle_axis(scene.tracker[0, :3])
    dt = scene.timestamps[1] - scene.timestamps[0]
    m, out = scene.mosaicker(), {}
    for i, a in enumerate(lead):
        R = _core.rotation_from_angle_axis(np.array([np.deg2rad(a), 0.0, 0.0])) @ R0
        m.add_frame(np.zeros_like(scene.frames[0]), scene.timestamps[0] - (len(lead) - i) * dt,
                    np.r_[_core.angle_axis_from_rotation(R), R @ R0.T @ scene.tracker[0, 3:]])
        out.update({f.frame_id: f for f in m.finalized()})
    for k in range(N):
        m.add_frame(scene.frames[k], scene.timestamps[k], scene.tracker[k])
        out.update({f.frame_id: f for f in m.finalized()})
    out.update({f.frame_id: f for f in m.flush()})
    G = np.stack([out[len(lead) + k].homography for k in range(N)])
    errors = frame_errors(np.linalg.inv(G[0]) @ G, scene.truth, SIZE, SIZE)
    assert errors.mean() < baseline[1].mean() + 0.5
    assert errors.max() < 2.5
    # flagged: the frames at the stop (and the spin's start), none of the later ones
    released = {k for k, r in out.items() if r.motion_released}
    assert released and max(released) <= len(lead) + 1


@pytest.mark.parametrize("glitched, startup", [([13], 8), ([13, 14], 8), ([9], 16),
                                               ([9, 10], 16)])
def test_a_glitch_on_a_black_frame_is_the_sample_not_the_motion(scene, glitched, startup):
    """Black frames with their tracker samples turned 20 deg: the triples ending at 13, 14, 15
    depart by d, -2 d, d (two consecutive ones: four triples). Releasing them left a frame
    with its glitched sample alone (116 px off); the gate takes them for the samples' doing
    once the later samples are known (motion.motion_verdict, judged again before each step),
    keeps every C_p and gates the samples. Measured e_M / worst: 0.60 / 3.9 px against 2.79 /
    27.4 px without the gate ([13]); 1.25 / 10.5 against 6.82 / 52.6 px ([13, 14]). Inside a
    16-frame start-up, which leaves them out: 0.47 / 0.9 against 1.19 / 9.2 px ([9]), 0.50 /
    0.9 against 2.74 / 23.3 px ([9, 10]); not gated there before, the same as without.
    (Measured with the paper's sigma_v of 1 px, where the comparison with the gate off is
    made: with the sigma_v measured on the recording (sigma_v_px "auto", session 49), the images
    resist the glitch more even without the gate.)"""
    frames = list(scene.frames)
    tracker = scene.tracker.copy()
    R = _core.rotation_from_angle_axis(np.array([np.deg2rad(20.0), 0.0, 0.0]))
    for k in glitched:
        frames[k] = np.zeros_like(frames[0])
        tracker[k, :3] = _core.angle_axis_from_rotation(
            R @ _core.rotation_from_angle_axis(tracker[k, :3]))

    def run(gate, sigma_v="auto"):
        m = SequentialMosaicker(scene.camera, SequentialOptions(
            bootstrap_frames=startup, motion_gate_chi2=gate, sigma_v_px=sigma_v))
        out = {}
        for k in range(N):
            m.add_frame(frames[k], scene.timestamps[k], tracker[k])
            out.update({f.frame_id: f for f in m.finalized()})
        out.update({f.frame_id: f for f in m.flush()})
        G = np.stack([out[k].homography for k in range(N)])
        return frame_errors(G, scene.truth, SIZE, SIZE), out

    for sigma_v in ("auto", 1.0):
        on, out = run(22.46, sigma_v)
        assert not any(r.motion_released for r in out.values())
        assert set(glitched) <= {k for k, r in out.items() if r.tracker_gated}
        assert on.max() < 15.0  # px
    off, _ = run(np.inf, 1.0)
    assert on.mean() < 0.5 * off.mean() and on.max() < 0.5 * off.max()


def test_no_motion_prior_released_on_a_steady_scan(scene):
    m = scene.mosaicker()
    out = scene.feed(m, range(N), {})
    out.update({f.frame_id: f for f in m.flush()})
    assert not any(r.motion_released for r in out.values())
    assert m.bootstrap_summary["motion_released_ids"] == []
    assert all(s.motion_released_ids == [] for s in m.step_summaries)


def test_matching_threads_give_the_same_mosaic(scene, baseline):
    """The pairs of a frame are matched on a thread pool when matching.num_threads > 1; each
    pair's result does not depend on the thread (OpenCV's RANSAC seeds its own generator)."""
    for threads in (1, 2):
        m = SequentialMosaicker(scene.camera, SequentialOptions(
            bootstrap_frames=8, matching=MatchOptions(num_threads=threads)))
        np.testing.assert_array_equal(scene.finish(m, scene.feed(m, range(N), {})), baseline[0])


def test_first_timestamp_in_nanoseconds_is_refused_as_the_robot_mosaicker_does(scene):
    """Review 5 #8: the first frame stamped in ns used to be accepted, and then every later
    frame in s was refused until reset(). Both mosaickers share io.tracking's check now."""
    m = scene.mosaicker()
    with pytest.raises(ValueError, match=r"frame 0: timestamp 1\.7e\+18 is beyond \|t\| <= "
                                         r"1e\+10 s .* a unit mix-up \(ms, µs or ns"):
        m.add_frame(scene.frames[0], 1.7e18, scene.tracker[0])
    assert m.add_frame(scene.frames[0], np.array(1.7e9), scene.tracker[0]).frame_id == 0
    assert m.add_frame(scene.frames[1], 1.7e9 + 0.04, scene.tracker[1]).frame_id == 1


# ------------------------------------------------------------------ item 4: rotation vectors
def long_vector(r):
    """The same rotation as r (norm theta < pi) written as -axis * (2 pi - theta)."""
    theta = np.linalg.norm(r)
    return -r / theta * (2 * np.pi - theta)


def test_canonical_rotation_vector():
    rng = np.random.default_rng(1)
    for r in [*rng.normal(0, 1.0, (20, 3)), np.array([0.0, 0.0, 0.0]), np.array([4.0, 0, 0]),
              np.array([0, 0.1 + 2 * np.pi, 0]), np.array([1e6, 2.0, -3.0])]:
        c = canonical_rotation_vector(r)
        assert np.linalg.norm(c) <= np.pi + 1e-12
        np.testing.assert_allclose(_core.rotation_from_angle_axis(c),
                                   _core.rotation_from_angle_axis(r), atol=1e-8)
        if np.linalg.norm(r) <= np.pi:
            assert c is r  # already canonical: untouched
    r = np.array([0.01, -0.02, 0.03])
    np.testing.assert_allclose(canonical_rotation_vector(long_vector(r)), r, atol=1e-14)


def test_same_rotation_as_a_long_vector_gives_the_same_mosaic(scene, baseline):
    tracker = scene.tracker.copy()
    for k in range(N):
        tracker[k, :3] = long_vector(tracker[k, :3])
        assert np.linalg.norm(tracker[k, :3]) > np.pi
    G = scene.run(tracker)
    assert_same(G, baseline[0])  # within 1e-6 px: before, one such frame cost e_M 2.8 px


# ------------------------------------------------------------------ item 5: tracker glitches
@pytest.mark.parametrize("offset_mm", [1e4, 1e5])
def test_single_tracker_glitch_leaves_the_other_frames_alone(scene, baseline, offset_mm):
    """A +10 m sample (gated, but it initialised the step: e_M 1131 px on the audit's feto60)
    is dropped before the window sees it: the mosaic is the one without that sample, and the
    frame is placed by its images."""
    tracker = scene.tracker.copy()
    tracker[AT, 3] += offset_mm
    m = scene.mosaicker()
    results = scene.feed(m, range(N), {}, tracker)
    G = scene.finish(m, results)
    assert results[AT].tracker_gated and results[AT].tracker_dropped
    assert results[AT].status == "placed"
    assert not any(results[k].tracker_gated for k in range(N) if k != AT)
    missing = list(scene.tracker)
    missing[AT] = None
    assert_same(G, scene.run(missing))
    errors = frame_errors(G, scene.truth, SIZE, SIZE)  # 0.42 / 0.85 px (baseline 0.47 / 1.33)
    assert errors.mean() <= 1.1 * baseline[1].mean() and errors.max() <= 1.1 * baseline[1].max()


def test_a_stretch_of_rotations_in_degrees_is_gated_and_the_frames_stay_placed():
    """Five samples with their rotations in degrees (frames 20-24 of a 110-frame scan, 37-132
    deg off): the glitch filter drops some and re-anchors on one (the third disagreeing sample
    in a row), the window step gates the rest. The gate's redo started again from the gated
    sample (124 deg off) and from the first solve's poses of the untracked frames beside it: it
    settled far from the images, and every frame after 22 came out 40-4e5 px off, all
    "placed". Tolerance against the simulator's truth: within 1.1 x the mean and worst error
    of the same run with every sample right (0.64 / 1.43 px; measured 0.63 / 1.38 px)."""
    scene = Scene(n=110)
    tracker = scene.tracker.copy()
    tracker[20:25, :3] = np.degrees(tracker[20:25, :3])
    errors, gated = {}, {}
    for name, samples in (("right", scene.tracker), ("degrees", tracker)):
        m = scene.mosaicker()
        results = scene.feed(m, range(scene.n), {}, samples)
        errors[name] = frame_errors(scene.finish(m, results), scene.truth, SIZE, SIZE)
        gated[name] = {k for k in range(scene.n) if results[k].tracker_gated}
    assert all(results[k].status == "placed" for k in range(scene.n))
    # the stretch is gated, and the samples after it are judged as in the run without it, but
    # for sample 25: judged against the re-anchored sample 24 before the step that gated 24
    # (which hands the filter 24's estimate as its reference; without that, 26 was dropped too)
    assert set(range(20, 25)) <= gated["degrees"]
    assert gated["degrees"] - set(range(20, 26)) == gated["right"] - set(range(20, 26))
    assert errors["degrees"].mean() <= 1.1 * errors["right"].mean()
    assert errors["degrees"].max() <= 1.1 * errors["right"].max(), \
        np.flatnonzero(errors["degrees"] > 1.1 * errors["right"].max())


def test_plausible_tracker_motion_is_never_dropped(scene, monkeypatch):
    """At 1 m/s + 50 mm, ordinary motion and noise pass: the baseline drops nothing, and a
    +20 mm error is kept for the window step's gating to judge, as before."""
    verdicts = []
    plausible = SequentialMosaicker._plausible

    def spy(self, timestamp, pose):
        verdicts.append(plausible(self, timestamp, pose))
        return verdicts[-1]

    monkeypatch.setattr(SequentialMosaicker, "_plausible", spy)
    tracker = scene.tracker.copy()
    tracker[AT, 3] += 20.0
    m = scene.mosaicker()
    results = scene.feed(m, range(N), {}, tracker)
    scene.finish(m, results)
    assert len(verdicts) == N and all(verdicts)
    assert results[AT].tracker_gated and not results[AT].tracker_dropped  # by the window step


# ------------------------------------------------------------------ item 6: rollback
class Boom(RuntimeError):
    pass


def once(target, name, exception, *, call_through=False):
    """Replaces target.name by a version that raises `exception` on its first call (after
    running the original when call_through), then behaves normally."""
    return raise_once(getattr(target, name), exception, call_through=call_through)


class WindowProxy:
    """The C++ window with one method failing once (attributes of pybind objects are
    read-only, so the window is wrapped)."""

    def __init__(self, window, name, exception, call_through):
        self._window = window
        self._method, self.state = once(window, name, exception, call_through=call_through)
        self._name = name

    def __getattr__(self, name):
        return self._method if name == self._name else getattr(self._window, name)


@pytest.mark.parametrize("where", [
    "extract", "match_pair", "window.add_frame", "window.add_pair (after the C++ call)",
    "window.step", "window.step (after the C++ call)", "keyframes.select",
    "KeyboardInterrupt in _finalize", "bootstrap _finalize", "flush",
])
def test_failure_inside_a_call_is_rolled_back(scene, baseline, where, monkeypatch):
    m = scene.mosaicker()
    start = {"bootstrap _finalize": 7, "flush": N}.get(where, AT)
    results = scene.feed(m, range(start), {})
    exception = KeyboardInterrupt() if "KeyboardInterrupt" in where else Boom(where)
    if where == "extract":
        replacement, state = once(m.extractor, "extract", exception)
        monkeypatch.setattr(m.extractor, "extract", replacement)
    elif where == "match_pair":
        replacement, state = once(sequential, "match_pair", exception)
        monkeypatch.setattr(sequential, "match_pair", replacement)
    elif where.startswith("window."):
        name = where.split()[0].split(".")[1]
        m.window = WindowProxy(m.window, name, exception, "after" in where)
        state = m.window.state
    elif where == "keyframes.select":
        replacement, state = once(m.keyframes, "select", exception)
        monkeypatch.setattr(m.keyframes, "select", replacement)
    else:  # _finalize, at the bootstrap or a window step, or flush's
        replacement, state = once(m, "_finalize", exception)
        monkeypatch.setattr(m, "_finalize", replacement)
    if where == "flush":
        assert m._pending  # flush has frames to finalise
        with pytest.raises(Boom):
            m.flush()
    else:
        with pytest.raises(type(exception)):
            scene.feed(m, range(start, N), results)
        assert not state["armed"]  # the failure did fire, within this call
    assert m.finalized() == []  # a failed call made nothing final
    failed_at = m._next_id  # the refused frame, sent again
    scene.feed(m, range(failed_at, N), results)
    assert_same(scene.finish(m, results), baseline[0])


def test_failed_restoration_marks_the_mosaicker_unusable_until_reset(scene, baseline,
                                                                     monkeypatch):
    m = scene.mosaicker()
    scene.feed(m, range(AT), {})
    m.window = WindowProxy(m.window, "add_frame", Boom("add_frame"), call_through=True)

    def rebuild_fails():
        raise MemoryError

    monkeypatch.setattr(m, "_rebuild_window", rebuild_fails)
    with pytest.raises(RuntimeError, match="unusable: restoring the state after Boom .*"
                       "MemoryError.*call reset"):
        m.add_frame(scene.frames[AT], scene.timestamps[AT], scene.tracker[AT])
    for call in (lambda: m.add_frame(scene.frames[AT], scene.timestamps[AT], None), m.flush):
        with pytest.raises(RuntimeError, match="SequentialMosaicker is unusable: .* reset()"):
            call()
    monkeypatch.undo()
    m.reset()
    assert m._next_id == 0 and not m._pending
    assert_same(scene.finish(m, scene.feed(m, range(N), {})), baseline[0])


# ------------------------------------------------------------------ item 7: late tracker
def test_startup_without_tracker_poses_keeps_frames_without_raising(scene):
    """Tracker switched on at frame 10, start-up of 8 frames: frames 7-9 cannot initialise the
    plane yet; they are kept (unplaced, pending) and placed once the tracker comes."""
    tracker = [None] * 10 + list(scene.tracker[10:])
    m = scene.mosaicker()
    results = {}
    for k in range(N):
        r = m.add_frame(scene.frames[k], scene.timestamps[k], tracker[k])
        if 7 <= k < 10:
            assert not r.final and r.status.startswith(
                "unplaced: waiting for a registered pair with tracker poses")
        results.update({f.frame_id: f for f in m.finalized()})
    G = scene.finish(m, results)
    assert all(results[k].status == "placed" for k in range(N))
    assert frame_errors(G, scene.truth, SIZE, SIZE).mean() < 1.0

    m = scene.mosaicker()
    for k in range(5):
        m.add_frame(scene.frames[k], scene.timestamps[k], None)
    with pytest.raises(ValueError, match="no pair among the first 5 frames .* tracker poses"):
        m.flush()
    assert len(m._pending) == 5  # refused, nothing lost: the tracker may still come


def test_a_late_tracker_startup_is_tried_on_a_short_iteration_budget(monkeypatch):
    """A tracker switched on at frame 40 of 60: the start-up holds 40+ frames with a handful of
    tracked ones, poorly conditioned; each attempt ran Ceres up to startup_max_iterations
    towards a plane refused anyway (400x400, 73 frames: 6 s an attempt, 16 s over 4 frames).
    While a refusal only makes it wait, an attempt is first solved with
    startup_trial_iterations: a plane still too uncertain then is refused at once, else it is
    solved on. Here (startup_max_plane_std 0.1) the first attempt is refused after 10
    iterations (std 0.101), the next is solved on (0.086). A trial's std is not the converged
    one: that first attempt, solved in full, converges at 0.097 and is taken, so the trial
    can start one frame later than full attempts, never more here (e_M 0.81 and 0.95 px, 40
    frames placed through their pairs alone; with the simulator's noise truncated rather than
    rounded, before session 47, both waited to the same frame: 1.636 px both).
    Measured with Levenberg-Marquardt: the start-up's default dogleg converges on each attempt
    within the trial's 10 iterations here (startup_trust_region), leaving no short attempt."""
    n, late = 60, 40
    scene = Scene(n=n, seed=3)
    tracker = [None] * late + list(scene.tracker[late:])
    solves = []
    solve = SequentialMosaicker._solve_startup

    def recorded(self, *args, **kwargs):
        ba, summary = solve(self, *args, **kwargs)
        solves.append(summary)
        return ba, summary

    monkeypatch.setattr(SequentialMosaicker, "_solve_startup", recorded)
    errors, started = {}, {}
    for trial in (10, 300):
        solves.clear()
        m = SequentialMosaicker(scene.camera, SequentialOptions(
            startup_trial_iterations=trial, startup_max_plane_std=0.1,
            startup_trust_region="levenberg_marquardt", features=FEW))
        results = {}
        for k in range(n):
            m.add_frame(scene.frames[k], scene.timestamps[k], tracker[k])
            results.update({f.frame_id: f for f in m.finalized()})
            if m.bootstrap_summary is not None and trial not in started:
                started[trial] = k
        G = scene.finish(m, results)
        errors[trial] = frame_errors(G, scene.truth, SIZE, SIZE).mean()
        assert errors[trial] < 2.0, (trial, errors[trial])
        assert m.bootstrap_summary["termination"] == "CONVERGENCE"
        assert m.bootstrap_summary["plane_relative_std"] <= 0.1
        short = [s for s in solves[:-1]
                 if s["iterations"] <= trial + 1 and s["termination"] == "NO_CONVERGENCE"]
        assert bool(short) == (trial == 10), solves  # refused after a short attempt
    assert late < started[300] <= started[10] <= started[300] + 1, started


@pytest.fixture
def trust_regions(monkeypatch):
    """The trust region of every BundleAdjuster made while the test runs, in order."""
    used = []
    adjuster = _core.BundleAdjuster

    def recorded(K, options):
        used.append(options.trust_region)
        return adjuster(K, options)

    monkeypatch.setattr(_core, "BundleAdjuster", recorded)
    return used


def test_a_forced_late_tracker_startup_converges_at_the_windows_tolerance(tmp_path,
                                                                           trust_regions):
    """A tracker invalid over frames 0-85 of 110 (300x300, the simulated tracker's noise): the
    start-up must decide on its 81 frames, 2 of them tracked. Solved to BundleAdjusterOptions'
    1e-10 it took 241 iterations (4.5 s; at startup_max_iterations 200: stopped there, with a
    warning); to the window steps' FUNCTION_TOLERANCE, 146 (2.8 s), cost 751.43 against
    751.41. Started from the nominal plane (_initial_plane: the lower cost after 5 iterations)
    Levenberg-Marquardt takes 11, the start-up's dogleg 3 (after the two probes' 5 each; 0.36
    s in all), cost 751.41."""
    from fusedmosaic.io import read_dataset
    from fusedmosaic.simulation import simulate_fetoscopy

    ds = read_dataset(simulate_fetoscopy(tmp_path / "late", FetoscopyOptions(
        n_frames=110, width=300, height=300, tracker_gap=(0, 85))))
    used = trust_regions
    for trust_region in ("levenberg_marquardt", "dogleg"):
        used.clear()
        # (the paper's sigma_v, with which the costs were measured; "auto" solves again)
        m = SequentialMosaicker(ds.camera, SequentialOptions(startup_max_iterations=200,
                                                             startup_trust_region=trust_region,
                                                             features=FEW, sigma_v_px=1.0))
        for k in range(len(ds)):
            m.add_frame(ds.frames[k], float(ds.timestamps[k]),
                        ds.cam_from_world[k] if ds.pose_valid[k] else None)
            m.finalized()
        m.flush()
        summary = m.bootstrap_summary
        assert summary["num_emt_blocks"] <= 3  # (the case: a handful tracked)
        assert summary["termination"] == "CONVERGENCE", summary
        assert summary["iterations"] <= (30 if trust_region == "dogleg" else 60), summary
        assert summary["final_cost"] < 751.41 * 1.0001, summary  # (the 1e-10 solution's)
        assert not sequential.live_solver_warnings(m)
        assert used and set(used) == {trust_region}, used  # (2 probes, then the solve)


def test_a_fully_tracked_startup_keeps_levenberg_marquardt(scene, trust_regions):
    """startup_trust_region applies to start-ups with frames lacking a tracker sample only."""
    m = scene.mosaicker()
    scene.feed(m, range(AT), {})
    assert m.bootstrap_summary is not None
    assert trust_regions and set(trust_regions) == {"levenberg_marquardt"}, trust_regions
    with pytest.raises(ValueError, match=r"startup_trust_region must be 'dogleg' or "
                       r"'levenberg_marquardt', got 'lm'"):
        SequentialMosaicker(scene.camera, SequentialOptions(startup_trust_region="lm"))
    with pytest.raises(ValueError, match=r"trust_region: 'dogleg' needs a factorising linear "
                       r"solver, not 'iterative_schur'"):
        _core.BundleAdjusterOptions(trust_region="dogleg", linear_solver="iterative_schur"
                                    ).validate()


# ------------------------------------------------------------------ item 8: threads
def test_concurrent_calls_are_refused_and_other_threads_may_call_in_turn(scene, baseline,
                                                                          monkeypatch):
    m = scene.mosaicker()
    results = scene.feed(m, range(AT), {})
    inside, release = threading.Event(), threading.Event()
    extract = m.extractor.extract

    def slow_extract(image, k):
        inside.set()
        assert release.wait(10)
        return extract(image, k)

    monkeypatch.setattr(m.extractor, "extract", slow_extract)
    errors = []

    def first():
        try:
            scene.feed(m, [AT], results)
        except BaseException as exc:  # noqa: BLE001 - reported to the main thread
            errors.append(exc)

    thread = threading.Thread(target=first)
    thread.start()
    assert inside.wait(10)
    for call in (lambda: m.add_frame(scene.frames[AT + 1], scene.timestamps[AT + 1], None),
                 m.flush, m.reset):
        with pytest.raises(RuntimeError, match="called while another call is running on this "
                           "mosaicker .* not re-entrant; serialise the calls"):
            call()
    release.set()
    thread.join()
    assert not errors
    monkeypatch.undo()
    # later calls from yet another thread, one at a time, carry on normally
    thread = threading.Thread(target=lambda: scene.feed(m, range(AT + 1, N), results))
    thread.start()
    thread.join()
    assert_same(scene.finish(m, results), baseline[0])


# --------------------------------------------- review 5: a tracker world where |r| is near pi
def rotate_world(poses, Q):
    """The same cameras in a tracker world rotated by Q (cam_from_world R -> R Q)."""
    out = np.array(poses, dtype=np.float64)
    for k in range(len(out)):
        R = _core.rotation_from_angle_axis(out[k, :3]) @ Q
        out[k, :3] = _core.angle_axis_from_rotation(R)
    return out


LOOKING_DOWN = np.diag([1.0, -1.0, -1.0])  # z-up tracker, scope looking down: |r| = pi


def move_world(poses, shift):
    """The same cameras in a tracker world whose origin is moved by -shift (X' = X + shift:
    cam_from_world t -> t - R shift)."""
    out = np.array(poses, dtype=np.float64)
    for k in range(len(out)):
        out[k, 3:] -= _core.rotation_from_angle_axis(out[k, :3]) @ shift
    return out


def test_world_alignment_round_trip_and_invariance(scene):
    from fusedmosaic.estimation.world import (
        plane_from_aligned,
        plane_to_aligned,
        poses_from_aligned,
        poses_to_aligned,
        world_alignment,
    )

    assert world_alignment(scene.tracker) is None  # near identity and the origin: no change
    K = scene.camera.camera_matrix
    plane = np.array([0.01, -0.02, -0.03])
    rotated = rotate_world(scene.tracker, LOOKING_DOWN)
    far = move_world(scene.tracker, np.array([300.0, -200.0, 1000.0]))
    for poses, rotates, moves in ((rotated, True, False), (far, False, True),
                                  (move_world(rotated, np.array([0.0, 0.0, -500.0])), True, True)):
        world = world_alignment(poses)
        assert (not np.allclose(world.rotation, np.eye(3))) == rotates
        assert (np.linalg.norm(world.centre) > 0) == moves
        aligned = poses_to_aligned(poses, world)
        if rotates:  # the first camera has rotation identity, the others are far from pi
            assert np.abs(aligned[0, :3]).max() < 1e-12
            assert np.linalg.norm(aligned[:, :3], axis=1).max() < 1.0
        else:
            np.testing.assert_allclose(aligned[:, :3], poses[:, :3], atol=1e-12)
        if moves:  # the first camera is at the origin, the others near it
            assert np.abs(aligned[0, 3:]).max() < 1e-9
            assert np.linalg.norm(aligned[:, 3:], axis=1).max() < 100.0
        else:
            np.testing.assert_allclose(aligned[:, 3:], poses[:, 3:])
        back = poses_from_aligned(aligned, world)
        np.testing.assert_allclose(back[:, 3:], poses[:, 3:], atol=1e-9)
        for k in range(N):  # the same rotations (vectors may differ by 2 pi near pi)
            np.testing.assert_allclose(_core.rotation_from_angle_axis(back[k, :3]),
                                       _core.rotation_from_angle_axis(poses[k, :3]), atol=1e-12)
        plane_w = plane_from_aligned(plane, world)  # some plane of that world
        np.testing.assert_allclose(plane_to_aligned(plane_w, world), plane, rtol=1e-12)
        np.testing.assert_allclose(plane_from_aligned(plane_to_aligned(plane_w, world), world),
                                   plane_w, rtol=1e-12)
        np.testing.assert_allclose(
            _core.frame_to_reference(aligned, plane, K),
            _core.frame_to_reference(poses, plane_w, K), atol=1e-6)


def test_tracker_world_near_pi_gives_the_same_mosaic(scene, baseline):
    """A z-up tracker with the scope looking down puts every rotation at |r| ~ pi, where tracker
    noise flips the angle-axis vector by ~2 pi (e_M was 45 239 px): the mosaicker works in a
    world where the first camera is identity and reports poses in the tracker's world."""
    tracker = rotate_world(scene.tracker, LOOKING_DOWN)
    assert np.linalg.norm(tracker[:, :3], axis=1).min() > 2.9
    m = scene.mosaicker()
    results = scene.feed(m, range(N), {}, tracker)
    G = scene.finish(m, results)
    errors = frame_errors(G, scene.truth, SIZE, SIZE)
    assert errors.mean() < max(2 * baseline[1].mean(), 0.5), errors
    # poses come back in the tracker's (rotated) world: within a few degrees of its samples
    for k in range(N):
        R_est = _core.rotation_from_angle_axis(results[k].pose[:3])
        R_trk = _core.rotation_from_angle_axis(tracker[k, :3])
        angle = np.degrees(np.arccos(np.clip((np.trace(R_est.T @ R_trk) - 1) / 2, -1, 1)))
        assert angle < 5.0, (k, angle)
    truth_plane_dot = results[N - 1].plane @ m.plane  # the property: same world as the results
    assert np.isclose(truth_plane_dot, m.plane @ m.plane)


def test_a_bad_first_tracker_sample_does_not_poison_the_glitch_filter(scene, baseline):
    """The first sample 10 m off, or a glitch right after a long dropout: the filter compares
    against a trusted reference, re-anchors after tracker_reanchor_after disagreeing samples
    and caps the gap it allows for."""
    tracker = scene.tracker.copy()
    tracker[0, 3] += 1e4
    m = scene.mosaicker()
    results = scene.feed(m, range(N), {}, tracker)
    G = scene.finish(m, results)
    errors = frame_errors(G, scene.truth, SIZE, SIZE)
    assert [k for k in range(N) if results[k].tracker_gated] == [0]  # only the bad sample
    assert results[0].tracker_dropped
    assert errors.mean() < 1.0, errors
    # a long dropout (frames 6..12 without tracker) then a +10 m glitch: dropped
    tracker = scene.tracker.copy()
    tracker[AT, 3] += 1e4
    m = scene.mosaicker()
    results = {}
    for k in range(N):
        pose = None if 6 <= k < AT else tracker[k]
        m.add_frame(scene.frames[k], scene.timestamps[k] + (30.0 if k >= AT else 0.0), pose)
        results.update({f.frame_id: f for f in m.finalized()})
    G = scene.finish(m, results)
    assert results[AT].tracker_gated and results[AT].tracker_dropped
    assert frame_errors(G, scene.truth, SIZE, SIZE).mean() < 1.0


@pytest.mark.parametrize("offset_mm", [30.0, 100.0])
def test_a_glitch_on_the_first_tracker_sample_is_gated_by_the_startup(scene, baseline,
                                                                      offset_mm):
    """+100 mm on frame 0's sample only: the glitch filter drops frame 1 against it, then
    accepts frame 2 (within 1000 mm/s x 0.08 s + 50 mm), so the sample stayed its reference
    and the start-up adjusted the plane to ~1.6 m: frames up to 144 px off. The start-up's
    gate (Mahalanobis^2 328 against a median of 50) drops it: 0.79 px mean, 1.8 px worst (0.45
    / 0.99 px without frame 0's sample)."""
    tracker = scene.tracker.copy()
    tracker[0, 3] += offset_mm
    m = scene.mosaicker()
    results = scene.feed(m, range(N), {}, tracker)
    errors = frame_errors(scene.finish(m, results), scene.truth, SIZE, SIZE)
    assert errors.max() < 3.0, errors  # px
    assert results[0].tracker_gated


def test_the_startup_gate_leaves_noisy_but_consistent_samples_alone(scene):
    """Samples 4x noisier than Sigma_EMT (every Mahalanobis^2 above gate_chi2): the gate's
    scale follows their median, so none is dropped."""
    rng = np.random.default_rng(5)
    noisy = scene.poses + 4 * np.hstack([rng.normal(0, np.deg2rad(1.0), (N, 3)),
                                         rng.normal(0, 1.0, (N, 3))])
    m = scene.mosaicker()
    results = scene.feed(m, range(N), {}, noisy)
    scene.finish(m, results)
    assert not any(results[k].tracker_gated for k in range(8))


def test_ba_emt_in_a_tracker_world_near_pi(tmp_path):
    """ba-emt runs in the aligned world too and returns poses and plane in the tracker's."""
    from dataclasses import replace

    from fusedmosaic.estimation.bundle import run_bundle
    from fusedmosaic.io import read_dataset
    from fusedmosaic.simulation import simulate_fetoscopy

    root = simulate_fetoscopy(tmp_path / "d", FetoscopyOptions(n_frames=16, width=SIZE,
                                                               height=SIZE, laps=16 / 37.5,
                                                               seed=3))
    dataset = read_dataset(root)
    rotated = replace(dataset, cam_from_world=rotate_world(dataset.cam_from_world, LOOKING_DOWN))
    assert np.linalg.norm(rotated.cam_from_world[:, :3], axis=1).min() > 2.9
    plain = run_bundle(dataset, progress=False)
    turned = run_bundle(rotated, progress=False)
    e_plain = frame_errors(plain.homographies, dataset.ground_truth, SIZE, SIZE).mean()
    e_turned = frame_errors(turned.homographies, dataset.ground_truth, SIZE, SIZE).mean()
    assert e_turned < max(2 * e_plain, 0.5), (e_turned, e_plain)
    # the plane comes back in the rotated world: pi' = Q^T pi
    np.testing.assert_allclose(turned.plane, LOOKING_DOWN.T @ plain.plane, rtol=0.05, atol=1e-4)
    R_est = _core.rotation_from_angle_axis(turned.poses[5, :3])
    R_ref = _core.rotation_from_angle_axis(plain.poses[5, :3]) @ LOOKING_DOWN
    assert np.abs(R_est - R_ref).max() < 0.05


# A tracker whose origin (its field generator) is far from the cameras: the methods work in a
# world centred on the first tracked camera (estimation/world.py). FAR, mm: the tracker's origin
# 1 m along the optical axis, and 0.5 m across it.
FAR = [np.array([0.0, 0.0, 1000.0]), np.array([0.0, 0.0, -1000.0]),
       np.array([500.0, -300.0, 0.0])]


def physical_tracker(scene, shift, rng):
    """Tracker samples in a world moved by `shift` (X' = X + shift) with the noise of a real
    sensor: 1 degree on its orientation, 1 mm on its position (not on t = -R c)."""
    out = []
    for pose in scene.poses:
        R = _core.rotation_from_angle_axis(pose[:3])
        c = -R.T @ pose[3:] + shift + rng.normal(0, 1.0, 3)
        R_n = _core.rotation_from_angle_axis(rng.normal(0, np.deg2rad(1.0), 3)) @ R
        out.append(np.r_[_core.angle_axis_from_rotation(R_n), -R_n @ c])
    return np.array(out)


@pytest.mark.parametrize("shift", FAR, ids=["above", "below", "across"])
def test_a_tracker_origin_far_from_the_cameras_gives_the_same_mosaic(scene, shift):
    """Before the recentring the first two, frames 3-8 untracked: e_M 3 959 and 56 409 px
    (orientation noise leaked into t = -R c by 1 m: 17 mm, and pi = n / d at d ~ 1 m); now the
    same as with the origin at the paper's virtual camera (measured 0.52 px, worst frame 1.2 px,
    against 0.43 / 0.97 px). Poses and plane come back in the tracker's world."""
    tracker = physical_tracker(scene, shift, np.random.default_rng(0))
    near = physical_tracker(scene, np.zeros(3), np.random.default_rng(0))
    errors = {}
    for name, samples in (("near", near), ("far", tracker)):
        samples = [None if 3 <= k <= 8 else samples[k] for k in range(N)]
        m = scene.mosaicker()
        results = scene.feed(m, range(N), {}, samples)
        errors[name] = frame_errors(scene.finish(m, results), scene.truth, SIZE, SIZE)
    assert errors["far"].mean() < max(1.5 * errors["near"].mean(), 0.5), errors
    assert errors["far"].max() < 2.0  # px
    # the tracker's world: the estimated camera centres within a few mm of the samples'
    for k in (0, 12, N - 1):
        R = _core.rotation_from_angle_axis(results[k].pose[:3])
        R_s = _core.rotation_from_angle_axis(tracker[k, :3])
        assert np.linalg.norm(-R.T @ results[k].pose[3:] + R_s.T @ tracker[k, 3:]) < 5.0
    # the plane too: the true plane's point below the first camera, X, is on it at X + shift
    # within 10 % of the depth (measured 0.2-6 %; the origin at the virtual camera: 3 %)
    pi = scene.plane
    c0 = -_core.rotation_from_angle_axis(scene.poses[0, :3]).T @ scene.poses[0, 3:]
    below = c0 - (pi @ c0 + 1.0) / (pi @ pi) * pi
    assert abs(m.plane @ (below + shift) + 1.0) < 0.1


def test_ba_emt_with_a_tracker_origin_far_from_the_cameras(tmp_path):
    """ba-emt centres its world too: the tracker's origin 1 m away along the optical axis (the
    simulated noise on [r, t] then leaks 1 degree x 1 m into t), the same e_M within 1.5x."""
    from dataclasses import replace

    from fusedmosaic.estimation.bundle import run_bundle
    from fusedmosaic.io import read_dataset
    from fusedmosaic.simulation import simulate_fetoscopy

    root = simulate_fetoscopy(tmp_path / "d", FetoscopyOptions(n_frames=16, width=SIZE,
                                                               height=SIZE, laps=16 / 37.5,
                                                               seed=3))
    dataset = read_dataset(root)
    shift = np.array([0.0, 0.0, 1000.0])
    far = replace(dataset, cam_from_world=move_world(dataset.cam_from_world, shift))
    plain = run_bundle(dataset, progress=False)
    moved = run_bundle(far, progress=False)
    e_plain = frame_errors(plain.homographies, dataset.ground_truth, SIZE, SIZE).mean()
    e_moved = frame_errors(moved.homographies, dataset.ground_truth, SIZE, SIZE).mean()
    assert e_moved < max(1.5 * e_plain, 0.5), (e_moved, e_plain)
    # poses and plane in the moved world: the centres shifted, the plane pi' = pi / (1 - pi.s)
    R = _core.rotation_from_angle_axis(moved.poses[5, :3])
    R_p = _core.rotation_from_angle_axis(plain.poses[5, :3])
    np.testing.assert_allclose(-R.T @ moved.poses[5, 3:], -R_p.T @ plain.poses[5, 3:] + shift,
                               atol=2.0)
    np.testing.assert_allclose(moved.plane, plain.plane / (1.0 - plain.plane @ shift),
                               rtol=0.1, atol=1e-5)


def test_motion_sigma_from_a_recording_in_a_tracker_world_near_pi(scene):
    """Sigma_p estimated from poses whose rotations sit at |r| ~ pi equals the estimate in the
    unrotated world (the angle-axis second differences would otherwise be ~2 pi)."""
    from fusedmosaic.estimation.motion import estimate_motion_sigma

    plain = estimate_motion_sigma(scene.tracker)
    turned = estimate_motion_sigma(rotate_world(scene.tracker, LOOKING_DOWN))
    np.testing.assert_allclose(turned, plain, rtol=0.02)
    assert turned[:3].max() < 0.1  # rad: ~2 pi without the alignment


def test_startup_waiting_for_the_tracker_is_bounded(scene):
    """With the tracker off, the start-up keeps at most startup_wait_frames frames (matching
    cost and memory bounded) and hands the oldest out as final and unplaced; once the tracker
    comes on, the kept frames and the new ones are placed."""
    m = SequentialMosaicker(scene.camera,
                            SequentialOptions(bootstrap_frames=8, startup_wait_frames=10))
    final = {}
    for k in range(18):
        assert m.add_frame(scene.frames[k], scene.timestamps[k], None).frame_id == k
        final.update({f.frame_id: f for f in m.finalized()})
        assert len(m._pending) <= 10 and len(m._boot_feats) <= 10
        assert len(m._startup_G) <= 10  # (the chain's homographies grew by one a frame)
    assert sorted(final) == list(range(8))
    assert m.reference_frame is None  # no frame placed yet
    for f in final.values():
        assert f.final and np.isnan(f.homography).all()
        assert f.status == ("unplaced: no registered pair with tracker poses within the "
                            "start-up's 10 frames")
    for k in range(18, N):
        m.add_frame(scene.frames[k], scene.timestamps[k], scene.tracker[k])
        final.update({f.frame_id: f for f in m.finalized()})
    final.update({f.frame_id: f for f in m.flush()})
    assert sorted(final) == list(range(N))
    # frame 18 alone has a tracker pose: still waiting, frame 8 goes too; 19 makes the pair
    assert final[8].status.startswith("unplaced: no registered pair")
    assert all(final[k].status in ("placed", "prior-only") for k in range(9, N))
    # frame 0 unplaced: the homographies map to the first placed frame's grid, and say so
    assert m.reference_frame == 9
    np.testing.assert_allclose(final[9].homography, np.eye(3), atol=1e-12)
    with pytest.raises(ValueError, match=r"startup_wait_frames must be >= bootstrap_frames"):
        SequentialMosaicker(scene.camera,
                            SequentialOptions(bootstrap_frames=8, startup_wait_frames=7))


def test_a_batch_run_whose_startup_hands_frames_out_unplaced_completes(tmp_path):
    """run_lba_emt over a recording whose tracker comes on late (frames 0-17 untracked, the
    start-up keeping 10 frames): the frames handed out before any plane have no plane, and
    the run's plane_history crashed on them (AttributeError, exit 1, no output; a helper's
    fuzzing: the tracker off for the first 86 of 110 frames, 82 black frames at the start, or
    90 frames hovering). Now they are listed with no plane and the rest placed."""
    from fusedmosaic.estimation.sequential import run_lba_emt
    from fusedmosaic.io import read_dataset
    from fusedmosaic.simulation import simulate_fetoscopy

    root = simulate_fetoscopy(tmp_path / "d", FetoscopyOptions(
        n_frames=N, width=SIZE, height=SIZE, laps=N / 37.5, seed=3, tracker_gap=[0, 17]))
    dataset = read_dataset(root, allow_untracked=True)
    result = run_lba_emt(dataset, progress=False, options=SequentialOptions(
        bootstrap_frames=8, startup_wait_frames=10))
    history = result.details["plane_history"]
    handed_out = [k for k, status in enumerate(result.status)
                  if status.startswith("unplaced: no registered pair")]
    assert handed_out and all(history[k] is None for k in handed_out)
    assert all(result.status[k] in ("placed", "prior-only") for k in range(handed_out[-1] + 2, N))


@pytest.mark.parametrize("n", [24, 16])
def test_a_camera_that_does_not_translate_is_mosaicked(tmp_path, n):
    """A scope held still for the whole start-up (24 frames, the start-up keeping 20; or 16
    frames, the sequence ending while it waits): its images show no parallax, the plane came
    out behind the cameras or ~3.7e4 mm away, and lba-emt handed the frames out unplaced and
    refused the sequence (a helper's fuzzing, 80 frames: exit 2; ba-emt e_M 0.027 px). Now
    the start-up puts the plane at nominal_plane_distance_mm and mosaics them, and the run
    warns that the plane's distance is not measured (not that the tracker is in
    micrometres)."""
    from fusedmosaic.estimation.sequential import run_lba_emt
    from fusedmosaic.io import read_dataset
    from fusedmosaic.simulation import simulate_fetoscopy

    root = simulate_fetoscopy(tmp_path / "d", FetoscopyOptions(
        n_frames=n, width=SIZE, height=SIZE, motion="handheld", step_px=0.0,
        rotation_deg=0.0, distance_variation=0.0, yaw_deg=0.0, seed=2))
    dataset = read_dataset(root)
    result = run_lba_emt(dataset, progress=False, options=SequentialOptions(
        bootstrap_frames=8, startup_wait_frames=20))
    errors = frame_errors(result.homographies, dataset.ground_truth, SIZE, SIZE)
    assert np.isfinite(errors).all() and errors.max() < 1.0, errors  # px
    warnings = result.details["warnings"]
    assert any("the camera barely translated" in w and "the plane's distance is not measured"
               in w for w in warnings), warnings
    assert not any("micrometres" in w for w in warnings), warnings


def test_a_startup_far_from_its_solution_converges(tmp_path):
    """A scope 5 mm from the plane: the tracker's 1 mm / 1 deg noise puts the start-up's
    initial poses far from the images' (cost 1.3e8); Ceres' default 100 iterations stopped it
    short with a warning (a helper's fuzzing), startup_max_iterations (300) lets it converge
    at the same accuracy."""
    from fusedmosaic.estimation.sequential import run_lba_emt
    from fusedmosaic.io import read_dataset
    from fusedmosaic.simulation import simulate_fetoscopy

    dataset = read_dataset(simulate_fetoscopy(tmp_path / "d", FetoscopyOptions(
        n_frames=40, width=300, height=300, motion="handheld", distance_mm=5.0,
        radius_mm=3.0)))
    stopped = "the start-up adjustment stopped at its iteration limit (100) before converging"
    short = run_lba_emt(dataset, progress=False,
                        options=SequentialOptions(startup_max_iterations=100))
    assert any(w.startswith(stopped) for w in short.details["warnings"])
    # (the option a user has: it said "raise max_iterations", the window steps' option)
    assert any("raise SequentialOptions.startup_max_iterations" in w
               for w in short.details["warnings"])
    result = run_lba_emt(dataset, progress=False)
    assert result.details["warnings"] == []
    errors = frame_errors(result.homographies, dataset.ground_truth, 300, 300)
    assert errors.max() < 1.0  # px


def test_keyframe_blocks_shorter_than_the_window_are_refused(scene):
    """A keyframe block shorter than the window's fixed part could be evicted while still in
    the window, and the rolled-back step would then fail on every call (review 5 #11)."""
    with pytest.raises(ValueError, match=r"frames_per_cluster must be >= window_size - 1, got 2"):
        SequentialMosaicker(scene.camera, SequentialOptions(window_size=5, frames_per_cluster=2))
    for preset in ("syn", "phb", "ex"):
        SequentialMosaicker(scene.camera, SequentialOptions.preset(preset))
    # (a string failed in arithmetic, naming no option; audit)
    for name, value in (("window_size", "10"), ("num_new", 2.5), ("frames_per_cluster", 0)):
        with pytest.raises(ValueError, match=rf"SequentialOptions\.{name} must be an integer "
                           rf">= 1, got {value!r}"):
            SequentialMosaicker(scene.camera, SequentialOptions(**{name: value}))


# --------------------------------------- the start-up's plane: in front of the cameras, observed
@pytest.fixture(scope="module")
def weak():
    """60 frames of a weakly textured scene (seed 1): the first 8 frames register one pair with
    a 2.5 mm baseline, and a third of the frames none."""
    return Scene(n=60, seed=1)


def test_a_startup_plane_behind_the_cameras_or_unobserved_is_not_taken(weak):
    """Before, the start-up took a plane behind every camera from its one pair: frames 182 px to
    3.4e6 px off. It now waits (measured: taken at frame 27 with 5 pairs, relative std 0.17,
    22.8 px mean, 48.6 px worst; at frame 20, std 0.23, when solved at every frame: 42 px mean,
    75 px worst; with the std check off, the in-front check alone: 1 119 px worst)."""
    from fusedmosaic.estimation.plane import plane_depths

    m = SequentialMosaicker(weak.camera, SequentialOptions(bootstrap_frames=8))
    results = weak.feed(m, range(weak.n), {})
    G = weak.finish(m, results)
    errors = frame_errors(G, weak.truth, SIZE, SIZE)
    assert errors.max() < 150.0, errors  # px
    assert m.bootstrap_summary["plane_relative_std"] <= 0.25
    poses = np.array([results[k].pose for k in range(weak.n)])
    assert (plane_depths(poses, m.plane) > 0).all()
    m = SequentialMosaicker(weak.camera, SequentialOptions(bootstrap_frames=8,
                                                           startup_max_plane_std=0))
    results = weak.feed(m, range(weak.n), {})
    weak.finish(m, results)
    poses = np.array([results[k].pose for k in range(weak.n)])
    assert (plane_depths(poses, m.plane) > 0).all()


def test_a_waiting_startup_is_solved_again_only_when_it_grew(weak, monkeypatch):
    """While its plane is refused, the start-up is solved again once its registered pairs with
    tracker poses, or its frames, grew by a quarter (SequentialMosaicker._startup_due): 9
    solves from frame 7 to frame 27 here, where every frame's re-solve made 20."""
    solves = []
    solve = SequentialMosaicker._solve_startup
    monkeypatch.setattr(SequentialMosaicker, "_solve_startup",
                        lambda self, *args: solves.append(len(args[0])) or solve(self, *args))
    m = SequentialMosaicker(weak.camera, SequentialOptions(bootstrap_frames=8, features=FEW))
    for k in range(weak.n):
        m.add_frame(weak.frames[k], weak.timestamps[k], weak.tracker[k])
        if m.plane is not None:
            break
    assert k > 20 and len(solves) <= 10, (k, solves)
    assert solves[0] == 8 and solves[-1] == k + 1


def test_a_refused_startup_is_taken_once_it_holds_startup_wait_frames():
    """Review: the retry rule asked for both a quarter more frames and startup_wait_frames
    (max, not min): a plane refused at 28 frames of 30 was never solved again (1.25 x 28 > 31,
    the start-up capped at 30 frames) and every frame came out unplaced. Every plane refused
    here (std limit 1e-6) until the start-up holds its 30 frames."""
    scene = Scene(n=40, seed=3)
    m = SequentialMosaicker(scene.camera, SequentialOptions(
        bootstrap_frames=8, startup_wait_frames=30, startup_max_plane_std=1e-6))
    results = scene.feed(m, range(30), {})
    assert m.plane is not None and not any(
        r.status.startswith("unplaced") for r in results.values())


def test_a_sequence_ending_with_the_startup_plane_behind_the_cameras_is_refused(weak):
    m = SequentialMosaicker(weak.camera, SequentialOptions(bootstrap_frames=8, features=FEW))
    weak.feed(m, range(10), {})
    # (the frames of the pair: the others see no plane the start-up could check)
    with pytest.raises(ValueError, match=r"the plane the start-up estimated from 1 registered "
                       r"pairs is not in front of frames \[5, 6\]: too few pairs or too short a "
                       r"baseline to initialise it \(the start-up cameras' centres lie within "
                       r"\d+(\.\d+)? mm of each other\)$"):
        m.flush()


def test_startup_checks_ignore_frames_without_a_registered_pair(scene):
    """Four black frames while the scope turns in (tracked, 120 to 30 degrees from frame 0's
    orientation): they see no plane, so the start-up's in-front check and gate look only at the
    frames with a registered pair. Before, the plane was 'not in front of frames [0]' and the
    start-up waited to frame 27 of 28, or flush refused the sequence (gate off)."""
    R0 = _core.rotation_from_angle_axis(scene.tracker[0, :3])
    c0 = -R0.T @ scene.tracker[0, 3:]
    dt = scene.timestamps[1] - scene.timestamps[0]
    frames, times, tracker = [], [], []
    for i, angle in enumerate((120, 90, 60, 30)):
        R = _core.rotation_from_angle_axis(np.array([np.deg2rad(angle), 0.0, 0.0])) @ R0
        frames.append(np.zeros_like(scene.frames[0]))
        times.append(scene.timestamps[0] - (4 - i) * dt)
        tracker.append(np.r_[_core.angle_axis_from_rotation(R), -R @ c0])
    frames += list(scene.frames)
    times += list(scene.timestamps)
    tracker += list(scene.tracker)
    m = SequentialMosaicker(scene.camera, SequentialOptions(bootstrap_frames=8,
                                                            gate_chi2=np.inf))
    first = None
    for k in range(len(frames)):
        m.add_frame(frames[k], times[k], tracker[k])
        if first is None and m.finalized():
            first = k
    m.flush()
    assert first is not None and first <= 10


def test_one_frame_in_the_start_up_at_the_end_is_named_as_such():
    """A stream ending with a single frame in the start-up (a live session stopped after one
    processed frame) was refused as 'no pair among the first 1 frames could be registered
    with tracker poses', blaming tracking and registration (review)."""
    from fusedmosaic.estimation.sequential import SequentialMosaicker
    from fusedmosaic.io import Camera

    camera = Camera(64, 48, camera_matrix=np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]]))
    m = SequentialMosaicker(camera)
    m.add_frame(np.zeros((48, 64), np.uint8), 0.0, np.zeros(6))
    with pytest.raises(ValueError, match=r"^the sequence ended with 1 frame in the start-up: the "
                                         r"plane needs a registered pair, at least 2 frames with "
                                         r"tracker poses$"):
        m.flush()


def test_a_startup_refused_at_its_bound_is_retried_every_few_frames(tmp_path, monkeypatch):
    """tracking.csv inverted: the start-up's plane is behind its cameras at every attempt. At
    startup_wait_frames it was solved again at every frame (4-8 s an attempt over 80 frames:
    an inverted hand-eye on 150 frames of 240 px took 5.6 min; review); now once every
    STARTUP_RETRY_FRACTION of the bound's frames, still refused with the tracker named."""
    from scipy.spatial.transform import Rotation

    from fusedmosaic.io import (
        TrackingSamples,
        read_dataset,
        read_tracking_csv,
        write_tracking_csv,
    )
    from fusedmosaic.simulation import simulate_fetoscopy

    root = simulate_fetoscopy(tmp_path / "d", FetoscopyOptions(n_frames=60, width=200,
                                                                height=200, laps=60 / 37.5))
    s = read_tracking_csv(root / "tracking.csv")
    inverse = Rotation.from_quat(s.quaternions).inv()
    write_tracking_csv(root / "tracking.csv", TrackingSamples(
        s.timestamps, -inverse.apply(s.translations), inverse.as_quat(), s.valid))
    ds = read_dataset(root)
    attempts = []
    solve = SequentialMosaicker._solve_startup

    def recorded(self, *args, **kwargs):
        attempts.append(self._next_id)
        return solve(self, *args, **kwargs)

    monkeypatch.setattr(SequentialMosaicker, "_solve_startup", recorded)
    wait = 24
    m = SequentialMosaicker(ds.camera, SequentialOptions(bootstrap_frames=8,
                                                         startup_wait_frames=wait))
    for k in range(len(ds)):
        m.add_frame(ds.frames[k], float(ds.timestamps[k]), ds.cam_from_world[k])
    assert m.plane is None
    assert "not in front of frames" in m._startup_problem
    assert "the tracker's poses likely contradict them" in m._startup_problem
    at_bound = sorted({k for k in attempts if k > wait})
    step = round(sequential.STARTUP_RETRY_FRACTION * wait)  # 3
    assert at_bound and np.diff([wait, *at_bound]).min() >= step, attempts
    assert len(at_bound) <= (len(ds) - wait) // step + 1, attempts  # was one every frame: 36
