"""Planning and running a grid render (the deterministic estimator, :mod:`._grid`).

:func:`plan_grid` reads the scene like :func:`~._plan.plan_render` (lens, lights, paths, layers,
culling), runs the grid pilot and decides every path's jobs; :func:`render_grid` traces and
splats them and returns the same :class:`~._result.RenderResult` (the same EXR layers) as the
Monte Carlo renderer.
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from ..colour import canonical_colour_space, spectral_table
from ..optics import EventTable, GhostPath, Lens, cast_floating, on_axis_fresnel, path_events, stop_pass_count
from ..scenes import LightKind, RenderSettings, Scene, camera_lens, load_scene, sensor_size_mm
from ._grid import (
    BLUR_DENSITY,
    EDGE_ERROR,
    GRID_QUALITY,
    GridJob,
    GridQuality,
    PreparedSplat,
    prepare_splat,
    splat_jobs,
    splat_prepared,
    trace_jobs,
    traced_wavelengths,
)
from ._grid_cells import cell_pieces, round_sub_nodes, summarise_cells
from ._grid_blur import BLUR_MAX_PX, BLUR_MIN_PX, BLUR_SPACING, blur_border, light_jacobian_px
from ._grid_refine import refine_mixed_cells, refined_edge_side
from ._grid_splat import COMPOSE_LAYERS, COMPOSE_LEVELS, LEVELS
from ._grid_trace import SENSOR
from ._lights import LightArrays, light_arrays
from ._plan import CullingPlan, LayerPlan, assign_layers, choose_paths, light_field_angle_deg, path_tints, render_settings
from ._quality import QUALITY_LEVELS, radiance_scale
from ._sampling import front_disc
from ._step import RenderSetup
from .effects import SceneEffects, scene_effects

MIN_MOTION_PX = 0.3
"""A light whose disc moves a path's image less than this (level pixels) is traced as a point."""


@dataclasses.dataclass(frozen=True)
class PathPlan:
    """What the pilot decided for one path (all its lights)."""

    level: int
    """Index into :data:`LEVELS`."""
    cells: int
    sub_nodes: int
    energy: float
    bound: float
    streak_px: float
    motion_px: float
    curvature_px: float
    estimated_error: float
    """Its share of the error model's squared relative error (at its level)."""


@dataclasses.dataclass
class GridPlan:
    """A grid render, decided (the fields :func:`render_result` reads, like a RenderPlan's)."""

    scene: Scene
    settings: RenderSettings
    quality_name: str
    grid: GridQuality
    seed: int
    colour_space: str
    lens: Lens
    pixel_pitch_mm: float
    spectral: object
    lights: LightArrays
    light_indices: tuple[int, ...]
    field_angle_deg: float
    paths: tuple[GhostPath | None, ...]
    num_flares: int
    events: list[np.ndarray]
    culling: CullingPlan
    layers: LayerPlan
    path_plans: list[PathPlan]
    jobs: list[GridJob]
    setup: RenderSetup
    path_fresnel: jax.Array
    wavelengths: np.ndarray
    pilot_subsamples: int
    pilot_rays: int
    estimated_error: float
    setup_seconds: float
    pilot_seconds: float
    started: float

    @property
    def luminance_weights(self) -> np.ndarray:
        return np.asarray(self.spectral.luminance_weights, np.float64)


CURVATURE_PERCENTILE = 90
"""A path's map bends by the this-percentile of its pilot's second differences (the grid's cells
are sized for it; the few most bent cells are resolved by the iris and rim clipping, or are off
the image)."""
MIN_BENDS = 16
"""Fewer second differences than this in the pilot: the path gets a second pilot over its domain."""


