"""Lens pose estimation from one Shack-Hartmann measurement: invert z = h(x).

Two estimators on the same forward model (``ForwardModel`` of the optics core):

``lm`` (default): nonlinear least squares on the noise-whitened residual
r(x) = L^-1 (h(x) - z), R = L L^T the Zernike noise covariance, solved with
scipy.optimize.least_squares (trust-region reflective, Levenberg-Marquardt-like
steps). The Jacobian comes from one batched trace of the 12 central-difference
poses (or 6 forward ones), warm-started from the aimed rays at x. The reported
covariance is the Gauss-Newton one, (J^T R^-1 J)^-1 at the solution: for the
noise levels of the bench the problem is locally linear, so this is the
Cramer-Rao bound evaluated at the estimate, and chi2 = r^T r follows a chi-square
law with m - 6 degrees of freedom.

``ukf``: the paper's baseline, an unscented Kalman filter on a static state (the
pose), prior N(x0, P0) from the gripper/robot uncertainty model
(``initial_poses.prior_covariance``), scaled sigma points (Van der Merwe), all 13
sigma points traced in one batch. ``ukf_repeats`` repeats predict/update on the
*same* measurement (the paper's "12 iterations"). CAUTION: each update treats the
measurement as new, independent information. With k repeats the filter has
effectively seen the measurement k times, so the reported covariance shrinks by
about 1/k (the information is counted k times: P ~ (P0^-1 + k S^T R^-1 S)^-1)
while the actual error does not: the UKF covariance is overconfident by ~k (its
normalised estimation error squared, NEES, ~ 6k instead of 6). The repeats do
help the *mean* walk towards the least-squares solution (like an iterated
filter); ``lm`` gets there directly and reports an honest covariance.

Rank loss (e.g. a rotationally symmetric lens: rotation about the optical axis
is unobservable). Choice made here: detected from the whitened, scaled Jacobian
at the initial pose with the bench's ``rank_rtol`` (the same test as
``metrics``). ``on_rank_loss="warn"`` (default) warns with
:class:`UnobservableWarning`, estimates only the observable subspace (the
unobservable directions stay at x0), names them in ``PoseEstimate.unobservable``
(the DOF each null direction mostly moves) and puts ``inf`` on that DOF's
covariance diagonal (zero off-diagonal);
``on_rank_loss="raise"`` raises :class:`~lensforge.errors.RankError`.

Units: pose (tx, ty, tz) mm, (rx, ry, rz) rad (rotation vector, DESIGN.md);
Zernike coefficients um.
"""

from __future__ import annotations

from numpy.typing import ArrayLike
from typing import Any

import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ..errors import ConfigError, PoseRangeError, PupilError, RankError
from ..optics.bench import Bench
from ..optics.lens import Lens
from ..optics.pose import DOF_NAMES
from ..optics.shack_hartmann import ForwardModel, check_pose_range

__all__ = ["PoseEstimate", "UnobservableWarning", "estimate_pose", "estimate_pose_model", "METHODS"]

METHODS = ("lm", "ukf")


class UnobservableWarning(UserWarning):
    """Some pose direction is not observable from the measurement (rank loss)."""


