"""``homographies.csv`` / ``ground_truth.csv`` (frame -> reference) and ``poses.csv``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fusedmosaic.io._table import format_float, read_table, write_table

HOMOGRAPHY_COLUMNS = [f"h{r}{c}" for r in range(3) for c in range(3)]
POSE_COLUMNS = ["rx", "ry", "rz", "tx", "ty", "tz"]
# Larger values are refused as corrupt: no placement (px, mm, rad) comes near, and their
# squares overflow.
MAX_ABS_VALUE = 1e100


def _read_rows(path: str | Path, columns: list[str], check=None) -> tuple[np.ndarray, np.ndarray]:
    """check(values) -> (index, problem) of the first unusable row, or None."""
    table, rows = read_table(path, ["frame", *columns], integer=["frame"])
    frame_ids = table["frame"]
    values = np.stack([table[c] for c in columns], axis=1)
    empty = np.isnan(values)
    partial = np.flatnonzero(empty.any(axis=1) & ~empty.all(axis=1))
    if partial.size:
        i = partial[0]
        missing = [c for c, e in zip(columns, empty[i], strict=True) if e]
        raise ValueError(
            f"{path}: row {rows[i]}: {','.join(missing)} empty or NaN; leave all of "
            f"{columns[0]}..{columns[-1]} empty for an unplaced frame, or none"
        )
    infinite = np.flatnonzero(np.isinf(values).any(axis=1))
    if infinite.size:
        raise ValueError(f"{path}: row {rows[infinite[0]]}: infinite value")
    huge = np.flatnonzero((np.abs(np.nan_to_num(values)) > MAX_ABS_VALUE).any(axis=1))
    if huge.size:  # (1e300 overflowed NumPy with a warning, then read as 'singular'; review)
        i = huge[0]
        v = values[i][np.abs(np.nan_to_num(values[i])) > MAX_ABS_VALUE][0]
        raise ValueError(f"{path}: row {rows[i]}: value {v:g} out of range (|value| > "
                         f"{MAX_ABS_VALUE:g})")
    _, first = np.unique(frame_ids, return_index=True)
    if first.size != frame_ids.size:
        i = np.setdiff1d(np.arange(frame_ids.size), first)[0]
        raise ValueError(f"{path}: row {rows[i]}: duplicate frame {frame_ids[i]}")
    bad = check(values) if check is not None else None
    if bad is not None:
        i, problem = bad
        raise ValueError(f"{path}: row {rows[i]} (frame {frame_ids[i]}): {problem}")
    return frame_ids, values


def _singular_homography(values: np.ndarray) -> tuple[int, str] | None:
    """The first row whose 3x3 is singular (it maps the image onto a line or a point, no
    placement), or None. Judged by |det| over the product of the column norms (1 for
    orthogonal columns, 0 for dependent ones), which a large translation leaves alone: relative
    to the largest entry, a pCLE frame 40 000 px from the reference (a robot in nm) was
    'singular'."""
    H = values.reshape(-1, 3, 3)
    placed = np.flatnonzero(np.isfinite(H).all(axis=(1, 2)))
    if placed.size == 0:
        return None
    norms = np.linalg.norm(H[placed], axis=1).prod(axis=1)  # over each column's entries
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ratio = np.abs(np.linalg.det(H[placed])) / norms
    singular = np.flatnonzero(~(ratio > 1e-12))
    if singular.size == 0:
        return None
    return int(placed[singular[0]]), ("singular homography (it maps the frame onto a line or "
                                      "a point); leave the fields empty for an unplaced frame")


def _write_rows(path: str | Path, columns: list[str], frame_ids, values: np.ndarray) -> None:
    frame_ids = np.asarray(frame_ids).reshape(-1)
    if frame_ids.size != values.shape[0]:
        raise ValueError(f"{path}: {frame_ids.size} frame ids for {values.shape[0]} rows")
    rows = []
    for frame, row in zip(frame_ids, values, strict=True):
        unplaced = bool(np.isnan(row).any())
        rows.append([str(int(frame))] + ["" if unplaced else format_float(v) for v in row])
    write_table(path, ["frame", *columns], rows)


def read_homographies_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``frame,h00,…,h22``. Returns frame ids (N,) int64 and H (N, 3, 3) float64; a row
    with empty fields (an unplaced frame) gives an all-NaN matrix; a singular one is refused."""
    frame_ids, values = _read_rows(path, HOMOGRAPHY_COLUMNS, _singular_homography)
    return frame_ids, values.reshape(-1, 3, 3)


def write_homographies_csv(path: str | Path, frame_ids, H) -> None:
    """Write H (N, 3, 3); a matrix with any NaN is written as empty fields (unplaced)."""
    H = np.asarray(H, dtype=np.float64)
    if H.ndim != 3 or H.shape[1:] != (3, 3):
        raise ValueError(f"{path}: homographies must be (N, 3, 3), got {H.shape}")
    _write_rows(path, HOMOGRAPHY_COLUMNS, frame_ids, H.reshape(-1, 9))


def read_poses_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``frame,rx,ry,rz,tx,ty,tz`` (cam_from_world, rad and mm). Returns frame ids (N,)
    int64 and poses (N, 6) float64, NaN rows for frames without a pose."""
    return _read_rows(path, POSE_COLUMNS)


def write_poses_csv(path: str | Path, frame_ids, poses) -> None:
    """Write poses (N, 6); a row with any NaN is written as empty fields."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 6:
        raise ValueError(f"{path}: poses must be (N, 6), got {poses.shape}")
    _write_rows(path, POSE_COLUMNS, frame_ids, poses)
