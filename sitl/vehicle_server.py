"""One simulated vehicle on the network: truth plant + autopilot logic behind MAVLink links.

Each loop iteration (`fleetmpc.sitl.vehicle_group` runs the loop, for one vehicle or several):
wait until the next plant tick or until a socket is readable; advance the plant tick by tick up
to the clock's time (the autopilot picks each tick's command, telemetry due at that tick is
sent, stamped with its simulated time); then read and handle every pending message. A loop
that finds the clock `LATE_TICKS` ticks or more ahead of the plant (the host kept the process
from running) reads what arrived meanwhile first, so the catch-up flies the
newest command: the autopilot's setpoint timeout then measures the gaps in what the agent sent,
not this process's own stall (a SITL starved for 250 ms of wall time at x4 would otherwise leave
OFFBOARD with setpoints waiting in its socket). Events are announced at once with
STATUSTEXT; mode and arming changes show in the next 1 Hz HEARTBEAT, as on PX4 and ArduPilot.
A parked vehicle (on the ground and not flying) does not move: wind only drifts a flying one, and
only while it flies a velocity demand; otherwise the autopilot holds or flies to a point.
Nothing raises out of the loop: a failing handler is counted and the loop goes on.

Signing (`ServerConfig.signing_key`): every frame sent is signed, and a frame received is acted
on only if `SigningGuard` accepts it (docs/design.md, "Security"); each reason for a rejection is
announced once in STATUSTEXT. SETUP_SIGNING changes the key only on a trusted link, one whose
frame passed the guard (signed with the current key), and only while disarmed (ArduPilot's
rule); an all-zero key with a zero timestamp turns signing off. Without a key no link is
trusted: the first key comes from the key file. (PX4 takes SETUP_SIGNING only over USB, which
a simulated vehicle lacks; ArduPilot takes it on any link while signing is off, so one hostile
frame could lock its owner out.)
"""

import contextlib
import selectors
import sys
from dataclasses import dataclass, field

import numpy as np

from fleetmpc.clock import Clock
from fleetmpc.errors import ConfigError
from fleetmpc.protocol.mavlink_map import Autopilot as AutopilotType
from fleetmpc.scenario import Site, VehicleSpec
from fleetmpc.security.mavlink_signing import (
    KEY_BYTES,
    MAX_SIGNING_TIMESTAMP,
    SigningGuard,
    advance_timestamp,
    sign_outgoing,
    stop_signing,
)
from fleetmpc.sitl.autopilot import Autopilot, AutopilotConfig, Profile
from fleetmpc.sitl.handlers import MessageHandler
from fleetmpc.sitl.mavlink_io import (
    DecodeStats,
    FrameDecoder,
    Incoming,
    MavlinkEncoder,
    TcpLink,
    TcpServer,
    UdpLink,
    mavlink,
)
from fleetmpc.sitl.plant import TruthPlant
from fleetmpc.sitl.telemetry import Identity, Snapshot, StreamSchedule, build, statustext
from fleetmpc.sitl.wind import WindField

__all__ = ["ServerConfig", "UdpEndpoint", "VehicleServer"]

_HEARTBEAT_ONLY = ((mavlink.MAVLINK_MSG_ID_HEARTBEAT, 1.0),)
LATE_TICKS = 2
"""A loop iteration that finds the plant this many ticks behind the clock, or more, reads its input
before catching up (module docstring)."""


@dataclass(frozen=True)
class UdpEndpoint:
    """One UDP link of the vehicle."""

    name: str
    """Label used in messages ("offboard", "gcs")."""
    local_port: int
    """Port the vehicle binds (0: any free port)."""
    remote_port: int | None
    """Port the vehicle streams to on the host; None: only answer peers that talk to it."""
    rates_hz: tuple[tuple[int, float], ...] = _HEARTBEAT_ONLY
    """Default message rates of this link: (message id, Hz) pairs."""
    remote_host: str | None = None
    """Address the vehicle streams to; None: the address it binds (`ServerConfig.host`)."""

    def __post_init__(self) -> None:
        if not 0 <= self.local_port <= 65535:
            raise ConfigError(f"{self.name}.local_port", f"must be a port, got {self.local_port}")
        if self.remote_port is not None and not 1 <= self.remote_port <= 65535:
            raise ConfigError(f"{self.name}.remote_port", f"must be a port, got {self.remote_port}")


