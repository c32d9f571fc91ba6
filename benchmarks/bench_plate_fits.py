"""Plate fits on a scene the tests do not fit: the table of fits (variant, parameters, solver,
time, error, coverage) through the fit's default forward model, the deterministic grid estimator.

Run:  python benchmarks/bench_plate_fits.py [--quick] [--out DIR]

The scene: the double Gauss of ``tests/data/zmx/double_gauss_50mm.zmx`` read from its Zemax file,
f/4.5, a six-blade iris, 128 x 72 pixels, a sphere light and a point light off axis. Plates are
Monte Carlo renders, traced exactly, with another seed than anything the fit uses (2^23 samples,
``--quick`` 2^21), of a true lens the fit does not know. Variants, each with the API's defaults
except ``params`` (and the inputs named):

1. ``coatings``: three coloured interfaces (RGB tints (1, 0.7, 0.4), (0.5, 0.9, 1.3), (1.2, 1, 0.6)
   on interfaces 2, 5, 8); clean plate, then with Gaussian noise of 1 % of the plate's mean level
   per pixel, then under a textured background patch masked out (weight 0);
2. ``thin-film``: MgF2 coatings (the scene's ``coating = "mgf2"``) whose layers on surfaces 2, 6
   and 9 are 0.85, 1.15 and 1.3 times the design thickness: recovered thicknesses;
3. ``coatings+dirt``: three plates of the true lens (the tints above and an 8 x 8 dirt map with a
   blotch at 0.4 and two specks at 0.2) with the lights moved, fitted together (shared coatings
   and dirt, per-plate gains); then the same plates with a 32 x 32 dirt map (the issue's size),
   whose truth is the 8 x 8 map read bilinearly at the 32 x 32 cells' centres;
4. ``coatings 2K`` (not with ``--quick``): the scene at 2048 x 1152, the three coloured
   interfaces, the plate a production-quality grid render at 2K (Monte Carlo at 2K would take as
   long and stay noisy; this grid is planned at 4x the resolution of the fit's model, which runs
   at the block resolution 512 x 288), plate render time reported separately.

Metrics per fit: wall time (model build included), steps, converged, the largest tint error over
the interfaces and channels the fit reports observable, the fraction of those parameters whose
truth lies within 3 standard errors (``coverage``), the thickness errors (thin film), the dirt
RMSE over lit cells (``dirt_sensitivity > 0.2``) and the largest deviation of unlit cells from the
prior, and the fit's residual RMS over the plate's own noise (where it has declared noise).

Outputs (atomic) under ``benchmarks/results/`` (``--quick``: a new temporary folder):
``plate_fits.csv``, ``plate_fits.json`` (with the machine header).
"""

from __future__ import annotations

import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _harness import Outputs, add_out_option, announce, log, make_parser, output_folder, run_meta, shown_paths

REPO = Path(__file__).resolve().parent.parent
ZEMAX = REPO / "tests" / "data" / "zmx" / "double_gauss_50mm.zmx"
TRUE_TINTS = {2: (1.0, 0.7, 0.4), 5: (0.5, 0.9, 1.3), 8: (1.2, 1.0, 0.6)}
FILM_SCALE = {2: 0.85, 6: 1.15, 9: 1.3}
MGF2_QUARTER_WAVE_NM = 550.0 / (4 * 1.38)
FIELDS = ["variant", "params", "solver", "plates", "seconds", "steps", "converged", "max_error_observable", "observable",
          "coverage_3se", "thickness_error_max", "dirt_rmse_lit", "unlit_deviation", "residual_over_noise", "status"]


def base_scene(resolution=(128, 72), lights=None, **camera):
    import jaxflare as jf

    lights = lights or (
        jf.Light(kind="sphere", position_m=(0.9, 0.35, -10.0), radius_m=0.04, intensity=1.0),
        jf.Light(kind="point", position_m=(-0.7, 0.25, -10.0), intensity=0.02),
    )
    cam = jf.Camera(lens=str(ZEMAX), f_number=4.5, aperture_blades=6, resolution=resolution, look_at_m=(0.0, 0.0, -10.0), **camera)
    return jf.Scene(camera=cam, lights=lights)


def tint_table(num_interfaces: int) -> np.ndarray:
    table = np.ones((num_interfaces, 3))
    for k, rgb in TRUE_TINTS.items():
        table[k] = rgb
    return table


def with_camera(scene, **changes):
    return dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, **changes))


def mc_plate(scene, samples: int, seed: int):
    import jaxflare as jf

    flare = dataclasses.replace(scene, render=dataclasses.replace(scene.render, core=False))
    return np.asarray(jf.render(flare, samples=samples, seed=seed, method="exact", estimator="monte-carlo").image[..., :3], np.float64)


