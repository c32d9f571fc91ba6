"""The render plan: everything decided before a render's batches, as one typed value.

:func:`plan_render` reads the scene and its settings, sets up the camera's lens, lights and
spectral tables, builds path systems where the method asks for them, runs a pilot of a few uniform
batches, and from what the pilot measured decides each path's tracer (exact, or polynomial with an
exact-fallback capacity), which flares are culled, which get their own layer, and the adaptive
sampling tables. The result, a :class:`RenderPlan`, is what :func:`jaxflare.render` runs and what
the fitting package draws its samples from: both read the batch keys from
:meth:`RenderPlan.batch_key`, so a fit sees the render's samples.

Each decision is a small pure function of what came before (:func:`render_settings`,
:func:`choose_paths`, :func:`build_path_systems`, :func:`exact_path_sets`,
:func:`polynomial_path_sets`, :func:`choose_fallbacks`, :func:`cull_paths`, :func:`assign_layers`,
:func:`learned_tables`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..colour import SpectralTable, canonical_colour_space, spectral_table
from ..optics import EventTable, ExactPathTracer, GhostPath, Lens, cast_floating, check_ghost_path, ghost_paths, on_axis_fresnel, path_events
from ..polynomial import PathSystemReport, PolynomialPathTracer, path_system
from ..scenes import LightKind, RenderSettings, Scene, camera_lens, check_settings, load_scene, sensor_size_mm
from ._adaptive import masked_table, uniform_table
from ._lights import LightArrays, light_arrays
from ._memory import check_image_memory
from ._path_sets import AbstractPathSet, AdaptivePathSet, UniformPathSet
from ._quality import AUTO_MAX_FALLBACK, FALLBACK_CAPACITIES, QUALITY_LEVELS, RAYS_PER_STEP, TRUSTED_FOR_DEGREE, Quality
from ._sampling import front_disc
from ._step import STEP, STEP_DONATING, Accumulators, RenderSetup, empty_accumulators
from .effects import scene_effects

PILOT_STREAM, RENDER_STREAM, TRUST_STREAM = 1, 2, 3
"""Random streams of the pilot's and the render's batches (see :meth:`RenderPlan.batch_key`), and
of the trust probe's batches (:data:`TRUST_PROBE_SEED`)."""
TRUST_PROBE_SEED = 0
"""The seed of the batches that measure how many of a scene's samples each path system trusts
(which sets each polynomial path's exact-fallback capacity, a static size of the compiled step).
Fixed, so that the capacity, and with it the compiled step, is the same for every render seed:
measured from the render's own pilot, a path near a capacity boundary (the Biotar's (4, 2) at
degree 5, 14 % untrusted) got another capacity for another seed and recompiled the step (5-6 s)."""
TRUST_PROBE_BATCHES = 2
"""Batches of the trust probe (it runs the pilot's compiled step: no compile of its own)."""


@dataclasses.dataclass(frozen=True)
class LayerPlan:
    """Which EXR layer each path's light goes to: the brightest flares get their own layer
    (``own``, by path index, brightest first), the others share ``flares_merged``, the primary
    path goes to ``core``."""

    layer_of_path: np.ndarray
    own: tuple[int, ...]
    num_individual: int
    """Layer slots for individual flares (``merged`` is the slot after them)."""
    has_core: bool

    @property
    def merged(self) -> int:
        return self.num_individual

    @property
    def core(self) -> int:
        return self.num_individual + 1

    @property
    def count(self) -> int:
        return self.num_individual + 1 + (1 if self.has_core else 0)


@dataclasses.dataclass(frozen=True)
class CullingPlan:
    """Which flares are rendered: a flare whose energy bound (its largest on-axis Fresnel factor x
    its largest tint x the light entering the lens, measured in the pilot) is below the cull
    threshold of the brightest flare's energy is left out, and the bounds it drops are summed."""

    enabled: np.ndarray
    energy_bound: np.ndarray
    """Per path, in the pilot's units (luminance per batch)."""
    brightest_energy: float
    culled_energy_bound: float


