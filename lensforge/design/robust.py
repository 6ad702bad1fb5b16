"""Tolerance-robust design: the criterion of a lens over its as-built samples.

The robust cost of a design p is a statistic (mean by default) of a design criterion
c (``design.criteria``: J, D or A) over K as-built draws of the lens,

    E[c(p)] ~ (1/K) sum_k c(as-built_k(p)),

with the K draws made from K fixed seeds: the children of
``SeedSequence(spec.seed)``, the same for every candidate p (common random numbers:
every candidate sees the same standardised manufacturing deviations, so differences
between candidates are not sampling noise, and the cost is a deterministic function
of p). Each draw is evaluated by the nominal cost's metrics path (ForwardModel ->
sensitivity_from_model -> metrics_from_S -> criterion_value) at the nominal pose. A
draw that is not a physical lens, or whose SH pupil is not measurable (rays lost,
TIR, pupil under-filled), counts as ``FAIL_VALUE``; every draw's value is capped at
``FAIL_VALUE`` so the cost stays finite and below the optimisers' infeasibility floor.

``RobustSpec`` configures it (``optimize_design(..., robust=RobustSpec(tol))``);
``robust_value`` evaluates one lens; ``compare_robust`` evaluates several designs
(e.g. the nominal and the robust optimum) under the same tolerances on a fresh,
larger set of draws and reports the criterion's mean / p95 and the CRLB std per DOF.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import ConfigError, LensforgeError, LensGeometryError
from ..asbuilt.tolerances import Tolerances, load_tolerances, sample_as_built
from ..optics.bench import Bench
from ..optics.lens import Lens, polar_grid
from ..optics.pose import DOF_NAMES
from ..optics.sensitivity import Metrics, metrics_from_S, sensitivity_from_model
from ..optics.shack_hartmann import ForwardModel

__all__ = ["RobustSpec", "RobustValue", "STATISTICS", "FAIL_VALUE", "as_built_draws", "robust_value",
           "compare_robust", "format_robust_table"]

STATISTICS = ("mean", "max", "mean+std")
FAIL_VALUE = 1e9  # criterion value of an unmeasurable / non-physical as-built draw (and the cap of every draw)
_MAX_SAMPLES = 100_000


@dataclass(frozen=True)
class RobustSpec:
    """Robust-design settings.

    tolerances: :class:`Tolerances` (a dict in the TOML layout or a TOML path is
    converted); n_samples: as-built draws per candidate (small: 4-16); seed: the
    SeedSequence whose children seed the draws (common random numbers, independent
    of the optimiser's seed); statistic: 'mean' (expected criterion), 'max' (worst
    draw) or 'mean+std'; sampler: the as-built sampler, sampler(lens, tolerances, rng,
    validate=False) -> Lens (default ``manufacturing.sample_as_built``; pass another
    to use a different manufacturing model).
    """

    tolerances: Tolerances
    n_samples: int = 8
    seed: int = 0
    statistic: str = "mean"
    sampler: Callable | None = field(default=None, compare=False)

    def __post_init__(self):
        tol = self.tolerances
        if isinstance(tol, dict):
            tol = Tolerances.from_dict(tol, where="robust.tolerances")
        elif isinstance(tol, (str, Path)):
            tol = load_tolerances(tol)
        elif not isinstance(tol, Tolerances):
            raise ConfigError(f"robust.tolerances: expected Tolerances, a dict or a TOML path, got {type(tol).__name__}")
        object.__setattr__(self, "tolerances", tol)
        n = self.n_samples
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= n <= _MAX_SAMPLES:
            raise ConfigError(f"robust.n_samples: expected an integer 1..{_MAX_SAMPLES}, got {n!r}")
        object.__setattr__(self, "n_samples", int(n))
        s = self.seed
        if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 0:
            raise ConfigError(f"robust.seed: expected an integer >= 0, got {s!r}")
        object.__setattr__(self, "seed", int(s))
        st = str(self.statistic).strip().lower()
        if st not in STATISTICS:
            raise ConfigError(f"robust.statistic: unknown {self.statistic!r}; use one of {', '.join(STATISTICS)}")
        object.__setattr__(self, "statistic", st)

    def seed_sequences(self) -> list:
        """The K per-draw SeedSequences (identical on every call: common random numbers)."""
        return np.random.SeedSequence(self.seed).spawn(self.n_samples)

    def rngs(self) -> list:
        """K fresh generators, draw k seeded by the k-th child of SeedSequence(seed)."""
        return [np.random.default_rng(ss) for ss in self.seed_sequences()]

    def aggregate(self, values) -> float:
        v = np.asarray(values, dtype=float)
        if self.statistic == "mean":
            return float(v.mean())
        if self.statistic == "max":
            return float(v.max())
        return float(v.mean() + v.std(ddof=1)) if v.size > 1 else float(v.mean())

    def to_dict(self) -> dict:
        return {"tolerances": self.tolerances.to_dict(), "n_samples": self.n_samples, "seed": self.seed,
                "statistic": self.statistic}

    @classmethod
    def from_dict(cls, d: dict, where: str = "robust") -> "RobustSpec":
        if not isinstance(d, dict) or "tolerances" not in d:
            raise ConfigError(f"{where}: expected an object with 'tolerances', 'n_samples', 'seed'")
        return cls(Tolerances.from_dict(d["tolerances"], where=f"{where}.tolerances"),
                   n_samples=d.get("n_samples", 8), seed=d.get("seed", 0), statistic=d.get("statistic", "mean"))


@dataclass(frozen=True)
class RobustValue:
    """mean: expected criterion; values: (K,) per as-built draw (capped at FAIL_VALUE);
    nominal: criterion of the nominal lens; n_failed: draws that were not
    measurable/physical; cost: the spec's statistic of values; statistic: its name."""

    mean: float
    values: np.ndarray
    nominal: float
    n_failed: int
    cost: float = float("nan")
    statistic: str = "mean"

    def to_dict(self) -> dict:
        return {"cost": self.cost, "statistic": self.statistic, "mean": self.mean, "nominal": self.nominal,
                "n_failed": self.n_failed, "values": [float(v) for v in self.values]}


