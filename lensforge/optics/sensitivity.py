"""The one Jacobian of the forward model and the one observability rule; the
sensitivity matrix S = dz/dx and the design metrics built on them.

``jacobian``: the exact dz/dx at P poses (``ForwardModel.jacobians``: the rays'
derivatives carried through the trace, the implicit function theorem for the aimed
rays and a complex step through the centroid), warm-started from the aimed rays at
each pose. Every estimator, metric and design constraint calls it.

``observability``: DESIGN.md's statistical rule on a whitened Jacobian J_w and the
scales D of its parameters. On S~ = J_w D a direction is unobservable when it is
numerically null (singular value below rtol * sigma_max) or when its predicted 1-sigma
(Fisher information S~^T S~) exceeds its scale (singular value below 1). A parameter
is unobservable when a null direction moves it (1-sigma inf, never a finite number)
or when its marginal predicted 1-sigma exceeds its scale. Lens poses use the bench's
pose scales (1 mm, 1 deg); hand-eye uses its own documented, settable limits.

Metrics (DESIGN.md) live on the scaled, noise-whitened matrix S~ = R^(-1/2) S D, with
R the Zernike noise covariance and D = diag(pose_scales): rank (singular values above
rank_rtol * sigma_max), kappa, sigma_min, the paper's cost J = w1 kappa + w2 /
sigma_min with a rank-loss penalty, the Cramer-Rao bound (S^T R^-1 S)^-1 on the pose
covariance and the observability of each DOF.
"""

from __future__ import annotations

from numpy.typing import ArrayLike

from dataclasses import dataclass

import numpy as np

from .bench import Bench
from .lens import Lens
from .pose import DOF_NAMES
from .shack_hartmann import ForwardModel, ZernikeResult

__all__ = ["jacobian", "JACOBIAN_EVALS", "observability", "Observability", "sensitivity", "sensitivity_from_model", "Metrics",
           "metrics", "metrics_from_S", "paper_cost", "RANK_PENALTY"]

RANK_PENALTY = 1e6  # added to J per lost rank
# pose traces one ``jacobian`` costs, for cost counts (n_evals, n_traced): the warm re-aim and
# three traced copies of every aimed ray with their derivatives (ForwardModel.jacobians)
JACOBIAN_EVALS = 4
# a null direction (unit vector, scaled units) "moves" a parameter when its entry exceeds
# this: exact symmetry gives exactly sparse null vectors; a geometry that is degenerate
# up to noise (``equilibrate``) gives noise-level entries (~1e-4) elsewhere
NULL_ENTRY_TOL = 1e-6
NULL_ENTRY_TOL_NOISY = 1e-2


def jacobian(model: ForwardModel, x: ArrayLike, *, uv: ArrayLike | None = None,
             check_range: bool = False) -> tuple[np.ndarray, np.ndarray, ZernikeResult]:
    """Exact Jacobians dz/dx at P poses, in one batched trace.

    Agrees with central differences (the tests' check) to their error (1e-8 relative at
    the default bench.fd_steps; tests/test_observability.py).

    Parameters
    ----------
    model : ForwardModel
        Bench and lens.
    x : array_like, shape (P, 6) or (6,)
        Poses (mm, rad) about nominal.
    uv : array_like, shape (P, ...), optional
        Aimed rays at x (``ZernikeResult.uv``) as a warm start; default: aimed here.
    check_range : bool
        Also require every lenslet's spot in the sensor's range for ``complete``.

    Returns
    -------
    J : numpy.ndarray, shape (P, m, 6)
        dz/dx in um per mm (tx, ty, tz) and um per rad (rx, ry, rz).
    complete : numpy.ndarray of bool, shape (P,)
        The pose is measurable (lit, traced, in the sensor's range).
    result : ZernikeResult
        The forward model at x (z, slopes, status, aimed rays).
    """
    x = np.atleast_2d(np.asarray(x, dtype=float))
    J, _, res = model.jacobians(x, uv0=uv, check_range=check_range)
    return J, res.valid, res


