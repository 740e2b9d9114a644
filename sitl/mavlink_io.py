"""MAVLink 2 bytes on loopback sockets: encoder, robust decoder, UDP links and a TCP server.

A link is one place messages come from and go to, with its own telemetry stream table:
- `UdpLink`: one bound UDP socket (like a PX4 `mavlink start -u LOCAL -o REMOTE` instance). It
  sends to its configured remote port and also to whoever sent it a valid MAVLink message
  recently (at most `max_peers`), so a client can talk to it from any port.
- `TcpServer` + `TcpLink`: an ArduPilot-SITL-like TCP server; each accepted client is a link.

Decoding never raises: garbage, bad CRCs, truncated frames and unknown message ids are dropped and
counted. UDP datagrams are decoded independently, so a corrupt one cannot poison the next.
"""

import os

os.environ["MAVLINK20"] = "1"  # before pymavlink is imported anywhere

import socket  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402

from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

__all__ = [
    "DecodeStats",
    "FrameDecoder",
    "Incoming",
    "MavlinkEncoder",
    "TcpLink",
    "TcpServer",
    "UdpLink",
    "mavlink",
]

Address = tuple[str, int]


class _Capture:
    """File-like sink that keeps the last frame pymavlink writes."""

    def __init__(self) -> None:
        self.frame = b""

    def write(self, data: bytes) -> None:
        self.frame = bytes(data)


class MavlinkEncoder:
    """Packs messages from one system/component with one sequence counter."""

    def __init__(self, *, system_id: int, component_id: int = 1) -> None:
        self._sink = _Capture()
        self.mav = mavlink.MAVLink(self._sink, srcSystem=system_id, srcComponent=component_id)
        """pymavlink object whose `*_encode` methods build messages."""

    def pack(self, message: mavlink.MAVLink_message) -> bytes:
        self.mav.send(message)
        return self._sink.frame


@dataclass
class DecodeStats:
    """Counters of what arrived on the wire."""

    bytes: int = 0
    messages: int = 0
    bad_frames: int = 0
    unknown: int = 0


class FrameDecoder:
    """Decodes MAVLink 1/2 frames of one input; never raises."""

    def __init__(self, stats: DecodeStats) -> None:
        self.stats = stats
        self._mav = mavlink.MAVLink(None)
        self._mav.robust_parsing = True

    def datagram(self, data: bytes) -> list[mavlink.MAVLink_message]:
        """Messages of one self-contained datagram (parser state is reset first)."""
        self._reset()
        return self.stream(data)

    def stream(self, data: bytes) -> list[mavlink.MAVLink_message]:
        """Messages completed by the next chunk of a byte stream."""
        self.stats.bytes += len(data)
        out: list[mavlink.MAVLink_message] = []
        try:
            parsed = self._mav.parse_buffer(data) or []
        except Exception:  # a malformed frame must never reach the I/O loop
            self._reset()
            self.stats.bad_frames += 1
            return out
        for m in parsed:
            if isinstance(m, mavlink.MAVLink_bad_data):
                self.stats.bad_frames += 1
            elif isinstance(m, mavlink.MAVLink_unknown):
                self.stats.unknown += 1
            else:
                self.stats.messages += 1
                out.append(m)
        return out

    def _reset(self) -> None:
        mav = self._mav
        mav.buf = bytearray()
        mav.buf_index = 0
        mav.expected_length = mavlink.HEADER_LEN_V1 + 2
        mav.have_prefix_error = False


@dataclass
class Incoming:
    """One decoded message and where to send the answer."""

    message: mavlink.MAVLink_message
    link: "UdpLink | TcpLink"
    peer: Address | None
    """UDP source address; None for a TCP link."""


def _bind_udp(host: str, port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 21)
        sock.bind((host, port))
    except OSError:
        sock.close()
        raise
    sock.setblocking(False)
    return sock


