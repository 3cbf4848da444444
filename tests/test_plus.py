"""PLUS toolkit sequence metafiles (io/plus.py): write / read round trips, import into the
dataset contract (then ba-emt on it), a hand-written header like a real PLUS recording, and bad
input (a ValueError naming the file and the problem, no dataset folder left behind)."""

from __future__ import annotations

import json
import re
import shutil
import zlib
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fusedmosaic.estimation.bundle import BundleOptions
from fusedmosaic.io import (
    Camera,
    TrackingSamples,
    interpolate_camera_poses,
    read_dataset,
    read_homographies_csv,
    read_tracking_csv,
    write_tracking_csv,
)
from fusedmosaic.io.plus import import_plus_sequence, read_plus_sequence, write_plus_sequence
from fusedmosaic.registration.features import FeatureOptions
from fusedmosaic.runner import run_dataset
from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

# 30 SYN frames of 200x200; at this size SIFT needs a lower contrast threshold than its default
# to register most pairs, and EMT-guided pairs keep the run at ~2 s.
SYN = FetoscopyOptions(n_frames=30, laps=30 / 37.5, width=200, height=200)
BA_EMT = BundleOptions(features=FeatureOptions(sift_contrast_threshold=0.01),
                       pair_selection="emt-guided")
E_M_TOLERANCE_PX = 0.5  # measured 0.09 px (seed 0); the original 40 Hz recording gives the same


@pytest.fixture(scope="module")
def syn(tmp_path_factory):
    """The simulated dataset, its frames, and the tracker poses interpolated to the frame
    timestamps (what a frame-synchronous PLUS recording holds) as tracker_from_sensor."""
    root = simulate_fetoscopy(tmp_path_factory.mktemp("plus") / "syn", SYN)
    ds = read_dataset(root)
    cam_from_sensor, valid = interpolate_camera_poses(ds.tracking, ds.timestamps)  # no hand-eye
    assert valid.all()
    sensor_in_tracker = Rotation.from_rotvec(cam_from_sensor[:, :3]).inv()
    T = np.tile(np.eye(4), (len(ds), 1, 1))
    T[:, :3, :3] = sensor_in_tracker.as_matrix()
    T[:, :3, 3] = -sensor_in_tracker.apply(cam_from_sensor[:, 3:])
    bgr = np.stack(list(ds.frames))
    return SimpleNamespace(root=root, ds=ds, T=T, quaternions=sensor_in_tracker.as_quat(),
                           bgr=bgr, gray=np.stack([cv2.cvtColor(f, cv2.COLOR_BGR2GRAY)
                                                   for f in bgr]))


def _check_tracking(path: Path, timestamps: np.ndarray, T: np.ndarray, valid, tol: float,
                    tol_mm: float | None = None):
    samples = read_tracking_csv(path)
    np.testing.assert_array_equal(samples.timestamps, timestamps)
    np.testing.assert_array_equal(samples.valid, valid)
    ok = samples.valid
    np.testing.assert_allclose(samples.translations[ok], T[ok, :3, 3], rtol=0,
                               atol=tol if tol_mm is None else tol_mm)
    R = Rotation.from_quat(samples.quaternions[ok]).as_matrix()
    np.testing.assert_allclose(R, T[ok, :3, :3], rtol=0, atol=tol)
    assert np.isnan(samples.translations[~ok]).all()


