"""The paper's Figs. 1-4 (and the learned parameters) from a FlightRecord, as PNG files.

Each vehicle, and each pair, wears the colour it has in the viewer (`fleetmpc.gcs.palette`). A
legend names at most `LABELLED_VEHICLES_MAX` lines, as the viewer's map labels at most that many
vehicles, and stands beside its plot, never on the data."""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from fleetmpc.gcs.metrics import pair_indices  # noqa: E402
from fleetmpc.gcs.palette import (  # noqa: E402
    CENTRE_RGB,
    LABELLED_VEHICLES_MAX,
    as_unit_rgb,
    pair_colour,
    vehicle_colour,
)
from fleetmpc.gcs.record import FlightRecord  # noqa: E402

__all__ = ["FIGURE_FILES", "write_figures"]

FIGURE_FILES = (
    "fig1_paths.png",
    "fig2_c.png",
    "fig3_separation.png",
    "fig4_centre_distance.png",
    "fig5_beta.png",
)


def _colour(i: int) -> tuple[float, float, float]:
    """Vehicle i's colour: the viewer's (`fleetmpc.gcs.palette`)."""
    return as_unit_rgb(vehicle_colour(i))


def _legend(ax, entries: int, *, fontsize: float = 8) -> None:
    """A legend beside the plot (outside its axes, so it covers no data), unless it would name
    more than `LABELLED_VEHICLES_MAX` coloured lines (a large fleet's lines are told apart by
    their colours, as on the map)."""
    if entries <= LABELLED_VEHICLES_MAX:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=fontsize)


def write_figures(rec: FlightRecord, out_dir: str | Path) -> list[Path]:
    """Write the figures into out_dir and return their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ids = rec.vehicle_ids
    pos = rec.truth[:, :, :2]
    centre = np.mean(pos - rec.slot_offsets_world, axis=1)
    paths = []

    # Fig. 1: paths (East to the right, North up), target and formation centre.
    fig, ax = plt.subplots(figsize=(7, 6))
    for i, vid in enumerate(ids):
        ax.plot(pos[:, i, 1], pos[:, i, 0], color=_colour(i), label=f"UAV {vid}")
        ax.plot(pos[0, i, 1], pos[0, i, 0], "o", color=_colour(i))
    ax.plot(rec.target[:, 1], rec.target[:, 0], "k-", label="target")
    centre_colour = as_unit_rgb(CENTRE_RGB)
    ax.plot(centre[:, 1], centre[:, 0], "--", color=centre_colour, label="formation centre")
    ax.set_xlabel("East y [m]")
    ax.set_ylabel("North x [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"{rec.scenario}: paths")
    _legend(ax, len(ids))
    paths.append(_save(fig, out / FIGURE_FILES[0]))

    # Fig. 2: the MPC's decision variables c_i (first of the horizon).
    fig, axes = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    for i, vid in enumerate(ids):
        axes[0].plot(rec.t_s, rec.c[:, i, 0], color=_colour(i), label=f"UAV {vid}")
        axes[1].plot(rec.t_s, rec.c[:, i, 1], color=_colour(i))
    axes[0].set_ylabel("c speed [m/s]")
    axes[1].set_ylabel("c yaw rate [rad/s]")
    axes[1].set_xlabel("t [s]")
    _legend(axes[0], len(ids))
    axes[0].set_title("MPC inputs c_i (converge to 0 at steady state)")
    paths.append(_save(fig, out / FIGURE_FILES[1]))

    # Fig. 3: neighbour separations against their desired values.
    fig, ax = plt.subplots(figsize=(7, 4))
    pairs = pair_indices(len(ids))
    for k, (a, b) in enumerate(pairs):
        d = np.linalg.norm(pos[:, a] - pos[:, b], axis=1)
        colour = as_unit_rgb(pair_colour(k, vehicles=len(ids)))
        ax.plot(rec.t_s, d, color=colour, label=f"UAV {ids[a]}-{ids[b]}")
        ax.axhline(rec.desired_distance_m[a, b], color=colour, ls=":", lw=0.8)
    ax.axhline(rec.d_safe_m, color="k", ls="--", lw=0.8, label="d_safe")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("separation [m]")
    ax.set_title("separation between vehicles (dotted: desired)")
    _legend(ax, len(pairs))
    paths.append(_save(fig, out / FIGURE_FILES[2]))

    # Fig. 4: target to formation-centre distance.
    fig, ax = plt.subplots(figsize=(7, 4))
    distance = np.linalg.norm(centre - rec.target, axis=1)
    ax.plot(rec.t_s, distance, color=centre_colour, label="|centre - target|")
    ax.axhline(rec.trail_m, color="k", ls=":", label="d_s")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("distance [m]")
    ax.set_title("target to formation centre")
    _legend(ax, 2)
    paths.append(_save(fig, out / FIGURE_FILES[3]))

    # Learned parameters against truth.
    names = (
        "speed effectiveness a_V",
        "yaw-rate effectiveness a_w",
        "drift North [m/s]",
        "drift East [m/s]",
    )
    fig, axes = plt.subplots(2, 2, figsize=(9, 6), sharex=True)
    for p, ax in enumerate(axes.ravel()):
        for i, vid in enumerate(ids):
            ax.plot(rec.t_s, rec.beta[:, i, p], color=_colour(i), label=f"UAV {vid}")
            ax.plot(rec.t_s, rec.beta_truth[:, i, p], color=_colour(i), ls=":", lw=0.9)
        ax.set_title(names[p], fontsize=9)
    for ax in axes[1]:
        ax.set_xlabel("t [s]")
    _legend(axes[0, 1], len(ids), fontsize=7)
    fig.suptitle("learned parameters (solid) against truth (dotted)")
    paths.append(_save(fig, out / FIGURE_FILES[4]))
    return paths


def _save(fig: "plt.Figure", path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
