"""The flare lights as arrays (lens frame, mm) and their colour at each sample's wavelength.

Kinds (:class:`jaxflare.scenes.LightKind`): point lights, sphere lights (seen from the lens as their
facing disc, exact for distances much larger than the radius), one-sided disk lights, and
directional lights (a parallel beam, or a cone of directions for a disc such as the sun).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..colour import SpectralTable, blackbody_spectrum, grid_position, normalise_spectrum, rgb_response_at
from ..scenes import LightKind, Scene, SceneError, light_travel_direction


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
    emission: Float[Array, " NL"]
    """``Light.intensity`` (in the unit of its kind, :attr:`jaxflare.Light.intensity_unit`) times
    ``flare_intensity``; point lights' radiant intensity is scaled by 1e6 (per mm^2 to per m^2,
    as their flux factor divides by a distance in mm squared)."""
    selection_probability: Float[Array, " NL"]


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
        kind = LightKind.from_label(light.kind)
        if kind == LightKind.DIRECTIONAL:
            centre = np.zeros(3)
        else:
            centre = rotation @ (np.asarray(light.position_m) - np.asarray(camera.position_m)) * 1000.0
        normal = axis  # spheres (seen as their facing disc) and default disks emit towards the lens
        if kind == LightKind.DISK and light.normal is not None:
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
        emission = light.intensity * light.flare_intensity * (1e6 if kind == LightKind.POINT else 1.0)
        rows.append(
            dict(
                kind=kind, centre_mm=centre, axis=axis, normal=normal, radius_mm=light.radius_m * 1000.0,
                cone_cos=math.cos(math.radians(light.angular_radius_deg)) if kind == LightKind.DIRECTIONAL else 1.0,
                rgb=rgb, spectral_rgb=spectral_rgb, is_spectral=is_spectral, emission=emission,
            )
        )
    luminance = np.asarray(spectral.luminance_weights)
    strength = []
    for row in rows:
        colour = row["spectral_rgb"].mean(axis=0) if row["is_spectral"] else row["rgb"]
        area = math.pi * row["radius_mm"] ** 2 if row["kind"] in (LightKind.SPHERE, LightKind.DISK) else 1.0
        distance2 = max(float(np.dot(row["centre_mm"], row["centre_mm"])), 1.0) if row["kind"] != LightKind.DIRECTIONAL else 1.0
        solid = 2 * math.pi * (1 - row["cone_cos"]) if row["kind"] == LightKind.DIRECTIONAL and row["cone_cos"] < 1 else 1.0
        strength.append(max(float(luminance @ colour), 1e-12) * row["emission"] * area * solid / distance2 + 1e-30)
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
        emission=jnp.asarray(stack["emission"]),
        selection_probability=jnp.asarray(probability),
    )
    return arrays, chosen


def light_rgb(lights: LightArrays, spectral, light: Array, wavelength: Array) -> Array:
    """RGB contribution per unit emission of each sample's light at its wavelength (N, 3)."""
    grid = spectral.wavelength_nm
    response = rgb_response_at(spectral, wavelength)  # (N, 3, 3)
    rgb = jnp.einsum("nij,nj->ni", response, lights.rgb[light])
    below, fraction = grid_position(grid, wavelength)
    fraction = fraction[:, None]
    num_grid = grid.shape[0]
    table = lights.spectral_rgb.reshape(-1, 3)  # (NL * L, 3)
    row = light * num_grid + below
    spectral = table[row] * (1 - fraction) + table[row + 1] * fraction
    return jnp.where(lights.is_spectral[light][:, None], spectral, rgb)
