import json
import subprocess
import sys
from pathlib import Path

from fleetmpc.cli import main
from fleetmpc.gcs.figures import FIGURE_FILES

ROOT = Path(__file__).resolve().parents[1]

KEYS = {
    "scenario",
    "learning",
    "feasible",
    "duration_s",
    "separation_error_m",
    "centre_distance_error_m",
    "formation_rms_m",
    "c_norm_final",
    "min_separation_m",
    "inputs_within_bounds",
    "beta_error",
    "step_time_ms",
    "qp_fallbacks",
}


def test_sim_writes_metrics_and_figures(tmp_path, capsys):
    metrics = tmp_path / "m.json"
    rc = main(
        [
            "sim",
            "scenarios/paper.toml",
            "--duration",
            "4",
            "--metrics",
            str(metrics),
            "--plots",
            str(tmp_path / "figs"),
            "--quiet",
        ]
    )
    assert rc == 0
    m = json.loads(metrics.read_text())
    assert set(m) >= KEYS
    assert m["scenario"] == "paper" and m["learning"] is True and m["feasible"] is True
    assert abs(m["duration_s"] - 4.0) < 1e-9
    assert set(m["step_time_ms"]) == {"median", "p99"}
    for name in FIGURE_FILES:
        assert (tmp_path / "figs" / name).stat().st_size > 10_000
    assert "separation error 1-2" in capsys.readouterr().out


def test_sim_of_the_infeasible_scenario_completes_and_says_so(tmp_path, capsys):
    metrics = tmp_path / "m.json"
    assert (
        main(
            [
                "sim",
                "scenarios/paper-strict.toml",
                "--duration",
                "3",
                "--metrics",
                str(metrics),
                "--quiet",
                "--no-learning",
            ]
        )
        == 0
    )
    m = json.loads(metrics.read_text())
    assert m["feasible"] is False and m["learning"] is False
    assert "outruns" in capsys.readouterr().out


def test_check_exit_codes(capsys):
    assert main(["check", "scenarios/paper.toml"]) == 0
    assert "verdict: FEASIBLE" in capsys.readouterr().out
    assert main(["check", "scenarios/paper-strict.toml"]) == 1
    assert "verdict: INFEASIBLE" in capsys.readouterr().out


def test_bad_scenario_is_a_clear_error(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\n[[vehicles]]\nid = 1\ninitial = [0, 0]\n')
    assert main(["check", str(bad)]) == 2
    assert "vehicles[0].initial" in capsys.readouterr().err


def test_a_fleet_process_exits_without_teardown_and_loses_no_output(tmp_path):
    """`entry` ends a fleet process (here `target`, on a configuration error) with os._exit
    after its atexit hooks: the exit status and everything printed survive."""
    missing = str(tmp_path / "missing.toml")
    code = (
        "import atexit, sys; atexit.register(lambda: print('atexit ran'))\n"
        f"sys.argv[1:] = ['target', '--scenario', {missing!r}]\n"
        "from fleetmpc.cli import entry; entry()"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 2, done.stderr
    assert "fleetmpc target: error:" in done.stderr and "missing.toml" in done.stderr
    assert done.stdout == "atexit ran\n"
