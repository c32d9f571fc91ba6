"""The grid estimator as a fit's forward model (jaxflare.rendering.GridFlareModel, model="grid").

The model re-splats a planned grid render for other coating tints, dirt maps and light gains, so
it must reproduce the grid render of a scene that has them, be linear in the path tints and the
dirt map, give gradients equal to finite differences, and recover a lens's tints from a plate of
it with the fit's defaults.
"""

import dataclasses

import numpy as np
import pytest

import fitting
import jaxflare as jf
from fitting._forward import _path_tints
from fitting._grid_model import grid_interfaces, grid_path_images
from jaxflare.rendering import grid_flare_model, render_grid
from tests.helpers import BIOTAR_TWO_LIGHTS, flare_only, with_tints

jax = pytest.importorskip("jax")
jnp = jax.numpy
eqx = pytest.importorskip("equinox")

SCENE = BIOTAR_TWO_LIGHTS
TRUE_TINTS = np.ones((10, 3))
TRUE_TINTS[7] = (1.0, 0.6, 0.3)
TRUE_TINTS[4] = (0.5, 0.9, 1.2)
IMAGE = eqx.filter_jit(lambda model, tint, dirt, gain: model.image(tint, dirt, gain))


@pytest.fixture(scope="module")
def model():
    return grid_flare_model(SCENE, "preview")


def tints_of(model, interface_tints):
    return _path_tints(jnp.asarray(grid_interfaces(model)), jnp.asarray(interface_tints, jnp.float32))


def test_model_reproduces_the_grid_render_and_its_path_images_sum_to_it(model):
    image = np.asarray(IMAGE(model, tints_of(model, np.ones((10, 3))), None, None), np.float64)
    render = jf.render(flare_only(SCENE), estimator="grid", quality="preview")
    weights = np.asarray(jf.colour.spectral_table(render.statistics["settings"]["colour_space"]).luminance_weights)
    # the render maps colours outside the gamut per layer (luminance kept), the model does not
    np.testing.assert_allclose(image @ weights, render.image[..., :3] @ weights, rtol=1e-4, atol=1e-6 * image.max())
    images = grid_path_images(model, per_light_colour=True)
    assert images.images.shape == (model.num_paths, 6, 48, 64, 3)
    np.testing.assert_allclose(np.asarray(images.images).sum(axis=(0, 1)), image, rtol=1e-4, atol=1e-6 * image.max())


def test_model_equals_a_grid_render_of_the_tinted_and_brighter_scene(model):
    """Tints and gains change only what the model scales: its image for the true tints and a
    light 1.5x brighter in red is the grid render of the scene that has them (same grid plan,
    every path at the level the unit-tint plan chose, so compare luminance after a 4 x 4 sum)."""
    gain = np.array([[1.0, 1.0, 1.0], [1.5, 1.0, 1.0]])
    image = np.asarray(IMAGE(model, tints_of(model, TRUE_TINTS), None, jnp.asarray(gain, jnp.float32)), np.float64)
    lights = (SCENE.lights[0], dataclasses.replace(SCENE.lights[1], rgb=(1.5, 0.8, 0.6)))
    truth = jf.render(flare_only(dataclasses.replace(with_tints(SCENE, TRUE_TINTS), lights=lights)), estimator="grid", quality="preview")
    pooled = lambda x: x.reshape(12, 4, 16, 4, 3).sum(axis=(1, 3))
    reference = pooled(np.asarray(truth.image[..., :3], np.float64))
    error = np.linalg.norm(pooled(image) - reference) / np.linalg.norm(reference)
    assert error < 0.03, error
    # and the tints and gain matter: the unit-tint image is far from it
    plain = pooled(np.asarray(IMAGE(model, tints_of(model, np.ones((10, 3))), None, None), np.float64))
    assert np.linalg.norm(plain - reference) / np.linalg.norm(reference) > 5 * error


def test_linear_in_tints_and_dirt_with_gradients_equal_to_finite_differences(model):
    tint = tints_of(model, TRUE_TINTS)
    dirt = jnp.full((8, 8, 1), 0.9, jnp.float32).at[3, 4, 0].set(0.5)
    base = np.asarray(IMAGE(model, tint, dirt, None), np.float64)
    np.testing.assert_allclose(np.asarray(IMAGE(model, 2 * tint, dirt, None)), 2 * base, rtol=1e-5, atol=1e-7 * base.max())
    np.testing.assert_allclose(np.asarray(IMAGE(model, tint, 0.5 * dirt, None)), 0.5 * base, rtol=1e-5, atol=1e-7 * base.max())
    target = jnp.asarray(base * 0.8)

    def loss(tint, dirt):
        return jnp.sum((model.image(tint, dirt) - target) ** 2)

    grad_tint, grad_dirt = eqx.filter_jit(jax.grad(loss, argnums=(0, 1)))(tint, dirt)
    assert np.all(np.isfinite(grad_tint)) and np.all(np.isfinite(grad_dirt))
    lit = np.unravel_index(int(np.argmax(np.abs(grad_dirt))), grad_dirt.shape)
    brightest = int(np.argmax(np.abs(np.asarray(grad_tint)[:, 1])))
    step = 0.05  # the loss is quadratic in each: central differences are exact up to rounding
    fd_loss = eqx.filter_jit(loss)
    fd_dirt = (fd_loss(tint, dirt.at[lit].add(step)) - fd_loss(tint, dirt.at[lit].add(-step))) / (2 * step)
    fd_tint = (fd_loss(tint.at[brightest, 1].add(step), dirt) - fd_loss(tint.at[brightest, 1].add(-step), dirt)) / (2 * step)
    np.testing.assert_allclose(float(grad_dirt[lit]), float(fd_dirt), rtol=2e-3)
    np.testing.assert_allclose(float(grad_tint[brightest, 1]), float(fd_tint), rtol=2e-3)


