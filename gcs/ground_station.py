"""`fleetmpc gcs`: the ground station of a fleet.

    fleetmpc gcs --scenario scenarios/paper.toml --zenoh-connect 127.0.0.1:7447 --speed 4 \
        --rrd runs/up/run.rrd --metrics runs/up/metrics.json --viewer spawn

What it does, in order:

1. listens for every vehicle's MAVLink telemetry on the ground-station port (default
   ``udpin:HOST:network.gcs_port``) and joins the fleet's Zenoh bus (a client of a router with
   ``--zenoh-connect``, else the ground station's member of the fleet's peer mesh,
   `fleetmpc.protocol.zenoh_config.options_from_args`);
2. waits until every vehicle's HEARTBEAT shows it armed and engaged (PX4 OFFBOARD, ArduPilot
   GUIDED), then announces the fleet epoch (``now + --lead`` on the wall clock) on
   ``fleetmpc/<fleet>/epoch`` every half second, so the target and the agents start together
   (with ``--epoch-ns`` the fleet already has an epoch: it is used and not announced);
3. records positions (GLOBAL_POSITION_INT, stamped in fleet time through each vehicle's
   ``time_boot_ms``), plans, statuses and target observations into a `fleetmpc.gcs.live.LiveRecord`
   and logs them to Rerun (the entity layout of `fleetmpc.gcs.recording`), teed to an ``.rrd``
   file and/or a viewer; mode changes and STATUSTEXT become events. Every ``--flush-s`` seconds
   of flight (default 4: every 4 / ``--speed`` wall seconds) it logs the map of the periods
   completed since the previous flush, and every ``--series-flush-s`` seconds of flight (default
   4: with every flush) the time series and the flight_record rows of the periods since their
   previous logging, all of them in the last flush. A logging call costs per entity, not per
   row, so the intervals are counted in flight time: what logging costs per vehicle and control
   period is then the same at every speed. The bus is drained with every status snapshot too,
   so the status table is as fresh whatever the interval. What logging costs is a figure of
   ``fleetmpc bench --gcs-logging``;
4. rewrites ``--status-file`` (JSON) twice a second for a launcher's status table;
5. at ``--duration`` (fleet time; then up to 2 s of wall time more, until the telemetry of the
   last periods is in) or on SIGINT/SIGTERM: finishes the recording, prints the same summary as
   `fleetmpc sim` and writes the same metrics JSON.

Exit status: 0 if the run completed and the safety gate held (no two vehicles closer than
d_safe), 1 if a gate broke (``--gate-formation-m`` adds the formation gates) or the run was cut
short, 2 on a configuration or start-up error (e.g. a vehicle never engaged).
"""

import argparse
import json
import math
import os
import queue
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from fleetmpc.clock import ClockSync, FleetClock
from fleetmpc.errors import ConfigError, FleetMpcError
from fleetmpc.gcs.check import check_scenario
from fleetmpc.gcs.live import LiveRecord
from fleetmpc.gcs.metrics import compute_metrics, format_summary
from fleetmpc.gcs.telemetry import RerunSink, TelemetrySink, open_sink, samples_of
from fleetmpc.onboard.open_bus import open_fleet_bus
from fleetmpc.protocol.local_frame import ned_from_geodetic
from fleetmpc.protocol.mavlink_map import (
    Autopilot,
    FlightMode,
    ModeFlag,
    Severity,
    mode_from_custom,
)
from fleetmpc.protocol.messages import (
    GROUND_STATION_ID,
    PlanMessage,
    StatusMessage,
    TargetObservation,
)
from fleetmpc.scenario import Scenario, flight_time, load_scenario

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

__all__ = ["FLUSH_S", "SERIES_FLUSH_S", "GroundStation", "add_arguments", "run", "series_every"]

EXIT_WITHOUT_TEARDOWN = True
"""A fleet process: `fleetmpc.cli.entry` skips the interpreter's teardown once `run` returns."""

GCS_SYSTEM_ID = 255
"""MAVLink system id of the ground station (the conventional GCS id)."""
_STATUS_WALL_S = 0.5
_LINK_LOST_WALL_S = 3.0
_AFTER_END_SIM_S = 0.5
"""Telemetry collected past the last period, so it can be interpolated."""
_END_GRACE_WALL_S = 2.0
"""Wall seconds the ground station waits past that for the telemetry of the last periods, which
a loaded host delivers late; then it ends with what it has (and the periods gate says so)."""
FLUSH_S = 4.0
"""Default seconds of flight between two Rerun logging batches: 20 control periods of the
paper's 0.2 s, at which logging costs under a tenth of the agents' step in a live run of the
paper's fleet (its summary gives the figure; `fleetmpc bench --gcs-logging` compares
intervals)."""
SERIES_FLUSH_S = 4.0
"""Default seconds of flight between two loggings of the time series and the flight_record
rows."""


