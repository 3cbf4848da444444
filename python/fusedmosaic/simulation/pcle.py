"""pCLE simulator: a robot scans a fibre-bundle endomicroscope over tissue (paper 004, Sec. III).

The probe field of view (512x448 px, ~1 µm/px, paper 004 Sec. III-B) follows a robot path in the
x-y plane, a circle or a spiral with straight lines at both ends (Sec. IV-A), at constant speed.
A sinusoidal z oscillation of 150 µm around the nominal contact (Sec. III-C) makes the contact
vary:

- probe lifted (z above ``contact_loss_um``): the image contrast fades smoothly into
  fibre-bundle noise (Fig. 1, middle);
- probe pressed (z below ``-stick_um``): stick-slip, the tissue sticks to the probe so the image
  is still while the robot keeps moving, until the tangential lag reaches ``slip_lag_um`` (or the
  pressure drops) and the image jumps to catch up within ``slip_time_s``.

Units and conventions:

- Positions are in µm, in the image axes (x to the right, y down). p(t) is the position of the
  field of view over the tissue; frame k's pixel (u, v) shows tissue point p_k / pixel_size +
  (u, v), so the ground truth frame -> reference homography is the translation
  G_k = [[1, 0, dx], [0, 1, dy], [0, 0, 1]] with (dx, dy) = (p_k - p_0) / pixel_size_um.
- robot.csv: the robot-reported probe position p_r(t) (the commanded path, which the
  robot follows perfectly, paper's X_r) at its own rate; p_r(0) = (0, 0) and p_k = p_r(t_k)
  except during stick-slip. robot_noisy.csv: the same integrated from velocities with added
  noise (paper's hat X_r: "we add artificial noise to the trajectory estimate V_r").
- events.csv: frame, contact_loss (0/1: contrast < 0.5 at the frame), stick_slip (0/1: the image
  is stuck at the frame time, or slipped since the previous frame), then contrast (0..1, the
  tissue signal's weight) and z_um (the probe height; > 0 lifted, < 0 pressed).
- truth_positions.csv: frame, timestamp, x_um, y_um = p_k - p_0.
"""

import json
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.special import erf

from fusedmosaic.io.tracking import MAX_ROBOT_UM
from fusedmosaic.simulation._options import (
    MAX_FRAMES,
    MAX_SAMPLES,
    NOISE_REACH_SIGMAS,
    check_fov_radius,
    check_frame_count,
    check_recording,
    check_signs,
    check_time_offsets,
    check_types,
    frame_times,
    most_changed,
    sample_times,
)
from fusedmosaic.simulation._options import option as _opt
from fusedmosaic.simulation.textures import cell_texture, fibre_bundle_pattern

TRAJECTORIES = ("circle", "spiral")
MAX_PATH_UM = 1e7  # 10 m of probe path (1e7 polyline points)
MAX_TEXTURE_PX = 60e6  # the tissue texture covering every field of view
TEXTURE_MARGIN_PX = 24.0  # texture beyond the outermost fields of view
CONTACT_STEP_S = 1e-3  # time step of the contact dynamics (z, stick-slip)
# The largest tissue cell and fibre-core spacing, as fractions of the field of view's smaller
# side: a frame shows a few cells (the texture NCC registers) and a honeycomb of cores.
MAX_CELL_FRACTION = 0.5
MAX_FIBRE_SPACING_FRACTION = 0.125


