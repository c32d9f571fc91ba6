"""Fresnel reflectance of an interface carrying a thin-film coating stack.

Method: the characteristic (transfer) matrix of a stack of homogeneous, isotropic thin films,
H. A. Macleod, *Thin-Film Optical Filters* (4th ed., CRC Press, 2010), ch. 2. Each layer ``j``
has the matrix ``[[cos d_j, i sin d_j / eta_j], [i eta_j sin d_j, cos d_j]]`` with phase thickness
``d_j = 2 pi n_j cos(theta_j) t_j / lambda``; ``[B, C] = M_1 ... M_L [1, eta_sub]`` and the
amplitude reflectance is ``r = (eta_0 B - C) / (eta_0 B + C)``. Tilted admittances (in units of
the free-space admittance): ``eta_s = n cos(theta)``, ``eta_p = n / cos(theta)``.

Conventions and units:

- All refractive indices are real (lossless, non-absorbing media), so transmittance is ``1 - R``.
- ``cos_incident`` is the cosine of the angle of incidence in the incident medium, in ``[0, 1]``
  (1 = normal incidence, 0 = grazing); values outside are clamped.
- ``wavelength_nm`` (vacuum wavelength) and ``layer_thicknesses_nm`` (physical thickness) are in
  nanometres; only their ratio matters.
- ``layer_indices`` / ``layer_thicknesses_nm`` have shape ``(..., L)`` (``L`` may be 0), ordered in
  the order the incident light meets them. A zero-thickness layer is an exact identity, so stacks
  can be padded to a common ``L``.
- Reflectances are power (intensity) reflectances; the unpolarised value is ``(R_s + R_p) / 2``.
- All arguments broadcast against each other (the layer arrays over their leading dimensions).

Numerics. Everything is written in terms of the Snell invariant ``Q_j = (n_j cos theta_j)^2 =
n_j^2 - n_0^2 sin^2 theta_0``, which is real. The layer entries ``cos d`` and ``sin d / d`` are
entire functions of ``d^2 = (2 pi t / lambda)^2 Q_j`` and are evaluated in real arithmetic:
trigonometric for propagating layers, hyperbolic for evanescent ones (there the matrix is divided
by ``cosh|d|``, which leaves ``r`` unchanged and prevents overflow), a Taylor series near ``d = 0``.
Only the substrate needs ``q_s = n_s cos theta_s = sqrt(Q_s)``, taken with ``Im q_s >= 0`` (the
decaying wave under total internal reflection, where ``R = 1``). The ``p`` admittances ``n^2 / q``
are used with denominators cleared, so normal incidence, grazing incidence and the critical angle
are regular points. At the critical angle the true derivative of ``R`` is infinite (and very large
within a few ulps of it); exactly there the square root's derivative is taken as 0, so gradients
stay finite. Exactly at grazing incidence on an index-matched bare interface ``R`` is 0/0 and
returned as 0. The public functions are jitted and compose with ``jax.grad``/``jit``/``vmap``.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

__all__ = [
    "coated_reflectance",
    "coated_reflectance_sp",
    "schlick_reflectance",
    "uncoated_reflectance",
]

_SERIES_BELOW = 1e-3  # |d^2| below which cos d and sin d / d use their Taylor series


def _sqrt_pos(x):
    """``sqrt(max(x, 0))`` with a finite gradient everywhere (zero where ``x`` is 0 or subnormal).

    ``abs`` guards against XLA recomputing ``x`` with different rounding (FMA) on the other side of 0."""
    pos = x > jnp.finfo(x.dtype).tiny
    return jnp.where(pos, jnp.sqrt(jnp.abs(jnp.where(pos, x, 1.0))), 0.0)


def _cos_sinc(x):
    """``(cos d, sin d / d)`` for real ``x = d^2``, both divided by ``cosh|d|`` when ``x < 0``."""
    small = jnp.abs(x) < _SERIES_BELOW
    xs = jnp.where(small, x, 0.0)
    c_series = 1 - xs / 2 * (1 - xs / 12 * (1 - xs / 30))
    s_series = 1 - xs / 6 * (1 - xs / 20 * (1 - xs / 42))
    y = jnp.sqrt(jnp.where(small, 1.0, jnp.abs(x)))
    c = jnp.where(small, c_series, jnp.where(x > 0, jnp.cos(y), 1.0))
    s = jnp.where(small, s_series, jnp.where(x > 0, jnp.sin(y), jnp.tanh(y)) / y)
    return c, s


def _reflectance_sp(n_incident, n_substrate, cos_incident, wavelength_nm, layer_indices, layer_thicknesses_nm):
    """``(R_s, R_p)``, unjitted (the public functions jit it; the tracer inlines it)."""
    args = (n_incident, n_substrate, cos_incident, wavelength_nm, layer_indices, layer_thicknesses_nm)
    dtype = jnp.result_type(float, *(jnp.asarray(a) for a in args))
    n0, ns, c0, lam, nl, tl = (jnp.asarray(a, dtype) for a in args)
    if nl.ndim == 0 or tl.ndim == 0:
        raise ValueError("layer_indices and layer_thicknesses_nm need a trailing layer axis")
    batch = jnp.broadcast_shapes(n0.shape, ns.shape, c0.shape, lam.shape, nl.shape[:-1], tl.shape[:-1])
    n_layers = jnp.broadcast_shapes(nl.shape[-1:], tl.shape[-1:])[0]
    n0, ns, c0, lam = (jnp.broadcast_to(a, batch) for a in (n0, ns, c0, lam))
    nl, tl = (jnp.broadcast_to(a, batch + (n_layers,)) for a in (nl, tl))

    c0 = jnp.where(c0 > 1, 1.0, jnp.where(c0 < 0, 0.0, c0))
    q0 = n0 * c0  # n_0 cos(theta_0)
    # Q = (n cos theta)^2 = n^2 - n_0^2 + q_0^2: exact when n == n_0, accurate near grazing.
    q_sub2 = (ns - n0) * (ns + n0) + q0**2
    u, v = _sqrt_pos(q_sub2), _sqrt_pos(-q_sub2)  # q_sub = u + i v, Im >= 0: decaying branch
    q_lay2 = (nl - n0[..., None]) * (nl + n0[..., None]) + q0[..., None] ** 2
    beta = (2 * math.pi) * tl / lam[..., None]  # 2 pi t / lambda
    cos_d, sinc_d = _cos_sinc(beta**2 * q_lay2)
    bs = beta * sinc_d  # sin(d) / q
    # Leading axis (s, p). Layer matrices [[cos d, i a], [i b, cos d]] with a = sin(d) / eta and
    # b = eta sin(d); eta_s = q, eta_p = n^2 / q.
    a = jnp.stack([bs, bs * q_lay2 / nl**2])
    b = jnp.stack([q_lay2 * bs, nl**2 * bs])
    zero, one = jnp.zeros_like(u), jnp.ones_like(u)
    # D_sub [B, C] = M_1 ... M_L [D_sub, N_sub] (real, imaginary parts), where eta_sub =
    # N_sub / D_sub is q_s / 1 (s) or n_s^2 / q_s (p).
    xr, xi = jnp.stack([one, u]), jnp.stack([zero, v])
    yr, yi = jnp.stack([u, ns**2]), jnp.stack([v, zero])
    # the layers from the substrate outwards, unrolled (the count is static and small), so that
    # XLA fuses the whole stack into the tracer's loop
    for j in reversed(range(n_layers)):
        c, aj, bj = cos_d[..., j], a[..., j], b[..., j]
        xr, xi, yr, yi = c * xr - aj * yi, c * xi + aj * yr, c * yr - bj * xi, c * yi + bj * xr
    # r = (eta_0 B - C) / (eta_0 B + C) with eta_0 = N_0 / D_0 (s: q_0 / 1, p: n_0^2 / q_0).
    n_0, d_0 = jnp.stack([q0, n0**2]), jnp.stack([one, q0])
    num2 = (n_0 * xr - d_0 * yr) ** 2 + (n_0 * xi - d_0 * yi) ** 2
    den2 = (n_0 * xr + d_0 * yr) ** 2 + (n_0 * xi + d_0 * yi) ** 2
    ok = den2 > 0  # den2 == 0 only for 0/0: grazing incidence on an index-matched bare interface
    r = jnp.where(ok, num2 / jnp.where(ok, den2, 1.0), 0.0)
    return r[0], r[1]


@jax.jit
def coated_reflectance_sp(
    n_incident, n_substrate, cos_incident, wavelength_nm, layer_indices, layer_thicknesses_nm
):
    """Return ``(R_s, R_p)`` of a coated interface; see the module docstring for conventions."""
    return _reflectance_sp(n_incident, n_substrate, cos_incident, wavelength_nm, layer_indices, layer_thicknesses_nm)


def unpolarised_reflectance(n_incident, n_substrate, cos_incident, wavelength_nm, layer_indices, layer_thicknesses_nm):
    """:func:`coated_reflectance`, unjitted (for the tracer's loop)."""
    r_s, r_p = _reflectance_sp(n_incident, n_substrate, cos_incident, wavelength_nm, layer_indices, layer_thicknesses_nm)
    return 0.5 * (r_s + r_p)


@jax.jit
def coated_reflectance(
    n_incident, n_substrate, cos_incident, wavelength_nm, layer_indices, layer_thicknesses_nm
):
    """Unpolarised reflectance ``(R_s + R_p) / 2`` of a coated interface."""
    r_s, r_p = coated_reflectance_sp(
        n_incident, n_substrate, cos_incident, wavelength_nm, layer_indices, layer_thicknesses_nm
    )
    return 0.5 * (r_s + r_p)


@jax.jit
def uncoated_reflectance(n_incident, n_substrate, cos_incident):
    """Unpolarised Fresnel reflectance of a bare interface (the zero-layer case)."""
    args = (n_incident, n_substrate, cos_incident)
    empty = jnp.zeros((0,), jnp.result_type(float, *(jnp.asarray(a) for a in args)))
    return coated_reflectance(n_incident, n_substrate, cos_incident, 550.0, empty, empty)


@jax.jit
def schlick_reflectance(r0, cos_incident):
    """Schlick's approximation ``R0 + (1 - R0) (1 - cos)^5`` (normal-incidence ``R0``)."""
    r0 = jnp.asarray(r0)
    return r0 + (1 - r0) * (1 - jnp.asarray(cos_incident)) ** 5
