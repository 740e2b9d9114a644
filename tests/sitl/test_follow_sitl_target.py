"""Following another vehicle, live: three agents on our SITL follow a fourth SITL vehicle that
this test's own script flies through a square at 1 m/s (offboard velocity setpoints), observed
only through its MAVLink ground-station stream (GLOBAL_POSITION_INT at 5 Hz) by `fleetmpc up
--target mavlink:udpin:... --target-sysid 4`. Judged against the fourth vehicle's own positions
(LOCAL_POSITION_NED on this test's link), placed on fleet time by this test."""

import json
import math
import re
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import scenario_on_free_ports
from sim_client import SimClient, fly_offboard, free_port

from fleetmpc.gcs.rrd_reader import read_recording
from fleetmpc.onboard.core.agent import reference_course_limit
from fleetmpc.onboard.core.formation import Formation, true_reference
from fleetmpc.protocol.mavlink_setpoint import Frame, SetpointFields, TypeMask
from fleetmpc.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]

SQUARE = ((10.0, 0.0), (40.0, 0.0), (40.0, 30.0), (10.0, 30.0), (10.0, 0.0))
"""The target vehicle's square (North, East) [m], flown at 1 m/s."""

TARGET_SCENARIO = """# The target: a fourth vehicle, ideal (what is commanded is what flies).
name = "square-target"
seed = 1
[truth]
speed_effectiveness = 1.0
yaw_rate_effectiveness = 1.0
actuator_lag_s = 0.0
position_noise_m = 0.0
heading_noise_rad = 0.0
[[vehicles]]
id = 1
initial = [-50.0, 0.0, 0.0]
slot_m = [0.0, 0.0]
[[vehicles]]
id = 2
initial = [-50.0, 10.0, 0.0]
slot_m = [0.0, 10.0]
[[vehicles]]
id = 3
initial = [-50.0, 20.0, 0.0]
slot_m = [0.0, 20.0]
[[vehicles]]
id = 4
initial = [10.0, 0.0, 0.0]
slot_m = [0.0, 30.0]
"""


def _fleet_flying(status: Path) -> float | None:
    try:
        snap = json.loads(status.read_text())
    except (OSError, ValueError):
        return None
    return snap.get("fleet_s") if snap.get("phase") == "flying" else None


def _square_setpoint(position, leg: int):
    """Velocity along the leg at 1 m/s, with a pull back onto its line; the heading along it."""
    (ax, ay), (bx, by) = SQUARE[leg], SQUARE[leg + 1]
    length = math.hypot(bx - ax, by - ay)
    ux, uy = (bx - ax) / length, (by - ay) / length
    px, py = position
    cross = -(px - ax) * uy + (py - ay) * ux  # (to the right of the leg)
    vx, vy = ux + 0.5 * cross * uy, uy - 0.5 * cross * ux
    along = (px - ax) * ux + (py - ay) * uy
    return along >= length, SetpointFields(
        Frame.LOCAL_NED, TypeMask.VELOCITY_YAW, vx_m_s=vx, vy_m_s=vy, yaw_rad=math.atan2(uy, ux)
    )