@dataclass(eq=False)
class UdpLink:
    """A bound UDP socket with a default remote and the peers that have talked to it."""

    name: str
    sock: socket.socket
    remote: Address | None
    stats: DecodeStats = field(default_factory=DecodeStats)
    max_peers: int = 8
    peers: dict[Address, int] = field(default_factory=dict)
    """Peer address -> simulated time it last sent a valid message [ns]."""
    send_errors: int = 0

    @classmethod
    def open(cls, name: str, *, host: str, local_port: int, remote: Address | None) -> "UdpLink":
        return cls(name=name, sock=_bind_udp(host, local_port), remote=remote)

    @property
    def local_address(self) -> Address:
        return self.sock.getsockname()

    def destinations(self) -> list[Address]:
        out = [] if self.remote is None else [self.remote]
        out.extend(a for a in self.peers if a != self.remote)
        return out

    def send(self, frame: bytes, peer: Address | None = None) -> None:
        """Send to `peer`, or to every destination when None; errors are counted, not raised."""
        for address in [peer] if peer is not None else self.destinations():
            try:
                self.sock.sendto(frame, address)
            except OSError:
                self.send_errors += 1

    def receive(
        self,
        decoder: FrameDecoder,
        now_ns: int,
        *,
        budget: int = 512,
        accept: Callable[[mavlink.MAVLink_message], bool] | None = None,
    ) -> list[Incoming]:
        """Drain up to `budget` datagrams without blocking; with `accept`, only the messages it
        accepts are returned, and only a sender of one becomes a peer (a signed vehicle streams
        nothing to whoever merely sends it a frame)."""
        out: list[Incoming] = []
        for _ in range(budget):
            try:
                data, address = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # e.g. ICMP port unreachable reported on a later call
                continue
            messages = decoder.datagram(data)
            if accept is not None:
                messages = [m for m in messages if accept(m)]
            if messages:
                self._remember(address, now_ns)
            out.extend(Incoming(m, self, address) for m in messages)
        return out

    def _remember(self, address: Address, now_ns: int) -> None:
        self.peers.pop(address, None)
        self.peers[address] = now_ns
        while len(self.peers) > self.max_peers:
            self.peers.pop(next(iter(self.peers)))

    def close(self) -> None:
        self.sock.close()


@dataclass(eq=False)
class TcpLink:
    """One accepted TCP client; output is buffered and dropped if the client stops reading."""

    name: str
    sock: socket.socket
    stats: DecodeStats
    decoder: FrameDecoder
    fd: int = -1
    """File descriptor at accept time (stays valid as a key after the socket closes)."""
    max_backlog_bytes: int = 1 << 20
    closed: bool = False
    _out: bytearray = field(default_factory=bytearray)

    def send(self, frame: bytes, peer: Address | None = None) -> None:
        if self.closed:
            return
        if len(self._out) + len(frame) > self.max_backlog_bytes:
            self.close()
            return
        self._out.extend(frame)
        self.flush()

    def flush(self) -> None:
        while self._out and not self.closed:
            try:
                sent = self.sock.send(self._out)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.close()
                return
            del self._out[:sent]

    def receive(self, now_ns: int) -> list[Incoming]:
        out: list[Incoming] = []
        for _ in range(64):
            try:
                data = self.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self.close()
                break
            if not data:
                self.close()
                break
            out.extend(Incoming(m, self, None) for m in self.decoder.stream(data))
        return out

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.sock.close()


@dataclass
class TcpServer:
    """Listening TCP socket; `accept` returns new client links."""

    sock: socket.socket
    stats: DecodeStats = field(default_factory=DecodeStats)
    max_clients: int = 8
    accepted: int = 0

    @classmethod
    def open(cls, *, host: str, port: int) -> "TcpServer":
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((host, port))
            sock.listen(4)
        except OSError:
            sock.close()
            raise
        sock.setblocking(False)
        return cls(sock=sock)

    @property
    def local_address(self) -> Address:
        return self.sock.getsockname()

    def accept(self, open_links: int) -> list[TcpLink]:
        out: list[TcpLink] = []
        while True:
            try:
                conn, _ = self.sock.accept()
            except (BlockingIOError, InterruptedError):
                return out
            except OSError:  # e.g. EMFILE or ECONNABORTED: try again on the next call
                return out
            if open_links + len(out) >= self.max_clients:
                conn.close()
                continue
            conn.setblocking(False)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.accepted += 1
            name = f"tcp{self.accepted}"
            out.append(TcpLink(name, conn, self.stats, FrameDecoder(self.stats), conn.fileno()))

    def close(self) -> None:
        self.sock.close()
