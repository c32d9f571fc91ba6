"""The grid model's linear decompositions that make fits fast: per-path images for each cell of a
one-hot dirt map (the flare is linear in the map: a bilinear lookup per sub-sample) and for each
spectral knot (linear in the paths' Fresnel factors). Their weighted sums must equal re-splatting
the fixed sub-samples with the same parameters."""

import numpy as np
import pytest

from fitting._forward import _path_tints
from fitting._grid_model import dirt_image_model, grid_dirt_images, grid_interfaces
from jaxflare.rendering import grid_flare_model
from tests.helpers import BIOTAR_TWO_LIGHTS

jax = pytest.importorskip("jax")
jnp = jax.numpy
eqx = pytest.importorskip("equinox")

SCENE = BIOTAR_TWO_LIGHTS
IMAGE = eqx.filter_jit(lambda model, tint, dirt, gain: model.image(tint, dirt, gain))


def test_dirt_cell_images_sum_to_the_resplat_for_any_map_tints_and_gains():
    model = grid_flare_model(SCENE, "preview")
    images = grid_dirt_images(model, (2, 3), block=1, per_light_colour=True)
    assert images.images.shape == (model.num_paths, 6, 6, 48, 64, 3)
    rng = np.random.default_rng(1)
    dirt = rng.uniform(0.2, 1.0, (2, 3, 1))  # rows x columns: the cells are row-major
    tints = rng.uniform(0.5, 1.5, (10, 3))
    gain = np.asarray([[1.0, 0.9, 0.8], [1.3, 1.2, 1.1]])
    summed = np.asarray(dirt_image_model(images, jnp.asarray(tints), jnp.asarray(dirt), jnp.asarray(gain)), np.float64)
    path_tint = _path_tints(jnp.asarray(grid_interfaces(model)), jnp.asarray(tints, jnp.float32))
    resplat = np.asarray(IMAGE(model, path_tint, jnp.asarray(dirt, jnp.float32), jnp.asarray(gain, jnp.float32)), np.float64)
    assert resplat.max() > 0
    np.testing.assert_allclose(summed, resplat, rtol=1e-4, atol=1e-5 * resplat.max())
    # a clean map (all ones) is the model without dirt
    clean = np.asarray(dirt_image_model(images, jnp.ones((10, 3)), jnp.ones((2, 3, 1)), jnp.ones((2, 3))), np.float64)
    no_dirt = np.asarray(IMAGE(model, jnp.ones((model.num_paths, 3)), None, None), np.float64)
    np.testing.assert_allclose(clean, no_dirt, rtol=1e-4, atol=1e-5 * no_dirt.max())
