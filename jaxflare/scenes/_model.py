"""The scene model: a camera (lens and its settings, sensor, pose), the lights whose flares are
rendered, occluding geometry and the render settings, as frozen dataclasses validated on
construction.

Frames and units. World positions are in metres, in a right-handed frame with y up. The camera
sits at ``position_m`` (the vertex of the lens's front surface) and looks along ``look_at_m`` (or
the rotation ``rotation_deg = [yaw, pitch, roll]`` applied to a camera that looks down -z with y
up). The lens frame (mm) has x to the right of the picture, y up and z along the optical axis
towards the sensor, so light from the scene travels towards +z and a point at distance d in front
of the camera has z = -d.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import numpy as np

from .._limits import MAX_RESOLUTION, MAX_SAMPLES
from ..colour import canonical_colour_space
from ..optics import COATING_INDEX_RANGE, COATING_PRESETS, F_NUMBER_RANGE, MAX_APERTURE_BLADES, MAX_COATING_THICKNESS_NM
from ._checks import choice, fail, integer, number, vector

LIGHT_KINDS = ("point", "sphere", "disk", "directional")


class LightKind(enum.IntEnum):
    """A light's kind, as the renderer's arrays store it (``Light.kind`` is its lower-case name)."""

    POINT = 0
    SPHERE = 1
    DISK = 2
    DIRECTIONAL = 3

    @property
    def label(self) -> str:
        return self.name.lower()

    @classmethod
    def from_label(cls, label: str) -> LightKind:
        return cls[label.upper()]


INTENSITY_UNITS = {
    "point": "radiant intensity, W/sr",
    "sphere": "radiance of the sphere's surface, W/(sr m^2)",
    "disk": "radiance of the disk, W/(sr m^2)",
    "directional": "radiance of the light's disc, W/(sr m^2) (irradiance at the lens, W/m^2, when angular_radius_deg is 0)",
}
"""What ``Light.intensity`` measures, per kind."""
QUALITIES = ("preview", "production")
METHODS = ("auto", "polynomial", "exact")
FRESNEL_MODELS = ("schlick", "exact")
WEIGHTINGS = ("all-samples", "sensor-hits")
SAMPLINGS = ("adaptive", "uniform")
ESTIMATORS = ("monte-carlo", "grid")
EXR_PIXEL_TYPES = ("half", "float")
EXR_COMPRESSIONS = ("none", "rle", "zips", "zip", "piz", "pxr24", "b44", "b44a", "dwaa", "dwab")
MAX_LIGHT_FIELD_ANGLE_DEG = 85.0
"""Lights further than this from the optical axis are rejected (their rays graze the front lens)."""
MAX_INTENSITY = 1.0e30
"""The brightest ``intensity * flare_intensity`` a light may have (any unit: far beyond the sun)."""
MAX_FLARE_LAYERS = 256
"""The most flares with a layer of their own (each is a full-size image)."""

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
    its clear aperture as seen from behind the camera (``jaxflare.rendering.effects._dirt``)."""
    hood: "Hood | None" = None
    distortion: "Distortion | None" = None

    def interface_tints(self, num_interfaces: int) -> np.ndarray:
        """The ``coating_tints`` as an ``(num_interfaces, 3)`` array of RGB multipliers (1 where
        none is set)."""
        tints = np.ones((num_interfaces, 3))
        for interface, rgb in self.coating_tints:
            tints[interface] = rgb
        return tints

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


HOOD_SHAPES = ("circular", "rectangular")


