"""Scenes: the camera (lens, iris, zoom, focus, sensor, pose, coatings, dirt, hood, distortion), the
lights whose flares are rendered, occluding geometry, and the render settings.

A scene is built in Python (:class:`Scene`, :class:`Camera`, :class:`Light`, :class:`RenderSettings`)
or read from a TOML file (:func:`load_scene`, documented in ``jaxflare/scenes/FORMAT.md``). Both
routes validate the same way: a bad value raises :class:`SceneError` naming the key (``light[1].
intensity``) and what would be valid. :func:`camera_lens` applies the camera's settings to its lens
physically. Builds on :mod:`jaxflare.optics`, :mod:`jaxflare.colour` and :mod:`jaxflare.io`.
"""

from ._camera import camera_lens, sensor_size_mm
from ._checks import SceneError
from ._model import (
    ESTIMATORS,
    EXR_COMPRESSIONS,
    EXR_PIXEL_TYPES,
    FRESNEL_MODELS,
    HOOD_SHAPES,
    INTENSITY_UNITS,
    LIGHT_KINDS,
    MAX_LIGHT_FIELD_ANGLE_DEG,
    METHODS,
    QUALITIES,
    SAMPLINGS,
    WEIGHTINGS,
    Camera,
    Distortion,
    Geometry,
    Hood,
    Light,
    LightKind,
    RenderSettings,
    Scene,
    SurfaceCoating,
    check_camera,
    check_light,
    check_scene,
    check_settings,
    light_travel_direction,
)
from ._toml import CAMERA_KEYS, LIGHT_KEYS, RENDER_KEYS, demo_scene_path, load_scene, scene_from_dict

__all__ = [
    "CAMERA_KEYS",
    "ESTIMATORS",
    "EXR_COMPRESSIONS",
    "EXR_PIXEL_TYPES",
    "FRESNEL_MODELS",
    "HOOD_SHAPES",
    "INTENSITY_UNITS",
    "LIGHT_KEYS",
    "LIGHT_KINDS",
    "MAX_LIGHT_FIELD_ANGLE_DEG",
    "METHODS",
    "QUALITIES",
    "RENDER_KEYS",
    "SAMPLINGS",
    "WEIGHTINGS",
    "Camera",
    "Distortion",
    "Geometry",
    "Hood",
    "Light",
    "LightKind",
    "RenderSettings",
    "Scene",
    "SceneError",
    "SurfaceCoating",
    "camera_lens",
    "check_camera",
    "check_light",
    "check_scene",
    "check_settings",
    "demo_scene_path",
    "light_travel_direction",
    "load_scene",
    "scene_from_dict",
]
