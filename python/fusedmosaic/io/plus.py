"""PLUS toolkit sequence metafiles (``*.seq.mha`` / ``*.igs.mha``, or ``.mhd`` + raw data):
reader, writer, and import into the dataset contract (design.md, "Dataset contract").

A sequence metafile is a MetaImage file: ``Key = Value`` text lines, the last one
``ElementDataFile`` (``LOCAL``: the pixel data follows that line's newline; else a file name
relative to the header), then W*H*channels*N bytes, frame-major and row-major within a frame
(RGB for 3 channels; zlib-compressed as one buffer with ``CompressedData = True``). Per-frame
fields are ``Seq_Frame<index>_<Name> = <value>``:

- ``Timestamp`` (s);
- ``ImageStatus``: absent or ``OK`` = the frame has an image;
- ``<X>To<Y>Transform``: 16 numbers, a row-major 4x4 mapping points from X's coordinates into
  Y's (mm), so ``SensorToTrackerTransform`` is the dataset's tracker_from_sensor;
- ``<X>To<Y>TransformStatus``: anything but ``OK`` = no sample (absent = ``OK`` when the
  transform is there).

``UltrasoundImageOrientation`` (absent = ``MF``) is converted to ``MF``, PLUS's own storage
order: first letter ``U`` = the columns are mirrored (flip left-right), second letter ``N`` = the
rows are (flip up-down). PLUS recordings are frame-synchronous: the importer writes one tracker
sample per frame, at the frame's timestamp.

The header is written in UTF-8 and read as UTF-8, a line that is not valid UTF-8 as latin-1
(PLUS on Windows writes the data file's name in the ANSI code page).
"""

from __future__ import annotations

import json
import os
import re
import tempfile
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from fusedmosaic.io._table import require_file
from fusedmosaic.io.calibration import Camera, read_camera_yaml
from fusedmosaic.io.dataset import _check_frame_times, created_mode, write_dataset
from fusedmosaic.io.tracking import (
    MAX_FRAME_SPACING_S,
    MAX_TIMESTAMP_S,
    MAX_TRANSLATION_MM,
    TrackingSamples,
    _time,
    check_time_offset,
    hand_eye_matrix,
    rigid_defects,
    rigid_problems,
    shift_tracking,
)

__all__ = [
    "IMPORT_RECORD",
    "ImportSummary",
    "PlusSequence",
    "SelectedTransform",
    "applied_tracker_time_offset",
    "import_plus_sequence",
    "read_plus_sequence",
    "write_plus_sequence",
]

SUPPORTED_ELEMENT_TYPES = ("MET_UCHAR",)
SUPPORTED_CHANNELS = (1, 3)
# UltrasoundImageOrientation -> (flip left-right, flip up-down) that gives MF. The transposed
# codes (FM, FU, ...: RF data) and 3-D ones are refused.
ORIENTATIONS = {"MF": (False, False), "MN": (False, True), "UF": (True, False), "UN": (True, True)}
# A tracker rotation block must be orthonormal with det +1 to this (PLUS writes ~6 digits).
RIGID_TOLERANCE = 1e-3
FRAME_PREFIX = "Seq_Frame"
_FRAME_KEY = re.compile(r"Seq_Frame(\d+)_(\S+)\Z")
_MAX_HEADER_LINE = 1 << 20  # bytes; longer means binary data, not a header line
_SHOWN = 5  # frames listed in a message
# What import writes into the dataset when it shifted tracking.csv by a tracker time offset
# (applied_tracker_time_offset reads it).
IMPORT_RECORD = "import.json"
# deflate's largest compression ratio is ~1032:1 (a 258-byte match per 2-bit code); a margin
# above it for the stream's header and trailer
MAX_ZLIB_RATIO = 1100


def _transform_field(name: str) -> str:
    """``ProbeToTracker`` or ``ProbeToTrackerTransform`` -> ``ProbeToTrackerTransform``."""
    return name if name.endswith("Transform") else name + "Transform"


def _frames_text(indices) -> str:
    indices = [int(i) for i in indices]
    shown = ", ".join(map(str, indices[:_SHOWN]))
    return shown + (f" and {len(indices) - _SHOWN} more" if len(indices) > _SHOWN else "")


@dataclass(eq=False)
class SelectedTransform:
    """A transform of every frame, in the requested direction.

    name : the requested field (``SensorToTrackerTransform``); source : the field read (the same,
    or its inverse ``TrackerToSensorTransform`` when ``inverted``); matrices : (N, 4, 4) float64,
    NaN where ``ok`` is False; ok : (N,) bool, status OK (the matrices of those frames are
    checked rigid, finite and within MAX_TRANSLATION_MM).
    """

    name: str
    source: str
    inverted: bool
    matrices: np.ndarray
    ok: np.ndarray


