"""Review 50 A, the calibration path: a tracker dropout mid-recording crashed the clock offset
search (H1); a lens model folding over inside the frame was written silently, for `run` to
refuse (M1); how far the board's corners reach into the frame was not said (M2); a tracker time
offset applied at import was left out of calibration.json's (M3); `run --calibration` took a
tracker noise inflated by a misfit lens without a word (L1)."""

from __future__ import annotations

import json
import re
import warnings
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusedmosaic.cli import main
from fusedmosaic.estimation import calibration
from fusedmosaic.estimation.calibration import (
    CalibrationOptions,
    calibrate_detections,
    calibrate_recording,
    read_tracker_calibration,
    write_calibration,
)
from fusedmosaic.io import TrackingSamples, read_tracking_csv, write_tracking_csv
from fusedmosaic.io.calibration import read_camera_yaml
from fusedmosaic.io.plus import IMPORT_RECORD
from fusedmosaic.simulation import CheckerboardOptions, generate_checkerboard, simulate_checkerboard


def _rotation_deg(R: np.ndarray) -> float:
    return float(np.rad2deg(Rotation.from_matrix(R).magnitude()))


def _scene(o: CheckerboardOptions, dropout: slice | None = None):
    """(scene, its corners projected with 0.05 px noise, its tracker samples with those of
    ``dropout`` valid=0)."""
    scene = generate_checkerboard(o)
    T = scene.tracker_from_sensor
    valid = np.ones(len(T), bool)
    if dropout is not None:
        valid[dropout] = False
    tracking = TrackingSamples(scene.tracker_timestamps, T[:, :3, 3].copy(),
                               Rotation.from_matrix(T[:, :3, :3]).as_quat(), valid)
    return scene, scene.projected_detections(0.05, np.random.default_rng(o.seed)), tracking


# --- H1: a dropout of the tracker mid-recording ---------------------------------------------------

@pytest.mark.parametrize(("samples", "delay_s"), [(4, 0.03), (30, -0.02)])
def test_tracker_dropout_mid_recording_keeps_the_offset_and_hand_eye(samples, delay_s):
    """valid=0 samples mid-recording (4: 0.1 s at 40 Hz; 30: 0.75 s) uncover views at offsets
    between the search's bounds, which alone were checked: numpy's "operands could not be
    broadcast" wrapped as "Lower --max-time-offset", no hand-eye. Now the views tracked at every
    offset the search tries take part (36 and 21 of 80 here, where both bounds alone kept more).
    Measured (20 views x 4 frames at 320x320, +-0.45 s, seeds 0-3): offset errors 0.03-0.38 ms,
    within 1.52 of its standard error (RMS 0.85); hand-eye 0.23-0.46 deg / 0.06-0.13 mm, within
    1.45 x the reported RMS. Stated: the offset within 1 ms and 2.5 standard errors of the
    truth, the hand-eye within 1 deg / 0.5 mm and 2.5 x its reported RMS error."""
    o = CheckerboardOptions(seed=0, n_views=20, frames_per_view=4, width=320, height=320,
                            tracker_delay_s=delay_s)
    mid = 60  # of 138 samples: 1.5 s into a 3.2 s recording
    scene, detections, tracking = _scene(o, slice(mid, mid + samples))
    result = calibrate_detections(detections, CalibrationOptions(max_time_offset_s=0.45),
                                  tracking=tracking)
    assert result.hand_eye_error is None, result.hand_eye_error
    he = result.report["hand_eye"]
    offset = he["tracker_time_offset"]
    error = offset["estimate_s"] - delay_s
    assert abs(error) < min(0.001, 2.5 * offset["std_s"]), offset
    assert offset["applied_s"] == offset["estimate_s"]
    rotation = _rotation_deg(scene.hand_eye[:3, :3].T @ result.hand_eye[:3, :3])
    translation = float(np.linalg.norm(result.hand_eye[:3, 3] - scene.hand_eye[:3, 3]))
    assert rotation < min(1.0, 2.5 * he["rotation_error_rms_deg"]), (rotation, he)
    assert translation < min(0.5, 2.5 * he["translation_error_rms_mm"]), (translation, he)
    # fewer views than both bounds alone cover: those near the dropout are left out
    ends = (_covered(tracking, detections.times - 0.454)
            & _covered(tracking, detections.times + 0.454))
    assert offset["views"] < ends.sum()


