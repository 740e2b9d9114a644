import json
import re
from pathlib import Path

import numpy as np
import pytest

from fleetmpc.bench.baseline import THIS_TREE, compare
from fleetmpc.bench.step import _cvxpy_rebuild, _input_bounds
from fleetmpc.cli import main
from fleetmpc.errors import FleetMpcError
from fleetmpc.onboard.core.condensed_qp import QpData
from fleetmpc.onboard.core.config import ControllerSettings
from fleetmpc.onboard.core.lbmpc import TubeLbmpc
from fleetmpc.onboard.core.unicycle import rollout

SETTINGS = ControllerSettings(reference_speed_m_s=1.4, solver_eps=1e-8, solver_max_iter=20000)


def _data(rng: np.random.Generator, mpc: TubeLbmpc) -> QpData:
    """A period whose steady inputs ask for flying backwards and turning hard the other way (so
    that the speed's lower bound, its rate and the yaw-rate trust region bind), with one
    neighbour's half-planes behind the vehicle's first two steps and the other's off."""
    M = mpc.M
    z0 = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi)])
    lin_u = np.column_stack([rng.uniform(0.8, 1.5, M), rng.uniform(-0.3, 0.3, M)])
    beta = np.array([rng.uniform(0.8, 1.2), rng.uniform(0.8, 1.2), *rng.uniform(-0.3, 0.3, 2)])
    lin_z = rollout(z0, lin_u, beta, mpc.tau)
    u_s = np.column_stack([np.full(M, -1.0), -np.sign(lin_u[:, 1]) * 0.5])
    # Neighbour 1's half-planes face the vehicle from 0.1 m behind its path's first two step
    # positions (then off); neighbour 2's are off.
    heading = np.column_stack([np.cos(lin_z[1:, 2]), np.sin(lin_z[1:, 2])])
    b = np.sum(heading * lin_z[1:, :2], axis=1) - 0.1
    b[2:] = np.inf
    planes = np.stack(
        [np.column_stack([heading, b]), np.column_stack([heading, np.full(M, np.inf)])]
    )
    return QpData(
        z0=z0,
        lin_states=lin_z,
        lin_inputs=lin_u,
        beta=beta,
        u_s=u_s,
        targets=lin_z[1:] - np.column_stack([2.0 * heading, np.zeros(M)]),  # behind: pulls back
        position_weights=np.full(M, 6.0),
        terminal_scale=1.0,
        separation_planes=planes,
        speed_now_m_s=float(lin_u[0, 0]),
        yaw_rate_now_rad_s=float(lin_u[0, 1]),
    )


@pytest.mark.parametrize("seed", range(4))
def test_the_cvxpy_rebuild_solves_the_same_qp(seed):
    rng = np.random.default_rng(seed)
    mpc = TubeLbmpc(SETTINGS, n_neighbours=2)
    rebuild = _cvxpy_rebuild(TubeLbmpc(SETTINGS, n_neighbours=2))
    d = _data(rng, mpc)
    sol = mpc.solve(d)
    assert sol.ok, sol.status
    np.testing.assert_allclose(rebuild(d), sol.c.ravel(), atol=1e-4)
    # The constraints this checks bind: a speed at its bound 0, a speed change at its limit, a
    # yaw rate at the edge of its trust region, a separation row.
    bounds = np.array([_input_bounds(mpc, d, j) for j in range(mpc.M)])  # (M, lower/upper, 2)
    assert np.all(sol.inputs >= bounds[:, 0] - 1e-5) and np.all(sol.inputs <= bounds[:, 1] + 1e-5)
    assert np.min(sol.inputs[:, 0]) < 1e-5
    changes = np.abs(np.diff([d.speed_now_m_s, *sol.inputs[:, 0]]))
    step = SETTINGS.speed_rate_max_m_s2 * mpc.tau
    assert np.max(changes) < step + 1e-5 and np.max(changes) > step - 1e-5
    turn = np.abs(sol.inputs[:, 1] - d.lin_inputs[:, 1])
    trust = np.array([SETTINGS.yaw_rate_trust(v) for v in d.lin_inputs[:, 0]])
    assert np.min(np.abs(turn - trust)) < 1e-5
    n, b = d.separation_planes[0, :2, :2], d.separation_planes[0, :2, 2]
    separation_slack = np.sum(n * sol.learned[1:3, :2], axis=1) - b
    assert separation_slack.min() > -1e-5 and separation_slack.min() < 1e-5


def _fake_tree(root: Path, *, step_ms: float, fail: bool = False) -> Path:
    """A tree with the two modules the measurement uses: every agent step takes `step_ms`."""
    (root / "gcs").mkdir(parents=True)
    (root / "protocol").mkdir()
    (root / "gcs" / "__init__.py").write_text("")
    (root / "protocol" / "__init__.py").write_text("")
    (root / "protocol" / "scenario.py").write_text(
        "class _Scenario:\n"
        "    duration_s = 30.0\n\n\n"
        "def load_scenario(path):\n"
        "    return _Scenario()\n"
    )
    (root / "gcs" / "lockstep.py").write_text(
        "import numpy as np\n\n\n"
        "class _Record:\n"
        f"    step_time_ms = np.full((151, 3), {step_ms})\n\n\n"
        "def run_lockstep(scenario, duration_s=None):\n"
        + ("    raise RuntimeError('boom')\n" if fail else "    return _Record()\n")
    )
    return root


