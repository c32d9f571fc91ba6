"""Render time and noise of the demo scene: a 720p preview and a 2K production render, against the
paper's budgets (Pekkarinen & Balzer 2019: about 10 s for a preview, 15 min for a production render).

Run:  python benchmarks/bench_render.py [--quick] [--no-production] [--no-reference] [--no-auto] [--out DIR]

The scene is ``jaxflare.load_scene("demo")`` (Zeiss Biotar at f/2.8, one sphere light, 45 ghost
paths plus the core), rendered with ``jaxflare.render`` in this process. Every render is timed with
``time.perf_counter`` around the call (``wall``: set-up, pilot, render and normalisation) and its
``statistics`` are kept (``render_seconds``, ``compile_seconds``, ``setup_seconds``, ...).

1. **Warm-up**: one small render (2^16 samples, method ``"exact"``) of each configuration (720p
   preview, 2K production: the quality's wavelength strata are part of the compiled step) before
   anything is timed; its ``compile_seconds`` is reported as the compile time.
2. **Preview, 720p** (the demo scene as is, ``quality="preview"`` = 2^22 samples, method
   ``"exact"``), seeds 0, 1, 2: median wall time against the 10 s budget. Noise, see below.
3. **Reference check**: one render with 8x the preview samples (seed 100); the preview noise
   measured against it must agree with the seed-to-seed estimate.
4. **1/sqrt(N) check**: two renders at 1/4 of the preview samples (seeds 0, 1): their sigma over
   the preview's sigma should be sqrt(4) = 2 (precisely: sqrt of the drawn-sample ratio).
5. **Production, 2K** (2048x1152, ``quality="production"`` = 2^26 samples): two renders at 1/8 of
   the samples (seeds 0, 1) give the noise, extrapolated to the full count by 1/sqrt(N); then one
   full render (seed 2) is timed against the 15 min budget (``--no-production`` skips it) and
   gives a direct cross-check of the extrapolated noise.
6. **Convergence, 720p**: relative RMSE (two seeds) against wall time for 2^19, 2^20, 2^21 and
   2^22 samples (the last is the preview above), saved as a log-log chart with a 1/sqrt(t) guide.
7. **method="auto"** at 720p preview (seed 0) with ``JAXFLARE_CACHE_DIR`` pointing at a fresh
   temporary folder (the polynomial path systems are built: ``setup_seconds``), then again with
   that cache warm; how many paths ended up polynomial or exact, and the relative difference of the
   auto image from the exact seed-0 preview. (Since adaptive sampling, the methods draw different
   samples for the same seed, so this difference includes Monte Carlo noise: compare it with the
   seed-to-seed noise, not with 0.)

**Noise.** All on the combined flare RGB, ``result.image[..., :3]`` (every flare layer, *not* the
``core`` layer: the light's own image is not a flare), as a whole-image norm ||x||^2 = sum over
pixels and channels. k independent renders A_i of the same configuration (distinct seeds: renders
with the same seed share their first batches) give the per-render noise variance
sigma^2 = sum_i ||A_i - mean||^2 / (k - 1) (for k = 2: ||A - B||^2 / 2, since E||A - B||^2 =
2 sigma^2) and the squared norm of the noise-free image ||mu||^2 = ||mean||^2 - sigma^2 / k. The
**relative RMSE** of one render against the infinitely sampled image is sqrt(sigma^2 / ||mu||^2).
Against the reference R (m times the samples): sigma^2 = mean_i ||A_i - R||^2 - sigma_R^2 with
sigma_R^2 = sigma^2_seeds / m (from the drawn-sample ratio) and ||mu||^2 = ||R||^2 - sigma_R^2.
Production: sigma^2 = sigma^2_eighth x (drawn eighth samples / drawn production samples), ||mu||^2 =
||P||^2 - sigma^2 from the full render P (from the eighths' mean without it); cross-check
sigma^2 = ||P - mean of eighths||^2 - sigma^2_eighth / 2.

``--quick``: the same code at 320x180 (preview, 2^18 samples) and 480x270 (production, 2^20),
convergence 2^16 ... 2^18, ``method="auto"`` on the 2 most energetic ghost paths only; it writes
into a new temporary folder (printed) unless ``--out`` is given, never into ``benchmarks/results``.

Outputs (atomic writes) under ``benchmarks/results/``: ``render_times.{csv,json}``,
``render_convergence.png`` and ``render_demo_preview.png`` (the tone-mapped 720p preview, seed 0).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _harness import (
    GuardedSteps,
    Outputs,
    add_out_option,
    announce,
    cpu_label,
    fmt,
    log,
    make_parser,
    median,
    output_folder,
    pyplot,
    relative,
    render_once,
    run_meta,
    seed_noise,
    shown_paths,
    sq_norm,
    temporary_env,
    with_resolution,
)

STEM = "render_times"
CHART = "render_convergence.png"
PREVIEW_PNG = "render_demo_preview.png"
PAPER_BUDGET_S = {"preview": 10.0, "production": 900.0}

FULL = {
    "scene": "demo", "preview_resolution": (1280, 720), "production_resolution": (2048, 1152),
    "preview_samples": None, "production_samples": None,  # None: the quality level's (QUALITY_LEVELS)
    "seeds": [0, 1, 2], "reference_factor": 8, "reference_seed": 100, "quarter_divisor": 4,
    "production_divisor": 8, "production_seed": 2, "convergence_samples": [2**19, 2**20, 2**21, 2**22],
    "warmup_samples": 2**16, "auto_paths": None, "reference": True, "production_full": True, "auto": True,
}
QUICK = dict(FULL, preview_resolution=(320, 180), production_resolution=(480, 270), preview_samples=2**18,
             production_samples=2**20, convergence_samples=[2**16, 2**17, 2**18], auto_paths=2)

CSV_FIELDS = [
    "case", "resolution", "quality", "method", "samples", "samples_requested", "renders", "seeds", "median_seconds",
    "render_seconds", "compile_seconds", "setup_seconds", "sensor_hit_rate", "relative_rmse", "noise_estimate",
    "paper_budget_seconds", "budget_ratio", "polynomial_paths", "exact_paths", "step_traces", "machine",
]


# --------------------------------------------------------------------------- rows


def row_from(case: str, records: list[dict], *, quality: str, method: str, requested, relative_rmse=float("nan"),
             noise_estimate: str = "", budget: float | None = None, machine: str = "") -> dict:
    med = median(records, "wall_seconds")
    return {
        "case": case, "resolution": records[0]["resolution"], "quality": quality, "method": method,
        "samples": records[0]["samples"], "samples_requested": requested, "renders": len(records),
        "seeds": " ".join(str(r["seed"]) for r in records), "median_seconds": med,
        "render_seconds": median(records, "render_seconds"), "compile_seconds": median(records, "compile_seconds"),
        "setup_seconds": median(records, "setup_seconds"), "sensor_hit_rate": median(records, "sensor_hit_rate"),
        "relative_rmse": relative_rmse, "noise_estimate": noise_estimate, "paper_budget_seconds": budget,
        "budget_ratio": med / budget if budget else None, "polynomial_paths": records[0]["polynomial_paths"],
        "exact_paths": records[0]["exact_paths"], "step_traces": sum(r["step_traces"] for r in records), "machine": machine,
    }


# --------------------------------------------------------------------------- the benchmark


class RenderBench(GuardedSteps):
    def __init__(self, cfg: dict, out_dir: Path, machine: str, log):
        import jaxflare

        self.cfg, self.out_dir, self.machine, self.log = cfg, out_dir, machine, log
        self.jaxflare = jaxflare
        demo = jaxflare.load_scene(cfg["scene"])
        self.scene_preview = with_resolution(demo, cfg["preview_resolution"])
        self.scene_production = with_resolution(demo, cfg["production_resolution"])
        levels = jaxflare.QUALITY_LEVELS
        self.preview_n = cfg["preview_samples"] or levels["preview"].samples
        self.production_n = cfg["production_samples"] or levels["production"].samples
        self.rows: list[dict] = []
        self.records: list[dict] = []
        self.checks: dict = {}
        self.skipped: list[str] = []
        self.preview_images: list[np.ndarray] = []
        self.preview_records: list[dict] = []
        self.preview_noise: dict | None = None
        self.convergence: list[dict] = []
        self.written: list[Path] = []

    def render(self, scene, label, **kwargs):
        record, flare, result = render_once(scene, self.log, label, **kwargs)
        record["case"] = label
        self.records.append(record)
        return record, flare, result

    def row(self, *args, **kwargs) -> dict:
        row = row_from(*args, machine=self.machine, **kwargs)
        self.rows.append(row)
        return row

    # ---- 1. warm-up
    def warm_up(self) -> None:
        self.log("\n-- warm-up (compiles the render step of each configuration; not timed as a render)")
        for case, scene, quality in (("warmup_preview", self.scene_preview, "preview"),
                                     ("warmup_production", self.scene_production, "production")):
            record, _, _ = self.render(scene, case, quality=quality, samples=self.cfg["warmup_samples"], seed=0, method="exact")
            self.row(case, [record], quality=quality, method="exact", requested=self.cfg["warmup_samples"])

    # ---- 2.-4. preview, reference, 1/sqrt(N)
    def preview(self) -> None:
        cfg = self.cfg
        self.log(f"\n-- preview {self.res(self.scene_preview)}: {self.preview_n} samples, method exact, seeds {cfg['seeds']}")
        for seed in cfg["seeds"]:
            record, flare, result = self.render(self.scene_preview, f"preview seed {seed}", quality="preview", samples=self.preview_n,
                                                seed=seed, method="exact")
            self.preview_records.append(record)
            self.preview_images.append(flare)
            if seed == cfg["seeds"][0]:
                path = self.out_dir / PREVIEW_PNG
                result.write_png(path)
                self.written.append(path)
                self.preview_paths = result.statistics["paths"]
            del result
        noise = self.preview_noise = seed_noise(self.preview_images)
        self.row("preview", self.preview_records, quality="preview", method="exact", requested=self.preview_n,
                 relative_rmse=noise["relative_rmse"], noise_estimate=f"seed-to-seed ({noise['renders']} renders)",
                 budget=PAPER_BUDGET_S["preview"])
        self.convergence.append({"samples_requested": self.preview_n, "samples": self.preview_records[0]["samples"],
                                 "median_seconds": median(self.preview_records, "wall_seconds"),
                                 "render_seconds": median(self.preview_records, "render_seconds"), **noise})
        self.log(f"  preview relative RMSE (seed-to-seed, {noise['renders']} renders): {noise['relative_rmse']:.4f}")

    def reference(self) -> None:
        cfg, noise = self.cfg, self.preview_noise
        requested = self.preview_n * cfg["reference_factor"]
        self.log(f"\n-- reference: {cfg['reference_factor']}x the preview samples, seed {cfg['reference_seed']}")
        record, ref, _ = self.render(self.scene_preview, "reference (8x preview)", quality="preview", samples=requested,
                                     seed=cfg["reference_seed"], method="exact")
        ratio = record["samples"] / self.preview_records[0]["samples"]
        sigma2_ref = noise["sigma2"] / ratio
        d2 = [sq_norm(np.asarray(a, np.float64) - ref) for a in self.preview_images]
        sigma2 = statistics.mean(d2) - sigma2_ref
        mu2 = sq_norm(ref) - sigma2_ref
        rel = relative(sigma2, mu2)
        self.checks["reference"] = {
            "sample_ratio": ratio, "sigma2_reference": sigma2_ref, "sigma2_vs_reference": sigma2, "mu2_reference": mu2,
            "relative_rmse_vs_reference": rel, "relative_rmse_vs_reference_per_seed": [relative(d - sigma2_ref, mu2) for d in d2],
            "relative_rmse_vs_reference_uncorrected": math.sqrt(statistics.mean(d2) / sq_norm(ref)),
            "relative_rmse_seed_to_seed": noise["relative_rmse"], "agreement": rel / noise["relative_rmse"],
            "reference_relative_rmse": relative(sigma2_ref, mu2),
        }
        self.row("preview_vs_reference", self.preview_records, quality="preview", method="exact", requested=self.preview_n,
                 relative_rmse=rel, noise_estimate=f"against the {ratio:.2f}x reference, less its noise",
                 budget=PAPER_BUDGET_S["preview"])
        self.row("reference", [record], quality="preview", method="exact", requested=requested,
                 relative_rmse=relative(sigma2_ref, mu2), noise_estimate="preview sigma^2 / sample ratio")
        self.log(f"  preview relative RMSE against the reference: {rel:.4f} (seed-to-seed {noise['relative_rmse']:.4f}; "
                 f"ratio {rel / noise['relative_rmse']:.3f}, expected 1); uncorrected "
                 f"{self.checks['reference']['relative_rmse_vs_reference_uncorrected']:.4f}")
        self.convergence_reference = {"samples": record["samples"], "median_seconds": record["wall_seconds"],
                                      "relative_rmse": relative(sigma2_ref, mu2)}

    def quarter(self) -> None:
        cfg, noise = self.cfg, self.preview_noise
        requested = self.preview_n // cfg["quarter_divisor"]
        self.log(f"\n-- 1/sqrt(N) check: preview at 1/{cfg['quarter_divisor']} of the samples, seeds {cfg['seeds'][:2]}")
        records, images = [], []
        for seed in cfg["seeds"][:2]:
            record, flare, _ = self.render(self.scene_preview, f"preview/{cfg['quarter_divisor']} seed {seed}",
                                           quality="preview", samples=requested, seed=seed, method="exact")
            records.append(record)
            images.append(flare)
        q = seed_noise(images)
        ratio = self.preview_records[0]["samples"] / records[0]["samples"]
        measured = math.sqrt(q["sigma2"] / noise["sigma2"]) if noise["sigma2"] > 0 else float("nan")
        self.checks["sqrt_n_scaling"] = {"divisor": cfg["quarter_divisor"], "drawn_sample_ratio": ratio,
                                         "sigma_ratio_measured": measured, "sigma_ratio_expected": math.sqrt(ratio),
                                         "relative_rmse_quarter": q["relative_rmse"]}
        self.row(f"preview_div{cfg['quarter_divisor']}", records, quality="preview", method="exact", requested=requested,
                 relative_rmse=q["relative_rmse"], noise_estimate="seed-to-seed (2 renders)")
        self.log(f"  sigma(1/{cfg['quarter_divisor']}) / sigma(full) = {measured:.3f}; expected sqrt({ratio:.3f}) = {math.sqrt(ratio):.3f}")

    # ---- 5. production
    def production(self) -> None:
        cfg = self.cfg
        divisor = cfg["production_divisor"]
        requested = self.production_n // divisor
        scene = self.scene_production
        self.log(f"\n-- production {self.res(scene)}: noise from 2 renders at 1/{divisor} of {self.production_n} samples, "
                 f"seeds {cfg['seeds'][:2]}")
        records, images = [], []
        for seed in cfg["seeds"][:2]:
            record, flare, _ = self.render(scene, f"production/{divisor} seed {seed}", quality="production", samples=requested,
                                           seed=seed, method="exact")
            records.append(record)
            images.append(flare)
        eighth = seed_noise(images)
        self.row(f"production_div{divisor}", records, quality="production", method="exact", requested=requested,
                 relative_rmse=eighth["relative_rmse"], noise_estimate="seed-to-seed (2 renders)")
        full_record, full = None, None
        if cfg["production_full"]:
            self.log(f"   full production render, seed {cfg['production_seed']} (the 15 min budget):")
            full_record, full, result = self.render(scene, f"production seed {cfg['production_seed']}", quality="production",
                                                    samples=self.production_n, seed=cfg["production_seed"], method="exact")
            del result
            full_samples = full_record["samples"]
        else:
            # the drawn count of a full render, as the renderer rounds it (whole batches per path)
            per_path = records[0]["samples"] // records[0]["paths_rendered"]
            rays_per_path = per_path // records[0]["batches"]
            batches = math.ceil(max(rays_per_path, self.production_n // records[0]["paths_rendered"]) / rays_per_path)
            full_samples = batches * rays_per_path * records[0]["paths_rendered"]
        ratio = full_samples / records[0]["samples"]
        sigma2 = eighth["sigma2"] / ratio
        mean8 = np.mean([np.asarray(a, np.float64) for a in images], axis=0)
        if full is not None:
            mu2 = sq_norm(full) - sigma2
            sigma2_direct = sq_norm(np.asarray(full, np.float64) - mean8) - eighth["sigma2"] / 2
            direct = relative(sigma2_direct, mu2)
        else:
            mu2, direct = eighth["mu2"], float("nan")
        rel = relative(sigma2, mu2)
        self.checks["production"] = {"drawn_sample_ratio": ratio, "sigma2_eighth": eighth["sigma2"], "sigma2_extrapolated": sigma2,
                                     "mu2": mu2, "relative_rmse_extrapolated": rel, "relative_rmse_cross_check": direct,
                                     "full_render": full_record is not None}
        estimate = f"1/{divisor} renders x 1/sqrt({ratio:.2f})"
        if full_record is not None:
            self.row("production", [full_record], quality="production", method="exact", requested=self.production_n,
                     relative_rmse=rel, noise_estimate=estimate, budget=PAPER_BUDGET_S["production"])
            self.log(f"  production relative RMSE {rel:.4f} (extrapolated from 1/{divisor}: {eighth['relative_rmse']:.4f} / "
                     f"sqrt({ratio:.2f})); cross-check against the full render {direct:.4f}")
        else:
            self.skipped.append("full production render (--no-production): noise extrapolated, no wall time")
            self.log(f"  production relative RMSE {rel:.4f} (extrapolated; full render skipped)")
        self.production_point = {"median_seconds": full_record["wall_seconds"] if full_record else None, "relative_rmse": rel,
                                 "eighth_seconds": median(records, "wall_seconds"), "eighth_relative_rmse": eighth["relative_rmse"],
                                 "resolution": records[0]["resolution"]}

    # ---- 6. convergence
    def convergence_curve(self) -> None:
        cfg = self.cfg
        self.log(f"\n-- convergence {self.res(self.scene_preview)}: samples {cfg['convergence_samples']}, seeds {cfg['seeds'][:2]}")
        for n in cfg["convergence_samples"]:
            if n == self.preview_n and self.preview_noise is not None:
                self.log(f"  {n} samples: the preview renders above")
                continue
            records, images = [], []
            for seed in cfg["seeds"][:2]:
                record, flare, _ = self.render(self.scene_preview, f"2^{round(math.log2(n))} seed {seed}", quality="preview",
                                               samples=n, seed=seed, method="exact")
                records.append(record)
                images.append(flare)
            noise = seed_noise(images)
            self.row(f"convergence_2^{round(math.log2(n))}", records, quality="preview", method="exact", requested=n,
                     relative_rmse=noise["relative_rmse"], noise_estimate="seed-to-seed (2 renders)")
            self.convergence.append({"samples_requested": n, "samples": records[0]["samples"],
                                     "median_seconds": median(records, "wall_seconds"),
                                     "render_seconds": median(records, "render_seconds"), **noise})
        self.convergence.sort(key=lambda c: c["samples"])

    # ---- 7. method="auto"
    def auto(self) -> None:
        cfg = self.cfg
        paths = None
        if cfg["auto_paths"]:
            ghosts = [p for p in getattr(self, "preview_paths", []) if p["path"] != "primary"]
            paths = [tuple(p["path"]) for p in sorted(ghosts, key=lambda p: -p["energy"])[: cfg["auto_paths"]]] or None
        cache = tempfile.mkdtemp(prefix="jaxflare_bench_render_cache_")
        self.log(f"\n-- method auto, preview {self.res(self.scene_preview)}, seed 0, paths "
                 f"{'all' if paths is None else paths}; JAXFLARE_CACHE_DIR={cache} (fresh, then warm)")
        try:
            with temporary_env("JAXFLARE_CACHE_DIR", cache):
                self.auto_renders(paths)
        finally:
            shutil.rmtree(cache, ignore_errors=True)

    def auto_renders(self, paths) -> None:
        """The cold and warm ``method="auto"`` renders (``JAXFLARE_CACHE_DIR`` set by :meth:`auto`)."""
        cfg = self.cfg
        out = {}
        for state in ("cold", "warm"):
            record, flare, _ = self.render(self.scene_preview, f"auto ({state} path cache)", quality="preview",
                                           samples=self.preview_n, seed=0, method="auto", paths=paths)
            difference = float("nan")
            if paths is None and self.preview_images and cfg["seeds"][0] == 0:
                exact = np.asarray(self.preview_images[0], np.float64)
                difference = math.sqrt(sq_norm(np.asarray(flare, np.float64) - exact) / sq_norm(exact))
            row = self.row(f"auto_{state}", [record], quality="preview", method="auto", requested=self.preview_n,
                           noise_estimate="" if paths is None else f"{len(paths)} ghost paths only",
                           budget=PAPER_BUDGET_S["preview"] if paths is None else None)
            out[state] = {"setup_seconds": record["setup_seconds"], "compile_seconds": record["compile_seconds"],
                          "render_seconds": record["render_seconds"], "wall_seconds": record["wall_seconds"],
                          "polynomial_paths": record["polynomial_paths"], "exact_paths": record["exact_paths"],
                          "step_traces": record["step_traces"], "relative_difference_from_exact_seed0": difference}
            self.log(f"  {state}: set-up (path systems) {record['setup_seconds']:.1f} s, {record['polynomial_paths']} paths "
                     f"polynomial / {record['exact_paths']} exact"
                     + (f", relative difference from the exact seed-0 preview {difference:.4f}" if math.isfinite(difference) else ""))
            del row
        out["paths"] = "all" if paths is None else [list(p) for p in paths]
        self.checks["auto"] = out

    @staticmethod
    def res(scene) -> str:
        return "x".join(map(str, scene.camera.resolution))

    def run(self) -> None:
        cfg = self.cfg
        self.step("warm-up", self.warm_up)
        self.step("preview", self.preview)
        if self.preview_noise is not None:
            if cfg["reference"]:
                self.step("reference", self.reference)
            else:
                self.skipped.append("reference render (--no-reference)")
            self.step("1/sqrt(N) check", self.quarter)
        self.step("convergence", self.convergence_curve)
        self.step("production", self.production)
        if cfg["auto"]:
            self.step("method auto", self.auto)
        else:
            self.skipped.append("method auto (--no-auto)")


# --------------------------------------------------------------------------- outputs


def _chart(bench: RenderBench, meta: dict):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8.0, 5.6))
    points = [c for c in bench.convergence if math.isfinite(c["relative_rmse"]) and c["median_seconds"] > 0]
    res = "x".join(map(str, bench.cfg["preview_resolution"]))
    if points:
        xs, ys = [c["median_seconds"] for c in points], [c["relative_rmse"] for c in points]
        ax.plot(xs, ys, "o-", color="C0", label=f"{res} preview, method exact (two-seed noise)")
        for c in points:
            ax.annotate(f"2^{math.log2(c['samples_requested']):.0f}", (c["median_seconds"], c["relative_rmse"]),
                        textcoords="offset points", xytext=(5, 4), fontsize=8, color="C0")
        anchor = points[-1]
        t = np.geomspace(min(xs + [PAPER_BUDGET_S["preview"]]) / 2, PAPER_BUDGET_S["production"] * 2, 50)
        ax.plot(t, anchor["relative_rmse"] * np.sqrt(anchor["median_seconds"] / t), ":", color="0.5", label="1/sqrt(t) guide")
    ref = getattr(bench, "convergence_reference", None)
    if ref and math.isfinite(ref["relative_rmse"]):
        ax.plot([ref["median_seconds"]], [ref["relative_rmse"]], "o", mfc="none", color="C0", ms=9,
                label=f"{res} reference ({bench.checks['reference']['sample_ratio']:.1f}x preview; sigma from the seeds)")
    prod = getattr(bench, "production_point", None)
    if prod:
        if math.isfinite(prod["eighth_relative_rmse"]):
            ax.plot([prod["eighth_seconds"]], [prod["eighth_relative_rmse"]], "s", mfc="none", color="C1", ms=8,
                    label=f"{prod['resolution']} production / {bench.cfg['production_divisor']} (two-seed noise)")
        if prod["median_seconds"] and math.isfinite(prod["relative_rmse"]):
            ax.plot([prod["median_seconds"]], [prod["relative_rmse"]], "s", color="C1", ms=8,
                    label=f"{prod['resolution']} production (noise extrapolated by 1/sqrt(N))")
    for quality, colour in (("preview", "C0"), ("production", "C1")):
        ax.axvline(PAPER_BUDGET_S[quality], color=colour, lw=1, ls="--", alpha=0.7)
        ax.annotate(f"paper: {quality} {PAPER_BUDGET_S[quality]:g} s", (PAPER_BUDGET_S[quality], 1), xycoords=("data", "axes fraction"),
                    textcoords="offset points", xytext=(3, -12), fontsize=8, color=colour)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time per render (warm, compile excluded) [s]")
    ax.set_ylabel("relative RMSE of the flare RGB vs the infinitely sampled image")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    m = meta["machine"]
    ax.set_title(f"jaxflare demo scene (Biotar f/2.8): noise against render time ({meta['mode']})\n"
                 f"{cpu_label(m)}, jax {m.get('jax')} ({m.get('jax_backend')})",
                 fontsize=9)
    fig.tight_layout()
    return fig


def write_outputs(bench: RenderBench, meta: dict, out_dir: Path, log) -> list[Path]:
    out = Outputs(out_dir, log)
    out.csv(f"{STEM}.csv", bench.rows, CSV_FIELDS, float_format=".6g", blank_nonfinite=True)
    out.json(f"{STEM}.json", dict(meta, rows=bench.rows, renders=bench.records, checks=bench.checks, convergence=bench.convergence))
    out.chart(CHART, _chart, bench, meta)
    return out.written + bench.written


def summary_text(bench: RenderBench) -> str:
    lines = [(f"{'case':22s} {'resolution':>10s} {'method':>6s} {'samples':>10s} {'median s':>9s} {'render s':>9s} "
              f"{'budget s':>8s} {'x budget':>8s} {'rel. RMSE':>9s}  noise estimate")]
    for r in bench.rows:
        lines.append(f"{r['case']:22s} {r['resolution']:>10s} {r['method']:>6s} {r['samples']:>10d} {fmt(r['median_seconds'], '9.2f')} "
                     f"{fmt(r['render_seconds'], '9.2f')} {fmt(r['paper_budget_seconds'], '8.0f')} {fmt(r['budget_ratio'], '8.2f')} "
                     f"{fmt(r['relative_rmse'], '9.4f')}  {r['noise_estimate']}")
    c = bench.checks
    if "reference" in c:
        lines.append(f"check: preview noise against the reference / seed-to-seed = {c['reference']['agreement']:.3f} (expect 1)")
    if "sqrt_n_scaling" in c:
        s = c["sqrt_n_scaling"]
        lines.append(f"check: sigma(1/{s['divisor']} samples) / sigma(preview) = {s['sigma_ratio_measured']:.3f} "
                     f"(expect {s['sigma_ratio_expected']:.3f})")
    if "production" in c and c["production"]["full_render"]:
        p = c["production"]
        lines.append(f"check: production noise extrapolated {p['relative_rmse_extrapolated']:.4f} vs against the full render "
                     f"{fmt(p['relative_rmse_cross_check'], '.4f')}")
    if "auto" in c:
        a = c["auto"]
        lines.append(f"auto: path-system set-up {a['cold']['setup_seconds']:.1f} s cold, {a['warm']['setup_seconds']:.1f} s warm; "
                     f"{a['cold']['polynomial_paths']} paths polynomial, {a['cold']['exact_paths']} exact"
                     + (f"; relative difference from exact {a['cold']['relative_difference_from_exact_seed0']:.4f}"
                        if math.isfinite(a["cold"]["relative_difference_from_exact_seed0"]) else ""))
    return "\n".join(lines)


# --------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    parser = make_parser(__doc__, "smoke test: 320x180 / 480x270, 2^18 / 2^20 samples, auto on 2 paths; writes to a temporary folder")
    parser.add_argument("--no-production", action="store_true", help="skip the full 2K production render (noise still extrapolated)")
    parser.add_argument("--no-reference", action="store_true", help="skip the 8x-samples reference render")
    parser.add_argument("--no-auto", action="store_true", help="skip the method='auto' renders (path-system build)")
    add_out_option(parser, quick_folder=True)
    args = parser.parse_args(argv)

    cfg = dict(QUICK if args.quick else FULL)
    cfg["production_full"] = cfg["production_full"] and not args.no_production
    cfg["reference"] = cfg["reference"] and not args.no_reference
    cfg["auto"] = cfg["auto"] and not args.no_auto
    out_dir = output_folder(args, "render")

    started = time.perf_counter()
    import jax

    import jaxflare

    info, machine = announce("bench_render", args.quick, log)
    if jax.config.jax_enable_x64:
        log("  WARNING: jax_enable_x64 is on; renders are float32 regardless, but other set-up work may be slower")
    log(f"  output folder: {out_dir}")

    bench = RenderBench(cfg, out_dir, machine, log)
    log(f"  scene '{cfg['scene']}': preview {cfg['preview_resolution']} x {bench.preview_n} samples, production "
        f"{cfg['production_resolution']} x {bench.production_n} samples; paper budgets {PAPER_BUDGET_S['preview']:g} s and "
        f"{PAPER_BUDGET_S['production']:g} s")
    bench.run()
    elapsed = time.perf_counter() - started
    meta = run_meta(
        "render_times", args.quick, cfg, info, machine, paper_budget_seconds=PAPER_BUDGET_S,
        quality_levels={k: dataclasses.asdict(v) for k, v in jaxflare.QUALITY_LEVELS.items()},
        skipped=bench.skipped, elapsed_s=elapsed,
        method=(
            "wall = time.perf_counter around jaxflare.render after a warm-up render of each configuration (compile excluded); "
            "median over seeds. Noise on image[..., :3] (all flares, no core layer), whole-image squared norms: "
            "sigma^2 = sum ||A_i - mean||^2 / (k - 1), ||mu||^2 = ||mean||^2 - sigma^2 / k, relative RMSE = sqrt(sigma^2 / ||mu||^2); "
            "reference: sigma^2 = mean ||A_i - R||^2 - sigma^2 / m; production: 1/8-sample renders extrapolated by the drawn-sample ratio."
        ),
    )
    written = write_outputs(bench, meta, out_dir, log)
    log("\n" + summary_text(bench))
    for note in bench.skipped:
        log(f"skipped: {note}")
    log(f"\n{elapsed:.1f} s; wrote {shown_paths(written)}")
    return 0 if bench.rows and not any("failed" in s for s in bench.skipped) else 1


if __name__ == "__main__":
    sys.exit(main())
