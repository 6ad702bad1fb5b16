"""Hypothesis fuzzing of the bench commands' inputs (issue 23, item 6): plan, calibrate,
estimate, simulate-session and budget, in process.

tests/test_hostile_cli.py fuzzes every command's *options*; here the *files* they read are
spoiled: one cell of the WFS or robot-pose CSV replaced by a hostile token, a row dropped or
duplicated, columns swapped, the bytes truncated, BOM-prefixed, garbage-spliced or NUL-filled
(calibrate, estimate); one field of the robot TOML (plan, simulate-session) or of the tolerance
TOML (simulate-session, budget) replaced by a hostile value. The outcome rule is
``hostile.assert_clean``: success, exit 2 with one ``error:`` line, or (calibrate, estimate)
exit 3 with one ``error: model check failed`` line; never a traceback. And the outputs follow
the verdict: nothing on exit 2; on exit 3 the diagnostics without ``easy_handeye.yaml``; on
exit 0 a valid result.

CI runs few examples (``hostile.PROFILE``); plan, simulate-session and budget cost seconds to
half a minute per example and are marked slow. ``LENSFORGE_FUZZ_EXAMPLES=N`` runs N examples
per test (the full run of the report).
"""

from __future__ import annotations

import json
import math
import os
import tomllib

import pytest
import tomli_w
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from hostile import BENCH_LENS, PROFILE, assert_clean, cli, corrupt, hostile_values, leaf_paths, mutate, session_files

settings.load_profile(PROFILE)
_N = os.environ.get("LENSFORGE_FUZZ_EXAMPLES")
FUZZ = settings(max_examples=int(_N), deadline=None, derandomize=False,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture]) if _N else \
    settings(deadline=None)

TOKENS = st.one_of(
    st.sampled_from(["nan", "inf", "-inf", "1e300", "-1e300", "1e-300", "1e400", "", " ", "abc", "1,5", "0", "-0",
                     "9" * 30, "0x10", "1 2", '"', "#", "\u00e9", "1e6", "-1e6", "1000", "0.001", "1", "99", "07"]),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**9, 10**9).map(str),
)
HOW = st.sampled_from(["truncate", "bom", "garbage", "nul"])


