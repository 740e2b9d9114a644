"""The secured Zenoh bus: users, the fleet's access list and TLS on a real router on 127.0.0.1.

A message "reaches" a session when that session's subscriber hears it; rogue publications are
followed by an allowed one from the same session (the router forwards a session's samples in
order), so once the allowed one is heard, nothing before it can still arrive.
"""

import base64
import json
import signal
import socket
import stat
import threading
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import zenoh
from helpers import free_port, router_process, wait_until
from test_zenoh_router import PERIOD_NS, make_plan

from fleetmpc.bus.open_bus import open_plan_bus
from fleetmpc.errors import ConfigError
from fleetmpc.protocol.key_expressions import (
    epoch_key,
    plan_key,
    status_key,
    target_observation_key,
)
from fleetmpc.protocol.messages import GROUND_STATION_ID, TARGET_ID
from fleetmpc.protocol.zenoh_config import ZenohOptions, connect_timeout
from fleetmpc.protocol.zenoh_router import open_router, router_config
from fleetmpc.security.zenoh_access import fleet_access_control, zenoh_user
from fleetmpc.security.zenoh_security import ZenohSecurity, make_zenoh_security

REFUSED_WAIT_S = 2.0
"""How long a session the router refuses keeps trying in these tests [s]."""
FLEET = "secured"
TEST_TIMEOUT_S = 20


