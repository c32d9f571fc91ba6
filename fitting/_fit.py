"""Fitting coating colours, front-lens dirt and light gains to a plate with optimistix.

Parameters are bounded by reparametrisation (optimistix has no box constraints): coating tints
``t = T_MAX sigmoid(a)`` in [0, T_MAX], dirt ``d = DIRT_MAX sigmoid(b)`` in [0, DIRT_MAX], light gains
``g = exp(c)`` > 0. Residuals are ``weight x (render - plate)`` over the pixels (RGB; optionally
summed over blocks of pixels), divided by the norm of the weighted plate so the loss is relative,
plus a weak prior on the dirt map (``dirt_prior_weight x (d - prior)``) so cells the flare never
lights stay at their prior instead of drifting, and on the tints towards 1. Solvers (``solver=``):

- ``"levenberg-marquardt"`` and ``"gauss-newton"``: least squares, each step's linear system solved
  densely (``lineax.QR``) for fits of at most :data:`DENSE_PARAMETERS` parameters (a dirt map only
  through per-cell images, and then up to :data:`DENSE_STACK_PARAMETERS`), else matrix-free
  (``lineax.Normal(lineax.CG(...))``), which scales to large dirt maps re-splatted;
- ``"bfgs"``: a quasi-Newton minimiser of the sum of squares (dense inverse Hessian: small fits).

The fit runs in float64 on a forward model: by default the deterministic grid estimator
(:mod:`fitting._grid_model`, noise-free), or Monte Carlo per-path images or samples
(:mod:`fitting._forward`). After the solve, standard errors of tints and gains come from the
Jacobian, the tint prior and the residual scatter, and the dirt map's sensitivity says which cells
the plate constrains.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from jaxflare.io import atomic_output_group, write_exr
from jaxflare.optics import cast_floating, ghost_paths
from jaxflare.rendering import GridFlareModel, grid_flare_model
from jaxflare.scenes import Light, Scene, SurfaceCoating, camera_lens, load_scene

from ._forward import (
    PATH_IMAGE_BYTES,
    FixedSamples,
    PathImages,
    _path_tints,
    fixed_path_images,
    fixed_samples,
    flare_render,
    path_image_model,
    path_images,
    path_images_bytes,
    render_image,
    reweighted,
)
from ._grid_model import (
    DirtImages,
    FilmImages,
    dirt_image_model,
    dirt_images_bytes,
    film_image_model,
    film_images_bytes,
    grid_dirt_images,
    grid_film_images,
    grid_interfaces,
    grid_path_images_and_full,
    stack_bytes,
)
from ._levenberg_marquardt import LevenbergMarquardt
from ._physical_termination import GaussNewton
from ._plate import Plate, check_fittable
from ._sample_images import sample_dirt_images
from ._thin_film import INDEX_PRIOR_WEIGHT, FilmLayers, air_side_stacks, equivalent_tints, film_arrays, film_layers, film_start_logits, film_values


PARAMETERS = ("coatings", "thin-film", "dirt", "lights")
"""What a fit can change: per-interface coating colours (free RGB tints) or the layers of the
coating stacks (thicknesses and indices, :mod:`fitting._thin_film`), the front-lens dirt map,
light gains."""
THICKNESS_PRIOR_WEIGHT = 1e-6
"""Weight of the prior pulling a fitted layer's relative thickness change to 0: only keeps the
normal matrix invertible for a layer no plate shows (as the grid model's tint prior)."""
SOLVERS = ("levenberg-marquardt", "gauss-newton", "bfgs")
DEFAULT_SOLVER = "levenberg-marquardt"
DIRT_PRIOR = 1.0
"""A clean front lens (transmission 1), as the dirt map's start and prior: cells the flare never
lights stay exactly here."""
DIRT_MAX = 1.02
"""Fitted dirt transmissions are bounded to [0, DIRT_MAX]. A transmission above 1 is unphysical,
and the bound near 1 is what anchors the dirt map's scale against the tints (a brighter clean
lens and darker coatings look alike); it lies just above 1 so that a clean cell (the prior) is an
interior point the solver converges to. Measured on 3-plate coatings + 8 x 8 dirt fits of the
Zemax double Gauss (Monte Carlo plates, ``benchmarks/bench_plate_fits.py``), dirt prior weight
1e-6: bound 1.25 let clean cells rise to 1.16 and the tints fall, largest observable tint error
0.106 and dirt RMSE over lit cells 0.118; bound 1 (prior 0.98, just inside it) 0.076 and 0.026,
bound 1.02 (prior 1) 0.066 and 0.015. :func:`save_fit` writes the map clipped to [0, 1], the
transmissions a scene's dirt map holds."""
TINT_MAX = 4.0
"""Coating tints are bounded to [0, TINT_MAX] (relative to the physical coating model)."""


class FlareParameters(eqx.Module):
    """Unconstrained fit variables; :meth:`values` gives the physical ones."""

    tint_logits: jax.Array
    dirt_logits: jax.Array | None
    light_log_gain: jax.Array
    film_logits: jax.Array | None = None
    """Thin-film layers (2, F): thickness and index logits (:func:`fitting._thin_film.film_values`)."""

    def values(self):
        tints = TINT_MAX * jax.nn.sigmoid(self.tint_logits)
        dirt = None if self.dirt_logits is None else DIRT_MAX * jax.nn.sigmoid(self.dirt_logits)
        return tints, dirt, jnp.exp(self.light_log_gain)


def _logit(x, upper=1.0):
    x = np.clip(np.asarray(x, np.float64) / upper, 1e-6, 1 - 1e-6)
    return np.log(x) - np.log1p(-x)


def initial_parameters(num_interfaces: int, num_lights: int, *, tints=None, dirt=None, light_gain=None) -> FlareParameters:
    """Start values: tints 1 (or ``tints``), no dirt map (or ``dirt``), gains 1 (or ``light_gain``)."""
    tints = np.ones((num_interfaces, 3)) if tints is None else np.asarray(tints, np.float64)
    gains = np.ones((num_lights, 3)) if light_gain is None else np.asarray(light_gain, np.float64)
    return FlareParameters(
        tint_logits=jnp.asarray(_logit(tints, TINT_MAX)), dirt_logits=None if dirt is None else jnp.asarray(_logit(dirt, DIRT_MAX)),
        light_log_gain=jnp.asarray(np.log(gains)),
    )


OBSERVABLE_STD = 0.1
"""A tint or gain whose standard error is above this is reported as not observable in the plate."""
OBSERVABLE_THICKNESS = 0.05
"""A coating layer whose thickness standard error (without the prior) is above this fraction of
its thickness is reported as not observable in the plate."""
MODELS = ("auto", "grid", "path-images", "samples")
"""Forward models: the deterministic grid estimator (noise-free; any parameters), or Monte Carlo
per-path images (coatings and lights only) or the samples themselves; ``auto`` picks the grid,
unless ``samples`` or a ``method`` other than exact ask for Monte Carlo."""
GRID_QUALITY = "production"
"""The grid estimator's quality for a fit's model."""
FINE_GRID = {"grid_error": 1e-4, "grid_options": {"tolerance_px": 0.05, "spacing_px": 0.25}}
"""Plates of at most :data:`FINE_GRID_PIXELS` get a finer grid than production: every path at
full resolution and 3x tighter cells and sub-samples. Measured on a 128 x 72 double-Gauss plate
(Monte Carlo, 2^25 samples): production's image differs from this grid by 4.6 % RMSE, and the
fitted tints' largest error on observable interfaces fell from 0.067 to 0.050 (4 x 4 blocks)."""
FINE_GRID_PIXELS = 512 * 288
"""Largest plate (pixels) whose grid model is rendered at the plate's own resolution with
:data:`FINE_GRID`; a larger plate is fitted at its block resolution with ``grid_quality`` (a 2K
coatings fit: 184 M sub-samples and 63 s for the fine grid's model at 512 x 288, 32 M and 15 s at
production; measured on the 2-core Xeon VM)."""


TINT_PRIOR_WEIGHTS = {"grid": 1e-6, "path-images": 1e-4, "samples": 1e-4}
"""Default weight of the prior pulling tints towards 1, per forward model. The data residuals are
relative to the plate, so a tint that changes a dim ghost moves the loss little and a strong prior
biases it: at 1e-4 it pulled a true tint of 0.3 by 0.054 on a noise-free 64 x 48 plate of the grid
model's own image (0.003 at 1e-8). The noise-free grid model gets a weak prior that only keeps the
normal matrix invertible (an interface no plate shows gets a large, finite standard error); a
Monte Carlo model's own noise also pulls on the tints, and the stronger prior damps that drift
(measured: at 1e-8 a 2^21-sample path-image fit of a 64 x 48 Biotar plate did not converge in 100
steps and missed a tint by 0.15)."""

DIRT_PRIOR_WEIGHTS = {"grid": 1e-6, "path-images": 1e-3, "samples": 1e-3}
"""Default weight of the prior pulling dirt cells towards :data:`DIRT_PRIOR` (a clean lens), per
forward model. A cell the flare never lights has no data term and stays at the prior under any
positive weight; for a lit cell the prior competes with the data, whose pull on one cell is small
(the residuals are relative to the whole plate). Measured on three noise-free 64 x 48 plates of
the Biotar with a 4 x 4 dirt map (blotch 0.4) and two tinted interfaces, fitted through the grid
model: at 1e-3 the prior cost more than the data misfit it took to raise the blotch to 0.48-0.50,
and the tints and the other cells absorbed the difference (largest observable tint error 0.13,
dirt RMSE over lit cells 0.17, measured with the dirt bounded at 1.25); at 1e-6 (bound
:data:`DIRT_MAX`) the fit recovered tints within 0.012 and dirt within RMSE 0.012, and on Monte
Carlo plates of the Zemax double Gauss (``benchmarks/bench_plate_fits.py``) dirt within RMSE
0.015. Cells lit only faintly (sensitivity below 0.2) are then free to wander within the bounds:
read ``dirt_sensitivity`` before trusting a cell. A Monte Carlo model's noise pulls on the dirt as
on the tints, and the stronger prior damps that drift."""


def default_block(width: int, height: int) -> int:
    """The default ``block`` of a fit: 4 x 4 pixel sums where 4 divides the resolution (else 2,
    else 1). A plate's noise and the model's sub-pixel error average out in them (measured: the
    largest tint error 0.065 at block 1, 0.050 at block 4, same plate and model), while a ghost
    spans many blocks."""
    for block in (4, 2):
        if width % block == 0 and height % block == 0:
            return block
    return 1
DEFAULT_SAMPLES = {"path-images": 2**22, "samples": 2**19}


@dataclasses.dataclass
class FitResult:
    """A finished fit: the physical parameters, the solver's verdict, the loss per step, the
    rendered flare and the residual, standard errors, and timings."""

    coating_tints: np.ndarray
    dirt: np.ndarray | None
    light_gain: np.ndarray
    fitted: tuple[str, ...]
    solver: str
    converged: bool
    status: str
    steps: int
    loss_history: list[float]
    seconds: float
    render: np.ndarray
    """The flare (every flare path, not the lights' own images) with the fitted parameters, at the
    plate's resolution, from the fit's samples."""
    residual: np.ndarray
    """``render - plate`` (unweighted; 0 where the plate's weight is 0)."""
    model: str = "samples"
    samples: int = 0
    block: int = 1
    tint_std: np.ndarray | None = None
    """Standard error of each fitted interface tint (I, 3), from the Jacobian, the tint prior and
    the residual scatter (:func:`_standard_errors`); a tint the plate does not show keeps about
    the prior's spread. None when coatings were not fitted."""
    light_gain_std: np.ndarray | None = None
    tint_observable: np.ndarray | None = None
    """Per interface and channel (I, 3): does the plate alone determine the tint (its standard
    error without the tint prior below :data:`OBSERVABLE_STD`)? None when coatings were not fitted."""
    dirt_sensitivity: np.ndarray | None = None
    """How much each dirt-map cell changes the flare, relative to the most sensitive cell (0: the
    flare never lights it, so it keeps its prior)."""
    plates: int = 1
    """Plates fitted together; with more than one, ``render``, ``residual``, ``light_gain`` and
    ``light_gain_std`` are tuples, one entry per plate."""
    coating_layers: list[dict] | None = None
    """A thin-film fit's layers, one dict per layer: ``surface``, ``layer`` (column in the lens's
    coating arrays, forward order), ``thickness_nm`` and ``index`` with their start
    (``*_start``) and standard errors (``*_std``), and ``observable`` (the plate alone determines
    the thickness to :data:`OBSERVABLE_THICKNESS`); ``coating_tints`` then holds the RGB tints
    the fitted stacks are equivalent to. None otherwise."""
    coating_stacks: list | None = None
    """A thin-film fit's stacks as ``(surface, [(index, thickness_nm), ...])`` from the air side,
    the form of a scene's ``surface_coatings`` (what :func:`apply_fit` writes)."""
    model_resolution: tuple[int, int] | None = None
    """(width, height) at which the forward model was rendered (plate 0's): the plate's own
    resolution, or its block resolution for a grid model of a plate larger than
    :data:`FINE_GRID_PIXELS` (compared with the plate spread onto its pixels: :func:`block_resolution_plate`)."""

    def as_dict(self) -> dict:
        def listed(x):
            if isinstance(x, tuple):
                return [listed(v) for v in x]
            return None if x is None else np.where(np.isfinite(x), x, -1.0).tolist()

        return {
            "fitted": list(self.fitted), "solver": self.solver, "model": self.model, "samples": self.samples, "block": self.block,
            "converged": self.converged, "status": self.status, "steps": self.steps, "loss_history": self.loss_history, "seconds": self.seconds,
            "coating_tints": self.coating_tints.tolist(), "coating_tint_std": listed(self.tint_std),
            "observable_interfaces": None if self.tint_observable is None else [int(k) for k in np.flatnonzero(np.all(self.tint_observable, axis=1))],
            "coating_tint_observable": None if self.tint_observable is None else self.tint_observable.tolist(),
            "plates": self.plates, "model_resolution": None if self.model_resolution is None else list(self.model_resolution),
            "light_gain": listed(self.light_gain), "light_gain_std": listed(self.light_gain_std),
            "dirt_shape": None if self.dirt is None else list(self.dirt.shape),
            "coating_layers": self.coating_layers,
            "coating_stacks": None if self.coating_stacks is None else [{"surface": s, "layers": [list(l) for l in stack]} for s, stack in self.coating_stacks],
        }


DENSE_PARAMETERS = 128
"""Fits of at most this many parameters solve each step's linear system densely (QR of the
Jacobian, one forward-mode pass per parameter), unless they fit the dirt map by re-splatting the
grid's sub-samples or re-tracing samples (too large to batch over parameters); larger ones, and
those dirt fits, go matrix-free with conjugate gradients on the normal equations. A dirt map fitted
through per-cell images (:class:`~._grid_model.DirtImages`) is solved densely like the tints, up to
:data:`DENSE_STACK_PARAMETERS`.
Measured on a 64 x 48 thin-film fit of 8 layers: 1.6 s per step matrix-free (CG runs to hundreds
of iterations on its ill-conditioned normal matrix)."""


DENSE_STACK_PARAMETERS = 2048
"""A dirt map fitted through per-cell image stacks (:class:`~._grid_model.DirtImages`) is solved
densely up to this many parameters: its Jacobian is a contraction of the stacks it already reads
for the residual, where conjugate gradients re-read them twice per iteration for hundreds of
iterations (a 32 x 32 map on three 128 x 72 plates: over 6 minutes in the solve, not finished)."""


def _solver(name: str, rtol: float, atol: float, verbose=False, dense: bool = False, physical=None):
    """The solver called ``name``; ``physical`` maps the free variables to the values ``rtol`` and
    ``atol`` are judged on (Gauss-Newton family: :mod:`._physical_termination`)."""
    if name not in SOLVERS:
        raise ValueError(f"solver must be one of {', '.join(SOLVERS)}, got {name!r}")
    linear = lx.QR() if dense else lx.Normal(lx.CG(rtol=1e-6, atol=1e-9, max_steps=500))
    if name == "levenberg-marquardt":
        return LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=linear, verbose=verbose, physical=physical)
    if name == "gauss-newton":
        return GaussNewton(rtol=rtol, atol=atol, linear_solver=linear, verbose=verbose, physical=physical)
    return optx.BFGS(rtol=rtol, atol=atol, verbose=verbose)


