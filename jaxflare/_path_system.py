"""Polynomial path systems: a lens path (primary or ghost) as a jit-compiled polynomial map.

A :class:`PathSystem` maps an entrance ray (position and direction on an entrance plane in front of
the lens, and wavelength) to the ray at the sensor, the ray at each pass through the aperture stop
(the aperture occlusion test of Hullin et al. 2011 and Pekkarinen & Balzer 2019), the ray at the
few clear apertures that clip the path most, and the Fresnel throughput. Its evaluation is one
monomial table and one matrix product, whatever the number of lens elements.

Two constructions (see :func:`path_system`):

- ``"taylor"``: the truncated Taylor expansion about the optical axis at the band's centre
  wavelength, composed surface by surface (Hullin, Hanika & Heidrich 2012; :mod:`._taylor`);
- ``"fit"``: least squares against exact float64 traces sampled over the domain the scene needs
  (as in lentil and Schrade et al. 2016), optionally sparse.

Every system is validated against the exact tracer when it is built: the measured errors are in
:attr:`PathSystem.report`, and a table over the input domain marks the cells where the polynomial
is within tolerance and agrees with the exact validity mask. Rays outside the domain or in a cell
that failed validation are *untrusted*: they are re-traced exactly (up to a fixed capacity, so
shapes stay static) or returned invalid and untrusted, never silently approximated.
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import io
import json
import math
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._io import write_bytes_atomic
from ._lens import Lens
from ._polybasis import monomial_exponents, monomials
from ._trace import TraceResult, _check_path, _inside_iris, _stop_pass_count, _surface_sag_slope, _trace_events, path_events, ray_arguments

Construction = Literal["fit", "taylor"]
GhostPath = tuple[int, int]

DEFAULT_WAVELENGTH_RANGE_NM = (380.0, 780.0)
DEFAULT_DEGREE = 5
CACHE_FORMAT = 1
_APERTURE_MARGIN = 1.03
"""Clear apertures are widened by this factor for the fit samples, so each polynomial is also
accurate slightly beyond the rims it is tested against (capped where a surface ends)."""
_TRUST_GRID = (5, 5, 5, 5, 2)
"""Cells of the trust table over (u, v, s, t, w)."""
_MIN_CELL_RAYS = 3
"""A cell with fewer validation samples than this is not trusted."""


# --------------------------------------------------------------------------- domain


@dataclasses.dataclass(frozen=True)
class PathDomain:
    """The inputs a path system is built and validated for.

    Rays cross the plane ``z = entrance_z_mm`` (in front of the front lens) within
    ``entrance_radius_mm`` of the axis, make an angle of at most ``max_field_angle_deg`` with the
    axis, and have wavelengths in ``[wavelength_min_nm, wavelength_max_nm]``. The entrance radius
    covers every ray that can reach the front clear aperture at that angle; a ray crossing the
    plane further out is certainly clipped by the front lens.
    """

    max_field_angle_deg: float
    entrance_z_mm: float
    entrance_radius_mm: float
    wavelength_min_nm: float = DEFAULT_WAVELENGTH_RANGE_NM[0]
    wavelength_max_nm: float = DEFAULT_WAVELENGTH_RANGE_NM[1]

    @property
    def sin_max_field(self) -> float:
        return math.sin(math.radians(self.max_field_angle_deg))

    @property
    def wavelength_center_nm(self) -> float:
        return 0.5 * (self.wavelength_min_nm + self.wavelength_max_nm)

    @property
    def wavelength_half_width_nm(self) -> float:
        return 0.5 * (self.wavelength_max_nm - self.wavelength_min_nm)


def _front_rim_sag_mm(lens: Lens) -> float:
    c, k = float(lens.curvature_per_mm[0]), float(lens.conic[0])
    rho2 = float(lens.semi_aperture_mm[0]) ** 2
    sag, _ = _surface_sag_slope(np.float64(rho2), c, k, np.asarray(lens.aspheric_coefficients[0], np.float64))
    return float(sag)


def make_domain(
    lens: Lens,
    max_field_angle_deg: float | None = None,
    wavelength_range_nm: tuple[float, float] = DEFAULT_WAVELENGTH_RANGE_NM,
) -> PathDomain:
    """The domain for ``lens``: the whole front lens, field angles up to ``max_field_angle_deg``
    (default: the lens's half field of view, :func:`half_field_of_view_deg`), the wavelength band."""
    if max_field_angle_deg is None:
        max_field_angle_deg = half_field_of_view_deg(lens)
    if not 0 < max_field_angle_deg < 89:
        raise ValueError(f"max_field_angle_deg must be in (0, 89) degrees, got {max_field_angle_deg}")
    low, high = (float(v) for v in wavelength_range_nm)
    if not 200 <= low < high <= 2500:
        raise ValueError(f"wavelength_range_nm must be (low, high) with 200 <= low < high <= 2500 nm, got {wavelength_range_nm}")
    sag = _front_rim_sag_mm(lens)
    entrance_z = min(0.0, sag) - 1.0
    reach = max(0.0, sag) - entrance_z  # axial distance from the entrance plane to the front rim
    radius = float(lens.semi_aperture_mm[0]) + reach * math.tan(math.radians(max_field_angle_deg))
    return PathDomain(float(max_field_angle_deg), entrance_z, radius, low, high)


def half_field_of_view_deg(lens: Lens, wavelength_nm: float = 587.56) -> float:
    """Half the diagonal field of view in degrees: the field angle whose chief ray (the ray of a
    meridional fan passing closest to the stop centre) meets the sensor at its corner.

    Found by exact tracing, so it holds for fisheyes as well as rectilinear lenses. If rays stop
    getting through before the corner is reached, the largest angle that still images is returned.
    """
    p = lens.prescription
    half_diagonal = 0.5 * math.hypot(p.sensor_width_mm, p.sensor_height_mm)
    angles = np.linspace(0.0, 88.0, 177)
    fan = 97
    entrance_z = min(0.0, _front_rim_sag_mm(lens)) - 1.0
    radius = float(lens.semi_aperture_mm[0])
    with jax.enable_x64(True):
        heights = np.linspace(-1.0, 1.0, fan) * radius
        theta = np.radians(angles)[:, None]
        ys = np.broadcast_to(heights[None, :], (len(angles), fan)).copy()  # a fan across the front aperture per angle
        origins = np.stack([np.zeros_like(ys), ys, np.full_like(ys, entrance_z)], -1).reshape(-1, 3)
        directions = np.stack([np.zeros_like(ys), np.broadcast_to(np.sin(theta), ys.shape), np.broadcast_to(np.cos(theta), ys.shape)], -1).reshape(-1, 3)
        lens64 = _as_float64(lens)
        # shift each fan so that it is centred on the entrance pupil: aim at the stop centre
        z_pupil, _ = lens64.entrance_pupil(wavelength_nm)
        shift = -(z_pupil - entrance_z) * np.tan(np.radians(np.repeat(angles, fan)))
        origins[:, 1] += shift
        result = _trace_events(
            lens64, jnp.asarray(origins), jnp.asarray(directions), jnp.full(len(origins), wavelength_nm),
            jnp.asarray(path_events(lens64, None)), 1,
        )
        valid = np.asarray(result.valid).reshape(len(angles), fan)
        sensor_y = np.asarray(result.positions[:, 1]).reshape(len(angles), fan)
        stop_r = np.hypot(*np.asarray(result.stop_positions[:, 0, :2]).T).reshape(len(angles), fan)
    chief_height = np.full(len(angles), np.nan)
    for a in range(len(angles)):
        if valid[a].any():
            k = np.argmin(np.where(valid[a], stop_r[a], np.inf))
            chief_height[a] = abs(sensor_y[a, k])
    imaging = np.flatnonzero(np.isfinite(chief_height))
    if imaging.size == 0:
        raise ValueError(f"no ray of '{lens.name}' reaches the sensor: cannot find its field of view")
    beyond = imaging[chief_height[imaging] >= half_diagonal]
    if beyond.size == 0:
        return float(angles[imaging[-1]])
    b = beyond[0]
    if b == 0:
        return float(angles[1])
    a = b - 1
    if not np.isfinite(chief_height[a]):
        return float(angles[b])
    frac = (half_diagonal - chief_height[a]) / (chief_height[b] - chief_height[a])
    return float(angles[a] + frac * (angles[b] - angles[a]))


def _as_float64(lens: Lens) -> Lens:
    return jax.tree.map(lambda x: jnp.asarray(x, jnp.float64) if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) else x, lens)


