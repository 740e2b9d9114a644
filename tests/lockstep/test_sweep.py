"""`fleetmpc sweep`: the grid's paths checked up front, run identities, rows written as runs
finish, --resume, time limits (a run hung inside a period killed, on the pool and on Dask), the
figures; and a real Dask scheduler with two workers as separate processes on loopback, one of
them killed mid-sweep, against the local process pool."""

import json
import multiprocessing
import os
import socket
import sys
import threading
from pathlib import Path

import psutil
import pyarrow.parquet as pq
import pytest
from helpers import ROOT, free_port, wait_until

from fleetmpc.cli import main
from fleetmpc.errors import ConfigError
from fleetmpc.lockstep import sweep_figures
from fleetmpc.lockstep.agent_pool import AgentPool
from fleetmpc.lockstep.run_process import fly_within
from fleetmpc.lockstep.sweep_grid import RunSpec, build_run, parse_vary, plan_runs, set_path
from fleetmpc.lockstep.sweep_run import fly_spec
from fleetmpc.lockstep.sweep_store import CONTEXT_COLUMNS, METRIC_COLUMNS

PAPER = str(ROOT / "scenarios" / "paper.toml")
WEDGE = str(ROOT / "scenarios" / "wedge-circle.toml")
NUMBERS = ["run_id", *CONTEXT_COLUMNS, *METRIC_COLUMNS]
"""The columns that must be the same bits wherever a run flies."""


def _plan(*vary: str, files=(PAPER,), **kwargs) -> list[RunSpec]:
    return plan_runs(list(files), [parse_vary(v) for v in vary], seeds=2, **kwargs)


def _refusal(*vary: str, **kwargs) -> str:
    with pytest.raises(ConfigError) as e:
        _plan(*vary, **kwargs)
    return str(e.value)


def test_the_grid_is_every_combination_in_table_order():
    runs = _plan("controller.horizon=4,6", "truth.actuator_lag_s=0.1,0.2", learning=(True, False))
    assert len(runs) == 2 * 2 * 2 * 2 and len({r.run_id for r in runs}) == 16
    assert [r.values for r in runs[:8:4]] == [
        {"controller.horizon": 4, "truth.actuator_lag_s": 0.1},
        {"controller.horizon": 4, "truth.actuator_lag_s": 0.2},
    ]
    assert [(r.learning, r.seed) for r in runs[:4]] == [
        (True, 7),
        (True, 8),
        (False, 7),
        (False, 8),
    ]
    sc, faults = build_run(runs[-1])
    assert sc.controller.horizon == 6 and faults is None
    assert {v.truth.actuator_lag_s for v in sc.vehicles} == {0.2}


def test_paths_address_tables_entries_and_the_fault_file():
    doc = {"controller": {"horizon": 5}, "vehicles": [{"id": 1}, {"id": 2, "truth": {"x": 1}}]}
    out = set_path(doc, "vehicles[*].truth.speed_effectiveness", 0.8)
    assert [v["truth"]["speed_effectiveness"] for v in out["vehicles"]] == [0.8, 0.8]
    assert out["vehicles"][1]["truth"]["x"] == 1 and "truth" not in doc["vehicles"][0]
    assert set_path(doc, "truth.wind.gust_amplitude_m_s", 0.1)["truth"] == {
        "wind": {"gust_amplitude_m_s": 0.1}
    }
    assert set_path(doc, "vehicles[1].slot_m", [0, 3])["vehicles"][1]["slot_m"] == [0, 3]
    (run,) = _plan(
        "faults[0].probability=0.1,0.6",
        fault_files=[ROOT / "faults" / "loss30.toml"],
    )[-1:]
    _, faults = build_run(run)
    assert faults.faults[0].probability == 0.6
    assert parse_vary("truth.wind.mean_m_s=[0.3, 0.0],[0.0, 0.1]").values == (
        [0.3, 0.0],
        [0.0, 0.1],
    )
    assert parse_vary("formation.pattern.kind=grid,ring").values == ("grid", "ring")


