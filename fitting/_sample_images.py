"""Per-path, per-dirt-cell images of fixed Monte Carlo samples: the forward model of a dirt fit
given samples, as :func:`fitting._grid_model.grid_dirt_images` is for the grid.

A sample's value is linear in the dirt map: the map is read bilinearly where the sample crosses the
front lens (:func:`jaxflare.rendering.effects.dirt_cell_taps`: four cells and weights). Splatting
each sample's clean value times a tap's weight into the image of that tap's cell, per flare path
and light-gain basis, gives a stack whose contraction with any tints, dirt map and gains is the
samples' own render (:func:`fitting._forward.render_image`), to float rounding. A solver step then
contracts that stack (three passes for a Jacobian) instead of re-splatting every sample once per
dirt cell.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ._forward import PATH_IMAGE_BYTES, FixedSamples, _flare_slots, _splat_unit_images, _unit_gains
from ._grid_model import DirtImages


def sample_dirt_images_bytes(samples: FixedSamples, dirt_shape, block: int, *, per_light_colour: bool) -> int:
    """Size (float64) of :func:`sample_dirt_images`' stack."""
    width, height = samples.resolution
    num_lights = int(samples.setup.lights.kind.shape[0])
    bases = 3 * num_lights if per_light_colour else 1
    paths = int(np.count_nonzero(np.asarray(samples.flare)))
    return 8 * paths * int(np.prod(dirt_shape)) * bases * (width // block) * (height // block) * 3


def sample_dirt_images(
    samples: FixedSamples, dirt_shape, pixel_weight: np.ndarray | None = None, block: int = 1, *, per_light_colour: bool = False,
) -> DirtImages | None:
    """The one-hot dirt-cell images of ``samples`` (unit tints), weighted by ``pixel_weight`` and
    summed over ``block`` x ``block`` pixels: ``(P, D, K, h, w, 3)`` for flare paths ``P``, dirt
    cells ``D`` (row-major over a ``dirt_shape`` map) and gain bases ``K``. None when the stack
    would exceed :data:`~fitting._forward.PATH_IMAGE_BYTES`."""
    width, height = samples.resolution
    if height % block or width % block:
        raise ValueError(f"block must divide the resolution {width} x {height}, got {block}")
    rows, columns = (int(v) for v in dirt_shape)
    if sample_dirt_images_bytes(samples, (rows, columns), block, per_light_colour=per_light_colour) > PATH_IMAGE_BYTES:
        return None
    flare_paths, slot = _flare_slots(np.asarray(samples.flare))
    num_lights = int(samples.setup.lights.kind.shape[0])
    gains = jnp.asarray(_unit_gains(num_lights, per_light_colour), jnp.float32)
    weight = jnp.ones((height, width), jnp.float32) if pixel_weight is None else jnp.asarray(pixel_weight, jnp.float32)
    num_cells, num_bases = rows * columns, int(gains.shape[0])
    buffer = jnp.zeros((len(flare_paths) * num_cells * num_bases, height // block, width // block, 3), jnp.float32)
    buffer = _splat_unit_images(samples.records, samples.setup, slot, gains, None, buffer, weight, block, (rows, columns))
    images = np.asarray(buffer, np.float64).reshape(len(flare_paths), num_cells, num_bases, height // block, width // block, 3)
    return DirtImages(
        images=jnp.asarray(images * float(samples.to_radiance)), dirt_shape=(rows, columns),
        path_interfaces=samples.path_interfaces[flare_paths], num_lights=num_lights,
    )