def _covered(tracking, t):
    from fusedmosaic.io.tracking import interpolate_camera_poses

    return interpolate_camera_poses(tracking, t, None, allow_outside=True)[1]


def test_offset_search_refusal_names_the_dropouts():
    """The same dropout on a recording too short for the bound: refused, naming the views the
    dropout leaves untracked and a bound that keeps half of them with it (+-0.25 s; from the
    tracker's ends alone it said +-0.56 s), not a numpy error."""
    o = CheckerboardOptions(seed=0, n_views=12, frames_per_view=4, width=320, height=320)
    _, detections, tracking = _scene(o, slice(42, 46))
    result = calibrate_detections(detections, CalibrationOptions(), tracking=tracking)
    assert re.fullmatch(
        r"tracking.csv: the clock offset search within \+-0.5 s \(--max-time-offset\) covers \d "
        r"of the 48 views \(those tracked at every offset within it\): at least 3 views tracked "
        r"at every offset are needed; the tracker spans \[-0.\d+, [\d.]+\] s, the views \[0, "
        r"1.88\] s, a 1.88 s recording; \+-0.25 s keeps half the views; the tracker's dropouts "
        r"\(over 75 ms between valid samples\) leave \d+ more views untracked at some offset "
        r"within it. Lower --max-time-offset, or give the offset with --time-offset S",
        result.hand_eye_error or ""), result.hand_eye_error


# --- M1: a lens model folding over inside the frame -----------------------------------------------

FOLDS = r"the pinhole lens model with 8 distortion coefficients folds over inside the 320x320 frame"


@pytest.fixture(scope="module")
def rational():
    """The rational model (--distortion 8) fitted to corners projected through the simulator's
    k1 -0.3 lens (seed 0, 12 views at 320x320): RMS 0.07 px, folding over beyond the corners."""
    o = CheckerboardOptions(seed=0, n_views=12, frames_per_view=2, width=320, height=320)
    _, detections, tracking = _scene(o)
    with pytest.warns(UserWarning, match=FOLDS):
        result = calibrate_detections(detections, CalibrationOptions(distortion=8))
    return result


def test_lens_model_folding_inside_the_frame_named(rational):
    """It was written without a word (exit 0, RMS 0.04 px on the review's recording) and `run`
    refused the camera.yaml. Now named: where it folds, against how far the corners reach, that
    run refuses it, what to change; calibration.json intrinsics.undistortion records it."""
    error = rational.camera_error
    assert re.fullmatch(
        FOLDS + r": undistorted pixel \(\d+, \d+\) is drawn from raw pixel \(\d+, \d+\), "
        r"mirrored, at \d+ % of the frame's radius from the principal point \(the board's "
        r"corners reach \d+ % that way, \d+ % at most\): it fits the corners but not the "
        r"frame beyond them, and run refuses this camera.yaml \(its undistorted frames would "
        r"show a double image\). Calibrate with fewer distortion coefficients \(--distortion 5 "
        r"or 4\), or with views that bring the board to the frame's edges and corners",
        error or ""), error
    fold = rational.report["intrinsics"]["undistortion"]
    assert fold["folds_over"] and fold["error"] == error and len(fold["pixel"]) == 2
    assert rational.report["intrinsics"]["rms_px"] < 0.1  # (the corners fit)
    with pytest.raises(ValueError, match="fold the pinhole lens model over"):
        rational.camera.undistortion()  # what run does with it


