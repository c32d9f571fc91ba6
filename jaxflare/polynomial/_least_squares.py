"""Building a path system's polynomial: the samples it is fitted to (exact float64 traces of the
lens with its clear apertures widened a little, where rays get through), its clipping events, and
weighted least squares; the constructions themselves are in :mod:`._constructions`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ..optics import Lens, TraceResult, path_events, stop_pass_count, trace
from ._basis import monomials
from ._domain import TRUST_GRID, PathDomain, rays_from_variables, sample_variables
from ._system import AUXILIARY_DEGREE, PathSystem, precise_columns

_APERTURE_MARGIN = 1.03
"""Clear apertures are widened by this factor for the fit samples, so each polynomial is also
accurate slightly beyond the rims it is tested against (capped where a surface ends)."""


def widened_lens(lens: Lens) -> Lens:
    """The lens with every clear aperture widened by ``_APERTURE_MARGIN`` (not past the point where
    a surface ends) and a circular iris at the widened stop: fit samples beyond the rims.
    Pure ``jax.numpy``, so :func:`refit` stays differentiable."""
    c = jnp.abs(lens.curvature_per_mm)
    k1 = 1.0 + lens.conic
    semi = lens.semi_aperture_mm
    curved = (c > 0) & (k1 > 0)
    limit = jnp.where(curved, 0.999 / jnp.where(curved, c * jnp.sqrt(jnp.where(curved, k1, 1.0)), 1.0), jnp.inf)
    widened = jnp.minimum(semi * _APERTURE_MARGIN, jnp.maximum(limit, semi))
    lens = eqx.tree_at(lambda l: (l.semi_aperture_mm, l.stop_radius_mm), lens, (widened, widened[lens.stop_index]))
    return lens.with_aperture(blades=0) if lens.aperture_blades else lens


def trace_samples(lens: Lens, path, domain: PathDomain, variables: np.ndarray, record_events: bool = False) -> TraceResult:
    """Exact traces of the rays of domain samples ``variables``."""
    return trace(lens, *rays_from_variables(domain, variables), path, record_events=record_events)


def _choose_clip_events(lens: Lens, events: np.ndarray, wide: TraceResult, max_clip_events: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Greedy choice of the event rows (not the stop) of the path's ``events`` whose real clear
    aperture clips the most widened-lens rays not already clipped by the iris or a chosen event."""
    semi = np.asarray(lens.semi_aperture_mm, np.float64)
    positions = np.asarray(wide.event_positions)  # (E, N, 3)
    valid = np.asarray(wide.valid)
    radius2 = positions[..., 0] ** 2 + positions[..., 1] ** 2
    candidates = [r for r in range(len(events)) if events[r, 3] == 1 and events[r, 0] != lens.stop_index]
    clipped = {r: valid & (radius2[r] > semi[events[r, 0]] ** 2) for r in candidates}
    stop_rows = [r for r in range(len(events)) if events[r, 3] == 1 and events[r, 0] == lens.stop_index]
    explained = np.zeros_like(valid)
    stop_radius = float(lens.stop_radius_mm)
    for r in stop_rows:
        explained |= valid & (radius2[r] > stop_radius**2)
    chosen: list[int] = []
    threshold = max(1, int(1e-3 * max(1, valid.sum())))
    for _ in range(max_clip_events):
        gains = {r: int(np.sum(clipped[r] & ~explained)) for r in candidates if r not in chosen}
        if not gains:
            break
        best = max(gains, key=gains.get)
        if gains[best] < threshold:
            break
        chosen.append(best)
        explained |= clipped[best]
    chosen.sort()
    return tuple(chosen), tuple(int(events[r, 0]) for r in chosen)


