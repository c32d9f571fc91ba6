"""Monte Carlo flare rendering (Pekkarinen & Balzer 2019, sections 2-4).

A sample connects a random point on a light with a random point on the front lens, picks a
wavelength, follows one lens path (a two-reflection ghost, or the primary path for the source's
own image) to the sensor, and is rejected by the clear apertures, the iris (the stop-plane
position of each pass) and the sensor bounds. Survivors are splatted bilinearly into the layer of
their path. Samples run in fixed-size vmapped batches (every path of a group at once), streamed
so memory stays bounded whatever the sample count.

Radiance per sample, the paper's equation (2): ``L(lambda) c_lens l F_lp w_s`` with

- ``L(lambda)``: the light's colour as a spectrum (:mod:`._colour`) times its intensity and the
  geometric factor of the light-lens connection (``cos cos / r^2`` times the sampled areas);
- ``c_lens = c_dirt c_coating``: dirt is 1 (no dirt map yet); ``c_coating`` is the product of the
  RGB tints of the path's two reflecting interfaces (1 unless the camera sets ``coating_tints``);
- ``l``: the cosine of the ray's angle with the sensor normal (Lambertian sensor response);
- ``F_lp``: the path's coated Fresnel factor at normal incidence and the sample's wavelength, times
  the Schlick angle term at the front lens, ``1 - (1 - cos theta)^5`` (the paper), or, with
  ``fresnel="exact"``, the coated Fresnel product at every event at the ray's own angles;
- ``w_s``: the normalised weight of equation (1), ``(1/p_s) / sum_i (1/p_i)``. Sampling is uniform
  per path here (adaptive sampling is a later step), so ``w_s`` is one over the number of samples
  of the path. The paper sums over the samples that hit the sensor, which keeps a flare's
  brightness when the iris blocks most of it; jaxflare sums over every sample drawn
  (``weights="all-samples"``), so stopping down dims flares as it does in a real lens, and offers
  the paper's normalisation as ``weights="sensor-hits"``.

Units (the paper leaves them as future work). A pixel holds the sensor irradiance it receives,
converted by the camera equation ``E = pi L / (4 N^2)`` into the scene radiance ``L`` that would
give the same irradiance through the lens at its working f-number N. So a flare pixel is directly
comparable with the main render: an extended light of radiance 100 makes a core of about 100 (less
the lens's transmission and vignetting), and its ghosts are that value times their energy fraction.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._colour import SpectralTable, blackbody_spectrum, canonical_colour_space, normalise_spectrum, spectral_table
from ._lens import Lens
from ._path_domain import entrance_plane_z_mm, front_rim_sag_mm
from ._scene import Scene, SceneError, camera_lens, light_travel_direction, load_scene, sensor_size_mm
from ._trace import _surface_sag_slope, _trace_events, ghost_paths, path_events

GhostPath = tuple[int, int]
POINT, SPHERE, DISK, DIRECTIONAL = 0, 1, 2, 3
_KINDS = {"point": POINT, "sphere": SPHERE, "disk": DISK, "directional": DIRECTIONAL}


class RenderWarning(UserWarning):
    """A render finished but something in it deserves attention (e.g. dropped samples)."""


@dataclasses.dataclass(frozen=True)
class Quality:
    """What a quality level spends: total Monte Carlo samples (spread evenly over the rendered
    paths), wavelength strata per batch, the polynomial degree and the sensor-position tolerance
    (in pixels of the render) a path system must meet to be used instead of exact tracing."""

    samples: int
    wavelength_strata: int
    degree: int
    tolerance_px: float
    pilot_fraction: float = 1 / 16


QUALITY_LEVELS = {
    "preview": Quality(samples=2**22, wavelength_strata=8, degree=5, tolerance_px=1.0),
    "production": Quality(samples=2**26, wavelength_strata=32, degree=5, tolerance_px=0.5),
}
RAYS_PER_STEP = 2**17
"""Rays per batch (all paths together): bounds the memory of one step."""


# --------------------------------------------------------------------------- set-up


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


class RenderSetup(eqx.Module):
    """Everything one render step reads: lens, path groups, lights, tables and image geometry."""

    lens: Lens
    groups: tuple
    """Path groups evaluated together: ``("exact", events (P, E, 4), path_index (P,))`` or
    ``("polynomial", stacked PathKernel, path_index (P,))``."""
    lights: LightArrays
    spectral: SpectralTable
    path_fresnel: Float[Array, "P L"]
    """Coated Fresnel factor of each path on the axis, per wavelength of the spectral grid."""
    path_tint: Float[Array, "P 3"]
    path_layer: Int[Array, " P"]
    front_radius_mm: Float[Array, ""]
    pixel_pitch_mm: Float[Array, ""]
    resolution: tuple[int, int] = eqx.field(static=True)
    num_layers: int = eqx.field(static=True)
    rays_per_path: int = eqx.field(static=True)
    wavelength_strata: int = eqx.field(static=True)
    schlick: bool = eqx.field(static=True)
    entrance_z_mm: float = eqx.field(static=True)
    front_z_range_mm: tuple[float, float] = eqx.field(static=True)


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
        kind = _KINDS[light.kind]
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


def _as_float32(tree):
    return jax.tree.map(lambda x: x.astype(jnp.float32) if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) else x, tree)


# --------------------------------------------------------------------------- one batch


def _sample_rays(setup: RenderSetup, key: Array, count: int):
    """``count`` light-to-front-lens connections: origins and directions in the lens frame, the
    wavelength, the chosen light and the flux weight (radiometric factor over the pdf)."""
    lights = setup.lights
    dtype = lights.axis.dtype
    k_light, k_light_point, k_front, k_wave = jax.random.split(key, 4)
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
    z_e = setup.entrance_z_mm
    z_low, z_high = setup.front_z_range_mm
    z_mid = 0.5 * (z_low + z_high)
    finite = kind != DIRECTIONAL
    towards_lens = jnp.array([0.0, 0.0, z_mid], dtype) - light_point
    distance = jnp.linalg.norm(towards_lens, axis=-1)
    central = jnp.where(finite[:, None], towards_lens / distance[:, None], cone_direction)
    tilt = central[:, :2] / central[:, 2:3]
    tilt_size = jnp.linalg.norm(tilt, axis=-1)
    front_r = setup.front_radius_mm
    parallax = jnp.where(finite, (z_high - z_e + 2 * front_r) * 2 * front_r / distance * (1 + tilt_size**2), 0.0)
    disc_radius = front_r * 1.02 + 0.5 * (z_high - z_low) * tilt_size + parallax
    disc_centre = -(z_mid - z_e) * tilt
    v = jax.random.uniform(k_front, (count, 2), dtype)
    rho = disc_radius * jnp.sqrt(v[:, 0])
    angle = 2 * jnp.pi * v[:, 1]
    front_xy = disc_centre + jnp.stack([rho * jnp.cos(angle), rho * jnp.sin(angle)], axis=-1)
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
    flux = geometry * lights.power[light] / lights.selection_probability[light]

    # stratified wavelengths: each stratum of the band gets the same number of samples per batch
    strata = setup.wavelength_strata
    grid = setup.spectral.wavelength_nm
    low, high = grid[0], grid[-1]
    stratum = jnp.arange(count) % strata
    wavelength = low + (high - low) * (stratum + jax.random.uniform(k_wave, (count,), dtype)) / strata
    return origins, directions, wavelength, light, flux


def _light_rgb(setup: RenderSetup, light: Array, wavelength: Array) -> Array:
    """RGB contribution per unit power of each sample's light at its wavelength (N, 3)."""
    from ._colour import rgb_response_at

    lights = setup.lights
    grid = setup.spectral.wavelength_nm
    response = rgb_response_at(setup.spectral, wavelength)  # (N, 3, 3)
    rgb = jnp.einsum("nij,nj->ni", response, lights.rgb[light])
    position = jnp.clip((wavelength - grid[0]) / (grid[1] - grid[0]), 0, grid.shape[0] - 1)
    below = jnp.clip(jnp.floor(position).astype(jnp.int32), 0, grid.shape[0] - 2)
    fraction = (position - below)[:, None]
    num_grid = grid.shape[0]
    table = lights.spectral_rgb.reshape(-1, 3)  # (NL * L, 3)
    row = light * num_grid + below
    spectral = table[row] * (1 - fraction) + table[row + 1] * fraction
    return jnp.where(lights.is_spectral[light][:, None], spectral, rgb)


