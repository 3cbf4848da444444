"""LBAVis+EMT after a review of the sequential method (its findings 1-8 and two of
its unconfirmed notes): a window step that Ceres ends in FAILURE (a tracker sample putting
its camera centre on the plane) is reported, recovered or flagged, never a crash nor silently
"placed"; history_steps=0; the start-up's tables sized by the frames it holds; SlidingWindow
refusing bad keyframe ids before any change; frames unplaced for a plane through their camera
forgotten; Ceres' error lines kept off stderr; tracker_pose shape messages; K-means on
coinciding centroids; window_size >= num_new + 2. Small frames (200x200) and an 8-frame
start-up keep every run to a few seconds."""

import sys
import warnings
from types import SimpleNamespace

import numpy as np
import pytest
from test_sequential_robustness import SIZE, Scene  # the 24-frame SYN scene

import fusedmosaic.estimation.sequential as sequential
from fusedmosaic import _core
from fusedmosaic.estimation.consistency import solver_warning
from fusedmosaic.estimation.keyframes import KeyframeIndex
from fusedmosaic.estimation.sequential import (
    SOLVER_FAILED_STATUS,
    SequentialMosaicker,
    SequentialOptions,
    live_solver_warnings,
    run_lba_emt,
)
from fusedmosaic.evaluation import frame_errors

GLITCH = 14


@pytest.fixture(scope="module")
def scene():
    return Scene()


def on_plane(pose, plane):
    """The cam_from_world pose with its camera centre moved onto the plane pi (pi . X + 1 = 0)."""
    R = _core.rotation_from_angle_axis(pose[:3])
    c = -R.T @ pose[3:]
    c_on = c - (plane @ c + 1.0) / (plane @ plane) * plane
    return np.r_[pose[:3], -R @ c_on]


def stream(scene, options=None, glitch=None, mosaicker=None):
    """Streams the scene; glitch: the frame whose sample is moved onto the current plane (as
    the review's r9_failure_summary.py). Returns the mosaicker, results by id, homographies."""
    m = mosaicker or SequentialMosaicker(scene.camera, options or SequentialOptions(
        bootstrap_frames=8))
    results = {}
    for k in range(scene.n):
        pose = scene.tracker[k]
        if k == glitch:
            pose = on_plane(pose, m.plane)
        m.add_frame(scene.frames[k], scene.timestamps[k], pose)
        results.update({f.frame_id: f for f in m.finalized()})
    results.update({f.frame_id: f for f in m.flush()})
    G = np.stack([results[k].homography for k in range(scene.n)])
    return m, results, G


@pytest.fixture(scope="module")
def baseline(scene):
    _, results, G = stream(scene)
    errors = frame_errors(G, scene.truth, SIZE, SIZE)
    assert errors.mean() < 1.0
    return results, errors


# ------------------------------------------------------------------ a failing window (C++)
K = np.array([[450.0, 0, 199.5], [0, 450, 199.5], [0, 0, 1]])
PLANE = np.array([0, 0, -1 / 35.0])  # z = 35 mm, in front of cameras looking along +z


def failing_window():
    """A window whose pending frame 5 has a tracker sample with its centre on the plane: the
    step's evaluation fails at the start."""
    w = _core.SlidingWindow(K, _core.SlidingWindowOptions(window_size=5, num_new=1))
    w.set_plane(PLANE)
    for k in range(5):
        pose = np.array([0, 0, 0, -0.5 * k, 0, 0.0])
        w.add_frame(k, pose, pose, fixed=True)
    w.add_frame(5, None, np.array([0, 0, 0, -2.5, 0, -35.0]))  # centre (2.5, 0, 35): on it
    pts = np.array([[100.0, 100], [300, 120], [150, 300], [250, 250], [200, 180]])
    w.add_pair(4, 5, pts, pts + [2.0, 0.0])
    w.add_pair(3, 4, pts, pts + [2.0, 0.0])
    return w


