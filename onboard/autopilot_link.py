"""AutopilotLink: how the agent flies a MAVLink autopilot, chosen by URL.

- any pymavlink URL (``udpin:HOST:PORT``, ``udpout:``, ``tcp:HOST:PORT``, ``serial:DEV:BAUD``,
  or a bare device path): `fleetmpc.onboard.mavlink_autopilot_link.MavlinkAutopilotLink`;
- ``fake://`` or ``fake://px4`` / ``fake://ardupilot``:
  `fleetmpc.onboard.fake_autopilot_link.FakeAutopilotLink`, an in-package kinematic autopilot
  for tests.

Every link publishes its validated telemetry as `LinkState` snapshots: `state()` returns the
latest; `wait_state(newer_than_ns=...)` blocks until telemetry newer than a boot time arrives.
Losing the engaged mode (the autopilot failing safe to HOLD) is detected and reported in the
snapshot (`mode_lost`), never fought.
"""

import math
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, replace

from fleetmpc.errors import ConfigError, FleetMpcError
from fleetmpc.protocol.mavlink_map import (
    Autopilot,
    FlightMode,
    LandedState,
    custom_mode_name,
    flight_mode_name,
)

__all__ = [
    "AutopilotLink",
    "AutopilotLinkError",
    "LinkState",
    "open_autopilot_link",
]


class AutopilotLinkError(FleetMpcError):
    """The autopilot could not be reached or refused to fly."""


@dataclass(frozen=True)
class LinkState:
    """The latest validated telemetry of the autopilot."""

    autopilot: Autopilot | None = None
    """Autopilot detected from its HEARTBEAT (None until one arrives)."""
    system_id: int = 0
    """MAVLink system id of the autopilot (0 until a HEARTBEAT arrives)."""
    time_boot_ns: int = -1
    """Autopilot boot time of the newest LOCAL_POSITION_NED or ATTITUDE [ns] (-1: none yet)."""
    received_ns: int = 0
    """Host clock (`now_ns` of the link) when that message arrived [ns]."""
    position_boot_ns: int = -1
    """Boot time of the newest valid position [ns] (-1: none yet)."""
    north_m: float = math.nan
    """Local position North [m]."""
    east_m: float = math.nan
    """Local position East [m]."""
    down_m: float = math.nan
    """Local position Down [m] (minus the altitude above home)."""
    yaw_rad: float = math.nan
    """Heading [rad], clockwise from North."""
    vel_north_m_s: float = math.nan
    """Ground velocity North [m/s], from the same message as the position (nan: not reported)."""
    vel_east_m_s: float = math.nan
    """Ground velocity East [m/s]."""
    armed: bool = False
    """HEARTBEAT's SAFETY_ARMED flag."""
    mode: FlightMode | None = None
    """Flight mode from HEARTBEAT.custom_mode (None: unknown or not reported)."""
    custom_mode: int | None = None
    """HEARTBEAT.custom_mode as sent (None: not reported)."""
    engaged: bool = False
    """The link has put the vehicle in offboard/guided mode."""
    mode_lost: bool = False
    """After engaging, the autopilot left offboard/guided (e.g. failsafe to HOLD)."""
    heartbeats: int = 0
    """Valid HEARTBEATs received."""
    rejected: int = 0
    """Messages dropped because a field failed validation."""
    last_text: str = ""
    """Last STATUSTEXT from the autopilot."""
    landed_state: LandedState | None = None
    """EXTENDED_SYS_STATE's landed state (None: not reported)."""

    @property
    def mode_name(self) -> str | None:
        """The mode as the autopilot names it (ArduCopter: GUIDED, LOITER, RTL, ...; PX4:
        OFFBOARD, HOLD, ...), None while unknown."""
        if self.custom_mode is not None and self.autopilot is not None:
            return custom_mode_name(self.custom_mode, self.autopilot)
        return None if self.mode is None else flight_mode_name(self.mode, self.autopilot)

    @property
    def has_pose(self) -> bool:
        """Position and heading both received."""
        return math.isfinite(self.north_m) and math.isfinite(self.yaw_rad)


_TELEMETRY_FIELDS = frozenset(
    {
        "time_boot_ns",
        "received_ns",
        "position_boot_ns",
        "north_m",
        "east_m",
        "down_m",
        "yaw_rad",
        "vel_north_m_s",
        "vel_east_m_s",
        "heartbeats",
        "rejected",
    }
)
"""LinkState fields that change with every message: no event of their own."""