@dataclass(frozen=True)
class Observability:
    """Observability of n parameters from a whitened Jacobian (see ``observability``).

    observable: (n,) bool per parameter; std: (n,) predicted 1-sigma in the
    parameters' units (inf where a null direction moves the parameter); cov: (n, n)
    predicted covariance (pseudo-inverse on the non-null subspace when rank is lost);
    rank: numerical rank; rank_tol: absolute singular-value threshold on S~;
    singular_values: of S~ = J_w D (descending); null_space: (n, n - rank) numerically
    null directions; weak_space: (n, k) directions whose predicted 1-sigma exceeds
    their scale (singular value < limit) but are not null (both in scaled units u =
    x / D); basis: (n, rank) orthonormal basis of the non-null directions (scaled);
    names: parameter names.
    """

    observable: np.ndarray
    std: np.ndarray
    cov: np.ndarray
    rank: int
    rank_tol: float
    singular_values: np.ndarray
    null_space: np.ndarray
    weak_space: np.ndarray
    basis: np.ndarray
    names: tuple = DOF_NAMES

    @property
    def all_observable(self) -> bool:
        return bool(self.observable.all()) and self.weak_space.shape[1] == 0

    @property
    def unobservable(self) -> tuple:
        """Names of the unobservable parameters."""
        return tuple(n for n, o in zip(self.names, self.observable) if not o)

    @property
    def null_names(self) -> tuple:
        """Names of the parameters a numerically null direction moves."""
        return tuple(n for n, s in zip(self.names, self.std) if not np.isfinite(s))

    @property
    def unobservable_directions(self) -> np.ndarray:
        """(n, k) unit directions (scaled units) that are null or weaker than their scale."""
        return np.concatenate([self.null_space, self.weak_space], axis=1)

    def to_dict(self) -> dict:
        """JSON-ready: per-parameter flag, unobservable names, the names moved by a null
        direction, and the unobservable directions (scaled units, one dict each)."""
        return {"observable": {n: bool(o) for n, o in zip(self.names, self.observable)},
                "unobservable": list(self.unobservable),
                "null": list(self.null_names),
                "unobservable_directions": [{n: round(float(c), 6) for n, c in zip(self.names, v)}
                                            for v in self.unobservable_directions.T]}


def observability(Jw: ArrayLike, scales: ArrayLike, rtol: float, limit: float = 1.0, names: tuple[str, ...] = DOF_NAMES,
                  equilibrate: bool = False) -> Observability:
    """DESIGN.md's observability rule on a whitened Jacobian: a parameter is unobservable when
    it is numerically null or its predicted 1-sigma exceeds its scale.

    Parameters
    ----------
    Jw : array_like, shape (rows, n)
        Jacobian whitened by the measurement noise (R^(-1/2) J).
    scales : array_like, shape (n,)
        The parameters' scales D (the 1-sigma beyond which a parameter counts as not
        measured; lens poses: bench.pose_scales, mm and rad).
    rtol : float
        Relative singular-value threshold of numerical rank, on S~ = Jw D, or with
        ``equilibrate`` on Jw with unit column norms.
    limit : float
        Predicted 1-sigma, in units of D, above which a parameter or direction is
        unobservable (1: the scale itself).
    names : tuple of str, shape (n,)
        Parameter names (default: the pose DOF names).
    equilibrate : bool
        Rank test on the column-equilibrated Jw (a unit-free test of the geometry alone:
        noise scales all rows and leaves it unchanged).

    Returns
    -------
    Observability
        ``observable`` (n,) bool, ``std`` (n,) predicted 1-sigma in the parameters' units,
        ``cov`` (n, n), ``rank``, ``rank_tol``, ``singular_values``, ``null_space``,
        ``weak_space`` and ``basis`` (scaled units), ``names``.
    """
    Jw = np.asarray(Jw, dtype=float)
    D = np.asarray(scales, dtype=float)
    n = Jw.shape[1]
    St = Jw * D
    _, sv, Vt = np.linalg.svd(St, full_matrices=St.shape[0] < n)
    sv = np.concatenate([sv, np.zeros(n - sv.size)])
    if equilibrate:
        d = np.linalg.norm(Jw, axis=0)
        d[d == 0] = 1.0
        _, se, Vte = np.linalg.svd(Jw / d, full_matrices=Jw.shape[0] < n)
        se = np.concatenate([se, np.zeros(n - se.size)])
        tol = rtol * se[0] if se[0] > 0 else 0.0
        rank = int(np.sum(se > tol))
        null = Vte[rank:].T / (d * D)[:, None]  # equilibrated -> scaled units
        null = np.linalg.qr(null)[0] if null.shape[1] else null
        # the non-null subspace of S~: the orthogonal complement of the null directions
        Q = np.linalg.svd(np.eye(n) - null @ null.T)[0][:, :rank]
        Sr = St @ Q
        _, sr, Vr = np.linalg.svd(Sr, full_matrices=False)
        cov_scaled = (Q @ Vr.T / sr**2) @ (Q @ Vr.T).T
        weak = (Q @ Vr.T)[:, sr < 1.0 / limit]
        basis = Q
    else:
        tol = rtol * sv[0] if sv[0] > 0 else 0.0
        rank = int(np.sum(sv > tol))
        null = Vt[rank:].T
        F = St.T @ St
        cov_scaled = np.linalg.inv(F) if rank == n else np.linalg.pinv(F, rcond=rtol**2)
        weak = Vt[:rank][sv[:rank] < 1.0 / limit].T
        basis = Vt[:rank].T
    std_scaled = np.sqrt(np.clip(np.diag(cov_scaled), 0, None))
    if rank < n:
        involved = np.any(np.abs(null) > (NULL_ENTRY_TOL_NOISY if equilibrate else NULL_ENTRY_TOL), axis=1)
        std_scaled = np.where(involved, np.inf, std_scaled)
    return Observability(observable=std_scaled <= limit, std=std_scaled * D, cov=cov_scaled * np.outer(D, D),
                         rank=rank, rank_tol=float(tol), singular_values=sv, null_space=null, weak_space=weak,
                         basis=basis, names=tuple(names))


