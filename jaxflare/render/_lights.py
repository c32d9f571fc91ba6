"""Lights as arrays, and the sampling of light-to-front-lens connections (Pekkarinen & Balzer
2019, section 3: "connecting a random sample on a light source with a random sample on the front
lens").

Kinds: point lights, sphere lights (seen from the lens as their facing disc, exact for distances
much larger than the radius), one-sided disk lights, and directional lights (a parallel beam, or a
cone of directions for a disc such as the sun). Geometry is in the lens frame in mm (x right, y up,
z along the axis towards the sensor; the front vertex at z = 0).

The front-lens point is uniform on a disc of the entrance plane (just in front of the lens) that
covers every ray able to reach the front clear aperture from the chosen light point (or in the
chosen direction): its centre and radius follow the light, so the sampled disc stays tight for
lights far off the axis. The flux factor of a sample is the radiometric coupling of the two points
over their sampling pdf: ``L A_light A_disc cos cos / r^2`` for area lights, ``I A_disc cos / r^2``
for point lights, ``L Omega A_disc cos`` for a directional disc, ``E A_disc cos`` for a beam.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxflare.colour._spectral import SpectralTable, blackbody_spectrum, normalise_spectrum, rgb_response_at
from jaxflare.scenes._scene import Scene, SceneError, light_travel_direction

POINT, SPHERE, DISK, DIRECTIONAL = 0, 1, 2, 3
KINDS = {"point": POINT, "sphere": SPHERE, "disk": DISK, "directional": DIRECTIONAL}


class LightArrays(eqx.Module):
    """The flare lights in the lens frame (mm), as arrays."""

    kind: Int[Array, " NL"]
    centre_mm: Float[Array, "NL 3"]
    axis: Float[Array, "NL 3"]
    """Travel direction of light from the light's centre to the lens (unit)."""
    normal: Float[Array, "NL 3"]
    """Emitting normal of disk and sphere lights (towards the lens for a sphere's facing disc)."""
    radius_mm: Float[Array, " NL"]
    cone_cos: Float[Array, " NL"]
    """Directional lights: cosine of the angular radius (1 for a parallel beam)."""
    rgb: Float[Array, "NL 3"]
    spectral_rgb: Float[Array, "NL L 3"]
    """Spectral lights: RGB response per wavelength of the grid; unused for RGB lights."""
    is_spectral: Array
    power: Float[Array, " NL"]
    """intensity x flare multiplier (x 1e6 for point lights: W/sr over mm^2 to W/m^2)."""
    selection_probability: Float[Array, " NL"]


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
    light_point_mm: Float[Array, "N 3"]
    """The sampled point on the light (lens frame, mm); the light's centre for directional lights."""


def light_arrays(scene: Scene, spectral: SpectralTable) -> tuple[LightArrays, list[int]]:
    """The scene's flare lights (``flare = true``) as :class:`LightArrays`, and their scene indices."""
    camera = scene.camera
    rotation = camera.world_to_camera()
    chosen = [k for k, light in enumerate(scene.lights) if light.flare]
    if not chosen:
        raise SceneError("light: no light has flare = true, so there is no flare to render")
    rows = []
    for k in chosen:
        light = scene.lights[k]
        axis = light_travel_direction(camera, light, rotation)
        kind = KINDS[light.kind]
        if kind == DIRECTIONAL:
            centre = np.zeros(3)
        else:
            centre = rotation @ (np.asarray(light.position_m) - np.asarray(camera.position_m)) * 1000.0
        normal = axis  # spheres (seen as their facing disc) and default disks emit towards the lens
        if kind == DISK and light.normal is not None:
            normal = rotation @ np.asarray(light.normal, float)
            normal = normal / np.linalg.norm(normal)
        spectral_rgb = np.zeros((spectral.wavelength_nm.shape[0], 3))
        is_spectral = light.spectrum is not None or light.temperature_k is not None
        if light.spectrum is not None:
            values = normalise_spectrum(light.spectrum[0], light.spectrum[1], spectral)
            spectral_rgb = values[:, None] * np.asarray(spectral.spectrum_response)
        elif light.temperature_k is not None:
            spectral_rgb = blackbody_spectrum(light.temperature_k, spectral)[:, None] * np.asarray(spectral.spectrum_response)
        rgb = np.asarray(light.rgb if light.rgb is not None else (1.0, 1.0, 1.0), float)
        power = light.intensity * light.flare_intensity * (1e6 if kind == POINT else 1.0)
        rows.append(
            dict(
                kind=kind, centre_mm=centre, axis=axis, normal=normal, radius_mm=light.radius_m * 1000.0,
                cone_cos=math.cos(math.radians(light.angular_radius_deg)) if kind == DIRECTIONAL else 1.0,
                rgb=rgb, spectral_rgb=spectral_rgb, is_spectral=is_spectral, power=power,
            )
        )
    luminance = np.asarray(spectral.luminance_weights)
    strength = []
    for row in rows:
        colour = row["spectral_rgb"].mean(axis=0) if row["is_spectral"] else row["rgb"]
        area = math.pi * row["radius_mm"] ** 2 if row["kind"] in (SPHERE, DISK) else 1.0
        distance2 = max(float(np.dot(row["centre_mm"], row["centre_mm"])), 1.0) if row["kind"] != DIRECTIONAL else 1.0
        solid = 2 * math.pi * (1 - row["cone_cos"]) if row["kind"] == DIRECTIONAL and row["cone_cos"] < 1 else 1.0
        strength.append(max(float(luminance @ colour), 1e-12) * row["power"] * area * solid / distance2 + 1e-30)
    probability = np.asarray(strength) / np.sum(strength)
    stack = {key: np.stack([np.asarray(row[key], float) for row in rows]) for key in rows[0]}
    arrays = LightArrays(
        kind=jnp.asarray(stack["kind"].astype(np.int32)),
        centre_mm=jnp.asarray(stack["centre_mm"]),
        axis=jnp.asarray(stack["axis"]),
        normal=jnp.asarray(stack["normal"]),
        radius_mm=jnp.asarray(stack["radius_mm"]),
        cone_cos=jnp.asarray(stack["cone_cos"]),
        rgb=jnp.asarray(stack["rgb"]),
        spectral_rgb=jnp.asarray(stack["spectral_rgb"]),
        is_spectral=jnp.asarray(stack["is_spectral"] > 0),
        power=jnp.asarray(stack["power"]),
        selection_probability=jnp.asarray(probability),
    )
    return arrays, chosen


