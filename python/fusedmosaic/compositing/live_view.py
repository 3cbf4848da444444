"""The mosaic of a live session as it grows, for the people in the room.

`LiveMosaicView` composites each frame once its placement is final (an IncrementalCanvas in frame
0's grid, linear blending) on a worker thread, so the session's loop only hands over the frame,
and publishes the whole canvas at most every ``interval_s``:

- ``preview``: a PNG file replaced atomically (written beside it, then renamed), so an image
  viewer that reloads the file never shows half an image;
- ``server``: an :class:`fusedmosaic.io.igtl.IgtlImageServer`, which sends it as an OpenIGTLink
  IMAGE message to every connected client (3D Slicer's OpenIGTLinkIF shows it as it arrives),
  placed in the world (mosaic_ijk_to_world) so that a reference pixel (frame 0's grid) stays
  at one world point while the canvas grows: reference pixel (x, y)'s centre is at world
  (x, y, 0) * pixel_size_mm (1 mm unless the caller knows the pixels' physical size, e.g.
  pCLE's pixel_size_um / 1000), each image pixel 1 / scale reference pixels.

The canvas (and so the published image) starts where the frames placed so far start, so its
pixel (0, 0) moves as frames extend it up or left: ``summary()`` records the last published
image's ``origin_reference_px`` (its pixel (0, 0) in reference pixels, as report.json's
mosaic.origin_reference_px for mosaic.png), size and ``scale``.

The published canvas is the same linear blend that ``run --blend linear`` renders from the final
homographies, at ``scale`` (the final outputs are written by the session as ``run`` writes
them). A frame without a final placement is not drawn. A failure of the view (a full disk, a
canvas above ``max_pixels``) is recorded in ``problems`` and never stops the session.
"""

from __future__ import annotations

import os
import queue
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from fusedmosaic.compositing.blending import BlendOptions
from fusedmosaic.compositing.canvas import CanvasTooLargeError
from fusedmosaic.compositing.incremental import IncrementalCanvas

_STOP = object()
MAX_QUEUED = 100  # frames waiting for the worker (memory bound: ~50 MB at 400x400 colour)


