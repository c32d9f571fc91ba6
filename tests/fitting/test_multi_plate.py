"""Fitting several plates of one lens at once: shared coatings (and dirt), light gains per plate."""

import dataclasses
import json

import numpy as np
import pytest

import fitting
import jaxflare as jf
from fitting._fit import _path_tints
from fitting._grid_model import grid_interfaces

jax = pytest.importorskip("jax")
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402

SCENE = jf.Scene(
    camera=jf.Camera(lens="zeiss_biotar", f_number=4.0, resolution=(64, 48), look_at_m=(0.0, 0.0, -10.0)),
    lights=(jf.Light(kind="directional", direction=(0.06, 0.03, -1.0)),),
)
SECOND = dataclasses.replace(SCENE, lights=(jf.Light(kind="directional", direction=(-0.05, 0.04, -1.0)),))
TRUE_TINTS = np.ones((10, 3))
TRUE_TINTS[7] = (1.0, 0.6, 0.3)
TRUE_TINTS[4] = (0.5, 0.9, 1.2)
GAINS = (1.0, 1.3)
_image = eqx.filter_jit(lambda flare, tint, gain: flare.image(tint, None, gain))


@pytest.fixture(scope="module")
def models_and_plates():
    models, plates = [], []
    for k, (scene, gain) in enumerate(zip((SCENE, SECOND), GAINS)):
        model = jf.rendering.grid_flare_model(scene, "production")
        tint = _path_tints(jnp.asarray(grid_interfaces(model)), jnp.asarray(TRUE_TINTS, jnp.float32))
        rgb = np.asarray(_image(model, tint, jnp.full((1, 3), gain, jnp.float32)), np.float64)
        models.append(model)
        plates.append(fitting.Plate(rgb=rgb, weight=np.ones(rgb.shape[:2]), source=f"plate {k}"))
    return models, plates


def test_two_plates_share_coatings_and_keep_their_own_gains(models_and_plates, tmp_path):
    models, plates = models_and_plates
    result = fitting.fit([SCENE, SECOND], plates, params=("coatings", "lights"), fixed=models)
    assert result.converged and result.plates == 2
    assert len(result.render) == 2 and len(result.light_gain) == 2
    # tints and gains share one overall scale (a brighter light or brighter coatings): their ratios are fixed
    ratio = result.light_gain[1] / result.light_gain[0]
    np.testing.assert_allclose(ratio, GAINS[1] / GAINS[0], rtol=0.01)
    scale = float(np.mean(result.light_gain[0]))
    np.testing.assert_allclose(result.coating_tints[[4, 7]] * scale, TRUE_TINTS[[4, 7]], atol=0.06)
    for render, plate in zip(result.render, plates):
        assert np.linalg.norm(render - plate.rgb) < 0.05 * np.linalg.norm(plate.rgb)
    path = fitting.save_fit(result, tmp_path / "two.json")
    data = json.loads(open(path).read())
    assert data["plates"] == 2 and data["renders"] == ["two_render_0.exr", "two_render_1.exr"]
    assert (tmp_path / "two_render_1.exr").exists()
    second = fitting.apply_fit(SECOND, path, plate=1)
    np.testing.assert_allclose(second.lights[0].rgb, result.light_gain[1][0], rtol=1e-6)
    with pytest.raises(ValueError, match="light gains for 2 plates: pass plate="):
        fitting.apply_fit(SECOND, path)


def test_coatings_from_two_plates(models_and_plates):
    models, plates = models_and_plates
    plates = [plates[0], dataclasses.replace(plates[1], rgb=plates[1].rgb / GAINS[1])]
    result = fitting.fit([SCENE, SECOND], plates, params=("coatings",), fixed=models)
    assert result.converged
    observable = np.all(result.tint_observable, axis=1)
    assert observable[[4, 7]].all()
    np.testing.assert_allclose(result.coating_tints[observable], TRUE_TINTS[observable], atol=0.05)
    single = fitting.fit(SCENE, plates[0], params=("coatings",), fixed=models[0])
    # two light positions show at least as much of the lens as one: no standard error grows
    assert np.all(result.tint_std <= single.tint_std * 1.001)


def test_plates_and_scenes_must_match(models_and_plates):
    models, plates = models_and_plates
    with pytest.raises(ValueError, match="3 scenes for 2 plates"):
        fitting.fit([SCENE, SECOND, SCENE], plates, params=("coatings",))
    with pytest.raises(ValueError, match="one forward model for 2 plates"):
        fitting.fit(SCENE, plates, params=("coatings",), fixed=models[0])
    other = dataclasses.replace(SCENE, camera=dataclasses.replace(SCENE.camera, lens="tronnier_heliar"))
    with pytest.raises(ValueError, match="another lens"):
        fitting.fit([SCENE, other], plates, params=("coatings",))
