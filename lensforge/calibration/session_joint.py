"""The joint as-built calibration of a bench session (``calibrate(..., method="joint")``).

The joint maximum-likelihood calibration (``joint.joint_calibrate``) on the raw
Zernike vectors and the recorded flange poses is run from EVERY start and the best
fit kept (``best_joint_fit``): the X, Z of a start method (``pipeline.two_stage``, given
by ``pipeline.joint``) and the robot program's nominal X, Z (the cell's). Running both
is needed because the chi2 test does not flag every wrong minimum: when the as-built
lens fools the two-stage pipeline (seen on 3 of 20 default-tolerance sessions, e.g. Z 92 mm
off), its start lights only 4 of 12 poses and the fit on those 4 passes the chi2 test
(chi2/dof 1.45) with Z still 90 mm off. "Best" is, among the fits the chi2 test
accepts, the one that explains the most poses, then the lowest cost: a fit that
leaves poses unlit has discarded data another start explains, and costs on different
pose sets are not comparable. A fit the test flags (e.g. a start that converges to a
chi2/dof of 1e5 on all poses) is kept only if every fit is flagged. A fit the test accepts
on every pose ends the search: no other start can explain more poses (on the co-designed
bench's as-built study, the cell's nominal start then reached the same minimum and cost 2-4x
the two-stage start's iterations: 26-40 against 10-12).
theta, the as-built lens parameters, is chosen from the tolerance model over the lens
poses each start predicts (``lens_params.parameterise``); its prior is N(0, I) in
units of the tolerances.

Per pose the result reports the robot-error chi2 a_i^T Sigma_A^-1 a_i (6 DOF, in the
plot's hand-eye row) and the whitened Zernike residual chi2 / m (the lens-fit row).
Poses the start leaves unlit, or that the fit's descent darkens at the pupil's edge,
are rejected; one robust outlier pass (Bonferroni chi2
quantile on the Zernike residual, scaled by the median over its expectation, as the
two-stage test) rejects poses and refits once.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import CalibrationError, LensforgeError
from ..asbuilt.tolerances import Tolerances, resolve_tolerances
from ..optics.pose import invert_poses, matrix_to_pose
from .joint import JointProblem, joint_calibrate
from ..asbuilt.lens_params import parameterise
from .session_result import OUTLIER_ALPHA, CalibrationResult, SessionData, robust_chi2_threshold, std_dict

__all__ = ["JointFrames", "best_joint_fit", "joint_session", "sensor_summary", "check_explained", "EXPLAINED_MIN"]


@dataclass(frozen=True, eq=False)
class JointFrames:
    """The X, Z part of a joint result in the shape CalibrationResult.handeye has
    (cov_X, cov_Z right perturbations, (mm, rad)^2, from the joint Fisher information)."""

    X: np.ndarray
    Z: np.ndarray
    cov_X: np.ndarray
    cov_Z: np.ndarray
    joint: object  # the JointCalibrationResult
    observable: bool = True
    null_directions: tuple = ()
    warnings: tuple = field(default=())


def _per_pose(bench, param, res, z, A, Tn, robot_cov, measurement=None):
    """(zernike chi2 (n,), robot chi2 (n,)) of the used poses at the estimate."""
    pb = JointProblem(bench, param, z, A, Tn, robot_cov, True, measurement, res.gain_sigma)
    r = pb.residuals(res.X, res.Z, res.theta, res.robot_errors)[0]
    return np.sum(r * r, axis=1), np.sum((res.robot_errors @ pb.WA.T) ** 2, axis=1)


def sensor_summary(bench, res) -> dict:
    """The estimated sensor parameters of a joint fit with the focal-length gain: the
    effective lenslet focal length (mm) with its 1-sigma, its prior, and whether the data
    determine it (posterior 1-sigma below half the prior's)."""
    f = float(bench.sensor.lenslet_focal_mm)
    prior = f * res.gain_sigma
    std = f * res.sensor_gain_std
    return {"lenslet_focal_mm": f * res.sensor_gain, "lenslet_focal_std_mm": std,
            "prior_lenslet_focal_mm": f, "prior_std_mm": prior, "identifiable": bool(std < 0.5 * prior)}


# a fit that leaves more of the measured poses dark than this share is a wrong minimum
EXPLAINED_MIN = 0.5


def check_explained(n_used: int, n_measured: int) -> None:
    """CalibrationError when the joint fit explains fewer than ``EXPLAINED_MIN`` of the poses the sensor
    measured (lit) and the outlier test kept: the others go dark at its estimate although the sensor saw
    them lit, so the estimate contradicts the data, however well it fits the rest. Seen on 1 of 200
    printed lenses of the co-designed study: 6 of 18 poses explained, chi2/dof 0.92, Z 0.2-0.6 m off."""
    if n_measured > 0 and n_used < EXPLAINED_MIN * n_measured:
        raise CalibrationError(f"joint calibration: the fit explains only {n_used} of {n_measured} measured poses (the "
                               "others go dark at its estimate though the sensor saw them lit): a wrong minimum; check "
                               "the robot cell's nominal X and Z and the pairing of poses with measurements")


def best_joint_fit(bench, lens, tol: Tolerances, z, A, T_SO_nominal, starts, robot_cov, *, alpha: float = OUTLIER_ALPHA,
                   params=None, measurement=None, known_lens: bool = False, gain_sigma: float | None = None):
    """(result, parameterisation, start index) of the best joint fit over ``starts``
    [(X0, Z0), ...] (module docstring): among the fits the chi2 test accepts, the one
    using most poses, then the lowest cost; if the test flags every fit, the lowest
    chi2/dof; a fit accepted on every pose ends the search (the later starts are not run). theta is
    parameterised over the lens poses each start predicts unless ``params`` (one
    LensParameterisation per start) is given (known_lens: no lens directions); gain_sigma:
    the sensor gain's prior (``joint_calibrate``). CalibrationError if no start gives a fit."""
    best, error = None, None
    for i, (X0, Z0) in enumerate(starts):
        if params is None:
            x_start = matrix_to_pose(invert_poses(T_SO_nominal) @ invert_poses(Z0) @ A @ X0)
            param = parameterise(bench, lens, tol, x_start, as_designed=known_lens)
        else:
            param = params[i]
        try:
            res = joint_calibrate(bench, param, z, A, T_SO_nominal, X0, Z0, robot_cov, alpha=alpha,
                                  measurement=measurement, gain_sigma=gain_sigma)
        except CalibrationError as e:
            error = e
            continue
        # accepted fits first (most poses, then lowest cost); a flagged fit only when none is accepted
        key = (0, -int(res.used.sum()), float(res.chi2)) if not res.mismatch else (1, float(res.chi2) / res.dof)
        if best is None or key < best[0]:
            best = (key, res, param, i)
        if not res.mismatch and res.used.all():  # no start can explain more poses
            break
    if best is None:
        raise error or CalibrationError("joint calibration: no start given")
    return best[1], best[2], best[3]


def joint_session(data: SessionData, *, start=None, outlier_alpha: float = OUTLIER_ALPHA, progress=None,
                  tolerances="default", known_lens: bool = False, gain_sigma: float | None = None) -> CalibrationResult:
    """Joint as-built calibration of a matched session (module docstring).

    start: a calibration method (SessionData -> CalibrationResult, e.g.
    ``pipeline.two_stage``) or its result on the same data, whose X, Z start the fit
    (None: the cell's nominal X, Z only);
    tolerances: the tolerance model of theta's prior ("default": the package's file,
    a TOML path or Tolerances); recorded in the result; known_lens: the lens as designed
    (no lens directions; for a fit of the sensor's gain alone); gain_sigma: the prior of the
    sensor's focal-length gain (default ``bench.sensor.focal_length_rel_sigma``)."""
    tol, tol_label = resolve_tolerances(tolerances)
    if tol is None:
        raise CalibrationError("joint calibration: no tolerance model for the as-built lens prior")
    model, scene = data.model, data.scene
    bench, lens, Tn = model.bench, model.lens, scene.T_SO_nominal
    robot_cov = scene.noise.cov
    starts, warns, start_names = [], [], []
    if isinstance(start, CalibrationResult):
        starts.append((start.X, start.Z))
        start_names.append(f"{start.method} solution")
    elif start is not None:
        try:
            ts = start(data, outlier_alpha=outlier_alpha, progress=progress)
            starts.append((ts.X, ts.Z))
            start_names.append(f"{start.__name__} solution")
        except LensforgeError as e:
            warns.append(f"{start.__name__} start failed ({e}); the joint fit starts from the robot cell's "
                         "nominal X, Z")
    starts.append((scene.X, scene.Z))
    start_names.append("the cell's nominal X, Z")
    ids = np.array(data.ids)
    rejected = list(data.rejected)
    keep = np.ones(len(ids), bool)
    res = None
    first_outliers = []  # per-pose rows of the poses the outlier pass left out (plotted in red)
    for attempt in range(2):
        if attempt == 0:
            res, param, i_best = best_joint_fit(bench, lens, tol, data.z, data.A, Tn, starts, robot_cov,
                                                alpha=outlier_alpha, measurement=data.measurement,
                                                known_lens=known_lens, gain_sigma=gain_sigma)
        else:  # outliers left out: refit from the estimate (the basin is found), same theta directions
            res, param, _ = best_joint_fit(bench, lens, tol, data.z[keep], data.A[keep], Tn, [(res.X, res.Z)],
                                           robot_cov, alpha=outlier_alpha, params=[param],
                                           measurement=data.measurement, gain_sigma=gain_sigma)
        kept = np.flatnonzero(keep)
        for k in kept[~res.used]:
            rejected.append({"pose": str(ids[k]), "reason": "unlit in the joint fit: at its start, or at the "
                             "pupil's edge on its way to the minimum (left out)"})
        keep[kept[~res.used]] = False
        used_idx = np.flatnonzero(keep)
        zc, rc = _per_pose(bench, param, res, data.z[used_idx], data.A[used_idx], Tn, robot_cov, data.measurement)
        m = data.z.shape[1]
        thr = robust_chi2_threshold(zc, m, outlier_alpha)
        out = zc > thr
        if attempt == 0 and out.any() and (~out).sum() >= 3:
            for j in np.flatnonzero(out):
                k = used_idx[j]
                first_outliers.append({"pose": str(ids[k]), "handeye_chi2": float(rc[j]),
                                       "estimate_chi2_dof": float(zc[j] / m), "outlier": True})
                rejected.append({"pose": str(ids[k]), "reason": f"outlier: joint Zernike residual chi2 "
                                 f"{zc[j]:.3g} above the robust threshold {thr:.3g} ({m} DOF)"})
            keep[used_idx[out]] = False
            continue
        break
    check_explained(len(used_idx), len(ids) - len(first_outliers))
    per_pose = tuple({"pose": str(i), "handeye_chi2": float(c6), "estimate_chi2_dof": float(cz / m),
                      "outlier": bool(o)} for i, c6, cz, o in zip(ids[used_idx], rc, zc, out)) + tuple(first_outliers)
    if res.mismatch:
        warns.append(f"model check failed: chi2/dof = {res.chi2 / res.dof:.3g} (p = {res.p_value:.2g}) even with "
                     "the as-built lens estimated: the tolerance model, the robot repeatability or the sensor noise "
                     "does not describe this bench; the reported 1-sigma are then too small")
    if not res.converged:
        warns.append(f"joint fit stopped after {res.iterations} iterations without meeting its tolerance")
    s = res.summary()
    names = [param.describe(i) for i in range(param.k)]
    extra = {"tolerances": "none" if known_lens else tol_label, "p_value": float(res.p_value), "outlier_threshold_zernike_chi2": thr,
             "n_zernike_modes": int(m),
             "lens_parameters": {"theta": s["theta"], "theta_sigma": s["theta_sigma"], "directions": names,
                                 "identifiable": [names[i] for i in np.flatnonzero(res.identifiable)],
                                 "n_identifiable": s["n_identifiable"],
                                 "units": "prior sigma of the tolerance model (prior N(0, 1))"},
             **({"sensor": sensor_summary(bench, res)} if res.has_gain else {}),
             "Z_std_known_lens": std_dict(np.sqrt(np.diag(res.crlb_Z_known_lens))),
             "iterations": res.iterations, "converged": bool(res.converged), "start": start_names[i_best]}
    frames = JointFrames(X=res.X, Z=res.Z, cov_X=res.cov_X, cov_Z=res.cov_Z, joint=res)
    return CalibrationResult(X=res.X, Z=res.Z, handeye=frames, poses_used=tuple(ids[used_idx].tolist()),
                             poses_rejected=tuple(rejected), per_pose=per_pose, chi2=float(res.chi2),
                             dof=int(res.dof), chi2_dof=float(res.chi2 / res.dof), p_value=float(res.p_value),
                             method="joint", robot=data.robot_name, warnings=tuple(warns), extra=extra)
