"""Monte Carlo study runner: trials on Dask (or in process), one durable store.

A study is ``n`` independent trials. Trial ``i`` gets the i-th child of
``np.random.SeedSequence(seed).spawn(n)`` (child i depends on ``seed`` and ``i``
only), so its result is the same whichever worker runs it and however many
workers there are. Every trial runs single-threaded (BLAS and numba pinned to
one thread, in process and on workers): its record does not depend on where it
ran, and throughput scales with the number of worker processes.

Results go to a :class:`TrialStore`, an SQLite file in WAL mode with one
transaction per finished trial: a study killed at any moment (even SIGKILL)
leaves a consistent file holding every trial that finished, and ``resume=True``
runs only the missing ones. Trial records are stored as JSON text (floats as
their shortest exact repr), so a resumed study ends byte-identical to an
uninterrupted one. The store records the study's configuration hash and refuses
to resume a different study.

Execution modes (``workers`` / ``scheduler``):
  * ``scheduler="tcp://host:8786"``: an existing Dask cluster;
  * ``workers=0``: in this process, no Dask (tests, small budgets);
  * ``workers=N`` (default: the number of CPU cores): a LocalCluster of N
    single-threaded worker processes, closed when the study ends.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import os
import sqlite3
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import ConfigError
from ..interrupts import Interrupted
from ..progress import progress_bar

__all__ = ["TrialStore", "config_hash", "trial_seed", "run_trials", "dask_client", "RunStats", "SINGLE_THREAD_ENV",
           "single_threaded"]

STORE_SCHEMA = 1

# Local worker processes start with BLAS/numba on one thread: one trial per core (each trial
# is also pinned where it runs, see single_threaded).
SINGLE_THREAD_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "NUMBA_NUM_THREADS": "1",
}


def config_hash(config: dict) -> str:
    """SHA-256 (hex) of a JSON-able study configuration (keys sorted)."""
    blob = json.dumps(config, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def trial_seed(seed: int, i: int) -> np.random.SeedSequence:
    """Trial i's seed sequence, made on demand: equal to ``SeedSequence(seed).spawn(n)[i]``
    for every n > i (spawn's child i is SeedSequence(seed, spawn_key=(i,)))."""
    return np.random.SeedSequence(int(seed), spawn_key=(int(i),))


class _LazySeeds:
    """seeds[i] -> trial_seed(seed, i), without materialising n seed sequences."""

    def __init__(self, seed: int, n: int):
        self.seed, self.n = int(seed), int(n)

    def __len__(self):
        return self.n

    def __getitem__(self, i):
        if not 0 <= i < self.n:
            raise IndexError(i)
        return trial_seed(self.seed, i)


def _dumps(record: dict) -> str:
    return json.dumps(record, sort_keys=True, separators=(",", ":"), allow_nan=True)


class TrialStore:
    """Durable, append-only store of trial records (SQLite, WAL, one transaction per trial).

    ``TrialStore.open(path, hash, config, resume)`` creates the file, or reopens it
    when ``resume`` is true and its hash matches; otherwise raises ConfigError.
    """

    def __init__(self, path: Path, conn: sqlite3.Connection, config_hash: str, lock_fd: int | None = None,
                 created: bool = False):
        self.path = path
        self._conn = conn
        self.config_hash = config_hash
        self._lock_fd = lock_fd
        self.created = created  # this open made the file (a failed start removes it again)
        self.made_dir = False  # ... and its folder

    @classmethod
    @contextmanager
    def session(cls, path, config_hash_: str, config: dict, resume: bool = False, n_trials: int | None = None):
        """``open`` as a context manager: closes the store (and releases its lock) on exit; a store
        this session created that holds no finished trial when an error or interrupt ends it is
        removed, so a failed start never blocks a rerun."""
        st = cls.open(path, config_hash_, config, resume=resume, n_trials=n_trials)
        try:
            yield st
        except BaseException:
            empty = st.created and not st.done()
            st.close()
            if empty:
                for f in (st.path, st.path.with_name(st.path.name + "-wal"), st.path.with_name(st.path.name + "-shm"),
                          _lock_path(st.path)):
                    f.unlink(missing_ok=True)
                if st.made_dir and not any(st.path.parent.iterdir()):
                    st.path.parent.rmdir()
            raise
        st.close()

    @classmethod
    def open(cls, path, config_hash_: str, config: dict, resume: bool = False,
             n_trials: int | None = None) -> "TrialStore":
        """Open (create, or with ``resume`` reopen) a store, holding its folder lock.

        n_trials: the study's size; a resumed study may grow (larger n) but not shrink.
        """
        path = Path(path)
        made_dir = not path.parent.exists()
        path.parent.mkdir(parents=True, exist_ok=True)
        lock_fd = _lock(path)
        try:
            st = cls._open_locked(path, config_hash_, config, resume, n_trials, lock_fd)
        except BaseException:
            os.close(lock_fd)
            if made_dir:
                _lock_path(path).unlink(missing_ok=True)
                path.parent.rmdir() if not any(path.parent.iterdir()) else None
            raise
        st.made_dir = made_dir
        return st

    @classmethod
    def _open_locked(cls, path, config_hash_, config, resume, n_trials, lock_fd) -> "TrialStore":
        exists = path.exists() and path.stat().st_size > 0
        if exists and not resume:
            raise ConfigError(
                f"store {path}: already exists; pass resume=True (--resume) to continue that study, "
                "or choose another output folder"
            )
        conn = None
        try:
            conn = sqlite3.connect(str(path), timeout=30.0, isolation_level=None)
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA synchronous=FULL")
            conn.execute("BEGIN IMMEDIATE")
            conn.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
            conn.execute("CREATE TABLE IF NOT EXISTS trials (idx INTEGER PRIMARY KEY, record TEXT NOT NULL)")
            row = conn.execute("SELECT value FROM meta WHERE key='config_hash'").fetchone()
            if row is None:
                conn.executemany(
                    "INSERT INTO meta (key, value) VALUES (?, ?)",
                    [("config_hash", config_hash_), ("config", _dumps(config)),
                     ("store_schema", str(STORE_SCHEMA)), ("created_unix", repr(time.time()))],
                )
            elif row[0] != config_hash_:
                conn.execute("ROLLBACK")
                conn.close()
                raise ConfigError(
                    f"store {path}: holds a different study (config hash {row[0][:12]}..., this study "
                    f"{config_hash_[:12]}...); resume only with the same lens, bench, tolerances, seed and "
                    "options, or choose another output folder"
                )
            if n_trials is not None:
                old = conn.execute("SELECT value FROM meta WHERE key='n_trials'").fetchone()
                if old is not None and int(old[0]) > int(n_trials):
                    conn.execute("ROLLBACK")
                    conn.close()
                    raise ConfigError(
                        f"store {path}: holds a study of {int(old[0])} lenses; resume it with -n {int(old[0])} "
                        f"or more (a larger -n extends it), not {int(n_trials)}"
                    )
                conn.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('n_trials', ?)", (str(int(n_trials)),))
            conn.execute("COMMIT")
        except sqlite3.DatabaseError as e:
            if conn is not None:
                conn.close()
            if isinstance(e, sqlite3.OperationalError) and not exists:
                raise ConfigError(f"store {path}: cannot be created ({e}); check free space and permissions "
                                  "of the output folder") from None
            raise ConfigError(f"store {path}: not a lensforge study store ({e}); choose another output folder") from None
        return cls(path, conn, config_hash_, lock_fd, created=not exists)

    def done(self) -> set[int]:
        """Indices of the finished trials."""
        return {r[0] for r in self._conn.execute("SELECT idx FROM trials")}

    def put(self, idx: int, record: dict) -> None:
        """Append one finished trial (its own transaction; a repeat is ignored)."""
        try:
            self._conn.execute("BEGIN IMMEDIATE")
            self._conn.execute("INSERT OR IGNORE INTO trials (idx, record) VALUES (?, ?)", (int(idx), _dumps(record)))
            self._conn.execute("COMMIT")
        except BaseException:
            if self._conn.in_transaction:
                try:
                    self._conn.execute("ROLLBACK")
                except sqlite3.Error:  # pragma: no cover - SQLite already rolled back
                    pass
            raise

    def records(self, n: int | None = None) -> dict[int, dict]:
        """Finished trial records by index (only indices < n when n is given)."""
        rows = self._conn.execute("SELECT idx, record FROM trials ORDER BY idx")
        return {i: json.loads(r) for i, r in rows if n is None or i < n}

    def meta(self) -> dict:
        return dict(self._conn.execute("SELECT key, value FROM meta"))

    def close(self) -> None:
        try:
            self._conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        except sqlite3.Error:  # e.g. a full disk: the WAL stays and is replayed on the next open
            pass
        finally:
            self._conn.close()
            if self._lock_fd is not None:
                os.close(self._lock_fd)
                self._lock_fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _lock_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.lock")


def _lock(path: Path) -> int:
    """An exclusive lock on ``.<store>.lock`` beside the store (released when the fd closes)."""
    import fcntl

    lock = _lock_path(path)
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as e:
        raise ConfigError(f"store {path}: cannot create its lock file ({e.strerror}); "
                          "check the output folder's permissions and free space") from None
    t_end = time.monotonic() + 1.0  # a writer killed a moment ago may still be exiting (its lock goes with it)
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return fd
        except OSError:
            if time.monotonic() < t_end:
                time.sleep(0.05)
                continue
        os.close(fd)
        raise ConfigError(f"store {path}: another lensforge process is writing this study; wait for it "
                          "to finish or choose another output folder") from None


@dataclass(frozen=True)
class RunStats:
    """What a run did: trials run now, trials found in the store, wall time (s), mode."""

    n_run: int
    n_resumed: int
    wall_s: float
    mode: str
    workers: int


@contextmanager
def single_threaded():
    """Within the block, BLAS (threadpoolctl) and numba run on one thread in the calling thread.

    Every trial runs under it, in process and on workers: a multi-threaded BLAS splits sums
    differently from a single-threaded one (a 4e-6 relative difference after a
    Levenberg-Marquardt fit under OpenBLAS's Haswell kernel), and a trial's record must not
    depend on where it ran. (numba's ``prange`` kernels write one element per iteration, no
    reductions, so their results do not depend on the thread count; pinned all the same, so
    the trial sees the same machine everywhere.)
    """
    import numba
    from threadpoolctl import threadpool_limits

    n_nb = numba.get_num_threads()  # thread-local in numba: restored for this thread only
    with threadpool_limits(limits=1):
        numba.set_num_threads(1)
        try:
            yield
        finally:
            numba.set_num_threads(n_nb)


def _pinned_trial(trial_fn: Callable, context, i: int, seedseq):
    """One trial on one thread (what Dask workers run; see :func:`single_threaded`)."""
    with single_threaded():
        return trial_fn(context, i, seedseq)


def run_trials(
    trial_fn: Callable,
    context,
    n_trials: int,
    seed: int,
    store: TrialStore | None = None,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
    description: str = "",
    client=None,
) -> tuple[dict[int, dict], RunStats]:
    """Run ``trial_fn(context, i, seedseq_i) -> dict`` for i < n_trials; returns (records, stats).

    trial_fn must be a module-level function (it is pickled to workers) and return a
    JSON-able dict; records already in ``store`` are not run again. An exception
    in a trial stops the study (finished trials stay in the store). ``client``: an
    open ``distributed.Client`` to reuse (see :func:`dask_client`), left open.
    """
    n_trials = int(n_trials)
    if n_trials < 0:
        raise ConfigError(f"n_trials: must be >= 0, got {n_trials}")
    if workers is not None and int(workers) < 0:
        raise ConfigError(f"workers: must be >= 0 (0 = in this process), got {workers}")
    seeds = _LazySeeds(seed, n_trials)
    records = store.records(n_trials) if store is not None else {}
    todo = (i for i in range(n_trials) if i not in records)
    n_resumed = len(records)
    t0 = time.perf_counter()

    def finish(i, rec):
        if store is not None:
            store.put(i, rec)
        records[i] = rec

    if client is not None:
        mode = "client"
    else:
        mode = "serial" if (scheduler is None and workers == 0) else ("scheduler" if scheduler else "local")
    n_workers = 0
    n_todo = n_trials - len(records)
    with progress_bar(n_trials, description or "trials", enabled=progress) as bar:
        bar.update(n_resumed)
        if not n_todo:
            pass
        elif mode == "serial":
            with single_threaded():
                for i in todo:
                    finish(i, trial_fn(context, i, seeds[i]))
                    bar.advance()
        elif client is not None:
            n_workers = _submit_all(client, trial_fn, context, todo, seeds, finish, lambda: bar.advance())
        else:
            with dask_client(workers, scheduler) as cl:
                n_workers = _submit_all(cl, trial_fn, context, todo, seeds, finish, lambda: bar.advance())
    stats = RunStats(n_todo, n_resumed, time.perf_counter() - t0, mode, n_workers)
    return {i: records[i] for i in sorted(records)}, stats


@contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None):
    """A distributed.Client: to ``scheduler`` if given, else a LocalCluster of
    ``workers`` single-threaded processes (default: all cores); None when
    workers == 0 and no scheduler (run in process). Closed on exit."""
    import logging

    if scheduler is None and workers == 0:
        yield None
        return
    import dask
    from distributed import Client, LocalCluster

    cluster = None
    if scheduler:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as e:
            raise ConfigError(f"scheduler: cannot reach Dask scheduler {scheduler!r} ({e}); check the address") from None
    else:
        n = int(workers) if workers is not None else (os.cpu_count() or 1)
        # distributed starts workers with MALLOC_TRIM_THRESHOLD_=65536 (to hand memory back to
        # the OS); setting it also switches off glibc's adaptive mmap threshold, so every large
        # temporary array of a trial is mmap'd, faulted in and unmapped again. Measured on the
        # joint study (2 cores): 1.8 s per lens in a worker against 1.2 s in process, a third of
        # it system time. Trials are short-lived and small: keep glibc's defaults.
        environ = {k: v for k, v in dask.config.get("distributed.nanny.pre-spawn-environ", {}).items()
                   if k != "MALLOC_TRIM_THRESHOLD_"}
        with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}):
            cluster = LocalCluster(
                n_workers=max(1, n), threads_per_worker=1, processes=True, dashboard_address=":0",
                env=dict(SINGLE_THREAD_ENV), silence_logs=logging.ERROR,
            )
        client = Client(cluster)
    try:
        if cluster is not None:
            client.run(_ignore_sigint)
        yield client
    except Interrupted:
        raise  # Ctrl-C under the CLI: it kills the workers itself, a graceful close only adds noise
    except BaseException:
        _close(client, cluster)
        raise
    _close(client, cluster)


