"""Ctrl-C for the command line: one line ``error: interrupted``, exit status 130, within 2 s.

:func:`sigint_guard` (used by ``cli.main``) replaces Python's SIGINT handler for the
duration of a command. The first SIGINT raises :class:`Interrupted` in the main
thread -- a ``BaseException`` that is *not* ``KeyboardInterrupt``, so click, Dask and
tornado do not turn it into "Aborted!" or log it -- and starts a watchdog: if the
command has not unwound after ``grace_s`` (a stuck cleanup, a blocking call), the
watchdog ends the process itself. A second SIGINT ends it at once (one that follows the
first within ``REPEAT_S`` is the same press, delivered twice). Ending means:
the message, child processes (Dask workers) killed quietly, ``os._exit(130)``; the
study store needs no cleanup (one SQLite transaction per trial: an interrupted
transaction rolls back on the next open), and staged outputs are removed by their
own ``finally`` blocks while the exception unwinds.

An interrupt that arrives while a C extension initialises is seen only when that
initialisation returns: CPython runs signal handlers between bytecodes, in the main thread,
with the GIL. OCP's initialisation (the first seconds of ``export``) holds the GIL for its
whole length -- measured 1-8 s depending on load -- so neither a handler nor a watchdog
thread can run, and importing it in a worker thread does not help either. Hence
:func:`supervise` (used by the ``lensforge`` executable): the process forks at once; the
child runs the command, and the parent -- a small process that only waits -- answers
Ctrl-C within ``grace_s`` whatever the child is doing. The parent is the one that prints
``error: interrupted`` (the supervised child exits 130 silently), so the line appears
exactly once, after the child's cleanup.

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

__all__ = ["Interrupted", "sigint_guard", "hard_exit", "supervise", "descendants", "alive",
           "EXIT_INTERRUPTED"]

EXIT_INTERRUPTED = 130  # 128 + SIGINT, the shell convention
INTERRUPTED_LINE = "error: interrupted"
_SUPERVISOR_ENV = "_LENSFORGE_SUPERVISOR"  # set in the supervised child: its supervisor's pid
REPEAT_S = 0.5  # a second SIGINT this soon after the first is the same press (terminal + forwarded copy)


class Interrupted(BaseException):
    """The user pressed Ctrl-C (SIGINT) while a lensforge command ran."""


def _parent_map() -> dict[int, int]:
    """{pid: parent pid} of every process, from /proc (empty where there is no /proc)."""
    parent_of = {}
    try:
        entries = os.listdir("/proc")
    except OSError:  # pragma: no cover - not Linux
        return parent_of
    for e in entries:
        if e.isdigit():
            try:
                with open(f"/proc/{e}/stat", "rb") as fh:
                    parent_of[int(e)] = int(fh.read().decode(errors="replace").rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
    return parent_of


def _child_pids() -> list[int]:
    """Our direct child processes (Dask workers, multiprocessing's resource tracker)."""
    me = os.getpid()
    return [p for p, pp in _parent_map().items() if pp == me]


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


def _supervised() -> bool:
    """True in the child of :func:`supervise` (whose parent prints the interrupt line)."""
    return os.environ.get(_SUPERVISOR_ENV) == str(os.getppid())


def _write_line(message: str) -> None:
    try:
        os.write(2, (message + "\n").encode())
    except OSError:  # pragma: no cover - stderr closed
        pass


def hard_exit(code: int = EXIT_INTERRUPTED, message: str = INTERRUPTED_LINE) -> None:
    """Print ``message`` on stderr, kill child processes, and end the process now (no atexit).
    Under :func:`supervise` the interrupt line is left to the supervisor (printed once)."""
    try:
        sys.stdout.flush()
    except Exception:  # pragma: no cover - closed pipe
        pass
    if not (code == EXIT_INTERRUPTED and message == INTERRUPTED_LINE and _supervised()):
        _write_line(message)
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
def sigint_guard(grace_s: float = 1.2):
    """Within the block, SIGINT raises :class:`Interrupted`; yields a callable telling whether
    one arrived. Does nothing outside the main thread (signal handlers live there)."""
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is signal.SIG_IGN):  # the caller chose to ignore Ctrl-C (nohup, `cmd &`)
        yield lambda: False
        return
    st = _State(grace_s)

    def handler(signum, frame):
        now = time.monotonic()
        if st.count and now - st.first_t < REPEAT_S:
            return  # the same press delivered twice (terminal and supervisor); already unwinding
        st.count += 1
        if st.count > 1:
            hard_exit()
        st.first_t = now
        threading.Thread(target=st.watchdog, name="lensforge-sigint-watchdog", daemon=True).start()
        raise Interrupted()

    old = signal.signal(signal.SIGINT, handler)
    try:
        yield lambda: st.count > 0
    finally:
        signal.signal(signal.SIGINT, old)


