"""Optimal experiment design of hand-eye calibration poses.

Choose n lens poses (relative to nominal, inside the working box where the
Shack-Hartmann pupil stays lit) that maximise log det of the Fisher information of
(X, Z) - D-optimality - with the same whitened Jacobian as the ``ml`` solver
(``handeye.handeye_fisher``): F = sum_i J_i^T Sigma_i^-1 J_i, J_i = [I, -Ad_{B_i^-1}],
Sigma_i = cov_B + Ad_{X^-1} Sigma_A Ad_{X^-1}^T. log det F is invariant to the units
of X and Z, so mm and rad mix without a scale choice.

Algorithm: greedy forward selection (rank-6 updates by the matrix determinant lemma,
all candidates at once) followed by Fedorov exchange passes until no swap improves
log det (a candidate may be chosen more than once: repeated poses are valid
measurements). Candidates: the 64 corners of the 6-D box plus random points (D-optimal
designs for such linearised models sit mostly on the box boundary).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from .handeye import handeye_jacobian, residual_covariances, whiteners
from .robot import Scene, flange_pose, lens_pose_matrix, random_lens_poses

__all__ = ["DesignResult", "design_poses", "predicted_uncertainty", "candidate_poses", "information_factors",
           "z_translation_std"]


def candidate_poses(rng: np.random.Generator, n_random: int = 436, translation_mm: float = 1.0,
                    rotation_rad: float = math.radians(1.0)) -> np.ndarray:
    """Candidate pose vectors (m, 6): the 64 box corners, then n_random uniform points."""
    corners = np.array(list(itertools.product((-1.0, 1.0), repeat=6)))
    corners *= [translation_mm] * 3 + [rotation_rad] * 3
    return np.concatenate([corners, random_lens_poses(rng, n_random, translation_mm, rotation_rad)])


def information_factors(scene: Scene, x, cov_B, sigma=None) -> np.ndarray:
    """G_c (m, 12, 6) with J_c^T Sigma_c^-1 J_c = G_c G_c^T for lens poses x (m, 6).
    sigma: robot noise (default scene.noise); cov_B: lens-pose covariance 6x6."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    B = lens_pose_matrix(scene, x)
    S = residual_covariances(scene.X, x.shape[0], scene.noise if sigma is None else sigma, cov_B)
    W = whiteners(S, "noise model")
    return np.swapaxes(W @ handeye_jacobian(B), 1, 2)


def _summary(F: np.ndarray) -> dict:
    cov = np.linalg.inv(F)
    d = np.diag(cov)
    return {
        "cov": cov,
        "logdet": float(np.linalg.slogdet(F)[1]),
        # root of the trace of each 3x3 block: RMS norm of the error vector
        "X_translation_mm": float(np.sqrt(d[0:3].sum())),
        "X_rotation_rad": float(np.sqrt(d[3:6].sum())),
        "Z_translation_mm": float(np.sqrt(d[6:9].sum())),
        "Z_rotation_rad": float(np.sqrt(d[9:12].sum())),
    }


def z_translation_std(F: np.ndarray, rtol: float = 1e-12) -> np.ndarray:
    """RMS Z translation 1-sigma (mm) of a stack of information matrices (m, G, G) with X in
    0:6 and Z in 6:12. A random plan may be singular: where a lost direction (eigenvalue below
    rtol * the largest) reaches Z's translation, that set's sigma is inf, not the pseudo-inverse's
    finite (or, with rounding, negative) trace that a pinv would give."""
    w, V = np.linalg.eigh(F)
    lost = w <= rtol * w[..., -1:]
    Vz = V[..., 6:9, :]
    reach = np.any(lost & np.any(np.abs(Vz) > 1e-6, axis=-2), axis=-1)
    var = np.sum(np.where(lost[..., None, :], 0.0, Vz ** 2 / np.where(lost, 1.0, w)[..., None, :]), axis=(-2, -1))
    return np.where(reach, np.inf, np.sqrt(var))


def predicted_uncertainty(scene: Scene, x, cov_B, sigma=None) -> dict:
    """Predicted (Cramer-Rao) calibration uncertainty for lens poses x (n, 6): keys cov
    (12x12, right perturbations of X then Z, (mm, rad)), logdet (of F), and the RMS
    error norms X_/Z_translation_mm and X_/Z_rotation_rad (sqrt of the block traces)."""
    G = information_factors(scene, x, cov_B, sigma)
    return _summary(np.einsum("mij,mkj->ik", G, G))