def _close(client, cluster) -> None:
    client.close()
    if cluster is not None:
        cluster.close()


def _ignore_sigint() -> None:
    """Run on each local worker: Ctrl-C in the terminal goes to the whole process group;
    the parent handles it, so workers must not print their own KeyboardInterrupt."""
    import signal

    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # pragma: no cover - not the worker's main thread
        pass


def _submit_all(client, trial_fn, context, todo, seeds, finish, advance) -> int:
    from distributed import as_completed

    n_workers = len(client.scheduler_info().get("workers", {}))
    ctx = client.scatter(context, broadcast=True)
    futures = {}
    tag = f"{os.getpid()}-{time.monotonic_ns()}"
    todo = iter(todo)
    window = max(64, 8 * max(n_workers, 1))  # trials in flight: memory stays bounded for any n

    def submit(k):
        for i in itertools.islice(todo, k):
            f = client.submit(_pinned_trial, trial_fn, ctx, i, seeds[i], key=f"trial-{i}-{tag}", pure=False)
            futures[f] = i
            ac.add(f)

    ac = as_completed()
    try:
        submit(window)
        for fut in ac:
            i = futures.pop(fut)
            finish(i, fut.result())
            advance()
            fut.release()
            submit(1)
    finally:
        for f in futures:
            f.cancel()
    return n_workers
