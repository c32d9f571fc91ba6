"""Which grid cells carry light, and how finely each is drawn (host side of :mod:`._grid`).

From a job's traced vertices (:mod:`._grid_trace` rows) the host decides, per cell:

- *excluded*: the bilinear interpolant of a cell (what the sub-samples use) is a convex
  combination of its corners, so if every corner, at every traced wavelength and allowing for the
  light's disc, lies beyond one edge of the iris polygon, outside a clear aperture (negative
  margin) or beyond one side of the image, no point of the cell can get through: it is skipped;
- *interior*: every corner inside every aperture, with the same allowance: no clipping edge can
  cross the cell, so its colours need not be resolved (drawn once, with the whole band's colour,
  when its irradiance is smooth over its colour spread);
- otherwise an *edge* cell: it is split in four (its pieces' corners interpolated from the cell's
  corners exactly as the sub-samples are), recursively, down to pieces as small as their colour
  spread; the pieces an edge still crosses are drawn at ``M`` wavelength sub-nodes, ``M`` from the
  piece's colour spread.

A cell whose corners disagree about validity (some were lost by the wide-open trace: a miss or
total internal reflection) is *mixed*: it is traced again as a finer sub-grid (:mod:`._grid_refine`),
and a sub-cell still mixed is drawn by four sub-samples, each taking one corner's traced values and
a quarter of the sub-cell's flux.

Every piece gets ``side x side`` sub-samples, ``side`` = its image's diagonal over the sub-sample
spacing (in pixels of its path's image level).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ._grid_splat import LEVELS, SUB_NODE_CHOICES
from ._grid_trace import MARGIN, NUM_QUANTITIES, SENSOR, STOP, VALID

MAX_DEPTH = 5
"""Most times an edge cell is split (pieces of 1/32 of a cell side)."""
MIN_PIECE_PX = 3.0
"""Edge pieces are split until their image's diagonal is below this (level pixels) or their colour spread."""
MAX_SPACING_STRETCH = 2.0
"""A piece drawn at M wavelength sub-nodes has its sub-node lattices interleaved (each shifted by
its own Kronecker point): each lattice may be up to this much (and sqrt(M)) sparser than the
sub-sample spacing, their union being as dense."""


def round_sub_nodes(count: float, limit: int) -> int:
    """The smallest sub-node choice of at least ``count`` (at most ``limit``)."""
    for choice in SUB_NODE_CHOICES:
        if choice >= count and choice <= limit:
            return choice
    return max(c for c in SUB_NODE_CHOICES if c <= limit)


def iris_half_planes(lens) -> tuple[np.ndarray, float]:
    """Outward normals (B, 2) and apothem of the iris polygon (a circle: a circumscribed 16-gon,
    conservative for exclusion)."""
    blades = lens.aperture_blades
    radius = float(lens.stop_radius_mm)
    if blades == 0:
        angles = np.arange(16) * 2 * np.pi / 16
        return np.stack([np.cos(angles), np.sin(angles)], axis=-1), radius
    angles = float(lens.aperture_rotation_rad) + (np.arange(blades) + 0.5) * 2 * np.pi / blades
    return np.stack([np.cos(angles), np.sin(angles)], axis=-1), radius * math.cos(math.pi / blades)


def passes_iris(x: np.ndarray, y: np.ndarray, lens) -> np.ndarray:
    """The iris test of :func:`jaxflare.optics.inside_iris` on host arrays (stop-plane mm): NumPy,
    since the host summarises grids of a new shape for every job (the JAX test dispatched and
    compiled per shape: 4.8 s of a fresh process's demo render)."""
    if lens.aperture_blades == 0:
        radius = float(lens.stop_radius_mm)
        return x * x + y * y <= radius * radius
    normals, apothem = iris_half_planes(lens)
    return np.all(x[..., None] * normals[:, 0] + y[..., None] * normals[:, 1] <= apothem, axis=-1)


@dataclasses.dataclass
class CellSummary:
    """What the host learnt about a job's vertices and cells."""

    kept: np.ndarray
    """(n, n) bool: cells that may carry light."""
    mixed: np.ndarray
    full: np.ndarray
    passing: np.ndarray
    """(K, n+1, n+1) bool: vertices inside every aperture (at the light's node)."""
    sensor_px: np.ndarray
    """(F, K, n+1, n+1, 2) image position in full-resolution pixels (undistorted)."""
    motion_px: float
    """How far the light's disc moves the image (px, largest over passing vertices)."""
    features: np.ndarray
    """(K, n+1, n+1, 12) per vertex: image x, y (px), stop x, y of three passes, margin, then the
    allowances for the light's disc: margin, stop (three passes), image (px)."""
    change: np.ndarray
    """(n, n): largest |change of log image area| to a neighbouring cell (irradiance smoothness)."""
    image_area_px: np.ndarray
    """(n, n): area of each cell's image at the middle traced wavelength (px^2, the quadrilateral of
    its corners)."""


