"""The child process a worker flies its runs in, so that a run's time limit is hard.

A run that hangs inside one control period (in native code, say) never comes back to the
lockstep's loop, and nothing in its own process can stop it. So a worker (a process of the pool,
or a thread of a Dask worker) hands each run with a time limit to its run process, a child it
started at its first such run (with the platform's start method, as the pool's: forked on
Linux, so with the flight code imported already), and waits for the row at most the limit. A run
still flying then has its run process killed (SIGKILL: whatever it is doing) and is an error,
"time limit N s exceeded"; a run process that dies under its run (a crash in native code) is an
error too. Either way the worker itself is unharmed, and its next run gets a new run process.

A run process lives as long as its worker's thread and flies that thread's runs one after the
other, as the worker would; its only cost per run is the pipe (the spec there, the row back).
It stops with its worker: terminated when the worker exits, or, when the worker is killed, at
the end of the pipe (idle) or of its run. Forked, it holds copies of the worker's sockets until
then, so a scheduler sees a killed worker gone once its run process has ended; a run that hangs
in a worker killed from outside outlives it (the scheduler's heartbeat timeout still drops the
worker).
"""

import multiprocessing
import signal
import threading
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

__all__ = ["RunProcess", "fly_within"]

DAEMON_HINT = (
    "this worker is a daemon process, which may not start the run's process: start Dask "
    "workers with DASK_DISTRIBUTED__WORKER__DAEMON=False (docs/sweeps.md)"
)


def _error_text(error: BaseException) -> str:
    return traceback.format_exception_only(error)[-1].strip()


def _serve(conn: Connection, workers_end: Connection) -> None:
    """The run process: fly each (fly, task) received, send back (row, None) or (None, error),
    until the worker closes its end of the pipe, or dies."""
    workers_end.close()  # its copy here would keep the pipe open after the worker is gone
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # not the worker's handlers: they ran its loop
    signal.signal(signal.SIGINT, signal.default_int_handler)
    while True:
        try:
            fly, task = conn.recv()
        except EOFError:  # the worker is done, or gone
            return
        try:
            answer = (fly(task), None)
        except Exception as e:  # the task itself raised (it should return a row)
            answer = (None, _error_text(e))
        conn.send(answer)


class RunProcess:
    """A child process that flies runs one at a time for the worker that started it."""

    def __init__(self) -> None:
        context = multiprocessing.get_context()
        self._conn, theirs = context.Pipe()
        self._process = context.Process(
            target=_serve, args=(theirs, self._conn), name="fleetmpc-run", daemon=True
        )
        self._process.start()
        theirs.close()

    @property
    def alive(self) -> bool:
        """False once a run outlived its limit or the process died (it is killed and joined)."""
        return self._process.exitcode is None

    def fly(
        self, fly: Callable[[Any], dict], task: Any, *, limit_s: float
    ) -> tuple[dict | None, str | None]:
        """``fly(task)`` in the run process: (its row, None), or (None, the error) when it
        raised, outlived `limit_s` of wall time, or its process died."""
        try:
            self._conn.send((fly, task))
            if self._conn.poll(limit_s):
                return self._conn.recv()
        except (EOFError, OSError):
            self.close()
            return None, f"its run process died (exit code {self._process.exitcode})"
        except BaseException:  # Ctrl-C, or the worker told to stop: not the run's fault
            self.close()
            raise
        self.close()
        return None, f"time limit {limit_s:g} s exceeded"

    def close(self) -> None:
        """Kill the process (whatever it is doing) and reap it; again: nothing."""
        self._process.kill()
        self._process.join()
        self._conn.close()


class _ThreadsRunProcess(threading.local):
    process: RunProcess | None = None


_of_this_thread = _ThreadsRunProcess()
"""The run process of each thread of this worker process (a Dask worker may have several)."""


def fly_within(
    fly: Callable[[Any], dict], task: Any, *, limit_s: float
) -> tuple[dict | None, str | None]:
    """``fly(task)`` in this thread's run process (started if it has none): its row, or the
    error of a run that raised, outlived `limit_s` or lost its process (`RunProcess.fly`)."""
    if multiprocessing.current_process().daemon:
        return None, DAEMON_HINT
    process = _of_this_thread.process
    if process is None or not process.alive:  # none yet, spent, or it died between runs
        if process is not None:
            process.close()
        process = _of_this_thread.process = RunProcess()
    return process.fly(fly, task, limit_s=limit_s)
