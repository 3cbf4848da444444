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
them). A frame without a final placement is not drawn. A failure of the view (a full disk, tiles
above ``max_pixels``, any error of the worker) is recorded in ``problems`` (a count per kind,
without frame numbers or coordinates, so it stays small however long the session;
``problem_details`` has the first frame of each kind and its full message) and never stops the
session or the worker. So is each frame the canvas leaves out, by its reason ("frame left out
of the view: " and IncrementalCanvas's reason, its figures replaced by N: a placement collapsed
to a point, a footprint 20 x the recent median, a stray, ...): a view that stops growing says
why (a collapsed first frame left every later one out as "1000000 x the recent median", and
the summary showed 1 frame drawn and no problem; review 50).

Frames placed far apart (more than the canvas's stray_diagonals frame diagonals from every
earlier frame: a re-localisation accepted as a new place, or a jump within the budget) make
places (IncrementalCanvas.places); the view then shows the place of the latest frames only
(IncrementalCanvas.view_bounds: a lone far frame does not move it), told once (``notify``;
``summary()``: ``places``). The whole bounding box, shrunk to the view's budget, made the latest
frames a line 2 pixels high after a re-localisation far away (review 50); the final outputs
show every place.

The canvas's bounding box can outgrow its tiles (a diagonal sweep's grows with the square of its
length): a bounding box above the view's budget, min(``max_pixels``, VIEW_MAX_PIXELS), is
published shrunk by the least whole factor that fits it (area averaged: IncrementalCanvas.render's
step), and the view keeps following the session (it stopped publishing there, for the rest of
the session; review 46). The first such publication is told once (``notify``), and they are
counted (``summary()``: ``reduced``; ``scale`` is the last published image's).

The worker renders each publication and hands it to a publisher thread, which writes the
preview and sends it to the server's clients: compositing never waits for a disk or a client (a
client taking the mosaic at 1.5 MB/s held the worker 5.4 s a publication, and frames beyond the
MAX_QUEUED waiting were never drawn; review). The publisher holds one publication waiting, the
latest: one rendered while it is still busy replaces the one waiting, not yet started
(``superseded``), so a slow client gets the newest view next, never a queue of old ones.
:meth:`close` delivers the last one. ``published`` counts the publications delivered.

