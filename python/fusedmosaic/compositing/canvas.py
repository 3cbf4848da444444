"""The mosaic canvas: bounds from the placed frames, absurd footprints left out, a pixel budget,
and rendering in one piece or tile by tile (streamed to a PNG, so memory stays bounded).

Canvas pixel (i, j) is reference pixel (x0 + i, y0 + j), the reference being frame 0's pixel grid
(design.md: output homographies map frame -> reference); report.json records (x0, y0).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from fusedmosaic.compositing.blending import (
    COVERED,
    BlendOptions,
    FrameWarper,
    MultibandRegion,
    Patch,
    SpecularMasks,
    _overlap,
    accumulate,
    as_blend_options,
    compensate_gains,
    filled_colour,
    fit_bands,
    footprint_box,
    resolve,
    thumbnail,
)

MAX_CANVAS_PIXELS = 64_000_000  # one-piece canvases above this are refused (compose_mosaic)
# issue 6: a footprint > 20x the median area is left out, as one > 20x the median extent (its
# bounding box's diagonal: a thin footprint of normal area)
ABSURD_AREA_FACTOR = 20.0
# Frames landing more than this many median footprint diagonals from the main group of frames
# are strays (a placement glitch), as IncrementalCanvas's stray_diagonals; they are left out when
# they are at most STRAY_MAX_FRACTION of the frames, within the pixel budget or not (review 47).
STRAY_DIAGONALS = 10.0
STRAY_MAX_FRACTION = 0.1


# A footprint corner farther than this from the reference (px) is left out ("beyond the canvas
# range"): a near-degenerate homography (diag(2e17, 5e-18, 1): det 1, a normal area) reached
# 2e19 px, beyond int64, and its canvas came out of negative size. 1e15 px keeps every sum of
# the bounds exact in float64 and int64; such a frame is far beyond any pixel budget anyway.
MAX_COORDINATE = 1e15
# A footprint of less than this fraction of the frame's own pixel area is a collapsed placement:
# a camera 32 times as far from the surface as frame 0's (the area goes with the distance
# squared; a simulated handheld fetoscopy sweep, 150 frames, spans 0.62 to 2.03 of it). A
# near-singular placement, diag(1e-3, 1e-3, 1), gives 1e-6 of it (0.003 pixels for a 64 x 48
# frame). Left out by footprint_problem, so mosaic.png, the live view and the video agree.
MIN_AREA_FRACTION = 1e-3
MAX_TILE_SIZE = 8192  # px: a tile's accumulator is then 8192^2 x (C + 1) x 4 B (1 GiB colour)


class CanvasTooLargeError(ValueError):
    pass


class NoFrameToComposeError(ValueError):
    """No placed frame is left to show (all unplaced, or left out: see the reasons)."""


@dataclass
class CanvasOptions:
    """Canvas size limits and tiling (CLI: ``--max-canvas-pixels``, ``--tile-size``)."""

    max_pixels: int = 400_000_000  # budget: larger canvases are refused before allocating
    in_memory_pixels: int = 8_000_000  # up to this, one piece; above, tile by tile to the PNG
    tile_size: int = 1024  # px; a tile's accumulator is tile_size^2 x (C + 1) float32
    cache_mb: float = 32.0  # warped frames kept for neighbouring tiles (256 MB: no faster, bench)
    absurd_area_factor: float = ABSURD_AREA_FACTOR
    # mosaic.png with an alpha channel (grey + alpha or BGRA): 255 where a frame shows the
    # pixel, 0 where none does (black either way); CLI --alpha
    alpha: bool = False

    def validate(self, names: dict[str, str] | None = None) -> None:
        """ValueError for a bad field; `names` maps fields to what the messages call them
        (e.g. the CLI's flags)."""
        name = (names or {}).get
        for key in ("max_pixels", "in_memory_pixels"):
            if getattr(self, key) <= 0:
                raise ValueError(f"{name(key, key)} must be > 0, got {getattr(self, key)}")
        if not 64 <= self.tile_size <= MAX_TILE_SIZE:
            raise ValueError(f"{name('tile_size', 'tile_size')} must be in 64..{MAX_TILE_SIZE} "
                             f"(pixels; a tile's accumulator is tile size squared x 16 bytes "
                             f"for colour), got {self.tile_size}")


def _corners(width: int, height: int) -> np.ndarray:
    return np.array([[0, 0], [width, 0], [width, height], [0, height]], np.float64)


def footprints(homographies: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N, 4, 2) corners of each frame in the reference, NaN for unplaced frames."""
    c = np.hstack([_corners(width, height), np.ones((4, 1))])
    hom = np.einsum("nij,pj->npi", homographies, c)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = hom[..., :2] / hom[..., 2:]
        out[(hom[..., 2] <= 0)] = np.nan  # a corner behind the camera: no valid footprint
    return out


def _orientation(width: int, height: int) -> float:
    """The sign of OpenCV's oriented area of an unmirrored footprint (the reference frame's)."""
    return float(np.sign(cv2.contourArea(_corners(width, height).astype(np.float32),
                                         oriented=True)))


def footprint_problem(G: np.ndarray, quad: np.ndarray, width: int, height: int
                      ) -> tuple[str | None, float]:
    """(why the frame placed by G, whose footprint() corners are `quad`, cannot be composed,
    or None; its footprint area). Shared by plan_canvas and IncrementalCanvas: a footprint behind
    the camera, beyond MAX_COORDINATE, non-convex, mirrored or below MIN_AREA_FRACTION of the
    frame's own area (collapsed)."""
    if not np.isfinite(quad).all():
        return "footprint behind the camera", np.nan
    if np.abs(quad).max() > MAX_COORDINATE:
        return (f"footprint beyond the canvas range (a corner {np.abs(quad).max():.3g} px from "
                f"the reference, more than {MAX_COORDINATE:g})"), np.nan
    if footprint_box(G, width, height) is None:
        # a corner of the pixel extent (-0.5 .. W - 0.5, which the warp covers) behind it
        return "footprint behind the camera", np.nan
    # about its centre before OpenCV's float32: a frame 1e10 px from the reference (a pixel
    # size wrong by 1e9) otherwise collapsed to a "non-convex" quad
    centred = (quad - quad.mean(axis=0)).astype(np.float32)
    if not cv2.isContourConvex(centred):
        return "non-convex footprint", np.nan
    signed = cv2.contourArea(centred, oriented=True)
    if np.sign(signed) != _orientation(width, height):
        # frame -> reference between two views on the same side of the surface keeps the
        # orientation; a flip is a placement failure (a plane or pose sign), not a view
        return "mirrored footprint (the homography flips the frame)", abs(signed)
    own = width * height
    if not abs(signed) >= MIN_AREA_FRACTION * own:
        return (f"footprint area {abs(signed):.3g} pixels, below {MIN_AREA_FRACTION:g} x the "
                f"frame's own {own} (a collapsed placement: a near-singular homography)",
                abs(signed))
    return None, abs(signed)


