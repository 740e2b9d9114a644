"""The fleet runner of one vehicle: `Agent.step` on the autopilot's clock, over real links.

Time base. Every process of a fleet shares *fleet time*: simulated nanoseconds since a common
epoch, ``fleet_ns = (host_wall_ns - epoch_ns) * speed`` (`FleetClock`; the SITL, the target and
the agents are started with the same ``--epoch-ns`` and ``--speed``). The runner does not step on
the host clock: it steps on the autopilot's ``time_boot_ms`` (so the SITL's ``--speed`` works
end to end) shifted by the boot offset `ClockSync` estimates — the minimum over all telemetry of
``fleet_ns(received) - time_boot_ns`` (transport latency only ever makes a sample larger).
Plans, statuses and the target's observations are stamped in fleet time, so neighbours' ages and
target stamps compare directly. Without an epoch, fleet time is the autopilot's boot time.

Loop. Each time the autopilot's fleet time crosses a period boundary k·τ (k·τ >= 0), the runner
steps the agent at stamp k·τ with the latest pose, the newest target observation and the
neighbours' latest plans, hands the command to the `SetpointStreamer` (a separate thread that
sends the latest command at a fixed rate whatever the loop does), and publishes the plan and a
status. Before the first step the streamer sends zeros, which is what PX4 needs to accept
OFFBOARD. An exception in a step never leaves the loop: the command becomes zero and the status
says why. Mode loss is reported, not fought.
"""

import contextlib
import json
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from onboard.autopilot_link import AutopilotLink, LinkState
from onboard.core.agent import Agent, AgentInput, AgentOutput
from onboard.core.errors import ConfigError
from onboard.planbus import PlanBus
from protocol.mavlink_map import FlightMode
from protocol.messages import (
    LearnedParams,
    NeighbourPlanAge,
    PlanStatus,
    VehicleMode,
    VehicleStatus,
)

__all__ = [
    "ClockSync",
    "FleetClock",
    "FleetRunner",
    "RunnerSettings",
    "SetpointStreamer",
    "gap_stats_ms",
]

_MAX_NEIGHBOURS = 8


@dataclass(frozen=True)
class FleetClock:
    """Fleet time from the host's wall clock: (wall - epoch) x speed."""

    epoch_ns: int | None = None
    """Host wall-clock time (time.time_ns) of fleet time 0; None: fleet time = autopilot time."""
    speed: float = 1.0
    """Simulated seconds per wall-clock second."""

    def __post_init__(self) -> None:
        if not (isinstance(self.speed, int | float) and 0.01 <= self.speed <= 1000.0):
            raise ConfigError("speed", f"must be in [0.01, 1000], got {self.speed!r}")
        if self.epoch_ns is not None and not isinstance(self.epoch_ns, int):
            raise ConfigError("epoch_ns", f"must be an integer, got {self.epoch_ns!r}")

    def fleet_ns(self, wall_ns: int) -> int:
        """Fleet time at host wall time `wall_ns` (0 without an epoch)."""
        if self.epoch_ns is None:
            return 0
        return round((wall_ns - self.epoch_ns) * self.speed)