@dataclass
class PcleOptions:
    """Options of :func:`generate_pcle` (the CLI builds its flags from these fields)."""

    trajectory: str = _opt(
        "circle", "'circle' or 'spiral' (lines at both ends), paper 004 Sec. IV-A",
        choices=TRAJECTORIES)
    width: int = _opt(512, "frame width, px (paper 004 Sec. III-B: 512x448 exported images)")
    height: int = _opt(448, "frame height, px")
    pixel_size_um: float = _opt(1.0, "µm/px (~500 µm field of view, paper 004 Sec. III-B)")
    fps: float = _opt(10.0, "frame rate (paper 004 Sec. III-B: 9-10 images/s)")
    speed_um_per_frame: float = _opt(40.0, "robot path speed, µm per frame")
    radius_um: float = _opt(500.0, "circle radius / outer radius of the spiral")
    laps: float = _opt(1.0, "circle: number of laps")
    spiral_inner_um: float = _opt(100.0, "spiral: inner radius")
    spiral_turns: float = _opt(2.5, "spiral: turns between inner and outer radius")
    line_um: float = _opt(300.0, "spiral: length of the straight lines at both ends")
    n_frames: int = _opt(0, "frames; 0 = the whole path")
    z_amplitude_um: float = _opt(150.0, "z oscillation amplitude (paper 004 Sec. III-C: 150 µm)")
    z_period_s: float = _opt(4.0, "z oscillation period")
    contact_loss: bool = _opt(True, "simulate contact loss (probe lifted)")
    contact_loss_um: float = _opt(
        125.0, "probe height above contact (>= 0) at which the contrast is 0.5")
    contact_fade_um: float = _opt(25.0, "width of the contrast fade (erf scale), µm")
    stick_slip: bool = _opt(True, "simulate stick-slip (probe pressed)")
    stick_um: float = _opt(
        125.0, "pressing depth (>= 0) beyond which the tissue sticks to the probe")
    slip_lag_um: float = _opt(120.0, "tangential lag at which a stuck probe slips")
    slip_time_s: float = _opt(0.02, "time constant of the catch-up jump after a slip")
    robot_rate_hz: float = _opt(50.0, "robot sample rate (own clock, not frame-synchronous)")
    robot_offset_s: float = _opt(0.0063, "robot clock phase vs frames")
    robot_margin_s: float = _opt(0.1, "robot samples extend this far beyond the first/last frame")
    robot_noise: float = _opt(0.3, "robot_noisy: velocity noise std / path speed")
    robot_noise_corr_s: float = _opt(0.5, "robot_noisy: correlation time of the velocity noise")
    cell_size_um: float = _opt(12.0, "tissue cell size")
    fibre_spacing_px: float = _opt(3.0, "fibre-core spacing of the honeycomb pattern")
    fibre_contrast: float = _opt(0.25, "depth of the honeycomb modulation in good contact")
    noise_floor: float = _opt(0.12, "level of the fibre-bundle noise when contact is lost (0..1)")
    image_noise_sigma: float = _opt(4.0, "std of per-frame Gaussian image noise, gray levels")
    fov_mask_radius: float = _opt(
        0.0, "circular field of view, px: black outside, camera.yaml's fov_mask_radius (a fibre "
        "bundle's raw round image; 0 = the whole frame, as the paper's exported images)")
    seed: int = _opt(0, "seed of every random draw (tissue, fibres, noise)")

    def validate(self) -> None:
        """Raise ValueError naming the first bad option."""
        check_types(self, whole=("width", "height", "n_frames"))
        if self.trajectory not in TRAJECTORIES:
            raise ValueError(
                f"PcleOptions.trajectory: expected one of {TRAJECTORIES}, got {self.trajectory!r}"
            )
        if self.width < 32 or self.height < 32:
            raise ValueError(
                f"PcleOptions.width/height: must be >= 32 px, got {self.width}x{self.height}"
            )
        check_signs(
            self,
            positive=(
                "pixel_size_um",
                "fps",
                "speed_um_per_frame",
                "radius_um",
                "laps",
                "spiral_turns",
                "z_period_s",
                "contact_fade_um",
                "slip_lag_um",
                "slip_time_s",
                "robot_rate_hz",
                "robot_noise_corr_s",
                "cell_size_um",
                "fibre_spacing_px",
            ),
            non_negative=(
                "n_frames",
                "z_amplitude_um",
                "line_um",
                "robot_noise",
                "robot_margin_s",
                "image_noise_sigma",
                "noise_floor",
                "fibre_contrast",
                "spiral_inner_um",
                "fov_mask_radius",
                "contact_loss_um",
                "stick_um",
            ),
        )
        if self.n_frames:
            check_frame_count(self, self.n_frames, "PcleOptions.n_frames")
        check_time_offsets(self, "robot_offset_s")
        check_fov_radius(self)
        if self.trajectory == "spiral" and not self.spiral_inner_um < self.radius_um:
            raise ValueError(
                f"PcleOptions.spiral_inner_um: must be below radius_um "
                f"({self.radius_um}), got {self.spiral_inner_um}"
            )
        for name in ("noise_floor", "fibre_contrast"):  # fractions of the signal
            if getattr(self, name) > 1:
                raise ValueError(f"PcleOptions.{name}: must be in 0..1, got {getattr(self, name)}")
        self._check_cells_and_fibres()
        # Sizes checked before anything is allocated (the path is a polyline of 1 µm steps).
        if self.trajectory == "circle":
            length, extent, what = 2 * np.pi * self.radius_um * self.laps, 2 * self.radius_um, (
                "PcleOptions.radius_um x PcleOptions.laps")
        else:
            length = (np.pi * self.spiral_turns * (self.spiral_inner_um + self.radius_um)
                      + 2 * self.line_um)
            extent, what = 2 * (self.radius_um + self.line_um), (
                "PcleOptions.radius_um, PcleOptions.spiral_turns, PcleOptions.line_um")
        if length > MAX_PATH_UM:
            raise ValueError(f"PcleOptions: the path is {length:.3g} µm long ({what}); at most "
                             f"{MAX_PATH_UM:.0e} µm")
        if self.n_frames:
            n, frames_name = self.n_frames, "PcleOptions.n_frames"
        else:  # the whole path (generate_pcle's count, from the polyline's length <= this)
            n = int(min(np.floor(length / self.speed_um_per_frame), MAX_FRAMES)) + 1
            frames_name = "PcleOptions.speed_um_per_frame (PcleOptions.n_frames 0: the whole path)"
            check_frame_count(self, np.floor(length / self.speed_um_per_frame) + 1, frames_name)
        check_recording(self, n, frames_name, "robot")
        self._check_contact_steps(n, frames_name)
        travel = self.speed_um_per_frame * max(self.n_frames - 1, 0)
        extent += max(travel - length, 0.0)  # frames beyond the path's end go straight on
        if travel > length:
            what += (", and PcleOptions.n_frames x PcleOptions.speed_um_per_frame beyond the "
                     "path")
        side = extent / self.pixel_size_um + 2 * TEXTURE_MARGIN_PX
        if (side + self.width) * (side + self.height) > MAX_TEXTURE_PX:
            raise ValueError(
                f"PcleOptions: the frames span up to {extent:.3g} µm ({what}): a texture of "
                f"~{side + self.width:.3g}x{side + self.height:.3g} px at "
                f"{self.pixel_size_um} µm/px, at most {MAX_TEXTURE_PX:.0e} px")
        self._check_robot_reach(n, extent, what)

    def fov_side_px(self) -> float:
        """The field of view's smaller side, px: the frame's, or the circular field's
        diameter."""
        side = min(self.width, self.height)
        return min(side, 2 * self.fov_mask_radius) if self.fov_mask_radius > 0 else side

    def _check_cells_and_fibres(self) -> None:
        """A cell at least a pixel and at most MAX_CELL_FRACTION of the field of view; fibre
        cores 1 px apart at least, MAX_FIBRE_SPACING_FRACTION of the field of view at most."""
        cls, ps = "PcleOptions", self.pixel_size_um
        cell_px, fov = self.cell_size_um / ps, self.fov_side_px()
        what = "the frame" if fov == min(self.width, self.height) else \
            f"{cls}.fov_mask_radius x 2"
        if cell_px < 1:
            if most_changed(self, "cell_size_um", "pixel_size_um") == "cell_size_um":
                raise ValueError(f"{cls}.cell_size_um: must be at least a pixel ({ps} µm), "
                                 f"got {self.cell_size_um}")
            raise ValueError(f"{cls}.pixel_size_um: a pixel of {ps:g} µm is larger than a "
                             f"cell ({cls}.cell_size_um {self.cell_size_um:g} µm); a cell "
                             "must be at least a pixel")
        most = MAX_CELL_FRACTION * fov
        if cell_px > most:
            lead = most_changed(self, "cell_size_um", "pixel_size_um")
            raise ValueError(f"{cls}.{lead}: a cell ({cls}.cell_size_um {self.cell_size_um:g} "
                             f"µm = {cell_px:.3g} px at {cls}.pixel_size_um {ps:g} µm) must be "
                             f"at most {MAX_CELL_FRACTION:g} x the field of view's {fov:g} px "
                             f"({what}): {most * ps:.3g} µm, so that a frame shows a few cells")
        if self.fibre_spacing_px < 1:
            raise ValueError(f"{cls}.fibre_spacing_px: must be >= 1, got "
                             f"{self.fibre_spacing_px}")
        most = MAX_FIBRE_SPACING_FRACTION * fov
        if self.fibre_spacing_px > most:
            raise ValueError(f"{cls}.fibre_spacing_px: must be at most "
                             f"{MAX_FIBRE_SPACING_FRACTION:g} x the field of view's {fov:g} px "
                             f"({what}): {most:.3g} px, got {self.fibre_spacing_px:g} (a "
                             "fibre bundle has thousands of cores)")

    def _check_contact_steps(self, n: int, frames_name: str) -> None:
        """The contact dynamics run every CONTACT_STEP_S over the frames and the robot's
        margins: at most MAX_SAMPLES steps."""
        cls = "PcleOptions"
        t_last = (n - 1) / self.fps
        steps = (t_last + 2 * self.robot_margin_s) / CONTACT_STEP_S
        if not steps <= MAX_SAMPLES:
            lead = (f"{cls}.robot_margin_s" if 2 * self.robot_margin_s >= t_last
                    else f"{frames_name}: {n} frames at {self.fps:g} fps ({cls}.fps)")
            raise ValueError(f"{lead}: the frames' {t_last:.3g} s and {cls}.robot_margin_s "
                             f"({self.robot_margin_s:g} s) on both sides make {steps:.3g} "
                             f"steps of the contact dynamics ({CONTACT_STEP_S * 1e3:g} ms "
                             f"each); at most {MAX_SAMPLES:.3g}")

    def _check_robot_reach(self, n: int, extent: float, what: str) -> None:
        """robot.csv / robot_noisy.csv within io.tracking.MAX_ROBOT_UM (what run reads): the
        frames' extent plus the margins' travel, plus NOISE_REACH_SIGMAS of the integrated
        velocity noise."""
        cls = "PcleOptions"
        speed = self.speed_um_per_frame * self.fps  # µm/s
        reach = extent + speed * (self.robot_margin_s + abs(self.robot_offset_s))
        if not reach <= MAX_ROBOT_UM:
            lead = most_changed(self, "pixel_size_um", "speed_um_per_frame", "radius_um")
            raise ValueError(f"{cls}.{lead}: the robot moves up to {reach:.3g} µm ({what}), "
                             f"beyond the {MAX_ROBOT_UM:g} µm a robot position may hold "
                             "(io.tracking.MAX_ROBOT_UM)")
        duration = (n - 1) / self.fps + 2 * self.robot_margin_s
        drift = NOISE_REACH_SIGMAS * self.robot_noise * speed * duration
        if not reach + drift <= MAX_ROBOT_UM:
            raise ValueError(f"{cls}.robot_noise: a velocity noise of {self.robot_noise:g} x "
                             f"the path speed ({speed:.3g} µm/s) over {duration:.3g} s could "
                             f"put robot_noisy.csv's positions {reach + drift:.3g} µm away, "
                             f"beyond the {MAX_ROBOT_UM:g} µm a robot position may hold "
                             "(io.tracking.MAX_ROBOT_UM)")


