"""Real-bench file formats: pose conventions, readers, writers, robots; bad input is one line."""

import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli
from lensforge.calibration import formats as F
from lensforge.calibration.robot import ROBOTS, forward_kinematics, inverse_kinematics, load_robot, robot_scene
from lensforge.errors import ConfigError


def _Rx(c):
    c = math.radians(c)
    return np.array([[1, 0, 0], [0, math.cos(c), -math.sin(c)], [0, math.sin(c), math.cos(c)]])


def _Ry(b):
    b = math.radians(b)
    return np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])


def _Rz(a):
    a = math.radians(a)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def test_kuka_abc_against_hand_computed_pose():
    # A = 90, C = 90: Rz(90) Rx(90) worked out by hand
    T = F.xyzabc_to_matrix([10.0, -20.0, 30.0, 90.0, 0.0, 90.0])
    assert np.allclose(T[:3, :3], [[0, 0, 1], [1, 0, 0], [0, 1, 0]], atol=1e-15)
    assert np.allclose(T[:3, 3], [10, -20, 30])
    # general angles: R = Rz(A) Ry(B) Rx(C) from elementary matrices
    T = F.xyzabc_to_matrix([1, 2, 3, 30.0, 45.0, -60.0])
    assert np.allclose(T[:3, :3], _Rz(30) @ _Ry(45) @ _Rx(-60), atol=1e-14)


def test_round_trips_xyzabc_matrix_quaternion():
    rng = np.random.default_rng(0)
    v = np.c_[rng.uniform(-1000, 1000, (50, 3)), rng.uniform(-179, 179, (50, 1)), rng.uniform(-89, 89, (50, 1)),
              rng.uniform(-179, 179, (50, 1))]
    T = F.xyzabc_to_matrix(v)
    assert np.allclose(F.matrix_to_xyzabc(T), v, atol=1e-9)
    q = F.matrix_to_quaternion(T)
    assert np.all(q[:, 0] >= 0) and np.allclose(np.linalg.norm(q, axis=1), 1)
    assert np.allclose(F.quaternion_to_matrix(T[:, :3, 3], q), T, atol=1e-12)
    # through the files
    ids = [str(i) for i in range(50)]
    for text, name in ((F.xyzabc_csv(ids, T), "p.csv"), (F.quaternion_csv(ids, T, "m"), "q.csv"),
                       (F.pose_table_json(ids, T), "p.json")):
        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / name
            path.write_text(text)
            t = F.read_robot_poses(path)
        assert t.ids == tuple(ids)
        assert np.abs(t.T - T).max() < 1e-5  # 6 decimals of mm / deg in the CSV


def test_quaternion_metres_are_converted(tmp_path):
    p = tmp_path / "q.csv"
    p.write_text("# units: m\npose,x,y,z,qw,qx,qy,qz\na,0.1,-0.2,0.3,1,0,0,0\nb,0,0,1,0.7071068,0,0.7071068,0\n"
                 "c,0,0,0,0,0,0,1\n")
    t = F.read_robot_poses(p)
    assert np.allclose(t.T[0, :3, 3], [100, -200, 300])
    assert np.allclose(t.T[1, :3, :3], _Ry(90), atol=1e-6)


def test_wfs_csv_and_json_agree(tmp_path):
    z = np.random.default_rng(1).normal(size=(3, 15))
    hdr = {"wavelength_nm": 532.0, "pupil_center_mm": (0.1, -0.2), "pupil_radius_mm": 0.9}
    (tmp_path / "w.csv").write_text(F.wfs_csv(["1", "2", "3"], z, hdr))
    a = F.read_wfs(tmp_path / "w.csv")
    js = {"schema_version": 1, "kind": "wfs_zernike", "units": "um", "ordering": "thorlabs", **hdr,
          "measurements": [{"pose": str(i + 1), "zernike": r} for i, r in enumerate(z.tolist())]}
    (tmp_path / "w.json").write_text(json.dumps(js))
    b = F.read_wfs(tmp_path / "w.json")
    for w in (a, b):
        assert w.ids == ("1", "2", "3") and w.order == 4
        assert np.allclose(w.zernike, z)
        assert w.header["pupil_center_mm"] == (0.1, -0.2)


def test_krl_pair_and_easy_handeye_yaml():
    T = F.xyzabc_to_matrix([[100, 200, 300, 10, 20, 30], [1, 2, 3, -10, -20, -30]])
    files = F.krl_program(["a", "b"], T, name="lf_calib")
    dat, src = files["lf_calib.dat"], files["lf_calib.src"]
    assert dat.startswith("DEFDAT lf_calib PUBLIC") and dat.rstrip().endswith("ENDDAT")
    assert "DECL E6POS XP1={X 100.0000,Y 200.0000,Z 300.0000,A 10.0000,B 20.0000,C 30.0000,E1 0.0" in dat
    assert src.startswith("DEF lf_calib( )") and src.rstrip().endswith("END") and "PTP XP2" in src
    y = F.easy_handeye_yaml(T[0])
    assert "eye_on_hand: false" in y and "  x: 0.1\n" in y and "  qw: " in y


