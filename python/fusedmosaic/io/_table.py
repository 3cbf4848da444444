"""Small strict CSV reader/writer shared by the io modules.

Rows are numbered as in a spreadsheet: the header is row 1, the first data row is row 2, so an
error message's row number is the file's line number.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np


def read_table(
    path: str | Path,
    columns: Sequence[str],
    optional: Sequence[str] = (),
    *,
    integer: Sequence[str] = (),
    text: Sequence[str] = (),
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Read a headed CSV with exactly ``columns`` followed by any prefix of ``optional``.

    Empty fields become NaN (float columns); ``integer`` columns must be filled with integers and
    come back as int64; ``text`` columns come back as the fields' stripped text (str arrays), for
    the caller to parse (e.g. with parse_numbers, skipping rows whose content does not count).
    Returns the columns by name and each data row's spreadsheet row number.
    """
    path = Path(path)
    require_file(path)
    try:  # utf-8-sig: a byte order mark (spreadsheets' "CSV UTF-8") is not part of the header
        with path.open(newline="", encoding="utf-8-sig") as f:
            lines = list(csv.reader(f))
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not UTF-8 text; expected a CSV file") from None
    while lines and not any(field.strip() for field in lines[-1]):
        lines.pop()  # trailing blank lines
    if not lines:
        raise ValueError(f"{path}: empty file, expected header {','.join(columns)}")
    header = [h.strip() for h in lines[0]]
    allowed = [list(columns) + list(optional[:k]) for k in range(len(optional) + 1)]
    if header not in allowed:
        expected = ",".join(columns) + "".join(f"[,{c}]" for c in optional)
        raise ValueError(f"{path}: row 1: header is {','.join(header)!r}, expected {expected!r}")

    values: dict[str, list] = {name: [] for name in header}
    rows = []
    for row_number, fields in enumerate(lines[1:], start=2):
        if not any(field.strip() for field in fields):
            continue  # blank line
        if len(fields) != len(header):
            raise ValueError(
                f"{path}: row {row_number}: {len(fields)} fields, expected {len(header)} "
                f"({','.join(header)})"
            )
        for name, field in zip(header, fields, strict=True):
            values[name].append(field.strip() if name in text else
                                _parse(path, row_number, name, field.strip(), name in integer))
        rows.append(row_number)
    table = {
        name: np.asarray(v, dtype=str if name in text else
                         np.int64 if name in integer else np.float64).reshape(-1)
        for name, v in values.items()
    }
    return table, np.asarray(rows, dtype=np.int64)


def parse_numbers(path: str | Path, rows: np.ndarray, column: str, fields: np.ndarray,
                  skip: np.ndarray | None = None) -> np.ndarray:
    """A ``text`` column of read_table as float64: empty fields NaN; text that is no number
    raises naming the row and column, except in rows where ``skip`` is True (rows whose content
    is ignored, e.g. flagged invalid), which become NaN."""
    out = np.full(len(fields), np.nan)
    for i, field in enumerate(fields):
        try:
            out[i] = _parse(Path(path), int(rows[i]), column, str(field), False)
        except ValueError:
            if skip is None or not skip[i]:
                raise
    return out


def require_file(path: Path) -> None:
    """ValueError naming ``path`` when it is a folder or does not exist (an input file)."""
    if path.is_dir():
        raise ValueError(f"{path}: is a folder; expected a file")
    if not path.is_file():
        raise ValueError(f"{path}: file not found")


INT64_MIN, INT64_MAX = int(np.iinfo(np.int64).min), int(np.iinfo(np.int64).max)


def _parse(path: Path, row: int, column: str, field: str, integer: bool) -> float | int:
    if integer:
        try:
            value = int(field)
        except ValueError:
            raise ValueError(
                f"{path}: row {row}, column {column!r}: expected an integer, got {field!r}"
            ) from None
        if not INT64_MIN <= value <= INT64_MAX:  # stored as int64
            raise ValueError(f"{path}: row {row}, column {column!r}: {field!r} is out of range "
                             f"(a 64-bit integer: {INT64_MIN}..{INT64_MAX})")
        return value
    if not field:
        return math.nan
    try:
        return float(field)
    except ValueError:
        raise ValueError(
            f"{path}: row {row}, column {column!r}: cannot parse {field!r} as a number"
        ) from None


def format_float(x: float) -> str:
    """Shortest text that round-trips exactly (Python's repr); NaN -> empty field."""
    x = float(x)
    return "" if math.isnan(x) else repr(x)


def write_table(path: str | Path, header: Sequence[str], rows: Iterable[Sequence[str]]) -> None:
    with Path(path).open("w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(header)
        writer.writerows(rows)


def check_increasing(path: str | Path, rows: np.ndarray, values: np.ndarray, what: str) -> None:
    """Raise naming the first row whose ``what`` is NaN or not strictly after the previous one."""
    missing = np.flatnonzero(~np.isfinite(values))
    if missing.size:
        raise ValueError(f"{path}: row {rows[missing[0]]}: {what} is missing or not finite")
    bad = np.flatnonzero(np.diff(values) <= 0)
    if bad.size:
        i = bad[0] + 1
        raise ValueError(
            f"{path}: row {rows[i]}: {what} {values[i].item()!r} is not after the previous "
            f"{values[i - 1].item()!r}; {what}s must be strictly increasing"
        )