@pytest.fixture(autouse=True)
def _deadline() -> Iterator[None]:
    """Fail a test that runs longer than TEST_TIMEOUT_S (SIGALRM in the main thread)."""

    def expire(*_: object) -> None:
        raise TimeoutError(f"test took more than {TEST_TIMEOUT_S} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(TEST_TIMEOUT_S)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


@pytest.fixture(scope="module")
def security(tmp_path_factory: pytest.TempPathFactory) -> ZenohSecurity:
    return make_zenoh_security(
        tmp_path_factory.mktemp("zenoh") / "secrets",
        fleet=FLEET,
        vehicle_ids=(1, 2, 3),
        router_host="127.0.0.1",
        router_port=free_port(socket.SOCK_STREAM),
    )


@pytest.fixture(scope="module")
def router(security: ZenohSecurity) -> Iterator[zenoh.Session]:
    with open_router(port=security.router_port, security=security.directory) as session:
        yield session


def user_config(security: ZenohSecurity, user: str) -> zenoh.Config:
    """A user's session config as a fleet process loads it (``--zenoh-config``), except that
    a refused session gives up after REFUSED_WAIT_S instead of waiting for its router."""
    conf = ZenohOptions(config_file=str(security.client_config(user))).to_config()
    conf.insert_json5("connect/timeout_ms", connect_timeout(REFUSED_WAIT_S))
    return conf


@dataclass
class Heard:
    """Keys heard by a session's subscribers (from other sessions only)."""

    keys: list[str] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.keys.append(str(sample.key_expr))

    def has(self, key: str) -> bool:
        with self.lock:
            return key in self.keys

    def distinct(self) -> set[str]:
        with self.lock:
            return set(self.keys)


def listen(stack: ExitStack, session: zenoh.Session, *keys: str) -> Heard:
    heard = Heard()
    for key in keys:
        sub = session.declare_subscriber(key, heard, allowed_origin=zenoh.Locality.REMOTE)
        stack.callback(sub.undeclare)
    return heard


def opened(stack: ExitStack, conf: zenoh.Config) -> zenoh.Session:
    session = zenoh.open(conf)
    stack.callback(session.close)
    return session


def agent_reads(stack: ExitStack, session: zenoh.Session) -> Heard:
    """An agent's subscriptions (those of `fleetmpc.bus.planbus`)."""
    f = FLEET
    return listen(
        stack,
        session,
        f"fleetmpc/{f}/uav/*/plan",
        f"fleetmpc/{f}/uav/*/status",
        target_observation_key(f),
        epoch_key(f),
    )


def test_files_are_private_and_each_password_is_in_two_files(security: ZenohSecurity) -> None:
    assert stat.S_IMODE(security.directory.stat().st_mode) == 0o700
    present = sorted(security.directory.iterdir())
    assert present == sorted(security.files())  # the CA's key and scratch files are gone
    assert all(stat.S_IMODE(p.stat().st_mode) == 0o600 for p in present)
    assert security.users == ("agent-1", "agent-2", "agent-3", "target", "gcs")
    texts = {p: p.read_text() for p in present}
    for user in security.users:
        conf = zenoh.Config.from_file(str(security.client_config(user)))
        password = json.loads(conf.get_json("transport/auth/usrpwd/password"))
        assert len(password) >= 32
        holders = {p for p, text in texts.items() if password in text}
        assert holders == {security.dictionary_file, security.client_config(user)}
        assert f"{user}:{password}\n" in texts[security.dictionary_file]
        assert json.loads(conf.get_json("connect/endpoints")) == [security.router_endpoint]
        ca = json.loads(conf.get_json("transport/link/tls/root_ca_certificate_base64"))
        assert base64.b64decode(ca) == security.ca_certificate.read_bytes(), "inline: movable"
    assert security.router_endpoint == f"tls/127.0.0.1:{security.router_port}"
    assert ZenohSecurity.load(security.directory) == security
    assert [zenoh_user(v) for v in (1, TARGET_ID, GROUND_STATION_ID)] == [
        "agent-1",
        "target",
        "gcs",
    ]


def test_router_config_adds_users_access_list_and_tls(security: ZenohSecurity) -> None:
    conf = router_config(port=security.router_port, security=security.directory)
    assert json.loads(conf.get_json("listen/endpoints")) == [security.router_endpoint]
    acl = json.loads(conf.get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert json.loads(conf.get_json("transport/auth/usrpwd/dictionary_file")) == str(
        security.dictionary_file
    )
    assert json.loads(conf.get_json("transport/link/tls/listen_certificate")) == str(
        security.router_certificate
    )
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False


def test_the_fleet_talks_through_the_secured_router(
    security: ZenohSecurity, router: zenoh.Session
) -> None:
    """The fleet's own buses (publishers on all their keys, subscribers as in a fleet)."""
    options = {u: ZenohOptions(config_file=str(security.client_config(u))) for u in security.users}
    with (
        open_plan_bus(options["agent-1"], fleet=FLEET, vehicle_id=1) as a1,
        open_plan_bus(options["agent-2"], fleet=FLEET, vehicle_id=2) as a2,
        open_plan_bus(options["target"], fleet=FLEET, vehicle_id=TARGET_ID) as target,
        open_plan_bus(options["gcs"], fleet=FLEET, vehicle_id=GROUND_STATION_ID) as gcs,
    ):
        step = [0]

        def publish() -> None:
            step[0] += 1
            now = step[0] * PERIOD_NS
            a1.publish_plan(make_plan(1, now))
            target.publish_target(stamp_ns=now, north_m=1.0, east_m=2.0)
            gcs.publish_epoch(epoch_ns=123, speed=1.0)

        def delivered() -> bool:
            now = step[0] * PERIOD_NS
            return (
                1 in a2.latest_plans(now, 10**9)
                and 1 in gcs.latest_plans(now, 10**9)
                and all(b.latest_target(now, 10**9) is not None for b in (a1, a2, gcs))
                and all(b.latest_epoch() is not None for b in (a1, a2, target))
            )

        assert wait_until(delivered, tick=publish, timeout_s=8.0)
        assert a2.latest_epoch().epoch_ns == 123
        assert all(b.counters().rejected_total == 0 for b in (a1, a2, target, gcs))


def test_a_user_publishes_only_its_own_keys(security: ZenohSecurity, router: zenoh.Session) -> None:
    with ExitStack() as stack:
        a1 = opened(stack, user_config(security, "agent-1"))
        a2 = opened(stack, user_config(security, "agent-2"))
        target = opened(stack, user_config(security, "target"))
        gcs = opened(stack, user_config(security, "gcs"))
        a1_heard = agent_reads(stack, a1)
        gcs_heard = listen(stack, gcs, f"fleetmpc/{FLEET}/**")
        own = (plan_key(FLEET, 2), status_key(FLEET, 2), target_observation_key(FLEET))

        def publish() -> None:
            # Forbidden first, then the allowed keys that tell the forbidden ones had their turn.
            a2.put(plan_key(FLEET, 3), b"forged plan of vehicle 3")
            a2.put(epoch_key(FLEET), b"forged epoch")
            a2.put(target_observation_key(FLEET), b"forged observation")
            target.put(epoch_key(FLEET), b"forged epoch")
            target.put(status_key(FLEET, 1), b"forged status")
            a2.put(f"fleetmpc/{FLEET}/uav/2/plan", b"allowed")
            a2.put(f"fleetmpc/{FLEET}/uav/2/status", b"allowed")
            target.put(target_observation_key(FLEET), b"allowed")

        def settled() -> bool:
            return all(h.has(k) for h in (a1_heard, gcs_heard) for k in own)

        assert wait_until(settled, tick=publish, timeout_s=8.0)
        assert a1_heard.distinct() == set(own)
        assert gcs_heard.distinct() == set(own)


def test_rogue_sessions_cannot_join(security: ZenohSecurity, router: zenoh.Session) -> None:
    def rogue(change: dict[str, str]) -> zenoh.Config:
        conf = user_config(security, "agent-1")
        for key, value in change.items():
            conf.insert_json5(key, value)
        return conf

    rogues = {
        "no credentials": rogue({"transport/auth/usrpwd": '{"user": null, "password": null}'}),
        "wrong password": rogue({"transport/auth/usrpwd/password": '"guessed"'}),
        "unknown user": rogue({"transport/auth/usrpwd/user": '"agent-9"'}),
        "no CA": rogue({"transport/link/tls/root_ca_certificate_base64": "null"}),
        "plain tcp": rogue({"connect/endpoints": f'["tcp/127.0.0.1:{security.router_port}"]'}),
    }
    with ExitStack() as stack:
        gcs = opened(stack, user_config(security, "gcs"))
        heard = listen(stack, gcs, "**")
        let_in = []
        for name, conf in rogues.items():
            try:
                session = zenoh.open(conf)
            except zenoh.ZError:
                continue  # refused while opening: zenoh.open raised
            let_in.append(name)
            with session:
                session.put(plan_key(FLEET, 1), b"rogue")
        assert let_in == []
        assert heard.distinct() == set()


def test_mutual_tls_needs_the_users_own_certificate(tmp_path: Path) -> None:
    security = make_zenoh_security(
        tmp_path / "secrets",
        fleet=FLEET,
        vehicle_ids=(1, 2),
        router_host="127.0.0.1",
        router_port=free_port(socket.SOCK_STREAM),
        mutual_tls=True,
    )
    assert stat.S_IMODE(security.client_private_key("agent-1").stat().st_mode) == 0o600
    no_cert = user_config(security, "agent-1")
    no_cert.insert_json5("transport/link/tls/connect_certificate_base64", "null")
    no_cert.insert_json5("transport/link/tls/connect_private_key_base64", "null")
    # agent-1's password with agent-2's certificate: connects, but is nobody to the access list.
    borrowed = user_config(security, "agent-1")
    for part, path in (
        ("certificate", security.client_certificate("agent-2")),
        ("private_key", security.client_private_key("agent-2")),
    ):
        inline = base64.b64encode(path.read_bytes()).decode()
        borrowed.insert_json5(f"transport/link/tls/connect_{part}_base64", json.dumps(inline))
    with ExitStack() as stack:
        stack.enter_context(open_router(port=security.router_port, security=security.directory))
        gcs = opened(stack, user_config(security, "gcs"))
        heard = listen(stack, gcs, f"fleetmpc/{FLEET}/**")
        with pytest.raises(zenoh.ZError):
            zenoh.open(no_cert).close()
        impostor = opened(stack, borrowed)
        a1 = opened(stack, user_config(security, "agent-1"))

        def publish() -> None:
            impostor.put(plan_key(FLEET, 1), b"impostor")
            a1.put(status_key(FLEET, 1), b"allowed")

        assert wait_until(lambda: heard.has(status_key(FLEET, 1)), tick=publish, timeout_s=8.0)
        assert heard.distinct() == {status_key(FLEET, 1)}


def test_router_command_line_serves_the_secured_bus(security: ZenohSecurity) -> None:
    port = free_port(socket.SOCK_STREAM)
    with router_process("--security", str(security.directory), "--port", str(port)) as proc:
        assert proc.stdout.readline().strip() == f"zenoh router listening on tls/127.0.0.1:{port}"
        options = ZenohOptions(
            config_file=str(security.client_config("agent-3")), connect=(f"tls/127.0.0.1:{port}",)
        )
        zenoh.open(options.to_config()).close()  # auth and TLS kept from the file
        plain = ZenohOptions(
            mode="client", connect=(f"tcp/127.0.0.1:{port}",), connect_wait_s=REFUSED_WAIT_S
        )
        with pytest.raises(zenoh.ZError):
            zenoh.open(plain.to_config()).close()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0


def test_access_list_without_tls_and_bad_arguments(tmp_path: Path) -> None:
    made = {"fleet": FLEET, "vehicle_ids": [4], "router_host": "localhost", "router_port": 7447}
    plain = make_zenoh_security(tmp_path / "plain", **made, tls=False)
    assert plain.router_endpoint == "tcp/localhost:7447" and plain.ca_certificate is None
    assert (
        json.loads(
            zenoh.Config.from_file(str(plain.client_config("agent-4"))).get_json(
                "transport/link/tls"
            )
        ).get("root_ca_certificate_base64")
        is None
    )
    acl = fleet_access_control(FLEET, [4])
    publish = {r["id"]: r["key_exprs"] for r in acl["rules"] if r["id"].startswith("publish-")}
    assert publish == {
        "publish-agent-4": [f"fleetmpc/{FLEET}/uav/4/**"],
        "publish-target": [target_observation_key(FLEET)],
        "publish-gcs": [epoch_key(FLEET)],
    }
    with pytest.raises(ConfigError) as info:
        make_zenoh_security(tmp_path / "plain", **made, tls=False)
    assert info.value.field == "directory"  # nothing is overwritten
    good = {"fleet": FLEET, "vehicle_ids": [1], "router_host": "127.0.0.1", "router_port": 7447}
    for change, name in [
        ({"vehicle_ids": [1, GROUND_STATION_ID]}, "vehicle_ids[1]"),
        ({"vehicle_ids": [2, 2]}, "vehicle_ids[1]"),
        ({"vehicle_ids": []}, "vehicle_ids"),
        ({"router_port": 0}, "router_port"),
        ({"router_host": "0.0.0.0"}, "router_host"),
        ({"router_host": "a b"}, "router_host"),
        ({"fleet": "a/b"}, "fleet"),
        ({"tls": False, "mutual_tls": True}, "mutual_tls"),
    ]:
        with pytest.raises(ConfigError) as info:
            make_zenoh_security(tmp_path / "bad", **{**good, **change})
        assert info.value.field == name
    with pytest.raises(ConfigError) as info:
        plain.client_config("agent-5")
    assert info.value.field == "user"
    with pytest.raises(ConfigError) as info:
        router_config(port=7447, security=tmp_path / "nowhere")
    assert info.value.field == "security"
    plain.dictionary_file.chmod(0o644)
    with pytest.raises(ConfigError) as info:
        router_config(port=7447, security=plain.directory)
    assert info.value.field == "security"
