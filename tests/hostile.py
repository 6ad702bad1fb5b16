"""Shared pieces of the hostile-input suite: in-process CLI calls, the outcome rule, and
hypothesis strategies for hostile values.

The rule (issue 12): a command either succeeds, or exits 2 with exactly one ``error:``
line on stderr; never a traceback, never another exit status (1 is reserved for
"ran, but the result failed its check", e.g. an unprintable export).
"""

from __future__ import annotations

import io
import json
import math
import os
from contextlib import redirect_stderr, redirect_stdout

import numpy as np

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from lensforge.cli import main
from lensforge.optics.pose import pose_to_matrix

# CI keeps hypothesis small; LENSFORGE_HOSTILE=campaign runs the long campaign.
settings.register_profile("hostile-ci", max_examples=6, deadline=None, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
settings.register_profile("hostile-campaign", max_examples=200, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
PROFILE = "hostile-campaign" if os.environ.get("LENSFORGE_HOSTILE") == "campaign" else "hostile-ci"


def cli(*args) -> tuple[int, str, str]:
    """Run ``lensforge ARGS`` in this process: (exit status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            main([str(a) for a in args])
            code = 0
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    return code, out.getvalue(), err.getvalue()


def assert_clean(code: int, err: str, allowed=(0, 2)) -> None:
    """Success, or exit 2 with one ``error:`` line (the last line), or (where allowed) exit 3 with
    one ``error: model check failed ...`` line; never a traceback."""
    assert "Traceback" not in err, err[-3000:]
    assert code in allowed, f"exit {code}: {err[-2000:]}"
    errors = [ln for ln in err.splitlines() if ln.startswith("error:")]
    if code == 3:
        assert len(errors) == 1 and errors[0].startswith("error: model check failed"), err[-2000:]
        assert err.rstrip().splitlines()[-1] == errors[0], err[-2000:]
    elif code == 2:
        assert len(errors) == 1, err[-2000:]
        assert err.rstrip().splitlines()[-1].startswith("error:"), err[-2000:]
        assert len(errors[0]) > len("error: ") + 5, errors[0]
    else:
        assert not errors, err[-2000:]


def assert_one_line_error(exc: BaseException) -> None:
    msg = str(exc)
    assert msg and "\n" not in msg.strip(), repr(msg)


# hostile scalars for file fields (JSON-able; TOML drops None)
hostile_values = st.one_of(
    st.none(), st.booleans(),
    st.integers(min_value=-10**6, max_value=10**6), st.sampled_from([0, -1, 10**18, 10**400, -10**400]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([1e300, -1e300, 1e-300, math.nan, math.inf, -math.inf, 0.0, -0.0]),
    st.text(max_size=6), st.sampled_from(["1.0", "0", "nan", "", "material", "front"]),
    st.lists(st.integers(-3, 3), max_size=3), st.dictionaries(st.text(max_size=2), st.integers(), max_size=2),
)

# hostile command-line option values
hostile_args = st.one_of(
    st.sampled_from(["-1", "0", "1", "2", "-0", "nan", "inf", "-inf", "1e9", "1e300", "-1e300", "1e-300",
                     "abc", "", " ", "1.0", "9" * 30, "/nonexistent/dir/x", ".", "..", "/", "\u00e9",
                     "paper:nope", "1,2,3", "a=1:2", "x" * 300]),
    st.integers(-10**12, 10**12).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.text(alphabet=st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"), max_size=10),
)


def mutate(doc, path, value):
    """A deep copy of ``doc`` with the value at ``path`` (keys / indices) replaced."""
    import copy

    d = copy.deepcopy(doc)
    cur = d
    for k in path[:-1]:
        cur = cur[k]
    cur[path[-1]] = value
    return d


def leaf_paths(doc, prefix=()):
    """Every path to a scalar or list leaf of a nested dict/list (lists of numbers: each entry too)."""
    out = []
    if isinstance(doc, dict):
        for k, v in doc.items():
            out.append(prefix + (k,))
            out.extend(leaf_paths(v, prefix + (k,)))
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:4]):
            out.append(prefix + (i,))
            out.extend(leaf_paths(v, prefix + (i,)))
    return out


def corrupt(data: bytes, how: str, where: float) -> bytes:
    """A damaged file: truncated, BOM-prefixed, garbage bytes spliced in, or NUL-filled."""
    k = int(where * len(data))
    if how == "truncate":
        return data[:k]
    if how == "bom":
        return b"\xef\xbb\xbf" + data
    if how == "garbage":
        return data[:k] + bytes([0xFF, 0xFE, 0x00, 0x80, 0xC3]) + data[k:]
    if how == "nul":
        return b"\x00" * max(1, k)
    return data


def poses_file(path, mutate=None):
    """A valid POSES.json (8 well-spread poses, exact AX = ZB); ``mutate(doc)`` may spoil it."""
    rng = np.random.default_rng(1)
    A = [pose_to_matrix(np.r_[rng.normal(0, 50, 3), rng.normal(0, 0.4, 3)]).tolist() for _ in range(8)]
    X = pose_to_matrix(np.r_[1.0, 2.0, 30.0, 0.1, 0.0, 0.2])
    Z = pose_to_matrix(np.r_[500.0, 10.0, 300.0, 0.0, 0.3, 0.0])
    B = [(np.linalg.inv(Z) @ np.array(a) @ X).tolist() for a in A]
    doc = {"units": "mm", "A": A, "B": B}
    if mutate:
        mutate(doc)
    path.write_text(json.dumps(doc))
    return path


_SESSION: dict = {}  # the bench commands' session files, built once per test process


def session_files() -> dict:
    """A small honest session of the extended-polynomial lens as designed (6 poses), written
    once per process into a temporary folder: {robot_poses.csv, wfs_zernike.csv, truth.json}."""
    if not _SESSION:
        import tempfile

        from lensforge.calibration import formats
        from lensforge.calibration.session import load_design_lens, plan
        from lensforge.verification.session_sim import simulate_session

        lens, bench = load_design_lens(BENCH_LENS)
        p = plan(lens, bench=bench, n=6, seed=0, tolerances="none")
        s = simulate_session(lens, tolerances=None, seed=7, bench=bench, session_plan=p)
        _SESSION.update(formats.write_bundle(tempfile.mkdtemp(prefix="lensforge-hostile-"), s.files()))
    return _SESSION


BENCH_LENS = "extended_polynomial"  # every DOF observable: the bench commands need one
BENCH_COMMANDS = ("plan", "calibrate", "estimate", "simulate-session", "budget")


def base_args(cmd, tmp):
    """A cheap, valid invocation of each command (hostile options are added to it)."""
    if cmd in ("calibrate", "estimate"):
        f = session_files()
        if cmd == "estimate":
            return [BENCH_LENS, "-m", f["wfs_zernike.csv"], "--pose", "1"]
        return [BENCH_LENS, "-m", f["wfs_zernike.csv"], "-r", f["robot_poses.csv"], "--method", "two-stage",
                "--no-progress", "-o", tmp / "cal"]
    if cmd == "plan":
        return [BENCH_LENS, "-n", "6", "-t", "none", "-o", tmp / "plan"]
    if cmd == "simulate-session":
        return [BENCH_LENS, "-t", "none", "-n", "6", "-o", tmp / "ss"]
    if cmd == "budget":
        return [BENCH_LENS, "-n", "2", "--poses", "8", "--workers", "0", "--relative-to-noise", "3",
                "--no-progress", "-o", tmp / "bu"]
    return {
        "evaluate": ["spherical"],
        "compare": ["spherical"],
        "design": ["--method", "nelder-mead", "--max-evals", "12", "-o", tmp / "d.json", "--no-progress"],
        "plot": ["spherical", "-o", tmp / "plots"],
        "export": ["spherical", "--stl", "--no-slicer", "--chord-tol", "0.05", "-o", tmp / "ex"],
        "estimate-study": ["spherical", "--trials", "2", "-o", tmp / "est"],
        "scenario": ["spherical", "--runs", "1", "--poses", "random", "-o", tmp / "sc"],
        "handeye": [poses_file(tmp / "poses.json")],
        "study": ["spherical", "-n", "2", "--poses", "8", "--workers", "0", "--no-progress", "-o", tmp / "st"],
    }[cmd]


def command_options(cmd):
    """(option name, is_flag) of each option of a command, from its click definition."""
    import typer

    from lensforge.cli import app

    group = typer.main.get_command(app)
    return [(p.opts[0], bool(getattr(p, "is_flag", False))) for p in group.commands[cmd].params
            if p.param_type_name == "option" and p.opts[0] != "--help"]


def mapped(pid: int, name: str) -> bool:
    """``name`` (a shared library) is loaded in ``pid`` or a process below it: the command
    runs in the child of the ``lensforge`` supervisor process."""
    from pathlib import Path

    from lensforge.interrupts import descendants

    for p in [pid, *descendants(pid)]:
        try:
            if name in Path(f"/proc/{p}/maps").read_text():
                return True
        except OSError:
            continue
    return False
