"""As-built tolerance Monte Carlo: what printing and polishing do to the calibration.

One trial = one as-built lens. The lens is drawn with
``asbuilt.tolerances.sample_as_built`` from the trial's own random stream; the whole
calibration procedure is then simulated: the robot moves the lens through the
calibration plan (``n_poses`` poses), the *as-built* lens produces the
Shack-Hartmann measurements (plus sensor noise, plus robot pose noise), while the
calibration uses the *nominal* design model (it does not know the lens was built
differently; the joint method estimates the as-built lens with X and Z). The trial records the error of Z = ^W T_S (rotation
in deg, translation in mm), the per-pose estimation bias (mean estimate - truth
per DOF) and the failures (pupil lost for the as-built lens at a pose,
non-convergence, too few poses left).

Random streams: trial i's SeedSequence (child i of SeedSequence(seed)) is split
into three fixed sub-streams: 0 = as-built lens, 1 = scene (grasp, robot noise),
2 = sensor noise. Scaling a tolerance therefore changes only the size of the
as-built deviations, never the noise draws (common random numbers), and zero
tolerances give exactly the noise-only trial (the as-built stream is unused).

The session is simulated by ``session_sim.record_session`` and calibrated by the one
pipeline ``calibration.pipeline.run``: the code ``lensforge calibrate`` runs on a bench
session, outlier passes, fallbacks and model check included.
"""

from __future__ import annotations

import math
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from functools import cached_property
from os import PathLike
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..asbuilt.tolerances import Tolerances, resolve_tolerances, sample_as_built
from ..calibration.initial_poses import InitialPoseModel
from ..calibration.pipeline import VERSION as PIPELINE_VERSION, TooFewPosesError, run
from ..calibration.robot import flange_pose, paper_scene
from ..calibration.session_result import OUTLIER_ALPHA
from ..errors import ConfigError, LensforgeError, PoseRangeError
from ..optics.bench import Bench
from ..optics.lens import Lens, LensSpec, resolve_lens
from ..optics.pose import DOF_NAMES, matrix_to_pose, pose_to_matrix, transform_error
from ..optics.shack_hartmann import ForwardModel, check_pose_range
from .runner import TrialStore, config_hash, run_trials
from .session_sim import nees, record_session
from .statistics import error_stats, outcome_counts

if TYPE_CHECKING:
    from distributed import Client

__all__ = ["StudyConfig", "StudyResult", "verify", "run_trial", "StudyContext", "summarize_errors",
           "SCHEMA_VERSION", "CALIBRATIONS", "calibration_records", "joint_statistics"]

SCHEMA_VERSION = 1
CALIBRATIONS = ("two-stage", "joint")


# ----------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class StudyConfig:
    """Options of an as-built study (everything but lens, bench, tolerances, seed).

    n_poses: calibration poses per lens; pose_span_mm / pose_span_deg: half-range of
    the calibration plan's lens poses about nominal (tx/ty, tz in mm; rotations in
    deg); handeye_method: "ml", "shah" or "li"; max_iter: LM iterations per pose;
    min_poses: fewer usable poses than this fails the trial; target_mm /
    target_deg: calibration accuracy target (summary and budget); percentile:
    the percentile judged against the target; calibration: "two-stage" (per-pose estimates, then AX = ZB) or "joint" (also run
    the joint as-built calibration, ``calibration.joint``; both results are stored,
    the summary shows the requested one); joint_prior: the joint calibration's lens
    prior, "study" (the study's tolerances) or "default" (the default tolerance file).
    """

    n_poses: int = 24
    pose_span_mm: tuple = (0.2, 0.2, 2.0)
    pose_span_deg: tuple = (6.0, 6.0, 6.0)
    handeye_method: str = "ml"
    max_iter: int = 40
    min_poses: int = 6
    target_mm: float = 0.1
    target_deg: float = 0.01
    percentile: float = 95.0
    calibration: str = "two-stage"
    joint_prior: str = "study"

    def __post_init__(self):
        if self.calibration not in CALIBRATIONS:
            raise ConfigError(f"calibration: {self.calibration!r} is not one of {', '.join(CALIBRATIONS)}")
        if self.joint_prior not in ("study", "default"):
            raise ConfigError(f"joint_prior: {self.joint_prior!r} is not 'study' or 'default'")
        if int(self.n_poses) != self.n_poses or self.n_poses < 3:
            raise ConfigError(f"n_poses: need an integer >= 3 (hand-eye needs 3 poses), got {self.n_poses!r}")
        if self.min_poses < 3 or self.min_poses > self.n_poses:
            raise ConfigError(f"min_poses: must be in 3..n_poses ({self.n_poses}), got {self.min_poses}")
        if self.handeye_method not in ("ml", "shah", "li"):
            raise ConfigError(f"handeye_method: {self.handeye_method!r} is not ml, shah or li")
        for name in ("target_mm", "target_deg"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f"{name}: must be a number > 0, got {v!r}")
        if not 0 < self.percentile <= 100:
            raise ConfigError(f"percentile: must be in (0, 100], got {self.percentile}")
        object.__setattr__(self, "pose_span_mm", tuple(float(v) for v in self.pose_span_mm))
        object.__setattr__(self, "pose_span_deg", tuple(float(v) for v in self.pose_span_deg))

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


