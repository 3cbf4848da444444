"""Which image pairs to attempt to match (seed 000, Sec. 1 and 3.4).

* `all_pairs`: every pair, the paper's O(N^2) attempts for bundle adjustment.
* `window_pairs`: pairs within a temporal window (PairVis uses w = 1).
* `emt_guided_pairs`: only pairs whose footprints, predicted from the tracker poses and the current
  plane estimate, overlap by at least a fraction of the smaller footprint: O(N k) attempts.
"""

from __future__ import annotations

import cv2
import numpy as np


def all_pairs(n: int) -> list[tuple[int, int]]:
    """(l, m) with l > m for all frames."""
    return [(l, m) for l in range(n) for m in range(l)]


def window_pairs(n: int, window: int = 1) -> list[tuple[int, int]]:
    return [(l, m) for l in range(n) for m in range(max(0, l - window), l)]


def footprint_polygons(homographies: np.ndarray, width: int, height: int,
                       fov_radius: float | None = None, n_vertices: int = 24) -> list:
    """Frame outlines in reference pixels (convex polygons), None for unplaced frames.

    With a circular field of view the outline is the circle, not the image rectangle, and
    the part of it within the frame when it is larger (a radius beyond half a side: the circle
    cropped, as HD fetoscopy video often is). The whole circle overestimated overlaps: 720x576,
    radius 400, shifted 400 / 500 px, 0.39 / 0.26 where circle and frame overlap by 0.28 /
    0.11, pairs below min_overlap selected (review)."""
    if fov_radius:
        a = np.linspace(0, 2 * np.pi, n_vertices, endpoint=False)
        outline = np.stack([(width - 1) / 2 + fov_radius * np.cos(a),
                            (height - 1) / 2 + fov_radius * np.sin(a)], axis=1)
        frame = np.array([[0, 0], [width, 0], [width, height], [0, height]], np.float64)
        if ((outline < 0) | (outline > [width, height])).any():
            area, inside = cv2.intersectConvexConvex(outline.astype(np.float32),
                                                     frame.astype(np.float32))
            # (a circle around the frame: the frame; none is left only for a degenerate frame)
            outline = frame if inside is None or area <= 0 else inside.reshape(-1, 2).astype(
                np.float64)
    else:
        outline = np.array([[0, 0], [width, 0], [width, height], [0, height]], np.float64)
    hom = np.hstack([outline, np.ones((len(outline), 1))])
    polys = []
    for G in homographies:
        if not np.isfinite(G).all():
            polys.append(None)
            continue
        q = hom @ G.T
        if (q[:, 2] <= 0).any():
            polys.append(None)
            continue
        poly = (q[:, :2] / q[:, 2:]).astype(np.float32)
        polys.append(poly if cv2.isContourConvex(poly) else cv2.convexHull(poly)[:, 0, :])
    return polys


def overlap_fraction(a: np.ndarray | None, b: np.ndarray | None, area_a: float | None = None,
                     area_b: float | None = None) -> float:
    """Intersection area of two convex footprints (footprint_polygons) over the smaller one's
    area; 0 when either is None. Pass the areas when they are already known."""
    if a is None or b is None:
        return 0.0
    area_a = cv2.contourArea(a) if area_a is None else area_a
    area_b = cv2.contourArea(b) if area_b is None else area_b
    inter, _ = cv2.intersectConvexConvex(a, b)
    return float(inter / max(min(area_a, area_b), 1e-9))


