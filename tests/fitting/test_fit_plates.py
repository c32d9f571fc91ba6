"""Fitting to plates made independently of the fit's own samples: another seed, added noise, a
background under a mask, exact tracing against polynomials, and the dirt map.

These are the cases a real plate brings (its noise is not the fit's noise), unlike
tests/test_fitting.py, which fits plates made from the fit's own samples. Tolerances come from the
fit's own standard errors where it reports them: a recovered tint must lie within a few standard
errors of the truth, and the standard errors must be small where the plate shows the interface.
"""

import dataclasses

import numpy as np
import pytest

import fitting
import jaxflare as jf
from fitting._forward import path_images
from tests.helpers import with_tints

jax = pytest.importorskip("jax")

SCENE = jf.Scene(
    camera=jf.Camera(lens="zeiss_biotar", f_number=4.0, resolution=(64, 48), look_at_m=(0.0, 0.0, -10.0)),
    lights=(jf.Light(kind="directional", direction=(0.06, 0.03, -1.0)),),
)
TRUE_TINTS = np.ones((10, 3))
TRUE_TINTS[7] = (1.0, 0.6, 0.3)
TRUE_TINTS[4] = (0.5, 0.9, 1.2)
BLOCK = 8
MODEL_SAMPLES = 2**21
PLATE_SAMPLES = 2**21


@pytest.fixture(scope="module")
def plate_rgb():
    """The true lens's flare, rendered with another seed than the fit's (independent noise)."""
    return jf.render(with_tints(SCENE, TRUE_TINTS), samples=PLATE_SAMPLES, seed=7).image[..., :3].astype(np.float64)


@pytest.fixture(scope="module")
def images():
    return path_images(SCENE, samples=MODEL_SAMPLES, seed=0, block=BLOCK)


def assert_recovered(result, *, sigmas=4.0, slack=0.03):
    """The two coloured interfaces, and every other interface the plate shows (standard errors
    below OBSERVABLE_STD), are within ``sigmas`` standard errors (+ ``slack`` for the model's own
    Monte Carlo noise, which the standard errors leave out) of the truth."""
    checked = np.all(result.tint_std < fitting.OBSERVABLE_STD, axis=1)
    checked[[4, 7]] = True
    error = np.abs(result.coating_tints - TRUE_TINTS)[checked]
    bound = sigmas * result.tint_std[checked] + slack
    assert np.all(error < bound), (np.flatnonzero(checked), error, bound)


def test_coatings_from_a_plate_rendered_with_another_seed(plate_rgb, images):
    plate = fitting.Plate(rgb=plate_rgb, weight=np.ones(plate_rgb.shape[:2]), source="seed 7", layer="")
    result = fitting.fit(SCENE, plate, params=("coatings",), fixed=images, block=BLOCK)
    assert result.model == "path-images" and result.converged, result.status
    assert_recovered(result)
    # the two coloured interfaces are found to better than 0.12 in every channel, and known to 0.25
    np.testing.assert_allclose(result.coating_tints[[4, 7]], TRUE_TINTS[[4, 7]], atol=0.12)
    assert np.all(result.tint_std[[4, 7]] < 0.25)
    # the result's render is the flare with the fitted tints at full resolution; the residual is plate - render
    np.testing.assert_allclose(result.residual, result.render - plate_rgb)
    assert result.render.shape == plate_rgb.shape
    # the fitted flare is much closer to the plate than the uncoloured start
    start = fitting.fit(SCENE, plate, params=("coatings",), fixed=images, block=BLOCK, max_steps=1)
    assert np.linalg.norm(result.residual) < 0.7 * np.linalg.norm(start.residual)


def within_errors(result, *, sigmas, slack=0.03):
    """Per checked (interface, channel) tint (the two coloured interfaces and every interface the
    plate shows): is it within ``sigmas`` standard errors (+ ``slack``) of the truth?"""
    checked = np.all(result.tint_std < fitting.OBSERVABLE_STD, axis=1)
    checked[[4, 7]] = True
    return (np.abs(result.coating_tints - TRUE_TINTS) < sigmas * result.tint_std + slack)[checked]


def test_coatings_under_added_noise_with_its_sigma(plate_rgb, images):
    """Gaussian noise of 1 % of the plate's peak, declared as the plate's sigma: the standard
    errors grow with it and, over four noise realisations, cover the truth for at least 95 % of
    the checked tints within 3 standard errors. (One realisation is not enough: a ghost's image is
    the product of its two interfaces' tints, so where noise pushes one tint up the linearised
    standard error of its partner shrinks, and a single draw landed 4.9 of them off.)"""
    sigma = 0.01 * plate_rgb.max()
    weight = np.full(plate_rgb.shape[:2], 1.0 / sigma)
    clean = fitting.fit(SCENE, fitting.Plate(rgb=plate_rgb, weight=weight, source="clean", layer=""), params=("coatings",),
                        fixed=images, block=BLOCK)
    covered, stds = [], []
    for seed in (3, 4, 5, 6):
        noisy = plate_rgb + np.random.default_rng(seed).normal(0.0, sigma, plate_rgb.shape)
        result = fitting.fit(SCENE, fitting.Plate(rgb=noisy, weight=weight, source=f"noisy {seed}", layer=""), params=("coatings",),
                             fixed=images, block=BLOCK)
        assert result.converged, result.status
        covered.append(within_errors(result, sigmas=3.0))
        stds.append(result.tint_std[[4, 7]])
    assert np.all(np.median(stds, axis=0) > clean.tint_std[[4, 7]])
    covered = np.concatenate(covered)
    assert covered.mean() >= 0.95, (covered.sum(), covered.size)


