"""MAVLink 2 message signing: key files, signing what we send, checking what we receive.

A signed MAVLink 2 frame carries 13 more bytes after its CRC: a link id (1 byte), a timestamp
(6 bytes, units of 10 us since 2015-01-01 00:00 UTC) and the first 6 bytes of
SHA-256(secret key + the frame up to and including the timestamp). A receiver with the key
accepts a frame when the signature matches and the timestamp is newer than the last one of
that stream (link id, system id, component id); a stream it has not seen must not be more than
a minute older than its own clock (the MAVLink signing specification,
https://mavlink.io/en/guide/message_signing.html).

The order of the two checks matters. pymavlink 2.4.50 records a stream's timestamp *before* it
compares the signature, so one forged frame with a far-future timestamp makes every later real
frame of that stream look like a replay: the link is locked out by anyone who can send it a
packet. `SigningGuard` checks the signature first, in constant time, and only then the
timestamp, and records the timestamp only of a frame that passed both. pymavlink still signs
what we send (its `MAVLink.signing` fields); its own receive check is replaced by the guard,
which runs on every decoded frame (`SigningGuard.admit`).

Keys: a key file holds a passphrase (one word of printable ASCII); the 32-byte secret key is
its SHA-256, as MAVProxy's ``signing setup``/``signing key`` derive it, so a user can give
MAVProxy the same passphrase. Key files must not be readable by group or others (like an ssh
private key).
"""

import enum
import hashlib
import hmac
import re
import secrets
import struct
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

from fleetmpc.errors import ConfigError
from fleetmpc.security.private_files import check_private, write_private

__all__ = [
    "KEY_BYTES",
    "MAX_SIGNING_TIMESTAMP",
    "KeyRing",
    "Rejection",
    "SigningGuard",
    "advance_timestamp",
    "key_file_name",
    "key_from_passphrase",
    "new_passphrase",
    "read_key_options",
    "read_key_file",
    "sign_outgoing",
    "signing_timestamp",
    "stop_signing",
    "write_key_file",
]

KEY_BYTES = 32
"""Length of a MAVLink signing secret key."""

_MAGIC_V1 = 0xFE
_MAGIC_V2 = 0xFD
_FLAG_SIGNED = 0x01
_SIGNATURE_BYTES = 13  # link id, 6-byte timestamp, 6-byte signature
_EPOCH_2015_NS = 1_420_070_400 * 1_000_000_000
_NEW_STREAM_SLACK = 60 * 100_000
"""A stream not seen before may be at most one minute older than our clock [10 us units]."""
MAX_SIGNING_TIMESTAMP = 1 << 48
"""Signing timestamps are 48-bit."""
_MAX_STREAMS = 4096
"""Streams (link id, system, component) remembered at most. Only a holder of the key can open
one (the signature is checked first); a new stream beyond this many is refused rather than the
table cleared, which would accept the last minute's frames again."""


class Rejection(enum.Enum):
    """Why a frame was not accepted on a signed link (short: a STATUSTEXT holds 50 characters)."""

    MAVLINK1 = "MAVLink 1"
    """A MAVLink 1 frame, which cannot be signed."""
    UNSIGNED = "unsigned"
    BAD_SIGNATURE = "bad signature"
    """A wrong key, or a frame changed on the way."""
    REPLAY = "replayed"
    """A timestamp not newer than the stream's last."""
    STALE = "stale stream"
    """A new stream more than a minute older than our clock."""
    TOO_MANY_STREAMS = "stream table full"


def key_from_passphrase(passphrase: str) -> bytes:
    """The 32-byte secret key of a passphrase (SHA-256 of its UTF-8 bytes)."""
    return hashlib.sha256(passphrase.encode("utf-8")).digest()


def new_passphrase() -> str:
    """A fresh random passphrase (256 bits, hexadecimal)."""
    return secrets.token_hex(32)


def write_key_file(path: Path, passphrase: str | None = None) -> Path:
    """Write a key file (mode 0600; refuses to overwrite) and return its path."""
    path = Path(path)
    text = passphrase if passphrase is not None else new_passphrase()
    _check_passphrase(text, "passphrase")
    write_private(path, text + "\n", field="key file")
    return path


