"""Robot-world-hand-eye calibration A_i X = Z B_i with uncertainty.

Frames (DESIGN.md): A_i = ^W T_E (robot flange in the base), B_i = ^S T_O (lens in
the sensor frame), X = ^E T_O (the grasp), Z = ^W T_S (the sensor in the robot
base). 4x4 homogeneous transforms, mm and rad.

Perturbation convention (used for every covariance in this module): a pose T is
perturbed on the right, T (+) xi = T . P(xi), with xi = (rho, omega) in (mm, rad)
and P = ``pose_to_matrix`` (translation rho and rotation vector omega, expressed in
T's own child frame). This is DESIGN.md's pose-vector convention T_SO(x) =
T_SO(nominal) . P(x), so a pose-estimator covariance of x taken at x ~ 0 can be
used as ``cov_B`` directly; ``pose_vector_cov_to_right`` converts it exactly at
any x. Hence cov_X is in {O} axes (at the lens origin) and cov_Z in {S} axes (at
the sensor origin).

Noise model: measured A_i = A_i,true P(a_i), a_i ~ N(0, Sigma_A) and measured
B_i = B_i,true P(b_i), b_i ~ N(0, Sigma_B,i). The pose residual
E_i = (Z B_i)^-1 A_i X = P(-b_i) P(Ad_{X^-1} a_i) has, to first order,
e_i = log E_i ~ N(0, Sigma_B,i + Ad_{X^-1} Sigma_A Ad_{X^-1}^T); maximum likelihood
minimises sum_i e_i^T Sigma_i^-1 e_i over (X, Z) (the errors-in-variables problem
with the nuisance true poses eliminated, Gauss-Helmert style), and its Fisher
information J^T Sigma^-1 J, J_i = [I, -Ad_{B_i^-1}], gives the Cramer-Rao bound.
The same residual and weighting idea underlies Strobl & Hirzinger, "Optimal
Hand-Eye Calibration", IROS 2006 (the paper's solver [26]).

Closed forms: Shah, "Solving the robot-world/hand-eye calibration problem using
the Kronecker product", J. Mech. Robot. 5(3) 2013 (rotation from the top singular
pair of sum R_B (x) R_A, then translations by linear least squares); Li, Wang & Wu,
"Simultaneous robot-world and hand-eye calibration using dual-quaternions and
Kronecker product", Int. J. Phys. Sci. 5(10) 2010 (rotation and translation from
one joint linear system).
"""

from __future__ import annotations

from numpy.typing import ArrayLike

import warnings as _warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ..errors import CalibrationError
from .formats import rotation_defects
from ..optics.pose import (DOF_NAMES, adjoint, invert_poses, matrix_to_pose, pose_to_matrix, pose_vector_cov_to_right,
                           right_jacobian_inv_so3, right_jacobian_so3, rotations, skew)
from ..optics.sensitivity import observability

__all__ = [
    "HandEyeResult",
    "solve_handeye",
    "handeye_jacobian",
    "handeye_fisher",
    "residual_covariances",
    "handeye_observability",
    "METHODS",
    "DEGENERATE_RTOL",
    "OBS_LIMITS",
]

METHODS = ("ml", "shah", "li")

# Observability of (X, Z) (optics.sensitivity.observability, DESIGN.md's rule):
# - degenerate: a direction the motion itself lacks (pure translations, rotations about
#   one axis): relative singular value of the column-equilibrated whitened Jacobian
#   below DEGENERATE_RTOL. The noise scales all rows alike and cannot change this test.
#   Its 1-sigma is inf. solve_handeye refuses it by default (on_degenerate="raise").
# - weak: the data cannot pin a direction to within OBS_LIMITS (predicted 1-sigma from
#   the Fisher information above limit_mm along a translation or limit_rad along a
#   rotation). Merely noisy: solved, reported observable=False, warned about, never
#   refused. Settable per call (obs_limits=).
# ASSUMPTION: 1 mm and 0.01 rad are far beyond any useful calibration; DEGENERATE_RTOL
# 1e-4 sits between pure translation with 1e-5 rad lens-pose noise (~1e-5) and +-1 deg
# of rotation (~5e-3).
DEGENERATE_RTOL = 1e-4
OBS_LIMITS = (1.0, 0.01)  # (mm, rad)
# input rotations: orthonormal to formats.ORTHO_TOL (1e-6) with det +1 (formats.rotation_defects)