@pytest.mark.parametrize("name", sorted(ROBOTS))
def test_robots_from_toml_reach_their_cell(name):
    robot = load_robot(name)
    s = robot_scene(robot)
    A = s.Z @ s.T_SO_nominal @ np.linalg.inv(s.X)
    q = inverse_kinematics(A, robot)
    assert np.abs(forward_kinematics(q, robot) - A).max() < 1e-6
    assert robot.repeatability_mm > 0 and robot.noise.translation_mm > 0


def test_ur5e_dh_zero_pose():
    # UR5e at q = 0 (DH): x = a2 + a3, y = -(d4 + d6), z = d1 - d5
    T = forward_kinematics(np.zeros(6), load_robot("ur5e"))
    assert np.allclose(T[:3, 3], [-425.0 - 392.2, -(133.3 + 99.6), 162.5 - 99.7])


def _csv(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


BAD = {
    "units": ("q.csv", "pose,x,y,z,qw,qx,qy,qz\n1,0,0,0,1,0,0,0\n"),
    "row 3, field A": ("p.csv", "pose,X,Y,Z,A,B,C\n1,0,0,0,0,0,0\n2,0,0,0,nan,0,0\n"),
    "duplicate pose id": ("p.csv", "pose,X,Y,Z,A,B,C\n1,0,0,0,0,0,0\n1,0,0,0,0,0,0\n"),
    "orthonormal": ("p.json", json.dumps({"schema_version": 1, "kind": "robot_poses", "units": "mm", "poses": [
        {"pose": "1", "matrix": [[1.001, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]})),
    "quaternion norm": ("q.csv", "# units: mm\npose,x,y,z,qw,qx,qy,qz\n1,0,0,0,0.9,0,0,0\n"),
    "units: 'inch'": ("q.csv", "# units: inch\npose,x,y,z,qw,qx,qy,qz\n1,0,0,0,1,0,0,0\n"),
}


@pytest.mark.parametrize("needle", sorted(BAD))
def test_bad_pose_files_one_line(tmp_path, needle):
    name, text = BAD[needle]
    p = _csv(tmp_path, name, text)
    with pytest.raises(ConfigError) as e:
        F.read_robot_poses(p)
    msg = str(e.value)
    assert needle in msg and str(p) in msg and "\n" not in msg


BAD_WFS = {
    "complete radial order": "pose," + ",".join(f"Z{k}" for k in range(1, 15)) + "\n1" + ",0" * 14 + "\n",
    "row 3: 13 Zernike modes": "pose," + ",".join(f"Z{k}" for k in range(1, 16)) + "\n1" + ",0" * 15
                               + "\n2" + ",0" * 13 + "\n",
    "field Z4": "pose," + ",".join(f"Z{k}" for k in range(1, 16)) + "\n1,0,0,0,NaN" + ",0" * 11 + "\n",
    "field pupil_radius_mm": "# pupil_radius_mm: -1\npose," + ",".join(f"Z{k}" for k in range(1, 16)) + "\n1"
                             + ",0" * 15 + "\n",
}


@pytest.mark.parametrize("needle", sorted(BAD_WFS))
def test_bad_wfs_files_one_line(tmp_path, needle):
    p = _csv(tmp_path, "w.csv", BAD_WFS[needle])
    with pytest.raises(ConfigError) as e:
        F.read_wfs(p)
    assert needle in str(e.value) and "\n" not in str(e.value)


def test_write_bundle_is_all_or_none(tmp_path):
    out = tmp_path / "o"
    F.write_bundle(out, {"a.txt": "1", "b.txt": "2"})
    with pytest.raises(TypeError):
        F.write_bundle(out, {"a.txt": "new", "c.txt": object()})  # fails half-way
    assert (out / "a.txt").read_text() == "1" and not (out / "c.txt").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["o"]


def test_cli_calibrate_bad_ids_one_line(tmp_path):
    w = _csv(tmp_path, "w.csv", "pose," + ",".join(f"Z{k}" for k in range(1, 16)) + "\n"
             + "".join(f"{i}" + ",0" * 15 + "\n" for i in range(1, 5)))
    r = _csv(tmp_path, "r.csv", "pose,X,Y,Z,A,B,C\n" + "".join(f"p{i},0,0,0,0,0,0\n" for i in range(1, 5)))
    res = run_cli("calibrate", "extended_polynomial", "-m", str(w), "-r", str(r), "-o", str(tmp_path / "cal"), "--json")
    out, err, code = res.stdout, res.stderr, res.returncode
    assert code == 2 and out == ""
    assert err.startswith("error: ") and err.count("\n") == 1 and "ids" in err
    assert not (tmp_path / "cal").exists()