def _output_matrix(result: TraceResult, clip_positions: Array) -> Array:
    """The fitted outputs per ray: sensor position and direction (x, y), each stop pass's position,
    each clear-aperture slot's position (``clip_positions`` (S, N, 3): zeros in inactive slots),
    throughput."""
    columns = [result.positions[:, 0], result.positions[:, 1], result.directions[:, 0], result.directions[:, 1]]
    for p in range(result.stop_positions.shape[1]):
        columns += [result.stop_positions[:, p, 0], result.stop_positions[:, p, 1]]
    for slot in range(clip_positions.shape[0]):
        columns += [clip_positions[slot, :, 0], clip_positions[slot, :, 1]]
    columns.append(result.throughput)
    return jnp.stack(columns, axis=-1)


def spd_solve(matrix: Array, rhs: Array) -> Array:
    """``matrix^-1 rhs`` for a symmetric positive definite ``matrix`` (M, M) and ``rhs`` (M, K), by
    Cholesky factorisation and two triangular solves written as plain XLA loops, differentiable
    through ``lax.custom_linear_solve`` (the derivative solves the same system again).

    Not LAPACK: jaxlib 0.10's CPU LAPACK kernels split a batched call over XLA's intra-op thread
    pool and block a pool thread until it is done, so as many calls at once as the pool has
    threads (2 on a 2-core machine: two solves of one fit, or two fits dispatched back to back)
    wait for each other for ever. Test runs hung there twice, every pool thread parked in
    ``CholeskyFactorization`` -> ``ParallelBatchMap`` -> ``BlockingCounter::Wait``. The loops
    cost O(M^3) like LAPACK's factorisation (M is a few hundred monomials)."""
    size = matrix.shape[-1]
    index = jnp.arange(size)

    def factor(k, lower):  # right-looking: column k of L, then its rank-1 update of the rest
        work, chol = lower
        pivot = jnp.sqrt(work[k, k])
        column = jnp.where(index >= k, work[:, k] / pivot, 0.0)
        return work - jnp.outer(column, column), chol.at[:, k].set(column)

    def solve(_, b):
        _, chol = jax.lax.fori_loop(0, size, factor, (matrix, jnp.zeros_like(matrix)))
        forward = lambda k, y: y.at[k].set((b[k] - chol[k] @ y) / chol[k, k])  # noqa: E731  L y = b
        y = jax.lax.fori_loop(0, size, forward, jnp.zeros_like(b))
        backward = lambda j, x: x.at[size - 1 - j].set((y[size - 1 - j] - chol[:, size - 1 - j] @ x) / chol[size - 1 - j, size - 1 - j])  # noqa: E731
        return jax.lax.fori_loop(0, size, backward, jnp.zeros_like(b))  # L^T x = y

    return jax.lax.custom_linear_solve(lambda x: matrix @ x, rhs, solve, symmetric=True)


def weighted_least_squares(design: Array, targets: Array, weights: Array, support: Array | None) -> Array:
    """Coefficients minimising sum_i w_i |design_i c - targets_i|^2 per output column (normal
    equations with a tiny ridge, Cholesky); ``support`` (M, O) restricts each column's terms."""
    weighted = design * weights[:, None]
    gram = weighted.T @ design
    scale = jnp.mean(jnp.diag(gram)) + 1e-300
    ridge = 1e-11 * scale
    rhs = weighted.T @ targets
    if support is None:
        return spd_solve(gram + ridge * jnp.eye(gram.shape[0], dtype=gram.dtype), rhs)

    def solve_one(mask, b):
        m = mask.astype(gram.dtype)
        g = gram * m[:, None] * m[None, :] + jnp.diag(1.0 - m) * scale + ridge * jnp.eye(gram.shape[0], dtype=gram.dtype)
        return spd_solve(g, b * m) * m

    return jax.vmap(solve_one, in_axes=(1, 1), out_axes=1)(support, rhs)


_SAMPLE_BUCKET = 2048
"""Fit sample counts are padded (with invalid rays) to this times a power of two, so that one
compiled fit serves the paths of a lens (their kept ray counts differ)."""


