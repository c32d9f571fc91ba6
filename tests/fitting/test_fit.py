"""Fitting coating colours, dirt and light gains to plates (fitting package)."""

import numpy as np
import pytest

import fitting
import jaxflare as jf
from fitting._forward import fixed_samples, render_image
from tests.helpers import flare_only

jax = pytest.importorskip("jax")
jnp = jax.numpy

SCENE = jf.Scene(
    camera=jf.Camera(lens="zeiss_biotar", f_number=4.0, resolution=(64, 48), look_at_m=(0.0, 0.0, -10.0)),
    lights=(jf.Light(kind="directional", direction=(0.06, 0.03, -1.0)),),
    render=jf.RenderSettings(cull_threshold=0.0, sampling="uniform"),  # samples independent of the parameters
)
TRUE_TINTS = np.ones((10, 3))
TRUE_TINTS[7] = (1.0, 0.6, 0.3)
TRUE_TINTS[4] = (0.5, 0.9, 1.2)


@pytest.fixture(scope="module")
def samples():
    return fixed_samples(SCENE, samples=2**14, seed=1)


def synthetic_plate(samples, tints=TRUE_TINTS, dirt=None):
    image = np.asarray(render_image(samples, jnp.asarray(tints, jnp.float32), None if dirt is None else jnp.asarray(dirt, jnp.float32)))
    return fitting.Plate(rgb=image, weight=np.ones(image.shape[:2]), source="synthetic", layer="")


def test_forward_model_reproduces_the_renderer(samples):
    image = render_image(samples, jnp.ones((10, 3)), None)
    render = jf.render(flare_only(SCENE), samples=2**14, seed=1)  # the fit's samples have no core
    # the renderer then maps each layer's colours outside the gamut into it, which keeps every
    # pixel's luminance (jaxflare.rendering.clip_to_gamut) but not its channels
    weights = np.asarray(jf.colour.spectral_table(render.statistics["settings"]["colour_space"]).luminance_weights)
    image = np.asarray(image, np.float64)
    np.testing.assert_allclose(image @ weights, render.image[..., :3] @ weights, rtol=1e-5, atol=1e-6)
    assert image.min() < 0 <= render.image.min()


def test_per_path_images_of_the_samples_equal_their_render_for_any_tints_and_gains(samples):
    """A fit of coatings and lights given samples solves on their per-path images: the tinted,
    gained sum of those images is the samples' own render (both linear in tints and gains)."""
    from fitting._forward import fixed_path_images, path_image_model

    images = fixed_path_images(samples, per_light_colour=True)
    rng = np.random.default_rng(3)
    for _ in range(2):
        tints, gain = rng.uniform(0.2, 1.5, (10, 3)), rng.uniform(0.5, 2.0, (1, 3))
        direct = np.asarray(render_image(samples, jnp.asarray(tints, jnp.float32), None, jnp.asarray(gain, jnp.float32)), np.float64)
        summed = np.asarray(path_image_model(images, jnp.asarray(tints), jnp.asarray(gain), full=True), np.float64)
        np.testing.assert_allclose(summed, direct, rtol=1e-4, atol=1e-6 * np.abs(direct).max())
    blocks = fixed_path_images(samples, pixel_weight=np.full((48, 64), 0.5), block=4)
    assert blocks.images.shape == (images.images.shape[0], 1, 12, 16, 3)
    # weighted block sums of the unit-gain images: half of their light, summed per 4 x 4 block
    np.testing.assert_allclose(np.asarray(blocks.images).sum(), 0.5 * np.asarray(blocks.full_images, np.float64).sum(), rtol=1e-5)


def test_per_dirt_cell_images_of_the_samples_equal_their_render_for_any_dirt_tints_and_gains(samples):
    """A dirt fit given samples solves on their per-path, per-dirt-cell images: contracted with a
    dirt map, tints and gains they give the samples' own render (linear in each), block-summed and
    weighted like the plate."""
    from fitting._grid_model import dirt_image_model
    from fitting._sample_images import sample_dirt_images

    weight = np.random.default_rng(4).uniform(0.5, 1.0, (48, 64))
    images = sample_dirt_images(samples, (5, 6), weight, block=4, per_light_colour=True)
    rng = np.random.default_rng(5)
    for _ in range(2):
        tints, dirt, gain = rng.uniform(0.2, 1.5, (10, 3)), rng.uniform(0.0, 1.0, (5, 6, 1)), rng.uniform(0.5, 2.0, (1, 3))
        direct = np.asarray(render_image(samples, *(jnp.asarray(a, jnp.float32) for a in (tints, dirt, gain))), np.float64)
        pooled = (direct * weight[..., None]).reshape(12, 4, 16, 4, 3).sum(axis=(1, 3))
        summed = np.asarray(dirt_image_model(images, jnp.asarray(tints), jnp.asarray(dirt), jnp.asarray(gain)))
        np.testing.assert_allclose(summed, pooled, rtol=1e-4, atol=1e-6 * np.abs(pooled).max())


@pytest.mark.parametrize("solver", ["gauss-newton", "levenberg-marquardt", "bfgs"])
def test_coating_colours_are_recovered_with_common_random_numbers(samples, solver):
    """With the plate's own samples (no Monte Carlo difference) every solver finds the true tints."""
    plate = synthetic_plate(samples)
    result = fitting.fit(SCENE, plate, params=("coatings",), solver=solver, fixed=samples, tint_prior_weight=1e-10, max_steps=200)
    assert result.loss_history[-1] < 1e-6 * result.loss_history[0]
    np.testing.assert_allclose(result.coating_tints[[4, 7]], TRUE_TINTS[[4, 7]], atol=2e-2)
    assert result.converged or solver == "bfgs", result.status


