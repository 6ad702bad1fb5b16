"""The real-bench calibration session: plan the robot poses, estimate one lens pose,
calibrate X and Z from a WFS export and the recorded flange poses.

Frames (DESIGN.md): A = ^W T_E (flange in the robot base), B = ^S T_O (lens in the
sensor frame), X = ^E T_O (grasp), Z = ^W T_S (sensor in the robot base); mm, rad.

``plan``: the joint calibration's experiment design (``joint_design.design_joint_poses``:
Ds-optimal for Z with the as-built lens parameters free) of lens poses in a working
box about the nominal placement, among candidates whose pupil stays lit on the
design's model (with a lateral margin) and whose flange pose the robot reaches
(inverse kinematics within the joint limits); the flange poses follow from the
robot's cell (nominal Z and X, robot TOML [cell]).

``calibrate``: ``method="two-stage"``: (1) each measured Zernike vector gives a lens
pose with its covariance (``pose_estimation``, Levenberg-Marquardt from the pose the
cell predicts for the recorded flange pose, then from nominal); (2) A X = Z B by
maximum likelihood (``handeye.solve_handeye``) with the robot's repeatability and
each pose's covariance. Poses are matched by id; ids in one file only, unlit poses
and poses whose estimate fails are reported and left out. Outliers, two robust
tests (Bonferroni 1 - alpha/n quantile of the chi2 law, scaled up by the median
chi2 over its expectation so that an overall misfit does not reject every pose):
first on each lens-pose fit (m - 6 DOF: a wrong local minimum or a corrupted frame),
then on each pose's hand-eye residual (6 DOF), after which the solve is repeated once. Model check: chi2 of the final solve against its degrees
of freedom (p-value); a small p-value warns that the lens as built or the noise
model differs from what the design says. ``method="joint"`` (the default,
``session_joint``) estimates the as-built lens with X and Z.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace
from os import PathLike
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.stats import chi2 as chi2_dist

from ..errors import CalibrationError, ConfigError, LensforgeError, PoseRangeError
from ..optics.bench import Bench
from ..optics.lens import Lens, LensSpec, resolve_lens
from ..optics.pose import invert_poses, matrix_to_pose, pose_to_matrix, pose_vector_cov_to_right
from ..optics.sensitivity import metrics
from ..optics.shack_hartmann import ForwardModel
from ..optics.zernike import from_thorlabs_vector
from . import formats
from .handeye import solve_handeye
from .joint_design import candidate_information, design_joint_poses
from ..asbuilt.lens_params import parameterise
from .pose_design import candidate_poses
from .pose_estimation import PoseEstimate, UnobservableWarning, estimate_pose_model, estimate_poses_batch
from .robot import RobotModel, Scene, inverse_kinematics, load_robot, robot_scene
from .session_joint import joint_session, resolve_tolerances
from .session_result import OUTLIER_ALPHA, SCHEMA_VERSION, CalibrationResult, SessionData, frame_dict, std_dict

if TYPE_CHECKING:
    from ..asbuilt.tolerances import Tolerances

__all__ = ["Plan", "plan", "lit_mask", "lens_pose_crlb", "CalibrationResult", "SessionData", "match_session",
           "two_stage", "calibrate", "estimate", "load_design_lens",
           "bench_for_measurements", "zernike_for_model", "frame_dict", "CALIBRATION_METHODS", "SCHEMA_VERSION"]

CALIBRATION_METHODS: dict = {}  # name -> function(SessionData, *, outlier_alpha, progress) -> CalibrationResult


# ----------------------------------------------------------------------------- inputs


def load_design_lens(design: LensSpec, bench: Bench | None = None) -> tuple[Lens, Bench]:
    """(lens, bench) of anything ``optics.lens.resolve_lens`` takes (design file, paper
    lens, Lens, Design); the bench is the given one, else the design's, else the default."""
    r = resolve_lens(design)
    return r.lens, r.bench_or(bench)


