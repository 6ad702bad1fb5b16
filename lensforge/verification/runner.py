"""Monte Carlo study runner: trials on Dask (or in process), one durable store.

A study is ``n`` independent trials. Trial ``i`` gets the i-th child of
``np.random.SeedSequence(seed).spawn(n)`` (child i depends on ``seed`` and ``i``
only), so its result is the same whichever worker runs it and however many
workers there are. Workers run single-threaded (BLAS and numba pinned to one
thread) so that throughput scales with the number of worker processes.

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
import json
import os
import sqlite3
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import ConfigError
from ..progress import progress_bar

__all__ = ["TrialStore", "config_hash", "trial_seeds", "run_trials", "dask_client", "RunStats", "SINGLE_THREAD_ENV"]

STORE_SCHEMA = 1

# Pin BLAS/numba to one thread in worker processes: one trial per core.
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


def trial_seeds(seed: int, n: int) -> list[np.random.SeedSequence]:
    """Per-trial seed sequences: child i of SeedSequence(seed), independent of n."""
    return np.random.SeedSequence(int(seed)).spawn(int(n))


def _dumps(record: dict) -> str:
    return json.dumps(record, sort_keys=True, separators=(",", ":"), allow_nan=True)


class TrialStore:
    """Durable, append-only store of trial records (SQLite, WAL, one transaction per trial).

    ``TrialStore.open(path, hash, config, resume)`` creates the file, or reopens it
    when ``resume`` is true and its hash matches; otherwise raises ConfigError.
    """

    def __init__(self, path: Path, conn: sqlite3.Connection, config_hash: str):
        self.path = path
        self._conn = conn
        self.config_hash = config_hash

    @classmethod
    def open(cls, path, config_hash_: str, config: dict, resume: bool = False) -> "TrialStore":
        path = Path(path)
        exists = path.exists() and path.stat().st_size > 0
        if exists and not resume:
            raise ConfigError(
                f"store {path}: already exists; pass resume=True (--resume) to continue that study, "
                "or choose another output folder"
            )
        path.parent.mkdir(parents=True, exist_ok=True)
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
            conn.execute("COMMIT")
        except sqlite3.DatabaseError as e:
            raise ConfigError(f"store {path}: not a lensforge study store ({e}); choose another output folder") from None
        return cls(path, conn, config_hash_)

    def done(self) -> set[int]:
        """Indices of the finished trials."""
        return {r[0] for r in self._conn.execute("SELECT idx FROM trials")}

    def put(self, idx: int, record: dict) -> None:
        """Append one finished trial (its own transaction; a repeat is ignored)."""
        self._conn.execute("BEGIN IMMEDIATE")
        try:
            self._conn.execute("INSERT OR IGNORE INTO trials (idx, record) VALUES (?, ?)", (int(idx), _dumps(record)))
            self._conn.execute("COMMIT")
        except BaseException:
            self._conn.execute("ROLLBACK")
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
        finally:
            self._conn.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


@dataclass(frozen=True)
class RunStats:
    """What a run did: trials run now, trials found in the store, wall time (s), mode."""

    n_run: int
    n_resumed: int
    wall_s: float
    mode: str
    workers: int


def _pin_threads() -> None:
    """Run on each worker: one BLAS and one numba thread."""
    for k, v in SINGLE_THREAD_ENV.items():
        os.environ.setdefault(k, v)
    try:
        import numba

        numba.set_num_threads(1)
    except Exception:  # pragma: no cover - numba already pinned by env
        pass


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
    seeds = trial_seeds(seed, n_trials)
    records = store.records(n_trials) if store is not None else {}
    todo = [i for i in range(n_trials) if i not in records]
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
    with progress_bar(n_trials, description or "trials", progress) as bar:
        bar.advance(n_resumed)
        if not todo:
            pass
        elif mode == "serial":
            for i in todo:
                finish(i, trial_fn(context, i, seeds[i]))
                bar.advance()
        elif client is not None:
            n_workers = _submit_all(client, trial_fn, context, todo, seeds, finish, bar.advance)
        else:
            with dask_client(workers, scheduler) as cl:
                n_workers = _submit_all(cl, trial_fn, context, todo, seeds, finish, bar.advance)
    stats = RunStats(len(todo), n_resumed, time.perf_counter() - t0, mode, n_workers)
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
    from distributed import Client, LocalCluster

    cluster = None
    if scheduler:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as e:
            raise ConfigError(f"scheduler: cannot reach Dask scheduler {scheduler!r} ({e}); check the address") from None
    else:
        n = int(workers) if workers is not None else (os.cpu_count() or 1)
        with warnings.catch_warnings():  # "port 8787 is already in use ... Hosting the HTTP server on port N
            warnings.filterwarnings("ignore", message=".*Hosting the HTTP server.*")  # instead": noise to a user
            cluster = LocalCluster(
                n_workers=max(1, n), threads_per_worker=1, processes=True, dashboard_address=None,
                env=dict(SINGLE_THREAD_ENV), silence_logs=logging.ERROR,
            )
        client = Client(cluster)
    try:
        client.run(_pin_threads)
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _submit_all(client, trial_fn, context, todo, seeds, finish, advance) -> int:
    from distributed import as_completed

    n_workers = len(client.scheduler_info().get("workers", {}))
    ctx = client.scatter(context, broadcast=True)
    futures = {}
    tag = f"{os.getpid()}-{time.monotonic_ns()}"
    for i in todo:
        f = client.submit(trial_fn, ctx, i, seeds[i], key=f"trial-{i}-{tag}", pure=False)
        futures[f] = i
    try:
        for fut in as_completed(futures):
            i = futures.pop(fut)
            finish(i, fut.result())
            advance()
            fut.release()
    finally:
        for f in futures:
            f.cancel()
    return n_workers
