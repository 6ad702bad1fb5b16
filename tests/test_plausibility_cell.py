"""Robot poses against the cell's nominal sensor and grasp (issue 23, plausibility before fitting):
a recorded flange pose that puts the lens far from the sensor is refused, naming the robot
file, the pose id and the likely mistake; honest plans and sessions never are, by a wide margin
(``calibration/cell_plausibility.py``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import run_cli_inprocess

from lensforge.calibration import formats
from lensforge.calibration.cell_plausibility import (cell_lens_poses, cell_limits, check_cell_poses,
                                                     implausible_cell_poses)
from lensforge.calibration.initial_poses import InitialPoseModel
from lensforge.calibration.robot import flange_pose, load_robot, robot_scene
from lensforge.calibration.session import load_design_lens, plan
from lensforge.errors import ConfigError
from lensforge.optics.pose import matrix_to_pose, pose_to_matrix
from lensforge.verification.session_sim import SENSOR_CAD_ROTATION_RAD, SENSOR_CAD_TRANSLATION_MM, simulate_session

LENS = "paper:extended_polynomial"


def _offsets(A, scene):
    """(lateral mm, along mm, turn rad) of each pose's lens about its nominal placement."""
    B = cell_lens_poses(A, scene)
    x = matrix_to_pose(np.linalg.inv(scene.T_SO_nominal) @ B)
    return np.hypot(x[:, 0], x[:, 1]), B[:, 2, 3] + scene.distance_mm, np.linalg.norm(x[:, 3:], axis=1)


def _margins(A, scene, bench):
    lat, along, turn = _offsets(A, scene)
    t_lim, r_lim = cell_limits(bench)
    return t_lim / max(lat.max(), np.abs(along).max()), r_lim / turn.max()


def _table(A, ids=None, source="r.csv"):
    ids = tuple(str(i + 1) for i in range(len(A))) if ids is None else ids
    return formats.PoseTable(ids=ids, T=np.asarray(A), source=source, rows=tuple(i + 2 for i in range(len(A))))


@pytest.mark.parametrize("robot", ["kr10_r1100_sixx", "ur5e"])
def test_the_working_box_and_cell_errors_at_5_sigma_are_far_inside(robot):
    """The plan's box corners (+-0.5 mm, +-5 deg per component: the largest honest plan pose), and
    hand-taught poses in a true cell off the nominal one by 5 sigma of every CAD and grasp error, with
    the robot's noise: accepted with margins of >= 60x / 5x (translation / rotation) and, with every
    error at 5 sigma at once (3.7 mm, 14 deg measured), >= 10x / 3x."""
    lens, bench = load_design_lens(LENS)
    scene = robot_scene(load_robot(robot), bench.placement.distance_mm)
    corners = np.array(np.meshgrid(*[[-1.0, 1.0]] * 6)).reshape(6, -1).T * ([0.5] * 3 + [math.radians(5.0)] * 3)
    A = flange_pose(scene, corners, check_reach=False)
    rng = np.random.default_rng(7)
    g = InitialPoseModel().sigma
    for _ in range(20):
        sign = rng.choice([-1.0, 1.0], 12)
        X = scene.X @ pose_to_matrix(5 * sign[:6] * g)
        Z = scene.Z @ pose_to_matrix(5 * sign[6:] * np.array([SENSOR_CAD_TRANSLATION_MM] * 3
                                                             + [SENSOR_CAD_ROTATION_RAD] * 3))
        B = scene.T_SO_nominal @ pose_to_matrix(corners)
        A_taught = Z @ B @ np.linalg.inv(X) @ pose_to_matrix(scene.noise.sample(rng, len(corners)))
        for AA, (t_margin, r_margin) in ((A, (60, 5)), (A_taught, (10, 3))):
            assert implausible_cell_poses(AA, scene, bench) == []
            mt, mr = _margins(AA, scene, bench)
            assert mt >= t_margin and mr >= r_margin, (mt, mr)
    check_cell_poses(_table(A), scene, bench, None)


@pytest.mark.parametrize("design, robot, seeds, n", [
    (LENS, None, (0, 1, 2), 12),
    pytest.param("paper:zernike", "ur5e", (3, 4, 5), 24, marks=pytest.mark.slow),
    pytest.param(LENS, "ur5e", (6, 7, 8), 8, marks=pytest.mark.slow),
])
def test_honest_plans_and_sessions_are_never_refused(design, robot, seeds, n):
    """`lensforge plan` output and simulate-session sessions (default tolerances, robot noise) of
    several seeds: no pose is implausible, and the closest comes within 1/25 of the limits."""
    lens, bench = load_design_lens(design)
    p = plan(lens, bench=bench, robot=robot, n=n, seed=seeds[0])
    check_cell_poses(_table(p.A), p.scene, bench, None)
    worst = []
    for seed in seeds:
        s = simulate_session(lens, bench=bench, robot=robot, seed=seed, session_plan=p)
        assert implausible_cell_poses(s.A_recorded, p.scene, bench) == []
        worst.append(_margins(s.A_recorded, p.scene, bench))
    mt, mr = np.min(worst, axis=0)
    assert mt >= 25 and mr >= 4, (mt, mr)


