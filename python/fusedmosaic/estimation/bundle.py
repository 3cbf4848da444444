"""Offline methods of seed 000 on a dataset: BAVis (`ba`), BAVis+EMT (`ba-emt`) and the EMT
baseline (`emt`: tracker poses with an estimated plane, no further visual term, Sec. 4.2.2).

Stages (each timed in the report): features -> pair selection -> matching -> plane
initialisation -> Ceres bundle adjustment (C++ `BundleAdjuster`) -> frame -> reference
homographies G_k = H_0 H_k^-1 from the estimated poses and plane.
"""

from __future__ import annotations

import numbers
import time
from collections import deque
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation, Slerp
from tqdm import tqdm

from fusedmosaic import _core
from fusedmosaic.estimation.consistency import (
    SIGMA_V_AUTO,
    TransferResiduals,
    add_tracker_agreement,
    auto_sigma_v,
    check_emt_sigma,
    check_sigma_v,
    given_sigma_v_report,
    solver_warning,
    starting_sigma_v,
    tracker_agreement,
    visual_agreement,
)
from fusedmosaic.estimation.motion import (
    MOTION_GATE_CHI2,
    RELEASED,
    motion_timing,
    tracker_motion_verdicts,
)
from fusedmosaic.estimation.plane import estimate_plane
from fusedmosaic.estimation.world import (
    plane_from_aligned,
    plane_to_aligned,
    poses_from_aligned,
    poses_to_aligned,
    same_world,
    tracked_world,
)
from fusedmosaic.methods import MethodResult
from fusedmosaic.registration.features import FeatureOptions, extract_features
from fusedmosaic.registration.pair_selection import all_pairs, emt_guided_pairs, window_pairs
from fusedmosaic.registration.pairs import MatchOptions, PairMatch, match_pairs

# BundleOptions.trust_region's values (Ceres' strategies the C++ core offers)
TRUST_REGIONS = ("levenberg_marquardt", "dogleg")


@dataclass
class BundleOptions:
    features: FeatureOptions = field(default_factory=FeatureOptions)
    matching: MatchOptions = field(default_factory=MatchOptions)
    # "all": every pair, the paper's O(N^2) attempts (Sec. 1); "emt-guided": pairs whose
    # footprints predicted from the tracker overlap (O(N k)); "window": temporal neighbours;
    # None: the method's own, "all" for ba / ba-emt (the paper's), "emt-guided" for emt (options
    # given to tune min_overlap made emt match every pair; review)
    pair_selection: str | None = None
    min_overlap: float = 0.3  # EMT-guided: overlap fraction of the smaller footprint
    max_pairs_per_frame: int | None = 6  # EMT-guided: older overlapping frames kept per
    # frame (None: all)
    min_pair_separation: int = 4  # EMT-guided: frames apart between kept older frames
    window: int = 2  # "window" selection, and the seed pairs used to initialise the plane
    max_points_per_pair: int = 100  # inliers kept per pair (paper Table 1: 67-222 on average)
    # px, the keypoints' noise per axis (Sec. 4.2's sigma_v, 1 px there, the default); "auto":
    # measured on the recording by ba-emt (consistency.SIGMA_V_AUTO: solved with 1 px, then
    # again with the transfer residuals' robust std; report.json "visual_sigma"). ba's visual
    # cost alone and emt's tracker alone do not depend on it.
    sigma_v_px: float | str = 1.0
    # Constant-velocity prior std devs (rad x3, mm x3); None = the paper's appendix values
    # (estimation/motion.py estimates them from an independent recording, as Sec. 4.2 did).
    motion_sigma: tuple[float, ...] | None = None
    # EMT prior std devs (rad x3, mm x3, Eq. 19): the tracker's noise; None = the paper's
    # appendix values (1 deg, 1 mm). `calibrate` measures a tracker's (calibration.json).
    emt_sigma: tuple[float, ...] | None = None
    loss: str = "none"  # "none" | "huber" | "cauchy" on the visual term
    loss_scale_px: float = 2.0
    linear_solver: str = "auto"
    # Ceres' iterations per solve; an adjustment Levenberg-Marquardt leaves at this limit is
    # continued with Powell's dogleg for up to as many more (see trust_region).
    max_iterations: int = 100
    # Ceres' trust region strategy: "levenberg_marquardt" or "dogleg". Levenberg-Marquardt (the
    # default, whose figures the benchmarks quote) damps every step by mu diag(J^T J), and
    # crawls along the directions few EMT priors hold (the scale and the plane): ba-emt on 80
    # SYN frames tracked at the last 5 only, or 5 mm from the plane, stopped at 100 iterations
    # short of the minimum (the plane 38.9 mm for 37.4; 5.16 for 4.99), where dogleg reached it
    # in 30 and 8 (review 46). So when it ends at max_iterations (NO_CONVERGENCE) the adjustment
    # is continued from there with dogleg (details["solver"]["continued_from"]); the normal runs
    # converge in 7-21 and are untouched. "dogleg": dogleg alone (on SYN-150 and hand-held-150
    # ba-emt: 4-5 iterations instead of 17-21, the same final cost).
    trust_region: str = "levenberg_marquardt"
    # Motion gate (not in the paper; SequentialOptions.motion_gate_chi2): C_p does not link a
    # frame whose tracker samples over k-2, k-1, k depart from constant velocity by more than
    # this (Mahalanobis^2) unless bad samples explain it (those are then left out: details
    # tracker_glitches; motion.motion_verdict), nor a frame with pairs and a triple missing a
    # sample whose solved block departs that far (details motion_released; inf: off).
    motion_gate_chi2: float = MOTION_GATE_CHI2
    num_threads: int = 2
    seed: int = 0  # inlier subsampling
    # ba-emt computes the plane's relative standard deviation given the costs (details
    # plane_relative_std; a warning above consistency.MAX_PLANE_RELATIVE_STD) over the poses of
    # the frames in a registered pair, the others held (a lower bound), when there are at most
    # this many: a dense Cholesky factorisation in 6 M + 3 (0.1-0.2 s at 150 paired frames,
    # timings "plane_std"; the eigen-decomposition it replaced took 0.8-1.4 s). Beyond, so many
    # frames see the plane that it is observed (0: never computed).
    plane_std_max_frames: int = 150


