"""Ctrl-C for the command line: one line ``error: interrupted``, exit status 130, within 2 s.

:func:`sigint_guard` (used by ``cli.main``) replaces Python's SIGINT handler for the
duration of a command. The first SIGINT raises :class:`Interrupted` in the main
thread -- a ``BaseException`` that is *not* ``KeyboardInterrupt``, so click, Dask and
tornado do not turn it into "Aborted!" or log it -- and starts a watchdog: if the
command has not unwound after ``grace_s`` (a stuck cleanup, a blocking call), the
watchdog ends the process itself. A second SIGINT ends it at once. Ending means:
the message, child processes (Dask workers) killed quietly, ``os._exit(130)``; the
study store needs no cleanup (one SQLite transaction per trial: an interrupted
transaction rolls back on the next open), and staged outputs are removed by their
own ``finally`` blocks while the exception unwinds.

An interrupt that arrives while a C extension initialises (e.g. OCP during the first
seconds of ``export``) is seen when that initialisation returns: CPython runs signal
handlers only between bytecodes.

Library code never needs this module: without the guard, Ctrl-C is the usual
KeyboardInterrupt.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from contextlib import contextmanager

__all__ = ["Interrupted", "sigint_guard", "hard_exit", "EXIT_INTERRUPTED"]

EXIT_INTERRUPTED = 130  # 128 + SIGINT, the shell convention


class Interrupted(BaseException):
    """The user pressed Ctrl-C (SIGINT) while a lensforge command ran."""


def _kill_children() -> None:
    """Kill our child processes (Dask workers) without letting them print anything."""
    try:
        import multiprocessing

        for p in multiprocessing.active_children():
            try:
                p.kill()
            except Exception:  # pragma: no cover - already gone
                pass
    except Exception:  # pragma: no cover
        pass


def hard_exit(code: int = EXIT_INTERRUPTED, message: str = "error: interrupted") -> None:
    """Print ``message`` on stderr, kill child processes, and end the process now (no atexit)."""
    try:
        sys.stdout.flush()
    except Exception:  # pragma: no cover - closed pipe
        pass
    try:
        os.write(2, (message + "\n").encode())
    except OSError:  # pragma: no cover - stderr closed
        pass
    _kill_children()
    os._exit(code)


class _State:
    """Per-guard state (not global: one instance per ``sigint_guard`` call)."""

    def __init__(self, grace_s: float):
        self.grace_s = grace_s
        self.count = 0
        self.first_t = None

    def watchdog(self) -> None:
        time.sleep(self.grace_s)
        hard_exit()


@contextmanager
def sigint_guard(grace_s: float = 1.5):
    """Within the block, SIGINT raises :class:`Interrupted`; yields a callable telling whether
    one arrived. Does nothing outside the main thread (signal handlers live there)."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: False
        return
    st = _State(grace_s)

    def handler(signum, frame):
        st.count += 1
        if st.count > 1:
            hard_exit()
        st.first_t = time.monotonic()
        threading.Thread(target=st.watchdog, name="lensforge-sigint-watchdog", daemon=True).start()
        raise Interrupted()

    old = signal.signal(signal.SIGINT, handler)
    try:
        yield lambda: st.count > 0
    finally:
        signal.signal(signal.SIGINT, old)
