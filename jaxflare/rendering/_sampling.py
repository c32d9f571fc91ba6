"""Sampling light-to-front-lens connections (Pekkarinen & Balzer 2019, section 3: "connecting a
random sample on a light source with a random sample on the front lens").

The front-lens point is uniform on a disc of the entrance plane (just in front of the lens) that
covers every ray able to reach the front clear aperture from the chosen light point (or in the
chosen direction): its centre and radius follow the light, so the sampled disc stays tight for
lights far off the axis. The flux factor of a sample is the radiometric coupling of the two points
over their sampling pdf: ``L A_light A_disc cos cos / r^2`` for area lights, ``I A_disc cos / r^2``
for point lights, ``L Omega A_disc cos`` for a directional disc, ``E A_disc cos`` for a beam.
Geometry is in the lens frame in mm (x right, y up, z along the axis towards the sensor; the front
vertex at z = 0).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..optics import entrance_plane_z_mm, front_rim_sag_mm
from ..scenes import LightKind
from ._lights import LightArrays


class FrontDisc(eqx.Module):
    """Where front-lens points are sampled: the front clear semi-aperture, the entrance plane and
    the axial range the front surface spans within its aperture (vertex to rim sag)."""

    radius_mm: Float[Array, ""]
    entrance_z_mm: float = eqx.field(static=True)
    z_range_mm: tuple[float, float] = eqx.field(static=True)


class Connections(eqx.Module):
    """Sampled connections: rays in the lens frame with their wavelength, light and flux factor."""

    origins: Float[Array, "N 3"]
    """Points on the entrance plane (mm)."""
    directions: Float[Array, "N 3"]
    wavelength_nm: Float[Array, " N"]
    light: Int[Array, " N"]
    flux: Float[Array, " N"]
    """The radiometric coupling of the light point and the front-lens point over their sampling
    pdf, times the light's emission (see the module docstring)."""
    light_point_mm: Float[Array, "N 3"]
    """The sampled point on the light (lens frame, mm); the light's centre for directional lights."""


def front_disc(lens) -> FrontDisc:
    """Where a lens's front-lens points are sampled: its front clear semi-aperture on the entrance
    plane, and the axial range from the front vertex to the rim's sag."""
    z_rim = front_rim_sag_mm(lens)
    return FrontDisc(jnp.asarray(float(lens.semi_aperture_mm[0])), entrance_plane_z_mm(lens), (min(0.0, z_rim), max(0.0, z_rim)))


