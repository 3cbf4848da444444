"""Review B (pCLE streaming / sampling) findings, each reproduced here before its fix:

1. The gap rule "3x the median sample spacing" flagged every long spacing of a robot sampled
   in pairs or bursts as a dropout: kalman-robot silently became ncc (e_M 10.5 -> 117.9 px),
   ``robot`` failed with "no placed frame to compose a mosaic from". Now 3x
   io.tracking.sample_spacing, in interpolate_robot, interpolate_camera_poses, the live
   replay's sample age and IgtlSource; ``robot`` names the cause when no frame has a sample.
2. The live replay took a robot sample stamped a rounding error after the frame for "not
   arrived yet"; the simulator stamped its samples j * (1 / rate), not j / rate as the frames.
3. After a dropped frame the Kalman filter judged the 2-interval image step a speed outlier.
"""

from __future__ import annotations

import numpy as np
import pytest

from fusedmosaic.estimation.kalman import RobotKalmanFilter
from fusedmosaic.estimation.live import newest_sample_index, replay_live
from fusedmosaic.estimation.translation import (
    RobotPriorMosaicker,
    run_kalman_robot,
    run_robot,
)
from fusedmosaic.io import read_dataset
from fusedmosaic.io.tracking import (
    RobotSamples,
    TrackingSamples,
    interpolate_camera_poses,
    interpolate_robot,
    read_robot_csv,
    sample_spacing,
    write_robot_csv,
)
from fusedmosaic.simulation import PcleOptions, simulate_pcle
from fusedmosaic.simulation._options import frame_times, sample_times
from fusedmosaic.simulation.pcle import generate_pcle

PCLE = PcleOptions(width=192, height=160, n_frames=14, speed_um_per_frame=12.0, radius_um=150.0,
                   contact_loss=False, stick_slip=False)


@pytest.fixture(scope="module")
def pcle(tmp_path_factory):
    return simulate_pcle(tmp_path_factory.mktemp("sampling") / "pcle", PCLE)


def _paired(times: np.ndarray, step: float = 0.001) -> np.ndarray:
    """Each sample time followed `step` s later by a second one (a controller reporting twice
    per cycle)."""
    return np.sort(np.r_[times, times + step])


def _robot_in_pairs(root, tmp_path):
    """A copy of the dataset at `root` whose robot.csv has a second sample 1 ms after each one,
    on the same path (the positions interpolated there)."""
    import shutil

    out = tmp_path / "pairs"
    shutil.copytree(root, out)
    robot = read_robot_csv(out / "robot.csv")
    ts = _paired(robot.timestamps[:-1])
    xy = np.stack([np.interp(ts, robot.timestamps, robot.xy_um[:, j]) for j in range(2)], 1)
    write_robot_csv(out / "robot.csv", RobotSamples(ts, xy))
    return out


# -- 1. the gap rule ----------------------------------------------------------------------------


def test_sample_spacing_of_even_paired_bunched_and_dropout_samples():
    even = np.arange(0.0, 2.0, 0.025)
    assert sample_spacing(even) == pytest.approx(float(np.median(np.diff(even))), rel=1e-12)
    # pairs 1 ms + 19 ms (50 Hz, twice per cycle): the long spacing, not the 1 ms median
    assert sample_spacing(_paired(np.arange(0.0, 2.0, 0.02))) == pytest.approx(0.019)
    # a 1 kHz logger bunching 15 samples per 15.6 ms tick (stamps 1 µs apart)
    ticks = np.arange(0.0, 2.0, 0.0156)
    bunched = (ticks[:, None] + 1e-6 * np.arange(15)).ravel()
    assert sample_spacing(bunched) == pytest.approx(0.0156 - 14e-6)
    # a dropout of 70 % of the span raises neither the median nor the quartile
    dropout = np.r_[np.arange(0.0, 0.3, 0.01), np.arange(1.0, 1.3, 0.01)]
    assert sample_spacing(dropout) == pytest.approx(0.01)
    # one holding 80 % of the span raises the quartile, not the 95th percentile (a tracker
    # off for frames 0-85 of 110 was bridged by a straight line)
    dropout = np.r_[-0.1, np.arange(3.4, 4.4, 0.025)]
    assert sample_spacing(dropout) == pytest.approx(0.025)
    with pytest.raises(ValueError, match="at least 2"):
        sample_spacing([1.0])


