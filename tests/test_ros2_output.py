"""ROS 2 output: the launch file with static_transform_publisher for Z and X."""

import ast

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lensforge.calibration.ros2 import LAUNCH_FILE_NAME, static_transform_launch
from lensforge.errors import ConfigError


def _nodes(text):
    """(name, arguments) of every Node(...) call in the launch file's source."""
    tree = ast.parse(text)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "Node":
            kw = {k.arg: k.value for k in node.keywords}
            assert ast.literal_eval(kw["package"]) == "tf2_ros"
            assert ast.literal_eval(kw["executable"]) == "static_transform_publisher"
            out.append((ast.literal_eval(kw["name"]), ast.literal_eval(kw["arguments"])))
    return out


def _transform(args):
    a = dict(zip(args[::2], args[1::2]))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([float(a[k]) for k in ("--qx", "--qy", "--qz", "--qw")]).as_matrix()
    T[:3, 3] = [1000.0 * float(a[k]) for k in ("--x", "--y", "--z")]
    return T, a["--frame-id"], a["--child-frame-id"]


def test_launch_file_publishes_z_and_x():
    rng = np.random.default_rng(0)
    Z, X = np.eye(4), np.eye(4)
    Z[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    Z[:3, 3] = [512.3, -499.9, 1000.1]
    X[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * 0.1).as_matrix()
    X[:3, 3] = [0.1, -0.2, 150.35]
    text = static_transform_launch(Z, X, robot_base_frame="kr10_base", sensor_frame="wfs40")
    nodes = _nodes(text)
    assert [n for n, _ in nodes] == ["lensforge_sensor_tf", "lensforge_lens_tf"]
    Tz, parent, child = _transform(nodes[0][1])
    assert (parent, child) == ("kr10_base", "wfs40")
    np.testing.assert_allclose(Tz, Z, rtol=0, atol=1e-12)
    Tx, parent, child = _transform(nodes[1][1])
    assert (parent, child) == ("tool0", "lens")
    np.testing.assert_allclose(Tx, X, rtol=0, atol=1e-12)
    assert "def generate_launch_description" in text and LAUNCH_FILE_NAME.endswith(".launch.py")
    assert len(_nodes(static_transform_launch(Z))) == 1


def test_bad_frames_and_transforms():
    with pytest.raises(ConfigError, match="sensor_frame: 'wfs sensor' is not a ROS frame name"):
        static_transform_launch(np.eye(4), sensor_frame="wfs sensor")
    with pytest.raises(ConfigError, match="expected a finite 4x4"):
        static_transform_launch(np.full((4, 4), np.nan))


def test_calibration_bundle_has_the_launch_file():
    from lensforge.calibration.session_result import CalibrationResult

    assert "ROS 2 launch file" in CalibrationResult.files.__doc__