class ClockSync:
    """Offset from the autopilot's boot time to fleet time, by a minimum filter."""

    def __init__(self, clock: FleetClock) -> None:
        self.clock = clock
        self.offset_ns: int | None = 0 if clock.epoch_ns is None else None
        self.samples = 0
        self.last_sample_ns = 0

    def update(self, *, time_boot_ns: int, received_wall_ns: int) -> None:
        """Take one telemetry sample."""
        if self.clock.epoch_ns is None or time_boot_ns < 0:
            return
        sample = self.clock.fleet_ns(received_wall_ns) - time_boot_ns
        self.samples += 1
        self.last_sample_ns = sample
        if self.offset_ns is None or sample < self.offset_ns:
            self.offset_ns = sample

    def fleet_ns(self, time_boot_ns: int) -> int | None:
        """Fleet time of an autopilot boot time (None before the first sample)."""
        return None if self.offset_ns is None else time_boot_ns + self.offset_ns


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
    """Sends the latest command to the autopilot at a fixed rate from its own thread."""

    def __init__(
        self,
        link: AutopilotLink,
        *,
        period_s: float,
        monotonic_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if not 0.001 <= period_s <= 0.1:
            raise ConfigError("setpoint period_s", f"must be in [0.001, 0.1] s, got {period_s}")
        self._link = link
        self._period_s = period_s
        self._now = monotonic_ns
        self._lock = threading.Lock()
        self._command = (0.0, 0.0)
        self._stop = threading.Event()
        self.send_times_ns: list[int] = []
        self._thread = threading.Thread(target=self._loop, name="setpoints", daemon=True)

    def set_command(self, *, speed_m_s: float, yaw_rate_rad_s: float) -> None:
        with self._lock:
            self._command = (float(speed_m_s), float(yaw_rate_rad_s))

    def start(self) -> None:
        self._thread.start()

    def _loop(self) -> None:
        next_s = time.monotonic()
        while not self._stop.is_set():
            with self._lock:
                v, w = self._command
            # A link must not raise, but never let the stream die.
            with contextlib.suppress(Exception):
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


@dataclass(frozen=True)
class RunnerSettings:
    """How the runner drives one agent."""

    period_ns: int
    """Control period tau [ns] (the scenario's)."""
    plan_max_age_ns: int = 5_000_000_000
    """Neighbours' plans older than this are not handed to the agent [ns]."""
    target_max_age_ns: int = 2_000_000_000
    """Target observations older than this are ignored [ns]."""
    engage: bool = True
    """Put the vehicle in offboard/guided once setpoints have streamed for `warmup_ns`."""
    warmup_ns: int = 1_500_000_000
    """Autopilot time of zero setpoints before engaging (PX4 needs >= 1 s) [ns]."""
    engage_timeout_s: float = 10.0
    """Wall time to keep asking the autopilot to engage [s]."""
    stop_at_fleet_ns: int | None = None
    """Stop once fleet time reaches this [ns] (None: run until stopped)."""
    extra: dict = field(default_factory=dict)
    """Free-form fields copied into the summary (e.g. the command line)."""

    def __post_init__(self) -> None:
        if not isinstance(self.period_ns, int) or self.period_ns <= 0:
            raise ConfigError("period_ns", f"must be a positive integer, got {self.period_ns!r}")
        for name in ("plan_max_age_ns", "target_max_age_ns", "warmup_ns"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 0:
                raise ConfigError(name, f"must be an integer >= 0, got {value!r}")


def _vehicle_mode(state: LinkState) -> VehicleMode:
    if state.mode_lost or state.mode == FlightMode.HOLD:
        return VehicleMode.HOLD
    if state.mode == FlightMode.OFFBOARD:
        return VehicleMode.OFFBOARD
    if state.mode == FlightMode.LAND:
        return VehicleMode.LAND
    if state.mode == FlightMode.TAKEOFF:
        return VehicleMode.TAKEOFF
    return VehicleMode.STANDBY if not state.armed else VehicleMode.UNKNOWN


class FleetRunner:
    """Drives one Agent from an AutopilotLink and a PlanBus."""

    def __init__(
        self,
        agent: Agent,
        *,
        link: AutopilotLink,
        bus: PlanBus,
        settings: RunnerSettings,
        clock: FleetClock,
        log: Callable[[str], None] | None = None,
        record: Callable[[dict], None] | None = None,
    ) -> None:
        self.agent = agent
        self.link = link
        self.bus = bus
        self.settings = settings
        self.sync = ClockSync(clock)
        self._log = log or (lambda _text: None)
        self._record = record
        self.next_step_ns = 0
        self.steps = 0
        self.overruns = 0
        self.step_errors = 0
        self.last_output: AgentOutput | None = None
        self.last_status = "waiting"
        self._last_pose_ns = -1
        self._last_target_stamp_ns = -1
        self._mode_lost_reported = False
        self.engaged = False
        self.engage_attempted = False

    # -- one wake-up ----------------------------------------------------------------------------
    def tick(self, state: LinkState) -> AgentOutput | None:
        """Handle one telemetry snapshot; step the agent if a period boundary passed."""
        self.sync.update(time_boot_ns=state.time_boot_ns, received_wall_ns=state.received_ns)
        if state.mode_lost and not self._mode_lost_reported:
            self._mode_lost_reported = True
            mode = state.mode.name if state.mode is not None else "unknown"
            self._log(f"vehicle {self.agent.vehicle_id}: mode lost ({mode}); not re-engaging")
        fleet_now = self.sync.fleet_ns(state.time_boot_ns)
        if fleet_now is None or not state.has_pose or fleet_now < self.next_step_ns:
            return None
        period = self.settings.period_ns
        k = fleet_now // period
        stamp = k * period
        if self.steps and stamp > self.next_step_ns:
            self.overruns += int((stamp - self.next_step_ns) // period)
        self.next_step_ns = stamp + period
        return self._step(state, stamp)

    def _step(self, state: LinkState, stamp_ns: int) -> AgentOutput | None:
        t0 = time.perf_counter_ns()
        try:
            measurement = None
            if state.position_boot_ns > self._last_pose_ns:
                self._last_pose_ns = state.position_boot_ns
                measurement = np.array([state.north_m, state.east_m, state.yaw_rad])
            obs, obs_stamp = None, None
            target = self.bus.latest_target(stamp_ns, self.settings.target_max_age_ns)
            if target is not None and target.stamp_ns > self._last_target_stamp_ns:
                self._last_target_stamp_ns = target.stamp_ns
                obs = np.array([target.north_m, target.east_m])
                obs_stamp = target.stamp_ns
            plans = self.bus.latest_plans(stamp_ns, self.settings.plan_max_age_ns)
            out = self.agent.step(
                AgentInput(
                    stamp_ns=stamp_ns,
                    measurement=measurement,
                    target_observation=obs,
                    target_stamp_ns=obs_stamp,
                    neighbour_plans=plans,
                )
            )
        except Exception as e:  # never raise out of the control loop
            self.step_errors += 1
            self.last_status = f"step error: {type(e).__name__}: {e}"
            self._log(self.last_status)
            return None
        step_ms = (time.perf_counter_ns() - t0) * 1e-6
        self.steps += 1
        self.last_output = out
        self.last_status = out.status
        self._publish(state, out, stamp_ns)
        if self._record is not None:
            self._record(self._row(state, out, stamp_ns, step_ms))
        return out

    def _publish(self, state: LinkState, out: AgentOutput, stamp_ns: int) -> None:
        mode = _vehicle_mode(state)
        learning = bool(self.agent.learning.enabled)
        try:
            self.bus.publish_plan(
                out.plan,
                PlanStatus(
                    mode=mode,
                    qp_fallback=not out.qp_ok,
                    learning_on=learning,
                    first_c_norm=float(np.linalg.norm(out.c[0])),
                ),
            )
            beta = [float(b) for b in out.beta]
            slot_err = float(np.linalg.norm(out.state_estimate[:2] - out.slot_m))
            ages = tuple(
                NeighbourPlanAge(vehicle_id=i, age_ns=max(0, min(round(a * 1e9), 2**62)))
                for i, a in sorted(out.neighbour_ages_s.items())
                if math.isfinite(a)
            )[:_MAX_NEIGHBOURS]
            self.bus.publish_status(
                VehicleStatus(
                    mode=mode,
                    armed=state.armed,
                    learning_on=learning,
                    beta=LearnedParams(*beta),
                    slot_error_m=slot_err if math.isfinite(slot_err) else 0.0,
                    neighbour_plan_ages=ages,
                    qp_fallbacks=self.agent.fallbacks % 2**32,
                    rejected_messages=self.bus.counters().rejected_total % 2**32,
                ),
                stamp_ns=stamp_ns,
            )
        except Exception as e:
            self._log(f"publish failed: {type(e).__name__}: {e}")

    def _row(self, state: LinkState, out: AgentOutput, stamp_ns: int, step_ms: float) -> dict:
        def clean(a) -> list:
            return [float(x) if math.isfinite(x) else None for x in np.ravel(a)]

        return {
            "stamp_ns": stamp_ns,
            "time_boot_ns": state.time_boot_ns,
            "offset_ns": self.sync.offset_ns,
            "pose": clean([state.north_m, state.east_m, state.yaw_rad]),
            "command": clean(out.command),
            "estimate": clean(out.state_estimate),
            "slot_m": clean(out.slot_m),
            "beta": clean(out.beta),
            "qp_ok": bool(out.qp_ok),
            "status": out.status,
            "neighbour_ages_s": {
                str(k): (v if math.isfinite(v) else None) for k, v in out.neighbour_ages_s.items()
            },
            "formation_terms": out.formation_terms,
            "mode": state.mode.name if state.mode is not None else None,
            "mode_lost": state.mode_lost,
            "step_ms": step_ms,
        }

    # -- the loop -------------------------------------------------------------------------------
    def run(self, stop: threading.Event, streamer: SetpointStreamer) -> None:
        """Step until `stop` is set (or fleet time reaches `stop_at_fleet_ns`)."""
        s = self.settings
        state = self.link.state()
        first_boot_ns = state.time_boot_ns
        while not stop.is_set():
            state = self.link.wait_state(newer_than_ns=state.time_boot_ns, timeout_s=0.2)
            if stop.is_set():
                break
            if (
                s.engage
                and not self.engage_attempted
                and state.time_boot_ns - first_boot_ns >= s.warmup_ns
            ):
                self.engage_attempted = True
                self.engaged = self.link.engage(timeout_s=s.engage_timeout_s)
                self._log(
                    f"vehicle {self.agent.vehicle_id}: "
                    + ("engaged" if self.engaged else "could not engage; flying nothing")
                )
                state = self.link.state()
            out = self.tick(state)
            if out is not None:
                streamer.set_command(
                    speed_m_s=float(out.command[0]), yaw_rate_rad_s=float(out.command[1])
                )
            elif self.step_errors and self.last_output is None:
                streamer.set_command(speed_m_s=0.0, yaw_rate_rad_s=0.0)
            fleet_now = self.sync.fleet_ns(state.time_boot_ns)
            if None not in (s.stop_at_fleet_ns, fleet_now) and fleet_now >= s.stop_at_fleet_ns:
                break

    def summary(self, streamer: SetpointStreamer | None = None) -> dict:
        """Counters and timing of the run, as plain JSON-able values."""
        c = self.bus.counters()
        st = self.link.state()
        out = {
            "vehicle": self.agent.vehicle_id,
            "steps": self.steps,
            "overruns": self.overruns,
            "step_errors": self.step_errors,
            "qp_fallbacks": self.agent.fallbacks,
            "engaged": self.engaged,
            "mode_lost": st.mode_lost,
            "mode": st.mode.name if st.mode is not None else None,
            "clock_offset_ns": self.sync.offset_ns,
            "clock_samples": self.sync.samples,
            "last_offset_sample_ns": self.sync.last_sample_ns,
            "bus": {
                "published": c.published,
                "received": c.received,
                "accepted": c.accepted,
                "rejected": {str(k): v for k, v in c.rejected.items()},
            },
            "link_rejected": st.rejected,
            "setpoints_sent": self.link.setpoints_sent,
            **self.settings.extra,
        }
        if streamer is not None:
            out["setpoint_gap_wall_ms"] = gap_stats_ms(streamer.send_times_ns)
        return json.loads(json.dumps(out, default=str))
