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

``calibrate``: reads the WFS export and the recorded flange poses, matches them by pose
id (ids in one file only are reported and left out; ``match_session``) into a
``SessionData`` and runs the one calibration pipeline (``pipeline.run``: ``joint``, the
default, or ``two-stage``), the same code every simulation of ``verification`` runs.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from os import PathLike
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..asbuilt.lens_params import parameterise
from ..asbuilt.tolerances import no_tolerance_model, resolve_tolerances
from ..errors import CalibrationError, ConfigError, PoseRangeError
from ..input_checks import BENCH_RANGES, number
from ..optics.bench import Bench
from ..optics.lens import Lens, LensSpec, resolve_lens
from ..optics.sensitivity import metrics
from ..optics.shack_hartmann import ForwardModel
from ..optics.zernike import from_thorlabs_vector
from . import formats, thorlabs
from .cell_plausibility import check_cell_poses
from .measurement import Measurement, canonical_ids, slope_inputs, spot_bench
from .joint_design import candidate_information, design_joint_poses, predicted_joint_uncertainty
from .pipeline import METHODS, estimate_one, run
from .pose_design import candidate_poses, z_translation_std
from .pose_linearity import linearity_check
from .plausibility import (check_job_memory, check_poses_count, check_robot_reach, check_wfs_header,
                           check_wfs_values, job_memory_bytes, pose_file_kind, MAX_ROWS)
from .robot import RobotModel, Scene, inverse_kinematics, load_robot, robot_scene
from .session_result import OUTLIER_ALPHA, SCHEMA_VERSION, CalibrationResult, SessionData, std_dict

if TYPE_CHECKING:
    from ..asbuilt.tolerances import Tolerances

__all__ = ["Plan", "plan", "lit_mask", "lens_pose_crlb", "match_session", "calibrate", "estimate",
           "load_design_lens", "bench_for_measurements", "zernike_for_model", "PLAN_BOX"]

#: (mm, rad) half-widths of the plan's box of lens poses about nominal when the design records none
#: (ASSUMPTION +-0.5 mm, +-5 deg, as verification/scenario.py; a design file records the box it was
#: checked over, ``lensforge design --plan-mm / --plan-deg``)
PLAN_BOX = (0.5, math.radians(5.0))


# ----------------------------------------------------------------------------- inputs


def load_design_lens(design: LensSpec, bench: Bench | None = None) -> tuple[Lens, Bench]:
    """(lens, bench) of anything ``optics.lens.resolve_lens`` takes (design file, paper
    lens, Lens, Design); the bench is the given one, else the design's, else the default."""
    r = resolve_lens(design)
    return r.lens, r.bench_or(bench)


def bench_for_measurements(bench: Bench, wfs: formats.WfsData, wfs_header: str = "file") -> Bench:
    """The bench with the WFS file's Zernike order, pupil and wavelength (the file
    describes the instrument's settings; absent header values keep the bench's).
    wfs_header: "file" (the file's header values win), "bench" (they are ignored) or
    "error" (a header value that contradicts the bench is a ConfigError naming both;
    ``plausibility.check_wfs_header``)."""
    h = check_wfs_header(bench, wfs.header, wfs.source or "WFS file", wfs_header)
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
            # null: most random plans of this size leave Z's translation unobservable
            "random_over_designed_Z_translation": float(self.random_ratio) if math.isfinite(self.random_ratio) else None,
            "poses": [{"pose": i, "lens_pose": {"tx_mm": p[0], "ty_mm": p[1], "tz_mm": p[2], "rx_rad": p[3],
                                                 "ry_rad": p[4], "rz_rad": p[5]},
                       "flange_xyzabc": formats.matrix_to_xyzabc(a).tolist(), "joints_deg": np.degrees(q).tolist()}
                      for i, p, a, q in zip(self.ids, self.x.tolist(), self.A, self.joints)],
        }