# --------------------------------------------------------------------------- variables


def _entrance_variables(domain: PathDomain, origins: Array, directions: Array, wavelength_nm: Array):
    """Normalised variables (u, v, s, t, w), unit directions and the crossing radius on the plane."""
    directions = directions / jnp.linalg.norm(directions, axis=-1, keepdims=True)
    dz = directions[:, 2]
    forward = dz > 1e-6
    travel = (domain.entrance_z_mm - origins[:, 2]) / jnp.where(forward, dz, 1.0)
    x = origins[:, 0] + travel * directions[:, 0]
    y = origins[:, 1] + travel * directions[:, 1]
    radius = domain.entrance_radius_mm
    sin_field = domain.sin_max_field
    variables = jnp.stack(
        [
            x / radius,
            y / radius,
            directions[:, 0] / sin_field,
            directions[:, 1] / sin_field,
            (wavelength_nm - domain.wavelength_center_nm) / domain.wavelength_half_width_nm,
        ],
        axis=-1,
    )
    return variables, forward


def _sample_variables(count: int, seed: int) -> np.ndarray:
    """Uniform samples of the domain: (u, v) and (s, t) uniform over unit disks, w over [-1, 1]."""
    rng = np.random.default_rng(seed)

    def disk(n):
        r = np.sqrt(rng.random(n))
        phi = 2 * np.pi * rng.random(n)
        return r * np.cos(phi), r * np.sin(phi)

    u, v = disk(count)
    s, t = disk(count)
    w = rng.uniform(-1.0, 1.0, count)
    return np.stack([u, v, s, t, w], axis=-1)


