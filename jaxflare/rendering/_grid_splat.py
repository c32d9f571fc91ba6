"""Spreading each grid cell's flux over its image: records and sub-samples (:mod:`._grid`).

A *record* is one cell of one job (a light node, a path, a grid over the entrance plane) at one
wavelength sub-node: its four corners' traced quantities interpolated to the sub-node's wavelength
(:mod:`._grid_trace` columns), and how they change with the point on the light (a finite
difference over the light's disc, averaged over the corners). A record holds ``s x s``
sub-samples, the points of a regular lattice in the cell (a cell whose corners disagree about
validity holds four, one per corner, each taking its own corner's values).

Each sub-sample interpolates its cell's corners bilinearly (sensor position, stop-plane positions,
clear-aperture margin, cosine, throughput, visibility), moves them to its own point on the light
(a Kronecker sequence over the light's disc, linear in the finite differences), is clipped by the
iris polygon on its interpolated stop positions and by the clear apertures on its interpolated
margin (so rims and polygon edges stay crisp), and carries its share of the cell's entrance flux:
the cell's area over the entrance disc's, times the light node's weight, times the sub-node's
colour (the light's colour and the path's coated Fresnel factor averaged over its wavelength
stratum). It is splatted with the one bilinear splat (:func:`._splat.splat`) into its layer at
the path's image level (a full, half, quarter ... resolution image: smooth, dim ghosts are drawn
coarser and upsampled). A sub-sample of a *blurred* job (:mod:`._grid_blur`: the light's disc
moves its path's image by a level pixel or more) stays at the light's centre and is splatted into
the job's slot instead, which is convolved with the disc's image when the layers are composed
(:func:`compose_layers`).

Everything is float32 with fixed shapes: one compiled loop over chunks of :data:`SUBSAMPLE_CHUNK`
sub-samples per render structure.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..optics import inside_iris
from ._grid_blur import BlurSlots, add_blurred_slots
from ._grid_trace import COS, FLUX, FRONT, HOOD, MARGIN, MAX_STOP_PASSES, NUM_QUANTITIES, SENSOR, STOP, THROUGHPUT, VALID, VISIBLE
from ._records import image_position
from ._splat import splat
from .effects import dirt_cell_taps, dirt_transmission, hood_inside

LINEAR = 9
"""Quantities that move with the point on the light (sensor x, y, stop x, y of three passes, margin)."""
RECORD = 4 * NUM_QUANTITIES + 2 * LINEAR
"""Floats per record: four corners, then the derivatives along the light's two axes."""
TILE = 16
"""Sub-samples per tile: a record's sub-samples are drawn in tiles of consecutive lattice points,
which read the record's corners, its job and its colour once (measured on the demo at 720p: the
per-sub-sample reads had cost more than the arithmetic)."""
SUBSAMPLE_CHUNK = 2**15
"""Sub-samples per step of the splat loop (tile slots, some of them empty)."""
TILES_PER_CHUNK = SUBSAMPLE_CHUNK // TILE
LEVELS = (1, 2, 4, 8, 16)
"""Image levels a path can be drawn at (pixels per level pixel along each axis)."""
SUB_NODE_CHOICES = (1, 2, 4, 5, 8, 10, 16, 20, 32)
"""Wavelength sub-nodes a piece can get (divisors of the colour table's band points)."""
SUB_NODE_OFFSETS = {m: sum(SUB_NODE_CHOICES[: SUB_NODE_CHOICES.index(m)]) for m in SUB_NODE_CHOICES}
"""Where each choice's sub-node colours start in a job's colour row."""
COLOUR_ROW = sum(SUB_NODE_CHOICES)
_KRONECKER = (0.7548776662466927, 0.5698402909980532)
"""The R2 sequence's multipliers (1 / g, 1 / g^2, g the plastic number): a low-discrepancy
sequence over the light's disc whose consecutive points are spread evenly."""


