"""Pose-estimation benchmark: cost per estimate and the calibration scenario's cost.

    .venv/bin/python benchmarks/bench_estimation.py [--n 40] [--quick] [--out exports/bench_estimation]

1. Per lens and estimator (lm / ukf x12): wall time
   per estimate (median over --n noisy estimates from grasp-error starts, one
   thread of work after a warm-up), Jacobian evaluations, poses traced.
2. One simulated calibration run (12 convergence + 12 calibration poses, ml
   hand-eye) with lm: seconds per run.
Prints a table and writes a JSON summary under --out.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import lensforge as lf  # noqa: E402
from lensforge.fileio import write_atomic  # noqa: E402
from lensforge.optics.shack_hartmann import ForwardModel  # noqa: E402
from lensforge.calibration.initial_poses import InitialPoseModel, prior_covariance  # noqa: E402
from lensforge.calibration.pose_estimation import UnobservableWarning, estimate_pose_model  # noqa: E402
from lensforge.verification.scenario import ScenarioConfig, plan_poses, run_calibration  # noqa: E402

LENSES = ("spherical", "polynomial", "extended_polynomial", "zernike")
VARIANTS = {
    "lm": {"method": "lm"},
    "ukf-12": {"method": "ukf", "ukf_repeats": 12, "prior_cov": prior_covariance()},
}


def time_estimates(bench, name: str, variant: str, n: int, seed: int) -> dict:
    model = ForwardModel(bench, lf.paper_lens(name))
    rng = np.random.default_rng(seed)
    sig = InitialPoseModel().sigma
    times, jacs, evals, fails = [], [], [], 0
    opts = VARIANTS[variant]
    for i in range(n + 1):
        x = rng.normal(size=6) * sig
        res = model.evaluate(x[None], check_range=False)
        if not res.valid[0]:
            fails += 1
            continue
        z = model.pupil.fit(res.slopes[0] + rng.normal(0, bench.noise.slope_sigma_urad * 1e-6, res.slopes[0].shape))
        t0 = time.perf_counter()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UnobservableWarning)
                est = estimate_pose_model(model, z, **opts)
        except lf.LensforgeError:
            fails += 1
            continue
        dt = time.perf_counter() - t0
        if i == 0:
            continue  # warm-up
        times.append(dt)
        jacs.append(est.iterations)
        evals.append(est.n_evals)
    return {"lens": name, "variant": variant, "n": len(times), "median_ms": 1e3 * float(np.median(times)),
            "p90_ms": 1e3 * float(np.percentile(times, 90)), "mean_iterations": float(np.mean(jacs)),
            "mean_poses_traced": float(np.mean(evals)), "failures": fails}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=40, help="estimates per lens and variant")
    ap.add_argument("--quick", action="store_true", help="5 estimates, two lenses")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="exports/bench_estimation")
    a = ap.parse_args(argv)
    n = 5 if a.quick else a.n
    lenses = LENSES[1:3] if a.quick else LENSES
    bench = lf.Bench.default()
    rows = []
    print(f"{'lens':<22}{'variant':<12}{'median ms':>10}{'p90 ms':>9}{'iters':>7}{'poses':>8}{'fail':>6}")
    for name in lenses:
        for v in VARIANTS:
            r = time_estimates(bench, name, v, n, a.seed)
            rows.append(r)
            print(f"{name:<22}{v:<12}{r['median_ms']:>10.1f}{r['p90_ms']:>9.1f}{r['mean_iterations']:>7.1f}"
                  f"{r['mean_poses_traced']:>8.0f}{r['failures']:>6}")
    lens = lf.paper_lens("extended_polynomial")
    cfg = ScenarioConfig()
    x, _ = plan_poses(bench, lens, "random", np.random.default_rng(a.seed), cfg)
    run_calibration(bench, lens, x, np.random.default_rng(a.seed), cfg)  # warm-up
    t0 = time.perf_counter()
    k = 1 if a.quick else 3
    for i in range(k):
        run_calibration(bench, lens, x, np.random.default_rng(a.seed + i + 1), cfg)
    per_run = (time.perf_counter() - t0) / k
    print(f"calibration run (12 + 12 poses, lm, ml hand-eye): {per_run:.2f} s")
    out = Path(a.out)
    write_atomic(out / "bench_estimation.json",
                 json.dumps({"estimates": rows, "calibration_run_s": per_run}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
