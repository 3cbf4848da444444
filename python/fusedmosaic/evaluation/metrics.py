"""Mosaic accuracy against ground truth.

* Seed 000, Eq. 28: e_j = mean over a 100 x 100 grid of image points rho_i of
  ||w(H_j^-1, rho_i) - w(H_GT^-1, rho_i)||, where w projects frame points into the mosaic. Our
  output homographies G_j are already frame -> reference, i.e. the paper's H_j^-1, so
  e_j = mean_i ||G_est,j(rho_i) - G_true,j(rho_i)|| in reference pixels. Eq. 29: e_M = mean e_j.
* Drift ratio: mean e_j over the last quarter of frames / mean over the first quarter.
* Seed 004, Sec. IV-B: distances in micrometres between estimated and true image positions at n
  evenly spaced frames (13 circle, 25 spiral) and at all frames; mean, max, std, median, and a
  Wilcoxon signed-rank test between two methods' paired errors (the paper writes "Wilcoxon
  U-test"; the errors are paired by frame, so the signed-rank form is the right one).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy import stats

from fusedmosaic.io._table import require_file

GRID_SIZE = 100  # points per axis, N_g = 100^2 (seed 000, Sec. 4.1)


def grid_points(width: int, height: int, n: int = GRID_SIZE) -> np.ndarray:
    """(n*n, 2) pixel grid spanning the image domain [0, w-1] x [0, h-1]."""
    xs, ys = np.meshgrid(np.linspace(0, width - 1, n), np.linspace(0, height - 1, n))
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def _apply(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Applies each (3,3) of H (N,3,3) to pts (P,2): returns (N,P,2)."""
    # batched matmul (BLAS), (N, 3, P): ~3x faster than the equivalent einsum at 100^2 points
    hom = np.matmul(H, np.hstack([pts, np.ones((len(pts), 1))]).T)
    with np.errstate(divide="ignore", invalid="ignore"):  # degenerate rows: inf/NaN, unplaced
        return np.moveaxis(hom[:, :2] / hom[:, 2:], 1, 2)


def _check_stack(H: np.ndarray, name: str) -> np.ndarray:
    H = np.asarray(H, dtype=np.float64)
    if H.ndim != 3 or H.shape[1:] != (3, 3):
        raise ValueError(f"{name}: expected homographies of shape (N, 3, 3), got {H.shape}")
    return H


def frame_errors(G_est: np.ndarray, G_true: np.ndarray, width: int, height: int) -> np.ndarray:
    """e_j (Eq. 28) per frame, NaN where either homography is missing (unplaced, or no truth);
    inf where both exist but the estimate sends grid points to infinity or overflows (a frame
    placed unusably counts against e_M instead of being left out)."""
    G_est = _check_stack(G_est, "G_est")
    G_true = _check_stack(G_true, "G_true")
    if G_est.shape != G_true.shape:
        raise ValueError(
            f"G_est and G_true differ in frame count: {len(G_est)} vs {len(G_true)}"
        )
    pts = grid_points(width, height)
    errors = np.full(len(G_est), np.nan)
    ok = np.isfinite(G_est).all(axis=(1, 2)) & np.isfinite(G_true).all(axis=(1, 2))
    if ok.any():
        with np.errstate(over="ignore", invalid="ignore"):
            diff = _apply(G_est[ok], pts) - _apply(G_true[ok], pts)
            e = np.linalg.norm(diff, axis=2).mean(axis=1)
        errors[ok] = np.where(np.isfinite(e), e, np.inf)
    return errors


def mosaic_error(errors: np.ndarray) -> float:
    """e_M (Eq. 29): mean of e_j over placed frames (NaN if none placed; inf if one is)."""
    placed = ~np.isnan(errors)
    return float(errors[placed].mean()) if placed.any() else float("nan")


def drift_ratio(errors: np.ndarray, reference: int | None = 0) -> float:
    """Mean e_j over the last quarter of frames / first quarter (frames with an e_j only; a
    quarter is max(n // 4, 1) frames). The reference frame's e_j (index `reference`, frame 0 by
    default; None: none), 0 by construction (the estimate writes it as the identity, the truth
    is taken to its grid), is left out of the quarter means when it is 0 up to EXACT_E_J_PX: a
    constant error would otherwise give a ratio above 1 (2.0 over 8 frames). NaN when undefined
    (drift_note says why: a quarter without a placed frame, a quarter with no scored frame but
    the reference (always so under 8 frames, a quarter being one frame), a first quarter whose
    mean e_j over its other frames is 0 (up to EXACT_E_J_PX) or inf); inf when the last quarter
    holds a frame placed at infinity (drift_note says so too)."""
    return _drift(errors, reference=reference)[0]


