"""Convergence judged on physical values (fitting._physical_termination): a parameter the data
pushes against its sigmoid bound stops the fit once its value (not its logit) stops moving."""

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
import pytest

from fitting._levenberg_marquardt import LevenbergMarquardt
from fitting._physical_termination import GaussNewton, physical_cauchy_converged

BOUND = 1.02


def _bounded_problem():
    """Two transmissions ``BOUND * sigmoid(b)``: one the data puts at 0.4 (interior), one it wants
    at 1.1, beyond the bound (as a faintly lit dirt cell the plate wants brighter than clean)."""
    target = jnp.asarray([0.4, 1.1])

    def physical(logits):
        return BOUND * jax.nn.sigmoid(logits)

    def residuals(logits, _):
        return physical(logits) - target

    return residuals, physical


def test_a_value_pressed_against_its_bound_converges_in_physical_units():
    """(Levenberg-Marquardt: undamped Gauss-Newton's first step from the start overshoots into
    the flat sigmoid and its Jacobian goes singular on this problem.)"""
    solver_class = LevenbergMarquardt
    with jax.enable_x64(True):
        residuals, physical = _bounded_problem()
        start = jnp.zeros(2)
        judged_on_values = solver_class(rtol=1e-6, atol=1e-9, linear_solver=lx.QR(), physical=physical)
        judged_on_logits = solver_class(rtol=1e-6, atol=1e-9, linear_solver=lx.QR())
        ours = optx.least_squares(residuals, judged_on_values, start, max_steps=200, throw=False)
        logits = optx.least_squares(residuals, judged_on_logits, start, max_steps=200, throw=False)
        # the bounded value's logit walks on until the sigmoid's slope vanishes in float64 (b ~ 37,
        # 97 steps measured); in physical units the value settles long before (25 steps measured)
        ours_steps, logit_steps = int(ours.stats["num_steps"]), int(logits.stats["num_steps"])
        assert ours.result == optx.RESULTS.successful and ours_steps < 40
        assert logit_steps > 2 * ours_steps, (ours_steps, logit_steps)
        values = np.asarray(physical(ours.value))
        assert values[0] == pytest.approx(0.4, abs=1e-8)
        assert values[1] == pytest.approx(BOUND, abs=1e-5)  # as close to the data as the bound allows


@pytest.mark.parametrize("solver_class", [LevenbergMarquardt, GaussNewton])
def test_the_same_answer_as_the_logit_test_where_both_converge(solver_class):
    """An interior minimum: both tests stop there."""
    with jax.enable_x64(True):
        target = jnp.asarray([0.4, 0.7])
        physical = lambda b: BOUND * jax.nn.sigmoid(b)  # noqa: E731
        residuals = lambda b, _: physical(b) - target  # noqa: E731
        ours = optx.least_squares(residuals, solver_class(1e-8, 1e-12, lx.QR(), physical=physical), jnp.zeros(2), max_steps=200, throw=False)
        plain = optx.least_squares(residuals, solver_class(1e-8, 1e-12, lx.QR()), jnp.zeros(2), max_steps=200, throw=False)
        assert ours.result == optx.RESULTS.successful and plain.result == optx.RESULTS.successful
        np.testing.assert_allclose(physical(ours.value), target, atol=1e-9)
        np.testing.assert_allclose(physical(plain.value), target, atol=1e-9)


def test_convergence_needs_values_and_residuals_both_settled():
    new, old = {"tint": jnp.asarray([1.0, 2.0])}, {"tint": jnp.asarray([1.0, 2.0 + 1e-7])}
    settled, moving = jnp.asarray([0.1, 0.2]), jnp.asarray([0.1, 0.3])
    assert bool(physical_cauchy_converged(1e-6, 1e-9, new, old, settled, settled))
    assert not bool(physical_cauchy_converged(1e-6, 1e-9, new, {"tint": jnp.asarray([1.0, 2.1])}, settled, settled))
    assert not bool(physical_cauchy_converged(1e-6, 1e-9, new, old, settled, moving))
    assert bool(physical_cauchy_converged(1e-6, 1e-9, (None, new["tint"]), (None, old["tint"]), settled, settled))  # None leaves (unfitted parameters) are skipped
