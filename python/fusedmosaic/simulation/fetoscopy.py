"""Fetoscopy simulator: the SYN dataset of paper 000 (Sec. 4.1) and a hand-held variant.

A textured plane is imaged by a pinhole camera moving over it; an EM tracker reports the camera
pose at its own rate with Gaussian noise (paper 000, assumption 2 and appendix Σ_EMT).

Conventions (design.md; the C++ core uses the same, but this module does not call it so it can
test it):

- world = the tracker frame; the paper's virtual camera sits at its origin with identity rotation.
- pose = [rx, ry, rz, tx, ty, tz]: angle-axis (rad) and translation (mm) of cam_from_world.
- plane π = n/d (3,), the plane n·X + d = 0; ``truth_plane.json`` gives π, the unit normal n
  (pointing from the plane towards the virtual camera) and the distance d > 0 (mm).
- H_k = K (R_k - t_k πᵀ) K⁻¹ maps virtual-camera pixels to frame-k pixels; the ground truth is
  G_k = H_0 H_k⁻¹ (frame k -> frame 0 pixels, G[2,2] = 1). Pixel (0, 0) is the centre of the
  top-left pixel (OpenCV's convention), so ``cv2.warpPerspective(frame_k, G_k, size)`` lands on
  frame 0.
- tracking.csv holds tracker_from_sensor, with world_from_cam = tracker_from_sensor @
  sensor_from_camera (hand_eye.txt). The noise is added to the camera pose parameters
  [r, t] of cam_from_world before that conversion, so reading the tracker back through the
  hand-eye transform gives truth + N(0, diag(ν·1°, ν·1 mm)²) per sample.

Rendering: the texture is an image of the plane, texture pixel (u, v) being the plane point
O + s (u e1 + v e2). Frame k sees it through M_k = K [s R_k e1 | s R_k e2 | R_k O + t_k], and
M_k = H_k M_v with M_v the same map for the virtual camera (πᵀe1 = πᵀe2 = 0, πᵀO = -1), so the
rendered images obey G_k = M_0 M_k⁻¹ = H_0 H_k⁻¹ exactly.
"""

import json
import numbers
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field, replace
from dataclasses import fields as dataclass_fields
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from fusedmosaic.io.calibration import LENS_MODELS, Camera
from fusedmosaic.io.tracking import GAP_SPACINGS, TrackingSamples, interpolate_camera_poses
from fusedmosaic.simulation._lens import ideal_border, ideal_pixel_grid
from fusedmosaic.simulation._options import (
    MAX_ROTATION_SIGMA_DEG,
    MIN_FOV_RADIUS_PX,
    check_fov_radius,
    check_frame_count,
    check_frame_list,
    check_hand_eye,
    check_recording,
    check_signs,
    check_time_offsets,
    check_tracker_reach,
    check_types,
    frame_times,
    most_changed,
    sample_times,
)
from fusedmosaic.simulation._options import option as _opt
from fusedmosaic.simulation.textures import placenta_texture, placenta_texture_cost

# Paper 000 Sec. 4.2.3: frames replaced by black frames in the loss-of-visual-information test.
PAPER_BLACK_FRAMES = [7, 11, 12, 23, 24, 37, 38, 42, 43, 45, 51, 54]

MOTIONS = ("syn", "handheld")
# The SYN pace: the default 150 frames make the default 4 laps (paper 000 Fig. 1); shorter or
# longer sequences keep the motion with laps = n_frames / SYN_FRAMES_PER_LAP.
SYN_FRAMES_PER_LAP = 37.5
MAX_TEXTURE_PX = 60e6  # the placenta texture covering every frame
# What drawing that texture may cost (textures.placenta_texture_cost's estimate): beyond, a
# simulation takes minutes and GBs for one texture (a 4000 px frame, or a camera coming 10x
# closer than its mean distance, needs a finer texture with thick vessels; review 44).
MAX_TEXTURE_SECONDS = 60.0
MAX_TEXTURE_GB = 3.0
# The farthest a frame may see the plane: MAX_VIEW_RANGE x the camera's distance from it, along
# a ray (a ray at most arccos(1 / MAX_VIEW_RANGE) = 87.1 deg from the plane's normal). Beyond,
# the view grazes the plane's horizon or looks past it, at points behind the camera that
# warpPerspective would still paint from the texture, mirrored (review 44).
MAX_VIEW_RANGE = 20.0


