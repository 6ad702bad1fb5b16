"""Joint maximum-likelihood calibration through an as-built lens, from the raw Zernike data.

Unknowns: X = ^E T_O (grasp), Z = ^W T_S (sensor in the robot base), the as-built lens
parameters theta (``lens_params.LensParameterisation``, prior N(0, I)) and the robot's
pose error a_i of every pose (recorded flange pose A_i, actual A_i P(a_i), a_i ~
N(0, Sigma_A): ``robot.RobotNoise``). Frames and the right-perturbation convention
are those of ``handeye`` (DESIGN.md): the lens at pose i is

    B_i = Z^-1 A_i P(a_i) X,   x_i = log(T_SO,nominal^-1 B_i)   (DESIGN's pose vector)

and the sensor reports z_i = h(x_i; theta) + noise, noise ~ N(0, R) (the Zernike
noise covariance of the bench, whitener L^-1). The negative log-likelihood (MAP with
the priors) is

    sum_i |L^-1 (h(x_i; theta) - z_i)|^2 + sum_i |L_A^-1 a_i|^2 + |theta|^2.

Robot pose errors are explicit parameters, not marginalised: the likelihood stays
exact (no linearisation of h in the robot error enters the cost), the per-pose blocks
are eliminated in every Gauss-Newton step by a Schur complement (6x6 solves, cost
linear in the number of poses), and the same elimination gives the covariance of
(X, Z, theta) with the robot errors as nuisance. Marginalising them into the residual
covariance instead (R + S_i G Sigma_A G^T S_i^T) would need an m x m factorisation per
pose and iteration and is exact only to first order.

Solver: Levenberg-Marquardt on the block-arrow normal equations with lensforge's one
step policy (``trust_region``: a radius on the step in conditional 1-sigma units, Marquardt's
scaling sqrt(diag H), changed by the gain ratio), started from a
two-stage solution (per-pose estimates + hand-eye) and theta = 0, all unknowns free
from the first step (theta steps capped at 3 prior sigmas; holding theta for a first
step moved the poses onto the nominal lens's biased fit, from which theta wandered to
10-26 prior sigmas before coming back: 2-4x more traces to the same minimum). Jacobians:
dh/dx and dh/dtheta exact, in one batched trace (``ForwardModel.jacobians`` with the
parameterisation's lens tangents), dh/dx chained analytically to (X, Z, a_i); the study
passes the parameterisation's dh/dtheta at the plan as the start. They cost most of the
time, so the iterations reuse them (inexact Gauss-Newton with exact residuals) and
relinearise only when a step fails to shrink the Gauss-Newton decrement by 4x. With
non-zero residuals r the fixed point of Jacobians J + dJ taken at another state is
off the minimum by (J^T J)^-1 dJ^T r, so convergence is always confirmed with pose
and theta Jacobians at the estimate: it is where the remaining step with those is
below ``tol`` (1e-2) sigma, and the covariance uses them (taken within 0.3 sigma of
the estimate, over which dh/dtheta changes by ~0.3 %).

Uncertainty: the covariance of (xi_X, xi_Z, theta) is the inverse of the Schur
complement of the joint information (priors included) at the estimate, i.e. the joint
Cramer-Rao bound with theta and the robot errors as nuisances (Bayesian in theta).
``crlb_Z_known_lens`` is the bound on Z if theta were known, for comparison. Model
mismatch: the minimised cost is chi^2 with n m - 12 degrees of freedom (the prior
terms add as many pseudo-observations as unknowns); ``p_value`` is its upper tail.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import chdtrc

from ..errors import CalibrationError
from ..optics.pose import invert_poses, matrix_to_pose, pose_to_matrix
from ..optics.sensitivity import JACOBIAN_EVALS
from ..optics.shack_hartmann import ForwardModel
from ..asbuilt.joint_information import chain_jacobians  # the chain's derivatives live below calibration (design uses them)
from ..asbuilt.lens_params import LensParameterisation
from .trust_region import damped_step, gain_ratio, next_radius, predicted_decrease

__all__ = ["JointCalibrationResult", "JointProblem", "WindowPasses", "joint_calibrate", "joint_information", "pose_chain",
           "simulate_joint_data"]

# relinearise the iteration Jacobians when a step is not at least this much smaller than the one before
_REFRESH_RATIO = 0.5
# converged when the remaining Gauss-Newton step is below this many 1-sigma (Mahalanobis length)
_STEP_TOL = 1e-2
_NUMERIC_FLOOR = 1e-9  # whitened misfit per dof treated as zero (a remaining step below ~3e-7 sigma)
# largest theta step per iteration (prior sigmas): the start's pose error must not be absorbed by theta
_THETA_TRUST = 3.0
# a step shorter than this (1-sigma units) keeps the Jacobians fresh for the covariance
_FRESH_STEP = 0.3
_MIN_RADIUS = 1e-12  # no descent within this trust radius (1-sigma units): a minimum, to rounding
# a cross-talk bench: times the fit goes on with the windows its minimum's spots put elsewhere (``JointProblem.windows``)
_WINDOW_PASSES = 4
# relative step of the central difference of h in the lenslet focal length (a cross-talk bench with the gain)
_FOCAL_STEP = 1e-4


def pose_chain(A, X, Z, a, T_SO_nominal):
    """Lens poses of the chain: B_i = Z^-1 A_i P(a_i) X (n, 4, 4) and their pose
    vectors x_i = log(T_SO,nominal^-1 B_i) (n, 6)."""
    B = invert_poses(Z) @ A @ pose_to_matrix(a) @ X
    return B, matrix_to_pose(invert_poses(T_SO_nominal) @ B)


def sensor_gain(theta, k_lens: int, gain_sigma: float) -> float:
    """The sensor gain g = 1 + gain_sigma s of a joint state theta = (lens (k_lens), s) (1
    without the gain parameter, gain_sigma = 0)."""
    return 1.0 + gain_sigma * float(theta[k_lens]) if gain_sigma > 0 else 1.0


class WindowPasses:
    """The window passes of a fit on a cross-talk model, whose centroid windows are frozen within a fit and
    placed again by the tracking rule at its minimum. A spot within the window's truncation bias of a half-pixel
    boundary has two stable windows, so the rule may put the next minimum's windows back where they were: the
    passes cycle and no window set is its own minimum's. The objective is chi2(x, windows(x)); a pass's minimum
    with windows the rule does not place there is not a value of it (``pose_estimation._polish`` compares its
    passes the same way). ``settle`` records each pass; the fit goes on while the windows are new and the passes
    last, then stands at ``best``, the state of least objective seen."""

    def __init__(self, limit: int):
        self.limit = int(limit)
        self.seen: list = []  # the window sets minimised with so far
        self.best = None  # the state of least objective seen
        self.best_objective = np.inf
        self.passes = 0

    def settle(self, frozen, placed, objective: float, state) -> bool:
        """A minimum found with the windows ``frozen``, where the rule places ``placed`` and the objective is
        ``objective`` (``state``: whatever the caller restores). True: go on with ``placed`` (a set not had
        before, within the limit); False: stop at ``best``."""
        if self.best is None or objective < self.best_objective:
            self.best, self.best_objective = state, float(objective)
        self.seen.append(np.asarray(frozen))
        if self.passes >= self.limit or any(np.array_equal(placed, w) for w in self.seen):
            return False
        self.passes += 1
        return True


@dataclass(frozen=True, eq=False)
class JointCalibrationResult:
    """Outcome of :func:`joint_calibrate`.

    X, Z: 4x4 (mm); theta: (k,) as-built parameters (prior-sigma units); robot_errors:
    (n, 6) estimated flange pose errors a_i (mm, rad); cov: (12+k, 12+k) covariance of
    (xi_X, xi_Z, theta) (right perturbations, mm and rad; joint CRLB at the estimate);
    cov_X, cov_Z (6x6), cov_theta (k x k); crlb_Z_known_lens: 6x6 bound on Z with theta
    known; theta_sigma: posterior 1-sigma of theta (prior is 1); identifiable: (k,)
    theta_sigma < 0.5 (the data at least halve the prior); chi2, dof, p_value: the
    model-mismatch test; mismatch: p_value < alpha; iterations, converged, n_traced
    (poses traced); used: (n,) poses used (lit at the start and not darkened by a
    descending step: a pose at the pupil's edge leaves the problem rather than block it;
    robot_errors has one row per used pose); lens: the as-built lens of theta.
    """

    X: np.ndarray
    Z: np.ndarray
    theta: np.ndarray
    robot_errors: np.ndarray
    cov: np.ndarray
    crlb_Z_known_lens: np.ndarray
    chi2: float
    dof: int
    p_value: float
    alpha: float
    iterations: int
    converged: bool
    n_traced: int
    parameterisation: LensParameterisation
    used: np.ndarray
    gain_sigma: float = 0.0

    @property
    def k_lens(self) -> int:
        return self.parameterisation.k

    @property
    def has_gain(self) -> bool:
        return self.gain_sigma > 0

    @property
    def theta_lens(self) -> np.ndarray:
        return self.theta[:self.k_lens]

    @property
    def sensor_gain(self) -> float:
        """Estimated g: effective lenslet focal length / the bench's (1 without the gain)."""
        return sensor_gain(self.theta, self.k_lens, self.gain_sigma)

    @property
    def sensor_gain_std(self) -> float:
        """Posterior 1-sigma of g (0 without the gain)."""
        return self.gain_sigma * float(np.sqrt(self.cov[12 + self.k_lens, 12 + self.k_lens])) if self.has_gain else 0.0

    @property
    def cov_X(self) -> np.ndarray:
        return self.cov[:6, :6]

    @property
    def cov_Z(self) -> np.ndarray:
        return self.cov[6:12, 6:12]

    @property
    def cov_theta(self) -> np.ndarray:
        """Covariance of the lens parameters (k_lens, k_lens)."""
        return self.cov[12:12 + self.k_lens, 12:12 + self.k_lens]

    @property
    def theta_sigma(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov_theta))

    @property
    def identifiable(self) -> np.ndarray:
        return self.theta_sigma < 0.5

    @property
    def mismatch(self) -> bool:
        return bool(self.p_value < self.alpha)

    @property
    def lens(self):
        return self.parameterisation.build(self.theta_lens)

    def summary(self) -> dict:
        """JSON-ready numbers: Z 1-sigma (mm, deg), chi2 test, theta and its identifiability."""
        dz = np.sqrt(np.diag(self.cov_Z))
        dk = np.sqrt(np.diag(self.crlb_Z_known_lens))
        return {"Z_sigma_mm": dz[:3].tolist(), "Z_sigma_deg": np.degrees(dz[3:]).tolist(),
                "Z_sigma_known_lens_mm": dk[:3].tolist(), "Z_sigma_known_lens_deg": np.degrees(dk[3:]).tolist(),
                "chi2": self.chi2, "dof": self.dof, "p_value": self.p_value, "mismatch": self.mismatch,
                "theta": self.theta_lens.tolist(), "theta_sigma": self.theta_sigma.tolist(),
                **({"sensor_gain": self.sensor_gain, "sensor_gain_std": self.sensor_gain_std}
                   if self.has_gain else {}),
                "n_identifiable": int(self.identifiable.sum()), "iterations": self.iterations,
                "converged": self.converged}


