"""report.json visual_agreement: the registered points' transfer residuals at the estimate, whose
robust standard deviation measures the keypoints' noise (sigma_v, --visual-sigma). Session 47
left it unmeasured: the paper's 1 px was given with calibrate's tracker noise, or 0.1 px from
the simulator. Compared here with the same residuals at the simulator's true homographies."""

import copy
import json

import cv2
import numpy as np
import pytest

from fusedmosaic.cli import main
from fusedmosaic.estimation import bundle
from fusedmosaic.estimation.consistency import TransferResiduals, visual_agreement
from fusedmosaic.estimation.sequential import SequentialOptions, run_lba_emt
from fusedmosaic.io import read_dataset
from fusedmosaic.io.calibration import read_camera_yaml, write_camera_yaml
from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

LENS = [-0.30, 0.10, 0.0008, -0.0005]  # bench_lens.py's barrel lens


@pytest.fixture(scope="module")
def syn(tmp_path_factory):
    root = tmp_path_factory.mktemp("va") / "syn"
    simulate_fetoscopy(root, FetoscopyOptions(n_frames=24, seed=3, laps=0.3))
    return root


def _robust_std(r: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(r)))


def test_unit_gaussian_residuals():
    rng = np.random.default_rng(0)
    K = np.array([[400.0, 0, 200], [0, 400, 200], [0, 0, 1]])
    pose, plane = np.zeros(6), np.array([0.0, 0.0, -1 / 30])  # both frames the same camera
    acc = TransferResiduals()
    for _ in range(20):
        pm = rng.uniform(0, 400, (500, 2))
        acc.add(pose, pose, plane, pm + rng.normal(0, 0.3, pm.shape), pm, K)
    s = acc.summary(1.0)
    assert s["points"] == 10000 and s["pairs"] == 20
    assert s["robust_std_px"] == pytest.approx(0.3, rel=0.03)  # (sampling: ~1 %)
    assert s["rms_px"] == pytest.approx(0.3, rel=0.03)
    assert s["ratio"] == s["robust_std_px"]


def test_unit_snapshot_and_non_finite_rows():
    K = np.eye(3)
    pose, plane = np.zeros(6), np.array([0.0, 0.0, -1.0])
    acc = TransferResiduals()
    snapshot = copy.copy(acc)  # SequentialMosaicker._save's copy
    pl = np.array([[0.0, 0.1], [np.nan, 0.0], [0.0, -0.1]])
    acc.add(pose, pose, plane, pl, np.zeros((3, 2)), K)
    assert acc.points == 2 and snapshot.points == 0 and snapshot.counts.sum() == 0
    assert TransferResiduals().summary(0.5) == {
        "points": 0, "pairs": 0, "sigma_v_px": 0.5, "robust_std_px": None, "rms_px": None,
        "ratio": None}


def test_unit_warning_names_the_knob_only_against_another_cost():
    K = np.eye(3)
    acc = TransferResiduals()
    pm = np.random.default_rng(1).normal(0, 1, (400, 2))
    acc.add(np.zeros(6), np.zeros(6), np.array([0.0, 0.0, -1.0]), pm + 1.0, pm, K)
    said = visual_agreement(acc, 0.1, source="DATA", knob="--visual-sigma")["warnings"]
    assert len(said) == 1 and said[0].startswith("DATA: the registered points lie 1.48 px")
    assert "give --visual-sigma 1.5" in said[0] and "lens distortion" in said[0]
    assert visual_agreement(acc, 0.1, source="DATA", knob=None)["warnings"] == []
    assert visual_agreement(acc, 1.0, source="DATA", knob="--visual-sigma")["warnings"] == []


def _truth_std(dataset, pairs) -> float:
    """The robust std of the pairs' residuals through the true frame -> reference
    homographies."""
    G = dataset.ground_truth
    r = [cv2.perspectiveTransform(pm.reshape(-1, 1, 2), np.linalg.inv(G[l]) @ G[m]).reshape(-1, 2)
         - pl for l, m, pl, pm in pairs]
    return _robust_std(np.concatenate(r).ravel())


