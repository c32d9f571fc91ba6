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
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._lens import Lens
from ._paths import EventAction, EventTable, GhostPath, event_table, ghost_paths, path_events, stop_pass_count
from ._surface import Vector, facing_normal, inside_iris, intersect, refract_or_reflect, safe_divide
from ._thin_film import unpolarised_reflectance


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
    return medium_rows(lens, wavelength_nm).T


def medium_rows(lens: Lens, wavelength_nm: Array) -> Array:
    """(M, N) refractive index of every medium for every ray's wavelength: one row per medium.

    Each distinct glass of the lens is evaluated once (air rows are 1), with the three Sellmeier
    terms over one common denominator, ``n^2 = 1 + sum_i B_i l / (l - C_i)`` with ``l = lambda^2``,
    so one division and one square root per glass and ray: the media are the tracer's costliest
    per-ray set-up, and most lenses repeat a few glasses."""
    lam2 = jnp.square(wavelength_nm * 1e-3)
    media = (None,) + tuple(lens.media)
    rows: list = [None] * len(media)
    first: dict = {}
    for m, glass in enumerate(media):
        if glass is None:
            continue
        key = (tuple(glass.sellmeier_b), tuple(glass.sellmeier_c_um2))
        if key in first:
            rows[m] = rows[first[key]]
            continue
        first[key] = m
        b, c = lens.sellmeier_b[m].astype(lam2.dtype), lens.sellmeier_c_um2[m].astype(lam2.dtype)
        d0, d1, d2 = lam2 - c[0], lam2 - c[1], lam2 - c[2]
        numerator = lam2 * (b[0] * d1 * d2 + b[1] * d0 * d2 + b[2] * d0 * d1)
        rows[m] = jnp.sqrt(1.0 + numerator / (d0 * d1 * d2))
    ones = jnp.ones_like(lam2)
    return jnp.stack([ones if row is None else row for row in rows])


CHUNK_RAYS = 16384
"""Rays traced together: larger batches are traced chunk by chunk (``lax.map``), so that each
event's arrays stay in the cache."""


class _Rays(NamedTuple):
    """The tracer's state, a structure of arrays (one entry per ray)."""

    position: Vector
    direction: Vector
    valid: Array
    throughput: Array
    lost_at: Array
    stop: tuple[Vector, ...]
    stop_pass: Array


def _runtime_one(wavelength_nm: Array) -> Array:
    """1.0 as a value only known at run time (from the data): dividing by it makes XLA keep a value
    in memory instead of recomputing its chain of cheap operations in every consumer, which on CPU
    multiplied the tracer's work about 26-fold (measured; REFERENCE.md section 8)."""
    w = jax.lax.stop_gradient(wavelength_nm[0])
    w = jnp.where(w > 0, w, 1.0)
    return w / w


