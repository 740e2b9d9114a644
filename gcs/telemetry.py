"""One telemetry path: a fleet run as one frozen sample per control period, into sinks.

The lockstep simulation and the live ground station both describe a run as `PeriodSample`s, one
per control period (every vehicle's pose, command, first correction c_0, learned β, QP status,
step time, plan, neighbour plan ages and setpoint rate; the target and the slots; the minimum
separation known so far; the first agent's target prediction and the ground side's), and hand
them to `TelemetrySink`s: opened with the run's constants, given samples and events, flushed,
told the facts of the run's end, closed. A sink is chosen by URL, as the links are:

- ``memory:`` keeps the samples; `MemorySink.record` stacks them into the `FlightRecord` the
  metrics and the figures read;
- ``rrd:PATH`` writes a Rerun recording; a Rerun viewer's gRPC URL
  (``rerun+http://HOST:PORT/proxy``) streams to that viewer; ``spawn:`` starts a local viewer
  (`fleetmpc.gcs.recording` holds the entity layout).

So a `sim --rrd` recording and an `up` recording are written by the same code from the same
type: the same entities, read back into the same record (`fleetmpc.gcs.rrd_reader`).
"""

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple, Protocol

import numpy as np

from fleetmpc.errors import ConfigError
from fleetmpc.gcs import blueprint, recording
from fleetmpc.gcs.record import PERIOD_FIELDS, FlightRecord, LiveRows, RunConstants, period_rows
from fleetmpc.onboard.core.target_watch import REACQUIRING, TRACKING

__all__ = [
    "FLUSH_S",
    "MemorySink",
    "PeriodSample",
    "RerunSink",
    "TargetFix",
    "TelemetrySink",
    "add_telemetry_argument",
    "open_sink",
    "record_of",
    "samples_of",
    "target_state_event",
    "write_recording",
]


FLUSH_S = 4.0
"""Default seconds of flight between two flushes of a run's sinks (a live ground station's and
the lockstep simulation's): 20 control periods of the paper's 0.2 s (`fleetmpc bench
--gcs-logging` compares intervals)."""


class TargetFix(NamedTuple):
    """A target observation as the fleet received it (before any filter)."""

    t_ns: int
    """Its time on the fleet clock [ns]."""
    north_m: float
    east_m: float


def target_state_event(vehicle_id: int, state: str) -> tuple[str, str]:
    """The level and text of the event that a vehicle's target state changed to `state`
    (tracking, predicting, holding, reacquiring: docs/design.md, "Target lost")."""
    level = "INFO" if state in (TRACKING, REACQUIRING) else "WARN"
    return level, f"UAV {vehicle_id}: target {state}"


@dataclass(frozen=True, eq=False)
class PeriodSample:
    """One control period of a fleet of N vehicles (horizon M)."""

    t_ns: int
    """The period's time on the fleet clock [ns]."""
    truth: np.ndarray
    """Each vehicle's pose (N, 3): North, East [m], yaw [rad]."""
    target: np.ndarray
    """The target's position (2,) [m]."""
    target_velocity: np.ndarray
    """The target's velocity (2,) [m/s]."""
    slots: np.ndarray
    """Each vehicle's slot (N, 2) [m], from the true target."""
    slot_offsets_world: np.ndarray
    """Each slot's offset from the formation centre (N, 2) [m]."""
    command: np.ndarray
    """Each vehicle's command (N, 2): speed [m/s], yaw rate [rad/s]."""
    c: np.ndarray
    """Each vehicle's first correction c_0 (N, 2) (a live run knows only its norm: (|c_0|, 0))."""
    beta: np.ndarray
    """Each vehicle's learned (a_V, a_w, d_x, d_y) (N, 4)."""
    beta_truth: np.ndarray
    """Each vehicle's true (a_V, a_w, wind North, wind East) (N, 4)."""
    qp_ok: np.ndarray
    """Each vehicle's QP status (N,): True when it solved and passed its checks."""
    step_time_ms: np.ndarray
    """Each agent's step time (N,) [ms]."""
    min_separation_m: float
    """The smallest distance between two vehicles of the run up to this period [m]."""
    plans: np.ndarray
    """Each vehicle's planned positions (N, M + 1, 2) [m]; NaN where it has none."""
    plan_age_s: np.ndarray
    """Age of each other vehicle's plan as vehicle i sees it (N, N - 1) [s], fleet order."""
    setpoint_rate_hz: np.ndarray
    """Each vehicle's setpoint rate (N,) [Hz]."""
    target_prediction: np.ndarray
    """The first agent's prediction of the target's position at the end of its horizon (2,)
    [m]; NaN where it has none (a live run: the agents do not send it)."""
    target_path: np.ndarray | None = None
    """The ground side's prediction of the target over the horizon from this period's time
    (M + 1, 2) [m]; None before its first target observation."""


