"""Blending frames into a canvas: `linear`, `multiband`, `average`, `last`, and gain compensation.

* `linear` (seed 000, Sec. 4.2, after Szeliski's feathering): each frame's pixels are weighted by
  their distance to the edge of its field of view, so seams fade; optionally each frame carries
  the paper's thin black border along its field-of-view edge, to show where it was stitched.
* `multiband` (seed 000, Sec. 4.2, Burt & Adelson / Brown & Lowe): every canvas pixel is given to
  the frame whose field-of-view centre is nearest (largest feathering weight), and these seam masks
  are blended band by band over a Laplacian pyramid; high frequencies switch sharply, low ones
  smoothly. Own float32 pyramids: OpenCV's MultiBandBlender accumulates in int16 and darkens
  pixels near mask edges by a few grey levels, which the accuracy tests would see.
* `average` (seed 004, Sec. III-D): the mean of every frame pixel that lands on a canvas pixel.
* `last`: the newest frame on top.

Frames are warped one at a time into a `Patch` that covers only the frame's own footprint, in
reference pixels (the canvas of frame 0's pixel grid); a canvas region then accumulates patches.
The patch stores colour premultiplied by the weight and the weight itself, so interpolating at the
footprint's edge never mixes in the black outside the frame, and black field-of-view corners carry
zero weight: they never paint over tissue.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

BLENDS = ("linear", "multiband", "average", "last")
COVERED = 1e-3  # total weight below which a canvas pixel counts as empty (background)
# A highlight pixel's weight, relative to its frame's (BlendOptions.mask_specular): low enough
# that a frame seeing the tissue there wins (linear: 1 % of white, ~2 grey levels, per frame
# whose highlight covers it; last: not painted; multiband: not owned), not zero, so a spot no
# other frame sees is still shown (linear, average, multiband).
SPECULAR_WEIGHT = 0.01
# ... and at least this, so the spot counts as covered (COVERED) even near its frame's edge,
# where the feathering weight is small: a spot no other frame sees is no hole in the mosaic.
SPECULAR_FLOOR = 2 * COVERED
# SpecularMasks keeps at most this many bytes of masks (1 bit per pixel of each mask's bounding
# box): the simulator's 3 lights took 0.46 kB per frame (hand-held runs, 60 frames of 400x400:
# 27.5 kB, 40 of 720x576: 18.4 kB; a full-size uint8 mask is 160 / 415 kB), a mask covering a
# whole 720x576 frame would take 52 kB: 64 MB hold ~140 000 such runs' frames, ~1 250 of the
# worst case; the frames beyond are found again (as before SpecularMasks).
SPECULAR_CACHE_BYTES = 64 * 2**20


@dataclass
class BlendOptions:
    """How frames are blended (CLI: ``fusedmosaic run --blend --border --bands --gain``)."""

    blend: str | None = "linear"  # seed 000 Sec. 4.2: linear shows misregistrations; None: method
    border_px: float = 0.0  # seed 000 Sec. 4.2: "thin circular black border in each image"; 0 off
    bands: int = 5  # multiband pyramid levels below full resolution (OpenCV's stitching default)
    gain_compensation: bool = False  # Brown & Lowe (2007) Sec. 6: one gain per frame
    # Specular highlights (registration.features.specular_mask: saturated white spots fixed to
    # the camera) weigh SPECULAR_WEIGHT of the frame's weight there, so any other frame showing
    # the spot paints it; otherwise each frame's highlights leave a white trail along the path.
    # None: off here, the method's choice in `fusedmosaic run` (on for the pose methods, i.e.
    # fetoscopy, MethodResult.mask_specular; off for pCLE's); run --keep-specular: False.
    mask_specular: bool | None = None

    def validate(self, names: dict[str, str] | None = None) -> None:
        """ValueError for a bad field; `names` maps fields to what the messages call them
        (e.g. the CLI's flags)."""
        name = (names or {}).get
        if self.blend not in BLENDS:
            raise ValueError(f"{name('blend', 'blend')} must be one of {', '.join(BLENDS)}; got "
                             f"{self.blend!r}")
        if not np.isfinite(self.border_px) or self.border_px < 0:
            raise ValueError(f"{name('border_px', 'border_px')} must be >= 0 (pixels), got "
                             f"{self.border_px}")
        if not 1 <= int(self.bands) <= 10:
            raise ValueError(f"{name('bands', 'bands')} must be in 1..10, got {self.bands}")


def max_bands(width: int, height: int) -> int:
    """The most multiband levels frames of this size support: log2 of the smaller side (the
    coarsest band of the frame is then about 1 px; coarser ones would only blend the padding
    around it, each band doubling the padding: 3 x 2^bands px a side)."""
    return max(1, int(np.floor(np.log2(max(1, min(int(width), int(height)))))))


def fit_bands(options: BlendOptions, width: int, height: int) -> BlendOptions:
    """`options` with multiband's bands capped at max_bands(width, height), with a warning when
    they are lowered (--bands 10 padded each 64 x 64 frame to ~7000 x 7000 float32: 3.4 s and
    1.5 GB for a two-frame mosaic); other blends as given."""
    if options.blend != "multiband":
        return options
    cap = max_bands(width, height)
    if int(options.bands) <= cap:
        return options
    import warnings

    warnings.warn(f"multiband bands (--bands) {int(options.bands)} is more than {width}x{height} "
                  f"frames support (log2 of the smaller side: {cap}); blending with {cap} "
                  "bands", stacklevel=3)
    return replace(options, bands=cap)


def check_frame_dtype(image: np.ndarray, name) -> None:
    """ValueError unless `image` is uint8: frames are not rescaled, so a 16-bit one saturates
    and a 0..1 float one is black; the message says how to convert it."""
    if image.dtype != np.uint8:
        hint = ""
        if image.dtype.kind == "f":
            hint = " (0..1 floats: np.clip(np.rint(image * 255), 0, 255).astype(np.uint8))"
        elif image.dtype.kind in "iu" and image.dtype.itemsize > 1:
            hint = " (16-bit: (image >> 8).astype(np.uint8))"
        raise ValueError(f"frame {name}: image is {image.dtype}, expected uint8: the canvas "
                         f"does not guess the value range; convert it first{hint}")


def as_blend_options(blend: str | BlendOptions | None) -> BlendOptions:
    options = BlendOptions() if blend is None else (
        BlendOptions(blend=blend) if isinstance(blend, str) else blend)
    options.validate()
    return options


@dataclass
class Patch:
    """A frame warped into reference pixels: data[0, 0] is reference pixel (x0, y0).

    data: (h, w, C + 1) float32, colour premultiplied by the weight, then the weight."""

    x0: int
    y0: int
    data: np.ndarray

    @property
    def x1(self) -> int:
        return self.x0 + self.data.shape[1]

    @property
    def y1(self) -> int:
        return self.y0 + self.data.shape[0]

    @property
    def nbytes(self) -> int:
        return self.data.nbytes


class SpecularMasks:
    """The specular highlight masks (registration.features.specular_mask) of one run's frames,
    by frame index, each found once and shared by whoever needs it: frame_gains' thumbnails,
    then the warper's weights (render_mosaic / write_mosaic_png: multiband's seams and its
    patches, tiles warping a frame again). A key must stand for the same image every time.

    Each mask is kept as its bounding box, 1 bit per pixel (a frame without highlights: None),
    up to max_bytes in all; beyond, masks are found again when asked (the same masks, at the
    cost of one specular_mask each: 400x400 ~0.4 ms, 720x576 ~0.8 ms)."""

    def __init__(self, max_bytes: int = SPECULAR_CACHE_BYTES) -> None:
        self.max_bytes = int(max_bytes)
        self.nbytes = 0  # bytes of packed masks held
        self._masks: dict[int, tuple] = {}  # key -> (shape, box or None, packed bits)

    def __len__(self) -> int:
        return len(self._masks)

    def get(self, key: int, image: np.ndarray, gray: np.ndarray | None = None
            ) -> np.ndarray | None:
        """specular_mask(image, gray=gray) of the frame `key` (uint8 (H, W), 255 on the
        highlights, or None), found on its first call."""
        key = int(key)
        shape = image.shape[:2]
        entry = self._masks.get(key)
        if entry is not None and entry[0] == shape:
            return None if entry[1] is None else _unpack_mask(*entry)
        from fusedmosaic.registration.features import specular_mask

        spots = specular_mask(image, gray=gray)
        if entry is None:  # (a key seen at another size is not replaced)
            if spots is None:
                self._masks[key] = (shape, None, None)
            else:
                x, y, w, h = cv2.boundingRect(spots)
                bits = np.packbits(spots[y:y + h, x:x + w] > 0)
                if self.nbytes + bits.nbytes <= self.max_bytes:
                    self._masks[key] = (shape, (x, y, w, h), bits)
                    self.nbytes += bits.nbytes
        return spots


def highlights_of(image: np.ndarray, highlights: SpecularMasks | None = None,
                  key: int | None = None, gray: np.ndarray | None = None) -> np.ndarray | None:
    """specular_mask(image, gray=gray), through the run's SpecularMasks when it has one and the
    frame's key (found once per frame), else found here."""
    if highlights is not None and key is not None:
        return highlights.get(key, image, gray)
    from fusedmosaic.registration.features import specular_mask

    return specular_mask(image, gray=gray)


def _unpack_mask(shape: tuple[int, int], box: tuple[int, int, int, int], bits: np.ndarray
                 ) -> np.ndarray:
    x, y, w, h = box
    spots = np.zeros(shape, np.uint8)
    spots[y:y + h, x:x + w] = np.unpackbits(bits, count=w * h).reshape(h, w) * np.uint8(255)
    return spots


def fov_mask_bool(mask: np.ndarray | None, width: int, height: int) -> np.ndarray:
    """(H, W) bool field of view from a uint8 (255 = tissue) or bool mask; all True if None."""
    if mask is None:
        return np.ones((height, width), bool)
    mask = np.asarray(mask)
    if mask.ndim != 2:  # (its last two sizes were reported as W x H: "40x30 but ... 40x30")
        raise ValueError(f"field-of-view mask must be one channel (H, W), got shape "
                         f"{mask.shape}; the frames are {width}x{height}")
    if mask.shape != (height, width):
        raise ValueError(f"field-of-view mask is {mask.shape[1]}x{mask.shape[0]} but the frames "
                         f"are {width}x{height}")
    return mask > 0


def edge_distance(mask: np.ndarray) -> np.ndarray:
    """Euclidean distance (px) of each field-of-view pixel to the nearest pixel outside it, the
    image border counting as outside (1 at the edge pixels, 0 outside the field of view)."""
    padded = np.pad(mask.astype(np.uint8), 1)
    return cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]