@dataclasses.dataclass(frozen=True)
class RenderPlan:
    """A render, decided: its settings, lens, lights, paths with their tracers, layers, culling,
    sampling tables and batches, and the :class:`RenderSetup` its steps read."""

    scene: Scene
    settings: RenderSettings
    quality: Quality
    seed: int
    colour_space: str
    lens: Lens
    pixel_pitch_mm: float
    spectral: SpectralTable
    lights: LightArrays
    light_indices: tuple[int, ...]
    """Scene index of each flare light."""
    field_angle_deg: float
    paths: tuple[GhostPath | None, ...]
    """The ghost paths rendered, then the primary path (None) when the core is rendered."""
    num_flares: int
    polynomial_reports: tuple[PathSystemReport | None, ...]
    fallback_capacity: tuple[float | None, ...]
    """Per path: None where it is traced exactly, else its polynomial's exact-fallback capacity
    (a fraction of its batch; 0 for none)."""
    untrusted_fraction: np.ndarray
    """Per path: the fraction of the pilot's samples its polynomial did not trust (0 if exact)."""
    pilot_samples: np.ndarray
    pilot_table_energy: dict
    """The pilot's table energies per adaptive set (exact renders: the same sets as the render's)."""
    culling: CullingPlan
    layers: LayerPlan
    samples_per_batch: int
    batches: int
    setup: RenderSetup
    setup_seconds: float
    compile_seconds: float
    started: float
    """``time.perf_counter()`` when planning began."""

    @property
    def method(self) -> str:
        return self.settings.method

    @property
    def adaptive_sampling(self) -> bool:
        return self.settings.sampling == "adaptive"

    @property
    def path_methods(self) -> tuple[str, ...]:
        return tuple("exact" if capacity is None else "polynomial" for capacity in self.fallback_capacity)

    @property
    def luminance_weights(self) -> np.ndarray:
        return np.asarray(self.spectral.luminance_weights, np.float64)

    def batch_key(self, batch: int, stream: int = RENDER_STREAM) -> jax.Array:
        """The random key of batch ``batch`` of the render (or, with ``stream=PILOT_STREAM``, of
        the pilot): the one place the key schedule lives, so a fit draws the render's samples."""
        return batch_key(self.seed, stream, batch)

    @property
    def step(self):
        """The compiled render step (donating its accumulators on accelerators)."""
        return render_step_function()

    def relearned(self, setup: RenderSetup, energies: dict) -> RenderSetup:
        """``setup`` with its adaptive tables re-learnt from the table energies seen so far."""
        sets = learned_tables(setup.path_sets, energies, self.culling.enabled, self.adaptive_sampling)
        return eqx.tree_at(lambda s: s.path_sets, setup, cast_floating(sets, jnp.float32))


def batch_key(seed: int, stream: int, batch: int) -> jax.Array:
    return jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), stream), batch)


def render_step_function():
    return STEP_DONATING if jax.default_backend() != "cpu" else STEP


# --------------------------------------------------------------------------- planning functions


def render_settings(scene: Scene, quality: str | None, samples: int | None, method: str | None) -> RenderSettings:
    """The scene's render settings with the call's overrides, validated."""
    overrides = {}
    if quality is not None:
        overrides["quality"] = quality
    if samples is not None:
        overrides["samples"] = samples
    if method is not None:
        overrides["method"] = method
    settings = dataclasses.replace(scene.render, **overrides)
    check_settings(settings, "render")
    return settings


def choose_paths(lens: Lens, paths) -> list[GhostPath]:
    """The ghost paths to render: ``paths`` checked, or every ghost path of the lens."""
    if paths is None:
        return ghost_paths(lens)
    chosen = []
    for path in paths:
        if path is None:
            raise ValueError("paths: list ghost paths (j, i) only; the primary path is rendered as the core layer (render.core)")
        chosen.append(check_ghost_path(lens, path))
    if not chosen or len(set(chosen)) != len(chosen):
        raise ValueError(f"paths: must be a non-empty list of distinct ghost paths (j, i), got {paths!r}")
    return chosen


