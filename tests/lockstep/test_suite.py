"""`fleetmpc suite`: a folder of short scenarios flown over a process pool, gates, JSON, exit."""

import json
import math
import tomllib
from pathlib import Path

import pytest

from fleetmpc.cli import main
from fleetmpc.lockstep import suite
from fleetmpc.scenario import load_scenario, parse_scenario

ROOT = Path(__file__).resolve().parents[2]

CALM = """
# Three vehicles on their slots, facing the way a slow target flies, in still air with a perfect
# model: every gate holds for any sane controller.
name = "calm"
seed = 3
duration_s = 12.0

[controller]
horizon = 5
reference_speed_m_s = 1.0

[formation]
frame = "world"
trail_m = 5.0

[target]
kind = "line"
start_m = [5.0, 0.0]
velocity_m_s = [0.8, 0.0]
observation_noise_m = 0.05

[truth]
actuator_lag_s = 0.1
position_noise_m = 0.02
heading_noise_rad = 0.005

[[vehicles]]
id = 1
initial = [0.0, 0.0, 0.0]
slot_m = [0.0, 0.0]

[[vehicles]]
id = 2
initial = [0.0, 10.0, 0.0]
slot_m = [0.0, 10.0]

[[vehicles]]
id = 3
initial = [0.0, -10.0, 0.0]
slot_m = [0.0, -10.0]
"""

ROW_KEYS = {
    "scenario",
    "file",
    "seed",
    "learning",
    "error",
    "feasible",
    "unmodeled_dynamics",
    "d_safe_m",
    "formation_rms_m",
    "slot_rms_max_vehicle_m",
    "learning_ratio",
    "min_separation_m",
    "yaw_rate_reversals_per_vehicle_min",
    "qp_fallbacks",
    "qp_fallback_fraction",
    "target_prediction_rms_m",
    "corners",
    "corner_recovery_s",
    "gates_failed",
}


@pytest.fixture
def loose_gates(monkeypatch) -> None:
    """Limits any run of a sane controller meets: these tests are about the suite (tasks, pool,
    rows, table, JSON, exit status), not the controller, whose closed-loop quality
    tests/lockstep/test_closed_loop.py holds (a 12 s run from rest can, for instance, show a few
    yaw-rate reversals while the vehicles get going, many per vehicle-minute of so short a run).
    Minimum separation keeps its real gate."""
    for name, value in (
        ("SLOT_RMS_MAX_M", 1.0),
        ("PAPER_SLOT_RMS_MAX_M", 1.0),
        ("LEARNING_RATIO_MAX", 100.0),
        ("REVERSALS_MAX_PER_VEHICLE_MIN", 1000.0),
        ("QP_FALLBACK_MAX_FRACTION", 0.5),
        ("CORNER_RECOVERY_MAX_S", math.inf),
    ):
        monkeypatch.setattr(suite, name, value)


@pytest.fixture
def calm_dir(tmp_path) -> Path:
    folder = tmp_path / "scenarios"
    folder.mkdir()
    (folder / "calm.toml").write_text(CALM)
    (folder / "notes.txt").write_text("not a scenario")
    return folder


def test_a_calm_fleet_passes_every_gate(calm_dir, tmp_path, capsys, loose_gates):
    out = tmp_path / "out" / "suite.json"  # the parent folder does not exist yet
    rc = main(["suite", str(calm_dir), "--seeds", "2", "--jobs", "2", "--json", str(out)])
    text = capsys.readouterr().out
    doc = json.loads(out.read_text())
    assert rc == 0, text
    rows = doc["rows"]
    assert [(r["seed"], r["learning"], r["known_model"]) for r in rows] == [
        (3, True, False), (3, False, False), (3, True, True),
        (4, True, False), (4, False, False), (4, True, True),
    ]  # fmt: skip
    for r in rows:
        assert set(r) >= ROW_KEYS
        assert r["error"] is None and r["gates_failed"] == []
        assert r["feasible"] is True and r["unmodeled_dynamics"] is False
        assert r["periods"] == 61 and r["duration_s"] == pytest.approx(12.0, abs=1e-9)
        assert 0.0 < r["formation_rms_m"] < 1.0
        assert r["slot_rms_max_vehicle_m"] >= r["formation_rms_m"]
        assert r["min_separation_m"] >= 2.0
        assert r["qp_fallback_fraction"] == r["qp_fallbacks"] / (61 * 3)
        assert r["corners"] == 0 and r["corner_recovery_s"] is None
    on, off, known = rows[0], rows[1], rows[2]
    assert on["learning_ratio"] == pytest.approx(on["formation_rms_m"] / off["formation_rms_m"])
    assert on["learned_over_known"] == pytest.approx(
        on["formation_rms_m"] / known["formation_rms_m"]
    )
    assert off["learning_ratio"] is None and known["learned_over_known"] is None
    assert doc["passed"] is True and doc["failed_gates"] == []
    assert set(doc["gates"]) == set(suite.GATES) and doc["wall_time_s"] > 0
    assert doc["seeds"] == 2 and doc["jobs"] == 2
    # one progress line per run, the table (a header and a row per run), the wall time
    assert text.count("] calm seed ") == 6
    assert "form RMS m" in text and "corner rec s" in text and "lrn/known" in text
    assert sum(line.startswith("calm ") for line in text.splitlines()) == 4
    assert "6 runs in" in text and "every gate held" in text


