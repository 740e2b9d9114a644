"""The scenario file (TOML): one description of a fleet, read by every process.

A scenario states the vehicles (initial state, slot, truth parameters), the target, the formation,
the controller and learning settings, the site, the network ports, the duration and the seed.
Loading validates every field; errors name the field, e.g. `vehicles[2].truth.speed_effectiveness`.
"""

import dataclasses
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fleetmpc.errors import ConfigError
from fleetmpc.network import Network, check_ports
from fleetmpc.onboard.core.config import ControllerSettings, FormationSettings, LearningSettings
from fleetmpc.sitl.plant import TruthParams
from fleetmpc.sitl.wind import Gust, Turbulence, Wind
from fleetmpc.targets.script import TargetScript
from fleetmpc.targets.track import RecordedTrack
from fleetmpc.targets.track_file import load_track
from fleetmpc.validate import finite, in_range, positive, vector

__all__ = [
    "flight_time",
    "AUTOPILOTS",
    "Scenario",
    "Site",
    "VehicleSpec",
    "load_scenario",
    "parse_scenario",
    "pattern_slots",
    "PATTERN_KINDS",
    "toml_files",
]

AUTOPILOTS = ("px4", "ardupilot")
"""Autopilot profiles a vehicle can fly: PX4 (UDP offboard API) or ArduPilot (TCP)."""


@dataclass(frozen=True)
class Site:
    """Where the fleet flies: the local NED origin and the flight altitude."""

    home_lat_deg: float = 47.397742
    """Latitude of the local origin [deg]."""
    home_lon_deg: float = 8.545594
    """Longitude of the local origin [deg]."""
    home_alt_m: float = 488.0
    """Altitude above mean sea level of the local origin [m]."""
    altitude_m: float = 10.0
    """Flight altitude above home after takeoff [m]."""

    def __post_init__(self) -> None:
        in_range("site.home_lat_deg", self.home_lat_deg, -90.0, 90.0)
        in_range("site.home_lon_deg", self.home_lon_deg, -180.0, 180.0)
        finite("site.home_alt_m", self.home_alt_m)
        positive("site.altitude_m", self.altitude_m)


@dataclass(frozen=True)
class VehicleSpec:
    """One vehicle of the fleet."""

    id: int
    """MAVLink system id (1..250), unique in the fleet."""
    initial: tuple[float, float, float]
    """Initial x North [m], y East [m], yaw [rad]."""
    slot_m: tuple[float, float]
    """Offset of this vehicle's slot from the formation centre [m] (frame: formation.frame)."""
    truth: TruthParams
    """The simulated vehicle's true parameters."""
    autopilot: str = "px4"
    """Autopilot profile of the vehicle's SITL and link: "px4" or "ardupilot"."""
    system_id: int | None = None
    """MAVLink system id of the vehicle's autopilot when it is not `id` (a stock ArduCopter
    answers as 1): the ground station tells vehicles apart by it; None: `id`."""
    response_delay_s: float = 0.0
    """How long the vehicle's autopilot takes to fly a command [s]: its agent plans from the
    state the commands already sent lead to (0 for the simulated vehicles)."""
    host: str | None = None
    """Address of the vehicle's companion computer, where its agent and its autopilot's link
    are (a simulated vehicle's SITL binds there); None: `network.host`."""

    def __post_init__(self) -> None:
        if self.autopilot not in AUTOPILOTS:
            raise ConfigError(
                "autopilot", f'must be "px4" or "ardupilot", got {_quoted(self.autopilot)}'
            )
        sid = self.system_id
        integer = isinstance(sid, int) and not isinstance(sid, bool)
        if sid is not None and not (integer and 1 <= sid <= 250):
            raise ConfigError("system_id", f"must be an integer in [1, 250], got {sid!r}")
        if self.host is not None and (not isinstance(self.host, str) or not self.host):
            raise ConfigError("host", f"must be a host name or address, got {self.host!r}")
        delay = self.response_delay_s
        if isinstance(delay, bool) or not isinstance(delay, int | float) or not 0 <= delay <= 5:
            raise ConfigError("response_delay_s", f"must be a number in [0, 5] s, got {delay!r}")

    @property
    def mavlink_system_id(self) -> int:
        """The system id the vehicle's autopilot answers as."""
        return self.id if self.system_id is None else self.system_id