class Hood(eqx.Module):
    """A lens hood or matte box: an opening ``distance_mm`` in front of the front lens vertex,
    circular (``radius_mm``) or rectangular (``half_width_mm`` x ``half_height_mm``, lens frame x
    and y), centred on the optical axis.

    Build with ``Hood(shape="circular", distance_mm=60, radius_mm=35)`` or the :meth:`circular` /
    :meth:`rectangular` shorthands; invalid values raise :class:`SceneError` naming the field. The
    opening is the only stop the hood adds: that is exact for a hood whose walls enclose the
    straight lines from the opening's rim to the front lens's rim (a cylinder, prism or flared hood
    no narrower than the front lens), since any ray through both the opening and the front lens
    then stays inside. The light is assumed in front of the opening (z < -distance). A pytree: the
    renderer's visibility test (:func:`jaxflare.rendering.hood_visible`) takes it inside ``jit``.
    """

    shape: str = eqx.field(static=True, default="circular")
    distance_mm: float = 50.0
    radius_mm: float | None = None
    half_width_mm: float | None = None
    half_height_mm: float | None = None

    def __check_init__(self):
        check_hood(self, "hood")

    @classmethod
    def circular(cls, distance_mm, radius_mm) -> Hood:
        return cls("circular", distance_mm, radius_mm=radius_mm)

    @classmethod
    def rectangular(cls, distance_mm, half_width_mm, half_height_mm) -> Hood:
        return cls("rectangular", distance_mm, half_width_mm=half_width_mm, half_height_mm=half_height_mm)


