"""Robot pose model for the hand-eye simulation: KUKA KR 10 R1100 sixx (KR AGILUS).

Kinematics: the joint chain of ROS-Industrial kuka_experimental,
kuka_kr10_support/urdf/kr10r1100sixx_macro.xacro: joint origins (mm) A1 (0, 0, 400),
A2 (25, 0, 0), A3 (560, 0, 0), A4 (0, 0, 35), A5 (515, 0, 0), A6 (80, 0, 0); axes
A1 -z, A2 +y, A3 +y, A4 -x, A5 +y, A6 -x; joint limits (deg) A1 +-170, A2 -190..45,
A3 -120..156, A4 +-185, A5 +-120, A6 +-350 (same file; they match KUKA's KR AGILUS
sixx data sheet). {W} = base_link; {E} = tool0 = flange rotated by +90 deg about y
(KUKA $TOOL convention: z out of the flange), as in that file.

Noise: repeatability +-0.02 mm (KUKA KR AGILUS sixx data sheet, ISO 9283). ISO 9283
defines RP = mean(l) + 3 std(l), l the distance of the attained positions from their
barycentre. ASSUMPTION: isotropic Gaussian flange translation noise with per-axis
sigma s; then l is Maxwell distributed, mean(l) = 2 s sqrt(2/pi), std(l) =
s sqrt(3 - 8/pi), so RP = 3.616 s and s = 0.02 / 3.616 = 5.5 um. KUKA quotes no
orientation repeatability. ASSUMPTION: rotation sigma = s / 500 mm (joint jitter
seen through a ~0.5 m lever, about half the reach) = 1.1e-5 rad per axis.

Scene (the paper's simulation, Optics Express 30(9) 14368, Eq. 21): Z = ^W T_S with
rotation [[0,0,-1],[0,1,0],[1,0,0]] and translation (0, -500, 1000) mm. The grasp
X = ^E T_O is an ASSUMPTION (the paper gives none): the lens 150 mm below the flange
along tool z, its optical axis along tool x, so that the tool points straight down
at the nominal lens placement. Nominal lens placement: {O} at z = -d in {S} (d =
bench.placement.distance_mm, 20 mm by default), DESIGN.md.

Reachability: checked by numerical inverse kinematics (scipy least_squares on the
joint angles, bounded by the joint limits, from several seeds); a pose counts as
reachable when the flange pose is attained within 1e-6 mm / 1e-9 rad. Self-collision
and cabling are not modelled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ..errors import ConfigError, PoseRangeError
from ..optics.pose import invert_poses, matrix_to_pose, pose_to_matrix

__all__ = [
    "RobotModel",
    "RobotNoise",
    "Scene",
    "CalibrationData",
    "kr10_r1100_sixx",
    "forward_kinematics",
    "inverse_kinematics",
    "paper_scene",
    "lens_pose_matrix",
    "flange_pose",
    "random_lens_poses",
    "simulate_calibration",
    "PAPER_Z",
]

# Paper Eq. (21): the sensor in the robot base (rounded to whole numbers by the authors)
PAPER_Z = np.array([[0.0, 0.0, -1.0, 0.0],
                    [0.0, 1.0, 0.0, -500.0],
                    [1.0, 0.0, 0.0, 1000.0],
                    [0.0, 0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class RobotModel:
    """A serial 6R chain in URDF form: joint i = Trans(origin_i) Rot(axis_i, q_i).

    origins_mm: (6, 3); axes: (6, 3) unit vectors; limits_rad: (6, 2) lower/upper;
    tool: 4x4 fixed transform from the last link to {E}."""

    name: str
    origins_mm: tuple
    axes: tuple
    limits_rad: tuple
    tool: tuple
    reach_mm: float


def kr10_r1100_sixx() -> RobotModel:
    """KUKA KR 10 R1100 sixx (ROS-Industrial kuka_experimental URDF values, mm/rad)."""
    d = math.radians
    tool = np.eye(4)
    tool[:3, :3] = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]  # Ry(+90 deg)
    return RobotModel(
        name="KUKA KR 10 R1100 sixx",
        origins_mm=((0.0, 0.0, 400.0), (25.0, 0.0, 0.0), (560.0, 0.0, 0.0),
                    (0.0, 0.0, 35.0), (515.0, 0.0, 0.0), (80.0, 0.0, 0.0)),
        axes=((0.0, 0.0, -1.0), (0.0, 1.0, 0.0), (0.0, 1.0, 0.0),
              (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0)),
        limits_rad=((d(-170), d(170)), (d(-190), d(45)), (d(-120), d(156)),
                    (d(-185), d(185)), (d(-120), d(120)), (d(-350), d(350))),
        tool=tuple(map(tuple, tool)),
        reach_mm=1101.0,  # KUKA data sheet: max. reach 1101 mm
    )


def _axis_rot(axis: np.ndarray, q: np.ndarray) -> np.ndarray:
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    s, c = np.sin(q)[..., None, None], np.cos(q)[..., None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def forward_kinematics(q, robot: RobotModel | None = None) -> np.ndarray:
    """^W T_E (..., 4, 4) in mm for joint angles q (..., 6) in rad."""
    robot = robot or kr10_r1100_sixx()
    q = np.asarray(q, dtype=float)
    T = np.broadcast_to(np.eye(4), q.shape[:-1] + (4, 4)).copy()
    for i in range(6):
        J = np.zeros(q.shape[:-1] + (4, 4))
        J[..., :3, :3] = _axis_rot(np.asarray(robot.axes[i]), q[..., i])
        J[..., :3, 3] = robot.origins_mm[i]
        J[..., 3, 3] = 1.0
        T = T @ J
    return T @ np.asarray(robot.tool)


def _ik_residual(q, T_goal, robot):
    T = forward_kinematics(q, robot)
    e = matrix_to_pose(invert_poses(T_goal) @ T)
    return np.concatenate([e[:3], 1000.0 * e[3:]])  # rad weighted as mm at 1 m


_SEEDS_DEG = ((0, -90, 90, 0, 0, 0), (-45, -90, 90, 0, 45, 0), (-90, -90, 90, 0, 45, 0),
              (-60, -60, 60, 0, 60, 0), (45, -90, 90, 0, 45, 0), (-90, -45, 45, 0, 90, 0))


def inverse_kinematics(T, robot: RobotModel | None = None, q0=None, tol_mm: float = 1e-6) -> np.ndarray:
    """Joint angles q (6,) rad that reach flange pose T = ^W T_E (4x4, mm) within the
    joint limits; numerical (bounded least squares) from q0 and built-in seeds.
    Raises PoseRangeError when no seed converges (unreachable or outside the limits)."""
    robot = robot or kr10_r1100_sixx()
    T = np.asarray(T, dtype=float)
    lim = np.asarray(robot.limits_rad)
    wrist = T[:3, 3] - T[:3, :3] @ np.array([0.0, 0.0, robot.origins_mm[5][0]])
    shoulder_dist = np.linalg.norm(wrist - np.array([0.0, 0.0, robot.origins_mm[0][2]]))
    arm = robot.origins_mm[2][0] + math.hypot(robot.origins_mm[3][2], robot.origins_mm[4][0])
    if shoulder_dist > arm + abs(robot.origins_mm[1][0]) + 1e-9:
        raise PoseRangeError(
            f"flange pose: wrist centre {shoulder_dist:.0f} mm from the shoulder exceeds the arm's "
            f"{arm + robot.origins_mm[1][0]:.0f} mm; move the scene (Z) or the grasp (X) closer to the robot"
        )
    seeds = ([np.asarray(q0, dtype=float)] if q0 is not None else []) + [np.radians(s) for s in _SEEDS_DEG]
    best = None
    for s in seeds:
        s = np.clip(s, lim[:, 0] + 1e-9, lim[:, 1] - 1e-9)
        sol = least_squares(_ik_residual, s, args=(T, robot), bounds=(lim[:, 0], lim[:, 1]),
                            xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=200)
        err = np.abs(sol.fun).max()
        if best is None or err < best[0]:
            best = (err, sol.x)
        if err < tol_mm:
            return sol.x
    raise PoseRangeError(
        f"flange pose: not reachable within the KR 10 joint limits (best IK error {best[0]:.3g} mm); "
        "choose lens poses closer to nominal or another grasp X"
    )


@dataclass(frozen=True)
class RobotNoise:
    """Flange pose noise: A_measured = A_true P(a), a ~ N(0, diag(t^2 I3, r^2 I3)).

    translation_mm: per-axis sigma (default from the +-0.02 mm ISO 9283 repeatability,
    see the module docstring); rotation_rad: per-axis sigma (ASSUMPTION, module doc)."""

    translation_mm: float = 0.02 / 3.616
    rotation_rad: float = 0.02 / 3.616 / 500.0

    @classmethod
    def from_repeatability(cls, rp_mm: float = 0.02, lever_mm: float = 500.0) -> "RobotNoise":
        """Sigmas from an ISO 9283 repeatability RP (mm) and an assumed lever (mm)."""
        if rp_mm < 0 or lever_mm <= 0:
            raise ConfigError("robot noise: rp_mm must be >= 0 and lever_mm > 0")
        k = 2 * math.sqrt(2 / math.pi) + 3 * math.sqrt(3 - 8 / math.pi)  # RP / sigma = 3.616
        return cls(rp_mm / k, rp_mm / k / lever_mm)

    @property
    def cov(self) -> np.ndarray:
        """6x6 covariance in (mm, rad)^2, right perturbation of ^W T_E."""
        return np.diag([self.translation_mm**2] * 3 + [self.rotation_rad**2] * 3)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n perturbation vectors (n, 6)."""
        s = np.array([self.translation_mm] * 3 + [self.rotation_rad] * 3)
        return rng.standard_normal((n, 6)) * s


