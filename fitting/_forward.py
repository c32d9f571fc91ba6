"""The differentiable forward models of a fit: a flare render with fixed samples, or per-path images.

The samples of a render (their light, path, wavelength, front-lens point, pixel position and
geometric weight) do not depend on what a fit changes -- light colours and intensities, coating
tints and the front-lens dirt map only scale each sample's value (equation (2) of Pekkarinen &
Balzer 2019). So the samples are drawn and traced once (common random numbers: the loss is then a
smooth function of the parameters), and the image is their values splatted with fixed bilinear
weights: linear in tints, dirt and light gains, differentiable in everything
(:func:`fixed_samples`, :func:`render_image`).

With the dirt map fixed, the flare is a sum of per-path images times each path's tint (the
product of its two reflecting interfaces' tints) and the lights' gains. :func:`path_images`
renders those images once, batch by batch, so their cost does not grow with the samples and a
fit of coatings and lights can use many more samples than it could carry as records. That
matters: a least-squares fit against a model with Monte Carlo noise is biased (the noise adds to
the model's energy, so tints come out low), and the bias falls as 1/samples.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxflare.rendering import SampleRecords, batch_records, plan_render, radiance_scale, record_values, splat
from jaxflare.rendering.effects import dirt_cell_taps
from jaxflare.scenes import load_scene


class FixedSamples(eqx.Module):
    """A scene's render as fixed samples; :func:`render_image` turns parameters into an image."""

    records: SampleRecords
    setup: eqx.Module
    """The renderer's :class:`jaxflare.rendering.RenderSetup` (lights, spectral tables, lens)."""
    path_interfaces: Int[Array, "P 2"]
    """Reflecting interfaces (j, i) of each path; (-1, -1) for the primary path (the core)."""
    flare: Array
    """Which paths are flares (the core is not)."""
    to_radiance: Float[Array, ""]
    """Scale from summed sample values to pixel values (camera-equation radiance)."""
    resolution: tuple[int, int] = eqx.field(static=True)
    num_interfaces: int = eqx.field(static=True)


def _fit_scene(scene):
    """The scene as a fit samples it: no culling, since a fit may brighten any path (tints up to
    :data:`fitting._fit.TINT_MAX`), so every path keeps its samples; and no core (the lights' own
    image, which a plate's flare layer does not hold and no fitted parameter changes), so no sample
    and no path system is spent on it."""
    scene = load_scene(scene) if isinstance(scene, (str, bytes)) or hasattr(scene, "__fspath__") else scene
    return dataclasses.replace(scene, render=dataclasses.replace(scene.render, cull_threshold=0.0, core=False))


_draw = eqx.filter_jit(batch_records)


def _batches(scene, samples: int, seed: int, method: str, quality: str, paths=None):
    """The render's plan and a generator of its batches' sample records (one list per batch):
    the samples :func:`jaxflare.render` draws for this seed (and these ``paths``), from the plan's
    key schedule and sampling tables after the pilot."""
    plan = plan_render(_fit_scene(scene), quality, seed, samples=samples, method=method, paths=paths)

    def batches():
        for b in range(plan.batches):
            yield [_without_index(r) for r in _draw(plan.setup, plan.batch_key(b))]

    return plan, batches


def _path_interfaces(plan) -> np.ndarray:
    return np.array([p if p is not None else (-1, -1) for p in plan.paths], np.int32)


def fixed_samples(scene, *, samples: int = 2**20, seed: int = 0, method: str = "exact", quality: str = "preview", paths=None) -> FixedSamples:
    """Draw and trace ``samples`` samples of ``scene`` once (in float32, as a render does). The
    records of every sample are kept, so memory grows with ``samples`` (about 60 bytes each)."""
    plan, batches = _batches(scene, samples, seed, method, quality, paths)
    flat = [records for batch in batches() for records in batch]
    records = jax.tree.map(lambda *xs: jnp.concatenate(xs), *flat)
    return FixedSamples(
        records=records, setup=plan.setup, path_interfaces=jnp.asarray(_path_interfaces(plan)),
        flare=jnp.asarray([p is not None for p in plan.paths]), to_radiance=jnp.asarray(_to_radiance(plan)),
        resolution=tuple(plan.scene.camera.resolution), num_interfaces=plan.lens.num_interfaces,
    )


