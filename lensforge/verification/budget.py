"""Per-component sensitivity and the tolerance budget of an as-built study.

Sensitivity: the study run with one tolerance component at a time (the others
zero) at its given size, with all of them together, and with none (noise only).

Budget: for a target calibration accuracy (default 0.1 mm and 0.01 deg on Z at
the 95th percentile) the largest *scale* s of each component (others zero) for
which the study still meets the target; the component's magnitudes are then s
times the given ones. Every evaluation uses the same trial seeds (common random
numbers: the same as-built draws, only their size changes; see study.py), so the
percentile is a smooth, nearly monotonic function of s. The search runs in
u = s^2 on g = (percentile / target)^2, which is close to linear for independent
error sources (g ~ g0 + a u), by secant / regula falsi steps with bracketing,
stopping when the bracket is within ``rel_tol``. The reported scale is the
largest one *evaluated* that meets the target (conservative).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import ConfigError
from ..asbuilt.tolerances import COMPONENT_SPECS, resolve_tolerances
from ..optics.lens import LensSpec, resolve_lens
from .runner import dask_client
from .study import StudyConfig, verify

if TYPE_CHECKING:
    from distributed import Client

    from ..asbuilt.tolerances import Tolerances
    from ..optics.bench import Bench

__all__ = ["SensitivityRow", "BudgetRow", "Budget", "sensitivity_analysis", "tolerance_budget", "scaled_all",
           "MAIN_FIELD"]

# the magnitude that names a component's size in the budget table (after Tolerances.resolved)
MAIN_FIELD = {name: c.main for name, c in COMPONENT_SPECS.items()}


def scaled_all(tolerances: Tolerances, factor: float) -> Tolerances:
    """Every component's magnitudes times ``factor``."""
    t = tolerances
    for name in t.component_names():
        t = t.scaled(name, factor)
    return t


def _main_value(tolerances, name: str, material, scale: float = 1.0):
    f, unit = MAIN_FIELD.get(name, (None, ""))
    if f is None:
        return None, unit
    v = getattr(tolerances.resolved(material), f, None)
    return (None if v is None else float(v) * scale), unit


@dataclass(frozen=True)
class SensitivityRow:
    """Z error statistics with one tolerance component (or all, or none).

    component; median/p95/max of rotation (deg) and translation (mm) error (None =
    infinite: failures above that percentile); failure_rate; mean_bias (6; mm, rad)."""

    component: str
    median_rot_deg: float | None
    p95_rot_deg: float | None
    max_rot_deg: float | None
    median_trans_mm: float | None
    p95_trans_mm: float | None
    max_trans_mm: float | None
    failure_rate: float
    target_ratio: float | None

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in self.__dict__.items()}


def _row(name: str, res) -> SensitivityRow:
    s = res.summary
    q = f"p{s['percentile']:g}"
    return SensitivityRow(name, s["rotation_deg"]["median"], s["rotation_deg"][q], s["rotation_deg"]["max"],
                          s["translation_mm"]["median"], s["translation_mm"][q], s["translation_mm"]["max"],
                          s["failure_rate"], s["target_ratio"])


def sensitivity_analysis(lens: LensSpec, tolerances: Tolerances | str | Path, n_lenses: int, seed: int, bench: Bench | None = None,
                         *, config: StudyConfig | None = None, workers: int | None = 0, scheduler: str | None = None,
                         client: Client | None = None,
                         progress: bool = False) -> list[SensitivityRow]:
    """Z error statistics with no tolerance (noise only), each component alone at its given
    size, and all together, on the same seeds.

    Parameters
    ----------
    lens : LensSpec
        Design file, paper lens name or Lens.
    tolerances : Tolerances, str or pathlib.Path
        The tolerance model.
    n_lenses : int
        As-built lenses per study.
    seed : int
        Study seed (the same for every row: common random numbers).
    bench : Bench, optional
        Default: the design's bench, else the built-in one.
    config : StudyConfig, optional
        Poses, calibration method, target etc. of every study.
    workers : int, optional
        0 = in this process, N = a local Dask cluster of N processes.
    scheduler : str, optional
        Address of an existing Dask scheduler.
    client : distributed.Client, optional
        An existing Dask client (reused across the studies).
    progress : bool
        Progress bar on stderr.

    Returns
    -------
    list of SensitivityRow
        Rows "none", one per component, "all": median, p95 and max of the rotation (deg)
        and translation (mm) error of Z (None = infinite), failure rate, mean bias (6,).
    """
    r = resolve_lens(lens)
    lens, bench = r.lens, r.bench_or(bench)
    tol = resolve_tolerances(tolerances)[0]
    if tol is None:
        raise ConfigError("tolerances: the sensitivity analysis needs a tolerance model")
    config = config or StudyConfig()
    rows = []
    with _studies(lens, n_lenses, seed, bench, workers, scheduler, client, progress) as run:
        rows.append(_row("none", run(None, config, "sensitivity: noise only")))
        for name in tol.component_names():
            rows.append(_row(name, run(tol.only(name), config, f"sensitivity: {name}")))
        rows.append(_row("all", run(tol, config, "sensitivity: all tolerances")))
    return rows