def test_each_tree_runs_its_own_code_and_the_ratios_are_of_the_two(tmp_path):
    slow = _fake_tree(tmp_path / "slow", step_ms=0.3)
    fast = _fake_tree(tmp_path / "fast", step_ms=0.2)
    result = compare(THIS_TREE / "scenarios" / "paper.toml", tree=slow, baseline=fast, rounds=2)
    assert result["this"]["step_median_ms"] == pytest.approx(0.3)
    assert result["baseline"]["step_p99_ms"] == pytest.approx(0.2)
    assert result["this"]["steps"] == result["baseline"]["steps"] == 2 * 151 * 3
    assert result["this_over_baseline"]["step_median_ms"] == pytest.approx(1.5)
    assert result["this_over_baseline"]["step_p99_ms"] == pytest.approx(1.5)
    assert result["round_ratios"]["step_median"] == pytest.approx([1.5, 1.5])
    assert len(result["this"]["round_realtime_factors"]) == 2


def test_each_tree_flies_its_own_copy_of_a_scenario_file_of_this_checkout(tmp_path):
    """A baseline written before a scenario key existed flies the file as it had it."""
    this = _fake_tree(tmp_path / "this", step_ms=0.2)
    old = _fake_tree(tmp_path / "old", step_ms=0.2)
    (old / "scenarios").mkdir()
    (old / "scenarios" / "paper.toml").write_text("# the file as the old tree had it\n")
    result = compare(THIS_TREE / "scenarios" / "paper.toml", tree=this, baseline=old, rounds=1)
    assert result["trees"]["baseline"]["scenario"] == str(old / "scenarios" / "paper.toml")
    assert result["trees"]["this"]["scenario"] == str(THIS_TREE / "scenarios" / "paper.toml")
    assert result["same_scenario_file"] is False


def test_a_failing_tree_or_a_directory_that_is_no_checkout_is_an_error(tmp_path):
    good = _fake_tree(tmp_path / "good", step_ms=0.2)
    broken = _fake_tree(tmp_path / "broken", step_ms=0.2, fail=True)
    scenario = THIS_TREE / "scenarios" / "paper.toml"
    with pytest.raises(FleetMpcError, match="boom"):
        compare(scenario, tree=good, baseline=broken, rounds=1)
    with pytest.raises(FleetMpcError, match="not a checkout of fleetmpc"):
        compare(scenario, tree=good, baseline=tmp_path, rounds=1)


def test_bench_against_this_tree_itself(tmp_path, capsys):
    """The real measurement, on a 2 s flight, with this tree as its own baseline."""
    text = (THIS_TREE / "scenarios" / "paper.toml").read_text()
    scenario = tmp_path / "short.toml"
    scenario.write_text(re.sub(r"(?m)^duration_s = .*$", "duration_s = 2.0", text))
    json_path = tmp_path / "bench.json"
    args = ["bench", str(scenario), "--baseline", str(THIS_TREE), "--repeats", "1"]
    assert main([*args, "--json", str(json_path)]) == 0
    out = capsys.readouterr().out
    assert "agent step median ms" in out and "lockstep real-time factor" in out
    result = json.loads(json_path.read_text())
    assert result["this"]["steps"] == result["baseline"]["steps"] == 11 * 3
    assert result["this"]["realtime_factor"] > 1.0


def test_stages_times_every_stage_of_every_step_and_leaves_the_agent_unwrapped(tmp_path, capsys):
    """`fleetmpc bench --stages` on a 2 s paper run: one row per stage with one call per step
    (none waits: telemetry and the target come from the start), shares that add up to the
    step, and the agent's methods as they were afterwards."""
    from fleetmpc.onboard.core.agent import Agent

    before = {name: getattr(Agent, name) for name in (*Agent.STAGES, "step")}
    text = (THIS_TREE / "scenarios" / "paper.toml").read_text()
    scenario = tmp_path / "paper.toml"
    scenario.write_text(re.sub(r"(?m)^duration_s = .*$", "duration_s = 2.0", text))
    json_path = tmp_path / "stages.json"
    args = ["bench", str(scenario), "--stages", "--repeats", "1", "--json", str(json_path)]
    assert main(args) == 0
    rows = {r["stage"]: r for r in json.loads(json_path.read_text())["stages"]}
    assert list(rows) == [*Agent.STAGES, "other", "step"]
    steps = rows["step"]["calls"]
    assert steps == 11 * 3
    assert all(rows[name]["calls"] == steps for name in Agent.STAGES)
    assert sum(rows[name]["share"] for name in (*Agent.STAGES, "other")) == pytest.approx(1.0)
    assert all(rows[name]["median_ms"] > 0.0 for name in Agent.STAGES)
    assert "place_formation" in capsys.readouterr().out
    assert {name: getattr(Agent, name) for name in before} == before