# ----------------------------------------------------------------------------- batched pose estimation


# ----------------------------------------------------------------------------- one trial


@dataclass(frozen=True, eq=False)
class StudyContext:
    """Everything a trial needs; pickled once to each worker.

    lens: nominal design; bench; tolerances (None = noise only); config; plan:
    (n_poses, 6) commanded lens poses (mm, rad, relative to nominal); scene:
    robot.Scene (Z, nominal grasp X, robot noise); grasp_sigma: (6,) 1-sigma grasp
    error (mm, rad) applied to X per trial.
    """

    lens: Lens
    bench: Bench
    tolerances: object
    config: StudyConfig
    plan: np.ndarray
    scene: object
    grasp_sigma: np.ndarray

    @cached_property
    def nominal_model(self) -> ForwardModel:
        """The nominal forward model, built once per context copy (i.e. once per worker)."""
        return ForwardModel(self.bench, self.lens)

    @property
    def joint_prior(self):
        """The joint method's lens prior: the study's tolerances, the default file
        (``config.joint_prior == "default"``), or zero tolerances for a noise-only study
        (theta empty: the joint fit without lens parameters)."""
        if self.config.joint_prior == "default":
            return "default"
        return self.tolerances if self.tolerances is not None else Tolerances.zero()

    def __getstate__(self):  # ship the inputs, not the cached models
        d = dict(self.__dict__)
        d.pop("nominal_model", None)
        return d

    def __setstate__(self, d):
        self.__dict__.update(d)


def _substream(ss: np.random.SeedSequence, k: int) -> np.random.Generator:
    """Sub-stream k of a trial's SeedSequence, without mutating it (fixed CRN layout)."""
    return np.random.default_rng(np.random.SeedSequence(ss.entropy, spawn_key=tuple(ss.spawn_key) + (k,)))




def _as_built(ctx: StudyContext, rng: np.random.Generator) -> Lens:
    if ctx.tolerances is None:
        return ctx.lens
    return sample_as_built(ctx.lens, ctx.tolerances, rng)


def _fail(reason: str, **extra) -> dict:
    rec = {"ok": False, "failure": reason, "rot_err_deg": None, "trans_err_mm": None}
    rec.update(extra)
    return rec


