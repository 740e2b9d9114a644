"""`fleetmpc bench --gcs-logging`: what the ground station's Rerun logging costs per control step.

One process, side by side on the same machine:

1. a lockstep run of the scenario, after a warm-up run (its agent step times are the
   reference: the control step);
2. a `GroundStation` fed what a live ground station would receive from that run (each vehicle's
   position, plan and status every period, the target's observation), flushed every `P`
   periods, as `fleetmpc gcs --flush-s F` flushes every F / period periods at any speed
   (`--flush-s F [F ...]`, default 1, 2 and 4 s of flight; the time series every
   `series_every` flushes, as `--series-flush-s` makes them): once without a recording and once
   into an `.rrd` file, in alternating pairs.

Each flush is timed from outside, and the process's CPU time over the whole feed (every thread:
the Rerun SDK encodes and writes in threads of its own after a call returns). Logging's cost is
the difference between the two runs of a pair, per vehicle-period (one vehicle's data of one
control period), next to the agent step median (the target is at most 10 % of it). Wall-clock
and CPU times; nothing is asserted.
"""

import argparse
import json
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fleetmpc.errors import FleetMpcError
from fleetmpc.gcs.ground_station import series_every
from fleetmpc.gcs.record import FlightRecord
from fleetmpc.gcs.station import GroundStation
from fleetmpc.gcs.telemetry import RerunSink
from fleetmpc.lockstep.flight import run_lockstep
from fleetmpc.protocol.messages import (
    TARGET_ID,
    LearnedParams,
    NeighbourPlanAge,
    PlanMessage,
    PlanStatus,
    StatusMessage,
    TargetObservation,
    VehicleStatus,
)
from fleetmpc.protocol.plan import Plan
from fleetmpc.scenario import load_scenario

__all__ = ["TARGET_FRACTION", "PeriodMessages", "period_messages", "receive_period", "run"]

TARGET_FRACTION = 0.10
"""Logging per vehicle-period at most this fraction of the agent step median."""


@dataclass(frozen=True)
class PeriodMessages:
    """What a ground station receives in one period of a run that flew a given FlightRecord."""

    poses: list[tuple[int, float, float, float, float]]
    """(vehicle id, t [s], north [m], east [m], yaw [rad]) per vehicle: its telemetry."""
    plans: list[PlanMessage]
    """Each vehicle's plan (states held at its pose, inputs at its command)."""
    statuses: list[StatusMessage]
    """Each vehicle's status (its learned parameters)."""
    target: TargetObservation
    """The target's observation (its true position)."""


def period_messages(
    rec: FlightRecord,
    k: int,
    *,
    period_ns: int,
    horizon: int,
    plan_age_ns: int | None = None,
    setpoint_rate_hz: float = 0.0,
) -> PeriodMessages:
    """The messages of period `k` of `rec`, as a live fleet that flew exactly `rec` sends them;
    each status reports every neighbour's plan `plan_age_ns` old (None: no ages) and the
    setpoint rate `setpoint_rate_hz`."""
    stamp = k * period_ns
    poses, plans, statuses = [], [], []
    for i, vid in enumerate(rec.vehicle_ids):
        poses.append((vid, float(rec.t_s[k]), *map(float, rec.truth[k, i])))
        plan = Plan(
            vehicle_id=vid,
            stamp_ns=stamp,
            period_ns=period_ns,
            states=np.tile(rec.truth[k, i], (horizon + 1, 1)),
            inputs=np.tile(rec.command[k, i], (horizon, 1)),
        )
        status = PlanStatus(
            qp_fallback=not rec.qp_ok[k, i],
            first_c_norm=float(np.linalg.norm(rec.c[k, i])),
            solve_time_us=round(rec.step_time_ms[k, i] * 1e3),
        )
        plans.append(PlanMessage(seq=k, plan=plan, status=status))
        ages = ()
        if plan_age_ns is not None:
            ages = tuple(NeighbourPlanAge(o, plan_age_ns) for o in rec.vehicle_ids if o != vid)
        vehicle = VehicleStatus(
            beta=LearnedParams(*map(float, rec.beta[k, i])),
            neighbour_plan_ages=ages,
            setpoint_rate_hz=setpoint_rate_hz,
        )
        statuses.append(StatusMessage(sender_id=vid, seq=k, stamp_ns=stamp, status=vehicle))
    north, east = map(float, rec.target[k])
    target = TargetObservation(
        sender_id=TARGET_ID, seq=k, stamp_ns=stamp, north_m=north, east_m=east
    )
    return PeriodMessages(poses=poses, plans=plans, statuses=statuses, target=target)


def receive_period(gs: GroundStation, rec: FlightRecord, k: int, **status) -> None:
    """What the ground station receives in period k of a run that flew `rec` (`status`: the
    plan ages and setpoint rate the statuses report, see `period_messages`)."""
    horizon = gs.scenario.controller.horizon
    msgs = period_messages(rec, k, period_ns=gs.live.period_ns, horizon=horizon, **status)
    for pose in msgs.poses:
        gs.live.add_pose(*pose)
    for message in (*msgs.plans, *msgs.statuses, msgs.target):
        gs.inbox.put(message)


