"""The ``lensforge`` supervisor (lensforge.interrupts.supervise): Ctrl-C is answered even while
the command's process is stuck in one C call that holds the GIL (as OCP's initialisation
does), the command's exit status passes through, and the command dies with its supervisor.

Latencies are asserted generously (< 5 s); the figures are benchmarks/sigint_latency.py's.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lensforge.interrupts import alive

ROOT = Path(__file__).resolve().parents[1]

_PROG = """
import os, sys
from lensforge.interrupts import Interrupted, hard_exit, sigint_guard, supervise
with sigint_guard():
    try:
        supervise()
        print(os.getpid(), flush=True)
        {body}
    except Interrupted:
        hard_exit()
"""
# one C call holding the GIL for minutes: no Python signal handler or thread runs meanwhile
_STUCK = "sum(range(10**13))"


def _start(body: str, **env):
    return subprocess.Popen([sys.executable, "-c", _PROG.format(body=body)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(ROOT), **env})


def _child_pid(p) -> int:
    return int(p.stdout.readline())


def _gone(pid: int, timeout: float = 5.0) -> bool:
    t0 = time.monotonic()
    while alive(pid):
        if time.monotonic() - t0 > timeout:
            return False
        time.sleep(0.05)
    return True


def test_ctrl_c_while_the_command_holds_the_gil():
    p = _start(_STUCK)
    child = _child_pid(p)
    assert child != p.pid  # the command runs in the supervisor's child
    time.sleep(0.3)
    t0 = time.monotonic()
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    dt = time.monotonic() - t0
    assert p.returncode == 130 and err == "error: interrupted\n", err
    assert dt < 5.0, f"took {dt:.2f} s"
    assert _gone(child)


def test_ctrl_c_unwinds_a_responsive_command_and_prints_once():
    p = _start("import time\n        while True: time.sleep(0.01)")
    _child_pid(p)
    os.kill(p.pid, signal.SIGINT)  # like a terminal: the supervisor forwards, the child unwinds
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130 and err == "error: interrupted\n", err


# death by SIGHUP, its default action restored first: under nohup the test runner, and so the child, ignore it
@pytest.mark.parametrize("body, code", [("sys.exit(3)", 3), ("sys.exit(0)", 0),
                                        ("import signal; signal.signal(1, signal.SIG_DFL); os.kill(os.getpid(), 1)",
                                         -1)])
def test_exit_status_passes_through(body, code):
    p = _start(body)
    _, err = p.communicate(timeout=60)
    assert p.returncode == code, err
    assert "error:" not in err


@pytest.mark.parametrize("to", ["supervisor", "command"])
def test_sigterm_unwinds_like_ctrl_c(to):
    """SIGTERM (kill, a batch scheduler): one line 'error: terminated', status 143, and the
    command unwinds (a staged output's finally block runs) instead of dying in place."""
    p = _start("import time\n        try:\n            time.sleep(60)\n        finally:\n"
               "            print('unwound', flush=True)")
    child = _child_pid(p)
    time.sleep(0.2)
    os.kill(p.pid if to == "supervisor" else child, signal.SIGTERM)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 143 and err == "error: terminated\n", err
    assert "unwound" in out


def test_sigterm_is_handled_when_ctrl_c_is_ignored():
    """A background job (`cmd &` in a script) or a batch scheduler ignores SIGINT: Ctrl-C stays
    ignored, but SIGTERM still unwinds with 'error: terminated' and 143 (it once killed silently)."""
    body = "import time\n        try:\n            time.sleep(60)\n        finally:\n            print('unwound', flush=True)"
    p = subprocess.Popen([sys.executable, "-c", _PROG.format(body=body)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)},
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    assert _child_pid(p) == p.pid  # unsupervised: SIGINT is ignored
    time.sleep(0.2)
    p.send_signal(signal.SIGINT)
    time.sleep(0.3)
    assert p.poll() is None  # still ignored
    p.send_signal(signal.SIGTERM)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 143 and err == "error: terminated\n", (p.returncode, err)
    assert "unwound" in out


def test_sigkill_of_the_command_is_one_line_not_a_traceback():
    """signal.signal(SIGKILL, ...) raises OSError: the supervisor once printed a traceback here."""
    p = _start("os.kill(os.getpid(), 9)")
    _, err = p.communicate(timeout=60)
    assert "Traceback" not in err
    assert err.count("error:") == 1 and err.startswith("error: killed by SIGKILL"), err
    assert p.returncode == 137


def test_oom_kill_is_named_out_of_memory(monkeypatch):
    """The OOM killer's SIGKILL: 'error: out of memory ...', exit 2 (a problem too large)."""
    from lensforge import interrupts

    monkeypatch.setattr(interrupts, "_memory_total_bytes", lambda: 8e9)
    monkeypatch.setattr(interrupts, "_oom_kills", lambda: None)
    line, rc = interrupts._sigkill_line(6e9, None)
    assert rc == 2 and line.startswith("error: out of memory") and "6.0 GB" in line
    line, rc = interrupts._sigkill_line(1e9, None)
    assert rc == 137
    monkeypatch.setattr(interrupts, "_oom_kills", lambda: 4)
    assert interrupts._sigkill_line(1e8, 3)[1] == 2  # the cgroup counted a new OOM kill


def test_sigkill_of_the_supervisor_ends_the_command():
    p = _start(_STUCK)
    child = _child_pid(p)
    p.kill()
    p.communicate(timeout=60)
    assert _gone(child)


def test_no_supervisor_when_disabled():
    p = _start("sys.exit(0)", LENSFORGE_NO_SUPERVISOR="1")
    out, _ = p.communicate(timeout=60)
    assert int(out) == p.pid and p.returncode == 0


def test_a_signal_after_the_outputs_are_committed_does_not_interrupt(tmp_path):
    """Outputs all or nothing (issue 23): once fileio.staged_dir has renamed them into place, a
    first Ctrl-C lets the command finish (exit 0) instead of 'error: interrupted' beside a
    complete output folder (as a late Ctrl-C during export did); before the commit it
    interrupts as always, and nothing is left."""
    for when, code, left in (("after", 0, ["out"]), ("before", 130, [])):
        signal_in_block = when == "before"
        body = ("from lensforge.fileio import staged_dir\n        import time, pathlib, signal\n"
                f"        with staged_dir(pathlib.Path({str(tmp_path / when / 'out')!r})) as st:\n"
                "            (st.tmp / 'a.txt').write_text('x')\n"
                + ("            os.kill(os.getpid(), signal.SIGINT); time.sleep(5)\n" if signal_in_block else
                   "        os.kill(os.getpid(), signal.SIGINT); time.sleep(0.3)\n        print('finished', flush=True)"))
        (tmp_path / when).mkdir()
        p = _start(body)
        _child_pid(p)
        out, err = p.communicate(timeout=60)
        assert p.returncode == code, (when, err)
        assert sorted(os.listdir(tmp_path / when)) == left, when
        assert ("finished" in out) == (code == 0)


def test_staged_output_is_complete_or_absent_under_sigterm(tmp_path):
    """SIGTERM while a staged folder is being filled: the command unwinds, exit 143, and neither the
    output folder nor a hidden temporary one is left."""
    body = ("from lensforge.fileio import staged_dir\n        import time, pathlib\n"
            f"        with staged_dir(pathlib.Path({str(tmp_path / 'out')!r})) as st:\n"
            "            (st.tmp / 'a.txt').write_text('x')\n            time.sleep(60)")
    p = _start(body)
    _child_pid(p)
    time.sleep(0.5)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 143 and err == "error: terminated\n", err
    assert os.listdir(tmp_path) == []


def test_a_killed_command_leaves_no_staged_temp(tmp_path):
    # a supervised command killed before its own cleanup can run (SIGKILL here; a Ctrl-C while OCP's C
    # initialisation holds the interpreter ends the same way): the supervisor deletes the temp folder
    # and temp file the command staged, and nothing else
    import subprocess
    import sys
    import textwrap

    keep = tmp_path / "keep.txt"
    keep.write_text("mine")
    script = textwrap.dedent(f"""
        import os, signal
        from lensforge.interrupts import supervise
        from lensforge.fileio import staged_dir, write_atomic
        supervise()
        cm = staged_dir({str(tmp_path / "out")!r})
        st = cm.__enter__()
        (st.tmp / "part.txt").write_text("partial")
        import tempfile
        from lensforge.interrupts import note_staging
        fd, half = tempfile.mkstemp(dir={str(tmp_path)!r}, prefix=".f.", suffix=".tmp")
        note_staging(half)
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert r.returncode != 0 and "SIGKILL" in r.stderr, r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt"]


def test_interrupt_inside_a_weakref_callback_is_one_line():
    """A signal whose handler runs inside a callback where Python ignores exceptions (importlib's
    module-lock weakref callback, seen once in CI during Ctrl-C at startup) ends the command with
    the one line and 130, not an "Exception ignored in" traceback."""
    prog = """
import os, signal, sys, time, weakref
from lensforge.interrupts import sigint_guard
class A: pass
with sigint_guard():
    a = A()
    def cb(ref):
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(1000): pass
    r = weakref.ref(a, cb)
    del a
    time.sleep(10)
print("not reached")
"""
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-c", prog], capture_output=True, text=True, timeout=30,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert p.returncode == 130, p
    assert p.stderr.strip() == "error: interrupted", p.stderr
    assert "not reached" not in p.stdout
    assert time.monotonic() - t0 < 8