def reference_frame(G: np.ndarray) -> int:
    """Index of the frame whose pixel grid (N, 3, 3) frame -> reference homographies map to:
    the first frame written as the identity (0 normally; a later one when frame 0 is unplaced,
    lba-emt's start-up handing out frames before its tracker came on or a pCLE chain starting
    at its first usable frame, or has no anchor, runner.flag_reference_frame); 0 if none is."""
    G = np.asarray(G, np.float64)
    for r in np.flatnonzero(np.isfinite(G).all(axis=(1, 2))):
        if G[r][2, 2] != 0 and np.allclose(G[r] / G[r][2, 2], np.eye(3), atol=1e-9):
            return int(r)
    return 0


def rereferenced(G: np.ndarray, r: int) -> np.ndarray:
    """(N, 3, 3) frame -> frame r homographies from frame -> frame 0 ones (NaN stays NaN)."""
    G = np.asarray(G, np.float64)
    return G if r == 0 else _rebased(G, r)


def _rebased(G: np.ndarray, r: int) -> np.ndarray:
    """inv(G[r]) @ G, each row normalised to h22 = 1: the homographies into frame r's grid,
    whatever grid G maps to. NaN rows stay NaN; a row whose h22 comes out 0 or non-finite (it
    sends its frame's pixel (0, 0) to infinity) is kept unnormalised."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        out = np.linalg.inv(G[r]) @ G
        scale = out[:, 2:3, 2:3]
        ok = np.isfinite(scale) & (scale != 0)
        return np.where(ok, out / np.where(ok, scale, 1.0), out)


def truth_in_reference(G_est: np.ndarray, G_true: np.ndarray) -> tuple[np.ndarray, int]:
    """The true homographies in the estimate's reference grid, and its index r: frame 0's, or,
    when frame 0 is unplaced, that of reference_frame(G_est). Whenever the truth has a row for
    frame r the truth is re-based to it (inv(G_true[r]) @ G_true, normalised), frame 0
    included: a truth given in another grid (frame 0 not the identity, e.g. positions in a
    microscope image, seed 004 Sec. IV-A) scores the same as one in frame 0's. Without a row
    for r the truth is returned as it is, with r = 0: its grid is then unknown (for r != 0 a
    score against it holds frame r's true offset on every frame, for r = 0 the offset of frame
    0 in the truth's grid when that is another), so scoring goes through scoring_truth, which
    refuses that case (kept for callers that only draw the truth)."""
    G_true = np.asarray(G_true, np.float64)
    r = reference_frame(G_est)
    if not np.isfinite(G_true[r]).all():
        return G_true, 0
    if np.array_equal(G_true[r], np.eye(3)):  # already in r's grid: bit for bit as it was
        return G_true, r
    return _rebased(G_true, r), r


def unscorable_reference(G_est: np.ndarray, G_true: np.ndarray, frame_ids=None,
                         output: str = "the output") -> str | None:
    """Why G_est cannot be scored against G_true (None when it can): the truth has no row for
    the estimate's reference frame r (reference_frame), so it cannot be taken to r's grid, and
    which grid it is in cannot be checked. r != 0 (frame 0 unplaced): scored in frame 0's grid
    every e_j would hold frame r's true offset (a run's e_M of 159.5 px for 0.46 px). r = 0
    (frame 0 placed, its truth row empty or missing) when a frame would be scored: a truth
    given in another grid (positions in a microscope image, seed 004 Sec. IV-A; or written
    with another frame as the identity) is taken to frame 0's grid through that row alone, and
    scored as it is every e_j would hold frame 0's offset in that grid (an exact estimate
    scored 111.8 px; review 52). Such a truth is refused, not aligned on another frame: that
    would absorb that frame's own error into every e_j, another measure than Eq. 28's. (A
    truth in frame 0's grid lacking only frame 0's row is refused too: its identity row, added,
    makes it scorable.) frame_ids names the frames (default: their index), `output` what
    writes r as the identity."""
    G_est = np.asarray(G_est, np.float64)
    G_true = np.asarray(G_true, np.float64)
    r = reference_frame(G_est)
    if np.isfinite(G_true[r]).all():
        return None
    ids = np.arange(len(G_true)) if frame_ids is None else np.asarray(frame_ids)
    k = int(ids[r])
    if r != 0:
        return (f"the truth has no row for the output's reference frame {k} (the frame "
                f"{output} writes as the identity, frame 0 being unplaced): the truth cannot "
                "be taken to the output's grid, and scored in another grid every e_j would "
                "hold that frame's offset")
    scored = np.isfinite(G_est).all(axis=(1, 2)) & np.isfinite(G_true).all(axis=(1, 2))
    if not scored.any():  # nothing would be scored: no figure in a wrong grid either
        return None
    identity = [j for j in np.flatnonzero(np.isfinite(G_true).all(axis=(1, 2)))
                if np.allclose(G_true[j] / G_true[j][2, 2], np.eye(3), atol=1e-9)]
    grid = (f"its identity row is frame {int(ids[identity[0]])}'s, so it is in that frame's "
            "grid, not the output's" if identity else
            "which grid it is in cannot be checked (a truth in another grid, e.g. positions "
            "in a microscope image, is taken to the output's grid through that row)")
    return (f"the truth has no row for the output's reference frame {k} (the frame {output} "
            f"writes as the identity): {grid}; scored as it is every e_j would hold frame "
            f"{k}'s offset in the truth's grid. Give the truth a row for frame {k} (the "
            f"identity when the truth is in frame {k}'s grid)")


def scoring_truth(G_est: np.ndarray, G_true: np.ndarray, frame_ids=None,
                  output: str = "the output") -> tuple[np.ndarray | None, int, str | None]:
    """truth_in_reference for scoring: (the truth in the estimate's reference grid, r, None),
    or (None, r, why) when it cannot be taken there (unscorable_reference): the scores are then
    undefined, not numbers in another grid."""
    why = unscorable_reference(G_est, G_true, frame_ids, output)
    if why is not None:
        return None, reference_frame(G_est), why
    G, r = truth_in_reference(G_est, G_true)
    return G, r, None


def run_metrics(G_est: np.ndarray, G_true: np.ndarray, width: int, height: int,
                frame_ids=None) -> dict:
    """report.json's scores of a run against its dataset's truth: {"metrics": {e_M_px,
    max_e_j_px, drift_ratio, frames_scored}}, or {"metrics": None, "metrics_note": why} when
    the truth has no row for the output's reference frame (scoring_truth; `evaluate` refuses
    it alike). As evaluate_output's: a measure that is undefined is None, with
    "drift_ratio_note" saying why the drift ratio is undefined or infinite; a frame placed at
    infinity keeps e_j inf, so e_M_px and max_e_j_px are inf (null in report.json, strict
    JSON) and "placed_at_infinity" names the frames (frame_ids; default: their index). Before,
    max_e_j_px was None beside an inf e_M when every scored frame was at infinity, and a null
    drift ratio came without a word (review 52)."""
    G_ref, r, why = scoring_truth(G_est, G_true, frame_ids, "homographies.csv")
    if why is not None:
        return {"metrics": None, "metrics_note": f"not scored: {why}"}
    errors = frame_errors(G_est, G_ref, width, height)
    ids = np.arange(len(errors)) if frame_ids is None else np.asarray(frame_ids)
    scored = ~np.isnan(errors)
    drift, drift_why = _drift(errors, ids, r)
    metrics: dict = {
        "e_M_px": mosaic_error(errors) if scored.any() else None,
        "drift_ratio": None if np.isnan(drift) else drift,  # (inf: null in the JSON file)
        "max_e_j_px": float(np.nanmax(errors)) if scored.any() else None,
        "frames_scored": int(scored.sum())}  # placed, with ground truth
    if drift_why is not None:
        metrics["drift_ratio_note"] = drift_why
    if np.isinf(errors).any():  # e_M, max e_j (and drift, when in the last quarter) inf:
        # null in report.json, so the frames are named
        metrics["placed_at_infinity"] = [int(k) for k in ids[np.isinf(errors)]]
    return {"metrics": metrics}


def drift_note(errors: np.ndarray, frame_ids=None, reference: int | None = 0) -> str | None:
    """Why drift_ratio(errors, reference) is undefined or infinite (None when it is a finite
    number), naming the quarters by frame_ids (default: positions 0..n-1)."""
    return _drift(errors, frame_ids, reference)[1]


# A mean e_j at or below this is 0 up to rounding (a reference frame written as the identity).
EXACT_E_J_PX = 1e-9


def _drift(errors: np.ndarray, frame_ids=None,
           reference: int | None = 0) -> tuple[float, str | None]:
    errors = np.asarray(errors, dtype=np.float64)
    n = len(errors)
    if n == 0:
        return float("nan"), "no frames"
    ids = np.arange(n) if frame_ids is None else np.asarray(frame_ids)
    q = max(n // 4, 1)

    def span(part: np.ndarray) -> str:
        return f"frame {part[0]}" if len(part) == 1 else f"frames {part[0]}-{part[-1]}"

    spans = (span(ids[:q]), span(ids[n - q:]))
    empty = [where for where, part in zip(spans, (errors[:q], errors[n - q:]), strict=True)
             if np.isnan(part).all()]
    if empty:  # (a placed frame without ground truth has no e_j either)
        return float("nan"), (
            f"needs placed frames in both the first and the last quarter of the sequence "
            f"({spans[0]}; {spans[1]}): drift = mean e_j of the last / of the first; none "
            f"placed in {' nor in '.join(empty)}")
    # the reference frame's e_j is 0 by construction: left out of the quarter means (a
    # larger one is a real error, kept); the quarters still count all frames
    if (reference is not None and 0 <= reference < n
            and abs(errors[reference]) <= EXACT_E_J_PX):
        errors = errors.copy()
        errors[reference] = np.nan
    first, last = errors[:q], errors[n - q:]
    # under 8 frames a quarter is one frame: the reference's alone, exact by definition (a
    # method writes it as the identity up to rounding: 1e-14 px would give a ratio 1e13)
    for which, where, part, ending in (("last", spans[1], last, "the ratio is undefined"),
                                       ("first", spans[0], first, "no ratio to it")):
        if np.isnan(part).all():  # scored frames there (checked above): the reference alone
            holds = ("holds only the reference frame, whose e_j is 0 by construction and left "
                     "out (with under 8 frames a quarter is one frame)" if q == 1 else
                     "has no scored frame but the reference frame, whose e_j is 0 by "
                     "construction and left out (the others are unplaced or have no "
                     "ground-truth homography)")
            return float("nan"), f"the {which} quarter ({where}) {holds}: {ending}"
    first, last = float(np.nanmean(first)), float(np.nanmean(last))
    if first <= EXACT_E_J_PX:  # frames other than the reference scored 0 (an exact estimate)
        return float("nan"), (f"the first quarter ({spans[0]}) has mean e_j 0 (up to "
                              f"{EXACT_E_J_PX:g} px) over its scored frames: no ratio to it")
    if np.isinf(first):
        return float("nan"), (f"the first quarter ({spans[0]}) holds a frame placed at "
                              "infinity (e_j inf): no ratio to it")
    if np.isinf(last):
        return float("inf"), (f"the last quarter ({spans[1]}) holds a frame placed at "
                              "infinity (e_j inf): the ratio is infinite")
    return last / first, None


def positions_px(G: np.ndarray, width: int, height: int) -> np.ndarray:
    """Image positions in the reference frame: where each frame's centre lands, minus the centre.

    For the translation-only pCLE methods this is exactly the translation of G_k."""
    centre = np.array([[(width - 1) / 2.0, (height - 1) / 2.0]])
    return _apply(_check_stack(G, "G"), centre)[:, 0, :] - centre


def position_errors_um(G_est: np.ndarray, G_true: np.ndarray, width: int, height: int,
                       pixel_size_um: float) -> np.ndarray:
    """Per-frame distance (µm) between estimated and true image positions (seed 004, IV-B):
    NaN where either homography is missing, inf where both exist but the estimate sends the
    frame's centre to infinity (as frame_errors: placed unusably, not unplaced)."""
    if not pixel_size_um or pixel_size_um <= 0 or not np.isfinite(pixel_size_um):
        raise ValueError(f"pixel_size_um must be a positive number, got {pixel_size_um}")
    G_est, G_true = _check_stack(G_est, "G_est"), _check_stack(G_true, "G_true")
    with np.errstate(over="ignore", invalid="ignore"):
        d = positions_px(G_est, width, height) - positions_px(G_true, width, height)
        dist = np.linalg.norm(d, axis=1) * pixel_size_um
    both = np.isfinite(G_est).all(axis=(1, 2)) & np.isfinite(G_true).all(axis=(1, 2))
    return np.where(both, np.where(np.isfinite(dist), dist, np.inf), np.nan)


