"""First-order (paraxial) optics of a lens: y-nu ray transfer matrices per meridional plane.

A paraxial ray is ``(y, nu)``: height in mm and reduced angle ``n * u`` (refractive index times
slope). Refraction at a surface of curvature ``c`` from index ``n`` to ``n'`` is
``[[1, 0], [-(n' - n) c, 1]]``; a gap of thickness ``t`` in index ``n`` is ``[[1, t / n], [0, 1]]``.
Every matrix has determinant 1. Cylindrical surfaces have power in one plane only, so the x-z and
y-z planes get separate systems (they agree for rotationally symmetric lenses).

Conventions: object and image space are air (n = 1), which the lens format guarantees.
All functions work on NumPy float64 arrays; they are used for analysis, set-up and checks.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

Plane = Literal["x", "y"]


def refraction_matrix(power_per_mm: float) -> np.ndarray:
    return np.array([[1.0, 0.0], [-power_per_mm, 1.0]])


def transfer_matrix(thickness_mm: float, index: float) -> np.ndarray:
    return np.array([[1.0, thickness_mm / index], [0.0, 1.0]])


def surface_powers(curvatures_per_mm: np.ndarray, indices_before: np.ndarray, indices_after: np.ndarray) -> np.ndarray:
    """Surface powers (n' - n) c in 1/mm."""
    return (indices_after - indices_before) * curvatures_per_mm


def system_matrix(
    powers_per_mm: np.ndarray,
    thicknesses_mm: np.ndarray,
    media_indices: np.ndarray,
    first: int,
    last: int,
    *,
    include_first_refraction: bool = True,
) -> np.ndarray:
    """Matrix from just before surface ``first`` to just after surface ``last`` (inclusive).

    ``media_indices[s]`` is the index in front of surface s (``media_indices[s + 1]`` behind it).
    Gaps between consecutive surfaces are included; the gap after ``last`` is not.
    """
    matrix = np.eye(2)
    for s in range(first, last + 1):
        if s > first:
            matrix = transfer_matrix(thicknesses_mm[s - 1], media_indices[s]) @ matrix
        if s > first or include_first_refraction:
            matrix = refraction_matrix(powers_per_mm[s]) @ matrix
    return matrix


def effective_focal_length(system: np.ndarray) -> float:
    """EFL in mm of a system in air: ``-1 / C``; ``inf`` for an afocal system."""
    c = system[1, 0]
    return math.inf if c == 0.0 else -1.0 / c


def back_focal_distance(system: np.ndarray) -> float:
    """Distance in mm from the last vertex to the rear focal point: ``-A / C``."""
    a, c = system[0, 0], system[1, 0]
    return math.inf if c == 0.0 else -a / c


def image_distance(system: np.ndarray, object_distance_mm: float) -> float:
    """Distance from the last vertex to the paraxial image of an axial point.

    ``object_distance_mm`` is measured from the first vertex towards the object (positive in front
    of the lens); ``inf`` gives the back focal distance.
    """
    if math.isinf(object_distance_mm):
        return back_focal_distance(system)
    (a, b), (c, d) = system
    y = a * object_distance_mm + b
    nu = c * object_distance_mm + d
    if nu == 0.0:
        return math.inf
    return -y / nu


def stop_image(system: np.ndarray) -> tuple[float, float]:
    """Position and magnification of the image of a plane through ``system`` (forward direction).

    Returns ``(z, m)``: the image lies ``z`` mm after the system's last vertex and is ``m`` times the
    object's size. Used for the exit pupil.
    """
    (a, b), (c, d) = system
    if d == 0.0:
        return math.inf, math.inf
    return -b / d, 1.0 / d


def entrance_pupil(system_front_to_stop: np.ndarray) -> tuple[float, float]:
    """Entrance pupil ``(z, m)``: position after the first vertex and magnification stop -> pupil.

    ``system_front_to_stop`` maps a ray at the first vertex (in object space) to the stop plane.
    """
    (a, b), _ = system_front_to_stop
    if a == 0.0:
        return math.inf, math.inf
    return b / a, 1.0 / a
