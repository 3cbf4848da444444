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
nothing.

Budget (`max_pixels`): it bounds the memory actually held, the pixels of the allocated tiles
(`tile_pixels`; a frame that would take them above it is refused with CanvasTooLargeError), and
the size of any one `render()` view. It does not bound the bounding box: a long or diagonal sweep
has a bounding box growing with the square of its length while its tiles grow with the length,
and all its frames are kept; once the bounding box is above `max_pixels`, `render()` of the
whole canvas raises CanvasTooLargeError and the caller renders sub-boxes (e.g. the box `add`
returned) or the whole shrunk (`render`'s step, at a cost of the tiles, not the box). Only a
stray frame is left out for the bounding box: one that would grow the bounds beyond
`max_pixels` while landing more than `stray_diagonals` (10) of its own diagonals away from
every frame placed so far (a wild jump such as a placement 1e6 px off; it is recorded in
`skipped`, like an unplaced frame). A far frame that keeps the bounds within `max_pixels` is
kept, as is anything landing near the content already there.

A genuine far jump (the estimator re-localised the scope elsewhere on the surface) looks like a
stray at first. After `stray_rebase` (3) strays in a row that are mutually consistent (each
within `stray_diagonals` of its own diagonals of the previous stray), the new place is accepted,
as the robot gate's `robot_gate_rebase` accepts a new robot offset: the first `stray_rebase` - 1
stay in `skipped`, the `stray_rebase`-th is placed (its call number is recorded in `rebased`)
and so is everything after it near it, since it is now placed content. A placed frame ends the
run, so an isolated stray between frames near the content is skipped and changes nothing, and
strays at different far places do not add up (a stray far from the previous one starts a new
run); a frame left out for another reason (unplaced, behind the camera, ...) has no position
and neither counts nor ends the run. An accepted far place costs only the tiles under its
footprints (the tile budget still applies); the bounding box then spans both places, so
`render()` of the whole raises and the caller renders sub-boxes. `stray_rebase=None` never
accepts a far place (every later frame near it is a stray too).

Footprint size. A frame is left out when its footprint's area is below canvas.MIN_AREA_FRACTION
of the frame's own pixel area (a placement collapsed towards a point: a near-singular homography;
canvas.footprint_problem's floor, so mosaic.png leaves it out too), or
more than `absurd_area_factor` (20) times above or below the median of the last 101 placed
frames' (or its extent, its bounding box's diagonal, above 20 x theirs). That median is seeded
by whichever frames are placed first, so a bad first placement poisoned it: a collapsed first
frame (1e-6 of the area) left every later frame out as "1000000 x the recent median", for the
whole session (review 50: a live view of 3 x 3 px, 1 frame drawn of 40). The floor leaves such a
frame out; one of 1 / 100 of the area is above it, so the median also re-bases as the stray
rule does: frames left out by these screens in a row whose areas and
extents agree with each other (each within CONSISTENT_SIZE_FACTOR of the previous one's, no
frame passing the screens in between) are a new footprint size once they outnumber the frames
the median holds; the last of them is placed, the median restarts from that run
(`median_rebased`), and the earlier ones stay left out. A bad seed costs one frame; an
established median (101 frames) needs 102 frames in a row of a consistent new size, so a short
glitch never moves it.

