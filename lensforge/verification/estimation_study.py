"""Pose-estimation study: the paper's Fig. 5 / Table 2 analogue, with the bound.

For each lens, ``trials`` times: the robot commands the nominal pose, the lens
really sits at a pose drawn from the gripper/robot uncertainty model
(``initial_poses``), the sensor measures it with noise, and the estimator starts
from the commanded pose. Reported per lens: median and standard deviation of the
translation and rotation error norms (the paper's Table 2 quantities; also the
paper-style norm of the per-DOF standard deviations), RMSE per DOF over the
Cramer-Rao bound (the bound averaged over the trials' true poses), the reported
covariance's honesty (mean NEES / DOF, 1 when honest), mean chi2/dof, and the
failure rate split into pupil lost (the true pose does not light the pupil, or
the UKF's sigma points leave it) and no convergence (solver failed or left the
bench's pose range). Statistics are over the successful trials. Unobservable DOF
(rank loss, e.g. the spherical lens's rz) are excluded from the error norms and
have no RMSE/CRLB; for a lens symmetric about its axis the estimate (rz held at 0)
is scored against the equivalent true pose without twist (``swing_equivalent``).

Trials are seeded with SeedSequence(seed).spawn(trials); the same seed gives the
same true poses and noise for every lens and method (common random numbers).
"""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError, PupilError, TraceError
from ..fileio import write_atomic
from ..optics.bench import Bench
from ..optics.lens import Lens
from ..optics.pose import DOF_NAMES
from ..optics.sensitivity import metrics_from_S, sensitivity_from_model
from ..optics.shack_hartmann import ForwardModel
from ..calibration.initial_poses import InitialPoseModel, prior_covariance
from ..calibration.pose_estimation import ESTIMATORS, UnobservableWarning, estimate_pose_model
from ..display import UNOBSERVABLE, UNOBSERVABLE_NOTE
from .statistics import median

__all__ = ["LensStudy", "study_lens", "format_table", "save_study",
           "SCHEMA_VERSION"]

SCHEMA_VERSION = 1
OK, PUPIL_LOST, NOT_CONVERGED = "ok", "pupil_lost", "not_converged"


@dataclass(frozen=True, eq=False)
class LensStudy:
    """Per-trial results of one lens and one method.

    errors: (N, 6) estimate - truth (mm, rad), NaN where the trial failed;
    true_poses: (N, 6); status: (N,) "ok" | "pupil_lost" | "not_converged";
    reported_std: (N, 6) the estimator's std (mm, rad); crlb_var: (N, 6) CRLB
    variances at the true poses (NaN where not computable); chi2, nees: (N,);
    n_evals: (N,) poses traced; unobservable: DOF names; seconds: wall time.
    """

    name: str
    method: str
    errors: np.ndarray
    true_poses: np.ndarray
    status: np.ndarray
    reported_std: np.ndarray
    crlb_var: np.ndarray
    chi2: np.ndarray
    nees: np.ndarray
    n_evals: np.ndarray
    dof: int
    unobservable: tuple = ()
    seconds: float = 0.0
    messages: tuple = field(default_factory=tuple)

    @property
    def ok(self) -> np.ndarray:
        return self.status == OK

    @property
    def observable(self) -> np.ndarray:
        return np.array([n not in self.unobservable for n in DOF_NAMES])

    def _norms(self):
        e = self.errors[self.ok]
        obs = self.observable
        t = np.linalg.norm(e[:, :3] * obs[:3], axis=1)
        r = np.linalg.norm(e[:, 3:] * obs[3:], axis=1)
        return t, r

    def summary(self) -> dict:
        """Table row; translation in um, rotation in urad (keys say so)."""
        n = len(self.status)
        ok = self.ok
        k = int(ok.sum())
        t, r = self._norms()
        e = self.errors[ok]
        nan = float("nan")
        rmse = np.sqrt(np.mean(e**2, axis=0)) if k else np.full(6, nan)
        crlb = np.sqrt(np.nanmean(self.crlb_var[ok], axis=0)) if k else np.full(6, nan)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.where(self.observable, rmse / crlb, nan)
        n_obs = int(self.observable.sum())
        scale = np.array([1e3] * 3 + [1e6] * 3)
        return {
            "lens": self.name,
            "method": self.method,
            "trials": n,
            "succeeded": k,
            "failure_rate": (n - k) / n if n else nan,
            "pupil_lost": int(np.sum(self.status == PUPIL_LOST)),
            "not_converged": int(np.sum(self.status == NOT_CONVERGED)),
            "median_translation_error_um": median(t) * 1e3 if k else nan,
            "std_translation_error_um": float(np.std(t, ddof=1) * 1e3) if k > 1 else nan,
            "median_rotation_error_urad": median(r) * 1e6 if k else nan,
            "std_rotation_error_urad": float(np.std(r, ddof=1) * 1e6) if k > 1 else nan,
            "norm_of_dof_std_translation_um": float(np.linalg.norm(np.std(e[:, :3] * self.observable[:3], axis=0, ddof=1)) * 1e3) if k > 1 else nan,
            "norm_of_dof_std_rotation_urad": float(np.linalg.norm(np.std(e[:, 3:] * self.observable[3:], axis=0, ddof=1)) * 1e6) if k > 1 else nan,
            "rmse": {f"{d}_{'um' if i < 3 else 'urad'}": float(rmse[i] * scale[i]) for i, d in enumerate(DOF_NAMES)},
            "crlb_std": {f"{d}_{'um' if i < 3 else 'urad'}": float(crlb[i] * scale[i]) for i, d in enumerate(DOF_NAMES)},
            "rmse_over_crlb": {d: float(ratio[i]) for i, d in enumerate(DOF_NAMES)},
            "mean_nees_per_dof": float(np.mean(self.nees[ok]) / n_obs) if k else nan,
            "mean_chi2_dof": float(np.mean(self.chi2[ok]) / self.dof) if k and self.dof > 0 else nan,
            "mean_poses_traced": float(np.mean(self.n_evals[ok])) if k else nan,
            "ms_per_estimate": 1e3 * self.seconds / n if n else nan,
            "unobservable": list(self.unobservable),
        }


