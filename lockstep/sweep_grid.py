"""The grid of a sweep: the varied fields by dotted path, their values, and the runs they make.

A dotted path addresses a value of the scenario's TOML document by its tables' names:
``controller.horizon``, ``truth.actuator_lag_s``, ``truth.wind.gust_amplitude_m_s``,
``formation.pattern.count``. Entries of an array of tables are addressed by their index from 0,
as the scenario's own error messages name them (``vehicles[1].truth.speed_effectiveness``), or
all at once with ``[*]`` (``vehicles[*].truth.speed_effectiveness``). Paths that start with
``faults[`` address the fault file given with ``--faults`` (``faults[0].probability``) the same
way. The scenario's parser is the schema: a path is valid when the document with its value set
parses, so any field a scenario (or fault file) accepts can be varied, including fields added
after this module was written.

Every value of every axis is set and parsed on every scenario file before anything flies, so a
bad path or value is refused up front, with the path, the value, the file and (for an unknown
key) the nearest known ones. So is an axis whose values fly the same scenario (a ``[truth]``
field that every vehicle sets for itself, for instance).

A run's identity (`RunSpec.run_id`) is a hash of what decides its flight: the scenario file's
text, the values set, the seed, learning, the fault file's text. The same inputs have the same
identity wherever and whenever they are flown, so a resumed sweep knows what it has.
"""

import copy
import dataclasses
import difflib
import hashlib
import itertools
import json
import re
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fleetmpc.bus.faults import FaultSchedule, parse_faults
from fleetmpc.errors import ConfigError
from fleetmpc.scenario import Scenario, parse_scenario

__all__ = [
    "Axis",
    "RunSpec",
    "build_run",
    "parse_vary",
    "plan_runs",
    "read_text",
    "set_path",
    "split_values",
]

_STEP = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)(?:\[(\d+|\*)\])?$")
"""One step of a dotted path: a key, optionally indexed (``vehicles[1]``, ``vehicles[*]``)."""

_REFUSED = {
    "seed": "the seeds are --seeds K (the scenario's seed and the K - 1 after it)",
}


@dataclass(frozen=True)
class Axis:
    """One varied field: its dotted path and the values the sweep gives it, in order."""

    path: str
    """Dotted path (module docstring)."""
    values: tuple[Any, ...]
    """TOML values (numbers, booleans, strings, arrays of them)."""

    @property
    def faults(self) -> bool:
        """True for a field of the fault file."""
        return self.path.startswith("faults[")


def split_values(text: str) -> list[str]:
    """The comma-separated items of `text`, commas inside brackets or quotes excepted
    (``[0.3, 0], [0.1, 0]`` is two arrays)."""
    items, depth, quote, start = [], 0, "", 0
    for i, ch in enumerate(text):
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch == "[":
            depth += 1
        elif ch == "]":
            depth -= 1
        elif ch == "," and depth == 0:
            items.append(text[start:i])
            start = i + 1
    items.append(text[start:])
    return [item.strip() for item in items]


def _value(path: str, text: str) -> Any:
    """One value as TOML reads it (``5``, ``0.1``, ``true``, ``"grid"``, ``[0.3, 0.0]``); a bare
    word is a string."""
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        if re.fullmatch(r"[A-Za-z_][A-Za-z0-9_.\-]*", text):
            return text
        raise ConfigError(f"--vary {path}", f"{text!r} is not a TOML value") from None
    if isinstance(value, dict):
        raise ConfigError(f"--vary {path}", f"{text!r}: give a field of the table, not a table")
    return value


def parse_vary(text: str) -> Axis:
    """``PATH=V1,V2,...`` as an Axis (the path checked for form, not yet against a file)."""
    path, sep, values = text.partition("=")
    path = path.strip()
    if not sep or not path or not values.strip():
        raise ConfigError("--vary", f"expected PATH=V1,V2,..., got {text!r}")
    steps = path.split(".")
    if not all(_STEP.match(s) for s in steps):
        raise ConfigError(f"--vary {path}", "not a dotted path (such as controller.horizon)")
    if path in _REFUSED:
        raise ConfigError(f"--vary {path}", _REFUSED[path])
    if path.startswith("faults") and not path.startswith("faults["):
        raise ConfigError(f"--vary {path}", "fault-file fields are faults[i].FIELD")
    items = split_values(values)
    if any(not item for item in items):
        raise ConfigError(f"--vary {path}", f"an empty value in {values!r}")
    parsed = [_value(path, item) for item in items]
    canon = [json.dumps(v, sort_keys=True) for v in parsed]
    if len(set(canon)) != len(canon):
        raise ConfigError(f"--vary {path}", f"a value is given twice: {values}")
    return Axis(path, tuple(parsed))


def set_path(doc: dict[str, Any], path: str, value: Any) -> dict[str, Any]:
    """A copy of `doc` with `value` at `path`; tables on the way are made when missing. Raises
    ConfigError naming the path when it goes through a value or past an array's end."""
    out = copy.deepcopy(doc)
    _set(out, path.split("."), value, path, "")
    return out