@dataclass
class PositionStats:
    """Table I/II statistics of seed 004, in µm. std is the population standard deviation
    (ddof 0, divided by n; recorded as std_ddof): the paper does not say which, and its
    authors' tools (MATLAB) default to the sample one (n - 1), sqrt(n / (n - 1)) = 1.04x larger
    at n = 13: compare like with like."""

    n: int
    mean: float
    max: float
    std: float
    median: float
    std_ddof: int = 0


def _json_stats(s: PositionStats) -> dict:
    """PositionStats as a dict, NaN (no placed frame) as None."""
    return {k: None if isinstance(v, float) and np.isnan(v) else v for k, v in asdict(s).items()}


def evenly_spaced(n_frames: int, n: int) -> np.ndarray:
    """n frame indices evenly spaced along the sequence, the first and last included (seed 004
    picks 13 / 25 such frames); n distinct ones, so n must be at most n_frames (ValueError)."""
    if n > n_frames:  # (rounding would repeat indices: fewer than n frames, silently)
        raise ValueError(f"{n} evenly spaced frames of a sequence of {n_frames}: at most "
                         f"{n_frames}")
    return np.round(np.linspace(0, n_frames - 1, n)).astype(int)


def position_sample(G_true: np.ndarray, n: int) -> np.ndarray:
    """Indices of n frames evenly spaced among those with a ground-truth homography (rows of
    G_true without NaN), the first and last of them included: seed 004 scores n images along
    the trajectory, and a sparse truth has rows only there. ValueError when fewer than n
    frames have one (statistics over fewer frames would be taken for a table over n)."""
    with_truth = np.flatnonzero(np.isfinite(_check_stack(G_true, "G_true")).all(axis=(1, 2)))
    return with_truth[evenly_spaced(len(with_truth), n)]


