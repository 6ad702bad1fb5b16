"""Hostile command lines, in process: every option of every command gets random types,
NaN/inf, huge or negative numbers, garbage text. The only allowed outcomes: success, or
exit 2 with one ``error:`` line (see tests/hostile.py). Output-target cases: a path under
a file, onto an existing folder, a read-only folder; outputs appear all or none.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import typer
from hypothesis import given, settings
from hypothesis import strategies as st

from hostile import PROFILE, assert_clean, cli, hostile_args
from lensforge.cli import app
from lensforge.optics.pose import pose_to_matrix

settings.load_profile(PROFILE)

GROUP = typer.main.get_command(app)


def _poses(path):
    rng = np.random.default_rng(1)
    A = [pose_to_matrix(np.r_[rng.normal(0, 50, 3), rng.normal(0, 0.4, 3)]).tolist() for _ in range(8)]
    X = pose_to_matrix(np.r_[1.0, 2.0, 30.0, 0.1, 0.0, 0.2])
    Z = pose_to_matrix(np.r_[500.0, 10.0, 300.0, 0.0, 0.3, 0.0])
    B = [(np.linalg.inv(Z) @ np.array(a) @ X).tolist() for a in A]
    path.write_text(json.dumps({"units": "mm", "A": A, "B": B}))
    return path


def _base(cmd, tmp):
    """A cheap, valid invocation of each command (hostile options are added to it)."""
    return {
        "evaluate": ["spherical"],
        "compare": ["spherical"],
        "design": ["--method", "nelder-mead", "--max-evals", "12", "-o", tmp / "d.json", "--no-progress"],
        "plot": ["spherical", "-o", tmp / "plots"],
        "export": ["spherical", "--stl", "--no-slicer", "--chord-tol", "0.05", "-o", tmp / "ex"],
        "estimate-study": ["spherical", "--trials", "2", "-o", tmp / "est"],
        "scenario": ["spherical", "--runs", "1", "--poses", "random", "-o", tmp / "sc"],
        "handeye": [_poses(tmp / "poses.json")],
        "study": ["spherical", "-n", "2", "--poses", "8", "--workers", "0", "--no-progress", "-o", tmp / "st"],
    }[cmd]


FAST = ["evaluate", "compare", "handeye", "estimate-study", "study", "design"]
SLOW = ["plot", "export", "scenario"]


def _options(cmd):
    """(option name, is_flag) of a command, from its click definition."""
    out = []
    for p in GROUP.commands[cmd].params:
        if p.param_type_name == "option" and p.opts[0] != "--help":
            out.append((p.opts[0], bool(getattr(p, "is_flag", False))))
    return out


def _hostile_run(cmd, tmp, option, value):
    name, is_flag = option
    args = _base(cmd, tmp)
    args = args + ([name] if is_flag else [name, value])
    if name in ("--workers",) or (name == "--scheduler"):
        args = [a for a in args]  # still in process: a bad value fails before any cluster starts
        if name == "--workers":
            try:
                if int(value) > 0:
                    return  # starting worker processes is the slow suite's job
            except ValueError:
                pass
        else:
            return  # connecting to random addresses takes the Dask timeout (20 s)
    cwd = os.getcwd()
    os.chdir(tmp)  # a hostile value taken as a relative output path lands in tmp
    try:
        code, out, err = cli(cmd, *args)
    finally:
        os.chdir(cwd)
    assert_clean(code, err, allowed=(0, 1, 2) if cmd == "export" else (0, 2))
    if code == 2 and cmd in ("plot", "export", "estimate-study"):  # outputs all or none
        folder = args[args.index("-o") + 1] if "-o" in args else None
        if folder is not None and os.path.isdir(folder):
            assert not [f for f in os.listdir(folder) if not f.startswith(".")] or code == 0


@pytest.mark.parametrize("cmd", FAST)
@given(data=st.data())
def test_hostile_options(tmp_path_factory, cmd, data):
    option = data.draw(st.sampled_from(_options(cmd)), label="option")
    value = data.draw(hostile_args, label="value")
    _hostile_run(cmd, tmp_path_factory.mktemp(cmd), option, value)


@pytest.mark.slow
@pytest.mark.parametrize("cmd", SLOW)
@given(data=st.data())
def test_hostile_options_slow_commands(tmp_path_factory, cmd, data):
    option = data.draw(st.sampled_from(_options(cmd)), label="option")
    value = data.draw(hostile_args, label="value")
    _hostile_run(cmd, tmp_path_factory.mktemp(cmd), option, value)


@pytest.mark.parametrize("value", ["-1", "abc"])
@pytest.mark.parametrize("cmd", SLOW)
def test_hostile_options_slow_commands_smoke(tmp_path, cmd, value):
    """CI: each slow command with its first options set to a hostile value."""
    for option in _options(cmd)[:2]:
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
