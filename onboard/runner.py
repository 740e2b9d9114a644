"""The fleet runner of one vehicle: `Agent.step` on the autopilot's clock, over real links.

Time base (`fleetmpc.clock`). Every process of a fleet shares *fleet time*: simulated nanoseconds
since a common epoch, ``fleet_ns = (host_wall_ns - epoch_ns) * speed`` (`FleetClock`). The epoch is
either given to every process (``--epoch-ns``) or announced on the bus by the ground station once
every vehicle is engaged (a `FleetEpoch` on ``fleetmpc/<fleet>/epoch``, ``--wait-epoch``): the
runner polls the bus and adopts the first announcement; an announced speed other than its own is a
configuration error that stops the run. The runner does not step on the host clock: it steps on the
autopilot's ``time_boot_ms`` (so the SITL's ``--speed`` works end to end) shifted by the boot
offset `ClockSync` estimates — the minimum of ``fleet_ns(received) - time_boot_ns`` over the last
3 s of telemetry (transport latency only ever makes a sample larger; an autopilot's clock may
drift). Plans, statuses and the target's observations
are stamped in fleet time, so neighbours' ages and target stamps compare directly. Without an epoch,
fleet time is the autopilot's boot time.

Loop. Each time the autopilot's fleet time crosses a period boundary k·τ (k·τ >= 0), the runner
steps the agent at stamp k·τ with the latest pose, the newest target observation and the
neighbours' latest plans, hands the command to the `SetpointStreamer` (a separate thread that
sends the latest command at a fixed rate whatever the loop does), and publishes the plan and a
status (with the step's wall time and the setpoint rate actually sent). Before the first step
the streamer holds the vehicle where the runner found it (position setpoints at the current
altitude: the autopilot's own position controller keeps it there against the wind, and the
stream is what PX4 needs to accept OFFBOARD), and the vehicle is engaged after the warm-up
whether or not the epoch is known yet: a ground station waits for that. So every vehicle starts
the fleet's first period where it was when its agent connected. An exception in a step never
leaves the loop: the command becomes zero and the status says why.
Mode loss is reported, not fought.
"""

import dataclasses
import json
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from fleetmpc.bus.planbus import PlanBus
from fleetmpc.clock import ClockSync, EpochMismatchError, FleetClock
from fleetmpc.errors import ConfigError
from fleetmpc.onboard.agent_feed import TargetFeed, listen_for
from fleetmpc.onboard.autopilot_link import AutopilotLink, LinkState
from fleetmpc.onboard.core.agent import Agent, AgentInput, AgentOutput
from fleetmpc.onboard.setpoints import SetpointStreamer, gap_stats_ms
from fleetmpc.protocol.mavlink_map import FlightMode
from fleetmpc.protocol.messages import (
    MAX_SETPOINT_RATE_HZ,
    LearnedParams,
    NeighbourPlanAge,
    PlanStatus,
    TargetState,
    VehicleMode,
    VehicleStatus,
)
from fleetmpc.protocol.plan import Plan

__all__ = ["FleetRunner", "RunnerSettings"]

_MAX_NEIGHBOURS = 8
_U32_MAX = 2**32 - 1


@dataclass(frozen=True)
class RunnerSettings:
    """How the runner drives one agent."""

    period_ns: int
    """Control period tau [ns] (the scenario's)."""
    plan_max_age_ns: int = 60_000_000_000
    """Neighbours' plans older than this are not handed to the agent [ns] (as long as the
    agent's plan_forget_s: a silent neighbour is kept clear of, not forgotten)."""
    target_max_age_ns: int = 2_000_000_000
    """Target observations older than this are ignored [ns]."""
    engage: bool = True
    """Put the vehicle in offboard/guided once setpoints have streamed for `warmup_ns`."""
    warmup_ns: int = 1_500_000_000
    """Autopilot time of zero setpoints before engaging (PX4 needs >= 1 s) [ns]."""
    engage_timeout_s: float = 10.0
    """Wall time to keep asking the autopilot to engage [s]."""
    reengage_after_gap_s: float | None = 0.5
    """Take the vehicle back when the autopilot left offboard/guided within a few seconds of a
    gap of at least this much fleet time in the agent's own setpoint stream (the agent froze or
    stalled: the autopilot's failsafe is the agent's doing) [s]; None: never. A mode change
    while the stream was whole is a pilot's or a ground station's, and is never undone."""
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
        gap = self.reengage_after_gap_s
        if gap is not None and not (isinstance(gap, int | float) and 0 < gap < math.inf):
            raise ConfigError("reengage_after_gap_s", f"must be None or seconds > 0, got {gap!r}")


