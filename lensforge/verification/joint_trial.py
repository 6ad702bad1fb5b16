"""The joint as-built calibration inside an as-built study trial.

A trial simulates the session once (``study.run_trial``); the two-stage pipeline
(per-pose estimates with the nominal model, then AX = ZB) runs first and its
solution starts the joint calibration (``calibration.joint``) on the same raw
Zernike data and recorded flange poses. Both results are stored in the trial record.

The joint estimator's prior on the as-built lens comes from the study's tolerance
model (``prior_tolerances`` overrides it, e.g. to calibrate perfect lenses with
the default prior). Its parameterisation theta is chosen once per study context
from the calibration plan (``asbuilt.lens_params.parameterise``).
"""

from __future__ import annotations

import numpy as np

from ..calibration.joint import joint_calibrate_from
from ..asbuilt.lens_params import LensParameterisation, parameterise
from ..errors import LensforgeError
from ..optics.pose import matrix_to_pose, transform_error

__all__ = ["study_parameterisation", "joint_trial_record", "nees"]


def study_parameterisation(bench, lens, tolerances, plan) -> LensParameterisation:
    """theta for a study: the leading directions over the plan under ``tolerances``
    (None or zero tolerances: no lens parameters, theta empty)."""
    from ..asbuilt.tolerances import Tolerances

    return parameterise(bench, lens, tolerances if tolerances is not None else Tolerances.zero(), plan)


def nees(T_true, T_est, cov) -> float:
    """Normalised estimation error squared e^T cov^-1 e of e = log(T_true^-1 T_est)
    (right perturbation, (mm, rad)); its mean over trials is the dimension (6)."""
    e = matrix_to_pose(np.linalg.solve(T_true, T_est))
    return float(e @ np.linalg.solve(cov, e))


def joint_trial_record(bench, param: LensParameterisation, z, A, T_SO_nominal, starts, robot_cov, Z_true,
                       X_true, theta_jacobian0=None) -> dict:
    """Run the joint calibration on one trial's data from the (X0, Z0) starts (the
    two-stage solution, then the robot program's nominal X, Z; see
    ``joint_calibrate_from``); a record like the trial's (ok,
    rot_err_deg, trans_err_mm, x_*), plus nees_Z (6 dof), chi2, dof, p_value,
    mismatch, theta, n_identifiable, iterations, converged, Z 1-sigma. theta_jacobian0:
    dh/dtheta at the commanded poses (``LensParameterisation.theta_jacobian`` rows; speed only)."""
    try:
        res = joint_calibrate_from(bench, param, z, A, T_SO_nominal, starts, robot_cov,
                                   theta_jacobian0=theta_jacobian0)
    except (LensforgeError, np.linalg.LinAlgError) as e:
        return {"ok": False, "failure": f"joint calibration failed: {e}", "rot_err_deg": None, "trans_err_mm": None}
    rot, trans = transform_error(Z_true, res.Z)
    xrot, xtrans = transform_error(X_true, res.X)
    s = res.summary()
    return {"ok": True, "failure": "", "rot_err_deg": rot, "trans_err_mm": trans, "x_rot_err_deg": xrot,
            "x_trans_err_mm": xtrans, "bias": [0.0] * 6, "nees_Z": nees(Z_true, res.Z, res.cov_Z),
            "chi2": res.chi2, "dof": res.dof, "p_value": res.p_value, "mismatch": res.mismatch,
            "theta": s["theta"], "n_identifiable": s["n_identifiable"], "iterations": res.iterations,
            "converged": res.converged, "Z_sigma_mm": s["Z_sigma_mm"], "Z_sigma_deg": s["Z_sigma_deg"],
            "n_traced": res.n_traced}
