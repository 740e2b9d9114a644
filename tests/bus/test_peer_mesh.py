"""The default Zenoh mode of the fleet's processes: a full peer mesh, no router.

Two SITLs, their agents and the target are started without ``--zenoh-connect``, so each is its
member of the fleet's peer mesh on the scenario's ``network.zenoh_port`` (vehicles in scenario
order, then the target, then the ground station: `fleetmpc.protocol.zenoh_config.peer_mesh_index`).
The test is the ground station's member: it announces the epoch and listens. Plans, statuses and
target observations must cross between every pair of processes.
"""

import json
import socket
import time
from pathlib import Path

from helpers import ROOT, free_port_block, scenario_on_free_ports, wait_until
from test_planbus import make_plan

from fleetmpc.bus.open_bus import open_plan_bus
from fleetmpc.protocol.messages import GROUND_STATION_ID, TARGET_ID
from fleetmpc.protocol.zenoh_config import (
    MeshLogin,
    ZenohOptions,
    options_from_args,
    peer_mesh_index,
)
from fleetmpc.scenario import load_scenario
from fleetmpc.security.zenoh_security import make_zenoh_security

SPEED = "4"


def test_agents_and_target_exchange_plans_as_peers_of_the_mesh(processes, tmp_path) -> None:
    path = scenario_on_free_ports(ROOT / "tests/sitl/data/ideal.toml", tmp_path / "mesh.toml")
    scenario = load_scenario(path)
    common = ("--scenario", str(path), "--speed", SPEED)
    for v in scenario.vehicles:
        processes.fleetmpc(f"sitl-{v.id}", "sitl", *common, "--vehicle", str(v.id)).wait_for(
            "ready"
        )
    for v in scenario.vehicles:
        record = str(tmp_path / f"agent-{v.id}.jsonl")
        processes.fleetmpc(
            f"agent-{v.id}", "agent", *common, "--vehicle", str(v.id), "--wait-epoch",
            "--record", record,
        )  # fmt: skip
    target = processes.fleetmpc("target", "target", *common, "--wait-epoch")
    options = options_from_args(
        None,
        None,
        host=scenario.network.host,
        base_port=scenario.network.zenoh_port,
        size=len(scenario.vehicles) + 2,
        member_index=peer_mesh_index(scenario.vehicle_ids, GROUND_STATION_ID),
    )
    assert options.listen == (f"tcp/127.0.0.1:{scenario.network.zenoh_port + 3}",)
    fresh_ns = 400_000_000
    # As a ground station does, the epoch comes once every vehicle is engaged (taken off).
    agents = {v.id: processes[f"agent-{v.id}"] for v in scenario.vehicles}
    assert wait_until(
        lambda: all(f"vehicle {vid}: engaged" in a.err() for vid, a in agents.items()),
        timeout_s=60.0,
        interval_s=0.1,
    ), [a.tail() for a in agents.values()]
    with open_plan_bus(options, fleet=scenario.name, vehicle_id=GROUND_STATION_ID) as gcs:
        epoch_ns = time.time_ns() + 1_000_000_000

        def announce() -> None:
            gcs.publish_epoch(epoch_ns=epoch_ns, speed=float(SPEED))
            for child in processes.children.values():
                assert child.proc.poll() is None, child.tail()

        def last_row(vid: int) -> dict | None:
            """The agent's last complete record line, None before its first."""
            path = tmp_path / f"agent-{vid}.jsonl"
            text = path.read_text() if path.exists() else ""
            lines = text[: text.rfind("\n") + 1].splitlines()
            return json.loads(lines[-1]) if lines else None

        def exchanged() -> bool:
            """Fresh plans of both agents and target observations here, and each agent's last
            step flew on the other's fresh plan and on the target (peers that start before
            the members they connect to retry, so links come up over a few seconds)."""
            now = round((time.time_ns() - epoch_ns) * float(SPEED))
            plans = gcs.latest_plans(now, fresh_ns)
            target = gcs.latest_target(now, fresh_ns)
            rows = {vid: last_row(vid) for vid in (1, 2)}
            return (
                sorted(plans) == [1, 2]
                and target is not None
                and all(
                    row is not None and row["formation_terms"] == 1 and None not in row["slot_m"]
                    for row in rows.values()
                )
            )

        assert wait_until(exchanged, timeout_s=60.0, interval_s=0.1, tick=announce)
        # Two more seconds of flight, for the rows checked below.
        until_ns = time.time_ns() + round(2e9 / float(SPEED))
        assert wait_until(lambda: time.time_ns() >= until_ns, timeout_s=5.0, tick=announce)
        assert exchanged()
        assert TARGET_ID not in gcs.latest_statuses(0, 2**62)
    codes = processes.stop(*(f"agent-{v.id}" for v in scenario.vehicles), "target")
    assert codes == dict.fromkeys(codes, 0), codes
    assert f"epoch_ns {epoch_ns} speed {SPEED}" in target.out()
    # Each agent flew on the other's fresh plan (one formation term) and on the target.
    for vid, other in ((1, 2), (2, 1)):
        summary = json.loads(processes[f"agent-{vid}"].out().strip().splitlines()[-1])
        assert summary["epoch_ns"] == epoch_ns and summary["failure"] is None, summary
        assert summary["bus"]["rejected"] == {} and summary["step_errors"] == 0, summary
        rows = [json.loads(line) for line in (tmp_path / f"agent-{vid}.jsonl").open()]
        last = rows[-5:]
        assert all(r["formation_terms"] == 1 for r in last), last
        assert all(r["neighbour_ages_s"][str(other)] <= 0.4 for r in last), last
        assert all(None not in r["slot_m"] for r in last), last


