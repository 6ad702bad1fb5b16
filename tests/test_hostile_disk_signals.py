"""Full disks, read-only folders, Ctrl-C and SIGKILL (issue 12).

Full-disk and read-only cases mount a small tmpfs (root only; skipped otherwise).
Signal cases run ``python -m lensforge`` in a subprocess and send SIGINT / SIGKILL.
"""

from __future__ import annotations

import errno
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hostile import assert_clean, cli, mapped
from lensforge.errors import ConfigError
from lensforge.fileio import check_output, staged_dir
from lensforge.interrupts import alive, descendants

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def small_fs(tmp_path):
    """A 64 KiB tmpfs (full after ~60 KiB), unmounted afterwards."""
    if os.geteuid() != 0:
        pytest.skip("mounting a size-limited tmpfs needs root")
    mnt = tmp_path / "small"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)], capture_output=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount tmpfs here: {r.stderr.decode().strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


@pytest.fixture
def read_only(small_fs):
    subprocess.run(["mount", "-o", "remount,ro", str(small_fs)], check=True, capture_output=True)
    return small_fs


def _listing(p: Path):
    return sorted(os.listdir(p)) if p.exists() else None


@pytest.mark.parametrize("cmd, args, target", [
    ("design", ["--max-evals", "12", "--no-progress"], "d.json"),
    ("plot", ["spherical"], "plots"),
    ("estimate-study", ["spherical", "--trials", "2"], "est"),
    ("scenario", ["spherical", "--runs", "1"], "sc"),
    ("study", ["spherical", "-n", "2", "--workers", "0", "--no-progress"], "st"),
    ("export", ["spherical", "--stl", "--no-slicer"], "ex"),
    ("demo", ["--quick"], "demo"),
    ("plan", ["polynomial", "-n", "4", "--no-progress"], "pl"),
])
def test_full_disk_refused_before_work(small_fs, cmd, args, target):
    (small_fs / "filler").write_bytes(b"\0" * 56 * 1024)
    code, _, err = cli(cmd, *args, "-o", small_fs / target)
    assert_clean(code, err)
    assert code == 2 and "free" in err, err
    assert _listing(small_fs) == ["filler"]


@pytest.mark.parametrize("cmd, args, target", [
    ("design", ["--max-evals", "12", "--no-progress"], "d.json"),
    ("plot", ["spherical"], "plots"),
    ("study", ["spherical", "-n", "2", "--workers", "0", "--no-progress"], "st"),
    ("plan", ["polynomial", "-n", "4", "--no-progress"], "pl"),
])
def test_read_only_folder_refused(read_only, cmd, args, target):
    code, _, err = cli(cmd, *args, "-o", read_only / target)
    assert_clean(code, err)
    assert code == 2 and "cannot write" in err, err


def test_disk_full_while_writing_leaves_nothing(small_fs):
    out = small_fs / "out"
    with pytest.raises(OSError) as e:
        with staged_dir(out) as st:
            (st.tmp / "a.bin").write_bytes(b"1" * 1000)
            (st.tmp / "b.bin").write_bytes(b"2" * 200_000)
    assert e.value.errno == errno.ENOSPC
    assert _listing(small_fs) == []


def test_disk_full_mid_command_is_one_line(small_fs, monkeypatch):
    import lensforge.commands.design as design_cmd

    monkeypatch.setattr(design_cmd, "check_output", lambda *a, **k: None)  # let it start, then fill up
    code, _, err = cli("plot", "spherical", "-o", small_fs / "plots")
    assert_clean(code, err)
    assert code == 2 and "disk is full" in err, err
    assert _listing(small_fs) == []


def test_check_output_cases(tmp_path):
    f = tmp_path / "f"
    f.write_text("x")
    with pytest.raises(ConfigError, match="is a file, so nothing"):
        check_output(f / "a" / "b.json", folder=False)
    with pytest.raises(ConfigError, match="is a folder"):
        check_output(tmp_path, folder=False)
    with pytest.raises(ConfigError, match="is a file, not a folder"):
        check_output(f, folder=True)
    with pytest.raises(ConfigError, match="MiB free"):
        check_output(tmp_path / "x", folder=True, need_mb=1e12)
    assert check_output(tmp_path / "new" / "deeper", folder=True) == tmp_path / "new" / "deeper"
    assert not (tmp_path / "new").exists()


def test_staged_dir_merges_into_existing_folder(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("k")
    with staged_dir(out) as st:
        (st.tmp / "new.txt").write_text("n")
        assert st.final(st.tmp / "new.txt") == out / "new.txt"
    assert sorted(os.listdir(out)) == ["keep.txt", "new.txt"]
    assert sorted(os.listdir(tmp_path)) == ["out"]


# --- signals ---------------------------------------------------------------------------

def _start(args, cwd):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, "-m", "lensforge", *map(str, args)], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(pred, timeout=120.0):
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout:
            raise AssertionError("timed out waiting")
        time.sleep(0.05)


def _interrupt(p, grace=2.0):
    t0 = time.monotonic()
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=60)
    return p.returncode, time.monotonic() - t0, err


