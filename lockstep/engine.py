"""Where the runs of a sweep (or suite) fly: Dask's distributed scheduler, or a process pool.

- ``dask``: a `distributed.LocalCluster` of this machine's cores (one single-threaded worker
  process per core, started as the pool's are: `local_cluster`), or, given a scheduler
  address, the cluster the user runs (``dask scheduler`` and ``dask worker`` on any hosts).
  Dask moves the runs of a worker that dies to the others by itself (docs/sweeps.md). Needs
  the ``cluster`` extra (``pip install fleetmpc[cluster]``).
- ``local``: `concurrent.futures.ProcessPoolExecutor` on this machine, always there.

Either way at most a few runs per worker are handed out ahead (`AHEAD_PER_WORKER`), the rest
wait here, so the number of runs does not weigh on the scheduler or on memory, and a run is
handed back (`on_finished`) as soon as it ends, in the order runs end. A run whose row says it
failed (`failed`), or whose worker died under it, is flown once more (`MAX_ATTEMPTS`), on another
worker where the engine lets us choose (Dask: yes; the pool: whichever is free); after that its
failed row is handed back with its error. With a time limit, a worker flies each run in its run
process (`fleetmpc.lockstep.run_process`), killed when the run outlives the limit: a run that hangs
anywhere, inside one control period too, fails with "time limit N s exceeded" and its worker
goes on.
"""

import argparse
import contextlib
import logging
import multiprocessing
import os
import socket
import traceback
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

from fleetmpc.errors import ConfigError, FleetMpcError
from fleetmpc.lockstep.run_process import fly_within

__all__ = [
    "AHEAD_PER_WORKER",
    "ENGINES",
    "MAX_ATTEMPTS",
    "EngineLost",
    "Finished",
    "add_engine_arguments",
    "dask_available",
    "engine_of",
    "local_cluster",
    "run_tasks",
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
    "distributed.worker.daemon": False,
    "distributed.admin.log-length": 100,
    "distributed.admin.low-level-log-length": 100,
}
"""Dask settings of the cluster a sweep starts: no statistical profiler (a thread that samples
the running run's stack every 10 ms and keeps an hour of it: time and memory a lockstep run
needs for itself); worker processes that are not daemons, so that they may start their run
processes (`fleetmpc.lockstep.run_process`; they still stop with their nanny); and logs of a hundred
entries where Dask keeps ten thousand and a thousand (its scheduler, in this process, kept about
12 kB a run until they filled; with these, the coordinator is flat from about 700 runs on).
Workers started by hand take them from the environment:
``DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False DASK_DISTRIBUTED__WORKER__DAEMON=False``
(docs/sweeps.md)."""


@contextlib.contextmanager
def local_cluster(jobs: int) -> Iterator[Any]:
    """A Dask `LocalCluster` of `jobs` single-threaded worker processes on loopback, closed on
    leaving.

    Its nannies start (and restart) the workers with `WORKER_CONFIG` and the start method of
    the process pool (this platform's multiprocessing default: fork on Linux), so a worker
    begins with what this process has imported, the flight code included, as the pool's
    processes do: spawned afresh, each worker imported it again before its first run, some 2 s
    of a sweep's start on two cores (docs/benchmarks.md, "Sweeps")."""
    import dask
    from distributed import LocalCluster

    method = multiprocessing.get_start_method()
    config = {**WORKER_CONFIG, "distributed.worker.multiprocessing-method": method}
    with (
        dask.config.set(config),
        LocalCluster(
            n_workers=jobs,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=":0",
            silence_logs=logging.ERROR,
        ) as cluster,
    ):
        yield cluster


@dataclass(frozen=True)
class _Flight:
    """What a worker is handed with each task: how to fly it, and for how long at most."""

    fly: Callable[[Any], dict]
    limit_s: float | None


def _attempt(flight: _Flight, task: Any) -> tuple[dict | None, str | None]:
    """One flight of a task in a worker: (its row, None), or (None, the error) when it
    outlived its time limit or lost its run process (`fleetmpc.lockstep.run_process`)."""
    if flight.limit_s is None:
        return flight.fly(task), None
    return fly_within(flight.fly, task, limit_s=flight.limit_s)