def _bucket(count: int) -> int:
    return _SAMPLE_BUCKET * 2 ** max(0, math.ceil(math.log2(max(count, 1) / _SAMPLE_BUCKET)))


def fit_columns(wide: TraceResult, variables, exponents: np.ndarray, clip_rows, clip_slots: int, support=None):
    """Least-squares coefficients of every output on exact traces ``wide`` of the widened lens,
    and the error estimator: the sensor columns minus those of the fit without the top degree.

    The compiled fit depends on the path only through its number of stop passes: the chosen
    clear-aperture events' positions are gathered into ``clip_slots`` slots here (inactive ones
    zero, fitted by zero coefficients), and the rays are padded to a bucket size."""
    count = variables.shape[0]
    size = _bucket(count)
    xp = np if isinstance(wide.positions, np.ndarray) else jnp  # NumPy for a build, jax.numpy under refit's tracing

    def pad(x, axis=0):
        widths = [(0, 0)] * x.ndim
        widths[axis] = (0, size - count)
        return np.pad(x, widths) if xp is np else jnp.pad(jnp.asarray(x), widths)

    clip_positions = xp.zeros((clip_slots - len(clip_rows), count, 3), wide.positions.dtype)  # the inactive slots
    if clip_rows:
        clip_positions = xp.concatenate([wide.event_positions[np.asarray(clip_rows)], clip_positions])
    padded = TraceResult(
        positions=pad(wide.positions), directions=pad(wide.directions), valid=pad(wide.valid), throughput=pad(wide.throughput),
        lost_at_surface=pad(wide.lost_at_surface), stop_positions=pad(wide.stop_positions), event_positions=None,
    )
    exponents_key = tuple(map(tuple, np.asarray(exponents).tolist()))
    return _fit_columns_jit(padded, pad(clip_positions, 1), pad(variables), exponents_key, support)


@eqx.filter_jit
def _fit_columns_jit(wide: TraceResult, clip_positions, variables, exponents_key, support):
    exponents = np.asarray(exponents_key, dtype=np.int64)
    # under an outer jit (a refit being differentiated) the samples are constants, and XLA would
    # constant-fold the whole design matrix at compile time (measured: > 1 s per gather, 19 s to
    # compile a degree-7 refit's Jacobian); the barrier keeps it a run-time computation
    variables = jax.lax.optimization_barrier(variables)
    design = monomials(variables, exponents)
    targets = _output_matrix(wide, clip_positions)
    weights = wide.valid.astype(design.dtype)
    totals = exponents.sum(axis=1)
    precise = precise_columns(wide.stop_positions.shape[1])
    auxiliary = np.setdiff1d(np.arange(targets.shape[1]), precise)
    low = np.flatnonzero(totals <= AUXILIARY_DEGREE)
    if support is None:
        coefficients = jnp.zeros((len(exponents), targets.shape[1]), design.dtype)
        coefficients = coefficients.at[:, precise].set(weighted_least_squares(design, targets[:, precise], weights, None))
        auxiliary_fit = weighted_least_squares(design[:, low], targets[:, auxiliary], weights, None)
        coefficients = coefficients.at[low[:, None], auxiliary[None, :]].set(auxiliary_fit)
    else:
        support = support.at[:, auxiliary].set(support[:, auxiliary] & jnp.asarray(totals <= AUXILIARY_DEGREE)[:, None])
        coefficients = weighted_least_squares(design, targets, weights, support)
    lower = np.flatnonzero(totals < totals.max())
    lower_support = None if support is None else support[lower][:, :2]
    lower_fit = weighted_least_squares(design[:, lower], targets[:, :2], weights, lower_support)
    estimator = coefficients[:, :2].at[lower].add(-lower_fit)
    return coefficients, estimator