def _front_cosine(lens: Lens, origins: Array, directions: Array) -> Array:
    """Cosine of the angle of incidence at the front surface (at the ray's crossing of its vertex plane)."""
    travel = -origins[:, 2] / directions[:, 2]
    x = origins[:, 0] + travel * directions[:, 0]
    y = origins[:, 1] + travel * directions[:, 1]
    _, g = _surface_sag_slope(x * x + y * y, lens.curvature_per_mm[0], lens.conic[0], lens.aspheric_coefficients[0])
    normal = jnp.stack([-g * x, -g * y, jnp.ones_like(x)], axis=-1)
    normal = normal / jnp.linalg.norm(normal, axis=-1, keepdims=True)
    return jnp.abs(jnp.sum(normal * directions, axis=-1))


def _interpolate_rows(table: Array, grid: Array, wavelength: Array) -> Array:
    """Linear interpolation of table (P, L) at wavelength (P, N) over the uniform grid."""
    position = jnp.clip((wavelength - grid[0]) / (grid[1] - grid[0]), 0, grid.shape[0] - 1)
    below = jnp.clip(jnp.floor(position).astype(jnp.int32), 0, grid.shape[0] - 2)
    fraction = position - below
    low = jnp.take_along_axis(table, below, 1)
    high = jnp.take_along_axis(table, below + 1, 1)
    return low * (1 - fraction) + high * fraction


