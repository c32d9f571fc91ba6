"""Levenberg-Marquardt with a trust region that opens as soon as the model's steps are good.

optimistix's :class:`optimistix.LevenbergMarquardt` starts at damping 1 and widens its trust
region (divides the damping by 3.5) only after a step whose actual loss decrease is at least 99 %
of the linear model's prediction. A flare fit's residuals are relative to the plate, so the normal
matrix's diagonal is far below 1 and damping 1 turns the first steps into short gradient steps;
its tints multiply (a ghost's colour is the product of two interfaces' tints) and its dirt cells
multiply the tints, so steps rarely predict the loss to 99 % and the region stays shut. Measured on
a 64 x 48 three-plate coatings + dirt fit of the Biotar (grid model): 60 steps, the loss creeping
from 2e-1 to 5e-3 over the first 20 of them (43 steps with the thresholds below). Not a uniform
win: on a single-plate coatings fit of the Zemax double Gauss it took 41 steps where optimistix's
took 30, to the same answer.

This is the same method (damped Newton descent in a classical trust region, as Moré 1978 and
Nocedal & Wright ch. 10 describe) with the textbook thresholds: the region widens after a step that
achieves at least :data:`GOOD_RATIO` of its predicted decrease; a step below :data:`POOR_RATIO` is
rejected and the region narrows.
"""

from __future__ import annotations

from collections.abc import Callable

import lineax as lx
import optimistix as optx

from ._physical_termination import identity, quiet, physical_step

GOOD_RATIO = 0.75
"""A step whose actual decrease is at least this fraction of the predicted one widens the region."""
POOR_RATIO = 0.1
"""A step below this fraction of its predicted decrease is rejected, and the region narrows."""
WIDEN = 4.0
"""Factor on the step size (1 / damping) after a good step."""
NARROW = 0.25
"""Factor on the step size after a poor step."""


class LevenbergMarquardt(optx.AbstractGaussNewton):
    """Levenberg-Marquardt (:class:`optimistix.DampedNewtonDescent` in a
    :class:`optimistix.ClassicalTrustRegion` with the thresholds above), converged when the
    physical values ``physical(y)`` stop changing (:mod:`._physical_termination`)."""

    rtol: float
    atol: float
    norm: Callable
    descent: optx.DampedNewtonDescent
    search: optx.ClassicalTrustRegion
    verbose: Callable
    physical: Callable

    def __init__(
        self, rtol: float, atol: float, linear_solver: lx.AbstractLinearSolver, verbose: Callable | None = None, physical: Callable | None = None
    ):
        self.rtol = rtol
        self.atol = atol
        self.norm = optx.max_norm
        self.descent = optx.DampedNewtonDescent(linear_solver=linear_solver)
        self.search = optx.ClassicalTrustRegion(high_cutoff=GOOD_RATIO, low_cutoff=POOR_RATIO, high_constant=WIDEN, low_constant=NARROW)
        self.verbose = verbose if callable(verbose) else quiet
        self.physical = identity if physical is None else physical

    step = physical_step