@dataclass(eq=False)
class PlusSequence:
    """A PLUS sequence metafile read by :func:`read_plus_sequence`.

    images : (N, H, W) or (N, H, W, 3) uint8 in the file's channel order (RGB), converted to the
        MF orientation. Uncompressed data is a read-only ``np.memmap`` (or a flipped view of
        one): nothing is loaded until a frame is indexed. Compressed data is decompressed once.
    timestamps : (N,) float64 s, finite and strictly increasing.
    transforms : field name (``ProbeToTrackerTransform``) -> (N, 4, 4) float64 as written (NaN
        where the frame has no such field); transform_status : the same names -> (N,) bool, True
        where the status is OK.
    image_ok : (N,) bool, False where ImageStatus is not OK (no image for that frame).
    orientation : the file's UltrasoundImageOrientation (the images are already MF).
    header : the non-frame header fields, as text.
    transform_errors : field name -> why it cannot be read (its first sample with status OK
        that is not 16 numbers, left NaN in ``transforms``); :meth:`transform` raises it when
        that field is the one selected, so a broken field of another tool blocks nothing.
    """

    path: Path
    images: np.ndarray
    timestamps: np.ndarray
    transforms: dict[str, np.ndarray]
    transform_status: dict[str, np.ndarray]
    image_ok: np.ndarray
    channels: int
    width: int
    height: int
    orientation: str = "MF"
    header: dict[str, str] = field(default_factory=dict, repr=False)
    transform_errors: dict[str, str] = field(default_factory=dict, repr=False)
    _fields: list[dict[str, str]] = field(default_factory=list, repr=False)

    def __len__(self) -> int:
        return self.timestamps.size

    def transform(self, name: str | None = None) -> SelectedTransform:
        """The transform ``name`` (``SensorToTracker`` or ``SensorToTrackerTransform``) of every
        frame. A field stored the other way round (``TrackerToSensorTransform``) is inverted.
        None picks the single ``*ToTrackerTransform`` or ``*ToReferenceTransform`` field.
        Frames with status OK are checked: finite, rotation block orthonormal with det +1 (to
        RIGID_TOLERANCE), last row 0 0 0 1, translation within MAX_TRANSLATION_MM. ValueError
        naming the file (and the frame and field) otherwise."""
        available = ", ".join(self.transforms) or "none"
        candidates = [
            n for n in self.transforms if re.search(r"To(Tracker|Reference)Transform\Z", n)
        ]
        if name is None:
            if len(candidates) != 1:
                problem = "several" if candidates else "no"
                example = (candidates or list(self.transforms) or ["ProbeToTrackerTransform"])[0]
                example = example.removesuffix("Transform")
                raise ValueError(
                    f"{self.path}: {problem} *ToTrackerTransform / *ToReferenceTransform fields "
                    f"({available} present); name the transform to import, e.g. --transform "
                    f"{example} (transform='{example}' in Python; a transform stored the other "
                    "way round is inverted)"
                )
            name = candidates[0]
        if not isinstance(name, str) or not name:
            raise ValueError(f"{self.path}: transform name must be a non-empty string, got "
                             f"{name!r}")
        name = _transform_field(name)
        source, inverted = name, False
        if name not in self.transforms:
            source = next((n for n in self.transforms if name in _inverse_names(n)), None)
            if source is None:
                hint = ""
                if self.transforms:  # the next step: a field of the file to name
                    example = (candidates or list(self.transforms))[0].removesuffix("Transform")
                    hint = (f"; import it with --transform {example}" if len(candidates) == 1
                            else f"; name the one to import, e.g. --transform {example}")
                    hint += f" (transform='{example}' in Python)"
                raise ValueError(
                    f"{self.path}: no {name} field (nor its inverse); transforms present: "
                    f"{available}{hint}"
                )
            inverted = True
        if source in self.transform_errors:  # selected, and a sample cannot be read
            raise ValueError(self.transform_errors[source])
        ok = self.transform_status[source].copy()
        matrices = self.transforms[source].copy()
        _check_rigid(self, source, matrices, ok)
        matrices[~ok] = np.nan
        if inverted and ok.any():  # rigid inverse of the nearest rotation (the file has ~6 digits)
            R = Rotation.from_matrix(matrices[ok, :3, :3]).inv().as_matrix()
            matrices[ok, :3, :3] = R
            matrices[ok, :3, 3] = -np.einsum("nij,nj->ni", R, matrices[ok, :3, 3])
            matrices[ok, 3] = [0.0, 0.0, 0.0, 1.0]
        return SelectedTransform(name, source, inverted, matrices, ok)

    def _key(self, index: int, name: str) -> str:
        """The field's key as written in the file (its frame index padding), for messages."""
        keys = self._fields[index] if index < len(self._fields) else {}
        return keys.get(name, f"{FRAME_PREFIX}{index:04d}_{name}")


def _inverse_names(field_name: str) -> set[str]:
    """``AToBTransform`` -> {``BToATransform``}; every split at a ``To`` leaving two non-empty
    names counts (``ProbeToTooltipTransform`` -> ``TooltipToProbeTransform`` and
    ``oltipToProbeToTransform``): only names present in the file are ever matched."""
    stem = field_name.removesuffix("Transform")
    return {
        f"{stem[i + 2:]}To{stem[:i]}Transform"
        for i in range(1, len(stem) - 2)
        if stem.startswith("To", i)
    }


def _check_rigid(seq: PlusSequence, source: str, matrices: np.ndarray, ok: np.ndarray) -> None:
    def fail(mask: np.ndarray, problem) -> None:
        bad = np.flatnonzero(mask)
        if bad.size:
            i = int(bad[0])
            more = f" ({bad.size} frames: {_frames_text(bad)})" if bad.size > 1 else ""
            problem = problem(i) if callable(problem) else problem
            raise ValueError(f"{seq.path}: frame {i} ({seq._key(i, source)}): {problem}{more}")

    not_finite, not_rigid, far = rigid_problems(matrices, RIGID_TOLERANCE)
    fail(ok & not_finite, "status OK but the transform has NaN or inf values")
    fail(
        ok & not_rigid,
        lambda i: f"not a rigid transform: {rigid_defects(matrices[i], RIGID_TOLERANCE)}",
    )
    fail(
        ok & far,
        f"translation beyond the {MAX_TRANSLATION_MM:g} mm bound (1 km), not physical "
        "(translations must be mm)",
    )


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


