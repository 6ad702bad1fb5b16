"""The exact Jacobians of the forward model: the joint calibration's hot path.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 .venv/bin/python benchmarks/bench_jacobians.py [DESIGN] [--poses 24]

Times ``ForwardModel.jacobians`` at the study's plan (``calibration_plan``) on one core, with the
pose directions only (pose estimation), with the as-built lens's theta tangents (the joint
calibration's covariance) and the same as iteration Jacobians (exact=False), and how much of each
is the ray trace (``trace_rays``: the aimed rays and their u- and v-displaced copies, or the aimed
rays alone for exact=False) and how much the rest (aimed-ray tangents, centroid derivatives,
Zernike fit). Median of --repeats calls, CPU time. DESIGN: a design JSON or a paper lens name
(default: the paper's polynomial lens on the built-in bench).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import lensforge.optics.shack_hartmann as sh
from lensforge.asbuilt.lens_params import parameterise
from lensforge.asbuilt.tolerances import Tolerances
from lensforge.optics.lens import resolve_lens
from lensforge.verification.study import StudyConfig, calibration_plan


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("design", nargs="?", default="polynomial")
    ap.add_argument("--poses", type=int, default=24)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    r = resolve_lens(a.design)
    lens, bench = r.lens, r.bench_or()
    plan = calibration_plan(StudyConfig(n_poses=a.poses))
    param = parameterise(bench, lens, Tolerances(), plan)
    theta = np.random.default_rng(1).standard_normal(param.k)
    model = sh.ForwardModel(bench, param.build(theta), validate=False)
    lt = param.tangents(theta, bench.laser.wavelength_nm)
    uv = model.evaluate(plan, check_range=False).uv
    trace_cpu = [0.0]
    trace = sh.trace_rays

    def timed_trace(*args, **kw):
        c0 = time.process_time()
        out = trace(*args, **kw)
        trace_cpu[0] += time.process_time() - c0
        return out

    sh.trace_rays = timed_trace
    model.jacobians(plan[:1], lens_tangents=lt)  # compile / warm
    n_rays = model.targets.shape[0]
    print(f"{a.design}: {a.poses} poses x {n_rays} aimed rays, theta {param.k} directions")
    cases = (("pose directions", {}), (f"pose + {param.k} lens tangents", {"lens_tangents": lt}),
             (f"pose + {param.k} lens tangents, iteration (exact=False)", {"lens_tangents": lt, "exact": False}))
    for name, kw in cases:
        total, traced = [], []
        for _ in range(a.repeats):
            trace_cpu[0] = 0.0
            c0 = time.process_time()
            model.jacobians(plan, uv0=uv, **kw)
            total.append(time.process_time() - c0)
            traced.append(trace_cpu[0])
        t, tr = float(np.median(total)), float(np.median(traced))
        print(f"  {name}: {t:.2f} s CPU per call ({tr:.2f} s ray trace, {t - tr:.2f} s the rest); "
              f"{t / (a.poses * n_rays) * 1e6:.2f} us per aimed ray")
    sh.trace_rays = trace


if __name__ == "__main__":
    main()