_OWN_GAP_WINDOW_S = 5.0
"""How far back (fleet time) a setpoint gap counts as the cause of a lost mode [s]: PX4 leaves
offboard 1 s (COM_OF_LOSS_T) and ArduCopter's guided mode 3 s (GUID_TIMEOUT) into a gap."""


def _hold_plan(plan: Plan, state: LinkState) -> Plan:
    """The plan of a vehicle its autopilot holds where it is: its pose over the whole horizon.

    While the autopilot is out of the agent's hands (HOLD, or a lost mode) the agent's own plan
    would tell the neighbours about motion that does not happen; they plan their separation
    against what the vehicle really does instead."""
    pose = np.array([state.north_m, state.east_m, state.yaw_rad])
    return Plan(
        vehicle_id=plan.vehicle_id,
        stamp_ns=plan.stamp_ns,
        period_ns=plan.period_ns,
        states=np.tile(pose, (len(plan.states), 1)),
        inputs=np.zeros_like(plan.inputs),
    )


def _measurement(state: LinkState) -> np.ndarray:
    """The pose (x, y, yaw), with the ground velocity after it when the autopilot reported one."""
    pose = [state.north_m, state.east_m, state.yaw_rad]
    velocity = [state.vel_north_m_s, state.vel_east_m_s]
    return np.array(pose + velocity if all(map(math.isfinite, velocity)) else pose)


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
        self.late_steps = 0
        """Steps that ran more than a quarter period after their period boundary."""
        self.max_late_ns = 0
        """The latest a step ran after its period boundary [ns of fleet time]."""
        self.step_errors = 0
        self.last_output: AgentOutput | None = None
        self.last_status = "waiting"
        self._last_pose_ns = -1
        self._targets = TargetFeed(bus, max_age_ns=settings.target_max_age_ns)
        self._mode_lost_reported = False
        self.engaged = False
        self.engage_attempted = False
        self.failure: str | None = None
        self.epoch_received_wall_ns: int | None = None
        self._streamer: SetpointStreamer | None = None
        self._other_epoch_reported = False
        self.reengaged = 0
        """Times the vehicle was taken back after the agent's own setpoint gap."""

    # -- the fleet epoch ------------------------------------------------------------------------
    def poll_epoch(self) -> None:
        """Adopt the first epoch announced on the bus, if the clock waits for one.

        A speed other than this runner's is a configuration error: it is logged and kept in
        `failure`, and `run` stops. Once adopted, a different announcement is logged once and
        ignored (fleet time never jumps).
        """
        clock = self.sync.clock
        if self.failure is not None or not clock.uses_epoch:
            return
        announced = self.bus.latest_epoch()
        if announced is None:
            return
        if clock.ready:
            if announced.epoch_ns != clock.epoch_ns and not self._other_epoch_reported:
                self._other_epoch_reported = True
                self._log(
                    f"ignoring another fleet epoch {announced.epoch_ns} from sender "
                    f"{announced.sender_id}: keeping {clock.epoch_ns}"
                )
            return
        try:
            adopted = clock.set_epoch(announced.epoch_ns, speed=announced.speed)
        except EpochMismatchError as e:
            self.failure = str(e)
            self._log(f"error: {self.failure}")
            return
        if adopted:
            self.epoch_received_wall_ns = time.time_ns()
            lead_s = (announced.epoch_ns - self.epoch_received_wall_ns) * 1e-9
            self._log(
                f"vehicle {self.agent.vehicle_id}: fleet epoch {announced.epoch_ns} "
                f"(x{announced.speed:g}) from sender {announced.sender_id}, {lead_s:+.3f} s wall "
                "from now"
            )

    # -- one wake-up ----------------------------------------------------------------------------
    def tick(self, state: LinkState) -> AgentOutput | None:
        """Handle one telemetry snapshot; step the agent if a period boundary passed."""
        if not self.sync.clock.ready:
            self.poll_epoch()
        self.sync.update(time_boot_ns=state.time_boot_ns, received_wall_ns=state.received_ns)
        if state.mode_lost and not self._mode_lost_reported and self._own_gap_s() is None:
            self._mode_lost_reported = True
            mode = state.mode_name or "unknown"
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
        late_ns = self._lateness_ns(fleet_now, stamp)
        if late_ns * 4 > period:
            self.late_steps += 1
        self.max_late_ns = max(self.max_late_ns, late_ns)
        return self._step(state, stamp, late_ns)

    def _lateness_ns(self, fleet_now_ns: int, stamp_ns: int) -> int:
        """How long after its period boundary `stamp_ns` a step taken now runs [ns]: by the
        telemetry it steps on (fleet time `fleet_now_ns`), or by the host's clock where that
        says later. On a host that starves this process the link's reader falls behind, and
        the telemetry it hands over is seconds old: its time says the step is on time while
        the vehicle has flown on (docs/design.md, "Safety": late steps)."""
        clock = self.sync.clock
        if clock.epoch_ns is None:  # (fleet time is the autopilot's: no other clock to ask)
            return fleet_now_ns - stamp_ns
        return max(fleet_now_ns, clock.fleet_ns(time.time_ns())) - stamp_ns

    def _step(self, state: LinkState, stamp_ns: int, late_ns: int) -> AgentOutput | None:
        t0 = time.perf_counter_ns()
        try:
            measurement = None
            if state.position_boot_ns > self._last_pose_ns:
                self._last_pose_ns = state.position_boot_ns
                measurement = _measurement(state)
            obs, obs_stamp = self._targets.take(stamp_ns)
            plans = self.bus.latest_plans(stamp_ns, self.settings.plan_max_age_ns)
            held = _vehicle_mode(state) == VehicleMode.HOLD
            out = self.agent.step(
                AgentInput(
                    stamp_ns=stamp_ns,
                    measurement=measurement,
                    target_observation=obs,
                    target_stamp_ns=obs_stamp,
                    neighbour_plans=plans,
                    # A held vehicle flies none of the commands: the filter is told so.
                    applied_input=np.zeros(2) if held else None,
                    late_s=late_ns * 1e-9,
                )
            )
            if held:
                out = dataclasses.replace(out, plan=_hold_plan(out.plan, state))
        except Exception as e:  # never raise out of the control loop
            self.step_errors += 1
            self.last_status = f"step error: {type(e).__name__}: {e}"
            self._log(self.last_status)
            return None
        step_ns = time.perf_counter_ns() - t0
        self.steps += 1
        self.last_output = out
        self.last_status = out.status
        listen_for(self.agent, self.bus)
        self._publish(state, out, stamp_ns, step_ns)
        if self._record is not None:
            self._record(self._row(state, out, stamp_ns, step_ns * 1e-6, late_ns * 1e-6))
        return out

    def setpoint_rate_hz(self) -> float:
        """Setpoints sent per simulated second over the last simulated second (0: no stream)."""
        if self._streamer is None:
            return 0.0
        speed = self.sync.clock.speed
        wall_rate_hz = self._streamer.rate_hz(window_ns=max(1, round(1e9 / speed)))
        return min(wall_rate_hz / speed, MAX_SETPOINT_RATE_HZ)

    def _publish(self, state: LinkState, out: AgentOutput, stamp_ns: int, step_ns: int) -> None:
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
                    solve_time_us=min(max(step_ns // 1000, 0), _U32_MAX),
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
                    setpoint_rate_hz=self.setpoint_rate_hz(),
                    target_state=TargetState[out.target_state.upper()],
                ),
                stamp_ns=stamp_ns,
            )
        except Exception as e:
            self._log(f"publish failed: {type(e).__name__}: {e}")

    def _row(
        self, state: LinkState, out: AgentOutput, stamp_ns: int, step_ms: float, late_ms: float
    ) -> dict:
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
            "target_state": out.target_state,
            "neighbour_ages_s": {
                str(k): (v if math.isfinite(v) else None) for k, v in out.neighbour_ages_s.items()
            },
            "formation_terms": out.formation_terms,
            "mode": state.mode_name,
            "mode_lost": state.mode_lost,
            "step_ms": step_ms,
            "late_ms": late_ms,
            "setpoint_rate_hz": self.setpoint_rate_hz(),
        }

    # -- taking the vehicle back ----------------------------------------------------------------
    def _own_gap_s(self) -> float | None:
        """The agent's own recent setpoint gap [s of fleet time] if it is one that re-engaging
        allows for (`RunnerSettings.reengage_after_gap_s`), else None."""
        limit_s, streamer = self.settings.reengage_after_gap_s, self._streamer
        if limit_s is None or streamer is None or not self.engaged:
            return None
        speed = self.sync.clock.speed
        window_ns = round(_OWN_GAP_WINDOW_S * 1e9 / speed)
        gap_s = streamer.longest_gap_ns(window_ns=window_ns) * 1e-9 * speed
        return gap_s if gap_s >= limit_s else None

    def _take_back(self, state: LinkState, streamer: SetpointStreamer) -> LinkState:
        """Re-engage after the autopilot's failsafe if the agent's own setpoint gap caused it;
        the vehicle holds where it is meanwhile. Returns the link's state after it."""
        gap_s = self._own_gap_s()
        if gap_s is None:
            return state
        mode = state.mode_name or "unknown"
        self._log(
            f"vehicle {self.agent.vehicle_id}: mode lost ({mode}) after a {gap_s:.1f} s gap in"
            " its own setpoints; taking it back"
        )
        streamer.hold_position(north_m=state.north_m, east_m=state.east_m)
        ok = self.link.engage(timeout_s=self.settings.engage_timeout_s)
        self.reengaged += int(ok)
        self._log(
            f"vehicle {self.agent.vehicle_id}: "
            + ("re-engaged" if ok else "could not re-engage; flying nothing")
        )
        if not ok:
            self.engaged = False
        return self.link.state()

    # -- the loop -------------------------------------------------------------------------------
    def run(self, stop: threading.Event, streamer: SetpointStreamer) -> None:
        """Step until `stop` is set, fleet time reaches `stop_at_fleet_ns` or `failure` is set.

        The vehicle is engaged after the warm-up whether or not the fleet epoch is known yet;
        steps start once it is (until then the streamer holds the vehicle where it was found).
        """
        s = self.settings
        self._streamer = streamer
        state = self.link.state()
        if state.has_pose:
            streamer.hold_position(north_m=state.north_m, east_m=state.east_m)
        first_boot_ns = state.time_boot_ns
        while not stop.is_set():
            state = self.link.wait_state(
                newer_than_ns=self._sleep_until_boot_ns(state, first_boot_ns), timeout_s=0.2
            )
            if not self.sync.clock.ready:
                self.poll_epoch()  # also without telemetry: a mismatch must stop the run
            if stop.is_set() or self.failure is not None:
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
            if state.mode_lost and self.engaged:
                state = self._take_back(state, streamer)
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

    def _sleep_until_boot_ns(self, state: LinkState, first_boot_ns: int) -> int:
        """The autopilot boot time [ns] whose telemetry the loop has nothing to do before:
        the next step's period boundary, or the end of the warm-up before engaging. Until
        fleet time is known, every new message (each one is a clock sample). Sleeping from one
        step to the next, not waking at each of the autopilot's 60 messages a second, keeps an
        agent's cost apart from its telemetry rate (docs/design.md, "MAVLink": waking)."""
        if not state.has_pose:
            return state.time_boot_ns
        offset_ns = self.sync.offset_ns
        if offset_ns is None:
            return state.time_boot_ns
        until_ns = self.next_step_ns - offset_ns - 1
        if self.settings.engage and not self.engage_attempted:
            until_ns = min(until_ns, first_boot_ns + self.settings.warmup_ns - 1)
        return max(state.time_boot_ns, until_ns)

    def summary(self, streamer: SetpointStreamer | None = None) -> dict:
        """Counters and timing of the run, as plain JSON-able values."""
        c = self.bus.counters()
        st = self.link.state()
        out = {
            "vehicle": self.agent.vehicle_id,
            "failure": self.failure,
            "epoch_ns": self.sync.clock.epoch_ns,
            "epoch_received_wall_ns": self.epoch_received_wall_ns,
            "steps": self.steps,
            "overruns": self.overruns,
            "late_steps": self.late_steps,
            "max_late_ms": self.max_late_ns * 1e-6,
            "step_errors": self.step_errors,
            "qp_fallbacks": self.agent.fallbacks,
            "engaged": self.engaged,
            "reengaged": self.reengaged,
            "resumes": self.agent.resumes,
            "mode_lost": st.mode_lost,
            "mode": st.mode_name,
            "clock_offset_ns": self.sync.offset_ns,
            "clock_samples": self.sync.samples,
            "last_offset_sample_ns": self.sync.last_sample_ns,
            "bus": {
                "published": c.published,
                "received": c.received,
                "accepted": c.accepted,
                "duplicates": c.duplicates,
                "out_of_order": c.out_of_order,
                "rejected": {str(k): v for k, v in c.rejected.items()},
            },
            "faults_injected": None if self.bus.faults is None else dict(self.bus.faults.counts),
            "link_faults": None
            if getattr(self.link, "faults", None) is None
            else dict(self.link.faults.counts),
            "link_rejected": st.rejected,
            "setpoints_sent": self.link.setpoints_sent,
            **self.settings.extra,
        }
        if streamer is not None:
            out["setpoint_gap_wall_ms"] = gap_stats_ms(streamer.send_times_ns)
            out["setpoints_faded"] = streamer.faded_sends  # (a command past its lifetime)
        return json.loads(json.dumps(out, default=str))