def read_key_file(path: Path, *, field: str = "--mavlink-key") -> bytes:
    """The secret key of a key file; ConfigError naming `field` if it is missing, malformed or
    readable by group or others."""
    path = Path(path)
    check_private(path, field=field)
    try:
        text = path.read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(field, f"cannot read key file {path}: {e}") from None
    _check_passphrase(text, field, f"key file {path}: ")
    return key_from_passphrase(text)


def _check_passphrase(text: str, field: str, where: str = "") -> None:
    """A passphrase is one word of printable ASCII: MAVProxy reads it as ASCII, and its
    signing.keys file splits lines at white space."""
    if not text or not text.isascii() or not text.isprintable() or any(c.isspace() for c in text):
        raise ConfigError(field, f"{where}must be one word of printable ASCII (no spaces)")


def key_file_name(vehicle_id: int) -> str:
    """The name of vehicle `vehicle_id`'s key file in a key directory."""
    return f"mavlink-{vehicle_id}.key"


def read_key_options(
    items: Iterable[str], vehicle_ids: Iterable[int], *, field: str = "--mavlink-key"
) -> dict[int, bytes]:
    """The keys of ``ID=FILE`` options, by vehicle id; errors name `field` and the item."""
    known = set(vehicle_ids)
    keys: dict[int, bytes] = {}
    for item in items:
        vid_text, sep, path = item.partition("=")
        if not sep or not re.fullmatch(r"[0-9]{1,3}", vid_text) or not path:
            raise ConfigError(
                field, f"must be ID=FILE (e.g. 2=secrets/mavlink-2.key), got {item!r}"
            )
        vid = int(vid_text)
        if vid not in known:
            raise ConfigError(field, f"vehicle {vid} is not in the scenario (ids: {sorted(known)})")
        if vid in keys:
            raise ConfigError(field, f"vehicle {vid} is given twice")
        keys[vid] = read_key_file(Path(path), field=field)
    return keys


