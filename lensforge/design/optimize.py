"""Derivative-free lens optimisation: Nelder-Mead, particle swarm, GA and CMA-ES.

All optimisers work in the unit box u in [0, 1]^n (p = lower + u (upper - lower)) on
one cost: the chosen criterion (criteria.py) for a feasible lens, and
INFEASIBLE + violation for a lens that breaks a constraint (constraints.py). All
four methods only compare cost values, so the penalty's size does not bias them.
The best feasible lens seen is returned, re-checked with the full constraint check;
an infeasible result raises DesignError naming the violated constraint.

Tolerance-robust design (``robust=RobustSpec(tolerances, n_samples, seed, statistic)``):
the cost of a feasible candidate is the statistic (mean by default) of the criterion
over ``n_samples`` as-built draws of its lens, seeded by the same SeedSequence
children for every candidate (common random numbers; see ``robust.py``). The
constraints (printability, working range) stay on the nominal design.

Seeds: every random draw lensforge makes comes from ``numpy.random.default_rng(seed)``.
pyswarms, pymoo and cma draw from numpy's *global* generator; lensforge seeds it for
the duration of the run and restores its previous state afterwards.
"""

from __future__ import annotations

import contextlib
import sys
import time
from collections import Counter
from dataclasses import dataclass
from collections.abc import Sequence
from typing import Callable

import numpy as np

from ..errors import ConfigError, DesignError, LensforgeError
from ..optics.bench import Bench
from ..optics.lens import Lens
from ..optics.sensitivity import metrics_from_S, sensitivity_from_model
from ..progress import Bar, progress_bar
from .constraints import Constraints, check_design, require_feasible, working_poses
from .criteria import check_criterion, criterion_value
from .design_file import Design, metrics_dict
from .bench_vars import BenchVariables, CoDesignParameterisation
from .parameterisation import Parameterisation, parameterisation
from .robust import RobustSpec, robust_value
from .selfcal import SelfCalSpec, plan_for, selfcal_value

__all__ = ["METHODS", "OPTIMISERS", "Optimiser", "optimize_design", "DesignProblem", "DEFAULT_MAX_EVALS", "INFEASIBLE",
           "bench_scan", "CODESIGN_LENS_EVALS", "CODESIGN_EVALS"]

INFEASIBLE = 1e30  # cost floor of an infeasible lens (above any feasible criterion value)
_MAX_START_TRIES = 400
_N_CANDIDATES = 10


class _Stop(Exception):
    """Budget (evaluations or wall time) exhausted."""




@contextlib.contextmanager
def _global_numpy_seed(seed: int):
    """Seed numpy's global generator (used by pyswarms, pymoo, cma); restore it after."""
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(state)