def refit(system: PathSystem, lens: Lens) -> PathSystem:
    """Re-fit the coefficients of a ``"fit"`` system for ``lens`` on the same samples (same
    structure: path, terms, clipping events, domain, trust table). Differentiable with respect to
    the lens's arrays, so gradients of polynomial outputs with respect to lens parameters can be
    taken through it; the trust table and error limit are not re-validated."""
    if system.construction != "least-squares":
        raise ValueError("refit needs a system built with construction='least-squares'")
    variables = np.asarray(system.fit_variables, np.float64)
    exponents = np.asarray(system.exponents, np.int32)
    wide = trace_samples(widened_lens(lens), system.path, system.domain, variables, record_events=bool(system.clip_event_rows))
    coefficients, estimator = fit_columns(wide, variables, exponents, system.clip_event_rows, system.clip_active.shape[0])
    return eqx.tree_at(lambda s: (s.lens, s.coefficients, s.error_estimator), system, (lens, coefficients, estimator))


_REGION_GRID = (12, 12, 6, 6)
"""Cells over (u, v, s, t) in which the fit sampling tracks where rays get through."""


def _region_cells(variables: np.ndarray) -> tuple[np.ndarray, ...]:
    grid = np.asarray(_REGION_GRID)
    return tuple(np.clip(np.floor((variables[:, :4] + 1.0) * 0.5 * grid).astype(int), 0, grid - 1).T)


def _with_neighbours(mask: np.ndarray) -> np.ndarray:
    out = mask.copy()
    for axis in range(mask.ndim):
        padded = np.pad(mask, [(1, 1) if a == axis else (0, 0) for a in range(mask.ndim)])
        size = mask.shape[axis]
        out |= np.take(padded, range(0, size), axis) | np.take(padded, range(2, size + 2), axis)
    return out