# ----------------------------------------------------------------------------- validation


def _as_poses(P, name: str) -> np.ndarray:
    try:
        P = np.asarray(P, dtype=float)
    except (TypeError, ValueError):
        raise CalibrationError(f"{name}: expected a list of 4x4 numeric matrices") from None
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise CalibrationError(f"{name}: expected shape (n, 4, 4), got {P.shape}; give a list of 4x4 homogeneous matrices")
    if not np.all(np.isfinite(P)):
        raise CalibrationError(f"{name}: contains NaN or infinite values")
    bad = np.flatnonzero(np.abs(P[:, 3, :] - [0, 0, 0, 1]).max(axis=1) > 1e-9)
    if bad.size:
        raise CalibrationError(f"{name}[{bad[0]}]: last row must be [0, 0, 0, 1]")
    R = P[:, :3, :3]
    orth, det, bad = rotation_defects(R)
    if bad.size:
        i = bad[0]
        raise CalibrationError(
            f"{name}[{i}]: rotation block is not orthonormal with det +1 (|R^T R - I| = {orth[i]:.2e}, "
            f"det = {det[i]:.6f}); give proper rotation matrices (orthonormalise them)"
        )
    # project to SO(3) exactly (removes ~1e-12 rounding so that inverses are exact)
    U, _, Vt = np.linalg.svd(R)
    P = P.copy()
    P[:, :3, :3] = U @ Vt
    return P


def _noise_cov_A(sigma, n: int) -> np.ndarray | None:
    """Sigma_A as (n, 6, 6) or None (no robot noise model given)."""
    if sigma is None:
        return None
    if hasattr(sigma, "cov"):
        sigma = sigma.cov
    if isinstance(sigma, dict):
        try:
            sigma = (float(sigma["translation_mm"]), float(sigma["rotation_rad"]))
        except (KeyError, TypeError, ValueError):
            raise CalibrationError("sigma: expected keys translation_mm and rotation_rad with numbers") from None
    s = np.asarray(sigma, dtype=float)
    if s.shape == (2,):
        if np.any(s < 0):
            raise CalibrationError("sigma: translation_mm and rotation_rad must be >= 0")
        C = np.diag([s[0] ** 2] * 3 + [s[1] ** 2] * 3)
        return np.broadcast_to(C, (n, 6, 6)).copy()
    if s.shape == (6, 6):
        return np.broadcast_to(s, (n, 6, 6)).copy()
    if s.shape == (n, 6, 6):
        return s.copy()
    raise CalibrationError(
        f"sigma: expected (translation_mm, rotation_rad), a 6x6 covariance or one per pose, got shape {s.shape}"
    )


def _noise_cov_B(cov_B, n: int) -> np.ndarray | None:
    if cov_B is None:
        return None
    c = np.asarray(cov_B, dtype=float)
    if c.shape == (6, 6):
        return np.broadcast_to(c, (n, 6, 6)).copy()
    if c.shape == (n, 6, 6):
        return c.copy()
    raise CalibrationError(f"cov_B: expected a 6x6 covariance or one per pose ({n}, 6, 6), got shape {c.shape}")


def residual_covariances(X, n: int, sigma=None, cov_B=None) -> np.ndarray:
    """Sigma_i = Sigma_B,i + Ad_{X^-1} Sigma_A Ad_{X^-1}^T, (n, 6, 6), (mm, rad)^2."""
    SA = _noise_cov_A(sigma, n)
    SB = _noise_cov_B(cov_B, n)
    S = np.zeros((n, 6, 6))
    if SA is not None:
        Ad = adjoint(invert_poses(X))
        S += Ad @ SA @ Ad.T
    if SB is not None:
        S += SB
    return S


def whiteners(S: np.ndarray, where: str) -> np.ndarray:
    """W_i with W_i^T W_i = S_i^-1 (inverse Cholesky factors), (n, 6, 6)."""
    S = 0.5 * (S + np.swapaxes(S, 1, 2))
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        raise CalibrationError(
            f"{where}: the combined pose-noise covariance is not positive definite; give sigma for A "
            "(translation_mm and rotation_rad > 0) and/or a full-rank cov_B"
        ) from None
    return np.linalg.inv(L)


# ----------------------------------------------------------------------------- residuals & Jacobian


