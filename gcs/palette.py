"""One colour per vehicle, everywhere a run is drawn: the viewer's map and series (the recording's
statics, `fleetmpc.gcs.blueprint`) and the report's figures (`fleetmpc.gcs.figures`).

Vehicle i (fleet order) takes colour i; a series of vehicle pairs takes the colours after the
vehicles', so a pair's line never wears a vehicle's colour. The palette is matplotlib's
"tab10" less its grey and cyan (cyan is the centre distance's), as 8-bit RGB.
"""

__all__ = ["CENTRE_RGB", "PALETTE_RGB", "as_unit_rgb", "pair_colour", "vehicle_colour"]

PALETTE_RGB = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (188, 189, 34),
)
"""The colours, in the order they are given out (they repeat past the eighth)."""
CENTRE_RGB = (23, 190, 207)
"""The formation centre's distance to the target."""


def vehicle_colour(i: int) -> tuple[int, int, int]:
    """The colour of the i-th vehicle in fleet order."""
    return PALETTE_RGB[i % len(PALETTE_RGB)]


def pair_colour(p: int, *, vehicles: int) -> tuple[int, int, int]:
    """The colour of the p-th vehicle pair (`pair_indices` order) of a fleet of `vehicles`."""
    return PALETTE_RGB[(vehicles + p) % len(PALETTE_RGB)]


def as_unit_rgb(rgb: tuple[int, int, int]) -> tuple[float, float, float]:
    """An 8-bit RGB colour as matplotlib takes it (each channel in 0 .. 1)."""
    return tuple(c / 255 for c in rgb)
