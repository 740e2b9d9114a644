"""The lockstep simulation's fleet side: the agents with their plan buses, in shares that step in
this process or in worker processes.

A `Share` holds some of the fleet's vehicles: each one's agent, its plan bus (on the share's own
in-memory hub, behind the vehicle's injected faults if the run has any) and its target feed.
The simulation hands each share the payloads the fleet published (plans and target
observations, in publication order, each batch at the fleet time it arrives), which the share
delivers to its buses as one hub for the whole fleet would: through the faults and the receive
rules, never to the sender's own bus. Then the share steps its agents on their measurements and
what their buses hold, publishes their plans on its hub, and hands back what each decided and
the payloads published. So the deliveries of a period (N senders to N receivers), like the
steps, are divided among the shares.

`fleetmpc sim --jobs J` gives each of J worker processes one share for the whole run (vehicle i
to worker i mod J). Every bus receives the same payloads at the same fleet times and every agent
the same inputs, bit for bit, whatever J, so a run's figures are the same for every J; only the
step times differ. With J = 1 the one share steps here, without workers. A worker that loses its
pipe (the simulation ended or died) exits.
"""

import contextlib
import multiprocessing as mp
import time
from collections.abc import Sequence
from multiprocessing.connection import Connection

import numpy as np

from fleetmpc.bus.faults import FaultLayer, FaultSchedule
from fleetmpc.bus.memory import InMemoryPlanBus, MemoryHub
from fleetmpc.onboard.agent_feed import TargetFeed, agent_for, listen_for
from fleetmpc.onboard.core.agent import Agent, AgentInput, AgentOutput
from fleetmpc.onboard.runner import RunnerSettings
from fleetmpc.scenario import Scenario

__all__ = ["AgentPool", "Published", "Share", "Stepped", "build_agents"]

Stepped = tuple[AgentOutput, float]
"""What one agent's period gives: its output and its step time [ms]."""
Published = list[tuple[str, bytes, int | None]]
"""Payloads in publication order: key, payload and the sender's vehicle index (None: from
outside the fleet's vehicles, such as the target's observations)."""
COUNTED = ("published", "accepted", "duplicates", "out_of_order", "filtered")
"""The bus counters a run's network report sums."""


def build_agents(
    scenario: Scenario, *, learning: bool = True, indices: Sequence[int] | None = None
) -> list[Agent]:
    """The Agents of the scenario's vehicles (all of them, or those at `indices`)."""
    vehicles = scenario.vehicles
    chosen = vehicles if indices is None else [vehicles[i] for i in indices]
    return [agent_for(scenario, v, learning=learning) for v in chosen]