def _choose_model(model: str, params, scene, block: int, paths, samples=None, method: str = "exact") -> str:
    if model not in MODELS:
        raise ValueError(f"model must be one of {', '.join(MODELS)}, got {model!r}")
    if model == "path-images" and "dirt" in params:
        raise ValueError("model='path-images' cannot fit the dirt map (the flare is not a sum of fixed images in it): use model='grid' or 'samples'")
    if "thin-film" in params and (model not in ("auto", "grid") or samples is not None or method != "exact"):
        raise ValueError(
            "params 'thin-film' fits through the grid model only (it recolours the grid's jobs per wavelength): "
            f"drop model={model!r}, samples and method (or use model='grid')"
        )
    if model == "grid" and method != "exact":
        raise ValueError(f"model='grid' traces exactly: method={method!r} needs model='path-images' or 'samples'")
    if model != "auto":
        return model
    if samples is None and method == "exact":
        return "grid"
    if "dirt" in params:
        return "samples"
    size = path_images_bytes(scene, _num_flare_paths(scene, paths), per_light_colour="lights" in params, block=block)
    return "path-images" if size <= PATH_IMAGE_BYTES else "samples"


def _num_flare_paths(scene: Scene, paths) -> int:
    """Flare paths a model of ``scene`` draws: ``paths``, or every ghost path of its lens (before culling)."""
    return len(ghost_paths(camera_lens(scene.camera))) if paths is None else len(paths)


