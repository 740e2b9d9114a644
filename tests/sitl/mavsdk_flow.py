"""The MAVSDK flight used by the MAVSDK and MAVProxy tests, and an independent observer.

MAVSDK here is the native 4.x binding (`mavsdk.asyncio`), a client nobody here wrote. The observer
is a pymavlink client on another link that measures speed and yaw rate from successive positions
and headings against time_boot_ms, independently of the velocity fields the vehicle fills in.
"""

import asyncio
import math
import threading

from mavsdk import ComponentType
from mavsdk.asyncio import Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.offboard import OffboardAsync, OffboardError, VelocityBodyYawspeed
from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync
from sim_client import SimClient

from fleetmpc.protocol.local_frame import ned_from_geodetic

HOME = dict(home_lat_deg=47.397742, home_lon_deg=8.545594)
FORWARD_M_S = 1.5
YAWSPEED_DEG_S = 10.0


class Observer:
    """Collects (time_boot_ms, north, east, yaw) samples from a pymavlink client in a thread."""

    def __init__(self, client: SimClient) -> None:
        self.client = client
        self.positions: list[tuple[int, float, float]] = []
        self.yaws: list[tuple[int, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> "Observer":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        while not self._stop.is_set():
            m = self.client.pump()
            if m is None:
                continue
            if m.get_type() == "LOCAL_POSITION_NED":
                self.positions.append((m.time_boot_ms, m.x, m.y))
            elif m.get_type() == "ATTITUDE":
                self.yaws.append((m.time_boot_ms, m.yaw))

    def rates_since(self, t0_ms: int) -> tuple[float, float]:
        """Mean path speed [m/s] and yaw rate [rad/s] over the samples after `t0_ms`."""
        p = [s for s in list(self.positions) if s[0] >= t0_ms]
        y = [s for s in list(self.yaws) if s[0] >= t0_ms]
        assert len(p) >= 10 and len(y) >= 10, "too few samples"
        path = sum(math.dist(a[1:], b[1:]) for a, b in zip(p, p[1:], strict=False))
        turned = sum(
            math.remainder(b[1] - a[1], 2 * math.pi) for a, b in zip(y, y[1:], strict=False)
        )
        return path / ((p[-1][0] - p[0][0]) / 1000), turned / ((y[-1][0] - y[0][0]) / 1000)


async def poll(read, predicate, *, timeout_s: float = 20.0, interval_s: float = 0.1):
    """Read a MAVSDK value until `predicate` holds."""
    deadline = asyncio.get_running_loop().time() + timeout_s
    while True:
        value = await read()
        if predicate(value):
            return value
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError(f"last value {value}")
        await asyncio.sleep(interval_s)


async def mavsdk_flight(port: int, observer: Observer | None = None) -> dict:
    """Discover, read position, arm, then MAVSDK's own offboard flow (one setpoint, then
    `offboard.start()` at once: accepted, as PX4's code accepts it), fly, stop."""
    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    out: dict = {}
    async with Mavsdk(config) as drone:
        await drone.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = await drone.first_autopilot(timeout_s=20.0)
        assert system is not None, "MAVSDK did not discover the vehicle"
        out["system_id"] = await system.get_system_id()
        out["autopilot"] = (await system.autopilot_type()).name
        telemetry, action, offboard = (
            TelemetryAsync(system),
            ActionAsync(system),
            OffboardAsync(system),
        )

        out["position"] = await poll(telemetry.position, lambda p: math.isfinite(p.latitude_deg))
        out["home"] = await poll(telemetry.home, lambda h: math.isfinite(h.latitude_deg))
        out["ned"] = await telemetry.position_velocity_ned()

        await action.arm()
        out["armed"] = await poll(telemetry.armed, bool)
        await offboard.set_velocity_body(
            VelocityBodyYawspeed(FORWARD_M_S, 0.0, 0.0, YAWSPEED_DEG_S)
        )
        try:
            await offboard.start()  # right after the first setpoint
            out["start"] = "accepted"
        except OffboardError as e:
            out["start"] = e.result
        out["mode"] = await poll(telemetry.flight_mode, lambda m: m == FlightMode.OFFBOARD)
        await asyncio.sleep(1.0)  # let the speed settle before measuring
        t0_ms = observer.client.t_ms if observer else 0
        await asyncio.sleep(2.0)
        pv = await telemetry.position_velocity_ned()
        out["speed_m_s"] = math.hypot(pv.velocity.north_m_s, pv.velocity.east_m_s)
        out["yaw_rate_rad_s"] = (await telemetry.attitude_angular_velocity_body()).yaw_rad_s
        if observer is not None:
            out["observed"] = observer.rates_since(t0_ms)
        out["mode_in_flight"] = await telemetry.flight_mode()

        await offboard.stop()
        out["mode_after_stop"] = await poll(telemetry.flight_mode, lambda m: m == FlightMode.HOLD)
        stopped = await poll(
            telemetry.position_velocity_ned,
            lambda p: math.hypot(p.velocity.north_m_s, p.velocity.east_m_s) < 1e-6,
            timeout_s=10.0,
        )
        out["speed_after_stop"] = math.hypot(stopped.velocity.north_m_s, stopped.velocity.east_m_s)
    return out


def position_ned(position) -> tuple[float, float]:
    """(north, east) [m] of a MAVSDK Position relative to the scenarios' default home."""
    return ned_from_geodetic(position.latitude_deg, position.longitude_deg, **HOME)