def stratum_reach(job) -> float:
    """The farthest point of the job's light stratum from its node (unit-disc units)."""
    inner, outer, angle0, span = job.stratum
    if job.step <= 0:
        return 0.0
    points = [(r * math.cos(a), r * math.sin(a)) for r in (inner, outer) for a in np.linspace(angle0, angle0 + span, 9)]
    return max(math.hypot(x - job.node[0], y - job.node[1]) for x, y in points)


def summarise_cells(job, rows: np.ndarray, traced: int, lens, pitch_mm: float, width: int, height: int, distortion: bool) -> CellSummary:
    n = job.cells
    variants = job.variants
    block = rows[job.row0 : job.row0 + variants * traced * job.vertices].reshape(variants, traced, n + 1, n + 1, NUM_QUANTITIES)
    base = block[0]
    valid = base[..., VALID] > 0.5
    sensor_px = np.stack([-block[..., SENSOR] / pitch_mm + 0.5 * width, block[..., SENSOR + 1] / pitch_mm + 0.5 * height], axis=-1)

    reach = stratum_reach(job)
    if variants == 3:
        both = valid & (block[1][..., VALID] > 0.5) & (block[2][..., VALID] > 0.5)
        slack = sum(np.where(both[..., None], np.abs(block[f][..., : MARGIN + 1] - base[..., : MARGIN + 1]), 0.0) for f in (1, 2)) / job.step * reach
    else:
        slack = np.zeros(base.shape[:-1] + (MARGIN + 1,))
    motion_px = np.hypot(slack[..., SENSOR], slack[..., SENSOR + 1]) / pitch_mm
    stop_slack = np.stack([np.hypot(slack[..., STOP + 2 * p], slack[..., STOP + 2 * p + 1]) for p in range(3)], axis=-1)
    features = np.concatenate(
        [sensor_px[0], base[..., STOP : STOP + 6], base[..., MARGIN : MARGIN + 1], slack[..., MARGIN : MARGIN + 1], stop_slack, motion_px[..., None]],
        axis=-1,
    )

    cv = _corners(valid)
    full = cv.all(axis=(0, 1))
    anyv = cv.any(axis=(0, 1))
    mixed = anyv & ~full
    cell_corners = np.moveaxis(_corners(features), (0, 1), (2, 3)).reshape(-1, 4, traced, features.shape[-1])  # (n * n, 4, K, 14)
    excluded, _ = classify(cell_corners, cv.transpose(2, 3, 0, 1).reshape(-1, 4, traced), job, lens, width, height, distortion)
    kept = anyv & ~excluded.reshape(n, n)

    passing = valid & (base[..., MARGIN] > 0)
    for p in range(job.passes):
        x, y = base[..., STOP + 2 * p], base[..., STOP + 2 * p + 1]
        passing &= passes_iris(x, y, lens)
    moving = float(motion_px[passing].max()) if passing.any() else 0.0

    middle = sensor_px[0, traced // 2]
    area = 0.5 * np.abs(_cross(middle[1:, 1:] - middle[:-1, :-1], middle[:-1, 1:] - middle[1:, :-1]))
    log_area = np.log(np.maximum(area, 1e-12))
    change = np.zeros_like(log_area)
    step_u, step_v = np.abs(np.diff(log_area, axis=1)), np.abs(np.diff(log_area, axis=0))
    change[:, 1:] = np.maximum(change[:, 1:], step_u)
    change[:, :-1] = np.maximum(change[:, :-1], step_u)
    change[1:] = np.maximum(change[1:], step_v)
    change[:-1] = np.maximum(change[:-1], step_v)
    return CellSummary(
        kept=kept, mixed=mixed, full=full, passing=passing, sensor_px=sensor_px, motion_px=moving, features=features, change=change, image_area_px=area,
    )


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z component of the cross product of 2-vectors (..., 2)."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _corners(a: np.ndarray) -> np.ndarray:
    """(K, n+1, n+1, ...) -> (4, K, n, n, ...): corners (0,0), (1,0), (0,1), (1,1) of every cell."""
    return np.stack([a[:, :-1, :-1], a[:, :-1, 1:], a[:, 1:, :-1], a[:, 1:, 1:]])


def classify(corners: np.ndarray, valid: np.ndarray, job, lens, width: int, height: int, distortion: bool):
    """Pieces (N, 4 corners, K, 12 features): (excluded, inside) per piece. A corner that was not
    traced through (``valid`` False) takes no part in the tests."""
    image, stop, margin = corners[..., 0:2], corners[..., 2:8], corners[..., 8]
    margin_slack, stop_slack, image_slack = corners[..., 9], corners[..., 10:13], corners[..., 13]
    any_valid = valid.any(axis=(1, 2))
    valid_b = valid[..., None]

    def beyond_all(outside):  # (N, 4, K, B) -> (N,): for some b, every valid corner beyond line b
        return (np.where(valid_b, outside, True).all(axis=(1, 2)) & any_valid[:, None]).any(axis=-1)

    excluded = beyond_all((margin + margin_slack < 0)[..., None])
    inside = np.where(valid, margin - margin_slack > 0, True).all(axis=(1, 2))
    normals, apothem = iris_half_planes(lens)
    radius = float(lens.stop_radius_mm)
    for p in range(job.passes):
        x, y, slack = stop[..., 2 * p, None], stop[..., 2 * p + 1, None], stop_slack[..., p, None]
        along = x * normals[:, 0] + y * normals[:, 1]  # (N, 4, K, B): along each blade's outward normal
        excluded |= beyond_all(along - apothem - slack > 0)
        if lens.aperture_blades == 0:
            inside &= np.where(valid, np.hypot(x[..., 0], y[..., 0]) + slack[..., 0] < radius, True).all(axis=(1, 2))
        else:
            inside &= np.where(valid_b, along + slack < apothem, True).all(axis=(1, 2, 3))
    pad = (2.0 + job.blur_border) * LEVELS[job.level] + (0.1 * max(width, height) if distortion else 0.0)
    column, row = image[..., 0], image[..., 1]
    excluded |= beyond_all(
        np.stack([column + image_slack < -pad, column - image_slack > width + pad, row + image_slack < -pad, row - image_slack > height + pad], axis=-1)
    )
    return excluded, inside & ~excluded


def _interpolate(corners: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of cell corners (N, 4, ...) at points (a, b) in the cell, (N,) each."""
    shape = (-1,) + (1,) * (corners.ndim - 2)
    a, b = a.reshape(shape), b.reshape(shape)
    return corners[:, 0] * (1 - a) * (1 - b) + corners[:, 1] * a * (1 - b) + corners[:, 2] * (1 - a) * b + corners[:, 3] * a * b


def cell_pieces(
    job, summary: CellSummary, lens, width: int, height: int, distortion: bool, fringe_px: float, max_sub_nodes: int, colour_error: float,
    edge_side: int = 1,
) -> dict:
    """The pieces a job's cells are drawn as: cell (column i, row j), piece corner (a0, b0) and
    size in the cell, wavelength sub-nodes, sub-samples per side, mixed flag.

    Sub-nodes: an edge piece gets enough for its colour fringe to be drawn in steps of
    ``fringe_px`` (level pixels; or of half the light disc's blur, when larger); an interior
    piece as many, and more if a stratum's colour shift (its colour spread / 3 M) x its
    irradiance's relative gradient would exceed ``colour_error`` (the first-order error of a
    channel's image drawn at its stratum's centre). Not fewer: where a piece drawn at fewer
    sub-nodes meets one drawn at more, each colour's two images are shifted by up to the colour
    spread, so a band that wide is doubled or left empty for that colour (measured: seams of 6 %
    along the cells of a wide ghost of the demo, whose colours spread over 73 px, when interior
    pieces were drawn with one sub-node).

    An edge piece (one a clipping edge may cross) gets at least ``edge_side`` sub-samples per side
    whatever the size of its image: where the map compresses (a focused ghost), a piece's image is
    a pixel or less, but the iris and the rims still cut it on the entrance plane, and one
    sub-sample would count it all in or all out (measured: 4 % too much energy in a focused
    ghost, and a 5 % asymmetric on-axis image, with one)."""
    level = LEVELS[job.level]
    traced = summary.features.shape[0]
    out = {k: [] for k in ("cell", "a0", "b0", "size", "sub_nodes", "side", "mixed")}

    def emit(cells, a0, b0, size, sub_nodes, side, mixed):
        out["cell"].append(cells)
        out["a0"].append(a0)
        out["b0"].append(b0)
        out["size"].append(size)
        out["sub_nodes"].append(sub_nodes)
        out["side"].append(side)
        out["mixed"].append(mixed)

    features = _corners(summary.features)  # (4, K, n, n, 12)
    cell_corners = np.moveaxis(features, (0, 1), (2, 3))  # (n, n, 4, K, 12)
    mixed_cells = np.argwhere(summary.kept & summary.mixed)
    if len(mixed_cells):
        j, i = mixed_cells[:, 0], mixed_cells[:, 1]
        corners = cell_corners[j, i]
        spread = np.linalg.norm(corners[:, :, -1, 0:2] - corners[:, :, 0, 0:2], axis=-1).max(axis=1) / level
        step = np.maximum(fringe_px, 0.5 * corners[:, :, :, 13].max(axis=(1, 2)) / level)
        m = np.asarray([round_sub_nodes(s, max_sub_nodes) for s in spread / step])
        count = len(j)
        emit(np.stack([i, j], -1), np.zeros(count), np.zeros(count), np.ones(count), m, np.full(count, 2), np.ones(count, bool))

    cells = np.argwhere(summary.kept & summary.full)
    j, i = cells[:, 0], cells[:, 1]
    corners = cell_corners[j, i]  # (N, 4, K, 12)
    change = summary.change[j, i]
    a0, b0, size = np.zeros(len(j)), np.zeros(len(j)), np.ones(len(j))
    for depth in range(MAX_DEPTH + 1):
        if len(j) == 0:
            break
        piece = np.stack([_interpolate(corners, a0 + da * size, b0 + db * size) for da, db in ((0, 0), (1, 0), (0, 1), (1, 1))], axis=1)
        excluded, inside = classify(piece, np.ones(piece.shape[:3], bool), job, lens, width, height, distortion)
        image = piece[..., 0:2]  # (N, 4, K, 2) px
        diagonal = np.maximum(np.linalg.norm(image[:, 3] - image[:, 0], axis=-1), np.linalg.norm(image[:, 2] - image[:, 1], axis=-1)).max(axis=1) / level
        spread = np.linalg.norm(image[:, :, -1] - image[:, :, 0], axis=-1).max(axis=1) / level
        area = 0.5 * np.abs(_cross(image[:, 3, traced // 2] - image[:, 0, traced // 2], image[:, 1, traced // 2] - image[:, 2, traced // 2])) / level**2
        piece_size = np.sqrt(np.maximum(area, 1e-12))
        blur = piece[:, :, :, 13].max(axis=(1, 2)) / level  # the light disc's blur (level px)
        done = ~excluded & (inside | (depth == MAX_DEPTH) | (diagonal <= MIN_PIECE_PX) | (diagonal <= spread))
        if done.any():
            edge_nodes = spread / np.maximum(fringe_px, 0.5 * blur)
            interior_nodes = spread * change / (3.0 * np.maximum(piece_size, 1e-9) * colour_error)
            wanted = np.where(inside, np.maximum(interior_nodes, edge_nodes), edge_nodes)[done]
            m = np.asarray([round_sub_nodes(w, max_sub_nodes) for w in wanted], np.int64)
            stretch = np.minimum(np.sqrt(m), MAX_SPACING_STRETCH) if job.interleave else np.ones(len(m))
            side = np.clip(np.ceil(diagonal[done] / (job.spacing_px * stretch)), 1, job.max_side).astype(np.int64)
            side = np.where(inside[done], side, np.maximum(side, edge_side))
            emit(np.stack([i[done], j[done]], -1), a0[done], b0[done], size[done], m, side, np.zeros(int(done.sum()), bool))
        split = ~excluded & ~done
        j, i, corners, change = (np.repeat(x[split], 4, axis=0) for x in (j, i, corners, change))
        half = size[split] / 2
        a0 = np.repeat(a0[split], 4) + np.tile([0, 1, 0, 1], int(split.sum())) * np.repeat(half, 4)
        b0 = np.repeat(b0[split], 4) + np.tile([0, 0, 1, 1], int(split.sum())) * np.repeat(half, 4)
        size = np.repeat(half, 4)
    if not out["cell"]:
        return {}
    pieces = {k: np.concatenate(v) for k, v in out.items()}
    if job.min_subsamples:  # a light's disc blurs the image beyond its cells' extent (the core)
        have = int((pieces["side"] ** 2 * pieces["sub_nodes"]).sum())
        if 0 < have < job.min_subsamples:
            pieces["side"] = np.ceil(pieces["side"] * math.sqrt(job.min_subsamples / have)).astype(np.int64)
    return pieces
