"""What is measured: the vector a calibration fits, its noise covariance and its Jacobian.

A Shack-Hartmann sensor measures one slope per lenslet and axis; the WFS software
reduces them to Zernike coefficients. lensforge's forward model
(``optics.shack_hartmann.ForwardModel``) computes the per-lenslet centroid slopes s and
then z = F s (F the fixed least-squares fit matrix). A ``Measurement`` says which
vector the likelihood is written on:

- ``zernike``: z (um, the bench's Noll modes), noise R = sigma^2 F F^T (the model as is);
- ``slopes``: the per-lenslet slopes [sx of the kept lenslets..., sy...] (rad), noise
  sigma^2 I (sigma = bench ``noise.slope_sigma_urad``, per lenslet and axis): the
  likelihood of the raw spot field, no fit between. Lenslets with no spot (NaN) in any
  pose are left out of every pose (an exact likelihood on the rest).

``Measurement.model(forward_model)`` returns a forward model whose ``evaluate(...).z``,
``noise_cov``, ``whitener`` and ``jacobians`` are those of the measured vector (for
slopes: the same model with the fit matrix replaced by the selection of the kept
lenslets' slopes; pose validity, irradiance and spot range are unchanged), so the pose
estimator (``pose_estimation``) and the joint fit (``joint.JointProblem(...,
measurement=...)``) run on either without change. Registry ``MEASUREMENTS``.

``referenced`` (a user reference spot field, ``WFS_SetSpotsToUserReference``, recorded at
session pose r): every pose reports y_i = h(x_i) - h(x_r) + n_i - n_r, x_r the lens pose
of the same chain (X, Z, the robot pose A_r with its own error a_r). ``referenced_information``
gives its exact Fisher information (a_r and the reference's noise n_r as nuisances
shared by every pose: the noise of y is correlated across poses), and
``referenced_calibrate`` the maximum-likelihood fit of X, Z, theta on such data.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import CalibrationError, ConfigError
from ..optics.pose import pose_to_matrix
from ..optics.shack_hartmann import ForwardModel
from ..asbuilt.joint_information import chain_jacobians
from .joint import JointProblem, pose_chain
from .trust_region import eigen_step, gain_ratio, next_radius, predicted_decrease
from . import thorlabs
from .plausibility import check_wfs_header

__all__ = ["Measurement", "MEASUREMENTS", "measurement", "slope_inputs", "plan_jacobians", "spot_bench", "joint_crlb", "canonical_ids",
           "referenced_session",
           "referenced_information", "referenced_calibrate", "ReferencedResult", "LENSLET_MATCH_MM"]

LENSLET_MATCH_MM = 1e-3  # a file's lenslet centre must lie this close to the model's (1/150 pitch)


@dataclass(frozen=True, eq=False)
class Measurement:
    """kind: a MEASUREMENTS name; lenslets: pupil-lenslet indices whose slopes are measured
    (slopes only; None = every pupil lenslet); dropped: pupil lenslets left out (no spot);
    reference: the session pose (index) the data are relative to, or None (absolute)."""

    kind: str = "zernike"
    lenslets: np.ndarray | None = None
    dropped: tuple = field(default=())
    reference: int | None = None  # index of the session pose of a user reference (referenced data)

    def model(self, fm: ForwardModel) -> ForwardModel:
        """The forward model of this measured vector (module docstring)."""
        return MEASUREMENTS[self.kind](self, fm)

    def labels(self, fm: ForwardModel) -> list[str]:
        if self.kind == "zernike":
            return [f"Z{int(j)}" for j in fm.modes]
        idx = self._idx(fm)
        return [f"s{a}[{i}]" for a in "xy" for i in idx]

    def _idx(self, fm: ForwardModel) -> np.ndarray:
        n = fm.pupil.n_lenslets
        return np.arange(n) if self.lenslets is None else np.asarray(self.lenslets, int)


def _zernike(meas: Measurement, fm: ForwardModel) -> ForwardModel:
    return fm


def _slopes(meas: Measurement, fm: ForwardModel) -> ForwardModel:
    idx = meas._idx(fm)
    n = fm.pupil.n_lenslets
    F = np.zeros((2 * idx.size, 2 * n))
    F[np.arange(idx.size), idx] = 1.0
    F[idx.size + np.arange(idx.size), n + idx] = 1.0
    F.setflags(write=False)
    out = copy.copy(fm)
    # the fit matrix becomes the selection of the kept slopes; "modes" number the measured entries
    out.pupil = replace(fm.pupil, F=F, modes=np.arange(2 * idx.size))
    for cached in ("noise_cov", "whitener"):
        out.__dict__.pop(cached, None)
    return out


MEASUREMENTS = {"zernike": _zernike, "slopes": _slopes}


def measurement(kind: str = "zernike", lenslets=None) -> Measurement:
    """A Measurement of a registered kind (ConfigError otherwise)."""
    if kind not in MEASUREMENTS:
        raise ConfigError(f"measurement: {kind!r} is not one of {', '.join(MEASUREMENTS)}")
    return Measurement(kind, None if lenslets is None else np.asarray(lenslets, int))


def spot_bench(bench, fields: thorlabs.SpotFields):
    """The bench with the device's MLA data (focal length, camera pixel) from a spot-field
    file; its header's wavelength and pupil are checked against the bench, and the lenslet
    pitch must be the bench's (ConfigError naming both values)."""
    check_wfs_header(bench, fields.header, fields.source, "file")  # an instrument file: checked in every mode
    pb = bench.sensor.pitch_mm * 1e3
    if abs(fields.lenslet_pitch_um - pb) > 1e-3:
        raise ConfigError(f"{fields.source}: field lenslet_pitch_um: the file's {fields.lenslet_pitch_um:g} um "
                          f"contradicts the bench's sensor.pitch_mm = {bench.sensor.pitch_mm:g} mm; give the bench "
                          "of this sensor (--bench)")
    return bench.replace(sensor={"lenslet_focal_mm": fields.focal_length_um * 1e-3,
                                 "pixel_mm": fields.pixel_pitch_um * 1e-3})