def test_bad_paths_and_values_are_refused_before_anything_flies():
    text = _refusal("controller.horizn=4,5")
    assert text.startswith("--vary controller.horizn: unknown field in ")
    assert "nearest: controller.horizon" in text
    assert "nearest: truth.actuator_lag_s" in _refusal("truth.actuator_lag=0.1,0.2")
    assert "nearest: faults[0].probability" in _refusal(
        "faults[0].probabilty=0.1", fault_files=[ROOT / "faults" / "loss30.toml"]
    )
    text = _refusal("controller.horizon=5,0")
    assert text.startswith("--vary controller.horizon=0: ")
    assert "controller.horizon: must be an integer in [1, 100], got 0" in text
    # paper.toml sets every vehicle's effectiveness: [truth]'s would change nothing
    text = _refusal("truth.speed_effectiveness=0.8,1.0")
    assert "0.8 and 1.0 fly the same scenario" in text
    assert "vary vehicles[*].truth.speed_effectiveness" in text
    assert "the file has 3 vehicles (indices 0 to 2)" in _refusal("vehicles[3].initial=[0,0,0]")
    assert "needs a fault file in every run" in _refusal("faults[0].probability=0.1")
    assert "--seeds" in _refusal("seed=1,2")
    assert "a value is given twice" in _refusal("controller.horizon=5,5")
    assert "closer than d_safe_m" in _refusal("controller.d_safe_m=2.0,15.0")
    text = _refusal("controller.horizon=5", "controller.d_safe_m=2.0", files=(PAPER, "nope.toml"))
    assert "nope.toml" in text


def test_a_runs_identity_is_its_inputs():
    a, b = _plan("controller.horizon=4,6")[:3:2]  # horizon 4 seed 7, horizon 6 seed 7
    assert a.run_id == _plan("controller.horizon=4,6")[0].run_id
    assert len({a.run_id, b.run_id}) == 2
    other_text = RunSpec(a.file, a.scenario_text + "\n", a.overrides, a.seed, a.learning)
    assert other_text.run_id != a.run_id
    # the same file given twice is flown once
    assert len(_plan("controller.horizon=4,6", files=(PAPER, PAPER))) == 4


def test_the_median_band_is_the_order_statistics_interval():
    # 20 seeds: x_(6) and x_(15) (P(B <= 5) = 0.0207 <= 2.5 % < P(B <= 6) = 0.0577)
    assert sweep_figures.median_band(range(20))[:3] == (9.5, 5.0, 14.0)
    assert sweep_figures.median_band(range(20))[3] == pytest.approx(1 - 2 * 0.0207, abs=1e-4)
    # five seeds or fewer: the range, its coverage below 95 %
    assert sweep_figures.median_band([3.0, 1.0, 2.0]) == (2.0, 1.0, 3.0, 0.75)
    assert sweep_figures.median_band([1.0, 2.0, float("inf")])[:3] == (2.0, 1.0, float("inf"))


def _sweep(out: Path, *extra: str, scenarios=(PAPER,)) -> int:
    return main(["sweep", *scenarios, "--out", str(out), "--quiet", *extra])


def _table(out: Path):
    return pq.read_table(out / "results.parquet").sort_by("run_id")


def test_a_local_sweep_writes_its_rows_and_figures_and_resumes(tmp_path, capsys):
    out = tmp_path / "sweep"
    grid = ["--vary", "controller.horizon=4,6", "--seeds", "2", "--duration", "3"]
    rc = _sweep(out, *grid, "--engine", "local", "--jobs", "2")
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "4 runs in the grid: 0 done already, 4 to fly" in text
    table = _table(out)
    assert table.num_rows == 4 and len(set(table.column("run_id").to_pylist())) == 4
    assert sorted(table.column("controller.horizon").to_pylist()) == [4, 4, 6, 6]
    assert set(table.column("status").to_pylist()) == {"ok"}
    assert set(table.column("attempts").to_pylist()) == {1}
    assert set(table.column("flown_s").to_pylist()) == {3.0}
    assert all(v > 0 for v in table.column("formation_rms_m").to_pylist())
    assert all(table.column("version").to_pylist())
    assert sorted(p.stem for p in (out / "runs").glob("*.parquet")) == sorted(
        table.column("run_id").to_pylist()
    )
    figures = sorted(p.name for p in (out / "figures").iterdir())
    assert "formation_rms_m__controller_horizon.png" in figures
    assert "min_separation_m__controller_horizon.svg" in figures
    plan = json.loads((out / "sweep.json").read_text())
    assert plan["runs"] == 4 and plan["vary"]["controller.horizon"] == [4, 6]

    # the same folder again without --resume is refused; with it, only the missing run flies
    assert _sweep(out, *grid, "--engine", "local") == 2
    assert "--resume to complete it" in capsys.readouterr().err
    lost = out / "runs" / f"{table.column('run_id')[1].as_py()}.parquet"
    lost.unlink()
    (out / "runs" / f".{lost.name}.123.tmp").write_bytes(b"half a file")  # a killed write
    assert _sweep(out, *grid, "--engine", "local", "--resume") == 0
    assert "4 runs in the grid: 3 done already, 1 to fly" in capsys.readouterr().out
    assert not list((out / "runs").glob(".*.tmp"))
    again = _table(out)
    assert again.select(NUMBERS).equals(table.select(NUMBERS))
    assert _sweep(out, *grid, "--engine", "local", "--resume", "--no-figures") == 0
    assert "4 runs in the grid: 4 done already, 0 to fly" in capsys.readouterr().out


