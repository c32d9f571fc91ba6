"""Bilinear lookup of an image at continuous pixel positions (shared by dirt maps and ST-maps)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array


def bilinear_taps(height: int, width: int, column: Array, row: Array, *, extend_edges: bool = False) -> tuple[tuple[Array, Array], ...]:
    """The four pixels (flat row-major indices into an ``height`` x ``width`` image) and bilinear
    weights of a lookup at continuous pixel coordinates (pixel centres at integer + 0.5), clamped as
    :func:`bilinear` says: ``bilinear(image, ...) == sum_k image.reshape(-1, C)[index_k] *
    weight_k[..., None]``. Four ``(index, weight)`` pairs, each shaped like ``column``; an image one
    pixel wide or high reads that pixel with the whole weight."""
    if extend_edges:
        u = jnp.clip(column, 0.0, width) - 0.5
        v = jnp.clip(row, 0.0, height) - 0.5
    else:
        u = jnp.clip(column - 0.5, 0.0, width - 1.0)
        v = jnp.clip(row - 0.5, 0.0, height - 1.0)
    i0 = jnp.clip(jnp.floor(u), 0, max(width - 2, 0)).astype(jnp.int32)
    j0 = jnp.clip(jnp.floor(v), 0, max(height - 2, 0)).astype(jnp.int32)
    i1, j1 = jnp.minimum(i0 + 1, width - 1), jnp.minimum(j0 + 1, height - 1)
    fu, fv = u - i0, v - j0
    return (
        (j0 * width + i0, (1 - fu) * (1 - fv)),
        (j0 * width + i1, fu * (1 - fv)),
        (j1 * width + i0, (1 - fu) * fv),
        (j1 * width + i1, fu * fv),
    )


def bilinear(image: Array, column: Array, row: Array, *, extend_edges: bool = False) -> Array:
    """``image`` (H, W, C) at continuous pixel coordinates (pixel centres at integer + 0.5).

    Positions are clamped to the outermost pixel centres (``extend_edges=False``: the border value
    is held) or to the image ``[0, W] x [0, H]`` with the border cell's bilinear function extended
    over the outer half pixel (``extend_edges=True``: a linear image, the identity map included,
    stays exact up to the edges). Returns (..., C); linear in ``image``, so differentiable in it.
    The pixels and weights are :func:`bilinear_taps`'.
    """
    height, width, channels = image.shape
    flat = image.reshape(-1, channels)
    taps = bilinear_taps(height, width, column, row, extend_edges=extend_edges)
    return sum(flat[index] * weight[..., None] for index, weight in taps)
