"""The live target sources behind one interface, chosen by URL (``--source``):
``mavlink:CONNECTION`` and ``track:FILE`` (the scripted target, ``script``, has its own loop in
`fleetmpc.targets.process`: it needs no screen).

A source's `poll(timeout_s, now_s)` returns the fixes that arrived (waiting up to `timeout_s`
wall seconds), `finished` says it has no more, `close()` lets go of it.
"""

import time
from pathlib import Path
from typing import Protocol

from fleetmpc.errors import ConfigError
from fleetmpc.targets.fix import Fix
from fleetmpc.targets.track_file import read_fixes

__all__ = ["TargetSource", "TrackReplay", "open_source"]

REPLAY_POLL_S = 0.005
"""A replay looks for due fixes this often (wall seconds): a fix goes out at most this late
(times the fleet's speed), which is what its source clock's delay spread then shows."""


class TargetSource(Protocol):
    finished: bool

    def poll(self, timeout_s: float, now_s: float) -> list[Fix]: ...

    def close(self) -> None: ...


class TrackReplay:
    """A recorded track's fixes, each handed over once fleet time reaches its time on the
    recording, the first fix at fleet time `start_s`; its fixes unchecked (the screen checks)."""

    def __init__(self, fixes: list[Fix], *, start_s: float) -> None:
        if not fixes:
            raise ConfigError("--source", "the track holds no fixes")
        self._fixes = fixes
        self._shift = start_s - fixes[0].source_s
        self._next = 0
        self.finished = False

    def poll(self, timeout_s: float, now_s: float) -> list[Fix]:
        out = []
        while self._next < len(self._fixes):
            fix = self._fixes[self._next]
            if fix.source_s == fix.source_s and fix.source_s + self._shift > now_s:  # (NaN: now)
                break
            out.append(fix)
            self._next += 1
        self.finished = self._next >= len(self._fixes)
        if not out and not self.finished:
            time.sleep(min(timeout_s, REPLAY_POLL_S))
        return out

    def close(self) -> None:
        pass


class _Mavlink:
    def __init__(self, connection: str) -> None:
        from fleetmpc.targets.mavlink_source import MavlinkSource

        self._source = MavlinkSource(connection)
        self.finished = False

    def poll(self, timeout_s: float, now_s: float) -> list[Fix]:
        return self._source.poll(timeout_s)

    def close(self) -> None:
        self._source.close()


def open_source(url: str, *, system_id: int | None, track_start_s: float) -> TargetSource:
    """The source a ``--source`` URL names (not ``script``)."""
    kind, _, rest = url.partition(":")
    if kind == "mavlink" and rest:
        if system_id is None:
            raise ConfigError("--sysid", "a MAVLink source needs the system id to follow")
        return _Mavlink(rest)
    if kind == "track" and rest:
        return TrackReplay(read_fixes(Path(rest), system_id=system_id), start_s=track_start_s)
    raise ConfigError("--source", f"expected script, mavlink:CONNECTION or track:FILE, got {url!r}")