def position_stats(errors_um: np.ndarray, frames: np.ndarray | None = None) -> PositionStats:
    """The statistics of the errors (µm) of the placed frames (NaN: unplaced, or no truth,
    left out) among `frames` (default all). A frame placed at infinity (inf) counts, as its
    e_j counts against e_M: mean, max and std are then inf (n counting it), the median as it
    falls. std: ddof 0 (PositionStats)."""
    e = np.asarray(errors_um, np.float64)
    e = e if frames is None else e[frames]
    e = e[~np.isnan(e)]
    if len(e) == 0:
        return PositionStats(0, *([float("nan")] * 4))
    if np.isinf(e).any():  # (np.std would warn: inf - inf)
        return PositionStats(len(e), float("inf"), float("inf"), float("inf"),
                             float(np.median(e)))
    return PositionStats(len(e), float(e.mean()), float(e.max()), float(e.std()),
                         float(np.median(e)))


# Paired errors (µm, or px: the unit compared) closer than this are equal: a difference of
# rounding (homographies written with 10 significant digits: 6e-8 µm) is no difference.
WILCOXON_ZERO = 1e-6


def compare_position_errors(errors_a: np.ndarray, errors_b: np.ndarray) -> dict:
    """Wilcoxon signed-rank test between two methods' per-frame errors (paired by frame).

    Pairs whose errors differ by at most WILCOXON_ZERO count as no difference and are not
    ranked (scipy's zero_method="wilcox"; the reference frame, 0 vs 0, is one): "n" counts the
    frames placed by both, "n_ranked" the pairs ranked. With none ranked p = 1 and "note" says
    why.

    A frame placed at infinity (error inf, as position_errors_um gives it: placed, unusably)
    is paired and counts as the worst: its difference ranks above every finite one, with its
    sign (the test uses ranks and signs only); placed at infinity by both, it is a tie.
    Before, such frames were dropped as if unplaced, so the method that placed them at
    infinity was compared on its good frames alone (review 52). "at_infinity_a" /
    "at_infinity_b" count them, and frames only one method places (NaN for the other: the
    other left it unplaced) are not paired but counted, "unplaced_a" / "unplaced_b" (placed by
    the other); "note" says so when any is not 0."""
    errors_a, errors_b = np.asarray(errors_a, np.float64), np.asarray(errors_b, np.float64)
    if errors_a.shape != errors_b.shape or errors_a.ndim != 1:
        raise ValueError(f"Wilcoxon test needs two per-frame error lists of the same length, "
                         f"got shapes {errors_a.shape} and {errors_b.shape}")
    if (errors_a == -np.inf).any() or (errors_b == -np.inf).any():
        raise ValueError("Wilcoxon test: an error of -inf (errors are distances, >= 0)")
    placed_a, placed_b = ~np.isnan(errors_a), ~np.isnan(errors_b)
    ok = placed_a & placed_b
    if ok.sum() < 2:
        raise ValueError("Wilcoxon test needs at least 2 frames placed by both methods")
    a, b = errors_a[ok], errors_b[ok]
    inf_a, inf_b = np.isinf(a), np.isinf(b)
    with np.errstate(invalid="ignore"):
        d = np.where(inf_a & inf_b, 0.0, a - b)  # (inf - inf: both at infinity, a tie)
    finite = d[np.isfinite(d)]
    # ranked above every finite difference: any larger magnitude gives the same ranks
    top = 2.0 * (float(np.abs(finite).max()) if finite.size else 0.0) + 1.0
    d = np.where(np.isinf(d), np.sign(d) * top, d)
    ranked = d[np.abs(d) > WILCOXON_ZERO]
    result = {"n": int(ok.sum()), "n_ranked": int(len(ranked)),
              "at_infinity_a": int(inf_a.sum()), "at_infinity_b": int(inf_b.sum()),
              "unplaced_a": int((placed_b & ~placed_a).sum()),
              "unplaced_b": int((placed_a & ~placed_b).sum())}
    notes = []
    if len(ranked) == 0:  # no difference at all: nothing to rank
        result.update(statistic=0.0, p_value=1.0)
        notes.append(f"no paired difference above {WILCOXON_ZERO:g}: nothing to rank")
    else:
        res = stats.wilcoxon(ranked)
        result.update(statistic=float(res.statistic), p_value=float(res.pvalue))
    for side in ("a", "b"):
        if result[f"at_infinity_{side}"]:
            k = result[f"at_infinity_{side}"]
            notes.append(f"{k} frame{'s' if k != 1 else ''} placed at infinity by {side}, "
                         "ranked as the largest differences")
    for side, other in (("a", "b"), ("b", "a")):
        if result[f"unplaced_{side}"]:
            k = result[f"unplaced_{side}"]
            notes.append(f"{k} frame{'s' if k != 1 else ''} placed by {other} only "
                         f"({side} left {'them' if k != 1 else 'it'} unplaced), not paired")
    if notes:
        result["note"] = "; ".join(notes)
    # (means as position_stats': inf when a frame is placed at infinity)
    result.update(mean_a=float(a.mean()), mean_b=float(b.mean()))
    return result


