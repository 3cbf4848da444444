"""Seeded procedural textures for the simulators (no downloads).

- :func:`placenta_texture`: a large, low-contrast, reddish placenta-like surface with a branching
  vessel tree, capillaries and low-frequency shading (the imaged plane of the fetoscopy SYN
  replica, paper 000 Sec. 4.1, which cut frames out of "a large image representing the plane").
- :func:`cell_texture`: a pCLE-like tissue at ~1 µm/px, bright cell borders and nuclei on a dark
  background (paper 004 Sec. IV-B: "cell nuclei (which are typically seen in Cellvizio images)").
- :func:`fibre_bundle_pattern`: a honeycomb of fibre cores (~3 px spacing, paper 004 Sec. III-B:
  a 30,000-fibre bundle over a 512x448 image) used for the pCLE look and for contact-loss noise.

All randomness comes from the ``numpy.random.Generator`` passed in, so a seed gives one image.
"""

from __future__ import annotations

import cv2
import numpy as np

_SHIFT = 4  # cv2 drawing sub-pixel bits: coordinates are passed as round(x * 16)


def _shape2(size) -> tuple[int, int]:
    """(height, width) from an int (square) or a (height, width) pair."""
    if np.isscalar(size):
        h = w = int(size)
    else:
        h, w = (int(s) for s in size)
    if h < 8 or w < 8:
        raise ValueError(f"texture size must be at least 8x8 px, got {w}x{h}")
    return h, w


# smooth_noise upsamples a grid padded by 2 features on every side: an intermediate of
# (h + 4 scale) (w + 4 scale) floats, about 4 h w for a square texture and scale max(h, w) / 4.
# An elongated texture (48 x 340000 px: 2.7e11 bytes, review 44) makes the pad of its short
# side huge: beyond SMOOTH_NOISE_MAX_PADDING x h w floats, only the rows and columns kept are
# interpolated (_cubic_crop; the same bicubic to float rounding).
SMOOTH_NOISE_MAX_PADDING = 16.0


def smooth_noise(shape: tuple[int, int], scale_px: float, rng: np.random.Generator) -> np.ndarray:
    """Zero-mean, unit-std float32 noise with features of about ``scale_px`` pixels.

    White noise on a grid ``scale_px`` times coarser, bicubically upsampled (much cheaper than a
    large Gaussian blur of full-size noise)."""
    h, w = shape
    scale = max(float(scale_px), 1.0)
    gh, gw = int(np.ceil(h / scale)) + 4, int(np.ceil(w / scale)) + 4
    coarse = rng.standard_normal((gh, gw)).astype(np.float32)
    if scale > 1.5:  # soften the grid before upsampling (cheap at the coarse resolution)
        coarse = cv2.GaussianBlur(coarse, (0, 0), 0.6)
    big_w, big_h = int(round(gw * scale)), int(round(gh * scale))
    o = int(round(2 * scale))
    if big_w * big_h <= SMOOTH_NOISE_MAX_PADDING * h * w:
        big = cv2.resize(coarse, (big_w, big_h), interpolation=cv2.INTER_CUBIC)
        out = big[o : o + h, o : o + w]
    else:
        out = _cubic_crop(coarse, (big_h, big_w), (o, o), (h, w))
    out = out - out.mean()
    return out / max(float(out.std()), 1e-6)


def smooth_noise_floats(shape: tuple[int, int], scale_px: float) -> float:
    """The floats smooth_noise's upsampled intermediate holds (its largest allocation)."""
    h, w = shape
    scale = max(float(scale_px), 1.0)
    gh, gw = int(np.ceil(h / scale)) + 4, int(np.ceil(w / scale)) + 4
    full = round(gw * scale) * round(gh * scale)
    return float(full if full <= SMOOTH_NOISE_MAX_PADDING * h * w else h * w + h * gw)


