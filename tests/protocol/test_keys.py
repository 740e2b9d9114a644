"""Zenoh key expressions: formats, parser, fleet-name validation, zenoh's own matching."""

import pytest
import zenoh
from hypothesis import given
from hypothesis import strategies as st

from fleetmpc.errors import ConfigError
from fleetmpc.protocol.key_expressions import (
    KeyFormatError,
    ParsedKey,
    all_plans_key,
    all_statuses_key,
    epoch_key,
    fleet_key,
    parse_key,
    plan_key,
    status_key,
    target_observation_key,
    validate_fleet,
)
from fleetmpc.protocol.messages import MessageKind

fleets = st.text(
    alphabet="abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-",
    min_size=1,
    max_size=64,
)
ids = st.integers(1, 250)


def test_key_formats() -> None:
    assert plan_key("paper", 3) == "fleetmpc/paper/uav/3/plan"
    assert status_key("paper", 250) == "fleetmpc/paper/uav/250/status"
    assert target_observation_key("paper") == "fleetmpc/paper/target/observation"
    assert all_plans_key("paper") == "fleetmpc/paper/uav/*/plan"
    assert all_statuses_key("paper") == "fleetmpc/paper/uav/*/status"
    assert fleet_key("paper") == "fleetmpc/paper/**"
    assert epoch_key("paper") == "fleetmpc/paper/epoch"


@given(fleet=fleets, vehicle_id=ids)
def test_parse_round_trip(fleet: str, vehicle_id: int) -> None:
    assert parse_key(plan_key(fleet, vehicle_id)) == ParsedKey(fleet, MessageKind.PLAN, vehicle_id)
    assert parse_key(status_key(fleet, vehicle_id)) == ParsedKey(
        fleet, MessageKind.STATUS, vehicle_id
    )
    assert parse_key(target_observation_key(fleet)) == ParsedKey(
        fleet, MessageKind.TARGET_OBSERVATION, None
    )
    assert parse_key(epoch_key(fleet)) == ParsedKey(fleet, MessageKind.FLEET_EPOCH, None)


@given(fleet=fleets, vehicle_id=ids)
def test_zenoh_accepts_keys_and_wildcards_select_the_right_kind(
    fleet: str, vehicle_id: int
) -> None:
    plan = zenoh.KeyExpr(plan_key(fleet, vehicle_id))
    status = zenoh.KeyExpr(status_key(fleet, vehicle_id))
    assert str(zenoh.KeyExpr.autocanonize(str(plan))) == str(plan)
    assert zenoh.KeyExpr(all_plans_key(fleet)).intersects(plan)
    assert not zenoh.KeyExpr(all_plans_key(fleet)).intersects(status)
    assert zenoh.KeyExpr(all_statuses_key(fleet)).intersects(status)
    assert zenoh.KeyExpr(fleet_key(fleet)).intersects(target_observation_key(fleet))
    assert not zenoh.KeyExpr(all_plans_key(fleet + "x")).intersects(plan)


@pytest.mark.parametrize(
    "key",
    [
        "",
        "fleetmpc",
        "fleetmpc/paper",
        "other/paper/uav/1/plan",
        "fleetmpc/pa*per/uav/1/plan",
        "fleetmpc/paper/uav/0/plan",
        "fleetmpc/paper/uav/251/plan",
        "fleetmpc/paper/uav/01/plan",
        "fleetmpc/paper/uav/+1/plan",
        "fleetmpc/paper/uav/1.0/plan",
        "fleetmpc/paper/uav/x/plan",
        "fleetmpc/paper/uav/*/plan",
        "fleetmpc/paper/uav/1/plans",
        "fleetmpc/paper/uav/1/plan/",
        "fleetmpc/paper/uav/1/plan/extra",
        "fleetmpc/paper/target",
        "fleetmpc/paper/target/observation/1",
        "fleetmpc//uav/1/plan",
    ],
)
def test_parse_rejects_malformed_keys(key: str) -> None:
    with pytest.raises(KeyFormatError):
        parse_key(key)


@pytest.mark.parametrize("fleet", ["", "a/b", "a*", "a$b", "a b", "x" * 65, "é", 7, None])
def test_bad_fleet_names_raise_config_error_naming_the_field(fleet: object) -> None:
    with pytest.raises(ConfigError) as info:
        plan_key(fleet, 1)  # type: ignore[arg-type]
    assert info.value.field == "fleet"
    with pytest.raises(ConfigError) as info:
        validate_fleet(fleet, field="scenario.fleet")  # type: ignore[arg-type]
    assert info.value.field == "scenario.fleet"


@pytest.mark.parametrize("vehicle_id", [0, 251, -1, True, 1.0, "1"])
def test_bad_vehicle_ids_raise_config_error(vehicle_id: object) -> None:
    with pytest.raises(ConfigError) as info:
        plan_key("paper", vehicle_id)  # type: ignore[arg-type]
    assert info.value.field == "vehicle_id"
