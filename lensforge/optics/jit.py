"""The numba kernels' surroundings: the compile notice and the thread count they run on.

Compile notice: say so on stderr when numba compiles a kernel (first run after install, or after
an edit). Compiled kernels are cached on disk (``cache=True``), so later runs load them in well
under a second and print nothing. The notice hangs on numba's event API: the ``numba:compile``
event fires only on a real compile, never on a cache load, so the message is never wrong.

Threads: the trace kernels are ``parallel=True`` (``prange`` over chunks of rays), but they run
on ONE thread unless ``LENSFORGE_NUM_THREADS`` asks for more. One S(p) is a ~2.5 ms job: a second
thread saves ~8 % on an idle machine (2.77 -> 2.56 ms, issue 20) and costs 10x when another process
holds a core (36 ms: every parallel region waits for the descheduled thread). Parallelism pays at
the pose, lens and study level, where studies already run one single-threaded trial per Dask
worker. A big single job (a dense trace, one long design run on an otherwise idle machine) may set
``LENSFORGE_NUM_THREADS=2`` (or more). The count never exceeds what numba allows the calling thread
(``numba.get_num_threads()``, i.e. ``NUMBA_NUM_THREADS`` or a caller's ``numba.set_num_threads``),
so a trial pinned to one thread (``verification.runner.single_threaded``) stays on one. The kernels
write one element per iteration with no reductions: results do not depend on the thread count.
"""

from __future__ import annotations

import os
import sys
import time
from contextlib import contextmanager

import numba
from numba.core import event

from ..errors import ConfigError

__all__ = ["compile_notice", "kernel_threads", "requested_threads", "THREADS_ENV"]

THREADS_ENV = "LENSFORGE_NUM_THREADS"


class _Notice(event.Listener):
    """Print one line when the outermost compile starts, finish it when it ends."""

    def __init__(self, what: str, stream):
        self.what = what
        self.stream = stream
        self.depth = 0
        self.t0 = 0.0

    def _write(self, text: str) -> None:
        try:
            self.stream.write(text)
            self.stream.flush()
        except (OSError, ValueError):  # closed or broken stderr: the notice is only a courtesy
            pass

    def on_start(self, ev) -> None:
        if self.depth == 0:
            self.t0 = time.perf_counter()
            self._write(f"compiling the {self.what} (once; cached for later runs) ...")
        self.depth += 1

    def on_end(self, ev) -> None:
        self.depth -= 1
        if self.depth == 0:
            self._write(f" done in {time.perf_counter() - self.t0:.1f} s\n")


@contextmanager
def compile_notice(what: str = "ray-trace kernels", stream=None):
    """Within this block, announce any numba compile on ``stream`` (default stderr)."""
    with event.install_listener("numba:compile", _Notice(what, stream or sys.stderr)):
        yield


def requested_threads() -> int:
    """Threads the trace kernels may use, from ``LENSFORGE_NUM_THREADS`` (default 1).

    Returns
    -------
    int
        The requested count, >= 1 (capped later by numba's own limit).

    Raises
    ------
    ConfigError
        When the variable is set but is not a positive integer.
    """
    raw = os.environ.get(THREADS_ENV, "").strip()
    if not raw:
        return 1
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if n < 1:
        raise ConfigError(f"{THREADS_ENV}={raw!r}: the trace kernels' thread count must be a positive integer "
                          f"(unset it for the default, 1)")
    return n


@contextmanager
def kernel_threads():
    """Within this block numba runs on ``min(requested_threads(), numba.get_num_threads())``
    threads (one by default), and on what it ran before afterwards (numba's count is per
    calling thread)."""
    before = numba.get_num_threads()
    n = min(requested_threads(), before)
    if n == before:
        yield
        return
    numba.set_num_threads(n)
    try:
        yield
    finally:
        numba.set_num_threads(before)