def _cubic_taps(n_src: int, n_dst: int, start: int, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(count, 4) source indices and weights of cv2.resize's INTER_CUBIC (A = -0.75, pixel
    centres aligned, border replicated) for destination samples start .. start + count - 1 of
    an n_src -> n_dst resize."""
    x = (np.arange(start, start + count) + 0.5) * (n_src / n_dst) - 0.5
    i = np.floor(x)
    t = x - i
    a = -0.75
    w0 = ((a * (t + 1) - 5 * a) * (t + 1) + 8 * a) * (t + 1) - 4 * a
    w1 = ((a + 2) * t - (a + 3)) * t * t + 1
    w2 = ((a + 2) * (1 - t) - (a + 3)) * (1 - t) * (1 - t) + 1
    weights = np.stack([w0, w1, w2, 1.0 - w0 - w1 - w2], 1)
    index = np.clip(i[:, None].astype(np.int64) + np.arange(-1, 3), 0, n_src - 1)
    return index, weights


def _cubic_crop(coarse: np.ndarray, size: tuple[int, int], origin: tuple[int, int],
                shape: tuple[int, int]) -> np.ndarray:
    """cv2.resize(coarse, size[::-1], INTER_CUBIC)[y0:y0 + h, x0:x0 + w] without the rest of
    the resized image: rows then columns, float32 (origin (y0, x0), shape (h, w))."""
    (big_h, big_w), (y0, x0), (h, w) = size, origin, shape
    iy, wy = _cubic_taps(coarse.shape[0], big_h, y0, h)
    ix, wx = _cubic_taps(coarse.shape[1], big_w, x0, w)
    rows = np.einsum("ik,ikj->ij", wy.astype(np.float32), coarse[iy])  # (h, gw)
    out = np.zeros((h, w), np.float32)
    for k in range(4):
        out += wx[:, k].astype(np.float32) * rows[:, ix[:, k]]
    return out


# --------------------------------------------------------------------------------------------
# Placenta
# --------------------------------------------------------------------------------------------


def _grow_vessels(
    rng: np.random.Generator,
    shape: tuple[int, int],
    root_width: float,
    root_spacing: float,
    segments_per_root: int,
) -> list[tuple]:
    """Segments (x0, y0, x1, y1, width) of recursively branching vessel trees.

    Roots sit on a jittered grid ``root_spacing`` apart (so vessels cover the whole surface), each
    with 2-3 trunks. A branch walks in steps of 2 px with a smoothly varying turning rate (an
    Ornstein-Uhlenbeck process, so bends are gentle), tapers, and ends in a bifurcation whose
    children are thinner (width ratios 0.55-0.85) and turn away from each other; big vessels
    also shed thin side branches. Each root has its own segment budget.
    """
    h, w = shape
    segments: list[tuple] = []
    margin = 3.0 * root_width
    roots = _jittered_grid((h, w), root_spacing, 0.25, rng)
    roots = roots[
        (roots[:, 0] > -0.3 * root_spacing)
        & (roots[:, 0] < w + 0.3 * root_spacing)
        & (roots[:, 1] > -0.3 * root_spacing)
        & (roots[:, 1] < h + 0.3 * root_spacing)
    ]
    for rx, ry in roots:
        heading0 = rng.uniform(-np.pi, np.pi)
        stack = [
            (
                rx,
                ry,
                heading0 + 2.0 * np.pi * k / 3.0 + rng.normal(0, 0.3),
                root_width * rng.uniform(0.7, 1.1),
                0,
            )
            for k in range(int(rng.integers(2, 4)))
        ]
        budget = len(segments) + segments_per_root
        while stack and len(segments) < budget:
            x, y, heading, width, depth = stack.pop(0)  # breadth-first: budget cuts the leaves
            length = width * rng.uniform(12.0, 26.0) + rng.uniform(20.0, 50.0)
            end_width = 0.85 * width
            step = 2.0
            n_steps = max(int(length / step), 2)
            turn = rng.normal(0.0, 0.5 / (length + 20.0))
            for i in range(n_steps):
                turn = 0.9 * turn + rng.normal(0.0, 0.25 / (8.0 * width + 40.0))
                heading += turn * step
                wi = width + (end_width - width) * i / n_steps
                nx, ny = x + step * np.cos(heading), y + step * np.sin(heading)
                segments.append((x, y, nx, ny, wi))
                x, y = nx, ny
                if not (-margin < x < w + margin and -margin < y < h + margin):
                    break
                if width > 2.5 and rng.random() < 0.01:  # thin side branch
                    side = heading + rng.choice([-1.0, 1.0]) * rng.uniform(0.8, 1.4)
                    stack.append((x, y, side, width * rng.uniform(0.3, 0.5), depth + 1))
            else:
                if end_width * 0.55 >= 0.7 and depth < 12:
                    split = rng.uniform(0.25, 0.9)
                    ratio = rng.uniform(0.65, 0.85)
                    stack.append(
                        (
                            x,
                            y,
                            heading + split * rng.uniform(0.4, 0.7),
                            end_width * ratio,
                            depth + 1,
                        )
                    )
                    stack.append(
                        (
                            x,
                            y,
                            heading - split * rng.uniform(0.5, 1.0),
                            end_width * rng.uniform(0.55, ratio),
                            depth + 1,
                        )
                    )
    return segments


def _draw_segments(mask: np.ndarray, segments, scale: float, width_gain: float = 1.0) -> None:
    """Anti-aliased thick lines into a uint8 mask drawn at ``scale`` x the texture resolution."""
    f = float(1 << _SHIFT) * scale
    for x0, y0, x1, y1, wd in segments:
        thickness = max(int(round(wd * width_gain * scale)), 1)
        cv2.line(
            mask,
            (int(round(x0 * f)), int(round(y0 * f))),
            (int(round(x1 * f)), int(round(y1 * f))),
            255,
            thickness,
            cv2.LINE_AA,
            _SHIFT,
        )


# placenta_texture's cost, measured on a 2-core x86 machine (2000 x 2000 px: 7.9 s with 9 px
# vessels, 15 s with 27 px: each 2 px step of a vessel is its own thick anti-aliased line, so
# thick vessels are drawn over and over): seconds per pixel, per pixel and px of vessel width,
# per float of smooth_noise's intermediates; bytes per pixel (peak RSS) and per float.
_COST_S_PER_PX = 0.8e-6
_COST_S_PER_PX_WIDTH = 0.1e-6
_COST_S_PER_FLOAT = 0.04e-6
_COST_BYTES_PER_PX = 75.0


def placenta_texture_cost(size_px, vessel_width_px: float = 9.0) -> tuple[float, float]:
    """(seconds, GB): an estimate of what placenta_texture(size_px, vessel_width_px=...) takes
    to draw and its peak memory, for refusing sizes before drawing them (linear in the pixels,
    with the vessels' overdraw growing with their width)."""
    h, w = _shape2(size_px)
    px = float(h) * float(w)
    floats = [smooth_noise_floats((h, w), scale)
              for scale in (max(h, w) / 6.0, 60.0, 7.0, 2.5, max(h, w) / 4.0)]
    seconds = (_COST_S_PER_PX * px + _COST_S_PER_PX_WIDTH * px * max(vessel_width_px, 1.0)
               + _COST_S_PER_FLOAT * sum(floats))
    return seconds, (_COST_BYTES_PER_PX * px + 4.0 * max(floats)) / 1e9


def placenta_texture(
    size_px,
    rng: np.random.Generator,
    *,
    vessel_width_px: float = 9.0,
    root_spacing_px: float = 450.0,
    vessel_contrast: float = 0.45,
    detail_contrast: float = 0.115,
    color_bgr: tuple[float, float, float] = (70.0, 100.0, 190.0),
) -> np.ndarray:
    """Placenta-like surface, (H, W, 3) BGR uint8.

    size_px : int (square) or (height, width).
    vessel_width_px : width of the root vessels; branches taper down to ~1 px.
    root_spacing_px : distance between vessel-tree roots (each with 2-3 trunks).
    vessel_contrast : darkening of vessels relative to the background (0..1), low by design.
    detail_contrast : relative amplitude of the fine mottling (villi/capillary-bed texture).
    color_bgr : mean background colour.

    Layers: low-frequency shading (+-8 %) and hue drift, mid/fine mottling, a vessel tree of two
    families (darker "veins", lighter "arteries") with a faint centre-line reflex, and many thin
    wiggly capillaries. Enough texture for SIFT/ORB everywhere, but low contrast, as in fetoscopy.
    """
    h, w = _shape2(size_px)

    # Background: luminance shading, colour drift, mottling at two scales.
    shading = 1.0 + 0.08 * smooth_noise((h, w), max(h, w) / 6.0, rng)
    shading += 0.05 * smooth_noise((h, w), 60.0, rng)
    mottle = detail_contrast * (
        0.6 * smooth_noise((h, w), 7.0, rng) + 0.4 * smooth_noise((h, w), 2.5, rng)
    )
    hue = 0.06 * smooth_noise((h, w), max(h, w) / 4.0, rng)
    base = np.asarray(color_bgr, np.float32)
    img = np.empty((h, w, 3), np.float32)
    lum = shading * (1.0 + mottle)
    img[..., 0] = base[0] * lum * (1.0 - hue)
    img[..., 1] = base[1] * lum * (1.0 - 0.5 * hue)
    img[..., 2] = base[2] * lum * (1.0 + 0.3 * hue)

    # Vessel trees drawn at 2x and area-downsampled for sub-pixel widths.
    ss = 2
    big = (h * ss, w * ss)
    families = [  # (colour BGR, contrast gain, fraction of roots)
        (np.array([45.0, 40.0, 110.0], np.float32), 1.0),
        (np.array([60.0, 55.0, 150.0], np.float32), 0.7),
    ]
    for fam, (vcolor, gain) in enumerate(families):
        segments = _grow_vessels(
            rng,
            (h, w),
            vessel_width_px * (1.0 if fam == 0 else 0.8),
            root_spacing_px * (1.0 if fam == 0 else 1.3),
            5000,
        )
        body = np.zeros(big, np.uint8)
        core = np.zeros(big, np.uint8)
        _draw_segments(body, segments, ss)
        _draw_segments(core, [s for s in segments if s[4] > 3.0], ss, width_gain=0.25)
        body_f = cv2.resize(body, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
        core_f = cv2.resize(core, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
        body_f = cv2.GaussianBlur(body_f, (0, 0), 0.8)
        alpha = (vessel_contrast * gain * body_f)[..., None]
        img = img * (1.0 - alpha) + (vcolor * shading[..., None]) * alpha
        img += (18.0 * gain * vessel_contrast * cv2.GaussianBlur(core_f, (0, 0), 0.7))[..., None]

    # Capillaries: many short thin wiggly vessels of low contrast.
    cap = np.zeros(big, np.uint8)
    n_cap = int(h * w / 1800)
    f = float(1 << _SHIFT) * ss
    for _ in range(n_cap):
        x, y = rng.uniform(0, w), rng.uniform(0, h)
        heading = rng.uniform(-np.pi, np.pi)
        pts = []
        for _i in range(int(rng.integers(6, 18))):
            pts.append((int(round(x * f)), int(round(y * f))))
            heading += rng.normal(0.0, 0.45)
            x += 2.5 * np.cos(heading)
            y += 2.5 * np.sin(heading)
        cv2.polylines(cap, [np.array(pts, np.int32)], False, 255, 1, cv2.LINE_AA, _SHIFT)
    cap_f = cv2.resize(cap, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    alpha = (0.5 * vessel_contrast * cap_f)[..., None]
    img = img * (1.0 - alpha) + np.array([55.0, 50.0, 140.0], np.float32) * alpha

    # Small light and dark spots (villi tips, fibrin, pigment): blob features for SIFT/ORB.
    for sigma, density, amp in ((1.3, 1.0 / 250.0, 2.5), (2.6, 1.0 / 1200.0, 1.5)):
        n_spots = int(h * w * density)
        pts = np.column_stack([rng.uniform(0, w, n_spots), rng.uniform(0, h, n_spots)])
        vals = rng.choice([-1.0, 1.0], n_spots, p=[0.6, 0.4]) * rng.uniform(0.5, 1.0, n_spots)
        spots = cv2.GaussianBlur(_splat((h, w), pts, vals), (0, 0), sigma)
        spots *= amp * detail_contrast * 2.0 * np.pi * sigma**2 / 2.0
        img *= (1.0 + spots)[..., None]

    img += rng.normal(0.0, 1.5, size=(h, w, 1)).astype(np.float32)  # film grain
    return np.clip(img, 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------------------------
# pCLE
# --------------------------------------------------------------------------------------------


def _jittered_grid(
    shape: tuple[int, int],
    spacing: float,
    jitter: float,
    rng: np.random.Generator,
    hexagonal: bool = False,
) -> np.ndarray:
    """(P, 2) points (x, y) of a jittered square or hexagonal lattice covering ``shape``."""
    h, w = shape
    dy = spacing * (np.sqrt(3.0) / 2.0 if hexagonal else 1.0)
    ys = np.arange(-1, int(np.ceil(h / dy)) + 2) * dy
    xs = np.arange(-1, int(np.ceil(w / spacing)) + 2) * spacing
    gx, gy = np.meshgrid(xs, ys)
    if hexagonal:
        gx = gx + (np.arange(ys.size)[:, None] % 2) * (spacing / 2.0)
    pts = np.stack([gx.ravel(), gy.ravel()], axis=1)
    pts += rng.normal(0.0, jitter * spacing, size=pts.shape)
    return pts


def _splat(shape: tuple[int, int], pts: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Bilinear splat of point values into a float32 image (sub-pixel point positions)."""
    h, w = shape
    out = np.zeros(h * w, np.float64)
    x0 = np.floor(pts[:, 0]).astype(np.int64)
    y0 = np.floor(pts[:, 1]).astype(np.int64)
    fx, fy = pts[:, 0] - x0, pts[:, 1] - y0
    for dx, dy, wt in (
        (0, 0, (1 - fx) * (1 - fy)),
        (1, 0, fx * (1 - fy)),
        (0, 1, (1 - fx) * fy),
        (1, 1, fx * fy),
    ):
        xi, yi = x0 + dx, y0 + dy
        ok = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
        np.add.at(out, yi[ok] * w + xi[ok], values[ok] * wt[ok])
    return out.reshape(h, w).astype(np.float32)


def fibre_bundle_pattern(
    shape,
    rng: np.random.Generator,
    *,
    spacing_px: float = 3.0,
    core_sigma_px: float = 0.65,
    jitter: float = 0.08,
) -> np.ndarray:
    """Honeycomb of fibre cores, (H, W) float32 in [0, 1] (max 1).

    shape : (height, width) or int. Cores sit on a jittered hexagonal lattice ``spacing_px``
    apart (about 30,000 cores in 512x448 at 3 px, as in the Z1800 probe, paper 004 Sec. III-B),
    each a Gaussian spot with its own transmission gain (0.55-1.0).
    """
    h, w = _shape2(shape)
    pts = _jittered_grid((h, w), spacing_px, jitter, rng, hexagonal=True)
    gains = rng.uniform(0.55, 1.0, size=len(pts))
    img = _splat((h, w), pts, gains)
    img = cv2.GaussianBlur(img, (0, 0), core_sigma_px)
    return img / max(float(img.max()), 1e-6)


def cell_texture(
    shape,
    rng: np.random.Generator,
    *,
    cell_size_px: float = 12.0,
    border_brightness: float = 0.8,
    nucleus_brightness: float = 0.7,
    nuclei: bool = True,
    background: float = 0.08,
) -> np.ndarray:
    """pCLE-like tissue, (H, W) gray uint8, at ~1 µm/px.

    shape : (height, width) or int. Cells are Voronoi regions of a jittered lattice of centres
    ``cell_size_px`` apart; their borders are bright (fluorescent interstitium), each cell has a
    faint cytoplasm level and, with ``nuclei``, a bright blurred nucleus near its centre. A
    low-frequency modulation varies the staining across the tissue. Background is dark.
    """
    h, w = _shape2(shape)
    centres = _jittered_grid((h, w), cell_size_px, 0.22, rng)
    inside = (centres[:, 0] >= 0) & (centres[:, 0] < w) & (centres[:, 1] >= 0) & (centres[:, 1] < h)
    centres = centres[inside]

    # Voronoi labels: distance transform from the centre pixels, labelled by nearest centre.
    seeds = np.full((h, w), 255, np.uint8)
    ci = np.clip(np.round(centres).astype(np.int64), 0, [w - 1, h - 1])
    seeds[ci[:, 1], ci[:, 0]] = 0
    dist, labels = cv2.distanceTransformWithLabels(
        seeds, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
    )
    border = np.zeros((h, w), np.float32)
    border[:, :-1] += labels[:, :-1] != labels[:, 1:]
    border[:-1, :] += labels[:-1, :] != labels[1:, :]
    border = cv2.GaussianBlur(np.minimum(border, 1.0), (0, 0), 0.9)
    border /= max(float(border.max()), 1e-6)

    n_labels = int(labels.max()) + 1
    cytoplasm = rng.uniform(0.0, 0.25, size=n_labels).astype(np.float32)[labels]
    cell_gain = rng.uniform(0.6, 1.0, size=n_labels).astype(np.float32)[labels]
    # Cytoplasm slightly brighter towards the border (membrane staining).
    rim = np.clip(dist / (0.5 * cell_size_px), 0.0, 1.0).astype(np.float32)
    img = background + cytoplasm * (0.5 + 0.5 * rim) + border_brightness * border * cell_gain

    if nuclei:
        offsets = rng.normal(0.0, 0.12 * cell_size_px, size=centres.shape)
        amps = rng.uniform(0.5, 1.0, size=len(centres)) * (rng.random(len(centres)) < 0.85)
        nuc = _splat((h, w), centres + offsets, amps)
        sigma = 0.16 * cell_size_px
        nuc = cv2.GaussianBlur(nuc, (0, 0), sigma) * (2.0 * np.pi * sigma**2)
        img += nucleus_brightness * np.clip(nuc, 0.0, 1.2)

    stain = 1.0 + 0.25 * smooth_noise((h, w), 120.0, rng) + 0.08 * smooth_noise((h, w), 25.0, rng)
    img *= np.clip(stain, 0.3, None)
    return np.clip(img * 200.0, 0, 255).astype(np.uint8)
