"""Pairwise registration: ratio-test matching, RANSAC homography (DLT on minimal samples) and
a least-squares DLT + Levenberg-Marquardt refinement on the inliers (seed 000, Sec. 3.1).

A pair is registered only if enough inliers support a non-degenerate homography; otherwise it is
reported with the reason (never silently accepted). Homographies map frame m -> frame l (the
paper's H_{l,m}), and correspondences are stored with their frame ids for the bundle adjuster.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np

from fusedmosaic import _core
from fusedmosaic.registration.features import C_INT_MAX, Features


@dataclass
class MatchOptions:
    ratio: float = 0.8  # Lowe's ratio test
    # Inlier reprojection threshold, full-resolution pixels, whatever the detection scale s
    # (FeatureOptions.max_image_side: keypoints only as precise as the shrunk copy's pixels).
    # Not scaled with s: no rule helped on every sequence. ORB, mean homography error vs truth
    # over the field of view, pairs 1 and 3 frames apart, 3 px vs 3 s px: 1280x720 hand-held
    # seeds 11 + 12 (56 pairs) at side 512 (s 2.5) 0.58 vs 0.31 px, 320 (s 4) 1.67 vs 0.61,
    # but seed 13 (20 pairs) 0.28 vs 0.33 and 0.55 vs 0.82; 960x540 seeds 0, 1 (48 pairs) at
    # 384 0.33-0.36 vs 0.55-0.65, at 240 1.09-1.15 vs 1.78-2.75 (3 x max(1, s / 2.5), 3 px to
    # s 2.5: 1.48-1.63); lba-emt on the SYN circle at 1280x720 (150 frames) e_M 2.67 vs 1.96
    # px at 512, 3.63 vs 2.68 at 320. SIFT (sub-pixel keypoints) lost accuracy with any larger
    # threshold.
    # Detection below ~1/3 of the frame's side costs 0.5-1.7 px per pair whatever the
    # threshold (session 51 review).
    ransac_threshold_px: float = 3.0
    ransac_confidence: float = 0.999
    ransac_max_iters: int = 2000
    # fewer inliers: the pair is not registered. Counted per match: SIFT's keypoints at one
    # location with several orientations can pair up twice (~25 % of inliers on a blurred-
    # noise texture; session 44 review), a count the weak-texture tests were measured with;
    # the pair then keeps each correspondence once (unique_correspondences)
    min_inliers: int = 15
    min_inlier_ratio: float = 0.2  # inliers / ratio-test matches
    # Inliers this thinly spread are refused (thin_support): the smaller principal standard
    # deviation of the inlier points in frame m, as a fraction of the frame's shorter side. A
    # homography fitted to a thin band or a small cluster is unconstrained across it and passes
    # degeneracy: on 400x400 frames a 40 px textured band (ORB: 0.009) was 11.5 px off on
    # average over the field of view, synthetic matches on two lines 10 px apart (0.012) and in
    # a 20 px cluster (0.013) put the corners 9-26 px off. The pairs of the simulator's scenes
    # (SYN 400, hand-held 400 circular, weak-texture SYN 200; ORB and SIFT; 2 seeds x 80
    # frames, every pair whose true footprints overlap, ~25 000 registered): median 0.09-0.20,
    # 1st percentile 0.016-0.10; below 0.015 only pairs overlapping by 0.07-0.19 whose
    # homographies were 16-24 px off (median) over the frame. SYN 152 (seed 0): SIFT lba-emt's
    # pairs 0.045 at least, ba-emt's 0.017, neither refuses one (e_M 0.134 / 0.093 px as
    # before); ORB lba-emt 0.023 (none refused), ba-emt 24 of 5295 refused, e_M 0.256 -> 0.255
    # px. An 80 px textured patch (0.022, 9 px off) is not refused: ba-emt registers pairs as
    # thin as it. 0: no check.
    min_inlier_spread: float = 0.015
    # the warped frame's area over the frame's outside (1/4, 4): degenerate (degeneracy)
    max_scale_change: float = 4.0
    num_threads: int = 2  # pairs matched in parallel (OpenCV releases the GIL)
    # Binary descriptors (ORB): "exact" Hamming nearest neighbours in the C++ core, or "lsh",
    # FLANN's approximate LSH index (the matcher before). On this 2-core Xeon per 1000 x 1000
    # pair 2.4 ms vs 5.1 ms (lba-emt end to end 25 vs 20 frames/s, bench/bench_sequential.py).
    # LSH's misses act as a stricter filter: lba-emt's e_M on SYN with ORB was 0.25 px with it,
    # 0.33 px exact (mean over 4 seeds x 600 frames; it varies 0.2-0.45 px between seeds).
    binary_matcher: str = "exact"
    # Guided matching (ORB with the exact matcher; SIFT if guided_sift): when a caller predicts a
    # pair's homography (the sequential mosaicker chains the new frame's registration to the
    # previous frame with the earlier pairs and the window's estimates), only keypoints within
    # this radius of their predicted position are compared; a pair the guided search cannot
    # register is matched again exhaustively. 0: always exhaustive.
    guided_radius_px: float = 20.0
    # The guided search's ratio test sees only the neighbours of the prediction, fewer
    # distractors than the whole frame: a stricter ratio keeps it as selective. Measured on SYN
    # ORB pairs (1 and 3 frames apart, 400x400): exhaustive 0.8 -> 395 inliers per pair, median
    # residual to the true homography 0.80 px; guided 0.8 -> 411, 0.82 px; guided 0.7 -> 389,
    # 0.80 px.
    guided_ratio: float = 0.7
    # SIFT pairs guided too (off by default). Faster (lba-emt, SYN 400x400, this 2-core Xeon,
    # 300 frames, 2 runs: matching 9.9 -> 7.0 ms per frame, 24.2 -> 25.4 frames/s end to end;
    # one 1000 x 1000 pair 20.8 -> 0.6 ms, SIFT's detection dominates) but not more accurate:
    # SIFT's keypoints are sparse (~100 per SYN frame), so few neighbours share a radius and the
    # local ratio test is weak: at ORB's 0.7 it admits matches 1-3 px off that RANSAC's 3 px
    # keeps (Fig. 9's 17 frames: e_M 0.055 -> 0.095 px). At 0.5, lba-emt e_M SYN 4 seeds x 300
    # frames 0.082 px vs 0.086 exhaustive, hand-held 2 x 300 frames 0.151 vs 0.148: within the
    # run-to-run spread of these figures, so the default stays the exhaustive search, whose
    # figures the paper's experiments were measured with.
    guided_sift: bool = False
    guided_sift_ratio: float = 0.5

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """ValueError naming a bad field (min_inliers below 4 failed in OpenCV's
        findHomography on the first pair with that few matches, mid-stream; review)."""
        def number(name: str, ok, expected: str) -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating) \
                    or not np.isfinite(v) or not ok(v):
                raise ValueError(f"{name}: expected {expected}, got {v!r}")

        def integer(name: str, low: int, high: int | None = None) -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < low \
                    or (high is not None and v > high):
                expected = f">= {low}" if high is None else f"in {low}..{high} (OpenCV's int)"
                raise ValueError(f"{name}: expected an integer {expected}, got {v!r}")

        for name in ("ratio", "guided_ratio", "guided_sift_ratio"):
            number(name, lambda v: 0 < v <= 1, "a value in (0, 1]")
        number("ransac_threshold_px", lambda v: v > 0, "pixels > 0")
        number("ransac_confidence", lambda v: 0 < v < 1, "a value in (0, 1)")
        number("min_inlier_ratio", lambda v: 0 <= v <= 1, "a value in [0, 1]")
        number("min_inlier_spread", lambda v: 0 <= v < 0.5,
               "a fraction in [0, 0.5) of the frame's shorter side (0: no check)")
        number("max_scale_change", lambda v: v > 1, "a factor > 1 (1 refuses every pair)")
        number("guided_radius_px", lambda v: v >= 0, "pixels >= 0 (0: no guided search)")
        integer("ransac_max_iters", 1, C_INT_MAX)  # findHomography's maxIters is a C int
        integer("min_inliers", 4)  # a homography needs 4 correspondences
        integer("num_threads", 1)
        if not isinstance(self.guided_sift, bool | np.bool_):  # ('no' is truthy: guided; review)
            raise ValueError(f"guided_sift: expected True or False, got {self.guided_sift!r}")
        if self.binary_matcher not in BINARY_MATCHERS:
            raise ValueError(f"binary_matcher: expected one of {BINARY_MATCHERS}, got "
                             f"{self.binary_matcher!r}")


@dataclass
class PairMatch:
    """Result of registering frame m into frame l."""

    frame_l: int
    frame_m: int
    status: str  # "ok" or the reason it failed
    H_lm: np.ndarray | None = None  # (3, 3) frame m pixels -> frame l pixels, H[2,2] = 1
    points_l: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # inliers (N, 2)
    points_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    n_matches: int = 0
    guided: bool = False  # matched by the guided search (a predicted homography), not exhaustive

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def n_inliers(self) -> int:
        return len(self.points_l)


_LSH_INDEX = {"algorithm": 6, "table_number": 6, "key_size": 12, "multi_probe_level": 1}
BINARY_MATCHERS = ("exact", "lsh")


def _ratio_matches(f_m: Features, f_l: Features, ratio: float,
                   binary_matcher: str = "exact") -> tuple[np.ndarray, np.ndarray]:
    """Points of frame m and of frame l of the ratio-test matches, one-to-one (the nearest query
    per target keypoint)."""
    if f_m.binary and binary_matcher == "exact":
        # ORB: exact Hamming nearest neighbours in the C++ core (registration/descriptor_match.h:
        # the OpenCV wheels count bits by table look-up; on the benchmark's 2-core Xeon 1000 x
        # 1000 descriptors took 7.9 ms with cv2.BFMatcher, 5.1 ms with FLANN's approximate LSH
        # index, 2.4 ms there, the same matches as BFMatcher).
        query, train, _ = _core.match_hamming(f_m.descriptors, f_l.descriptors, ratio)
        return f_m.points[query].reshape(-1, 2), f_l.points[train].reshape(-1, 2)
    if f_m.binary:
        # LSH draws random hash tables from OpenCV's thread-local RNG: seeded, so that a pair
        # always gets the same matches (reproducible runs, serial == threaded matching).
        cv2.setRNGSeed(0)
        matcher = cv2.FlannBasedMatcher(_LSH_INDEX, {"checks": 32})
    else:
        matcher = cv2.BFMatcher(cv2.NORM_L2)
    knn = matcher.knnMatch(f_m.descriptors, f_l.descriptors, k=2)
    good = [p[0] for p in knn if len(p) == 2 and p[0].distance < ratio * p[1].distance]
    # one-to-one: keep the best match per target keypoint
    best: dict[int, cv2.DMatch] = {}
    for m in good:
        if m.trainIdx not in best or m.distance < best[m.trainIdx].distance:
            best[m.trainIdx] = m
    chosen = list(best.values())
    pm = f_m.points[[m.queryIdx for m in chosen]].reshape(-1, 2)
    pl = f_l.points[[m.trainIdx for m in chosen]].reshape(-1, 2)
    return pm, pl


def degeneracy(H: np.ndarray, width: int, height: int, max_scale_change: float) -> str | None:
    """Why H is not a plausible frame-to-frame homography, or None if it is: the frame's corners
    must map in front of the camera to a convex quadrilateral whose area is that of the frame
    times a scale within (1 / max_scale_change, max_scale_change), positive (not mirrored)."""
    if not np.isfinite(H).all() or abs(H[2, 2]) < 1e-12:
        return "degenerate homography (non-finite)"
    A = H / H[2, 2]
    corners = np.array([[0, 0], [width, 0], [width, height], [0, height]], np.float64)
    hom = np.hstack([corners, np.ones((4, 1))]) @ A.T
    if (hom[:, 2] <= 0).any():
        return "degenerate homography (image corners behind the camera)"
    # The frame's area scale: the warped frame's signed (shoelace) area over the frame's. Not
    # det(A[:2, :2]), the scale at pixel (0, 0) alone: with perspective terms it told a camera
    # turned 30 deg one way (frame area x 2.1) from the same turn the other way (det 0.37 vs
    # 4.2: one rejected), and passed a zoom to 0.25 of the area (det 0.69; review).
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        quad = hom[:, :2] / hom[:, 2:]
        x, y = quad[:, 0], quad[:, 1]
        scale = 0.5 * float(x @ np.roll(y, -1) - np.roll(x, -1) @ y) / (width * height)
    if scale < 0:
        return (f"degenerate homography (mirrored: the warped frame's signed area is {scale:.3g}"
                " x the frame's)")
    if not 1.0 / max_scale_change < scale < max_scale_change:  # (nan too)
        s = max_scale_change
        return (f"degenerate homography (area scale {scale:.3g}: the warped frame's area over "
                f"the frame's, outside (1/{s:g}, {s:g}) for max_scale_change {s:g})")
    with np.errstate(over="ignore"):
        quad32 = quad.astype(np.float32)
    if not np.isfinite(quad32).all() or not cv2.isContourConvex(quad32):
        return "degenerate homography (warped frame not convex)"
    return None


def guided_search(features: Features, options: MatchOptions) -> bool:
    """Whether match_pair searches these features guided when it is given a prediction: a
    guided radius, and binary descriptors with the exact matcher or float ones (SIFT) with
    guided_sift."""
    if features.binary:
        return options.guided_radius_px > 0 and options.binary_matcher == "exact"
    return options.guided_radius_px > 0 and options.guided_sift


def _guided_matches(f_m: Features, f_l: Features, H_lm: np.ndarray, radius: float,
                    ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """_ratio_matches among the keypoints of frame l within `radius` px of where H_lm puts
    each keypoint of frame m."""
    h = np.hstack([f_m.points, np.ones((len(f_m), 1))]) @ np.asarray(H_lm, np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        predicted = np.where(h[:, 2:] > 0, h[:, :2] / h[:, 2:], np.nan)  # behind: not matched
    guided = _core.match_hamming_guided if f_m.binary else _core.match_l2_guided
    query, train, _ = guided(f_m.descriptors, predicted, f_l.descriptors, f_l.points, radius,
                             ratio)
    return f_m.points[query].reshape(-1, 2), f_l.points[train].reshape(-1, 2)


def match_pair(f_l: Features, f_m: Features, image_size: tuple[int, int],
               options: MatchOptions | None = None,
               predicted: np.ndarray | None = None) -> PairMatch:
    """Registers frame m (source) into frame l (target). image_size = (width, height).

    predicted: an estimate of H_lm (3, 3) for the guided search (MatchOptions.guided_radius_px;
    binary descriptors with the exact matcher, float ones with guided_sift; otherwise ignored);
    if that search does not register the pair, it is matched exhaustively."""
    o = options or MatchOptions()
    o.validate()  # (fields set after construction)
    if predicted is not None and guided_search(f_m, o) and np.isfinite(predicted).all():
        out = _register(f_l, f_m, image_size, o, predicted)
        if out.ok:
            return out
    return _register(f_l, f_m, image_size, o, None)


def _register(f_l: Features, f_m: Features, image_size: tuple[int, int], o: MatchOptions,
              predicted: np.ndarray | None) -> PairMatch:
    out = PairMatch(f_l.frame_id, f_m.frame_id, "ok", guided=predicted is not None)
    if len(f_m) < o.min_inliers or len(f_l) < o.min_inliers:
        out.status = f"too few features ({len(f_l)}, {len(f_m)})"  # in the pair's order (l, m)
        return out
    if predicted is None:
        pm, pl = _ratio_matches(f_m, f_l, o.ratio, o.binary_matcher)
    else:
        ratio = o.guided_ratio if f_m.binary else o.guided_sift_ratio
        pm, pl = _guided_matches(f_m, f_l, predicted, o.guided_radius_px, ratio)
    out.n_matches = len(pm)
    if len(pm) < o.min_inliers:
        out.status = f"too few matches ({len(pm)} < {o.min_inliers})"
        return out
    H, inl = cv2.findHomography(pm, pl, cv2.RANSAC, o.ransac_threshold_px,
                                maxIters=o.ransac_max_iters, confidence=o.ransac_confidence)
    if H is None:
        out.status = "RANSAC found no homography"
        return out
    inl = inl.ravel().astype(bool)
    if inl.sum() >= 4:
        # DLT on all inliers followed by Levenberg-Marquardt refinement (method 0 in OpenCV).
        refined, _ = cv2.findHomography(pm[inl], pl[inl], 0)
        if refined is not None:
            H = refined
    n_in = int(inl.sum())
    if n_in < o.min_inliers or n_in < o.min_inlier_ratio * len(pm):
        out.status = f"too few inliers ({n_in} of {len(pm)} matches)"
        return out
    reason = degeneracy(H, *image_size, o.max_scale_change)
    if reason:
        out.status = reason
        return out
    points_l, points_m = unique_correspondences(pl[inl], pm[inl])
    reason = thin_support(points_m, image_size, o.min_inlier_spread)
    if reason:
        out.status = reason
        return out
    out.H_lm = H / H[2, 2]
    out.points_l, out.points_m = points_l, points_m
    return out


def inlier_spread(points: np.ndarray) -> float:
    """The smaller principal standard deviation of (N, 2) points, pixels (0 for fewer than 2)."""
    if len(points) < 2:
        return 0.0
    return float(np.sqrt(max(np.linalg.eigvalsh(np.cov(np.asarray(points, np.float64).T))[0],
                             0.0)))


def thin_support(points_m: np.ndarray, image_size: tuple[int, int],
                 min_spread: float) -> str | None:
    """Why a homography fitted to these inliers (frame m) is not constrained over the frame,
    or None: their smaller principal standard deviation below min_spread (MatchOptions.
    min_inlier_spread) times the frame's shorter side."""
    if min_spread <= 0:
        return None
    spread, limit = inlier_spread(points_m), min_spread * min(image_size)
    if spread >= limit:
        return None
    return (f"inliers too thinly spread ({len(points_m)} inliers span {spread:.1f} px across "
            f"(smaller principal standard deviation), under min_inlier_spread "
            f"{min_spread:g} x the frame's shorter side = {limit:.1f} px: a thin band or small "
            f"cluster leaves the homography unconstrained over the frame)")