def test_interpolate_robot_sampled_in_pairs_is_no_dropout_but_a_real_gap_is():
    ts = _paired(np.r_[np.arange(0.0, 1.0, 0.02), np.arange(1.5, 3.0, 0.02)])
    samples = RobotSamples(ts, np.stack([100.0 * ts, -50.0 * ts], axis=1))
    frames = np.arange(0.05, 2.9, 0.1)
    xy, valid = interpolate_robot(samples, frames)
    in_gap = (frames > 0.981) & (frames < 1.5)
    assert in_gap.sum() == 5
    np.testing.assert_array_equal(valid, ~in_gap)  # (before: every frame invalid)
    np.testing.assert_allclose(xy[valid], np.stack([100.0 * frames, -50.0 * frames], 1)[valid])


def test_interpolate_camera_poses_of_a_tracker_sampled_in_pairs():
    ts = _paired(np.arange(0.0, 2.0, 0.025))
    translations = np.stack([ts, 2 * ts, 0 * ts], axis=1)
    quaternions = np.tile([0.0, 0.0, 0.0, 1.0], (ts.size, 1))
    samples = TrackingSamples(ts, translations, quaternions)
    frames = np.arange(0.01, 1.9, 0.04)
    for method in ("linear", "cubic"):
        poses, valid = interpolate_camera_poses(samples, frames, method=method)
        assert valid.all(), (method, np.flatnonzero(~valid))  # (before: most invalid)
        np.testing.assert_allclose(poses[:, 3], -frames, atol=1e-9)


def test_kalman_robot_and_robot_with_a_robot_sampled_in_pairs_offline_and_live(pcle, tmp_path):
    """The robot of the simulated pCLE dataset reporting in pairs (1 ms, then 19 ms): no frame
    without a sample, offline, in the live replay, and for ``robot``; positions as with the
    original robot.csv (before: 14 of 14 frames without a sample, kalman-robot = ncc, ``robot``
    unplaced everywhere)."""
    original = read_dataset(pcle)
    pairs = read_dataset(_robot_in_pairs(pcle, tmp_path))
    assert pairs.robot_valid.all()
    expected = run_kalman_robot(original, progress=False)
    fused = run_kalman_robot(pairs, progress=False)
    assert fused.details["frames_without_robot_sample"] == []
    np.testing.assert_allclose(fused.homographies, expected.homographies, atol=1e-6)
    robot = run_robot(pairs, progress=False)
    assert all(s == "prior-only" for s in robot.status[1:]), robot.status
    for method in ("kalman-robot", "robot"):
        live = replay_live(pairs, method, progress=False, processing_time=lambda k: 0.0)
        assert live.details["live"]["frames_without_sample"] == [], method
        assert live.details["live"]["max_sample_age_s"] == pytest.approx(3 * 0.019, rel=1e-6)