def bench_for_measurements(bench: Bench, wfs: formats.WfsData) -> Bench:
    """The bench with the WFS file's Zernike order, pupil and wavelength (the file
    describes the instrument's settings; absent header values keep the bench's)."""
    h = wfs.header
    sensor = {"zernike_order": int(wfs.order)}
    if "pupil_radius_mm" in h:
        sensor["pupil_radius_mm"] = float(h["pupil_radius_mm"])
    if "pupil_center_mm" in h:
        sensor["pupil_center_mm"] = tuple(float(v) for v in h["pupil_center_mm"])
    changes = {"sensor": sensor}
    if "wavelength_nm" in h:
        changes["laser"] = {"wavelength_nm": float(h["wavelength_nm"])}
    return bench.replace(**changes)


def zernike_for_model(z_thorlabs, model: ForwardModel) -> np.ndarray:
    """Noll-ordered coefficients (n, m) of the model's modes from Thorlabs-ordered rows
    (n, K) (piston dropped)."""
    z = np.atleast_2d(np.asarray(z_thorlabs, dtype=float))
    out = []
    for row in z:
        noll, c = from_thorlabs_vector(row)
        lut = dict(zip(noll.tolist(), c))
        out.append([lut[int(j)] for j in model.modes])
    return np.array(out)


def _as_table(obj, reader):
    return obj if not isinstance(obj, (str, Path)) else reader(obj)


def lit_mask(model: ForwardModel, x: np.ndarray, margin_mm: float) -> np.ndarray:
    """Poses (k, 6) lit on the model at x and at +-margin_mm in tx and ty, inside the
    bench's pose range."""
    x = np.atleast_2d(x)
    shifts = np.zeros((5, 6))
    shifts[1, 0], shifts[2, 0], shifts[3, 1], shifts[4, 1] = margin_mm, -margin_mm, margin_mm, -margin_mm
    P = (x[:, None, :] + shifts[None]).reshape(-1, 6)
    v = model.evaluate(P, check_range=False).valid.reshape(len(x), 5)
    lim = model.bench.pose_limits
    inside = (np.abs(x[:, :3]) <= lim.translation_mm).all(1) & (np.linalg.norm(x[:, 3:], axis=1) <= lim.rotation_rad)
    return v.all(1) & inside


def lens_pose_crlb(bench: Bench, lens: Lens) -> np.ndarray:
    """Pose-estimation CRLB (6x6, (mm, rad)^2) at nominal; CalibrationError if rank < 6."""
    m = metrics(bench, lens)
    if m.rank < 6:
        raise CalibrationError(f"lens: its pose is not fully observable (rank {m.rank} < 6); hand-eye calibration "
                               "needs all 6 DOF of the lens pose: use a freeform lens")
    return m.crlb


# ----------------------------------------------------------------------------- plan


