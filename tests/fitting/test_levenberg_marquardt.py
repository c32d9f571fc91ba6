"""The fit's Levenberg-Marquardt solver (fitting._levenberg_marquardt): the same minimum as
optimistix's, reached in fewer steps on a poorly scaled product model like a flare fit's."""

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from fitting._levenberg_marquardt import LevenbergMarquardt


def _product_problem():
    """Residuals of a small "ghost = tint_a x tint_b x dirt" model, relative to a large target as a
    fit's residuals are (the normal matrix's diagonal is far below 1)."""
    rng = np.random.default_rng(3)
    basis = jnp.asarray(rng.uniform(0.0, 1.0, (40, 6)))
    truth = jnp.asarray([0.5, 1.3, 0.8, 0.4, 1.1, 0.9])

    def model(x):
        products = jnp.stack([x[0] * x[1], x[1] * x[2], x[0] * x[3], x[4] * x[5], x[2] * x[4], x[5]])  # x[5] alone fixes the products' scale
        return basis @ products

    target = model(truth)
    norm = 30.0 * jnp.linalg.norm(target)

    def residuals(logx, _):
        return (model(jnp.exp(logx)) - target) / norm

    return residuals, truth


def test_same_minimum_as_optimistix_in_fewer_steps():
    with jax.enable_x64(True):
        residuals, truth = _product_problem()
        start = jnp.zeros(6)
        ours = optx.least_squares(residuals, LevenbergMarquardt(rtol=1e-8, atol=1e-12, linear_solver=lx.QR()), start, max_steps=500, throw=False)
        theirs = optx.least_squares(residuals, optx.LevenbergMarquardt(rtol=1e-8, atol=1e-12), start, max_steps=500, throw=False)
        assert ours.result == optx.RESULTS.successful and theirs.result == optx.RESULTS.successful
        loss = lambda y: 0.5 * float(jnp.sum(residuals(y, None) ** 2))
        assert loss(ours.value) < 1e-14 * loss(start)
        np.testing.assert_allclose(np.exp(ours.value), truth, rtol=1e-5)
        ours_steps, theirs_steps = int(ours.stats["num_steps"]), int(theirs.stats["num_steps"])
        assert ours_steps < theirs_steps, (ours_steps, theirs_steps)


def test_a_quiet_solver_needs_no_callback():
    with jax.enable_x64(True):
        residuals, _ = _product_problem()
        solution = optx.least_squares(residuals, LevenbergMarquardt(rtol=1e-6, atol=1e-9, linear_solver=lx.QR()), jnp.zeros(6), max_steps=200, throw=False)
        assert bool(jnp.all(jnp.isfinite(solution.value)))