@pytest.mark.parametrize("compress", [False, True], ids=["raw", "zlib"])
@pytest.mark.parametrize("suffix", [".mha", ".mhd"])
@pytest.mark.parametrize("colour", ["gray", "rgb"])
def test_round_trip_through_a_plus_sequence(syn, tmp_path, colour, suffix, compress):
    images = syn.bgr[..., ::-1] if colour == "rgb" else syn.gray  # PLUS stores RGB
    path = write_plus_sequence(tmp_path / f"rec.seq{suffix}", images, syn.ds.timestamps,
                               {"SensorToTracker": syn.T}, compress=compress)
    if suffix == ".mhd":
        raw = tmp_path / ("rec.seq.zraw" if compress else "rec.seq.raw")
        assert f"ElementDataFile = {raw.name}" in path.read_text()
    seq = read_plus_sequence(path)
    assert isinstance(seq.images, np.memmap) is not compress  # lazy unless compressed
    channels = 1 if images.ndim == 3 else 3
    assert (seq.width, seq.height, seq.channels, len(seq)) == (200, 200, channels, 30)
    np.testing.assert_array_equal(seq.images, images)
    np.testing.assert_array_equal(seq.transforms["SensorToTrackerTransform"], syn.T)

    summary = import_plus_sequence(path, tmp_path / "ds", camera=syn.root / "camera.yaml",
                                   hand_eye=syn.ds.hand_eye)
    assert (summary.frames, summary.skipped_frames, summary.invalid_samples) == (30, [], [])
    assert (summary.transform, summary.inverted) == ("SensorToTrackerTransform", False)
    ds = read_dataset(tmp_path / "ds")
    expected = syn.bgr if colour == "rgb" else syn.gray
    for k in range(len(ds)):
        np.testing.assert_array_equal(ds.frames[k], expected[k])
    np.testing.assert_array_equal(ds.frame_ids, np.arange(30))
    np.testing.assert_array_equal(ds.timestamps, syn.ds.timestamps)
    _check_tracking(tmp_path / "ds" / "tracking.csv", syn.ds.timestamps, syn.T, np.ones(30, bool),
                    tol=1e-9)
    np.testing.assert_allclose(ds.hand_eye, syn.ds.hand_eye, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(ds.camera.camera_matrix, syn.ds.camera.camera_matrix)
    # the imported dataset's camera poses are the original's at the frame times
    np.testing.assert_allclose(ds.cam_from_world, syn.ds.cam_from_world, rtol=0, atol=1e-9)


def test_imported_recording_runs_like_the_frame_synchronous_original(syn, tmp_path):
    path = write_plus_sequence(tmp_path / "rec.seq.mha", syn.bgr[..., ::-1], syn.ds.timestamps,
                               {"SensorToTracker": syn.T})
    imported = tmp_path / "imported"
    import_plus_sequence(path, imported, camera=syn.root / "camera.yaml",
                         hand_eye=syn.root / "hand_eye.txt")
    shutil.copy(syn.root / "ground_truth.csv", imported / "ground_truth.csv")
    # The reference: the simulated dataset with its tracker samples replaced by the
    # frame-synchronous poses the PLUS file holds.
    reference = shutil.copytree(syn.root, tmp_path / "reference")
    write_tracking_csv(reference / "tracking.csv",
                       TrackingSamples(syn.ds.timestamps, syn.T[:, :3, 3], syn.quaternions))

    e_M, G = {}, {}
    for name, root in (("imported", imported), ("reference", reference)):
        out = tmp_path / f"out_{name}"
        run_dataset(root, "ba-emt", out, progress=False, report=False, options=BA_EMT)
        e_M[name] = json.loads((out / "report.json").read_text())["metrics"]["e_M_px"]
        G[name] = read_homographies_csv(out / "homographies.csv")[1]
    assert e_M["imported"] < E_M_TOLERANCE_PX
    assert e_M["imported"] == pytest.approx(e_M["reference"], rel=0, abs=1e-6)
    np.testing.assert_allclose(G["imported"], G["reference"], rtol=0, atol=1e-6)


# --------------------------------------------------------------------------------------------
# A header written by hand as PLUS writes it
# --------------------------------------------------------------------------------------------

FW, FH, FN = 8, 6, 4
TIMES = [14.374, 14.407, 14.441, 14.474]


def _plus_matrix(T: np.ndarray) -> str:
    return " ".join(f"{v:.6g}" for v in T.reshape(-1))


def _tracker_to_probe(k: int) -> np.ndarray:
    """A tracker -> probe pose as PLUS would record it (a probe ~1 m from the tracker)."""
    probe_in_tracker = np.eye(4)
    probe_in_tracker[:3, :3] = Rotation.from_rotvec([0.4 + 0.05 * k, -1.2, 2.0]).as_matrix()
    probe_in_tracker[:3, 3] = [212.75 + 3 * k, -78.33, -1095.6 + k]
    return np.linalg.inv(probe_in_tracker)


def _real_plus_file(path: Path) -> np.ndarray:
    """A PLUS-style RGB recording: extra fields, whitespace variants, TrackerToProbe stored the
    other way round (frame 2 INVALID, its values garbage), a ReferenceToTracker field missing in
    frame 2, frame 1's image INVALID, orientation UN. Returns the pixels as stored."""
    lines = [
        "ObjectType = Image", "NDims = 3", "AnatomicalOrientation = RAI", "BinaryData = True",
        "BinaryDataByteOrderMSB = False", "CenterOfRotation = 0 0 0", "CompressedData = False",
        f"DimSize = {FW} {FH} {FN}", "ElementNumberOfChannels = 3", "ElementSpacing = 1 1 1",
        "ElementType = MET_UCHAR", "Kinds = domain domain list", "Offset = 0 0 0",
        "TransformMatrix = 1 0 0 0 1 0 0 0 1", "UltrasoundImageOrientation = UN",
        "UltrasoundImageType = BRIGHTNESS",
    ]
    for k in range(FN):
        p = f"Seq_Frame{k:04d}_"
        lines.append(f"{p}FrameNumber = {k}")
        if k == 2:
            lines += [f"{p}TrackerToProbeTransform = {' '.join(['0'] * 16)}",
                      f"{p}TrackerToProbeTransformStatus = INVALID"]
        else:
            lines += [f"{p}TrackerToProbeTransform =  {_plus_matrix(_tracker_to_probe(k))}  ",
                      f"{p}TrackerToProbeTransformStatus=OK"]
            lines += [f"{p}ReferenceToTrackerTransform = 1 0 0 {k} 0 1 0 0 0 0 1 0 0 0 0 1",
                      f"{p}ReferenceToTrackerTransformStatus = OK"]
        lines += [f"{p}Timestamp\t= {TIMES[k]}", f"{p}UnfilteredTimestamp = {TIMES[k] + 0.002}",
                  f"{p}ImageStatus = {'INVALID' if k == 1 else 'OK'}"]
    lines.append("ElementDataFile = LOCAL")
    pixels = np.random.default_rng(7).integers(0, 256, (FN, FH, FW, 3), dtype=np.uint8)
    path.write_bytes(("\n".join(lines) + "\n").encode() + pixels.tobytes())
    return pixels


def test_real_plus_header(tmp_path):
    path = tmp_path / "Recording.igs.mha"
    stored = _real_plus_file(path)
    seq = read_plus_sequence(path)
    assert seq.orientation == "UN"
    np.testing.assert_array_equal(seq.images, stored[:, ::-1, ::-1])  # to MF: both flips
    np.testing.assert_array_equal(seq.image_ok, [True, False, True, True])
    np.testing.assert_array_equal(seq.timestamps, TIMES)
    assert sorted(seq.transforms) == ["ReferenceToTrackerTransform", "TrackerToProbeTransform"]
    np.testing.assert_array_equal(seq.transform_status["ReferenceToTrackerTransform"],
                                  [True, True, False, True])  # field missing in frame 2
    assert seq.header["Kinds"] == "domain domain list"
    # None: the single *ToTracker field
    assert seq.transform(None).source == "ReferenceToTrackerTransform"

    out = tmp_path / "ds"
    summary = import_plus_sequence(path, out, camera=Camera(FW, FH), transform="ProbeToTracker")
    assert (summary.transform, summary.inverted) == ("TrackerToProbeTransform", True)
    assert (summary.skipped_frames, summary.invalid_samples) == ([1], [2])
    assert summary.frames == 3 and "skipped frames" in str(summary)
    assert (out / "frames.csv").read_text().splitlines() == [
        "frame,timestamp", "0,14.374", "2,14.441", "3,14.474"]  # sequence indices kept
    ds = read_dataset(out)
    for j, k in enumerate([0, 2, 3]):  # RGB -> BGR, MF
        np.testing.assert_array_equal(ds.frames[j], stored[k, ::-1, ::-1, ::-1])
    probe_in_tracker = np.stack([np.linalg.inv(_tracker_to_probe(k)) for k in range(FN)])
    # 6 significant digits in the file: rotations to ~1e-6, translations (~1 m) to ~0.01 mm
    _check_tracking(out / "tracking.csv", np.array(TIMES), probe_in_tracker,
                    [True, True, False, True], tol=1e-5, tol_mm=0.01)
    assert not (out / "hand_eye.txt").exists()


def test_write_read_status_and_layout_variants(tmp_path):
    images = np.arange(FN * FH * FW, dtype=np.uint8).reshape(FN, FH, FW)
    T = np.tile(np.eye(4), (FN, 1, 1))
    T[:, 0, 3] = np.arange(FN)
    path = write_plus_sequence(tmp_path / "a.mha", images, TIMES, {"ProbeToReferenceTransform": T},
                               status={"ProbeToReference": [True, False, True, True]},
                               image_ok=[True, True, False, True])
    seq = read_plus_sequence(path)
    np.testing.assert_array_equal(seq.transform_status["ProbeToReferenceTransform"],
                                  [True, False, True, True])
    np.testing.assert_array_equal(seq.image_ok, [True, True, False, True])
    selected = seq.transform()  # the single *ToReference field
    assert np.isnan(selected.matrices[1]).all() and selected.matrices[3, 0, 3] == 3.0
    inverse = seq.transform("ReferenceToProbe")
    assert inverse.inverted and inverse.matrices[3, 0, 3] == -3.0

    # NDims 4 with a z dimension of 1 (PLUS's Output2DDataWithZDimensionIncluded)
    _edit(path, r"NDims = 3", "NDims = 4")
    _edit(path, r"DimSize = 8 6 4", "DimSize = 8 6 1 4")
    np.testing.assert_array_equal(read_plus_sequence(path).images, images)

    # .mhd whose data file starts with a 16-byte header (HeaderSize)
    mhd = write_plus_sequence(tmp_path / "b.mhd", images, TIMES)
    raw = tmp_path / "b.raw"
    raw.write_bytes(b"x" * 16 + raw.read_bytes())
    _edit(mhd, r"ElementDataFile", "HeaderSize = 16\nElementDataFile")
    np.testing.assert_array_equal(read_plus_sequence(mhd).images, images)


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------


def _small(tmp_path: Path, suffix: str = ".mha", compress: bool = False, transforms=None,
           status=None, image_ok=None) -> Path:
    """4 grey frames of 8x6 (pixel values < 10, so no header text occurs in the data), the
    sensor 1 mm apart per frame, frame k at k/25 s."""
    images = (np.arange(FN * FH * FW) % 10).astype(np.uint8).reshape(FN, FH, FW)
    if transforms is None:
        T = np.tile(np.eye(4), (FN, 1, 1))
        T[:, :3, 3] = np.array([[k, 2.0, 3.0] for k in range(FN)])
        transforms = {"SensorToTracker": T}
    return write_plus_sequence(tmp_path / f"rec{suffix}", images, np.arange(FN) / 25.0,
                               transforms, status=status, compress=compress, image_ok=image_ok)


def _edit(path: Path, pattern: str, replacement: str) -> None:
    """re.sub (first match) in the header of a sequence file, data left as it is."""
    data = path.read_bytes()
    end = data.index(b"\n", data.index(b"ElementDataFile")) + 1
    header = re.sub(pattern, replacement, data[:end].decode(), count=1)
    path.write_bytes(header.encode() + data[end:])


def _refused(tmp_path: Path, path: Path, match: str, names: str | None = None, **kwargs):
    out = tmp_path / "out"
    kwargs.setdefault("camera", Camera(FW, FH))
    with pytest.raises(ValueError, match=match) as info:
        import_plus_sequence(path, out, **kwargs)
    assert (names or str(path)) in str(info.value)
    assert not out.exists() and not list(tmp_path.glob(".out*"))  # nothing left behind


def _identity_with(k: int, T: np.ndarray):
    transforms = np.tile(np.eye(4), (FN, 1, 1))
    transforms[k] = T
    return {"SensorToTracker": transforms}


def _scaled() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] *= 1.01
    return T


