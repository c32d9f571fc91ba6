"""The polynomial fit's symmetric positive definite solve (plain XLA loops instead of LAPACK, whose
jaxlib 0.10 CPU kernels deadlocked a 2-core test run): the same answers and derivatives as a
LAPACK solve, batched under vmap, and no LAPACK call in its compiled program."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxflare.polynomial._least_squares import spd_solve


def _system(size=40, columns=3, seed=0):
    rng = np.random.default_rng(seed)
    design = rng.normal(size=(3 * size, size))
    return design.T @ design + 1e-6 * np.eye(size), rng.normal(size=(size, columns))


def test_solution_and_gradients_equal_a_lapack_solve():
    matrix, rhs = _system()
    np.testing.assert_allclose(spd_solve(jnp.asarray(matrix), jnp.asarray(rhs)), np.linalg.solve(matrix, rhs), rtol=1e-10, atol=1e-12)
    ours = jax.grad(lambda m, b: jnp.sum(jnp.sin(spd_solve(m, b))), argnums=(0, 1))(jnp.asarray(matrix), jnp.asarray(rhs))
    lapack = jax.grad(lambda m, b: jnp.sum(jnp.sin(jnp.linalg.solve(m, b))), argnums=(0, 1))(jnp.asarray(matrix), jnp.asarray(rhs))
    for a, b in zip(ours, lapack):
        np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-10 * float(jnp.abs(b).max()))


def test_batched_solves_equal_one_by_one_and_call_no_lapack():
    matrices, rhs = zip(*(_system(seed=s) for s in range(3)))
    matrices, rhs = jnp.asarray(np.stack(matrices)), jnp.asarray(np.stack(rhs))
    batched = jax.vmap(spd_solve)(matrices, rhs)
    for k in range(3):
        np.testing.assert_allclose(batched[k], np.linalg.solve(matrices[k], rhs[k]), rtol=1e-10, atol=1e-12)
    program = jax.jit(jax.vmap(spd_solve)).lower(matrices, rhs).as_text()
    assert "custom_call" not in program and "lapack" not in program