class JointProblem:
    """Residuals and Jacobians of the joint problem (see the module doc)."""

    def __init__(self, bench, param: LensParameterisation, z, A, T_SO_nominal, robot_cov, theta_prior: bool,
                 measurement=None, gain_sigma: float = 0.0):
        self.bench = bench
        self.measurement = measurement  # what is measured (calibration.measurement; None: the Zernikes)
        self.param = param
        self.z = z
        self.A = A
        self.Tn = T_SO_nominal
        self.n, self.m = z.shape
        # the sensor's gain g = 1 + gain_sigma s (s ~ N(0, 1), theta's last entry): the effective
        # lenslet focal length f (1 + gain_sigma s) scales every reported slope (module doc)
        self.gain_sigma = float(gain_sigma)
        # on a cross-talk bench the focal length is also the model's: the neighbours' light interferes in each
        # window over a path difference ~p^2 / 2f (~25 rad), so 1 % of f moves the small modes by up to 9 sigma
        # beyond the gain (the physical sensor, polynomial lens at nominal, f 5.252 against 5.2 mm: the gain
        # alone leaves 8.8 sigma, the model at f g 0.38); the own centroid's h does not depend on f
        self.focal_in_model = self.gain_sigma > 0 and bench.sensor.crosstalk != "none"
        self.k_lens = param.k
        self.k = param.k + (1 if self.gain_sigma > 0 else 0)
        self.theta_prior = theta_prior
        LA = np.linalg.cholesky(robot_cov)
        self.WA = np.linalg.inv(LA)  # L_A^-1
        self.robot_cov = robot_cov
        self._model_key = None
        self._model = None
        self.Li = None
        self.n_traced = 0
        # the cross-talk model's centroid windows (n, lenslets, 2), frozen at the first exact linearisation (None:
        # placed on the spots at each evaluation): whole-pixel placement makes h jump, ~3 whitened units where a
        # spot crosses a half pixel, and a fit across such jumps stalls (seen: a physical session cycling at chi2 398)
        self.windows = None

    def drop(self, keep) -> None:
        """Keep only the poses ``keep`` (n,) of the problem."""
        self.z, self.A = self.z[keep], self.A[keep]
        self.n = int(np.sum(keep))
        if self.windows is not None:
            self.windows = self.windows[keep]

    def gain(self, theta) -> float:
        """The sensor gain g of the state (1 without the gain parameter)."""
        return sensor_gain(theta, self.k_lens, self.gain_sigma)

    def model(self, theta, focal_step: float = 0.0) -> ForwardModel:
        """The forward model of the state theta: its lens, and on a cross-talk bench the lenslet focal length
        f g (times 1 + focal_step: a difference step, not cached)."""
        theta = np.asarray(theta, float)
        g = self.gain(theta) if self.focal_in_model else 1.0
        key = theta[:self.k_lens].tobytes() + np.float64(g).tobytes()
        if key == self._model_key and not focal_step:
            return self._model
        bench = self.bench
        if g != 1.0 or focal_step:
            bench = bench.replace(sensor={"lenslet_focal_mm": bench.sensor.lenslet_focal_mm * g * (1 + focal_step)})
        model = ForwardModel(bench, self.param.build(theta[:self.k_lens]), validate=False)
        if self.measurement is not None:
            model = self.measurement.model(model)
        if focal_step:
            return model
        self._model, self._model_key = model, key
        if self.Li is None:
            self.Li = model.whitener
        return model

    def residuals(self, X, Z, theta, a, uv0=None, place_windows: bool = False):
        """(r_z (n, m) whitened, lit (n,), B, x, uv, z_model) at the state; place_windows: the
        cross-talk model's windows placed on the state's spots, and frozen there."""
        B, x = pose_chain(self.A, X, Z, a, self.Tn)
        res = self.model(theta).evaluate(x, uv0=uv0, check_range=False,
                                         windows=None if place_windows else self.windows)
        if place_windows:
            self.windows = res.windows
        self.n_traced += self.n
        zm = self.gain(theta) * res.z
        r = (zm - self.z) @ self.Li.T
        return r, res.valid, B, x, res.uv, zm

    def cost(self, r, a, theta) -> float:
        c = float(np.sum(r * r)) + float(np.sum((a @ self.WA.T) ** 2))
        return c + (float(theta @ theta) if self.theta_prior else 0.0)

    def pose_jacobian(self, theta, x, uv):
        """Whitened dh/dx (n, m, 6): the optics' exact Jacobian, rays warm-started from uv."""
        J, _, _ = self.model(theta).jacobians(x, uv0=uv, windows=self.windows)
        self.n_traced += JACOBIAN_EVALS * self.n
        return self.gain(theta) * np.einsum("ij,njp->nip", self.Li, J)

    def jacobians(self, theta, x, uv, exact: bool = True):
        """Whitened dh/dx (n, m, 6) and dh/dtheta (n, m, k) in one batched trace
        (``ForwardModel.jacobians`` with the parameterisation's lens tangents at theta); exact,
        or (exact=False) the iteration Jacobians without the change of det J (~1e-3 off, half
        the cost)."""
        lt = self.param.tangents(np.asarray(theta, float)[:self.k_lens], self.bench.laser.wavelength_nm)
        J, Jt, res = self.model(theta).jacobians(x, uv0=uv, lens_tangents=lt, exact=exact, windows=self.windows)
        if exact and self.windows is None:  # frozen at the first exact linearisation (the same residuals there)
            self.windows = res.windows
        self.n_traced += JACOBIAN_EVALS * self.n
        g = self.gain(theta)
        S, Jt = g * np.einsum("ij,njp->nip", self.Li, J), g * np.einsum("ij,njp->nip", self.Li, Jt)
        if self.k > self.k_lens:  # d(g h)/ds = gain_sigma h (+ g dh/ds through the model's focal length)
            dz = self.gain_sigma * res.z
            if self.focal_in_model:  # g dh/ds = g gain_sigma f_bench dh/df, f = f_bench g: a central difference in
                e = _FOCAL_STEP       # f (1 +- e), the windows frozen
                hp, hm = (self.model(theta, focal_step=t).evaluate(x, uv0=uv, check_range=False,
                                                                     windows=self.windows).z for t in (e, -e))
                self.n_traced += 2 * self.n
                dz = dz + self.gain_sigma * (hp - hm) / (2 * e)
            Jt = np.concatenate([Jt, (dz @ self.Li.T)[..., None]], axis=2)
        return S, Jt

    def blocks(self, S, Jt, B, x, X):
        """Per-pose Jacobians: global (n, m, 12+k) and robot error (n, m, 6)."""
        dX, dZ, dA = chain_jacobians(B, x, X)
        Jg = np.concatenate([S @ dX, S @ dZ, Jt], axis=2)
        return Jg, S @ dA