def screen_frames(homographies: np.ndarray, width: int, height: int,
                  absurd_area_factor: float = ABSURD_AREA_FACTOR
                  ) -> tuple[np.ndarray, dict[int, str]]:
    """Which frames go on the canvas: placed, with a convex, unmirrored footprint in front of
    the camera, within MAX_COORDINATE px of the reference, of area and of extent (its bounding
    box's diagonal) <= factor x the median. Returns (use (N,) bool, reasons for placed frames
    left out)."""
    G = np.asarray(homographies, np.float64)
    placed = np.isfinite(G).all(axis=(1, 2))
    fp = footprints(np.where(placed[:, None, None], G, np.eye(3)), width, height)
    use = placed.copy()
    reasons: dict[int, str] = {}
    areas = np.full(len(G), np.nan)
    for k in np.flatnonzero(placed):
        why, areas[k] = footprint_problem(G[k], fp[k], width, height)
        if why is not None:
            use[k] = False
            reasons[int(k)] = why
    if use.any():
        # By extent too: a sheared footprint of normal area (diag(1e4, 1e-4) in the placement)
        # centred among the others passed both this and the stray rule, and made a 990001 x 100
        # canvas 99 % black; at 1e5 the canvas was refused, mosaic and video lost (review 46).
        extents = footprint_extents(fp)
        med, med_extent = np.median(areas[use]), np.median(extents[use])
        for k in np.flatnonzero(use):
            if areas[k] > absurd_area_factor * med:
                reasons[int(k)] = (f"footprint area {areas[k] / med:.0f} x the median "
                                   f"(limit {absurd_area_factor:g})")
            elif extents[k] > absurd_area_factor * med_extent:
                reasons[int(k)] = (f"footprint extent {extents[k] / med_extent:.0f} x the median "
                                   f"(its bounding box's diagonal; limit {absurd_area_factor:g})")
            else:
                continue
            use[k] = False
    return use, reasons


def footprint_extents(quads: np.ndarray) -> np.ndarray:
    """(N,) diagonal of each (4, 2) footprint's bounding box (px)."""
    quads = np.asarray(quads, np.float64)
    return np.hypot(*np.moveaxis(quads.max(axis=-2) - quads.min(axis=-2), -1, 0))


def usable_frames(homographies: np.ndarray, width: int, height: int) -> np.ndarray:
    """Placed frames whose footprint is a sane convex quad of non-absurd area."""
    return screen_frames(homographies, width, height)[0]