def _evaluate_group(setup: RenderSetup, group, origins, directions, wavelength):
    """Trace a group's rays: returns sensor xy (P, n, 2), sensor-normal cosine, valid, throughput,
    and whether each ray was evaluated (False: untrusted polynomial input not re-traced)."""
    kind, data, _ = group
    if kind == "exact":

        def one(events, o, d, w):
            r = _trace_events(setup.lens, o, d, w, events, 1)
            return r.positions[:, :2], r.directions[:, 2], r.valid, r.throughput, jnp.ones_like(r.valid)

        return jax.vmap(one)(data, origins, directions, wavelength)
    from ._path_system import evaluate

    def one_polynomial(kernel, o, d, w):
        r = evaluate(kernel, o, d, w)
        return r.positions[:, :2], r.directions[:, 2], r.valid, r.throughput, r.trusted

    return jax.vmap(one_polynomial)(data, origins, directions, wavelength)


STEP_TRACES = [0]
"""How often the render step has been traced by JAX (tests use it to catch retracing)."""


def _render_step(setup: RenderSetup, buffer: Array, key: Array):
    """One batch: ``rays_per_path`` samples for every path; returns the buffer with the samples
    splatted, and per path the flux splatted (RGB), sensor hits, lens-valid rays and unevaluated rays."""
    STEP_TRACES[0] += 1
    width, height = setup.resolution
    n = setup.rays_per_path
    num_paths = setup.path_layer.shape[0]
    energy = jnp.zeros((num_paths, 3), buffer.dtype)
    hits = jnp.zeros(num_paths, jnp.int32)
    passed = jnp.zeros(num_paths, jnp.int32)
    unevaluated = jnp.zeros(num_paths, jnp.int32)
    grid = setup.spectral.wavelength_nm
    for group in setup.groups:
        path_index = group[2]
        # each path draws its own samples (keyed by the path, not the group), so a path sees the
        # same samples whichever way it is evaluated: common random numbers across methods
        keys = jax.vmap(lambda p: jax.random.fold_in(key, p))(path_index)
        origins, directions, wavelength, light, flux = jax.vmap(lambda k: _sample_rays(setup, k, n))(keys)
        rgb = jax.vmap(lambda l, w: _light_rgb(setup, l, w))(light, wavelength) * flux[..., None]
        shape = (path_index.shape[0], n)
        sensor_xy, cos_sensor, valid, throughput, evaluated = _evaluate_group(setup, group, origins, directions, wavelength)
        if setup.schlick:
            fresnel = _interpolate_rows(setup.path_fresnel[path_index], grid, wavelength)
            cos_front = _front_cosine(setup.lens, origins.reshape(-1, 3), directions.reshape(-1, 3)).reshape(shape)
            fresnel = fresnel * (1.0 - (1.0 - cos_front) ** 5)
        else:
            fresnel = throughput
        column = -sensor_xy[..., 0] / setup.pixel_pitch_mm + 0.5 * width
        row = sensor_xy[..., 1] / setup.pixel_pitch_mm + 0.5 * height
        on_sensor = (column >= 0) & (column < width) & (row >= 0) & (row < height)
        hit = valid & on_sensor
        weight = jnp.where(hit, fresnel * jnp.abs(cos_sensor), 0.0)
        value = rgb * weight[..., None] * setup.path_tint[path_index][:, None, :]
        value = jnp.where(hit[..., None], value, 0.0)
        layer = jnp.broadcast_to(setup.path_layer[path_index][:, None], shape)
        value = value.astype(buffer.dtype)
        buffer = _splat(buffer, layer.reshape(-1), column.reshape(-1), row.reshape(-1), value.reshape(-1, 3), hit.reshape(-1))
        energy = energy.at[path_index].add(jnp.sum(value, axis=1))
        hits = hits.at[path_index].add(jnp.sum(hit, axis=1, dtype=jnp.int32))
        passed = passed.at[path_index].add(jnp.sum(valid, axis=1, dtype=jnp.int32))
        unevaluated = unevaluated.at[path_index].add(jnp.sum(~evaluated, axis=1, dtype=jnp.int32))
    return buffer, energy, hits, passed, unevaluated


