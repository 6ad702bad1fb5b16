"""KUKA $POS_ACT logs: columns or the controller's E6POS text, ids or times."""

import numpy as np
import pytest

from lensforge.calibration.formats import matrix_to_xyzabc, read_robot_poses, xyzabc_to_matrix
from lensforge.calibration.kuka_log import assign_by_time, parse_e6pos
from lensforge.errors import ConfigError

POSES = np.array([[512.25, -480.5, 998.0, -80.0, -89.5, 80.0], [500.0, -500.0, 1000.0, 10.0, 20.0, -30.0],
                  [490.125, -510.0, 1001.5, 179.0, 0.5, -179.5]])


def test_columns_any_order_with_status_and_turn(tmp_path):
    p = tmp_path / "log.csv"
    rows = ["# $POS_ACT, $TOOL = $NULLFRAME", "# tool: $NULLFRAME", "Pose;A;B;C;X;Y;Z;S;T;E1"]
    for i, v in enumerate(POSES, start=1):
        rows.append(";".join([f"{i:02d}"] + [repr(float(a)) for a in v[3:]] + [repr(float(a)) for a in v[:3]]
                             + ["6", "27", "0.0"]))
    p.write_bytes("\r\n".join(rows).encode("cp1252"))
    t = read_robot_poses(p)  # sniffed as a KUKA log (S, T columns)
    assert t.ids == ("01", "02", "03")
    np.testing.assert_allclose(t.T, xyzabc_to_matrix(POSES), rtol=0, atol=1e-12)
    from lensforge.calibration.kuka_log import read_kuka_log

    np.testing.assert_allclose(read_kuka_log(p)["status_turn"], [[6, 27]] * 3)


def test_e6pos_text_column(tmp_path):
    assert parse_e6pos("{E6POS: X 1.5, Y -2, Z 3E2, A 0.0, B 90.0, C -1.25, S 6, T 27, E1 0.0}") == {
        "X": 1.5, "Y": -2.0, "Z": 300.0, "A": 0.0, "B": 90.0, "C": -1.25, "S": 6.0, "T": 27.0, "E1": 0.0}
    p = tmp_path / "log.csv"
    rows = ["pose,POS_ACT"]
    for i, v in enumerate(POSES, start=1):
        rows.append(f'{i},"{{E6POS: X {v[0]}, Y {v[1]}, Z {v[2]}, A {v[3]}, B {v[4]}, C {v[5]}, S 2, T 35, E1 0.0}}"')
    p.write_text("\n".join(rows))
    t = read_robot_poses(p, 'kuka_log')
    np.testing.assert_allclose(matrix_to_xyzabc(t.T)[:, :3], POSES[:, :3], atol=1e-9)
    np.testing.assert_allclose(t.T, xyzabc_to_matrix(POSES), atol=1e-12)
    p.write_text('pose,POS_ACT\n1,"{E6POS: X 1, Y 2, Z 3, A 0, B 0, S 2}"\n')
    with pytest.raises(ConfigError, match="row 2, field POS_ACT: C missing"):
        read_robot_poses(p, 'kuka_log')


def test_times_match_the_wfs_files(tmp_path):
    p = tmp_path / "log.csv"
    rows = ["time,X,Y,Z,A,B,C"]
    stamps = ["2026-12-01T10:00:00", "2026-12-01T10:00:10", "2026-12-01T10:00:20"]
    for ts, v in zip(stamps, POSES):
        rows.append(",".join([ts] + [repr(float(a)) for a in v]))
    p.write_text("\n".join(rows))
    t = read_robot_poses(p)
    assert t.times is not None and np.allclose(np.diff(t.times), 10.0)
    t0 = t.times[0]
    m = assign_by_time(t, {"7": t0 + 10.5, "3": t0 - 1.0, "9": t0 + 100.0})
    assert m.ids == ("7", "3")  # 9 has no record within 5 s: left to the matcher to report
    np.testing.assert_allclose(m.T[0], xyzabc_to_matrix(POSES[1]), atol=1e-12)
    with pytest.raises(ConfigError, match="nearest to both pose"):
        assign_by_time(t, {"1": t0 + 9.0, "2": t0 + 11.0})


def test_log_errors(tmp_path):
    p = tmp_path / "log.csv"
    p.write_text("# tool: tool_data[3]\npose,X,Y,Z,A,B,C\n1,0,0,0,0,0,0\n")
    with pytest.raises(ConfigError, match=r"row 1, field tool.*\$TOOL = \$NULLFRAME"):
        read_robot_poses(p, 'kuka_log')
    p.write_text("pose;X;Y;Z;A;B;C\n1;0,5;0;0;0;0;0\n")
    with pytest.raises(ConfigError, match="row 2, field X: '0,5' uses a decimal comma"):
        read_robot_poses(p, 'kuka_log')
    p.write_text("X,Y,Z,A,B,C\n0,0,0,0,0,0\n")
    with pytest.raises(ConfigError, match="no 'pose' or 'time' column"):
        read_robot_poses(p, 'kuka_log')
    p.write_text("pose,X,Y,Z,A,B,C\n1,0,0,0,0,400,0\n")
    with pytest.raises(ConfigError, match="row 2, field B: 400 deg is beyond the plausible 360 deg"):
        read_robot_poses(p, 'kuka_log')
    p.write_text("pose,X,Y,Z,A,B,C,S,T\n1,0,0,0,0,0,0,2,3\n1,0,0,0,0,0,0,2,3\n")
    with pytest.raises(ConfigError, match="duplicate pose id '1'"):
        read_robot_poses(p)