def canvas_bounds(homographies: np.ndarray, width: int, height: int,
                  use: np.ndarray | None = None) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) integer bounds in reference pixels of the used frames (x1, y1
    exclusive): the bounding box of the reference pixels whose square the frames' pixel extent
    (-0.5 .. W - 0.5 in frame pixels: what the warp covers, as footprint_box) overlaps.

    Before (review 50), the bounds were those of the pixel centres (0 .. W - 1), which equals
    this for a translation but not for a frame magnified against the reference: a frame
    zoomed 2x at frame 0 gave (0, 0, 319, 239) where its warp covers (-1, -1, 320, 240), so
    mosaic.png lost a covered rim that IncrementalCanvas (the live view, the video) shows.
    This box lies within footprint_box's, which rounds the same extent outward."""
    use = usable_frames(homographies, width, height) if use is None else use
    if not use.any():
        raise NoFrameToComposeError("no placed frame to compose a mosaic from")
    # frame pixel (u, v) -> (u - 0.5, v - 0.5): footprints' corners 0 .. W become the extent
    half = np.array([[1.0, 0, -0.5], [0, 1.0, -0.5], [0, 0, 1.0]])
    pts = footprints(homographies[use] @ half, width, height).reshape(-1, 2)
    # reference pixel p's square [p - 0.5, p + 0.5] overlaps [lo, hi] for p in
    # floor(lo + 0.5) .. ceil(hi - 0.5)
    lo, hi = np.floor(pts.min(axis=0) + 0.5), np.ceil(pts.max(axis=0) - 0.5) + 1
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()
            and np.abs(np.concatenate([lo, hi])).max() <= 2 * MAX_COORDINATE):
        raise ValueError(f"canvas bounds x {lo[0]:.3g}..{hi[0]:.3g}, y {lo[1]:.3g}..{hi[1]:.3g} "
                         "cannot be represented (a footprint not screened: screen_frames)")
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


@dataclass
class CanvasPlan:
    """Where the mosaic lies in reference pixels and which frames it shows."""

    x0: int
    y0: int
    x1: int
    y1: int
    use: np.ndarray
    skipped: dict[int, str] = field(default_factory=dict)

    @property
    def width(self) -> int:
        return self.x1 - self.x0

    @property
    def height(self) -> int:
        return self.y1 - self.y0

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def reference_to_mosaic(self) -> np.ndarray:
        """3x3 translation: reference pixels -> mosaic pixels."""
        return np.array([[1.0, 0, -self.x0], [0, 1.0, -self.y0], [0, 0, 1.0]])


def plan_canvas(homographies: np.ndarray, width: int, height: int, *,
                max_pixels: int = MAX_CANVAS_PIXELS,
                absurd_area_factor: float = ABSURD_AREA_FACTOR) -> CanvasPlan:
    """Bounds and frames of the mosaic: the frames screen_frames keeps, less the strays (at
    most STRAY_MAX_FRACTION of them, landing more than STRAY_DIAGONALS median footprint
    diagonals from the main group), which are left out with their reason in `skipped` whatever
    the budget. Raises CanvasTooLargeError above the pixel budget (nothing is allocated) and
    ValueError if no frame can be shown."""
    G = np.asarray(homographies, np.float64)
    if G.ndim != 3 or G.shape[1:] != (3, 3):
        raise ValueError(f"homographies must be (N, 3, 3), got {G.shape}")
    use, reasons = screen_frames(G, width, height, absurd_area_factor)
    x0, y0, x1, y1 = canvas_bounds(G, width, height, use)
    plan = CanvasPlan(x0, y0, x1, y1, use, reasons)
    over = plan.pixels > max_pixels
    if not over and STRAY_MAX_FRACTION * use.sum() < 1:
        return plan  # too few frames for one to be a stray (and nothing to report)
    # A few frames far from all the others (a robot or tracker glitch) are left out as strays.
    # Over the budget only at first (one frame 3e5 px off lost the whole mosaic and video), when
    # the rest then fits; within it too since review 47: one emt frame 2.7 m off (a tracker
    # jump) gave a 42111 x 2085 mosaic, 98.8 % black, and no warning, where README promises the
    # frame left out and named. Normal scans are one group, far from the limit: on the
    # simulator's syn / handheld / pCLE circle and spiral scans, with black frames or 16
    # dead-reckoned ones left out (18 runs of emt, ba-emt, lba-emt, robot, kalman-robot, ncc),
    # no frame was a stray; the longest link joining the shown frames was 0.20 footprint
    # diagonals, against the 11 that would split them.
    groups = _proximity_groups(G, width, height, use)
    main = max(groups, key=len)
    strays = np.setdiff1d(np.flatnonzero(use), main)
    if 0 < strays.size <= STRAY_MAX_FRACTION * use.sum():
        kept = use.copy()
        kept[strays] = False
        bounds = canvas_bounds(G, width, height, kept)
        size = (bounds[2] - bounds[0], bounds[3] - bounds[1])
        if size[0] * size[1] <= max_pixels:
            from scipy.spatial import cKDTree

            # (a tree: up to a tenth of the frames are strays, each against all the others)
            distances, _ = cKDTree(footprints(G[main], width, height).mean(axis=1)).query(
                footprints(G[strays], width, height).mean(axis=1))
            budget = f" (above the budget of {max_pixels})" if over else ""
            for k, distance in zip(strays, distances, strict=True):
                reasons[int(k)] = (
                    f"stray: lands {distance:.3g} px from the other frames (more than "
                    f"{STRAY_DIAGONALS:g} footprint diagonals from any): a placement glitch? "
                    f"The canvas would be {plan.width} x {plan.height} pixels with the strays"
                    f"{budget}, {size[0]} x {size[1]} without")
            return CanvasPlan(*bounds, kept, reasons)
    if not over:
        return plan
    far = ""
    if len(groups) > 1:
        listed = ", ".join(f"{len(g)} frame{'s' if len(g) > 1 else ''} from {g[0]}"
                           for g in sorted(groups, key=len, reverse=True)[:4])
        far = (f"; the frames lie in {len(groups)} groups far apart ({listed}"
               f"{', ...' if len(groups) > 4 else ''}: frame positions)")
    raise CanvasTooLargeError(
        f"mosaic canvas of {plan.width} x {plan.height} pixels "
        f"({plan.pixels / 1e6:.1f} Mpixel, reference x {x0}..{x1}, y {y0}..{y1}) exceeds the "
        f"budget of {max_pixels} pixels ({max_pixels / 1e6:.1f} Mpixel){far}; the frames are "
        "spread over too large an area: check the homographies, or raise the budget "
        "(CanvasOptions.max_pixels, fusedmosaic run --max-canvas-pixels)")