def light_field_angle_deg(lights: LightArrays, front_radius_mm: float) -> float:
    """Largest angle to the axis of any ray from the flare lights to the front lens (degrees)."""
    axis = np.asarray(lights.axis)
    angles = np.degrees(np.arccos(np.clip(axis[:, 2], -1, 1)))
    spread = np.degrees(np.arccos(np.clip(np.asarray(lights.cone_cos), -1, 1)))
    distance = np.linalg.norm(np.asarray(lights.centre_mm), axis=-1)
    finite = np.asarray(lights.kind) != LightKind.DIRECTIONAL
    size = np.where(finite, np.degrees(np.arctan2(np.asarray(lights.radius_mm) + front_radius_mm, np.maximum(distance, 1.0))), 0.0)
    return float(np.max(angles + spread + size))


def build_path_systems(lens, wide_open_lens, paths, quality: Quality, pitch_mm: float, field_deg: float, progress: bool):
    """Polynomial path systems of every path, built over the field the lights use to the
    render's pixel tolerance, as float32 systems on the render lens (iris, coatings): each path
    gets the lowest degree of the quality whose validation meets the tolerance (else the highest)."""
    domain_field = min(85.0, 5.0 * math.ceil((field_deg + 1.0) / 5.0))
    iterator = range(len(paths))
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc="path systems", unit="path", leave=False)
    systems, reports = [], []
    for k in iterator:
        for degree in quality.degrees:
            system = path_system(
                wide_open_lens, paths[k], degree=degree, max_field_angle_deg=domain_field, tolerance_mm=quality.tolerance_px * pitch_mm,
            )
            if system.report.trusted_fraction >= TRUSTED_FOR_DEGREE:
                break
        reports.append(system.report)
        systems.append(cast_floating(system.with_lens(lens), jnp.float32))
    return systems, reports


def exact_path_sets(
    lens: Lens, paths, exact_index: Sequence[int], lights: LightArrays, rays_per_path: int, fresnel: bool,
) -> list[AdaptivePathSet]:
    """The exactly traced paths as adaptive sets: the flares in one, the core (primary path) in
    its own, so the core's brightness does not take the flares' samples; both are traced by one
    call in the render step (one trace group). ``fresnel``: trace the
    coated Fresnel factor of every event (the exact Fresnel model; the Schlick model uses the
    paths' on-axis factors instead)."""
    sets = []
    for members in ([k for k in exact_index if paths[k] is not None], [k for k in exact_index if paths[k] is None]):
        if not members:
            continue
        tracer = ExactPathTracer.for_paths(lens, [paths[k] for k in members], 1, fresnel=fresnel)
        table = uniform_table(lights.kind.shape[0], len(members), light_probability=np.asarray(lights.selection_probability))
        sets.append(
            AdaptivePathSet(jnp.asarray(members, jnp.int32), tracer, table, rays_per_path * len(members), stream=1000 + len(sets), joint_trace_group=0)
        )
    return sets


def polynomial_path_sets(systems, fallback_capacity: Sequence[float | None], rays_per_path: int) -> list[UniformPathSet]:
    """Polynomial paths whose kernels share one structure (and fallback capacity), one set each."""
    by_signature: dict = {}
    for k, capacity in enumerate(fallback_capacity):
        if capacity is None:
            continue
        system = systems[k]
        if capacity == 0:
            kernel = system.kernel(fallback="none")
        else:
            kernel = dataclasses.replace(system, fallback_fraction=capacity).kernel(fallback="exact")
        leaves, treedef = jax.tree.flatten(kernel)
        signature = (treedef, tuple((x.shape, x.dtype) for x in leaves))
        by_signature.setdefault(signature, []).append((k, kernel, capacity))
    sets = []
    for members in by_signature.values():
        kernels = jax.tree.map(lambda *xs: jnp.stack(xs), *[kernel for _, kernel, _ in members])
        tracer = PolynomialPathTracer(kernels, float(members[0][2]))
        sets.append(UniformPathSet(jnp.asarray([k for k, _, _ in members], jnp.int32), tracer, rays_per_path))
    return sets


def choose_fallbacks(method: str, untrusted_fraction: np.ndarray) -> list[float | None]:
    """Each path's tracer from the trust probe (:data:`TRUST_PROBE_SEED`): polynomial paths get the smallest exact-fallback capacity
    covering the samples their system does not trust; ``"auto"`` traces a path exactly (None) when
    that would need more than :data:`AUTO_MAX_FALLBACK`."""
    capacity: list[float | None] = [None] * len(untrusted_fraction)
    if method == "exact":
        return capacity
    for k, fraction in enumerate(untrusted_fraction):
        needed = 0 if fraction == 0 else next((c for c in FALLBACK_CAPACITIES if 1.5 * fraction <= c), 1.0)
        if method == "polynomial" or needed <= AUTO_MAX_FALLBACK:
            capacity[k] = needed
    return capacity