def mosaic_difference(mosaic: np.ndarray, origin: tuple[int, int], truth: np.ndarray,
                      truth_origin: tuple[int, int], truth_covered: np.ndarray) -> dict:
    """Photometric difference of a mosaic from a truth mosaic (e.g. the simulator's pinhole
    frames composed at the true homographies), both in reference pixels with their pixel (0, 0)
    at `origin` / `truth_origin`: the mean absolute difference (grey levels, over channels) on
    the pixels the truth covers and the mosaic shows (not black), and the fraction of the truth's
    covered pixels that is."""
    a, b = np.asarray(mosaic), np.asarray(truth)
    if a.shape[2:] != b.shape[2:]:
        raise ValueError(f"mosaic has {a.shape[2:] or 1} channels, the truth {b.shape[2:] or 1}")
    (x0, y0), (tx0, ty0) = origin, truth_origin
    ax0, ay0 = max(x0, tx0), max(y0, ty0)
    ax1, ay1 = min(x0 + a.shape[1], tx0 + b.shape[1]), min(y0 + a.shape[0], ty0 + b.shape[0])
    if ax1 <= ax0 or ay1 <= ay0:
        return {"mean_abs_difference": float("nan"), "compared_fraction": 0.0}
    a = a[ay0 - y0:ay1 - y0, ax0 - x0:ax1 - x0].astype(np.float64)
    b = b[ay0 - ty0:ay1 - ty0, ax0 - tx0:ax1 - tx0].astype(np.float64)
    shown = a.reshape(a.shape[0], a.shape[1], -1).sum(axis=2) > 0
    both = np.asarray(truth_covered)[ay0 - ty0:ay1 - ty0, ax0 - tx0:ax1 - tx0] & shown
    diff = np.abs(a - b)[both]
    return {"mean_abs_difference": float(diff.mean()) if diff.size else float("nan"),
            "compared_fraction": float(both.sum() / max(int(np.count_nonzero(truth_covered)),
                                                          1))}