def max_n_frames(options: PcleOptions | Callable[[int], PcleOptions], least: int = 1) -> int:
    """The most frames (n_frames) PcleOptions.validate takes with the other options as given
    (at most MAX_FRAMES; 0 when it refuses even ``least`` frames): past the path's end the
    frames go straight on, so the tissue texture's bound ends the sequence. ``options`` may
    also be a function of the frame count giving the options (e.g. laps growing with it)."""
    options_for = (options if callable(options)
                   else lambda n: replace(options, n_frames=n))

    def ok(n: int) -> bool:
        try:
            options_for(n).validate()
        except ValueError:
            return False
        return True

    if not ok(least):
        return 0
    lo, hi = least, MAX_FRAMES  # ok(lo); the answer is in lo..hi
    if ok(hi):
        return hi
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    return lo


# --------------------------------------------------------------------------------------------
# Robot path
# --------------------------------------------------------------------------------------------


def robot_path(o: PcleOptions) -> np.ndarray:
    """Dense polyline (P, 2) µm of the commanded path, starting at (0, 0), points <= 1 µm apart."""
    if o.trajectory == "circle":
        length = 2 * np.pi * o.radius_um * o.laps
        a = np.linspace(0.0, 2 * np.pi * o.laps, int(np.ceil(length)) + 2)
        return np.stack([o.radius_um * (np.cos(a) - 1.0), o.radius_um * np.sin(a)], axis=1)
    # Archimedean spiral r(θ) = r_in + (r_out - r_in) θ / θ_end, straight lines in and out along
    # its end tangents.
    theta_end = 2 * np.pi * o.spiral_turns
    rough = 2 * np.pi * o.spiral_turns * 0.5 * (o.spiral_inner_um + o.radius_um)
    th = np.linspace(0.0, theta_end, int(np.ceil(rough * 1.2)) + 2)
    r = o.spiral_inner_um + (o.radius_um - o.spiral_inner_um) * th / theta_end
    spiral = np.stack([r * np.cos(th), r * np.sin(th)], axis=1)
    dr = (o.radius_um - o.spiral_inner_um) / theta_end

    def tangent(t: float, rr: float) -> np.ndarray:
        v = np.array([dr * np.cos(t) - rr * np.sin(t), dr * np.sin(t) + rr * np.cos(t)])
        return v / np.linalg.norm(v)

    n_line = int(np.ceil(o.line_um)) + 2
    s = np.linspace(0.0, o.line_um, n_line)[:, None]
    t0, t1 = tangent(0.0, r[0]), tangent(theta_end, r[-1])
    line_in = spiral[0] - t0 * (o.line_um - s)
    line_out = spiral[-1] + t1 * s
    path = np.concatenate([line_in[:-1], spiral, line_out[1:]])
    return path - path[0]


