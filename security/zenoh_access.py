"""The secured bus's users and what each may do: a user per process and the router's
access list (`fleet_access_control`).

The access list (`fleet_access_control`) denies everything it does not allow, per user name
(and, with mutual TLS, also per certificate common name, which is the user name):

- agent <i> publishes under ``fleetmpc/<fleet>/uav/<i>/**`` and reads every vehicle's plans and
  statuses, the target observation and the epoch;
- the target publishes ``fleetmpc/<fleet>/target/observation`` and reads the epoch;
- the ground station publishes the epoch and reads everything under ``fleetmpc/<fleet>/``.

Through a router, a sample enters it from the publisher's session (ingress) and leaves it to each
subscriber's session (egress). Tried with eclipse-zenoh 1.10.2, a flow needs exactly: ``put``
(and ``delete``) ingress for the publisher on its keys; ``declare_subscriber`` ingress for the
subscriber on its subscriptions and ``put`` (``delete``) egress to it on them; and
``declare_subscriber`` *egress* to the publisher on the subscriptions: a client session sends a
sample only where the router has told it a subscriber exists, so without that nothing leaves the
publisher. Every user may hear of the fleet's subscriptions. Queries, replies, queryables and
liveliness are not used by the fleet and stay denied.
"""

from collections.abc import Sequence

from fleetmpc.errors import ConfigError
from fleetmpc.protocol.key_expressions import (
    all_plans_key,
    all_statuses_key,
    epoch_key,
    fleet_key,
    plan_key,
    target_observation_key,
    validate_fleet,
)
from fleetmpc.protocol.messages import GROUND_STATION_ID, MAX_SENDER_ID, MIN_SENDER_ID, TARGET_ID

__all__ = [
    "GROUND_STATION_USER",
    "TARGET_USER",
    "fleet_access_control",
    "check_vehicle_ids",
    "zenoh_user",
]

TARGET_USER = "target"
GROUND_STATION_USER = "gcs"


def zenoh_user(sender_id: int) -> str:
    """The bus user of a sender: ``agent-<id>`` for a vehicle, ``target``, or ``gcs``."""
    if sender_id == TARGET_ID:
        return TARGET_USER
    if sender_id == GROUND_STATION_ID:
        return GROUND_STATION_USER
    return f"agent-{_vehicle_id('sender_id', sender_id)}"


def fleet_access_control(
    fleet: str, vehicle_ids: Sequence[int], *, mutual_tls: bool = False
) -> dict:
    """The router's ``access_control`` section for a fleet (see the module docstring).

    Default deny; one subject, policy and publish rule per user, matched by user name and, with
    `mutual_tls`, also by the common name of the session's certificate.
    """
    fleet = validate_fleet(fleet)
    ids = check_vehicle_ids(vehicle_ids)
    everything = fleet_key(fleet)
    reads = {
        "agent": [
            all_plans_key(fleet),
            all_statuses_key(fleet),
            target_observation_key(fleet),
            epoch_key(fleet),
        ],
        "target": [epoch_key(fleet)],
        "gcs": [everything],
    }
    members = [
        (zenoh_user(v), "agent", [plan_key(fleet, v).removesuffix("/plan") + "/**"]) for v in ids
    ]
    members += [
        (TARGET_USER, "target", [target_observation_key(fleet)]),
        (GROUND_STATION_USER, "gcs", [epoch_key(fleet)]),
    ]
    # A client sends a sample only where the router told it of a subscriber.
    rules = [_rule("learn-subscribers", ["declare_subscriber"], "egress", [everything])]
    for role, keys in reads.items():
        rules.append(_rule(f"subscribe-{role}", ["declare_subscriber"], "ingress", keys))
        rules.append(_rule(f"receive-{role}", ["put", "delete"], "egress", keys))
    subjects, policies = [], []
    for user, role, publishes in members:
        rules.append(_rule(f"publish-{user}", ["put", "delete"], "ingress", publishes))
        subject = {"id": user, "usernames": [user]}
        if mutual_tls:
            subject["cert_common_names"] = [user]
        subjects.append(subject)
        policies.append(
            {
                "id": user,
                "rules": [
                    "learn-subscribers",
                    f"subscribe-{role}",
                    f"receive-{role}",
                    f"publish-{user}",
                ],
                "subjects": [user],
            }
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def _rule(rule_id: str, messages: list[str], flow: str, keys: list[str]) -> dict:
    return {
        "id": rule_id,
        "messages": messages,
        "flows": [flow],
        "permission": "allow",
        "key_exprs": keys,
    }


def _vehicle_id(field: str, value: object) -> int:
    if (
        isinstance(value, bool)
        or not isinstance(value, int)
        or not MIN_SENDER_ID <= value <= MAX_SENDER_ID
        or value in (GROUND_STATION_ID, TARGET_ID)
    ):
        raise ConfigError(
            field,
            f"must be a vehicle id in [{MIN_SENDER_ID}, {MAX_SENDER_ID}] other than the ground"
            f" station's {GROUND_STATION_ID} and the target's {TARGET_ID}, got {value!r}",
        )
    return value


def check_vehicle_ids(values: Sequence[int]) -> tuple[int, ...]:
    try:
        items = None if isinstance(values, (str, bytes)) else tuple(values)
    except TypeError:
        items = None
    if not items:
        raise ConfigError("vehicle_ids", f"must be a non-empty list of vehicle ids, got {values!r}")
    ids = tuple(_vehicle_id(f"vehicle_ids[{k}]", v) for k, v in enumerate(items))
    for k, v in enumerate(ids):
        if v in ids[:k]:
            raise ConfigError(f"vehicle_ids[{k}]", f"vehicle {v} is listed twice")
    return ids
