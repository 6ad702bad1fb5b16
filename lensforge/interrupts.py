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

__all__ = ["Interrupted", "Terminated", "sigint_guard", "committing", "hard_exit", "supervise", "descendants", "alive",
           "EXIT_INTERRUPTED", "EXIT_TERMINATED", "OUT_OF_MEMORY_LINE", "note_staging"]

EXIT_INTERRUPTED = 130  # 128 + SIGINT, the shell convention
EXIT_TERMINATED = 143  # 128 + SIGTERM
INTERRUPTED_LINE = "error: interrupted"
TERMINATED_LINE = "error: terminated"
OUT_OF_MEMORY_LINE = ("error: out of memory: the system killed the command (SIGKILL) at {gb:.1f} GB; "
                      "reduce the problem size (lenses, poses, mesh tolerance) or free memory")
KILLED_LINE = "error: killed by SIGKILL from outside lensforge (not out of memory); run the command again"
_SUPERVISOR_ENV = "_LENSFORGE_SUPERVISOR"  # set in the supervised child: its supervisor's pid
_STAGING_FD_ENV = "_LENSFORGE_STAGING_FD"  # the supervised child's pipe to its supervisor: staged temp paths
REPEAT_S = 0.5  # a second SIGINT this soon after the first is the same press (terminal + forwarded copy)


class Interrupted(BaseException):
    """The user pressed Ctrl-C (SIGINT) while a lensforge command ran."""


class Terminated(Interrupted):
    """The process got SIGTERM (``kill``, a scheduler, systemd): unwound like Ctrl-C, exit 143."""


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


_SIGNAL_EXIT = {EXIT_INTERRUPTED: INTERRUPTED_LINE, EXIT_TERMINATED: TERMINATED_LINE}


def hard_exit(code: int | None = None, message: str | None = None) -> None:
    """Print ``message`` on stderr, kill child processes, and end the process now (no atexit).
    Default: the line and status of the signal that arrived (Ctrl-C: 130, SIGTERM: 143; see
    :func:`sigint_guard`). Under :func:`supervise` the signal's line is left to the supervisor
    (printed once)."""
    if code is None:
        code = _last_signal_exit[0]
    if message is None:
        message = _SIGNAL_EXIT.get(code, INTERRUPTED_LINE)
    try:
        sys.stdout.flush()
    except Exception:  # pragma: no cover - closed pipe
        pass
    if not (_SIGNAL_EXIT.get(code) == message and _supervised()):
        _write_line(message)
    _kill_children()
    os._exit(code)


# the exit status of the signal that ended the command (set by the guard's handlers; read by
# hard_exit() called without arguments). A one-element list: the process has one signal state.
_last_signal_exit = [EXIT_INTERRUPTED]
# True once a command's outputs are in place (``committing``): a first Ctrl-C / SIGTERM after that
# is not an interrupt -- the command only prints what it wrote and ends with status 0
_committed = [False]


@contextmanager
def committing():
    """Around the rename that puts a command's outputs in place (``fileio.staged_dir``,
    ``formats.write_bundle``): SIGINT and SIGTERM wait until it is done, and once it is, the
    outputs are complete, so a first signal that follows no longer interrupts: the command
    ends normally (status 0) within the supervisor's grace. Outside the main thread it only
    runs the block."""
    main = threading.current_thread() is threading.main_thread()
    sigs = {signal.SIGINT, signal.SIGTERM}
    old = signal.pthread_sigmask(signal.SIG_BLOCK, sigs) if main else None
    try:
        yield
        _committed[0] = True
    finally:
        if old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


class _State:
    """Per-guard state (one instance per ``sigint_guard`` call)."""

    def __init__(self, grace_s: float):
        self.grace_s = grace_s
        self.count = 0
        self.first_t = None
        self.code = EXIT_INTERRUPTED
        self.deferred = None  # when a signal arrived after the outputs were committed

    def watchdog(self) -> None:
        time.sleep(self.grace_s)
        hard_exit(self.code)