def _set(node: dict[str, Any], steps: list[str], value: Any, path: str, done: str) -> None:
    m = _STEP.match(steps[0])
    if m is None:
        raise ConfigError(path, "not a dotted path")
    key, index = m.group(1), m.group(2)
    here = f"{done}.{key}" if done else key
    if index is None:
        if len(steps) == 1:
            node[key] = value
            return
        child = node.setdefault(key, {})
        if not isinstance(child, dict):
            raise ConfigError(path, f"{here} is a value, not a table")
        _set(child, steps[1:], value, path, here)
        return
    entries = node.get(key)
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        what = "has no" if entries is None else "is not an"
        raise ConfigError(path, f"the file {what} array of tables {key} ([[{key}]])")
    chosen = range(len(entries)) if index == "*" else [int(index)]
    for i in chosen:
        if i >= len(entries):
            raise ConfigError(
                path, f"the file has {len(entries)} {key} (indices 0 to {len(entries) - 1})"
            )
        if len(steps) == 1:
            raise ConfigError(path, f"{key}[{i}] is a table: give one of its fields")
        _set(entries[i], steps[1:], value, path, f"{here}[{i}]")


@dataclass(frozen=True)
class RunSpec:
    """Everything one run needs, self-contained (a worker on another host reads no file)."""

    file: str
    """The scenario file, as given (for the table)."""
    scenario_text: str
    """The scenario file's text."""
    overrides: tuple[tuple[str, Any], ...]
    """(dotted path, value) set on the scenario or the fault file, in the order of the axes."""
    seed: int
    """Random seed of the run."""
    learning: bool
    """Learn beta online (False: plain tube MPC)."""
    fault_file: str | None = None
    """The fault file, as given (None: no faults)."""
    fault_text: str | None = None
    """The fault file's text."""

    @property
    def run_id(self) -> str:
        """Hash of the inputs: the same for the same flight wherever it is flown."""
        doc = {
            "scenario": self.scenario_text,
            "overrides": [[p, v] for p, v in self.overrides],
            "seed": self.seed,
            "learning": self.learning,
            "faults": self.fault_text,
        }
        text = json.dumps(doc, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:20]

    @property
    def values(self) -> dict[str, Any]:
        """The values set, by path."""
        return dict(self.overrides)