def _csv_edit(text: str, data) -> str:
    """One hostile edit of a CSV text (comment lines kept as they are)."""
    lines = text.splitlines()
    body = [i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")]
    op = data.draw(st.sampled_from(["cell", "cell", "cell", "drop", "dup", "swap", "bytes"]), label="op")
    if op == "bytes":
        how, where = data.draw(HOW, label="how"), data.draw(st.floats(0, 1), label="where")
        return corrupt(text.encode(), how, where).decode("utf-8", errors="surrogateescape")
    i = data.draw(st.sampled_from(body), label="line")
    cells = lines[i].split(",")
    if op == "cell":
        j = data.draw(st.integers(0, len(cells) - 1), label="column")
        cells[j] = data.draw(TOKENS, label="token")
        lines[i] = ",".join(cells)
    elif op == "drop":
        del lines[i]
    elif op == "dup":
        lines.insert(i, lines[i])
    else:
        j, k = data.draw(st.integers(0, len(cells) - 1), label="c1"), data.draw(st.integers(0, len(cells) - 1),
                                                                               label="c2")
        for n in body:
            c = lines[n].split(",")
            if max(j, k) < len(c):
                c[j], c[k] = c[k], c[j]
                lines[n] = ",".join(c)
    return "\n".join(lines) + "\n"


def _write_text(path, text: str):
    path.write_bytes(text.encode("utf-8", errors="surrogateescape"))
    return path


def _outputs_follow_the_verdict(code: int, out_dir) -> None:
    if code == 2:  # refused: all or none
        assert not out_dir.exists() or not [f for f in os.listdir(out_dir) if not f.startswith(".")]
    elif code == 3:  # diagnostics, never the file a cell would load
        d = json.loads((out_dir / "calibration.json").read_text())
        assert d["valid"] is False and not (out_dir / "easy_handeye.yaml").exists()
    else:
        d = json.loads((out_dir / "calibration.json").read_text())
        assert d["valid"] is True and (out_dir / "easy_handeye.yaml").exists()
        assert all(math.isfinite(v) for row in d["Z"]["matrix"] for v in row)


@FUZZ
@given(data=st.data(), which=st.sampled_from(["robot_poses.csv", "wfs_zernike.csv"]))
def test_calibrate_with_a_spoiled_file(tmp_path_factory, data, which):
    f = session_files()
    tmp = tmp_path_factory.mktemp("cal")
    spoiled = _write_text(tmp / which, _csv_edit(f[which].read_text(), data))
    m = spoiled if which == "wfs_zernike.csv" else f["wfs_zernike.csv"]
    r = spoiled if which == "robot_poses.csv" else f["robot_poses.csv"]
    code, _, err = cli("calibrate", BENCH_LENS, "-m", m, "-r", r, "--method", "two-stage", "--no-progress",
                       "-o", tmp / "out")
    event(f"exit {code}")
    assert_clean(code, err, allowed=(0, 2, 3))
    _outputs_follow_the_verdict(code, tmp / "out")


@FUZZ
@given(data=st.data(), pose=st.sampled_from(["1", "3", "6", "01", "0", "-1", "99", "", "nan", "1.0"]))
def test_estimate_with_a_spoiled_file(tmp_path_factory, data, pose):
    f = session_files()
    tmp = tmp_path_factory.mktemp("est")
    spoiled = _write_text(tmp / "w.csv", _csv_edit(f["wfs_zernike.csv"].read_text(), data))
    code, out, err = cli("estimate", BENCH_LENS, "-m", spoiled, "--pose", pose, "--json")
    event(f"exit {code}")
    assert_clean(code, err, allowed=(0, 2, 3))
    if code in (0, 3):  # a verdict with numbers: finite, and the model check's word
        d = json.loads(out)
        assert d["valid"] is (code == 0)
        assert all(math.isfinite(v) for v in d["pose"].values() if isinstance(v, float)), d["pose"]


def _robot_doc():
    from lensforge.calibration.robot import ROBOTS

    return tomllib.loads(ROBOTS["kr10_r1100_sixx"].read_text())


def _tolerance_doc():
    from lensforge.asbuilt.tolerances import DEFAULT_TOLERANCES_FILE

    return tomllib.loads(DEFAULT_TOLERANCES_FILE.read_text())


ROBOT_DOC = _robot_doc()
TOL_DOC = _tolerance_doc()


def _toml_file(path, doc, value, where):
    try:
        path.write_text(tomli_w.dumps(mutate(doc, where, value)))
    except (TypeError, ValueError):  # None or a mixed list: not expressible in TOML
        return None
    return path


@pytest.mark.slow
@FUZZ
@given(where=st.sampled_from(leaf_paths(ROBOT_DOC)), value=hostile_values)
def test_plan_with_a_spoiled_robot_file(tmp_path_factory, where, value):
    tmp = tmp_path_factory.mktemp("plan")
    robot = _toml_file(tmp / "robot.toml", ROBOT_DOC, value, where)
    if robot is None:
        return
    code, _, err = cli("plan", BENCH_LENS, "--robot", robot, "-n", "6", "-t", "none", "-o", tmp / "plan")
    event(f"exit {code}")
    assert_clean(code, err)
    if code == 0:
        assert (tmp / "plan" / "plan.json").exists()
    else:
        assert not (tmp / "plan").exists()


@pytest.mark.slow
@FUZZ
@given(which=st.sampled_from(["robot", "tolerances"]), data=st.data())
def test_simulate_session_with_a_spoiled_file(tmp_path_factory, which, data):
    tmp = tmp_path_factory.mktemp("ss")
    doc = ROBOT_DOC if which == "robot" else TOL_DOC
    where = data.draw(st.sampled_from(leaf_paths(doc)), label="where")
    f = _toml_file(tmp / f"{which}.toml", doc, data.draw(hostile_values, label="value"), where)
    if f is None:
        return
    opt = ["--robot", f] if which == "robot" else ["-t", f]
    code, _, err = cli("simulate-session", BENCH_LENS, *opt, "-n", "6", "-o", tmp / "ss")
    event(f"exit {code}")
    assert_clean(code, err)
    files = sorted(os.listdir(tmp / "ss")) if (tmp / "ss").exists() else []
    assert files == (["robot_poses.csv", "truth.json", "wfs_zernike.csv"] if code == 0 else []), files


@pytest.mark.slow
@FUZZ
@given(where=st.sampled_from(leaf_paths(TOL_DOC)), value=hostile_values)
def test_budget_with_a_spoiled_tolerance_file(tmp_path_factory, where, value):
    tmp = tmp_path_factory.mktemp("bu")
    f = _toml_file(tmp / "tol.toml", TOL_DOC, value, where)
    if f is None:
        return
    code, _, err = cli("budget", BENCH_LENS, "-t", f, "-n", "2", "--poses", "8", "--workers", "0",
                       "--relative-to-noise", "3", "--no-progress", "-o", tmp / "bu")
    event(f"exit {code}")
    assert_clean(code, err)
    if code != 0:
        assert not (tmp / "bu").exists() or not [x for x in os.listdir(tmp / "bu") if not x.startswith(".")]


@pytest.mark.parametrize("where, value", [
    (("ik_seeds_deg", 0, 0), 10**400), (("ik_seeds_deg", 0, 1), math.nan), (("reach_mm",), 10**400),
    (("repeatability_mm",), -10**400), (("joints", 0, "limits_deg", 0), 10**400),
    (("cell", "sensor_xyzabc", 0), 10**400),
])
def test_robot_file_numbers_beyond_floats_are_refused(tmp_path, where, value):
    """What the fuzzing of simulate-session found: a TOML integer beyond the float range (or a NaN
    IK seed) in the robot file raised OverflowError (a traceback); now one short line naming the field."""
    robot = _toml_file(tmp_path / "robot.toml", ROBOT_DOC, value, where)
    code, _, err = cli("plan", BENCH_LENS, "--robot", robot, "-n", "6", "-t", "none", "-o", tmp_path / "plan")
    assert_clean(code, err)
    line = err.rstrip().splitlines()[-1]
    assert code == 2 and where[0] in line and len(line) < 200, line
