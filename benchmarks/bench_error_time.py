"""Image error against warm wall time on the demo scene: Monte Carlo at several sample counts and the grid estimator at several resolutions.

Each configuration is rendered twice (the first run compiles; the second is the warm time) and
compared with a reference: relative RMSE of the flare RGB (the default layer, core excluded) and
mean NVIDIA FLIP (``flip-evaluator``, LDR) of the tone-mapped flare previews at the reference's
exposure. The reference is the grid estimator at finer settings than any configuration charted
(``REFERENCE_OPTIONS``): Monte Carlo cannot be converged to a few percent at 720p on this machine
in reasonable time (its relative RMSE falls as 1 / sqrt(samples)). The grid's agreement with Monte
Carlo is checked independently by ``tests/rendering/test_grid_energy.py``; here the JSON also holds
each Monte Carlo render's error against the reference and the seed-to-seed noise of two MC renders,
so a grid bias would show as MC error above its noise.

    python benchmarks/bench_error_time.py            # demo 720p preview (several minutes)
    python benchmarks/bench_error_time.py --quick    # 160 x 90, fewer configurations (a smoke test)
"""

from __future__ import annotations

import math
import time

import numpy as np
from _harness import (
    Outputs,
    add_out_option,
    add_stem_option,
    announce,
    log,
    make_parser,
    output_folder,
    pyplot,
    quick_stem,
    run_meta,
    shown_paths,
    with_resolution,
)

import jaxflare
from jaxflare import rendering
from jaxflare.colour import display_matrix, spectral_table
from jaxflare.io import tone_map

REFERENCE_OPTIONS = {"spacing_px": 0.4, "max_sub_nodes": 16, "max_cells": 64, "min_cells": 16, "wavelengths": 3, "tolerance_px": 0.2, "fringe_px": 1.0}
"""The reference: finer than every charted grid (spacing, cells, fringes, and every path at full
resolution through ``grid_error``) yet affordable on a loaded 2-core machine."""
MC_SAMPLES = (2**20, 2**22)
GRID_CONFIGS = (
    ("grid coarse", {"grid_error": 0.1, "grid_options": {"spacing_px": 1.0, "max_sub_nodes": 8, "max_cells": 24}}),
    ("grid preview", {}),
)


def flip_mean(reference_ldr: np.ndarray, test_ldr: np.ndarray) -> float:
    import flip_evaluator

    _, mean, _ = flip_evaluator.evaluate(reference_ldr, test_ldr, "LDR", applyMagma=False)
    return float(mean)


def ldr(flare: np.ndarray, exposure: float) -> np.ndarray:
    return np.asarray(tone_map(flare, to_srgb_matrix=display_matrix("ACEScg"), exposure_stops=exposure), np.float32) / 255.0


def render(scene, label, **kwargs):
    runs = []
    for _ in range(2):
        t0 = time.perf_counter()
        result = jaxflare.render(scene, **kwargs)
        runs.append(time.perf_counter() - t0)
    log(f"  {label:28s} cold {runs[0]:7.2f} s  warm {runs[1]:7.2f} s  samples {result.statistics.samples:,}")
    return result, runs