def slope_inputs(fields: thorlabs.SpotFields, fm: ForwardModel, rows=None) -> tuple[Measurement, np.ndarray, list]:
    """(Measurement "slopes", y (n, 2k) measured slopes in rad, warnings) of the spot fields
    at the model's pupil lenslets (rows: the poses to take, default all). A pupil lenslet
    with no spot in any pose is left out of every pose (a warning names how many)."""
    S = fields.slopes if rows is None else fields.slopes[rows]
    cen = fields.centres.reshape(-1, 2)
    pc = fm.pupil.centres
    d = np.linalg.norm(pc[:, None, :] - cen[None, :, :], axis=-1)
    cell = np.argmin(d, axis=1)
    far = d[np.arange(len(pc)), cell] > LENSLET_MATCH_MM
    if far.any():
        raise ConfigError(f"{fields.source}: field center_offset_mm: {int(far.sum())} of the bench's {len(pc)} pupil "
                          f"lenslets have no lenslet in the file's grid within {LENSLET_MATCH_MM * 1e3:g} um (e.g. at "
                          f"{np.round(pc[np.argmax(far)], 4).tolist()} mm); the grid must cover the pupil with the "
                          "bench's lenslet positions")
    s = S.reshape(S.shape[0], -1, 2)[:, cell, :]  # (n, n_pupil, 2)
    ok = np.all(np.isfinite(s), axis=(0, 2))
    warns = []
    if not ok.all():
        warns.append(f"{int((~ok).sum())} of {len(pc)} pupil lenslets have no spot in some pose "
                     f"({fields.source}); they are left out of every pose")
    idx = np.flatnonzero(ok)
    if 2 * idx.size < len(fm.modes) + 6:
        raise ConfigError(f"{fields.source}: only {idx.size} pupil lenslets have a spot in every pose; the pupil "
                          "must be lit (check the beam and the pupil settings)")
    y = np.concatenate([s[:, idx, 0], s[:, idx, 1]], axis=1)
    return Measurement("slopes", idx, tuple(np.flatnonzero(~ok).tolist())), y, warns


# ----------------------------------------------------------------------------- CRLB