def test_ba_emt_measures_the_keypoint_noise(syn, monkeypatch):
    pairs = []
    real = bundle._adjuster

    class Spy:  # the pairs the adjustment was given
        def __init__(self, adjuster):
            self.adjuster = adjuster

        def add_pair(self, *pair):
            pairs.append(pair)
            return self.adjuster.add_pair(*pair)

        def __getattr__(self, name):
            return getattr(self.adjuster, name)

    monkeypatch.setattr(bundle, "_adjuster", lambda *a, **k: Spy(real(*a, **k)))
    dataset = read_dataset(syn)
    details = bundle.run_ba_emt(dataset, progress=False,
                                options=bundle.BundleOptions(sigma_v_px="auto")).details
    agreement = details["visual_agreement"]
    truth = _truth_std(dataset, pairs)
    assert 0.05 < truth < 0.2  # (the simulator's keypoints: ~0.09 px)
    assert agreement["pairs"] == len(pairs) and agreement["points"] > 5000
    # at the estimate within 5 % of the truth's (measured: 0.0908 against 0.0902 at 60 frames)
    assert agreement["robust_std_px"] == pytest.approx(truth, rel=0.05)
    # sigma_v "auto" (session 49): measured at the first solve's estimate (the paper's 1 px),
    # and the adjustment solved again with it (within 5 % of the truth's too)
    used = details["visual_sigma"]
    assert used["mode"] == "auto" and used["start_px"] == 1.0
    assert used["sigma_v_px"] == used["measured_px"] == pytest.approx(truth, rel=0.05)
    assert agreement["sigma_v_px"] == used["sigma_v_px"]
    assert agreement["ratio"] == pytest.approx(1.0, abs=0.05)
    assert details["solver"]["sigma_v_from"]["sigma_v_px"] == 1.0
    monkeypatch.undo()
    # lba-emt's (pairs forgotten by the window, at their final poses, and those it holds)
    details = run_lba_emt(dataset, progress=False,
                          options=SequentialOptions(sigma_v_px="auto")).details
    streamed = details["visual_agreement"]
    assert streamed["points"] > 3000
    assert streamed["robust_std_px"] == pytest.approx(truth, rel=0.1)
    # (auto: measured by the start-up, over its 40 frames' pairs, every inlier)
    used = details["visual_sigma"]
    assert used["mode"] == "auto" and used["points"] > 3000
    assert used["sigma_v_px"] == pytest.approx(truth, rel=0.1)
    assert streamed["sigma_v_px"] == used["sigma_v_px"]


def test_lens_left_out_of_camera_yaml_shows(tmp_path):
    root = tmp_path / "lens"
    simulate_fetoscopy(root, FetoscopyOptions(n_frames=16, seed=0, laps=0.25,
                                              lens_distortion=LENS))
    with_lens = bundle.run_ba_emt(read_dataset(root), progress=False)
    camera = read_camera_yaml(root / "camera.yaml")
    camera.distortion = None
    write_camera_yaml(root / "camera.yaml", camera)
    without = bundle.run_ba_emt(read_dataset(root), progress=False)
    a, b = (r.details["visual_agreement"]["robust_std_px"] for r in (with_lens, without))
    assert a < 0.15 and b > 10 * a  # (measured at 50 frames: 0.092 against 1.90 px)


def test_cli_report_and_warning(syn, tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["--quiet", "run", str(syn), "--method", "ba-emt", "--out", str(out),
                 "--no-report", "--visual-sigma", "0.02"]) == 0
    report = json.loads((out / "report.json").read_text())
    agreement = report["visual_agreement"]
    assert agreement["sigma_v_px"] == 0.02 and agreement["ratio"] > 2
    said = [w for w in report["warnings"] if "the registered points lie" in w]
    assert len(said) == 1 and said[0].startswith(f"{syn}: ")
    assert "x the visual cost's 0.02 px" in said[0]
    assert "the registered points lie" in capsys.readouterr().err