def _to_radiance(plan) -> float:
    return radiance_scale(plan.lens, plan.pixel_pitch_mm) / plan.batches


class PathImages(eqx.Module):
    """Each flare path's image with unit coating tints, weighted by the plate's pixel weights and
    summed over ``block`` x ``block`` pixels: with the dirt map fixed the flare is linear in the
    paths' tints and the lights' gains, so a fit of coatings and lights needs only these images,
    not the samples (:func:`path_image_model`). Their cost does not grow with the number of
    samples, so they can be made from many more samples than a fit could carry, which keeps
    the model's Monte Carlo noise (and the bias it gives a least-squares fit) small."""

    images: Float[Array, "P K Hb Wb 3"]
    """Per flare path ``P``, per gain basis ``K`` (light k, input channel c: ``K = 3 k + c``, or
    one basis, every gain 1, when the lights are not fitted)."""
    full_images: Float[Array, "P K H W 3"] | None
    """The same, unweighted at full resolution (float32), when they fit in
    :data:`FULL_IMAGE_BYTES`: the fit's final render is then their tinted sum."""
    path_interfaces: Int[Array, "P 2"]
    block: int = eqx.field(static=True)
    resolution: tuple[int, int] = eqx.field(static=True)
    num_interfaces: int = eqx.field(static=True)
    num_lights: int = eqx.field(static=True)
    samples: int = eqx.field(static=True)
    seed: int = eqx.field(static=True)
    method: str = eqx.field(static=True)
    quality: str = eqx.field(static=True)
    paths: tuple | None = eqx.field(static=True)
    """How they were made: :func:`flare_render` with these draws the same samples."""


def _unit_gains(num_lights: int, per_light_colour: bool) -> np.ndarray:
    if not per_light_colour:
        return np.ones((1, num_lights, 3))
    basis = np.zeros((3 * num_lights, num_lights, 3))
    for k in range(num_lights):
        for c in range(3):
            basis[3 * k + c, k, c] = 1.0
    return basis


def _gained_lights(lights, gain):
    """Light arrays with each light's colour scaled by ``gain`` (NL, 3): RGB lights per channel,
    spectral lights (a spectrum or a temperature) by the mean gain."""
    gain = gain.astype(lights.rgb.dtype)
    return eqx.tree_at(lambda l: (l.rgb, l.spectral_rgb), lights, (lights.rgb * gain, lights.spectral_rgb * jnp.mean(gain, axis=1)[:, None, None]))


PATH_IMAGE_BYTES = 2**30
"""Largest path-image stack (float64) a fit builds; above it the fit uses the samples."""
FULL_IMAGE_BYTES = 2**27
"""Largest full-resolution path-image stack (float32) kept for the fit's final render."""