def _crlb_var(model: ForwardModel, x: np.ndarray) -> np.ndarray:
    """CRLB variances (6,) at x (NaN if not computable; inf for unobservable DOF)."""
    S, _, _ = sensitivity_from_model(model, x, raise_invalid=False)
    if S is None:
        return np.full(6, np.nan)
    return metrics_from_S(S, model.noise_cov, model.bench).crlb_std ** 2


def swing_equivalent(x: np.ndarray) -> np.ndarray:
    """For a lens symmetric about its own axis: the pose equivalent to x (rotated about
    the lens's z axis) whose rotation vector has no z component (swing-twist split:
    q (x) q_z(phi) with tan(phi/2) = -q_z / q_w). Translation is unchanged."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_rotvec(x[3:]).as_quat()  # (x, y, z, w)
    phi = -2.0 * np.arctan2(q[2], q[3])
    y = np.array(x, dtype=float)
    y[3:] = (Rotation.from_rotvec(x[3:]) * Rotation.from_rotvec([0.0, 0.0, phi])).as_rotvec()
    return y


def study_lens(bench: Bench, lens: Lens, name: str = "lens", trials: int = 100, method: str = "lm", seed: int = 0,
               initial: InitialPoseModel | None = None, commanded=None, tick=None, **estimator_options) -> LensStudy:
    """Run ``trials`` seeded estimates of one lens (see module docstring); ``tick()`` is called
    after each trial (a progress bar's advance)."""
    if method not in ESTIMATORS:
        raise ConfigError(f"method: {method!r} is not one of {', '.join(ESTIMATORS)}")
    if int(trials) != trials or trials < 1:
        raise ConfigError(f"trials: expected an integer >= 1, got {trials!r}")
    initial = initial or InitialPoseModel()
    c = np.zeros(6) if commanded is None else np.asarray(commanded, dtype=float)
    model = ForwardModel(bench, lens)
    m = len(model.modes)
    opts = dict(estimator_options)
    if method == "ukf":
        opts.setdefault("prior_cov", prior_covariance(initial))
    children = np.random.SeedSequence(seed).spawn(int(trials))
    N = int(trials)
    errors = np.full((N, 6), np.nan)
    truth = np.empty((N, 6))
    status = np.empty(N, dtype=object)
    rstd = np.full((N, 6), np.nan)
    crlb = np.full((N, 6), np.nan)
    chi2 = np.full(N, np.nan)
    nees = np.full(N, np.nan)
    nev = np.zeros(N, dtype=int)
    msgs = []
    unobs: tuple = ()
    dof = m - 6
    t0 = time.perf_counter()
    lim = bench.pose_limits
    for i, child in enumerate(children):
        if tick is not None and i:
            tick()  # trial i - 1 is done (the body below leaves early with ``continue``)
        rng = np.random.default_rng(child)
        x = c + rng.normal(size=6) * initial.sigma
        x[:3] = np.clip(x[:3], -lim.translation_mm, lim.translation_mm)
        truth[i] = x
        res = model.evaluate(x[None], check_range=False)
        if not res.valid[0]:
            status[i] = PUPIL_LOST
            msgs.append(f"trial {i}: true pose does not light the pupil: {res.reason(0)}")
            continue
        z = model.add_noise(res, rng)[0]
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UnobservableWarning)
                est = estimate_pose_model(model, z, x0=c, method=method, **opts)
        except (PupilError, TraceError) as e:
            status[i] = PUPIL_LOST
            msgs.append(f"trial {i}: {e}")
            continue
        nev[i] = est.n_evals
        unobs = est.unobservable or unobs
        dof = est.dof
        if not est.converged:
            status[i] = NOT_CONVERGED
            msgs.append(f"trial {i}: {est.message}")
            continue
        status[i] = OK
        # a lens symmetric about its axis: rz is held at the commanded value (0), so
        # score against the equivalent true pose with no twist
        xs = swing_equivalent(x) if est.unobservable == ("rz",) and c[5] == 0 else x
        errors[i] = est.pose - xs
        rstd[i] = est.std
        chi2[i] = est.chi2
        nees[i] = est.nees(xs)
        crlb[i] = _crlb_var(model, xs)
    if tick is not None:
        tick()
    seconds = time.perf_counter() - t0
    return LensStudy(name=name, method=method, errors=errors, true_poses=truth, status=status.astype(str),
                     reported_std=rstd, crlb_var=crlb, chi2=chi2, nees=nees, n_evals=nev, dof=dof,
                     unobservable=unobs, seconds=seconds, messages=tuple(msgs))


