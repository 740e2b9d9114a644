"""A sweep's results on disk: one Parquet file per finished run, and the table of them all.

``OUT/runs/<run_id>.parquet`` holds one row, written as the run finishes: to a temporary file
in the same folder, flushed to disk, then renamed over its final name, so a file under its
final name is always whole (a sweep killed mid-write leaves at most a temporary file, ignored
and swept away by the next start). A run's file name is its identity, so no run is ever
written twice: a resumed sweep reads which identities are there and flies the others.

``OUT/results.parquet`` is the table of the sweep's runs in table order, with the gates
applied (`fleetmpc.lockstep.suite.apply_gates`: ``learning_ratio`` and ``gates_failed``), rewritten
at the end of every sweep, interrupted or not. Columns: `BASE_COLUMNS`, then one per varied
field (named by its dotted path, typed by its values), then `OUTCOME_COLUMNS`,
`CONTEXT_COLUMNS`, `METRIC_COLUMNS`, `PROVENANCE_COLUMNS` and `GATE_COLUMNS`.
"""

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from fleetmpc.errors import ConfigError
from fleetmpc.lockstep.sweep_grid import Axis

__all__ = [
    "BASE_COLUMNS",
    "CONTEXT_COLUMNS",
    "GATE_COLUMNS",
    "METRIC_COLUMNS",
    "OUTCOME_COLUMNS",
    "PROVENANCE_COLUMNS",
    "ResultStore",
    "axis_type",
    "row_schema",
]

BASE_COLUMNS: dict[str, tuple[pa.DataType, str]] = {
    "run_id": (pa.string(), "hash of its inputs: file text, values set, seed, learning, faults"),
    "scenario": (pa.string(), "the scenario's name"),
    "file": (pa.string(), "the scenario file, as given"),
    "seed": (pa.int64(), "random seed"),
    "learning": (pa.bool_(), "learning asked for (the file may still disable it)"),
    "faults": (pa.string(), "the fault file, as given (null: none)"),
    "overrides": (pa.string(), "the values set, as a JSON object by dotted path"),
}
"""Identity and inputs of a run."""

OUTCOME_COLUMNS: dict[str, tuple[pa.DataType, str]] = {
    "status": (pa.string(), '"ok" (it flew) or "failed" (no numbers)'),
    "error": (pa.string(), "its error (a failed run's, or the feasibility check's)"),
    "first_error": (pa.string(), "the error of its first flight, when it was flown again"),
    "attempts": (pa.int64(), "flights it took (2: flown again after a failure)"),
}

CONTEXT_COLUMNS: dict[str, tuple[pa.DataType, str]] = {
    "vehicle_count": (pa.int64(), "vehicles in the fleet"),
    "d_safe_m": (pa.float64(), "the scenario's minimum separation [m]"),
    "unmodeled_dynamics": (pa.bool_(), "the truth has an effectiveness other than 1, or wind"),
    "feasible": (pa.bool_(), "fleetmpc check's verdict (null: the check failed)"),
    "flown_s": (pa.float64(), "simulated seconds flown [s]"),
    "periods": (pa.int64(), "control periods flown"),
}

METRIC_COLUMNS: dict[str, tuple[pa.DataType, str]] = {
    "formation_rms_m": (pa.float64(), "RMS distance to the slot, last 10 s, all vehicles [m]"),
    "slot_rms_max_vehicle_m": (pa.float64(), "the worst vehicle's own slot RMS [m]"),
    "separation_error_max_m": (pa.float64(), "worst pair's mean |d - d*|, last 10 s [m]"),
    "centre_distance_error_m": (pa.float64(), "mean fleet-centre error, last 10 s [m]"),
    "c_norm_final": (pa.float64(), "max over vehicles of the mean |c_0|, last 5 s"),
    "min_separation_m": (pa.float64(), "closest approach of any pair, at plant rate [m]"),
    "inputs_within_bounds": (pa.float64(), "share of commands inside U"),
    "yaw_rate_reversals_per_vehicle_min": (pa.float64(), "yaw-rate reversals [1/min/vehicle]"),
    "qp_fallbacks": (pa.int64(), "agent periods whose QP fell back"),
    "qp_fallback_fraction": (pa.float64(), "the same over agent steps"),
    "target_prediction_rms_m": (pa.float64(), "target prediction error M periods ahead [m]"),
    "corners": (pa.int64(), "the target's corners"),
    "corner_recovery_s": (pa.float64(), "longest recovery from a corner (inf: never) [s]"),
    "beta_error_speed_max": (pa.float64(), "worst final relative error of a_V"),
    "beta_error_yaw_rate_max": (pa.float64(), "worst final relative error of a_omega"),
    "beta_error_drift_max_m_s": (pa.float64(), "worst final drift error [m/s]"),
    "plan_age_p99_s": (pa.float64(), "p99 age of the neighbours' plans used [s]"),
    "plan_age_max_s": (pa.float64(), "largest age of a neighbour's plan used [s]"),
    "plan_missing_fraction": (pa.float64(), "share of (period, vehicle, neighbour) without plan"),
}
"""Every metric of a run (docs/design.md, "Metrics and gates"), deterministic for its inputs:
the same bits wherever it flies. (The agents' step times are not among them: they measure the
machine.)"""

PROVENANCE_COLUMNS: dict[str, tuple[pa.DataType, str]] = {
    "wall_s": (pa.float64(), "wall time of its last flight [s]"),
    "worker": (pa.string(), "the worker that flew it last (Dask address, or host:pid)"),
    "version": (pa.string(), "the code's version (package version +g commit, .dirty)"),
}

