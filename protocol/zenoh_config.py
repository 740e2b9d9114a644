"""How fleetmpc processes join a Zenoh network: explicit endpoints, never scouting.

Every configuration built here turns multicast scouting and gossip off, also on top of a user's
config file: a session talks only to the endpoints it is given. The default is a peer that connects
to ``tcp/127.0.0.1:7447`` (a router, or the first peer, on the scenario's ``network.zenoh_port``).
Peers do not relay for each other without gossip, so either every process connects to one router
(`fleetmpc.protocol.zenoh_router`, `mode="client"`), or the peers form an explicit full mesh
(`ZenohOptions.peer_mesh`).

URL form, parsed by `ZenohOptions.from_url`::

    zenoh                                    peer connecting to tcp/127.0.0.1:7447
    zenoh://HOST:PORT[,HOST:PORT...]         connect to these TCP endpoints
        ?mode=peer|client                    session mode (default peer)
        &listen=HOST:PORT                    listen here (repeatable; peers only)
        &connect=PROTO/HOST:PORT             one more connect endpoint (repeatable)
        &config=PATH                         base config file (JSON5), see `config_file`
        &wait=S                              a client waits this long for its router at
                                             open (default CONNECT_WAIT_S)

Examples: ``zenoh://127.0.0.1:7447?mode=client`` (client of a router),
``zenoh://127.0.0.1:7447?listen=127.0.0.1:7448`` (a peer of a mesh).

Processes of a fleet take their options from the command line with `options_from_args`: a
config file (on a secured bus, the process's ``zenoh-<user>.json5`` of
`fleetmpc.security.zenoh_security`), or ``--zenoh-connect HOST:PORT[,...]`` (a client of a
router), or by default a member of the fleet's full peer mesh on the scenario's ``network.host``
and ``network.zenoh_port`` (`peer_mesh_index`: the vehicles in scenario order, then the target,
then the ground station).
"""

import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import parse_qsl, urlsplit

import zenoh

from fleetmpc.errors import ConfigError
from fleetmpc.protocol.messages import GROUND_STATION_ID, TARGET_ID
from fleetmpc.security.private_files import check_private

RECONNECT_RETRY = '{"period_init_ms": 250, "period_max_ms": 500, "period_increase_factor": 2}'
"""Zenoh's connect/retry: how often a member tries its router again once it is lost."""

CONNECT_WAIT_S = 30.0
"""How long a client waits at open for a router that is not up yet (a process started before
its router: a companion computer booted first, a router still loading its certificates) before
it gives up with an error naming the endpoint. Zenoh's own default gives up at once."""


def connect_timeout(wait_s: float) -> str:
    """Zenoh's ``connect/timeout_ms`` (JSON) for a client that waits `wait_s` for its router."""
    return json.dumps({"router": -1, "peer": -1, "client": round(wait_s * 1000)})


__all__ = [
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "MeshLogin",
    "ZenohOptions",
    "disable_scouting",
    "endpoint",
    "load_config_file",
    "options_from_args",
    "peer_mesh_index",
]

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 7447
_ENDPOINT_RE = re.compile(r"(tcp|udp|tls|quic)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+):([0-9]{1,5})")
_MODES = ("peer", "client")


def endpoint(host: str, port: int, *, proto: str = "tcp") -> str:
    """A Zenoh endpoint string, e.g. ``tcp/127.0.0.1:7447``; raises ConfigError if malformed."""
    text = f"{proto}/{host}:{port}"
    _check_endpoint("endpoint", text)
    return text


def _check_endpoint(field: str, text: object) -> str:
    match = _ENDPOINT_RE.fullmatch(text) if isinstance(text, str) else None
    if match is None or int(match.group(3)) > 65535:
        raise ConfigError(field, f"must look like tcp/127.0.0.1:7447, got {text!r}")
    return text


def _json_list(items: tuple[str, ...]) -> str:
    return "[" + ", ".join(f'"{x}"' for x in items) + "]"


def disable_scouting(conf: zenoh.Config) -> zenoh.Config:
    """Turn multicast scouting and gossip off in `conf` (in place) and return it."""
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    return conf


def load_config_file(path: str, *, field: str) -> zenoh.Config:
    """A Zenoh config file; ConfigError naming `field` if it is not one (without repeating
    Zenoh's message, which may quote a password from the file) or if it holds a password and
    others may read it."""
    try:
        conf = zenoh.Config.from_file(path)
    except zenoh.ZError:
        raise ConfigError(field, f"{path}: not a valid Zenoh config (JSON5)") from None
    if json.loads(conf.get_json("transport/auth/usrpwd/password")) is not None:
        check_private(Path(path), field=field)
    return conf


