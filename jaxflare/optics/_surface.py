"""One lens surface, physically: its shape (sag), where a ray meets it (``intersect``), and what
the ray does there (``refract`` by the vector form of Snell's law, or ``reflect``), plus the iris
test at the aperture stop.

Conventions (pbrt-v4's, in millimetres): the lens frame has z along the optical axis towards the
sensor; a surface's vertex lies at ``vertex_z``; its sag ``z(rho^2)`` is a conic of vertex curvature
``c`` (1/mm) and conic constant ``k`` plus an even asphere ``A4 rho^4 + A6 rho^6 + ...``. A
cylindrical surface has power in one meridian only (:class:`SurfaceKind`). Directions are unit
vectors; normals face the incoming light (``-z`` at the vertex).

Every square root and division is guarded (:func:`safe_sqrt`, :func:`safe_divide`) so that values
*and gradients* stay finite for rays that miss, clip or totally reflect: the tracer masks those rays
out, and a NaN behind a mask would still poison a gradient.
"""

from __future__ import annotations

import enum
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array


class SurfaceKind(enum.IntEnum):
    """Shape family of a surface (the integer is what :class:`~jaxflare.Lens` stores per surface)."""

    SPHERICAL = 0
    """Rotationally symmetric about the axis: a sphere, flat, conic or even asphere."""
    CYLINDRICAL_X = 1
    """Power in the x-z plane only: the sag depends on x alone (the cylinder axis lies along y)."""
    CYLINDRICAL_Y = 2
    """Power in the y-z plane only."""

    @property
    def label(self) -> str:
        """The name lens files use: ``"spherical"``, ``"cylindrical_x"`` or ``"cylindrical_y"``."""
        return self.name.lower()

    @classmethod
    def from_label(cls, label: str) -> SurfaceKind:
        return cls[label.upper()]


def safe_sqrt(x: Array) -> Array:
    """``sqrt(x)`` where ``x > 0``, else 0, with a finite gradient everywhere."""
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def safe_divide(numerator: Array, denominator: Array) -> Array:
    """``numerator / denominator`` where the denominator is non-zero, else 0 (finite gradients)."""
    ok = denominator != 0
    return jnp.where(ok, numerator / jnp.where(ok, denominator, 1.0), 0.0)


def sag_and_slope(rho2: Array, curvature: Array, conic: Array, aspheric: Array) -> tuple[Array, Array]:
    """Sag ``z(rho^2)`` (mm) and ``g = (dz/drho)/rho`` (1/mm) of a conic plus even asphere, guarded
    beyond the conic's rim. ``aspheric``: the coefficients A4, A6, ... along its last axis."""
    arg = 1.0 - (1.0 + conic) * curvature**2 * rho2
    root = safe_sqrt(arg)
    sag = safe_divide(curvature * rho2, 1.0 + root)
    slope = safe_divide(curvature, root)
    for k in range(aspheric.shape[-1]):  # A4 rho^4 + A6 rho^6 + ...
        m = k + 2
        coefficient = aspheric[..., k]
        # a zero (padding) coefficient's power is taken at 0: rho^(2m) may overflow where the
        # surface's own terms do not, and 0 * inf is NaN in the value and in the gradient
        base = jnp.where(coefficient != 0, rho2, 0.0)
        slope = slope + 2 * m * coefficient * base ** (m - 1)
        sag = sag + coefficient * base**m
    return sag, slope


ASPHERE_SAG_LIMIT_MM = 1.0e12
"""Newton iterates of an aspheric intersection stay where every term of the polynomial is below
this (mm): far beyond any lens, well inside the float32 range even after squaring for a normal."""


