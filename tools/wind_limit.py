"""What the wind costs the formation: `fleetmpc check`'s figures against lockstep runs
(docs/design.md, "What the controller leaves of the wind").

Each case is a scenario with some settings changed; each is flown with the known model (or, with
--learned, learning as usual) in its wind and in its mean wind alone, over the seeds, and the
wind's share of the slot RMS (all vehicles, from t = 20 s on) is the quadrature difference of
the two.

    python tools/wind_limit.py [--seeds 4] [--learned]
"""

import argparse
import copy
import math
import tomllib
from pathlib import Path

import numpy as np

from fleetmpc.check.wind_report import drift_filter, wind_share_m
from fleetmpc.lockstep.flight import run_lockstep
from fleetmpc.scenario import Scenario, parse_scenario

ROOT = Path(__file__).resolve().parents[1]
SETTLED_S = 20.0


def _turbulence(sigma: float, length_m: float, time_s: float, mean=(0.3, -0.2)) -> dict:
    t = {"sigma_m_s": sigma, "length_scale_m": length_m, "time_scale_s": time_s}
    return {"truth": {"wind": {"mean_m_s": list(mean), "turbulence": t}}}


SLOW = {"target": {"velocity_m_s": [0.5, 0.5]}, "controller": {"reference_speed_m_s": 0.7071}}
CASES = [
    ("turbulence-moderate (0.15 m/s, 20 m, 5 s)", "turbulence-moderate", {}),
    ("the same at 0.08 m/s", "turbulence-moderate", _turbulence(0.08, 20.0, 5.0)),
    ("the same, 6 m and 1.5 s", "turbulence-moderate", _turbulence(0.15, 6.0, 1.5)),
    ("the same, 60 m and 15 s", "turbulence-moderate", _turbulence(0.15, 60.0, 15.0)),
    ("the same, horizon 8", "turbulence-moderate", {"controller": {"horizon": 8}}),
    ("the same at 0.71 m/s", "turbulence-moderate", SLOW),
    ("gusty-square (0.2 m/s over 20 s, 8 vehicles)", "gusty-square", {}),
    (
        "wedge-circle, turbulence 0.12 m/s, 15 m, 4 s",
        "wedge-circle",
        _turbulence(0.12, 15.0, 4.0, (0.2, 0.2)),
    ),
]


def _merged(doc: dict, changes: dict) -> dict:
    out = copy.deepcopy(doc)
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict) and key != "wind":
            out[key] = _merged(out[key], value)
        else:
            out[key] = value
    return out


def _slot_errors(doc: dict, seed: int, *, in_track_frame: bool = False, known: bool = True):
    """Sample times (K,) and each vehicle's offset from its slot (K, N, 2), known model (or
    learned); `in_track_frame`: along and across the vehicle's heading, not North and East."""
    rec = run_lockstep(parse_scenario(doc), known_model=known, seed=seed)
    error = rec.truth[:, :, :2] - rec.slots
    if in_track_frame:
        c, s = np.cos(rec.truth[:, :, 2]), np.sin(rec.truth[:, :, 2])
        error = np.stack(
            [c * error[..., 0] + s * error[..., 1], c * error[..., 1] - s * error[..., 0]], axis=-1
        )
    return rec.t_s, error


def along_and_across(name: str, seeds: list[int]) -> list[tuple[float, float]]:
    """Slot RMS along and across the track [m], in the case's wind and in its mean alone."""
    rows = []
    for doc in _case(name, {})[:2]:
        squares = []
        for seed in seeds:
            t_s, error = _slot_errors(doc, seed, in_track_frame=True)
            squares.append(np.mean(error[t_s >= SETTLED_S] ** 2, axis=(0, 1)))
        rows.append(tuple(np.sqrt(np.mean(squares, axis=0)).tolist()))
    return rows


def _slot_rms(doc: dict, seeds: list[int], known: bool) -> float:
    squares = []
    for seed in seeds:
        t_s, error = _slot_errors(doc, seed, known=known)
        squares.append(np.mean(np.sum(error[t_s >= SETTLED_S] ** 2, axis=-1)))
    return math.sqrt(float(np.mean(squares)))


def _case(name: str, changes: dict) -> tuple[dict, dict, Scenario]:
    """The case's document, the same in its mean wind alone, and the case's scenario."""
    doc = _merged(tomllib.loads((ROOT / "scenarios" / f"{name}.toml").read_text()), changes)
    scenario = parse_scenario(doc)
    mean = list(scenario.vehicles[0].truth.wind.mean_m_s)
    calm = _merged(doc, {"truth": {"wind": {"mean_m_s": mean}}})
    return doc, calm, scenario


def measure(name: str, changes: dict, seeds: list[int], known: bool) -> tuple[float, float]:
    """(check's figure, the measured share) for one case [m]."""
    doc, calm, scenario = _case(name, changes)
    lag = 0.0 if known else 1.0 / drift_filter(scenario).bandwidth_rad_s
    airspeed = scenario.controller.reference_speed_m_s
    predicted = wind_share_m(scenario.vehicles[0].truth.wind, airspeed, lag)
    windy_rms, calm_rms = _slot_rms(doc, seeds, known), _slot_rms(calm, seeds, known)
    return predicted, math.sqrt(max(windy_rms**2 - calm_rms**2, 0.0))


def gust_peaks(seeds: list[int]) -> np.ndarray:
    """scenarios/gust-in-turn.toml: each vehicle's largest offset that the gust alone causes
    (the gusty run's slot error less the mean-wind run's, same seed) [m], over the seeds."""
    doc, calm, _ = _case("gust-in-turn", {})
    peaks = [
        np.linalg.norm(_slot_errors(doc, seed)[1] - _slot_errors(calm, seed)[1], axis=-1)
        for seed in seeds
    ]
    return np.max(np.concatenate(peaks), axis=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4, help="seeds 1..N per case (default 4)")
    parser.add_argument("--learned", action="store_true", help="learned runs, not known-model")
    args = parser.parse_args()
    seeds = list(range(1, args.seeds + 1))
    print(f"{'case':<48} {'check':>7} {'flown':>7} {'ratio':>6}")
    for label, name, changes in CASES:
        predicted, flown = measure(name, changes, seeds, not args.learned)
        print(f"{label:<48} {predicted:7.3f} {flown:7.3f} {flown / predicted:6.2f}", flush=True)
    if args.learned:
        return
    (along, across), (calm_along, calm_across) = along_and_across("turbulence-moderate", seeds)
    print(
        f"turbulence-moderate: along the track {along:.3f} m, across {across:.3f} m "
        f"(mean wind alone: {calm_along:.3f}, {calm_across:.3f} m)"
    )
    peaks = ", ".join(f"{p:.3f}" for p in gust_peaks(seeds))
    print(f"gust-in-turn: the gust's own offset, largest per vehicle [m]: {peaks}")


if __name__ == "__main__":
    main()