def _normal_equations(Jg, Ja, r, a, theta, WA, theta_prior: bool):
    """Schur complement of the block-arrow normal equations over the robot errors.

    Returns (Sg (G, G), bg (G,), Haa_inv (n, 6, 6), Hga (n, G, 6), ba (n, 6)) with
    H = J^T J and b = J^T r (priors included)."""
    G = Jg.shape[2]
    k = G - 12
    P = WA.T @ WA
    Hgg = np.einsum("nmi,nmj->ij", Jg, Jg)
    bg = np.einsum("nmi,nm->i", Jg, r)
    if theta_prior and k:
        Hgg[12:, 12:] += np.eye(k)
        bg[12:] += theta
    Haa = np.einsum("nmi,nmj->nij", Ja, Ja) + P
    ba = np.einsum("nmi,nm->ni", Ja, r) + a @ P.T
    Hga = np.einsum("nmi,nmj->nij", Jg, Ja)
    return Hgg, bg, Haa, Hga, ba


def _schur(Hgg, bg, Haa, Hga, ba, lam: float = 0.0):
    Dg = np.diag(np.diag(Hgg)) * lam
    Haa_l = Haa + lam * np.einsum("nii->ni", Haa)[..., None] * np.eye(6)
    Hinv = np.linalg.inv(Haa_l)
    HgaHi = Hga @ Hinv  # (n, G, 6)
    S = Hgg + Dg - np.einsum("ngi,nhi->gh", HgaHi, Hga)
    rhs = bg - np.einsum("ngi,ni->g", HgaHi, ba)
    return S, rhs, Hinv


