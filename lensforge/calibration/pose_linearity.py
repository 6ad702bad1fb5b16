"""Is a pose estimate's covariance a fair account of its uncertainty?

The reported covariance C = (J^T R^-1 J)^-1 describes the likelihood as the quadratic
chi2(x) - chi2(x_hat) = (x - x_hat)^T C^-1 (x - x_hat) over the ellipsoid it spans. Where
the sensor barely tells a translation from a tilt (a small pupil with few modes:
information condition ~1e8), the likelihood's valley is curved within a few sigma in the
pose vector's coordinates. The likelihood ratio then keeps its chi2_6 law but the
ellipsoid does not: on the paper polynomial lens with a 0.5 mm pupil at Zernike order 3,
400 noisy estimates of one pose had chi2(truth) - chi2(estimate) of mean 6.0 (1 % above
chi2_6's 99th percentile) and NEES of mean 19 (21 % above it), where the bench's 0.9 mm
pupil at order 4 gave 6.0 and 6.1 (README, issue 21).

``linearity_check`` evaluates chi2 at x_hat +- k sigma along the covariance's weakest
principal axis (in the bench's pose scales) and compares the rise with k^2. At order 4
(200 draws a pupil, k = 3, 10th-90th percentile) it was 8.5-38 times k^2 on the 0.5 mm
pupil and 1.19-1.35 times on the 0.9 mm one: a ratio outside ``LIMITS`` says the sigmas
are not a confidence statement there. Two model evaluations (and an iteration Jacobian
where a DOF has infinite variance).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..optics.pose import DOF_NAMES
from ..optics.sensitivity import observability

__all__ = ["LinearityCheck", "linearity_check", "LIMITS", "SIGMAS"]

# chi2 rise at k sigma over k^2: outside, the covariance misdescribes the likelihood. On the polynomial lens
# (200 noisy draws a pupil, order 4) a median ratio of 1.16, 1.27, 1.56, 2.47, 6.2 and 18.8 went with a NEES mean
# of 5.7, 5.8, 5.9, 6.6, 9.8 and 20.8 (6 expected) at pupil radii 1.0, 0.9, 0.8, 0.7, 0.6 and 0.5 mm; flagged
# 0, 0, 0, 15, 99 and 100 % of the draws
LIMITS = (1.0 / 3.0, 3.0)
SIGMAS = 3.0  # k: how far along the weakest axis the likelihood is probed


@dataclass(frozen=True)
class LinearityCheck:
    """ratio: chi2 rise at ``sigmas`` along the weakest axis over sigmas^2, the side furthest from 1 (1 for the
    quadratic the covariance assumes; inf where a side leaves the pupil unlit); axis: that axis (6,) as a unit
    pose-scaled direction; sigma: its 1-sigma length (pose-scaled units)."""

    ratio: float
    sides: tuple
    axis: np.ndarray
    sigma: float
    sigmas: float = SIGMAS

    @property
    def reliable(self) -> bool:
        return bool(LIMITS[0] <= self.ratio <= LIMITS[1])

    @property
    def message(self) -> str:
        order = np.argsort(-np.abs(self.axis))
        main = ", ".join(f"{DOF_NAMES[i]} {self.axis[i]:+.2f}" for k, i in enumerate(order[:3])
                         if k == 0 or abs(self.axis[i]) >= 0.2)
        if not np.isfinite(self.ratio):
            how = f"a {self.sigmas:g}-sigma step leaves the pupil unlit"
        elif self.ratio <= 0:
            how = f"chi2 falls {self.sigmas:g} sigma out (the estimate is not the likelihood's minimum along it)"
        else:
            how = f"chi2 changes {self.ratio:.3g} times as much as the covariance predicts {self.sigmas:g} sigma out"
        return (f"the likelihood is not the covariance's quadratic along its weakest direction ({main}): {how}, so "
                "the reported sigmas there are not a confidence statement (a larger Zernike pupil or order, or a lens "
                "that measures that direction better, narrows it)")

    def to_dict(self) -> dict:
        return {"ratio": float(self.ratio) if np.isfinite(self.ratio) else None,
                "sides": [float(s) if np.isfinite(s) else None for s in self.sides],
                "axis": dict(zip(DOF_NAMES, map(float, self.axis))), "sigma_scaled": float(self.sigma),
                "sigmas": self.sigmas, "limits": list(LIMITS), "reliable": self.reliable}


def linearity_check(model, z, pose, cov, chi2: float, sigmas: float = SIGMAS) -> LinearityCheck:
    """The chi2 rise at pose +- sigmas along the weakest principal axis of cov (6, 6; mm and rad) against
    sigmas^2 (module doc). A DOF a numerically null direction moves (infinite variance: a rotationally symmetric
    lens's tilts) hides which directions were estimated, so there the axis comes from the model's iteration
    Jacobian at the pose and the estimator's observability rule, as the estimate's covariance did. model: the
    estimate's ForwardModel (its ``evaluate(...).z`` the measured vector, ``whitener`` its noise); z: the measured
    vector; chi2: the estimate's."""
    D = np.asarray(model.bench.pose_scales, dtype=float)
    cov = np.asarray(cov, dtype=float)
    pose = np.asarray(pose, dtype=float)
    if np.all(np.isfinite(np.diag(cov))):
        basis, cb = np.eye(6), cov / np.outer(D, D)
    else:
        J = model.jacobians(pose[None], exact=False)[0][0]
        Jw = model.whitener @ J
        basis = observability(Jw, D, model.bench.rank_rtol).basis  # scaled units (6, k)
        Jb = (Jw * D) @ basis
        cb = np.linalg.pinv(Jb.T @ Jb, hermitian=True)
    if basis.shape[1] == 0:
        return LinearityCheck(1.0, (1.0, 1.0), np.zeros(6), 0.0, sigmas)
    lam, V = np.linalg.eigh(0.5 * (cb + cb.T))
    axis = basis @ V[:, -1]
    sigma = float(np.sqrt(max(lam[-1], 0.0)) * np.linalg.norm(axis))
    axis = axis / np.linalg.norm(axis)
    step = sigmas * sigma * axis * D
    res = model.evaluate(pose + np.array([-step, step]), check_range=False)
    r = (res.z - np.asarray(z, dtype=float)) @ model.whitener.T
    rise = np.where(res.valid, np.sum(r * r, axis=1), np.inf) - float(chi2)
    sides = tuple(float(v) for v in rise / sigmas**2)
    worst = max(sides, key=lambda v: abs(np.log(v)) if v > 0 else np.inf)
    return LinearityCheck(worst, sides, axis, sigma, sigmas)
