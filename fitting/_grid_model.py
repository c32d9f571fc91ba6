"""The grid estimator as a fit's forward model (:class:`jaxflare.rendering.GridFlareModel`).

The grid render is deterministic: its model of the flare has no Monte Carlo noise, so a
least-squares fit through it is unbiased and its loss is smooth. With the dirt map fixed the fit
needs only each path's image (:func:`grid_path_images`, as :class:`~._forward.PathImages`); a fit
of the dirt map re-splats the grid's fixed sub-samples for every dirt map the solver tries.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from jaxflare.rendering import GridFlareModel

from ._forward import FULL_IMAGE_BYTES, PathImages, _weighted_blocks


def grid_interfaces(flare: GridFlareModel) -> np.ndarray:
    """Reflecting interfaces (j, i) of each of the model's flare paths (P, 2)."""
    return np.asarray(flare.paths, np.int32).reshape(-1, 2)


_path_images = eqx.filter_jit(lambda flare, per_light_colour: flare.path_images(per_light_colour=per_light_colour))


def grid_path_images(flare: GridFlareModel, pixel_weight=None, block: int = 1, *, per_light_colour: bool = False) -> PathImages:
    """Each flare path's grid image (unit tints, the scene's dirt map), weighted by
    ``pixel_weight`` and summed over ``block`` x ``block`` pixels; the full-resolution images are
    kept when they fit in :data:`~._forward.FULL_IMAGE_BYTES` (float32)."""
    width, height = flare.resolution
    if height % block or width % block:
        raise ValueError(f"block must divide the resolution {width} x {height}, got {block}")
    full = np.asarray(_path_images(flare, per_light_colour), np.float32)  # (P, K, H, W, 3)
    weight = np.ones((height, width)) if pixel_weight is None else np.asarray(pixel_weight, np.float64)
    images = _weighted_blocks(full, weight, block)
    keep_full = full.nbytes <= FULL_IMAGE_BYTES
    return PathImages(
        images=jnp.asarray(images), full_images=jnp.asarray(full) if keep_full else None, path_interfaces=jnp.asarray(grid_interfaces(flare)),
        block=block, resolution=(width, height), num_interfaces=int(flare.setup.lens.num_interfaces), num_lights=flare.num_lights,
        samples=flare.subsamples, seed=0, method="grid", quality=flare.quality, paths=flare.paths,
    )
