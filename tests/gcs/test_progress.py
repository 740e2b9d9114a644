"""The progress bar of `fleetmpc sim` and the status table of `fleetmpc up`, on a terminal and off.

Away from a terminal both write plain lines that CI logs and tests read, so their text is pinned
here; on a terminal (a `rich` console forced to be one, writing to a string) they must draw,
stop, and give the cursor back.
"""

import io
import json
import re

import pytest
from rich.console import Console

from fleetmpc.gcs.progress import ProgressBar
from fleetmpc.launch.status_view import StatusView, status_renderable, status_table

HIDE_CURSOR, SHOW_CURSOR = "\x1b[?25l", "\x1b[?25h"

STATUS = {
    "phase": "flying",
    "fleet_s": 12.34,
    "vehicles": {
        "1": {
            "mode": "OFFBOARD",
            "armed": True,
            "slot_error_m": 0.0123,
            "solve_ms": 1.5,
            "plan_age_s": 0.2,
            "setpoint_rate_hz": 5.0,
            "link_age_s": 0.1,
            "qp_fallbacks": 2,
            "target": "holding",
        },
        "12": {"mode": None, "armed": False, "link_age_s": 3.25},
    },
}

STATUS_LINES = [
    "phase flying, fleet time   12.3 s",
    " UAV mode      armed  slot err    solve  plan age  setpoints    link fallbk target     ",
    "   1 OFFBOARD  yes     0.012 m  1.50 ms    0.20 s     5.0 Hz      ok      2 holding    ",
    "  12 -         no            -        -         -          -   3.2s!      0 -          ",
]


def _terminal(width: int = 120) -> Console:
    return Console(force_terminal=True, file=io.StringIO(), width=width)


def _restored_cursor(text: str) -> bool:
    """The drawing hid the cursor and showed it again when it stopped."""
    return HIDE_CURSOR in text and text.rfind(SHOW_CURSOR) > text.rfind(HIDE_CURSOR)


def test_off_a_terminal_the_bar_writes_a_line_every_quarter():
    out = io.StringIO()
    with ProgressBar("sim paper", stream=out) as bar:
        assert not bar.tty
        for k in range(301):
            bar(k * 0.2, 60.0)
        bar(60.0, 60.0)  # after 100 %: nothing more
    lines = out.getvalue().splitlines()
    assert [int(re.search(r"(\d+)%", line).group(1)) for line in lines] == [0, 25, 50, 75, 100]
    pattern = r"sim paper \[[#.]{30}\] +\d+%  +[\d.]+/60\.0 s sim, +[\d.]+ s wall"
    assert all(re.fullmatch(pattern, line) for line in lines), lines
    assert lines[-1].startswith("sim paper [" + "#" * 30 + "] 100%    60.0/60.0 s sim, ")
    assert "\x1b" not in out.getvalue()


def test_off_a_terminal_the_bar_marks_each_quarter_it_passes():
    out = io.StringIO()
    with ProgressBar("sim calm", stream=out) as bar:
        for k in range(1, 51):  # 2 % a step: no call lands on 25 % or 75 %
            bar(k * 0.2, 10.0)
    pcts = [int(re.search(r"(\d+)%", line).group(1)) for line in out.getvalue().splitlines()]
    assert pcts == [2, 26, 50, 76, 100]


def test_off_a_terminal_a_closed_bar_writes_nothing_more():
    out = io.StringIO()
    bar = ProgressBar("sim calm", stream=out)
    bar(0.0, 10.0)
    bar(2.5, 10.0)
    bar.close()
    bar(10.0, 10.0)
    assert len(out.getvalue().splitlines()) == 2


def test_on_a_terminal_the_bar_draws_and_stops_at_100_percent():
    console = _terminal()
    bar = ProgressBar("sim paper", console=console)
    assert bar.tty
    for k in range(301):
        bar(k * 0.2, 60.0)
    text = console.file.getvalue()
    assert "100%" in text and "60.0/60.0 s sim" in text and "s wall" in text
    assert _restored_cursor(text)
    bar(60.0, 60.0)
    bar.close()  # already stopped: nothing more
    assert console.file.getvalue() == text


def test_on_a_terminal_the_bar_stops_when_the_run_raises():
    console = _terminal()
    with pytest.raises(RuntimeError), ProgressBar("sim paper", console=console) as bar:
        bar(15.0, 60.0)
        raise RuntimeError("solver diverged")
    text = console.file.getvalue()
    assert "15.0/60.0 s sim" in text and "100%" not in text
    assert _restored_cursor(text)


def test_status_table_plain_lines():
    assert status_table(STATUS) == STATUS_LINES
    assert status_table({}) == ["phase ?, fleet time -", STATUS_LINES[1]]


def test_status_table_for_a_terminal():
    console = Console(file=io.StringIO(), width=120)
    console.print(status_renderable(STATUS))
    text = console.file.getvalue()
    assert "phase flying, fleet time   12.3 s" in text
    for cells in (("UAV", "mode", "slot err", "setpoints", "fallbk"), ("OFFBOARD", "0.012 m")):
        assert all(c in text for c in cells), text
    assert re.search(r"12 +- +no( +-){4} +3\.2s! +0", text), text


def test_status_view_off_a_terminal_prints_the_plain_lines(tmp_path):
    path = tmp_path / "status.json"
    path.write_text(json.dumps(STATUS))
    out = io.StringIO()
    view = StatusView(path, quiet=False, console=Console(file=out, force_terminal=False))
    view.update()
    view.update()  # within a few seconds of the last: not printed again
    view.close()
    assert out.getvalue() == "\n".join(STATUS_LINES) + "\n"


def test_status_view_on_a_terminal_redraws_in_place(tmp_path):
    path = tmp_path / "status.json"
    console = _terminal()
    view = StatusView(path, quiet=False, console=console)
    view.update()  # no status file yet: nothing drawn
    assert console.file.getvalue() == ""
    path.write_text(json.dumps(STATUS))
    view.update()
    path.write_text(json.dumps({**STATUS, "fleet_s": 14.0}))
    view.update()
    view.close()
    text = console.file.getvalue()
    assert "fleet time   12.3 s" in text and "fleet time   14.0 s" in text
    assert "\x1b[2K" in text  # the second table is drawn over the first
    assert _restored_cursor(text)
