"""`fleetmpc up` secures the fleet by default: a rogue on the Zenoh bus is refused or heard by
nobody, and no secret shows in the process table, the logs or the recording."""

import json
import re
import subprocess
import time
from pathlib import Path

import numpy as np
import zenoh
from helpers import scenario_on_free_ports
from test_up import PAPER, launch  # noqa: F401 (the fixture)

from fleetmpc.protocol.codec import decode, encode
from fleetmpc.protocol.key_expressions import epoch_key, plan_key
from fleetmpc.protocol.messages import FleetEpoch, PlanMessage
from fleetmpc.protocol.plan import Plan
from fleetmpc.protocol.zenoh_config import connect_timeout

ROGUE_NORTH_M = 999.0
"""The rogue's plans place vehicle 3 here: far from anywhere the fleet flies."""


def _config(path: Path, **changes: str) -> zenoh.Config:
    """A client config file of the run, with some of its settings changed (JSON5 values); a
    refused session gives up after 2 s instead of waiting for its router."""
    conf = zenoh.Config.from_file(str(path))
    conf.insert_json5("connect/timeout_ms", connect_timeout(2.0))
    for key, value in changes.items():
        conf.insert_json5(key, value)
    return conf


def _rogue_plan(seq: int) -> bytes:
    states = np.column_stack([np.full(6, ROGUE_NORTH_M), np.zeros(6), np.zeros(6)])
    plan = Plan(
        vehicle_id=3,
        stamp_ns=time.time_ns(),
        period_ns=200_000_000,
        states=states,
        inputs=np.zeros((5, 2)),
    )
    return encode(PlanMessage(seq=seq, plan=plan))


def _secrets(secrets: Path) -> list[str]:
    """Every secret of the run: passwords, signing passphrases, private key bodies."""
    found = []
    for line in (secrets / "zenoh-users.txt").read_text().splitlines():
        found.append(line.split(":", 1)[1])
    found += [p.read_text().strip() for p in secrets.glob("mavlink-*.key")]
    for key in secrets.glob("zenoh-*.key"):
        body = "".join(key.read_text().splitlines()[1:-1])
        found.append(body[:40])
    return found


def test_a_secured_fleet_hears_no_rogue_and_shows_no_secret(launch, tmp_path):  # noqa: F811
    scenario = scenario_on_free_ports(PAPER, tmp_path / "paper-secure.toml")
    run_dir = tmp_path / "run"
    up = launch(scenario, run_dir, "--duration", "20")
    up.wait_flying(fleet_s=2.0, timeout_s=90.0)
    secrets_dir = run_dir / "secrets"
    fleet = json.loads((secrets_dir / "zenoh-security.json").read_text())["fleet"]
    table = subprocess.run(["ps", "-eo", "args"], capture_output=True, text=True).stdout

    # A listener with the ground station's rights hears whatever the router lets through.
    heard: list = []
    listener = zenoh.open(_config(secrets_dir / "zenoh-gcs.json5"))
    refused = {}
    try:
        listener.declare_subscriber(
            f"fleetmpc/{fleet}/**", lambda s: heard.append(s.payload.to_bytes())
        )
        agent2 = secrets_dir / "zenoh-agent-2.json5"
        for name, conf in {
            "no credentials": _config(
                agent2,
                **{"transport/auth/usrpwd/user": "null", "transport/auth/usrpwd/password": "null"},
            ),
            "wrong password": _config(agent2, **{"transport/auth/usrpwd/password": '"guess"'}),
        }.items():
            try:
                zenoh.open(conf).close()
                refused[name] = False
            except zenoh.ZError:
                refused[name] = True
        # Agent 2's own valid credentials, speaking for vehicle 3 and for the ground station.
        rogue = zenoh.open(_config(agent2))
        try:
            for seq in range(20):
                rogue.put(plan_key(fleet, 3), _rogue_plan(10_000 + seq))
                epoch = FleetEpoch(sender_id=249, seq=seq, epoch_ns=1, speed=1.0)
                rogue.put(epoch_key(fleet), encode(epoch))
                time.sleep(0.05)
        finally:
            rogue.close()
        time.sleep(0.5)
    finally:
        listener.close()
    rc = up.wait(timeout_s=180.0)
    assert rc == 0, up.text()
    assert refused == {"no credentials": True, "wrong password": True}
    messages = [decode(payload) for payload in heard]
    plans = [m for m in messages if isinstance(m, PlanMessage)]
    assert plans, "the listener hears the fleet's real plans"
    assert not [p for p in plans if p.plan.states[0, 0] == ROGUE_NORTH_M], "a rogue plan passed"
    assert not [m for m in messages if isinstance(m, FleetEpoch) and m.epoch_ns == 1]

    # Every agent flew on the ground station's epoch, not the rogue's.
    gcs_log = (run_dir / "logs" / "gcs.log").read_text()
    epoch_ns = int(re.search(r"all engaged; epoch (\d+)", gcs_log)[1])
    for vid in (1, 2, 3):
        summary = (run_dir / "logs" / f"agent-{vid}.log").read_text().splitlines()
        final = json.loads(next(line for line in reversed(summary) if line.startswith("{")))
        assert final["epoch_ns"] == epoch_ns and final["engaged"], final

    # No secret in the process table, the logs, the outputs or the recording.
    logs = [p.read_bytes() for p in (run_dir / "logs").glob("*.log")]
    outputs = [p.read_bytes() for p in run_dir.glob("*") if p.is_file()]
    for secret in _secrets(secrets_dir):
        assert secret not in table
        assert not any(secret.encode() in blob for blob in (*logs, *outputs)), secret[:6]