def _read_header(path: Path) -> tuple[dict[str, tuple[str, int]], dict[int, dict], int]:
    """Header fields {key: (value, line)}, frame fields {index: {name: (value, line, key)}}
    and the byte offset after the ElementDataFile line."""
    header: dict[str, tuple[str, int]] = {}
    frames: dict[int, dict[str, tuple[str, int, str]]] = {}
    with path.open("rb") as f:
        magic = f.read(8)
        for start, what in ((b"NRRD000", "a NRRD file (PLUS's or 3D Slicer's .seq.nrrd)"),
                            (b"PK\x03\x04", "a zip archive (e.g. a 3D Slicer .mrb scene)")):
            if magic.startswith(start):
                raise ValueError(f"{path}: {what}, not a MetaImage sequence; only PLUS "
                                 ".mha / .mhd sequence metafiles are read (PLUS's "
                                 "EditSequenceFile writes one from a .seq.nrrd)")
        f.seek(0)
        line_number = 0
        while True:
            raw = f.readline(_MAX_HEADER_LINE)
            if not raw:
                raise ValueError(
                    f"{path}: no ElementDataFile line (the header's last line, LOCAL or the data "
                    "file's name); not a complete MetaImage header"
                )
            line_number += 1
            if line_number == 1 and raw.startswith(b"\xef\xbb\xbf"):  # a UTF-8 BOM
                raw = raw[3:]
            text = _header_text(raw).strip()
            if not text:
                continue
            key, eq, value = text.partition("=")
            key, value = key.strip(), value.strip()
            if eq and key.lower() == "elementdatafile":  # before the length check: binary
                # data on this line is a missing line break, not a line before ElementDataFile
                _check_data_file_value(path, line_number, value, len(raw) >= _MAX_HEADER_LINE)
            if not eq or not key or not key.isprintable() or len(raw) >= _MAX_HEADER_LINE:
                raise ValueError(
                    f"{path}: line {line_number} is not a 'Key = Value' header line: "
                    f"{text[:60]!r} (binary data before an ElementDataFile line?)"
                )
            if key.lower() == "elementdatafile":  # PLUS compares it without case
                key = "ElementDataFile"
                value = "LOCAL" if value.upper() == "LOCAL" else value
            m = _FRAME_KEY.match(key)
            if m is not None:
                index, name = int(m.group(1)), m.group(2)
                fields = frames.setdefault(index, {})
                if name in fields:
                    raise ValueError(
                        f"{path}: line {line_number}: {key} repeats line {fields[name][1]}"
                    )
                fields[name] = (value, line_number, key)
                continue
            if key in header:
                raise ValueError(f"{path}: line {line_number}: {key} repeats line "
                                 f"{header[key][1]}")
            header[key] = (value, line_number)
            if key == "ElementDataFile":
                return header, frames, f.tell()


def _check_data_file_value(path: Path, line_number: int, value: str, too_long: bool) -> None:
    """ValueError when ElementDataFile's value holds binary data (control characters, or a
    line too long to be text): the image data was put on the header's last line, without the
    line break that ends it (a header edited or damaged by hand). PLUS's own value is LOCAL or
    a file name, which have none (a name in the Windows code page read as latin-1 may hold
    U+0080-U+009F, so only the C0 controls and DEL count)."""
    binary = too_long or any(ord(c) < 32 or ord(c) == 127 for c in value)
    rest = value[5:]
    if value[:5].upper() == "LOCAL" and rest and (binary or not " " < rest[0] <= "~"):
        raise ValueError(
            f"{path}: line {line_number}: the ElementDataFile line is not terminated: the image "
            f"data follows LOCAL on the same line ({_cut(value)}); it must start after the line "
            "break that ends 'ElementDataFile = LOCAL' (a header edited or damaged by hand?)")
    if binary:
        raise ValueError(
            f"{path}: line {line_number}: ElementDataFile {_cut(value)} is not LOCAL or a file "
            "name (binary data: the line is not terminated, or the header is damaged)")


def _cut(value: str, limit: int = 40) -> str:
    """A header value quoted for a message, cut to `limit` characters (it may be megabytes of
    binary data)."""
    if len(value) <= limit:
        return repr(value)
    return f"{value[:limit]!r}... ({len(value)} characters)"


def _header_text(raw: bytes) -> str:
    """A header line's text: UTF-8 (what this writer and PLUS on Linux / macOS write), else
    latin-1 (PLUS on Windows writes file names in the ANSI code page; every byte is valid
    latin-1, so the line still parses and a data file name in the western code page is found)."""
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def _integers(path: Path, key: str, value: str) -> list[int]:
    try:
        return [int(v) for v in value.split()]
    except ValueError:
        raise ValueError(f"{path}: {key}: cannot parse {value!r} as integers") from None


def _integer(path: Path, key: str, value: str) -> int:
    values = _integers(path, key, value)
    if len(values) != 1:
        raise ValueError(f"{path}: {key}: expected one integer, got {value!r}")
    return values[0]


def _flag(path: Path, header, key: str, default: bool) -> bool:
    if key not in header:
        return default
    value = header[key][0]
    if value.lower() not in ("true", "false"):
        raise ValueError(f"{path}: {key}: expected True or False, got {value!r}")
    return value.lower() == "true"


