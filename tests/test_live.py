"""Live replay (estimation/live.py, `fusedmosaic run --live`): frames at their timestamps, the
newest tracker / robot sample, frames dropped while the mosaicker is busy."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from fusedmosaic.cli import main
from fusedmosaic.estimation.live import newest_sample_index, replay_live
from fusedmosaic.estimation.sequential import SequentialOptions, run_lba_emt
from fusedmosaic.estimation.translation import RobotPriorOptions
from fusedmosaic.evaluation import frame_errors, mosaic_error
from fusedmosaic.io import read_dataset
from fusedmosaic.registration.features import FeatureOptions
from fusedmosaic.simulation import FetoscopyOptions, PcleOptions, simulate_fetoscopy, simulate_pcle

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
    times = np.array([0.0, 0.025, 0.05, 0.075])
    assert newest_sample_index(times, 0.04, 0.1) == 1  # the newest at or before, not the nearest
    assert newest_sample_index(times, 0.05, 0.1) == 2  # a sample at the frame time counts
    assert newest_sample_index(times, -0.01, 0.1) is None  # no sample yet
    assert newest_sample_index(times, 0.2, 0.1) is None  # the newest is 0.125 s old
    assert newest_sample_index(times, 0.17, 0.1) == 3


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


def test_lba_emt_replay_with_drops_places_the_processed_frames(syn):
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
    assert np.nanmean(e[kept]) < 1.5  # px: the motion prior spans the gaps


def test_live_refuses_methods_without_a_streaming_form(pcle):
    ds = read_dataset(pcle)
    with pytest.raises(ValueError, match=r"live replay: method 'ba-emt' has no streaming form; "
                                         r"use one of lba-emt, kalman-robot"):
        replay_live(ds, "ba-emt", progress=False)
    with pytest.raises(ValueError, match=r"max_sample_age_s must be a finite number >= 0"):
        replay_live(ds, "kalman-robot", progress=False, max_sample_age_s=float("nan"))
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
    assert main(["run", str(pcle), "--method", "ncc", "--live", "--out",
                 str(tmp_path / "x")]) != 0
    assert "live replay: method 'ncc' has no streaming form" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