def _rays_from_variables(domain: PathDomain, variables: np.ndarray):
    u, v, s, t, w = variables.T
    sx, sy = s * domain.sin_max_field, t * domain.sin_max_field
    origins = np.stack([u * domain.entrance_radius_mm, v * domain.entrance_radius_mm, np.full_like(u, domain.entrance_z_mm)], -1)
    directions = np.stack([sx, sy, np.sqrt(np.clip(1 - sx * sx - sy * sy, 0, 1))], -1)
    wavelength = domain.wavelength_center_nm + w * domain.wavelength_half_width_nm
    return origins, directions, wavelength


# --------------------------------------------------------------------------- report


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
        return _evaluate(self.kernel(), *ray_arguments(origins, directions, wavelength_nm))

    def kernel(self, fallback: str | None = None) -> "_Kernel":
        """What evaluation needs: systems of one lens with the same degree, terms and number of
        stop passes share one compiled evaluator (the path itself is data, not structure)."""
        return _Kernel(
            lens=self.lens, coefficients=self.coefficients, trust_table=self.trust_table, events=self.events,
            error_estimator=self.error_estimator, estimate_limit_mm=self.estimate_limit_mm,
            clip_surface_index=self.clip_surface_index, clip_active=self.clip_active, exponents=self.exponents,
            domain=self.domain, num_stop_passes=self.num_stop_passes, fallback=fallback or self.fallback,
            fallback_fraction=self.fallback_fraction,
        )

    def polynomial(self, origins: ArrayLike, directions: ArrayLike, wavelength_nm: ArrayLike = 587.56) -> TraceResult:
        """The polynomial alone, without the exact fallback: untrusted rays come back invalid."""
        return dataclasses.replace(self, fallback="none")(origins, directions, wavelength_nm)


class _Kernel(eqx.Module):
    lens: Lens
    coefficients: Float[Array, "M O"]
    trust_table: Bool[Array, "a b c d e"]
    error_estimator: Float[Array, "M 2"]
    estimate_limit_mm: Float[Array, ""]
    events: Int[Array, "E 4"]
    clip_surface_index: Int[Array, " K"]
    clip_active: Bool[Array, " K"]
    exponents: tuple[tuple[int, ...], ...] = eqx.field(static=True)
    domain: PathDomain = eqx.field(static=True)
    num_stop_passes: int = eqx.field(static=True)
    fallback: str = eqx.field(static=True)
    fallback_fraction: float = eqx.field(static=True)


EVALUATIONS = [0]
"""How often the evaluator has been traced by JAX (tests use it to catch retracing)."""


def _polynomial_outputs(system: "_Kernel", variables: Array) -> tuple[Array, Array]:
    """All outputs, and each ray's estimated sensor-position error (mm)."""
    exponents = np.asarray(system.exponents, dtype=np.int32)
    table = monomials(jnp.clip(variables, -1.5, 1.5), exponents)
    difference = table @ system.error_estimator.astype(variables.dtype)
    estimate = jnp.sqrt(jnp.sum(difference**2, axis=-1) + 1e-30)
    return table @ system.coefficients.astype(variables.dtype), estimate


def _surface_z(lens: Lens, surface: int, x: Array, y: Array) -> Array:
    kind = lens.surface_kind[surface]
    rho2 = jnp.where(kind == 2, 0.0, x * x) + jnp.where(kind == 1, 0.0, y * y)
    sag, _ = _surface_sag_slope(rho2, lens.curvature_per_mm[surface], lens.conic[surface], lens.aspheric_coefficients[surface])
    vertex_z = jnp.sum(lens.thickness_mm[:surface])
    return vertex_z + sag


