"""sigma_v "auto" (session 49; `--visual-sigma auto`, not the default): the visual cost's noise
measured on the recording (ba-emt: after
its first solve; lba-emt: at its start-up, which the window then keeps), the C++ window's
set_sigma_v, the plane gate's limit following sigma_v, and the bad values refused."""

import sys
from pathlib import Path

import numpy as np
import pytest

from fusedmosaic import _core
from fusedmosaic.estimation import sequential
from fusedmosaic.estimation.bundle import BundleOptions, run_ba_emt
from fusedmosaic.estimation.consistency import (
    SIGMA_V_FLOOR_PX,
    SIGMA_V_MIN_POINTS,
    TransferResiduals,
    measured_sigma_v,
)
from fusedmosaic.estimation.sequential import SequentialMosaicker, SequentialOptions
from fusedmosaic.evaluation.benchmark import syn_stream
from fusedmosaic.io import read_dataset
from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from _common import WindowRecorder  # noqa: E402
from bench_cpp import load_problem, python_replay  # noqa: E402

K = np.array([[300.0, 0.0, 150.0], [0.0, 300.0, 150.0], [0.0, 0.0, 1.0]])
PLANE = np.array([0.0, 0.0, -1.0 / 30.0])


def _recorded(sigma_v_px: float, n: int = 12) -> dict:
    """A 6-frame start-up and 6 more SYN frames streamed with `sigma_v_px`: what the window
    held (the mirror: frames, pairs, plane), the camera and the tracker poses."""
    scene, camera, poses, _ = syn_stream(n)
    m = SequentialMosaicker(camera, SequentialOptions(bootstrap_frames=6, sigma_v_px=sigma_v_px))
    for k in range(n):
        m.add_frame(scene.render(k), float(scene.timestamps[k]), poses[k])
    m.flush()
    return {"camera": camera, "poses": poses, "frames": m._mirror_frames,
            "pairs": m._mirror_pairs, "plane": m._mirror_plane}


def _replayed_window(rec: dict, options, last: int):
    """A new SlidingWindow (`options`) holding `rec`'s plane, its start-up frames 0-5 fixed,
    frames 6 .. last-1 pending with their tracker samples, and the pairs among those frames."""
    w = _core.SlidingWindow(rec["camera"].camera_matrix, options)
    w.set_plane(rec["plane"])
    for k in range(6):
        w.add_frame(k, rec["frames"][k][0], rec["frames"][k][1], True)
    for k in range(6, last):
        w.add_frame(k, None, rec["poses"][k])
    for (l, m), (pl, pm) in rec["pairs"].items():
        if max(l, m) < last:
            w.add_pair(l, m, pl, pm)
    return w


def _residuals(std_px: float, points: int) -> TransferResiduals:
    """Transfer residuals of `points` points scattered by std_px per axis (identity cameras on
    the plane z = 30: the transfer is the identity)."""
    rng = np.random.default_rng(0)
    acc = TransferResiduals()
    pm = rng.uniform(0, 300, (points, 2))
    acc.add(np.zeros(6), np.zeros(6), PLANE, pm + rng.normal(0, std_px, pm.shape), pm, K)
    return acc


def test_measured_sigma_v_needs_enough_points_and_has_a_floor():
    sigma, report = measured_sigma_v(_residuals(0.3, 2000))
    assert sigma == report["sigma_v_px"] == report["measured_px"] == pytest.approx(0.3, rel=0.1)
    assert "note" not in report and report["points"] == 2000
    few = SIGMA_V_MIN_POINTS - 1
    sigma, report = measured_sigma_v(_residuals(0.3, few), start_px=1.0)
    assert sigma == 1.0 and report["measured_px"] == pytest.approx(0.3, rel=0.2)
    assert report["note"] == (f"{few} registered points (< {SIGMA_V_MIN_POINTS}): too few to "
                              "measure the keypoints' noise; the paper's 1 px kept")
    sigma, report = measured_sigma_v(_residuals(0.01, 2000))
    assert sigma == SIGMA_V_FLOOR_PX and report["measured_px"] < SIGMA_V_FLOOR_PX
    assert "below the 0.05 px floor" in report["note"]
    sigma, report = measured_sigma_v(TransferResiduals())
    assert sigma == 1.0 and report["measured_px"] is None and report["points"] == 0


