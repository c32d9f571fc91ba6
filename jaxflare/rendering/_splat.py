"""Writing sample values into pixels: a bilinear splat (a tent filter one pixel wide)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array


def splat(buffer: Array, layer: Array, column: Array, row: Array, value: Array, hit: Array, *, pixel_weight: Array | None = None, block: int = 1) -> Array:
    """Add each sample's ``value`` (N, C) to the four pixels around its position (column, row; pixel
    centres at integer + 0.5) of layer ``layer`` (N,), where ``hit``. A sample near the border keeps
    its whole weight (what would fall off the image goes to the edge pixel).

    ``buffer`` is (Y, H, W, C); with ``block`` > 1 it is (Y, H / block, W / block, C) and each pixel
    adds into its block's sum, and ``pixel_weight`` (H, W) weights the pixels (a plate's mask and
    noise, for fitting). Linear in ``value``, so differentiable in it.
    """
    num_layers, height_b, width_b, channels = buffer.shape
    height, width = (height_b * block, width_b * block) if pixel_weight is None else pixel_weight.shape
    x = column - 0.5
    y = row - 0.5
    x0 = jnp.floor(x)
    y0 = jnp.floor(y)
    fx = x - x0
    fy = y - y0
    flat = buffer.reshape(-1, channels)
    outside = num_layers * height_b * width_b
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        xi = jnp.clip((x0 + dx).astype(jnp.int32), 0, width - 1)
        yi = jnp.clip((y0 + dy).astype(jnp.int32), 0, height - 1)
        if block == 1 and pixel_weight is None:
            index = jnp.where(hit, (layer * height + yi) * width + xi, outside)
            weighted = value * w[:, None]
        else:
            index = jnp.where(hit, (layer * height_b + yi // block) * width_b + xi // block, outside)
            weighted = value * (w if pixel_weight is None else w * pixel_weight[yi, xi])[:, None]
        flat = flat.at[index].add(weighted.astype(flat.dtype), mode="drop")
    return flat.reshape(buffer.shape)
