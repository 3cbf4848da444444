"""Calibration recording simulator: a tracked endoscope waved over a printed checkerboard.

What a user records before mosaicking (paper 000 Sec. 4.1: "the fetoscope was pre-calibrated
... We also pre-computed ... the Hand-eye Calibration matrix from a sequence of images of a
checkerboard as well as synchronized sensor poses"): a video of a checkerboard seen from varied
angles while the EM tracker reports the sensor on the scope. The ground truth is what
``fusedmosaic calibrate`` must recover: the intrinsics with their lens distortion
(truth_camera.yaml) and sensor_from_camera (truth_hand_eye.txt).

Conventions:

- board frame: inner corner (i, j) (i along a row, j down the columns) at (i s, j s, 0) mm,
  z pointing into the board (away from a camera that sees it), so a camera looking at the board
  with identity rotation sees i to the right and j downwards.
- the scope rests at each of ``n_views`` random views (tilt up to ``tilt_deg`` about a random
  axis, roll up to ``roll_deg``, distance about ``distance_mm``) and moves to the next one; the
  board is fully in view at every rest, not necessarily while moving.
- tracking.csv holds tracker_from_sensor at the tracker's own rate, stamped tracker_delay_s
  late (the sample of the frame at time t says t + tracker_delay_s); its noise is a rotation of
  N(0, rot_sigma_deg) per axis applied in the sensor frame and a translation of
  N(0, trans_sigma_mm) per axis in the tracker frame.
- frames are rendered through the distorted camera (OpenCV's model: k1, k2, p1, p2; or its
  fisheye model: ``fisheye`` k1..k4), each pixel averaged over 3x3 samples, plus Gaussian
  noise.
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from fusedmosaic.io.calibration import project_points
from fusedmosaic.simulation._lens import ideal_pixel_grid, on_inner_branch
from fusedmosaic.simulation._options import (
    MAX_ROTATION_SIGMA_DEG,
    check_frame_count,
    check_hand_eye,
    check_recording,
    check_signs,
    check_time_offsets,
    check_tracker_reach,
    check_types,
    frame_times,
    sample_times,
)
from fusedmosaic.simulation._options import option as _opt
from fusedmosaic.simulation.fetoscopy import default_hand_eye, pose_matrix

SUPERSAMPLE = 3  # samples per pixel side when rendering (anti-aliased board edges)
TEXTURE_PX_PER_SQUARE = 96  # board texture resolution
MIN_SQUARE_PX = 6.0  # a board square's width in the image at the farthest views, at least
# tracker_from_board: the board lies in front of the field generator (any fixed rigid pose).
TRACKER_FROM_BOARD = pose_matrix(np.array([0.25, -0.15, 0.4, 30.0, -20.0, 160.0]))


@dataclass
class CheckerboardOptions:
    """Options of :func:`generate_checkerboard` (the CLI builds its flags from these fields)."""

    board_cols: int = _opt(9, "inner corners per board row")
    board_rows: int = _opt(6, "inner corners per board column")
    square_mm: float = _opt(2.0, "side of a board square, mm")
    n_views: int = _opt(20, "views the scope rests at")
    frames_per_view: int = _opt(8, "frames from one view to the next (half resting, half moving)")
    width: int = _opt(480, "frame width, px")
    height: int = _opt(480, "frame height, px")
    focal_factor: float = _opt(1.0, "focal length in px / image width")
    principal_offset_px: float = _opt(
        8.0, "principal point offset from the image centre, px, along (0.8, -0.6) (right and "
        "up; negative: left and down)")
    k1: float = _opt(-0.30, "radial distortion k1 (fetoscopes: strong barrel)")
    k2: float = _opt(0.10, "radial distortion k2")
    p1: float = _opt(0.0008, "tangential distortion p1")
    p2: float = _opt(-0.0005, "tangential distortion p2")
    fisheye: list[float] | None = _opt(
        None, "k1 k2 k3 k4 of OpenCV's fisheye (equidistant) model: render through that lens "
        "instead (k1..p2 unused)")
    distance_mm: float = _opt(30.0, "mean camera-board distance at the views, mm")
    distance_variation: float = _opt(0.2, "relative spread of that distance")
    tilt_deg: float = _opt(35.0, "largest view tilt from the board normal, deg")
    roll_deg: float = _opt(60.0, "largest roll about the viewing axis, deg")
    fps: float = _opt(25.0, "frame rate")
    tracker_rate_hz: float = _opt(40.0, "EM tracker rate")
    tracker_offset_s: float = _opt(0.0071, "tracker clock phase vs frames")
    tracker_margin_s: float = _opt(0.1, "tracker samples extend this far beyond the frames")
    tracker_delay_s: float = _opt(
        0.0, "tracker timestamps late by this much against the frames' (unsynchronised clocks)")
    rot_sigma_deg: float = _opt(
        0.9, "EM tracker rotation noise std (paper 000 Sec. 4.1: Aurora in the laboratory)")
    trans_sigma_mm: float = _opt(0.25, "EM tracker translation noise std (same source)")
    hand_eye_rot_deg: float = _opt(4.0, "sensor_from_camera rotation angle")
    hand_eye_offset_mm: float = _opt(
        6.0, "sensor_from_camera translation, mm, along a fixed direction mostly along the scope "
        "axis (negative: the opposite way)")
    image_noise_sigma: float = _opt(2.0, "std of per-frame Gaussian image noise, gray levels")
    seed: int = _opt(0, "seed of every random draw (views, noise)")

    def validate(self) -> None:
        """Raise ValueError naming the first bad option (every number finite, signs and
        ranges; the lens's invertibility over the frame is checked by generate_checkerboard,
        which builds the camera matrix)."""
        name = type(self).__name__
        check_types(self, whole=("board_cols", "board_rows", "n_views", "frames_per_view",
                                 "width", "height"))
        for key, low in (("board_cols", 2), ("board_rows", 2), ("n_views", 1),
                         ("frames_per_view", 2), ("width", 64), ("height", 64)):
            if getattr(self, key) < low:
                raise ValueError(f"{name}.{key}: must be >= {low}, got {getattr(self, key)}")
        frames_name = f"{name}.n_views x {name}.frames_per_view"
        check_frame_count(self, self.n_views * self.frames_per_view, frames_name)
        check_signs(self, positive=("square_mm", "focal_factor", "distance_mm", "fps",
                                    "tracker_rate_hz"),
                    non_negative=("rot_sigma_deg", "trans_sigma_mm", "image_noise_sigma",
                                  "tracker_margin_s", "tilt_deg", "roll_deg"))
        check_time_offsets(self, "tracker_offset_s", "tracker_delay_s")
        check_hand_eye(self)
        if not 0 <= self.distance_variation < 0.9:
            raise ValueError(f"{name}.distance_variation: must be in [0, 0.9), "
                             f"got {self.distance_variation}")
        if self.tilt_deg >= 70:
            raise ValueError(f"{name}.tilt_deg: must be below 70 deg, got {self.tilt_deg}")
        check_recording(self, self.n_views * self.frames_per_view, frames_name, "tracker")
        self._check_tracker_reach()
        # the principal point (offset along (0.8, -0.6)) in the frame's middle half, as in a
        # real scope, and squares big enough to find the corners at the farthest views
        shift = abs(self.principal_offset_px) * np.array([0.8, 0.6])
        if not (np.isfinite(self.principal_offset_px)
                and np.all(shift <= np.array([self.width, self.height]) / 4)):
            raise ValueError(f"{name}.principal_offset_px: the principal point must stay in "
                             f"the middle half of the {self.width}x{self.height} frame "
                             f"(|offset| <= {min(self.width / 3.2, self.height / 2.4):g} px), "
                             f"got {self.principal_offset_px}")
        far_mm = self.distance_mm * (1 + self.distance_variation)
        square_px = self.focal_factor * self.width * self.square_mm / far_mm
        if square_px < MIN_SQUARE_PX:
            raise ValueError(f"{name}.focal_factor: a {self.square_mm:g} mm square at the "
                             f"farthest views ({far_mm:g} mm) would be {square_px:.3g} px wide "
                             f"with focal factor {self.focal_factor:g}, under the "
                             f"{MIN_SQUARE_PX:g} px the corner finder needs: raise "
                             f"{name}.focal_factor or {name}.square_mm, or lower "
                             f"{name}.distance_mm")
        if self.fisheye is not None and (np.asarray(self.fisheye).shape != (4,)
                                         or not np.isfinite(self.fisheye).all()):
            raise ValueError(f"{name}.fisheye: expected 4 finite numbers k1 k2 k3 k4, got "
                             f"{self.fisheye}")

    def _check_tracker_reach(self) -> None:
        """What tracking.csv would hold, within what run / calibrate read: positions within
        io.tracking.MAX_TRANSLATION_MM of the tracker's origin (the board's place, the views'
        reach, the hand-eye offset and NOISE_REACH_SIGMAS of the noise), and a rotation noise
        under MAX_ROTATION_SIGMA_DEG."""
        name = type(self).__name__
        if not self.rot_sigma_deg <= MAX_ROTATION_SIGMA_DEG:
            raise ValueError(f"{name}.rot_sigma_deg: at most {MAX_ROTATION_SIGMA_DEG:g} deg "
                             f"(beyond, the orientation is random), got {self.rot_sigma_deg}")
        board = self.square_mm * np.hypot(self.board_cols - 1, self.board_rows - 1)
        camera = (float(np.linalg.norm(TRACKER_FROM_BOARD[:3, 3])) + 1.5 * board
                  + self.distance_mm * (1 + self.distance_variation))
        check_tracker_reach(self, camera, "the views reach", ("distance_mm", "square_mm"),
                            self.trans_sigma_mm, ("trans_sigma_mm",))

    @property
    def lens_model(self) -> str:
        return "pinhole" if self.fisheye is None else "fisheye"

    @property
    def lens_options(self) -> str:
        """The options that set the lens coefficients, as error messages name them."""
        names = ("fisheye",) if self.fisheye is not None else ("k1", "k2", "p1", "p2")
        return ", ".join(f"{type(self).__name__}.{n}" for n in names)


@dataclass(eq=False)
class CheckerboardScene:
    """A simulated calibration recording.

    camera_matrix (3, 3), distortion (4,) k1 k2 p1 p2 (fisheye: k1..k4): the true
    intrinsics; hand_eye (4, 4) sensor_from_camera; tracker_from_board (4, 4); timestamps (N,)
    frame times; cam_from_board (N, 4, 4) true camera poses; resting (N,) frames at a view (the
    board fully visible); tracker_timestamps (M,), tracker_from_sensor (M, 4, 4) noisy samples;
    ideal_pixels (3 H, 3 W, 2): the ideal (pinhole) pixel of every raw sub-pixel sample the
    frames are rendered from (SUPERSAMPLE per side).
    """

    options: CheckerboardOptions
    camera_matrix: np.ndarray
    distortion: np.ndarray
    hand_eye: np.ndarray
    tracker_from_board: np.ndarray
    timestamps: np.ndarray
    cam_from_board: np.ndarray
    resting: np.ndarray
    tracker_timestamps: np.ndarray
    tracker_from_sensor: np.ndarray
    ideal_pixels: np.ndarray | None = None

    def board_points(self) -> np.ndarray:
        """(rows * cols, 3) inner corners in the board frame, row by row (mm)."""
        o = self.options
        j, i = np.mgrid[0:o.board_rows, 0:o.board_cols]
        return np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], 1) * o.square_mm

    def projected_detections(self, noise_px: float, rng: np.random.Generator):
        """The board corners of every frame that shows the whole board (2 px inside the image),
        projected through the true camera with Gaussian noise of noise_px (the board search's
        is ~0.05 px), as estimation.calibration.BoardDetections: calibration without
        rendering and searching the frames."""
        from fusedmosaic.estimation.calibration import BoardDetections

        o = self.options
        obj = self.board_points()
        points, frames = [], []
        for k, T in enumerate(self.cam_from_board):
            uv = project_points(obj, self.camera_matrix, self.distortion, o.lens_model,
                                Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3])
            if (uv.min() >= 2 and uv[:, 0].max() <= o.width - 3
                    and uv[:, 1].max() <= o.height - 3):
                points.append(uv + rng.normal(0.0, noise_px, uv.shape))
                frames.append(k)
        frames = np.array(frames)
        return BoardDetections(points, frames, frames, self.timestamps[frames],
                               (o.width, o.height))

    def frames(self) -> Iterator[np.ndarray]:
        """The frames, (H, W) gray uint8, rendered one at a time."""
        o = self.options
        texture, mm_per_px, origin_mm = _board_texture(o)
        s = SUPERSAMPLE
        if self.ideal_pixels is None:
            self.ideal_pixels = _ideal_pixels(o, self.camera_matrix, self.distortion)
        ideal = self.ideal_pixels.reshape(-1, 1, 2)
        rng = np.random.default_rng([o.seed, 4])
        last_T, clean = None, None
        for T in self.cam_from_board:
            if last_T is not None and np.array_equal(T, last_T):  # resting at a view: the
                # same noise-free render (about half the frames)
                yield self._noisy(clean, rng)
                continue
            # Ray (x, y, 1) = K^-1 (u, v, 1) meets the board at (bx, by, 1) ~ [r1 r2 t]^-1
            # (x, y, 1): a homography of the ideal pixels (cv2.perspectiveTransform, in
            # float64; 3x faster than the NumPy product).
            M = np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]])
            H = np.linalg.inv(M) @ np.linalg.inv(self.camera_matrix)
            b = cv2.perspectiveTransform(ideal, H).reshape(-1, 2)
            bx, by = b[:, 0], b[:, 1]
            # behind the camera, or at the horizon, where perspectiveTransform gives (0, 0)
            # for |w| <= FLT_EPSILON
            behind = ideal[:, 0] @ H[2, :2] + H[2, 2] <= np.finfo(np.float32).eps
            map_x = ((bx - origin_mm[0]) / mm_per_px).astype(np.float32)
            map_y = ((by - origin_mm[1]) / mm_per_px).astype(np.float32)
            map_x[behind] = -1e6
            fine = cv2.remap(texture, map_x.reshape(o.height * s, o.width * s),
                             map_y.reshape(o.height * s, o.width * s), cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=110.0)
            clean = cv2.resize(fine, (o.width, o.height), interpolation=cv2.INTER_AREA)
            last_T = T
            yield self._noisy(clean, rng)

    def _noisy(self, image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        if self.options.image_noise_sigma > 0:
            image = image + rng.normal(0.0, self.options.image_noise_sigma, image.shape)
        return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _board_texture(o: CheckerboardOptions) -> tuple[np.ndarray, float, np.ndarray]:
    """The printed board: (rows + 1) x (cols + 1) squares, the one left of and above inner
    corner (0, 0) dark, a one-square white margin. Returns the image (float32, 0..255), mm per
    texture pixel and the board coordinates (mm) of texture pixel (0, 0)'s centre."""
    q = TEXTURE_PX_PER_SQUARE
    nx, ny = o.board_cols + 3, o.board_rows + 3  # squares incl. margin
    jj, ii = np.mgrid[0:ny * q, 0:nx * q] // q
    dark = ((ii + jj) % 2 == 0) & (ii >= 1) & (jj >= 1) & (ii <= nx - 2) & (jj <= ny - 2)
    texture = np.where(dark, 25.0, 235.0).astype(np.float32)
    mm_per_px = o.square_mm / q
    # Inner corner (0, 0) sits at the corner between squares (1, 1) and (2, 2) -> pixel 2q.
    origin_mm = np.array([-2 * o.square_mm + 0.5 * mm_per_px] * 2)
    return texture, mm_per_px, origin_mm