# --- one lens ------------------------------------------------------------------

_CHECK_GRID = polar_grid(1.0, n_r=9, n_phi=24)  # coarse unit-disc grid (incl. centre and rim)


def cheap_check(lens: Lens) -> Lens:
    """A cheap stand-in for Lens.validate on an as-built draw (~0.2 ms instead of ~5 ms).

    Checks the same conditions (positive thickness, edge >= aperture, finite sags and
    positive thickness over the edge diameter, physical index) on a coarse polar grid;
    a draw that slips through a fine-grid failure is still caught by the trace (rays
    lost -> unmeasurable).
    """
    if not (lens.thickness > 0 and lens.aperture > 0 and lens.edge_diameter >= lens.aperture):
        raise LensGeometryError(f"as-built lens: thickness {lens.thickness:.4g} mm, aperture {lens.aperture:.4g} mm, "
                                f"edge diameter {lens.edge_diameter:.4g} mm are not a lens")
    r = 0.5 * lens.edge_diameter
    t = lens.thickness_at(_CHECK_GRID[0] * r, _CHECK_GRID[1] * r)
    if not np.all(np.isfinite(t)) or np.min(t) <= 0:
        raise LensGeometryError("as-built lens: surfaces undefined or crossing inside the edge diameter")
    n = lens.index(532.0)
    if not 1.0 < n < 4.0:
        raise LensGeometryError(f"as-built lens: index {n:.4g} is not physical")
    return lens


def as_built_draws(lens: Lens, spec: RobustSpec) -> list:
    """The K as-built lenses of ``lens`` under ``spec`` (None for a non-physical draw)."""
    out = []
    for rng in spec.rngs():
        try:
            out.append(cheap_check((spec.sampler or sample_as_built)(lens, spec.tolerances, rng, validate=False)))
        except LensforgeError:
            out.append(None)
    return out


def lens_metrics(bench: Bench, lens: Lens, weights=(1.0, 1.0)) -> Metrics | None:
    """Metrics at the nominal pose by the optimiser's path; None if not measurable."""
    try:
        model = ForwardModel(bench, lens, validate=False)
        S, z0, _ = sensitivity_from_model(model, raise_invalid=False)
        if S is None or not np.all(np.isfinite(S)):
            return None
        return metrics_from_S(S, model.noise_cov, bench, z0, weights)
    except (LensforgeError, np.linalg.LinAlgError, FloatingPointError):
        return None


def _value(crit: str, m: Metrics | None, weights) -> float:
    from .criteria import criterion_value

    if m is None:
        return FAIL_VALUE
    v = criterion_value(crit, m, weights)
    return float(min(v, FAIL_VALUE)) if math.isfinite(v) else FAIL_VALUE


def robust_value(bench: Bench, lens: Lens, spec: RobustSpec, criterion: str = "A", weights=(1.0, 1.0),
                 nominal: float | None = None, return_metrics: bool = False):
    """RobustValue of ``lens`` (its K as-built draws under ``spec``); with
    return_metrics also the list of per-draw Metrics (None for failed draws).

    nominal: the nominal criterion if already known (else computed here).
    """
    from .criteria import check_criterion

    crit = check_criterion(criterion)
    weights = tuple(float(w) for w in weights)
    if nominal is None:
        nominal = _value(crit, lens_metrics(bench, lens, weights), weights)
    ms = [None if ab is None else lens_metrics(bench, ab, weights) for ab in as_built_draws(lens, spec)]
    vals = np.array([_value(crit, m, weights) for m in ms])
    failed = sum(m is None for m in ms)
    rv = RobustValue(float(vals.mean()), vals, float(nominal), int(failed), spec.aggregate(vals), spec.statistic)
    return (rv, ms) if return_metrics else rv


