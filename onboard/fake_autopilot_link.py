"""FakeAutopilotLink: a kinematic autopilot behind the AutopilotLink interface, for tests.

It flies a unicycle with the nominal parameters on a time the test drives, holds a position
setpoint ideally, and, as PX4 does, falls back to HOLD when setpoints stop while it is engaged.
No threads, no sockets, no MAVLink.
"""

from fleetmpc.errors import ConfigError
from fleetmpc.onboard.autopilot_link import AutopilotLink, LinkState
from fleetmpc.onboard.core.unicycle import NOMINAL_BETA, advance, wrap
from fleetmpc.protocol.mavlink_map import Autopilot, FlightMode

__all__ = ["FakeAutopilotLink"]


class FakeAutopilotLink(AutopilotLink):
    """A kinematic unicycle behind the link interface, on a time the test drives.

    `advance(duration_ns)` integrates the last setpoint (PX4-like: HOLD after
    `loss_timeout_ns` without one while engaged) and publishes a new snapshot.
    """

    def __init__(
        self,
        *,
        autopilot: Autopilot = Autopilot.PX4,
        system_id: int = 1,
        north_m: float = 0.0,
        east_m: float = 0.0,
        yaw_rad: float = 0.0,
        loss_timeout_ns: int = 1_000_000_000,
    ) -> None:
        super().__init__()
        if loss_timeout_ns <= 0:
            raise ConfigError("loss_timeout_ns", f"must be > 0, got {loss_timeout_ns}")
        self._autopilot = autopilot
        self._system_id = system_id
        self._pose = [float(north_m), float(east_m), float(yaw_rad)]
        self._loss_timeout_ns = loss_timeout_ns
        self._now_ns = 0
        self._last_setpoint_ns: int | None = None
        self.command = (0.0, 0.0)
        self.hold_point: tuple[float, float, float] | None = None
        """The last position setpoint (North, East, Down), until a velocity replaces it."""
        self.setpoint_times_ns: list[int] = []
        self.closed = False
        self.hold_requests = 0

    def connect(self, *, timeout_s: float) -> LinkState:
        self._publish(mode=FlightMode.HOLD, armed=False)
        return self.state()

    def _publish(self, **extra: object) -> None:
        self._update(
            autopilot=self._autopilot,
            system_id=self._system_id,
            time_boot_ns=self._now_ns,
            position_boot_ns=self._now_ns,
            north_m=self._pose[0],
            east_m=self._pose[1],
            down_m=0.0,
            yaw_rad=wrap(self._pose[2]),
            **extra,
        )

    def send_setpoint(self, *, speed_m_s: float, yaw_rate_rad_s: float) -> None:
        self._received((float(speed_m_s), float(yaw_rate_rad_s)), None)

    def send_position_setpoint(self, *, north_m: float, east_m: float, down_m: float) -> None:
        self._received((0.0, 0.0), (float(north_m), float(east_m), float(down_m)))

    def _received(
        self, command: tuple[float, float], hold_point: tuple[float, float, float] | None
    ) -> None:
        """The autopilot's side of one setpoint: what it flies, and when it came."""
        with self._cond:
            self.command, self.hold_point = command, hold_point
            self._last_setpoint_ns = self._now_ns
            self.setpoint_times_ns.append(self._now_ns)
            self.setpoints_sent += 1

    def engage(self, *, timeout_s: float) -> bool:
        self._update(engaged=True, armed=True, mode=FlightMode.OFFBOARD, mode_lost=False)
        return True

    def hold(self) -> bool:
        self.hold_requests += 1
        self._update(engaged=False, mode=FlightMode.HOLD)
        return True

    def advance(self, duration_ns: int, *, steps: int = 10) -> None:
        """Fly the current setpoint for `duration_ns` and publish the new pose."""
        dt_ns = duration_ns // steps
        for _ in range(steps):
            st = self.state()
            flying = st.mode == FlightMode.OFFBOARD and st.armed
            with self._cond:
                last = self._last_setpoint_ns
            if flying and (last is None or self._now_ns - last >= self._loss_timeout_ns):
                self._update(mode=FlightMode.HOLD)
                flying = False
            if flying and self.hold_point is not None:
                self._pose[0], self._pose[1] = self.hold_point[:2]  # an ideal position hold
            elif flying:
                v, w = self.command
                self._pose[:] = advance(*self._pose, v, w, NOMINAL_BETA, dt_ns * 1e-9)
            self._now_ns += dt_ns
        self._publish()

    def close(self) -> None:
        self.closed = True
