"""Thin-film coatings as fit parameters (params "thin-film"): the grid model recoloured per
wavelength by the characteristic-matrix model, its spectral-knot images, and a fit that recovers
layer thicknesses from a plate rendered with a known stack.

The truths are coatings a real lens could have: single MgF2 layers 0.85 and 1.3 times their design
thickness on the two interfaces whose ghosts dominate, and 1.15 on a third.
"""

import dataclasses

import numpy as np
import pytest

import fitting
from fitting._thin_film import film_layers
from jaxflare import rendering
from jaxflare.rendering import grid_flare_model
from jaxflare.scenes import SurfaceCoating, camera_lens
from tests.helpers import BIOTAR_TWO_LIGHTS, flare_only

jax = pytest.importorskip("jax")
jnp = jax.numpy
eqx = pytest.importorskip("equinox")

SCENE = dataclasses.replace(BIOTAR_TWO_LIGHTS, camera=dataclasses.replace(BIOTAR_TWO_LIGHTS.camera, coating="mgf2"))
QUARTER_WAVE_NM = 550.0 / (4 * 1.38)
TRUE_SCALE = {1: 0.85, 4: 1.15, 8: 1.3}
IMAGE = eqx.filter_jit(lambda model, fresnel: model.image(jnp.ones((model.num_paths, 3)), None, None, fresnel))
FRESNEL = eqx.filter_jit(lambda model, indices, thicknesses: model.path_fresnel(indices, thicknesses))
GRID = dict(grid_error=0.03, grid_options=dict(spacing_px=0.5, edge_side=8, max_cells=48))
"""The model's and the plates' grid, finer than the preview default (these tests are about the
thin-film model, not the grid's error): with the preview's 5 % target, 4 sub-samples per edge side
and a spacing of 0.7 (tried 2026-12-07) the fit still recovered every thickness within 1 %, but 6
of 8 layers lay within 3 standard errors against the 80 % asked below."""


def grid_render(scene):
    return rendering.render_grid(flare_only(scene), "preview", **GRID).image[..., :3]


def with_stacks(scene, scale):
    overrides = tuple(SurfaceCoating(surfaces=(s,), layers=((1.38, QUARTER_WAVE_NM * f),)) for s, f in scale.items())
    return dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, surface_coatings=overrides))


@pytest.fixture(scope="module")
def model():
    return grid_flare_model(SCENE, "preview", **GRID)


def relative_rmse(a, b):
    return float(jnp.sqrt(jnp.mean((a - b) ** 2)) / jnp.sqrt(jnp.mean(b**2)))


def test_recoloured_model_equals_the_render_of_the_changed_coating(model):
    lens = model.setup.lens
    base = FRESNEL(model, lens.coating_indices, lens.coating_thicknesses_nm)
    np.testing.assert_allclose(np.asarray(base), np.asarray(model.base_fresnel), rtol=1e-6, atol=0)
    np.testing.assert_allclose(np.asarray(IMAGE(model, base)), np.asarray(IMAGE(model, None)), rtol=1e-5, atol=1e-6 * float(IMAGE(model, None).max()))
    # recolouring the scene's grid with another stack is the grid render of a scene with that stack
    truth = with_stacks(SCENE, TRUE_SCALE)
    changed = np.asarray(camera_lens(truth.camera).coating_thicknesses_nm, np.float32)
    recoloured = np.asarray(IMAGE(model, FRESNEL(model, lens.coating_indices, jnp.asarray(changed))), np.float64)
    rendered = grid_render(truth)
    assert relative_rmse(recoloured, rendered) < 0.02  # the planned grid differs a little with the coatings
    assert relative_rmse(np.asarray(IMAGE(model, None)), rendered) > 0.3  # and the change is large


