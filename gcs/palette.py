"""One colour per vehicle, everywhere a run is drawn: the viewer's map and series (the recording's
statics, `fleetmpc.gcs.blueprint`) and the report's figures (`fleetmpc.gcs.figures`).

Vehicle i (fleet order) takes colour i whatever the fleet's size; a series of vehicle pairs
takes the colours after the vehicles', so a pair's line never wears a vehicle's colour. The first
eight colours are matplotlib's "tab10" less its grey and cyan (cyan is the centre distance's);
each next one is the candidate farthest, in CIELAB, from every colour given out before it (and
from the centre's cyan and the target's black), so none of the first `PALETTE_SIZE` repeats and
the nearest two of a fleet's first 50 are 21 CIELAB units apart (tab10's nearest two are 28).
Candidates are a grid of hues, lightnesses and saturations whose CIELAB lightness reads on the
viewer's dark background and on a white page. As 8-bit RGB.
"""

import colorsys
from functools import lru_cache

import numpy as np

__all__ = [
    "CENTRE_RGB",
    "FIRST_RGB",
    "LABELLED_VEHICLES_MAX",
    "PALETTE_SIZE",
    "TARGET_RGB",
    "as_unit_rgb",
    "lab_of_rgb",
    "lighter",
    "pair_colour",
    "vehicle_colour",
]

FIRST_RGB = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (188, 189, 34),
)
"""The first eight colours, in the order they are given out."""
CENTRE_RGB = (23, 190, 207)
"""The formation centre's distance to the target."""
TARGET_RGB = (0, 0, 0)
"""The target and its predicted path."""
PALETTE_SIZE = 256
"""Colours given out before they repeat (vehicles and pairs together)."""
LABELLED_VEHICLES_MAX = 12
"""Largest fleet whose vehicles are named on the map and in the figures' legends; a larger
fleet's are told apart by colour (its names are in the recording, not shown)."""

_HUES = 72
_LIGHTNESS = (0.3, 0.4, 0.5, 0.6, 0.7)
_SATURATION = (0.5, 0.75, 1.0)
_LAB_LIGHTNESS = (40.0, 85.0)
"""CIELAB lightness of a candidate: seen on the viewer's dark background and on a white page."""


def lab_of_rgb(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) 8-bit sRGB -> (..., 3) CIELAB (D65 white): L in 0 .. 100, a, b."""
    c = np.asarray(rgb, dtype=np.float64) / 255.0
    linear = np.where(c > 0.04045, ((c + 0.055) / 1.055) ** 2.4, c / 12.92)
    to_xyz = np.array(
        [[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]]
    )
    xyz = linear @ to_xyz.T / np.array([0.9505, 1.0, 1.089])
    delta = 6 / 29
    f = np.where(xyz > delta**3, np.cbrt(xyz), xyz / (3 * delta**2) + 4 / 29)
    return np.stack(
        [116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])],
        axis=-1,
    )


@lru_cache(maxsize=1)
def _palette() -> tuple[tuple[int, int, int], ...]:
    """The `PALETTE_SIZE` colours: `FIRST_RGB`, then each the candidate farthest from the rest."""
    grid = {
        tuple(round(255 * x) for x in colorsys.hls_to_rgb(h / _HUES, lightness, saturation))
        for h in range(_HUES)
        for lightness in _LIGHTNESS
        for saturation in _SATURATION
    }
    candidates = np.array(sorted(grid))
    lightness = lab_of_rgb(candidates)[:, 0]
    candidates = candidates[(lightness >= _LAB_LIGHTNESS[0]) & (lightness <= _LAB_LIGHTNESS[1])]
    lab = lab_of_rgb(candidates)
    taken = [*FIRST_RGB, CENTRE_RGB, TARGET_RGB]
    nearest = np.linalg.norm(lab[:, None] - lab_of_rgb(np.array(taken))[None], axis=-1).min(1)
    out = list(FIRST_RGB)
    while len(out) < PALETTE_SIZE:
        j = int(np.argmax(nearest))
        out.append(tuple(int(v) for v in candidates[j]))
        nearest = np.minimum(nearest, np.linalg.norm(lab - lab[j], axis=-1))
    return tuple(out)


def vehicle_colour(i: int) -> tuple[int, int, int]:
    """The colour of the i-th vehicle in fleet order (the same in a fleet of any size)."""
    return _palette()[i % PALETTE_SIZE]


def pair_colour(p: int, *, vehicles: int) -> tuple[int, int, int]:
    """The colour of the p-th vehicle pair (`pair_indices` order) of a fleet of `vehicles`."""
    return _palette()[(vehicles + p) % PALETTE_SIZE]


def lighter(rgb: tuple[int, int, int]) -> tuple[int, int, int]:
    """A colour halfway to white: a vehicle's second line (its plan on the map, the second
    parameter of a pair in a series)."""
    return tuple((c + 255) // 2 for c in rgb)


def as_unit_rgb(rgb: tuple[int, ...]) -> tuple[float, ...]:
    """An 8-bit RGB(A) colour as matplotlib takes it (each channel in 0 .. 1)."""
    return tuple(c / 255 for c in rgb)
