"""World frame the pose methods work in, when the tracker's own frame makes the priors misbehave.

The EMT pose prior (paper 000, Eq. 18) and the constant-velocity prior (Eq. 19) compare
angle-axis + translation components of cam_from_world (cpp/fusedmosaic/residuals/pose_prior.h,
constant_velocity.h), as does the linear interpolation of missing poses. Two properties of the
tracker's frame make that go wrong:

- Rotation. Near a rotation of pi two vectors of almost the same rotation differ by about
  2 pi, and a tracker frame can put every camera there: a scope looking down in a tracker frame
  whose z axis points up has |r| = pi for any yaw. Tracker noise then flips the vector between
  +pi a and -pi a and the priors pull the poses apart (measured: the same scene in a world
  rotated by 180 degrees gave e_M 45 239 px instead of 0.47 px).
- Origin. The translation of cam_from_world is t = -R c (c: the camera centre), so with the
  tracker's origin (its field generator) far from the cameras, orientation noise leaks into t
  (1 degree at 1 m: 17 mm, against Sigma_EMT's 1 mm), a rotation between frames moves t by
  metres for the motion prior, and the plane pi = n / d, d the origin's distance to the plane,
  is tiny and ill-conditioned. The paper's world has its origin at a virtual camera looking at
  the plane (Sec. 3.2). Measured on the 24-frame test scene with physical tracker noise
  (1 degree, 1 mm on the sensor's position), the tracker's origin moved 1 m along the optical
  axis: e_M 56 409 px one way, 87 145 px worst frame the other with frames 3-8 untracked;
  recentred, 0.4 px (worst frame 1 px) for origins 0.2-1 m away along or across the axis.

- Origin near the plane. pi = n / d puts the plane at 1 / |pi| from the origin, and the images
  measure it relative to the cameras, D from it: an error of the plane's position is D / d
  times larger relative to pi, and H_k = R_k - t_k pi^T is nearly its rank-1 term (a tracker
  origin 1 mm from the tissue, the cameras 29 mm: ba-emt's pi went to 1e5 and every induced
  homography tested singular; review). D / d is |det H_k| = |1 + pi . c_k| (c_k the centre).

So the methods work in an aligned world X' = R_a (X - c_a), taken from a tracked camera (lba-emt:
the first; offline methods and the checks: the one nearest the median centre, tracked_world):
c_a its centre when that is more than ``ALIGN_DISTANCE`` from the tracker's origin, or (given a
plane) when the origin lies nearer the plane than ``ORIGIN_PLANE_FRACTION`` of the cameras'
median distance to it (else 0), R_a its rotation when that is more than ``ALIGN_ANGLE`` from
identity (else I). lba-emt decides its world at its first tracker sample, before any plane,
and again before each start-up adjustment: if the plane of the start-up's registered pairs
puts the world's origin near it, the world becomes tracked_world's of the start-up's tracked
cameras, centred on one (SYN 60 frames, the tracker's origin 0.2 mm from the tissue,
29.8 from the cameras: the start-up's plane was refused as unbounded from 650 pairs, and the
run with it; 1 mm away, taken with a relative std of 0.28, and the run warned that the images
barely observe the plane; recentred, relative std 0.0006 and e_M 0.131 / 0.127 px, as with the
origin 30 mm away, 0.130 px; review). Then

    cam_from_world' = (R R_a^T, t + R c_a),   pi' = R_a pi / (1 + pi . c_a)

(plane n.X + d = 0, pi = n / d), and poses and plane are reported back in the tracker's world.
Frame -> reference homographies do not depend on the world frame. Within both bounds nothing
changes (the simulator's worlds: the origin is the paper's virtual camera, at most 26 mm
from the cameras, and rotations stay near identity), so the simulated noise, on [r, t] there,
keeps its meaning; for a real tracker, whose noise is on the sensor's orientation and position,
the aligned world is where a diagonal Sigma_EMT on [r, t] describes it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "ALIGN_ANGLE",
    "ALIGN_DISTANCE",
    "ORIGIN_PLANE_FRACTION",
    "WorldAlignment",
    "origin_near_plane",
    "plane_from_aligned",
    "plane_to_aligned",
    "poses_from_aligned",
    "poses_to_aligned",
    "same_world",
    "tracked_world",
    "world_alignment",
]

# rad; a first camera rotated further than this from the tracker frame triggers the rotation.
ALIGN_ANGLE = np.pi / 2
# mm; a first camera centre further than this from the tracker's origin becomes the origin.
ALIGN_DISTANCE = 50.0
# An origin nearer the plane than this fraction of the cameras' median distance to it becomes a
# camera's centre (given the plane): pi's conditioning then loses at most a factor 2 against a
# world centred on a camera (D / d = 1), which is where the paper puts the origin (Sec. 3.2).
ORIGIN_PLANE_FRACTION = 0.5


@dataclass(frozen=True)
class WorldAlignment:
    """The aligned world X' = R_a (X - c_a) of :func:`world_alignment`."""

    rotation: np.ndarray  # R_a (3, 3)
    centre: np.ndarray  # c_a (3,), mm in the tracker's world


