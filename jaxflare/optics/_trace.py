"""Exact sequential ray tracing through a lens along the primary path or a two-reflection ghost path.

A path is a fixed-length sequence of *events* (:mod:`jaxflare.optics._paths`), padded with
inactive events so that every path of a lens has the same shape: one compiled function serves all
ghost paths of a lens, and paths can be vmapped. ``lax.scan`` walks the events; at each one the ray
is intersected with the surface, tested against its clear aperture (and the iris at the stop), and
refracted or reflected (:mod:`jaxflare.optics._surface`), its throughput multiplied by the coated
Fresnel factor (:mod:`jaxflare.optics._thin_film`).

Rays that miss a surface, fall outside a clear aperture or the iris, or are totally internally
reflected where they should refract are marked invalid. Their state is frozen at the last valid
values, and every square root and division is guarded so that values *and gradients* stay finite.
"""

from __future__ import annotations

import enum

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._glass import sellmeier_index
from ._lens import Lens
from ._paths import EventAction, EventTable, GhostPath, event_table, ghost_paths, path_events, stop_pass_count
from ._surface import facing_normal, inside_iris, intersect, reflect, refract, safe_divide
from ._thin_film import coated_reflectance


class LossReason(enum.IntEnum):
    """The codes :attr:`TraceResult.lost_at_surface` uses besides surface indices (a ray that
    misses the sensor plane is lost at ``lens.num_surfaces``)."""

    NOT_LOST = -1
    """The ray got through the whole path."""
    UNTRUSTED = -2
    """A path system did not trust the ray and did not trace it exactly."""


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


def media_indices(lens: Lens, wavelength_nm: Array) -> Array:
    """(N, M) refractive index of every medium (Sellmeier; air 1) for every ray's wavelength."""
    n = sellmeier_index(lens.sellmeier_b[None, :, :], lens.sellmeier_c_um2[None, :, :], wavelength_nm[:, None])
    return jnp.where(lens.medium_is_air[None, :], 1.0, n)


@eqx.debug.assert_max_traces(max_traces=None)  # counts compilations: tests catch retracing with get_num_traces
def _trace_events(
    lens: Lens, origins: Array, directions: Array, wavelength_nm: Array, events: EventTable, num_stop_passes: int, record_events: bool = False
) -> TraceResult:
    """Trace rays along ``events``: columns of shape (E,) for one path shared by every ray, or
    (N, E) for a path per ray (a renderer batch that mixes paths). ``num_stop_passes`` (static):
    how many stop crossings to record."""
    num_rays = origins.shape[0]
    vertex_z = jnp.concatenate([jnp.zeros(1, lens.thickness_mm.dtype), jnp.cumsum(lens.thickness_mm[:-1])])
    indices = media_indices(lens, wavelength_nm)
    directions = directions / jnp.linalg.norm(directions, axis=-1, keepdims=True)
    dtype = origins.dtype

    per_ray = events.surface.ndim == 2  # (N, E): every ray follows its own path

    def column(table, surface):  # table[:, surface] for one surface or one per ray
        return jnp.take_along_axis(table, surface[:, None], 1)[:, 0] if per_ray else table[:, surface]

    def apply_event(state, event):
        position, direction, valid, throughput, lost_at, stop_positions, stop_pass = state
        surface, travel, action = event.surface, event.travel, event.action
        point, normal, hit = intersect(
            position, direction, vertex_z[surface], lens.curvature_per_mm[surface], lens.conic[surface],
            lens.aspheric_coefficients[surface], lens.surface_kind[surface], lens.has_aspheres,
        )
        is_stop = surface == lens.stop_index
        inside_clear = point[:, 0] ** 2 + point[:, 1] ** 2 <= lens.semi_aperture_mm[surface] ** 2
        inside_stop = inside_iris(point[:, 0], point[:, 1], lens.stop_radius_mm, lens.aperture_blades, lens.aperture_rotation_rad)
        inside = jnp.where(is_stop, inside_clear & inside_stop, inside_clear)

        forward = travel > 0
        n_before = jnp.where(forward, column(indices, surface), column(indices, surface + 1))
        n_after = jnp.where(forward, column(indices, surface + 1), column(indices, surface))
        normal, cos_in = facing_normal(normal, direction)

        reflects = action == EventAction.REFLECT
        refracted, total_internal = refract(direction, normal, cos_in, n_before / n_after)
        new_direction = jnp.where(reflects[..., None], reflect(direction, normal, cos_in), refracted)
        new_direction = new_direction / jnp.linalg.norm(new_direction, axis=-1, keepdims=True)
        total_internal = (~reflects) & total_internal

        layers_n = lens.coating_indices[surface]
        layers_d = lens.coating_thicknesses_nm[surface]
        layers_n = jnp.where(forward[..., None], layers_n, layers_n[..., ::-1])
        layers_d = jnp.where(forward[..., None], layers_d, layers_d[..., ::-1])
        reflectance = coated_reflectance(n_before, n_after, cos_in, wavelength_nm, layers_n, layers_d)
        factor = jnp.where(reflects, reflectance, 1.0 - reflectance)

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
            active = event.active == 1
            state = jax.tree.map(lambda n, o: jnp.where(active.reshape(active.shape + (1,) * (n.ndim - 1)), n, o), new, state)
        else:  # padded (inactive) events are skipped at run time; cond stays reverse-differentiable
            state = jax.lax.cond(event.active == 1, apply_event, lambda state, _: state, state, event)
        return state, (state[0] if record_events else None)

    state = (
        origins,
        directions,
        jnp.ones(num_rays, bool),
        jnp.ones(num_rays, dtype),
        jnp.full(num_rays, LossReason.NOT_LOST, jnp.int32),
        jnp.zeros((num_rays, max(num_stop_passes, 1), 3), dtype),
        jnp.zeros(num_rays, jnp.int32),
    )
    scanned = jax.tree.map(lambda column: jnp.swapaxes(column, 0, 1), events) if per_ray else events
    (position, direction, valid, throughput, lost_at, stop_positions, _), history = jax.lax.scan(step, state, scanned)

    # propagate to the sensor plane
    dz = direction[:, 2]
    reaches = dz > 0
    t = safe_divide(lens.sensor_z_mm - position[:, 2], dz)
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