class Share:
    """The vehicles at `indices` of the scenario's fleet: their agents, buses and target feeds."""

    def __init__(
        self,
        scenario: Scenario,
        indices: Sequence[int],
        *,
        learning: bool,
        faults: FaultSchedule | None,
        seed: int,
    ) -> None:
        self.indices = list(indices)
        self._now_ns = 0
        self._agents = build_agents(scenario, learning=learning, indices=self.indices)
        self._hub = MemoryHub(scenario.name, deliver_immediately=False)
        ids = scenario.vehicle_ids
        self._buses = [
            InMemoryPlanBus(
                self._hub,
                fleet=scenario.name,
                vehicle_id=ids[i],
                faults=None
                if faults is None
                else FaultLayer(faults, vehicle_id=ids[i], clock=self._clock, seed=seed),
            )
            for i in self.indices
        ]
        self._origin = {i: bus for i, bus in zip(self.indices, self._buses, strict=True)}
        """Each vehicle's bus by the vehicle's index: the origin of its payloads on the hub."""
        self._sender = {id(bus): i for i, bus in self._origin.items()}
        """The vehicle index of each bus (by its id), to name the sender of what it published."""
        self._settings = RunnerSettings(period_ns=scenario.controller.period_ns)
        """The plan and target ages a live runner accepts, which the agents here accept too."""
        self._targets = [
            TargetFeed(bus, max_age_ns=self._settings.target_max_age_ns) for bus in self._buses
        ]

    def _clock(self) -> int:
        return self._now_ns

    def deliver(self, now_ns: int, payloads: Published) -> None:
        """Hand payloads published in the fleet to the buses, at fleet time `now_ns`."""
        self._now_ns = now_ns
        for key, payload, sender in payloads:
            self._hub.dispatch(key, payload, origin=self._origin.get(sender))

    def step(
        self,
        now_ns: int,
        measurements: Sequence[np.ndarray],
        known: Sequence[np.ndarray | None] | None = None,
    ) -> tuple[list[Stepped], Published]:
        """Step the agents on their vehicles' measurements (in the share's order), and in a
        known-model run on their truths (`known`); publish their plans; return what each
        decided and what was published."""
        self._now_ns = now_ns
        max_age_ns = self._settings.plan_max_age_ns
        stepped: list[Stepped] = []
        known = [None] * len(measurements) if known is None else known
        for agent, bus, feed, y, truth in zip(
            self._agents, self._buses, self._targets, measurements, known, strict=True
        ):
            observation, observed_ns = feed.take(now_ns)
            inp = AgentInput(
                stamp_ns=now_ns,
                measurement=y,
                target_observation=observation,
                target_stamp_ns=observed_ns,
                neighbour_plans=bus.latest_plans(now_ns, max_age_ns),
                known_beta=truth,
            )
            t0 = time.perf_counter_ns()
            out = agent.step(inp)
            stepped.append((out, (time.perf_counter_ns() - t0) * 1e-6))
            listen_for(agent, bus)
        for bus, (out, _) in zip(self._buses, stepped, strict=True):
            bus.publish_plan(out.plan)
        published = [(k, p, self._sender[id(origin)]) for k, p, origin in self._hub.take()]
        return stepped, published

    def report(self) -> list[tuple[dict[str, int], dict[str, int] | None]]:
        """Each bus's counters that a network report sums, and its faults' counts (None
        without faults), in the share's order."""
        return [
            (
                {name: getattr(counters, name) for name in COUNTED},
                None if bus.faults is None else dict(bus.faults.counts),
            )
            for bus, counters in ((bus, bus.counters()) for bus in self._buses)
        ]

    def close(self) -> None:
        for bus in self._buses:
            bus.close()


def _run(share: Share, calls: list[tuple]) -> object:
    """Make a batch of calls (method name, arguments...) on `share` in order; return what the
    last one returned."""
    result = None
    for name, *args in calls:
        result = getattr(share, name)(*args)
    return result


def _worker(conn: Connection, scenario: Scenario, indices: list[int], options: dict) -> None:
    """A worker's life: build its share, then run each batch of calls it is sent, answering
    with what the batch's last call returned."""
    share = Share(scenario, indices, **options)
    try:
        while (calls := conn.recv()) is not None:
            conn.send(_run(share, calls))
    except (EOFError, KeyboardInterrupt, BrokenPipeError):
        return
    finally:
        share.close()


def _pick(values: Sequence | None, indices: Sequence[int]) -> list | None:
    return None if values is None else [values[i] for i in indices]


def _lost(process: mp.process.BaseProcess) -> RuntimeError:
    """The error of a worker whose pipe broke, with its exit code once it is reaped."""
    process.join(timeout=5)
    return RuntimeError(f"simulation worker {process.pid} exited (code {process.exitcode})")


