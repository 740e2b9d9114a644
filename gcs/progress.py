"""A small progress bar for long runs: redrawn in place on a terminal, sparse lines otherwise."""

import sys
import time
from typing import TextIO

__all__ = ["ProgressBar"]


class ProgressBar:
    """Call with (done, total); prints to `stream` (stderr by default)."""

    def __init__(self, label: str, *, stream: TextIO | None = None, width: int = 30) -> None:
        self.label = label
        self.stream = stream or sys.stderr
        self.width = width
        self._tty = self.stream.isatty()
        self._last_pct = -1
        self._start = time.monotonic()

    def __call__(self, done: float, total: float) -> None:
        frac = 0.0 if total <= 0 else min(max(done / total, 0.0), 1.0)
        pct = int(frac * 100)
        step = 1 if self._tty else 25
        if pct == self._last_pct or (pct % step and pct != 100):
            return
        self._last_pct = pct
        filled = int(frac * self.width)
        bar = "#" * filled + "." * (self.width - filled)
        elapsed = time.monotonic() - self._start
        line = (
            f"{self.label} [{bar}] {pct:3d}%  {done:6.1f}/{total:.1f} s sim, {elapsed:5.1f} s wall"
        )
        if self._tty:
            self.stream.write("\r" + line + ("\n" if pct == 100 else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
