"""The one step policy of lensforge's least-squares solvers: a trust region (Moré, 1978).

Who uses it:

- pose estimation (``pose_estimation.estimate_poses_batch``): P small dense problems
  at once, the step from ``eigen_step``;
- the joint calibration (``joint.joint_calibrate``): block-arrow normal equations whose
  robot-error blocks are eliminated by a Schur complement, the step from
  ``damped_step`` on the caller's damped solve;
- the referenced joint calibration (``measurement.referenced_calibrate``): dense normal
  equations, ``eigen_step`` after the scaling below;
- hand-eye (``handeye``) calls scipy's ``least_squares(method="lm")``, i.e. MINPACK's
  ``lmder``, which is Moré's implementation of this same rule: for 12 unknowns it is as
  fast as a copy here would be, so it is not re-implemented.

The rule. The cost is c = |r|^2 (priors included as residual rows), the model of a
step d its Gauss-Newton quadratic, H = J^T J, g = J^T r:

- the step is the Levenberg-Marquardt step d(lam) = -(H + lam D^2)^-1 g with the
  smallest lam >= 0 whose scaled length |D d| stays inside the radius (lam = 0, the
  Gauss-Newton step, when that fits);
- a step is accepted when the cost does not increase;
- rho = (actual decrease) / (decrease the quadratic predicted);
- the radius is quartered to the step's length after a rejected or poorly predicted
  step (rho < 1/4) and doubled after a well predicted one (rho > 3/4) that reached it.

D is the solver's scaling: the bench's pose scales for pose estimation (1 mm, 1 deg),
Marquardt's sqrt(diag H) for the calibrations (so that |D d| is the step in
conditional 1-sigma units).

Why this and not Marquardt's "lam x 10 on a rejected step, lam / 10 on an accepted
one" (the joint fits' loop before): a weakly observable direction is damped least by
lam D^2, so a fixed lam lets it jump (pose estimation, paper Zernike lens: 7 of 30
noisy estimates converged with Marquardt's damping, 26 of 30 with the radius;
``benchmarks/bench_pose_convergence.py``), and the fixed factor ignores how well the
model predicted the step: after a rejection it takes up to log10(lam ratio) extra traces
to find a step, and after a run of accepted ones lam has fallen to where one bad step
costs several. The radius changes by what rho measured. Every trial point costs a
trace, so the number of trial points is what the rule saves.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

__all__ = ["SHRINK_BELOW", "GROW_ABOVE", "gain_ratio", "next_radius", "eigen_step", "damped_step",
           "predicted_decrease"]

SHRINK_BELOW = 0.25  # rho below this (or a rejected step): radius -> |step| / 4
GROW_ABOVE = 0.75  # rho above this on the boundary: radius x 2
_SHRINK = 0.25
_GROW = 2.0
_ON_BOUNDARY = 0.95  # a step at least this fraction of the radius "reached" it
_RADIUS_RTOL = 0.1  # damped_step: |D d| within 10 % of the radius (MINPACK lmpar's tolerance)


def predicted_decrease(g, d, Hd):
    """Decrease of c = |r|^2 the Gauss-Newton model predicts for step d: -(2 g.d + d.H d).

    g, d, Hd: (..., n) gradient J^T r, step and H d. Returns (...,)."""
    g, d, Hd = np.asarray(g), np.asarray(d), np.asarray(Hd)
    return -(2.0 * np.sum(g * d, axis=-1) + np.sum(d * Hd, axis=-1))


def gain_ratio(actual, predicted):
    """rho = actual / predicted decrease (0 where the model predicted no decrease)."""
    actual, predicted = np.asarray(actual, float), np.asarray(predicted, float)
    return np.divide(actual, predicted, out=np.zeros(np.broadcast(actual, predicted).shape),
                     where=predicted > 0)


def next_radius(radius, step, rho, accepted, cap=np.inf):
    """The radius after a trial step of scaled length ``step`` (module doc's rule), at most cap.

    radius, step, rho, accepted: scalars or arrays of one shape."""
    radius, step = np.asarray(radius, float), np.asarray(step, float)
    rho, accepted = np.asarray(rho, float), np.asarray(accepted, bool)
    shrink = ~accepted | (rho < SHRINK_BELOW)
    grow = accepted & (rho > GROW_ABOVE) & (step >= _ON_BOUNDARY * radius)
    new = np.where(shrink, _SHRINK * step, np.where(grow, _GROW * radius, radius))
    return np.minimum(new, cap)


def eigen_step(A, g, delta, n_newton: int = 30):
    """Batched exact trust-region step: du minimising g.du + du.A du / 2 with |du| <= delta.

    A: (P, n, n) symmetric positive semi-definite (Gauss-Newton J^T J, in scaled units);
    g: (P, n); delta: (P,). The Levenberg-Marquardt step du = -(A + lam I)^-1 g with lam >= 0
    the smallest value that keeps the step inside the region, found by Newton's method on
    1/|du(lam)| - 1/delta (Moré & Sorensen) in A's eigenbasis; lam = 0 (the Gauss-Newton
    step) when that fits. Returns (du (P, n), lam (P,))."""
    w, Q = np.linalg.eigh(A)
    w = np.clip(w, 0.0, None)
    gq = np.einsum("pji,pj->pi", Q, g)
    floor = 1e-15 * np.maximum(w[:, -1:], 1e-300)  # an exactly singular direction: a huge, finite GN step
    lam = np.zeros(len(delta))
    for _ in range(n_newton):
        d = np.maximum(w + lam[:, None], floor)
        norm = np.sqrt(np.sum((gq / d) ** 2, axis=1))
        s3 = np.sum(gq**2 / d**3, axis=1)
        outside = norm > delta * (1 + 1e-6)
        if not outside.any():
            break
        step = np.divide(norm**2 * (norm - delta), s3 * delta, out=np.zeros_like(norm), where=outside & (s3 > 0))
        lam = np.where(outside, lam + step, lam)
    d = np.maximum(w + lam[:, None], floor)
    du = -np.einsum("pij,pj->pi", Q, gq / d)
    # Newton converges from below (lam too small, step slightly long): clip onto the boundary
    n = np.linalg.norm(du, axis=1)
    du *= np.minimum(1.0, delta / np.maximum(n, 1e-300))[:, None]
    return du, lam


def damped_step(solve: Callable[[float], tuple], delta: float, lam: float = 0.0, max_solves: int = 30):
    """The trust-region step of a structured problem, from the caller's damped solve.

    solve(lam) -> (step, scaled_length): the solution of (H + lam D^2) d = -g (any
    structure; the block-arrow Schur solve of the joint fit) and |D d|. Returns
    (step, scaled_length, lam): lam = 0 when the Gauss-Newton step fits in ``delta``, else
    |D d| within 10 % of delta (MINPACK's tolerance; the length falls monotonically in lam)
    or, when ``max_solves`` runs out, the longest step found inside. ``lam`` (> 0) is a start
    for the search, e.g. the previous step's; the search brackets the root by factors of 10
    and then runs a safeguarded secant on log|D d| against log lam, one solve per try."""
    step, length = solve(0.0)
    if not np.isfinite(length) or length <= delta:
        return step, length, 0.0
    # with D^2 ~ diag H, |D d(lam)| ~ |D d(0)| / (1 + lam) on the well-determined directions
    lam = float(lam) if lam > 0 else max(length / delta - 1.0, 1e-6)
    lo = hi = None  # (lam, length): too long / inside
    best = None
    for _ in range(max_solves):
        step, length = solve(lam)
        if abs(length - delta) <= _RADIUS_RTOL * delta:
            return step, length, lam
        if length > delta:
            lo = (lam, length)
        else:
            hi, best = (lam, length), (step, length, lam)
        if hi is None:
            lam *= 10.0
        elif lo is None:
            lam /= 10.0
        else:
            t = (np.log(delta) - np.log(lo[1])) / (np.log(hi[1]) - np.log(lo[1]))
            lam = float(np.exp(np.log(lo[0]) + np.clip(t, 0.05, 0.95) * (np.log(hi[0]) - np.log(lo[0]))))
    if best is None:  # never inside: the last (shortest) step, scaled onto the boundary
        return step * (delta / length), delta, lam
    return best
