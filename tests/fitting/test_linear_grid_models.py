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


def test_dirt_cells_splatted_in_runs_equal_one_splat_per_one_hot_map(monkeypatch):
    """grid_dirt_images splats runs of cells together (each sub-sample into its four bilinear
    cells' layers); with runs of four cells of a 2 x 3 map (two passes with the boundary between
    them inside the map, the second padded with two cells past its end) every cell's images, weighted
    and summed in blocks, equal re-splatting its one-hot map."""
    import fitting._grid_model as grid_model

    model = grid_flare_model(SCENE, "preview")
    monkeypatch.setattr(grid_model, "DIRT_RUN_BYTES", 4 * model.num_paths * model.layer_bytes)
    weight = np.random.default_rng(2).uniform(0.0, 2.0, (48, 64))
    images = np.asarray(grid_dirt_images(model, (2, 3), weight, block=4).images, np.float64)  # (P, 6, 1, 12, 16, 3)
    assert images.shape == (model.num_paths, 6, 1, 12, 16, 3)
    for cell in range(6):
        one_hot = np.zeros((2, 3, 1), np.float32)
        one_hot.flat[cell] = 1.0
        full = np.asarray(model.per_path_image(jnp.asarray(one_hot)), np.float64) * weight[:, :, None]
        expected = full.reshape(model.num_paths, 12, 4, 16, 4, 3).sum(axis=(2, 4))
        assert expected.sum() > 0, cell
        np.testing.assert_allclose(images[:, cell, 0], expected, rtol=1e-4, atol=1e-6 * expected.max())


def test_dirt_model_derivatives_equal_the_plain_contractions():
    """dirt_image_model's own derivative rule (three contractions of the stack, made once per
    Jacobian) gives the Jacobian and the gradient of the plain einsum, in tints, dirt and gains."""
    from fitting._grid_model import DirtImages

    rng = np.random.default_rng(4)
    paths, cells, lights, h, w = 3, 4, 2, 3, 5
    stack = jnp.asarray(rng.uniform(0.0, 1.0, (paths, cells, 3 * lights, h, w, 3)))
    images = DirtImages(images=stack, dirt_shape=(2, 2), path_interfaces=jnp.asarray([[2, 1], [3, 0], [3, 2]]), num_lights=lights)
    tints, dirt, gain = (jnp.asarray(rng.uniform(0.5, 1.5, shape)) for shape in ((4, 3), (2, 2, 1), (lights, 3)))

    def plain(t, d, g):
        return jnp.einsum("pc,d,k,pdkhwc->hwc", _path_tints(images.path_interfaces, t), d.reshape(-1), g.reshape(-1), stack)

    ours = lambda t, d, g: dirt_image_model(images, t, d, g)  # noqa: E731
    np.testing.assert_allclose(ours(tints, dirt, gain), plain(tints, dirt, gain), rtol=1e-12)
    for argnum in range(3):
        np.testing.assert_allclose(jax.jacfwd(ours, argnum)(tints, dirt, gain), jax.jacfwd(plain, argnum)(tints, dirt, gain), rtol=1e-10, atol=1e-12)
        loss = lambda f: lambda *a: jnp.sum(f(*a) ** 2)  # noqa: E731
        np.testing.assert_allclose(jax.grad(loss(ours), argnum)(tints, dirt, gain), jax.grad(loss(plain), argnum)(tints, dirt, gain), rtol=1e-10)
