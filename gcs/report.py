"""`fleetmpc report RUN.rrd --out DIR`: the paper's figures and the metrics from a recording.

The recording is read back into a FlightRecord (`fleetmpc.gcs.rrd_reader`), then the same
`write_figures` and metrics as `fleetmpc sim` and the ground station run on it
(`judged_metrics`): the metrics are those `sim --metrics` (or the ground station's `--metrics`)
wrote for the same run, key by key, with the facts logged at its start and end (a live run's
periods recorded, the vehicles it had ground truth for), and the recording's id.
"""

import argparse
import json
from pathlib import Path

from fleetmpc.gcs.figures import write_figures
from fleetmpc.gcs.metrics import judged_metrics, known_model_figures
from fleetmpc.gcs.rrd_reader import read_recording

__all__ = ["METRICS_FILE", "add_arguments", "run"]

METRICS_FILE = "metrics.json"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", help="Rerun recording (.rrd) written by `fleetmpc sim --rrd`")
    parser.add_argument(
        "--out", required=True, metavar="DIR", help="folder for the figures and metrics.json"
    )


def run(args: argparse.Namespace) -> int:
    loaded = read_recording(args.recording)
    rec = loaded.record
    metrics = {
        **loaded.run_info,
        "scenario": rec.scenario,
        "duration_s": float(rec.t_s[-1]),
        "recording_id": loaded.recording_id,
        **judged_metrics(
            rec,
            ground_truth=loaded.run_end.get("ground_truth"),
            target_source=loaded.run_info.get("target_source", "script"),
        ),
        **{k: v for k, v in loaded.run_end.items() if k != "network"},
    }
    known_rms = loaded.run_info.get("known_model_formation_rms_m")
    if known_rms is not None:
        metrics |= known_model_figures(metrics, known_rms)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / METRICS_FILE
    path.write_text(json.dumps(metrics, indent=2) + "\n")
    print(f"metrics: {path}")
    for p in write_figures(rec, out):
        print(f"figure: {p}")
    return 0
