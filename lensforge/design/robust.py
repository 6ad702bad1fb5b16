"""Tolerance-robust design criterion: the expected criterion over as-built samples.

E[c(p)] ~ (1/K) sum_k c(as-built_k(p)), with the K as-built draws made from K fixed
seeds (common random numbers: every candidate design p sees the same standardised
manufacturing deviations, so differences between candidates are not sampling
noise). c is a design criterion of ``design.criteria`` (J, D or A) evaluated on the
as-built lens's metrics at the nominal pose. A draw whose lens is not physical or
whose pupil is not lit scores ``INFEASIBLE``-like penalty ``fail_value``.

``expected_criterion`` is a plain function of a Lens, so any optimiser that
minimises a function of the lens can use it; ``compare_designs`` evaluates a
nominal optimum and a robust one under the same tolerances and seeds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import LensforgeError
from ..optics.bench import Bench
from ..optics.lens import Lens
from ..optics.sensitivity import metrics

__all__ = ["expected_criterion", "RobustValue", "compare_designs"]


@dataclass(frozen=True)
class RobustValue:
    """mean: expected criterion; values: (K,) per as-built draw; nominal: criterion of
    the nominal lens; n_failed: draws that were not measurable/physical."""

    mean: float
    values: np.ndarray
    nominal: float
    n_failed: int

    def to_dict(self) -> dict:
        return {"mean": self.mean, "nominal": self.nominal, "n_failed": self.n_failed,
                "values": [float(v) for v in self.values]}


def expected_criterion(lens: Lens, tolerances, bench: Bench | None = None, criterion: str = "D",
                       n_samples: int = 8, seed: int = 0, weights=(1.0, 1.0), fail_value: float = 1e6) -> RobustValue:
    """Mean of ``criterion`` over ``n_samples`` as-built draws of ``lens`` (CRN seeds)."""
    from ..manufacturing.tolerances import sample_as_built
    from .criteria import check_criterion, criterion_value

    crit = check_criterion(criterion)
    bench = bench or Bench.default()
    nominal = criterion_value(crit, metrics(bench, lens, weights=weights), weights)
    vals = np.empty(int(n_samples))
    failed = 0
    for k, ss in enumerate(np.random.SeedSequence(int(seed)).spawn(int(n_samples))):
        try:
            ab = sample_as_built(lens, tolerances, np.random.default_rng(ss))
            vals[k] = criterion_value(crit, metrics(bench, ab, weights=weights), weights)
        except LensforgeError:
            vals[k] = fail_value
            failed += 1
    return RobustValue(float(vals.mean()), vals, float(nominal), failed)


def compare_designs(designs: dict, tolerances, bench: Bench | None = None, criterion: str = "D",
                    n_samples: int = 16, seed: int = 0) -> dict:
    """{name: RobustValue.to_dict()} for several lenses under the same tolerances and seeds."""
    return {name: expected_criterion(lens, tolerances, bench, criterion, n_samples, seed).to_dict()
            for name, lens in designs.items()}
