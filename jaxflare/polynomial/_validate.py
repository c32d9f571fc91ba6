"""Validation of a path system against the exact tracer: measured errors, the calibrated limit
on the error estimate, and the trust table."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._domain import TRUST_GRID, cell_index, rays_from_variables
from ._least_squares import trace_samples
from ._system import PathSystem, evaluate, polynomial_outputs

_MIN_CELL_RAYS = 3
"""A cell with fewer validation samples than this is not trusted."""
_MIN_CALIBRATION_RAYS = 200
"""The limit on the error estimate is only raised above the tolerance on this much evidence."""


def validate(system: PathSystem, variables: np.ndarray, tolerance_mm: float, max_mismatch: float):
    """Exact float64 traces of the real lens against the polynomial on fresh samples: errors,
    mask agreement and the trust table.

    A cell of the table is trusted when it holds at least ``_MIN_CELL_RAYS`` samples and, among
    those whose error estimate is within tolerance: at least ``_MIN_CELL_RAYS`` are valid in both
    (unless the polynomial answers none of them valid); every ray valid in both is within tolerance;
    at most ``max_mismatch`` of them (at least one) disagree on validity; and none that the
    polynomial calls valid is lost in the exact trace for a reason no aperture explains (total
    internal reflection, a missed surface: found by tracing with every aperture opened wide).
    """
    lens = system.lens
    exact = trace_samples(lens, system.path, system.domain, variables)
    opened = eqx.tree_at(lambda l: (l.semi_aperture_mm, l.stop_radius_mm), lens, (lens.semi_aperture_mm * 0 + 1e6, lens.stop_radius_mm * 0 + 1e6))
    unobstructed = trace_samples(opened, system.path, system.domain, variables)
    rays = tuple(jnp.asarray(v) for v in rays_from_variables(system.domain, variables))
    kernel = eqx.tree_at(
        lambda s: (s.trust_table, s.estimate_limit_mm), system, (jnp.ones(TRUST_GRID, bool), jnp.asarray(jnp.inf))
    ).kernel(fallback="none")
    poly = evaluate(kernel, *rays)  # the polynomial's answers everywhere in the domain
    estimate = np.asarray(polynomial_outputs(kernel, jnp.asarray(variables))[1])
    exact_valid = np.asarray(exact.valid)
    poly_valid = np.asarray(poly.valid)
    both = exact_valid & poly_valid
    error = np.linalg.norm(np.asarray(poly.positions)[:, :2] - np.asarray(exact.positions)[:, :2], axis=-1)
    # calibrate the limit on the error estimate: the largest factor whose accepted rays meet the tolerance
    factor = 1.0
    for candidate in (1.5, 2.0, 3.0, 4.0, 6.0, 8.0):
        accepted = error[both & (estimate <= candidate * tolerance_mm)]
        if accepted.size >= _MIN_CALIBRATION_RAYS and np.percentile(accepted, 99.5) <= tolerance_mm and accepted.max() <= 2 * tolerance_mm:
            factor = candidate
    estimate_limit_mm = factor * tolerance_mm
    estimate_ok = estimate <= estimate_limit_mm
    flat = np.ravel_multi_index(cell_index(variables).T, TRUST_GRID)
    size = int(np.prod(TRUST_GRID))
    samples = np.bincount(flat, minlength=size)
    considered = np.bincount(flat, weights=estimate_ok, minlength=size)
    mismatches = np.bincount(flat, weights=estimate_ok & (exact_valid != poly_valid), minlength=size)
    unexplained = np.bincount(flat, weights=estimate_ok & poly_valid & ~np.asarray(unobstructed.valid), minlength=size)
    evidence = np.bincount(flat, weights=both & estimate_ok, minlength=size)
    answered = np.bincount(flat, weights=poly_valid & estimate_ok, minlength=size)
    worst = np.zeros(size)
    np.maximum.at(worst, flat[both & estimate_ok], error[both & estimate_ok])
    trusted = (
        (samples >= _MIN_CELL_RAYS) & ((evidence >= _MIN_CELL_RAYS) | (answered == 0))
        & (worst <= tolerance_mm) & (unexplained == 0)
        & (mismatches <= np.maximum(1.0, max_mismatch * considered))
    )
    table = trusted.reshape(TRUST_GRID)
    ray_trusted = trusted[flat] & estimate_ok

    def stats(values):
        return (float(np.median(values)), float(np.percentile(values, 99)), float(values.max())) if values.size else (0.0, 0.0, 0.0)

    all_stats = stats(error[both] * 1e3)
    trusted_stats = stats(error[both & ray_trusted] * 1e3)
    # rays the exact trace loses at a clear aperture the system does not test
    lost = np.asarray(exact.lost_at_surface)
    modelled = set(system.clip_surfaces) | {lens.stop_index}
    unmodelled = np.mean((~exact_valid) & poly_valid & (lost >= 0) & ~np.isin(lost, list(modelled)) & (lost < lens.num_surfaces))
    summary = dict(
        error_um_median=all_stats[0], error_um_p99=all_stats[1], error_um_max=all_stats[2],
        trusted_error_um_p99=trusted_stats[1], trusted_error_um_max=trusted_stats[2],
        mask_mismatch=float(np.mean(exact_valid != poly_valid)), trusted_fraction=float(np.mean(ray_trusted)),
        valid_fraction=float(np.mean(exact_valid)), unmodelled_clip_fraction=float(unmodelled),
    )
    return table, estimate_limit_mm, summary
