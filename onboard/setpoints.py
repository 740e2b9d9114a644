"""The setpoint stream to an autopilot: the latest command sent at a fixed rate from a thread of
its own, whatever the control loop does (PX4 leaves OFFBOARD after COM_OF_LOSS_T without
setpoints, ArduPilot stops after GUID_TIMEOUT), and the wind-down that holds a vehicle where it is
when an agent stops.

A command is not flown for ever: once it is older than its lifetime (`COMMAND_LIFETIME_PERIODS`
control periods: the agent is starved of CPU or stalled), the stream fades it linearly to a stop
over one more lifetime, so an overloaded agent's vehicle slows down and stops instead of flying
a stale command into a neighbour (docs/design.md, "Safety": stopping stays within the margins
the others keep from its last plan). A new command is flown at once.
"""

import bisect
import contextlib
import math
import threading
import time
from collections.abc import Callable

import numpy as np

from fleetmpc.errors import ConfigError
from fleetmpc.onboard.autopilot_link import AutopilotLink

__all__ = ["COMMAND_LIFETIME_PERIODS", "SetpointStreamer", "gap_stats_ms", "wind_down"]

COMMAND_LIFETIME_PERIODS = 2.0
"""Control periods a command is flown as it is before the stream fades it to a stop."""


def gap_stats_ms(times_ns: list[int]) -> dict[str, float]:
    """p50 / p99 / max of the gaps between consecutive times [ms]."""
    if len(times_ns) < 2:
        return {"p50": math.nan, "p99": math.nan, "max": math.nan, "count": float(len(times_ns))}
    gaps = np.diff(np.asarray(times_ns, dtype=np.int64)) * 1e-6
    return {
        "p50": float(np.percentile(gaps, 50)),
        "p99": float(np.percentile(gaps, 99)),
        "max": float(gaps.max()),
        "count": float(len(times_ns)),
    }


class SetpointStreamer:
    """Sends the latest command to the autopilot at a fixed rate from its own thread.

    The command is a velocity (`set_command`) or a point to hold (`hold_position`, sent at the
    altitude the link last reported; zeros until it reports one); the newest call wins.
    """

    def __init__(
        self,
        link: AutopilotLink,
        *,
        period_s: float,
        command_lifetime_s: float | None = None,
        monotonic_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if not 0.001 <= period_s <= 0.1:
            raise ConfigError("setpoint period_s", f"must be in [0.001, 0.1] s, got {period_s}")
        if command_lifetime_s is not None and not command_lifetime_s > 0:
            raise ConfigError(
                "command_lifetime_s", f"must be > 0 (or None), got {command_lifetime_s}"
            )
        self._link = link
        self._period_s = period_s
        self._lifetime_ns = None if command_lifetime_s is None else round(command_lifetime_s * 1e9)
        """Wall time a command is flown as it is [ns]; None: for ever."""
        self._now = monotonic_ns
        self._lock = threading.Lock()
        self._command = (0.0, 0.0)
        self._command_ns = self._now()
        self.faded_sends = 0
        """Setpoints sent from a command older than its lifetime (faded toward a stop)."""
        self._hold: tuple[float, float] | None = None
        self._stop = threading.Event()
        self.send_times_ns: list[int] = []
        self._thread = threading.Thread(target=self._loop, name="setpoints", daemon=True)

    def set_command(self, *, speed_m_s: float, yaw_rate_rad_s: float) -> None:
        with self._lock:
            self._command = (float(speed_m_s), float(yaw_rate_rad_s))
            self._command_ns = self._now()
            self._hold = None

    def hold_position(self, *, north_m: float, east_m: float) -> None:
        """Stream position setpoints at (North, East) from now on, until `set_command`."""
        with self._lock:
            self._hold = (float(north_m), float(east_m))

    def longest_gap_ns(self, *, window_ns: int) -> int:
        """The longest time between consecutive sends over the last `window_ns` of the
        streamer's clock, counting the time since the last send [ns] (0 before any send)."""
        times = self.send_times_ns
        end = len(times)
        if end == 0:
            return 0
        now = self._now()
        start = max(0, bisect.bisect_right(times, now - window_ns, 0, end) - 1)
        recent = times[start:end]
        gaps = [b - a for a, b in zip(recent, recent[1:], strict=False)]
        return max([now - recent[-1], *gaps])

    def rate_hz(self, *, window_ns: int) -> float:
        """Setpoints sent per second of the streamer's clock over its last `window_ns`."""
        if window_ns <= 0:
            raise ConfigError("window_ns", f"must be > 0, got {window_ns}")
        times = self.send_times_ns  # appended by the streaming thread, never reordered
        end = len(times)
        start = bisect.bisect_right(times, self._now() - window_ns, 0, end)
        return (end - start) * 1e9 / window_ns

    def flown(self) -> tuple[float, float]:
        """The velocity command to send now: the latest, or once it is older than its lifetime,
        the same faded linearly to a stop over one more lifetime (module docstring)."""
        with self._lock:
            (v, w), since = self._command, self._command_ns
        life = self._lifetime_ns
        age = self._now() - since
        if life is None or age <= life:
            return v, w
        self.faded_sends += 1
        keep = max(0.0, 1.0 - (age - life) / life)
        return v * keep, w * keep

    def start(self) -> None:
        self._thread.start()

    def _loop(self) -> None:
        next_s = time.monotonic()
        while not self._stop.is_set():
            with self._lock:
                hold = self._hold
            v, w = self.flown()
            down = self._link.state().down_m if hold is not None else math.nan
            # A link must not raise, but never let the stream die.
            with contextlib.suppress(Exception):
                if math.isfinite(down):
                    self._link.send_position_setpoint(north_m=hold[0], east_m=hold[1], down_m=down)
                else:
                    self._link.send_setpoint(speed_m_s=v, yaw_rate_rad_s=w)
            self.send_times_ns.append(self._now())
            next_s += self._period_s
            delay = next_s - time.monotonic()
            if delay < 0:
                next_s = time.monotonic()
                delay = 0.0
            self._stop.wait(delay)

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1.0)


def wind_down(
    link: AutopilotLink, streamer: SetpointStreamer | None, *, engaged: bool, settle_s: float = 0.05
) -> None:
    """The agent's last act on its vehicle: leave it holding where it is.

    The stream switches to position setpoints where the link last saw the vehicle (zero velocity
    when it never reported a pose) for `settle_s` of wall time, so the last command the autopilot
    flies is a point, not the agent's last velocity, then stops; an engaged vehicle is then asked
    to HOLD (a real autopilot would otherwise fall back to its failsafe when the stream ends).
    """
    if streamer is not None:
        state = link.state()
        if state.has_pose:
            streamer.hold_position(north_m=state.north_m, east_m=state.east_m)
        else:
            streamer.set_command(speed_m_s=0.0, yaw_rate_rad_s=0.0)
        time.sleep(settle_s)
        streamer.stop()
    if engaged:
        link.hold()