def _residuals(A, B, X, Z) -> np.ndarray:
    """e_i = log((Z B_i)^-1 A_i X), (n, 6) in (mm, rad), in {O} axes."""
    E = invert_poses(Z @ B) @ A @ X
    return matrix_to_pose(E)


def handeye_jacobian(B) -> np.ndarray:
    """d e / d (xi_X, xi_Z) at E = I: block rows [I, -Ad_{B_i^-1}], shape (n, 6, 12)."""
    B = np.asarray(B, dtype=float)
    n = B.shape[0]
    J = np.zeros((n, 6, 12))
    J[:, :, :6] = np.eye(6)
    J[:, :, 6:] = -adjoint(invert_poses(B))
    return J


def handeye_fisher(B, X, sigma=None, cov_B=None) -> np.ndarray:
    """Fisher information (12x12) of (xi_X, xi_Z) given lens poses B (n,4,4), grasp X and
    the noise model; its inverse is the Cramer-Rao bound in the right-perturbation
    convention (mm, rad)."""
    B = np.asarray(B, dtype=float)
    n = B.shape[0]
    W = whiteners(residual_covariances(X, n, sigma, cov_B), "noise model")
    Jw = (W @ handeye_jacobian(B)).reshape(-1, 12)
    return Jw.T @ Jw


# ----------------------------------------------------------------------------- closed forms


