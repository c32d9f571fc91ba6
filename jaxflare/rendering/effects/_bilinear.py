"""Bilinear lookup of an image at continuous pixel positions (shared by dirt maps and ST-maps)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array


def bilinear(image: Array, column: Array, row: Array, *, extend_edges: bool = False) -> Array:
    """``image`` (H, W, C) at continuous pixel coordinates (pixel centres at integer + 0.5).

    Positions are clamped to the outermost pixel centres (``extend_edges=False``: the border value
    is held) or to the image ``[0, W] x [0, H]`` with the border cell's bilinear function extended
    over the outer half pixel (``extend_edges=True``: a linear image, the identity map included,
    stays exact up to the edges). Returns (..., C); linear in ``image``, so differentiable in it.
    """
    height, width = image.shape[:2]
    if extend_edges:
        u = jnp.clip(column, 0.0, width) - 0.5
        v = jnp.clip(row, 0.0, height) - 0.5
    else:
        u = jnp.clip(column - 0.5, 0.0, width - 1.0)
        v = jnp.clip(row - 0.5, 0.0, height - 1.0)
    i0 = jnp.clip(jnp.floor(u), 0, width - 2).astype(jnp.int32)
    j0 = jnp.clip(jnp.floor(v), 0, height - 2).astype(jnp.int32)
    fu = (u - i0)[..., None]
    fv = (v - j0)[..., None]
    top = image[j0, i0] * (1 - fu) + image[j0, i0 + 1] * fu
    bottom = image[j0 + 1, i0] * (1 - fu) + image[j0 + 1, i0 + 1] * fu
    return top * (1 - fv) + bottom * fv
