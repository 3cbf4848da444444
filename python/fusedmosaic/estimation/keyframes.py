"""Sparse keyframe sets for the LBA window (seed 000, Sec. 3.4, Fig. 5).

The image corners of every estimated frame are projected to the mosaic with the current
estimates and their centroid is taken (Fig. 5a); centroids are clustered with K-means (5b) and a
random consecutive subset of frames is picked in each cluster (5c). Their fixed cameras and
correspondences keep the plane observed over the whole explored area.

Frames are grouped in blocks of `block_size` consecutive frames, the "consecutive subsets" of
the paper; K-means runs on block centroids and one random block is picked per cluster. To keep
the per-step cost and the memory flat in sequence length (the paper keeps everything), at most
`max_blocks` blocks are retained: when full, a block is evicted from the most crowded cell of a
grid over the mosaic (the oldest there), so coverage of the explored area is kept while revisits
stop adding state. Evicted frames are returned so the caller can forget their data.
"""

from __future__ import annotations

import numbers
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from scipy.cluster.vq import kmeans2


@dataclass
class _Block:
    frame_ids: list[int]
    centroids: list[np.ndarray]
    centroid: np.ndarray | None = None  # mean of centroids, set once when the block closes


class KeyframeIndex:
    """Keyframe candidates: blocks of `block_size` consecutive frames (an integer >= 1), at
    most `max_blocks` (an integer >= 1) kept, evicted by crowding on a grid of square cells
    `cell_size_px` reference pixels wide (a finite number > 0: 0 or NaN put every block in
    one cell of NaN, eviction then oldest first whatever the coverage, with numpy warnings at
    each eviction; review 52). ValueError otherwise, naming the argument."""

    def __init__(self, block_size: int, *, max_blocks: int = 200, cell_size_px: float = 200.0,
                 rng: np.random.Generator | None = None):
        for name, value in (("block_size", block_size), ("max_blocks", max_blocks)):
            if (not isinstance(value, numbers.Integral) or isinstance(value, bool | np.bool_)
                    or value < 1):
                raise ValueError(f"KeyframeIndex: {name} must be an integer >= 1, got "
                                 f"{value!r}")
        if (not isinstance(cell_size_px, numbers.Real) or isinstance(cell_size_px, bool | np.bool_)
                or not np.isfinite(cell_size_px) or cell_size_px <= 0):
            raise ValueError("KeyframeIndex: cell_size_px (the crowding grid's cell, reference "
                             f"pixels) must be a finite number > 0, got {cell_size_px!r}")
        self.block_size = block_size
        self.max_blocks = max_blocks
        self.cell_size_px = cell_size_px
        self.rng = rng or np.random.default_rng(0)
        self._blocks: OrderedDict[int, _Block] = OrderedDict()  # block id -> block (old first)
        self._open: _Block | None = None
        self._next_id = 0

    def __len__(self) -> int:
        return len(self._blocks)

    def snapshot(self) -> tuple:
        """The index's state, for restore() (a caller rolling back a failed step)."""
        open_ = None if self._open is None else _Block(list(self._open.frame_ids),
                                                        list(self._open.centroids))
        return OrderedDict(self._blocks), open_, self._next_id, self.rng.bit_generator.state

    def restore(self, state: tuple) -> None:
        blocks, open_, next_id, rng_state = state
        self._blocks = OrderedDict(blocks)  # closed blocks are never changed, only dropped
        self._open = None if open_ is None else _Block(list(open_.frame_ids),
                                                       list(open_.centroids))
        self._next_id = next_id
        self.rng.bit_generator.state = rng_state

    def add(self, frame_id: int, centroid: np.ndarray) -> list[int]:
        """Adds an estimated frame's centroid (reference pixels). Returns frame ids to forget.
        A centroid that is not finite (its outline projects to infinity) is skipped: that frame
        is no keyframe. Stored, it made every later select() raise in K-means, and the block
        stayed until crowding evicted it (review)."""
        centroid = np.asarray(centroid, float)
        if not np.isfinite(centroid).all():
            return []
        if self._open is None:
            self._open = _Block([], [])
        self._open.frame_ids.append(frame_id)
        self._open.centroids.append(centroid)
        if len(self._open.frame_ids) < self.block_size:
            return []
        self._open.centroid = np.mean(self._open.centroids, axis=0)
        self._blocks[self._next_id] = self._open
        self._next_id += 1
        self._open = None
        return self._evict() if len(self._blocks) > self.max_blocks else []

    def _evict(self) -> list[int]:
        ids = list(self._blocks)
        cells = np.floor(np.array([self._blocks[i].centroid for i in ids]) / self.cell_size_px)
        _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
        crowded = np.flatnonzero(counts[inverse.ravel()] == counts.max())[0]  # oldest there
        return self._blocks.pop(ids[crowded]).frame_ids

    def select(self, num_clusters: int, exclude: set[int] | None = None) -> list[int]:
        """Keyframe ids: one random block of consecutive frames per K-means cluster."""
        exclude = exclude or set()
        blocks = [b for b in self._blocks.values() if not exclude.intersection(b.frame_ids)]
        if not blocks or num_clusters < 1:
            return []
        if len(blocks) <= num_clusters:
            return sorted(k for b in blocks for k in b.frame_ids)
        pts = np.array([b.centroid for b in blocks])
        # Coinciding block centroids (a camera held over one spot) are clustered once: K-means
        # on fewer distinct points than clusters divided by zero and left clusters empty, with
        # scipy warnings at every step. Each distinct centroid is then a cluster of its own
        # when there are at most num_clusters of them.
        unique, inverse = np.unique(pts, axis=0, return_inverse=True)
        inverse = inverse.ravel()
        distinct = len(unique) == len(pts)  # (then clustered as given: the same draws)
        if not distinct and len(unique) <= num_clusters:
            labels = inverse
        else:
            seed = int(self.rng.integers(2**31 - 1))
            _, labels = kmeans2(pts if distinct else unique, num_clusters, minit="++", seed=seed)
            labels = labels if distinct else labels[inverse]
        chosen = []
        for c in range(num_clusters):
            members = np.flatnonzero(labels == c)
            if len(members):
                chosen.append(blocks[int(self.rng.choice(members))])
        return sorted(k for b in chosen for k in b.frame_ids)

    def centroids(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids, centroids) of retained frames, for plots and tests."""
        ids = [k for b in self._blocks.values() for k in b.frame_ids]
        pts = [c for b in self._blocks.values() for c in b.centroids]
        return np.array(ids, int), np.array(pts).reshape(-1, 2)
