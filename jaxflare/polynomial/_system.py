"""Polynomial path systems: a lens path (primary or ghost) as a jit-compiled polynomial map.

A :class:`PathSystem` maps an entrance ray (position and direction on an entrance plane in front of
the lens, and wavelength) to the ray at the sensor, the ray at each pass through the aperture stop
(the aperture occlusion test of Hullin et al. 2011 and Pekkarinen & Balzer 2019), the ray at the
few clear apertures that clip the path most, and the Fresnel throughput. Its evaluation is one
monomial table and one matrix product, whatever the number of lens elements.

Two constructions (see :func:`path_system` and :mod:`._constructions`):

- ``"taylor"``: the truncated Taylor expansion about the optical axis at the band's centre
  wavelength, composed surface by surface (Hullin, Hanika & Heidrich 2012; :mod:`._taylor`);
- ``"least-squares"``: least squares against exact float64 traces sampled over the domain the
  scene needs (as in lentil and Schrade et al. 2016), optionally sparse.

In the renderer a :class:`PolynomialPathTracer` evaluates systems of one structure together,
behind the same :class:`~jaxflare.optics.AbstractPathTracer` interface as the exact tracer.

Every system is validated against the exact tracer when it is built: the measured errors are in
:attr:`PathSystem.report`, and a table over the input domain marks the cells where the polynomial
is within tolerance and agrees with the exact validity mask. Rays outside the domain or in a cell
that failed validation are *untrusted*: they are re-traced exactly (up to a fixed capacity, so
shapes stay static) or returned invalid and untrusted, never silently approximated.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ..optics import AbstractPathTracer, EventTable, Lens, LossReason, TraceResult, inside_iris, ray_arguments, surface_sag_mm, trace_events
from ._basis import graded_plan, monomial_rows
from ._domain import PathDomain, cell_index, entrance_variables

GhostPath = tuple[int, int]


@dataclasses.dataclass(frozen=True)
class PathSystemReport:
    """How a path system was built and how accurate it measured against the exact tracer.

    Errors are sensor-plane distances in micrometres over rays valid in both the exact trace and
    the polynomial (``all``: every such validation ray; ``trusted``: those in trusted cells).
    ``mask_mismatch`` is the fraction of validation rays whose validity differs.
    """

    construction: str
    degree: int
    num_terms: int
    fit_rays: int
    validation_rays: int
    error_um_median: float
    error_um_p99: float
    error_um_max: float
    trusted_error_um_p99: float
    trusted_error_um_max: float
    mask_mismatch: float
    trusted_fraction: float
    valid_fraction: float
    clip_surfaces: tuple[int, ...]
    unmodelled_clip_fraction: float
    """Validation rays lost at a clear aperture the system does not test (not among the top few)."""
    tolerance_um: float
    estimate_limit_um: float
    """Rays whose error estimate exceeds this are not trusted (see ``PathSystem.estimate_limit_mm``)."""
    build_seconds: float

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


# --------------------------------------------------------------------------- the system


class PathSystem(eqx.Module):
    """One lens path as a polynomial; call it like :func:`jaxflare.trace` without lens and path.

    ``system(origins, directions, wavelength_nm)`` returns a :class:`~jaxflare.TraceResult` with the
    same fields (``event_positions`` is None) plus ``trusted``. The aperture tests use the iris and
    clear apertures of :attr:`lens` at call time, so stopping down needs no rebuild
    (``eqx.tree_at(lambda s: s.lens, system, lens.with_f_number(8))`` or :meth:`with_lens`).
    """

    lens: Lens
    coefficients: Float[Array, "M O"]
    """Polynomial coefficients: one column per output (sensor x, y; direction x, y; stop x, y per
    pass; x, y at each clipping event; throughput), rows in :attr:`exponents` order."""
    trust_table: Bool[Array, "a b c d e"]
    """Per cell of the (u, v, s, t, w) domain: validated against the exact tracer."""
    error_estimator: Float[Array, "M 2"]
    """Sensor x, y of this polynomial minus those of the next lower degree: the size of that
    difference is each ray's error estimate (the Taylor construction's truncation term)."""
    estimate_limit_mm: Float[Array, ""]
    """Largest error estimate a ray may have and still be trusted: the tolerance times a factor
    (1 to 8) calibrated on the validation samples, as the estimate of a degree-d polynomial by its
    difference to degree d - 1 overstates its error."""
    fit_variables: Float[Array, "K 5"]
    """The (u, v, s, t, w) samples the construction traced exactly (for :func:`refit`)."""
    path_blocked: Bool[Array, ""]
    """True when no sampled ray gets through the path at all: every ray is invalid."""
    events: Int[Array, "E 4"]
    """The path's event table (:func:`jaxflare.path_events`), for the exact fallback."""
    clip_surface_index: Int[Array, " K"]
    """Surface of each clear-aperture test slot (padded slots are inactive)."""
    clip_active: Bool[Array, " K"]
    path: GhostPath | None = eqx.field(static=True)
    degree: int = eqx.field(static=True)
    construction: str = eqx.field(static=True)
    exponents: tuple[tuple[int, ...], ...] = eqx.field(static=True)
    """Exponents of (u, v, s, t, w) of each term kept."""
    domain: PathDomain = eqx.field(static=True)
    num_stop_passes: int = eqx.field(static=True)
    clip_event_rows: tuple[int, ...] = eqx.field(static=True)
    clip_surfaces: tuple[int, ...] = eqx.field(static=True)
    report: PathSystemReport = eqx.field(static=True)
    fallback: str = eqx.field(static=True, default="exact")
    fallback_fraction: float = eqx.field(static=True, default=0.125)

    @property
    def num_terms(self) -> int:
        return len(self.exponents)

    def with_lens(self, lens: Lens) -> "PathSystem":
        """The same polynomial with the apertures (iris radius, blades, rotation) of ``lens``."""
        return eqx.tree_at(lambda s: s.lens, self, lens)

    def __call__(self, origins: ArrayLike, directions: ArrayLike, wavelength_nm: ArrayLike = 587.56) -> TraceResult:
        """Evaluate the path for (N, 3) ``origins`` and ``directions`` (mm, lens frame, as for
        :func:`jaxflare.trace`) and scalar or (N,) ``wavelength_nm``.

        Untrusted rays (outside the domain, or in a part of it where validation failed or the
        error estimate exceeds the limit) are traced exactly, up to ``fallback_fraction`` of the
        batch; beyond that they come back invalid with ``trusted`` False and ``lost_at_surface``
        -2. Jit-compiled; systems of one lens with the same degree and stop passes share it.
        """
        return evaluate(self.kernel(), *ray_arguments(origins, directions, wavelength_nm))

    def kernel(self, fallback: str | None = None) -> "PathKernel":
        """What evaluation needs: systems of one lens with the same degree, terms and number of
        stop passes share one compiled evaluator (the path itself is data, not structure)."""
        return PathKernel(
            lens=self.lens, coefficients=self.coefficients, trust_table=self.trust_table, events=self.events,
            error_estimator=self.error_estimator, estimate_limit_mm=self.estimate_limit_mm, path_blocked=self.path_blocked,
            clip_surface_index=self.clip_surface_index, clip_active=self.clip_active, exponents=self.exponents,
            domain=self.domain, num_stop_passes=self.num_stop_passes, fallback=fallback or self.fallback,
            fallback_fraction=self.fallback_fraction,
        )

    def polynomial(self, origins: ArrayLike, directions: ArrayLike, wavelength_nm: ArrayLike = 587.56) -> TraceResult:
        """The polynomial alone, without the exact fallback: untrusted rays come back invalid."""
        return evaluate(self.kernel(fallback="none"), *ray_arguments(origins, directions, wavelength_nm))