def _far() -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = 2e6  # 2 km
    return T


HEADER_CASES = {  # id: ((pattern, replacement), ...), message
    "no-ElementDataFile": ((r"ElementDataFile = LOCAL\n", ""), "ElementDataFile"),
    "garbage-line": ((r"Offset = 0 0 0", "Offset 0 0 0"), r"line 13 is not a 'Key = Value'"),
    "duplicate-field": ((r"(Seq_Frame0001_Timestamp = .*\n)", r"\1\1"), "repeats line"),
    "no-DimSize": ((r"DimSize = .*\n", ""), "missing DimSize"),
    "no-ElementType": ((r"ElementType = .*\n", ""), "missing ElementType"),
    "NDims-2": ((r"NDims = 3", "NDims = 2"), "DimSize has 3 values but NDims is 2"),
    "NDims-4-volume": ((r"NDims = 3\n(.*\n)*DimSize = 8 6 4", "NDims = 4\nDimSize = 8 3 2 4"),
                       "NDims is 4; supported: 3"),
    "DimSize-unparsable": ((r"DimSize = 8 6 4", "DimSize = 8 x 4"),
                           r"DimSize: cannot parse '8 x 4' as integers"),
    "ElementType-ushort": ((r"MET_UCHAR", "MET_USHORT"),
                           "ElementType MET_USHORT is not supported; supported: MET_UCHAR"),
    "channels-4": ((r"ElementNumberOfChannels = 1", "ElementNumberOfChannels = 4"),
                   "ElementNumberOfChannels 4 is not supported"),
    "ascii-data": ((r"BinaryData = True", "BinaryData = False"), r"ASCII pixel data"),
    "orientation-FM": ((r"UltrasoundImageOrientation = MF", "UltrasoundImageOrientation = FM"),
                       "UltrasoundImageOrientation 'FM' is not supported"),
    "frame-beyond-DimSize": ((r"Seq_Frame0003_FrameNumber", "Seq_Frame0009_FrameNumber"),
                             "frame 9 is beyond DimSize's 4 frames"),
    "timestamp-missing": ((r"Seq_Frame0002_Timestamp = .*\n", ""),
                          r"no Timestamp for frame\(s\) 2"),
    "timestamp-unparsable": ((r"Seq_Frame0002_Timestamp = .*\n",
                              "Seq_Frame0002_Timestamp = 0.08s\n"),
                             r"frame 2 \(Seq_Frame0002_Timestamp\): cannot parse '0.08s'"),
    "timestamp-nan": ((r"Seq_Frame0002_Timestamp = .*\n", "Seq_Frame0002_Timestamp = nan\n"),
                      r"frame\(s\) 2: timestamp is not finite"),
    "timestamp-not-increasing": ((r"Seq_Frame0002_Timestamp = .*\n",
                                  "Seq_Frame0002_Timestamp = 0.04\n"),
                                 "frame 2: timestamp 0.04 is not after frame 1's 0.04"),
    "transform-15-numbers": ((r"(Seq_Frame0001_SensorToTrackerTransform = .*) 1.0\n", r"\1\n"),
                             r"frame 1 \(Seq_Frame0001_SensorToTrackerTransform\): cannot parse "
                             r"'.*' as 16 numbers"),
    "transform-nan": ((r"(Seq_Frame0001_SensorToTrackerTransform = )1.0", r"\1nan"),
                      r"frame 1 \(Seq_Frame0001_SensorToTrackerTransform\): status OK but the "
                      "transform has NaN or inf"),
}