Each publication renders and encodes the whole canvas, at a cost growing with it (4096 x 4096:
~1.8 s). So that the view never spends more than about 1 / PUBLISH_DUTY of a core on them, the
next publication waits at least PUBLISH_DUTY x the last one's cost (``summary()``:
``publish_s``, ``effective_interval_s``): the render's time on the worker plus the publisher's
CPU time for the last delivery (encoding, writing, packing; the time spent waiting for clients
is no cost). An OpenIGTLink IMAGE holds at most 65535 px a side: a larger canvas is sent shrunk
by a whole factor (area averaged; its geometry says so), and counted in ``server.downscaled``.
"""

from __future__ import annotations

import os
import queue
import re
import threading
import time
import warnings
from pathlib import Path

import cv2
import numpy as np

from fusedmosaic.compositing.blending import BlendOptions
from fusedmosaic.compositing.canvas import CanvasTooLargeError
from fusedmosaic.compositing.incremental import IncrementalCanvas, reason_kind
from fusedmosaic.io.output import write_image_file

_STOP = object()
MAX_QUEUED = 100  # frames waiting for the worker (memory bound: ~50 MB at 400x400 colour)
# The next publication waits at least this many times the last one's cost (render, encode,
# send): the view's worker spends at most ~1/4 of a core on publishing, whatever the canvas.
PUBLISH_DUTY = 4.0
IGTL_MAX_SIDE = 65535  # an OpenIGTLink IMAGE's size fields are uint16
# A published image holds at most this many pixels (a larger bounding box is shrunk): rendering
# and encoding it costs ~1.8 s at 4096 x 4096, so ~5 s here, and PUBLISH_DUTY spaces the
# publications by 4x that.
VIEW_MAX_PIXELS = 50_000_000
MAX_PROBLEM_KINDS = 32  # distinct problem texts kept; further kinds are counted together


class LiveMosaicView:
    """See the module docstring. width, height: the frames' size (after undistortion); mask:
    their valid pixels (None: all); lens: a LensUndistortion applied to each frame first
    (lba-emt's homographies hold between undistorted pixels), or None; preview: PNG path or
    None; server: an IgtlImageServer or None (closed by the caller); interval_s: s between
    publications (the last frame is always published by :meth:`close`); scale: canvas pixels
    per reference pixel; max_pixels: the canvas budget (IncrementalCanvas: the tiles, 16 bytes
    a pixel for colour; a published image holds at most min(max_pixels, VIEW_MAX_PIXELS), a
    larger bounding box being shrunk: module notes); mask_specular: specular highlights not
    pasted (BlendOptions.mask_specular); pixel_size_mm: a reference pixel's size on the tissue
    for the server's image geometry (None: 1 mm); notify(text): told once, on the worker's
    thread, when the view is first published shrunk and when it first shows one place of
    several (None: a warning); its errors are
    ignored."""

    def __init__(self, width: int, height: int, *, mask: np.ndarray | None = None, lens=None,
                 preview: str | Path | None = None, server=None, interval_s: float = 1.0,
                 scale: float = 1.0, max_pixels: int = 50_000_000,
                 mask_specular: bool = False, pixel_size_mm: float | None = None,
                 notify=None) -> None:
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
        self.published = 0  # publications delivered (preview written, sent: as far as they went)
        self.superseded = 0  # publications replaced by a newer one before the publisher took them
        self.problems: dict[str, int] = {}  # what went wrong -> how often
        self._problems_lock = threading.Lock()  # (the worker and the publisher record them)
        # each kind's first occurrence: {"frame": the view's frame number, "message": full text}
        self.problem_details: dict[str, dict] = {}
        self._queue: queue.Queue = queue.Queue()
        self._last_publish = -np.inf
        self._dirty = False
        self._received = 0  # frames handed to add(), numbering them for problem_details
        self._current: int | None = None  # the frame the worker is at
        self.publish_s: list[float] = []  # the last publications' costs (module notes), s
        self.effective_interval_s = self.interval_s
        self.igtl_downscaled = 0  # images sent to the server shrunk to fit OpenIGTLink
        self.igtl_scale: float | None = None  # the last sent image's pixels per reference pixel
        self.view_max_pixels = min(self.canvas.max_pixels, VIEW_MAX_PIXELS)
        self.reduced = 0  # publications shrunk to fit view_max_pixels (module notes)
        self.view_scale: float | None = None  # the last published image's pixels per ref. pixel
        self._notify = notify
        self._told_reduced = False
        self._told_places = False
        # the publication waiting for the publisher (frame, view, origin, scale), or None
        self._waiting: tuple | None = None
        self._waiting_cv = threading.Condition()
        self._closing = False  # the publisher ends once nothing waits
        self._deliver_cpu_s = 0.0  # the publisher's CPU time for the last delivery, s
        self._thread = threading.Thread(target=self._work, name="live-mosaic-view", daemon=True)
        self._publisher = threading.Thread(target=self._deliver_loop,
                                           name="live-mosaic-publisher", daemon=True)
        self._thread.start()
        self._publisher.start()

    @staticmethod
    def check_preview(preview: str | Path | None) -> None:
        if preview is not None and Path(preview).suffix.lower() != ".png":
            raise ValueError(f"{preview}: the preview is a PNG file (name it .png)")

    def add(self, image: np.ndarray, homography: np.ndarray) -> None:
        """A frame and its final frame -> reference homography (the call returns at once). A
        worker more than ``MAX_QUEUED`` frames behind leaves the frame out of the view (counted
        in ``problems``) rather than holding ever more images."""
        index = self._received
        self._received += 1
        if self._queue.qsize() >= MAX_QUEUED:
            self._problem(f"frame left out of the view: {MAX_QUEUED} frames were waiting",
                          frame=index)
            return
        self._queue.put((index, image, np.asarray(homography, np.float64)))

    def close(self, timeout_s: float = 30.0) -> None:
        """Composites what is queued, publishes the result once more (delivered: written and
        sent), stops the worker and the publisher, within timeout_s in all."""
        end = time.monotonic() + timeout_s
        self._queue.put(_STOP)
        self._thread.join(timeout=timeout_s)
        if self._thread.is_alive():
            self._problem(f"the view was still compositing after {timeout_s:g} s")
        with self._waiting_cv:
            self._closing = True
            self._waiting_cv.notify()
        self._publisher.join(timeout=max(end - time.monotonic(), 0.0))
        if self._publisher.is_alive():
            self._problem(f"the view was still publishing after {timeout_s:g} s")

    def _problem(self, what: str, frame: int | None = None, message: str | None = None
                 ) -> None:
        """Counts a problem of kind `what` (no frame numbers in it); the first of each kind
        keeps its frame and full message in problem_details."""
        with self._problems_lock:
            if what not in self.problems and len(self.problems) >= MAX_PROBLEM_KINDS:
                what = "other problems (more kinds than the report keeps)"
            if what not in self.problems:
                self.problem_details[what] = {"frame": frame, "message": message or what}
            self.problems[what] = self.problems.get(what, 0) + 1

    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is _STOP:
                break
            index, image, G = item
            self._current = index
            try:
                if self.lens is not None:
                    image = self.lens.image(image)
                if self.canvas.add(image, G) is not None:
                    self.frames_added += 1
                    self._dirty = True
                else:
                    reason = self.canvas.skipped[-1][1]
                    self._problem(f"frame left out of the view: {reason_kind(reason)}",
                                  frame=index, message=reason)
            except Exception as exc:  # noqa: BLE001 (recorded: the worker must not die)
                self._problem(f"frame left out of the view: {_kind(exc)}", frame=index,
                              message=f"{type(exc).__name__}: {exc}")
            if self._dirty and time.monotonic() - self._last_publish >= self.effective_interval_s:
                self._publish_safely()
        if self._dirty:
            self._publish_safely()

    def _publish_safely(self) -> None:
        start = time.monotonic()
        try:
            self._publish()
        except Exception as exc:  # noqa: BLE001 (recorded: the worker must not die)
            self._problem(f"not published: {_kind(exc)}", frame=self._current,
                          message=f"{type(exc).__name__}: {exc}")
        cost = time.monotonic() - start + self._deliver_cpu_s
        self.publish_s = (self.publish_s + [cost])[-20:]
        self.effective_interval_s = max(self.interval_s, PUBLISH_DUTY * cost)

    def _publish(self) -> None:
        """Renders the canvas (the worker's) and hands it to the publisher, replacing the
        publication waiting, if any (latest wins)."""
        self._last_publish = time.monotonic()
        self._dirty = False
        # (the worker's thread: bounds are the view's) the place of the latest frames only,
        # once frames were placed far apart (module notes)
        x0, y0, x1, y1 = box = self.canvas.view_bounds
        if self.canvas.places > 1 and not self._told_places:
            self._told_places = True
            self._tell(f"live view: frames were placed {self.canvas.places} places far apart "
                       f"(more than {self.canvas.stray_diagonals:g} frame diagonals: a "
                       "re-localisation?); the view shows the place of the latest frames, the "
                       "final mosaic all of them (report.json live view places)")
        step = shrink_step(x1 - x0, y1 - y0, self.view_max_pixels)
        view = self.canvas.render(box, step=step)
        if step > 1:
            self.reduced += 1
            if not self._told_reduced:
                self._told_reduced = True
                self._tell(f"live view: the mosaic's bounding box ({x1 - x0} x {y1 - y0} "
                           f"pixels) is above the view's budget of {self.view_max_pixels} "
                           f"pixels: it is published shrunk {step} times (area averaged), more "
                           "as it grows; the final outputs are at full resolution "
                           "(report.json live view reduced)")
        # view pixel (0, 0): the mean of canvas pixels x0 .. x0 + step - 1 (y0 ..), centred at
        # canvas x0 + (step - 1) / 2, i.e. reference pixel that / scale
        c = self.canvas.scale
        s = c / step
        origin = ((x0 + (step - 1) / 2) / c, (y0 + (step - 1) / 2) / c)
        with self._waiting_cv:
            if self._waiting is not None:
                self.superseded += 1
            self._waiting = (self._current, view, origin, s)
            self._waiting_cv.notify()

    def _tell(self, text: str) -> None:
        try:
            if self._notify is not None:
                self._notify(text)
            else:
                warnings.warn(text, stacklevel=2)
        except Exception:  # noqa: BLE001 (a warning made an error must not stop the view)
            pass

    def _deliver_loop(self) -> None:
        """The publisher: delivers the publication waiting, until close() and none waits."""
        while True:
            with self._waiting_cv:
                while self._waiting is None and not self._closing:
                    self._waiting_cv.wait()
                if self._waiting is None:
                    return
                publication, self._waiting = self._waiting, None
            start = time.thread_time()  # (CPU: waiting for a slow client costs nothing)
            try:
                self._deliver(*publication)
            except Exception as exc:  # noqa: BLE001 (recorded: the publisher must not die)
                self._problem(f"not published: {_kind(exc)}", frame=publication[0],
                              message=f"{type(exc).__name__}: {exc}")
            self._deliver_cpu_s = time.thread_time() - start

    def _deliver(self, frame: int | None, view: np.ndarray, origin: tuple[float, float],
                 s: float) -> None:
        """Writes the preview and sends the view to the server (the publisher's thread)."""
        self.origin_reference_px, self.view_size = origin, (view.shape[1], view.shape[0])
        self.view_scale = s
        if self.preview is not None:
            tmp = self.preview.with_name(f".{self.preview.name}.{os.getpid()}.tmp.png")
            try:
                write_image_file(tmp, view, [cv2.IMWRITE_PNG_COMPRESSION, 1])
                os.replace(tmp, self.preview)
            except (OSError, ValueError) as exc:  # (ValueError: ImageEncodingError)
                tmp.unlink(missing_ok=True)
                self._problem(f"{self.preview}: not written: "
                              f"{getattr(exc, 'strerror', None) or exc}", frame=frame)
        if self.server is not None:
            from fusedmosaic.io.igtl import mosaic_ijk_to_world

            image, step = _fit_igtl(view)
            if step > 1:
                self.igtl_downscaled += 1
            # pixel i of the image shrunk `step` times: the mean of view pixels i*step ..
            # i*step + step - 1, centred at view pixel i*step + (step - 1) / 2
            at = (origin[0] + (step - 1) / (2 * s), origin[1] + (step - 1) / (2 * s))
            self.igtl_scale = s / step
            self.server.send(image, ijk_to_world=mosaic_ijk_to_world(at, s / step,
                                                                     self.pixel_size_mm))
        self.published += 1

    def summary(self) -> dict:
        """For report.json: frames drawn, publications (delivered; superseded), the last
        published image's place (origin_reference_px: its pixel (0, 0) in reference pixels,
        None before the first; width, height; scale: its pixels per reference pixel;
        pixel_size_mm: the world's mm per reference pixel in the server's image geometry),
        clients, problems."""
        origin = self.origin_reference_px
        with self._problems_lock:  # (the publisher may be recording one)
            problems = dict(self.problems)
            details = {k: dict(v) for k, v in self.problem_details.items()}
        out = {"frames_drawn": self.frames_added, "published": self.published,
               # replaced by a newer one before the publisher was free (a slow client, disk)
               "superseded": self.superseded,
               "interval_s": self.interval_s,
               "preview": None if self.preview is None else str(self.preview),
               "origin_reference_px": None if origin is None else [float(v) for v in origin],
               "width": None if self.view_size is None else self.view_size[0],
               "height": None if self.view_size is None else self.view_size[1],
               "scale": self.canvas.scale if self.view_scale is None else self.view_scale,
               # publications shrunk to fit the view's budget (its bounding box above it)
               "reduced": self.reduced, "view_max_pixels": self.view_max_pixels,
               # groups of frames placed far apart; the view shows the latest frames' one
               "places": self.canvas.places,
               "pixel_size_mm": 1.0 if self.pixel_size_mm is None else self.pixel_size_mm,
               # a publication's cost (render, and the publisher's CPU time for the last
               # delivery) and the interval it imposes
               "publish_s": ({"last": self.publish_s[-1], "max": max(self.publish_s)}
                             if self.publish_s else None),
               "effective_interval_s": self.effective_interval_s,
               "problems": problems, "problem_details": details}
        if self.server is not None:
            out["server"] = {"address": self.server.address,
                             "device": self.server.device_name,
                             "clients": self.server.clients_served,
                             "messages_sent": self.server.messages_sent,
                             # images shrunk to fit OpenIGTLink's 65535 px a side; the last
                             # one's pixels per reference pixel
                             "downscaled": self.igtl_downscaled,
                             "scale": self.igtl_scale}
        return out


def _kind(exc: BaseException) -> str:
    """An error's text without what changes from frame to frame (its number, where it lands,
    pixel counts), for the problems' keys."""
    if isinstance(exc, CanvasTooLargeError):
        return "the live canvas's tiles would exceed max_pixels"
    text = re.sub(r"^frame \d+: ", "", str(exc).splitlines()[0] if str(exc) else "")
    text = re.sub(r"\(frame \d+[^)]*\)", "", text)
    text = re.sub(r"-?\d+(\.\d+)?(e[+-]?\d+)?", "N", text)
    return f"{type(exc).__name__}: {text.strip()}"[:200]


def shrink_step(width: int, height: int, max_pixels: int) -> int:
    """The least whole factor by which a width x height image shrinks (padded to a multiple of
    it) to at most max_pixels pixels."""
    lo, hi = 1, max(width, height, 1)  # (the pixels are non-increasing with the step)
    while lo < hi:
        mid = (lo + hi) // 2
        if -(-width // mid) * -(-height // mid) > max_pixels:
            lo = mid + 1
        else:
            hi = mid
    return lo


def _fit_igtl(view: np.ndarray) -> tuple[np.ndarray, int]:
    """(image, step): `view` shrunk by the whole factor `step` (area averaged, padded with black
    to a multiple of it) when a side exceeds OpenIGTLink's 65535 px, else as it is (step 1)."""
    h, w = view.shape[:2]
    step = -(-max(h, w) // IGTL_MAX_SIDE)
    if step <= 1:
        return view, 1
    ph, pw = -(-h // step) * step, -(-w // step) * step
    padded = np.zeros((ph, pw) + view.shape[2:], view.dtype)
    padded[:h, :w] = view
    small = cv2.resize(padded, (pw // step, ph // step), interpolation=cv2.INTER_AREA)
    return small, step
