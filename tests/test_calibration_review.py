"""Review findings on calibration and PLUS import (review A): a compressed sequence too large to
decompress, a HeaderSize past the data file, a clock offset search bound below the 5 ms scan
step, a high reprojection error (a lens model lacking coefficients), a tracker time offset
applied twice (import, then run --calibration), and messages naming the wrong cause (--board,
--every, a failed hand-eye, --focal-factor)."""

from __future__ import annotations

import json
import re
import warnings
import zlib
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusedmosaic.cli import main
from fusedmosaic.estimation.calibration import (
    BoardDetections,
    CalibrationOptions,
    calibrate_detections,
    find_board_views,
    read_tracker_calibration,
    write_calibration,
)
from fusedmosaic.io import TrackingSamples, plus, read_tracking_csv
from fusedmosaic.io.dataset import read_frame_times
from fusedmosaic.io.plus import import_plus_sequence, read_plus_sequence, write_plus_sequence
from fusedmosaic.io.video import FrameSource
from fusedmosaic.simulation import CheckerboardOptions, simulate_checkerboard

# 10 views x 6 frames at 320x320, exact clocks (no tracker delay): the simulator's default lens
# (k1 -0.30, k2 0.10) and EM noise (0.9 deg / 0.25 mm).
SMALL = dict(n_views=10, frames_per_view=6, width=320, height=320)


@pytest.fixture(scope="module")
def board(tmp_path_factory):
    """The recording, its board detections (every frame searched), its tracker samples, and
    the default calibration of it written to a folder (calibration.json)."""
    root = tmp_path_factory.mktemp("review") / "board"
    simulate_checkerboard(root, CheckerboardOptions(**SMALL))
    o = CalibrationOptions()
    frames = FrameSource.open(root)
    ids, times, _ = read_frame_times(root, frames, None)
    detections, searched = find_board_views(frames, ids, times, o)
    tracking = read_tracking_csv(root / "tracking.csv")
    result = calibrate_detections(detections, o, tracking=tracking, searched=searched)
    assert result.hand_eye_error is None, result.hand_eye_error
    cal = root.parent / "cal"
    write_calibration(cal, result)
    return dict(root=root, detections=detections, tracking=tracking, result=result,
                cal_json=cal / "calibration.json", searched=searched)


