"""Lens pose estimation from Shack-Hartmann measurements: invert z = h(x).

One estimator interface, ``estimate_pose`` / ``estimate_pose_model``, with the
estimators in the registry ``ESTIMATORS`` (name -> function; add one there):

``lm`` (default): nonlinear least squares on the noise-whitened residual
r(x) = L^-1 (h(x) - z), R = L L^T the Zernike noise covariance, by ONE solver,
``estimate_poses_batch``: a trust-region Levenberg-Marquardt batched over P poses (what
the as-built study runs); one measurement is its P = 1 call. Each pose has its own
trust region in the bench's pose scales (u = x / D: 1 mm, 1 deg), radius 1 at the
start (widened to the first Gauss-Newton step if that step stays in the bench's pose
range), then changed by the step policy every lensforge solver shares
(``trust_region``: doubled after a well predicted step on the boundary, quartered after
a poor or rejected one); the step is the exact trust-region (LM) step, found in the
eigenbasis of J^T J (``trust_region.eigen_step``). The trust region keeps a weakly
observable DOF (the paper Zernike lens's rz, 1-sigma ~ 11 deg at nominal) from jumping
out of the bench's range on the first Gauss-Newton step; Marquardt's damping (lambda diag(J^T J)) does not, since it damps
a weak direction least (on 30 noisy paper-Zernike estimates it converged on 7, the
trust region on 26; ``benchmarks/bench_pose_convergence.py``). The Jacobian is
``ForwardModel.jacobians`` (exact: the rays' derivatives carried through the
trace), warm-started from the aimed rays. On a cross-talk bench (``sensor.crosstalk``) the fit
iterates on the own-centroid model with the cross-talk's correction frozen and refreshed
(``_frozen_crosstalk_fit``), then finishes with Gauss-Newton steps on the exact Jacobian; with
``frozen_crosstalk=False`` the trust region runs on the whole model, its iterations on the own
centroid's Jacobians (exact=False) and a pose that stops on them goes on with exact ones. The
reported covariance is the Gauss-Newton one, (J^T R^-1 J)^-1 at the solution (the exact J): for the
noise levels of the bench the problem is locally linear, so this is the Cramer-Rao
bound evaluated at the estimate, and chi2 = r^T r follows a chi-square law with
m - 6 degrees of freedom.

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

Observability (``optics.sensitivity.observability``, DESIGN.md's statistical rule,
judged on the whitened, scaled Jacobian at the initial pose). A numerically null
direction (e.g. rz of a rotationally symmetric lens) cannot be estimated:
``on_rank_loss="warn"`` (default) warns with :class:`UnobservableWarning`,
estimates only the other directions (the null ones stay at x0), names the DOF they
move in ``PoseEstimate.unobservable`` and puts ``inf`` on those DOF's covariance
diagonal (zero off-diagonal); ``on_rank_loss="raise"`` raises
:class:`~lensforge.errors.RankError`. A DOF that is estimated but whose predicted
1-sigma exceeds the bench's pose scale (e.g. rz of the paper's Zernike lens) is
merely noisy: it is solved, flagged in ``PoseEstimate.observable`` and warned about
(:class:`WeakObservabilityWarning`), never refused.

Units: pose (tx, ty, tz) mm, (rx, ry, rz) rad (rotation vector, DESIGN.md);
Zernike coefficients um.
"""

from __future__ import annotations

from numpy.typing import ArrayLike
from typing import Any

import warnings
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError, PoseRangeError, PupilError, RankError
from ..optics.bench import Bench
from ..optics.lens import Lens
from ..optics.pose import DOF_NAMES
from ..optics.sensitivity import JACOBIAN_EVALS, observability
from ..optics.shack_hartmann import ForwardModel, check_pose_range
from .initial_poses import prior_covariance
from .trust_region import SHRINK_BELOW, eigen_step, gain_ratio, next_radius, predicted_decrease

__all__ = ["PoseEstimate", "BatchPoseEstimate", "UnobservableWarning", "WeakObservabilityWarning", "estimate_pose",
           "estimate_pose_model", "estimate_poses_batch", "normalised_error_squared", "ESTIMATORS", "METHODS",
           "STOP_REASONS"]


def normalised_error_squared(error: np.ndarray, cov: np.ndarray) -> float:
    """NEES e^T cov^-1 e of a pose error (6,) over the DOF the covariance (6, 6) observes (finite variance);
    ~ chi-square with that many DOF for an honest covariance."""
    obs = np.isfinite(np.diag(cov))
    return float(error[obs] @ np.linalg.solve(cov[np.ix_(obs, obs)], error[obs]))


class UnobservableWarning(UserWarning):
    """Some pose direction is not observable from the measurement (rank loss)."""


class WeakObservabilityWarning(UnobservableWarning):
    """Some pose DOF is estimated but its predicted 1-sigma exceeds the bench's pose scale."""


