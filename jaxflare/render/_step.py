"""One batch of the flare renderer: sample, trace, weigh by equation (2), splat.

Two kinds of path sets are rendered in each batch:

- *adaptive sets* of exactly traced paths: every sample draws its (light, path, front-lens cell)
  from a :class:`~jaxflare.render._adaptive.SamplingTable` and is traced along its own path's event table
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

from jaxflare.render._adaptive import SamplingTable, draw
from jaxflare.optics._lens import Lens
from jaxflare.render._lights import Connections, FrontDisc, LightArrays, light_rgb, sample_connections
from jaxflare.optics._trace import _surface_sag_slope, _trace_events


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


class SampleRecords(eqx.Module):
    """What a batch's samples are, apart from the quantities a fit may change (light colour and
    intensity, coatings, coating tints, dirt): the value of sample ``s`` is
    ``light_rgb(light_s, wavelength_s) x geometry_s x fresnel(path_s, wavelength_s) x tint(path_s)
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
    geometry: Float[Array, " N"]
    """Flux factor (with the light's power) x visibility (hood, geometry) x the Schlick term at
    the front lens (Schlick model only) x the sensor cosine x the normalised sample weight."""
    exact_throughput: Float[Array, " N"] | None
    """With ``fresnel="exact"``: the traced coated throughput (replaces the on-axis factor)."""
    weight: Float[Array, " N"]
    """The normalised sample weight (a_cell / q / batch size)."""
    table_index: Int[Array, " N"] | None = None


def _records(setup: RenderSetup, connections: Connections, path, traced, weight, table_index=None) -> SampleRecords:
    width, height = setup.resolution
    effects = setup.effects
    xy = front_vertex_plane_xy(connections.origins, connections.directions)
    visible = jnp.ones(xy.shape[0], bool)
    if effects.hood is not None:
        from jaxflare.render.effects._occluders import hood_visible

        visible = visible & hood_visible(effects.hood, connections.origins, connections.directions)
    if effects.occluders is not None:
        from jaxflare.render.effects._occluders import segment_visibility

        to_world = effects.camera_to_world
        start = effects.camera_position_m + (connections.origins / 1000.0) @ to_world.T
        light_end = effects.camera_position_m + (connections.light_point_mm / 1000.0) @ to_world.T
        far_end = start - 1e6 * connections.directions @ to_world.T
        directional = setup.lights.kind[connections.light] == 3
        end = jnp.where(directional[:, None], far_end, light_end)
        visible = visible & segment_visibility(effects.occluders, start, end)
    geometry = connections.flux * jnp.where(visible, 1.0, 0.0) * jnp.abs(traced.directions[:, 2]) * weight
    if setup.schlick:
        geometry = geometry * (1.0 - (1.0 - front_cosine(setup.lens, xy, connections.directions)) ** 5)
    column, row = _image_position(setup, traced.positions[:, :2])
    on_sensor = (column >= 0) & (column < width) & (row >= 0) & (row < height)
    evaluated = traced.trusted if traced.trusted is not None else jnp.ones_like(traced.valid)
    return SampleRecords(
        path=path, light=connections.light, wavelength_nm=connections.wavelength_nm, front_xy_mm=xy, column=column, row=row,
        hit=traced.valid & on_sensor & setup.path_enabled[path], valid=traced.valid, evaluated=evaluated, geometry=geometry,
        exact_throughput=None if setup.schlick else traced.throughput, weight=weight, table_index=table_index,
    )


def record_values(
    records: SampleRecords, lights: LightArrays, spectral, path_fresnel: Array, path_tint: Array, dirt: Array | None,
    front_radius_mm, rgb: Array | None = None,
) -> Array:
    """RGB value (N, 3) of each recorded sample for the given light colours, coatings (on-axis
    Fresnel factor per path and wavelength), tints and dirt map: equation (2). Differentiable in all
    of them; zero where the sample did not hit. ``rgb``: each sample's light colour at its
    wavelength (:func:`jaxflare.render._lights.light_rgb`), when the caller has it already."""
    if rgb is None:
        rgb = light_rgb(lights, spectral, records.light, records.wavelength_nm)
    if records.exact_throughput is None:
        fresnel = interpolate_rows(path_fresnel, records.path, spectral.wavelength_nm, records.wavelength_nm)
    else:
        fresnel = records.exact_throughput
    value = rgb * (records.geometry * fresnel)[:, None] * path_tint[records.path]
    if dirt is not None:
        from jaxflare.render.effects._dirt import dirt_transmission

        value = value * dirt_transmission(dirt, records.front_xy_mm, front_radius_mm)
    return jnp.where(records.hit[:, None], value, 0.0)