@dataclass
class FetoscopyOptions:
    """Options of :func:`generate_fetoscopy` (the CLI builds its flags from these fields)."""

    motion: str = _opt("syn", "'syn' (paper 000 Sec. 4.1: xy-translation circles) or 'handheld'",
                       choices=MOTIONS)
    n_frames: int = _opt(150, "frames (paper 000 Sec. 4.2.1 uses 152 SYN frames)")
    width: int = _opt(400, "frame width, px (paper's SYN frames are 368x378)")
    height: int = _opt(400, "frame height, px")
    focal_factor: float = _opt(1.2, "focal length in px / image width (~45 deg horizontal FOV)")
    fps: float = _opt(25.0, "frame rate (paper 000 Sec. 4.1: video at 25 fps)")
    distance_mm: float = _opt(30.0, "camera-plane distance (perpendicular, mm)")
    laps: float = _opt(4.0, "syn: laps of the circle in --n-frames frames (paper 000 Fig. 1: "
                            "four laps in 152 frames; fewer frames, same laps: faster motion, "
                            "where demo --frames keeps SYN's pace); negative: the same circle "
                            "the other way round, 0: the camera rests")
    radius_mm: float = _opt(15.0, "syn: circle radius; handheld: extent of the random path")
    step_px: float = _opt(
        30.0, "handheld: rms image motion per frame, px (keeps ~90 percent overlap)"
    )
    tilt_deg: float = _opt(15.0, "handheld: plane tilt w.r.t. the virtual camera's image plane")
    rotation_deg: float = _opt(4.0, "handheld: roll/pitch amplitude, deg")
    yaw_deg: float = _opt(20.0, "handheld: slow yaw amplitude, deg")
    distance_variation: float = _opt(0.15, "handheld: relative camera-plane distance variation")
    tracker_rate_hz: float = _opt(40.0, "EM tracker rate (paper 000 Sec. 4.1: 40 Hz)")
    tracker_offset_s: float = _opt(0.0071, "tracker clock phase vs frames (not frame-synchronous)")
    tracker_margin_s: float = _opt(
        0.1, "tracker samples extend this far beyond the first/last frame"
    )
    noise_multiplier: float = _opt(1.0, "ν: EMT noise std = ν·(1 deg, 1 mm) (paper 000 Sec. 4.2.2)")
    rot_sigma_deg: float = _opt(1.0, "EMT rotation noise std at ν=1 (paper 000 appendix Σ_EMT)")
    trans_sigma_mm: float = _opt(1.0, "EMT translation noise std at ν=1 (paper 000 appendix Σ_EMT)")
    hand_eye_rot_deg: float = _opt(4.0, "sensor_from_camera rotation angle (0 = aligned)")
    hand_eye_offset_mm: float = _opt(
        6.0, "sensor_from_camera translation, mm, along a fixed direction mostly along the scope "
        "axis (0 = co-located; negative: the opposite way)")
    tracker_gap: list[int] | None = _opt(
        None, "[first, last] frames left untracked, exactly as run's reader flags them: the "
        "tracker samples between them dropped (a hole over 3 tracker periods; refused when "
        "the tracker rate cannot make one, e.g. for 1 frame at 40 Hz and 25 fps)"
    )
    black_frames: list[int] | None = _opt(
        None, "frames replaced by black; the bare CLI flag = paper 000 Sec. 4.2.3 list"
    )
    fov_mask_radius: float = _opt(
        -1.0, f"px circular FOV, at least {MIN_FOV_RADIUS_PX:g}; 0 none; -1 auto (syn none, "
        "handheld 0.48 min(W,H))"
    )
    image_noise_sigma: float = _opt(2.0, "std of per-frame Gaussian image noise, gray levels")
    lens_distortion: list[float] | None = _opt(
        None, "OpenCV k1 k2 p1 p2 [k3] (--lens-model fisheye: k1 k2 k3 k4): frames rendered "
        "through this lens, written to camera.yaml (a fetoscope's barrel lens: -0.3 0.1 0 0); "
        "none: a pinhole"
    )
    lens_model: str = _opt(
        "pinhole", "lens model of --lens-distortion: 'pinhole' (OpenCV's standard model) or "
        "'fisheye' (OpenCV's fisheye / equidistant model)", choices=LENS_MODELS)
    specular_lights: int = _opt(
        0, "light fibres at the scope tip, each mirrored in the wet tissue as a saturated "
        "specular highlight that moves with the camera (in-vivo fetoscopy); 0 none")
    specular_sigma_px: float = _opt(
        5.0, "size of a highlight: its glow's Gaussian sigma, px (its saturated core is ~1.5 "
        "sigma in radius)")
    light_offset_mm: float = _opt(
        1.0, "distance of the light fibres from the optical axis at the tip, mm")
    seed: int = _opt(0, "seed of every random draw (texture, path, noise)")

    def validate(self) -> None:
        """Raise ValueError naming the first bad option."""
        check_types(self, whole=("n_frames", "width", "height"))
        if self.motion not in MOTIONS:
            raise ValueError(
                f"FetoscopyOptions.motion: expected one of {MOTIONS}, got {self.motion!r}"
            )
        if self.n_frames < 1:
            raise ValueError(f"FetoscopyOptions.n_frames: must be >= 1, got {self.n_frames}")
        check_frame_count(self, self.n_frames, "FetoscopyOptions.n_frames")
        if self.width < 16 or self.height < 16:
            raise ValueError(
                f"FetoscopyOptions.width/height: must be >= 16 px, got {self.width}x{self.height}"
            )
        check_signs(
            self,
            positive=(
                "focal_factor",
                "fps",
                "distance_mm",
                "tracker_rate_hz",
            ),
            non_negative=(
                "noise_multiplier",
                "rot_sigma_deg",
                "trans_sigma_mm",
                "image_noise_sigma",
                "tracker_margin_s",
                "radius_mm",
                "step_px",
                "light_offset_mm",
            ),
        )
        if not self.specular_sigma_px > 0:
            raise ValueError(f"FetoscopyOptions.specular_sigma_px: must be > 0, got "
                             f"{self.specular_sigma_px}")
        n = self.specular_lights
        if isinstance(n, bool) or not isinstance(n, numbers.Integral) or not 0 <= n <= 8:
            raise ValueError(f"FetoscopyOptions.specular_lights: must be an integer in 0..8, "
                             f"got {n!r}")
        check_time_offsets(self, "tracker_offset_s")
        check_hand_eye(self)
        if not 0 <= self.distance_variation < 0.9:
            raise ValueError(
                f"FetoscopyOptions.distance_variation: must be in [0, 0.9), "
                f"got {self.distance_variation}"
            )
        check_recording(self, self.n_frames, "FetoscopyOptions.n_frames", "tracker")
        self._check_tracker_reach()
        if not 0 <= abs(self.tilt_deg) < 60:
            raise ValueError(
                f"FetoscopyOptions.tilt_deg: must be below 60 deg, got {self.tilt_deg}"
            )
        if self.black_frames is not None:
            check_frame_list(self, "black_frames", self.n_frames)
        if self.tracker_gap is not None:
            gap = check_frame_list(self, "tracker_gap")
            if len(gap) != 2 or gap[0] > gap[1]:
                raise ValueError(
                    "FetoscopyOptions.tracker_gap: expected [first, last] frames, "
                    f"got {self.tracker_gap}"
                )
            check_frame_list(self, "tracker_gap", self.n_frames)
        if self.lens_model not in LENS_MODELS:
            raise ValueError(f"FetoscopyOptions.lens_model: expected one of {LENS_MODELS}, "
                             f"got {self.lens_model!r}")
        if self.lens_distortion is not None:
            d = np.asarray(self.lens_distortion, np.float64)
            sizes, names = (((4,), "k1 k2 k3 k4") if self.lens_model == "fisheye"
                            else ((4, 5), "k1 k2 p1 p2 [k3]"))
            if d.ndim != 1 or d.size not in sizes or not np.isfinite(d).all():
                raise ValueError(
                    f"FetoscopyOptions.lens_distortion: expected {' or '.join(map(str, sizes))} "
                    f"finite numbers ({names}) for the {self.lens_model} model, got "
                    f"{self.lens_distortion}"
                )
        elif self.lens_model == "fisheye":
            raise ValueError("FetoscopyOptions.lens_model: 'fisheye' needs lens_distortion "
                             "k1 k2 k3 k4 (0 0 0 0: the pure equidistant lens)")
        check_fov_radius(self, auto=True)

    def _check_tracker_reach(self) -> None:
        """What tracking.csv would hold, within what run reads: positions within
        io.tracking.MAX_TRANSLATION_MM of the tracker's origin (the camera's reach plus the
        hand-eye offset plus NOISE_REACH_SIGMAS of the noise), and a rotation noise under
        MAX_ROTATION_SIGMA_DEG."""
        cls = "FetoscopyOptions"
        nu = f"{cls}.noise_multiplier"
        rot = self.noise_multiplier * self.rot_sigma_deg
        if not rot <= MAX_ROTATION_SIGMA_DEG:
            lead = most_changed(self, "rot_sigma_deg", "noise_multiplier")
            raise ValueError(f"{cls}.{lead}: a tracker rotation noise of {rot:.3g} deg "
                             f"({cls}.rot_sigma_deg x {nu}); at most {MAX_ROTATION_SIGMA_DEG:g} "
                             "deg (beyond, the orientation is random)")
        h = self.distance_mm * (1 + (self.distance_variation if self.motion == "handheld"
                                     else 0.0))
        check_tracker_reach(self, self.distance_mm + h + np.sqrt(2.0) * self.radius_mm,
                            "the camera moves up to", ("distance_mm", "radius_mm"),
                            self.noise_multiplier * self.trans_sigma_mm,
                            ("trans_sigma_mm", "noise_multiplier"))