def plan(design: LensSpec, *, bench: Bench | None = None, robot: RobotModel | str | None = None, n: int = 12,
         seed: int = 0, tolerances: Tolerances | str | PathLike[str] | None = "default",
         work_translation_mm: float | None = None, work_rotation_rad: float | None = None,
         lit_margin_mm: float = 0.3, n_candidates: int = 100,
         n_random_sets: int = 5, progress: Callable[[str], None] | None = None) -> Plan:
    """Calibration poses for the joint calibration (see the module docstring).

    The choice is ``joint_design.design_joint_poses`` (Ds-optimal for Z with X, the robot
    errors and the lens parameters theta as nuisances; theta from
    ``lens_params.parameterise`` over the lit candidates). Every pose is reach-checked by
    inverse kinematics and pupil-lit on the design's model. On a bench with the cross-talk
    sensor model the candidates are searched on the own-centroid model (the cross-talk model
    costs ~100x a pose and scales the CRLB near-uniformly) and the chosen plan's prediction
    (``predicted``, ``z_std``) comes from the cross-talk model.

    Parameters
    ----------
    design : LensSpec
        Design file, paper lens name or Lens.
    bench : Bench, optional
        Default: the design's bench, else the built-in one.
    robot : RobotModel or str, optional
        RobotModel, registry name or TOML path (default KR 10).
    n : int
        Number of poses.
    seed : int
        Seed of the candidates and of the random comparison plans.
    tolerances : Tolerances, str or os.PathLike, optional
        The tolerance model of the as-built lens prior ("default", a TOML path or
        Tolerances); None or "none": the lens as designed (the known-lens problem).
    work_translation_mm, work_rotation_rad : float, optional
        Half-widths of the box about nominal the poses are drawn from. Default: the box
        the design was checked over (its constraints' plan_mm / plan_rad, which
        ``lensforge design`` sets with --plan-mm / --plan-deg), else ``PLAN_BOX``
        (ASSUMPTION +-0.5 mm, +-5 deg, as verification/scenario.py).
    lit_margin_mm : float
        Lateral margin a pose must keep lit, mm.
    n_candidates : int
        Candidate poses the design chooses from.
    n_random_sets : int
        Random n-pose plans of the lit candidates the design is compared with (median).
    progress : callable, optional
        Called with the name of each stage as it starts (a progress bar's description).

    Returns
    -------
    Plan
        ``ids``, ``x`` (n, 6) lens poses (mm, rad), ``A`` (n, 4, 4) flange poses (mm),
        ``joints`` (n, 6) rad, the predicted Z 1-sigma ``z_std`` (6,) (mm, rad) with and
        without the lens free, and ``files()`` (CSV, JSON 4x4, KRL).

    Raises
    ------
    ConfigError
        Bad input (e.g. n < 3), or no candidate that is lit and reachable.
    PoseRangeError
        Fewer than n lit candidate poses the robot can reach in the working box.
    """
    resolved = resolve_lens(design)
    lens, bench = resolved.lens, resolved.bench_or(bench)
    box = resolved.plan_box or PLAN_BOX
    work_translation_mm = box[0] if work_translation_mm is None else work_translation_mm
    work_rotation_rad = box[1] if work_rotation_rad is None else work_rotation_rad
    for name, v, unit in (("work_translation_mm", work_translation_mm, "mm"),
                          ("work_rotation_rad", work_rotation_rad, "rad")):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ConfigError(f"{name}: the plan box's half-width must be a number > 0 {unit}, got {v!r}")
    robot = robot if isinstance(robot, RobotModel) else load_robot(robot)
    if int(n) != n or n < 3:
        raise ConfigError(f"n: need an integer >= 3 poses, got {n!r}")
    lens_known = no_tolerance_model(tolerances)  # no prior: the lens as designed, theta has no direction
    tol, tol_label = resolve_tolerances("default" if lens_known else tolerances)
    scene = robot_scene(robot, bench.placement.distance_mm)
    # the candidate search runs on the own-centroid sensor model: the cross-talk model (``sensor.crosstalk``)
    # costs ~100x a pose and scales the pose CRLB by a near-uniform 1.04-1.11 (paper lenses, 3 poses), which
    # leaves the ranking of candidates; the chosen plan's prediction is then the bench's own model's
    search = bench.own_centroid()
    stage = progress or (lambda _text: None)
    stage("plan: lighting the candidate poses")
    model = ForwardModel(search, lens)
    lens_pose_crlb(search, lens)  # a lens whose pose is not observable cannot calibrate: say so first
    rng = np.random.default_rng(seed)
    cand = candidate_poses(rng, n_candidates, work_translation_mm, work_rotation_rad)
    cand = cand[lit_mask(model, cand, lit_margin_mm)]
    if len(cand) < n:
        raise PoseRangeError(f"plan: only {len(cand)} candidate poses light the pupil in the working box "
                             f"(+-{work_translation_mm} mm, +-{math.degrees(work_rotation_rad):.1f} deg); ask for at most "
                             f"{len(cand)} poses")
    # theta's directions over a sample of the working range (the joint fit re-derives them over its own poses)
    sub = cand[rng.choice(len(cand), min(len(cand), 32), replace=False)]
    stage("plan: choosing the poses")
    param = parameterise(search, lens, tol, sub, as_designed=lens_known)
    try:
        res = design_joint_poses(search, param, scene, n, cand, robot_cov=robot.noise.cov, check_reach=True)
    except ConfigError as e:
        raise PoseRangeError(f"plan: no {n} lit candidate poses the {robot.name} can reach in the working box "
                             f"(+-{work_translation_mm} mm, +-{math.degrees(work_rotation_rad):.1f} deg); check the "
                             f"robot file's [cell] (sensor and grasp) or shrink the box ({e})") from None
    joints, q = [], None
    for A in res.A:
        q = inverse_kinematics(A, robot, q0=q)
        joints.append(q)
    # random plans of the same size from the same lit candidates: RMS Z translation 1-sigma. Each distinct
    # candidate is traced once (a pose's information does not depend on the others), so the trace holds at
    # most len(cand) poses whatever n_random_sets * n is (150-pose plans reached 3.3 GB tracing 750)
    sets = np.array([rng.choice(len(cand), n, replace=False) for _ in range(n_random_sets)])
    used, inverse = np.unique(sets, return_inverse=True)
    Iu = candidate_information(search, param, scene, cand[used], robot.noise.cov)[0]
    F = Iu[inverse.reshape(sets.shape)].sum(axis=1)
    F[:, 12:, 12:] += np.eye(param.k)  # theta's N(0, I) prior
    rand = z_translation_std(F)
    random_ratio = float(np.median(rand)) / res.chosen["Z_translation_mm"]  # both on the search model
    if search is not bench:
        stage("plan: predicting the chosen poses with the cross-talk sensor model")
        res = replace(res, chosen=predicted_joint_uncertainty(bench, param, scene, res.x, robot.noise.cov))
    cov = res.chosen["cov"]
    cov_known = np.linalg.inv(np.linalg.inv(cov)[:12, :12])
    return Plan(ids=tuple(str(i + 1) for i in range(n)), x=res.x, A=res.A, joints=np.array(joints),
                predicted=res.chosen, z_std=np.sqrt(np.diag(cov)[6:12]), z_std_known_lens=np.sqrt(np.diag(cov_known)[6:12]),
                random_ratio=random_ratio, robot=robot, scene=scene,
                bench=bench, work_translation_mm=work_translation_mm, work_rotation_rad=work_rotation_rad,
                tolerances="none" if lens_known else tol_label)


