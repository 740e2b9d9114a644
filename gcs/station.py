"""The ground station's state: what it knows of each vehicle's MAVLink side, the live record of
the run, the telemetry sinks it feeds, its status snapshots and metrics, and the gates.

`fleetmpc.gcs.ground_station` drives it from the command line (`fleetmpc gcs`); tests and the
logging benchmark feed it directly.
"""

import contextlib
import math
import queue
import time
from dataclasses import dataclass

from fleetmpc.check.feasibility import check_scenario
from fleetmpc.clock import ClockSync, FleetClock
from fleetmpc.gcs.live import LiveRecord
from fleetmpc.gcs.metrics import judged_metrics
from fleetmpc.gcs.telemetry import TargetFix, TelemetrySink, samples_of, target_state_event
from fleetmpc.onboard.telemetry_streams import MAX_BOOT_MS
from fleetmpc.protocol.local_frame import ned_from_geodetic, quaternion_yaw
from fleetmpc.protocol.mavlink_map import (
    Autopilot,
    FlightMode,
    LandedState,
    ModeFlag,
    Severity,
    custom_mode_name,
    mode_from_custom,
)
from fleetmpc.protocol.messages import (
    PlanMessage,
    StatusMessage,
    TargetObservation,
    TargetState,
)
from fleetmpc.scenario import Scenario

__all__ = ["GroundStation", "VehicleLink", "gate_failures"]

STREAMS_SILENT_WALL_S = 2.0
"""Wall seconds a heard vehicle may send no position before the ground station asks it for its
streams (and between two askings)."""

_LINK_LOST_WALL_S = 3.0
"""Wall seconds without MAVLink from a vehicle before the ground station says so."""


@dataclass
class VehicleLink:
    """What the ground station knows of one vehicle's MAVLink side."""

    autopilot: Autopilot | None = None
    mode: FlightMode | None = None
    mode_name: str | None = None
    """Its mode as its autopilot names it (ArduCopter: GUIDED, LOITER, ...; PX4: OFFBOARD,
    HOLD, ...), None before its first HEARTBEAT."""
    armed: bool = False
    last_wall_s: float | None = None
    messages: int = 0
    lost_reported: bool = False
    clock: ClockSync | None = None
    landed_state: LandedState | None = None
    """EXTENDED_SYS_STATE's landed state (None: not reported)."""
    last_position_wall_s: float | None = None
    """When its last GLOBAL_POSITION_INT came [wall s]."""
    streams_asked_wall_s: float | None = None
    """When it was last asked for its streams [wall s]."""
    ground_truth: bool = False
    """It sends the simulator's ground truth (a timed HIL_STATE_QUATERNION): the record's
    positions come from that, not from its estimate (docs/design.md, "Ground truth")."""

    @property
    def engaged(self) -> bool:
        """Armed, in offboard/guided, and able to fly the agent's setpoints: ArduCopter's agent
        sends none until its takeoff is over (a guided target would end the takeoff), so it must
        report itself in the air (when it reports a landed state at all); PX4 flies offboard
        setpoints from the ground, but not through a takeoff."""
        if not (self.armed and self.mode == FlightMode.OFFBOARD):
            return False
        if self.autopilot == Autopilot.ARDUPILOTMEGA:
            return self.landed_state == LandedState.IN_AIR
        return self.landed_state != LandedState.TAKEOFF