def check_hood(hood: Hood, where: str) -> None:
    """A hood's shape and the sizes that shape needs (positive, finite mm); traced values (inside
    ``jit``) are not checked."""
    shape = choice(f"{where}.shape", hood.shape, HOOD_SHAPES)
    needed = ("radius_mm",) if shape == "circular" else ("half_width_mm", "half_height_mm")
    other = ("half_width_mm", "half_height_mm") if shape == "circular" else ("radius_mm",)
    for name in other:
        if getattr(hood, name) is not None:
            fail(f"{where}.{name}", f"belongs to the other hood shape: a {shape} hood takes {' and '.join(needed)}")
    for name in ("distance_mm",) + needed:
        value = getattr(hood, name)
        if value is None:
            fail(f"{where}.{name}", f"a {shape} hood needs {' and '.join(needed)}")
        if isinstance(value, jax.core.Tracer):
            continue
        if getattr(value, "shape", None) == ():  # a NumPy or JAX scalar
            value = float(value)
        number(f"{where}.{name}", value, minimum=0.0, exclusive=True)


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

    @property
    def intensity_unit(self) -> str:
        """What :attr:`intensity` measures for this kind of light (see :data:`INTENSITY_UNITS`)."""
        if self.kind == "directional" and self.angular_radius_deg == 0:
            return "irradiance at the lens, W/m^2"
        return INTENSITY_UNITS[self.kind]


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
    ``estimator``: ``"monte-carlo"`` (random samples, unbiased, the default) or ``"grid"`` (the
    deterministic ray-grid estimator after Hullin et al. 2011: noise-free, exact tracing; it ignores
    ``samples``, ``method``, ``sampling`` and ``weights``).
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
    estimator: str = "monte-carlo"


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
        fail(f"{where}.lens", f"must be a bundled lens name or a path to a .toml/.zmx lens file, got {camera.lens!r}")
    if camera.f_number is not None:
        number(f"{where}.f_number", camera.f_number, minimum=F_NUMBER_RANGE[0], maximum=F_NUMBER_RANGE[1])
    if camera.aperture_blades is not None:
        blades = integer(f"{where}.aperture_blades", camera.aperture_blades, minimum=0, maximum=MAX_APERTURE_BLADES)
        if blades in (1, 2):
            fail(f"{where}.aperture_blades", "must be 0 (circular iris) or at least 3")
    if camera.aperture_rotation_deg is not None:
        number(f"{where}.aperture_rotation_deg", camera.aperture_rotation_deg)
    if camera.zoom_position is not None and camera.focal_length_mm is not None:
        fail(where, "give zoom_position or focal_length_mm, not both")
    if camera.zoom_position is not None:
        integer(f"{where}.zoom_position", camera.zoom_position, minimum=0, maximum=1000)
    if camera.focal_length_mm is not None:
        number(f"{where}.focal_length_mm", camera.focal_length_mm, minimum=0.0, exclusive=True, maximum=1e5)
    number(f"{where}.focus_distance_m", camera.focus_distance_m, minimum=0.0, exclusive=True, allow_inf=True, maximum=1e9)
    if camera.sensor_width_mm is not None:
        number(f"{where}.sensor_width_mm", camera.sensor_width_mm, minimum=0.0, exclusive=True, maximum=1000.0)
    if (
        isinstance(camera.resolution, (str, bytes))
        or not isinstance(camera.resolution, Sequence)
        or len(camera.resolution) != 2
    ):
        fail(f"{where}.resolution", f"must be [width, height] in pixels, got {camera.resolution!r}")
    for k, value in enumerate(camera.resolution):
        integer(f"{where}.resolution[{k}]", value, minimum=1, maximum=MAX_RESOLUTION)
    vector(f"{where}.position_m", camera.position_m)
    vector(f"{where}.up", camera.up)
    if camera.look_at_m is not None and camera.rotation_deg is not None:
        fail(where, "give look_at_m or rotation_deg, not both")
    if camera.look_at_m is not None:
        forward = np.subtract(vector(f"{where}.look_at_m", camera.look_at_m), camera.position_m)
        if np.linalg.norm(forward) == 0:
            fail(f"{where}.look_at_m", "must differ from position_m")
        if np.linalg.norm(np.cross(forward, camera.up)) <= 1e-9 * np.linalg.norm(forward) * np.linalg.norm(camera.up):
            fail(f"{where}.up", "must not be parallel to the viewing direction (look_at_m - position_m)")
    if camera.rotation_deg is not None:
        vector(f"{where}.rotation_deg", camera.rotation_deg)
    choice(f"{where}.coating", camera.coating, tuple(COATING_PRESETS))
    for k, override in enumerate(camera.surface_coatings):
        place = f"{where}.surface_coatings[{k}]"
        if not override.surfaces:
            fail(f"{place}.surfaces", "must list at least one surface index")
        for s in override.surfaces:
            integer(f"{place}.surfaces", s, minimum=0)
        if (override.preset is None) == (override.layers is None):
            fail(place, "give exactly one of preset or layers")
        if override.preset is not None:
            choice(f"{place}.preset", override.preset, tuple(COATING_PRESETS))
        for m, layer in enumerate(override.layers or ()):
            index, thickness = vector(f"{place}.layers[{m}]", layer, 2)
            if not (COATING_INDEX_RANGE[0] <= index <= COATING_INDEX_RANGE[1] and 0.0 <= thickness <= MAX_COATING_THICKNESS_NM):
                fail(
                    f"{place}.layers[{m}]",
                    f"must be [index {COATING_INDEX_RANGE[0]:g} .. {COATING_INDEX_RANGE[1]:g}, thickness_nm 0 .. {MAX_COATING_THICKNESS_NM:g}], got {list(layer)}",
                )
    for k, (interface, rgb) in enumerate(camera.coating_tints):
        integer(f"{where}.coating_tints[{k}].interface", interface, minimum=0)
        vector(f"{where}.coating_tints[{k}].rgb", rgb, non_negative=True)
    if camera.dirt_map is not None and (not isinstance(camera.dirt_map, str) or not camera.dirt_map):
        fail(f"{where}.dirt_map", f"must be a path to an image file, got {camera.dirt_map!r}")
    if camera.hood is not None:
        if not isinstance(camera.hood, Hood):
            fail(f"{where}.hood", f"must be a jaxflare.Hood, got {type(camera.hood).__name__}")
        check_hood(camera.hood, f"{where}.hood")
    if camera.distortion is not None:
        distortion = camera.distortion
        if not isinstance(distortion, Distortion):
            fail(f"{where}.distortion", f"must be a jaxflare.Distortion, got {type(distortion).__name__}")
        for name in ("k1", "k2", "k3", "p1", "p2"):
            number(f"{where}.distortion.{name}", getattr(distortion, name))
        if distortion.focal_length_px is not None:
            number(f"{where}.distortion.focal_length_px", distortion.focal_length_px, minimum=0.0, exclusive=True)
        if distortion.st_map is not None and any(getattr(distortion, n) for n in ("k1", "k2", "k3", "p1", "p2")):
            fail(f"{where}.distortion", "give Brown-Conrady coefficients or an st_map, not both")


