"""As-built tolerance Monte Carlo: what printing and polishing do to the calibration.

One trial = one as-built lens. The lens is drawn with
``manufacturing.sample_as_built`` from the trial's own random stream; the whole
calibration procedure is then simulated: the robot moves the lens through the
calibration plan (``n_poses`` poses), the *as-built* lens produces the
Shack-Hartmann measurements (plus sensor noise, plus robot pose noise), while the
estimator uses the *nominal* design model (it does not know the lens was built
differently). The poses are estimated, the robot-world-hand-eye problem
A_i X = Z B_i is solved, and the trial records the error of Z = ^W T_S (rotation
in deg, translation in mm), the per-pose estimation bias (mean estimate - truth
per DOF) and the failures (pupil lost for the as-built lens at a pose,
non-convergence, too few poses left).

Random streams: trial i's SeedSequence (child i of SeedSequence(seed)) is split
into three fixed sub-streams: 0 = as-built lens, 1 = scene (grasp, robot noise),
2 = sensor noise. Scaling a tolerance therefore changes only the size of the
as-built deviations, never the noise draws (common random numbers), and zero
tolerances give exactly the noise-only trial (the as-built stream is unused).

Pose estimation is the same whitened least-squares estimator as
``pose_estimation.estimate_pose`` (objective |L^-1 (h(x) - z)|^2, central-difference
Jacobian, rank-deficient directions held at x0), run as one Levenberg-Marquardt
loop batched over all poses of a trial so that every forward-model call traces
all poses together. Jacobians are reused only where that is exact: after a
rejected step the point, hence the Jacobian, is unchanged.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import ConfigError, LensforgeError
from ..optics.bench import Bench
from ..optics.lens import Lens
from ..optics.pose import DOF_NAMES, matrix_to_pose, pose_to_matrix, pose_vector_cov_to_right, transform_error
from ..optics.shack_hartmann import ForwardModel
from .statistics import error_stats, outcome_counts

__all__ = ["StudyConfig", "StudyResult", "verify", "estimate_poses_batch", "BatchPoseEstimate", "run_trial",
           "StudyContext", "summarize_errors", "SCHEMA_VERSION"]

SCHEMA_VERSION = 1


# ----------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class StudyConfig:
    """Options of an as-built study (everything but lens, bench, tolerances, seed).

    n_poses: calibration poses per lens; pose_span_mm / pose_span_deg: half-range of
    the calibration plan's lens poses about nominal (tx/ty, tz in mm; rotations in
    deg); handeye_method: "ml", "shah" or "li"; max_iter: LM iterations per pose;
    min_poses: fewer usable poses than this fails the trial; target_mm /
    target_deg: calibration accuracy target (summary and budget); percentile:
    the percentile judged against the target; self_calibrate: also estimate the
    dominant as-built parameters jointly with the poses (see self_calibration).
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
    self_calibrate: bool = False

    def __post_init__(self):
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


@dataclass(frozen=True)
class BatchPoseEstimate:
    """Pose estimates of P measurements.

    poses: (P, 6) mm, rad; cov: (P, 6, 6) Gauss-Newton covariance (J^T R^-1 J)^-1 at
    the estimate (inf on the diagonal of unobservable DOF); chi2: (P,) whitened
    residual sum of squares; converged: (P,) met the tolerance with the pupil lit
    and in the bench's range; iterations: LM iterations run; n_evals: poses traced.
    """

    poses: np.ndarray
    cov: np.ndarray
    chi2: np.ndarray
    converged: np.ndarray
    iterations: int
    n_evals: int
    out_of_range: np.ndarray = None


def _whiten(Li, d):
    """L^-1 d for d (..., m), given Li = L^-1 (m, m)."""
    return d @ Li.T


