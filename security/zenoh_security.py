"""A secured Zenoh bus for a fleet: a password per process, a default-deny access list on the
router, and TLS to the router with a run-local certificate authority.

    security = make_zenoh_security(
        Path("runs/demo/secrets"), fleet="paper", vehicle_ids=(1, 2, 3),
        router_host="127.0.0.1", router_port=7447,
    )
    fleetmpc zenoh-router --security runs/demo/secrets        # listens on tls/127.0.0.1:7447
    fleetmpc agent ... --zenoh-config runs/demo/secrets/zenoh-agent-1.json5

Every process of the fleet is a user (`zenoh_user`): ``agent-<id>`` for vehicle <id>, ``target``
and ``gcs``; SITLs do not use the bus and have none. `make_zenoh_security` writes into one
directory (mode 0700, every file 0600, nothing overwritten):

- ``zenoh-users.txt``: the router's user dictionary (zenoh's
  ``transport/auth/usrpwd/dictionary_file``), one ``user:password`` line per user;
- ``zenoh-<user>.json5``: a client config per user (`ZenohSecurity.client_config`): mode client,
  the router's endpoint (``tls/HOST:PORT``, or ``tcp/`` without TLS), the user's password, the CA,
  and with mutual TLS the user's certificate and key. A process loads it with ``--zenoh-config``
  (`fleetmpc.protocol.zenoh_config.ZenohOptions`, which keeps these sections);
- ``zenoh-router.json5``: a whole router config (endpoint, users, access list, TLS), whose
  authentication, access list and TLS sections `router_security_config` puts into a router's;
- ``zenoh-ca.pem``, ``zenoh-router.pem``/``.key`` and with mutual TLS ``zenoh-<user>.pem``/``.key``:
  certificates of a CA made for this directory (its key is deleted once they are signed);
- ``zenoh-security.json``: what was made (fleet, vehicles, router address, TLS), for
  `ZenohSecurity.load`.

A client config is self-contained (the CA, and with mutual TLS the user's certificate and key, are
inline in base64), so it works wherever it is mounted (a compose secret); the router builds its
sections from the directory as it sees it at start (`router_security_config`), so the folder may
be mounted anywhere too. (``zenoh-router.json5`` names absolute paths: it is for running a
``zenohd`` on the same machine.)

The access list is `fleetmpc.security.zenoh_access.fleet_access_control`'s.

Passwords are random (192 bits) and stored in clear: zenoh 1.10's usrpwd authentication cannot
take hashed passwords. The router checks an HMAC of its challenge keyed with the password itself,
so it must hold the password (a hash in the dictionary would just be the password). The
dictionary and each user's config are the only files that hold a password; the challenge keeps
it off the wire even without TLS. No secret is ever put on a command line: keys and certificates
are made by the ``openssl`` command line, which writes the keys to files itself.
"""

import base64
import ipaddress
import json
import os
import re
import secrets
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import zenoh

from fleetmpc.errors import ConfigError
from fleetmpc.protocol.key_expressions import validate_fleet
from fleetmpc.protocol.zenoh_config import (
    CONNECT_WAIT_S,
    RECONNECT_RETRY,
    connect_timeout,
    endpoint,
)
from fleetmpc.security.private_files import check_private, write_private
from fleetmpc.security.zenoh_access import (
    GROUND_STATION_USER,
    TARGET_USER,
    check_vehicle_ids,
    fleet_access_control,
    zenoh_user,
)
from fleetmpc.security.zenoh_certificates import make_certificates

__all__ = [
    "MANIFEST_NAME",
    "ZenohSecurity",
    "make_zenoh_security",
    "router_security_config",
    "zenoh_user",
]

MANIFEST_NAME = "zenoh-security.json"
"""The file that says what a folder of the bus's secrets holds (`ZenohSecurity.load`)."""
_LABEL = r"[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
_DNS_RE = re.compile(rf"(?=.{{1,253}}$){_LABEL}(\.{_LABEL})*")