@contextmanager
def sigint_guard(grace_s: float = 1.2):
    """Within the block, SIGINT raises :class:`Interrupted` and SIGTERM :class:`Terminated`
    (unwound the same way, so staged outputs are removed; exit 143 with ``error: terminated``);
    yields a callable telling whether one arrived. Does nothing outside the main thread (signal
    handlers live there); SIGINT ignored by the caller (nohup, `cmd &`) stays ignored, and so
    does an ignored SIGTERM (a SIGTERM that is not ignored is handled even then: a background job
    or a batch scheduler ignores Ctrl-C, and its SIGTERM ended the command silently)."""
    int_ignored = signal.getsignal(signal.SIGINT) is signal.SIG_IGN  # the caller chose to ignore Ctrl-C
    if (threading.current_thread() is not threading.main_thread()
            or (int_ignored and signal.getsignal(signal.SIGTERM) is signal.SIG_IGN)):
        yield lambda: False
        return
    st = _State(grace_s)
    _committed[0] = False  # a new command: nothing of it is written yet

    def handler(signum, frame):
        now = time.monotonic()
        if _committed[0] and not st.count:
            # the outputs are in place: let the command finish (exit 0; see committing()), but not for
            # longer than the grace, and a second press still ends it
            if st.deferred is not None and now - st.deferred >= REPEAT_S:
                hard_exit(EXIT_TERMINATED if signum == signal.SIGTERM else EXIT_INTERRUPTED)
            if st.deferred is None:
                st.deferred = now
                st.code = EXIT_TERMINATED if signum == signal.SIGTERM else EXIT_INTERRUPTED
                _last_signal_exit[0] = st.code
                threading.Thread(target=st.watchdog, name="lensforge-sigint-watchdog", daemon=True).start()
            return
        if st.count and now - st.first_t < REPEAT_S:
            return  # the same press delivered twice (terminal and supervisor); already unwinding
        st.count += 1
        if st.count > 1:
            hard_exit(st.code)
        st.first_t = now
        st.code = EXIT_TERMINATED if signum == signal.SIGTERM else EXIT_INTERRUPTED
        _last_signal_exit[0] = st.code
        threading.Thread(target=st.watchdog, name="lensforge-sigint-watchdog", daemon=True).start()
        raise Terminated() if signum == signal.SIGTERM else Interrupted()

    def unraisable(info):
        # the handler's exception can land where Python ignores exceptions (a weakref callback
        # inside importlib's module locks, a __del__) and prints "Exception ignored in" with a
        # traceback; the interrupt is then lost. End the command the way the watchdog would.
        if isinstance(info.exc_value, Interrupted):
            hard_exit(st.code)
        old_hook(info)

    old_hook = sys.unraisablehook
    sys.unraisablehook = unraisable
    old = None if int_ignored else signal.signal(signal.SIGINT, handler)
    old_term = signal.getsignal(signal.SIGTERM)
    if old_term is not signal.SIG_IGN:
        signal.signal(signal.SIGTERM, handler)
    try:
        yield lambda: st.count > 0
    finally:
        sys.unraisablehook = old_hook
        if not int_ignored:
            signal.signal(signal.SIGINT, old)
        if old_term is not signal.SIG_IGN:
            signal.signal(signal.SIGTERM, old_term if old_term is not None else signal.SIG_DFL)


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
    oom_before = _oom_kills()
    staging_r, staging_w = os.pipe()  # the child names its staged temp files here (``note_staging``)
    try:
        pid = os.fork()
    except OSError:  # pragma: no cover - out of processes: run unsupervised
        os.close(staging_r)
        os.close(staging_w)
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
        return
    if pid == 0:
        _die_with_parent(parent)
        os.close(staging_r)
        os.environ[_SUPERVISOR_ENV] = str(parent)
        os.environ[_STAGING_FD_ENV] = f"{os.getpid()}:{staging_w}"
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)  # a pending Ctrl-C now reaches the caller's guard
        return
    os.close(staging_w)
    os.set_blocking(staging_r, False)
    _wait_for_child(pid, watch, grace_s, oom_before, staging_r)


def note_staging(path) -> None:
    """Tell the supervisor (``supervise``) about a temporary output ``path`` this command creates,
    so that a command killed before its own cleanup runs (a Ctrl-C while OCP's C initialisation
    holds the interpreter, the watchdog's hard exit, SIGKILL) leaves no temp file or folder: the
    supervisor deletes the named paths that still exist once the child is gone by a signal.
    Nothing happens outside a supervised command (or in its worker processes)."""
    v = os.environ.get(_STAGING_FD_ENV, "")
    pid, _, fd = v.partition(":")
    if not fd or pid != str(os.getpid()):
        return
    try:
        os.write(int(fd), (os.path.abspath(os.fsdecode(os.fspath(path))) + "\0").encode("utf-8", "surrogateescape"))
    except (OSError, ValueError):  # pragma: no cover - a full pipe (64 KiB of paths) or a closed one
        pass


def _remove_staged(fd: int | None) -> None:
    """Delete the temp paths the killed child named (``note_staging``) that still exist."""
    import shutil

    if fd is None:
        return
    data = b""
    while True:
        try:
            chunk = os.read(fd, 65536)
        except BlockingIOError:
            break
        except OSError:  # pragma: no cover
            break
        if not chunk:
            break
        data += chunk
    for raw in data.split(b"\0"):
        if not raw:
            continue
        p = raw.decode("utf-8", "surrogateescape")
        try:
            if os.path.isdir(p) and not os.path.islink(p):
                shutil.rmtree(p, ignore_errors=True)
            elif os.path.lexists(p):
                os.unlink(p)
        except OSError:  # pragma: no cover - gone meanwhile, or not ours to delete
            pass


