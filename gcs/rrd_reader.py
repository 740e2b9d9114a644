"""Rebuild a FlightRecord from a Rerun recording written by `fleetmpc.gcs.recording`.

Reads the `meta` and `flight_record` entities with rerun-sdk's chunk reader
(`rr.chunk.RrdReader(path).stream()`); each `flight_record` row is unpacked by
`fleetmpc.gcs.recording.record_layout`, the float64 arrays come back bit for bit, and the sample
times as `sim_time` nanoseconds * 1e-9 (exactly the lockstep's `t_s`). The run's minimum separation
is the newest row's `min_separation_known_m` (a live recording grows in slices); what the plan
bus did comes from the static `run_end`. A recording made before `flight_record` held the
agents' target prediction and plan ages reads back without them.
"""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import rerun as rr

from fleetmpc.errors import FleetMpcError
from fleetmpc.gcs.blueprint import TIMELINE
from fleetmpc.gcs.record import FlightRecord
from fleetmpc.gcs.recording import (
    LEGACY_RECORD_ARRAYS,
    MIN_SEPARATION_COLUMN,
    RECORD_COLUMN,
    record_layout,
)

__all__ = ["RecordingError", "RecordingRun", "read_recording"]

_META_ENTITY = "/meta"
_RECORD_ENTITY = "/flight_record"
_RUN_END_ENTITY = "/run_end"


class RecordingError(FleetMpcError):
    """A recording is missing, unreadable or not a fleetmpc flight recording."""


class RecordingRun:
    """A FlightRecord read back from a recording, with the run facts logged beside it."""

    def __init__(
        self, *, record: FlightRecord, run_info: dict, recording_id: str, run_end: dict
    ) -> None:
        self.record = record
        self.run_info = run_info
        """Facts logged when the recording opened."""
        self.recording_id = recording_id
        self.run_end = run_end
        """Facts logged when the run ended (`network` is also the record's)."""


def _data_columns(batch: pa.RecordBatch) -> dict[str, pa.Array]:
    out = {}
    for field, column in zip(batch.schema, batch.columns, strict=True):
        meta = field.metadata or {}
        if meta.get(b"rerun:kind") == b"data":
            out[meta[b"rerun:component"].decode()] = column
    return out


def _rows(column: pa.Array) -> list[np.ndarray]:
    return [np.asarray(row.values.to_numpy(zero_copy_only=False)) for row in column]


def read_recording(path: str | Path) -> RecordingRun:
    """Read a `.rrd` written through `fleetmpc.gcs.telemetry.RerunSink` back into a
    FlightRecord."""
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"{p}: no such recording")
    try:
        reader = rr.chunk.RrdReader(p)
        recordings = reader.recordings()
        chunks = list(reader.stream())
    except Exception as e:  # the reader raises plain exceptions on a corrupt file
        raise RecordingError(f"{p}: not a readable Rerun recording ({e})") from e
    found = _Found.of(chunks, p)
    t_ns, parts = _unpack(found, p)
    facts = _json(found.run_end, "run_end_json")
    record = _flight_record(found, t_ns, parts, facts)
    run_info = _json(found.meta, "run_info_json")
    rid = recordings[0].recording_id if recordings else ""
    return RecordingRun(record=record, run_info=run_info, recording_id=rid, run_end=facts)


def _json(columns: dict[str, pa.Array], name: str) -> dict:
    """The JSON object of a one-row text column, {} where the recording has none."""
    return json.loads(str(columns[name][0][0])) if name in columns else {}


