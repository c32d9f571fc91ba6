"""Where light enters a lens and how wide a field it images: the entrance plane in front of the
front element, and the half field of view found by exact tracing."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._lens import Lens
from ._surface import sag_and_slope
from ._trace import trace


def front_rim_sag_mm(lens: Lens) -> float:
    """Sag (mm) of the front surface at the rim of its clear aperture (negative when the rim lies
    in front of the vertex)."""
    c, k = float(lens.curvature_per_mm[0]), float(lens.conic[0])
    rho2 = float(lens.semi_aperture_mm[0]) ** 2
    sag, _ = sag_and_slope(np.float64(rho2), c, k, np.asarray(lens.aspheric_coefficients[0], np.float64))
    return float(sag)


def entrance_plane_z_mm(lens: Lens) -> float:
    """z of the entrance plane: 1 mm in front of the front lens's vertex or rim, whichever is
    further forward."""
    return min(0.0, front_rim_sag_mm(lens)) - 1.0


def half_field_of_view_deg(lens: Lens, wavelength_nm: float = 587.56) -> float:
    """Half the diagonal field of view in degrees: the field angle whose chief ray (the ray of a
    meridional fan passing closest to the stop centre) meets the sensor at its corner.

    Found by exact tracing, so it holds for fisheyes as well as rectilinear lenses. If rays stop
    getting through before the corner is reached, the largest angle that still images is returned.
    """
    p = lens.prescription
    half_diagonal = 0.5 * math.hypot(p.sensor_width_mm, p.sensor_height_mm)
    angles = np.linspace(0.0, 88.0, 177)
    fan = 97
    entrance_z = entrance_plane_z_mm(lens)
    radius = float(lens.semi_aperture_mm[0])
    with jax.enable_x64(True):
        heights = np.linspace(-1.0, 1.0, fan) * radius
        theta = np.radians(angles)[:, None]
        ys = np.broadcast_to(heights[None, :], (len(angles), fan)).copy()  # a fan across the front aperture per angle
        origins = np.stack([np.zeros_like(ys), ys, np.full_like(ys, entrance_z)], -1).reshape(-1, 3)
        directions = np.stack([np.zeros_like(ys), np.broadcast_to(np.sin(theta), ys.shape), np.broadcast_to(np.cos(theta), ys.shape)], -1).reshape(-1, 3)
        lens64 = cast_floating(lens, jnp.float64)
        # shift each fan so that it is centred on the entrance pupil: aim at the stop centre
        z_pupil, _ = lens64.entrance_pupil(wavelength_nm)
        shift = -(z_pupil - entrance_z) * np.tan(np.radians(np.repeat(angles, fan)))
        origins[:, 1] += shift
        result = trace(lens64, origins, directions, wavelength_nm)
        valid = np.asarray(result.valid).reshape(len(angles), fan)
        sensor_y = np.asarray(result.positions[:, 1]).reshape(len(angles), fan)
        stop_r = np.hypot(*np.asarray(result.stop_positions[:, 0, :2]).T).reshape(len(angles), fan)
    chief_height = np.full(len(angles), np.nan)
    for a in range(len(angles)):
        if valid[a].any():
            k = np.argmin(np.where(valid[a], stop_r[a], np.inf))
            chief_height[a] = abs(sensor_y[a, k])
    imaging = np.flatnonzero(np.isfinite(chief_height))
    if imaging.size == 0:
        raise ValueError(f"no ray of '{lens.name}' reaches the sensor: cannot find its field of view")
    beyond = imaging[chief_height[imaging] >= half_diagonal]
    if beyond.size == 0:
        return float(angles[imaging[-1]])
    b = beyond[0]
    if b == 0:
        return float(angles[1])
    a = b - 1
    if not np.isfinite(chief_height[a]):
        return float(angles[b])
    frac = (half_diagonal - chief_height[a]) / (chief_height[b] - chief_height[a])
    return float(angles[a] + frac * (angles[b] - angles[a]))






def cast_floating(tree, dtype):
    """``tree`` with every floating-point array cast to ``dtype`` (integer and boolean arrays and
    non-array leaves unchanged): a lens, a render set-up or a fit model in float32 or float64."""
    return jax.tree.map(lambda x: x.astype(dtype) if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) else x, tree)
