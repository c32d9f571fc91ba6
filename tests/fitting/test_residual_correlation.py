"""The residuals' spatial correlation that scales the fit's standard errors (fitting._fit.residual_correlation)."""

import numpy as np
import pytest

from fitting._fit import _tile_sandwich_diagonal, residual_correlation


def test_independent_pixels_count_once():
    residuals = np.random.default_rng(0).normal(size=(96, 128, 3))
    assert residual_correlation(residuals.ravel(), residuals.shape) == pytest.approx(1.0, abs=0.1)


@pytest.mark.parametrize("side", [2, 4, 8])
def test_a_residual_constant_over_blocks_counts_once_per_block(side):
    blocks = np.random.default_rng(1).normal(size=(96 // side, 128 // side, 3))
    residuals = np.repeat(np.repeat(blocks, side, axis=0), side, axis=1)
    assert residual_correlation(residuals.ravel(), residuals.shape) == pytest.approx(side**2, rel=0.1)


def test_several_plates_are_measured_together_and_tiny_images_are_skipped():
    rng = np.random.default_rng(2)
    smooth = np.repeat(np.repeat(rng.normal(size=(12, 16, 3)), 8, axis=0), 8, axis=1)
    noise = rng.normal(size=(96, 128, 3))
    both = residual_correlation(np.concatenate([smooth.ravel(), noise.ravel()]), [smooth.shape, noise.shape])
    assert 1.0 < both < residual_correlation(smooth.ravel(), smooth.shape)
    assert residual_correlation(np.ones(3), (1, 1, 3)) == 1.0
    assert residual_correlation(np.ones(12), None) == 1.0


def _linear_fit_errors(noise, columns):
    """Classic s^2 (J^T J)^-1 and the 2 x 2-tile sandwich errors of a linear least-squares fit."""
    normal = columns @ columns.T
    solution = np.linalg.solve(normal, columns @ noise.ravel())
    residual = noise.ravel() - columns.T @ solution
    scatter = residual @ residual / (residual.size - columns.shape[0])
    classic = np.sqrt(np.diag(np.linalg.inv(normal)) * scatter)
    robust = np.sqrt(_tile_sandwich_diagonal(columns, residual, [noise.shape], normal, 2))
    return classic, robust


def test_sandwich_errors_equal_the_classic_for_independent_noise_and_grow_with_correlated_noise():
    """A linear model with smooth columns over a 96 x 128 image: for independent noise the tile
    sandwich agrees with s^2 (J^T J)^-1; for noise constant over 2 x 2 tiles (each tile one draw)
    a parameter's true spread is 2x the classic error's, and the sandwich finds that factor."""
    rng = np.random.default_rng(4)
    rows, cols = np.indices((96, 128)) / 64.0
    columns = np.stack([np.repeat((f(rows, cols))[..., None], 3, -1).ravel() for f in (lambda y, x: np.ones_like(x), lambda y, x: x, lambda y, x: y * x)])
    classic, robust = _linear_fit_errors(rng.normal(size=(96, 128, 3)), columns)
    np.testing.assert_allclose(robust / classic, 1.0, atol=0.15)
    tiles = np.repeat(np.repeat(rng.normal(size=(48, 64, 3)), 2, axis=0), 2, axis=1)
    classic, robust = _linear_fit_errors(tiles, columns)
    np.testing.assert_allclose(robust / classic, 2.0, rtol=0.15)
