"""Optics: lens prescriptions, glass, thin-film coatings, surfaces, lenses, paths and the exact tracer.

The first stage of the pipeline (lens -> paths -> path systems -> samples -> image -> fit). It
imports nothing else of jaxflare.

- Prescriptions (plain Python, what a lens file says): :class:`LensPrescription`,
  :class:`SurfaceSpec`, :class:`MediumSpec`, :class:`CoatingSpec`.
- Glass: :func:`find_glass` (manufacturer catalogs, Sellmeier), :func:`model_glass` (n_d, V_d).
- Thin films: :func:`coated_reflectance` (characteristic-matrix method); presets on a lens with
  :func:`with_coating`.
- The lens as arrays (an ``equinox.Module``): :class:`Lens`, :func:`build_lens`; paraxial optics
  are its methods (focal length, pupils, focus).
- A surface, physically: :func:`intersect`, :func:`refract`, :func:`reflect`, :func:`inside_iris`.
- Paths: :func:`ghost_paths`, :func:`path_events` / :class:`EventTable`.
- Tracing: :func:`trace` (:class:`TraceResult`), :class:`ExactPathTracer` behind the
  :class:`AbstractPathTracer` interface, on-axis Fresnel factors of paths.
"""

from ._coatings import COATING_PRESETS, with_coating, with_coating_layers
from ._field import cast_floating, entrance_plane_z_mm, front_rim_sag_mm, half_field_of_view_deg
from ._glass import (
    C_LINE_NM,
    D_LINE_NM,
    F_LINE_NM,
    Glass,
    UnknownGlassError,
    catalogs,
    find_glass,
    glass_names,
    model_glass,
    nearest_glass,
    sellmeier_index,
)
from ._lens import STATED_INDEX_TOLERANCE, Lens, LensWarning, build_lens
from ._paths import (
    EventAction,
    EventColumn,
    EventTable,
    GhostPath,
    active_event_count,
    check_ghost_path,
    event_table,
    ghost_paths,
    path_events,
    stop_pass_count,
)
from ._prescription import (
    AIR,
    DEFAULT_COATING,
    SURFACE_KINDS,
    UNCOATED,
    CoatingLayerSpec,
    CoatingSpec,
    LensFormatError,
    LensPrescription,
    MediumSpec,
    SurfaceSpec,
)
from ._surface import (
    BEHIND_TOLERANCE_MM,
    SurfaceKind,
    facing_normal,
    inside_iris,
    intersect,
    meridian_weights,
    Vector,
    reflect,
    refract,
    refract_or_reflect,
    safe_divide,
    safe_sqrt,
    sag_and_slope,
    surface_sag_mm,
)
from ._thin_film import coated_reflectance, coated_reflectance_sp, schlick_reflectance, uncoated_reflectance
from ._trace import (
    CHUNK_RAYS,
    LossReason,
    TraceResult,
    media_indices,
    medium_rows,
    on_axis_fresnel,
    path_fresnel_factor,
    rank_ghost_paths,
    ray_arguments,
    strongest_ghost_path,
    trace,
    trace_events,
)
from ._tracer import AbstractPathTracer, ExactPathTracer

__all__ = [
    "AIR",
    "BEHIND_TOLERANCE_MM",
    "CHUNK_RAYS",
    "COATING_PRESETS",
    "C_LINE_NM",
    "DEFAULT_COATING",
    "D_LINE_NM",
    "F_LINE_NM",
    "STATED_INDEX_TOLERANCE",
    "SURFACE_KINDS",
    "UNCOATED",
    "AbstractPathTracer",
    "CoatingLayerSpec",
    "CoatingSpec",
    "EventAction",
    "EventColumn",
    "EventTable",
    "ExactPathTracer",
    "GhostPath",
    "Glass",
    "Lens",
    "LensFormatError",
    "LensPrescription",
    "LensWarning",
    "LossReason",
    "MediumSpec",
    "SurfaceKind",
    "SurfaceSpec",
    "TraceResult",
    "UnknownGlassError",
    "Vector",
    "active_event_count",
    "build_lens",
    "cast_floating",
    "catalogs",
    "check_ghost_path",
    "coated_reflectance",
    "coated_reflectance_sp",
    "entrance_plane_z_mm",
    "event_table",
    "facing_normal",
    "find_glass",
    "front_rim_sag_mm",
    "ghost_paths",
    "glass_names",
    "half_field_of_view_deg",
    "inside_iris",
    "intersect",
    "media_indices",
    "medium_rows",
    "meridian_weights",
    "model_glass",
    "nearest_glass",
    "on_axis_fresnel",
    "path_events",
    "path_fresnel_factor",
    "rank_ghost_paths",
    "ray_arguments",
    "reflect",
    "refract",
    "refract_or_reflect",
    "safe_divide",
    "safe_sqrt",
    "sag_and_slope",
    "schlick_reflectance",
    "sellmeier_index",
    "stop_pass_count",
    "strongest_ghost_path",
    "surface_sag_mm",
    "trace",
    "trace_events",
    "uncoated_reflectance",
    "with_coating",
    "with_coating_layers",
]