@pytest.fixture(scope="module")
def nominal():
    lens, bench = load_design_lens(LENS)
    scene = robot_scene(load_robot(None), bench.placement.distance_mm)
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.uniform(-0.5, 0.5, (10, 3)), rng.uniform(-0.08, 0.08, (10, 3))], axis=1)
    return bench, scene, flange_pose(scene, x, check_reach=False)


def _refused(table, scene, bench, path=None):
    with pytest.raises(ConfigError) as e:
        check_cell_poses(table, scene, bench, path)
    msg = str(e.value)
    assert "\n" not in msg
    return msg


def test_a_pose_that_only_misses_the_pupil_is_not_refused(nominal):
    """3 mm off the axis, 4 mm along it or turned 15 deg: unlit or out of the working range, but
    plausible (the calibration reports it as a rejected pose)."""
    bench, scene, A = nominal
    for x in ([3.0, 0, 0, 0, 0, 0], [0, 2.0, 4.0, 0, 0, 0], [0, 0, 0, math.radians(15), 0, 0],
              [0, 0, 0, 0, 0, math.radians(30)]):
        check_cell_poses(_table(np.concatenate([A, flange_pose(scene, np.array([x]), check_reach=False)])),
                         scene, bench, None)


@pytest.mark.parametrize("shift, words", [
    ([0, 0, -300.0], ("farther from the sensor than its nominal 20 mm", "1 of 10 poses is off (pose 4)", "re-record")),
    ([120.0, 0, 0], ("mm from the sensor's line of sight",)),
    ([0, 0, 90.0], ("behind the sensor's lenslet plane",)),
])
def test_one_stray_pose_is_named(nominal, shift, words):
    """One pose moved in {S} (a typo, or a pose of another session)."""
    bench, scene, A = nominal
    A = A.copy()
    T = np.eye(4)
    T[:3, 3] = shift
    A[3] = scene.Z @ T @ np.linalg.inv(scene.Z) @ A[3]
    msg = _refused(_table(A), scene, bench)
    assert msg.startswith("r.csv: pose 4 (row 5): with the cell's nominal sensor and grasp"), msg
    for w in words:
        assert w in msg, (w, msg)


def test_every_pose_off_names_units_frame_and_cell(nominal):
    """A constant offset (another base frame, or a [cell] that is not this cell's)."""
    bench, scene, A = nominal
    A = A.copy()
    A[:, 1, 3] += 200.0
    msg = _refused(_table(A), scene, bench)
    for w in ("all 10 poses are off", "base frame ($BASE)", "[cell]", "kr10_r1100_sixx.toml"):
        assert w in msg, (w, msg)


def test_the_limits_follow_the_working_range():
    lens, bench = load_design_lens(LENS)
    t, r = cell_limits(bench)
    assert t == pytest.approx(50.0, rel=1e-12) and r == pytest.approx(math.radians(45.0), rel=1e-12)
    wide = bench.replace(pose_limits={"translation_mm": 8.0, "rotation_rad": math.radians(20.0)})
    t, r = cell_limits(wide)
    assert t == pytest.approx(80.0, rel=1e-12) and r == pytest.approx(math.radians(60.0), rel=1e-12)


def _spoil_units(p, d):
    T = p.T.copy()
    T[:, :3, 3] /= 1000.0
    (d / "r.csv").write_text(formats.quaternion_csv(p.ids, T, units="mm"))
    return d / "r.csv", ("read in m", "`# units: mm` line is probably wrong")


def _spoil_abc(p, d):
    x = np.array([formats.matrix_to_xyzabc(t) for t in p.T])
    rows = [",".join([i] + [f"{v:.6f}" for v in r[:3]] + [f"{v:.9f}" for v in np.radians(r[3:])])
            for i, r in zip(p.ids, x)]
    (d / "r.csv").write_text("pose,X,Y,Z,A,B,C\n" + "\n".join(rows) + "\n")
    return d / "r.csv", ("A, B, C", "radians", "turned")


def _spoil_quaternion(p, d):
    q = formats.matrix_to_quaternion(p.T)
    rows = [",".join([i] + [f"{v:.6f}" for v in t[:3, 3]] + [f"{v:.10f}" for v in qq[[1, 2, 3, 0]]])
            for i, t, qq in zip(p.ids, p.T, q)]
    (d / "r.csv").write_text("# units: mm\npose,x,y,z,qw,qx,qy,qz\n" + "\n".join(rows) + "\n")
    return d / "r.csv", ("x, y, z, w", "turned")