@dataclass(frozen=True, eq=False)
class Plan:
    """Calibration poses for the robot.

    ids: pose ids ("1".."n"); x: (n, 6) lens poses relative to nominal (mm, rad); A:
    (n, 4, 4) flange poses ^W T_E (mm); joints: (n, 6) IK joint angles (rad);
    predicted: the joint design's predicted (Cramer-Rao) uncertainty
    (``asbuilt.joint_information.z_sigma`` keys; cov: (12 + k)^2, right perturbations of X, Z, then
    theta); z_std: (6,) predicted 1-sigma of Z with the as-built lens theta free (mm,
    rad, {S} axes); z_std_known_lens: the same were the lens known; random_ratio:
    random / designed RMS Z translation error (theta free); tolerances: the tolerance
    file of theta's prior; robot: the RobotModel; scene: the nominal cell; bench: the
    design's."""

    ids: tuple
    x: np.ndarray
    A: np.ndarray
    joints: np.ndarray
    predicted: dict
    z_std: np.ndarray
    z_std_known_lens: np.ndarray
    random_ratio: float
    robot: RobotModel
    scene: Scene
    bench: Bench
    work_translation_mm: float
    work_rotation_rad: float
    tolerances: str = "default"

    def files(self, formats_: tuple = ("csv", "json", "krl")) -> dict:
        """{file name: text} for the plan writers (formats.PLAN_WRITERS)."""
        out = {}
        extra = {"robot": self.robot.name, "frame": "flange ^W T_E in the robot base"}
        for f in formats_:
            if f not in formats.PLAN_WRITERS:
                raise ConfigError(f"plan format: {f!r} is not one of {', '.join(formats.PLAN_WRITERS)}")
            out.update(formats.PLAN_WRITERS[f](self.ids, self.A, joints_deg=np.degrees(self.joints), extra=extra))
        out["plan.json"] = formats.dumps_json(self.to_dict()) + "\n"
        return out

    def to_dict(self) -> dict:
        """JSON-ready summary (units in the keys)."""
        return {
            "schema_version": SCHEMA_VERSION,
            "kind": "calibration_plan",
            "robot": self.robot.name,
            "n_poses": len(self.ids),
            "design": "joint Ds-optimal for Z (as-built lens theta free, prior from the tolerances)",
            "tolerances": self.tolerances,
            "n_lens_parameters": len(self.predicted["theta_sigma"]),
            "work_box": {"translation_mm": self.work_translation_mm,
                         "rotation_deg": math.degrees(self.work_rotation_rad)},
            "predicted_Z_std": std_dict(self.z_std),
            "predicted_Z_std_known_lens": std_dict(self.z_std_known_lens),
            "predicted_Z_translation_rms_mm": float(self.predicted["Z_translation_mm"]),
            "predicted_Z_rotation_rms_deg": float(self.predicted["Z_rotation_deg"]),
            "predicted_Z_translation_rms_known_lens_mm": float(self.predicted["Z_translation_known_lens_mm"]),
            "predicted_Z_rotation_rms_known_lens_deg": float(self.predicted["Z_rotation_known_lens_deg"]),
            "random_over_designed_Z_translation": float(self.random_ratio),
            "poses": [{"pose": i, "lens_pose": {"tx_mm": p[0], "ty_mm": p[1], "tz_mm": p[2], "rx_rad": p[3],
                                                 "ry_rad": p[4], "rz_rad": p[5]},
                       "flange_xyzabc": formats.matrix_to_xyzabc(a).tolist(), "joints_deg": np.degrees(q).tolist()}
                      for i, p, a, q in zip(self.ids, self.x.tolist(), self.A, self.joints)],
        }