class AutopilotLink(ABC):
    """Connect, read telemetry, send velocity + yaw-rate setpoints, arm/mode, close."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._state = LinkState()
        self.setpoints_sent = 0
        self._events = 0
        """Changes of the state other than telemetry (`_TELEMETRY_FIELDS`) so far."""
        self._waits: list[int] = []
        """The boot times [ns] the threads in `wait_state` wait to see passed."""

    # -- state shared between the reader and the runner -----------------------------------------
    def _update(self, **changes: object) -> None:
        """Take a new state. Waiters wake on an event (a change of anything but telemetry) or
        on telemetry past the boot time one of them waits for, not on every message: at 60
        messages a second a wake-up each would cost an agent more than its steps."""
        with self._cond:
            old = self._state
            state = replace(old, **changes)
            if state.engaged and state.mode is not None and state.mode != FlightMode.OFFBOARD:
                state = replace(state, mode_lost=True)
            self._state = state
            if state.mode_lost != old.mode_lost or any(
                getattr(state, k) != getattr(old, k) for k in changes if k not in _TELEMETRY_FIELDS
            ):
                self._events += 1
                self._cond.notify_all()
            elif self._waits and state.time_boot_ns > min(self._waits):
                self._cond.notify_all()

    def state(self) -> LinkState:
        """The latest validated snapshot."""
        with self._cond:
            return self._state

    def wait_state(self, *, newer_than_ns: int, timeout_s: float) -> LinkState:
        """Block until telemetry newer than `newer_than_ns` (boot time), an event (a change of
        the mode, arming, engagement, landed state, autopilot or text) or the timeout."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            events = self._events
            self._waits.append(newer_than_ns)
            try:
                while self._state.time_boot_ns <= newer_than_ns and self._events == events:
                    left = deadline - time.monotonic()
                    if left <= 0 or not self._cond.wait(left):
                        break
            finally:
                self._waits.remove(newer_than_ns)
            return self._state

    # -- what an implementation provides --------------------------------------------------------
    @abstractmethod
    def connect(self, *, timeout_s: float) -> LinkState:
        """Wait for the autopilot's HEARTBEAT and first pose; AutopilotLinkError on timeout."""

    @abstractmethod
    def send_setpoint(self, *, speed_m_s: float, yaw_rate_rad_s: float) -> None:
        """Send one body-frame forward speed + yaw rate setpoint (never raises)."""

    @abstractmethod
    def send_position_setpoint(self, *, north_m: float, east_m: float, down_m: float) -> None:
        """Send one LOCAL_NED point to fly to and hold (never raises)."""

    @abstractmethod
    def engage(self, *, timeout_s: float) -> bool:
        """Put the vehicle under external control (PX4 offboard, ArduPilot guided + takeoff)."""

    @abstractmethod
    def hold(self) -> bool:
        """Ask the autopilot to hold position (PX4 HOLD, ArduPilot LOITER); best effort."""

    @abstractmethod
    def close(self) -> None:
        """Stop the reader and release the connection; idempotent."""


def open_autopilot_link(
    url: str,
    *,
    system_id: int | None = None,
    vehicle_id: int | None = None,
    log: Callable[[str], None] | None = None,
    home_deg: tuple[float, float] | None = None,
    signing_key: bytes | None = None,
) -> AutopilotLink:
    """The AutopilotLink a URL names (see the module docstring). `system_id`: the autopilot's
    MAVLink system id to insist on (None: the first autopilot heard); a fake autopilot takes it,
    else `vehicle_id`. `home_deg`: the scenario's origin (latitude, longitude), against which a
    MAVLink link places the vehicle whatever its autopilot's own local origin."""
    # Both implementations build on this module's interface.
    from fleetmpc.onboard.fake_autopilot_link import FakeAutopilotLink
    from fleetmpc.onboard.mavlink_autopilot_link import MavlinkAutopilotLink

    if not isinstance(url, str) or not url:
        raise ConfigError("mavlink_url", f"must be a connection string, got {url!r}")
    if url.startswith("fake://"):
        kind = url.removeprefix("fake://") or "px4"
        autopilots = {"px4": Autopilot.PX4, "ardupilot": Autopilot.ARDUPILOTMEGA}
        if kind not in autopilots:
            raise ConfigError("mavlink_url", f"fake://{kind}: known fakes are px4, ardupilot")
        return FakeAutopilotLink(autopilot=autopilots[kind], system_id=system_id or vehicle_id or 1)
    return MavlinkAutopilotLink(
        url, system_id=system_id, log=log, home_deg=home_deg, signing_key=signing_key
    )
