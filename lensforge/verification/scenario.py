"""The paper's hand-eye calibration procedure as a simulation (Sec. 4.3, Eq. 21-22).

One calibration run:

1. Scene: the true sensor pose Z = ^W T_S (paper Eq. 21) and the true grasp
   X = ^E T_O differ from what the robot believes (CAD Z, nominal grasp X): grasp
   error from ``initial_poses.InitialPoseModel`` (0.3 mm / 0.5 deg) and a sensor
   placement error of the CAD Z (``ScenarioConfig.sensor_cad_*``, ASSUMPTION
   0.2 mm / 0.2 deg: the sensor was aligned by hand so that the nominal lens
   placement lights the pupil; the paper's real cell was ~45 mm off and lost the
   beam, Sec. 5).
2. Convergence: the robot visits ``n_convergence`` (12) poses near nominal; the
   lens pose is estimated at each from a noisy measurement. The paper uses these
   to let its UKF converge. Here they give the constant offset between commanded
   and actual lens pose (mean of log(B_cmd^-1 B_est)), which is then taken off the
   commands, so the calibration poses land where they were planned and the
   estimator starts close.
3. Calibration: ``n_calibration`` (12) lens poses in the working box (ASSUMPTION
   +-0.5 mm, +-5 deg about nominal) where the pupil stays lit (checked on the
   nominal lens model with a 0.3 mm lateral margin): random, or chosen by
   D-optimal design (``calib_design.design_poses``). The robot lands with its
   repeatability noise, the sensor measures with noise, the lens pose and its
   covariance are estimated (``estimate_pose``, lm or ukf), and A X = Z B is solved
   with the ``ml`` solver using the robot noise and each pose's estimator
   covariance (converted to the solver's right perturbation).
4. Score: the error of Z (rotation and translation norms of log(Z_true^-1 Z_est),
   right perturbation, {S} axes) against the solver's predicted covariance cov_Z
   (NEES) and against the design-time bound (``calib_design.predicted_uncertainty``).

Poses where the true lens does not light the pupil are dropped and counted.
All randomness flows from one SeedSequence per run (explicit rng, no globals).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from ..errors import CalibrationError, ConfigError, PupilError
from ..optics.bench import Bench
from ..optics.lens import Lens
from ..optics.pose import invert_poses, matrix_to_pose, pose_to_matrix
from ..optics.shack_hartmann import ForwardModel
from ..calibration.initial_poses import InitialPoseModel, prior_covariance
from ..calibration.pose_design import candidate_poses, design_poses, predicted_uncertainty
from ..calibration.pose_estimation import ESTIMATORS
from ..calibration.pipeline import estimate_one, run
from ..calibration.session import lens_pose_crlb, lit_mask
from ..calibration.robot import PAPER_Z, Scene, flange_pose, paper_scene, random_lens_poses
from .session_sim import record_session
from .statistics import median

__all__ = ["scenario_scene", "ScenarioConfig", "CalibrationRun", "run_calibration", "plan_poses", "compare_pose_designs",
           "format_comparison"]


def scenario_scene(bench: Bench, grasp: str = "side") -> Scene:
    """The paper's cell (Z of Eq. 21) with a grasp X.

    grasp="top": ``robot.paper_scene`` (tool pointing down, lens 150 mm below the
    flange). Its nominal pose has joint A5 at 117.8 deg of the KR 10's +-120 deg, so
    about half the lens poses tilted by a few degrees are unreachable.
    grasp="side" (default, ASSUMPTION): the tool points horizontally along -y of {W}
    (from the robot towards the sensor's beam line), lens 150 mm along tool z, lens
    axes parallel to {S} at nominal; the flange then sits at (20, -350, 1000) mm and
    every pose of the +-0.5 mm / +-10 deg box is reachable.
    """
    if grasp == "top":
        return paper_scene(bench.placement.distance_mm)
    if grasp != "side":
        raise ConfigError(f"grasp: {grasp!r} is not side or top")
    R_E = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # flange axes in {W}
    X = np.eye(4)
    X[:3, :3] = R_E.T @ PAPER_Z[:3, :3]
    X[:3, 3] = (0.0, 0.0, 150.0)
    return Scene(X=X, distance_mm=float(bench.placement.distance_mm))


@dataclass(frozen=True)
class ScenarioConfig:
    """Options of the simulated calibration (mm, rad; see the module docstring).

    n_convergence, n_calibration: poses per phase (paper: 12 and 12);
    convergence_translation_mm / _rotation_rad: box of the convergence poses;
    work_translation_mm / work_rotation_rad: working box of the calibration poses
    (ASSUMPTION +-0.5 mm, +-5 deg: lit for all four paper lenses on the default bench);
    lit_margin_mm: lateral margin a planned pose must keep lit (nominal model);
    sensor_cad_translation_mm / _rotation_rad: 1-sigma CAD error of Z (ASSUMPTION);
    grasp: gripper/robot uncertainty of the grasp; estimator: "lm" or "ukf";
    ukf_repeats: for ukf.
    """

    n_convergence: int = 12
    n_calibration: int = 12
    convergence_translation_mm: float = 0.2
    convergence_rotation_rad: float = math.radians(1.0)
    work_translation_mm: float = 0.5
    work_rotation_rad: float = math.radians(5.0)
    lit_margin_mm: float = 0.3
    sensor_cad_translation_mm: float = 0.2
    sensor_cad_rotation_rad: float = math.radians(0.2)
    grasp: InitialPoseModel = field(default_factory=InitialPoseModel)
    estimator: str = "lm"
    ukf_repeats: int = 12

    def __post_init__(self):
        if self.estimator not in ESTIMATORS:
            raise ConfigError(f"scenario.estimator: {self.estimator!r} is not one of {', '.join(ESTIMATORS)}")
        if self.n_calibration < 3 or self.n_convergence < 0:
            raise ConfigError("scenario: n_calibration must be >= 3 and n_convergence >= 0")


@dataclass(frozen=True, eq=False)
class CalibrationRun:
    """One simulated calibration.

    Z_true, Z_est, X_true, X_est: 4x4 (mm); z_error: (6,) right-perturbation error of
    Z (mm, rad, {S} axes); cov_Z: the solver's 6x6 prediction; nees_Z: z_error^T
    cov_Z^-1 z_error (~ chi2 with 6 DOF when honest); x_planned: (n, 6) planned
    calibration lens poses; n_used: poses that entered the solve; pupil_lost:
    dropped poses; chi2_dof: of the hand-eye solve; observable: the solver's
    observability verdict (False: it flagged near-degenerate motion, see messages); offset: (6,) the convergence
    phase's commanded-vs-actual lens offset (mm, rad); seconds: wall time.
    """

    Z_true: np.ndarray
    Z_est: np.ndarray
    X_true: np.ndarray
    X_est: np.ndarray
    z_error: np.ndarray
    x_error: np.ndarray
    cov_Z: np.ndarray
    cov_X: np.ndarray
    nees_Z: float
    chi2_dof: float
    x_planned: np.ndarray
    n_used: int
    pupil_lost: int
    not_converged: int
    offset: np.ndarray
    estimator: str
    seconds: float
    observable: bool = True
    messages: tuple = ()

    @property
    def z_translation_error_mm(self) -> float:
        return float(np.linalg.norm(self.z_error[:3]))

    @property
    def z_rotation_error_rad(self) -> float:
        return float(np.linalg.norm(self.z_error[3:]))

    @property
    def z_translation_bound_mm(self) -> float:
        """Predicted RMS norm of the translation error: sqrt(trace) of its cov block."""
        return float(np.sqrt(np.trace(self.cov_Z[:3, :3])))

    @property
    def z_rotation_bound_rad(self) -> float:
        return float(np.sqrt(np.trace(self.cov_Z[3:, 3:])))


def _log_right(T_true, T_est) -> np.ndarray:
    """xi with T_est = T_true P(xi) (mm, rad)."""
    return matrix_to_pose(invert_poses(T_true) @ T_est)


def plan_poses(bench: Bench, lens: Lens, design: str, rng: np.random.Generator, cfg: ScenarioConfig | None = None,
               scene: Scene | None = None, model: ForwardModel | None = None, n_candidates: int = 600,
               check_reach: bool = True):
    """Planned calibration lens poses (n, 6) and the design-time prediction dict.

    design: "random" (uniform in the working box, lit ones kept) or "oed"
    (D-optimal among lit candidates, ``calib_design.design_poses``).
    """
    cfg = cfg or ScenarioConfig()
    scene = scene or scenario_scene(bench)
    model = model or ForwardModel(bench, lens)
    cov_B = lens_pose_crlb(bench, lens)
    n = cfg.n_calibration
    t, r = cfg.work_translation_mm, cfg.work_rotation_rad
    if design == "random":
        x = np.empty((0, 6))
        for _ in range(20):
            c = random_lens_poses(rng, 4 * n, t, r)
            x = np.concatenate([x, c[lit_mask(model, c, cfg.lit_margin_mm)]])
            if len(x) >= n:
                break
        if len(x) < n:
            raise PupilError(f"scenario: fewer than {n} lit poses in the working box; shrink work_translation_mm")
        x = x[:n]
        flange_pose(scene, x, check_reach=check_reach)  # PoseRangeError if the robot cannot
    elif design == "oed":
        cand = candidate_poses(rng, n_candidates, t, r)
        cand = cand[lit_mask(model, cand, cfg.lit_margin_mm)]
        if len(cand) < n:
            raise PupilError(f"scenario: only {len(cand)} lit candidate poses; shrink the working box")
        res = design_poses(scene, cov_B, n, rng, candidates=cand, n_random_sets=1, check_reach=check_reach)
        x = res.x
    else:
        raise ConfigError(f"design: {design!r} is not random or oed")
    return x, predicted_uncertainty(scene, x, cov_B)


def run_calibration(bench: Bench, lens: Lens, x_planned, rng: np.random.Generator, cfg: ScenarioConfig | None = None,
                    scene: Scene | None = None, model: ForwardModel | None = None) -> CalibrationRun:
    """Simulate one calibration with the planned lens poses x_planned (n, 6) (see module doc)."""
    t0 = time.perf_counter()
    cfg = cfg or ScenarioConfig()
    scene = scene or scenario_scene(bench)
    model = model or ForwardModel(bench, lens)
    if not isinstance(rng, np.random.Generator):
        raise ConfigError("rng: expected a numpy.random.Generator")
    x_planned = np.atleast_2d(np.asarray(x_planned, dtype=float))
    T_nom = scene.T_SO_nominal
    prior = prior_covariance(cfg.grasp)
    # 1. the true cell
    g = rng.normal(size=6) * cfg.grasp.sigma
    s = rng.normal(size=6) * np.array([cfg.sensor_cad_translation_mm] * 3 + [cfg.sensor_cad_rotation_rad] * 3)
    X_true = scene.X @ pose_to_matrix(g)
    Z_true = scene.Z @ pose_to_matrix(s)
    Z_inv = invert_poses(Z_true)
    msgs = []

    def visit(x_cmd, correction):
        """Command lens poses x_cmd (k, 6), offset-corrected; return the flange poses as commanded
        and as reached (the robot lands with its repeatability noise)."""
        B_cmd = T_nom @ pose_to_matrix(x_cmd) @ invert_poses(pose_to_matrix(correction))
        A_cmd = scene.Z @ B_cmd @ invert_poses(scene.X)
        return A_cmd, A_cmd @ pose_to_matrix(scene.noise.sample(rng, len(x_cmd)))

    opts = {"prior_cov": prior, "ukf_repeats": cfg.ukf_repeats} if cfg.estimator == "ukf" else {}
    # 2. convergence poses: learn the constant commanded-vs-actual offset
    offset = np.zeros(6)
    if cfg.n_convergence:
        xc = random_lens_poses(rng, cfg.n_convergence, cfg.convergence_translation_mm, cfg.convergence_rotation_rad)
        _, A_true = visit(xc, offset)
        zc, lit, _ = model.measure_noisy(matrix_to_pose(invert_poses(T_nom) @ Z_inv @ A_true @ X_true), rng)
        logs = []
        for i in range(len(xc)):
            if not lit[i]:
                msgs.append(f"convergence pose {i}: pupil not lit")
                continue
            est, why = estimate_one(model, zc[i], [np.zeros(6)], cfg.estimator, **opts)
            if est is None:
                msgs.append(f"convergence pose {i}: {why}")
                continue
            logs.append(_log_right(pose_to_matrix(xc[i]), pose_to_matrix(est.pose)))
        if logs:
            offset = np.mean(logs, axis=0)
    # 3. calibration poses: the session the cell records, calibrated by the one pipeline (two-stage)
    A_cmd, A_true = visit(x_planned, offset)
    rec = record_session(model, model, scene, A_true, A_cmd, X_true, Z_true, rng)
    try:
        res = run(rec.data, "two-stage", estimator=cfg.estimator, estimator_options=opts)
    except CalibrationError as e:
        raise CalibrationError(f"scenario: {e}; shrink the working box") from None
    lost = int((~rec.lit).sum())
    nconv = sum(r.get("code") == "no-estimate" for r in res.poses_rejected)
    msgs += [f"calibration pose {r['pose']}: {r['reason']}" for r in res.poses_rejected]
    he = res.handeye
    ez = _log_right(Z_true, he.Z)
    ex = _log_right(X_true, he.X)
    nees = float(ez @ np.linalg.solve(he.cov_Z, ez))
    return CalibrationRun(Z_true=Z_true, Z_est=he.Z, X_true=X_true, X_est=he.X, z_error=ez, x_error=ex,
                          cov_Z=he.cov_Z, cov_X=he.cov_X, nees_Z=nees, chi2_dof=float(he.chi2_dof),
                          x_planned=x_planned, n_used=len(res.poses_used), pupil_lost=lost, not_converged=nconv,
                          offset=offset, estimator=cfg.estimator, seconds=time.perf_counter() - t0,
                          observable=bool(he.observable), messages=tuple(msgs) + tuple(he.warnings))


def _summarize(runs: list[CalibrationRun], prediction: dict) -> dict:
    et = np.array([r.z_translation_error_mm for r in runs])
    er = np.array([r.z_rotation_error_rad for r in runs])
    bt = np.array([r.z_translation_bound_mm for r in runs])
    br = np.array([r.z_rotation_bound_rad for r in runs])
    ex = np.array([r.x_error for r in runs])
    return {
        "runs": len(runs),
        "Z_translation_error_rms_um": float(np.sqrt(np.mean(et**2)) * 1e3),
        "Z_translation_error_median_um": median(et) * 1e3,
        "Z_translation_predicted_rms_um": float(np.sqrt(np.mean(bt**2)) * 1e3),
        "Z_rotation_error_rms_urad": float(np.sqrt(np.mean(er**2)) * 1e6),
        "Z_rotation_error_median_urad": median(er) * 1e6,
        "Z_rotation_predicted_rms_urad": float(np.sqrt(np.mean(br**2)) * 1e6),
        "Z_design_bound_translation_um": float(prediction["Z_translation_mm"] * 1e3),
        "Z_design_bound_rotation_urad": float(prediction["Z_rotation_rad"] * 1e6),
        "X_translation_error_rms_um": float(np.sqrt(np.mean(np.sum(ex[:, :3] ** 2, 1))) * 1e3),
        "X_rotation_error_rms_urad": float(np.sqrt(np.mean(np.sum(ex[:, 3:] ** 2, 1))) * 1e6),
        "mean_nees_Z_per_dof": float(np.mean([r.nees_Z for r in runs]) / 6),
        "mean_chi2_dof": float(np.mean([r.chi2_dof for r in runs])),
        "pupil_lost": int(sum(r.pupil_lost for r in runs)),
        "flagged_degenerate": int(sum(not r.observable for r in runs)),
        "not_converged": int(sum(r.not_converged for r in runs)),
        "seconds_per_run": float(np.mean([r.seconds for r in runs])),
        "example_Z_est": runs[0].Z_est.tolist(),
    }


def compare_pose_designs(bench: Bench, lens: Lens, cfg: ScenarioConfig | None = None,
                         designs=("random", "oed"), runs: int = 20, seed: int = 0, scene: Scene | None = None,
                         tick=None) -> dict:
    """Run ``runs`` seeded calibrations per pose design; JSON-ready summary.

    "random" draws new random lit poses for every run; "oed" designs the poses once
    (nominal model, CRLB at nominal) and reuses them. Runs i of both designs share
    their scene/noise stream (common random numbers). ``tick()`` is called after each calibration.
    """
    cfg = cfg or ScenarioConfig()
    if int(runs) != runs or runs < 1:
        raise ConfigError(f"runs: expected an integer >= 1, got {runs!r}")
    scene = scene or scenario_scene(bench)
    model = ForwardModel(bench, lens)
    plan_ss, run_ss = np.random.SeedSequence(seed).spawn(2)
    # run i: (plan stream, scene/noise stream); the scene stream is shared by all designs
    run_streams = [c.spawn(2) for c in run_ss.spawn(int(runs))]
    out = {"config": asdict(cfg), "seed": seed, "designs": {}}
    for d in designs:
        if d == "oed":
            x_fixed, pred = plan_poses(bench, lens, "oed", np.random.default_rng(plan_ss), cfg, scene, model)
        results, preds = [], []
        for ps, ss in run_streams:
            if d == "random":
                x, p = plan_poses(bench, lens, "random", np.random.default_rng(ps), cfg, scene, model)
            elif d == "oed":
                x, p = x_fixed, pred
            else:
                raise ConfigError(f"design: {d!r} is not random or oed")
            results.append(run_calibration(bench, lens, x, np.random.default_rng(ss), cfg, scene, model))
            preds.append(p)
            if tick is not None:
                tick()
        # design-time bound; for random, the RMS over the runs' own designs
        bound = {k: float(np.sqrt(np.mean([q[k] ** 2 for q in preds]))) for k in ("Z_translation_mm", "Z_rotation_rad")}
        s = _summarize(results, bound)
        if d == "oed":
            s["poses"] = x_fixed.tolist()
        out["designs"][d] = s
    return out


def format_comparison(rep: dict) -> str:
    """Plain-text table of compare_pose_designs (um, urad)."""
    lines = [f"{'poses':<8}{'runs':>5}{'|dZ_t| rms um':>15}{'pred um':>9}{'bound um':>10}{'|dZ_r| rms urad':>17}"
             f"{'pred urad':>11}{'bound urad':>12}{'NEES/dof':>10}{'chi2/dof':>10}{'lost':>6}{'unconv':>8}"
             f"{'degen':>7}"]
    for d, s in rep["designs"].items():
        lines.append(f"{d:<8}{s['runs']:>5}{s['Z_translation_error_rms_um']:>15.1f}{s['Z_translation_predicted_rms_um']:>9.1f}"
                     f"{s['Z_design_bound_translation_um']:>10.1f}{s['Z_rotation_error_rms_urad']:>17.1f}"
                     f"{s['Z_rotation_predicted_rms_urad']:>11.1f}{s['Z_design_bound_rotation_urad']:>12.1f}"
                     f"{s['mean_nees_Z_per_dof']:>10.2f}{s['mean_chi2_dof']:>10.2f}{s['pupil_lost']:>6}"
                     f"{s['not_converged']:>8}{s['flagged_degenerate']:>7}")
    lines.append("lost: poses whose beam left the SH pupil dark; unconv: pose estimates that did not converge; "
                 "degen: calibrations flagged as degenerate motion")
    return "\n".join(lines)