def _jacobian(model: ForwardModel, x, uv, z0, valid0, L, central: bool = True):
    """Whitened finite-difference Jacobian (P, m, 6) at poses x (P, 6): central (one
    trace of 12P poses; one-sided where one side is unlit, as estimate_pose does) or
    forward (6P poses)."""
    P = x.shape[0]
    h = np.asarray(model.bench.fd_steps, dtype=float)
    if not central:
        poses = (x[:, None, :] + np.diag(h)[None]).reshape(-1, 6)
        res = model.evaluate(poses, uv0=np.repeat(uv, 6, axis=0), check_range=False)
        zp = res.z.reshape(P, 6, -1)
        J = np.where(res.valid.reshape(P, 6)[..., None], (zp - z0[:, None]) / h[None, :, None], 0.0)
        return _whiten(L, J).transpose(0, 2, 1), 6 * P
    steps = np.concatenate([np.diag(h), -np.diag(h)])  # (12, 6)
    poses = (x[:, None, :] + steps[None]).reshape(-1, 6)
    uv0 = np.repeat(uv, 12, axis=0)
    res = model.evaluate(poses, uv0=uv0, check_range=False)
    z = res.z.reshape(P, 12, -1)
    v = res.valid.reshape(P, 12)
    zp, zm, vp, vm = z[:, :6], z[:, 6:], v[:, :6], v[:, 6:]
    central = (zp - zm) / (2 * h[None, :, None])
    fwd = (zp - z0[:, None]) / h[None, :, None]
    bwd = (z0[:, None] - zm) / h[None, :, None]
    J = np.where((vp & vm)[..., None], central, np.where(vp[..., None], fwd, np.where(vm[..., None], bwd, 0.0)))
    return _whiten(L, J).transpose(0, 2, 1), 12 * P  # (P, m, 6)


