"""A PNG written band by band, so a mosaic larger than memory never exists in one piece.

PNG stores rows top to bottom in one zlib stream; each row is written with the "Up" filter (the
difference to the row above), which compresses smooth images well and needs only the previous
row. Standard library only (zlib, struct); any PNG reader (OpenCV, PIL, browsers) opens the file.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import numpy as np

from fusedmosaic.io.output import temp_beside

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_COLOUR_TYPE = {1: 0, 2: 4, 3: 2, 4: 6}  # grey, grey + alpha, RGB, RGB + alpha
_IDAT_BYTES = 1 << 20
# write_rows encodes this many bytes of rows at a time (or one row, if larger): its temporaries
# (the colour swap, the filtered rows, their compressed bytes and IDAT chunk) stay within about
# 9 x this. A 60 MB band: 9.1 MB at its peak beyond the band, 0.93 s (in one piece: 254 MB,
# 1.02 s).
_CHUNK_BYTES = 1 << 20


def _chunk(kind: bytes, payload: bytes) -> bytes:
    crc = zlib.crc32(payload, zlib.crc32(kind)) & 0xFFFFFFFF
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc)


class PngStreamWriter:
    """Writes an 8-bit grey, grey + alpha, BGR or BGRA image of known size as PNG, rows in
    order.

    >>> with PngStreamWriter(path, width, height, channels=3) as png:
    ...     for band in bands:  # (h, width, 3) uint8 BGR, top to bottom
    ...         png.write_rows(band)

    The rows go to a hidden temporary file beside `path` (io.output.temp_beside), renamed to
    `path` by a successful close(): until then an earlier file at `path` is kept as it was,
    and a failure (an exception inside ``with``, or in close()) removes the temporary file
    rather than leave a truncated PNG there.
    """

    def __init__(self, path: str | Path, width: int, height: int, channels: int = 3,
                 level: int = 6) -> None:
        if channels not in _COLOUR_TYPE:
            raise ValueError(f"{path}: PNG writer takes 1 (grey), 2 (grey + alpha), 3 (BGR) "
                             f"or 4 (BGRA) channels, got {channels}")
        if width <= 0 or height <= 0 or width >= 2**31 or height >= 2**31:
            raise ValueError(f"{path}: invalid PNG size {width}x{height}")
        self.path = Path(path)
        self.width, self.height, self.channels = int(width), int(height), int(channels)
        self._rows = 0
        self._prev = np.zeros((1, self.width * self.channels), np.uint8)
        self._zip = zlib.compressobj(level)
        self._pending = bytearray()
        self._tmp = temp_beside(self.path)
        try:
            self._file = open(self._tmp, "wb")  # noqa: SIM115 (closed in close())
        except OSError as exc:  # named by the path asked for, not the temporary one
            raise OSError(exc.errno, exc.strerror, str(self.path)) from None
        header = struct.pack(">IIBBBBB", self.width, self.height, 8,
                             _COLOUR_TYPE[self.channels], 0, 0, 0)
        try:
            self._file.write(_SIGNATURE + _chunk(b"IHDR", header))
        except BaseException as exc:
            self.abort()
            if isinstance(exc, OSError):
                raise self._named(exc) from None
            raise

    def write_rows(self, rows: np.ndarray) -> None:
        """rows: (h, width) or (h, width, channels) uint8, the next h rows (BGR(A) order).
        They are encoded in chunks of _CHUNK_BYTES (1 MiB, or one row if larger), so the memory
        this takes beyond `rows` is about 9 chunks, however many rows. A write error is an
        OSError naming `path`."""
        rows = np.asarray(rows)
        if rows.dtype != np.uint8:
            raise ValueError(f"{self.path}: rows must be uint8, got {rows.dtype}")
        rows = rows.reshape(rows.shape[0], self.width, -1)
        if rows.shape[2] != self.channels:
            raise ValueError(f"{self.path}: rows have {rows.shape[2]} channels, "
                             f"expected {self.channels}")
        if self._rows + rows.shape[0] > self.height:
            raise ValueError(f"{self.path}: more than {self.height} rows written")
        # The whole band at once took four copies of it (colour swap, contiguous copy, the
        # filtered rows, their bytes): a 286 MB band peaked at 1148 MB more (review 46).
        step = max(1, _CHUNK_BYTES // (self.width * self.channels))
        try:
            for start in range(0, rows.shape[0], step):
                self._write_chunk(rows[start:start + step])
        except OSError as exc:
            raise self._named(exc) from None

    def _named(self, exc: OSError) -> OSError:
        """`exc` named by the path asked for (not the temporary one; cli._os_error prints it:
        a failed write said only 'File too large')."""
        return OSError(exc.errno, exc.strerror or str(exc), str(self.path))

    def _write_chunk(self, rows: np.ndarray) -> None:
        if self.channels >= 3:
            rows = rows[:, :, [2, 1, 0, 3][:self.channels]]  # BGR(A) -> RGB(A), a copy
        flat = np.ascontiguousarray(rows).reshape(rows.shape[0], -1)
        filtered = np.empty((flat.shape[0], flat.shape[1] + 1), np.uint8)
        filtered[:, 0] = 2  # "Up" filter
        np.subtract(flat[:1], self._prev, out=filtered[:1, 1:])
        np.subtract(flat[1:], flat[:-1], out=filtered[1:, 1:])
        self._prev = flat[-1:].copy()
        self._rows += flat.shape[0]
        self._pending += self._zip.compress(filtered)
        if len(self._pending) >= _IDAT_BYTES:
            self._file.write(_chunk(b"IDAT", bytes(self._pending)))
            self._pending.clear()

    def close(self) -> None:
        """Finishes the PNG and renames it to `path`; on any failure removes it. A write error
        is an OSError naming `path`."""
        if self._file.closed:
            return
        try:
            try:
                try:
                    if self._rows != self.height:
                        raise ValueError(f"{self.path}: {self._rows} of {self.height} rows "
                                         "written")
                    self._pending += self._zip.flush()
                    self._file.write(_chunk(b"IDAT", bytes(self._pending)))
                    self._file.write(_chunk(b"IEND", b""))
                finally:
                    self._file.close()
                os.replace(self._tmp, self.path)
            except OSError as exc:
                raise self._named(exc) from None
        except BaseException:
            self._tmp.unlink(missing_ok=True)
            raise

    def abort(self) -> None:
        """Drops the PNG: `path` is left as it was."""
        self._file.close()
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> PngStreamWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_png(path: str | Path, image: np.ndarray, level: int = 6) -> None:
    """Writes a whole (h, w) or (h, w, C) uint8 image (C = 1, 2, 3 or 4; BGR(A) order), e.g. a
    grey + alpha image, which OpenCV's PNG encoder does not take."""
    image = np.asarray(image)
    channels = 1 if image.ndim == 2 else image.shape[2]
    with PngStreamWriter(path, image.shape[1], image.shape[0], channels, level) as png:
        png.write_rows(image)