def plan_jacobians(bench, param, scene, x, robot_cov, meas: Measurement | None):
    """Whitened S (n, m, 6), Jt (n, m, k), chain blocks, at lens poses x (n, 6) of the
    nominal cell; CalibrationError when a pose is unlit."""
    x = np.atleast_2d(np.asarray(x, float))
    B = scene.T_SO_nominal @ pose_to_matrix(x)
    A = scene.Z @ B @ np.linalg.inv(scene.X)
    pb = JointProblem(bench, param, np.zeros((len(x), 1)), A, scene.T_SO_nominal, robot_cov, True, meas)
    theta = np.zeros(param.k)
    res = pb.model(theta).evaluate(x, check_range=False)
    if not res.valid.all():
        raise CalibrationError(f"poses {np.flatnonzero(~res.valid).tolist()} leave the pupil unlit")
    S, Jt = pb.jacobians(theta, x, res.uv)
    dX, dZ, dA = chain_jacobians(B, x, scene.X)
    return S, Jt, dX, dZ, dA


def _z_block(info: np.ndarray) -> np.ndarray:
    C = np.linalg.inv(0.5 * (info + info.T))
    return C[6:12, 6:12]


def referenced_information(S, Jt, dX, dZ, dA, robot_cov, ref: int | None) -> np.ndarray:
    """Fisher information of (xi_X, xi_Z, theta) from whitened pose and lens Jacobians of
    n poses (module ``joint``'s chain blocks dX, dZ, dA), every robot error and (ref given)
    the reference pose's robot error and reference noise eliminated. ref None: absolute
    measurements (equals ``joint.joint_information``); ref = r: every pose i != r reports
    h(x_i) - h(x_r) with the shared reference noise (module docstring)."""
    n, m, _ = S.shape
    k = Jt.shape[2]
    P = np.linalg.inv(robot_cov)
    rows = [i for i in range(n) if i != ref]
    G = 12 + k + (6 + m if ref is not None else 0)
    N = G + 6 * len(rows)
    H = np.zeros((N, N))
    H[12:12 + k, 12:12 + k] += np.eye(k)  # theta prior N(0, I)
    if ref is not None:
        H[12 + k:18 + k, 12 + k:18 + k] += P  # a_r prior
        H[18 + k:G, 18 + k:G] += np.eye(m)  # reference noise, whitened: N(0, I)
    for b, i in enumerate(rows):
        J = np.zeros((m, N))
        J[:, :6], J[:, 6:12], J[:, 12:12 + k] = S[i] @ dX[i], S[i] @ dZ[i], Jt[i]
        if ref is not None:
            J[:, :6] -= S[ref] @ dX[ref]
            J[:, 6:12] -= S[ref] @ dZ[ref]
            J[:, 12:12 + k] -= Jt[ref]
            J[:, 12 + k:18 + k] = -S[ref] @ dA[ref]
            J[:, 18 + k:G] = -np.eye(m)
        c = G + 6 * b
        J[:, c:c + 6] = S[i] @ dA[i]
        H += J.T @ J
        H[c:c + 6, c:c + 6] += P
    # eliminate everything but (X, Z, theta)
    g = 12 + k
    Hgg, Hgo, Hoo = H[:g, :g], H[:g, g:], H[g:, g:]
    return Hgg - Hgo @ np.linalg.solve(Hoo, Hgo.T)


def joint_crlb(bench, param, scene, x, robot_cov=None, *, kinds=("zernike", "slopes"), reference: int | None = None) -> dict:
    """Joint Z CRLB (theta free, robot errors eliminated) of the lens poses x (n, 6) for
    each measured vector of ``kinds`` and, with ``reference`` = r, the same referenced to
    pose r. Returns {kind: {"Z_sigma": (6,) mm, rad, "Z_translation_mm", "Z_rotation_deg"
    (RMS norms), "cov_Z"}, "<kind>_referenced": ...}."""
    robot_cov = scene.noise.cov if robot_cov is None else np.asarray(robot_cov, float)
    out = {}
    for kind in kinds:
        jac = plan_jacobians(bench, param, scene, x, robot_cov, measurement(kind))
        for ref, name in ((None, kind), (reference, f"{kind}_referenced")):
            if name != kind and reference is None:
                continue
            C = _z_block(referenced_information(*jac, robot_cov, ref))
            d = np.sqrt(np.diag(C))
            out[name] = {"Z_sigma": d.tolist(), "Z_translation_mm": float(np.linalg.norm(d[:3])),
                         "Z_rotation_deg": math.degrees(float(np.linalg.norm(d[3:]))), "cov_Z": C.tolist()}
    return out


