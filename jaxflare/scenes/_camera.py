"""The camera's lens, physically set up: zoom, focus, iris and coatings applied to the lens file."""

from __future__ import annotations

import math
import warnings

from ..io import load_lens
from ..optics import LensFormatError, LensWarning, with_coating, with_coating_layers
from ._checks import fail
from ._model import Camera

# --------------------------------------------------------------------------- the camera's lens


def camera_lens(camera: Camera, *, with_iris: bool = True, with_coatings: bool = True):
    """The camera's lens with its zoom, focus, iris and coatings applied physically.

    ``with_iris=False`` leaves the iris wide open (the geometry polynomial path systems are built
    for, shared by every f-stop); ``with_coatings=False`` keeps the lens file's coatings.
    Errors name the camera key at fault.
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", LensWarning)
            lens = load_lens(camera.lens)
    except (FileNotFoundError, LensFormatError) as error:
        fail("camera.lens", str(error))
    try:
        if camera.zoom_position is not None:
            lens = lens.at_zoom(camera.zoom_position)
        elif camera.focal_length_mm is not None:
            lens = lens.at_focal_length(camera.focal_length_mm)
    except ValueError as error:
        fail("camera.zoom_position" if camera.zoom_position is not None else "camera.focal_length_mm", str(error))
    if math.isfinite(camera.focus_distance_m):
        try:
            lens = lens.focused_at(camera.focus_distance_m * 1000.0)
        except ValueError as error:
            fail("camera.focus_distance_m", str(error))
    if camera.aperture_blades is not None or camera.aperture_rotation_deg is not None:
        lens = lens.with_aperture(camera.aperture_blades, camera.aperture_rotation_deg)
    if with_iris and camera.f_number is not None:
        try:
            lens = lens.with_f_number(camera.f_number)
        except ValueError as error:
            fail("camera.f_number", str(error))
    if with_coatings:
        if camera.coating != "lens":
            lens = with_coating(lens, camera.coating)
        for k, override in enumerate(camera.surface_coatings):
            try:
                if override.preset is not None:
                    lens = with_coating(lens, override.preset, override.surfaces)
                else:
                    lens = with_coating_layers(lens, override.surfaces, override.layers)
            except ValueError as error:
                fail(f"camera.surface_coatings[{k}]", str(error))
    for k, (interface, _) in enumerate(camera.coating_tints):
        if interface >= lens.num_interfaces:
            fail(f"camera.coating_tints[{k}].interface", f"must be an interface index 0..{lens.num_interfaces - 1} of '{lens.name}', got {interface}")
    return lens


def sensor_size_mm(camera: Camera, lens) -> tuple[float, float]:
    """(width, height) of the sensor area the image covers, in mm (square pixels)."""
    width = camera.sensor_width_mm or lens.prescription.sensor_width_mm
    return width, width * camera.resolution[1] / camera.resolution[0]