def _refused(argv: list[str], message: str, capsys) -> str:
    """The CLI exits 2 with `message` (a regular expression) on stderr."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert re.search(message, err), err
    return err


# --- 1. a compressed sequence too large to decompress -------------------------------------------

def _header(dims: str, data: bytes, extra: str = "") -> bytes:
    return (f"ObjectType = Image\nNDims = 3\nBinaryData = True\nCompressedData = True\n"
            f"DimSize = {dims}\nElementNumberOfChannels = 1\nElementType = MET_UCHAR\n{extra}"
            "Seq_Frame0000_Timestamp = 0\nElementDataFile = LOCAL\n").encode() + data


def test_compressed_sequence_beyond_zlibs_ratio_refused_before_allocating(tmp_path, capsys,
                                                                          monkeypatch):
    """A 278-byte .mha asking for 100000 x 100000 x 1000 bytes: numpy's MemoryError traceback,
    exit 1. Now refused before any allocation: zlib cannot inflate 11 bytes to 9 TiB."""
    allocated = []
    monkeypatch.setattr(plus, "_allocate", lambda n: allocated.append(n))
    huge = tmp_path / "huge.mha"
    huge.write_bytes(_header("100000 100000 1000", zlib.compress(b"\0" * 10)))
    with pytest.raises(ValueError, match=r"huge.mha: DimSize 100000 100000 1000 with 1 "
                                         r"channel\(s\) of MET_UCHAR needs 10000000000000 bytes "
                                         r"decompressed \(9.09 TiB\) from 11 compressed bytes, "
                                         r"more than zlib's maximum ratio"):
        read_plus_sequence(huge)
    assert allocated == []
    _refused(["import", str(huge), str(tmp_path / "out")],
             r"^fusedmosaic: error: .*huge.mha: DimSize 100000 100000 1000 .*zlib's maximum "
             r"ratio .*damaged\n$", capsys)
    assert not (tmp_path / "out").exists()


def test_compressed_sequence_larger_than_memory_refused_with_the_workaround(tmp_path,
                                                                           monkeypatch):
    """A plausible compressed sequence that this machine cannot hold decompressed: refused
    naming the file, DimSize, the size and the workaround (uncompressed, memory-mapped), both
    ahead (beyond the physical memory) and when the allocation fails."""
    images = np.zeros((40, 48, 64), np.uint8)  # 122880 bytes, compressed ~150: ratio ~800
    path = write_plus_sequence(tmp_path / "rec.seq.mha", images, np.arange(40) / 25.0,
                               compress=True)
    assert read_plus_sequence(path).images.shape == (40, 48, 64)  # within zlib's ratio
    message = (r"rec.seq.mha: DimSize 64 48 40 with 1 channel\(s\) of MET_UCHAR needs 122880 "
               r"bytes, 120 KiB decompressed, more than this machine can hold{}: a compressed "
               r"sequence is decompressed into memory. Write it uncompressed \(PLUS's "
               r"EditSequenceFile can; an uncompressed sequence is read memory-mapped")
    monkeypatch.setattr(plus, "_physical_memory", lambda: 100_000)
    with pytest.raises(ValueError, match=message.format(r" \(97.7 KiB of memory\)")):
        read_plus_sequence(path)

    def no_memory(n):
        raise MemoryError(n)

    monkeypatch.setattr(plus, "_physical_memory", lambda: None)
    monkeypatch.setattr(plus, "_allocate", no_memory)
    with pytest.raises(ValueError, match=message.format("")):
        read_plus_sequence(path)


def test_header_size_beyond_the_data_file_named(tmp_path, capsys):
    """It said 'image data (hs.raw) is -99904 bytes ...: truncated'."""
    (tmp_path / "hs.mhd").write_text(
        "ObjectType = Image\nNDims = 3\nDimSize = 8 6 2\nElementType = MET_UCHAR\n"
        "HeaderSize = 100000\nSeq_Frame0000_Timestamp = 0\nSeq_Frame0001_Timestamp = 0.04\n"
        "ElementDataFile = hs.raw\n")
    (tmp_path / "hs.raw").write_bytes(bytes(96))
    err = _refused(["import", str(tmp_path / "hs.mhd"), str(tmp_path / "out")],
                   r"hs.mhd: HeaderSize 100000 is beyond the end of the data file .*hs.raw, "
                   r"which is 96 bytes\n$", capsys)
    assert "-99904" not in err and not (tmp_path / "out").exists()


# --- 2. a clock offset search bound below the scan step -----------------------------------------

@pytest.mark.parametrize("bound", [0.004, 0.001])
def test_time_offset_bound_below_the_scan_step_finds_agreeing_clocks(board, bound):
    """Clocks that agree, searched within +-4 ms or +-1 ms: every estimate was 'at the bound'
    (a 5 ms tolerance) and, under 2.5 ms, the grid was the single point -bound; the hand-eye was
    refused with 'the fit still improves beyond it'. Now ~0, not at the bound, not applied."""
    result = calibrate_detections(board["detections"],
                                  CalibrationOptions(max_time_offset_s=bound),
                                  tracking=board["tracking"], searched=board["searched"])
    assert result.hand_eye_error is None, result.hand_eye_error
    offset = result.report["hand_eye"]["tracker_time_offset"]
    assert offset["estimated"] and not offset["at_bound"]
    assert abs(offset["estimate_s"]) < min(0.5 * bound, 3 * offset["std_s"]), offset
    assert offset["applied_s"] == 0.0 and offset["search_bound_s"] == bound


def test_time_offset_beyond_a_small_bound_still_at_the_bound(board):
    """The scaled tolerance still sees an offset beyond the bound: a tracker 10 ms late
    searched within +-4 ms stops at +4 ms and is refused as before."""
    s = board["tracking"]
    late = TrackingSamples(s.timestamps + 0.01, s.translations, s.quaternions, s.valid)
    result = calibrate_detections(board["detections"],
                                  CalibrationOptions(max_time_offset_s=0.004), tracking=late,
                                  searched=board["searched"])
    assert re.search(r"not within the search bound: the estimate \(\+4 \+- [\d.]+ ms\) lies at "
                     r"\+-0.004 s", result.hand_eye_error or ""), result.hand_eye_error


# --- 3. a high reprojection error ---------------------------------------------------------------

def test_high_reprojection_error_warned_and_named_in_the_hand_eye_refusal(board, tmp_path,
                                                                         capsys):
    """--distortion 0 on the k1 = -0.3 lens: RMS 0.87 px (0.045 with 5 coefficients), cx 12 px
    off; it exited 0 without a word, and with the tracker the hand-eye's refusal blamed
    tracking.csv alone. Now warned (calibration.json intrinsics.warning and a warning on the
    terminal), and the refusal names the camera model first."""
    default = board["result"].report["intrinsics"]
    assert default["rms_px"] < 0.1 and "warning" not in default  # (no warning: pytest errors)
    o = CalibrationOptions(distortion=0)
    hint = (r"the RMS reprojection error is 0\.8\d\d px, above the 0\.5 px a camera model "
            r"fitting the lens leaves .*: the pinhole model with 0 distortion coefficients may "
            r"not describe this lens.* try more distortion coefficients \(--distortion 5\) or, "
            r"for a wide-angle scope, --lens-model fisheye")
    with pytest.warns(UserWarning, match=hint):
        result = calibrate_detections(board["detections"], o, tracking=board["tracking"],
                                      searched=board["searched"])
    assert re.search(hint, result.report["intrinsics"]["warning"])
    assert re.search(r"tracking.csv: the tracker and the board disagree: .* Suspect the camera "
                     r"model first: " + hint + r".*\. Otherwise check that tracking.csv holds "
                     r"tracker_from_sensor", result.hand_eye_error or ""), result.hand_eye_error
    # the CLI, without the tracker: exit 0, the warning on stderr and in calibration.json
    notrack = tmp_path / "notrack"
    notrack.mkdir()
    (notrack / "frames").symlink_to(board["root"] / "frames")
    for name in ("camera.yaml", "frames.csv"):
        (notrack / name).write_bytes((board["root"] / name).read_bytes())
    with warnings.catch_warnings():
        warnings.simplefilter("default")  # as outside pytest: the CLI prints it
        assert main(["--quiet", "calibrate", str(notrack), "--board", "9x6", "--square-mm",
                     "2", "--distortion", "0", "--out", str(tmp_path / "out")]) == 0
    assert re.search("fusedmosaic: warning: .*" + hint, capsys.readouterr().err)
    written = json.loads((tmp_path / "out" / "calibration.json").read_text())
    assert re.search(hint, written["intrinsics"]["warning"])


# --- 4. the tracker time offset applied twice ---------------------------------------------------

def _plus_recording(tmp_path: Path) -> Path:
    rng = np.random.default_rng(0)
    n = 12
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(rng.normal(size=(n, 3)) * 0.2).as_matrix()
    T[:, :3, 3] = rng.normal(size=(n, 3)) * 10
    images = rng.integers(0, 255, (n, 48, 64), dtype=np.uint8)
    return write_plus_sequence(tmp_path / "rec.igs.mha", images, np.arange(n) / 25.0,
                               {"SensorToTracker": T})


def test_import_records_its_time_offset_and_calibration_is_not_applied_again(board, tmp_path):
    """import --tracker-time-offset S wrote tracking.csv on the video's clock and kept no
    record of it; run --calibration then shifted it again by calibration.json's offset (159 ms
    in all for 80 ms), silently. Now import writes import.json, and the calibration read for
    that dataset does not apply its offset again (warning once); for a dataset imported without
    a shift (no import.json) it applies as before."""
    from fusedmosaic.io.plus import IMPORT_RECORD, applied_tracker_time_offset

    seq = _plus_recording(tmp_path)
    shifted = tmp_path / "shifted"
    import_plus_sequence(seq, shifted, camera=None, tracker_time_offset=0.03)
    record = json.loads((shifted / IMPORT_RECORD).read_text())
    assert record["tracker_time_offset_applied_s"] == 0.03
    assert record["source"] == str(seq) and record["transform"] == "SensorToTrackerTransform"
    assert applied_tracker_time_offset(shifted) == 0.03
    plain = tmp_path / "plain"
    import_plus_sequence(seq, plain, camera=None)
    assert not (plain / IMPORT_RECORD).exists() and applied_tracker_time_offset(plain) is None
    # calibration.json with a measured, applied offset (the module's clocks agree: 0 applied)
    report = json.loads(board["cal_json"].read_text())
    report["hand_eye"]["tracker_time_offset"].update(estimated=True, estimate_s=0.0301,
                                                     applied_s=0.0301)
    # as calibrate wrote it before it read its recording's import.json (no import_shift_s /
    # total_s): its offset against its own recording (review 50 M3: tests/
    # test_calibration_review50.py has the difference applied for the calibration.json now)
    for key in ("import_shift_s", "total_s"):
        del report["hand_eye"]["tracker_time_offset"][key]
    cal_json = tmp_path / "calibration.json"
    cal_json.write_text(json.dumps(report))
    assert read_tracker_calibration(cal_json).time_offset_s == 0.0301
    assert read_tracker_calibration(cal_json, dataset=plain).time_offset_s == 0.0301
    with pytest.warns(UserWarning, match=(
            r"shifted/tracking.csv was already shifted by the tracker time offset \+0.03 s at "
            r"import \(.*shifted/import.json\); .*calibration.json's offset \+0.0301 s not "
            r"applied again")) as said:
        cal = read_tracker_calibration(cal_json, dataset=shifted)
    assert len(said) == 1
    assert cal.time_offset_s == 0.0
    assert cal.time_offset_note == "not applied: tracking.csv was shifted by +0.03 s at import"
    # a damaged record is named
    (shifted / IMPORT_RECORD).write_text('{"tracker_time_offset_applied_s": "soon"}')
    with pytest.raises(ValueError, match=r"import.json: tracker_time_offset_applied_s: expected "
                                         r"seconds within \+-10, got 'soon'"):
        read_tracker_calibration(cal_json, dataset=shifted)


# --- 5. messages --------------------------------------------------------------------------------

def test_failed_hand_eye_calibration_not_told_to_add_a_tracker(board, tmp_path):
    """run --calibration on a calibration.json whose hand-eye failed (the recording had
    tracking.csv) said 'calibrate a recording with tracking.csv'; that is the advice for a
    skipped hand-eye only."""
    report = json.loads(board["cal_json"].read_text())
    for entry, advice in (
            ({"failed": "tracking.csv: the tracker's motions are 0.5 x those the board gives"},
             "the hand-eye failed at calibrate: correct what its message names and calibrate "
             "again"),
            ({"skipped": "no tracking.csv in REC"}, "calibrate a recording with tracking.csv")):
        path = tmp_path / f"{next(iter(entry))}.json"
        path.write_text(json.dumps({**report, "hand_eye": entry}))
        with pytest.raises(ValueError) as err:
            read_tracker_calibration(path)
        assert str(err.value) == (f"{path}: holds no hand-eye calibration "
                                  f"({next(iter(entry.values()))}), so no tracker time offset "
                                  f"or noise: {advice}")
    # no hand_eye entry at all (the advice's test above read it from a None: AttributeError)
    path = tmp_path / "none.json"
    path.write_text(json.dumps({"camera": {}}))
    with pytest.raises(ValueError, match=r'holds no hand-eye calibration \(no "hand_eye" '
                       r"entry\), so no tracker time offset or noise: calibrate a recording "
                       r"with tracking.csv$"):
        read_tracker_calibration(path)


def test_wrong_board_size_named_when_few_frames_have_it(board):
    """A wrong --board (8x6 on a 9x6 board) finds a part of the board in a few frames; the
    focal length is then not determined and the advice was only 'film more angles'. Modelled:
    the 8x6 part of 4 frames' corners (1 px of noise: a part found off the squares' corners)."""
    d = board["detections"]
    rng = np.random.default_rng(0)
    pick = [0, 12, 24, 36]
    points = [d.points[k].reshape(6, 9, 2)[:, :8].reshape(-1, 2)
              + rng.normal(0, 1.0, (48, 2)).astype(np.float32) for k in pick]
    part = BoardDetections(points, d.frames[pick], d.ids[pick], d.times[pick], d.size)
    o = CalibrationOptions(board_cols=8, board_rows=6)
    with pytest.raises(ValueError, match=r"the 4 distinct views do not determine the focal "
                                         r"length .* different distances\); the 8x6 board was "
                                         r"found in only 4 of 60 frames searched: check --board "
                                         r"\(inner corners"):
        calibrate_detections(part, o, searched=60)
    with pytest.raises(ValueError, match=r"do not determine the focal length") as err:
        calibrate_detections(part, o, searched=4)  # found in every frame searched
    assert "--board" not in str(err.value)


def test_every_named_when_every_frame_searched_had_the_board(board, tmp_path, capsys):
    """--every 1000 on 60 frames: 'found in 1 of 1 frames searched ... Check the board size';
    the board was in every frame searched, --every is the cause."""
    err = _refused(["--quiet", "calibrate", str(board["root"]), "--board", "9x6", "--square-mm",
                    "2", "--every", "1000", "--out", str(tmp_path / "out")],
                   r"found in 1 of 1 frames searched; calibration needs at least 4 views .*\. "
                   r"The board was found in every frame searched: lower --every \(now 1000: one "
                   r"frame in 1000 searched\)\n$", capsys)
    assert "Check the board size" not in err and not (tmp_path / "out").exists()
    d = board["detections"]
    few = BoardDetections(d.points[:3], d.frames[:3], d.ids[:3], d.times[:3], d.size)
    with pytest.raises(ValueError, match=r"found in 3 of 3 frames searched; .*The board was "
                                         r"found in every frame searched: record more views$"):
        calibrate_detections(few, CalibrationOptions(), searched=3)
    with pytest.raises(ValueError, match=r"found in 3 of 9 frames searched; .*Check the board "
                                         r"size \(inner corners, not squares\)"):
        calibrate_detections(few, CalibrationOptions(), searched=9)


def test_simulate_checkerboard_names_the_focal_factor(tmp_path, capsys):
    """--focal-factor 1e6 was told to 'raise --distance-mm, lower --square-mm, or give a
    milder lens'."""
    _refused(["simulate", "checkerboard", str(tmp_path / "s"), "--width", "128", "--height",
              "128", "--focal-factor", "1e6"],
             r"^fusedmosaic: error: no view shows the whole 9x6 board inside the 128x128 image "
             r"through the lens \(.*\): at the farthest views \(36 mm\) it would span 5\.69e\+07 "
             r"px with --focal-factor 1e\+06, where the image leaves 118 px: lower "
             r"--focal-factor \(or raise --distance-mm, lower --square-mm\)\n$", capsys)
    assert not (tmp_path / "s").exists()


