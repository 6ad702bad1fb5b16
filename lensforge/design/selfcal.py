"""The self-calibration criterion: how well a printed lens lets the robot calibrate the sensor.

The single-pose criteria (A, D, J) judge a lens by its pose Cramer-Rao bound. A lens that is
printed deviates from its design (``asbuilt.tolerances``), and the joint calibration
(``calibration.joint``) estimates those deviations theta beside the grasp X and the sensor
pose Z. The criterion ``DS`` here is the Ds-criterion of Z for that problem over a
calibration plan: log det Cov(Z), Cov the inverse of the joint Fisher information
(``asbuilt.joint_information``: robot pose errors eliminated, theta a nuisance with the
tolerance model's N(0, I) prior) summed over the plan's lens poses. Lower is better; a lens
and bench that separate lens form from sensor pose bring it close to the lens-known value.

theta here is the tolerance model's whole elementary space (``asbuilt.lens_params.lens_space``:
every deviation it draws, prior-scaled), i.e. the Bayesian bound with the full prior; the
calibration's own theta keeps the directions visible in the data, which changes the bound
on Z only by what the dropped directions (below 0.1 noise sigma each) could move.

The scene: the information does not depend on where the sensor stands in the robot's world
(Z enters only through the lens pose in {S}); it depends on the grasp X and the robot's
repeatability. Defaults match the calibration's default scene (``calibration.robot``; the
tests check they agree): the lens 150 mm along the tool z axis with its optical axis along
tool x (ASSUMPTION there) and the KR 10's +-0.02 mm repeatability (ISO 9283, RP / sigma =
3.616, rotation over an assumed 500 mm lever).

``plan_for`` chooses the plan for a lens (Ds-optimal, greedy + exchanges, from lit candidates
of the plan box), so a design can alternate lens steps and plan steps (``optimize_design``
with criterion DS).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from ..asbuilt.joint_information import pose_information, select_ds, theta_prior, z_ds, z_sigma
from ..asbuilt.lens_params import lens_space, lens_tangents
from ..optics.bench import Bench
from ..optics.lens import Lens
from ..optics.pose import pose_to_matrix
from ..optics.shack_hartmann import ForwardModel
from .constraints import PLAN_BOX_DEG, PLAN_BOX_MM

__all__ = ["SelfCalSpec", "default_grasp", "joint_information", "selfcal_value", "plan_for", "plan_candidates"]

# ISO 9283 RP / sigma = 2 sqrt(2/pi) + 3 sqrt(3 - 8/pi) = 3.616, rounded as calibration.robot.RobotNoise's default
_RP_TO_SIGMA = 3.616


def default_grasp() -> np.ndarray:
    """^E T_O of the calibration's default scene: lens 150 mm along tool z, optical axis along tool x."""
    X = np.eye(4)
    X[:3, :3] = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]
    X[:3, 3] = [0.0, 0.0, 150.0]
    return X


@dataclass(frozen=True, eq=False)
class SelfCalSpec:
    """tolerances (``asbuilt.tolerances.Tolerances``); poses (n, 6) the plan's lens poses about
    nominal (mm, rad; None: chosen by ``plan_for``); n_poses; grasp X (4, 4); robot
    repeatability_mm and lever_mm (the robot-noise model); plan box plan_mm / plan_rad and
    n_candidates random candidates (plus the box's 64 corners)."""

    tolerances: object
    poses: np.ndarray | None = None
    n_poses: int = 24
    grasp: np.ndarray = field(default_factory=default_grasp)
    repeatability_mm: float = 0.02
    lever_mm: float = 500.0
    plan_mm: float = PLAN_BOX_MM
    plan_rad: float = math.radians(PLAN_BOX_DEG)
    n_candidates: int = 60
    seed: int = 0

    @property
    def robot_cov(self) -> np.ndarray:
        t = self.repeatability_mm / _RP_TO_SIGMA
        return np.diag([t * t] * 3 + [(t / self.lever_mm) ** 2] * 3)

    def with_poses(self, poses) -> "SelfCalSpec":
        import dataclasses

        return dataclasses.replace(self, poses=np.atleast_2d(np.asarray(poses, dtype=float)).copy())


def joint_information(bench: Bench, lens: Lens, spec: SelfCalSpec, poses=None):
    """(I (n, G, G) per pose, lit (n,)) of the joint problem at lens poses (default spec.poses),
    theta = the tolerance model's prior-scaled elementary deviations; unlit poses give 0."""
    x = np.atleast_2d(np.asarray(spec.poses if poses is None else poses, dtype=float))
    space = lens_space(lens, spec.tolerances)
    mean_lens = space.build(space.mean)
    model = ForwardModel(bench, mean_lens, validate=False)
    res = model.evaluate(x, check_range=False)
    lt = lens_tangents(space.build, space.mean, np.diag(space.sigma), bench.laser.wavelength_nm)
    J, Jt, _ = model.jacobians(x, uv0=res.uv, lens_tangents=lt)
    L = model.whitener
    S = np.einsum("ij,njp->nip", L, J)
    Jt = np.einsum("ij,njp->nip", L, Jt)
    Tn = np.eye(4)
    Tn[2, 3] = -bench.placement.distance_mm
    I = pose_information(S, Jt, Tn @ pose_to_matrix(x), x, spec.grasp, spec.robot_cov)
    I[~res.valid] = 0.0
    return I, res.valid


def selfcal_value(bench: Bench, lens: Lens, spec: SelfCalSpec) -> tuple[float, dict]:
    """(DS criterion: log det Cov(Z) in (mm, rad)^6 units, the z_sigma summary with n_lit)."""
    I, lit = joint_information(bench, lens, spec)
    k = I.shape[1] - 12
    F = I.sum(axis=0) + theta_prior(k)
    value = float(-z_ds(F))
    summary = {k_: v for k_, v in z_sigma(F).items() if k_ != "cov"}
    return value, {**summary, "n_lit": int(lit.sum())}


def plan_candidates(spec: SelfCalSpec) -> np.ndarray:
    """The plan box's 64 corners and n_candidates uniform poses (seeded)."""
    span = np.array([spec.plan_mm] * 3 + [spec.plan_rad] * 3)
    corners = np.array(list(itertools.product((-1.0, 1.0), repeat=6))) * span
    rng = np.random.default_rng(spec.seed)
    return np.concatenate([corners, rng.uniform(-1.0, 1.0, (spec.n_candidates, 6)) * span])


def plan_for(bench: Bench, lens: Lens, spec: SelfCalSpec, candidates=None) -> np.ndarray:
    """Ds-optimal n_poses lens poses (n, 6) for this lens and bench among the lit candidates."""
    cand = plan_candidates(spec) if candidates is None else np.atleast_2d(candidates)
    I, lit = joint_information(bench, lens, spec, cand)
    idx = np.flatnonzero(lit)
    if idx.size == 0:
        return np.zeros((1, 6))
    chosen, _, _, _ = select_ds(I[idx], I.shape[1] - 12, spec.n_poses)
    return cand[idx[chosen]]
