"""Say so on stderr when numba compiles a kernel (first run after install, or after an edit).

Compiled kernels are cached on disk (``cache=True``), so later runs load them in well under a
second and print nothing. The notice hangs on numba's event API: the ``numba:compile`` event
fires only on a real compile, never on a cache load, so the message is never wrong.
"""

from __future__ import annotations

import sys
import time
from contextlib import contextmanager

from numba.core import event

__all__ = ["compile_notice"]


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