@dataclass(frozen=True)
class DesignResult:
    """Chosen calibration poses and their predicted uncertainty vs random poses.

    x: (n, 6) chosen lens pose vectors (mm, rad) relative to nominal; A: (n, 4, 4)
    commanded flange poses; chosen / random: predicted_uncertainty() dicts (random:
    median over n_random_sets random designs of the same size, each entry a median);
    ratio_Z_translation / ratio_Z_rotation: random / chosen (> 1 means the design helps).
    """

    x: np.ndarray
    A: np.ndarray
    chosen: dict
    random: dict
    ratio_Z_translation: float
    ratio_Z_rotation: float
    exchanges: int


def _greedy_exchange(G: np.ndarray, n: int, max_passes: int = 20) -> tuple[list[int], int]:
    m = G.shape[0]
    Msum = np.einsum("mij,mkj->ik", G, G)
    eps = 1e-9 * np.trace(Msum) / (12 * m)
    F = eps * np.eye(12)
    chosen: list[int] = []
    I6 = np.eye(6)

    def gains(Finv):
        H = I6 + np.einsum("mji,jk,mkl->mil", G, Finv, G)
        return np.linalg.slogdet(H)[1]

    for _ in range(n):
        g = gains(np.linalg.inv(F))
        k = int(np.argmax(g))
        chosen.append(k)
        F = F + G[k] @ G[k].T
    swaps = 0
    for _ in range(max_passes):
        improved = False
        for pos in range(n):
            i = chosen[pos]
            F_minus = F - G[i] @ G[i].T
            ld_minus = np.linalg.slogdet(F_minus)[1]
            g = gains(np.linalg.inv(F_minus))
            k = int(np.argmax(g))
            cur = np.linalg.slogdet(F)[1]
            if ld_minus + g[k] > cur + 1e-10 and k != i:
                chosen[pos] = k
                F = F_minus + G[k] @ G[k].T
                swaps += 1
                improved = True
        if not improved:
            break
    return chosen, swaps


def design_poses(scene: Scene, cov_B, n: int = 12, rng: np.random.Generator | None = None, *,
                 candidates=None, translation_mm: float = 1.0, rotation_rad: float = math.radians(1.0),
                 n_random_sets: int = 50, sigma=None, check_reach: bool = True) -> DesignResult:
    """D-optimal choice of n calibration lens poses.

    scene: robot.Scene (X, Z, robot noise); cov_B: 6x6 lens-pose covariance (the
    pose-estimation CRLB at nominal, (mm, rad)^2); candidates: (m, 6) pose vectors
    (default: candidate_poses(rng, ...) in the +-translation_mm / +-rotation_rad box);
    n_random_sets: random n-pose designs drawn from the same box for comparison.
    check_reach: verify the chosen flange poses with inverse kinematics.
    """
    if rng is None:
        raise ConfigError("design_poses: pass rng=np.random.default_rng(seed) (no hidden global state)")
    if n < 3:
        raise ConfigError(f"design_poses: n must be >= 3 (got {n})")
    cand = candidate_poses(rng, 436, translation_mm, rotation_rad) if candidates is None else \
        np.atleast_2d(np.asarray(candidates, dtype=float))
    if cand.ndim != 2 or cand.shape[1] != 6 or cand.shape[0] < n:
        raise ConfigError(f"candidates: need an (m >= {n}, 6) array of pose vectors, got {cand.shape}")
    G = information_factors(scene, cand, cov_B, sigma)
    idx, swaps = _greedy_exchange(G, n)
    x = cand[idx]
    chosen = _summary(np.einsum("mij,mkj->ik", G[idx], G[idx]))
    rand = []
    for _ in range(n_random_sets):
        xr = random_lens_poses(rng, n, translation_mm, rotation_rad)
        rand.append(predicted_uncertainty(scene, xr, cov_B, sigma))
    keys = ("logdet", "X_translation_mm", "X_rotation_rad", "Z_translation_mm", "Z_rotation_rad")
    random = {k: float(np.median([r[k] for r in rand])) for k in keys}
    A = flange_pose(scene, x, check_reach=check_reach)
    return DesignResult(
        x=x, A=A, chosen=chosen, random=random,
        ratio_Z_translation=random["Z_translation_mm"] / chosen["Z_translation_mm"],
        ratio_Z_rotation=random["Z_rotation_rad"] / chosen["Z_rotation_rad"],
        exchanges=swaps,
    )