def _project_so3(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _unvec(v):
    return v.reshape(3, 3).T


def _solve_translations(A, B, RX, RZ):
    """Least squares for t_X, t_Z given rotations: R_A t_X - t_Z = R_Z t_B - t_A."""
    n = A.shape[0]
    M = np.zeros((3 * n, 6))
    M[:, :3] = A[:, :3, :3].reshape(3 * n, 3)
    M[:, 3:] = np.tile(-np.eye(3), (n, 1))
    rhs = (np.einsum("ij,nj->ni", RZ, B[:, :3, 3]) - A[:, :3, 3]).reshape(-1)
    sol, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    X = np.eye(4)
    Z = np.eye(4)
    X[:3, :3], X[:3, 3] = RX, sol[:3]
    Z[:3, :3], Z[:3, 3] = RZ, sol[3:]
    return X, Z


def _scaled_rotation(v):
    M = _unvec(v)
    d = np.linalg.det(M)
    # degenerate motion can leave det ~ 0; the projection still returns a rotation and
    # the observability check reports the ambiguity
    return _project_so3(M if d == 0 else np.sign(d) * M)


def _shah(A, B):
    """Shah 2013: R_X = R_A^T R_Z R_B  =>  n vec(R_X) = K vec(R_Z), K = sum R_B^T (x) R_A^T
    (column-major vec); the top singular pair of K gives vec R_X and vec R_Z."""
    RA, RB = A[:, :3, :3], B[:, :3, :3]
    K = np.einsum("nji,nlk->nikjl", RB, RA).reshape(-1, 9, 9).sum(axis=0)
    # kron(P, Q)[3i+k, 3j+l] = P[i,j] Q[k,l] with P = R_B^T, Q = R_A^T
    U, s, Vt = np.linalg.svd(K)
    RX = _scaled_rotation(U[:, 0])
    RZ = _scaled_rotation(Vt[0])
    return _solve_translations(A, B, RX, RZ)


def _li(A, B):
    """Li 2010 (Kronecker form): one linear system in (vec R_X, vec R_Z, t_X, t_Z)
    from both the rotation and translation parts, then projection onto SO(3) and
    the translations re-solved with the projected rotations."""
    n = A.shape[0]
    RA, RB = A[:, :3, :3], B[:, :3, :3]
    tA, tB = A[:, :3, 3], B[:, :3, 3]
    s = max(np.sqrt(np.mean(np.sum(tA**2, axis=1))), np.sqrt(np.mean(np.sum(tB**2, axis=1))), 1.0)
    # translations scaled by s (numerical conditioning only; exact data stay exact)
    I3 = np.eye(3)
    M = np.zeros((n, 12, 24))
    rhs = np.zeros((n, 12))
    M[:, :9, 0:9] = np.einsum("ij,nkl->nikjl", I3, RA).reshape(n, 9, 9)  # I (x) R_A
    M[:, :9, 9:18] = -np.einsum("nji,kl->nikjl", RB, I3).reshape(n, 9, 9)  # R_B^T (x) I
    M[:, 9:, 9:18] = -np.einsum("nj,kl->nkjl", tB / s, I3).reshape(n, 3, 9)  # t_B^T (x) I
    M[:, 9:, 18:21] = RA
    M[:, 9:, 21:24] = -I3
    rhs[:, 9:] = -tA / s
    M = M.reshape(12 * n, 24)
    rhs = rhs.reshape(-1)
    sol, *_ = np.linalg.lstsq(M, rhs, rcond=None)
    RX = _scaled_rotation(sol[0:9])
    RZ = _scaled_rotation(sol[9:18])
    return _solve_translations(A, B, RX, RZ)


_CLOSED_FORMS = {"shah": _shah, "li": _li}


# ----------------------------------------------------------------------------- observability


_AXIS_NAMES = ("x", "y", "z")


def _describe_dir(v: np.ndarray, frame: str) -> str:
    v = v / np.linalg.norm(v)
    k = int(np.argmax(np.abs(v)))
    if abs(v[k]) > 0.99:
        sign = "" if v[k] > 0 else "-"
        extra = " (the optical axis)" if frame == "{S}" and k == 2 else ""
        return f"{frame} {sign}{_AXIS_NAMES[k]}{extra}"
    return f"{frame} direction [{v[0]:+.2f}, {v[1]:+.2f}, {v[2]:+.2f}]"


def _name_null_vector(v: np.ndarray, length_mm: float) -> str:
    """Human-readable name of a null direction v = (xi_X, xi_Z) (physical units); a
    rotation part smaller than 10 % of the translation part over length_mm is ignored."""
    # -v is null too: the sign that makes Z's largest part positive (rotation if any, else translation),
    # so that the name does not depend on the SVD's arbitrary sign (it flipped between CPUs)
    lead = v[9:12] if np.linalg.norm(v[9:12]) * length_mm >= 0.1 * np.linalg.norm(v[6:9]) else v[6:9]
    if lead[int(np.argmax(np.abs(lead)))] < 0:
        v = -v
    xr, xw, zr, zw = v[0:3], v[3:6], v[6:9], v[9:12]
    nz_w = np.linalg.norm(zw)
    nx_w = np.linalg.norm(xw)
    if nz_w * length_mm < 0.1 * np.linalg.norm(zr):
        zpart = f"translation of Z along {_describe_dir(zr, '{S}')}"
    else:
        u = zw / nz_w
        # a twist (rho, omega) is a rotation about the line through p = omega x rho / |omega|^2
        p = np.cross(zw, zr) / nz_w**2
        pitch = float(zr @ zw) / nz_w**2
        zpart = f"rotation of Z about {_describe_dir(u, '{S}')} through [{p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}] mm in {{S}}"
        if abs(pitch) > 0.1 * length_mm:
            zpart += f" with {pitch:.3g} mm/rad translation along it"
    if nx_w * length_mm < 0.1 * np.linalg.norm(xr):
        xpart = f"translation of X along {_describe_dir(xr, '{O}')}"
    else:
        xpart = f"rotation of X about {_describe_dir(xw / nx_w, '{O}')}"
    return f"{zpart} coupled with {xpart}"


def _null_basis_names(N: np.ndarray, length_mm: float) -> list[str]:
    """Names for a basis of the null space N (12 x k, physical units): first the
    combinations without Z rotation (aligned with the {S} axes where possible), then
    rotations with those translations projected out."""
    k = N.shape[1]
    if k == 0:
        return []
    Nm = N.copy()
    Nm[3:6] *= length_mm
    Nm[9:12] *= length_mm  # rotations as displacements over length_mm
    _, s, Vt = np.linalg.svd(Nm[9:12, :] / np.linalg.norm(Nm, axis=0))
    s = np.concatenate([s, np.zeros(k - s.size)])
    is_rot = s > 0.01
    trans = N @ Vt[~is_rot].T
    rot = N @ Vt[is_rot].T
    if trans.shape[1] == 3:
        trans = trans @ np.linalg.solve(trans[6:9, :], np.eye(3))
    names = [_name_null_vector(trans[:, j], length_mm) for j in range(trans.shape[1])]
    for j in range(rot.shape[1]):
        v = rot[:, j].copy()
        if trans.shape[1]:
            # remove translation along the rotation axis (a pitch) when translations are null too
            u = v[9:12] / np.linalg.norm(v[9:12])
            for t in trans.T:
                tz = t[6:9] / np.linalg.norm(t[6:9])
                if abs(tz @ u) > 0.9:
                    v = v - (v[6:9] @ tz) / (t[6:9] @ tz) * t
        names.append(_name_null_vector(v, length_mm))
    return names


def handeye_observability(B, X, sigma=None, cov_B=None, S=None, obs_limits=OBS_LIMITS) -> dict:
    """Observability of (X, Z) from lens poses B (see DEGENERATE_RTOL / OBS_LIMITS):
    singular values of the whitened Jacobian (physical units 1/mm, 1/rad), relative
    singular values of its column-equilibrated form, the thresholds used, `observable`
    (no degenerate and no weak direction), `degenerate` (some direction is null), the
    per-parameter 1-sigma (12,: X then Z; inf where degenerate) and named unobservable
    directions (weak ones first)."""
    B = np.asarray(B, dtype=float)
    n = B.shape[0]
    if S is None:
        S = residual_covariances(X, n, sigma, cov_B)
    W = whiteners(S, "noise model")
    Jw = (W @ handeye_jacobian(B)).reshape(-1, 12)
    sv_phys = np.linalg.svd(Jw, compute_uv=False)
    d = np.linalg.norm(Jw, axis=0)
    d[d == 0] = 1.0
    rel = np.linalg.svd(Jw / d, compute_uv=False)
    rel = rel / rel[0]
    lim_mm, lim_rad = (float(v) for v in obs_limits)
    if not (lim_mm > 0 and lim_rad > 0):
        raise CalibrationError(f"obs_limits: expected two positive numbers (mm, rad), got {obs_limits!r}")
    lim = np.array(([lim_mm] * 3 + [lim_rad] * 3) * 2)
    ob = observability(Jw, lim, DEGENERATE_RTOL, equilibrate=True,
                                   names=tuple(f"X.{p}" for p in DOF_NAMES) + tuple(f"Z.{p}" for p in DOF_NAMES))
    N = np.concatenate([ob.weak_space, ob.null_space], axis=1) * lim[:, None]  # back to physical units
    if N.shape[1]:
        N = N / np.linalg.norm(N, axis=0)
    length = max(float(np.sqrt(np.mean(np.sum(B[:, :3, 3] ** 2, axis=1)))), 10.0)
    names = _null_basis_names(N, length) if N.shape[1] else []
    return {
        "singular_values": sv_phys,
        "relative_singular_values": rel,
        "tolerance": {"degenerate_rtol": DEGENERATE_RTOL, "limit_mm": lim_mm, "limit_rad": lim_rad},
        "observable": ob.all_observable,
        "degenerate": ob.rank < 12,
        "std": ob.std,
        "null_space": N,
        "null_directions": tuple(names),
    }


# ----------------------------------------------------------------------------- result


def _finite_or_none(a: np.ndarray) -> list:
    """Nested lists with inf (a degenerate direction's variance) as None (strict JSON)."""
    return np.where(np.isfinite(a), a, None).tolist()


@dataclass(frozen=True)
class HandEyeResult:
    """Solution of A_i X = Z B_i.

    The covariances are the Gauss-Newton information at the solution (the Cramer-Rao
    bound of the noise model; for closed-form methods this is the bound, not their own
    spread). A direction is unobservable when the motion lacks it (degenerate; inf
    variance) or its predicted 1-sigma exceeds obs_limits (default OBS_LIMITS: 1 mm /
    0.01 rad; see ``handeye_observability``).

    Parameters
    ----------
    X, Z : numpy.ndarray, shape (4, 4)
        X = ^E T_O (lens in the flange frame) and Z = ^W T_S (sensor in the robot base), mm.
    cov_X, cov_Z : numpy.ndarray, shape (6, 6)
        Covariances of the right perturbations xi = (rho mm, omega rad) of X (in {O} axes)
        and Z (in {S} axes).
    cov : numpy.ndarray, shape (12, 12)
        The full covariance, X first, then Z.
    residuals : numpy.ndarray, shape (n, 6)
        e_i = log((Z B_i)^-1 A_i X), mm and rad.
    residual_chi2 : numpy.ndarray, shape (n,)
        e_i^T Sigma_i^-1 e_i per pose.
    chi2 : float
        Their sum.
    dof : int
        6 n - 12.
    chi2_dof : float
        chi2 / dof.
    singular_values, relative_singular_values : numpy.ndarray, shape (12,)
        Of the whitened Jacobian (relative: of its column-equilibrated form, over the largest).
    observable : bool
        Every direction observable.
    null_directions : tuple of str
        The directions that are not.
    method : str
        The method asked for.
    start_method : str
        The closed form used (for "ml", the better of Shah and Li by the weighted cost).
    iterations : int
        Residual evaluations of the ML refinement (0 for closed forms).
    converged : bool
        The refinement met its tolerance.
    noise_model : str
        "given" or "estimated" (no sigma and no cov_B: isotropic translation/rotation
        variances estimated from the closed-form residuals, so chi2_dof is ~1 by construction).
    warnings : tuple of str
        What the caller should know (weak or null directions).
    """

    X: np.ndarray
    Z: np.ndarray
    cov_X: np.ndarray
    cov_Z: np.ndarray
    cov: np.ndarray
    residuals: np.ndarray
    residual_chi2: np.ndarray
    chi2: float
    dof: int
    chi2_dof: float
    singular_values: np.ndarray
    relative_singular_values: np.ndarray
    observable: bool
    null_directions: tuple
    method: str
    start_method: str
    iterations: int
    converged: bool
    noise_model: str
    warnings: tuple = field(default=())

    @property
    def std_X(self) -> np.ndarray:
        """1-sigma of xi_X (mm, mm, mm, rad, rad, rad)."""
        return np.sqrt(np.diag(self.cov_X))

    @property
    def std_Z(self) -> np.ndarray:
        """1-sigma of xi_Z (mm, mm, mm, rad, rad, rad)."""
        return np.sqrt(np.diag(self.cov_Z))

    def to_dict(self) -> dict:
        """JSON-ready dict with the CLI's stable keys."""
        return {
            "method": self.method,
            "start_method": self.start_method,
            "X": self.X.tolist(),
            "Z": self.Z.tolist(),
            "cov_X": _finite_or_none(self.cov_X),
            "cov_Z": _finite_or_none(self.cov_Z),
            "std_X": _finite_or_none(self.std_X),
            "std_Z": _finite_or_none(self.std_Z),
            "perturbation": "right: T*P(xi), xi=(t_mm, rotvec_rad); X in {O} axes, Z in {S} axes",
            "chi2_dof": float(self.chi2_dof),
            "dof": int(self.dof),
            "residuals": self.residuals.tolist(),
            "residual_chi2": self.residual_chi2.tolist(),
            "observable": bool(self.observable),
            "null_directions": list(self.null_directions),
            "singular_values": self.singular_values.tolist(),
            "iterations": int(self.iterations),
            "converged": bool(self.converged),
            "noise_model": self.noise_model,
            "warnings": list(self.warnings),
        }


# ----------------------------------------------------------------------------- solver


def _cost(A, B, X, Z, Wh):
    e = _residuals(A, B, X, Z)
    r = np.einsum("nij,nj->ni", Wh, e)
    return float(np.sum(r * r))


def _param_jac(xi: np.ndarray) -> np.ndarray:
    """J_P(xi): P(xi + d) = P(xi) P(J_P(xi) d) to first order (6x6)."""
    M = np.zeros((6, 6))
    M[:3, :3] = pose_to_matrix(xi)[:3, :3].T
    M[3:, 3:] = right_jacobian_so3(xi[3:])
    return M


def _refine(A, B, X0, Z0, Wh, max_nfev):
    """Weighted least squares in the local parametrisation X = X0 P(p_X), Z = Z0 P(p_Z),
    with the exact analytic Jacobian of e_i = log((Z B_i)^-1 A_i X)."""
    n = A.shape[0]
    AdBinv = adjoint(invert_poses(B))

    def fun(p):
        X = X0 @ pose_to_matrix(p[:6])
        Z = Z0 @ pose_to_matrix(p[6:])
        return np.einsum("nij,nj->ni", Wh, _residuals(A, B, X, Z)).reshape(-1)

    def jac(p):
        X = X0 @ pose_to_matrix(p[:6])
        Z = Z0 @ pose_to_matrix(p[6:])
        E = invert_poses(Z @ B) @ A @ X
        e = matrix_to_pose(E)
        Jx = np.zeros((n, 6, 6))
        Jx[:, :3, :3] = E[:, :3, :3]
        Jx[:, 3:, 3:] = right_jacobian_inv_so3(e[:, 3:])
        Jx = Jx @ _param_jac(p[:6])
        L = np.zeros((n, 6, 6))
        L[:, :3, :3] = np.eye(3)
        L[:, :3, 3:] = -skew(e[:, :3])
        L[:, 3:, 3:] = right_jacobian_inv_so3(e[:, 3:], left=True)
        Jz = -(L @ AdBinv) @ _param_jac(p[6:])
        J = np.concatenate([Jx, Jz], axis=2)
        return (Wh @ J).reshape(-1, 12)

    sol = least_squares(fun, np.zeros(12), jac=jac, method="lm", xtol=1e-12, ftol=1e-12,
                        gtol=1e-12, max_nfev=max_nfev)
    return X0 @ pose_to_matrix(sol.x[:6]), Z0 @ pose_to_matrix(sol.x[6:]), sol


def _unobservable_message(obs: dict) -> str:
    t = obs["tolerance"]
    if obs["degenerate"]:
        return ("degenerate motion: unobservable " + "; ".join(obs["null_directions"])
                + ". Add poses with rotations about at least two non-parallel axes")
    return (f"weakly observable (predicted 1-sigma above {t['limit_mm']:g} mm / {t['limit_rad']:g} rad): "
            + "; ".join(obs["null_directions"]) + ". Solved anyway; more poses, larger motions or less noise "
            "would pin it down")


def solve_handeye(A: ArrayLike, B: ArrayLike, method: str = "ml", sigma: tuple[float, float] | None = None,
                  cov_B: ArrayLike | None = None, *, on_degenerate: str = "raise",
                  obs_limits: tuple[float, float] = OBS_LIMITS, max_outer: int = 4,
                  max_nfev: int = 2000) -> HandEyeResult:
    """Solve A_i X = Z B_i for X = ^E T_O and Z = ^W T_S.

    A merely noisy problem (a direction whose predicted 1-sigma exceeds ``obs_limits``) is
    always solved, with observable=False, a warning in ``warnings`` and a RuntimeWarning.

    Parameters
    ----------
    A : array_like, shape (n, 4, 4)
        Flange poses ^W T_E, mm; n >= 3.
    B : array_like, shape (n, 4, 4)
        Lens poses ^S T_O, mm.
    method : str
        "ml" (maximum likelihood over SE(3) x SE(3), started from the better of Shah and Li
        by the weighted cost), "shah" or "li" (closed forms).
    sigma : tuple, dict, array_like or object, optional
        Robot pose noise of A: (translation_mm, rotation_rad) isotropic, a dict with those
        keys, a 6x6 covariance, one per pose (n, 6, 6), or an object with ``.cov``
        (robot.RobotNoise).
    cov_B : array_like, shape (6, 6) or (n, 6, 6), optional
        Lens-pose covariance in the right-perturbation convention (the pose estimator's
        covariance at x ~ 0; see ``pose_vector_cov_to_right``). With neither sigma nor
        cov_B the noise is estimated from the data.
    on_degenerate : str
        Degenerate motion (a direction the motion lacks, see DEGENERATE_RTOL): "raise"
        (CalibrationError naming the null directions) or "warn" (return with
        observable=False, inf 1-sigma on the parameters the null directions move).
    obs_limits : tuple of float
        (mm, rad): the predicted 1-sigma beyond which a direction counts as unobservable.
    max_outer : int
        Outer re-weighting passes of the ML refinement.
    max_nfev : int
        Residual evaluations allowed per pass.

    Returns
    -------
    HandEyeResult
        X, Z (mm), their covariances, residuals, chi2 and observability.

    Raises
    ------
    CalibrationError
        Malformed input, fewer than 3 poses or (by default) degenerate motion.
    """
    if method not in METHODS:
        raise CalibrationError(f"method: {method!r} is not one of {', '.join(METHODS)}")
    if on_degenerate not in ("raise", "warn"):
        raise CalibrationError("on_degenerate: use 'raise' or 'warn'")
    A = _as_poses(A, "A")
    B = _as_poses(B, "B")
    n = A.shape[0]
    if B.shape[0] != n:
        raise CalibrationError(f"A and B: need the same number of poses, got {n} and {B.shape[0]}")
    if n < 3:
        raise CalibrationError(f"A, B: need at least 3 pose pairs with rotations about different axes, got {n}")

    candidates = {}
    for name, f in _CLOSED_FORMS.items():
        if method in (name, "ml"):
            with np.errstate(all="ignore"):
                candidates[name] = f(A, B)

    noise_given = sigma is not None or cov_B is not None
    if noise_given:
        def covs(X):
            return residual_covariances(X, n, sigma, cov_B)
    else:
        # isotropic translation / rotation variances from the closed-form residuals
        ref = min(candidates.values(), key=lambda XZ: float(np.sum(_residuals(A, B, *XZ) ** 2 * [1, 1, 1, 1e6, 1e6, 1e6])))
        e = _residuals(A, B, *ref)
        dof = max(6 * n - 12, 1)
        vt = max(float(np.sum(e[:, :3] ** 2)) / (dof / 2), 1e-24)
        vr = max(float(np.sum(e[:, 3:] ** 2)) / (dof / 2), 1e-24)
        S_est = np.broadcast_to(np.diag([vt] * 3 + [vr] * 3), (n, 6, 6)).copy()

        def covs(X):
            return S_est

    # pick the start (or the closed form asked for)
    scored = []
    for name, (X, Z) in candidates.items():
        Wh = whiteners(covs(X), "noise model")
        scored.append((_cost(A, B, X, Z, Wh), name, X, Z))
    scored.sort(key=lambda s: s[0])
    _, start, X, Z = scored[0]

    warns = []
    obs = handeye_observability(B, X, S=covs(X), obs_limits=obs_limits)
    if not obs["observable"]:
        msg = _unobservable_message(obs)
        if obs["degenerate"] and on_degenerate == "raise":
            raise CalibrationError("A, B: " + msg)
        warns.append(msg)
        _warnings.warn(msg, RuntimeWarning, stacklevel=2)

    iterations = 0
    converged = True
    if method == "ml":
        converged = False
        for _ in range(max_outer):
            Wh = whiteners(covs(X), "noise model")
            X_new, Z_new, sol = _refine(A, B, X, Z, Wh, max_nfev)
            iterations += int(sol.nfev)
            step = np.abs(matrix_to_pose(invert_poses(np.stack([X, Z])) @ np.stack([X_new, Z_new]))).max()
            X, Z = X_new, Z_new
            converged = sol.status > 0
            if not noise_given or sigma is None or step < 1e-8:
                break  # weights do not depend on X then
        if not converged:
            warns.append("ml: the optimiser stopped before converging")

    S = covs(X)
    Wh = whiteners(S, "noise model")
    e = _residuals(A, B, X, Z)
    r = np.einsum("nij,nj->ni", Wh, e)
    chi2_i = np.sum(r * r, axis=1)
    dof = 6 * n - 12
    obs = handeye_observability(B, X, S=S, obs_limits=obs_limits)
    if not obs["observable"] and not warns:
        msg = _unobservable_message(obs)
        if obs["degenerate"] and on_degenerate == "raise":
            raise CalibrationError("A, B: " + msg)
        warns.append(msg)
    Jw = (Wh @ handeye_jacobian(B)).reshape(-1, 12)
    F = Jw.T @ Jw
    cov = np.linalg.pinv(F, rcond=1e-14, hermitian=True) if obs["degenerate"] else np.linalg.inv(F)
    cov = 0.5 * (cov + cov.T)
    moved = ~np.isfinite(obs["std"])  # degenerate: inf 1-sigma, never a small finite number
    cov[moved, :] = 0.0
    cov[:, moved] = 0.0
    cov[moved, moved] = np.inf
    return HandEyeResult(
        X=X, Z=Z, cov_X=cov[:6, :6].copy(), cov_Z=cov[6:, 6:].copy(), cov=cov,
        residuals=e, residual_chi2=chi2_i, chi2=float(chi2_i.sum()), dof=dof,
        chi2_dof=float(chi2_i.sum() / dof) if dof > 0 else float("nan"),
        singular_values=obs["singular_values"], relative_singular_values=obs["relative_singular_values"],
        observable=obs["observable"], null_directions=obs["null_directions"],
        method=method, start_method=start, iterations=iterations,
        converged=converged, noise_model="given" if noise_given else "estimated", warnings=tuple(warns),
    )
