"""The differentiable forward model of a fit: a flare render with fixed samples.

The samples of a render (their light, path, wavelength, front-lens point, pixel position and
geometric weight) do not depend on what a fit changes -- light colours and intensities, coating
tints and the front-lens dirt map only scale each sample's value (equation (2) of Pekkarinen &
Balzer 2019). So the samples are drawn and traced once (common random numbers: the loss is then a
smooth function of the parameters), and the image is their values splatted with fixed bilinear
weights: linear in tints, dirt and light gains, differentiable in everything, and fast.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxflare._render import prepare_render, radiance_scale
from jaxflare._render_step import SampleRecords, _splat, batch_records, record_values


class FixedSamples(eqx.Module):
    """A scene's render as fixed samples; :func:`render_image` turns parameters into an image."""

    records: SampleRecords
    setup: eqx.Module
    """The renderer's :class:`jaxflare._render_step.RenderSetup` (lights, spectral tables, lens)."""
    path_interfaces: Int[Array, "P 2"]
    """Reflecting interfaces (j, i) of each path; (-1, -1) for the primary path (the core)."""
    flare: Array
    """Which paths are flares (the core is not)."""
    to_radiance: Float[Array, ""]
    """Scale from summed sample values to pixel values (camera-equation radiance)."""
    resolution: tuple[int, int] = eqx.field(static=True)
    num_interfaces: int = eqx.field(static=True)


def fixed_samples(scene, *, samples: int = 2**20, seed: int = 0, method: str = "exact", quality: str = "preview") -> FixedSamples:
    """Draw and trace ``samples`` samples of ``scene`` once (in float32, as a render does)."""
    prepared = prepare_render(scene, quality, seed, samples=samples, method=method)
    setup = prepared.setup
    draw = eqx.filter_jit(batch_records)
    batches = []
    for b in range(prepared.batches):
        batches.append(draw(setup, jax.random.fold_in(jax.random.fold_in(prepared.key, 2), b)))
    # one SampleRecords for everything: concatenate over batches and path sets
    flat = [records for batch in batches for records in batch]
    records = jax.tree.map(lambda *xs: jnp.concatenate(xs), *[_without_index(r) for r in flat])
    to_radiance = radiance_scale(prepared.lens, prepared.pitch) / prepared.batches
    interfaces = np.array([p if p is not None else (-1, -1) for p in prepared.paths_all], np.int32)
    return FixedSamples(
        records=records, setup=setup, path_interfaces=jnp.asarray(interfaces), flare=jnp.asarray([p is not None for p in prepared.paths_all]),
        to_radiance=jnp.asarray(to_radiance), resolution=tuple(prepared.scene.camera.resolution),
        num_interfaces=prepared.lens.num_interfaces,
    )


def _without_index(records: SampleRecords) -> SampleRecords:
    return dataclasses.replace(records, table_index=None)


def path_tints(samples: FixedSamples, interface_tints: Float[Array, "I 3"]) -> Float[Array, "P 3"]:
    """Each path's coating colour: the product of the tints of its two reflecting interfaces."""
    j, i = samples.path_interfaces[:, 0], samples.path_interfaces[:, 1]
    tint = interface_tints[jnp.clip(j, 0)] * interface_tints[jnp.clip(i, 0)]
    return jnp.where((j >= 0)[:, None], tint, 1.0)


def render_image(
    samples: FixedSamples,
    interface_tints: Float[Array, "I 3"],
    dirt: Float[Array, "H W C"] | None,
    light_gain: Float[Array, "NL 3"] | None = None,
    *,
    include_core: bool = False,
) -> Float[Array, "H W 3"]:
    """The flare image (every flare together; with ``include_core`` also the lights' images) for
    the given interface tints, dirt map and light gains, in the renderer's pixel units."""
    setup = samples.setup
    records = samples.records
    tints = path_tints(samples, interface_tints.astype(records.geometry.dtype))
    lights = setup.lights
    if light_gain is not None:  # gains scale each light's colour (RGB lights) or brightness (spectra)
        gain = light_gain.astype(lights.rgb.dtype)
        lights = eqx.tree_at(
            lambda l: (l.rgb, l.spectral_rgb), lights, (lights.rgb * gain, lights.spectral_rgb * jnp.mean(gain, axis=1)[:, None, None])
        )
    values = record_values(records, lights, setup.spectral, setup.path_fresnel, tints, dirt, setup.front.radius_mm)
    keep = records.hit & (samples.flare[records.path] | include_core)
    width, height = samples.resolution
    buffer = jnp.zeros((1, height, width, 3), values.dtype)
    image = _splat(buffer, jnp.zeros_like(records.path), records.column, records.row, values, keep)[0]
    return image * samples.to_radiance.astype(values.dtype)


def as_float64(samples: FixedSamples) -> FixedSamples:
    """The samples with every float array in float64 (fits run in float64; needs jax x64)."""
    return jax.tree.map(lambda x: x.astype(jnp.float64) if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) else x, samples)


