"""Issue 5's gates: the whole fleet as `fleetmpc up` starts it, over loopback MAVLink and Zenoh.

One flight of ``scenarios/mixed-autopilots.toml`` at x2 (vehicles 1 and 3 on the PX4 profile over
UDP, vehicle 2 on the ArduPilot profile over TCP), from a copy whose ``[network]`` ports are free
ones, so it never meets another fleet on this machine. The processes are the argument lists of
`fleetmpc.launch.fleet.fleet_processes`: Zenoh router, target, three SITLs, three agents and the
ground station ``fleetmpc gcs`` (with ``--metrics``), every Zenoh member a client of the router. No
process is given an epoch: the ground station announces it once every vehicle is armed and engaged,
and the others wait for it. Two arguments are added:

- the PX4 SITLs run with ``--com-of-loss-t 0.5``: a gap of 0.5 s of fleet time in the setpoint
  stream, as the autopilot sees it, drops the vehicle to HOLD (and the agent does not re-engage),
  so "the vehicle stayed in OFFBOARD" is the autopilot's own measurement of "max gap < 0.5 s";
- the target flies on past the ground station's 30 s, so the phase after the kill has a target.

The test is also a second ground station: it sends HEARTBEATs to each SITL's ground-station port,
which then streams to it as to any peer (modes, STATUSTEXT, GLOBAL_POSITION_INT), and it is a
Zenoh client of the router (it hears the epoch and puts malformed payloads). Timeline in fleet
time: 0 the epoch; 10 s malformed payloads on vehicle 2's plan key; 30.5 s the ground station
finishes and writes its metrics; then agent 3 is SIGKILLed and the fleet is watched for 3 s;
then every process is stopped by PID (SIGTERM, then SIGKILL) and none may be left.

One flight (a module fixture; a second if the host stalled the first, see ``flight``) serves
every gate test; each test asserts one gate. The figures
(live against lockstep, setpoint gaps, reactions to the kill, and diagnostics such as how long
each vehicle waited for the epoch) go to ``report.json`` in the flight's folder and are printed.

The fleet needs about 0.6 of this machine's 2 cores at x2 (it passes with both cores held busy
by other processes). A flight in which an agent skipped a period, by its own records, is flown
once more (see ``flight``): a host that stops every process for a quarter of a second fails
the period gates in fleet time without any fault of the code.
"""

import contextlib
import dataclasses
import itertools
import json
import math
import os
import socket
import struct
import time
import warnings
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest
import zenoh
from helpers import ROOT, ProcessGroup, live_processes_naming, scenario_on_free_ports

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

from fleetmpc.gcs.metrics import compute_metrics  # noqa: E402
from fleetmpc.launch.fleet import FleetOptions, fleet_processes  # noqa: E402
from fleetmpc.lockstep.flight import run_lockstep  # noqa: E402
from fleetmpc.protocol.codec import SCHEMA_VERSION, DecodeError, decode, encode  # noqa: E402
from fleetmpc.protocol.key_expressions import epoch_key, plan_key  # noqa: E402
from fleetmpc.protocol.local_frame import ned_from_geodetic  # noqa: E402
from fleetmpc.protocol.mavlink_map import Autopilot, FlightMode, ModeFlag, mode_from_custom  # noqa: E402
from fleetmpc.protocol.messages import FleetEpoch, MessageKind, PlanMessage, RejectReason  # noqa: E402
from fleetmpc.protocol.plan import Plan  # noqa: E402
from fleetmpc.protocol.zenoh_config import ZenohOptions, endpoint  # noqa: E402
from fleetmpc.scenario import Scenario, load_scenario  # noqa: E402

M = mavutil.mavlink
SOURCE = ROOT / "scenarios" / "mixed-autopilots.toml"
SPEED = 2.0
GCS_DURATION_S = 30.0
COM_OF_LOSS_T_S = 0.5
TARGET_DURATION_S = 60.0
MALFORMED_AT_S = 10.0
WATCH_AFTER_KILL_S = 3.0
KILLED = 3
SURVIVORS = (1, 2)
ARDUPILOT = 2
ENGAGE_TIMEOUT_S = 120.0
FORMATION_TOLERANCE_M = 0.1
PLAN_AGE_REACTION_S = 0.5
TEST_SYSTEM_ID = 254


