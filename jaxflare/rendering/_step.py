"""One batch of the Monte Carlo flare renderer: sample, trace, weigh by equation (2), splat.

Every path set of the render (:mod:`._path_sets`) draws its samples and traces them with its own
path tracer; values are normalised per batch (divided by the batch's sample count), so the image
is the mean over batches and each batch is an unbiased estimate whatever its sampling table.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..colour import SpectralTable
from ..optics import Lens
from ._lights import LightArrays, light_rgb
from ._path_sets import AbstractPathSet
from ._records import SampleRecords, record_values
from ._sampling import FrontDisc
from ._splat import splat
from .effects import SceneEffects


class RenderSetup(eqx.Module):
    """Everything one render step reads."""

    lens: Lens
    lights: LightArrays
    front: FrontDisc
    spectral: SpectralTable
    path_sets: tuple[AbstractPathSet, ...]
    effects: SceneEffects
    path_fresnel: Float[Array, "P L"]
    """Coated Fresnel factor of each path on the axis, per wavelength of the spectral grid."""
    path_tint: Float[Array, "P 3"]
    path_layer: Int[Array, " P"]
    path_is_flare: Array
    path_enabled: Array
    """False for culled paths: their samples count for nothing (and adaptive tables skip them)."""
    pixel_pitch_mm: Float[Array, ""]
    resolution: tuple[int, int] = eqx.field(static=True)
    wavelength_strata: int = eqx.field(static=True)
    schlick: bool = eqx.field(static=True)


class Accumulators(eqx.Module):
    """What the batches add up (all normalised per batch: divide by the number of batches)."""

    layers: Float[Array, "Y H W 3"]
    flare_luminance_sum: Float[Array, "H W"]
    flare_luminance_squares: Float[Array, "H W"]
    """Per-batch flare luminance images divided by :func:`luminance_norm`, summed and squared: the
    per-pixel standard-deviation layer."""
    path_energy: Float[Array, "P 3"]
    path_incoming: Float[Array, " P"]
    """Luminance of the light entering the sampled front disc, per path (for the culling bound)."""
    path_hits: Int[Array, " P"]
    path_passed: Int[Array, " P"]
    path_unevaluated: Int[Array, " P"]
    path_samples: Int[Array, " P"]
    table_energy: tuple[Float[Array, " K"], ...]
    """Per path set with a sampling table: the energy each table entry carried."""
    weight_all: Float[Array, ""]
    weight_hits: Float[Array, ""]


def luminance_norm(lights) -> Array:
    """The brightest light's emission (at least 1e-30): the unit of the accumulated luminance
    squares."""
    return jnp.maximum(jnp.max(lights.emission), 1e-30).astype(jnp.float32)


def empty_accumulators(setup: RenderSetup, num_layers: int) -> Accumulators:
    width, height = setup.resolution
    paths = setup.path_layer.shape[0]
    f32 = jnp.float32
    return Accumulators(
        layers=jnp.zeros((num_layers, height, width, 3), f32),
        flare_luminance_sum=jnp.zeros((height, width), f32),
        flare_luminance_squares=jnp.zeros((height, width), f32),
        path_energy=jnp.zeros((paths, 3), f32),
        path_incoming=jnp.zeros(paths, f32),
        path_hits=jnp.zeros(paths, jnp.int32),
        path_passed=jnp.zeros(paths, jnp.int32),
        path_unevaluated=jnp.zeros(paths, jnp.int32),
        path_samples=jnp.zeros(paths, jnp.int32),
        table_energy=tuple(jnp.zeros(s.table.probability.shape, f32) for s in setup.path_sets if s.table is not None),
        weight_all=jnp.zeros((), f32),
        weight_hits=jnp.zeros((), f32),
    )


def batch_records(setup: RenderSetup, key: Array) -> tuple[SampleRecords, ...]:
    """Sample and trace one batch of every path set: one :class:`SampleRecords` per set."""
    return tuple(path_set.records(setup, key) for path_set in setup.path_sets)


@eqx.debug.assert_max_traces(max_traces=None)  # counts compilations: tests catch retracing with get_num_traces
def render_step(setup: RenderSetup, acc: Accumulators, key: Array) -> Accumulators:
    """One batch of every path set; returns the accumulators with the batch added."""
    width, height = setup.resolution
    luminance_weights = setup.spectral.luminance_weights.astype(jnp.float32)
    batch_luminance = jnp.zeros((1, height, width, 1), jnp.float32)
    table = 0
    for path_set, records in zip(setup.path_sets, batch_records(setup, key)):
        colour = light_rgb(setup.lights, setup.spectral, records.light, records.wavelength_nm)
        value = record_values(
            records, setup.lights, setup.spectral, setup.path_fresnel, setup.path_tint, setup.effects.dirt, setup.front.radius_mm,
            rgb=colour,
        ).astype(jnp.float32)
        path, hit = records.path, records.hit
        layer = setup.path_layer[path]
        flare = setup.path_is_flare[path] & hit
        lum = value @ luminance_weights
        # light entering the front disc (before the lens path), for the culling bound
        incoming = (colour @ luminance_weights) * records.flux_factor
        is_flare = setup.path_is_flare[path] & setup.path_enabled[path]
        acc = eqx.tree_at(
            lambda a: (a.layers, a.path_energy, a.path_incoming, a.path_hits, a.path_passed, a.path_unevaluated, a.path_samples, a.weight_all, a.weight_hits),
            acc,
            (
                splat(acc.layers, layer, records.column, records.row, value, hit),
                acc.path_energy.at[path].add(value),
                acc.path_incoming.at[path].add(incoming.astype(jnp.float32)),
                acc.path_hits.at[path].add(hit.astype(jnp.int32)),
                acc.path_passed.at[path].add(records.valid.astype(jnp.int32)),
                acc.path_unevaluated.at[path].add((~records.evaluated).astype(jnp.int32)),
                acc.path_samples.at[path].add(1),
                acc.weight_all + jnp.sum(jnp.where(is_flare, records.weight, 0.0)),
                acc.weight_hits + jnp.sum(jnp.where(flare, records.weight, 0.0)),
            ),
        )
        batch_luminance = splat(batch_luminance, jnp.zeros_like(layer), records.column, records.row, lum[:, None], flare)
        if path_set.table is not None:
            energy = jnp.where(hit, lum, 0.0)
            acc = eqx.tree_at(lambda a: a.table_energy[table], acc, acc.table_energy[table].at[records.table_index].add(energy))
            table += 1
    # relative to the brightest light's emission, so that the squares stay in float32's range
    # for any light intensity (the result's standard deviation multiplies it back in float64)
    image = batch_luminance[0, :, :, 0] / luminance_norm(setup.lights)
    return eqx.tree_at(
        lambda a: (a.flare_luminance_sum, a.flare_luminance_squares),
        acc,
        (acc.flare_luminance_sum + image, acc.flare_luminance_squares + image * image),
    )


STEP = eqx.filter_jit(render_step)
STEP_DONATING = eqx.filter_jit(render_step, donate="all-except-first")
"""One compiled step per render structure (lens, path sets, lights, resolution, layers, effects),
shared by every render with that structure. Accelerators update the accumulators in place (CPU
XLA cannot donate buffers)."""