`skipped` keeps the first and the last SKIPPED_KEPT (call number, reason) of the frames left out
(all of them up to 2 x SKIPPED_KEPT), `skipped_total` counts them all and `skipped_counts` by
reason (its figures replaced by N): bounded however long a live session runs (a list of every
one held 9.1 MB after 100 000 frames left out; review 50).
"""

from __future__ import annotations

import math
import re
from collections import deque

import cv2
import numpy as np

from fusedmosaic.compositing.blending import (
    BlendOptions,
    FrameWarper,
    Patch,
    _warp,
    accumulate,
    as_blend_options,
    check_frame_dtype,
    resolve,
)
from fusedmosaic.compositing.canvas import (
    ABSURD_AREA_FACTOR,
    CanvasTooLargeError,
    footprint_extents,
    footprint_problem,
    footprints,
)

Box = tuple[int, int, int, int]  # x0, y0, x1, y1 (x1, y1 exclusive), canvas pixels

# Frames left out by the median screens in a row are one new footprint size (towards re-basing
# the median) when each one's area and extent are within this factor of the previous one's (the
# simulated handheld sweep's consecutive frames: areas within 1.17 of each other), while the
# screens leave out frames 20 x off the median.
CONSISTENT_SIZE_FACTOR = 2.0
SKIPPED_KEPT = 20  # the first and the last entries of `skipped` kept
# Places (groups of placed frames far apart: `places`) tracked at most; beyond, the one of
# fewest frames other than the latest frame's is forgotten (it only chooses the view's box).
MAX_PLACES = 16
# A place is shown by `view_bounds` once it holds this many frames (a lone glitch placed far
# within the budget does not move the view).
MIN_VIEW_PLACE_FRAMES = 3
MAX_SKIP_KINDS = 32  # distinct reasons counted in `skipped_counts`; further ones together
# The view rendered shrunk is summed in float32 blocks of at most this many bytes
# (IncrementalCanvas._render_shrunk).
SHRUNK_BLOCK_BYTES = 64 << 20


class IncrementalCanvas:
    """Tiled canvas in reference pixels (frame 0's grid) times `scale`.

    >>> canvas = IncrementalCanvas(400, 400, mask=fov, blend="linear")
    >>> for image, G in stream:            # G: frame -> reference homography
    ...     box = canvas.add(image, G)     # None if the frame was left out
    ...     view = canvas.render(box)      # only the part that changed

    max_pixels: budget in canvas pixels for the allocated tiles (`tile_pixels`, 16 bytes each
    for colour) and for one `render()` view; not for the bounding box (see the module notes).
    stray_diagonals: a frame that would grow the bounds beyond `max_pixels` is left out as a
    stray if it lands more than this many of its footprint diagonals from every placed frame;
    math.inf never leaves a frame out for its position.
    stray_rebase: after this many consistent strays in a row (each within `stray_diagonals`
    diagonals of the previous one, no frame placed in between) the last of them is placed and
    the new place is kept (`rebased` lists those frames' call numbers); None never does.
    skipped: the first and last SKIPPED_KEPT (call number, reason) of the frames left out (all
    of them up to 2 x SKIPPED_KEPT); skipped_total: how many; skipped_counts: how many by
    reason, its figures replaced by N. median_rebased: the first call numbers of the frames
    that re-based the footprint-size median (module notes), median_rebases: how many.
    """

    def __init__(self, width: int, height: int, *, mask: np.ndarray | None = None,
                 blend: str | BlendOptions = "linear", tile_size: int = 256,
                 scale: float = 1.0, max_pixels: int = 400_000_000,
                 absurd_area_factor: float = ABSURD_AREA_FACTOR,
                 stray_diagonals: float = 10.0, stray_rebase: int | None = 3) -> None:
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
        if not stray_diagonals > 0:
            raise ValueError(f"stray_diagonals must be > 0, got {stray_diagonals}")
        self.stray_diagonals = float(stray_diagonals)
        if stray_rebase is not None and not (isinstance(stray_rebase, int | np.integer)
                                             and not isinstance(stray_rebase, bool)
                                             and stray_rebase >= 1):
            raise ValueError(f"stray_rebase must be an integer >= 1 or None, got "
                             f"{stray_rebase!r}")
        self.stray_rebase = None if stray_rebase is None else int(stray_rebase)
        self.absurd_area_factor = absurd_area_factor
        self._warpers: dict[int | None, FrameWarper] = {None: FrameWarper(width, height, mask,
                                                                          options)}
        self.tiles: dict[tuple[int, int], np.ndarray] = {}
        self.bounds: Box | None = None
        self._last_box: Box | None = None  # the last placed frame's
        self.frames_added = 0
        # the frames left out (module notes): the first and the last few, counts
        self._skipped_first: list[tuple[int, str]] = []  # (call number, reason)
        self._skipped_last: deque[tuple[int, str]] = deque(maxlen=SKIPPED_KEPT)
        self.skipped_total = 0
        self.skipped_counts: dict[str, int] = {}
        self.rebased: list[int] = []  # call numbers of the frames placed as a new far place
        # places: id -> [box, frames] of groups of placed frames, each more than
        # stray_diagonals frame diagonals from the others (`places`, `view_bounds`)
        self._places: dict[int, list] = {}
        self._place_ids = 0
        self._place: int | None = None  # the latest placed frame's place
        self._view_place: int | None = None  # the latest place with MIN_VIEW_PLACE_FRAMES
        self.median_rebased: list[int] = []  # the first of those re-basing the median
        self.median_rebases = 0
        # (area, extent) of the frames left out by the median screens in a row, each consistent
        # with the previous one (CONSISTENT_SIZE_FACTOR), since a frame last passed them
        self._odd_sizes: list[tuple[float, float]] = []
        self._strays = 0  # consistent strays in a row since the last placed frame
        self._stray_box: Box | None = None  # the last of them
        self._areas: deque[float] = deque(maxlen=101)
        self._extents: deque[float] = deque(maxlen=101)  # footprints' bounding box diagonals
        self._calls = 0
        self._channels: int | None = None  # the tiles': the frames' + 1 (the weight)
        self._frame_channels: int | None = None  # the frames' (those of every call that passed)

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

    @property
    def skipped(self) -> list[tuple[int, str]]:
        """(call number, reason) of the first and the last SKIPPED_KEPT frames left out, in
        order: every one while skipped_total <= 2 x SKIPPED_KEPT."""
        return self._skipped_first + list(self._skipped_last)

    def _skip(self, name: int, reason: str) -> None:
        if len(self._skipped_first) < SKIPPED_KEPT:
            self._skipped_first.append((name, reason))
        else:
            self._skipped_last.append((name, reason))
        self.skipped_total += 1
        kind = reason_kind(reason)
        if kind not in self.skipped_counts and len(self.skipped_counts) >= MAX_SKIP_KINDS:
            kind = "other reasons (more kinds than are counted apart)"
        self.skipped_counts[kind] = self.skipped_counts.get(kind, 0) + 1

    def _screen(self, G: np.ndarray) -> tuple[str | None, float, float, bool]:
        """(reason to leave the frame out or None, footprint area, footprint extent, whether
        the reason is the recent median's)."""
        if not np.isfinite(G).all():
            return "not placed", np.nan, np.nan, False
        quad = footprints(G[None], self.width, self.height)[0]
        reason, area = footprint_problem(G, quad, self.width, self.height)
        if reason is not None:  # (a collapse below MIN_AREA_FRACTION included)
            return reason, np.nan, np.nan, False
        extent = float(footprint_extents(quad))
        factor = self.absurd_area_factor
        if self._areas:
            median = float(np.median(self._areas))
            if area > factor * median:
                return (f"footprint area {area / median:.0f} x the recent median", area, extent,
                        True)
            if area * factor < median:  # (a collapse short of the floor; a bad seed above)
                return (f"footprint area 1 / {median / area:.0f} of the recent median", area,
                        extent, True)
        # (as canvas.screen_frames: a thin footprint of normal area)
        if self._extents and extent > factor * float(np.median(self._extents)):
            return (f"footprint extent {extent / np.median(self._extents):.0f} x the recent "
                    "median (its bounding box's diagonal)", area, extent, True)
        return None, area, extent, False

    def _size_run(self, area: float, extent: float) -> list[tuple[float, float]]:
        """The run of frames left out by the median screens with this one appended, or starting
        with it when it does not agree with the previous one (CONSISTENT_SIZE_FACTOR)."""
        if self._odd_sizes:
            a, e = self._odd_sizes[-1]
            f = CONSISTENT_SIZE_FACTOR
            if a / f <= area <= a * f and e / f <= extent <= e * f:
                return [*self._odd_sizes, (area, extent)]
        return [(area, extent)]

    def _check_image(self, image, name: int) -> np.ndarray:
        if image is None:
            raise TypeError(f"frame {name}: image is None; expected an (H, W) gray or (H, W, 3) "
                            "BGR uint8 array")
        image = np.asarray(image)
        check_frame_dtype(image, name)
        if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3, 4)):
            raise ValueError(f"frame {name}: expected an (H, W) gray or (H, W, 3) BGR image, got "
                             f"shape {image.shape}")
        return image

    def _bounds_with(self, box: Box) -> Box:
        b = self.bounds
        return box if b is None else (min(b[0], box[0]), min(b[1], box[1]),
                                      max(b[2], box[2]), max(b[3], box[3]))

    def _reach(self, box: Box) -> float:
        return self.stray_diagonals * math.hypot(box[2] - box[0], box[3] - box[1])

    def _is_stray(self, box: Box) -> bool:
        """True if `box` lands more than `stray_diagonals` of its diagonals from every frame
        placed so far: checked against the last placed frame (the usual neighbour in a sweep),
        then, for a jump, against the allocated tiles (a return near earlier content is not a
        stray; tiles over-cover the footprints by less than a tile, so this errs towards keeping).
        """
        reach = self._reach(box)
        if self._last_box is None or _gap(box, self._last_box) <= reach:
            return False
        T = self.tile_size
        keys = np.array(list(self.tiles), np.int64).reshape(-1, 2) * T  # (y, x) tile corners
        dx = np.maximum(0, np.maximum(keys[:, 1] - box[2], box[0] - keys[:, 1] - T))
        dy = np.maximum(0, np.maximum(keys[:, 0] - box[3], box[1] - keys[:, 0] - T))
        return not bool((np.hypot(dx, dy) <= reach).any())

    def add(self, image: np.ndarray, homography: np.ndarray, mask: np.ndarray | None = None,
            *, gain: float = 1.0) -> Box | None:
        """Blends one frame placed by `homography` (frame -> reference). mask: this frame's field
        of view if it differs from the canvas's. Returns the canvas box that changed, or None if
        the frame was left out (unplaced, footprint behind the camera, non-convex, collapsed
        below MIN_AREA_FRACTION of the frame's area, area 20 x above or below the recent median
        or extent 20 x above it, or a stray: growing the canvas bounds beyond `max_pixels`
        while landing more than `stray_diagonals` frame diagonals from every placed frame; see
        `skipped`). A frame near the content is kept however large the bounding box gets. The
        `stray_rebase`-th consistent stray in a row is placed instead, accepting the new place,
        and a run of frames of a consistent odd size re-bases the median once it outnumbers
        the median's frames (see the module notes).

        Raises TypeError (None image), ValueError (pixel type other than uint8, wrong size or
        channel count, homography not 3x3) or CanvasTooLargeError (the allocated tiles would
        exceed `max_pixels`); a call that raises changes nothing, and the next call has the same
        frame number."""
        name = self._calls
        image = self._check_image(image, name)
        G = np.asarray(homography, np.float64)
        if G.shape != (3, 3):
            raise ValueError(f"frame {name}: homography must be 3x3, got {G.shape}")
        warper = self._warper(mask)
        # size and channels, before any state change; the channel count checked is the
        # canvas's, not the warper's (each mask has its own warper: a colour frame with its own
        # mask on a grey canvas passed, and broke the tiles or render())
        warper.channels = self._frame_channels
        image = warper._check_image(image, name)  # (H, W, channels)
        channels = image.shape[2]
        reason, area, extent, by_median = self._screen(G)
        sizes = None  # the run of frames of one odd size (left out by the median screens)
        median_run = None  # that run when it re-bases the median (this frame passes)
        if by_median:
            sizes = self._size_run(area, extent)
            if len(sizes) > len(self._areas):  # it outnumbers the median's frames
                reason, sizes, median_run = None, None, sizes
        elif reason is None:
            sizes = []  # a frame passing the screens ends a run
        if self.scale != 1.0:
            G = np.diag([self.scale, self.scale, 1.0]) @ G
        box = warper.box(G) if reason is None else None
        if reason is None and box is None:
            reason = "footprint behind the camera"
        strays = None  # the run of consistent strays if this frame is left out as one
        rebase = False  # the frame is placed as the end of such a run
        if reason is None:
            # A stray (a jump far from every placed frame that would take the bounding box
            # beyond the budget) is left out; a frame near the content is kept however large
            # the bounding box gets, since only the tiles hold memory (render() of a box over
            # the budget raises instead). Then the tiles under the footprint: the area covered
            # over budget -> error.
            bounds = self._bounds_with(box)
            x0, y0, x1, y1 = bounds
            if (bounds != self.bounds and (x1 - x0) * (y1 - y0) > self.max_pixels
                    and self._is_stray(box)):
                # A run of strays each near the previous one is a new place (re-localisation),
                # not a glitch: its stray_rebase-th frame is placed, and the frames after it
                # land near placed content.
                strays = (self._strays + 1 if self._stray_box is not None
                          and _gap(box, self._stray_box) <= self._reach(box) else 1)
                if self.stray_rebase is not None and strays >= self.stray_rebase:
                    strays, rebase = None, True
                else:
                    reason = (f"would grow the canvas bounds to {x1 - x0} x {y1 - y0} pixels, "
                              f"above max_pixels {self.max_pixels} (frame lands at x "
                              f"{box[0]}..{box[2]}, y {box[1]}..{box[3]}: a stray placement?)")
        if reason is None:
            T = self.tile_size
            ty0, tx0, ty1, tx1 = box[1] // T, box[0] // T, (box[3] - 1) // T, (box[2] - 1) // T
            # counted before any list of them: a near-singular first frame's footprint spans
            # 6.4e6 x 4.8e6 px, whose list of tiles took > 2 GB (review 50); the tiles under
            # the footprint alone above the budget cannot fit, whatever is allocated already
            under = (ty1 - ty0 + 1) * (tx1 - tx0 + 1)
            if under * T * T > self.max_pixels:
                raise self._too_large(f"at least {under * T * T}", name, box)
            tiles = [(ty, tx) for ty in range(ty0, ty1 + 1) for tx in range(tx0, tx1 + 1)]
            new = sum(key not in self.tiles for key in tiles)
            if (len(self.tiles) + new) * T * T > self.max_pixels:
                raise self._too_large(f"{(len(self.tiles) + new) * T * T}", name, box)
        if median_run is not None:  # (the call no longer raises: the state changes)
            self._areas.clear()
            self._extents.clear()
            for a, e in median_run:
                self._areas.append(a)
                self._extents.append(e)
            self.median_rebases += 1
            if len(self.median_rebased) < SKIPPED_KEPT:
                self.median_rebased.append(name)
            sizes = []
        if sizes is not None:
            self._odd_sizes = sizes
        if reason is not None:
            self._calls += 1
            self._frame_channels = channels
            self._skip(name, reason)
            if strays is not None:
                self._strays, self._stray_box = strays, box
            return None
        if self.scale < 1.0:
            patch = _warp_shrunk(warper, image, G, box, self.scale, gain, name)
        else:
            patch = warper.warp(image, G, gain=gain, name=name)
        self._calls += 1
        self._frame_channels = channels
        if median_run is None:  # (else the median holds it already)
            self._areas.append(area)
            self._extents.append(extent)
        if self._channels is None:
            self._channels = patch.data.shape[2]
        for key in tiles:
            tile = self.tiles.get(key)
            if tile is None:
                tile = self.tiles[key] = np.zeros((T, T, self._channels), np.float32)
            accumulate(tile, key[1] * T, key[0] * T, patch, self.options.blend)
        self.bounds = self._bounds_with(box)
        self._last_box = box
        self._join_place(box)
        self._strays, self._stray_box = 0, None
        if rebase:
            self.rebased.append(name)
        self.frames_added += 1
        return box

    def _join_place(self, box: Box) -> None:
        """Adds a placed frame's box to its place: the places within `stray_diagonals` of its
        diagonals merge with it into one, or it starts a new one."""
        reach = self._reach(box)
        near = [k for k, (b, _) in self._places.items() if _gap(box, b) <= reach]
        frames = 1
        for k in near:
            b, n = self._places.pop(k)
            box = (min(box[0], b[0]), min(box[1], b[1]), max(box[2], b[2]), max(box[3], b[3]))
            frames += n
        self._place_ids += 1
        self._place = self._place_ids
        self._places[self._place] = [box, frames]
        if self._view_place in near or frames >= MIN_VIEW_PLACE_FRAMES or self._view_place is None:
            self._view_place = self._place
        if len(self._places) > MAX_PLACES:
            keep = (self._place, self._view_place)
            drop = min((k for k in self._places if k not in keep),
                       key=lambda k: self._places[k][1])
            del self._places[drop]

    @property
    def places(self) -> int:
        """Groups of placed frames, each more than `stray_diagonals` frame diagonals from the
        others (a re-localisation far away, or a far jump within the budget, starts one; a
        frame near two joins them): 1 for a normal session (at most MAX_PLACES tracked)."""
        return len(self._places)

    @property
    def view_bounds(self) -> Box | None:
        """The bounding box of the place where the latest frames are (the latest place with at
        least MIN_VIEW_PLACE_FRAMES frames, so a lone far frame does not move it): `bounds`
        while there is one place. What a live view shows after a re-localisation far away,
        where the whole bounding box, shrunk to a view, made the latest frames a line 2 pixels
        high (review 50)."""
        if self._view_place is None:
            return self.bounds
        return tuple(self._places[self._view_place][0])

    def _too_large(self, pixels: str, name: int, box: Box) -> CanvasTooLargeError:
        return CanvasTooLargeError(
            f"live canvas would need {pixels} pixels of tiles, above the budget of "
            f"{self.max_pixels} pixels (frame {name} lands at x {box[0]}..{box[2]}, y "
            f"{box[1]}..{box[3]}); raise max_pixels, lower scale, or start a new canvas")

    # -- views --------------------------------------------------------------------------------
    @property
    def nbytes(self) -> int:
        return sum(t.nbytes for t in self.tiles.values())

    @property
    def tile_pixels(self) -> int:
        """Canvas pixels held in tiles: the memory `max_pixels` bounds."""
        return len(self.tiles) * self.tile_size * self.tile_size

    def render(self, box: Box | None = None, *, step: int = 1) -> np.ndarray:
        """uint8 (h, w, C) view of `box` (default: everything so far, `bounds`); empty pixels are
        black. Cost proportional to the box; a view of more than `max_pixels` pixels raises
        CanvasTooLargeError (render a part of it instead, or shrunk). The default box can be
        above the budget with the tiles far below it (a long or diagonal sweep: see the module
        notes).

        step: the view shrunk by this whole factor, (ceil(h / step), ceil(w / step)): pixel
        (i, j) is the mean of the box's pixels (x0 + j step .. + step - 1, y0 + i step ..), the
        box padded with black (empty) to a multiple of step, as cv2.resize's INTER_AREA gives
        it; its cost is proportional to the tiles in the box and the view, not to the box."""
        if self._channels is None:
            raise ValueError("no frame added yet")
        if not (isinstance(step, int | np.integer) and not isinstance(step, bool) and step >= 1):
            raise ValueError(f"render: step must be an integer >= 1, got {step!r}")
        step = int(step)
        given, box = box, self.bounds if box is None else box
        try:
            x0, y0, x1, y1 = (int(v) for v in box)
        except (TypeError, ValueError):
            raise ValueError(f"render: box must be (x0, y0, x1, y1) integers, got {box!r}"
                             ) from None
        if not (x1 > x0 and y1 > y0):
            raise ValueError(f"render: empty box {box!r} (need x1 > x0 and y1 > y0)")
        vw, vh = -(-(x1 - x0) // step), -(-(y1 - y0) // step)
        if vw * vh > self.max_pixels:
            whole = (" (the whole canvas: its bounding box; the tiles hold "
                     f"{self.tile_pixels} pixels)") if given is None else ""
            shrunk = f" shrunk {step} times" if step > 1 else ""
            raise CanvasTooLargeError(
                f"render: the view of x {x0}..{x1}, y {y0}..{y1}{shrunk} is {vw} x {vh} "
                f"pixels, above the budget of {self.max_pixels} pixels (max_pixels){whole}; "
                "render a smaller box, e.g. the one add() returned, or a larger step")
        if step > 1:
            return self._render_shrunk((x0, y0, x1, y1), step)
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

    def _render_shrunk(self, box: Box, step: int) -> np.ndarray:
        """render(box, step=step) for step > 1: each tile's pixels are summed by blocks of the
        view's pixels into a float32 block of view rows and columns, so memory is the view plus
        one block (<= SHRUNK_BLOCK_BYTES, 64 MB), and only allocated tiles are visited. A block
        spans whole view rows unless one row alone is above that: a view of 2 x 24 691 361 px
        (a canvas spanning a re-localisation 2e9 px away) took a 592 MB strip (review 50)."""
        x0, y0, x1, y1 = box
        C, T = self._channels - 1, self.tile_size
        vw, vh = -(-(x1 - x0) // step), -(-(y1 - y0) // step)
        out = np.zeros((vh, vw, C), np.uint8)
        columns: dict[int, list[int]] = {}  # tile row -> its allocated tiles' columns in box
        for ty, tx in self.tiles:
            if tx * T < x1 and tx * T + T > x0 and ty * T < y1 and ty * T + T > y0:
                columns.setdefault(ty, []).append(tx)
        row_bytes = vw * C * 4
        rows = max(1, min(-(-T // step), SHRUNK_BLOCK_BYTES // row_bytes))  # view rows a block
        cols = vw if row_bytes <= SHRUNK_BLOCK_BYTES else max(1, SHRUNK_BLOCK_BYTES // (C * 4))
        for r0 in range(0, vh, rows):
            r1 = min(r0 + rows, vh)
            cy0, cy1 = y0 + r0 * step, min(y0 + r1 * step, y1)  # the block's canvas rows
            for c0 in range(0, vw, cols):
                c1 = min(c0 + cols, vw)
                cx0, cx1 = x0 + c0 * step, min(x0 + c1 * step, x1)  # its canvas columns
                acc = None
                for ty in range(cy0 // T, (cy1 - 1) // T + 1):
                    for tx in columns.get(ty, ()):
                        if not (tx * T < cx1 and tx * T + T > cx0):
                            continue
                        ax0, ay0 = max(cx0, tx * T), max(cy0, ty * T)
                        ax1, ay1 = min(cx1, tx * T + T), min(cy1, ty * T + T)
                        sub = resolve(self.tiles[(ty, tx)][ay0 - ty * T:ay1 - ty * T,
                                                           ax0 - tx * T:ax1 - tx * T])[0]
                        sums, i0 = _block_sums(sub, ay0 - y0, step, axis=0)
                        sums, j0 = _block_sums(sums, ax0 - x0, step, axis=1)
                        if acc is None:
                            acc = np.zeros((r1 - r0, c1 - c0, C), np.float32)
                        acc[i0 - r0:i0 - r0 + sums.shape[0],
                            j0 - c0:j0 - c0 + sums.shape[1]] += sums
                if acc is not None:
                    acc *= np.float32(1.0 / (step * step))
                    acc += np.float32(0.5)  # round half up (values are >= 0)
                    np.clip(acc, 0, 255, out=acc)
                    out[r0:r1, c0:c1] = acc.astype(np.uint8)
        return out[:, :, 0] if C == 1 else out


def reason_kind(reason: str) -> str:
    """A reason without its figures (each number replaced by N), for counting by kind."""
    return re.sub(r"-?\d+(\.\d+)?(e[+-]?\d+)?", "N", reason)[:200]


def _block_sums(a: np.ndarray, start: int, step: int, axis: int) -> tuple[np.ndarray, int]:
    """(float32 sums of `a` over blocks of `step` along `axis`, the first block's index), a's
    index 0 lying at `start` in a grid of blocks starting at 0."""
    cuts = np.arange(step - start % step, a.shape[axis], step)
    return (np.add.reduceat(a, np.concatenate([[0], cuts]), axis=axis, dtype=np.float32),
            start // step)


def _warp_shrunk(warper: FrameWarper, image: np.ndarray, G: np.ndarray, box: Box, scale: float,
                 gain: float, name) -> Patch:
    """The patch `warper.warp` gives, for a canvas below the frames' resolution (scale < 1):
    the frame's premultiplied colour and its weight are first shrunk by `scale` with area
    averaging (cv2.INTER_AREA), then warped by G (frame -> canvas) composed with the shrunk
    grid's map to the frame's (same pixel extent -0.5 .. W - 0.5), so each canvas pixel is the
    mean of the frame pixels under it, as an image resize gives it. Warping the full-size frame
    with INTER_LINEAR point-samples it instead: a 0.19 creation video of a 6716 x 6253 pCLE
    mosaic was 14.8 grey levels from the area-downscaled mosaic.png (moire in the cell
    texture). Colour and weight are shrunk together, so the frame's edge, its field-of-view
    mask, its border and its specular weights keep their place and the blend its weights."""
    image = warper._check_image(image, name)
    image, weight, colour_weight = warper._weights(image, name=name)
    h, w = weight.shape
    channels = image.shape[2]
    src = np.empty((h, w, channels + 1), np.float32)
    np.multiply(image, colour_weight * np.float32(gain), out=src[:, :, :-1])
    src[:, :, -1] = weight
    sw, sh = max(1, round(w * scale)), max(1, round(h * scale))
    small = cv2.resize(src, (sw, sh), interpolation=cv2.INTER_AREA).reshape(sh, sw, -1)
    fx, fy = sw / w, sh / h  # the shrink actually done (whole pixels)
    # shrunk pixel centre u -> frame (u + 0.5) / fx - 0.5 (cv2.resize's convention)
    A = np.array([[1.0 / fx, 0.0, 0.5 / fx - 0.5], [0.0, 1.0 / fy, 0.5 / fy - 0.5],
                  [0.0, 0.0, 1.0]])
    M = np.asarray(G, np.float64) @ A
    x0, y0, x1, y1 = box
    if channels != 3:  # warped apart, as FrameWarper.warp does (OpenCV's 2-channel path)
        data = np.empty((y1 - y0, x1 - x0, channels + 1), np.float32)
        data[:, :, :-1] = _warp(np.ascontiguousarray(small[:, :, :-1]), M, x0, y0, x1 - x0,
                                y1 - y0)
        data[:, :, -1:] = _warp(np.ascontiguousarray(small[:, :, -1]), M, x0, y0, x1 - x0,
                                y1 - y0)
        return Patch(x0, y0, data)
    return Patch(x0, y0, _warp(small, M, x0, y0, x1 - x0, y1 - y0))


def _gap(a: Box, b: Box) -> float:
    """Distance between two boxes (0 if they touch or overlap)."""
    dx = max(0, b[0] - a[2], a[0] - b[2])
    dy = max(0, b[1] - a[3], a[1] - b[3])
    return math.hypot(dx, dy)