def test_a_mesh_with_the_runs_secrets_lets_in_only_the_fleets_users(tmp_path) -> None:
    """Members log in with their own user (``--zenoh-secrets``): plans cross between them; a
    member with a wrong password is not let in, so it neither hears nor is heard."""
    base = free_port_block(range(4), kinds=(socket.SOCK_STREAM,))
    secrets = make_zenoh_security(
        tmp_path / "secrets", fleet="mesh", vehicle_ids=(1, 2), router_host="127.0.0.1",
        router_port=base, tls=False,
    )  # fmt: skip
    text = secrets.client_config("agent-2").read_text()
    wrong = json.loads(text[text.index("{") :])
    wrong["transport"]["auth"]["usrpwd"]["password"] = "guess"
    (tmp_path / "wrong.json5").write_text(json.dumps(wrong))
    (tmp_path / "wrong.json5").chmod(0o600)  # (a file holding a password must be private)

    def member(index: int, user_config: Path) -> ZenohOptions:
        login = MeshLogin(user_config=str(user_config), users_file=str(secrets.dictionary_file))
        return ZenohOptions.peer_mesh(index=index, size=4, base_port=base, login=login)

    rogue_options = member(3, tmp_path / "wrong.json5")
    assert "guess" not in repr(rogue_options), "options name files, never a password"
    with (
        open_plan_bus(
            member(0, secrets.client_config("agent-1")), fleet="mesh", vehicle_id=1
        ) as one,
        open_plan_bus(
            member(1, secrets.client_config("agent-2")), fleet="mesh", vehicle_id=2
        ) as two,
        open_plan_bus(rogue_options, fleet="mesh", vehicle_id=3) as rogue,
    ):

        def crossed() -> bool:
            two.publish_plan(make_plan(2, time.time_ns()))
            rogue.publish_plan(make_plan(3, time.time_ns()))
            return 2 in one.latest_plans(time.time_ns(), 10**9)

        assert wait_until(crossed, timeout_s=10.0, interval_s=0.1)
        time.sleep(0.5)
        assert 3 not in one.latest_plans(time.time_ns(), 10**9), "the rogue's plan was heard"
        assert rogue.latest_plans(time.time_ns(), 10**9) == {}, "the rogue heard the fleet"