def path_images_bytes(scene, num_paths: int, *, per_light_colour: bool, block: int) -> int:
    width, height = scene.camera.resolution
    num_lights = sum(1 for light in scene.lights if light.flare)
    bases = 3 * num_lights if per_light_colour else 1
    return num_paths * bases * (height // block) * (width // block) * 3 * 8


def path_images(
    scene, *, samples: int = 2**22, seed: int = 0, method: str = "exact", quality: str = "preview",
    pixel_weight: np.ndarray | None = None, block: int = 1, per_light_colour: bool = False, dirt=None, paths=None,
) -> PathImages:
    """Render every flare path's image of ``scene`` (unit tints, the scene's dirt map unless
    ``dirt`` is given) with ``samples`` samples, batch by batch (memory does not grow with
    ``samples``), weighted by ``pixel_weight`` and summed over ``block`` x ``block`` pixels.
    ``per_light_colour``: one image per light and colour channel, so light gains can be fitted.
    ``paths``: only these ghost paths (default: all of the lens's)."""
    plan, batches = _batches(scene, samples, seed, method, quality, paths)
    setup = plan.setup
    width, height = plan.scene.camera.resolution
    if height % block or width % block:
        raise ValueError(f"block must divide the resolution {width} x {height}, got {block}")
    weight = jnp.ones((height, width), jnp.float32) if pixel_weight is None else jnp.asarray(pixel_weight, jnp.float32)
    flare_paths, slot = _flare_slots(np.array([p is not None for p in plan.paths]))
    num_lights = int(setup.lights.kind.shape[0])
    gains = jnp.asarray(_unit_gains(num_lights, per_light_colour), jnp.float32)
    dirt = setup.effects.dirt if dirt is None else jnp.asarray(dirt, jnp.float32)

    def accumulate(buffer, batch, splat_weight, splat_block):
        for records in batch:
            buffer = _splat_unit_images(records, setup, slot, gains, dirt, buffer, splat_weight, splat_block)
        return buffer

    num_images = len(flare_paths) * gains.shape[0]
    keep_full = num_images * height * width * 3 * 4 <= FULL_IMAGE_BYTES
    if keep_full:  # splat at full resolution, then weight and sum blocks: the full images give the final render
        splat_weight, splat_block = jnp.ones((height, width), jnp.float32), 1
    else:
        splat_weight, splat_block = weight, block
    buffer = jnp.zeros((num_images, height // splat_block, width // splat_block, 3), jnp.float32)
    for batch in batches():
        buffer = accumulate(buffer, batch, splat_weight, splat_block)
    scale = _to_radiance(plan)
    full = None
    if keep_full:
        full = np.asarray(buffer).reshape(len(flare_paths), gains.shape[0], height, width, 3) * np.float32(scale)
        images = _weighted_blocks(full, weight, block)
    else:
        images = np.asarray(buffer, np.float64).reshape(len(flare_paths), gains.shape[0], height // block, width // block, 3) * scale
    return PathImages(
        images=jnp.asarray(images), full_images=None if full is None else jnp.asarray(full), path_interfaces=jnp.asarray(_path_interfaces(plan)[flare_paths]), block=block,
        resolution=(width, height), num_interfaces=plan.lens.num_interfaces, num_lights=num_lights, samples=samples, seed=seed,
        method=method, quality=quality, paths=None if paths is None else tuple(tuple(p) for p in paths),
    )


def fixed_path_images(samples: FixedSamples, *, pixel_weight: np.ndarray | None = None, block: int = 1, per_light_colour: bool = False) -> PathImages | None:
    """The per-path images of fixed samples (unit tints, the scene's dirt map), with the
    full-resolution images kept: :func:`path_image_model` of them equals :func:`render_image` of
    the samples for any tints and light gains (both are linear in them), so a fit of coatings and
    lights that is given samples solves on the images instead, and each step's Jacobian is a
    contraction of a small stack instead of a pass over every sample per parameter. None when the
    full-resolution stack would exceed :data:`FULL_IMAGE_BYTES`."""
    width, height = samples.resolution
    if height % block or width % block:
        raise ValueError(f"block must divide the resolution {width} x {height}, got {block}")
    setup, records = samples.setup, samples.records
    flare_paths, slot = _flare_slots(np.asarray(samples.flare))
    num_lights = int(setup.lights.kind.shape[0])
    num_bases = 3 * num_lights if per_light_colour else 1
    if len(flare_paths) * num_bases * height * width * 3 * 4 > FULL_IMAGE_BYTES:
        return None
    gains = jnp.asarray(_unit_gains(num_lights, per_light_colour), jnp.float32)
    buffer = jnp.zeros((len(flare_paths) * num_bases, height, width, 3), jnp.float32)
    buffer = _splat_unit_images(records, setup, slot, gains, setup.effects.dirt, buffer)
    full = np.asarray(buffer).reshape(len(flare_paths), num_bases, height, width, 3) * np.float32(samples.to_radiance)
    weight = np.ones((height, width)) if pixel_weight is None else np.asarray(pixel_weight)
    return PathImages(
        images=jnp.asarray(_weighted_blocks(full, weight, block)), full_images=jnp.asarray(full),
        path_interfaces=samples.path_interfaces[flare_paths], block=block, resolution=(width, height), num_interfaces=samples.num_interfaces,
        num_lights=num_lights, samples=int(records.path.shape[0]), seed=0, method="fixed-samples", quality="", paths=None,
    )


def _flare_slots(is_flare: np.ndarray) -> tuple[np.ndarray, Array]:
    """The flare paths' indices and each path's slot among them (-1 for the core): the layer of
    its images in a per-path stack."""
    flare_paths = np.flatnonzero(is_flare)
    slot = np.full(len(is_flare), -1, np.int32)
    slot[flare_paths] = np.arange(len(flare_paths))
    return flare_paths, jnp.asarray(slot)


@eqx.filter_jit
def _splat_unit_images(records: SampleRecords, setup, slot, gains, dirt, buffer, pixel_weight=None, block: int = 1, dirt_shape=None):
    """Splat every flare sample with unit tints into its path's image, once per gain basis ``k``
    (layer ``slot K + k``), weighted by ``pixel_weight`` and summed over ``block`` x ``block``
    pixels. With ``dirt_shape`` (rows, columns), into per-path, per-dirt-cell images instead (layer
    ``(slot D + cell) K + k``), each sample weighted by its four bilinear dirt-map taps
    (:func:`dirt_cell_taps`; pass ``dirt=None``): the images of every one-hot dirt map at once."""
    keep = records.hit & (slot[records.path] >= 0)
    ones = jnp.ones_like(setup.path_tint)
    num_bases = gains.shape[0]
    if dirt_shape is None:
        num_cells, taps = 1, [(0, None)]
    else:
        num_cells, taps = dirt_shape[0] * dirt_shape[1], dirt_cell_taps(dirt_shape, records.front_xy_mm, setup.front.radius_mm)
    for k in range(num_bases):
        values = record_values(records, _gained_lights(setup.lights, gains[k]), setup.spectral, setup.path_fresnel, ones, dirt, setup.front.radius_mm)
        for cell, tap in taps:
            layer = (jnp.clip(slot[records.path], 0) * num_cells + cell) * num_bases + k
            weighted = values if tap is None else values * tap[:, None]
            buffer = splat(buffer, layer, records.column, records.row, weighted, keep, pixel_weight=pixel_weight, block=block)
    return buffer


def _weighted_blocks(full, pixel_weight, block: int) -> np.ndarray:
    num_paths, num_bases, height, width, _ = full.shape
    weighted = np.asarray(full, np.float64) * np.asarray(pixel_weight, np.float64)[:, :, None]
    return weighted.reshape(num_paths, num_bases, height // block, block, width // block, block, 3).sum(axis=(3, 5))


def reweighted(images: PathImages, pixel_weight, block: int) -> PathImages:
    """The path images weighted by another plate's ``pixel_weight`` and summed over ``block`` x
    ``block`` pixels (needs their full-resolution images)."""
    if images.full_images is None:
        raise ValueError("these path images keep no full-resolution images, so they cannot be weighted again")
    width, height = images.resolution
    if height % block or width % block:
        raise ValueError(f"block must divide the resolution {width} x {height}, got {block}")
    pooled = _weighted_blocks(np.asarray(images.full_images), pixel_weight, block)
    return dataclasses.replace(images, images=jnp.asarray(pooled), block=block)


def flare_render(
    scene, interface_tints, light_gain=None, *, samples: int = 2**22, seed: int = 0, method: str = "exact", quality: str = "preview", dirt=None,
    paths=None,
):
    """The flare image (every flare path) of ``scene`` with the given interface tints and light
    gains, from the same samples :func:`path_images` uses for this seed, batch by batch."""
    plan, batches = _batches(scene, samples, seed, method, quality, paths)
    setup = plan.setup
    width, height = plan.scene.camera.resolution
    tints = _path_tints(jnp.asarray(_path_interfaces(plan)), jnp.asarray(interface_tints, jnp.float32))
    lights = setup.lights if light_gain is None else _gained_lights(setup.lights, jnp.asarray(light_gain, jnp.float32))
    dirt = setup.effects.dirt if dirt is None else jnp.asarray(dirt, jnp.float32)

    @eqx.filter_jit
    def accumulate(buffer, batch):
        for records in batch:
            values = record_values(records, lights, setup.spectral, setup.path_fresnel, tints, dirt, setup.front.radius_mm)
            keep = records.hit & setup.path_is_flare[records.path]
            buffer = splat(buffer, jnp.zeros_like(records.path), records.column, records.row, values, keep)
        return buffer

    buffer = jnp.zeros((1, height, width, 3), jnp.float32)
    for batch in batches():
        buffer = accumulate(buffer, batch)
    return np.asarray(buffer[0], np.float64) * _to_radiance(plan)


def path_image_model(
    images: PathImages, interface_tints: Float[Array, "I 3"], light_gain: Float[Array, "NL 3"] | None = None, *, full: bool = False,
):
    """The weighted, block-summed flare image for the given interface tints and light gains (with
    ``full``: the unweighted full-resolution image, when the path images keep it)."""
    tints = _path_tints(images.path_interfaces, interface_tints)
    stack = images.full_images if full else images.images
    if stack.shape[1] == 1:
        per_path = stack[:, 0]
        if light_gain is not None:
            raise ValueError("these path images were made without per_light_colour: they cannot fit light gains")
    else:
        per_path = jnp.einsum("pkhwc,k->phwc", stack, light_gain.reshape(-1).astype(stack.dtype))
    return jnp.einsum("phwc,pc->hwc", per_path, tints.astype(per_path.dtype))


def _without_index(records: SampleRecords) -> SampleRecords:
    return dataclasses.replace(records, table_index=None)


def path_tints(samples: FixedSamples, interface_tints: Float[Array, "I 3"]) -> Float[Array, "P 3"]:
    """Each path's coating colour: the product of the tints of its two reflecting interfaces."""
    return _path_tints(samples.path_interfaces, interface_tints)


def _path_tints(path_interfaces, interface_tints):
    j, i = path_interfaces[:, 0], path_interfaces[:, 1]
    tint = interface_tints[jnp.clip(j, 0)] * interface_tints[jnp.clip(i, 0)]
    return jnp.where((j >= 0)[:, None], tint, 1.0)


def render_image(
    samples: FixedSamples,
    interface_tints: Float[Array, "I 3"],
    dirt: Float[Array, "H W C"] | None,
    light_gain: Float[Array, "NL 3"] | None = None,
) -> Float[Array, "H W 3"]:
    """The flare image (every flare together; the fit's samples have no core) for the given
    interface tints, dirt map (None: the scene's own, if it has one) and light gains (scaling each
    RGB light's colour per channel, a spectral light's brightness by their mean), in the
    renderer's pixel units."""
    setup = samples.setup
    records = samples.records
    tints = path_tints(samples, interface_tints.astype(records.flux_factor.dtype))
    lights = setup.lights if light_gain is None else _gained_lights(setup.lights, light_gain)
    dirt = setup.effects.dirt if dirt is None else dirt
    values = record_values(records, lights, setup.spectral, setup.path_fresnel, tints, dirt, setup.front.radius_mm)
    keep = records.hit & samples.flare[records.path]
    width, height = samples.resolution
    buffer = jnp.zeros((1, height, width, 3), values.dtype)
    image = splat(buffer, jnp.zeros_like(records.path), records.column, records.row, values, keep)[0]
    return image * samples.to_radiance.astype(values.dtype)