# ----------------------------------------------------------------------------- referenced fit


@dataclass(frozen=True, eq=False)
class ReferencedResult:
    """ML fit of referenced data: X, Z (4x4, mm); theta; robot_errors (n, 6) incl. the
    reference pose's; cov: (12 + k)^2 of (xi_X, xi_Z, theta); chi2, dof; iterations; converged."""

    X: np.ndarray
    Z: np.ndarray
    theta: np.ndarray
    robot_errors: np.ndarray
    cov: np.ndarray
    chi2: float
    dof: int
    iterations: int
    converged: bool

    @property
    def cov_X(self):
        return self.cov[:6, :6]

    @property
    def cov_Z(self):
        return self.cov[6:12, 6:12]


def referenced_calibrate(bench, param, y, A, ref: int, T_SO_nominal, X0, Z0, robot_cov, *, meas=None,
                         max_iter: int = 40, tol: float = 1e-2) -> ReferencedResult:
    """Maximum-likelihood X, Z, theta from referenced measurements y (n, m): row i holds
    h(x_i) - h(x_ref) + noise (row ref is unused: zero by construction), x_i the lens pose
    of the chain Z^-1 A_i P(a_i) X (``joint.pose_chain``), theta ~ N(0, I), a_i ~
    N(0, robot_cov), the reference's whitened noise e ~ N(0, I) shared by every row.
    Levenberg-Marquardt on the dense normal equations with the shared step policy
    (``trust_region``; the model is exact: no linearisation enters the cost); covariance
    from the information at the estimate. The Jacobians are retaken every iteration and the
    radius carries over (Moré's scheme); the first step is Gauss-Newton's."""
    y = np.asarray(y, float)
    A = np.asarray(A, float)
    n, m = y.shape
    k = param.k
    if not 0 <= ref < n:
        raise ConfigError(f"reference pose: index {ref} is not one of the {n} poses")
    rows = np.array([i for i in range(n) if i != ref])
    if rows.size < 3:
        raise CalibrationError("referenced calibration: needs at least 3 poses besides the reference")
    P = np.linalg.inv(robot_cov)
    WA = np.linalg.inv(np.linalg.cholesky(robot_cov))
    pb = JointProblem(bench, param, y, A, T_SO_nominal, robot_cov, True, meas)
    X, Z, theta = np.array(X0, float), np.array(Z0, float), np.zeros(k)
    a, e = np.zeros((n, 6)), np.zeros(m)
    G = 12 + k + 6 + m

    def residual(X, Z, theta, a, e, uv0=None):
        B, x = pose_chain(A, X, Z, a, T_SO_nominal)
        res = pb.model(theta).evaluate(x, uv0=uv0, check_range=False)
        L = pb.model(theta).whitener
        w = (res.z[rows] - res.z[ref] - y[rows]) @ L.T + e  # whitened: + the reference's noise
        return w, bool(res.valid.all()), B, x, res.uv

    def cost(w, a, theta, e):
        return float(np.sum(w * w) + np.sum((a @ WA.T) ** 2) + theta @ theta + e @ e)

    w, lit, B, x, uv = residual(X, Z, theta, a, e)
    if not lit:
        raise CalibrationError("referenced calibration: the start leaves a pose unlit; start closer")
    c = cost(w, a, theta, e)
    radius, converged, it = None, False, 0  # trust radius (None: the Gauss-Newton step's length)
    N = G + 6 * rows.size
    for it in range(1, max_iter + 1):
        S, Jt = pb.jacobians(theta, x, uv)
        dX, dZ, dA = chain_jacobians(B, x, X)
        J = np.zeros((rows.size * m, N))
        for b, i in enumerate(rows):
            r = slice(b * m, (b + 1) * m)
            J[r, :6] = S[i] @ dX[i] - S[ref] @ dX[ref]
            J[r, 6:12] = S[i] @ dZ[i] - S[ref] @ dZ[ref]
            J[r, 12:12 + k] = Jt[i] - Jt[ref]
            J[r, 12 + k:18 + k] = -S[ref] @ dA[ref]
            J[r, 18 + k:G] = np.eye(m)
            J[r, G + 6 * b:G + 6 * b + 6] = S[i] @ dA[i]
        # priors: theta, e (unit), a_ref and every a_i (robot covariance)
        H = J.T @ J
        g = J.T @ w.ravel()
        H[12:12 + k, 12:12 + k] += np.eye(k)
        g[12:12 + k] += theta
        H[18 + k:G, 18 + k:G] += np.eye(m)
        g[18 + k:G] += e
        H[12 + k:18 + k, 12 + k:18 + k] += P
        g[12 + k:18 + k] += P @ a[ref]
        for b, i in enumerate(rows):
            c6 = slice(G + 6 * b, G + 6 * b + 6)
            H[c6, c6] += P
            g[c6] += P @ a[i]
        dec = float(g @ np.linalg.lstsq(H, g, rcond=None)[0])
        if dec < tol ** 2 * max(c / max(rows.size * m - 12, 1), 1e-9):
            converged = True
            break
        # the shared step policy (trust_region): Marquardt's scaling, radius in 1-sigma units
        D = np.sqrt(np.maximum(np.diag(H), 1e-300))
        As, gs = H / np.outer(D, D), g / D
        accepted = False
        while True:
            if radius is None:  # the first step: Gauss-Newton's, its length the radius
                u = eigen_step(As[None], gs[None], np.array([np.inf]))[0][0]
                radius = float(np.linalg.norm(u))
            else:
                u = eigen_step(As[None], gs[None], np.array([radius]))[0][0]
            d = u / D
            Xn, Zn = X @ pose_to_matrix(d[:6]), Z @ pose_to_matrix(d[6:12])
            thn, en = theta + d[12:12 + k], e + d[18 + k:G]
            an = a.copy()
            an[ref] += d[12 + k:18 + k]
            an[rows] += d[G:].reshape(-1, 6)
            wn, litn, Bn, xn, uvn = residual(Xn, Zn, thn, an, en, uv)
            cn = cost(wn, an, thn, en) if litn else np.inf
            rho = float(gain_ratio(c - cn, predicted_decrease(g, d, H @ d)))
            radius = float(next_radius(radius, np.linalg.norm(u), rho, cn <= c))
            if cn <= c:
                X, Z, theta, a, e, w, B, x, uv, c = Xn, Zn, thn, an, en, wn, Bn, xn, uvn, cn
                accepted = True
                break
            if radius <= 1e-12:
                break
        if not accepted:
            converged = True
            break
    S, Jt = pb.jacobians(theta, x, uv)
    dX, dZ, dA = chain_jacobians(B, x, X)
    info = referenced_information(S, Jt, dX, dZ, dA, robot_cov, ref)
    cov = np.linalg.inv(0.5 * (info + info.T))
    return ReferencedResult(X=X, Z=Z, theta=theta, robot_errors=a, cov=0.5 * (cov + cov.T), chi2=c,
                            dof=int(rows.size * m - 12), iterations=it, converged=converged)


