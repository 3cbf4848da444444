"""Video of the sequential creation of a mosaic (seed 000, Sec. 4.2.4, Videos 1-3): each video
frame shows the mosaic after blending one more image, with that image's outline drawn.

The mosaic is kept by an IncrementalCanvas at the video's scale, and only the region a new frame
touched is re-rendered into the displayed image, so each video frame costs the new frame's area
plus the encoding of one video frame, at frame 10 as at frame 10 000.
"""

from __future__ import annotations

import dataclasses
import errno
import os
import struct
from pathlib import Path

import cv2
import numpy as np

from fusedmosaic.compositing.blending import BlendOptions, as_blend_options, fov_mask_bool
from fusedmosaic.compositing.incremental import IncrementalCanvas
from fusedmosaic.io._paths import opencv_path
from fusedmosaic.io.output import temp_beside

OUTLINE_BGR = (0, 255, 0)  # the current frame's outline: green
# Containers that take OpenCV's 'mp4v' (MPEG-4 part 2) stream; others (.gif, .txt, none) fail.
VIDEO_SUFFIXES = (".mp4", ".m4v", ".mov", ".avi", ".mkv")
ATOM_SUFFIXES = (".mp4", ".m4v", ".mov")  # ISO base media / QuickTime: a sequence of atoms


def check_video_suffix(path: str | Path) -> None:
    """ValueError naming `path` unless its extension is one the mp4v writer supports."""
    if Path(path).suffix.lower() not in VIDEO_SUFFIXES:
        raise ValueError(f"{path}: unsupported video file extension "
                         f"{Path(path).suffix or '(none)'!r}; use one of "
                         f"{', '.join(VIDEO_SUFFIXES)}")