@dataclass(frozen=True)
class MeshLogin:
    """How a member of a peer mesh authenticates (`fleetmpc.security.zenoh_security`): with the
    user and password of its client config file, and it lets in only the users of a dictionary
    file. Only paths: the password is read when the session opens, never kept or printed."""

    user_config: str
    """A Zenoh config file whose ``transport/auth/usrpwd`` user and password this member uses."""
    users_file: str
    """The fleet's user dictionary (``user:password`` lines) the other members must be in."""

    def section(self) -> str:
        """The ``transport/auth/usrpwd`` section (JSON) of the member's config."""
        check_private(Path(self.users_file), field="--zenoh-secrets")
        own = load_config_file(self.user_config, field="--zenoh-secrets")
        usrpwd = json.loads(own.get_json("transport/auth/usrpwd"))
        if not usrpwd.get("user") or not usrpwd.get("password"):
            raise ConfigError("--zenoh-secrets", f"{self.user_config} has no user and password")
        return json.dumps({**usrpwd, "dictionary_file": self.users_file})


@dataclass(frozen=True)
class ZenohOptions:
    """How a session joins the network."""

    mode: str | None = None
    """"peer" or "client"; None means "peer", or the config file's mode if one is given."""
    connect: tuple[str, ...] = ()
    """Endpoints to connect to, e.g. ("tcp/127.0.0.1:7447",)."""
    listen: tuple[str, ...] = ()
    """Endpoints to listen on (peers only), e.g. ("tcp/127.0.0.1:7448",)."""
    config_file: str | None = None
    """A Zenoh JSON5 config file used as the base; mode and endpoints given here override it,
    and scouting is turned off regardless. Its other sections are kept, e.g. the user, password
    and TLS files of a secured bus (``zenoh-<user>.json5``, `fleetmpc.security.zenoh_security`)."""
    login: MeshLogin | None = None
    """Authentication of a peer-mesh member (user/password, and the users it lets in)."""
    connect_wait_s: float = CONNECT_WAIT_S
    """A client: how long it waits at open for its router (`CONNECT_WAIT_S`)."""

    def __post_init__(self) -> None:
        if self.mode is not None and self.mode not in _MODES:
            raise ConfigError("zenoh.mode", f"must be one of {_MODES}, got {self.mode!r}")
        for name in ("connect", "listen"):
            value = getattr(self, name)
            if isinstance(value, str):
                raise ConfigError(f"zenoh.{name}", "must be a list of endpoints, not a string")
            items = tuple(value)
            for i, text in enumerate(items):
                _check_endpoint(f"zenoh.{name}[{i}]", text)
            object.__setattr__(self, name, items)
        if self.mode == "client" and self.listen:
            raise ConfigError("zenoh.listen", "a client does not listen; use mode peer")
        if self.config_file is None and not (self.connect or self.listen):
            raise ConfigError("zenoh.connect", "give at least one connect or listen endpoint")
        if self.config_file is None and self.mode == "client" and not self.connect:
            raise ConfigError("zenoh.connect", "a client needs the endpoint of a router")
        if self.config_file is not None and not Path(self.config_file).is_file():
            raise ConfigError("zenoh.config_file", f"no such file: {self.config_file}")

    def to_config(self) -> zenoh.Config:
        """The zenoh.Config these options describe (scouting off)."""
        if self.config_file is not None:
            conf = load_config_file(self.config_file, field="zenoh.config_file")
            if self.mode is not None:
                conf.insert_json5("mode", f'"{self.mode}"')
            if self.connect:
                conf.insert_json5("connect/endpoints", _json_list(self.connect))
            if self.listen:
                conf.insert_json5("listen/endpoints", _json_list(self.listen))
            return disable_scouting(conf)
        conf = zenoh.Config()
        conf.insert_json5("mode", f'"{self.mode or "peer"}"')
        conf.insert_json5("connect/endpoints", _json_list(self.connect))
        # Explicitly empty: zenoh's peer default listens on tcp/[::]:0, every interface.
        conf.insert_json5("listen/endpoints", _json_list(self.listen))
        # Retry a lost router every half second at most (zenoh's default backs off to 4 s):
        # a restarted router is rejoined within a period or two.
        conf.insert_json5("connect/retry", RECONNECT_RETRY)
        conf.insert_json5("connect/timeout_ms", connect_timeout(self.connect_wait_s))
        if self.login is not None:
            conf.insert_json5("transport/auth/usrpwd", self.login.section())
        return disable_scouting(conf)

    @classmethod
    def from_url(cls, url: str) -> "ZenohOptions":
        """Parse the ``zenoh[://...]`` URL form described in the module docstring."""
        if url == "zenoh":
            return cls(connect=(endpoint(DEFAULT_HOST, DEFAULT_PORT),))
        parts = urlsplit(url)
        if parts.scheme != "zenoh" or parts.path not in ("", "/") or parts.fragment:
            raise ConfigError("zenoh_url", f"must look like zenoh://HOST:PORT?..., got {url!r}")
        connect = [
            _host_port("zenoh_url", item, proto_optional=False)
            for item in parts.netloc.split(",")
            if item
        ]
        listen: list[str] = []
        mode = config_file = None
        wait_s = CONNECT_WAIT_S
        for key, value in parse_qsl(parts.query, keep_blank_values=True):
            if key == "mode":
                mode = value
            elif key == "wait":
                try:
                    wait_s = float(value)
                except ValueError:
                    wait_s = math.nan
                if not 0.0 <= wait_s <= 3600.0:
                    raise ConfigError(
                        "zenoh_url.wait", f"must be seconds in [0, 3600], got {value!r}"
                    )
            elif key == "listen":
                listen.append(_host_port("zenoh_url.listen", value))
            elif key == "connect":
                connect.append(_host_port("zenoh_url.connect", value))
            elif key == "config":
                config_file = value
            else:
                raise ConfigError(
                    f"zenoh_url.{key}",
                    "unknown option (known: mode, listen, connect, config, wait)",
                )
        return cls(
            mode=mode,
            connect=tuple(connect),
            listen=tuple(listen),
            config_file=config_file,
            connect_wait_s=wait_s,
        )

    @classmethod
    def peer_mesh(
        cls,
        *,
        index: int,
        size: int,
        base_port: int,
        host: str = DEFAULT_HOST,
        login: MeshLogin | None = None,
    ) -> "ZenohOptions":
        """Member `index` of a full peer mesh of `size` members on consecutive ports.

        Member k listens on base_port + k and connects to every member j < k (the session
        retries until they are up), so every pair is linked without gossip.
        """
        if not isinstance(size, int) or size < 1:
            raise ConfigError("size", f"must be an integer >= 1, got {size!r}")
        if not isinstance(index, int) or not 0 <= index < size:
            raise ConfigError("index", f"must be an integer in [0, {size - 1}], got {index!r}")
        if not isinstance(base_port, int) or not 1 <= base_port <= 65535 - size:
            raise ConfigError("base_port", f"must leave room for {size} ports, got {base_port!r}")
        return cls(
            mode="peer",
            connect=tuple(endpoint(host, base_port + j) for j in range(index)),
            listen=(endpoint(host, base_port + index),),
            login=login,
        )