def _calibration_record(res, rec, X_true, Z_true) -> dict:
    """A trial record (ok, Z and X errors, per-pose counts, model check) of a pipeline result."""
    rot, trans = transform_error(Z_true, res.Z)
    xrot, xtrans = transform_error(X_true, res.X)
    no_est = [r for r in res.poses_rejected if r.get("code") == "no-estimate"]
    out = {"ok": True, "failure": "", "rot_err_deg": rot, "trans_err_mm": trans, "x_rot_err_deg": xrot,
           "x_trans_err_mm": xtrans, "n_used": len(res.poses_used), "n_pupil_lost": int((~rec.lit).sum()),
           "n_not_converged": len(no_est),
           "n_out_of_range": sum("left the bench's pose range" in r["reason"] for r in no_est),
           "n_outliers": sum(r.get("code") == "outlier" for r in res.poses_rejected),
           "chi2": float(res.chi2), "dof": int(res.dof), "p_value": float(res.p_value),
           "mismatch": bool(res.p_value < OUTLIER_ALPHA), "nees_Z": nees(Z_true, res.Z, res.handeye.cov_Z),
           "Z_sigma_mm": float(np.sqrt(np.trace(res.handeye.cov_Z[:3, :3]))),
           "Z_sigma_deg": math.degrees(float(np.sqrt(np.trace(res.handeye.cov_Z[3:, 3:])))),
           "fallback": res.extra.get("fallback", {}).get("reason", "")}
    if not res.valid:  # not a calibration (``calibrate`` exits 3): the trial fails; its errors stay for diagnosis
        out.update(ok=False, failure=f"model check failed: {res.check_failure}")
    if res.estimates:  # two-stage: the per-pose estimation bias against the true lens poses
        index = {i: k for k, i in enumerate(np.array(rec.data.ids))}
        lit_idx = np.flatnonzero(rec.lit)
        err = np.array([x - rec.x_true[lit_idx[index[i]]] for i, x, _ in res.estimates])
        out.update(bias=err.mean(axis=0).tolist(), bias_std=err.std(axis=0).tolist(),
                   handeye_chi2_dof=float(res.chi2_dof), handeye_observable=bool(res.handeye.observable),
                   chi2_dof=float(np.mean([p["estimate_chi2_dof"] for p in res.per_pose])))
    else:
        jr = res.handeye.joint
        s = jr.summary()
        out.update(bias=[0.0] * 6, theta=s["theta"], n_identifiable=s["n_identifiable"],
                   iterations=jr.iterations, converged=bool(jr.converged), n_traced=jr.n_traced,
                   start=res.extra.get("start", ""))
    return out


def run_trial(ctx: StudyContext, index: int, ss: np.random.SeedSequence) -> dict:
    """Simulate the calibration with one as-built lens; returns a JSON-able record.

    The session is simulated by ``session_sim.record_session`` (the robot reaches the
    commanded flange pose up to its repeatability and records the commanded one; the
    as-built lens makes the light; unlit poses give no measurement) and calibrated by the
    one pipeline ``calibration.pipeline`` that ``lensforge calibrate`` runs: always the
    two-stage method, and with calibration "joint" also the joint method on the same data,
    started from the two-stage solution (record under "joint").

    A calibration that fails its chi2 model check (``CalibrationResult.valid`` False: what
    ``calibrate`` refuses with exit 3) fails the trial ("model check failed: ..."); its
    errors stay in the record.

    Keys: ok, failure ("" or why), rot_err_deg / trans_err_mm (Z = ^W T_S error),
    x_rot_err_deg / x_trans_err_mm (grasp X error), bias (6: mean estimate - truth,
    mm and rad), bias_std (6), n_used, n_pupil_lost, n_not_converged, n_out_of_range,
    n_outliers, chi2_dof (pose fits, mean), handeye_chi2_dof, chi2, dof, p_value, mismatch,
    nees_Z, Z_sigma_mm / Z_sigma_deg, grasp_error.
    """
    cfg = ctx.config
    rng_lens, rng_scene, rng_noise = (_substream(ss, k) for k in range(3))
    nominal = ctx.nominal_model
    try:
        lens_ab = _as_built(ctx, rng_lens)
        # sample_as_built has validated the lens already
        model_ab = nominal if lens_ab is ctx.lens else ForwardModel(ctx.bench, lens_ab, validate=False)
    except LensforgeError as e:
        return _fail(f"as-built lens not physical: {e}")
    scene = ctx.scene
    n = len(ctx.plan)
    # the robot is commanded with the nominal grasp; the real grasp is off by g
    g = rng_scene.standard_normal(6) * ctx.grasp_sigma
    X_true = scene.X @ pose_to_matrix(g)
    A_cmd = flange_pose(scene, ctx.plan, check_reach=False)
    A_true = A_cmd @ pose_to_matrix(scene.noise.sample(rng_scene, n))
    rec = record_session(nominal, model_ab, scene, A_true, A_cmd, X_true, scene.Z, rng_noise)
    base = {"n_pupil_lost": int((~rec.lit).sum()), "grasp_error": g.tolist()}
    opts = {"handeye_method": cfg.handeye_method, "max_iter": cfg.max_iter, "min_poses": cfg.min_poses}
    try:
        ts = run(rec.data, "two-stage", **opts)
        out = {**_calibration_record(ts, rec, X_true, scene.Z), **base}
    except TooFewPosesError as e:  # the poses still count: used, lost, not converged
        no_est = [r for r in e.rejected if r.get("code") == "no-estimate"]
        ts, out = None, _fail(f"too few usable poses: {e}", n_used=len(rec.data.ids) - len(no_est),
                              n_not_converged=len(no_est),
                              n_out_of_range=sum("left the bench's pose range" in r["reason"] for r in no_est), **base)
    except LensforgeError as e:
        ts, out = None, _fail(f"two-stage calibration failed: {e}", **base)
    if cfg.calibration == "joint":
        try:
            jr = run(rec.data, "joint", tolerances=ctx.joint_prior, start=ts)
            out["joint"] = {**_calibration_record(jr, rec, X_true, scene.Z), **base}
        except LensforgeError as e:
            out["joint"] = _fail(f"joint calibration failed: {e}", **base)
    return out