# --- comparison on fresh draws ---------------------------------------------------

def _lens_of(item) -> Lens:
    return item if isinstance(item, Lens) else item.lens


def _crlb_std_dict(std) -> dict:
    std = np.asarray(std, dtype=float)
    out = {}
    for i, n in enumerate(DOF_NAMES):
        v = std[i] * (1e3 if i < 3 else 1e6)
        out[f"{n}_{'um' if i < 3 else 'urad'}"] = float(v) if np.isfinite(v) else None
    return out


def compare_robust(designs: dict, tolerances, bench: Bench | None = None, criterion: str = "A",
                   n_samples: int = 64, seed: int = 1, weights=(1.0, 1.0), exclude_seeds=()) -> dict:
    """Evaluate several designs under the same tolerances on the same fresh as-built draws.

    designs: {name: Design or Lens}; draws: the children of SeedSequence(seed), common
    to all designs (pick a seed other than the one any design was optimised on;
    ``exclude_seeds`` raises ConfigError if ``seed`` is one of them). A Design's own
    robust seed is excluded automatically.

    Returns {"criterion", "n_samples", "seed", "tolerances", "designs": {name: row}}
    with row: nominal criterion, as-built mean / median / p95 / max, n_failed, the
    nominal CRLB std per DOF (um, urad) and the median and p95 of the as-built CRLB
    std per DOF over the measurable draws.
    """
    from .criteria import check_criterion

    crit = check_criterion(criterion)
    bench = bench or Bench.default()
    spec = RobustSpec(tolerances, n_samples, seed)
    used = {int(s) for s in exclude_seeds}
    for d in designs.values():
        r = getattr(d, "robust", None)
        if r:
            used.add(int(r.get("seed", -1)))
    if spec.seed in used:
        raise ConfigError(f"compare_robust: seed {spec.seed} was used in optimisation; evaluate on fresh draws "
                          "(another seed)")
    rows = {}
    for name, item in designs.items():
        lens = _lens_of(item)
        m0 = lens_metrics(bench, lens, weights)
        rv, ms = robust_value(bench, lens, spec, crit, weights, nominal=_value(crit, m0, weights),
                              return_metrics=True)
        v = rv.values
        good = [m.crlb_std for m in ms if m is not None]
        std = np.array(good) if good else np.full((1, 6), np.nan)
        rows[name] = {
            "nominal": rv.nominal,
            "mean": rv.mean, "median": float(np.median(v)), "p95": float(np.percentile(v, 95)),
            "max": float(v.max()), "n_failed": rv.n_failed,
            "crlb_std_nominal": _crlb_std_dict(m0.crlb_std if m0 is not None else np.full(6, np.nan)),
            "crlb_std_as_built_median": _crlb_std_dict(np.median(std, axis=0)),
            "crlb_std_as_built_p95": _crlb_std_dict(np.percentile(std, 95, axis=0)),
        }
    return {"criterion": crit, "n_samples": spec.n_samples, "seed": spec.seed,
            "tolerances": spec.tolerances.to_dict(), "designs": rows}


def format_robust_table(result: dict) -> str:
    """Plain-text table of a ``compare_robust`` result."""
    crit = result["criterion"]
    lines = [f"criterion {crit} over {result['n_samples']} fresh as-built draws (seed {result['seed']})",
             f"{'design':<12}{'nominal':>11}{'mean':>11}{'median':>11}{'p95':>11}{'max':>11}{'failed':>8}"]
    for name, r in result["designs"].items():
        lines.append(f"{name:<12}{r['nominal']:>11.4g}{r['mean']:>11.4g}{r['median']:>11.4g}{r['p95']:>11.4g}"
                     f"{r['max']:>11.4g}{r['n_failed']:>8d}")
    dofs = list(next(iter(result["designs"].values()))["crlb_std_nominal"])
    lines.append("CRLB std per DOF (um, urad): nominal lens | as-built median | as-built p95")
    lines.append(f"{'design':<12}" + "".join(f"{d:>27}" for d in dofs))
    for name, r in result["designs"].items():
        cells = []
        for d in dofs:
            a, b, c = (r["crlb_std_nominal"][d], r["crlb_std_as_built_median"][d], r["crlb_std_as_built_p95"][d])
            cells.append("/".join("-" if x is None else f"{x:.3g}" for x in (a, b, c)))
        lines.append(f"{name:<12}" + "".join(f"{c:>27}" for c in cells))
    return "\n".join(lines)