def _proximity_groups(G: np.ndarray, width: int, height: int,
                      use: np.ndarray) -> list[np.ndarray]:
    """The used frames in groups linked by footprint centres within STRAY_DIAGONALS + 1 median
    footprint diagonals of each other (frame positions, each group in increasing order)."""
    from scipy.sparse.csgraph import connected_components

    idx = np.flatnonzero(use)
    fp = footprints(G[idx], width, height)
    centres = fp.mean(axis=1)
    diagonal = float(np.median(np.maximum(np.linalg.norm(fp[:, 2] - fp[:, 0], axis=1),
                                          np.linalg.norm(fp[:, 3] - fp[:, 1], axis=1))))
    graph = _linkage_graph(centres, (STRAY_DIAGONALS + 1) * diagonal)
    _, labels = connected_components(graph, directed=False)
    return [idx[labels == label] for label in np.unique(labels)]


def _linkage_graph(points: np.ndarray, radius: float):
    """A sparse graph on (N, 2) `points` with the connected components of "within `radius` of
    each other" (single linkage), from O(N) candidate edges.

    Every pair within the radius (cKDTree.query_pairs) is O(N^2) for a compact sweep, since the
    radius spans 11 footprints: 10 000 frames took 16.6 s and 2.8 GB (review 46), 30 000 would
    exhaust 24 GB. The Delaunay triangulation's edges hold the minimum spanning tree (a pair
    whose closed diametral disk holds a third point is linked through it by two shorter edges),
    so its edges within the radius link the same groups: 20 000 frames 0.14 s. Qhull refuses
    fewer than 3 distinct points and points on a line (to its precision): those are linked by a
    sweep along the line, consecutive points being the line's spanning tree."""
    from scipy.sparse import coo_matrix
    from scipy.spatial import Delaunay, QhullError

    points = np.asarray(points, np.float64)
    # duplicates (frames placed at one spot) are one point to Qhull: grouped by `inverse`
    unique, first, inverse = np.unique(points, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    edges = np.zeros((0, 2), np.int64)
    if len(unique) >= 3:
        try:
            tri = Delaunay(unique)
            s = tri.simplices
            # points Qhull left out as coincident with a vertex (closer than its precision):
            # linked to that vertex
            edges = np.vstack([s[:, [0, 1]], s[:, [1, 2]], s[:, [2, 0]],
                               tri.coplanar[:, [0, 2]]]).astype(np.int64)
        except QhullError:  # flat: on one line
            pass
    if len(unique) >= 2 and not edges.size:
        centred = unique - unique.mean(axis=0)
        direction = np.linalg.svd(centred, full_matrices=False)[2][0]
        order = np.argsort(centred @ direction, kind="stable")
        edges = np.column_stack([order[:-1], order[1:]])
    if edges.size:
        edges = edges[np.linalg.norm(unique[edges[:, 0]] - unique[edges[:, 1]], axis=1)
                      <= radius]
    # edges between the first of each set of duplicates, and each point to its first
    n = len(points)
    rows = np.concatenate([first[edges[:, 0]], np.arange(n)])
    cols = np.concatenate([first[edges[:, 1]], first[inverse]])
    return coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))


# ------------------------------------------------------------------------------------------
# Frames -> patches (warped once, kept for neighbouring tiles within a memory budget)
# ------------------------------------------------------------------------------------------


