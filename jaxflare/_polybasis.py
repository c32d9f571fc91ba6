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


def monomials(variables: jnp.ndarray, exponents: np.ndarray) -> jnp.ndarray:
    """(N, M) monomial values (JAX): a power table per variable by repeated multiplication (exact
    and differentiable for negative values too), gathered and multiplied."""
    degree = int(exponents.max(initial=0))
    table = [jnp.ones_like(variables)]
    for _ in range(degree):
        table.append(table[-1] * variables)
    powers = jnp.stack(table, axis=-1)  # (N, V, D+1)
    out = powers[:, 0, exponents[:, 0]]
    for k in range(1, variables.shape[1]):
        out = out * powers[:, k, exponents[:, k]]
    return out
