"""End-to-end session study (issue 11's test at full size): simulate-session then calibrate.

Simulates N seeded bench sessions (seeds SEED .. SEED + N - 1) through as-built lenses
drawn from the tolerance model, on one shared plan (``lensforge plan``'s joint design,
plan seed SEED), calibrates each through the files a real session writes (the joint
method by default) and reports:

- how many sessions have the true Z inside the reported 3-sigma-equivalent ellipsoid
  (6-D NEES <= chi2_6 quantile at 0.9973) and inside 3 sigma on every axis;
- the chi2 calibration: mean chi2/dof, the fraction of p-values below 0.05 / 0.01 / 1e-3
  (expected 5 %, 1 %, 0.1 %) and the KS test of the p-values against U(0, 1);
- the mean NEES / 6 (1 when the reported covariance is honest);
- every session outside, with its NEES, chi2/dof and the joint fit's start.

Per-session outcomes are appended to --jsonl as they finish (an interrupted run keeps
what it did; --resume skips seeds already there). Sessions run on --workers processes.

Run (the figure of the report):
  OPENBLAS_NUM_THREADS=1 nice python benchmarks/bench_session_study.py extended_polynomial \\
      --sessions 200 --seed 1000 --workers 2 --jsonl /tmp/session_study.jsonl
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import time
from pathlib import Path

import numpy as np
from scipy.stats import kstest

from lensforge.calibration.session import load_design_lens, plan
from lensforge.verification.session_sim import NEES_3SIGMA_6DOF, session_outcome, summarise_sessions

_JOB: dict = {}


def _run(seed: int) -> dict:
    j = _JOB
    t = time.process_time()
    o = session_outcome(j["lens"], j["bench"], j["plan"], seed, tolerances=j["tolerances"], method=j["method"])
    return {**o, "cpu_s": time.process_time() - t}


def report(outcomes: list[dict]) -> dict:
    """The study's figures (module docstring) from session_outcome dicts."""
    r = summarise_sessions(outcomes)
    nees, p = r["nees"], r["p_values"]
    inside = nees <= NEES_3SIGMA_6DOF
    return {"sessions": len(outcomes), "failed": r["failed"], "scored": int(len(nees)),
            "inside_3sigma": int(inside.sum()), "inside_3sigma_fraction": r["inside_3sigma"],
            "inside_3sigma_each_axis_fraction": r["inside_3sigma_each_axis"],
            "mean_nees_over_6": float(nees.mean() / 6) if len(nees) else None,
            "median_nees_over_6": float(np.median(nees) / 6) if len(nees) else None,
            "mean_chi2_dof": float(r["chi2_dof"].mean()) if len(nees) else None,
            "p_below": {str(a): float(np.mean(p < a)) for a in (0.05, 0.01, 1e-3)} if len(p) else None,
            "ks_pvalue_uniform": float(kstest(p, "uniform").pvalue) if len(p) > 1 else None,
            "outside": [{"seed": int(s), "nees": float(v), "chi2_dof": float(c)}
                        for s, v, c in zip(r["seeds"], nees, r["chi2_dof"]) if v > NEES_3SIGMA_6DOF]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("design", nargs="?", default="extended_polynomial")
    ap.add_argument("--sessions", type=int, default=200)
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--poses", type=int, default=12)
    ap.add_argument("--candidates", type=int, default=None, help="plan's n_candidates (default: plan's default)")
    ap.add_argument("--tolerances", default="default", help="'default', a TOML path or 'none' (perfect lenses)")
    ap.add_argument("--method", default="joint")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--jsonl", type=Path, default=Path("session_study.jsonl"))
    ap.add_argument("--resume", action="store_true", help="skip seeds already in --jsonl")
    a = ap.parse_args()
    lens, bench = load_design_lens(a.design)
    t0 = time.time()
    p = plan(lens, bench=bench, n=a.poses, seed=a.seed,
             **({} if a.candidates is None else {"n_candidates": a.candidates}))
    print(f"plan: {len(p.ids)} poses, {time.time() - t0:.0f} s; predicted Z 1-sigma (theta free) "
          f"{p.predicted['Z_translation_mm'] * 1e3:.1f} um RMS", flush=True)
    _JOB.update(lens=lens, bench=bench, plan=p, method=a.method,
                tolerances=None if a.tolerances == "none" else a.tolerances)
    done = []
    if a.resume and a.jsonl.exists():
        done = [json.loads(line) for line in a.jsonl.read_text().splitlines() if line.strip()]
    have = {o["seed"] for o in done}
    seeds = [s for s in range(a.seed, a.seed + a.sessions) if s not in have]
    outcomes = [o for o in done if a.seed <= o["seed"] < a.seed + a.sessions]
    # --workers 0: in this process (a forked pool aborts when numba's OpenMP threading layer is loaded)
    pool = mp.get_context("fork").Pool(a.workers) if a.workers > 0 else None
    with a.jsonl.open("a") as fh:
        for o in (pool.imap_unordered(_run, seeds) if pool is not None else map(_run, seeds)):
            outcomes.append(o)
            fh.write(json.dumps(o) + "\n")
            fh.flush()
            if o["failed"] is None and o["nees"] > NEES_3SIGMA_6DOF:
                print(f"  seed {o['seed']}: OUTSIDE, NEES {o['nees']:.1f}, chi2/dof {o['chi2_dof']:.3f}, "
                      f"start {o['start']}", flush=True)
            if len(outcomes) % 10 == 0:
                print(f"  {len(outcomes)}/{a.sessions} sessions, {time.time() - t0:.0f} s", flush=True)
    if pool is not None:
        pool.close()
    print(json.dumps(report(outcomes), indent=1))


if __name__ == "__main__":
    main()
