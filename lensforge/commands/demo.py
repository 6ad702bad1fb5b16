"""``lensforge demo``: the main job on the built-in default bench and lenses.

1. evaluate the paper's four lenses on the default bench;
2. design a Zernike freeform lens (CMA-ES, A-optimal, Noll terms 1..8 per surface
   plus base curvatures, seed 0) together with its bench (beam expander, Zernike pupil,
   lens-sensor distance; ``--bench paper`` keeps the paper's bench) and compare it with them;
3. export it as STL + STEP with a printability report;
4. run a small as-built verification study of the designed lens under the default
   tolerances (sanding/polishing, form error, thickness, index, shrinkage, ripple).
Everything lands in the output folder (default ``exports/``).
"""

from __future__ import annotations

import time
from pathlib import Path

import typer
from rich.console import Console

from ..fileio import check_output, staged_dir
from ._common import check_seed
from .evaluate import evaluate_lenses, metrics_table


def demo(
    out: Path = typer.Option(Path("exports"), "-o", "--out", help="output folder"),
    quick: bool = typer.Option(False, "--quick", help="small budgets (smoke test)"),
    seed: int = typer.Option(0, "--seed", help="seed of the design and the study"),
    bench_choice: str = typer.Option("codesign", "--bench", help="codesign (the bench designed with the lens, "
                                     "default) | paper (the paper's 3.5 mm beam and 0.9 mm pupil: the Table-1 analogue)"),
) -> None:
    """The main job: evaluate, design, export, verify.

    Evaluates the paper lenses, designs a Zernike lens, exports it, verifies it as built."""
    import math

    from ..design.bench_vars import BenchVariables, bench_label
    from ..design.constraints import PLAN_BOX_DEG, PLAN_BOX_MM, Constraints
    from ..design.design_file import save_design
    from ..errors import ConfigError
    from ..design.optimize import DEFAULT_MAX_EVALS, optimize_design
    from ..asbuilt.tolerances import DEFAULT_TOLERANCES_FILE, load_tolerances
    from ..optics.bench import Bench
    from ..verification.statistics import format_counts
    from ..verification.study import StudyConfig, verify

    console = Console(stderr=True, width=160)
    check_seed(seed)
    if bench_choice not in ("codesign", "paper"):
        raise ConfigError(f"--bench: expected codesign or paper, got {bench_choice!r}")
    codesign = bench_choice == "codesign"
    check_output(out, folder=True, need_mb=50)
    # everything is made in a temporary folder and moved into OUT at the end: all or nothing
    # (a rerun replaces the previous demo's files, its study store included)
    with staged_dir(out) as st:
        work = st.tmp
        bench = Bench.default()
        t_all = time.perf_counter()

        console.rule("1. The paper's lenses on the default bench")
        rows = evaluate_lenses(["spherical", "polynomial", "extended_polynomial", "zernike"])
        console.print(metrics_table(rows, title="The paper's four lenses (scaled, noise-whitened S)"))

        console.rule("2. Design a Zernike freeform lens (CMA-ES, A-optimal criterion, Noll 1..8 + base curvatures)"
                     + (" with its bench" if codesign else " on the paper's bench"))
        t0 = time.perf_counter()
        cons = Constraints(plan_mm=PLAN_BOX_MM, plan_rad=math.radians(PLAN_BOX_DEG))
        if codesign:
            design = optimize_design(bench, model="zernike", method="cmaes", seed=seed, criterion="A", free="full",
                                     constraints=cons, bench_vars=BenchVariables(), lens_evals=60 if quick else None,
                                     max_evals=30 if quick else None)
        else:
            design = optimize_design(bench, model="zernike", method="cmaes", seed=seed, criterion="A", free="full",
                                     constraints=cons, max_evals=150 if quick else DEFAULT_MAX_EVALS["cmaes"])
        bench = design.bench
        design_path = save_design(design, work / "zernike.json")
        console.print(f"designed in {time.perf_counter() - t0:.1f} s -> {st.final(design_path)}")
        console.print(f"bench: {bench_label(bench)}")
        rows.append({"lens": f"lensforge zernike ({design_path.name})", "description": "",
                     **design.compute_metrics(bench).to_dict(), "bench_label": bench_label(bench)})
        console.print(metrics_table(rows, title="Table 1 analogue: paper lenses vs the lensforge design"))

        console.rule("3. Export for the Form 2 (STL + STEP + printability report)")
        from ..manufacturing.report import export_lens  # imports OCP (~0.8 s): only exports pay it

        rep = export_lens(design.lens, work, "zernike", stl=True, step=True, run_slicer=not quick)
        console.print(st.relocate(rep.summary()))

        console.rule("4. As-built verification: calibration error of printed lenses")
        # an as-built lens costs a few s of joint calibration on the paper's 0.9 mm pupil and about three
        # minutes of CPU on a co-designed 3.5 mm pupil (15x the lenslets, two starts of 10-30 iterations):
        # fewer lenses there, one per core (Dask; the kernels are compiled once, on disk)
        n = (2 if codesign else 4) if quick else (4 if codesign else 20)
        store = work / "demo-study.sqlite"
        res = verify(design, load_tolerances(DEFAULT_TOLERANCES_FILE), n_lenses=n, seed=seed, bench=bench,
                     config=StudyConfig(n_poses=12 if quick else 24, calibration="joint"),
                     workers=0 if quick else None, store=store)
        s = res.summary

        def fmt(d, unit):
            return ", ".join(f"{k} {v:.4g} {unit}" if v is not None else f"{k} n/a" for k, v in d.items())

        console.print(f"{n} as-built lenses x {res.config['config']['n_poses']} calibration poses, "
                      f"failure rate {s['failure_rate']:.0%}; joint calibration through the as-built lens:")
        console.print(f"  sensor pose Z translation error: {fmt(s['translation_mm'], 'mm')}")
        console.print(f"  sensor pose Z rotation error:    {fmt(s['rotation_deg'], 'deg')}")
        two = res.calibration_summary("two-stage")
        p95 = [two[k]["p95"] for k in ("translation_mm", "rotation_deg")]
        if None in p95:  # every two-stage calibration failed its model check (a printed lens is not the design)
            console.print(f"  (two-stage, nominal lens model, same data: {two['n_ok']} of {two['n_lenses']} "
                          "calibrations pass their model check; no p95)")
        else:
            console.print(f"  (two-stage, nominal lens model, same data: translation p95 {p95[0]:.4g} mm, "
                          f"rotation p95 {p95[1]:.4g} deg)")
        console.print(f"  {format_counts(s)}")
        console.print(f"  target {s['target']['translation_mm']} mm / {s['target']['rotation_deg']} deg at the "
                      f"{s['percentile']:.0f}th percentile met: {'yes' if s['meets_target'] else 'no'}")
        for stale in ("demo-study.sqlite-wal", "demo-study.sqlite-shm"):  # a killed earlier demo's journal
            (out / stale).unlink(missing_ok=True)                          # must not meet the new store
    console.print(f"done in {time.perf_counter() - t_all:.0f} s; files in {out}/")
