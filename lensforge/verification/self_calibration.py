"""As-built self-calibration: estimate dominant as-built parameters with the calibration.

The standard pipeline estimates each lens pose from its own measurement with the
nominal model, then solves A_i X = Z B_i. Here the calibration is instead solved
directly from the raw Zernike data: the unknowns are X = ^E T_O, Z = ^W T_S (right
perturbations, 12 values) and k as-built lens parameters theta; the lens pose at
robot pose i follows from the rigid chain, B_i = Z^-1 A_i X (the recorded flange
poses A_i are taken as exact: their noise, ~5 um, is far below the as-built
effects), and the residual is the whitened Zernike misfit
L^-1 (h(x_i; theta) - z_i) of all poses, plus a weak Gaussian prior on theta from
the tolerance sizes (a MAP estimate, which keeps nearly-degenerate parameter
combinations finite). Started from the standard hand-eye solution and theta = 0.

Parameters (``PARAMS``): thickness_mm (centre thickness change), index (index
offset), front_power_mm / back_power_mm (sag change at the clear-aperture edge
from a vertex-curvature change, i.e. the defocus part of the form error). These
are the as-built effects a collimated-beam wavefront is most sensitive to.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ..errors import LensforgeError
from ..optics.lens import Lens
from ..optics.pose import matrix_to_pose, pose_to_matrix, transform_error
from ..optics.shack_hartmann import ForwardModel
from ..optics.surfaces import Freeform

__all__ = ["PARAMS", "PRIOR_SIGMA", "perturbed_lens", "self_calibrate", "SelfCalResult", "self_calibrate_trial"]

PARAMS = ("thickness_mm", "index", "front_power_mm", "back_power_mm")
DEFAULT_PARAMS = ("thickness_mm", "index")
# prior 1-sigma per parameter (ASSUMPTION: a few times the default tolerance sizes)
PRIOR_SIGMA = {"thickness_mm": 0.2, "index": 0.01, "front_power_mm": 0.01, "back_power_mm": 0.01}


def perturbed_lens(lens: Lens, theta, names=PARAMS) -> Lens:
    """The nominal lens with the as-built parameters theta (see module doc) applied."""
    th = dict(zip(names, np.asarray(theta, dtype=float)))
    out = lens
    if th.get("thickness_mm", 0.0):
        out = out.replace(thickness=out.thickness + th["thickness_mm"])
    if th.get("index", 0.0):
        out = out.replace(index_offset=out.index_offset + th["index"])
    Ra = 0.5 * lens.aperture
    for side in ("front", "back"):
        s = th.get(f"{side}_power_mm", 0.0)
        if s:
            cs = getattr(out, side).canonical()
            dc = 2.0 * s / (Ra * Ra)
            cs = type(cs)(cs.c + dc, cs.k, cs.alpha, cs.poly, cs.ripple_amplitude, cs.ripple_period)
            out = out.replace(**{side: Freeform.from_canonical(cs)})
    return out


@dataclass(frozen=True)
class SelfCalResult:
    """X, Z (4x4, mm), theta (k,) by name, cost (whitened chi2 incl. prior), success, nfev."""

    X: np.ndarray
    Z: np.ndarray
    theta: dict
    cost: float
    success: bool
    nfev: int


def self_calibrate(bench, lens: Lens, z, A, X0, Z0, T_SO_nominal, names=DEFAULT_PARAMS, prior_sigma=None,
                   max_nfev: int = 30) -> SelfCalResult:
    """Joint estimate of X, Z and the as-built parameters from raw Zernikes z (n, m)
    and flange poses A (n, 4, 4); X0, Z0 from the standard hand-eye solution."""
    names = tuple(names)
    k = len(names)
    ps = np.array([(prior_sigma or PRIOR_SIGMA)[n] for n in names], float)
    nominal = ForwardModel(bench, lens)
    Linv = nominal.whitener
    Tn_inv = np.linalg.inv(T_SO_nominal)
    models: dict = {}

    def model(theta):
        key = tuple(np.round(theta, 15))
        if key not in models:
            if len(models) > 64:
                models.clear()
            models[key] = ForwardModel(bench, perturbed_lens(lens, theta, names), validate=False)
        return models[key]

    # scale: xi in (mm, rad) -> unit steps ~ (1 mm, 1 deg); theta in prior-sigma units
    D = np.r_[np.tile(np.r_[np.ones(3), np.full(3, np.radians(1.0))], 2), ps]

    def unpack(p):
        q = p * D
        X = X0 @ pose_to_matrix(q[:6])
        Z = Z0 @ pose_to_matrix(q[6:12])
        return X, Z, q[12:]

    def poses(X, Z):
        B = np.linalg.solve(Z, A @ X)
        return matrix_to_pose(Tn_inv @ B)

    def fun_many(P):
        """Residuals for several parameter vectors with one trace per distinct lens."""
        out = []
        for p in P:
            X, Z, th = unpack(p)
            res = model(th).evaluate(poses(X, Z), check_range=False)
            r = ((res.z - z) @ Linv.T).ravel()
            if not res.valid.all():
                r = np.where(np.repeat(res.valid, z.shape[1]), r, 1e3)
            out.append(np.r_[r, p[12:]])  # prior: theta / sigma
        return out

    def fun(p):
        return fun_many([p])[0]

    h = 1e-4

    def jac(p):
        f0 = fun(p)
        cols = []
        for j in range(p.size):
            e = np.zeros_like(p)
            e[j] = h
            cols.append((fun_many([p + e])[0] - f0) / h)
        return np.stack(cols, axis=1)

    p0 = np.zeros(12 + k)
    sol = least_squares(fun, p0, jac=jac, method="lm", xtol=1e-10, ftol=1e-10, max_nfev=max_nfev)
    X, Z, th = unpack(sol.x)
    return SelfCalResult(X=X, Z=Z, theta=dict(zip(names, th.tolist())), cost=float(2 * sol.cost),
                         success=bool(sol.success), nfev=int(sol.nfev))


def self_calibrate_trial(ctx, nominal: ForwardModel, z, x_est, x_true, A, X_true, Z_std, X_std,
                         lens_ab: Lens) -> dict:
    """Run self-calibration inside a study trial; returns a record like the trial's
    (ok, rot_err_deg, trans_err_mm, ...) plus the estimated and true parameters."""

    scene = ctx.scene
    try:
        sc = self_calibrate(ctx.bench, ctx.lens, z, A, X_std, Z_std, scene.T_SO_nominal)
    except LensforgeError as e:
        return {"ok": False, "failure": f"self-calibration failed: {e}", "rot_err_deg": None, "trans_err_mm": None}
    rot, trans = transform_error(scene.Z, sc.Z)
    xrot, xtrans = transform_error(X_true, sc.X)
    true = {"thickness_mm": lens_ab.thickness - ctx.lens.thickness,
            "index": lens_ab.index(ctx.bench.laser.wavelength_nm) - ctx.lens.index(ctx.bench.laser.wavelength_nm)}
    return {"ok": True, "failure": "", "rot_err_deg": rot, "trans_err_mm": trans, "x_rot_err_deg": xrot,
            "x_trans_err_mm": xtrans, "theta": sc.theta, "theta_true": true, "chi2": sc.cost,
            "converged": sc.success, "nfev": sc.nfev, "bias": [0.0] * 6, "n_used": int(len(z)),
            "n_pupil_lost": 0, "n_not_converged": 0}