@pytest.mark.parametrize("case", HEADER_CASES, ids=list(HEADER_CASES))
def test_bad_header(tmp_path, case):
    edit, match = HEADER_CASES[case]
    path = _small(tmp_path)
    _edit(path, *edit)
    _refused(tmp_path, path, match)


@pytest.mark.parametrize("start, what", [
    (b"NRRD0004\n# Complete NRRD file format specification at:\n", r"a NRRD file"),
    (b"PK\x03\x04\x14\x00\x00\x00\x08\x00", r"a zip archive \(e\.g\. a 3D Slicer \.mrb")])
def test_nrrd_and_mrb_sequences_are_named_as_such(tmp_path, start, what):
    """A PLUS / Slicer .seq.nrrd or a Slicer .mrb was refused as "line 1 is not a 'Key =
    Value' header line" (with zip bytes in the message)."""
    path = tmp_path / "scan.seq.mha"
    path.write_bytes(start + bytes(range(256)))
    _refused(tmp_path, path, what + r".*, not a MetaImage sequence; only PLUS \.mha / \.mhd")


def test_bad_data(tmp_path):
    _refused(tmp_path, tmp_path / "nope.seq.mha", "file not found", names="nope.seq.mha")
    path = _small(tmp_path)
    data = path.read_bytes()
    path.write_bytes(data[:-10])
    _refused(tmp_path, path, "image data is 182 bytes but DimSize 8 6 4 with 1 channel.* needs "
             "192 bytes: truncated")
    path.write_bytes(data + b"\0" * 5)
    _refused(tmp_path, path, "197 bytes but .* needs 192 bytes: longer than DimSize says")

    mhd = _small(tmp_path, ".mhd")
    raw = tmp_path / "rec.raw"
    raw.write_bytes(raw.read_bytes()[:100])
    _refused(tmp_path, mhd, r"image data \(.*rec.raw\) is 100 bytes but .* needs 192 bytes")
    raw.unlink()
    _refused(tmp_path, mhd, "ElementDataFile 'rec.raw': .*rec.raw not found")

    zipped = _small(tmp_path, ".mha", compress=True)
    good = zipped.read_bytes()
    _edit(zipped, r"CompressedDataSize = (\d+)", "CompressedDataSize = 9999")
    _refused(tmp_path, zipped, r"compressed image data is \d+ bytes but CompressedDataSize says "
             "9999")
    zipped.write_bytes(good[:-20] + bytes(20))  # a corrupt stream
    _refused(tmp_path, zipped, "cannot decompress the image data")
    zipped.write_bytes(good)
    _edit(zipped, r"DimSize = 8 6 4", "DimSize = 8 6 5")  # the stream is one frame short
    _refused(tmp_path, zipped, "decompressed image data is 192 bytes but DimSize 8 6 5 .* needs "
             "240 bytes")
    zipped.write_bytes(good)
    _edit(zipped, r"DimSize = 8 6 4", "DimSize = 8 6 3")
    _refused(tmp_path, zipped, "decompressed image data is more than 144 bytes")