# ----------------------------------------------------------------------------- estimate


def estimate(design: LensSpec, measurement: str | PathLike[str] | formats.WfsData, *, bench: Bench | None = None,
             pose_id: str | None = None, wfs_header: str = "error") -> dict:
    """One lens pose with its covariance from one WFS measurement.

    Parameters
    ----------
    design : LensSpec
        Design file, paper lens name or Lens.
    measurement : str, os.PathLike or WfsData
        WFS CSV/JSON path or WfsData.
    bench : Bench, optional
        Default: the design's bench, adjusted to the measurement's header.
    pose_id : str, optional
        The row to use (default: the file must hold exactly one).
    wfs_header : str
        "error" (a header value that contradicts the bench is a ConfigError naming both),
        "file" (the file's values win) or "bench" (they are ignored).

    Returns
    -------
    dict
        ``pose_id``, ``estimate`` (PoseEstimate: pose (6,) mm and rad, cov (6, 6)), ``bench`` (the bench
        used) and ``linearity`` (``pose_linearity.LinearityCheck``: is the covariance's Gaussian a fair account
        of the likelihood over its 3 sigma?).

    Raises
    ------
    ConfigError
        A bad file or pose id.
    """
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
    if isinstance(wfs, thorlabs.SpotFields):  # the likelihood on the per-lenslet slopes
        b = spot_bench(bench, wfs)
        meas, y, _ = slope_inputs(wfs, ForwardModel(b, lens), rows=[k])
        model, z, where = meas.model(ForwardModel(b, lens)), y[0], wfs.files[k]
    else:
        check_wfs_values(wfs.zernike[k:k + 1], wfs.source or "WFS file", wfs.rows[k:k + 1])
        b = bench_for_measurements(bench, wfs, wfs_header)
        model = ForwardModel(b, lens)
        z = zernike_for_model(wfs.zernike[k], model)[0]
        where = f"{wfs.source}: row {wfs.rows[k] if k < len(wfs.rows) else k + 1}"
    est, reason = estimate_one(model, z, [None])
    if est is None:
        raise CalibrationError(f"{where}: no lens pose found ({reason})")
    return {"pose_id": wfs.ids[k], "estimate": est, "bench": b,
            "linearity": linearity_check(model, z, est.pose, est.cov, est.chi2)}