# ----------------------------------------------------------------------------- the study


def summarize_errors(records: list[dict], target_mm: float, target_deg: float, percentile: float = 95.0) -> dict:
    """Summary of trial records: median / percentile / max of the Z error (failed
    trials count as infinitely wrong), failure counts, mean pose bias, pass/fail.
    Statistics and counts come from ``verification.statistics`` (as do the plots')."""
    n = len(records)
    counts = outcome_counts(records)
    rot = np.array([r["rot_err_deg"] if r["ok"] else np.inf for r in records], float)
    tr = np.array([r["trans_err_mm"] if r["ok"] else np.inf for r in records], float)
    bias = np.array([r["bias"] for r in records if r["ok"]], float).reshape(-1, 6)
    q = float(percentile)
    rot_stats, tr_stats = error_stats(rot, q), error_stats(tr, q)
    p_rot, p_tr = rot_stats[f"p{q:g}"], tr_stats[f"p{q:g}"]
    mb = bias.mean(axis=0) if bias.size else np.full(6, np.nan)
    return {
        "n_lenses": n,
        "n_ok": counts["n_ok"],
        "failure_rate": counts["n_failed"] / n if n else None,
        "failures": counts["failures"],
        "rotation_deg": rot_stats,
        "translation_mm": tr_stats,
        "percentile": q,
        "target": {"translation_mm": target_mm, "rotation_deg": target_deg},
        "meets_target": bool(p_rot is not None and p_tr is not None and p_rot <= target_deg and p_tr <= target_mm),
        "target_ratio": (max(p_rot / target_deg, p_tr / target_mm) if p_rot is not None and p_tr is not None
                         else None),
        "mean_pose_bias": {**{f"{k}_um": (float(v * 1e3) if np.isfinite(v) else None) for k, v in zip(DOF_NAMES[:3], mb[:3])},
                           **{f"{k}_mdeg": (float(np.degrees(v) * 1e3) if np.isfinite(v) else None)
                              for k, v in zip(DOF_NAMES[3:], mb[3:])}},
        **{k: counts[k] for k in ("pupil_lost_poses", "not_converged_poses", "out_of_range_poses")},
    }


