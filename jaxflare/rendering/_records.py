"""What a batch's samples are, and what they are worth: equation (2) of Pekkarinen & Balzer 2019.

A sample's record holds what does not change when a fit changes light colours, coatings, coating
tints or the dirt map: its path, light, wavelength, where it entered the front lens, where it lands
in the image, whether it got there, and its flux factor. :func:`record_values` turns records into
RGB values for given colours, tints and dirt, so the renderer and the fitting package share one
equation.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..colour import grid_position
from ..scenes import LightKind
from ._lights import LightArrays, light_rgb
from ._sampling import Connections
from .effects import dirt_transmission, hood_visible, segment_visibility
from ..optics import sag_and_slope


class SampleRecords(eqx.Module):
    """What a batch's samples are, apart from the quantities a fit may change (light colour and
    intensity, coatings, coating tints, dirt): the value of sample ``s`` is
    ``light_rgb(light_s, wavelength_s) x flux_factor_s x fresnel(path_s, wavelength_s) x tint(path_s)
    x dirt(front_xy_s)``, splatted at (column_s, row_s) when ``hit_s``."""

    path: Int[Array, " N"]
    light: Int[Array, " N"]
    wavelength_nm: Float[Array, " N"]
    front_xy_mm: Float[Array, "N 2"]
    """Where the sample crosses the front vertex plane (for the dirt map)."""
    column: Float[Array, " N"]
    row: Float[Array, " N"]
    hit: Array
    """Got through the lens, onto the picture, and its path is not culled."""
    valid: Array
    evaluated: Array
    flux_factor: Float[Array, " N"]
    """The light-to-lens coupling (with the light's emission) x visibility (hood, occluding
    geometry) x the Schlick term at the front lens (Schlick model only) x the sensor cosine x the
    normalised sample weight."""
    exact_throughput: Float[Array, " N"] | None
    """With ``fresnel="exact"``: the traced coated throughput (replaces the on-axis factor)."""
    weight: Float[Array, " N"]
    """The normalised sample weight (a_cell / q / batch size)."""
    table_index: Int[Array, " N"] | None = None


def front_vertex_plane_xy(origins: Array, directions: Array) -> Array:
    """Where each ray crosses the front vertex plane z = 0 (mm)."""
    travel = -origins[:, 2] / directions[:, 2]
    return origins[:, :2] + travel[:, None] * directions[:, :2]


def front_cosine(lens, xy: Array, directions: Array) -> Array:
    """Cosine of the angle of incidence at the front surface, evaluated at ``xy`` on it."""
    x, y = xy[:, 0], xy[:, 1]
    _, g = sag_and_slope(x * x + y * y, lens.curvature_per_mm[0], lens.conic[0], lens.aspheric_coefficients[0])
    normal = jnp.stack([-g * x, -g * y, jnp.ones_like(x)], axis=-1)
    normal = normal / jnp.linalg.norm(normal, axis=-1, keepdims=True)
    return jnp.abs(jnp.sum(normal * directions, axis=-1))


def interpolate_rows(table: Array, row: Array, grid: Array, wavelength: Array) -> Array:
    """Linear interpolation of ``table[row]`` (table (P, L) over the uniform wavelength grid) at each
    sample's wavelength."""
    below, fraction = grid_position(grid, wavelength)
    return table[row, below] * (1 - fraction) + table[row, below + 1] * fraction


def image_position(setup, sensor_xy: Array) -> tuple[Array, Array]:
    """Pixel position (column, row; pixel centres at integer + 0.5) of sensor points: the image is
    upright (the lens inverts it), then the main render's distortion is applied."""
    width, height = setup.resolution
    column = -sensor_xy[:, 0] / setup.pixel_pitch_mm + 0.5 * width
    row = sensor_xy[:, 1] / setup.pixel_pitch_mm + 0.5 * height
    if setup.effects.distortion is not None:
        column, row = setup.effects.distortion(column, row, width, height)
    return column, row


def sample_records(setup, connections: Connections, path, traced, weight, table_index=None) -> SampleRecords:
    """The records of traced connections: visibility (hood, occluders), flux factor, image position."""
    width, height = setup.resolution
    effects = setup.effects
    xy = front_vertex_plane_xy(connections.origins, connections.directions)
    visible = jnp.ones(xy.shape[0], bool)
    if effects.hood is not None:
        visible = visible & hood_visible(effects.hood, connections.origins, connections.directions)
    if effects.occluders is not None:
        to_world = effects.camera_to_world
        start = effects.camera_position_m + (connections.origins / 1000.0) @ to_world.T
        light_end = effects.camera_position_m + (connections.light_point_mm / 1000.0) @ to_world.T
        far_end = start - 1e6 * connections.directions @ to_world.T
        directional = setup.lights.kind[connections.light] == LightKind.DIRECTIONAL
        end = jnp.where(directional[:, None], far_end, light_end)
        visible = visible & segment_visibility(effects.occluders, start, end)
    flux_factor = connections.flux * jnp.where(visible, 1.0, 0.0) * jnp.abs(traced.directions[:, 2]) * weight
    if setup.schlick:
        flux_factor = flux_factor * (1.0 - (1.0 - front_cosine(setup.lens, xy, connections.directions)) ** 5)
    column, row = image_position(setup, traced.positions[:, :2])
    on_sensor = (column >= 0) & (column < width) & (row >= 0) & (row < height)
    evaluated = traced.trusted if traced.trusted is not None else jnp.ones_like(traced.valid)
    return SampleRecords(
        path=path, light=connections.light, wavelength_nm=connections.wavelength_nm, front_xy_mm=xy, column=column, row=row,
        hit=traced.valid & on_sensor & setup.path_enabled[path], valid=traced.valid, evaluated=evaluated, flux_factor=flux_factor,
        exact_throughput=None if setup.schlick else traced.throughput, weight=weight, table_index=table_index,
    )


def record_values(
    records: SampleRecords, lights: LightArrays, spectral, path_fresnel: Array, path_tint: Array, dirt: Array | None,
    front_radius_mm, rgb: Array | None = None,
) -> Array:
    """RGB value (N, 3) of each recorded sample for the given light colours, coatings (on-axis
    Fresnel factor per path and wavelength), tints and dirt map: equation (2). Differentiable in all
    of them; zero where the sample did not hit. ``rgb``: each sample's light colour at its
    wavelength (:func:`light_rgb`), when the caller has it already."""
    if rgb is None:
        rgb = light_rgb(lights, spectral, records.light, records.wavelength_nm)
    if records.exact_throughput is None:
        fresnel = interpolate_rows(path_fresnel, records.path, spectral.wavelength_nm, records.wavelength_nm)
    else:
        fresnel = records.exact_throughput
    value = rgb * (records.flux_factor * fresnel)[:, None] * path_tint[records.path]
    if dirt is not None:
        value = value * dirt_transmission(dirt, records.front_xy_mm, front_radius_mm)
    return jnp.where(records.hit[:, None], value, 0.0)
