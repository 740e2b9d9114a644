"""Where the runs of a sweep (or suite) fly: Dask's distributed scheduler, or a process pool.

- ``dask``: a `distributed.LocalCluster` of this machine's cores (one single-threaded worker
  process per core), or, given a scheduler address, the cluster the user runs (``dask
  scheduler`` and ``dask worker`` on any hosts). Dask moves the runs of a worker that dies to
  the others by itself (docs/sweeps.md). Needs the ``cluster`` extra
  (``pip install fleetmpc[cluster]``).
- ``local``: `concurrent.futures.ProcessPoolExecutor` on this machine, always there.

Either way at most a few runs per worker are handed out ahead (`AHEAD_PER_WORKER`), the rest
wait here, so the number of runs does not weigh on the scheduler or on memory, and a run is
handed back (`on_finished`) as soon as it ends, in the order runs end. A run whose row says it
failed (`failed`), or whose worker died under it, is flown once more (`MAX_ATTEMPTS`), on another
worker where the engine lets us choose (Dask: yes; the pool: whichever is free); after that its
failed row is handed back with its error.
"""

import argparse
import logging
import os
import socket
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

from fleetmpc.errors import ConfigError, FleetMpcError

__all__ = [
    "AHEAD_PER_WORKER",
    "ENGINES",
    "MAX_ATTEMPTS",
    "EngineLost",
    "Finished",
    "TimeLimitError",
    "add_engine_arguments",
    "dask_available",
    "engine_of",
    "local_cluster",
    "run_tasks",
    "time_limit",
]

ENGINES = ("dask", "local")
MAX_ATTEMPTS = 2
"""Flights of a run at most: the first, and one retry after a failure."""
AHEAD_PER_WORKER = 2
"""Runs handed to the engine per worker before one comes back."""
WORKERS_WAIT_S = 60.0
"""How long a sweep waits for a first worker to join a scheduler [s]."""


class EngineLost(FleetMpcError):
    """The engine itself went away (the scheduler stopped answering): finished runs are kept."""


@dataclass(frozen=True)
class Finished:
    """A run handed back: its row and how it got it."""

    task: Any
    """The caller's task."""
    row: dict
    """The row of its last flight (its numbers, or its error)."""
    worker: str
    """The worker that flew it last (Dask's worker address, or host:pid)."""
    attempts: int
    """How many times it was flown (or handed to a worker that died under it)."""
    first_error: str | None
    """The error of its first flight, when it was flown again."""


@dataclass(frozen=True)
class _Attempt:
    index: int
    task: Any
    attempts: int = 0
    first_error: str | None = None
    avoid: str | None = None


class TimeLimitError(FleetMpcError):
    """A run still flying when its time limit passed."""


def time_limit(limit_s: float | None) -> Callable[[float, float], None] | None:
    """A lockstep progress callback that stops the run (TimeLimitError) once `limit_s` of wall
    time have passed; None without a limit."""
    if limit_s is None:
        return None
    t0 = time.monotonic()

    def check(done_s: float, total_s: float) -> None:
        if time.monotonic() - t0 > limit_s:
            raise TimeLimitError(
                f"still flying after {limit_s:g} s of wall time ({done_s:.1f} of {total_s:g} s "
                "simulated)"
            )

    return check


def add_engine_arguments(parser: argparse.ArgumentParser, *, default: str) -> None:
    """--engine and --scheduler, as `fleetmpc suite` and `fleetmpc sweep` take them."""
    parser.add_argument(
        "--engine",
        choices=ENGINES,
        default=None,
        help=f"where the runs fly: dask (a local Dask cluster, or --scheduler's) or local (a"
        f" process pool) (default: {default})",
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="fly on a running Dask cluster (tcp://HOST:8786); implies --engine dask",
    )


def engine_of(args: argparse.Namespace, *, default: str) -> str:
    """The engine the arguments ask for."""
    if args.engine is None:
        return "dask" if args.scheduler is not None else default
    return args.engine