def _image_position(setup: RenderSetup, sensor_xy: Array):
    """Pixel position (column, row; pixel centres at integer + 0.5) of sensor points: the image is
    upright (the lens inverts it), then the main render's distortion is applied."""
    width, height = setup.resolution
    column = -sensor_xy[:, 0] / setup.pixel_pitch_mm + 0.5 * width
    row = sensor_xy[:, 1] / setup.pixel_pitch_mm + 0.5 * height
    effects = setup.effects
    if effects.distortion is not None:
        from jaxflare.render.effects._distortion import distort

        column, row = distort(effects.distortion, column, row, width, height)
    if effects.st_map is not None:
        from jaxflare.render.effects._distortion import st_map_distort

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


def batch_records(setup: RenderSetup, key: Array) -> tuple[SampleRecords, ...]:
    """Sample and trace one batch of every path set: one :class:`SampleRecords` per set."""
    records = []
    for k, adaptive in enumerate(setup.adaptive):
        count = adaptive.samples
        k_table, k_rays = jax.random.split(jax.random.fold_in(key, 1000 + k))
        light, slot, unit, index, weight = draw(adaptive.table, k_table, count)
        connections = sample_connections(
            setup.lights, setup.front, setup.spectral, k_rays, count, setup.wavelength_strata, light=light, front_unit=unit,
        )
        path = adaptive.path_index[slot]
        traced = _trace_events(setup.lens, connections.origins, connections.directions, connections.wavelength_nm, adaptive.events[slot], 1)
        records.append(_records(setup, connections, path, traced, weight / count, index))

    for group in setup.polynomial:
        from jaxflare.polynomial._system import evaluate

        n = setup.rays_per_path
        keys = jax.vmap(lambda p: jax.random.fold_in(key, p))(group.path_index)
        connections = jax.vmap(lambda k: sample_connections(setup.lights, setup.front, setup.spectral, k, n, setup.wavelength_strata))(keys)
        traced = jax.vmap(evaluate)(group.kernel, connections.origins, connections.directions, connections.wavelength_nm)
        connections, traced = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), (connections, traced))
        path = jnp.repeat(group.path_index, n)
        records.append(_records(setup, connections, path, traced, jnp.full(path.shape, 1.0 / n, connections.flux.dtype)))
    return tuple(records)


def render_step(setup: RenderSetup, acc: Accumulators, key: Array) -> Accumulators:
    """One batch of every path set; returns the accumulators with the batch added."""
    STEP_TRACES[0] += 1
    width, height = setup.resolution
    luminance_weights = setup.spectral.luminance_weights.astype(jnp.float32)
    batch_luminance = jnp.zeros((1, height, width, 1), jnp.float32)
    adaptive_count = len(setup.adaptive)
    for k, records in enumerate(batch_records(setup, key)):
        colour = light_rgb(setup.lights, setup.spectral, records.light, records.wavelength_nm)
        value = record_values(
            records, setup.lights, setup.spectral, setup.path_fresnel, setup.path_tint, setup.effects.dirt, setup.front.radius_mm,
            rgb=colour,
        ).astype(jnp.float32)
        path, hit = records.path, records.hit
        layer = setup.path_layer[path]
        flare = setup.path_is_flare[path] & hit
        lum = value @ luminance_weights
        # light entering the front disc (before the lens path), for the culling bound
        incoming = (colour @ luminance_weights) * records.geometry
        is_flare = setup.path_is_flare[path] & setup.path_enabled[path]
        acc = eqx.tree_at(
            lambda a: (a.layers, a.path_energy, a.path_incoming, a.path_hits, a.path_passed, a.path_unevaluated, a.path_samples, a.weight_all, a.weight_hits),
            acc,
            (
                _splat(acc.layers, layer, records.column, records.row, value, hit),
                acc.path_energy.at[path].add(value),
                acc.path_incoming.at[path].add(incoming.astype(jnp.float32)),
                acc.path_hits.at[path].add(hit.astype(jnp.int32)),
                acc.path_passed.at[path].add(records.valid.astype(jnp.int32)),
                acc.path_unevaluated.at[path].add((~records.evaluated).astype(jnp.int32)),
                acc.path_samples.at[path].add(1),
                acc.weight_all + jnp.sum(jnp.where(is_flare, records.weight, 0.0)),
                acc.weight_hits + jnp.sum(jnp.where(flare, records.weight, 0.0)),
            ),
        )
        batch_luminance = _splat(batch_luminance, jnp.zeros_like(layer), records.column, records.row, lum[:, None], flare)
        if k < adaptive_count:
            energy = jnp.where(hit, lum, 0.0)
            acc = eqx.tree_at(lambda a: a.table_energy[k], acc, acc.table_energy[k].at[records.table_index].add(energy))
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