def second_differences(sensor_px: np.ndarray, passing: np.ndarray, cell_u: float, cell_v: float) -> np.ndarray:
    """Lengths (px) of the second differences of the image positions at the middle traced
    wavelength along both grid directions, between vertices that pass, per *pilot cell* squared
    (a grid whose cells are ``cell_u`` x ``cell_v`` pilot cells scales them by 1 / cell^2)."""
    middle, ok = sensor_px[0, sensor_px.shape[1] // 2], passing[passing.shape[0] // 2]
    d2u = np.linalg.norm(middle[:, 2:] - 2 * middle[:, 1:-1] + middle[:, :-2], axis=-1)[ok[:, 2:] & ok[:, 1:-1] & ok[:, :-2]]
    d2v = np.linalg.norm(middle[2:] - 2 * middle[1:-1] + middle[:-2], axis=-1)[ok[2:] & ok[1:-1] & ok[:-2]]
    return np.concatenate([d2u / max(cell_u, 1e-12) ** 2, d2v / max(cell_v, 1e-12) ** 2])


def cell_flux_areas(summary, energy: float, px_per_pilot_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Each passing pilot cell's share of a job's ``energy`` (even shares) and the area of its
    image (full-resolution px^2, middle traced wavelength): where the map compresses a cell into
    a pixel or two (a caustic, a ghost focused near the sensor) the irradiance peaks far above
    what the pilot's 16 px image shows."""
    ok = summary.passing[summary.passing.shape[0] // 2]
    cell_ok = ok[1:, 1:] & ok[:-1, :-1] & ok[:-1, 1:] & ok[1:, :-1]
    if energy <= 0 or not cell_ok.any():
        return np.zeros(0), np.zeros(0)
    area = summary.image_area_px[cell_ok] * px_per_pilot_px**2
    return np.full(area.shape, energy / area.size), area


def compression_error2(compressed, level_px: int) -> float:
    """Squared error (sum over full-resolution pixels) of drawing cells of flux F and image area
    a at ``level_px``-pixel resolution: a cell smaller than a level pixel loses its peak, F^2 (1/a
    - 1/l^2) (a and l^2 at least one pixel)."""
    total = 0.0
    for flux, area in compressed:
        a = np.maximum(area, 1.0)
        total += float(np.sum(flux**2 * np.maximum(1.0 / a - 1.0 / np.maximum(a, level_px**2), 0.0)))
    return total


def grid_setup(lens, lights, front, spectral, effects, fresnel, tint, layer, flare, enabled, pitch, resolution, schlick) -> RenderSetup:
    return cast_floating(
        RenderSetup(
            lens=lens, lights=lights, front=front, spectral=spectral, path_sets=(), effects=effects,
            path_fresnel=jnp.asarray(fresnel), path_tint=jnp.asarray(tint), path_layer=jnp.asarray(layer, jnp.int32),
            path_is_flare=jnp.asarray(flare), path_enabled=jnp.asarray(enabled, bool), pixel_pitch_mm=jnp.asarray(pitch),
            resolution=resolution, wavelength_strata=1, schlick=schlick,
        ),
        jnp.float32,
    )


def light_is_extended(lights: LightArrays, k: int) -> bool:
    kind = int(lights.kind[k])
    if kind == LightKind.DIRECTIONAL:
        return float(lights.cone_cos[k]) < 1.0
    return kind in (LightKind.SPHERE, LightKind.DISK) and float(lights.radius_mm[k]) > 0


def plan_grid(
    scene: Scene | str, quality: str | None = None, seed: int = 0, *, paths=None, grid_error: float | None = None, progress: bool = False,
    grid_options: dict | None = None,
) -> GridPlan:
    """Everything before the grid render's main pass: scene, lens, lights, paths, the pilot and
    each path's jobs (arguments as for :func:`jaxflare.render`). ``grid_error`` overrides the
    quality's target relative error; ``grid_options`` overrides any :class:`GridQuality` field
    (e.g. ``spacing_px``, ``max_sub_nodes``, ``max_cells``) by name."""
    started = time.perf_counter()
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    settings = render_settings(scene, quality, None, None)
    grid = GRID_QUALITY[settings.quality]
    if grid_error is not None:
        grid = dataclasses.replace(grid, target_error=float(grid_error))
    if grid_options:
        unknown = sorted(set(grid_options) - {f.name for f in dataclasses.fields(GridQuality)})
        if unknown:
            raise ValueError(f"grid_options: unknown {unknown}; valid: {[f.name for f in dataclasses.fields(GridQuality)]}")
        grid = dataclasses.replace(grid, **grid_options)
    colour_space = canonical_colour_space(settings.colour_space)
    camera = scene.camera
    width, height = camera.resolution
    lens = camera_lens(camera)
    sensor_w, _ = sensor_size_mm(camera, lens)
    pitch = sensor_w / width
    spectral = spectral_table(colour_space)
    band = spectral.band_nm
    lights, light_indices = light_arrays(scene, spectral)
    field_deg = light_field_angle_deg(lights, float(lens.semi_aperture_mm[0]))
    flare_paths = choose_paths(lens, paths)
    paths_all: list[GhostPath | None] = list(flare_paths) + ([None] if settings.core else [])
    num_paths, num_flares = len(paths_all), len(flare_paths)
    num_lights = int(lights.kind.shape[0])
    schlick = settings.fresnel != "exact"

    lens32 = cast_floating(lens, jnp.float32)
    events = [path_events(lens, p) for p in paths_all]
    passes = [stop_pass_count(e, lens.stop_index) for e in events]
    fresnel = on_axis_fresnel(lens32, EventTable.from_array(np.stack(events)), jnp.asarray(spectral.wavelength_nm, jnp.float32))
    tint = path_tints(camera, lens.num_interfaces, paths_all)
    front = front_disc(lens)
    effects = scene_effects(scene, lens, pitch)
    is_flare = np.asarray([p is not None for p in paths_all])
    setup_seconds = time.perf_counter() - started

    # ---------------------------------------------------------------- the pilot
    pilot_started = time.perf_counter()
    scale = grid.pilot_level
    pilot_w, pilot_h = -(-width // scale), -(-height // scale)
    pilot_pitch = sensor_w / pilot_w
    pilot_effects = SceneEffects(
        dirt=effects.dirt, hood=effects.hood, occluders=effects.occluders, camera_position_m=effects.camera_position_m,
        camera_to_world=effects.camera_to_world, distortion=None,
    )
    pilot_setup = grid_setup(
        lens, lights, front, spectral, pilot_effects, fresnel, tint, np.zeros(num_paths), is_flare, np.ones(num_paths, bool), pilot_pitch,
        (pilot_w, pilot_h), schlick,
    )
    pilot_nodes = traced_wavelengths(3, band)
    pilot_jobs = []
    for k in range(num_paths):
        for light in range(num_lights):
            n = grid.pilot_cells
            pilot_jobs.append(
                GridJob(
                    path=k, slot=len(pilot_jobs), light=light, layer=len(pilot_jobs), level=0, passes=passes[k], domain=(-1.0, -1.0, 2.0 / n, 2.0 / n),
                    cells=n, step=1.0 if light_is_extended(lights, light) else 0.0, sub_nodes=1, max_side=4, spacing_px=1.0,
                )
            )
    rows, host_rows = trace_jobs(pilot_setup, lens32, pilot_jobs, events, pilot_nodes)
    distortion = effects.distortion is not None
    pilot_summaries = [summarise_cells(job, host_rows, 3, lens32, pilot_pitch, pilot_w, pilot_h, False) for job in pilot_jobs]
    pilot_pieces = [cell_pieces(job, s, lens32, pilot_w, pilot_h, False, 1.0, 1, 1.0) for job, s in zip(pilot_jobs, pilot_summaries)]
    acc, pilot_subsamples, _ = splat_jobs(pilot_setup, pilot_jobs, rows, pilot_pieces, pilot_nodes, fresnel, band, len(pilot_jobs), len(pilot_jobs))
    luminance = np.asarray(spectral.luminance_weights, np.float64)
    pilot_energy = np.asarray(acc.path_energy, np.float64) @ luminance
    pilot_bound = np.asarray(acc.path_bound, np.float64) @ luminance
    images = np.asarray(COMPOSE_LEVELS(acc.buffer, pilot_w, pilot_h), np.float64) @ luminance  # (J, h, w)
    pilot_seconds = time.perf_counter() - pilot_started

    # ---------------------------------------------------------------- culling and layers
    energy = pilot_energy.reshape(num_paths, num_lights).sum(axis=1)
    bound = pilot_bound.reshape(num_paths, num_lights).sum(axis=1)
    brightest = float(energy[:num_flares].max()) if num_flares else 0.0
    enabled = energy > 0  # a path whose pilot saw nothing: its bound is zero too (no cell may carry light)
    enabled |= bound > 0
    if settings.cull_threshold > 0 and brightest > 0:
        enabled[:num_flares] &= bound[:num_flares] >= settings.cull_threshold * brightest
    culled = float(bound[:num_flares][~enabled[:num_flares]].sum())
    culling = CullingPlan(enabled=enabled, energy_bound=bound, brightest_energy=brightest, culled_energy_bound=culled)
    layers = assign_layers(energy, culling, num_flares, settings)

    # ---------------------------------------------------------------- each path's level, grid and sub-nodes
    area_scale = (width / pilot_w) * (height / pilot_h)
    flare_jobs = [j for j, job in enumerate(pilot_jobs) if is_flare[job.path]]
    total_image = images[flare_jobs].sum(axis=0) if flare_jobs else np.zeros((pilot_h, pilot_w))
    norm2 = float(np.sum(total_image**2)) / area_scale
    budget = (0.7 * grid.target_error) ** 2 * norm2
    per_path = []
    for k in range(num_paths):
        members = [j for j, job in enumerate(pilot_jobs) if job.path == k]
        image = images[members].sum(axis=0)
        gy, gx = np.gradient(image)
        edge = float(np.sum(np.hypot(gx, gy) * np.abs(image))) / math.sqrt(area_scale) ** 3
        compressed = [cell_flux_areas(pilot_summaries[j], float(images[j].sum()), width / pilot_w) for j in members]
        coverage = float(np.count_nonzero(image > 1e-6 * max(image.max(), 1e-300))) * area_scale
        streak = motion = 0.0
        bends = []
        extent = [0, grid.pilot_cells, 0, grid.pilot_cells]
        kept_any = False
        for j in members:
            s = pilot_summaries[j]
            px = s.sensor_px * (width / pilot_w)
            passing = s.passing
            if passing.any():
                streak = max(streak, float(np.linalg.norm(px[0, -1] - px[0, 0], axis=-1)[passing[0] & passing[-1]].max(initial=0.0)))
                bends.append(second_differences(px, passing, 1.0, 1.0))
            motion = max(motion, s.motion_px * (width / pilot_w))
            if s.kept.any():
                rows_kept, cols_kept = np.nonzero(s.kept)
                box = [cols_kept.min(), cols_kept.max() + 1, rows_kept.min(), rows_kept.max() + 1]
                extent = box if not kept_any else [min(extent[0], box[0]), max(extent[1], box[1]), min(extent[2], box[2]), max(extent[3], box[3])]
                kept_any = True
        bends = np.concatenate(bends) if bends else np.zeros(0)
        curvature = float(np.percentile(bends, CURVATURE_PERCENTILE)) if bends.size else 0.0
        per_path.append(
            {"edge": edge, "compressed": compressed, "coverage": coverage, "streak": streak, "motion": motion, "curvature": curvature, "bends": bends.size, "extent": extent, "kept": kept_any}
        )

    # a path seen through too few pilot vertices to tell how its map bends (a small entrance domain)
    # gets a second pilot over its own domain: with a guessed curvature of 0 it would be drawn with
    # the fewest cells, and a bilinear cell far too large for the map folds its light into a spike
    # (measured: 5 % of a ghost's energy in 10 pixels of the demo, 4 % too much in total)
    closer = [k for k in range(num_paths) if enabled[k] and per_path[k]["kept"] and per_path[k]["bends"] < MIN_BENDS]
    if closer:
        pilot_cell = 2.0 / grid.pilot_cells
        zoom_jobs = []
        for k in closer:
            c0, c1, r0, r1 = per_path[k]["extent"]
            n = grid.pilot_cells
            du, dv = (c1 - c0) * pilot_cell / n, (r1 - r0) * pilot_cell / n
            for light in range(num_lights):
                zoom_jobs.append(
                    GridJob(
                        path=k, slot=len(zoom_jobs), light=light, layer=len(zoom_jobs), level=0, passes=passes[k],
                        domain=(-1.0 + c0 * pilot_cell, -1.0 + r0 * pilot_cell, du, dv), cells=n, sub_nodes=1, max_side=4, spacing_px=1.0,
                    )
                )
        _, zoom_rows = trace_jobs(pilot_setup, lens32, zoom_jobs, events, pilot_nodes)
        for k in closer:
            c0, c1, r0, r1 = per_path[k]["extent"]
            scale_u, scale_v = (c1 - c0) / grid.pilot_cells, (r1 - r0) / grid.pilot_cells  # zoomed cell, in pilot cells
            bends = []
            for job in (j for j in zoom_jobs if j.path == k):
                s = summarise_cells(job, zoom_rows, 3, lens32, pilot_pitch, pilot_w, pilot_h, False)
                bends.append(second_differences(s.sensor_px * (width / pilot_w), s.passing, scale_u, scale_v))
            bends = np.concatenate(bends)
            if bends.size:
                per_path[k]["curvature"] = float(np.percentile(bends, CURVATURE_PERCENTILE))
            per_path[k]["bends"] = bends.size

    def sub_nodes_at(k, level):
        return round_sub_nodes(per_path[k]["streak"] / LEVELS[level], grid.max_sub_nodes)

    def cost(k, level):
        scale_px = LEVELS[level]
        return per_path[k]["coverage"] / (scale_px * grid.spacing_px) ** 2 * sub_nodes_at(k, level)

    # the error model (squared error of path k drawn at a level): its edges blurred over a level
    # pixel (the pilot image's edge term) and its compressed cells' peaks lost (a caustic the
    # 16 px pilot image cannot see). Not modelled: the cells' bilinear interpolation (cells
    # capped at max_cells), the colour steps (fringe_px, colour_error), sub-sample spacing; the
    # wide-angle benchmark scene, whose ghosts bend most, is where these show (see benchmarks/README.md)
    # (made once per path and level: the level search below reads it thousands of times)
    error2_table = [
        [EDGE_ERROR * (scale_px - 1) * info["edge"] + compression_error2(info["compressed"], scale_px) for scale_px in LEVELS] for info in per_path
    ]

    def error2(k, level):  # drawn at full resolution, a path blurs nothing the reference does not
        return error2_table[k][level]

    level_of = [len(LEVELS) - 1] * num_paths
    drawn = [k for k in range(num_paths) if enabled[k] and per_path[k]["kept"]]
    for k in range(num_paths):  # the core is no flare: its own layer at full resolution
        if not is_flare[k]:
            level_of[k] = 0
    flares = [k for k in drawn if is_flare[k]]
    while flares and sum(error2(k, level_of[k]) for k in flares) > budget:
        best, best_gain = None, -1.0
        for k in flares:
            if level_of[k] == 0:
                continue
            gain = (error2(k, level_of[k]) - error2(k, level_of[k] - 1)) / max(cost(k, level_of[k] - 1) - cost(k, level_of[k]), 1.0)
            if gain > best_gain:
                best, best_gain = k, gain
        if best is None:
            break
        level_of[best] -= 1
    estimated = math.sqrt(sum(error2(k, level_of[k]) for k in flares) / norm2) if norm2 > 0 else 0.0

    path_plans, jobs = [], []
    nodes = traced_wavelengths(grid.wavelengths, band)
    pilot_cell = 2.0 / grid.pilot_cells
    for k in range(num_paths):
        info = per_path[k]
        level = level_of[k]
        scale_px = LEVELS[level]
        c0, c1, r0, r1 = info["extent"]
        c0, r0 = max(c0 - 1, 0), max(r0 - 1, 0)
        c1, r1 = min(c1 + 1, grid.pilot_cells), min(r1 + 1, grid.pilot_cells)
        span = max(c1 - c0, r1 - r0)
        # cells sized for the tolerance in full-resolution pixels whatever the level: cells cost
        # only their traced vertices, and a cell too large for the map folds its light into a spike
        spacing = math.sqrt(8 * grid.tolerance_px / info["curvature"]) if info["curvature"] > 0 else span
        cells = int(np.clip(math.ceil(span / max(spacing, 1e-9)), grid.min_cells, grid.max_cells))
        sub_nodes = sub_nodes_at(k, level) if is_flare[k] else round_sub_nodes(info["streak"] / scale_px, grid.max_sub_nodes)
        path_plans.append(
            PathPlan(
                level=level, cells=cells, sub_nodes=sub_nodes, energy=float(energy[k]), bound=float(bound[k]), streak_px=info["streak"],
                motion_px=info["motion"], curvature_px=info["curvature"], estimated_error=error2(k, level) / norm2 if norm2 > 0 else 0.0,
            )
        )
        if not (enabled[k] and info["kept"]):
            continue
        u0, v0 = -1.0 + c0 * pilot_cell, -1.0 + r0 * pilot_cell
        du, dv = (c1 - c0) * pilot_cell / cells, (r1 - r0) * pilot_cell / cells
        for light in range(num_lights):
            extended = light_is_extended(lights, light) and info["motion"] / scale_px >= MIN_MOTION_PX
            blur = extended and grid.blur and BLUR_MIN_PX <= info["motion"] / scale_px <= BLUR_MAX_PX
            blur_area = math.pi * (info["motion"] / scale_px) ** 2 if extended and not blur else 0.0
            jobs.append(
                GridJob(
                    path=k, slot=k, light=light, layer=int(layers.layer_of_path[k]), level=level, passes=passes[k], domain=(u0, v0, du, dv),
                    cells=cells, step=0.5 if extended else 0.0, sub_nodes=sub_nodes, max_side=grid.max_side, spacing_px=grid.spacing_px,
                    min_subsamples=int(BLUR_DENSITY * blur_area), interleave=grid.interleave, blur=blur,
                    blur_border=blur_border(np.full((2, 2), info["motion"] / scale_px / math.sqrt(2))) if blur else 0,
                )
            )
    setup = grid_setup(
        lens, lights, front, spectral, effects, fresnel, tint, layers.layer_of_path, is_flare, enabled, pitch, (width, height), schlick,
    )
    del distortion
    return GridPlan(
        scene=scene, settings=settings, quality_name=settings.quality, grid=grid, seed=seed, colour_space=colour_space, lens=lens,
        pixel_pitch_mm=pitch, spectral=spectral, lights=lights, light_indices=tuple(light_indices), field_angle_deg=field_deg,
        paths=tuple(paths_all), num_flares=num_flares, events=events, culling=culling, layers=layers, path_plans=path_plans, jobs=jobs,
        setup=setup, path_fresnel=fresnel, wavelengths=nodes, pilot_subsamples=int(pilot_subsamples), pilot_rays=int(host_rows.shape[0]),
        estimated_error=estimated, setup_seconds=setup_seconds, pilot_seconds=pilot_seconds, started=started,
    )


CORE_EDGE_SIDE = 8
"""Fewest sub-samples per side of the core's edge pieces, whatever the quality: the core of a
distant light is focused to a point, so its energy is the iris-clipped entrance area its edge
pieces count (measured: a sphere light's core 2 % dark with 4 per side), and one path's edge
pieces cost little."""


def edge_side(plan: GridPlan, job) -> int:
    """Fewest sub-samples per side of the job's edge pieces (:func:`cell_pieces`)."""
    return plan.grid.edge_side if plan.paths[job.path] is not None else max(plan.grid.edge_side, CORE_EDGE_SIDE)


@dataclasses.dataclass
class PreparedGrid:
    """The main pass of a grid render up to the splat: traced vertices and device record tables."""

    prepared: PreparedSplat | None
    rays: int


def prepare_grid(plan: GridPlan) -> PreparedGrid:
    """Trace every job's vertices and decide how each cell is drawn (the host side of the main pass)."""
    setup = plan.setup
    width, height = setup.resolution
    lens32 = setup.lens
    if not plan.jobs:
        return PreparedGrid(prepared=None, rays=0)
    rows, host_rows = trace_jobs(setup, lens32, plan.jobs, plan.events, plan.wavelengths)
    distortion = setup.effects.distortion is not None
    summaries = [
        summarise_cells(job, host_rows, len(plan.wavelengths), lens32, plan.pixel_pitch_mm, width, height, distortion) for job in plan.jobs
    ]
    for job, summary in zip(plan.jobs, summaries):
        jacobian = None
        if job.blur:
            jacobian = light_jacobian_px(job, host_rows, len(plan.wavelengths), summary.passing, plan.pixel_pitch_mm, LEVELS[job.level])
            if jacobian is not None and not np.max(np.linalg.norm(jacobian, axis=1)) <= BLUR_MAX_PX:
                jacobian = None
        job.blur_jacobian = jacobian
        job.blur_border = 0 if jacobian is None else max(job.blur_border, blur_border(jacobian))
        if jacobian is not None:  # the disc's image smooths a lattice much finer than its narrowest width
            job.spacing_px = max(job.spacing_px, BLUR_SPACING * float(np.linalg.svd(jacobian, compute_uv=False)[-1]))
    summaries, refined, refined_rows, refined_host = refine_mixed_cells(
        setup, lens32, plan.jobs, summaries, plan.events, plan.wavelengths, plan.pixel_pitch_mm, distortion
    )
    pieces = [
        cell_pieces(job, s, lens32, width, height, distortion, plan.grid.fringe_px, job.sub_nodes, plan.grid.colour_error, edge_side(plan, job))
        for job, s in zip(plan.jobs, summaries)
    ]
    rays = int(host_rows.shape[0])
    if refined:
        for cell in refined:
            cell.pieces = cell_pieces(
                cell.view, cell.summary, lens32, width, height, distortion, plan.grid.fringe_px, cell.view.sub_nodes, plan.grid.colour_error,
                refined_edge_side(edge_side(plan, cell.view)),
            )
            cell.view.row0 += rays
        rows = jnp.concatenate([rows, refined_rows])
        rays += int(refined_host.shape[0])
    prepared = prepare_splat(
        setup, plan.jobs, rows, pieces, plan.wavelengths, plan.path_fresnel, plan.spectral.band_nm, len(plan.paths), refined=refined
    )
    return PreparedGrid(prepared=prepared, rays=rays)


def grid_layers(setup: RenderSetup, plan: GridPlan, prepared: PreparedGrid):
    """The full-resolution layers (Y, H, W, 3, splat units) and the accumulators of a prepared
    grid render. Differentiable in ``setup``'s tints, dirt and light gains (pass a modified
    ``plan.setup``); the grid itself (which cells, how finely) stays as planned."""
    width, height = setup.resolution
    acc = splat_prepared(setup, prepared.prepared, plan.layers.count, len(plan.paths))
    if prepared.prepared is None:
        return COMPOSE_LEVELS(acc.buffer, width, height), acc
    return COMPOSE_LAYERS(acc, prepared.prepared.jobs, width, height), acc


def run_grid(plan: GridPlan):
    """The main pass: trace every job's vertices, spread their cells; returns the full-resolution
    layers (Y, H, W, 3) in splat units, the accumulators, and counts."""
    prepared = prepare_grid(plan)
    layers, acc = grid_layers(plan.setup, plan, prepared)
    inner = prepared.prepared
    slot_samples = inner.slot_samples if inner is not None else np.zeros(len(plan.paths))
    return layers, acc, {
        "rays": prepared.rays, "subsamples": 0 if inner is None else int(inner.total), "records": 0 if inner is None else int(inner.records),
        "path_samples": slot_samples,
    }


__all__ = ["QUALITY_LEVELS", "SENSOR", "GridPlan", "PathPlan", "PreparedGrid", "grid_layers", "plan_grid", "prepare_grid", "radiance_scale", "run_grid"]