# emt_guided_pairs computes at most this many footprint overlaps per frame among its older
# frames beyond the temporal window (with max_per_frame set). It computes them in order of an
# upper bound and stops as soon as the greedy choice is settled, which in a scene that moves on
# takes a few dozen; but when every footprint overlaps every other (the scope held over one
# area) the bounds settle it late and every older frame was computed: 0.93 s at 500 frames,
# 3.4 s at 1000, 14 s at 2000, ~50 s for the paper's 3770 (review). Capped, the choice is made
# among the frames with the highest bounds (the nearest footprints, overlapping almost fully):
# that scene (5 px jitter, fov radius 190 px) beside 6.9 s before took 2.2 s at 2000 frames,
# 5.8 s at 3770, with the same pairs as every overlap computed, as on the truths of SYN and
# hand-held sequences (150 and 1500 frames) and 800-frame random walks; capped at 128, 2-8 of
# 15 000-42 000 pairs differed.
MAX_OVERLAPS_PER_FRAME = 256
_FIRST_BATCH = 32  # overlaps computed before the first check whether the choice is settled


def _disc_overlap_area(d: np.ndarray, r1: np.ndarray, r2: float) -> np.ndarray:
    """Area of the intersection of discs of radii r1 and r2 whose centres are d apart."""
    d = np.asarray(d, np.float64)
    r1 = np.broadcast_to(np.asarray(r1, np.float64), d.shape)
    small = np.minimum(r1, r2)
    with np.errstate(divide="ignore", invalid="ignore"):
        a1 = np.clip((d * d + r1 * r1 - r2 * r2) / (2 * d * r1), -1, 1)
        a2 = np.clip((d * d + r2 * r2 - r1 * r1) / (2 * d * r2), -1, 1)
        kite = np.sqrt(np.maximum((-d + r1 + r2) * (d + r1 - r2) * (d - r1 + r2)
                                  * (d + r1 + r2), 0))
        lens = r1 * r1 * np.arccos(a1) + r2 * r2 * np.arccos(a2) - 0.5 * kite
    return np.where(d >= r1 + r2, 0.0,
                    np.where(d <= np.abs(r1 - r2), np.pi * small * small, lens))


def _overlapping(polys: list, areas: np.ndarray, l: int, ms: np.ndarray,
                 min_overlap: float) -> list[tuple[float, int]]:
    """(overlap fraction, m) of the frames m whose footprints overlap l's by >= min_overlap."""
    out = []
    for m in ms.tolist():
        frac = overlap_fraction(polys[l], polys[m], areas[l], areas[m])
        if frac >= min_overlap:
            out.append((frac, m))
    return out


def _greedy_older(older: list[tuple[float, int]], max_per_frame: int | None,
                  min_separation: int) -> list[int]:
    """kept_pairs' greedy choice: older (overlap fraction, m) sorted best first."""
    picked: list[int] = []
    for _, m in older:
        if max_per_frame is not None and len(picked) >= max_per_frame:
            break
        if all(abs(m - q) >= min_separation for q in picked):
            picked.append(m)
    return picked


