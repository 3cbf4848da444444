"""Session-45 review of the C++ sliding window (review A, findings 4 and 6): the step summary
counts the new frames' temporal pairs (with the window_size - 1 frames before the first new one,
outside the window) apart from loop pairs, and a fixed frame whose tracker sample was dropped
keeps its pose."""

from __future__ import annotations

import numpy as np
import pytest

from fusedmosaic import _core
from fusedmosaic.simulation import FetoscopyOptions, generate_fetoscopy


@pytest.fixture(scope="module")
def scene():
    return generate_fetoscopy(FetoscopyOptions(n_frames=9, width=200, height=200,
                                               laps=9 / 152, seed=3))


def _pair(scene, l, m, n):
    """n correspondences of frame m transferred into frame l through the true plane."""
    K, poses = scene.camera_matrix, scene.poses
    rng = np.random.default_rng(l * 100 + m)
    pts_m = rng.uniform(60, 140, (n, 2))
    pts_l = _core.transfer_points(pts_m, poses[l], poses[m], scene.plane, K)
    return l, m, pts_l, pts_m


def _window(scene):
    """SYN preset (W = 5, chi_e = 3): frames 0-5 fixed at the truth, 6-8 pending."""
    w = _core.SlidingWindow(scene.camera_matrix, _core.SlidingWindowOptions(window_size=5,
                                                                             num_new=3))
    for k in range(9):
        w.add_frame(k, scene.poses[k], scene.poses[k], fixed=k < 6)
    w.set_plane(scene.plane)
    return w


def test_step_counts_temporal_pairs_apart_from_loop_pairs(scene):
    """Frame 6's pairs: with 5 (window: the last W - chi_e = 2 fixed frames are 4, 5), with 3
    (temporal: one of the W - 1 = 4 frames 2-5 before it, outside the window) and with 1
    (outside both: loop). Before, the pair with 3 was counted as a loop pair."""
    w = _window(scene)
    for l, m, n in ((6, 5, 20), (6, 3, 30), (6, 1, 40)):
        w.add_pair(*_pair(scene, l, m, n))
    s = w.step([])
    assert list(s.fixed_ids) == [4, 5]
    assert (s.num_window_correspondences, s.num_temporal_correspondences,
            s.num_loop_correspondences) == (20, 30, 40)
    assert s.num_correspondences == 90


def test_a_fixed_frame_keeps_its_pose_when_its_sample_is_dropped(scene):
    """drop_emt_measurement on a fixed frame: pose() gives the pose later steps hold constant
    (it said 'pending without a pose'); a pending frame without a pose is still refused."""
    w = _window(scene)
    w.drop_emt_measurement(2)
    np.testing.assert_array_equal(w.pose(2), scene.poses[2])
    assert 2 not in w.pending_ids()
    w.add_frame(9, None, None)
    with pytest.raises(ValueError, match="frame 9 is pending without a pose yet"):
        w.pose(9)


def test_forgetting_frames_keeps_the_window_mirror_consistent():
    """Keyframe candidates evicted early (max_keyframe_blocks=2): SequentialMosaicker's mirror of
    the C++ window (what a failed call rebuilds it from) forgets exactly the evicted frames'
    pairs, through its per-frame index, and a window rebuilt from it holds what the C++ one
    does; the run stays accurate."""
    from test_sequential_robustness import Scene

    from fusedmosaic.estimation.sequential import SequentialMosaicker, SequentialOptions
    from fusedmosaic.evaluation import frame_errors

    scene = Scene(n=90)
    m = SequentialMosaicker(scene.camera, SequentialOptions(bootstrap_frames=8,
                                                            max_keyframe_blocks=2))
    results = scene.feed(m, range(scene.n), {})
    frames, pairs = m._mirror_frames, m._mirror_pairs
    assert len(frames) < 60 and m.window.num_frames == len(frames)  # frames were forgotten
    assert m.window.num_pairs == len(pairs)
    assert all(l in frames and f in frames for l, f in pairs)
    indexed = {key for keys in m._mirror_pair_index.values() for key in keys}
    assert indexed == set(pairs) and set(m._mirror_pair_index) <= set(frames)
    assert all(key in m._mirror_pair_index[k] for key in pairs for k in key)
    before = (m.window.num_frames, m.window.num_pairs, m.window.num_correspondences)
    m._rebuild_window()
    assert (m.window.num_frames, m.window.num_pairs, m.window.num_correspondences) == before
    G = scene.finish(m, results)
    assert np.nanmedian(frame_errors(G, scene.truth, 200, 200)) < 1.0  # px
