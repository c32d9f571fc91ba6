"""Trace groups: the exact sets of a render (flares, core) are connected, traced and recorded by
one call, and each ray comes out as its own set's tracer would have traced it."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxflare as jf
from jaxflare.optics import ExactPathTracer
from jaxflare.rendering import group_records, plan_render, trace_groups

# compiled as a render step compiles them (run op by op, their scans and gathers compile one by one)
jit_group_records = eqx.filter_jit(group_records)
jit_set_records = eqx.filter_jit(lambda path_set, setup, key: path_set.records(setup, key))
jit_draw_cells = eqx.filter_jit(lambda path_set, key: path_set.draw_cells(key))


def test_a_joined_tracer_traces_each_ray_along_its_own_sets_path(biotar):
    ghosts = ExactPathTracer.for_paths(biotar, [(4, 2), (6, 1)], 1)
    core = ExactPathTracer.for_paths(biotar, [None], 1)
    joined = ExactPathTracer.joined([ghosts, core])
    assert joined.num_paths == 3 and joined.events.surface.shape[1] == ghosts.events.surface.shape[1]
    rng = np.random.default_rng(3)
    count = 96
    origins = np.column_stack([rng.uniform(-6, 6, (count, 2)), np.full(count, -5.0)])
    directions = np.column_stack([rng.uniform(-0.05, 0.05, (count, 2)), np.ones(count)])
    wavelengths = rng.uniform(420.0, 680.0, count)
    slot = rng.integers(0, 3, count)
    together = joined.trace(jnp.asarray(origins), jnp.asarray(directions), jnp.asarray(wavelengths), jnp.asarray(slot))
    ghost_rays, core_rays = slot < 2, slot == 2
    apart_ghosts = ghosts.trace(*(jnp.asarray(x[ghost_rays]) for x in (origins, directions, wavelengths, slot)))
    apart_core = core.trace(*(jnp.asarray(x[core_rays]) for x in (origins, directions, wavelengths)), jnp.zeros(int(core_rays.sum()), int))
    for part, mask in ((apart_ghosts, ghost_rays), (apart_core, core_rays)):
        np.testing.assert_array_equal(np.asarray(together.valid)[mask], np.asarray(part.valid))
        np.testing.assert_allclose(np.asarray(together.positions)[mask], np.asarray(part.positions), rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(together.throughput)[mask], np.asarray(part.throughput), rtol=1e-12, atol=0)
    assert np.asarray(together.valid)[core_rays].mean() > 0.5 and np.asarray(together.valid)[ghost_rays].any()


def test_tracers_of_different_fresnel_models_do_not_join(biotar):
    with pytest.raises(ValueError, match="Fresnel"):
        ExactPathTracer.joined([ExactPathTracer.for_paths(biotar, [(4, 2)]), ExactPathTracer.for_paths(biotar, [None], fresnel=False)])


def test_the_flares_and_the_core_are_one_group_recorded_set_by_set():
    scene = jf.Scene(
        camera=jf.Camera(lens="zeiss_biotar", f_number=8.0, resolution=(32, 24), look_at_m=(0.0, 0.0, -10.0)),
        lights=(jf.Light(kind="directional", direction=(0.03, 0.0, -1.0)),),
    )
    plan = plan_render(scene, samples=2**12, method="exact", paths=[(4, 2), (6, 1)])
    sets = plan.setup.path_sets
    assert trace_groups(sets) == [[0, 1]]
    key = plan.batch_key(0)
    records = jit_group_records(plan.setup, list(sets), key)
    core_index = plan.paths.index(None)
    for path_set, record in zip(sets, records):
        assert record.path.shape == (path_set.samples,)
        assert set(np.unique(np.asarray(record.path))) <= set(np.asarray(path_set.path_index).tolist())
        index = np.asarray(record.table_index)
        assert index.min() >= 0 and index.max() < path_set.sampling_table.probability.shape[0]
        _, _, _, drawn_index, weight, _ = jit_draw_cells(path_set, key)  # each set keeps its own table's draw
        np.testing.assert_array_equal(index, np.asarray(drawn_index))
        np.testing.assert_allclose(np.asarray(record.weight), np.asarray(weight))
    assert np.all(np.asarray(records[1].path) == core_index)
    # the core's rays get through as often as when the core set is traced on its own (other
    # random numbers: within five standard errors of the difference)
    together, apart = np.asarray(records[1].hit).mean(), np.asarray(jit_set_records(sets[1], plan.setup, key).hit).mean()
    assert together > 0.05 and abs(together - apart) < 5 * np.sqrt(2 * apart * (1 - apart) / records[1].hit.shape[0])
    # a set alone is recorded exactly as the set records itself
    alone = jit_group_records(plan.setup, [sets[0]], key)[0]
    direct = jit_set_records(sets[0], plan.setup, key)
    for a, b in zip(jax.tree.leaves(alone), jax.tree.leaves(direct)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
