"""A simple one-piece canvas: bounds from placed frames, `last` (newest on top) or `average`
blending (seed 004, Sec. III-D). Richer blending and tiling come with the compositing module's
own issue; what is here already refuses absurd footprints and canvases above a pixel budget.
"""

from __future__ import annotations

from collections.abc import Iterable

import cv2
import numpy as np

MAX_CANVAS_PIXELS = 64_000_000  # refuse larger canvases instead of allocating them
ABSURD_AREA_FACTOR = 20.0  # a footprint > 20x the median area is left out


class CanvasTooLargeError(ValueError):
    pass


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


def usable_frames(homographies: np.ndarray, width: int, height: int) -> np.ndarray:
    """Placed frames whose footprint is a sane convex quad of non-absurd area."""
    fp = footprints(homographies, width, height)
    ok = np.isfinite(fp).all(axis=(1, 2))
    areas = np.full(len(fp), np.nan)
    for k in np.flatnonzero(ok):
        quad = fp[k].astype(np.float32)
        ok[k] = cv2.isContourConvex(quad)
        areas[k] = cv2.contourArea(quad)
    if ok.any():
        med = np.median(areas[ok])
        ok &= areas <= ABSURD_AREA_FACTOR * med
    return ok


def canvas_bounds(homographies: np.ndarray, width: int, height: int,
                  use: np.ndarray | None = None) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) integer bounds in reference pixels of the used frames."""
    use = usable_frames(homographies, width, height) if use is None else use
    if not use.any():
        raise ValueError("no placed frame to compose a mosaic from")
    pts = footprints(homographies[use], width, height).reshape(-1, 2)
    x0, y0 = np.floor(pts.min(axis=0)).astype(int)
    x1, y1 = np.ceil(pts.max(axis=0)).astype(int)
    return int(x0), int(y0), int(x1), int(y1)


def compose_mosaic(frames: Iterable[tuple[int, np.ndarray]], homographies: np.ndarray,
                   width: int, height: int, *, mask: np.ndarray | None = None,
                   blend: str = "last", max_pixels: int = MAX_CANVAS_PIXELS) -> np.ndarray:
    """Warps (index, image) pairs into one canvas. Unplaced / absurd frames are skipped.

    mask: (H, W) uint8 field-of-view mask (255 = tissue) so black corners never paint."""
    if blend not in ("last", "average"):
        raise ValueError(f"blend must be 'last' or 'average', got {blend!r}")
    use = usable_frames(homographies, width, height)
    x0, y0, x1, y1 = canvas_bounds(homographies, width, height, use)
    cw, ch = x1 - x0, y1 - y0
    if cw * ch > max_pixels:
        raise CanvasTooLargeError(
            f"mosaic canvas of {cw} x {ch} pixels exceeds the budget of {max_pixels} pixels")
    offset = np.array([[1.0, 0, -x0], [0, 1.0, -y0], [0, 0, 1.0]])
    full_mask = np.full((height, width), 255, np.uint8) if mask is None else mask
    canvas = None
    weight = np.zeros((ch, cw), np.float32)
    for k, image in frames:
        if not use[k]:
            continue
        if canvas is None:
            channels = () if image.ndim == 2 else (image.shape[2],)
            canvas = np.zeros((ch, cw, *channels), np.float32)
        H = offset @ homographies[k]
        warped = cv2.warpPerspective(image, H, (cw, ch), flags=cv2.INTER_LINEAR)
        m = cv2.warpPerspective(full_mask, H, (cw, ch), flags=cv2.INTER_NEAREST) > 0
        if blend == "last":
            canvas[m] = warped[m]
            weight[m] = 1
        else:
            canvas[m] += warped[m]
            weight[m] += 1
    if canvas is None:
        raise ValueError("no placed frame to compose a mosaic from")
    if blend == "average":
        nz = weight > 0
        canvas[nz] /= weight[nz][:, None] if canvas.ndim == 3 else weight[nz]
    return np.clip(canvas, 0, 255).astype(np.uint8)