def tint_metrics(result, truth: np.ndarray) -> dict:
    observable = result.tint_observable
    error = np.abs(result.coating_tints - truth)
    covered = error <= 3 * result.tint_std
    return {
        "max_error_observable": float(error[observable].max()) if observable.any() else None,
        "observable": int(observable.sum()),
        "coverage_3se": float(covered[observable].mean()) if observable.any() else None,
    }


def row(variant: str, result, seconds: float, **metrics) -> dict:
    return {"variant": variant, "params": "+".join(result.fitted), "solver": result.solver, "plates": result.plates, "seconds": seconds,
            "steps": result.steps, "converged": result.converged, "status": result.status, **metrics}


def run(quick: bool) -> tuple[list[dict], dict]:
    import fitting
    import jaxflare as jf
    from jaxflare.scenes import SurfaceCoating, camera_lens

    samples = 2**21 if quick else 2**23
    rows, extra = [], {}
    scene = base_scene()
    num_interfaces = camera_lens(scene.camera).num_interfaces
    truth = tint_table(num_interfaces)
    tinted = with_camera(scene, coating_tints=tuple((k, tuple(v)) for k, v in TRUE_TINTS.items()))

    # 1. coatings: clean, noisy, masked background
    clean = mc_plate(tinted, samples, seed=11)
    rng = np.random.default_rng(5)
    sigma = 0.01 * clean.mean()
    height, width = clean.shape[:2]
    background = np.zeros_like(clean)
    background[: height // 2, : width // 3] = clean.max() * (0.5 + rng.uniform(size=(height // 2, width // 3, 1)))
    weight = np.ones((height, width))
    weight[: height // 2, : width // 3] = 0.0
    cases = [
        ("coatings clean", fitting.Plate(rgb=clean, weight=np.ones((height, width)), source="clean", layer=""), None),
        ("coatings 1% noise", fitting.Plate(rgb=clean + rng.normal(0, sigma, clean.shape), weight=np.full((height, width), 1.0 / sigma),
                                            source="noisy", layer=""), sigma),
        ("coatings masked background", fitting.Plate(rgb=clean + background, weight=weight, source="background", layer=""), None),
    ]
    for name, plate, noise in cases:
        started = time.perf_counter()
        result = fitting.fit(scene, plate, params=("coatings",))
        seconds = time.perf_counter() - started
        metrics = tint_metrics(result, truth)
        if noise is not None:
            inside = plate.weight > 0
            metrics["residual_over_noise"] = float(np.sqrt(np.mean(result.residual[inside] ** 2)) / noise)
        rows.append(row(name, result, seconds, **metrics))
        log(f"  {name}: {seconds:.1f} s, {result.status}, max error {metrics['max_error_observable']}, coverage {metrics['coverage_3se']}")

    # 2. thin film
    coated = with_camera(scene, coating="mgf2")
    stacks = tuple(SurfaceCoating(surfaces=(s,), layers=((1.38, MGF2_QUARTER_WAVE_NM * f),)) for s, f in FILM_SCALE.items())
    film_plate_rgb = mc_plate(with_camera(coated, surface_coatings=stacks), samples, seed=12)
    plate = fitting.Plate(rgb=film_plate_rgb, weight=np.ones((height, width)), source="known stack", layer="")
    started = time.perf_counter()
    result = fitting.fit(coated, plate, params=("thin-film",))
    seconds = time.perf_counter() - started
    observed = [layer for layer in result.coating_layers if layer["observable"]]
    errors = [layer["thickness_nm"] / (MGF2_QUARTER_WAVE_NM * FILM_SCALE.get(layer["surface"], 1.0)) - 1 for layer in observed]
    covered = [abs(layer["thickness_nm"] - MGF2_QUARTER_WAVE_NM * FILM_SCALE.get(layer["surface"], 1.0)) <= 3 * (layer["thickness_std_nm"] or np.inf)
               for layer in observed]
    rows.append(row("thin-film known stack", result, seconds, thickness_error_max=float(np.max(np.abs(errors))) if errors else None,
                    observable=len(observed), coverage_3se=float(np.mean(covered)) if covered else None))
    extra["thin_film_layers"] = result.coating_layers
    log(f"  thin film: {seconds:.1f} s, {result.status}, thickness errors {np.round(errors, 4).tolist()}")

    # 3. coatings + dirt from three plates
    folder = Path(tempfile.mkdtemp(prefix="jaxflare_bench_plate_fits_"))
    true_dirt = np.ones((8, 8, 1), np.float32)
    true_dirt[2:5, 4:7] = 0.4
    true_dirt[5, 2] = true_dirt[1, 1] = 0.2
    jf.write_exr(folder / "dirt.exr", {"": true_dirt}, pixel_type="float")
    offsets = [(0.0, 0.0), (-1.2, -0.5), (0.4, -0.9)]
    scenes, plates = [], []
    for k, (dx, dy) in enumerate(offsets):
        lights = tuple(dataclasses.replace(light, position_m=(light.position_m[0] + dx, light.position_m[1] + dy, light.position_m[2]))
                       for light in scene.lights)
        s = dataclasses.replace(scene, lights=lights)
        scenes.append(s)
        rgb = mc_plate(with_camera(dataclasses.replace(tinted, lights=lights), dirt_map=str(folder / "dirt.exr")), samples, seed=20 + k)
        plates.append(fitting.Plate(rgb=rgb, weight=np.ones((height, width)), source=f"plate {k}", layer=""))
    started = time.perf_counter()
    result = fitting.fit(scenes, plates, params=("coatings", "dirt"), dirt_resolution=8)
    seconds = time.perf_counter() - started
    lit = result.dirt_sensitivity[..., 0] > 0.2
    metrics = tint_metrics(result, truth)
    metrics["dirt_rmse_lit"] = float(np.sqrt(np.mean((result.dirt[lit] - true_dirt[lit]) ** 2)))
    metrics["unlit_deviation"] = float(np.abs(result.dirt[~lit] - fitting.DIRT_PRIOR).max()) if (~lit).any() else None
    rows.append(row("coatings+dirt 3 plates", result, seconds, **metrics))
    extra["dirt"] = {"fitted": result.dirt[..., 0].tolist(), "sensitivity": result.dirt_sensitivity[..., 0].tolist(), "truth": true_dirt[..., 0].tolist()}
    log(f"  coatings+dirt: {seconds:.1f} s, {result.status}, {metrics}")

    # the same plates, a 32 x 32 dirt map
    from jaxflare.rendering.effects import bilinear

    fine = 32
    centres = (np.arange(fine) + 0.5) * (true_dirt.shape[0] / fine)
    truth_fine = np.asarray(bilinear(true_dirt.astype(np.float64), centres[None, :], centres[:, None]))  # (32, 32, 1)
    started = time.perf_counter()
    result = fitting.fit(scenes, plates, params=("coatings", "dirt"), dirt_resolution=fine)
    seconds = time.perf_counter() - started
    lit = result.dirt_sensitivity[..., 0] > 0.2
    metrics = tint_metrics(result, truth)
    metrics["dirt_rmse_lit"] = float(np.sqrt(np.mean((result.dirt[lit] - truth_fine[lit]) ** 2))) if lit.any() else None
    metrics["unlit_deviation"] = float(np.abs(result.dirt[~lit] - fitting.DIRT_PRIOR).max()) if (~lit).any() else None
    rows.append(row(f"coatings+dirt {fine}x{fine} 3 plates", result, seconds, **metrics))
    extra["dirt_32"] = {"fitted": result.dirt[..., 0].tolist(), "sensitivity": result.dirt_sensitivity[..., 0].tolist(), "truth": truth_fine[..., 0].tolist()}
    log(f"  coatings+dirt {fine}x{fine}: {seconds:.1f} s, {result.status}, {metrics}")
    if not quick:
        rows.append(coatings_2k(truth))
    return rows, extra


def coatings_2k(truth: np.ndarray) -> dict:
    """Variant 4: a coatings fit of a 2K plate with the API's defaults."""
    import fitting
    import jaxflare as jf

    scene = base_scene(resolution=(2048, 1152))
    tinted = with_camera(scene, coating_tints=tuple((k, tuple(v)) for k, v in TRUE_TINTS.items()))
    flare = dataclasses.replace(tinted, render=dataclasses.replace(tinted.render, core=False))
    started = time.perf_counter()
    rgb = np.asarray(jf.render(flare, "production", estimator="grid").image[..., :3], np.float64)
    log(f"  2K plate (grid, production): {time.perf_counter() - started:.1f} s")
    plate = fitting.Plate(rgb=rgb, weight=np.ones(rgb.shape[:2]), source="2K grid production", layer="")
    started = time.perf_counter()
    result = fitting.fit(scene, plate, params=("coatings",))
    seconds = time.perf_counter() - started
    metrics = tint_metrics(result, truth)
    log(f"  coatings 2K: {seconds:.1f} s, {result.status}, model at {result.model_resolution}, {metrics}")
    return row("coatings 2K", result, seconds, **metrics)


def main(argv: list[str] | None = None) -> int:
    parser = make_parser(__doc__, "2^21-sample plates instead of 2^23, results in a temporary folder")
    add_out_option(parser, quick_folder=True)
    args = parser.parse_args(argv)
    info, machine = announce("plate fits", args.quick)
    rows, extra = run(args.quick)
    meta = run_meta("plate_fits", args.quick, {"samples": 2**21 if args.quick else 2**23, "scene": str(ZEMAX.relative_to(REPO))}, info, machine)
    outputs = Outputs(output_folder(args, "plate_fits"))
    outputs.csv("plate_fits.csv", rows, FIELDS)
    outputs.json("plate_fits.json", {**meta, "rows": rows, **extra})
    log(f"wrote {shown_paths(outputs.written)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
