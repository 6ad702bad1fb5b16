"""Where the lens really is versus where the robot thinks it put it.

The robot commands a lens pose from CAD (the grasp the gripper should achieve and
the nominal sensor placement). The lens actually sits somewhat off: the gripper
grasps it with an error, and the robot reaches the commanded flange pose only to
its repeatability. The estimator starts from the commanded pose (x0) and must
find the true one. This module holds that uncertainty model and draws the pairs.

All values below are ASSUMPTIONS (the paper says only "previously estimated serial
kinematic chain and grasping uncertainties"), chosen as plausible for a custom
parallel gripper on a KUKA KR 10 R1100 sixx:

- grasp error: sigma 0.3 mm per translation axis, 0.5 deg per rotation axis
  (lens seated in V-jaws; dominant term);
- robot repeatability: KUKA quotes +-0.02 mm (ISO 9283); read as 3 sigma ->
  sigma 0.0067 mm per axis at the flange; its rotation part is taken as
  0.02 mm over a 200 mm lever -> 1e-4 rad (3 sigma) -> sigma 3.3e-5 rad.

Both are independent, zero-mean Gaussian in the pose-vector coordinates (mm, rad)
of DESIGN.md; the prior covariance is their sum. Draws that would put the lens
outside the bench's pose range, or (optionally) where the pupil is not lit, are
redrawn, up to ``max_redraws`` times.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError

__all__ = ["InitialPoseModel", "prior_covariance"]


@dataclass(frozen=True)
class InitialPoseModel:
    """Gripper and robot pose uncertainty (1 sigma, per axis; ASSUMPTIONS, see module).

    grasp_translation_mm, grasp_rotation_rad: grasp error;
    robot_translation_mm, robot_rotation_rad: robot repeatability at the lens.
    """

    grasp_translation_mm: float = 0.3
    grasp_rotation_rad: float = math.radians(0.5)
    robot_translation_mm: float = 0.02 / 3.0
    robot_rotation_rad: float = 1e-4 / 3.0

    def __post_init__(self):
        for name in ("grasp_translation_mm", "grasp_rotation_rad", "robot_translation_mm", "robot_rotation_rad"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"initial pose model.{name}: must be a finite number >= 0, got {v!r}")

    @property
    def sigma(self) -> np.ndarray:
        """Per-DOF 1-sigma (mm, mm, mm, rad, rad, rad) of the true pose about the commanded one."""
        t = math.hypot(self.grasp_translation_mm, self.robot_translation_mm)
        r = math.hypot(self.grasp_rotation_rad, self.robot_rotation_rad)
        return np.array([t, t, t, r, r, r])

    def scaled(self, factor: float) -> "InitialPoseModel":
        """All sigmas times ``factor`` (for sweeps of the initial error)."""
        return InitialPoseModel(self.grasp_translation_mm * factor, self.grasp_rotation_rad * factor,
                                self.robot_translation_mm * factor, self.robot_rotation_rad * factor)


def prior_covariance(model: InitialPoseModel | None = None) -> np.ndarray:
    """Prior covariance (6, 6) of the true pose about the commanded pose (mm^2, rad^2)."""
    model = model or InitialPoseModel()
    return np.diag(model.sigma**2)
