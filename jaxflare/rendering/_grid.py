"""The deterministic ray-grid estimator (after Hullin, Eisemann, Seidel & Lee 2011).

For each job (a light node x a lens path) a regular grid of rays over the part of the entrance
disc that can reach the image is traced through the wide-open lens at a few wavelengths
(:mod:`._grid_trace`); every grid cell's flux is then spread over the cell's image on the sensor by
sub-samples interpolated from its corners, clipped by the iris on interpolated stop-plane
positions and by the clear apertures on interpolated margins, and splatted (:mod:`._grid_splat`).
Where the map compresses, the sub-samples crowd and the image brightens; where it folds, they
overlap: flux is conserved either way. Nothing is random: the image is the same at every seed.

How much each path gets is decided from a pilot: a coarse grid render (16 x 16 cells over the
whole entrance disc, three wavelengths, one sixteenth of the image resolution) that gives each
path's energy, an upper bound of it (the flux of every cell the convex-hull tests cannot exclude:
the culling bound), its image (for the error model), how much its map bends, how far its colours
spread and how far the light's disc moves it. From these, per path:

- the entrance domain (the pilot cells that may carry light, dilated by one cell);
- the grid resolution: bilinear interpolation of the sensor position within tolerance
  (second differences measured on the pilot grid);
- the image level (full, 1/2 ... 1/16 resolution): the coarsest whose edge blur (measured on the
  pilot image: total variation x irradiance x level) keeps the estimated relative RMSE of the
  picture within the quality's target, greedily, cheapest first;
- wavelength sub-nodes: enough that the colour fringes' steps stay under a level pixel.

Spectra: the band is split into ``M`` equal strata per path; each stratum's sub-samples take the
sensor positions at its centre (interpolated between the traced wavelengths, linear in 1 / lambda^2)
and carry the stratum's mean colour (the light's RGB response x the path's coated Fresnel factor,
averaged over 160 wavelengths), so the colour integral is exact whatever ``M``.

Extended lights (spheres, discs, a sun's disc): each vertex is also traced from two points of the
light's disc, so each cell knows how its image moves with the point on the light (linearly). A
path whose image the disc moves by at least a level pixel is drawn for the light's centre and
convolved with the disc's image under its mean move (:mod:`._grid_blur`: noise free); a smaller
move is sampled, each sub-sample at its own point of the disc.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..optics import EventTable
from ..scenes import LightKind
from ._grid_splat import (
    COLOUR_ROW,
    LEVELS,
    RECORD_VALUES,
    SPLAT_SUBSAMPLES,
    SUB_NODE_CHOICES,
    SUB_NODE_OFFSETS,
    TILE,
    TILES_PER_CHUNK,
    JobTable,
    RecordTable,
    chunk_count,
    empty_grid_accumulators,
    level_layout,
)
from ._grid_blur import blur_slots
from ._grid_trace import TRACE_BLOCK, TRACE_CHUNK, TRACE_GRID
from ._lights import light_rgb
from ._records import front_cosine, front_vertex_plane_xy
from ._sampling import sample_connections
from .effects import hood_crossing, segment_visibility

BAND_POINTS = 160
"""Wavelengths over the band each sub-node's colour is averaged over (2.5 nm apart)."""


@dataclasses.dataclass(frozen=True)
class GridQuality:
    """What the grid estimator spends at a quality level."""

    target_error: float
    """The relative RMSE of the flare image the plan aims for (its error model's budget)."""
    wavelengths: int
    """Traced wavelengths per vertex (sub-node positions are interpolated between them)."""
    max_sub_nodes: int
    max_cells: int
    """Most grid cells per side of a path's entrance domain."""
    min_cells: int
    tolerance_px: float
    """Bilinear interpolation tolerance of sensor positions, in level pixels."""
    spacing_px: float
    """Sub-sample spacing on the image, in level pixels."""
    fringe_px: float
    """Colour fringes are drawn in steps of at most this (level pixels): an edge piece gets
    enough wavelength sub-nodes for its colour spread."""
    colour_error: float
    """Relative error allowed to a smooth region's channels from drawing each wavelength stratum
    at its centre (its lateral colour shift x the irradiance gradient)."""
    max_side: int
    """Most sub-samples per cell side."""
    blur: bool = True
    """Draw an extended light's disc by convolving its paths' images (:mod:`._grid_blur`: noise
    free); False samples the disc per sub-sample (a Kronecker point each: speckled where the disc
    moves an image by many pixels)."""
    interleave: bool = True
    """Shift each wavelength sub-node's sub-sample lattice by its own Kronecker point, so that each
    can be up to twice sparser (fewer sub-samples); False centres every lattice in its cells (the
    image of a symmetric scene is then symmetric to float rounding, at up to 4 times the cost)."""
    edge_side: int = 8
    """Fewest sub-samples per side of a piece a clipping edge may cross (see :func:`cell_pieces`)."""
    pilot_cells: int = 16
    pilot_level: int = 16


