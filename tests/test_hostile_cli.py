"""Hostile command lines, in process: every option of every command gets random types,
NaN/inf, huge or negative numbers, garbage text. The only allowed outcomes: success, or
exit 2 with one ``error:`` line (see tests/hostile.py), or for the commands with a model
check (calibrate, estimate, handeye) exit 3 with one ``error: model check failed`` line.
The bench commands (plan, calibrate, estimate, simulate-session, budget) run on a small
honest session (``hostile.session_files``). Output-target cases: a path under
a file, onto an existing folder, a read-only folder; outputs appear all or none.
"""

from __future__ import annotations

import os

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hostile import PROFILE, assert_clean, base_args, cli, command_options, hostile_args

settings.load_profile(PROFILE)

FAST = ["evaluate", "compare", "handeye", "estimate-study", "study", "design", "calibrate", "estimate"]
SLOW = ["plot", "export", "scenario", "plan", "simulate-session", "budget"]
MODEL_CHECKED = ("calibrate", "estimate", "handeye")  # may exit 3: a fit that fails its model check


def _hostile_run(cmd, tmp, option, value):
    name, is_flag = option
    if name == "--scheduler":
        return  # connecting to random addresses waits for the Dask timeout (20 s)
    if name == "--workers" and value.strip().lstrip("+").isdigit() and int(value) > 0:
        return  # starting worker processes is the slow suite's job
    args = base_args(cmd, tmp) + ([name] if is_flag else [name, value])
    cwd = os.getcwd()
    os.chdir(tmp)  # a hostile value taken as a relative output path lands in tmp
    try:
        code, out, err = cli(cmd, *args)
    finally:
        os.chdir(cwd)
    assert_clean(code, err, allowed=(0, 1, 2) if cmd == "export" else (0, 2, 3) if cmd in MODEL_CHECKED else (0, 2))
    if code == 2 and cmd in ("plot", "export", "estimate-study"):  # outputs all or none
        folder = args[args.index("-o") + 1] if "-o" in args else None
        if folder is not None and os.path.isdir(folder):
            assert not [f for f in os.listdir(folder) if not f.startswith(".")] or code == 0


@pytest.mark.parametrize("cmd", FAST + [pytest.param(c, marks=pytest.mark.slow) for c in SLOW])
@given(data=st.data())
def test_hostile_options(tmp_path_factory, cmd, data):
    option = data.draw(st.sampled_from(command_options(cmd)), label="option")
    value = data.draw(hostile_args, label="value")
    _hostile_run(cmd, tmp_path_factory.mktemp(cmd), option, value)


@pytest.mark.parametrize("value", ["-1", "abc"])
@pytest.mark.parametrize("cmd", SLOW)
def test_hostile_options_slow_commands_smoke(tmp_path, cmd, value):
    """CI: each slow command with its first options set to a hostile value."""
    for option in command_options(cmd)[:2]:
        _hostile_run(cmd, tmp_path, option, value)


def test_bare_lensforge_has_one_error_line():
    code, out, err = cli()
    assert code == 2
    assert [ln for ln in err.splitlines() if ln.startswith("error:")] == \
        ["error: no command given; pick one of the commands listed above"]


def test_unknown_command_and_option():
    for args in (["nope"], ["evaluate", "--nope"], ["study"], ["evaluate", "spherical", "--bench"]):
        code, _, err = cli(*args)
        assert_clean(code, err)
        assert code == 2


@pytest.mark.parametrize("cmd, args", [
    ("study", ["spherical", "-n", "1000000000", "--workers", "0"]),
    ("study", ["spherical", "-n", "2", "--seed", "-1", "--workers", "0"]),
    ("estimate-study", ["spherical", "--trials", "2", "--seed", "-5"]),
    ("estimate-study", ["spherical", "--trials", "100000000000"]),
    ("export", ["spherical", "--chord-tol", "1e-9"]),
    ("design", ["--seed", "-1"]),
])
def test_resource_guards_and_seeds(tmp_path, cmd, args):
    code, _, err = cli(cmd, *args, "-o", tmp_path / "out")
    assert_clean(code, err)
    assert code == 2
    assert "limit" in err or "--seed" in err, err


@pytest.mark.parametrize("cmd, args, target", [
    ("design", ["--max-evals", "12"], "d.json"),
    ("plot", ["spherical"], "plots"),
    ("estimate-study", ["spherical", "--trials", "2"], "est"),
    ("scenario", ["spherical", "--runs", "1"], "sc"),
    ("study", ["spherical", "-n", "2", "--workers", "0"], "st"),
    ("export", ["spherical", "--stl", "--no-slicer"], "ex"),
])
def test_output_under_a_file_and_onto_a_folder(tmp_path, cmd, args, target):
    f = tmp_path / "file"
    f.write_text("x")
    code, _, err = cli(cmd, *args, "-o", f / target)
    assert_clean(code, err)
    assert code == 2 and "is a file" in err, err
    if target.endswith(".json"):  # a file target onto an existing folder
        (tmp_path / "dir").mkdir()
        code, _, err = cli(cmd, *args, "-o", tmp_path / "dir")
        assert code == 2 and "is a folder" in err, err
    else:  # a folder target that is a file
        code, _, err = cli(cmd, *args, "-o", f)
        assert code == 2 and "is a file" in err, err
    assert f.read_text() == "x"
