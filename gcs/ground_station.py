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
import contextlib
import json
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from fleetmpc.bus.open_bus import add_bus_arguments, open_fleet_bus
from fleetmpc.bus.planbus import PlanBus
from fleetmpc.errors import ConfigError, FleetMpcError
from fleetmpc.gcs.metrics import format_summary
from fleetmpc.gcs.station import GroundStation, gate_failures
from fleetmpc.gcs.telemetry import (
    FLUSH_S,
    RerunSink,
    TelemetrySink,
    add_telemetry_argument,
    open_sink,
)
from fleetmpc.protocol.messages import (
    GROUND_STATION_ID,
)
from fleetmpc.scenario import flight_time, load_scenario
from fleetmpc.security.mavlink_signing import KeyRing, read_key_options

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

__all__ = ["SERIES_FLUSH_S", "add_arguments", "run", "series_every"]

EXIT_WITHOUT_TEARDOWN = True
"""A fleet process: `fleetmpc.cli.entry` skips the interpreter's teardown once `run` returns."""

GCS_SYSTEM_ID = 255
"""MAVLink system id of the ground station (the conventional GCS id)."""
_STATUS_WALL_S = 0.5
_AFTER_END_SIM_S = 0.5
"""Telemetry collected past the last period, so it can be interpolated."""
_END_GRACE_WALL_S = 2.0
"""Wall seconds the ground station waits past that for the telemetry of the last periods, which
a loaded host delivers late; then it ends with what it has (and the periods gate says so)."""
SERIES_FLUSH_S = 4.0
"""Default seconds of flight between two loggings of the time series and the flight_record
rows."""


def series_every(*, flush_s: float, series_flush_s: float = SERIES_FLUSH_S) -> int:
    """Flushes per logging of the time series, for flushes every `flush_s` [s of flight]."""
    return max(1, round(series_flush_s / flush_s))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", required=True, type=Path, help="scenario TOML file")
    parser.add_argument("--mavlink", help="MAVLink URL to listen on (default udpin:HOST:gcs_port)")
    parser.add_argument(
        "--mavlink-key",
        action="append",
        default=[],
        metavar="ID=FILE",
        help="vehicle ID's MAVLink signing key file (`fleetmpc keys`): that vehicle is heard only"
        " signed with it, and asked for telemetry signed; repeatable (default: unsigned)",
    )
    add_bus_arguments(parser)
    parser.add_argument("--speed", type=float, default=1.0, help="simulated seconds per second")
    parser.add_argument(
        "--duration", type=float, help="fleet time to record [s] (default: scenario)"
    )
    parser.add_argument(
        "--target-source",
        default="script",
        metavar="URL",
        help="what the fleet's target process follows (its --source; default: script, the"
        " scenario's own target): with another, the figures against the target are not judged",
    )
    parser.add_argument("--rrd", type=Path, help="write the Rerun recording here")
    add_telemetry_argument(parser)
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


GCS_STREAMS_US = {
    33: 200_000,
    115: 200_000,
    231: 200_000,
    245: 1_000_000,
    30: -1,
    32: -1,
    74: -1,
    1: -1,
    242: -1,
}
"""SET_MESSAGE_INTERVAL asked of every vehicle when first heard, and of a silent one [us]:
GLOBAL_POSITION_INT at 5 Hz (its place on the map), a simulator's ground truth
(HIL_STATE_QUATERNION) and its true wind (WIND_COV) at 5 Hz where there is one
(docs/design.md, "Ground truth") and
EXTENDED_SYS_STATE at 1 Hz (is it in the air); stopped (-1): ATTITUDE, LOCAL_POSITION_NED,
VFR_HUD, SYS_STATUS and HOME_POSITION, which the ground station does not read (a PX4
ground-station link streams them at 21 messages a second, each one a send for the autopilot and
a parse for the ground station). HEARTBEAT and STATUSTEXT come unasked."""
GCS_DATA_STREAMS_HZ = {6: 5, 2: 1}
"""REQUEST_DATA_STREAM for autopilots that know only that (MAV_DATA_STREAM POSITION at 5 Hz,
EXTENDED_STATUS at 1 Hz). Sent before the message intervals, which override it per message
where the autopilot knows both."""


def _ask_for_streams(mav, system_id: int, keys: KeyRing) -> None:
    """Ask the autopilot of MAVLink system `system_id` for the messages the ground station
    reads, and no others, on this link (a real ArduPilot streams nothing to a ground station
    until asked, a PX4 more than it reads). A UDP server link writes to every vehicle it hears;
    the commands' target system picks the one."""
    messages = [
        mav.mav.request_data_stream_encode(system_id, 1, stream, rate, 1)
        for stream, rate in GCS_DATA_STREAMS_HZ.items()
    ] + [
        mav.mav.command_long_encode(system_id, 1, 511, 0, msg_id, interval, 0, 0, 0, 0, 0)
        for msg_id, interval in GCS_STREAMS_US.items()
    ]
    for message in messages:
        with contextlib.suppress(OSError):
            mav.write(keys.pack(mav.mav, message, system_id))


def _log(text: str) -> None:
    print(f"fleetmpc gcs: {text}", file=sys.stderr, flush=True)


