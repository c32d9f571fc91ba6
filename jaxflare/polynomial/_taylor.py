"""Taylor expansion of the exact ray trace about the optical axis ("Polynomial Optics", Hullin,
Hanika and Heidrich 2012).

The sequential trace of :mod:`jaxflare.optics._trace` is repeated surface by surface on truncated
multivariate power series (TPS, "differential algebra") in the five normalised entrance variables
``(u, v, s, t, w)`` of :mod:`jaxflare.polynomial._basis`, expanded at zero: the on-axis ray at the centre
wavelength. Every intermediate quantity (intersection distance, normal, index, direction) is a
series truncated at total degree ``degree``, so the outputs are the exact Taylor polynomials of the
traced ray's coordinates, not fits. Arithmetic is NumPy float64; a series is a coefficient array
``(..., M)`` in :func:`monomial_exponents` order, leading axes batch several series (3-vectors).

Clipping by apertures and the iris, and Fresnel factors, are not polynomial and are left out.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np

from ..optics import BEHIND_TOLERANCE_MM, EventAction, GhostPath, Lens, path_events
from ._basis import NUM_VARIABLES, monomial_exponents


class _SeriesAlgebra:
    """Products and power functions of truncated power series in five variables."""

    def __init__(self, degree: int):
        self.degree = degree
        exponents = monomial_exponents(degree).astype(np.int64)
        self.size = len(exponents)
        total = exponents.sum(axis=1)
        left, right = np.nonzero(total[:, None] + total[None, :] <= degree)
        code_weights = (degree + 1) ** np.arange(NUM_VARIABLES, dtype=np.int64)
        codes = exponents @ code_weights
        code_order = np.argsort(codes)
        product = code_order[np.searchsorted(codes[code_order], (exponents[left] + exponents[right]) @ code_weights)]
        order = np.argsort(product, kind="stable")
        self._left, self._right = left[order], right[order]
        self._starts = np.searchsorted(product[order], np.arange(self.size))
        units = np.eye(NUM_VARIABLES, dtype=np.int64)
        self.variable_index = [int(np.flatnonzero((exponents == unit).all(axis=1))[0]) for unit in units]

    def constant(self, value) -> np.ndarray:
        """The constant series ``value`` (scalar or array of values, one series each)."""
        value = np.asarray(value, np.float64)
        out = np.zeros(value.shape + (self.size,))
        out[..., 0] = value
        return out

    def variable(self, k: int, scale: float, offset: float = 0.0) -> np.ndarray:
        """``offset + scale * x_k`` for the k-th entrance variable."""
        out = self.constant(offset)
        out[self.variable_index[k]] = scale
        return out

    def mul(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Truncated product, broadcast over leading axes."""
        return np.add.reduceat(a.take(self._left, axis=-1) * b.take(self._right, axis=-1), self._starts, axis=-1)

    def power(self, a: np.ndarray, exponent: float) -> np.ndarray:
        """``a ** exponent`` for a constant term > 0 (any non-zero one for an integer exponent):
        ``a0^p (1 + x)^p = a0^p sum_k binom(p, k) x^k`` with the nilpotent ``x = a / a0 - 1``,
        summed by Horner's rule up to x^degree (higher powers vanish)."""
        a0 = a[..., :1]
        x = a / a0
        x[..., 0] = 0.0
        binomial = [1.0]
        for k in range(1, self.degree + 1):
            binomial.append(binomial[-1] * (exponent - k + 1) / k)
        series = binomial[-1] * x
        for k in range(self.degree - 1, 0, -1):
            series[..., 0] += binomial[k]
            series = self.mul(x, series)
        series[..., 0] += 1.0
        return a0**exponent * series

    def reciprocal(self, a: np.ndarray) -> np.ndarray:
        return self.power(a, -1.0)

    def horner(self, x: np.ndarray, coefficients: Sequence[float]) -> np.ndarray:
        """Polynomial ``sum_k coefficients[k] x^k`` of a series ``x``."""
        out = self.constant(coefficients[-1])
        for c in coefficients[-2::-1]:
            out = self.mul(x, out)
            out[..., 0] += c
        return out


@functools.lru_cache(maxsize=None)
def _algebra(degree: int) -> _SeriesAlgebra:
    return _SeriesAlgebra(degree)