@dataclass(frozen=True)
class ServerConfig:
    """Everything one vehicle process needs."""

    vehicle: VehicleSpec
    """Id, initial state and truth parameters."""
    site: Site
    """Home position and flight altitude."""
    tick_ns: int
    """Plant integration tick [ns]."""
    autopilot: AutopilotConfig
    """Autopilot limits, timeouts and profile."""
    seed: int = 0
    """Seed of the measurement noise (combined with the vehicle id) and of the wind field."""
    wind_clock_offset_ns: int = 0
    """What the fleet's wind clock reads when this vehicle boots [ns] (`TruthPlant`)."""
    host: str = "127.0.0.1"
    """Address every socket binds to and streams to."""
    udp: tuple[UdpEndpoint, ...] = ()
    """UDP links (PX4 profile)."""
    tcp_port: int | None = None
    """TCP server port (ArduPilot profile); None: no TCP server, 0: any free port."""
    tcp_rates_hz: tuple[tuple[int, float], ...] = _HEARTBEAT_ONLY
    """Default message rates of each TCP client link."""
    peer_timeout_ns: int = 10_000_000_000
    """A UDP peer silent for this long stops receiving telemetry [ns]."""
    signing_key: bytes | None = None
    """MAVLink 2 signing secret key (32 bytes); None: signing off until a SETUP_SIGNING."""

    def __post_init__(self) -> None:
        if not isinstance(self.tick_ns, int) or self.tick_ns <= 0:
            raise ConfigError("tick_ns", f"must be a positive integer, got {self.tick_ns!r}")
        if not self.udp and self.tcp_port is None:
            raise ConfigError("links", "a vehicle needs at least one UDP link or a TCP port")
        if self.tcp_port is not None and not 0 <= self.tcp_port <= 65535:
            raise ConfigError("tcp_port", f"must be a port, got {self.tcp_port}")
        if self.signing_key is not None and len(self.signing_key) != KEY_BYTES:
            raise ConfigError("signing_key", f"must be {KEY_BYTES} bytes")


@dataclass
class _Counters:
    loop_errors: int = 0
    last_error: str = ""
    ticks: int = 0
    sent: int = 0


@dataclass
class _Links:
    udp: list[UdpLink] = field(default_factory=list)
    tcp_server: TcpServer | None = None
    tcp: list[TcpLink] = field(default_factory=list)

    def all(self) -> list[UdpLink | TcpLink]:
        return [*self.udp, *self.tcp]