@dataclass(frozen=True, eq=False)
class PoseEstimate:
    """Result of one pose estimate.

    pose: (6,) estimate (mm, rad), relative to the nominal placement;
    cov: (6, 6) reported covariance (mm^2, mm rad, rad^2); inf on the diagonal of
    unobservable DOF; chi2: whitened residual sum of squares r^T R^-1 r at the
    estimate; dof: m - (number of estimated DOF); iterations: Jacobian
    evaluations (lm) or filter updates (ukf); converged: the solver met its
    tolerances and the estimate is measurable and in range; n_evals: poses
    traced by the forward model (cost measure: ~0.3 ms each on one core);
    message: solver message or why it failed; method: "lm" or "ukf";
    unobservable: names of unobservable DOF ("rz", ...); x0: the initial pose.
    """

    pose: np.ndarray
    cov: np.ndarray
    chi2: float
    dof: int
    iterations: int
    converged: bool
    n_evals: int
    message: str
    method: str = "lm"
    unobservable: tuple = ()
    x0: np.ndarray = field(default_factory=lambda: np.zeros(6))

    @property
    def std(self) -> np.ndarray:
        """Reported per-DOF standard deviation (mm, rad)."""
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    @property
    def chi2_dof(self) -> float:
        """chi2 / dof (~1 when the model and the noise model are right)."""
        return float(self.chi2 / self.dof) if self.dof > 0 else float("nan")

    def nees(self, true_pose) -> float:
        """Normalised estimation error squared (e^T cov^-1 e) over the observable
        DOF; ~ chi-square with that many DOF for an honest covariance."""
        e = self.pose - np.asarray(true_pose, dtype=float)
        obs = np.isfinite(np.diag(self.cov))
        c = self.cov[np.ix_(obs, obs)]
        return float(e[obs] @ np.linalg.solve(c, e[obs]))

    def to_dict(self) -> dict:
        """JSON-ready summary (inf -> None); units in the keys."""
        std = self.std
        return {
            "method": self.method,
            "pose": {**{f"{n}_mm": float(v) for n, v in zip(DOF_NAMES[:3], self.pose[:3])},
                     **{f"{n}_rad": float(v) for n, v in zip(DOF_NAMES[3:], self.pose[3:])}},
            "std": {**{f"{n}_um": (float(s * 1e3) if np.isfinite(s) else None) for n, s in zip(DOF_NAMES[:3], std[:3])},
                    **{f"{n}_urad": (float(s * 1e6) if np.isfinite(s) else None)
                       for n, s in zip(DOF_NAMES[3:], std[3:])}},
            "chi2": float(self.chi2),
            "dof": int(self.dof),
            "iterations": int(self.iterations),
            "converged": bool(self.converged),
            "n_evals": int(self.n_evals),
            "unobservable": list(self.unobservable),
            "message": self.message,
        }


# --- input checks ------------------------------------------------------------------


