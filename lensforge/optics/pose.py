"""Pose vectors x = (tx, ty, tz, rx, ry, rz) and homogeneous transforms.

Translation in mm, rotation as a rotation vector (axis * angle, rad),
R = exp([r]x) (scipy Rotation.from_rotvec). ^A T_B maps B coordinates to A.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["pose_to_matrix", "matrix_to_pose", "rotations", "DOF_NAMES", "DOF_UNITS"]

DOF_NAMES = ("tx", "ty", "tz", "rx", "ry", "rz")
DOF_UNITS = ("mm", "mm", "mm", "rad", "rad", "rad")


def rotations(rotvecs) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) in rad."""
    rv = np.asarray(rotvecs, dtype=float)
    flat = rv.reshape(-1, 3)
    return Rotation.from_rotvec(flat).as_matrix().reshape(rv.shape[:-1] + (3, 3))


def pose_to_matrix(x) -> np.ndarray:
    """4x4 transform(s) [R(r), t; 0, 1] of pose vector(s) (..., 6)."""
    x = np.asarray(x, dtype=float)
    T = np.zeros(x.shape[:-1] + (4, 4))
    T[..., :3, :3] = rotations(x[..., 3:])
    T[..., :3, 3] = x[..., :3]
    T[..., 3, 3] = 1.0
    return T


def matrix_to_pose(T) -> np.ndarray:
    """Pose vector(s) (..., 6) of 4x4 transform(s)."""
    T = np.asarray(T, dtype=float)
    flat = T.reshape(-1, 4, 4)
    r = Rotation.from_matrix(flat[:, :3, :3]).as_rotvec()
    return np.concatenate([flat[:, :3, 3], r], axis=1).reshape(T.shape[:-2] + (6,))