def test_robot_without_any_frame_sample_names_the_file_and_the_cause(pcle, tmp_path, capsys):
    """Every frame inside one dropout of the robot: ``robot`` said only "no placed frame to
    compose a mosaic from"."""
    import shutil

    from fusedmosaic.cli import main

    root = tmp_path / "gap"
    shutil.copytree(pcle, root)
    frames = read_dataset(root).timestamps
    ts = np.r_[np.arange(frames[0] - 1.0, frames[0] - 0.04, 0.01),
               np.arange(frames[-1] + 0.05, frames[-1] + 1.0, 0.01)]
    write_robot_csv(root / "robot.csv", RobotSamples(ts, np.zeros((ts.size, 2))))
    dataset = read_dataset(root)
    assert not dataset.robot_valid.any()
    message = (f"{root / 'robot.csv'}: none of the {len(dataset)} frames has a robot sample "
               "(each lies outside its time span or in a gap between samples longer than 3x "
               "their typical spacing (10 ms)): method 'robot' places "
               "frames by their robot samples alone and has none to place")
    with pytest.raises(ValueError) as raised:
        run_robot(dataset, progress=False)
    assert str(raised.value) == message
    with pytest.raises(ValueError, match=r"none of the 14 frames has a robot sample \(live "
                                         r"replay: none at or up to 30 ms before each frame\)"):
        replay_live(dataset, "robot", progress=False, processing_time=lambda k: 0.0)
    out = tmp_path / "out"
    assert main(["--quiet", "run", str(root), "--method", "robot", "--out", str(out)]) == 2
    assert capsys.readouterr().err == f"fusedmosaic: error: {message}\n"


# -- 2. a sample a rounding error after the frame ---------------------------------------------


def test_newest_sample_index_counts_a_sample_a_rounding_error_late_as_at_the_frame():
    times = np.array([0.2, 0.1 + 0.1 + 0.1])  # 0.30000000000000004
    assert newest_sample_index(times, 0.3, 0.25) == 1  # (before: 0, the sample 100 ms older)
    assert newest_sample_index(np.array([0.2, 0.301]), 0.3, 0.25) == 0  # 1 ms late: not yet
    big = 1.7e9 + 0.3  # a Unix time: 16 ulp is ~4 µs, over the 1 µs floor
    assert newest_sample_index(np.array([big - 0.1, big + 3e-6]), big, 0.25) == 1
    assert newest_sample_index(np.array([big - 0.1, big + 1e-4]), big, 0.25) == 0
    assert newest_sample_index(np.array([0.31]), 0.3, 1.0) is None


def test_simulated_samples_at_the_frame_rate_stamp_the_frame_times():
    options = PcleOptions(robot_rate_hz=10.0, robot_offset_s=0.0, n_frames=79)
    frames = frame_times(options, 79)
    samples = sample_times(options, "robot", float(frames[-1]))
    assert np.isin(frames, samples).all()  # (before: 30 % of frames 1 ulp off their sample)


def test_live_replay_of_a_frame_synchronous_robot_equals_offline(pcle, tmp_path):
    """A robot sampled at the frame times, its stamps sums of the period (some 1 ulp after the
    frame): the replay took the previous sample for those and differed from offline."""
    import shutil

    root = tmp_path / "sync"
    shutil.copytree(pcle, root)
    frames = read_dataset(root).timestamps
    robot = read_robot_csv(root / "robot.csv")
    period = 1.0 / PCLE.fps
    ts = np.cumsum(np.r_[-period, np.full(frames.size + 1, period)])  # -0.1, 0, 0.1, ...
    assert (ts[1:-1] != frames).any()  # some stamps a rounding error off the frame times
    xy = np.stack([np.interp(ts, robot.timestamps, robot.xy_um[:, j]) for j in range(2)], 1)
    write_robot_csv(root / "robot.csv", RobotSamples(ts, xy))
    dataset = read_dataset(root)
    offline = run_kalman_robot(dataset, progress=False)
    live = replay_live(dataset, "kalman-robot", progress=False, processing_time=lambda k: 0.0)
    assert live.details["live"]["sample_age_ms"]["max"] == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(live.homographies, offline.homographies, atol=1e-6)


# -- 3. a frame after a dropped one -----------------------------------------------------------


def test_kalman_speed_history_takes_the_step_per_frame_interval():
    def run(last_step, intervals):
        kf = RobotKalmanFilter()
        for _ in range(10):
            kf.update([10.0, 0.0], [10.0, 0.0], 0.9)
        return kf.update([last_step, 0.0], [last_step, 0.0], 0.9, intervals)

    steady = run(10.0, 1.0)
    after_drop = run(20.0, 2.0)
    assert after_drop.c_speed == pytest.approx(steady.c_speed)
    assert run(20.0, 1.0).c_speed < 0.6  # a real jump is still one
    with pytest.raises(ValueError, match="intervals must be a number > 0"):
        RobotKalmanFilter().update([1.0, 0.0], [1.0, 0.0], 0.9, 0.0)


