"""The input domain of a polynomial path system and its five normalised variables.

A ray crossing the entrance plane ``z = entrance_z_mm`` at (x, y) with unit direction (dx, dy, dz)
and wavelength lambda has the variables of :mod:`._polybasis`:
``u, v = x, y / entrance_radius_mm``, ``s, t = dx, dy / sin(max field angle)``,
``w = (lambda - band centre) / band half-width``; the domain is ``u^2 + v^2 <= 1``,
``s^2 + t^2 <= 1``, ``|w| <= 1``.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..optics import Lens, entrance_plane_z_mm, front_rim_sag_mm, half_field_of_view_deg

DEFAULT_WAVELENGTH_RANGE_NM = (380.0, 780.0)
TRUST_GRID = (5, 5, 5, 5, 2)
"""Cells of a path system's trust table over (u, v, s, t, w)."""


def cell_index(variables):
    """Index of each ray's trust-table cell along each variable (NumPy or JAX arrays)."""
    xp = jnp if isinstance(variables, jax.Array) else np
    grid = np.asarray(TRUST_GRID)
    return xp.clip(xp.floor((variables + 1.0) * 0.5 * grid).astype(xp.int32), 0, grid - 1)


@dataclasses.dataclass(frozen=True)
class PathDomain:
    """The inputs a path system is built and validated for.

    Rays cross the plane ``z = entrance_z_mm`` (in front of the front lens) within
    ``entrance_radius_mm`` of the axis, make an angle of at most ``max_field_angle_deg`` with the
    axis, and have wavelengths in ``[wavelength_min_nm, wavelength_max_nm]``. The entrance radius
    covers every ray that can reach the front clear aperture at that angle; a ray crossing the
    plane further out is certainly clipped by the front lens.
    """

    max_field_angle_deg: float
    entrance_z_mm: float
    entrance_radius_mm: float
    wavelength_min_nm: float = DEFAULT_WAVELENGTH_RANGE_NM[0]
    wavelength_max_nm: float = DEFAULT_WAVELENGTH_RANGE_NM[1]

    @property
    def sin_max_field(self) -> float:
        return math.sin(math.radians(self.max_field_angle_deg))

    @property
    def wavelength_center_nm(self) -> float:
        return 0.5 * (self.wavelength_min_nm + self.wavelength_max_nm)

    @property
    def wavelength_half_width_nm(self) -> float:
        return 0.5 * (self.wavelength_max_nm - self.wavelength_min_nm)


def make_domain(
    lens: Lens,
    max_field_angle_deg: float | None = None,
    wavelength_range_nm: tuple[float, float] = DEFAULT_WAVELENGTH_RANGE_NM,
) -> PathDomain:
    """The domain for ``lens``: the whole front lens, field angles up to ``max_field_angle_deg``
    (default: the lens's half field of view, :func:`half_field_of_view_deg`), the wavelength band."""
    if max_field_angle_deg is None:
        max_field_angle_deg = half_field_of_view_deg(lens)
    if not 0 < max_field_angle_deg < 89:
        raise ValueError(f"max_field_angle_deg must be in (0, 89) degrees, got {max_field_angle_deg}")
    low, high = (float(v) for v in wavelength_range_nm)
    if not 200 <= low < high <= 2500:
        raise ValueError(f"wavelength_range_nm must be (low, high) with 200 <= low < high <= 2500 nm, got {wavelength_range_nm}")
    sag = front_rim_sag_mm(lens)
    entrance_z = entrance_plane_z_mm(lens)
    reach = max(0.0, sag) - entrance_z  # axial distance from the entrance plane to the front rim
    radius = float(lens.semi_aperture_mm[0]) + reach * math.tan(math.radians(max_field_angle_deg))
    return PathDomain(float(max_field_angle_deg), entrance_z, radius, low, high)


# --------------------------------------------------------------------------- variables


def entrance_variables(domain: PathDomain, origins: Array, directions: Array, wavelength_nm: Array):
    """Normalised variables (u, v, s, t, w) of each ray, and whether it travels towards the lens
    (only those have a meaningful crossing of the entrance plane)."""
    directions = directions / jnp.linalg.norm(directions, axis=-1, keepdims=True)
    dz = directions[:, 2]
    forward = dz > 1e-6
    travel = (domain.entrance_z_mm - origins[:, 2]) / jnp.where(forward, dz, 1.0)
    x = origins[:, 0] + travel * directions[:, 0]
    y = origins[:, 1] + travel * directions[:, 1]
    radius = domain.entrance_radius_mm
    sin_field = domain.sin_max_field
    variables = jnp.stack(
        [
            x / radius,
            y / radius,
            directions[:, 0] / sin_field,
            directions[:, 1] / sin_field,
            (wavelength_nm - domain.wavelength_center_nm) / domain.wavelength_half_width_nm,
        ],
        axis=-1,
    )
    return variables, forward


def sample_variables(count: int, seed: int | np.random.Generator) -> np.ndarray:
    """Uniform samples of the domain: (u, v) and (s, t) uniform over unit disks, w over [-1, 1]."""
    rng = np.random.default_rng(seed)

    def disk(n):
        r = np.sqrt(rng.random(n))
        phi = 2 * np.pi * rng.random(n)
        return r * np.cos(phi), r * np.sin(phi)

    u, v = disk(count)
    s, t = disk(count)
    w = rng.uniform(-1.0, 1.0, count)
    return np.stack([u, v, s, t, w], axis=-1)


def rays_from_variables(domain: PathDomain, variables: np.ndarray):
    u, v, s, t, w = variables.T
    sx, sy = s * domain.sin_max_field, t * domain.sin_max_field
    origins = np.stack([u * domain.entrance_radius_mm, v * domain.entrance_radius_mm, np.full_like(u, domain.entrance_z_mm)], -1)
    directions = np.stack([sx, sy, np.sqrt(np.clip(1 - sx * sx - sy * sy, 0, 1))], -1)
    wavelength = domain.wavelength_center_nm + w * domain.wavelength_half_width_nm
    return origins, directions, wavelength