def _n_trials(store: Path) -> int:
    with sqlite3.connect(store) as c:
        assert c.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        return c.execute("SELECT COUNT(*) FROM trials").fetchone()[0]


def _started(store: Path, n: int = 1) -> bool:
    """The store holds at least n finished trials (False while it is being created)."""
    try:
        return store.exists() and _n_trials(store) >= n
    except sqlite3.Error:
        return False


def _assert_interrupted(rc, dt, err):
    assert rc == 130, err
    assert "Traceback" not in err, err
    assert err.strip().splitlines()[-1] == "error: interrupted", err
    assert [ln for ln in err.splitlines() if ln.startswith("error:")] == ["error: interrupted"], err
    assert dt < 5.0, f"took {dt:.2f} s"  # goal 2 s; measured by benchmarks/sigint_latency.py, not timed here


@pytest.mark.parametrize("stage", ["numpy", "scipy", "OCP.cpython"])
def test_sigint_during_startup(tmp_path, stage):
    """Ctrl-C while the command modules import, including the seconds in which OCP's C
    extension initialises holding the interpreter (the ``lensforge`` supervisor answers)."""
    p = _start(["export", "spherical", "--no-slicer", "-o", tmp_path / "ex"], tmp_path)
    _wait_for(lambda: mapped(p.pid, stage) or p.poll() is not None)
    kids = descendants(p.pid)
    _assert_interrupted(*_interrupt(p))
    assert not (tmp_path / "ex").exists()
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".")]
    time.sleep(0.2)
    assert not [k for k in kids if alive(k)]  # the command's process went with the supervisor


def test_sigint_study_lock_resume_and_size(tmp_path):
    out = tmp_path / "st"
    store = out / "store.sqlite"
    args = ["study", "spherical", "--poses", "8", "--workers", "0", "--no-progress", "-o", out]
    p = _start([*args, "-n", "400"], tmp_path)
    try:
        _wait_for(lambda: _started(store))
        # a second writer is refused while the first runs
        code, _, err = cli(*args, "-n", "400", "--resume")
        assert code == 2 and "another lensforge process" in err, err
    finally:
        rc, dt, err = _interrupt(p)
    _assert_interrupted(rc, dt, err)
    n = _n_trials(store)
    assert n >= 1
    assert not (out / "summary.json").exists()
    # shrinking a stored study is refused; the store is untouched
    code, _, err = cli(*args, "-n", "3", "--resume")
    assert code == 2 and "holds a study of 400 lenses" in err, err
    assert _n_trials(store) == n


def test_sigkill_then_resume_and_extend(tmp_path):
    out = tmp_path / "st"
    store = out / "store.sqlite"
    args = ["study", "spherical", "--poses", "8", "--workers", "0", "--no-progress", "-o", out]
    p = _start([*args, "-n", "4"], tmp_path)
    _wait_for(lambda: p.poll() is not None or _started(store))
    p.kill()
    p.communicate(timeout=60)
    n = _n_trials(store)
    code, _, err = cli(*args, "-n", "4", "--resume")
    assert_clean(code, err)
    assert code == 0 and _n_trials(store) == 4, err
    assert f"({n} resumed" in err or n == 4, err
    code, out_json, err = cli(*args, "-n", "5", "--resume", "--json")
    assert code == 0 and _n_trials(store) == 5, err
    assert '"n_lenses": 5' in out_json


def test_failed_start_leaves_no_store(tmp_path):
    out = tmp_path / "st"
    bad = tmp_path / "t.toml"
    bad.write_text("[thickness]\nsigma_mm = 50\n")
    code, _, err = cli("study", "spherical", "-n", "2", "--workers", "0", "-t", bad, "-o", out)
    assert code == 2 and "thickness.sigma_mm" in err
    assert not out.exists()


@pytest.mark.slow
def test_sigint_study_with_dask_workers(tmp_path):
    out = tmp_path / "st"
    store = out / "store.sqlite"
    p = _start(["study", "spherical", "-n", "200", "--poses", "8", "--workers", "2", "--no-progress", "-o", out],
               tmp_path)
    _wait_for(lambda: _started(store, 2), timeout=300)
    _assert_interrupted(*_interrupt(p))
    _n_trials(store)  # consistent
    time.sleep(1.0)
    ps = subprocess.run(["pgrep", "-P", str(p.pid)], capture_output=True, text=True)
    assert not ps.stdout.strip()  # no orphaned workers
