"""How fast Rerun's web viewer redraws a fleet's recording after an input, and how big it is.

    python tools/viewer_bench.py [FLEET ...] [--duration S] [--inputs N] [--rounds R]
                                 [--baseline DIR] [--json FILE]

A FLEET is a vehicle count (the grid of `scenarios/scale/grid50.toml` resized to that many
vehicles, as `fleetmpc bench --scale` flies it), a scenario file, or a recording (`.rrd`,
measured as it is, made with `--duration` seconds); by default
`scenarios/wedge-circle.toml` (5 vehicles), 10, 50 and 100. Each flies `--duration` seconds in
lockstep into a recording (`fleetmpc sim --rrd`), whose size is reported per vehicle-minute.

Redraw after input, as a user sees it (docs/benchmarks.md, "The viewer"): the recording is
served with `rerun --serve-web` on loopback and shown in headless Chromium with software
rendering (SwiftShader), at 1600 x 1000, through the tests' viewer driver
(`tests/viewer.py`: Rerun's analytics off in a private HOME, nothing off the machine). Once
the page has loaded and settled, playback is paused (Space), then `--inputs` clicks on the time
slider move the time cursor back and forth (`scrub_points`). Each is timed on the page's clock
from the press (the event's timeStamp) until the viewer, having drawn the input's effect, has
drawn nothing more for 1.5 s and its frames come at the display's rate again (`viewer.Redraw`:
when each frame that drew was on the screen); each click waits for the page to be at rest so.
The same clicks are then made again with the page hashing each drawn frame's picture, which
slows the frames too much to time them, and says which of the frames changed the picture: the
redraw time is when the timed redraw's last such frame was on the screen (the viewer often
draws the same picture again for several frames after it). Per fleet: the median, p99 and max
over the inputs of every round; also the first frame's time and the last drawn frame's.

With `--baseline DIR` (another checkout, e.g. `git worktree add /tmp/base <commit>`), each
fleet is also recorded by that tree's code, and each round measures both recordings, the two
in turn, so that both see the same machine. Wall-clock times; nothing is asserted.
"""

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import viewer  # noqa: E402  (the tests' viewer driver)

GRID = ROOT / "scenarios" / "scale" / "grid50.toml"
DEFAULT_FLEETS = ("scenarios/wedge-circle.toml", "10", "50", "100")

_CHILD = """
import os, sys
import fleetmpc
fleetmpc.__path__.append(os.getcwd())  # the tree's parts, as its pyproject's package-dir maps them
from fleetmpc.cli import main
sys.exit(main(sys.argv[1:]))
"""
"""`fleetmpc` run from the tree in the working directory."""


def grid_file(count: int, folder: Path) -> Path:
    """`scenarios/scale/grid50.toml` with `count` vehicles (rows of up to 10), as a file."""
    text = GRID.read_text()
    text = re.sub(r'^name = "grid50"', f'name = "grid{count}"', text, flags=re.M)
    text = re.sub(r"count = 50,", f"count = {count},", text)
    text = re.sub(r"columns = 10 }", f"columns = {min(10, count)} }}", text)
    path = folder / f"grid{count}.toml"
    path.write_text(text)
    return path


def record(tree: Path, scenario: Path, rrd: Path, duration_s: float) -> None:
    """Fly `scenario` in lockstep with `tree`'s code into the recording `rrd`."""
    argv = [sys.executable, "-c", _CHILD, "sim", str(scenario), "--rrd", str(rrd)]
    argv += ["--duration", f"{duration_s:g}", "--quiet", "--jobs", "2"]
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run(argv, cwd=tree, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"fleetmpc sim in {tree} failed:\n{done.stdout}\n{done.stderr}")


def vehicles_of(rrd: Path) -> int:
    """The vehicle count a recording's map view names (`map (N UAVs)`)."""
    for view in viewer.recorded_blueprint(rrd).views(hidden=True):
        if found := re.fullmatch(r"map \((\d+) UAVs\)", view.name):
            return int(found[1])
    raise SystemExit(f"{rrd}: no map view")


def redraws(rrd: Path, workdir: Path, env: dict[str, str], inputs: int) -> list[dict]:
    """The redraws of `inputs` clicks on the time slider, the viewer paused: each timed, then
    each again with the pictures read (`viewer.Viewer.read_pictures`), which says when the
    timed one's picture was final."""
    blueprint = viewer.recorded_blueprint(rrd)
    with viewer.open_viewer(rrd, workdir, env, on_new_document=viewer.FRAME_PROBE) as page:
        settled, _ = page.settle(blueprint, timeout_s=300.0)
        page.redraw_after(lambda: page.press(" ", "Space", 32, " "))  # pause the playback
        passes = []
        for read in (False, True):
            page.read_pictures(read)
            passes.append([_click(page, rrd, x, y) for x, y in viewer.scrub_points(inputs)])
        moved = page.screenshot()
        if np.array_equal(moved, settled):
            raise SystemExit(f"{rrd}: the clicks on the time slider changed nothing")
    return [
        {
            "timed": timed,
            "final_ms": timed.final_ms(read.changed),
            "changed": sum(read.changed or ()),
        }
        for timed, read in zip(*passes, strict=True)
    ]