@dataclass(frozen=True)
class ZenohSecurity:
    """The files of a secured bus, all in `directory` (see the module docstring)."""

    directory: Path
    """Where the files are (mode 0700); absolute."""
    fleet: str
    """The fleet whose keys the access list covers."""
    vehicle_ids: tuple[int, ...]
    """The vehicles that have a user (``agent-<id>``)."""
    router_host: str
    """The router's address as clients connect to it (and its certificate names it)."""
    router_port: int
    """The router's port."""
    tls: bool
    """Clients connect over TLS and check the router's certificate against the run's CA."""
    mutual_tls: bool
    """Clients also show a certificate of the run's CA, whose common name is their user."""

    @property
    def users(self) -> tuple[str, ...]:
        """Every user: the agents in `vehicle_ids` order, then ``target`` and ``gcs``."""
        return (*map(zenoh_user, self.vehicle_ids), TARGET_USER, GROUND_STATION_USER)

    @property
    def router_endpoint(self) -> str:
        """The endpoint clients connect to, e.g. ``tls/127.0.0.1:7447``."""
        return endpoint(self.router_host, self.router_port, proto="tls" if self.tls else "tcp")

    @property
    def manifest_file(self) -> Path:
        """``zenoh-security.json``: what `make_zenoh_security` made (no secret)."""
        return self.directory / MANIFEST_NAME

    @property
    def dictionary_file(self) -> Path:
        """``zenoh-users.txt``: the router's ``user:password`` lines."""
        return self.directory / "zenoh-users.txt"

    @property
    def router_file(self) -> Path:
        """``zenoh-router.json5``: the router's config (auth, access list, TLS, endpoint)."""
        return self.directory / "zenoh-router.json5"

    @property
    def ca_certificate(self) -> Path | None:
        """The run's CA certificate (None without TLS)."""
        return self.directory / "zenoh-ca.pem" if self.tls else None

    @property
    def router_certificate(self) -> Path | None:
        """The router's certificate, for `router_host` and ``localhost`` (None without TLS)."""
        return self.directory / "zenoh-router.pem" if self.tls else None

    @property
    def router_private_key(self) -> Path | None:
        """The router's private key (None without TLS)."""
        return self.directory / "zenoh-router.key" if self.tls else None

    @staticmethod
    def client_config_name(user: str) -> str:
        """The file name of `user`'s client config (in the directory)."""
        return f"zenoh-{user}.json5"

    def router_files(self) -> tuple[Path, ...]:
        """The files the router reads: the manifest, the user dictionary and, with TLS, its
        certificate and key and the CA (which checks client certificates under mutual TLS)."""
        tls = (self.router_certificate, self.router_private_key, self.ca_certificate)
        return (self.manifest_file, self.dictionary_file, *(p for p in tls if p is not None))

    def client_config(self, user: str) -> Path:
        """``zenoh-<user>.json5``: the Zenoh client config of `user` (see `zenoh_user`)."""
        return self.directory / self.client_config_name(self._user(user))

    def client_certificate(self, user: str) -> Path | None:
        """The certificate of `user` (None without mutual TLS)."""
        return self.directory / f"zenoh-{self._user(user)}.pem" if self.mutual_tls else None

    def client_private_key(self, user: str) -> Path | None:
        """The private key of `user`'s certificate (None without mutual TLS)."""
        return self.directory / f"zenoh-{self._user(user)}.key" if self.mutual_tls else None

    def files(self) -> tuple[Path, ...]:
        """Every file of the bus's security in `directory`."""
        paths = [self.manifest_file, self.dictionary_file, self.router_file]
        paths += [self.ca_certificate, self.router_certificate, self.router_private_key]
        for user in self.users:
            paths += [self.client_config(user)]
            paths += [self.client_certificate(user), self.client_private_key(user)]
        return tuple(p for p in paths if p is not None)

    def _user(self, user: str) -> str:
        if user not in self.users:
            raise ConfigError("user", f"no bus user {user!r} (users: {', '.join(self.users)})")
        return user

    @classmethod
    def load(cls, directory: str | Path, *, field: str = "security") -> "ZenohSecurity":
        """The security `make_zenoh_security` wrote into `directory`; ConfigError naming
        `field` if it is missing or malformed."""
        directory = Path(directory).absolute()
        path = directory / MANIFEST_NAME
        try:
            manifest = json.loads(path.read_text(encoding="utf-8"))
            security = cls(
                directory=directory,
                fleet=validate_fleet(manifest["fleet"]),
                vehicle_ids=check_vehicle_ids(manifest["vehicle_ids"]),
                router_host=str(manifest["router_host"]),
                router_port=_port("router_port", manifest["router_port"]),
                tls=bool(manifest["tls"]),
                mutual_tls=bool(manifest["mutual_tls"]),
            )
        except OSError as e:
            raise ConfigError(field, f"cannot read {path}: {e.strerror}") from None
        except (ValueError, KeyError, TypeError) as e:
            raise ConfigError(field, f"{path} is not a zenoh security manifest: {e}") from None
        return security