def match_session(design, measurements, robot_poses, *, bench: Bench | None = None,
                  robot: RobotModel | str | None = None, wfs_header: str = "error", pose_pattern: str | None = None,
                  reference_pose: str | None = None) -> SessionData:
    """Read and match a session's files by pose id (ids in one file only are reported in
    ``rejected``; fewer than 3 matches is a ConfigError naming both files). measurements:
    a WFS file, or a folder/glob of per-pose instrument files (``formats.read_wfs``;
    pose_pattern: the file-name pattern of their ids); integer ids match as integers;
    reference_pose: the pose of a user reference the measurements are relative to
    (default: the files' own ``reference_pose``; ``measurement.referenced_session``).
    Implausible inputs are refused first (``plausibility``): an all-zero or constant WFS
    file, header values that contradict the bench (wfs_header: "error", "file" or "bench"),
    flange poses beyond the robot's reach or that the cell's nominal sensor and grasp put far
    from the sensor (``cell_plausibility.check_cell_poses``), more than
    ``plausibility.MAX_ROWS`` rows in a file or ``plausibility.MAX_POSES`` matched poses."""
    lens, bench = load_design_lens(design, bench)
    robot = robot if isinstance(robot, RobotModel) else load_robot(robot)
    wfs = _as_table(measurements, lambda p: formats.read_wfs(p, pose_pattern=pose_pattern))
    poses = _as_table(robot_poses, formats.read_robot_poses)
    check_poses_count(len(poses.ids), f"{poses.source or 'robot poses'}: rows", MAX_ROWS)
    check_poses_count(len(wfs.ids), f"{wfs.source or 'WFS file'}: rows", MAX_ROWS)
    units = pose_file_kind(robot_poses)[1] if isinstance(robot_poses, (str, PathLike)) else None
    check_robot_reach(poses.T, robot, poses.source or "robot poses", poses.rows, units)
    poses, wfs, ref = canonical_ids(poses, wfs, reference_pose)
    if not isinstance(wfs, thorlabs.SpotFields):  # the reference pose's own row is zero by construction
        rows = [k for k, i in enumerate(wfs.ids) if i != ref]
        check_wfs_values(wfs.zernike[rows], wfs.source or "WFS file",
                         tuple(wfs.rows[k] if k < len(wfs.rows) else k + 1 for k in rows))
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
    check_poses_count(len(common), f"{wfs.source} and {poses.source}: matched poses")
    at = [poses.ids.index(i) for i in common]
    A = poses.T[at]
    scene = robot_scene(robot, bench.placement.distance_mm)  # the measurements' bench keeps the placement
    # the matched poses only: a robot log may hold home and approach poses that have no measurement
    check_cell_poses(replace(poses, ids=tuple(common), T=A, rows=tuple(poses.rows[k] for k in at)
                             if len(poses.rows) == len(poses.ids) else (), times=None),
                     scene, bench,
                     robot_poses if isinstance(robot_poses, (str, PathLike)) else (poses.source or None))
    meas = None
    if isinstance(wfs, thorlabs.SpotFields):  # the likelihood on the per-lenslet slopes
        b = spot_bench(bench, wfs)
        meas, z, _ = slope_inputs(wfs, ForwardModel(b, lens), rows=[wfs.ids.index(i) for i in common])
        model = meas.model(ForwardModel(b, lens))
    else:
        b = bench_for_measurements(bench, wfs, wfs_header)
        model = ForwardModel(b, lens)
        z = zernike_for_model(wfs.zernike[[wfs.ids.index(i) for i in common]], model)
    check_job_memory(job_memory_bytes(len(common), len(model.modes), model.pupil.n_lenslets),
                     f"calibrating {len(common)} poses", f"{poses.source or 'robot poses'}")
    if ref is not None:
        meas = Measurement(meas.kind if meas else "zernike", meas.lenslets if meas else None,
                           meas.dropped if meas else (), reference=common.index(ref))
    return SessionData(ids=tuple(common), A=A, z=z, model=model, robot=robot,
                       scene=scene, rejected=tuple(rejected), measurement=meas)


