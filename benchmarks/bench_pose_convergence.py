"""Pose-estimator robustness: convergence counts of the single-pose entry point and the
batched LM on the same noisy measurements.

    .venv/bin/python benchmarks/bench_pose_convergence.py [--n 30] [--seed 0] [--lenses zernike,...]

Protocol (that of ``verification.estimation_study``): per lens, n seeded trials; the
true pose is drawn about the nominal one from the gripper/robot prior
(``InitialPoseModel``, translations clipped to the bench's range), the slopes get the
bench's noise, the estimate starts at the nominal pose (zeros). Counted per estimator:
converged (its own flag), and "correct" = converged with the error inside 5 sigma of
the reported covariance on every observable DOF (a converged but wrong minimum is not
correct). Estimators: ``estimate_pose_model`` (method lm), the batch ``estimate_poses_batch``
with P = 1 per trial, and the batch with all n trials at once.
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

from lensforge.calibration.initial_poses import InitialPoseModel  # noqa: E402
from lensforge.calibration.pose_estimation import (  # noqa: E402
    UnobservableWarning,
    estimate_pose_model,
    estimate_poses_batch,
)
from lensforge.errors import LensforgeError  # noqa: E402
from lensforge.optics.lens import resolve_lens  # noqa: E402
from lensforge.optics.shack_hartmann import ForwardModel  # noqa: E402


def trials(model, n, seed):
    bench = model.bench
    sig = InitialPoseModel().sigma
    lim = bench.pose_limits
    out = []
    for child in np.random.SeedSequence(seed).spawn(n):
        rng = np.random.default_rng(child)
        x = rng.normal(size=6) * sig
        x[:3] = np.clip(x[:3], -lim.translation_mm, lim.translation_mm)
        res = model.evaluate(x[None], check_range=False)
        if not res.valid[0]:
            continue
        sigma = bench.noise.slope_sigma_urad * 1e-6
        out.append((x, model.pupil.fit(res.slopes[0] + rng.normal(0.0, sigma, res.slopes[0].shape))))
    return out


def correct(x, xt, cov):
    d = np.diag(cov)
    obs = np.isfinite(d)
    return bool(np.all(np.abs(x - xt)[obs] <= 5 * np.sqrt(d[obs])))


def run(name, n, seed):
    rl = resolve_lens(name)
    model = ForwardModel(rl.bench_or(None), rl.lens)
    tr = trials(model, n, seed)
    row = {"lens": name, "trials": len(tr)}
    # single-pose entry point
    conv = ok = 0
    t0 = time.process_time()
    for xt, z in tr:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UnobservableWarning)
                e = estimate_pose_model(model, z, x0=np.zeros(6))
        except LensforgeError:
            continue
        conv += e.converged
        ok += e.converged and correct(e.pose, xt, e.cov)
    row["single"] = {"converged": conv, "correct": ok, "cpu_s": round(time.process_time() - t0, 2)}
    # batch, P = 1 per trial
    conv = ok = 0
    t0 = time.process_time()
    for xt, z in tr:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UnobservableWarning)
            b = estimate_poses_batch(model, z[None], np.zeros((1, 6)))
        conv += bool(b.converged[0])
        ok += bool(b.converged[0]) and correct(b.poses[0], xt, b.cov[0])
    row["batch_p1"] = {"converged": conv, "correct": ok, "cpu_s": round(time.process_time() - t0, 2)}
    # batch, all at once
    t0 = time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnobservableWarning)
        b = estimate_poses_batch(model, np.array([z for _, z in tr]), np.zeros((len(tr), 6)))
    ok = sum(bool(b.converged[i]) and correct(b.poses[i], tr[i][0], b.cov[i]) for i in range(len(tr)))
    row["batch_all"] = {"converged": int(b.converged.sum()), "correct": ok,
                        "cpu_s": round(time.process_time() - t0, 2)}
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lenses", default="zernike,extended_polynomial,polynomial")
    ap.add_argument("--json", default=None, help="write the rows here")
    a = ap.parse_args()
    rows = []
    for name in a.lenses.split(","):
        r = run(name, a.n, a.seed)
        rows.append(r)
        print(f"{name:40s} trials {r['trials']:3d} | " + " | ".join(
            f"{k}: conv {r[k]['converged']:3d} correct {r[k]['correct']:3d} ({r[k]['cpu_s']:.1f} s)"
            for k in ("single", "batch_p1", "batch_all")), flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