GRID_QUALITY = {
    # preview: aims at the 5 % preview error; sub-samples half a level pixel apart and 4
    # per side of an edge piece, up to 96 cells (chosen from the error-against-time chart: see
    # benchmarks/README.md; 0.7 or 1 level pixel apart was 10-20 % faster on the demo but the
    # lattice beat against the pixel grid in stripes over its veil, seen at 1:1)
    "preview": GridQuality(
        target_error=0.05, wavelengths=3, max_sub_nodes=16, max_cells=96, min_cells=8, tolerance_px=0.3, spacing_px=0.5, fringe_px=1.5, colour_error=0.01, max_side=256,
        edge_side=4,
    ),
    "production": GridQuality(
        target_error=0.006, wavelengths=5, max_sub_nodes=32, max_cells=96, min_cells=12, tolerance_px=0.15, spacing_px=0.4, fringe_px=0.75, colour_error=0.003, max_side=512,
    ),
}
EDGE_ERROR = 0.3
"""The error model's constant: squared error of an edge of irradiance I and length L drawn at
level l ~ EDGE_ERROR x I^2 x L x l (a step blurred over about a level pixel)."""
BLUR_DENSITY = 4.0
"""Sub-samples per level pixel^2 of a light's blurred image (the core and sharp ghosts)."""



@dataclasses.dataclass
class GridJob:
    """One light node of one path: its grid and how its cells are drawn."""

    path: int
    slot: int
    light: int
    layer: int
    level: int
    """Index into :data:`LEVELS`."""
    passes: int
    domain: tuple[float, float, float, float]
    """u0, v0, du, dv on the unit entrance disc."""
    cells: int
    node: tuple[float, float] = (0.0, 0.0)
    stratum: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 2 * math.pi)
    step: float = 0.0
    """Finite-difference step on the light's unit disc (0: traced at the node only)."""
    weight: float = 1.0
    sub_nodes: int = 1
    max_side: int = 24
    spacing_px: float = 0.7
    min_subsamples: int = 0
    interleave: bool = True
    blur: bool = False
    """An extended light whose disc may be drawn by convolution (:mod:`._grid_blur`)."""
    blur_jacobian: np.ndarray | None = None
    """Set when the job is traced: its image move per unit disc move (level px), None: sampled."""
    blur_border: int = 0
    """Set with ``blur_jacobian``: how far (level px) beyond the image its cells can still blur in."""
    row0: int = 0

    @property
    def vertices(self) -> int:
        return (self.cells + 1) ** 2

    @property
    def variants(self) -> int:
        return 3 if self.step > 0 else 1


def traced_wavelengths(count: int, band: tuple[float, float]) -> np.ndarray:
    """``count`` wavelengths over the band, evenly spaced in 1 / lambda^2 (ends included)."""
    low, high = band
    if count == 1:
        return np.asarray([0.5 * (low + high)])
    x = np.linspace(low**-2, high**-2, count)
    return x**-0.5


# --------------------------------------------------------------------------- tracing