def sample_region(region: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Exactly ``count`` domain samples (none if ``region`` is empty), uniform within the cells of
    ``region`` (a boolean grid of ``_REGION_GRID`` over (u, v, s, t)), w uniform. A fixed count
    keeps the traced shapes, and so the compiled tracer, the same from batch to batch."""
    cells = np.argwhere(region)
    if len(cells) == 0:
        return np.zeros((0, 5))
    width = 2.0 / np.asarray(_REGION_GRID)
    found, total = [], 0
    while total < count:
        pick = cells[rng.integers(len(cells), size=2 * count)]
        variables = np.empty((2 * count, 5))
        variables[:, :4] = -1.0 + (pick + rng.random((2 * count, 4))) * width
        variables[:, 4] = rng.uniform(-1.0, 1.0, 2 * count)
        inside = (variables[:, 0] ** 2 + variables[:, 1] ** 2 <= 1.0) & (variables[:, 2] ** 2 + variables[:, 3] ** 2 <= 1.0)
        found.append(variables[inside])
        total += int(inside.sum())
    return np.concatenate(found)[:count]


def fit_samples(lens: Lens, path, domain: PathDomain, needed: int, seed: int, max_candidates: int = 2**15):
    """Domain samples whose rays get through ``lens`` (exact traces with the events recorded).

    Returns ``(variables, traces, region)``: at least ``needed`` rays where that takes at most
    ``max_candidates`` candidates, and the cells (with their neighbours) where rays got through.
    The first batch is uniform over the domain. When few of its rays get through (a fast zoom at
    its wide end passes about 1 % of the front lens), later batches are drawn from the region
    found so far, which each batch extends.
    """
    rng = np.random.default_rng(seed)
    chunk = 8192
    max_candidates = max(max_candidates, chunk)
    kept_variables, kept_traces, candidates = [], [], 0
    hit = np.zeros(_REGION_GRID, bool)
    variables = sample_variables(chunk, rng)
    while len(variables):
        # selected and joined in NumPy: each batch keeps a different number of rays, and jax.numpy
        # would compile a gather and a concatenation per count (measured: 2 of a warm 5 s build)
        traces = jax.tree.map(np.asarray, trace_samples(lens, path, domain, variables, record_events=True))
        valid = traces.valid
        candidates += len(variables)
        kept_variables.append(variables[valid])
        kept_traces.append(_select_rays(traces, valid))
        hit[_region_cells(variables[valid])] = True
        total = sum(len(v) for v in kept_variables)
        if total >= needed or candidates >= max_candidates:
            break
        variables = sample_region(_with_neighbours(hit), chunk, rng)
    return np.concatenate(kept_variables), _concatenate_rays(kept_traces), _with_neighbours(hit)


def _select_rays(traces: TraceResult, keep: np.ndarray) -> TraceResult:
    return TraceResult(
        positions=traces.positions[keep], directions=traces.directions[keep], valid=traces.valid[keep],
        throughput=traces.throughput[keep], lost_at_surface=traces.lost_at_surface[keep],
        stop_positions=traces.stop_positions[keep], event_positions=traces.event_positions[:, keep],
    )


def _concatenate_rays(parts: Sequence[TraceResult]) -> TraceResult:
    def join(name, axis=0):
        return np.concatenate([getattr(p, name) for p in parts], axis=axis)

    return TraceResult(
        positions=join("positions"), directions=join("directions"), valid=join("valid"), throughput=join("throughput"),
        lost_at_surface=join("lost_at_surface"), stop_positions=join("stop_positions"), event_positions=join("event_positions", 1),
    )


class FitSamples(NamedTuple):
    """What a construction fits to: entrance variables, their exact traces through the widened
    lens, the path's clipping events and its number of stop passes."""

    variables: np.ndarray
    traced: TraceResult
    clip_rows: tuple[int, ...]
    clip_slots: int
    num_stop_passes: int


def structure_arrays(events: np.ndarray, clip_surfaces: Sequence[int], slots: int) -> dict:
    """The path's event table and its clear-aperture test slots (``slots`` of them, the unused
    ones inactive), as the arrays a :class:`PathSystem` holds."""
    index = np.zeros(slots, np.int32)
    index[: len(clip_surfaces)] = clip_surfaces
    return dict(
        events=jnp.asarray(events), clip_surface_index=jnp.asarray(index),
        clip_active=jnp.asarray(np.arange(slots) < len(clip_surfaces)),
    )


def build_polynomial(lens, path, domain, exponents, construction, max_clip_events, fit_rays, seed, tolerance_mm):
    """The polynomial (coefficients, error estimator, clipping events), not yet validated, and the
    region of the domain where the fit samples got through (see :func:`fit_samples`).
    ``construction``: an :class:`~jaxflare.polynomial.AbstractConstruction`."""
    events = path_events(lens, path)
    num_passes = stop_pass_count(events, lens.stop_index)
    variables, wide, region = fit_samples(widened_lens(lens), path, domain, fit_rays, seed)
    clip_rows, clip_surfaces = _choose_clip_events(lens, events, wide, max_clip_events)
    samples = FitSamples(variables=variables, traced=wide, clip_rows=clip_rows, clip_slots=max_clip_events, num_stop_passes=num_passes)
    coefficients, estimator, exponents = construction.coefficients(lens, path, domain, exponents, samples)
    system = PathSystem(
        lens=lens, coefficients=coefficients, trust_table=jnp.ones(TRUST_GRID, bool), path=path,
        fit_variables=jnp.asarray(variables), path_blocked=jnp.asarray(len(variables) == 0),
        error_estimator=estimator, estimate_limit_mm=jnp.asarray(tolerance_mm),
        **structure_arrays(events, clip_surfaces, max_clip_events),
        degree=int(exponents.max(initial=0)), construction=construction.name, exponents=tuple(map(tuple, np.asarray(exponents).tolist())),
        domain=domain, num_stop_passes=num_passes, clip_event_rows=clip_rows, clip_surfaces=clip_surfaces,
        report=None, fallback="none",
    )
    return system, region