def check_positions_n(positions_n, what: str = "positions") -> None:
    """The number of evenly spaced frames for the position statistics: an integer >= 1."""
    if (isinstance(positions_n, bool) or not isinstance(positions_n, (int, np.integer))
            or positions_n < 1):
        raise ValueError(f"{what}: the number of evenly spaced frames must be an integer >= 1, "
                         f"got {positions_n!r}")


def evaluation_notes(result: dict) -> list[str]:
    """What an evaluate_output result holds beside its table's figures, as sentences (for the
    terminal and evaluation.md): the dead-reckoned frames with e_M without them, the frames
    whose centre lands at infinity, and the grid scored in when the output's reference frame is
    not frame 0. (How many frames e_M is over is "frames_scored"; report.write_report says it
    when fewer than all.)"""
    notes = []
    dead = result.get("dead_reckoned")
    if dead:
        without = result.get("e_M_px_without_dead_reckoned")
        notes.append(
            f"{len(dead)} of the placed frames dead-reckoned (placed with no anchor: "
            f"{_listed(dead)}); e_M without them: "
            + ("undefined (no other frame scored)" if without is None else f"{without:.3f} px"))
    inf = result.get("position_at_infinity")
    if inf:
        notes.append(f"{_listed(inf)} placed with the centre at infinity: counted in the µm "
                     "position statistics, whose mean, max and std are then inf")
    ref, first = result.get("reference_frame", 0), result.get("first_frame", 0)
    if ref != first:  # (ids, not indices: a dataset's frames may start at id 100)
        notes.append(f"scored in frame {ref}'s pixel grid: the output's reference frame (the "
                     f"one it writes as the identity; frame {first} unplaced), the truth taken "
                     "to it")
    return notes