def test_a_run_past_its_time_limit_fails_and_is_flown_once_more(tmp_path, capsys):
    out = tmp_path / "sweep"
    rc = _sweep(
        out,
        *("--seeds", "1", "--duration", "3", "--time-limit", "1e-6"),
        *("--engine", "local", "--jobs", "1", "--no-figures"),
    )
    text = capsys.readouterr().out
    assert rc == 1
    (row,) = _table(out).to_pylist()
    assert row["status"] == "failed" and row["attempts"] == 2
    assert row["error"] == row["first_error"] == "time limit 1e-06 s exceeded"
    assert row["formation_rms_m"] is None and row["gates_failed"] == ["error"]
    assert "failed: time limit 1e-06 s exceeded" in text
    # --resume leaves it failed; --retry-failed flies it again
    assert _sweep(out, "--seeds", "1", "--duration", "3", "--resume", "--engine", "local") == 1
    assert "1 done already, 0 to fly" in capsys.readouterr().out
    rc = _sweep(
        out,
        *("--seeds", "1", "--duration", "3", "--resume", "--retry-failed"),
        *("--engine", "local", "--no-figures"),
    )
    assert rc == 0 and _table(out).column("status").to_pylist() == ["ok"]


HANG_LIMIT_S = 6.0
"""The time limit of the hang test: some 40 times what a run of 2 s takes here (0.15 s)."""
HANG_S = 20 * HANG_LIMIT_S
"""How long a hung step blocks: far beyond the limit, so that a limit not enforced fails the
test (the run flies on after it) rather than hanging it."""


def _hang_inside_a_period(monkeypatch, folder: Path) -> None:
    """The agents of 5-vehicle runs (wedge-circle's) block for `HANG_S` inside their period at
    1 s of flight, each hung process first leaving a file ``folder/<pid>`` holding its parent's pid;
    3-vehicle runs (paper's) fly. The sweep's workers are forked from this process (the
    platform's start method, as the engine's), and so are their run processes: they fly this
    step."""
    folder.mkdir()
    step = AgentPool.step

    def step_or_hang(self, t_ns, measurements, *args, **kwargs):
        if len(measurements) == 5 and t_ns >= 1_000_000_000:
            (folder / str(os.getpid())).write_text(str(os.getppid()))
            threading.Event().wait(HANG_S)
        return step(self, t_ns, measurements, *args, **kwargs)

    monkeypatch.setattr(AgentPool, "step", step_or_hang)


@pytest.mark.parametrize("engine", ["local", "dask"])
def test_a_run_that_hangs_inside_a_period_is_killed_at_its_time_limit(
    tmp_path, capsys, monkeypatch, engine
):
    hung = tmp_path / "hung"
    _hang_inside_a_period(monkeypatch, hung)
    before = {p.pid for p in psutil.Process().children(recursive=True)}
    out = tmp_path / "sweep"
    rc = _sweep(
        out,
        *("--seeds", "1", "--duration", "2", "--time-limit", f"{HANG_LIMIT_S:g}"),
        *("--engine", engine, "--jobs", "2", "--no-figures"),
        scenarios=(PAPER, WEDGE),
    )
    text = capsys.readouterr().out
    assert rc == 1, text
    rows = {r["scenario"]: r for r in _table(out).to_pylist()}
    assert rows["paper"]["status"] == "ok" and rows["paper"]["attempts"] == 1
    wedge = rows["wedge-circle"]
    assert wedge["status"] == "failed" and wedge["attempts"] == 2
    assert wedge["error"] == wedge["first_error"] == "time limit 6 s exceeded"
    assert wedge["formation_rms_m"] is None
    # each flight hung in a run process of its own, killed; with Dask on the other worker
    parents = {int(f.name): int(f.read_text()) for f in hung.iterdir()}
    assert len(parents) == 2, parents
    if engine == "dask":
        assert len(set(parents.values())) == 2, parents
    assert not [pid for pid in parents if psutil.pid_exists(pid)]
    # and nothing the sweep started is left: workers, run processes
    left = [p for p in psutil.Process().children(recursive=True) if p.pid not in before]
    assert not left, left


def _attempt_as_a_daemon(conn) -> None:
    conn.send(fly_within(fly_spec, _plan()[0], limit_s=60.0))