@eqx.filter_jit
def _evaluate(system: _Kernel, origins: Array, directions: Array, wavelength: Array) -> TraceResult:
    EVALUATIONS[0] += 1
    lens = system.lens
    dtype = origins.dtype
    count = origins.shape[0]
    domain = system.domain
    variables, forward = _entrance_variables(domain, origins, directions, wavelength)
    out, estimated_error = _polynomial_outputs(system, variables)

    entrance_r2 = variables[:, 0] ** 2 + variables[:, 1] ** 2
    field2 = variables[:, 2] ** 2 + variables[:, 3] ** 2
    in_field = forward & (field2 <= 1.0)
    in_band = jnp.abs(variables[:, 4]) <= 1.0
    certainly_clipped = in_field & (entrance_r2 > 1.0)
    grid = np.asarray(_TRUST_GRID)
    cell = jnp.clip(jnp.floor((variables + 1.0) * 0.5 * grid).astype(jnp.int32), 0, grid - 1)
    cell_trusted = system.trust_table[cell[:, 0], cell[:, 1], cell[:, 2], cell[:, 3], cell[:, 4]]
    within_tolerance = jax.lax.stop_gradient(estimated_error) <= system.estimate_limit_mm
    trusted = certainly_clipped | (in_field & in_band & cell_trusted & within_tolerance)

    sensor_xy = out[:, 0:2]
    direction_xy = out[:, 2:4]
    dz = jnp.sqrt(jnp.clip(1.0 - jnp.sum(direction_xy**2, axis=-1), 1e-12, 1.0))
    column = 4
    passes_ok = jnp.ones(count, bool)
    stop_positions = []
    lost_at = jnp.full(count, -1, jnp.int32)
    for _ in range(system.num_stop_passes):
        x, y = out[:, column], out[:, column + 1]
        column += 2
        inside = _inside_iris(x, y, lens.stop_radius_mm, lens.aperture_blades, lens.aperture_rotation_rad)
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

    valid = trusted & ~certainly_clipped & passes_ok
    lost_at = jnp.where(certainly_clipped, 0, lost_at)
    lost_at = jnp.where(trusted, lost_at, -2)
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