class DesignProblem:
    """Cost function of one design run: u (unit box) -> criterion or penalty.

    Counts evaluations, keeps the best feasible point and the iteration history.
    Stateful by design but local to one run; not shared.
    """

    def __init__(self, bench: Bench, par: Parameterisation, criterion: str = "J", weights=(1.0, 1.0),
                 constraints: Constraints | None = None, max_evals: int = 1000, time_limit_s: float | None = None,
                 progress: Bar | None = None, robust: RobustSpec | None = None, label: str = "",
                 search_quadrature: int | None = None, selfcal: SelfCalSpec | None = None):
        self.bench = bench
        self.selfcal = selfcal
        # the bench the search evaluates on: with search_quadrature, a coarser sub-aperture rule
        # (co-design: 1 point per lenslet is ~4x faster and moves the CRLB by ~1 %); the returned
        # design is always checked and scored on ``bench``
        self.search_quadrature = search_quadrature
        self.search_bench = bench if search_quadrature is None else bench.replace(
            sensor={"subaperture_quadrature": int(search_quadrature)})
        self.robust = robust
        self.par = par
        self.criterion = check_criterion(criterion)
        self.weights = tuple(float(w) for w in weights)
        self.constraints = constraints or Constraints()
        self.constraints.check_bench(bench)
        self.poses = working_poses(self.constraints)
        self.max_evals = int(max_evals)
        self.label = label  # the progress bar's text
        self.time_limit_s = time_limit_s
        self.progress = progress
        self.n_evals = 0
        self.best_cost = np.inf
        self.best_u = None
        self.history: list[dict] = []
        self.candidates: list = []  # best feasible points (cost, eval index, u), fallback if the full check fails
        self.iteration = 0
        self.t0 = time.perf_counter()

    # one lens ---------------------------------------------------------------
    def evaluate_p(self, p, nominal_only: bool = False):
        """(cost, Feasibility, Metrics or None) of parameter vector p; never raises for bad lenses.

        Metrics are the nominal lens's; with a robust spec the cost of a feasible lens
        is the robust statistic over its as-built draws (nominal_only: the nominal
        criterion, for feasibility probes).
        """
        try:
            lens = self.par.to_lens(p)
            bench = self.bench_of(p, search=True)
        except LensforgeError as e:
            from .constraints import Feasibility, Violation

            return INFEASIBLE * 10, Feasibility(False, (Violation("geometry", np.nan, 0.0, str(e)),), 1e3), None
        f = check_design(bench, lens, self.constraints, self.poses, fast=True)
        if not f.ok:
            return INFEASIBLE * (1.0 + f.violation), f, None
        S, z0, _ = sensitivity_from_model(f.model, raise_invalid=False)
        if S is None:
            return INFEASIBLE * 2.0, f, None
        m = metrics_from_S(S, f.model.noise_cov, bench, z0, self.weights)
        if self.criterion == "DS":
            value = selfcal_value(bench, lens, self.selfcal)[0] if not nominal_only else criterion_value("A", m)
        else:
            value = criterion_value(self.criterion, m, self.weights)
        if self.robust is not None and not nominal_only:
            value = robust_value(bench, lens, self.robust, self.criterion, self.weights, nominal=value).cost
        return value, f, m

    def bench_of(self, p, search: bool = False) -> Bench:
        """The bench of parameter vector p (the design's bench unless bench variables are free);
        search: with the search's sub-aperture rule."""
        base = self.search_bench if search else self.bench
        return self.par.to_bench(p, base) if isinstance(self.par, CoDesignParameterisation) else base

    def __call__(self, u) -> float:
        if self.n_evals >= self.max_evals:
            raise _Stop
        if self.time_limit_s is not None and time.perf_counter() - self.t0 > self.time_limit_s:
            raise _Stop
        u = np.clip(np.asarray(u, dtype=float), 0.0, 1.0)
        cost = float(self.evaluate_p(self.par.from_unit(u))[0])
        self.n_evals += 1
        if cost < self.best_cost:
            self.best_cost = cost
            self.best_u = u.copy()
        if cost < INFEASIBLE:
            self.candidates.append((cost, self.n_evals, u.copy()))
            if len(self.candidates) > 4 * _N_CANDIDATES:
                self.candidates = sorted(self.candidates, key=lambda c: (c[0], c[1]))[:_N_CANDIDATES]
        if self.progress is not None:
            self.progress.update(min(self.n_evals, self.max_evals))
            self.progress.describe(f"{self.label}  best {self.best_cost:.5g}" if self.best_cost < INFEASIBLE
                                   else f"{self.label}  (no feasible yet)")
        return cost

    def batch(self, U) -> np.ndarray:
        """Costs of the rows of U (raises _Stop once the budget is spent)."""
        out = np.array([self(u) for u in np.atleast_2d(U)])
        self.record()
        return out

    def record(self, **extra) -> None:
        """Append one iteration row to the history."""
        self.iteration += 1
        row = {"iteration": self.iteration, "n_evals": self.n_evals,
               "best": float(self.best_cost) if np.isfinite(self.best_cost) else None,
               "feasible": bool(self.best_cost < INFEASIBLE),
               "t_s": round(time.perf_counter() - self.t0, 4)}
        row.update(extra)
        self.history.append(row)

    # starts -----------------------------------------------------------------
    def random_feasible_start(self, rng: np.random.Generator, tries: int = _MAX_START_TRIES,
                              shrink: float = 0.97) -> np.ndarray:
        """A random feasible point of the unit box (DesignError if none in ``tries``).

        Draws uniformly in a box around the centre of the bounds whose half-width starts
        at the full box and shrinks by ``shrink`` per rejected draw: feasible regions
        can be a small part of the bounds (strong surfaces break the thickness and
        pupil constraints), while the centre is usually a mild lens.
        """
        seen = Counter()
        first = {}
        for i in range(tries):
            u = 0.5 + shrink**i * (rng.random(self.par.n) - 0.5)
            cost, f, m = self.evaluate_p(self.par.from_unit(u), nominal_only=True)
            if cost < INFEASIBLE:
                return u
            for v in f.violations:
                seen[v.constraint] += 1
                first.setdefault(v.constraint, v.message)
        name, count = seen.most_common(1)[0]
        raise DesignError(
            f"no feasible design found in {tries} random samples of the bounds: constraint {name!r} violated in "
            f"{count} of them (e.g. {first[name]}); widen the bounds, relax the constraints or change the bench"
        )