def check_light(light: Light, where: str) -> None:
    kind = choice(f"{where}.kind", light.kind, LIGHT_KINDS)
    if kind == "directional":
        if light.direction is None:
            fail(f"{where}.direction", "a directional light needs direction = [x, y, z] (from the camera towards the light)")
        if light.position_m is not None:
            fail(f"{where}.position_m", "a directional light has a direction, not a position")
        if np.linalg.norm(vector(f"{where}.direction", light.direction)) == 0:
            fail(f"{where}.direction", "must not be the zero vector")
        angle = number(f"{where}.angular_radius_deg", light.angular_radius_deg, minimum=0.0)
        if angle > 10.0:
            fail(f"{where}.angular_radius_deg", f"must be at most 10 degrees, got {angle:g}")
    else:
        if light.position_m is None:
            fail(f"{where}.position_m", f"a {kind} light needs position_m = [x, y, z] in metres")
        if light.direction is not None:
            fail(f"{where}.direction", f"a {kind} light has a position, not a direction")
        vector(f"{where}.position_m", light.position_m)
        radius = number(f"{where}.radius_m", light.radius_m, minimum=0.0)
        if kind in ("sphere", "disk") and radius <= 0:
            fail(f"{where}.radius_m", f"a {kind} light needs radius_m > 0")
        if kind == "point" and radius != 0:
            fail(f"{where}.radius_m", "a point light has no radius (use kind = \"sphere\" or \"disk\")")
    if light.normal is not None:
        if kind != "disk":
            fail(f"{where}.normal", "only disk lights have a normal")
        if np.linalg.norm(vector(f"{where}.normal", light.normal)) == 0:
            fail(f"{where}.normal", "must not be the zero vector")
    colours = [name for name in ("rgb", "spectrum", "temperature_k") if getattr(light, name) is not None]
    if len(colours) > 1:
        fail(where, f"give one colour (rgb, spectrum or temperature_k), got {', '.join(colours)}")
    if light.rgb is not None:
        vector(f"{where}.rgb", light.rgb, non_negative=True)
    if light.spectrum is not None:
        try:
            wavelengths, values = light.spectrum
        except (TypeError, ValueError):
            fail(f"{where}.spectrum", "must be (wavelengths_nm, values)")
        if len(wavelengths) != len(values) or len(values) < 2:
            fail(f"{where}.spectrum", f"needs at least 2 wavelengths and as many values, got {len(wavelengths)} and {len(values)}")
        for k, (w, v) in enumerate(zip(wavelengths, values)):
            number(f"{where}.spectrum.wavelengths_nm[{k}]", w, minimum=0.0, exclusive=True)
            number(f"{where}.spectrum.values[{k}]", v, minimum=0.0)
        if any(b <= a for a, b in zip(wavelengths, wavelengths[1:])):
            fail(f"{where}.spectrum.wavelengths_nm", "must increase strictly")
    if light.temperature_k is not None:
        temperature = number(f"{where}.temperature_k", light.temperature_k)
        if not 500 <= temperature <= 50000:
            fail(f"{where}.temperature_k", f"must be within 500-50000 K, got {temperature:g}")
    intensity = number(f"{where}.intensity", light.intensity, minimum=0.0, maximum=MAX_INTENSITY)
    gain = number(f"{where}.flare_intensity", light.flare_intensity, minimum=0.0, maximum=MAX_INTENSITY)
    if intensity * gain > MAX_INTENSITY:
        fail(where, f"intensity x flare_intensity = {intensity * gain:g} is beyond the maximum {MAX_INTENSITY:g}")
    if not isinstance(light.flare, bool):
        fail(f"{where}.flare", f"must be true or false, got {light.flare!r}")
    if not isinstance(light.name, str):
        fail(f"{where}.name", f"must be a string, got {light.name!r}")