class GroundStationPeer:
    """A second ground station on every SITL's GCS link, stamping what it hears in wall time.

    A SITL streams its ground-station link to the configured port and to every peer that sent it
    a valid message in the last 10 s of simulated time, so a HEARTBEAT every half second keeps
    this socket in the stream; with it go requests for the position, attitude and status streams
    (an ArduPilot-profile SITL streams nothing else unasked).
    """

    def __init__(self, scenario: Scenario) -> None:
        self.scenario = scenario
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.mav = M.MAVLink(
            None, srcSystem=TEST_SYSTEM_ID, srcComponent=M.MAV_COMP_ID_MISSIONPLANNER
        )
        self.sitls: list[tuple[str, int]] = []
        self.heartbeats: dict[int, list[tuple[int, int, FlightMode | None, bool]]] = defaultdict(
            list
        )
        """vehicle -> (wall ns, MAV_AUTOPILOT, mode, armed) of every HEARTBEAT."""
        self.texts: dict[int, list[tuple[int, str]]] = defaultdict(list)
        """vehicle -> (wall ns, text) of every STATUSTEXT."""
        self.positions: dict[int, list[tuple[int, float, float, float]]] = defaultdict(list)
        """vehicle -> (wall ns, north m, east m, altitude above home m) of GLOBAL_POSITION_INT."""
        self._next_hello = 0.0

    def add_sitl(self, port: int) -> None:
        self.sitls.append(("127.0.0.1", port))
        self._next_hello = 0.0

    def poll(self) -> None:
        now = time.monotonic()
        if now >= self._next_hello:
            hello = self.mav.heartbeat_encode(
                M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, M.MAV_STATE_ACTIVE
            ).pack(self.mav)
            # An ArduPilot streams to a ground station only what it is asked for.
            asks = [
                self.mav.request_data_stream_encode(0, 0, stream, 10, 1).pack(self.mav)
                for stream in (
                    M.MAV_DATA_STREAM_POSITION,
                    M.MAV_DATA_STREAM_EXTRA1,
                    M.MAV_DATA_STREAM_EXTENDED_STATUS,
                )
            ]
            for address in self.sitls:
                for data in (hello, *asks):
                    self.sock.sendto(data, address)
            self._next_hello = now + 0.5
        while True:
            try:
                data = self.sock.recv(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # ICMP from a SITL that is gone
                continue
            wall_ns = time.time_ns()
            for msg in self.mav.parse_buffer(data) or []:
                self._on_message(msg, wall_ns)

    def _on_message(self, msg, wall_ns: int) -> None:
        vid, kind = msg.get_srcSystem(), msg.get_type()
        if msg.get_srcComponent() != 1 or vid not in self.scenario.vehicle_ids:
            return
        if kind == "HEARTBEAT":
            mode = mode_from_custom(msg.custom_mode, Autopilot(msg.autopilot))
            armed = bool(msg.base_mode & ModeFlag.SAFETY_ARMED)
            self.heartbeats[vid].append((wall_ns, msg.autopilot, mode, armed))
        elif kind == "STATUSTEXT":
            self.texts[vid].append((wall_ns, msg.text))
        elif kind == "GLOBAL_POSITION_INT":
            site = self.scenario.site
            north, east = ned_from_geodetic(
                msg.lat * 1e-7,
                msg.lon * 1e-7,
                home_lat_deg=site.home_lat_deg,
                home_lon_deg=site.home_lon_deg,
            )
            self.positions[vid].append((wall_ns, north, east, msg.relative_alt * 1e-3))

    def close(self) -> None:
        self.sock.close()


def malformed_plan_payloads() -> list[tuple[RejectReason, bytes]]:
    """Payloads for vehicle 2's plan key, each with the reason its receivers must give."""
    plan = Plan(
        vehicle_id=2,
        stamp_ns=0,
        period_ns=200_000_000,
        states=np.zeros((6, 3)),
        inputs=np.zeros((5, 2)),
    )
    valid = encode(PlanMessage(seq=0, plan=plan))
    wrong_version = bytearray(valid)
    wrong_version[2] = SCHEMA_VERSION + 1
    nan_state = bytearray(valid)
    struct.pack_into("<d", nan_state, 66, math.nan)  # states[0].x (protocol.codec layout)
    garbage = b"\x00\xff" + np.random.default_rng(5).bytes(len(valid) - 2)
    from_vehicle_1 = encode(PlanMessage(seq=0, plan=dataclasses.replace(plan, vehicle_id=1)))
    return [
        (RejectReason.SIZE, valid[:7]),  # shorter than a header
        (RejectReason.SIZE, valid[:-8]),  # truncated plan
        (RejectReason.VERSION, bytes(wrong_version)),
        (RejectReason.NON_FINITE, bytes(nan_state)),
        (RejectReason.MAGIC, garbage),
        (RejectReason.KEY_MISMATCH, from_vehicle_1),  # a valid plan of vehicle 1 on 2's key
    ]


@dataclasses.dataclass
class Flight:
    """What one flight left behind; times in fleet seconds."""

    scenario: Scenario
    epoch: FleetEpoch
    malformed_s: float
    gcs_done_s: float
    kill_s: float
    stop_s: float
    metrics: dict
    """The ground station's metrics JSON."""
    lockstep: dict
    """compute_metrics of the lockstep run of the same scenario, seed and duration."""
    summaries: dict[int, dict]
    """Exit summaries of the agents that were stopped (not the killed one)."""
    records: dict[int, list[dict]]
    """Each agent's per-step rows."""
    peer: GroundStationPeer
    exit_codes: dict[str, int | None]
    leftovers: list[tuple[int, str]]
    logs: ProcessGroup

    def fleet_s(self, wall_ns: int) -> float:
        return (wall_ns - self.epoch.epoch_ns) * self.epoch.speed * 1e-9

    def modes(self, vid: int, start_s: float, end_s: float) -> list[tuple[FlightMode, bool]]:
        """(mode, armed) of vehicle `vid`'s heartbeats heard in [start_s, end_s]."""
        return [
            (mode, armed)
            for wall, _, mode, armed in self.peer.heartbeats[vid]
            if start_s <= self.fleet_s(wall) <= end_s
        ]

    def track(self, vid: int) -> np.ndarray:
        """(fleet s, north, east, altitude) rows of vehicle `vid`."""
        return np.array([(self.fleet_s(w), n, e, a) for w, n, e, a in self.peer.positions[vid]])


def _formation(metrics: dict) -> dict:
    keys = ("separation_error_m", "centre_distance_error_m", "min_separation_m")
    return {k: metrics[k] for k in keys}


def engaged_before_epoch_s(flight: "Flight") -> dict[int, float]:
    """Fleet seconds each vehicle was armed and engaged before fleet time 0."""
    out = {}
    for vid, beats in flight.peer.heartbeats.items():
        engaged = [w for w, _, mode, armed in beats if mode == FlightMode.OFFBOARD and armed]
        out[vid] = -flight.fleet_s(engaged[0]) if engaged else math.nan
    return out


def _report(flight_dir: Path, flight: "Flight") -> None:
    """The measured figures, in ``report.json`` beside the logs and printed (``pytest -s``)."""
    try:
        text = json.dumps(_figures(flight), default=str)
    except Exception as e:  # a broken flight: the gate tests say what broke
        text = json.dumps({"incomplete": f"{type(e).__name__}: {e}"})
    (flight_dir / "report.json").write_text(text + "\n")
    print(f"fleet e2e figures ({flight_dir}): {text}")


def _figures(flight: "Flight") -> dict:
    return {
        "times_s": {
            "malformed": flight.malformed_s,
            "gcs_done": flight.gcs_done_s,
            "kill": flight.kill_s,
            "stop": flight.stop_s,
        },
        "live": _formation(flight.metrics),
        "lockstep": _formation(flight.lockstep),
        "setpoint_gap_fleet_ms": {
            vid: {k: s["setpoint_gap_wall_ms"][k] * SPEED for k in ("p50", "p99", "max")}
            for vid, s in flight.summaries.items()
        },
        "hold_after_kill_s": hold_after_kill_s(flight),
        "killed_plan_seen": {
            vid: {k: v for k, v in killed_plan_as_seen_by(flight, vid).items() if k != "after"}
            for vid in SURVIVORS
        },
        "closest_m": min_distances(flight, flight.stop_s),
        "engaged_before_epoch_s": engaged_before_epoch_s(flight),
        "start_offset_m": {
            v.id: math.dist(flight.records[v.id][0]["pose"][:2], v.initial[:2])
            for v in flight.scenario.vehicles
        },
        "lockstep_from_live_start": _formation(
            compute_metrics(
                run_lockstep(
                    dataclasses.replace(
                        flight.scenario,
                        vehicles=tuple(
                            dataclasses.replace(v, initial=tuple(flight.records[v.id][0]["pose"]))
                            for v in flight.scenario.vehicles
                        ),
                    ),
                    duration_s=GCS_DURATION_S,
                )
            )
        ),
        "overruns": {vid: s["overruns"] for vid, s in flight.summaries.items()},
        "skipped_periods": skipped_periods(flight),
        "exit_codes": flight.exit_codes,
    }


def skipped_periods(flight: Flight) -> dict[int, list[float]]:
    """Per agent, the fleet times of the periods it did not step before the kill, by its own
    records (the step after a gap runs at the newest boundary; the ones between are skipped)."""
    period = flight.scenario.controller.period_s
    out = {}
    for vid, rows in flight.records.items():
        stamps = [r["stamp_ns"] * 1e-9 for r in rows if r["stamp_ns"] * 1e-9 < flight.kill_s]
        out[vid] = [
            a + k * period
            for a, b in itertools.pairwise(stamps)
            for k in range(1, round((b - a) / period))
        ]
    return out


def host_stalled(flight: Flight) -> bool:
    """Whether the first flight's skipped periods are the host's doing: a surviving agent that
    skipped any counted each as an overrun (it woke past the period's boundary) and no step of
    either failed (a failed step leaves no row either), and no process was left behind."""
    skipped = skipped_periods(flight)
    if not any(skipped.values()) or flight.leftovers:
        return False
    return all(
        flight.summaries[vid]["step_errors"] == 0
        and flight.summaries[vid]["overruns"] >= len(skipped[vid])
        for vid in SURVIVORS
    )


@pytest.fixture(scope="module")
def flight(tmp_path_factory) -> Flight:
    """One flight, or a second, said in a warning, when the host stalled the first
    (`host_stalled`): a machine that stops every process for a fraction of a second is not a
    failure of a gate. A fault of the code that stalls an agent in every flight (a payload that
    hangs the bus, say) fails the second; one that does so in one flight in two would pass in
    three cases of four, a price of flying on a shared host."""
    result = fly(tmp_path_factory.mktemp("fleet"))
    if host_stalled(result):
        warnings.warn(
            "fleet e2e: flown again, the host stalled the first flight "
            f"(skipped periods by agent: {skipped_periods(result)})",
            stacklevel=1,
        )
        result = fly(tmp_path_factory.mktemp("fleet"))
    return result


def fly(tmp: Path) -> Flight:
    path = scenario_on_free_ports(SOURCE, tmp / "mixed-autopilots.toml")
    scenario = load_scenario(path)
    fleet = f"e2e-{os.getpid()}"
    records_dir = tmp / "records"
    specs = fleet_processes(
        scenario,
        FleetOptions(
            scenario_path=str(path),
            speed=SPEED,
            duration_s=GCS_DURATION_S,
            fleet=fleet,
            metrics=str(tmp / "metrics.json"),
            viewer="none",
            agent_records_dir=str(records_dir),
        ),
    )
    extra = {
        "sitl": ("--com-of-loss-t", f"{COM_OF_LOSS_T_S:g}"),
        "target": ("--duration", f"{TARGET_DURATION_S:g}"),
    }
    argv = {s.name: (*s.argv, *extra.get(s.role, ())) for s in specs}
    roles = {s.name: s.role for s in specs}
    procs = ProcessGroup(tmp / "logs")
    peer = GroundStationPeer(scenario)
    session = None
    epochs: list[FleetEpoch] = []

    def alive(*, allowed_to_exit: set[str]) -> None:
        for name, child in procs.children.items():
            if name not in allowed_to_exit and child.proc.poll() is not None:
                raise AssertionError(f"{name} exited with {child.proc.returncode}\n{child.tail()}")

    try:
        # The start order of `fleetmpc up`; the SITLs are ready before an agent looks for them.
        procs.fleetmpc("zenoh-router", *argv["zenoh-router"]).wait_for("listening")
        net = scenario.network
        session = zenoh.open(
            ZenohOptions(mode="client", connect=(endpoint(net.host, net.zenoh_port),)).to_config()
        )

        def on_epoch(sample: zenoh.Sample) -> None:
            with contextlib.suppress(DecodeError):
                epochs.append(decode(sample.payload.to_bytes(), expect=MessageKind.FLEET_EPOCH))

        subscriber = session.declare_subscriber(epoch_key(fleet), on_epoch)
        procs.fleetmpc("target", *argv["target"])
        sitls = [name for name, role in roles.items() if role == "sitl"]
        for name in sitls:
            procs.fleetmpc(name, *argv[name])
        for name in sitls:
            ready = procs[name].wait_for(r"gcs udp 127\.0\.0\.1:(\d+) ->")
            peer.add_sitl(int(ready.group(1)))
        peer.poll()
        for name, role in roles.items():
            if role in ("agent", "gcs"):
                procs.fleetmpc(name, *argv[name])

        deadline = time.monotonic() + ENGAGE_TIMEOUT_S
        while not epochs:
            peer.poll()
            alive(allowed_to_exit=set())
            assert time.monotonic() < deadline, "no epoch announced:\n" + procs["gcs"].tail()
            time.sleep(0.01)
        epoch = epochs[0]

        def now_s() -> float:
            return (time.time_ns() - epoch.epoch_ns) * epoch.speed * 1e-9

        malformed_s = gcs_done_s = kill_s = None
        deadline = time.monotonic() + (GCS_DURATION_S + WATCH_AFTER_KILL_S) / SPEED + 60.0
        while kill_s is None or now_s() < kill_s + WATCH_AFTER_KILL_S:
            peer.poll()
            if malformed_s is None and now_s() >= MALFORMED_AT_S:
                malformed_s = now_s()
                for _, payload in malformed_plan_payloads():
                    session.put(plan_key(fleet, 2), payload)
            if kill_s is None and procs["gcs"].proc.poll() is not None:
                gcs_done_s = now_s()
                assert gcs_done_s >= GCS_DURATION_S, procs["gcs"].tail()
                kill_s = now_s()  # the signal's time; reaping the child takes a while
                procs.kill(f"agent-{KILLED}")
            alive(allowed_to_exit={"gcs", f"agent-{KILLED}"})
            assert time.monotonic() < deadline, "the flight did not end:\n" + procs["gcs"].tail()
            time.sleep(0.01)
        stop_s = now_s()
        subscriber.undeclare()
        # Shutdown in `fleetmpc up`'s order: agents (they ask for HOLD), target, SITLs, router.
        procs.stop(*(f"agent-{vid}" for vid in SURVIVORS))
        peer.poll()
        summaries = {
            vid: json.loads(procs[f"agent-{vid}"].out().strip().splitlines()[-1])
            for vid in SURVIVORS
        }
        for role in ("target", "sitl", "router"):
            procs.stop(*(name for name, r in roles.items() if r == role))
    finally:
        exit_codes = procs.stop_all()
        if session is not None:
            session.close()
        peer.close()
    leftovers = live_processes_naming(str(path))
    records = {
        v.id: [
            json.loads(line)
            for line in (records_dir / f"agent-{v.id}.jsonl").read_text().splitlines()
        ]
        for v in scenario.vehicles
    }
    lockstep = compute_metrics(run_lockstep(scenario, duration_s=GCS_DURATION_S))
    result = Flight(
        scenario=scenario,
        epoch=epoch,
        malformed_s=malformed_s,
        gcs_done_s=gcs_done_s,
        kill_s=kill_s,
        stop_s=stop_s,
        metrics=json.loads((tmp / "metrics.json").read_text()),
        lockstep=lockstep,
        summaries=summaries,
        records=records,
        peer=peer,
        exit_codes=exit_codes,
        leftovers=leftovers,
        logs=procs,
    )
    _report(tmp, result)
    return result


# -- formation ----------------------------------------------------------------------------------
START_TOLERANCE_M = 0.5
"""Measured first pose vs the scenario's initial one: two measurements, each within 3 sigma
(0.15 m per axis) of the truth, the hold point and the first pose."""


def test_every_vehicle_waits_for_the_epoch_where_the_scenario_puts_it(flight: Flight) -> None:
    """Engaged seconds before the epoch, each vehicle is held by its autopilot at the point its
    agent found it (position setpoints; the wind moves nothing), so live and lockstep start
    together."""
    for v in flight.scenario.vehicles:
        first = flight.records[v.id][0]
        assert first["stamp_ns"] == 0, first
        offset = math.dist(first["pose"][:2], v.initial[:2])
        assert offset <= START_TOLERANCE_M, (v.id, offset, engaged_before_epoch_s(flight))


def test_fleet_flies_the_formation_of_the_lockstep_run(flight: Flight) -> None:
    """Same metrics as the lockstep run of the same scenario and seed, within 0.1 m."""
    live, ref = flight.metrics, flight.lockstep
    # The ground station's own gates held: d_safe, and every period of the 30 s recorded.
    assert flight.exit_codes["gcs"] == 0, flight.logs["gcs"].tail()
    periods = round(GCS_DURATION_S / flight.scenario.controller.period_s) + 1
    assert live["periods_recorded"] == live["periods_expected"] == periods
    assert live["separation_pairs"] == ref["separation_pairs"]
    for pair, a, b in zip(
        live["separation_pairs"], live["separation_error_m"], ref["separation_error_m"], strict=True
    ):
        assert abs(a - b) <= FORMATION_TOLERANCE_M, (pair, a, b)
    assert (
        abs(live["centre_distance_error_m"] - ref["centre_distance_error_m"])
        <= FORMATION_TOLERANCE_M
    ), (live["centre_distance_error_m"], ref["centre_distance_error_m"])
    assert live["min_separation_m"] >= flight.scenario.controller.d_safe_m
    # Every agent took the announced epoch in time: its first step is fleet time 0, engaged (in
    # its autopilot's own mode: OFFBOARD for PX4, GUIDED for ArduPilot).
    engaged = {"px4": "OFFBOARD", "ardupilot": "GUIDED"}
    for vid, rows in flight.records.items():
        mode = engaged[flight.scenario.vehicle(vid).autopilot]
        assert rows[0]["stamp_ns"] == 0 and rows[0]["mode"] == mode, (vid, rows[0])


# -- malformed payloads -------------------------------------------------------------------------
def _steps_between(rows: list[dict], start_s: float, end_s: float) -> list[float]:
    return [r["stamp_ns"] * 1e-9 for r in rows if start_s <= r["stamp_ns"] * 1e-9 <= end_s]


def test_malformed_plan_payloads_are_rejected_counted_and_flown_through(flight: Flight) -> None:
    """Too short, truncated, wrong version, NaN state, garbage, wrong sender: each one counted
    by its reason at every agent, and the agents kept stepping and flying."""
    expected = Counter(str(reason) for reason, _ in malformed_plan_payloads())
    period_s = flight.scenario.controller.period_s
    for vid in SURVIVORS:
        summary = flight.summaries[vid]
        assert summary["bus"]["rejected"] == dict(expected), (vid, summary["bus"])
        assert summary["step_errors"] == 0 and summary["failure"] is None, summary
        # Not one period missed from a second before the payloads to five seconds after.
        start = flight.malformed_s - 1.0
        stamps = _steps_between(flight.records[vid], start, flight.malformed_s + 5.0)
        assert len(stamps) >= round(6.0 / period_s) - 1, stamps
        assert np.allclose(np.diff(stamps), period_s), stamps
    for vid in flight.scenario.vehicle_ids:
        after = flight.modes(vid, flight.malformed_s, flight.gcs_done_s)
        assert after and set(after) == {(FlightMode.OFFBOARD, True)}, (vid, after)


# -- a killed agent -----------------------------------------------------------------------------
def min_distances(flight: Flight, end_s: float) -> dict[str, float]:
    """Closest approach of every pair of vehicles, and of each vehicle to the target, 0..end_s."""
    t = np.arange(0.0, end_s, 0.05)
    pos = {}
    for vid in flight.scenario.vehicle_ids:
        track = flight.track(vid)
        pos[vid] = np.stack([np.interp(t, track[:, 0], track[:, k]) for k in (1, 2)], axis=1)
    target = np.array([flight.scenario.target.state_at(float(s))[0][:2] for s in t])
    out = {}
    ids = flight.scenario.vehicle_ids
    for i, a in enumerate(ids):
        out[f"{a}-target"] = float(np.min(np.linalg.norm(pos[a] - target, axis=1)))
        for b in ids[i + 1 :]:
            out[f"{a}-{b}"] = float(np.min(np.linalg.norm(pos[a] - pos[b], axis=1)))
    return out


def hold_after_kill_s(flight: Flight) -> float | None:
    """Fleet seconds from the SIGKILL to the killed agent's SITL saying it lost offboard (its
    STATUSTEXT comes at once), provided a HOLD heartbeat follows within its 1 Hz."""
    lost = [
        flight.fleet_s(wall) - flight.kill_s
        for wall, text in flight.peer.texts[KILLED]
        if "Offboard lost" in text and flight.fleet_s(wall) > flight.kill_s
    ]
    holds = [
        flight.fleet_s(wall) - flight.kill_s
        for wall, _, mode, _ in flight.peer.heartbeats[KILLED]
        if mode == FlightMode.HOLD and flight.fleet_s(wall) > flight.kill_s
    ]
    if not lost or not holds or not 0.0 <= holds[0] - lost[0] <= 1.1:
        return None
    return lost[0]


def killed_plan_as_seen_by(flight: Flight, vid: int) -> dict:
    """How agent `vid`'s steps saw the killed agent's plan: its age [s] and formation terms.

    ``normal_max_s``: the largest age before the kill (from 1 s on); ``stale_after_s``: fleet
    seconds from the kill to the first step whose age is beyond that (``stale_after_steps``:
    which step after the kill it is); ``dropped_after_s``: to
    the first step without the killed agent's formation term; ``after``: (t, age, terms) rows
    from the kill to the shutdown; ``terms_before``: the formation terms of the steps from 2 s
    to the kill.
    """
    kill, period = flight.kill_s, flight.scenario.controller.period_s
    rows = [
        (r["stamp_ns"] * 1e-9, r["neighbour_ages_s"].get(str(KILLED)), r["formation_terms"])
        for r in flight.records[vid]
    ]
    normal = [a for t, a, _ in rows if 1.0 <= t < kill - period]
    after = [(t, a, n) for t, a, n in rows if kill < t <= flight.stop_s]
    normal_max = max(normal) if None not in normal else math.inf
    stale_rows = [k for k, (_, a, _) in enumerate(after) if a is not None and a > normal_max]
    stale = [after[k][0] - kill for k in stale_rows]
    dropped = [t - kill for t, _, n in after if n < len(flight.scenario.vehicles) - 1]
    return {
        "normal_max_s": normal_max,
        "stale_after_s": stale[0] if stale else None,
        "stale_after_steps": stale_rows[0] + 1 if stale_rows else None,
        "dropped_after_s": dropped[0] if dropped else None,
        "after": after,
        "terms_before": {n for t, _, n in rows if 2.0 <= t < kill},
    }


def test_a_killed_agent_holds_its_vehicle_and_goes_stale_for_the_others(flight: Flight) -> None:
    """SIGKILL agent 3: its SITL fails safe to HOLD; agents 1 and 2 see its plan age run away
    at their first step after it is older than it ever was, and drop its formation term past
    the staleness bound; no two vehicles come closer than d_safe, from the epoch to the
    shutdown."""
    kill, stop = flight.kill_s, flight.stop_s
    settings = flight.scenario.controller
    assert set(flight.modes(KILLED, 0.0, kill)) == {(FlightMode.OFFBOARD, True)}
    # Its autopilot saw no setpoint for COM_OF_LOSS_T and held (one stream period of slack).
    hold = hold_after_kill_s(flight)
    assert hold is not None, flight.peer.heartbeats[KILLED][-5:]
    assert COM_OF_LOSS_T_S - 0.1 <= hold <= COM_OF_LOSS_T_S + 0.3, hold
    for vid in SURVIVORS:
        assert set(flight.modes(vid, 0.0, stop)) == {(FlightMode.OFFBOARD, True)}, vid
        seen = killed_plan_as_seen_by(flight, vid)
        assert seen["normal_max_s"] < PLAN_AGE_REACTION_S, seen["normal_max_s"]
        after = seen["after"]
        assert after[-1][0] >= kill + WATCH_AFTER_KILL_S - 0.5, after[-1]
        # At the first step after the plan got older than it ever was (its normal largest age,
        # in steps, and one for the step's phase), the age leaves its normal range, and from
        # then on it grows with time: nothing newer than the kill arrives. (Counted in steps, not
        # seconds: a loaded machine runs late steps, not fewer.)
        assert seen["stale_after_steps"] is not None, after
        steps = math.ceil(seen["normal_max_s"] / settings.period_s) + 2
        assert seen["stale_after_steps"] <= steps, (seen["stale_after_steps"], steps, after[:5])
        assert all(a >= t - kill - 0.05 for t, a, _ in after if t >= kill + 0.2), after
        # Past plan_stale_s its formation term is dropped; the live neighbour's stays.
        assert seen["terms_before"] == {2}, seen["terms_before"]
        assert all(n == (1 if a > settings.plan_stale_s else 2) for _, a, n in after), after
        assert seen["dropped_after_s"] is not None, after
    # d_safe holds between vehicles, the held one included (the target is tracked, not avoided:
    # its distances are in the report).
    closest = min_distances(flight, stop)
    pairs = {k: v for k, v in closest.items() if "target" not in k}
    assert len(pairs) == 3 and min(pairs.values()) >= settings.d_safe_m, closest


# -- ArduPilot with PX4 neighbours --------------------------------------------------------------
def _states(flight: Flight, vid: int, end_s: float) -> list[tuple[FlightMode, bool]]:
    """Vehicle `vid`'s (mode, armed) changes up to `end_s`, from its first heartbeat."""
    out: list[tuple[FlightMode, bool]] = []
    for wall, _, mode, armed in flight.peer.heartbeats[vid]:
        if flight.fleet_s(wall) <= end_s and (not out or out[-1] != (mode, armed)):
            out.append((mode, armed))
    return out


def test_ardupilot_vehicle_takes_off_in_guided_and_flies_with_px4_neighbours(
    flight: Flight,
) -> None:
    """Vehicle 2 is an ArduPilot-profile SITL on TCP: its agent sets GUIDED, arms, takes off,
    and it holds its slots next to two PX4-profile vehicles."""
    autopilots = {vid: {hb[1] for hb in hbs} for vid, hbs in flight.peer.heartbeats.items()}
    assert autopilots == {1: {Autopilot.PX4}, 2: {Autopilot.ARDUPILOTMEGA}, 3: {Autopilot.PX4}}
    # Boot mode, then GUIDED (OFFBOARD here), then armed; nothing else until the shutdown.
    # (GUIDED unarmed may fall between two of its 1 Hz HEARTBEATs.)
    states = _states(flight, ARDUPILOT, flight.stop_s)
    assert states in (
        [(FlightMode.STABILIZE, False), (FlightMode.OFFBOARD, False), (FlightMode.OFFBOARD, True)],
        [(FlightMode.STABILIZE, False), (FlightMode.OFFBOARD, True)],
    ), states
    texts = [text for _, text in flight.peer.texts[ARDUPILOT]]
    assert "Armed by external command" in texts, texts
    assert "Takeoff complete at 10.0 m" in texts, texts
    track = flight.track(ARDUPILOT)
    flying = track[(track[:, 0] >= 5.0) & (track[:, 0] <= flight.stop_s)]
    assert len(flying) > 100 and np.all(flying[:, 3] >= 9.9), flying[:, 3].min()
    port = flight.scenario.network.ardupilot_tcp_port(ARDUPILOT)
    log = flight.logs[f"agent-{ARDUPILOT}"].err()
    assert f"vehicle 2: ARDUPILOTMEGA on tcp:127.0.0.1:{port}" in log, log
    assert "vehicle 2: engaged" in log, log
    live, ref = flight.metrics, flight.lockstep
    for pair, a, b in zip(
        live["separation_pairs"], live["separation_error_m"], ref["separation_error_m"], strict=True
    ):
        if ARDUPILOT in pair:
            assert abs(a - b) <= FORMATION_TOLERANCE_M, (pair, a, b)


# -- the setpoint stream ------------------------------------------------------------------------
def test_setpoint_stream_gap_at_the_autopilot(flight: Flight) -> None:
    """No gap of 0.5 s of fleet time in any setpoint stream, as the autopilot saw it.

    The PX4 SITLs ran with COM_OF_LOSS_T = 0.5 s, so a gap of 0.5 s of fleet time between
    setpoints as they arrived would have dropped them to HOLD; they stayed in OFFBOARD until the
    kill (vehicle 3) or the shutdown (vehicle 1). The agents' own timing of the gaps (wall clock,
    their p50/p99/max in the summaries) depends on how loaded the machine is, so it is not
    asserted; that the streams ran the whole flight is.
    """
    for vid in SURVIVORS:
        gaps = flight.summaries[vid]["setpoint_gap_wall_ms"]
        assert gaps["count"] >= 20.0 * flight.stop_s, gaps  # 20 Hz over the flight at least
    for vid, end_s in ((1, flight.stop_s), (KILLED, flight.kill_s)):
        assert set(flight.modes(vid, 0.0, end_s)) == {(FlightMode.OFFBOARD, True)}, vid


# -- clean-up -----------------------------------------------------------------------------------
def test_every_process_ends_and_nothing_is_left(flight: Flight) -> None:
    codes = dict(flight.exit_codes)
    assert codes.pop(f"agent-{KILLED}") == -9
    assert codes == dict.fromkeys(codes, 0), codes
    assert flight.leftovers == []
