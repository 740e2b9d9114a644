"""`fleetmpc real-autopilots`: the fleet measured against real autopilot SITLs, as a table.

    fleetmpc real-autopilots --px4 PX4_BUILD \\
        [--arducopter ARDUCOPTER --arducopter-defaults COPTER_PARM]

Given autopilots already built by their own projects' documentation (nothing here builds one:
PX4_BUILD is the folder PX4's SITL build made, holding `bin/px4` and `etc/`), it flies the
measurements of docs/real-autopilots.md, each `--runs` times at x1:

- vehicle 2 of `scenarios/paper.toml` on a PX4 SIH instance, the others on our SITL;
- every vehicle of `scenarios/paper.toml` on PX4;
- `scenarios/mixed-autopilots.toml` with vehicle 1 on PX4 and vehicle 2 on ArduCopter (only with
  `--arducopter`);
- vehicle 2 on PX4 with its agent frozen for 3 s at t = 10 s.

For each run it starts the autopilots (vehicle i is instance i - 1, at its start on the globe as
`fleetmpc home` places it, with system id i), flies `fleetmpc up ... --mavlink i=URL`, stops the
autopilots it started (by PID) and reads the run's metrics. The table gives every pair's
separation error, the centre error and the minimum separation against the gates (each pair at
most 0.15 m, the centre at most 0.1 m, never closer than d_safe). Exit status 0 when every run
met them, 1 otherwise.
"""

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from fleetmpc.errors import ConfigError
from fleetmpc.launch.home import VehicleHome, vehicle_home
from fleetmpc.network import ARDUCOPTER_TCP_BASE_PORT, PX4_OFFBOARD_REMOTE_BASE_PORT
from fleetmpc.scenario import Scenario, load_scenario

__all__ = ["Autopilot", "Measurement", "add_arguments", "judge", "measurements", "run"]

SEPARATION_GATE_M = 0.15
"""Largest separation error of any pair in a run's last 10 s [m]."""
CENTRE_GATE_M = 0.1
"""Largest centre-distance error in a run's last 10 s [m]."""
BOOT_S = 5.0
"""Wall seconds an autopilot is given to boot before the fleet starts (the agents wait for
its estimator as long as their engage timeout allows)."""
STOP_S = 5.0
"""Wall seconds an autopilot has to exit after SIGTERM before it is killed."""


@dataclass(frozen=True)
class Autopilot:
    """One real autopilot SITL instance serving one vehicle."""

    kind: str
    """"px4" (PX4 SITL with SIH) or "arducopter"."""
    home: VehicleHome

    @property
    def instance(self) -> int:
        return self.home.vehicle_id - 1

    @property
    def url(self) -> str:
        """Where the vehicle's agent reaches it (each SITL's own default ports)."""
        if self.kind == "px4":
            return f"udpin:127.0.0.1:{PX4_OFFBOARD_REMOTE_BASE_PORT + self.instance}"
        return f"tcp:127.0.0.1:{ARDUCOPTER_TCP_BASE_PORT + 10 * self.instance}"

    def command(self, paths: argparse.Namespace, folder: Path) -> tuple[list[str], dict[str, str]]:
        """The command line and the environment that start it in `folder`."""
        env = dict(os.environ)
        if self.kind == "px4":
            build = Path(paths.px4).resolve()
            env.update(
                PX4_SIM_MODEL="sihsim_quadx",
                PX4_HOME_LAT=f"{self.home.lat_deg:.7f}",
                PX4_HOME_LON=f"{self.home.lon_deg:.7f}",
                PX4_HOME_ALT=f"{self.home.alt_m:g}",
            )
            return [
                str(build / "bin" / "px4"),
                "-i",
                str(self.instance),
                "-d",
                str(build / "etc"),
            ], env
        sysid = folder / "sysid.parm"
        sysid.write_text(f"MAV_SYSID {self.home.vehicle_id}\n")
        defaults = f"{Path(paths.arducopter_defaults).resolve()},{sysid}"
        return [
            str(Path(paths.arducopter).resolve()), "--model", "+", "--speedup", "1",
            "-I", str(self.instance), "--home", self.home.ardupilot_home(),
            "--defaults", defaults, "--serial1", "udpclient:127.0.0.1:14550",
        ], env  # fmt: skip


@dataclass(frozen=True)
class Measurement:
    """One line of the table: a scenario with some vehicles on real autopilots."""

    name: str
    scenario: Path
    autopilots: dict[int, str]
    """Vehicle id -> "px4" or "arducopter"; the others fly on our SITL."""
    freeze_agent: int | None = None
    """Freeze this vehicle's agent for 3 s at t = 10 s (None: no fault)."""


def measurements(scenarios: Path, *, arducopter: bool) -> list[Measurement]:
    """The measurements of docs/real-autopilots.md (the mixed fleet only with ArduCopter)."""
    paper, mixed = scenarios / "paper.toml", scenarios / "mixed-autopilots.toml"
    out = [
        Measurement("vehicle 2 on PX4", paper, {2: "px4"}),
        Measurement("all on PX4", paper, dict.fromkeys(load_scenario(paper).vehicle_ids, "px4")),
    ]
    if arducopter:
        out.append(Measurement("PX4 + ArduCopter + ours", mixed, {1: "px4", 2: "arducopter"}))
    out.append(Measurement("agent 2 frozen 3 s, PX4", paper, {2: "px4"}, freeze_agent=2))
    return out