class PathKernel(eqx.Module):
    """The part of a :class:`PathSystem` that evaluation reads. It leaves out the path, the report
    and other metadata, so that every path of a lens with the same degree and number of stop
    passes has the same structure and shares one compiled evaluator."""

    lens: Lens
    coefficients: Float[Array, "M O"]
    trust_table: Bool[Array, "a b c d e"]
    error_estimator: Float[Array, "M 2"]
    estimate_limit_mm: Float[Array, ""]
    path_blocked: Bool[Array, ""]
    events: Int[Array, "E 4"]
    clip_surface_index: Int[Array, " K"]
    clip_active: Bool[Array, " K"]
    exponents: tuple[tuple[int, ...], ...] = eqx.field(static=True)
    domain: PathDomain = eqx.field(static=True)
    num_stop_passes: int = eqx.field(static=True)
    fallback: str = eqx.field(static=True)
    fallback_fraction: float = eqx.field(static=True)




def precise_columns(num_stop_passes: int) -> np.ndarray:
    """Output columns that get the full degree: sensor x, y and the stop positions. The others
    (direction, clipping events, throughput) get at most ``AUXILIARY_DEGREE``."""
    return np.concatenate([[0, 1], 4 + np.arange(2 * num_stop_passes)])


AUXILIARY_DEGREE = 4
"""Highest degree of the auxiliary outputs. They decide clipping at rims and weight samples,
where a few micrometres do not matter, and skipping their high-degree terms roughly halves the
cost of a degree-7 evaluation (measured on the Biotar: see the polynomial benchmark)."""


