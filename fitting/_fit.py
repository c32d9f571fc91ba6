"""Fitting coating colours, front-lens dirt and light gains to a plate with optimistix.

Parameters are bounded by reparametrisation (optimistix has no box constraints): coating tints
``t = T_MAX sigmoid(a)`` in [0, T_MAX], dirt ``d = sigmoid(b)`` in [0, 1], light gains
``g = exp(c)`` > 0. Residuals are ``weight x (render - plate)`` over the pixels (RGB), plus a weak
prior on the dirt map (``dirt_prior_weight x (d - prior)``) so cells the flare never lights stay
at their prior instead of drifting, and on the tints towards 1. Solvers (``solver=``):

- ``"levenberg-marquardt"`` and ``"gauss-newton"``: least squares with a matrix-free linear solver
  (``lineax.Normal(lineax.CG(...))``), which scales to large dirt maps;
- ``"bfgs"``: a quasi-Newton minimiser of the sum of squares (dense inverse Hessian: small fits).

The fit runs in float64 with the samples fixed (:mod:`fitting._forward`).
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

from ._forward import FixedSamples, as_float64, fixed_samples, render_image
from ._plate import Plate

PARAMETERS = ("coatings", "dirt", "lights")
"""What a fit can change: per-interface coating colours, the front-lens dirt map, light gains."""
SOLVERS = ("levenberg-marquardt", "gauss-newton", "bfgs")
DEFAULT_SOLVER = "levenberg-marquardt"
DIRT_PRIOR = 0.98
"""A clean front lens, as the dirt map's start and prior: just inside the bound 1 of the sigmoid
(which reaches 1 only at infinity), so cells the flare never lights stay exactly here."""
TINT_MAX = 4.0
"""Coating tints are bounded to [0, TINT_MAX] (relative to the physical coating model)."""


class FlareParameters(eqx.Module):
    """Unconstrained fit variables; :meth:`values` gives the physical ones."""

    tint_logits: jax.Array
    dirt_logits: jax.Array | None
    light_log_gain: jax.Array

    def values(self):
        tints = TINT_MAX * jax.nn.sigmoid(self.tint_logits)
        dirt = None if self.dirt_logits is None else jax.nn.sigmoid(self.dirt_logits)
        return tints, dirt, jnp.exp(self.light_log_gain)


def _logit(x, upper=1.0):
    x = np.clip(np.asarray(x, np.float64) / upper, 1e-6, 1 - 1e-6)
    return np.log(x) - np.log1p(-x)


def initial_parameters(samples: FixedSamples, *, tints=None, dirt=None, dirt_resolution: int = 16, light_gain=None) -> FlareParameters:
    """Start values: tints 1, the dirt prior (a clean lens), gains 1."""
    num_lights = samples.setup.lights.kind.shape[0]
    tints = np.ones((samples.num_interfaces, 3)) if tints is None else np.asarray(tints, np.float64)
    if dirt is None:
        dirt = np.full((dirt_resolution, dirt_resolution, 1), DIRT_PRIOR)
    gains = np.ones((num_lights, 3)) if light_gain is None else np.asarray(light_gain, np.float64)
    return FlareParameters(
        tint_logits=jnp.asarray(_logit(tints, TINT_MAX)), dirt_logits=jnp.asarray(_logit(dirt)), light_log_gain=jnp.asarray(np.log(gains)),
    )


@dataclasses.dataclass
class FitResult:
    """A finished fit: the physical parameters, the solver's verdict, the loss per step, the
    rendered flare and the residual, and timings."""

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
    residual: np.ndarray

    def as_dict(self) -> dict:
        return dict(
            fitted=list(self.fitted), solver=self.solver, converged=self.converged, status=self.status, steps=self.steps,
            loss_history=self.loss_history, seconds=self.seconds, coating_tints=self.coating_tints.tolist(),
            light_gain=self.light_gain.tolist(), dirt_shape=None if self.dirt is None else list(self.dirt.shape),
        )


def _solver(name: str, rtol: float, atol: float):
    if name not in SOLVERS:
        raise ValueError(f"solver must be one of {', '.join(SOLVERS)}, got {name!r}")
    matrix_free = lx.Normal(lx.CG(rtol=1e-6, atol=1e-9, max_steps=500))
    if name == "levenberg-marquardt":
        return optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=matrix_free)
    if name == "gauss-newton":
        return optx.GaussNewton(rtol=rtol, atol=atol, linear_solver=matrix_free)
    return optx.BFGS(rtol=rtol, atol=atol)


def fit(
    scene,
    plate: Plate,
    *,
    params: Sequence[str] = ("coatings", "dirt"),
    solver: str = DEFAULT_SOLVER,
    samples: int = 2**19,
    seed: int = 0,
    method: str = "exact",
    dirt_resolution: int = 16,
    dirt_prior: float = DIRT_PRIOR,
    dirt_prior_weight: float = 1e-3,
    tint_prior_weight: float = 1e-4,
    max_steps: int = 100,
    rtol: float = 1e-6,
    atol: float = 1e-9,
    block: int = 1,
    fixed: FixedSamples | None = None,
    progress: Callable[[int, float], None] | None = None,
) -> FitResult:
    """Fit ``params`` (any of :data:`PARAMETERS`) of ``scene`` so its flare render matches ``plate``.

    The others stay at their start values (tints 1, a clean lens, gains 1). ``samples`` fixed
    samples (drawn with ``seed``) make the render a smooth function of the parameters. A solver
    that does not converge in ``max_steps`` still returns its best parameters, with ``converged``
    False and its ``status``. ``progress(step, loss)`` is called after each step. ``block`` > 1
    compares block averages of ``block`` x ``block`` pixels (weighted by the plate's weights):
    ghosts are smooth and Monte Carlo noise is not, so this keeps a fit to a plate made with other
    samples (or a photograph) from fitting noise.
    """
    unknown = [p for p in params if p not in PARAMETERS]
    if unknown or not params:
        raise ValueError(f"params must be a non-empty subset of {', '.join(PARAMETERS)}, got {list(params)!r}")
    started = time.perf_counter()
    width, height = scene.camera.resolution
    if plate.rgb.shape[:2] != (height, width):
        raise ValueError(
            f"plate {plate.source}: {plate.rgb.shape[1]} x {plate.rgb.shape[0]} pixels, but the scene renders "
            f"{width} x {height} (camera.resolution): they must match"
        )
    with jax.enable_x64(True):
        samples_ = as_float64(fixed if fixed is not None else fixed_samples(scene, samples=samples, seed=seed, method=method))
        start = initial_parameters(samples_, dirt=np.full((dirt_resolution, dirt_resolution, 1), dirt_prior), dirt_resolution=dirt_resolution)
        if "dirt" not in params:
            start = dataclasses.replace(start, dirt_logits=None)
        free_mask = FlareParameters(
            tint_logits="coatings" in params, dirt_logits=None if start.dirt_logits is None else "dirt" in params, light_log_gain="lights" in params,
        )
        free, frozen = eqx.partition(start, free_mask, is_leaf=lambda x: x is None)
        if not (isinstance(block, int) and block >= 1 and width % block == 0 and height % block == 0):
            raise ValueError(f"block must be a positive integer dividing the resolution {width} x {height}, got {block!r}")
        weight = jnp.asarray(plate.weight, jnp.float64)[..., None]

        def pooled(image):  # weighted block averages
            shape = (height // block, block, width // block, block, image.shape[-1])
            return (image * weight).reshape(shape).sum(axis=(1, 3))

        target = pooled(jnp.asarray(plate.rgb, jnp.float64))
        prior = jnp.asarray(dirt_prior, jnp.float64)

        def residuals(free_params, _):
            parameters = eqx.combine(free_params, frozen, is_leaf=lambda x: x is None)
            tints, dirt, gain = parameters.values()
            image = render_image(samples_, tints, dirt, gain)
            parts = [(pooled(image) - target).ravel() / block]
            if dirt is not None and "dirt" in params:
                parts.append(math.sqrt(dirt_prior_weight) * (dirt - prior).ravel())
            if "coatings" in params:
                parts.append(math.sqrt(tint_prior_weight) * (tints - 1.0).ravel())
            return jnp.concatenate(parts)

        chosen = _solver(solver, rtol, atol)
        least_squares = solver != "bfgs"
        fn = residuals if least_squares else (lambda y, a: 0.5 * jnp.sum(residuals(y, a) ** 2))
        # run the solver step by step to report the loss as it goes (optimistix's init/step/terminate)
        options = {}
        f_struct = jax.eval_shape(lambda y: fn(y, None), free)
        aux_struct = None
        tags = frozenset()

        def loss_of(y):
            r = residuals(y, None)
            return 0.5 * jnp.sum(r**2)

        loss_jit = eqx.filter_jit(loss_of)
        state = chosen.init(_fn_aux(fn), free, None, options, f_struct, aux_struct, tags)
        step = eqx.filter_jit(lambda y, s: chosen.step(_fn_aux(fn), y, None, options, s, tags))
        terminate = eqx.filter_jit(lambda y, s: chosen.terminate(_fn_aux(fn), y, None, options, s, tags))
        y = free
        history = [float(loss_jit(y))]
        best, best_loss = y, history[0]
        done, result = False, optx.RESULTS.successful
        steps, diverged = 0, None
        for steps in range(1, max_steps + 1):
            y, state, _ = step(y, state)
            loss = float(loss_jit(y))
            if not math.isfinite(loss):  # a diverging step: stop, keep the best parameters, say so
                diverged = steps
                break
            history.append(loss)
            if loss <= best_loss:
                best, best_loss = y, loss
            if progress is not None:
                progress(steps, loss)
            done, result = terminate(y, state)
            if bool(done):
                break
        converged = diverged is None and bool(done) and bool(result == optx.RESULTS.successful)
        if diverged is not None:
            status = f"diverged at step {diverged} (non-finite loss): returned the best parameters, from step {history.index(best_loss)}"
        elif converged:
            status = "converged"
        else:
            status = f"stopped: {optx.RESULTS[result]}" if bool(done) else f"not converged in {max_steps} steps"
        parameters = eqx.combine(best, frozen, is_leaf=lambda x: x is None)
        tints, dirt, gain = parameters.values()
        image = np.asarray(render_image(samples_, tints, dirt, gain))
    return FitResult(
        coating_tints=np.asarray(tints), dirt=None if dirt is None else np.asarray(dirt), light_gain=np.asarray(gain), fitted=tuple(params),
        solver=solver, converged=converged, status=status, steps=steps, loss_history=history, seconds=time.perf_counter() - started,
        render=image, residual=image - plate.rgb,
    )


def _fn_aux(fn):
    """optimistix solvers call ``fn(y, args)`` and expect ``(out, aux)``."""
    return lambda y, args: (fn(y, args), None)


def save_fit(result: FitResult, path: str | os.PathLike) -> str:
    """Write the fitted parameters as JSON (``path``), the dirt map as ``<stem>_dirt.exr`` beside it,
    and the re-rendered flare and the residual as ``<stem>_render.exr``; all atomically."""
    from jaxflare._exr import write_exr
    from jaxflare._io import write_text_atomic

    path = os.fspath(path)
    stem = os.path.splitext(path)[0]
    data = result.as_dict()
    if result.dirt is not None:
        dirt_file = stem + "_dirt.exr"
        write_exr(dirt_file, {"": np.ascontiguousarray(result.dirt.astype(np.float32))}, pixel_type="float")
        data["dirt_map"] = os.path.basename(dirt_file)
    write_exr(stem + "_render.exr", {"": result.render.astype(np.float32), "residual": result.residual.astype(np.float32)}, pixel_type="float")
    write_text_atomic(path, json.dumps(data, indent=2))
    return path


def apply_fit(scene, fitted: str | os.PathLike | dict):
    """The scene with fitted parameters (a JSON file from :func:`save_fit` or its dict) applied:
    coating tints, the dirt map, and light gains (multiplying each light's RGB colour)."""
    from jaxflare._scene import Light

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
    if fitted.get("dirt_map"):
        changes["dirt_map"] = os.path.join(folder, fitted["dirt_map"])
    camera = dataclasses.replace(camera, **changes)
    lights = scene.lights
    if "lights" in fitted["fitted"]:
        flare_lights = [k for k, light in enumerate(lights) if light.flare]
        lights = list(lights)
        for gain, k in zip(fitted["light_gain"], flare_lights):
            light: Light = lights[k]
            if light.rgb is None and (light.spectrum is not None or light.temperature_k is not None):
                scale = float(np.mean(gain))
                lights[k] = dataclasses.replace(light, intensity=light.intensity * scale)
            else:
                base = np.asarray(light.rgb or (1.0, 1.0, 1.0))
                lights[k] = dataclasses.replace(light, rgb=tuple(float(v) for v in base * np.asarray(gain)))
        lights = tuple(lights)
    return dataclasses.replace(scene, camera=camera, lights=lights)
