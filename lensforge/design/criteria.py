"""Design criteria on the scaled, noise-whitened sensitivity matrix S~ = R^-1/2 S D.

* ``J`` -- the paper's cost J = w1 kappa(S~) + w2 / sigma_min(S~) plus RANK_PENALTY per
  lost rank (Optics Express 30(9) 14368, 2022, Eq. 7; computed on S~ as DESIGN.md asks).
* ``D`` -- D-optimal design: -log det F~ with F~ = S~^T S~ the Fisher information in
  pose-scale units. Changing the units of x or z only adds a constant, so the optimum
  does not depend on them. Equals -2 sum log sigma_i(S~).
* ``A`` -- A-optimal design: trace of the Cramer-Rao covariance in the user's pose
  units, i.e. each DOF's variance measured in its bench pose scale (1 mm, 1 deg by
  default): trace(D^-1 CRLB D^-1) = sum 1/sigma_i(S~)^2 (dimensionless).

All three are finite for any S (lost rank adds RANK_PENALTY per lost rank), lower is
better, and the optimisers only compare values.
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError
from ..optics.sensitivity import RANK_PENALTY, Metrics, paper_cost

__all__ = ["CRITERIA", "PLAN_CRITERIA", "criterion_value", "check_criterion", "criteria_values"]

CRITERIA = {
    "J": "paper cost w1*kappa + w2/sigma_min of the scaled whitened S (+ rank penalty)",
    "D": "D-optimal: -log det of the Fisher information of the scaled S (unit-independent)",
    "A": "A-optimal: trace of the Cramer-Rao covariance in pose-scale units (1 mm, 1 deg)",
}

# criteria that need more than the single-pose metrics (a calibration plan and a tolerance model):
# evaluated by the design problem (``optimize.DesignProblem``), not by ``criterion_value``
PLAN_CRITERIA = {
    "DS": "self-calibration: log det Cov(Z) of the joint calibration over a plan, the as-built lens a "
          "nuisance with the tolerance prior (selfcal.py; plan and lens designed in turn)",
}

_SV_FLOOR = 1e-15  # relative floor on singular values keeps D and A finite


def check_criterion(name: str) -> str:
    """Canonical criterion name ('J', 'D' or 'A'); ConfigError otherwise."""
    key = str(name).strip().upper()
    if key not in CRITERIA and key not in PLAN_CRITERIA:
        every = {**CRITERIA, **PLAN_CRITERIA}
        raise ConfigError(f"criterion: unknown {name!r}; use one of {', '.join(every)} ({'; '.join(f'{k}: {v}' for k, v in every.items())})")
    return key


def _floored(sv: np.ndarray) -> np.ndarray:
    sv = np.asarray(sv, dtype=float)
    top = sv[0] if sv.size and sv[0] > 0 else 1.0
    return np.maximum(sv, top * _SV_FLOOR)


def criterion_value(name: str, m: Metrics, weights=(1.0, 1.0)) -> float:
    """Value of criterion ``name`` for metrics m (lower is better, always finite)."""
    sv = np.asarray(m.singular_values, dtype=float)
    lost = sv.size - int(m.rank)
    if name == "J":
        return paper_cost(sv, int(m.rank), weights, n_dof=sv.size)
    s = _floored(sv)
    if name == "D":
        return float(-2.0 * np.sum(np.log(s)) + RANK_PENALTY * lost)
    if name == "A":
        return float(min(np.sum(1.0 / s**2), 1e300) + RANK_PENALTY * lost)
    raise ConfigError(f"criterion: unknown {name!r}; use one of {', '.join(CRITERIA)}")


def criteria_values(m: Metrics, weights=(1.0, 1.0)) -> dict:
    """{'J': .., 'D': .., 'A': ..} for one metrics object."""
    return {k: criterion_value(k, m, weights) for k in CRITERIA}
