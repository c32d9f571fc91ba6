"""One batch of the flare renderer: sample, trace, weigh by equation (2), splat.

Two kinds of path sets are rendered in each batch:

- *adaptive sets* of exactly traced paths: every sample draws its (light, path, front-lens cell)
  from a :class:`~jaxflare._adaptive.SamplingTable` and is traced along its own path's event table
  (one batch mixes paths); its weight is ``a_cell / q``;
- *polynomial groups*: paths with path systems of one structure, ``rays_per_path`` samples each,
  uniform over the front lens, evaluated together (vmapped).

Values are normalised per batch (divided by the batch's sample count), so the image is the mean
over batches; each batch is an unbiased estimate whatever its sampling table.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ._adaptive import SamplingTable, draw
from ._lens import Lens
from ._lights import Connections, FrontDisc, LightArrays, light_rgb, sample_connections
from ._trace import _surface_sag_slope, _trace_events


class AdaptiveSet(eqx.Module):
    """Exactly traced paths sampled through one joint (light, path, cell) table."""

    events: Int[Array, "P E 4"]
    path_index: Int[Array, " P"]
    """Index of each path in the render's path list."""
    table: SamplingTable
    samples: int = eqx.field(static=True)
    """Samples per batch."""


class PolynomialGroup(eqx.Module):
    """Paths whose polynomial systems share one structure (stacked kernels), sampled uniformly."""

    kernel: eqx.Module
    path_index: Int[Array, " P"]


class SceneEffects(eqx.Module):
    """What the scene adds on top of the lens: dirt on the front element, a hood, occluding
    geometry and the main render's distortion. Each is optional (None: skipped, no cost)."""

    dirt: Float[Array, "H W C"] | None = None
    hood: eqx.Module | None = None
    occluders: object | None = eqx.field(static=True, default=None)
    camera_position_m: Float[Array, " 3"] | None = None
    camera_to_world: Float[Array, "3 3"] | None = None
    distortion: eqx.Module | None = None
    st_map: Float[Array, "H W 2"] | None = None


class RenderSetup(eqx.Module):
    """Everything one render step reads."""

    lens: Lens
    lights: LightArrays
    front: FrontDisc
    spectral: eqx.Module
    adaptive: tuple[AdaptiveSet, ...]
    polynomial: tuple[PolynomialGroup, ...]
    effects: SceneEffects
    path_fresnel: Float[Array, "P L"]
    """Coated Fresnel factor of each path on the axis, per wavelength of the spectral grid."""
    path_tint: Float[Array, "P 3"]
    path_layer: Int[Array, " P"]
    path_is_flare: Array
    path_enabled: Array
    """False for culled paths: their samples count for nothing (and adaptive tables skip them)."""
    pixel_pitch_mm: Float[Array, ""]
    resolution: tuple[int, int] = eqx.field(static=True)
    rays_per_path: int = eqx.field(static=True)
    wavelength_strata: int = eqx.field(static=True)
    schlick: bool = eqx.field(static=True)


class Accumulators(eqx.Module):
    """What the batches add up (all normalised per batch: divide by the number of batches)."""

    layers: Float[Array, "Y H W 3"]
    flare_luminance_sum: Float[Array, "H W"]
    flare_luminance_squares: Float[Array, "H W"]
    """Per-batch flare luminance images, summed and squared: the per-pixel variance layer."""
    path_energy: Float[Array, "P 3"]
    path_incoming: Float[Array, " P"]
    """Luminance of the light entering the sampled front disc, per path (for the culling bound)."""
    path_hits: Int[Array, " P"]
    path_passed: Int[Array, " P"]
    path_unevaluated: Int[Array, " P"]
    path_samples: Int[Array, " P"]
    table_energy: tuple[Float[Array, " K"], ...]
    weight_all: Float[Array, ""]
    weight_hits: Float[Array, ""]