@contextmanager
def _studies(lens, n_lenses, seed, bench, workers, scheduler, client, progress):
    """Yield run(tolerances, config) -> StudyResult, all runs sharing one Dask client (or
    in-process when workers == 0 and no scheduler/client is given), with common random numbers."""
    own = client is None and not (workers == 0 and scheduler is None)
    with (dask_client(workers, scheduler) if own else nullcontext(client)) as cl:
        def run(t, config, label="as-built lenses"):
            return verify(lens, t, n_lenses, seed, bench, config=config, workers=0 if cl is None else None,
                          client=cl, progress=progress, description=label)

        yield run


@dataclass(frozen=True)
class BudgetRow:
    """Budget of one component (others zero).

    max_scale: largest evaluated scale meeting the target (0.0 if even the noise
    floor fails; None if it still meets it at ``max_search_scale``); max_value /
    unit: the component's main magnitude at that scale (see MAIN_FIELD);
    given_value: at scale 1; ratio_at_max: percentile/target at max_scale;
    status: "ok", "noise floor exceeds target", "not limiting up to N x",
    "below search range"; evaluations: (scale, ratio) pairs tried.
    """

    component: str
    max_scale: float | None
    max_value: float | None
    given_value: float | None
    unit: str
    ratio_at_max: float | None
    status: str
    evaluations: tuple = field(default=())

    def to_dict(self) -> dict:
        d = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in self.__dict__.items()}
        d["evaluations"] = [[s, (r if math.isfinite(r) else None)] for s, r in self.evaluations]
        return d


@dataclass(frozen=True)
class Budget:
    """Tolerance budget: rows per component, the noise-only ratio, the dominant
    component (smallest max_scale), target and study size."""

    rows: tuple
    noise_ratio: float | None
    dominant: str | None
    target_mm: float
    target_deg: float
    percentile: float
    n_lenses: int
    seed: int

    def to_dict(self) -> dict:
        return {"target": {"translation_mm": self.target_mm, "rotation_deg": self.target_deg,
                           "percentile": self.percentile},
                "n_lenses": self.n_lenses, "seed": self.seed, "noise_only_ratio": self.noise_ratio,
                "dominant": self.dominant, "rows": [r.to_dict() for r in self.rows]}


def _ratio(res) -> float:
    r = res.summary["target_ratio"]
    return math.inf if r is None else float(r)


def search_scale(f: Callable[[float], float], f0: float, rel_tol: float = 0.1, max_evals: int = 8, s_min: float = 1e-3,
                 s_max: float = 1e3) -> tuple[float | None, float | None, str, list]:
    """Largest s in [s_min, s_max] with f(s) <= 1, given f(0) = f0 (see module doc).

    Returns (scale, f(scale), status, evaluations)."""
    evals = []
    if not f0 <= 1.0:
        return 0.0, f0, "noise floor exceeds target", evals
    g0 = f0 * f0
    lo, flo = 0.0, f0  # passing
    hi, fhi = None, None  # failing
    s = 1.0
    for _ in range(max_evals):
        v = f(s)
        evals.append((s, v))
        if v <= 1.0:
            lo, flo = s, v
        else:
            hi, fhi = s, v
        if hi is not None and lo > 0 and hi / lo <= 1.0 + rel_tol:
            break
        if hi is None and lo >= s_max:
            return None, flo, f"not limiting up to {s_max:g} x", evals
        if lo == 0.0 and hi is not None and hi <= s_min:
            return 0.0, f0, "below search range", evals
        # secant in u = s^2 on g = ratio^2 between the passing and failing ends
        if hi is None:
            u1, g1 = lo * lo, flo * flo
            a = (g1 - g0) / u1 if u1 > 0 else 0.0
            s_new = math.sqrt((1.0 - g0) / a) if a > 0 else lo * 100.0
            s_new = min(max(s_new, lo * 1.5), lo * 100.0, s_max)
        else:
            ul, gl = lo * lo, flo * flo
            uh, gh = hi * hi, (fhi * fhi if math.isfinite(fhi) else math.inf)
            if math.isfinite(gh) and gh > gl:
                u = ul + (1.0 - gl) * (uh - ul) / (gh - gl)
                s_new = math.sqrt(max(u, 0.0))
            else:
                s_new = math.sqrt(max(lo, hi / 100.0) * hi)
            lo_b = max(lo, hi / 100.0) if lo > 0 else hi / 100.0
            # stay strictly inside the bracket, away from its ends
            s_new = min(max(s_new, lo_b + 0.05 * (hi - lo_b)), hi - 0.05 * (hi - lo_b))
            s_new = max(s_new, s_min)
        s = s_new
    if lo == 0.0:
        return 0.0, f0, "below search range" if hi is not None and hi <= s_min * 1.01 else "ok", evals
    return lo, flo, "ok", evals