def judge(metrics: dict, d_safe_m: float) -> list[str]:
    """The gates a run's metrics miss, by name (empty: it met them all)."""
    missed = []
    pairs = metrics.get("separation_pairs") or []
    for pair, err in zip(pairs, metrics["separation_error_m"], strict=False):
        if not err <= SEPARATION_GATE_M:
            missed.append(f"pair {pair[0]}-{pair[1]} {err:.3f} m")
    if not metrics["centre_distance_error_m"] <= CENTRE_GATE_M:
        missed.append(f"centre {metrics['centre_distance_error_m']:.3f} m")
    if not metrics["min_separation_m"] >= d_safe_m:
        missed.append(f"min separation {metrics['min_separation_m']:.2f} m < d_safe")
    return missed


def _start(autopilots: list[Autopilot], paths, folder: Path) -> list[subprocess.Popen]:
    procs = []
    for ap in autopilots:
        where = folder / f"{ap.kind}-{ap.instance}"
        where.mkdir(parents=True, exist_ok=True)
        argv, env = ap.command(paths, where)
        log = open(where / "out.log", "wb")  # noqa: SIM115 (the child keeps it)
        procs.append(
            subprocess.Popen(
                argv,
                cwd=where,
                env=env,
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                start_new_session=True,
            )  # fmt: skip
        )
        log.close()
    return procs


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + STOP_S
    for p in procs:
        try:
            p.wait(max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def _fly(m: Measurement, scenario: Scenario, paths, folder: Path) -> tuple[int, dict | None]:
    """Start the autopilots, fly `fleetmpc up`, stop them: (up's exit status, its metrics)."""
    folder.mkdir(parents=True, exist_ok=True)
    autopilots = [
        Autopilot(kind, vehicle_home(scenario, vid)) for vid, kind in m.autopilots.items()
    ]
    argv = [sys.executable, "-m", "fleetmpc.cli", "up", str(m.scenario), "--speed", "1"]
    argv += ["--viewer", "none", "--run-dir", str(folder / "up")]
    for ap in autopilots:
        argv += ["--mavlink", f"{ap.home.vehicle_id}={ap.url}"]
    if m.freeze_agent is not None:
        faults = folder / "freeze.toml"
        faults.write_text(
            f'[[faults]]\nkind = "freeze"\nprocess = "agent-{m.freeze_agent}"\n'
            "start_s = 10.0\nduration_s = 3.0\n"
        )
        argv += ["--faults", str(faults)]
    procs = _start(autopilots, paths, folder)
    try:
        time.sleep(BOOT_S)
        with open(folder / "up.log", "wb") as log:
            code = subprocess.run(
                argv, stdout=log, stderr=subprocess.STDOUT, check=False
            ).returncode
    finally:
        _stop(procs)
    metrics = folder / "up" / "metrics.json"
    return code, json.loads(metrics.read_text()) if metrics.is_file() else None


def _row(m: Measurement, k: int, code: int, metrics: dict | None, scenario: Scenario) -> str:
    if metrics is None:
        return f"{m.name:<26} {k:>3}  no metrics (fleetmpc up exited with {code})"
    errs = " / ".join(f"{e:.3f}" for e in metrics["separation_error_m"])
    missed = judge(metrics, scenario.controller.d_safe_m)
    verdict = "met" if not missed else "missed: " + ", ".join(missed)
    return (
        f"{m.name:<26} {k:>3}  {errs:<24} {metrics['centre_distance_error_m']:>8.3f}"
        f" {metrics['min_separation_m']:>8.2f}  {verdict}"
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--px4",
        required=True,
        metavar="DIR",
        help="the folder PX4's SITL build made (bin/px4, etc/)",
    )
    parser.add_argument("--arducopter", metavar="BIN", help="ArduPilot's arducopter SITL binary")
    parser.add_argument("--arducopter-defaults", metavar="FILE", help="its default parameters file")
    parser.add_argument("--scenarios", default="scenarios", help="folder of the shipped scenarios")
    parser.add_argument("--runs", type=int, default=3, help="runs of each measurement")
    parser.add_argument("--run-dir", default="runs/real-autopilots", help="logs and recordings")


def _check(args: argparse.Namespace) -> None:
    if not (Path(args.px4) / "bin" / "px4").is_file():
        raise ConfigError("--px4", f"no bin/px4 under {args.px4}: give PX4's build folder")
    if args.arducopter and not args.arducopter_defaults:
        raise ConfigError(
            "--arducopter-defaults", "needed with --arducopter (its default parameters file)"
        )
    if args.runs < 1:
        raise ConfigError("--runs", f"must be at least 1, got {args.runs}")


def run(args: argparse.Namespace) -> int:
    _check(args)
    root = Path(args.run_dir)
    print(f"{'measurement':<26} run  {'separation errors m':<24} {'centre m':>8} {'min sep':>8}")
    all_met = True
    for m in measurements(Path(args.scenarios), arducopter=bool(args.arducopter)):
        scenario = load_scenario(m.scenario)
        for k in range(1, args.runs + 1):
            folder = root / m.name.replace(" ", "-").replace(",", "") / f"run-{k}"
            code, metrics = _fly(m, scenario, args, folder)
            all_met &= (
                code == 0
                and metrics is not None
                and not judge(metrics, scenario.controller.d_safe_m)
            )
            print(_row(m, k, code, metrics, scenario), flush=True)
    return 0 if all_met else 1