_STEP = eqx.filter_jit(_render_step)
_STEP_DONATING = eqx.filter_jit(_render_step, donate="all-except-first")
"""One compiled step per render structure (lens, path groups, lights, resolution, layers), shared
by every render with that structure. Accelerators update the image buffer in place (CPU XLA
cannot donate buffers)."""


def _splat(buffer: Array, layer: Array, column: Array, row: Array, value: Array, hit: Array) -> Array:
    """Bilinear splat (a tent filter one pixel wide; pixel centres at integer + 0.5)."""
    num_layers, height, width, _ = buffer.shape
    x = column - 0.5
    y = row - 0.5
    x0 = jnp.floor(x)
    y0 = jnp.floor(y)
    fx = x - x0
    fy = y - y0
    flat = buffer.reshape(-1, 3)
    outside = num_layers * height * width
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        xi = (x0 + dx).astype(jnp.int32)
        yi = (y0 + dy).astype(jnp.int32)
        # a sample near the border keeps its whole weight: what would fall off goes to the edge pixel
        xi = jnp.clip(xi, 0, width - 1)
        yi = jnp.clip(yi, 0, height - 1)
        index = jnp.where(hit, (layer * height + yi) * width + xi, outside)
        flat = flat.at[index].add((value * w[:, None]).astype(flat.dtype), mode="drop")
    return flat.reshape(buffer.shape)


def path_fresnel_table(lens: Lens, events: Array, wavelength_nm: Array) -> Array:
    """Coated Fresnel factor of each path (events (P, E, 4)) for the on-axis ray, per wavelength (P, L)."""
    count = wavelength_nm.shape[0]
    origins = jnp.zeros((count, 3), lens.thickness_mm.dtype).at[:, 2].set(-1.0)
    directions = jnp.zeros((count, 3), lens.thickness_mm.dtype).at[:, 2].set(1.0)
    return jax.vmap(lambda e: _trace_events(lens, origins, directions, wavelength_nm.astype(origins.dtype), e, 1).throughput)(events)


# --------------------------------------------------------------------------- results


@dataclasses.dataclass
class RenderResult:
    """A rendered flare.

    ``image``: (H, W, 4) linear RGBA of every flare together (alpha = min(1, max(R, G, B)); add the
    RGB to the plate). ``layers``: name -> (H, W, 3): ``core`` (the lights' primary images, not a
    flare), ``flare_J_I`` per flare with its own layer (ghost path (J, I)), ``flares_merged`` (all
    other flares). ``statistics``: samples, hit rate, per-path energies, times, settings.
    """

    image: np.ndarray
    layers: dict[str, np.ndarray]
    statistics: dict
    scene: Scene

    def write_exr(self, path, *, pixel_type: str | None = None, compression: str | None = None) -> str:
        """Multi-layer OpenEXR: the RGBA flare as the default layer plus every layer; lens, settings
        and statistics in the header (``jaxflare/...`` attributes). Written atomically."""
        import json
        import os

        from ._exr import write_exr

        settings = self.scene.render
        layers = {"": self.image}
        layers.update(self.layers)
        header = {
            "jaxflare/version": self.statistics.get("jaxflare_version", ""),
            "jaxflare/lens": self.statistics["lens"],
            "jaxflare/scene": self.scene.source or "",
            "jaxflare/settings": json.dumps(self.statistics["settings"]),
            "jaxflare/statistics": json.dumps({k: v for k, v in self.statistics.items() if k not in ("settings", "paths")}),
            "jaxflare/layers": json.dumps(self.statistics["layers"]),
        }
        write_exr(path, layers, pixel_type=pixel_type or settings.exr_pixel_type, compression=compression or settings.exr_compression, header=header)
        return os.fspath(path)

    def preview(self, *, include_core: bool = True, exposure_stops: float | None = None) -> np.ndarray:
        """A tone-mapped sRGB 8-bit preview of the flare (and the core)."""
        from ._colour import display_matrix
        from ._preview import tone_map

        flare = self.image[..., :3]
        if exposure_stops is None:  # expose for the flares: the core would otherwise set the exposure
            luminance = flare @ np.asarray(spectral_table(self.statistics["settings"]["colour_space"]).luminance_weights)
            lit = luminance[luminance > 0]
            level = float(np.percentile(lit, 99.5)) if lit.size else 0.0
            exposure_stops = math.log2(4.0 / level) if level > 0 else 0.0
        rgb = flare + (self.layers["core"] if include_core and "core" in self.layers else 0.0)
        return tone_map(rgb, to_srgb_matrix=display_matrix(self.statistics["settings"]["colour_space"]), exposure_stops=exposure_stops)

    def write_png(self, path, **options) -> str:
        import os

        from ._preview import write_png

        write_png(path, self.preview(**options))
        return os.fspath(path)