@pytest.mark.realtime  # (a replay at the frames' timestamps)
def test_live_replay_reports_it(syn, tmp_path):
    out = tmp_path / "live"
    assert main(["--quiet", "run", str(syn), "--method", "lba-emt", "--out", str(out),
                 "--no-report", "--live"]) == 0
    agreement = json.loads((out / "report.json").read_text())["visual_agreement"]
    assert agreement["points"] > 1000 and 0.05 < agreement["robust_std_px"] < 0.2


def test_lba_emt_counts_each_registered_pair_once(tmp_path):
    """The keyframe index forgets blocks of consecutive frames; their pairs among themselves
    were counted under both frames (review Z: 888 pairs said for 601 registered)."""
    root = tmp_path / "evicting"
    simulate_fetoscopy(root, FetoscopyOptions(n_frames=120, laps=120 / 37.5, width=200,
                                              height=200))
    result = run_lba_emt(read_dataset(root), progress=False,
                         options=SequentialOptions(max_keyframe_blocks=3))
    assert result.details["visual_agreement"]["pairs"] == \
        result.details["pairs"]["registered"]
    assert result.details["pairs"]["registered"] > 300  # (the blocks were evicted: 601)


def test_a_pair_with_an_unplaced_frame_is_left_out():
    acc = TransferResiduals()
    K, plane = np.eye(3), np.array([0.0, 0.0, -1.0])
    acc.add(np.full(6, np.nan), np.zeros(6), plane, np.zeros((3, 2)), np.zeros((3, 2)), K)
    acc.add(np.zeros(6), np.zeros(6), np.full(3, np.nan), np.zeros((3, 2)), np.zeros((3, 2)), K)
    assert acc.points == acc.pairs == 0


def test_measured_sigma_v_flattens_fig9(tmp_path):
    """Issue 4, Fig. 9 (17 SYN frames, tracker noise nu x the prior's 1 deg / 1 mm): with the
    paper's sigma_v of 1 px lba-emt's e_M follows the tracker's noise (max/min over nu 3.66 on
    seed 3, 1.39-3.66 over seeds 0-7 and 11, session 48); with the sigma_v measured on the
    recording it does not: given back from a first run (session 48's workflow: 1.00-1.02 on all
    of them), or measured by the start-up (sigma_v_px "auto", session 49;
    bench/bench_lba_experiments.py). Seed 3, the worst with 1 px; bound 1.25."""
    from fusedmosaic.evaluation import frame_errors, mosaic_error

    def e_m(ds, result) -> float:
        return mosaic_error(frame_errors(result.homographies, ds.ground_truth, ds.camera.width,
                                         ds.camera.height))

    paper, measured, auto = [], [], []
    for nu in (0.25, 1.0, 4.0):
        root = tmp_path / f"nu{nu}"
        simulate_fetoscopy(root, FetoscopyOptions(n_frames=17, laps=17 / 37.5, seed=3,
                                                  noise_multiplier=nu))
        ds = read_dataset(root)
        first = run_lba_emt(ds, progress=False,
                            options=SequentialOptions(bootstrap_frames=6, sigma_v_px=1.0))
        sigma = first.details["visual_agreement"]["robust_std_px"]
        assert 0.05 < sigma < 0.2  # (the simulator's keypoints: ~0.09 px)
        given = run_lba_emt(ds, progress=False,
                            options=SequentialOptions(bootstrap_frames=6, sigma_v_px=sigma))
        default = run_lba_emt(ds, progress=False, options=SequentialOptions(
            bootstrap_frames=6, sigma_v_px="auto"))
        assert default.details["visual_sigma"]["mode"] == "auto"
        assert 0.05 < default.details["visual_sigma"]["sigma_v_px"] < 0.2
        paper.append(e_m(ds, first))
        measured.append(e_m(ds, given))
        auto.append(e_m(ds, default))
    assert max(paper) / min(paper) > 2  # (the scenario: with 1 px lba-emt follows the tracker)
    assert max(measured) / min(measured) <= 1.25
    assert max(auto) / min(auto) <= 1.25
