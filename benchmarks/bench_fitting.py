"""Fitting solvers compared: recovered coating colours and dirt, and wall time, per solver, on
synthetic plates with known parameters (``fitting.SOLVERS``: levenberg-marquardt, gauss-newton, bfgs).

Run:  python benchmarks/bench_fitting.py [--quick] [--no-polynomial] [--no-dirt] [--joint] [--out DIR]

The scene is the one of ``tests/test_fitting_plates.py``: Zeiss Biotar at f/4, 64x48 pixels, one
directional light at (0.06, 0.03, -1). The true lens has coating tints (1, 0.6, 0.3) on interface 7,
(0.5, 0.9, 1.2) on interface 4 and 1 elsewhere; plates are ``jaxflare.render`` images of the true
scene (its ``camera.coating_tints``, and for the dirt scenarios its ``camera.dirt_map`` file). The
expensive objects are made once and shared by every solver (``fit(..., fixed=...)``): the plates,
the path-image model (``fitting.path_images`` with full-resolution images, reweighted per plate and
block by ``fit``) and the fixed samples of the sample model. Scenarios:

1. ``crn``: common random numbers: the plate is the path-image model's own full-resolution image
   with the true tints (no Monte Carlo difference between plate and model): the noise-free baseline;
   once with the default tint prior and once with ``tint_prior_weight=1e-10`` (what the prior
   itself costs);
2. ``seed``: a plate rendered with another seed (seed 7, 2^22 samples) against the model (seed 0,
   2^22 samples), compared in blocks of 1, 4 and 8 pixels (``block=``);
3. ``polynomial``: the model traced with ``method="polynomial"`` against an exactly traced plate, on
   two ghost paths, (4, 2) and (7, 4), at 96x64 (path systems cost ~20 s per path to build on this
   lens, so only these two; they are cached under ``.cache/jaxflare_bench_fitting`` by default). Each
   path's colour is the product of its two interfaces' tints, and only the products are determined
   (three interfaces, two paths), so the error is on the path colours. The same fit with an exactly
   traced model (``polynomial-exact``) separates the polynomials' error from the plate's noise;
4. ``noise``: the seed-7 plate plus Gaussian noise of 0.5, 1, 2 and 5 % of its peak (one normal
   field, scaled), its sigma declared (``weight = 1 / sigma``), in blocks of 8 and of 1 pixel:
   error against the standard errors;
5. ``background``: a bright textured patch (0.5-1.5 x the plate's peak) over the top-left quarter
   of the seed-7 plate, masked out (weight 0) or not; the masked fit must equal the fit of the
   clean plate under the same mask (``masked_vs_clean`` in the JSON);
6. ``far-start``: the fit starts from the scene's ``coating_tints``: a scene whose tints are all
   3.5 (or all 0.1) instead of 1;
7. ``dirt``: an 8x8 dirt map, clean (1) except a 3x3 blotch at 0.3, rendered into the plate through
   the ``dirt_map`` file (seed 7, with the true tints); the fit of ``params=("dirt",)`` to a scene
   with the true tints (the coatings known) uses the sample model (2^19 fixed samples, seed 0).
   Dirt RMSE and PSNR (peak 1) over the lit cells (``dirt_sensitivity > 0.2``) and over all 64
   cells; the cells no light reaches (sensitivity exactly 0: unobservable) must keep
   ``fitting.DIRT_PRIOR`` exactly;
8. ``joint`` (only with ``--joint``: it adds 4-9 minutes): coatings and dirt together, same plate,
   from unit tints (the sample model with 2^18 samples, half of scenario 7's: with 2^19 the
   Levenberg-Marquardt fit alone took 270 s).

Before the scenarios, the fixed cost of a fit is measured: a 1-step fit per solver (after an
untimed warm-up; ``checks.fit_overhead_seconds``). Path-image fits are dominated by it: ``fit``
traces and compiles its own closures on every call.

Every fit uses ``fit``'s defaults (``max_steps=100``, ``rtol=1e-6``, ``atol=1e-9``, the priors)
except ``block`` and the inputs above; scenarios 3 and 5-8 compare 8x8 blocks (``BLOCK``), 4 both 8 and 1. A fit is
deterministic: each runs once for its result, and, when that took under ``retime_below_s``, once
more for a second timing (the median of both is ``fit_seconds``; both runs must give the same
parameters: ``repeat_difference``). Fit times include ``fit``'s own tracing and compilation (every
call builds new closures, so nothing is reused between calls), not the compilation every fit of a
shape shares (an untimed 1-step fit runs first for each solver, block, resolution and model); the
sample-model fits (7, 8) run with jax's caches cleared before each
(:func:`release_compiled`: memory), so they include all their compilation. Model and plate build
times are separate columns (``model_seconds``, ``plate_seconds``), paid once per scenario, not per
solver.

Metrics per (scenario, variant, solver): ``fit_seconds``, ``steps``, ``converged``, ``status``,
``tint_error_47`` (max abs error of interfaces 4 and 7, every channel), ``tint_error_observable``
(max abs error over the interfaces the fit calls observable: every channel's ``tint_std`` below
``fitting.OBSERVABLE_STD``; none may be), ``tint_error_observable_channels`` (the same over single
channels with ``tint_std`` below it; ``observable_channels`` counts them), ``tint_error_all``, ``within_3se`` (the fraction of channel errors on
the observable interfaces and 4 and 7 that lie within 3 of the fit's standard errors),
``tint_std_47`` (the largest standard error on 4 and 7), ``path_colour_error`` (scenario 3),
``final_loss`` (the relative loss ``0.5 |w r|^2 / |w plate|^2`` plus priors, of the parameters the
fit returned: its best step), ``loss_ratio`` (final / initial), ``loss_change_last10`` (for a fit
that ran out of steps, the relative drop of the loss over its last 10 steps: near 0 means it had
stalled, not that it was still moving), and the dirt RMSE / PSNR columns.

``--quick``: fewer samples (2^18 plate and model, 2^16 for the sample model), block 8 only, two
noise levels, one far start, dirt fits capped at 20 steps, no joint fit, each fit timed once; writes
into a new temporary folder (printed) unless ``--out`` is given, never into ``benchmarks/results``.

Outputs (atomic writes) under ``benchmarks/results/``: ``fitting_solvers.csv`` (one row per
scenario, variant and solver), ``fitting_solvers.json`` (the rows, each fit's loss history and
fitted values, the build times, the machine header with the load average at start and end) and
``fitting_solvers.png`` (error against fit time per solver and scenario; the noise sweep per block:
tint error and 3 standard errors against noise level; the dirt maps).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from _harness import (
    REPO,
    GuardedSteps,
    Outputs,
    add_out_option,
    announce,
    cpu_label,
    fmt,
    log,
    make_parser,
    output_folder,
    pyplot,
    run_meta,
    shown_paths,
    temporary_env,
)

STEM = "fitting_solvers"
DEFAULT_CACHE = REPO / ".cache" / "jaxflare_bench_fitting"

NUM_INTERFACES = 10
TRUE_TINTS = np.ones((NUM_INTERFACES, 3))
TRUE_TINTS[7] = (1.0, 0.6, 0.3)
TRUE_TINTS[4] = (0.5, 0.9, 1.2)
COLOURED = [4, 7]
POLY_PATHS = [(4, 2), (7, 4)]
BLOCK = 8
LIT = 0.2  # dirt cells with sensitivity above this count as lit

FULL = {
    "resolution": (64, 48), "light": (0.06, 0.03, -1.0), "plate_samples": 2**22, "plate_seed": 7, "model_samples": 2**22,
    "model_seed": 0, "blocks": [1, 4, 8], "noise_levels": [0.005, 0.01, 0.02, 0.05], "noise_blocks": [BLOCK, 1], "noise_seed": 3,
    "background_seed": 5,
    "far_starts": [3.5, 0.1], "poly_resolution": (96, 64), "poly_samples": 2**21, "poly_paths": POLY_PATHS,
    "dirt_resolution": 8, "dirt_plate_samples": 2**21, "dirt_model_samples": 2**19, "dirt_max_steps": 100, "joint": False,
    "joint_model_samples": 2**18, "polynomial": True, "dirt": True, "retime_below_s": 8.0,
}
QUICK = dict(FULL, plate_samples=2**18, model_samples=2**18, blocks=[8], noise_levels=[0.01, 0.05], noise_blocks=[BLOCK], far_starts=[3.5],
             poly_samples=2**17, dirt_plate_samples=2**18, dirt_model_samples=2**16, dirt_max_steps=20, joint=False,
             retime_below_s=0.0)

CSV_FIELDS = [
    "scenario", "variant", "solver", "model", "method", "model_samples", "plate_samples", "block", "fit_seconds", "fit_runs",
    "model_seconds", "plate_seconds", "steps", "converged", "status", "tint_error_47", "tint_error_observable", "tint_error_all",
    "observable_interfaces", "tint_error_observable_channels", "observable_channels", "within_3se", "tint_std_47", "path_colour_error", "path_colour_rel_error", "final_loss", "loss_ratio",
    "loss_change_last10", "noise_fraction", "dirt_rmse_lit", "dirt_psnr_lit", "dirt_rmse_all", "dirt_psnr_all", "dirt_lit_cells",
    "dirt_dark_cells", "dirt_dark_max_deviation", "repeat_difference", "machine",
]


# --------------------------------------------------------------------------- scene and metrics


def with_tints(scene, tints):
    camera = dataclasses.replace(scene.camera, coating_tints=tuple((k, tuple(float(v) for v in rgb)) for k, rgb in enumerate(tints)))
    return dataclasses.replace(scene, camera=camera)


def with_camera(scene, **changes):
    return dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, **changes))


def psnr(rmse: float, peak: float = 1.0) -> float:
    return 20.0 * math.log10(peak / rmse) if rmse > 0 else float("inf")


def tint_metrics(result, truth=TRUE_TINTS) -> dict:
    """Recovered-tint errors of a coatings fit (see the module docstring)."""
    if result.tint_std is None:
        return {}
    tints, std = np.asarray(result.coating_tints), np.asarray(result.tint_std)
    error = np.abs(tints - truth)
    observable = np.all(std < _observable_std(), axis=1)
    checked = observable.copy()
    checked[COLOURED] = True
    with np.errstate(invalid="ignore"):
        within = float(np.mean(error[checked] <= 3.0 * std[checked]))
    channels = std < _observable_std()
    return {
        "tint_error_47": float(error[COLOURED].max()), "tint_error_observable": float(error[observable].max()) if observable.any() else float("nan"),
        "tint_error_observable_channels": float(error[channels].max()) if channels.any() else float("nan"),
        "observable_channels": int(channels.sum()), "tint_error_all": float(error.max()), "observable_interfaces": " ".join(str(k) for k in np.flatnonzero(observable)),
        "within_3se": within, "tint_std_47": float(std[COLOURED].max()),
    }


def path_colour_metrics(result, paths, truth=TRUE_TINTS) -> dict:
    tints = np.asarray(result.coating_tints)
    fitted = np.array([tints[j] * tints[i] for j, i in paths])
    true = np.array([truth[j] * truth[i] for j, i in paths])
    return {"path_colour_error": float(np.abs(fitted - true).max()), "path_colour_rel_error": float(np.abs(fitted / true - 1.0).max())}


def dirt_metrics(result, truth) -> dict:
    if result.dirt is None:
        return {}
    dirt, sensitivity, truth = np.asarray(result.dirt)[..., 0], np.asarray(result.dirt_sensitivity)[..., 0], np.asarray(truth)[..., 0]
    import fitting

    lit, dark = sensitivity > LIT, sensitivity == 0.0
    error = dirt - truth
    rmse_lit = float(np.sqrt(np.mean(error[lit] ** 2))) if lit.any() else float("nan")
    rmse_all = float(np.sqrt(np.mean(error**2)))
    return {
        "dirt_rmse_lit": rmse_lit, "dirt_psnr_lit": psnr(rmse_lit), "dirt_rmse_all": rmse_all, "dirt_psnr_all": psnr(rmse_all),
        "dirt_lit_cells": int(lit.sum()), "dirt_dark_cells": int(dark.sum()),
        "dirt_dark_max_deviation": float(np.abs(dirt[dark] - fitting.DIRT_PRIOR).max()) if dark.any() else float("nan"),
    }


def loss_metrics(result) -> dict:
    """The loss of the parameters the fit returned (its best: the last step's loss when it diverged
    or went uphill is not that), its ratio to the start's, and for a fit that ran out of steps the
    relative drop of the loss over its last 10 steps (about 0: it had stalled)."""
    history = result.loss_history
    best = min(history)
    stalled = not result.converged and "not converged" in result.status and len(history) > 10 and history[-1] > 0
    last10 = (history[-11] - history[-1]) / history[-1] if stalled else float("nan")
    return {"final_loss": best, "loss_ratio": best / history[0] if history[0] > 0 else float("nan"), "loss_change_last10": last10}


def release_compiled() -> None:
    """Drop jax's compiled-function caches. Every ``fitting.fit`` call traces and compiles its own
    closures, and the compiled code stays cached: about 35 MiB per path-image fit and several
    hundred per sample-model fit, never reused. Cleared before and after each sample-model fit
    (those are then timed with their compile, as a first fit in a process is), so the run's memory
    stays a few GiB on the shared machine."""
    import gc

    import jax

    gc.collect()
    jax.clear_caches()


def peak_rss_mib() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _observable_std() -> float:
    import fitting

    return fitting.OBSERVABLE_STD


# --------------------------------------------------------------------------- the benchmark


class FittingBench(GuardedSteps):
    def __init__(self, cfg: dict, machine: str, log, work: Path, cache_dir: Path):
        import jaxflare as jf

        self.cfg, self.machine, self.log, self.work, self.cache_dir = cfg, machine, log, work, cache_dir
        self.jf = jf
        self.scene = jf.Scene(
            camera=jf.Camera(lens="zeiss_biotar", f_number=4.0, resolution=tuple(cfg["resolution"]), look_at_m=(0.0, 0.0, -10.0)),
            lights=(jf.Light(kind="directional", direction=tuple(cfg["light"])),),
        )
        self.rows: list[dict] = []
        self.fits: list[dict] = []
        self.builds: dict = {}
        self.checks: dict = {}
        self.skipped: list[str] = []
        self.dirt_maps: dict = {}
        self.warmed: set = set()

    # ---- shared objects
    def timed_build(self, name: str, fn, **info):
        t0 = time.perf_counter()
        value = fn()
        seconds = time.perf_counter() - t0
        self.builds[name] = {"seconds": seconds, **info}
        self.log(f"  built {name:34s} {seconds:8.1f} s  {info}")
        return value, seconds

    def render_plate(self, scene, samples: int, seed: int, **kwargs) -> np.ndarray:
        return np.asarray(self.jf.render(scene, samples=samples, seed=seed, **kwargs).image[..., :3], np.float64)

    # ---- one fit, timed, with its metrics
    def fit_row(self, scenario: str, variant: str, solver: str, scene, plate, fixed, *, model_seconds: float, plate_seconds: float,
                plate_samples: int | None, truth_dirt=None, paths=None, method: str = "exact", extra: dict | None = None,
                retime: bool = True, **kwargs) -> tuple[dict, object]:
        import fitting

        if "dirt" not in kwargs.get("params", ()):  # sample-model fits are timed cold (see release_compiled)
            self.warm_up(solver, scene, plate, fixed, **kwargs)
        runs, result, first = [], None, None
        repeat_difference = float("nan")
        repeat = 2 if retime else 1
        for k in range(repeat):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                t0 = time.perf_counter()
                out = fitting.fit(scene, plate, solver=solver, fixed=fixed, **kwargs)
                runs.append(time.perf_counter() - t0)
            if k == 0:
                result = first = out
                if runs[0] >= self.cfg["retime_below_s"]:
                    break
            else:
                first_values = np.concatenate([np.ravel(first.coating_tints)] + ([np.ravel(first.dirt)] if first.dirt is not None else []))
                values = np.concatenate([np.ravel(out.coating_tints)] + ([np.ravel(out.dirt)] if out.dirt is not None else []))
                repeat_difference = float(np.abs(values - first_values).max())
        row = {
            "scenario": scenario, "variant": variant, "solver": solver, "model": result.model, "method": method,
            "model_samples": result.samples, "plate_samples": plate_samples, "block": result.block,
            "fit_seconds": statistics.median(runs), "fit_runs": len(runs), "model_seconds": model_seconds, "plate_seconds": plate_seconds,
            "steps": result.steps, "converged": result.converged, "status": result.status,
            **tint_metrics(result), **loss_metrics(result), "repeat_difference": repeat_difference,
            "machine": self.machine,
        }
        if paths is not None:
            row.update(path_colour_metrics(result, paths))
        if truth_dirt is not None:
            row.update(dirt_metrics(result, truth_dirt))
        row.update(extra or {})
        self.rows.append(row)
        self.fits.append({
            "scenario": scenario, "variant": variant, "solver": solver, "fit_seconds_runs": runs, "loss_history": result.loss_history,
            "coating_tints": np.asarray(result.coating_tints), "tint_std": result.tint_std,
            "dirt": None if result.dirt is None else np.asarray(result.dirt)[..., 0],
            "dirt_sensitivity": None if result.dirt_sensitivity is None else np.asarray(result.dirt_sensitivity)[..., 0],
        })
        headline = row.get("dirt_rmse_lit") if truth_dirt is not None and "coatings" not in kwargs.get("params", ()) else (
            row.get("path_colour_error") if paths is not None else row.get("tint_error_47"))
        label = "dirt RMSE (lit)" if truth_dirt is not None and "coatings" not in kwargs.get("params", ()) else (
            "path-colour err" if paths is not None else "tint err 4,7")
        self.log(f"  {scenario:11s} {variant:22s} {solver:20s} {label} {fmt(headline, '7.4f')}  "
                 f"{fmt(row['fit_seconds'], '6.2f')} s ({len(runs)}x)  {result.steps:3d} steps  {result.status}")
        return row, result

    def solvers(self):
        import fitting

        return list(fitting.SOLVERS)

    # ---- 1, 2, 4, 5, 6: the path-image model against the seed-7 plate
    def shared(self) -> None:
        from fitting import path_images

        cfg = self.cfg
        self.log(f"\n-- shared objects: {cfg['resolution'][0]}x{cfg['resolution'][1]}, light {cfg['light']}")
        truth = with_tints(self.scene, TRUE_TINTS)
        self.plate_rgb, self.plate_seconds = self.timed_build(
            "plate (seed 7)", lambda: self.render_plate(truth, cfg["plate_samples"], cfg["plate_seed"]), samples=cfg["plate_samples"], seed=cfg["plate_seed"])
        self.images, self.model_seconds = self.timed_build(
            "path images (seed 0)", lambda: path_images(self.scene, samples=cfg["model_samples"], seed=cfg["model_seed"]),
            samples=cfg["model_samples"], seed=cfg["model_seed"])
        assert self.images.full_images is not None, "the path images keep no full-resolution images: they cannot be reweighted per plate"

    def warm_up(self, solver: str, scene, plate, fixed, **kwargs) -> None:
        """One untimed 1-step fit with this solver, model and shapes (block, resolution, parameters),
        unless one ran already: no timed fit pays for compiling what every fit of its shape shares
        (a fit's own closures are traced and compiled anew on every call, and that is timed)."""
        import fitting

        key = (solver, tuple(scene.camera.resolution), kwargs.get("block", 1), type(fixed).__name__, tuple(kwargs.get("params", ())))
        if key in self.warmed:
            return
        self.warmed.add(key)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fitting.fit(scene, plate, solver=solver, fixed=fixed, **dict(kwargs, max_steps=1))

    def overhead(self) -> None:
        """The fixed cost of a fit: a 1-step fit (after a warm-up) on the seed-7 plate, block 8."""
        import fitting

        self.log(f"\n-- fit overhead: 1-step fits (path-image model, seed-7 plate, block {BLOCK}), after an untimed warm-up")
        plate = self.plate()
        self.checks["fit_overhead_seconds"] = {}
        for solver in self.solvers():
            self.warm_up(solver, self.scene, plate, self.images, params=("coatings",), block=BLOCK)
            runs = []
            for _ in range(2):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    t0 = time.perf_counter()
                    fitting.fit(self.scene, plate, solver=solver, fixed=self.images, params=("coatings",), block=BLOCK, max_steps=1)
                    runs.append(time.perf_counter() - t0)
            self.checks["fit_overhead_seconds"][solver] = statistics.median(runs)
            self.log(f"  {solver:20s} 1-step fit {statistics.median(runs):6.2f} s (runs {', '.join(f'{t:.2f}' for t in runs)})")

    def crn(self) -> None:
        import jax.numpy as jnp

        import fitting
        from fitting import path_image_model

        self.log("\n-- 1. common random numbers: the plate is the model's own image with the true tints")
        image = np.asarray(path_image_model(self.images, jnp.asarray(TRUE_TINTS, jnp.float32), full=True), np.float64)
        plate = fitting.Plate(rgb=image, weight=np.ones(image.shape[:2]), source="crn", layer="")
        for variant, prior in (("block 1", {}), ("block 1, prior 1e-10", {"tint_prior_weight": 1e-10})):
            for solver in self.solvers():
                self.fit_row("crn", variant, solver, self.scene, plate, self.images, model_seconds=self.model_seconds, plate_seconds=0.0,
                             plate_samples=None, params=("coatings",), block=1, **prior)

    def plate(self, rgb=None, weight=None, source="seed 7"):
        import fitting

        rgb = self.plate_rgb if rgb is None else rgb
        return fitting.Plate(rgb=rgb, weight=np.ones(rgb.shape[:2]) if weight is None else weight, source=source, layer="")

    def seed(self) -> None:
        self.log(f"\n-- 2. plate with another seed ({self.cfg['plate_samples']} samples, seed {self.cfg['plate_seed']}), blocks {self.cfg['blocks']}")
        plate = self.plate()
        for block in self.cfg["blocks"]:
            for solver in self.solvers():
                self.fit_row("seed", f"block {block}", solver, self.scene, plate, self.images, model_seconds=self.model_seconds,
                             plate_seconds=self.plate_seconds, plate_samples=self.cfg["plate_samples"], params=("coatings",), block=block)

    def noise(self) -> None:
        cfg = self.cfg
        self.log(f"\n-- 4. added Gaussian noise, sigma declared (weight 1/sigma), blocks {cfg['noise_blocks']}: {cfg['noise_levels']} of the peak")
        field = np.random.default_rng(cfg["noise_seed"]).normal(0.0, 1.0, self.plate_rgb.shape)
        peak = float(self.plate_rgb.max())
        for block in cfg["noise_blocks"]:
            for level in cfg["noise_levels"]:
                sigma = level * peak
                plate = self.plate(self.plate_rgb + sigma * field, np.full(self.plate_rgb.shape[:2], 1.0 / sigma), f"noise {level:g}")
                for solver in self.solvers():
                    self.fit_row("noise", f"{100 * level:g} %, block {block}", solver, self.scene, plate, self.images,
                                 model_seconds=self.model_seconds, plate_seconds=self.plate_seconds, plate_samples=cfg["plate_samples"],
                                 params=("coatings",), block=block, extra={"noise_fraction": level})

    def background(self) -> None:
        cfg = self.cfg
        height, width = self.plate_rgb.shape[:2]
        self.log(f"\n-- 5. textured background over the top-left quarter ({height // 2}x{width // 2} px), masked or not, block {BLOCK}")
        rng = np.random.default_rng(cfg["background_seed"])
        background = np.zeros_like(self.plate_rgb)
        background[: height // 2, : width // 2] = self.plate_rgb.max() * (0.5 + rng.random((height // 2, width // 2, 3)))
        mask = np.ones((height, width))
        mask[: height // 2, : width // 2] = 0.0
        cases = [("masked", self.plate(self.plate_rgb + background, mask, "background, masked")),
                 ("not masked", self.plate(self.plate_rgb + background, None, "background, not masked"))]
        clean_masked = self.plate(self.plate_rgb, mask, "clean, masked")
        self.checks["background_masked_vs_clean"] = {}
        for variant, plate in cases:
            for solver in self.solvers():
                _, result = self.fit_row("background", variant, solver, self.scene, plate, self.images, model_seconds=self.model_seconds,
                                         plate_seconds=self.plate_seconds, plate_samples=cfg["plate_samples"], params=("coatings",), block=BLOCK)
                if variant == "masked":
                    import fitting

                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        clean = fitting.fit(self.scene, clean_masked, solver=solver, fixed=self.images, params=("coatings",), block=BLOCK)
                    difference = float(np.abs(result.coating_tints - clean.coating_tints).max())
                    residual_in_mask = float(np.abs(result.residual[: height // 2, : width // 2]).max())
                    self.checks["background_masked_vs_clean"][solver] = {"max_tint_difference": difference, "max_residual_under_mask": residual_in_mask}
                    self.log(f"      masked fit vs the clean plate under the same mask: max tint difference {difference:.2e}, "
                             f"max residual under the mask {residual_in_mask:.1e}")

    def far_start(self) -> None:
        cfg = self.cfg
        self.log(f"\n-- 6. far initial guess: every tint of the scene {cfg['far_starts']} instead of 1, block {BLOCK}")
        plate = self.plate()
        for start in cfg["far_starts"]:
            scene = with_tints(self.scene, np.full((NUM_INTERFACES, 3), start))
            for solver in self.solvers():
                self.fit_row("far-start", f"tints {start:g}", solver, scene, plate, self.images, model_seconds=self.model_seconds,
                             plate_seconds=self.plate_seconds, plate_samples=cfg["plate_samples"], params=("coatings",), block=BLOCK)

    # ---- 3. polynomial model against an exact plate
    def polynomial(self) -> None:
        from fitting import path_images

        cfg = self.cfg
        paths = [tuple(p) for p in cfg["poly_paths"]]
        scene = with_camera(self.scene, resolution=tuple(cfg["poly_resolution"]))
        self.log(f"\n-- 3. polynomial model vs an exactly traced plate: paths {paths}, {cfg['poly_resolution'][0]}x{cfg['poly_resolution'][1]}, "
                 f"{cfg['poly_samples']} samples, block {BLOCK}; JAXFLARE_CACHE_DIR={self.cache_dir}")
        self.cache_dir.mkdir(parents=True, exist_ok=True)
        cached_before = len(list(self.cache_dir.glob("*.npz")))
        with temporary_env("JAXFLARE_CACHE_DIR", str(self.cache_dir)):
            rgb, plate_seconds = self.timed_build(
                "exact plate (polynomial scenario)",
                lambda: self.render_plate(with_tints(scene, TRUE_TINTS), cfg["poly_samples"], cfg["plate_seed"], method="exact", paths=paths),
                samples=cfg["poly_samples"], seed=cfg["plate_seed"], paths=paths)
            poly, poly_seconds = self.timed_build(
                "polynomial path images", lambda: path_images(scene, samples=cfg["poly_samples"], seed=cfg["model_seed"], method="polynomial", paths=paths),
                samples=cfg["poly_samples"], cache_files_before=cached_before)
            self.builds["polynomial path images"]["cache_files_after"] = len(list(self.cache_dir.glob("*.npz")))
            self.builds["polynomial path images"]["cold_cache"] = self.builds["polynomial path images"]["cache_files_after"] > cached_before
            exact, exact_seconds = self.timed_build(
                "exact path images (reference)", lambda: path_images(scene, samples=cfg["poly_samples"], seed=cfg["model_seed"], method="exact", paths=paths),
                samples=cfg["poly_samples"])
        full_poly, full_exact = np.asarray(poly.full_images, np.float64), np.asarray(exact.full_images, np.float64)
        self.checks["polynomial_vs_exact_images"] = {
            "relative_l2_difference": float(np.linalg.norm(full_poly - full_exact) / np.linalg.norm(full_exact)),
            "energy_ratio": float(full_poly.sum() / full_exact.sum()),
        }
        self.log(f"      polynomial vs exact path images (same seed): relative L2 difference "
                 f"{self.checks['polynomial_vs_exact_images']['relative_l2_difference']:.3f}, energy ratio "
                 f"{self.checks['polynomial_vs_exact_images']['energy_ratio']:.4f}")
        plate = self.plate(rgb, None, "exact plate")
        for variant, fixed, seconds, method in (("polynomial model", poly, poly_seconds, "polynomial"), ("exact model", exact, exact_seconds, "exact")):
            for solver in self.solvers():
                self.fit_row("polynomial" if method == "polynomial" else "polynomial-exact", variant, solver, scene, plate, fixed,
                             model_seconds=seconds, plate_seconds=plate_seconds, plate_samples=cfg["poly_samples"], paths=paths,
                             method=method, params=("coatings",), block=BLOCK)

    # ---- 7, 8. dirt
    def dirt(self) -> None:
        import fitting
        from fitting import fixed_samples

        cfg = self.cfg
        n = cfg["dirt_resolution"]
        truth = np.ones((n, n, 1), np.float32)
        truth[n // 4 : n // 4 + 3, 3 * n // 8 : 3 * n // 8 + 3] = 0.3
        self.dirt_maps["truth"] = truth[..., 0]
        dirt_file = self.work / "dirt.exr"
        self.jf.write_exr(dirt_file, {"": truth}, pixel_type="float")
        true_scene = with_tints(self.scene, TRUE_TINTS)
        self.log(f"\n-- 7. dirt: {n}x{n} map, blotch of 3x3 cells at 0.3; plate {cfg['dirt_plate_samples']} samples (seed {cfg['plate_seed']}) "
                 f"through the dirt_map file; sample model {cfg['dirt_model_samples']} samples; block {BLOCK}")
        rgb, plate_seconds = self.timed_build(
            "dirty plate (seed 7)", lambda: self.render_plate(with_camera(true_scene, dirt_map=str(dirt_file)), cfg["dirt_plate_samples"], cfg["plate_seed"]),
            samples=cfg["dirt_plate_samples"])
        samples, model_seconds = self.timed_build(
            "fixed samples (seed 0)", lambda: fixed_samples(self.scene, samples=cfg["dirt_model_samples"], seed=cfg["model_seed"]),
            samples=cfg["dirt_model_samples"])
        plate = self.plate(rgb, None, "dirty plate")
        release_compiled()
        common = {"model_seconds": model_seconds, "plate_seconds": plate_seconds, "plate_samples": cfg["dirt_plate_samples"], "truth_dirt": truth,
                  "block": BLOCK, "dirt_resolution": n, "max_steps": cfg["dirt_max_steps"]}
        for solver in self.solvers():
            _, result = self.fit_row("dirt", "coatings known", solver, true_scene, plate, samples, params=("dirt",), **common)
            self.dirt_maps[solver] = np.asarray(result.dirt)[..., 0]
            self.dirt_maps["sensitivity"] = np.asarray(result.dirt_sensitivity)[..., 0]
            del result
            release_compiled()
        self.checks["dirt_prior"] = fitting.DIRT_PRIOR
        if cfg["joint"]:
            self.log(f"\n-- 8. coatings and dirt together, from unit tints (sample model, {cfg['joint_model_samples']} samples)")
            if cfg["joint_model_samples"] != cfg["dirt_model_samples"]:
                samples, model_seconds = self.timed_build(
                    "fixed samples (joint, seed 0)", lambda: fixed_samples(self.scene, samples=cfg["joint_model_samples"], seed=cfg["model_seed"]),
                    samples=cfg["joint_model_samples"])
                common["model_seconds"] = model_seconds
            for solver in self.solvers():
                self.fit_row("joint", "coatings + dirt", solver, self.scene, plate, samples, params=("coatings", "dirt"), retime=False, **common)
                release_compiled()
        else:
            self.skipped.append("scenario 8, joint coatings + dirt fit (run with --joint)")

    def run(self) -> None:
        cfg = self.cfg
        self.step("shared objects", self.shared)
        if hasattr(self, "images"):
            self.step("fit overhead", self.overhead)
            self.step("crn", self.crn)
            self.step("seed", self.seed)
            self.step("noise", self.noise)
            self.step("background", self.background)
            self.step("far start", self.far_start)
        if cfg["polynomial"]:
            self.step("polynomial", self.polynomial)
        else:
            self.skipped.append("polynomial scenario (--no-polynomial)")
        if cfg["dirt"]:
            self.step("dirt", self.dirt)
        else:
            self.skipped.append("dirt scenarios (--no-dirt)")


# --------------------------------------------------------------------------- outputs


SOLVER_COLOURS = {"levenberg-marquardt": "C0", "gauss-newton": "C3", "bfgs": "C2"}
SCENARIO_MARKERS = {"crn": "o", "seed": "s", "polynomial": "P", "polynomial-exact": "X", "noise": "^", "background": "D", "far-start": "v",
                    "dirt": "*", "joint": "h"}


def headline(row: dict) -> tuple[float, str]:
    if row["scenario"] == "dirt":
        return row.get("dirt_rmse_lit", float("nan")), "dirt RMSE (lit cells)"
    if row["scenario"].startswith("polynomial"):
        return row.get("path_colour_error", float("nan")), "path-colour error"
    return row.get("tint_error_47", float("nan")), "tint error 4, 7"


def _chart(bench: FittingBench, meta: dict):
    plt = pyplot()
    import matplotlib.ticker

    maps = [k for k in ("truth", "sensitivity", *SOLVER_COLOURS) if k in bench.dirt_maps]
    noise_rows = [r for r in bench.rows if r["scenario"] == "noise"]
    noise_blocks = sorted({r["block"] for r in noise_rows}, reverse=True)
    panels = 1 + len(noise_blocks)
    columns = 15
    fig = plt.figure(figsize=(16.0, 9.5 if maps else 5.8))
    grid = fig.add_gridspec(2 if maps else 1, columns, height_ratios=[1.5, 1] if maps else [1])
    width = columns // panels

    ax = fig.add_subplot(grid[0, :width])
    for row in bench.rows:
        value, _ = headline(row)
        if not (math.isfinite(value) and row["fit_seconds"] > 0):
            continue
        colour = SOLVER_COLOURS.get(row["solver"], "k")
        ax.plot([row["fit_seconds"]], [max(value, 1e-4)], SCENARIO_MARKERS.get(row["scenario"], "o"), color=colour, ms=8,
                mfc=colour if row["converged"] else "none", alpha=0.85)
    for solver, colour in SOLVER_COLOURS.items():
        ax.plot([], [], "s", color=colour, label=solver)
    for scenario, marker in SCENARIO_MARKERS.items():
        if any(r["scenario"] == scenario for r in bench.rows):
            ax.plot([], [], marker, color="0.4", mfc="none", label=scenario)
    ax.plot([], [], "o", color="0.4", label="filled: converged; hollow: not")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("fit wall time [s] (models shared, built outside)")
    ax.set_ylabel("max |tint - truth| on 4, 7; path colour (polynomial); dirt RMSE, lit (dirt)", fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=6.5, ncol=2, loc="best")
    ax.set_title("error against fit time, per solver and scenario (values < 1e-4 drawn at 1e-4)", fontsize=9)

    first = None
    for k, block in enumerate(noise_blocks):
        ax = fig.add_subplot(grid[0, (k + 1) * width : (k + 2) * width], sharey=first)
        first = first or ax
        for solver, colour in SOLVER_COLOURS.items():
            rows = sorted((r for r in noise_rows if r["solver"] == solver and r["block"] == block), key=lambda r: r["noise_fraction"])
            if not rows:
                continue
            x = [100 * r["noise_fraction"] for r in rows]
            wide = 4.5 if solver == "levenberg-marquardt" else 1.5  # drawn under the others: LM and GN often coincide
            ax.plot(x, [r["tint_error_47"] for r in rows], "o-", color=colour, lw=wide, ms=8 if wide > 2 else 5, alpha=0.8,
                    label=f"{solver}: max error on 4, 7")
            ax.plot(x, [3 * r["tint_std_47"] for r in rows], "--", color=colour, lw=wide, alpha=0.6, label=f"{solver}: 3 x largest standard error")
        seed = [r for r in bench.rows if r["scenario"] == "seed" and r["block"] == block and r["solver"] == "levenberg-marquardt"]
        if seed:
            ax.axhline(seed[0]["tint_error_47"], color="0.5", ls=":", lw=1, label="no added noise (seed plate, LM)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        levels = sorted({100 * r["noise_fraction"] for r in noise_rows})
        ax.set_xticks(levels, [f"{v:g}" for v in levels])
        ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        ax.set_xlabel("added Gaussian noise [% of the plate's peak], sigma declared")
        ax.set_ylabel("tint error, 3 x standard error")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6.5)
        ax.set_title(f"noise sweep, block {block} (path-image model, {meta['config']['model_samples']} samples)", fontsize=9)

    titles = {"truth": "true dirt map", "sensitivity": "dirt sensitivity"}
    span = columns // max(len(maps), 1)
    for k, name in enumerate(maps):
        ax = fig.add_subplot(grid[1, k * span : (k + 1) * span])
        ax.imshow(bench.dirt_maps[name], vmin=0, vmax=1, cmap="gray" if name != "sensitivity" else "magma")
        if name in SOLVER_COLOURS:
            row = next((r for r in bench.rows if r["scenario"] == "dirt" and r["solver"] == name), None)
            title = (f"dirt fit: {name}\nRMSE lit {fmt(row['dirt_rmse_lit'], '.3f')}, all {fmt(row['dirt_rmse_all'], '.3f')}; "
                     f"{row['steps']} steps" if row else name)
        else:
            title = titles[name] + (f"\n(lit: > {LIT}; black: exactly 0)" if name == "sensitivity" else "\n(1 clean, blotch 0.3)")
        ax.set_title(title, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    m = meta["machine"]
    fig.suptitle(f"jaxflare fitting solvers: Biotar f/4 64x48, synthetic plates ({meta['mode']}); {cpu_label(m)}, "
                 f"load {m.get('load_average_start')}-{m.get('load_average_end')}", fontsize=9)
    fig.tight_layout()
    return fig


def write_outputs(bench: FittingBench, meta: dict, out_dir: Path, log) -> list[Path]:
    out = Outputs(out_dir, log)
    out.csv(f"{STEM}.csv", bench.rows, CSV_FIELDS, float_format=".6g", blank_nonfinite=True)
    out.json(f"{STEM}.json", dict(meta, rows=bench.rows, builds=bench.builds, checks=bench.checks, fits=bench.fits,
                                  dirt_maps={k: v for k, v in bench.dirt_maps.items()}))
    out.chart(f"{STEM}.png", _chart, bench, meta, dpi=100)
    return out.written


def summary_text(bench: FittingBench) -> str:
    lines = [(f"{'scenario':17s} {'variant':20s} {'solver':20s} {'error':>8s} {'obs.err':>8s} {'ch.err':>8s} {'in 3se':>6s} {'fit s':>7s} "
              f"{'steps':>5s}  status")]
    for r in bench.rows:
        value, _ = headline(r)
        lines.append(f"{r['scenario']:17s} {r['variant']:20s} {r['solver']:20s} {fmt(value, '8.4f')} {fmt(r.get('tint_error_observable'), '8.4f')} "
                     f"{fmt(r.get('tint_error_observable_channels'), '8.4f')} {fmt(r.get('within_3se'), '6.2f')} {fmt(r['fit_seconds'], '7.2f')} "
                     f"{r['steps']:5d}  {r['status']}")
    lines.append("error: max |tint - truth| over interfaces 4 and 7; polynomial*: max |path colour - truth|; dirt: RMSE over lit cells. "
                 "obs.err / ch.err: over observable interfaces / channels (tint_std < OBSERVABLE_STD)")
    by_solver: dict = {}
    for r in bench.rows:
        by_solver.setdefault(r["solver"], []).append(r)
    for solver, rows in by_solver.items():
        converged = sum(1 for r in rows if r["converged"])
        lines.append(f"{solver:20s}: {converged}/{len(rows)} converged, median fit {statistics.median(r['fit_seconds'] for r in rows):.2f} s, "
                     f"total {sum(r['fit_seconds'] for r in rows):.1f} s")
    return "\n".join(lines)


# --------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    parser = make_parser(__doc__, "smoke test: 2^18-sample plates and models, block 8 only; writes to a temporary folder")
    parser.add_argument("--no-polynomial", action="store_true", help="skip scenario 3 (polynomial path systems: ~40 s to build when not cached)")
    parser.add_argument("--no-dirt", action="store_true", help="skip scenarios 7 and 8 (dirt map, sample model)")
    parser.add_argument("--joint", action="store_true", help="add scenario 8 (coatings and dirt together: the slowest fits, +4-9 min)")
    parser.add_argument("--cache-dir", type=Path, default=DEFAULT_CACHE, help=f"JAXFLARE_CACHE_DIR for the path systems (default {DEFAULT_CACHE})")
    add_out_option(parser, quick_folder=True)
    args = parser.parse_args(argv)

    cfg = dict(QUICK if args.quick else FULL)
    cfg["polynomial"] = cfg["polynomial"] and not args.no_polynomial
    cfg["dirt"] = cfg["dirt"] and not args.no_dirt
    cfg["joint"] = args.joint and not args.quick
    out_dir = output_folder(args, "fitting")

    started = time.perf_counter()
    import fitting

    info, machine = announce("bench_fitting", args.quick, log)
    log(f"  output folder: {out_dir}")
    log(f"  solvers {', '.join(fitting.SOLVERS)} (default {fitting.DEFAULT_SOLVER}); fit defaults otherwise (max_steps 100, rtol 1e-6, atol 1e-9)")
    work = Path(tempfile.mkdtemp(prefix="jaxflare_bench_fitting_inputs_"))
    try:
        bench = FittingBench(cfg, machine, log, work, args.cache_dir.resolve())
        bench.run()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    elapsed = time.perf_counter() - started
    meta = run_meta(
        STEM, args.quick, cfg, info, machine,
        solvers=list(fitting.SOLVERS), default_solver=fitting.DEFAULT_SOLVER, observable_std=fitting.OBSERVABLE_STD,
        dirt_prior=fitting.DIRT_PRIOR, true_tints=TRUE_TINTS, block=BLOCK, lit_sensitivity=LIT, skipped=bench.skipped,
        elapsed_s=elapsed, peak_rss_mib=peak_rss_mib(),
        method=(
            "fit_seconds = time.perf_counter around fitting.fit with the shared model passed as fixed= (median of 2 runs when the first took "
            "under retime_below_s, else 1); model/plate build times separate. Tint errors: |fitted - true| per channel; observable: every "
            "channel's tint_std < OBSERVABLE_STD; within_3se over the observable interfaces and 4, 7. Dirt: RMSE over cells with "
            "dirt_sensitivity > 0.2 (lit) and over all cells; PSNR = 20 log10(1 / RMSE)."
        ),
    )
    written = write_outputs(bench, meta, out_dir, log)
    log("\n" + summary_text(bench))
    for note in bench.skipped:
        log(f"skipped: {note}")
    log(f"\n{elapsed:.1f} s (load average {info['load_average_start']} at the start, {info['load_average_end']} at the end; peak memory "
        f"{meta['peak_rss_mib']:.0f} MiB); wrote {shown_paths(written)}")
    return 0 if bench.rows and not any("failed" in s for s in bench.skipped) else 1


if __name__ == "__main__":
    sys.exit(main())