def _vertex_rays(lights, front, spectral, lens, hood, schlick, light, front_unit, node, light_unit, wavelength):
    """The rays of vertices: from the point ``light_unit`` of each light to the entrance point
    ``front_unit`` of the node's entrance disc, and the entrance columns of the node's ray (its
    flux factor, front-plane and hood-plane crossings). Takes only what it reads of the render
    set-up, so the pilot and the main pass share one compilation."""
    count = light.shape[0]
    key = jax.random.PRNGKey(0)
    base = sample_connections(lights, front, spectral, key, count, 1, light=light, front_unit=front_unit, light_unit=node)
    moved = sample_connections(lights, front, spectral, key, count, 1, light=light, front_unit=front_unit, light_unit=light_unit)
    finite = lights.kind[light] != LightKind.DIRECTIONAL
    towards = base.origins - moved.light_point_mm
    towards = towards / jnp.linalg.norm(towards, axis=-1, keepdims=True)
    directions = jnp.where(finite[:, None], towards, moved.directions)
    flux = base.flux
    xy = front_vertex_plane_xy(base.origins, base.directions)
    if schlick:
        flux = flux * (1.0 - (1.0 - front_cosine(lens, xy, base.directions)) ** 5)
    if hood is not None:
        crossing = jnp.clip(hood_crossing(hood, base.origins, base.directions), -1e6, 1e6)
    else:
        crossing = jnp.zeros_like(xy)
    entrance = jnp.concatenate([flux[:, None], xy, crossing], axis=-1)
    return base.origins, directions, moved.light_point_mm, wavelength.astype(base.origins.dtype), entrance


VERTEX_RAYS = eqx.filter_jit(_vertex_rays)


