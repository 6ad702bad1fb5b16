"""Pose vectors x = (tx, ty, tz, rx, ry, rz) and homogeneous transforms.

Translation in mm, rotation as a rotation vector (axis * angle, rad),
R = exp([r]x) (the same as scipy Rotation.from_rotvec). ^A T_B maps B coordinates
to A. Vectorised quaternion code: these run in every estimator and hand-eye
iteration, where scipy's per-call overhead dominated.
"""

from __future__ import annotations

from numpy.typing import ArrayLike

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["pose_to_matrix", "matrix_to_pose", "rotations", "rotvecs", "skew", "invert_poses", "adjoint",
           "right_jacobian_so3", "right_jacobian_inv_so3", "pose_vector_cov_to_right", "rotation_angle_deg", "transform_error",
           "DOF_NAMES", "DOF_UNITS"]

DOF_NAMES = ("tx", "ty", "tz", "rx", "ry", "rz")
DOF_UNITS = ("mm", "mm", "mm", "rad", "rad", "rad")


def skew(v) -> np.ndarray:
    """Cross-product matrices [v]x (..., 3, 3) of vectors (..., 3)."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def rotations(rotvecs_) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) in rad, through the unit
    quaternion (orthonormal to machine precision, as scipy's from_rotvec)."""
    r = np.asarray(rotvecs_, dtype=float)
    th = np.linalg.norm(r, axis=-1)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    s = np.where(small, 0.5 - th**2 / 48.0, np.sin(0.5 * ths) / ths)  # sin(th/2) / th
    x, y, z = (r[..., i] * s for i in range(3))
    w = np.cos(0.5 * th)
    R = np.empty(r.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def rotvecs(R) -> np.ndarray:
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3), via quaternions with
    Shepperd's branch choice (accurate near the identity and near pi)."""
    R = np.asarray(R, dtype=float)
    m = R.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    k = np.argmax(np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1), axis=1)
    q = np.empty((m.shape[0], 4))  # (x, y, z, w)
    i0 = k == 0
    if i0.any():
        t = m[i0]
        w = 0.5 * np.sqrt(1.0 + tr[i0])
        q[i0, 3] = w
        q[i0, 0] = (t[:, 2, 1] - t[:, 1, 2]) / (4 * w)
        q[i0, 1] = (t[:, 0, 2] - t[:, 2, 0]) / (4 * w)
        q[i0, 2] = (t[:, 1, 0] - t[:, 0, 1]) / (4 * w)
    for a in range(3):
        sel = k == a + 1
        if not sel.any():
            continue
        b, c = (a + 1) % 3, (a + 2) % 3
        t = m[sel]
        qa = 0.5 * np.sqrt(1.0 + t[:, a, a] - t[:, b, b] - t[:, c, c])
        q[sel, a] = qa
        q[sel, b] = (t[:, b, a] + t[:, a, b]) / (4 * qa)
        q[sel, c] = (t[:, c, a] + t[:, a, c]) / (4 * qa)
        q[sel, 3] = (t[:, c, b] - t[:, b, c]) / (4 * qa)
    q[q[:, 3] < 0] *= -1.0
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    vn = np.linalg.norm(q[:, :3], axis=1)
    ang = 2.0 * np.arctan2(vn, q[:, 3])
    small = vn < 1e-8
    scale = np.where(small, 2.0 / np.maximum(q[:, 3], 1e-300) * (1.0 + vn**2 / 3.0),
                     ang / np.where(small, 1.0, vn))
    return (q[:, :3] * scale[:, None]).reshape(R.shape[:-2] + (3,))


def pose_to_matrix(x: ArrayLike) -> np.ndarray:
    """Homogeneous transform(s) [R(r), t; 0, 1] of pose vector(s).

    Parameters
    ----------
    x : array_like, shape (..., 6)
        Pose vectors (tx, ty, tz, rx, ry, rz): translation in mm and a rotation vector
        (axis times angle) in rad.

    Returns
    -------
    numpy.ndarray, shape (..., 4, 4)
        The transforms, R = exp([r]x).
    """
    x = np.asarray(x, dtype=float)
    T = np.zeros(x.shape[:-1] + (4, 4))
    T[..., :3, :3] = rotations(x[..., 3:])
    T[..., :3, 3] = x[..., :3]
    T[..., 3, 3] = 1.0
    return T


