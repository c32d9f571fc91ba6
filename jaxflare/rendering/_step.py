"""One batch of the Monte Carlo flare renderer: sample, trace, weigh by equation (2), splat.

Every path set of the render (:mod:`._path_sets`) draws its samples and traces them with its own
path tracer (the exact sets of one lens as one trace group: one tracer call); values are
normalised per batch (divided by the batch's sample count), so the image is the mean over batches
and each batch is an unbiased estimate whatever its sampling table. The compiled step holds each
piece of code once: CPU compilation time grows with the number of kernels (a 128 x 96 Biotar step
with its core went from 528 to 332 kernels, 15.5 s to 9.1 s of compiler CPU time, when the sets
were grouped and their records merged).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..colour import SpectralTable
from ..optics import Lens
from ._lights import LightArrays, light_rgb
from ._path_sets import AbstractPathSet, group_records, trace_groups
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
    """Sample and trace one batch of every path set: one :class:`SampleRecords` per set (the sets
    of a trace group sampled, traced and recorded together, :func:`group_records`)."""
    records: list = [None] * len(setup.path_sets)
    for members in trace_groups(setup.path_sets):
        if len(members) == 1:
            records[members[0]] = setup.path_sets[members[0]].records(setup, key)
            continue
        for k, r in zip(members, group_records(setup, [setup.path_sets[k] for k in members], key)):
            records[k] = r
    return tuple(records)


def merged_records(records: tuple[SampleRecords, ...]) -> SampleRecords:
    """The sets' records as one (concatenated in set order; without table entries)."""
    bare = [dataclasses.replace(r, table_index=None) for r in records]
    return bare[0] if len(bare) == 1 else jax.tree.map(lambda *xs: jnp.concatenate(xs), *bare)


@eqx.debug.assert_max_traces(max_traces=None)  # counts compilations: tests catch retracing with get_num_traces
def render_step(setup: RenderSetup, acc: Accumulators, key: Array) -> Accumulators:
    """One batch of every path set; returns the accumulators with the batch added. The sets'
    records are splatted and counted together (one copy of that code in the compiled step); only
    the adaptive tables' energies are summed set by set."""
    width, height = setup.resolution
    luminance_weights = setup.spectral.luminance_weights.astype(jnp.float32)
    per_set = batch_records(setup, key)
    records = merged_records(per_set)
    colour = light_rgb(setup.lights, setup.spectral, records.light, records.wavelength_nm)
    value = record_values(
        records, setup.lights, setup.spectral, setup.path_fresnel, setup.path_tint, setup.effects.dirt, setup.front.radius_mm, rgb=colour,
    ).astype(jnp.float32)
    path, hit = records.path, records.hit
    layer = setup.path_layer[path]
    flare = setup.path_is_flare[path] & hit
    lum = value @ luminance_weights
    # light entering the front disc (before the lens path), for the culling bound
    incoming = (colour @ luminance_weights) * records.flux_factor
    is_flare = setup.path_is_flare[path] & setup.path_enabled[path]
    # the per-path sums in one scatter (the counts are at most the batch size: exact in float32)
    per_sample = jnp.concatenate(
        [value, jnp.stack([incoming, hit, records.valid, ~records.evaluated, jnp.ones_like(hit)], axis=-1).astype(jnp.float32)], axis=-1,
    )
    per_path = jnp.zeros((acc.path_energy.shape[0], per_sample.shape[1]), jnp.float32).at[path].add(per_sample)
    count = lambda column: jnp.round(per_path[:, column]).astype(jnp.int32)  # noqa: E731
    table_energy = list(acc.table_energy)
    table, start = 0, 0
    energy = jnp.where(hit, lum, 0.0)
    for path_set, set_records in zip(setup.path_sets, per_set):
        size = set_records.path.shape[0]
        if path_set.table is not None:
            table_energy[table] = table_energy[table].at[set_records.table_index].add(energy[start : start + size])
            table += 1
        start += size
    batch_luminance = splat(jnp.zeros((1, height, width, 1), jnp.float32), jnp.zeros_like(layer), records.column, records.row, lum[:, None], flare)
    # relative to the brightest light's emission, so that the squares stay in float32's range
    # for any light intensity (the result's standard deviation multiplies it back in float64)
    image = batch_luminance[0, :, :, 0] / luminance_norm(setup.lights)
    return Accumulators(
        layers=splat(acc.layers, layer, records.column, records.row, value, hit),
        flare_luminance_sum=acc.flare_luminance_sum + image,
        flare_luminance_squares=acc.flare_luminance_squares + image * image,
        path_energy=acc.path_energy + per_path[:, :3],
        path_incoming=acc.path_incoming + per_path[:, 3],
        path_hits=acc.path_hits + count(4),
        path_passed=acc.path_passed + count(5),
        path_unevaluated=acc.path_unevaluated + count(6),
        path_samples=acc.path_samples + count(7),
        table_energy=tuple(table_energy),
        weight_all=acc.weight_all + jnp.sum(jnp.where(is_flare, records.weight, 0.0)),
        weight_hits=acc.weight_hits + jnp.sum(jnp.where(flare, records.weight, 0.0)),
    )


STEP = eqx.filter_jit(render_step)
STEP_DONATING = eqx.filter_jit(render_step, donate="all-except-first")
"""One compiled step per render structure (lens, path sets, lights, resolution, layers, effects),
shared by every render with that structure. Accelerators update the accumulators in place (CPU
XLA cannot donate buffers)."""