def _listed(frames: list[int], first: int = 8) -> str:
    """'frames 3, 4, 5' (the first `first` of more, then '... (N in all)')."""
    shown = ", ".join(map(str, frames[:first]))
    more = f", ... ({len(frames)} in all)" if len(frames) > first else ""
    return f"frame{'s' if len(frames) != 1 else ''} {shown}{more}"


# Keys of evaluate_output's result that every version wrote: how `evaluate` recognises an
# evaluation JSON of an older version (no manifest record) as its own, not a user's file.
RESULT_KEYS = ("output", "truth", "frames", "e_M_px", "e_j_px")


def read_truth_dataset(root):
    """The dataset at `root` as scoring reads it: its truth and frames, not its tracker / robot
    (a run with --allow-untracked or --live on a late tracker, or an ncc run beside an unusable
    robot.csv, is scored like any other), and frames that cannot be read as `run` reads them,
    blank (a damaged first frame was refused here while `run` had accepted it; review)."""
    from fusedmosaic.io import read_dataset

    return read_dataset(root, allow_untracked=True, strict_tracking=False, strict_robot=False,
                        blank_unreadable=True)


def evaluate_output(out_dir: str | Path, truth_root, *,
                    positions_n: int | None = None, allow_other_dataset: bool = False) -> dict:
    """Scores an output folder's homographies.csv against a dataset's ground_truth.csv.

    truth_root: the dataset folder, or the Dataset read from it by read_truth_dataset (a caller
    scoring several outputs reads it once: a video dataset is decoded end to end when read).

    The result is ready for JSON: a measure that is undefined is None (null), not NaN — e_M_px
    and max_e_j_px with no scored frame, e_j_px of an unplaced frame, drift_ratio when a
    quarter of the sequence has no placed frame (then "drift_ratio_note" says why). A frame
    placed at infinity keeps e_j inf (it counts against e_M; "placed_at_infinity" names it,
    as "position_at_infinity" names those whose centre lands at infinity: counted, inf, in the
    µm statistics). "frames_scored": the frames e_M is over (placed, with a ground-truth
    homography); evaluation_notes words the other keys.

    The truth is taken to the grid of the output's reference frame (truth_in_reference); an
    output whose reference frame r the truth has no row for is refused (ValueError): it could
    only be scored in another grid (r != 0), or in a grid that cannot be checked (r = 0, when a
    frame would be scored; see unscorable_reference).

    positions_n: also the position statistics at that many evenly spaced frames, chosen among
    the frames that have a ground-truth homography (a sparse truth, as seed 004's n images),
    the first and last of them included (>= 1, at most the frames with a truth: ValueError
    otherwise; "position_sampled_frames" names them).
    When the output's report.json records another dataset than `truth_root` (camera.yaml or
    the frames' pixels differ) it is refused (ValueError) unless allow_other_dataset, then the
    result's "dataset_warning" says so (as for frames.csv differing, or an older report.json's
    other path); ground_truth.csv alone differing gets a "truth_note"; without report.json,
    "provenance_note" says the dataset could not be checked; frames of another size are
    refused (see evaluation.provenance)."""
    from fusedmosaic.evaluation.provenance import check_frame_size, dataset_mismatch
    from fusedmosaic.io import Dataset, read_homographies_csv
    from fusedmosaic.io.output import read_json_object

    if positions_n is not None:
        check_positions_n(positions_n)
    dataset = truth_root if isinstance(truth_root, Dataset) else read_truth_dataset(truth_root)
    out_dir, truth_root = Path(out_dir), Path(dataset.root)
    if dataset.ground_truth is None:
        raise ValueError(f"{truth_root / 'ground_truth.csv'}: file not found; nothing to score")
    est_path = out_dir / "homographies.csv"
    require_file(est_path)
    report_path = out_dir / "report.json"
    report = read_json_object(report_path) if report_path.is_file() else None
    if report is not None:
        check_frame_size(report, dataset, report_path)
        # (refused here, before the scores: another dataset's truth)
        provenance = dataset_mismatch(report, dataset, report_path,
                                      allow_other=allow_other_dataset)
    else:
        provenance = {"provenance_note": (
            f"{out_dir} has no report.json: which dataset the output was computed from could "
            f"not be checked against {truth_root}")}
    ids, G_est = read_homographies_csv(est_path)
    truth_ids = dataset.frame_ids
    if not np.array_equal(np.sort(ids), np.sort(truth_ids)):
        def listed(frames: set) -> str:  # "3 frames [5, 6, 7]", the first 5 of more, "..."
            first = ", ".join(map(str, sorted(frames)[:5]))
            return (f"{len(frames)} frame{'s' if len(frames) != 1 else ''} "
                    f"[{first}{', ...' if len(frames) > 5 else ''}]")

        missing = set(truth_ids.tolist()) - set(ids.tolist())
        extra = set(ids.tolist()) - set(truth_ids.tolist())
        raise ValueError(f"{est_path}: frames do not match {truth_root / 'ground_truth.csv'} "
                         f"(missing {listed(missing)}, unexpected {listed(extra)})")
    G_est = G_est[np.argsort(ids)]
    w, h = dataset.camera.width, dataset.camera.height
    G_true, r, why = scoring_truth(G_est, dataset.ground_truth, truth_ids, str(est_path))
    if why is not None:
        raise ValueError(f"{truth_root / 'ground_truth.csv'}: {why}")
    errors = frame_errors(G_est, G_true, w, h)
    placed = np.isfinite(G_est).all(axis=(1, 2))
    scored = ~np.isnan(errors)
    drift, why = _drift(errors, truth_ids, r)
    result: dict = {
        "output": str(out_dir),
        "truth": str(truth_root),
        "frames": int(len(errors)),
        "placed": int(placed.sum()),
        "unplaced": int((~placed).sum()),
        "e_M_px": mosaic_error(errors) if scored.any() else None,
        # e_M is over these: placed and with a ground-truth homography (a sparse truth: fewer
        # than placed)
        "frames_scored": int(scored.sum()),
        "max_e_j_px": float(np.nanmax(errors)) if scored.any() else None,
        "drift_ratio": None if np.isnan(drift) else drift,  # (inf: null in the JSON file)
        "e_j_px": [None if np.isnan(e) else float(e) for e in errors],
        "reference_frame": int(truth_ids[r]),
        "first_frame": int(truth_ids[0]),  # (reference_frame is another when it is unplaced)
    }
    if why is not None:
        result["drift_ratio_note"] = why
    at_infinity = np.isinf(errors)
    if at_infinity.any():  # e_j (and so e_M) inf: written as null in evaluation.json (strict
        # JSON), so the frames are named here
        result["placed_at_infinity"] = [int(k) for k in dataset.frame_ids[at_infinity]]
    without_truth = placed & ~scored
    if without_truth.any():  # placed, but ground_truth.csv has no homography for them
        result["placed_without_truth"] = [int(k) for k in dataset.frame_ids[without_truth]]
    statuses = report.get("frame_status") if report is not None else None
    if isinstance(statuses, list) and len(statuses) == len(errors):
        # frames placed with no anchor (lba-emt, ba-emt): counted as placed, and apart
        dead = np.array([s == "dead-reckoned" for s in statuses])
        if dead.any():
            rest = scored & ~dead
            result["dead_reckoned"] = [int(k) for k in truth_ids[dead]]
            result["e_M_px_without_dead_reckoned"] = (mosaic_error(errors[rest]) if rest.any()
                                                      else None)
    result.update(provenance)
    if positions_n is not None and not dataset.camera.pixel_size_um:
        raise ValueError(f"{truth_root / 'camera.yaml'}: no pixel_size_um, so no position "
                         f"errors in µm at {positions_n} evenly spaced frames (a pCLE "
                         "measure): leave out positions_n (--positions)")
    with_truth = np.flatnonzero(np.isfinite(dataset.ground_truth).all(axis=(1, 2)))
    if positions_n is not None and positions_n > len(with_truth):
        # refused, not reduced: statistics over fewer frames than asked for would be taken for
        # a table over positions_n (seed 004's 13 / 25 images)
        if len(with_truth) == len(errors):
            raise ValueError(f"{truth_root}: {len(errors)} frames, fewer than the {positions_n} "
                             "evenly spaced frames asked for (positions_n, --positions); give "
                             f"at most {len(errors)}")
        raise ValueError(f"{truth_root / 'ground_truth.csv'}: {len(with_truth)} of the "
                         f"{len(errors)} frames have a ground-truth homography, fewer than the "
                         f"{positions_n} evenly spaced frames asked for (positions_n, "
                         f"--positions), which are chosen among them; give at most "
                         f"{len(with_truth)}")
    if dataset.camera.pixel_size_um:
        err_um = position_errors_um(G_est, G_true, w, h,
                                    dataset.camera.pixel_size_um)
        result["position_errors_um"] = [None if not np.isfinite(e) else float(e) for e in err_um]
        if np.isinf(err_um).any():  # counted in the statistics (inf), null in the list
            result["position_at_infinity"] = [int(k) for k in truth_ids[np.isinf(err_um)]]
        result["position_all_um"] = _json_stats(position_stats(err_um))
        if positions_n:
            sampled = position_sample(dataset.ground_truth, positions_n)
            result["position_sampled_um"] = _json_stats(position_stats(err_um, sampled))
            result["position_sampled_frames"] = [int(k) for k in truth_ids[sampled]]
    return result