def _fmt(v, nd=1):
    return "n/a" if v is None or not np.isfinite(v) else f"{v:.{nd}f}"


def format_table(results: list[LensStudy]) -> str:
    """Plain-text table (translation um, rotation urad; fail = share of failed trials, lost = pupil
    lost, unconv = not converged), then a legend line."""
    head = (f"{'lens':<22}{'method':<7}{'fail':>6}{'lost':>5}{'unconv':>7}{'med|t| um':>11}{'std|t| um':>11}"
            f"{'med|r| urad':>13}{'std|r| urad':>13}  RMSE/CRLB tx ty tz rx ry rz{'':>6}{'NEES/dof':>9}{'chi2/dof':>9}{'ms':>7}")
    lines = [head]
    for r in results:
        s = r.summary()
        ratio = " ".join((UNOBSERVABLE if d in s["unobservable"] else _fmt(s["rmse_over_crlb"][d], 2)).rjust(4)
                         for d in DOF_NAMES)
        lines.append(
            f"{s['lens'][:21]:<22}{s['method']:<7}{100 * s['failure_rate']:>5.0f}%{s['pupil_lost']:>5}"
            f"{s['not_converged']:>7}{_fmt(s['median_translation_error_um']):>11}"
            f"{_fmt(s['std_translation_error_um']):>11}{_fmt(s['median_rotation_error_urad']):>13}"
            f"{_fmt(s['std_rotation_error_urad']):>13}  {ratio:<32}{_fmt(s['mean_nees_per_dof'], 2):>9}"
            f"{_fmt(s['mean_chi2_dof'], 2):>9}{_fmt(s['ms_per_estimate'], 0):>7}"
        )
    lines.append(f"fail: failed trials (lost: the pose left the SH pupil dark; unconv: the estimator did not "
                 f"converge); {UNOBSERVABLE_NOTE}")
    return "\n".join(lines)


def study_to_dict(results: list[LensStudy], **meta) -> dict:
    """JSON-ready study (schema_version, meta, per-lens summary rows)."""
    def clean(o):
        if isinstance(o, dict):
            return {k: clean(v) for k, v in o.items()}
        if isinstance(o, list):
            return [clean(v) for v in o]
        if isinstance(o, float) and not np.isfinite(o):
            return None
        return o

    return clean({"schema_version": SCHEMA_VERSION, **meta, "lenses": [r.summary() for r in results]})


def save_study(results: list[LensStudy], out_dir, stem: str = "estimate_study", **meta) -> dict:
    """Write <stem>.json (summary), <stem>_trials.csv (per trial) and <stem>.png; return paths."""
    from pathlib import Path

    out = Path(out_dir)
    d = study_to_dict(results, **meta)
    pj = write_atomic(out / f"{stem}.json", json.dumps(d, indent=2, allow_nan=False))
    rows = ["lens,method,trial,status," + ",".join(f"true_{n}" for n in DOF_NAMES) + ","
            + ",".join(f"err_{n}" for n in DOF_NAMES) + ",chi2,nees"]
    for r in results:
        for i in range(len(r.status)):
            vals = list(r.true_poses[i]) + list(r.errors[i]) + [r.chi2[i], r.nees[i]]
            rows.append(f"{r.name},{r.method},{i},{r.status[i]}," + ",".join(f"{v:.9g}" for v in vals))
    pc = write_atomic(out / f"{stem}_trials.csv", "\n".join(rows) + "\n")
    from ..plots.study import plot_estimation_study

    pp = plot_estimation_study(results, out / f"{stem}.png")
    return {"json": pj, "csv": pc, "png": pp}