def read_plus_sequence(path: str | Path) -> PlusSequence:
    """Read a PLUS sequence metafile (``.mha`` with LOCAL data, or ``.mhd`` + its data file).

    Supported: NDims 3 (W H N; NDims 4 with DimSize W H 1 N, PLUS's 2-D data with the z
    dimension included), MET_UCHAR, 1 or 3 channels, binary data, optionally zlib-compressed
    (``CompressedData = True``), UltrasoundImageOrientation MF, MN, UF, UN (converted to MF).
    Every problem is a ValueError naming the file (and the field, line or frame)."""
    path = Path(path)
    require_file(path)
    header, frame_fields, header_end = _read_header(path)

    def value(key: str, required: bool = True) -> str | None:
        if key not in header:
            if required:
                raise ValueError(f"{path}: missing {key} (a sequence metafile needs it)")
            return None
        return header[key][0]

    if value("ObjectType", False) not in (None, "Image"):
        raise ValueError(f"{path}: ObjectType is {value('ObjectType')!r}, expected Image")
    dims = _integers(path, "DimSize", value("DimSize"))
    ndims_text = value("NDims", False)
    ndims = len(dims) if ndims_text is None else _integer(path, "NDims", ndims_text)
    kinds = (value("Kinds", False) or "").split()
    if "vector" in kinds and len(kinds) == len(dims):  # IGSIO: "3 W H 1 N" for RGB frames
        dims = _dims_by_kind(path, dims, kinds)
        ndims = len(dims)
    if len(dims) != ndims:
        raise ValueError(f"{path}: DimSize has {len(dims)} values but NDims is {ndims}")
    if ndims == 4 and dims[2] == 1:  # 2-D frames written with their z dimension (PLUS option)
        dims = [dims[0], dims[1], dims[3]]
    elif ndims != 3:
        raise ValueError(
            f"{path}: NDims is {ndims}; supported: 3 (a 2-D image sequence: DimSize = width "
            "height frames), or 4 with DimSize width height 1 frames"
        )
    width, height, n = dims
    if width <= 0 or height <= 0 or n <= 0:
        raise ValueError(f"{path}: DimSize {value('DimSize')!r}: width, height and frames must "
                         "be positive (a sequence without images cannot be imported)")
    element_type = value("ElementType")
    if element_type not in SUPPORTED_ELEMENT_TYPES:
        raise ValueError(f"{path}: ElementType {element_type} is not supported; supported: "
                         f"{', '.join(SUPPORTED_ELEMENT_TYPES)} (8-bit images)")
    channels_text = value("ElementNumberOfChannels", False)
    channels = 1 if channels_text is None else _integer(
        path, "ElementNumberOfChannels", channels_text)
    if channels not in SUPPORTED_CHANNELS:
        raise ValueError(f"{path}: ElementNumberOfChannels {channels} is not supported; "
                         "supported: 1 (grey) or 3 (RGB)")
    if not _flag(path, header, "BinaryData", True):
        raise ValueError(f"{path}: BinaryData = False (ASCII pixel data) is not supported")
    compressed = _flag(path, header, "CompressedData", False)
    orientation = value("UltrasoundImageOrientation", False) or "MF"
    if orientation.upper() not in ORIENTATIONS:
        raise ValueError(f"{path}: UltrasoundImageOrientation {orientation!r} is not supported; "
                         f"supported: {', '.join(ORIENTATIONS)} (absent = MF)")
    orientation = orientation.upper()

    images = _read_pixels(path, header, header_end, (n, height, width, channels), compressed)
    if channels == 1:
        images = images[..., 0]
    flip_lr, flip_ud = ORIENTATIONS[orientation]
    if flip_lr:
        images = images[:, :, ::-1]
    if flip_ud:
        images = images[:, ::-1]

    unknown = sorted(i for i in frame_fields if i >= n)
    if unknown:
        key = next(iter(frame_fields[unknown[0]].values()))[2]
        raise ValueError(f"{path}: {key}: frame {unknown[0]} is beyond DimSize's {n} frames "
                         f"(frames {_frames_text(unknown)})")
    fields = [frame_fields.get(i, {}) for i in range(n)]
    timestamps = _timestamps(path, fields)
    image_ok = np.array([_status_ok(f.get("ImageStatus")) for f in fields], bool)
    transforms, status, transform_errors = _transforms(path, fields)
    return PlusSequence(
        path=path,
        images=images,
        timestamps=timestamps,
        transforms=transforms,
        transform_status=status,
        image_ok=image_ok,
        channels=channels,
        width=width,
        height=height,
        orientation=orientation,
        header={k: v for k, (v, _) in header.items()},
        transform_errors=transform_errors,
        _fields=[{name: key for name, (_, _, key) in f.items()} for f in fields],
    )


def _dims_by_kind(path: Path, dims: list[int], kinds: list[str]) -> list[int]:
    """DimSize paired with Kinds (as PLUS's IGSIO writer pairs them): the 'domain' / 'space'
    sizes (width, height[, 1]) and the 'list' / 'time' one (frames); 'vector' (the channels,
    ElementNumberOfChannels) dropped. ValueError for other layouts."""
    spatial = [d for d, k in zip(dims, kinds, strict=True) if k in ("domain", "space")]
    frames = [d for d, k in zip(dims, kinds, strict=True) if k in ("list", "time")]
    other = [k for k in kinds if k not in ("domain", "space", "list", "time", "vector")]
    if len(spatial) == 3 and spatial[2] == 1:
        spatial = spatial[:2]
    if other or len(spatial) != 2 or len(frames) != 1:
        raise ValueError(f"{path}: Kinds {' '.join(kinds)!r} with DimSize {dims}: expected 2-D "
                         "frames (two 'domain' sizes, one 'list' or 'time')")
    return [*spatial, frames[0]]


def _status_ok(entry) -> bool:
    """Absent = OK (PLUS's convention for ImageStatus); else OK in any case."""
    return entry is None or entry[0].upper() == "OK"


def _read_pixels(path: Path, header, header_end: int, shape: tuple[int, ...],
                 compressed: bool) -> np.ndarray:
    n, height, width, channels = shape
    expected = n * height * width * channels
    what = (f"DimSize {width} {height} {n} with {channels} channel(s) of MET_UCHAR needs "
            f"{expected} bytes")
    data_file, line = header["ElementDataFile"]
    if data_file == "LOCAL":
        data_path, offset = path, header_end
    else:
        if data_file.upper().startswith("LIST") or "%" in data_file:
            raise ValueError(f"{path}: ElementDataFile {_cut(data_file)}: one data file per "
                             "slice (LIST or a pattern) is not supported; expected LOCAL or one "
                             "file")
        data_path, offset = path.parent / data_file, 0
        if not data_path.is_file():
            raise ValueError(f"{path}: line {line}: ElementDataFile {_cut(data_file)}: "
                             f"{data_path} not found")
    size = data_path.stat().st_size
    if "HeaderSize" in header and data_file != "LOCAL":  # bytes to skip in the data file
        skip = _integer(path, "HeaderSize", header["HeaderSize"][0])
        if skip < -1 or (skip == -1 and compressed):
            raise ValueError(f"{path}: HeaderSize {skip} is not supported (expected >= 0, or -1 "
                             "for uncompressed data at the end of the file)")
        offset = max(size - expected, 0) if skip == -1 else skip  # -1: the file's last bytes
        if offset > size:  # (it read "image data is -99904 bytes")
            raise ValueError(f"{path}: HeaderSize {skip} is beyond the end of the data file "
                             f"{data_path}, which is {size} bytes")
    found = size - offset
    if not compressed:
        if found != expected:
            where = "" if data_path == path else f" ({data_path})"
            raise ValueError(f"{path}: image data{where} is {found} bytes but {what}: "
                             f"{'truncated' if found < expected else 'longer than DimSize says'}")
        return np.memmap(data_path, dtype=np.uint8, mode="r", offset=offset, shape=shape)

    stored = header.get("CompressedDataSize")
    if stored is not None:
        parsed = _integer(path, "CompressedDataSize", stored[0])
        if parsed <= 0:
            raise ValueError(f"{path}: CompressedDataSize: expected a positive integer, got "
                             f"{stored[0]!r}")
        if found != parsed:
            raise ValueError(f"{path}: compressed image data is {found} bytes but "
                             f"CompressedDataSize says {parsed}")
    # zlib's deflate cannot compress by more than ~1032:1 (its longest match, 258 bytes, in a
    # code of at least 2 bits): a header asking for more than MAX_ZLIB_RATIO x the compressed
    # bytes is damaged or not this data's, refused before allocating (a 278-byte file asking for
    # 9 TiB ended in numpy's MemoryError traceback)
    if expected > MAX_ZLIB_RATIO * max(found, 1):
        raise ValueError(f"{path}: {what} decompressed ({_bytes_text(expected)}) from {found} "
                         f"compressed bytes, more than zlib's maximum ratio (~1032:1) allows: "
                         "the header (DimSize, ElementNumberOfChannels) does not match the data, "
                         "or the file is damaged")
    # inflated chunk by chunk into one preallocated array: memory = the images, not the
    # images + the compressed file + a second copy
    memory = _physical_memory()
    too_big = (f"{path}: {what}, {_bytes_text(expected)} decompressed, more than this machine "
               f"can hold{'' if memory is None else f' ({_bytes_text(memory)} of memory)'}: a "
               "compressed sequence is decompressed into memory. Write it uncompressed (PLUS's "
               "EditSequenceFile can; an uncompressed sequence is read memory-mapped, frame by "
               "frame)")
    if memory is not None and expected > memory:
        raise ValueError(too_big)
    try:
        pixels = _allocate(expected)
    except MemoryError:
        raise ValueError(too_big) from None
    done = 0
    inflate = zlib.decompressobj()
    try:
        with data_path.open("rb") as f:
            f.seek(offset)
            while not inflate.eof:
                chunk = inflate.unconsumed_tail or f.read(1 << 22)
                if not chunk:
                    break
                # at most one byte more than expected: a longer stream is refused, not inflated
                data = inflate.decompress(chunk, expected + 1 - done)
                if done + len(data) > expected:
                    done += len(data)
                    break
                pixels[done:done + len(data)] = np.frombuffer(data, np.uint8)
                done += len(data)
    except zlib.error as e:
        raise ValueError(f"{path}: cannot decompress the image data (zlib: {e})") from None
    if done != expected or not inflate.eof:
        found_text = f"{done}" if done <= expected else f"more than {expected}"
        raise ValueError(f"{path}: decompressed image data is {found_text} bytes but {what}")
    return pixels.reshape(shape)


