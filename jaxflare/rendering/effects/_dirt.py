"""Front-lens dirt: the ``c_dirt`` factor of the paper's equation (2).

Pekkarinen & Balzer write a sample's lens factor as ``c_lens = c_dirt c_coating``. ``c_dirt`` is
the transmission of the front element at the point where the sample's ray enters the lens: a dust
speck, a smear or a fingerprint there dims (or tints) every flare path through that point. Since
each ghost images the front element's aperture differently, one dirt map gives each ghost its own,
correctly warped, pattern of specks.

The dirt map
------------
An image of shape ``(H, W, C)``, ``C`` = 1 (grey) or 3 (RGB tint), float values in ``[0, 1]``: a
*transmission*, 1 passes all light, 0 blocks it. It is laid over the front element's clear
aperture and covers the square ``[-R0, R0]^2`` of the lens frame, ``R0`` the front clear
semi-aperture in mm (``lens.semi_aperture_mm[0]``); anything outside the circle of radius ``R0`` is
stopped by the clear aperture anyway.

Orientation. The lens frame has x to the right of the picture, y up and z towards the sensor. The
map is seen from *behind* the camera, as the photographer sees the front element through the
camera (the way the picture itself is seen):

* image column increases with +x: column 0 is at ``x = -R0``, the last column at ``x = +R0``;
* image row increases with -y: row 0 (the top of the image) is at ``y = +R0``, the last row at
  ``y = -R0``.

Pixel ``(row i, column j)`` is centred at ``x = -R0 + 2 R0 (j + 0.5) / W``,
``y = R0 - 2 R0 (i + 0.5) / H``; between centres the map is interpolated bilinearly, and beyond the
outermost centres (the outer half pixel, and any point outside the square) it is clamped to the
border value. Non-square maps stretch to the square.

What the renderer multiplies
----------------------------
For each sample, :func:`dirt_transmission` at the sample's point on the front lens (its ``x, y``
in mm, lens frame) gives an RGB factor that multiplies the sample's radiance, together with the
coating tint of its path. The same factor applies to every path, the primary (the source's own
image) included. :func:`dirt_transmission` is differentiable with respect to the map, so a plate
fit can optimise the dirt map as a parameter.

Files
-----
:func:`load_dirt_map` reads PNG, JPEG and TIFF (8-bit values divided by 255, 16-bit ones by 65535;
an alpha channel is dropped, palette images are expanded to RGB) and OpenEXR (the default layer,
or the only one; RGB or Y; alpha dropped) with :func:`jaxflare.io.read_linear_image`. Floating-point images
(EXR, float TIFF) must already lie in ``[0, 1]``.
"""

from __future__ import annotations

import math
import os

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ...io import read_linear_image
from ._bilinear import bilinear, bilinear_taps

__all__ = ["DIRT_FORMATS", "dirt_cell_taps", "dirt_transmission", "load_dirt_map"]

DIRT_FORMATS = "PNG (.png), JPEG (.jpg, .jpeg), TIFF (.tif, .tiff) or OpenEXR (.exr)"
"""The dirt-map formats :func:`load_dirt_map` reads, for messages."""


def load_dirt_map(path: str | os.PathLike) -> np.ndarray:
    """Read a dirt map: an ``(H, W, C)`` float32 transmission in ``[0, 1]``, ``C`` = 1 or 3.

    See the module docstring for the formats, orientation and meaning. Raises
    ``FileNotFoundError`` for a missing file and ``ValueError`` for an unsupported or unreadable
    file, non-finite values, values outside ``[0, 1]`` or a map smaller than 2 x 2 pixels.
    """
    image = read_linear_image(path, what="dirt map", formats=DIRT_FORMATS)
    path, pixels = image.path, image.pixels
    if pixels.shape[-1] not in (1, 3):
        raise ValueError(f"dirt map {path!r} has {pixels.shape[-1]} channels; expected 1 (grey) or 3 (RGB)")
    height, width = pixels.shape[:2]
    if height < 2 or width < 2:
        raise ValueError(f"dirt map {path!r} is {width} x {height} pixels; it must be at least 2 x 2")
    if not np.all(np.isfinite(pixels)):
        count = int(np.size(pixels) - np.count_nonzero(np.isfinite(pixels)))
        raise ValueError(f"dirt map {path!r} has {count} non-finite (NaN or infinite) values")
    low, high = float(pixels.min()), float(pixels.max())
    if low < 0.0 or high > 1.0:
        raise ValueError(
            f"dirt map {path!r}: values span [{low:.6g}, {high:.6g}], outside [0, 1]; dirt is a transmission "
            "in [0, 1] (1 passes all light, 0 blocks it): rescale the image"
        )
    return np.ascontiguousarray(pixels, dtype=np.float32)


