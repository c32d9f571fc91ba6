"""Reading scenes from TOML files (the format of ``jaxflare/scenes/FORMAT.md``)."""

from __future__ import annotations

import dataclasses
import difflib
import os
import tomllib
from collections.abc import Mapping
from typing import Any

from ..io import decode_text, read_input_bytes
from ._checks import SceneError, fail, sequence
from ._model import LIGHT_KINDS, Camera, Distortion, Geometry, Hood, Light, RenderSettings, Scene, SurfaceCoating

# --------------------------------------------------------------------------- TOML

CAMERA_KEYS = {
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
LIGHT_KEYS = {
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
RENDER_KEYS = {field.name: "" for field in dataclasses.fields(RenderSettings)}


def _check_keys(where: str, table: Any, allowed: Mapping[str, str]) -> Mapping[str, Any]:
    if not isinstance(table, Mapping):
        fail(where, f"must be a table, got {table!r}")
    for key in table:
        if key not in allowed:
            close = difflib.get_close_matches(key, list(allowed), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            fail(f"{where}.{key}", f"unknown key{hint}; valid keys: {', '.join(allowed)}")
    return table


def _tuple3(value):
    return None if value is None else tuple(value) if isinstance(value, (list, tuple)) else value


def scene_from_dict(data: Mapping[str, Any], source: str | None = None) -> Scene:
    """Build a :class:`Scene` from parsed TOML (``camera``, ``light`` array, optional ``render``)."""
    prefix = f"{source}: " if source else ""
    try:
        _check_keys("scene", data, {"camera": "", "light": "", "render": "", "geometry": ""})
        if "camera" not in data:
            fail("camera", "missing: the scene needs a [camera] table with at least lens = \"...\"")
        camera_table = dict(_check_keys("camera", data["camera"], CAMERA_KEYS))
        if "lens" not in camera_table:
            fail("camera.lens", "missing: name a bundled lens or a lens file")
        lens = camera_table["lens"]
        if isinstance(lens, str) and source and (lens.lower().endswith((".toml", ".zmx")) or os.sep in lens):
            lens = os.path.join(os.path.dirname(os.path.abspath(source)), lens)
        camera_table["lens"] = lens
        overrides = []
        for k, entry in enumerate(sequence("camera.surface_coatings", camera_table.pop("surface_coatings", []), "tables {surfaces = [...], preset = ...}")):
            entry = _check_keys(f"camera.surface_coatings[{k}]", entry, {"surfaces": "", "preset": "", "layers": ""})
            surfaces = entry.get("surfaces", [])
            surfaces = tuple(surfaces) if isinstance(surfaces, list) else (surfaces,)
            layers = entry.get("layers")
            if layers is not None:
                layers = tuple(
                    tuple(sequence(f"camera.surface_coatings[{k}].layers[{m}]", x, "2 numbers [index, thickness_nm]"))
                    for m, x in enumerate(sequence(f"camera.surface_coatings[{k}].layers", layers, "[index, thickness_nm] pairs"))
                )
            overrides.append(SurfaceCoating(surfaces, entry.get("preset"), layers))
        tints = []
        for k, entry in enumerate(sequence("camera.coating_tints", camera_table.pop("coating_tints", []), "tables {interface = k, rgb = [r, g, b]}")):
            entry = _check_keys(f"camera.coating_tints[{k}]", entry, {"interface": "", "rgb": ""})
            if "interface" not in entry or "rgb" not in entry:
                fail(f"camera.coating_tints[{k}]", "needs interface = k and rgb = [r, g, b]")
            tints.append((entry["interface"], _tuple3(entry["rgb"])))
        for key in ("resolution", "position_m", "look_at_m", "rotation_deg", "up"):
            if key in camera_table:
                camera_table[key] = _tuple3(camera_table[key])
        if isinstance(camera_table.get("dirt_map"), str):
            camera_table["dirt_map"] = _relative(camera_table["dirt_map"], source)
        if "hood" in camera_table:
            hood = _check_keys("camera.hood", camera_table["hood"], {f.name: "" for f in dataclasses.fields(Hood)})
            try:
                camera_table["hood"] = Hood(**hood)
            except SceneError as error:
                raise SceneError(f"camera.{error}") from None
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
            fail("light", "must be an array of tables: write each light as [[light]]")
        lights = []
        for k, table in enumerate(light_tables):
            table = dict(_check_keys(f"light[{k}]", table, LIGHT_KEYS))
            for key in ("position_m", "direction", "normal", "rgb"):
                if key in table:
                    table[key] = _tuple3(table[key])
            if "spectrum" in table:
                spectrum = _check_keys(f"light[{k}].spectrum", table["spectrum"], {"wavelengths_nm": "", "values": ""})
                if "wavelengths_nm" not in spectrum or "values" not in spectrum:
                    fail(f"light[{k}].spectrum", "needs wavelengths_nm = [...] and values = [...]")
                table["spectrum"] = (
                    tuple(sequence(f"light[{k}].spectrum.wavelengths_nm", spectrum["wavelengths_nm"], "wavelengths in nm")),
                    tuple(sequence(f"light[{k}].spectrum.values", spectrum["values"], "numbers")),
                )
            lights.append(Light(**table))
        settings = RenderSettings(**_check_keys("render", data.get("render", {}), RENDER_KEYS))
        meshes = []
        tables = data.get("geometry", [])
        if not isinstance(tables, list):
            fail("geometry", "must be an array of tables: write each mesh as [[geometry]]")
        for k, table in enumerate(tables):
            table = dict(_check_keys(f"geometry[{k}]", table, {"file": "mesh file (OBJ, PLY, GLB/GLTF, STL)", "scale": "scene units to metres", "transform": "4x4 matrix"}))
            if "file" not in table:
                fail(f"geometry[{k}].file", "missing: name the mesh file")
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
    text = decode_text(read_input_bytes(path, "scene file", SceneError), path, "scene file", SceneError)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"{path}: not valid TOML: {error}") from None
    return scene_from_dict(data, source=path)


def demo_scene_path() -> str:
    """Path of the bundled demo scene (``jaxflare/scenes/demo.toml``)."""
    return os.path.join(os.path.dirname(__file__), "demo.toml")