def test_data_on_the_element_data_file_line_is_named_and_cut_short(tmp_path):
    """Review A #6: with the line break after `ElementDataFile = LOCAL` missing, the data
    follows on that line: it was diagnosed as "LIST or a pattern" (the pixels held a '%') or
    a data file not found, with the whole line of binary data quoted."""
    path = _small(tmp_path)
    data = path.read_bytes()
    end = data.index(b"\n", data.index(b"ElementDataFile"))
    big = (np.arange(5000) % 256).astype(np.uint8).tobytes().replace(b"\n", b"%")
    for tail in (data[end + 1:], big):
        path.write_bytes(data[:end] + tail)
        with pytest.raises(ValueError) as info:
            import_plus_sequence(path, tmp_path / "out", camera=Camera(FW, FH))
        message = str(info.value)
        assert message.startswith(f"{path}: line ") and (
            ": the ElementDataFile line is not terminated: the image data follows LOCAL on the "
            "same line ('LOCAL\\x00\\x01") in message, message
        assert "LIST" not in message and "not found" not in message
        assert len(message) < len(str(path)) + 400  # (was the whole line of data)
        assert not (tmp_path / "out").exists()
    # binary data where a file name goes: not LOCAL or a file name
    mhd = _small(tmp_path, ".mhd")
    data = mhd.read_bytes()
    mhd.write_bytes(data.replace(b"ElementDataFile = rec.raw", b"ElementDataFile = \x01%" + big))
    _refused(tmp_path, mhd, r"line \d+: ElementDataFile '\\x01%\\x00\\x01.*'\.\.\. \(\d+ "
             r"characters\) is not LOCAL or a file name \(binary data: the line is not "
             r"terminated, or the header is damaged\)$")

def test_bad_transforms_camera_and_hand_eye(tmp_path):
    path = _small(tmp_path)
    _refused(tmp_path, path, "no ProbeToTrackerTransform field \\(nor its inverse\\); transforms "
             "present: SensorToTrackerTransform", transform="ProbeToTracker")
    _refused(tmp_path, path, r"images are 8x6 but .* says 10x6", camera=Camera(10, FH))
    bad_hand_eye = _scaled()
    _refused(tmp_path, path, "hand_eye: not a rigid transform", names="hand_eye",
             hand_eye=bad_hand_eye)

    two = {"SensorToTracker": np.tile(np.eye(4), (FN, 1, 1)),
           "StylusToTracker": np.tile(np.eye(4), (FN, 1, 1))}
    _refused(tmp_path, _small(tmp_path, transforms=two),
             r"several \*ToTrackerTransform .*\(SensorToTrackerTransform, "
             "StylusToTrackerTransform present\\)", transform=None)
    none = {"ImageToProbe": np.tile(np.eye(4), (FN, 1, 1))}
    _refused(tmp_path, _small(tmp_path, transforms=none),
             r"no \*ToTrackerTransform .*\(ImageToProbeTransform present\)", transform=None)

    _refused(tmp_path, _small(tmp_path, transforms=_identity_with(1, _scaled())),
             r"frame 1 \(Seq_Frame0001_SensorToTrackerTransform\): not a rigid transform: the "
             r"rotation block's columns have norms .*not 1 \(scaled\)")
    _refused(tmp_path, _small(tmp_path, transforms=_identity_with(2, _far())),
             r"frame 2 \(Seq_Frame0002_SensorToTrackerTransform\): translation beyond the 1e\+06 "
             "mm bound")
    # the same values with status INVALID are not samples: not checked
    status = {"SensorToTracker": [True, True, False, True]}
    summary = import_plus_sequence(
        _small(tmp_path, transforms=_identity_with(2, _far()), status=status), tmp_path / "ok",
        camera=Camera(FW, FH))
    assert summary.invalid_samples == [2]

    _refused(tmp_path, _small(tmp_path, status={"SensorToTracker": [False, True, False, False]}),
             r"SensorToTrackerTransform: 1 frame\(s\) with status OK; tracking needs at least 2")
    _refused(tmp_path, _small(tmp_path, image_ok=[False] * FN), "no frame has ImageStatus OK")


def test_auto_transform_message_reads_right_for_the_cli_and_python(tmp_path, capsys):
    """The 'name it' hint gives the flag and the keyword, with a field of the file as example."""
    from fusedmosaic.cli import main

    two = {"SensorToTracker": np.tile(np.eye(4), (FN, 1, 1)),
           "StylusToTracker": np.tile(np.eye(4), (FN, 1, 1))}
    path = _small(tmp_path, transforms=two)
    _refused(tmp_path, path, r"name the transform to import, e\.g\. --transform SensorToTracker "
             r"\(transform='SensorToTracker' in Python; a transform stored the other way round "
             r"is inverted\)$", transform=None)
    assert main(["import", str(path), str(tmp_path / "cli"), "--transform", "auto"]) == 2
    assert "e.g. --transform SensorToTracker (transform=" in capsys.readouterr().err
    assert not (tmp_path / "cli").exists()


def test_a_failed_import_leaves_no_folder_it_created(tmp_path, monkeypatch, capsys):
    """Review A #4: the up-front check created OUT's parents (and write_dataset creates them
    while writing), and a failed import left them: newp/a after `import bad.mha newp/a/b`.
    Folders that existed before stay."""
    import fusedmosaic.io.dataset as dataset_module
    from fusedmosaic.cli import main

    path = _small(tmp_path)
    good = path.read_bytes()
    path.write_bytes(good[:-10])
    before = sorted(p.name for p in tmp_path.iterdir())
    assert main(["import", str(path), str(tmp_path / "newp" / "a" / "b")]) == 2
    assert "image data is 182 bytes but" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no newp/
    # a failure while the frames are written (write_dataset has made the parents by then)
    path.write_bytes(good)
    (tmp_path / "pre").mkdir()

    def failing(folder, frames):
        raise ValueError(f"{folder}: disk full")

    monkeypatch.setattr(dataset_module, "write_frames", failing)
    assert main(["import", str(path), str(tmp_path / "pre" / "x" / "y")]) == 2
    assert "disk full" in capsys.readouterr().err
    assert (tmp_path / "pre").is_dir() and not list((tmp_path / "pre").iterdir())