def test_a_failed_window_step_reports_ceres_message():
    summary = failing_window().step()
    assert summary.termination == "FAILURE"
    assert "evaluation failed" in summary.message
    warning = solver_warning(summary, 20, "a window step")
    assert warning.startswith("a window step failed: Ceres FAILURE: ")
    assert summary.message in warning


def test_solver_warning_without_a_message_field():
    """A summary without `message` (an older build's, a stand-in) is reported, not a crash."""
    summary = SimpleNamespace(termination="FAILURE")
    assert solver_warning(summary, 20) == "the adjustment failed: Ceres FAILURE"
    assert solver_warning({"termination": "FAILURE", "message": ""}, 20) == (
        "the adjustment failed: Ceres FAILURE")
    assert solver_warning(SimpleNamespace(termination="CONVERGENCE"), 20) is None


def test_ceres_error_lines_stay_off_stderr(capfd):
    """Finding 7: a failed solve printed glog's "Terminating: Residual and Jacobian evaluation
    failed." (and "Logging before InitGoogleLogging()") on stderr; its summary says it."""
    capfd.readouterr()
    summary = failing_window().step()
    assert summary.termination == "FAILURE"
    err = capfd.readouterr().err
    assert "Terminating" not in err and "InitGoogleLogging" not in err, err


def test_drop_emt_measurement_reinitialises_the_frame_from_the_motion():
    w = failing_window()
    assert w.step().termination == "FAILURE"
    w.drop_emt_measurement(5)
    summary = w.redo([5])
    assert summary.termination == "CONVERGENCE", summary.message
    assert np.isnan(summary.emt_mahalanobis2[0])  # no sample any more
    # predicted at constant velocity from frames 3, 4 (0.5 mm a frame), and the images agree
    centre = -_core.rotation_from_angle_axis(w.pose(5)[:3]).T @ w.pose(5)[3:]
    assert abs(centre[2]) < 5.0 and 1.5 < centre[0] < 3.5


# ---------------------------------------------------------------- findings 1 and 2 (streams)
def test_a_sample_on_the_plane_is_dropped_and_its_step_redone(scene, baseline, capfd):
    """Findings 1, 2, 7: frame 14's sample on the plane (within the glitch filter's bound)
    failed its step and the next ones, leaving frames 15-21 4-25 px off, labelled "placed",
    and live_solver_warnings raised AttributeError. Now the sample is dropped, the step redone:
    every frame within 0.1 px of its error without the glitch, no failed step, nothing on
    stderr."""
    _, base = baseline
    capfd.readouterr()
    m, results, G = stream(scene, glitch=GLITCH)
    assert "Terminating" not in capfd.readouterr().err
    errors = frame_errors(G, scene.truth, SIZE, SIZE)
    assert [s.termination for s in m.step_summaries if s.termination == "FAILURE"] == []
    assert live_solver_warnings(m) == []
    assert results[GLITCH].tracker_dropped and results[GLITCH].tracker_gated
    assert all(r.status == "placed" for r in results.values()), {
        k: r.status for k, r in results.items() if r.status != "placed"}
    worst = np.max(np.abs(errors - base))
    assert worst < 0.1, np.round(errors - base, 3)


def test_a_step_that_still_fails_flags_its_frames(scene, monkeypatch, capfd):
    """Finding 2's fallback: when the failing samples cannot be found (here: the search is
    switched off) the step's frames are "prior-only (solver failed)", never "placed"; the
    warnings count the failed steps and live_solver_warnings does not crash (finding 1)."""
    monkeypatch.setattr(SequentialMosaicker, "_unusable_samples", lambda self, ids: set())
    m = SequentialMosaicker(scene.camera, SequentialOptions(bootstrap_frames=8))
    results, failed_frames = {}, set()
    for k in range(scene.n):
        pose = on_plane(scene.tracker[k], m.plane) if k == GLITCH else scene.tracker[k]
        steps = m.num_steps
        m.add_frame(scene.frames[k], scene.timestamps[k], pose)
        if m.num_steps > steps and m.last_step_summary.termination == "FAILURE":
            failed_frames |= set(m.last_step_summary.frame_ids)
        results.update({f.frame_id: f for f in m.finalized()})
    results.update({f.frame_id: f for f in m.flush()})
    assert GLITCH in failed_frames
    flagged = {k for k, r in results.items() if r.status == SOLVER_FAILED_STATUS}
    # (frame 14, left on the plane, cannot even be placed: unplaced, as such frames were)
    on_the_plane = {k for k, r in results.items() if "plane passes through" in r.status}
    assert on_the_plane == {GLITCH}
    assert flagged | on_the_plane == failed_frames
    assert all(results[k].final for k in flagged)
    assert all(r.status == "placed" for k, r in results.items() if k not in failed_frames)
    warnings_ = live_solver_warnings(m)
    assert any("did not converge (Ceres FAILURE" in w for w in warnings_), warnings_
    assert "Terminating" not in capfd.readouterr().err


