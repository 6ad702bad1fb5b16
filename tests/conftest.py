import numpy as np
import pytest

import lensforge as lf


@pytest.fixture(scope="session")
def bench():
    return lf.Bench.default()


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def check_json_output(command, stdout):
    """Validate a command's ``--json`` stdout against its documented schema (docs/json.md);
    returns the parsed object."""
    import json

    data = json.loads(stdout)
    try:
        import jsonschema
    except ImportError:  # the test extra installs it; without it only the JSON itself is checked
        return data
    from lensforge.schemas import load_schema

    jsonschema.validate(data, load_schema(command))
    return data


def run_cli(*args, cwd=None):
    """Run ``python -m lensforge ARGS`` in a subprocess (stdout, stderr, returncode). A
    successful ``--json`` run is checked against the command's JSON schema on the way."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "lensforge", *map(str, args)], capture_output=True, text=True,
                       timeout=300, cwd=cwd)
    from lensforge.schemas import COMMANDS

    if r.returncode == 0 and "--json" in args and args and args[0] in COMMANDS:
        check_json_output(args[0], r.stdout)
    return r


def run_cli_inprocess(monkeypatch, capsys, *args):
    """Run the CLI in this process (shares traced kernels): (exit code, stdout, stderr)."""
    import sys

    from lensforge.cli import main

    monkeypatch.setattr(sys, "argv", ["lensforge", *map(str, args)])
    code = 0
    try:
        main()
    except SystemExit as e:
        code = e.code or 0
    out = capsys.readouterr()
    return code, out.out, out.err
