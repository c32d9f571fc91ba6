"""Scenes: a camera (lens and its settings, sensor, pose) and the lights whose flares are rendered.

A scene is built in Python (:class:`Scene`, :class:`Camera`, :class:`Light`, :class:`RenderSettings`)
or read from a TOML file (:func:`load_scene`, documented in ``jaxflare/scenes/FORMAT.md``). Both
routes validate the same way: a bad value raises :class:`SceneError` naming the key (``light[1].
intensity``) and what would be valid.

Frames and units. World positions are in metres, in a right-handed frame with y up. The camera
sits at ``position_m`` (the vertex of the lens's front surface) and looks along ``look_at_m`` (or
the rotation ``rotation_deg = [yaw, pitch, roll]`` applied to a camera that looks down -z with y
up). The lens frame (mm) has x to the right of the picture, y up and z along the optical axis
towards the sensor, so light from the scene travels towards +z and a point at distance d in front
of the camera has z = -d.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

LIGHT_KINDS = ("point", "sphere", "disk", "directional")
QUALITIES = ("preview", "production")
METHODS = ("auto", "polynomial", "exact")
FRESNEL_MODELS = ("schlick", "exact")
WEIGHTINGS = ("all-samples", "sensor-hits")
SAMPLINGS = ("adaptive", "uniform")
EXR_PIXEL_TYPES = ("half", "float")
EXR_COMPRESSIONS = ("none", "rle", "zips", "zip", "piz", "pxr24", "b44", "b44a", "dwaa", "dwab")
MAX_LIGHT_FIELD_ANGLE_DEG = 85.0
"""Lights further than this from the optical axis are rejected (their rays graze the front lens)."""


class SceneError(ValueError):
    """A scene (file or Python object) that cannot be rendered; the message names the key."""


def _fail(where: str, message: str):
    raise SceneError(f"{where}: {message}")


def _number(where: str, value: Any, *, minimum: float | None = None, exclusive: bool = False, allow_inf: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        _fail(where, f"must be a number, got {value!r}")
    value = float(value)
    if math.isnan(value) or (math.isinf(value) and not allow_inf):
        _fail(where, f"must be finite, got {value!r}")
    if minimum is not None and (value < minimum or (exclusive and value == minimum)):
        _fail(where, f"must be {'>' if exclusive else '>='} {minimum:g}, got {value:g}")
    return value


def _vector(where: str, value: Any, length: int = 3, *, non_negative: bool = False) -> tuple[float, ...]:
    if isinstance(value, (str, bytes)) or not isinstance(value, (Sequence, np.ndarray)) or len(value) != length:
        _fail(where, f"must be a list of {length} numbers, got {value!r}")
    numbers = tuple(_number(f"{where}[{k}]", v, minimum=0.0 if non_negative else None) for k, v in enumerate(value))
    return numbers


def _choice(where: str, value: Any, choices: Sequence[str]) -> str:
    if not isinstance(value, str) or value not in choices:
        _fail(where, f"must be one of {', '.join(repr(c) for c in choices)} (as written), got {value!r}")
    return value


def _integer(where: str, value: Any, minimum: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        _fail(where, f"must be an integer, got {value!r}")
    if minimum is not None and value < minimum:
        _fail(where, f"must be >= {minimum}, got {value}")
    return int(value)


# --------------------------------------------------------------------------- data classes


@dataclasses.dataclass(frozen=True)
class Camera:
    """The render camera: lens, iris, zoom, focus, sensor and pose.

    ``f_number`` None means wide open; ``aperture_blades`` None keeps the lens file's iris (0 is a
    circle); ``zoom_position`` or ``focal_length_mm`` (zoom lenses, interpolated between positions)
    pick the zoom; ``focus_distance_m`` moves the sensor to focus (infinity by default).
    ``sensor_width_mm`` (default: the lens file's) and ``resolution = (width, height)`` in pixels
    define square pixels; the sensor height is ``width * height / width_px``.
    ``coating`` is a preset of :data:`jaxflare.COATING_PRESETS` applied to every glass-air
    interface; ``surface_coatings`` override single surfaces; ``coating_tints`` multiply the
    reflection colour of single interfaces (c_coating of the paper's equation (2)).
    """

    lens: str
    f_number: float | None = None
    aperture_blades: int | None = None
    aperture_rotation_deg: float | None = None
    zoom_position: int | None = None
    focal_length_mm: float | None = None
    focus_distance_m: float = math.inf
    sensor_width_mm: float | None = None
    resolution: tuple[int, int] = (1280, 720)
    position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    look_at_m: tuple[float, float, float] | None = None
    rotation_deg: tuple[float, float, float] | None = None
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    coating: str = "lens"
    surface_coatings: tuple["SurfaceCoating", ...] = ()
    coating_tints: tuple[tuple[int, tuple[float, float, float]], ...] = ()
    """(interface index, RGB multiplier of its reflectance) pairs."""
    dirt_map: str | None = None
    """Image of the dirt on the front element (PNG/TIFF/JPEG/EXR; 1 = clean, 0 = opaque), laid over
    its clear aperture as seen from behind the camera (``jaxflare.render.effects._dirt``)."""
    hood: "Hood | None" = None
    distortion: "Distortion | None" = None

    def world_to_camera(self) -> np.ndarray:
        """3x3 rotation taking world vectors to the lens frame (x right, y up, z towards the sensor)."""
        if self.look_at_m is not None:
            forward = np.subtract(self.look_at_m, self.position_m)
            forward = forward / np.linalg.norm(forward)
            right = np.cross(forward, self.up)
            right = right / np.linalg.norm(right)
            true_up = np.cross(right, forward)
            return np.stack([right, true_up, -forward])
        yaw, pitch, roll = np.radians(self.rotation_deg or (0.0, 0.0, 0.0))
        ry = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        rx = np.array([[1, 0, 0], [0, np.cos(pitch), -np.sin(pitch)], [0, np.sin(pitch), np.cos(pitch)]])
        rz = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1]])
        return (ry @ rx @ rz).T  # camera-to-world is Ry Rx Rz; its inverse is the transpose


@dataclasses.dataclass(frozen=True)
class Hood:
    """A lens hood or matte box: an opening ``distance_mm`` in front of the front lens vertex,
    circular (``radius_mm``) or rectangular (``half_width_mm`` x ``half_height_mm``, lens frame)."""

    shape: str = "circular"
    distance_mm: float = 50.0
    radius_mm: float | None = None
    half_width_mm: float | None = None
    half_height_mm: float | None = None


@dataclasses.dataclass(frozen=True)
class Distortion:
    """The main render's lens distortion, applied to flare samples in image space so flares line
    up with their source: Brown-Conrady coefficients (OpenCV convention, normalised by
    ``focal_length_px``, default the lens's focal length in pixels) or an ST-map file."""

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    focal_length_px: float | None = None
    st_map: str | None = None


@dataclasses.dataclass(frozen=True)
class Geometry:
    """A mesh (OBJ, PLY, GLB/GLTF, STL) that can block light on its way to the lens: world units
    times ``scale`` give metres; ``transform`` (4x4, row-major) places it in the world."""

    file: str
    scale: float = 1.0
    transform: tuple[tuple[float, ...], ...] | None = None


@dataclasses.dataclass(frozen=True)
class SurfaceCoating:
    """A coating override: a preset name or explicit layers ((index, thickness_nm) from the air side)."""

    surfaces: tuple[int, ...]
    preset: str | None = None
    layers: tuple[tuple[float, float], ...] | None = None


@dataclasses.dataclass(frozen=True)
class Light:
    """A light whose flare is rendered.

    Kinds and what ``intensity`` means (pixel values come out in the same units: see
    :func:`jaxflare.render`):

    - ``"point"`` at ``position_m``: radiant intensity (W/sr);
    - ``"sphere"`` at ``position_m`` with ``radius_m``: radiance of its surface (what the main
      render shows where it sees the light);
    - ``"disk"`` at ``position_m`` with ``radius_m``, emitting from the side its ``normal`` points to
      (default: facing the camera): radiance;
    - ``"directional"`` towards ``direction`` (from the camera to the light, world frame), e.g. the
      sun: radiance of its disc of ``angular_radius_deg`` (the sun's is 0.266), or irradiance at the
      lens (W/m^2) when ``angular_radius_deg`` is 0.

    Colour: ``rgb`` (linear, in the render's colour space), or a spectrum ``spectrum =
    (wavelengths_nm, values)``, or a black body ``temperature_k``; spectra are normalised to the
    luminance of RGB white, so ``intensity`` sets the brightness either way. ``flare_intensity``
    multiplies the intensity in the flare pass only; ``flare = False`` leaves the light out.
    """

    kind: str = "point"
    position_m: tuple[float, float, float] | None = None
    direction: tuple[float, float, float] | None = None
    radius_m: float = 0.0
    angular_radius_deg: float = 0.0
    normal: tuple[float, float, float] | None = None
    rgb: tuple[float, float, float] | None = None
    spectrum: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    temperature_k: float | None = None
    intensity: float = 1.0
    flare_intensity: float = 1.0
    flare: bool = True
    name: str = ""


@dataclasses.dataclass(frozen=True)
class RenderSettings:
    """How to render (the command line and :func:`jaxflare.render` arguments override these).

    ``quality``: ``"preview"`` or ``"production"`` (sample budget, wavelength strata, accuracy);
    ``samples``: total Monte Carlo samples, overriding the quality's budget;
    ``method``: ``"exact"`` tracing (the default), ``"polynomial"`` path systems (rays a system
    does not trust are traced exactly up to its fallback capacity, the rest dropped and counted in
    the statistics), or ``"auto"`` (each path's polynomial where its validation met the pixel-size
    tolerance of the render, exact tracing elsewhere). Exact is the default because, measured on the
    bundled lenses at 720p, few ghost polynomials of degree 5 meet a one-pixel tolerance, so
    building them costs more than it saves (see the renderer benchmark);
    ``fresnel``: ``"schlick"`` (the paper: on-axis coated Fresnel factor of the path times a
    Schlick angle term at the front lens) or ``"exact"`` (coated Fresnel at every event);
    ``weights``: ``"all-samples"`` (normalise by every sample drawn: flares dim when the iris
    blocks them) or ``"sensor-hits"`` (the paper's equation (1) literally: by the samples that hit
    the sensor); ``core``: also render the primary image of each light as layer ``core``;
    ``layer_threshold``: flares whose energy is below this fraction of the brightest go to layer
    ``flares_merged``; at most ``max_flare_layers`` flares get their own layer.
    ``sampling``: ``"adaptive"`` (the paper's section 3: lights, paths and front-lens cells drawn in
    proportion to the radiance they carry, learnt from a pilot and updated as the render goes) or
    ``"uniform"``; ``cull_threshold``: flares whose energy is provably below this fraction of the
    brightest are not rendered (0 renders every path).
    """

    quality: str = "preview"
    samples: int | None = None
    colour_space: str = "ACEScg"
    method: str = "exact"
    fresnel: str = "schlick"
    weights: str = "all-samples"
    core: bool = True
    layer_threshold: float = 0.05
    max_flare_layers: int = 12
    exr_pixel_type: str = "half"
    exr_compression: str = "zip"
    sampling: str = "adaptive"
    cull_threshold: float = 1e-3


@dataclasses.dataclass(frozen=True)
class Scene:
    camera: Camera
    lights: tuple[Light, ...]
    render: RenderSettings = RenderSettings()
    geometry: tuple[Geometry, ...] = ()
    """Meshes that occlude the lights (each sample's light-to-lens segment is ray-cast)."""
    source: str | None = None
    """The file the scene was read from (lens paths in it are relative to its folder)."""

    def __post_init__(self):
        object.__setattr__(self, "lights", tuple(self.lights))
        object.__setattr__(self, "geometry", tuple(self.geometry))
        check_scene(self)


# --------------------------------------------------------------------------- validation


def check_camera(camera: Camera, where: str = "camera") -> None:
    if not isinstance(camera.lens, str) or not camera.lens:
        _fail(f"{where}.lens", f"must be a bundled lens name or a path to a .toml/.zmx lens file, got {camera.lens!r}")
    if camera.f_number is not None:
        _number(f"{where}.f_number", camera.f_number, minimum=0.0, exclusive=True)
    if camera.aperture_blades is not None:
        blades = _integer(f"{where}.aperture_blades", camera.aperture_blades, minimum=0)
        if blades in (1, 2):
            _fail(f"{where}.aperture_blades", "must be 0 (circular iris) or at least 3")
    if camera.aperture_rotation_deg is not None:
        _number(f"{where}.aperture_rotation_deg", camera.aperture_rotation_deg)
    if camera.zoom_position is not None and camera.focal_length_mm is not None:
        _fail(where, "give zoom_position or focal_length_mm, not both")
    if camera.zoom_position is not None:
        _integer(f"{where}.zoom_position", camera.zoom_position, minimum=0)
    if camera.focal_length_mm is not None:
        _number(f"{where}.focal_length_mm", camera.focal_length_mm, minimum=0.0, exclusive=True)
    _number(f"{where}.focus_distance_m", camera.focus_distance_m, minimum=0.0, exclusive=True, allow_inf=True)
    if camera.sensor_width_mm is not None:
        _number(f"{where}.sensor_width_mm", camera.sensor_width_mm, minimum=0.0, exclusive=True)
    if (
        isinstance(camera.resolution, (str, bytes))
        or not isinstance(camera.resolution, Sequence)
        or len(camera.resolution) != 2
    ):
        _fail(f"{where}.resolution", f"must be [width, height] in pixels, got {camera.resolution!r}")
    for k, value in enumerate(camera.resolution):
        pixels = _integer(f"{where}.resolution[{k}]", value, minimum=1)
        if pixels > 16384:
            _fail(f"{where}.resolution[{k}]", f"must be at most 16384 pixels, got {pixels}")
    _vector(f"{where}.position_m", camera.position_m)
    _vector(f"{where}.up", camera.up)
    if camera.look_at_m is not None and camera.rotation_deg is not None:
        _fail(where, "give look_at_m or rotation_deg, not both")
    if camera.look_at_m is not None:
        forward = np.subtract(_vector(f"{where}.look_at_m", camera.look_at_m), camera.position_m)
        if np.linalg.norm(forward) == 0:
            _fail(f"{where}.look_at_m", "must differ from position_m")
        if np.linalg.norm(np.cross(forward, camera.up)) <= 1e-9 * np.linalg.norm(forward) * np.linalg.norm(camera.up):
            _fail(f"{where}.up", "must not be parallel to the viewing direction (look_at_m - position_m)")
    if camera.rotation_deg is not None:
        _vector(f"{where}.rotation_deg", camera.rotation_deg)
    from jaxflare.optics._coatings import COATING_PRESETS

    _choice(f"{where}.coating", camera.coating, tuple(COATING_PRESETS))
    for k, override in enumerate(camera.surface_coatings):
        place = f"{where}.surface_coatings[{k}]"
        if not override.surfaces:
            _fail(f"{place}.surfaces", "must list at least one surface index")
        for s in override.surfaces:
            _integer(f"{place}.surfaces", s, minimum=0)
        if (override.preset is None) == (override.layers is None):
            _fail(place, "give exactly one of preset or layers")
        if override.preset is not None:
            _choice(f"{place}.preset", override.preset, tuple(COATING_PRESETS))
        for m, layer in enumerate(override.layers or ()):
            index, thickness = _vector(f"{place}.layers[{m}]", layer, 2)
            if index < 1.0 or thickness < 0.0:
                _fail(f"{place}.layers[{m}]", f"must be [index >= 1, thickness_nm >= 0], got {list(layer)}")
    for k, (interface, rgb) in enumerate(camera.coating_tints):
        _integer(f"{where}.coating_tints[{k}].interface", interface, minimum=0)
        _vector(f"{where}.coating_tints[{k}].rgb", rgb, non_negative=True)
    if camera.dirt_map is not None and (not isinstance(camera.dirt_map, str) or not camera.dirt_map):
        _fail(f"{where}.dirt_map", f"must be a path to an image file, got {camera.dirt_map!r}")
    if camera.hood is not None:
        hood = camera.hood
        if not isinstance(hood, Hood):
            _fail(f"{where}.hood", f"must be a jaxflare.Hood, got {type(hood).__name__}")
        shape = _choice(f"{where}.hood.shape", hood.shape, ("circular", "rectangular"))
        _number(f"{where}.hood.distance_mm", hood.distance_mm, minimum=0.0, exclusive=True)
        needed = ("radius_mm",) if shape == "circular" else ("half_width_mm", "half_height_mm")
        other = ("half_width_mm", "half_height_mm") if shape == "circular" else ("radius_mm",)
        for name in other:
            if getattr(hood, name) is not None:
                _fail(f"{where}.hood.{name}", f"belongs to the other hood shape: a {shape} hood takes {' and '.join(needed)}")
        for name in needed:
            if getattr(hood, name) is None:
                _fail(f"{where}.hood.{name}", f"a {shape} hood needs {' and '.join(needed)}")
            _number(f"{where}.hood.{name}", getattr(hood, name), minimum=0.0, exclusive=True)
    if camera.distortion is not None:
        distortion = camera.distortion
        if not isinstance(distortion, Distortion):
            _fail(f"{where}.distortion", f"must be a jaxflare.Distortion, got {type(distortion).__name__}")
        for name in ("k1", "k2", "k3", "p1", "p2"):
            _number(f"{where}.distortion.{name}", getattr(distortion, name))
        if distortion.focal_length_px is not None:
            _number(f"{where}.distortion.focal_length_px", distortion.focal_length_px, minimum=0.0, exclusive=True)
        if distortion.st_map is not None and any(getattr(distortion, n) for n in ("k1", "k2", "k3", "p1", "p2")):
            _fail(f"{where}.distortion", "give Brown-Conrady coefficients or an st_map, not both")


def check_light(light: Light, where: str) -> None:
    kind = _choice(f"{where}.kind", light.kind, LIGHT_KINDS)
    if kind == "directional":
        if light.direction is None:
            _fail(f"{where}.direction", "a directional light needs direction = [x, y, z] (from the camera towards the light)")
        if light.position_m is not None:
            _fail(f"{where}.position_m", "a directional light has a direction, not a position")
        if np.linalg.norm(_vector(f"{where}.direction", light.direction)) == 0:
            _fail(f"{where}.direction", "must not be the zero vector")
        angle = _number(f"{where}.angular_radius_deg", light.angular_radius_deg, minimum=0.0)
        if angle > 10.0:
            _fail(f"{where}.angular_radius_deg", f"must be at most 10 degrees, got {angle:g}")
    else:
        if light.position_m is None:
            _fail(f"{where}.position_m", f"a {kind} light needs position_m = [x, y, z] in metres")
        if light.direction is not None:
            _fail(f"{where}.direction", f"a {kind} light has a position, not a direction")
        _vector(f"{where}.position_m", light.position_m)
        radius = _number(f"{where}.radius_m", light.radius_m, minimum=0.0)
        if kind in ("sphere", "disk") and radius <= 0:
            _fail(f"{where}.radius_m", f"a {kind} light needs radius_m > 0")
        if kind == "point" and radius != 0:
            _fail(f"{where}.radius_m", "a point light has no radius (use kind = \"sphere\" or \"disk\")")
    if light.normal is not None:
        if kind != "disk":
            _fail(f"{where}.normal", "only disk lights have a normal")
        if np.linalg.norm(_vector(f"{where}.normal", light.normal)) == 0:
            _fail(f"{where}.normal", "must not be the zero vector")
    colours = [name for name in ("rgb", "spectrum", "temperature_k") if getattr(light, name) is not None]
    if len(colours) > 1:
        _fail(where, f"give one colour (rgb, spectrum or temperature_k), got {', '.join(colours)}")
    if light.rgb is not None:
        _vector(f"{where}.rgb", light.rgb, non_negative=True)
    if light.spectrum is not None:
        try:
            wavelengths, values = light.spectrum
        except (TypeError, ValueError):
            _fail(f"{where}.spectrum", "must be (wavelengths_nm, values)")
        if len(wavelengths) != len(values) or len(values) < 2:
            _fail(f"{where}.spectrum", f"needs at least 2 wavelengths and as many values, got {len(wavelengths)} and {len(values)}")
        for k, (w, v) in enumerate(zip(wavelengths, values)):
            _number(f"{where}.spectrum.wavelengths_nm[{k}]", w, minimum=0.0, exclusive=True)
            _number(f"{where}.spectrum.values[{k}]", v, minimum=0.0)
        if any(b <= a for a, b in zip(wavelengths, wavelengths[1:])):
            _fail(f"{where}.spectrum.wavelengths_nm", "must increase strictly")
    if light.temperature_k is not None:
        temperature = _number(f"{where}.temperature_k", light.temperature_k)
        if not 500 <= temperature <= 50000:
            _fail(f"{where}.temperature_k", f"must be within 500-50000 K, got {temperature:g}")
    _number(f"{where}.intensity", light.intensity, minimum=0.0)
    _number(f"{where}.flare_intensity", light.flare_intensity, minimum=0.0)
    if not isinstance(light.flare, bool):
        _fail(f"{where}.flare", f"must be true or false, got {light.flare!r}")
    if not isinstance(light.name, str):
        _fail(f"{where}.name", f"must be a string, got {light.name!r}")


def check_settings(settings: RenderSettings, where: str = "render") -> None:
    _choice(f"{where}.quality", settings.quality, QUALITIES)
    if settings.samples is not None:
        _integer(f"{where}.samples", settings.samples, minimum=1)
    from jaxflare.colour._spectral import canonical_colour_space

    try:
        canonical_colour_space(settings.colour_space)
    except ValueError as error:
        _fail(f"{where}.colour_space", str(error))
    _choice(f"{where}.method", settings.method, METHODS)
    _choice(f"{where}.fresnel", settings.fresnel, FRESNEL_MODELS)
    _choice(f"{where}.weights", settings.weights, WEIGHTINGS)
    if not isinstance(settings.core, bool):
        _fail(f"{where}.core", f"must be true or false, got {settings.core!r}")
    threshold = _number(f"{where}.layer_threshold", settings.layer_threshold, minimum=0.0)
    if threshold > 1:
        _fail(f"{where}.layer_threshold", f"is a fraction of the brightest flare and must be <= 1, got {threshold:g}")
    _integer(f"{where}.max_flare_layers", settings.max_flare_layers, minimum=0)
    _choice(f"{where}.sampling", settings.sampling, SAMPLINGS)
    cull = _number(f"{where}.cull_threshold", settings.cull_threshold, minimum=0.0)
    if cull >= 1:
        _fail(f"{where}.cull_threshold", f"is a fraction of the brightest flare and must be < 1, got {cull:g}")
    _choice(f"{where}.exr_pixel_type", settings.exr_pixel_type, EXR_PIXEL_TYPES)
    _choice(f"{where}.exr_compression", settings.exr_compression, EXR_COMPRESSIONS)


def check_scene(scene: Scene) -> None:
    if not isinstance(scene.camera, Camera):
        _fail("camera", f"must be a jaxflare.Camera, got {type(scene.camera).__name__}")
    check_camera(scene.camera)
    if not scene.lights:
        _fail("light", "the scene has no lights: add at least one [[light]]")
    rotation = scene.camera.world_to_camera()
    for k, light in enumerate(scene.lights):
        if not isinstance(light, Light):
            _fail(f"light[{k}]", f"must be a jaxflare.Light, got {type(light).__name__}")
        check_light(light, f"light[{k}]")
        travel = light_travel_direction(scene.camera, light, rotation)
        angle = math.degrees(math.acos(max(-1.0, min(1.0, travel[2]))))
        if angle >= MAX_LIGHT_FIELD_ANGLE_DEG:
            label = f" ({light.name!r})" if light.name else ""
            side = "behind the camera" if travel[2] <= 0 else "too far off the optical axis"
            _fail(
                f"light[{k}]{label}",
                f"is {side}: {angle:.1f} degrees from the viewing direction; a flare needs a light within "
                f"{MAX_LIGHT_FIELD_ANGLE_DEG:g} degrees of it, in front of the lens",
            )
    for k, mesh in enumerate(scene.geometry):
        if not isinstance(mesh, Geometry):
            _fail(f"geometry[{k}]", f"must be a jaxflare.Geometry, got {type(mesh).__name__}")
        if not isinstance(mesh.file, str) or not mesh.file:
            _fail(f"geometry[{k}].file", f"must be a path to a mesh file, got {mesh.file!r}")
        _number(f"geometry[{k}].scale", mesh.scale, minimum=0.0, exclusive=True)
        if mesh.transform is not None:
            matrix = np.asarray(mesh.transform, dtype=object)
            if matrix.shape != (4, 4):
                _fail(f"geometry[{k}].transform", "must be a 4x4 matrix (4 rows of 4 numbers)")
            for r in range(4):
                _vector(f"geometry[{k}].transform[{r}]", mesh.transform[r], 4)
    if not isinstance(scene.render, RenderSettings):
        _fail("render", f"must be a jaxflare.RenderSettings, got {type(scene.render).__name__}")
    check_settings(scene.render)


def light_travel_direction(camera: Camera, light: Light, rotation: np.ndarray | None = None) -> np.ndarray:
    """Unit direction, in the lens frame, in which light from the light's centre travels to the camera."""
    rotation = camera.world_to_camera() if rotation is None else rotation
    if light.kind == "directional":
        towards_light = rotation @ np.asarray(light.direction, float)
        return -towards_light / np.linalg.norm(towards_light)
    offset = rotation @ (np.asarray(light.position_m, float) - np.asarray(camera.position_m, float))
    distance = np.linalg.norm(offset)
    if distance == 0:
        return np.array([0.0, 0.0, -1.0])
    return -offset / distance


# --------------------------------------------------------------------------- TOML

_CAMERA_KEYS = {
    "lens": "bundled lens name, or a .toml/.zmx path relative to the scene file",
    "f_number": "f-stop (default wide open)",
    "aperture_blades": "iris blade count, 0 = circular (default: the lens file's)",
    "aperture_rotation_deg": "iris rotation in degrees",
    "zoom_position": "zoom position index (zoom lenses)",
    "focal_length_mm": "focal length in mm (zoom lenses; interpolated between positions)",
    "focus_distance_m": "focus distance in metres (default inf)",
    "sensor_width_mm": "sensor width in mm (default: the lens file's)",
    "resolution": "[width, height] in pixels",
    "position_m": "camera position in metres",
    "look_at_m": "point the camera looks at, in metres",
    "rotation_deg": "[yaw, pitch, roll] in degrees (instead of look_at_m)",
    "up": "world up vector for look_at_m (default [0, 1, 0])",
    "coating": "coating preset for every glass-air interface",
    "surface_coatings": "list of {surfaces = [...], preset = ...} or {surfaces = [...], layers = [[index, nm], ...]}",
    "coating_tints": "list of {interface = k, rgb = [r, g, b]}",
    "dirt_map": "image of the front-lens dirt (path relative to the scene file)",
    "hood": "{shape = \"circular\" or \"rectangular\", distance_mm, radius_mm or half_width_mm and half_height_mm}",
    "distortion": "{k1, k2, k3, p1, p2, focal_length_px} or {st_map = \"file.exr\"}",
}
_LIGHT_KEYS = {
    "kind": "one of " + ", ".join(LIGHT_KINDS),
    "name": "a label",
    "position_m": "[x, y, z] in metres (point, sphere, disk)",
    "direction": "[x, y, z] from the camera towards the light (directional)",
    "radius_m": "radius in metres (sphere, disk)",
    "angular_radius_deg": "angular radius of a directional light's disc",
    "normal": "emitting side of a disk light",
    "rgb": "[r, g, b] linear colour",
    "spectrum": "{wavelengths_nm = [...], values = [...]}",
    "temperature_k": "black-body temperature in kelvin",
    "intensity": "brightness (see the format notes for units)",
    "flare_intensity": "multiplier in the flare pass",
    "flare": "true/false: render this light's flare",
}
_RENDER_KEYS = {field.name: "" for field in dataclasses.fields(RenderSettings)}


def _check_keys(where: str, table: Any, allowed: Mapping[str, str]) -> Mapping[str, Any]:
    if not isinstance(table, Mapping):
        _fail(where, f"must be a table, got {table!r}")
    for key in table:
        if key not in allowed:
            import difflib

            close = difflib.get_close_matches(key, list(allowed), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            _fail(f"{where}.{key}", f"unknown key{hint}; valid keys: {', '.join(allowed)}")
    return table


def _tuple3(value):
    return None if value is None else tuple(value) if isinstance(value, (list, tuple)) else value


def scene_from_dict(data: Mapping[str, Any], source: str | None = None) -> Scene:
    """Build a :class:`Scene` from parsed TOML (``camera``, ``light`` array, optional ``render``)."""
    prefix = f"{source}: " if source else ""
    try:
        _check_keys("scene", data, {"camera": "", "light": "", "render": "", "geometry": ""})
        if "camera" not in data:
            _fail("camera", "missing: the scene needs a [camera] table with at least lens = \"...\"")
        camera_table = dict(_check_keys("camera", data["camera"], _CAMERA_KEYS))
        if "lens" not in camera_table:
            _fail("camera.lens", "missing: name a bundled lens or a lens file")
        lens = camera_table["lens"]
        if isinstance(lens, str) and source and (lens.lower().endswith((".toml", ".zmx")) or os.sep in lens):
            lens = os.path.join(os.path.dirname(os.path.abspath(source)), lens)
        camera_table["lens"] = lens
        overrides = []
        for k, entry in enumerate(camera_table.pop("surface_coatings", [])):
            entry = _check_keys(f"camera.surface_coatings[{k}]", entry, {"surfaces": "", "preset": "", "layers": ""})
            surfaces = entry.get("surfaces", [])
            surfaces = tuple(surfaces) if isinstance(surfaces, list) else (surfaces,)
            layers = entry.get("layers")
            overrides.append(SurfaceCoating(surfaces, entry.get("preset"), None if layers is None else tuple(tuple(x) for x in layers)))
        tints = []
        for k, entry in enumerate(camera_table.pop("coating_tints", [])):
            entry = _check_keys(f"camera.coating_tints[{k}]", entry, {"interface": "", "rgb": ""})
            if "interface" not in entry or "rgb" not in entry:
                _fail(f"camera.coating_tints[{k}]", "needs interface = k and rgb = [r, g, b]")
            tints.append((entry["interface"], _tuple3(entry["rgb"])))
        for key in ("resolution", "position_m", "look_at_m", "rotation_deg", "up"):
            if key in camera_table:
                camera_table[key] = _tuple3(camera_table[key])
        if isinstance(camera_table.get("dirt_map"), str):
            camera_table["dirt_map"] = _relative(camera_table["dirt_map"], source)
        if "hood" in camera_table:
            hood = _check_keys("camera.hood", camera_table["hood"], {f.name: "" for f in dataclasses.fields(Hood)})
            camera_table["hood"] = Hood(**hood)
        if "distortion" in camera_table:
            distortion = dict(_check_keys("camera.distortion", camera_table["distortion"], {f.name: "" for f in dataclasses.fields(Distortion)}))
            if isinstance(distortion.get("st_map"), str):
                distortion["st_map"] = _relative(distortion["st_map"], source)
            camera_table["distortion"] = Distortion(**distortion)
        camera = Camera(**camera_table, surface_coatings=tuple(overrides), coating_tints=tuple(tints))

        light_tables = data.get("light", [])
        if isinstance(light_tables, Mapping):
            light_tables = [light_tables]
        if not isinstance(light_tables, list):
            _fail("light", "must be an array of tables: write each light as [[light]]")
        lights = []
        for k, table in enumerate(light_tables):
            table = dict(_check_keys(f"light[{k}]", table, _LIGHT_KEYS))
            for key in ("position_m", "direction", "normal", "rgb"):
                if key in table:
                    table[key] = _tuple3(table[key])
            if "spectrum" in table:
                spectrum = _check_keys(f"light[{k}].spectrum", table["spectrum"], {"wavelengths_nm": "", "values": ""})
                if "wavelengths_nm" not in spectrum or "values" not in spectrum:
                    _fail(f"light[{k}].spectrum", "needs wavelengths_nm = [...] and values = [...]")
                table["spectrum"] = (tuple(spectrum["wavelengths_nm"]), tuple(spectrum["values"]))
            lights.append(Light(**table))
        settings = RenderSettings(**_check_keys("render", data.get("render", {}), _RENDER_KEYS))
        meshes = []
        tables = data.get("geometry", [])
        if not isinstance(tables, list):
            _fail("geometry", "must be an array of tables: write each mesh as [[geometry]]")
        for k, table in enumerate(tables):
            table = dict(_check_keys(f"geometry[{k}]", table, {"file": "mesh file (OBJ, PLY, GLB/GLTF, STL)", "scale": "scene units to metres", "transform": "4x4 matrix"}))
            if "file" not in table:
                _fail(f"geometry[{k}].file", "missing: name the mesh file")
            if isinstance(table["file"], str):
                table["file"] = _relative(table["file"], source)
            if isinstance(table.get("transform"), list):
                table["transform"] = tuple(tuple(row) if isinstance(row, list) else row for row in table["transform"])
            meshes.append(Geometry(**table))
        return Scene(camera=camera, lights=tuple(lights), render=settings, geometry=tuple(meshes), source=source)
    except SceneError as error:
        raise SceneError(f"{prefix}{error}") from None


def _relative(path: str, source: str | None) -> str:
    """A path from a scene file, relative to that file's folder."""
    if source and not os.path.isabs(path):
        return os.path.join(os.path.dirname(os.path.abspath(source)), path)
    return path


def load_scene(path: str | os.PathLike) -> Scene:
    """Read and validate a scene TOML file (format: ``jaxflare/scenes/FORMAT.md``)."""
    path = os.fspath(path)
    if path == "demo":
        path = demo_scene_path()
    try:
        with open(path, "rb") as handle:
            data = tomllib.load(handle)
    except FileNotFoundError:
        raise FileNotFoundError(f"scene file not found: {path}") from None
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"{path}: not valid TOML: {error}") from None
    return scene_from_dict(data, source=path)


def demo_scene_path() -> str:
    """Path of the bundled demo scene (``jaxflare/scenes/demo.toml``)."""
    return os.path.join(os.path.dirname(__file__), "demo.toml")


# --------------------------------------------------------------------------- the camera's lens


def camera_lens(camera: Camera, *, with_iris: bool = True, with_coatings: bool = True):
    """The camera's lens with its zoom, focus, iris and coatings applied physically.

    ``with_iris=False`` leaves the iris wide open (the geometry polynomial path systems are built
    for, shared by every f-stop); ``with_coatings=False`` keeps the lens file's coatings.
    Errors name the camera key at fault.
    """
    import warnings

    from jaxflare.optics._lens import LensWarning
    from jaxflare.io._lens_files import load_lens
    from jaxflare.optics._prescription import LensFormatError

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", LensWarning)
            lens = load_lens(camera.lens)
    except (FileNotFoundError, LensFormatError) as error:
        _fail("camera.lens", str(error))
    try:
        if camera.zoom_position is not None:
            lens = lens.at_zoom(camera.zoom_position)
        elif camera.focal_length_mm is not None:
            lens = lens.at_focal_length(camera.focal_length_mm)
    except ValueError as error:
        _fail("camera.zoom_position" if camera.zoom_position is not None else "camera.focal_length_mm", str(error))
    if math.isfinite(camera.focus_distance_m):
        try:
            lens = lens.focused_at(camera.focus_distance_m * 1000.0)
        except ValueError as error:
            _fail("camera.focus_distance_m", str(error))
    if camera.aperture_blades is not None or camera.aperture_rotation_deg is not None:
        lens = lens.with_aperture(camera.aperture_blades, camera.aperture_rotation_deg)
    if with_iris and camera.f_number is not None:
        try:
            lens = lens.with_f_number(camera.f_number)
        except ValueError as error:
            _fail("camera.f_number", str(error))
    if with_coatings:
        from jaxflare.optics._coatings import with_coating, with_coating_layers

        if camera.coating != "lens":
            lens = with_coating(lens, camera.coating)
        for k, override in enumerate(camera.surface_coatings):
            try:
                if override.preset is not None:
                    lens = with_coating(lens, override.preset, override.surfaces)
                else:
                    lens = with_coating_layers(lens, override.surfaces, override.layers)
            except ValueError as error:
                _fail(f"camera.surface_coatings[{k}]", str(error))
    for k, (interface, _) in enumerate(camera.coating_tints):
        if interface >= lens.num_interfaces:
            _fail(f"camera.coating_tints[{k}].interface", f"must be an interface index 0..{lens.num_interfaces - 1} of '{lens.name}', got {interface}")
    return lens


def sensor_size_mm(camera: Camera, lens) -> tuple[float, float]:
    """(width, height) of the sensor area the image covers, in mm (square pixels)."""
    width = camera.sensor_width_mm or lens.prescription.sensor_width_mm
    return width, width * camera.resolution[1] / camera.resolution[0]