def _check_map(dirt_map: Array) -> Array:
    dirt_map = jnp.asarray(dirt_map)
    if dirt_map.ndim == 2:
        dirt_map = dirt_map[..., None]
    if dirt_map.ndim != 3 or dirt_map.shape[-1] not in (1, 3):
        raise ValueError(f"a dirt map must have shape (H, W, 1) or (H, W, 3), got {dirt_map.shape}")
    _check_size(dirt_map.shape)
    return dirt_map


def _check_size(shape) -> None:
    if len(shape) < 2 or shape[0] < 2 or shape[1] < 2:
        raise ValueError(f"a dirt map must be at least 2 x 2 pixels, got shape {tuple(shape)}")


def _bilinear_clamped(image: Array, column: Array, row: Array) -> Array:
    return bilinear(image, column, row, extend_edges=False)


def dirt_transmission(
    dirt_map: Float[Array, "H W C"], xy_mm: Float[Array, "N 2"], front_radius_mm: float | Float[Array, ""]
) -> Float[Array, "N 3"]:
    """The dirt map's RGB transmission at front-lens points ``xy_mm`` (lens frame, mm).

    ``dirt_map`` is ``(H, W, 1)`` or ``(H, W, 3)`` (``(H, W)`` is taken as one channel), laid over
    ``[-front_radius_mm, front_radius_mm]^2`` as in the module docstring: column with +x, row 0 at
    +y. Bilinear between pixel centres, clamped at the borders (points outside the square take the
    border value); one channel is broadcast to RGB. Linear, hence differentiable, in ``dirt_map``
    (the gradient of a point's value is its four bilinear weights); jit and vmap friendly.
    ``xy_mm`` may have any leading shape ``(..., 2)``; the result is ``(..., 3)``.
    """
    dirt_map = _check_map(dirt_map)
    xy_mm = jnp.asarray(xy_mm)
    if xy_mm.shape[-1:] != (2,):
        raise ValueError(f"xy_mm must have shape (..., 2), got {xy_mm.shape}")
    if isinstance(front_radius_mm, (int, float)) and not (math.isfinite(front_radius_mm) and front_radius_mm > 0):
        raise ValueError(f"front_radius_mm must be a finite positive number, got {front_radius_mm!r}")
    column, row = _map_position(dirt_map.shape[:2], xy_mm, front_radius_mm)
    value = _bilinear_clamped(dirt_map, column, row)
    return jnp.broadcast_to(value, value.shape[:-1] + (3,))


def _map_position(shape: tuple[int, int], xy_mm: Array, front_radius_mm) -> tuple[Array, Array]:
    """Continuous (column, row) in a dirt map of ``shape`` (rows, columns) of front-lens points."""
    height, width = shape
    radius = jnp.asarray(front_radius_mm, dtype=jnp.result_type(xy_mm.dtype, float))
    return (xy_mm[..., 0] + radius) / (2 * radius) * width, (radius - xy_mm[..., 1]) / (2 * radius) * height


def dirt_cell_taps(shape: tuple[int, int], xy_mm: Array, front_radius_mm) -> tuple[tuple[Array, Array], ...]:
    """The dirt-map cells (row-major indices into a map of ``shape`` (rows, columns)) and weights
    through which :func:`dirt_transmission` reads each front-lens point: four ``(cell, weight)``
    pairs shaped like ``xy_mm[..., 0]``. The transmission of a one-channel map ``d`` is
    ``sum_k d.flat[cell_k] * weight_k``, so a point's light splatted with ``weight_k`` into cell
    ``cell_k``'s image builds every one-hot map's image in one pass."""
    _check_size(shape)
    column, row = _map_position(shape, jnp.asarray(xy_mm), front_radius_mm)
    return bilinear_taps(*shape, column, row, extend_edges=False)
