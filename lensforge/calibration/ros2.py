"""ROS 2 output: a launch file that publishes the calibrated frames as static transforms.

MoveIt 2's hand-eye calibration exports a Python launch file with a
``tf2_ros static_transform_publisher`` node; lensforge writes the same kind beside
``easy_handeye.yaml`` so a cell can use the result directly
(``ros2 launch ./lensforge_calibration.launch.py``):

- Z = ^W T_S: parent ``robot_base_frame`` (default ``base_link``) -> child
  ``sensor_frame`` (``wfs_sensor``);
- X = ^E T_O: parent ``robot_effector_frame`` (``tool0``, the flange) -> child
  ``lens_frame`` (``lens``).

Translations in metres, rotations as unit quaternions (x, y, z, w), in the
``static_transform_publisher`` named-argument form of ROS 2 Humble and later
(``--x --y --z --qx --qy --qz --qw --frame-id --child-frame-id``).
"""

from __future__ import annotations

import re

import numpy as np

from ..errors import ConfigError
from .formats import matrix_to_quaternion

__all__ = ["static_transform_launch", "LAUNCH_FILE_NAME"]

LAUNCH_FILE_NAME = "lensforge_calibration.launch.py"
_FRAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_/]*$")


def _args(T, parent: str, child: str) -> list[str]:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ConfigError(f"transform {parent} -> {child}: expected a finite 4x4 matrix")
    w, x, y, z = matrix_to_quaternion(T)
    t = T[:3, 3] / 1000.0  # mm -> m
    vals = [("--x", t[0]), ("--y", t[1]), ("--z", t[2]), ("--qx", x), ("--qy", y), ("--qz", z), ("--qw", w)]
    out = []
    for k, v in vals:
        out += [k, repr(float(v))]
    return out + ["--frame-id", parent, "--child-frame-id", child]


def static_transform_launch(Z, X=None, *, robot_base_frame: str = "base_link", sensor_frame: str = "wfs_sensor",
                            robot_effector_frame: str = "tool0", lens_frame: str = "lens") -> str:
    """Text of a ROS 2 Python launch file publishing Z (and X when given) as static
    transforms (module docstring); Z, X 4x4 in mm."""
    for name, v in (("robot_base_frame", robot_base_frame), ("sensor_frame", sensor_frame),
                    ("robot_effector_frame", robot_effector_frame), ("lens_frame", lens_frame)):
        if not _FRAME.match(v):
            raise ConfigError(f"{name}: {v!r} is not a ROS frame name (letters, digits, _ and /)")
    nodes = [("lensforge_sensor_tf", _args(Z, robot_base_frame, sensor_frame))]
    if X is not None:
        nodes.append(("lensforge_lens_tf", _args(X, robot_effector_frame, lens_frame)))
    lines = ['"""lensforge calibration: static transforms of the calibrated frames (ROS 2 launch file).',
             "",
             f"Z: {robot_base_frame} -> {sensor_frame} (sensor in the robot base)"
             + (f"; X: {robot_effector_frame} -> {lens_frame} (lens in the flange)" if X is not None else "")
             + ". Metres, quaternions.", '"""', "",
             "from launch import LaunchDescription", "from launch_ros.actions import Node", "", "",
             "def generate_launch_description():", "    return LaunchDescription(["]
    for name, args in nodes:
        lines += ["        Node(", '            package="tf2_ros",', '            executable="static_transform_publisher",',
                  f'            name="{name}",', "            arguments=["]
        for i in range(0, len(args), 2):
            lines.append(f'                "{args[i]}", "{args[i + 1]}",')
        lines += ["            ],", "        ),"]
    lines += ["    ])", ""]
    return "\n".join(lines)
