"""Mixed cells traced again on a finer grid (host side of :mod:`._grid`).

A *mixed* cell (:mod:`._grid_cells`) has corners that disagree about validity: some of its rays
miss a surface or reflect totally. Nothing can be interpolated across it, so it is drawn as four
sub-samples, each carrying a quarter of its flux at one corner's image. Where the region of the
entrance plane that reaches the sensor is small against the grid (a ghost near the edge of the
field of a wide angle, whose rays are lost on every side), most of a ghost's cells are mixed and it
turns into a lattice of dots, each drawn as a dash across its colour spread (measured: a
retrofocus wide angle with a point light 29 degrees off axis, 413 of 8811 cells mixed, a
third of the flare's energy in them, coloured dashes all over the frame).

Each mixed cell is traced again as a sub-grid of :data:`MIXED_SUBCELLS` x :data:`MIXED_SUBCELLS`
cells (a :class:`~._grid.GridJob` over the cell's domain, its rows appended to the render's). Its
sub-cells are then drawn like any cell, as pieces of the parent cell whose corners are the
sub-cell's (``frame`` in the record table): the full ones interpolated, the ones still mixed as
four sub-samples of a 64th of the flux each.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ._grid import GridJob, trace_jobs
from ._grid_cells import CellSummary, summarise_cells

MIXED_SUBCELLS = 8
"""Sub-cells per side of a mixed cell traced again."""


def refined_edge_side(edge_side: int) -> int:
    """The fewest sub-samples per side of a sub-cell's edge piece: a cell's ``edge_side`` shared
    among its sub-cells, so that a clipping edge is resolved on the entrance plane as finely as in
    any other cell (each sub-cell's own ``edge_side``: 64 times the sub-samples, +20 % in all on
    the demo's fine reference)."""
    return max(1, math.ceil(edge_side / MIXED_SUBCELLS))


@dataclasses.dataclass
class RefinedCell:
    """A mixed cell of a job, traced again as a sub-grid."""

    job_index: int
    """The job the cell belongs to (its records are that job's)."""
    view: GridJob
    """The sub-grid: the job over the cell's domain, ``MIXED_SUBCELLS`` cells per side."""
    summary: CellSummary | None = None
    pieces: dict | None = None


def refine_mixed_cells(setup, lens, jobs: list[GridJob], summaries: list[CellSummary], events, wavelengths: np.ndarray, pitch_mm: float, distortion: bool):
    """Trace every kept mixed cell of ``jobs`` again on a sub-grid. Returns the summaries without
    those cells (they are drawn through their sub-grids), the :class:`RefinedCell` list (in job
    order, summarised) and the sub-grids' rows on the device and on the host (None, None: no
    mixed cell); the views' ``row0`` count from the start of those rows."""
    width, height = setup.resolution
    refined: list[RefinedCell] = []
    kept_summaries = list(summaries)
    for index, (job, summary) in enumerate(zip(jobs, summaries)):
        mixed = summary.kept & summary.mixed
        if not mixed.any():
            continue
        u0, v0, du, dv = job.domain
        for j, i in np.argwhere(mixed):
            domain = (u0 + i * du, v0 + j * dv, du / MIXED_SUBCELLS, dv / MIXED_SUBCELLS)
            view = dataclasses.replace(job, domain=domain, cells=MIXED_SUBCELLS, blur_jacobian=None, row0=0)
            refined.append(RefinedCell(job_index=index, view=view))
        kept_summaries[index] = dataclasses.replace(summary, kept=summary.kept & ~mixed)
    if not refined:
        return kept_summaries, refined, None, None
    rows, host_rows = trace_jobs(setup, lens, [cell.view for cell in refined], events, wavelengths, packed=True)
    for cell in refined:
        cell.summary = summarise_cells(cell.view, host_rows, len(wavelengths), lens, pitch_mm, width, height, distortion)
    return kept_summaries, refined, rows, host_rows