@dataclasses.dataclass
class _Found:
    """A recording's fleetmpc entities, as stored: the meta and run-end columns, and each
    flight_record chunk's times [ns] and packed rows."""

    meta: dict[str, pa.Array] = dataclasses.field(default_factory=dict)
    run_end: dict[str, pa.Array] = dataclasses.field(default_factory=dict)
    times: list[np.ndarray] = dataclasses.field(default_factory=list)
    packed: list[pa.Array] = dataclasses.field(default_factory=list)

    @property
    def vehicle_ids(self) -> tuple[int, ...]:
        return tuple(int(v) for v in _rows(self.meta["vehicle_ids"])[0])

    @property
    def legacy(self) -> bool:
        """A recording made before the target's prediction and the plan ages were recorded."""
        return "prediction_horizon_periods" not in self.meta

    @classmethod
    def of(cls, chunks: list, p: Path) -> "_Found":
        """The fleetmpc entities of a recording's chunks (`p`: its file, for errors)."""
        found = cls()
        for chunk in chunks:
            if chunk.entity_path == _META_ENTITY:
                found.meta.update(_data_columns(chunk.to_record_batch()))
            elif chunk.entity_path == _RUN_END_ENTITY:
                found.run_end.update(_data_columns(chunk.to_record_batch()))
            elif chunk.entity_path == _RECORD_ENTITY:
                batch = chunk.to_record_batch()
                data = _data_columns(batch)
                if RECORD_COLUMN not in data:
                    raise RecordingError(f"{p}: a flight_record chunk has no {RECORD_COLUMN!r}")
                t = batch.column(batch.schema.get_field_index(TIMELINE))
                found.times.append(t.cast(pa.int64()).to_numpy())
                found.packed.append(data[RECORD_COLUMN])
        if not found.meta or not found.times:
            raise RecordingError(f"{p}: no fleetmpc flight record (meta / flight_record) in it")
        return found


def _unpack(found: _Found, p: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The periods' times [ns] in order, and each record array (K, ...) by its name."""
    t_ns = np.concatenate(found.times)
    order = np.argsort(t_ns, kind="stable")
    t_ns = t_ns[order]
    n, k = len(found.vehicle_ids), len(t_ns)
    legacy = found.legacy
    layout = record_layout(n, arrays=LEGACY_RECORD_ARRAYS) if legacy else record_layout(n)
    width = sum(int(np.prod(shape)) for _, shape in layout)
    flat = np.concatenate([c.flatten().to_numpy(zero_copy_only=False) for c in found.packed])
    if flat.size != k * width:
        raise RecordingError(f"{p}: flight_record rows are not {width} values for {n} vehicles")
    rows = flat.reshape(k, width)[order]
    parts: dict[str, np.ndarray] = {}
    at = 0
    for name, shape in layout:
        size = int(np.prod(shape))
        parts[name] = rows[:, at : at + size].reshape(k, *shape).copy()
        at += size
    return t_ns, parts


def _flight_record(
    found: _Found, t_ns: np.ndarray, parts: dict[str, np.ndarray], facts: dict
) -> FlightRecord:
    """The FlightRecord of the unpacked arrays and the recording's meta (an older recording,
    without the target's prediction and the plan ages, has None for them)."""
    meta, legacy, ids = found.meta, found.legacy, found.vehicle_ids

    def scalar(name: str) -> float:
        return float(_rows(meta[name])[0][0])

    return FlightRecord(
        scenario=str(meta["scenario"][0][0]),
        vehicle_ids=ids,
        t_s=t_ns * 1e-9,
        truth=parts["truth"],
        target=parts["target"],
        target_velocity=parts["target_velocity"],
        slots=parts["slots"],
        command=parts["command"],
        c=parts["c"],
        beta=parts["beta"],
        beta_truth=parts["beta_truth"],
        qp_ok=parts["qp_ok"].astype(bool),
        step_time_ms=parts["step_time_ms"],
        desired_distance_m=_rows(meta["desired_distance_m"])[0].reshape(len(ids), len(ids)),
        trail_m=scalar("trail_m"),
        slot_offsets_world=parts["slot_offsets_world"],
        min_separation_m=float(parts[MIN_SEPARATION_COLUMN][-1, 0]),
        speed_max_m_s=scalar("speed_max_m_s"),
        yaw_rate_max_rad_s=scalar("yaw_rate_max_rad_s"),
        d_safe_m=scalar("d_safe_m"),
        target_prediction=None if legacy else parts["target_prediction"],
        prediction_horizon_periods=0
        if legacy
        else int(_rows(meta["prediction_horizon_periods"])[0][0]),
        plan_age_s=None if legacy else parts["plan_age_s"],
        network=facts.get("network"),
    )
