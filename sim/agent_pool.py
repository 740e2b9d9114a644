"""The lockstep simulation's agents, stepped in this process or shared among worker processes.

`fleetmpc sim --jobs J` hands each of J worker processes a share of the fleet's agents for the
whole run (vehicle i to worker i mod J): each worker builds its agents once, and every period
steps them on the inputs the simulation sends and returns what they decided. The agents are
deterministic and their inputs cross the pipe bit for bit (pickled float64), so a run's figures
are the same for every J; only the step times differ. With J = 1 the agents step here, without
workers. A worker that loses its pipe (the simulation ended or died) exits.
"""

import contextlib
import multiprocessing as mp
import time
from collections.abc import Sequence
from multiprocessing.connection import Connection

from fleetmpc.onboard.agent_feed import agent_for
from fleetmpc.onboard.core.agent import Agent, AgentInput, AgentOutput
from fleetmpc.scenario import Scenario

__all__ = ["AgentPool", "Stepped", "build_agents"]

Interest = tuple[tuple[float, float], float, frozenset[int]] | None
Stepped = tuple[AgentOutput, float, Interest]
"""What one agent's period gives: its output, its step time [ms] and its plan-bus interest."""


def build_agents(
    scenario: Scenario, *, learning: bool = True, indices: Sequence[int] | None = None
) -> list[Agent]:
    """The Agents of the scenario's vehicles (all of them, or those at `indices`)."""
    vehicles = scenario.vehicles
    chosen = vehicles if indices is None else [vehicles[i] for i in indices]
    return [agent_for(scenario, v, learning=learning) for v in chosen]


def _step(agent: Agent, inp: AgentInput) -> Stepped:
    t0 = time.perf_counter_ns()
    out = agent.step(inp)
    return out, (time.perf_counter_ns() - t0) * 1e-6, agent.interest()


def _worker(conn: Connection, scenario: Scenario, indices: list[int], learning: bool) -> None:
    """A worker's life: build its agents, then step them on each batch of inputs received."""
    agents = build_agents(scenario, learning=learning, indices=indices)
    try:
        while True:
            inputs = conn.recv()
            if inputs is None:
                return
            conn.send([_step(a, inp) for a, inp in zip(agents, inputs, strict=True)])
    except (EOFError, KeyboardInterrupt, BrokenPipeError):
        return


class AgentPool:
    """The agents of `scenario`, stepped by `jobs` processes; a context manager that stops its
    workers on exit."""

    def __init__(self, scenario: Scenario, *, learning: bool, jobs: int = 1) -> None:
        n = len(scenario.vehicles)
        self.jobs = max(1, min(jobs, n))
        self._agents: list[Agent] = []
        self._shares: list[list[int]] = []
        self._workers: list[tuple[mp.process.BaseProcess, Connection]] = []
        if self.jobs == 1:
            self._agents = build_agents(scenario, learning=learning)
            return
        context = mp.get_context("spawn")  # (no state of this process leaks into a worker)
        self._shares = [list(range(j, n, self.jobs)) for j in range(self.jobs)]
        try:
            for share in self._shares:
                ours, theirs = context.Pipe()
                process = context.Process(
                    target=_worker,
                    args=(theirs, scenario, share, learning),
                    name="fleetmpc-sim-worker",
                    daemon=True,
                )
                process.start()
                theirs.close()
                self._workers.append((process, ours))
        except BaseException:
            self.close()
            raise

    def step(self, inputs: Sequence[AgentInput]) -> list[Stepped]:
        """Step every agent (in vehicle order) on its input; return what each decided."""
        if not self._workers:
            return [_step(a, inp) for a, inp in zip(self._agents, inputs, strict=True)]
        for (_, conn), share in zip(self._workers, self._shares, strict=True):
            conn.send([inputs[i] for i in share])
        results: list[Stepped | None] = [None] * len(inputs)
        for (process, conn), share in zip(self._workers, self._shares, strict=True):
            try:
                batch = conn.recv()
            except (EOFError, OSError):
                raise RuntimeError(
                    f"simulation worker {process.pid} exited (code {process.exitcode})"
                ) from None
            for i, stepped in zip(share, batch, strict=True):
                results[i] = stepped
        return results  # type: ignore[return-value]

    def close(self) -> None:
        """Stop the workers (idempotent)."""
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