def test_run_calibration_on_an_import_shifted_dataset_does_not_shift_again(tmp_path, capsys):
    """import --tracker-time-offset S, then run --calibration CAL (offset S): tracking.csv is
    not shifted a second time (it was by 2 S, silently); one warning says so; an explicit
    --tracker-time-offset still applies as given."""
    from fusedmosaic.io import interpolate_camera_poses, read_dataset
    from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

    data = simulate_fetoscopy(tmp_path / "syn", FetoscopyOptions(n_frames=12, laps=12 / 37.5,
                                                                  width=200, height=200))
    ds = read_dataset(data)
    cam_from_sensor, _ = interpolate_camera_poses(ds.tracking, ds.timestamps)
    R = Rotation.from_rotvec(cam_from_sensor[:, :3]).inv()
    T = np.tile(np.eye(4), (len(ds), 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R.as_matrix(), -R.apply(cam_from_sensor[:, 3:])
    seq = write_plus_sequence(tmp_path / "rec.igs.mha", np.stack(list(ds.frames))[..., ::-1],
                              ds.timestamps, {"SensorToTracker": T})
    imported = tmp_path / "imported"
    assert main(["--quiet", "import", str(seq), str(imported), "--camera",
                 str(data / "camera.yaml"), "--hand-eye", str(data / "hand_eye.txt"),
                 "--tracker-time-offset", "0.02"]) == 0
    cal = {"hand_eye": {"tracker_time_offset": {"estimated": True, "estimate_s": 0.02,
                                                "applied_s": 0.02},
                        "tracker_sigma_deg": 0.9, "tracker_sigma_mm": 0.25}}
    (tmp_path / "calibration.json").write_text(json.dumps(cal))
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        assert main(["run", str(imported), "--method", "emt", "--out", str(tmp_path / "out"),
                     "--calibration", str(tmp_path / "calibration.json"), "--allow-untracked",
                     "--no-report"]) == 0
    said = capsys.readouterr()
    assert said.err.count("already shifted by the tracker time offset +0.02 s at import") == 1
    assert "not applied again" in said.err
    assert ("tracker time offset +0.0000 s (not applied: tracking.csv was shifted by +0.02 s "
            "at import)") in said.out
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["tracker_time_offset_s"] == 0.0
    # an explicit offset applies as given
    assert main(["--quiet", "run", str(imported), "--method", "emt", "--out",
                 str(tmp_path / "out2"), "--tracker-time-offset", "0.02", "--allow-untracked",
                 "--no-report"]) == 0
    assert json.loads((tmp_path / "out2" / "report.json").read_text())[
        "tracker_time_offset_s"] == 0.02


def test_a_live_recording_with_a_time_offset_records_it(tmp_path):
    """live --record DATA --tracker-time-offset S writes the samples on the video's clock (as
    import does), and now says so as import does (import.json), so that run --calibration on
    the recording does not shift them a second time; without an offset nothing is written."""
    from fusedmosaic.io.calibration import Camera
    from fusedmosaic.io.plus import applied_tracker_time_offset
    from fusedmosaic.io.recorder import DatasetRecorder

    camera = Camera(64, 48, camera_matrix=np.array([[60.0, 0, 32], [0, 60, 24], [0, 0, 1]]))
    for name, offset in (("shifted", 0.05), ("plain", 0.0)):
        recorder = DatasetRecorder(tmp_path / name, camera, tracker_time_offset=offset)
        for k in range(3):
            recorder.add_sample(0.04 * k, np.eye(4))
            recorder.add_frame(np.full((48, 64), 10 * k, np.uint8), 0.04 * k)
        recorder.finish()
    assert applied_tracker_time_offset(tmp_path / "shifted") == 0.05
    assert applied_tracker_time_offset(tmp_path / "plain") is None
