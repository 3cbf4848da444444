"""World frame the pose methods work in, when the tracker's own frame makes rotations large.

The EMT pose prior (paper 000, Eq. 18) and the constant-velocity prior (Eq. 19) compare
angle-axis components (cpp/fusedmosaic/residuals/pose_prior.h, constant_velocity.h), as does the
linear interpolation of missing poses. Near a rotation of pi two vectors of almost the same
rotation differ by about 2 pi, and a tracker frame can put every camera there: a scope looking
down in a tracker frame whose z axis points up has |r| = pi for any yaw. Tracker noise then flips
the vector between +pi a and -pi a and the priors pull the poses apart (measured: the same scene
in a world rotated by 180 degrees gave e_M 45 239 px instead of 0.47 px).

So when the first tracked camera is more than ``ALIGN_ANGLE`` from identity, the methods work in
the world rotated by that camera's rotation R_a (X' = R_a X), where its rotation is identity and
a hand-held sweep stays far from pi:

    cam_from_world' = (R R_a^T, t),   pi' = R_a pi    (plane n.X + d = 0, pi = n / d)

and report poses and plane back in the tracker's world. Frame -> reference homographies do not
depend on the world frame, and the translation part is unchanged, so the priors' Sigma_EMT and
Sigma_p keep their meaning (isotropic rotation noise is the same on either side). Below
``ALIGN_ANGLE`` nothing changes (the simulator's worlds, where rotations stay near identity).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "ALIGN_ANGLE",
    "plane_from_aligned",
    "plane_to_aligned",
    "poses_from_aligned",
    "poses_to_aligned",
    "world_rotation",
]

# rad; a first camera rotated further than this from the tracker frame triggers the alignment.
ALIGN_ANGLE = np.pi / 2


def world_rotation(poses: np.ndarray) -> np.ndarray | None:
    """R_a (3x3) from the first finite pose of ``poses`` ((N, 6) or (6,) cam_from_world), or None
    when that camera is within ALIGN_ANGLE of identity (or there is no finite pose)."""
    p = np.atleast_2d(np.asarray(poses, dtype=np.float64))
    finite = np.flatnonzero(np.isfinite(p).all(axis=1))
    if not len(finite):
        return None
    r = p[finite[0], :3]
    if np.linalg.norm(r) <= ALIGN_ANGLE:
        return None
    return Rotation.from_rotvec(r).as_matrix()


def _rotate(poses: np.ndarray, right: Rotation) -> np.ndarray:
    p = np.asarray(poses, dtype=np.float64)
    out = p.copy()
    flat = out.reshape(-1, 6)
    ok = np.isfinite(flat).all(axis=1)
    if ok.any():
        flat[ok, :3] = (Rotation.from_rotvec(flat[ok, :3]) * right).as_rotvec()
    return out


def poses_to_aligned(poses: np.ndarray, rotation: np.ndarray | None) -> np.ndarray:
    """cam_from_world -> cam_from_world' (rotation R R_a^T, translation unchanged); NaN rows stay
    NaN; a copy either way."""
    if rotation is None:
        return np.array(poses, dtype=np.float64)
    return _rotate(poses, Rotation.from_matrix(rotation).inv())


def poses_from_aligned(poses: np.ndarray, rotation: np.ndarray | None) -> np.ndarray:
    """Inverse of :func:`poses_to_aligned`."""
    if rotation is None:
        return np.array(poses, dtype=np.float64)
    return _rotate(poses, Rotation.from_matrix(rotation))


def plane_to_aligned(plane: np.ndarray, rotation: np.ndarray | None) -> np.ndarray:
    """pi -> pi' = R_a pi."""
    plane = np.asarray(plane, dtype=np.float64)
    return plane.copy() if rotation is None else rotation @ plane


def plane_from_aligned(plane: np.ndarray, rotation: np.ndarray | None) -> np.ndarray:
    """pi' -> pi = R_a^T pi'."""
    plane = np.asarray(plane, dtype=np.float64)
    return plane.copy() if rotation is None else rotation.T @ plane