def emt_guided_pairs(predicted: np.ndarray, width: int, height: int, *,
                     min_overlap: float = 0.3, max_per_frame: int | None = 20,
                     fov_radius: float | None = None, temporal_window: int = 2,
                     min_separation: int = 4,
                     max_overlaps: int = MAX_OVERLAPS_PER_FRAME) -> list[tuple[int, int]]:
    """Pairs (l > m) whose predicted footprints overlap by >= min_overlap of the smaller one.

    predicted: (N, 3, 3) frame -> reference homographies from tracker poses and a plane.
    Temporal neighbours (l - m <= temporal_window) that overlap are always kept; frames without a
    prediction (NaN) are paired with their temporal neighbours only. Of the older overlapping
    frames, at most max_per_frame are kept per l (O(N k) attempts), chosen greedily by overlap
    but at least min_separation frames apart: a revisit of the same area contributes one wide-
    baseline loop pair instead of k near-duplicates (measured: better e_M per attempted pair).
    With max_per_frame set, at most max_overlaps overlaps are computed per l among the older
    frames (MAX_OVERLAPS_PER_FRAME), the choice otherwise exact.
    """
    polys = footprint_polygons(predicted, width, height, fov_radius)
    n = len(polys)
    placed = np.array([p is not None for p in polys], bool)
    areas = np.array([cv2.contourArea(p) if p is not None else 0.0 for p in polys])
    centres = np.array([p.mean(axis=0) if p is not None else (np.nan, np.nan) for p in polys])
    radii = np.array([np.linalg.norm(p - p.mean(axis=0), axis=1).max() if p is not None else 0
                      for p in polys])
    # Discs and boxes a little larger than the footprints' bounding circles and boxes (float32
    # vertices) bound each overlap fraction from above.
    bounding = radii * (1 + 1e-5) + 1e-3
    low = np.array([p.min(axis=0) if p is not None else (np.nan, np.nan) for p in polys])
    high = np.array([p.max(axis=0) if p is not None else (np.nan, np.nan) for p in polys])
    low, high = low - 1e-5 * np.abs(low) - 1e-3, high + 1e-5 * np.abs(high) + 1e-3
    pairs: list[tuple[int, int]] = []
    for l in range(n):
        if not placed[l]:
            pairs += [(l, m) for m in (l - 1,) if m >= 0]
            continue
        # Bounding circles apart cannot overlap: one vector test per l over the older frames
        # (a Python loop over every (l, m) took 25 s at 2000 frames; review).
        distance = np.linalg.norm(centres[:l] - centres[l], axis=1)
        near = placed[:l] & (distance <= radii[:l] + radii[l])
        bound = np.zeros(l)
        if near.any():
            # the footprints' intersection lies in their discs' and in their boxes'
            box = np.prod(np.clip(np.minimum(high[:l][near], high[l])
                                  - np.maximum(low[:l][near], low[l]), 0, None), axis=1)
            inter = np.minimum(_disc_overlap_area(distance[near], bounding[:l][near],
                                                  bounding[l]), box)
            bound[near] = (inter / np.maximum(np.minimum(areas[:l][near], areas[l]), 1e-9)
                           * (1 + 1e-6) + 1e-9)
            near &= bound >= min_overlap
        indices = np.flatnonzero(near)
        temporal = indices[l - indices <= temporal_window]
        older = indices[l - indices > temporal_window]
        if max_per_frame is not None:  # best bound first (ties: the later frame first)
            older = older[np.lexsort((-older, -bound[older]))]
        if max_per_frame == 0:
            older = older[:0]
        candidates = _overlapping(polys, areas, l, temporal, min_overlap)
        if max_per_frame is None:
            candidates += _overlapping(polys, areas, l, older, min_overlap)
        else:
            # Computed in batches, best bound first, until the choice is settled: the greedy
            # choice among the overlaps above every bound left to compute (they come first in
            # its order, all the rest after them) has max_per_frame frames already.
            found: list[tuple[float, int]] = []
            done, batch, limit = 0, _FIRST_BATCH, min(len(older), max_overlaps)
            while done < limit:
                end = min(done + batch, limit)
                found += _overlapping(polys, areas, l, older[done:end], min_overlap)
                done = end
                if done == len(older):
                    break
                above = sorted((c for c in found if c[0] > bound[older[done]]), reverse=True)
                if len(_greedy_older(above, max_per_frame, min_separation)) >= max_per_frame:
                    break
                batch *= 2
            candidates += found
        if l >= 1 and not placed[l - 1]:
            pairs.append((l, l - 1))
        pairs += kept_pairs(l, candidates, temporal_window, max_per_frame, min_separation)
    return pairs


def kept_pairs(l: int, candidates: list[tuple[float, int]], temporal_window: int,
               max_per_frame: int | None, min_separation: int) -> list[tuple[int, int]]:
    """emt_guided_pairs' choice for frame l among its overlapping older frames, candidates
    (overlap fraction, m): every temporal neighbour, and greedily by overlap at most
    max_per_frame older frames at least min_separation apart; (l, m) pairs in order of m."""
    chosen = [m for _, m in candidates if l - m <= temporal_window]
    older = sorted((c for c in candidates if l - c[1] > temporal_window), reverse=True)
    picked = _greedy_older(older, max_per_frame, min_separation)
    return [(l, m) for m in sorted(chosen + picked)]