def cull_paths(fresnel_table, path_tint, pilot_incoming, pilot_energy, num_flares: int, cull_threshold: float) -> CullingPlan:
    """Cull flares whose energy is provably negligible: under the Schlick Fresnel model a path's
    energy is at most its largest on-axis Fresnel factor x its largest tint x the light entering."""
    bound = fresnel_table.max(axis=1) * path_tint.max(axis=1) * pilot_incoming
    brightest = float(pilot_energy[:num_flares].max()) if num_flares else 0.0
    enabled = np.ones(len(bound), bool)
    if cull_threshold > 0 and brightest > 0:
        enabled[:num_flares] = bound[:num_flares] >= cull_threshold * brightest
    culled = float(bound[:num_flares][~enabled[:num_flares]].sum())
    return CullingPlan(enabled=enabled, energy_bound=bound, brightest_energy=brightest, culled_energy_bound=culled)


def assign_layers(pilot_energy, culling: CullingPlan, num_flares: int, settings: RenderSettings) -> LayerPlan:
    """The brightest flares get their own layer (at most ``max_flare_layers``, each at least
    ``layer_threshold`` of the brightest), the rest share one; the primary path goes to ``core``."""
    num_paths = len(culling.enabled)
    num_individual = min(settings.max_flare_layers, num_flares)
    enabled, brightest = culling.enabled, culling.brightest_energy
    flare_energy = np.where(enabled[:num_flares], pilot_energy[:num_flares], -1.0)
    order = np.argsort(-flare_energy)
    layer_of_path = np.full(num_paths, num_individual)
    own = [int(k) for k in order[:num_individual] if brightest > 0 and flare_energy[k] >= settings.layer_threshold * brightest]
    for slot, k in enumerate(own):
        layer_of_path[k] = slot
    if settings.core:
        layer_of_path[-1] = num_individual + 1
    return LayerPlan(layer_of_path=layer_of_path, own=tuple(own), num_individual=num_individual, has_core=settings.core)


def path_mask(path_set: AdaptivePathSet, enabled: np.ndarray) -> np.ndarray:
    """Which (light, path, cell) entries of a set's table belong to enabled paths."""
    table = path_set.sampling_table
    return np.tile(np.repeat(enabled[np.asarray(path_set.path_index)], table.num_cells), table.num_lights)


def learned_tables(path_sets, energies: dict, enabled: np.ndarray, adaptive: bool) -> tuple[AbstractPathSet, ...]:
    """The sets' sampling tables proportional to the energy seen (``adaptive``) or uniform, culled
    paths left out; ``energies`` maps each adaptive set's position among the sets with tables to
    its table energies."""
    learnt, table = [], 0
    for path_set in path_sets:
        if path_set.table is None:
            learnt.append(path_set)
            continue
        energy = energies.get(table) if adaptive else None
        new_table = masked_table(path_set.sampling_table, energy, path_mask(path_set, enabled))
        learnt.append(eqx.tree_at(lambda s: s.sampling_table, path_set, new_table))
        table += 1
    return tuple(learnt)


