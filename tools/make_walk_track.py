"""Write the recorded walk the track scenarios fly (scenarios/tracks/walk-dropout.csv).

A person walking at about 1.3 m/s, North-East from (5, 5) m about the default site's home:
straight, a gentle right turn (radius 25 m), straight, a gentle left turn (radius 30 m),
straight. Observed at 5 Hz the way a phone's GPS sees it: a slowly wandering error (first-order
Gauss-Markov, 0.3 m, 15 s) and a little white noise (0.05 m), quantized to 1e-7 degrees, with a
5 s dropout on the straight after the first turn (fixes from 65 s to 70 s missing). Times are the
phone's own, 1000 s after its boot at the walk's start. Deterministic for its seed.

    python tools/make_walk_track.py scenarios/tracks/walk-dropout.csv
"""

import argparse
import math
from pathlib import Path

import numpy as np

from fleetmpc.protocol.local_frame import geodetic_from_ned

HOME = (47.397742, 8.545594)
"""The default site's home (`fleetmpc.scenario.Site`)."""
RATE_HZ = 5.0
DURATION_S = 110.0
DROPOUT_S = (65.0, 70.0)
SOURCE_START_S = 1000.0
LEGS = ((0.0, 30.0), (-1.0 / 25.0, 20.0), (0.0, 40.0), (1.0 / 30.0, 15.0), (0.0, 5.0))
"""(curvature [1/m], duration [s]) of each leg: positive turns left (counter-clockwise)."""


def walk(t_s: np.ndarray) -> np.ndarray:
    """The walker's true (North, East) at times t_s [m]."""
    dt = float(t_s[1] - t_s[0])
    x, y, course = 5.0, 5.0, math.pi / 4
    out = []
    for t in t_s:
        out.append((x, y))
        speed = 1.3 + 0.08 * math.sin(2 * math.pi * t / 23.0)
        elapsed, curvature = t, 0.0
        for kappa, length in LEGS:
            if elapsed < length:
                curvature = kappa
                break
            elapsed -= length
        course -= curvature * speed * dt  # (NED: a left turn lowers the course)
        x += speed * dt * math.cos(course)
        y += speed * dt * math.sin(course)
    return np.array(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--seed", type=int, default=40)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    t = np.arange(0.0, DURATION_S + 1e-9, 1.0 / RATE_HZ)
    true = walk(t)
    tau, sigma = 15.0, 0.3
    a = math.exp(-1.0 / (RATE_HZ * tau))
    wander = np.zeros_like(true)
    wander[0] = sigma * rng.standard_normal(2)
    for k in range(1, len(t)):
        wander[k] = a * wander[k - 1] + sigma * math.sqrt(1 - a * a) * rng.standard_normal(2)
    seen = true + wander + 0.05 * rng.standard_normal(true.shape)
    keep = (t < DROPOUT_S[0]) | (t >= DROPOUT_S[1])
    lines = ["time_s,lat_deg,lon_deg"]
    for tk, (n, e) in zip(t[keep], seen[keep], strict=True):
        lat, lon = geodetic_from_ned(n, e, home_lat_deg=HOME[0], home_lon_deg=HOME[1])
        lines.append(f"{SOURCE_START_S + tk:.1f},{lat:.7f},{lon:.7f}")
    args.out.write_text("\n".join(lines) + "\n")
    print(f"{args.out}: {len(lines) - 1} fixes")


if __name__ == "__main__":
    main()