def test_dirt_map_is_recovered_where_light_passes_and_stays_at_its_prior_elsewhere(samples):
    truth = np.ones((8, 8, 1))
    truth[2:5, 3:6] = 0.3
    plate = synthetic_plate(samples, tints=np.ones((10, 3)), dirt=truth)
    result = fitting.fit(SCENE, plate, params=("dirt",), solver="levenberg-marquardt", fixed=samples, dirt_resolution=8, dirt_prior_weight=1e-6, max_steps=30)
    assert result.loss_history[-1] < 1e-2 * result.loss_history[0]  # what is left is mostly the weak prior
    # cells the flare never lights keep the prior (clean); lit cells take the true value
    sensitivity = np.asarray(jax.grad(lambda d: render_image(samples, jnp.ones((10, 3)), d).sum())(jnp.ones((8, 8, 1), jnp.float32)))
    lit = sensitivity[..., 0] > 0.05 * sensitivity.max()
    dark = sensitivity[..., 0] == 0
    assert lit.sum() > 4 and dark.sum() > 4
    np.testing.assert_allclose(result.dirt[lit], truth[lit], atol=0.05)
    np.testing.assert_allclose(result.dirt[dark], fitting.DIRT_PRIOR, atol=1e-6)


def test_a_fit_that_runs_out_of_steps_says_so_and_keeps_its_best(samples):
    plate = synthetic_plate(samples)
    result = fitting.fit(SCENE, plate, params=("coatings",), solver="gauss-newton", fixed=samples, max_steps=1)
    assert not result.converged and "not converged in 1 steps" in result.status
    assert result.loss_history[-1] <= result.loss_history[0]


def test_bad_fit_inputs_are_clear_errors(samples):
    plate = synthetic_plate(samples)
    with pytest.raises(ValueError, match="params must be a non-empty subset of coatings, thin-film, dirt, lights"):
        fitting.fit(SCENE, plate, params=("colours",), fixed=samples)
    with pytest.raises(ValueError, match="solver must be one of"):
        fitting.fit(SCENE, plate, params=("coatings",), solver="adam", fixed=samples)
    with pytest.raises(ValueError, match="max_steps must be an integer of at least 1, got 0"):
        fitting.fit(SCENE, plate, params=("coatings",), max_steps=0, fixed=samples)
    with pytest.raises(ValueError, match="progress must be a callable progress\\(step, loss\\) or None, got True"):
        fitting.fit(SCENE, plate, params=("coatings",), progress=True, fixed=samples)
    small = fitting.Plate(rgb=plate.rgb[:10], weight=plate.weight[:10], source="small.exr", layer="")
    with pytest.raises(ValueError, match=r"small.exr: 64 x 10 pixels, but the scene renders 64 x 48"):
        fitting.fit(SCENE, small, fixed=samples)


def test_fitted_parameters_round_trip_into_the_renderer(samples, tmp_path):
    plate = synthetic_plate(samples)
    # tints and light gains trade off (a common scale): the fit creeps on for its 100 steps, but
    # by 40 the loss is below 1e-5 of its start, as close as the round trip needs (the
    # renderer maps colours outside the gamut, so the parameters must be near the truth)
    result = fitting.fit(SCENE, plate, params=("coatings", "lights"), fixed=samples, tint_prior_weight=1e-10, max_steps=40)
    assert result.loss_history[-1] < 1e-5 * result.loss_history[0]
    path = fitting.save_fit(result, tmp_path / "fitted.json")
    refit = fitting.apply_fit(SCENE, path)
    rendered = jf.render(flare_only(refit), samples=2**14, seed=1)  # the fit's samples have no core
    # luminance: the renderer maps each layer into the gamut, keeping its luminance where positive
    # (a tinted single-wavelength colour can have a negative one: black), the fit's model does not
    weights = np.asarray(jf.colour.spectral_table(rendered.statistics["settings"]["colour_space"]).luminance_weights)
    model = np.asarray(result.render, np.float64) @ weights
    near = np.isclose(rendered.image[..., :3] @ weights, model, rtol=1e-3, atol=1e-4 * model.max())
    assert near.mean() > 0.95
    np.testing.assert_allclose((rendered.image[..., :3] @ weights).sum(), model.sum(), rtol=1e-2)
    layers, _ = jf.read_exr(tmp_path / "fitted_render.exr")
    assert "residual" in layers


def test_fit_command(samples, tmp_path, capsys):
    from jaxflare.cli import main

    scene_file = tmp_path / "scene.toml"
    scene_file.write_text(
        '[camera]\nlens = "zeiss_biotar"\nf_number = 4.0\nresolution = [64, 48]\nlook_at_m = [0.0, 0.0, -10.0]\n'
        '[[light]]\nkind = "directional"\ndirection = [0.06, 0.03, -1.0]\n[render]\ncull_threshold = 0.0\nsampling = "uniform"\n'
    )
    plate = synthetic_plate(samples)
    fitting.save_plate(tmp_path / "plate.exr", plate.rgb)
    code = main(["fit", str(tmp_path / "plate.exr"), "--scene", str(scene_file), "-o", str(tmp_path / "fit.json"), "--params", "coatings", "--samples", str(2**14), "--seed", "1", "--max-steps", "30"])
    out = capsys.readouterr()
    assert code in (0, 1) and "wrote" in out.out and "step" in out.err
    import json

    data = json.loads((tmp_path / "fit.json").read_text())
    np.testing.assert_allclose(np.asarray(data["coating_tints"])[[4, 7]], TRUE_TINTS[[4, 7]], atol=0.05)
    assert main(["fit", str(tmp_path / "plate.exr"), "--scene", str(scene_file), "-o", str(tmp_path / "x.json"), "--params", "colour"]) == 2