def _default_X() -> np.ndarray:
    # ASSUMPTION (module doc): lens 150 mm along tool z, optical axis along tool x
    X = np.eye(4)
    X[:3, :3] = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]
    X[:3, 3] = [0.0, 0.0, 150.0]
    return X


@dataclass(frozen=True)
class Scene:
    """The simulated cell: Z = ^W T_S, X = ^E T_O (4x4, mm), nominal lens distance
    distance_mm ({O} at z = -distance_mm in {S}), robot model and noise."""

    Z: np.ndarray = field(default_factory=lambda: PAPER_Z.copy())
    X: np.ndarray = field(default_factory=_default_X)
    distance_mm: float = 20.0
    robot: RobotModel = field(default_factory=kr10_r1100_sixx)
    noise: RobotNoise = field(default_factory=RobotNoise)

    @property
    def T_SO_nominal(self) -> np.ndarray:
        T = np.eye(4)
        T[2, 3] = -self.distance_mm
        return T


def paper_scene(distance_mm: float = 20.0, noise: RobotNoise | None = None) -> Scene:
    """The paper's default scene (Z of Eq. 21), the assumed grasp and KR 10 noise.
    Pass bench.placement.distance_mm as distance_mm to match a bench."""
    return Scene(distance_mm=float(distance_mm), noise=noise or RobotNoise())