def _quoted(value: object) -> str:
    return f'"{value}"' if isinstance(value, str) else repr(value)


@dataclass(frozen=True)
class Scenario:
    """A whole fleet, as described by one TOML file."""

    name: str
    description: str
    seed: int
    duration_s: float
    plant_steps_per_period: int
    controller: ControllerSettings
    learning: LearningSettings
    formation: FormationSettings
    target: TargetScript | RecordedTrack
    vehicles: tuple[VehicleSpec, ...]
    site: Site
    network: Network
    source: str = ""

    @property
    def vehicle_ids(self) -> tuple[int, ...]:
        return tuple(v.id for v in self.vehicles)

    def vehicle(self, vehicle_id: int) -> VehicleSpec:
        for v in self.vehicles:
            if v.id == vehicle_id:
                return v
        raise ConfigError(
            "vehicle",
            f"no vehicle with id {vehicle_id} in scenario {self.name!r} (ids: {self.vehicle_ids})",
        )

    def index_of(self, vehicle_id: int) -> int:
        return self.vehicle_ids.index(self.vehicle(vehicle_id).id)

    @property
    def tick_ns(self) -> int:
        return self.controller.period_ns // self.plant_steps_per_period

    def with_overrides(self, **changes: Any) -> "Scenario":
        return dataclasses.replace(self, **changes)


def _build(cls: type, table: Any, prefix: str, **extra: Any) -> Any:
    """Construct dataclass `cls` from a TOML table, naming unknown or malformed keys."""
    if not isinstance(table, dict):
        raise ConfigError(prefix, f"must be a table, got {table!r}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - names)
    if unknown:
        raise ConfigError(
            f"{prefix}.{unknown[0]}", f"unknown key (known: {', '.join(sorted(names))})"
        )
    kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in table.items()}
    kwargs.update(extra)
    try:
        return cls(**kwargs)
    except ConfigError as e:
        field = e.field if e.field.startswith(prefix) else f"{prefix}.{e.field.split('.')[-1]}"
        raise ConfigError(field, str(e).split(": ", 1)[1]) from None
    except TypeError as e:
        raise ConfigError(prefix, str(e)) from None


def _wind(table: Any, prefix: str) -> Wind:
    """A `Wind` from its TOML table, with its `turbulence` table and `gusts` list."""
    if not isinstance(table, dict):
        raise ConfigError(prefix, f"must be a table, got {table!r}")
    table = dict(table)
    turbulence = _build(Turbulence, table.pop("turbulence", {}), f"{prefix}.turbulence")
    gusts = table.pop("gusts", [])
    if not isinstance(gusts, list):
        raise ConfigError(f"{prefix}.gusts", f"must be a list of tables, got {gusts!r}")
    built = tuple(_build(Gust, g, f"{prefix}.gusts[{i}]") for i, g in enumerate(gusts))
    return _build(Wind, table, prefix, turbulence=turbulence, gusts=built)


def _drift_for_the_wind(
    learning: LearningSettings, wind_table: Any, controller: ControllerSettings, given: Any
) -> LearningSettings:
    """The learned drift's gust as the site's wind: its intensity (`Wind.gust_std_m_s`), the
    time constant of a Gauss-Markov process that changes as fast (`Wind.rate_m_s` at the cruise
    airspeed, sigma sqrt(2 / T)) and the distance over which it decorrelates (`wind_length_m`):
    what a forecast of the site's turbulence tells the agents (docs/design.md, "The wind's two
    parts", "The fleet's wind"). Settings the scenario's [learning] gives stay."""
    wind = _wind(wind_table, "truth.wind")
    sigma, rate = wind.gust_std_m_s(), wind.rate_m_s(controller.reference_speed_m_s)
    if sigma == 0.0 or rate == 0.0:
        return learning
    given = given if isinstance(given, dict) else {}
    forecast: dict[str, float] = {}
    if "gust_std_m_s" not in given:  # (the gust's time constant goes with its intensity)
        forecast["gust_std_m_s"] = sigma
        forecast["gust_time_constant_s"] = 2.0 * sigma * sigma / (rate * rate)
    if "wind_length_m" not in given:
        forecast["wind_length_m"] = _wind_length_m(wind)
    return dataclasses.replace(learning, **forecast)


