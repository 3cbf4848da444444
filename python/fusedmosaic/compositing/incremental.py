"""A live canvas for the sequential methods: frames are blended one at a time as they are placed.

Each `add` warps only the frame's own footprint and touches only the tiles under it, so its cost
is proportional to the frame's area, not to the canvas; the canvas grows by tiles allocated on
first touch, so a live display costs the same per frame at frame 10 and at frame 10 000, and
memory grows with the area covered (16 bytes per pixel for colour), not with the bounding box.

Blending: `linear`, `average` or `last` (see blending.py); multi-band blending needs every frame
before the seams are known and is offline only (`render_mosaic`).

Input: frames are uint8, (H, W) gray or (H, W, 3) BGR, as the dataset contract and the reader
give them (design.md). Other pixel types are refused rather than guessed: the offline compositor
(`render_mosaic`) takes pixel values at face value as 0..255, so a float 0..1 frame renders black
and a 16-bit one saturates; convert first (`np.clip(np.rint(f * 255), 0, 255).astype(np.uint8)`
for 0..1 floats, `(f >> 8).astype(np.uint8)` for 16-bit). A refused call (exception) changes
nothing. A frame whose footprint would grow the canvas bounds beyond `max_pixels` (a stray
placement far from the rest) is skipped and recorded in `skipped`, like an unplaced one, since
`render()` of the whole canvas needs a bounds-sized array.
"""

from __future__ import annotations

from collections import deque

import cv2
import numpy as np

from fusedmosaic.compositing.blending import (
    BlendOptions,
    FrameWarper,
    accumulate,
    as_blend_options,
    resolve,
)
from fusedmosaic.compositing.canvas import ABSURD_AREA_FACTOR, CanvasTooLargeError, footprints

Box = tuple[int, int, int, int]  # x0, y0, x1, y1 (x1, y1 exclusive), canvas pixels