def check_settings(settings: RenderSettings, where: str = "render") -> None:
    choice(f"{where}.quality", settings.quality, QUALITIES)
    if settings.samples is not None:
        integer(f"{where}.samples", settings.samples, minimum=1, maximum=MAX_SAMPLES)
    try:
        canonical_colour_space(settings.colour_space)
    except ValueError as error:
        fail(f"{where}.colour_space", str(error))
    choice(f"{where}.method", settings.method, METHODS)
    choice(f"{where}.fresnel", settings.fresnel, FRESNEL_MODELS)
    choice(f"{where}.weights", settings.weights, WEIGHTINGS)
    if not isinstance(settings.core, bool):
        fail(f"{where}.core", f"must be true or false, got {settings.core!r}")
    threshold = number(f"{where}.layer_threshold", settings.layer_threshold, minimum=0.0)
    if threshold > 1:
        fail(f"{where}.layer_threshold", f"is a fraction of the brightest flare and must be <= 1, got {threshold:g}")
    integer(f"{where}.max_flare_layers", settings.max_flare_layers, minimum=0, maximum=MAX_FLARE_LAYERS)
    choice(f"{where}.sampling", settings.sampling, SAMPLINGS)
    cull = number(f"{where}.cull_threshold", settings.cull_threshold, minimum=0.0)
    if cull >= 1:
        fail(f"{where}.cull_threshold", f"is a fraction of the brightest flare and must be < 1, got {cull:g}")
    choice(f"{where}.estimator", settings.estimator, ESTIMATORS)
    choice(f"{where}.exr_pixel_type", settings.exr_pixel_type, EXR_PIXEL_TYPES)
    choice(f"{where}.exr_compression", settings.exr_compression, EXR_COMPRESSIONS)


def check_scene(scene: Scene) -> None:
    if not isinstance(scene.camera, Camera):
        fail("camera", f"must be a jaxflare.Camera, got {type(scene.camera).__name__}")
    check_camera(scene.camera)
    if not scene.lights:
        fail("light", "the scene has no lights: add at least one [[light]]")
    rotation = scene.camera.world_to_camera()
    for k, light in enumerate(scene.lights):
        if not isinstance(light, Light):
            fail(f"light[{k}]", f"must be a jaxflare.Light, got {type(light).__name__}")
        check_light(light, f"light[{k}]")
        travel = light_travel_direction(scene.camera, light, rotation)
        angle = math.degrees(math.acos(max(-1.0, min(1.0, travel[2]))))
        if angle >= MAX_LIGHT_FIELD_ANGLE_DEG:
            label = f" ({light.name!r})" if light.name else ""
            side = "behind the camera" if travel[2] <= 0 else "too far off the optical axis"
            fail(
                f"light[{k}]{label}",
                f"is {side}: {angle:.1f} degrees from the viewing direction; a flare needs a light within "
                f"{MAX_LIGHT_FIELD_ANGLE_DEG:g} degrees of it, in front of the lens",
            )
    for k, mesh in enumerate(scene.geometry):
        if not isinstance(mesh, Geometry):
            fail(f"geometry[{k}]", f"must be a jaxflare.Geometry, got {type(mesh).__name__}")
        if not isinstance(mesh.file, str) or not mesh.file:
            fail(f"geometry[{k}].file", f"must be a path to a mesh file, got {mesh.file!r}")
        number(f"geometry[{k}].scale", mesh.scale, minimum=0.0, exclusive=True)
        if mesh.transform is not None:
            matrix = np.asarray(mesh.transform, dtype=object)
            if matrix.shape != (4, 4):
                fail(f"geometry[{k}].transform", "must be a 4x4 matrix (4 rows of 4 numbers)")
            for r in range(4):
                vector(f"geometry[{k}].transform[{r}]", mesh.transform[r], 4)
    if not isinstance(scene.render, RenderSettings):
        fail("render", f"must be a jaxflare.RenderSettings, got {type(scene.render).__name__}")
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