# --------------------------------------------------------------------------------------------
# Small geometry helpers (numpy + scipy only, independent of fusedmosaic._core)
# --------------------------------------------------------------------------------------------


def pose_matrix(pose: np.ndarray) -> np.ndarray:
    """[r, t] (6,) or (N, 6) -> 4x4 (or (N, 4, 4)) rigid transforms."""
    pose = np.asarray(pose, np.float64)
    flat = pose.reshape(-1, 6)
    T = np.tile(np.eye(4), (flat.shape[0], 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(flat[:, :3]).as_matrix()
    T[:, :3, 3] = flat[:, 3:]
    return T[0] if pose.ndim == 1 else T


def pose_vector(T: np.ndarray) -> np.ndarray:
    """4x4 (or (N, 4, 4)) rigid transforms -> [r, t] (6,) or (N, 6)."""
    T = np.asarray(T, np.float64)
    flat = T.reshape(-1, 4, 4)
    out = np.concatenate([Rotation.from_matrix(flat[:, :3, :3]).as_rotvec(), flat[:, :3, 3]], 1)
    return out[0] if T.ndim == 2 else out


def induced_homographies(poses: np.ndarray, plane: np.ndarray, K: np.ndarray) -> np.ndarray:
    """H_k = K (R_k - t_k πᵀ) K⁻¹ for (N, 6) cam_from_world poses (paper 000 Eq. 5)."""
    poses = np.asarray(poses, np.float64).reshape(-1, 6)
    R = Rotation.from_rotvec(poses[:, :3]).as_matrix()
    A = R - poses[:, 3:, None] * np.asarray(plane, np.float64)[None, None, :]
    return K @ A @ np.linalg.inv(K)


def frame_to_reference_truth(
    poses: np.ndarray, plane: np.ndarray, K: np.ndarray, reference: int = 0
) -> np.ndarray:
    """G_k = H_ref H_k⁻¹ (frame k -> reference pixels), normalised so G[2,2] = 1."""
    H = induced_homographies(poses, plane, K)
    G = H[reference] @ np.linalg.inv(H)
    return G / G[:, 2:3, 2:3]


def _rigid(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def default_hand_eye(rot_deg: float, offset_mm: float) -> np.ndarray:
    """sensor_from_camera: a rotation of ``rot_deg`` about a fixed oblique axis and an offset of
    ``offset_mm`` along a fixed direction (mostly along the scope axis, as for a sensor mounted
    a few mm behind the tip)."""
    axis = np.array([0.3, -0.8, 0.5])
    direction = np.array([0.25, -0.4, 0.88])
    return _rigid(
        np.deg2rad(rot_deg) * axis / np.linalg.norm(axis),
        offset_mm * direction / np.linalg.norm(direction),
    )


# --------------------------------------------------------------------------------------------
# Trajectories (continuous in time so the tracker can sample them at its own rate)
# --------------------------------------------------------------------------------------------


@dataclass
class _Trajectory:
    """Camera motion over a plane through P0 with world_from_plane rotation R_p (e3 = normal
    pointing away from the camera). Returns cam_from_world poses at arbitrary times."""

    options: FetoscopyOptions
    R_p: np.ndarray  # (3, 3) world_from_plane
    P0: np.ndarray  # (3,) a point of the plane
    rng: np.random.Generator
    params: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        o = self.options
        if o.motion == "handheld":
            r = self.rng
            duration = o.n_frames / o.fps
            n_sin = 3
            # Sum of sinusoids per axis; amplitudes share the path extent radius_mm.
            freqs = r.uniform(0.3, 1.6, size=(2, n_sin)) / duration
            amps = r.dirichlet(np.ones(n_sin), size=2) * o.radius_mm
            phases = r.uniform(0, 2 * np.pi, size=(2, n_sin))
            # Rescale the frequencies so the rms in-plane speed gives step_px per frame.
            rms = np.sqrt(np.sum((2 * np.pi * freqs * amps) ** 2) / 2.0)
            target = o.step_px * o.distance_mm / (o.focal_factor * o.width) * o.fps
            freqs = freqs * (target / max(rms, 1e-12))
            self.params = {
                "freqs": freqs,
                "amps": amps,
                "phases": phases,
                "rp_f": r.uniform(0.2, 0.5, size=2),
                "rp_phase": r.uniform(0, 2 * np.pi, 2),
                "yaw_f": r.uniform(0.04, 0.08),
                "yaw_phase": r.uniform(0, 2 * np.pi),
                "h_f": r.uniform(0.1, 0.25),
                "h_phase": r.uniform(0, 2 * np.pi),
            }

    def world_from_cam(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotations (N, 3, 3) and centres (N, 3) of the camera at times t (s)."""
        o = self.options
        t = np.asarray(t, np.float64).reshape(-1)
        e1, e2, e3 = self.R_p[:, 0], self.R_p[:, 1], self.R_p[:, 2]
        if o.motion == "syn":
            # Paper 000 Sec. 4.1: xy-translation only, circular pattern; laps over n_frames.
            theta = 2.0 * np.pi * o.laps * t * o.fps / o.n_frames
            a, b = o.radius_mm * np.cos(theta), o.radius_mm * np.sin(theta)
            h = np.full_like(t, o.distance_mm)
            R = np.tile(np.eye(3), (t.size, 1, 1))
        else:
            p = self.params
            arg = 2 * np.pi * p["freqs"][:, :, None] * t + p["phases"][:, :, None]
            ab = np.sum(p["amps"][:, :, None] * np.sin(arg), axis=1)
            a, b = ab[0], ab[1]
            h = o.distance_mm * (
                1.0 + o.distance_variation * np.sin(2 * np.pi * p["h_f"] * t + p["h_phase"])
            )
            amp = np.deg2rad(o.rotation_deg)
            roll = amp * np.sin(2 * np.pi * p["rp_f"][0] * t + p["rp_phase"][0])
            pitch = amp * np.sin(2 * np.pi * p["rp_f"][1] * t + p["rp_phase"][1])
            yaw = np.deg2rad(o.yaw_deg) * np.sin(2 * np.pi * p["yaw_f"] * t + p["yaw_phase"])
            R = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], 1)).as_matrix()
        C = self.P0 + a[:, None] * e1 + b[:, None] * e2 - h[:, None] * e3
        return R, C

    def poses(self, t: np.ndarray) -> np.ndarray:
        """cam_from_world [r, t] (N, 6) at times t."""
        R_wc, C = self.world_from_cam(t)
        R_cw = np.transpose(R_wc, (0, 2, 1))
        return np.concatenate(
            [Rotation.from_matrix(R_cw).as_rotvec(), -np.einsum("nij,nj->ni", R_cw, C)], axis=1
        )


# --------------------------------------------------------------------------------------------
# Scene
# --------------------------------------------------------------------------------------------


@dataclass
class FetoscopyScene:
    """Everything :func:`generate_fetoscopy` makes; frames are rendered on demand.

    camera_matrix (3, 3); timestamps (N,) s; poses (N, 6) true cam_from_world; plane (3,) π;
    homographies (N, 3, 3) true frame -> frame-0 G_k; hand_eye (4, 4) sensor_from_camera;
    tracker_timestamps (M,); tracker_poses (M, 6) measured (noisy) cam_from_world, NaN where
    invalid; tracker_truth (M, 6) true cam_from_world at the tracker times; tracker_valid (M,);
    tracker_translations (M, 3) mm and tracker_quaternions (M, 4) (x, y, z, w) of
    tracker_from_sensor (NaN where invalid); texture (Ht, Wt, 3) BGR; frame_from_texture
    (N, 3, 3) the warps used to render; black_frames (sorted list); fov_mask_radius px or None.
    """

    options: FetoscopyOptions
    camera_matrix: np.ndarray
    timestamps: np.ndarray
    poses: np.ndarray
    plane: np.ndarray
    homographies: np.ndarray
    hand_eye: np.ndarray
    tracker_timestamps: np.ndarray
    tracker_poses: np.ndarray
    tracker_truth: np.ndarray
    tracker_valid: np.ndarray
    tracker_translations: np.ndarray
    tracker_quaternions: np.ndarray
    texture: np.ndarray
    texture_mm_per_px: float
    frame_from_texture: np.ndarray
    black_frames: list[int]
    fov_mask_radius: float | None
    # With lens_distortion: the ideal (pinhole) pixel of every raw sub-pixel sample (see
    # LENS_SUPERSAMPLE), (3 H, 3 W, 2).
    ideal_pixels: np.ndarray | None = None

    @property
    def distortion(self) -> np.ndarray | None:
        d = self.options.lens_distortion
        return None if d is None else np.asarray(d, np.float64)

    @property
    def n_frames(self) -> int:
        return self.timestamps.size

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the frames."""
        return self.options.width, self.options.height

    def fov_mask(self) -> np.ndarray | None:
        """(H, W) bool, True inside the circular field of view (centre ((W-1)/2, (H-1)/2))."""
        if self.fov_mask_radius is None:
            return None
        # camera.yaml's mask, by construction (io.calibration.Camera.fov_mask)
        w, h = self.size
        return Camera(w, h, fov_mask_radius=self.fov_mask_radius).fov_mask() > 0

    def render(self, k: int, *, noise: bool = True) -> np.ndarray:
        """Frame k, (H, W, 3) BGR uint8: the texture warped by the true M_k, its specular
        highlights (specular_light), seeded noise (the same for a given seed and k, whatever
        the order of calls), the FOV mask, and black if k is a black frame."""
        if not 0 <= k < self.n_frames:
            raise IndexError(f"frame {k} outside 0..{self.n_frames - 1}")
        w, h = self.size
        if k in self.black_frames:
            return np.zeros((h, w, 3), np.uint8)
        img = self._base(k)
        light = self.specular_light(k, img)
        # rounded to grey levels, as the checkerboard's frames: truncating made every noisy
        # frame 0.5 grey levels darker than its scene (review 47)
        if light is not None:
            img = np.clip(np.rint(img + light[:, :, None]), 0, 255).astype(np.uint8)
        sigma = self.options.image_noise_sigma
        if noise and sigma > 0:
            rng = np.random.default_rng([self.options.seed, 1, k])
            img = np.clip(np.rint(img + rng.normal(0.0, sigma, img.shape)), 0,
                          255).astype(np.uint8)
        mask = self.fov_mask()
        if mask is not None:
            img[~mask] = 0
        return img

    def _base(self, k: int) -> np.ndarray:
        """Frame k's tissue through the lens (if any): no highlights, noise, mask or black."""
        if self.ideal_pixels is None:
            return self.pinhole(k)
        # through the lens: raw sub-pixel -> ideal pixel -> texture, then averaged
        A = np.linalg.inv(self.frame_from_texture[k])
        q = self.ideal_pixels @ A[:, :2].T + A[:, 2]
        uv = (q[..., :2] / q[..., 2:]).astype(np.float32)
        img = cv2.remap(self.texture, uv[..., 0], uv[..., 1], cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REFLECT)
        return cv2.resize(img, self.size, interpolation=cv2.INTER_AREA)

    def highlight_centres(self, k: int) -> np.ndarray:
        """(L, 2) raw pixels where frame k sees its specular highlights: for each light fibre
        (specular_lights of them, light_offset_mm from the optical axis, evenly around it) the
        point of the plane that mirrors it into the camera centre, projected (through the lens,
        if any). Highlights behind the camera are left out; (0, 2) without lights."""
        o = self.options
        if o.specular_lights == 0:
            return np.zeros((0, 2))
        R_cw = Rotation.from_rotvec(self.poses[k, :3]).as_matrix()
        t = self.poses[k, 3:]
        C = -R_cw.T @ t
        phi = 2.0 * np.pi * np.arange(o.specular_lights) / o.specular_lights + np.pi / 4.0
        lights_cam = o.light_offset_mm * np.stack([np.cos(phi), np.sin(phi), 0.0 * phi], 1)
        lights = C + lights_cam @ R_cw  # world (rows: R_cw.T @ l)
        norm = float(np.linalg.norm(self.plane))
        n = self.plane / norm  # the plane: n.X = -1 / |pi|

        def side(X):
            return X @ n + 1.0 / norm

        mirrored = lights - 2.0 * side(lights)[:, None] * n
        d = mirrored - C
        spots = C + (-side(C) / (d @ n))[:, None] * d
        cam = spots @ R_cw.T + t
        cam = cam[cam[:, 2] > 1e-9]
        if len(cam) == 0:
            return np.zeros((0, 2))
        dist = self.distortion
        if dist is None:
            px = cam[:, :2] / cam[:, 2:] @ self.camera_matrix[:2, :2].T + self.camera_matrix[:2, 2]
        elif o.lens_model == "fisheye":
            px = cv2.fisheye.projectPoints(cam[:, None], np.zeros(3), np.zeros(3),
                                           self.camera_matrix, dist)[0][:, 0]
        else:
            px = cv2.projectPoints(cam, np.zeros(3), np.zeros(3), self.camera_matrix,
                                   dist)[0][:, 0]
        return np.asarray(px, np.float64)

    def specular_light(self, k: int, image: np.ndarray | None = None) -> np.ndarray | None:
        """(H, W) float32 grey levels the specular highlights add to every channel of frame k
        (before saturation), None without lights: a Gaussian glow of specular_sigma_px around
        each highlight centre, peak 420 grey levels (saturating a core of ~1.5 sigma), scaled
        by 0.5 + the tissue's grey level / 255 under it, so a core's outline follows the
        tissue. image: frame k before noise (default: rendered here)."""
        centres = self.highlight_centres(k)
        if len(centres) == 0:
            return None
        if image is None:
            image = self._base(k)
        w, h = self.size
        y, x = np.mgrid[:h, :w].astype(np.float32)
        sigma = np.float32(self.options.specular_sigma_px)
        glow = np.zeros((h, w), np.float32)
        for cx, cy in centres:
            glow += np.exp(-((x - np.float32(cx)) ** 2 + (y - np.float32(cy)) ** 2)
                           / (2 * sigma * sigma))
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.float32)
        return np.float32(420.0) * glow * (np.float32(0.5) + grey / np.float32(255.0))

    def pinhole(self, k: int) -> np.ndarray:
        """Frame k as a pinhole camera sees it: the texture warped by the true M_k, without
        lens, noise, field-of-view mask or black frames (what render gives without a lens,
        before its noise and mask; the truth a lens's undistortion is compared with)."""
        return cv2.warpPerspective(
            self.texture,
            self.frame_from_texture[k],
            self.size,
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REFLECT,
        )

    def frames(self, *, noise: bool = True) -> Iterator[np.ndarray]:
        """Render all frames lazily, in order."""
        for k in range(self.n_frames):
            yield self.render(k, noise=noise)


def generate_fetoscopy(options: FetoscopyOptions | None = None) -> FetoscopyScene:
    """Build a fetoscopy scene (poses, plane, K, timestamps, tracker samples, ground truth and a
    lazy frame renderer) without touching the disk."""
    o = FetoscopyOptions() if options is None else options
    o.validate()
    K, R_p, P0, plane, traj, timestamps, poses = _geometry(o)
    G = frame_to_reference_truth(poses, plane, K)

    # Through a lens, the view and the texture are checked first on the frame's border pixels
    # alone (with the fold check; milliseconds), then on the grid's outline, which lies at most
    # 1/3 px beyond them: the grid takes ~4.5 us a pixel (9 s at 1920x1080), and a request
    # refused for its texture took a minute and gigabytes to reach that error (review 47).
    ideal = None
    corners = _view_outline(o, K, None, border_only=True, checked=True)
    _check_view(o, _view_cosines(poses, plane, K, corners))
    lo, s, size = _texture_box(o, K, R_p, P0, poses, corners)
    _check_texture(o, size, s)
    if o.lens_distortion is not None:
        ideal = _ideal_pixels(o, K)
        corners = _view_outline(o, K, ideal)
        _check_view(o, _view_cosines(poses, plane, K, corners))
        lo, s, size = _texture_box(o, K, R_p, P0, poses, corners)
        _check_texture(o, size, s)
    tex_w, tex_h = (int(v) for v in size)
    vessel_width = _vessel_width_px(s)
    O = P0 + lo[0] * R_p[:, 0] + lo[1] * R_p[:, 1]
    texture = placenta_texture(
        (tex_h, tex_w),
        np.random.default_rng([o.seed, 2]),
        vessel_width_px=vessel_width,
    )
    R = Rotation.from_rotvec(poses[:, :3]).as_matrix()
    M = K @ np.stack([s * (R @ R_p[:, 0]), s * (R @ R_p[:, 1]), R @ O + poses[:, 3:]], axis=2)

    # EM tracker: truth at its own times, noise on [r, t] of cam_from_world, then
    # tracker_from_sensor = world_from_cam @ cam_from_sensor.
    t_tr = sample_times(o, "tracker", float(timestamps[-1]))
    truth_tr = traj.poses(t_tr)
    sigma = o.noise_multiplier * np.array(
        [np.deg2rad(o.rot_sigma_deg)] * 3 + [o.trans_sigma_mm] * 3
    )
    noisy = truth_tr + np.random.default_rng([o.seed, 3]).normal(size=truth_tr.shape) * sigma
    hand_eye = default_hand_eye(o.hand_eye_rot_deg, o.hand_eye_offset_mm)
    tracker_from_sensor = np.linalg.inv(pose_matrix(noisy)) @ np.linalg.inv(hand_eye)
    valid = np.ones(t_tr.size, bool)
    if o.tracker_gap is not None:
        valid = _tracker_gap_valid(o, timestamps, t_tr)
    translations = tracker_from_sensor[:, :3, 3].copy()
    quaternions = Rotation.from_matrix(tracker_from_sensor[:, :3, :3]).as_quat()
    translations[~valid] = np.nan
    quaternions[~valid] = np.nan
    noisy[~valid] = np.nan

    if o.fov_mask_radius == -1:
        fov = 0.48 * min(o.width, o.height) if o.motion == "handheld" else None
    else:
        fov = float(o.fov_mask_radius) if o.fov_mask_radius > 0 else None

    return FetoscopyScene(
        options=o,
        camera_matrix=K,
        timestamps=timestamps,
        poses=poses,
        plane=plane,
        homographies=G,
        hand_eye=hand_eye,
        tracker_timestamps=t_tr,
        tracker_poses=noisy,
        tracker_truth=truth_tr,
        tracker_valid=valid,
        tracker_translations=translations,
        tracker_quaternions=quaternions,
        texture=texture,
        texture_mm_per_px=s,
        frame_from_texture=M,
        black_frames=sorted({int(k) for k in o.black_frames or []}),
        fov_mask_radius=fov,
        ideal_pixels=ideal,
    )


def _geometry(o: FetoscopyOptions) -> tuple:
    """K, world_from_plane R_p, the plane's point P0, π, the trajectory, the frame times and the
    true cam_from_world poses of options ``o`` (the draws of rng [seed, 0])."""
    rng = np.random.default_rng([o.seed, 0])
    f = o.focal_factor * o.width
    K = np.array([[f, 0.0, (o.width - 1) / 2.0], [0.0, f, (o.height - 1) / 2.0], [0, 0, 1.0]])

    # Plane through P0 = (0, 0, D) seen by the virtual camera; tilted about a random in-plane
    # axis in hand-held mode.
    if o.motion == "handheld":
        phi = rng.uniform(0, 2 * np.pi)
        R_p = Rotation.from_rotvec(
            np.deg2rad(o.tilt_deg) * np.array([np.cos(phi), np.sin(phi), 0.0])
        ).as_matrix()
    else:
        R_p = np.eye(3)
    P0 = np.array([0.0, 0.0, o.distance_mm])
    e3 = R_p[:, 2]
    plane = -e3 / float(e3 @ P0) + 0.0  # n·X + d = 0 with n = e3, d = -e3·P0; π = n/d

    traj = _Trajectory(o, R_p, P0, rng)
    timestamps = frame_times(o, o.n_frames)
    poses = traj.poses(timestamps) + 0.0  # (+ 0.0 turns -0.0 into 0.0 in the files)
    return K, R_p, P0, plane, traj, timestamps, poses


def _check_texture(o: FetoscopyOptions, size: np.ndarray, s: float) -> None:
    """ValueError naming the likely cause when the texture of ``size`` (width, height) px at
    ``s`` mm/px is over MAX_TEXTURE_PX, or would take over MAX_TEXTURE_SECONDS or
    MAX_TEXTURE_GB to draw."""
    cls = "FetoscopyOptions"
    if not np.prod(size) <= MAX_TEXTURE_PX:
        lead, remedy = _size_remedies(o, lambda box: float(np.prod(box[2])))
        raise ValueError(
            f"{cls}.{lead}: the camera path needs a {size[0]:.3g}x"
            f"{size[1]:.3g} px texture (its pixels as fine as a frame's: {cls}.focal_factor x "
            f"{cls}.width px per {cls}.distance_mm); at most {MAX_TEXTURE_PX:.3g} px: {remedy}"
        )
    tex_w, tex_h = (int(v) for v in size)
    vessel_width = _vessel_width_px(s)
    seconds, gigabytes = placenta_texture_cost((tex_h, tex_w), vessel_width)
    if seconds > MAX_TEXTURE_SECONDS or gigabytes > MAX_TEXTURE_GB:
        lead, remedy = _size_remedies(o, _texture_cost_ratio)
        raise ValueError(
            f"{cls}.{lead}: the camera path needs a {tex_w}x{tex_h} px texture with "
            f"{vessel_width:.3g} px vessels (its pixels as fine as a frame's: {cls}.focal_factor "
            f"x {cls}.width px per {cls}.distance_mm), which takes about {seconds:.0f} s and "
            f"{gigabytes:.2g} GB to draw; at most {MAX_TEXTURE_SECONDS:g} s and "
            f"{MAX_TEXTURE_GB:g} GB (textures.placenta_texture_cost): {remedy}"
        )


def _view_outline(o: FetoscopyOptions, K: np.ndarray, ideal: np.ndarray | None,
                  border_only: bool = False, checked: bool = False) -> np.ndarray:
    """(3, P) homogeneous ideal pixels outlining what a frame shows (its corners; through a
    lens, the ideal pixels of its border, beyond the corners for a barrel lens): the whole
    frame, FOV mask or not, which the renderer warps (the mask blacks it afterwards) and the
    texture box covers, so _check_view refuses a corner past the horizon too. ideal: the
    scene's ideal pixel grid (_ideal_pixels); with ``border_only`` (and no grid) the lens's
    border is undistorted alone, pixel by pixel (cheap: the remedies' estimates, and
    generate_fetoscopy's first checks), and with ``checked`` refused as _ideal_pixels refuses
    a lens that folds over there."""
    if o.lens_distortion is None:
        return np.array([[0, 0, 1], [o.width - 1, 0, 1], [0, o.height - 1, 1],
                         [o.width - 1, o.height - 1, 1.0]]).T
    if ideal is None and border_only:
        border = ideal_border(K, np.asarray(o.lens_distortion, np.float64), o.lens_model,
                              o.width, o.height, _LENS_OPTION if checked else None)
    else:
        border = np.concatenate([ideal[0], ideal[-1], ideal[:, 0], ideal[:, -1]])
    return np.hstack([border, np.ones((len(border), 1))]).T


def _chunks(n_frames: int, n_points: int) -> Iterator[slice]:
    """Frames at a time so that (chunk, 3, n_points) float64 stays <= 100 MB."""
    chunk = max(1, 2**22 // n_points)
    for k in range(0, n_frames, chunk):
        yield slice(k, k + chunk)


def _view_cosines(poses: np.ndarray, plane: np.ndarray, K: np.ndarray,
                  corners: np.ndarray) -> np.ndarray:
    """(N,) per frame, the smallest cosine between a ray through the ideal pixels ``corners``
    (3, P) and the plane's normal (pointing away from the camera): 1 / the farthest range at
    which the frame sees the plane, in camera-plane distances; <= 0 when a ray misses the plane
    (it meets it behind the camera: the view reaches past the plane's horizon). The cosine is
    quasi-concave over the image, so a region's outline holds its smallest value."""
    rays = np.linalg.solve(K, corners)
    rays /= np.linalg.norm(rays, axis=0)
    normal = -plane / np.linalg.norm(plane)
    out = np.empty(len(poses))
    for k in _chunks(len(poses), rays.shape[1]):
        R_cw = Rotation.from_rotvec(poses[k, :3]).as_matrix()
        out[k] = ((R_cw @ normal) @ rays).min(axis=1)
    return out


def _check_view(o: FetoscopyOptions, cosines: np.ndarray) -> None:
    """ValueError naming the likely cause when a frame sees the plane beyond MAX_VIEW_RANGE x
    its distance from it, or past its horizon (rays that meet it behind the camera, which
    warpPerspective still paints from the texture, mirrored, and whose G_k lands at negative
    depth)."""
    limit = 1.0 / MAX_VIEW_RANGE
    bad = np.flatnonzero(~(cosines >= limit))
    if bad.size == 0:
        return
    cls = "FetoscopyOptions"
    worst = int(bad[np.argmin(cosines[bad])])
    c = float(cosines[worst])
    angle = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
    if c > 0:
        sees = (f"sees the plane {1.0 / c:.3g}x as far as the camera is from it (a ray "
                f"{angle:.3g} deg from the plane's normal)")
    else:
        sees = (f"reaches past the plane's horizon (a ray {angle:.3g} deg from the plane's "
                "normal meets it behind the camera)")
    defaults = {f.name: f.default for f in dataclass_fields(o)}
    worse = {"focal_factor": o.focal_factor < defaults["focal_factor"]}  # a wider view
    remedy = f"raise {cls}.focal_factor"
    if o.motion == "handheld":
        worse["tilt_deg"] = abs(o.tilt_deg) > abs(defaults["tilt_deg"])
        worse["rotation_deg"] = abs(o.rotation_deg) > abs(defaults["rotation_deg"])
        remedy = f"lower {cls}.tilt_deg or {cls}.rotation_deg, or " + remedy
    if o.lens_distortion is not None:
        remedy += f", or a milder {cls}.lens_distortion"
    causes = [name for name, yes in worse.items() if yes]
    if causes:
        lead = most_changed(o, *causes)
    else:
        lead = ("lens_distortion" if o.lens_distortion is not None
                else "tilt_deg" if o.motion == "handheld" else "focal_factor")
    more = f" (and {bad.size - 1} more frames)" if bad.size > 1 else ""
    raise ValueError(
        f"{cls}.{lead}: frame {worst}{more} {sees}; a frame may see it at most "
        f"{MAX_VIEW_RANGE:g}x as far ({np.degrees(np.arccos(limit)):.3g} deg from the normal): "
        f"{remedy}"
    )


def _vessel_width_px(s: float) -> float:
    """Width of the root vessels in a texture of s mm/px (9 px at 1/16 mm/px)."""
    return 9.0 * (0.0625 / s) ** 0.5


def _texture_box(o: FetoscopyOptions, K: np.ndarray, R_p: np.ndarray, P0: np.ndarray,
                 poses: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """The texture covering every frame: (lo (2,) its corner in plane mm about P0, s its mm/px,
    size (2,) its width and height, px)."""
    # Plane coordinates (mm) of every frame corner, then a margin.
    R = Rotation.from_rotvec(poses[:, :3]).as_matrix()
    M1 = K @ np.stack(
        [R @ R_p[:, 0], R @ R_p[:, 1], R @ P0 + poses[:, 3:]], axis=2
    )  # plane mm (about P0) -> frame px
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for k in _chunks(o.n_frames, corners.shape[1]):
        M1k = M1[k]
        uv = np.linalg.solve(M1k, np.broadcast_to(corners, (len(M1k), 3, corners.shape[1])))
        uv = (uv[:, :2] / uv[:, 2:3]).transpose(0, 2, 1).reshape(-1, 2)
        lo, hi = np.minimum(lo, uv.min(0)), np.maximum(hi, uv.max(0))
    f = o.focal_factor * o.width
    closest = o.distance_mm * (1.0 - (o.distance_variation if o.motion == "handheld" else 0.0))
    s = closest / f  # texture mm/px: never coarser than a frame pixel
    margin = 16 * s
    lo, hi = lo - margin, hi + margin
    return lo, s, np.ceil((hi - lo) / s)


def _texture_cost_ratio(box) -> float:
    """The placenta texture's estimated cost over its bound (time or memory, the larger)."""
    _, s, size = box
    seconds, gigabytes = placenta_texture_cost((size[1], size[0]), _vessel_width_px(s))
    return max(seconds / MAX_TEXTURE_SECONDS, gigabytes / MAX_TEXTURE_GB)


def _size_remedies(o: FetoscopyOptions, measure) -> tuple[str, str]:
    """(the option to name, "lower A, B or C, or raise D"): the size options that, halved or
    doubled, make ``measure`` (of _texture_box's result) smaller, each tried on a copy of the
    options (the path is redrawn: the same random draws). A wider view can grow the texture
    (a tilted plane's far side) as well as shrink it (fewer pixels per mm), so none is assumed.
    The option named is the one furthest from its default among those."""
    base = measure(_options_box(o))
    tries = [("focal_factor", "lower", o.focal_factor / 2), ("width", "lower", o.width // 2),
             ("radius_mm", "lower", o.radius_mm / 2), ("distance_mm", "raise", 2 * o.distance_mm)]
    if o.motion == "handheld":
        tries += [("distance_variation", "lower", o.distance_variation / 2),
                  ("tilt_deg", "lower", o.tilt_deg / 2),
                  ("rotation_deg", "lower", o.rotation_deg / 2),
                  ("step_px", "lower", o.step_px / 2)]
    tries.append(("focal_factor", "raise", 2 * o.focal_factor))
    helps: dict[str, list[str]] = {"lower": [], "raise": []}
    for name, way, value in tries:
        if value == getattr(o, name) or name in helps["lower"]:
            continue
        try:
            smaller = measure(_options_box(replace(o, **{name: value}))) < base
        except ValueError:  # the change is itself refused
            smaller = False
        if smaller:
            helps[way].append(name)
    cls = "FetoscopyOptions"
    parts = [f"{way} " + _or_list([f"{cls}.{n}" for n in names])
             for way, names in helps.items() if names]
    named = helps["lower"] + helps["raise"]
    if not named:
        return "width", f"lower {cls}.width or {cls}.height"
    return most_changed(o, *named), ", or ".join(parts)


def _or_list(items: list[str]) -> str:
    """"a", "a or b", "a, b or c"."""
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " or " + items[-1]


def _options_box(o: FetoscopyOptions) -> tuple[np.ndarray, float, np.ndarray]:
    """_texture_box of options ``o`` (validated; lens border undistorted alone); ValueError
    when the options are refused or the view reaches beyond MAX_VIEW_RANGE."""
    o.validate()
    K, R_p, P0, plane, _, _, poses = _geometry(o)
    corners = _view_outline(o, K, None, border_only=True)
    _check_view(o, _view_cosines(poses, plane, K, corners))
    return _texture_box(o, K, R_p, P0, poses, corners)


def _tracker_gap_valid(o: FetoscopyOptions, timestamps: np.ndarray,
                       t_tr: np.ndarray) -> np.ndarray:
    """(M,) validity of the tracker samples at t_tr for tracker_gap = [first, last]: a reader
    (io.tracking.interpolate_camera_poses, the one run uses) flags exactly frames first..last
    untracked. It flags the frames inside a hole between valid samples longer than
    GAP_SPACINGS sample spacings, and every frame in it: the samples from frame first's time to
    frame last's are dropped, and if that hole is too short, the widest hole that leaves frames
    first - 1 and last + 1 out (from the first sample at or after frame first - 1 to the last
    at or before frame last + 1). ValueError when neither works (a gap of one or two frames at
    40 Hz and 25 fps: a 75 ms hole needs about three frame periods)."""
    first, last = (int(v) for v in o.tracker_gap)
    frames = np.arange(timestamps.size)
    wanted = (frames >= first) & (frames <= last)
    # the samples that bound the widest hole (none before frame 0 / after the last frame)
    start = t_tr[t_tr >= timestamps[first - 1]].min() if first > 0 else -np.inf
    end = t_tr[t_tr <= timestamps[last + 1]].max() if last + 1 < timestamps.size else np.inf
    flagged = wanted
    for drop in ((t_tr >= timestamps[first]) & (t_tr <= timestamps[last]),
                 (t_tr > start) & (t_tr < end)):
        flagged = _untracked_frames(timestamps, t_tr, ~drop)
        if np.array_equal(flagged, wanted):
            return ~drop
    cls = "FetoscopyOptions"
    asked = f"frames {first}..{last}" if last > first else f"frame {first}"
    got = np.flatnonzero(flagged)
    got = "none" if got.size == 0 else f"frames {got[0]}..{got[-1]}" if np.all(
        np.diff(got) == 1) else f"frames {got.tolist()}"
    raise ValueError(
        f"{cls}.tracker_gap: {asked} cannot be untracked alone with a "
        f"tracker at {o.tracker_rate_hz:g} Hz ({cls}.tracker_rate_hz): a reader (io.tracking."
        "interpolate_camera_poses) flags the frames inside a hole between valid samples over "
        f"{GAP_SPACINGS:g} sample spacings ({GAP_SPACINGS / o.tracker_rate_hz * 1e3:.3g} ms), "
        f"and the widest hole between frames {first - 1} and {last + 1} flags {got}: "
        "give a longer gap or a faster tracker"
    )


def _untracked_frames(timestamps: np.ndarray, t_tr: np.ndarray,
                      valid: np.ndarray) -> np.ndarray:
    """(N,) the frames a reader of tracking.csv (io.tracking.interpolate_camera_poses) flags
    untracked, given which samples are valid (all, when it refuses the samples)."""
    m = t_tr.size
    quaternions = np.tile([0.0, 0.0, 0.0, 1.0], (m, 1))
    samples = TrackingSamples(t_tr, np.zeros((m, 3)), quaternions, valid)
    try:
        _, tracked = interpolate_camera_poses(samples, timestamps, allow_outside=True)
    except ValueError:  # e.g. under 2 valid samples
        return np.ones(timestamps.size, bool)
    return ~tracked


# Raw pixels are rendered as the mean of LENS_SUPERSAMPLE^2 samples: a barrel lens compresses
# the periphery, where one sample per pixel would alias (a lens integrates over the pixel).
LENS_SUPERSAMPLE = 3
_LENS_OPTION = "FetoscopyOptions.lens_distortion"  # what a lens that folds over is blamed on


def _ideal_pixels(o: FetoscopyOptions, K: np.ndarray) -> np.ndarray:
    """(S H, S W, 2) ideal pixel of every raw sub-pixel sample (S = LENS_SUPERSAMPLE) through
    the lens; refuses a lens whose model folds over within the frame (_lens.ideal_pixel_grid)."""
    return ideal_pixel_grid(K, np.asarray(o.lens_distortion, np.float64), o.lens_model,
                            o.width, o.height, LENS_SUPERSAMPLE, _LENS_OPTION)


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def _poses_csv(poses: np.ndarray) -> str:
    lines = ["frame,rx,ry,rz,tx,ty,tz"]
    lines += [",".join([str(k), *(repr(float(v)) for v in p)]) for k, p in enumerate(poses)]
    return "\n".join(lines) + "\n"


def _plane_json(plane: np.ndarray) -> str:
    d = 1.0 / float(np.linalg.norm(plane))
    return (
        json.dumps(
            {
                "plane": [float(v) for v in plane],
                "normal": [float(v) for v in plane * d],
                "distance_mm": d,
            },
            indent=2,
        )
        + "\n"
    )


def simulate_fetoscopy(
    out: str | Path, options: FetoscopyOptions | None = None, *, overwrite: bool = False
) -> Path:
    """Generate a fetoscopy dataset folder (dataset contract of design.md) at ``out``.

    Writes frames/, frames.csv, camera.yaml (K, distortion, fov_mask_radius), tracking.csv,
    hand_eye.txt, ground_truth.csv, and for evaluation truth_poses.csv (frame,rx,ry,rz,tx,ty,tz
    of the true cam_from_world), truth_plane.json ({"plane", "normal", "distance_mm"}) and
    simulation.json (the options used)."""
    from fusedmosaic.io import Camera, TrackingSamples, write_dataset

    scene = generate_fetoscopy(options)
    o = scene.options
    camera = Camera(
        o.width,
        o.height,
        camera_matrix=scene.camera_matrix,
        distortion=scene.distortion,
        fov_mask_radius=scene.fov_mask_radius,
        lens_model=o.lens_model,
    )
    tracking = TrackingSamples(
        scene.tracker_timestamps,
        scene.tracker_translations,
        scene.tracker_quaternions,
        scene.tracker_valid,
    )
    info = {
        "simulator": "fetoscopy",
        "options": asdict(o),
        "texture_mm_per_px": scene.texture_mm_per_px,
    }
    root = write_dataset(
        out,
        camera=camera,
        frames=scene.frames(),
        timestamps=scene.timestamps,
        tracking=tracking,
        hand_eye=scene.hand_eye,
        ground_truth=scene.homographies,
        extra_files={
            "truth_poses.csv": _poses_csv(scene.poses),
            "truth_plane.json": _plane_json(scene.plane),
            "simulation.json": json.dumps(info, indent=2) + "\n",
        },
        overwrite=overwrite,
    )
    return root