def level_layout(width: int, height: int) -> tuple[tuple[int, int, int, int], ...]:
    """Where each level's image lies in the packed buffer: (row0, column0, height, width).
    Level 1 fills the top ``height`` rows; the coarser levels lie side by side below it."""
    layout = [(0, 0, height, width)]
    column = 0
    for level in LEVELS[1:]:
        h, w = -(-height // level), -(-width // level)
        layout.append((height, column, h, w))
        column += w
    return tuple(layout)


def packed_shape(width: int, height: int) -> tuple[int, int]:
    layout = level_layout(width, height)
    return height + layout[1][2], max(width, sum(w for _, _, _, w in layout[1:]))


class JobTable(eqx.Module):
    """Per job (a light node x a path x a grid), what its sub-samples share."""

    path: Int[Array, " J"]
    slot: Int[Array, " J"]
    """Where the job's statistics go (its path in a render, the job itself in the pilot)."""
    light: Int[Array, " J"]
    layer: Int[Array, " J"]
    level: Int[Array, " J"]
    """Index into :data:`LEVELS`."""
    passes: Int[Array, " J"]
    """Stop passes of the path (1 or 3)."""
    domain: Float[Array, "J 4"]
    """u0, v0 (the grid's corner on the unit entrance disc) and the cell size du, dv."""
    node: Float[Array, "J 2"]
    """The light node (a point of the unit disc)."""
    stratum: Float[Array, "J 4"]
    """The node's stratum of the unit disc: inner and outer radius, first angle, angular span."""
    step: Float[Array, " J"]
    """The finite-difference step along the light's axes (0: a point light, no derivative)."""
    weight: Float[Array, " J"]
    """The node's share of its light (strata of equal area: 1 / nodes)."""
    interleave: Int[Array, " J"]
    """1: each wavelength sub-node's sub-sample lattice is shifted by its own Kronecker point (their
    union is finer, so each may be sparser); 0: every lattice centred in its cells (symmetric)."""
    colour: Float[Array, "J M C"]
    """Per wavelength sub-node of every sub-node choice (:data:`._grid_cells.SUB_NODE_OFFSETS`):
    the light's RGB x (Schlick model) the path's on-axis coated Fresnel factor, averaged over the
    sub-node's stratum of the band. ``C`` is 3 for a render; a fit's model may stack several
    colour planes (RGB each: its light-gain bases or spectral knots), splatted in one pass into
    buffers of ``C`` channels."""
    blur: BlurSlots | None = None
    """The blurred jobs' slots and kernels (:mod:`._grid_blur`); None: every extended light's
    disc is sampled per sub-sample."""


class RecordTable(eqx.Module):
    """Records (cells x sub-nodes) and their sub-sample counts, in sub-sample order."""

    values: Float[Array, "R F"]
    job: Int[Array, " R"]
    sub_node: Int[Array, " R"]
    sub_nodes: Int[Array, " R"]
    """How many sub-nodes the record's piece has (1: the whole band at once)."""
    piece: Float[Array, "R 3"]
    """The piece of the cell: its corner (a0, b0) and size, in cell units."""
    frame: Float[Array, "R 3"]
    """The square its four corners span (a0, b0, size, in cell units): (0, 0, 1) for the cell's
    own corners, a sub-cell's for a cell traced again on a finer grid (:mod:`._grid_refine`)."""
    side: Int[Array, " R"]
    """Sub-samples per side (``side**2`` of them; a mixed cell has side 2, one per corner)."""
    mixed: Array
    end: Int[Array, " R"]
    """Cumulative sub-sample count (exclusive end of each record's sub-samples)."""
    tile_record: Int[Array, " T"]
    """The record of each tile of :data:`TILE` sub-samples (padding tiles: any record)."""
    tile_local: Int[Array, " T"]
    """The index in its record of each tile's first sub-sample (padding tiles: past every record's end)."""


# --------------------------------------------------------------------------- records


def record_values(rows: Array, corners: Array, bracket: Array, step: Array) -> Array:
    """Record values (R, :data:`RECORD`) from vertex rows (N, Q): ``corners`` (R, 3, 2, 4) row
    indices of the four corners at the two traced wavelengths that bracket the sub-node (for the
    light's centre node and its two finite-difference points), ``bracket`` (R,) the weight of the
    second wavelength, ``step`` (R,) the finite-difference step (0: none)."""
    data = rows[corners]  # (R, 3, 2, 4, Q)
    w = bracket[:, None, None, None]
    at_wavelength = data[:, :, 0] * (1 - w) + data[:, :, 1] * w  # (R, 3, 4, Q)
    base = at_wavelength[:, 0]
    # a corner's derivative counts where it and its finite-difference point were traced through
    both = (data[:, :, 0, :, VALID] * data[:, :, 1, :, VALID]).min(axis=1)  # (R, 4)
    moves = []
    safe = jnp.where(step > 0, step, 1.0)[:, None, None]
    for f in (1, 2):
        usable = (both * (step > 0)[:, None])[:, :, None]
        difference = (at_wavelength[:, f, :, :LINEAR] - base[:, :, :LINEAR]) / safe
        count = jnp.maximum(usable.sum(axis=1), 1.0)
        moves.append(jnp.sum(jnp.where(usable > 0, difference, 0.0), axis=1) / count)
    return jnp.concatenate([base.reshape(base.shape[0], -1), moves[0], moves[1]], axis=-1)


RECORD_VALUES = eqx.filter_jit(record_values)


# --------------------------------------------------------------------------- sub-samples


def _runtime_one(count: Array) -> Array:
    """1.0 known only at run time: dividing by it keeps a value in memory instead of letting XLA
    recompute its chain of cheap operations in every consumer (REFERENCE.md section 8)."""
    c = jax.lax.stop_gradient(count).astype(jnp.float32)
    c = jnp.where(c > 0, c, 1.0)
    return c / c


def _kronecker(index: Array) -> tuple[Array, Array]:
    """The R2 point of each integer index, exact in 32-bit arithmetic (fractions in [0, 1))."""
    index = index.astype(jnp.uint32)
    scale = 2.0**-32
    a = jnp.uint32(int(_KRONECKER[0] * 2**32))
    b = jnp.uint32(int(_KRONECKER[1] * 2**32))
    half = jnp.uint32(2**31)
    return (index * a + half).astype(jnp.float32) * scale, (index * b + half).astype(jnp.float32) * scale


def tile_lattice(records: RecordTable, start_tile: Array, num_tiles: int):
    """The ``num_tiles`` tiles from ``start_tile``: each tile's record (T,) and its sub-samples'
    index in their record (T, :data:`TILE`), and which of them exist (a record's last tile may be
    part-filled; padding tiles hold none)."""
    t = start_tile + jnp.arange(num_tiles, dtype=jnp.int32)
    r = jnp.clip(records.tile_record[t], 0, records.end.shape[0] - 1)
    local = records.tile_local[t][:, None] + jnp.arange(TILE, dtype=jnp.int32)[None, :]
    side = records.side[r]
    return r, local, local < (side * side)[:, None]


class Subsamples(NamedTuple):
    """What :func:`subsample_values` gives per sub-sample (flat, in tile order)."""

    layer: Array
    level: Array
    column: Array
    """Image position (full-resolution pixels; pixel centres at integer + 0.5)."""
    row: Array
    value: Array
    """RGB (N, 3), or (N, C) with C / 3 colour planes (:class:`JobTable` ``colour``); zero where it
    misses the image."""
    hit: Array
    """It gets through and lands on the image (its statistics count)."""
    drawn: Array
    """``hit`` and splatted into its layer (not into a blur slot)."""
    slot: Array
    """The statistics slot."""
    share: Array
    """Its entrance weight where it hits."""
    unclipped: Array
    """Its value unclipped by the iris and clear apertures (the culling bound)."""
    front_xy: Array
    """Where it crosses the front vertex plane (mm)."""
    job: Array
    blur_value: Array
    """RGB where it gets through and lands in its job's blur slot (zero unless ``blur``)."""


def subsample_values(setup, jobs: JobTable, records: RecordTable, total: Array, start_tile: Array, num_tiles: int, blur: bool = False) -> Subsamples:
    """The sub-samples of ``num_tiles`` tiles from ``start_tile`` (``num_tiles * TILE`` of them,
    flat, in tile order; see :class:`Subsamples`). What a record or a job holds is read once per
    tile and shared by its sub-samples; ``total`` (the sub-sample count) only feeds the run-time
    one that keeps shared values in memory. With ``blur``, the sub-samples of blurred jobs
    (``jobs.blur``) are drawn at the light's node, for their slots (:mod:`._grid_blur`)."""
    r, local, used = tile_lattice(records, start_tile, num_tiles)
    one = _runtime_one(total)

    def keep(x):  # a value used many times: computed once, kept in memory
        return x / one

    side = records.side[r]
    index = (records.end[r] - side * side)[:, None] + local  # the sub-sample's global index
    sub_node, sub_nodes = records.sub_node[r], records.sub_nodes[r]
    job = records.job[r]
    # each sub-node's lattice is shifted by its own Kronecker point (interleaved: their union is finer)
    shift_a, shift_b = _kronecker(jnp.where(jobs.interleave[job] > 0, sub_node, 0))  # index 0: the centred lattice
    mixed = records.mixed[r]
    piece = records.piece[r]
    sidef = side.astype(jnp.float32)[:, None]
    a = piece[:, :1] + piece[:, 2:3] * (local % side[:, None] + jnp.where(mixed, 0.5, shift_a)[:, None]) / sidef
    b = piece[:, 1:2] + piece[:, 2:3] * (local // side[:, None] + jnp.where(mixed, 0.5, shift_b)[:, None]) / sidef
    frame = records.frame[r]
    wa = (a - frame[:, :1]) / frame[:, 2:3]  # where the sub-sample lies between its record's corners
    wb = (b - frame[:, 1:2]) / frame[:, 2:3]
    wa = jnp.where(mixed[:, None], jnp.round(wa), wa)
    wb = jnp.where(mixed[:, None], jnp.round(wb), wb)
    values = records.values[r]
    corners = values[:, : 4 * NUM_QUANTITIES].reshape(num_tiles, 4, NUM_QUANTITIES)
    weights = ((1 - wa) * (1 - wb), wa * (1 - wb), (1 - wa) * wb, wa * wb)  # (T, TILE) each
    # element-wise, not a batched product of tiny matrices (slower on a CPU)
    q = keep(sum(w[..., None] * corners[:, None, k] for k, w in enumerate(weights)))

    # the sub-sample's point on the light: a Kronecker point of the node's stratum
    k1, k2 = _kronecker(index)
    inner, outer, angle0, span = (jobs.stratum[job, k][:, None] for k in range(4))
    rho = jnp.sqrt(inner**2 + k1 * (outer**2 - inner**2))
    phi = angle0 + k2 * span
    node = jobs.node[job]
    sampled = jobs.step[job] > 0
    if blur:
        blurred = jobs.blur.base[job] >= 0
        sampled = sampled & ~blurred
    offset_s = jnp.where(sampled[:, None], rho * jnp.cos(phi) - node[:, :1], 0.0)
    offset_t = jnp.where(sampled[:, None], rho * jnp.sin(phi) - node[:, 1:], 0.0)
    move_s = values[:, None, 4 * NUM_QUANTITIES : 4 * NUM_QUANTITIES + LINEAR]
    move_t = values[:, None, 4 * NUM_QUANTITIES + LINEAR :]
    moved = keep(q[..., :LINEAR] + offset_s[..., None] * move_s + offset_t[..., None] * move_t)

    lens = setup.lens
    passes = jobs.passes[job][:, None]
    inside = jnp.ones(local.shape, bool)
    for p in range(MAX_STOP_PASSES):
        x, y = moved[..., STOP + 2 * p], moved[..., STOP + 2 * p + 1]
        through = inside_iris(x, y, lens.stop_radius_mm, lens.aperture_blades, lens.aperture_rotation_rad)
        inside = inside & (through | (p >= passes))
    valid = (q[..., VALID] > 0.999) & (moved[..., MARGIN] > 0) & inside

    effects = setup.effects
    factor = q[..., FLUX] * q[..., COS] * q[..., VISIBLE]
    if effects.hood is not None:
        factor = factor * jnp.where(hood_inside(effects.hood, q[..., HOOD : HOOD + 2].reshape(-1, 2)).reshape(local.shape), 1.0, 0.0)
    if not setup.schlick:
        factor = factor * q[..., THROUGHPUT]
    domain = jobs.domain[job]
    area = domain[:, 2] * domain[:, 3] * piece[:, 2] ** 2 / jnp.pi
    share = area / (side * side).astype(jnp.float32) * jobs.weight[job] / sub_nodes.astype(jnp.float32)  # per tile
    path = jobs.path[job]
    offset = jnp.asarray(np.asarray([SUB_NODE_OFFSETS.get(m, 0) for m in range(max(SUB_NODE_OFFSETS) + 1)], np.int32))[sub_nodes]
    # (T, C): RGB, or RGB per colour plane (a fit's light-gain bases or spectral knots in one pass)
    colour = jobs.colour[job, offset + sub_node]
    channels = colour.shape[-1]
    colour = (colour.reshape(-1, channels // 3, 3) * setup.path_tint[path][:, None, :]).reshape(-1, channels)
    value = keep(colour[:, None, :] * (factor * share[:, None])[..., None])
    flat = num_tiles * TILE
    value = value.reshape(flat, channels)
    if effects.dirt is not None:
        dirt = dirt_transmission(effects.dirt, q[..., FRONT : FRONT + 2].reshape(flat, 2), setup.front.radius_mm)
        value = (value.reshape(flat, channels // 3, 3) * dirt[:, None, :]).reshape(flat, channels)

    column, row = image_position(setup, moved[..., SENSOR : SENSOR + 2].reshape(flat, 2))
    width, height = setup.resolution
    on_sensor = (column >= 0) & (column < width) & (row >= 0) & (row < height)
    enabled = used.reshape(flat) & jnp.repeat(setup.path_enabled[path], TILE)
    reaches = enabled & on_sensor
    hit = reaches & valid.reshape(flat)
    per_sample = lambda x: jnp.repeat(x, TILE)  # noqa: E731
    if blur:  # the slot reaches its border beyond the image
        reach = per_sample(jobs.blur.border[job] * jnp.asarray(np.asarray(LEVELS, np.float32))[jobs.level[job]])
        in_slot = (column >= -reach) & (column < width + reach) & (row >= -reach) & (row < height + reach)
        into_slot = enabled & in_slot & valid.reshape(flat) & per_sample(blurred)
        blur_value = jnp.where(into_slot[:, None], value, 0.0)
        drawn = hit & ~per_sample(blurred)
    else:
        blur_value = jnp.zeros_like(value)
        drawn = hit
    # what the cell could carry at most: clipped by nothing but the image (the culling bound)
    unclipped = jnp.where((reaches & (q[..., VALID] > 0.999).reshape(flat))[:, None], value, 0.0)
    value = jnp.where(hit[:, None], value, 0.0)
    share = jnp.where(hit, per_sample(share), 0.0)
    front_xy = q[..., FRONT : FRONT + 2].reshape(flat, 2)
    return Subsamples(
        layer=per_sample(jobs.layer[job]), level=per_sample(jobs.level[job]), column=column, row=row, value=value, hit=hit, drawn=drawn,
        slot=per_sample(jobs.slot[job]), share=share, unclipped=unclipped, front_xy=front_xy, job=per_sample(job), blur_value=blur_value,
    )


def _level_position(level: Array, column: Array, row: Array, width: int, height: int):
    """Position in the packed buffer of a full-resolution position drawn at ``level``."""
    layout = np.asarray(level_layout(width, height), np.float32)
    scale = jnp.asarray(np.asarray(LEVELS, np.float32))[level]
    row0, column0, h, w = (jnp.asarray(layout[:, k])[level] for k in range(4))
    c = jnp.clip(column / scale, 0.5, w - 0.5) + column0
    r = jnp.clip(row / scale, 0.5, h - 0.5) + row0
    return c, r


class GridAccumulators(eqx.Module):
    buffer: Float[Array, "Y H W 3"]
    """The packed level images of every layer (:func:`level_layout`)."""
    path_energy: Float[Array, "P 3"]
    path_hits: Float[Array, " P"]
    """Sub-samples that reached the image."""
    path_weight: Float[Array, " P"]
    """Entrance-area weight of the sub-samples that reached the image (per path, summed over lights)."""
    path_bound: Float[Array, "P 3"]
    """What the path's cells could carry if the iris and the clear apertures clipped nothing."""
    atlas: Float[Array, "A 3"]
    """The blurred jobs' slots, flat (:class:`._grid_blur.BlurSlots`; one black pixel when none)."""


class DirtCells(eqx.Module):
    """A run of cells of a one-channel dirt map (row-major), each splatted into its own layer."""

    shape: tuple[int, int] = eqx.field(static=True)
    """The map's (rows, columns)."""
    first: Int[Array, ""]
    """The run's first cell (data: every run of a map shares one compiled splat)."""
    count: int = eqx.field(static=True)
    """Cells in the run (a run past the map's last cell has empty layers there)."""


def _splat_dirt_cells(buffer, atlas, slots: BlurSlots | None, cells: DirtCells, front_radius_mm, s: Subsamples, x, y):
    """Each sub-sample's value, times the weight with which :func:`dirt_transmission` reads each of
    its four dirt cells, into layer ``layer * cells.count + (cell - cells.first)`` (cells outside
    the run are dropped), or into the cell's copy of its blur slot (``slots``)."""
    for cell, weight in dirt_cell_taps(cells.shape, s.front_xy, front_radius_mm):
        local = cell - cells.first
        inside = (local >= 0) & (local < cells.count)
        local = jnp.clip(local, 0, cells.count - 1)
        buffer = splat(buffer, s.layer * cells.count + local, x, y, s.value * weight[:, None], s.drawn & inside)
        if slots is not None:
            atlas = _splat_slots(atlas, slots, s, s.blur_value * weight[:, None], inside & jnp.any(s.blur_value != 0.0, axis=-1), local * slots.size)
    return buffer, atlas


def _splat_slots(atlas: Array, slots: BlurSlots, s: Subsamples, value: Array, into: Array, offset: Array | int = 0) -> Array:
    """Blurred jobs' sub-samples (``value`` where ``into``) into their slots, bilinear at their
    level, offset by the border; ``offset`` (atlas pixels) picks a copy of the atlas (a dirt cell)."""
    job = s.job
    scale = jnp.asarray(np.asarray(LEVELS, np.float32))[s.level]
    border = slots.border[job]
    slot_w, slot_h = slots.width[job], slots.height[job]
    x = jnp.clip(s.column / scale + border, 0.5, slot_w - 0.5) - 0.5
    y = jnp.clip(s.row / scale + border, 0.5, slot_h - 0.5) - 0.5
    x0, y0 = jnp.floor(x), jnp.floor(y)
    fx, fy = x - x0, y - y0
    outside = atlas.shape[0]
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        xi = jnp.clip(x0.astype(jnp.int32) + dx, 0, slot_w - 1)
        yi = jnp.clip(y0.astype(jnp.int32) + dy, 0, slot_h - 1)
        index = jnp.where(into, offset + slots.base[job] + yi * slot_w + xi, outside)
        atlas = atlas.at[index].add((value * w[:, None]).astype(atlas.dtype), mode="drop")
    return atlas


def _splat_layers_and_slots(flat: Array, buffer_shape: tuple, slots: BlurSlots, s: Subsamples, x: Array, y: Array) -> Array:
    """:func:`._splat.splat` of the drawn sub-samples into their layers (packed position ``x``,
    ``y``) and of the blurred jobs' sub-samples into their slots, in one scatter per bilinear tap:
    ``flat`` holds the packed layers (``buffer_shape``), then the atlas."""
    num_layers, rows, columns, _ = buffer_shape
    job = s.job
    blurred = slots.base[job] >= 0
    border = slots.border[job]
    slot_w, slot_h = slots.width[job], slots.height[job]
    scale = jnp.asarray(np.asarray(LEVELS, np.float32))[s.level]
    px = jnp.where(blurred, jnp.clip(s.column / scale + border, 0.5, slot_w - 0.5), x) - 0.5
    py = jnp.where(blurred, jnp.clip(s.row / scale + border, 0.5, slot_h - 0.5), y) - 0.5
    origin = jnp.where(blurred, num_layers * rows * columns + slots.base[job], s.layer * rows * columns)
    stride = jnp.where(blurred, slot_w, columns)
    last_x, last_y = jnp.where(blurred, slot_w - 1, columns - 1), jnp.where(blurred, slot_h - 1, rows - 1)
    value = jnp.where(blurred[:, None], s.blur_value, s.value)
    into = jnp.where(blurred, jnp.any(s.blur_value != 0.0, axis=-1), s.drawn)
    x0, y0 = jnp.floor(px), jnp.floor(py)
    fx, fy = px - x0, py - y0
    outside = flat.shape[0]
    for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        xi = jnp.clip(x0.astype(jnp.int32) + dx, 0, last_x)
        yi = jnp.clip(y0.astype(jnp.int32) + dy, 0, last_y)
        index = jnp.where(into, origin + yi * stride + xi, outside)
        flat = flat.at[index].add((value * w[:, None]).astype(flat.dtype), mode="drop")
    return flat


@eqx.debug.assert_max_traces(max_traces=None)  # counts compilations: tests catch retracing with get_num_traces
def splat_subsamples(
    setup, jobs: JobTable, records: RecordTable, acc: GridAccumulators, total: Array, chunk_first: Array, chunks: Array,
    dirt_cells: DirtCells | None = None,
) -> GridAccumulators:
    """Every sub-sample of the records, in ``chunks`` chunks of :data:`TILES_PER_CHUNK` tiles (chunk
    ``c`` starts at tile ``chunk_first[c]``), splatted into the packed level images (a loop: one
    compilation per render structure). With ``dirt_cells`` (and no dirt map in ``setup``) each
    layer ``l`` becomes ``dirt_cells.count`` layers ``l * count + k``: the images of the one-hot
    maps of the run's cells, all in one pass over the sub-samples."""
    width, height = setup.resolution
    blur = jobs.blur is not None
    flat_layers = blur and dirt_cells is None  # the packed layers and the atlas as one flat array
    layer_pixels = acc.buffer.size // acc.buffer.shape[-1]

    def body(c, carry):
        acc, flat = carry
        s = subsample_values(setup, jobs, records, total, chunk_first[c], TILES_PER_CHUNK, blur=blur)
        x, y = _level_position(s.level, s.column, s.row, width, height)
        buffer, atlas = acc.buffer, acc.atlas
        if flat_layers:
            flat = _splat_layers_and_slots(flat, acc.buffer.shape, jobs.blur, s, x, y)
        elif dirt_cells is None:
            buffer = splat(acc.buffer, s.layer, x, y, s.value, s.drawn)
        else:
            buffer, atlas = _splat_dirt_cells(acc.buffer, acc.atlas, jobs.blur, dirt_cells, setup.front.radius_mm, s, x, y)
        acc = GridAccumulators(
            buffer=buffer,
            path_energy=acc.path_energy.at[s.slot].add(s.value),
            path_hits=acc.path_hits.at[s.slot].add(jnp.where(s.hit, 1.0, 0.0)),
            path_weight=acc.path_weight.at[s.slot].add(s.share),
            path_bound=acc.path_bound.at[s.slot].add(s.unclipped),
            atlas=atlas,
        )
        return acc, flat

    channels = acc.buffer.shape[-1]
    flat = jnp.concatenate([acc.buffer.reshape(-1, channels), acc.atlas]) if flat_layers else jnp.zeros((1, channels), acc.buffer.dtype)
    # a loop of static length (the bucketed chunk table) whose padding chunks are skipped at run
    # time: reverse-mode differentiable, unlike a loop to the dynamic ``chunks``
    acc, flat = jax.lax.fori_loop(
        0, chunk_first.shape[0], lambda c, carry: jax.lax.cond(c < chunks, body, lambda c, carry: carry, c, carry), (acc, flat)
    )
    if flat_layers:
        acc = dataclasses.replace(acc, buffer=flat[:layer_pixels].reshape(acc.buffer.shape), atlas=flat[layer_pixels:])
    return acc


SPLAT_SUBSAMPLES = eqx.filter_jit(splat_subsamples)


def compose_levels(buffer: Array, width: int, height: int) -> Array:
    """The full-resolution layers (Y, H, W, 3) of a packed buffer: every coarser level upsampled
    bilinearly (its pixels' flux shared out over the full-resolution pixels) and added."""
    layout = level_layout(width, height)
    row0, column0, h, w = layout[0]
    image = buffer[:, row0 : row0 + h, column0 : column0 + w]
    x = jnp.arange(width, dtype=jnp.float32) + 0.5
    y = jnp.arange(height, dtype=jnp.float32) + 0.5
    for level, (r0, c0, lh, lw) in zip(LEVELS[1:], layout[1:]):
        coarse = buffer[:, r0 : r0 + lh, c0 : c0 + lw]
        fx = jnp.clip(x / level - 0.5, 0.0, lw - 1.0)
        fy = jnp.clip(y / level - 0.5, 0.0, lh - 1.0)
        x0 = jnp.clip(jnp.floor(fx).astype(jnp.int32), 0, max(lw - 2, 0))
        y0 = jnp.clip(jnp.floor(fy).astype(jnp.int32), 0, max(lh - 2, 0))
        tx, ty = fx - x0, fy - y0
        x1, y1 = jnp.minimum(x0 + 1, lw - 1), jnp.minimum(y0 + 1, lh - 1)
        rows = coarse[:, y0] * (1 - ty)[None, :, None, None] + coarse[:, y1] * ty[None, :, None, None]
        up = rows[:, :, x0] * (1 - tx)[None, None, :, None] + rows[:, :, x1] * tx[None, None, :, None]
        image = image + up / (level * level)
    return image


COMPOSE_LEVELS = jax.jit(compose_levels, static_argnums=(1, 2))


def compose_layers(acc: GridAccumulators, jobs: JobTable, width: int, height: int, dirt_cells: int = 0) -> Array:
    """The full-resolution layers (Y, H, W, 3) of a splat: the blurred jobs' slots convolved and
    added to their layers, then every level composed (:func:`compose_levels`). ``dirt_cells``:
    the splat drew that many one-hot dirt cells per layer (``DirtCells.count``; each its own copy
    of the atlas, layer ``l`` becoming ``l * count + k``)."""
    buffer = acc.buffer
    if jobs.blur is not None:
        copies = max(dirt_cells, 1)
        buffer = add_blurred_slots(buffer, acc.atlas.reshape(copies, jobs.blur.size, acc.atlas.shape[-1]), jobs.blur, jobs.layer, width, height, level_layout)
    return compose_levels(buffer, width, height)


COMPOSE_LAYERS = eqx.filter_jit(compose_layers)


def empty_grid_accumulators(num_layers: int, num_paths: int, width: int, height: int, atlas_size: int = 1, channels: int = 3) -> GridAccumulators:
    """Zeroed accumulators; ``channels`` is 3 (RGB) or 3 per colour plane of the job colours."""
    h, w = packed_shape(width, height)
    return GridAccumulators(
        buffer=jnp.zeros((num_layers, h, w, channels), jnp.float32),
        path_energy=jnp.zeros((num_paths, channels), jnp.float32),
        path_hits=jnp.zeros(num_paths, jnp.float32),
        path_weight=jnp.zeros(num_paths, jnp.float32),
        path_bound=jnp.zeros((num_paths, channels), jnp.float32),
        atlas=jnp.zeros((max(atlas_size, 1), channels), jnp.float32),
    )


def chunk_count(tiles: int) -> int:
    """Chunks of the splat loop for ``tiles`` tiles."""
    return max(1, math.ceil(tiles / TILES_PER_CHUNK))