def aspheric_rho2_limit(aspheric: Array) -> Array:
    """The largest rho^2 (mm^2) at which every even-asphere term ``|A_m| rho^(2m)`` stays below
    :data:`ASPHERE_SAG_LIMIT_MM` (capped at 1e12 mm^2); no gradient flows through it."""
    aspheric = jax.lax.stop_gradient(jnp.asarray(aspheric))
    limit = jnp.asarray(1.0e12, aspheric.dtype)
    for k in range(aspheric.shape[-1]):
        m = k + 2
        size = jnp.abs(aspheric[..., k])
        bound = jnp.where(size > 0, (ASPHERE_SAG_LIMIT_MM / jnp.where(size > 0, size, 1.0)) ** (1.0 / m), limit)
        limit = jnp.minimum(limit, bound)
    return limit


def meridian_weights(kind: Array) -> tuple[Array, Array]:
    """``(wx, wy)``: 1 where the surface's shape depends on x (resp. y), 0 for a cylinder without
    power in that meridian."""
    wx = jnp.where(kind == SurfaceKind.CYLINDRICAL_Y, 0.0, 1.0)
    wy = jnp.where(kind == SurfaceKind.CYLINDRICAL_X, 0.0, 1.0)
    return wx, wy


def surface_sag_mm(lens, surface: int, x: Array, y: Array) -> Array:
    """Sag (mm, relative to the vertex) of ``lens``'s surface ``surface`` at lens-frame (x, y)."""
    wx, wy = meridian_weights(lens.surface_kind[surface])
    x, y = jnp.asarray(x), jnp.asarray(y)
    sag, _ = sag_and_slope(wx * x * x + wy * y * y, lens.curvature_per_mm[surface], lens.conic[surface], lens.aspheric_coefficients[surface])
    return sag


BEHIND_TOLERANCE_MM = 1e-4
"""A root up to this far behind the ray origin still counts: the origin lies on the previous surface,
which may touch this one (cemented rims), and float32 positions carry about 1e-5 mm of rounding."""


class Vector(NamedTuple):
    """Three components of a point or direction, each an array of one value per ray (the tracer
    keeps its rays as a structure of arrays)."""

    x: Array
    y: Array
    z: Array


def _keep(value: Array) -> Array:
    return value


