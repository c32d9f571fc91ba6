"""jaxflare: differentiable, physically based lens-flare simulation in JAX.

Public API: :func:`load_lens`, :class:`Lens`, :func:`trace`, :func:`ghost_paths`, polynomial
path systems (:func:`path_system`, :class:`PathSystem`), flare rendering (:func:`render`,
:class:`Scene`, :func:`load_scene`), the glass catalog (:func:`find_glass`, :func:`model_glass`),
coating presets and the lens file readers and writers.
"""

from ._glass import Glass, UnknownGlassError, find_glass, model_glass, nearest_glass
from ._lens import Lens, LensWarning, build_lens
from ._lens_format import lens_toml_text, parse_lens_toml, read_lens_toml
from ._load import bundled_lens_names, load_lens, read_prescription
from ._prescription import (
    CoatingLayerSpec,
    CoatingSpec,
    LensFormatError,
    LensPrescription,
    MediumSpec,
    SurfaceSpec,
)
from ._path_build import default_cache_dir, path_system, path_systems
from ._path_domain import PathDomain, half_field_of_view_deg, make_domain
from ._path_fit import refit
from ._path_system import PathSystem, PathSystemReport
from ._trace import TraceResult, ghost_paths, path_events, path_fresnel_factor, trace
from ._coatings import COATING_PRESETS, with_coating, with_coating_layers
from ._scene import Camera, Distortion, Geometry, Hood, Light, RenderSettings, Scene, SceneError, SurfaceCoating, load_scene
from ._render import QUALITY_LEVELS, RenderResult, render
from ._exr import read_exr, write_exr

__version__ = "0.1.0"

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