@pytest.mark.parametrize("value", [0.0, -1.0, float("nan"), float("inf")])
def test_window_set_sigma_v_refuses_bad_values(value):
    w = _core.SlidingWindow(K, _core.SlidingWindowOptions())
    with pytest.raises(ValueError, match=r"sigma_v_px: must be finite and > 0, got"):
        w.set_sigma_v(value)
    assert w.sigma_v_px == 1.0


def test_window_set_sigma_v_solves_as_a_window_built_with_it():
    """set_sigma_v before the steps gives the window a window built with that sigma_v gives
    (the C_v blocks are made at each step from the costs), and differs from 1 px's."""
    n = 12
    rec = _recorded(0.2, n)

    def window(built_px, set_px):
        costs = _core.BundleAdjusterOptions(sigma_v_px=built_px)
        w = _replayed_window(rec, _core.SlidingWindowOptions(window_size=5, num_new=3,
                                                             costs=costs), n)
        if set_px is not None:
            w.set_sigma_v(set_px)
        w.step([])
        return np.array([w.pose(k) for k in range(6, n)]), w.sigma_v_px

    built, built_sigma = window(0.2, None)
    set_, set_sigma = window(1.0, 0.2)
    paper, _ = window(1.0, None)
    assert built_sigma == set_sigma == 0.2
    np.testing.assert_array_equal(set_, built)
    assert np.abs(paper - built).max() > 1e-6


@pytest.mark.parametrize("value", ["measured", 0.0, float("nan"), True])
def test_bad_sigma_v_option_refused(value):
    _, camera, _, _ = syn_stream(2)
    with pytest.raises(ValueError, match=r"SequentialOptions\.sigma_v_px must be 'auto' "
                                         r"\(measured on the recording\) or a standard "
                                         r"deviation > 0 in pixels, got"):
        SequentialMosaicker(camera, SequentialOptions(sigma_v_px=value))


def test_bad_sigma_v_bundle_option_refused(tmp_path):
    data = read_dataset(simulate_fetoscopy(tmp_path / "d", FetoscopyOptions(
        n_frames=4, width=120, height=120)))
    with pytest.raises(ValueError, match=r"BundleOptions\.sigma_v_px must be 'auto'"):
        run_ba_emt(data, progress=False, options=BundleOptions(sigma_v_px="1 px"))


def test_a_failed_startup_call_restores_the_paper_sigma_v(monkeypatch):
    """A start-up interrupted after it measured sigma_v (here: its frames' finalisation
    raises): the mosaicker is back at 1 px, its window too, and the same frames fed again
    give what an uninterrupted run gives."""
    n = 16
    scene, camera, poses, _ = syn_stream(n)
    options = SequentialOptions(bootstrap_frames=8, sigma_v_px="auto")

    def feed(m, frames, out):
        for k in frames:
            m.add_frame(scene.render(k), float(scene.timestamps[k]), poses[k])
            out.update({r.frame_id: r.homography for r in m.finalized()})
        return out

    plain_G = feed(plain := SequentialMosaicker(camera, options), range(n), {})
    plain_G.update({r.frame_id: r.homography for r in plain.flush()})
    assert plain.visual_sigma["mode"] == "auto" and plain.sigma_v_px < 0.2

    m = SequentialMosaicker(camera, options)
    G = feed(m, range(7), {})
    real = SequentialMosaicker._finalize
    calls = []

    def failing(self, *args, **kwargs):
        calls.append(self.sigma_v_px)
        raise KeyboardInterrupt

    monkeypatch.setattr(SequentialMosaicker, "_finalize", failing)
    with pytest.raises(KeyboardInterrupt):
        feed(m, [7], G)
    assert calls and calls[0] < 0.2  # (measured before the failure)
    assert m.sigma_v_px == 1.0 and m.window.sigma_v_px == 1.0
    assert m.visual_sigma == {"mode": "auto", "sigma_v_px": 1.0}
    monkeypatch.setattr(SequentialMosaicker, "_finalize", real)
    feed(m, range(7, n), G)
    G.update({r.frame_id: r.homography for r in m.flush()})
    assert m.sigma_v_px == plain.sigma_v_px and m.window.sigma_v_px == plain.sigma_v_px
    for k in range(n):
        np.testing.assert_allclose(G[k], plain_G[k], rtol=0, atol=1e-9)