def test_video_without_transform_fields_is_imported_without_tracking(tmp_path, capsys):
    """A recording without a tracker (no transform field at all) becomes a dataset without
    tracking.csv, said in the summary, whatever transform names; calibrate-style reading works.
    With transforms present, a name that is not among them is still refused."""
    from fusedmosaic.cli import main

    path = _small(tmp_path, transforms={})
    assert read_plus_sequence(path).transforms == {}
    for transform in ("SensorToTracker", None, "ProbeToTracker"):
        out = tmp_path / f"ds_{transform}"
        summary = import_plus_sequence(path, out, camera=None, transform=transform)
        assert summary.transform is None and not summary.inverted
        assert summary.frames == FN and summary.invalid_samples == []
        assert sorted(p.name for p in out.iterdir()) == ["camera.yaml", "frames", "frames.csv"]
        assert "no tracking.csv: the sequence has no transform field" in str(summary)
        ds = read_dataset(out)
        assert ds.tracking is None and len(ds) == FN
        np.testing.assert_array_equal(ds.timestamps, np.arange(FN) / 25.0)
    _refused(tmp_path, path, r"transform name must be a non-empty string, got ''", transform="")
    assert main(["import", str(path), str(tmp_path / "cli")]) == 0
    assert "; no tracking.csv: the sequence has no transform field" in capsys.readouterr().out
    assert not (tmp_path / "cli" / "tracking.csv").exists()
    _refused(tmp_path, _small(tmp_path), "no ProbeToTrackerTransform field",
             transform="ProbeToTracker")


@pytest.mark.parametrize("suffix", [".mha", ".mhd"])
def test_non_ascii_names_round_trip(tmp_path, suffix):
    """The header is UTF-8: a name with accents or spaces is written and read back."""
    folder = tmp_path / "données ü"
    folder.mkdir()
    images = (np.arange(FN * FH * FW) % 10).astype(np.uint8).reshape(FN, FH, FW)
    path = write_plus_sequence(folder / f"rec ü{suffix}", images, np.arange(FN) / 25.0,
                               {"SensorToTracker": np.tile(np.eye(4), (FN, 1, 1))})
    if suffix == ".mhd":
        assert "ElementDataFile = rec ü.raw\n".encode() in path.read_bytes()
        assert (folder / "rec ü.raw").is_file()
    np.testing.assert_array_equal(read_plus_sequence(path).images, images)
    summary = import_plus_sequence(path, tmp_path / "ds", camera=None)
    assert summary.frames == FN and (tmp_path / "ds" / "tracking.csv").is_file()


@pytest.mark.parametrize("encoding", ["utf-8", "latin-1"], ids=["utf8", "windows"])
def test_data_file_name_in_utf8_or_the_windows_code_page(tmp_path, encoding):
    """ElementDataFile naming 'données ü.raw' in UTF-8 (PLUS on Linux, this writer) or in the
    ANSI code page (PLUS on Windows: not valid UTF-8, read as latin-1) finds the data file."""
    path = _small(tmp_path, ".mhd")
    images = read_plus_sequence(path).images.copy()
    (tmp_path / "rec.raw").rename(tmp_path / "données ü.raw")
    data = path.read_bytes().replace(b"ElementDataFile = rec.raw",
                                     "ElementDataFile = données ü.raw".encode(encoding))
    assert data.count("données ü.raw".encode(encoding)) == 1
    (tmp_path / "named.mhd").write_bytes(data)
    seq = read_plus_sequence(tmp_path / "named.mhd")
    assert seq.header["ElementDataFile"] == "données ü.raw"
    np.testing.assert_array_equal(seq.images, images)


def test_mhd_names_the_header_cannot_hold_are_refused(tmp_path):
    images = np.zeros((FN, FH, FW), np.uint8)
    for name, match in ((" rec.mhd", "leading or trailing spaces"),
                        ("rec\udcff.mhd", "not valid Unicode text")):
        with pytest.raises(ValueError, match=match):
            write_plus_sequence(tmp_path / name, images, np.arange(FN) / 25.0)
    assert list(tmp_path.iterdir()) == []