def dask_available() -> bool:
    """True when Dask's distributed scheduler is installed (the ``cluster`` extra)."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        return False
    return True


WORKER_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.log-length": 100,
    "distributed.admin.low-level-log-length": 100,
}
"""Dask settings of the cluster a sweep starts: no statistical profiler (a thread that samples
the running run's stack every 10 ms and keeps an hour of it: time and memory a lockstep run
needs for itself), and logs of a hundred entries where Dask keeps ten thousand and a thousand
(its scheduler, in this process, kept about 12 kB a run until they filled; with these, the
coordinator is flat from about 700 runs on). Workers started by hand take them from the
environment: ``DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False`` (docs/sweeps.md)."""


def local_cluster(jobs: int) -> Any:
    """A Dask `LocalCluster` of `jobs` single-threaded worker processes on loopback."""
    import dask
    from distributed import LocalCluster

    with dask.config.set(WORKER_CONFIG):
        return LocalCluster(
            n_workers=jobs,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=":0",
            silence_logs=logging.ERROR,
        )


def _pool_attempt(fly: Callable[[Any], dict], task: Any) -> tuple[dict, str]:
    return fly(task), f"{socket.gethostname()}:{os.getpid()}"


def _dask_attempt(fly: Callable[[Any], dict], task: Any) -> tuple[dict, str]:
    from distributed import get_worker

    return fly(task), get_worker().address


def _error_text(error: BaseException) -> str:
    return traceback.format_exception_only(error)[-1].strip()


class _Book:
    """The runs still to fly, and what to do with each flight's outcome."""

    def __init__(
        self,
        tasks: Iterable[Any],
        *,
        failed: Callable[[dict], str | None],
        error_row: Callable[[Any, str], dict],
        on_finished: Callable[[Finished], None],
        on_retry: Callable[[Any, str], None] | None,
    ) -> None:
        self.pending = deque(_Attempt(i, t) for i, t in enumerate(tasks))
        self.failed = failed
        self.error_row = error_row
        self.on_finished = on_finished
        self.on_retry = on_retry

    def settle(self, a: _Attempt, row: dict | None, worker: str, error: str | None) -> None:
        attempts = a.attempts + 1
        if error is None and row is not None:
            self.on_finished(Finished(a.task, row, worker, attempts, a.first_error))
        elif attempts < MAX_ATTEMPTS:
            first = error or "failed"
            self.pending.appendleft(_Attempt(a.index, a.task, attempts, first, avoid=worker))
            if self.on_retry is not None:
                self.on_retry(a.task, first)
        else:
            final = row if row is not None else self.error_row(a.task, str(error))
            self.on_finished(Finished(a.task, final, worker, attempts, a.first_error))


def run_tasks(
    fly: Callable[[Any], dict],
    tasks: Iterable[Any],
    *,
    failed: Callable[[dict], str | None],
    error_row: Callable[[Any, str], dict],
    on_finished: Callable[[Finished], None],
    on_retry: Callable[[Any, str], None] | None = None,
    engine: str = "local",
    jobs: int | None = None,
    scheduler: str | None = None,
    on_start: Callable[[str], None] | None = None,
) -> None:
    """Fly every task (``fly(task) -> row``, a module-level function: it is pickled by name)
    on the engine; `failed(row)` is the error of a failed row (None when it flew);
    `error_row(task, error)` the row of a run whose worker died. `jobs`: workers of the local
    pool or cluster (default: this machine's cores); `scheduler`: a running Dask scheduler's
    address (engine dask). `on_start` gets a line saying where the runs fly."""
    jobs = (os.cpu_count() or 1) if jobs is None else jobs
    if jobs < 1:
        raise ConfigError("--jobs", f"must be >= 1, got {jobs}")
    if engine not in ENGINES:
        raise ConfigError("--engine", f"must be one of {', '.join(ENGINES)}, got {engine!r}")
    if scheduler is not None and engine != "dask":
        raise ConfigError("--scheduler", "a scheduler address needs --engine dask")
    if engine == "dask" and not dask_available():
        raise ConfigError(
            "--engine",
            "dask needs Dask's distributed scheduler: pip install 'fleetmpc[cluster]'"
            " (or --engine local, the process pool)",
        )
    book = _Book(
        tasks, failed=failed, error_row=error_row, on_finished=on_finished, on_retry=on_retry
    )
    if not book.pending:
        return
    if engine == "local":
        _run_pool(fly, book, jobs=min(jobs, len(book.pending)), on_start=on_start)
    else:
        _run_dask(fly, book, jobs=jobs, scheduler=scheduler, on_start=on_start)