def test_a_missed_gate_exits_1_and_names_it(calm_dir, tmp_path, capsys, monkeypatch, loose_gates):
    # no run can hold its formation within 0: the slot-RMS gate fails on the learning-on row only
    monkeypatch.setattr(suite, "SLOT_RMS_MAX_M", 0.0)
    out = tmp_path / "suite.json"
    rc = main(
        ["suite", str(calm_dir), "--seeds", "1", "--jobs", "2", "--json", str(out), "--quiet",
         "--no-known-model"]
    )  # fmt: skip
    text = capsys.readouterr().out
    assert rc == 1
    doc = json.loads(out.read_text())
    assert [r["gates_failed"] for r in doc["rows"]] == [["slot_rms"], []]
    assert doc["passed"] is False and doc["failed_gates"] == ["slot_rms"]
    assert "] calm seed" not in text  # --quiet: no progress lines
    assert "gates missed: slot_rms" in text


def test_bad_folders_and_arguments_are_errors(tmp_path, capsys):
    assert main(["suite", str(tmp_path / "missing")]) == 2
    assert "error: DIR: not a folder" in capsys.readouterr().err
    assert main(["suite", str(tmp_path)]) == 2
    assert "error: DIR: no scenario (*.toml)" in capsys.readouterr().err
    (tmp_path / "bad.toml").write_text('name = "bad"\nduration_s = -1.0\n')
    assert main(["suite", str(tmp_path)]) == 2
    assert "bad.toml: duration_s: must be > 0" in capsys.readouterr().err
    assert main(["suite", str(tmp_path), "--seeds", "0"]) == 2
    assert "error: --seeds" in capsys.readouterr().err


def _row(**changes) -> dict:
    """A learning-on row of a feasible scenario with unmodeled dynamics that holds every gate."""
    row = {
        "scenario": "s",
        "file": "s.toml",
        "seed": 1,
        "learning": True,
        "error": None,
        "feasible": True,
        "unmodeled_dynamics": True,
        "d_safe_m": 2.0,
        "formation_rms_m": 0.1,
        "min_separation_m": 2.0,
        "yaw_rate_reversals_per_vehicle_min": 3.0,
        "qp_fallback_fraction": 0.01,
        "corners": 2,
        "corner_recovery_s": 15.0,
        "beta_error_speed_max": 0.1,
        "beta_error_yaw_rate_max": 0.1,
    }
    return {**row, **changes}


def _off(**changes) -> dict:
    return _row(**{"learning": False, "formation_rms_m": 1.0, **changes})