@eqx.debug.assert_max_traces(max_traces=None)  # counts compilations: tests catch retracing with get_num_traces
def _trace_events(
    lens: Lens, origins: Array, directions: Array, wavelength_nm: Array, events: EventTable, num_stop_passes: int,
    record_events: bool = False, fresnel: bool = True, slot: Array | None = None,
) -> TraceResult:
    """Trace rays along ``events``: columns of shape (E,) for one path shared by every ray; (N, E)
    for a path per ray; or, with ``slot`` (N,), (P, E) for P paths of which ray n follows path
    ``slot[n]`` (a renderer batch that mixes paths). ``num_stop_passes`` (static): how many stop
    crossings to record; ``fresnel`` (static): multiply the coated Fresnel factor of every event
    into ``throughput`` (else the throughput is 1 for every valid ray).

    One ``lax.scan`` over the events; events no ray of a chunk needs (a path's padding) are skipped
    at run time (``lax.cond`` on a scalar), the rest masked per ray. Rays go in chunks of
    :data:`CHUNK_RAYS`.
    """
    count = origins.shape[0]
    dtype = origins.dtype
    per_ray = events.surface.ndim == 2
    if slot is None and per_ray:  # a path per ray: each ray its own row
        slot = jnp.arange(count)
    vertex_z = jnp.concatenate([jnp.zeros(1, lens.thickness_mm.dtype), jnp.cumsum(lens.thickness_mm[:-1])]).astype(dtype)
    surface_table = jnp.stack(
        [vertex_z, lens.curvature_per_mm.astype(dtype), lens.conic.astype(dtype), lens.surface_kind.astype(dtype), (lens.semi_aperture_mm**2).astype(dtype)],
        axis=-1,
    )  # (S, 5): one gather per event fetches a surface's parameters for every ray
    aspheric = lens.aspheric_coefficients.astype(dtype)
    num_slots = max(num_stop_passes, 1)

    def trace_chunk(origins, directions, wavelength, slot):
        size = origins.shape[0]
        one = _runtime_one(wavelength)

        def keep(value):  # a value used many times: computed once, kept in memory
            return value / one

        by_medium = keep(medium_rows(lens, wavelength).astype(dtype))  # (M, n): a medium's indices for every ray are one row
        indices = by_medium.T if per_ray else None  # (n, M), gathered per ray
        norm = jnp.sqrt(jnp.sum(directions**2, axis=-1))
        zeros = jnp.zeros(size, dtype)
        rays = _Rays(
            position=Vector(origins[:, 0], origins[:, 1], origins[:, 2]),
            direction=Vector(*(directions[:, k] / norm for k in range(3))),
            valid=jnp.ones(size, bool),
            throughput=jnp.ones(size, dtype),
            lost_at=jnp.full(size, LossReason.NOT_LOST, jnp.int32),
            stop=tuple(Vector(zeros, zeros, zeros) for _ in range(num_slots)),
            stop_pass=jnp.zeros(size, jnp.int32),
        )

        def apply_event(rays: _Rays, event) -> _Rays:
            surface, forward, reflects = event.surface, event.travel > 0, event.action == EventAction.REFLECT
            active = event.active == 1
            vz, curvature, conic, kind, semi2 = (surface_table[surface, k] for k in range(5))
            point, normal, hit = intersect(
                rays.position, rays.direction, vz, curvature, conic, aspheric[surface], kind, lens.has_aspheres, keep,
            )
            r2 = keep(point.x**2 + point.y**2)
            is_stop = surface == lens.stop_index
            iris = inside_iris(point.x, point.y, lens.stop_radius_mm.astype(dtype), lens.aperture_blades, lens.aperture_rotation_rad.astype(dtype))
            inside = (r2 <= semi2) & (~is_stop | iris)
            medium_before = jnp.where(forward, surface, surface + 1)
            medium_after = jnp.where(forward, surface + 1, surface)
            if per_ray:
                n_before = jnp.take_along_axis(indices, medium_before[:, None], 1)[:, 0]
                n_after = jnp.take_along_axis(indices, medium_after[:, None], 1)[:, 0]
            else:
                n_before, n_after = by_medium[medium_before], by_medium[medium_after]
            normal, cos_in = facing_normal(normal, rays.direction, keep)
            direction, total_internal = refract_or_reflect(rays.direction, normal, cos_in, keep(n_before / n_after), reflects, keep)
            ok = hit & inside & ~total_internal
            update = rays.valid & ok & active
            throughput = rays.throughput
            if fresnel:
                layers_n = lens.coating_indices[surface].astype(dtype)
                layers_d = lens.coating_thicknesses_nm[surface].astype(dtype)
                layers_n = jnp.where(forward[..., None], layers_n, layers_n[..., ::-1])
                layers_d = jnp.where(forward[..., None], layers_d, layers_d[..., ::-1])
                reflectance = unpolarised_reflectance(n_before, n_after, cos_in, wavelength, layers_n, layers_d)
                throughput = jnp.where(update, throughput * jnp.where(reflects, reflectance, 1.0 - reflectance), throughput)
            record = is_stop & active
            stop = tuple(
                Vector(*(jnp.where(record & (rays.stop_pass == slot), new, old) for new, old in zip(point, recorded)))
                for slot, recorded in enumerate(rays.stop)
            )
            return _Rays(
                position=Vector(*(keep(jnp.where(update, new, old)) for new, old in zip(point, rays.position))),
                direction=Vector(*(keep(jnp.where(update, new, old)) for new, old in zip(direction, rays.direction))),
                valid=rays.valid & (ok | ~active),
                throughput=throughput,
                lost_at=jnp.where(rays.valid & ~ok & active, surface, rays.lost_at),
                stop=stop,
                stop_pass=rays.stop_pass + jnp.where(record, 1, 0),
            )

        def step(rays, event):
            # padding is skipped at run time: a path shared by every ray skips its own; with a path
            # per ray, an event no ray of the chunk needs is skipped (sort rays by path length to
            # make that common: ExactPathTracer does), and the others mask it ray by ray
            needed = jnp.any(event.active == 1) if per_ray else event.active == 1
            rays = jax.lax.cond(needed, apply_event, lambda rays, _: rays, rays, event)
            return rays, (jnp.stack(rays.position, axis=-1) if record_events else None)

        if per_ray:  # the scan reads each event's row of the paths' table; each ray takes its path's entry
            scanned = jax.tree.map(lambda column: jnp.swapaxes(column, 0, 1), events)
            rows = lambda row: jax.tree.map(lambda column: column[slot], row)  # noqa: E731
        else:
            scanned, rows = events, lambda row: row
        rays, history = jax.lax.scan(lambda rays, row: step(rays, rows(row)), rays, scanned)

        # propagate to the sensor plane
        sensor_z = lens.sensor_z_mm.astype(dtype)
        position, direction = rays.position, rays.direction
        reaches = direction.z > 0
        t = safe_divide(sensor_z - position.z, direction.z)
        valid = rays.valid & reaches
        at_sensor = jnp.stack([position.x + t * direction.x, position.y + t * direction.y, jnp.broadcast_to(sensor_z, (size,))], axis=-1)
        positions = jnp.where(valid[:, None], at_sensor, jnp.stack(position, axis=-1))
        stops = jnp.stack([jnp.stack(stop, axis=-1) for stop in rays.stop], axis=1)[:, :num_stop_passes]
        return (
            positions, jnp.stack(direction, axis=-1), valid, jnp.where(valid, rays.throughput, 0.0),
            jnp.where(rays.valid & ~reaches, lens.num_surfaces, rays.lost_at), stops, history,
        )

    if count <= CHUNK_RAYS:
        out = trace_chunk(origins, directions, wavelength_nm, slot)
    else:
        blocks = -(-count // CHUNK_RAYS)
        pad = blocks * CHUNK_RAYS - count

        def in_blocks(x):  # pad with copies of the last ray, then (blocks, CHUNK_RAYS, ...)
            x = jnp.concatenate([x, jnp.broadcast_to(x[-1:], (pad,) + x.shape[1:])]) if pad else x
            return x.reshape((blocks, CHUNK_RAYS) + x.shape[1:])

        chunks = (in_blocks(origins), in_blocks(directions), in_blocks(wavelength_nm))
        if per_ray:
            out = jax.lax.map(lambda args: trace_chunk(*args), chunks + (in_blocks(slot),))
        else:
            out = jax.lax.map(lambda args: trace_chunk(*args, None), chunks)
        *fields, history = out
        fields = [x.reshape((-1,) + x.shape[2:])[:count] for x in fields]
        if record_events:  # (blocks, E, CHUNK, 3) -> (E, N, 3)
            history = jnp.swapaxes(history, 0, 1).reshape((history.shape[1], -1, 3))[:, :count]
        out = (*fields, history)
    positions, directions_out, valid, throughput, lost_at, stops, history = out
    return TraceResult(
        positions=positions, directions=directions_out, valid=valid, throughput=throughput, lost_at_surface=lost_at,
        stop_positions=stops, event_positions=history,
    )


_trace_events_jit = eqx.filter_jit(_trace_events)


MIN_RAY_BUCKET = 2048
"""The smallest batch a trace called with concrete arrays compiles for: every batch of up to this
many rays shares one program per lens (a compile costs 1-2 s on a 2-core CPU; tracing 2048 rays
about a millisecond). A trace inside a transformation (a render step's ``jit``, ``grad``) pads to
:data:`MIN_TRACED_RAY_BUCKET`: its padding is work inside the caller's program."""
MIN_TRACED_RAY_BUCKET = 128


def ray_bucket(count: int, minimum: int = MIN_RAY_BUCKET) -> int:
    """The number of rays a batch of ``count`` is traced as: the next power of two (at least
    ``minimum``) up to :data:`CHUNK_RAYS`, then the next multiple of it. Batches of nearby sizes
    share one compiled program (compiling costs seconds; tracing the padding, milliseconds at
    most)."""
    if count <= CHUNK_RAYS:
        return max(minimum, 1 << max(count - 1, 0).bit_length())
    return -(-count // CHUNK_RAYS) * CHUNK_RAYS


def trace_events(
    lens: Lens, origins: Array, directions: Array, wavelength_nm: Array, events: EventTable, num_stop_passes: int,
    record_events: bool = False, fresnel: bool = True, slot: Array | None = None,
) -> TraceResult:
    """Trace rays along ``events``: columns of shape (E,) for one path shared by every ray; (N, E)
    for a path per ray; or, with ``slot`` (N,), (P, E) for P paths of which ray n follows path
    ``slot[n]``. ``num_stop_passes`` (static): how many stop crossings to record; ``fresnel``
    (static): multiply the coated Fresnel factor of every event into ``throughput`` (else the
    throughput is 1 for every valid ray).

    Jit-compiled once per lens structure, event-table shape and :func:`ray_bucket` of the batch:
    the rays are padded with copies of the last one up to the bucket, and the padding is cut off
    the result. Inside a transformation (a render step's ``jit``, ``grad``) the smallest bucket is
    :data:`MIN_TRACED_RAY_BUCKET`: the padding is work inside the caller's program."""
    count = origins.shape[0]
    traced = any(isinstance(x, jax.core.Tracer) for x in (origins, directions, wavelength_nm, slot, events.surface))
    size = ray_bucket(count, MIN_TRACED_RAY_BUCKET if traced else MIN_RAY_BUCKET)
    if count == 0 or size == count:
        return _trace_events_jit(lens, origins, directions, wavelength_nm, events, num_stop_passes, record_events, fresnel, slot)

    def pad(x):
        x = jnp.asarray(x)
        return jnp.concatenate([x, jnp.broadcast_to(x[-1:], (size - count,) + x.shape[1:])])

    if slot is not None:
        slot = pad(slot)
    elif events.surface.ndim == 2:  # a path per ray
        events = jax.tree.map(pad, events)
    result = _trace_events_jit(lens, pad(origins), pad(directions), pad(wavelength_nm), events, num_stop_passes, record_events, fresnel, slot)
    return TraceResult(
        positions=result.positions[:count], directions=result.directions[:count], valid=result.valid[:count],
        throughput=result.throughput[:count], lost_at_surface=result.lost_at_surface[:count],
        stop_positions=result.stop_positions[:count],
        event_positions=None if result.event_positions is None else result.event_positions[:, :count],
    )


trace_events.__wrapped__ = _trace_events  # the traced kernel: eqx.debug.get_num_traces counts its compilations


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
    fresnel: bool = True,
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
        fresnel: compute the coated Fresnel throughput (default); False skips it (the throughput
            is then 1 for every valid ray), for callers that only need where rays go.

    Returns:
        A :class:`TraceResult` with positions, directions, a validity mask, Fresnel throughput,
        the surface where each invalid ray was lost, and the stop-plane positions of each pass.

    Differentiable with respect to ray inputs and the lens's array fields; jit-compiled once per
    lens structure (all paths of a lens share one compilation).
    """
    origins, directions, wavelength = ray_arguments(origins, directions, wavelength_nm)
    events = path_events(lens, path)
    return trace_events(
        lens, origins, directions, wavelength, EventTable.from_array(events), stop_pass_count(events, lens.stop_index), record_events, fresnel
    )


@eqx.filter_jit
def on_axis_fresnel(lens: Lens, events: EventTable, wavelength_nm: Array) -> Array:
    """Coated Fresnel factor of the on-axis ray for each stacked path (``events`` columns (P, E))
    at each wavelength (L,): (P, L). The product of the coated reflectances at the reflecting
    interfaces and the transmittances at every other surface crossed, at normal incidence.

    Evaluated in closed form, event by event: on the axis every surface is met at its vertex at
    normal incidence (inside every clear aperture and the iris, no total internal reflection), so
    the trace reduces to these factors; ``tests/optics/test_trace.py`` checks the two agree. One
    small compiled program per shape (the tracer's loop would compile for seconds per path count)."""
    wavelength = jnp.asarray(wavelength_nm)
    dtype = lens.thickness_mm.dtype
    wavelength = wavelength.astype(dtype)
    indices = medium_rows(lens, wavelength)  # (M, L)
    surface = events.surface
    forward = events.travel > 0
    reflects = events.action == EventAction.REFLECT
    n_before = indices[jnp.where(forward, surface, surface + 1)]  # (P, E, L)
    n_after = indices[jnp.where(forward, surface + 1, surface)]
    layers_n = lens.coating_indices[surface].astype(dtype)  # (P, E, K), in the order the light meets them
    layers_d = lens.coating_thicknesses_nm[surface].astype(dtype)
    layers_n = jnp.where(forward[..., None], layers_n, layers_n[..., ::-1])
    layers_d = jnp.where(forward[..., None], layers_d, layers_d[..., ::-1])
    reflectance = unpolarised_reflectance(n_before, n_after, 1.0, wavelength, layers_n[..., None, :], layers_d[..., None, :])
    factor = jnp.where(reflects[..., None], reflectance, 1.0 - reflectance)
    return jnp.prod(jnp.where((events.active == 1)[..., None], factor, 1.0), axis=-2)


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