def series_every(*, flush_s: float, series_flush_s: float = SERIES_FLUSH_S) -> int:
    """Flushes per logging of the time series, for flushes every `flush_s` [s of flight]."""
    return max(1, round(series_flush_s / flush_s))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", required=True, type=Path, help="scenario TOML file")
    parser.add_argument("--mavlink", help="MAVLink URL to listen on (default udpin:HOST:gcs_port)")
    zenoh = parser.add_mutually_exclusive_group()
    zenoh.add_argument("--zenoh-config", type=Path, help="Zenoh config file")
    zenoh.add_argument(
        "--zenoh-connect",
        help="comma-separated router endpoints (default: a member of the fleet's peer mesh)",
    )
    parser.add_argument("--fleet", default=None, help="fleet name on Zenoh (default: scenario)")
    parser.add_argument("--speed", type=float, default=1.0, help="simulated seconds per second")
    parser.add_argument(
        "--duration", type=float, help="fleet time to record [s] (default: scenario)"
    )
    parser.add_argument("--rrd", type=Path, help="write the Rerun recording here")
    parser.add_argument(
        "--telemetry",
        metavar="URL",
        action="append",
        default=[],
        help="also send the run to this sink: rrd:PATH, a Rerun viewer's rerun+http://HOST:PORT"
        "/proxy, spawn: (a local viewer), memory:; repeatable",
    )
    parser.add_argument(
        "--viewer",
        default="none",
        help="Rerun viewer: spawn, connect=URL (rerun+http://HOST:9876/proxy) or none",
    )
    parser.add_argument("--metrics", type=Path, help="write the metrics JSON here")
    parser.add_argument("--status-file", type=Path, help="rewrite a JSON status snapshot here")
    parser.add_argument(
        "--engage-timeout", type=float, default=120.0, help="wall seconds to wait for engagement"
    )
    parser.add_argument(
        "--lead", type=float, default=1.0, help="wall seconds from the announcement to the epoch"
    )
    parser.add_argument(
        "--epoch-ns",
        type=int,
        help="use this fleet epoch (host time.time_ns() of fleet time 0) instead of announcing one",
    )
    parser.add_argument(
        "--flush-s",
        type=float,
        default=FLUSH_S,
        help="seconds of flight (wall seconds x --speed) between two Rerun logging batches:"
        " how late a live viewer shows the fleet; shorter costs more per control period"
        f" (default {FLUSH_S:g})",
    )
    parser.add_argument(
        "--series-flush-s",
        type=float,
        default=SERIES_FLUSH_S,
        help="seconds of flight between two loggings of the time series and the flight record,"
        " rounded to a whole number of flushes, at least one"
        f" (default {SERIES_FLUSH_S:g}; the map goes out with every flush)",
    )
    parser.add_argument(
        "--gate-formation-m",
        type=float,
        help="also fail if a separation or the centre-distance error exceeds this [m]",
    )


def _viewer(text: str) -> tuple[bool, str | None]:
    """(spawn, connect URL) of a --viewer value."""
    if text == "none":
        return False, None
    if text == "spawn":
        return True, None
    if text.startswith("connect="):
        url = text.removeprefix("connect=")
        if url.startswith(("rerun://", "rerun+http://", "rerun+https://")):
            return False, url
    raise ConfigError(
        "--viewer",
        f"must be spawn, connect=rerun+http://HOST:PORT/proxy or none, got {text!r}",
    )


@dataclass
class VehicleLink:
    """What the ground station knows of one vehicle's MAVLink side."""

    autopilot: Autopilot | None = None
    mode: FlightMode | None = None
    armed: bool = False
    last_wall_s: float | None = None
    messages: int = 0
    lost_reported: bool = False
    clock: ClockSync | None = None

    @property
    def engaged(self) -> bool:
        return self.armed and self.mode == FlightMode.OFFBOARD


