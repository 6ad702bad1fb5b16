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

When the process starts with SIGINT ignored (``nohup``, ``cmd &`` in a script) it stays
ignored, as Unix tools do. Library code never needs this module: without the guard, Ctrl-C is the usual
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


def _child_pids() -> list[int]:
    """Our direct child processes (Dask workers, multiprocessing's resource tracker), from /proc."""
    me, pids = os.getpid(), []
    try:
        entries = os.listdir("/proc")
    except OSError:  # pragma: no cover - not Linux
        return []
    for e in entries:
        if not e.isdigit():
            continue
        try:
            with open(f"/proc/{e}/stat", "rb") as fh:
                stat = fh.read().decode(errors="replace")
            if int(stat.rsplit(")", 1)[1].split()[1]) == me:
                pids.append(int(e))
        except (OSError, ValueError, IndexError):
            continue
    return pids


def _kill_children() -> None:
    """Kill our child processes without letting them print anything (they hold no results:
    every finished trial is already in the store)."""
    pids = set(_child_pids())
    try:
        import multiprocessing

        pids |= {p.pid for p in multiprocessing.active_children() if p.pid}
    except Exception:  # pragma: no cover
        pass
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:  # pragma: no cover - already gone
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
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is signal.SIG_IGN):  # the caller chose to ignore Ctrl-C (nohup, `cmd &`)
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