def test_run_lba_emt_survives_a_failed_step(scene, monkeypatch):
    """Finding 1 through run_lba_emt (its take() read the step summary's message): the run
    completes, its statuses flag the failed frames, and its warnings say why."""
    monkeypatch.setattr(SequentialMosaicker, "_unusable_samples", lambda self, ids: set())
    m = SequentialMosaicker(scene.camera, SequentialOptions(bootstrap_frames=8))
    for k in range(GLITCH):
        m.add_frame(scene.frames[k], scene.timestamps[k], scene.tracker[k])
    poses = scene.tracker.copy()
    poses[GLITCH] = on_plane(poses[GLITCH], m.plane)
    dataset = SimpleNamespace(frames=scene.frames, timestamps=scene.timestamps,
                              camera=scene.camera, pose_valid=np.ones(scene.n, bool),
                              cam_from_world=poses)
    monkeypatch.setattr(sequential, "add_tracker_agreement", lambda *args, **kw: None)
    result = run_lba_emt(dataset, progress=False,
                         options=SequentialOptions(bootstrap_frames=8, history_steps=0))
    assert SOLVER_FAILED_STATUS in result.status
    assert result.details["solver_failed"] == [k for k, s in enumerate(result.status)
                                                if s == SOLVER_FAILED_STATUS]
    assert any("Ceres FAILURE" in w for w in result.details["warnings"])


# ------------------------------------------------------------------------------- finding 3
def test_history_steps_zero_runs(scene, monkeypatch):
    monkeypatch.setattr(sequential, "add_tracker_agreement", lambda *args, **kw: None)
    dataset = SimpleNamespace(frames=scene.frames, timestamps=scene.timestamps,
                              camera=scene.camera, pose_valid=np.ones(scene.n, bool),
                              cam_from_world=scene.tracker)
    runs = {h: run_lba_emt(dataset, progress=False,
                           options=SequentialOptions(bootstrap_frames=8, history_steps=h))
            for h in (0, 1)}
    assert runs[0].details["window_step_ms"]["steps"] == runs[1].details["window_step_ms"][
        "steps"] > 0
    np.testing.assert_array_equal(runs[0].homographies, runs[1].homographies)


# ------------------------------------------------------------------------------- finding 4
def test_startup_tables_are_sized_by_the_frames_held_not_the_frame_count(scene, monkeypatch):
    """A start-up waiting for its tracker held 8 frames but built its tables over every frame
    id (np.full((frame count, 6))) at each frame, and unanchored_frames over all ids when it
    finally ran. The frame counter is fast-forwarded (the only input to those sizes), then the
    tracker comes on: the start-up runs, places the frames, with tables of <= 8 rows."""
    o = SequentialOptions(bootstrap_frames=8, startup_wait_frames=8)
    m = SequentialMosaicker(scene.camera, o)
    rows, sizes = [], []
    real_poses = m._pending_tracker_poses

    def spy():
        tracked, table = real_poses()
        rows.append(table.shape[0])
        return tracked, table

    monkeypatch.setattr(m, "_pending_tracker_poses", spy)
    real_unanchored = sequential.unanchored_frames
    monkeypatch.setattr(sequential, "unanchored_frames",
                        lambda n, *args: sizes.append(n) or real_unanchored(n, *args))
    t = 0.0
    for k in range(10):  # no tracker: the start-up waits
        t += 0.04
        m.add_frame(scene.frames[k], t, None)
    m._next_id = 3_000_000  # ~28 h at 30 frames/s
    results = {}
    for k in range(10, scene.n):
        t += 0.04
        r = m.add_frame(scene.frames[k], t, scene.tracker[k])
        assert r.frame_id == 3_000_000 + k - 10
        results.update({f.frame_id: f for f in m.finalized()})
    results.update({f.frame_id: f for f in m.flush()})
    # (the new frame joins before the oldest is handed out: one more)
    assert rows and max(rows) <= o.startup_wait_frames + 1, max(rows)
    assert sizes and max(sizes) <= o.startup_wait_frames + 1, sizes
    placed = [k for k, r in results.items() if k >= 3_000_000 and r.status == "placed"]
    assert len(placed) >= 10, {k: r.status for k, r in results.items()}