def test_spectral_knot_images_sum_to_the_recoloured_model(model):
    images, knots = model.path_knot_images()
    assert images.shape[:3] == (model.num_paths, knots.size, 1)
    lens = model.setup.lens
    for scale in (0.85, 1.0, 1.3):
        fresnel = FRESNEL(model, lens.coating_indices, lens.coating_thicknesses_nm * scale)
        knot_sum = jnp.einsum("pb,pbkhwc->hwc", fresnel[:, knots], images)
        assert relative_rmse(knot_sum, IMAGE(model, fresnel)) < 0.005


def test_thickness_gradient_matches_finite_differences(model):
    lens = model.setup.lens
    loss = lambda s: jnp.sum(IMAGE(model, FRESNEL(model, lens.coating_indices, lens.coating_thicknesses_nm.at[4, 0].multiply(s))) ** 2)
    grad = float(jax.grad(loss)(1.0))
    h = 1e-2
    numeric = (float(loss(1.0 + h)) - float(loss(1.0 - h))) / (2 * h)
    assert grad != 0 and abs(grad - numeric) < 0.02 * abs(numeric)


def test_thin_film_fit_recovers_the_thicknesses_of_a_known_stack(model, tmp_path):
    truth = with_stacks(SCENE, TRUE_SCALE)
    rendered = grid_render(truth)
    # 1 % of the plate's mean level per pixel (the peak is ~370 times the mean: 1 % of it would
    # bury every ghost but the brightest)
    noise = np.random.default_rng(0).normal(0.0, 0.01 * rendered.mean(), rendered.shape)
    plate = fitting.Plate(rgb=rendered + noise, weight=np.ones((48, 64)), source="known stack")
    result = fitting.fit(SCENE, plate, params=("thin-film",), fixed=model)
    assert result.converged, result.status
    layers = {layer["surface"]: layer for layer in result.coating_layers}
    true_nm = {s: QUARTER_WAVE_NM * TRUE_SCALE.get(s, 1.0) for s in layers}
    errors = {s: layers[s]["thickness_nm"] / true_nm[s] - 1 for s in layers}
    for s in TRUE_SCALE:
        assert layers[s]["observable"], layers[s]
    for s, layer in layers.items():
        if layer["observable"]:
            assert abs(errors[s]) < 0.05, (s, errors[s])
            assert abs(layer["index"] - 1.38) <= 0.1 + 1e-9
    within = [abs(layers[s]["thickness_nm"] - true_nm[s]) <= 3 * layers[s]["thickness_std_nm"] for s in layers if layers[s]["observable"]]
    assert np.mean(within) >= 0.8, errors
    # the RGB tints the stacks are equivalent to: thinner MgF2 reflects warmer, thicker bluer
    interface = camera_lens(SCENE.camera).interface_surfaces.index
    tints = result.coating_tints
    assert tints[interface(1), 0] > tints[interface(1), 2] and tints[interface(8), 2] > tints[interface(8), 0]
    # the fitted stacks applied to the scene give its lens those layers
    saved = fitting.save_fit(result, tmp_path / "film.json")
    applied = camera_lens(fitting.apply_fit(SCENE, saved).camera)
    for s, layer in layers.items():
        assert float(applied.coating_thicknesses_nm[s, layer["layer"]]) == pytest.approx(layer["thickness_nm"], rel=1e-9)


def test_thin_film_needs_a_coated_lens_the_grid_model_and_no_free_tints():
    plate = fitting.Plate(rgb=np.ones((48, 64, 3)), weight=np.ones((48, 64)), source="flat")
    with pytest.raises(ValueError, match="choose one"):
        fitting.fit(SCENE, plate, params=("coatings", "thin-film"))
    with pytest.raises(ValueError, match="grid model only"):
        fitting.fit(SCENE, plate, params=("thin-film",), model="path-images")
    bare = dataclasses.replace(SCENE, camera=dataclasses.replace(SCENE.camera, coating="uncoated"))
    with pytest.raises(ValueError, match="no coating layers"):
        film_layers(camera_lens(bare.camera))
    with pytest.raises(ValueError, match="no coating layers"):
        fitting.fit(bare, plate, params=("thin-film",))