def empty_accumulators(setup: RenderSetup, num_layers: int) -> Accumulators:
    width, height = setup.resolution
    paths = setup.path_layer.shape[0]
    f32 = jnp.float32
    return Accumulators(
        layers=jnp.zeros((num_layers, height, width, 3), f32),
        flare_luminance_sum=jnp.zeros((height, width), f32),
        flare_luminance_squares=jnp.zeros((height, width), f32),
        path_energy=jnp.zeros((paths, 3), f32),
        path_incoming=jnp.zeros(paths, f32),
        path_hits=jnp.zeros(paths, jnp.int32),
        path_passed=jnp.zeros(paths, jnp.int32),
        path_unevaluated=jnp.zeros(paths, jnp.int32),
        path_samples=jnp.zeros(paths, jnp.int32),
        table_energy=tuple(jnp.zeros(s.table.probability.shape, f32) for s in setup.adaptive),
        weight_all=jnp.zeros((), f32),
        weight_hits=jnp.zeros((), f32),
    )


def front_vertex_plane_xy(origins: Array, directions: Array) -> Array:
    """Where each ray crosses the front vertex plane z = 0 (mm)."""
    travel = -origins[:, 2] / directions[:, 2]
    return origins[:, :2] + travel[:, None] * directions[:, :2]


def front_cosine(lens: Lens, xy: Array, directions: Array) -> Array:
    """Cosine of the angle of incidence at the front surface, evaluated at ``xy`` on it."""
    x, y = xy[:, 0], xy[:, 1]
    _, g = _surface_sag_slope(x * x + y * y, lens.curvature_per_mm[0], lens.conic[0], lens.aspheric_coefficients[0])
    normal = jnp.stack([-g * x, -g * y, jnp.ones_like(x)], axis=-1)
    normal = normal / jnp.linalg.norm(normal, axis=-1, keepdims=True)
    return jnp.abs(jnp.sum(normal * directions, axis=-1))


def interpolate_rows(table: Array, row: Array, grid: Array, wavelength: Array) -> Array:
    """Linear interpolation of ``table[row]`` (table (P, L) over a uniform grid) at each wavelength."""
    position = jnp.clip((wavelength - grid[0]) / (grid[1] - grid[0]), 0, grid.shape[0] - 1)
    below = jnp.clip(jnp.floor(position).astype(jnp.int32), 0, grid.shape[0] - 2)
    fraction = position - below
    return table[row, below] * (1 - fraction) + table[row, below + 1] * fraction


def _lens_and_scene_factor(setup: RenderSetup, connections: Connections, path: Array):
    """Per sample: RGB before the lens path (light colour x flux x dirt x visibility) and the path's
    Fresnel factor (Schlick model) -- everything of equation (2) except the path's own throughput."""
    effects = setup.effects
    rgb = light_rgb(setup.lights, setup.spectral, connections.light, connections.wavelength_nm) * connections.flux[:, None]
    xy = front_vertex_plane_xy(connections.origins, connections.directions)
    if effects.dirt is not None:
        from ._dirt import dirt_transmission

        rgb = rgb * dirt_transmission(effects.dirt, xy, setup.front.radius_mm)
    visible = jnp.ones(rgb.shape[0], bool)
    if effects.hood is not None:
        from ._occlusion import hood_visible

        visible = visible & hood_visible(effects.hood, connections.origins, connections.directions)
    if effects.occluders is not None:
        from ._occlusion import segment_visibility

        to_world = effects.camera_to_world
        start = effects.camera_position_m + (connections.origins / 1000.0) @ to_world.T
        light_end = effects.camera_position_m + (connections.light_point_mm / 1000.0) @ to_world.T
        far_end = start - 1e6 * connections.directions @ to_world.T
        directional = setup.lights.kind[connections.light] == 3
        end = jnp.where(directional[:, None], far_end, light_end)
        visible = visible & segment_visibility(effects.occluders, start, end)
    rgb = jnp.where(visible[:, None], rgb, 0.0)
    fresnel = interpolate_rows(setup.path_fresnel, path, setup.spectral.wavelength_nm, connections.wavelength_nm)
    fresnel = fresnel * (1.0 - (1.0 - front_cosine(setup.lens, xy, connections.directions)) ** 5)
    return rgb, fresnel