def rays_per_path_for(num_paths: int, wavelength_strata: int) -> int:
    """Samples per path and batch: the batch's ray budget shared out, a power of two in [256,
    8192], a multiple of the wavelength strata."""
    rays = int(max(256, min(8192, 2 ** round(math.log2(max(1, RAYS_PER_STEP // num_paths))))))
    return rays - rays % wavelength_strata


def path_tints(camera, num_interfaces: int, paths) -> np.ndarray:
    """Each path's coating tint (the product of its two interfaces' ``coating_tints``; 1 for the
    primary path), (P, 3)."""
    tints = camera.interface_tints(num_interfaces)
    return np.stack([tints[p[0]] * tints[p[1]] if p is not None else np.ones(3) for p in paths])


# --------------------------------------------------------------------------- the plan


def plan_render(
    scene: Scene | str,
    quality: str | None = None,
    seed: int = 0,
    *,
    samples: int | None = None,
    method: str | None = None,
    paths: Sequence[GhostPath] | None = None,
    progress: bool = False,
) -> RenderPlan:
    """Everything before the render's batches (arguments as for :func:`jaxflare.render`)."""
    started = time.perf_counter()
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    settings = render_settings(scene, quality, samples, method)
    level = QUALITY_LEVELS[settings.quality]
    total_samples = settings.samples or level.samples
    colour_space = canonical_colour_space(settings.colour_space)
    camera = scene.camera
    width, height = camera.resolution

    lens = camera_lens(camera)
    fresnel_exact = settings.fresnel == "exact"
    wide_open_lens = camera_lens(camera, with_iris=False, with_coatings=fresnel_exact)
    sensor_w, _ = sensor_size_mm(camera, lens)
    pitch = sensor_w / width
    spectral = spectral_table(colour_space)
    lights, light_indices = light_arrays(scene, spectral)
    field_deg = light_field_angle_deg(lights, float(lens.semi_aperture_mm[0]))

    flare_paths = choose_paths(lens, paths)
    paths_all: list[GhostPath | None] = list(flare_paths) + ([None] if settings.core else [])
    num_paths, num_flares = len(paths_all), len(flare_paths)
    if settings.method == "exact":
        systems, reports = [None] * num_paths, [None] * num_paths
    else:
        systems, reports = build_path_systems(lens, wide_open_lens, paths_all, level, pitch, field_deg, progress)
    build_seconds = time.perf_counter() - started

    lens32 = cast_floating(lens, jnp.float32)
    events_all = EventTable.from_array(np.stack([path_events(lens, p) for p in paths_all]))
    fresnel_table = np.asarray(on_axis_fresnel(lens32, events_all, jnp.asarray(spectral.wavelength_nm, jnp.float32)))
    path_tint = path_tints(camera, lens.num_interfaces, paths_all)
    num_layers = min(settings.max_flare_layers, num_flares) + 1 + (1 if settings.core else 0)
    check_image_memory(width, height, num_layers)  # before anything large is allocated
    rays_per_path = rays_per_path_for(num_paths, level.wavelength_strata)
    front = front_disc(lens)
    effects = scene_effects(scene, lens, pitch)

    def make_setup(path_sets, layer_of_path, enabled) -> RenderSetup:
        return cast_floating(
            RenderSetup(
                lens=lens, lights=lights, front=front, spectral=spectral, path_sets=tuple(path_sets), effects=effects,
                path_fresnel=jnp.asarray(fresnel_table), path_tint=jnp.asarray(path_tint), path_layer=jnp.asarray(layer_of_path, jnp.int32),
                path_is_flare=jnp.asarray([p is not None for p in paths_all]), path_enabled=jnp.asarray(enabled, bool),
                pixel_pitch_mm=jnp.asarray(pitch), resolution=(width, height), wavelength_strata=level.wavelength_strata, schlick=not fresnel_exact,
            ),
            jnp.float32,
        )

    # pilot: a few uniform batches measure each path's energy (layers, culling, sampling table)
    # and, for polynomial paths, how many of the scene's samples each system trusts
    pilot_capacity = [None] * num_paths if settings.method == "exact" else [0] * num_paths
    exact_index = [k for k in range(num_paths) if pilot_capacity[k] is None]
    sets = exact_path_sets(lens, paths_all, exact_index, lights, rays_per_path, fresnel_exact) + polynomial_path_sets(systems, pilot_capacity, rays_per_path)
    setup = make_setup(sets, np.zeros(num_paths), np.ones(num_paths, bool))
    step = render_step_function()
    samples_per_batch = rays_per_path * num_paths
    batches = max(1, math.ceil(max(total_samples, samples_per_batch) / samples_per_batch))
    pilot_batches = max(1, math.ceil(batches * level.pilot_fraction))
    compile_started = time.perf_counter()
    pilot = empty_accumulators(setup, num_layers)
    for b in range(pilot_batches):
        pilot = step(setup, pilot, batch_key(seed, PILOT_STREAM, b))
        if b == 0:
            jax.block_until_ready(pilot.path_energy)
            compile_seconds = time.perf_counter() - compile_started
    luminance = np.asarray(spectral.luminance_weights, np.float64)
    pilot_energy = np.asarray(pilot.path_energy, np.float64) @ luminance / pilot_batches
    pilot_incoming = np.asarray(pilot.path_incoming, np.float64) / pilot_batches
    pilot_samples = np.asarray(pilot.path_samples, np.float64)
    trust = pilot
    if settings.method != "exact":  # the fallback capacities from batches of a fixed seed (TRUST_PROBE_SEED)
        trust = empty_accumulators(setup, num_layers)
        for b in range(TRUST_PROBE_BATCHES):
            trust = step(setup, trust, batch_key(TRUST_PROBE_SEED, TRUST_STREAM, b))
    untrusted_fraction = np.asarray(trust.path_unevaluated, np.float64) / np.maximum(np.asarray(trust.path_samples, np.float64), 1)
    del trust

    fallback_capacity = choose_fallbacks(settings.method, untrusted_fraction)
    culling = cull_paths(fresnel_table, path_tint, pilot_incoming, pilot_energy, num_flares, settings.cull_threshold)
    layers = assign_layers(pilot_energy, culling, num_flares, settings)

    # the per-path budget stays the same: culled paths take their samples with them
    batches = max(1, math.ceil(batches * culling.enabled.sum() / num_paths))
    exact_index = [k for k in range(num_paths) if fallback_capacity[k] is None]
    adaptive = exact_path_sets(lens, paths_all, exact_index, lights, rays_per_path, fresnel_exact)
    pilot_tables = {}
    if settings.method == "exact":  # the pilot's table energies belong to the same sets
        pilot_tables = {k: np.asarray(e, np.float64) for k, e in enumerate(pilot.table_energy)}
    del pilot
    adaptive = learned_tables(adaptive, pilot_tables, culling.enabled, settings.sampling == "adaptive")
    setup = make_setup(list(adaptive) + polynomial_path_sets(systems, fallback_capacity, rays_per_path), layers.layer_of_path, culling.enabled)

    return RenderPlan(
        scene=scene, settings=settings, quality=level, seed=seed, colour_space=colour_space, lens=lens, pixel_pitch_mm=pitch,
        spectral=spectral, lights=lights, light_indices=tuple(light_indices), field_angle_deg=field_deg, paths=tuple(paths_all),
        num_flares=num_flares, polynomial_reports=tuple(reports), fallback_capacity=tuple(fallback_capacity),
        untrusted_fraction=untrusted_fraction, pilot_samples=pilot_samples, pilot_table_energy=pilot_tables, culling=culling,
        layers=layers, samples_per_batch=samples_per_batch, batches=batches, setup=setup, setup_seconds=build_seconds,
        compile_seconds=compile_seconds, started=started,
    )


def run_batches(plan: RenderPlan, progress=False) -> tuple[Accumulators, int]:
    """The render's batches, with the adaptive tables re-learnt after batches 1, 2, 4, ..., 512;
    returns the accumulators and the number of table updates."""
    setup, step = plan.setup, plan.step
    acc = empty_accumulators(setup, plan.layers.count)
    bar = None
    if progress is True:
        from tqdm import tqdm

        bar = tqdm(total=plan.batches, desc="rendering", unit="batch", leave=False)
    updates = {1, 2, 4, 8, 16, 32, 64, 128, 256, 512}
    has_tables = any(s.table is not None for s in setup.path_sets)
    table_updates = 0
    for b in range(plan.batches):
        acc = step(setup, acc, plan.batch_key(b))
        if plan.adaptive_sampling and (b + 1) in updates and b + 1 < plan.batches and has_tables:
            energies = {k: plan.pilot_table_energy.get(k, 0.0) + np.asarray(e, np.float64) for k, e in enumerate(acc.table_energy)}
            setup = plan.relearned(setup, energies)
            table_updates += 1
        if bar is not None:
            bar.update(1)
        elif callable(progress):
            progress(b + 1, plan.batches)
    if bar is not None:
        bar.close()
    jax.block_until_ready(acc.layers)
    return acc, table_updates