def estimate_poses_batch(model: ForwardModel, z_measured, x0, *, max_iter: int = 40, xtol: float = 1e-10,
                         ftol: float = 1e-10, fast_start: bool = True) -> BatchPoseEstimate:
    """Whitened least-squares pose estimates for P measurements at once (LM, batched).

    z_measured: (P, m) Zernikes (um); x0: (P, 6) initial poses (mm, rad). Same
    objective as ``estimate_pose(method="lm")``; each pose has its own damping and
    stops on its own (relative step < xtol in scaled units, or relative cost change
    < ftol). Pose directions unobservable at x0 (bench.rank_rtol, as in
    ``metrics``) stay at x0 with inf variance. fast_start: forward-difference
    Jacobians until the cost stalls (same fixed point, fewer traces).
    """
    Z = np.atleast_2d(np.asarray(z_measured, dtype=float))
    x = np.array(np.atleast_2d(x0), dtype=float)
    P = x.shape[0]
    bench = model.bench
    L = model.whitener
    D = np.asarray(bench.pose_scales, dtype=float)
    n_evals = 0

    res = model.evaluate(x, check_range=False)
    n_evals += P
    uv, zc, valid = res.uv.copy(), res.z.copy(), res.valid.copy()
    r = _whiten(L, zc - Z)
    cost = np.where(valid, np.sum(r * r, axis=1), np.inf)
    lam = np.full(P, 1e-10)  # Gauss-Newton first; damp only after a rejected step
    active = valid.copy()
    converged = np.zeros(P, bool)
    J = np.zeros((P, Z.shape[1], 6))
    need_J = valid.copy()
    obs_mask = np.ones((P, 6), bool)
    # Forward differences (half the traces) while far from the minimum; central ones
    # once the cost stalls, and only central-Jacobian steps may end the iteration, so
    # the fixed point J^T r = 0 is the central-difference one of estimate_pose.
    near = np.full(P, not fast_start)
    J_central = np.zeros(P, bool)
    lim = bench.pose_limits
    first = True
    it = 0
    for it in range(1, max_iter + 1):
        for cen in (True, False):
            idx = np.flatnonzero(active & need_J & (near == cen))
            if idx.size:
                Jn, ne = _jacobian(model, x[idx], uv[idx], zc[idx], valid[idx], L, central=cen)
                J[idx] = Jn * D  # scaled: d r / d u, u = x / D
                J_central[idx] = cen
                n_evals += ne
                need_J[idx] = False
        if first:
            # rank test at x0 on the scaled whitened Jacobian (as metrics / estimate_pose)
            for p in np.flatnonzero(valid):
                _, s, Vt = np.linalg.svd(J[p])
                k = int(np.sum(s > bench.rank_rtol * s[0]))
                if k < 6:
                    null = Vt[k:].T
                    obs_mask[p] = ~np.any(np.abs(null) > 1e-6, axis=1)
            first = False
        a = np.flatnonzero(active)
        if a.size == 0:
            break
        Ja, ra = J[a] * obs_mask[a][:, None, :], r[a]
        A = np.einsum("pmi,pmj->pij", Ja, Ja)
        g = np.einsum("pmi,pm->pi", Ja, ra)
        dA = np.einsum("pii->pi", A)
        # Marquardt damping on the diagonal; unobservable directions pinned (identity, zero gradient)
        M = A + (lam[a, None] * np.where(dA > 0, dA, 1.0) + (~obs_mask[a]))[:, :, None] * np.eye(6)[None]
        du = -np.linalg.solve(M, g[..., None])[..., 0]
        xn = x[a] + du * D
        rn_res = model.evaluate(xn, uv0=uv[a], check_range=False)
        n_evals += a.size
        rn = _whiten(L, rn_res.z - Z[a])
        cn = np.where(rn_res.valid, np.sum(rn * rn, axis=1), np.inf)
        acc = cn <= cost[a]
        # predicted decrease of the linear model |r + J du|^2 - |r|^2
        pred = -(2.0 * np.einsum("pi,pi->p", g, du) + np.einsum("pi,pij,pj->p", du, A, du))
        u_norm = np.linalg.norm(x[a] / D, axis=1)
        tiny = ((np.linalg.norm(du, axis=1) <= xtol * (xtol + u_norm))
                | (pred <= ftol * np.maximum(cost[a], 1e-300)))
        ai = a[acc]
        small_step = tiny[acc]
        small_cost = (cost[ai] - cn[acc]) <= ftol * cost[ai]
        stalled = (cost[ai] - cn[acc]) <= 0.1 * cost[ai]
        near[ai] |= stalled | small_step | small_cost
        fin = J_central[ai]
        small_step &= fin
        small_cost &= fin
        x[ai], r[ai], cost[ai], zc[ai] = xn[acc], rn[acc], cn[acc], rn_res.z[acc]
        uv[ai] = rn_res.uv[acc]
        lam[ai] = np.maximum(lam[ai] / 10.0, 1e-10)
        need_J[ai] = True
        rej = a[~acc]
        # a rejected step leaves the point, hence the Jacobian, unchanged: reused exactly;
        # a forward-difference J that fails to descend is replaced by the central one
        fwd_rej = rej[~J_central[rej]]
        near[fwd_rej] = True
        need_J[fwd_rej] = True
        rej = rej[J_central[rej]]
        lam[rej] = np.maximum(lam[rej] * 10.0, 1e-4)
        done = ai[small_step | small_cost]
        converged[done] = True
        active[done] = False
        stuck = rej[tiny[np.isin(a, rej)] | (lam[rej] > 1e12)]
        converged[stuck] = True  # no descent direction left: a (possibly flat) minimum
        active[stuck] = False
        # an estimate far outside the bench's pose range is abandoned (reported out of range)
        far = ai[(np.abs(x[ai, :3]) > 2 * lim.translation_mm).any(axis=1)
                 | (np.linalg.norm(x[ai, 3:], axis=1) > 2 * lim.rotation_rad)]
        converged[far] = True
        active[far] = False
    # covariance from the Jacobian at the last linearisation point
    cov = np.full((P, 6, 6), np.nan)
    for p in np.flatnonzero(valid):
        Jp = J[p][:, obs_mask[p]]
        c = np.zeros((6, 6))
        try:
            sub = np.linalg.inv(Jp.T @ Jp)
        except np.linalg.LinAlgError:
            sub = np.linalg.pinv(Jp.T @ Jp)
        c[np.ix_(obs_mask[p], obs_mask[p])] = sub
        c *= np.outer(D, D)
        for i in np.flatnonzero(~obs_mask[p]):
            c[i, i] = np.inf
        cov[p] = c
    in_range = (np.all(np.abs(x[:, :3]) <= lim.translation_mm, axis=1)
                & (np.linalg.norm(x[:, 3:], axis=1) <= lim.rotation_rad))
    ok = converged & np.isfinite(cost) & in_range
    return BatchPoseEstimate(poses=x, cov=cov, chi2=np.where(np.isfinite(cost), cost, np.inf), converged=ok,
                             iterations=it, n_evals=n_evals, out_of_range=converged & np.isfinite(cost) & ~in_range)


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

    def __getstate__(self):  # ship the inputs, not the cached model
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
    from ..manufacturing.tolerances import sample_as_built

    return sample_as_built(ctx.lens, ctx.tolerances, rng)