GATE_COLUMNS: dict[str, tuple[pa.DataType, str]] = {
    "learning_ratio": (pa.float64(), "formation RMS over the learning-off run's, same inputs"),
    "gates_failed": (pa.list_(pa.string()), "the suite's gates it misses, by name"),
}
"""Only in results.parquet: they compare runs with each other."""

_RENAMED = {"duration_s": "flown_s", "vehicles": "vehicle_count"}
"""Keys of a flown row (`fleetmpc.lockstep.suite.fly_row`) that are columns under another name, so
that no column is named like a scenario field a sweep can vary."""


def axis_type(axis: Axis) -> pa.DataType:
    """The column type of an axis's values: Arrow's for them all (integers and floats together
    are floats), a string of their TOML/JSON text when they have none in common."""
    try:
        return pa.array(list(axis.values)).type
    except (pa.ArrowInvalid, pa.ArrowTypeError):
        return pa.string()


def _axis_value(axis_types: dict[str, pa.DataType], path: str, value: Any) -> Any:
    if axis_types[path] == pa.string() and not isinstance(value, str):
        return json.dumps(value)
    return value


def row_schema(axes: Sequence[Axis], *, gates: bool = False) -> pa.Schema:
    """The columns of a sweep's rows, in order; `gates`: with `GATE_COLUMNS` (the table)."""
    fields = [pa.field(n, t) for n, (t, _) in BASE_COLUMNS.items()]
    fields += [pa.field(a.path, axis_type(a)) for a in axes]
    groups = [OUTCOME_COLUMNS, CONTEXT_COLUMNS, METRIC_COLUMNS, PROVENANCE_COLUMNS]
    if gates:
        groups.append(GATE_COLUMNS)
    fields += [pa.field(n, t) for g in groups for n, (t, _) in g.items()]
    return pa.schema(fields)


class ResultStore:
    """A sweep's folder of results (module docstring)."""

    def __init__(self, folder: str | Path, axes: Sequence[Axis]) -> None:
        self.folder = Path(folder)
        self.runs = self.folder / "runs"
        self.table_path = self.folder / "results.parquet"
        self.axes = tuple(axes)
        self.schema = row_schema(axes)
        self._axis_types = {a.path: axis_type(a) for a in axes}

    def open(self, *, resume: bool) -> None:
        """Make the folder; without `resume`, refuse one that holds runs already. Sweeps away
        temporary files a killed sweep left."""
        if self.runs.is_dir() and not resume and any(self.runs.glob("*.parquet")):
            raise ConfigError(
                "--out",
                f"{self.folder} holds a sweep's results: --resume to complete it, or another --out",
            )
        self.runs.mkdir(parents=True, exist_ok=True)
        for tmp in self.runs.glob(".*.tmp"):
            tmp.unlink(missing_ok=True)

    def path_of(self, run_id: str) -> Path:
        return self.runs / f"{run_id}.parquet"

    def finished(self, run_ids: Sequence[str]) -> dict[str, str]:
        """Status ("ok" or "failed") of the runs among `run_ids` that have a file."""
        out = {}
        for run_id in run_ids:
            path = self.path_of(run_id)
            if path.is_file():
                status = pq.read_table(path, columns=["status"]).column("status")
                out[run_id] = str(status[0].as_py())
        return out

    def record(self, row: dict) -> dict:
        """The columns of a flown row (`fleetmpc.lockstep.sweep_run.fly_spec`, plus the engine's
        attempts, first_error and worker), by `self.schema`."""
        flat = {_RENAMED.get(k, k): v for k, v in row.items() if k != "values"}
        for path, value in (row.get("values") or {}).items():
            flat[path] = _axis_value(self._axis_types, path, value)
        return {name: flat.get(name) for name in self.schema.names}

    def write(self, row: dict) -> Path:
        """Write one run's row (`record`) to its file, whole or not at all."""
        table = pa.Table.from_pylist([self.record(row)], schema=self.schema)
        final = self.path_of(str(row["run_id"]))
        tmp = final.with_name(f".{final.name}.{os.getpid()}.tmp")
        pq.write_table(table, tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, final)
        return final

    def read(self, run_ids: Sequence[str]) -> pa.Table:
        """The rows of the runs among `run_ids` that have a file, in the order of `run_ids`."""
        tables = []
        for run_id in run_ids:
            path = self.path_of(run_id)
            if not path.is_file():
                continue
            table = pq.read_table(path)
            try:
                tables.append(table.select(self.schema.names).cast(self.schema))
            except (KeyError, pa.ArrowInvalid, pa.ArrowTypeError) as e:
                raise ConfigError(str(path), f"does not fit this sweep's columns: {e}") from None
        if not tables:
            return self.schema.empty_table()
        return pa.concat_tables(tables)

    def other_runs(self, run_ids: Sequence[str]) -> int:
        """Files of runs that are not among `run_ids` (another sweep's, in the same folder)."""
        wanted = set(run_ids)
        return sum(1 for p in self.runs.glob("*.parquet") if p.stem not in wanted)

    def write_table(self, rows: Sequence[dict]) -> Path:
        """Write the sweep's table (`OUT/results.parquet`: the rows with `GATE_COLUMNS`), whole
        or not at all."""
        table = pa.Table.from_pylist(list(rows), schema=row_schema(self.axes, gates=True))
        tmp = self.table_path.with_name(f".{self.table_path.name}.tmp")
        pq.write_table(table, tmp)
        os.replace(tmp, self.table_path)
        return self.table_path
