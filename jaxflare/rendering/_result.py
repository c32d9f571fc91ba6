"""A finished render: the flare image, its layers, and typed statistics.

:class:`RenderStatistics` and :class:`PathStatistics` are frozen dataclasses that also read as
mappings (``result.statistics["sensor_hit_rate"]``, ``result.statistics.paths[0].energy``); their
``to_dict()`` is what the EXR header and JSON hold.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import warnings
from collections.abc import Iterator, Mapping

import numpy as np

from .._version import __version__
from ..colour import colour_space_chromaticities, display_matrix, spectral_table
from ..io import atomic_output_group, is_jaxflare_png, tone_map, write_exr, write_png
from ..scenes import Scene
from ._gamut import clip_to_gamut, gamut_clipped_fraction
from ._quality import radiance_scale
from ._step import luminance_norm

VARIANCE_MAX = float(np.finfo(np.float32).max)
"""The largest value the ``variance`` layer holds (float32's): larger ones are clipped and counted."""
VARIANCE_PIXEL_TYPE = "float"
"""The ``variance`` layer is float32 in every EXR: in half floats a luminance squared underflows."""


class RenderWarning(UserWarning):
    """A render finished but something in it deserves attention (e.g. dropped samples)."""


class _Record(Mapping):
    """A frozen dataclass that reads as a read-only mapping of its fields."""

    def __getitem__(self, key: str):
        if key not in self._names():
            raise KeyError(key)
        return getattr(self, key)

    def __iter__(self) -> Iterator[str]:
        return iter(self._names())

    def __len__(self) -> int:
        return len(self._names())

    @classmethod
    def _names(cls) -> tuple[str, ...]:
        return tuple(field.name for field in dataclasses.fields(cls))

    def to_dict(self) -> dict:
        """Plain Python values (lists, dicts, numbers, strings), ready for JSON."""
        return {name: _plain(getattr(self, name)) for name in self._names()}


def _plain(value):
    if isinstance(value, _Record):
        return value.to_dict()
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


@dataclasses.dataclass(frozen=True, eq=False)
class PathStatistics(_Record):
    """What one lens path put into the image, and how it was traced."""

    path: list[int] | str
    """``[j, i]`` for a ghost path, ``"primary"`` for the lights' own images (the core)."""
    method: str
    """``"exact"`` or ``"polynomial"``."""
    enabled: bool
    """False for a culled flare (not rendered)."""
    energy: float
    """Luminance the path put into the image (pixel values times pixel area, summed)."""
    rgb: list[float]
    energy_bound: float
    """The culling bound of its energy (same units)."""
    samples: int
    hit_rate: float
    """Fraction of its samples that reached the image."""
    polynomial_degree: int | None
    polynomial_validation_trusted_fraction: float | None
    polynomial_untrusted_sample_fraction: float | None
    """Fraction of the trust probe's samples (fixed-seed batches of this scene) the path's system
    did not trust; it sets ``exact_fallback_capacity``."""
    exact_fallback_capacity: float | None


@dataclasses.dataclass(frozen=True, eq=False)
class RenderStatistics(_Record):
    """Samples, hit rates, culling, layers, per-path energies, times and settings of a render."""

    jaxflare_version: str
    lens: str
    resolution: list[int]
    samples: int
    pilot_samples: int
    batches: int
    rays_per_batch: int
    flare_paths: int
    paths_rendered: int
    culled_paths: int
    culled_energy_bound: float
    """Sum of the culled flares' energy bounds, relative to the brightest flare."""
    polynomial_paths: int
    exact_paths: int
    sampling: str
    table_updates: int
    lens_pass_rate: float
    sensor_hit_rate: float
    core_hit_rate: float | None
    unevaluated_fraction: float
    """Samples dropped because their path system did not trust them and the fallback was full."""
    f_number: float
    pixel_pitch_mm: float
    field_angle_deg: float
    lights: list[str]
    layers: list[dict]
    """Per EXR layer: its name and the paths it holds."""
    setup_seconds: float
    compile_seconds: float
    render_seconds: float
    total_seconds: float
    settings: dict
    paths: list[PathStatistics]

    def header_dict(self) -> dict:
        """The statistics the EXR header holds (everything but the settings and the paths)."""
        return {k: v for k, v in self.to_dict().items() if k not in ("settings", "paths")}


PREVIEW_BLOCK_PX = 8
"""The preview's exposure is set on the flare's luminance averaged over blocks of this many pixels
a side, so that Monte Carlo's brightest single samples do not set it."""


def preview_exposure_stops(luminance: np.ndarray) -> float:
    """Exposure (stops) that puts the 99.5th percentile of the lit blocks' mean luminance at 1 (just
    white): the brightest ghosts are bright, a dim veil over the frame stays dim, and a noisy and a
    noise-free render of one scene get about the same exposure."""
    height, width = luminance.shape
    block = PREVIEW_BLOCK_PX
    rows, columns = -(-height // block) * block, -(-width // block) * block
    padded = np.zeros((rows, columns))
    padded[:height, :width] = luminance
    means = padded.reshape(rows // block, block, columns // block, block).mean(axis=(1, 3))
    lit = means[means > 0]
    level = float(np.percentile(lit, 99.5)) if lit.size else 0.0
    return math.log2(1.0 / level) if level > 0 else 0.0


@dataclasses.dataclass
class RenderResult:
    """A rendered flare.

    ``image``: (H, W, 4) linear RGBA of every flare together (alpha = min(1, max(R, G, B)); add the
    RGB to the plate). ``layers``: name -> (H, W, 3): ``core`` (the lights' primary images, not a
    flare), ``flare_JJ_II`` per flare with its own layer (ghost path (J, I), two digits each, e.g.
    ``flare_07_04``), ``flares_merged`` (all other flares); and ``variance`` (H, W, 1), the
    per-pixel variance of the flare luminance (float32, also in half-float EXRs, where its small
    values would underflow). ``statistics``: a :class:`RenderStatistics`
    (samples, hit rate, per-path energies, times, settings).
    """

    image: np.ndarray
    layers: dict[str, np.ndarray]
    statistics: RenderStatistics
    scene: Scene

    def write_exr(self, path, *, pixel_type: str | None = None, compression: str | None = None) -> str:
        """Multi-layer OpenEXR: the RGBA flare as the default layer plus every layer; lens, settings
        and statistics in the header (``jaxflare/...`` attributes), the ``variance`` layer as float32
        whatever ``pixel_type`` (a half-float variance is mostly zero), and the standard
        ``chromaticities`` attribute of the render's colour space (ACEScg: AP1 primaries, ACES
        white; linear sRGB: Rec. 709, D65). No ``whiteLuminance``: the pixels are in the units of
        the lights' intensities, not photometric ones. Written atomically."""
        settings = self.scene.render
        layers = {"": self.image}
        layers.update(self.layers)
        statistics = self.statistics
        header = {
            "jaxflare/version": statistics.jaxflare_version,
            "jaxflare/lens": statistics.lens,
            "jaxflare/scene": self.scene.source or "",
            "jaxflare/settings": json.dumps(statistics.settings),
            "jaxflare/statistics": json.dumps(statistics.header_dict()),
            "jaxflare/layers": json.dumps(statistics.layers),
        }
        write_exr(
            path,
            layers,
            pixel_type=pixel_type or settings.exr_pixel_type,
            compression=compression or settings.exr_compression,
            header=header,
            layer_pixel_types={"variance": VARIANCE_PIXEL_TYPE} if "variance" in layers else None,
            chromaticities=colour_space_chromaticities(statistics.settings["colour_space"]),
        )
        return os.fspath(path)

    def preview(self, *, include_core: bool = True, exposure_stops: float | None = None) -> np.ndarray:
        """A tone-mapped sRGB 8-bit preview of the flare (and the core)."""
        colour_space = self.statistics.settings["colour_space"]
        flare = self.image[..., :3]
        if exposure_stops is None:  # expose for the flares: the core would otherwise set the exposure
            exposure_stops = preview_exposure_stops(flare @ np.asarray(spectral_table(colour_space).luminance_weights))
        rgb = flare + (self.layers["core"] if include_core and "core" in self.layers else 0.0)
        return tone_map(rgb, to_srgb_matrix=display_matrix(colour_space), exposure_stops=exposure_stops)

    def write_png(self, path, **options) -> str:
        write_png(path, self.preview(**options))
        return os.fspath(path)

    def write_files(self, exr_path, *, png: bool = False) -> list[str]:
        """The EXR and, with ``png``, its preview ``<stem>.png``, committed together
        (:func:`jaxflare.io.atomic_output_group`): a reader never sees an EXR and a PNG of two
        different renders. Without ``png`` a preview that an earlier render wrote beside the EXR
        (a jaxflare PNG) is removed; any other PNG is left alone. Returns the paths written."""
        exr_path = os.fspath(exr_path)
        png_path = os.path.splitext(exr_path)[0] + ".png"
        targets = [exr_path] + ([png_path] if png else [])
        stale = () if png or not is_jaxflare_png(png_path) else (png_path,)
        with atomic_output_group(targets, stale=stale) as temporaries:
            self.write_exr(temporaries[0])
            if png:
                self.write_png(temporaries[1])
        return targets


def gamut_mapped(plan, layers: np.ndarray, scale: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Every layer of ``layers`` (Y, H, W, 3), times its ``scale`` (Y,) in float64 (None: 1),
    through :func:`._gamut.clip_to_gamut`, as float32, and the fraction of the default image's
    pixels that were outside the gamut before. One layer at a time: a 720p render's 15 layers in
    float64 are 330 MB."""
    luminance = np.asarray(plan.luminance_weights, np.float64)
    scale = np.ones(len(layers)) if scale is None else np.asarray(scale, np.float64)

    def scaled(slot):
        return np.asarray(layers[slot], np.float64) * scale[slot]

    outside = gamut_clipped_fraction(sum(scaled(slot) for slot in range(plan.layers.num_individual + 1)))
    mapped = np.empty(np.shape(layers), np.float32)
    for slot in range(len(layers)):
        mapped[slot] = clip_to_gamut(scaled(slot), luminance)
    return mapped, outside


def named_layers(plan, layers: np.ndarray) -> tuple[dict[str, np.ndarray], list[dict]]:
    """The EXR layers of a render (``layers``: (Y, H, W, 3), one slot per layer of the plan) by
    name, and the description of each (which paths it holds) for the statistics."""
    layers_plan, paths_all = plan.layers, plan.paths
    named: dict[str, np.ndarray] = {}
    info = []
    for slot, k in enumerate(layers_plan.own):
        name = f"flare_{paths_all[k][0]:02d}_{paths_all[k][1]:02d}"
        named[name] = layers[slot]
        info.append(dict(layer=name, paths=[list(paths_all[k])]))
    merged_paths = [
        list(paths_all[k]) for k in range(plan.num_flares) if layers_plan.layer_of_path[k] == layers_plan.merged and plan.culling.enabled[k]
    ]
    named["flares_merged"] = layers[layers_plan.merged]
    info.append(dict(layer="flares_merged", paths=merged_paths))
    if plan.settings.core:
        named["core"] = layers[layers_plan.core]
        info.append(dict(layer="core", paths=["primary"]))
    return named, info


def flare_image(plan, layers: np.ndarray) -> np.ndarray:
    """The default image: the flare layers summed (RGB) and an alpha of their clipped peak."""
    flare_rgb = sum(layers[slot] for slot in range(plan.layers.num_individual + 1))
    return np.concatenate([flare_rgb, np.clip(np.max(flare_rgb, axis=-1, keepdims=True), 0.0, 1.0)], axis=-1).astype(np.float32)


def frame_statistics(plan, layer_info: list[dict]) -> dict:
    """The statistics every estimator reports the same way: the lens, the frame, the lights, the
    paths and what culling dropped."""
    lens, culling = plan.lens, plan.culling
    brightest = culling.brightest_energy
    return dict(
        jaxflare_version=__version__,
        lens=lens.name,
        resolution=list(plan.scene.camera.resolution),
        flare_paths=plan.num_flares,
        paths_rendered=len(plan.paths),
        culled_paths=int((~culling.enabled).sum()),
        culled_energy_bound=float(culling.culled_energy_bound / max(brightest, 1e-300)) if brightest > 0 else 0.0,
        f_number=float(lens.f_number()),
        pixel_pitch_mm=float(plan.pixel_pitch_mm),
        field_angle_deg=float(plan.field_angle_deg),
        lights=[plan.scene.lights[k].name or f"light[{k}]" for k in plan.light_indices],
        layers=layer_info,
    )


def hit_statistics(plan, path_samples: np.ndarray, hits: np.ndarray, passed: np.ndarray) -> dict:
    """Pass and hit rates of the flare paths and the core over the samples each path drew."""
    num_flares = plan.num_flares
    flare_samples = max(1.0, float(path_samples[:num_flares].sum()))
    return dict(
        lens_pass_rate=float(passed[:num_flares].sum() / flare_samples),
        sensor_hit_rate=float(hits[:num_flares].sum() / flare_samples),
        core_hit_rate=float(hits[-1] / max(1.0, path_samples[-1])) if plan.settings.core else None,
    )


def path_statistics(
    plan, path_energy, path_samples, hits, methods, to_radiance: float, *, polynomial_reports=None, untrusted_fraction=None, fallback_capacity=None
) -> list[PathStatistics]:
    """One :class:`PathStatistics` per path of the plan (``path_energy``: (P, 3) flux on the
    sensor; the polynomial fields are None for paths traced exactly)."""
    culling, pitch = plan.culling, plan.pixel_pitch_mm
    luminance = np.asarray(plan.luminance_weights, np.float64)
    count = len(plan.paths)
    reports = polynomial_reports if polynomial_reports is not None else [None] * count
    capacity = fallback_capacity if fallback_capacity is not None else [None] * count
    return [
        PathStatistics(
            path="primary" if p is None else list(p), method=methods[k], enabled=bool(culling.enabled[k]),
            energy=float(path_energy[k] @ luminance), rgb=[float(v) for v in path_energy[k]],
            energy_bound=float(culling.energy_bound[k] * to_radiance * pitch * pitch), samples=int(path_samples[k]),
            hit_rate=float(hits[k] / max(1.0, path_samples[k])),
            polynomial_degree=None if reports[k] is None else int(reports[k].degree),
            polynomial_validation_trusted_fraction=None if reports[k] is None else float(reports[k].trusted_fraction),
            polynomial_untrusted_sample_fraction=None if reports[k] is None else float(untrusted_fraction[k]),
            exact_fallback_capacity=None if capacity[k] is None else float(capacity[k]),
        )
        for k, p in enumerate(plan.paths)
    ]



def render_result(plan, acc, render_seconds: float, table_updates: int, *, time_now: float) -> RenderResult:
    """The image, layers and statistics of a finished render (the accumulators of its batches)."""
    settings, lens, pitch = plan.settings, plan.lens, plan.pixel_pitch_mm
    layers_plan, batches = plan.layers, plan.batches

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
            stacklevel=3,
        )

    # normalisation: mean over batches, per unit pixel area, as camera-equation radiance
    num_layers = layers_plan.count
    to_radiance = radiance_scale(lens, pitch)
    scale = np.full(num_layers, to_radiance / batches)
    flare_scale = scale[0]
    if settings.weights == "sensor-hits":
        ratio = float(acc.weight_all) / max(float(acc.weight_hits), 1e-30)
        scale[: layers_plan.num_individual + 1] *= ratio
        flare_scale *= ratio
        if settings.core:
            scale[layers_plan.core] *= path_samples[-1] / max(hits[-1], 1.0)
    layers_array = np.asarray(acc.layers)
    if not (np.all(np.isfinite(layers_array)) and np.all(np.isfinite(scale))):
        raise FloatingPointError("the render produced non-finite pixels; please report this scene")
    layers_array, out_of_gamut = gamut_mapped(plan, layers_array, scale)

    layers, layer_info = named_layers(plan, layers_array)
    if batches >= 2:
        # the accumulated luminances are in units of the brightest light's emission (_step.luminance_norm)
        norm = float(np.asarray(luminance_norm(plan.setup.lights), np.float64))
        mean = np.asarray(acc.flare_luminance_sum, np.float64) / batches
        second = np.asarray(acc.flare_luminance_squares, np.float64) / batches
        variance = np.clip(second - mean**2, 0.0, None) / (batches - 1) * batches**2 * (flare_scale * norm) ** 2
        # float64 here; the layer is float32 (and written as float32 even in half EXRs): values
        # beyond float32's range (lights of ~1e30) are clipped to it and counted, never Inf
        beyond = variance > VARIANCE_MAX
        variance_clipped = int(np.count_nonzero(beyond))
        layers["variance"] = np.minimum(variance, VARIANCE_MAX)[..., None].astype(np.float32)
        layer_info.append(
            dict(layer="variance", paths=[], meaning="per-pixel variance of the flare luminance estimate", clipped_values=variance_clipped)
        )
    image = flare_image(plan, layers_array)

    path_energy = np.asarray(acc.path_energy, np.float64) * scale[layers_plan.layer_of_path][:, None] * pitch * pitch
    methods, reports = plan.path_methods, plan.polynomial_reports
    level, camera = plan.quality, plan.scene.camera
    statistics = RenderStatistics(
        **frame_statistics(plan, layer_info),
        **hit_statistics(plan, path_samples, hits, passed),
        samples=int(drawn),
        pilot_samples=int(plan.pilot_samples.sum()),
        batches=int(batches),
        rays_per_batch=int(plan.samples_per_batch),
        polynomial_paths=int(sum(m == "polynomial" for m in methods)),
        exact_paths=int(sum(m == "exact" for m in methods)),
        sampling=settings.sampling,
        table_updates=table_updates,
        unevaluated_fraction=dropped,
        setup_seconds=float(plan.setup_seconds),
        compile_seconds=float(plan.compile_seconds),
        render_seconds=float(render_seconds),
        total_seconds=float(time_now - plan.started),
        settings=dict(
            quality=settings.quality, method=settings.method, fresnel=settings.fresnel, weights=settings.weights, sampling=settings.sampling,
            colour_space=plan.colour_space, seed=int(plan.seed), wavelength_strata=level.wavelength_strata,
            polynomial_degrees=list(level.degrees), tolerance_px=level.tolerance_px, f_number=camera.f_number, aperture_blades=lens.aperture_blades,
            cull_threshold=settings.cull_threshold, estimator="monte-carlo", out_of_gamut_fraction=out_of_gamut,
        ),
        paths=path_statistics(
            plan, path_energy, path_samples, hits, methods, to_radiance,
            polynomial_reports=reports, untrusted_fraction=plan.untrusted_fraction, fallback_capacity=plan.fallback_capacity,
        ),
    )
    return RenderResult(image=image, layers=layers, statistics=statistics, scene=plan.scene)
