"""Exact sequential ray tracing through a lens along the primary path or a two-reflection ghost path.

A path is a fixed-length sequence of *events* (surface index, travel direction, refract or reflect),
padded with inactive events so that every path of a lens has the same shape: one compiled function
serves all ghost paths of a lens, and paths can be vmapped. ``lax.scan`` walks the events.

Rays that miss a surface, fall outside a clear aperture or the iris, or are totally internally
reflected where they should refract are marked invalid. Their state is frozen at the last valid
values, and every square root and division is guarded so that values *and gradients* stay finite.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxflare.optics._thin_film import coated_reflectance
from jaxflare.optics._glass import sellmeier_index
from jaxflare.optics._lens import Lens

REFRACT = 0
REFLECT = 1
GhostPath = tuple[int, int]


class TraceResult(eqx.Module):
    """Rays at the sensor plane after one path.

    ``positions`` and ``directions`` are only meaningful where ``valid``; elsewhere they are finite
    but arbitrary (the state where the ray was lost).
    """

    positions: Float[Array, "N 3"]
    """Position on the sensor plane in mm (z = ``lens.sensor_z_mm``)."""
    directions: Float[Array, "N 3"]
    """Unit direction at the sensor."""
    valid: Bool[Array, " N"]
    throughput: Float[Array, " N"]
    """Product of the Fresnel transmittances and reflectances along the path (unpolarised, with
    coatings, at each ray's own angles and wavelength); 0 where invalid."""
    lost_at_surface: Int[Array, " N"]
    """Surface index where the ray was lost (-1 if valid, ``num_surfaces`` if it missed the sensor,
    -2 for an untrusted ray a path system did not evaluate)."""
    stop_positions: Float[Array, "N P 3"]
    """Position where the ray crossed the stop surface, for each pass through it (P = 1 for the
    primary path, 1 or 3 for ghosts); zeros for passes a path does not make."""
    event_positions: Float[Array, "E N 3"] | None = None
    """With ``record_events=True``: the ray position after every event of the path (surface hits
    in path order, padded events repeat the last position). For drawing ray paths."""
    trusted: Bool[Array, " N"] | None = None
    """From a :class:`~jaxflare.PathSystem`: False where the polynomial was not validated for the
    ray's inputs and the ray was not re-traced exactly (such rays are also invalid, with
    ``lost_at_surface == -2``). None from the exact tracer, whose every ray is trusted."""


def ghost_paths(lens: Lens) -> list[GhostPath]:
    """Every two-reflection path ``(j, i)``: first reflection at interface j, second at i < j.

    Interfaces are numbered 0 .. ``lens.num_interfaces - 1``; there are N (N - 1) / 2 paths.
    """
    n = lens.num_interfaces
    return [(j, i) for j in range(1, n) for i in range(j)]


def _check_path(lens: Lens, path: GhostPath | None) -> GhostPath | None:
    if path is None:
        return None
    try:
        j, i = (int(k) for k in path)
    except (TypeError, ValueError):
        raise ValueError(f"path must be None (primary) or a pair (j, i) of interface indices, got {path!r}") from None
    n = lens.num_interfaces
    if not (0 <= i < j < n):
        raise ValueError(f"ghost path (j, i) needs 0 <= i < j < {n} (the interfaces of '{lens.name}'), got {path!r}")
    return j, i


def path_events(lens: Lens, path: GhostPath | None = None) -> np.ndarray:
    """The event table of a path: int32 array (3 * num_surfaces, 4) of
    ``(surface, direction +1/-1 before the event, REFRACT/REFLECT, active)`` rows."""
    path = _check_path(lens, path)
    num = lens.num_surfaces
    rows: list[tuple[int, int, int]] = []
    if path is None:
        rows = [(s, 1, REFRACT) for s in range(num)]
    else:
        sj, si = lens.interface_surfaces[path[0]], lens.interface_surfaces[path[1]]
        rows += [(s, 1, REFRACT) for s in range(sj)]
        rows.append((sj, 1, REFLECT))
        rows += [(s, -1, REFRACT) for s in range(sj - 1, si, -1)]
        rows.append((si, -1, REFLECT))
        rows += [(s, 1, REFRACT) for s in range(si + 1, num)]
    table = np.zeros((3 * num, 4), dtype=np.int32)
    table[:, 1] = 1
    table[: len(rows), :3] = rows
    table[: len(rows), 3] = 1
    return table


def _stop_pass_count(events: np.ndarray, stop_index: int) -> int:
    return int(np.sum((events[:, 0] == stop_index) & (events[:, 3] == 1)))


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


TRACE_COMPILATIONS = [0]
"""How often the tracer has been traced by JAX (tests use it to catch retracing)."""


@eqx.filter_jit
def _trace_events(
    lens: Lens, origins: Array, directions: Array, wavelength_nm: Array, events: Array, num_stop_passes: int, record_events: bool = False
) -> TraceResult:
    """Trace rays along the event table ``events``: (E, 4) for one path shared by every ray, or
    (N, E, 4) for a path per ray (a renderer batch that mixes paths)."""
    TRACE_COMPILATIONS[0] += 1
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


def ray_arguments(origins: ArrayLike, directions: ArrayLike, wavelength_nm: ArrayLike) -> tuple[Array, Array, Array]:
    """Check and convert the ray inputs shared by :func:`trace` and path systems: (N, 3) origins
    and directions in one floating dtype, and one wavelength per ray."""
    origins = jnp.asarray(origins)
    directions = jnp.asarray(directions)
    if origins.ndim != 2 or origins.shape[-1] != 3 or directions.shape != origins.shape:
        raise ValueError(f"origins and directions must both have shape (N, 3), got {origins.shape} and {directions.shape}")
    if not jnp.issubdtype(origins.dtype, jnp.floating):
        origins = origins.astype(jnp.result_type(float))
    directions = directions.astype(origins.dtype)
    wavelength = jnp.broadcast_to(jnp.asarray(wavelength_nm, origins.dtype), origins.shape[:1])
    return origins, directions, wavelength


def trace(
    lens: Lens,
    origins: ArrayLike,
    directions: ArrayLike,
    wavelength_nm: ArrayLike = 587.56,
    path: GhostPath | None = None,
    *,
    record_events: bool = False,
) -> TraceResult:
    """Trace rays exactly through ``lens`` along ``path`` to the sensor plane.

    Args:
        lens: the lens (see :func:`jaxflare.load_lens`).
        origins: (N, 3) ray origins in mm in the lens frame (z along the axis towards the sensor,
            z = 0 at the vertex of surface 0); they must lie in front of the first surface.
        directions: (N, 3) directions (normalised here).
        wavelength_nm: scalar or (N,) wavelengths in nm.
        path: ``None`` for the primary (image-forming) path, or a ghost path ``(j, i)`` with
            ``j > i`` interface indices: reflect at interface j, then at interface i.
        record_events: also return every intermediate surface hit (``event_positions``).

    Returns:
        A :class:`TraceResult` with positions, directions, a validity mask, Fresnel throughput,
        the surface where each invalid ray was lost, and the stop-plane positions of each pass.

    Differentiable with respect to ray inputs and the lens's array fields; jit-compiled once per
    lens structure (all paths of a lens share one compilation).
    """
    origins, directions, wavelength = ray_arguments(origins, directions, wavelength_nm)
    events = path_events(lens, path)
    return _trace_events(
        lens, origins, directions, wavelength, jnp.asarray(events), _stop_pass_count(events, lens.stop_index), record_events
    )


def path_fresnel_factor(lens: Lens, path: GhostPath | None, wavelength_nm: ArrayLike = 587.56) -> Array:
    """Fresnel factor of a whole path at normal incidence (the on-axis ray), per wavelength.

    The product of the coated reflectances at the two reflecting interfaces and the transmittances
    at every other surface crossed; ``wavelength_nm`` may be a scalar or a 1-D array.
    """
    wavelength = jnp.atleast_1d(jnp.asarray(wavelength_nm, jnp.result_type(float)))
    count = wavelength.shape[0]
    origins = jnp.zeros((count, 3), wavelength.dtype).at[:, 2].set(-1.0)
    directions = jnp.zeros((count, 3), wavelength.dtype).at[:, 2].set(1.0)
    result = trace(lens, origins, directions, wavelength, path)
    return result.throughput if jnp.ndim(wavelength_nm) else result.throughput[0]
