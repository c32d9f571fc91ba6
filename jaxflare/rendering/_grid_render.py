"""A grid render as a :class:`~._result.RenderResult`: the same EXR layers and statistics as the
Monte Carlo renderer (:func:`jaxflare.render` with ``estimator="grid"``).

The grid estimator (:mod:`._grid`, :mod:`._grid_plan`) is deterministic, so its ``variance`` layer
is zero (it has no sampling noise; its discretisation error is estimated by the plan, reported as
``statistics["settings"]["grid_estimated_error"]``, a relative RMSE of the flare image). Colours
outside the output gamut are mapped as for Monte Carlo (:mod:`._gamut`).
"""

from __future__ import annotations

import math
import time
import warnings

import numpy as np

from ._grid_plan import GridPlan, plan_grid, run_grid
from ._quality import radiance_scale
from ._result import RenderResult, RenderStatistics, flare_image, frame_statistics, gamut_mapped, hit_statistics, named_layers, path_statistics

__all__ = ["grid_result", "render_grid", "render_plan"]


def render_grid(scene, quality: str | None = None, seed: int = 0, *, paths=None, grid_error: float | None = None, grid_options: dict | None = None) -> RenderResult:
    """Render ``scene`` with the grid estimator (arguments as for :func:`jaxflare.render`;
    ``grid_error`` and ``grid_options`` as for :func:`plan_grid`)."""
    return render_plan(plan_grid(scene, quality, seed, paths=paths, grid_error=grid_error, grid_options=grid_options))


def render_plan(plan: GridPlan) -> RenderResult:
    """The grid render of a finished :func:`plan_grid` plan (what :func:`render_grid` does after planning)."""
    started = time.perf_counter()
    layers, acc, counts = run_grid(plan)
    layers = np.asarray(layers)
    now = time.perf_counter()
    return grid_result(plan, layers, acc, counts["path_samples"], counts["subsamples"], counts["rays"], now - started, time_now=now)


def grid_result(plan: GridPlan, layers: np.ndarray, acc, path_samples: np.ndarray, subsamples: int, rays: int, render_seconds: float, *, time_now: float) -> RenderResult:
    """The image, layers and statistics of a finished grid render (``layers``: (Y, H, W, 3) in
    splat units, from :func:`grid_layers`)."""
    settings, lens, pitch = plan.settings, plan.lens, plan.pixel_pitch_mm
    width, height = plan.scene.camera.resolution
    to_radiance = radiance_scale(lens, pitch)

    if not (np.all(np.isfinite(layers)) and math.isfinite(to_radiance)):
        raise FloatingPointError("the grid render produced non-finite pixels; please report this scene")
    mapped, out_of_gamut = gamut_mapped(plan, layers, np.full(len(layers), to_radiance))
    out, layer_info = named_layers(plan, mapped)
    out["variance"] = np.zeros((height, width, 1), np.float32)
    layer_info.append({"layer": "variance", "paths": [], "meaning": "grid estimator: deterministic, no sampling variance (zero)", "clipped_values": 0})

    path_energy = np.asarray(acc.path_energy, np.float64) * to_radiance * pitch * pitch
    hits = np.asarray(acc.path_hits, np.float64)
    if settings.samples is not None or settings.method != "exact":
        warnings.warn("the grid estimator traces exactly and chooses its own grid: [render] samples and method are ignored", stacklevel=3)
    statistics = RenderStatistics(
        **frame_statistics(plan, layer_info),
        # every grid vertex that reached the sensor passed the lens: the pass rate is the hit rate
        **hit_statistics(plan, path_samples, hits, hits),
        samples=int(subsamples),
        pilot_samples=int(plan.pilot_subsamples),
        batches=1,
        rays_per_batch=int(rays),
        polynomial_paths=0,
        exact_paths=len(plan.paths),
        sampling="grid",
        table_updates=0,
        unevaluated_fraction=0.0,
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
            "out_of_gamut_fraction": out_of_gamut,
        },
        paths=path_statistics(plan, path_energy, path_samples, hits, ["exact"] * len(plan.paths), to_radiance),
    )
    return RenderResult(image=flare_image(plan, mapped), layers=out, statistics=statistics, scene=plan.scene)
