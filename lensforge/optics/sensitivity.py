"""Sensitivity matrix S = dz/dx and the design metrics built on it.

S (m x 6, um per mm / um per rad) by central differences: all 12 displaced poses
traced in one batched call, warm-started from the nominal pose's aimed rays.
Metrics (DESIGN.md) live on the scaled, noise-whitened matrix
S~ = R^(-1/2) S D, with R the Zernike noise covariance and D = diag(pose_scales):
rank (singular values above rank_rtol * sigma_max), kappa, sigma_min, the paper's
cost J = w1 kappa + w2 / sigma_min with a rank-loss penalty, and the Cramer-Rao
bound (S^T R^-1 S)^-1 on the pose covariance.
"""

from __future__ import annotations

from numpy.typing import ArrayLike

from dataclasses import dataclass

import numpy as np

from .bench import Bench
from .lens import Lens
from .pose import DOF_NAMES
from .shack_hartmann import ForwardModel

__all__ = ["sensitivity", "sensitivity_from_model", "Metrics", "metrics", "metrics_from_S", "paper_cost",
           "RANK_PENALTY"]

RANK_PENALTY = 1e6  # added to J per lost rank


def sensitivity_from_model(model: ForwardModel, pose=None, raise_invalid: bool = True):
    """(S, z0, result) for a ForwardModel at ``pose`` (default nominal).

    S: (m, 6); z0: (m,) noise-free Zernikes at the pose. With raise_invalid=False,
    S is None when any of the 13 poses is not measurable.
    """
    x0 = np.zeros(6) if pose is None else np.asarray(pose, dtype=float)
    h = np.asarray(model.bench.fd_steps, dtype=float)
    base = model.evaluate(x0[None, :])
    if not base.valid[0]:
        if raise_invalid:
            base.raise_if_invalid()
        return None, base.z[0], base
    steps = np.diag(h)
    poses = np.concatenate([x0 + steps, x0 - steps])
    res = model.evaluate(poses, uv0=np.broadcast_to(base.uv, (12,) + base.uv.shape[1:]))
    if not res.valid.all():
        if raise_invalid:
            res.raise_if_invalid()
        return None, base.z[0], res
    S = (res.z[:6] - res.z[6:]).T / (2.0 * h)
    return S, base.z[0], res


def sensitivity(bench: Bench, lens: Lens, pose: ArrayLike | None = None) -> np.ndarray:
    """Sensitivity matrix S = dz/dx (m x 6): um per mm (tx, ty, tz), um per rad (rx, ry, rz)."""
    return sensitivity_from_model(ForwardModel(bench, lens), pose)[0]


def paper_cost(sv: np.ndarray, rank: int, weights=(1.0, 1.0), n_dof: int = 6) -> float:
    """J = w1 kappa + w2 / sigma_min on singular values sv (descending), plus
    RANK_PENALTY per lost rank; finite for any input."""
    sv = np.asarray(sv, dtype=float)
    smax = sv[0] if sv.size else 0.0
    if smax <= 0:
        return RANK_PENALTY * (n_dof + 1)
    smin = max(sv[-1], smax * 1e-15)
    kappa = min(smax / smin, 1e15)
    return float(weights[0] * kappa + weights[1] / smin + RANK_PENALTY * (n_dof - rank))