def calibrate(design: LensSpec, measurements: str | PathLike[str] | formats.WfsData,
              robot_poses: str | PathLike[str] | formats.PoseTable, *, bench: Bench | None = None,
              robot: RobotModel | str | None = None, method: str = "joint",
              tolerances: Tolerances | str | PathLike[str] | None = "default", outlier_alpha: float = OUTLIER_ALPHA,
              progress: Callable[[int, int], None] | None = None, wfs_header: str = "error",
              pose_pattern: str | None = None, reference_pose: str | None = None,
              focal_length_sigma: float | None = None) -> CalibrationResult:
    """X and Z from a WFS export and the recorded flange poses (see the module docstring).

    Parameters
    ----------
    design : LensSpec
        Design file, paper lens name or Lens.
    measurements : str, os.PathLike or WfsData
        WFS CSV/JSON path or WfsData.
    robot_poses : str, os.PathLike or PoseTable
        Flange-pose CSV/JSON path or PoseTable.
    bench : Bench, optional
        Default: the design's bench, adjusted to the measurements' header.
    robot : RobotModel or str, optional
        RobotModel, name or TOML (repeatability -> robot noise; [cell] -> initial guesses).
    method : str
        A ``pipeline.METHODS`` name: "joint" (the default: the as-built lens estimated with
        X and Z, ``session_joint``) or "two-stage" (nominal lens).
    tolerances : Tolerances, str or os.PathLike, optional
        The tolerance model of the joint method's lens prior ("default": the package's
        file, or a TOML path; two-stage ignores it).
    outlier_alpha : float
        Significance of the chi-square outlier test per pose.
    progress : callable, optional
        Called (done, total) after the lens-pose estimates.
    wfs_header : str
        "error" (a WFS header value that contradicts the bench is a ConfigError naming both),
        "file" (the file's values win) or "bench" (they are ignored); see ``match_session``.
    pose_pattern : str, optional
        A regular expression whose first group is the pose id in a measurement file's name
        (default: its last integer), for a folder or glob of per-pose instrument files.
    reference_pose : str, optional
        The pose id of the user reference the measurements are relative to (default: the
        files' own ``reference_pose``, if any).
    focal_length_sigma : float, optional
        Relative 1-sigma prior of the sensor's effective lenslet focal length, estimated by
        the joint method (default: the bench's ``sensor.focal_length_rel_sigma``; 0: known).

    Returns
    -------
    CalibrationResult
        ``X`` = ^E T_O and ``Z`` = ^W T_S (4x4, mm), the hand-eye result with covariances,
        poses used and rejected, per-pose chi2, the model check's p-value, warnings; its
        ``valid`` says whether it passed its chi2 model check (``model_check``): one that
        did not is not a calibration (``calibration.diagnosis`` names the likely mistake).

    Raises
    ------
    ConfigError, CalibrationError
        Bad input or fewer than 3 usable poses.
    """
    if method not in METHODS:
        raise ConfigError(f"method: {method!r} is not available; use one of {', '.join(METHODS)}")
    if focal_length_sigma is not None:
        focal_length_sigma = number(focal_length_sigma, "focal_length_sigma (--focal-length-sigma)",
                                    BENCH_RANGES["sensor.focal_length_rel_sigma"])
        if focal_length_sigma > 0 and method != "joint":
            raise ConfigError(f"focal_length_sigma (--focal-length-sigma): the focal-length gain is estimated "
                              f"only by the joint method, not {method}; use --method joint")
    data = match_session(design, measurements, robot_poses, bench=bench, robot=robot, wfs_header=wfs_header,
                         pose_pattern=pose_pattern, reference_pose=reference_pose)
    opts = {} if focal_length_sigma is None or method != "joint" else {"gain_sigma": focal_length_sigma}
    return run(data, method, outlier_alpha=outlier_alpha, progress=progress, tolerances=tolerances, **opts)
