"""Tracing the vertices of a ray grid (the deterministic estimator, :mod:`._grid`).

Hullin et al. 2011 trace a regular grid of rays through a lens without clipping and clip
afterwards, by the rays' coordinates on the aperture stop, so that the iris polygon stays crisp
however coarse the grid. Here every vertex is traced along its path through the *wide-open* lens
(clear apertures and iris removed, :func:`open_lens`) with the exact tracer's kernel
(:func:`jaxflare.optics.trace_events`, recording every event's position), and what clipping needs
is kept as numbers that can be interpolated between vertices:

- the stop-plane position of every pass through the stop (the iris test is made on interpolated
  positions, so the polygon's edges are exact lines whatever the grid);
- the clear-aperture margin: the smallest ``semi_aperture - r`` over the path's events, in mm
  (positive inside every clear aperture; interpolated, its zero line is the rim);
- the sensor position, the cosine at the sensor and the coated throughput.

A vertex the wide-open trace loses (it misses a surface, or is totally internally reflected where
it should refract) is invalid: the cells around it are handled by the estimator.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ..optics import EventTable, Lens, trace_events

OPEN_APERTURE_MM = 1.0e6
"""The clear semi-aperture and iris radius of the wide-open lens (mm): large enough to clip nothing."""


class VertexData(eqx.Module):
    """What the grid estimator keeps of each traced vertex (N rays)."""

    sensor_xy: Float[Array, "N 2"]
    stop_xy: Float[Array, "N P 2"]
    """Stop-plane position of each pass through the stop."""
    margin: Float[Array, " N"]
    """Smallest ``semi_aperture - r`` over the path's events (mm); > 0 inside every clear aperture."""
    cos_sensor: Float[Array, " N"]
    throughput: Float[Array, " N"]
    """Coated Fresnel product along the path at the ray's own angles and wavelength."""
    valid: Bool[Array, " N"]
    """The wide-open trace got through (no miss, no total internal reflection where it refracts)."""


def open_lens(lens: Lens) -> Lens:
    """``lens`` with every clear aperture and the iris opened (:data:`OPEN_APERTURE_MM`)."""
    big = jnp.full_like(lens.semi_aperture_mm, OPEN_APERTURE_MM)
    return eqx.tree_at(lambda l: (l.semi_aperture_mm, l.stop_radius_mm), lens, (big, jnp.asarray(OPEN_APERTURE_MM, lens.stop_radius_mm.dtype)))


def vertex_data(lens: Lens, origins: Array, directions: Array, wavelength_nm: Array, events: EventTable, num_stop_passes: int) -> VertexData:
    """Trace vertices (N rays) along one path (``events``: columns (E,)) through the wide-open
    ``lens`` and keep what the estimator interpolates. Differentiable in the lens's arrays (the
    tracer's guards keep lost rays finite)."""
    opened = open_lens(lens)
    traced = trace_events(opened, origins, directions, wavelength_nm, events, num_stop_passes, True)
    points = traced.event_positions  # (E, N, 3): the position after every event
    radius = jnp.sqrt(points[..., 0] ** 2 + points[..., 1] ** 2 + 1e-12)
    aperture = lens.semi_aperture_mm[events.surface][:, None]
    margins = jnp.where((events.active == 1)[:, None], aperture - radius, OPEN_APERTURE_MM)
    return VertexData(
        sensor_xy=traced.positions[:, :2],
        stop_xy=traced.stop_positions[:, :, :2],
        margin=jnp.min(margins, axis=0),
        cos_sensor=jnp.abs(traced.directions[:, 2]),
        throughput=traced.throughput,
        valid=traced.valid,
    )


TRACE_CHUNK = 1024
"""Rays per traced chunk: every chunk follows one path (measured: the exact kernel's throughput is
flat from 1k rays per call up, and small chunks waste little padding per path)."""

TRACE_BLOCK = 16
"""Chunks traced per call: every render traces whole blocks of ``TRACE_BLOCK * TRACE_CHUNK`` rays,
so the pilot and the main pass of every render of a lens share one compiled kernel."""

NUM_QUANTITIES = 18
"""Columns of a traced vertex row (see :func:`trace_grid`)."""
SENSOR, STOP, MARGIN, COS, THROUGHPUT, VALID, VISIBLE, FLUX, FRONT, HOOD = 0, 2, 8, 9, 10, 11, 12, 13, 14, 16
"""Column offsets in a vertex row: sensor x, y; stop x, y of passes 1-3; margin; cosine at the
sensor; throughput; valid (0/1); visibility of the light through the scene's geometry (0/1); then
what depends on the entrance ray alone: its flux factor (the light-to-lens coupling, times the
Schlick term at the front lens under that model); where it crosses the front vertex plane (x, y,
for the dirt map); where it crosses the hood's plane (x, y)."""
ENTRANCE_COLUMNS = 5
"""The entrance-ray columns (flux, front x, y, hood x, y), computed before tracing."""
MAX_STOP_PASSES = 3


def _pack(data: VertexData, visible: Array, entrance: Array) -> Array:
    passes = data.stop_xy.shape[1]
    stop = jnp.zeros((data.margin.shape[0], MAX_STOP_PASSES, 2), data.margin.dtype).at[:, :passes].set(data.stop_xy)
    return jnp.concatenate(
        [
            data.sensor_xy,
            stop.reshape(-1, 2 * MAX_STOP_PASSES),
            data.margin[:, None],
            data.cos_sensor[:, None],
            data.throughput[:, None],
            data.valid[:, None].astype(data.margin.dtype),
            visible[:, None].astype(data.margin.dtype),
            entrance.astype(data.margin.dtype),
        ],
        axis=-1,
    )


@eqx.debug.assert_max_traces(max_traces=None)  # counts compilations: tests catch retracing with get_num_traces
def trace_grid(
    lens: Lens, origins: Array, directions: Array, wavelength_nm: Array, visible: Array, entrance: Array, chunk_events: EventTable
) -> Array:
    """Trace every vertex of a grid render: (N, 3) rays in chunks of :data:`TRACE_CHUNK` (N a
    multiple of it), chunk ``c`` along the path ``chunk_events[c]`` (columns (C, E)); ``visible``
    (N,) and ``entrance`` (N, :data:`ENTRANCE_COLUMNS`) are copied into the rows. Returns the
    (N, :data:`NUM_QUANTITIES`) vertex rows. One compiled loop per lens structure and ray count."""
    count = origins.shape[0]
    chunks = count // TRACE_CHUNK
    rows = jnp.zeros((count, NUM_QUANTITIES), origins.dtype)

    def body(c, rows):
        start = c * TRACE_CHUNK
        take = lambda x: jax.lax.dynamic_slice_in_dim(x, start, TRACE_CHUNK)
        events = jax.tree.map(lambda column: column[c], chunk_events)
        data = vertex_data(lens, take(origins), take(directions), take(wavelength_nm), events, MAX_STOP_PASSES)
        return jax.lax.dynamic_update_slice_in_dim(rows, _pack(data, take(visible), take(entrance)), start, 0)

    return jax.lax.fori_loop(0, chunks, body, rows)


TRACE_GRID = eqx.filter_jit(trace_grid)