trace_events = eqx.filter_jit(_trace_events)


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
    return trace_events(
        lens, origins, directions, wavelength, EventTable.from_array(events), stop_pass_count(events, lens.stop_index), record_events
    )


def on_axis_fresnel(lens: Lens, events: EventTable, wavelength_nm: Array) -> Array:
    """Coated Fresnel factor of the on-axis ray for each stacked path (``events`` columns (P, E))
    at each wavelength (L,): (P, L). The product of the coated reflectances at the reflecting
    interfaces and the transmittances at every other surface crossed, at normal incidence."""
    wavelength_nm = jnp.asarray(wavelength_nm)
    count = wavelength_nm.shape[0]
    dtype = lens.thickness_mm.dtype
    origins = jnp.zeros((count, 3), dtype).at[:, 2].set(-1.0)
    directions = jnp.zeros((count, 3), dtype).at[:, 2].set(1.0)
    return jax.vmap(lambda e: trace_events(lens, origins, directions, wavelength_nm.astype(dtype), e, 1).throughput)(events)


def path_fresnel_factor(lens: Lens, path: GhostPath | None, wavelength_nm: ArrayLike = 587.56) -> Array:
    """Fresnel factor of a whole path at normal incidence (the on-axis ray), per wavelength.

    The product of the coated reflectances at the two reflecting interfaces and the transmittances
    at every other surface crossed; ``wavelength_nm`` may be a scalar or a 1-D array.
    """
    wavelength = jnp.atleast_1d(jnp.asarray(wavelength_nm, jnp.result_type(float)))
    events = jax.tree.map(lambda column: column[None], event_table(lens, path))
    factor = on_axis_fresnel(lens, events, wavelength)[0]
    return factor if jnp.ndim(wavelength_nm) else factor[0]


def rank_ghost_paths(lens: Lens, wavelength_nm: float = 550.0) -> list[tuple[GhostPath, float]]:
    """Ghost paths sorted by their on-axis (normal-incidence) Fresnel factor, strongest first."""
    factors = [(path, float(path_fresnel_factor(lens, path, wavelength_nm))) for path in ghost_paths(lens)]
    return sorted(factors, key=lambda item: -item[1])


def strongest_ghost_path(lens: Lens, wavelength_nm: float = 550.0) -> GhostPath:
    """The ghost path with the largest on-axis Fresnel factor (see :func:`rank_ghost_paths`)."""
    return rank_ghost_paths(lens, wavelength_nm)[0][0]