def _image_position(setup: RenderSetup, sensor_xy: Array):
    """Pixel position (column, row; pixel centres at integer + 0.5) of sensor points: the image is
    upright (the lens inverts it), then the main render's distortion is applied."""
    width, height = setup.resolution
    column = -sensor_xy[:, 0] / setup.pixel_pitch_mm + 0.5 * width
    row = sensor_xy[:, 1] / setup.pixel_pitch_mm + 0.5 * height
    effects = setup.effects
    if effects.distortion is not None:
        from ._distortion import distort

        column, row = distort(effects.distortion, column, row, width, height)
    if effects.st_map is not None:
        from ._distortion import st_map_distort

        column, row = st_map_distort(effects.st_map, column, row, width, height)
    return column, row


def _splat(buffer: Array, layer: Array, column: Array, row: Array, value: Array, hit: Array) -> Array:
    """Bilinear splat (a tent filter one pixel wide); a sample near the border keeps its whole
    weight (what would fall off the image goes to the edge pixel). ``buffer``: (Y, H, W, C)."""
    num_layers, height, width, channels = buffer.shape
    x = column - 0.5
    y = row - 0.5
    x0 = jnp.floor(x)
    y0 = jnp.floor(y)
    fx = x - x0
    fy = y - y0
    flat = buffer.reshape(-1, channels)
    outside = num_layers * height * width
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        xi = jnp.clip((x0 + dx).astype(jnp.int32), 0, width - 1)
        yi = jnp.clip((y0 + dy).astype(jnp.int32), 0, height - 1)
        index = jnp.where(hit, (layer * height + yi) * width + xi, outside)
        flat = flat.at[index].add((value * w[:, None]).astype(flat.dtype), mode="drop")
    return flat.reshape(buffer.shape)


STEP_TRACES = [0]
"""How often the render step has been traced by JAX (tests use it to catch retracing)."""


