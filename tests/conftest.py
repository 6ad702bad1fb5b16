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