def sample_connections(
    lights: LightArrays, front: FrontDisc, spectral, key: Array, count: int, wavelength_strata: int,
    light: Array | None = None, front_unit: Array | None = None,
) -> Connections:
    """``count`` connections between a point on a light and a point on the front lens.

    ``light`` (N,) fixes each sample's light (else it is drawn by ``selection_probability`` and the
    flux divided by that probability); ``front_unit`` (N, 2) fixes the front-lens point on the unit
    disc (else uniform), which :class:`FrontDisc` maps onto the entrance plane. The flux is the
    radiometric factor over the pdf of the light point and of a uniform front point.
    """
    dtype = lights.axis.dtype
    k_light, k_light_point, k_front, k_wave = jax.random.split(key, 4)
    chosen = light is None
    if chosen:
        light = jax.random.choice(k_light, lights.kind.shape[0], (count,), p=lights.selection_probability)
    kind = lights.kind[light]
    u = jax.random.uniform(k_light_point, (count, 2), dtype)

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
    light_point = lights.centre_mm[light] + jnp.where((kind == SPHERE) | (kind == DISK), 1.0, 0.0)[:, None] * on_disc
    cone_cos = lights.cone_cos[light]
    cos_t = 1.0 - u[:, 0] * (1.0 - cone_cos)
    sin_t = jnp.sqrt(jnp.clip(1.0 - cos_t**2, 0.0, 1.0))
    cone_direction = cos_t[:, None] * normal + (sin_t * jnp.cos(phi))[:, None] * e1 + (sin_t * jnp.sin(phi))[:, None] * e2

    # a point on the front lens: uniform on a disc of the entrance plane covering every ray that can
    # reach the front clear aperture from this light point (or in this direction)
    z_e = front.entrance_z_mm
    z_low, z_high = front.z_range_mm
    z_mid = 0.5 * (z_low + z_high)
    finite = kind != DIRECTIONAL
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
    geometry = jnp.select(
        [kind == POINT, (kind == SPHERE) | (kind == DISK), cone_cos < 1.0],
        [disc_area * cos_front / distance2, light_area * disc_area * cos_light * cos_front / distance2, solid_angle * disc_area * cos_front],
        disc_area * cos_front,
    )
    flux = geometry * lights.power[light]
    if chosen:
        flux = flux / lights.selection_probability[light]

    # stratified wavelengths: each stratum of the band gets the same number of samples per batch
    strata = wavelength_strata
    grid = spectral.wavelength_nm
    low, high = grid[0], grid[-1]
    stratum = jnp.arange(count) % strata
    wavelength = low + (high - low) * (stratum + jax.random.uniform(k_wave, (count,), dtype)) / strata
    return Connections(origins, directions, wavelength, light, flux, light_point)


def light_rgb(lights: LightArrays, spectral, light: Array, wavelength: Array) -> Array:
    """RGB contribution per unit power of each sample's light at its wavelength (N, 3)."""
    grid = spectral.wavelength_nm
    response = rgb_response_at(spectral, wavelength)  # (N, 3, 3)
    rgb = jnp.einsum("nij,nj->ni", response, lights.rgb[light])
    position = jnp.clip((wavelength - grid[0]) / (grid[1] - grid[0]), 0, grid.shape[0] - 1)
    below = jnp.clip(jnp.floor(position).astype(jnp.int32), 0, grid.shape[0] - 2)
    fraction = (position - below)[:, None]
    num_grid = grid.shape[0]
    table = lights.spectral_rgb.reshape(-1, 3)  # (NL * L, 3)
    row = light * num_grid + below
    spectral = table[row] * (1 - fraction) + table[row + 1] * fraction
    return jnp.where(lights.is_spectral[light][:, None], spectral, rgb)