def _newton_steps(degree: int) -> int:
    """Newton steps on an asphere after the conic start: that start errs by O(rho^4) (the A4 rho^4
    term), i.e. it is exact to degree 3, and each series Newton step doubles the number of exact
    orders plus one (3 -> 7 -> 15)."""
    steps, exact = 0, 3
    while exact < degree:
        steps, exact = steps + 1, 2 * exact + 1
    return steps


class _PathTrace:
    """One path's trace on series; raises ``ValueError`` where the on-axis ray is not valid."""

    def __init__(
        self,
        lens: Lens,
        path: GhostPath | None,
        algebra: _SeriesAlgebra,
        wavelength_center_nm: float,
        wavelength_half_width_nm: float,
    ):
        self.lens, self.algebra = lens, algebra
        self.label = f"primary path of '{lens.name}'" if path is None else f"ghost path {tuple(path)} of '{lens.name}'"
        self.curvature = np.asarray(lens.curvature_per_mm, np.float64)
        self.conic = np.asarray(lens.conic, np.float64)
        self.aspheric = np.asarray(lens.aspheric_coefficients, np.float64)
        self.kind = np.asarray(lens.surface_kind)
        self.vertex_z = lens.vertex_z_mm
        indices = self._media_indices(wavelength_center_nm, wavelength_half_width_nm)
        # index ratio n_before / n_after at each surface, (num_surfaces, M) series, travelling +z / -z
        before, after = np.concatenate([indices[:-1], indices[1:]]), np.concatenate([indices[1:], indices[:-1]])
        ratios = algebra.mul(before, algebra.reciprocal(after))
        self.eta_forward, self.eta_backward = np.split(ratios, 2)
        b, c = np.asarray(lens.sellmeier_b, np.float64), np.asarray(lens.sellmeier_c_um2, np.float64)
        air = np.asarray(lens.medium_is_air)
        self.same_medium = [
            bool(air[m] == air[m + 1] and np.array_equal(b[m], b[m + 1]) and np.array_equal(c[m], c[m + 1]))
            for m in range(lens.num_surfaces)
        ]

    def _media_indices(self, center_nm: float, half_width_nm: float) -> np.ndarray:
        """(num_media, M) Sellmeier index of every medium as a series in w (air exactly 1):
        n^2 = 1 + sum_i B_i lambda^2 / (lambda^2 - C_i), lambda = (center + half_width w) / 1000 um."""
        alg = self.algebra
        b = np.asarray(self.lens.sellmeier_b, np.float64)
        c = np.asarray(self.lens.sellmeier_c_um2, np.float64)
        wavelength_um = alg.variable(4, half_width_nm * 1e-3, center_nm * 1e-3)
        lam2 = alg.mul(wavelength_um, wavelength_um)
        terms = alg.mul(lam2, alg.reciprocal(lam2 - alg.constant(c)))
        index = alg.power(alg.constant(1.0) + np.sum(b[..., None] * terms, axis=1), 0.5)
        return np.where(np.asarray(self.lens.medium_is_air)[:, None], alg.constant(1.0), index)

    def invalid(self, surface: int, why: str) -> ValueError:
        return ValueError(f"{self.label}: the on-axis ray {why} surface {surface}; it cannot be Taylor-expanded")

    def intersect(self, position: np.ndarray, direction: np.ndarray, surface: int) -> tuple[np.ndarray, np.ndarray]:
        """Hit point (3, M) in mm and unit normal (3, M) facing -z at the vertex, as in
        ``jaxflare.optics.intersect``: the first root ahead of the ray on the vertex sheet, chosen by the
        constant terms, then (aspheres) Newton steps from that conic root."""
        alg = self.algebra
        c, k1 = self.curvature[surface], 1.0 + self.conic[surface]
        wx = 0.0 if self.kind[surface] == 2 else 1.0
        wy = 0.0 if self.kind[surface] == 1 else 1.0
        relative = position - alg.constant([0.0, 0.0, self.vertex_z[surface]])
        p, d = relative, direction
        pp, pd, dd = alg.mul(np.stack([p, p, d]), np.stack([p, d, d]))
        a = c * (wx * dd[0] + wy * dd[1]) + k1 * c * dd[2]
        b = c * (wx * pd[0] + wy * pd[1]) - d[2] + k1 * c * pd[2]
        g = c * (wx * pp[0] + wy * pp[1]) - 2.0 * p[2] + k1 * c * pp[2]
        bb, ag = alg.mul(np.stack([b, a]), np.stack([b, g]))
        disc = bb - ag
        if not disc[0] > 0.0:
            raise self.invalid(surface, "misses")
        q = -(b + math.copysign(1.0, b[0]) * alg.power(disc, 0.5))
        candidates = []  # (constant term of the distance, numerator, denominator)
        if q[0] != 0.0:
            candidates.append((g[0] / q[0], g, q))
        if a[0] != 0.0:
            candidates.append((q[0] / a[0], q, a))
        usable = [
            cand for cand in candidates if cand[0] >= -BEHIND_TOLERANCE_MM and k1 * c * (p[2, 0] + cand[0] * d[2, 0]) <= 1.0
        ]
        if not usable:
            raise self.invalid(surface, "has no intersection ahead on the vertex sheet of")
        _, numerator, denominator = min(usable, key=lambda cand: cand[0])
        distance = alg.mul(numerator, alg.reciprocal(denominator))
        point = relative + alg.mul(distance, direction)
        coefficients = self.aspheric[surface]
        if np.any(coefficients != 0.0):
            for _ in range(_newton_steps(alg.degree)):
                sag, slope, xy = self._sag_slope(point, surface, wx, wy)
                along = alg.mul(xy, d[:2])
                rate = d[2] - alg.mul(slope, wx * along[0] + wy * along[1])
                distance = distance - alg.mul(point[2] - sag, alg.reciprocal(rate))
                point = relative + alg.mul(distance, direction)
            _, slope, xy = self._sag_slope(point, surface, wx, wy)
            normal = np.stack([wx * alg.mul(xy[0], slope), wy * alg.mul(xy[1], slope), -alg.constant(1.0)])
        else:  # half the gradient of the quadric c rho^2 - 2 z + (1 + k) c z^2
            normal = np.stack([wx * c * point[0], wy * c * point[1], k1 * c * point[2] - alg.constant(1.0)])
        norm2 = np.sum(alg.mul(normal, normal), axis=0)
        normal = alg.mul(normal, alg.power(norm2, -0.5))
        return point + alg.constant([0.0, 0.0, self.vertex_z[surface]]), normal

    def _sag_slope(self, point: np.ndarray, surface: int, wx: float, wy: float):
        """Sag z(rho^2) in mm and g = (dz/drho)/rho in 1/mm of a conic plus even asphere at a
        point (relative to the vertex), and the point's (x, y)."""
        alg = self.algebra
        c, k1 = self.curvature[surface], 1.0 + self.conic[surface]
        xy = point[:2]
        squares = alg.mul(xy, xy)
        rho2 = wx * squares[0] + wy * squares[1]
        root = alg.power(alg.constant(1.0) - k1 * c * c * rho2, 0.5)
        sag = alg.mul(c * rho2, alg.reciprocal(alg.constant(1.0) + root))
        slope = c * alg.reciprocal(root)
        coefficients = np.trim_zeros(self.aspheric[surface], "b")  # A4 rho^4 + A6 rho^6 + ... = rho^4 (A4 + A6 rho^2 + ...)
        sag = sag + alg.mul(alg.mul(rho2, rho2), alg.horner(rho2, coefficients))
        orders = np.arange(2, len(coefficients) + 2)
        slope = slope + alg.mul(rho2, alg.horner(rho2, 2 * orders * coefficients))
        return sag, slope, xy

    def deflect(self, direction: np.ndarray, normal: np.ndarray, surface: int, travel: int, action: int) -> np.ndarray:
        """Direction after reflecting or refracting (vector Snell law) at the surface."""
        alg = self.algebra
        if action != EventAction.REFLECT and self.same_medium[surface]:
            return direction  # a stop or dummy surface inside one medium
        cos_in = -np.sum(alg.mul(normal, direction), axis=0)
        if cos_in[0] < 0.0:
            normal, cos_in = -normal, -cos_in
        if action == EventAction.REFLECT:
            return direction + 2.0 * alg.mul(cos_in, normal)
        eta = self.eta_forward[surface] if travel > 0 else self.eta_backward[surface]
        eta2, cos2 = alg.mul(np.stack([eta, cos_in]), np.stack([eta, cos_in]))
        k = alg.constant(1.0) - alg.mul(eta2, alg.constant(1.0) - cos2)
        if not k[0] > 0.0:
            raise self.invalid(surface, "is totally internally reflected at")
        scaled = alg.mul(eta, np.concatenate([direction, cos_in[None]]))
        return scaled[:3] + alg.mul(scaled[3] - alg.power(k, 0.5), normal)


