"""First contact (issue 13): cheap CLI import, one kernel specialisation, a compile notice."""

import io
import subprocess
import sys

import numba as nb
import numpy as np

import lensforge as lf
from lensforge.optics import trace
from lensforge.optics.jit import compile_notice
from lensforge.optics.shack_hartmann import ForwardModel


def test_cli_import_loads_no_heavy_module():
    code = ("import sys, lensforge.cli; "
            "print(' '.join(m for m in ('numba', 'scipy', 'matplotlib', 'trimesh', 'dask', 'cadquery') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == ""


def test_read_only_inputs_reuse_the_one_compiled_kernel(bench):
    lens = lf.paper_lens("zernike")
    fm = ForwardModel(bench, lens)
    targets = np.array(fm.pupil.centres)
    ro = targets.copy()
    ro.flags.writeable = False
    a = trace.aim_rays(bench, lens, np.zeros((2, 6)), targets, kernel=fm.kernel)
    b = trace.aim_rays(bench, lens, np.zeros((2, 6)), ro, u0=np.broadcast_to(targets, (2, len(targets), 2)),
                       kernel=fm.kernel)
    assert len(trace._aim.signatures) == 1
    np.testing.assert_array_equal(a[1], b[1])


def test_compile_notice_says_when_numba_compiles_and_stays_quiet_otherwise():
    @nb.njit
    def f(x):
        return x + 1

    buf = io.StringIO()
    with compile_notice("test kernel", stream=buf):
        f(1.0)
    first = buf.getvalue()
    assert first.startswith("compiling the test kernel") and first.rstrip().endswith(" s")
    assert first.count("\n") == 1
    buf2 = io.StringIO()
    with compile_notice("test kernel", stream=buf2):
        f(2.0)  # already compiled
    assert buf2.getvalue() == ""