def fit(
    scene,
    plate: Plate | Sequence[Plate],
    *,
    params: Sequence[str] = ("coatings", "dirt"),
    solver: str = DEFAULT_SOLVER,
    model: str = "auto",
    samples: int | None = None,
    seed: int = 0,
    method: str = "exact",
    paths: Sequence[tuple[int, int]] | None = None,
    dirt_resolution: int = 16,
    dirt_prior: float = DIRT_PRIOR,
    dirt_prior_weight: float | None = None,
    tint_prior_weight: float | None = None,
    max_steps: int = 100,
    rtol: float = 1e-6,
    atol: float = 1e-9,
    block: int | None = None,
    fixed: FixedSamples | PathImages | GridFlareModel | Sequence | None = None,
    progress: Callable[[int, float], None] | None = None,
    grid_quality: str = GRID_QUALITY,
) -> FitResult:
    """Fit ``params`` (any of :data:`PARAMETERS`) of ``scene`` so its flare render matches ``plate``.

    ``plate`` may also be a sequence of plates of one lens (frames of a shot, light positions of a
    lens test), fitted together: the coatings and the dirt map are shared, each plate has its own
    light gains, and ``scene`` is then one scene for all of them or a sequence of scenes, one per
    plate (same lens, aperture and coatings; their lights and resolutions may differ). Seeing a
    ghost cross the front lens at several places is what separates its tint from the dirt it
    crosses. The result's ``render``, ``residual``, ``light_gain`` and ``light_gain_std`` are then
    tuples with one entry per plate.

    The others keep the scene's values (its ``coating_tints``, its dirt map, gains 1); fitted
    tints start from the scene's, the dirt map from ``dirt_prior`` (a clean lens). ``"thin-film"``
    fits the layers of the scene's coating stacks (thickness and index, :mod:`fitting._thin_film`)
    instead of free tints (not both), through the grid model only; the result then reports the
    layers (``coating_layers``, ``coating_stacks``) and the tints they are equivalent to. The loss is
    ``0.5 |w (render - plate)|^2 / |w plate|^2`` (``w``: the plate's weights, block-summed;
    numerator and denominator summed over the plates) plus
    the priors ``0.5 dirt_prior_weight |dirt - dirt_prior|^2`` and ``0.5 tint_prior_weight
    |tints - 1|^2``: relative to the plate's light, so the prior weights do not depend on units.

    ``model``: ``"grid"`` plans and traces the scene's flare once with the deterministic grid
    estimator (:func:`jaxflare.rendering.grid_flare_model`, at ``grid_quality``; plates of at most
    :data:`FINE_GRID_PIXELS` get the finer :data:`FINE_GRID`) and fits through it: noise-free, so
    the fit is not biased by the model's own noise, and it fits any parameters (coatings and lights
    through its per-path images, the dirt map through per-path images of each one-hot dirt cell and
    thin-film layers through per-path images of each spectral knot, where those fit in
    :data:`~fitting._forward.PATH_IMAGE_BYTES`, else by re-splatting its fixed sub-samples);
    ``"path-images"`` renders each flare path once with Monte Carlo, ``samples`` samples (default
    2**22), and fits their tinted sum (coatings and lights only); ``"samples"`` keeps the
    ``samples`` Monte Carlo samples (default 2**19) themselves and solves on their per-path images
    (per path and dirt cell when the dirt map is fitted; :func:`~fitting._forward.fixed_path_images`,
    :func:`~fitting._sample_images.sample_dirt_images`), which equal their render; ``"auto"`` picks the grid unless
    ``samples`` is given or ``method`` is not ``"exact"`` (Monte Carlo is then asked for), and then
    path images when it can. ``block`` > 1 compares sums over ``block`` x ``block`` pixels (default
    :func:`default_block`): a plate's noise and the model's sub-pixel error average out in them,
    while a ghost spans many blocks. A grid model of a plate of more than :data:`FINE_GRID_PIXELS`
    pixels is planned and rendered at the block resolution (a 2K plate at block 4: 512 x 288) and
    compared with the plate spread onto the block resolution's pixels (:func:`block_resolution_plate`), at
    ``grid_quality``; the result's ``render`` and ``residual`` are then a full-resolution grid render
    with the fitted parameters (:data:`FULL_RESOLUTION_GRID_QUALITY`), and ``model_resolution``
    says which resolution the fit compared (a dirt fit reduces further, by powers of 2, until its
    per-cell image stack fits in :data:`~fitting._forward.PATH_IMAGE_BYTES`: a 2K plate with a
    16 x 16 map at 64 x 36). ``fixed``: a grid model, samples or path images made earlier
    (tests, benchmarks; a sequence, one per plate, for several plates). ``tint_prior_weight``: None takes the model's default
    (:data:`TINT_PRIOR_WEIGHTS`), and so does ``dirt_prior_weight`` (:data:`DIRT_PRIOR_WEIGHTS`).
    ``method``: how samples are traced (``"exact"``, ``"polynomial"``, ``"auto"``), as in
    :func:`jaxflare.render`; ``paths``: only these ghost paths (default: all).

    Levenberg-Marquardt and Gauss-Newton have converged when an accepted step changes every
    fitted value (tint, dirt transmission, gain, layer thickness and index) and every residual by
    less than ``atol + rtol |value|``; BFGS applies optimistix's test to its free variables.
    A solver that does not converge in ``max_steps`` still returns its best parameters, with
    ``converged`` False and its ``status``; so does one that diverges. ``progress(step, loss)``
    is called after each step.
    """
    unknown = [p for p in params if p not in PARAMETERS]
    if unknown or not params:
        raise ValueError(f"params must be a non-empty subset of {', '.join(PARAMETERS)}, got {list(params)!r}")
    params = tuple(p for p in PARAMETERS if p in params)
    if "coatings" in params and "thin-film" in params:
        raise ValueError("params: 'coatings' (free RGB tints) and 'thin-film' (the coating layers) both set the coatings' colours: choose one")
    started = time.perf_counter()
    scenes, plates, fixeds = _plates_and_scenes(scene, plate, fixed)
    resolutions = [tuple(s.camera.resolution) for s in scenes]
    for s, p in zip(scenes, plates):
        width, height = s.camera.resolution
        if p.rgb.shape[:2] != (height, width):
            raise ValueError(
                f"plate {p.source}: {p.rgb.shape[1]} x {p.rgb.shape[0]} pixels, but the scene renders "
                f"{width} x {height} (camera.resolution): they must match"
            )
    if block is None:
        block = min(default_block(w, h) for w, h in resolutions)
    for width, height in resolutions:
        if not (isinstance(block, int) and not isinstance(block, bool) and block >= 1 and width % block == 0 and height % block == 0):
            raise ValueError(f"block must be a positive integer dividing the resolution {width} x {height}, got {block!r}")
    if isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1:
        raise ValueError(f"max_steps must be an integer of at least 1, got {max_steps!r}")
    _solver(solver, rtol, atol)  # a bad solver name fails before any rendering
    if progress is not None and not callable(progress):
        raise ValueError(f"progress must be a callable progress(step, loss) or None, got {progress!r}")
    for p in plates:
        check_fittable(p)  # and so does a plate no flare can match
    num_interfaces = _shared_lens_interfaces(scenes)
    layers: FilmLayers | None = None
    if "thin-film" in params:
        if scenes[0].render.fresnel != "schlick":
            raise ValueError(f"params 'thin-film' needs render.fresnel = 'schlick' (the coatings scale each path's colour), got {scenes[0].render.fresnel!r}")
        layers = film_layers(camera_lens(scenes[0].camera))
    if fixeds[0] is not None:
        model = "grid" if isinstance(fixeds[0], GridFlareModel) else "path-images" if isinstance(fixeds[0], PathImages) else "samples"
    model = _choose_model(model, params, scenes[0], block, paths, samples, method)
    full_scenes, full_plates, model_block = scenes, plates, block
    if model == "grid" and fixeds[0] is None and block > 1 and max(w * h for w, h in resolutions) > FINE_GRID_PIXELS:
        # a large plate: the grid model is planned and splatted at the block resolution, against
        # the plate spread onto that resolution's pixels (block_resolution_plate)
        factor = block
        if "dirt" in params and "thin-film" not in params:  # down to where its per-cell stack fits in memory
            factor = _dirt_stack_factor(scenes, resolutions, block, paths, dirt_resolution, per_light_colour="lights" in params)
        scenes = [at_resolution(s, (w // factor, h // factor)) for s, (w, h) in zip(scenes, resolutions)]
        plates = [block_resolution_plate(p, factor) for p in plates]
        resolutions = [tuple(s.camera.resolution) for s in scenes]
        model_block = 1
    if tint_prior_weight is None:
        tint_prior_weight = TINT_PRIOR_WEIGHTS[model]
    if dirt_prior_weight is None:
        dirt_prior_weight = DIRT_PRIOR_WEIGHTS[model]
    built = [
        _plate_model(
            s, p, f, model, params, model_block, samples=samples, seed=seed, method=method, paths=paths, grid_quality=grid_quality,
            dirt_shape=(dirt_resolution, dirt_resolution), fine_grid=model_block == block,
        )
        for s, p, f in zip(scenes, plates, fixeds)
    ]
    with jax.enable_x64(True):
        # the grid model's splat stays in float32 (as its render); the loss and solver are float64
        forwards = [b.forward if isinstance(b.forward, GridFlareModel) else cast_floating(b.forward, jnp.float64) for b in built]
        light_counts = [_num_lights(f) for f in forwards]
        gain_offsets = np.concatenate([[0], np.cumsum(light_counts)]).astype(int)
        grid_paths = [jnp.asarray(grid_interfaces(f)) if isinstance(f, GridFlareModel) else None for f in forwards]
        scene_tints = np.clip(scenes[0].camera.interface_tints(num_interfaces), 1e-3, TINT_MAX - 1e-3)
        start = initial_parameters(
            num_interfaces, int(gain_offsets[-1]), tints=scene_tints,
            dirt=np.full((dirt_resolution, dirt_resolution, 1), dirt_prior) if "dirt" in params else None,
        )
        if layers is not None:
            start = dataclasses.replace(start, film_logits=jnp.asarray(film_start_logits(layers)))
        free_mask = FlareParameters(
            tint_logits="coatings" in params, dirt_logits=None if start.dirt_logits is None else True, light_log_gain="lights" in params,
            film_logits=None if layers is None else True,
        )
        free, frozen = eqx.partition(start, free_mask, is_leaf=lambda x: x is None)
        weights = [jnp.asarray(p.weight, jnp.float64)[..., None] for p in plates]

        def pooled(k, image, weight):  # weighted block sums of plate k
            width, height = resolutions[k]
            shape = (height // model_block, model_block, width // model_block, model_block, image.shape[-1])
            return (image * weight).reshape(shape).sum(axis=(1, 3))

        targets = [pooled(k, jnp.asarray(np.where(p.weight[..., None] > 0, p.rgb, 0.0), jnp.float64), weights[k]) for k, p in enumerate(plates)]
        target_norm = float(jnp.sqrt(sum(jnp.sum(t**2) for t in targets)))
        prior = jnp.asarray(dirt_prior, jnp.float64)
        # what the residuals read, passed to the solver as its ``args``: closed over, the image
        # stacks would be constants of every compiled step (XLA then folds transposes of them:
        # seconds per compile on a 2K plate)
        data = (forwards, targets, weights, grid_paths, [b.grid if isinstance(b.forward, FilmImages) else None for b in built])

        def model_image(k, tints, dirt, gain, film, data):
            forwards, _, weights, grid_paths, film_grids = data
            forward, gain = forwards[k], gain[gain_offsets[k] : gain_offsets[k + 1]] if "lights" in params else None
            if isinstance(forward, DirtImages):
                return dirt_image_model(forward, tints, dirt, gain)
            if isinstance(forward, FilmImages):
                fresnel = film_grids[k].path_fresnel(*film_arrays(layers, *film))
                return film_image_model(forward, fresnel.astype(jnp.float64), tints, gain)
            if isinstance(forward, GridFlareModel):
                fresnel = None if film is None else forward.path_fresnel(*film_arrays(layers, *film))
                return pooled(k, forward.image(_path_tints(grid_paths[k], tints), dirt, gain, fresnel).astype(jnp.float64), weights[k])
            if isinstance(forward, PathImages):
                return path_image_model(forward, tints, gain)
            return pooled(k, render_image(forward, tints, dirt, gain), weights[k])

        def data_residuals(tints, dirt, gain, film, data):
            targets = data[1]
            return jnp.concatenate([(model_image(k, tints, dirt, gain, film, data) - targets[k]).ravel() for k in range(len(plates))]) / target_norm

        def unpacked(free_params):
            combined = eqx.combine(free_params, frozen, is_leaf=lambda x: x is None)
            film = None if layers is None else film_values(layers, combined.film_logits)
            return (*combined.values(), film)

        def residuals(free_params, data):
            tints, dirt, gain, film = unpacked(free_params)
            parts = [data_residuals(tints, dirt, gain, film, data)]
            if "dirt" in params:
                parts.append(math.sqrt(dirt_prior_weight) * (dirt - prior).ravel())
            if "coatings" in params:
                parts.append(math.sqrt(tint_prior_weight) * (tints - 1.0).ravel())
            if layers is not None:
                parts.append(math.sqrt(THICKNESS_PRIOR_WEIGHT) * (film[0] / jnp.asarray(layers.thickness_nm) - 1.0))
                parts.append(math.sqrt(INDEX_PRIOR_WEIGHT) * (film[1] - jnp.asarray(layers.index)))
            return jnp.concatenate(parts)

        num_free = sum(int(np.size(leaf)) for leaf in jax.tree.leaves(free))
        # a dirt map fitted by re-splatting (or re-tracing) is too large to batch over parameters;
        # through per-cell image stacks the dirt is as linear and as cheap as the tints
        resplats = "dirt" in params and not all(isinstance(f, DirtImages) for f in forwards)
        dense = not resplats and num_free <= (DENSE_STACK_PARAMETERS if "dirt" in params else DENSE_PARAMETERS)
        best, history, steps, converged, status = _solve(
            residuals, free, solver, rtol, atol, max_steps, progress, dense=dense, physical=unpacked, args=data
        )
        tints, dirt, gain, film = unpacked(best)
        fitted_values = {name: value for name, value in (("coatings", tints), ("lights", gain)) if name in params}
        prior_weights = {"coatings": tint_prior_weight}
        if film is not None:
            fitted_values.update(thickness=film[0], index=film[1])
            prior_weights.update(thickness=THICKNESS_PRIOR_WEIGHT / layers.thickness_nm**2, index=INDEX_PRIOR_WEIGHT)

        def data_at(values, data):
            at_film = None if film is None else (values["thickness"], values["index"])
            return data_residuals(values.get("coatings", tints), dirt, values.get("lights", gain), at_film, data)

        std, data_std = _standard_errors(data_at, fitted_values, prior_weights=prior_weights, residual_shape=[t.shape for t in targets], data=data)
        tint_std, gain_std = std.get("coatings"), std.get("lights")
        tint_observable = data_std["coatings"] < OBSERVABLE_STD if "coatings" in data_std else None
        sensitivity = None
        if "dirt" in params:
            grad = jax.grad(lambda d: sum(jnp.sum(model_image(k, tints, d, gain, film, data)) for k in range(len(plates))))(dirt)
            sensitivity = np.abs(np.asarray(grad))
            sensitivity = sensitivity / max(float(sensitivity.max()), 1e-300)
        tints, gain = np.asarray(tints), np.asarray(gain)
        dirt = None if dirt is None else np.asarray(dirt)
        model_tints = tints  # what the model renders with (the scene's tints in a thin-film fit)
        coating_layers = coating_stacks = None
        if film is not None:
            lens = camera_lens(scenes[0].camera)
            thickness, index = np.asarray(film[0], np.float64), np.asarray(film[1], np.float64)
            coating_layers = _layer_report(layers, thickness, index, std, data_std)
            coating_stacks = air_side_stacks(lens, layers, thickness, index)
            tints = tints * equivalent_tints(lens, layers, thickness, index, scenes[0].render.colour_space)
            film = (thickness, index)
        images = [
            _final_image(b, f, scenes[k], model_tints, dirt,
                         gain[gain_offsets[k] : gain_offsets[k + 1]] if "lights" in params else None, film=None if film is None else (layers, film))
            for k, (b, f) in enumerate(zip(built, forwards))
        ] if model_block == block else [
            _full_resolution_image(full_scenes[k], b.grid, model_tints, dirt,
                                   gain[gain_offsets[k] : gain_offsets[k + 1]] if "lights" in params else None, film=None if film is None else (layers, film))
            for k, b in enumerate(built)
        ]
    residual = [np.where(p.weight[..., None] > 0, image - p.rgb, 0.0) for p, image in zip(full_plates, images)]
    gains = [gain[gain_offsets[k] : gain_offsets[k + 1]] for k in range(len(plates))]
    gain_stds = None if gain_std is None else [gain_std[gain_offsets[k] : gain_offsets[k + 1]] for k in range(len(plates))]
    one = len(plates) == 1
    return FitResult(
        coating_tints=tints, dirt=dirt, light_gain=gains[0] if one else tuple(gains), fitted=params, solver=solver, converged=converged,
        status=status, steps=steps, loss_history=history, seconds=time.perf_counter() - started, render=images[0] if one else tuple(images),
        residual=residual[0] if one else tuple(residual), model=model, samples=built[0].samples, block=block, tint_std=tint_std,
        light_gain_std=None if gain_stds is None else gain_stds[0] if one else tuple(gain_stds), dirt_sensitivity=sensitivity,
        tint_observable=tint_observable, plates=len(plates), coating_layers=coating_layers, coating_stacks=coating_stacks,
        model_resolution=resolutions[0],
    )


def _layer_report(layers: FilmLayers, thickness, index, std: dict, data_std: dict) -> list[dict]:
    """One dict per fitted layer (see :attr:`FitResult.coating_layers`)."""
    def number(x):
        return float(x) if math.isfinite(float(x)) else None

    return [
        {
            "surface": int(layers.surfaces[f]), "layer": int(layers.columns[f]),
            "thickness_nm": float(thickness[f]), "thickness_start_nm": float(layers.thickness_nm[f]), "thickness_std_nm": number(std["thickness"][f]),
            "index": float(index[f]), "index_start": float(layers.index[f]), "index_std": number(std["index"][f]),
            "observable": bool(data_std["thickness"][f] < OBSERVABLE_THICKNESS * layers.thickness_nm[f]),
        }
        for f in range(layers.size)
    ]


def _plates_and_scenes(scene, plate, fixed):
    """One plate or a sequence; one scene for all or one per plate; ``fixed`` likewise."""
    plates = [plate] if isinstance(plate, Plate) else list(plate)
    if not plates or not all(isinstance(p, Plate) for p in plates):
        raise ValueError(f"plate must be a fitting.Plate or a non-empty sequence of them, got {type(plate).__name__}")
    scenes = list(scene) if isinstance(scene, (list, tuple)) else [scene] * len(plates)
    if len(scenes) != len(plates):
        raise ValueError(f"{len(scenes)} scenes for {len(plates)} plates: give one scene for all plates or one per plate")
    scenes = [s if isinstance(s, Scene) else load_scene(s) for s in scenes]
    if fixed is None or isinstance(fixed, (GridFlareModel, PathImages, FixedSamples)):
        if fixed is not None and len(plates) > 1:
            raise ValueError(f"fixed: one forward model for {len(plates)} plates; give one per plate (a sequence)")
        fixeds = [fixed] * len(plates)
    else:
        fixeds = list(fixed)
        if len(fixeds) != len(plates) or len({type(f) for f in fixeds}) != 1:
            raise ValueError(f"fixed: {len(fixeds)} forward models for {len(plates)} plates: give one of one kind per plate")
    return scenes, plates, fixeds


def _shared_lens_interfaces(scenes) -> int:
    """The interfaces of the lens every plate's scene shares (coatings and dirt are shared)."""
    lenses = [camera_lens(s.camera) for s in scenes]
    first = lenses[0]
    for k, lens in enumerate(lenses[1:], start=1):
        same = lens.num_interfaces == first.num_interfaces and lens.curvature_per_mm.shape == first.curvature_per_mm.shape and np.allclose(
            np.asarray(lens.curvature_per_mm), np.asarray(first.curvature_per_mm)
        )
        if not same:
            raise ValueError(
                f"the scene of plate {k} has another lens ({lens.num_interfaces} interfaces) than plate 0's ({first.num_interfaces}): "
                "plates fitted together share coatings and dirt, so they must show one lens"
            )
    return int(first.num_interfaces)


@dataclasses.dataclass
class _BuiltModel:
    forward: object
    """What the fit evaluates: a GridFlareModel (dirt fitted), PathImages, DirtImages or FixedSamples."""
    grid: GridFlareModel | None
    samples: int
    full_images: np.ndarray | None = None
    """Per-path full-resolution images on the host (P, K, H, W, 3) float32, where the forward
    model's own stack does not keep them: the final render is their tinted sum."""
    fixed_samples: FixedSamples | None = None
    """The samples a per-dirt-cell image stack was made from: the final render splats them."""


def _plate_model(
    scene, plate: Plate, fixed, model: str, params, block: int, *, samples, seed, method, paths, grid_quality, dirt_shape=(16, 16), fine_grid: bool = True,
) -> _BuiltModel:
    """The forward model of one plate: built (or checked, when ``fixed``) for its resolution, weights
    and block (a grid model with :data:`FINE_GRID` where ``fine_grid`` and the plate has at most
    :data:`FINE_GRID_PIXELS`)."""
    width, height = scene.camera.resolution
    grid_flare = None
    if model == "grid":
        if fixed is not None and fixed.resolution != (width, height):
            raise ValueError(f"the grid model given was made at {fixed.resolution[0]} x {fixed.resolution[1]}, not {width} x {height}")
        grid_flare = fixed if fixed is not None else grid_flare_model(scene, grid_quality, paths=paths, **(FINE_GRID if fine_grid and width * height <= FINE_GRID_PIXELS else {}))
        # with the dirt map fixed the flare is a tinted sum of per-path images; a dirt fit re-splats
        per_light = "lights" in params
        if "dirt" in params and "thin-film" not in params:  # a sum of per-path, per-dirt-cell images, where they fit in memory
            small = dirt_images_bytes(grid_flare, dirt_shape, block, per_light_colour=per_light) <= PATH_IMAGE_BYTES
            forward = grid_dirt_images(grid_flare, dirt_shape, plate.weight, block, per_light_colour=per_light) if small else grid_flare
        elif "dirt" in params:  # re-splat the fixed sub-samples for every dirt map and coating the solver tries
            forward = grid_flare
        elif "thin-film" in params:  # a sum of per-path, per-spectral-knot images, where they fit in memory
            small = film_images_bytes(grid_flare, block, per_light_colour=per_light) <= PATH_IMAGE_BYTES
            forward = grid_film_images(grid_flare, plate.weight, block, per_light_colour=per_light) if small else grid_flare
        else:
            forward, full = grid_path_images_and_full(grid_flare, plate.weight, block, per_light_colour=per_light)
            return _BuiltModel(forward, grid_flare, grid_flare.subsamples, full_images=full if forward.full_images is None else None)
        return _BuiltModel(forward, grid_flare, grid_flare.subsamples)
    if fixed is not None:
        samples = fixed.samples if isinstance(fixed, PathImages) else int(fixed.records.path.shape[0])
    elif samples is None:
        samples = DEFAULT_SAMPLES[model]
    if fixed is None and model == "path-images":
        fixed = path_images(
            scene, samples=samples, seed=seed, method=method, pixel_weight=plate.weight, block=block, per_light_colour="lights" in params, paths=paths,
        )
    elif fixed is None:
        fixed = fixed_samples(scene, samples=samples, seed=seed, method=method, paths=paths)
    if isinstance(fixed, PathImages) and fixed.resolution != (width, height):
        raise ValueError(f"the path images given were made at {fixed.resolution[0]} x {fixed.resolution[1]}, not {width} x {height}")
    if isinstance(fixed, PathImages) and fixed.full_images is not None:  # weight and sum blocks for this plate
        fixed = reweighted(fixed, plate.weight, block)
    elif isinstance(fixed, PathImages) and fixed.block != block:
        raise ValueError(f"the path images given were made for block {fixed.block} (without full-resolution images), not block {block}")
    if isinstance(fixed, FixedSamples):
        # the samples' image is a tinted (and dirt-weighted) sum of their per-path (per-dirt-cell)
        # images: the same model, and a step's Jacobian no longer re-splats every sample per parameter
        per_light = "lights" in params
        if "dirt" in params:
            images = sample_dirt_images(fixed, dirt_shape, plate.weight, block, per_light_colour=per_light)
        else:
            images = fixed_path_images(fixed, pixel_weight=plate.weight, block=block, per_light_colour=per_light)
        if images is not None:
            return _BuiltModel(images, None, samples, fixed_samples=fixed)
    return _BuiltModel(fixed, None, samples)


def _num_lights(forward) -> int:
    if isinstance(forward, (GridFlareModel, PathImages, FilmImages, DirtImages)):
        return forward.num_lights
    return int(forward.setup.lights.kind.shape[0])


_grid_image = eqx.filter_jit(lambda flare, path_tint, dirt, gain, fresnel=None: flare.image(path_tint, dirt, gain, fresnel))
_grid_fresnel = eqx.filter_jit(lambda flare, indices, thicknesses: flare.path_fresnel(indices, thicknesses))


def _final_image(built: _BuiltModel, forward, scene, tints, dirt, gain, film=None) -> np.ndarray:
    """The flare with the fitted parameters at the plate's full resolution (``film``: a thin-film
    fit's ``(layers, (thickness, index))``)."""
    gain = None if gain is None else jnp.asarray(gain)
    if film is not None:
        layers, (thickness, index) = film
        fresnel = _grid_fresnel(built.grid, *film_arrays(layers, jnp.asarray(thickness), jnp.asarray(index)))
        path_tint = _path_tints(jnp.asarray(grid_interfaces(built.grid)), jnp.asarray(tints))
        return np.asarray(_grid_image(built.grid, path_tint, None if dirt is None else jnp.asarray(dirt), gain, fresnel), np.float64)
    if isinstance(forward, PathImages) and forward.full_images is not None:
        return np.asarray(path_image_model(forward, jnp.asarray(tints), gain, full=True))
    if isinstance(forward, PathImages) and built.full_images is not None:  # a tinted sum on the host, path by path
        path_tint = np.asarray(_path_tints(jnp.asarray(forward.path_interfaces), jnp.asarray(tints)), np.float32)
        weights = np.ones(1, np.float32) if built.full_images.shape[1] == 1 else np.asarray(gain, np.float32).reshape(-1)
        image = np.zeros(built.full_images.shape[2:], np.float32)
        for p in range(built.full_images.shape[0]):
            for k, w in enumerate(weights):
                image += built.full_images[p, k] * (w * path_tint[p])
        return image.astype(np.float64)
    if built.grid is not None:
        path_tint = _path_tints(jnp.asarray(grid_interfaces(built.grid)), jnp.asarray(tints))
        return np.asarray(_grid_image(built.grid, path_tint, None if dirt is None else jnp.asarray(dirt), gain), np.float64)
    if built.fixed_samples is not None and not isinstance(forward, PathImages):  # per-dirt-cell images of samples
        forward = cast_floating(built.fixed_samples, jnp.float64)
    elif isinstance(forward, PathImages):
        fixed = built.forward
        return flare_render(scene, tints, gain, samples=fixed.samples, seed=fixed.seed, method=fixed.method, quality=fixed.quality, paths=fixed.paths)
    return np.asarray(render_image(forward, jnp.asarray(tints), None if dirt is None else jnp.asarray(dirt), jnp.ones((_num_lights(forward), 3)) if gain is None else gain))


FULL_RESOLUTION_GRID_QUALITY = "preview"
"""The grid estimator's quality for the full-resolution render of a fit made at the block
resolution (plates of more than :data:`FINE_GRID_PIXELS`)."""


def at_resolution(scene: Scene, resolution: tuple[int, int]) -> Scene:
    """``scene`` rendered at ``resolution`` (the same sensor and framing, larger or smaller pixels)."""
    return dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, resolution=tuple(int(r) for r in resolution)))


def _dirt_stack_factor(scenes, resolutions, block: int, paths, dirt_resolution: int, *, per_light_colour: bool) -> int:
    """How much a dirt fit of large plates reduces them: ``block``, doubled while the per-path,
    per-dirt-cell image stack at the reduced resolution would exceed
    :data:`~._forward.PATH_IMAGE_BYTES` (its paths counted before culling) and the resolutions
    stay divisible. Without the stack the fit re-splats every sub-sample for every parameter the
    solver tries (matrix-free: hours at 512 x 288)."""
    num_paths, lights = _num_flare_paths(scenes[0], paths), max(len(s.lights) for s in scenes)

    def total_bytes(factor):
        return sum(stack_bytes(num_paths, lights, dirt_resolution**2, (w, h), factor, per_light_colour) for w, h in resolutions)

    factor = block
    while total_bytes(factor) > PATH_IMAGE_BYTES and all(w % (2 * factor) == 0 and h % (2 * factor) == 0 for w, h in resolutions):
        factor *= 2
    return factor


def splat_weights(size: int, block: int) -> np.ndarray:
    """(size / block, size) weights with which a renderer at 1 / ``block`` of the resolution
    splats a point at each full-resolution pixel centre along one axis: bilinear, with what would
    fall off the image kept by the edge pixel (as :func:`jaxflare.rendering._splat.splat`)."""
    small = size // block
    centre = (np.arange(size) + 0.5) / block - 0.5
    first = np.floor(centre)
    fraction = centre - first
    weights = np.zeros((small, size))
    columns = np.arange(size)
    np.add.at(weights, (np.clip(first, 0, small - 1).astype(int), columns), 1.0 - fraction)
    np.add.at(weights, (np.clip(first + 1, 0, small - 1).astype(int), columns), fraction)
    return weights


def block_resolution_plate(plate: Plate, block: int) -> Plate:
    """``plate`` at 1 / ``block`` of its resolution, as a renderer at that resolution sees the same
    light: every pixel's value spread bilinearly over the four pixel centres around it
    (:func:`splat_weights`) and normalised by the weights (the plate's weights times the splat's),
    with the summed weights as the new pixel weights. A plain block mean is not what a render at the
    block resolution makes: its bilinear splats blur edges over two of its pixels, and on a 64 x 48
    Biotar render it differed from the block means of a 256 x 192 one by 28 % relative RMSE.
    Pixels whose splat reaches a masked pixel (weight 0) are left out (weight 0), unless that would
    leave nothing: a model rendered at the block resolution cannot see which pixels a mask drops."""
    height, width = plate.rgb.shape[:2]
    if height % block or width % block:
        raise ValueError(f"block must divide the plate's resolution {width} x {height}, got {block}")
    rows, columns = splat_weights(height, block), splat_weights(width, block)

    def spread(image):  # (H, W[, C]) -> (H / block, W / block[, C]), as two matrix products
        flat = image.reshape(height, width, -1)
        out = np.einsum("ih,hwc->iwc", rows, flat, optimize=True)
        out = np.einsum("iwc,jw->ijc", out, columns, optimize=True)
        return out.reshape(out.shape[:2] + image.shape[2:])

    summed = spread(plate.weight)
    values = spread(plate.rgb * plate.weight[..., None]) / np.maximum(summed, 1e-300)[..., None]
    masked = (rows > 0).astype(np.float64) @ (plate.weight == 0).astype(np.float64) @ (columns > 0).astype(np.float64).T > 0
    weighted = summed > 0
    keep = weighted & ~masked if np.any(weighted & ~masked) else weighted
    return Plate(rgb=np.where(keep[..., None], values, 0.0), weight=np.where(keep, summed, 0.0), source=plate.source, layer=plate.layer)


def _full_resolution_image(scene: Scene, grid: GridFlareModel, tints, dirt, gain, film=None) -> np.ndarray:
    """The flare with the fitted parameters at ``scene``'s (the plate's) resolution, from a grid
    model of the paths ``grid`` (the fit's, at the block resolution) drew, at
    :data:`FULL_RESOLUTION_GRID_QUALITY`."""
    full = grid_flare_model(scene, FULL_RESOLUTION_GRID_QUALITY, paths=list(grid.paths))
    return _final_image(_BuiltModel(full, full, full.subsamples), full, scene, tints, dirt, gain, film=film)


def _solve(residuals, free, solver: str, rtol: float, atol: float, max_steps: int, progress, dense: bool = False, physical=None, args=None):
    """Solve with optimistix (``optx.least_squares``, or ``optx.minimise`` for BFGS), wrapped in its
    best-so-far solver, so the parameters returned are the best seen even when the solver stops
    early or a step goes astray; ``residuals(y, args)``. The solver's own verbose hook reports each step's loss, which
    feeds ``progress`` and the loss history (the best loss after each step, the start first).
    Each step reports the loss at the point it evaluates, and the first step evaluates the start:
    the start's loss comes from there, not from a separate compilation of the model."""
    losses: list[float] = []

    def report(**fields):
        def record(loss):
            losses.append(float(loss))
            if progress is not None:
                progress(len(losses), min(losses))

        jax.debug.callback(record, fields["loss_this_step"][1], ordered=True)

    chosen = _solver(solver, rtol, atol, verbose=report, dense=dense, physical=physical)
    if solver == "bfgs":
        solution = optx.minimise(
            lambda y, args: 0.5 * jnp.sum(residuals(y, args) ** 2), optx.BestSoFarMinimiser(chosen), free, args, max_steps=max_steps, throw=False
        )
    else:
        solution = optx.least_squares(residuals, optx.BestSoFarLeastSquares(chosen), free, args, max_steps=max_steps, throw=False)
    result = solution.result
    steps = int(solution.stats["num_steps"])
    initial = losses[0] if losses else float(0.5 * jnp.sum(residuals(free, args) ** 2))
    history = [initial]
    for loss in losses[:steps]:
        history.append(min(history[-1], loss) if math.isfinite(loss) else history[-1])
    converged = bool(result == optx.RESULTS.successful)
    if converged:
        status = "converged"
    elif result in (optx.RESULTS.max_steps_reached, optx.RESULTS.nonlinear_max_steps_reached):
        status = f"not converged in {max_steps} steps"
    else:
        status = f"stopped: {optx.RESULTS[result]}"
    return solution.value, history, steps, converged, status


def _standard_errors(data_residuals, fitted: dict, *, prior_weights: dict, residual_shape=None, data=None) -> tuple[dict, dict]:
    """Standard errors of the fitted parameters ``fitted`` (name -> physical values: tints,
    gains, layer thicknesses and indices; ``data_residuals(values, data)`` maps such a dict to the
    data residuals): ``s^2 kappa (J^T J + W)^-1`` with the Jacobian ``J`` of the data residuals in
    the physical parameters, ``W`` the priors' weights (``prior_weights``, name -> a weight per
    entry or one for all: the loss's own Hessian, so a parameter the plate does not show keeps
    the prior's spread), ``s^2`` the residuals' mean square (the plate's noise and the model's own
    error together) and ``kappa`` >= 1 the residuals' spatial correlation
    (:func:`residual_correlation`: 1 for independent pixels; a model error spread over a ghost
    counts fewer times than it has pixels). The errors with the priors are at least the
    cluster-robust (sandwich) errors over :data:`ROBUST_TILE` tiles (:func:`_tile_sandwich_diagonal`),
    which weigh each parameter's own residuals instead of one scatter for all. Returns the errors
    with the priors and without them (scatter-based: whether the plate alone determines a
    parameter, as ``tint_observable``), as dicts like ``fitted``; directions nothing constrains get
    infinite errors."""
    names = list(fitted)
    if not names:
        return {}, {}
    shapes = {n: fitted[n].shape for n in names}
    sizes = [int(np.prod(shapes[n])) for n in names]
    flat = jnp.concatenate([jnp.ravel(fitted[n]) for n in names])

    def unflatten(x):
        return {n: part.reshape(shapes[n]) for n, part in zip(names, jnp.split(x, np.cumsum(sizes)[:-1]))}

    @eqx.filter_jit  # ``data`` an argument: closed over, its image stacks would be compiled in as constants
    def residuals_and_columns(flat, data):
        residual_at = lambda x: data_residuals(unflatten(x), data)  # noqa: E731
        basis = jnp.eye(flat.size, dtype=flat.dtype)
        # (p, n): memory p x n only; in batches, so that what a derivative shares (contractions of
        # a model's image stacks with the fitted values) is made once a batch
        return residual_at(flat), jax.lax.map(lambda e: jax.jvp(residual_at, (flat,), (e,))[1], basis, batch_size=32)

    r, columns = residuals_and_columns(flat, data)
    data_normal = np.asarray(columns @ columns.T)  # the plate's information alone
    prior = np.concatenate([np.broadcast_to(np.asarray(prior_weights.get(n, 0.0), np.float64), (size,)).ravel() for n, size in zip(names, sizes)])
    normal = data_normal + np.diag(prior)
    dof = max(int(r.size) - flat.size, 1)
    scatter = float(jnp.sum(r**2)) / dof
    scatter *= residual_correlation(np.asarray(r), residual_shape)
    std = np.sqrt(_inverse_diagonal(normal) * scatter)
    data_std = np.sqrt(scatter * _inverse_diagonal(data_normal))
    if residual_shape is not None:  # and no smaller than the cluster-robust (sandwich) error
        std = np.maximum(std, np.sqrt(_tile_sandwich_diagonal(np.asarray(columns), np.asarray(r), residual_shape, normal, ROBUST_TILE)))

    def split(values):
        return {n: part.reshape(shapes[n]) for n, part in zip(names, np.split(values, np.cumsum(sizes)[:-1]))}

    return split(std), split(data_std)


ROBUST_TILE = 2
"""Side (residual pixels: blocks of the plate) of the tiles over which :func:`_standard_errors`'
cluster-robust error lets residuals correlate. Measured on the plate-fit benchmark's 128 x 72
coatings fits (4 x 4 blocks, quick 2^21-sample plates, 20 observable tint channels): truth within
3 standard errors for 80 % (clean) and 85 % (1 % noise) of them with the scatter-based errors
alone, 100 % and 100 % with 2 x 2 tiles, 95 % with 4 x 4, 85-90 % with 8 x 8 (too few tiles for
the parameters: the sandwich's middle matrix loses rank and underestimates)."""


def _tile_sandwich_diagonal(columns: np.ndarray, r: np.ndarray, residual_shape, normal: np.ndarray, tile: int) -> np.ndarray:
    """Diagonal of the cluster-robust (sandwich) covariance ``N^-1 (sum_g s_g s_g^T) N^-1`` with
    ``s_g = J_g^T r_g`` summed over square tiles of ``tile`` x ``tile`` pixels of each plate's
    residual image: a model error correlated within a tile counts once per tile."""
    ids, offset = [], 0
    for shape in residual_shape:
        height, width = shape[:2]
        channels = int(np.prod(shape[2:]))
        across = -(-width // tile)
        rows, cols = np.indices((height, width))
        ids.append(np.repeat(((rows // tile) * across + cols // tile).ravel() + offset, channels))
        offset += -(-height // tile) * across
    ids = np.concatenate(ids)
    scores = np.stack([np.bincount(ids, weights=column * r, minlength=offset) for column in columns])  # (p, tiles)
    inverse = np.linalg.pinv(normal, hermitian=True)
    return np.maximum(np.einsum("ij,jk,ik->i", inverse, scores @ scores.T, inverse), 0.0)


def _inverse_diagonal(normal: np.ndarray) -> np.ndarray:
    """The diagonal of the pseudo-inverse of a symmetric positive semi-definite ``normal``
    matrix, infinite along directions it does not constrain."""
    eigenvalues, eigenvectors = np.linalg.eigh(normal)
    floor = 1e-12 * max(float(eigenvalues.max()), 1e-300)
    inverse_eigen = np.where(eigenvalues > floor, 1.0 / np.maximum(eigenvalues, floor), np.inf)
    with np.errstate(invalid="ignore"):
        return np.nansum(np.where(eigenvectors**2 > 1e-12, eigenvectors**2 * inverse_eigen, 0.0), axis=1)


CORRELATION_BLOCKS = (2, 4, 8)
"""Block sides (pixels) over which :func:`residual_correlation` looks for correlated residuals."""


def residual_correlation(residuals: np.ndarray, shape) -> float:
    """``kappa`` of :func:`_standard_errors`: how many pixels a residual is spread over. For each
    block side ``b`` of :data:`CORRELATION_BLOCKS`, the sum of squared ``b x b`` sums of the residual
    images (``shape``: (H, W, C), or a list of shapes for the plates' residuals one after the other)
    over the sum of squared residuals: 1 when pixels are independent, ``b^2`` when a model error is
    the same over the whole block. The largest over the sides the images are large enough for, at
    least 1 (1 when ``shape`` is None or every image is smaller than 2 x 2). A model error spread
    over a ghost counts as few independent residuals as it has blocks."""
    if shape is None:
        return 1.0
    shapes = [tuple(shape)] if isinstance(shape, tuple) and all(isinstance(v, int) for v in shape) else [tuple(v) for v in shape]
    residuals = np.asarray(residuals, np.float64).ravel()
    images = []
    offset = 0
    for one in shapes:
        size = int(np.prod(one))
        images.append(residuals[offset : offset + size].reshape(one))
        offset += size
    kappa = 1.0
    for side in CORRELATION_BLOCKS:
        single = paired = 0.0
        for image in images:
            if image.shape[0] < side or image.shape[1] < side:
                continue
            h, w = image.shape[0] // side * side, image.shape[1] // side * side
            single += float(np.sum(image[:h, :w] ** 2))
            paired += float(np.sum(image[:h, :w].reshape(h // side, side, w // side, side, -1).sum(axis=(1, 3)) ** 2))
        if single > 0:
            kappa = max(kappa, paired / single)
    return kappa


def save_fit(result: FitResult, path: str | os.PathLike) -> str:
    """Write the fitted parameters as JSON (``path``), the dirt map as ``<stem>_dirt.exr`` beside it
    (clipped to the transmissions [0, 1] a scene's dirt map holds, see :data:`DIRT_MAX`),
    and the re-rendered flare and the residual as ``<stem>_render.exr`` (``<stem>_render_<k>.exr``
    for plate k of a fit of several plates); all atomically."""
    path = os.fspath(path)
    stem = os.path.splitext(path)[0]
    data = result.as_dict()
    renders = [result.render] if result.plates == 1 else list(result.render)
    residuals = [result.residual] if result.plates == 1 else list(result.residual)
    render_files = [stem + "_render.exr"] if result.plates == 1 else [f"{stem}_render_{k}.exr" for k in range(result.plates)]
    dirt_file = stem + "_dirt.exr"
    targets = [path, *render_files] + ([dirt_file] if result.dirt is not None else [])
    # the files are committed together: a reader never sees a JSON next to another fit's renders
    with atomic_output_group(targets, stale=() if result.dirt is not None else (dirt_file,)) as temporaries:
        if result.dirt is not None:
            transmission = np.clip(result.dirt, 0.0, 1.0).astype(np.float32)  # a loadable dirt map (DIRT_MAX)
            write_exr(temporaries[-1], {"": np.ascontiguousarray(transmission)}, pixel_type="float")
            data["dirt_map"] = os.path.basename(dirt_file)
        for temporary, render, residual in zip(temporaries[1 : 1 + len(render_files)], renders, residuals):
            write_exr(temporary, {"": render.astype(np.float32), "residual": residual.astype(np.float32)}, pixel_type="float")
        data["renders"] = [os.path.basename(f) for f in render_files]
        with open(temporaries[0], "w", encoding="utf-8") as handle:
            handle.write(json.dumps(data, indent=2))
    return path


def apply_fit(scene, fitted: str | os.PathLike | dict, *, plate: int | None = None):
    """The scene with fitted parameters (a JSON file from :func:`save_fit` or its dict) applied:
    coating tints or a thin-film fit's coating stacks (as ``surface_coatings``), the dirt map, and light gains (multiplying each light's RGB colour). A fit of
    several plates has light gains per plate: ``plate`` says whose (needed when lights were
    fitted; the coatings and dirt are shared)."""
    if not isinstance(fitted, dict):
        folder = os.path.dirname(os.path.abspath(fitted))
        with open(fitted) as handle:
            fitted = json.load(handle)
    else:
        folder = os.getcwd()
    camera = scene.camera
    changes = {}
    if "coatings" in fitted["fitted"]:
        changes["coating_tints"] = tuple((k, tuple(float(v) for v in rgb)) for k, rgb in enumerate(fitted["coating_tints"]))
    if "thin-film" in fitted["fitted"]:  # the fitted stacks override the scene's coatings surface by surface
        stacks = tuple(
            SurfaceCoating(surfaces=(int(stack["surface"]),), layers=tuple((float(n), float(t)) for n, t in stack["layers"]))
            for stack in fitted["coating_stacks"]
        )
        changes["surface_coatings"] = tuple(camera.surface_coatings) + stacks
    if fitted.get("dirt_map"):
        changes["dirt_map"] = os.path.join(folder, fitted["dirt_map"])
    camera = dataclasses.replace(camera, **changes)
    lights = scene.lights
    light_gain = fitted.get("light_gain")
    plates = int(fitted.get("plates", 1))
    if "lights" in fitted["fitted"] and plates > 1:
        if plate is None or isinstance(plate, bool) or not isinstance(plate, int) or not 0 <= plate < plates:
            raise ValueError(f"the fit has light gains for {plates} plates: pass plate= an index 0 .. {plates - 1} to choose whose, got {plate!r}")
        light_gain = light_gain[plate]
    if "lights" in fitted["fitted"]:
        flare_lights = [k for k, light in enumerate(lights) if light.flare]
        lights = list(lights)
        for gain, k in zip(light_gain, flare_lights):
            light: Light = lights[k]
            if light.rgb is None and (light.spectrum is not None or light.temperature_k is not None):
                scale = float(np.mean(gain))
                lights[k] = dataclasses.replace(light, intensity=light.intensity * scale)
            else:
                base = np.asarray(light.rgb or (1.0, 1.0, 1.0))
                lights[k] = dataclasses.replace(light, rgb=tuple(float(v) for v in base * np.asarray(gain)))
        lights = tuple(lights)
    return dataclasses.replace(scene, camera=camera, lights=lights)