def taylor_path_coefficients(
    lens: Lens,
    path: GhostPath | None,
    degree: int,
    *,
    entrance_z_mm: float,
    front_radius_mm: float,
    sin_max_field: float,
    wavelength_center_nm: float,
    wavelength_half_width_nm: float,
    record_event_rows: Sequence[int] = (),
) -> dict[str, np.ndarray]:
    """Taylor coefficients of a path's ray trace in the normalised entrance variables.

    A ray crosses the plane ``z = entrance_z_mm`` at ``(R u, R v)`` (R = ``front_radius_mm``) with
    direction ``(S s, S t, sqrt(1 - S^2 (s^2 + t^2)))`` (S = ``sin_max_field``) and wavelength
    ``wavelength_center_nm + wavelength_half_width_nm * w``; it is traced exactly as
    :func:`jaxflare.trace` does (no clipping, no Fresnel) on power series truncated at total degree
    ``degree``, expanded at the on-axis ray of the centre wavelength.

    Args:
        lens: the lens; path: ``None`` (primary) or a ghost path ``(j, i)``.
        degree: total degree of the expansion (>= 1).
        record_event_rows: indices into ``path_events(lens, path)`` whose hit points to return.

    Returns:
        float64 coefficient arrays in :func:`monomial_exponents` ``(degree)`` order, M monomials:
        ``"sensor"`` (2, M) x, y in mm on the plane ``z = lens.sensor_z_mm``; ``"direction"``
        (2, M) x, y of the unit direction there; ``"stop"`` (P, 2, M) x, y in mm at each of the P
        passes through the stop surface; ``"events"`` (K, 2, M) x, y in mm at the recorded rows.

    Raises:
        ValueError: if the on-axis ray misses a surface, meets it behind itself or only on its far
            sheet, is totally internally reflected, or does not reach the sensor plane.
    """
    if degree < 1:
        raise ValueError(f"degree must be >= 1, got {degree}")
    events = path_events(lens, path)
    active = events[:, 3] == 1
    for row in record_event_rows:
        if not (0 <= row < len(events) and active[row]):
            raise ValueError(f"record_event_rows: {row} is not an active event row of the path (0 .. {int(active.sum()) - 1})")
    alg = _algebra(int(degree))
    tracer = _PathTrace(lens, path, alg, wavelength_center_nm, wavelength_half_width_nm)

    dx, dy = alg.variable(2, sin_max_field), alg.variable(3, sin_max_field)
    dz = alg.power(alg.constant(1.0) - np.sum(alg.mul(np.stack([dx, dy]), np.stack([dx, dy])), axis=0), 0.5)
    direction = np.stack([dx, dy, dz])
    position = np.stack([alg.variable(0, front_radius_mm), alg.variable(1, front_radius_mm), alg.constant(entrance_z_mm)])
    stop_points, event_points = [], {}
    for row, (surface, travel, action, _) in enumerate(events[active]):
        position, normal = tracer.intersect(position, direction, int(surface))
        direction = tracer.deflect(direction, normal, int(surface), int(travel), int(action))
        if surface == lens.stop_index:
            stop_points.append(position[:2])
        event_points[row] = position[:2]

    if not direction[2, 0] > 0.0:
        raise tracer.invalid(lens.num_surfaces - 1, "does not travel towards the sensor after")
    sensor_z = float(np.asarray(lens.sensor_z_mm, np.float64))
    distance = alg.mul(alg.constant(sensor_z) - position[2], alg.reciprocal(direction[2]))
    sensor = position[:2] + alg.mul(distance, direction[:2])
    return {
        "sensor": sensor,
        "direction": direction[:2].copy(),
        "stop": np.stack(stop_points),  # every path crosses every surface, the stop too
        "events": np.array([event_points[row] for row in record_event_rows]).reshape(-1, 2, alg.size),
    }
