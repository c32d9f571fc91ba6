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

from ._version import __version__
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
from .polynomial import PathDomain, PathSystem, PathSystemReport, default_cache_dir, make_domain, path_system, path_systems, refit
from .rendering import QUALITY_LEVELS, RenderResult, RenderStatistics, render
from .scenes import Camera, Distortion, Geometry, Hood, Light, RenderSettings, Scene, SceneError, SurfaceCoating, load_scene

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