class AgentPool:
    """The fleet's agents in `jobs` shares; a context manager that stops its workers on exit.

    Deliveries are sent to the workers with the next call that needs an answer (one message
    each way per worker and period)."""

    def __init__(
        self,
        scenario: Scenario,
        *,
        learning: bool,
        jobs: int = 1,
        faults: FaultSchedule | None = None,
        seed: int | None = None,
    ) -> None:
        n = len(scenario.vehicles)
        self.jobs = max(1, min(jobs, n))
        options = {
            "learning": learning,
            "faults": faults,
            "seed": scenario.seed if seed is None else seed,
        }
        self._shares = [list(range(j, n, self.jobs)) for j in range(self.jobs)]
        self._here: Share | None = None
        self._workers: list[tuple[mp.process.BaseProcess, Connection]] = []
        self._pending: list[tuple] = []
        if self.jobs == 1:
            self._here = Share(scenario, self._shares[0], **options)
            return
        # Workers fork from a server process that started afresh and imported this module once
        # (and the main module, as spawned workers would): no state of this process leaks into
        # a worker, and none imports the agent's libraries again, in this pool or the next.
        context = mp.get_context("forkserver")
        context.set_forkserver_preload(["__main__", __name__])
        try:
            for share in self._shares:
                ours, theirs = context.Pipe()
                process = context.Process(
                    target=_worker,
                    args=(theirs, scenario, share, options),
                    name="fleetmpc-sim-worker",
                    daemon=True,
                )
                process.start()
                theirs.close()
                self._workers.append((process, ours))
        except BaseException:
            self.close()
            raise

    def _call(self, name: str, args: Sequence[tuple]) -> list:
        """Call `name` on every share (the k-th share with the k-th arguments), after the
        deliveries pending; return each share's answer."""
        batches = [[*self._pending, (name, *a)] for a in args]
        self._pending = []
        if self._here is not None:
            return [_run(self._here, batch) for batch in batches]
        for (process, conn), batch in zip(self._workers, batches, strict=True):
            try:
                conn.send(batch)
            except OSError:  # (a broken pipe: the worker is gone)
                raise _lost(process) from None
        answers = []
        for process, conn in self._workers:
            try:
                answers.append(conn.recv())
            except (EOFError, OSError):
                raise _lost(process) from None
        return answers

    def deliver(self, now_ns: int, payloads: Published) -> None:
        """Deliver payloads published in the fleet to every share's buses at `now_ns`."""
        if payloads:
            self._pending.append(("deliver", now_ns, payloads))

    def step(
        self,
        now_ns: int,
        measurements: Sequence[np.ndarray],
        known: Sequence[np.ndarray] | None = None,
    ) -> tuple[list[Stepped], Published]:
        """Step every agent (in vehicle order) on its measurement, and its truth in a
        known-model run; return what each decided, and the plans published, in vehicle order."""
        answers = self._call(
            "step",
            [
                (now_ns, [measurements[i] for i in share], _pick(known, share))
                for share in self._shares
            ],
        )
        published = [payload for _, payloads in answers for payload in payloads]
        published.sort(key=lambda payload: payload[2])  # (by sender; stable: its order is kept)
        return self._in_vehicle_order([outs for outs, _ in answers]), published

    def report(self) -> list[tuple[dict[str, int], dict[str, int] | None]]:
        """`Share.report` of every vehicle, in vehicle order (after the deliveries pending)."""
        return self._in_vehicle_order(self._call("report", [()] * self.jobs))

    def _in_vehicle_order(self, answers: Sequence[Sequence]) -> list:
        """The shares' per-vehicle answers (each in its share's order), in vehicle order."""
        rows: list = [None] * sum(len(share) for share in self._shares)
        for share, answer in zip(self._shares, answers, strict=True):
            for i, row in zip(share, answer, strict=True):
                rows[i] = row
        return rows

    def close(self) -> None:
        """Stop the workers (idempotent)."""
        if self._here is not None:
            self._here.close()
            self._here = None
        workers, self._workers = self._workers, []
        for _, conn in workers:
            with contextlib.suppress(BrokenPipeError, OSError):
                conn.send(None)
            conn.close()
        for process, _ in workers:
            process.join(timeout=5)
            if process.is_alive():
                process.kill()
                process.join()

    def __enter__(self) -> "AgentPool":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