def check_border(border_px: float, distance: np.ndarray,
                 name: str = "border (border_px, --border)") -> None:
    """ValueError if a frame border of `border_px` covers more than half the field of view whose
    edge_distance is `distance`: the border is drawn black at a frame centre's weight, so most
    of every frame, and of the mosaic, would be black. The largest border accepted is the
    median distance to the edge (for a circular field of view 0.29 of its radius)."""
    inside = distance[distance > 0]
    if inside.size == 0:
        raise ValueError("field-of-view mask is empty: no pixel would be blended")
    inner = float(inside.max())
    limit = float(np.median(inside))
    if border_px < inner and border_px <= limit:  # (ties: a median at the centre's distance)
        return
    covered = float(np.mean(inside <= border_px))
    what = ("the whole field of view" if border_px >= inner
            else f"{min(99.0, 100 * covered):.0f} % of the field of view")
    raise ValueError(f"{name} {border_px:g} covers {what} (its centre is {inner:g} px from the "
                     f"edge): the frames would be drawn {'all' if covered == 1 else 'mostly'} "
                     f"black; give {'less than' if limit == inner else 'at most'} "
                     f"{limit:g} px (a border is a thin seam, e.g. 1.5)")  # (median <= max)


def footprint_box(G: np.ndarray, width: int, height: int, align: int = 1, pad: int = 0
                  ) -> tuple[int, int, int, int] | None:
    """Integer box [x0, x1) x [y0, y1) in reference pixels holding the frame's footprint
    (pixel extent -0.5 .. W - 0.5), grown by `pad` and to multiples of `align`; None if a corner
    is behind the camera, not finite or beyond 2^62 px."""
    c = np.array([[-0.5, -0.5, 1], [width - 0.5, -0.5, 1], [width - 0.5, height - 0.5, 1],
                  [-0.5, height - 0.5, 1]]) @ np.asarray(G, np.float64).T
    if not np.isfinite(c).all() or (c[:, 2] <= 0).any():
        return None
    xy = c[:, :2] / c[:, 2:]
    if not np.abs(xy).max() < 2.0**62:  # (int64 holds the box: canvas.MAX_COORDINATE)
        return None
    x0, y0 = np.floor(xy.min(axis=0)).astype(int) - pad
    x1, y1 = np.ceil(xy.max(axis=0)).astype(int) + 1 + pad
    if align > 1:
        x0, y0 = (x0 // align) * align, (y0 // align) * align
        x1, y1 = -((-x1) // align) * align, -((-y1) // align) * align
    return int(x0), int(y0), int(x1), int(y1)


class FrameWarper:
    """Warps frames (image, frame -> reference homography) into patches with blending weights.

    The weights depend only on the frame size, the field-of-view mask and the blend, so they are
    computed once; `warp` costs one perspective warp of the frame's footprint box.
    highlights: the run's SpecularMasks (options.mask_specular), looked up by the `name` given
    to warp / warp_weight (the frame's index); None: each frame's mask found when warped."""

    def __init__(self, width: int, height: int, mask: np.ndarray | None = None,
                 options: BlendOptions | str | None = None, *,
                 highlights: SpecularMasks | None = None) -> None:
        self.options = as_blend_options(options)
        self.highlights = highlights
        self.width, self.height = int(width), int(height)
        self.mask = fov_mask_bool(mask, self.width, self.height)
        if not self.mask.any():
            raise ValueError("field-of-view mask is empty: no pixel would be blended")
        multiband = self.options.blend == "multiband"
        self.align = 2 ** int(self.options.bands) if multiband else 1
        # Multiband: the coarse bands of a frame reach ~2^(bands+1) px beyond its footprint, so
        # its patch extends that far (filled by extrapolation); OpenCV pads 3 x 2^bands too.
        self.pad = 3 * self.align if multiband else 0
        self.distance = edge_distance(self.mask)
        check_border(self.options.border_px, self.distance)
        if self.options.blend in ("linear", "multiband"):
            weight = self.distance / self.distance.max()
        else:
            weight = self.mask.astype(np.float32)
        colour_weight = weight.copy()
        if self.options.border_px > 0:
            ring = self.mask & (self.distance <= self.options.border_px)
            weight[ring] = 1.0  # the border is as strong as a frame centre: it stays visible
            colour_weight[ring] = 0.0  # ... and black
        self.weight = weight.astype(np.float32)
        self.colour_weight = colour_weight.astype(np.float32)[:, :, None]
        self.channels: int | None = None

    def _check_image(self, image: np.ndarray, name) -> np.ndarray:
        image = np.asarray(image)
        check_frame_dtype(image, name)
        if image.shape[:2] != (self.height, self.width):
            raise ValueError(f"frame {name}: image is {image.shape[1]}x{image.shape[0]}, "
                             f"expected {self.width}x{self.height}")
        channels = 1 if image.ndim == 2 else image.shape[2]
        if self.channels is None:
            self.channels = channels
        elif channels != self.channels:
            raise ValueError(f"frame {name}: {channels} channel(s), earlier frames have "
                             f"{self.channels}")
        return image.reshape(self.height, self.width, channels)

    def box(self, G: np.ndarray) -> tuple[int, int, int, int] | None:
        return footprint_box(G, self.width, self.height, self.align, self.pad)

    def _weights(self, image: np.ndarray | None, fill: bool = True, name=None
                 ) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
        """(image, weight (H, W), colour weight (H, W, 1)) of this frame: as given and the fixed
        weights, or, when the options ask and it has specular highlights, the weights lowered
        there (to SPECULAR_WEIGHT of theirs, at least SPECULAR_FLOOR inside the field of view)
        and, with `fill`, the highlights filled with the tissue around them (fill_highlights)."""
        if image is None or not self.options.mask_specular:
            return image, self.weight, self.colour_weight
        flat = image.reshape(image.shape[:2]) if image.shape[2] == 1 else image
        spots = highlights_of(flat, self.highlights, name)
        if spots is None:
            return image, self.weight, self.colour_weight
        x, y, w, h = cv2.boundingRect(spots)
        box = (slice(y, y + h), slice(x, x + w))
        on = (spots[box] > 0) & self.mask[box]
        weight, colour_weight = self.weight.copy(), self.colour_weight.copy()
        lowered = np.maximum(weight[box] * np.float32(SPECULAR_WEIGHT), np.float32(SPECULAR_FLOOR))
        weight[box][on] = lowered[on]
        colour_weight[box][on] = np.where(self.colour_weight[box][on] > 0, lowered[on, None], 0)
        return (fill_highlights(image, spots, self.mask) if fill else image, weight,
                colour_weight)

    def warp(self, image: np.ndarray, G: np.ndarray, *, gain: float = 1.0, name=None,
             box: tuple[int, int, int, int] | None = None) -> Patch | None:
        """Patch of `image` placed by G (frame -> reference); None if G is not usable.
        box: only this part of the frame's box (x0, y0, x1, y1; e.g. the part a tile needs)."""
        image = self._check_image(image, name)
        box = _clipped(self.box(G), box)
        if box is None:
            return None
        x0, y0, x1, y1 = box
        w, h = x1 - x0, y1 - y0
        channels = image.shape[2]
        image, weight, colour_weight = self._weights(image, name=name)
        if channels != 3:
            # Gray (and 4-channel) frames: the frame and its weight warped apart. OpenCV warps
            # a 2-channel array on a slower path (400x400: 3.8 ms against 1.5 ms for the two
            # apart) whose rounding differs from a 1-channel warp's (up to 4.5e-5; 5 channels
            # up to 1.1e-4), and multiband gives each canvas pixel to the frame whose weight
            # here is the largest of warp_weight's: pixels no frame owned lost their fine
            # bands (gray pCLE mosaics: 27 % of the canvas > 10 grey levels off). A 4-channel
            # warp (BGR + weight) rounds the weight as a 1-channel one
            # (test_warped_weight_is_warp_weight).
            data = np.empty((h, w, channels + 1), np.float32)
            colour = np.multiply(image, colour_weight * np.float32(gain), dtype=np.float32)
            data[:, :, :-1] = _warp(colour, G, x0, y0, w, h)
            data[:, :, -1:] = _warp(weight, G, x0, y0, w, h)
            return Patch(x0, y0, data)
        src = np.empty((self.height, self.width, channels + 1), np.float32)
        np.multiply(image, colour_weight * np.float32(gain), out=src[:, :, :-1])
        src[:, :, -1] = weight
        return Patch(x0, y0, _warp(src, G, x0, y0, w, h))

    def warp_weight(self, G: np.ndarray, image: np.ndarray | None = None, *, name=None,
                    box: tuple[int, int, int, int] | None = None) -> Patch | None:
        """Only the weight channel, as `warp` gives it (multiband seam selection): `image`
        is needed only for mask_specular, whose weights depend on the frame. box: as warp's."""
        box = _clipped(self.box(G), box)
        if box is None:
            return None
        x0, y0, x1, y1 = box
        image = None if image is None else self._check_image(image, name)
        _, weight, _ = self._weights(image, fill=False, name=name)
        return Patch(x0, y0, _warp(weight, G, x0, y0, x1 - x0, y1 - y0))


def _clipped(box, region) -> tuple[int, int, int, int] | None:
    """The frame's box cut to `region` (None: the whole box); an empty cut is an empty box at
    the region's corner (a patch of no pixels, which overlaps nothing)."""
    if box is None or region is None:
        return box
    x0, y0 = max(box[0], int(region[0])), max(box[1], int(region[1]))
    x1, y1 = min(box[2], int(region[2])), min(box[3], int(region[3]))
    if x1 <= x0 or y1 <= y0:
        return x0, y0, x0, y0
    return x0, y0, x1, y1


def fill_highlights(image: np.ndarray, spots: np.ndarray, fov: np.ndarray) -> np.ndarray:
    """A copy of `image` (H, W, C) whose pixels under `spots` (uint8, 255 = highlight) hold the
    mean of the field of view's other pixels around them (a normalised box filter reaching
    past the highlights): what the low bands of a multiband blend see there instead of white
    (it left a glow of ~7 grey levels around each frame's highlights), and what a pixel no
    other frame shows gets (at SPECULAR_WEIGHT, so only there)."""
    out = image.copy()
    contours, _ = cv2.findContours(spots, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    for contour in contours:  # each highlight in its own box, padded by its size
        x, y, w, h = cv2.boundingRect(contour)
        pad = max(w, h) + 1
        y0, y1 = max(0, y - pad), min(image.shape[0], y + h + pad)
        x0, x1 = max(0, x - pad), min(image.shape[1], x + w + pad)
        inside = spots[y0:y1, x0:x1] > 0
        valid = (~inside & fov[y0:y1, x0:x1]).astype(np.float32)
        crop = image[y0:y1, x0:x1].astype(np.float32)
        size = (2 * pad + 1, 2 * pad + 1)
        total = cv2.blur(crop * valid[:, :, None], size).reshape(crop.shape)
        count = cv2.blur(valid, size)[:, :, None]
        fill = np.divide(total, count, out=np.zeros_like(total), where=count > 1e-6)
        out[y0:y1, x0:x1][inside] = np.clip(np.rint(fill[inside]), 0, 255).astype(image.dtype)
    return out


def _warp(src: np.ndarray, G: np.ndarray, x0: int, y0: int, w: int, h: int) -> np.ndarray:
    if w <= 0 or h <= 0:  # (OpenCV takes a size of 0 for the source's)
        return np.zeros((max(h, 0), max(w, 0), 1 if src.ndim == 2 else src.shape[2]), src.dtype)
    M = np.array([[1.0, 0, -x0], [0, 1.0, -y0], [0, 0, 1.0]]) @ np.asarray(G, np.float64)
    out = cv2.warpPerspective(src, M, (w, h), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out.reshape(h, w, -1)


def _overlap(patch: Patch, x0: int, y0: int, w: int, h: int):
    """Slices (region, patch) of the overlap of a patch with region [x0, x0+w) x [y0, y0+h)."""
    ax0, ay0 = max(patch.x0, x0), max(patch.y0, y0)
    ax1, ay1 = min(patch.x1, x0 + w), min(patch.y1, y0 + h)
    if ax0 >= ax1 or ay0 >= ay1:
        return None
    region = (slice(ay0 - y0, ay1 - y0), slice(ax0 - x0, ax1 - x0))
    inside = (slice(ay0 - patch.y0, ay1 - patch.y0), slice(ax0 - patch.x0, ax1 - patch.x0))
    return region, inside


def accumulate(acc: np.ndarray, x0: int, y0: int, patch: Patch, blend: str) -> bool:
    """Adds a patch to an accumulator (h, w, C + 1) whose [0, 0] is reference pixel (x0, y0).

    linear / average: sums of premultiplied colour and weight. last: the covered pixels are
    replaced (colour, weight 1). Returns False if the patch misses the region."""
    ov = _overlap(patch, x0, y0, acc.shape[1], acc.shape[0])
    if ov is None:
        return False
    region, inside = ov
    if blend == "last":
        src = patch.data[inside]
        w = src[:, :, -1]
        dst = acc[region]  # a view: cv2.copyTo writes into acc (numpy's masked copy is 5x slower)
        # A frame covers its pixels of weight >= 0.5; below (a footprint's edge, a specular
        # highlight at SPECULAR_WEIGHT) only pixels still empty, so a spot no other frame shows
        # is no hole (and is painted over by any later frame seeing it).
        covered = ((w >= 0.5) | ((w > COVERED) & (dst[:, :, -1] == 0))).view(np.uint8)
        value = src / np.maximum(w, np.float32(1e-6))[:, :, None]
        value[:, :, -1] = 1.0
        cv2.copyTo(value, covered, dst)
    else:
        acc[region] += patch.data[inside]
    return True


def resolve(acc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Accumulator -> (uint8 image (h, w, C), covered (h, w) bool); empty pixels are black."""
    w = acc[:, :, -1]
    covered = w > COVERED
    inv = np.divide(np.float32(1.0), w, out=np.zeros_like(w), where=covered)
    out = acc[:, :, :-1] * inv[:, :, None]
    out += np.float32(0.5)  # round half up (values are >= 0)
    np.clip(out, 0, 255, out=out)
    return out.astype(np.uint8), covered


# ------------------------------------------------------------------------------------------
# Multi-band blending
# ------------------------------------------------------------------------------------------


def filled_colour(colour_w: np.ndarray) -> np.ndarray:
    """(h, w, C) float32 colour of a weighted patch's data `colour_w` (h, w, C + 1: colour
    premultiplied by the weight, then the weight): divided by its weight where it covers
    (COVERED), push-pull filled elsewhere (fill_outside)."""
    w = colour_w[:, :, -1:]
    covered = w > COVERED
    colour = np.zeros(colour_w.shape[:2] + (colour_w.shape[2] - 1,), np.float32)
    np.divide(colour_w[:, :, :-1], w, out=colour, where=covered)
    return fill_outside(colour, covered[:, :, 0])


def fill_outside(colour: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """Push-pull fill: pixels outside `covered` take smooth values extrapolated from inside, so
    the Laplacian pyramid of a frame does not see the black outside its footprint.

    colour (h, w, C) float32, zero outside `covered` (h, w) bool. Returns a new array."""
    alpha = covered.astype(np.float32)
    levels = [(colour, alpha)]  # colour premultiplied by alpha (alpha is 0/1 here)
    while min(levels[-1][1].shape) > 2 and levels[-1][1].min() <= 0:
        c, a = levels[-1]
        levels.append((_pyr_down(c), cv2.pyrDown(a)))
    c, a = levels[-1]
    filled = np.zeros_like(c)
    np.divide(c, a[:, :, None], out=filled, where=a[:, :, None] > 1e-12)
    empty = a <= 1e-12
    if empty.any():
        inside = ~empty
        filled[empty] = filled[inside].mean(axis=0) if inside.any() else 0.0
    for c, a in reversed(levels[1:-1]):
        up = _pyr_up(filled, c.shape[:2])
        filled = c + (1.0 - np.minimum(a, 1.0))[:, :, None] * up  # "over" compositing
    if len(levels) > 1:
        up = _pyr_up(filled, colour.shape[:2])
        filled = colour.copy()
        np.copyto(filled, up, where=~covered[:, :, None])
    else:
        filled = colour.copy()
    return filled


def _pyr_down(x: np.ndarray) -> np.ndarray:
    out = cv2.pyrDown(x)
    return out.reshape(out.shape[0], out.shape[1], -1)


def _pyr_up(x: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    out = cv2.pyrUp(x, dstsize=(shape[1], shape[0]))
    return out.reshape(shape[0], shape[1], -1)


class MultibandRegion:
    """Laplacian-pyramid accumulation over a canvas region whose origin and size are multiples
    of 2**bands in reference pixels, so every frame's pyramid lines up with the region's."""

    def __init__(self, x0: int, y0: int, width: int, height: int, channels: int,
                 bands: int) -> None:
        step = 2**bands
        if x0 % step or y0 % step or width % step or height % step:
            raise ValueError(f"multiband region ({x0}, {y0}, {width}, {height}) is not aligned "
                             f"to {step} px")
        self.x0, self.y0, self.bands = x0, y0, bands
        self.acc = [np.zeros((height >> l, width >> l, channels + 1), np.float32)
                    for l in range(bands + 1)]

    def feed(self, patch: Patch, seam: np.ndarray) -> None:
        """patch: aligned, cropped to the region; seam: (h, w) bool, the pixels it owns."""
        gauss = filled_colour(patch.data)
        mask = seam.astype(np.float32)
        for l in range(self.bands + 1):
            if l < self.bands:
                down = _pyr_down(gauss)
                band = gauss
                band -= _pyr_up(down, gauss.shape[:2])  # Laplacian band (in place)
                next_mask = cv2.pyrDown(mask)
            else:
                band = gauss
            ox, oy = (patch.x0 - self.x0) >> l, (patch.y0 - self.y0) >> l
            h, wd = band.shape[:2]
            dst = self.acc[l][oy:oy + h, ox:ox + wd]
            if l == 0:  # the mask is the 0/1 seam itself
                np.add(dst[:, :, :-1], band, out=dst[:, :, :-1], where=seam[:, :, None])
            else:
                band *= mask[:, :, None]
                dst[:, :, :-1] += band
            dst[:, :, -1] += mask
            if l < self.bands:
                gauss, mask = down, next_mask

    def result(self) -> np.ndarray:
        """(h, w, C) float32 collapsed pyramid (unclipped)."""
        out = None
        for l in range(self.bands, -1, -1):
            acc = self.acc[l]
            level = np.zeros(acc.shape[:2] + (acc.shape[2] - 1,), np.float32)
            np.divide(acc[:, :, :-1], acc[:, :, -1:], out=level,
                      where=acc[:, :, -1:] > 1e-12)
            out = level if out is None else level + _pyr_up(out, level.shape[:2])
        return out


# ------------------------------------------------------------------------------------------
# Gain compensation (Brown & Lowe, "Automatic panoramic image stitching", IJCV 2007, Sec. 6)
# ------------------------------------------------------------------------------------------

SIGMA_N = 10.0  # grey levels, Brown & Lowe 2007 Sec. 6
SIGMA_G = 0.1  # gain prior std, Brown & Lowe 2007 Sec. 6


def compensate_gains(thumbnails: dict[int, np.ndarray], G: np.ndarray, width: int, height: int,
                     mask: np.ndarray | None = None, *, neighbours: int = 16,
                     samples: int = 24, margin: float = 12.0) -> np.ndarray:
    """One gain per frame minimising Brown & Lowe's error over overlapping pairs:
    e = 1/2 sum_ij N_ij ((g_i I_ij - g_j I_ji)^2 / sigma_N^2 + (1 - g_i)^2 / sigma_g^2),
    with I_ij the mean intensity of frame i where it overlaps frame j, N_ij the overlap size.

    thumbnails: frame -> (h, w) float32 grey image at any reduced size (bilinear sampled),
    NaN where the frame is not to be compared (thumbnail(mask_specular=True): its specular
    highlights); G: (N, 3, 3) frame -> reference (full-resolution pixels). Pairs: each frame
    with its `neighbours` nearest frame centres; overlaps sampled on a samples x samples grid,
    at least `margin` px inside both fields of view (a thumbnail pixel near the edge mixes in
    black) and valid in both thumbnails (a sample next to a NaN pixel is NaN): I_ij and I_ji
    average the same points, N_ij counts them.
    Returns (N,) gains, 1 for frames without thumbnail or overlap."""
    from scipy import sparse
    from scipy.sparse.linalg import spsolve
    from scipy.spatial import cKDTree

    n = len(G)
    gains = np.ones(n)
    ks = np.array(sorted(thumbnails))
    if len(ks) < 2:
        return gains
    fov = edge_distance(fov_mask_bool(mask, width, height)) >= margin
    if not fov.any():
        return gains
    xs, ys = np.meshgrid(np.linspace(0, width - 1, samples), np.linspace(0, height - 1, samples))
    grid = np.stack([xs.ravel(), ys.ravel()], axis=1)
    grid = grid[fov[np.rint(grid[:, 1]).astype(int), np.rint(grid[:, 0]).astype(int)]]
    hom = np.hstack([grid, np.ones((len(grid), 1))])
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0, 1.0])
    c = G[ks] @ centre
    centres = c[:, :2] / c[:, 2:]
    tree = cKDTree(centres)
    k = min(neighbours + 1, len(ks))
    _, nn = tree.query(centres, k=k)
    pairs = {(min(a, b), max(a, b)) for a, row in enumerate(nn) for b in row[1:]}

    def sample(thumb: np.ndarray, pts: np.ndarray) -> np.ndarray:
        sx = (thumb.shape[1]) / width
        sy = (thumb.shape[0]) / height
        mx = ((pts[:, 0] + 0.5) * sx - 0.5).astype(np.float32)[None]
        my = ((pts[:, 1] + 0.5) * sy - 0.5).astype(np.float32)[None]
        return cv2.remap(thumb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]

    rows, cols, vals = [], [], []
    b = np.zeros(n)
    diag = np.zeros(n)
    for a, bb in sorted(pairs):
        i, j = ks[a], ks[bb]
        # frame i's grid points that land inside frame j's field of view
        ref = hom @ G[i].T
        in_j = ref @ np.linalg.inv(G[j]).T
        with np.errstate(divide="ignore", invalid="ignore"):
            pj = in_j[:, :2] / in_j[:, 2:]
        ok = (in_j[:, 2] > 0) & np.isfinite(pj).all(axis=1)
        ok &= (pj[:, 0] >= 0) & (pj[:, 0] <= width - 1) & (pj[:, 1] >= 0) & (pj[:, 1] <= height - 1)
        if ok.any():
            pji = np.rint(pj[ok]).astype(int)
            ok[ok] = fov[pji[:, 1], pji[:, 0]]
        if int(ok.sum()) < 4:
            continue
        s_ij = sample(thumbnails[i], grid[ok])
        s_ji = sample(thumbnails[j], pj[ok])
        valid = np.isfinite(s_ij) & np.isfinite(s_ji)
        if not valid.all():  # highlights (NaN) in either frame: the points valid in both
            s_ij, s_ji = s_ij[valid], s_ji[valid]
        count = len(s_ij)
        if count < 4:
            continue
        I_ij = float(s_ij.mean())
        I_ji = float(s_ji.mean())
        N = count / len(grid)
        # both orders of the pair, as in Brown & Lowe's double sum
        for p, q, Ip, Iq in ((i, j, I_ij, I_ji), (j, i, I_ji, I_ij)):
            diag[p] += N * (Ip * Ip / SIGMA_N**2 + 1.0 / SIGMA_G**2)
            diag[q] += N * Iq * Iq / SIGMA_N**2
            rows += [p, q]
            cols += [q, p]
            vals += [-N * Ip * Iq / SIGMA_N**2] * 2
            b[p] += N / SIGMA_G**2
    involved = diag > 0
    if not involved.any():
        return gains
    A = sparse.coo_matrix((vals, (rows, cols)), shape=(n, n)).tocsr() + sparse.diags(diag)
    idx = np.flatnonzero(involved)
    sol = spsolve(A[idx][:, idx].tocsc(), b[idx])
    gains[idx] = sol
    return gains


# Highlights are small: the simulator's (3 lights, sigma 8 px, 240 px frames) cover 3.5-4 % of a
# thumbnail with their glow. A frame whose "highlights" would blank more than this fraction is
# over-exposed tissue (every channel >= 235 in patches), the frame gain compensation is for: its
# thumbnail is kept whole (a review: grey tissue x 1.7, 100 % masked, kept its gain of 1).
MAX_HIGHLIGHT_FRACTION = 0.5


def thumbnail(image: np.ndarray, scale: int = 8, *, mask_specular: bool = False,
              highlights: SpecularMasks | None = None, key: int | None = None) -> np.ndarray:
    """Grey float32 thumbnail (1/scale per side) used by :func:`compensate_gains`.

    mask_specular (BlendOptions.mask_specular): thumbnail pixels whose area holds any pixel of
    a specular highlight (registration.features.specular_mask, its glow included) are NaN,
    left out of the overlap means. A highlight moves with the camera, so it made its frame look
    brighter than the frames overlapping it, which darkened it. A frame without highlights
    gives the same thumbnail either way, and so does an over-exposed one (more than
    MAX_HIGHLIGHT_FRACTION of it masked). highlights: the run's SpecularMasks, which keeps
    the mask of frame `key` for the warper (None, or no key: found here alone)."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image[:, :, :3], cv2.COLOR_BGR2GRAY)
    h, w = grey.shape
    size = (max(1, w // scale), max(1, h // scale))
    small = cv2.resize(grey, size, interpolation=cv2.INTER_AREA).astype(np.float32)
    if mask_specular:
        spots = highlights_of(image, highlights, key, gray=grey)
        if spots is not None:
            touched = cv2.resize((spots > 0).astype(np.float32), size,
                                 interpolation=cv2.INTER_AREA) > 0
            if touched.mean() <= MAX_HIGHLIGHT_FRACTION:
                small[touched] = np.nan
    return small
