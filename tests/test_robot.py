"""KUKA KR 10 R1100 sixx pose model and the simulated calibration scene."""

import math

import numpy as np
import pytest

from lensforge.errors import PoseRangeError
from lensforge.optics.pose import invert_poses
from lensforge.calibration.robot import (
    PAPER_Z,
    RobotNoise,
    flange_pose,
    forward_kinematics,
    inverse_kinematics,
    kr10_r1100_sixx,
    lens_pose_matrix,
    paper_scene,
    random_lens_poses,
    simulate_calibration,
)


def test_forward_kinematics_zero_pose():
    # URDF offsets: x = 25 + 560 + 515 + 80 = 1180 mm, z = 400 + 35 = 435 mm; tool0 z along +x
    T = forward_kinematics(np.zeros(6))
    assert np.allclose(T[:3, 3], [1180.0, 0.0, 435.0])
    assert np.allclose(T[:3, 2], [1.0, 0.0, 0.0])


def test_forward_kinematics_vectorised():
    q = np.random.default_rng(0).uniform(-1, 1, (5, 6))
    T = forward_kinematics(q)
    assert T.shape == (5, 4, 4)
    assert np.allclose(T[3], forward_kinematics(q[3]))


def test_inverse_kinematics_roundtrip_and_limits():
    robot = kr10_r1100_sixx()
    A = flange_pose(paper_scene(), np.zeros(6), check_reach=False)
    q = inverse_kinematics(A, robot)
    lim = np.asarray(robot.limits_rad)
    assert np.all(q >= lim[:, 0]) and np.all(q <= lim[:, 1])
    assert np.abs(forward_kinematics(q, robot) - A).max() < 1e-6


def test_unreachable_pose_raises():
    T = np.eye(4)
    T[:3, 3] = [1500.0, 0.0, 400.0]
    with pytest.raises(PoseRangeError, match="flange pose"):
        inverse_kinematics(T)


def test_paper_scene_and_nominal_placement():
    s = paper_scene(distance_mm=20.0)
    assert np.allclose(s.Z, PAPER_Z)
    B = lens_pose_matrix(s, np.zeros(6))
    assert np.allclose(B[:3, 3], [0, 0, -20.0])
    # working-range corners are reachable
    x = np.array([[1, 1, 1, 0.0175, 0.0175, 0.0175], [-1, -1, -1, -0.0175, -0.0175, -0.0175]])
    A = flange_pose(s, x, check_reach=True)
    assert np.allclose(A @ s.X, s.Z @ lens_pose_matrix(s, x))


def test_repeatability_mapping_iso9283():
    """sigma from RP = mean(l) + 3 std(l) (ISO 9283) for isotropic Gaussian noise."""
    n = RobotNoise.from_repeatability(0.02)
    assert n.translation_mm == pytest.approx(0.02 / 3.616, rel=1e-3)
    a = n.sample(np.random.default_rng(1), 200000)[:, :3]
    l = np.linalg.norm(a - a.mean(0), axis=1)
    assert l.mean() + 3 * l.std() == pytest.approx(0.02, rel=0.01)
    assert RobotNoise().cov.shape == (6, 6)


def test_simulate_calibration_consistency():
    rng = np.random.default_rng(2)
    s = paper_scene()
    x = random_lens_poses(rng, 12)
    assert np.all(np.abs(x[:, :3]) <= 1.0) and np.all(np.abs(x[:, 3:]) <= math.radians(1.0))
    d = simulate_calibration(s, x, rng, cov_B=np.eye(6) * 1e-10)
    assert np.allclose(d.A_true @ s.X, s.Z @ d.B_true, atol=1e-9)
    dA = np.linalg.norm((invert_poses(d.A) @ d.A_true)[:, :3, 3], axis=1)
    assert 0 < dA.max() < 0.05  # flange noise at the um level