def make_zenoh_security(
    directory: Path,
    *,
    fleet: str,
    vehicle_ids: Sequence[int],
    router_host: str,
    router_port: int,
    tls: bool = True,
    mutual_tls: bool = False,
) -> ZenohSecurity:
    """Write a secured bus's passwords, configs and certificates into `directory` and name them.

    `directory` is created with mode 0700 (an existing one is set to 0700; it may hold other
    files, e.g. `fleetmpc keys`' MAVLink keys, but none of these: nothing is overwritten). Every
    file is written with mode 0600. `router_host` is the address clients connect to; the router's
    certificate names it and ``localhost``. `mutual_tls` needs `tls`.
    """
    fleet = validate_fleet(fleet)
    ids = check_vehicle_ids(vehicle_ids)
    port = _port("router_port", router_port)
    host, san = _router_host(router_host)
    if mutual_tls and not tls:
        raise ConfigError("mutual_tls", "needs tls")
    directory = Path(directory).absolute()
    security = ZenohSecurity(directory, fleet, ids, host, port, bool(tls), bool(mutual_tls))
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(directory, 0o700)
    for path in security.files():
        if path.exists() or path.is_symlink():
            raise ConfigError("directory", f"{path} exists; not overwriting the bus's secrets")

    passwords = {user: secrets.token_urlsafe(24) for user in security.users}
    if tls:
        make_certificates(security, san)
    users = "".join(f"{u}:{p}\n" for u, p in passwords.items())
    write_private(security.dictionary_file, users, field="directory")
    for user, password in passwords.items():
        write_private(
            security.client_config(user),
            f"// Zenoh client of fleet {fleet!r} as user {user!r}. Secret: holds its password.\n"
            + json.dumps(_client_config(security, user, password), indent=2)
            + "\n",
            field="directory",
        )
    write_private(
        security.router_file,
        f"// Zenoh router of fleet {fleet!r}: users, access list, TLS. No password inside.\n"
        + json.dumps(_router_config(security), indent=2)
        + "\n",
        field="directory",
    )
    manifest = {
        "fleet": fleet,
        "vehicle_ids": list(ids),
        "router_host": host,
        "router_port": port,
        "tls": security.tls,
        "mutual_tls": security.mutual_tls,
    }
    write_private(security.manifest_file, json.dumps(manifest, indent=2) + "\n", field="directory")
    return security


