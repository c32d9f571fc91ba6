"""The tracer's fast formulation (struct of arrays, skipped padding, materialised values, chunks,
optional Fresnel, rays of several paths sorted by length) traces the same rays as the formulation
it replaced (tests/optics/reference_tracer.py), on every bundled lens, for the primary path and a
sample of ghost paths, over the whole visible band, gradients included."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxflare
from jaxflare.optics import CHUNK_RAYS, EventTable, ExactPathTracer, path_events, trace_events
from tests.optics.reference_tracer import reference_trace_events


def rays(lens, count, seed, spread=0.12):
    rng = np.random.default_rng(seed)
    radius = float(lens.semi_aperture_mm[0])
    origins = np.stack([rng.uniform(-radius, radius, count), rng.uniform(-radius, radius, count), np.full(count, -2.0)], -1)
    directions = np.stack([rng.normal(0, spread, count), rng.normal(0, spread, count), np.ones(count)], -1)
    return jnp.asarray(origins), jnp.asarray(directions), jnp.asarray(rng.uniform(380.0, 780.0, count))


def assert_same_rays(reference, result, passes):
    valid = np.asarray(reference.valid)
    np.testing.assert_array_equal(np.asarray(result.valid), valid)
    np.testing.assert_array_equal(np.asarray(result.lost_at_surface), np.asarray(reference.lost_at_surface))
    np.testing.assert_allclose(np.asarray(result.positions)[valid], np.asarray(reference.positions)[valid], atol=1e-9)
    np.testing.assert_allclose(np.asarray(result.directions)[valid], np.asarray(reference.directions)[valid], atol=1e-11)
    np.testing.assert_allclose(np.asarray(result.throughput), np.asarray(reference.throughput), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(np.asarray(result.stop_positions), np.asarray(reference.stop_positions)[:, :passes], atol=1e-9)


@pytest.mark.parametrize("name", jaxflare.bundled_lens_names())
def test_every_bundled_lens_traces_as_before(name):
    lens = jaxflare.load_lens(name)
    ghosts = jaxflare.ghost_paths(lens)
    origins, directions, wavelength = rays(lens, 1500, seed=len(name))
    for path in [None, ghosts[0], ghosts[len(ghosts) // 2], ghosts[-1]]:
        events = path_events(lens, path)
        # the first stop pass of every path: one compilation per lens for each tracer
        reference = reference_trace_events(lens, origins, directions, wavelength, jnp.asarray(events), 1)
        assert_same_rays(reference, trace_events(lens, origins, directions, wavelength, EventTable.from_array(events), 1), 1)


def test_rays_of_mixed_paths_sorted_by_length_come_back_in_their_order(biotar):
    """The renderer's batches: rays of 45 ghost paths and the primary path mixed, in more than
    one chunk, traced in order of path length and put back."""
    paths = [None] + jaxflare.ghost_paths(biotar)
    count = CHUNK_RAYS + 3000
    origins, directions, wavelength = rays(biotar, count, seed=4, spread=0.05)
    slot = jnp.asarray(np.random.default_rng(5).integers(0, len(paths), count))
    tables = np.stack([path_events(biotar, p) for p in paths])
    reference = reference_trace_events(biotar, origins, directions, wavelength, jnp.asarray(tables)[slot], 1)
    tracer = ExactPathTracer.for_paths(biotar, paths, 1)
    assert tracer.events.surface.shape[1] < tables.shape[1]  # padding no path needs is cut
    assert_same_rays(reference, tracer.trace(origins, directions, wavelength, slot), 1)
    # a table row per ray, without slots, is the same trace
    assert_same_rays(reference, trace_events(biotar, origins, directions, wavelength, EventTable.from_array(tables[np.asarray(slot)]), 1), 1)


def test_without_fresnel_the_geometry_is_unchanged_and_the_throughput_is_one(biotar):
    origins, directions, wavelength = rays(biotar, 2000, seed=6)
    full = jaxflare.trace(biotar, origins, directions, wavelength, (5, 2))
    geometric = jaxflare.trace(biotar, origins, directions, wavelength, (5, 2), fresnel=False)
    valid = np.asarray(full.valid)
    np.testing.assert_array_equal(np.asarray(geometric.valid), valid)
    np.testing.assert_array_equal(np.asarray(geometric.positions), np.asarray(full.positions))
    np.testing.assert_array_equal(np.asarray(geometric.throughput), valid.astype(float))
    assert np.all(np.asarray(full.throughput)[valid] < 1e-2)  # two reflections


def test_gradients_match_the_former_formulation(biotar):
    """Gradients of a masked sensor loss with respect to the rays and to the curvatures."""
    origins, directions, wavelength = rays(biotar, 600, seed=7, spread=0.04)
    events = path_events(biotar, (7, 4))

    def gradients(trace):
        def value(curvature, o, d):
            lens = eqx.tree_at(lambda l: l.curvature_per_mm, biotar, curvature)
            result = trace(lens, o, d)
            return jnp.sum(jnp.where(result.valid, result.positions[:, 0] ** 2 + result.throughput * 1e3, 0.0))

        return jax.grad(value, argnums=(0, 1, 2))(biotar.curvature_per_mm, origins, directions)

    new = gradients(lambda lens, o, d: jaxflare.trace(lens, o, d, wavelength, (7, 4)))
    old = gradients(lambda lens, o, d: reference_trace_events(lens, o, d, wavelength, jnp.asarray(events), 1))
    for a, b in zip(new, old):
        assert np.all(np.isfinite(np.asarray(a)))
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-7, atol=1e-6 * np.abs(np.asarray(b)).max())
    assert np.abs(np.asarray(new[0])).max() > 0