def _cgroup_file(name: str) -> str | None:
    """Text of this process's cgroup v2 file ``name`` (e.g. memory.events), or None."""
    try:
        with open("/proc/self/cgroup") as fh:
            rel = next((ln.split(":", 2)[2].strip() for ln in fh if ln.startswith("0::")), None)
        if rel is None:
            return None
        with open(f"/sys/fs/cgroup{rel.rstrip('/')}/{name}") as fh:
            return fh.read()
    except (OSError, StopIteration, IndexError):
        return None


def _oom_kills() -> int | None:
    """The cgroup's count of out-of-memory kills (memory.events ``oom_kill``), or None."""
    text = _cgroup_file("memory.events")
    if text is None:
        return None
    for ln in text.splitlines():
        k, _, v = ln.partition(" ")
        if k == "oom_kill" and v.strip().isdigit():
            return int(v)
    return None


def _memory_total_bytes() -> float:
    """The memory the command may use: the cgroup's limit, else the machine's RAM."""
    text = _cgroup_file("memory.max")
    if text and text.strip().isdigit():
        return float(text.strip())
    try:
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (OSError, ValueError):  # pragma: no cover
        return float("inf")


def _sigkill_line(peak_bytes: float, oom_before: int | None) -> tuple[str, int]:
    """(message, exit status) for a command killed by SIGKILL: the kernel's out-of-memory
    killer (the cgroup counted an OOM kill, or the command held over half the memory) is
    named as a user's problem size (exit 2); any other SIGKILL came from outside (137)."""
    after = _oom_kills()
    oom = (oom_before is not None and after is not None and after > oom_before) or \
        peak_bytes > 0.5 * _memory_total_bytes()
    if oom:
        return OUT_OF_MEMORY_LINE.format(gb=peak_bytes / 1e9), 2
    return KILLED_LINE, 128 + int(signal.SIGKILL)


def _wait_for_child(pid: int, watch: set, grace_s: float, oom_before: int | None = None,
                    staging_fd: int | None = None) -> None:
    """The supervisor's loop (never returns)."""
    deadline = None
    first_int = None
    term = False  # the signal that started the deadline was SIGTERM (status 143, "error: terminated")
    while True:
        try:
            done, status, usage = os.wait4(pid, os.WNOHANG)
        except ChildProcessError:  # pragma: no cover - reaped elsewhere
            done, status, usage = pid, 0, None
        if done == pid:
            code = os.waitstatus_to_exitcode(status)
            if code in (EXIT_INTERRUPTED, EXIT_TERMINATED) or code < 0:  # ended by a signal: its leftovers
                _remove_staged(staging_fd)
            if code in (EXIT_INTERRUPTED, EXIT_TERMINATED) or (deadline is not None and code < 0):
                final = EXIT_TERMINATED if (term or code == EXIT_TERMINATED) else EXIT_INTERRUPTED
                _write_line(_SIGNAL_EXIT[final])
                os._exit(final)
            if code == -signal.SIGKILL:  # SIGKILL cannot be re-raised on us (signal.signal refuses it)
                peak = (usage.ru_maxrss * 1024.0) if usage is not None else 0.0  # Linux: kB
                line, rc = _sigkill_line(peak, oom_before)
                _write_line(line)
                os._exit(rc)
            if code < 0:  # killed by another signal: end the same way, so the caller sees it
                try:
                    signal.signal(-code, signal.SIG_DFL)
                    signal.pthread_sigmask(signal.SIG_UNBLOCK, {-code})
                    os.kill(os.getpid(), -code)
                except (OSError, ValueError):  # pragma: no cover - an uncatchable signal
                    pass
                os._exit(128 - code)  # pragma: no cover - the signal did not end us
            os._exit(code)
        now = time.monotonic()
        if deadline is not None and now >= deadline:
            _kill_tree(pid)
            os.waitpid(pid, 0)  # SIGKILL: soon
            _remove_staged(staging_fd)
            final = EXIT_TERMINATED if term else EXIT_INTERRUPTED
            _write_line(_SIGNAL_EXIT[final])
            os._exit(final)
        wait = 0.1 if deadline is None else max(0.005, min(0.1, deadline - now))
        info = signal.sigtimedwait(watch, wait)
        if info is None or info.si_signo == signal.SIGCHLD:
            continue
        sig = info.si_signo
        if sig == signal.SIGTERM and deadline is None:
            term = True
            deadline = now + grace_s
        if sig == signal.SIGINT:
            if first_int is not None and now - first_int >= REPEAT_S:  # pressed again: end now
                _kill_tree(pid)
                deadline = now
                continue
            if first_int is None:
                first_int = now
                if deadline is None:
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
