"""Live replay (estimation/live.py, `fusedmosaic run --live`): frames at their timestamps, the
newest tracker / robot sample, frames dropped while the mosaicker is busy."""

from __future__ import annotations

import json
import re
import time
import warnings
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusedmosaic.cli import main
from fusedmosaic.estimation.live import _schedule, newest_sample_index, replay_live
from fusedmosaic.estimation.sequential import SequentialOptions, run_lba_emt
from fusedmosaic.estimation.translation import RobotPriorOptions
from fusedmosaic.evaluation import frame_errors, mosaic_error
from fusedmosaic.io import read_dataset, read_poses_csv
from fusedmosaic.registration.features import FeatureOptions
from fusedmosaic.registration.pairs import MatchOptions
from fusedmosaic.runner import run_dataset
from fusedmosaic.simulation import FetoscopyOptions, PcleOptions, simulate_fetoscopy, simulate_pcle

# run --live and live sessions measure their processing time: run alone (make test)
pytestmark = pytest.mark.realtime

PCLE = PcleOptions(width=192, height=160, n_frames=14, speed_um_per_frame=12.0, radius_um=150.0,
                   contact_loss=False, stick_slip=False)


@pytest.fixture(scope="module")
def pcle(tmp_path_factory):
    return simulate_pcle(tmp_path_factory.mktemp("live") / "pcle", PCLE)


@pytest.fixture(scope="module")
def syn(tmp_path_factory):
    options = FetoscopyOptions(n_frames=40, laps=40 / 37.5, width=200, height=200)
    return simulate_fetoscopy(tmp_path_factory.mktemp("live") / "syn", options)


def _e_M(ds, result):
    return mosaic_error(frame_errors(result.homographies, ds.ground_truth, ds.camera.width,
                                     ds.camera.height))


def test_newest_sample_index():
    times = np.array([0.0, 0.25, 0.5, 0.75])
    assert newest_sample_index(times, 0.4, 0.5) == 1  # the newest at or before, not the nearest
    assert newest_sample_index(times, 0.5, 0.5) == 2  # a sample at the frame time counts
    assert newest_sample_index(times, -0.01, 0.5) is None  # no sample yet
    assert newest_sample_index(times, 1.25, 0.5) == 3  # exactly max_age old: still used
    assert newest_sample_index(times, 1.25 + 2**-20, 0.5) is None  # older: none


def _one_slot_queue(arrival, duration):
    """Reference: an event-by-event one-slot capture queue. A frame arriving while the
    mosaicker is busy replaces the waiting one (dropped); a frame arriving exactly when the
    processing ends counts as already there. Returns [(dropped, busy)], {frame: latency}."""
    dropped, latency = [], {}
    free_at, current, waiting = -np.inf, None, None
    for k, a in enumerate(arrival):
        while waiting is not None and free_at < a:  # the processor took the waiting frame
            current, free_at = waiting, free_at + duration[waiting]
            latency[current], waiting = free_at - arrival[current], None
        if waiting is None and free_at <= a:  # idle: frame k at once
            current, free_at = k, a + duration[k]
            latency[k] = duration[k]
        else:
            if waiting is not None:
                dropped.append((waiting, current))
            waiting = k
    if waiting is not None:
        latency[waiting] = free_at + duration[waiting] - arrival[waiting]
    return dropped, latency


def test_schedule_matches_an_event_simulation_of_the_queue():
    rng = np.random.default_rng(4)
    for _ in range(300):
        n = int(rng.integers(1, 12))
        # dyadic times (multiples of 1/8): exact ties between arrivals and ends happen
        arrival = np.cumsum(np.concatenate([[0], rng.integers(1, 4, n - 1)])) / 8.0
        duration = rng.integers(0, 24, n) / 8.0
        expected = _one_slot_queue(arrival, duration)
        got = _schedule(arrival, lambda k, d=duration: float(d[k]))
        assert got[0] == expected[0]
        assert got[1] == pytest.approx(expected[1])