def record_of(constants: RunConstants, samples: Sequence[PeriodSample], **extra) -> FlightRecord:
    """The FlightRecord of consecutive samples (its minimum separation the last one's);
    `extra`: FlightRecord fields samples do not carry (what the plan bus did)."""
    if not samples:
        raise ValueError("no samples")
    arrays = {name: np.array([getattr(s, name) for s in samples]) for name in PERIOD_FIELDS}
    return FlightRecord(
        t_s=np.array([s.t_ns for s in samples], dtype=np.int64) * 1e-9,
        **arrays,
        min_separation_m=samples[-1].min_separation_m,
        **constants.as_fields(),
        **extra,
    )


def live_rows_of(samples: Sequence[PeriodSample]) -> LiveRows:
    """Plans, plan ages, setpoint rates and the ground side's target predictions of the samples
    (NaN rows where a sample has no prediction)."""
    paths = [s.target_path for s in samples]
    shape = next((np.shape(p) for p in paths if p is not None), (1, 2))
    return LiveRows(
        plans=np.array([s.plans for s in samples]),
        setpoint_rate_hz=np.array([s.setpoint_rate_hz for s in samples]),
        plan_age_s=np.array([s.plan_age_s for s in samples]),
        target_path=np.array([np.full(shape, np.nan) if p is None else p for p in paths]),
    )


def samples_of(rec: FlightRecord, live: LiveRows) -> list[PeriodSample]:
    """The samples of a record's periods and the live rows of the same periods."""
    k = len(rec.t_s)
    rows = {name: period_rows(rec, name) for name in PERIOD_FIELDS}
    known_path = np.isfinite(live.target_path).all(axis=(1, 2))
    out = []
    for j in range(k):
        out.append(
            PeriodSample(
                t_ns=round(float(rec.t_s[j]) * 1e9),
                **{name: rows[name][j] for name in PERIOD_FIELDS},
                min_separation_m=rec.min_separation_m,
                plans=live.plans[j],
                setpoint_rate_hz=live.setpoint_rate_hz[j],
                target_path=live.target_path[j] if known_path[j] else None,
            )
        )
    return out


class TelemetrySink(Protocol):
    """Where a run's samples and events go."""

    def open(self, constants: RunConstants, run_info: dict) -> None:
        """Start a run: its constants and the facts about it (JSON-able)."""
        ...

    def log(self, samples: Sequence[PeriodSample]) -> None:
        """The next periods of the run, in order."""
        ...

    def event(self, t_ns: int, level: str, text: str) -> None:
        """An event at t_ns: level "INFO" or "WARN"."""
        ...

    def observe(self, observations: Sequence[TargetFix]) -> None:
        """Target observations as the fleet received them, each at its own time."""
        ...

    def flush(self) -> None:
        """Pass on what was logged so far (a live viewer shows it)."""
        ...

    def finish(self, facts: dict) -> None:
        """Facts about the run known only at its end (JSON-able: `network`, what the plan bus
        did), before `close`."""
        ...

    def close(self) -> None:
        """End the run: everything logged is passed on."""
        ...


class MemorySink:
    """Keeps a run's samples and events."""

    def __init__(self) -> None:
        self.constants: RunConstants | None = None
        self.run_info: dict = {}
        self.samples: list[PeriodSample] = []
        self.events: list[tuple[int, str, str]] = []
        self.observations: list[TargetFix] = []
        self.run_end: dict = {}

    def open(self, constants: RunConstants, run_info: dict) -> None:
        self.constants, self.run_info = constants, dict(run_info)

    def log(self, samples: Sequence[PeriodSample]) -> None:
        self.samples.extend(samples)

    def event(self, t_ns: int, level: str, text: str) -> None:
        self.events.append((t_ns, level, text))

    def observe(self, observations: Sequence[TargetFix]) -> None:
        self.observations.extend(observations)

    def flush(self) -> None:
        pass

    def finish(self, facts: dict) -> None:
        self.run_end = dict(facts)

    def close(self) -> None:
        pass

    def record(self, **extra) -> FlightRecord:
        """The FlightRecord of every sample so far (`record_of`), with the run's end facts."""
        if self.constants is None:
            raise RuntimeError("the sink was never opened")
        return record_of(self.constants, self.samples, **{**self.run_end, **extra})