def _check_vector(name: str, v, n: int) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}: expected {n} numbers, got {type(v).__name__}") from None
    if a.shape != (n,):
        raise ConfigError(f"{name}: expected shape ({n},), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"{name}: contains NaN or inf")
    return a


def _check_cov(name: str, c, n: int) -> np.ndarray:
    a = np.asarray(c, dtype=float)
    if a.shape != (n, n) or not np.all(np.isfinite(a)):
        raise ConfigError(f"{name}: expected a finite ({n}, {n}) matrix, got shape {a.shape}")
    a = 0.5 * (a + a.T)
    try:
        np.linalg.cholesky(a)
    except np.linalg.LinAlgError:
        raise ConfigError(f"{name}: not positive definite") from None
    return a


# --- the whitened problem ------------------------------------------------------------


class _Whitened:
    """Residuals and Jacobians of one measurement; counts traced poses; keeps
    the last aimed rays as warm start. Internal, one per estimate."""

    def __init__(self, model: ForwardModel, z: np.ndarray, jac: str):
        self.model = model
        self.z = z
        self.Linv = model.whitener  # whitening: r = Linv d
        self.h = np.asarray(model.bench.fd_steps, dtype=float)
        self.jac_mode = jac
        self.n_evals = 0
        self._uv = None
        self._cache = {}
        self._jcache = {}

    def whiten(self, d: np.ndarray) -> np.ndarray:
        return d @ self.Linv.T

    def evaluate(self, poses):
        poses = np.atleast_2d(poses)
        uv0 = None if self._uv is None else np.broadcast_to(self._uv, (len(poses),) + self._uv.shape)
        res = self.model.evaluate(poses, uv0=uv0, check_range=False)
        self.n_evals += len(poses)
        return res

    def base(self, x: np.ndarray):
        """(z(x), valid) with caching of the last point."""
        key = x.tobytes()
        if key not in self._cache:
            res = self.evaluate(x)
            if res.valid[0]:
                self._uv = res.uv[0].copy()
            self._cache = {key: (res.z[0], bool(res.valid[0]), res)}
        return self._cache[key]

    def residual(self, x: np.ndarray) -> np.ndarray:
        zx, ok, _ = self.base(x)
        if not ok:
            return np.full(self.z.shape, np.nan)
        return self.whiten(zx - self.z)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """dz/dx (m, 6), whitened; one batched trace; one-sided where a side is unlit."""
        key = x.tobytes()
        if key in self._jcache:
            return self._jcache[key]
        z0, ok0, _ = self.base(x)
        h = self.h
        steps = np.diag(h)
        if self.jac_mode == "forward":
            res = self.evaluate(x + steps)
            zp, vp = res.z, res.valid
            J = np.where(vp[None, :], (zp - z0).T / h, 0.0)
        else:
            res = self.evaluate(np.concatenate([x + steps, x - steps]))
            zp, zm, vp, vm = res.z[:6], res.z[6:], res.valid[:6], res.valid[6:]
            central = (zp - zm).T / (2 * h)
            fwd = (zp - z0).T / h
            bwd = (z0 - zm).T / h
            J = np.where(vp & vm, central, np.where(vp, fwd, np.where(vm, bwd, 0.0)))
        Jw = self.whiten(J.T).T
        self._jcache = {key: Jw}
        return Jw


def _rank_split(Jw: np.ndarray, bench: Bench):
    """Observable basis (6, k) and null basis (6, 6-k) in scaled coordinates u = x / D."""
    D = np.asarray(bench.pose_scales, dtype=float)
    _, sv, Vt = np.linalg.svd(Jw * D, full_matrices=True)
    tol = bench.rank_rtol * sv[0] if sv[0] > 0 else np.inf
    k = int(np.sum(sv > tol))
    return Vt[:k].T, Vt[k:].T, D


def _null_names(null: np.ndarray) -> tuple:
    return tuple(DOF_NAMES[int(np.argmax(np.abs(v)))] for v in null.T)


def _expand_cov(cov_obs_u: np.ndarray, V: np.ndarray, null: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Covariance in x of an estimate restricted to span(V) (scaled coords); inf on
    the DOF the null space touches."""
    cov = (V @ cov_obs_u @ V.T) * np.outer(D, D)
    return _mark_unobservable(cov, null)


def _mark_unobservable(cov: np.ndarray, null: np.ndarray) -> np.ndarray:
    """inf variance (zero covariances) on the DOF each null direction mostly moves."""
    cov = cov.copy()
    for v in null.T:
        i = int(np.argmax(np.abs(v)))
        cov[i, :] = 0.0
        cov[:, i] = 0.0
        cov[i, i] = np.inf
    return cov


def _in_range(bench: Bench, x: np.ndarray) -> str:
    try:
        check_pose_range(bench, x)
    except PoseRangeError as e:
        return str(e)
    return ""


# --- estimators --------------------------------------------------------------------------


def _lm(prob: _Whitened, x0: np.ndarray, V: np.ndarray, D: np.ndarray, max_iter: int, tol: float):
    """least_squares over y, x = x0 + D * (V y)."""
    k = V.shape[1]

    def to_x(y):
        return x0 + D * (V @ y)

    def fun(y):
        return prob.residual(to_x(y))

    def jac(y):
        return (prob.jacobian(to_x(y)) * D) @ V

    sol = least_squares(fun, np.zeros(k), jac=jac, method="trf", xtol=tol, ftol=tol, gtol=tol,
                        max_nfev=max_iter, x_scale=1.0)
    x = to_x(sol.x)
    Jy = sol.jac
    return x, sol, Jy


def _merwe_weights(n: int, alpha: float, beta: float, kappa: float):
    lam = alpha**2 * (n + kappa) - n
    wm = np.full(2 * n + 1, 0.5 / (n + lam))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = lam / (n + lam) + (1 - alpha**2 + beta)
    return wm, wc, n + lam


def _ukf(prob: _Whitened, x0, P0, Q, R, repeats: int, alpha: float, beta: float, kappa: float, V, D):
    """Static-state UKF in the observable subspace y (x = x0 + D V y); returns (x, P_x, msg)."""
    k = V.shape[1]
    T = D[:, None] * V  # x = x0 + T y
    Tp = np.linalg.pinv(T)
    y = np.zeros(k)
    Py = Tp @ P0 @ Tp.T
    Qy = Tp @ Q @ Tp.T
    wm, wc, c = _merwe_weights(k, alpha, beta, kappa)
    msg = f"{repeats} update(s) on the same measurement"
    for it in range(repeats):
        Py = Py + Qy
        scale = 1.0
        for _ in range(6):
            try:
                S = np.linalg.cholesky(c * scale**2 * Py)
            except np.linalg.LinAlgError:
                S = np.linalg.cholesky(c * scale**2 * Py + 1e-18 * np.eye(k))
            Y = np.vstack([y, y + S.T, y - S.T])
            X = x0 + Y @ T.T
            res = prob.evaluate(X)
            if res.valid.all():
                break
            scale *= 0.5  # shrink the sigma-point spread until the pupil stays lit
        else:
            raise PupilError(f"ukf: sigma points leave the lit pupil at update {it + 1}: {res.reason(int(np.argmin(res.valid)))}")
        if scale != 1.0:
            msg += f"; sigma spread shrunk x{scale:g} at update {it + 1}"
        Zs = res.z
        zhat = wm @ Zs
        dZ = Zs - zhat
        dY = Y - y
        Pzz = (dZ * wc[:, None]).T @ dZ + R
        Pyz = (dY * wc[:, None]).T @ dZ
        K = np.linalg.solve(Pzz, Pyz.T).T
        y = y + K @ (prob.z - zhat)
        Py = Py - K @ Pzz @ K.T
        Py = 0.5 * (Py + Py.T)
    x = x0 + T @ y
    return x, Py, msg


def estimate_pose_model(model: ForwardModel, z_measured, x0=None, method: str = "lm", *, prior_cov=None,
                        ukf_repeats: int = 12, ukf_alpha: float = 0.5, ukf_beta: float = 2.0,
                        ukf_kappa: float = 0.0, ukf_process_cov=None, jac: str = "central",
                        max_iter: int = 50, tol: float = 1e-8, on_rank_loss: str = "warn") -> PoseEstimate:
    """:func:`estimate_pose` on a prepared ForwardModel (reuse it across many estimates)."""
    bench = model.bench
    m = len(model.modes)
    if method not in METHODS:
        raise ConfigError(f"method: {method!r} is not one of {', '.join(METHODS)}")
    if jac not in ("central", "forward"):
        raise ConfigError(f"jac: {jac!r} is not 'central' or 'forward'")
    if on_rank_loss not in ("warn", "raise"):
        raise ConfigError(f"on_rank_loss: {on_rank_loss!r} is not 'warn' or 'raise'")
    z = _check_vector("z_measured", z_measured, m) if np.ndim(z_measured) == 1 else None
    if z is None:
        raise ConfigError(f"z_measured: expected shape ({m},) (Noll modes {int(model.modes[0])}..{int(model.modes[-1])}, "
                          f"um), got {np.shape(z_measured)}")
    x0 = np.zeros(6) if x0 is None else _check_vector("x0", x0, 6)
    check_pose_range(bench, x0)
    if method == "ukf":
        if prior_cov is None:
            from .initial_poses import prior_covariance
            prior_cov = prior_covariance()
        P0 = _check_cov("prior_cov", prior_cov, 6)
        Q = np.zeros((6, 6)) if ukf_process_cov is None else np.asarray(ukf_process_cov, dtype=float)
        if Q.shape != (6, 6) or not np.all(np.isfinite(Q)):
            raise ConfigError("ukf_process_cov: expected a finite (6, 6) matrix")
        if int(ukf_repeats) != ukf_repeats or ukf_repeats < 1:
            raise ConfigError(f"ukf_repeats: expected an integer >= 1, got {ukf_repeats!r}")
        if not ukf_alpha > 0:
            raise ConfigError(f"ukf_alpha: must be > 0, got {ukf_alpha!r}")

    prob = _Whitened(model, z, jac)
    _, ok, res0 = prob.base(x0)
    if not ok:
        raise PupilError(f"initial pose {np.round(x0, 4).tolist()}: {res0.reason(0)}; "
                         "start closer to the lens's true pose (the pupil must stay lit)")
    J0 = prob.jacobian(x0)
    V, null, D = _rank_split(J0, bench)
    unobs = _null_names(null)
    if unobs:
        msg = (f"pose direction(s) {', '.join(unobs)} unobservable from the measurement (Jacobian rank "
               f"{V.shape[1]} < 6, e.g. a rotationally symmetric lens)")
        if on_rank_loss == "raise":
            raise RankError(msg + "; break the lens's rotational symmetry (freeform terms)")
        warnings.warn(msg + f"; estimating the other {V.shape[1]} DOF, the rest stay at x0", UnobservableWarning,
                      stacklevel=3)

    if method == "lm":
        x, sol, Jy = _lm(prob, x0, V, D, max_iter, tol)
        try:
            cov_y = np.linalg.inv(Jy.T @ Jy)
        except np.linalg.LinAlgError:
            cov_y = np.linalg.pinv(Jy.T @ Jy)
        cov = _expand_cov(cov_y, V, null, D)
        r = sol.fun
        converged = bool(sol.success and sol.status > 0 and np.all(np.isfinite(r)))
        message = sol.message
        iterations = int(sol.njev)
    else:
        R = model.noise_cov
        x, Py, message = _ukf(prob, x0, P0, Q, R, int(ukf_repeats), ukf_alpha, ukf_beta, ukf_kappa, V, D)
        T = D[:, None] * V
        cov = _mark_unobservable(T @ Py @ T.T, null)
        r = prob.residual(x)
        converged = bool(np.all(np.isfinite(r)))
        if not converged:
            message += "; the pupil is not lit at the estimate"
        iterations = int(ukf_repeats)
    out = _in_range(bench, x)
    if out:
        converged = False
        message = f"estimate left the bench's pose range: {out}"
    chi2 = float(r @ r) if np.all(np.isfinite(r)) else float("inf")
    return PoseEstimate(pose=x, cov=cov, chi2=chi2, dof=m - V.shape[1], iterations=iterations, converged=converged,
                        n_evals=prob.n_evals, message=message, method=method, unobservable=unobs, x0=x0)


def estimate_pose(bench: Bench, lens: Lens, z_measured: ArrayLike, x0: ArrayLike | None = None, method: str = "lm",
                  **options: Any) -> PoseEstimate:
    """Estimate the lens pose (mm, rad; relative to nominal) from measured Zernikes (um).

    method: "lm" (default; least squares on noise-whitened residuals, covariance
    (J^T R^-1 J)^-1) or "ukf" (the paper's baseline; see the module docstring for
    why ``ukf_repeats`` > 1 gives an overconfident covariance). x0: initial pose
    (default nominal). Options: prior_cov (ukf prior, default from
    ``initial_poses``), ukf_repeats (12, the paper's), ukf_alpha/beta/kappa
    (0.5, 2, 0), ukf_process_cov (zero: static state), jac ("central" or
    "forward"; forward halves the cost per iteration), max_iter (50 function evaluations), tol (1e-8),
    on_rank_loss ("warn" or "raise").
    Raises ConfigError (bad inputs), PoseRangeError (x0 outside the bench's range),
    PupilError (pupil not lit at x0), RankError (rank loss with on_rank_loss="raise").
    For many estimates on one lens build the ForwardModel once and call
    :func:`estimate_pose_model`.
    """
    return estimate_pose_model(ForwardModel(bench, lens), z_measured, x0, method, **options)