@pytest.mark.parametrize(
    ("on", "off", "failed"),
    [
        ({}, {}, []),  # every number on its limit
        ({"formation_rms_m": 0.151}, {"formation_rms_m": 1.0}, ["slot_rms"]),
        ({"scenario": "paper", "formation_rms_m": 0.051}, {"scenario": "paper"}, ["slot_rms"]),
        ({"scenario": "paper", "formation_rms_m": 0.05}, {"scenario": "paper"}, []),
        ({"formation_rms_m": 0.1}, {"formation_rms_m": 0.33}, ["learning_ratio"]),
        ({"min_separation_m": 1.99}, {}, ["min_separation"]),
        ({"yaw_rate_reversals_per_vehicle_min": 3.01}, {}, ["reversals"]),
        ({"qp_fallback_fraction": 0.0101}, {}, ["qp_fallbacks"]),
        ({"corner_recovery_s": 15.2}, {}, ["corner_recovery"]),
        ({"corner_recovery_s": math.inf}, {}, ["corner_recovery"]),
        ({"corners": 0, "corner_recovery_s": None}, {}, []),
        ({"beta_error_speed_max": 0.101}, {}, ["effectiveness"]),
        ({"beta_error_yaw_rate_max": 0.101}, {}, ["effectiveness"]),
        ({"beta_error_speed_max": 0.5, "feasible": False}, {}, []),
        # an infeasible target or no unmodeled dynamics switch the learning gates off
        ({"feasible": False, "formation_rms_m": 9.0, "corner_recovery_s": math.inf}, {}, []),
        ({"unmodeled_dynamics": False, "formation_rms_m": 0.1}, {"formation_rms_m": 0.1}, []),
        ({"error": "ValueError: boom"}, {}, ["error"]),
    ],
)
def test_gates_on_crafted_rows(on, off, failed):
    rows = suite.apply_gates([_row(**on), _off(**off)])
    assert rows[0]["gates_failed"] == failed
    if not on.get("error"):
        assert rows[0]["learning_ratio"] == pytest.approx(
            rows[0]["formation_rms_m"] / rows[1]["formation_rms_m"]
        )


def test_learning_off_rows_are_held_to_the_every_run_gates_only():
    rows = suite.apply_gates(
        [
            _off(formation_rms_m=5.0, corner_recovery_s=math.inf),  # no on row to pair with
            _off(seed=2, min_separation_m=1.0, qp_fallback_fraction=0.5),
        ]
    )
    assert [r["gates_failed"] for r in rows] == [[], ["min_separation", "qp_fallbacks"]]
    assert [r["learning_ratio"] for r in rows] == [None, None]


def test_the_ratio_pairs_runs_of_the_same_file_and_seed():
    rows = suite.apply_gates(
        [
            _row(seed=1, formation_rms_m=0.1),
            _row(seed=2, formation_rms_m=0.1),
            _off(seed=2, formation_rms_m=0.2),  # seed 2: 0.5, too little gain
            _off(seed=1, formation_rms_m=1.0),  # seed 1: 0.1
        ]
    )
    assert [r["learning_ratio"] for r in rows[:2]] == pytest.approx([0.1, 0.5])
    assert [r["gates_failed"] for r in rows[:2]] == [[], ["learning_ratio"]]


def test_the_known_model_run_is_a_ratio_on_its_learned_runs_line():
    known = _row(known_model=True, formation_rms_m=0.04, beta_error_speed_max=0.0)
    rows = suite.apply_gates(
        [
            _row(formation_rms_m=0.1, slot_rms_max_vehicle_m=0.1, qp_fallbacks=0),
            {**known, "min_separation_m": 1.0},  # the known model breaches d_safe
            _off(),
        ]
    )
    assert rows[0]["learned_over_known"] == pytest.approx(2.5)  # reported, not gated
    assert rows[0]["gates_failed"] == [] and rows[1]["gates_failed"] == ["min_separation"]
    assert rows[1]["learning_ratio"] is None and rows[1]["learned_over_known"] is None
    table = suite.format_table(
        [{**r, "target_prediction_rms_m": 0.1, "slot_rms_max_vehicle_m": 0.1, "qp_fallbacks": 0}
         for r in rows]
    )  # fmt: skip
    lines = table.splitlines()
    assert "lrn/known" in lines[0] and len(lines) == 3  # the known-model run has no line
    assert "2.50" in lines[1] and lines[1].endswith("known model: min_separation")


def test_suite_tasks_add_a_known_model_run_where_learning_is_on(tmp_path):
    (tmp_path / "a.toml").write_text(Path("scenarios/paper.toml").read_text())
    tasks = suite.suite_tasks([tmp_path / "a.toml"], seeds=2)
    assert [(t.seed, t.learning, t.known_model) for t in tasks] == [
        (7, True, False), (7, False, False), (7, True, True),
        (8, True, False), (8, False, False), (8, True, True),
    ]  # fmt: skip
    plain = suite.suite_tasks([tmp_path / "a.toml"], seeds=1, known_model=False)
    assert not any(t.known_model for t in plain)