def router_security_config(conf: zenoh.Config, security_dir: str | Path) -> zenoh.Config:
    """Secure a router's config `conf` (in place) with `security_dir`'s bus and return it.

    Sessions must then log in as one of the bus's users, the fleet's access list applies, and
    with TLS the router's ``tcp/`` listen endpoints become ``tls/`` ones on the same address,
    with the router's certificate (and with mutual TLS, client certificates of the run's CA
    required). The dictionary and the router's key must not be readable by group or others.
    """
    security = ZenohSecurity.load(security_dir)
    for path in (security.dictionary_file, security.router_private_key):
        if path is not None:
            check_private(path, field="security")
    pieces = _router_config(security)  # (paths in `security_dir` as this process sees it)
    conf.insert_json5("transport/auth/usrpwd", json.dumps(pieces["transport"]["auth"]["usrpwd"]))
    conf.insert_json5("access_control", json.dumps(pieces["access_control"]))
    if security.tls:
        conf.insert_json5("transport/link/tls", json.dumps(pieces["transport"]["link"]["tls"]))
        listen = json.loads(conf.get_json("listen/endpoints"))
        if not isinstance(listen, list):
            raise ConfigError("listen/endpoints", f"must be a list of endpoints, got {listen!r}")
        conf.insert_json5("listen/endpoints", json.dumps([_tls(e) for e in listen]))
    return conf


def _tls(text: str) -> str:
    """A listen endpoint on TLS: ``tcp/A:P`` becomes ``tls/A:P``; ``tls/`` ones stay."""
    proto, _, address = str(text).partition("/")
    if proto not in ("tcp", "tls") or not address:
        raise ConfigError("listen/endpoints", f"a TLS router listens on tcp/ or tls/, not {text!r}")
    return f"tls/{address}"


def _client_config(security: ZenohSecurity, user: str, password: str) -> dict:
    conf: dict = {
        "mode": "client",
        "connect": {
            "endpoints": [security.router_endpoint],
            "retry": json.loads(RECONNECT_RETRY),
            "timeout_ms": json.loads(connect_timeout(CONNECT_WAIT_S)),
        },
        "listen": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"user": user, "password": password}}},
    }
    if security.tls:
        tls: dict = {"root_ca_certificate_base64": _base64(security.ca_certificate)}
        if security.mutual_tls:
            tls["enable_mtls"] = True
            tls["connect_certificate_base64"] = _base64(security.client_certificate(user))
            tls["connect_private_key_base64"] = _base64(security.client_private_key(user))
        conf["transport"]["link"] = {"tls": tls}
    return conf


def _base64(path: Path) -> str:
    """A PEM file's bytes in base64, as Zenoh's ``*_base64`` TLS settings take them."""
    return base64.b64encode(path.read_bytes()).decode("ascii")


def _router_config(security: ZenohSecurity) -> dict:
    transport: dict = {"auth": {"usrpwd": {"dictionary_file": str(security.dictionary_file)}}}
    if security.tls:
        tls: dict = {
            "listen_certificate": str(security.router_certificate),
            "listen_private_key": str(security.router_private_key),
        }
        if security.mutual_tls:
            tls["root_ca_certificate"] = str(security.ca_certificate)
            tls["enable_mtls"] = True
        transport["link"] = {"tls": tls}
    return {
        "mode": "router",
        "listen": {"endpoints": [security.router_endpoint]},
        "connect": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": transport,
        "access_control": fleet_access_control(
            security.fleet, security.vehicle_ids, mutual_tls=security.mutual_tls
        ),
    }


def _port(field: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 65535:
        raise ConfigError(field, f"must be a port number, got {value!r}")
    return value


def _router_host(host: object) -> tuple[str, str]:
    """(the host as an endpoint writes it, the certificate's subjectAltName entry for it)."""
    text = host if isinstance(host, str) else ""
    bare = text[1:-1] if text.startswith("[") and text.endswith("]") else text
    try:
        ip = ipaddress.ip_address(bare)
    except ValueError:
        if not _DNS_RE.fullmatch(text):
            raise ConfigError(
                "router_host", f"must be an IP address or a DNS name, got {host!r}"
            ) from None
        return text, f"DNS:{text}"
    if ip.is_unspecified:
        raise ConfigError(
            "router_host", f"must be the address clients connect to, not the wildcard {host!r}"
        )
    return (f"[{ip}]" if ip.version == 6 else str(ip)), f"IP:{ip}"