@pytest.fixture(scope="module")
def scene():
    return generate_pcle(PcleOptions(width=192, height=160, n_frames=30, speed_um_per_frame=12.0,
                                     radius_um=150.0, contact_loss=False, stick_slip=False))


class _Camera:
    def __init__(self, scene):
        self.width, self.height = scene.size
        self.pixel_size_um = scene.options.pixel_size_um


def _stream(scene, frames, times):
    """The frames `frames` given at `times`, each with the robot at its true time."""
    true = np.asarray(scene.timestamps, dtype=np.float64)
    robot = np.stack([np.interp(true, scene.robot_timestamps, scene.robot_xy_um[:, j])
                      for j in range(2)], axis=1)
    mosaicker = RobotPriorMosaicker(_Camera(scene))
    return {k: mosaicker.add_frame(scene.render(k), times[k], robot[k]) for k in frames}


def test_a_frame_after_a_dropped_one_is_no_speed_outlier(scene):
    """Frames 20, 24 and 25 not given (a live stream busy): the registration of frames 21 and 26
    spans 2 (3) frame intervals, which the timestamps say; c_speed was ~0.5 (~0.2)."""
    times = np.asarray(scene.timestamps, dtype=np.float64)
    kept = [k for k in range(scene.n_frames) if k not in (20, 24, 25)]
    results = _stream(scene, kept, times)
    for k in (21, 26):
        assert results[k].status == "placed"
        assert results[k].c_speed > 0.9, (k, results[k].c_speed)
    # timing jitter (+-20 % of a frame interval) changes nothing: whole intervals
    rng = np.random.default_rng(0)
    jittered = times + rng.uniform(-0.2, 0.2, times.size) / scene.options.fps
    again = _stream(scene, kept, jittered)
    for k in kept:
        np.testing.assert_array_equal(again[k].position, results[k].position)
        assert again[k].c_speed == results[k].c_speed or np.isnan(results[k].c_speed)


# -- the live OpenIGTLink source ---------------------------------------------------------------


@pytest.mark.realtime
def test_igtl_live_position_of_a_robot_sampled_in_pairs():
    """IgtlSource.position_at's default sample age: 3x the typical spacing (19 ms for pairs
    1 ms apart every 20 ms), not 3x the 1 ms median; a real dropout still gives none."""
    from _igtl_sender import T0, Sender, transform_message

    from fusedmosaic.io.igtl import IgtlSource

    ts = _paired(np.r_[np.arange(0.0, 0.6, 0.02), np.arange(0.8, 1.2, 0.02)])
    events = []
    for t in ts:
        M = np.eye(4)
        M[:3, 3] = [t, -t, 0.0]
        events.append((float(t), transform_message(M, float(t), "RobotToBase")))
    sender = Sender(events, speed=100.0, delay=0.0)
    with IgtlSource(f":{sender.port}", transform_device="RobotToBase") as source:
        sender.join()
        while source.next_frame(2.0) is not None:  # no frame sent: ends when the stream closes
            pass
        position, age = source.position_at(T0 + 0.315, wait_s=0.0)  # 14 ms after a pair
        np.testing.assert_allclose(position, [0.315, -0.315, 0.0], atol=1e-6)
        assert age == pytest.approx(0.014, abs=1e-6)  # (before: None, older than 3 ms)
        position, age = source.position_at(T0 + 1.2, wait_s=0.0)  # after the last: extrapolated
        # (1 ms pairs extrapolated 19 ms: the stamps' 0.24 µs resolution at 1.7e9 s, x19)
        np.testing.assert_allclose(position, [1.2, -1.2, 0.0], atol=1e-4)
        position, age = source.position_at(T0 + 0.7, wait_s=0.0)  # in the dropout: none
        assert position is None and age == pytest.approx(0.119, abs=1e-6)