# ----------------------------------------------------------------------------- session inputs


def _int_id(i: str) -> str:
    t = str(i).strip()
    return str(int(t)) if t.lstrip("+-").isdigit() else t


def canonical_ids(poses, wfs, reference_pose=None):
    """(poses, wfs, reference id or None) with ids matched as integers when every id of
    both files is an integer ("07" = "7"); a robot log with times and no ids
    (``kuka_log``) gets the WFS ids by time; a reference pose without its own
    measurement (its data are zero by construction) gets a zero row."""
    from .kuka_log import assign_by_time

    if getattr(poses, "times", None) is not None:
        times = wfs.header.get("times")
        if not times:
            raise ConfigError(f"{poses.source}: field pose: the log has times but no pose ids, and "
                              f"{wfs.source} has no times (give a folder of per-pose files, or log the pose id)")
        poses = assign_by_time(poses, times)
    if all(str(i).strip().lstrip("+-").isdigit() for i in tuple(poses.ids) + tuple(wfs.ids)):
        for table in (poses, wfs):
            c = [_int_id(i) for i in table.ids]
            if len(set(c)) != len(c):
                dup = next(i for i in c if c.count(i) > 1)
                raise ConfigError(f"{table.source}: field pose: two ids are the integer {dup}; give each pose "
                                  "its own id")
        poses = replace(poses, ids=tuple(_int_id(i) for i in poses.ids))
        wfs = replace(wfs, ids=tuple(_int_id(i) for i in wfs.ids))
    ref = reference_pose if reference_pose is not None else wfs.header.get("reference_pose")
    if ref is None:
        return poses, wfs, None
    ref = _int_id(ref) if str(ref).strip().lstrip("+-").isdigit() and all(
        str(i).lstrip("+-").isdigit() for i in poses.ids) else str(ref).strip()
    if ref not in poses.ids:
        raise ConfigError(f"{poses.source}: field pose: the reference pose {ref!r} has no robot pose; the "
                          "reference must be recorded at one of the session's poses")
    if ref not in wfs.ids:  # the reference's own measurement is zero by construction
        if isinstance(wfs, thorlabs.SpotFields):
            zero = np.where(np.isfinite(wfs.slopes[0]), 0.0, np.nan)[None]
            wfs = replace(wfs, ids=wfs.ids + (ref,), slopes=np.concatenate([wfs.slopes, zero]))
        else:
            wfs = replace(wfs, ids=wfs.ids + (ref,), zernike=np.vstack([wfs.zernike, np.zeros(wfs.zernike.shape[1])]),
                          rows=tuple(wfs.rows) + (0,))
    return poses, wfs, ref