@dataclass
class _PathFollower:
    """Position at arc length s along a polyline; linear extrapolation beyond both ends."""

    points: np.ndarray

    def __post_init__(self) -> None:
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        keep = np.concatenate([[True], seg > 1e-9])
        self.points = self.points[keep]
        self.s = np.concatenate([[0.0], np.cumsum(seg[seg > 1e-9])])
        self.length = float(self.s[-1])
        d0 = self.points[1] - self.points[0]
        d1 = self.points[-1] - self.points[-2]
        self.t0, self.t1 = d0 / np.linalg.norm(d0), d1 / np.linalg.norm(d1)

    def __call__(self, s: np.ndarray) -> np.ndarray:
        s = np.asarray(s, np.float64)
        xy = np.stack([np.interp(s, self.s, self.points[:, j]) for j in range(2)], axis=-1)
        before, after = s < 0, s > self.length
        xy[before] = self.points[0] + s[before, None] * self.t0
        xy[after] = self.points[-1] + (s[after, None] - self.length) * self.t1
        return xy


# --------------------------------------------------------------------------------------------
# Contact: z oscillation, contrast and stick-slip
# --------------------------------------------------------------------------------------------


def _contrast(z: np.ndarray, o: PcleOptions) -> np.ndarray:
    """Tissue-signal weight in 0..1: 0.5 at z = contact_loss_um, erf-shaped fade."""
    if not o.contact_loss:
        return np.ones_like(z)
    return 0.5 * (1.0 - erf((z - o.contact_loss_um) / o.contact_fade_um))