def plan(design: LensSpec, *, bench: Bench | None = None, robot: RobotModel | str | None = None, n: int = 12,
         seed: int = 0, tolerances: Tolerances | str | PathLike[str] | None = "default", work_translation_mm: float = 0.5,
         work_rotation_rad: float = math.radians(5.0), lit_margin_mm: float = 0.3, n_candidates: int = 100,
         n_random_sets: int = 5) -> Plan:
    """Calibration poses for the joint calibration (see the module docstring).

    design: design file / paper lens name / Lens; robot: RobotModel, registry name or
    TOML path (default KR 10); n: poses; tolerances: the tolerance model of the
    as-built lens prior (as ``calibrate``'s: "default", a TOML path or Tolerances;
    None or "none": the lens as designed, the design of the known-lens problem);
    work_*: the box about nominal the poses are drawn from (ASSUMPTION +-0.5 mm,
    +-5 deg, as verification/scenario.py); lit_margin_mm: lateral margin a pose must
    keep lit; n_random_sets: random n-pose plans of the lit candidates the design is
    compared with (median). The choice is ``joint_design.design_joint_poses`` (Ds-optimal
    for Z with X, the robot errors and the lens parameters theta as nuisances; theta
    from ``lens_params.parameterise`` over the lit candidates). Every pose is
    reach-checked by inverse kinematics and pupil-lit on the design's model.
    """
    lens, bench = load_design_lens(design, bench)
    robot = robot if isinstance(robot, RobotModel) else load_robot(robot)
    if int(n) != n or n < 3:
        raise ConfigError(f"n: need an integer >= 3 poses, got {n!r}")
    lens_known = no_tolerance_model(tolerances)  # no prior: the lens as designed, theta has no direction
    tol, tol_label = resolve_tolerances("default" if lens_known else tolerances)
    scene = robot_scene(robot, bench.placement.distance_mm)
    model = ForwardModel(bench, lens)
    lens_pose_crlb(bench, lens)  # a lens whose pose is not observable cannot calibrate: say so first
    rng = np.random.default_rng(seed)
    cand = candidate_poses(rng, n_candidates, work_translation_mm, work_rotation_rad)
    cand = cand[lit_mask(model, cand, lit_margin_mm)]
    if len(cand) < n:
        raise PoseRangeError(f"plan: only {len(cand)} candidate poses light the pupil in the working box "
                             f"(+-{work_translation_mm} mm, +-{math.degrees(work_rotation_rad):.1f} deg); shrink the box")
    # theta's directions over a sample of the working range (the joint fit re-derives them over its own poses)
    sub = cand[rng.choice(len(cand), min(len(cand), 32), replace=False)]
    param = parameterise(bench, lens, tol, sub, max_directions=0 if lens_known else None)
    try:
        res = design_joint_poses(bench, param, scene, n, cand, robot_cov=robot.noise.cov, check_reach=True)
    except ConfigError as e:
        raise PoseRangeError(f"plan: no {n} lit candidate poses the {robot.name} can reach in the working box "
                             f"(+-{work_translation_mm} mm, +-{math.degrees(work_rotation_rad):.1f} deg); check the "
                             f"robot file's [cell] (sensor and grasp) or shrink the box ({e})") from None
    joints, q = [], None
    for A in res.A:
        q = inverse_kinematics(A, robot, q0=q)
        joints.append(q)
    # random plans of the same size from the same lit candidates, traced in one batch: RMS Z translation 1-sigma
    xr = np.concatenate([cand[rng.choice(len(cand), n, replace=False)] for _ in range(n_random_sets)])
    Ir = candidate_information(bench, param, scene, xr, robot.noise.cov)[0].reshape(n_random_sets, n, 12 + param.k,
                                                                                    12 + param.k)
    F = Ir.sum(axis=1)
    F[:, 12:, 12:] += np.eye(param.k)  # theta's N(0, I) prior
    rand = [float(np.sqrt(np.trace(np.linalg.pinv(f, hermitian=True)[6:9, 6:9]))) for f in F]
    cov = res.chosen["cov"]
    cov_known = np.linalg.inv(np.linalg.inv(cov)[:12, :12])
    return Plan(ids=tuple(str(i + 1) for i in range(n)), x=res.x, A=res.A, joints=np.array(joints),
                predicted=res.chosen, z_std=np.sqrt(np.diag(cov)[6:12]), z_std_known_lens=np.sqrt(np.diag(cov_known)[6:12]),
                random_ratio=float(np.median(rand)) / res.chosen["Z_translation_mm"], robot=robot, scene=scene,
                bench=bench, work_translation_mm=work_translation_mm, work_rotation_rad=work_rotation_rad,
                tolerances="none" if lens_known else tol_label)


# ----------------------------------------------------------------------------- estimate


def _estimate_one(model: ForwardModel, z: np.ndarray, starts) -> tuple[PoseEstimate | None, str]:
    """LM estimate from the first start that converges; (None, reason) otherwise."""
    reason = ""
    for x0 in starts:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UnobservableWarning)
                est = estimate_pose_model(model, z, x0=np.clip(x0, -4.0, 4.0) if x0 is not None else None)
        except LensforgeError as e:
            reason = str(e)
            continue
        if est.converged:
            return est, ""
        reason = est.message
    return None, reason or "the estimate did not converge"


