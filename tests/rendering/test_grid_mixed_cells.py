"""Mixed cells (corners that disagree about validity: rays lost to a miss or total internal
reflection) are traced again on a finer grid (jaxflare/rendering/_grid_refine.py). A ghost near the
edge of a wide angle's field, whose rays are lost on every side, is mostly such cells: drawn as
four dots each, its energy was 50 % too high on a coarse grid and its image a lattice of dashes."""

from unittest import mock

import numpy as np

from jaxflare import rendering
from jaxflare.rendering import _grid_refine

from .grid_cases import blur, grid, luminance, monte_carlo, scene

LENS, DIRECTION, BLADES, F_NUMBER = "nikon_retrofocus_wide", (0.55, 0.075, -1.0), 7, 4.0
"""A 28 mm retrofocus with a light 29 degrees off axis (its half field is 32.7 degrees)."""
PATHS = ((13, 1), (6, 3), (7, 1))
"""Ghosts whose grids are a third to three quarters mixed cells at 8 cells per side."""
COARSE = (("min_cells", 8), ("max_cells", 8))
FINE = (("min_cells", 64), ("max_cells", 64))


def render(options):
    return grid(LENS, DIRECTION, PATHS, BLADES, F_NUMBER, options=options)


def test_coarse_grid_path_energy_within_three_monte_carlo_standard_errors():
    result = render(COARSE)
    runs = monte_carlo(LENS, DIRECTION, PATHS, BLADES, F_NUMBER)
    for k, path in enumerate(PATHS):
        mc = np.asarray([r.statistics.paths[k].energy for r in runs])
        standard_error = mc.std(ddof=1) / np.sqrt(len(mc))
        energy = result.statistics.paths[k].energy
        assert standard_error > 0
        assert abs(energy - mc.mean()) < 3 * standard_error, (path, energy, mc.mean(), standard_error)


def test_refined_coarse_grid_is_closer_to_a_fine_grid_than_four_dots_per_mixed_cell():
    fine = blur(luminance(render(FINE).image))
    refined = blur(luminance(render(COARSE).image))
    with mock.patch.object(_grid_refine, "MIXED_SUBCELLS", 1):  # each mixed cell traced again as itself: four dots, as before
        plain = rendering.render_grid(scene(LENS, DIRECTION, BLADES, F_NUMBER), paths=list(PATHS), grid_error=1e-9, grid_options=dict(COARSE))
    dots = blur(luminance(plain.image))
    error = np.linalg.norm(refined - fine) / np.linalg.norm(fine)
    error_dots = np.linalg.norm(dots - fine) / np.linalg.norm(fine)
    assert error < 0.5 * error_dots, (error, error_dots)
