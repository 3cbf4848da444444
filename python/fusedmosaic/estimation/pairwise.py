"""PairVis (seed 000, Sec. 3.1, Eq. 2): consecutive homographies chained to the first frame.

G_{k+1} = G_k H_{k,k+1}, where H_{k,k+1} maps frame k+1 pixels into frame k. It is the paper's
baseline: small registration errors accumulate (drift), and when a consecutive pair cannot be
registered the chain breaks, so that frame and every later frame are left unplaced.
"""

from __future__ import annotations

import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field

import numpy as np
from tqdm import tqdm

from fusedmosaic.methods import MethodResult
from fusedmosaic.registration.features import FeatureExtractor, FeatureOptions, Features
from fusedmosaic.registration.pairs import MatchOptions, PairMatch, match_pair


@dataclass
class PairwiseOptions:
    features: FeatureOptions = field(default_factory=FeatureOptions)
    matching: MatchOptions = field(default_factory=MatchOptions)


def chain_homographies(consecutive: list[np.ndarray | None], start: int = 0) -> np.ndarray:
    """Chains H_{k,k+1} (frame k+1 -> k), k = 0..N-2, into frame -> reference G_k (Eq. 2), the
    reference being frame ``start`` (0; frames before it get NaN).

    A None entry from ``start`` on breaks the chain: that frame and all later ones get NaN."""
    n = len(consecutive) + 1
    G = np.full((n, 3, 3), np.nan)
    G[start] = np.eye(3)
    for k in range(start, n - 1):
        H = consecutive[k]
        if H is None:
            break
        g = G[k] @ H
        G[k + 1] = g / g[2, 2]
    return G


def _stream_pairs(frames, n: int, extractor: FeatureExtractor, image_size: tuple[int, int],
                  matching: MatchOptions, bar,
                  timings: dict) -> tuple[list[int], list[PairMatch], list[int]]:
    """Features of frames 0..n-1 and the matches (k, k + 1), streamed: frames are detected in
    order a few ahead, each pair is matched as soon as both frames' features exist, and a
    frame's features are dropped once its pairs are matched. PairVis needs no more: extracting
    every frame first held all their features (~100 kB per frame at ~200 SIFT keypoints, 500
    kB at 1000: 7.5 GB for a 10-minute recording at 25 frames/s; review); streamed, the run's
    peak memory grew 89 MB over 300 hand-held frames and 98 MB over 1500, where it grew 116 and
    230 MB. Returns the keypoint count per frame, the matches in pair order with their inlier
    points dropped, and their inlier counts.

    Detection and matching share one pool of threads (OpenCV releases the GIL), each task the
    same computation as before, so the results are the same whatever the threads' order."""
    workers = max(2, matching.num_threads)  # (features had 2 threads, matching num_threads)
    ahead = 2 * workers  # frames detected ahead of the one being paired, and pairs in flight
    counts: list[int] = []
    matches: list[PairMatch] = []
    inliers: list[int] = []
    pending_features: deque = deque()
    pending_matches: deque = deque()

    # The stages' times are their tasks' summed durations (the work each did, as the paper's
    # Table 1 reports them): detection and matching overlap in the pool, so wall-clock
    # segments split them arbitrarily (matching read 0.002 s for 151 SYN pairs: only what was
    # left after the last frame's features; review of session 47's bench). (list.append is
    # atomic under the GIL.)
    spent: dict[str, list[float]] = {"features": [], "matching": []}

    def extract(k: int) -> Features:
        t = time.perf_counter()
        try:
            return extractor.extract(frames[k], k)
        finally:
            spent["features"].append(time.perf_counter() - t)

    def match(f_l: Features, f_m: Features) -> tuple[PairMatch, int]:
        t = time.perf_counter()
        m = match_pair(f_l, f_m, image_size, matching)
        spent["matching"].append(time.perf_counter() - t)
        n_inliers = m.n_inliers
        m.points_l = m.points_m = np.zeros((0, 2))  # (~6 kB a pair) only their count is used
        return m, n_inliers

    def collect(limit: int) -> None:
        while len(pending_matches) > limit:
            m, n_inliers = pending_matches.popleft().result()
            matches.append(m)
            inliers.append(n_inliers)
            bar.update(1)

    pool = ThreadPoolExecutor(workers)
    try:
        submitted = 0
        previous = None
        for k in range(n):
            while submitted < n and submitted <= k + ahead:
                pending_features.append(pool.submit(extract, submitted))
                submitted += 1
            features = pending_features.popleft().result()
            counts.append(len(features))
            if previous is not None:
                pending_matches.append(pool.submit(match, previous, features))
            previous = features
            collect(ahead)
        del features, previous
        collect(0)
        timings["features"], timings["matching"] = (float(sum(spent["features"])),
                                                    float(sum(spent["matching"])))
    finally:
        pool.shutdown(wait=True, cancel_futures=True)  # (an error: no more frames read)
    return counts, matches, inliers


