"""Flare rendering: Monte Carlo over lights, lens paths and front-lens points (Pekkarinen & Balzer
2019), in vmapped batches, with adaptive sampling, scene effects and multi-layer EXR output; or
deterministically, by the ray-grid estimator (:func:`render_grid`, after Hullin et al. 2011).

The data flow is one-way: :func:`plan_render` decides everything before the batches (a typed
:class:`RenderPlan`: lens, lights, paths with their tracers, layers, culling, sampling tables and
the key schedule); :func:`render` runs its batches (:mod:`._step`: sample, trace, weigh by
equation (2), splat) and returns a :class:`RenderResult` with typed :class:`RenderStatistics`.

- Lights and sampling: :func:`light_arrays`, :func:`sample_connections`, adaptive tables
  (:class:`SamplingTable`).
- Path sets (:class:`AbstractPathSet`): :class:`AdaptivePathSet` (exact tracing, adaptive
  sampling) and :class:`UniformPathSet` (polynomial path systems), each with its own tracer;
  adaptive sets of one trace group are connected, traced and recorded together
  (:func:`group_records`).
- Samples and pixels: :class:`SampleRecords`, :func:`record_values` (equation (2)), :func:`splat`.
- Effects (:mod:`jaxflare.rendering.effects`): dirt, hood, occluding geometry, distortion.
"""

from . import effects
from ._adaptive import SamplingTable, draw, masked_table, uniform_table
from ._grid_model import KNOT_STEP_NM, GridFlareModel, gain_basis, grid_flare_model, knot_hats, scaled_lights
from ._grid_plan import GridPlan, PreparedGrid, grid_layers, plan_grid, prepare_grid, run_grid
from ._gamut import clip_to_gamut
from ._grid_render import grid_result, render_grid, render_plan
from ._lights import LightArrays, light_arrays, light_rgb
from ._path_sets import AbstractPathSet, AdaptivePathSet, UniformPathSet, group_records, trace_groups
from ._plan import (
    PILOT_STREAM,
    RENDER_STREAM,
    CullingPlan,
    LayerPlan,
    RenderPlan,
    assign_layers,
    batch_key,
    build_path_systems,
    choose_fallbacks,
    choose_paths,
    cull_paths,
    exact_path_sets,
    learned_tables,
    light_field_angle_deg,
    path_tints,
    plan_render,
    polynomial_path_sets,
    render_settings,
    run_batches,
)
from ._quality import (
    AUTO_MAX_FALLBACK,
    FALLBACK_CAPACITIES,
    QUALITY_LEVELS,
    RAYS_PER_STEP,
    TRUSTED_FOR_DEGREE,
    Quality,
    radiance_scale,
)
from ._records import (
    SampleRecords,
    front_cosine,
    front_vertex_plane_xy,
    image_position,
    interpolate_rows,
    record_values,
    sample_records,
)
from ._render import render
from ._result import PathStatistics, RenderResult, RenderStatistics, RenderWarning, render_result
from ._sampling import Connections, FrontDisc, front_disc, sample_connections
from ._splat import splat
from ._step import STEP, Accumulators, RenderSetup, batch_records, empty_accumulators, render_step
from .effects import BrownConrady, SceneEffects, dirt_transmission, hood_visible, load_dirt_map, load_st_map, scene_effects

__all__ = [
    "GridFlareModel",
    "KNOT_STEP_NM",
    "knot_hats",
    "gain_basis",
    "grid_flare_model",
    "scaled_lights",
    "AUTO_MAX_FALLBACK",
    "FALLBACK_CAPACITIES",
    "PILOT_STREAM",
    "QUALITY_LEVELS",
    "RAYS_PER_STEP",
    "RENDER_STREAM",
    "STEP",
    "TRUSTED_FOR_DEGREE",
    "AbstractPathSet",
    "Accumulators",
    "AdaptivePathSet",
    "group_records",
    "trace_groups",
    "BrownConrady",
    "Connections",
    "CullingPlan",
    "FrontDisc",
    "GridPlan",
    "LayerPlan",
    "LightArrays",
    "PathStatistics",
    "PreparedGrid",
    "Quality",
    "RenderPlan",
    "RenderResult",
    "RenderSetup",
    "RenderStatistics",
    "RenderWarning",
    "SampleRecords",
    "SamplingTable",
    "SceneEffects",
    "UniformPathSet",
    "assign_layers",
    "batch_key",
    "batch_records",
    "build_path_systems",
    "choose_fallbacks",
    "choose_paths",
    "clip_to_gamut",
    "cull_paths",
    "dirt_transmission",
    "draw",
    "effects",
    "empty_accumulators",
    "exact_path_sets",
    "front_cosine",
    "front_disc",
    "front_vertex_plane_xy",
    "grid_layers",
    "grid_result",
    "hood_visible",
    "image_position",
    "interpolate_rows",
    "learned_tables",
    "light_arrays",
    "light_field_angle_deg",
    "light_rgb",
    "load_dirt_map",
    "load_st_map",
    "masked_table",
    "path_tints",
    "plan_grid",
    "plan_render",
    "polynomial_path_sets",
    "prepare_grid",
    "radiance_scale",
    "record_values",
    "render",
    "render_grid",
    "render_plan",
    "render_result",
    "render_settings",
    "render_step",
    "run_batches",
    "run_grid",
    "sample_connections",
    "sample_records",
    "scene_effects",
    "splat",
    "uniform_table",
]