class _PatchSource:
    """Warped patches of the used frames. `frames` is a sequence (frames[k]) or an iterable of
    (k, image) pairs in increasing k, which can then only be read once, in order.

    clip: a patch too large for the cache (cache_bytes) is warped only over the region asked
    for (a tile and its margin), not over the frame's whole box for every tile it touches: a
    thin diagonal footprint's 6000 x 6000 box took 497 MB and 36 whole warps. Patches that
    fit are warped whole and kept, as before."""

    def __init__(self, frames, G: np.ndarray, warper: FrameWarper, gains: np.ndarray | None,
                 cache_bytes: int, clip: bool = False) -> None:
        self._seq = frames if hasattr(frames, "__getitem__") else None
        self._iter = None if self._seq is not None else iter(frames)
        self.G, self.warper, self.gains = G, warper, gains
        self._cache: OrderedDict[int, Patch] = OrderedDict()
        self._filled: dict[int, np.ndarray] = {}  # a cached patch's colour, filled (`filled`)
        self._cache_bytes, self._bytes = cache_bytes, 0
        self._clip = clip

    def image(self, k: int) -> np.ndarray:
        if self._seq is not None:
            return self._seq[k]
        for j, image in self._iter:
            if j == k:
                return image
            if j > k:
                break
        raise ValueError(f"frame {k} missing from the frames given (pairs must come in order)")

    def _cut(self, k: int, region) -> tuple[int, int, int, int] | None:
        """The part of frame k's box to warp for `region`: None (the whole box) unless clipping
        and its whole patch would not fit the cache."""
        if not self._clip or region is None:
            return None
        box = self.warper.box(self.G[k])
        if box is None:
            return None
        channels = (self.warper.channels or 3) + 1
        whole = (box[2] - box[0]) * (box[3] - box[1]) * channels * 4
        return None if whole <= self._cache_bytes else tuple(region)

    def patch(self, k: int, region: tuple[int, int, int, int] | None = None) -> Patch:
        """Frame k's patch; region (x0, y0, x1, y1): the part needed (see `clip`)."""
        if k in self._cache:
            self._cache.move_to_end(k)
            return self._cache[k]
        gain = 1.0 if self.gains is None else float(self.gains[k])
        cut = self._cut(k, region)
        patch = self.warper.warp(self.image(k), self.G[k], gain=gain, name=k, box=cut)
        if patch is None:  # screened out by plan_canvas; here only if G changed
            raise ValueError(f"frame {k}: homography has no valid footprint")
        if (cut is None and self._seq is not None and patch.nbytes <= self._cache_bytes):
            self._cache[k] = patch
            self._bytes += patch.nbytes
            self._evict()
        return patch

    def _evict(self) -> None:
        while self._bytes > self._cache_bytes:
            k, patch = self._cache.popitem(last=False)
            filled = self._filled.pop(k, None)
            self._bytes -= patch.nbytes + (0 if filled is None else filled.nbytes)

    def filled(self, k: int, patch: Patch) -> np.ndarray:
        """(h, w, C) float32 colour of frame k's `patch`: its premultiplied colour divided by
        its weight, and where no frame pixel reaches, the push-pull fill of the whole patch
        (fill_outside), so every part multiband cuts from it shows the same values there
        (MULTIBAND_REACH). Kept with the patch while it is cached (its bytes counted in the
        cache's). A patch warped only over a tile's region (`clip`) is filled from that part:
        tiled then differs from one piece near that frame's edges (a frame too large for the
        cache: 32 MB holds a 1400 x 1400 px colour patch)."""
        cached = self._cache.get(k) is patch
        if cached and k in self._filled:
            return self._filled[k]
        colour = filled_colour(patch.data)  # (as MultibandRegion.feed fills a part)
        if cached:
            self._filled[k] = colour
            self._bytes += colour.nbytes
            self._evict()
        return colour

    def weight_patch(self, k: int, region: tuple[int, int, int, int] | None = None) -> Patch:
        if k in self._cache:
            p = self._cache[k]
            return Patch(p.x0, p.y0, p.data[:, :, -1:])
        # The frame's own weights (highlights lowered) when the frames can be read twice; a
        # one-pass iterable is warped without mask_specular (render_mosaic), so the seams
        # chosen here are those of the patches.
        image = (self.image(k) if self.warper.options.mask_specular and self._seq is not None
                 else None)
        return self.warper.warp_weight(self.G[k], image, name=k, box=self._cut(k, region))