def test_the_table_marks_infeasible_targets_errors_and_unknowns():
    rows = suite.apply_gates(
        [
            _row(
                feasible=False,
                slot_rms_max_vehicle_m=0.2,
                qp_fallbacks=0,
                target_prediction_rms_m=None,
                corner_recovery_s=math.inf,
            ),
            {
                "scenario": "s",
                "file": "s.toml",
                "seed": 1,
                "learning": False,
                "error": "ValueError: boom",
            },
        ]
    )
    lines = suite.format_table(rows).splitlines()
    assert lines[1].split()[:4] == ["s", "*", "1", "on"]
    assert lines[1].split()[-3:] == ["unknown", "inf", "ok"]
    assert lines[2].split() == ["s", "1", "off", *["-"] * 9, "error"]
    assert lines[3].startswith("* infeasible target")
    assert lines[4] == "error in 1 run: ValueError: boom"


def test_tasks_cover_files_seeds_and_learning(tmp_path):
    (tmp_path / "a.toml").write_text(CALM)
    (tmp_path / "b.toml").write_text(
        CALM.replace('name = "calm"', 'name = "fixed"') + "\n[learning]\nenabled = false\n"
    )
    tasks = suite.suite_tasks(
        sorted(tmp_path.glob("*.toml")), seeds=2, duration_s=None, known_model=False
    )
    assert [(Path(t.path).name, t.seed, t.learning, t.duration_s) for t in tasks] == [
        ("a.toml", 3, True, 12.0),
        ("a.toml", 3, False, 12.0),
        ("a.toml", 4, True, 12.0),
        ("a.toml", 4, False, 12.0),
        ("b.toml", 3, False, 12.0),  # learning disabled in the file: flown off only
        ("b.toml", 4, False, 12.0),
    ]
    assert {
        t.duration_s for t in suite.suite_tasks([tmp_path / "a.toml"], seeds=1, duration_s=5.0)
    } == {5.0}


def test_unmodeled_dynamics_of_the_repository_scenarios():
    assert suite.has_unmodeled_dynamics(load_scenario(ROOT / "scenarios" / "paper.toml"))
    assert not suite.has_unmodeled_dynamics(parse_scenario(tomllib.loads(CALM)))
    gusty = tomllib.loads(CALM)
    gusty["truth"]["wind"] = {"gust_amplitude_m_s": 0.05}
    assert suite.has_unmodeled_dynamics(parse_scenario(gusty))


def _boom(*args, **kwargs):
    raise ValueError("boom")


def test_a_run_flies_when_the_check_fails_and_its_row_fails_the_error_gate(
    tmp_path, monkeypatch, loose_gates
):
    (tmp_path / "calm.toml").write_text(CALM)
    monkeypatch.setattr(suite, "check_scenario", _boom)
    task = suite.SuiteTask(str(tmp_path / "calm.toml"), seed=3, learning=True, duration_s=4.0)
    row = suite.fly(task)  # in this process: no pool
    assert row["error"] == "check: ValueError: boom" and row["feasible"] is None
    assert row["periods"] == 21 and row["formation_rms_m"] > 0.0
    (gated,) = suite.apply_gates([row])
    assert gated["gates_failed"] == ["error"]
    lines = suite.format_table([gated]).splitlines()
    assert lines[1].startswith("calm ?") and lines[1].endswith(" error")
    assert lines[2].startswith("? feasibility unknown")
    assert lines[3] == "error in 1 run: check: ValueError: boom"
    # unknown feasibility is judged as feasible
    monkeypatch.setattr(suite, "SLOT_RMS_MAX_M", 0.0)
    assert suite.apply_gates([row])[0]["gates_failed"] == ["error", "slot_rms"]


def test_a_run_that_raises_is_a_row_without_numbers(tmp_path, monkeypatch):
    (tmp_path / "calm.toml").write_text(CALM)
    monkeypatch.setattr(suite, "run_lockstep", _boom)
    task = suite.SuiteTask(str(tmp_path / "calm.toml"), seed=3, learning=False, duration_s=4.0)
    row = suite.fly(task)
    assert row["error"] == "ValueError: boom" and "formation_rms_m" not in row
    assert (row["scenario"], row["seed"], row["learning"]) == ("calm", 3, False)
    assert suite.apply_gates([row])[0]["gates_failed"] == ["error"]
