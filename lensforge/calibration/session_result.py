"""What a bench-session calibration takes and returns: SessionData (the matched
inputs every method gets), CalibrationResult (the stable JSON, summary, YAML and
residual plot) and frame_dict (a calibrated frame's JSON block). Shared by the
methods of ``session`` (two-stage) and ``session_joint`` (joint as-built).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2 as chi2_dist

from ..optics.shack_hartmann import ForwardModel
from . import formats
from .model_check import ModelCheck, check_chi2
from .robot import RobotModel, Scene

__all__ = ["CalibrationResult", "SessionData", "frame_dict", "std_dict", "robust_chi2_threshold", "OUTLIER_ALPHA",
           "SCHEMA_VERSION"]

SCHEMA_VERSION = 1

# ----------------------------------------------------------------------------- frames for output


STD_KEYS = ("tx_mm", "ty_mm", "tz_mm", "rx_deg", "ry_deg", "rz_deg")


def std_dict(sigma) -> dict:
    """{tx_mm, ty_mm, tz_mm, rx_deg, ry_deg, rz_deg} of a (6,) 1-sigma in (mm, rad);
    a non-finite entry (unobservable) is None."""
    scale = (1.0, 1.0, 1.0, 180.0 / math.pi, 180.0 / math.pi, 180.0 / math.pi)
    return {n: (float(s * k) if np.isfinite(s) else None) for n, s, k in zip(STD_KEYS, sigma, scale)}


def frame_dict(T: np.ndarray, cov_right: np.ndarray) -> dict:
    """JSON block of a calibrated frame: matrix (4x4, mm), xyzabc (mm, deg, KUKA),
    quaternion_wxyz, std {tx_mm, ty_mm, tz_mm, rx_deg, ry_deg, rz_deg} and cov (6x6).

    std and cov are of the translation error t_est - t_true (mm) and the rotation-error
    vector of R_est R_true^T (rad; std in deg), both in the parent frame: the solver's
    right-perturbation covariance rotated by R. Unobservable directions: std null,
    cov entries null."""
    T = np.asarray(T, dtype=float)
    R = T[:3, :3]
    M = np.zeros((6, 6))
    M[:3, :3] = R
    M[3:, 3:] = R
    with np.errstate(invalid="ignore"):
        cov_fin = np.where(np.isfinite(cov_right), cov_right, 0.0)
        cov = M @ cov_fin @ M.T
    bad_dof = ~np.isfinite(np.diag(cov_right))
    if bad_dof.any():  # an infinite right-frame variance spreads to every parent axis it touches
        touched = (np.abs(M[:, bad_dof]) > 1e-9).any(axis=1)
        cov[touched, :] = np.nan
        cov[:, touched] = np.nan
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return {
        "matrix": T.tolist(),
        "xyzabc": formats.matrix_to_xyzabc(T).tolist(),
        "quaternion_wxyz": formats.matrix_to_quaternion(T).tolist(),
        "std": std_dict(std),
        "cov": [[(float(v) if np.isfinite(v) else None) for v in row] for row in cov],
    }



# ----------------------------------------------------------------------------- calibrate


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """X = ^E T_O and Z = ^W T_S from a bench session.

    handeye: the final HandEyeResult (cov_X, cov_Z right perturbations, see handeye);
    poses_used: ids in the solve; poses_rejected: [{"pose", "reason"}]; per_pose:
    [{"pose", "handeye_chi2", "estimate_chi2_dof", "outlier"}] of every estimated pose;
    p_value: of the chi2 model check; warnings; method; robot; bench (as measured).

    model_check / valid / check_failure: the verdict of ``model_check.check_chi2`` on
    (chi2, dof): a result that fails it (valid False) is not a calibration; its files()
    hold the diagnostics but no easy_handeye.yaml."""

    X: np.ndarray
    Z: np.ndarray
    handeye: object
    poses_used: tuple
    poses_rejected: tuple
    per_pose: tuple
    chi2: float
    dof: int
    chi2_dof: float
    p_value: float
    method: str
    robot: str
    warnings: tuple = field(default=())
    outlier_threshold: float = float("nan")
    extra: dict = field(default_factory=dict)
    estimates: tuple = field(default=())  # two-stage: (id, lens pose (6,), cov (6, 6)) of each used pose

    @property
    def model_check(self) -> ModelCheck:
        """The chi2 model check of the final fit (``model_check.check_chi2``)."""
        return check_chi2(self.chi2, self.dof, what=f"{self.method} calibration")

    @property
    def valid(self) -> bool:
        """False when the fit fails its model check: then it is not a calibration."""
        return self.model_check.passed

    @property
    def check_failure(self) -> str | None:
        """Why the model check failed (None when it passed)."""
        mc = self.model_check
        return None if mc.passed else mc.reason

    def to_json(self) -> dict:
        """The stable --json keys: schema_version, valid, check_failure, Z, X, chi2_dof,
        poses_used, poses_rejected, method, and the method's own keys (``extra``; joint:
        tolerances, p_value, lens_parameters, ...; diagnosis: the likely mistake after a
        failed check)."""
        return {
            "schema_version": SCHEMA_VERSION,
            "valid": self.valid,
            "check_failure": self.check_failure,
            "Z": frame_dict(self.Z, self.handeye.cov_Z),
            "X": frame_dict(self.X, self.handeye.cov_X),
            "chi2_dof": float(self.chi2_dof),
            "poses_used": list(self.poses_used),
            "poses_rejected": list(self.poses_rejected),
            "method": self.method,
            **self.extra,
        }

    def to_dict(self) -> dict:
        """The full result file: to_json() plus the model check and per-pose table."""
        return {**self.to_json(), "kind": "calibration_result", "method": self.method, "robot": self.robot,
                "chi2": float(self.chi2), "dof": int(self.dof), "p_value": float(self.p_value),
                "outlier_threshold_chi2": (float(self.outlier_threshold) if np.isfinite(self.outlier_threshold)
                                          else None),
                "observable": bool(self.handeye.observable),
                "null_directions": list(self.handeye.null_directions),
                "model_check": self.model_check.to_dict(),
                "per_pose": list(self.per_pose), "warnings": list(self.warnings),
                "std_convention": "translation error and rotation-error vector of R_est R_true^T, parent frame "
                                  "(Z: robot base {W}; X: flange {E}); cov (mm, rad)^2"}

    def summary(self) -> str:
        """Human summary (the numbers of to_dict())."""
        d = self.to_json()
        lines = [f"lensforge calibration ({self.method}, {self.robot}): {len(self.poses_used)} poses used, "
                 f"{len(self.poses_rejected)} rejected",
                 f"chi2/dof = {self.chi2_dof:.3g} (dof {self.dof}, p = {self.p_value:.3g})"]
        if not self.valid:
            lines.insert(0, f"NOT A CALIBRATION: {self.check_failure}; no easy_handeye.yaml is written")
            dx = self.extra.get("diagnosis")
            if dx:
                lines.insert(1, f"likely mistake: {dx['message']}")
        lp = self.extra.get("lens_parameters")
        if lp is not None:
            lines.append(f"as-built lens: {len(lp['theta'])} parameters from {self.extra['tolerances']}, "
                         f"{lp['n_identifiable']} identified by the data (1-sigma < half the prior)")
        sp = self.extra.get("sensor")
        if sp is not None:
            lines.append(f"sensor: effective lenslet focal length {sp['lenslet_focal_mm']:.4f} +- "
                         f"{sp['lenslet_focal_std_mm']:.4f} mm (prior {sp['prior_lenslet_focal_mm']:.4f} +- "
                         f"{sp['prior_std_mm']:.4f} mm" + ("" if sp["identifiable"] else "; not identified by the data")
                         + ")")
        for name, frame in (("Z = ^W T_S (sensor in the robot base)", "Z"), ("X = ^E T_O (lens in the flange)", "X")):
            f = d[frame]
            s = f["std"]

            def fmt(v, k=1.0, nd=4):
                return "n/a (unobservable)" if v is None else f"{v * k:.{nd}g}"
            lines += [name,
                      "  X Y Z (mm):  " + "  ".join(f"{v:.4f}" for v in f["xyzabc"][:3]),
                      "  A B C (deg): " + "  ".join(f"{v:.5f}" for v in f["xyzabc"][3:]),
                      "  quaternion (w x y z): " + "  ".join(f"{v:.8f}" for v in f["quaternion_wxyz"]),
                      f"  1-sigma translation (um): {fmt(s['tx_mm'], 1e3)} {fmt(s['ty_mm'], 1e3)} {fmt(s['tz_mm'], 1e3)}",
                      f"  1-sigma rotation (mdeg):  {fmt(s['rx_deg'], 1e3)} {fmt(s['ry_deg'], 1e3)} {fmt(s['rz_deg'], 1e3)}"]
        for r in self.poses_rejected:
            lines.append(f"rejected pose {r['pose']}: {r['reason']}")
        for w in self.warnings:
            lines.append(f"warning: {w}")
        return "\n".join(lines) + "\n"

    def residual_plot(self) -> bytes:
        """PNG, per pose: two-stage: the hand-eye residual chi2 (6 DOF) and the lens-pose
        fit chi2/dof; joint: the robot pose error chi2 a^T Sigma_A^-1 a (6 DOF) and the
        whitened Zernike residual chi2 / m; each with its expectation and the outlier
        threshold; outliers in red, poses left out named below."""
        from ..plots.calibration import plot_calibration_residuals
        from ..plots.figure import png_bytes

        return png_bytes(plot_calibration_residuals(self))

    def files(self, accept_failed_check: bool = False) -> dict:
        """{file name: text | bytes}: calibration.json, easy_handeye.yaml, the ROS 2 launch file
        (``ros2.static_transform_launch``: Z and X), summary.txt, residuals.png; without the two
        files a robot cell would load (easy_handeye.yaml, the launch file) when the model check
        failed (unless ``accept_failed_check``, for research: the JSON still says "valid": false)."""
        from .ros2 import LAUNCH_FILE_NAME, static_transform_launch

        out = {"calibration.json": formats.dumps_json(self.to_dict()) + "\n"}
        if self.valid or accept_failed_check:
            out["easy_handeye.yaml"] = formats.easy_handeye_yaml(self.Z)
            out[LAUNCH_FILE_NAME] = static_transform_launch(self.Z, self.X)
        out["summary.txt"] = self.summary()
        out["residuals.png"] = self.residual_plot()
        return out


OUTLIER_ALPHA = 1e-3  # family-wise false-alarm rate of the outlier test


def robust_chi2_threshold(chi2_values, dof: int, alpha: float = OUTLIER_ALPHA) -> float:
    """The outlier threshold of every calibration method: the Bonferroni 1 - alpha/n quantile of
    the chi2(dof) law over n values, scaled up by their median over its expectation, so that an
    overall misfit (a lens as built, a noise model too small) does not reject every pose."""
    v = np.asarray(chi2_values, dtype=float)
    scale = max(1.0, float(np.median(v)) / chi2_dist.median(dof)) if v.size else 1.0
    return float(chi2_dist.ppf(1.0 - alpha / max(v.size, 1), dof) * scale)


@dataclass(frozen=True, eq=False)
class SessionData:
    """A bench session's inputs, matched by pose id: what every calibration method gets.

    ids (n,); A: (n, 4, 4) recorded flange poses (mm); z: (n, m) measured Zernikes (um,
    Noll modes model.modes); model: ForwardModel of the design's lens on the bench as
    measured (WFS order, pupil, wavelength); robot; scene: the robot's nominal cell
    (initial guesses; its ``noise`` is the robot's repeatability every method uses);
    rejected: [{"pose", "reason"}] so far (unmatched ids, poses the sensor did not see)."""

    ids: tuple
    A: np.ndarray
    z: np.ndarray
    model: ForwardModel
    robot: RobotModel | None
    scene: Scene
    rejected: tuple = ()
    measurement: object = None  # calibration.measurement.Measurement of z (None: Zernikes; model is its model)

    @property
    def robot_name(self) -> str:
        return self.robot.name if self.robot is not None else self.scene.robot.name