def _host_port(field: str, text: str, *, proto_optional: bool = True) -> str:
    if proto_optional and "/" in text:
        return _check_endpoint(field, text)
    return _check_endpoint(field, f"tcp/{text}")


def peer_mesh_index(vehicle_ids: Sequence[int], sender_id: int) -> int:
    """Member index of `sender_id` in the peer mesh of a fleet of `vehicle_ids`.

    Vehicles take 0..N-1 in the order given (the scenario's), the target (`TARGET_ID`) N and the
    ground station (`GROUND_STATION_ID`) N + 1.
    """
    n = len(vehicle_ids)
    if sender_id == TARGET_ID:
        return n
    if sender_id == GROUND_STATION_ID:
        return n + 1
    if sender_id not in vehicle_ids:
        raise ConfigError(
            "vehicle", f"no vehicle with id {sender_id} in the fleet (ids: {tuple(vehicle_ids)})"
        )
    return list(vehicle_ids).index(sender_id)


def options_from_args(
    config_file: str | Path | None,
    connect: str | None,
    *,
    host: str,
    base_port: int,
    size: int,
    member_index: int,
    login: MeshLogin | None = None,
) -> ZenohOptions:
    """The Zenoh options of a fleet process's command line.

    `config_file` (``--zenoh-config``) loads a Zenoh config file; else `connect`
    (``--zenoh-connect``, comma-separated ``HOST:PORT`` or ``PROTO/HOST:PORT``) makes a client of
    those routers; else the process is member `member_index` (see `peer_mesh_index`) of the
    fleet's full peer mesh of `size` members on `host`, ports `base_port` onwards (the scenario's
    network), logging in with `login` if given (``--zenoh-secrets``).
    """
    if login is not None and (config_file is not None or connect):
        raise ConfigError(
            "--zenoh-secrets",
            "is for the peer mesh; a client of a router takes --zenoh-config"
            " SECRETS/zenoh-<user>.json5",
        )
    if config_file is not None:
        return ZenohOptions(config_file=str(config_file))
    if connect:
        items = [e.strip() for e in connect.split(",") if e.strip()]
        return ZenohOptions(
            mode="client", connect=tuple(_host_port("--zenoh-connect", e) for e in items)
        )
    return ZenohOptions.peer_mesh(
        index=member_index, size=size, base_port=base_port, host=host, login=login
    )