def lens_pose_matrix(scene: Scene, x) -> np.ndarray:
    """B = ^S T_O = T_SO(nominal) P(x) for pose vector(s) x (..., 6) (mm, rad)."""
    return scene.T_SO_nominal @ pose_to_matrix(x)


def flange_pose(scene: Scene, x, check_reach: bool = True) -> np.ndarray:
    """Commanded flange pose(s) A = Z B X^-1 (..., 4, 4) that put the lens at pose x
    (..., 6) relative to nominal. check_reach: run inverse kinematics on each and
    raise PoseRangeError if one is unreachable."""
    B = lens_pose_matrix(scene, x)
    A = scene.Z @ B @ invert_poses(scene.X)
    if check_reach:
        q = None
        for T in A.reshape(-1, 4, 4):
            q = inverse_kinematics(T, scene.robot, q0=q)
    return A


def random_lens_poses(rng: np.random.Generator, n: int, translation_mm: float = 1.0,
                      rotation_rad: float = math.radians(1.0)) -> np.ndarray:
    """n pose vectors (n, 6) uniform in the box +-translation_mm, +-rotation_rad
    (rotation-vector components) about nominal. Defaults: +-1 mm, +-1 deg, the range
    where the Shack-Hartmann pupil stays lit (ASSUMPTION, see bench.PoseLimits)."""
    if n < 1 or translation_mm < 0 or rotation_rad < 0:
        raise ConfigError("calibration poses: n >= 1 and non-negative ranges required")
    return np.concatenate([rng.uniform(-translation_mm, translation_mm, (n, 3)),
                           rng.uniform(-rotation_rad, rotation_rad, (n, 3))], axis=1)


@dataclass(frozen=True)
class CalibrationData:
    """Simulated calibration run: A (n,4,4) recorded flange poses, B (n,4,4) estimated
    lens poses, A_true/B_true the actual ones, x (n,6) the commanded lens poses."""

    A: np.ndarray
    B: np.ndarray
    A_true: np.ndarray
    B_true: np.ndarray
    x: np.ndarray


def simulate_calibration(scene: Scene, x, rng: np.random.Generator, cov_B=None,
                         check_reach: bool = True) -> CalibrationData:
    """Drive the robot to the lens poses x (n, 6): record commanded A, the flange
    actually lands at A P(a) (a ~ scene.noise), the lens sits at B_true = Z^-1 A_true X,
    and the estimator reports B = B_true P(b), b ~ N(0, cov_B) (6x6 or (n,6,6) in
    (mm, rad)^2; None = exact lens poses)."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    n = x.shape[0]
    A_cmd = flange_pose(scene, x, check_reach=check_reach)
    A_true = A_cmd @ pose_to_matrix(scene.noise.sample(rng, n))
    B_true = invert_poses(scene.Z) @ A_true @ scene.X
    if cov_B is None:
        B = B_true.copy()
    else:
        C = np.broadcast_to(np.asarray(cov_B, dtype=float), (n, 6, 6))
        L = np.linalg.cholesky(C)
        b = np.einsum("nij,nj->ni", L, rng.standard_normal((n, 6)))
        B = B_true @ pose_to_matrix(b)
    return CalibrationData(A=A_cmd, B=B, A_true=A_true, B_true=B_true, x=x)