@dataclass(frozen=True)
class BatchPoseEstimate:
    """Pose estimates of P measurements.

    poses: (P, 6) mm, rad; cov: (P, 6, 6) Gauss-Newton covariance (J^T R^-1 J)^-1 at
    the estimate (inf on the diagonal of unobservable DOF); chi2: (P,) whitened
    residual sum of squares; converged: (P,) met the tolerance with the pupil lit
    and in the bench's range; iterations: LM iterations run (the longest pose);
    n_evals: poses traced; out_of_range: (P,) stopped outside the bench's pose range;
    observable: (P, 6) DESIGN.md's statistical rule at x0
    (``optics.sensitivity.observability``); status: (P,) why each pose stopped, a key
    of ``STOP_REASONS``; n_iter: (P,) iterations of each pose.
    """

    poses: np.ndarray
    cov: np.ndarray
    chi2: np.ndarray
    converged: np.ndarray
    iterations: int
    n_evals: int
    out_of_range: np.ndarray = None
    observable: np.ndarray = None
    status: np.ndarray = None
    n_iter: np.ndarray = None

    def nees(self, true_poses) -> np.ndarray:
        """(P,) NEES of each estimate against true_poses (P, 6) (``normalised_error_squared``)."""
        errors = self.poses - np.asarray(true_poses, dtype=float)
        return np.array([normalised_error_squared(e, c) for e, c in zip(errors, self.cov)])


# why a pose's iteration stopped (BatchPoseEstimate.status)
STOP_REASONS = {
    "converged": "converged (relative step or cost change below the tolerance)",
    "flat": "converged (no descent left: the trust region shrank to nothing at a flat minimum)",
    "far": "abandoned: the iterate left the bench's pose range by a factor 2",
    "max_iter": "iteration limit reached",
    "unlit": "the pupil is not lit at the initial pose",
}


def _whiten(Li, d):
    """L^-1 d for d (..., m), given Li = L^-1 (m, m)."""
    return d @ Li.T


def _whiten_jac(Li, J):
    """L^-1 J for Jacobians J (P, m, 6)."""
    return _whiten(Li, J.transpose(0, 2, 1)).transpose(0, 2, 1)


@dataclass(frozen=True)
class _Start:
    """What ``estimate_pose_model`` already computed at x0 for one pose (saves a Jacobian)."""

    uv: np.ndarray  # (1, ...) aimed rays
    z: np.ndarray  # (1, m) h(x0)
    Jw: np.ndarray  # (1, m, 6) whitened Jacobian: the exact one, or on a cross-talk bench the iteration one
    basis: np.ndarray  # (6, k) estimated directions in scaled units
    observable: np.ndarray  # (6,)
    null: np.ndarray  # (6,) DOF moved by a numerically null direction


def _gauss_newton_cov(Jw: np.ndarray, basis: np.ndarray, null: np.ndarray, D: np.ndarray):
    """(cb, cov): the inverse normal matrix (k, k) on the estimated directions ``basis`` (6, k) of the whitened,
    scaled Jacobian Jw (m, 6), and the pose covariance (6, 6) in mm and rad (inf on the DOF ``null`` moves)."""
    Jb = Jw @ basis  # d r / d (coordinates along the estimated directions)
    try:
        cb = np.linalg.inv(Jb.T @ Jb)
    except np.linalg.LinAlgError:
        cb = np.linalg.pinv(Jb.T @ Jb)
    return cb, _mark_unobservable((basis @ cb @ basis.T) * np.outer(D, D), null)


def _within(lim, x: np.ndarray) -> np.ndarray:
    """(P,) bool: the poses x (P, 6) inside the pose limits ``lim`` (``Bench.pose_limits``)."""
    return np.all(np.abs(x[:, :3]) <= lim.translation_mm, axis=1) & (np.linalg.norm(x[:, 3:], axis=1) <= lim.rotation_rad)


def _batch_result(bench: Bench, x, cov, cost, status, iterations: int, n_evals: int, observable, n_iter):
    """The BatchPoseEstimate of poses x (P, 6) that stopped with ``status``: converged where stopped, finite and
    in the bench's pose range."""
    in_range = _within(bench.pose_limits, x)
    stopped = np.isin(status, ("converged", "flat", "far")) & np.isfinite(cost)
    return BatchPoseEstimate(poses=x, cov=cov, chi2=np.where(np.isfinite(cost), cost, np.inf),
                             converged=stopped & in_range, iterations=iterations, n_evals=n_evals,
                             out_of_range=stopped & ~in_range, observable=observable, status=status, n_iter=n_iter)