def estimate(design: LensSpec, measurement: str | PathLike[str] | formats.WfsData, *, bench: Bench | None = None, pose_id: str | None = None) -> dict:
    """One lens pose with its covariance from one WFS measurement.

    measurement: WFS CSV/JSON path or WfsData; pose_id selects a row (default: the
    file must hold exactly one). Returns {"pose_id", "estimate": PoseEstimate,
    "bench": the bench used}."""
    lens, bench = load_design_lens(design, bench)
    wfs = _as_table(measurement, formats.read_wfs)
    if pose_id is None:
        if len(wfs.ids) != 1:
            raise ConfigError(f"{wfs.source}: holds {len(wfs.ids)} poses; choose one with --pose ID")
        k = 0
    else:
        if str(pose_id) not in wfs.ids:
            raise ConfigError(f"{wfs.source}: field pose: no pose id {pose_id!r} (ids: {', '.join(wfs.ids[:10])}...)")
        k = wfs.ids.index(str(pose_id))
    b = bench_for_measurements(bench, wfs)
    model = ForwardModel(b, lens)
    z = zernike_for_model(wfs.zernike[k], model)[0]
    est, reason = _estimate_one(model, z, [None])
    if est is None:
        raise CalibrationError(f"{wfs.source}: row {wfs.rows[k]}: no lens pose found ({reason})")
    return {"pose_id": wfs.ids[k], "estimate": est, "bench": b}



def _threshold(n: int, scale: float, alpha: float = OUTLIER_ALPHA) -> float:
    return float(chi2_dist.ppf(1.0 - alpha / max(n, 1), 6) * scale)


def _solve(A, B, C, noise):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return solve_handeye(A, B, method="ml", sigma=noise, cov_B=C, on_degenerate="warn")


def match_session(design, measurements, robot_poses, *, bench: Bench | None = None,
                  robot: RobotModel | str | None = None) -> SessionData:
    """Read and match a session's files by pose id (ids in one file only are reported in
    ``rejected``; fewer than 3 matches is a ConfigError naming both files)."""
    lens, bench = load_design_lens(design, bench)
    robot = robot if isinstance(robot, RobotModel) else load_robot(robot)
    wfs = _as_table(measurements, formats.read_wfs)
    poses = _as_table(robot_poses, formats.read_robot_poses)
    rejected = []
    wfs_ids = set(wfs.ids)
    for i in poses.ids:
        if i not in wfs_ids:
            rejected.append({"pose": i, "reason": f"no WFS measurement in {Path(wfs.source).name}"})
    pose_ids = set(poses.ids)
    for i in wfs.ids:
        if i not in pose_ids:
            rejected.append({"pose": i, "reason": f"no robot pose in {Path(poses.source).name}"})
    common = [i for i in poses.ids if i in wfs_ids]
    if len(common) < 3:
        raise ConfigError(f"{wfs.source} and {poses.source}: field pose: only {len(common)} pose ids match "
                          f"(need >= 3); the ids of the two files must name the same poses")
    b = bench_for_measurements(bench, wfs)
    model = ForwardModel(b, lens)
    A = poses.T[[poses.ids.index(i) for i in common]]
    z = zernike_for_model(wfs.zernike[[wfs.ids.index(i) for i in common]], model)
    return SessionData(ids=tuple(common), A=A, z=z, model=model, robot=robot,
                       scene=robot_scene(robot, b.placement.distance_mm), rejected=tuple(rejected))


def calibrate(design: LensSpec, measurements: str | PathLike[str] | formats.WfsData,
              robot_poses: str | PathLike[str] | formats.PoseTable, *, bench: Bench | None = None,
              robot: RobotModel | str | None = None, method: str = "joint",
              tolerances: Tolerances | str | PathLike[str] | None = "default", outlier_alpha: float = OUTLIER_ALPHA,
              progress: Callable[[int, int], None] | None = None) -> CalibrationResult:
    """X and Z from a WFS export and the recorded flange poses (see the module docstring).

    design: design file / paper lens / Lens; measurements: WFS CSV/JSON path or
    WfsData; robot_poses: flange-pose CSV/JSON path or PoseTable; robot: RobotModel,
    name or TOML (repeatability -> robot noise; [cell] -> initial guesses); method: a
    CALIBRATION_METHODS name ("joint", the default: the as-built lens estimated with
    X and Z, ``session_joint``; "two-stage": nominal lens); tolerances: the tolerance
    model of the joint method's lens prior ("default": the package's file, or a TOML
    path; two-stage ignores it); progress: optional callable (done, total) called after each
    lens-pose estimate. Raises ConfigError/CalibrationError for bad input or fewer
    than 3 usable poses.
    """
    if method not in CALIBRATION_METHODS:
        raise ConfigError(f"method: {method!r} is not available; use one of {', '.join(CALIBRATION_METHODS)}")
    data = match_session(design, measurements, robot_poses, bench=bench, robot=robot)
    return CALIBRATION_METHODS[method](data, outlier_alpha=outlier_alpha, progress=progress, tolerances=tolerances)