def test_a_daemon_worker_refuses_runs_saying_how_to_start_workers():
    # Dask's nannies make their workers daemons unless told otherwise: such a worker may not
    # start a run process, and says how to start workers that may
    context = multiprocessing.get_context()
    ours, theirs = context.Pipe()
    worker = context.Process(target=_attempt_as_a_daemon, args=(theirs,), daemon=True)
    worker.start()
    try:
        assert ours.poll(60.0)
        row, error = ours.recv()
    finally:
        worker.join(10.0)
    assert row is None
    assert "daemon process" in error and "DASK_DISTRIBUTED__WORKER__DAEMON=False" in error


def test_without_dask_the_sweep_flies_on_the_process_pool(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # `import distributed` fails
    assert main(["sweep", PAPER, "--engine", "dask", "--out", str(tmp_path / "a")]) == 2
    assert "pip install 'fleetmpc[cluster]'" in capsys.readouterr().err
    out = tmp_path / "b"
    rc = main(
        ["sweep", PAPER, "--out", str(out), "--seeds", "1", "--duration", "3", "--no-figures"]
        + ["--learning", "on,off"]
    )
    assert rc == 0
    assert "flying on a process pool of 2 workers" in capsys.readouterr().err
    table = _table(out)
    assert sorted(table.column("learning").to_pylist()) == [False, True]
    ratio = [r for r in table.column("learning_ratio").to_pylist() if r is not None]
    assert len(ratio) == 1 and ratio[0] > 0


def _worker(processes, name: str, address: str):
    child = processes.start(
        name,
        [
            sys.executable,
            "-m",
            "distributed.cli.dask_worker",
            address,
            *("--nthreads", "1", "--no-nanny", "--no-dashboard"),
            *("--name", name, "--host", "127.0.0.1"),
        ],
    )
    child.wait_for(r"Registered to", stream="err", timeout_s=60.0)
    return child


def test_a_real_scheduler_and_two_workers_one_killed_give_the_local_pools_rows(
    tmp_path, capsys, processes
):
    grid = [
        *(WEDGE, PAPER),
        *("--vary", "controller.horizon=4,5,6", "--seeds", "4", "--duration", "6"),
    ]
    local = tmp_path / "local"
    assert main(["sweep", *grid, "--out", str(local), "--quiet", "--engine", "local"]) == 0
    capsys.readouterr()
    expected = _table(local)
    assert expected.num_rows == 24

    port = free_port(socket.SOCK_STREAM)
    address = f"tcp://127.0.0.1:{port}"
    processes.start(
        "scheduler",
        [
            sys.executable,
            "-m",
            "distributed.cli.dask_scheduler",
            *("--host", "127.0.0.1", "--port", str(port), "--no-dashboard"),
        ],
    ).wait_for(r"Scheduler at:", stream="err", timeout_s=60.0)
    _worker(processes, "w1", address)
    _worker(processes, "w2", address)

    whole = tmp_path / "whole"
    args = ["sweep", *grid, "--scheduler", address, "--quiet", "--no-figures"]
    assert main([*args, "--out", str(whole)]) == 0
    capsys.readouterr()
    assert _table(whole).select(NUMBERS).equals(expected.select(NUMBERS))
    assert len(set(_table(whole).column("worker").to_pylist())) == 2

    # again, in a process of its own, and worker w1 killed once 4 runs have come back
    killed = tmp_path / "killed"
    sweep = processes.fleetmpc(
        "sweep", "sweep", *grid, "--scheduler", address, "--quiet", "--out", str(killed)
    )
    runs = killed / "runs"
    assert wait_until(lambda: len(list(runs.glob("*.parquet"))) >= 4, timeout_s=60.0), sweep.tail()
    processes.kill("w1")
    finished_at_kill = len(list(runs.glob("*.parquet")))
    assert finished_at_kill < 24
    assert sweep.proc.wait(timeout=120) == 0, sweep.tail()
    table = _table(killed)
    assert table.num_rows == 24 and len(set(table.column("run_id").to_pylist())) == 24
    assert len(list(runs.glob("*.parquet"))) == 24
    assert table.select(NUMBERS).equals(expected.select(NUMBERS))
    # the figures too, byte for byte
    names = sorted(p.name for p in (local / "figures").iterdir())
    assert names and names == sorted(p.name for p in (killed / "figures").iterdir())
    for name in names:
        assert (local / "figures" / name).read_bytes() == (killed / "figures" / name).read_bytes()
    # the worker stops on SIGTERM (before the scheduler: it would wait for it otherwise)
    assert processes.stop("w2", timeout_s=20.0)["w2"] is not None, processes["w2"].tail()
