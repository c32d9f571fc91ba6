"""Colour planes: a grid model splats several job colourings (light-gain bases, spectral knots) as
channels of one pass over its sub-samples. Each plane must equal its own splat, bit for bit up to
float32 summation order: the geometry is shared, only the colour differs."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflare.rendering import gain_basis, grid_flare_model
from tests.helpers import BIOTAR_TWO_LIGHTS


@pytest.fixture(scope="module")
def model():
    return grid_flare_model(BIOTAR_TWO_LIGHTS, "preview")


ONE_SPLAT = eqx.filter_jit(lambda m, gain, fresnel: m._splat(jnp.ones((m.num_paths, 3)), None, gain, per_path=True, path_fresnel=fresnel))


def test_each_light_gain_plane_equals_its_own_splat(model):
    planes = np.asarray(eqx.filter_jit(lambda m: m.path_images(per_light_colour=True))(model))
    assert planes.shape == (model.num_paths, 3 * model.num_lights, 48, 64, 3)
    for k, basis in enumerate(gain_basis(model.num_lights)):
        alone = np.asarray(ONE_SPLAT(model, jnp.asarray(basis, jnp.float32), None))
        np.testing.assert_allclose(planes[:, k], alone, rtol=1e-5, atol=1e-6 * alone.max())
        # light k's planes see only light k: the other light's colour is black in them
        assert np.abs(alone).max() > 0


def test_each_spectral_knot_and_gain_plane_equals_its_own_splat(model):
    images, knots = model.path_knot_images(per_light_colour=True, knot_slice=slice(10, 12))
    images = np.asarray(images)
    assert images.shape == (model.num_paths, 2, 3 * model.num_lights, 48, 64, 3) and len(knots) == 2
    _, fresnels = model.knot_fresnels()
    for b, fresnel in enumerate(fresnels[10:12]):
        for k, basis in enumerate(gain_basis(model.num_lights)):
            alone = np.asarray(ONE_SPLAT(model, jnp.asarray(basis, jnp.float32), fresnel))
            np.testing.assert_allclose(images[:, b, k], alone, rtol=1e-5, atol=1e-6 * np.abs(images).max())