def _fail(reason: str, **extra) -> dict:
    rec = {"ok": False, "failure": reason, "rot_err_deg": None, "trans_err_mm": None}
    rec.update(extra)
    return rec


def run_trial(ctx: StudyContext, index: int, ss: np.random.SeedSequence) -> dict:
    """Simulate the calibration with one as-built lens; returns a JSON-able record.

    Keys: ok, failure ("" or why), rot_err_deg / trans_err_mm (Z = ^W T_S error),
    x_rot_err_deg / x_trans_err_mm (grasp X error), bias (6: mean estimate - truth,
    mm and rad), bias_std (6), n_used, n_pupil_lost, n_not_converged, chi2_dof
    (pose fits, mean), handeye_chi2_dof, and, with self-calibration, the same
    errors after it under "selfcal".
    """
    from ..calibration.handeye import solve_handeye
    from ..calibration.robot import flange_pose, lens_pose_matrix

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
    B_true = np.linalg.solve(scene.Z, A_true @ X_true)
    x_true = matrix_to_pose(np.linalg.solve(scene.T_SO_nominal, B_true))
    # the as-built lens produces the measurements
    meas = model_ab.evaluate(x_true, check_range=False)
    sigma = ctx.bench.noise.slope_sigma_urad * 1e-6
    noise = rng_noise.normal(0.0, sigma, meas.slopes.shape)  # drawn for all poses: fixed CRN layout
    z = model_ab.pupil.fit(meas.slopes + noise)
    lit = meas.valid.copy()
    n_lost = int((~lit).sum())
    # the estimator uses the nominal model, starting from the commanded poses
    est = estimate_poses_batch(nominal, z[lit], ctx.plan[lit], max_iter=cfg.max_iter)
    used = np.flatnonzero(lit)[est.converged]
    n_nc = int((~est.converged).sum())
    n_oor = int(est.out_of_range.sum())
    base = {"n_used": int(used.size), "n_pupil_lost": n_lost, "n_not_converged": n_nc, "n_out_of_range": n_oor,
            "grasp_error": g.tolist()}
    if used.size < cfg.min_poses:
        return _fail(f"too few usable poses: {used.size} of {n} ({n_lost} pupil lost for the as-built lens, "
                     f"{n_nc} estimates not converged, of which {n_oor} left the bench's pose range)", **base)
    x_est = est.poses[est.converged]
    err = x_est - x_true[used]
    cov = est.cov[est.converged]
    cov = np.where(np.isfinite(cov), cov, 0.0) + np.where(np.isinf(cov), 100.0, 0.0)  # unobservable: (10 rad)^2
    cov_B = np.stack([pose_vector_cov_to_right(x, c) for x, c in zip(x_est, cov)])
    try:
        with warnings.catch_warnings():  # weak motion is recorded (handeye_observable), not printed per trial
            warnings.simplefilter("ignore", RuntimeWarning)
            he = solve_handeye(A_cmd[used], lens_pose_matrix(scene, x_est), cfg.handeye_method,
                               sigma=scene.noise, cov_B=cov_B, on_degenerate="warn")
    except LensforgeError as e:
        return _fail(f"hand-eye failed: {e}", **base)
    rot, trans = transform_error(scene.Z, he.Z)
    xrot, xtrans = transform_error(X_true, he.X)
    rec = {"ok": True, "failure": "", "rot_err_deg": rot, "trans_err_mm": trans,
           "x_rot_err_deg": xrot, "x_trans_err_mm": xtrans,
           "bias": err.mean(axis=0).tolist(), "bias_std": err.std(axis=0).tolist(),
           "chi2_dof": float(np.mean(est.chi2[est.converged]) / max(len(nominal.modes) - 6, 1)),
           "handeye_chi2_dof": float(he.chi2_dof), "handeye_observable": bool(he.observable), **base}
    if cfg.self_calibrate:
        from .self_calibration import self_calibrate_trial

        rec["selfcal"] = self_calibrate_trial(ctx, nominal, z[used], x_est, x_true[used], A_cmd[used], X_true,
                                              he.Z, he.X, lens_ab)
    return rec


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

    records: per-trial dicts (index order); rot_err_deg / trans_err_mm: (n,) Z error
    (nan for failed trials); bias: (n, 6) mean pose-estimation bias per trial (mm,
    rad; nan when failed); ok: (n,); summary: see ``summarize_errors``; config:
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

    def selfcal_summary(self) -> dict | None:
        """Summary of the errors after as-built self-calibration (if it ran)."""
        recs = [r.get("selfcal") for r in self.records]
        if not recs or any(r is None for r in recs):
            return None
        t = self.summary["target"]
        return summarize_errors(list(recs), t["translation_mm"], t["rotation_deg"], self.summary["percentile"])

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
        sc = self.selfcal_summary()
        if sc is not None:
            d["selfcal_summary"] = sc
        return d