def _ideal_pixels(o: CheckerboardOptions, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """The ideal pixel behind every raw sub-pixel sample; ValueError naming the lens options
    when the lens model folds over within the frame (the check simulate fetoscopy makes)."""
    return ideal_pixel_grid(K, dist, o.lens_model, o.width, o.height, SUPERSAMPLE,
                            o.lens_options)


def _random_view(o: CheckerboardOptions, K, dist, rng, corners) -> np.ndarray:
    """cam_from_board of a random view that sees every inner corner (with a margin of 4 % of
    the image; a corner beyond the lens model's fold that projects into the image is not
    seen there), ValueError if none is found."""
    centre = corners.mean(0)
    extent = corners.max(0) - corners.min(0)
    margin = 0.04 * min(o.width, o.height)
    for _ in range(500):
        target = centre + rng.uniform(-0.5, 0.5, 3) * extent * np.array([1, 1, 0])
        phi = rng.uniform(0, 2 * np.pi)
        tilt = np.deg2rad(o.tilt_deg) * np.sqrt(rng.uniform())
        roll = np.deg2rad(rng.uniform(-o.roll_deg, o.roll_deg))
        board_from_cam = Rotation.from_rotvec(tilt * np.array([np.cos(phi), np.sin(phi), 0])) \
            * Rotation.from_rotvec([0, 0, roll])
        d = o.distance_mm * (1 + rng.uniform(-o.distance_variation, o.distance_variation))
        position = target - d * board_from_cam.apply([0.0, 0.0, 1.0])
        R = board_from_cam.inv()
        t = -R.apply(position)
        uv = project_points(corners, K, dist, o.lens_model, R.as_rotvec(), t)
        if (uv.min() >= margin and uv[:, 0].max() <= o.width - 1 - margin
                and uv[:, 1].max() <= o.height - 1 - margin
                and on_inner_branch(uv, R.apply(corners) + t, K, dist, o.lens_model)):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R.as_matrix(), t
            return T
    name = type(o).__name__
    # The board's inner corners facing the camera at the farthest views, through a pinhole:
    # wider than the image there, the focal length is the first suspect (--focal-factor 1e6
    # was told to raise the distance or give a milder lens).
    far_mm = o.distance_mm * (1 + o.distance_variation)
    board_px = K[0, 0] * float(np.max(extent[:2])) / far_mm
    room = min(o.width, o.height) - 2 * margin
    advice = (f"raise {name}.distance_mm, lower {name}.square_mm, or give a milder lens"
              if board_px <= room else
              f"at the farthest views ({far_mm:g} mm) it would span {board_px:.3g} px with "
              f"{name}.focal_factor {o.focal_factor:g}, where the image leaves {room:.0f} px: "
              f"lower {name}.focal_factor (or raise {name}.distance_mm, lower "
              f"{name}.square_mm)")
    raise ValueError(
        f"{name}: no view shows the whole {o.board_cols}x{o.board_rows} board inside the "
        f"{o.width}x{o.height} image through the lens ({o.lens_options} = "
        f"{', '.join(f'{v:.3g}' for v in dist)}): {advice}")


def _path(views: np.ndarray, period: float, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_board at `times` along the path resting at view v during [v, v + 1/2) * period
    and moving to view v + 1 over the second half (smoothstep, SLERP of board_from_cam); and a
    mask of the times at rest."""
    world = np.linalg.inv(views)  # board_from_cam: interpolate the camera in the board frame
    n = len(views)
    v = np.clip(np.floor(times / period).astype(int), 0, n - 1)
    tau = np.clip((times - v * period) / period, 0.0, 1.0)
    u = np.clip((tau - 0.5) / 0.5, 0.0, 1.0)
    u = np.where(v >= n - 1, 0.0, u * u * (3 - 2 * u))
    out = np.tile(np.eye(4), (times.size, 1, 1))
    for k in range(times.size):
        a, b = world[v[k]], world[min(v[k] + 1, n - 1)]
        slerp = Slerp([0, 1], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))
        out[k, :3, :3] = slerp([u[k]]).as_matrix()[0]
        out[k, :3, 3] = (1 - u[k]) * a[:3, 3] + u[k] * b[:3, 3]
    return np.linalg.inv(out), u == 0


def generate_checkerboard(options: CheckerboardOptions | None = None) -> CheckerboardScene:
    """Build a calibration recording (intrinsics, hand-eye, path, tracker samples and a lazy
    frame renderer) without touching the disk."""
    o = CheckerboardOptions() if options is None else options
    o.validate()
    rng = np.random.default_rng([o.seed, 0])
    f = o.focal_factor * o.width
    c = np.array([(o.width - 1) / 2.0, (o.height - 1) / 2.0]) + o.principal_offset_px * np.array(
        [0.8, -0.6])
    K = np.array([[f, 0.0, c[0]], [0.0, f * 1.0, c[1]], [0.0, 0.0, 1.0]])
    dist = np.array([o.k1, o.k2, o.p1, o.p2] if o.fisheye is None else o.fisheye, np.float64)
    scene = CheckerboardScene(o, K, dist, default_hand_eye(o.hand_eye_rot_deg,
                                                           o.hand_eye_offset_mm),
                              TRACKER_FROM_BOARD.copy(), np.empty(0), np.empty((0, 4, 4)),
                              np.empty(0, bool), np.empty(0), np.empty((0, 4, 4)))
    scene.ideal_pixels = _ideal_pixels(o, K, dist)  # before anything else: the lens is usable
    corners = scene.board_points()
    views = np.stack([_random_view(o, K, dist, rng, corners) for _ in range(o.n_views)])
    period = o.frames_per_view / o.fps
    scene.timestamps = frame_times(o, o.n_views * o.frames_per_view)
    scene.cam_from_board, scene.resting = _path(views, period, scene.timestamps)

    # tracker_from_sensor = tracker_from_board @ board_from_cam @ cam_from_sensor, then noise.
    scene.tracker_timestamps = sample_times(o, "tracker", float(scene.timestamps[-1]))
    cam_from_board, _ = _path(views, period, scene.tracker_timestamps)
    truth = TRACKER_FROM_BOARD @ np.linalg.inv(cam_from_board) @ np.linalg.inv(scene.hand_eye)
    noise = np.random.default_rng([o.seed, 3]).normal(size=(truth.shape[0], 6))
    noisy = truth.copy()
    noisy[:, :3, :3] = truth[:, :3, :3] @ Rotation.from_rotvec(
        noise[:, :3] * np.deg2rad(o.rot_sigma_deg)).as_matrix()
    noisy[:, :3, 3] += noise[:, 3:] * o.trans_sigma_mm
    scene.tracker_from_sensor = noisy
    scene.tracker_timestamps = scene.tracker_timestamps + o.tracker_delay_s
    return scene


def simulate_checkerboard(
    out: str | Path, options: CheckerboardOptions | None = None, *, overwrite: bool = False
) -> Path:
    """Write a calibration recording at ``out``: frames/, frames.csv, camera.yaml (image size
    only: the intrinsics are what calibration finds), tracking.csv, and for evaluation
    truth_camera.yaml, truth_hand_eye.txt, truth_board.txt (tracker_from_board) and
    simulation.json (the options used)."""
    from fusedmosaic.io import Camera, TrackingSamples, write_camera_yaml, write_dataset
    from fusedmosaic.io.tracking import write_hand_eye

    scene = generate_checkerboard(options)
    o = scene.options
    T = scene.tracker_from_sensor
    tracking = TrackingSamples(scene.tracker_timestamps, T[:, :3, 3].copy(),
                               Rotation.from_matrix(T[:, :3, :3]).as_quat(),
                               np.ones(T.shape[0], bool))
    with tempfile.TemporaryDirectory() as staging:  # the writers take paths
        truth = Path(staging)
        write_camera_yaml(truth / "truth_camera.yaml",
                          Camera(o.width, o.height, camera_matrix=scene.camera_matrix,
                                 distortion=scene.distortion, lens_model=o.lens_model))
        write_hand_eye(truth / "truth_hand_eye.txt", scene.hand_eye)
        write_hand_eye(truth / "truth_board.txt", scene.tracker_from_board)
        extra: dict[str, bytes | str] = {p.name: p.read_bytes() for p in truth.iterdir()}
    info = {"simulator": "checkerboard", "options": asdict(o),
            "resting_frames": np.flatnonzero(scene.resting).tolist()}
    extra["simulation.json"] = json.dumps(info, indent=2) + "\n"
    return write_dataset(out, camera=Camera(o.width, o.height), frames=scene.frames(),
                         timestamps=scene.timestamps, tracking=tracking, extra_files=extra,
                         overwrite=overwrite)