# --------------------------------------------------------------------------- the renderer


def _field_angle_deg(lights: LightArrays, front_radius_mm: float) -> float:
    """Largest angle to the axis of any ray from the flare lights to the front lens (degrees)."""
    axis = np.asarray(lights.axis)
    angles = np.degrees(np.arccos(np.clip(axis[:, 2], -1, 1)))
    spread = np.degrees(np.arccos(np.clip(np.asarray(lights.cone_cos), -1, 1)))
    distance = np.linalg.norm(np.asarray(lights.centre_mm), axis=-1)
    finite = np.asarray(lights.kind) != DIRECTIONAL
    size = np.where(finite, np.degrees(np.arctan2(np.asarray(lights.radius_mm) + front_radius_mm, np.maximum(distance, 1.0))), 0.0)
    return float(np.max(angles + spread + size))


def _choose_paths(lens: Lens, paths) -> list[GhostPath]:
    if paths is None:
        return ghost_paths(lens)
    from ._trace import _check_path

    chosen = []
    for path in paths:
        if path is None:
            raise ValueError("paths: list ghost paths (j, i) only; the primary path is rendered as the core layer (render.core)")
        chosen.append(_check_path(lens, path))
    if not chosen or len(set(chosen)) != len(chosen):
        raise ValueError(f"paths: must be a non-empty list of distinct ghost paths (j, i), got {paths!r}")
    return chosen


def _build_kernels(lens, geometry_lens, paths, quality, pitch_mm, field_deg, progress):
    """Polynomial path systems of every path, built over the field the lights use to the
    render's pixel tolerance, as float32 kernels on the render lens (iris, coatings)."""
    from ._path_build import path_system

    domain_field = min(85.0, 5.0 * math.ceil((field_deg + 1.0) / 5.0))
    iterator = range(len(paths))
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc="path systems", unit="path", leave=False)
    kernels, reports = [], []
    for k in iterator:
        system = path_system(
            geometry_lens, paths[k], degree=quality.degree, max_field_angle_deg=domain_field, tolerance_mm=quality.tolerance_px * pitch_mm,
        )
        reports.append(system.report)
        kernels.append(_as_float32(system.with_lens(lens)))
    return kernels, reports


FALLBACK_CAPACITIES = (0.125, 0.25, 0.5, 1.0)
"""Exact-fallback capacities (fractions of a batch) a polynomial path can get."""
AUTO_MAX_FALLBACK = 0.25
"""``method="auto"``: a path whose polynomial does not trust more than this fraction of the
scene's samples (measured in the pilot) is traced exactly instead: beyond it, polynomial plus
fallback costs about as much as exact tracing (measured: degree-5 systems are 1.6-5.6x faster
than the exact tracer on CPU)."""


def _groups(lens, paths, kernels, fallback_of_path):
    """Group the paths by how they are evaluated: polynomial kernels with the same structure (and
    fallback capacity) together, every exactly traced path in one group."""
    groups, by_signature, exact_index = [], {}, []
    for k, path in enumerate(paths):
        fallback = fallback_of_path[k]
        if fallback == "exact":
            exact_index.append(k)
            continue
        system = kernels[k]
        kernel = system.kernel(fallback="none") if fallback == 0 else dataclasses.replace(system, fallback_fraction=fallback).kernel(fallback="exact")
        leaves, treedef = jax.tree.flatten(kernel)
        signature = (treedef, tuple((x.shape, x.dtype) for x in leaves))
        by_signature.setdefault(signature, []).append((k, kernel))
    for members in by_signature.values():
        stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *[kernel for _, kernel in members])
        groups.append(("polynomial", stacked, jnp.asarray([k for k, _ in members], jnp.int32)))
    if exact_index:
        events = jnp.asarray(np.stack([path_events(lens, paths[k]) for k in exact_index]))
        groups.append(("exact", events, jnp.asarray(exact_index, jnp.int32)))
    return groups