def joint_information(S_w, B, x, X, Jt, robot_cov, theta_prior: bool = True) -> np.ndarray:
    """Information of (xi_X, xi_Z, theta) with the robot errors eliminated, from the
    whitened pose Jacobians S_w (n, m, 6) and theta Jacobians Jt (n, m, k) at lens poses
    B (n,4,4) / pose vectors x (n, 6) and grasp X; its inverse is the joint CRLB."""
    dX, dZ, dA = chain_jacobians(B, x, X)
    Jg = np.concatenate([S_w @ dX, S_w @ dZ, Jt], axis=2)
    n = Jg.shape[0]
    WA = np.linalg.inv(np.linalg.cholesky(robot_cov))
    Hgg, bg, Haa, Hga, ba = _normal_equations(Jg, S_w @ dA, np.zeros(Jg.shape[:2]), np.zeros((n, 6)),
                                              np.zeros(Jt.shape[2]), WA, theta_prior)
    S, _, _ = _schur(Hgg, bg, Haa, Hga, ba)
    return 0.5 * (S + S.T)


def _solve(S, b):
    try:
        return np.linalg.solve(S, b)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(S, b, rcond=None)[0]


def _inv(S):
    try:
        C = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        C = np.linalg.pinv(S, hermitian=True)
    return 0.5 * (C + C.T)