@pytest.mark.parametrize("spoil", [_spoil_units, _spoil_abc, _spoil_quaternion])
def test_robot_file_mistakes_are_refused_and_named_before_fitting(spoil, perfect_sessions, tmp_path, monkeypatch,
                                                                 capsys):
    """Through `calibrate`: exit 2, one line naming the file, the pose and the re-read that makes
    every pose plausible; nothing written, and no fit run (under a few seconds)."""
    import time

    paths = perfect_sessions[0]
    f, words = spoil(formats.read_robot_poses(paths["robot_poses.csv"]), tmp_path)
    t0 = time.process_time()
    code, _, err = run_cli_inprocess(monkeypatch, capsys, "calibrate", LENS, "-m", paths["wfs_zernike.csv"], "-r", f,
                                     "-o", tmp_path / "out", "--no-progress")
    assert time.process_time() - t0 < 10
    errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert code == 2 and len(errors) == 1 and "Traceback" not in err, err[-2000:]
    line = errors[0]
    assert line.startswith(f"error: {f}: pose 1 (row "), line
    for w in ("with the cell's nominal sensor and grasp", "the poses are plausible if", *words):
        assert w in line, (w, line)
    assert not (tmp_path / "out").exists()


def test_only_matched_poses_are_checked(perfect_sessions, tmp_path, monkeypatch, capsys):
    """A home pose in the robot file without a WFS measurement is not a calibration pose: the
    session calibrates and reports it as rejected."""
    import json

    paths = perfect_sessions[0]
    p = formats.read_robot_poses(paths["robot_poses.csv"])
    home = np.eye(4)
    home[:3, 3] = [400.0, 0.0, 800.0]
    (tmp_path / "r.csv").write_text(formats.quaternion_csv(p.ids + ("99",), np.concatenate([p.T, home[None]])))
    code, out, err = run_cli_inprocess(monkeypatch, capsys, "calibrate", LENS, "-m", paths["wfs_zernike.csv"], "-r",
                                       tmp_path / "r.csv", "--method", "two-stage", "-o", tmp_path / "out",
                                       "--no-progress", "--json")
    assert code == 0, err[-2000:]
    d = json.loads((tmp_path / "out" / "calibration.json").read_text())
    assert any(str(r["pose"]) == "99" for r in d["poses_rejected"]), d["poses_rejected"]


# ----------------------------------------------------------------------------- properties (hypothesis)

from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_unit = st.floats(-1.0, 1.0)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(x=st.lists(_unit, min_size=6, max_size=6), cell=st.lists(_unit, min_size=12, max_size=12),
       robot=st.sampled_from(["kr10_r1100_sixx", "ur5e"]), seed=st.integers(0, 2**16))
def test_any_honest_pose_is_accepted(x, cell, robot, seed):
    """Any lens pose of the plan's box, in a true cell off the nominal one by up to 4 sigma of every
    CAD and grasp error, recorded with the robot's noise."""
    lens, bench = load_design_lens(LENS)
    scene = robot_scene(load_robot(robot), bench.placement.distance_mm)
    xv = np.array(x) * ([0.5] * 3 + [math.radians(5.0)] * 3)
    c = 4 * np.array(cell)
    X = scene.X @ pose_to_matrix(c[:6] * InitialPoseModel().sigma)
    Z = scene.Z @ pose_to_matrix(c[6:] * np.array([SENSOR_CAD_TRANSLATION_MM] * 3 + [SENSOR_CAD_ROTATION_RAD] * 3))
    A = Z @ scene.T_SO_nominal @ pose_to_matrix(xv) @ np.linalg.inv(X)
    A = A @ pose_to_matrix(scene.noise.sample(np.random.default_rng(seed), 1)[0])
    assert implausible_cell_poses(A[None], scene, bench) == []


@settings(max_examples=60, deadline=None, derandomize=True)
@given(direction=st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 0.1),
       scale=st.floats(1.05, 1e4), turn=st.booleans())
def test_any_pose_beyond_the_limits_is_refused(nominal, direction, scale, turn):
    """A pose moved by more than the limit (in {S}) or turned by more than it: refused, one line
    naming the file and the pose."""
    bench, scene, A = nominal
    t_lim, r_lim = cell_limits(bench)
    d = np.array(direction) / np.linalg.norm(direction)
    T = np.eye(4)
    if turn:  # about the lens origin, by more than the limit (at most half a turn)
        T = pose_to_matrix(np.r_[0, 0, 0, d * min(math.pi, r_lim * max(scale, 1.3))])  # 1.3: beyond the fixture's 8 deg
        T = scene.Z @ scene.T_SO_nominal @ T @ np.linalg.inv(scene.Z @ scene.T_SO_nominal)
    else:  # a move whose largest component (off or along the axis) exceeds the limit
        v = d * t_lim * scale
        v *= max(1.0, 1.01 * t_lim / max(math.hypot(v[0], v[1]), abs(v[2])))
        T[:3, 3] = scene.Z[:3, :3] @ v
    A = A.copy()
    A[6] = T @ A[6]
    if turn and r_lim * max(scale, 1.3) > math.pi:  # more than half a turn is a turn the other way
        return
    msg = _refused(_table(A), scene, bench)
    assert msg.startswith("r.csv: pose 7 (row 8): "), msg
