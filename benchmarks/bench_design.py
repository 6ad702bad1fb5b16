"""Design benchmark: optimiser wall times and the Table-1 analogue on the default bench.

    .venv/bin/python benchmarks/bench_design.py [--budget 1500] [--quick] [--out exports/bench_design]

1. Nelder-Mead design of the Zernike model with the default settings (goal <= 30 s).
2. PSO with 30 particles x 100 iterations on the Zernike model (goal <= 2 min).
3. Table-1 analogue: the paper's spherical lens and three parameter vectors, and
   lensforge's optimum per model and optimiser (same evaluation budget each): rank,
   kappa, sigma_min, J, CRLB std per DOF (um, urad), evaluations, seconds.
Writes the designs and a JSON summary under --out; the table goes to stdout.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import lensforge as lf  # noqa: E402
from lensforge.design.compare import compare_rows  # noqa: E402
from lensforge.design.design_file import save_design  # noqa: E402
from lensforge.design.optimize import METHODS, optimize_design  # noqa: E402
from lensforge.fileio import write_atomic  # noqa: E402

MODELS = ("polynomial", "extended_polynomial", "zernike")


def _row_text(r: dict) -> str:
    std = r["crlb_std"] or {}
    keys = ["tx_um", "ty_um", "tz_um", "rx_urad", "ry_urad", "rz_urad"]

    def f(v, spec=".3g"):
        return "-" if v is None else format(v, spec)

    return (f"{r['label']:<34} {f(r['rank'], 'd'):>4} {f(r['kappa'], '.4g'):>10} {f(r['sigma_min'], '.4g'):>10} "
            f"{f(r['J'], '.5g'):>11} " + " ".join(f"{f(std.get(k)):>8}" for k in keys)
            + f" {('yes' if r['feasible'] else 'no'):>4} {f(r['n_evals'], 'd'):>6} {f(r['wall_time_s'], '.1f'):>7}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget", type=int, default=1500, help="evaluations per optimiser run in the table")
    ap.add_argument("--quick", action="store_true", help="tiny budgets (smoke test)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="exports/bench_design")
    a = ap.parse_args(argv)
    out = Path(a.out)
    bench = lf.Bench.default()
    budget = 60 if a.quick else a.budget
    lf.metrics(bench, lf.paper_lens("zernike"))  # numba compile / cache load outside the timings
    summary = {"cpu_count": os.cpu_count(), "budget": budget, "seed": a.seed}

    t = time.perf_counter()
    nm = optimize_design(bench, model="zernike", method="nelder-mead", seed=a.seed, progress=False,
                         max_evals=60 if a.quick else None)
    summary["nelder_mead_zernike"] = {"wall_s": time.perf_counter() - t, "n_evals": nm.n_evals, "J": nm.metrics["J"]}
    print(f"Nelder-Mead, zernike, default settings: {summary['nelder_mead_zernike']['wall_s']:.1f} s, "
          f"{nm.n_evals} evaluations, J = {nm.metrics['J']:.5g} (goal <= 30 s)", flush=True)

    iters = 3 if a.quick else 100
    t = time.perf_counter()
    pso = optimize_design(bench, model="zernike", method="pso", seed=a.seed, progress=False, particles=30,
                          max_evals=30 * iters)
    summary["pso_zernike_30x100"] = {"wall_s": time.perf_counter() - t, "n_evals": pso.n_evals, "J": pso.metrics["J"]}
    print(f"PSO 30 particles x {iters} iterations, zernike: {summary['pso_zernike_30x100']['wall_s']:.1f} s, "
          f"{pso.n_evals} evaluations, J = {pso.metrics['J']:.5g} (goal <= 120 s)", flush=True)

    entries = ["paper:spherical", "paper:polynomial", "paper:extended_polynomial", "paper:zernike"]
    designs = {}
    for model in MODELS:
        for meth in METHODS:
            d = optimize_design(bench, model=model, method=meth, seed=a.seed, max_evals=budget, progress=False,
                                n_starts=3 if meth == "nelder-mead" else 1)
            save_design(d, out / f"{model}_{meth}.json")
            designs[(model, meth)] = d
            entries.append(d)
            print(f"  {model:<20} {meth:<12} J = {d.metrics['J']:.5g}  ({d.n_evals} evals, {d.wall_time_s:.1f} s)",
                  flush=True)
    rows = compare_rows(entries, bench)
    summary["table"] = rows
    print("\nTable-1 analogue on the default bench (scaled, whitened S; CRLB std in um / urad; "
          "feasible = thickness, TIR and +-1 mm / +-1 deg working range)")
    print(f"{'lens':<34} {'rank':>4} {'kappa':>10} {'sigma_min':>10} {'J':>11} " +
          " ".join(f"{k:>8}" for k in ["tx um", "ty um", "tz um", "rx urad", "ry urad", "rz urad"]) +
          f" {'feas':>4} {'evals':>6} {'s':>7}")
    for r in rows:
        print(_row_text(r))
    print("\nbest optimiser per model (lowest J):")
    for model in MODELS:
        best = min(METHODS, key=lambda m: designs[(model, m)].metrics["J"])
        d = designs[(model, best)]
        print(f"  {model:<20} {best:<12} J = {d.metrics['J']:.5g} ({d.n_evals} evals, {d.wall_time_s:.1f} s)")
    write_atomic(out / "summary.json", json.dumps(summary, indent=2, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