def _exact_fallback(system: _Kernel, result: TraceResult, origins, directions, wavelength) -> TraceResult:
    """Re-trace up to ``ceil(fallback_fraction * N)`` untrusted rays exactly (fixed shapes: the
    untrusted rays are gathered into a buffer of that size; any beyond it stay untrusted)."""
    count = origins.shape[0]
    capacity = max(1, math.ceil(system.fallback_fraction * count))
    (index,) = jnp.nonzero(~result.trusted, size=capacity, fill_value=count)
    used = index < count
    take = jnp.where(used, index, 0)
    exact = _trace_events(
        system.lens, origins[take], directions[take], wavelength[take], system.events, system.num_stop_passes,
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


# --------------------------------------------------------------------------- construction


def _widened_lens(lens: Lens) -> Lens:
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


def _trace_samples(lens: Lens, path, domain: PathDomain, variables: np.ndarray, record_events: bool = False) -> TraceResult:
    origins, directions, wavelength = _rays_from_variables(domain, variables)
    events = path_events(lens, path)
    return _trace_events(
        lens, jnp.asarray(origins), jnp.asarray(directions), jnp.asarray(wavelength), jnp.asarray(events),
        _stop_pass_count(events, lens.stop_index), record_events,
    )


def _choose_clip_events(lens: Lens, path, wide: TraceResult, max_clip_events: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Greedy choice of the event rows (not the stop) whose real clear aperture clips the most
    widened-lens rays not already clipped by the iris or a chosen event."""
    events = path_events(lens, path)
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


def _output_matrix(result: TraceResult, clip_rows: Sequence[int], clip_slots: int) -> Array:
    columns = [result.positions[:, 0], result.positions[:, 1], result.directions[:, 0], result.directions[:, 1]]
    for p in range(result.stop_positions.shape[1]):
        columns += [result.stop_positions[:, p, 0], result.stop_positions[:, p, 1]]
    for r in clip_rows:
        columns += [result.event_positions[r, :, 0], result.event_positions[r, :, 1]]
    columns += [jnp.zeros_like(result.throughput)] * (2 * (clip_slots - len(clip_rows)))  # inactive slots
    columns.append(result.throughput)
    return jnp.stack(columns, axis=-1)


def _weighted_least_squares(design: Array, targets: Array, weights: Array, support: Array | None) -> Array:
    """Coefficients minimising sum_i w_i |design_i c - targets_i|^2 per output column (normal
    equations with a tiny ridge, Cholesky); ``support`` (M, O) restricts each column's terms."""
    weighted = design * weights[:, None]
    gram = weighted.T @ design
    scale = jnp.mean(jnp.diag(gram)) + 1e-300
    ridge = 1e-11 * scale
    rhs = weighted.T @ targets
    if support is None:
        factor = jax.scipy.linalg.cho_factor(gram + ridge * jnp.eye(gram.shape[0], dtype=gram.dtype))
        return jax.scipy.linalg.cho_solve(factor, rhs)

    def solve_one(mask, b):
        m = mask.astype(gram.dtype)
        g = gram * m[:, None] * m[None, :] + jnp.diag(1.0 - m) * scale + ridge * jnp.eye(gram.shape[0], dtype=gram.dtype)
        factor = jax.scipy.linalg.cho_factor(g)
        return jax.scipy.linalg.cho_solve(factor, b * m) * m

    return jax.vmap(solve_one, in_axes=(1, 1), out_axes=1)(support, rhs)


def _fit_columns(wide: TraceResult, variables: np.ndarray, exponents: np.ndarray, clip_rows, clip_slots: int, support=None):
    """Least-squares coefficients of every output on exact traces ``wide`` of the widened lens,
    and the error estimator: the sensor columns minus those of the fit without the top degree."""
    design = monomials(jnp.asarray(variables), exponents)
    targets = _output_matrix(wide, clip_rows, clip_slots)
    weights = wide.valid.astype(design.dtype)
    coefficients = _weighted_least_squares(design, targets, weights, support)
    lower = np.flatnonzero(exponents.sum(axis=1) < exponents.sum(axis=1).max())
    lower_support = None if support is None else support[lower][:, :2]
    lower_fit = _weighted_least_squares(design[:, lower], targets[:, :2], weights, lower_support)
    estimator = coefficients[:, :2].at[lower].add(-lower_fit)
    return coefficients, estimator


def refit(system: PathSystem, lens: Lens, fit_rays: int | None = None, seed: int = 0) -> PathSystem:
    """Re-fit the coefficients of a ``"fit"`` system for ``lens`` (same structure: path, terms,
    clipping events, domain, trust table). Differentiable with respect to the lens's arrays, so
    gradients of polynomial outputs with respect to lens parameters can be taken through it."""
    if system.construction != "fit":
        raise ValueError("refit needs a system built with construction='fit'")
    count = fit_rays or system.report.fit_rays
    variables = _sample_variables(count, seed)
    exponents = np.asarray(system.exponents, np.int32)
    wide = _trace_samples(_widened_lens(lens), system.path, system.domain, variables, record_events=bool(system.clip_event_rows))
    coefficients, estimator = _fit_columns(wide, variables, exponents, system.clip_event_rows, system.clip_active.shape[0])
    return eqx.tree_at(lambda s: (s.lens, s.coefficients, s.error_estimator), system, (lens, coefficients, estimator))


# --------------------------------------------------------------------------- validation


def _validate(system: PathSystem, variables: np.ndarray, tolerance_mm: float, max_mismatch: float):
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
    exact = _trace_samples(lens, system.path, system.domain, variables)
    opened = eqx.tree_at(lambda l: (l.semi_aperture_mm, l.stop_radius_mm), lens, (lens.semi_aperture_mm * 0 + 1e6, lens.stop_radius_mm * 0 + 1e6))
    unobstructed = _trace_samples(opened, system.path, system.domain, variables)
    rays = tuple(jnp.asarray(v) for v in _rays_from_variables(system.domain, variables))
    kernel = eqx.tree_at(
        lambda s: (s.trust_table, s.estimate_limit_mm), system, (jnp.ones(_TRUST_GRID, bool), jnp.asarray(jnp.inf))
    ).kernel(fallback="none")
    poly = _evaluate(kernel, *rays)  # the polynomial's answers everywhere in the domain
    estimate = np.asarray(_polynomial_outputs(kernel, jnp.asarray(variables))[1])
    exact_valid = np.asarray(exact.valid)
    poly_valid = np.asarray(poly.valid)
    both = exact_valid & poly_valid
    error = np.linalg.norm(np.asarray(poly.positions)[:, :2] - np.asarray(exact.positions)[:, :2], axis=-1)
    # calibrate the limit on the error estimate: the largest factor whose accepted rays meet the tolerance
    factor = 1.0
    for candidate in (1.5, 2.0, 3.0, 4.0, 6.0, 8.0):
        accepted = error[both & (estimate <= candidate * tolerance_mm)]
        if accepted.size and np.percentile(accepted, 99.5) <= tolerance_mm and accepted.max() <= 2 * tolerance_mm:
            factor = candidate
    estimate_limit_mm = factor * tolerance_mm
    estimate_ok = estimate <= estimate_limit_mm
    grid = np.asarray(_TRUST_GRID)
    cell = np.clip(np.floor((variables + 1.0) * 0.5 * grid).astype(int), 0, grid - 1)
    flat = np.ravel_multi_index(cell.T, _TRUST_GRID)
    size = int(np.prod(grid))
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
    table = trusted.reshape(_TRUST_GRID)
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


# --------------------------------------------------------------------------- build


def _code_version() -> str:
    from . import __version__, _polybasis, _taylor, _trace

    digest = hashlib.sha256()
    for module in (_polybasis, _taylor, _trace):
        digest.update(inspect.getsource(module).encode())
    digest.update(inspect.getsource(inspect.getmodule(_code_version)).encode())
    return f"{__version__}-{CACHE_FORMAT}-{digest.hexdigest()[:16]}"


def _lens_key(lens: Lens) -> str:
    digest = hashlib.sha256()
    for leaf in jax.tree.leaves(lens):
        if eqx.is_array(leaf):
            digest.update(np.ascontiguousarray(np.asarray(leaf, np.float64 if jnp.issubdtype(leaf.dtype, jnp.floating) else np.int64)).tobytes())
    digest.update(repr((lens.stop_index, lens.aperture_blades, lens.interface_surfaces, lens.has_aspheres, lens.zoom_position)).encode())
    return digest.hexdigest()


def default_cache_dir() -> Path:
    """``$JAXFLARE_CACHE_DIR``, else ``$XDG_CACHE_HOME/jaxflare``, else ``~/.cache/jaxflare``."""
    if os.environ.get("JAXFLARE_CACHE_DIR"):
        return Path(os.environ["JAXFLARE_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jaxflare"


def path_system(
    lens: Lens,
    path: GhostPath | None = None,
    *,
    degree: int = DEFAULT_DEGREE,
    construction: Construction = "fit",
    max_field_angle_deg: float | None = None,
    wavelength_range_nm: tuple[float, float] = DEFAULT_WAVELENGTH_RANGE_NM,
    sparse_terms: int | None = None,
    max_clip_events: int = 4,
    fit_rays: int | None = None,
    validation_rays: int = 32768,
    tolerance_mm: float | None = None,
    max_mask_mismatch: float = 0.1,
    fallback: Literal["exact", "none"] = "exact",
    fallback_fraction: float = 0.125,
    cache: bool | str | os.PathLike = True,
    seed: int = 0,
) -> PathSystem:
    """Build (or load from the disk cache) the polynomial system of one path of ``lens``.

    Args:
        lens: the lens; its iris and clear apertures are the ones tested at call time.
        path: ``None`` for the primary path or a ghost path ``(j, i)`` as in :func:`jaxflare.trace`.
        degree: total degree of the polynomials (1 to 9).
        construction: ``"fit"`` (least squares on exact traces over the domain; the default: it is
            accurate across the whole domain) or ``"taylor"`` (expansion about the axis, 2012).
        max_field_angle_deg: largest angle between an incoming ray and the axis; default the lens's
            half field of view. Lights further off-axis need a wider domain.
        wavelength_range_nm: the band the system is built for (default the visible 380-780 nm).
        sparse_terms: keep at most this many terms per output (``"fit"`` only), chosen by the size
            of their contribution, and evaluate only the union of the kept terms.
        max_clip_events: clear apertures (besides the iris) tested per ray; the ones that clip the
            most rays are chosen; rays lost elsewhere show up as ``unmodelled_clip_fraction``.
        fit_rays: exact traces used to fit (default: enough for the number of terms).
        validation_rays: exact traces used to measure the error and build the trust table.
        tolerance_mm: sensor-position error a cell of the domain may have and still be trusted
            (default half a pixel of a 2048-pixel-wide image on the lens's sensor).
        max_mask_mismatch: fraction of a cell's rays whose validity may differ from the exact trace.
        fallback: ``"exact"`` re-traces untrusted rays exactly (up to ``fallback_fraction`` of each
            batch); ``"none"`` returns them invalid. Either way ``result.trusted`` marks them.
        cache: True for :func:`default_cache_dir`, a directory, or False for no cache.
        seed: seed of the fit and validation samples.
    """
    path = _check_path(lens, path)
    if not (isinstance(degree, int) and 1 <= degree <= 9):
        raise ValueError(f"degree must be an integer from 1 to 9, got {degree!r}")
    if construction not in ("fit", "taylor"):
        raise ValueError(f"construction must be 'fit' or 'taylor', got {construction!r}")
    if sparse_terms is not None and (construction != "fit" or not (isinstance(sparse_terms, int) and sparse_terms >= 1)):
        raise ValueError(f"sparse_terms must be a positive integer and needs construction='fit', got {sparse_terms!r} with {construction!r}")
    if fallback not in ("exact", "none"):
        raise ValueError(f"fallback must be 'exact' or 'none', got {fallback!r}")
    if not 0 < fallback_fraction <= 1:
        raise ValueError(f"fallback_fraction must be in (0, 1], got {fallback_fraction}")
    domain = make_domain(lens, max_field_angle_deg, wavelength_range_nm)
    if tolerance_mm is None:
        tolerance_mm = 0.5 * lens.prescription.sensor_width_mm / 2048
    exponents = monomial_exponents(degree)
    if fit_rays is None:
        fit_rays = int(2 ** math.ceil(math.log2(max(4096, 16 * len(exponents)))))
    settings = dict(
        path=path, degree=degree, construction=construction, domain=dataclasses.asdict(domain), sparse_terms=sparse_terms,
        max_clip_events=max_clip_events, fit_rays=fit_rays, validation_rays=validation_rays, tolerance_mm=tolerance_mm,
        max_mask_mismatch=max_mask_mismatch, seed=seed,
    )
    cache_file = None
    if cache:
        directory = default_cache_dir() if cache is True else Path(cache)
        key = hashlib.sha256((_lens_key(lens) + json.dumps(settings, sort_keys=True) + _code_version()).encode()).hexdigest()[:32]
        cache_file = directory / f"path-{key}.npz"
        if cache_file.exists():
            try:
                return _load_cached(cache_file, lens, fallback, fallback_fraction)
            except (OSError, ValueError, KeyError):
                pass  # a damaged cache entry is rebuilt and overwritten
    start = time.perf_counter()
    with jax.enable_x64(True):
        lens64 = _as_float64(lens)
        system = _build(lens64, path, domain, exponents, construction, sparse_terms, max_clip_events, fit_rays, seed, tolerance_mm)
        table, estimate_limit_mm, summary = _validate(system, _sample_variables(validation_rays, seed + 1), tolerance_mm, max_mask_mismatch)
        coefficients = np.asarray(system.coefficients)
        estimator = np.asarray(system.error_estimator)
    report = PathSystemReport(
        construction=construction, degree=degree, num_terms=len(system.exponents), fit_rays=fit_rays,
        validation_rays=validation_rays, clip_surfaces=system.clip_surfaces, tolerance_um=tolerance_mm * 1e3,
        estimate_limit_um=estimate_limit_mm * 1e3,
        build_seconds=time.perf_counter() - start, **summary,
    )
    result = PathSystem(
        lens=lens, coefficients=jnp.asarray(coefficients, lens.curvature_per_mm.dtype), trust_table=jnp.asarray(table),
        path=path, **_structure_arrays(lens, path, system.clip_surfaces, max_clip_events),
        error_estimator=jnp.asarray(estimator, lens.curvature_per_mm.dtype), estimate_limit_mm=jnp.asarray(estimate_limit_mm, lens.curvature_per_mm.dtype), degree=degree, construction=construction, exponents=system.exponents, domain=domain,
        num_stop_passes=system.num_stop_passes, clip_event_rows=system.clip_event_rows, clip_surfaces=system.clip_surfaces,
        report=report, fallback=fallback, fallback_fraction=fallback_fraction,
    )
    if cache_file is not None:
        _save_cached(cache_file, result, coefficients, estimator)
    return result


def _structure_arrays(lens: Lens, path, clip_surfaces: Sequence[int], slots: int) -> dict:
    index = np.zeros(slots, np.int32)
    index[: len(clip_surfaces)] = clip_surfaces
    return dict(
        events=jnp.asarray(path_events(lens, path)), clip_surface_index=jnp.asarray(index),
        clip_active=jnp.asarray(np.arange(slots) < len(clip_surfaces)),
    )


def _build(lens, path, domain, exponents, construction, sparse_terms, max_clip_events, fit_rays, seed, tolerance_mm) -> PathSystem:
    """The polynomial (coefficients, error estimator, clipping events); validated by the caller."""
    events = path_events(lens, path)
    num_passes = _stop_pass_count(events, lens.stop_index)
    variables = _sample_variables(fit_rays, seed)
    wide = _trace_samples(_widened_lens(lens), path, domain, variables, record_events=True)
    clip_rows, clip_surfaces = _choose_clip_events(lens, path, wide, max_clip_events)
    if construction == "fit":
        coefficients, estimator = _fit_columns(wide, variables, exponents, clip_rows, max_clip_events)
        if sparse_terms is not None and sparse_terms < len(exponents):
            design = monomials(jnp.asarray(variables), exponents)
            weights = wide.valid.astype(design.dtype)
            contribution = jnp.abs(coefficients) * jnp.sqrt(jnp.sum(design**2 * weights[:, None], axis=0))[:, None]
            rank = jnp.argsort(-contribution, axis=0)[:sparse_terms]
            support = jnp.zeros(coefficients.shape, bool).at[rank, jnp.arange(coefficients.shape[1])[None, :]].set(True)
            support = support.at[0].set(True)  # always keep the constant term
            used = np.flatnonzero(np.asarray(support).any(axis=1))
            exponents = exponents[used]
            coefficients, estimator = _fit_columns(wide, variables, exponents, clip_rows, max_clip_events, support[used])
    else:
        from ._taylor import taylor_path_coefficients

        series = taylor_path_coefficients(
            lens, path, int(exponents.max(initial=0)) if len(exponents) else 0,
            entrance_z_mm=domain.entrance_z_mm, front_radius_mm=domain.entrance_radius_mm, sin_max_field=domain.sin_max_field,
            wavelength_center_nm=domain.wavelength_center_nm, wavelength_half_width_nm=domain.wavelength_half_width_nm,
            record_event_rows=clip_rows,
        )
        geometric = [series["sensor"][0], series["sensor"][1], series["direction"][0], series["direction"][1]]
        for p in range(num_passes):
            geometric += [series["stop"][p, 0], series["stop"][p, 1]]
        for k in range(len(clip_rows)):
            geometric += [series["events"][k, 0], series["events"][k, 1]]
        geometric += [np.zeros(len(exponents))] * (2 * (max_clip_events - len(clip_rows)))
        # the series carries geometry only: the Fresnel throughput (thin-film interference) is fitted
        design = monomials(jnp.asarray(variables), exponents)
        throughput = _weighted_least_squares(design, wide.throughput[:, None], wide.valid.astype(design.dtype), None)
        coefficients = jnp.concatenate([jnp.asarray(np.stack(geometric, axis=-1)), throughput], axis=-1)
        top = exponents.sum(axis=1) == exponents.sum(axis=1).max()
        estimator = coefficients[:, :2] * jnp.asarray(top, coefficients.dtype)[:, None]  # the truncation term
    return PathSystem(
        lens=lens, coefficients=coefficients, trust_table=jnp.ones(_TRUST_GRID, bool), path=path,
        error_estimator=estimator, estimate_limit_mm=jnp.asarray(tolerance_mm),
        **_structure_arrays(lens, path, clip_surfaces, max_clip_events),
        degree=int(exponents.max(initial=0)), construction=construction, exponents=tuple(map(tuple, np.asarray(exponents).tolist())),
        domain=domain, num_stop_passes=num_passes, clip_event_rows=clip_rows, clip_surfaces=clip_surfaces,
        report=None, fallback="none",
    )


def path_systems(lens: Lens, paths: Sequence[GhostPath | None] | None = None, **options) -> dict:
    """Path systems for several paths (default: every ghost path of ``lens``), keyed by path."""
    from ._trace import ghost_paths

    paths = ghost_paths(lens) if paths is None else list(paths)
    return {path: path_system(lens, path, **options) for path in paths}


# --------------------------------------------------------------------------- cache


def _save_cached(file: Path, system: PathSystem, coefficients: np.ndarray, estimator: np.ndarray) -> None:
    meta = dict(
        path=system.path, degree=system.degree, construction=system.construction, exponents=system.exponents,
        domain=dataclasses.asdict(system.domain), num_stop_passes=system.num_stop_passes,
        clip_event_rows=system.clip_event_rows, clip_surfaces=system.clip_surfaces, report=system.report.as_dict(),
        clip_slots=int(system.clip_active.shape[0]),
    )
    buffer = io.BytesIO()
    np.savez(buffer, coefficients=coefficients, error_estimator=estimator, trust_table=np.asarray(system.trust_table), meta=np.asarray(json.dumps(meta)))
    try:
        write_bytes_atomic(file, buffer.getvalue())
    except OSError:
        pass  # an unwritable cache only costs a rebuild next time


def _load_cached(file: Path, lens: Lens, fallback: str, fallback_fraction: float) -> PathSystem:
    with np.load(file, allow_pickle=False) as data:
        coefficients = data["coefficients"]
        estimator = data["error_estimator"]
        table = data["trust_table"]
        meta = json.loads(str(data["meta"]))
    report = meta["report"]
    report["clip_surfaces"] = tuple(report["clip_surfaces"])
    path = tuple(meta["path"]) if meta["path"] is not None else None
    dtype = lens.curvature_per_mm.dtype
    return PathSystem(
        **_structure_arrays(lens, path, meta["clip_surfaces"], meta["clip_slots"]),
        error_estimator=jnp.asarray(estimator, dtype), estimate_limit_mm=jnp.asarray(meta["report"]["estimate_limit_um"] * 1e-3, dtype),
        lens=lens, coefficients=jnp.asarray(coefficients, lens.curvature_per_mm.dtype), trust_table=jnp.asarray(table, bool),
        path=path, degree=meta["degree"], construction=meta["construction"],
        exponents=tuple(tuple(e) for e in meta["exponents"]), domain=PathDomain(**meta["domain"]),
        num_stop_passes=meta["num_stop_passes"], clip_event_rows=tuple(meta["clip_event_rows"]),
        clip_surfaces=tuple(meta["clip_surfaces"]), report=PathSystemReport(**report), fallback=fallback,
        fallback_fraction=fallback_fraction,
    )