def _feed(gs: GroundStation, rec: FlightRecord, *, periods_per_flush: int) -> list[float]:
    """The ground station (its sinks open) fed the run period by period, flushed every
    `periods_per_flush`, its sinks closed (so Rerun has encoded and written everything) and its
    metrics computed, as a ground station ends. The wall time of each flush [ms], the closing
    in the last."""
    flush_ms = []
    for k in range(len(rec.t_s)):
        receive_period(gs, rec, k)
        last = k == len(rec.t_s) - 1
        if last or (k + 1) % periods_per_flush == 0:
            t0 = time.perf_counter()
            gs.flush(final=last)
            if last:
                gs.close_sinks()
            flush_ms.append((time.perf_counter() - t0) * 1e3)
    gs.metrics()
    return flush_ms


def _logging(
    rec: FlightRecord,
    scenario,
    *,
    periods_per_flush: int,
    series_every: int,
    rrd: Path,
    repeats: int = 3,
) -> dict:
    """Flush times with and without a recording, and the CPU time of the whole process with
    logging less without it: `repeats` pairs run alternately, medians compared (a single pair's
    difference is noisy, even negative). As in `fleetmpc gcs`, the recording is opened, with its
    meta and statics, before the flight: that is not timed."""
    cpu_without, cpu_with, wall_without, wall_with = [], [], [], []
    flush_without, flush_with = [], []

    def station() -> GroundStation:
        return GroundStation(scenario, speed=1.0, duration_s=float(rec.t_s[-1]))

    for _ in range(repeats):
        gs = station()
        t0 = time.process_time()
        flush_without += (ms := _feed(gs, rec, periods_per_flush=periods_per_flush))
        cpu_without.append(time.process_time() - t0)
        wall_without.append(sum(ms))
        gs = station()
        gs.open_sinks([RerunSink(path=rrd, series_every=series_every)])  # before the flight
        t0 = time.process_time()
        flush_with += (ms := _feed(gs, rec, periods_per_flush=periods_per_flush))
        cpu_with.append(time.process_time() - t0)
        wall_with.append(sum(ms))
    vehicle_periods = len(rec.t_s) * len(scenario.vehicles)
    return {
        "periods_per_flush": periods_per_flush,
        "series_every": series_every,
        "flushes": len(flush_with) // repeats,
        "repeats": repeats,
        "flush_median_ms": float(np.median(flush_with)),
        "flush_p99_ms": float(np.percentile(flush_with, 99)),
        "flush_without_median_ms": float(np.median(flush_without)),
        "ms_per_vehicle_period": float(np.median(wall_with) - np.median(wall_without))
        / vehicle_periods,
        "cpu_ms_per_vehicle_period": float(np.median(cpu_with) - np.median(cpu_without))
        * 1e3
        / vehicle_periods,
        "rrd_kib": rrd.stat().st_size / 1024,
    }


def run(args: argparse.Namespace) -> int:
    for name, values in (("--flush-s", args.flush_s), ("--series-flush-s", [args.series_flush_s])):
        bad = [v for v in values if not (v > 0 and np.isfinite(v))]
        if bad:
            raise FleetMpcError(f"{name}: must be > 0, got {bad[0]:g}")
    sc = load_scenario(args.scenario)
    run_lockstep(sc)  # warm-up: the first run in a process pays for first calls
    rec = run_lockstep(sc)
    step_median_ms = float(np.median(rec.step_time_ms))
    period_s = sc.controller.period_ns * 1e-9
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for flush_s in args.flush_s:
            periods = max(1, round(flush_s / period_s))
            row = _logging(
                rec,
                sc,
                periods_per_flush=periods,
                series_every=series_every(flush_s=flush_s, series_flush_s=args.series_flush_s),
                rrd=Path(tmp) / f"{periods}.rrd",
            )
            row |= {"flush_s": flush_s}
            for key in ("", "cpu_"):
                fraction = row[f"{key}ms_per_vehicle_period"] / step_median_ms
                row[f"{key}fraction_of_agent_step"] = fraction
            rows.append(row)
    result = {
        "scenario": sc.name,
        "vehicles": len(sc.vehicles),
        "periods": len(rec.t_s),
        "agent_step_median_ms": step_median_ms,
        "target_fraction": TARGET_FRACTION,
        "gcs_logging": rows,
    }
    print(
        f"fleetmpc bench --gcs-logging: scenario {sc.name!r}, {len(sc.vehicles)} vehicles, "
        f"{len(rec.t_s)} periods; agent step median {step_median_ms:.3f} ms (same process)"
    )
    print(
        f"  {'flush every (series every)':33s} {'flush ms':>16s} {'without':>8s}   "
        f"{'logging ms / vehicle-period (of agent step)':>45s}"
    )
    print(f"  {'':33s} {'median':>8s} {'p99':>7s} {'median':>8s}   {'wall':>14s} {'CPU':>14s}")
    for r in rows:
        name = f"{r['flush_s']:g} s ({r['periods_per_flush']} periods) ({r['series_every']})"
        cells = [
            f"{r[key]:.3f} ({100 * r[key] / step_median_ms:.0f}%)"
            for key in ("ms_per_vehicle_period", "cpu_ms_per_vehicle_period")
        ]
        print(
            f"  {name:33s} {r['flush_median_ms']:>8.2f} {r['flush_p99_ms']:>7.2f} "
            f"{r['flush_without_median_ms']:>8.2f}   " + " ".join(f"{c:>14s}" for c in cells)
        )
    print(
        "  (wall: the flushes with a recording less without, over the run's vehicle-periods;"
        " CPU: every thread of the process, Rerun's included, with less without)"
    )
    print(f"  (target: logging per vehicle-period <= {100 * TARGET_FRACTION:.0f} % of the step)")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0
