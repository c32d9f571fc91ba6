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
- ``w_s``: the normalised weight of equation (1), ``(1/p_s) / sum_i (1/p_i)``, with ``p_s`` the
  probability of the sample's (light, path, front-lens cell) under the adaptive table
  (:mod:`._adaptive`; uniform for ``sampling="uniform"``) relative to uniform sampling. The paper
  sums over the samples that hit the sensor, which keeps a flare's brightness when the iris blocks
  most of it; jaxflare sums over every sample drawn (``weights="all-samples"``), so a flare holds
  exactly the light that gets through, and offers the paper's normalisation as
  ``weights="sensor-hits"`` (scaled to agree with it when every sample hits).

Model no more than the scene needs: paths whose energy is provably below ``cull_threshold`` of the
brightest flare (an upper bound from their on-axis Fresnel factor and the light entering the lens)
are culled after the pilot, and the bound on the energy dropped is reported.

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
import warnings
from collections.abc import Callable, Sequence
from types import SimpleNamespace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxflare.render._adaptive import masked_table, uniform_table
from jaxflare.colour._spectral import canonical_colour_space, spectral_table
from jaxflare.optics._lens import Lens
from jaxflare.render._lights import DIRECTIONAL, FrontDisc, LightArrays, light_arrays
from jaxflare.polynomial._domain import entrance_plane_z_mm, front_rim_sag_mm
from jaxflare.render._step import (
    STEP,
    STEP_DONATING,
    AdaptiveSet,
    PolynomialGroup,
    RenderSetup,
    SceneEffects,
    empty_accumulators,
    path_fresnel_table,
)
from jaxflare.scenes._scene import Scene, camera_lens, load_scene, sensor_size_mm
from jaxflare.optics._trace import ghost_paths, path_events

GhostPath = tuple[int, int]


class RenderWarning(UserWarning):
    """A render finished but something in it deserves attention (e.g. dropped samples)."""


@dataclasses.dataclass(frozen=True)
class Quality:
    """What a quality level spends: total Monte Carlo samples (``rays_per_path`` per path and batch),
    wavelength strata per batch, the polynomial degree and the sensor-position tolerance (in pixels
    of the render) a path system must meet to be used instead of exact tracing."""

    samples: int
    wavelength_strata: int
    degrees: tuple[int, ...]
    """Polynomial degrees tried, lowest first: each path gets the lowest that meets the tolerance."""
    tolerance_px: float
    pilot_fraction: float = 1 / 16


QUALITY_LEVELS = {
    "preview": Quality(samples=2**22, wavelength_strata=8, degrees=(3, 5), tolerance_px=1.0),
    "production": Quality(samples=2**26, wavelength_strata=32, degrees=(5, 7), tolerance_px=0.5),
}
TRUSTED_FOR_DEGREE = 0.9
"""A degree meets the tolerance when this fraction of its validation rays is trusted."""
RAYS_PER_STEP = 2**17
"""Rays per batch (all paths together): bounds the memory of one step."""
FALLBACK_CAPACITIES = (0.125, 0.25, 0.5, 1.0)
"""Exact-fallback capacities (fractions of a batch) a polynomial path can get."""
AUTO_MAX_FALLBACK = 0.25
"""``method="auto"``: a path whose polynomial does not trust more than this fraction of the
scene's samples (measured in the pilot) is traced exactly instead: beyond it, polynomial plus
fallback costs about as much as exact tracing (measured: degree-5 systems are 1.6-5.6x faster
than the exact tracer on CPU)."""


def _as_float32(tree):
    return jax.tree.map(lambda x: x.astype(jnp.float32) if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) else x, tree)


