"""``lensforge design``, ``lensforge plot`` and ``lensforge compare``."""

from __future__ import annotations

import math
from pathlib import Path
from typing import List, Optional

import typer
from rich.console import Console

from ..errors import ConfigError
from ..fileio import check_output, staged_dir
from ._common import bench_arg, check_seed, emit_json, info, load_bench_arg


def _weights(text: str) -> tuple[float, float]:
    parts = [s for s in str(text).replace(";", ",").split(",") if s.strip()]
    try:
        w = tuple(float(s) for s in parts)
    except ValueError:
        raise ConfigError(f"--weights: expected 'w1,w2' (e.g. 1,1), got {text!r}") from None
    if len(w) != 2:
        raise ConfigError(f"--weights: expected two numbers 'w1,w2', got {text!r}")
    return w


def design(
    model: str = typer.Option("zernike", "--model", help="polynomial | extended_polynomial | zernike | conic"),
    method: str = typer.Option("cmaes", "--method", help="optimiser: cmaes (CMA-ES, default) | nelder-mead | pso | ga (the registry in design/optimize.py)"),
    seed: int = typer.Option(0, "--seed", help="random seed (same seed, same design)"),
    criterion: str = typer.Option("A", "--criterion", help="A (A-optimal: smallest sum of CRLB variances in pose-scale units) | D (D-optimal) | J (the paper's kappa + 1/sigma_min) | DS (self-calibration: the joint calibration's bound on Z over a plan designed with the lens, the printed lens a nuisance; slow: minutes per round)"),
    weights: str = typer.Option("1,1", "--weights", help="w1,w2 of J = w1*kappa + w2/sigma_min"),
    free: Optional[str] = typer.Option(None, "--free", help="which lens parameters the optimiser may change: 'full' (default for zernike: thickness, both base curvatures, Noll 1-8 per surface), 'paper' (the paper's set), 'base' (zernike only: paper set + base curvatures), or a comma list of names such as thickness,front.coefficients[3]; default: full for zernike, paper for the other models"),
    bounds: Optional[str] = typer.Option(None, "--bounds", help="overrides 'name=lo:hi,...', e.g. thickness=4:8"),
    max_evals: Optional[int] = typer.Option(None, "--max-evals", help="cost evaluations (default per method)"),
    start: str = typer.Option("paper", "--start", help="paper (template vector if feasible) | random"),
    starts: int = typer.Option(1, "--starts", help="Nelder-Mead multi-start count"),
    particles: int = typer.Option(30, "--particles", help="PSO swarm size"),
    population: Optional[int] = typer.Option(None, "--population", help="GA / CMA-ES population"),
    sigma0: float = typer.Option(0.1, "--sigma0", help="CMA-ES first step in the unit box of the parameters (a "
                                 "first generation with no feasible lens narrows it 10x, down to 0.001); small "
                                 "values search a thin feasible region, e.g. 0.01 with --spot-assignment fixed"),
    min_thickness: float = typer.Option(1.0, "--min-thickness", help="minimum centre and edge thickness (mm)"),
    range_mm: float = typer.Option(1.0, "--range-mm", help="working range, translation half-width (mm)"),
    range_deg: float = typer.Option(1.0, "--range-deg", help="working range, rotation half-width (deg)"),
    max_slope: float = typer.Option(50.0, "--max-slope", help="steepest surface slope in the clear aperture (deg; 90 = off)"),
    require_observable: bool = typer.Option(False, "--require-observable",
                                            help="constraint: every pose DOF observable (predicted 1-sigma within "
                                                 "the bench's pose scale, DESIGN.md)"),
    plan_mm: float = typer.Option(1.5, "--plan-mm", help="calibration plan's box, translation half-width (mm): the "
                                  "sensor range and slope bound also hold there, and lensforge plan draws from the "
                                  "box the design records; 0 = off"),
    plan_deg: float = typer.Option(5.0, "--plan-deg", help="calibration plan's box, rotation half-width (deg)"),
    time_limit: Optional[float] = typer.Option(None, "--time-limit", help="wall-clock limit (s)"),
    bench: Optional[str] = typer.Option(None, "--bench", help="bench TOML, or 'paper' for the paper's bench (built-in "
                                        "default: the paper's laser and sensor, with the bench variables designed)"),
    bench_free: Optional[str] = typer.Option(None, "--bench-free", help="bench variables designed with the lens: 'all' "
                                             "(expander from design/expanders.py, pupil radius and centre, lens-sensor "
                                             "distance), 'none', or a comma list of expander,pupil_radius,pupil_center,"
                                             "distance; default: all without --bench, none with it"),
    spot_assignment: Optional[str] = typer.Option(None, "--spot-assignment", help="override the bench's "
                                                  "sensor.spot_assignment: tracking | fixed (lenslet-bound windows) | none"),
    lens_evals: Optional[int] = typer.Option(None, "--lens-evals", help="co-design: evaluations of the first, lens-only "
                                             "step (default 300); --max-evals sets the joint step's (default 160)"),
    robust: Optional[Path] = typer.Option(None, "--robust", help="tolerance TOML: minimise the expected criterion over as-built draws (tolerance-robust design)"),
    robust_samples: int = typer.Option(8, "--robust-samples", help="as-built draws per candidate (with --robust)"),
    robust_seed: int = typer.Option(0, "--robust-seed", help="seed of the as-built draws, common to all candidates (with --robust)"),
    robust_statistic: str = typer.Option("mean", "--robust-statistic", help="mean | max | mean+std of the criterion over the draws (with --robust)"),
    selfcal_tolerances: str = typer.Option("default", "--selfcal-tolerances", help="criterion DS: tolerance TOML of the printed lens ('default': the package's)"),
    selfcal_rounds: int = typer.Option(2, "--selfcal-rounds", help="criterion DS: plan step + lens step rounds"),
    selfcal_poses: int = typer.Option(24, "--selfcal-poses", help="criterion DS: poses of the plan designed with the lens"),
    out: Path = typer.Option(Path("exports/design.json"), "-o", "--out", help="design JSON to write"),
    no_progress: bool = typer.Option(False, "--no-progress", help="no progress bar"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable summary on stdout"),
) -> None:
    """Optimise a freeform lens and write its design file."""
    from ..design.bench_vars import bench_label, bench_summary
    from ..design.compare import compare_rows, feasibility_notes, format_table
    from ..design.constraints import Constraints
    from ..design.design_file import save_design
    from ..design.optimize import optimize_design
    from ..design.bench_vars import BenchVariables
    from ..design.robust import RobustSpec
    from ..asbuilt.tolerances import load_tolerances

    b = load_bench_arg(bench)
    if spot_assignment is not None:
        b = b.replace(sensor={"spot_assignment": spot_assignment.strip().lower()})
    bvars = BenchVariables.parse(bench_free or ("none" if bench is not None or robust is not None else "all"))
    spec = None
    if robust is not None:

        spec = RobustSpec(load_tolerances(robust), n_samples=robust_samples, seed=robust_seed,
                          statistic=robust_statistic)
    check_seed(seed)
    check_seed(robust_seed, "--robust-seed")
    selfcal = None
    if criterion.strip().upper() == "DS":
        from ..asbuilt.tolerances import DEFAULT_TOLERANCES_FILE
        from ..design.selfcal import SelfCalSpec

        from ..calibration.plausibility import check_poses_count

        check_poses_count(selfcal_poses, "--selfcal-poses")
        selfcal = SelfCalSpec(load_tolerances(DEFAULT_TOLERANCES_FILE if selfcal_tolerances == "default"
                                              else selfcal_tolerances), n_poses=selfcal_poses,
                              plan_mm=plan_mm, plan_rad=math.radians(plan_deg))
    if not (math.isfinite(sigma0) and 1e-4 <= sigma0 <= 1.0):
        raise ConfigError(f"--sigma0: the CMA-ES step must be in [0.0001, 1] (unit box), got {sigma0!r}")
    check_output(out, folder=False, option="-o/--out")
    cons = Constraints(min_center_mm=min_thickness, min_edge_mm=min_thickness, range_mm=range_mm,
                       range_rad=math.radians(range_deg), max_slope_deg=max_slope, observable=require_observable,
                       plan_mm=plan_mm, plan_rad=math.radians(plan_deg))
    d = optimize_design(b, model=model, method=method, seed=seed, criterion=criterion, weights=_weights(weights),
                        free=free, bounds=bounds, constraints=cons, max_evals=max_evals, start=start,
                        n_starts=starts, particles=particles, population=population, sigma0=sigma0, time_limit_s=time_limit,
                        progress=not no_progress and not json_out, robust=spec, bench_vars=bvars,
                        lens_evals=lens_evals, selfcal=selfcal, selfcal_rounds=selfcal_rounds)
    path = save_design(d, out)
    if json_out:
        emit_json({"schema_version": 1, "design": str(path), "model": d.model, "method": d.method, "seed": d.seed,
                   "criterion": d.criterion, "n_evals": d.n_evals, "wall_time_s": d.wall_time_s,
                   "parameters": d.parameters, "metrics": d.metrics, "bench": bench_summary(d.bench),
                   "robust": None if d.robust is None else
                   {k: d.robust[k] for k in ("n_samples", "seed", "statistic", "cost", "mean", "nominal", "n_failed")}})
    else:
        info(f"wrote {path}  ({d.n_evals} evaluations, {d.wall_time_s:.1f} s)")
        info(f"bench: {bench_label(d.bench)}" + ("  (co-designed)" if bvars.free else ""))
        sc = d.settings.get("selfcal")
        if sc:
            s0, s1 = sc["start_summary"], sc["summary"]
            info(f"self-calibration bound on Z over its {sc['n_poses']}-pose plan: "
                 f"{s1['Z_translation_mm'] * 1e3:.1f} um / {s1['Z_rotation_deg'] * 1e3:.2f} mdeg with the printed lens "
                 f"free ({s1['Z_translation_known_lens_mm'] * 1e3:.1f} um / {s1['Z_rotation_known_lens_deg'] * 1e3:.2f} "
                 f"mdeg known); the A-optimal start: {s0['Z_translation_mm'] * 1e3:.1f} um / "
                 f"{s0['Z_rotation_deg'] * 1e3:.2f} mdeg")
        if d.robust is not None:
            r = d.robust
            info(f"robust {d.criterion}: {r['statistic']} {r['cost']:.5g} over {r['n_samples']} as-built draws "
                 f"(seed {r['seed']}, {r['n_failed']} unmeasurable); nominal {r['nominal']:.5g}")
        rows = compare_rows([d], d.bench, cons)
        Console(stderr=True, width=200).print(format_table(rows))
        for note in feasibility_notes(rows):
            info(f"infeasible: {note}")

def plot(
    design_file: str = typer.Argument(..., help="design JSON (or a paper lens name)"),
    out: Path = typer.Option(Path("exports"), "-o", "--out", help="folder for the PNGs"),
    json_out: bool = typer.Option(False, "--json", help="list the written files on stdout"),
) -> None:
    """Plot a design (PNGs).

    Singular values, sag maps with the lit area, Zernike response per DOF, beam
    footprint over the working range, lenslet slope field, dimensioned cross-section
    and the optimiser's convergence history."""
    from ..design.design_file import load_design
    from ..optics.lens import resolve_lens
    from ..plots.design import design_plots

    r = resolve_lens(design_file)
    obj, stem = ((load_design(design_file), Path(design_file).stem) if "model" in r.data  # a design file:
                 else (r.lens, r.label.replace(" ", "_")))  # its plots show the design's parameters too
    check_output(out, folder=True, need_mb=5)
    with staged_dir(out) as st:  # the three PNGs appear together or not at all
        paths = [st.final(p) for p in design_plots(obj, st.tmp, stem=stem)]
    if json_out:
        emit_json({"schema_version": 1, "files": [str(p) for p in paths]})
    else:
        for p in paths:
            info(f"wrote {p}")

def compare(
    items: List[str] = typer.Argument(..., help="design JSON files and/or paper:NAME (spherical, polynomial, extended_polynomial, zernike)"),
    bench: Optional[str] = typer.Option(None, "--bench", help="bench TOML or 'paper' for all lenses (default: each "
                                        "design on its own bench, paper lenses on the built-in default)"),
    range_mm: float = typer.Option(1.0, "--range-mm", help="working range for the feasibility column (mm)"),
    range_deg: float = typer.Option(1.0, "--range-deg", help="working range for the feasibility column (deg)"),
    json_out: bool = typer.Option(False, "--json", help="machine-readable rows on stdout"),
) -> None:
    """Compare lenses on one bench (Table-1 analogue).

    Metrics, CRLB (um, urad), sensor range and feasibility (explained in words) per lens."""
    from ..design.compare import compare_rows, feasibility_notes, format_table
    from ..design.constraints import Constraints

    b = bench_arg(bench)  # None: each design on its own bench
    rows = compare_rows(items, b, Constraints(range_mm=range_mm, range_rad=math.radians(range_deg)))
    if json_out:
        emit_json({"schema_version": 1, "rows": rows})
    else:
        Console(stderr=True, width=220).print(format_table(rows))
        for note in feasibility_notes(rows):
            info(f"infeasible: {note}")