class RerunSink:
    """A Rerun recording (a `.rrd` file, a viewer, or both): samples are kept until `flush`,
    which logs the map of the new periods, each at its own time; the time series, the
    flight_record rows and the QP events go out every `series_every` flushes that had new
    periods, and at `close`, which also sends the blueprint again with the map fixed on the
    whole flight (`recording.show_whole_flight`). A logging call costs per entity, not per row,
    so bigger slices cost less per period."""

    def __init__(
        self,
        *,
        path: str | Path | None = None,
        viewer_url: str | None = None,
        spawn_viewer: bool = False,
        series_every: int = 1,
        recording_id: str | None = None,
    ) -> None:
        if path is None and viewer_url is None and not spawn_viewer:
            raise ValueError("a Rerun sink needs a file, a viewer URL or a spawned viewer")
        self._target = {
            "path": path,
            "viewer_url": viewer_url,
            "spawn_viewer": spawn_viewer,
            "recording_id": recording_id,
        }
        self.series_every = max(1, int(series_every))
        self.stream = None
        self._constants: RunConstants | None = None
        self._map: list[PeriodSample] = []
        """Samples whose map is not logged yet, after the last logged one (its trail's start)."""
        self._series: list[PeriodSample] = []
        """Samples whose time series and flight_record rows are not logged yet."""
        self._last: PeriodSample | None = None
        self._series_started = False
        self._flushes = 0
        self._events: list[tuple[int, str, str]] = []
        self._observations: list[TargetFix] = []
        self._extent = recording.MapExtent()

    def open(self, constants: RunConstants, run_info: dict) -> None:
        self._constants = constants
        self.stream = recording.open_recording(vehicle_ids=constants.vehicle_ids, **self._target)
        recording.log_meta(self.stream, constants, run_info=run_info)
        blueprint.log_statics(self.stream, constants.vehicle_ids)
        self.stream.flush(timeout_sec=0)

    def log(self, samples: Sequence[PeriodSample]) -> None:
        self._map.extend(samples)
        self._series.extend(samples)

    def event(self, t_ns: int, level: str, text: str) -> None:
        self._events.append((t_ns, level, text))

    def observe(self, observations: Sequence[TargetFix]) -> None:
        self._observations.extend(observations)

    def _send(self, *, series: bool) -> None:
        events, self._events = self._events, []
        recording.log_events(self.stream, events)
        observations, self._observations = self._observations, []
        recording.log_target_observations(self.stream, observations)
        if self._map:
            # From the last period logged, when there is one: the trail's first step starts there.
            head = [self._last] if self._last is not None else []
            rec = record_of(self._constants, head + self._map)
            recording.log_map(self.stream, rec, live_rows_of(self._map), head=bool(head))
            self._extent.add(rec)
            self._last, self._map = self._map[-1], []
        if series and self._series:
            rec = record_of(self._constants, self._series)
            run_start = not self._series_started
            recording.log_series(
                self.stream,
                rec,
                live_rows_of(self._series),
                run_start=run_start,
                plan_stale_s=self._constants.plan_stale_s,
            )
            self._series_started, self._series = True, []

    def flush(self) -> None:
        if self.stream is None:
            return
        new = bool(self._map)
        self._flushes += new
        self._send(series=new and self._flushes % self.series_every == 0)
        self.stream.flush(timeout_sec=0)

    def finish(self, facts: dict) -> None:
        if self.stream is not None:
            recording.log_run_end(self.stream, facts)

    def close(self) -> None:
        if self.stream is None:
            return
        self._send(series=True)
        recording.show_whole_flight(self.stream, self._constants.vehicle_ids, self._extent)
        self.stream.flush()
        self.stream.disconnect()
        self.stream = None


def add_telemetry_argument(parser) -> None:
    """The ``--telemetry URL`` option of a command that runs a fleet (repeatable)."""
    parser.add_argument(
        "--telemetry",
        metavar="URL",
        action="append",
        default=[],
        help="also send the run to this sink: rrd:PATH, a Rerun viewer's rerun+http://HOST:PORT"
        "/proxy, spawn: (a local viewer), memory:; repeatable",
    )


def open_sink(url: str, *, series_every: int = 1) -> TelemetrySink:
    """The sink a URL names: ``memory:``, ``rrd:PATH``, ``rerun+http://HOST:PORT/proxy`` (a
    running viewer) or ``spawn:`` (a local viewer)."""
    if url == "memory:":
        return MemorySink()
    if url.startswith("rrd:") and len(url) > 4:
        return RerunSink(path=url[4:], series_every=series_every)
    if url.startswith(("rerun+http://", "rerun+https://")):
        return RerunSink(viewer_url=url, series_every=series_every)
    if url == "spawn:":
        return RerunSink(spawn_viewer=True, series_every=series_every)
    raise ConfigError(
        "telemetry",
        f"{url!r} is not a sink URL (memory:, rrd:PATH, rerun+http://HOST:PORT/proxy, spawn:)",
    )


def write_recording(
    rec: FlightRecord,
    path: str | Path,
    *,
    recording_id: str | None = None,
    run_info: dict | None = None,
) -> str:
    """Write a FlightRecord on its own (no plans, setpoint rates or ground-side target
    predictions) to an `.rrd` file; the recording's id."""
    sink = RerunSink(path=path, recording_id=recording_id)
    sink.open(RunConstants.of(rec), run_info or {})
    rid = sink.stream.get_recording_id()
    sink.log(samples_of(rec, LiveRows.blank(*rec.truth.shape[:2])))
    if rec.network is not None:
        sink.finish({"network": rec.network})
    sink.close()
    return rid