class LiveMosaicView:
    """See the module docstring. width, height: the frames' size (after undistortion); mask:
    their valid pixels (None: all); lens: a LensUndistortion applied to each frame first
    (lba-emt's homographies hold between undistorted pixels), or None; preview: PNG path or
    None; server: an IgtlImageServer or None (closed by the caller); interval_s: s between
    publications (the last frame is always published by :meth:`close`); scale: canvas pixels
    per reference pixel; max_pixels: the canvas budget (IncrementalCanvas); mask_specular:
    specular highlights not pasted (BlendOptions.mask_specular); pixel_size_mm: a reference
    pixel's size on the tissue for the server's image geometry (None: 1 mm)."""

    def __init__(self, width: int, height: int, *, mask: np.ndarray | None = None, lens=None,
                 preview: str | Path | None = None, server=None, interval_s: float = 1.0,
                 scale: float = 1.0, max_pixels: int = 50_000_000,
                 mask_specular: bool = False, pixel_size_mm: float | None = None) -> None:
        if not (np.isfinite(interval_s) and interval_s >= 0):
            raise ValueError(f"interval_s must be >= 0, got {interval_s}")
        if pixel_size_mm is not None and not (np.isfinite(pixel_size_mm) and pixel_size_mm > 0):
            raise ValueError(f"pixel_size_mm must be a number > 0, got {pixel_size_mm}")
        self.check_preview(preview)
        self.canvas = IncrementalCanvas(
            width, height, mask=mask, blend=BlendOptions("linear", mask_specular=mask_specular),
            scale=scale, max_pixels=max_pixels)
        self.lens = lens
        self.preview = None if preview is None else Path(preview)
        self.server = server
        self.interval_s = float(interval_s)
        self.pixel_size_mm = None if pixel_size_mm is None else float(pixel_size_mm)
        # the last published image: its pixel (0, 0) in reference pixels, its size (w, h)
        self.origin_reference_px: tuple[float, float] | None = None
        self.view_size: tuple[int, int] | None = None
        self.frames_added = 0
        self.published = 0
        self.problems: dict[str, int] = {}  # what went wrong -> how often
        self._queue: queue.Queue = queue.Queue()
        self._last_publish = -np.inf
        self._dirty = False
        self._thread = threading.Thread(target=self._work, name="live-mosaic-view", daemon=True)
        self._thread.start()

    @staticmethod
    def check_preview(preview: str | Path | None) -> None:
        if preview is not None and Path(preview).suffix.lower() != ".png":
            raise ValueError(f"{preview}: the preview is a PNG file (name it .png)")

    def add(self, image: np.ndarray, homography: np.ndarray) -> None:
        """A frame and its final frame -> reference homography (the call returns at once). A
        worker more than ``MAX_QUEUED`` frames behind leaves the frame out of the view (counted
        in ``problems``) rather than holding ever more images."""
        if self._queue.qsize() >= MAX_QUEUED:
            self._problem(f"frame left out of the view: {MAX_QUEUED} frames were waiting")
            return
        self._queue.put((image, np.asarray(homography, np.float64)))

    def close(self, timeout_s: float = 30.0) -> None:
        """Composites what is queued, publishes the result once more, stops the worker."""
        self._queue.put(_STOP)
        self._thread.join(timeout=timeout_s)
        if self._thread.is_alive():
            self._problem(f"the view was still compositing after {timeout_s:g} s")

    def _problem(self, what: str) -> None:
        self.problems[what] = self.problems.get(what, 0) + 1

    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                break
            image, G = item
            try:
                if self.lens is not None:
                    image = self.lens.image(image)
                if self.canvas.add(image, G) is not None:
                    self.frames_added += 1
                    self._dirty = True
            except (ValueError, cv2.error) as exc:  # CanvasTooLargeError is a ValueError
                self._problem(f"frame left out of the view: {exc}")
            if self._dirty and time.monotonic() - self._last_publish >= self.interval_s:
                self._publish()
        if self._dirty:
            self._publish()

    def _publish(self) -> None:
        self._last_publish = time.monotonic()
        self._dirty = False
        try:
            view = self.canvas.render()  # (the worker's thread: bounds are the view's)
        except CanvasTooLargeError as exc:
            self._problem(f"not published: {exc}")
            return
        s = self.canvas.scale
        origin = (self.canvas.bounds[0] / s, self.canvas.bounds[1] / s)
        self.origin_reference_px, self.view_size = origin, (view.shape[1], view.shape[0])
        if self.preview is not None:
            tmp = self.preview.with_name(f".{self.preview.name}.{os.getpid()}.tmp.png")
            try:
                ok, data = cv2.imencode(".png", view, [cv2.IMWRITE_PNG_COMPRESSION, 1])
                if not ok:
                    raise OSError("PNG encoding failed")
                tmp.write_bytes(data.tobytes())
                os.replace(tmp, self.preview)
            except OSError as exc:
                tmp.unlink(missing_ok=True)
                self._problem(f"{self.preview}: not written: {exc.strerror or exc}")
        if self.server is not None:
            from fusedmosaic.io.igtl import mosaic_ijk_to_world

            self.server.send(view, ijk_to_world=mosaic_ijk_to_world(origin, s,
                                                                    self.pixel_size_mm))
        self.published += 1

    def summary(self) -> dict:
        """For report.json: frames drawn, publications, the last published image's place
        (origin_reference_px: its pixel (0, 0) in reference pixels, None before the first;
        width, height; scale: its pixels per reference pixel; pixel_size_mm: the world's mm per
        reference pixel in the server's image geometry), clients, problems."""
        origin = self.origin_reference_px
        out = {"frames_drawn": self.frames_added, "published": self.published,
               "interval_s": self.interval_s,
               "preview": None if self.preview is None else str(self.preview),
               "origin_reference_px": None if origin is None else [float(v) for v in origin],
               "width": None if self.view_size is None else self.view_size[0],
               "height": None if self.view_size is None else self.view_size[1],
               "scale": self.canvas.scale,
               "pixel_size_mm": 1.0 if self.pixel_size_mm is None else self.pixel_size_mm,
               "problems": dict(self.problems)}
        if self.server is not None:
            out["server"] = {"address": self.server.address,
                             "device": self.server.device_name,
                             "clients": self.server.clients_served,
                             "messages_sent": self.server.messages_sent}
        return out