class GroundStation:
    """The ground station's state and loop; `run` drives it from the command line."""

    def __init__(
        self, scenario: Scenario, *, speed: float, duration_s: float, target_source: str = "script"
    ) -> None:
        """`target_source`: what the fleet's target process follows (``fleetmpc target
        --source``); other than "script" (the scenario's own target), the figures against the
        target are not judged (`TARGET_FIGURES`)."""
        self.scenario = scenario
        self.speed = speed
        self.duration_s = duration_s
        self.periods = int(round(duration_s * 1e9 / scenario.controller.period_ns)) + 1
        self.live = LiveRecord(scenario, periods=self.periods)
        self.links = {vid: VehicleLink() for vid in scenario.vehicle_ids}
        self._vehicle_of_system = {v.mavlink_system_id: v.id for v in scenario.vehicles}
        """Vehicle id of each autopilot's MAVLink system id (the same unless the scenario says)."""
        self.inbox: queue.SimpleQueue = queue.SimpleQueue()
        self.epoch_ns: int | None = None
        self.logged_periods = 0
        """Periods given to the sinks."""
        self.sinks: list[TelemetrySink] = []
        self._events: list[tuple[int | None, int, str, str]] = []
        """(fleet time [ns] or None, wall time [ns], level, text) of the events not logged
        yet: None for one that happened on the wall clock (a mode change, a STATUSTEXT), placed
        on the fleet clock once it has an epoch (`_timed_events`)."""
        self._observations: list[TargetFix] = []
        """Target observations received and not logged yet."""
        self.run_info = {
            "learning": scenario.learning.enabled,
            "feasible": check_scenario(scenario).feasible,
            "seed": scenario.seed,
            "source": "live",
            "target_source": target_source,
        }

    # -- clocks -----------------------------------------------------------------------------------
    def fleet_s(self, wall_ns: int | None = None) -> float | None:
        if self.epoch_ns is None:
            return None
        wall_ns = time.time_ns() if wall_ns is None else wall_ns
        return (wall_ns - self.epoch_ns) * self.speed * 1e-9

    def set_epoch(self, epoch_ns: int) -> None:
        self.epoch_ns = epoch_ns
        clock = FleetClock(epoch_ns=epoch_ns, speed=self.speed)
        for link in self.links.values():
            link.clock = ClockSync(clock)

    # -- MAVLink ----------------------------------------------------------------------------------
    def on_mavlink(self, msg, received_ns: int) -> None:
        vid = self._vehicle_of_system.get(msg.get_srcSystem())
        link = self.links.get(vid)
        if link is None or msg.get_srcComponent() != 1:
            return
        link.messages += 1
        link.last_wall_s = received_ns * 1e-9
        if link.lost_reported:
            link.lost_reported = False
            self._event("INFO", f"UAV {vid}: link back", wall_ns=received_ns)
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            try:
                autopilot = Autopilot(msg.autopilot)
            except ValueError:
                return
            mode = mode_from_custom(msg.custom_mode, autopilot)
            name = custom_mode_name(msg.custom_mode, autopilot)
            armed = bool(msg.base_mode & ModeFlag.SAFETY_ARMED)
            if (name, armed) != (link.mode_name, link.armed):
                state = "armed" if armed else "disarmed"
                self._event("INFO", f"UAV {vid}: {name}, {state}", wall_ns=received_ns)
            link.autopilot, link.mode, link.mode_name, link.armed = autopilot, mode, name, armed
        elif kind == "EXTENDED_SYS_STATE":
            with contextlib.suppress(ValueError):
                link.landed_state = LandedState(msg.landed_state)
        elif kind == "STATUSTEXT":
            level = "WARN" if msg.severity <= Severity.WARNING else "INFO"
            self._event(level, f"UAV {vid}: {msg.text}", wall_ns=received_ns)
        elif kind == "GLOBAL_POSITION_INT":
            link.last_position_wall_s = received_ns * 1e-9
            if not link.ground_truth:
                yaw = math.radians(msg.hdg * 0.01) if msg.hdg != 65535 else math.nan
                self._pose(vid, link, msg.time_boot_ms * 1_000_000, received_ns, msg, yaw)
        elif kind == "HIL_STATE_QUATERNION" and 0 < msg.time_usec <= MAX_BOOT_MS * 1000:
            # (A time of 0 is none, PX4's; one beyond a boot time is not one this can place.)
            link.ground_truth = True
            yaw = quaternion_yaw(*msg.attitude_quaternion)
            self._pose(vid, link, msg.time_usec * 1000, received_ns, msg, yaw)
        elif kind == "WIND_COV" and link.ground_truth:
            # A simulator that sends its ground truth sends its true wind here; a real
            # autopilot's WIND_COV is its estimate, not a truth to judge the learner by.
            self._true_wind(vid, link, msg, received_ns)

    def _true_wind(self, vid: int, link: VehicleLink, msg, received_ns: int) -> None:
        """A simulator's true wind (WIND_COV, NED) at its boot time, into the live record."""
        if link.clock is None or not 0 < msg.time_usec <= MAX_BOOT_MS * 1000:
            return  # (before the epoch, or a time this cannot place)
        boot_ns = msg.time_usec * 1000
        link.clock.update(time_boot_ns=boot_ns, received_wall_ns=received_ns)
        t_ns = link.clock.fleet_ns(boot_ns)
        if t_ns is not None:  # (None: the clock has no epoch yet)
            self.live.add_wind(vid, t_ns * 1e-9, msg.wind_x, msg.wind_y)

    def _pose(self, vid: int, link: VehicleLink, boot_ns: int, received_ns: int, msg, yaw: float):
        """A position of vehicle `vid` (`msg.lat`, `msg.lon` in degE7) at its boot time
        `boot_ns`, into the live record."""
        if link.clock is None:
            return  # (before the epoch: no fleet time to put it at)
        link.clock.update(time_boot_ns=boot_ns, received_wall_ns=received_ns)
        north, east = ned_from_geodetic(
            msg.lat * 1e-7,
            msg.lon * 1e-7,
            home_lat_deg=self.scenario.site.home_lat_deg,
            home_lon_deg=self.scenario.site.home_lon_deg,
        )
        self.live.add_pose(vid, link.clock.fleet_ns(boot_ns) * 1e-9, north, east, yaw)

    def _event(self, level: str, text: str, *, wall_ns: int | None = None) -> None:
        """An event that happens now (or at `wall_ns`) on the wall clock."""
        wall_ns = time.time_ns() if wall_ns is None else wall_ns
        self._events.append((None, wall_ns, level, text))

    def _timed_events(self, *, final: bool) -> list[tuple[int, str, str]]:
        """The events not logged yet, each at its own fleet time [ns]: one that happened before
        the fleet clock started is before 0, as far back as its wall time scaled by the speed.
        Before the epoch they are kept (an empty list), unless `final`: a fleet that never got
        an epoch has its events placed as if the fleet clock started now."""
        if self.epoch_ns is None and not final:
            return []
        epoch = self.epoch_ns if self.epoch_ns is not None else time.time_ns()
        events, self._events = self._events, []
        return [
            (round((wall - epoch) * self.speed) if t is None else t, level, text)
            for t, wall, level, text in events
        ]

    def links_to_ask(self, now_wall_s: float) -> list[int]:
        """The ids of every vehicle heard for the first time, or heard but sending no position
        for `STREAMS_SILENT_WALL_S` (or, an ArduPilot, no landed state), each at most once per
        that time: a real ArduPilot streams nothing to a ground station until asked (its SRn_
        rates are 0), a PX4 streams more than the ground station reads until told not to."""
        out = []
        for vid, link in self.links.items():
            heard = link.last_wall_s is not None
            fresh = link.last_position_wall_s is not None and (
                now_wall_s - link.last_position_wall_s < STREAMS_SILENT_WALL_S
            )
            asked = link.streams_asked_wall_s is not None and (
                now_wall_s - link.streams_asked_wall_s < STREAMS_SILENT_WALL_S
            )
            # (an ArduPilot that reports no landed state cannot be counted as engaged)
            blind = link.autopilot == Autopilot.ARDUPILOTMEGA and link.landed_state is None
            first = link.streams_asked_wall_s is None
            if heard and (first or blind or not fresh) and not asked:
                link.streams_asked_wall_s = now_wall_s
                out.append(vid)
        return out

    def check_links(self, now_wall_s: float) -> None:
        for vid, link in self.links.items():
            if link.last_wall_s is None or link.lost_reported:
                continue
            if now_wall_s - link.last_wall_s > _LINK_LOST_WALL_S:
                link.lost_reported = True
                text = f"UAV {vid}: no MAVLink for {_LINK_LOST_WALL_S:g} s"
                self._event("WARN", text, wall_ns=round(now_wall_s * 1e9))

    # -- the bus ----------------------------------------------------------------------------------
    def drain_bus(self) -> None:
        while True:
            try:
                message = self.inbox.get_nowait()
            except queue.Empty:
                return
            if isinstance(message, PlanMessage):
                self.live.add_plan(message)
                if message.status.qp_fallback:
                    text = f"UAV {message.sender_id}: QP fallback"
                    self._events.append((message.stamp_ns, time.time_ns(), "WARN", text))
            elif isinstance(message, StatusMessage):
                self._target_event(message)
                self.live.add_status(message)
            elif isinstance(message, TargetObservation):
                self.live.add_target(message)
                fix = TargetFix(message.stamp_ns, message.north_m, message.east_m)
                self._observations.append(fix)

    def _target_event(self, message: StatusMessage) -> None:
        """An event when a vehicle's formation starts following something else than before: the
        target lost (its prediction), held, being re-acquired, tracked again."""
        before = self.live.latest_status(message.sender_id)
        state = message.status.target_state
        was = TargetState.TRACKING if before is None else before.status.target_state
        if state != was and (before is None or message.stamp_ns > before.stamp_ns):
            level, text = target_state_event(message.sender_id, state.name.lower())
            self._events.append((message.stamp_ns, time.time_ns(), level, text))

    # -- telemetry --------------------------------------------------------------------------------
    def open_sinks(self, sinks: list[TelemetrySink]) -> None:
        """Open the telemetry sinks before the flight: the run's constants and facts go out now
        (the flushes give only the periods)."""
        self.sinks = list(sinks)
        for sink in self.sinks:
            sink.open(self.live.constants(), self.run_info)

    def close_sinks(self) -> None:
        """Close the sinks: everything given to them is written, and the facts of the run's
        end (`run_end_facts`)."""
        facts = self.run_end_facts()
        events = self._timed_events(final=True)  # (a run cut short before its last flush)
        for sink in self.sinks:
            for event in events:
                sink.event(*event)
            sink.finish(facts)
            sink.close()
        self.sinks = []

    def run_end_facts(self) -> dict:
        """What the metrics say of the run beside its record: the periods recorded of those
        expected, and the vehicles recorded from their simulator's ground truth."""
        return {
            "periods_recorded": min(self.live.complete_periods(), self.periods),
            "periods_expected": self.periods,
            "ground_truth": sorted(v for v, link in self.links.items() if link.ground_truth),
        }

    def flush(self, *, final: bool = False) -> None:
        """Give the sinks what arrived since the last flush: the events, the target
        observations, and the samples of the periods completed since then; then flush them
        (the last flush of a run leaves that to `close_sinks`)."""
        self.drain_bus()
        events = self._timed_events(final=final)
        observations, self._observations = self._observations, []
        done = min(self.live.complete_periods(), self.periods)
        if not self.sinks:
            self.logged_periods = done
            return
        samples = []
        if done > self.logged_periods:
            first = self.logged_periods
            samples = samples_of(
                self.live.record(done, first=first), self.live.live_rows(first, done)
            )
        for sink in self.sinks:
            for event in events:
                sink.event(*event)
            sink.observe(observations)
            sink.log(samples)
            if not final:
                sink.flush()
        self.logged_periods = done

    def status_snapshot(self, phase: str) -> dict:
        now = time.time()
        vehicles = {}
        for vid, link in self.links.items():
            st = self.live.latest_status(vid)
            plan = self.live.latest_plan(vid)
            ages = [a.age_ns * 1e-9 for a in st.status.neighbour_plan_ages] if st else []
            vehicles[str(vid)] = {
                "mode": link.mode_name,
                "armed": link.armed,
                "slot_error_m": st.status.slot_error_m if st else None,
                "solve_ms": plan.status.solve_time_us * 1e-3 if plan else None,
                "plan_age_s": max(ages) if ages else None,
                "setpoint_rate_hz": st.status.setpoint_rate_hz if st else None,
                "link_age_s": None if link.last_wall_s is None else now - link.last_wall_s,
                "qp_fallbacks": st.status.qp_fallbacks if st else 0,
                "target": st.status.target_state.name.lower() if st else None,
            }
        return {
            "phase": phase,
            "fleet_s": self.fleet_s(),
            "epoch_ns": self.epoch_ns,
            "vehicles": vehicles,
        }

    def metrics(self) -> dict | None:
        periods = min(self.live.complete_periods(), self.periods)
        if periods < 1:
            return None
        rec = self.live.record(periods)
        facts = self.run_end_facts()
        # The learned model's error is against the simulated truth: a vehicle that sends none (a
        # real autopilot, or its SITL) has no truth to compare with.
        metrics = judged_metrics(
            rec, ground_truth=facts["ground_truth"], target_source=self.run_info["target_source"]
        )
        return {
            "scenario": self.scenario.name,
            **self.run_info,
            "duration_s": float(rec.t_s[-1]),
            **metrics,
            **facts,
        }


def gate_failures(metrics: dict, scenario: Scenario, *, formation_m: float | None) -> list[str]:
    """What broke, as sentences; empty if the run passes."""
    broken = []
    d_safe = scenario.controller.d_safe_m
    if not metrics["min_separation_m"] >= d_safe:
        broken.append(f"min separation {metrics['min_separation_m']:.3f} m < d_safe {d_safe} m")
    if metrics["periods_recorded"] < metrics["periods_expected"]:
        broken.append(
            f"recorded {metrics['periods_recorded']} of {metrics['periods_expected']} periods"
        )
    if formation_m is not None:
        pairs = metrics["separation_pairs"]
        for (a, b), e in zip(pairs, metrics["separation_error_m"], strict=True):
            if not e <= formation_m:
                broken.append(f"separation error {a}-{b} {e:.4f} m > {formation_m} m")
        if metrics["centre_distance_error_m"] is not None and not (
            metrics["centre_distance_error_m"] <= formation_m
        ):
            c = metrics["centre_distance_error_m"]
            broken.append(f"centre distance error {c:.4f} m > {formation_m} m")
    return broken