@dataclass(frozen=True, eq=False)
class StudyResult:
    """Outcome of :func:`verify`.

    records: per-trial dicts (index order; the joint calibration's result under
    "joint"); rot_err_deg / trans_err_mm: (n,) Z error of the requested calibration
    (config.calibration; nan for failed trials); bias: (n, 6) mean pose-estimation
    bias per trial (mm, rad; nan when failed); ok: (n,); summary: see
    ``summarize_errors``, plus "calibration" and, for joint, "joint"
    (``joint_statistics``); config:
    the hashed study configuration; config_hash; store: the store path or None;
    stats: runner.RunStats.
    """

    records: tuple
    rot_err_deg: np.ndarray
    trans_err_mm: np.ndarray
    bias: np.ndarray
    ok: np.ndarray
    summary: dict
    config: dict
    config_hash: str
    store: Path | None
    stats: object

    @property
    def n_lenses(self) -> int:
        return len(self.records)

    def to_dict(self) -> dict:
        """JSON-ready summary (schema_version, config hash, summary, per-trial errors)."""
        def fl(a):
            return [float(v) if np.isfinite(v) else None for v in a]

        d = {"schema_version": SCHEMA_VERSION, "config_hash": self.config_hash, "summary": self.summary,
             "trials": {"rot_err_deg": fl(self.rot_err_deg), "trans_err_mm": fl(self.trans_err_mm),
                        "ok": [bool(v) for v in self.ok]},
             "store": str(self.store) if self.store else None,
             "run": {"n_run": self.stats.n_run, "n_resumed": self.stats.n_resumed, "wall_s": self.stats.wall_s,
                     "mode": self.stats.mode, "workers": self.stats.workers}}
        if self.summary.get("calibration") == "joint":
            d["two_stage_summary"] = self.calibration_summary("two-stage")
            d["joint_summary"] = self.summary
        return d

    def calibration_summary(self, calibration: str) -> dict:
        """Summary (as ``summary``) of the given calibration's errors ("two-stage" always
        exists; "joint" when the study ran it)."""
        t = self.summary["target"]
        return summarize_errors(calibration_records(self.records, calibration), t["translation_mm"],
                                t["rotation_deg"], self.summary["percentile"])


def calibration_plan(config: StudyConfig, plan_seed: int = 0) -> np.ndarray:
    """The commanded lens poses (n_poses, 6) of the calibration: uniform in the box
    +-pose_span about nominal (mm, rad); the same robot program for every trial."""
    rng = np.random.default_rng(np.random.SeedSequence([int(plan_seed), 0x504C414E]))
    span = np.r_[config.pose_span_mm, np.radians(config.pose_span_deg)]
    return rng.uniform(-1.0, 1.0, (config.n_poses, 6)) * span


def check_plan(plan, source: str = "pose plan") -> np.ndarray:
    """A calibration plan (n, 6) of lens pose vectors (mm, rad, relative to nominal),
    validated: n >= 3 rows of 6 finite numbers; raises ConfigError naming ``source``."""
    try:
        a = np.asarray(plan, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"{source}: poses must be rows of 6 numbers (tx ty tz mm, rx ry rz rad)") from None
    if a.ndim != 2 or a.shape[1] != 6 or a.shape[0] < 3:
        raise ConfigError(f"{source}: need at least 3 rows of 6 numbers (tx ty tz mm, rx ry rz rad), "
                          f"got shape {a.shape}")
    bad = np.argwhere(~np.isfinite(a))
    if bad.size:
        i, j = bad[0]
        names = ("tx_mm", "ty_mm", "tz_mm", "rx_rad", "ry_rad", "rz_rad")
        raise ConfigError(f"{source}: poses[{i}].{names[j]} is {a[i, j]}: every pose entry must be a finite number")
    return a


def load_plan(path) -> np.ndarray:
    """A calibration plan from JSON: {"poses": [[tx, ty, tz, rx, ry, rz], ...]}, the bare
    list (lens pose vectors relative to nominal, mm and rad; e.g. a joint design's x), or the
    plan.json that ``lensforge plan`` writes (its poses' "lens_pose" entries)."""
    from ..fileio import read_json

    d = read_json(path, "pose plan")
    poses = d.get("poses") if isinstance(d, dict) else d
    if poses is None:
        raise ConfigError(f"{path}: no \"poses\" list (rows of tx ty tz mm, rx ry rz rad)")
    if isinstance(poses, list) and poses and all(isinstance(p, dict) for p in poses):
        keys = ("tx_mm", "ty_mm", "tz_mm", "rx_rad", "ry_rad", "rz_rad")
        try:
            poses = [[p["lens_pose"][k] for k in keys] for p in poses]
        except (KeyError, TypeError):
            raise ConfigError(f"{path}: poses: each entry needs \"lens_pose\" with {', '.join(keys)} "
                              "(the plan.json of `lensforge plan`)") from None
    return check_plan(poses, str(path))