def test_existing_folder_is_kept(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    with pytest.raises(ValueError, match="exists and is not empty"):
        import_plus_sequence(_small(tmp_path), out, camera=Camera(FW, FH))
    assert [p.name for p in out.iterdir()] == ["mine.txt"]


def test_compressed_stream_is_zlib(tmp_path):
    """CompressedData is one zlib stream of all frames (what PLUS's deflate writes)."""
    path = _small(tmp_path, compress=True)
    data = path.read_bytes()
    start = data.index(b"\n", data.index(b"ElementDataFile")) + 1
    pixels = zlib.decompress(data[start:])
    np.testing.assert_array_equal(np.frombuffer(pixels, np.uint8).reshape(FN, FH, FW),
                                  read_plus_sequence(path).images)


def test_cli_import(syn, tmp_path, capsys):
    """`fusedmosaic import`: the summary line, files readable with normal permissions, and a
    bad transform name refused with the fields present (exit 2, no folder)."""
    from fusedmosaic.cli import main

    seq = write_plus_sequence(tmp_path / "rec.igs.mha", syn.bgr[..., ::-1], syn.ds.timestamps,
                              {"SensorToTracker": syn.T})
    assert seq.stat().st_mode & 0o044 == 0o044  # readable by others, as a normal write
    camera = str(syn.root / "camera.yaml")
    assert main(["import", str(seq), str(tmp_path / "ds"), "--camera", camera]) == 0
    out = capsys.readouterr().out
    assert f"imported {tmp_path / 'ds'}: {len(syn.ds)} frames 200x200 RGB->BGR" in out
    np.testing.assert_array_equal(read_dataset(tmp_path / "ds").frames[3], syn.bgr[3])
    assert main(["import", str(seq), str(tmp_path / "ds2"), "--camera", camera,
                 "--transform", "ProbeToTracker"]) == 2
    err = capsys.readouterr().err
    assert "no ProbeToTrackerTransform field (nor its inverse); transforms present: " \
           "SensorToTrackerTransform" in err
    assert not (tmp_path / "ds2").exists()
    assert main(["import", str(seq), str(tmp_path / "ds3"), "--camera", camera,
                 "--transform", "auto", "--quiet"]) == 0


def test_header_variants_plus_itself_accepts(tmp_path):
    """A UTF-8 BOM, `ElementDataFile = Local`, a transform name with '-', and a sample marked
    missing whose numbers do not parse ('-nan(ind)', as MSVC prints NaN) are read as PLUS reads
    them."""
    path = _small(tmp_path)
    _edit(path, r"ElementDataFile = LOCAL", "ElementDataFile = Local")
    _edit(path, r"Seq_Frame0001_SensorToTrackerTransform = [^\n]*",
          "Seq_Frame0001_SensorToTrackerTransform = -nan(ind) -nan(ind)\n"
          "Seq_Frame0001_Probe-SequenceTransform = 1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1")
    _edit(path, r"Seq_Frame0001_SensorToTrackerTransformStatus = OK",
          "Seq_Frame0001_SensorToTrackerTransformStatus = INVALID")
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    seq = read_plus_sequence(path)
    assert seq.images.shape == (FN, FH, FW)
    ok = seq.transform_status["SensorToTrackerTransform"]
    assert ok.tolist() == [True, False, True, True]
    assert "Probe-SequenceTransform" in seq.transforms


def test_compressed_import_memory_is_the_images(tmp_path):
    """zlib data is inflated chunk by chunk into one array (not file + copy + copy)."""
    images = np.random.default_rng(0).integers(0, 255, (12, 64, 80), dtype=np.uint8)
    path = write_plus_sequence(tmp_path / "z.mha", images, np.arange(12) / 25.0, compress=True)
    np.testing.assert_array_equal(read_plus_sequence(path).images, images)


def test_overwrite_never_deletes_the_inputs(tmp_path, capsys):
    """--overwrite into the folder that holds the recording (with its camera.yaml beside it) is
    refused before anything is written."""
    from fusedmosaic.cli import main
    from fusedmosaic.io.calibration import write_camera_yaml

    folder = tmp_path / "session"
    folder.mkdir()
    path = _small(folder)
    write_camera_yaml(folder / "camera.yaml", Camera(FW, FH))
    assert main(["import", str(path), str(folder), "--camera", str(folder / "camera.yaml"),
                 "--overwrite"]) == 2
    assert "an input of this import, which overwriting would delete" in capsys.readouterr().err
    assert path.is_file() and (folder / "camera.yaml").is_file()
    # without --overwrite the message names the flag, not the Python keyword
    assert main(["import", str(path), str(folder), "--camera", str(folder / "camera.yaml")]) == 2
    assert "pass --overwrite" in capsys.readouterr().err


def test_dimsize_by_kinds(tmp_path):
    """IGSIO (PLUS's writer) lists colour frames as DimSize = 3 W H 1 N with Kinds = vector
    domain domain domain list: read as W x H x N RGB."""
    rgb = (np.arange(FN * FH * FW * 3) % 7).astype(np.uint8).reshape(FN, FH, FW, 3)
    path = write_plus_sequence(tmp_path / "c.mha", rgb, np.arange(FN) / 25.0)
    _edit(path, r"DimSize = [^\n]*", f"DimSize = 3 {FW} {FH} 1 {FN}")
    _edit(path, r"Kinds = [^\n]*", "Kinds = vector domain domain domain list")
    np.testing.assert_array_equal(read_plus_sequence(path).images, rgb)
    _edit(path, r"Kinds = [^\n]*", "Kinds = vector domain domain domain domain")
    with pytest.raises(ValueError, match="expected 2-D frames"):
        read_plus_sequence(path)


def test_import_with_tracker_time_offset(tmp_path, capsys):
    """--tracker-time-offset S writes tracking.csv on the video's clock (timestamps - S); a
    bad value is refused naming the flag, before anything is written."""
    from fusedmosaic.cli import main
    from fusedmosaic.io import read_tracking_csv

    seq = _small(tmp_path)
    assert main(["import", str(seq), str(tmp_path / "a"), "--quiet"]) == 0
    assert main(["import", str(seq), str(tmp_path / "b"), "--quiet",
                 "--tracker-time-offset", "0.03"]) == 0
    a = read_tracking_csv(tmp_path / "a" / "tracking.csv")
    b = read_tracking_csv(tmp_path / "b" / "tracking.csv")
    np.testing.assert_allclose(b.timestamps, a.timestamps - 0.03, atol=1e-12)
    np.testing.assert_array_equal(b.translations, a.translations)
    assert main(["import", str(seq), str(tmp_path / "c"), "--tracker-time-offset", "nan"]) == 2
    assert "--tracker-time-offset: expected seconds within +-10, got nan" in \
        capsys.readouterr().err
    assert not (tmp_path / "c").exists()
    # an offset that moves every sample away from the frames is an error (it was a note on a
    # dataset no tracked method could read), naming the shift and both spans
    assert main(["import", str(seq), str(tmp_path / "d"), "--tracker-time-offset", "5"]) == 2
    err = capsys.readouterr().err
    assert "rec.mha: SensorToTrackerTransform shifted by -5 s (tracker time offset 5 s) " \
           "spans [-5, -4.88] s, outside every frame's time ([0, 0.12] s): no frame would be " \
           "tracked; check the offset (calibrate measures it)" in err, err
    assert not (tmp_path / "d").exists()


def test_a_broken_transform_blocks_only_its_own_import(tmp_path):
    """A field of another tool whose sample cannot be read (15 numbers) does not block importing
    the selected transform; selecting it (or its inverse) is refused naming the frame and key."""
    T = np.tile(np.eye(4), (FN, 1, 1))
    T[:, :3, 3] = np.array([[k, 2.0, 3.0] for k in range(FN)])
    path = _small(tmp_path, transforms={"ProbeToTracker": T, "StylusToTracker": T})
    _edit(path, r"(Seq_Frame0002_StylusToTrackerTransform = .*) 1.0\n", r"\1\n")
    summary = import_plus_sequence(path, tmp_path / "ds", camera=Camera(FW, FH),
                                   transform="ProbeToTracker")
    assert summary.transform == "ProbeToTrackerTransform" and summary.invalid_samples == []
    for name in ("StylusToTracker", "TrackerToStylus"):
        _refused(tmp_path, path, r"frame 2 \(Seq_Frame0002_StylusToTrackerTransform\): cannot "
                 r"parse '.*' as 16 numbers", transform=name)


def test_missing_default_transform_names_the_next_step(tmp_path):
    """The default SensorToTracker absent: the message names the field to import instead."""
    T = np.tile(np.eye(4), (FN, 1, 1))
    _refused(tmp_path, _small(tmp_path, transforms={"ProbeToTracker": T}),
             r"no SensorToTrackerTransform field \(nor its inverse\); transforms present: "
             r"ProbeToTrackerTransform; import it with --transform ProbeToTracker "
             r"\(transform='ProbeToTracker' in Python\)$")
    two = {"ProbeToTracker": T, "StylusToReference": T}
    _refused(tmp_path, _small(tmp_path, transforms=two),
             r"transforms present: ProbeToTrackerTransform, StylusToReferenceTransform; name the "
             r"one to import, e\.g\. --transform ProbeToTracker \(transform='ProbeToTracker' in "
             r"Python\)$")


def test_import_refuses_what_run_would_refuse(tmp_path):
    """Frame times in ms or a day's jump, and a transposed camera_matrix, are refused at import
    (run refused the written dataset), naming the sequence's key / the user's camera.yaml."""
    path = _small(tmp_path)
    good = path.read_bytes()
    for k in range(FN):  # k/25 s written in ms
        _edit(path, rf"Seq_Frame{k:04d}_Timestamp = .*\n",
              f"Seq_Frame{k:04d}_Timestamp = {k * 40}\n")
    _refused(tmp_path, path, r"frames come every 40 s \(median spacing; e\.g\. rows "
             r"Seq_Frame0000_Timestamp and Seq_Frame0001_Timestamp are 40 s apart\), more than "
             r"MAX_FRAME_SPACING_S .*\(the sequence's timestamps, which frames\.csv would hold: "
             r"`run` would refuse the dataset\)")
    path.write_bytes(good)
    for k in (2, 3):  # two days' pause
        _edit(path, rf"Seq_Frame{k:04d}_Timestamp = .*\n",
              f"Seq_Frame{k:04d}_Timestamp = {172800 + k / 25}\n")
    _refused(tmp_path, path, r"rec\.mha: row Seq_Frame0002_Timestamp: timestamp 172800\.08 is "
             r"172800\.040 s after the previous row's, more than MAX_FRAME_GAP_S")

    camera = tmp_path / "camera.yaml"

    def write_camera(K):
        camera.write_text(f"%YAML:1.0\n---\nimage_width: {FW}\nimage_height: {FH}\n"
                          f"camera_matrix: [{', '.join(map(str, np.ravel(K)))}]\n")

    K = np.array([[100.0, 0, 3.5], [0, 100.0, 2.5], [0, 0, 1]])
    write_camera(K.T)
    _refused(tmp_path, _small(tmp_path), r"camera\.yaml: camera_matrix: last row must be 0 0 1 .*"
             r"\(the matrix looks transposed\): the pose methods \(ba, ba-emt, lba-emt, emt\) "
             "would refuse the dataset", names=str(camera), camera=camera)
    write_camera(2 * K)  # last row 0 0 2: divided by 2, as run takes it
    import_plus_sequence(_small(tmp_path), tmp_path / "ok", camera=camera)


def test_missing_samples_at_the_start_and_a_clock_offset(tmp_path, capsys):
    """A sensor entering the field late (the first samples MISSING): the dataset reads, those
    frames flagged untracked (run refused it whole). An offset shifting tracking.csv off the
    last frame: the summary says run needs --allow-untracked, and why."""
    from fusedmosaic.cli import main

    T = np.tile(np.eye(4), (FN, 1, 1))
    path = _small(tmp_path, transforms={"ProbeToTracker": T},
                  status={"ProbeToTracker": [False, True, True, True]})
    summary = import_plus_sequence(path, tmp_path / "late", camera=Camera(FW, FH),
                                   transform="ProbeToTracker")
    assert (summary.invalid_samples, summary.untracked_frames) == ([0], [])
    np.testing.assert_array_equal(read_dataset(tmp_path / "late").pose_valid,
                                  [False, True, True, True])

    assert main(["import", str(_small(tmp_path)), str(tmp_path / "shifted"),
                 "--tracker-time-offset", "0.03"]) == 0
    assert ("; frames outside the tracker's time span (tracking.csv shifted by -0.03 s, the "
            "tracker time offset): 3; `fusedmosaic run` refuses the dataset unless "
            "--allow-untracked, which flags them untracked") in capsys.readouterr().out
    with pytest.raises(ValueError, match="1 frames outside the tracker's time span"):
        read_dataset(tmp_path / "shifted")
    np.testing.assert_array_equal(
        read_dataset(tmp_path / "shifted", allow_untracked=True).pose_valid,
        [True, True, True, False])