def _pool_attempt(flight: _Flight, task: Any) -> tuple[dict | None, str | None, str]:
    return *_attempt(flight, task), f"{socket.gethostname()}:{os.getpid()}"


def _dask_attempt(flight: _Flight, task: Any) -> tuple[dict | None, str | None, str]:
    from distributed import get_worker

    return *_attempt(flight, task), get_worker().address


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
    time_limit_s: float | None = None,
    on_start: Callable[[str], None] | None = None,
) -> None:
    """Fly every task (``fly(task) -> row``, a module-level function: it is pickled by name)
    on the engine; `failed(row)` is the error of a failed row (None when it flew);
    `error_row(task, error)` the row of a run whose worker died or that outlived
    `time_limit_s` of wall time (None: no limit, the runs fly in the workers themselves).
    `jobs`: workers of the local pool or cluster (default: this machine's cores); `scheduler`:
    a running Dask scheduler's address (engine dask). `on_start` gets a line saying where the
    runs fly."""
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
    if time_limit_s is not None and not time_limit_s > 0:
        raise ConfigError("--time-limit", f"must be > 0, got {time_limit_s}")
    book = _Book(
        tasks, failed=failed, error_row=error_row, on_finished=on_finished, on_retry=on_retry
    )
    if not book.pending:
        return
    flight = _Flight(fly, time_limit_s)
    if engine == "local":
        _run_pool(flight, book, jobs=min(jobs, len(book.pending)), on_start=on_start)
    else:
        _run_dask(flight, book, jobs=jobs, scheduler=scheduler, on_start=on_start)


def _run_pool(
    flight: _Flight,
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
                inflight[pool.submit(_pool_attempt, flight, a.task)] = a
            done, _ = wait(inflight, return_when=FIRST_COMPLETED)
            broken = False
            for future in sorted(done, key=lambda f: inflight[f].index):
                a = inflight.pop(future)
                try:
                    row, error, worker = future.result()
                    book.settle(a, row, worker, error or book.failed(row))
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
                row, error, worker = future.result()
                if error is None and book.failed(row) is None:
                    book.on_finished(Finished(a.task, row, worker, a.attempts + 1, a.first_error))
        raise
    pool.shutdown(wait=True)


def _dask_client(jobs: int, scheduler: str | None, stack: contextlib.ExitStack) -> tuple[Any, str]:
    """A client of a local cluster of `jobs` workers (closed with `stack`), or of the running
    scheduler at `scheduler`; and where the runs fly, in words."""
    from distributed import Client

    if scheduler is None:
        cluster = stack.enter_context(local_cluster(jobs))
        client = stack.enter_context(Client(cluster))
        return client, f"a local Dask cluster of {jobs} workers at {cluster.scheduler_address}"
    try:
        client = stack.enter_context(Client(scheduler, timeout="20s"))
    except OSError as e:
        raise ConfigError("--scheduler", f"no Dask scheduler answers at {scheduler}: {e}") from None
    return client, f"the Dask scheduler at {scheduler}"


def _run_dask(
    flight: _Flight,
    book: _Book,
    *,
    jobs: int,
    scheduler: str | None,
    on_start: Callable[[str], None] | None,
) -> None:
    from distributed import as_completed
    from distributed.client import FutureCancelledError

    try:
        from distributed.scheduler import KilledWorker
    except ImportError:  # pragma: no cover - older layout
        from distributed import KilledWorker

    with contextlib.ExitStack() as stack:
        client, where = _dask_client(jobs, scheduler, stack)
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
        inflight: dict[str, tuple[Any, _Attempt]] = {}

        def submit(a: _Attempt) -> None:
            workers = None
            if a.avoid:
                others = [w for w in client.scheduler_info()["workers"] if w != a.avoid]
                workers = others or None
            future = client.submit(
                _dask_attempt,
                flight,
                a.task,
                key=f"fleetmpc-run-{a.index}-{a.attempts}",
                pure=False,
                workers=workers,
                allow_other_workers=workers is not None,
            )
            inflight[future.key] = (future, a)
            running.add(future)

        try:
            while book.pending and len(inflight) < ahead:
                submit(book.pending.popleft())
            for future in running:
                _, a = inflight.pop(future.key)
                try:
                    row, error, worker = future.result()
                    error = error or book.failed(row)
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