def make_context(lens: Lens, bench: Bench, tolerances, config: StudyConfig, plan_seed: int = 0,
                 scene=None, grasp_sigma=None, plan=None) -> StudyContext:
    """Assemble the trial context (plan, paper scene at the bench's distance, grasp error
    model); plan: (n_poses, 6) given calibration plan (default: ``calibration_plan``)."""
    scene = scene or paper_scene(bench.placement.distance_mm)
    if grasp_sigma is None:
        m = InitialPoseModel()
        grasp_sigma = np.array([m.grasp_translation_mm] * 3 + [m.grasp_rotation_rad] * 3)
    if plan is None:
        plan = calibration_plan(config, plan_seed)
    else:
        plan = check_plan(plan)
        try:  # a plan outside the bench's pose range is a unit or frame mistake (um or m for mm, deg for rad)
            check_pose_range(bench, plan)
        except PoseRangeError as e:
            raise ConfigError(f"pose plan: {e} (plan poses are mm and rad about nominal)") from None
    if len(plan) != config.n_poses:
        raise ConfigError(f"pose plan: {len(plan)} poses but n_poses is {config.n_poses}")
    return StudyContext(lens=lens, bench=bench, tolerances=tolerances, config=config,
                        plan=plan, scene=scene,
                        grasp_sigma=np.asarray(grasp_sigma, dtype=float))


def context_config(ctx: StudyContext, seed: int) -> dict:
    """The JSON configuration that identifies a study (hashed into its store)."""
    sc = ctx.scene
    return {
        "schema_version": SCHEMA_VERSION,
        "pipeline": PIPELINE_VERSION,
        "lens": ctx.lens.to_dict(),
        "bench": ctx.bench.to_dict(),
        "tolerances": ctx.tolerances.to_dict() if ctx.tolerances is not None else None,
        "config": ctx.config.to_dict(),
        "plan": ctx.plan.tolist(),
        "scene": {"Z": np.asarray(sc.Z).tolist(), "X": np.asarray(sc.X).tolist(), "distance_mm": sc.distance_mm,
                  "robot_noise": [sc.noise.translation_mm, sc.noise.rotation_rad]},
        "grasp_sigma": ctx.grasp_sigma.tolist(),
        "seed": int(seed),
    }


def calibration_records(records, calibration: str) -> list[dict]:
    """Trial records of one calibration: the two-stage record itself, or its "joint"
    sub-record (the joint calibration runs even when the two-stage one fails; a trial
    whose simulation failed before calibrating fails for both)."""
    if calibration == "two-stage":
        return list(records)
    return [r["joint"] if "joint" in r else (r if not r["ok"] else
            {"ok": False, "failure": "joint calibration not run", "rot_err_deg": None, "trans_err_mm": None})
            for r in records]


def joint_statistics(records) -> dict:
    """Consistency of the joint calibration over trials: mean NEES/dof of Z (6 dof),
    chi^2 mismatch rate, median iterations and identifiable theta directions."""
    ok = [r for r in records if r.get("ok") and "nees_Z" in r]
    if not ok:
        return {"nees_dof": None, "mismatch_rate": None, "iterations_median": None, "n_identifiable_median": None}
    return {"nees_dof": float(np.mean([r["nees_Z"] for r in ok]) / 6.0),
            "mismatch_rate": float(np.mean([r["mismatch"] for r in ok])),
            "iterations_median": float(np.median([r["iterations"] for r in ok])),
            "n_identifiable_median": float(np.median([r["n_identifiable"] for r in ok]))}


