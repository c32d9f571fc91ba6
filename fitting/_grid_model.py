"""The grid estimator as a fit's forward model (:class:`jaxflare.rendering.GridFlareModel`).

The grid render is deterministic: its model of the flare has no Monte Carlo noise, so a
least-squares fit through it is unbiased and its loss is smooth. With the dirt map fixed the fit
needs only each path's image (:func:`grid_path_images`, as :class:`~._forward.PathImages`), a
thin-film fit each path's image per spectral knot (:func:`grid_film_images`) and a dirt fit each
path's image per cell of a one-hot dirt map (:func:`grid_dirt_images`): the flare is linear in
each. Where a stack does not fit in memory the fit re-splats the grid's fixed sub-samples for
every parameter the solver tries.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxflare.rendering import GridFlareModel, knot_hats

from ._forward import FULL_IMAGE_BYTES, PathImages, _path_tints, _weighted_blocks


def grid_interfaces(flare: GridFlareModel) -> np.ndarray:
    """Reflecting interfaces (j, i) of each of the model's flare paths (P, 2)."""
    return np.asarray(flare.paths, np.int32).reshape(-1, 2)


_path_images = eqx.filter_jit(lambda flare, per_light_colour: flare.path_images(per_light_colour=per_light_colour))


def _check_block(flare: GridFlareModel, block: int) -> None:
    width, height = flare.resolution
    if height % block or width % block:
        raise ValueError(f"block must divide the resolution {width} x {height}, got {block}")