def _wind_length_m(wind: Wind) -> float:
    """How far apart two vehicles feel different gusts [m]: the turbulence's length scale, else
    the shortest discrete gust's length; inf when the changing part (a sinusoid) blows the same
    everywhere."""
    if wind.turbulence.sigma_m_s > 0.0:
        return wind.turbulence.length_scale_m
    return min((g.length_m for g in wind.gusts), default=math.inf)


def _refuse_own_turbulence(truth: Any, prefix: str) -> None:
    """A vehicle's truth may change its mean wind, not the fleet's turbulence or gusts: those
    are one field that every vehicle flies through (sitl/wind.py)."""
    wind = truth.get("wind", {}) if isinstance(truth, dict) else {}
    for key in ("turbulence", "gusts"):
        if isinstance(wind, dict) and key in wind:
            raise ConfigError(
                f"{prefix}.wind.{key}",
                "the wind's turbulence and gusts are the fleet's: set them in [truth.wind]",
            )


def _truth(table: dict[str, Any], prefix: str, controller: ControllerSettings) -> TruthParams:
    table = dict(table)
    wind = _wind(table.pop("wind", {}), f"{prefix}.wind")
    table.setdefault("speed_limit_m_s", controller.speed_max_m_s)
    table.setdefault("yaw_rate_limit_rad_s", controller.yaw_rate_max_rad_s)
    return _build(TruthParams, table, prefix, wind=wind)


_VEHICLE_KEYS = {
    "id",
    "initial",
    "slot_m",
    "truth",
    "autopilot",
    "system_id",
    "response_delay_s",
    "host",
}

_TOP_KEYS = {
    "name",
    "description",
    "seed",
    "duration_s",
    "plant_steps_per_period",
    "controller",
    "learning",
    "formation",
    "target",
    "truth",
    "vehicles",
    "site",
    "network",
}


PATTERN_KINDS = ("grid", "line", "wedge", "ring")