def two_stage(data: SessionData, *, outlier_alpha: float = OUTLIER_ALPHA, progress=None,
              tolerances=None) -> CalibrationResult:
    """Two-stage calibration of a matched session: lens poses one by one, then A X = Z B
    by maximum likelihood, robust outlier test and chi2 model check (module docstring).
    tolerances: unused (the nominal lens is assumed)."""
    model, scene, robot = data.model, data.scene, data.robot
    rejected = list(data.rejected)
    common, A_all, z_all = data.ids, data.A, data.z
    # initial guesses: the lens pose the nominal cell predicts for each recorded flange pose
    T_nom_inv = invert_poses(scene.T_SO_nominal)
    x_cell = matrix_to_pose(T_nom_inv @ invert_poses(scene.Z) @ A_all @ scene.X)
    ids, A, B, C, est_chi2 = [], [], [], [], []
    # all poses at once (batched LM from the cell's prediction); a pose that fails is retried alone from nominal
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UnobservableWarning)
        batch = estimate_poses_batch(model, z_all, np.clip(x_cell, -4.0, 4.0))
    dof = len(model.modes) - 6
    for k, i in enumerate(common):
        if batch.converged[k] and np.all(np.isfinite(batch.cov[k])):
            pose, cov, chi2_dof = batch.poses[k], batch.cov[k], float(batch.chi2[k]) / dof
        else:
            est, reason = _estimate_one(model, z_all[k], [None])
            if est is None:
                rejected.append({"pose": i, "reason": f"lens pose not found (unlit or out of range): {reason}"})
                continue
            pose, cov, chi2_dof = est.pose, est.cov, est.chi2_dof
        ids.append(i)
        A.append(A_all[k])
        B.append(scene.T_SO_nominal @ pose_to_matrix(pose))
        C.append(pose_vector_cov_to_right(pose, cov))
        est_chi2.append(chi2_dof)
        if progress is not None:
            progress(k + 1, len(common))
    if len(ids) < 3:
        raise CalibrationError(f"calibrate: only {len(ids)} poses gave a lens pose (need >= 3); "
                               + "; ".join(f"{r['pose']}: {r['reason']}" for r in rejected[:3]))
    # robust test on the lens-pose fits: a wrong local minimum or a corrupted frame fits far worse than the rest
    fit = np.array(est_chi2) * dof
    fit_thr = float(chi2_dist.ppf(1.0 - outlier_alpha / len(ids), dof)
                    * max(1.0, float(np.median(fit)) / chi2_dist.median(dof)))
    bad_fit = fit > fit_thr
    if bad_fit.any() and (~bad_fit).sum() >= 3:
        for k in np.flatnonzero(bad_fit):
            rejected.append({"pose": ids[k], "reason": f"outlier: lens-pose fit chi2/dof {est_chi2[k]:.3g} above the "
                             f"robust {100 * (1 - outlier_alpha):.1f} % threshold {fit_thr / dof:.3g}"})
        keep_fit = np.flatnonzero(~bad_fit)
        ids = [ids[k] for k in keep_fit]
        A, B, C, est_chi2 = ([v[k] for k in keep_fit] for v in (A, B, C, est_chi2))
    A, B, C = np.array(A), np.array(B), np.array(C)
    noise = robot.noise
    he = _solve(A, B, C, noise)
    # robust outlier test on the per-pose residual chi2 (scaled by the median / its expectation)
    scale = max(1.0, float(np.median(he.residual_chi2)) / chi2_dist.median(6))
    thr = _threshold(len(ids), scale, outlier_alpha)
    first_chi2 = he.residual_chi2.copy()
    out = first_chi2 > thr
    keep = ~out
    if out.any() and keep.sum() >= 3:
        he = _solve(A[keep], B[keep], C[keep], noise)
    else:
        keep = np.ones(len(ids), bool)
    chi2_final = dict(zip(np.array(ids)[keep].tolist(), he.residual_chi2.tolist()))
    per_pose = []
    for k, i in enumerate(ids):
        per_pose.append({"pose": i, "handeye_chi2": chi2_final.get(i, float(first_chi2[k])), "estimate_chi2_dof": float(est_chi2[k]),
                         "outlier": bool(out[k])})
        if not keep[k]:
            rejected.append({"pose": i, "reason": f"outlier: hand-eye residual chi2 {first_chi2[k]:.3g} above the "
                             f"robust {100 * (1 - outlier_alpha):.1f} % threshold {thr:.3g}"})
    used = tuple(np.array(ids)[keep].tolist())
    p = float(chi2_dist.sf(he.chi2, he.dof)) if he.dof > 0 else float("nan")
    warns = list(he.warnings)
    if he.dof > 0 and p < 1e-3:
        warns.append(f"model check failed: chi2/dof = {he.chi2_dof:.3g} (p = {p:.2g}): the residuals exceed the "
                     "noise model; the lens as built may differ from its design (a joint as-built calibration "
                     "estimates it) or the robot/sensor noise is larger than assumed; the reported 1-sigma are "
                     "then too small")
    m_fit = float(np.median(est_chi2))
    fit_dof = len(model.modes) - 6
    if fit_dof > 0 and m_fit > chi2_dist.ppf(0.999, fit_dof) / fit_dof:
        warns.append(f"lens-pose fits: median chi2/dof = {m_fit:.3g} over {fit_dof} DOF: the measured wavefronts do "
                     "not match the design's model (lens as built, bench pupil/wavelength, or sensor noise)")
    return CalibrationResult(X=he.X, Z=he.Z, handeye=he, poses_used=used, poses_rejected=tuple(rejected),
                             per_pose=tuple(per_pose), chi2=float(he.chi2), dof=int(he.dof),
                             chi2_dof=float(he.chi2_dof), p_value=p, method="two-stage", robot=robot.name,
                             warnings=tuple(warns), outlier_threshold=thr)


