"""The exact tracer as it was formulated before the speed-up (jaxflare 0.1.0, commit 96faa6a):
``lax.cond`` over padded events, array-of-structures state, coated Fresnel at every event. Kept
verbatim as an independent reference: the tests check that today's tracer gives the same rays."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from jaxflare.optics import Lens, TraceResult, coated_reflectance, sellmeier_index


def _safe_sqrt(x: Array) -> Array:
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def _safe_divide(numerator: Array, denominator: Array) -> Array:
    ok = denominator != 0
    return jnp.where(ok, numerator / jnp.where(ok, denominator, 1.0), 0.0)


def _inside_iris(x: Array, y: Array, radius: Array, blades: int, rotation: Array) -> Array:
    """Point-in-iris test: a circle for ``blades == 0``, else a regular polygon with its vertices on
    the circle of ``radius`` and the first vertex at angle ``rotation``."""
    x, y, radius, rotation = (jax.lax.stop_gradient(v) for v in (x, y, radius, rotation))
    if blades == 0:
        return x * x + y * y <= radius * radius
    apothem = radius * math.cos(math.pi / blades)
    inside = jnp.ones_like(x, dtype=bool)
    for k in range(blades):
        angle = rotation + (k + 0.5) * 2.0 * math.pi / blades
        inside = inside & (x * jnp.cos(angle) + y * jnp.sin(angle) <= apothem)
    return inside


def _surface_sag_slope(rho2: Array, curvature: Array, conic: Array, aspheric: Array) -> tuple[Array, Array]:
    """Sag z(rho^2) and g = (dz/drho)/rho of a conic plus even asphere, guarded beyond the conic rim."""
    arg = 1.0 - (1.0 + conic) * curvature**2 * rho2
    root = _safe_sqrt(arg)
    sag = _safe_divide(curvature * rho2, 1.0 + root)
    slope = _safe_divide(curvature, root)
    for k in range(aspheric.shape[-1]):  # A4 rho^4 + A6 rho^6 + ...
        m = k + 2
        slope = slope + 2 * m * aspheric[..., k] * rho2 ** (m - 1)
        sag = sag + aspheric[..., k] * rho2**m
    return sag, slope


_BEHIND_TOLERANCE_MM = 1e-4
"""A root up to this far behind the ray origin still counts: the origin lies on the previous surface,
which may touch this one (cemented rims), and float32 positions carry about 1e-5 mm of rounding."""


def _intersect(origin, direction, vertex_z, curvature, conic, aspheric, kind, has_aspheres):
    """First intersection ahead of the ray with the vertex sheet of the surface.

    Returns (point, unit normal facing -z, hit); ``hit`` is False for a miss, a surface behind the
    ray (sequential order violated, as where two surfaces cross) or a hit only on the far sheet.
    """
    wx = jnp.where(kind == 2, 0.0, 1.0)  # cylindrical_y has no x dependence
    wy = jnp.where(kind == 1, 0.0, 1.0)
    px, py, pz = origin[:, 0], origin[:, 1], origin[:, 2] - vertex_z
    dx, dy, dz = direction[:, 0], direction[:, 1], direction[:, 2]
    c, k1 = curvature, 1.0 + conic
    a = c * (wx * dx * dx + wy * dy * dy) + k1 * c * dz * dz
    b = c * (wx * px * dx + wy * py * dy) - dz + k1 * c * pz * dz
    g = c * (wx * px * px + wy * py * py) - 2.0 * pz + k1 * c * pz * pz
    disc = b * b - a * g
    # Both roots of a t^2 + 2 b t + g = 0, computed without cancellation. Keep the first one ahead of
    # the ray (t >= 0) that lies on the vertex sheet of the quadric (k1 c z <= 1: the sheet through
    # the vertex, whose normal faces -z); a root behind the ray or on the far sheet is not a hit.
    root = _safe_sqrt(disc)
    sign = jnp.where(b >= 0, 1.0, -1.0)
    q = -(b + sign * root)
    roots = jnp.stack([_safe_divide(g, q), _safe_divide(q, a)])
    exists = jnp.stack([q != 0, a != 0]) & (disc >= 0)
    z_roots = pz + roots * dz
    usable = exists & (roots >= -_BEHIND_TOLERANCE_MM) & (k1 * c * z_roots <= 1.0)
    first = jnp.where(usable[0] & (~usable[1] | (roots[0] <= roots[1])), 0, 1)
    t = jnp.where(first == 0, roots[0], roots[1])
    hit = jnp.where(first == 0, usable[0], usable[1])
    t = jnp.where(hit, t, 0.0)
    x, y, z = px + t * dx, py + t * dy, pz + t * dz
    if has_aspheres:
        for _ in range(4):  # Newton on f(t) = z(t) - sag(rho^2(t)), starting at the conic solution
            rho2 = wx * x * x + wy * y * y
            sag, slope = _surface_sag_slope(rho2, c, conic, aspheric)
            f = z - sag
            df = dz - slope * (wx * x * dx + wy * y * dy)
            t = t - _safe_divide(f, df)
            x, y, z = px + t * dx, py + t * dy, pz + t * dz
        rho2 = wx * x * x + wy * y * y
        sag, slope = _surface_sag_slope(rho2, c, conic, aspheric)
        hit = hit & (jnp.abs(z - sag) < 1e-4) & (1.0 - k1 * c * c * rho2 >= 0)
        normal = jnp.stack([wx * x * slope, wy * y * slope, -jnp.ones_like(z)], axis=-1)
    else:
        # gradient of the quadric c rho^2 - 2 z + (1 + k) c z^2, halved (exact on the surface)
        normal = jnp.stack([wx * c * x, wy * c * y, k1 * c * z - 1.0], axis=-1)
    normal = normal / jnp.linalg.norm(normal, axis=-1, keepdims=True)
    point = jnp.stack([x, y, z + vertex_z], axis=-1)
    return point, normal, hit


def _media_indices(lens: Lens, wavelength_nm: Array) -> Array:
    """(N, M) refractive index of every medium for every ray's wavelength."""
    n = sellmeier_index(lens.sellmeier_b[None, :, :], lens.sellmeier_c_um2[None, :, :], wavelength_nm[:, None])
    return jnp.where(lens.medium_is_air[None, :], 1.0, n)