def resolve_lens(design_or_lens, bench: Bench | None = None) -> tuple[Lens, Bench]:
    """(lens, bench) from a Lens, a Design (.lens, .bench), a paper lens name or a
    design/lens JSON path; ``bench`` overrides the design's bench."""
    from ..optics.lens import PAPER_LENSES, paper_lens

    obj = design_or_lens
    des_bench = None
    if isinstance(obj, (str, Path)):
        key = str(obj).lower().replace("-", "_")
        if isinstance(obj, str) and key in PAPER_LENSES:
            obj = paper_lens(key)
        else:
            from ..optics.lens import load_lens

            lens, data = load_lens(str(obj))
            if isinstance(data, dict) and isinstance(data.get("bench"), dict):
                des_bench = Bench.from_dict(data["bench"], "design.bench")
            obj = lens
    if not isinstance(obj, Lens):
        lens = getattr(obj, "lens", None)
        if not isinstance(lens, Lens):
            raise ConfigError(f"design: expected a Lens, a Design, a paper lens name or a JSON path, got "
                              f"{type(design_or_lens).__name__}")
        des_bench = getattr(obj, "bench", None)
        obj = lens
    return obj.validate(), (bench or des_bench or Bench.default())


def resolve_tolerances(tolerances):
    """A Tolerances from a Tolerances, a TOML path, or None (noise only -> None)."""
    if tolerances is None:
        return None
    if isinstance(tolerances, (str, Path)):
        from ..manufacturing.tolerances import load_tolerances

        return load_tolerances(tolerances)
    if not hasattr(tolerances, "to_dict"):
        raise ConfigError(f"tolerances: expected a Tolerances or a TOML path, got {type(tolerances).__name__}")
    return tolerances


def calibration_plan(config: StudyConfig, plan_seed: int = 0) -> np.ndarray:
    """The commanded lens poses (n_poses, 6) of the calibration: uniform in the box
    +-pose_span about nominal (mm, rad); the same robot program for every trial."""
    rng = np.random.default_rng(np.random.SeedSequence([int(plan_seed), 0x504C414E]))
    span = np.r_[config.pose_span_mm, np.radians(config.pose_span_deg)]
    return rng.uniform(-1.0, 1.0, (config.n_poses, 6)) * span