def world_alignment(poses: np.ndarray, *, recentre: bool = False) -> WorldAlignment | None:
    """The aligned world from the first finite pose of ``poses`` ((N, 6) or (6,)
    cam_from_world), or None when that camera is within ALIGN_ANGLE of identity and
    ALIGN_DISTANCE of the origin (or there is no finite pose). ``recentre``: its centre becomes
    the origin whatever its distance."""
    p = np.atleast_2d(np.asarray(poses, dtype=np.float64))
    finite = np.flatnonzero(np.isfinite(p).all(axis=1))
    if not len(finite):
        return None
    r, t = p[finite[0], :3], p[finite[0], 3:]
    R = Rotation.from_rotvec(r)
    centre = -R.inv().apply(t)
    rotate = np.linalg.norm(r) > ALIGN_ANGLE
    move = recentre or np.linalg.norm(centre) > ALIGN_DISTANCE
    if not (rotate or move):
        return None
    return WorldAlignment(R.as_matrix() if rotate else np.eye(3),
                          centre if move else np.zeros(3))


def origin_near_plane(poses: np.ndarray, plane: np.ndarray) -> bool:
    """True when the world's origin lies nearer the plane pi (n . X + d = 0, pi = n / d, at
    1 / |pi| from the origin) than ORIGIN_PLANE_FRACTION of the median distance of the (N, 6)
    cam_from_world poses' centres (finite rows) to it: median |1 + pi . c| above
    1 / ORIGIN_PLANE_FRACTION (module docstring). A plane through the origin (pi not finite) is
    near; a plane at infinity (pi = 0), or no finite pose, is not."""
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
    return _origin_near_plane(_centres(p[np.isfinite(p).all(axis=1)]), plane)


def _centres(poses: np.ndarray) -> np.ndarray:
    """(N, 3) camera centres of (N, 6) finite cam_from_world poses."""
    return -Rotation.from_rotvec(poses[:, :3]).inv().apply(poses[:, 3:])


def _origin_near_plane(centres: np.ndarray, plane) -> bool:
    """origin_near_plane from the cameras' (N, 3) centres."""
    plane = np.asarray(plane, dtype=np.float64).reshape(3)
    if not np.isfinite(plane).all():
        return True
    if not len(centres) or not np.any(plane):
        return False
    return bool(np.median(np.abs(1.0 + centres @ plane)) > 1.0 / ORIGIN_PLANE_FRACTION)


def tracked_world(poses: np.ndarray, valid=None, plane=None, *,
                  recentre: bool = False) -> WorldAlignment | None:
    """The aligned world of a whole recording's tracked cameras ((N, 6) cam_from_world, rows
    NaN or not ``valid`` left out), as the offline methods and the checks take it: from the
    camera whose centre lies nearest the cameras' median centre, so that one bad sample (the
    first, say, 2 m off) does not move the world's origin (world_alignment of the first
    camera: a consistent tracker then read 20 x its noise). None as world_alignment. Given
    the plane pi (in the same world as ``poses``), that camera's centre also becomes the origin
    when the origin lies near the plane (origin_near_plane); ``recentre``: whatever the
    plane."""
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 6)
    ok = np.isfinite(p).all(axis=1)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    if not ok.any():
        return None
    tracked = p[ok]
    centres = _centres(tracked)
    nearest = int(np.argmin(np.linalg.norm(centres - np.median(centres, axis=0), axis=1)))
    recentre = recentre or (plane is not None and _origin_near_plane(centres, plane))
    return world_alignment(tracked[nearest], recentre=recentre)


def same_world(a: WorldAlignment | None, b: WorldAlignment | None) -> bool:
    """Whether two alignments (None: the tracker's own world) are the same."""
    if a is None or b is None:
        return a is b
    return bool(np.array_equal(a.rotation, b.rotation) and np.array_equal(a.centre, b.centre))


def _transform(poses: np.ndarray, right: Rotation, shift: np.ndarray) -> np.ndarray:
    """cam_from_world -> (R right, t + R shift) on the finite rows (R the input rotation)."""
    p = np.asarray(poses, dtype=np.float64)
    out = p.copy()
    flat = out.reshape(-1, 6)
    ok = np.isfinite(flat).all(axis=1)
    if ok.any():
        R = Rotation.from_rotvec(flat[ok, :3])
        flat[ok, 3:] = flat[ok, 3:] + R.apply(shift)
        flat[ok, :3] = (R * right).as_rotvec()
    return out


def poses_to_aligned(poses: np.ndarray, world: WorldAlignment | None) -> np.ndarray:
    """cam_from_world -> cam_from_world' = (R R_a^T, t + R c_a); NaN rows stay NaN; a copy
    either way."""
    if world is None:
        return np.array(poses, dtype=np.float64)
    return _transform(poses, Rotation.from_matrix(world.rotation).inv(), world.centre)


def poses_from_aligned(poses: np.ndarray, world: WorldAlignment | None) -> np.ndarray:
    """Inverse of :func:`poses_to_aligned`: (R' R_a, t' - R' R_a c_a)."""
    if world is None:
        return np.array(poses, dtype=np.float64)
    return _transform(poses, Rotation.from_matrix(world.rotation),
                      -world.rotation @ np.asarray(world.centre, np.float64))


def plane_to_aligned(plane: np.ndarray, world: WorldAlignment | None) -> np.ndarray:
    """pi -> pi' = R_a pi / (1 + pi . c_a)."""
    plane = np.asarray(plane, dtype=np.float64)
    if world is None:
        return plane.copy()
    return world.rotation @ plane / (1.0 + plane @ world.centre)


def plane_from_aligned(plane: np.ndarray, world: WorldAlignment | None) -> np.ndarray:
    """pi' -> pi = q / (1 - q . c_a), q = R_a^T pi'. A plane through the tracker's origin
    (1 - q . c_a = 0) has no pi = n / d there: infinite components."""
    plane = np.asarray(plane, dtype=np.float64)
    if world is None:
        return plane.copy()
    q = world.rotation.T @ plane
    with np.errstate(divide="ignore", invalid="ignore"):
        return q / (1.0 - q @ world.centre)