def _stick_slip(
    t: np.ndarray, robot_xy: np.ndarray, z: np.ndarray, o: PcleOptions
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lag (T, 2) of the image behind the robot on a fine time grid, and stuck / slipping flags.

    While pressed (z < -stick_um) the tissue sticks: the lag grows by the robot's displacement, so
    the image is still. It slips when |lag| >= slip_lag_um or the pressure drops; the lag then
    decays with time constant slip_time_s (the jump), and it can stick again once caught up.
    """
    n = t.size
    lag = np.zeros((n, 2))
    stuck = np.zeros(n, bool)
    slipping = np.zeros(n, bool)
    if not o.stick_slip:
        return lag, stuck, slipping
    pressed = z < -o.stick_um
    state = "free"
    current = np.zeros(2)
    for i in range(1, n):
        dt = t[i] - t[i - 1]
        if state == "free" and pressed[i]:
            state = "stuck"
        if state == "stuck":
            current = current + (robot_xy[i] - robot_xy[i - 1])
            if np.hypot(*current) >= o.slip_lag_um or not pressed[i]:
                state = "slip"
        elif state == "slip":
            current = current * np.exp(-dt / o.slip_time_s)
            if np.hypot(*current) < 0.5:
                current = np.zeros(2)
                state = "free"
        lag[i] = current
        stuck[i] = state == "stuck"
        slipping[i] = state == "slip"
    return lag, stuck, slipping


# --------------------------------------------------------------------------------------------
# Scene
# --------------------------------------------------------------------------------------------


@dataclass
class PcleScene:
    """Everything :func:`generate_pcle` makes; frames are rendered on demand.

    timestamps (N,) s; positions_um (N, 2) true field-of-view positions p_k - p_0 (image axes);
    homographies (N, 3, 3) true frame -> frame-0 translations; contrast (N,) 0..1; z_um (N,);
    contact_loss (N,) bool; stick_slip (N,) bool; robot_timestamps (M,); robot_xy_um (M, 2)
    commanded/perfect robot positions; robot_noisy_xy_um (M, 2); texture (Ht, Wt) uint8 tissue;
    fibre (H, W) float32 honeycomb; texture_origin_px (2,) texture pixel of tissue point p = 0.
    """

    options: PcleOptions
    timestamps: np.ndarray
    positions_um: np.ndarray
    homographies: np.ndarray
    contrast: np.ndarray
    z_um: np.ndarray
    contact_loss: np.ndarray
    stick_slip: np.ndarray
    robot_timestamps: np.ndarray
    robot_xy_um: np.ndarray
    robot_noisy_xy_um: np.ndarray
    texture: np.ndarray
    fibre: np.ndarray
    texture_origin_px: np.ndarray
    path_length_um: float

    @property
    def n_frames(self) -> int:
        return self.timestamps.size

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the frames."""
        return self.options.width, self.options.height

    def tissue(self, k: int) -> np.ndarray:
        """The noiseless tissue under frame k, (H, W) float32 in 0..1."""
        o = self.options
        ox, oy = self.texture_origin_px + self.positions_um[k] / o.pixel_size_um
        A = np.array([[1.0, 0.0, ox], [0.0, 1.0, oy]])
        img = cv2.warpAffine(
            self.texture,
            A,
            (o.width, o.height),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REFLECT,
        )
        return img.astype(np.float32) / 255.0

    def render(self, k: int) -> np.ndarray:
        """Frame k, (H, W) gray uint8: tissue x contrast seen through the fibre bundle, faded into
        fibre-bundle noise as contact is lost, plus seeded Gaussian noise (the same for a given
        seed and k, whatever the order of calls)."""
        # rounded to grey levels, as the checkerboard's frames: truncating made every frame 0.5
        # grey levels darker than its scene (review 47)
        return np.clip(np.rint(self.grey_levels(k)), 0, 255).astype(np.uint8)

    def grey_levels(self, k: int) -> np.ndarray:
        """Frame k before render rounds it to uint8: (H, W) float32 grey levels, unclipped."""
        if not 0 <= k < self.n_frames:
            raise IndexError(f"frame {k} outside 0..{self.n_frames - 1}")
        o = self.options
        rng = np.random.default_rng([o.seed, 1, k])
        c = float(self.contrast[k])
        fib = self.fibre
        signal = c * self.tissue(k) * (1.0 - o.fibre_contrast + o.fibre_contrast * fib)
        # Without signal the normalised fibre bundle shows its cores with per-frame fluctuation.
        flicker = cv2.GaussianBlur(rng.standard_normal(fib.shape).astype(np.float32), (0, 0), 0.8)
        floor = o.noise_floor * fib * (1.0 + 1.5 * flicker)
        img = 255.0 * (signal + (1.0 - c) * floor)
        if o.image_noise_sigma > 0:
            img += rng.normal(0.0, o.image_noise_sigma, img.shape).astype(np.float32)
        if o.fov_mask_radius > 0:
            img[~self.fov_mask()] = 0.0
        return img

    def fov_mask(self) -> np.ndarray:
        """(H, W) bool: inside the circular field of view (all True without one), as
        Camera.fov_mask."""
        from fusedmosaic.io import Camera

        o = self.options
        if o.fov_mask_radius <= 0:
            return np.ones((o.height, o.width), bool)
        return Camera(o.width, o.height, fov_mask_radius=o.fov_mask_radius).fov_mask() > 0

    def frames(self) -> Iterator[np.ndarray]:
        """Render all frames lazily, in order."""
        for k in range(self.n_frames):
            yield self.render(k)


def generate_pcle(options: PcleOptions | None = None) -> PcleScene:
    """Build a pCLE scene (robot path, contact events, true positions, robot samples and a lazy
    frame renderer) without touching the disk."""
    o = PcleOptions() if options is None else options
    o.validate()
    follow = _PathFollower(robot_path(o))
    speed = o.speed_um_per_frame * o.fps  # µm/s
    n = o.n_frames or int(np.floor(follow.length / o.speed_um_per_frame)) + 1
    timestamps = frame_times(o, n)
    t_last = float(timestamps[-1])

    # Robot samples and a fine grid for the contact dynamics, both covering the margins.
    t_robot = sample_times(o, "robot", t_last)
    dt = CONTACT_STEP_S
    t_fine = np.arange(min(t_robot[0], 0.0) - dt, max(t_robot[-1], t_last) + 2 * dt, dt)
    xy_fine = follow(speed * t_fine)
    z_fine = o.z_amplitude_um * np.sin(2 * np.pi * t_fine / o.z_period_s)
    lag, stuck, slipping = _stick_slip(t_fine, xy_fine, z_fine, o)

    def at(values: np.ndarray, t: np.ndarray) -> np.ndarray:
        if values.ndim == 1:
            return np.interp(t, t_fine, values)
        return np.stack([np.interp(t, t_fine, values[:, j]) for j in range(values.shape[1])], 1)

    robot_frames = follow(speed * timestamps)
    image_xy = robot_frames - at(lag, timestamps)
    # Frames exactly on a grid node read its state; between nodes, the state of the node before.
    idx = np.clip(np.searchsorted(t_fine, timestamps, side="right") - 1, 0, t_fine.size - 1)
    prev = np.concatenate([[0], idx[:-1]])
    slipped = np.array([slipping[a + 1 : b + 1].any() for a, b in zip(prev, idx, strict=True)])
    stick_event = stuck[idx] | slipped
    z = o.z_amplitude_um * np.sin(2 * np.pi * timestamps / o.z_period_s)
    contrast = _contrast(z, o)

    positions = image_xy - image_xy[0]
    G = np.tile(np.eye(3), (n, 1, 1))
    G[:, :2, 2] = positions / o.pixel_size_um

    # Robot: perfect (commanded) positions and a noisy estimate integrated from noisy velocities.
    robot_xy = follow(speed * t_robot)
    rng_robot = np.random.default_rng([o.seed, 3])
    period = 1.0 / o.robot_rate_hz
    a = np.exp(-period / o.robot_noise_corr_s)
    sigma = o.robot_noise * speed
    noise = np.empty((t_robot.size, 2))
    noise[0] = rng_robot.normal(0.0, sigma, 2)
    xi = rng_robot.standard_normal((t_robot.size, 2))
    for j in range(1, t_robot.size):
        noise[j] = a * noise[j - 1] + np.sqrt(1.0 - a * a) * sigma * xi[j]
    velocity = np.diff(robot_xy, axis=0) / period
    noisy = np.concatenate(
        [robot_xy[:1], robot_xy[0] + np.cumsum((velocity + noise[1:]) * period, axis=0)]
    )

    # Tissue texture covering every field of view with a margin.
    margin = TEXTURE_MARGIN_PX
    lo = image_xy.min(0) / o.pixel_size_um - margin
    hi = image_xy.max(0) / o.pixel_size_um + np.array([o.width, o.height]) + margin
    tex_w, tex_h = (int(np.ceil(v)) for v in hi - lo)
    if tex_w * tex_h > MAX_TEXTURE_PX:
        raise ValueError(
            f"PcleOptions: the path needs a {tex_w}x{tex_h} px texture; at most "
            f"{MAX_TEXTURE_PX:.0e} px: lower PcleOptions.radius_um, PcleOptions.laps or "
            "PcleOptions.spiral_turns, or raise PcleOptions.pixel_size_um"
        )
    texture = cell_texture(
        (tex_h, tex_w),
        np.random.default_rng([o.seed, 2]),
        cell_size_px=o.cell_size_um / o.pixel_size_um,
    )
    fibre = fibre_bundle_pattern(
        (o.height, o.width), np.random.default_rng([o.seed, 4]), spacing_px=o.fibre_spacing_px
    )
    fibre = fibre / float(fibre.mean())  # mean 1: the honeycomb modulates, it does not dim
    # texture pixel of tissue point p (µm, the frame's top-left pixel centre) = p / ps - lo;
    # positions_um are relative to frame 0, so add frame 0's absolute position.
    origin = image_xy[0] / o.pixel_size_um - lo

    return PcleScene(
        options=o,
        timestamps=timestamps,
        positions_um=positions,
        homographies=G,
        contrast=contrast,
        z_um=z,
        contact_loss=contrast < 0.5,
        stick_slip=stick_event,
        robot_timestamps=t_robot,
        robot_xy_um=robot_xy,
        robot_noisy_xy_um=noisy,
        texture=texture,
        fibre=fibre.astype(np.float32),
        texture_origin_px=origin,
        path_length_um=follow.length,
    )


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def _events_csv(scene: PcleScene) -> str:
    lines = ["frame,contact_loss,stick_slip,contrast,z_um"]
    for k in range(scene.n_frames):
        lines.append(
            f"{k},{int(scene.contact_loss[k])},{int(scene.stick_slip[k])},"
            f"{float(scene.contrast[k])!r},{float(scene.z_um[k])!r}"
        )
    return "\n".join(lines) + "\n"


def _positions_csv(scene: PcleScene) -> str:
    lines = ["frame,timestamp,x_um,y_um"]
    for k in range(scene.n_frames):
        x, y = scene.positions_um[k]
        lines.append(f"{k},{float(scene.timestamps[k])!r},{float(x)!r},{float(y)!r}")
    return "\n".join(lines) + "\n"


def simulate_pcle(
    out: str | Path, options: PcleOptions | None = None, *, overwrite: bool = False
) -> Path:
    """Generate a pCLE dataset folder (dataset contract of design.md) at ``out``.

    Writes frames/, frames.csv, camera.yaml (size, pixel_size_um[, fov_mask_radius]), robot.csv,
    robot_noisy.csv, ground_truth.csv, events.csv, truth_positions.csv and simulation.json (the
    options used)."""
    from fusedmosaic.io import Camera, RobotSamples, write_dataset

    scene = generate_pcle(options)
    o = scene.options
    camera = Camera(o.width, o.height, pixel_size_um=o.pixel_size_um,
                    fov_mask_radius=o.fov_mask_radius if o.fov_mask_radius > 0 else None)
    info = {"simulator": "pcle", "options": asdict(o), "path_length_um": scene.path_length_um}
    return write_dataset(
        out,
        camera=camera,
        frames=scene.frames(),
        timestamps=scene.timestamps,
        robot=RobotSamples(scene.robot_timestamps, scene.robot_xy_um),
        robot_files={
            "robot_noisy.csv": RobotSamples(scene.robot_timestamps, scene.robot_noisy_xy_um)
        },
        ground_truth=scene.homographies,
        extra_files={
            "events.csv": _events_csv(scene),
            "truth_positions.csv": _positions_csv(scene),
            "simulation.json": json.dumps(info, indent=2) + "\n",
        },
        overwrite=overwrite,
    )