def test_background_under_a_mask_is_ignored_and_without_it_spoils_the_fit(plate_rgb, images):
    """Picture content (a bright textured patch) over a corner of the plate: masked out, the fit is
    the same as on the clean plate; not masked, it drags the tints away."""
    height, width = plate_rgb.shape[:2]
    rng = np.random.default_rng(5)
    background = np.zeros_like(plate_rgb)
    background[: height // 2, : width // 4] = plate_rgb.max() * (0.5 + rng.random((height // 2, width // 4, 3)))
    mask = np.ones((height, width))
    mask[: height // 2, : width // 4] = 0.0
    masked = fitting.fit(SCENE, fitting.Plate(rgb=plate_rgb + background, weight=mask, source="masked", layer=""), params=("coatings",),
                         fixed=images, block=BLOCK)
    clean = fitting.fit(SCENE, fitting.Plate(rgb=plate_rgb, weight=mask, source="clean", layer=""), params=("coatings",), fixed=images, block=BLOCK)
    np.testing.assert_allclose(masked.coating_tints, clean.coating_tints, atol=1e-6)
    assert np.all(masked.residual[: height // 2, : width // 4] == 0.0)  # no residual where the plate is masked
    assert_recovered(masked)
    unmasked = fitting.fit(SCENE, fitting.Plate(rgb=plate_rgb + background, weight=np.ones((height, width)), source="unmasked", layer=""),
                           params=("coatings",), fixed=images, block=BLOCK)
    assert np.abs(unmasked.coating_tints - TRUE_TINTS).max() > 0.3


def test_polynomial_model_fits_an_exactly_traced_plate(tmp_path, monkeypatch):
    """The plate is traced exactly, the fit's path images come from the polynomial path system of
    the brightest ghost: its colour (the product of its interfaces' tints) agrees to 8 %."""
    monkeypatch.setenv("JAXFLARE_CACHE_DIR", str(tmp_path))
    scene = dataclasses.replace(SCENE, camera=dataclasses.replace(SCENE.camera, resolution=(96, 64)),
                                lights=(jf.Light(kind="directional", direction=(0.03, 0.01, -1.0)),))
    paths = [(7, 4)]
    truth = with_tints(scene, TRUE_TINTS)
    plate_rgb = jf.render(truth, samples=2**18, seed=7, method="exact", paths=paths).image[..., :3]
    plate = fitting.Plate(rgb=plate_rgb, weight=np.ones(plate_rgb.shape[:2]), source="exact", layer="")
    result = fitting.fit(scene, plate, params=("coatings",), method="polynomial", paths=paths, samples=2**18, block=BLOCK, max_steps=300)
    assert result.model == "path-images", result.model
    for j, i in paths:
        np.testing.assert_allclose(result.coating_tints[j] * result.coating_tints[i], TRUE_TINTS[j] * TRUE_TINTS[i], rtol=0.08, atol=0.02)


def test_dirt_from_a_plate_rendered_with_another_seed(tmp_path):
    """A dirt blotch on the front lens, rendered into the plate through a dirt-map file with
    another seed: the fit (sample model, 4 x 4 map) finds it where the flare's light passes,
    and cells no light passes keep the prior, with zero sensitivity."""
    truth = np.ones((4, 4, 1), np.float32)
    truth[1:3, 2:4] = 0.4
    jf.write_exr(tmp_path / "dirt.exr", {"": truth}, pixel_type="float")
    dirty = dataclasses.replace(SCENE, camera=dataclasses.replace(SCENE.camera, dirt_map=str(tmp_path / "dirt.exr")))
    plate_rgb = jf.render(dirty, samples=2**19, seed=7).image[..., :3]
    plate = fitting.Plate(rgb=plate_rgb, weight=np.ones(plate_rgb.shape[:2]), source="dirty", layer="")
    result = fitting.fit(SCENE, plate, params=("dirt",), samples=2**18, dirt_resolution=4, block=BLOCK, max_steps=40)
    assert result.model == "samples"
    lit = result.dirt_sensitivity[..., 0] > 0.2
    dark = result.dirt_sensitivity[..., 0] == 0.0
    blotch = truth[..., 0] < 1.0
    assert (lit & blotch).sum() >= 2 and (lit & ~blotch).sum() >= 2
    np.testing.assert_allclose(result.dirt[lit], truth[lit], atol=0.2)
    assert result.dirt[lit & blotch].max() < result.dirt[lit & ~blotch].min() - 0.3  # the blotch stands out
    np.testing.assert_allclose(result.dirt[dark], fitting.DIRT_PRIOR, atol=1e-6)


def test_bad_model_choices_are_clear_errors(plate_rgb, images):
    plate = fitting.Plate(rgb=plate_rgb, weight=np.ones(plate_rgb.shape[:2]), source="p", layer="")
    with pytest.raises(ValueError, match="model must be one of auto, grid, path-images, samples"):
        fitting.fit(SCENE, plate, params=("coatings",), model="fast")
    with pytest.raises(ValueError, match="cannot fit the dirt map"):
        fitting.fit(SCENE, plate, params=("dirt",), model="path-images")
    with pytest.raises(ValueError, match="block must be a positive integer dividing the resolution 64 x 48, got 5"):
        fitting.fit(SCENE, plate, params=("coatings",), fixed=images, block=5)
    black = fitting.Plate(rgb=np.zeros_like(plate_rgb), weight=np.ones(plate_rgb.shape[:2]), source="black.exr", layer="")
    with pytest.raises(ValueError, match="black.exr: no light where its weight is non-zero"):
        fitting.fit(SCENE, black, params=("coatings",), fixed=images, block=BLOCK)
