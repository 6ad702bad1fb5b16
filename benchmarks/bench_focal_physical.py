"""The lenslet focal length estimated by the joint calibration on the full-array physical sensor (issue 21).

Mini sessions: the paper's polynomial lens, the bench's pupil reduced to 0.5 mm at Zernike order 3 (so the
'cells' model costs minutes, not hours), 4 of the 12-pose study plan's poses with robot errors drawn, the
full-array physical sensor (4 samples per pixel, 5 lit rings) with lenslets of focal length --true-focal
against the bench's 5.2 mm, slope noise; then the joint fit on 'cells' with the lens known and a --sigma
(relative) prior on the focal length, which the cross-talk model carries (``JointProblem.focal_in_model``).
--gain-only: the focal length as a plain gain on every slope instead (the model before 0009a70; a diagnostic).
Prints per seed the estimate against its truth, chi2/dof, Z's NEES and error, and the mean and spread of the
normalised errors.

    python benchmarks/bench_focal_physical.py --seeds 0-9
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import lensforge as lf
from lensforge.asbuilt.lens_params import parameterise
from lensforge.asbuilt.tolerances import Tolerances
from lensforge.calibration import joint as J
from lensforge.calibration.robot import flange_pose, paper_scene
from lensforge.optics.pose import matrix_to_pose, pose_to_matrix
from lensforge.optics.shack_hartmann import ForwardModel
from lensforge.verification.physical_sensor import PhysicalSensor, physical_measure
from lensforge.verification.study import StudyConfig, calibration_plan


def _seeds(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b) + 1)) if b else [int(s) for s in text.split(",")]


def session(seed: int, true_focal: float, sigma: float, gain_only: bool = False) -> dict:
    bench = lf.Bench.default().replace(sensor={"crosstalk": "cells", "pupil_radius_mm": 0.5, "zernike_order": 3})
    f_bench = bench.sensor.lenslet_focal_mm
    lens = lf.paper_lens("polynomial")
    scene = paper_scene(bench.placement.distance_mm)
    plan = calibration_plan(StudyConfig(n_poses=12))[[0, 3, 6, 9]]
    param = parameterise(bench, lens, Tolerances(form_modes=(4, 5, 6, 7, 8)), plan, as_designed=True)
    rng = np.random.default_rng(seed)
    A_cmd = flange_pose(scene, plan, check_reach=False)
    a_true = scene.noise.sample(rng, len(A_cmd))
    _, x = J.pose_chain(A_cmd @ pose_to_matrix(a_true), scene.X, scene.Z, np.zeros((len(plan), 6)),
                        scene.T_SO_nominal)
    own = ForwardModel(bench.replace(sensor={"crosstalk": "none"}), lens)
    cfg = PhysicalSensor(samples_per_pixel=4, margin_lenslets=5, focal_mm=true_focal)
    z = np.stack([physical_measure(own, xi, cfg).z for xi in x])
    z = z + rng.standard_normal(z.shape) @ np.linalg.cholesky(own.noise_cov).T
    X0 = scene.X @ pose_to_matrix([0.03, -0.02, 0.04, 5e-4, -4e-4, 6e-4])
    Z0 = scene.Z @ pose_to_matrix([-0.04, 0.03, 0.02, -5e-4, 3e-4, 4e-4])
    init = J.JointProblem.__init__
    if gain_only:
        def plain(self, *a, **k):
            init(self, *a, **k)
            self.focal_in_model = False
        J.JointProblem.__init__ = plain
    t0 = time.perf_counter()
    try:
        res = J.joint_calibrate(bench, param, z, A_cmd, scene.T_SO_nominal, X0, Z0, scene.noise.cov, gain_sigma=sigma)
    finally:
        J.JointProblem.__init__ = init
    e = matrix_to_pose(np.linalg.solve(scene.Z, res.Z))
    f_est, f_sd = f_bench * res.sensor_gain, f_bench * res.sensor_gain_std
    return {"seed": seed, "focal_mm": f_est, "focal_sigma_mm": f_sd, "error_sigma": (f_est - true_focal) / f_sd,
            "chi2_dof": res.chi2 / res.dof, "dof": res.dof, "p_value": res.p_value,
            "nees_Z": float(e @ np.linalg.solve(res.cov_Z, e)), "Z_err_um": float(np.linalg.norm(e[:3]) * 1e3),
            "Z_err_mrad": float(np.linalg.norm(e[3:]) * 1e3), "converged": bool(res.converged),
            "seconds": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=_seeds, default=_seeds("0-9"), help="'0-9' or '0,3,5'")
    ap.add_argument("--true-focal", type=float, default=5.252, help="the lenslets' focal length, mm (bench: 5.2)")
    ap.add_argument("--sigma", type=float, default=0.01, help="relative prior 1-sigma of the focal length")
    ap.add_argument("--gain-only", action="store_true", help="the focal length as a plain gain (diagnostic)")
    a = ap.parse_args()
    rows = []
    for s in a.seeds:
        r = session(s, a.true_focal, a.sigma, a.gain_only)
        rows.append(r)
        print(f"seed {s}: focal {r['focal_mm']:.4f} +- {r['focal_sigma_mm']:.4f} mm (true {a.true_focal}; "
              f"error/sigma {r['error_sigma']:+.2f}) | chi2/dof {r['chi2_dof']:.2f} (dof {r['dof']}, "
              f"p {r['p_value']:.3g}) | Z NEES {r['nees_Z']:.2f} | Z err {r['Z_err_um']:.1f} um "
              f"{r['Z_err_mrad']:.2f} mrad | converged {r['converged']} | {r['seconds']:.0f} s", flush=True)
    zn = np.array([r["error_sigma"] for r in rows])
    print(f"{len(rows)} sessions: focal error/sigma mean {zn.mean():+.2f}, RMS {np.sqrt(np.mean(zn**2)):.2f} "
          f"(1 expected); chi2 p < 0.05 in {sum(r['p_value'] < 0.05 for r in rows)}; Z NEES mean "
          f"{np.mean([r['nees_Z'] for r in rows]):.2f} (6 expected)")


if __name__ == "__main__":
    main()