# ----------------------------------------------------------------------------- supervisor

_FORWARDED = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def descendants(root: int) -> list[int]:
    """All processes below ``root`` (children first level first), from /proc."""
    parent_of = _parent_map()
    out, frontier = [], [root]
    while frontier:
        kids = [p for p, pp in parent_of.items() if pp in frontier]
        out += kids
        frontier = kids
    return out


def alive(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            return fh.read().decode(errors="replace").rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def _die_with_parent(parent: int) -> None:
    """In the child: SIGKILL when the supervisor dies (prctl PR_SET_PDEATHSIG), so killing the
    ``lensforge`` process (even with SIGKILL) ends the command as before."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):  # pragma: no cover - not Linux
        pass
    if os.getppid() != parent:  # the supervisor died before prctl took effect
        os._exit(EXIT_INTERRUPTED)


def supervise(grace_s: float = 1.5) -> None:
    """Fork; return in the child, which runs the command. The parent never returns: it waits
    for the child and exits with its status. On SIGINT it forwards the signal, waits up to
    ``grace_s`` for the child to unwind (its own watchdog ends it after 1.2 s), then kills the
    child and everything below it; either way it prints ``error: interrupted`` once and exits
    130. SIGTERM and SIGHUP are forwarded and the child's fate is mirrored.

    Does nothing (the command runs in this process) without fork, outside the main thread,
    when threads already run, when SIGINT is ignored (``nohup``), or with
    ``LENSFORGE_NO_SUPERVISOR=1`` (profilers, debuggers).
    """
    if (not hasattr(os, "fork") or not sys.platform.startswith("linux")
            or os.environ.get("LENSFORGE_NO_SUPERVISOR") or threading.active_count() > 1
            or threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is signal.SIG_IGN):
        return
    watch = set(_FORWARDED) | {signal.SIGCHLD}
    for f in (sys.stdout, sys.stderr):
        try:
            f.flush()
        except Exception:  # pragma: no cover - closed pipe
            pass
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, watch)  # nothing lost between fork and wait
    parent = os.getpid()
    try:
        pid = os.fork()
    except OSError:  # pragma: no cover - out of processes: run unsupervised
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
        return
    if pid == 0:
        _die_with_parent(parent)
        os.environ[_SUPERVISOR_ENV] = str(parent)
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)  # a pending Ctrl-C now reaches the caller's guard
        return
    _wait_for_child(pid, watch, grace_s)


def _wait_for_child(pid: int, watch: set, grace_s: float) -> None:
    """The supervisor's loop (never returns)."""
    deadline = None
    first_int = None
    while True:
        try:
            done, status = os.waitpid(pid, os.WNOHANG)
        except ChildProcessError:  # pragma: no cover - reaped elsewhere
            done, status = pid, 0
        if done == pid:
            code = os.waitstatus_to_exitcode(status)
            if code == EXIT_INTERRUPTED or (deadline is not None and code < 0):
                _write_line(INTERRUPTED_LINE)
                os._exit(EXIT_INTERRUPTED)
            if code < 0:  # killed by a signal: end the same way, so the caller sees it
                signal.signal(-code, signal.SIG_DFL)
                signal.pthread_sigmask(signal.SIG_UNBLOCK, {-code})
                os.kill(os.getpid(), -code)
                os._exit(128 - code)  # pragma: no cover - the signal did not end us
            os._exit(code)
        now = time.monotonic()
        if deadline is not None and now >= deadline:
            _kill_tree(pid)
            os.waitpid(pid, 0)  # SIGKILL: soon
            _write_line(INTERRUPTED_LINE)
            os._exit(EXIT_INTERRUPTED)
        wait = 0.1 if deadline is None else max(0.005, min(0.1, deadline - now))
        info = signal.sigtimedwait(watch, wait)
        if info is None or info.si_signo == signal.SIGCHLD:
            continue
        sig = info.si_signo
        if sig == signal.SIGINT:
            if first_int is not None and now - first_int >= REPEAT_S:  # pressed again: end now
                _kill_tree(pid)
                deadline = now
                continue
            if first_int is None:
                first_int = now
                deadline = now + grace_s
        try:
            os.kill(pid, sig)  # the child's guard ignores the copy of a press it already saw
        except ProcessLookupError:  # pragma: no cover - already gone
            pass


def _kill_tree(pid: int) -> None:
    for p in [*descendants(pid), pid]:
        try:
            os.kill(p, signal.SIGKILL)
        except OSError:
            pass