def referenced_session(data, *, tolerances="default", outlier_alpha: float = 1e-3, progress=None):
    """CalibrationResult of a session whose measurements are relative to a user reference
    taken at pose ``data.measurement.reference`` (``referenced_calibrate`` from the cell's
    nominal X, Z; theta from the tolerance model as the joint method's; tolerances "none" or
    None: the lens as designed). No outlier pass, no two-stage fallback."""
    from scipy.special import chdtrc

    from ..asbuilt.lens_params import parameterise
    from ..optics.pose import invert_poses, matrix_to_pose
    from ..asbuilt.tolerances import no_tolerance_model, resolve_tolerances
    from .session_joint import JointFrames
    from .session_result import CalibrationResult

    known = no_tolerance_model(tolerances)  # no prior: the lens as designed (theta has no direction)
    tol, tol_label = resolve_tolerances("default" if known else tolerances)
    model, scene = data.model, data.scene
    meas = data.measurement
    base = Measurement(meas.kind, meas.lenslets, meas.dropped)
    Tn = scene.T_SO_nominal
    x_start = matrix_to_pose(invert_poses(Tn) @ invert_poses(scene.Z) @ data.A @ scene.X)
    param = parameterise(model.bench, model.lens, tol, x_start, as_designed=known)
    res = referenced_calibrate(model.bench, param, data.z, data.A, meas.reference, Tn, scene.X, scene.Z,
                               scene.noise.cov, meas=base)
    p = float(chdtrc(res.dof, res.chi2))
    warns = []
    if p < outlier_alpha:
        warns.append(f"model check failed: chi2/dof = {res.chi2 / res.dof:.3g} (p = {p:.2g}) on the referenced data")
    if not res.converged:
        warns.append(f"referenced fit stopped after {res.iterations} iterations without meeting its tolerance")
    frames = JointFrames(X=res.X, Z=res.Z, cov_X=res.cov_X, cov_Z=res.cov_Z, joint=res)
    ref_id = data.ids[meas.reference]
    extra = {"tolerances": "none" if known else tol_label, "measurement": meas.kind, "reference_pose": ref_id,
             "iterations": res.iterations, "converged": bool(res.converged), "start": "the cell's nominal X, Z"}
    return CalibrationResult(X=res.X, Z=res.Z, handeye=frames, poses_used=tuple(data.ids),
                             poses_rejected=tuple(data.rejected), per_pose=(), chi2=float(res.chi2), dof=int(res.dof),
                             chi2_dof=float(res.chi2 / res.dof), p_value=p, method="joint-referenced",
                             robot=data.robot_name, warnings=tuple(warns), extra=extra)