@dataclasses.dataclass
class RenderResult:
    """A rendered flare.

    ``image``: (H, W, 4) linear RGBA of every flare together (alpha = min(1, max(R, G, B)); add the
    RGB to the plate). ``layers``: name -> (H, W, 3): ``core`` (the lights' primary images, not a
    flare), ``flare_JJ_II`` per flare with its own layer (ghost path (J, I), two digits each, e.g.
    ``flare_07_04``), ``flares_merged`` (all other flares); and ``variance`` (H, W, 1), the
    per-pixel variance of the flare luminance. ``statistics``: samples, hit rate, per-path
    energies, times, settings.
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

        from jaxflare.io._exr import write_exr

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
        from jaxflare.colour._spectral import display_matrix
        from jaxflare.io._preview import tone_map

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

        from jaxflare.io._preview import write_png

        write_png(path, self.preview(**options))
        return os.fspath(path)


def radiance_scale(lens: Lens, pitch_mm: float) -> float:
    """Pixel value per unit of splatted flux: the camera equation ``E = pi L / (4 N^2)`` solved for
    the scene radiance L, over the pixel area (N: the lens's working f-number)."""
    return 4.0 * lens.f_number() ** 2 / math.pi / (pitch_mm * pitch_mm)


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
    from jaxflare.optics._trace import _check_path

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
    from jaxflare.polynomial._build import path_system

    domain_field = min(85.0, 5.0 * math.ceil((field_deg + 1.0) / 5.0))
    iterator = range(len(paths))
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc="path systems", unit="path", leave=False)
    kernels, reports = [], []
    for k in iterator:
        # the polynomial degree from the pixel footprint: the lowest degree whose validation meets
        # the render's pixel tolerance (else the highest tried)
        for degree in quality.degrees:
            system = path_system(
                geometry_lens, paths[k], degree=degree, max_field_angle_deg=domain_field, tolerance_mm=quality.tolerance_px * pitch_mm,
            )
            if system.report.trusted_fraction >= TRUSTED_FOR_DEGREE:
                break
        reports.append(system.report)
        kernels.append(_as_float32(system.with_lens(lens)))
    return kernels, reports


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
    from jaxflare.scenes._scene import check_settings

    check_settings(settings, "render")
    return settings


def _polynomial_groups(paths, kernels, fallback_of_path) -> tuple[PolynomialGroup, ...]:
    """Polynomial kernels with the same structure (and fallback capacity) evaluated together."""
    by_signature = {}
    for k, fallback in enumerate(fallback_of_path):
        if fallback == "exact":
            continue
        system = kernels[k]
        kernel = system.kernel(fallback="none") if fallback == 0 else dataclasses.replace(system, fallback_fraction=fallback).kernel(fallback="exact")
        leaves, treedef = jax.tree.flatten(kernel)
        signature = (treedef, tuple((x.shape, x.dtype) for x in leaves))
        by_signature.setdefault(signature, []).append((k, kernel))
    return tuple(
        PolynomialGroup(jax.tree.map(lambda *xs: jnp.stack(xs), *[kernel for _, kernel in members]), jnp.asarray([k for k, _ in members], jnp.int32))
        for members in by_signature.values()
    )


def _adaptive_sets(lens, paths, exact_paths, lights: LightArrays, rays_per_path: int) -> tuple[AdaptiveSet, ...]:
    """The exactly traced paths as adaptive sets: the flares in one, the core (primary path) in
    its own, so the core's brightness does not take the flares' samples."""
    sets = []
    for members in ([k for k in exact_paths if paths[k] is not None], [k for k in exact_paths if paths[k] is None]):
        if not members:
            continue
        events = jnp.asarray(np.stack([path_events(lens, paths[k]) for k in members]))
        table = uniform_table(lights.kind.shape[0], len(members), light_probability=np.asarray(lights.selection_probability))
        sets.append(AdaptiveSet(events, jnp.asarray(members, jnp.int32), table, rays_per_path * len(members)))
    return tuple(sets)


_OCCLUDER_CACHE: dict = {}


def _cached_occluders(files: list[str], transforms: list[np.ndarray]):
    """Loaded meshes, reused while the files are unchanged: the render step is compiled for its
    occluders (a static field), so reloading them would recompile every render."""
    import os

    from jaxflare.render.effects._occluders import load_occluders

    key = (tuple(files), tuple(t.tobytes() for t in transforms), tuple(os.stat(f).st_mtime_ns if os.path.exists(f) else None for f in files))
    if key not in _OCCLUDER_CACHE:
        if len(_OCCLUDER_CACHE) > 8:
            _OCCLUDER_CACHE.clear()
        _OCCLUDER_CACHE[key] = load_occluders(files, transforms=transforms)
    return _OCCLUDER_CACHE[key]