def _click(page, rrd: Path, x: int, y: int) -> viewer.Redraw:
    redraw = page.redraw_after(lambda: page.click(x, y))
    if redraw.drawn == 0:
        raise SystemExit(f"{rrd}: the viewer drew nothing after a click at {x}, {y}")
    return redraw


def _summary(redraws: list[dict]) -> dict:
    times = [r["final_ms"] for r in redraws]
    timed = [r["timed"] for r in redraws]
    return {
        "frames_drawn_median": float(np.median([r.drawn for r in timed])),
        "frames_changed_median": float(np.median([r["changed"] for r in redraws])),
        "last_drawn_median_ms": float(np.median([r.done_ms for r in timed])),
        "redraw_median_ms": float(np.median(times)),
        "redraw_p99_ms": float(np.percentile(times, 99)),
        "redraw_max_ms": float(np.max(times)),
        "redraw_ms": [round(t, 1) for t in times],
        "first_frame_median_ms": float(np.median([r.first_ms for r in timed])),
        "first_frame_max_ms": float(np.max([r.first_ms for r in timed])),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("fleets", nargs="*", default=list(DEFAULT_FLEETS), metavar="FLEET")
    parser.add_argument("--duration", type=float, default=60.0, metavar="S")
    parser.add_argument("--inputs", type=int, default=10, metavar="N")
    parser.add_argument("--rounds", type=int, default=1, metavar="R")
    parser.add_argument("--baseline", type=Path, metavar="DIR")
    parser.add_argument("--json", type=Path, metavar="FILE")
    parser.add_argument("--keep", type=Path, metavar="DIR", help="keep recordings and shots here")
    args = parser.parse_args(argv)
    if viewer.CHROMIUM is None:
        raise SystemExit("chromium is not installed")
    work = args.keep or Path(tempfile.mkdtemp(prefix="viewer-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    trees = {"this tree": ROOT, **({"baseline": args.baseline.resolve()} if args.baseline else {})}
    env = viewer.rerun_home(work / "home")
    rows = []
    for fleet in args.fleets:
        scenario = grid_file(int(fleet), work) if fleet.isdigit() else Path(fleet).resolve()
        rrds = {}
        for label, tree in trees.items():
            if scenario.suffix == ".rrd":
                rrds[label] = scenario
                continue
            rrds[label] = work / f"{scenario.stem}-{label.replace(' ', '-')}.rrd"
            record(tree, scenario, rrds[label], args.duration)
        times: dict[str, list[dict]] = {label: [] for label in trees}
        for r in range(args.rounds):
            order = list(trees) if r % 2 == 0 else list(reversed(trees))
            for label in order:
                shots = work / f"{rrds[label].stem}-round{r}"
                times[label] += redraws(rrds[label], shots, env, args.inputs)
        for label, rrd in rrds.items():
            n = vehicles_of(rrd)
            row = {
                "fleet": scenario.stem,
                "tree": label,
                "vehicles": n,
                "bytes_per_vehicle_minute": rrd.stat().st_size / (n * args.duration / 60.0),
                **_summary(times[label]),
            }
            rows.append(row)
            print(
                f"{row['fleet']:>14} ({n:3d} UAVs, {label}): "
                f"{row['bytes_per_vehicle_minute'] / 1e3:7.1f} kB per vehicle-minute; redraw "
                f"median {row['redraw_median_ms']:5.0f} ms, p99 {row['redraw_p99_ms']:5.0f} ms,"
                f" max {row['redraw_max_ms']:5.0f} ms; first frame median"
                f" {row['first_frame_median_ms']:5.0f} ms, max {row['first_frame_max_ms']:5.0f} ms"
                f"; last drawn median {row['last_drawn_median_ms']:5.0f} ms"
                f" ({len(times[label])} inputs, median {row['frames_drawn_median']:g} frames"
                f" drawn each, {row['frames_changed_median']:g} of them changed the picture)",
                flush=True,
            )
    load = [round(x, 2) for x in os.getloadavg()]
    print(f"machine load after: {load}; recordings in {work}")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "load": load, "at": time.time()}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
