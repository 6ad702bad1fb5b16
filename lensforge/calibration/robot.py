"""Robot models (from TOML files, a registry) and the hand-eye scene; default KUKA KR 10 R1100 sixx.

Robots are TOML files (package data in ``calibration/robots/``, or any path given to
``load_robot``): ``kinematics = "urdf"`` with joints {origin_mm, rpy_deg, axis,
limits_deg} or ``kinematics = "dh"`` with standard Denavit-Hartenberg joints {a_mm,
d_mm, alpha_deg, offset_deg, limits_deg}, an optional [tool] {origin_mm, rpy_deg},
reach_mm, repeatability_mm (ISO 9283), repeatability_lever_mm, ik_seeds_deg and a
[cell] {sensor_xyzabc, grasp_xyzabc} (KUKA mm/deg) giving the nominal Z and X used to
plan poses and simulate sessions. Each file cites its sources.

KR 10 kinematics: the joint chain of ROS-Industrial kuka_experimental,
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

from pathlib import Path

from scipy.spatial.transform import Rotation

from ..errors import ConfigError, PoseRangeError
from .plausibility import check_repeatability
from ..fileio import read_toml
from ..optics.pose import invert_poses, matrix_to_pose, pose_to_matrix
from .formats import xyzabc_to_matrix

__all__ = [
    "RobotModel",
    "RobotNoise",
    "Scene",
    "CalibrationData",
    "kr10_r1100_sixx",
    "load_robot",
    "ROBOTS",
    "robot_scene",
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
    """A serial 6R chain in URDF form: joint i = Trans(origin_i) Rot_i Rot(axis_i, q_i).

    origins_mm: (6, 3); axes: (6, 3) unit vectors; limits_rad: (6, 2) lower/upper;
    tool: 4x4 fixed transform from the last link to {E}; origins_rot: (6, 3, 3) fixed
    joint-origin rotations (None: identity, the KR 10's); repeatability_mm: ISO 9283
    RP; repeatability_lever_mm: lever turning it into a rotation sigma (ASSUMPTION);
    ik_seeds_deg: IK start configurations; cell_Z / cell_X: nominal ^W T_S and ^E T_O
    (4x4 mm) of the robot's cell (None: the paper's cell); source: the TOML file."""

    name: str
    origins_mm: tuple
    axes: tuple
    limits_rad: tuple
    tool: tuple
    reach_mm: float
    origins_rot: tuple | None = None
    repeatability_mm: float = 0.02
    repeatability_lever_mm: float = 500.0
    ik_seeds_deg: tuple = ()
    cell_Z: tuple | None = None
    cell_X: tuple | None = None
    source: str = ""

    @property
    def noise(self) -> "RobotNoise":
        """Flange pose noise from the repeatability (see RobotNoise.from_repeatability)."""
        return RobotNoise.from_repeatability(self.repeatability_mm, self.repeatability_lever_mm)


ROBOTS_DIR = Path(__file__).with_name("robots")
ROBOTS = {p.stem: p for p in sorted(ROBOTS_DIR.glob("*.toml"))}  # name -> TOML file (package data)


def _rot(rpy_deg) -> np.ndarray:
    """URDF rpy (roll, pitch, yaw) in deg -> R = Rz(yaw) Ry(pitch) Rx(roll)."""
    return Rotation.from_euler("xyz", rpy_deg, degrees=True).as_matrix()


def _shown(v) -> str:
    """repr(v), cut to 40 characters (a TOML integer may have 400 digits)."""
    r = repr(v)
    return r if len(r) <= 40 else r[:37] + "..."


def _vec(d: dict, key: str, n: int, where: str, default=None) -> np.ndarray:
    v = d.get(key, default)
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError, OverflowError):
        a = np.zeros(0)
    if v is None or a.shape != (n,) or not np.all(np.isfinite(a)):
        raise ConfigError(f"{where}.{key}: expected {n} finite numbers, got {_shown(v)}")
    return a


def _num(d: dict, key: str, where: str, default=None, positive: bool = True) -> float:
    v = d.get(key, default)
    try:  # an integer beyond the float range (TOML allows 10**400) is no number either
        ok = not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(float(v))
    except OverflowError:
        ok = False
    if not ok or (positive and v <= 0):
        raise ConfigError(f"{where}.{key}: expected a {'positive ' if positive else ''}number, got {_shown(v)}")
    return float(v)


def robot_from_dict(d: dict, where: str = "robot") -> RobotModel:
    """RobotModel of a parsed robot TOML (see the module docstring); ConfigError naming the field."""
    known = {"name", "kinematics", "reach_mm", "repeatability_mm", "repeatability_lever_mm", "ik_seeds_deg",
             "joints", "tool", "cell"}
    extra = set(d) - known
    if extra:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(sorted(extra))}; allowed: {', '.join(sorted(known))}")
    kin = d.get("kinematics")
    if kin not in ("urdf", "dh"):
        raise ConfigError(f"{where}.kinematics: expected \"urdf\" or \"dh\", got {kin!r}")
    joints = d.get("joints")
    if not isinstance(joints, list) or len(joints) != 6 or not all(isinstance(j, dict) for j in joints):
        raise ConfigError(f"{where}.joints: expected six [[joints]] tables")
    origins, rots, axes, limits = [], [], [], []
    fixed = np.eye(4)  # DH: the fixed transform after the previous joint
    for i, j in enumerate(joints):
        w = f"{where}.joints[{i}]"
        lim = _vec(j, "limits_deg", 2, w)
        if not lim[0] < lim[1]:
            raise ConfigError(f"{w}.limits_deg: lower must be below upper, got {lim.tolist()}")
        limits.append(tuple(np.radians(lim)))
        if kin == "urdf":
            origins.append(tuple(_vec(j, "origin_mm", 3, w)))
            rots.append(_rot(_vec(j, "rpy_deg", 3, w, [0.0, 0.0, 0.0])))
            ax = _vec(j, "axis", 3, w)
            if abs(np.linalg.norm(ax) - 1.0) > 1e-9:
                raise ConfigError(f"{w}.axis: must be a unit vector, got {ax.tolist()}")
            axes.append(tuple(ax))
        else:
            # T_i = Rz(theta_i + offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i): joint i rotates about z after the
            # previous joint's fixed part; its own fixed part comes after it
            origins.append(tuple(fixed[:3, 3]))
            rots.append(fixed[:3, :3].copy())
            axes.append((0.0, 0.0, 1.0))
            a, dd = _num(j, "a_mm", w, positive=False), _num(j, "d_mm", w, positive=False)
            al, off = math.radians(_num(j, "alpha_deg", w, positive=False)), \
                math.radians(_num(j, "offset_deg", w, 0.0, positive=False))
            F = np.eye(4)
            F[:3, :3] = Rotation.from_euler("z", off).as_matrix() @ Rotation.from_euler("x", al).as_matrix()
            F[:3, 3] = Rotation.from_euler("z", off).as_matrix() @ np.array([a, 0.0, dd])
            fixed = F
    tool = np.eye(4)
    if kin == "dh":
        tool = fixed.copy()
    t = d.get("tool", {})
    if not isinstance(t, dict):
        raise ConfigError(f"{where}.tool: expected a table")
    T_tool = np.eye(4)
    T_tool[:3, :3] = _rot(_vec(t, "rpy_deg", 3, f"{where}.tool", [0.0, 0.0, 0.0]))
    T_tool[:3, 3] = _vec(t, "origin_mm", 3, f"{where}.tool", [0.0, 0.0, 0.0])
    tool = tool @ T_tool
    seeds = d.get("ik_seeds_deg", [[0, -90, 90, 0, 45, 0]])
    try:
        seeds = tuple(tuple(float(a) for a in s_) for s_ in seeds)
    except (TypeError, ValueError, OverflowError):
        raise ConfigError(f"{where}.ik_seeds_deg: expected a list of 6-number lists") from None
    if not seeds or any(len(s_) != 6 or not all(math.isfinite(a) for a in s_) for s_ in seeds):
        raise ConfigError(f"{where}.ik_seeds_deg: expected a list of 6-number lists")
    cell = d.get("cell", {})
    if not isinstance(cell, dict):
        raise ConfigError(f"{where}.cell: expected a table")
    cZ = xyzabc_to_matrix(_vec(cell, "sensor_xyzabc", 6, f"{where}.cell")) if "sensor_xyzabc" in cell else None
    cX = xyzabc_to_matrix(_vec(cell, "grasp_xyzabc", 6, f"{where}.cell")) if "grasp_xyzabc" in cell else None
    name = d.get("name")
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{where}.name: expected a non-empty string")
    return RobotModel(
        name=name, origins_mm=tuple(origins), axes=tuple(axes), limits_rad=tuple(limits),
        tool=tuple(map(tuple, tool)), reach_mm=_num(d, "reach_mm", where),
        origins_rot=None if all(np.allclose(r, np.eye(3)) for r in rots) else tuple(tuple(map(tuple, r)) for r in rots),
        repeatability_mm=_num(d, "repeatability_mm", where),
        repeatability_lever_mm=_num(d, "repeatability_lever_mm", where, 500.0),
        ik_seeds_deg=seeds,
        cell_Z=None if cZ is None else tuple(map(tuple, cZ)),
        cell_X=None if cX is None else tuple(map(tuple, cX)),
        source=where,
    )


def load_robot(spec: str | Path | None = None) -> RobotModel:
    """A robot model by registry name or TOML file.

    Parameters
    ----------
    spec : str or pathlib.Path, optional
        A ``ROBOTS`` name (kr10_r1100_sixx, ur5e) or a robot TOML path; None: the KR 10.

    Returns
    -------
    RobotModel
        Kinematics (mm, rad), joint limits, repeatability (the robot noise) and the cell's
        nominal placement.

    Raises
    ------
    ConfigError
        An unknown name or a bad file.
    """
    spec = "kr10_r1100_sixx" if spec is None else spec
    key = str(spec)
    if key in ROBOTS:
        path = ROBOTS[key]
    else:
        path = Path(spec)
        if not path.exists():
            raise ConfigError(f"robot: {key!r} is neither a built-in robot ({', '.join(ROBOTS)}) nor an existing "
                              "TOML file")
    robot = robot_from_dict(read_toml(path, "robot file"), where=path.name)
    check_repeatability(robot.repeatability_mm, path.name)  # a robot file's value; simulations may go lower
    return robot


def kr10_r1100_sixx() -> RobotModel:
    """KUKA KR 10 R1100 sixx, read from ``robots/kr10_r1100_sixx.toml`` (mm/rad)."""
    return load_robot("kr10_r1100_sixx")


def _axis_rot(axis: np.ndarray, q: np.ndarray) -> np.ndarray:
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    s, c = np.sin(q)[..., None, None], np.cos(q)[..., None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def forward_kinematics(q, robot: RobotModel | None = None) -> np.ndarray:
    """^W T_E (..., 4, 4) in mm for joint angles q (..., 6) in rad."""
    robot = robot or kr10_r1100_sixx()
    q = np.asarray(q, dtype=float)
    T = np.broadcast_to(np.eye(4), q.shape[:-1] + (4, 4)).copy()
    rots = robot.origins_rot
    for i in range(6):
        J = np.zeros(q.shape[:-1] + (4, 4))
        Rq = _axis_rot(np.asarray(robot.axes[i]), q[..., i])
        J[..., :3, :3] = Rq if rots is None else np.asarray(rots[i]) @ Rq
        J[..., :3, 3] = robot.origins_mm[i]
        J[..., 3, 3] = 1.0
        T = T @ J
    return T @ np.asarray(robot.tool)


def _ik_residual(q, T_goal, robot):
    T = forward_kinematics(q, robot)
    e = matrix_to_pose(invert_poses(T_goal) @ T)
    return np.concatenate([e[:3], 1000.0 * e[3:]])  # rad weighted as mm at 1 m


def inverse_kinematics(T, robot: RobotModel | None = None, q0=None, tol_mm: float = 1e-6) -> np.ndarray:
    """Joint angles q (6,) rad that reach flange pose T = ^W T_E (4x4, mm) within the
    joint limits; numerical (bounded least squares) from q0 and the robot's seeds.
    Raises PoseRangeError when no seed converges (unreachable or outside the limits)."""
    robot = robot or kr10_r1100_sixx()
    T = np.asarray(T, dtype=float)
    lim = np.asarray(robot.limits_rad)
    # necessary condition (triangle inequality): the flange is no farther from the first joint's
    # origin than the sum of the link offsets and the tool
    links = sum(np.linalg.norm(o) for o in robot.origins_mm[1:]) + np.linalg.norm(np.asarray(robot.tool)[:3, 3])
    dist = np.linalg.norm(T[:3, 3] - np.asarray(robot.origins_mm[0]))
    if dist > links + 1e-9:
        raise PoseRangeError(
            f"flange pose: {dist:.0f} mm from the first joint exceeds the {robot.name}'s {links:.0f} mm of links; "
            "move the scene (Z) or the grasp (X) closer to the robot"
        )
    seeds = ([np.asarray(q0, dtype=float)] if q0 is not None else []) + [np.radians(s) for s in robot.ik_seeds_deg]
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
        f"flange pose: not reachable within the {robot.name} joint limits (best IK error {best[0]:.3g} mm); "
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


def robot_scene(robot: RobotModel | None = None, distance_mm: float = 20.0) -> Scene:
    """The robot's cell (its TOML [cell]: nominal Z and X; else the paper's Z and the
    side grasp), its repeatability noise and the bench's nominal lens distance."""
    robot = robot or kr10_r1100_sixx()
    kw = {}
    if robot.cell_Z is not None:
        kw["Z"] = np.array(robot.cell_Z)
    if robot.cell_X is not None:
        kw["X"] = np.array(robot.cell_X)
    return Scene(distance_mm=float(distance_mm), robot=robot, noise=robot.noise, **kw)


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