def result_from_records(records: dict[int, dict], config: dict, chash: str, store, stats,
                        study_config: StudyConfig) -> StudyResult:
    recs = tuple(records[i] for i in sorted(records))
    shown = calibration_records(recs, study_config.calibration)
    ok = np.array([r["ok"] for r in shown], bool)
    rot = np.array([r["rot_err_deg"] if r["ok"] else np.nan for r in shown], float)
    tr = np.array([r["trans_err_mm"] if r["ok"] else np.nan for r in shown], float)
    bias = np.array([r["bias"] if r["ok"] else [np.nan] * 6 for r in recs], float).reshape(-1, 6)
    summ = summarize_errors(shown, study_config.target_mm, study_config.target_deg, study_config.percentile)
    summ["calibration"] = study_config.calibration
    if study_config.calibration == "joint":
        summ["joint"] = joint_statistics(shown)
    return StudyResult(records=recs, rot_err_deg=rot, trans_err_mm=tr, bias=bias, ok=ok, summary=summ,
                       config=config, config_hash=chash, store=Path(store) if store else None, stats=stats)


def verify(design_or_lens: LensSpec, tolerances: Tolerances | str | Path | None, n_lenses: int, seed: int,
           bench: Bench | None = None, config: StudyConfig | None = None, *, workers: int | None = None,
           scheduler: str | None = None, store: str | PathLike[str] | None = None, resume: bool = False,
           progress: bool = True, plan_seed: int = 0, client: Client | None = None,
           description: str = "as-built lenses", plan: np.ndarray | None = None) -> StudyResult:
    """As-built Monte Carlo of the calibration for ``n_lenses`` as-built lenses.

    A script that starts a local cluster (workers != 0) needs the usual
    ``if __name__ == "__main__":`` guard (worker processes are spawned).

    Parameters
    ----------
    design_or_lens : LensSpec
        Lens, Design, paper lens name or design JSON path.
    tolerances : Tolerances, str, pathlib.Path or None
        Tolerances, a TOML path, or None (noise only; ``Tolerances.zero()`` gives the same numbers).
    n_lenses : int
        As-built lenses (trials).
    seed : int
        Study seed: trial i uses child i of SeedSequence(seed).
    bench : Bench, optional
        Default: the design's bench, else the built-in one.
    config : StudyConfig, optional
        The study's options: poses per lens, calibration method ("two-stage", or "joint" which
        also runs the two-stage method on the same data), targets (default ``StudyConfig()``).
    workers : int, optional
        0 = in this process, N = local Dask cluster of N processes (default: all cores).
    scheduler : str, optional
        Address of an existing Dask scheduler.
    store : str or os.PathLike, optional
        SQLite file to append finished trials to.
    resume : bool
        Continue a killed study from ``store`` (the store refuses a different study).
    progress : bool
        Progress bar on stderr.
    plan_seed : int
        Seed of the random calibration-pose box.
    client : distributed.Client, optional
        An existing Dask client.
    description : str
        The progress bar's label.
    plan : numpy.ndarray, shape (n, 6), optional
        Calibration plan (lens pose vectors, mm and rad, relative to nominal, e.g. a joint
        design's; n_poses becomes n) instead of the seeded random box.

    Returns
    -------
    StudyResult
        Per-trial records, ``rot_err_deg`` and ``trans_err_mm`` (n,) of Z (nan for failed
        trials), per-trial bias (n, 6) mm and rad, ``ok`` (n,), the summary statistics,
        the hashed configuration and ``config_hash``.
    """
    if int(n_lenses) != n_lenses or n_lenses < 1:
        raise ConfigError(f"n_lenses: need an integer >= 1, got {n_lenses!r}")
    r = resolve_lens(design_or_lens)
    lens, bench = r.lens, r.bench_or(bench)
    tol = resolve_tolerances(tolerances)[0]
    config = config or StudyConfig()
    if plan is not None:
        from dataclasses import replace

        plan = check_plan(plan)
        config = replace(config, n_poses=len(plan), min_poses=min(config.min_poses, len(plan)))
    ctx = make_context(lens, bench, tol, config, plan_seed, plan=plan)
    cfg = context_config(ctx, seed)
    chash = config_hash(cfg)
    with (TrialStore.session(store, chash, cfg, resume=resume, n_trials=int(n_lenses)) if store is not None
          else nullcontext()) as st:
        records, stats = run_trials(run_trial, ctx, int(n_lenses), int(seed), st, workers=workers,
                                    scheduler=scheduler, progress=progress, description=description,
                                    client=client)
    return result_from_records(records, cfg, chash, store, stats, config)
