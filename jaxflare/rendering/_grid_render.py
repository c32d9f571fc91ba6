"""A grid render as a :class:`~._result.RenderResult`: the same EXR layers and statistics as the
Monte Carlo renderer (:func:`jaxflare.render` with ``estimator="grid"``).

The grid estimator (:mod:`._grid`, :mod:`._grid_plan`) is deterministic, so its ``variance`` layer
is zero (it has no sampling noise; its discretisation error is estimated by the plan, reported as
``statistics["settings"]["grid_estimated_error"]``, a relative RMSE of the flare image).

Colours outside the gamut. A wavelength stratum's colour (the CIE observer over a narrow band,
mapped to the output space) can have a negative channel; summed over the band they are not, but a
pixel lit by part of the band (a colour fringe) can be. :func:`clip_to_gamut` moves such a pixel
towards the grey of the same luminance until its lowest channel is zero (luminance kept, hue kept,
saturation reduced); a pixel of non-positive luminance becomes black. It is applied to every layer
before the default layer is summed, so no layer has a negative pixel.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from .._version import __version__
from ._grid_plan import GridPlan, grid_layers, plan_grid, prepare_grid
from ._quality import radiance_scale
from ._result import PathStatistics, RenderResult, RenderStatistics


def clip_to_gamut(rgb: np.ndarray, luminance_weights: np.ndarray) -> np.ndarray:
    """``rgb`` (..., 3) with every pixel that has a negative channel desaturated towards the grey
    of its own luminance just enough that its lowest channel is 0; pixels of luminance <= 0 become
    0. Pixels without a negative channel are unchanged."""
    rgb = np.asarray(rgb, np.float64)
    luminance = rgb @ np.asarray(luminance_weights, np.float64)
    lowest = rgb.min(axis=-1)
    negative = lowest < 0
    scale = np.where(negative, luminance / np.where(negative, luminance - lowest, 1.0), 1.0)
    mapped = luminance[..., None] + scale[..., None] * (rgb - luminance[..., None])
    mapped = np.where((negative & (luminance <= 0))[..., None], 0.0, mapped)
    return np.maximum(mapped, 0.0)


def render_grid(scene, quality: str | None = None, seed: int = 0, *, paths=None, grid_error: float | None = None, grid_options: dict | None = None) -> RenderResult:
    """Render ``scene`` with the grid estimator (arguments as for :func:`jaxflare.render`;
    ``grid_error`` and ``grid_options`` as for :func:`plan_grid`)."""
    plan = plan_grid(scene, quality, seed, paths=paths, grid_error=grid_error, grid_options=grid_options)
    started = time.perf_counter()
    prepared = prepare_grid(plan)
    layers, acc = grid_layers(plan.setup, plan, prepared)
    layers = np.asarray(layers, np.float64)
    now = time.perf_counter()
    inner = prepared.prepared
    path_samples = inner.slot_samples if inner is not None else np.zeros(len(plan.paths))
    subsamples = 0 if inner is None else int(inner.total)
    return grid_result(plan, layers, acc, path_samples, subsamples, prepared.rays, now - started, time_now=now)


def grid_result(plan: GridPlan, layers: np.ndarray, acc, path_samples: np.ndarray, subsamples: int, rays: int, render_seconds: float, *, time_now: float) -> RenderResult:
    """The image, layers and statistics of a finished grid render (``layers``: (Y, H, W, 3) in
    splat units, from :func:`grid_layers`)."""
    settings, lens, pitch = plan.settings, plan.lens, plan.pixel_pitch_mm
    layers_plan, culling = plan.layers, plan.culling
    paths_all, num_flares = plan.paths, plan.num_flares
    width, height = plan.scene.camera.resolution
    luminance = np.asarray(plan.spectral.luminance_weights, np.float64)
    to_radiance = radiance_scale(lens, pitch)

    scaled = layers * to_radiance
    if not np.all(np.isfinite(scaled)):
        raise FloatingPointError("the grid render produced non-finite pixels; please report this scene")
    mapped = np.stack([clip_to_gamut(layer, luminance) for layer in scaled]).astype(np.float32)

    out: dict[str, np.ndarray] = {}
    layer_info = []
    for slot, k in enumerate(layers_plan.own):
        name = f"flare_{paths_all[k][0]:02d}_{paths_all[k][1]:02d}"
        out[name] = mapped[slot]
        layer_info.append({"layer": name, "paths": [list(paths_all[k])]})
    merged_paths = [list(paths_all[k]) for k in range(num_flares) if layers_plan.layer_of_path[k] == layers_plan.merged and culling.enabled[k]]
    out["flares_merged"] = mapped[layers_plan.merged]
    layer_info.append({"layer": "flares_merged", "paths": merged_paths})
    if settings.core:
        out["core"] = mapped[layers_plan.core]
        layer_info.append({"layer": "core", "paths": ["primary"]})
    out["variance"] = np.zeros((height, width, 1), np.float32)
    layer_info.append({"layer": "variance", "paths": [], "meaning": "grid estimator: deterministic, no sampling variance (zero)", "clipped_values": 0})
    flare_rgb = sum(mapped[slot] for slot in range(layers_plan.num_individual + 1))
    image = np.concatenate([flare_rgb, np.clip(np.max(flare_rgb, axis=-1, keepdims=True), 0.0, 1.0)], axis=-1).astype(np.float32)

    path_energy = np.asarray(acc.path_energy, np.float64) * to_radiance * pitch * pitch
    hits = np.asarray(acc.path_hits, np.float64)
    flare_samples = float(path_samples[:num_flares].sum())
    brightest = culling.brightest_energy
    dropped = 0.0
    if settings.samples is not None or settings.method != "exact":
        warnings.warn("the grid estimator traces exactly and chooses its own grid: [render] samples and method are ignored", stacklevel=3)
    statistics = RenderStatistics(
        jaxflare_version=__version__,
        lens=lens.name,
        resolution=[width, height],
        samples=int(subsamples),
        pilot_samples=int(plan.pilot_subsamples),
        batches=1,
        rays_per_batch=int(rays),
        flare_paths=num_flares,
        paths_rendered=len(paths_all),
        culled_paths=int((~culling.enabled).sum()),
        culled_energy_bound=float(culling.culled_energy_bound / max(brightest, 1e-300)) if brightest > 0 else 0.0,
        polynomial_paths=0,
        exact_paths=len(paths_all),
        sampling="grid",
        table_updates=0,
        lens_pass_rate=float(hits[:num_flares].sum() / max(1.0, flare_samples)),
        sensor_hit_rate=float(hits[:num_flares].sum() / max(1.0, flare_samples)),
        core_hit_rate=float(hits[-1] / max(1.0, path_samples[-1])) if settings.core else None,
        unevaluated_fraction=dropped,
        f_number=float(lens.f_number()),
        pixel_pitch_mm=float(pitch),
        field_angle_deg=float(plan.field_angle_deg),
        lights=[plan.scene.lights[k].name or f"light[{k}]" for k in plan.light_indices],
        layers=layer_info,
        setup_seconds=float(plan.setup_seconds),
        compile_seconds=float(plan.pilot_seconds),
        render_seconds=float(render_seconds),
        total_seconds=float(time_now - plan.started),
        settings={
            "quality": settings.quality, "estimator": "grid", "method": "exact", "fresnel": settings.fresnel, "weights": "all-samples", "sampling": "grid",
            "colour_space": plan.colour_space, "seed": int(plan.seed), "wavelength_strata": int(plan.grid.max_sub_nodes),
            "polynomial_degrees": [], "tolerance_px": float(plan.grid.tolerance_px), "f_number": plan.scene.camera.f_number,
            "aperture_blades": lens.aperture_blades, "cull_threshold": settings.cull_threshold, "grid_target_error": float(plan.grid.target_error),
            "grid_estimated_error": float(plan.estimated_error), "grid_traced_wavelengths": len(plan.wavelengths),
        },
        paths=[
            PathStatistics(
                path="primary" if p is None else list(p), method="exact", enabled=bool(culling.enabled[k]),
                energy=float(path_energy[k] @ luminance), rgb=[float(v) for v in path_energy[k]],
                energy_bound=float(culling.energy_bound[k] * to_radiance * pitch * pitch), samples=int(path_samples[k]),
                hit_rate=float(hits[k] / max(1.0, path_samples[k])), polynomial_degree=None, polynomial_validation_trusted_fraction=None,
                polynomial_untrusted_sample_fraction=None, exact_fallback_capacity=None,
            )
            for k, p in enumerate(paths_all)
        ],
    )
    return RenderResult(image=image, layers=out, statistics=statistics, scene=plan.scene)
