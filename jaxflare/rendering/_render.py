"""Monte Carlo flare rendering (Pekkarinen & Balzer 2019, sections 2-4).

A sample connects a random point on a light with a random point on the front lens, picks a
wavelength, follows one lens path (a two-reflection ghost, or the primary path for the source's
own image) to the sensor, and is rejected by the clear apertures, the iris (the stop-plane
position of each pass) and the sensor bounds. Survivors are splatted bilinearly into the layer of
their path. Samples run in fixed-size vmapped batches (every path of a group at once), streamed
so memory stays bounded whatever the sample count.

Radiance per sample, the paper's equation (2): ``L(lambda) c_lens l F_lp w_s`` with

- ``L(lambda)``: the light's colour as a spectrum (:mod:`._colour`) times its intensity and the
  geometric factor of the light-lens connection (``cos cos / r^2`` times the sampled areas);
- ``c_lens = c_dirt c_coating``: dirt is 1 (no dirt map yet); ``c_coating`` is the product of the
  RGB tints of the path's two reflecting interfaces (1 unless the camera sets ``coating_tints``);
- ``l``: the cosine of the ray's angle with the sensor normal (Lambertian sensor response);
- ``F_lp``: the path's coated Fresnel factor at normal incidence and the sample's wavelength, times
  the Schlick angle term at the front lens, ``1 - (1 - cos theta)^5`` (the paper), or, with
  ``fresnel="exact"``, the coated Fresnel product at every event at the ray's own angles;
- ``w_s``: the normalised weight of equation (1), ``(1/p_s) / sum_i (1/p_i)``, with ``p_s`` the
  probability of the sample's (light, path, front-lens cell) under the adaptive table
  (:mod:`._adaptive`; uniform for ``sampling="uniform"``) relative to uniform sampling. The paper
  sums over the samples that hit the sensor, which keeps a flare's brightness when the iris blocks
  most of it; jaxflare sums over every sample drawn (``weights="all-samples"``), so a flare holds
  exactly the light that gets through, and offers the paper's normalisation as
  ``weights="sensor-hits"`` (scaled to agree with it when every sample hits).

Model no more than the scene needs: paths whose energy is provably below ``cull_threshold`` of the
brightest flare (an upper bound from their on-axis Fresnel factor and the light entering the lens)
are culled after the pilot, and the bound on the energy dropped is reported.

Units (the paper leaves them as future work). A pixel holds the sensor irradiance it receives,
converted by the camera equation ``E = pi L / (4 N^2)`` into the scene radiance ``L`` that would
give the same irradiance through the lens at its working f-number N. So a flare pixel is directly
comparable with the main render: an extended light of radiance 100 makes a core of about 100 (less
the lens's transmission and vignetting), and its ghosts are that value times their energy fraction.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

from .._limits import MAX_SEED
from ..optics import GhostPath
from ..scenes import ESTIMATORS, Scene, load_scene
from ._grid_render import render_grid
from ._plan import plan_render, run_batches
from ._result import RenderResult, render_result


def render(
    scene: Scene | str,
    quality: str | None = None,
    seed: int = 0,
    *,
    samples: int | None = None,
    method: str | None = None,
    paths: Sequence[GhostPath] | None = None,
    progress: bool | Callable[[int, int], None] = False,
    estimator: str | None = None,
) -> RenderResult:
    """Render the flares of ``scene`` (a :class:`Scene` or a scene TOML path).

    Args:
        scene: the scene; its ``render`` settings apply unless overridden here.
        quality: ``"preview"`` or ``"production"`` (see :data:`QUALITY_LEVELS`); default the scene's.
        seed: random seed, 0 .. 2^32 - 1; the same seed gives the same image.
        samples: total Monte Carlo samples (default the quality's), rounded up to whole batches.
        method: ``"exact"``, ``"polynomial"`` or ``"auto"`` (default the scene's).
        paths: render only these ghost paths ``(j, i)`` (default: every two-reflection path).
        progress: True for a progress bar on stderr, or a callable ``(batches_done, batches)``.
        estimator: ``"monte-carlo"`` (random samples, the default) or ``"grid"`` (the deterministic
            ray-grid estimator, :mod:`._grid`: noise-free; ``samples`` and ``method`` do not apply);
            default the scene's ``[render] estimator`` -- except that ``samples`` or ``method``
            given here make a scene's ``"grid"`` a Monte Carlo render (asking for both explicitly
            is an error).

    Returns:
        A :class:`RenderResult` (image, layers, statistics; ``write_exr``/``write_png``).
    """
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        raise ValueError(f"seed must be an integer from 0 to {MAX_SEED:,}, got {seed!r}")
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    chosen = estimator if estimator is not None else scene.render.estimator
    if estimator is None and chosen == "grid" and (samples is not None or method is not None):
        chosen = "monte-carlo"  # a sample budget or a tracing method asked for is a Monte Carlo render
    if chosen not in ESTIMATORS:
        raise ValueError(f"estimator: must be one of {', '.join(repr(e) for e in ESTIMATORS)}, got {chosen!r}")
    if chosen == "grid":
        if samples is not None or method is not None:
            raise ValueError("estimator='grid' traces exactly on its own grid: samples= and method= apply to estimator='monte-carlo' only")
        return render_grid(scene, quality, seed, paths=paths)
    plan = plan_render(scene, quality, seed, samples=samples, method=method, paths=paths, progress=progress is True)
    render_started = time.perf_counter()
    acc, table_updates = run_batches(plan, progress)
    now = time.perf_counter()
    return render_result(plan, acc, now - render_started, table_updates, time_now=now)