def _start_point(prob: DesignProblem, start, rng, start_lens: Lens | None = None) -> tuple[np.ndarray, str]:
    """Feasible start u0 and a word on where it came from (start_lens: the lens 'paper' starts from)."""
    par = prob.par
    if isinstance(start, str):
        key = start.lower()
        if key not in ("paper", "template", "random"):
            raise ConfigError(f"start: expected 'paper', 'random' or a parameter vector, got {start!r}")
        if key in ("paper", "template"):
            p = par.from_lens(start_lens) if start_lens is not None else par.from_lens(par.template)
            if par.in_bounds(p) and prob.evaluate_p(p, nominal_only=True)[0] < INFEASIBLE:
                return par.to_unit(p), "template"
        return prob.random_feasible_start(rng), "random"
    p = np.asarray(start, dtype=float)
    if p.shape != (par.n,):
        raise ConfigError(f"start: expected {par.n} values for {list(par.names)}, got shape {p.shape}")
    if not par.in_bounds(p):
        raise ConfigError(f"start: vector lies outside the bounds {par.bounds_dict()}")
    cost, f, _ = prob.evaluate_p(p, nominal_only=True)
    if cost >= INFEASIBLE:
        require_feasible(check_design(prob.bench_of(p), par.to_lens(p), prob.constraints), "start design")
    return par.to_unit(p), "given"


# --- the optimisers (registered in OPTIMISERS below) -------------------------------------------------------

def _initial_population(rng, u0, k: int, spread: float = 0.1) -> np.ndarray:
    """k points of the unit box: the feasible start, half of the rest scattered around it
    (normal, sd ``spread``; feasible regions can be small), the others uniform."""
    n = len(u0)
    X = rng.random((k, n))
    X[0] = u0
    near = (k - 1) // 2
    X[1:1 + near] = np.clip(u0 + spread * rng.standard_normal((near, n)), 0.0, 1.0)
    return X