def read_text(path: str | Path, *, field: str) -> str:
    """A file's text; an error naming `field` (the option that gave it) when it cannot be read."""
    p = Path(path)
    try:
        return p.read_text()
    except OSError as e:
        raise ConfigError(field, f"cannot read {p}: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise ConfigError(field, f"{p} is not UTF-8 text") from None


def _toml(text: str, source: str, field: str) -> dict[str, Any]:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(field, f"{source} is not valid TOML: {e}") from None


def build_run(spec: RunSpec) -> tuple[Scenario, FaultSchedule | None]:
    """The scenario and fault schedule a run flies: the files' texts with the values set."""
    doc = _toml(spec.scenario_text, spec.file, "scenario")
    fault_doc = None
    if spec.fault_text is not None:
        fault_doc = _toml(spec.fault_text, str(spec.fault_file), "--faults")
    for path, value in spec.overrides:
        if path.startswith("faults["):
            fault_doc = set_path(fault_doc or {}, path, value)
        else:
            doc = set_path(doc, path, value)
    sc = parse_scenario(doc, source=spec.file)
    faults = None
    if fault_doc is not None:
        try:
            faults = parse_faults(fault_doc, vehicle_ids=sc.vehicle_ids)
        except ConfigError as e:
            raise ConfigError(f"{spec.fault_file}: {e.field}", str(e).split(": ", 1)[1]) from None
    return sc, faults


def _known_keys(message: str) -> list[str]:
    m = re.search(r"\(known: ([^)]*)\)", message)
    return [] if m is None else [k.strip() for k in m.group(1).split(",") if k.strip()]


def _same_field(error_field: str, path: str) -> bool:
    """True when the parser's error names the varied path (an index [*] matches any index; a
    [truth] field is named in the vehicle that reads it)."""
    pattern = re.escape(path).replace(r"\[\*\]", r"\[\d+\]")
    if path.startswith("truth."):
        pattern = rf"(vehicles\[\d+\]\.)?{pattern}"
    return re.fullmatch(pattern, error_field) is not None


def _refusal(error: ConfigError, axis: Axis, value: Any, source: str) -> ConfigError:
    """The parser's error on a value set at the axis's path, as the user's --vary sees it."""
    given = f"--vary {axis.path}={json.dumps(value)}"
    message = str(error)
    known = _known_keys(message)
    if known and _same_field(error.field, axis.path):
        parent, _, leaf = axis.path.rpartition(".")
        near = difflib.get_close_matches(leaf, known, n=3, cutoff=0.5)
        hint = f"; nearest: {', '.join(f'{parent}.{k}' if parent else k for k in near)}"
        return ConfigError(
            f"--vary {axis.path}",
            f"unknown field in {source} (known here: {', '.join(known)}){hint if near else ''}",
        )
    return ConfigError(given, f"{source}: {message}")


def _truth_hint(doc: dict[str, Any], path: str) -> str:
    """Why a [truth] field may change nothing: every vehicle sets it for itself."""
    if not path.startswith("truth."):
        return ""
    steps = path.split(".")[1:]
    vehicles = doc.get("vehicles") or []
    for i, v in enumerate(vehicles):
        node: Any = v.get("truth", {}) if isinstance(v, dict) else {}
        for s in steps:
            node = node.get(s) if isinstance(node, dict) else None
        if node is not None:
            return (
                f" (vehicles[{i}].truth sets {'.'.join(steps)} itself, over [truth]: vary "
                f"vehicles[*].truth.{'.'.join(steps)})"
            )
    return ""


def _check_axis(axis: Axis, spec: RunSpec) -> None:
    """Set each of the axis's values on the file(s) of `spec` and parse: refuse a bad path or
    value, and values that fly the same scenario."""
    flown: list[tuple[Any, Any]] = []
    for value in axis.values:
        trial = RunSpec(
            spec.file,
            spec.scenario_text,
            ((axis.path, value),),
            spec.seed,
            spec.learning,
            spec.fault_file,
            spec.fault_text,
        )
        source = str(spec.fault_file) if axis.faults else spec.file
        try:
            result = build_run(trial)
        except ConfigError as e:
            if axis.faults and e.field.startswith(f"{spec.fault_file}: "):
                inner = ConfigError(e.field.split(": ", 1)[1], str(e).split(": ", 2)[2])
                raise _refusal(inner, axis, value, source) from None
            raise _refusal(e, axis, value, source) from None
        for other_value, other in flown:
            try:
                same = other == result
            except (ValueError, TypeError):  # a field that does not compare (an array)
                same = False
            if same:
                doc = _toml(spec.scenario_text, spec.file, "scenario")
                raise ConfigError(
                    f"--vary {axis.path}",
                    f"{json.dumps(other_value)} and {json.dumps(value)} fly the same scenario "
                    f"in {spec.file}{_truth_hint(doc, axis.path)}",
                )
        flown.append((value, result))


def plan_runs(
    files: Sequence[str | Path],
    axes: Sequence[Axis],
    *,
    seeds: int,
    learning: Sequence[bool] = (True,),
    fault_files: Sequence[str | Path | None] = (None,),
) -> list[RunSpec]:
    """Every run of the grid, in table order: file, fault file, the axes' values (the first
    axis slowest), learning, seed (s, s + 1, ..., s + seeds - 1, s the file's seed); each axis
    checked against each file first (module docstring). Raises ConfigError before any run."""
    if seeds < 1:
        raise ConfigError("--seeds", f"must be >= 1, got {seeds}")
    paths = [a.path for a in axes]
    if len(set(paths)) != len(paths):
        raise ConfigError("--vary", f"a path is varied twice: {paths}")
    if any(a.faults for a in axes) and None in fault_files:
        raise ConfigError(
            f"--vary {next(a.path for a in axes if a.faults)}",
            "a fault-file field needs a fault file in every run (--faults FILE, without none)",
        )
    faults = [
        (None, None) if f is None else (str(f), read_text(f, field="--faults")) for f in fault_files
    ]
    runs: list[RunSpec] = []
    for file in files:
        text = read_text(file, field="scenario")
        base = RunSpec(str(file), text, (), 0, True)
        try:
            sc, _ = build_run(base)
        except ConfigError as e:
            raise ConfigError(str(file), str(e)) from None
        for fault_file, fault_text in faults:
            spec = RunSpec(str(file), text, (), sc.seed, True, fault_file, fault_text)
            if fault_text is not None:
                build_run(spec)  # the fault file against this scenario's vehicles
            for axis in axes:
                _check_axis(axis, spec)
            for combo in itertools.product(*(a.values for a in axes)):
                overrides = tuple(zip(paths, combo, strict=True))
                try:  # the values together (each alone is checked above)
                    build_run(dataclasses.replace(spec, overrides=overrides))
                except ConfigError as e:
                    given = " ".join(f"{p}={json.dumps(v)}" for p, v in overrides)
                    raise ConfigError(f"--vary {given}", f"{file}: {e}") from None
                for on in learning:
                    for seed in range(sc.seed, sc.seed + seeds):
                        runs.append(
                            RunSpec(str(file), text, overrides, seed, on, fault_file, fault_text)
                        )
    seen: set[str] = set()
    unique = []
    for r in runs:  # the same file given twice is flown once
        if r.run_id not in seen:
            seen.add(r.run_id)
            unique.append(r)
    return unique