def tolerance_budget(lens: LensSpec, tolerances: Tolerances | str | Path, *, target_mm: float = 0.1, target_deg: float = 0.01,
                     n_lenses: int = 64, seed: int = 0, bench: Bench | None = None, config: StudyConfig | None = None,
                     rel_tol: float = 0.1, max_evals: int = 8, workers: int | None = 0, scheduler: str | None = None,
                     client: Client | None = None, components: Sequence[str] | None = None,
                     relative_to_noise: float | None = None,
                     progress: bool = False) -> Budget:
    """The tolerance budget table (see the module docstring): for each component, the largest
    scale of its size at which the calibration still meets the target.

    Each evaluation is a study of ``n_lenses`` as-built lenses with the same seeds.

    Parameters
    ----------
    lens : LensSpec
        Design file, paper lens name or Lens.
    tolerances : Tolerances, str or pathlib.Path
        The tolerance model (its sizes are the scale 1).
    target_mm, target_deg : float
        Target percentile error of Z, mm and degrees (replaced with relative_to_noise).
    n_lenses : int
        As-built lenses per study.
    seed : int
        Study seed (the same for every evaluation: common random numbers).
    bench : Bench, optional
        Default: the design's bench, else the built-in one.
    config : StudyConfig, optional
        Poses, calibration method, target etc. of every study.
    workers : int, optional
        0 = in this process, N = a local Dask cluster of N processes.
    scheduler : str, optional
        Address of an existing Dask scheduler.
    client : distributed.Client, optional
        An existing Dask client (reused across the studies).
    progress : bool
        Progress bar on stderr.
    rel_tol : float
        Relative tolerance of each component's search for its largest allowed scale.
    max_evals : int
        Studies per component at most.
    components : sequence of str, optional
        The components to budget (default: all).
    relative_to_noise : float, optional
        k: the target becomes k times the noise-only percentile errors (the as-built lens
        may make the calibration at most k times worse than a perfect lens).

    Returns
    -------
    Budget
        One row per component (its largest allowed scale and errors), the noise-only
        ratio, the dominant component (smallest allowed scale), the target and study size.
    """
    from dataclasses import replace

    r = resolve_lens(lens)
    lens, bench = r.lens, r.bench_or(bench)
    tol = resolve_tolerances(tolerances)[0]
    if tol is None:
        raise ConfigError("tolerances: the budget needs a tolerance model (--tolerances T.toml)")
    config = replace(config or StudyConfig(), target_mm=float(target_mm), target_deg=float(target_deg))
    names = tuple(components) if components else tol.component_names()
    for c in names:
        if c not in tol.component_names():
            raise ConfigError(f"component: unknown {c!r}; use one of {list(tol.component_names())}")
    rows = []
    with _studies(lens, n_lenses, seed, bench, workers, scheduler, client, progress) as run:

        def study(t, label):
            return run(t, config, f"budget: {label}")  # config is re-bound below for a target relative to noise

        noise = study(None, "noise only")
        if relative_to_noise is not None:
            k = float(relative_to_noise)
            if not k > 1.0:
                raise ConfigError(f"relative_to_noise: must be > 1 (a multiple of the noise-only error), got {k}")
            q = f"p{config.percentile:g}"
            pr, pt = noise.summary["rotation_deg"][q], noise.summary["translation_mm"][q]
            if pr is None or pt is None:
                raise ConfigError("relative_to_noise: the noise-only study fails too often to define a target")
            config = replace(config, target_mm=k * pt, target_deg=k * pr)
            target_mm, target_deg = config.target_mm, config.target_deg
            noise = study(None, "noise only")
        f0 = _ratio(noise)
        for c in names:
            base = tol.only(c)

            def f(s, base=base, c=c):
                return _ratio(study(base.scaled(c, s), f"{c} x {s:.3g}"))

            scale, ratio, status, evals = search_scale(f, f0, rel_tol=rel_tol, max_evals=max_evals)
            given, unit = _main_value(tol, c, lens.material_data)
            val = None if scale is None else _main_value(tol, c, lens.material_data, scale)[0]
            rows.append(BudgetRow(c, scale, val, given, unit, ratio, status, tuple(evals)))
    limiting = [r for r in rows if r.max_scale is not None]
    dominant = (min(limiting, key=lambda r: r.max_scale).component
                if limiting and math.isfinite(f0) and f0 <= 1.0 else None)
    return Budget(tuple(rows), f0 if math.isfinite(f0) else None, dominant, float(target_mm), float(target_deg),
                  config.percentile, int(n_lenses), int(seed))