def test_slow_mosaicker_drops_runs_of_frames(pcle):
    """Each call 3.4 intervals T: frame 0 ends at 3.4 T, frames 1-3 arrived, 3 is taken and
    ends at 6.8 T (4-6 arrived: 6 taken), then 10.2 T (7-10: 10 taken), 13.6 T (13 taken)."""
    ds = read_dataset(pcle)
    interval = float(np.median(np.diff(ds.timestamps)))
    live = replay_live(ds, "kalman-robot", progress=False,
                       processing_time=lambda k: 3.4 * interval).details["live"]
    assert live["dropped"] == [1, 2, 4, 5, 7, 8, 9, 11, 12]


def test_busy_mosaicker_drops_all_but_the_newest_frame(pcle):
    """Frames every interval T, each call taking 1.9 T. Frame 0 ends at 1.9 T; frame 1 (arrived
    at T) is processed until 3.8 T; meanwhile frames 2 and 3 arrived: 2 is dropped, 3 processed
    until 5.7 T; and so on: the even frames from 2 on are dropped. Frame 1 waited 0.9 T, the
    longest wait (each later one is 0.1 T shorter)."""
    ds = read_dataset(pcle)
    interval = float(np.median(np.diff(ds.timestamps)))
    res = replay_live(ds, "kalman-robot", progress=False,
                      processing_time=lambda k: 1.9 * interval)
    live = res.details["live"]
    n = len(ds)
    assert n == 14
    assert live["dropped"] == list(range(2, n, 2))
    assert live["frames_processed"] == n - len(range(2, n, 2))
    for k in range(2, n, 2):
        assert res.status[k] == (f"unplaced: dropped (live replay: arrived while frame {k - 1} "
                                 "was being processed)")
        assert not np.isfinite(res.homographies[k]).any()
    assert all(np.isfinite(res.homographies[k]).all() for k in [0, *range(1, n, 2)])
    assert live["latency_ms"]["max"] == pytest.approx((0.9 + 1.9) * interval * 1e3)
    assert live["processing_ms"]["median"] == pytest.approx(1.9 * interval * 1e3)
    assert live["processing_time"] == "given"


def test_fast_mosaicker_drops_nothing_and_matches_the_truth(pcle):
    ds = read_dataset(pcle)
    res = replay_live(ds, "kalman-robot", progress=False, processing_time=lambda k: 0.0)
    assert res.details["live"]["frames_dropped"] == 0
    assert res.details["live"]["latency_ms"]["max"] == 0.0
    err = np.linalg.norm(res.homographies[:, :2, 2] - ds.ground_truth[:, :2, 2], axis=1)
    assert err.max() < 3.0  # px; clean frames, robot at the frame times


def test_lba_emt_replay_with_the_newest_tracker_sample(syn):
    """No drops: every frame placed, about as accurate as the offline run (the newest tracker
    sample is up to 25 ms old instead of interpolated; measured 1.16 vs 1.06 px)."""
    ds = read_dataset(syn)
    options = SequentialOptions(bootstrap_frames=10,
                                features=FeatureOptions(detector="orb"))
    res = replay_live(ds, "lba-emt", options=options, progress=False,
                      processing_time=lambda k: 0.0)
    offline = run_lba_emt(ds, progress=False, options=options)
    assert res.details["live"]["frames_dropped"] == 0
    assert res.status == ["placed"] * len(ds)
    e_live, e_offline = _e_M(ds, res), _e_M(ds, offline)
    assert e_live < 2.0  # px, 200x200 frames, 10-frame start-up
    assert e_live < 1.5 * e_offline + 0.1
    assert res.poses.shape == (len(ds), 6) and np.isfinite(res.poses).all()
    assert res.parameters["live"] is True
    assert res.details["live"]["frames_without_sample"] == []
    # camera centres against the truth (mm): through the hand-eye transform as offline
    # (measured median 0.75 mm; without the hand-eye ~4.6 mm)
    _, truth = read_poses_csv(ds.root / "truth_poses.csv")

    def centres(p):
        R = Rotation.from_rotvec(p[:, :3]).as_matrix()
        return -np.einsum("nji,nj->ni", R, p[:, 3:])

    assert np.median(np.linalg.norm(centres(res.poses) - centres(truth), axis=1)) < 1.5