def test_an_unconverged_startup_keeps_the_paper_sigma_v(tmp_path):
    """Residuals of an adjustment stopped short are its distance to the minimum, not the
    keypoints' noise: nothing is measured, and the iteration warning stands."""
    data = read_dataset(simulate_fetoscopy(tmp_path / "d", FetoscopyOptions(
        n_frames=40, width=300, height=300, motion="handheld", distance_mm=5.0,
        radius_mm=3.0)))
    r = sequential.run_lba_emt(data, progress=False,
                               options=SequentialOptions(startup_max_iterations=100,
                                                         sigma_v_px="auto"))
    assert r.details["visual_sigma"]["sigma_v_px"] == 1.0
    assert r.details["visual_sigma"]["note"] == (
        "the start-up adjustment ended NO_CONVERGENCE: the keypoints' noise not measured; the "
        "paper's 1 px kept")
    assert any(w.startswith("the start-up adjustment stopped at its iteration limit")
               for w in r.details["warnings"])
    b = run_ba_emt(data, progress=False, options=BundleOptions(
        max_iterations=2, trust_region="dogleg", sigma_v_px="auto"))
    assert b.details["visual_sigma"]["sigma_v_px"] == 1.0
    assert "ended NO_CONVERGENCE" in b.details["visual_sigma"]["note"]
    assert "sigma_v_from" not in b.details["solver"]


def test_the_window_log_replays_with_the_measured_sigma_v(tmp_path):
    """bench/_common.WindowRecorder logs set_sigma_v, and the replay (bench_cpp, as
    solver_bench.cc) solves the recorded steps to the recorded poses."""
    n = 20
    scene, camera, poses, _ = syn_stream(n)
    options = SequentialOptions(bootstrap_frames=8, sigma_v_px="auto")
    m = SequentialMosaicker(camera, options)
    log = tmp_path / "window.txt"
    wopts = _core.SlidingWindowOptions(window_size=options.window_size, num_new=options.num_new,
                                       costs=m._costs)
    m.window = WindowRecorder(m.window, m.K, m._costs, wopts, log)
    for k in range(n):
        m.add_frame(scene.render(k), float(scene.timestamps[k]), poses[k])
        m.finalized()
    m.flush()
    m.window.close()
    lines = log.read_text().splitlines()
    assert [x for x in lines if x.startswith("set_sigma_v")] == [
        f"set_sigma_v {m.sigma_v_px!r}"]
    assert m.sigma_v_px < 0.2
    replay = python_replay(load_problem(log), 1)
    assert replay["step_wall_ms"] and replay["max_abs_diff_vs_recorded"] < 1e-9


def test_the_plane_gate_limit_follows_sigma_v():
    """The gate's limit (plane_max_relative_std) is stated for sigma_v 1 px; a step compares
    the plane's relative std with it x sigma_v (pi is observed through C_v alone). At sigma_v
    0.1: held with a limit of 5 std (0.5 std after the factor), not with 15 std (1.5 std).
    Before, the limit was compared as given: 5 std did not hold it."""
    rec = _recorded(1.0)

    def step(limit, sigma_v=0.1):
        o = _core.SlidingWindowOptions(window_size=5, num_new=3,
                                       costs=_core.BundleAdjusterOptions(sigma_v_px=sigma_v))
        o.plane_max_relative_std = limit
        return _replayed_window(rec, o, 9).step([])

    first = step(1e6)  # (a limit nothing reaches: the std alone)
    std = first.plane_relative_std
    assert 0 < std < 1.0 and not first.plane_held
    assert not step(15 * std).plane_held
    held = step(5 * std)
    assert held.plane_held and held.plane_relative_std == pytest.approx(std, rel=1e-6)
    # (the std scales with sigma_v: 10 x at 1 px, the figure the limit was measured on)
    assert step(1e6, sigma_v=1.0).plane_relative_std == pytest.approx(10 * std, rel=0.05)
