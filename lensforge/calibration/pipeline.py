"""The one calibration pipeline: ``SessionData`` in, ``CalibrationResult`` out.

Every calibration of X = ^E T_O and Z = ^W T_S runs here, whoever asks: ``lensforge
calibrate`` on a real bench session (``session.calibrate`` reads and matches the files) and
every simulation of ``verification`` (study, scenario, budget, rehearsal sessions), which
builds the same ``SessionData`` from its simulated session. A number a study reports is
therefore the number the bench command would give on that data.

Methods are a registry (``METHODS``: name -> function(data, **options) -> CalibrationResult);
each includes its outlier passes, fallbacks and its chi2 model check:

* ``two-stage``: (1) each measured Zernike vector gives a lens pose with its covariance
  (``pose_estimation``: all poses at once by the batched Levenberg-Marquardt from the pose
  the cell predicts for the recorded flange pose; a pose that fails is retried alone from
  nominal; ``estimator`` picks another registered estimator, pose by pose); (2) A X = Z B by
  maximum likelihood (``handeye.solve_handeye``) with the robot's repeatability and each
  pose's covariance. Two robust outlier tests (``session_result.robust_chi2_threshold``):
  first on each lens-pose fit (m - 6 DOF: a wrong local minimum or a corrupted frame), then
  on each pose's hand-eye residual (6 DOF), after which the solve is repeated once. A lens
  direction its pose estimate does not observe (infinite variance) enters the solve with no
  information (a 10 mm / 10 rad 1-sigma). Model check: chi2 of the final solve against its
  degrees of freedom (p-value); the median lens-pose fit chi2 is checked too.
* ``joint`` (the default of ``calibrate`` and ``study``): the as-built lens estimated with X
  and Z (``session_joint.joint_session``), started from the two-stage solution and from the
  cell's nominal X, Z. It falls back to ``two-stage`` (method "two-stage", a warning, and
  ``extra["fallback"]`` = {"from": "joint", "reason"}) when it cannot run: no tolerance
  model (tolerances None or "none") or the joint fit fails. A tolerance file that cannot be
  read stays an error (the user's mistake).
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
from scipy.stats import chi2 as chi2_dist

from ..asbuilt.tolerances import no_tolerance_model
from ..errors import CalibrationError, ConfigError, LensforgeError
from ..optics.pose import invert_poses, matrix_to_pose, pose_to_matrix, pose_vector_cov_to_right
from ..optics.shack_hartmann import ForwardModel
from .handeye import solve_handeye
from .measurement import referenced_session
from .pose_estimation import PoseEstimate, UnobservableWarning, estimate_pose_model, estimate_poses_batch
from .session_joint import joint_session
from .session_result import OUTLIER_ALPHA, CalibrationResult, SessionData, robust_chi2_threshold

__all__ = ["METHODS", "VERSION", "run", "two_stage", "joint", "estimate_one", "TooFewPosesError", "UNINFORMATIVE_VARIANCE"]

# variance (mm^2 or rad^2) of a lens-pose direction its estimate does not observe: (10 mm)^2, (10 rad)^2
UNINFORMATIVE_VARIANCE = 100.0
# What the methods compute, versioned: stored studies hash it (a store made by another
# version is not resumed). 1: one pipeline for calibrate and the study (issue 20);
# 2: the joint fits step by the shared trust-region policy (``trust_region``).
VERSION = 2


class TooFewPosesError(CalibrationError):
    """Fewer poses gave a lens pose than the method needs; ``rejected`` lists every pose left
    out ({"pose", "reason", "code"}), so a caller can count why."""

    def __init__(self, message: str, rejected):
        super().__init__(message)
        self.rejected = tuple(rejected)


def run(data: SessionData, method: str = "joint", **options) -> CalibrationResult:
    """Calibrate a matched session with a ``METHODS`` entry (options: the method's keywords).

    Measurements relative to a user reference (``data.measurement.reference``) are modelled
    exactly, z = h(x) - h(x_ref), by ``measurement.referenced_session`` whatever the method."""
    if method not in METHODS:
        raise ConfigError(f"method: {method!r} is not available; use one of {', '.join(METHODS)}")
    if data.measurement is not None and data.measurement.reference is not None:
        if gain_prior(data, options.get("gain_sigma")) > 0:
            raise ConfigError("sensor.focal_length_rel_sigma: the focal-length gain is not estimated from data "
                              "relative to a user reference (not implemented); set it to 0 for this session, or "
                              "record against the factory reference")
        keep = ("outlier_alpha", "progress", "tolerances")
        return referenced_session(data, **{k: v for k, v in options.items() if k in keep})
    return METHODS[method](data, **options)


def gain_prior(data: SessionData, gain_sigma: float | None = None) -> float:
    """The focal-length gain's prior 1-sigma of a session: the given one, else the bench's
    ``sensor.focal_length_rel_sigma``."""
    return float(data.model.bench.sensor.focal_length_rel_sigma if gain_sigma is None else gain_sigma)


def estimate_one(model: ForwardModel, z: np.ndarray, starts, estimator: str = "lm",
                 **options) -> tuple[PoseEstimate | None, str]:
    """A lens pose from the first start (None: nominal) that converges; (None, reason) otherwise."""
    reason = ""
    for x0 in starts:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UnobservableWarning)
                est = estimate_pose_model(model, z, x0=np.clip(x0, -4.0, 4.0) if x0 is not None else None,
                                          method=estimator, **options)
        except LensforgeError as e:
            reason = str(e)
            continue
        if est.converged:
            return est, ""
        reason = est.message
    return None, reason or "the estimate did not converge"


def _informative(cov: np.ndarray) -> np.ndarray:
    """cov with its unobserved (non-finite) entries replaced: no information along them."""
    bad = ~np.isfinite(cov)
    return np.where(bad, 0.0, cov) + np.where(np.isinf(np.diag(cov))[:, None] & np.eye(6, dtype=bool),
                                              UNINFORMATIVE_VARIANCE, 0.0)


def _lens_poses(data: SessionData, x_start: np.ndarray, estimator: str, max_iter: int, estimator_options: dict):
    """Per pose: (pose, cov, chi2/dof) or the reason it has none."""
    model = data.model
    dof = len(model.modes) - 6
    out = []
    if estimator == "lm":  # all poses at once; a pose that fails is retried alone from nominal
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UnobservableWarning)
            batch = estimate_poses_batch(model, data.z, np.clip(x_start, -4.0, 4.0), max_iter=max_iter)
        for k in range(len(data.ids)):
            if batch.converged[k] and np.all(np.isfinite(np.diag(batch.cov[k]))):
                out.append((batch.poses[k], batch.cov[k], float(batch.chi2[k]) / dof))
                continue
            est, reason = estimate_one(model, data.z[k], [None])
            out.append((est.pose, est.cov, est.chi2_dof) if est is not None else reason)
        return out
    for k in range(len(data.ids)):
        est, reason = estimate_one(model, data.z[k], [x_start[k], None], estimator, **estimator_options)
        out.append((est.pose, est.cov, est.chi2_dof) if est is not None else reason)
    return out


def _solve(A, B, C, noise, method: str):
    with warnings.catch_warnings():  # weak motion is reported in the result, not printed
        warnings.simplefilter("ignore", RuntimeWarning)
        return solve_handeye(A, B, method=method, sigma=noise, cov_B=C, on_degenerate="warn")


def two_stage(data: SessionData, *, outlier_alpha: float = OUTLIER_ALPHA, progress=None, tolerances=None,
              estimator: str = "lm", estimator_options: dict | None = None, handeye_method: str = "ml",
              max_iter: int = 40, min_poses: int = 3) -> CalibrationResult:
    """Two-stage calibration of a matched session (module docstring).

    estimator: a ``pose_estimation.ESTIMATORS`` name ("lm": batched over all poses);
    estimator_options: its keywords (e.g. the UKF's prior_cov); handeye_method: "ml",
    "shah" or "li"; max_iter: LM iterations per pose; min_poses: fewer poses with a lens
    pose than this is a CalibrationError; tolerances: unused (the nominal lens is assumed);
    progress: callable (done, total) after the lens poses. The result's ``estimates`` hold
    each used pose's lens pose and covariance."""
    model, scene = data.model, data.scene
    rejected = list(data.rejected)
    # initial guesses: the lens pose the nominal cell predicts for each recorded flange pose
    x_cell = matrix_to_pose(invert_poses(scene.T_SO_nominal) @ invert_poses(scene.Z) @ data.A @ scene.X)
    poses = _lens_poses(data, x_cell, estimator, max_iter, estimator_options or {})
    if progress is not None:
        progress(len(data.ids), len(data.ids))
    keep_idx = [k for k, p in enumerate(poses) if not isinstance(p, str)]
    for k, p in enumerate(poses):
        if isinstance(p, str):
            rejected.append({"pose": data.ids[k], "reason": f"lens pose not found (unlit or out of range): {p}",
                             "code": "no-estimate"})
    if len(keep_idx) < max(3, min_poses):
        raise TooFewPosesError(f"calibrate: only {len(keep_idx)} poses gave a lens pose (need >= {max(3, min_poses)}); "
                               + "; ".join(f"{r['pose']}: {r['reason']}" for r in rejected[:3]), rejected)
    ids = [data.ids[k] for k in keep_idx]
    A = data.A[keep_idx]
    x_est = np.array([poses[k][0] for k in keep_idx])
    cov = np.array([_informative(poses[k][1]) for k in keep_idx])
    est_chi2 = np.array([poses[k][2] for k in keep_idx])
    dof = len(model.modes) - 6
    # robust test on the lens-pose fits: a wrong local minimum or a corrupted frame fits far worse than the rest
    fit_thr = robust_chi2_threshold(est_chi2 * dof, dof, outlier_alpha)
    bad_fit = est_chi2 * dof > fit_thr
    if bad_fit.any() and (~bad_fit).sum() >= 3:
        for k in np.flatnonzero(bad_fit):
            rejected.append({"pose": ids[k], "reason": f"outlier: lens-pose fit chi2/dof {est_chi2[k]:.3g} above the "
                             f"robust {100 * (1 - outlier_alpha):.1f} % threshold {fit_thr / dof:.3g}",
                             "code": "outlier"})
        good = ~bad_fit
        ids = [i for i, g in zip(ids, good) if g]
        A, x_est, cov, est_chi2 = A[good], x_est[good], cov[good], est_chi2[good]
    B = scene.T_SO_nominal @ pose_to_matrix(x_est)
    C = np.stack([pose_vector_cov_to_right(x, c) for x, c in zip(x_est, cov)])
    noise = scene.noise
    he = _solve(A, B, C, noise, handeye_method)
    # robust outlier test on the per-pose residual chi2 (scaled by the median / its expectation)
    first_chi2 = he.residual_chi2.copy()
    thr = robust_chi2_threshold(first_chi2, 6, outlier_alpha)
    out = first_chi2 > thr
    keep = ~out
    if out.any() and keep.sum() >= 3:
        he = _solve(A[keep], B[keep], C[keep], noise, handeye_method)
    else:
        keep = np.ones(len(ids), bool)
    chi2_final = dict(zip(np.array(ids)[keep].tolist(), he.residual_chi2.tolist()))
    per_pose = []
    for k, i in enumerate(ids):
        per_pose.append({"pose": i, "handeye_chi2": chi2_final.get(i, float(first_chi2[k])),
                         "estimate_chi2_dof": float(est_chi2[k]), "outlier": bool(out[k])})
        if not keep[k]:
            rejected.append({"pose": i, "reason": f"outlier: hand-eye residual chi2 {first_chi2[k]:.3g} above the "
                             f"robust {100 * (1 - outlier_alpha):.1f} % threshold {thr:.3g}", "code": "outlier"})
    used = tuple(np.array(ids)[keep].tolist())
    p = float(chi2_dist.sf(he.chi2, he.dof)) if he.dof > 0 else float("nan")
    warns = list(he.warnings)
    if he.dof > 0 and p < 1e-3:
        warns.append(f"model check failed: chi2/dof = {he.chi2_dof:.3g} (p = {p:.2g}): the residuals exceed the "
                     "noise model; the lens as built may differ from its design (a joint as-built calibration "
                     "estimates it) or the robot/sensor noise is larger than assumed; the reported 1-sigma are "
                     "then too small")
    if gain_prior(data) > 0:
        warns.append("the sensor's focal-length gain (sensor.focal_length_rel_sigma > 0) is estimated only by "
                     "the joint method; the two-stage pipeline takes the bench's lenslet_focal_mm as exact")
    m_fit = float(np.median(est_chi2))
    if dof > 0 and m_fit > chi2_dist.ppf(0.999, dof) / dof:
        warns.append(f"lens-pose fits: median chi2/dof = {m_fit:.3g} over {dof} DOF: the measured wavefronts do "
                     "not match the design's model (lens as built, bench pupil/wavelength, or sensor noise)")
    estimates = tuple((i, x, c) for i, x, c, k in zip(ids, x_est, cov, keep) if k)
    return CalibrationResult(X=he.X, Z=he.Z, handeye=he, poses_used=used, poses_rejected=tuple(rejected),
                             per_pose=tuple(per_pose), chi2=float(he.chi2), dof=int(he.dof),
                             chi2_dof=float(he.chi2_dof), p_value=p, method="two-stage", robot=data.robot_name,
                             warnings=tuple(warns), outlier_threshold=thr, estimates=estimates)


def _fallback(data: SessionData, reason: str, start: CalibrationResult | None, **kw) -> CalibrationResult:
    r = start if isinstance(start, CalibrationResult) else two_stage(data, **kw)
    w = (f"the joint as-built calibration could not run ({reason}); fell back to the two-stage pipeline, "
         "which assumes the lens as designed",)
    return replace(r, warnings=w + tuple(r.warnings), extra={**r.extra, "fallback": {"from": "joint", "reason": reason}})


def joint(data: SessionData, *, tolerances="default", start=two_stage, **kw) -> CalibrationResult:
    """Joint as-built calibration of a matched session (module docstring).

    tolerances: the tolerance model of the lens prior (Tolerances, "default", a TOML path;
    None or "none": the two-stage fallback); start: the start method (default
    ``two_stage``), or its CalibrationResult when already computed on the same data, or None
    (the cell's nominal X, Z only); gain_sigma: the prior of the sensor's focal-length gain
    (default ``bench.sensor.focal_length_rel_sigma``; with a gain the joint fit runs even
    when the lens is known, tolerances "none"); other keywords go to both methods where
    they apply (outlier_alpha, progress)."""
    ts_kw = {k: v for k, v in kw.items() if k in ("outlier_alpha", "progress")}
    gain_sigma = gain_prior(data, kw.get("gain_sigma"))
    known_lens = no_tolerance_model(tolerances)
    if known_lens and not gain_sigma > 0:
        return _fallback(data, "no tolerance model for the as-built lens prior (tolerances: none)", start, **ts_kw)
    try:  # the lens known but the sensor's focal length free: the joint fit with no lens directions
        return joint_session(data, start=start, tolerances="default" if known_lens else tolerances,
                             known_lens=known_lens, gain_sigma=gain_sigma, **ts_kw)
    except CalibrationError as e:
        return _fallback(data, f"the joint fit failed: {e}", start, **ts_kw)


METHODS = {"joint": joint, "two-stage": two_stage}  # name -> function(SessionData, **options) -> CalibrationResult
