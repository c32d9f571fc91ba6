"""The residuals' spatial correlation that scales the fit's standard errors (fitting._fit.residual_correlation)."""

import numpy as np
import pytest

from fitting._fit import residual_correlation


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
