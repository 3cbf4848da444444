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

    With a circular field of view the outline is the circle, not the image rectangle."""
    if fov_radius:
        a = np.linspace(0, 2 * np.pi, n_vertices, endpoint=False)
        outline = np.stack([(width - 1) / 2 + fov_radius * np.cos(a),
                            (height - 1) / 2 + fov_radius * np.sin(a)], axis=1)
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


def emt_guided_pairs(predicted: np.ndarray, width: int, height: int, *,
                     min_overlap: float = 0.3, max_per_frame: int | None = 20,
                     fov_radius: float | None = None, temporal_window: int = 2,
                     min_separation: int = 4) -> list[tuple[int, int]]:
    """Pairs (l > m) whose predicted footprints overlap by >= min_overlap of the smaller one.

    predicted: (N, 3, 3) frame -> reference homographies from tracker poses and a plane.
    Temporal neighbours (l - m <= temporal_window) that overlap are always kept; frames without a
    prediction (NaN) are paired with their temporal neighbours only. Of the older overlapping
    frames, at most max_per_frame are kept per l (O(N k) attempts), chosen greedily by overlap
    but at least min_separation frames apart: a revisit of the same area contributes one wide-
    baseline loop pair instead of k near-duplicates (measured: better e_M per attempted pair).
    """
    polys = footprint_polygons(predicted, width, height, fov_radius)
    n = len(polys)
    placed = np.array([p is not None for p in polys], bool)
    areas = np.array([cv2.contourArea(p) if p is not None else 0.0 for p in polys])
    centres = np.array([p.mean(axis=0) if p is not None else (np.nan, np.nan) for p in polys])
    radii = np.array([np.linalg.norm(p - p.mean(axis=0), axis=1).max() if p is not None else 0
                      for p in polys])
    pairs: list[tuple[int, int]] = []
    for l in range(n):
        if not placed[l]:
            pairs += [(l, m) for m in (l - 1,) if m >= 0]
            continue
        # Bounding circles apart cannot overlap: one vector test per l over the older frames
        # (a Python loop over every (l, m) took 25 s at 2000 frames; review).
        near = np.flatnonzero(placed[:l] & (np.linalg.norm(centres[:l] - centres[l], axis=1)
                                            <= radii[:l] + radii[l]))
        candidates = []
        for m in near.tolist():
            frac = overlap_fraction(polys[l], polys[m], areas[l], areas[m])
            if frac >= min_overlap:
                candidates.append((frac, m))
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
    picked: list[int] = []
    for _, m in older:
        if max_per_frame is not None and len(picked) >= max_per_frame:
            break
        if all(abs(m - q) >= min_separation for q in picked):
            picked.append(m)
    return [(l, m) for m in sorted(chosen + picked)]