def joint_calibrate(bench, param: LensParameterisation, z, A, T_SO_nominal, X0, Z0, robot_cov, *,
                    theta0=None, theta_prior: bool = True, max_iter: int = 40, tol: float = _STEP_TOL,
                    alpha: float = 1e-3, theta_jacobian0=None,
                    refresh_ratio: float = _REFRESH_RATIO, measurement=None,
                    gain_sigma: float | None = None) -> JointCalibrationResult:
    """Joint ML/MAP estimate of X, Z, theta and the robot pose errors (module doc).

    bench: the optics bench; param: theta parameterisation; z: (n, m) measured Zernikes
    (um, the bench's modes); A: (n, 4, 4) recorded flange poses ^W T_E; T_SO_nominal:
    4x4 nominal lens placement; X0, Z0: start (e.g. the two-stage hand-eye solution);
    robot_cov: 6x6 flange pose noise covariance (right perturbation, (mm, rad)^2, e.g.
    RobotNoise().cov); theta0: start for theta (default 0); theta_prior: include the
    N(0, I) prior on theta (False: pure ML in theta, for noise-free checks); tol:
    convergence when the remaining Gauss-Newton step is shorter than tol 1-sigma
    (Mahalanobis length; sigma scaled by the residuals' RMS, so that noise-free data
    converge to rounding); alpha: level of
    the chi^2 mismatch test. Speed only (the minimum and the covariance do not depend
    on them): theta_jacobian0: (n, m, k) whitened dh/dtheta near the start, e.g.
    ``LensParameterisation.theta_jacobian`` at the commanded poses (default: traced
    here); refresh_ratio: relinearise the iteration Jacobians when a step shrinks by
    less than this factor. gain_sigma: relative 1-sigma prior of the sensor's effective
    lenslet focal length, estimated as a common gain on every reported value (theta's
    last entry; default ``bench.sensor.focal_length_rel_sigma``; 0: known).
    """
    z = np.atleast_2d(np.asarray(z, dtype=float))
    A = np.asarray(A, dtype=float)
    n = z.shape[0]
    if A.shape != (n, 4, 4):
        raise CalibrationError(f"A: expected ({n}, 4, 4) flange poses (one per Zernike vector), got {A.shape}")
    if n < 3:
        raise CalibrationError(f"joint calibration: needs at least 3 poses, got {n}")
    gain_sigma = float(bench.sensor.focal_length_rel_sigma if gain_sigma is None else gain_sigma)
    if not (math.isfinite(gain_sigma) and gain_sigma >= 0):
        raise CalibrationError(f"gain_sigma: expected a finite number >= 0, got {gain_sigma!r}")
    if gain_sigma > 0:
        theta_jacobian0 = None  # a lens-only start Jacobian has no gain column: traced here
    k = param.k + (1 if gain_sigma > 0 else 0)
    if theta_jacobian0 is not None and np.shape(theta_jacobian0) != (n, z.shape[1], k):
        raise CalibrationError(f"theta_jacobian0: expected shape ({n}, {z.shape[1]}, {k}), "
                               f"got {np.shape(theta_jacobian0)}")
    X, Z = np.array(X0, float), np.array(Z0, float)
    theta = np.zeros(k) if theta0 is None else np.array(theta0, float)
    Tn = np.asarray(T_SO_nominal, float)
    # poses the start model cannot light are left out (the pupil test is not differentiable)
    _, x0 = pose_chain(A, X, Z, np.zeros((n, 6)), Tn)
    used = ForwardModel(bench, param.build(theta[:param.k]), validate=False).evaluate(x0, check_range=False).valid
    if used.sum() < 3:
        raise CalibrationError(f"joint calibration: only {int(used.sum())} of {n} poses light the pupil at the "
                               "start; start closer (X0, Z0) or choose poses nearer nominal")
    pb = JointProblem(bench, param, z[used], A[used], Tn, np.asarray(robot_cov, float), theta_prior, measurement,
                      gain_sigma)
    n = int(used.sum())
    a = np.zeros((n, 6))
    r, lit, B, x, uv, zm = pb.residuals(X, Z, theta, a)
    cost = pb.cost(r, a, theta)
    # Iteration Jacobians (inexact Gauss-Newton): the approximate ones (``JointProblem.jacobians``,
    # exact=False), kept while the steps contract; the residuals are exact, so the fixed point is the
    # exact minimiser once the Jacobians are fresh: exact, at the current state (or within 0.3 sigma),
    # the covariance's. Convergence is only declared on fresh ones.
    if theta_jacobian0 is not None:
        S, Jt = pb.pose_jacobian(theta, x, uv), np.asarray(theta_jacobian0, float)[used]
    else:
        S, Jt = pb.jacobians(theta, x, uv, exact=False)
    fresh = False
    passes = WindowPasses(_WINDOW_PASSES)

    def moved_windows() -> bool:
        # at a minimum with frozen windows: do the estimate's spots put them elsewhere? Then the fit goes on with
        # those (and their residuals), up to _WINDOW_PASSES times and until the windows come back to a set it has
        # had (a spot on a half pixel may flip back and forth); it then stands at the best point seen by the
        # objective, chi2 with the windows the rule places there (WindowPasses)
        nonlocal r, lit, B, x, uv, zm, cost, X, Z, theta, a, fresh
        if pb.windows is None:
            return False
        frozen = pb.windows
        placed = pb.residuals(X, Z, theta, a, uv0=uv, place_windows=True)
        objective = pb.cost(placed[0], a, theta) if placed[1].all() else np.inf
        state = (X, Z, theta, a, *placed, pb.windows)
        if passes.settle(frozen, pb.windows, objective, state):
            (r, lit, B, x, uv, zm), cost = placed, objective
            return True
        best, cost = passes.best, passes.best_objective
        X, Z, theta, a, r, lit, B, x, uv, zm, pb.windows = best
        # the Jacobians are the covariance's only at the point and windows they were taken with
        fresh = fresh and best is state and np.array_equal(frozen, pb.windows)
        return False

    dof = n * pb.m - 12 - (0 if theta_prior else k)
    radius, lam = None, 0.0  # trust radius, conditional 1-sigma units (None: the next Gauss-Newton step's length)
    converged = False
    it = 0
    prev_dec = np.inf
    for it in range(1, max_iter + 1):
        Jg, Ja = pb.blocks(S, Jt, B, x, X)
        Hgg, bg, Haa, Hga, ba = _normal_equations(Jg, Ja, r, a, theta, pb.WA, theta_prior)
        # Gauss-Newton decrement: the squared Mahalanobis length of the remaining step
        # (compared in 1-sigma units scaled by the residuals' RMS: noise-free data converge too)
        # (block elimination: b^T H^-1 b = rhs^T Sg^-1 rhs + sum_i ba_i^T Haa_i^-1 ba_i; the
        # robot-error part alone once hid a remaining 0.2 drop of chi^2)
        Sg, rhs, Hinv = _schur(Hgg, bg, Haa, Hga, ba)
        dec = float(rhs @ _solve(Sg, rhs)) + float(np.einsum("ni,nij,nj->", ba, Hinv, ba))
        # below _NUMERIC_FLOOR the misfit is the forward model's own rounding (noise-free
        # data: whitened RMS ~3e-8), where the decrement fits rounding and never shrinks
        scale = max(cost / dof, _NUMERIC_FLOOR)
        if dec < tol ** 2 * scale:
            if fresh and not moved_windows():  # at the minimum, by the covariance's own Jacobians
                converged = True
                break
            # the iteration Jacobians' fixed point is off the minimum by (J^T J)^-1 dJ^T r
            # when the residuals r are not zero: finish with fresh ones
            (S, Jt), fresh = pb.jacobians(theta, x, uv), True
            prev_dec, radius = np.inf, None
            continue
        accepted = False
        Dg2, Da2 = np.diag(Hgg), np.einsum("nii->ni", Haa)  # Marquardt's scaling D^2 = diag H

        def solve(lam_):
            Sg_, rhs_, Hinv_ = _schur(Hgg, bg, Haa, Hga, ba, lam_)
            dg_ = -_solve(Sg_, rhs_)
            da_ = -np.einsum("nij,nj->ni", Hinv_, ba + np.einsum("ngi,g->ni", Hga, dg_))
            return (dg_, da_), float(np.sqrt(dg_**2 @ Dg2 + np.sum(da_**2 * Da2)))

        while True:
            if radius is None:  # the first step after a (re)linearisation: Gauss-Newton, its length the radius
                (dg, da), length = solve(0.0)
                radius, lam = length, 0.0
            else:
                (dg, da), length, lam = damped_step(solve, radius, lam)
            big = np.max(np.abs(dg[12:]), initial=0.0) / _THETA_TRUST
            if big > 1.0:  # theta's trust region: far outside its prior h is not near-linear
                dg, da, length = dg / big, da / big, length / big
            Hd_g = Hgg @ dg + np.einsum("ngi,ni->g", Hga, da)  # H d, block by block
            Hd_a = np.einsum("ngi,g->ni", Hga, dg) + np.einsum("nij,nj->ni", Haa, da)
            pred = predicted_decrease(np.r_[bg, ba.ravel()], np.r_[dg, da.ravel()], np.r_[Hd_g, Hd_a.ravel()])
            Xn, Zn = X @ pose_to_matrix(dg[:6]), Z @ pose_to_matrix(dg[6:12])
            thn, an = theta + dg[12:], a + da
            rn, litn, Bn, xn, uvn, zmn = pb.residuals(Xn, Zn, thn, an, uv0=uv)
            dropped = False
            if not litn.all() and litn.sum() >= 3 and (pb.cost(rn[litn], an[litn], thn)
                                                        <= pb.cost(r[litn], a[litn], theta)):
                # a step that descends on the poses it keeps lit but darkens others: those sit at
                # the pupil's edge, and kept they would block every step (the fit stalled there);
                # they leave the problem (``used``)
                keep = litn
                used[np.flatnonzero(used)[~keep]] = False
                pb.drop(keep)
                rn, an, Bn, xn, uvn, zmn = rn[keep], an[keep], Bn[keep], xn[keep], uvn[keep], zmn[keep]
                r, a, B, x, uv, zm = r[keep], a[keep], B[keep], x[keep], uv[keep], zm[keep]
                S, Jt = S[keep], Jt[keep]
                n = int(keep.sum())
                dof = n * pb.m - 12 - (0 if theta_prior else k)
                cost, litn = pb.cost(r, a, theta), np.ones(n, bool)
                fresh, prev_dec, dropped = False, np.inf, True
                passes = WindowPasses(_WINDOW_PASSES - passes.passes)  # its states had the dropped poses
            cn = pb.cost(rn, an, thn) if litn.all() else np.inf
            acc = cn <= cost
            # the shared step policy (trust_region); after dropping poses the model's prediction
            # was for the larger problem, so the radius stays
            rho = 0.5 if dropped else float(gain_ratio(cost - cn, pred))
            radius = float(next_radius(radius, length, rho, acc))
            if acc:
                accepted = True
                X, Z, theta, a, r, B, x, uv, zm = Xn, Zn, thn, an, rn, Bn, xn, uvn, zmn
                cost = cn
                break
            if radius <= _MIN_RADIUS or dropped:  # dropped: the normal equations are the larger problem's
                break
        if not accepted:
            if not fresh or moved_windows():  # the iteration Jacobians limit the descent: relinearise here and go on
                (S, Jt), fresh = pb.jacobians(theta, x, uv), True
                prev_dec, radius = np.inf, None
                continue
            converged = True  # no descent left with exact Jacobians: a minimum (to the residuals' accuracy)
            break
        # fresh Jacobians stay the covariance's over a step shorter than _FRESH_STEP sigma
        # (dh/dtheta changes by ~1 % per prior sigma of theta, dh/dx far less)
        fresh = fresh and dec < _FRESH_STEP ** 2 * scale
        if not fresh and dec > refresh_ratio ** 2 * prev_dec:  # slow contraction: the Jacobians are stale
            # on a cross-talk bench the iteration Jacobians leave out the cross-talk's derivative: fresh ones
            # there at the same point would repeat the same stalled steps (seen: a physical session cycling at
            # chi2 398 until max_iter), so the refresh is exact
            xt = pb.model(theta).crosstalk
            (S, Jt), fresh = pb.jacobians(theta, x, uv, exact=xt), xt
            prev_dec, radius = np.inf, None  # a new linearisation starts with its Gauss-Newton step
        else:
            prev_dec = dec
    if not fresh:  # max_iter reached: the covariance needs Jacobians at the estimate
        (S, Jt), fresh = pb.jacobians(theta, x, uv), True
    # covariance at the estimate, fresh Jacobians
    info = joint_information(S, B, x, X, Jt, pb.robot_cov, theta_prior)
    cov = _inv(info)
    crlb_known = _inv(info[:12, :12])[6:12, 6:12]  # theta known: the (X, Z) block alone
    return JointCalibrationResult(
        X=X, Z=Z, theta=theta, robot_errors=a, cov=cov, crlb_Z_known_lens=crlb_known, chi2=cost, dof=dof,
        p_value=float(chdtrc(dof, cost)), alpha=alpha, iterations=it, converged=converged,
        n_traced=pb.n_traced, parameterisation=param, used=used, gain_sigma=gain_sigma)


def simulate_joint_data(bench, param: LensParameterisation, theta, A_true, X, Z, T_SO_nominal, rng=None):
    """Zernike data (n, m) of the as-built lens of theta at the lens poses of the chain
    Z^-1 A_true X (noise added when an rng is given); raises if a pose is unlit."""
    _, x = pose_chain(A_true, X, Z, np.zeros((len(A_true), 6)), T_SO_nominal)
    model = ForwardModel(bench, param.build(theta), validate=False)
    res = model.evaluate(x, check_range=False)
    if not res.valid.all():
        raise CalibrationError(f"simulated data: poses {np.flatnonzero(~res.valid).tolist()} leave the pupil unlit")
    return res.z if rng is None else model.add_noise(res, rng)
