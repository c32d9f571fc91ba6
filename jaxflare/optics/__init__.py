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

from __future__ import annotations

from typing import TYPE_CHECKING

from ._prescription import (
    AIR,
    COATING_INDEX_RANGE,
    DEFAULT_COATING,
    F_NUMBER_RANGE,
    MAX_APERTURE_BLADES,
    MAX_ASPHERIC_SAG_MM,
    MAX_COATING_THICKNESS_NM,
    MAX_CONIC,
    MAX_LENGTH_MM,
    MAX_SURFACES,
    MIN_RADIUS_MM,
    SURFACE_KINDS,
    UNCOATED,
    WAVELENGTH_RANGE_NM,
    CoatingLayerSpec,
    CoatingSpec,
    LensFormatError,
    LensPrescription,
    MediumSpec,
    SurfaceSpec,
    check_blades,
    check_prescription,
)

# Everything else imports JAX: loaded on first use (PEP 562), so that reading and writing lens
# files (plain Python prescriptions) stays fast and JAX-free.
_LAZY = {
    "COATING_PRESETS": "_coatings",
    "with_coating": "_coatings",
    "with_coating_layers": "_coatings",
    "cast_floating": "_field",
    "entrance_plane_z_mm": "_field",
    "front_rim_sag_mm": "_field",
    "half_field_of_view_deg": "_field",
    "C_LINE_NM": "_glass",
    "D_LINE_NM": "_glass",
    "F_LINE_NM": "_glass",
    "Glass": "_glass",
    "UnknownGlassError": "_glass",
    "catalogs": "_glass",
    "find_glass": "_glass",
    "glass_names": "_glass",
    "model_glass": "_glass",
    "nearest_glass": "_glass",
    "sellmeier_index": "_glass",
    "Lens": "_lens",
    "LensWarning": "_lens",
    "STATED_INDEX_TOLERANCE": "_lens",
    "build_lens": "_lens",
    "EventAction": "_paths",
    "EventColumn": "_paths",
    "EventTable": "_paths",
    "GhostPath": "_paths",
    "active_event_count": "_paths",
    "check_ghost_path": "_paths",
    "event_table": "_paths",
    "ghost_paths": "_paths",
    "path_events": "_paths",
    "stop_pass_count": "_paths",
    "BEHIND_TOLERANCE_MM": "_surface",
    "SurfaceKind": "_surface",
    "facing_normal": "_surface",
    "inside_iris": "_surface",
    "intersect": "_surface",
    "meridian_weights": "_surface",
    "reflect": "_surface",
    "refract": "_surface",
    "refract_or_reflect": "_surface",
    "Vector": "_surface",
    "safe_divide": "_surface",
    "safe_sqrt": "_surface",
    "sag_and_slope": "_surface",
    "surface_sag_mm": "_surface",
    "coated_reflectance": "_thin_film",
    "coated_reflectance_sp": "_thin_film",
    "schlick_reflectance": "_thin_film",
    "uncoated_reflectance": "_thin_film",
    "LossReason": "_trace",
    "TraceResult": "_trace",
    "media_indices": "_trace",
    "medium_rows": "_trace",
    "CHUNK_RAYS": "_trace",
    "on_axis_fresnel": "_trace",
    "path_fresnel_factor": "_trace",
    "rank_ghost_paths": "_trace",
    "ray_arguments": "_trace",
    "strongest_ghost_path": "_trace",
    "trace": "_trace",
    "trace_events": "_trace",
    "AbstractPathTracer": "_tracer",
    "ExactPathTracer": "_tracer",
}

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs
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
    from ._surface import (
        BEHIND_TOLERANCE_MM,
        SurfaceKind,
        Vector,
        facing_normal,
        inside_iris,
        intersect,
        meridian_weights,
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


def _modules() -> dict:
    """The JAX-based modules (imported together: they import one another)."""
    from . import _coatings, _field, _glass, _lens, _paths, _surface, _thin_film, _trace, _tracer

    return {
        "_coatings": _coatings, "_field": _field, "_glass": _glass, "_lens": _lens, "_paths": _paths,
        "_surface": _surface, "_thin_film": _thin_film, "_trace": _trace, "_tracer": _tracer,
    }


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(_modules()[module], name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


__all__ = [
    "AIR",
    "BEHIND_TOLERANCE_MM",
    "CHUNK_RAYS",
    "COATING_INDEX_RANGE",
    "COATING_PRESETS",
    "C_LINE_NM",
    "DEFAULT_COATING",
    "D_LINE_NM",
    "F_LINE_NM",
    "F_NUMBER_RANGE",
    "MAX_APERTURE_BLADES",
    "MAX_ASPHERIC_SAG_MM",
    "MAX_COATING_THICKNESS_NM",
    "MAX_CONIC",
    "MAX_LENGTH_MM",
    "MAX_SURFACES",
    "MIN_RADIUS_MM",
    "STATED_INDEX_TOLERANCE",
    "SURFACE_KINDS",
    "UNCOATED",
    "WAVELENGTH_RANGE_NM",
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
    "check_blades",
    "check_ghost_path",
    "check_prescription",
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