def no_tolerance_model(tolerances) -> bool:
    """True for tolerances None or "none" (any case): no as-built lens prior."""
    return tolerances is None or (isinstance(tolerances, str) and tolerances.strip().lower() == "none")


def _fallback(data: SessionData, reason: str, **kw) -> CalibrationResult:
    r = two_stage(data, **kw)
    w = (f"the joint as-built calibration could not run ({reason}); fell back to the two-stage pipeline, "
         "which assumes the lens as designed",)
    return replace(r, warnings=w + tuple(r.warnings),
                               extra={**r.extra, "fallback": {"from": "joint", "reason": reason}})


def joint(data: SessionData, *, tolerances="default", **kw) -> CalibrationResult:
    """Joint as-built calibration of a matched session (``session_joint.joint_session``)
    started from the two-stage solution and from the cell's nominal X, Z. Falls back to
    ``two_stage`` (method "two-stage", a warning, and ``extra["fallback"]`` = {"from":
    "joint", "reason"}) when it cannot run: no tolerance model (tolerances None or
    "none") or the joint fit fails (CalibrationError, e.g. no start lights 3 poses).
    A tolerance file that cannot be read stays an error (the user's mistake)."""
    if no_tolerance_model(tolerances):
        return _fallback(data, "no tolerance model for the as-built lens prior (tolerances: none)", **kw)
    try:
        return joint_session(data, start=two_stage, tolerances=tolerances, **kw)
    except CalibrationError as e:
        return _fallback(data, f"the joint fit failed: {e}", **kw)


CALIBRATION_METHODS["joint"] = joint
CALIBRATION_METHODS["two-stage"] = two_stage