def _write_json(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    tmp.replace(path)


def run(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario, live=True)
    duration = flight_time(scenario, speed=args.speed, duration_s=args.duration)
    for name in ("engage_timeout", "lead", "flush_s", "series_flush_s"):
        if not getattr(args, name) > 0:
            raise ConfigError(
                f"--{name.replace('_', '-')}", f"must be > 0, got {getattr(args, name)}"
            )
    spawn, viewer_url = _viewer(args.viewer)
    net = scenario.network
    url = args.mavlink or f"udpin:{net.ground_station_address}:{net.gcs_port}"
    sinks = _sinks(args, spawn, viewer_url)
    keys = KeyRing(
        {
            scenario.vehicle(vid).mavlink_system_id: key
            for vid, key in read_key_options(args.mavlink_key, scenario.vehicle_ids).items()
        },
        report=lambda _reason, text: _log(text),
    )
    gs = GroundStation(
        scenario, speed=args.speed, duration_s=duration, target_source=args.target_source
    )
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
        completed = _listen(gs, _Station(mav, bus, keys), args, stop, duration)
        gs.flush(final=True)
    finally:
        if bus is not None:
            bus.close()
        if mav is not None:
            mav.close()
        for s, handler in previous.items():
            signal.signal(s, handler)
        gs.close_sinks()
    return _conclude(gs, args, completed)


def _sinks(args: argparse.Namespace, spawn: bool, viewer_url: str | None) -> list[TelemetrySink]:
    """The telemetry sinks the command line asks for, the Rerun one last."""
    every = series_every(flush_s=args.flush_s, series_flush_s=args.series_flush_s)
    sinks: list[TelemetrySink] = [open_sink(u, series_every=every) for u in args.telemetry]
    if args.rrd is not None or spawn or viewer_url is not None:
        sinks.append(
            RerunSink(path=args.rrd, viewer_url=viewer_url, spawn_viewer=spawn, series_every=every)
        )
    return sinks


@dataclass(frozen=True)
class _Station:
    """The ground station's links: MAVLink from the vehicles (`keys` admits signed frames),
    the plan bus."""

    mav: mavutil.mavfile
    bus: PlanBus
    keys: KeyRing


def _listen(
    gs: GroundStation,
    station: _Station,
    args: argparse.Namespace,
    stop: threading.Event,
    duration: float,
) -> bool:
    """Take the vehicles' telemetry until the run's end (True) or `stop` (False): set the
    fleet's epoch once every vehicle is engaged (and announce it), flush the sinks, and keep
    the links and the status file current."""
    deadline = time.monotonic() + args.engage_timeout
    next_flush = next_status = next_announce = time.monotonic()
    end_s = duration + _AFTER_END_SIM_S
    end_grace = None
    while not stop.is_set():
        msg = station.mav.recv_match(blocking=True, timeout=0.02)
        now = time.monotonic()
        if msg is not None and station.keys.admit(msg):
            gs.on_mavlink(msg, time.time_ns())
        if gs.epoch_ns is None:
            _engage(gs, args, overdue=now > deadline)
        if args.epoch_ns is None and gs.epoch_ns is not None and now >= next_announce:
            station.bus.publish_epoch(epoch_ns=gs.epoch_ns, speed=args.speed)
            next_announce = now + 0.5
        if now >= next_flush:
            gs.flush()
            next_flush = now + args.flush_s / args.speed
        if now >= next_status:
            _keep_current(gs, station, args)
            next_status = now + _STATUS_WALL_S
        t = gs.fleet_s()
        if t is not None and t >= end_s:
            # (read anew: a slow flush or status in this pass must not use up the wait)
            if end_grace is None:
                end_grace = time.monotonic() + _END_GRACE_WALL_S
            done = gs.live.complete_periods() >= gs.periods
            if done or time.monotonic() >= end_grace:
                return True
    return False


def _engage(gs: GroundStation, args: argparse.Namespace, *, overdue: bool) -> None:
    """Set the fleet's epoch, `args.lead` ahead, once every vehicle is armed and engaged;
    fail naming the vehicles that are not when `overdue`."""
    if all(link.engaged for link in gs.links.values()):
        gs.set_epoch(time.time_ns() + round(args.lead * 1e9))
        _log(f"all engaged; epoch {gs.epoch_ns} (x{args.speed:g})")
    elif overdue:
        missing = [str(v) for v, link in gs.links.items() if not link.engaged]
        modes = ", ".join(f"{v}: {link.mode_name or 'silent'}" for v, link in gs.links.items())
        raise FleetMpcError(
            f"vehicles {', '.join(missing)} not armed and engaged after "
            f"{args.engage_timeout:g} s (modes: {modes})"
        )


def _keep_current(gs: GroundStation, station: _Station, args: argparse.Namespace) -> None:
    """Take what the plan bus brought, judge the links (asking silent vehicles for their
    streams again) and write the status file."""
    gs.drain_bus()
    gs.check_links(time.time())
    for vid in gs.links_to_ask(time.time()):
        system_id = gs.scenario.vehicle(vid).mavlink_system_id
        _ask_for_streams(station.mav, system_id, station.keys)
    if args.status_file is not None:
        phase = "waiting" if gs.epoch_ns is None else "flying"
        _write_json(args.status_file, gs.status_snapshot(phase))


def _conclude(gs: GroundStation, args: argparse.Namespace, completed: bool) -> int:
    """The run's metrics printed and written, and its gates judged: 0 when every gate held."""
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
    broken = gate_failures(metrics, gs.scenario, formation_m=args.gate_formation_m)
    if not completed:
        broken.append("interrupted before the end of the run")
    for b in broken:
        _log(f"gate: {b}")
    return 1 if broken else 0