def fov_outline(width: int, height: int, mask: np.ndarray | None = None,
                points: int = 96) -> np.ndarray:
    """(P, 2) float64 polygon along the field-of-view edge in frame pixels (the image rectangle
    without a mask)."""
    if mask is None:
        return np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5],
                         [-0.5, height - 0.5]])
    m = fov_mask_bool(mask, width, height).astype(np.uint8)
    contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contour = max(contours, key=cv2.contourArea)[:, 0, :].astype(np.float64)
    step = max(1, len(contour) // points)
    return contour[::step]


class MosaicVideoWriter:
    """Writes the growing mosaic to an MP4 (OpenCV VideoWriter, 'mp4v').

    bounds: (x0, y0, x1, y1) of the final mosaic in reference pixels (e.g. a CanvasPlan), so the
    video frame is fixed; scaled down so its longer side is at most `max_side`.
    The file is written to a temporary name beside `path` and renamed by close(), so a reader
    never sees a partial video; on an exception inside ``with`` it is removed."""

    def __init__(self, path: str | Path, bounds: tuple[int, int, int, int], width: int,
                 height: int, *, mask: np.ndarray | None = None,
                 blend: str | BlendOptions = "linear", fps: float = 25.0, max_side: int = 1280,
                 outline: bool = True) -> None:
        options = as_blend_options(blend)
        if options.blend == "multiband":  # not incremental: show the linear blend instead
            # (the rest kept: rebuilt, the options lost mask_specular, and lba-emt's video had
            # each frame's highlights as a trail along the path; review 46)
            options = dataclasses.replace(options, blend="linear")
        if not fps > 0:
            raise ValueError(f"video fps must be > 0, got {fps}")
        check_video_suffix(path)
        # (before any folder is made; the temporary name beside it, written and read back by
        # OpenCV, is then UTF-8 too)
        opencv_path(path, "write a video")
        self.path = Path(path)
        x0, y0, x1, y1 = bounds
        self.scale = min(1.0, max_side / max(x1 - x0, y1 - y0))
        s = self.scale
        self.origin = (int(np.floor(x0 * s)), int(np.floor(y0 * s)))
        vw = int(np.ceil(x1 * s)) - self.origin[0]
        vh = int(np.ceil(y1 * s)) - self.origin[1]
        self.size = (vw + vw % 2, vh + vh % 2)  # even sizes: safest for MPEG-4 encoders
        self.canvas = IncrementalCanvas(width, height, mask=mask, blend=options,
                                        scale=s, tile_size=128)
        self.display = np.zeros((self.size[1], self.size[0], 3), np.uint8)
        self.outline = fov_outline(width, height, mask) if outline else None
        self.frames_written = 0
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = temp_beside(self.path)
        self._writer = cv2.VideoWriter(str(self._tmp), cv2.VideoWriter_fourcc(*"mp4v"),
                                       float(fps), self.size)
        if not self._writer.isOpened():
            raise ValueError(f"{self.path}: cannot open an mp4v video writer (OpenCV without "
                             "video encoding support, or an unwritable folder?)")

    def add(self, image: np.ndarray, homography: np.ndarray, *, label: str | None = None,
            gain: float = 1.0) -> bool:
        """Blends one frame and writes one video frame; False if the frame was left out."""
        box = self.canvas.add(image, homography, gain=gain)
        if box is None:
            return False
        ox, oy = self.origin
        vw, vh = self.size
        x0, y0 = max(box[0], ox), max(box[1], oy)
        x1, y1 = min(box[2], ox + vw), min(box[3], oy + vh)
        if x0 < x1 and y0 < y1:
            view = self.canvas.render((x0, y0, x1, y1))
            if view.ndim == 2:
                view = cv2.cvtColor(view, cv2.COLOR_GRAY2BGR)
            self.display[y0 - oy:y1 - oy, x0 - ox:x1 - ox] = view
        frame = self.display.copy()
        if self.outline is not None:
            G = np.diag([self.scale, self.scale, 1.0]) @ np.asarray(homography, np.float64)
            pts = np.hstack([self.outline, np.ones((len(self.outline), 1))]) @ G.T
            pts = pts[:, :2] / pts[:, 2:] - [ox, oy]
            cv2.polylines(frame, [np.rint(pts * 4).astype(np.int32)], True, OUTLINE_BGR,
                          thickness=2, lineType=cv2.LINE_AA, shift=2)
        if label:
            cv2.putText(frame, label, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1,
                        cv2.LINE_AA)
        self._writer.write(frame)
        self.frames_written += 1
        return True

    def close(self) -> None:
        """Finishes the video and renames it to `path`; on any failure (an interrupt too)
        removes the temporary file."""
        if self._writer is None:
            return
        try:
            self._finish()
        except BaseException:
            self._writer = None
            self._tmp.unlink(missing_ok=True)
            raise

    def _finish(self) -> None:
        self._writer.release()
        self._writer = None
        if self.frames_written == 0:
            self._tmp.unlink(missing_ok=True)
            raise ValueError(f"{self.path}: no frame could be placed; no video written")
        # VideoWriter reports no write error: a full disk left an unplayable file (no index)
        # and exit 0. Read the header back (~2 ms) and count the frames (exact in all five
        # containers, measured; one frame of slack for a container that counts by duration,
        # but never none: a one-frame video that does not open is refused too).
        reader = cv2.VideoCapture(str(self._tmp))
        readable = int(reader.get(cv2.CAP_PROP_FRAME_COUNT)) if reader.isOpened() else 0
        reader.release()
        if readable < 1 or abs(readable - self.frames_written) > 1:
            self._tmp.unlink(missing_ok=True)
            raise OSError(errno.EIO, f"the video does not read back ({readable} of "
                          f"{self.frames_written} frames; a full disk?): no video written",
                          str(self.path))
        # A file cut in its last atom (the index's tail: 71 bytes short, its metadata gone)
        # still decodes every frame: the atoms' sizes must add up to the file's.
        problem = (_atoms_problem(self._tmp) if self.path.suffix.lower() in ATOM_SUFFIXES
                   else None)
        if problem is not None:
            self._tmp.unlink(missing_ok=True)
            raise OSError(errno.EIO, f"the video is incomplete ({problem}; a full disk?): no "
                          "video written", str(self.path))
        os.replace(self._tmp, self.path)

    def abort(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> MosaicVideoWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()  # (which removes the temporary file if it fails)
        else:
            self.abort()


def _atoms_problem(path: Path) -> str | None:
    """What is wrong with the top-level atoms of an MP4 / QuickTime file (each: a 32-bit size,
    1 for a 64-bit one after the type, 0 for "to the end"; then a 4-byte type), None if their
    sizes add up to the file's."""
    size = path.stat().st_size
    offset = 0
    with open(path, "rb") as f:
        while offset < size:
            f.seek(offset)
            header = f.read(16)
            if len(header) < 8:
                return f"{size - offset} stray bytes at its end"
            length, kind = struct.unpack(">I4s", header[:8])
            name = kind.decode("latin-1")
            least = 8
            if length == 1:
                if len(header) < 16:
                    return f"the atom '{name}' at byte {offset} is cut in its header"
                length, least = struct.unpack(">Q", header[8:16])[0], 16
            elif length == 0:
                length = size - offset
            if length < least:
                return f"the atom '{name}' at byte {offset} has an invalid size {length}"
            if offset + length > size:
                return (f"the atom '{name}' at byte {offset} declares {length} bytes, "
                        f"{offset + length - size} beyond the file's end at {size}")
            offset += length
    return None


def write_creation_video(path: str | Path, frames, homographies: np.ndarray, width: int,
                         height: int, bounds: tuple[int, int, int, int], *,
                         use: np.ndarray | None = None, mask: np.ndarray | None = None,
                         blend: str | BlendOptions = "linear", fps: float = 25.0,
                         max_side: int = 1280, gains: np.ndarray | None = None,
                         frame_ids: np.ndarray | None = None, progress: bool = False) -> int:
    """The sequential creation of the mosaic, one video frame per placed frame, in frame order.
    frames: a sequence (frames[k]). Returns the number of video frames written."""
    from tqdm import tqdm

    G = np.asarray(homographies, np.float64)
    use = np.isfinite(G).all(axis=(1, 2)) if use is None else use
    ks = np.flatnonzero(use)
    with MosaicVideoWriter(path, bounds, width, height, mask=mask, blend=blend, fps=fps,
                           max_side=max_side) as video:
        for k in tqdm(ks, desc="video", disable=not progress, leave=False):
            ident = int(frame_ids[k]) if frame_ids is not None else int(k)
            video.add(frames[int(k)], G[k], label=f"frame {ident}",
                      gain=1.0 if gains is None else float(gains[k]))
        return video.frames_written
