"""How a learned run's bias along the track becomes slot error (docs/design.md, "Where the calm
scenarios' ratio comes from").

Each scenario is flown in lockstep with learning as usual, in its wind and, with --mean-wind, in
its mean wind alone (its slow sinusoid taken out). Over the last 10 s, for each vehicle: the mean
error along its track of the velocity its learned model predicts at the commanded speed
(a_V V + d against the truth's), and its mean slot error along the track; then the slope of the
second on the first across the fleet [s] (least squares through the origin).

    python tools/drift_bias.py scenarios/grid9.toml [--seed 51] [--mean-wind]
"""

import argparse
import tomllib

import numpy as np

from fleetmpc.gcs.record import FlightRecord
from fleetmpc.lockstep.flight import run_lockstep
from fleetmpc.scenario import parse_scenario

LAST_S = 10.0


def _along(record: FlightRecord) -> tuple[np.ndarray, np.ndarray]:
    """Each vehicle's mean velocity-model error and mean slot error along its track over the
    last LAST_S, (N,) each [m/s], [m]."""
    last = record.t_s >= record.t_s[-1] - LAST_S
    heading = record.truth[last, :, 2]
    track = np.stack((np.cos(heading), np.sin(heading)), axis=-1)
    beta, truth = record.beta[last], record.beta_truth[last]
    speed = record.command[last, :, 0]
    model = ((beta[..., 0] - truth[..., 0]) * speed)[..., None] * track
    model += beta[..., 2:4] - truth[..., 2:4]
    slot = record.truth[last, :, :2] - record.slots[last]
    return (model * track).sum(-1).mean(0), (slot * track).sum(-1).mean(0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario")
    parser.add_argument("--seed", type=int, default=None)
    parser.add_argument("--mean-wind", action="store_true", help="the mean wind alone")
    args = parser.parse_args()
    with open(args.scenario, "rb") as f:
        doc = tomllib.load(f)
    if args.mean_wind:  # (parsed again, so that the learner's forecast has no sinusoid either)
        tables = [doc.get("truth", {}), *(v.get("truth", {}) for v in doc.get("vehicles", []))]
        for wind in (t.get("wind", {}) for t in tables):
            for key in ("gust_amplitude_m_s", "gust_period_s", "gust_phase_rad"):
                wind.pop(key, None)
    sc = parse_scenario(doc, source=args.scenario)
    record = run_lockstep(sc, seed=args.seed)
    bias, offset = _along(record)
    slope = float(bias.dot(offset) / bias.dot(bias))
    for vid, b, o in zip(sc.vehicle_ids, bias, offset, strict=True):
        print(f"UAV {vid}: model along the track {1e3 * b:+6.1f} mm/s, slot {1e3 * o:+6.1f} mm")
    print(f"slot error along the track per model bias: {slope:+.1f} s")


if __name__ == "__main__":
    main()