def make_context(lens: Lens, bench: Bench, tolerances, config: StudyConfig, plan_seed: int = 0,
                 scene=None, grasp_sigma=None) -> StudyContext:
    """Assemble the trial context (plan, paper scene at the bench's distance, grasp error model)."""
    from ..calibration.initial_poses import InitialPoseModel
    from ..calibration.robot import paper_scene

    scene = scene or paper_scene(bench.placement.distance_mm)
    if grasp_sigma is None:
        m = InitialPoseModel()
        grasp_sigma = np.array([m.grasp_translation_mm] * 3 + [m.grasp_rotation_rad] * 3)
    return StudyContext(lens=lens, bench=bench, tolerances=tolerances, config=config,
                        plan=calibration_plan(config, plan_seed), scene=scene,
                        grasp_sigma=np.asarray(grasp_sigma, dtype=float))


def context_config(ctx: StudyContext, seed: int) -> dict:
    """The JSON configuration that identifies a study (hashed into its store)."""
    sc = ctx.scene
    return {
        "schema_version": SCHEMA_VERSION,
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


def result_from_records(records: dict[int, dict], config: dict, chash: str, store, stats,
                        study_config: StudyConfig) -> StudyResult:
    recs = tuple(records[i] for i in sorted(records))
    ok = np.array([r["ok"] for r in recs], bool)
    rot = np.array([r["rot_err_deg"] if r["ok"] else np.nan for r in recs], float)
    tr = np.array([r["trans_err_mm"] if r["ok"] else np.nan for r in recs], float)
    bias = np.array([r["bias"] if r["ok"] else [np.nan] * 6 for r in recs], float).reshape(-1, 6)
    summ = summarize_errors(list(recs), study_config.target_mm, study_config.target_deg, study_config.percentile)
    return StudyResult(records=recs, rot_err_deg=rot, trans_err_mm=tr, bias=bias, ok=ok, summary=summ,
                       config=config, config_hash=chash, store=Path(store) if store else None, stats=stats)


def verify(design_or_lens, tolerances, n_lenses: int, seed: int, bench: Bench | None = None, n_poses: int = 24, *,
           workers: int | None = None, scheduler: str | None = None, store=None, resume: bool = False,
           progress: bool = True, self_calibrate: bool = False, config: StudyConfig | None = None,
           plan_seed: int = 0, client=None, description: str = "as-built lenses") -> StudyResult:
    """As-built Monte Carlo of the calibration for ``n_lenses`` as-built lenses.

    design_or_lens: Lens, Design, paper lens name or design JSON path; tolerances:
    Tolerances, TOML path, or None (noise only; ``Tolerances.zero()`` gives the same
    numbers); seed: study seed (trial i uses child i of SeedSequence(seed));
    n_poses: calibration poses per lens (ignored when ``config`` is given);
    workers: 0 = in this process, N = local Dask cluster of N processes (default:
    all cores); scheduler: address of an existing Dask scheduler; store: SQLite file
    to append finished trials to (resume=True continues a killed study; the store
    refuses a different study); self_calibrate: also estimate as-built parameters
    jointly with the poses; description: the progress bar's label. Returns a :class:`StudyResult` (errors in deg and mm).
    A script that starts a local cluster (workers != 0) needs the usual
    ``if __name__ == "__main__":`` guard (worker processes are spawned).
    """
    from .runner import TrialStore, config_hash, run_trials

    if int(n_lenses) != n_lenses or n_lenses < 1:
        raise ConfigError(f"n_lenses: need an integer >= 1, got {n_lenses!r}")
    lens, bench = resolve_lens(design_or_lens, bench)
    tol = resolve_tolerances(tolerances)
    if config is None:
        config = StudyConfig(n_poses=int(n_poses), self_calibrate=bool(self_calibrate))
    elif self_calibrate and not config.self_calibrate:
        config = replace(config, self_calibrate=True)
    ctx = make_context(lens, bench, tol, config, plan_seed)
    cfg = context_config(ctx, seed)
    chash = config_hash(cfg)
    st = TrialStore.open(store, chash, cfg, resume=resume) if store is not None else None
    try:
        records, stats = run_trials(run_trial, ctx, int(n_lenses), int(seed), st, workers=workers,
                                    scheduler=scheduler, progress=progress, description=description,
                                    client=client)
    finally:
        if st is not None:
            st.close()
    return result_from_records(records, cfg, chash, store, stats, config)