@pytest.mark.slow
def test_up_follows_another_sitl_vehicle_flying_a_square(tmp_path, processes):
    speed = 4.0
    fleet_path = scenario_on_free_ports(ROOT / "scenarios" / "paper.toml", tmp_path / "fleet.toml")
    (tmp_path / "t.toml").write_text(TARGET_SCENARIO)
    target_path = scenario_on_free_ports(tmp_path / "t.toml", tmp_path / "target.toml")
    listen = SimClient.listen_udp(target_system=4)
    relay_port = free_port()
    # The fourth vehicle, its offboard link to this test, its ground-station stream to the
    # target process; flown by this test's script alone.
    processes.fleetmpc(
        "sitl-4", "sitl", "--scenario", str(target_path), "--vehicle", "4",
        "--speed", f"{speed:g}", "--offboard-port", str(listen.port),
        "--offboard-local-port", "0", "--gcs-port", str(relay_port), "--gcs-local-port", "0",
    )  # fmt: skip
    hover = SetpointFields(Frame.LOCAL_NED, TypeMask.VELOCITY_YAW)
    fly_offboard(listen, hover)
    run_dir = tmp_path / "run"
    up = processes.fleetmpc(
        "up", "up", str(fleet_path), "--speed", f"{speed:g}", "--duration", "150",
        "--viewer", "none", "--quiet", "--run-dir", str(run_dir),
        "--target", f"mavlink:udpin:127.0.0.1:{relay_port}", "--target-sysid", "4",
    )  # fmt: skip
    # The target's truth on fleet time: its positions by its boot time, and the offset from its
    # boot time to fleet time, the least (wall time of receipt - fleet epoch) x speed - boot time.
    track, offsets = [], []
    origin = SQUARE[0]  # (its local frame's origin: where it booted)
    epoch_ns = None
    leg, corners = 0, []
    deadline = time.monotonic() + 240.0
    while up.proc.poll() is None and time.monotonic() < deadline:
        m = listen.pump(0.02)
        if epoch_ns is None:
            found = re.search(r"epoch_ns (\d+)", (run_dir / "logs" / "target.log").read_text()
                              if (run_dir / "logs" / "target.log").exists() else "")  # fmt: skip
            epoch_ns = int(found.group(1)) if found else None
        if m is None or m.get_type() != "LOCAL_POSITION_NED":
            continue
        position = (origin[0] + m.x, origin[1] + m.y)
        track.append((m.time_boot_ms * 1e-3, *position))
        if epoch_ns is not None:
            offsets.append((time.time_ns() - epoch_ns) * 1e-9 * speed - m.time_boot_ms * 1e-3)
        if leg >= len(SQUARE) - 1 or _fleet_flying(run_dir / "status.json") is None:
            listen.stream(hover)
            continue
        done, sp = _square_setpoint(position, leg)
        if done:
            corners.append(m.time_boot_ms * 1e-3)
            leg += 1
            continue
        listen.stream(sp)
    assert up.proc.wait(timeout=60.0) == 0, up.tail()
    assert leg == len(SQUARE) - 1, (
        f"the square was not finished: leg {leg}, {len(track)} positions, last {track[-1:]},"
        f" flying {_fleet_flying(run_dir / 'status.json')}, texts {listen.texts[-5:]}"
    )
    offset = min(offsets)
    record = read_recording(run_dir / "run.rrd").record
    t = record.t_s
    boot = np.array([r[0] for r in track]) + offset
    truth = np.column_stack([np.interp(t, boot, [r[i] for r in track]) for i in (1, 2)])
    velocity = np.gradient(truth, t, axis=0)
    sc = load_scenario(fleet_path)
    formation = Formation(sc.formation)
    limit = reference_course_limit(sc.controller, sc.formation)
    centres, courses = true_reference(formation, limit, truth, velocity, 0.2)
    slots = formation.slots(centres, courses)
    err = np.linalg.norm(record.truth[:, :, :2] - slots, axis=2)
    assert record.min_separation_m >= sc.controller.d_safe_m
    log = (run_dir / "logs" / "target.log").read_text()
    assert "rejected (wrong system)" not in log and "Traceback" not in log, log
    # The last 10 s of each straight leg (ending 1 s before its corner).
    rms = []
    for end in np.array(corners) + offset:
        window = (t >= end - 11.0) & (t <= end - 1.0)
        rms.append(float(np.sqrt(np.mean(err[window] ** 2))))
    print("slot RMS over the last 10 s of each leg [m]:", [f"{r:.3f}" for r in rms])
    print("min separation [m]:", record.min_separation_m, "clock offset [s]:", offset)
    assert max(rms) <= 0.2, rms
    assert math.isfinite(offset)
