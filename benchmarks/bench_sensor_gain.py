"""The sensor's focal-length gain in the joint calibration: estimates against their truths.

Sessions of the paper's polynomial lens on the default bench (12-pose study plan, robot
noise, slope noise) whose reported Zernikes are scaled by a true gain g = f_true / f_bench
(the WFS divides spot displacements by its calibrated focal length). Each is calibrated
with the gain free (prior --sigma) and with it fixed at 1, lens known or free (the
default tolerance model's directions). Prints per session the truth, the estimate, its
1-sigma, the normalised error, and Z's NEES and chi2/dof with and without the gain.

    python benchmarks/bench_sensor_gain.py --sessions 10 --sigma 0.05 --truth 1.02
"""

from __future__ import annotations

import argparse

import numpy as np

from lensforge.asbuilt.lens_params import parameterise
from lensforge.asbuilt.tolerances import resolve_tolerances
from lensforge.calibration.joint import joint_calibrate, simulate_joint_data
from lensforge.calibration.robot import flange_pose, paper_scene
from lensforge.optics.bench import Bench
from lensforge.optics.lens import paper_lens
from lensforge.optics.pose import matrix_to_pose, pose_to_matrix
from lensforge.verification.study import StudyConfig, calibration_plan


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=10)
    ap.add_argument("--sigma", type=float, default=0.05, help="relative prior 1-sigma of the focal length")
    ap.add_argument("--truth", type=float, default=None, help="true gain (default: drawn from the prior)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lens-free", action="store_true", help="the default tolerance model's lens directions free")
    a = ap.parse_args()
    bench, lens = Bench.default(), paper_lens("polynomial")
    scene = paper_scene(bench.placement.distance_mm)
    plan = calibration_plan(StudyConfig(n_poses=12))
    tol = resolve_tolerances("default")[0]
    param = parameterise(bench, lens, tol, plan, as_designed=not a.lens_free)
    A_cmd = flange_pose(scene, plan, check_reach=False)
    rng = np.random.default_rng(a.seed)
    print(f"lens {'free (%d directions)' % param.k if a.lens_free else 'known'}, prior sigma {a.sigma:g}")
    print(" i   g true    g est   1-sigma   (est-true)/sigma   NEES_Z  chi2/dof | without gain: NEES_Z chi2/dof")
    zs, nees = [], []
    for i in range(a.sessions):
        g = a.truth if a.truth is not None else 1 + a.sigma * rng.standard_normal()
        theta = rng.standard_normal(param.k)
        A_true = A_cmd @ pose_to_matrix(scene.noise.sample(rng, len(A_cmd)))
        z = g * simulate_joint_data(bench, param, theta, A_true, scene.X, scene.Z, scene.T_SO_nominal, rng=rng)
        X0 = scene.X @ pose_to_matrix(rng.standard_normal(6) * ([0.05] * 3 + [1e-3] * 3))
        Z0 = scene.Z @ pose_to_matrix(rng.standard_normal(6) * ([0.05] * 3 + [1e-3] * 3))
        row = []
        for gs in (a.sigma, 0.0):
            r = joint_calibrate(bench, param, z, A_cmd, scene.T_SO_nominal, X0, Z0, scene.noise.cov, gain_sigma=gs)
            e = matrix_to_pose(np.linalg.solve(scene.Z, r.Z))
            row.append((r, float(e @ np.linalg.solve(r.cov_Z, e))))
        (r, n1), (r0, n0) = row
        zn = (r.sensor_gain - g) / r.sensor_gain_std
        zs.append(zn)
        nees.append(n1)
        print(f"{i:2d} {g:9.5f} {r.sensor_gain:9.5f} {r.sensor_gain_std:9.2e} {zn:12.2f} {n1:14.2f} "
              f"{r.chi2 / r.dof:8.3f} | {n0:12.1f} {r0.chi2 / r0.dof:8.3f}")
    zs = np.asarray(zs)
    print(f"mean square normalised gain error {np.mean(zs**2):.2f} (1 expected), mean NEES_Z/6 "
          f"{np.mean(nees) / 6:.2f} (1 expected)")


if __name__ == "__main__":
    main()