def sample_connections(
    lights: LightArrays, front: FrontDisc, spectral, key: Array, count: int, wavelength_strata: int,
    light: Array | None = None, front_unit: Array | None = None, light_unit: Array | None = None,
) -> Connections:
    """``count`` connections between a point on a light and a point on the front lens.

    ``light`` (N,) fixes each sample's light (else it is drawn by ``selection_probability`` and the
    flux divided by that probability); ``front_unit`` (N, 2) fixes the front-lens point on the unit
    disc (else uniform), which :class:`FrontDisc` maps onto the entrance plane. ``light_unit``
    (N, 2) fixes the point on the light the same way: a point of the unit disc, mapped onto a disc
    or sphere light's disc by area, or onto a directional light's cone by solid angle (else
    uniform). The flux is the radiometric factor over the pdf of the light point and of a uniform
    front point (the deterministic grid estimator weighs fixed points by their share of the area).
    """
    dtype = lights.axis.dtype
    k_light, k_light_point, k_front, k_wave = jax.random.split(key, 4)
    chosen = light is None
    if chosen:
        light = jax.random.choice(k_light, lights.kind.shape[0], (count,), p=lights.selection_probability)
    kind = lights.kind[light]
    if light_unit is None:
        u = jax.random.uniform(k_light_point, (count, 2), dtype)
    else:  # a point of the unit disc: u0 = rho^2 (area, or solid angle in a cone), u1 = angle / 2 pi
        light_unit = jnp.broadcast_to(jnp.asarray(light_unit, dtype), (count, 2))
        angle = jnp.arctan2(light_unit[:, 1], light_unit[:, 0])
        u = jnp.stack([jnp.clip(jnp.sum(light_unit**2, axis=-1), 0.0, 1.0), jnp.where(angle < 0, angle + 2 * jnp.pi, angle) / (2 * jnp.pi)], axis=-1)

    # a point on the light (finite lights) or a direction in its cone (directional lights)
    normal = lights.normal[light]
    helper = jnp.where(jnp.abs(normal[:, :1]) < 0.9, jnp.array([1.0, 0.0, 0.0], dtype), jnp.array([0.0, 1.0, 0.0], dtype))
    e1 = jnp.cross(normal, helper)
    e1 = e1 / jnp.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = jnp.cross(normal, e1)
    phi = 2 * jnp.pi * u[:, 1]
    radius = lights.radius_mm[light]
    r = radius * jnp.sqrt(u[:, 0])
    on_disc = (r * jnp.cos(phi))[:, None] * e1 + (r * jnp.sin(phi))[:, None] * e2
    light_point = lights.centre_mm[light] + jnp.where((kind == LightKind.SPHERE) | (kind == LightKind.DISK), 1.0, 0.0)[:, None] * on_disc
    cone_cos = lights.cone_cos[light]
    cos_t = 1.0 - u[:, 0] * (1.0 - cone_cos)
    sin_t = jnp.sqrt(jnp.clip(1.0 - cos_t**2, 0.0, 1.0))
    cone_direction = cos_t[:, None] * normal + (sin_t * jnp.cos(phi))[:, None] * e1 + (sin_t * jnp.sin(phi))[:, None] * e2

    # a point on the front lens: uniform on a disc of the entrance plane covering every ray that can
    # reach the front clear aperture from this light point (or in this direction)
    z_e = front.entrance_z_mm
    z_low, z_high = front.z_range_mm
    z_mid = 0.5 * (z_low + z_high)
    finite = kind != LightKind.DIRECTIONAL
    towards_lens = jnp.array([0.0, 0.0, z_mid], dtype) - light_point
    distance = jnp.linalg.norm(towards_lens, axis=-1)
    central = jnp.where(finite[:, None], towards_lens / distance[:, None], cone_direction)
    tilt = central[:, :2] / central[:, 2:3]
    tilt_size = jnp.linalg.norm(tilt, axis=-1)
    front_r = front.radius_mm
    parallax = jnp.where(finite, (z_high - z_e + 2 * front_r) * 2 * front_r / distance * (1 + tilt_size**2), 0.0)
    disc_radius = front_r * 1.02 + 0.5 * (z_high - z_low) * tilt_size + parallax
    disc_centre = -(z_mid - z_e) * tilt
    if front_unit is None:
        v = jax.random.uniform(k_front, (count, 2), dtype)
        rho = jnp.sqrt(v[:, 0])
        angle = 2 * jnp.pi * v[:, 1]
        front_unit = jnp.stack([rho * jnp.cos(angle), rho * jnp.sin(angle)], axis=-1)
    front_xy = disc_centre + disc_radius[:, None] * front_unit
    origins = jnp.concatenate([front_xy, jnp.full((count, 1), z_e, dtype)], axis=-1)
    offset = origins - light_point
    distance2 = jnp.sum(offset**2, axis=-1)
    finite_direction = offset / jnp.sqrt(distance2)[:, None]
    directions = jnp.where(finite[:, None], finite_direction, cone_direction)

    disc_area = jnp.pi * disc_radius**2
    cos_front = jnp.clip(directions[:, 2], 0.0, 1.0)
    cos_light = jnp.clip(jnp.sum(normal * directions, axis=-1), 0.0, 1.0)
    light_area = jnp.pi * radius**2
    solid_angle = 2 * jnp.pi * (1.0 - cone_cos)
    coupling = jnp.select(
        [kind == LightKind.POINT, (kind == LightKind.SPHERE) | (kind == LightKind.DISK), cone_cos < 1.0],
        [disc_area * cos_front / distance2, light_area * disc_area * cos_light * cos_front / distance2, solid_angle * disc_area * cos_front],
        disc_area * cos_front,
    )
    flux = coupling * lights.emission[light]
    if chosen:
        flux = flux / lights.selection_probability[light]

    # stratified wavelengths: each stratum of the band gets the same number of samples per batch
    strata = wavelength_strata
    grid = spectral.wavelength_nm
    low, high = grid[0], grid[-1]
    stratum = jnp.arange(count) % strata
    wavelength = low + (high - low) * (stratum + jax.random.uniform(k_wave, (count,), dtype)) / strata
    return Connections(origins, directions, wavelength, light, flux, light_point)
