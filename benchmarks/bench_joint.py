"""Joint as-built calibration: time of one calibration and of an as-built study with it.

1. One joint calibration (calibration.joint.joint_calibrate) of n poses: the study's
   plan, an as-built lens drawn from theta's prior, robot and sensor noise, started
   0.3 mm / 0.5 deg off (the two-stage solution's typical error); median wall time over
   --repeats draws, single core (BLAS pinned to one thread by the caller). CPU time
   (process_time) is reported beside wall time: on a shared machine it is the figure
   that compares with the 2 s goal.
2. --study N: an as-built study of N lenses with --calibration joint on --workers
   processes (default tolerances), wall time and the extrapolation to 1000 lenses;
   --workers 0 runs it in this process and reports CPU time per lens (what to use on
   a loaded machine: 1000 lenses on 2 cores ~ 1000 x CPU per lens / 2).

Run: OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 NUMBA_NUM_THREADS=1 \
     .venv/bin/python benchmarks/bench_joint.py [DESIGN] [--poses 24]
     [--repeats 10] [--study 40 --workers 2]
DESIGN: a design JSON (e.g. exports/zernike.json from `make demo`) or a paper lens name.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from lensforge.calibration.joint import joint_calibrate, simulate_joint_data
from lensforge.asbuilt.lens_params import parameterise
from lensforge.asbuilt.tolerances import Tolerances
from lensforge.optics.lens import resolve_lens
from lensforge.optics.pose import pose_to_matrix
from lensforge.optics.shack_hartmann import ForwardModel
from lensforge.verification.study import StudyConfig, calibration_plan, verify


def one_calibration(design: str, n_poses: int, repeats: int) -> None:
    from lensforge.calibration.robot import flange_pose, paper_scene

    r = resolve_lens(design)
    lens, bench = r.lens, r.bench_or()
    scene = paper_scene(bench.placement.distance_mm)
    plan = calibration_plan(StudyConfig(n_poses=n_poses))
    t0 = time.perf_counter()
    param = parameterise(bench, lens, Tolerances(), plan)
    t_param = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    lit = ForwardModel(bench, param.build(np.zeros(param.k)), validate=False).evaluate(plan, check_range=False).valid
    J0 = param.theta_jacobian[lit]  # what the study passes: dh/dtheta at the plan (once per study)
    plan = plan[lit]  # poses that light the pupil for the mean as-built lens
    A_cmd = flange_pose(scene, plan, check_reach=False)
    times, cpu, iters, traced = [], [], [], []
    off = np.r_[[0.3] * 3, [math.radians(0.5)] * 3]
    for _ in range(repeats):
        theta = rng.standard_normal(param.k)
        A_true = A_cmd @ pose_to_matrix(scene.noise.sample(rng, len(plan)))
        try:
            z = simulate_joint_data(bench, param, theta, A_true, scene.X, scene.Z, scene.T_SO_nominal, rng=rng)
        except Exception:  # a draw that leaves a pose unlit: skip it
            continue
        X0 = scene.X @ pose_to_matrix(rng.standard_normal(6) * off)
        Z0 = scene.Z @ pose_to_matrix(rng.standard_normal(6) * off)
        t0, c0 = time.perf_counter(), time.process_time()
        res = joint_calibrate(bench, param, z, A_cmd, scene.T_SO_nominal, X0, Z0, scene.noise.cov,
                              theta_jacobian0=J0)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        iters.append(res.iterations)
        traced.append(res.n_traced)
    print(f"theta: {param.k} directions, chosen in {t_param:.2f} s (once per study)")
    print(f"one joint calibration, {len(plan)} lit of {n_poses} poses: median {np.median(cpu):.2f} s CPU "
          f"(max {np.max(cpu):.2f}), {np.median(times):.2f} s wall over {len(times)} draws; "
          f"median {np.median(iters):.0f} LM iterations, {np.median(traced):.0f} poses traced "
          f"({np.median(cpu) / np.median(traced) * 1e3:.1f} ms CPU per pose trace)")


def study(design: str, n: int, workers: int, n_poses: int) -> None:
    cfg = StudyConfig(n_poses=n_poses, calibration="joint")
    t0, c0 = time.perf_counter(), time.process_time()
    res = verify(design, Tolerances(), n_lenses=n, seed=0, config=cfg, workers=workers, progress=False)
    wall, cpu0 = time.perf_counter() - t0, time.process_time() - c0
    if workers == 0:  # in this process: CPU time is measurable on a shared machine
        print(f"study, {n} lenses, joint, in-process: {cpu0:.0f} s CPU = {cpu0 / n:.2f} s per lens (measured, "
              f"including theta's choice) -> 1000 lenses on 2 cores ~ {cpu0 / n * 1000 / 2 / 60:.1f} min "
              f"(CPU / 2, extrapolated; Z p95 {res.summary['translation_mm']['p95']} mm)")
        return
    cpu = res.stats.wall_s
    print(f"study, {n} lenses, joint, {workers} workers: {wall:.0f} s wall (measured, including the worker start "
          f"and theta's choice) -> 1000 lenses ~ {wall * 1000 / n / 60:.1f} min by linear extrapolation "
          f"(Z p95 {res.summary['translation_mm']['p95']} mm; runner wall {cpu:.0f} s)")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("design", nargs="?", default="polynomial")
    ap.add_argument("--poses", type=int, default=24)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--study", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args()
    one_calibration(a.design, a.poses, a.repeats)
    if a.study:
        study(a.design, a.study, a.workers, a.poses)


if __name__ == "__main__":
    main()