def signing_timestamp(now_ns: int) -> int:
    """A signing timestamp (10 us units since 2015-01-01 UTC) of a Unix time [ns]."""
    return max(0, (now_ns - _EPOCH_2015_NS) // 10_000)


def _check_key(key: bytes) -> bytes:
    if len(key) != KEY_BYTES:
        raise ValueError(f"a signing key has {KEY_BYTES} bytes, got {len(key)}")
    return bytes(key)


def advance_timestamp(mav, stamp: int) -> None:
    """Raise `mav`'s outgoing signing timestamp to `stamp` if it is lower (never backwards:
    a receiver would take what follows for replays)."""
    mav.signing.timestamp = max(mav.signing.timestamp, stamp)


def sign_outgoing(mav, key: bytes, *, link_id: int = 0, now_ns: int | None = None) -> None:
    """Make pymavlink's `mav` (a `MAVLink` object) sign every frame it packs with `key`.

    Its own receive check is switched off (it would record a forged frame's timestamp before
    comparing the signature): whoever receives on `mav` checks with a `SigningGuard`. Call
    `SigningGuard.refresh(mav)` before sending so the timestamp keeps up with the clock.
    """
    s = mav.signing
    s.secret_key = _check_key(key)
    s.link_id = link_id & 0xFF
    s.sign_outgoing = True
    advance_timestamp(mav, signing_timestamp(time.time_ns() if now_ns is None else now_ns))
    s.allow_unsigned_callback = lambda _mav, _msg_id: True
    mav.check_signature = lambda _buf, _sys, _comp: True  # decided by SigningGuard.admit


def stop_signing(mav) -> None:
    """`mav` packs unsigned frames from now on."""
    mav.signing.secret_key = None
    mav.signing.sign_outgoing = False


class SigningGuard:
    """Accepts the frames of a signed link: signature first (constant time), then freshness.

    Counts every rejection by reason (`rejected`) and calls `report(reason, text)` the first
    time each reason occurs, so a vehicle can say it once in STATUSTEXT.
    """

    def __init__(
        self,
        key: bytes,
        *,
        now_ns: Callable[[], int] = time.time_ns,
        report: Callable[[Rejection, str], None] | None = None,
    ) -> None:
        self._key = _check_key(key)
        self._now_ns = now_ns
        self._report = report
        self._streams: dict[tuple[int, int, int], int] = {}
        self.accepted = 0
        self.rejected: Counter[Rejection] = Counter()

    def has_key(self, key: bytes) -> bool:
        """True if this guard checks with `key` (compared in constant time)."""
        return hmac.compare_digest(self._key, bytes(key))

    def verdict(self, frame: bytes) -> Rejection | None:
        """None if `frame` (one whole MAVLink frame) is to be acted on, else why not. An
        accepted frame's timestamp is recorded: the same frame checked again is a replay."""
        if not frame or frame[0] == _MAGIC_V1:
            return Rejection.MAVLINK1
        if frame[0] != _MAGIC_V2 or len(frame) < 12 or not frame[2] & _FLAG_SIGNED:
            return Rejection.UNSIGNED
        if len(frame) < 12 + _SIGNATURE_BYTES:
            return Rejection.BAD_SIGNATURE
        signed, signature = frame[:-6], frame[-6:]
        expected = hashlib.sha256(self._key + signed).digest()[:6]
        if not hmac.compare_digest(expected, signature):
            return Rejection.BAD_SIGNATURE
        link_id = frame[-13]
        low, high = struct.unpack("<IH", frame[-12:-6])
        stamp = low | (high << 32)
        stream = (link_id, frame[5], frame[6])
        last = self._streams.get(stream)
        if last is not None and stamp <= last:
            return Rejection.REPLAY
        if last is None:
            if stamp + _NEW_STREAM_SLACK < signing_timestamp(self._now_ns()):
                return Rejection.STALE
            if len(self._streams) >= _MAX_STREAMS:
                return Rejection.TOO_MANY_STREAMS
        self._streams[stream] = stamp
        return None

    def admit(self, message) -> bool:
        """True if a decoded pymavlink message may be acted on; counts it either way."""
        reason = self.verdict(bytes(message.get_msgbuf()))
        if reason is None:
            self.accepted += 1
            return True
        self.rejected[reason] += 1
        if self.rejected[reason] == 1 and self._report is not None:
            src = f"{message.get_srcSystem()}/{message.get_srcComponent()}"
            self._report(reason, f"signing: {reason.value}, refused ({src})")
        return False

    def refresh(self, mav) -> None:
        """Bring `mav`'s outgoing timestamp up to the clock (never backwards)."""
        advance_timestamp(mav, signing_timestamp(self._now_ns()))

    def summary(self) -> str:
        """One line: accepted and rejected counts by reason."""
        parts = [f"{r.name.lower()} {n}" for r, n in sorted(self.rejected.items(), key=str)]
        return f"signing: accepted {self.accepted}, rejected " + (", ".join(parts) or "none")


class KeyRing:
    """The keys of several vehicles heard on one link (a ground station's), by system id.

    A frame from a system with a key must pass that key's guard; a system without a key is
    heard unsigned, as before signing.
    """

    def __init__(
        self, keys: Mapping[int, bytes], *, report: Callable[[Rejection, str], None] | None = None
    ) -> None:
        self._keys = dict(keys)
        self.guards = {sid: SigningGuard(k, report=report) for sid, k in self._keys.items()}

    def admit(self, message) -> bool:
        """True if the message may be acted on."""
        guard = self.guards.get(message.get_srcSystem())
        return guard is None or guard.admit(message)

    def pack(self, mav, message, system_id: int) -> bytes:
        """`message` packed by pymavlink's `mav` (a MAVLink object) for `system_id`: signed
        with that system's key if it has one, else unsigned."""
        key = self._keys.get(system_id)
        if key is None:
            return message.pack(mav)
        sign_outgoing(mav, key, link_id=mav.signing.link_id)
        try:
            return message.pack(mav)
        finally:  # (nothing else packed on `mav` is signed with this vehicle's key)
            stop_signing(mav)
