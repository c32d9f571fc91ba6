"""First-order (paraxial) optics of a prescription whose media are given by their d-line index,
in plain Python: what the lens-file importers need before any glass is resolved (where the
sensor of a file that leaves it "at focus" goes, which surface limits the axial beam when a file
names no iris). The lens's own paraxial methods (:class:`jaxflare.Lens`) resolve catalog glasses
and are the reference; this is the same y-nu trace for indices known up front.
"""

from __future__ import annotations

import math
from collections.abc import Sequence


def marginal_ray(curvatures: Sequence[float], thicknesses: Sequence[float], indices: Sequence[float]) -> tuple[list[float], float, float]:
    """Trace the paraxial ray of unit height parallel to the axis through the surfaces.

    ``indices[k]`` is the index after surface ``k`` (object space is air). Returns the ray height
    at every surface, the effective focal length and the back focal distance from the last
    surface (both ``inf`` for an afocal system).
    """
    y, nu, n = 1.0, 0.0, 1.0
    heights = []
    for k, (c, n_after) in enumerate(zip(curvatures, indices)):
        if k > 0:
            y += thicknesses[k - 1] * nu / n
        heights.append(y)
        nu -= (n_after - n) * c * y
        n = n_after
    if nu == 0.0:
        return heights, math.inf, math.inf
    return heights, -1.0 / nu, -y / nu


def limiting_surface(heights: Sequence[float], semi_apertures: Sequence[float]) -> int | None:
    """The surface whose semi-aperture limits an axial beam (the aperture stop, physically):
    the smallest ratio of semi-aperture to marginal-ray height; None if no surface has both."""
    best, best_ratio = None, math.inf
    for k, (h, semi) in enumerate(zip(heights, semi_apertures)):
        if math.isfinite(semi) and semi > 0 and abs(h) > 1e-12:
            ratio = semi / abs(h)
            if ratio < best_ratio:
                best, best_ratio = k, ratio
    return best
