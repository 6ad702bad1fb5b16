"""``lensforge study`` (as-built Monte Carlo of the calibration) and ``lensforge budget``
(per-component sensitivity and tolerance budget)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..errors import ConfigError
from ..fileio import check_output, dumps_json, staged_dir, write_atomic
from ._common import MAX_TRIALS, bench_arg, check_seed, emit_json, info


def _tolerances(path):
    """The --tolerances option: a TOML path, "default" (also when omitted) or "none" (noise only)."""
    from ..asbuilt.tolerances import resolve_tolerances

    return resolve_tolerances("default" if path is None else str(path))[0]


def _fmt(v, unit, digits=3):
    return "inf (failures)" if v is None else f"{v:.{digits}g} {unit}"


def _write_json(path: Path, obj) -> None:
    write_atomic(path, dumps_json(obj))


def check_job(design, bench_path, poses: int, calibration: str, workers: int | None, option: str = "--poses",
              plan=None) -> None:
    """Refuse, before any work, a study or budget whose poses are out of range
    (``plausibility.check_poses_count``), that cannot fit in memory (the estimate, per worker
    process, ``plausibility.job_memory_bytes``), or whose --pose-plan leaves hand-eye directions
    unobservable (identical poses, one rotation axis), naming them."""
    import math
    import os

    from ..calibration.plausibility import check_job_memory, check_plan_motion, check_poses_count, job_memory_bytes
    from ..calibration.robot import paper_scene
    from ..optics.lens import resolve_lens

    check_poses_count(poses, option)
    r = resolve_lens(design)
    bench = r.bench_or(bench_arg(bench_path))
    n_lenslets = math.pi * bench.sensor.pupil_radius_mm ** 2 / bench.sensor.pitch_mm ** 2
    order = bench.sensor.zernike_order
    procs = max(1, os.cpu_count() or 1) if workers is None else max(1, workers)
    per = job_memory_bytes(poses, (order + 1) * (order + 2) // 2, int(n_lenslets) + 1,
                           n_params=30 if calibration == "joint" else 0)
    check_job_memory(per * procs, f"a {calibration} calibration of {poses} poses on {procs} worker(s)", option)
    if plan is not None:
        scene = paper_scene(bench.placement.distance_mm)
        check_plan_motion(plan, scene.T_SO_nominal, scene.X, "--pose-plan")


def _check_sizes(seed: int, lenses: int, workers: int | None) -> None:
    check_seed(seed)
    if lenses < 1:
        raise ConfigError(f"--lenses/-n: must be >= 1, got {lenses}")
    if lenses > MAX_TRIALS:
        raise ConfigError(f"--lenses/-n: {lenses} is over the limit of {MAX_TRIALS} as-built lenses per study")
    if workers is not None and not 0 <= workers <= 256:
        raise ConfigError(f"--workers: must be from 0 (in this process) to 256, got {workers}")


def _print_errors(s: dict) -> None:
    q = f"p{s['percentile']:g}"
    for key, unit in (("rotation_deg", "deg"), ("translation_mm", "mm")):
        v = s[key]
        info(f"  Z {key.split('_')[0]}: median {_fmt(v['median'], unit)}, {q} {_fmt(v[q], unit)}, "
             f"max {_fmt(v['max'], unit)}")


def study_cmd(
    design: str = typer.Argument(..., help="design JSON (key \"lens\") or a paper lens name"),
    tolerances: Optional[str] = typer.Option(None, "--tolerances", "-t", help="tolerance TOML, 'default' (the shipped one, also when omitted) or 'none' (noise only)"),
    lenses: int = typer.Option(1000, "--lenses", "-n", help="number of as-built lenses"),
    poses: int = typer.Option(24, "--poses", help="calibration poses per lens"),
    pose_plan: Path = typer.Option(None, "--pose-plan", help="JSON {\"poses\": [[tx, ty, tz, rx, ry, rz], ...]} "
                                   "(mm, rad, lens pose relative to nominal; e.g. a joint design) or the plan.json of lensforge plan instead of "
                                   "--poses random ones"),
    seed: int = typer.Option(0, "--seed", help="study seed (trial i uses SeedSequence(seed) child i)"),
    workers: int = typer.Option(None, "--workers", help="local Dask worker processes (0 = in this process; "
                                                        "default: all cores)"),
    scheduler: str = typer.Option(None, "--scheduler", help="address of an existing Dask scheduler"),
    resume: bool = typer.Option(False, "--resume", help="continue the study stored in the output folder"),
    calibration: str = typer.Option("joint", "--calibration", help="two-stage (per-pose estimates, then AX = ZB) "
                                    "or joint (X, Z and the as-built lens from the raw Zernikes; both are stored)"),
    bench: Path = typer.Option(None, "--bench", help="bench TOML (default: the design's, else built-in)"),
    target_mm: float = typer.Option(0.1, "--target-mm", help="Z translation target (mm)"),
    target_deg: float = typer.Option(0.01, "--target-deg", help="Z rotation target (deg)"),
    out: Path = typer.Option(Path("exports/study"), "--out", "-o", help="output folder"),
    json_out: bool = typer.Option(False, "--json", help="summary on stdout"),
    no_progress: bool = typer.Option(False, "--no-progress", help="no progress bar"),
) -> None:
    """As-built Monte Carlo of the calibration.

    Calibrates simulated as-built lenses; writes a resumable store, summary.json and PNGs
    (Z error in mm and deg)."""
    from ..verification.statistics import format_counts
    from ..verification.study import StudyConfig, load_plan, verify
    from ..plots.study import plot_error_histograms

    tol = _tolerances(tolerances)
    plan = load_plan(pose_plan) if pose_plan is not None else None
    if plan is not None:
        poses = len(plan)
    _check_sizes(seed, lenses, workers)
    check_job(design, bench, poses, calibration, workers, "--pose-plan" if plan is not None else "--poses", plan)
    cfg = StudyConfig(n_poses=poses, target_mm=target_mm, target_deg=target_deg, calibration=calibration)
    b = bench_arg(str(bench)) if bench else None
    check_output(out, folder=True, need_mb=5 + lenses * 2e-3)
    res = verify(design, tol, lenses, seed, b, config=cfg, workers=workers, scheduler=scheduler,
                 store=out / "store.sqlite", resume=resume, progress=not (no_progress or json_out), plan=plan)
    d = res.to_dict()
    d["design"] = str(design)
    d["tolerances"] = res.config["tolerances"]
    with staged_dir(out) as st:  # summary and plot together or not at all (the store is already durable)
        _write_json(st.tmp / "summary.json", d)
        plot_error_histograms(res.rot_err_deg, res.trans_err_mm, st.tmp / "errors.png", target_deg, target_mm,
                              summary=res.summary,
                              title=f"{design}: Z error over {res.n_lenses} as-built lenses")
    s = res.summary
    info(f"{s['n_ok']} of {s['n_lenses']} {calibration} calibrations succeeded ({res.stats.n_resumed} resumed, "
         f"{res.stats.wall_s:.1f} s, {res.stats.mode})")
    _print_errors(s)
    info(f"  target {target_mm} mm / {target_deg} deg at p{s['percentile']:g}: "
         f"{'met' if s['meets_target'] else 'NOT met'}")
    info(f"  {format_counts(s)}")
    if s["failures"]:
        info(f"  failures: {s['failures']}")
    if calibration == "joint":
        j = s["joint"]
        if j["nees_dof"] is not None:
            info(f"  joint: NEES/dof of Z {j['nees_dof']:.2f}, chi2 mismatch flagged in {j['mismatch_rate']:.1%} "
                 f"of lenses, median {j['n_identifiable_median']:g} identifiable lens directions")
        info("two-stage calibration on the same data:")
        _print_errors(d["two_stage_summary"])
    info(f"wrote {out / 'store.sqlite'}, {out / 'summary.json'}, {out / 'errors.png'}")
    if json_out:
        emit_json(d)

def budget_advice(bud) -> list[str]:
    """What the budget means, in words: the limiting tolerance, or why there is none and what to change."""
    p = f"p{bud.percentile:g}"
    if bud.noise_ratio is None or bud.noise_ratio > 1.0:
        how = ("fails too often" if bud.noise_ratio is None
               else f"misses it {bud.noise_ratio:.3g}x")
        return [f"no tolerance fits: even a perfect lens (noise only) {how} at {p}, so every max scale is 0.",
                "Budget relative to the noise-only error instead (--relative-to-noise 2 allows twice it), "
                "or loosen --target-mm / --target-deg."]
    if bud.dominant is None:
        return ["no tolerance limits the calibration within the searched range (up to 1000x its given size)."]
    return [f"dominant: {bud.dominant} (the tolerance with the smallest max scale; tighten it first)."]


def budget_cmd(
    design: str = typer.Argument(..., help="design JSON (key \"lens\") or a paper lens name"),
    tolerances: Optional[str] = typer.Option(None, "--tolerances", "-t", help="tolerance TOML, 'default' (the shipped one, also when omitted) or 'none' (noise only)"),
    target_mm: float = typer.Option(0.1, "--target-mm", help="Z translation target (mm)"),
    target_deg: float = typer.Option(0.01, "--target-deg", help="Z rotation target (deg)"),
    relative: float = typer.Option(None, "--relative-to-noise",
                                   help="target = this multiple of the noise-only errors instead"),
    lenses: int = typer.Option(64, "--lenses", "-n", help="as-built lenses per evaluation"),
    poses: int = typer.Option(24, "--poses", help="calibration poses per lens"),
    seed: int = typer.Option(0, "--seed", help="seed (the same trials for every evaluation)"),
    workers: int = typer.Option(None, "--workers", help="local Dask workers (0 = in this process)"),
    scheduler: str = typer.Option(None, "--scheduler", help="address of an existing Dask scheduler"),
    bench: Path = typer.Option(None, "--bench", help="bench TOML (default: the design's bench or the built-in default)"),
    out: Path = typer.Option(Path("exports/budget"), "--out", "-o", help="output folder"),
    calibration: str = typer.Option("two-stage", "--calibration",
                                    help="two-stage, or joint (see `lensforge study`; about 10x the CPU per lens)"),
    json_out: bool = typer.Option(False, "--json", help="budget on stdout"),
    no_progress: bool = typer.Option(False, "--no-progress", help="no progress bar"),
) -> None:
    """Tolerance budget for a target calibration accuracy.

    The largest size of each tolerance (alone) whose p95 Z error meets the target,
    and each tolerance's sensitivity."""
    from ..verification.budget import sensitivity_analysis, tolerance_budget
    from ..verification.runner import dask_client
    from ..verification.study import StudyConfig
    from ..plots.study import plot_budget, plot_sensitivity

    tol = _tolerances(tolerances)
    if tol is None:
        raise ConfigError("--tolerances: 'none' leaves nothing to budget; give a tolerance TOML or 'default'")
    _check_sizes(seed, lenses, workers)
    check_job(design, bench, poses, calibration, workers)
    cfg = StudyConfig(n_poses=poses, target_mm=target_mm, target_deg=target_deg, calibration=calibration)
    b = bench_arg(str(bench)) if bench else None
    check_output(out, folder=True, need_mb=10)
    with dask_client(workers, scheduler) as cl:
        kw = dict(config=cfg, client=cl, workers=0, progress=not (no_progress or json_out))
        bud = tolerance_budget(design, tol, target_mm=target_mm, target_deg=target_deg, n_lenses=lenses,
                               seed=seed, bench=b, relative_to_noise=relative, **kw)
        cfg2 = StudyConfig(n_poses=poses, target_mm=bud.target_mm, target_deg=bud.target_deg,
                           calibration=calibration)
        sens = sensitivity_analysis(design, tol, lenses, seed, b, config=cfg2, client=cl, workers=0,
                                    progress=kw["progress"])
    d = {"schema_version": 1, "design": str(design), "calibration": calibration, **bud.to_dict(),
         "sensitivity": [r.to_dict() for r in sens], "tolerances": tol.to_dict()}
    rows = []
    for r in bud.rows:
        rd = r.to_dict()
        rd["max_value_label"] = ("n/a" if r.max_value is None else f"<= {r.max_value:.3g} {r.unit}")
        rows.append(rd)
    with staged_dir(out) as st:  # budget.json and both plots together or not at all
        _write_json(st.tmp / "budget.json", d)
        plot_sensitivity([r.to_dict() for r in sens], st.tmp / "sensitivity.png",
                         title=f"{design}: p95 Z error per tolerance ({lenses} lenses)")
        plot_budget(rows, st.tmp / "budget.png", title=f"{design}: tolerance budget "
                    f"({bud.target_mm:.3g} mm, {bud.target_deg:.3g} deg at p{bud.percentile:g})")
    info(f"budget for {design} ({calibration} calibration): target {bud.target_mm:.3g} mm and {bud.target_deg:.3g} deg at "
         f"p{bud.percentile:g}; noise-only ratio {bud.noise_ratio if bud.noise_ratio is None else round(bud.noise_ratio, 3)}")
    info(f"  {'component':<10} {'given':>12} {'max scale':>10} {'max value':>12}  unit / status")
    for r in bud.rows:
        ms = "-" if r.max_scale is None else f"{r.max_scale:.3g}"
        mv = "-" if r.max_value is None else f"{r.max_value:.3g}"
        gv = "-" if r.given_value is None else f"{r.given_value:.3g}"
        info(f"  {r.component:<10} {gv:>12} {ms:>10} {mv:>12}  {r.unit} / {r.status}")
    for line in budget_advice(bud):
        info(f"  {line}")
    info(f"sensitivity ({lenses} as-built lenses per row, each tolerance alone at its given size):")
    info(f"  {'component':<10} {'p95 Z rotation':>16} {'p95 Z translation':>18} {'failed lenses':>14}")
    for r in sens:
        info(f"  {r.component:<10} {_fmt(r.p95_rot_deg, 'deg'):>16} {_fmt(r.p95_trans_mm, 'mm'):>18} "
             f"{round(r.failure_rate * lenses):>7} of {lenses}")
    info(f"wrote {out / 'budget.json'}, {out / 'budget.png'}, {out / 'sensitivity.png'}")
    if json_out:
        emit_json(d)
