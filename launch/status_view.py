"""The status table `fleetmpc up` shows while a fleet flies: one row per vehicle (mode, arming,
slot error, last solve time, oldest neighbour plan, setpoint rate, link age, QP fallbacks) from the
ground station's status file, redrawn in place on a terminal (`rich`) and printed as plain lines
every few seconds otherwise.
"""

import json
import math
import sys
import time
from pathlib import Path

from rich import box
from rich.console import Console
from rich.live import Live
from rich.table import Table

__all__ = ["StatusView", "status_renderable", "status_table"]


def _fmt(value, spec: str, unit: str = "") -> str:
    return "-" if value is None else f"{value:{spec}}{unit}"


_COLUMNS = (
    ("UAV", ">", 4),
    ("mode", "<", 9),
    ("armed", "<", 5),
    ("slot err", ">", 9),
    ("solve", ">", 8),
    ("plan age", ">", 9),
    ("setpoints", ">", 10),
    ("link", ">", 7),
    ("fallbk", ">", 6),
    ("target", "<", 11),
)
"""The status table's columns: heading, alignment and width of its plain-text form."""


def _status_head(status: dict) -> str:
    t = status.get("fleet_s")
    return f"phase {status.get('phase', '?')}, fleet time " + ("-" if t is None else f"{t:6.1f} s")


def _status_cells(status: dict) -> list[list[str]]:
    """One row of cells per vehicle, in the order of `_COLUMNS`."""
    rows = []
    for vid, v in status.get("vehicles", {}).items():
        link = v.get("link_age_s")
        health = "-" if link is None else ("ok" if link < 1.0 else f"{link:4.1f}s!")
        rows.append(
            [
                str(vid),
                v.get("mode") or "-",
                "yes" if v.get("armed") else "no",
                _fmt(v.get("slot_error_m"), "7.3f", " m"),
                _fmt(v.get("solve_ms"), "5.2f", " ms"),
                _fmt(v.get("plan_age_s"), "6.2f", " s"),
                _fmt(v.get("setpoint_rate_hz"), "6.1f", " Hz"),
                health,
                str(v.get("qp_fallbacks", 0)),
                v.get("target") or "-",
            ]
        )
    return rows


def status_table(status: dict) -> list[str]:
    """The status table's plain lines for a ground-station status snapshot."""

    def line(cells) -> str:
        return " ".join(f"{c:{a}{w}}" for c, (_, a, w) in zip(cells, _COLUMNS, strict=True))

    head = [_status_head(status), line(name for name, _, _ in _COLUMNS)]
    return head + [line(cells) for cells in _status_cells(status)]


def status_renderable(status: dict) -> Table:
    """The status table as a `rich` table, for a terminal."""
    table = Table(title=_status_head(status), title_justify="left", box=box.SIMPLE_HEAD)
    for name, align, _ in _COLUMNS:
        table.add_column(name, justify="right" if align == ">" else "left", no_wrap=True)
    for cells in _status_cells(status):
        table.add_row(*(c.strip() for c in cells))
    return table


class StatusView:
    """Redraws the table in place on a terminal; its plain lines every few seconds otherwise.

    Output goes to `console` (stdout by default); `close` ends the drawing.
    """

    def __init__(self, path: Path, *, quiet: bool, console: Console | None = None) -> None:
        self.path = path
        self.quiet = quiet
        self.console = console or Console(force_terminal=sys.stdout.isatty())
        self.tty = self.console.is_terminal
        self._live: Live | None = None
        self._last_plain = -math.inf

    def update(self) -> None:
        if self.quiet:
            return
        try:
            status = json.loads(self.path.read_text())
        except (OSError, ValueError):
            return
        if self.tty:
            if self._live is None:
                self._live = Live(console=self.console, auto_refresh=False)
                self._live.start()
            self._live.update(status_renderable(status), refresh=True)
        elif time.monotonic() - self._last_plain >= 5.0:
            self._last_plain = time.monotonic()
            out = self.console.file
            out.write("\n".join(status_table(status)) + "\n")
            out.flush()

    def close(self) -> None:
        """Stop redrawing, leaving the last table on screen."""
        if self._live is not None:
            self._live.stop()
            self._live = None