def intersect(point: Vector, direction: Vector, vertex_z, curvature, conic, aspheric, kind, has_aspheres: bool, materialise=_keep):
    """First intersection ahead of each ray with the vertex sheet of a surface.

    ``point`` and ``direction`` are per-ray components; the surface's parameters are scalars or
    one per ray. Returns ``(hit point, unit normal facing -z at the vertex, hit)``; ``hit`` is
    False for a miss, a surface behind the ray (sequential order violated, as where two surfaces
    cross) or a hit only on the far sheet. Aspheres (``has_aspheres``, static) refine the conic root
    by Newton. ``materialise`` marks values used many times (the tracer uses it to keep XLA from
    recomputing them in every consumer); it must return its argument's value.
    """
    wx, wy = meridian_weights(kind)
    px, py, pz = point.x, point.y, point.z - vertex_z
    dx, dy, dz = direction
    c, k1 = curvature, 1.0 + conic
    a = materialise(c * (wx * dx * dx + wy * dy * dy) + k1 * c * dz * dz)
    b = materialise(c * (wx * px * dx + wy * py * dy) - dz + k1 * c * pz * dz)
    g = materialise(c * (wx * px * px + wy * py * py) - 2.0 * pz + k1 * c * pz * pz)
    # Both roots of a t^2 + 2 b t + g = 0, computed without cancellation. Keep the first one ahead of
    # the ray (t >= 0) that lies on the vertex sheet of the quadric (k1 c z <= 1: the sheet through
    # the vertex, whose normal faces -z); a root behind the ray or on the far sheet is not a hit.
    disc = materialise(b * b - a * g)
    root = materialise(safe_sqrt(disc))
    q = materialise(-(b + jnp.where(b >= 0, root, -root)))
    t0 = materialise(safe_divide(g, q))
    t1 = materialise(safe_divide(q, a))
    real = disc >= 0
    usable0 = real & (q != 0) & (t0 >= -BEHIND_TOLERANCE_MM) & (k1 * c * (pz + t0 * dz) <= 1.0)
    usable1 = real & (a != 0) & (t1 >= -BEHIND_TOLERANCE_MM) & (k1 * c * (pz + t1 * dz) <= 1.0)
    take0 = usable0 & (~usable1 | (t0 <= t1))
    hit = usable0 | usable1
    t = materialise(jnp.where(hit, jnp.where(take0, t0, t1), 0.0))
    x, y, z = materialise(px + t * dx), materialise(py + t * dy), materialise(pz + t * dz)
    if has_aspheres:
        # Newton on f(t) = z(t) - sag(rho^2(t)), starting at the conic solution. A ray far outside
        # the surface can send the iterate to where the polynomial overflows (float32: A10 rho^10
        # at rho ~ 1e4 mm) and an inf, even behind a mask, makes the gradient NaN. So the
        # polynomial is only evaluated where it stays below ASPHERE_SAG_LIMIT_MM (elsewhere at
        # rho = 0, a safe point), an iterate that leaves that region is frozen, and such a ray
        # is no hit.
        # The iterations run without gradients; the root's derivative comes from the implicit
        # function theorem at the root, dt = -(df/dparameters) / (df/dt), as one differentiable
        # step that adds exactly 0 to the value. That is the derivative of the exact root (the
        # unrolled iterations only approach it) and keeps the iterations out of the reverse pass:
        # a float32 gradient of a trace through two aspheres compiled in 1/3 of the time.
        limit = aspheric_rho2_limit(aspheric)
        still = jax.lax.stop_gradient
        spx, spy, spz, sdx, sdy, sdz = (still(v) for v in (px, py, pz, dx, dy, dz))
        sc, sconic, saspheric = still(c), still(conic), still(aspheric)
        t = still(t)
        x, y, z = still(x), still(y), still(z)
        inside = jnp.ones_like(hit)
        for _ in range(4):
            rho2 = wx * x * x + wy * y * y
            ok = rho2 <= limit
            sag, slope = sag_and_slope(jnp.where(ok, rho2, 0.0), sc, sconic, saspheric)
            f = z - sag
            df = sdz - slope * (wx * x * sdx + wy * y * sdy)
            t_next = t - safe_divide(f, df)
            x_next, y_next = spx + t_next * sdx, spy + t_next * sdy
            ok = ok & (wx * x_next * x_next + wy * y_next * y_next <= limit)
            t = materialise(jnp.where(ok, t_next, t))
            inside = inside & ok
            x, y, z = materialise(spx + t * sdx), materialise(spy + t * sdy), materialise(spz + t * sdz)
        # the implicit step: f and its parameter derivatives at the root, df/dt held constant
        x, y, z = px + t * dx, py + t * dy, pz + t * dz
        rho2 = wx * x * x + wy * y * y
        usable = inside & (rho2 <= limit)
        sag, slope = sag_and_slope(jnp.where(usable, rho2, 0.0), c, conic, aspheric)
        f = z - sag
        df = still(dz - slope * (wx * x * dx + wy * y * dy))
        t = materialise(t - jnp.where(usable, safe_divide(f - still(f), df), 0.0))
        x, y, z = materialise(px + t * dx), materialise(py + t * dy), materialise(pz + t * dz)
        rho2 = wx * x * x + wy * y * y
        ok = inside & (rho2 <= limit)
        rho2 = jnp.where(ok, rho2, 0.0)
        sag, slope = sag_and_slope(rho2, c, conic, aspheric)
        hit = hit & ok & (jnp.abs(z - sag) < 1e-4) & (1.0 - k1 * c * c * rho2 >= 0)
        # a ray that misses gets a finite point and normal (where it started, facing -z): callers
        # that record positions unconditionally (the stop crossings) stay finite, and so do their
        # gradients (on a conic a miss has t = 0 already; Newton may have moved it here)
        x, y, z = materialise(jnp.where(hit, x, px)), materialise(jnp.where(hit, y, py)), materialise(jnp.where(hit, z, pz))
        nx = jnp.where(hit, wx * x * slope, 0.0)
        ny = jnp.where(hit, wy * y * slope, 0.0)
        nz = -jnp.ones_like(z)
    else:
        # gradient of the quadric c rho^2 - 2 z + (1 + k) c z^2, halved (exact on the surface)
        nx, ny, nz = wx * c * x, wy * c * y, k1 * c * z - 1.0
    nx, ny, nz = materialise(nx), materialise(ny), materialise(nz)
    # a zero-length normal (only where a quadric's rim meets the ray) is taken as -z, not 0/0
    length2 = nx * nx + ny * ny + nz * nz
    positive = length2 > 0
    scale = materialise(jnp.where(positive, 1.0 / jnp.sqrt(jnp.where(positive, length2, 1.0)), 0.0))
    normal = Vector(materialise(nx * scale), materialise(ny * scale), materialise(jnp.where(positive, nz * scale, -1.0)))
    return Vector(x, y, z + vertex_z), normal, hit