def estimate_poses_batch(model: ForwardModel, z_measured: ArrayLike, x0: ArrayLike, *, max_iter: int = 40,
                         xtol: float = 1e-10, ftol: float = 1e-10,
                         max_step: float | None = None, trust_radius: float = 1.0, frozen_crosstalk: bool = True,
                         _start: _Start | None = None) -> BatchPoseEstimate:
    """Whitened least-squares pose estimates for P measurements at once (trust-region LM, batched).

    The same objective |L^-1 (h(x) - z)|^2 for every pose; each pose has its own trust region
    and stops on its own (relative step < xtol in scaled units, or relative cost change
    < ftol with a step the linear model predicted well). The trust region lives in the
    bench's pose scales u = x / D (1 mm, 1 deg by default), starts at radius
    ``trust_radius`` (1), widened to the first Gauss-Newton step when that step stays
    inside the bench's pose range (a fixed larger start lost 3 (radius 3) to 17 (radius
    100) of 30 noisy paper-Zernike estimates), and grows on good steps up to ``max_step``
    (default unbounded); this is what keeps a weakly observable DOF (the paper Zernike
    lens's rz, 1-sigma ~ 11 deg) from jumping out of the bench's range on the first
    Gauss-Newton step. Directions numerically null at x0 (``observability``,
    bench.rank_rtol) stay at x0 with inf variance.

    Parameters
    ----------
    model : ForwardModel
        Bench and lens.
    z_measured : array_like, shape (P, m)
        Measured Zernikes, um.
    x0 : array_like, shape (P, 6)
        Initial poses, mm and rad.
    max_iter : int
        LM iterations per pose.
    xtol, ftol : float
        Relative step (scaled units) and relative cost-change tolerances.
    max_step : float, optional
        Largest trust radius, scaled units (default unbounded).
    trust_radius : float
        Initial trust radius, scaled units.
    frozen_crosstalk : bool
        On a cross-talk bench (``model.crosstalk``), iterate on the own-centroid model with the cross-talk's
        correction frozen (``_frozen_crosstalk_fit``): the same estimate for a few evaluations of the cross-talk
        model instead of two per iteration. False: the trust region on the whole model throughout.

    Returns
    -------
    BatchPoseEstimate
        ``poses`` (P, 6) mm and rad, ``cov`` (P, 6, 6), ``chi2`` (P,), ``converged`` (P,),
        ``out_of_range`` (P,), ``observable`` (P, 6), ``status`` (P,) and iteration counts.
    """
    Z = np.atleast_2d(np.asarray(z_measured, dtype=float))
    x = np.array(np.atleast_2d(x0), dtype=float)
    kw = dict(max_iter=max_iter, xtol=xtol, ftol=ftol, max_step=max_step, trust_radius=trust_radius)
    if model.crosstalk and frozen_crosstalk:
        return _frozen_crosstalk_fit(model, Z, x, kw, _start)
    return _batch_lm(model, Z, x, _start=_start, **kw)


# the frozen cross-talk correction's rounds at most, and its change (whitened: noise sigma, any mode) that ends them
FROZEN_ROUNDS = 6
FROZEN_TOL = 0.1
# then Gauss-Newton steps on the exact Jacobian at most, until a step is below this many sigma in every DOF
POLISH_STEPS = 6
POLISH_TOL = 1e-4
# passes of the windows re-placed at the estimates (a spot on a half pixel may flip back and forth)
WINDOW_PASSES = 4


def _frozen_crosstalk_fit(model: ForwardModel, Z: np.ndarray, x0: np.ndarray, kw: dict,
                          start: _Start | None) -> BatchPoseEstimate:
    """``estimate_poses_batch`` on a cross-talk bench, by deferred correction. The cross-talk model h (seconds a
    pose for 'cells') differs from the own-centroid model h_own (milliseconds) by a correction
    c(x) = h(x) - h_own(x) that moves slowly with the pose (its derivative ~13 % of h's on the paper polynomial
    lens). Each round fits h_own(x) + c to z with c frozen at the last round's poses (``_batch_lm`` on
    ``model.own_centroid_model`` and z - c), then evaluates h once at the new poses; the rounds end when c moved
    by less than ``FROZEN_TOL`` sigma. At that fixed point J_own^T R^-1 (z - h(x)) = 0; Gauss-Newton steps on h's
    exact Jacobian J there (a chord method: the steps are a few percent of sigma) reach the whole model's
    minimum, J^T R^-1 (z - h(x)) = 0, and J gives the covariance (J^T R^-1 J)^-1. About 4 evaluations of h and
    one exact Jacobian a pose, against two evaluations of h per iteration.

    The centroid windows are frozen at the first fit's poses (``ForwardModel.evaluate``'s windows): whole-pixel
    placement makes h jump where a spot crosses a half pixel, by up to ~1 sigma for one lenslet, while after the
    first fit every spot is within microradians of its final place, far below a pixel. At the estimates the
    windows are placed again by the tracking rule; where one moved, the steps go on with the new ones (at most
    ``WINDOW_PASSES`` times): noise-free data then give their pose exactly. A pose whose rounds do
    not settle, whose own-model fit fails, or whose polishing step is rejected is fitted on h throughout
    (``_batch_lm``) from where the rounds left it. ``observable``: the statistical rule on the own-centroid model
    at the last round's start."""
    own = model.own_centroid_model
    L = model.whitener
    P, m = Z.shape
    x = x0.copy()
    full = model.evaluate(x, check_range=False)
    zf, uvf, lit0 = full.z.copy(), full.uv.copy(), full.valid.copy()
    win = None  # the centroid windows, frozen from the first fit's poses on
    n_evals, n_iter, iterations = P, np.zeros(P, int), 0
    c = np.full((P, m), np.nan)
    status = np.where(lit0, "max_iter", "unlit").astype(object)
    observable = np.ones((P, 6), bool)
    settled = np.zeros(P, bool)
    todo = lit0.copy()
    for rnd in range(FROZEN_ROUNDS + 1):
        idx = np.flatnonzero(todo)
        if idx.size == 0:
            break
        base = own.evaluate(x[idx], check_range=False)
        n_evals += idx.size
        c_new = zf[idx] - base.z
        if rnd:  # c at the poses fitted with the previous c
            moved = np.abs(_whiten(L, c_new - c[idx])).max(axis=1)
            settled[idx[moved < FROZEN_TOL]] = True
        todo[idx[settled[idx] | ~base.valid]] = False
        if rnd == FROZEN_ROUNDS:
            break
        keep = todo[idx]
        c[idx[keep]] = c_new[keep]
        idx = idx[keep]
        if idx.size == 0:
            break
        inner = _batch_lm(own, Z[idx] - c[idx], x[idx], **kw)
        n_evals += inner.n_evals
        n_iter[idx] += inner.n_iter
        iterations += inner.iterations
        status[idx], observable[idx] = inner.status, inner.observable
        ok = np.isin(inner.status, ("converged", "flat")) & np.isfinite(inner.chi2)
        todo[idx[~ok]] = False
        idx = idx[ok]
        x[idx] = inner.poses[ok]
        full = model.evaluate(x[idx], check_range=False, windows=None if win is None else win[idx])
        n_evals += idx.size
        zf[idx], uvf[idx] = full.z, full.uv
        if win is None and full.windows is not None:
            win = np.zeros((P,) + full.windows.shape[1:])
            win[idx] = full.windows
        todo[idx[~full.valid]] = False
    cov = np.full((P, 6, 6), np.nan)
    cost = np.full(P, np.inf)
    polished = np.zeros(P, bool)
    s = np.flatnonzero(settled)
    if s.size:
        n_evals += _polish(model, Z, x, s, uvf[s], None if win is None else win[s], start, cov, cost, polished)
    rest = np.flatnonzero(lit0 & ~polished)
    if rest.size:  # from where the rounds left it (x0 where the own model's fit failed)
        left_x0 = np.any(x[rest] != x0[rest])
        b = _batch_lm(model, Z[rest], x[rest], _start=None if left_x0 else start, **kw)
        n_evals += b.n_evals
        iterations += b.iterations
        x[rest], cov[rest], cost[rest], status[rest] = b.poses, b.cov, b.chi2, b.status
        observable[rest], n_iter[rest] = b.observable, n_iter[rest] + b.n_iter
    return _batch_result(model.bench, x, cov, cost, status, iterations, n_evals, observable, n_iter)


