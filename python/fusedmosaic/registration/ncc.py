"""Translation registration of consecutive pCLE frames by normalised cross-correlation.

Rosa et al. 2018 (paper 004), Sec. III-D: a template covering the central 3/5 of frame i-1 is
matched in frame i by normalised cross-correlation (NCC); the same is repeated backward (the
central template of frame i matched in frame i-1) and the two displacements are averaged. The
displacement is the registration ``dX_{i-1}^i`` of Eq. 1: ``X_m(i) = X_m(i-1) + dX_{i-1}^i``.

Sign convention (image axes, x right, y down, pixels): ``dx`` is the position of frame i minus
the position of frame i-1 in the mosaic, where a mosaic point is ``frame pixel + X_m``. A scene
point seen at pixel ``p`` in frame i-1 is therefore seen at ``p - dx`` in frame i (the content
moves opposite to the probe).

Speed: an exhaustive full-resolution search of a 3/5 template (the search range is then the
whole frame, +-1/5 of its size) costs ~2.8 ms per direction at 512x448 with OpenCV's DFT
correlation. The default coarse-to-fine search (``pyramid_levels=2``: exhaustive search at 1/4
resolution, then a small full-resolution window around the up-scaled peak) costs ~1.1 ms per
direction; ``pyramid_levels=0`` gives the exhaustive search. See ``bench/bench_pcle_core.py``.

Checks beyond the paper (on by default, ``max_disagreement`` / ``fallback_template_fraction``):
the forward and backward estimates of one dX must agree within 3 px (below the probe's 3.5 µm
optical resolution); if they do not, or a peak is clipped at the edge of the +-1/5 search range
(a stick-slip release jumps ~150 µm in one frame, Sec. III-C), a 2/5 template is searched over
+-3/10 of the frame and used if its own two directions agree. ``NccResult.consistent`` tells a
caller with another estimate (the robot) whether to trust the result. The retry runs only on
those frames (~6 ms at 512x448).

``aligned_overlap_ssim`` gives the matching confidence ``c_match`` of Sec. II-C: the structural
similarity (Wang et al. 2004, the paper's ref. [17]) of the overlap of the two frames once aligned.

``fixed_pattern_gain`` / ``flat_field`` (optional, not in the paper): raw fibre-bundle frames carry
the bundle's honeycomb, fixed in the image while the tissue moves, and at low contrast NCC can
lock on it at zero shift. Dividing each frame by the pattern (flat-field correction, as the
endomicroscope's own calibration does) removes it; here the pattern is the per-pixel mean of a
recording's frames, over which the moving tissue averages out.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import cv2
import numpy as np

__all__ = [
    "NccResult",
    "fixed_pattern_gain",
    "flat_field",
    "gray_from_color",
    "register_ncc",
    "aligned_overlap_ssim",
    "structural_similarity",
]

# Smallest template side (pixels) still searched at a pyramid level; below it levels are dropped.
_MIN_TEMPLATE_SIDE = 16
# Relative template standard deviation under which the template is considered featureless.
_FLAT_TEMPLATE_STD = 1e-6
# A second thread (None on a 1-core machine): the backward NCC search beside the forward one,
# one half of the SSIM beside the other (OpenCV and numpy release the GIL): the same numbers,
# ~1.5x faster per pair on 2 cores. Set to None for serial work (the tests do).
_SECOND = ThreadPoolExecutor(1, "fusedmosaic-ncc") if (os.cpu_count() or 1) > 1 else None


def _new_second_in_child() -> None:
    """After a fork: the child inherits the parent's executor but not its worker thread, so a
    task submitted to it never ran and ``.result()`` waited for ever (a ``multiprocessing``
    worker forked after a registration in the parent hung). The child gets an executor of its
    own, which starts its thread on first use."""
    global _SECOND
    if _SECOND is not None:
        _SECOND = ThreadPoolExecutor(1, "fusedmosaic-ncc")


os.register_at_fork(after_in_child=_new_second_in_child)


@dataclass(frozen=True)
class NccResult:
    """Result of :func:`register_ncc`.

    Attributes
    ----------
    dx : (2,) float64
        Averaged displacement ``(dx, dy)`` in pixels of ``current`` relative to ``previous``,
        so that ``X_m(i) = X_m(i-1) + dx`` (paper 004, Eq. 1). NaN when registration failed
        (featureless template).
    score : float
        Mean of the forward and backward peak NCC values, in [-1, 1] (0 on failure).
    dx_forward, dx_backward : (2,) float64
        The two estimates of the same ``dx``: forward (central template of ``previous`` found in
        ``current``) and backward (central template of ``current`` found in ``previous``, sign
        flipped so that both estimate ``dx``).
    score_forward, score_backward : float
        Peak NCC value of each direction.
    consistent : bool
        The forward and backward estimates agree within ``max_disagreement`` px (always True
        when that check is off). False means at least one of the two peaks is a false match: the
        averaged ``dx`` is then unreliable (a caller with another estimate should not use it).
    fallback : bool
        The result comes from the wide-range fallback search (see :func:`register_ncc`).
    """

    dx: np.ndarray
    score: float
    dx_forward: np.ndarray
    dx_backward: np.ndarray
    score_forward: float
    score_backward: float
    consistent: bool = True
    fallback: bool = False

    @property
    def disagreement(self) -> float:
        """Distance in pixels between the forward and backward estimates (a sanity check)."""
        return float(np.linalg.norm(self.dx_forward - self.dx_backward))


def _as_gray_float32(image: np.ndarray, name: str) -> np.ndarray:
    """Validate a 2-D grayscale image and return it as C-contiguous float32."""
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(
            f"{name}: expected a 2-D grayscale image (H, W), got an array of shape {image.shape}"
        )
    if image.dtype == np.uint8:
        return image.astype(np.float32)
    if not np.issubdtype(image.dtype, np.floating) and not np.issubdtype(image.dtype, np.integer):
        raise ValueError(f"{name}: expected uint8 or float pixels, got dtype {image.dtype}")
    out = np.ascontiguousarray(image, dtype=np.float32)
    if not np.isfinite(out).all():
        raise ValueError(f"{name}: image contains NaN or infinite pixels")
    return out


def _check_pair(
    previous: np.ndarray, current: np.ndarray, prepared: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    if prepared:
        # The caller converted and checked the pixels once per frame (RobotPriorMosaicker keeps
        # its anchor as float32): no second conversion, only the cheap structural checks.
        prev, curr = np.asarray(previous), np.asarray(current)
        for name, image in (("previous", prev), ("current", curr)):
            if image.ndim != 2 or image.dtype != np.float32:
                raise ValueError(
                    f"{name}: prepared=True needs a 2-D float32 image, got shape "
                    f"{image.shape} and dtype {image.dtype}"
                )
    else:
        prev = _as_gray_float32(previous, "previous")
        curr = _as_gray_float32(current, "current")
    if prev.shape != curr.shape:
        raise ValueError(
            f"previous and current frames differ in size: previous has shape {prev.shape}, "
            f"current has shape {curr.shape}"
        )
    return prev, curr


def _quadratic_peak(patch: np.ndarray) -> tuple[float, float]:
    """Sub-pixel offset (du, dv) of the maximum of a 3x3 patch centred on its integer peak.

    Least-squares fit of ``a + b u + c v + d u^2 + e u v + g v^2`` to the 9 samples (closed form
    on the 3x3 grid), maximum where the gradient vanishes. When the fitted surface has no maximum
    inside the centre pixel's +-1 neighbourhood (degenerate or saddle-shaped peak), falls back to
    independent 1-D parabolas through the centre row and column.
    """
    z = patch.astype(np.float64)
    u = np.array([-1.0, 0.0, 1.0])
    uu = u[None, :]  # column offset (x)
    vv = u[:, None]  # row offset (y)
    b = float((uu * z).sum() / 6.0)
    c = float((vv * z).sum() / 6.0)
    e = float((uu * vv * z).sum() / 4.0)
    d = float(((uu**2 - 2.0 / 3.0) * z).sum() / 2.0)
    g = float(((vv**2 - 2.0 / 3.0) * z).sum() / 2.0)
    det = 4.0 * d * g - e * e
    if d < 0.0 and det > 0.0:
        du = (-2.0 * g * b + e * c) / det
        dv = (-2.0 * d * c + e * b) / det
        if abs(du) <= 1.0 and abs(dv) <= 1.0:
            return du, dv

    def parabola(m1: float, m0: float, p1: float) -> float:
        den = m1 - 2.0 * m0 + p1
        if den >= 0.0:
            return 0.0
        return float(np.clip(0.5 * (m1 - p1) / den, -0.5, 0.5))

    return parabola(z[1, 0], z[1, 1], z[1, 2]), parabola(z[0, 1], z[1, 1], z[2, 1])


def _match(
    image: np.ndarray, template: np.ndarray, x0: int, y0: int, x1: int, y1: int
) -> tuple[np.ndarray, int, int]:
    """NCC of ``template`` at top-left positions [x0, x1] x [y0, y1] (inclusive) of ``image``."""
    th, tw = template.shape
    window = image[y0 : y1 + th, x0 : x1 + tw]
    return cv2.matchTemplate(window, template, cv2.TM_CCOEFF_NORMED), x0, y0


def _find_template(
    image: np.ndarray,
    template: np.ndarray,
    origin: tuple[int, int],
    max_shift: tuple[int, int],
    levels: int,
    refine_radius: int,
) -> tuple[np.ndarray, float, bool]:
    """Top-left position (x, y) of ``template`` in ``image`` (sub-pixel), its peak NCC, and
    whether the integer peak lies on the border of the search range (the true shift may then be
    beyond the range: the peak is clipped).

    ``origin`` is the template's own top-left position (its position for a zero shift); the
    search covers ``origin +- max_shift``, clipped to the image.
    """
    h, w = image.shape
    th, tw = template.shape
    ox, oy = origin
    # Inclusive range of top-left positions at full resolution.
    lo_x, hi_x = max(0, ox - max_shift[0]), min(w - tw, ox + max_shift[0])
    lo_y, hi_y = max(0, oy - max_shift[1]), min(h - th, oy + max_shift[1])

    if levels > 0:
        scale = 1 << levels
        # cv2.resize with INTER_AREA: an exact box average for integer factors (alias-free enough
        # for a coarse peak, cheaper than a Gaussian pyramid).
        small = cv2.resize(image, (w // scale, h // scale), interpolation=cv2.INTER_AREA)
        small_t = cv2.resize(template, (tw // scale, th // scale), interpolation=cv2.INTER_AREA)
        sh, sw = small.shape
        sth, stw = small_t.shape
        cx0 = min(max(0, -(-lo_x // scale)), sw - stw)
        cx1 = max(min(hi_x // scale, sw - stw), cx0)
        cy0 = min(max(0, -(-lo_y // scale)), sh - sth)
        cy1 = max(min(hi_y // scale, sh - sth), cy0)
        ncc, bx, by = _match(small, small_t, cx0, cy0, cx1, cy1)
        py, px = np.unravel_index(int(np.argmax(ncc)), ncc.shape)
        guess_x, guess_y = (bx + px) * scale, (by + py) * scale
        radius = scale + refine_radius
    else:
        guess_x, guess_y = ox, oy
        radius = max(hi_x - lo_x, hi_y - lo_y)

    # Full-resolution search around the guess; re-centre if the peak lands on a window border
    # that is not the search-range border (the coarse guess was off by more than the radius).
    for _ in range(4):
        x0, x1 = max(lo_x, guess_x - radius), min(hi_x, guess_x + radius)
        y0, y1 = max(lo_y, guess_y - radius), min(hi_y, guess_y + radius)
        x0, y0 = min(x0, hi_x), min(y0, hi_y)
        x1, y1 = max(x1, x0), max(y1, y0)
        ncc, bx, by = _match(image, template, x0, y0, x1, y1)
        py, px = np.unravel_index(int(np.argmax(ncc)), ncc.shape)
        on_inner_border = (
            (px == 0 and x0 > lo_x)
            or (px == ncc.shape[1] - 1 and x1 < hi_x)
            or (py == 0 and y0 > lo_y)
            or (py == ncc.shape[0] - 1 and y1 < hi_y)
        )
        if not on_inner_border:
            break
        guess_x, guess_y = bx + int(px), by + int(py)

    peak = float(ncc[py, px])
    sub_x = sub_y = 0.0
    if 0 < py < ncc.shape[0] - 1 and 0 < px < ncc.shape[1] - 1:
        sub_x, sub_y = _quadratic_peak(ncc[py - 1 : py + 2, px - 1 : px + 2])
    elif 0 < px < ncc.shape[1] - 1:  # peak on the search-range border in y only
        sub_x, _ = _quadratic_peak(np.repeat(ncc[py : py + 1, px - 1 : px + 2], 3, axis=0))
    elif 0 < py < ncc.shape[0] - 1:
        _, sub_y = _quadratic_peak(np.repeat(ncc[py - 1 : py + 2, px : px + 1], 3, axis=1))
    position = np.array([bx + px + sub_x, by + py + sub_y], dtype=np.float64)
    ix, iy = bx + int(px), by + int(py)
    on_range_border = ix in (lo_x, hi_x) or iy in (lo_y, hi_y)
    return position, peak, on_range_border


def register_ncc(
    previous: np.ndarray,
    current: np.ndarray,
    *,
    template_fraction: float = 0.6,
    max_displacement: float | None = None,
    pyramid_levels: int = 2,
    refine_radius: int = 2,
    presmooth_sigma: float = 0.0,
    max_disagreement: float | None = 3.0,
    fallback_template_fraction: float | None = 0.4,
    prepared: bool = False,
) -> NccResult:
    """Register ``current`` (frame i) to ``previous`` (frame i-1) by forward/backward NCC.

    Parameters
    ----------
    previous, current : (H, W) uint8 or float
        Consecutive grayscale frames of the same size.
    template_fraction : float
        Side of the central template as a fraction of the frame side; 3/5 in paper 004,
        Sec. III-D (268x307 px for 448x512 frames).
    max_displacement : float or None
        Largest displacement searched, in pixels per axis. ``None`` searches as far as the frame
        allows: +-(1 - template_fraction)/2 of the frame side, i.e. +-1/5 of the frame (102 px
        in x, 89 px in y at 512x448) for the paper's template.
    pyramid_levels : int
        Coarse-to-fine search: exhaustive NCC at resolution 1/2**levels, then a full-resolution
        window of radius 2**levels + ``refine_radius`` pixels around the up-scaled coarse peak.
        0 = exhaustive full-resolution search (slower, ~2.5x at 512x448). Usually the same peak,
        but not always: at low contrast (a contact loss) the two can find different ones, the
        exhaustive search more often the fibre-pattern lock at 0 px. Levels that would make
        the template smaller than 16 px are dropped.
    refine_radius : int
        Extra radius (px) of the full-resolution refinement window.
    presmooth_sigma : float
        Gaussian blur (px) applied to both frames before matching, 0 = none (the paper uses
        none). A sigma of ~1-2 px damps pixel noise and the fibre-bundle honeycomb, which is
        fixed in image coordinates and otherwise pulls the NCC peak towards zero displacement.
    max_disagreement : float or None
        Largest distance (px) between the forward and backward estimates for the match to count
        as ``consistent``. Both estimate the same dX, so on a true match they agree to the
        sub-pixel registration noise (99th percentile 0.07 px on the simulator's good frames);
        two peaks further apart than the probe's optical resolution (3.5 µm, paper 004
        Sec. III-B, ~3.5 px at 1 µm/px) are different matches. The default 3 px stays below
        it. None = no check (every result is consistent, no fallback for disagreement).
    fallback_template_fraction : float or None
        Template side of the wide-range retry made when the primary search is inconsistent or
        its peak is clipped at the edge of its range: 2/5 searches +-3/10 of the frame (154 px
        in x, 134 px in y at 512x448) instead of +-1/5, e.g. a stick-slip release that jumps
        ~150 µm in one frame (Sec. III-C). Accepted only if its own directions agree; otherwise
        the primary result is returned (``consistent`` tells whether to trust it). It runs on
        the failing frames only. None = no retry (the paper's registration as written).
    prepared : bool
        True: both frames are already 2-D float32 with finite pixels (e.g. uint8 frames
        converted once with ``astype(np.float32)``); they are used as they are, without the
        per-call conversion and finiteness check. A streaming caller converts each frame once
        and keeps the previous one's float copy. Same results as the unprepared call.

    Returns
    -------
    NccResult
        ``dx`` (2,) float64, with ``X_m(i) = X_m(i-1) + dx`` (Eq. 1). The integer NCC peak is
        refined to sub-pixel by a 2-D quadratic least-squares fit on its 3x3 neighbourhood.
        ``consistent`` and ``fallback`` report the checks above.

    Raises
    ------
    ValueError
        If the frames are not 2-D, differ in shape, hold non-finite values, or the options are
        out of range.
    """
    prev, curr = _check_pair(previous, current, prepared)
    if not 0.0 < template_fraction < 1.0:
        raise ValueError(f"template_fraction must be in (0, 1), got {template_fraction}")
    if pyramid_levels < 0:
        raise ValueError(f"pyramid_levels must be >= 0, got {pyramid_levels}")
    if refine_radius < 1:
        raise ValueError(f"refine_radius must be >= 1, got {refine_radius}")
    if max_displacement is not None and not max_displacement >= 0.0:
        raise ValueError(f"max_displacement must be >= 0 or None, got {max_displacement}")
    if not presmooth_sigma >= 0.0:
        raise ValueError(f"presmooth_sigma must be >= 0, got {presmooth_sigma}")
    if max_disagreement is not None and not max_disagreement >= 0.0:
        raise ValueError(f"max_disagreement must be >= 0 or None, got {max_disagreement}")
    if fallback_template_fraction is not None and not 0.0 < fallback_template_fraction < 1.0:
        raise ValueError(
            f"fallback_template_fraction must be in (0, 1) or None, got "
            f"{fallback_template_fraction}"
        )
    if presmooth_sigma > 0.0:
        prev = cv2.GaussianBlur(prev, (0, 0), presmooth_sigma, borderType=cv2.BORDER_REFLECT)
        curr = cv2.GaussianBlur(curr, (0, 0), presmooth_sigma, borderType=cv2.BORDER_REFLECT)

    primary = _register(
        prev, curr, template_fraction, max_displacement, pyramid_levels, refine_radius
    )
    if primary is None:
        return NccResult(
            dx=np.full(2, np.nan),
            score=0.0,
            dx_forward=np.full(2, np.nan),
            dx_backward=np.full(2, np.nan),
            score_forward=0.0,
            score_backward=0.0,
            consistent=False,
        )
    result, clipped = primary
    agree = max_disagreement is None or result.disagreement <= max_disagreement
    result = replace(result, consistent=agree)
    if fallback_template_fraction is None or (agree and not clipped):
        return result
    # The primary search failed its own check: the two directions disagree (a false peak in at
    # least one) or the peak is clipped at the edge of the search range (the shift is larger
    # than the 3/5 template can see, e.g. a stick-slip release). Retry with a smaller central
    # template, whose search covers +-(1 - fraction)/2 of the frame, and accept it only if its
    # own forward and backward estimates agree.
    second = _register(
        prev, curr, fallback_template_fraction, max_displacement, pyramid_levels, refine_radius
    )
    if second is None:
        return result
    retry, _ = second
    if max_disagreement is None or retry.disagreement <= max_disagreement:
        return replace(retry, consistent=True, fallback=True)
    return result


def template_problem(shape: tuple[int, int], template_fraction: float,
                     name: str = "template_fraction") -> str | None:
    """Why frames of `shape` (H, W) cannot be registered with a central template of
    `template_fraction` of their size (the option called `name`), or None when they can."""
    h, w = shape
    th, tw = int(template_fraction * h), int(template_fraction * w)
    if th < 3 or tw < 3 or th > h - 2 or tw > w - 2:
        return (f"{name}={template_fraction} gives a {th}x{tw} template for frames of shape "
                f"{tuple(shape)}; need at least 3x3 and a margin of 1 px on each side")
    return None


def _register(
    prev: np.ndarray,
    curr: np.ndarray,
    template_fraction: float,
    max_displacement: float | None,
    pyramid_levels: int,
    refine_radius: int,
) -> tuple[NccResult, bool] | None:
    """One forward + backward NCC search with a central template; None for a featureless
    template. Also returns whether either peak was clipped at the edge of the search range."""
    h, w = prev.shape
    th, tw = int(template_fraction * h), int(template_fraction * w)
    problem = template_problem(prev.shape, template_fraction)
    if problem is not None:
        raise ValueError(problem)
    oy, ox = (h - th) // 2, (w - tw) // 2
    if max_displacement is None:
        max_shift = (w - tw, h - th)
    else:
        max_shift = (int(np.ceil(max_displacement)) + 1, int(np.ceil(max_displacement)) + 1)
    levels = pyramid_levels
    while levels > 0 and min(th, tw) >> levels < _MIN_TEMPLATE_SIDE:
        levels -= 1

    template_prev = prev[oy : oy + th, ox : ox + tw]
    template_curr = curr[oy : oy + th, ox : ox + tw]
    for t in (template_prev, template_curr):
        spread = float(t.max() - t.min())
        if spread <= _FLAT_TEMPLATE_STD * max(1.0, float(np.abs(t).max())):
            return None  # featureless template: NCC is undefined (OpenCV returns 1 everywhere)

    # Forward: the template of frame i-1 at (ox, oy) is found at p in frame i; content moved by
    # p - origin = -dx.
    # Backward: the template of frame i is found at p' in frame i-1; content moved by
    # p' - origin = +dx.
    backward = (prev, template_curr, (ox, oy), max_shift, levels, refine_radius)
    pending = None if _SECOND is None else _SECOND.submit(_find_template, *backward)
    pos_f, score_f, clip_f = _find_template(
        curr, template_prev, (ox, oy), max_shift, levels, refine_radius
    )
    dx_f = np.array([ox, oy], dtype=np.float64) - pos_f
    pos_b, score_b, clip_b = (_find_template(*backward) if pending is None
                              else pending.result())
    dx_b = pos_b - np.array([ox, oy], dtype=np.float64)
    if max_displacement is not None:
        # The search window is rounded outward to whole pixels; enforce the stated bound.
        dx_f = np.clip(dx_f, -max_displacement, max_displacement)
        dx_b = np.clip(dx_b, -max_displacement, max_displacement)
    result = NccResult(
        dx=0.5 * (dx_f + dx_b),
        score=0.5 * (score_f + score_b),
        dx_forward=dx_f,
        dx_backward=dx_b,
        score_forward=score_f,
        score_backward=score_b,
    )
    # A user-set max_displacement is a deliberate bound, not a reason for a wider search.
    return result, (clip_f or clip_b) and max_displacement is None


def structural_similarity(
    a: np.ndarray, b: np.ndarray, *, data_range: float, win_size: int = 7
) -> float:
    """Mean SSIM of two same-shape float images, OpenCV box filters.

    Numerically the same as ``skimage.metrics.structural_similarity(a, b, data_range=...)`` with
    its defaults (uniform ``win_size`` window, K1=0.01, K2=0.03, sample covariance, mean over the
    image minus a ``(win_size-1)/2`` border), about 5-10x faster because ``cv2.boxFilter``
    replaces ``scipy.ndimage.uniform_filter`` on float32.
    """
    if a.shape != b.shape or a.ndim != 2:
        raise ValueError(
            f"structural_similarity: need two 2-D images of one shape, got {a.shape} and {b.shape}"
        )
    if min(a.shape) < win_size:
        raise ValueError(
            f"structural_similarity: images of shape {a.shape} are smaller than "
            f"the {win_size}x{win_size} window"
        )
    a, b = _float32_rows(a), _float32_rows(b)
    pad = (win_size - 1) // 2
    h = a.shape[0]
    if _SECOND is None or h < 64:
        return _ssim_sum(a, b, data_range, win_size) / ((h - 2 * pad) * (a.shape[1] - 2 * pad))
    # Two slabs of rows on two threads (the box filters and numpy's arithmetic release the
    # GIL). A slab carries `pad` rows of its neighbour, so that the rows it scores see real
    # pixels only (the image border is excluded from the mean anyway): the same sum.
    mid = h // 2
    upper = _SECOND.submit(_ssim_sum, a[: mid + pad], b[: mid + pad], data_range, win_size)
    lower = _ssim_sum(a[mid - pad:], b[mid - pad:], data_range, win_size)
    return (upper.result() + lower) / ((h - 2 * pad) * (a.shape[1] - 2 * pad))


def _float32_rows(x: np.ndarray) -> np.ndarray:
    """x as float32 whose rows are contiguous: a slice of a float32 image (an overlap) is used as
    it is, OpenCV and numpy read it through its strides (the same numbers as a copy)."""
    x = np.asarray(x, dtype=np.float32)
    if x.strides[1] == x.itemsize and x.strides[0] > 0:
        return x
    return np.ascontiguousarray(x)


def _ssim_sum(a: np.ndarray, b: np.ndarray, data_range: float, win_size: int) -> float:
    """Sum of the SSIM map of float32 images a, b without its (win_size - 1) / 2 border."""
    # float32 is enough: the second-moment rounding error (~1e-7 * range^2) is far below the
    # stabilising constant c2 = (0.03 * range)^2. The arithmetic is done in place on six
    # buffers: at 512x448 fresh temporaries (page faults) cost more than the arithmetic.
    k = (win_size, win_size)
    border = cv2.BORDER_REFLECT  # = scipy.ndimage "reflect", skimage's mode

    def box(x: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(x, cv2.CV_32F, k, borderType=border)

    n = win_size * win_size
    cov_norm = n / (n - 1.0)  # sample covariance, as skimage's use_sample_covariance=True
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    mu_a, mu_b = box(a), box(b)
    t = np.multiply(a, a)
    s_aa = box(t)
    s_bb = box(np.multiply(b, b, out=t))
    s_ab = box(np.multiply(a, b, out=t))
    np.multiply(mu_a, mu_b, out=t)
    s_ab -= t  # E[ab] - mu_a mu_b
    s_ab *= 2.0 * cov_norm
    s_ab += c2  # 2 cov_ab + c2
    t *= 2.0
    t += c1  # 2 mu_a mu_b + c1
    t *= s_ab  # numerator
    np.multiply(mu_a, mu_a, out=mu_a)
    np.multiply(mu_b, mu_b, out=mu_b)
    s_aa -= mu_a
    s_bb -= mu_b
    s_aa += s_bb
    s_aa *= cov_norm
    s_aa += c2  # var_a + var_b + c2
    mu_a += mu_b
    mu_a += c1  # mu_a^2 + mu_b^2 + c1
    mu_a *= s_aa  # denominator
    ssim_map = np.divide(t, mu_a, out=t)
    pad = (win_size - 1) // 2
    return float(ssim_map[pad:-pad, pad:-pad].sum(dtype=np.float64))


def aligned_overlap_ssim(
    previous: np.ndarray,
    current: np.ndarray,
    dx: np.ndarray,
    *,
    data_range: float | None = None,
    downsample: int = 1,
    min_overlap: int = 16,
    prepared: bool = False,
) -> float:
    """Matching confidence ``c_match`` (paper 004, Sec. II-C): SSIM of the aligned overlap.

    ``current`` is aligned on ``previous`` with the displacement ``dx`` of :func:`register_ncc`
    (pixel ``p`` of ``previous`` matches pixel ``p - dx`` of ``current``), rounded to whole
    pixels: a residual shift of <= 0.5 px barely changes SSIM on cell-scale pCLE texture and
    avoids an interpolation (which would itself smooth the noise SSIM is meant to see). The
    overlap is scored with :func:`structural_similarity` (skimage's SSIM definition, computed with
    OpenCV box filters for speed) and clipped to [0, 1].

    Parameters
    ----------
    previous, current : (H, W) uint8 or float, same shape
    dx : (2,) displacement (dx, dy) in pixels; non-finite gives 0.0.
    data_range : float or None
        Dynamic range for the SSIM constants; ``None`` = 255 for uint8 inputs, else the
        max - min over both overlaps.
    downsample : int
        Integer factor (area averaging) applied to the overlap before SSIM; 1 = full resolution.
        A factor of 2 is ~4x cheaper but ignores the finest (pixel-level) noise.
    min_overlap : int
        Overlap narrower than this (pixels, per axis) gives 0.0.
    prepared : bool
        As in :func:`register_ncc`: both frames are already 2-D float32 with finite pixels, used
        as they are. Their source type is then unknown: give ``data_range=255`` for frames that
        were uint8.
    """
    prev_in, curr_in = np.asarray(previous), np.asarray(current)
    prev, curr = _check_pair(prev_in, curr_in, prepared)
    dx = np.asarray(dx, dtype=np.float64)
    if dx.shape != (2,):
        raise ValueError(f"dx: expected shape (2,), got {dx.shape}")
    if downsample < 1:
        raise ValueError(f"downsample must be >= 1, got {downsample}")
    if not np.isfinite(dx).all():
        return 0.0
    h, w = prev.shape
    sx, sy = int(np.rint(dx[0])), int(np.rint(dx[1]))
    x0, x1 = max(0, sx), min(w, w + sx)
    y0, y1 = max(0, sy), min(h, h + sy)
    if x1 - x0 < min_overlap or y1 - y0 < min_overlap:
        return 0.0
    a = prev[y0:y1, x0:x1]
    b = curr[y0 - sy : y1 - sy, x0 - sx : x1 - sx]
    if downsample > 1:
        size = ((x1 - x0) // downsample, (y1 - y0) // downsample)
        if min(size) < 7:
            return 0.0
        a = cv2.resize(a, size, interpolation=cv2.INTER_AREA)
        b = cv2.resize(b, size, interpolation=cv2.INTER_AREA)
    if data_range is None:
        if prev_in.dtype == np.uint8 and curr_in.dtype == np.uint8:
            data_range = 255.0
        else:
            data_range = float(max(a.max(), b.max()) - min(a.min(), b.min()))
    if not data_range > 0.0:
        return 0.0  # both overlaps constant and equal in value: no structure to compare
    return float(np.clip(structural_similarity(a, b, data_range=data_range), 0.0, 1.0))


def gray_from_color(image) -> np.ndarray:
    """(H, W, 3) BGR or (H, W, 4) BGRA -> (H, W) gray (OpenCV weights; other dtypes via
    float32); any other array is returned as is (callers check its shape)."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        if image.dtype not in (np.uint8, np.uint16, np.float32):
            image = image.astype(np.float32)
        image = cv2.cvtColor(image, code)
    return image


def fixed_pattern_gain(frames, *, floor: float = 0.05) -> np.ndarray:
    """Per-pixel gain of a fibre bundle's fixed pattern, float32 (H, W): the mean of a
    recording's frames (gray, BGR or BGRA) scaled to mean 1; pixels whose mean is below
    ``floor`` (no signal, e.g. outside a circular field of view) get gain 0, which
    :func:`flat_field` turns into 0 instead of amplifying their noise. The tissue must move
    across the recording for it to average out; frames of differing sizes or fewer than two
    raise ValueError."""
    total, count = None, 0
    for k, frame in enumerate(frames):
        gray = _as_gray_float32(gray_from_color(frame), f"frame {k}")
        if total is None:
            total = np.zeros(gray.shape, np.float64)
        elif gray.shape != total.shape:
            raise ValueError(f"frame {k}: {gray.shape[1]}x{gray.shape[0]} differs from frame 0's "
                             f"{total.shape[1]}x{total.shape[0]}; no common fixed pattern")
        total += gray
        count += 1
    if count < 2:
        raise ValueError(f"the fixed pattern is the mean of a recording's frames: got {count} "
                         "frame(s), need at least 2 (over which the tissue moves)")
    mean = total / count
    level = float(mean.mean())
    if not level > 0.0:
        raise ValueError("the fixed pattern is the mean of the frames, and they are all black")
    gain = mean / level
    return np.where(gain >= floor, gain, 0.0).astype(np.float32)


def flat_field(image: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """image / gain (flat-field correction), 0 where the gain is 0; uint8 stays uint8
    (rounded, clipped to 0..255) so that SSIM keeps its 8-bit constants, anything else becomes
    float32."""
    if image.shape != gain.shape:
        raise ValueError(f"image {image.shape} and fixed-pattern gain {gain.shape} differ in size")
    out = np.zeros(image.shape, np.float32)
    np.divide(image.astype(np.float32), gain, out=out, where=gain > 0)
    if image.dtype == np.uint8:
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)
    return out