def pattern_slots(
    kind: str, count: int, spacing_m: float, columns: int
) -> list[tuple[float, float]]:
    """Slot offsets (forward, right) [m] of `count` vehicles in a pattern, about its centre:

    - grid: rows of `columns`, `spacing_m` apart both ways, the first row in front;
    - line: abreast, `spacing_m` apart, perpendicular to the formation's forward axis;
    - wedge: a V behind a leader, each arm's vehicles `spacing_m` back and aside of the last;
    - ring: evenly on a circle whose neighbours are `spacing_m` apart.
    """
    s = spacing_m
    if kind == "grid":
        rows = math.ceil(count / columns)
        return [
            ((rows - 1) / 2 * s - (i // columns) * s, (i % columns - (columns - 1) / 2) * s)
            for i in range(count)
        ]
    if kind == "line":
        return [(0.0, (i - (count - 1) / 2) * s) for i in range(count)]
    if kind == "wedge":
        out = [(0.0, 0.0)]
        for i in range(1, count):
            rank, side = (i + 1) // 2, 1.0 if i % 2 else -1.0
            out.append((-rank * s * math.sqrt(0.5), side * rank * s * math.sqrt(0.5)))
        depth = max(-x for x, _ in out)
        return [(x + depth / 2, y) for x, y in out]
    radius = 0.0 if count == 1 else s / (2 * math.sin(math.pi / count))
    return [
        (radius * math.cos(2 * math.pi * i / count), radius * math.sin(2 * math.pi * i / count))
        for i in range(count)
    ]


def _pattern_vehicles(pattern: Any, formation: dict[str, Any], target: TargetScript) -> list:
    """The [[vehicles]] tables a `formation.pattern` stands for: ids 1..count, their slots, and
    each starting at its slot around the target's start, facing the target's course."""
    field = "formation.pattern"
    if not isinstance(pattern, dict):
        raise ConfigError(field, f"must be a table, got {pattern!r}")
    unknown = sorted(set(pattern) - {"kind", "count", "spacing_m", "columns"})
    if unknown:
        raise ConfigError(
            f"{field}.{unknown[0]}", "unknown key (known: kind, count, spacing_m, columns)"
        )
    kind = pattern.get("kind")
    if kind not in PATTERN_KINDS:
        raise ConfigError(
            f"{field}.kind", f"must be one of {', '.join(PATTERN_KINDS)}, got {kind!r}"
        )
    count = pattern.get("count")
    if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= 250:
        raise ConfigError(f"{field}.count", f"must be an integer in [1, 250], got {count!r}")
    spacing = positive(f"{field}.spacing_m", pattern.get("spacing_m", 5.0))
    columns = pattern.get("columns", math.ceil(math.sqrt(count)))
    if isinstance(columns, bool) or not isinstance(columns, int) or columns < 1:
        raise ConfigError(f"{field}.columns", f"must be an integer >= 1, got {columns!r}")
    slots = pattern_slots(kind, count, spacing, columns)
    frame = formation.get("frame", "world")
    trail = float(formation.get("trail_m", 5.0))
    position, velocity = target.state_at(0.0)
    course = math.atan2(velocity[1], velocity[0]) if math.hypot(*velocity) > 1e-9 else 0.0
    cx, cy = position[0] - trail * math.cos(course), position[1] - trail * math.sin(course)
    ux, uy = math.cos(course), math.sin(course)
    vehicles = []
    for i, (f, r) in enumerate(slots):
        if frame == "course":  # (forward, right) turned by the course
            slot, world = [f, r], (f * ux - r * uy, f * uy + r * ux)
        else:  # the pattern's forward axis is North
            slot, world = [f, r], (f, r)
        initial = [cx + world[0], cy + world[1], course]
        vehicles.append({"id": i + 1, "slot_m": slot, "initial": initial})
    return vehicles


_TRACK_KEYS = {"kind", "file", "system_id", "observation_noise_m"}


def _target(table: Any, site: "Site", source: str) -> TargetScript | RecordedTrack:
    """The scenario's target: a script, or a recorded track (`kind = "track"`, its `file` relative
    to the scenario's folder, the `system_id` to follow in a .tlog, the fixes'
    `observation_noise_m` if not estimated)."""
    if not isinstance(table, dict) or table.get("kind") != "track":
        return _build(TargetScript, table, "target")
    unknown = sorted(set(table) - _TRACK_KEYS)
    if unknown:
        raise ConfigError(
            f"target.{unknown[0]}",
            f"unknown key for a track (known: {', '.join(sorted(_TRACK_KEYS))})",
        )
    file = table.get("file")
    if not isinstance(file, str) or not file:
        raise ConfigError("target.file", f"a track needs its file, got {file!r}")
    path = Path(file)
    if not path.is_absolute() and source != "<memory>":
        path = Path(source).parent / path
    noise = table.get("observation_noise_m")
    if noise is not None:
        positive("target.observation_noise_m", noise)
    return load_track(
        path,
        home_lat_deg=site.home_lat_deg,
        home_lon_deg=site.home_lon_deg,
        system_id=table.get("system_id"),
        noise_m=noise,
    )


def parse_scenario(
    doc: dict[str, Any], *, source: str = "<memory>", live: bool = False
) -> Scenario:
    """Validate a parsed TOML document and return the Scenario it describes; `live`: also
    refuse ports that would clash (`load_scenario`)."""
    name, seed, duration_s, steps = _top_level(doc)
    controller = _build(ControllerSettings, doc.get("controller", {}), "controller")
    if controller.period_ns % steps:
        raise ConfigError(
            "plant_steps_per_period",
            f"must divide the control period ({controller.period_ns} ns) exactly",
        )
    learning = _build(LearningSettings, doc.get("learning", {}), "learning")
    site = _build(Site, doc.get("site", {}), "site")
    target = _target(doc.get("target", {}), site, source)
    truth_default = doc.get("truth", {})
    if not isinstance(truth_default, dict):
        raise ConfigError("truth", "must be a table")
    learning = _drift_for_the_wind(
        learning, truth_default.get("wind", {}), controller, doc.get("learning", {})
    )
    formation_table = dict(doc.get("formation", {}))
    pattern = formation_table.pop("pattern", None)
    raw_vehicles = doc.get("vehicles")
    if pattern is not None:
        if raw_vehicles is not None:
            raise ConfigError("formation.pattern", "give a pattern or [[vehicles]], not both")
        raw_vehicles = _pattern_vehicles(pattern, formation_table, target)
    if not isinstance(raw_vehicles, list) or not raw_vehicles:
        raise ConfigError("vehicles", "must be a non-empty array of tables ([[vehicles]])")
    vehicles = tuple(
        _vehicle(raw, i, truth_default, controller) for i, raw in enumerate(raw_vehicles)
    )
    _refuse_shared_ids(vehicles)
    if "slots_m" in formation_table:
        raise ConfigError("formation.slots_m", "give each vehicle's slot as vehicles[i].slot_m")
    formation = _build(
        FormationSettings, formation_table, "formation", slots_m=tuple(v.slot_m for v in vehicles)
    )
    _refuse_close_pairs(vehicles, formation, controller.d_safe_m)
    network = _build(Network, doc.get("network", {}), "network")
    for v in vehicles:  # every vehicle's default ports exist (either profile can fly it)
        network.offboard_port(v.id)
        network.ardupilot_tcp_port(v.id)
    if live:
        check_ports(network, vehicles)
    return Scenario(
        name=name,
        description=str(doc.get("description", "")),
        seed=seed,
        duration_s=duration_s,
        plant_steps_per_period=steps,
        controller=controller,
        learning=learning,
        formation=formation,
        target=target,
        vehicles=vehicles,
        site=site,
        network=network,
        source=source,
    )


def _top_level(doc: dict[str, Any]) -> tuple[str, int, float, int]:
    """The document's own keys checked: its name, seed, duration and plant steps a period."""
    unknown = sorted(set(doc) - _TOP_KEYS)
    if unknown:
        raise ConfigError(
            unknown[0], f"unknown top-level key (known: {', '.join(sorted(_TOP_KEYS))})"
        )
    name = doc.get("name")
    if not isinstance(name, str) or not name:
        raise ConfigError("name", f"must be a non-empty string, got {name!r}")
    seed = doc.get("seed", 0)
    if not isinstance(seed, int) or seed < 0:
        raise ConfigError("seed", f"must be a non-negative integer, got {seed!r}")
    duration_s = positive("duration_s", doc.get("duration_s", 30.0))
    steps = doc.get("plant_steps_per_period", 10)
    if not isinstance(steps, int) or not 1 <= steps <= 1000:
        raise ConfigError(
            "plant_steps_per_period", f"must be an integer in [1, 1000], got {steps!r}"
        )
    return name, seed, duration_s, steps


def _vehicle(
    raw: Any, i: int, truth_default: dict[str, Any], controller: ControllerSettings
) -> VehicleSpec:
    """The vehicle of the `i`-th [[vehicles]] table, its truth over the file's `[truth]`."""
    prefix = f"vehicles[{i}]"
    if not isinstance(raw, dict):
        raise ConfigError(prefix, "must be a table")
    extra = sorted(set(raw) - _VEHICLE_KEYS)
    if extra:
        raise ConfigError(
            f"{prefix}.{extra[0]}",
            f"unknown key (known: {', '.join(sorted(_VEHICLE_KEYS))})",
        )
    vid = raw.get("id", i + 1)
    if not isinstance(vid, int) or not 1 <= vid <= 250:
        raise ConfigError(f"{prefix}.id", f"must be an integer in [1, 250], got {vid!r}")
    initial = vector(f"{prefix}.initial", raw.get("initial", [0.0, 0.0, 0.0]), 3)
    slot = vector(f"{prefix}.slot_m", raw.get("slot_m", [0.0, 0.0]), 2)
    truth_table = {**truth_default, **raw.get("truth", {})}
    _refuse_own_turbulence(raw.get("truth", {}), f"{prefix}.truth")
    if "wind" in truth_default and "wind" in raw.get("truth", {}):
        truth_table["wind"] = {**truth_default["wind"], **raw["truth"]["wind"]}
    truth = _truth(truth_table, f"{prefix}.truth", controller)
    try:
        return VehicleSpec(
            vid,
            initial,
            slot,
            truth,
            autopilot=raw.get("autopilot", "px4"),
            system_id=raw.get("system_id"),
            response_delay_s=raw.get("response_delay_s", 0.0),
            host=raw.get("host"),
        )
    except ConfigError as e:
        raise ConfigError(f"{prefix}.{e.field}", str(e).split(": ", 1)[1]) from None


def _refuse_shared_ids(vehicles: tuple[VehicleSpec, ...]) -> None:
    """Each vehicle's id and MAVLink system id are its own."""
    ids = [v.id for v in vehicles]
    if len(set(ids)) != len(ids):
        raise ConfigError("vehicles", f"ids must be unique, got {ids}")
    systems = [v.mavlink_system_id for v in vehicles]
    if len(set(systems)) != len(systems):
        raise ConfigError(
            "vehicles",
            f"MAVLink system ids (system_id, else id) must be unique, got {systems}",
        )


def _refuse_close_pairs(
    vehicles: tuple[VehicleSpec, ...], formation: FormationSettings, d_safe_m: float
) -> None:
    """No two vehicles start, and no two slots lie, closer than d_safe_m."""
    for a in range(len(vehicles)):
        for b in range(a + 1, len(vehicles)):
            pa, pb = vehicles[a].initial, vehicles[b].initial
            gap = math.hypot(pa[0] - pb[0], pa[1] - pb[1])
            if gap < d_safe_m:
                raise ConfigError(
                    f"vehicles[{b}].initial",
                    f"starts {gap:.2f} m from vehicle {vehicles[a].id}, "
                    f"closer than d_safe_m = {d_safe_m}",
                )
            sa, sb = formation.slots_m[a], formation.slots_m[b]
            if math.hypot(sa[0] - sb[0], sa[1] - sb[1]) < d_safe_m:
                raise ConfigError(
                    f"vehicles[{b}].slot_m",
                    f"slot is closer than d_safe_m to vehicle {vehicles[a].id}'s",
                )


def toml_files(folder: Path, *, field: str, what: str) -> list[Path]:
    """The ``*.toml`` files of a folder, sorted; a missing or empty folder is an error naming
    `field` (the option that gave it)."""
    if not folder.is_dir():
        raise ConfigError(field, f"not a folder: {folder}")
    files = sorted(folder.glob("*.toml"))
    if not files:
        raise ConfigError(field, f"no {what} (*.toml) in {folder}")
    return files


def load_scenario(path: str | Path, *, live: bool = False) -> Scenario:
    """Read and validate a scenario TOML file; `live`: for processes that open its ports (`up`,
    `compose`, the vehicle, agent and ground-station processes), which must not clash. A
    lockstep run, `check` and `suite` open none and do not ask."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError("scenario", f"no such file: {p}")
    try:
        doc = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ConfigError("scenario", f"{p} is not valid TOML: {e}") from None
    return parse_scenario(doc, source=str(p), live=live)


def flight_time(scenario: Scenario, *, speed: float, duration_s: float | None) -> float:
    """The flight time [s] of a launch (the scenario's without `duration_s`), after checking the
    command line's ``--speed`` and ``--duration``."""
    if not 0.01 <= speed <= 1000.0:
        raise ConfigError("--speed", f"must be in [0.01, 1000], got {speed}")
    duration = scenario.duration_s if duration_s is None else duration_s
    if not duration > 0:
        raise ConfigError("--duration", f"must be > 0, got {duration}")
    return duration