def _polish(model: ForwardModel, Z: np.ndarray, x: np.ndarray, s: np.ndarray, uv: np.ndarray, ws: np.ndarray | None,
            start: _Start | None, cov: np.ndarray, cost: np.ndarray, polished: np.ndarray) -> int:
    """``_frozen_crosstalk_fit``'s finish for the settled poses s: Gauss-Newton steps on the whole model's exact
    Jacobian at the rounds' poses x[s] (a chord method: the steps are a few percent of sigma), which also gives
    the covariance, with the windows ws frozen, then again with the windows the tracking rule places at the
    estimates where they moved (``WINDOW_PASSES``). A spot within the window's truncation bias of a half-pixel
    boundary has two stable windows ~70 urad apart, and the rule may pick the other one at the next pass's
    estimate (seen on a physical session: one pose's minima over three passes at chi2 12.0, 9.4 and 10.5), so each
    pose keeps the pass whose estimate fits its data best with the windows the rule places there: the objective
    is chi2(x, windows(x)), and a pass's minimum with windows the rule does not give at it is not a value of it.
    (Comparing the passes' frozen-window minima instead picked windows of no pose, and a pose 3 CRLB off the
    truth: on the polynomial lens's 0.9 mm pupil, chi2 8.0 with them, 49.9 with its own windows, 12.7 at the
    truth; NEES median 10.1 over 12 draws.) Fills x, cov, cost and polished (a step below ``POLISH_TOL`` sigma,
    or a rejected one below 1e-2 sigma, in some pass) in place; returns the poses traced."""
    L, D = model.whitener, np.asarray(model.bench.pose_scales, dtype=float)
    J, _, res = model.jacobians(x[s], uv0=uv, exact=True, windows=ws)
    n_evals = (JACOBIAN_EVALS + 1) * s.size
    Jw = _whiten_jac(L, J) * D  # d r / d u, u = x / D
    r = _whiten(L, res.z - Z[s])
    cost[s] = np.where(res.valid, np.sum(r * r, axis=1), np.inf)
    gain = np.zeros((s.size, 6, Z.shape[1]))  # u step = gain @ -r on the estimated directions
    for k, p in enumerate(s):
        if start is not None:
            basis, null = start.basis, start.null
        else:
            ob = observability(Jw[k] / D, D, model.bench.rank_rtol)
            basis, null = ob.basis, ~np.isfinite(ob.std)
        cb, cov[p] = _gauss_newton_cov(Jw[k], basis, null, D)
        gain[k] = basis @ cb @ (Jw[k] @ basis).T
    sig_u = np.sqrt(np.diagonal(cov[s], axis1=1, axis2=2)) / D
    sig_u = np.where(np.isfinite(sig_u), sig_u, 1.0)
    uv, live = res.uv, res.valid.copy()
    ws = None if ws is None else ws.copy()
    best_x, best_cost = x[s].copy(), np.full(s.size, np.inf)

    def objective(new, k):  # (whitened residuals, chi2; inf where unlit) of an evaluation at the poses s[k]
        rn = _whiten(L, new.z - Z[s[k]])
        return rn, np.where(new.valid, np.sum(rn * rn, axis=1), np.inf)

    in_play = np.ones(s.size, bool)  # poses whose windows may still move
    seen = [] if ws is None else [ws.copy()]  # the windows of every pass so far (a pose back at one: a cycle)
    for pas in range(WINDOW_PASSES + 1):
        for _ in range(POLISH_STEPS):
            k = np.flatnonzero(live)
            if k.size == 0:
                break
            du = np.einsum("kij,kj->ki", gain[k], -r[k])
            xn = x[s[k]] + du * D
            new = model.evaluate(xn, uv0=uv[k], check_range=False, windows=None if ws is None else ws[k])
            n_evals += k.size
            rn, cn = objective(new, k)
            acc = cn <= cost[s[k]] * (1.0 + 1e-12)
            a = k[acc]
            x[s[a]], cost[s[a]], r[a], uv[a] = xn[acc], cn[acc], rn[acc], new.uv[acc]
            size = np.max(np.abs(du) / sig_u[k], axis=1)
            small = size < POLISH_TOL
            # a rejected step below 1e-2 sigma: the point stands (h is flat there at its rounding; the trust
            # region would stop there too)
            polished[s[k[(acc & small) | (~acc & (size < 1e-2))]]] = True
            live[k[~acc | small]] = False
        live[:] = False
        # the pass's candidates: its minima (a later pass's point after its steps too: its windows' pass began
        # at a polished minimum, and the objective below decides)
        k = np.flatnonzero(in_play & (polished[s] | (pas > 0)))
        if ws is None or k.size == 0:
            better = polished[s] & (cost[s] < best_cost)
            best_x[better], best_cost[better] = x[s[better]], cost[s[better]]
            break
        # the windows the tracking rule places at the estimates (the data's own, noise-free), and the objective
        # there; where they differ from the frozen ones, on with those (chord steps on the same Jacobian)
        new = model.evaluate(x[s[k]], uv0=uv[k], check_range=False)
        n_evals += k.size
        rn, cn = objective(new, k)
        better = cn < best_cost[k]
        best_x[k[better]], best_cost[k[better]] = x[s[k[better]]], cn[better]
        moved = np.any(new.windows != ws[k], axis=(1, 2)) & new.valid
        # windows a previous pass had: the passes cycle between window sets (no set is its own minimum's; the
        # objective's minimum lies on their boundary), and the best of the points seen stands
        moved &= ~np.any([np.all(new.windows == w[k], axis=(1, 2)) for w in seen], axis=0)
        in_play[k[~moved]] = False
        if not moved.any() or pas == WINDOW_PASSES:
            break
        k = k[moved]
        ws[k], uv[k] = new.windows[moved], new.uv[moved]
        seen.append(ws.copy())
        r[k], cost[s[k]] = rn[moved], cn[moved]
        polished[s[k]], live[k] = False, True
    got = np.isfinite(best_cost)
    x[s[got]], cost[s[got]], polished[s[got]] = best_x[got], best_cost[got], True
    return n_evals


