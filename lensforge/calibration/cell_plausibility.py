"""Robot poses against the cell: a recorded flange pose must put the lens in front of the sensor.

With the cell's nominal sensor pose Z = ^W T_S and grasp X = ^E T_O (the robot TOML's
``[cell]``, else the paper's cell; ``robot.robot_scene``), a recorded flange pose A predicts
the lens pose B = Z^-1 A X in the sensor frame {S}. A calibration pose keeps the lens within
the bench's working range (``bench.pose_limits``: +-5 mm, +-10 deg) of its nominal placement
({O} at z = -d on the sensor's axis); a pose that does not light the pupil misses it by
millimetres. :func:`check_cell_poses` refuses a pose that puts the lens many working ranges
away -- far from the sensor's line of sight, far along it or behind the lenslet plane, or
turned far from the beam -- which is a unit, angle, quaternion-order or base-frame mistake in
the robot file, or a ``[cell]`` that is not this cell's. The one-line message names the file,
the pose id, what is wrong and, when a usual mistake re-read (:func:`robot_file_readings`, the
same readings ``diagnosis`` tries after a failed fit) makes every pose plausible, that mistake.

Thresholds (``CELL_TRANSLATION_FACTOR``, ``CELL_ROTATION_FACTOR`` and their floors), with
the honest poses they must never refuse: ``lensforge plan`` draws its candidates in the box
the design records, +-1.5 mm, +-5 deg per rotation-vector component about nominal for
``lensforge design``'s default (at most 2.1 mm from the axis and an 8.7 deg turn; +-0.5 mm for
the paper lenses); a simulated session adds the grasp error (0.3 mm, 0.5 deg 1-sigma,
``initial_poses.InitialPoseModel``), the sensor's CAD error (0.2 mm, 0.2 deg,
``session_sim``) and the robot's repeatability (5.5 um). Measured over plans and
simulate-session sessions of several seeds, designs and both robots: at most 0.8 mm from the
axis, 0.6 mm along it and a 9 deg turn (tests/test_plausibility_cell.py). The limits are
max(50 mm, 10 working ranges) off and along the axis (60x the honest maximum) and max(45
deg, 3 working ranges) of rotation (5x); with every cell and grasp error at 5 sigma at once
(3.7 mm, 14 deg) the margins are still 13x and 3.3x, and a cell whose ``[cell]`` was measured
with a ruler (centimetres, a few degrees off) passes.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..optics.pose import invert_poses, matrix_to_pose
from . import formats
from .plausibility import pose_file_kind

__all__ = ["CELL_TRANSLATION_FACTOR", "CELL_TRANSLATION_MIN_MM", "CELL_ROTATION_FACTOR", "CELL_ROTATION_MIN_RAD",
           "robot_file_readings", "cell_lens_poses", "cell_limits", "implausible_cell_poses", "check_cell_poses"]

CELL_TRANSLATION_FACTOR = 10.0  # working ranges (bench.pose_limits.translation_mm) off or along the axis
CELL_TRANSLATION_MIN_MM = 50.0
CELL_ROTATION_FACTOR = 3.0  # working ranges (bench.pose_limits.rotation_rad) of turn about nominal
CELL_ROTATION_MIN_RAD = math.radians(45.0)


def robot_file_readings(poses: formats.PoseTable, path) -> list[tuple[str, str, formats.PoseTable]]:
    """The usual mistakes of a robot-pose file, each as (name, condition, re-read poses):
    translations in m instead of mm (or the reverse, by the file's ``# units:`` line or
    JSON "units"), KUKA A, B, C in radians, quaternion columns in x, y, z, w order. The
    condition completes "... if <condition>" (e.g. "the robot file r.csv is read in m: its
    `# units: mm` line is probably wrong")."""
    kind, units = pose_file_kind(path)
    name = Path(path).name

    def scaled(k):
        T = poses.T.copy()
        T[:, :3, 3] *= k
        return replace(poses, T=T)

    out = []
    if kind in ("quaternion_csv", "json_4x4") and units in ("m", "mm"):
        other = "mm" if units == "m" else "m"
        where = "its `# units: {u}` line" if kind == "quaternion_csv" else 'its "units": "{u}"'
        out.append((f"robot units {other}", f"the robot file {name} is read in {other}: "
                    f"{where.format(u=units)} is probably wrong", scaled(1e-3 if units == "m" else 1e3)))
    if kind == "xyzabc_csv":
        out.append(("robot units m", f"X, Y, Z of the robot file {name} are read in metres: the XYZABC CSV takes "
                    "mm; multiply them by 1000", scaled(1e3)))
        xyzabc = np.array([formats.matrix_to_xyzabc(T) for T in poses.T])  # the file's values (|B| < 90 deg)
        if np.all(np.abs(xyzabc[:, 3:]) <= 2 * math.pi + 1e-9):  # angles that could be radians
            xyzabc[:, 3:] = np.degrees(xyzabc[:, 3:])
            out.append(("robot angles rad", f"A, B, C of the robot file {name} are read in radians: the XYZABC CSV "
                        "takes degrees (KUKA); convert them", replace(poses, T=formats.xyzabc_to_matrix(xyzabc))))
    if kind == "quaternion_csv":
        q = formats.matrix_to_quaternion(poses.T)  # the columns (qw, qx, qy, qz) as read, up to sign
        T = formats.quaternion_to_matrix(poses.T[:, :3, 3], q[:, [3, 0, 1, 2]])
        out.append(("quaternion xyzw", f"the quaternion columns of the robot file {name} are read in x, y, z, w "
                    "order: reorder them to the header's qw, qx, qy, qz", replace(poses, T=T)))
    return out


def cell_lens_poses(A: np.ndarray, scene) -> np.ndarray:
    """Lens poses B = ^S T_O (n, 4, 4) that the nominal cell ``scene`` (a ``robot.Scene``)
    predicts for flange poses A (n, 4, 4) (mm)."""
    return invert_poses(scene.Z) @ np.asarray(A, float) @ scene.X


def cell_limits(bench) -> tuple[float, float]:
    """(translation mm, rotation rad) beyond which a pose is implausible on ``bench``
    (module docstring)."""
    lim = bench.pose_limits
    return (max(CELL_TRANSLATION_MIN_MM, CELL_TRANSLATION_FACTOR * float(lim.translation_mm)),
            max(CELL_ROTATION_MIN_RAD, CELL_ROTATION_FACTOR * float(lim.rotation_rad)))


def implausible_cell_poses(A: np.ndarray, scene, bench) -> list[tuple[int, str]]:
    """(index, what is wrong) of the flange poses A (n, 4, 4) that the nominal cell puts
    implausibly far from the sensor (``cell_limits``), in the order of A."""
    t_lim, r_lim = cell_limits(bench)
    B = cell_lens_poses(A, scene)
    d = float(scene.distance_mm)
    out = []
    for k, b in enumerate(B):
        if not np.all(np.isfinite(b)):
            out.append((k, "the pose is not a finite transform"))
            continue
        p = b[:3, 3]
        lateral, along = float(math.hypot(p[0], p[1])), float(p[2] + d)  # along: from the nominal placement
        turn = float(np.linalg.norm(matrix_to_pose(invert_poses(scene.T_SO_nominal) @ b)[3:]))
        tilt = math.degrees(math.acos(float(np.clip(b[2, 2], -1.0, 1.0))))
        what = []
        if lateral > t_lim:
            what.append(f"{lateral:.4g} mm from the sensor's line of sight")
        if p[2] > 0.0 and along > t_lim:
            what.append(f"{p[2]:.4g} mm behind the sensor's lenslet plane")
        elif abs(along) > t_lim:
            what.append(f"{abs(along):.4g} mm {'nearer to' if along > 0 else 'farther from'} the sensor than its "
                        f"nominal {d:g} mm")
        if turn > r_lim:
            what.append(f"turned {math.degrees(turn):.3g} deg from its nominal orientation (its axis {tilt:.3g} deg "
                        "from the beam)")
        if what:
            out.append((k, ", ".join(what)))
    return out


def check_cell_poses(poses: formats.PoseTable, scene, bench, path=None) -> None:
    """Refuse (ConfigError, one line) flange poses that the nominal cell puts far from the
    sensor (module docstring): the file, the first such pose's id, where the lens would be,
    and the likely mistake -- a usual misreading of the file (``robot_file_readings``) that
    makes every pose plausible, else a wrong base frame or ``[cell]`` (every pose off) or a
    stray pose (some)."""
    bad = implausible_cell_poses(poses.T, scene, bench)
    if not bad:
        return
    k, what = bad[0]
    source = poses.source or "robot poses"
    row = f" (row {poses.rows[k]})" if len(poses.rows) > k else ""
    t_lim, r_lim = cell_limits(bench)
    robot = scene.robot
    cell = (f"the [cell] of {Path(robot.source).name}" if robot.cell_Z is not None and robot.source
            else f"the {robot.name}'s default cell" if robot.cell_Z is None else f"the {robot.name}'s [cell]")
    hint = None
    if path is not None:
        for _, condition, table in robot_file_readings(poses, path):
            if not implausible_cell_poses(table.T, scene, bench):
                hint = f"the poses are plausible if {condition}"
                break
    if hint is None:
        if len(bad) == len(poses.ids):
            hint = (f"all {len(bad)} poses are off: check the file's units and base frame ($BASE) and the robot "
                    f"TOML's [cell] sensor_xyzabc / grasp_xyzabc (here {cell})")
        else:
            ids = ", ".join(str(poses.ids[j]) for j, _ in bad[:5]) + (" ..." if len(bad) > 5 else "")
            hint = (f"{len(bad)} of {len(poses.ids)} poses {'is' if len(bad) == 1 else 'are'} off (pose {ids}): "
                    "remove or re-record them (a typo, or a pose of another session or frame)")
    raise ConfigError(f"{source}: pose {poses.ids[k]}{row}: with the cell's nominal sensor and grasp ({cell}) "
                      f"the lens would be {what} (a calibration pose stays within "
                      f"{bench.pose_limits.translation_mm:g} mm / {math.degrees(bench.pose_limits.rotation_rad):g} "
                      f"deg of the nominal placement; the limit is {t_lim:g} mm / {math.degrees(r_lim):g} deg); "
                      f"{hint}")
