"""One palette for the viewer and the figures: a colour per vehicle that does not repeat."""

import numpy as np

from fleetmpc.gcs.palette import (
    CENTRE_RGB,
    FIRST_RGB,
    PALETTE_SIZE,
    TARGET_RGB,
    lab_of_rgb,
    pair_colour,
    vehicle_colour,
)


def _nearest_lab(colours: list) -> float:
    """The smallest CIELAB distance between two of the colours."""
    lab = lab_of_rgb(np.array(colours))
    d = np.linalg.norm(lab[:, None] - lab[None], axis=-1)
    return float(d[np.triu_indices(len(colours), 1)].min())


def test_the_first_eight_are_the_paper_figures_tab10():
    assert [vehicle_colour(i) for i in range(8)] == list(FIRST_RGB)


def test_no_colour_repeats_nor_wears_the_centre_or_target_colour():
    colours = [vehicle_colour(i) for i in range(PALETTE_SIZE)]
    assert len(set(colours)) == PALETTE_SIZE
    assert CENTRE_RGB not in colours and TARGET_RGB not in colours
    assert vehicle_colour(PALETTE_SIZE) == vehicle_colour(0)  # (past it, they repeat)


def test_a_fleet_of_fifty_is_told_apart_as_well_as_tab10_tells_eight():
    assert _nearest_lab(list(FIRST_RGB)) > 27  # (tab10 less grey and cyan: 27.7)
    assert _nearest_lab([vehicle_colour(i) for i in range(50)]) > 20
    assert _nearest_lab([vehicle_colour(i) for i in range(100)]) > 14
    # Each reads on the viewer's dark background and on a white page.
    lightness = lab_of_rgb(np.array([vehicle_colour(i) for i in range(PALETTE_SIZE)]))[:, 0]
    assert lightness.min() >= 40 and lightness.max() <= 85


def test_a_pair_never_wears_a_vehicles_colour():
    for n in (3, 12, 20):
        vehicles = {vehicle_colour(i) for i in range(n)}
        pairs = [pair_colour(p, vehicles=n) for p in range(n * (n - 1) // 2)]
        assert not vehicles & set(pairs) and len(set(pairs)) == len(pairs), n