def _batch_lm(model: ForwardModel, Z: np.ndarray, x: np.ndarray, *, max_iter: int, xtol: float, ftol: float,
              max_step: float | None, trust_radius: float, _start: _Start | None = None) -> BatchPoseEstimate:
    """``estimate_poses_batch``'s trust-region LM on ``model`` throughout (Z (P, m) and x (P, 6) its own copies)."""
    P = x.shape[0]
    bench = model.bench
    L = model.whitener
    D = np.asarray(bench.pose_scales, dtype=float)
    eye = np.eye(6)
    n_evals = 0

    J = np.zeros((P, Z.shape[1], 6))  # whitened, scaled: d r / d u
    if _start is None:
        res = model.evaluate(x, check_range=False)
        n_evals += P
        uv, zc, valid = res.uv.copy(), res.z.copy(), res.valid.copy()
        need_J = valid.copy()
    else:
        uv, zc, valid = _start.uv.copy(), _start.z.copy(), np.ones(1, bool)
        J[0] = _start.Jw[0] * D
        need_J = np.zeros(1, bool)
    r = _whiten(L, zc - Z)
    cost = np.where(valid, np.sum(r * r, axis=1), np.inf)
    delta = np.full(P, float(trust_radius))  # trust radius, scaled units
    cap = np.inf if max_step is None else float(max_step)
    delta = np.minimum(delta, cap)
    active = valid.copy()
    status = np.where(valid, "max_iter", "unlit").astype(object)
    n_iter = np.zeros(P, int)
    proj = np.broadcast_to(eye, (P, 6, 6)).copy()  # projector on the estimated directions
    bases = [eye] * P  # (6, k) estimated directions per pose
    null = np.zeros((P, 6), bool)  # DOF moved by a numerically null direction
    observable = np.ones((P, 6), bool)  # the statistical rule
    lim = bench.pose_limits
    first = True
    it = 0
    # on a cross-talk bench the iterations take the own centroid's Jacobians (``ForwardModel.jacobians``,
    # exact=False: ~9x cheaper there); a pose that stops on them goes on from there with exact ones, so the
    # minimum and the covariance are the exact model's
    exact = np.full(P, not model.crosstalk)  # as the start's Jw (``_Start``)

    def linearise(idx):
        nonlocal n_evals
        for e in (True, False):
            sel = idx[exact[idx] == e]
            if sel.size:
                J[sel] = _whiten_jac(L, model.jacobians(x[sel], uv0=uv[sel], exact=e)[0]) * D
                n_evals += JACOBIAN_EVALS * sel.size
        need_J[idx] = False

    for it in range(1, max_iter + 1):
        idx = np.flatnonzero(active & need_J)
        if idx.size:
            linearise(idx)
        if first:
            # observability at x0 (the rule of optics.sensitivity): numerically null
            # directions are pinned at x0; weak ones are estimated and flagged
            for p in np.flatnonzero(valid):
                if _start is None:
                    ob = observability(J[p] / D, D, bench.rank_rtol)
                    basis, observable[p], null[p] = ob.basis, ob.observable, ~np.isfinite(ob.std)
                else:
                    basis, observable[p], null[p] = _start.basis, _start.observable, _start.null
                bases[p] = basis
                proj[p] = eye if basis.shape[1] == 6 else basis @ basis.T  # exact when full rank
            first = False
        a = np.flatnonzero(active)
        if a.size == 0:
            break
        n_iter[a] += 1
        Pa = proj[a]
        Ja = J[a] @ Pa  # estimated directions only
        A = np.einsum("pmi,pmj->pij", Ja, Ja)
        g = np.einsum("pmi,pm->pi", Ja, r[a])
        A = A + (eye - Pa)  # pinned directions: identity, zero gradient
        if it == 1:
            # a first Gauss-Newton step that stays inside the bench's pose range widens the
            # initial region to its length: a well observed lens converges as fast as with
            # undamped GN, a weak direction that would jump out keeps the small region
            gn = eigen_step(A, g, np.full(a.size, np.inf))[0]
            xg = x[a] + gn * D
            delta[a] = np.where(_within(lim, xg), np.minimum(np.maximum(delta[a], np.linalg.norm(gn, axis=1)), cap), delta[a])
        du, _ = eigen_step(A, g, delta[a])
        xn = x[a] + du * D
        rn_res = model.evaluate(xn, uv0=uv[a], check_range=False)
        n_evals += a.size
        rn = _whiten(L, rn_res.z - Z[a])
        cn = np.where(rn_res.valid, np.sum(rn * rn, axis=1), np.inf)
        # predicted decrease of the linear model, |r|^2 - |r + J du|^2
        pred = predicted_decrease(g, du, np.einsum("pij,pj->pi", A, du))
        actual = cost[a] - cn
        rho = gain_ratio(actual, pred)
        acc = cn <= cost[a]
        step = np.linalg.norm(du, axis=1)
        u_norm = np.linalg.norm(x[a] / D, axis=1)
        small_step = step <= xtol * (xtol + u_norm)
        small_cost = (actual <= ftol * cost[a]) & (rho > SHRINK_BELOW)
        tiny = small_step | (pred <= ftol * np.maximum(cost[a], 1e-300))
        delta[a] = next_radius(delta[a], step, rho, acc, cap)  # the shared rule (trust_region)
        ai = a[acc]
        x[ai], r[ai], cost[ai], zc[ai] = xn[acc], rn[acc], cn[acc], rn_res.z[acc]
        uv[ai] = rn_res.uv[acc]
        need_J[ai] = True
        # a rejected step leaves the point, hence the Jacobian, unchanged: reused exactly
        done = ai[small_step[acc] | small_cost[acc]]
        stuck = a[~acc & (tiny | (delta[a] <= 1e-12 * (1.0 + u_norm)))]
        relin = np.concatenate([done, stuck])
        relin = relin[~exact[relin]]  # stopped on iteration Jacobians: on with exact ones
        done, stuck = done[exact[done]], stuck[exact[stuck]]  # before the switch: the relinearised go on
        exact[relin], need_J[relin] = True, True
        delta[relin] = np.minimum(np.maximum(delta[relin], trust_radius), cap)  # a new linearisation's region
        status[done] = "converged"
        active[done] = False
        status[stuck] = "flat"  # no descent direction left: a (possibly flat) minimum
        active[stuck] = False
        # an estimate far outside the bench's pose range is abandoned (reported out of range)
        far = ai[(np.abs(x[ai, :3]) > 2 * lim.translation_mm).any(axis=1)
                 | (np.linalg.norm(x[ai, 3:], axis=1) > 2 * lim.rotation_rad)]
        status[far] = "far"
        active[far] = False
    late = np.flatnonzero(valid & ~exact)  # max_iter on iteration Jacobians: the covariance's exact one here
    if late.size:
        exact[late] = True
        linearise(late)
    # covariance from the Jacobian at the last linearisation point, on the estimated directions
    cov = np.full((P, 6, 6), np.nan)
    for p in np.flatnonzero(valid):
        cov[p] = _gauss_newton_cov(J[p], bases[p], null[p], D)[1]
    return _batch_result(bench, x, cov, cost, status, it, n_evals, observable, n_iter)