def main(argv=None) -> int:
    parser = make_parser(__doc__, "160 x 90 and fewer configurations (a smoke test)")
    add_out_option(parser, quick_folder=True)
    add_stem_option(parser, "file name stem of the results (default error_time, error_time_quick with --quick)")
    args = parser.parse_args(argv)
    info, machine = announce("bench_error_time", args.quick)
    scene = jaxflare.load_scene("demo")
    if args.quick:
        scene = with_resolution(scene, (160, 90))
    width, height = scene.camera.resolution
    luminance = np.asarray(spectral_table("ACEScg").luminance_weights)

    t0 = time.perf_counter()
    log("  rendering the reference (grid, fine) ...")
    reference = rendering.render_grid(scene, "preview", grid_error=0.003, grid_options=REFERENCE_OPTIONS)
    reference_seconds = time.perf_counter() - t0
    ref = np.asarray(reference.image[..., :3], np.float64)
    lit = (ref @ luminance)[ref @ luminance > 0]
    exposure = math.log2(4.0 / float(np.percentile(lit, 99.5)))
    ref_ldr = ldr(ref, exposure)
    log(f"  reference (grid, fine)       {reference_seconds:7.2f} s  samples {reference.statistics.samples:,}")

    rows = []

    def measure(label, estimator, result, runs, setting):
        image = np.asarray(result.image[..., :3], np.float64)
        rmse = float(np.linalg.norm(image - ref) / np.linalg.norm(ref))
        row = {
            "label": label, "estimator": estimator, "setting": setting, "resolution": f"{width}x{height}", "cold_seconds": runs[0], "warm_seconds": runs[1],
            "samples": int(result.statistics.samples), "relative_rmse": rmse, "flip": flip_mean(ref_ldr, ldr(image, exposure)),
            "negative_fraction": float(np.mean(image < -1e-6 * image.max())),
        }
        rows.append(row)
        log(f"    relative RMSE {rmse:.4f}  FLIP {row['flip']:.4f}  negative {row['negative_fraction']:.2e}")

    counts = MC_SAMPLES[:2] if args.quick else MC_SAMPLES
    mc_images = []
    for samples in counts:
        result, runs = render(scene, f"monte-carlo {samples:,}", samples=samples, estimator="monte-carlo", seed=1)
        measure(f"monte-carlo {samples:,}", "monte-carlo", result, runs, samples)
        if samples == jaxflare.QUALITY_LEVELS["preview"].samples:
            mc_images.append(np.asarray(result.image[..., :3], np.float64))
    noise = None
    if mc_images:
        other = np.asarray(jaxflare.render(scene, samples=jaxflare.QUALITY_LEVELS["preview"].samples, seed=2, estimator="monte-carlo").image[..., :3], np.float64)
        noise = float(np.linalg.norm(other - mc_images[0]) / math.sqrt(2) / np.linalg.norm(ref))
        log(f"  MC preview seed-to-seed noise (relative to the reference's norm): {noise:.4f}")
    for label, options in GRID_CONFIGS[1:2] if args.quick else GRID_CONFIGS:
        t0 = time.perf_counter()
        result = rendering.render_grid(scene, "preview", **options)
        cold = time.perf_counter() - t0
        t0 = time.perf_counter()
        result = rendering.render_grid(scene, "preview", **options)
        warm = time.perf_counter() - t0
        log(f"  {label:28s} cold {cold:7.2f} s  warm {warm:7.2f} s  samples {result.statistics.samples:,}")
        measure(label, "grid", result, (cold, warm), repr(options))

    meta = run_meta(
        "bench_error_time", args.quick, {"scene": "demo", "resolution": [width, height], "mc_samples": list(counts), "grid": [c[0] for c in GRID_CONFIGS]},
        info, machine, reference={"estimator": "grid", "options": REFERENCE_OPTIONS, "grid_error": 0.003, "seconds": reference_seconds,
                                      "samples": int(reference.statistics.samples)},
        mc_preview_seed_noise=noise, rows=rows,
    )
    write_results(args, rows, meta, machine, width, height)
    return 0


FIELDS = ["label", "estimator", "setting", "resolution", "cold_seconds", "warm_seconds", "samples", "relative_rmse", "flip", "negative_fraction"]


def draw(rows, machine, width, height):
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for estimator, marker in (("monte-carlo", "o-"), ("grid", "s-")):
        chosen = sorted((r for r in rows if r["estimator"] == estimator), key=lambda r: r["warm_seconds"])
        for ax, key in zip(axes, ("relative_rmse", "flip"), strict=True):
            ax.plot([r["warm_seconds"] for r in chosen], [r[key] for r in chosen], marker, label=estimator)
            for r in chosen:
                ax.annotate(r["label"], (r["warm_seconds"], r[key]), fontsize=6)
    for ax, title in zip(axes, ("relative RMSE of the flare RGB", "mean FLIP (LDR previews)"), strict=True):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("warm wall time (s)")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle(f"demo scene {width}x{height}: error vs warm time against a fine-grid reference ({machine})", fontsize=8)
    return fig


def write_results(args, rows, meta, machine, width, height):
    out = Outputs(output_folder(args, "error_time"))
    stem = quick_stem(args, "error_time")
    out.csv(f"{stem}.csv", rows, FIELDS)
    out.json(f"{stem}.json", meta)
    out.chart(f"{stem}.png", draw, rows, machine, width, height)
    log(f"wrote {shown_paths(out.written)}")


if __name__ == "__main__":
    raise SystemExit(main())
