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


def emt_guided_pairs(predicted: np.ndarray, width: int, height: int, *,
                     min_overlap: float = 0.3, max_per_frame: int | None = 20,
                     fov_radius: float | None = None) -> list[tuple[int, int]]:
    """Pairs (l > m) whose predicted footprints overlap by >= min_overlap of the smaller one.

    predicted: (N, 3, 3) frame -> reference homographies from tracker poses and a plane.
    Frames without a prediction (NaN) are paired with their temporal neighbours only.
    max_per_frame keeps, for each l, the m with the largest overlap (bounds attempts to O(N k)).
    """
    polys = footprint_polygons(predicted, width, height, fov_radius)
    n = len(polys)
    areas = np.array([cv2.contourArea(p) if p is not None else 0.0 for p in polys])
    centres = np.array([p.mean(axis=0) if p is not None else (np.nan, np.nan) for p in polys])
    radii = np.array([np.linalg.norm(p - p.mean(axis=0), axis=1).max() if p is not None else 0
                      for p in polys])
    pairs: list[tuple[int, int]] = []
    for l in range(n):
        if polys[l] is None:
            pairs += [(l, m) for m in (l - 1,) if m >= 0]
            continue
        candidates = []
        for m in range(l):
            if polys[m] is None:
                if m == l - 1:
                    pairs.append((l, m))
                continue
            if np.linalg.norm(centres[l] - centres[m]) > radii[l] + radii[m]:
                continue  # bounding circles apart: cannot overlap
            inter, _ = cv2.intersectConvexConvex(polys[l], polys[m])
            frac = inter / max(min(areas[l], areas[m]), 1e-9)
            if frac >= min_overlap:
                candidates.append((frac, m))
        candidates.sort(reverse=True)
        if max_per_frame is not None:
            candidates = candidates[:max_per_frame]
        pairs += [(l, m) for _, m in sorted(candidates, key=lambda c: c[1])]
    return pairs
