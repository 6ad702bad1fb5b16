import numpy as np
import pytest

import lensforge as lf


@pytest.fixture(scope="session")
def bench():
    return lf.Bench.default()


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def run_cli(*args, cwd=None):
    """Run ``python -m lensforge ARGS`` in a subprocess (stdout, stderr, returncode)."""
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "lensforge", *args], capture_output=True, text=True,
                          timeout=300, cwd=cwd)


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