def run_pairwise(dataset, *, progress: bool = True,
                 options: PairwiseOptions | None = None) -> MethodResult:
    o = options or PairwiseOptions()
    o.matching.validate()
    cam = dataset.camera
    n = len(dataset.frames)
    if n == 0:
        raise ValueError(f"{dataset.root}: no frames")
    timings = {}
    # keypoints in undistorted pixels (camera.yaml's lens distortion removed), where the
    # frame-to-frame mapping of a plane is a homography
    extractor = FeatureExtractor(o.features, cam.fov_mask(), cam.undistortion())
    with tqdm(total=max(n - 1, 0), desc="features and matching", disable=not progress,
              leave=False) as bar:
        counts, matches, inliers = _stream_pairs(dataset.frames, n, extractor,
                                                 (cam.width, cam.height), o.matching, bar,
                                                 timings)
    ids = dataset.frame_ids
    unreadable = getattr(dataset.frames, "unreadable", {})

    def pair_name(k: int) -> str:
        return f"pair ({int(ids[k])}, {int(ids[k + 1])})"

    def why_unplaced(k: int) -> str:  # a frame before the chain's first
        if k in unreadable:
            return "its image cannot be read"
        if k == n - 1:
            return f"too few features ({counts[k]} < {o.matching.min_inliers})"
        return f"{pair_name(k)} not registered: {matches[k].status}"

    # The chain starts at the first frame registered to the next one: that frame is the
    # reference, the frames before it unplaced. A first frame with features that matched
    # nothing (defocused while the scope went in, a flash, smoke, noise) lost the whole
    # sequence, 1 of 150 placed, where a black one (no features) moved the start (review).
    start = next((k for k in range(n - 1) if matches[k].ok), None)
    if start is None:
        if n > 1:
            first = unreadable.get(0) or f"{pair_name(0)}: {matches[0].status}"
            raise ValueError(f"{dataset.root}: no consecutive pair of frames could be registered "
                             f"(first failure: {first})")
        if 0 in unreadable or counts[0] < o.matching.min_inliers:
            # (a single black frame was 'placed', exit 0, a black mosaic and no warning; review)
            raise ValueError(f"{dataset.root}: its only frame ({int(ids[0])}) has no visual "
                             f"content to place ({unreadable.get(0) or why_unplaced(0)})")
        start = 0
    t0 = time.perf_counter()
    G = chain_homographies([m.H_lm if m.ok else None for m in matches], start)
    timings["optimisation"] = time.perf_counter() - t0
    status = [f"unplaced: before the chain's first frame ({why_unplaced(k)})"
              for k in range(start)]
    status.append("placed")
    broken = None
    for k in range(start, n - 1):
        m = matches[k]
        if broken is None and not m.ok:
            broken = k + 1  # (the statuses name frame ids, as homographies.csv: a dataset
            # with files missing named positions, 'pair (9, 10)' for frames 9 and 12; review)
            status.append(f"unplaced: {pair_name(k)} not registered: {m.status}")
        elif broken is not None:
            status.append(f"unplaced: chain broken at frame {int(ids[broken])}")
        else:
            status.append("placed")
    ok = [c for m, c in zip(matches, inliers, strict=True) if m.ok]
    details = {"pairs": {"attempted": len(matches), "registered": len(ok),
                         "mean_correspondences": float(np.mean(ok)) if ok else 0.0}}
    warnings = []
    if start > 0:
        warnings.append(
            f"the pairwise chain starts at frame {int(ids[start])}, the first frame registered "
            f"to the next one: the {start} frame(s) before it are unplaced (frame "
            f"{int(ids[0])}: {why_unplaced(0)})")
    if broken is not None:  # exit 0 with most frames unplaced must not pass unnoticed
        # (counted with the frames before the chain's start: 5 of 10 said where 7 were; review)
        warnings.append(
            f"the pairwise chain breaks at frame {int(ids[broken])}: {pair_name(broken - 1)} "
            f"not registered ({matches[broken - 1].status}), so {n - broken + start} of {n} "
            "frames are unplaced (PairVis cannot continue past a failed pair; ba-emt / lba-emt "
            "place them with the tracker)")
    if warnings:
        details["warnings"] = warnings
    return MethodResult(
        homographies=G,
        status=status,
        timings=timings,
        parameters=asdict(o),
        details=details,
    )