def _canonical_settings(scene: Scene, quality: str | None, samples: int | None, method: str | None):
    settings = scene.render
    overrides = {}
    if quality is not None:
        overrides["quality"] = quality
    if samples is not None:
        overrides["samples"] = samples
    if method is not None:
        overrides["method"] = method
    settings = dataclasses.replace(settings, **overrides)
    from ._scene import check_settings

    check_settings(settings, "render")
    return settings


def render(
    scene: Scene | str,
    quality: str | None = None,
    seed: int = 0,
    *,
    samples: int | None = None,
    method: str | None = None,
    paths: Sequence[GhostPath] | None = None,
    progress: bool | Callable[[int, int], None] = False,
) -> RenderResult:
    """Render the flares of ``scene`` (a :class:`Scene` or a scene TOML path).

    Args:
        scene: the scene; its ``render`` settings apply unless overridden here.
        quality: ``"preview"`` or ``"production"`` (see :data:`QUALITY_LEVELS`); default the scene's.
        seed: random seed; the same seed gives the same image.
        samples: total Monte Carlo samples (default the quality's), spread evenly over the paths.
        method: ``"auto"``, ``"polynomial"`` or ``"exact"`` (default the scene's).
        paths: render only these ghost paths ``(j, i)`` (default: every two-reflection path).
        progress: True for a progress bar on stderr, or a callable ``(batches_done, batches)``.

    Returns:
        A :class:`RenderResult` (image, layers, statistics; ``write_exr``/``write_png``).
    """
    started = time.perf_counter()
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    settings = _canonical_settings(scene, quality, samples, method)
    level = QUALITY_LEVELS[settings.quality.lower()]
    total_samples = settings.samples or level.samples
    method_name = settings.method.lower()
    colour_space = canonical_colour_space(settings.colour_space)
    camera = scene.camera
    width, height = camera.resolution

    lens = camera_lens(camera)
    fresnel_exact = settings.fresnel.lower() == "exact"
    geometry_lens = camera_lens(camera, with_iris=False, with_coatings=fresnel_exact)
    sensor_w, _ = sensor_size_mm(camera, lens)
    pitch = sensor_w / width
    spectral = spectral_table(colour_space)
    lights, light_indices = light_arrays(scene, spectral)
    field_deg = _field_angle_deg(lights, float(lens.semi_aperture_mm[0]))

    flare_paths = _choose_paths(lens, paths)
    paths: list[GhostPath | None] = list(flare_paths) + ([None] if settings.core else [])
    if method_name == "exact":
        kernels, reports = [None] * len(paths), [None] * len(paths)
        pilot_fallback = ["exact"] * len(paths)
    else:
        kernels, reports = _build_kernels(lens, geometry_lens, paths, level, pitch, field_deg, progress is True)
        pilot_fallback = [0] * len(paths)  # the pilot measures which samples each polynomial trusts
    groups = _groups(lens, paths, kernels, pilot_fallback)
    build_seconds = time.perf_counter() - started

    lens32 = _as_float32(lens)
    events_all = jnp.asarray(np.stack([path_events(lens, p) for p in paths]))
    fresnel_table = path_fresnel_table(lens32, events_all, jnp.asarray(spectral.wavelength_nm, jnp.float32))
    tints = np.ones((lens.num_interfaces, 3))
    for interface, rgb in camera.coating_tints:
        tints[interface] = rgb
    path_tint = np.stack([tints[p[0]] * tints[p[1]] if p is not None else np.ones(3) for p in paths])

    num_flares = len(flare_paths)
    num_individual = min(settings.max_flare_layers, num_flares)
    merged_layer = num_individual
    core_layer = num_individual + 1
    num_layers = num_individual + 1 + (1 if settings.core else 0)
    rays_per_path = int(max(256, min(8192, 2 ** round(math.log2(max(1, RAYS_PER_STEP // len(paths)))))))
    rays_per_path -= rays_per_path % level.wavelength_strata
    z_rim = front_rim_sag_mm(lens)

    def make_setup(layer_of_path):
        return _as_float32(
            RenderSetup(
                lens=lens, groups=tuple(groups), lights=lights, spectral=spectral, path_fresnel=fresnel_table,
                path_tint=jnp.asarray(path_tint), path_layer=jnp.asarray(layer_of_path, jnp.int32),
                front_radius_mm=jnp.asarray(float(lens.semi_aperture_mm[0])), pixel_pitch_mm=jnp.asarray(pitch),
                resolution=(width, height), num_layers=num_layers, rays_per_path=rays_per_path,
                wavelength_strata=level.wavelength_strata, schlick=not fresnel_exact,
                entrance_z_mm=entrance_plane_z_mm(lens), front_z_range_mm=(min(0.0, z_rim), max(0.0, z_rim)),
            )
        )

    setup = make_setup(np.zeros(len(paths)))
    step = _STEP_DONATING if jax.default_backend() != "cpu" else _STEP
    key = jax.random.PRNGKey(seed)
    buffer_shape = (num_layers, height, width, 3)

    # pilot: a few batches to measure each flare's energy, which decides the layers
    samples_per_path = max(rays_per_path, total_samples // len(paths))
    batches = max(1, math.ceil(samples_per_path / rays_per_path))
    pilot_batches = max(1, math.ceil(batches * level.pilot_fraction))
    pilot_energy = np.zeros((len(paths), 3))
    compile_started = time.perf_counter()
    pilot_untrusted = np.zeros(len(paths))
    scratch = jnp.zeros(buffer_shape, jnp.float32)
    for b in range(pilot_batches):
        scratch, energy, _, _, untrusted = step(setup, scratch, jax.random.fold_in(jax.random.fold_in(key, 1), b))
        pilot_energy += np.asarray(energy, np.float64)
        pilot_untrusted += np.asarray(untrusted, np.float64)
        if b == 0:
            jax.block_until_ready(energy)
            compile_seconds = time.perf_counter() - compile_started
    del scratch
    # each polynomial path gets the smallest exact fallback that covers the samples it does not
    # trust (with a margin); "auto" traces a path exactly when that would need too large a fallback
    untrusted_fraction = pilot_untrusted / (pilot_batches * rays_per_path)
    fallback_of_path = ["exact"] * len(paths)
    if method_name != "exact":
        for k, fraction in enumerate(untrusted_fraction):
            needed = 0 if fraction == 0 else next((c for c in FALLBACK_CAPACITIES if 1.5 * fraction <= c), 1.0)
            if method_name == "polynomial" or needed <= AUTO_MAX_FALLBACK:
                fallback_of_path[k] = needed
        setup = eqx.tree_at(lambda d: d.groups, setup, tuple(_as_float32(_groups(lens, paths, kernels, fallback_of_path))))
    methods = ["exact" if f == "exact" else "polynomial" for f in fallback_of_path]
    luminance = np.asarray(spectral.luminance_weights, np.float64)
    flare_energy = pilot_energy[:num_flares] @ luminance
    order = np.argsort(-flare_energy)
    brightest = flare_energy[order[0]] if num_flares else 0.0
    layer_of_path = np.full(len(paths), merged_layer)
    own = [k for k in order[:num_individual] if brightest > 0 and flare_energy[k] >= settings.layer_threshold * brightest]
    own.sort(key=lambda k: -flare_energy[k])
    for slot, k in enumerate(own):
        layer_of_path[k] = slot
    if settings.core:
        layer_of_path[-1] = core_layer
    setup = eqx.tree_at(lambda d: d.path_layer, setup, jnp.asarray(layer_of_path, jnp.int32))

    # the render
    render_started = time.perf_counter()
    buffer = jnp.zeros(buffer_shape, jnp.float32)
    totals = [np.zeros((len(paths), 3)), np.zeros(len(paths)), np.zeros(len(paths)), np.zeros(len(paths))]
    bar = None
    if progress is True:
        from tqdm import tqdm

        bar = tqdm(total=batches, desc="rendering", unit="batch", leave=False)
    for b in range(batches):
        buffer, *counts = step(setup, buffer, jax.random.fold_in(jax.random.fold_in(key, 2), b))
        for total, count in zip(totals, counts):
            total += np.asarray(count, np.float64)
        if bar is not None:
            bar.update(1)
        elif callable(progress):
            progress(b + 1, batches)
    if bar is not None:
        bar.close()
    image_sum = np.asarray(buffer, np.float64)
    dropped = float(totals[3].sum() / (batches * rays_per_path * len(paths)))
    if dropped > 0.01:
        import warnings

        warnings.warn(
            f"{dropped:.1%} of the samples were dropped: their path systems do not trust them and the exact "
            "fallback was full. Their light is missing from the image; render with method='auto' or 'exact'.",
            RenderWarning,
            stacklevel=2,
        )
    render_seconds = time.perf_counter() - render_started
    energy, hits, passed, unevaluated = totals

    # normalisation: mean over each path's samples, per unit pixel area, as camera-equation radiance
    per_path_samples = batches * rays_per_path
    f_number = lens.f_number()
    to_radiance = 4.0 * f_number**2 / math.pi / (pitch * pitch)
    scale = np.full(num_layers, to_radiance / per_path_samples)
    flare_hits = hits[:num_flares].sum()
    if settings.weights.lower() == "sensor-hits":
        scale[: num_individual + 1] *= (num_flares * per_path_samples) / max(flare_hits, 1.0)
        if settings.core:
            scale[core_layer] *= per_path_samples / max(hits[-1], 1.0)
    layers_array = (image_sum * scale[:, None, None, None]).astype(np.float32)
    if not np.all(np.isfinite(layers_array)):
        raise FloatingPointError("the render produced non-finite pixels; please report this scene")

    layers: dict[str, np.ndarray] = {}
    layer_info = []
    for slot, k in enumerate(own):
        name = f"flare_{paths[k][0]:02d}_{paths[k][1]:02d}"
        layers[name] = layers_array[slot]
        layer_info.append(dict(layer=name, paths=[list(paths[k])]))
    merged_paths = [list(paths[k]) for k in range(num_flares) if layer_of_path[k] == merged_layer]
    layers["flares_merged"] = layers_array[merged_layer]
    layer_info.append(dict(layer="flares_merged", paths=merged_paths))
    if settings.core:
        layers["core"] = layers_array[core_layer]
        layer_info.append(dict(layer="core", paths=["primary"]))
    flare_rgb = sum(layers_array[slot] for slot in range(num_individual + 1))
    image = np.concatenate([flare_rgb, np.clip(np.max(flare_rgb, axis=-1, keepdims=True), 0.0, 1.0)], axis=-1).astype(np.float32)

    path_energy = energy * scale[layer_of_path][:, None] * pitch * pitch  # radiance x mm^2: pixel sums x pixel area
    drawn = per_path_samples * len(paths)
    from . import __version__

    statistics = dict(
        jaxflare_version=__version__,
        lens=lens.name,
        resolution=[width, height],
        samples=int(drawn),
        pilot_samples=int(pilot_batches * rays_per_path * len(paths)),
        samples_per_path=int(per_path_samples),
        batches=int(batches),
        rays_per_batch=int(rays_per_path * len(paths)),
        flare_paths=num_flares,
        paths_rendered=len(paths),
        polynomial_paths=int(sum(m == "polynomial" for m in methods)),
        exact_paths=int(sum(m == "exact" for m in methods)),
        lens_pass_rate=float(passed[:num_flares].sum() / max(1, num_flares * per_path_samples)),
        sensor_hit_rate=float(flare_hits / max(1, num_flares * per_path_samples)),
        core_hit_rate=float(hits[-1] / per_path_samples) if settings.core else None,
        unevaluated_fraction=float(unevaluated.sum() / drawn),
        f_number=float(f_number),
        pixel_pitch_mm=float(pitch),
        field_angle_deg=float(field_deg),
        lights=[scene.lights[k].name or f"light[{k}]" for k in light_indices],
        layers=layer_info,
        setup_seconds=float(build_seconds),
        compile_seconds=float(compile_seconds),
        render_seconds=float(render_seconds),
        total_seconds=float(time.perf_counter() - started),
        settings=dict(
            quality=settings.quality, method=method_name, fresnel=settings.fresnel.lower(), weights=settings.weights.lower(),
            colour_space=colour_space, seed=int(seed), wavelength_strata=level.wavelength_strata, degree=level.degree,
            tolerance_px=level.tolerance_px, f_number=camera.f_number, aperture_blades=lens.aperture_blades,
        ),
        paths=[
            dict(
                path="primary" if p is None else list(p), method=methods[k],
                energy=float(path_energy[k] @ luminance), rgb=[float(v) for v in path_energy[k]],
                hit_rate=float(hits[k] / per_path_samples),
                polynomial_validation_trusted_fraction=None if reports[k] is None else float(reports[k].trusted_fraction),
                polynomial_untrusted_sample_fraction=None if reports[k] is None else float(untrusted_fraction[k]),
                exact_fallback_capacity=None if fallback_of_path[k] == "exact" else float(fallback_of_path[k]),
            )
            for k, p in enumerate(paths)
        ],
    )
    return RenderResult(image=image, layers=layers, statistics=statistics, scene=scene)