def grid_plate(scene):
    return render_grid(scene, "production", **fitting._fit.FINE_GRID).image[..., :3]


@pytest.fixture(scope="module")
def true_plate():
    """A noise-free grid plate of the lens with :data:`TRUE_TINTS`, as finely as the fit's model."""
    rgb = grid_plate(with_tints(SCENE, TRUE_TINTS))
    return fitting.Plate(rgb=np.asarray(rgb, np.float64), weight=np.ones((48, 64)), source="grid plate", layer="")


@pytest.fixture(scope="module")
def fine_model():
    """The model a fit with the defaults builds for :data:`SCENE` (its grid planned for the scene's coatings)."""
    return grid_flare_model(SCENE, fitting._fit.GRID_QUALITY, **fitting._fit.FINE_GRID)


def test_fit_defaults_use_the_grid_and_recover_tints_and_a_gain(true_plate, fine_model):
    """With the fit's defaults (model auto = grid) on noise-free grid plates of the true lens (drawn
    as finely as the fit's model, :data:`fitting._fit.FINE_GRID`; a production-quality plate
    differs from it by a few percent at 64 x 48 and gave a largest error of 0.055): its tints
    within 0.05 where the plate shows them, and, with the tints known, the second light's gain of 1.3. (Tints and gains together are degenerate: all tints x s and all gains
    / s^2 give the same flare, and the fit says so by calling the tints unobservable.)"""
    result = fitting.fit(SCENE, true_plate, params=("coatings",))
    assert result.model == "grid" and result.block == 4 and result.converged
    observable = np.all(result.tint_observable, axis=1)
    assert observable[[4, 7]].all()
    error = np.abs(result.coating_tints - TRUE_TINTS)
    assert error[observable].max() < 0.05, error[observable]
    assert result.as_dict()["observable_interfaces"] == [int(k) for k in np.flatnonzero(observable)]

    lights = (SCENE.lights[0], dataclasses.replace(SCENE.lights[1], rgb=(1.3, 1.04, 0.78)))
    brighter = dataclasses.replace(with_tints(SCENE, TRUE_TINTS), lights=lights)
    rgb = grid_plate(brighter)
    plate = fitting.Plate(rgb=np.asarray(rgb, np.float64), weight=np.ones((48, 64)), source="brighter plate", layer="")
    # the model the defaults build (planned for the scene's coatings, tints applied per call), and
    # its per-path images per light colour (what a fit of the lights sums), once for both fits
    per_light_colour = grid_path_images(fine_model, per_light_colour=True)
    result = fitting.fit(with_tints(SCENE, TRUE_TINTS), plate, params=("lights",), fixed=per_light_colour)
    np.testing.assert_allclose(result.light_gain, [[1.0, 1.0, 1.0], [1.3, 1.3, 1.3]], atol=0.05)
    joint = fitting.fit(SCENE, plate, params=("coatings", "lights"), fixed=per_light_colour)
    assert joint.model == "path-images"
    assert not np.any(np.all(joint.tint_observable, axis=1))  # the degenerate scale


def test_plates_no_flare_can_match_are_refused_before_the_model_is_built(monkeypatch):
    def no_model(*args, **kwargs):
        raise AssertionError("the model was built")

    monkeypatch.setattr(fitting._fit, "grid_flare_model", no_model)
    rgb = np.full((48, 64, 3), 0.01)
    cases = {
        "black": (np.zeros_like(rgb), "no light where its weight is non-zero"),
        "negative": (-rgb, r"no light where its weight is non-zero \(it is black or negative"),
        "subtracted": (rgb - 0.02 + np.eye(48, 64)[..., None] * 0.5, "channel sums to .* a flare only adds light"),
        "spike": (np.where(np.arange(64)[None, :, None] == 5, -1.0, rgb) + np.eye(48, 64)[..., None], r"pixel \(x=5, y=\d+\) is -1"),
    }
    for name, (values, message) in cases.items():
        plate = fitting.Plate(rgb=values, weight=np.ones((48, 64)), source=f"{name}.exr", layer="")
        with pytest.raises(ValueError, match=message):
            fitting.fit(SCENE, plate, params=("coatings",))
    noisy = rgb + np.random.default_rng(0).normal(0, 0.005, rgb.shape)  # small negative values of noise are fine
    fitting._plate.check_fittable(fitting.Plate(rgb=noisy, weight=np.ones((48, 64)), source="noisy.exr", layer=""))


def test_final_render_of_a_plate_too_large_to_keep_in_the_stack_is_the_tinted_sum(monkeypatch, true_plate, fine_model):
    """Where the path-image stack cannot keep its full-resolution images (FULL_IMAGE_BYTES, here
    set to 0), the fit's render is still their tinted sum (kept on the host), not a re-splat of the
    grid: equal to the render of a fit that kept them (both from the model the defaults build)."""
    kept = fitting.fit(SCENE, true_plate, params=("coatings",), max_steps=3, fixed=fine_model)
    monkeypatch.setattr(fitting._grid_model, "FULL_IMAGE_BYTES", 0)
    monkeypatch.setattr(fitting._fit, "_grid_image", lambda *a, **k: pytest.fail("the final render re-splatted the grid"))
    summed = fitting.fit(SCENE, true_plate, params=("coatings",), max_steps=3, fixed=fine_model)
    np.testing.assert_allclose(summed.coating_tints, kept.coating_tints, rtol=1e-6)
    np.testing.assert_allclose(summed.render, kept.render, rtol=1e-5, atol=1e-6 * kept.render.max())
