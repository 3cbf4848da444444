"""Small strict CSV reader/writer shared by the io modules.

Rows are numbered as in a spreadsheet: the header is row 1, the first data row is row 2, so an
error message's row number is the file's line number.
"""

from __future__ import annotations

import csv
import math
import operator
import warnings
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
    come back as int64; ``text`` columns come back as the fields' stripped text (object arrays of
    str), for the caller to parse (e.g. with parse_numbers, skipping rows whose content does not
    count).
    Returns the columns by name and each data row's spreadsheet row number.
    """
    path = Path(path)
    require_file(path)
    records: list[list[str]] = []
    try:  # utf-8-sig: a byte order mark (spreadsheets' "CSV UTF-8") is not part of the header
        with path.open(newline="", encoding="utf-8-sig") as f:
            try:
                records.extend(csv.reader(f))
            except csv.Error as e:  # (not a ValueError: it crashed every command; review)
                raise ValueError(
                    f"{path}: row {len(records) + 1}: cannot be read as CSV ({e}): an unbalanced "
                    f'quote (") or a field over {csv.field_size_limit()} characters; not a CSV '
                    "of numbers?") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not UTF-8 text; expected a CSV file") from None
    while records and not "".join(records[-1]).strip():
        records.pop()  # trailing blank lines
    if not records:
        raise ValueError(f"{path}: empty file, expected header {','.join(columns)}")
    header = [h.strip() for h in records[0]]
    allowed = _headers(columns, optional)
    if header not in allowed:
        expected = ",".join(columns) + "".join(f"[,{c}]" for c in optional)
        raise ValueError(f"{path}: row 1: header is {','.join(header)!r}, expected "
                         f"{expected!r}{_header_hint(header)}")

    n = len(header)
    body = records[1:]
    del records
    # rows of another length than the header's: blank ones skipped, the first other refused
    keep = np.ones(len(body), bool)
    lengths = np.fromiter(map(len, body), np.int64, len(body))
    for i in np.flatnonzero(lengths != n):
        fields = body[i]
        if "".join(fields).strip():
            comment = fields[0].lstrip().startswith("#")
            raise ValueError(
                f"{path}: row {i + 2}: {len(fields)} fields, expected {n} "
                f"({','.join(header)})" + (" (a comment line? comment lines are not allowed)"
                                           if comment else "")
            )
        keep[i] = False
    joined = list(map("".join, body))  # a line of empty fields is a blank one too
    keep &= ~(np.fromiter(map(str.isspace, joined), bool, len(body))
              | np.fromiter(map(operator.not_, joined), bool, len(body)))
    del joined
    row_numbers = np.flatnonzero(keep).astype(np.int64) + 2
    if not keep.all():
        body = [body[i] for i in np.flatnonzero(keep)]
    columns_text = list(zip(*body, strict=True)) if body else [()] * n
    del body
    table = {}
    for name, fields in zip(header, columns_text, strict=True):
        if name in text:
            table[name] = np.array(list(map(str.strip, fields)), dtype=object).reshape(-1)
        elif name in integer:
            table[name] = _integers(path, row_numbers, name, fields)
        else:
            table[name] = _floats(path, row_numbers, name, fields)
    return table, row_numbers


def read_number_table(path: str | Path, columns: Sequence[str], optional: Sequence[str] = ()
                      ) -> tuple[dict[str, np.ndarray], np.ndarray] | None:
    """read_table's result for a file of numbers only (every field filled, no quotes, no blank
    line; e.g. tracking.csv or robot.csv as write_table writes them), its columns all float64,
    parsed by numpy's C reader (np.loadtxt, which parses numbers as Python's float does: a
    long tracking.csv took 120 µs a row field by field; review); None for any other file,
    which the caller then reads with read_table (whose messages name the problem).

    The file is streamed, not held as text: read whole, then parsed from an io.StringIO (4
    bytes a character), a 74 MB tracking.csv of 500 000 rows peaked at 546 MB (review 46)."""
    path = Path(path)
    try:  # lines end at LF alone (as str.partition and np.loadtxt split them): a lone CR is
        # inside a line, which then is no number
        with path.open(newline="\n", encoding="utf-8-sig") as f:
            first = f.readline()
            if not first.endswith("\n"):  # one line only
                return None
            header = [h.strip() for h in first.rstrip("\r\n").split(",")]
            if header not in _headers(columns, optional):
                return None
            n_rows = _lines_to_last_content(f)  # the rows but trailing blank lines
            if not n_rows:
                return None
            f.seek(0)
            f.readline()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                # a quote is no number: such a file goes to read_table, as it did
                data = np.loadtxt(f, delimiter=",", dtype=np.float64, comments=None, ndmin=2,
                                  max_rows=n_rows)
    except (OSError, UnicodeDecodeError, ValueError, TypeError, OverflowError):
        return None
    if data.shape != (n_rows, len(header)):  # a blank line skipped, a lone CR line end
        return None
    return ({name: np.ascontiguousarray(data[:, j]) for j, name in enumerate(header)},
            np.arange(2, n_rows + 2, dtype=np.int64))


def _lines_to_last_content(f) -> int:
    """The lines of the text file ``f`` from its position to its last character that is not
    blank (a last line without a line end counts), in 1 MiB pieces."""
    lines = count = 0
    while piece := f.read(1 << 20):
        content = piece.rstrip()
        if content:
            count = lines + content.count("\n") + 1
        lines += piece.count("\n")
    return count


def _floats(path: Path, rows: np.ndarray, column: str, fields: Sequence) -> np.ndarray:
    """Fields (text) as float64, empty ones NaN: in one pass of Python's float when every one
    is a number; else field by field, naming the row of the first that is no number
    (ValueError)."""
    try:
        return np.fromiter(map(float, fields), np.float64, len(fields))
    except ValueError:
        pass
    try:  # empty fields (NaN) among numbers
        return np.array([float(f) if f.strip() else math.nan for f in fields], np.float64)
    except ValueError:
        pass
    return np.array([_parse(path, int(r), column, str(f).strip(), False)
                     for r, f in zip(rows, fields, strict=True)], np.float64).reshape(-1)


def _integers(path: Path, rows: np.ndarray, column: str, fields: Sequence) -> np.ndarray:
    """Fields (text) as int64; ValueError naming the row of the first that is no integer or
    beyond int64."""
    try:
        return np.fromiter(map(int, fields), np.int64, len(fields))
    except (ValueError, OverflowError):
        return np.array([_parse(path, int(r), column, str(f).strip(), True)
                         for r, f in zip(rows, fields, strict=True)], np.int64).reshape(-1)


def _headers(columns: Sequence[str], optional: Sequence[str]) -> list[list[str]]:
    """The headers a table may have: its columns, then a prefix of the optional ones."""
    return [list(columns) + list(optional[:k]) for k in range(len(optional) + 1)]


def _header_hint(header: list[str]) -> str:
    """A hint for headers of common exports: a comment line first, pandas' index column."""
    if header and header[0].startswith("#"):
        return " (a comment line? comment lines are not allowed: the first line is the header)"
    if header and header[0] == "" and len(header) > 1:
        return (" (an unnamed first column: pandas' index? write the file with "
                "to_csv(..., index=False))")
    return ""


def parse_numbers(path: str | Path, rows: np.ndarray, column: str, fields: np.ndarray,
                  skip: np.ndarray | None = None) -> np.ndarray:
    """A ``text`` column of read_table as float64: empty fields NaN; text that is no number
    raises naming the row and column, except in rows where ``skip`` is True (rows whose content
    is ignored, e.g. flagged invalid), which become NaN."""
    path = Path(path)
    fields = np.asarray(fields, dtype=object).reshape(-1)
    rows = np.asarray(rows).reshape(-1)
    if skip is None or not np.any(skip):
        return _floats(path, rows, column, fields)
    skip = np.asarray(skip, bool).reshape(-1)
    out = np.full(len(fields), np.nan)
    checked = np.flatnonzero(~skip)
    out[checked] = _floats(path, rows[checked], column, fields[checked])  # names a bad row
    for i in np.flatnonzero(skip):  # rows whose content is ignored: a number kept, else NaN
        try:
            out[i] = _parse(path, int(rows[i]), column, str(fields[i]).strip(), False)
        except ValueError:
            pass
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