# ------------------------------------------------------------------------------- finding 5
def stepped_window():
    w = _core.SlidingWindow(K, _core.SlidingWindowOptions(window_size=5, num_new=3))
    w.set_plane(PLANE)
    poses = [np.array([0, 0, 0, 0.5 * k, 0, 0.0]) for k in range(8)]
    for k in range(5):
        w.add_frame(k, poses[k], poses[k], fixed=True)
    for k in range(5, 8):
        w.add_frame(k, None, poses[k] + 0.3)
    w.step([])
    return w


@pytest.mark.parametrize("keyframes, error, message", [
    ([6], ValueError, "redo: keyframe 6 is among the frames this call estimates"),
    ([99], IndexError, "unknown frame id 99"), ([2, 99], IndexError, "unknown frame id 99")])
def test_redo_refused_for_a_bad_keyframe_changes_nothing(keyframes, error, message):
    w = stepped_window()
    before = [np.array(w.pose(k)) for k in range(8)]
    with pytest.raises(error, match=message):
        w.redo([5, 6, 7], keyframes)
    assert w.pending_ids() == []
    for k in range(8):
        np.testing.assert_array_equal(w.pose(k), before[k])
    assert w.redo([5, 6, 7], [2]).termination == "CONVERGENCE"


@pytest.mark.parametrize("keyframes, error, message", [
    ([8], ValueError, "step: keyframe 8 is not yet fixed"),
    ([99], IndexError, "unknown frame id 99")])
def test_step_refused_for_a_bad_keyframe_changes_nothing(keyframes, error, message):
    w = stepped_window()
    w.add_frame(8, None, None)  # no pose until its step
    w.add_frame(9, None, np.array([0, 0, 0, 4.5, 0, 0.0]))
    with pytest.raises(error, match=message):
        w.step(keyframes)
    assert w.pending_ids() == [8, 9]
    with pytest.raises(ValueError, match="pending without a pose yet"):
        w.pose(8)  # not initialised by the refused call
    assert w.step([2]).frame_ids == [8, 9]


# ------------------------------------------------------------------------------- finding 6
def test_frames_unplaced_for_a_plane_through_their_camera_are_forgotten(monkeypatch):
    """As the review's r7: transfer_homography raises for frame 20 inside _finalize (a camera
    on the plane); with max_keyframe_blocks=2 every other old frame is forgotten, frame 20 was
    kept for the rest of the run."""
    scene = Scene(n=60)
    real = sequential._core

    class Proxy:
        def __getattr__(self, name):
            return getattr(real, name)

        def transfer_homography(self, *args):
            caller = sys._getframe(1)
            if caller.f_code.co_name == "_finalize" and caller.f_locals.get("k") == 20:
                raise ValueError("plane through the camera (injected)")
            return real.transfer_homography(*args)

    monkeypatch.setattr(sequential, "_core", Proxy())
    m = SequentialMosaicker(scene.camera, SequentialOptions(bootstrap_frames=8,
                                                            max_keyframe_blocks=2))
    status = {}
    for k in range(scene.n):
        m.add_frame(scene.frames[k], scene.timestamps[k], scene.tracker[k])
        status.update({f.frame_id: f.status for f in m.finalized()})
    assert status[20].startswith("unplaced: the estimated plane passes through")
    assert 20 not in m._mirror_frames and 20 not in m._orphans
    assert all(20 not in key for key in m._mirror_pairs)
    assert m.window.num_frames == len(m._mirror_frames) <= 2 * 5 + 8