@dataclass
class FrontEnd:
    features: dict
    matches: list[PairMatch]
    timings: dict[str, float]


def register_frames(dataset, pairs_fn, options: BundleOptions, progress: bool,
                    features: dict | None = None) -> FrontEnd:
    """Features for every frame, then matches of the pairs returned by pairs_fn(features)."""
    cam = dataset.camera
    n = len(dataset.frames)
    timings: dict[str, float] = {}
    if features is None:
        t0 = time.perf_counter()
        # keypoints in undistorted pixels (camera.yaml's lens distortion removed)
        features = extract_features(dataset.frames, range(n), cam.fov_mask(), options.features,
                                    progress, options.num_threads, cam.undistortion())
        timings["features"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pairs = pairs_fn(features)
    with tqdm(total=len(pairs), desc="matching", disable=not progress, leave=False) as bar:
        matches = match_pairs(features, pairs, (cam.width, cam.height), options.matching,
                              bar.update)
    timings["matching"] = time.perf_counter() - t0
    return FrontEnd(features, matches, timings)


def subsample_inliers(match: PairMatch, k: int, rng: np.random.Generator):
    """At most k of a pair's inlier correspondences (points_l, points_m), drawn with rng."""
    if len(match.points_l) <= k:
        return match.points_l, match.points_m
    idx = np.sort(rng.choice(len(match.points_l), k, replace=False))
    return match.points_l[idx], match.points_m[idx]


def _select_pairs_with_emt(dataset, options: BundleOptions, progress: bool):
    """EMT-guided selection: temporal seed pairs -> first plane -> footprints predicted from the
    tracker -> overlapping pairs matched -> plane re-estimated from the wider baselines. The
    footprints are relative to the first tracked frame (their overlaps do not depend on the
    reference; frame 0 without a sample failed the run; review)."""
    cam = dataset.camera
    K = cam.camera_matrix
    n = len(dataset.frames)
    seed = register_frames(dataset, lambda f: window_pairs(n, options.window), options, progress)
    plane = estimate_plane(seed.matches, dataset.cam_from_world, K, source=str(dataset.root))
    predicted = predicted_homographies(dataset.cam_from_world, plane, K)
    selected = emt_guided_pairs(predicted, cam.width, cam.height, min_overlap=options.min_overlap,
                                max_per_frame=options.max_pairs_per_frame,
                                fov_radius=cam.fov_mask_radius, temporal_window=options.window,
                                min_separation=options.min_pair_separation)
    done = {(m.frame_l, m.frame_m): m for m in seed.matches}
    rest = [p for p in selected if p not in done]
    more = register_frames(dataset, lambda f: rest, options, progress, seed.features)
    matches = seed.matches + more.matches
    plane = estimate_plane(matches, dataset.cam_from_world, K, source=str(dataset.root))
    timings = {"features": seed.timings["features"],
               "matching": seed.timings["matching"] + more.timings["matching"]}
    return FrontEnd(seed.features, matches, timings), plane


# What ba's poses and plane are expressed in (report.json "world"): its gauge holds the first
# frame at the origin and |pi| at 1 (bundle_adjuster.h), and no term of its cost has a scale.
BA_WORLD = ("the first frame's camera frame, lengths in units of that camera's distance to the "
            "plane (the visual cost fixes no scale): poses.csv's translations and plane.json's "
            "distances are in this unit, not mm")

# Status of a frame whose pose is known but whose homography through the plane is singular.
UNPLACED_SINGULAR = ("unplaced: its homography through the estimated plane is singular (its "
                     "camera centre on the plane, or nearer it than floating point resolves)")


def predicted_homographies(poses: np.ndarray, plane: np.ndarray, K: np.ndarray,
                           reference: int | None = None) -> np.ndarray:
    """(N, 3, 3) G_k = H_ref H_k^-1 from (N, 6) cam_from_world poses and a plane, normalised
    (G[2, 2] = 1, G_ref = I). NaN rows: frames without a pose (NaN rows of `poses`) and frames
    whose induced homography is singular (_core.frame_to_reference's test: one such frame no
    longer fails the table). The reference is `reference` (a frame with a regular homography;
    ValueError otherwise), by default the first frame that has one: frame 0 normally."""
    return _predicted(poses, plane, K, reference)[0]


def _predicted(poses: np.ndarray, plane: np.ndarray, K: np.ndarray,
               reference: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """predicted_homographies and the (N,) mask of frames with a pose but a singular
    homography."""
    poses = np.asarray(poses, np.float64)
    G = np.full((len(poses), 3, 3), np.nan)
    singular = np.zeros(len(poses), bool)
    valid = np.isfinite(poses).all(axis=1)
    if reference is not None and not valid[reference]:
        raise ValueError(f"frame {reference} has no valid pose: the reference frame cannot be "
                         "placed")
    idx = np.flatnonzero(valid)
    if not len(idx):
        return G, singular
    first = int(np.searchsorted(idx, reference)) if reference is not None else 0
    try:
        G[idx] = _core.frame_to_reference(poses[idx], plane, K, reference=first)
        return G, singular
    except ValueError as error:
        if "induced homography is singular" not in str(error):
            raise
    # frame by frame (a rare path): the singular ones stay NaN
    for k in idx:
        try:
            _core.frame_to_reference(poses[k:k + 1], plane, K, reference=0)
        except ValueError as error:
            if "induced homography is singular" not in str(error):
                raise
            singular[k] = True
    regular = idx[~singular[idx]]
    if reference is not None and singular[reference]:
        raise ValueError(f"frame {reference}, the reference, cannot be placed: "
                         + UNPLACED_SINGULAR.removeprefix("unplaced: "))
    if len(regular):
        ref = int(np.searchsorted(regular, reference)) if reference is not None else 0
        G[regular] = _core.frame_to_reference(poses[regular], plane, K, reference=ref)
    return G, singular


def fill_missing_poses(poses: np.ndarray) -> np.ndarray:
    """Initial values for frames without a tracker sample (NaN rows of the (N, 6) poses, angle-
    axis then translation): between the nearest valid neighbours the rotation by slerp, the
    translation linearly; before the first and after the last valid one, that one's pose.
    (Angle-axis vectors interpolated linearly across a rotation of pi, [3.1, 0, 0] to
    [-3.1, 0, 0], 0.08 rad apart, gave the identity, ~180 deg off.)"""
    out = np.array(poses, np.float64)
    valid = np.isfinite(out).all(axis=1)
    if valid.all():
        return out
    idx = np.flatnonzero(valid)
    if idx.size == 0:
        raise ValueError("fill_missing_poses: no valid pose (every row has a NaN or inf) to "
                         "fill the others from")
    missing = np.flatnonzero(~valid)
    for j in range(3, 6):
        out[missing, j] = np.interp(missing, idx, out[idx, j])
    if idx.size == 1:
        out[missing, :3] = out[idx[0], :3]
    else:
        slerp = Slerp(idx, Rotation.from_rotvec(out[idx, :3]))
        out[missing, :3] = slerp(np.clip(missing, idx[0], idx[-1])).as_rotvec()
    return out


def pose_through_pair(H_lm: np.ndarray, known: np.ndarray, known_is_l: bool,
                      plane: np.ndarray, K: np.ndarray) -> np.ndarray | None:
    """cam_from_world of one frame of a registered pair (H_lm: pixels m -> l) from the other
    frame's pose `known` (frame l's when known_is_l) and the plane pi (world): the plane fixes
    the homography's decomposition. None when the result is not finite or the plane is not in
    front of the camera."""
    Rj = _core.rotation_from_angle_axis(known[:3])
    tj = known[3:]
    Hj = K @ (Rj - np.outer(tj, plane)) @ np.linalg.inv(K)  # virtual camera -> frame j
    try:
        Hk = (np.linalg.inv(H_lm) @ Hj) if known_is_l else (H_lm @ Hj)
    except np.linalg.LinAlgError:  # (a singular homography)
        return None
    M = np.linalg.inv(K) @ Hk @ K  # = s (R_k - t_k pi^T)
    n = plane / np.linalg.norm(plane)
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    Ma, Mb = M @ a, M @ b  # directions in the plane: M v = s R_k v
    s = 0.5 * (np.linalg.norm(Ma) + np.linalg.norm(Mb))
    if not np.isfinite(s) or s <= 0:
        return None
    for sign in (1.0, -1.0):
        A = np.column_stack([a, b, np.cross(a, b)])
        B = np.column_stack([sign * Ma / s, sign * Mb / s,
                             np.cross(sign * Ma / s, sign * Mb / s)])
        U, _, Vt = np.linalg.svd(B @ A.T)
        R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        t = (R @ plane - sign * (M @ plane) / s) / float(plane @ plane)
        pose = np.r_[_core.angle_axis_from_rotation(R), t]
        centre = -R.T @ t
        along = float(plane @ R[2])
        depth = -(plane @ centre + 1.0) / along if along != 0.0 else np.inf
        if np.isfinite(pose).all() and np.isfinite(depth) and depth > 0:
            return pose
    return None


def chain_missing_poses(poses: np.ndarray, pairs, plane: np.ndarray, K: np.ndarray, *,
                        fill: bool = True) -> np.ndarray:
    """Initial values for frames without a tracker sample (NaN rows of `poses`, indexed by
    frame id): through registered pairs (PairMatch, ok) from frames with one, breadth first
    (pose_through_pair with the plane), the rest as fill_missing_poses (fill False: left NaN).
    A start-up whose first 10 of 19 frames had no sample started them all at the first
    sample's pose and stopped at its iteration limit with the tracked frames 15 mm from their
    samples: the next prior-only frame was 1073 px off."""
    out = np.array(poses, np.float64)
    known = np.isfinite(out).all(axis=1)
    if known.all() or not known.any():
        return fill_missing_poses(out) if fill else out
    usable = [m for m in pairs if m.ok]
    grew = True
    while grew:
        grew = False
        for m in usable:
            l_known, m_known = known[m.frame_l], known[m.frame_m]
            if l_known == m_known:
                continue
            j, k = (m.frame_l, m.frame_m) if l_known else (m.frame_m, m.frame_l)
            pose = pose_through_pair(m.H_lm, out[j], bool(l_known), plane, K)
            if pose is not None:
                out[k], known[k] = pose, True
                grew = True
    return fill_missing_poses(out) if fill else out


def _pose_from_homography(G: np.ndarray, K: np.ndarray) -> np.ndarray:
    """cam_from_world of a frame whose frame -> reference homography is G, for the plane
    pi = (0, 0, -1) in the reference camera (virtual camera = frame 0, unit distance).

    H_k ~ K^-1 G^-1 K = R + t e3^T: the first two columns are r1, r2 up to scale."""
    M = np.linalg.inv(K) @ np.linalg.inv(G) @ K
    s = 0.5 * (np.linalg.norm(M[:, 0]) + np.linalg.norm(M[:, 1]))
    M = M / s
    if M[2, 2] < 0:  # the plane point (0, 0, 1) must lie in front of the camera
        M = -M
    B = np.column_stack([M[:, 0], M[:, 1], np.cross(M[:, 0], M[:, 1])])
    U, _, Vt = np.linalg.svd(B)
    R = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    t = M[:, 2] - R[:, 2]
    return np.concatenate([_core.angle_axis_from_rotation(R), t])


def _visual_initialisation(n: int, matches: list[PairMatch], K: np.ndarray) -> np.ndarray:
    """Poses from a breadth-first spanning tree of registered pairs rooted at frame 0 (BAVis).

    Frames not connected to frame 0 by registered pairs get NaN (they cannot be placed)."""
    adjacency: dict[int, list[tuple[int, np.ndarray]]] = {k: [] for k in range(n)}
    for m in matches:
        if m.ok:
            adjacency[m.frame_l].append((m.frame_m, m.H_lm))  # frame_m -> frame_l
            adjacency[m.frame_m].append((m.frame_l, np.linalg.inv(m.H_lm)))
    G = {0: np.eye(3)}
    queue = deque([0])
    while queue:
        k = queue.popleft()
        # prefer temporal neighbours (shortest chains) by visiting in order of |j - k|
        for j, H_kj in sorted(adjacency[k], key=lambda e: abs(e[0] - k)):
            if j not in G:
                G[j] = G[k] @ H_kj
                queue.append(j)
    poses = np.full((n, 6), np.nan)
    for k, g in G.items():
        poses[k] = _pose_from_homography(g / g[2, 2], K)
    poses[0] = 0.0
    return poses


def _adjuster(K, options: BundleOptions, use_emt: bool, plane_std: bool = False):
    costs = _core.BundleAdjusterOptions(
        sigma_v_px=starting_sigma_v(options.sigma_v_px), loss=options.loss,
        loss_scale_px=options.loss_scale_px,
        linear_solver=options.linear_solver, trust_region=options.trust_region,
        max_iterations=options.max_iterations,
        num_threads=options.num_threads, use_emt=use_emt, use_motion_prior=use_emt,
        motion_gate_chi2=options.motion_gate_chi2, plane_std=plane_std,
        plane_std_paired_only=plane_std)
    if options.motion_sigma is not None:
        costs.motion_sigma = np.asarray(options.motion_sigma, np.float64)
    if options.emt_sigma is not None:
        costs.emt_sigma = np.asarray(options.emt_sigma, np.float64)
    return _core.BundleAdjuster(K, costs)


def _continued_with_dogleg(first, summary, frames, pairs):
    """(adjuster, solver dict) of the adjustment `first` left by Levenberg-Marquardt at its
    iteration limit (`summary`, a dict), solved on with Powell's dogleg
    (BundleOptions.trust_region) from where it stopped: the same options, `frames` ((frame,
    sample or None, C_p timing)), `pairs` ((frame_l, frame_m, points_l, points_m)) and the C_p
    blocks its motion gate released. The dict is the continuation's summary with the whole
    adjustment's iterations, initial cost, times and released blocks, and "continued_from": the
    first solve's trust region, termination, iterations and final cost. A continuation Ceres
    fails leaves the first solve's result (its dict, with "continuation_failed")."""
    return _solved_on(first, summary, frames, pairs, "trust_region", "dogleg")


def _rebuilt_adjuster(camera_matrix, costs):
    """A BundleAdjuster for an adjustment solved again (_solved_on): a hook, as _adjuster is,
    for bench/_common.record_bundle_problems."""
    return _core.BundleAdjuster(camera_matrix, costs)


def _solved_on(first, summary: dict, frames, pairs, field: str, value):
    """(adjuster, solver dict): the adjustment `first` (its solve's `summary`, a dict) solved
    again from its poses and plane with its options' `field` set to `value`, with `frames`,
    `pairs` and the C_p blocks its motion gate released (see _continued_with_dogleg).
    field "trust_region" (dogleg) records the first solve as "continued_from"; "sigma_v_px"
    (the measured keypoint noise) as "sigma_v_from", keeping the first's "continued_from" and
    its plane std (at the paper's sigma_v, which MAX_PLANE_RELATIVE_STD is stated for; not
    computed again). A second solve Ceres fails leaves the first's result, with
    "continuation_failed"."""
    options = first.options
    start = getattr(options, field)
    setattr(options, field, value)
    if field == "sigma_v_px":
        options.plane_std = False
    ba = _rebuilt_adjuster(first.camera_matrix, options)
    released = {int(k) for k in summary["motion_released_ids"]}
    for k, z, timing in frames:
        ba.add_frame(k, first.pose(k), z, *(RELEASED if k in released else timing))
    for pair in pairs:
        ba.add_pair(*pair)
    ba.set_plane(first.plane())
    second = ba.solve()
    label = "dogleg" if field == "trust_region" else f"{field} {value:.4g}"
    if second.termination == "FAILURE":  # (the first solve's point stands, and is reported)
        return first, {**summary, "continuation_failed": f"{label}: {second.message}"}
    solver = second.as_dict()
    before = {key: summary[key] for key in ("trust_region", "termination", "message",
                                            "iterations", "final_cost")}
    solver.update(
        iterations=summary["iterations"] + second.iterations,
        initial_cost=summary["initial_cost"],
        solve_time_s=summary["solve_time_s"] + second.solve_time_s,
        plane_std_time_s=summary["plane_std_time_s"] + second.plane_std_time_s,
        motion_released_ids=sorted(released | {int(k) for k in second.motion_released_ids}),
        trust_region=options.trust_region)
    if field == "trust_region":
        solver["continued_from"] = before
    else:
        solver["sigma_v_from"] = before | {field: start}
        solver["plane_relative_std"] = summary["plane_relative_std"]
        if "continued_from" in summary:
            solver["continued_from"] = summary["continued_from"]
    return ba, solver


def _with_measured_sigma_v(ba, solver: dict, frames, pairs, K) -> tuple:
    """sigma_v "auto" (consistency.measured_sigma_v): (adjuster, solver dict, report) of the
    adjustment `ba` solved again with the keypoints' noise its `pairs`' transfer residuals
    show at its estimate. `ba` itself, with the paper's value, where consistency.auto_sigma_v
    measures nothing to solve again with (the first solve did not converge, the images barely
    observe the plane), and when the second solve does not converge (a camera held still: 1 px
    converged in 42 iterations, 0.07 px stopped at 100 and its dogleg continuation at 100
    more)."""
    start = ba.options.sigma_v_px
    sigma, report = auto_sigma_v(
        start, solver["termination"], solver["plane_relative_std"],
        lambda: TransferResiduals.of(pairs, lambda k: np.asarray(ba.pose(k)),
                                     np.asarray(ba.plane()), K), "the adjustment")
    if sigma == start:
        return ba, solver, report
    second, merged = _solved_on(ba, solver, frames, pairs, "sigma_v_px", sigma)
    if second is ba:  # (a failed second solve: the paper's value stands)
        return ba, solver, report | {
            "sigma_v_px": start,
            "note": f"solving again with the measured sigma_v failed "
                    f"({merged['continuation_failed']}); the paper's {start:g} px kept"}
    if merged["termination"] != "CONVERGENCE":
        return ba, solver, report | {
            "sigma_v_px": start,
            "note": f"solved again with the measured sigma_v, the adjustment ended "
                    f"{merged['termination']} ({merged['message']}); the first solve, with the "
                    f"paper's {start:g} px, kept"}
    return second, merged, report


def _status(n: int, placed: np.ndarray, matches: list[PairMatch], why: str) -> list[str]:
    seen = np.zeros(n, bool)
    for m in matches:
        if m.ok:
            seen[m.frame_l] = seen[m.frame_m] = True
    return ["placed" if p and s else "prior-only" if p else f"unplaced: {why}"
            for p, s in zip(placed, seen, strict=True)]


def unanchored_frames(n: int, matches: list[PairMatch], tracked: np.ndarray) -> np.ndarray:
    """(n,) True for the frames not linked by registered pairs (through any chain of them) to
    a frame with a tracker sample (`tracked`, (n,) bool): the EMT does not anchor them. Frame
    ids index the arrays (ba-emt; lba-emt's start-up)."""
    parent = list(range(n))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for m in matches:
        parent[root(m.frame_l)] = root(m.frame_m)
    anchored = {root(k) for k in np.flatnonzero(tracked)}
    return np.array([root(k) not in anchored for k in range(n)], dtype=bool)


def _pair_details(front: FrontEnd) -> dict:
    ok = [m for m in front.matches if m.ok]
    return {"pairs": {"attempted": len(front.matches), "registered": len(ok),
                      "mean_correspondences": float(np.mean([m.n_inliers for m in ok]))
                      if ok else 0.0}}


def _count(value, low: int) -> bool:
    return (isinstance(value, numbers.Integral) and not isinstance(value, bool | np.bool_)
            and value >= low)


def check_bundle_options(options, *, use_emt: bool, camera_matrix: np.ndarray,
                         default_selection: str = "all") -> BundleOptions:
    """`options` (pair_selection None resolved to the method's `default_selection`) when every
    field of the BundleOptions is usable by ba / ba-emt (use_emt) / emt; ValueError
    "BundleOptions.<field> ..." otherwise, before minutes of feature extraction and matching
    (unchecked, a bad count failed after them with a numpy message, or a NaN min_overlap
    silently kept only the seed pairs; review)."""
    if not isinstance(options, BundleOptions):
        raise ValueError(f"options must be a BundleOptions, got {type(options).__name__}")
    o = options if options.pair_selection is not None else replace(
        options, pair_selection=default_selection)
    for name, kind in (("features", FeatureOptions), ("matching", MatchOptions)):
        value = getattr(o, name)
        if not isinstance(value, kind):
            raise ValueError(f"BundleOptions.{name} must be a {kind.__name__}, got "
                             f"{type(value).__name__}")
        try:
            value.validate()
        except ValueError as error:
            raise ValueError(f"BundleOptions.{name}.{error}") from None
    pairings = ("all", "window") + (("emt-guided",) if use_emt else ())
    if o.pair_selection not in pairings:
        raise ValueError(f"BundleOptions.pair_selection must be 'all', 'window' or "
                         f"'emt-guided', got {o.pair_selection!r} (emt-guided needs the EMT)")
    for name, low in (("window", 1), ("max_points_per_pair", 1), ("min_pair_separation", 0),
                      ("plane_std_max_frames", 0), ("seed", 0)):
        value = getattr(o, name)
        if not _count(value, low):
            raise ValueError(f"BundleOptions.{name} must be an integer >= {low}, got {value!r}")
    if not (o.max_pairs_per_frame is None or _count(o.max_pairs_per_frame, 0)):
        raise ValueError("BundleOptions.max_pairs_per_frame must be an integer >= 0 (older "
                         f"frames paired per frame) or None (no limit), got "
                         f"{o.max_pairs_per_frame!r}")
    if not (isinstance(o.min_overlap, numbers.Real) and not isinstance(o.min_overlap, bool)
            and 0.0 < o.min_overlap <= 1.0):
        raise ValueError("BundleOptions.min_overlap must be a fraction in (0, 1] (of the smaller "
                         f"footprint), got {o.min_overlap!r}")
    if not (isinstance(o.motion_gate_chi2, numbers.Real) and o.motion_gate_chi2 > 0):
        raise ValueError("BundleOptions.motion_gate_chi2 must be > 0 (inf: no gate), got "
                         f"{o.motion_gate_chi2!r}")
    if o.emt_sigma is not None:
        check_emt_sigma(o.emt_sigma, "BundleOptions.emt_sigma")
    check_sigma_v(o.sigma_v_px, "BundleOptions.sigma_v_px")
    if not (isinstance(o.trust_region, str) and o.trust_region in TRUST_REGIONS):
        raise ValueError(f"BundleOptions.trust_region must be one of {', '.join(TRUST_REGIONS)}, "
                         f"got {o.trust_region!r}")
    try:  # the solver's fields (sigma_v_px, motion_sigma, loss, ..., num_threads)
        _adjuster(camera_matrix, o, use_emt)
    except (ValueError, TypeError) as error:
        raise ValueError(f"BundleOptions.{error}") from None
    return o


def _frame_name(dataset, k: int) -> str:
    ids = getattr(dataset, "frame_ids", None)
    return f"frame {ids[k]}" if ids is not None and len(ids) > k else f"frame {k}"


def tracker_poses(dataset, method: str) -> tuple[np.ndarray, np.ndarray]:
    """The dataset's (N, 6) tracker cam_from_world poses at its N frames, NaN where not valid,
    and their (N,) validity. ValueError naming the dataset (and the frame) when it has no
    tracking.csv (Dataset.require_tracking) or its poses do not fit its frames."""
    dataset.require_tracking(method)
    n = len(dataset.frames)
    where = f"{dataset.root}: method {method!r}"
    if dataset.cam_from_world is None or dataset.pose_valid is None:
        raise ValueError(f"{where} needs the tracker's camera poses at the frames "
                         "(cam_from_world, pose_valid), got None")
    try:
        poses = np.asarray(dataset.cam_from_world, np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: cam_from_world must be an ({n}, 6) array of numbers, got "
                         f"{type(dataset.cam_from_world).__name__}") from None
    valid = np.asarray(dataset.pose_valid)
    if poses.shape != (n, 6):
        raise ValueError(f"{where}: cam_from_world must hold one pose (angle-axis, translation) "
                         f"per frame, shape ({n}, 6), got {poses.shape}")
    if valid.shape != (n,) or not (valid.dtype == bool or (
            np.issubdtype(valid.dtype, np.integer) and np.isin(valid, (0, 1)).all())):
        raise ValueError(f"{where}: pose_valid must be ({n},) booleans, one per frame, got shape "
                         f"{valid.shape} of {valid.dtype}")
    valid = valid.astype(bool)
    bad = np.flatnonzero(valid & ~np.isfinite(poses).all(axis=1))
    if bad.size:
        raise ValueError(f"{where}: the tracker pose of {_frame_name(dataset, int(bad[0]))} (row "
                         f"{bad[0]} of cam_from_world) is marked valid but holds NaN or infinite "
                         f"values ({bad.size} such frames)")
    return np.where(valid[:, None], poses, np.nan), valid


def _front_end(dataset, o: BundleOptions, progress: bool, method: str):
    """(FrontEnd, plane or None) of the pair selection o.pair_selection: the EMT-guided one also
    gives the plane it estimated (in the dataset's world)."""
    n = len(dataset.frames)
    if n < 2:
        raise ValueError(f"{dataset.root}: method {method!r} registers pairs of frames, and the "
                         f"dataset has {n} frame{'s' if n != 1 else ''}")
    if o.pair_selection == "emt-guided":
        return _select_pairs_with_emt(dataset, o, progress)
    select = {"all": lambda f: all_pairs(n), "window": lambda f: window_pairs(n, o.window)}
    return register_frames(dataset, select[o.pair_selection], o, progress), None


def _world_for_plane(poses: np.ndarray, valid: np.ndarray, world, plane, matches, K, root):
    """(world, poses in it, plane in it) after a first plane `plane` (in `world`): the world is
    recentred on a tracked camera when its origin lies near that plane (world.tracked_world;
    origin_near_plane), then the plane re-estimated there from the same pairs. `poses`: the
    tracker's, in its own world."""
    recentred = tracked_world(poses, valid, plane=plane_from_aligned(plane, world))
    if same_world(recentred, world):
        return world, poses_to_aligned(poses, world), plane
    aligned = poses_to_aligned(poses, recentred)
    return recentred, aligned, estimate_plane(matches, aligned, K, source=str(root))


def run_bundle(dataset, *, progress: bool = True, options: BundleOptions | None = None,
               use_emt: bool = True) -> MethodResult:
    """BAVis+EMT (use_emt=True, Eq. 17-20) or BAVis (visual cost only). With the EMT, the
    adjustment runs in a world aligned on a tracked camera when the tracker's frame is near a
    rotation of pi, its origin far from the cameras or near the plane (estimation/world.py);
    poses and plane are returned in the tracker's world."""
    method = "ba-emt" if use_emt else "ba"
    K = dataset.camera.require_camera_matrix(method)
    o = check_bundle_options(BundleOptions() if options is None else options, use_emt=use_emt,
                             camera_matrix=K)
    n = len(dataset.frames)
    world = None
    if use_emt:
        emt, valid = tracker_poses(dataset, method)
        world = tracked_world(emt, valid)
        dataset = replace(dataset, cam_from_world=poses_to_aligned(emt, world), pose_valid=valid)
    rng = np.random.default_rng(o.seed)
    front, plane = _front_end(dataset, o, progress, method)
    ok = [m for m in front.matches if m.ok]
    if not ok:
        raise ValueError(f"{dataset.root}: no pair of frames could be registered "
                         f"({len(front.matches)} attempted); nothing to adjust")
    timings = dict(front.timings)

    t0 = time.perf_counter()
    if use_emt:
        if plane is None:
            plane = estimate_plane(ok, dataset.cam_from_world, K, source=str(dataset.root))
        world, aligned, plane = _world_for_plane(emt, valid, world, plane, ok, K, dataset.root)
        dataset = replace(dataset, cam_from_world=aligned)
        init = chain_missing_poses(dataset.cam_from_world, ok, plane, K)
        frames = range(n)
    else:
        init = _visual_initialisation(n, ok, K)
        plane = np.array([0.0, 0.0, -1.0])
        frames = [k for k in range(n) if np.isfinite(init[k]).all()]
        if len(frames) < 2:
            raise ValueError(
                f"{dataset.root}: frame 0, the reference of every output homography, has no "
                f"registered pair ({len(ok)} pairs registered between other frames): the visual "
                "cost alone cannot place any frame relative to it; ba-emt and lba-emt place "
                "untextured frames from the tracker")
    timings["initialisation"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    paired = {k for m in ok for k in (m.frame_l, m.frame_m)}
    ba = _adjuster(K, o, use_emt, use_emt and len(paired) <= o.plane_std_max_frames)
    times = np.asarray(dataset.timestamps, np.float64)
    nominal = float(np.median(np.diff(times))) if n > 1 else None  # Sigma_p's frame spacing
    # C_p over frames k-2, k-1, k follows their timestamps (dropped frames: motion_timing),
    # released where the tracker says the motion left constant velocity (tracker_motion_verdicts)
    timing = [motion_timing(*times[k - 2:k + 1], nominal) if k >= 2 else (1.0, 1.0)
              for k in range(n)]
    # (and tracker samples that explained a departure, motion_verdict, are left out: a +20 deg
    # glitch on a black frame pulled it and its neighbours against C_p)
    breaks, glitches = [], []
    if use_emt:
        breaks, glitches = tracker_motion_verdicts(
            dataset.cam_from_world, times, ba.options.motion_sigma, ba.options.emt_sigma,
            o.motion_gate_chi2, nominal)
        for k in breaks:
            timing[k] = RELEASED
    added = []  # (frame, tracker sample or None, C_p timing): for a continuation
    for k in frames:
        z = (dataset.cam_from_world[k] if use_emt and dataset.pose_valid[k]
             and k not in glitches else None)
        ba.add_frame(k, init[k], z, *timing[k])
        added.append((k, z, timing[k]))
    in_problem = set(frames)
    pairs = []
    for m in ok:
        if m.frame_l in in_problem and m.frame_m in in_problem:
            pl, pm = subsample_inliers(m, o.max_points_per_pair, rng)
            ba.add_pair(m.frame_l, m.frame_m, pl, pm)
            pairs.append((m.frame_l, m.frame_m, pl, pm))
    ba.set_plane(plane)
    summary = ba.solve()
    solver = {**summary.as_dict(), "trust_region": o.trust_region}
    if (summary.termination == "NO_CONVERGENCE" and o.trust_region == "levenberg_marquardt"
            and o.linear_solver != "iterative_schur"):  # (which dogleg cannot use)
        ba, solver = _continued_with_dogleg(ba, solver, added, pairs)
    visual_sigma = None
    if use_emt and o.sigma_v_px == SIGMA_V_AUTO and solver["termination"] != "FAILURE":
        ba, solver, visual_sigma = _with_measured_sigma_v(ba, solver, added, pairs, K)
    timings["optimisation"] = solver["solve_time_s"]
    # (pi's covariance for the warning, booked apart: 1.2 s of "problem_setup" at 150 frames
    # before its Cholesky path; review)
    timings["plane_std"] = solver["plane_std_time_s"]
    timings["problem_setup"] = (time.perf_counter() - t0 - solver["solve_time_s"]
                                - solver["plane_std_time_s"])
    ids, est = ba.poses()
    poses = np.full((n, 6), np.nan)
    poses[ids] = est
    plane = ba.plane()
    G, singular = _predicted(poses, plane, K)
    placed = np.isfinite(G).all(axis=(1, 2))
    details = _pair_details(front)
    details["solver"] = solver
    # (with every camera free, pi's std is the tracker's share of the scale and position: SYN
    # 60 frames 0.0095 with sigma_v 1 px and with 0.09; the window's steps scale with sigma_v)
    std = solver["plane_relative_std"]
    details["plane_relative_std"] = None if np.isnan(std) else float(std)
    if not use_emt:  # (plane.json's "distance_mm" read 1.0 for a plane 30 mm away; review 46)
        details["world"] = BA_WORLD
    if use_emt:  # C_p released by the motion gate: tracker samples, or the solve
        details["motion_released"] = sorted({*breaks, *solver["motion_released_ids"]})
        details["tracker_glitches"] = [int(k) for k in glitches]
    details["warnings"] = []
    if solver["termination"] != "FAILURE":  # (the keypoints' noise, for --visual-sigma)
        residuals = TransferResiduals.of(pairs, poses.__getitem__, plane, K)
        agreement = visual_agreement(residuals, ba.options.sigma_v_px, source=str(dataset.root),
                                     knob="--visual-sigma" if use_emt else None)
        details["warnings"] += agreement.pop("warnings")
        details["visual_agreement"] = agreement
    if use_emt:  # the visual cost's sigma_v: given, or measured ("auto")
        details["visual_sigma"] = visual_sigma or given_sigma_v_report(o.sigma_v_px)
    if use_emt and solver["termination"] == "FAILURE":
        # the poses are where the failed solve left them (the tracker's, at first): their
        # agreement, 0.0 on every axis, read as perfect (e_M 117 px; helper fuzz 32)
        details["tracker_agreement"] = {"skipped": "the adjustment failed"}
    elif use_emt:  # (in the aligned world, where the EMT prior weighed the poses)
        add_tracker_agreement(details, poses, dataset, plane, o.emt_sigma, o.motion_sigma)
    # (after the tracker's agreement, which tells whether the tracker can be the cause)
    warning = solver_warning(
        solver, o.max_iterations, knob="BundleOptions.max_iterations in the Python API",
        uses_tracker=use_emt, noise_ratio=details.get("tracker_agreement", {}).get("noise_ratio"))
    details["warnings"] += [warning] if warning else []
    status = _status(n, placed, ok, "not connected to frame 0 by registered pairs")
    for k in np.flatnonzero(singular):
        status[k] = UNPLACED_SINGULAR
    if use_emt:  # as lba-emt's: placed by C_p alone, however far from their anchors
        tracked = np.asarray(dataset.pose_valid, bool).copy()
        tracked[list(glitches)] = False
        for k in np.flatnonzero(placed & unanchored_frames(n, ok, tracked)):
            status[k] = "dead-reckoned"
    return MethodResult(G, status, poses=poses_from_aligned(poses, world),
                        plane=plane_from_aligned(plane, world), timings=timings,
                        parameters=asdict(o), details=details)


def run_ba(dataset, *, progress: bool = True, options: BundleOptions | None = None):
    """BAVis: bundle adjustment with the visual cost only (Sec. 4.1)."""
    return run_bundle(dataset, progress=progress, options=options, use_emt=False)


def run_ba_emt(dataset, *, progress: bool = True, options: BundleOptions | None = None):
    """BAVis+EMT: visual + EMT + constant-velocity costs, initialised from the tracker."""
    return run_bundle(dataset, progress=progress, options=options, use_emt=True)


def run_emt(dataset, *, progress: bool = True, options: BundleOptions | None = None,
            plane: np.ndarray | None = None) -> MethodResult:
    """EMT baseline: tracker poses + a plane (estimated unless given, in the tracker's world)
    from the pairs of options.pair_selection (None, the default: EMT-guided). The plane is
    estimated in the world ba-emt adjusts in (world.tracked_world: aligned on a tracked camera
    when the tracker's origin is far, or near the plane): with the origin 800 mm away its fit in
    the tracker's world put e_M at 81 px, 35 near it. The homographies map to frame 0's pixel grid,
    or, when frame 0 has no tracker sample, to the first placed frame's (its status says why;
    runner.flag_reference_frame names the reference)."""
    K = dataset.camera.require_camera_matrix("emt")
    o = check_bundle_options(BundleOptions() if options is None else options, use_emt=True,
                             camera_matrix=K, default_selection="emt-guided")
    emt, valid = tracker_poses(dataset, "emt")
    if plane is not None:
        plane = np.asarray(plane, np.float64)
        if plane.shape != (3,) or not np.isfinite(plane).all() or not np.any(plane):
            raise ValueError(f"plane must be pi = n / d, 3 finite numbers not all 0, got {plane}")
    world = tracked_world(emt, valid, plane=plane)
    aligned = poses_to_aligned(emt, world)
    timings: dict[str, float] = {}
    details: dict = {}
    if plane is None:
        t0 = time.perf_counter()
        work = replace(dataset, cam_from_world=aligned, pose_valid=valid)
        front, plane = _front_end(work, o, progress, "emt")
        if plane is None:
            plane = estimate_plane(front.matches, aligned, K, source=str(dataset.root))
        world, aligned, plane = _world_for_plane(emt, valid, world, plane, front.matches, K,
                                                 dataset.root)
        timings.update(front.timings)
        timings["initialisation"] = time.perf_counter() - t0 - sum(front.timings.values())
        details = _pair_details(front)
    else:
        plane = plane_to_aligned(plane, world)
    G, singular = _predicted(aligned, plane, K)
    placed = np.isfinite(G).all(axis=(1, 2))
    status = ["placed" if p else UNPLACED_SINGULAR if s else "unplaced: no tracker sample"
              for p, s in zip(placed, singular, strict=True)]
    # the tracker's own poses: only the plane's distance can be implausible (a unit mix-up)
    agreement = tracker_agreement(aligned, aligned, valid, plane, o.emt_sigma,
                                  source=str(dataset.root / "tracking.csv"))
    details["warnings"] = agreement.pop("warnings")
    return MethodResult(G, status, poses=np.array(dataset.cam_from_world, np.float64),
                        plane=plane_from_aligned(plane, world), timings=timings,
                        parameters=asdict(o), details=details, images_seen=False)