def _run_nelder_mead(prob: DesignProblem, u0, rng, seed: int, opts: dict) -> dict:
    starts = [u0] + [prob.random_feasible_start(rng) for _ in range(int(opts.get("n_starts", 1)) - 1)]
    from scipy.optimize import minimize

    n = prob.par.n
    per = max(n + 2, (prob.max_evals - prob.n_evals) // max(len(starts), 1))
    step = float(opts.get("simplex_step", 0.1))
    info = {"starts": len(starts), "evals_per_start": per}
    for k, u0 in enumerate(starts):
        simplex = [u0]
        for i in range(n):
            v = u0.copy()
            v[i] = v[i] + step if v[i] + step <= 1.0 else v[i] - step
            simplex.append(v)
        f0 = max(abs(prob.best_cost), 1.0) if prob.best_cost < INFEASIBLE else 1.0
        budget_end = min(prob.max_evals, prob.n_evals + per - 1)
        try:
            minimize(lambda u: prob(u) if prob.n_evals < budget_end else _raise_stop(), u0, method="Nelder-Mead",
                     bounds=[(0.0, 1.0)] * n, callback=lambda *a: prob.record(start=k),
                     options={"initial_simplex": np.array(simplex), "maxfev": per, "maxiter": 100 * per,
                              "xatol": float(opts.get("xtol", 1e-5)), "fatol": float(opts.get("ftol", 1e-7)) * f0,
                              "adaptive": n > 4})
        except _Stop:
            if prob.n_evals >= prob.max_evals or _time_up(prob):
                break
    return info


def _raise_stop():
    raise _Stop


def _time_up(prob: DesignProblem) -> bool:
    return prob.time_limit_s is not None and time.perf_counter() - prob.t0 > prob.time_limit_s


def _run_pso(prob: DesignProblem, u0, rng, seed: int, opts: dict) -> dict:
    from pyswarms.single import GlobalBestPSO

    n = prob.par.n
    particles = int(opts.get("particles", 30))
    iters = max(1, (prob.max_evals - prob.n_evals) // particles)
    init = _initial_population(rng, u0, particles)
    # Clerc-Kennedy constriction coefficients (w = 0.7298, c1 = c2 = 1.49618)
    options = {"c1": float(opts.get("c1", 1.49618)), "c2": float(opts.get("c2", 1.49618)),
               "w": float(opts.get("w", 0.7298))}
    ftol = float(opts.get("ftol", 0.0))
    pso = GlobalBestPSO(n_particles=particles, dimensions=n, options=options,
                        bounds=(np.zeros(n), np.ones(n)), bh_strategy="nearest", velocity_clamp=(-0.3, 0.3),
                        ftol=ftol if ftol > 0 else -np.inf, ftol_iter=int(opts.get("ftol_iter", 20)), init_pos=init)
    try:
        pso.optimize(prob.batch, iters=iters, verbose=False)
    except _Stop:
        pass
    return {"particles": particles, "iterations": iters, **options}


def _run_ga(prob: DesignProblem, u0, rng, seed: int, opts: dict) -> dict:
    from pymoo.algorithms.soo.nonconvex.ga import GA
    from pymoo.core.problem import Problem
    from pymoo.optimize import minimize

    n = prob.par.n
    pop = int(opts.get("population") or 30)
    X0 = _initial_population(rng, u0, pop)

    class _P(Problem):
        def __init__(self):
            super().__init__(n_var=n, n_obj=1, xl=np.zeros(n), xu=np.ones(n))

        def _evaluate(self, X, out, *args, **kwargs):
            out["F"] = prob.batch(X)[:, None]

    gens = max(1, (prob.max_evals - prob.n_evals) // pop)
    try:
        minimize(_P(), GA(pop_size=pop, sampling=X0, eliminate_duplicates=True), ("n_gen", gens),
                 seed=seed, verbose=False)
    except _Stop:
        pass
    return {"population": pop, "generations": gens}


def _run_cmaes(prob: DesignProblem, u0, rng, seed: int, opts: dict) -> dict:
    import cma

    sigma0 = float(opts.get("sigma0", 0.1))
    cma_seed = int(np.random.SeedSequence(seed).generate_state(1)[0] % (2**31 - 2)) + 1  # cma: 0 means 'time'
    copts = {"seed": cma_seed, "bounds": [0.0, 1.0], "maxfevals": prob.max_evals - prob.n_evals, "verbose": -9,
             "verb_disp": 0, "verb_log": 0, "tolfun": float(opts.get("ftol", 1e-11)), "tolx": float(opts.get("xtol", 1e-8))}
    if opts.get("population"):
        copts["popsize"] = int(opts["population"])
    # a feasible region thinner than the search width (e.g. fixed spot windows: every slope below ~9 mrad)
    # leaves a whole first generation infeasible and CMA-ES does not leave its start: restart it from the
    # start with a 10x smaller step until a first generation holds a feasible lens (the default designs'
    # first generations do, so they are unchanged)
    def generation(es) -> np.ndarray:
        X = es.ask()
        F = prob.batch(np.array(X))
        es.tell(X, list(F))
        return np.asarray(F)

    sigma, narrowed = sigma0, 0
    try:
        while True:
            es = cma.CMAEvolutionStrategy(np.asarray(u0, dtype=float), sigma,
                                          {**copts, "maxfevals": prob.max_evals - prob.n_evals})
            if np.any(generation(es) < INFEASIBLE) or sigma <= _CMA_MIN_SIGMA * 1.0001:
                break
            sigma, narrowed = max(0.1 * sigma, _CMA_MIN_SIGMA), narrowed + 1
        while not es.stop():
            generation(es)
    except _Stop:
        pass
    return {"sigma0": sigma0, "sigma_used": sigma, "narrowed": narrowed, "popsize": int(es.popsize),
            "stop": {k: _plain_stop(v) for k, v in es.stop().items()}}


_CMA_MIN_SIGMA = 1e-3  # smallest first step of a narrowed CMA-ES restart (unit box)


def _plain_stop(v):
    try:
        return float(v)
    except (TypeError, ValueError):
        return str(v)


@dataclass(frozen=True)
class Optimiser:
    """One optimiser of the unit box: run(problem, u0, rng, seed, opts) -> settings dict
    (it calls problem(u) / problem.batch(U) until the budget raises _Stop);
    default_max_evals: budget when none is given; aliases: other accepted names."""

    name: str
    run: Callable[..., dict]
    default_max_evals: int
    aliases: tuple = ()


# The registry: adding an optimiser is one _run_* function and one entry here.
OPTIMISERS = {o.name: o for o in (
    Optimiser("nelder-mead", _run_nelder_mead, 1000, ("nm", "nelder_mead", "neldermead", "simplex")),
    Optimiser("pso", _run_pso, 3000, ("swarm",)),
    Optimiser("ga", _run_ga, 3000, ("genetic",)),
    # 800: the default design (zernike, criterion A, free set 'full', seed 0) is within its CRLB goals
    Optimiser("cmaes", _run_cmaes, 800, ("cma", "cma-es", "cma_es")),
)}
METHODS = tuple(OPTIMISERS)
DEFAULT_MAX_EVALS = {name: o.default_max_evals for name, o in OPTIMISERS.items()}  # ~30 ms per evaluation
_ALIASES = {a: o.name for o in OPTIMISERS.values() for a in o.aliases}


# co-design budgets: the lens step on the given bench, then lens and bench jointly (``optimize_design``)
CODESIGN_LENS_EVALS = 300
CODESIGN_EVALS = 160


def bench_scan(par: CoDesignParameterisation, lens: Lens, constraints: Constraints, criterion: str = "A",
               weights=(1.0, 1.0), quadrature: int | None = 1, radii_mm=(1.5, 2.0, 2.5, 3.0, 3.5)) -> list[dict]:
    """The lens on each catalogue expander x pupil radius (other bench variables at the base
    bench): one row per bench with feasible, the criterion value (inf if infeasible) and the
    bench. Radii beyond the expanded beam's 1/e^2 radius are skipped (the pupil cannot be lit)."""
    base = par.base
    rows = []
    exps = par.expanders or ("",)
    for i, name in enumerate(exps):
        p = par.from_lens(lens, base)
        names = list(par.names)
        if "bench.expander" in names:
            p[names.index("bench.expander")] = float(i)
        for r in radii_mm:
            if "bench.pupil_radius_mm" in names:
                j = names.index("bench.pupil_radius_mm")
                if not par.lo[j] <= r <= par.hi[j]:
                    continue
                p[j] = r
            try:
                b = par.to_bench(p, base)
            except LensforgeError:
                continue
            if b.sensor.pupil_radius_mm >= 0.5 * b.laser.beam_diameter_mm:
                continue
            sb = b if quadrature is None else b.replace(sensor={"subaperture_quadrature": int(quadrature)})
            f = check_design(sb, lens, constraints, fast=True)
            value = np.inf
            if f.ok:
                S, z0, _ = sensitivity_from_model(f.model, raise_invalid=False)
                if S is not None:
                    value = criterion_value(criterion, metrics_from_S(S, f.model.noise_cov, sb, z0, weights), weights)
            rows.append({"expander": name or "none", "pupil_radius_mm": float(b.sensor.pupil_radius_mm),
                         "feasible": bool(np.isfinite(value)), "value": float(value) if np.isfinite(value) else None,
                         "bench": b})
            if "bench.pupil_radius_mm" not in names:
                break
    for r in rows:
        if r["value"] is None:
            r["value"] = np.inf
    return rows


def _selfcal_design(bench, model, method, seed, weights, free, bounds, constraints, max_evals, start, progress,
                    template, bench_vars, lens_evals, search_quadrature, spec, rounds) -> Design:
    """criterion DS: the A-optimal design (and bench), then rounds of plan step + lens step."""
    import dataclasses

    if spec is None:
        raise ConfigError("criterion DS: needs a SelfCalSpec (the tolerance model of the printed lens); "
                          "CLI: --selfcal-tolerances")
    if int(rounds) < 1:
        raise ConfigError(f"selfcal_rounds: need at least 1, got {rounds!r}")
    codesign = bench_vars is not None and bool(bench_vars.free)
    d = optimize_design(bench, model=model, method=method, seed=seed, criterion="A", weights=weights, free=free,
                        bounds=bounds, constraints=constraints, start=start, progress=progress, template=template,
                        bench_vars=bench_vars, lens_evals=lens_evals, search_quadrature=search_quadrature,
                        max_evals=None if codesign else lens_evals)
    q = 1 if search_quadrature is None else int(search_quadrature)  # the DS lens steps search on 1 point/lenslet
    first_value, first_summary = None, None
    log = []
    lens_par = parameterisation(model, free=free, bounds=bounds, template=template)
    for r in range(int(rounds)):
        poses = plan_for(d.bench, d.lens, spec)
        sp = spec.with_poses(poses)
        value, summary = selfcal_value(d.bench, d.lens, sp)
        if first_value is None:
            first_value, first_summary = value, summary
        p0 = np.clip([d.parameters[n] for n in lens_par.names], lens_par.lo, lens_par.hi)
        nxt = optimize_design(d.bench, model=model, method=method, seed=seed + r + 1, criterion="DS",
                              weights=weights, free=free, bounds=bounds, constraints=constraints,
                              max_evals=max_evals or 40, start=p0, progress=progress, template=template,
                              search_quadrature=q, selfcal=sp, sigma0=0.03)
        v_new, s_new = selfcal_value(nxt.bench, nxt.lens, sp)
        log.append({"round": r + 1, "plan_value": value, "lens_value": v_new,
                    "Z_translation_mm": s_new["Z_translation_mm"], "Z_rotation_deg": s_new["Z_rotation_deg"],
                    "Z_translation_known_lens_mm": s_new["Z_translation_known_lens_mm"],
                    "Z_rotation_known_lens_deg": s_new["Z_rotation_known_lens_deg"], "n_evals": nxt.n_evals})
        if v_new < value:
            d = nxt
    plan = plan_for(d.bench, d.lens, spec)
    v_final, s_final = selfcal_value(d.bench, d.lens, spec.with_poses(plan))
    settings = {**d.settings, "selfcal": {"rounds": log, "plan": plan.tolist(), "value": v_final,
                                          "start_value": first_value, "summary": s_final,
                                          "start_summary": first_summary, "n_poses": spec.n_poses,
                                          "plan_mm": spec.plan_mm, "plan_rad": spec.plan_rad}}
    return dataclasses.replace(d, criterion="DS", settings=settings,
                               lens=d.lens.replace(name=d.lens.name.replace(", A,", ", DS,")))


def check_method(method: str) -> str:
    key = str(method).strip().lower()
    key = _ALIASES.get(key, key)
    if key not in OPTIMISERS:
        raise ConfigError(f"method: unknown optimiser {method!r}; use one of {', '.join(METHODS)}")
    return key


# --- public entry point ----------------------------------------------------------

def optimize_design(bench: Bench | None = None, model: str = "zernike", method: str = "cmaes", seed: int = 0,
                    criterion: str = "A", weights: Sequence[float] = (1.0, 1.0),
                    free: str | Sequence[str] | None = None,
                    bounds: str | dict[str, tuple[float, float]] | None = None,
                    constraints: Constraints | None = None, max_evals: int | None = None,
                    start: str | np.ndarray = "paper",
                    n_starts: int = 1, particles: int = 30, population: int | None = None, sigma0: float = 0.1,
                    ftol: float | None = None, time_limit_s: float | None = None, progress: bool = True,
                    template: Lens | None = None, robust: RobustSpec | None = None,
                    bench_vars: BenchVariables | None = None, lens_evals: int | None = None,
                    search_quadrature: int | None = None, start_lens: Lens | None = None,
                    start_bench: Bench | None = None, selfcal: SelfCalSpec | None = None,
                    selfcal_rounds: int = 2) -> Design:
    """Optimise a lens of ``model`` on ``bench`` and return the feasible :class:`Design`.

    Co-design (``bench_vars`` with free variables, ``bench_vars.BenchVariables``): the bench
    around the lens is designed too. Three steps: (1) the lens alone on ``bench``
    (``lens_evals`` evaluations, default CODESIGN_LENS_EVALS); (2) a scan of the expander
    catalogue and pupil radii (``bench_scan``) with that lens, the best feasible bench by
    the criterion; (3) lens and bench variables jointly from there (``max_evals``, default
    CODESIGN_EVALS). Steps 1-3 search with ``search_quadrature`` points per lenslet side
    (default 1 when co-designing); the returned design is checked and scored on the full
    bench. The design's ``bench`` is the co-designed bench, its ``settings.codesign`` says
    how it was reached.

    Self-calibration criterion (``criterion='DS'``, ``selfcal`` a :class:`SelfCalSpec` with the
    tolerance model): first the A-optimal design (with its bench, if ``bench_vars`` are free),
    then ``selfcal_rounds`` rounds of a plan step (``selfcal.plan_for``: the Ds-optimal plan for
    the current lens) and a lens step (the lens's DS over that plan, ``max_evals`` evaluations,
    the bench kept); ``settings.selfcal`` holds the plan and the bound per round.

    Parameters
    ----------
    bench : Bench, optional
        Default ``Bench.default()``.
    model : str
        'polynomial', 'extended_polynomial', 'zernike' or 'conic'.
    method : str
        'nelder-mead', 'pso', 'ga' or 'cmaes' (the registry ``METHODS``).
    seed : int
        Same seed, same result.
    criterion : str
        'J' (paper), 'D', 'A', or 'DS' (self-calibration, needs ``selfcal``).
    weights : sequence of float
        (w1, w2) of J.
    free, bounds : str, sequence or dict, optional
        Free parameters and their search box (see ``design.parameterisation``).
    constraints : Constraints, optional
        Thickness, TIR, lit pupil over the working range.
    max_evals : int, optional
        Cost evaluations (default per method, DEFAULT_MAX_EVALS).
    start : str or numpy.ndarray
        'paper' (the template lens's vector if feasible, else random), 'random' or a
        parameter vector.
    n_starts : int
        Nelder-Mead starts (the first from ``start``, the rest random feasible).
    particles : int
        PSO swarm size.
    population : int, optional
        GA and CMA-ES population.
    sigma0 : float
        CMA-ES step in the unit box.
    ftol : float, optional
        Relative stopping tolerance on the cost.
    time_limit_s : float, optional
        Wall-clock limit, s.
    progress : bool
        Progress bar on stderr.
    template : Lens, optional
        The lens whose fixed parameters the design keeps (default: the paper's lens of ``model``).
    robust : RobustSpec, optional
        Minimise the statistic of the criterion over as-built draws (common random
        numbers) instead of the nominal criterion; the design's ``robust`` record holds
        the spec and the returned lens's robust cost.
    bench_vars : BenchVariables, optional
        Bench variables designed with the lens (co-design, see above); None or none free:
        the bench is kept.
    lens_evals : int, optional
        Co-design: evaluations of the lens-only first step (default CODESIGN_LENS_EVALS).
    search_quadrature : int, optional
        Sub-aperture points per lenslet side during the search (default: the bench's; 1
        when co-designing); the result is always scored on the bench's own rule.
    start_lens, start_bench : Lens, Bench, optional
        Where a 'paper'/'template' start begins (internal to the co-design steps).
    selfcal : SelfCalSpec, optional
        Criterion 'DS': the tolerance model, plan box and robot of the self-calibration bound.
    selfcal_rounds : int
        Criterion 'DS': plan step + lens step rounds.

    Returns
    -------
    Design
        The best feasible design with its metrics and provenance.

    Raises
    ------
    ConfigError
        Bad settings.
    DesignError
        An infeasible problem.
    """
    bench = bench or Bench.default()
    meth = check_method(method)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed: expected an integer >= 0, got {seed!r}")
    seed = int(seed)
    crit = check_criterion(criterion)
    try:
        weights = tuple(float(w) for w in weights)
    except (TypeError, ValueError):
        raise ConfigError(f"weights: expected two numbers (w1, w2), got {weights!r}") from None
    if len(weights) != 2 or not all(np.isfinite(weights)) or min(weights) < 0 or max(weights) <= 0:
        raise ConfigError(f"weights: expected two finite numbers >= 0, not both 0, got {weights!r}")
    par = parameterisation(model, free=free, bounds=bounds, template=template)
    if check_criterion(criterion) == "DS" and (selfcal is None or selfcal.poses is None):
        return _selfcal_design(bench, model, method, seed, weights, free, bounds, constraints, max_evals, start,
                               progress, template, bench_vars, lens_evals, search_quadrature, selfcal, selfcal_rounds)
    codesign = None
    if bench_vars is not None and bench_vars.free:
        if robust is not None:
            raise ConfigError("robust: a tolerance-robust design keeps its bench; use --bench-free none with --robust")
        q = 1 if search_quadrature is None else int(search_quadrature)
        n1 = CODESIGN_LENS_EVALS if lens_evals is None else int(lens_evals)
        first = optimize_design(bench, model=model, method=method, seed=seed, criterion=criterion, weights=weights,
                                free=free, bounds=bounds, constraints=constraints, max_evals=n1, start=start,
                                n_starts=n_starts, particles=particles, population=population, sigma0=sigma0,
                                ftol=ftol, time_limit_s=time_limit_s, progress=progress, template=template,
                                search_quadrature=q)
        par = CoDesignParameterisation.build(par, bench_vars, bench)
        scan = bench_scan(par, first.lens, constraints or Constraints(), criterion=check_criterion(criterion),
                          weights=weights, quadrature=q)
        best = min((r for r in scan if r["feasible"]), key=lambda r: r["value"], default=None)
        start_lens, start_bench = first.lens, (best["bench"] if best is not None else bench)
        search_quadrature = q
        codesign = {"lens_evals": first.n_evals, "lens_wall_time_s": first.wall_time_s,
                    "lens_step_metrics": {k: first.metrics.get(k) for k in ("crlb_std", "criterion_value")},
                    "scan": [{k: r[k] for k in ("expander", "pupil_radius_mm", "feasible", "value")} for r in scan],
                    "variables": bench_vars.to_dict(), "search_quadrature": q}
        if max_evals is None:
            max_evals = CODESIGN_EVALS
        if start == "paper":
            start = "template"
    evals = DEFAULT_MAX_EVALS[meth] if max_evals is None else int(max_evals)
    if evals < par.n + 2:
        raise ConfigError(f"max_evals: {evals} is too small for {par.n} free parameters; use at least {par.n + 2}")
    if int(n_starts) < 1 or int(particles) < 2 or (population is not None and int(population) < 4):
        raise ConfigError("n_starts must be >= 1, particles >= 2 and population >= 4")
    if time_limit_s is not None and not time_limit_s > 0:
        raise ConfigError(f"time_limit_s: must be > 0 seconds, got {time_limit_s}")
    constraints = constraints or Constraints()
    if robust is not None and not isinstance(robust, RobustSpec):
        raise ConfigError(f"robust: expected a RobustSpec(tolerances, n_samples, seed, statistic), got {robust!r}")
    rng = np.random.default_rng(seed)
    label = f"{meth} {par.model} ({crit}{', robust' if robust is not None else ''})"
    t0 = time.perf_counter()
    with progress_bar(evals, label, enabled=progress) as bar:
        prob = DesignProblem(bench, par, crit, weights, constraints, evals, time_limit_s, bar, robust, label,
                             search_quadrature, selfcal)
        if start_bench is not None and isinstance(par, CoDesignParameterisation):
            u0, start_kind = _start_point(prob, par.from_lens(start_lens or par.template, start_bench)
                                          if start in ("template", "paper") else start, rng)
            if start_kind == "given":
                start_kind = "lens step + bench scan"
        else:
            u0, start_kind = _start_point(prob, start, rng, start_lens)
        p_start = par.from_unit(u0)
        start_cost = prob(u0)  # counted, so the start is always a candidate
        opts = {"particles": particles, "population": population, "sigma0": sigma0, "n_starts": int(n_starts)}
        if ftol is not None:
            opts["ftol"] = ftol
        with contextlib.redirect_stdout(sys.stderr), _global_numpy_seed(seed):
            info = OPTIMISERS[meth].run(prob, u0, rng, seed, opts)
        prob.record(final=True)
    wall = time.perf_counter() - t0
    if prob.best_u is None or prob.best_cost >= INFEASIBLE:
        raise DesignError(f"{meth} found no feasible design in {prob.n_evals} evaluations; "
                          "widen the bounds or relax the constraints")
    # the returned design passes the full check; fall back through the next-best
    # feasible points if the optimiser's best fails it (e.g. Lens.validate)
    first_fail = None
    for cost, _, u in sorted(prob.candidates, key=lambda c: (c[0], c[1]))[:_N_CANDIDATES]:
        p_best = par.from_unit(u)
        lens = par.to_lens(p_best).replace(
            name=f"lensforge {par.model} ({meth}, {crit}{', robust' if robust is not None else ''}"
                 f"{', co-designed bench' if codesign else ''}, seed {seed})")
        bench_best = prob.bench_of(p_best)
        feas = check_design(bench_best, lens, constraints, prob.poses, fast=False)
        if feas.ok:
            break
        first_fail = first_fail or feas
    else:
        require_feasible(first_fail, f"optimised {par.model} design")
    bench = bench_best
    S, z0, _ = sensitivity_from_model(feas.model)
    m = metrics_from_S(S, feas.model.noise_cov, bench, z0, weights)
    nominal_value = selfcal_value(bench, lens, selfcal)[0] if crit == "DS" else criterion_value(crit, m, weights)
    robust_record = None
    if robust is not None:
        rv = robust_value(bench, lens, robust, crit, weights, nominal=nominal_value)
        robust_record = {**robust.to_dict(), "criterion": crit, **rv.to_dict()}
    settings = {"max_evals": evals, "n_starts": int(n_starts), "ftol": ftol, "time_limit_s": time_limit_s, **info}
    if search_quadrature is not None:
        settings["search_quadrature"] = int(search_quadrature)
    if codesign is not None:
        settings["codesign"] = codesign
        wall += codesign["lens_wall_time_s"]
    return Design(
        lens=lens, bench=bench, model=par.model, free=par.names,
        parameters={n: float(v) for n, v in zip(par.names, p_best)}, bounds=par.bounds_dict(),
        criterion=crit, weights=weights, constraints=constraints.to_dict(), feasibility=feas.to_dict(),
        metrics={**metrics_dict(m, weights), "criterion_value": nominal_value},
        method=meth, seed=seed, settings=settings,
        start={"kind": start_kind, "parameters": [float(v) for v in p_start], "cost": float(start_cost)},
        history=prob.history, n_evals=prob.n_evals, wall_time_s=round(wall, 3), labels=par.labels(),
        robust=robust_record,
    )