def stack_bytes(num_paths: int, num_lights: int, count: int, resolution: tuple[int, int], block: int, per_light_colour: bool) -> int:
    """Size (float64) of a block-summed stack of ``count`` images per path and gain basis, at
    ``resolution`` (width, height)."""
    width, height = resolution
    bases = 3 * num_lights if per_light_colour else 1
    return 8 * num_paths * count * bases * (width // block) * (height // block) * 3


def _stack_bytes(flare: GridFlareModel, count: int, block: int, per_light_colour: bool) -> int:
    """:func:`stack_bytes` of ``flare``'s paths, lights and resolution."""
    return stack_bytes(flare.num_paths, flare.num_lights, count, flare.resolution, block, per_light_colour)


def grid_path_images(flare: GridFlareModel, pixel_weight=None, block: int = 1, *, per_light_colour: bool = False) -> PathImages:
    """Each flare path's grid image (unit tints, the scene's dirt map), weighted by
    ``pixel_weight`` and summed over ``block`` x ``block`` pixels; the full-resolution images are
    kept when they fit in :data:`~._forward.FULL_IMAGE_BYTES` (float32)."""
    return grid_path_images_and_full(flare, pixel_weight, block, per_light_colour=per_light_colour)[0]


def grid_path_images_and_full(
    flare: GridFlareModel, pixel_weight=None, block: int = 1, *, per_light_colour: bool = False
) -> tuple[PathImages, np.ndarray]:
    """:func:`grid_path_images` and the full-resolution images it pooled, (P, K, H, W, 3) float32
    on the host (a fit's final render is their tinted sum, however large: re-splatting a 2K
    production grid took 3 minutes)."""
    _check_block(flare, block)
    width, height = flare.resolution
    full = np.asarray(_path_images(flare, per_light_colour), np.float32)  # (P, K, H, W, 3)
    weight = np.ones((height, width)) if pixel_weight is None else np.asarray(pixel_weight, np.float64)
    images = _weighted_blocks(full, weight, block)
    keep_full = full.nbytes <= FULL_IMAGE_BYTES
    return PathImages(
        images=jnp.asarray(images), full_images=jnp.asarray(full) if keep_full else None, path_interfaces=jnp.asarray(grid_interfaces(flare)),
        block=block, resolution=(width, height), num_interfaces=int(flare.setup.lens.num_interfaces), num_lights=flare.num_lights,
        samples=flare.subsamples, seed=0, method="grid", quality=flare.quality, paths=flare.paths,
    ), full


class FilmImages(eqx.Module):
    """Each flare path's grid image per spectral knot (:meth:`GridFlareModel.path_knot_images`),
    weighted and block-summed: the forward model of a thin-film fit with the dirt map fixed. The
    flare is linear in the paths' Fresnel factors, so it is a weighted sum of these images."""

    images: jax.Array
    """(P, B, K, h, w, 3): path, knot, light gain basis (as :class:`~._forward.PathImages`)."""
    knots: tuple[int, ...] = eqx.field(static=True)
    """The knots' indices into the spectral grid (B,)."""
    path_interfaces: jax.Array
    num_lights: int = eqx.field(static=True)


def film_images_bytes(flare: GridFlareModel, block: int, *, per_light_colour: bool) -> int:
    """Size (float64) of :func:`grid_film_images`' stack."""
    knots, _ = knot_hats(np.asarray(flare.setup.spectral.wavelength_nm))
    return _stack_bytes(flare, knots.size, block, per_light_colour)


FILM_PASS_BYTES = 2**28
"""Largest packed-image buffer (float32) of one pass of :func:`grid_film_images`: as many
spectral knots (times light-gain bases) as fit are colour planes of one pass over the sub-samples."""


def grid_film_images(flare: GridFlareModel, pixel_weight=None, block: int = 1, *, per_light_colour: bool = False) -> FilmImages:
    """The knot images of ``flare`` (:meth:`GridFlareModel.path_knot_images`: the knots and gain
    bases as colour planes, as many per pass over the sub-samples as fit in
    :data:`FILM_PASS_BYTES`) weighted by ``pixel_weight`` and summed over ``block`` x ``block`` as
    they are made."""
    _check_block(flare, block)
    knots, _ = flare.knot_fresnels()
    width, height = flare.resolution
    weight = np.ones((height, width)) if pixel_weight is None else np.asarray(pixel_weight, np.float64)
    bases = 3 * flare.num_lights if per_light_colour else 1
    group = int(np.clip(FILM_PASS_BYTES // (bases * (flare.num_paths * flare.layer_bytes + flare.atlas_bytes)), 1, knots.size))
    stacks = []
    for first in range(0, knots.size, group):
        images, _ = flare.path_knot_images(per_light_colour=per_light_colour, knot_slice=slice(first, first + group))  # (P, b, K, H, W, 3)
        images = np.asarray(images, np.float32)
        stacks.append(_weighted_blocks(images.reshape((-1,) + images.shape[2:]), weight, block).reshape(images.shape[:2] + (bases, height // block, width // block, 3)))
    return FilmImages(
        images=jnp.asarray(np.concatenate(stacks, axis=1)), knots=tuple(int(k) for k in knots),
        path_interfaces=jnp.asarray(grid_interfaces(flare)), num_lights=flare.num_lights,
    )


def film_image_model(images: FilmImages, path_fresnel, interface_tints, light_gain=None):
    """The weighted, block-summed flare for paths' Fresnel factors ``path_fresnel`` (P, L on the
    spectral grid), interface tints and light gains."""
    tints = _path_tints(images.path_interfaces, interface_tints)  # (P, 3)
    weights = jnp.asarray(path_fresnel)[:, np.asarray(images.knots)].astype(images.images.dtype)  # (P, B)
    gains = jnp.ones((1,), images.images.dtype) if images.images.shape[2] == 1 else jnp.asarray(light_gain).reshape(-1).astype(images.images.dtype)
    return jnp.einsum("pc,pb,k,pbkhwc->hwc", tints, weights, gains, images.images)


class DirtImages(eqx.Module):
    """Each flare path's grid image for each cell of a one-hot dirt map, weighted and
    block-summed: the forward model of a dirt fit where it fits in memory. The flare is linear in
    the dirt map (each sub-sample reads it bilinearly where it crosses the front lens) and in the
    tints and gains, so it is a weighted sum of these images, exactly."""

    images: jax.Array
    """(P, D, K, h, w, 3): path, dirt cell (row-major over the map), light gain basis."""
    dirt_shape: tuple[int, int] = eqx.field(static=True)
    path_interfaces: jax.Array
    num_lights: int = eqx.field(static=True)


def dirt_images_bytes(flare: GridFlareModel, dirt_shape, block: int, *, per_light_colour: bool) -> int:
    """Size (float64) of :func:`grid_dirt_images`' stack."""
    return _stack_bytes(flare, int(np.prod(dirt_shape)), block, per_light_colour)


DIRT_RUN_BYTES = 2**30
"""Largest packed-image buffer (float32) of one pass of :func:`grid_dirt_images`: as many dirt
cells as fit are splatted together (every pass reads all the grid's sub-samples). Measured on the
plate-fit benchmark's double Gauss (128 x 72, 45 paths, 13 M sub-samples, a 32 x 32 map): runs of
35 cells (2^28 bytes) took 4.0 s a pass, runs of 143 (2^30) 7.8-8.9 s, i.e. 0.11 and 0.06 s a
cell; one splat per one-hot map took 1.37 s a cell."""


@eqx.filter_jit
def _cell_blocks(flare: GridFlareModel, dirt_shape, first, count: int, per_light_colour: bool, weight, block: int):
    """The run's dirt-cell images (per light-gain basis with ``per_light_colour``, in the same
    pass), weighted per pixel and summed over ``block`` x ``block`` pixels in the compiled
    program (the full-resolution images never leave it): (P, count, K, h, w, 3)."""
    images = flare.per_path_cell_images(dirt_shape, first, count, per_light_colour=True) if per_light_colour else (
        flare.per_path_cell_images(dirt_shape, first, count)[:, :, None]
    )
    images = images * weight[:, :, None]
    paths, cells, bases, height, width, _ = images.shape
    return images.reshape(paths, cells, bases, height // block, block, width // block, block, 3).sum(axis=(4, 6))


def grid_dirt_images(flare: GridFlareModel, dirt_shape, pixel_weight=None, block: int = 1, *, per_light_colour: bool = False) -> DirtImages:
    """The one-hot dirt-cell images of ``flare`` (:meth:`GridFlareModel.per_path_cell_images`:
    one pass over the sub-samples per run of cells that fits in :data:`DIRT_RUN_BYTES`, every
    light-gain basis a colour plane of the pass), weighted by ``pixel_weight`` and summed over ``block`` x ``block``
    pixels as they are made."""
    _check_block(flare, block)
    rows, columns = (int(v) for v in dirt_shape)
    num_cells = rows * columns
    width, height = flare.resolution
    bases = 3 * flare.num_lights if per_light_colour else 1  # colour planes of each pass
    run = int(np.clip(DIRT_RUN_BYTES // (bases * (flare.num_paths * flare.layer_bytes + flare.atlas_bytes)), 1, num_cells))
    weight = jnp.ones((height, width), jnp.float32) if pixel_weight is None else jnp.asarray(pixel_weight, jnp.float32)
    # every run as long as the first (the last one padded with empty cells): one compiled splat
    runs = [np.asarray(_cell_blocks(flare, (rows, columns), jnp.asarray(first, jnp.int32), run, per_light_colour, weight, block))
            for first in range(0, num_cells, run)]
    images = np.concatenate(runs, axis=1)[:, :num_cells].astype(np.float64)  # (P, D, K, h, w, 3)
    return DirtImages(
        images=jnp.asarray(images), dirt_shape=(rows, columns), path_interfaces=jnp.asarray(grid_interfaces(flare)),
        num_lights=flare.num_lights,
    )


def dirt_image_model(images: DirtImages, interface_tints, dirt, light_gain=None):
    """The weighted, block-summed flare for interface tints, a dirt map (rows, columns, 1) and light gains."""
    tints = _path_tints(images.path_interfaces, interface_tints)
    cells = jnp.asarray(dirt).reshape(-1).astype(images.images.dtype)
    gains = jnp.ones((1,), images.images.dtype) if images.images.shape[2] == 1 else jnp.asarray(light_gain).reshape(-1).astype(images.images.dtype)
    return _trilinear(tints.astype(images.images.dtype), cells, gains, images.images)


@jax.custom_jvp
def _trilinear(tints, cells, gains, stack):
    """``sum_pdk tints_pc cells_d gains_k stack_pdkhwc``: linear in each of the three vectors."""
    return jnp.einsum("pc,d,k,pdkhwc->hwc", tints, cells, gains, stack)


@_trilinear.defjvp
def _trilinear_jvp(primals, tangents):
    """The derivative as three contractions of the stack with the primal vectors (made once, also
    when the tangents are batched: a Jacobian costs three passes over the stack, not one per
    parameter as the einsum's own rule under ``vmap`` would). The stack is a constant: its
    tangent is ignored."""
    tints, cells, gains, stack = primals
    d_tints, d_cells, d_gains, _ = tangents
    by_path = jnp.einsum("d,k,pdkhwc->phwc", cells, gains, stack)
    by_cell = jnp.einsum("pc,k,pdkhwc->dhwc", tints, gains, stack)
    by_gain = jnp.einsum("pc,d,pdkhwc->khwc", tints, cells, stack)
    value = jnp.einsum("pc,phwc->hwc", tints, by_path)
    tangent = jnp.einsum("pc,phwc->hwc", d_tints, by_path) + jnp.einsum("d,dhwc->hwc", d_cells, by_cell) + jnp.einsum("k,khwc->hwc", d_gains, by_gain)
    return value, tangent
