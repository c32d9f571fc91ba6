"""The grid estimator through the public routes: ``render(estimator=...)``, the scene's
``[render] estimator`` key, ``jaxflare render --estimator``; its EXR holds the same layers as a
Monte Carlo render's, with a zero variance layer, finite and non-negative pixels."""

import json

import numpy as np
import pytest

import jaxflare as jf
from jaxflare.cli import build_parser
from jaxflare import rendering
from jaxflare.io import read_exr
from jaxflare.scenes import SceneError, scene_from_dict

from .grid_cases import grid, monte_carlo, scene

A_SCENE = {"camera": {"lens": "zeiss_biotar"}, "light": [{"kind": "point", "position_m": [1.0, 0.5, -10.0]}]}


def test_scene_key_and_command_line_choose_the_estimator():
    assert scene_from_dict({**A_SCENE, "render": {"estimator": "grid"}}).render.estimator == "grid"
    assert scene_from_dict(A_SCENE).render.estimator == "monte-carlo"
    with pytest.raises(SceneError, match=r"render\.estimator"):
        scene_from_dict({**A_SCENE, "render": {"estimator": "grids"}})
    args = build_parser().parse_args(["render", "demo", "-o", "x.exr", "--estimator", "grid"])
    assert args.estimator == "grid"


def test_render_rejects_unknown_estimators_and_monte_carlo_options_for_the_grid():
    with pytest.raises(ValueError, match="estimator"):
        jf.render(scene(), estimator="grids")
    with pytest.raises(ValueError, match="samples= and method="):
        jf.render(scene(), estimator="grid", samples=1000)


def test_grid_exr_has_the_monte_carlo_layers(tmp_path):
    result = grid()
    mc = monte_carlo()[0]
    assert set(result.layers) == set(mc.layers)
    assert not np.any(result.layers["variance"])
    layers, header = read_exr(result.write_exr(tmp_path / "grid.exr"))
    assert set(layers) == {""} | set(mc.layers)
    assert json.loads(header["jaxflare/settings"])["estimator"] == "grid"
    for name, layer in result.layers.items():
        assert np.all(np.isfinite(layer)) and layer.min() >= -1e-6 * max(layer.max(), 0.0), name
    np.testing.assert_allclose(result.image[..., :3], sum(result.layers[n] for n in result.layers if n.startswith("flare")), rtol=1e-6, atol=1e-9)


def test_a_splat_of_more_sub_samples_than_one_table_holds_is_split_into_groups(monkeypatch):
    """Sub-sample indices are 32-bit integers on the device, so a render of more than
    ``SPLAT_GROUP_SUBSAMPLES`` (2^30) is splatted in groups (a 720p reference asked for 4.3 G and
    overflowed). Forced here at a tiny limit: the same sub-samples in several groups give the same
    energy, and the image differs only by each group's sub-sample lattice offsets restarting."""
    from jaxflare.rendering import _grid

    s = scene()
    whole = rendering.render_grid(s, paths=[(7, 4), (9, 7)])
    monkeypatch.setattr(_grid, "SPLAT_GROUP_SUBSAMPLES", whole.statistics.samples // 3)
    plan = rendering.plan_grid(s, paths=[(7, 4), (9, 7)])
    assert len(rendering.prepare_grid(plan).prepared.more) >= 2
    grouped = rendering.render_grid(s, paths=[(7, 4), (9, 7)])
    assert grouped.statistics.samples == whole.statistics.samples
    a, b = np.asarray(whole.image[..., :3], np.float64), np.asarray(grouped.image[..., :3], np.float64)
    assert b.sum() == pytest.approx(a.sum(), rel=1e-4)
    assert np.linalg.norm(b - a) < 0.02 * np.linalg.norm(a)
