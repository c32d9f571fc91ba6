"""The grid estimator agrees with Monte Carlo: each path's energy within three of Monte Carlo's
standard errors (estimated from independent seeds), on two lenses; and the images, blurred a
little, within the Monte Carlo noise."""

import numpy as np
import pytest

from .grid_cases import blur, grid, luminance, monte_carlo, strongest_paths

CASES = [("zeiss_biotar", ((7, 4), (9, 7))), ("tronnier_heliar", None)]


@pytest.mark.parametrize("lens, paths", CASES)
def test_grid_path_energy_within_three_monte_carlo_standard_errors(lens, paths):
    paths = paths or strongest_paths(lens)
    result = grid(lens, paths=paths)
    runs = monte_carlo(lens, paths=paths)
    for k, path in enumerate(paths):
        mc = np.asarray([r.statistics.paths[k].energy for r in runs])
        standard_error = mc.std(ddof=1) / np.sqrt(len(mc))
        energy = result.statistics.paths[k].energy
        assert energy > 0 and standard_error > 0
        assert abs(energy - mc.mean()) < 3 * standard_error, (lens, path, energy, mc.mean(), standard_error)


def test_blurred_grid_image_within_monte_carlo_noise():
    """After a small blur, grid minus the Monte Carlo mean is no larger than the Monte Carlo
    mean's own noise allows (three times its estimated RMS error)."""
    runs = monte_carlo()
    images = np.stack([blur(luminance(r.image)) for r in runs])
    mean = images.mean(axis=0)
    noise_of_mean = np.sqrt(np.sum(images.var(axis=0, ddof=1)) / len(images))
    difference = np.linalg.norm(blur(luminance(grid().image)) - mean)
    assert difference < 3 * noise_of_mean, (difference, noise_of_mean, np.linalg.norm(mean))
