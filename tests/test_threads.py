"""The trace kernels run on one numba thread unless LENSFORGE_NUM_THREADS asks for more (optics/jit.py)."""

import numba
import numpy as np
import pytest

import lensforge as lf
from lensforge.errors import ConfigError
from lensforge.optics.jit import THREADS_ENV, kernel_threads
from lensforge.optics.trace import trace_rays


def _inside(monkeypatch, value):
    if value is None:
        monkeypatch.delenv(THREADS_ENV, raising=False)
    else:
        monkeypatch.setenv(THREADS_ENV, value)
    with kernel_threads():
        return numba.get_num_threads()


def test_default_is_one_thread_and_the_count_is_restored(monkeypatch):
    before = numba.get_num_threads()
    assert _inside(monkeypatch, None) == 1
    assert numba.get_num_threads() == before


def test_env_raises_the_count_up_to_numbas_limit(monkeypatch):
    cap = numba.config.NUMBA_NUM_THREADS
    assert _inside(monkeypatch, "2") == min(2, numba.get_num_threads())
    assert _inside(monkeypatch, str(cap + 5)) == numba.get_num_threads()
    numba.set_num_threads(1)  # a caller pinned to one thread (a study trial) stays on one
    try:
        assert _inside(monkeypatch, "2") == 1
    finally:
        numba.set_num_threads(cap)


@pytest.mark.parametrize("bad", ["0", "-1", "two", "1.5"])
def test_bad_value_is_one_config_error(monkeypatch, bad):
    with pytest.raises(ConfigError, match=THREADS_ENV):
        _inside(monkeypatch, bad)


def test_trace_does_not_depend_on_the_thread_count(monkeypatch):
    bench, lens = lf.Bench.default(), lf.paper_lens("zernike")
    g = np.linspace(-1.5, 1.5, 23)
    uv = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    poses = np.array([[0.1, -0.2, 0.3, 0.01, -0.02, 0.03], np.zeros(6)])
    runs = []
    for n in ("1", "2"):
        monkeypatch.setenv(THREADS_ENV, n)
        r = trace_rays(bench, lens, poses, uv, pose_derivatives=True)
        runs.append((r.xy, r.direction, r.all_derivatives, r.status))
    for a, b in zip(*runs):
        np.testing.assert_array_equal(a, b)  # one element per iteration, no reductions: bit-identical