class VehicleServer:
    """The simulated vehicle process's state and I/O loop."""

    def __init__(self, config: ServerConfig, *, clock: Clock) -> None:
        self.config = config
        self.clock = clock
        v = config.vehicle
        self.plant = TruthPlant(
            v.truth,
            x_m=v.initial[0],
            y_m=v.initial[1],
            yaw_rad=v.initial[2],
            wind=WindField(v.truth.wind, seed=config.seed),
            wind_clock_offset_ns=config.wind_clock_offset_ns,
        )
        self.autopilot = Autopilot(config.autopilot)
        px4 = config.autopilot.profile == Profile.PX4
        self.ident = Identity(
            system_id=v.mavlink_system_id,
            autopilot=AutopilotType.PX4 if px4 else AutopilotType.ARDUPILOTMEGA,
            site=config.site,
            local_origin_m=config.autopilot.local_origin_m,
        )
        self.encoder = MavlinkEncoder(system_id=v.mavlink_system_id)
        self.stats = DecodeStats()
        self.counters = _Counters()
        self._rng = np.random.default_rng([config.seed, v.id])
        self._links = _Links()
        self._schedules: dict[UdpLink | TcpLink, StreamSchedule] = {}
        self._decoder = FrameDecoder(self.stats)
        self._selector = selectors.DefaultSelector()
        self.signing: SigningGuard | None = None
        """Checks incoming frames while signing is on; None while it is off."""
        self.signing_rejected = 0
        """Frames refused by signing, over every key this vehicle has had."""
        if config.signing_key is not None:
            self._set_signing_key(config.signing_key, timestamp=0)
        self.handler = MessageHandler(
            self.autopilot,
            self.ident,
            self.encoder.mav,
            schedule_of=lambda inc: self._schedules[inc.link],
            snapshot=self.snapshot,
            log=self._log,
        )
        try:
            self._open()
        except BaseException:
            self.close()
            raise

    def _log(self, text: str) -> None:
        print(f"fleetmpc sitl: vehicle {self.ident.system_id}: {text}", file=sys.stderr, flush=True)

    # ----------------------------------------------------------------------------- set-up
    def _open(self) -> None:
        c = self.config
        for ep in c.udp:
            remote = None if ep.remote_port is None else (ep.remote_host or c.host, ep.remote_port)
            try:
                link = UdpLink.open(ep.name, host=c.host, local_port=ep.local_port, remote=remote)
            except OSError as e:
                raise ConfigError(
                    f"{ep.name}-local-port", f"cannot bind {c.host}:{ep.local_port}: {e}"
                ) from None
            self._links.udp.append(link)
            self._schedules[link] = StreamSchedule(dict(ep.rates_hz))
            self._selector.register(link.sock, selectors.EVENT_READ)
        if c.tcp_port is not None:
            try:
                server = TcpServer.open(host=c.host, port=c.tcp_port)
            except OSError as e:
                raise ConfigError(
                    "tcp-port", f"cannot listen on {c.host}:{c.tcp_port}: {e}"
                ) from None
            server.stats = self.stats
            self._links.tcp_server = server
            self._selector.register(server.sock, selectors.EVENT_READ)

    @property
    def addresses(self) -> dict[str, str]:
        """Local endpoints by link name, e.g. "udp 127.0.0.1:24580 -> 127.0.0.1:14540"."""
        out = {}
        for link in self._links.udp:
            host, port = link.local_address
            target = f" -> {link.remote[0]}:{link.remote[1]}" if link.remote else ""
            out[link.name] = f"udp {host}:{port}{target}"
        if self._links.tcp_server is not None:
            host, port = self._links.tcp_server.local_address
            out["ardupilot"] = f"tcp {host}:{port}"
        return out

    def local_address(self, link_name: str) -> tuple[str, int]:
        """(host, port) bound by the UDP link `link_name`, or by the TCP server ("ardupilot")."""
        for link in self._links.udp:
            if link.name == link_name:
                return link.local_address
        if link_name == "ardupilot" and self._links.tcp_server is not None:
            return self._links.tcp_server.local_address
        raise KeyError(link_name)

    # ----------------------------------------------------------------------------- state
    def snapshot(self) -> Snapshot:
        """The vehicle as reported now (fresh measurement noise)."""
        z = self.plant.measure(self._rng)
        parked = self.parked
        vn, ve = (0.0, 0.0) if parked else (float(z[3]), float(z[4]))
        true_vn, true_ve = (0.0, 0.0) if parked else self.plant.ground_velocity_m_s
        wind_n, wind_e = self.plant.wind_m_s
        ap = self.autopilot
        x, y, yaw = self.plant.pose
        return Snapshot(
            time_ns=self.plant.time_ns,
            north_m=float(z[0]),
            east_m=float(z[1]),
            yaw_rad=float(z[2]),
            vel_north_m_s=vn,
            vel_east_m_s=ve,
            yaw_rate_rad_s=0.0 if parked else self.plant.achieved_input[1],
            altitude_m=ap.altitude_m,
            climb_rate_m_s=ap.climb_rate_m_s,
            armed=ap.armed,
            mode=ap.mode,
            landed_state=ap.landed_state,
            system_status=ap.system_status,
            position_ready=ap.position_ready(self.plant.time_ns),
            true_north_m=x,
            true_east_m=y,
            true_yaw_rad=yaw,
            true_vel_north_m_s=true_vn,
            true_vel_east_m_s=true_ve,
            true_wind_north_m_s=wind_n,
            true_wind_east_m_s=wind_e,
        )

    # ----------------------------------------------------------------------------- loop
    def step(self, timeout_s: float = 0.0) -> None:
        """One loop iteration: wait up to `timeout_s`, advance the plant, handle input."""
        if timeout_s > 0:
            self._selector.select(timeout_s)
        self.serve(self.clock.now_ns())

    def serve(self, now_ns: int, *, read: bool = True) -> None:
        """Advance the plant to `now_ns` and, if `read`, handle what arrived (a loop that knows
        no socket of this vehicle is readable passes False and saves the reads)."""
        try:
            if read and now_ns - self.plant.time_ns >= LATE_TICKS * self.config.tick_ns:
                self._serve_input(now_ns)
            self._advance_to(now_ns)
            if read:
                self._serve_input(now_ns)
            self._announce()
            self._housekeeping(now_ns)
        except Exception as e:  # never let one bad event end the vehicle
            self.counters.loop_errors += 1
            self.counters.last_error = f"{type(e).__name__}: {e}"

    @property
    def next_tick_ns(self) -> int:
        """Simulated time of the plant's next tick [ns]."""
        return self.plant.time_ns + self.config.tick_ns

    def fileno(self) -> int:
        """A descriptor that is readable while any socket of this vehicle is (its selector's),
        so one loop can wait on many vehicles (`fleetmpc.sitl.vehicle_group`)."""
        return self._selector.fileno()

    @property
    def parked(self) -> bool:
        """On the ground and not flying horizontally: the plant (wind included) stands still.

        A PX4 vehicle armed on the ground counts as flying (offboard from the ground is allowed).
        """
        ap = self.autopilot
        return ap.landed and not (ap.armed and ap.px4)

    def _advance_to(self, now_ns: int) -> None:
        tick = self.config.tick_ns
        while self.plant.time_ns + tick <= now_ns:
            x, y, heading = self.plant.pose
            ap = self.autopilot
            speed, yaw_rate = ap.step(
                self.plant.time_ns, tick, heading_rad=heading, position_m=(x, y)
            )
            self.plant.command(speed, yaw_rate)
            if self.parked:
                self.plant.time_ns += tick  # time passes, the parked vehicle does not drift
            elif ap.holding is not None:
                self.plant.fly_to(ap.holding, tick, speed_m_s=ap.config.speed_limit_m_s)
            else:
                self.plant.advance(tick)
            self.counters.ticks += 1
            self._announce()
            self._send_telemetry(self.plant.time_ns)

    def _send_telemetry(self, now_ns: int) -> None:
        snap: Snapshot | None = None
        for link in self._links.all():
            for msg_id in self._schedules[link].due(now_ns):
                snap = snap or self.snapshot()
                message = build(self.encoder.mav, msg_id, snap, ident=self.ident)
                if message is not None:
                    self._send(message, link)

    def _serve_input(self, now_ns: int) -> None:
        server = self._links.tcp_server
        if server is not None:
            for link in server.accept(len(self._links.tcp)):
                self._links.tcp.append(link)
                self._schedules[link] = StreamSchedule(dict(self.config.tcp_rates_hz))
                self._selector.register(link.fd, selectors.EVENT_READ)
        incoming: list[Incoming] = []
        for udp in self._links.udp:
            incoming.extend(udp.receive(self._decoder, now_ns, accept=self._admitted))
        for tcp in self._links.tcp:
            incoming.extend(i for i in tcp.receive(now_ns) if self._admitted(i.message))
        for inc in incoming:
            if inc.message.get_msgId() == mavlink.MAVLINK_MSG_ID_SETUP_SIGNING:
                self._setup_signing(inc.message)
                continue
            try:
                replies = self.handler.handle(inc, now_ns)
            except Exception as e:
                self.counters.loop_errors += 1
                self.counters.last_error = f"{inc.message.get_type()}: {type(e).__name__}: {e}"
                continue
            self._announce()
            for reply in replies:
                self._send(reply.message, reply.to.link, reply.to.peer)

    def _announce(self) -> None:
        """STATUSTEXT for every notice, at once. HEARTBEAT keeps its constant 1 Hz (PX4's
        `mavlink_main.cpp`, ArduPilot's GCS_MAVLINK): a mode or arming change shows in the next
        one, up to a second after the COMMAND_ACK of the command that made it."""
        for notice in self.autopilot.take_notices():
            self._broadcast(statustext(self.encoder.mav, notice.severity, notice.text))

    # ----------------------------------------------------------------------------- signing
    def _set_signing_key(self, key: bytes | None, *, timestamp: int) -> None:
        """Sign with `key` from now on (None: signing off)."""
        mav = self.encoder.mav
        if key is None:
            self.signing = None
            stop_signing(mav)
            return
        self.signing = SigningGuard(key, report=lambda _reason, text: self._warn(text))
        sign_outgoing(mav, key)
        advance_timestamp(mav, timestamp)

    def _admitted(self, message) -> bool:
        """True if `message` may be acted on: signing is off, or the guard accepts it. A
        message for another system is not this vehicle's to check: it is dropped unchecked and
        uncounted (a ground station's UDP server link sends every vehicle's commands, each
        signed with that vehicle's key, to every vehicle it hears; checked here they were "bad
        signature" once per vehicle in every clean run), but for a command: that one goes on,
        unchecked, to the handler, which ignores it as PX4 does, with its "Ignore command" log."""
        if getattr(message, "target_system", 0) not in (0, self.ident.system_id):
            return message.get_type() in ("COMMAND_LONG", "COMMAND_INT")
        if self.signing is None or self.signing.admit(message):
            return True
        self.signing_rejected += 1
        return False

    def _warn(self, text: str) -> None:
        self._broadcast(statustext(self.encoder.mav, mavlink.MAV_SEVERITY_WARNING, text))

    def _setup_signing(self, m) -> None:
        """SETUP_SIGNING (already passed the guard): refused while armed or while signing is off
        (module docstring); a zero key turns signing off."""
        if m.target_system not in (0, self.ident.system_id):
            return
        if self.signing is None:
            self._warn("SETUP_SIGNING refused: no trusted link")
            return
        if self.autopilot.armed:
            self._warn("ERROR: Won't setup signing when armed")
            return
        if not 0 <= m.initial_timestamp < MAX_SIGNING_TIMESTAMP:
            self._warn("SETUP_SIGNING refused: timestamp over 48 bits")
            return
        key = bytes(m.secret_key)
        off = m.initial_timestamp == 0 and not any(key)
        if not off and self.signing.has_key(key):
            # (the same key: its streams' last timestamps stay, so no replay reopens)
            advance_timestamp(self.encoder.mav, int(m.initial_timestamp))
        else:
            self._set_signing_key(None if off else key, timestamp=int(m.initial_timestamp))
        text = "signing off" if off else "signing key set"
        self._broadcast(statustext(self.encoder.mav, mavlink.MAV_SEVERITY_INFO, text))

    def _housekeeping(self, now_ns: int) -> None:
        for link in self._links.udp:
            stale = [a for a, t in link.peers.items() if now_ns - t > self.config.peer_timeout_ns]
            for address in stale:
                del link.peers[address]
        for link in [t for t in self._links.tcp if t.closed]:
            self._links.tcp.remove(link)
            self._schedules.pop(link, None)
            with contextlib.suppress(KeyError, ValueError):
                self._selector.unregister(link.fd)
        for link in self._links.tcp:
            link.flush()

    def _broadcast(self, message) -> None:
        for link in self._links.all():
            self._send(message, link)

    def _send(self, message, link: UdpLink | TcpLink, peer=None) -> None:
        if self.signing is not None:
            self.signing.refresh(self.encoder.mav)
        frame = self.encoder.pack(message)
        link.send(frame, peer)
        self.counters.sent += 1

    # ----------------------------------------------------------------------------- shutdown
    def summary(self) -> str:
        s, c, ap = self.stats, self.counters, self.autopilot
        rejected = ", ".join(f"{r.value}: {n}" for r, n in ap.rejected.items()) or "none"
        text = (
            f"vehicle {self.ident.system_id}: t = {self.plant.time_ns * 1e-9:.2f} s, "
            f"received {s.messages} messages ({s.bytes} bytes), dropped {s.bad_frames} bad frames "
            f"and {s.unknown} unknown, {self.handler.commands} commands"
            f" ({self.handler.commands_to_others} to other systems ignored), sent {c.sent}; "
            f"setpoints rejected: {rejected}; loop errors: {c.loop_errors}"
        )
        if self.signing is not None or self.signing_rejected:
            text += "; " + (self.signing.summary() if self.signing else "signing off")
            text += f" ({self.signing_rejected} refused in all)"
        return text + (f" (last: {c.last_error})" if c.last_error else "")

    def close(self) -> None:
        """Close every socket; safe to call twice."""
        for link in self._links.all():
            link.close()
        if self._links.tcp_server is not None:
            self._links.tcp_server.close()
        self._links = _Links()
        self._selector.close()