class GroundStation:
    """The ground station's state and loop; `run` drives it from the command line."""

    def __init__(self, scenario: Scenario, *, speed: float, duration_s: float) -> None:
        self.scenario = scenario
        self.speed = speed
        self.duration_s = duration_s
        self.periods = int(round(duration_s * 1e9 / scenario.controller.period_ns)) + 1
        self.live = LiveRecord(scenario, periods=self.periods)
        self.links = {vid: VehicleLink() for vid in scenario.vehicle_ids}
        self.inbox: queue.SimpleQueue = queue.SimpleQueue()
        self.epoch_ns: int | None = None
        self.logged_periods = 0
        """Periods given to the sinks."""
        self.sinks: list[TelemetrySink] = []
        self._events: list[tuple[int, str, str]] = []
        """(sim_time ns, level, text) events not logged yet."""
        self.run_info = {
            "learning": scenario.learning.enabled,
            "feasible": check_scenario(scenario).feasible,
            "seed": scenario.seed,
            "source": "live",
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
        vid = msg.get_srcSystem()
        link = self.links.get(vid)
        if link is None or msg.get_srcComponent() != 1:
            return
        link.messages += 1
        link.last_wall_s = received_ns * 1e-9
        if link.lost_reported:
            link.lost_reported = False
            self._event("INFO", f"UAV {vid}: link back")
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            try:
                autopilot = Autopilot(msg.autopilot)
            except ValueError:
                return
            mode = mode_from_custom(msg.custom_mode, autopilot)
            armed = bool(msg.base_mode & ModeFlag.SAFETY_ARMED)
            if (mode, armed) != (link.mode, link.armed):
                name = mode.name if mode is not None else f"custom mode {msg.custom_mode}"
                self._event("INFO", f"UAV {vid}: {name}, {'armed' if armed else 'disarmed'}")
            link.autopilot, link.mode, link.armed = autopilot, mode, armed
        elif kind == "STATUSTEXT":
            level = "WARN" if msg.severity <= Severity.WARNING else "INFO"
            self._event(level, f"UAV {vid}: {msg.text}")
        elif kind == "GLOBAL_POSITION_INT" and link.clock is not None:
            link.clock.update(
                time_boot_ns=msg.time_boot_ms * 1_000_000, received_wall_ns=received_ns
            )
            t_ns = link.clock.fleet_ns(msg.time_boot_ms * 1_000_000)
            north, east = ned_from_geodetic(
                msg.lat * 1e-7,
                msg.lon * 1e-7,
                home_lat_deg=self.scenario.site.home_lat_deg,
                home_lon_deg=self.scenario.site.home_lon_deg,
            )
            yaw = math.radians(msg.hdg * 0.01) if msg.hdg != 65535 else math.nan
            self.live.add_pose(vid, t_ns * 1e-9, north, east, yaw)

    def _event(self, level: str, text: str) -> None:
        t = self.fleet_s()
        self._events.append((max(0, round((t or 0.0) * 1e9)), level, text))

    def check_links(self, now_wall_s: float) -> None:
        for vid, link in self.links.items():
            if link.last_wall_s is None or link.lost_reported:
                continue
            if now_wall_s - link.last_wall_s > _LINK_LOST_WALL_S:
                link.lost_reported = True
                self._event("WARN", f"UAV {vid}: no MAVLink for {_LINK_LOST_WALL_S:g} s")

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
                    self._events.append(
                        (message.stamp_ns, "WARN", f"UAV {message.sender_id}: QP fallback")
                    )
            elif isinstance(message, StatusMessage):
                self.live.add_status(message)
            elif isinstance(message, TargetObservation):
                self.live.add_target(message)

    # -- telemetry --------------------------------------------------------------------------------
    def open_sinks(self, sinks: list[TelemetrySink]) -> None:
        """Open the telemetry sinks before the flight: the run's constants and facts go out now
        (the flushes give only the periods)."""
        self.sinks = list(sinks)
        for sink in self.sinks:
            sink.open(self.live.constants(), self.run_info)

    def close_sinks(self) -> None:
        """Close the sinks: everything given to them is written."""
        for sink in self.sinks:
            sink.close()
        self.sinks = []

    def flush(self, *, final: bool = False) -> None:
        """Give the sinks what arrived since the last flush: the events, and the samples of the
        periods completed since then; then flush them (the last flush of a run leaves that to
        `close_sinks`)."""
        self.drain_bus()
        events, self._events = self._events, []
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
                "mode": link.mode.name if link.mode is not None else None,
                "armed": link.armed,
                "slot_error_m": st.status.slot_error_m if st else None,
                "solve_ms": plan.status.solve_time_us * 1e-3 if plan else None,
                "plan_age_s": max(ages) if ages else None,
                "setpoint_rate_hz": st.status.setpoint_rate_hz if st else None,
                "link_age_s": None if link.last_wall_s is None else now - link.last_wall_s,
                "qp_fallbacks": st.status.qp_fallbacks if st else 0,
            }
        return {"phase": phase, "fleet_s": self.fleet_s(), "vehicles": vehicles}

    def metrics(self) -> dict | None:
        periods = min(self.live.complete_periods(), self.periods)
        if periods < 1:
            return None
        rec = self.live.record(periods)
        return {
            "scenario": self.scenario.name,
            **self.run_info,
            "duration_s": float(rec.t_s[-1]),
            **compute_metrics(rec),
            "periods_recorded": periods,
            "periods_expected": self.periods,
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
        if not metrics["centre_distance_error_m"] <= formation_m:
            c = metrics["centre_distance_error_m"]
            broken.append(f"centre distance error {c:.4f} m > {formation_m} m")
    return broken


def _log(text: str) -> None:
    print(f"fleetmpc gcs: {text}", file=sys.stderr, flush=True)


def _write_json(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    tmp.replace(path)


def run(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    duration = flight_time(scenario, speed=args.speed, duration_s=args.duration)
    for name in ("engage_timeout", "lead", "flush_s", "series_flush_s"):
        if not getattr(args, name) > 0:
            raise ConfigError(
                f"--{name.replace('_', '-')}", f"must be > 0, got {getattr(args, name)}"
            )
    spawn, viewer_url = _viewer(args.viewer)
    net = scenario.network
    url = args.mavlink or f"udpin:{net.host}:{net.gcs_port}"
    every = series_every(flush_s=args.flush_s, series_flush_s=args.series_flush_s)
    sinks: list[TelemetrySink] = [open_sink(u, series_every=every) for u in args.telemetry]
    if args.rrd is not None or spawn or viewer_url is not None:
        sinks.append(
            RerunSink(path=args.rrd, viewer_url=viewer_url, spawn_viewer=spawn, series_every=every)
        )
    gs = GroundStation(scenario, speed=args.speed, duration_s=duration)
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    mav = bus = None
    completed = False
    try:
        mav = mavutil.mavlink_connection(url, source_system=GCS_SYSTEM_ID)
        bus = open_fleet_bus(args, scenario, sender_id=GROUND_STATION_ID, on_accept=gs.inbox.put)
        gs.open_sinks(sinks)
        if args.epoch_ns is not None:
            gs.set_epoch(args.epoch_ns)
        _log(f"listening on {url}; waiting for {len(gs.links)} vehicles to engage")
        deadline = time.monotonic() + args.engage_timeout
        next_flush = next_status = next_announce = time.monotonic()
        end_s = duration + _AFTER_END_SIM_S
        end_grace = None
        while not stop.is_set():
            msg = mav.recv_match(blocking=True, timeout=0.02)
            now = time.monotonic()
            if msg is not None:
                gs.on_mavlink(msg, time.time_ns())
            if gs.epoch_ns is None:
                if all(link.engaged for link in gs.links.values()):
                    gs.set_epoch(time.time_ns() + round(args.lead * 1e9))
                    _log(f"all engaged; epoch {gs.epoch_ns} (x{args.speed:g})")
                elif now > deadline:
                    missing = [str(v) for v, link in gs.links.items() if not link.engaged]
                    raise FleetMpcError(
                        f"vehicles {', '.join(missing)} not armed and engaged after "
                        f"{args.engage_timeout:g} s (modes: "
                        + ", ".join(
                            f"{v}: {link.mode.name if link.mode else 'silent'}"
                            for v, link in gs.links.items()
                        )
                        + ")"
                    )
            if args.epoch_ns is None and gs.epoch_ns is not None and now >= next_announce:
                bus.publish_epoch(epoch_ns=gs.epoch_ns, speed=args.speed)
                next_announce = now + 0.5
            if now >= next_flush:
                gs.flush()
                next_flush = now + args.flush_s / args.speed
            if now >= next_status:
                gs.drain_bus()
                gs.check_links(time.time())
                if args.status_file is not None:
                    phase = "waiting" if gs.epoch_ns is None else "flying"
                    _write_json(args.status_file, gs.status_snapshot(phase))
                next_status = now + _STATUS_WALL_S
            t = gs.fleet_s()
            if t is not None and t >= end_s:
                # (read anew: a slow flush or status in this pass must not use up the wait)
                if end_grace is None:
                    end_grace = time.monotonic() + _END_GRACE_WALL_S
                done = gs.live.complete_periods() >= gs.periods
                if done or time.monotonic() >= end_grace:
                    completed = True
                    break
        gs.flush(final=True)
    finally:
        if bus is not None:
            bus.close()
        if mav is not None:
            mav.close()
        for s, handler in previous.items():
            signal.signal(s, handler)
        gs.close_sinks()
    metrics = gs.metrics()
    if args.status_file is not None:
        _write_json(args.status_file, gs.status_snapshot("done"))
    if metrics is None:
        _log("no complete control period recorded")
        return 1
    print(format_summary(metrics), flush=True)
    if args.metrics is not None:
        _write_json(args.metrics, metrics)
        print(f"metrics: {args.metrics}", flush=True)
    if args.rrd is not None:
        print(f"recording: {args.rrd}", flush=True)
    broken = gate_failures(metrics, scenario, formation_m=args.gate_formation_m)
    if not completed:
        broken.append("interrupted before the end of the run")
    for b in broken:
        _log(f"gate: {b}")
    return 1 if broken else 0