def render_step(setup: RenderSetup, acc: Accumulators, key: Array) -> Accumulators:
    """One batch of every path set; returns the accumulators with the batch added."""
    STEP_TRACES[0] += 1
    width, height = setup.resolution
    luminance_weights = setup.spectral.luminance_weights.astype(jnp.float32)
    batch_luminance = jnp.zeros((1, height, width, 1), jnp.float32)

    def record(acc, batch_luminance, path, value, incoming, hit, valid, evaluated, column, row, weight):
        """Splat one set's samples and add their statistics (``value`` already normalised)."""
        enabled = setup.path_enabled[path]
        value = jnp.where((hit & enabled)[:, None], value, 0.0).astype(jnp.float32)
        layer = setup.path_layer[path]
        layers = _splat(acc.layers, layer, column, row, value, hit & enabled)
        flare = setup.path_is_flare[path] & hit & enabled
        lum = value @ luminance_weights
        batch_luminance = _splat(batch_luminance, jnp.zeros_like(layer), column, row, lum[:, None], flare)
        is_flare = setup.path_is_flare[path] & enabled
        return eqx.tree_at(
            lambda a: (a.layers, a.path_energy, a.path_incoming, a.path_hits, a.path_passed, a.path_unevaluated, a.path_samples, a.weight_all, a.weight_hits),
            acc,
            (
                layers,
                acc.path_energy.at[path].add(value),
                acc.path_incoming.at[path].add(incoming.astype(jnp.float32)),
                acc.path_hits.at[path].add(hit.astype(jnp.int32)),
                acc.path_passed.at[path].add(valid.astype(jnp.int32)),
                acc.path_unevaluated.at[path].add((~evaluated).astype(jnp.int32)),
                acc.path_samples.at[path].add(1),
                acc.weight_all + jnp.sum(jnp.where(is_flare, weight, 0.0)),
                acc.weight_hits + jnp.sum(jnp.where(flare, weight, 0.0)),
            ),
        ), batch_luminance

    for k, adaptive in enumerate(setup.adaptive):
        count = adaptive.samples
        k_table, k_rays = jax.random.split(jax.random.fold_in(key, 1000 + k))
        light, slot, unit, index, weight = draw(adaptive.table, k_table, count)
        connections = sample_connections(
            setup.lights, setup.front, setup.spectral, k_rays, count, setup.wavelength_strata, light=light, front_unit=unit,
        )
        path = adaptive.path_index[slot]
        traced = _trace_events(setup.lens, connections.origins, connections.directions, connections.wavelength_nm, adaptive.events[slot], 1)
        rgb, fresnel = _lens_and_scene_factor(setup, connections, path)
        if not setup.schlick:
            fresnel = traced.throughput
        column, row = _image_position(setup, traced.positions[:, :2])
        on_sensor = (column >= 0) & (column < width) & (row >= 0) & (row < height)
        hit = traced.valid & on_sensor
        norm = weight / count
        tint = setup.path_tint[path]
        value = rgb * (fresnel * jnp.abs(traced.directions[:, 2]) * norm)[:, None] * tint
        incoming = (rgb @ luminance_weights) * norm
        acc, batch_luminance = record(acc, batch_luminance, path, value, incoming, hit, traced.valid, jnp.ones_like(hit), column, row, norm)
        energy = jnp.where(hit & setup.path_enabled[path], value @ luminance_weights, 0.0)
        acc = eqx.tree_at(lambda a: a.table_energy[k], acc, acc.table_energy[k].at[index].add(energy.astype(jnp.float32)))

    for g, group in enumerate(setup.polynomial):
        from ._path_system import evaluate

        n = setup.rays_per_path
        keys = jax.vmap(lambda p: jax.random.fold_in(key, p))(group.path_index)
        connections = jax.vmap(lambda k: sample_connections(setup.lights, setup.front, setup.spectral, k, n, setup.wavelength_strata))(keys)
        traced = jax.vmap(evaluate)(group.kernel, connections.origins, connections.directions, connections.wavelength_nm)
        flat = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), (connections, traced))
        connections, traced = flat
        path = jnp.repeat(group.path_index, n)
        rgb, fresnel = _lens_and_scene_factor(setup, connections, path)
        if not setup.schlick:
            fresnel = traced.throughput
        column, row = _image_position(setup, traced.positions[:, :2])
        on_sensor = (column >= 0) & (column < width) & (row >= 0) & (row < height)
        hit = traced.valid & on_sensor
        norm = jnp.full(hit.shape, 1.0 / n, jnp.float32)
        value = rgb * (fresnel * jnp.abs(traced.directions[:, 2]) / n)[:, None] * setup.path_tint[path]
        incoming = (rgb @ luminance_weights) / n
        acc, batch_luminance = record(acc, batch_luminance, path, value, incoming, hit, traced.valid, traced.trusted, column, row, norm)

    image = batch_luminance[0, :, :, 0]
    return eqx.tree_at(
        lambda a: (a.flare_luminance_sum, a.flare_luminance_squares),
        acc,
        (acc.flare_luminance_sum + image, acc.flare_luminance_squares + image * image),
    )


STEP = eqx.filter_jit(render_step)
STEP_DONATING = eqx.filter_jit(render_step, donate="all-except-first")
"""One compiled step per render structure (lens, path sets, lights, resolution, layers, effects),
shared by every render with that structure. Accelerators update the accumulators in place (CPU
XLA cannot donate buffers)."""


def path_fresnel_table(lens: Lens, events: Array, wavelength_nm: Array) -> Array:
    """Coated Fresnel factor of each path (events (P, E, 4)) for the on-axis ray, per wavelength (P, L)."""
    count = wavelength_nm.shape[0]
    origins = jnp.zeros((count, 3), lens.thickness_mm.dtype).at[:, 2].set(-1.0)
    directions = jnp.zeros((count, 3), lens.thickness_mm.dtype).at[:, 2].set(1.0)
    return jax.vmap(lambda e: _trace_events(lens, origins, directions, wavelength_nm.astype(origins.dtype), e, 1).throughput)(events)