@dataclass(frozen=True, eq=False)
class PoseEstimate:
    """Result of one pose estimate.

    pose: (6,) estimate (mm, rad), relative to the nominal placement;
    cov: (6, 6) reported covariance (mm^2, mm rad, rad^2); inf on the diagonal of
    unobservable DOF; chi2: whitened residual sum of squares r^T R^-1 r at the
    estimate; dof: m - (number of estimated DOF); iterations: trust-region
    iterations (lm) or filter updates (ukf); converged: the solver met its
    tolerances and the estimate is measurable and in range; n_evals: poses
    traced by the forward model (cost measure: ~0.3 ms each on one core);
    message: solver message or why it failed; method: "lm" or "ukf";
    unobservable: names of the DOF a numerically null direction moves (not
    estimated, left at x0); x0: the initial pose; observable: (6,) DESIGN.md's
    statistical rule (False also where the predicted 1-sigma exceeds the pose scale).
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
    observable: np.ndarray = field(default_factory=lambda: np.ones(6, bool))

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
        return normalised_error_squared(self.pose - np.asarray(true_pose, dtype=float), self.cov)

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
            "observable": {n: bool(o) for n, o in zip(DOF_NAMES, self.observable)},
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


# --- estimators (the registry) -----------------------------------------------------------


@dataclass(frozen=True)
class _Problem:
    """One measurement and what every estimator needs at the initial pose."""

    model: ForwardModel
    z: np.ndarray
    x0: np.ndarray
    uv0: np.ndarray  # aimed rays at x0 (warm start)
    z0: np.ndarray  # h(x0)
    Jw0: np.ndarray  # whitened Jacobian at x0 (m, 6); the iteration one on a cross-talk bench
    basis: np.ndarray  # (6, k) estimated directions, scaled units u = x / D
    null: np.ndarray  # (6,) bool: DOF moved by a numerically null direction
    D: np.ndarray  # bench pose scales
    observable: np.ndarray  # (6,) bool: DESIGN.md's statistical rule at x0


def _mark_unobservable(cov: np.ndarray, null: np.ndarray) -> np.ndarray:
    """inf variance (zero covariances) on the DOF a null direction moves."""
    cov = cov.copy()
    cov[null, :] = 0.0
    cov[:, null] = 0.0
    cov[null, null] = np.inf
    return cov


def _lm(prob: _Problem, *, max_iter: int = 50, tol: float = 1e-8, **_):
    """Least squares on the whitened residual for one measurement: ``estimate_poses_batch``
    with P = 1, started from what ``estimate_pose_model`` computed at x0 (rays, h(x0),
    Jacobian, the estimated directions)."""
    start = _Start(uv=prob.uv0[None], z=prob.z0[None], Jw=prob.Jw0[None], basis=prob.basis,
                   observable=prob.observable, null=prob.null)
    b = estimate_poses_batch(prob.model, prob.z[None], prob.x0[None], max_iter=max_iter, xtol=tol, ftol=tol,
                             _start=start)
    status = str(b.status[0])
    ok = status in ("converged", "flat") and bool(np.isfinite(b.chi2[0]))
    return b.poses[0], b.cov[0], ok, STOP_REASONS[status], int(b.n_iter[0]), b.n_evals


def _merwe_weights(n: int, alpha: float, beta: float, kappa: float):
    lam = alpha**2 * (n + kappa) - n
    wm = np.full(2 * n + 1, 0.5 / (n + lam))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = lam / (n + lam) + (1 - alpha**2 + beta)
    return wm, wc, n + lam


def _ukf(prob: _Problem, *, prior_cov=None, ukf_repeats: int = 12, ukf_alpha: float = 0.5, ukf_beta: float = 2.0,
         ukf_kappa: float = 0.0, ukf_process_cov=None, **_):
    """Static-state UKF in the estimated subspace y (x = x0 + D V y)."""
    P0 = _check_cov("prior_cov", prior_covariance() if prior_cov is None else prior_cov, 6)
    Q = np.zeros((6, 6)) if ukf_process_cov is None else np.asarray(ukf_process_cov, dtype=float)
    if Q.shape != (6, 6) or not np.all(np.isfinite(Q)):
        raise ConfigError("ukf_process_cov: expected a finite (6, 6) matrix")
    if int(ukf_repeats) != ukf_repeats or ukf_repeats < 1:
        raise ConfigError(f"ukf_repeats: expected an integer >= 1, got {ukf_repeats!r}")
    if not ukf_alpha > 0:
        raise ConfigError(f"ukf_alpha: must be > 0, got {ukf_alpha!r}")
    repeats = int(ukf_repeats)
    model, x0, V, D = prob.model, prob.x0, prob.basis, prob.D
    k = V.shape[1]
    T = D[:, None] * V  # x = x0 + T y
    Tp = np.linalg.pinv(T)
    y = np.zeros(k)
    Py = Tp @ P0 @ Tp.T
    Qy = Tp @ Q @ Tp.T
    wm, wc, c = _merwe_weights(k, ukf_alpha, ukf_beta, ukf_kappa)
    R = model.noise_cov
    msg = f"{repeats} update(s) on the same measurement"
    n_evals = 0
    uv0 = np.broadcast_to(prob.uv0, (2 * k + 1,) + prob.uv0.shape)
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
            res = model.evaluate(X, uv0=uv0, check_range=False)
            n_evals += len(X)
            if res.valid.all():
                break
            scale *= 0.5  # shrink the sigma-point spread until the pupil stays lit
        else:
            raise PupilError(f"ukf: sigma points leave the lit pupil at update {it + 1}: "
                             f"{res.reason(int(np.argmin(res.valid)))}")
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
    lit = bool(model.evaluate(x[None], uv0=prob.uv0[None], check_range=False).valid[0])
    n_evals += 1
    if not lit:
        msg += "; the pupil is not lit at the estimate"
    return x, _mark_unobservable(T @ Py @ T.T, prob.null), lit, msg, repeats, n_evals


ESTIMATORS = {"lm": _lm, "ukf": _ukf}  # name -> estimator(problem, **options) -> (x, cov, ok, msg, iterations, n_evals)
METHODS = tuple(ESTIMATORS)


def _in_range(bench: Bench, x: np.ndarray) -> str:
    try:
        check_pose_range(bench, x)
    except PoseRangeError as e:
        return str(e)
    return ""


def estimate_pose_model(model: ForwardModel, z_measured, x0=None, method: str = "lm", *, on_rank_loss: str = "warn",
                        **options) -> PoseEstimate:
    """:func:`estimate_pose` on a prepared ForwardModel (reuse it across many estimates)."""
    bench = model.bench
    m = len(model.modes)
    if method not in ESTIMATORS:
        raise ConfigError(f"method: {method!r} is not one of {', '.join(ESTIMATORS)}")
    if on_rank_loss not in ("warn", "raise"):
        raise ConfigError(f"on_rank_loss: {on_rank_loss!r} is not 'warn' or 'raise'")
    z = _check_vector("z_measured", z_measured, m) if np.ndim(z_measured) == 1 else None
    if z is None:
        raise ConfigError(f"z_measured: expected shape ({m},) (Noll modes {int(model.modes[0])}..{int(model.modes[-1])}, "
                          f"um), got {np.shape(z_measured)}")
    x0 = np.zeros(6) if x0 is None else _check_vector("x0", x0, 6)
    check_pose_range(bench, x0)

    base = model.evaluate(x0[None], check_range=False)
    if not base.valid[0]:
        raise PupilError(f"initial pose {np.round(x0, 4).tolist()}: {base.reason(0)}; "
                         "start closer to the lens's true pose (the pupil must stay lit)")
    D = np.asarray(bench.pose_scales, dtype=float)
    # on a cross-talk bench the start's Jacobian (the rank check and the statistical rule at x0, the first step)
    # is the iteration one (~9x cheaper on 'cells'; a few 1e-2 off): the fit's covariance is the exact one's
    J0 = model.jacobians(x0[None], uv0=base.uv, exact=not model.crosstalk)[0][0]
    Jw0 = _whiten(model.whitener, J0.T).T
    ob = observability(Jw0, D, bench.rank_rtol)
    null = ~np.isfinite(ob.std)
    unobs = ob.null_names
    if unobs:
        msg = (f"pose direction(s) {', '.join(unobs)} unobservable from the measurement (Jacobian rank "
               f"{ob.rank} < 6, e.g. a rotationally symmetric lens)")
        if on_rank_loss == "raise":
            raise RankError(msg + "; break the lens's rotational symmetry (freeform terms)")
        warnings.warn(msg + f"; estimating the other {ob.rank} DOF, the rest stay at x0", UnobservableWarning,
                      stacklevel=3)
    weak = tuple(n for n, o, nl in zip(DOF_NAMES, ob.observable, null) if not o and not nl)
    if weak:
        warnings.warn(f"pose DOF {', '.join(weak)}: predicted 1-sigma exceeds the bench's pose scale "
                      "(estimated, but barely measured)", WeakObservabilityWarning, stacklevel=3)
    prob = _Problem(model=model, z=z, x0=x0, uv0=base.uv[0], z0=base.z[0], Jw0=Jw0, basis=ob.basis, null=null, D=D,
                    observable=ob.observable)
    x, cov, converged, message, iterations, n_evals = ESTIMATORS[method](prob, **options)
    n_evals += 1 + JACOBIAN_EVALS
    out = _in_range(bench, x)
    if out:
        converged = False
        message = f"estimate left the bench's pose range: {out}"
    res = model.evaluate(x[None], check_range=False)
    r = model.whitener @ (res.z[0] - z) if res.valid[0] else np.full(m, np.inf)
    chi2 = float(r @ r) if np.all(np.isfinite(r)) else float("inf")
    return PoseEstimate(pose=x, cov=cov, chi2=chi2, dof=m - ob.rank, iterations=iterations, converged=bool(converged),
                        n_evals=n_evals + 1, message=message, method=method, unobservable=unobs, x0=x0,
                        observable=ob.observable)


def estimate_pose(bench: Bench, lens: Lens, z_measured: ArrayLike, x0: ArrayLike | None = None, method: str = "lm",
                  **options: Any) -> PoseEstimate:
    """Estimate the lens pose relative to nominal from measured Zernikes.

    For many estimates on one lens build the ForwardModel once and call
    :func:`estimate_pose_model`; for many measurements at once, :func:`estimate_poses_batch`.

    Parameters
    ----------
    bench : Bench
        The bench.
    lens : Lens
        The lens model.
    z_measured : array_like, shape (m,)
        Measured Zernike coefficients, um (Noll modes of the bench's sensor).
    x0 : array_like, shape (6,), optional
        Initial pose (mm, rad); default nominal.
    method : str
        A name in ``ESTIMATORS``: "lm" (default; least squares on noise-whitened
        residuals, covariance (J^T R^-1 J)^-1) or "ukf" (the paper's baseline; see the
        module docstring for why ``ukf_repeats`` > 1 gives an overconfident covariance).
    **options
        on_rank_loss ("warn" or "raise"); lm: max_iter (50), tol (1e-8, relative step and
        cost change); ukf: prior_cov (default from ``initial_poses``), ukf_repeats (12, the
        paper's), ukf_alpha/beta/kappa (0.5, 2, 0), ukf_process_cov (zero: static state).

    Returns
    -------
    PoseEstimate
        ``pose`` (6,) mm and rad, ``cov`` (6, 6) (inf on the diagonal of unobservable DOF),
        ``chi2``, ``dof``, ``converged``, ``observable`` and the solver's record.

    Raises
    ------
    ConfigError
        Bad inputs.
    PoseRangeError
        x0 outside the bench's range.
    PupilError
        Pupil not lit at x0.
    RankError
        Rank loss with on_rank_loss="raise".
    """
    return estimate_pose_model(ForwardModel(bench, lens), z_measured, x0, method, **options)
