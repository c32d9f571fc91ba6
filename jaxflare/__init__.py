"""jaxflare: differentiable, physically based lens-flare simulation in JAX.

Public API: :func:`load_lens`, :class:`Lens`, :func:`trace`, :func:`ghost_paths`, polynomial
path systems (:func:`path_system`, :class:`PathSystem`), flare rendering (:func:`render`,
:class:`Scene`, :func:`load_scene`), the glass catalog (:func:`find_glass`, :func:`model_glass`),
coating presets and the lens file readers and writers.
"""

from jaxflare.optics._glass import Glass, UnknownGlassError, find_glass, model_glass, nearest_glass
from jaxflare.optics._lens import Lens, LensWarning, build_lens
from jaxflare.io._lens_toml import lens_toml_text, parse_lens_toml, read_lens_toml
from jaxflare.io._lens_files import bundled_lens_names, load_lens, read_prescription
from jaxflare.optics._prescription import (
    CoatingLayerSpec,
    CoatingSpec,
    LensFormatError,
    LensPrescription,
    MediumSpec,
    SurfaceSpec,
)
from jaxflare.polynomial._build import default_cache_dir, path_system, path_systems
from jaxflare.polynomial._domain import PathDomain, half_field_of_view_deg, make_domain
from jaxflare.polynomial._least_squares import refit
from jaxflare.polynomial._system import PathSystem, PathSystemReport
from jaxflare.optics._trace import TraceResult, ghost_paths, path_events, path_fresnel_factor, trace
from jaxflare.optics._coatings import COATING_PRESETS, with_coating, with_coating_layers
from jaxflare.scenes._scene import Camera, Distortion, Geometry, Hood, Light, RenderSettings, Scene, SceneError, SurfaceCoating, load_scene
from jaxflare.render._render import QUALITY_LEVELS, RenderResult, render
from jaxflare.io._exr import read_exr, write_exr

from ._version import __version__

__all__ = [
    "COATING_PRESETS",
    "QUALITY_LEVELS",
    "Camera",
    "Distortion",
    "Geometry",
    "Hood",
    "Light",
    "RenderResult",
    "RenderSettings",
    "Scene",
    "SceneError",
    "SurfaceCoating",
    "load_scene",
    "read_exr",
    "render",
    "with_coating",
    "with_coating_layers",
    "write_exr",
    "CoatingLayerSpec",
    "CoatingSpec",
    "Glass",
    "Lens",
    "LensFormatError",
    "LensPrescription",
    "LensWarning",
    "MediumSpec",
    "PathDomain",
    "PathSystem",
    "PathSystemReport",
    "SurfaceSpec",
    "TraceResult",
    "UnknownGlassError",
    "build_lens",
    "default_cache_dir",
    "bundled_lens_names",
    "find_glass",
    "ghost_paths",
    "half_field_of_view_deg",
    "lens_toml_text",
    "load_lens",
    "make_domain",
    "model_glass",
    "nearest_glass",
    "parse_lens_toml",
    "path_events",
    "path_fresnel_factor",
    "path_system",
    "path_systems",
    "read_lens_toml",
    "read_prescription",
    "refit",
    "trace",
]