def polynomial_outputs(system: "PathKernel", variables: Array) -> tuple[Array, Array]:
    """All outputs (N, O), and each ray's estimated sensor-position error (mm).

    A full (graded) basis is evaluated degree by degree, each degree's monomials contracted with
    their coefficients at once (the auxiliary outputs only up to ``AUXILIARY_DEGREE``); a sparse
    subset from one table of its monomials.
    """
    count, num_outputs = variables.shape[0], system.coefficients.shape[1]
    precise = precise_columns(system.num_stop_passes)
    auxiliary = np.setdiff1d(np.arange(num_outputs), precise)
    dtype = variables.dtype
    exact_weights = jnp.concatenate([system.coefficients[:, precise], system.error_estimator], axis=1).astype(dtype)
    auxiliary_weights = system.coefficients[:, auxiliary].astype(dtype)
    by_variable = jnp.clip(variables, -1.5, 1.5).T  # (V, N)
    plan = graded_plan(system.exponents)
    if plan is None:
        table = monomial_rows(by_variable.T, np.asarray(system.exponents, dtype=np.int32))  # (M, N)
        precise_values = exact_weights.T @ table
        auxiliary_values = auxiliary_weights.T @ table
    else:
        block = jnp.ones((1, count), dtype)
        precise_values = jnp.broadcast_to(exact_weights[0][:, None], (exact_weights.shape[1], count))
        auxiliary_values = jnp.broadcast_to(auxiliary_weights[0][:, None], (auxiliary_weights.shape[1], count))
        for degree, (columns, pieces) in enumerate(plan, start=1):
            block = jnp.concatenate([block[start:] * by_variable[v] for v, start in pieces], axis=0)
            precise_values = precise_values + exact_weights[columns].T @ block
            if degree <= AUXILIARY_DEGREE:
                auxiliary_values = auxiliary_values + auxiliary_weights[columns].T @ block
    precise_values, auxiliary_values = precise_values.T, auxiliary_values.T
    order = np.argsort(np.concatenate([precise, auxiliary]))
    outputs = jnp.concatenate([precise_values[:, : len(precise)], auxiliary_values], axis=1)[:, order]
    difference = precise_values[:, len(precise) :]
    estimate = jnp.sqrt(jnp.sum(difference**2, axis=-1) + 1e-30)
    return outputs, estimate


def _surface_z(lens: Lens, surface: int, x: Array, y: Array) -> Array:
    vertex_z = jnp.sum(lens.thickness_mm[:surface])
    return vertex_z + surface_sag_mm(lens, surface, x, y)


@eqx.debug.assert_max_traces(max_traces=None)  # counts compilations: tests catch retracing with get_num_traces
def _evaluate(system: PathKernel, origins: Array, directions: Array, wavelength: Array) -> TraceResult:
    """A path kernel at (N, 3) ``origins`` and ``directions`` and (N,) ``wavelength``, with its exact
    fallback (``system.fallback == "exact"``) for untrusted rays."""
    lens = system.lens
    dtype = origins.dtype
    count = origins.shape[0]
    domain = system.domain
    variables, forward = entrance_variables(domain, origins, directions, wavelength)
    out, estimated_error = polynomial_outputs(system, variables)

    entrance_r2 = variables[:, 0] ** 2 + variables[:, 1] ** 2
    field2 = variables[:, 2] ** 2 + variables[:, 3] ** 2
    in_field = forward & (field2 <= 1.0)
    in_band = jnp.abs(variables[:, 4]) <= 1.0
    certainly_clipped = in_field & (entrance_r2 > 1.0)
    cell = cell_index(variables)
    cell_trusted = system.trust_table[cell[:, 0], cell[:, 1], cell[:, 2], cell[:, 3], cell[:, 4]]
    within_tolerance = jax.lax.stop_gradient(estimated_error) <= system.estimate_limit_mm
    trusted = certainly_clipped | (in_field & in_band & cell_trusted & within_tolerance)

    sensor_xy = out[:, 0:2]
    direction_xy = out[:, 2:4]
    dz = jnp.sqrt(jnp.clip(1.0 - jnp.sum(direction_xy**2, axis=-1), 1e-12, 1.0))
    column = 4
    passes_ok = jnp.ones(count, bool)
    stop_positions = []
    lost_at = jnp.full(count, LossReason.NOT_LOST, jnp.int32)
    for _ in range(system.num_stop_passes):
        x, y = out[:, column], out[:, column + 1]
        column += 2
        inside = inside_iris(x, y, lens.stop_radius_mm, lens.aperture_blades, lens.aperture_rotation_rad)
        inside = inside & (x * x + y * y <= lens.semi_aperture_mm[lens.stop_index] ** 2)
        lost_at = jnp.where(passes_ok & ~inside, lens.stop_index, lost_at)
        passes_ok = passes_ok & inside
        stop_positions.append(jnp.stack([x, y, _surface_z(lens, lens.stop_index, x, y)], axis=-1))
    for k in range(system.clip_active.shape[0]):
        x, y = out[:, column], out[:, column + 1]
        column += 2
        surface = system.clip_surface_index[k]
        inside = ~system.clip_active[k] | (x * x + y * y <= lens.semi_aperture_mm[surface] ** 2)
        lost_at = jnp.where(passes_ok & ~inside, surface, lost_at)
        passes_ok = passes_ok & inside
    throughput = jnp.clip(out[:, column], 0.0, 1.0)

    valid = trusted & ~certainly_clipped & passes_ok & ~system.path_blocked
    lost_at = jnp.where(certainly_clipped, 0, lost_at)
    lost_at = jnp.where(trusted, lost_at, LossReason.UNTRUSTED)
    positions = jnp.concatenate([sensor_xy, jnp.broadcast_to(lens.sensor_z_mm.astype(dtype), (count,))[:, None]], axis=-1)
    directions_out = jnp.concatenate([direction_xy, dz[:, None]], axis=-1)
    stops = jnp.stack(stop_positions, axis=1) if stop_positions else jnp.zeros((count, 0, 3), dtype)
    result = TraceResult(
        positions=positions,
        directions=directions_out,
        valid=valid,
        throughput=jnp.where(valid, throughput, 0.0),
        lost_at_surface=lost_at,
        stop_positions=stops,
        trusted=trusted,
    )
    if system.fallback == "exact":
        result = _exact_fallback(system, result, origins, directions, wavelength)
    return result