def trace_jobs(
    setup, lens, jobs: list[GridJob], events: list[np.ndarray], wavelengths: np.ndarray, *, packed: bool = False
) -> tuple[jax.Array, np.ndarray]:
    """Trace every vertex of ``jobs`` (their ``row0`` is set here) at the traced ``wavelengths``;
    ``events[k]`` is path k's event array. Returns the vertex rows on the device and on the host.
    Each job's rows start a new chunk of :data:`TRACE_CHUNK`; ``packed``: only each run of
    consecutive jobs of one path does (many small jobs, such as the sub-grids of
    :mod:`._grid_refine`, would otherwise be mostly padding)."""
    pieces = {k: [] for k in ("light", "unit", "node", "light_unit", "wavelength")}
    chunk_paths = []
    row = 0
    run_start = 0
    for index, job in enumerate(jobs):
        job.row0 = row
        n = job.cells
        u0, v0, du, dv = job.domain
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1))
        unit = np.stack([u0 + i.ravel() * du, v0 + j.ravel() * dv], axis=-1)
        offsets = [(0.0, 0.0), (job.step, 0.0), (0.0, job.step)][: job.variants]
        count = 0
        for offset in offsets:
            for wavelength in wavelengths:
                v = unit.shape[0]
                pieces["light"].append(np.full(v, job.light, np.int32))
                pieces["unit"].append(unit)
                pieces["node"].append(np.broadcast_to(job.node, (v, 2)))
                pieces["light_unit"].append(np.broadcast_to((job.node[0] + offset[0], job.node[1] + offset[1]), (v, 2)))
                pieces["wavelength"].append(np.full(v, wavelength))
                count += v
        row += count
        if packed and index + 1 < len(jobs) and jobs[index + 1].path == job.path:
            continue  # the next job's rows follow in the same chunk
        count = row - run_start
        padded = -(-count // TRACE_CHUNK) * TRACE_CHUNK
        if padded > count:
            pad = padded - count
            pieces["light"].append(np.full(pad, job.light, np.int32))
            pieces["unit"].append(np.zeros((pad, 2)))
            pieces["node"].append(np.zeros((pad, 2)))
            pieces["light_unit"].append(np.zeros((pad, 2)))
            pieces["wavelength"].append(np.full(pad, wavelengths[0]))
        chunk_paths += [job.path] * (padded // TRACE_CHUNK)
        row = run_start + padded
        run_start = row
    total = row
    block_rays = TRACE_BLOCK * TRACE_CHUNK
    padded_total = -(-total // block_rays) * block_rays  # whole blocks: one compiled shape for every render
    if padded_total > total:
        pad = padded_total - total
        pieces["light"].append(np.zeros(pad, np.int32))
        pieces["unit"].append(np.zeros((pad, 2)))
        pieces["node"].append(np.zeros((pad, 2)))
        pieces["light_unit"].append(np.zeros((pad, 2)))
        pieces["wavelength"].append(np.full(pad, wavelengths[0]))
        chunk_paths += [jobs[0].path] * ((padded_total - total) // TRACE_CHUNK)
    arrays = {k: np.concatenate(v) for k, v in pieces.items()}
    f32 = jnp.float32
    effects = setup.effects
    event_rows = np.stack([events[k] for k in chunk_paths])
    blocks = []
    for start in range(0, padded_total, block_rays):
        part = slice(start, start + block_rays)
        light = jnp.asarray(arrays["light"][part])
        origins, directions, light_points, wavelength, entrance = VERTEX_RAYS(
            setup.lights, setup.front, setup.spectral, setup.lens, effects.hood, setup.schlick, light, jnp.asarray(arrays["unit"][part], f32), jnp.asarray(arrays["node"][part], f32),
            jnp.asarray(arrays["light_unit"][part], f32), jnp.asarray(arrays["wavelength"][part], f32),
        )
        visible = jnp.ones(origins.shape[0], bool)
        if effects.occluders is not None:
            to_world = effects.camera_to_world
            start_m = effects.camera_position_m + (origins / 1000.0) @ to_world.T
            light_end = effects.camera_position_m + (light_points / 1000.0) @ to_world.T
            far_end = start_m - 1e6 * directions @ to_world.T
            directional = setup.lights.kind[light] == LightKind.DIRECTIONAL
            visible = segment_visibility(effects.occluders, start_m, jnp.where(directional[:, None], far_end, light_end))
        chunk0 = start // TRACE_CHUNK
        table = EventTable.from_array(event_rows[chunk0 : chunk0 + TRACE_BLOCK])
        blocks.append(TRACE_GRID(lens, origins, directions, wavelength, visible, entrance, table))
    rows = blocks[0] if len(blocks) == 1 else jnp.concatenate(blocks)
    return rows, np.asarray(rows, np.float64)


MIN_RECORDS, MIN_JOBS, MIN_CHUNKS = 2**14, 16, 16
"""Smallest table sizes: small renders (tests, thumbnails) share one compiled splat kernel."""


def _bucket(count: int) -> int:
    """``count`` rounded up to 1, 1.5 or 2 times a power of two."""
    if count <= 2:
        return max(count, 1)
    power = 2 ** math.floor(math.log2(count))
    for factor in (1, 1.5, 2):
        if count <= factor * power:
            return int(factor * power)
    return 2 * power


# --------------------------------------------------------------------------- cells and records


def _bracket(wavelength: float, x_nodes: np.ndarray) -> tuple[int, int, float]:
    """The two traced wavelengths around ``wavelength`` and the second one's weight (linear in 1 / lambda^2)."""
    traced = len(x_nodes)
    if traced == 1:
        return 0, 0, 0.0
    x = wavelength**-2.0
    k0 = int(np.clip(np.searchsorted(-x_nodes, -x) - 1, 0, traced - 2))
    return k0, k0 + 1, float(np.clip((x_nodes[k0] - x) / (x_nodes[k0] - x_nodes[k0 + 1]), 0.0, 1.0))


def job_records(jobs: list[GridJob], pieces: list[dict], traced_nodes: np.ndarray, band: tuple[float, float], refined=()) -> dict:
    """Host arrays of every record (a piece at one wavelength sub-node), in sub-sample order.
    ``refined``: the :class:`._grid_refine.RefinedCell` sub-grids of cells of ``jobs`` traced
    again, each with its pieces: their records belong to the cell's job, with the piece and the
    corners' frame in the cell's units."""
    x_nodes = traced_nodes**-2.0
    traced = len(traced_nodes)
    out = {k: [] for k in ("job", "sub_node", "sub_nodes", "piece", "side", "mixed", "corners", "bracket", "step", "count", "frame")}
    low, high = band
    owners = [(index, job, piece, None) for index, (job, piece) in enumerate(zip(jobs, pieces))]
    owners += [(cell.job_index, cell.view, cell.pieces, cell) for cell in refined]
    for index, job, piece, cell in owners:
        if not piece:
            continue
        n = job.cells
        variants = [0, 1, 2] if job.variants == 3 else [0, 0, 0]
        for m_count in np.unique(piece["sub_nodes"]):
            chosen = piece["sub_nodes"] == m_count
            i, j = piece["cell"][chosen, 0], piece["cell"][chosen, 1]
            vertex = j * (n + 1) + i
            corner_vertex = np.stack([vertex, vertex + 1, vertex + n + 1, vertex + n + 2], axis=-1)
            count = len(i)
            for m in range(int(m_count)):
                wavelength = low + (m + 0.5) * (high - low) / m_count
                k0, k1, w = _bracket(wavelength, x_nodes)
                rows = np.stack(
                    [np.stack([job.row0 + (f * traced + k) * job.vertices + corner_vertex for k in (k0, k1)], axis=1) for f in variants], axis=1
                )  # (C, 3, 2, 4)
                out["job"].append(np.full(count, index))
                out["sub_node"].append(np.full(count, m))
                out["sub_nodes"].append(np.full(count, m_count))
                own = np.stack([piece["a0"][chosen], piece["b0"][chosen], piece["size"][chosen]], axis=-1)
                if cell is None:  # the piece of the job's own cell, its corners the cell's
                    out["piece"].append(own)
                    out["frame"].append(np.tile([0.0, 0.0, 1.0], (count, 1)))
                else:  # a piece of a sub-cell (i, j) of a refined cell: both in the cell's units
                    sub = 1.0 / cell.view.cells
                    out["piece"].append(np.stack([(i + own[:, 0]) * sub, (j + own[:, 1]) * sub, own[:, 2] * sub], axis=-1))
                    out["frame"].append(np.stack([i * sub, j * sub, np.full(count, sub)], axis=-1))
                out["side"].append(piece["side"][chosen])
                out["mixed"].append(piece["mixed"][chosen])
                out["corners"].append(rows)
                out["bracket"].append(np.full(count, w))
                out["step"].append(np.full(count, job.step))
                out["count"].append(piece["side"][chosen] ** 2)
    if not out["job"]:
        return {}
    return {k: np.concatenate(v) for k, v in out.items()}


def record_table(rows: jax.Array, records: dict) -> tuple[RecordTable, int, np.ndarray]:
    """The device record table (records and their tiles of :data:`TILE` sub-samples, each padded to
    a bucketed size, the tiles by a chunk for the kernel's windows), the number of sub-samples and
    the tile each chunk starts at."""
    count = records["count"]
    total = int(count.sum())
    size = _bucket(max(len(count), MIN_RECORDS))
    pad = size - len(count)

    def padded(a, value=0):
        return np.concatenate([a, np.full((pad,) + a.shape[1:], value, a.dtype)]) if pad else a

    end = np.cumsum(count)
    tiles_per_record = -(-count // TILE)
    tiles = int(tiles_per_record.sum())
    tile_record = np.repeat(np.arange(len(count)), tiles_per_record)
    tile_local = (np.arange(tiles) - np.repeat(np.cumsum(tiles_per_record) - tiles_per_record, tiles_per_record)) * TILE
    tile_size = _bucket(max(tiles, MIN_RECORDS)) + TILES_PER_CHUNK
    tile_record = np.concatenate([tile_record, np.zeros(tile_size - tiles, tile_record.dtype)])
    tile_local = np.concatenate([tile_local, np.full(tile_size - tiles, np.iinfo(np.int32).max - TILE)])  # past every record's end
    end = padded(end, total)
    values = RECORD_VALUES(rows, jnp.asarray(padded(records["corners"])), jnp.asarray(padded(records["bracket"]), jnp.float32), jnp.asarray(padded(records["step"]), jnp.float32))
    table = RecordTable(
        values=values,
        job=jnp.asarray(padded(records["job"]), jnp.int32),
        sub_node=jnp.asarray(padded(records["sub_node"]), jnp.int32),
        sub_nodes=jnp.asarray(padded(records["sub_nodes"], 1), jnp.int32),
        piece=jnp.asarray(padded(records["piece"]), jnp.float32),
        frame=jnp.asarray(padded(records["frame"], 1.0), jnp.float32),
        side=jnp.asarray(padded(records["side"], 1), jnp.int32),
        mixed=jnp.asarray(padded(records["mixed"], False)),
        end=jnp.asarray(end, jnp.int32),
        tile_record=jnp.asarray(tile_record, jnp.int32),
        tile_local=jnp.asarray(tile_local, jnp.int32),
    )
    first = np.arange(chunk_count(tiles)) * TILES_PER_CHUNK
    return table, total, first


def band_averaging(band: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """The :data:`BAND_POINTS` wavelengths (nm) spanning ``band`` and the (COLOUR_ROW, BAND_POINTS)
    matrix averaging them over each sub-node's stratum, for every sub-node choice."""
    low, high = band
    fine = low + (np.arange(BAND_POINTS) + 0.5) * (high - low) / BAND_POINTS
    averaging = np.zeros((COLOUR_ROW, BAND_POINTS))
    for choice in SUB_NODE_CHOICES:
        per = BAND_POINTS // choice
        for m in range(choice):
            averaging[SUB_NODE_OFFSETS[choice] + m, m * per : (m + 1) * per] = 1.0 / per
    return fine, averaging


def job_table(setup, jobs: list[GridJob], path_fresnel: jax.Array, band: tuple[float, float]) -> JobTable:
    """The device job table: each job's sub-node colours are the light's RGB x the path's on-axis
    coated Fresnel factor (Schlick model; the exact model's throughput is per vertex) averaged over
    the sub-node's stratum of :data:`BAND_POINTS` wavelengths, for every sub-node choice."""
    size = _bucket(max(len(jobs), MIN_JOBS))
    jobs_padded = jobs + [jobs[0]] * (size - len(jobs))
    fine, averaging = band_averaging(band)
    light = np.asarray([job.light for job in jobs_padded], np.int32)
    path = np.asarray([job.path for job in jobs_padded], np.int32)
    colour = _job_colours(setup, path_fresnel, jnp.asarray(light), jnp.asarray(path), jnp.asarray(fine, jnp.float32), jnp.asarray(averaging, jnp.float32))
    f32 = jnp.float32
    return JobTable(
        path=jnp.asarray(path),
        slot=jnp.asarray([job.slot for job in jobs_padded], jnp.int32),
        light=jnp.asarray(light),
        layer=jnp.asarray([job.layer for job in jobs_padded], jnp.int32),
        level=jnp.asarray([job.level for job in jobs_padded], jnp.int32),
        passes=jnp.asarray([job.passes for job in jobs_padded], jnp.int32),
        domain=jnp.asarray([job.domain for job in jobs_padded], f32),
        node=jnp.asarray([job.node for job in jobs_padded], f32),
        stratum=jnp.asarray([job.stratum for job in jobs_padded], f32),
        step=jnp.asarray([job.step for job in jobs_padded], f32),
        weight=jnp.asarray([job.weight for job in jobs_padded], f32),
        interleave=jnp.asarray([int(job.interleave) for job in jobs_padded], jnp.int32),
        colour=colour,
        blur=blur_slots(jobs_padded, [job.blur_jacobian for job in jobs] + [None] * (size - len(jobs)), *setup.resolution, LEVELS, level_layout),
    )


def job_colours(setup, path_fresnel, light, path, fine, averaging):
    """Each job's sub-node colours (J, COLOUR_ROW, 3): its light's RGB at the ``fine`` band
    wavelengths, times its path's Fresnel factor ``path_fresnel`` (P, L on the spectral grid,
    linearly interpolated) under the Schlick model, averaged by ``averaging``. Differentiable in
    ``path_fresnel`` and the lights (a fit of thin-film coatings goes through it)."""
    count, points = light.shape[0], fine.shape[0]
    lights = jnp.repeat(light, points)
    wavelengths = jnp.tile(fine, count)
    rgb = light_rgb(setup.lights, setup.spectral, lights, wavelengths).reshape(count, points, 3)
    if setup.schlick:
        grid = setup.spectral.wavelength_nm
        position = jnp.clip((fine - grid[0]) / (grid[1] - grid[0]), 0, grid.shape[0] - 1)
        below = jnp.clip(jnp.floor(position).astype(jnp.int32), 0, grid.shape[0] - 2)
        t = position - below
        fresnel = path_fresnel[path][:, below] * (1 - t) + path_fresnel[path][:, below + 1] * t  # (J, points)
        rgb = rgb * fresnel[:, :, None]
    return jnp.einsum("mp,jpc->jmc", averaging, rgb)


_job_colours = eqx.filter_jit(job_colours)


SPLAT_GROUP_SUBSAMPLES = 2**30
"""Most sub-samples in one splat (their indices are 32-bit integers on the device; a fine
reference of a two-light 720p scene asked for 4.3 G)."""


@dataclasses.dataclass
class PreparedSplat:
    """Everything the splat kernel reads, built on the host from traced vertices: the device
    record and job tables, the sub-sample count and the chunk starts; ``slot_samples`` counts the
    sub-samples of every statistics slot (host)."""

    table: RecordTable
    jobs: JobTable
    total: int
    """Sub-samples of every group (this one and ``more``)."""
    first: np.ndarray
    chunks: int
    records: int
    slot_samples: np.ndarray
    more: tuple = ()
    """Further groups of records (table, sub-samples, chunk starts, chunks), splatted after this
    one: a render of more than :data:`SPLAT_GROUP_SUBSAMPLES` sub-samples is split so that every
    sub-sample index fits the kernel's 32-bit integers."""


def prepare_splat(setup, jobs: list[GridJob], rows: jax.Array, pieces, traced_nodes, path_fresnel, band, num_slots: int, refined=()) -> PreparedSplat | None:
    """The records of ``jobs`` (``pieces``: :func:`cell_pieces` of each; ``refined``: their cells
    traced again, see :func:`job_records`) as device tables (None when no cell of any job may
    carry light)."""
    records = job_records(jobs, pieces, traced_nodes, band, refined)
    if not records:
        return None
    end = np.cumsum(records["count"])
    bounds = np.searchsorted(end, np.arange(1, -(-int(end[-1]) // SPLAT_GROUP_SUBSAMPLES)) * SPLAT_GROUP_SUBSAMPLES, side="right")
    groups = []
    for start, stop in zip(np.concatenate([[0], bounds]), np.concatenate([bounds, [len(end)]])):
        table, total, first = record_table(rows, {key: value[start:stop] for key, value in records.items()})
        chunks = len(first)
        groups.append((table, total, np.concatenate([first, np.zeros(_bucket(max(chunks, MIN_CHUNKS)) - chunks, first.dtype)]), chunks))
    job_arrays = job_table(setup, jobs, path_fresnel, band)
    slots = np.asarray([job.slot for job in jobs])[records["job"]]
    slot_samples = np.bincount(slots, weights=records["count"], minlength=num_slots)
    table, _, first, chunks = groups[0]
    return PreparedSplat(
        table=table, jobs=job_arrays, total=int(end[-1]), first=first, chunks=chunks, records=len(records["count"]), slot_samples=slot_samples,
        more=tuple(groups[1:]),
    )


def splat_prepared(setup, prepared: PreparedSplat | None, num_layers: int, num_slots: int):
    """The accumulated packed images and per-slot statistics of prepared records. Differentiable
    in what ``setup`` holds (tints, dirt, light gains): the record tables are fixed."""
    width, height = setup.resolution
    blur = None if prepared is None else prepared.jobs.blur
    acc = empty_grid_accumulators(num_layers, num_slots, width, height, 1 if blur is None else blur.size)
    if prepared is None:
        return acc
    first_total = prepared.total - sum(group[1] for group in prepared.more)
    for table, total, first, chunks in ((prepared.table, first_total, prepared.first, prepared.chunks),) + prepared.more:
        acc = SPLAT_SUBSAMPLES(setup, prepared.jobs, table, acc, jnp.asarray(total, jnp.int32), jnp.asarray(first, jnp.int32), jnp.asarray(chunks, jnp.int32))
    return acc


def splat_jobs(setup, jobs: list[GridJob], rows: jax.Array, pieces, traced_nodes, path_fresnel, band, num_layers: int, num_slots: int):
    """Records and sub-samples of ``jobs`` (``pieces``: :func:`cell_pieces` of each): the
    accumulated packed images and per-slot statistics, the sub-sample and record counts."""
    prepared = prepare_splat(setup, jobs, rows, pieces, traced_nodes, path_fresnel, band, num_slots)
    acc = splat_prepared(setup, prepared, num_layers, num_slots)
    if prepared is None:
        return acc, 0, 0
    return acc, prepared.total, prepared.records