def matrix_to_pose(T: ArrayLike) -> np.ndarray:
    """Pose vector(s) of homogeneous transform(s).

    Parameters
    ----------
    T : array_like, shape (..., 4, 4)
        Rigid transforms (orthonormal rotation block).

    Returns
    -------
    numpy.ndarray, shape (..., 6)
        (tx, ty, tz, rx, ry, rz): translation in the transforms' unit (mm in lensforge) and
        the rotation vector in rad (angle in [0, pi]).
    """
    T = np.asarray(T, dtype=float)
    return np.concatenate([T[..., :3, 3], rotvecs(T[..., :3, :3])], axis=-1)


def invert_poses(T: ArrayLike) -> np.ndarray:
    """Inverse(s) of rigid transform(s), exact for an orthonormal rotation block.

    Parameters
    ----------
    T : array_like, shape (..., 4, 4)
        Rigid transforms [R, t; 0, 1].

    Returns
    -------
    numpy.ndarray, shape (..., 4, 4)
        [R^T, -R^T t; 0, 1].
    """
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def adjoint(T) -> np.ndarray:
    """6x6 adjoint(s) of T for xi = (rho, omega): T P(xi) T^-1 = P(Ad_T xi) to first order."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ad = np.zeros(T.shape[:-2] + (6, 6))
    Ad[..., :3, :3] = R
    Ad[..., :3, 3:] = skew(t) @ R
    Ad[..., 3:, 3:] = R
    return Ad


def right_jacobian_so3(r) -> np.ndarray:
    """Right Jacobian J_r(r) (..., 3, 3) of SO(3) for rotation vectors r (..., 3):
    R(r + dr) = R(r) Exp(J_r(r) dr) to first order."""
    r = np.asarray(r, dtype=float)
    th = np.linalg.norm(r, axis=-1)[..., None, None]
    K = skew(r)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 0.5, (1 - np.cos(ths)) / ths**2)
    b = np.where(small, 1.0 / 6.0, (ths - np.sin(ths)) / ths**3)
    return np.eye(3) - a * K + b * K @ K


def right_jacobian_inv_so3(r, left: bool = False) -> np.ndarray:
    """Inverse right Jacobian J_r(r)^-1 (..., 3, 3) of SO(3) for rotation vectors r (..., 3)
    (left=True: the inverse left Jacobian, J_l(r)^-1 = J_r(-r)^-1). Below 1e-4 rad the
    coefficient's series 1/12 + th^2/720 replaces the closed form (which cancels there)."""
    r = np.asarray(r, dtype=float)
    th = np.linalg.norm(r, axis=-1)[..., None, None]
    K = skew(-r if left else r)
    small = th < 1e-4
    ths = np.where(small, 1.0, th)
    c = np.where(small, 1.0 / 12.0 + th**2 / 720.0, 1.0 / ths**2 - (1.0 + np.cos(ths)) / (2.0 * ths * np.sin(ths)))
    return np.eye(3) + 0.5 * K + c * (K @ K)


def pose_vector_cov_to_right(x, cov_x) -> np.ndarray:
    """Covariance of a pose vector x = (t, r) (as returned by the pose estimator, where
    T = T_nominal P(x)) converted to the right perturbation of T used by hand-eye (T P(xi)).

    P(x + dx) = P(x) P(xi) with xi = (R(r)^T dt, J_r(r) dr) to first order.
    """
    x = np.asarray(x, dtype=float)
    M = np.zeros((6, 6))
    M[:3, :3] = rotations(x[3:]).T
    M[3:, 3:] = right_jacobian_so3(x[3:])
    return M @ np.asarray(cov_x, dtype=float) @ M.T


def rotation_angle_deg(R: np.ndarray) -> float:
    """Rotation angle (deg) of a rotation matrix, accurate for small angles."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))) if c < 0.999 else \
        float(np.degrees(np.linalg.norm(Rotation.from_matrix(R).as_rotvec())))


def transform_error(T_true: np.ndarray, T_est: np.ndarray) -> tuple[float, float]:
    """Rotation and translation error of an estimated transform against the true one.

    Parameters
    ----------
    T_true, T_est : numpy.ndarray, shape (4, 4)
        True and estimated rigid transforms (translations in mm).

    Returns
    -------
    rotation_deg : float
        Rotation angle of T_true^-1 T_est, degrees.
    translation_mm : float
        Distance between the two translations |t_est - t_true|, mm.
    """
    E = np.linalg.solve(T_true, T_est)
    return rotation_angle_deg(E[:3, :3]), float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
