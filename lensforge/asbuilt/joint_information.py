"""Fisher information of the joint calibration (X, Z, as-built lens theta), pose by pose.

Pure mathematics shared by the calibration's pose design (``calibration.joint_design``,
``calibration.joint``) and the lens-and-bench design (``design.selfcal``), which may not
import calibration (imports run optics <- asbuilt <- design / calibration).

A lens pose i at ^S T_O = B_i (pose vector x_i about nominal), held with grasp X, gives
the whitened Zernike Jacobians S_i = L^-1 dh/dx (m, 6) and Jt_i = L^-1 dh/dtheta (m, k).
With the robot's pose error a_i ~ N(0, Sigma_A) eliminated (Schur complement), its
information on g = (xi_X, xi_Z, theta) is

    I_i = Jg^T Jg - Jg^T Ja (Ja^T Ja + Sigma_A^-1)^-1 Ja^T Jg,   Jg = [S dX, S dZ, Jt], Ja = S dA,

with dX, dZ, dA the derivatives of x_i along right perturbations of X, Z and the flange
pose (``chain_jacobians``). The prior on theta is N(0, I) (``theta_prior``). The
Ds-criterion of Z is -log det of the Z block of (sum_i I_i + prior)^-1 (``z_ds``);
``select_ds`` picks n of a set of candidate poses for it (greedy forward selection, then
exchange passes; a pose may be chosen more than once).
"""

from __future__ import annotations

import numpy as np

from ..optics.pose import adjoint, invert_poses, right_jacobian_inv_so3, rotations

__all__ = ["chain_jacobians", "pose_information", "theta_prior", "z_ds", "z_sigma",
           "select_ds"]


def chain_jacobians(B, x, X):
    """dx_i / d(xi_X, xi_Z, a_i): (n, 6, 6) each (right perturbations; a_i small), for lens
    poses B (n, 4, 4) = ^S T_O, their pose vectors x (n, 6) and the grasp X (4, 4)."""
    Minv = np.zeros(x.shape[:-1] + (6, 6))
    Minv[..., :3, :3] = rotations(x[..., 3:])
    Minv[..., 3:, 3:] = right_jacobian_inv_so3(x[..., 3:])
    dX = Minv
    dZ = -Minv @ adjoint(invert_poses(B))
    dA = Minv @ adjoint(invert_poses(X))
    return dX, dZ, dA


def pose_information(S_w, Jt, B, x, X, robot_cov) -> np.ndarray:
    """I (n, G, G), G = 12 + k: information of (xi_X, xi_Z, theta) of each pose with its robot
    error eliminated. S_w (n, m, 6) and Jt (n, m, k): whitened Jacobians of h in pose and
    theta; B (n, 4, 4), x (n, 6): the lens poses; X (4, 4) grasp; robot_cov (6, 6) (mm, rad)^2."""
    dX, dZ, dA = chain_jacobians(B, x, X)
    Jg = np.concatenate([S_w @ dX, S_w @ dZ, Jt], axis=2)
    Ja = S_w @ dA
    P = np.linalg.inv(np.asarray(robot_cov, dtype=float))
    Haa = np.einsum("nmi,nmj->nij", Ja, Ja) + P
    Hga = np.einsum("nmi,nmj->nij", Jg, Ja)
    I = np.einsum("nmi,nmj->nij", Jg, Jg) - Hga @ np.linalg.solve(Haa, np.swapaxes(Hga, 1, 2))
    return 0.5 * (I + np.swapaxes(I, 1, 2))


def theta_prior(k: int) -> np.ndarray:
    """(12 + k)^2 prior information: N(0, I) on theta, nothing on X and Z."""
    P = np.zeros((12 + k, 12 + k))
    P[12:, 12:] = np.eye(k)
    return P


def z_ds(F) -> np.ndarray:
    """-log det of the Z block of F^-1 for a stack of information matrices (..., G, G)
    (lower Cov(Z): higher value; the Ds-criterion to maximise)."""
    C = np.linalg.inv(F)
    return -np.linalg.slogdet(C[..., 6:12, 6:12])[1]


def z_sigma(F: np.ndarray) -> dict:
    """Predicted Z 1-sigma of information F (G, G), with theta free and, for comparison, known:
    keys cov, Z_sigma_mm (3), Z_sigma_deg (3), Z_translation_mm / Z_rotation_deg (RMS norms of
    the error vectors), *_known_lens_*, theta_sigma (posterior sd, prior 1)."""
    C = np.linalg.inv(F)
    d = np.sqrt(np.diag(C)[6:12])
    d0 = np.sqrt(np.diag(np.linalg.inv(F[:12, :12]))[6:12])
    return {"cov": C, "Z_sigma_mm": d[:3].tolist(), "Z_sigma_deg": np.degrees(d[3:]).tolist(),
            "Z_translation_mm": float(np.sqrt(np.sum(d[:3] ** 2))),
            "Z_rotation_deg": float(np.degrees(np.sqrt(np.sum(d[3:] ** 2)))),
            "Z_translation_known_lens_mm": float(np.sqrt(np.sum(d0[:3] ** 2))),
            "Z_rotation_known_lens_deg": float(np.degrees(np.sqrt(np.sum(d0[3:] ** 2)))),
            "theta_sigma": np.sqrt(np.diag(C)[12:]).tolist()}


def select_ds(Ic, k: int, n: int, max_passes: int = 10):
    """Greedy Ds selection of n of the candidates' informations Ic (m, G, G), then exchange
    passes. Returns (chosen indices (n,), F = sum + prior + eps, eps (G, G), swaps)."""
    F0 = theta_prior(k)
    eps = 1e-9 * np.trace(Ic.sum(axis=0)) / Ic.shape[0] * np.eye(F0.shape[0])
    F = F0 + eps
    chosen: list[int] = []
    for _ in range(n):
        j = int(np.argmax(z_ds(F[None] + Ic)))
        chosen.append(j)
        F = F + Ic[j]
    swaps = 0
    for _ in range(max_passes):
        improved = False
        for pos in range(n):
            Fm = F - Ic[chosen[pos]]
            g = z_ds(Fm[None] + Ic)
            j = int(np.argmax(g))
            if j != chosen[pos] and g[j] > z_ds(F) + 1e-9:
                chosen[pos] = j
                F = Fm + Ic[j]
                swaps += 1
                improved = True
        if not improved:
            break
    return chosen, F, eps, swaps