class IncrementalCanvas:
    """Tiled canvas in reference pixels (frame 0's grid) times `scale`.

    >>> canvas = IncrementalCanvas(400, 400, mask=fov, blend="linear")
    >>> for image, G in stream:            # G: frame -> reference homography
    ...     box = canvas.add(image, G)     # None if the frame was left out
    ...     view = canvas.render(box)      # only the part that changed
    """

    def __init__(self, width: int, height: int, *, mask: np.ndarray | None = None,
                 blend: str | BlendOptions = "linear", tile_size: int = 256,
                 scale: float = 1.0, max_pixels: int = 400_000_000,
                 absurd_area_factor: float = ABSURD_AREA_FACTOR) -> None:
        options = as_blend_options(blend)
        if options.blend == "multiband":
            raise ValueError("multiband blending needs the whole sequence (its seams depend on "
                             "every frame); use render_mosaic, or linear / average / last here")
        if tile_size < 16:
            raise ValueError(f"tile_size must be >= 16 px, got {tile_size}")
        if not scale > 0:
            raise ValueError(f"scale must be > 0, got {scale}")
        self.width, self.height = int(width), int(height)
        self.options = options
        self.tile_size = int(tile_size)
        self.scale = float(scale)
        if not max_pixels > 0:
            raise ValueError(f"max_pixels must be > 0, got {max_pixels}")
        self.max_pixels = int(max_pixels)
        self.absurd_area_factor = absurd_area_factor
        self._warpers: dict[int | None, FrameWarper] = {None: FrameWarper(width, height, mask,
                                                                          options)}
        self.tiles: dict[tuple[int, int], np.ndarray] = {}
        self.bounds: Box | None = None
        self.frames_added = 0
        self.skipped: list[tuple[int, str]] = []  # (call number, reason)
        self._areas: deque[float] = deque(maxlen=101)
        self._calls = 0
        self._channels: int | None = None

    # -- frames -------------------------------------------------------------------------------
    def _warper(self, mask: np.ndarray | None) -> FrameWarper:
        if mask is None:
            return self._warpers[None]
        key = hash(np.ascontiguousarray(mask).tobytes())
        if key not in self._warpers:
            if len(self._warpers) > 8:  # keep the default and a few recent masks
                self._warpers.pop(next(k for k in self._warpers if k is not None))
            self._warpers[key] = FrameWarper(self.width, self.height, mask, self.options)
        return self._warpers[key]

    def _screen(self, G: np.ndarray) -> tuple[str | None, float]:
        """(reason to leave the frame out or None, footprint area)."""
        if not np.isfinite(G).all():
            return "not placed", np.nan
        quad = footprints(G[None], self.width, self.height)[0]
        if not np.isfinite(quad).all():
            return "footprint behind the camera", np.nan
        quad = quad.astype(np.float32)
        if not cv2.isContourConvex(quad):
            return "non-convex footprint", np.nan
        area = cv2.contourArea(quad)
        if self._areas and area > self.absurd_area_factor * float(np.median(self._areas)):
            return f"footprint area {area / np.median(self._areas):.0f} x the recent median", area
        return None, area

    def _check_image(self, image, name: int) -> np.ndarray:
        if image is None:
            raise TypeError(f"frame {name}: image is None; expected an (H, W) gray or (H, W, 3) "
                            "BGR uint8 array")
        image = np.asarray(image)
        if image.dtype != np.uint8:
            hint = ""
            if image.dtype.kind == "f":
                hint = " (0..1 floats: np.clip(np.rint(image * 255), 0, 255).astype(np.uint8))"
            elif image.dtype.kind in "iu" and image.dtype.itemsize > 1:
                hint = " (16-bit: (image >> 8).astype(np.uint8))"
            raise ValueError(f"frame {name}: image is {image.dtype}, expected uint8: the canvas "
                             f"does not guess the value range; convert it first{hint}")
        if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3, 4)):
            raise ValueError(f"frame {name}: expected an (H, W) gray or (H, W, 3) BGR image, got "
                             f"shape {image.shape}")
        return image

    def _bounds_with(self, box: Box) -> Box:
        b = self.bounds
        return box if b is None else (min(b[0], box[0]), min(b[1], box[1]),
                                      max(b[2], box[2]), max(b[3], box[3]))

    def add(self, image: np.ndarray, homography: np.ndarray, mask: np.ndarray | None = None,
            *, gain: float = 1.0) -> Box | None:
        """Blends one frame placed by `homography` (frame -> reference). mask: this frame's field
        of view if it differs from the canvas's. Returns the canvas box that changed, or None if
        the frame was left out (unplaced, footprint behind the camera, non-convex, > 20 x the
        recent median area, or growing the canvas bounds beyond `max_pixels`; see `skipped`).

        Raises TypeError (None image), ValueError (pixel type other than uint8, wrong size or
        channel count, homography not 3x3) or CanvasTooLargeError (the tiles would exceed
        `max_pixels`); a call that raises changes nothing, and the next call has the same frame
        number."""
        name = self._calls
        image = self._check_image(image, name)
        G = np.asarray(homography, np.float64)
        if G.shape != (3, 3):
            raise ValueError(f"frame {name}: homography must be 3x3, got {G.shape}")
        warper = self._warper(mask)
        image = warper._check_image(image, name)  # size and channels, before any state change
        reason, area = self._screen(G)
        if self.scale != 1.0:
            G = np.diag([self.scale, self.scale, 1.0]) @ G
        box = warper.box(G) if reason is None else None
        if reason is None and box is None:
            reason = "footprint behind the camera"
        if reason is None:
            # The tiles under the footprint: the area covered is over budget -> error; within
            # budget, but the bounding box would be (a stray placement far from the rest, which
            # render() of the whole canvas could not allocate) -> the frame is left out.
            T = self.tile_size
            tiles = [(ty, tx) for ty in range(box[1] // T, (box[3] - 1) // T + 1)
                     for tx in range(box[0] // T, (box[2] - 1) // T + 1)]
            new = sum(key not in self.tiles for key in tiles)
            if (len(self.tiles) + new) * T * T > self.max_pixels:
                raise CanvasTooLargeError(
                    f"live canvas would need {(len(self.tiles) + new) * T * T} pixels of tiles, "
                    f"above the budget of {self.max_pixels} pixels (frame {name} lands at "
                    f"x {box[0]}..{box[2]}, y {box[1]}..{box[3]})")
            x0, y0, x1, y1 = self._bounds_with(box)
            if (x1 - x0) * (y1 - y0) > self.max_pixels:
                reason = (f"would grow the canvas bounds to {x1 - x0} x {y1 - y0} pixels, above "
                          f"max_pixels {self.max_pixels} (frame lands at x {box[0]}..{box[2]}, "
                          f"y {box[1]}..{box[3]}: a stray placement?)")
        if reason is not None:
            self._calls += 1
            self.skipped.append((name, reason))
            return None
        patch = warper.warp(image, G, gain=gain, name=name)
        channels = patch.data.shape[2]
        self._calls += 1
        self._areas.append(area)
        if self._channels is None:
            self._channels = channels
        for key in tiles:
            tile = self.tiles.get(key)
            if tile is None:
                tile = self.tiles[key] = np.zeros((T, T, channels), np.float32)
            accumulate(tile, key[1] * T, key[0] * T, patch, self.options.blend)
        self.bounds = self._bounds_with(box)
        self.frames_added += 1
        return box

    # -- views --------------------------------------------------------------------------------
    @property
    def nbytes(self) -> int:
        return sum(t.nbytes for t in self.tiles.values())

    def render(self, box: Box | None = None) -> np.ndarray:
        """uint8 (h, w, C) view of `box` (default: everything so far); empty pixels are black.
        Cost proportional to the box; a box of more than `max_pixels` pixels raises
        CanvasTooLargeError (render a part of it instead)."""
        if self._channels is None:
            raise ValueError("no frame added yet")
        box = self.bounds if box is None else box
        try:
            x0, y0, x1, y1 = (int(v) for v in box)
        except (TypeError, ValueError):
            raise ValueError(f"render: box must be (x0, y0, x1, y1) integers, got {box!r}"
                             ) from None
        if not (x1 > x0 and y1 > y0):
            raise ValueError(f"render: empty box {box!r} (need x1 > x0 and y1 > y0)")
        if (x1 - x0) * (y1 - y0) > self.max_pixels:
            raise CanvasTooLargeError(
                f"render: the view of x {x0}..{x1}, y {y0}..{y1} is {x1 - x0} x {y1 - y0} "
                f"pixels, above the budget of {self.max_pixels} pixels (max_pixels); render a "
                "smaller box")
        C = self._channels - 1
        out = np.zeros((y1 - y0, x1 - x0, C), np.uint8)
        T = self.tile_size
        for ty in range(y0 // T, (y1 - 1) // T + 1):
            for tx in range(x0 // T, (x1 - 1) // T + 1):
                tile = self.tiles.get((ty, tx))
                if tile is None:
                    continue
                ax0, ay0 = max(x0, tx * T), max(y0, ty * T)
                ax1, ay1 = min(x1, tx * T + T), min(y1, ty * T + T)
                sub = tile[ay0 - ty * T:ay1 - ty * T, ax0 - tx * T:ax1 - tx * T]
                out[ay0 - y0:ay1 - y0, ax0 - x0:ax1 - x0] = resolve(sub)[0]
        return out[:, :, 0] if C == 1 else out
