"""Which dataset an output was computed from: `run` records a cheap fingerprint in report.json,
`evaluate` compares it with the dataset given as --truth. Datasets get moved, and a moved copy
keeps its fingerprint (a path alone differing is no mismatch). Another camera.yaml or other
frame pixels mean another dataset: refused (ValueError) unless allowed, then warned about;
frames.csv or the frame count differing is warned about; ground_truth.csv alone differing (a
corrected, extended or sparse truth for the same frames) only gets a note; frames of another
size are an error, since e_j's grid of points comes from the truth's frame size."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

# Small files that tell datasets apart; the frames themselves are summarised by count and size,
# and by the pixels of a few (FINGERPRINT_FRAMES): two recordings with the same camera.yaml and
# regular frame times (and a run's dataset without ground_truth.csv) differ only there.
FINGERPRINT_FILES = ("camera.yaml", "frames.csv", "ground_truth.csv")
# (its key in "sha256", which the warnings name)
FINGERPRINT_FRAMES = "pixels of the first, middle and last frame"


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:16]


def dataset_fingerprint(dataset) -> dict:
    """{frames, width, height, sha256: {file: first 16 hex digits}} of a read Dataset; files of
    FINGERPRINT_FILES that are absent are left out; sha256[FINGERPRINT_FRAMES]: the pixels of
    the first, middle and last frame as decoded (a copy with the frames re-encoded, or the
    same recording imported again, matches)."""
    root = Path(dataset.root)
    sha256 = {name: _sha256(root / name) for name in FINGERPRINT_FILES if (root / name).is_file()}
    sha256[FINGERPRINT_FRAMES] = _frame_pixels_sha256(dataset.frames)
    return {
        "frames": int(len(dataset.frame_ids)),
        "width": int(dataset.camera.width),
        "height": int(dataset.camera.height),
        "sha256": sha256,
    }


def _frame_pixels_sha256(frames) -> str:
    """First 16 hex digits of the SHA-256 of the first, middle and last frame's pixels (their
    shape and bytes). A frame that cannot be read counts as "unreadable": `run` reads it as a
    blank frame (its default) where `evaluate` gets an error, and both must agree."""
    digest = hashlib.sha256()
    n = len(frames)
    for k in sorted({0, n // 2, n - 1}):
        try:
            image = frames[k]
        except ValueError:
            image = None
        if image is None or k in getattr(frames, "unreadable", {}):
            digest.update(b"unreadable")
            continue
        image = np.ascontiguousarray(image)
        digest.update(f"{image.shape} {image.dtype}".encode())
        digest.update(image.tobytes())
    return digest.hexdigest()[:16]


# Fingerprint entries that differ only between different datasets (a copy, moved or with its
# frames re-encoded, matches): a mismatch there is refused unless allowed.
IDENTIFYING = ("camera.yaml", FINGERPRINT_FRAMES)
# The truth alone: edited, extended or made sparse since the run without the frames changing.
TRUTH_FILE = "ground_truth.csv"


def dataset_mismatch(report: dict, dataset, report_path: str | Path, *,
                     allow_other: bool = False) -> dict:
    """How report.json's recorded dataset compares with `dataset`: {} when they agree, else
    {"dataset_warning": ...} and / or {"truth_note": ...}.

    With a recorded fingerprint only the fingerprint counts (a moved copy matches): camera.yaml
    or the frames' pixels differing is another dataset, a ValueError naming what differs unless
    `allow_other` (then a warning); frames.csv or the frame count differing, a warning;
    ground_truth.csv alone, a note that the truth changed since the run. Without a fingerprint
    (older outputs), a different path is warned about."""
    recorded = report.get("dataset_fingerprint")
    here = Path(dataset.root)
    where = f"{report_path} records the dataset {report.get('dataset', '(unknown)')}"
    found: dict = {}
    if isinstance(recorded, dict):
        now = dataset_fingerprint(dataset)
        differ = [key for key in ("frames", "width", "height") if recorded.get(key) != now[key]]
        old_files = recorded.get("sha256") if isinstance(recorded.get("sha256"), dict) else {}
        # Only files both sides have: a run on a copy without ground_truth.csv (held out) is
        # still the same dataset; and older versions recorded no FINGERPRINT_FRAMES.
        differ += [
            name
            for name in sorted(set(old_files) & set(now["sha256"]))
            if old_files[name] != now["sha256"][name]
        ]
        truth_changed = TRUTH_FILE in differ
        differ = [name for name in differ if name != TRUTH_FILE]
        if any(name in IDENTIFYING for name in differ) and not allow_other:
            raise ValueError(
                f"{where}, but {here} differs from it ({', '.join(differ)}): it is another "
                "dataset, whose ground truth would score the output meaninglessly; give the "
                "dataset the output was computed from as --truth, or pass "
                "--allow-other-dataset to score it anyway"
            )
        if differ:
            found["dataset_warning"] = (
                f"{where}, but {here} differs from it ({', '.join(differ)}): the scores "
                "may compare the output with another dataset's ground truth"
            )
        if truth_changed:
            found["truth_note"] = (
                f"{here / TRUTH_FILE} differs from the ground_truth.csv of the dataset the "
                f"output was computed from ({report_path}): the truth changed since the run"
            )
        return found
    recorded_path = report.get("dataset")
    if isinstance(recorded_path, str) and Path(recorded_path).resolve() != here.resolve():
        found["dataset_warning"] = (
            f"{where}, not {here.resolve()}: check that --truth is the dataset the output "
            "was computed from"
        )
    return found


def check_frame_size(report: dict, dataset, report_path: str | Path) -> None:
    """ValueError when report.json records frames of another size than `dataset`'s: e_j is
    measured on a grid over the truth's frame, so the scores would mean nothing."""
    recorded = report.get("dataset_fingerprint")
    if not isinstance(recorded, dict):
        return
    size = (recorded.get("width"), recorded.get("height"))
    here = (int(dataset.camera.width), int(dataset.camera.height))
    if size != here:
        raise ValueError(
            f"{report_path}: the output was computed on {size[0]}x{size[1]} frames, the truth "
            f"dataset {dataset.root} has {here[0]}x{here[1]} frames; e_j compares points of the "
            "truth's frame, so the scores would mean nothing (wrong --truth?)"
        )