@eqx.filter_jit
def reference_trace_events(
    lens: Lens, origins: Array, directions: Array, wavelength_nm: Array, events: Array, num_stop_passes: int, record_events: bool = False
) -> TraceResult:
    """Trace rays along the event table ``events``: (E, 4) for one path shared by every ray, or
    (N, E, 4) for a path per ray (a renderer batch that mixes paths)."""
    num_rays = origins.shape[0]
    vertex_z = jnp.concatenate([jnp.zeros(1, lens.thickness_mm.dtype), jnp.cumsum(lens.thickness_mm[:-1])])
    indices = _media_indices(lens, wavelength_nm)
    directions = directions / jnp.linalg.norm(directions, axis=-1, keepdims=True)
    dtype = origins.dtype

    per_ray = events.ndim == 3  # (N, E, 4): every ray follows its own path

    def column(table, surface):  # table[:, surface] for one surface or one per ray
        return jnp.take_along_axis(table, surface[:, None], 1)[:, 0] if per_ray else table[:, surface]

    def apply_event(state, event):
        position, direction, valid, throughput, lost_at, stop_positions, stop_pass = state
        surface, travel, action = event[..., 0], event[..., 1], event[..., 2]
        point, normal, hit = _intersect(
            position, direction, vertex_z[surface], lens.curvature_per_mm[surface], lens.conic[surface],
            lens.aspheric_coefficients[surface], lens.surface_kind[surface], lens.has_aspheres,
        )
        is_stop = surface == lens.stop_index
        inside_clear = point[:, 0] ** 2 + point[:, 1] ** 2 <= lens.semi_aperture_mm[surface] ** 2
        inside_iris = _inside_iris(point[:, 0], point[:, 1], lens.stop_radius_mm, lens.aperture_blades, lens.aperture_rotation_rad)
        inside = jnp.where(is_stop, inside_clear & inside_iris, inside_clear)

        forward = travel > 0
        n_before = jnp.where(forward, column(indices, surface), column(indices, surface + 1))
        n_after = jnp.where(forward, column(indices, surface + 1), column(indices, surface))
        cos_in = -jnp.sum(normal * direction, axis=-1)
        facing = jnp.where(cos_in < 0, -1.0, 1.0)
        normal = normal * facing[:, None]
        cos_in = jnp.clip(cos_in * facing, 0.0, 1.0)

        reflect = action == 1
        reflect_xyz = reflect[..., None]
        eta = n_before / n_after
        k = 1.0 - eta**2 * (1.0 - cos_in**2)
        refracted = eta[:, None] * direction + (eta * cos_in - _safe_sqrt(k))[:, None] * normal
        reflected = direction + 2.0 * cos_in[:, None] * normal
        new_direction = jnp.where(reflect_xyz, reflected, refracted)
        new_direction = new_direction / jnp.linalg.norm(new_direction, axis=-1, keepdims=True)
        total_internal = (~reflect) & (k < 0)

        layers_n = lens.coating_indices[surface]
        layers_d = lens.coating_thicknesses_nm[surface]
        layers_n = jnp.where(forward[..., None], layers_n, layers_n[..., ::-1])
        layers_d = jnp.where(forward[..., None], layers_d, layers_d[..., ::-1])
        reflectance = coated_reflectance(n_before, n_after, cos_in, wavelength_nm, layers_n, layers_d)
        factor = jnp.where(reflect, reflectance, 1.0 - reflectance)

        ok = hit & inside & ~total_internal
        newly_lost = valid & ~ok
        update = valid & ok
        position = jnp.where(update[:, None], point, position)
        direction = jnp.where(update[:, None], new_direction, direction)
        throughput = jnp.where(update, throughput * factor, throughput)
        lost_at = jnp.where(newly_lost, surface, lost_at)
        valid = valid & ok
        record = jnp.broadcast_to(is_stop, stop_pass.shape)
        slot = jax.nn.one_hot(stop_pass, stop_positions.shape[1], dtype=dtype)  # (N, P)
        stop_positions = jnp.where(record[:, None, None], stop_positions + slot[:, :, None] * point[:, None, :], stop_positions)
        stop_pass = stop_pass + jnp.where(record, 1, 0)
        return position, direction, valid, throughput, lost_at, stop_positions, stop_pass

    def step(state, event):
        if per_ray:  # each ray skips its own padded events
            new = apply_event(state, event)
            active = event[:, 3] == 1
            state = jax.tree.map(lambda n, o: jnp.where(active.reshape(active.shape + (1,) * (n.ndim - 1)), n, o), new, state)
        else:  # padded (inactive) events are skipped at run time; cond stays reverse-differentiable
            state = jax.lax.cond(event[3] == 1, apply_event, lambda state, _: state, state, event)
        return state, (state[0] if record_events else None)

    state = (
        origins,
        directions,
        jnp.ones(num_rays, bool),
        jnp.ones(num_rays, dtype),
        jnp.full(num_rays, -1, jnp.int32),
        jnp.zeros((num_rays, max(num_stop_passes, 1), 3), dtype),
        jnp.zeros(num_rays, jnp.int32),
    )
    scanned = jnp.swapaxes(events, 0, 1) if per_ray else events
    (position, direction, valid, throughput, lost_at, stop_positions, _), history = jax.lax.scan(step, state, scanned)

    # propagate to the sensor plane
    dz = direction[:, 2]
    reaches = dz > 0
    t = _safe_divide(lens.sensor_z_mm - position[:, 2], dz)
    sensor_position = position + t[:, None] * direction
    sensor_position = sensor_position.at[:, 2].set(jnp.broadcast_to(lens.sensor_z_mm, (num_rays,)))
    lost_at = jnp.where(valid & ~reaches, lens.num_surfaces, lost_at)
    valid = valid & reaches
    return TraceResult(
        positions=jnp.where(valid[:, None], sensor_position, position),
        directions=direction,
        valid=valid,
        throughput=jnp.where(valid, throughput, 0.0),
        lost_at_surface=lost_at,
        stop_positions=stop_positions[:, :num_stop_passes] if num_stop_passes else stop_positions[:, :0],
        event_positions=history,
    )