def _scene_effects(scene: Scene, lens: Lens, pitch_mm: float) -> SceneEffects:
    """Dirt, hood, occluding geometry and distortion of a scene, loaded (errors name the key)."""
    from jaxflare.scenes._scene import SceneError

    camera = scene.camera
    effects = {}
    if camera.dirt_map is not None:
        from jaxflare.render.effects._dirt import load_dirt_map

        try:
            effects["dirt"] = jnp.asarray(load_dirt_map(camera.dirt_map), jnp.float32)
        except (OSError, ValueError) as error:
            raise SceneError(f"camera.dirt_map: {error}") from None
    if camera.hood is not None:
        from jaxflare.render.effects._occluders import Hood

        hood = camera.hood
        effects["hood"] = Hood(hood.shape, hood.distance_mm, hood.radius_mm, hood.half_width_mm, hood.half_height_mm)
    if scene.geometry:
        transforms = []
        for mesh in scene.geometry:
            place = np.eye(4) if mesh.transform is None else np.asarray(mesh.transform, np.float64)
            transforms.append(place @ np.diag([mesh.scale, mesh.scale, mesh.scale, 1.0]))
        try:
            effects["occluders"] = _cached_occluders([mesh.file for mesh in scene.geometry], transforms)
        except (OSError, ValueError) as error:
            raise SceneError(f"geometry: {error}") from None
        effects["camera_position_m"] = jnp.asarray(camera.position_m, jnp.float32)
        effects["camera_to_world"] = jnp.asarray(camera.world_to_camera().T, jnp.float32)
    if camera.distortion is not None:
        distortion = camera.distortion
        if distortion.st_map is not None:
            from jaxflare.render.effects._distortion import load_st_map

            try:
                effects["st_map"] = jnp.asarray(load_st_map(distortion.st_map), jnp.float32)
            except (OSError, ValueError) as error:
                raise SceneError(f"camera.distortion.st_map: {error}") from None
        else:
            from jaxflare.render.effects._distortion import BrownConrady

            focal = distortion.focal_length_px or lens.focal_length() / pitch_mm
            effects["distortion"] = BrownConrady.create(
                k1=distortion.k1, k2=distortion.k2, k3=distortion.k3, p1=distortion.p1, p2=distortion.p2, focal_length_px=focal,
            )
    return SceneEffects(**effects)


def _path_mask(adaptive: AdaptiveSet, enabled: np.ndarray) -> np.ndarray:
    """Which (light, path, cell) entries of a set's table belong to enabled paths."""
    table = adaptive.table
    return np.tile(np.repeat(enabled[np.asarray(adaptive.path_index)], table.num_cells), table.num_lights)