# A frame's patch enters multiband's pyramids cut to the pixels the frame owns plus this many
# 2^bands px around them (the reach of the coarsest band's weights): with many overlapping
# frames each owns a small part of its footprint. Where the part lies outside the frame's
# footprint it takes the push-pull fill (fill_outside) of the whole patch (_PatchSource.filled),
# not of the part: that fill depends on where the part was cut, and changed the blend near the
# frames' edges by up to 6 grey levels against the uncut blend, and tiled against one piece by
# as much (17 with the hand-held frames' black corners and no field-of-view mask; review 50).
# Now 1 and 0-1. Widening the cut instead did less for more: 150 SYN frames 400x400 (no mask,
# bands 5, true homographies), CPU with OpenCV on 1 thread (median of 5) and grey levels off
# the uncut blend (pixels > 2): the part's fill 2.39 s, 6 (387); the whole patch's 3.94 s, 1 (0);
# the part's at reach 4 3.02 s, 4 (53); uncut 3.71 s. Hand-held with its mask: 1.15 s, 2 (0);
# 1.75 s, 1; 1.74 s, 1; 4.45 s. bench_compositing's tiled 3000-frame mosaic (tile 1024): 64 s,
# 110 s, 87 s (tiled still 3-4 levels off one piece; a tile margin of 8 x 2^bands, not 4,
# brought that to 1 and took 113 s).
MULTIBAND_REACH = 2


