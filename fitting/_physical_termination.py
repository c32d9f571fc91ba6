"""Gauss-Newton-family solvers that decide convergence on the physical parameters.

A fit's free variables are logits (tints and dirt bounded by sigmoids) and log gains. optimistix's
Cauchy test asks every free variable to stop moving (``|dy| < atol + rtol |y|``), and a variable
whose bound the data pushes against never stops: a dirt cell the plate wants a little above the
bound walks its logit up by about one per step while its transmission changes by less than 1e-6
and the loss by nothing. Measured on notebook 03's 8 x 8 dirt fit (grid model, 64 x 48 Biotar):
the loss settled at 5.20788e-6 by step 28 to ten digits, yet the fit reported "not converged in
40 steps" with two faintly lit cells at the 1.02 bound.

The solvers here apply the same Cauchy test to the values the user reads (tints, transmissions,
gains, layer thicknesses and indices), given by ``physical(y)``: a step converges when those and the
residuals change by less than ``atol + rtol |value|``. Everything else is optimistix's
:class:`optimistix.AbstractGaussNewton` step.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx


def physical_cauchy_converged(rtol: float, atol: float, physical_new, physical_old, residual_new, residual_old) -> jax.Array:
    """True when every physical value and every residual changed by less than ``atol + rtol |new|``."""

    def small(new, old) -> jax.Array:
        leaves = [jnp.all(jnp.abs(n - o) < atol + rtol * jnp.abs(n)) for n, o in zip(jax.tree.leaves(new), jax.tree.leaves(old))]
        return jnp.all(jnp.stack(leaves)) if leaves else jnp.array(True)

    return small(physical_new, physical_old) & small(residual_new, residual_old)


def physical_step(solver: optx.AbstractGaussNewton, fn, y, args, options, state, tags):
    """optimistix's Gauss-Newton step, with its ``terminate`` flag recomputed in physical units.

    The step evaluates the point ``state.y_eval``; when it is accepted, the new iterate is that
    point and the residuals are ``new_state.f_info.residual``. The flag is only raised on an
    accepted step after the first (the first step evaluates the start itself)."""
    new_y, new_state, aux = optx.AbstractGaussNewton.step(solver, fn, y, args, options, state, tags)
    accepted = (new_state.num_steps_since_acceptance == 0) & jnp.logical_not(state.first_step)
    converged = physical_cauchy_converged(
        solver.rtol, solver.atol, solver.physical(state.y_eval), solver.physical(y), new_state.f_info.residual, state.f_info.residual
    )
    return new_y, eqx.tree_at(lambda s: s.terminate, new_state, accepted & converged), aux


def identity(y):
    return y


class GaussNewton(optx.AbstractGaussNewton):
    """Gauss-Newton (full Newton steps, :class:`optimistix.NewtonDescent` with learning rate 1),
    converged in physical units (module docstring)."""

    rtol: float
    atol: float
    norm: Callable
    descent: optx.NewtonDescent
    search: optx.LearningRate
    verbose: Callable
    physical: Callable

    def __init__(self, rtol: float, atol: float, linear_solver, verbose: Callable | None = None, physical: Callable | None = None):
        self.rtol = rtol
        self.atol = atol
        self.norm = optx.max_norm
        self.descent = optx.NewtonDescent(linear_solver=linear_solver)
        self.search = optx.LearningRate(1.0)
        self.verbose = verbose if callable(verbose) else quiet
        self.physical = identity if physical is None else physical

    step = physical_step


def quiet(**fields) -> None:
    del fields