def test_lba_emt_replay_with_drops_places_the_processed_frames(syn, tmp_path):
    """Frames processed in 1.5 frame intervals: about a third dropped, the kept ones placed by
    their pairs and the motion prior across the gaps. Tolerance: a tenth of the tracker alone's
    e_M (emt, the same frames): 1.51 px against 18.4 (the same replay without drops: 0.44; the
    bound was a fixed 1.5 px, crossed by the simulator's rounded frames, session 47)."""
    ds = read_dataset(syn)
    options = SequentialOptions(bootstrap_frames=10, features=FeatureOptions(detector="orb"))
    interval = float(np.median(np.diff(ds.timestamps)))
    res = replay_live(ds, "lba-emt", options=options, progress=False,
                      processing_time=lambda k: 1.5 * interval)
    dropped = res.details["live"]["dropped"]
    assert 0 < len(dropped) < len(ds)
    kept = [k for k in range(len(ds)) if k not in dropped]
    assert all(res.status[k] == "placed" for k in kept)
    e = frame_errors(res.homographies, ds.ground_truth, ds.camera.width, ds.camera.height)
    assert np.all(np.isnan(e[dropped]))
    run_dataset(syn, "emt", tmp_path / "emt", progress=False, report=False)
    emt = json.loads((tmp_path / "emt" / "report.json").read_text())["metrics"]["e_M_px"]
    assert np.nanmean(e[kept]) < emt / 10, (np.nanmean(e[kept]), emt)


def test_live_refuses_methods_without_a_streaming_form(pcle):
    ds = read_dataset(pcle)
    with pytest.raises(ValueError, match=r"live replay: method 'ba-emt' has no streaming form; "
                                         r"use one of lba-emt, kalman-robot"):
        replay_live(ds, "ba-emt", progress=False)
    with pytest.raises(ValueError, match=r"max_sample_age_s must be a finite number >= 0"):
        replay_live(ds, "kalman-robot", progress=False, max_sample_age_s=float("nan"))
    with pytest.raises(ValueError, match=r"processing_time\(0\) must be a finite number >= 0, "
                                         r"got nan"):
        replay_live(ds, "kalman-robot", progress=False, processing_time=lambda k: float("nan"))
    with pytest.raises(ValueError, match=r"flat_field needs the fibre pattern of the whole "
                                         r"recording"):
        replay_live(ds, "kalman-robot", progress=False,
                    options=replace(RobotPriorOptions(), flat_field=True))