def _render_region(x0: int, y0: int, w: int, h: int, ks: Iterable[int], source: _PatchSource,
                   options: BlendOptions, channels: int | None = None, progress=None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Blends frames `ks` (increasing) into region [x0, x0+w) x [y0, y0+h) of reference pixels.
    Returns (uint8 (h, w, C), covered (h, w) bool). channels: needed only if ks is empty."""
    ks = list(ks)
    if options.blend != "multiband":
        acc = None if not channels else np.zeros((h, w, channels + 1), np.float32)
        for k in ks:
            patch = source.patch(k, (x0, y0, x0 + w, y0 + h))
            if acc is None:
                acc = np.zeros((h, w, patch.data.shape[2]), np.float32)
            accumulate(acc, x0, y0, patch, options.blend)
            if progress is not None:
                progress.update(1)
        if acc is None:
            raise ValueError("no frame to render and no channel count given")
        return resolve(acc)

    step = 2 ** int(options.bands)
    ax0, ay0 = (x0 // step) * step, (y0 // step) * step
    ax1, ay1 = -((-(x0 + w)) // step) * step, -((-(y0 + h)) // step) * step
    aw, ah = ax1 - ax0, ay1 - ay0
    best = np.zeros((ah, aw), np.float32)  # largest feathering weight: who owns each pixel
    for k in ks:
        wp = source.weight_patch(k, (ax0, ay0, ax1, ay1))
        ov = _overlap(wp, ax0, ay0, aw, ah)
        if ov is not None:
            np.maximum(best[ov[0]], wp.data[ov[1]][:, :, 0], out=best[ov[0]])
    region = None if not channels else MultibandRegion(ax0, ay0, aw, ah, channels,
                                                       options.bands)
    for k in ks:
        p = source.patch(k, (ax0, ay0, ax1, ay1))
        if region is None:
            region = MultibandRegion(ax0, ay0, aw, ah, p.data.shape[2] - 1, options.bands)
        ov = _overlap(p, ax0, ay0, aw, ah)
        if progress is not None:
            progress.update(1)
        if ov is None:
            continue
        reg, inside = ov
        data = p.data[inside]
        weight = data[:, :, -1]
        seam = (weight >= best[reg]) & (weight > 1e-3)
        rows, cols = np.flatnonzero(seam.any(axis=1)), np.flatnonzero(seam.any(axis=0))
        if len(rows) == 0:
            continue
        # Only the part the frame owns, plus MULTIBAND_REACH x 2^bands px, enters the
        # pyramids, filled outside the footprint as the whole patch is (MULTIBAND_REACH).
        reach = MULTIBAND_REACH * step
        r0, r1 = max(0, (rows[0] - reach) // step * step), rows[-1] + 1 + reach
        c0, c1 = max(0, (cols[0] - reach) // step * step), cols[-1] + 1 + reach
        r1 = min(-(-r1 // step) * step, seam.shape[0])
        c1 = min(-(-c1 // step) * step, seam.shape[1])
        part = data[r0:r1, c0:c1]
        if (part[:, :, -1] <= COVERED).any():
            part = np.empty(part.shape, np.float32)
            part[:, :, :-1] = source.filled(k, p)[inside][r0:r1, c0:c1]
            part[:, :, -1] = 1.0  # (weight 1 everywhere: MultibandRegion.feed fills no more)
        region.feed(Patch(ax0 + reg[1].start + c0, ay0 + reg[0].start + r0, part),
                    seam[r0:r1, c0:c1])
    if region is None:
        raise ValueError("no frame to render and no channel count given")
    out = region.result()[y0 - ay0:y0 - ay0 + h, x0 - ax0:x0 - ax0 + w]
    covered = best[y0 - ay0:y0 - ay0 + h, x0 - ax0:x0 - ax0 + w] > 1e-3
    image = np.clip(np.rint(out), 0, 255).astype(np.uint8)
    image[~covered] = 0
    return image, covered


# ------------------------------------------------------------------------------------------
# Public renderers
# ------------------------------------------------------------------------------------------


@dataclass
class RenderedMosaic:
    image: np.ndarray  # (H, W) or (H, W, 3) uint8
    covered: np.ndarray  # (H, W) bool: some frame shows this pixel
    plan: CanvasPlan


def _frame_boxes(G: np.ndarray, use: np.ndarray, warper: FrameWarper) -> np.ndarray:
    boxes = np.zeros((len(G), 4), np.int64)
    for k in np.flatnonzero(use):
        boxes[k] = warper.box(G[k])
    return boxes


def _progress_bar(progress: bool, total: int, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, disable=not progress, leave=False)


def _is_pairs(frames) -> bool:
    """A list / tuple of (k, image) pairs (render_mosaic's other form), not of images: it has
    __getitem__ too, and was taken as frames[k] (a NumPy 'inhomogeneous shape' error)."""
    if not isinstance(frames, list | tuple) or not frames:
        return False
    first = frames[0]
    return (isinstance(first, tuple) and len(first) == 2
            and isinstance(first[0], int | np.integer) and not isinstance(first[0], bool))


def render_mosaic(frames, homographies: np.ndarray, width: int, height: int, *,
                  mask: np.ndarray | None = None, blend: str | BlendOptions = "linear",
                  max_pixels: int = MAX_CANVAS_PIXELS, gains: np.ndarray | None = None,
                  plan: CanvasPlan | None = None, progress: bool = False,
                  highlights: SpecularMasks | None = None) -> RenderedMosaic:
    """Renders the whole mosaic in one piece (memory ~ 16 bytes per canvas pixel, more for
    multiband).

    frames: a sequence (frames[k], e.g. a FrameSource) or an iterable of (k, image) pairs in
    increasing k (unplaced frames may be left out). mask: (H, W) field of view (uint8 255 or bool).
    gains: (N,) per-frame gains (see :func:`frame_gains`). Multiband from a one-pass iterable
    leaves highlights in (BlendOptions.mask_specular): its seams are chosen before any frame is
    read. highlights: the specular masks frame_gains found (the same SpecularMasks), so each
    frame's is found once; None: found here (multiband: once for its seams and patches)."""
    if _is_pairs(frames):  # a list of (k, image) pairs: read once, in order (not frames[k])
        frames = iter(frames)
    options = as_blend_options(blend)
    if (options.blend == "multiband" and options.mask_specular
            and not hasattr(frames, "__getitem__")):
        options = replace(options, mask_specular=False)
    if highlights is None and options.mask_specular and options.blend == "multiband":
        highlights = SpecularMasks()
    options = fit_bands(options, width, height)
    G = np.asarray(homographies, np.float64)
    plan = plan or plan_canvas(G, width, height, max_pixels=max_pixels)
    if plan.pixels > max_pixels:
        raise CanvasTooLargeError(f"mosaic canvas of {plan.width} x {plan.height} pixels exceeds "
                                  f"the budget of {max_pixels} pixels")
    warper = FrameWarper(width, height, mask, options,
                         highlights=highlights if options.mask_specular else None)
    source = _PatchSource(frames, G, warper, gains, cache_bytes=0)
    ks = np.flatnonzero(plan.use)
    with _progress_bar(progress, len(ks), "mosaic") as bar:
        image, covered = _render_region(plan.x0, plan.y0, plan.width, plan.height, ks, source,
                                        options, progress=bar)
    if warper.channels == 1:
        image = image[:, :, 0]
    return RenderedMosaic(image, covered, plan)


def write_mosaic_png(path: str | Path, frames: Sequence, homographies: np.ndarray, width: int,
                     height: int, *, mask: np.ndarray | None = None,
                     blend: str | BlendOptions = "linear", canvas: CanvasOptions | None = None,
                     gains: np.ndarray | None = None, plan: CanvasPlan | None = None,
                     progress: bool = False, highlights: SpecularMasks | None = None
                     ) -> tuple[CanvasPlan, float]:
    """Renders the mosaic tile by tile and streams it into a PNG at `path`; memory is bounded by
    one band of tiles (tile_size rows x canvas width x C bytes, C + 1 with canvas.alpha), the
    rendering of one tile (its accumulator, tile_size^2 x (C + 1) x 4 bytes, and its uint8
    result; for multiband, a tile and its margin of 4 x 2^bands px, in pyramids), the patch
    cache (canvas.cache_mb; for multiband, the patches' filled colour counted in it) and the
    PNG encoding (~9 MiB: png.PngStreamWriter), whatever the canvas size (up to
    canvas.max_pixels). A 29800 x 2048 canvas, tile 2048 (band 175 MB, accumulator 64 MB) peaks
    at 386 MB traced (899 MB when the encoding took four copies of the band).

    frames: a sequence (frames[k]); frames overlapping several tiles are read and warped again
    unless still in the cache; each frame's specular mask is found once (highlights: those
    frame_gains found, else a new SpecularMasks). Returns (plan, fraction of covered pixels).
    canvas.alpha: the PNG gets an alpha channel, 255 where covered."""
    from fusedmosaic.compositing.png import PngStreamWriter

    if _is_pairs(frames) or not hasattr(frames, "__getitem__"):
        raise TypeError("write_mosaic_png: frames must be a sequence of images (frames[k]: "
                        "the tiles read a frame again), not (k, image) pairs or a one-pass "
                        "iterable; render_mosaic takes those")
    options = fit_bands(as_blend_options(blend), width, height)
    canvas = canvas or CanvasOptions()
    canvas.validate()
    G = np.asarray(homographies, np.float64)
    plan = plan or plan_canvas(G, width, height, max_pixels=canvas.max_pixels,
                               absurd_area_factor=canvas.absurd_area_factor)
    if highlights is None and options.mask_specular:
        highlights = SpecularMasks()
    warper = FrameWarper(width, height, mask, options,
                         highlights=highlights if options.mask_specular else None)
    source = _PatchSource(frames, G, warper, gains, int(canvas.cache_mb * 2**20), clip=True)
    ks = np.flatnonzero(plan.use)
    first = np.asarray(frames[int(ks[0])])
    warper.channels = 1 if first.ndim == 2 else first.shape[2]
    boxes = _frame_boxes(G, plan.use, warper)
    margin = 4 * 2 ** int(options.bands) if options.blend == "multiband" else 0
    T = int(canvas.tile_size)
    covered_px = 0
    n_tiles = -(-plan.width // T) * -(-plan.height // T)
    C = warper.channels
    with PngStreamWriter(path, plan.width, plan.height, C + bool(canvas.alpha)) as png, \
            _progress_bar(progress, n_tiles, "mosaic tiles") as bar:
        for ty in range(plan.y0, plan.y1, T):
            th = min(T, plan.y1 - ty)
            band = np.zeros((th, plan.width, C + bool(canvas.alpha)), np.uint8)
            for tx in range(plan.x0, plan.x1, T):
                tw = min(T, plan.x1 - tx)
                rx0, ry0 = max(tx - margin, plan.x0), max(ty - margin, plan.y0)
                rx1, ry1 = min(tx + tw + margin, plan.x1), min(ty + th + margin, plan.y1)
                hit = ks[(boxes[ks, 0] < rx1) & (boxes[ks, 2] > rx0)
                         & (boxes[ks, 1] < ry1) & (boxes[ks, 3] > ry0)]
                if len(hit):
                    img, cov = _render_region(rx0, ry0, rx1 - rx0, ry1 - ry0, hit, source,
                                              options, warper.channels)
                    sy, sx = ty - ry0, tx - rx0
                    cov = cov[sy:sy + th, sx:sx + tw]
                    band[:, tx - plan.x0:tx - plan.x0 + tw, :C] = img[sy:sy + th, sx:sx + tw]
                    if canvas.alpha:
                        band[:, tx - plan.x0:tx - plan.x0 + tw, C] = cov * np.uint8(255)
                    covered_px += int(cov.sum())
                bar.update(1)
            png.write_rows(band)
    return plan, covered_px / plan.pixels


def frame_gains(frames: Sequence, homographies: np.ndarray, width: int, height: int, *,
                mask: np.ndarray | None = None, use: np.ndarray | None = None,
                progress: bool = False, mask_specular: bool | None = False,
                highlights: SpecularMasks | None = None) -> np.ndarray:
    """Gain compensation (Brown & Lowe 2007, Sec. 6): reads every used frame once at 1/8 size and
    returns (N,) gains equalising the mean intensity of overlapping frames. mask_specular: the
    blend's (BlendOptions.mask_specular; None: off): the frames' specular highlights are left
    out of the overlaps compared (thumbnail). highlights: a SpecularMasks to keep the masks
    found in, for the renderer (render_mosaic / write_mosaic_png) to reuse."""
    G = np.asarray(homographies, np.float64)
    use = usable_frames(G, width, height) if use is None else use
    thumbs = {}
    from tqdm import tqdm

    for k in tqdm(np.flatnonzero(use), desc="gains", disable=not progress, leave=False):
        thumbs[int(k)] = thumbnail(frames[int(k)], mask_specular=bool(mask_specular),
                                   highlights=highlights, key=int(k))
    return compensate_gains(thumbs, G, width, height, mask)


def compose_mosaic(frames: Iterable[tuple[int, np.ndarray]], homographies: np.ndarray,
                   width: int, height: int, *, mask: np.ndarray | None = None,
                   blend: str | BlendOptions = "last", max_pixels: int = MAX_CANVAS_PIXELS,
                   gains: np.ndarray | None = None) -> np.ndarray:
    """Warps (index, image) pairs into one canvas (see :func:`render_mosaic`); unplaced and
    absurd frames are skipped. Returns the uint8 mosaic."""
    pairs = iter(frames)  # (index, image) pairs, even if given as a list
    return render_mosaic(pairs, homographies, width, height, mask=mask, blend=blend,
                         max_pixels=max_pixels, gains=gains).image