def _run_pool(
    fly: Callable[[Any], dict],
    book: _Book,
    *,
    jobs: int,
    on_start: Callable[[str], None] | None,
) -> None:
    if on_start is not None:
        on_start(f"a process pool of {jobs} workers on this machine")
    pool = ProcessPoolExecutor(max_workers=jobs)
    inflight: dict[Any, _Attempt] = {}
    try:
        while book.pending or inflight:
            while book.pending and len(inflight) < AHEAD_PER_WORKER * jobs:
                a = book.pending.popleft()
                inflight[pool.submit(_pool_attempt, fly, a.task)] = a
            done, _ = wait(inflight, return_when=FIRST_COMPLETED)
            broken = False
            for future in sorted(done, key=lambda f: inflight[f].index):
                a = inflight.pop(future)
                try:
                    row, worker = future.result()
                    book.settle(a, row, worker, book.failed(row))
                except BrokenProcessPool:  # a worker died: every run in flight is suspect
                    broken = True
                    book.settle(a, None, "", "its worker process died (BrokenProcessPool)")
                except Exception as e:  # the task itself raised (it should return a row)
                    book.settle(a, None, "", _error_text(e))
            if broken:
                pool.shutdown(wait=False)
                pool = ProcessPoolExecutor(max_workers=jobs)
    except BaseException:  # Ctrl-C: keep what finished meanwhile, leave no worker behind
        for future in inflight:
            future.cancel()
        pool.shutdown(wait=True, cancel_futures=True)
        for future, a in sorted(inflight.items(), key=lambda item: item[1].index):
            if future.done() and not future.cancelled() and future.exception() is None:
                row, worker = future.result()
                if book.failed(row) is None:
                    book.on_finished(Finished(a.task, row, worker, a.attempts + 1, a.first_error))
        raise
    pool.shutdown(wait=True)


def _run_dask(
    fly: Callable[[Any], dict],
    book: _Book,
    *,
    jobs: int,
    scheduler: str | None,
    on_start: Callable[[str], None] | None,
) -> None:
    from distributed import Client, as_completed
    from distributed.client import FutureCancelledError

    try:
        from distributed.scheduler import KilledWorker
    except ImportError:  # pragma: no cover - older layout
        from distributed import KilledWorker

    cluster = None
    if scheduler is None:
        cluster = local_cluster(jobs)
        client = Client(cluster)
        where = f"a local Dask cluster of {jobs} workers at {cluster.scheduler_address}"
    else:
        try:
            client = Client(scheduler, timeout="20s")
        except OSError as e:
            raise ConfigError(
                "--scheduler", f"no Dask scheduler answers at {scheduler}: {e}"
            ) from None
        where = f"the Dask scheduler at {scheduler}"
    inflight: dict[str, tuple[Any, _Attempt]] = {}
    try:
        try:
            client.wait_for_workers(1, timeout=WORKERS_WAIT_S)
        except TimeoutError:
            raise EngineLost(
                f"no worker joined {where} in {WORKERS_WAIT_S:g} s (dask worker ADDRESS)"
            ) from None
        info = client.scheduler_info()
        slots = sum(w.get("nthreads", 1) for w in info["workers"].values())
        if on_start is not None:
            on_start(f"{where}, {len(info['workers'])} workers, {slots} threads")
        ahead = AHEAD_PER_WORKER * max(1, slots)
        running = as_completed(with_results=False)

        def submit(a: _Attempt) -> None:
            workers = None
            if a.avoid:
                others = [w for w in client.scheduler_info()["workers"] if w != a.avoid]
                workers = others or None
            future = client.submit(
                _dask_attempt,
                fly,
                a.task,
                key=f"fleetmpc-run-{a.index}-{a.attempts}",
                pure=False,
                workers=workers,
                allow_other_workers=workers is not None,
            )
            inflight[future.key] = (future, a)
            running.add(future)

        while book.pending and len(inflight) < ahead:
            submit(book.pending.popleft())
        for future in running:
            _, a = inflight.pop(future.key)
            try:
                row, worker = future.result()
                error = book.failed(row)
            except KilledWorker as e:  # its workers died under it, more than Dask allows
                row, worker, error = None, "", f"its workers died under it ({_error_text(e)})"
            except (FutureCancelledError, OSError) as e:
                raise EngineLost(f"{where} stopped answering ({_error_text(e)})") from None
            except Exception as e:  # the task itself raised (it should return a row)
                row, worker, error = None, "", _error_text(e)
            future.release()
            book.settle(a, row, worker, error)
            while book.pending and len(inflight) < ahead:
                submit(book.pending.popleft())
    except BaseException:
        if inflight:
            client.cancel([future for future, _ in inflight.values()], force=True)
        raise
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
