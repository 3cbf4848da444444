"""PairVis (seed 000, Sec. 3.1, Eq. 2): consecutive homographies chained to the first frame.

G_{k+1} = G_k H_{k,k+1}, where H_{k,k+1} maps frame k+1 pixels into frame k. It is the paper's
baseline: small registration errors accumulate (drift), and when a consecutive pair cannot be
registered the chain breaks, so that frame and every later frame are left unplaced.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np
from tqdm import tqdm

from fusedmosaic.methods import MethodResult
from fusedmosaic.registration.features import FeatureOptions, extract_features
from fusedmosaic.registration.pairs import MatchOptions, match_pairs


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


def run_pairwise(dataset, *, progress: bool = True,
                 options: PairwiseOptions | None = None) -> MethodResult:
    o = options or PairwiseOptions()
    cam = dataset.camera
    n = len(dataset.frames)
    timings = {}
    t0 = time.perf_counter()
    # keypoints in undistorted pixels (camera.yaml's lens distortion removed), where the
    # frame-to-frame mapping of a plane is a homography
    feats = extract_features(dataset.frames, range(n), cam.fov_mask(), o.features, progress,
                             undistortion=cam.undistortion())
    timings["features"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pairs = [(k, k + 1) for k in range(n - 1)]  # target k, source k + 1
    with tqdm(total=len(pairs), desc="matching", disable=not progress, leave=False) as bar:
        matches = match_pairs(feats, pairs, (cam.width, cam.height), o.matching, bar.update)
    timings["matching"] = time.perf_counter() - t0
    ids = dataset.frame_ids
    unreadable = getattr(dataset.frames, "unreadable", {})
    # The chain starts at the first frame with content: frame 0 unreadable (read as a black
    # frame) or featureless left every frame unplaced and the run failed with "no placed frame"
    # naming neither (review). Frames before it are unplaced; it is the reference.
    start = next((k for k in range(n) if k not in unreadable
                  and len(feats[k]) >= o.matching.min_inliers), 0)
    if n > 1 and not any(m.ok for m in matches):
        first = unreadable.get(0) or (f"pair ({int(ids[0])}, {int(ids[1])}): "
                                      f"{matches[0].status}")
        raise ValueError(f"{dataset.root}: no consecutive pair of frames could be registered "
                         f"(first failure: {first})")
    t0 = time.perf_counter()
    G = chain_homographies([m.H_lm if m.ok else None for m in matches], start)
    timings["optimisation"] = time.perf_counter() - t0
    status = []
    for k in range(start):
        why = ("its image cannot be read" if k in unreadable else
               f"too few features ({len(feats[k])})")
        status.append(f"unplaced: before the chain's first frame ({why})")
    status.append("placed")
    broken = None
    for k in range(start, n - 1):
        m = matches[k]
        if broken is None and not m.ok:
            broken = k + 1  # (the statuses name frame ids, as homographies.csv: a dataset
            # with files missing named positions, 'pair (9, 10)' for frames 9 and 12; review)
            status.append(f"unplaced: pair ({int(ids[k])}, {int(ids[k + 1])}) not registered: "
                          f"{m.status}")
        elif broken is not None:
            status.append(f"unplaced: chain broken at frame {int(ids[broken])}")
        else:
            status.append("placed")
    ok = [m for m in matches if m.ok]
    details = {"pairs": {"attempted": len(matches), "registered": len(ok),
                         "mean_correspondences": float(np.mean([m.n_inliers for m in ok]))
                         if ok else 0.0}}
    warnings = []
    if start > 0:
        warnings.append(
            f"the pairwise chain starts at frame {int(ids[start])}, the first frame whose image "
            f"can be read and has features: the {start} frame(s) before it are unplaced")
    if broken is not None:  # exit 0 with most frames unplaced must not pass unnoticed
        warnings.append(
            f"the pairwise chain breaks at frame {int(ids[broken])}: pair ({int(ids[broken - 1])}, "
            f"{int(ids[broken])}) not registered ({matches[broken - 1].status}), so "
            f"{n - broken} of {n} frames are unplaced (PairVis cannot continue past a failed "
            "pair; ba-emt / lba-emt place them with the tracker)")
    if warnings:
        details["warnings"] = warnings
    return MethodResult(
        homographies=G,
        status=status,
        timings=timings,
        parameters=asdict(o),
        details=details,
    )