def test_cli_writes_a_folding_lens_model_and_exits_2(rational, tmp_path, capsys, monkeypatch):
    """The CLI writes camera.yaml and calibration.json (for inspection) and exits 2 naming
    the fold; the default 5 coefficients on the same corners: no fold, recorded as such."""
    found = replace(rational, report={**rational.report, "frames_searched": 24,
                                      "frame_times": "frames.csv"})
    monkeypatch.setattr(calibration, "calibrate_recording", lambda *a, **k: found)
    rec, out = tmp_path / "rec", tmp_path / "out"
    rec.mkdir()
    assert main(["--quiet", "calibrate", str(rec), "--board", "9x6", "--square-mm", "2",
                 "--distortion", "8", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert (f"fusedmosaic: error: {out}/camera.yaml: its lens model folds over inside the "
            "frame, so run refuses it (calibration.json intrinsics.undistortion; the warning "
            "above says where and what to change)") in err
    written = json.loads((out / "calibration.json").read_text())
    assert written["intrinsics"]["undistortion"]["folds_over"]
    with pytest.raises(ValueError, match="fold the pinhole lens model over"):
        read_camera_yaml(out / "camera.yaml").undistortion()
    o = CheckerboardOptions(seed=0, n_views=12, frames_per_view=2, width=320, height=320)
    _, detections, _ = _scene(o)
    five = calibrate_detections(detections, CalibrationOptions())
    assert five.camera_error is None
    assert five.report["intrinsics"]["undistortion"] == {"folds_over": False,
                                                        "fov_mask_radius": None}


def test_high_rms_warning_says_the_rational_model_is_checked():
    """The intrinsics' warning advised --distortion 8 without a word of its folding over."""
    hint = calibration._camera_model_warning(0.9, CalibrationOptions())
    assert ("try --distortion 8 (the rational model: calibrate then checks that it does not "
            "fold over inside the frame) or, for a wide-angle scope, --lens-model fisheye") in hint


# --- M2: how far the corners reach ---------------------------------------------------------------

def test_corners_reaching_little_of_the_frame_warned():
    """Views at 60 mm (12 at 320x320) put the corners within 38 % of the frame's radius: the
    model fitted them to 0.07 px and erred by tens of px at the periphery (corner_reach's
    measurements), without a word. Now calibration.json intrinsics.corner_reach gives the
    fraction and below 60 % it is warned of; the simulator's default 30 mm views reach 69 %."""
    o = CheckerboardOptions(seed=0, n_views=12, frames_per_view=2, width=320, height=320,
                            distance_mm=60.0)
    _, detections, _ = _scene(o)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        result = calibrate_detections(detections, CalibrationOptions())
    reach = result.report["intrinsics"]["corner_reach"]
    assert 0.3 < reach["fraction"] < 0.45
    assert reach["fraction"] == pytest.approx(reach["corner_radius_px"]
                                              / reach["frame_radius_px"])
    assert re.fullmatch(
        r"the board's corners reach 3\d % of the frame's radius from the principal point "
        r"\(\d+ of 23\d px; 70 % advised\): beyond it, over the frame's periphery, the lens "
        r"model is extrapolated and may err by pixels to tens of pixels, whatever the RMS "
        r"reprojection error and the standard errors say \(they see the corners only\). Film "
        r"views with the board near the frame's edges and corners", reach["warning"])
    assert any(str(w.message) == f"the recording: {reach['warning']}" for w in said)
    o = CheckerboardOptions(seed=0, n_views=12, frames_per_view=2, width=320, height=320)
    _, detections, _ = _scene(o)
    result = calibrate_detections(detections, CalibrationOptions())  # (a warning: an error)
    assert 0.6 < result.report["intrinsics"]["corner_reach"]["fraction"] < 0.8


# --- M3 and L1: calibration.json read for run --calibration --------------------------------------

@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    """A checkerboard recording whose tracker runs 40 ms late, its tracking.csv shifted onto the
    video's clock at import (import.json 0.04 s, as import / live --record write), calibrated;
    and datasets imported without a shift, with +0.01 s and with +0.04 s."""
    base = tmp_path_factory.mktemp("review50")
    root = base / "rec"
    simulate_checkerboard(root, CheckerboardOptions(n_views=12, frames_per_view=4, width=320,
                                                    height=320, tracker_delay_s=0.04))
    s = read_tracking_csv(root / "tracking.csv")
    write_tracking_csv(root / "tracking.csv", TrackingSamples(
        s.timestamps - 0.04, s.translations, s.quaternions, s.valid))
    (root / IMPORT_RECORD).write_text(json.dumps({"tracker_time_offset_applied_s": 0.04}))
    result = calibrate_recording(root)
    assert result.hand_eye_error is None, result.hand_eye_error
    write_calibration(base / "cal", result)
    datasets = {}
    for shift in (None, 0.01, 0.04):
        d = datasets[shift] = base / f"ds_{shift}"
        d.mkdir()
        if shift is not None:
            (d / IMPORT_RECORD).write_text(json.dumps({"tracker_time_offset_applied_s": shift}))
    return dict(result=result, cal_json=base / "cal" / "calibration.json", datasets=datasets)


def test_calibration_counts_the_shift_its_recording_had_at_import(imported):
    """calibrate measured ~0 on tracking.csv shifted at import and wrote applied_s 0: run
    --calibration then applied 0 to a dataset imported without a shift, where the tracker is 40
    ms late. Now calibration.json gives import_shift_s and total_s, and run applies the total
    less the dataset's own shift at import, warning where the two differ."""
    offset = imported["result"].report["hand_eye"]["tracker_time_offset"]
    assert offset["import_shift_s"] == 0.04
    assert abs(offset["estimate_s"]) < 0.002
    assert offset["total_s"] == 0.04 + offset["applied_s"]
    cal_json, datasets = imported["cal_json"], imported["datasets"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning for these two
        plain = read_tracker_calibration(cal_json, dataset=datasets[None])
        same = read_tracker_calibration(cal_json, dataset=datasets[0.04])
    assert abs(plain.time_offset_s - 0.04) < 0.002
    assert "calibrate's recording was shifted by +0.04 s at import" in plain.time_offset_note
    assert abs(same.time_offset_s) < 0.002
    if offset["applied_s"] == 0:
        assert same.time_offset_s == 0.0
        assert same.time_offset_note == ("tracking.csv was shifted by +0.04 s at import, the "
                                         "offset calibrate measured")
    with pytest.warns(UserWarning, match=(
            r"ds_0.01/tracking.csv was shifted by the tracker time offset \+0.01 s at import "
            r"\(.*ds_0.01/import.json\), .*calibration.json measured \+0.04\d* s: the "
            r"difference \+0.03\d* s applied")):
        other = read_tracker_calibration(cal_json, dataset=datasets[0.01])
    assert abs(other.time_offset_s - 0.03) < 0.002


def test_run_calibration_warns_of_the_intrinsics_warning(imported, tmp_path):
    """An intrinsics warning (a misfit lens: --distortion 0 gave 1.52 deg / 0.80 mm of tracker
    noise seen for a true 0.9 / 0.25) was not passed on; hand_eye.warning alone was."""
    report = json.loads(imported["cal_json"].read_text())
    assert "warning" not in report["intrinsics"]
    report["intrinsics"]["warning"] = "the RMS reprojection error is 1.229 px, above the 0.5 px"
    edited = tmp_path / "calibration.json"
    edited.write_text(json.dumps(report))
    with pytest.warns(UserWarning, match=(
            r"calibration.json: calibrate warned of its intrinsics, so the tracker noise it saw "
            r"\([\d.]+ deg / [\d.]+ mm\) may be inflated by the lens model's misfit: the RMS "
            r"reprojection error is 1.229 px")):
        read_tracker_calibration(edited)

