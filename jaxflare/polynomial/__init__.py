"""Polynomial path systems: each lens path as a polynomial map, validated against the exact tracer.

The second stage (lens -> paths -> **path systems** -> samples -> image -> fit): builds on
:mod:`jaxflare.optics` only (and :mod:`jaxflare.io` for its disk cache).

- :func:`path_system` / :func:`path_systems` build (or load from the cache) a :class:`PathSystem`:
  call it like :func:`jaxflare.trace`; its :class:`PathSystemReport` says how accurate it measured.
- Constructions: :class:`LeastSquaresConstruction` (optionally sparse) and
  :class:`TaylorConstruction`, behind :class:`AbstractConstruction`.
- :class:`PathDomain` (:func:`make_domain`): the entrance rays a system is built for.
- :class:`PolynomialPathTracer`: systems of one structure evaluated together, behind the
  :class:`~jaxflare.optics.AbstractPathTracer` interface the renderer uses.
- :func:`refit`: re-fit a least-squares system for changed lens parameters, differentiably.
"""

from ._basis import NUM_VARIABLES, VARIABLE_NAMES, monomial_exponents, monomials, monomials_numpy
from ._build import DEFAULT_DEGREE, default_cache_dir, path_system, path_systems
from ._constructions import CONSTRUCTION_NAMES, AbstractConstruction, LeastSquaresConstruction, TaylorConstruction
from ._domain import DEFAULT_WAVELENGTH_RANGE_NM, TRUST_GRID, PathDomain, entrance_variables, make_domain, rays_from_variables, sample_variables
from ._least_squares import refit
from ._system import PathKernel, PathSystem, PathSystemReport, PolynomialPathTracer, evaluate
from ._taylor import taylor_path_coefficients

__all__ = [
    "CONSTRUCTION_NAMES",
    "DEFAULT_DEGREE",
    "DEFAULT_WAVELENGTH_RANGE_NM",
    "NUM_VARIABLES",
    "TRUST_GRID",
    "VARIABLE_NAMES",
    "AbstractConstruction",
    "LeastSquaresConstruction",
    "PathDomain",
    "PathKernel",
    "PathSystem",
    "PathSystemReport",
    "PolynomialPathTracer",
    "TaylorConstruction",
    "default_cache_dir",
    "entrance_variables",
    "evaluate",
    "make_domain",
    "monomial_exponents",
    "monomials",
    "monomials_numpy",
    "path_system",
    "path_systems",
    "rays_from_variables",
    "refit",
    "sample_variables",
    "taylor_path_coefficients",
]