def _allocate(size: int) -> np.ndarray:
    """The buffer a compressed sequence is decompressed into (a function: the tests make it
    fail)."""
    return np.empty(size, np.uint8)


def _physical_memory() -> int | None:
    """This machine's physical memory in bytes (None where the OS does not say): beyond it an
    allocation may succeed (overcommitted) and the process be killed while filling it."""
    try:
        return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


def _bytes_text(n: int) -> str:
    """A byte count for messages: 9.1 TiB, 120 MiB, 96 bytes."""
    for unit, scale in (("TiB", 1 << 40), ("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n} bytes"


def _timestamps(path: Path, fields: list[dict]) -> np.ndarray:
    missing = [i for i, f in enumerate(fields) if "Timestamp" not in f]
    if missing:
        raise ValueError(f"{path}: no Timestamp for frame(s) {_frames_text(missing)} "
                         f"(Seq_Frame{missing[0]:04d}_Timestamp)")
    t = np.empty(len(fields))
    for i, f in enumerate(fields):
        text, _, key = f["Timestamp"]
        try:
            t[i] = float(text)
        except ValueError:
            raise ValueError(f"{path}: frame {i} ({key}): cannot parse {text!r} as a "
                             "number") from None
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise ValueError(f"{path}: frame(s) {_frames_text(bad)}: timestamp is not finite "
                         f"({fields[bad[0]]['Timestamp'][2]} = {fields[bad[0]]['Timestamp'][0]})")
    beyond = np.flatnonzero(np.abs(t) > MAX_TIMESTAMP_S)
    if beyond.size:
        raise ValueError(f"{path}: frame {beyond[0]}: timestamp {float(t[beyond[0]])!r} is beyond "
                         f"|t| <= {MAX_TIMESTAMP_S:g} s; timestamps are seconds (ms, µs or ns?)")
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        i = int(back[0]) + 1
        raise ValueError(f"{path}: frame {i}: timestamp {float(t[i])!r} is not after frame "
                         f"{i - 1}'s {float(t[i - 1])!r}; timestamps must be strictly increasing "
                         f"({back.size} such frame(s): {_frames_text(back + 1)})")
    return t


def _transforms(path: Path, fields: list[dict]) -> tuple[dict, dict, dict]:
    """(matrices, status, errors) per transform field (PlusSequence's transforms,
    transform_status and transform_errors). A sample with status OK that is not 16 numbers is
    recorded in errors (the first per field), not raised: only the field imported matters."""
    n = len(fields)
    names = sorted({name for f in fields for name in f if name.endswith("Transform")})
    transforms, status, errors = {}, {}, {}
    for name in names:
        M = np.full((n, 4, 4), np.nan)
        ok = np.zeros(n, bool)
        for i, f in enumerate(fields):
            entry = f.get(name)
            if entry is None:
                continue  # no sample in this frame
            text, _, key = entry
            ok[i] = _status_ok(f.get(name + "Status"))
            try:
                values = [float(v) for v in text.split()]
            except ValueError:
                values = []
            if len(values) != 16:
                if ok[i]:  # a sample marked missing may hold anything ("-nan(ind)", "")
                    errors.setdefault(name, f"{path}: frame {i} ({key}): cannot parse "
                                            f"{text!r} as 16 numbers (a row-major 4x4 matrix)")
                continue
            M[i] = np.reshape(values, (4, 4))
        transforms[name], status[name] = M, ok
    return transforms, status, errors


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def write_plus_sequence(
    path: str | Path,
    images,
    timestamps,
    transforms: Mapping[str, np.ndarray] | None = None,
    status: Mapping[str, np.ndarray] | None = None,
    compress: bool = False,
    *,
    image_ok=None,
) -> Path:
    """Write a PLUS sequence metafile as PLUS writes it: ``.mha`` with the data inline (LOCAL),
    or ``.mhd`` with the data in ``<name>.raw`` (``.zraw`` when compressed) beside it.

    images : (N, H, W) or (N, H, W, 3) uint8 (RGB), or a sequence of such frames (written one at
        a time). timestamps : (N,) s. transforms : name (``SensorToTracker`` or
        ``SensorToTrackerTransform``) -> (N, 4, 4). status : the same names -> (N,) bool (absent:
        all OK); frames whose status is False are written INVALID (non-finite matrices as the
        identity). image_ok : (N,) bool, False = ImageStatus INVALID (the pixels are still
        written: the data block always holds N frames). compress : zlib (CompressedData).
    Files are written to temporary names and renamed, so a failure leaves no partial file."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".mha", ".mhd"):
        raise ValueError(f"{path}: expected a .mha (data inline) or .mhd (separate data) name")
    n = len(images)
    if n == 0:
        raise ValueError(f"{path}: no images to write")
    first = np.asarray(images[0])
    if first.dtype != np.uint8 or first.ndim not in (2, 3) or (
            first.ndim == 3 and first.shape[2] not in SUPPORTED_CHANNELS):
        raise ValueError(f"{path}: images must be uint8 (H, W) or (H, W, 3), got "
                         f"{first.dtype} {first.shape}")
    shape = first.shape
    height, width = shape[:2]
    channels = 1 if first.ndim == 2 else shape[2]
    timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if timestamps.size != n:
        raise ValueError(f"{path}: {timestamps.size} timestamps for {n} images")
    ok_image = np.ones(n, bool) if image_ok is None else np.asarray(image_ok, bool).reshape(-1)
    if ok_image.size != n:
        raise ValueError(f"{path}: image_ok has {ok_image.size} values for {n} images")
    fields, oks = {}, {}
    status = {_transform_field(k): v for k, v in (status or {}).items()}
    for name, matrices in (transforms or {}).items():
        name = _transform_field(name)
        matrices = np.asarray(matrices, dtype=np.float64)
        if matrices.shape != (n, 4, 4):
            raise ValueError(f"{path}: transform {name}: expected shape ({n}, 4, 4), got "
                             f"{matrices.shape}")
        ok = np.asarray(status.pop(name, np.ones(n, bool)), bool).reshape(-1)
        if ok.size != n:
            raise ValueError(f"{path}: status of {name}: {ok.size} values for {n} frames")
        bad = np.flatnonzero(ok & ~np.isfinite(matrices).all(axis=(1, 2)))
        if bad.size:
            raise ValueError(f"{path}: transform {name}: frame {bad[0]} has status OK but "
                             "non-finite values")
        fields[name], oks[name] = matrices, ok
    if status:
        raise ValueError(f"{path}: status given for {', '.join(status)} without its transform")

    lines = [
        "ObjectType = Image",
        "NDims = 3",
        "AnatomicalOrientation = RAI",
        "BinaryData = True",
        "BinaryDataByteOrderMSB = False",
        "CenterOfRotation = 0 0 0",
        f"CompressedData = {compress}",
        None,  # CompressedDataSize, once known
        f"DimSize = {width} {height} {n}",
        f"ElementNumberOfChannels = {channels}",
        "ElementSpacing = 1 1 1",
        "ElementType = MET_UCHAR",
        "Kinds = domain domain list",
        "Offset = 0 0 0",
        "TransformMatrix = 1 0 0 0 1 0 0 0 1",
        "UltrasoundImageOrientation = MF",
        f"UltrasoundImageType = {'RGB_COLOR' if channels == 3 else 'BRIGHTNESS'}",
    ]
    for i in range(n):
        prefix = f"{FRAME_PREFIX}{i:04d}_"
        lines.append(f"{prefix}FrameNumber = {i}")
        for name, matrices in fields.items():
            M = matrices[i] if np.isfinite(matrices[i]).all() else np.eye(4)
            lines.append(f"{prefix}{name} = {' '.join(_number(v) for v in M.reshape(-1))}")
            lines.append(f"{prefix}{name}Status = {'OK' if oks[name][i] else 'INVALID'}")
        t = _number(timestamps[i])
        lines += [f"{prefix}Timestamp = {t}", f"{prefix}UnfilteredTimestamp = {t}"]
        lines.append(f"{prefix}ImageStatus = {'OK' if ok_image[i] else 'INVALID'}")

    def frames():
        for i in range(n):
            image = np.asarray(images[i])
            if image.shape != shape or image.dtype != np.uint8:
                raise ValueError(f"{path}: image {i} is {image.dtype} {image.shape}, the first "
                                 f"is uint8 {shape}")
            yield np.ascontiguousarray(image).tobytes()

    data_name = path.name[: -len(path.suffix)] + (".zraw" if compress else ".raw")
    if suffix == ".mhd":  # the header names the data file on a line of its own, in UTF-8
        try:
            data_name.encode("utf-8")
        except UnicodeEncodeError:
            raise ValueError(f"{path}: the file name is not valid Unicode text (undecodable "
                             "bytes); the header cannot name its data file") from None
        if data_name != data_name.strip() or any(c in data_name for c in "\r\n\x00"):
            raise ValueError(f"{path}: a .mhd name with leading or trailing spaces or a line "
                             "break cannot be named in the header; rename it")
    temps: list[Path] = []
    try:
        data_tmp = _temp(path, temps)
        with data_tmp.open("wb") as f:
            deflate = zlib.compressobj() if compress else None
            for chunk in frames():
                f.write(deflate.compress(chunk) if deflate else chunk)
            if deflate:
                f.write(deflate.flush())
        if compress:
            lines[7] = f"CompressedDataSize = {data_tmp.stat().st_size}"
        lines = [line for line in lines if line is not None]
        lines.append(f"ElementDataFile = {'LOCAL' if suffix == '.mha' else data_name}")
        header = ("\n".join(lines) + "\n").encode("utf-8")
        if suffix == ".mha":
            header_tmp = _temp(path, temps)
            with header_tmp.open("wb") as out, data_tmp.open("rb") as data:
                out.write(header)
                while chunk := data.read(1 << 22):
                    out.write(chunk)
            os.replace(header_tmp, path)
        else:
            header_tmp = _temp(path, temps)
            header_tmp.write_bytes(header)
            os.replace(data_tmp, path.parent / data_name)
            os.replace(header_tmp, path)
    finally:
        for tmp in temps:
            tmp.unlink(missing_ok=True)
    return path


def _temp(path: Path, temps: list[Path]) -> Path:
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.tmp-", dir=path.parent)
    os.close(fd)
    os.chmod(name, created_mode(0o666))  # the permissions of a file written normally
    temps.append(Path(name))
    return temps[-1]


def _number(x: float) -> str:
    """Shortest text that reads back as the same double."""
    return repr(float(x)) if np.isfinite(x) else str(float(x))


# --------------------------------------------------------------------------------------------
# Import into the dataset contract
# --------------------------------------------------------------------------------------------


@dataclass(eq=False)
class ImportSummary:
    """What :func:`import_plus_sequence` wrote.

    root : the dataset folder. source : the sequence file. transform : the field imported as
    tracker_from_sensor (``inverted``: it was stored the other way round); None when the
    sequence has no transform field at all (the video alone: no tracking.csv). frames : images
    written; their frame ids are their indices in the sequence. skipped_frames : sequence indices
    whose ImageStatus is not OK (left out). invalid_samples : sequence indices whose transform
    status is not OK (tracking.csv rows with valid=0; read_dataset flags the frames in a stretch
    of them untracked, at the ends as inside). untracked_frames : written frames outside the
    tracker's time span, tracking.csv's first to last row: only with a tracker_time_offset, which
    shifts the rows off the frames at one end (read_dataset refuses them unless
    allow_untracked; run: --allow-untracked).
    """

    root: Path
    source: Path
    transform: str | None
    inverted: bool
    frames: int
    skipped_frames: list[int]
    invalid_samples: list[int]
    untracked_frames: list[int]
    width: int
    height: int
    channels: int
    orientation: str
    tracker_time_offset: float = 0.0

    def __str__(self) -> str:
        parts = [f"{self.root}: {self.frames} frames {self.width}x{self.height} "
                 f"{'RGB->BGR' if self.channels == 3 else 'grey'} from {self.source}"]
        if self.transform is None:
            parts.append(UNTRACKED_NOTE)
        else:
            parts.append(f"tracking.csv from {self.transform}"
                         f"{' (inverted)' if self.inverted else ''}")
        if self.orientation != "MF":
            parts.append(f"orientation {self.orientation} converted to MF")
        if self.skipped_frames:
            parts.append(f"skipped frames (ImageStatus not OK): "
                         f"{_frames_text(self.skipped_frames)}")
        if self.invalid_samples:
            parts.append(f"invalid tracker samples: {_frames_text(self.invalid_samples)}")
        if self.untracked_frames:
            shift = (f" (tracking.csv shifted by {-self.tracker_time_offset:+g} s, the tracker "
                     "time offset)" if self.tracker_time_offset else "")
            parts.append(f"frames outside the tracker's time span{shift}: "
                         f"{_frames_text(self.untracked_frames)}; `fusedmosaic run` refuses the "
                         "dataset unless --allow-untracked, which flags them untracked")
        return "; ".join(parts)


UNTRACKED_NOTE = ("no tracking.csv: the sequence has no transform field, so the dataset is the "
                  "video alone (enough for `calibrate`'s intrinsics and the image-only methods; "
                  "the tracked methods refuse it)")


def import_plus_sequence(
    path: str | Path,
    root: str | Path,
    *,
    camera: Camera | str | Path | None,
    transform: str | None = "SensorToTracker",
    hand_eye=None,
    overwrite: bool = False,
    tracker_time_offset: float = 0.0,
) -> ImportSummary:
    """Write the dataset folder ``root`` (design.md contract) from a PLUS sequence metafile.

    frames/ : the images whose ImageStatus is OK (RGB converted to BGR, orientation to MF);
    frames.csv : their sequence indices and timestamps; tracking.csv : one row per sequence
    frame at its timestamp, ``transform`` as tracker_from_sensor (``SensorToTracker``; stored as
    ``TrackerToSensor`` it is inverted; None picks the single *ToTracker / *ToReference field),
    valid=0 where its status is not OK; a sequence without any transform field (a video
    recorded without a tracker) is imported without tracking.csv, whatever ``transform`` says
    (the summary says so; a sequence with transforms but not the one named is refused);
    camera.yaml : ``camera`` (a Camera or a camera.yaml
    path), whose image size must match; None writes the image size only (a recording to
    calibrate the camera from, `fusedmosaic calibrate`); hand_eye.txt : ``hand_eye`` (4x4
    sensor_from_camera or a path) when given. tracker_time_offset : s, the tracker's clock
    ahead of the video's (calibrate's calibration.json "tracker_time_offset"): tracking.csv's
    timestamps are written shifted by -tracker_time_offset (io.shift_tracking), on the video's
    clock. Everything is checked before anything is written, as read_dataset and run would
    check the dataset (the frame times' spacing, camera_matrix's layout), and write_dataset
    writes atomically: a failure leaves no folder (or the previous one, with overwrite).
    """
    tracker_time_offset = check_time_offset(tracker_time_offset)
    sequence = read_plus_sequence(path)
    if overwrite:  # replacing root must not delete this import's own inputs
        data = sequence.header.get("ElementDataFile", "LOCAL")
        inputs = [sequence.path, *([] if data == "LOCAL" else [sequence.path.parent / data]),
                  *(Path(p) for p in (camera, hand_eye) if isinstance(p, (str, os.PathLike)))]
        for item in inputs:
            if Path(root).resolve() in item.resolve().parents:
                raise ValueError(f"{root}: holds {item}, an input of this import, which "
                                 "overwriting would delete; choose another folder")
    if camera is None:
        camera = Camera(sequence.width, sequence.height, source=str(sequence.path))
    elif isinstance(camera, (str, os.PathLike)):
        camera = read_camera_yaml(camera)
    elif not isinstance(camera, Camera):
        raise ValueError(f"camera must be a fusedmosaic.io.Camera or a camera.yaml path, got "
                         f"{type(camera).__name__}")
    if camera.size != (sequence.width, sequence.height):
        raise ValueError(
            f"{sequence.path}: images are {sequence.width}x{sequence.height} but "
            f"{camera.source} says {camera.width}x{camera.height}"
        )
    if camera.camera_matrix is not None:  # checked as require_camera_matrix checks it
        try:
            camera._checked_camera_matrix(camera.camera_matrix)
        except ValueError as e:
            raise ValueError(
                f"{e}: the pose methods (ba, ba-emt, lba-emt, emt) would refuse the dataset; "
                "correct it, or leave camera_matrix out for the other methods and calibrate"
            ) from None
    if transform is not None and (not isinstance(transform, str) or not transform):
        raise ValueError(f"{sequence.path}: transform name must be a non-empty string, got "
                         f"{transform!r}")
    selected = sequence.transform(transform) if sequence.transforms else None
    if selected is not None and selected.ok.sum() < 2:
        raise ValueError(f"{sequence.path}: {selected.source}: {int(selected.ok.sum())} "
                         "frame(s) with status OK; tracking needs at least 2 samples")
    sensor_from_camera = None if hand_eye is None else hand_eye_matrix(hand_eye)
    kept = np.flatnonzero(sequence.image_ok)
    if kept.size == 0:
        raise ValueError(f"{sequence.path}: no frame has ImageStatus OK; nothing to import")
    # frames.csv's times, checked as read_dataset checks them (at most MAX_FRAME_GAP_S apart,
    # MAX_FRAME_SPACING_S in the median), named by their keys in the sequence
    keys = np.array([sequence._key(int(i), "Timestamp") for i in kept], dtype=object)
    try:
        _check_frame_times(sequence.path, keys, sequence.timestamps[kept], MAX_FRAME_SPACING_S)
    except ValueError as e:
        raise ValueError(f"{e} (the sequence's timestamps, which frames.csv would hold: `run` "
                         "would refuse the dataset)") from None

    t = sequence.timestamps
    tracking, invalid, untracked = None, np.empty(0, int), np.empty(0, int)
    if selected is not None:
        ok = selected.ok
        translations = np.full((len(t), 3), np.nan)
        quaternions = np.full((len(t), 4), np.nan)
        translations[ok] = selected.matrices[ok, :3, 3]
        quaternions[ok] = Rotation.from_matrix(selected.matrices[ok, :3, :3]).as_quat()
        tracking = shift_tracking(TrackingSamples(t, translations, quaternions, ok),
                                  tracker_time_offset)
        t_ok, rows = tracking.timestamps[ok], tracking.timestamps
        # read_dataset refuses frames beyond every row (the offset moves the rows off one end)
        # and flags those beyond the OK samples among invalid rows
        untracked = kept[(t[kept] < rows[0]) | (t[kept] > rows[-1])]
        invalid = np.flatnonzero(~ok)
        off_ok = (t[kept] < t_ok[0]) | (t[kept] > t_ok[-1])
        if tracker_time_offset and off_ok.all():  # the offset moved them all
            raise ValueError(
                f"{sequence.path}: {selected.source} shifted by {-tracker_time_offset:+g} s "
                f"(tracker time offset {tracker_time_offset:g} s) spans "
                f"[{_time(t_ok[0])}, {_time(t_ok[-1])}] s, outside every frame's time "
                f"([{_time(t[kept].min())}, {_time(t[kept].max())}] s): no frame would be "
                "tracked; check the offset (calibrate measures it)")

    def frames():
        for i in kept:
            image = sequence.images[i]
            yield np.ascontiguousarray(image[..., ::-1] if sequence.channels == 3 else image)

    # tracking.csv already on the video's clock: said in the dataset (IMPORT_RECORD), so that
    # run --calibration does not shift it again by calibration.json's offset
    # (applied_tracker_time_offset)
    extra = {}
    if tracking is not None and tracker_time_offset:
        extra[IMPORT_RECORD] = time_offset_record(
            tracker_time_offset, str(sequence.path), "tracking.csv",
            "import --tracker-time-offset", transform=selected.source)
    # frames.csv keeps the sequence indices as frame ids (frames left out leave a gap), so the
    # ids match annotations of the recording.
    written = write_dataset(
        root,
        camera=camera,
        frames=frames(),
        timestamps=t[kept],
        frame_ids=kept,
        tracking=tracking,
        hand_eye=sensor_from_camera,
        extra_files=extra,
        overwrite=overwrite,
    )
    return ImportSummary(
        root=Path(written),
        source=sequence.path,
        transform=None if selected is None else selected.source,
        inverted=selected is not None and selected.inverted,
        frames=int(kept.size),
        skipped_frames=np.flatnonzero(~sequence.image_ok).tolist(),
        invalid_samples=invalid.tolist(),
        untracked_frames=untracked.tolist(),
        width=sequence.width,
        height=sequence.height,
        channels=sequence.channels,
        orientation=sequence.orientation,
        tracker_time_offset=tracker_time_offset,
    )


def time_offset_record(offset: float, source: str, samples: str, how: str, **more) -> str:
    """IMPORT_RECORD's text: the `samples` file's timestamps were shifted by -offset onto the
    video's clock (`how`: the option that did it), for applied_tracker_time_offset to read."""
    return json.dumps({
        "tracker_time_offset_applied_s": float(offset),
        "source": source,
        **more,
        "note": (f"{samples}'s timestamps are the sender's shifted by {-offset:+g} s ({how}): on "
                 "the video's clock; run --calibration does not apply calibration.json's offset "
                 "again"),
    }, indent=2) + "\n"


def applied_tracker_time_offset(root: str | Path) -> float | None:
    """The tracker time offset (s) import_plus_sequence already applied to the dataset
    ``root``'s tracking.csv (``import --tracker-time-offset S``: its timestamps shifted by -S,
    on the video's clock), from its IMPORT_RECORD; None when the dataset has none (nothing
    shifted at import). ValueError naming the file when it is unreadable or the value is not a
    number within the offsets import takes."""
    from fusedmosaic.io.output import read_json_object

    path = Path(root) / IMPORT_RECORD
    if not path.is_file():
        return None
    return check_time_offset(read_json_object(path).get("tracker_time_offset_applied_s"),
                             f"{path}: tracker_time_offset_applied_s")
