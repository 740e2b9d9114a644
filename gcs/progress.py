"""A progress bar for long runs: redrawn in place on a terminal, sparse lines otherwise."""

import sys
import time
from typing import TextIO

from rich.console import Console
from rich.progress import BarColumn, Progress, TaskID, TaskProgressColumn, TextColumn

__all__ = ["ProgressBar"]

_PLAIN_STEP_PCT = 25
"""Away from a terminal, a line each time the run passes a multiple of this percentage."""


class ProgressBar:
    """Progress of a run, called with (done, total) simulated seconds.

    On a terminal it is a `rich` bar redrawn in place; anywhere else (a pipe, a log file) it
    writes a plain line as the run passes 0, 25, 50, 75 and 100 %. Output goes to `stream`
    (stderr by default), or to `console` when one is given (its `is_terminal` then picks the
    kind of output).

    The bar stops by itself at 100 %; use it as a context manager, or call `close`, so that it
    also stops when the run ends early or raises.
    """

    def __init__(
        self,
        label: str,
        *,
        stream: TextIO | None = None,
        console: Console | None = None,
        width: int = 30,
    ) -> None:
        if console is None:
            stream = stream or sys.stderr
            console = Console(file=stream, force_terminal=stream.isatty())
        self.label = label
        self.console = console
        self.width = width
        self.tty = console.is_terminal
        self._last_step = -1
        self._start = time.monotonic()
        self._progress: Progress | None = None
        self._task: TaskID | None = None
        self._closed = False

    def __enter__(self) -> "ProgressBar":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __call__(self, done: float, total: float) -> None:
        if self._closed:
            return
        frac = 0.0 if total <= 0 else min(max(done / total, 0.0), 1.0)
        pct = int(frac * 100)
        if self.tty:
            self._draw(done, total)
        elif pct // _PLAIN_STEP_PCT > self._last_step:
            self._last_step = pct // _PLAIN_STEP_PCT
            self._write_line(done, total, frac, pct)
        if pct == 100:
            self.close()

    def close(self) -> None:
        """Stop the bar, leaving its last state on screen; later calls draw nothing."""
        self._closed = True
        if self._progress is not None:
            self._progress.stop()
            self._progress = None

    def _draw(self, done: float, total: float) -> None:
        if self._progress is None:
            self._progress = Progress(
                TextColumn("{task.description}", markup=False),
                BarColumn(bar_width=self.width),
                TaskProgressColumn(),
                TextColumn("{task.completed:6.1f}/{task.total:.1f} s sim", markup=False),
                TextColumn("{task.elapsed:5.1f} s wall", markup=False),
                console=self.console,
            )
            self._task = self._progress.add_task(self.label, total=total)
            self._progress.start()
        self._progress.update(self._task, completed=min(done, total), total=total)

    def _write_line(self, done: float, total: float, frac: float, pct: int) -> None:
        filled = int(frac * self.width)
        bar = "#" * filled + "." * (self.width - filled)
        elapsed = time.monotonic() - self._start
        line = (
            f"{self.label} [{bar}] {pct:3d}%  {done:6.1f}/{total:.1f} s sim, {elapsed:5.1f} s wall"
        )
        self.console.file.write(line + "\n")
        self.console.file.flush()
