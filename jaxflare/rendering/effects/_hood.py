"""A lens hood or matte box as an occluder: which light-to-lens rays pass its opening (pure JAX,
lens frame, mm). The hood itself is :class:`jaxflare.Hood` (a scene object)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

from ...scenes import Hood


def hood_crossing(hood: Hood, origins_mm: Array, directions: Array) -> Array:
    """Where each ray (lens frame: a point on it, mm, and its direction, (..., 3)) crosses the
    hood's plane ``z = -distance_mm``: (..., 2) x, y in mm (NaN-free: parallel rays give inf)."""
    origins_mm = jnp.asarray(origins_mm)
    directions = jnp.asarray(directions)
    dz = directions[..., 2]
    safe = jnp.where(dz > 0, dz, 1.0)
    t = (-hood.distance_mm - origins_mm[..., 2]) / safe
    xy = origins_mm[..., :2] + t[..., None] * directions[..., :2]
    return jnp.where((dz > 0)[..., None], xy, jnp.inf)


def hood_visible(hood: Hood, origins_mm: Array, directions: Array) -> Array:
    """True where a ray travelling towards +z (from the light to the lens) passes through the hood's
    opening (boundary included). Lens frame: ``origins_mm`` a point on each ray (e.g. on the
    entrance plane), ``directions`` its direction (need not be unit), shapes (..., 3). Rays with
    ``directions[..., 2] <= 0`` never reach the lens from the front and are reported blocked."""
    xy = hood_crossing(hood, origins_mm, directions)
    travelling = jnp.asarray(directions)[..., 2] > 0
    return hood_inside(hood, xy) & travelling


def hood_inside(hood: Hood, xy: Array) -> Array:
    """True where points of the hood's plane (lens frame x, y in mm, (..., 2)) lie in its opening
    (boundary included). A 0/1 test: no gradient flows through it."""
    xy = jax.lax.stop_gradient(jnp.asarray(xy))
    if hood.shape == "circular":
        return jnp.sum(xy**2, axis=-1) <= hood.radius_mm**2
    return (jnp.abs(xy[..., 0]) <= hood.half_width_mm) & (jnp.abs(xy[..., 1]) <= hood.half_height_mm)