@dataclass(frozen=True)
class Metrics:
    """Design metrics of a lens on a bench (see module docstring).

    rank/rank_tol, kappa, sigma_min, sigma_max, singular_values: of S~ (dimensionless);
    J: paper cost; crlb: (6, 6) pose covariance bound (mm, rad); crlb_std: (6,)
    per-DOF std (mm, rad; inf for unobservable DOF); raw_*: of S in its own units
    (um/mm, um/rad); S: (m, 6); R: (m, m) um^2; z0: Zernikes at the pose (um);
    null_space: (6, 6 - rank) unobservable pose directions (scaled units).
    """

    rank: int
    rank_tol: float
    kappa: float
    sigma_min: float
    sigma_max: float
    singular_values: np.ndarray
    J: float
    crlb: np.ndarray
    crlb_std: np.ndarray
    raw_singular_values: np.ndarray
    raw_kappa: float
    S: np.ndarray
    R: np.ndarray
    z0: np.ndarray
    null_space: np.ndarray
    weights: tuple = (1.0, 1.0)

    def to_dict(self) -> dict:
        """JSON-ready summary (inf -> None) with units in the keys."""
        def f(v):
            v = float(v)
            return v if np.isfinite(v) else None

        std = self.crlb_std
        return {
            "rank": int(self.rank),
            "rank_tol": self.rank_tol,
            "kappa": f(self.kappa),
            "sigma_min": f(self.sigma_min),
            "sigma_max": f(self.sigma_max),
            "J": f(self.J),
            "weights": list(self.weights),
            "singular_values": [f(v) for v in self.singular_values],
            "crlb_std": {
                **{f"{n}_um": f(s * 1e3) for n, s in zip(DOF_NAMES[:3], std[:3])},
                **{f"{n}_urad": f(s * 1e6) for n, s in zip(DOF_NAMES[3:], std[3:])},
            },
            "raw_singular_values": [f(v) for v in self.raw_singular_values],
            "raw_kappa": f(self.raw_kappa),
        }


def metrics_from_S(S: np.ndarray, R: np.ndarray, bench: Bench, z0=None, weights=(1.0, 1.0)) -> Metrics:
    """Metrics of a sensitivity matrix S (m, 6) with Zernike noise covariance R (m, m)."""
    L = np.linalg.cholesky(R)
    D = np.asarray(bench.pose_scales, dtype=float)
    St = np.linalg.solve(L, S) * D  # whitened and scaled; same singular values as R^-1/2 S D
    U, sv, Vt = np.linalg.svd(St, full_matrices=False)
    tol = bench.rank_rtol * sv[0] if sv[0] > 0 else 0.0
    rank = int(np.sum(sv > tol))
    kappa = sv[0] / sv[-1] if sv[-1] > 0 else np.inf
    null = Vt[rank:].T
    F = St.T @ St  # scaled Fisher information
    if rank == S.shape[1]:
        cov_scaled = np.linalg.inv(F)
        std_scaled = np.sqrt(np.diag(cov_scaled))
    else:
        cov_scaled = np.linalg.pinv(F, rcond=bench.rank_rtol**2)
        std_scaled = np.sqrt(np.clip(np.diag(cov_scaled), 0, None))
        involved = np.any(np.abs(null) > 1e-6, axis=1)
        std_scaled = np.where(involved, np.inf, std_scaled)
    crlb = cov_scaled * np.outer(D, D)
    raw_sv = np.linalg.svd(S, compute_uv=False)
    return Metrics(
        rank=rank, rank_tol=tol, kappa=float(kappa), sigma_min=float(sv[-1]), sigma_max=float(sv[0]),
        singular_values=sv, J=paper_cost(sv, rank, weights), crlb=crlb, crlb_std=std_scaled * D,
        raw_singular_values=raw_sv, raw_kappa=float(raw_sv[0] / raw_sv[-1]) if raw_sv[-1] > 0 else np.inf,
        S=S, R=R, z0=np.zeros(S.shape[0]) if z0 is None else z0, null_space=null, weights=tuple(weights),
    )


def metrics(bench: Bench, lens: Lens, pose: ArrayLike | None = None,
            weights: tuple[float, float] = (1.0, 1.0)) -> Metrics:
    """Rank, kappa, sigma_min, J and the Cramer-Rao bound of a lens on a bench."""
    model = ForwardModel(bench, lens)
    S, z0, _ = sensitivity_from_model(model, pose)
    return metrics_from_S(S, model.noise_cov, bench, z0, weights)