def facing_normal(normal: Vector, direction: Vector, materialise=_keep) -> tuple[Vector, Array]:
    """The normal turned to face the incoming ray, and the cosine of incidence in [0, 1]."""
    cos_in = -(normal.x * direction.x + normal.y * direction.y + normal.z * direction.z)
    facing = jnp.where(cos_in < 0, -1.0, 1.0)
    return Vector(normal.x * facing, normal.y * facing, normal.z * facing), materialise(jnp.clip(cos_in * facing, 0.0, 1.0))


def refract_or_reflect(direction: Vector, normal: Vector, cos_in: Array, eta: Array, reflects, materialise=_keep) -> tuple[Vector, Array]:
    """The unit direction after the surface: the mirror direction about the (facing) normal where
    ``reflects``, else Snell's law in vector form for the index ratio ``eta = n_before / n_after``;
    and where a refracted ray is totally internally reflected instead (its direction then is
    meaningless)."""
    k = materialise(1.0 - eta * eta * (1.0 - cos_in * cos_in))
    along_normal = materialise(jnp.where(reflects, 2.0 * cos_in, eta * cos_in - safe_sqrt(k)))  # reflect: d + 2 cos n
    along_ray = materialise(jnp.where(reflects, 1.0, eta))  # refract: eta d + (eta cos - sqrt(k)) n
    ex, ey, ez = (materialise(along_ray * d + along_normal * n) for d, n in zip(direction, normal))
    scale = materialise(1.0 / jnp.sqrt(ex * ex + ey * ey + ez * ez))
    return Vector(materialise(ex * scale), materialise(ey * scale), materialise(ez * scale)), ~reflects & (k < 0)


def refract(direction: Vector, normal: Vector, cos_in: Array, eta: Array) -> tuple[Vector, Array]:
    """Snell's law in vector form: the unit refracted direction for ``eta = n_before / n_after``, and
    where the ray is totally internally reflected instead."""
    return refract_or_reflect(direction, normal, cos_in, eta, False)


def reflect(direction: Vector, normal: Vector, cos_in: Array) -> Vector:
    """The mirror direction about the (facing) normal."""
    return refract_or_reflect(direction, normal, cos_in, jnp.ones_like(cos_in), True)[0]


def inside_iris(x: Array, y: Array, radius: Array, blades: int, rotation: Array) -> Array:
    """Point-in-iris test on the stop plane: a circle for ``blades == 0``, else a regular polygon
    with its vertices on the circle of ``radius`` and the first vertex at angle ``rotation``.
    A 0/1 test: no gradient flows through it."""
    x, y, radius, rotation = (jax.lax.stop_gradient(v) for v in (x, y, radius, rotation))
    if blades == 0:
        return x * x + y * y <= radius * radius
    apothem = radius * math.cos(math.pi / blades)
    inside = jnp.ones_like(x, dtype=bool)
    for k in range(blades):
        angle = rotation + (k + 0.5) * 2.0 * math.pi / blades
        inside = inside & (x * jnp.cos(angle) + y * jnp.sin(angle) <= apothem)
    return inside
