"""The chi2 model check that decides whether a fit is a calibration at all.

A fit minimises a whitened sum of squares; with the right model and noise model its minimum
is chi2-distributed with ``dof`` degrees of freedom. The check fails -- the result is not a
calibration, the CLI exits 3 and writes no file a robot cell would load -- when both

- the p-value P(chi2_dof > chi2) is below ``ALPHA`` (1e-6): honest noise trips it once in a
  million fits, and
- chi2 / dof exceeds ``MIN_RATIO`` (2): the residuals are more than sqrt(2) times the noise
  model. ASSUMPTION: below that factor a fit is kept and warned about (the p < 1e-3 warning
  of ``session``): with thousands of degrees of freedom a few per cent of unmodelled noise
  already gives p < 1e-6, and such a fit is still a calibration with 1-sigma too small by
  that factor. The convention mistakes this check exists for (units, angle units, column
  orders, the wrong design) give chi2/dof of 10^2 to 10^12 (issue 23's campaign).

For small dof the p-value rule is the stricter one (dof 8: chi2/dof > 4.7), for dof above
~60 the ratio. Both keep the false-alarm rate of an honest fit at or below ``ALPHA``; the
measured rate on simulated sessions is in ``tests/test_model_check.py``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from scipy.stats import chi2 as chi2_dist

__all__ = ["ALPHA", "MIN_RATIO", "ModelCheck", "check_chi2", "threshold_chi2_dof"]

ALPHA = 1e-6
MIN_RATIO = 2.0


@dataclass(frozen=True)
class ModelCheck:
    """Outcome of the chi2 model check of one fit.

    chi2, dof: the fit's; p_value: upper tail of chi2_dof at chi2; threshold_chi2_dof: the
    chi2/dof above which the check fails; passed; reason: why it failed ('' when passed);
    what: the fit's name in messages."""

    chi2: float
    dof: int
    p_value: float
    threshold_chi2_dof: float
    passed: bool
    reason: str = ""
    what: str = "fit"

    @property
    def chi2_dof(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else float("nan")

    def to_dict(self) -> dict:
        """JSON block: valid, reason, chi2, dof, chi2_dof, p_value, threshold_chi2_dof, rule."""
        def fin(v):
            return float(v) if math.isfinite(v) else None
        return {"valid": bool(self.passed), "reason": self.reason or None, "chi2": fin(self.chi2),
                "dof": int(self.dof), "chi2_dof": fin(self.chi2_dof), "p_value": fin(self.p_value),
                "threshold_chi2_dof": fin(self.threshold_chi2_dof),
                "rule": f"fails when p < {ALPHA:g} and chi2/dof > {MIN_RATIO:g}"}


def threshold_chi2_dof(dof: int) -> float:
    """The chi2/dof above which a fit with ``dof`` degrees of freedom fails the check."""
    if dof <= 0:
        return float("inf")
    return max(MIN_RATIO, float(chi2_dist.isf(ALPHA, dof)) / dof)


def check_chi2(chi2: float, dof: int, what: str = "fit") -> ModelCheck:
    """The model check of a fit with minimum ``chi2`` over ``dof`` degrees of freedom.

    dof <= 0 (no redundancy): nothing to check, passed. A non-finite chi2 fails."""
    chi2, dof = float(chi2), int(dof)
    if dof <= 0:
        return ModelCheck(chi2, dof, float("nan"), float("inf"), True, "", what)
    thr = threshold_chi2_dof(dof)
    if not math.isfinite(chi2):
        return ModelCheck(chi2, dof, 0.0, thr, False, f"{what}: chi2 is not finite", what)
    p = float(chi2_dist.sf(chi2, dof))
    passed = chi2 / dof <= thr
    reason = "" if passed else (f"{what}: model check failed (chi2/dof {chi2 / dof:.3g} over {dof} DOF, "
                                f"p = {p:.2g}; the check fails above {thr:.3g}): the data do not fit the model")
    return ModelCheck(chi2, dof, p, thr, passed, reason, what)