def unique_correspondences(points_l: np.ndarray, points_m: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Each correspondence once, in their order. SIFT gives a location one keypoint per dominant
    orientation, and two at one location can match two at the other frame's: one observation
    twice, which the bundle adjustment would weigh double (Eq. 13 assumes independent
    keypoints). Measured on SYN 400x400 (SIFT, 40 frames, pairs 1-3 frames apart): 16.4 % of
    the inliers were such copies. The pair's acceptance counts per match, before this
    (MatchOptions.min_inliers)."""
    rows = np.hstack([points_l, points_m])
    _, first = np.unique(rows, axis=0, return_index=True)
    if len(first) == len(rows):
        return points_l, points_m
    keep = np.sort(first)
    return points_l[keep], points_m[keep]


def match_pairs(features: Mapping[int, Features], pairs: Iterable[tuple[int, int]],
                image_size: tuple[int, int], options: MatchOptions | None = None,
                progress=None) -> list[PairMatch]:
    """Matches (l, m) pairs, in parallel threads. Returns results in the order of `pairs`."""
    o = options or MatchOptions()
    pairs = list(pairs)
    for l, m in pairs:
        for k in (l, m):
            if k not in features:
                raise ValueError(f"pair ({l}, {m}): no features for frame {k}")

    def one(pair):
        l, m = pair
        return match_pair(features[l], features[m], image_size, o)

    if o.num_threads <= 1:
        results = []
        for p in pairs:
            results.append(one(p))
            if progress:
                progress(1)
        return results
    with ThreadPoolExecutor(o.num_threads) as pool:
        results = []
        for r in pool.map(one, pairs):
            results.append(r)
            if progress:
                progress(1)
    return results
