"""Monomial basis shared by both path-system constructions.

A path system maps five normalised entrance variables ``(u, v, s, t, w)`` to its outputs through
polynomials in the monomials ``u^a v^b s^c t^d w^e`` with ``a + b + c + d + e <= degree``:

- ``u, v``: ray position on the entrance plane divided by the front clear semi-aperture;
- ``s, t``: x and y direction cosines divided by the sine of the domain's largest field angle;
- ``w``: (wavelength - centre) / half-width of the domain's wavelength band.

The ordering of :func:`monomial_exponents` is the contract between the Taylor expansion, the
least-squares fit and the evaluator.
"""

from __future__ import annotations

import functools
import itertools

import jax.numpy as jnp
import numpy as np

NUM_VARIABLES = 5
VARIABLE_NAMES = ("u", "v", "s", "t", "w")


@functools.lru_cache(maxsize=None)
def monomial_exponents(degree: int, num_variables: int = NUM_VARIABLES) -> np.ndarray:
    """(M, num_variables) int exponents of every monomial of total degree <= ``degree``.

    Sorted by total degree, then lexicographically with the first variable's exponent falling;
    M = C(degree + num_variables, num_variables) (792 for five variables at degree 7).
    """
    if degree < 0:
        raise ValueError(f"degree must be >= 0, got {degree}")
    rows = [
        exps
        for total in range(degree + 1)
        for exps in sorted(
            (e for e in itertools.product(range(total + 1), repeat=num_variables) if sum(e) == total), reverse=True
        )
    ]
    out = np.asarray(rows, dtype=np.int32)
    out.setflags(write=False)
    return out


def monomials_numpy(variables: np.ndarray, exponents: np.ndarray) -> np.ndarray:
    """(N, M) monomial values in float64 (NumPy), for building and validating systems."""
    degree = int(exponents.max(initial=0))
    table = [np.ones_like(variables)]
    for _ in range(degree):
        table.append(table[-1] * variables)
    powers = np.stack(table, axis=-1)  # (N, V, D+1)
    out = np.ones((variables.shape[0], exponents.shape[0]))
    for k in range(variables.shape[1]):
        out *= powers[:, k, exponents[:, k]]
    return out


def monomial_rows(variables: jnp.ndarray, exponents: np.ndarray) -> jnp.ndarray:
    """(M, N) monomial values (JAX), one row per term: power tables of each variable (exact and
    differentiable for negative values too), gathered by row and multiplied. Rows keep each
    term's values contiguous, which is several times faster on a CPU than (N, M) columns."""
    exponents = np.asarray(exponents)
    degree = int(exponents.max(initial=0))
    by_variable = variables.T  # (V, N)
    powers = [jnp.ones_like(by_variable)]
    for _ in range(degree):
        powers.append(powers[-1] * by_variable)
    table = jnp.stack(powers, axis=1)  # (V, D+1, N)
    out = table[0, exponents[:, 0]]
    for k in range(1, by_variable.shape[0]):
        out = out * table[k, exponents[:, k]]
    return out


def monomials(variables: jnp.ndarray, exponents: np.ndarray) -> jnp.ndarray:
    """(N, M) monomial values (JAX): the design matrix of a least-squares fit."""
    return monomial_rows(variables, exponents).T


@functools.lru_cache(maxsize=64)
def graded_plan(exponents_key: tuple[tuple[int, ...], ...]) -> tuple[tuple[np.ndarray, tuple[tuple[int, int], ...]], ...] | None:
    """Build-up of a full basis degree by degree, or None if ``exponents_key`` is not one in the
    order of :func:`monomial_exponents`.

    In that order the monomials of degree k are, for each variable v in turn, x_v times the
    monomials of degree k - 1 that use only variables v and later, which are a contiguous tail of
    the degree-(k - 1) block. So each degree is built from slices and products, with no gather:
    returns, for each degree k >= 1, its columns and the (variable, start of the tail) pieces.
    """
    exponents = np.asarray(exponents_key, dtype=np.int64).reshape(-1, NUM_VARIABLES)
    degree = int(exponents.sum(axis=1).max(initial=0))
    if len(exponents) != len(monomial_exponents(degree)) or not np.array_equal(exponents, monomial_exponents(degree)):
        return None
    totals = exponents.sum(axis=1)
    plan = []
    for k in range(1, degree + 1):
        previous = exponents[totals == k - 1]
        pieces = []
        for v in range(NUM_VARIABLES):
            uses_only_later = np.flatnonzero(~previous[:, :v].any(axis=1))
            pieces.append((v, int(uses_only_later[0])))
        plan.append((np.flatnonzero(totals == k).astype(np.int32), tuple(pieces)))
    return tuple(plan)