evaluate = eqx.filter_jit(_evaluate)


def _exact_fallback(system: PathKernel, result: TraceResult, origins, directions, wavelength) -> TraceResult:
    """Re-trace up to ``ceil(fallback_fraction * N)`` untrusted rays exactly (fixed shapes: the
    untrusted rays are gathered into a buffer of that size; any beyond it stay untrusted)."""
    count = origins.shape[0]
    capacity = max(1, math.ceil(system.fallback_fraction * count))
    (index,) = jnp.nonzero(~result.trusted, size=capacity, fill_value=count)
    used = index < count
    take = jnp.where(used, index, 0)
    exact = trace_events(
        system.lens, origins[take], directions[take], wavelength[take], EventTable.from_array(system.events), system.num_stop_passes,
    )
    target = jnp.where(used, index, count)  # out-of-range rows are dropped by the scatter

    def put(field, value):
        return field.at[target].set(value, mode="drop")

    return TraceResult(
        positions=put(result.positions, exact.positions),
        directions=put(result.directions, exact.directions),
        valid=put(result.valid, exact.valid),
        throughput=put(result.throughput, exact.throughput),
        lost_at_surface=put(result.lost_at_surface, exact.lost_at_surface),
        stop_positions=put(result.stop_positions, exact.stop_positions),
        trusted=put(result.trusted, jnp.ones_like(exact.valid)),
    )


class PolynomialPathTracer(AbstractPathTracer):
    """Path systems of one structure (same lens, degree, terms and stop passes) evaluated together.

    ``kernels`` holds ``num_paths`` :class:`PathKernel` stacked along a leading axis; ``trace``
    expects the rays grouped by path in equal blocks (``slot = repeat(arange(num_paths), n)``), as
    the renderer draws them, and evaluates the blocks vmapped. Untrusted rays are re-traced exactly
    up to ``fallback_capacity`` of each path's block (0: none; they come back invalid and
    untrusted).
    """

    kernels: PathKernel
    fallback_capacity: float = eqx.field(static=True)

    @classmethod
    def for_systems(cls, systems, fallback_capacity: float) -> PolynomialPathTracer:
        """Stack ``systems`` (:class:`PathSystem`, one structure) with an exact fallback of
        ``fallback_capacity`` (a fraction of each path's rays, in (0, 1], or 0 for none)."""
        if fallback_capacity == 0:
            kernels = [system.kernel(fallback="none") for system in systems]
        else:
            kernels = [dataclasses.replace(system, fallback_fraction=fallback_capacity).kernel(fallback="exact") for system in systems]
        return cls(jax.tree.map(lambda *xs: jnp.stack(xs), *kernels), fallback_capacity)

    @property
    def num_paths(self) -> int:
        return int(self.kernels.coefficients.shape[0])

    def trace(self, origins: Array, directions: Array, wavelength_nm: Array, slot=None) -> TraceResult:
        blocks = self.num_paths
        origins, directions, wavelength_nm = (x.reshape((blocks, -1) + x.shape[1:]) for x in (origins, directions, wavelength_nm))
        traced = jax.vmap(evaluate)(self.kernels, origins, directions, wavelength_nm)
        return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), traced)
