"""jaxflare: differentiable, physically based lens-flare simulation in JAX.

The pipeline, one package per stage (imports only go down this list):

- :mod:`jaxflare.optics`: lens prescriptions, glass, coatings, surfaces, lenses, paths, the exact tracer;
- :mod:`jaxflare.colour`: spectra to RGB through the CIE observer;
- :mod:`jaxflare.io`: lens files (TOML, Zemax), images (EXR, PNG), previews, plots;
- :mod:`jaxflare.polynomial`: polynomial path systems, validated against the exact tracer;
- :mod:`jaxflare.scenes`: cameras, lights, geometry and render settings (TOML scenes);
- :mod:`jaxflare.rendering`: the render plan, Monte Carlo batches, scene effects, EXR layers;
- the separate package ``fitting`` fits coatings, dirt and light gains to plates; ``jaxflare.cli``
  is the command line.

What a script needs is re-exported here (``__all__``): load a lens and trace it
(:func:`load_lens`, :func:`trace`, :func:`ghost_paths`), build path systems (:func:`path_system`),
read and write Zemax files (:func:`read_zmx`, :func:`write_zmx`), draw a lens
(:func:`plot_cross_section`), rank its ghosts (:func:`rank_ghost_paths`), and render a scene
(:func:`load_scene`, :class:`Scene`, :func:`render`). Everything else lives in the stage packages;
the names earlier versions exported here (``build_lens``, ``parse_lens_toml``, ``with_coating``,
...) still import from here.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ._version import __version__

# The names are loaded from their stage on first use (PEP 562): ``import jaxflare`` and the
# command line's ``--help`` and lens-file commands do not import JAX, matplotlib or OpenEXR until
# something needs them. ``jaxflare.X`` and ``from jaxflare import X`` work as before.
_LAZY = {
    "bundled_lens_names": "io",
    "lens_toml_text": "io",
    "load_lens": "io",
    "parse_lens_toml": "io",
    "plot_cross_section": "io",
    "read_exr": "io",
    "read_lens_toml": "io",
    "read_prescription": "io",
    "read_zmx": "io",
    "save_cross_section": "io",
    "write_exr": "io",
    "write_zmx": "io",
    "COATING_PRESETS": "optics",
    "CoatingLayerSpec": "optics",
    "CoatingSpec": "optics",
    "Glass": "optics",
    "Lens": "optics",
    "LensFormatError": "optics",
    "LensPrescription": "optics",
    "LensWarning": "optics",
    "MediumSpec": "optics",
    "SurfaceSpec": "optics",
    "TraceResult": "optics",
    "UnknownGlassError": "optics",
    "build_lens": "optics",
    "find_glass": "optics",
    "ghost_paths": "optics",
    "half_field_of_view_deg": "optics",
    "model_glass": "optics",
    "nearest_glass": "optics",
    "path_events": "optics",
    "path_fresnel_factor": "optics",
    "rank_ghost_paths": "optics",
    "trace": "optics",
    "with_coating": "optics",
    "with_coating_layers": "optics",
    "PathDomain": "polynomial",
    "PathSystem": "polynomial",
    "PathSystemReport": "polynomial",
    "default_cache_dir": "polynomial",
    "make_domain": "polynomial",
    "path_system": "polynomial",
    "path_systems": "polynomial",
    "refit": "polynomial",
    "QUALITY_LEVELS": "rendering",
    "RenderResult": "rendering",
    "RenderStatistics": "rendering",
    "render": "rendering",
    "Camera": "scenes",
    "Distortion": "scenes",
    "Geometry": "scenes",
    "Hood": "scenes",
    "Light": "scenes",
    "RenderSettings": "scenes",
    "Scene": "scenes",
    "SceneError": "scenes",
    "SurfaceCoating": "scenes",
    "load_scene": "scenes",
}

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs
    from .io import (
        bundled_lens_names,
        lens_toml_text,
        load_lens,
        parse_lens_toml,
        plot_cross_section,
        read_exr,
        read_lens_toml,
        read_prescription,
        read_zmx,
        save_cross_section,
        write_exr,
        write_zmx,
    )
    from .optics import (
        COATING_PRESETS,
        CoatingLayerSpec,
        CoatingSpec,
        Glass,
        Lens,
        LensFormatError,
        LensPrescription,
        LensWarning,
        MediumSpec,
        SurfaceSpec,
        TraceResult,
        UnknownGlassError,
        build_lens,
        find_glass,
        ghost_paths,
        half_field_of_view_deg,
        model_glass,
        nearest_glass,
        path_events,
        path_fresnel_factor,
        rank_ghost_paths,
        trace,
        with_coating,
        with_coating_layers,
    )
    from .polynomial import (
        PathDomain,
        PathSystem,
        PathSystemReport,
        default_cache_dir,
        make_domain,
        path_system,
        path_systems,
        refit,
    )
    from .rendering import QUALITY_LEVELS, RenderResult, RenderStatistics, render
    from .scenes import Camera, Distortion, Geometry, Hood, Light, RenderSettings, Scene, SceneError, SurfaceCoating, load_scene


def _stage(name: str):
    """The stage package ``name``, imported on its own (importing one stage does not import the others above it)."""
    if name == "io":
        from . import io as stage
    elif name == "optics":
        from . import optics as stage
    elif name == "polynomial":
        from . import polynomial as stage
    elif name == "rendering":
        from . import rendering as stage
    else:
        from . import scenes as stage
    return stage


def __getattr__(name: str):
    stage = _LAZY.get(name)
    if stage is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(_stage(stage), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__) | set(_LAZY))


__all__ = [
    "Camera",
    "Distortion",
    "Geometry",
    "Hood",
    "Lens",
    "Light",
    "PathSystem",
    "RenderResult",
    "RenderSettings",
    "Scene",
    "TraceResult",
    "__version__",
    "ghost_paths",
    "load_lens",
    "load_scene",
    "path_system",
    "plot_cross_section",
    "rank_ghost_paths",
    "read_zmx",
    "render",
    "trace",
    "write_zmx",
]