def prepare_render(
    scene: Scene | str,
    quality: str | None = None,
    seed: int = 0,
    *,
    samples: int | None = None,
    method: str | None = None,
    paths: Sequence[GhostPath] | None = None,
    progress: bool = False,
) -> SimpleNamespace:
    """Everything before the render's batches: settings, lens, paths, path systems, the pilot and
    what it decides (layers, culling, sampling tables, polynomial fallbacks), and the final
    :class:`RenderSetup`. :func:`render` runs the batches; the fitting package draws fixed sample
    records from the same set-up (:func:`jaxflare.render._step.batch_records`)."""
    started = time.perf_counter()
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    settings = _canonical_settings(scene, quality, samples, method)
    level = QUALITY_LEVELS[settings.quality]
    total_samples = settings.samples or level.samples
    method_name = settings.method
    adaptive_sampling = settings.sampling == "adaptive"
    colour_space = canonical_colour_space(settings.colour_space)
    camera = scene.camera
    width, height = camera.resolution

    lens = camera_lens(camera)
    fresnel_exact = settings.fresnel == "exact"
    geometry_lens = camera_lens(camera, with_iris=False, with_coatings=fresnel_exact)
    sensor_w, _ = sensor_size_mm(camera, lens)
    pitch = sensor_w / width
    spectral = spectral_table(colour_space)
    lights, light_indices = light_arrays(scene, spectral)
    field_deg = _field_angle_deg(lights, float(lens.semi_aperture_mm[0]))

    flare_paths = _choose_paths(lens, paths)
    paths_all: list[GhostPath | None] = list(flare_paths) + ([None] if settings.core else [])
    num_paths = len(paths_all)
    num_flares = len(flare_paths)
    if method_name == "exact":
        kernels, reports = [None] * num_paths, [None] * num_paths
    else:
        kernels, reports = _build_kernels(lens, geometry_lens, paths_all, level, pitch, field_deg, progress is True)
    build_seconds = time.perf_counter() - started

    lens32 = _as_float32(lens)
    events_all = jnp.asarray(np.stack([path_events(lens, p) for p in paths_all]))
    fresnel_table = np.asarray(path_fresnel_table(lens32, events_all, jnp.asarray(spectral.wavelength_nm, jnp.float32)))
    tints = np.ones((lens.num_interfaces, 3))
    for interface, rgb in camera.coating_tints:
        tints[interface] = rgb
    path_tint = np.stack([tints[p[0]] * tints[p[1]] if p is not None else np.ones(3) for p in paths_all])

    num_individual = min(settings.max_flare_layers, num_flares)
    merged_layer = num_individual
    core_layer = num_individual + 1
    num_layers = num_individual + 1 + (1 if settings.core else 0)
    rays_per_path = int(max(256, min(8192, 2 ** round(math.log2(max(1, RAYS_PER_STEP // num_paths))))))
    rays_per_path -= rays_per_path % level.wavelength_strata
    z_rim = front_rim_sag_mm(lens)
    front = FrontDisc(jnp.asarray(float(lens.semi_aperture_mm[0])), entrance_plane_z_mm(lens), (min(0.0, z_rim), max(0.0, z_rim)))
    effects = _scene_effects(scene, lens, pitch)

    def make_setup(adaptive, polynomial, layer_of_path, enabled):
        return _as_float32(
            RenderSetup(
                lens=lens, lights=lights, front=front, spectral=spectral, adaptive=adaptive, polynomial=polynomial, effects=effects,
                path_fresnel=jnp.asarray(fresnel_table), path_tint=jnp.asarray(path_tint), path_layer=jnp.asarray(layer_of_path, jnp.int32),
                path_is_flare=jnp.asarray([p is not None for p in paths_all]), path_enabled=jnp.asarray(enabled, bool),
                pixel_pitch_mm=jnp.asarray(pitch), resolution=(width, height), rays_per_path=rays_per_path,
                wavelength_strata=level.wavelength_strata, schlick=not fresnel_exact,
            )
        )

    # pilot: a few uniform batches measure each path's energy (layers, culling, sampling table)
    # and, for polynomial paths, how many of the scene's samples each system trusts
    if method_name == "exact":
        pilot_fallback = ["exact"] * num_paths
    else:
        pilot_fallback = [0] * num_paths
    exact_index = [k for k in range(num_paths) if pilot_fallback[k] == "exact"]
    adaptive = _adaptive_sets(lens, paths_all, exact_index, lights, rays_per_path)
    polynomial = _polynomial_groups(paths_all, kernels, pilot_fallback)
    setup = make_setup(adaptive, polynomial, np.zeros(num_paths), np.ones(num_paths, bool))
    step = STEP_DONATING if jax.default_backend() != "cpu" else STEP
    key = jax.random.PRNGKey(seed)
    samples_per_batch = rays_per_path * num_paths
    batches = max(1, math.ceil(max(total_samples, samples_per_batch) / samples_per_batch))
    pilot_batches = max(1, math.ceil(batches * level.pilot_fraction))
    compile_started = time.perf_counter()
    pilot = empty_accumulators(setup, num_layers)
    for b in range(pilot_batches):
        pilot = step(setup, pilot, jax.random.fold_in(jax.random.fold_in(key, 1), b))
        if b == 0:
            jax.block_until_ready(pilot.path_energy)
            compile_seconds = time.perf_counter() - compile_started
    luminance = np.asarray(spectral.luminance_weights, np.float64)
    pilot_energy = np.asarray(pilot.path_energy, np.float64) @ luminance / pilot_batches
    pilot_incoming = np.asarray(pilot.path_incoming, np.float64) / pilot_batches
    pilot_samples = np.asarray(pilot.path_samples, np.float64)

    # polynomial paths: the smallest exact fallback covering the samples a system does not trust;
    # "auto" traces a path exactly when that would need too large a fallback
    untrusted_fraction = np.asarray(pilot.path_unevaluated, np.float64) / np.maximum(pilot_samples, 1)
    fallback_of_path = ["exact"] * num_paths
    if method_name != "exact":
        for k, fraction in enumerate(untrusted_fraction):
            needed = 0 if fraction == 0 else next((c for c in FALLBACK_CAPACITIES if 1.5 * fraction <= c), 1.0)
            if method_name == "polynomial" or needed <= AUTO_MAX_FALLBACK:
                fallback_of_path[k] = needed
    methods = ["exact" if f == "exact" else "polynomial" for f in fallback_of_path]

    # cull flares whose energy is provably negligible: under the Schlick Fresnel model a path's
    # energy is at most its largest on-axis Fresnel factor x its largest tint x the light entering
    bound = fresnel_table.max(axis=1) * path_tint.max(axis=1) * pilot_incoming
    brightest = pilot_energy[:num_flares].max() if num_flares else 0.0
    enabled = np.ones(num_paths, bool)
    if settings.cull_threshold > 0 and brightest > 0:
        enabled[:num_flares] = bound[:num_flares] >= settings.cull_threshold * brightest
    culled_bound = float(bound[:num_flares][~enabled[:num_flares]].sum())

    # layers: the brightest flares get their own, the rest share one
    flare_energy = np.where(enabled[:num_flares], pilot_energy[:num_flares], -1.0)
    order = np.argsort(-flare_energy)
    layer_of_path = np.full(num_paths, merged_layer)
    own = [k for k in order[:num_individual] if brightest > 0 and flare_energy[k] >= settings.layer_threshold * brightest]
    for slot, k in enumerate(own):
        layer_of_path[k] = slot
    if settings.core:
        layer_of_path[-1] = core_layer

    # the per-path budget stays the same: culled paths take their samples with them
    batches = max(1, math.ceil(batches * enabled.sum() / num_paths))
    exact_index = [k for k in range(num_paths) if fallback_of_path[k] == "exact"]
    adaptive = _adaptive_sets(lens, paths_all, exact_index, lights, rays_per_path)
    pilot_tables = {}
    if method_name == "exact":  # the pilot's table energies belong to the same sets
        pilot_tables = {k: np.asarray(e, np.float64) for k, e in enumerate(pilot.table_energy)}
    del pilot

    def learn(adaptive, energies):
        """Tables proportional to the energy seen (adaptive) or uniform, culled paths left out."""
        learnt = []
        for k, a in enumerate(adaptive):
            energy = energies.get(k) if adaptive_sampling else None
            learnt.append(dataclasses.replace(a, table=masked_table(a.table, energy, _path_mask(a, enabled))))
        return tuple(learnt)

    adaptive = learn(adaptive, pilot_tables)
    polynomial = _polynomial_groups(paths_all, kernels, fallback_of_path)
    setup = make_setup(adaptive, polynomial, layer_of_path, enabled)

    return SimpleNamespace(
        started=started, scene=scene, settings=settings, level=level, colour_space=colour_space, lens=lens, pitch=pitch,
        spectral=spectral, lights=lights, light_indices=light_indices, field_deg=field_deg, paths_all=paths_all,
        num_paths=num_paths, num_flares=num_flares, reports=reports, build_seconds=build_seconds, compile_seconds=compile_seconds,
        num_individual=num_individual, merged_layer=merged_layer, core_layer=core_layer, num_layers=num_layers,
        samples_per_batch=samples_per_batch, batches=batches, pilot_samples=pilot_samples, untrusted_fraction=untrusted_fraction,
        fallback_of_path=fallback_of_path, methods=methods, bound=bound, brightest=brightest, enabled=enabled,
        culled_bound=culled_bound, own=own, layer_of_path=layer_of_path, pilot_tables=pilot_tables, learn=learn, setup=setup,
        step=step, key=key, adaptive_sampling=adaptive_sampling, method_name=method_name, luminance=luminance,
    )


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
        samples: total Monte Carlo samples (default the quality's), rounded up to whole batches.
        method: ``"exact"``, ``"polynomial"`` or ``"auto"`` (default the scene's).
        paths: render only these ghost paths ``(j, i)`` (default: every two-reflection path).
        progress: True for a progress bar on stderr, or a callable ``(batches_done, batches)``.

    Returns:
        A :class:`RenderResult` (image, layers, statistics; ``write_exr``/``write_png``).
    """
    prepared = prepare_render(scene, quality, seed, samples=samples, method=method, paths=paths, progress=progress is True)
    p = prepared
    (started, scene, settings, level, colour_space, lens, pitch, light_indices, field_deg, paths_all,
     num_paths, num_flares, reports, build_seconds, compile_seconds, num_individual, merged_layer, core_layer, num_layers,
     samples_per_batch, batches, pilot_samples, untrusted_fraction, fallback_of_path, methods, bound, brightest, enabled,
     culled_bound, own, layer_of_path, pilot_tables, learn, setup, step, key, adaptive_sampling, method_name, luminance) = (
        p.started, p.scene, p.settings, p.level, p.colour_space, p.lens, p.pitch, p.light_indices,
        p.field_deg, p.paths_all, p.num_paths, p.num_flares, p.reports, p.build_seconds, p.compile_seconds, p.num_individual,
        p.merged_layer, p.core_layer, p.num_layers, p.samples_per_batch, p.batches, p.pilot_samples, p.untrusted_fraction,
        p.fallback_of_path, p.methods, p.bound, p.brightest, p.enabled, p.culled_bound, p.own, p.layer_of_path,
        p.pilot_tables, p.learn, p.setup, p.step, p.key, p.adaptive_sampling, p.method_name, p.luminance,
    )
    camera = scene.camera
    width, height = camera.resolution

    # the render
    render_started = time.perf_counter()
    acc = empty_accumulators(setup, num_layers)
    bar = None
    if progress is True:
        from tqdm import tqdm

        bar = tqdm(total=batches, desc="rendering", unit="batch", leave=False)
    updates = {1, 2, 4, 8, 16, 32, 64, 128, 256, 512}
    table_updates = 0
    for b in range(batches):
        acc = step(setup, acc, jax.random.fold_in(jax.random.fold_in(key, 2), b))
        if adaptive_sampling and (b + 1) in updates and b + 1 < batches and setup.adaptive:
            energies = {k: pilot_tables.get(k, 0.0) + np.asarray(e, np.float64) for k, e in enumerate(acc.table_energy)}
            setup = eqx.tree_at(lambda s: s.adaptive, setup, _as_float32(learn(setup.adaptive, energies)))
            table_updates += 1
        if bar is not None:
            bar.update(1)
        elif callable(progress):
            progress(b + 1, batches)
    if bar is not None:
        bar.close()
    jax.block_until_ready(acc.layers)
    render_seconds = time.perf_counter() - render_started

    path_samples = np.asarray(acc.path_samples, np.float64)
    hits = np.asarray(acc.path_hits, np.float64)
    passed = np.asarray(acc.path_passed, np.float64)
    unevaluated = np.asarray(acc.path_unevaluated, np.float64)
    drawn = float(path_samples.sum())
    dropped = float(unevaluated.sum() / max(drawn, 1.0))
    if dropped > 0.01:
        warnings.warn(
            f"{dropped:.1%} of the samples were dropped: their path systems do not trust them and the exact "
            "fallback was full. Their light is missing from the image; render with method='auto' or 'exact'.",
            RenderWarning,
            stacklevel=2,
        )

    # normalisation: mean over batches, per unit pixel area, as camera-equation radiance
    f_number = lens.f_number()
    to_radiance = radiance_scale(lens, pitch)
    scale = np.full(num_layers, to_radiance / batches)
    flare_scale = scale[0]
    if settings.weights == "sensor-hits":
        ratio = float(acc.weight_all) / max(float(acc.weight_hits), 1e-30)
        scale[: num_individual + 1] *= ratio
        flare_scale *= ratio
        if settings.core:
            scale[core_layer] *= path_samples[-1] / max(hits[-1], 1.0)
    layers_array = (np.asarray(acc.layers, np.float64) * scale[:, None, None, None]).astype(np.float32)
    if not np.all(np.isfinite(layers_array)):
        raise FloatingPointError("the render produced non-finite pixels; please report this scene")

    layers: dict[str, np.ndarray] = {}
    layer_info = []
    for slot, k in enumerate(own):
        name = f"flare_{paths_all[k][0]:02d}_{paths_all[k][1]:02d}"
        layers[name] = layers_array[slot]
        layer_info.append(dict(layer=name, paths=[list(paths_all[k])]))
    merged_paths = [list(paths_all[k]) for k in range(num_flares) if layer_of_path[k] == merged_layer and enabled[k]]
    layers["flares_merged"] = layers_array[merged_layer]
    layer_info.append(dict(layer="flares_merged", paths=merged_paths))
    if settings.core:
        layers["core"] = layers_array[core_layer]
        layer_info.append(dict(layer="core", paths=["primary"]))
    if batches >= 2:
        mean = np.asarray(acc.flare_luminance_sum, np.float64) / batches
        second = np.asarray(acc.flare_luminance_squares, np.float64) / batches
        variance = np.clip(second - mean**2, 0.0, None) / (batches - 1) * flare_scale**2 * batches**2
        layers["variance"] = variance[..., None].astype(np.float32)
        layer_info.append(dict(layer="variance", paths=[], meaning="per-pixel variance of the flare luminance estimate"))
    flare_rgb = sum(layers_array[slot] for slot in range(num_individual + 1))
    image = np.concatenate([flare_rgb, np.clip(np.max(flare_rgb, axis=-1, keepdims=True), 0.0, 1.0)], axis=-1).astype(np.float32)

    path_energy = np.asarray(acc.path_energy, np.float64) * scale[layer_of_path][:, None] * pitch * pitch
    flare_samples = path_samples[:num_flares].sum()
    from jaxflare._version import __version__

    statistics = dict(
        jaxflare_version=__version__,
        lens=lens.name,
        resolution=[width, height],
        samples=int(drawn),
        pilot_samples=int(pilot_samples.sum()),
        batches=int(batches),
        rays_per_batch=int(samples_per_batch),
        flare_paths=num_flares,
        paths_rendered=num_paths,
        culled_paths=int((~enabled).sum()),
        culled_energy_bound=float(culled_bound / max(brightest, 1e-300)) if brightest > 0 else 0.0,
        polynomial_paths=int(sum(m == "polynomial" for m in methods)),
        exact_paths=int(sum(m == "exact" for m in methods)),
        sampling=settings.sampling,
        table_updates=table_updates,
        lens_pass_rate=float(passed[:num_flares].sum() / max(1.0, flare_samples)),
        sensor_hit_rate=float(hits[:num_flares].sum() / max(1.0, flare_samples)),
        core_hit_rate=float(hits[-1] / max(1.0, path_samples[-1])) if settings.core else None,
        unevaluated_fraction=dropped,
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
            quality=settings.quality, method=method_name, fresnel=settings.fresnel, weights=settings.weights, sampling=settings.sampling,
            colour_space=colour_space, seed=int(seed), wavelength_strata=level.wavelength_strata,
            polynomial_degrees=list(level.degrees), tolerance_px=level.tolerance_px, f_number=camera.f_number, aperture_blades=lens.aperture_blades,
            cull_threshold=settings.cull_threshold,
        ),
        paths=[
            dict(
                path="primary" if p is None else list(p), method=methods[k], enabled=bool(enabled[k]),
                energy=float(path_energy[k] @ luminance), rgb=[float(v) for v in path_energy[k]],
                energy_bound=float(bound[k] * to_radiance * pitch * pitch), samples=int(path_samples[k]),
                hit_rate=float(hits[k] / max(1.0, path_samples[k])),
                polynomial_degree=None if reports[k] is None else int(reports[k].degree),
                polynomial_validation_trusted_fraction=None if reports[k] is None else float(reports[k].trusted_fraction),
                polynomial_untrusted_sample_fraction=None if reports[k] is None else float(untrusted_fraction[k]),
                exact_fallback_capacity=None if fallback_of_path[k] == "exact" else float(fallback_of_path[k]),
            )
            for k, p in enumerate(paths_all)
        ],
    )
    return RenderResult(image=image, layers=layers, statistics=statistics, scene=scene)