# ------------------------------------------------------------------------------- finding 8
@pytest.mark.parametrize("shape", [(1, 6), (6, 1), (4, 4), (7,)])
def test_tracker_pose_shape_errors_name_the_shapes(scene, shape):
    m = SequentialMosaicker(scene.camera, SequentialOptions(bootstrap_frames=8))
    pose = np.zeros(shape)
    if shape == (4, 4):
        pose = np.eye(4)
    with pytest.raises(ValueError) as info:
        m.add_frame(scene.frames[0], 0.0, pose)
    text = str(info.value)
    assert "shape (6,)" in text and f"got shape {shape}" in text, text
    assert ("camera_pose_from_sample" in text) == (shape == (4, 4)), text
    assert m.frame_count == 0


# ------------------------------------------------------------------ unconfirmed notes
def test_kmeans_on_coinciding_centroids_is_quiet_and_picks_a_block():
    index = KeyframeIndex(5, max_blocks=200, rng=np.random.default_rng(0))
    for k in range(60):
        index.add(k, np.array([100.0, 100.0]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        picks = index.select(3)
    assert len(picks) == 5 and picks == list(range(picks[0], picks[0] + 5))
    # two distinct spots, 3 clusters: one block from each
    index = KeyframeIndex(5, max_blocks=200, rng=np.random.default_rng(0))
    for k in range(60):
        index.add(k, np.array([100.0, 100.0]) if k < 30 else np.array([500.0, 100.0]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        picks = index.select(3)
    assert len(picks) == 10 and min(picks) < 30 <= max(picks)
    # four spots, K = 3: K-means over the distinct ones
    index = KeyframeIndex(5, max_blocks=200, rng=np.random.default_rng(0))
    for k in range(80):
        index.add(k, np.array([100.0 + 400.0 * (k // 20), 100.0]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        picks = index.select(3)
    assert len(picks) == 15


def test_kmeans_on_distinct_centroids_is_unchanged():
    """Distinct centroids take the path they took before (same draws, same picks)."""
    from scipy.cluster.vq import kmeans2

    rng = np.random.default_rng(5)
    points = rng.uniform(0, 1000, (12, 2))
    index = KeyframeIndex(5, max_blocks=200, rng=np.random.default_rng(0))
    for k in range(60):
        index.add(k, points[k // 5] + rng.normal(0, 1, 2))
    blocks = list(index._blocks.values())
    pts = np.array([b.centroid for b in blocks])
    draw = np.random.default_rng(0)
    _, labels = kmeans2(pts, 3, minit="++", seed=int(draw.integers(2**31 - 1)))
    expected = []
    for c in range(3):
        members = np.flatnonzero(labels == c)
        if len(members):
            expected.append(blocks[int(draw.choice(members))])
    assert index.select(3) == sorted(k for b in expected for k in b.frame_ids)


def test_window_needs_two_fixed_predecessors_for_the_motion_prior(scene):
    with pytest.raises(ValueError, match=r"window_size: must be >= num_new \+ 2 \(3\)"):
        _core.SlidingWindowOptions(window_size=2, num_new=1)
    with pytest.raises(ValueError, match=r"window_size: must be >= num_new \+ 2"):
        _core.SlidingWindowOptions(window_size=3, num_new=3)
    # without C_p the window may be as short as num_new
    costs = _core.BundleAdjusterOptions()
    costs.use_motion_prior = False
    _core.SlidingWindowOptions(window_size=3, num_new=3, costs=costs)
    _core.SlidingWindowOptions(window_size=3, num_new=1)  # (the phb preset)
    with pytest.raises(ValueError, match=r"window_size must be >= num_new \+ 2"):
        SequentialMosaicker(scene.camera, SequentialOptions(window_size=4, num_new=3,
                                                            frames_per_cluster=5))