def test_cli_run_live(pcle, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run", str(pcle), "--method", "kalman-robot", "--live", "--out", str(out),
                 "--no-report"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["live"]["frames_processed"] + report["live"]["frames_dropped"] == len(
        report["frame_status"])
    assert report["parameters"]["live"] is True
    assert "frame(s) dropped; latency median" in capsys.readouterr().out
    assert main(["run", str(pcle), "--method", "ba", "--live", "--out",
                 str(tmp_path / "x")]) != 0
    assert ("live replay: method 'ba' has no streaming form; use one of lba-emt, kalman-robot, "
            "ncc, robot") in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_stale_samples_are_not_used_and_reported(pcle):
    """A sample older than max_sample_age_s is no sample: with 0 s only frames taken exactly at
    a robot sample get one; the others are listed and still handled (image only)."""
    ds = read_dataset(pcle)
    res = replay_live(ds, "kalman-robot", progress=False, max_sample_age_s=0.0,
                      processing_time=lambda k: 0.0)
    robot_times = set(ds.robot.timestamps.tolist())
    expected = [int(ds.frame_ids[k]) for k in range(len(ds))
                if float(ds.timestamps[k]) not in robot_times]
    assert expected  # the robot is not sampled at every frame time
    assert res.details["live"]["frames_without_sample"] == expected
    default = replay_live(ds, "kalman-robot", progress=False, processing_time=lambda k: 0.0)
    assert default.details["live"]["frames_without_sample"] == []
    assert default.parameters["robot_file"] == "robot.csv"


def test_cli_run_live_on_one_frame(tmp_path, capsys):
    data = simulate_pcle(tmp_path / "one", replace(PCLE, n_frames=1))
    assert main(["run", str(data), "--method", "kalman-robot", "--live", "--out",
                 str(tmp_path / "out"), "--no-report"]) == 0
    assert "(frame interval n/a)" in capsys.readouterr().out


def test_extrapolated_robot_follows_the_motion_between_samples():
    from fusedmosaic.estimation.live import extrapolated_robot
    from fusedmosaic.io import RobotSamples

    robot = RobotSamples(np.array([0.0, 0.1, 0.2, 1.0]),
                         np.array([[0.0, 0.0], [4.0, 2.0], [8.0, 4.0], [9.0, 9.0]]))
    np.testing.assert_allclose(extrapolated_robot(robot, 2, 0.25, 0.3), [10.0, 5.0])
    np.testing.assert_allclose(extrapolated_robot(robot, 0, 0.05, 0.3), [0.0, 0.0])  # one sample
    # samples further apart than max_age: a dropout between them, the newest is held
    np.testing.assert_allclose(extrapolated_robot(robot, 3, 1.05, 0.3), [9.0, 9.0])


def test_accurate_robot_live_as_accurate_as_offline(pcle):
    """The newest robot sample is ~14 ms old at each frame (the simulator's robot clock phase);
    held, an accurate robot's lag is followed by the filter (measured on the spiral: 27.0 px
    live vs 10.5 offline); extrapolated along the last two samples it is not."""
    from fusedmosaic.estimation.translation import run_kalman_robot

    ds = read_dataset(pcle)
    live = replay_live(ds, "kalman-robot", progress=False, processing_time=lambda k: 0.0)
    offline = run_kalman_robot(ds, progress=False)
    assert live.details["live"]["sample_age_ms"]["max"] > 5.0  # the case this is about
    assert _e_M(ds, live) <= 1.2 * _e_M(ds, offline) + 0.2


def test_ncc_and_robot_replayed_live_as_offline(pcle, tmp_path):
    """The pCLE baselines have streaming forms too: ncc (images only) places every frame as the
    offline run does (it takes no samples: nothing differs live); robot follows the newest
    sample extrapolated to the frame time, as accurate as the offline interpolation."""
    import shutil

    from fusedmosaic.estimation.translation import run_ncc, run_robot

    ds = read_dataset(pcle)
    live = replay_live(ds, "ncc", progress=False, processing_time=lambda k: 0.0)
    np.testing.assert_array_equal(live.homographies, run_ncc(ds, progress=False).homographies)
    assert live.parameters["estimate"] == "image" and live.parameters["robot_file"] is None
    assert live.details["live"]["frames_without_sample"] == []
    assert live.details["ncc_inconsistent"] == [] and live.details["warnings"] == []
    live = replay_live(ds, "robot", progress=False, processing_time=lambda k: 0.0)
    assert live.parameters["estimate"] == "robot"
    assert set(live.status[1:]) == {"prior-only"}  # (as offline: no image evidence)
    # against the truth: measured 0.020 px live (extrapolated), 0.004 offline (interpolated)
    assert _e_M(ds, live) <= 1.2 * _e_M(ds, run_robot(ds, progress=False)) + 0.2
    # ncc needs no robot file, robot names it
    bare = tmp_path / "bare"
    shutil.copytree(pcle, bare)
    (bare / "robot.csv").unlink()
    assert main(["--quiet", "run", str(bare), "--method", "ncc", "--live", "--out",
                 str(tmp_path / "out"), "--no-report"]) == 0
    with pytest.raises(ValueError, match=r"robot\.csv"):
        replay_live(read_dataset(bare), "robot", progress=False)


@pytest.fixture(scope="module")
def late(syn, tmp_path_factory):
    """The SYN dataset with the tracker switched on 0.4 s after the first frame."""
    import shutil

    root = tmp_path_factory.mktemp("live") / "late"
    shutil.copytree(syn, root)
    lines = (root / "tracking.csv").read_text().splitlines()
    kept = [line for line in lines[1:] if float(line.split(",")[0]) >= 0.4]
    (root / "tracking.csv").write_text("\n".join([lines[0], *kept]) + "\n")
    return root


def test_live_and_evaluate_with_a_tracker_that_starts_late(late, tmp_path, capsys):
    """--live uses the samples as they come (no time-span check; frames before the first
    sample are listed); evaluate scores runs of such datasets (it needs only the truth)."""
    out = tmp_path / "live"
    assert main(["--quiet", "run", str(late), "--method", "lba-emt", "--live", "--out",
                 str(out), "--no-report", "--detector", "orb"]) == 0
    live = json.loads((out / "report.json").read_text())["live"]
    ds = read_dataset(late, allow_untracked=True)
    first = ds.tracking.timestamps.min()
    before = [int(ds.frame_ids[k]) for k in range(len(ds)) if ds.timestamps[k] < first]
    # the processed ones (a loaded machine drops frames while busy; frame 0 is never dropped)
    processed = [k for k in before if k not in live["dropped"]]
    assert processed[0] == 0 and live["frames_without_sample"] == processed
    offline = tmp_path / "offline"
    assert main(["--quiet", "run", str(late), "--method", "lba-emt", "--allow-untracked",
                 "--out", str(offline), "--no-report", "--detector", "orb"]) == 0
    assert main(["evaluate", str(offline), "--truth", str(late), "--compare", str(out)]) == 0
    table = (offline / "evaluation.md").read_text()
    assert "lba-emt (live)" in table


class _Source:
    """A live source for live_session without a socket: the frames of `ds` handed over one
    per next_frame, `interval_s` apart; a tracker (robot) device that sends `valid` samples
    (position_at / pose_at give none) while `heard` devices are ignored."""

    def __init__(self, ds, *, interval_s: float = 0.0, valid: int = 0, heard=()) -> None:
        self.ds, self.interval_s = ds, interval_s
        self.transform_device = "RobotToBase"
        self.valid_samples, self.invalid_samples = valid, {}
        self.ignored_devices = set(heard)
        self.received = 0

    def next_frame(self, timeout_s: float):
        from fusedmosaic.io.igtl import LiveFrame

        if self.received == len(self.ds):
            return None
        time.sleep(self.interval_s)
        k = self.received
        self.received += 1
        return LiveFrame(self.ds.frames[k], float(self.ds.timestamps[k]), time.perf_counter(), k)

    def position_at(self, t, *, max_age_s=None):
        return None, None


def _session(ds, source, **kwargs):
    from fusedmosaic.estimation.live import live_session

    return live_session(source, ds.camera, method="kalman-robot", **kwargs)


def test_a_session_without_valid_samples_warns_once_while_it_runs(pcle, monkeypatch):
    """Frames for NO_SAMPLE_WARNING_S and no valid sample of the device while others are heard
    (a misnamed --transform): one warning during the session, naming them (it was said only
    in the final error, or for kalman-robot not at all)."""
    from fusedmosaic.estimation import live

    ds = read_dataset(pcle)
    monkeypatch.setattr(live, "NO_SAMPLE_WARNING_S", 0.1)
    source = _Source(ds, interval_s=0.02, heard=["TRANSFORM ProbeToBase", "IMAGE Other"])
    with pytest.warns(UserWarning) as said:
        session = _session(ds, source)
    assert len(session.processed) == len(ds)
    assert len(said) == 1 and re.fullmatch(
        r"live session: no valid robot sample \(TRANSFORM or POSITION\) of RobotToBase in the "
        r"[0-9.]+ s since the first frame \(other devices heard: IMAGE Other, TRANSFORM "
        r"ProbeToBase\): the frames get no robot sample; check --transform", str(said[0].message))


def test_a_short_session_without_valid_samples_warns_at_its_end(pcle):
    from fusedmosaic.estimation import live

    ds = read_dataset(pcle)
    assert live.NO_SAMPLE_WARNING_S > 1.0  # longer than this session
    with pytest.warns(UserWarning, match=r"^live session: no valid robot sample \(TRANSFORM or "
                      r"POSITION\) of RobotToBase in the whole session \(no other device heard "
                      r"either\): the frames get no robot sample; check --transform$"):
        _session(ds, _Source(ds))
    invalid = _Source(ds)
    invalid.invalid_samples = {"status MISSING": 3}
    with pytest.warns(UserWarning, match=r"\(its samples are all invalid: 3 x status MISSING\)"):
        _session(ds, invalid)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # valid samples: no warning
        _session(ds, _Source(ds, valid=5))


def test_max_frames_ends_the_session_at_that_frame(pcle):
    """The session stops once the frame numbered max_frames - 1 is processed (run_igtl records
    no frame after it), and says so."""
    ds = read_dataset(pcle)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (no samples)
        session = _session(ds, _Source(ds), max_frames=5)
    assert session.processed == [0, 1, 2, 3, 4]
    assert session.stopped_by == "5 frames recorded (--max-frames)"


def _blank_start(pcle, tmp_path):
    """A copy of `pcle` whose frame 0 is black and whose robot.csv starts after frame 0."""
    import shutil

    import cv2

    root = shutil.copytree(pcle, tmp_path / "blank0")
    first = sorted((root / "frames").iterdir())[0]
    cv2.imwrite(str(first), np.zeros_like(cv2.imread(str(first), cv2.IMREAD_UNCHANGED)))
    t0 = read_dataset(pcle).timestamps[0]
    lines = (root / "robot.csv").read_text().splitlines()
    kept = [line for line in lines[1:] if float(line.split(",")[0]) > t0 + 0.05]
    (root / "robot.csv").write_text("\n".join([lines[0], *kept]) + "\n")
    return root


def test_a_streamed_chain_without_frame0_warns_as_the_offline_run(pcle, tmp_path):
    """Frame 0 black and no robot sample at it: kalman-robot starts its chain at frame 1, put at
    frame 0's position. The offline run warned so; run --live placed the frames alike but said
    nothing (report.json warnings [] against the offline run's one; sim60: e_M 44.94 offline,
    44.95 px live). Now the same warning. Tolerance: placements within 1 px of the offline
    run's (the live robot position is extrapolated, not interpolated: sim60 0.17 px)."""
    data = _blank_start(pcle, tmp_path)
    reports, positions = {}, {}
    for name, live in (("offline", []), ("live", ["--live"])):
        out = tmp_path / name
        assert main(["run", str(data), "--method", "kalman-robot", *live, "--allow-untracked",
                     "--quiet", "--no-report", "--out", str(out)]) == 0
        reports[name] = json.loads((out / "report.json").read_text())
        H = np.loadtxt(out / "homographies.csv", delimiter=",", skiprows=1)[:, 1:]
        positions[name] = H.reshape(-1, 3, 3)[:, :2, 2]
    expected = ("frame 0 is blank (a constant image) and robot.csv has no sample at frame 0: "
                "the fused chain starts at frame 1, put at frame 0's position")
    assert [w for w in reports["offline"]["warnings"] if expected in w], reports["offline"]
    # the same warnings, the frames without a robot sample for their own reason (the replay
    # takes the newest sample up to max_sample_age_s old, offline interpolates)
    assert reports["live"]["warnings"][0] == reports["offline"]["warnings"][0]
    for report in reports.values():
        assert report["frames_without_robot_sample"] == [0]
        assert report["warnings"][1].startswith("1 of 14 frames have no robot sample in "
                                                "robot.csv ("), report["warnings"]
    assert len(reports["live"]["warnings"]) == len(reports["offline"]["warnings"]) == 2
    assert reports["live"]["reference_frame"] == reports["offline"]["reference_frame"] == 0
    np.testing.assert_allclose(positions["live"], positions["offline"], atol=1.0)


def test_a_session_without_frame0_warns_as_the_offline_run(pcle, tmp_path):
    """The same in a live session (`fusedmosaic live`): frame 0 black, the robot stream without
    a sample: the chain starts at frame 1, and the session's result says so."""
    from fusedmosaic.estimation.live import session_result

    ds = read_dataset(_blank_start(pcle, tmp_path), allow_untracked=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (no robot samples)
        session = _session(ds, _Source(ds))
    result = session_result(session, list(ds.timestamps), [], source_details={},
                            method="kalman-robot")
    assert result.details["warnings"] == [
        "frame 0 is blank (a constant image) and the robot stream has no sample at frame 0: the "
        "fused chain starts at frame 1, put at frame 0's position, so every frame is offset by "
        "the (unknown) motion between frames 0 and 1; the mosaic itself is consistent",
        "14 of 14 frames have no robot sample in the robot stream (none at the frame or recent "
        "enough before it; frames 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, ... (4 more)): kalman-robot "
        "placed them by the NCC registrations alone, whose drift the robot does not correct "
        "there (report.json frames_without_robot_sample)"]


def test_a_streamed_run_reports_a_plane_the_images_barely_observe(tmp_path):
    """lba-emt replayed live through a 60 px field stop (50 hand-held frames, a frame every
    50 ms of processing, so some dropped): one registered pair, the plane's relative std ~2;
    the offline run warned of it (consistency.MAX_PLANE_RELATIVE_STD) and the streamed one
    did not, its details having no plane_relative_std."""
    from fusedmosaic.estimation.consistency import MAX_PLANE_RELATIVE_STD
    from fusedmosaic.runner import add_streamed_checks

    dataset = read_dataset(simulate_fetoscopy(tmp_path / "d", FetoscopyOptions(
        n_frames=50, width=300, height=300, motion="handheld", fov_mask_radius=60)))
    # few keypoints is the scenario: SIFT's low-contrast retry off (it registers such frames)
    few = SequentialOptions(features=FeatureOptions(sift_min_features=0))
    result = replay_live(dataset, "lba-emt", progress=False, processing_time=lambda k: 0.05,
                         options=few)
    assert result.details["plane_relative_std"] > MAX_PLANE_RELATIVE_STD
    add_streamed_checks(result, dataset, "lba-emt", few)
    registered = result.details["pairs"]["registered"]
    assert any(w.startswith(f"{dataset.root / 'tracking.csv'}: the images barely observe the "
                            f"plane: its relative standard deviation from {registered} "
                            "registered pairs is ") for w in result.details["warnings"])


def test_a_streamed_startup_whose_plane_is_unbounded_is_refused(tmp_path, monkeypatch):
    """Behind a 55 px field stop (60 hand-held frames, seed 1), replayed at 30 ms a frame, the
    start-up's 2 registered pairs leave the plane unbounded: it was taken at the sequence's end
    (pi 6e-5 mm from the world's origin) and the run crashed on a singular homography
    ("camera centre on the plane", nothing written; a helper's fuzzing). It is refused as a
    plane behind the cameras is, saying why. (max_scale_change 6: by default one of the two
    pairs, whose warped frame is 5.1 x the frame's area, is now refused as degenerate.) The
    scenario was found with the pairs' SIFT correspondences counted as matched, copies at one
    location twice; each once (pairs.unique_correspondences), the same 2 pairs bound the plane
    (relative std 0.93, taken at the sequence's end, warned of by the run's checks), and no
    other field stop, seed or length tried (12) leaves it unbounded: the copies are kept here
    to reach the refusal."""
    from fusedmosaic.registration import pairs

    monkeypatch.setattr(pairs, "unique_correspondences", lambda points_l, points_m: (
        points_l, points_m))
    dataset = read_dataset(simulate_fetoscopy(tmp_path / "d", FetoscopyOptions(
        n_frames=60, width=280, height=280, motion="handheld", fov_mask_radius=55, seed=1)))
    with pytest.raises(ValueError, match=r"^the plane the start-up estimated from \d+ registered "
                       r"pairs has a relative standard deviation that the images leave "
                       r"unbounded") as refused:
        replay_live(dataset, "lba-emt", progress=False, processing_time=lambda k: 0.03,
                    options=SequentialOptions(features=FeatureOptions(sift_min_features=0),
                                              matching=MatchOptions(max_scale_change=6.0)))
    assert "disagree" not in str(refused.value)  # (the simulated tracker)


def test_a_streamed_run_reports_a_startup_that_did_not_converge(tmp_path):
    """The solver warnings of the offline run (a start-up stopped at its iteration limit, here
    a scope 5 mm from the plane held to 100 iterations) were missing from streamed runs."""
    dataset = read_dataset(simulate_fetoscopy(tmp_path / "d", FetoscopyOptions(
        n_frames=40, width=300, height=300, motion="handheld", distance_mm=5.0,
        radius_mm=3.0)))
    result = replay_live(dataset, "lba-emt", progress=False, processing_time=lambda k: 0.0,
                         options=SequentialOptions(startup_max_iterations=100))
    assert any(w.startswith("the start-up adjustment stopped at its iteration limit (100)")
               for w in result.details["warnings"]), result.details.get("warnings")


def test_a_frame_dropped_before_the_first_processed_one_says_so():
    """A frame dropped before the session processed any (a newer one had arrived: a loaded
    machine at the start) was 'dropped (live: arrived while frame ? was being processed)'."""
    from fusedmosaic.estimation.live import LiveSession, session_result

    result = session_result(LiveSession(), [0.0, 0.1], [0], source_details={}, method="ncc")
    assert result.status[0] == ("unplaced: dropped (live: a newer frame had arrived when the "
                                "session took one)")


def test_streamed_pcle_statuses_name_the_recorded_anchor(monkeypatch):
    """The mosaicker counts the frames it is given; a live run drops frames, so its 'against
    frame N' named the N-th processed frame, another frame of the recording: named by the
    recorded frame's id now (by its index in a live recording)."""
    from types import SimpleNamespace

    import fusedmosaic.estimation.translation as translation
    from fusedmosaic.estimation.live import _streamed_result

    monkeypatch.setattr(translation, "frame_columns", lambda results, ids: {})  # (not the point)
    finals = {k: SimpleNamespace(index=count, status=status, homography=np.eye(3))
              for k, count, status in (
                  (0, 0, "placed"), (3, 1, "placed"),
                  (7, 2, "unplaced: NCC registration against frame 1 failed (featureless "
                         "template)"))}
    out = _streamed_result("ncc", ["dropped"] * 8, finals, None, {}, 0.0, {})
    assert out.status[7] == ("unplaced: NCC registration against frame 3 failed (featureless "
                             "template)")
    out = _streamed_result("ncc", ["dropped"] * 8, finals, None, {}, 0.0, {},
                           ids=np.arange(8) * 10)
    assert out.status[7].startswith("unplaced: NCC registration against frame 30 failed")
    assert out.status[3] == "placed" and out.status[1] == "dropped"