def sensitivity_from_model(model: ForwardModel, pose=None, raise_invalid: bool = True):
    """(S, z0, result) for a ForwardModel at ``pose`` (default nominal).

    S: (m, 6); z0: (m,) noise-free Zernikes at the pose. With raise_invalid=False,
    S is None when the pose is not measurable.
    """
    x0 = np.zeros(6) if pose is None else np.asarray(pose, dtype=float)
    base = model.evaluate(x0[None, :])
    if not base.valid[0]:
        if raise_invalid:
            base.raise_if_invalid()
        return None, base.z[0], base
    J, _, res = jacobian(model, x0[None, :], uv=base.uv, check_range=True)
    return J[0], base.z[0], res


def sensitivity(bench: Bench, lens: Lens, pose: ArrayLike | None = None) -> np.ndarray:
    """Sensitivity matrix S = dz/dx of a lens on a bench (exact: rays carry their tangents).

    Parameters
    ----------
    bench : Bench
        The bench.
    lens : Lens
        The lens.
    pose : array_like, shape (6,), optional
        Pose (mm, rad) about nominal; default nominal.

    Returns
    -------
    numpy.ndarray, shape (m, 6)
        um per mm (tx, ty, tz) and um per rad (rx, ry, rz); m Zernike modes (Noll 2..).
    """
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
    """Design metrics of a lens on a bench (see the module docstring for the scaling).

    Parameters
    ----------
    rank : int
        Numerical rank of the scaled, whitened S~ = R^(-1/2) S D.
    rank_tol : float
        Absolute singular-value threshold of that rank.
    kappa, sigma_min, sigma_max : float
        Condition number and extreme singular values of S~ (dimensionless).
    singular_values : numpy.ndarray, shape (6,)
        Of S~, descending.
    J : float
        The paper's cost w1 kappa + w2 / sigma_min plus the rank-loss penalty.
    crlb : numpy.ndarray, shape (6, 6)
        Cramer-Rao bound (S^T R^-1 S)^-1 of the pose, mm and rad.
    crlb_std : numpy.ndarray, shape (6,)
        Its per-DOF 1-sigma, mm and rad (inf for an unobservable DOF).
    raw_singular_values : numpy.ndarray, shape (6,)
        Of S in its own units (um/mm, um/rad).
    raw_kappa : float
        Condition number of S in its own units.
    S : numpy.ndarray, shape (m, 6)
        The sensitivity matrix dz/dx, um/mm and um/rad.
    R : numpy.ndarray, shape (m, m)
        Zernike noise covariance, um^2.
    z0 : numpy.ndarray, shape (m,)
        Zernike coefficients at the pose, um.
    null_space : numpy.ndarray, shape (6, 6 - rank)
        Numerically null pose directions (scaled units).
    weights : tuple of float
        (w1, w2) of J.
    observability : Observability or None
        DESIGN.md's statistical rule per DOF (:func:`observability`).
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
    observability: Observability | None = None

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
            **(self.observability.to_dict() if self.observability is not None else {}),
        }


def metrics_from_S(S: np.ndarray, R: np.ndarray, bench: Bench, z0=None, weights=(1.0, 1.0)) -> Metrics:
    """Metrics of a sensitivity matrix S (m, 6) with Zernike noise covariance R (m, m)."""
    L = np.linalg.cholesky(R)
    obs = observability(np.linalg.solve(L, S), bench.pose_scales, bench.rank_rtol)
    sv = obs.singular_values
    kappa = sv[0] / sv[-1] if sv[-1] > 0 else np.inf
    raw_sv = np.linalg.svd(S, compute_uv=False)
    return Metrics(
        rank=obs.rank, rank_tol=obs.rank_tol, kappa=float(kappa), sigma_min=float(sv[-1]), sigma_max=float(sv[0]),
        singular_values=sv, J=paper_cost(sv, obs.rank, weights), crlb=obs.cov, crlb_std=obs.std,
        raw_singular_values=raw_sv, raw_kappa=float(raw_sv[0] / raw_sv[-1]) if raw_sv[-1] > 0 else np.inf,
        S=S, R=R, z0=np.zeros(S.shape[0]) if z0 is None else z0, null_space=obs.null_space, weights=tuple(weights),
        observability=obs,
    )


def metrics(bench: Bench, lens: Lens, pose: ArrayLike | None = None,
            weights: tuple[float, float] = (1.0, 1.0)) -> Metrics:
    """Rank, kappa, sigma_min, J and the Cramer-Rao bound of a lens on a bench.

    Parameters
    ----------
    bench : Bench
        The bench (its noise model gives R, its pose_scales D).
    lens : Lens
        The lens.
    pose : array_like, shape (6,), optional
        Pose (mm, rad) about nominal; default nominal.
    weights : tuple of float
        (w1, w2) of the paper's cost J = w1 kappa + w2 / sigma_min.

    Returns
    -------
    Metrics
        Metrics of the scaled S~ = R^(-1/2) S D, the CRLB (mm, rad) and observability.
    """
    model = ForwardModel(bench, lens)
    S, z0, _ = sensitivity_from_model(model, pose)
    return metrics_from_S(S, model.noise_cov, bench, z0, weights)
