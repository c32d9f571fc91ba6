"""How a path system's polynomial is made: least squares on exact traces, or a Taylor expansion.

Both take the same fit samples (:class:`~jaxflare.polynomial._least_squares.FitSamples`) and return
the coefficient matrix (one column per output: sensor x, y; direction x, y; stop x, y per pass;
x, y at each clipping event; throughput), the error estimator (the sensor outputs minus their
degree-(d - 1) counterpart) and the exponents kept.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._basis import monomials
from ._least_squares import fit_columns, weighted_least_squares
from ._system import AUXILIARY_DEGREE, precise_columns


class AbstractConstruction(eqx.Module):
    """A way to make a path system's polynomial from its fit samples."""

    name: ClassVar[str]

    @abc.abstractmethod
    def coefficients(self, lens, path, domain, exponents: np.ndarray, samples) -> tuple:
        """``(coefficients (M, O), error estimator (M, 2), exponents (M, 5))`` for ``path``."""


class LeastSquaresConstruction(AbstractConstruction):
    """Least squares against exact float64 traces sampled over the domain the scene needs (as in
    lentil and Schrade et al. 2016): accurate across the whole domain. With ``sparse_terms``, each
    output keeps at most that many terms, chosen by the size of their contribution over the
    samples, and only the union of the kept terms is evaluated."""

    name: ClassVar[str] = "least-squares"
    sparse_terms: int | None = eqx.field(static=True, default=None)

    def coefficients(self, lens, path, domain, exponents, samples):
        coefficients, estimator = fit_columns(samples.traced, samples.variables, exponents, samples.clip_rows, samples.clip_slots)
        if self.sparse_terms is not None and self.sparse_terms < len(exponents):
            design = monomials(jnp.asarray(samples.variables), exponents)
            weights = samples.traced.valid.astype(design.dtype)
            contribution = jnp.abs(coefficients) * jnp.sqrt(jnp.sum(design**2 * weights[:, None], axis=0))[:, None]
            rank = jnp.argsort(-contribution, axis=0)[: self.sparse_terms]
            support = jnp.zeros(coefficients.shape, bool).at[rank, jnp.arange(coefficients.shape[1])[None, :]].set(True)
            support = support.at[0].set(True)  # always keep the constant term
            used = np.flatnonzero(np.asarray(support).any(axis=1))
            exponents = exponents[used]
            coefficients, estimator = fit_columns(
                samples.traced, samples.variables, exponents, samples.clip_rows, samples.clip_slots, support[used]
            )
        return coefficients, estimator, exponents


class TaylorConstruction(AbstractConstruction):
    """The truncated Taylor expansion about the optical axis at the band's centre wavelength,
    composed surface by surface (Hullin, Hanika & Heidrich 2012; :mod:`._taylor`). It carries the
    geometry only: the Fresnel throughput (thin-film interference) is fitted by least squares."""

    name: ClassVar[str] = "taylor"

    def coefficients(self, lens, path, domain, exponents, samples):
        from ._taylor import taylor_path_coefficients

        clip_rows, num_passes = samples.clip_rows, samples.num_stop_passes
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
        geometric += [np.zeros(len(exponents))] * (2 * (samples.clip_slots - len(clip_rows)))
        totals = exponents.sum(axis=1)
        low = np.flatnonzero(totals <= AUXILIARY_DEGREE)
        design = monomials(jnp.asarray(samples.variables), exponents[low])
        wide = samples.traced
        throughput = weighted_least_squares(design, wide.throughput[:, None], wide.valid.astype(design.dtype), None)
        coefficients = jnp.asarray(np.stack(geometric + [np.zeros(len(exponents))], axis=-1))
        coefficients = coefficients.at[low, -1:].set(throughput)
        auxiliary = np.setdiff1d(np.arange(coefficients.shape[1]), precise_columns(num_passes))
        coefficients = coefficients.at[np.flatnonzero(totals > AUXILIARY_DEGREE)[:, None], auxiliary[None, :]].set(0.0)
        top = totals == totals.max()
        estimator = coefficients[:, :2] * jnp.asarray(top, coefficients.dtype)[:, None]  # the truncation term
        return coefficients, estimator, exponents


CONSTRUCTION_NAMES = ("least-squares", "taylor")
"""``construction=`` strings :func:`~jaxflare.path_system` takes (``"fit"`` is accepted as the
former name of ``"least-squares"``)."""


def construction_from(construction, sparse_terms: int | None = None) -> AbstractConstruction:
    """An :class:`AbstractConstruction` from ``path_system``'s arguments (a name or an instance)."""
    if isinstance(construction, AbstractConstruction):
        if sparse_terms is not None:
            raise ValueError("sparse_terms: give it to LeastSquaresConstruction(sparse_terms=...) itself, not beside it")
        return construction
    if construction == "fit":
        construction = "least-squares"
    if construction not in CONSTRUCTION_NAMES:
        raise ValueError(f"construction must be one of {', '.join(repr(c) for c in CONSTRUCTION_NAMES)} or an AbstractConstruction, got {construction!r}")
    if sparse_terms is not None and (construction != "least-squares" or not (isinstance(sparse_terms, int) and sparse_terms >= 1)):
        raise ValueError(f"sparse_terms must be a positive integer and needs construction='least-squares', got {sparse_terms!r} with {construction!r}")
    if construction == "taylor":
        return TaylorConstruction()
    return LeastSquaresConstruction(sparse_terms)
