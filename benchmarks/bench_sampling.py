"""Sampling and "model no more than the scene needs": noise against render time per sampling mode,
and the time saved and image error of each modelling shortcut the renderer takes.

Run:  python benchmarks/bench_sampling.py [--quick] [--no-convergence] [--no-choices] [--out DIR]

Part 1, **convergence** (``sampling_convergence.{csv,json,png}``). Two scenes at 720p: the demo scene
(``jaxflare.load_scene("demo")``: Zeiss Biotar f/2.8, one sphere light) and a *geometry and dirt*
scene built here: the demo camera plus a dirt map (a PNG with a few dark blotches, 1 = clean,
written to a temporary folder) and an occluding plate (a thin ``trimesh`` box written to OBJ) in
front of the lamp that covers part of it (the fraction of light-to-lens segments it blocks is
measured with ``Occluders.segment_visible`` and printed, with the drop of the flare energy against
the demo scene). For 2^19 ... 2^22 samples and three modes,

- ``uniform``: ``sampling="uniform"``, ``method="exact"``;
- ``adaptive``: ``sampling="adaptive"`` (the default), ``method="exact"``;
- ``auto``: ``sampling="adaptive"``, ``method="auto"`` (a path's polynomial where its validation met
  the pixel tolerance and the pilot found its fallback small enough, exact tracing elsewhere); the
  path systems are built once by a warm-up render into a fresh ``JAXFLARE_CACHE_DIR`` (that build
  time is reported on its own) and loaded from there by the timed renders;

two renders (seeds 0, 1) give the relative RMSE (seed pairs, below) against the median wall time, and
the sensor hit rate. ``auto`` also reports its same-seed relative difference from ``adaptive`` (the
same samples per path: the polynomial approximation, not noise). Chart: log-log RMSE against
seconds, one line per mode, one panel per scene.

Part 2, **model choices** (``model_choices.{csv,json,png}``), on two lenses (Zeiss Biotar and
Tronnier Heliar: a double Gauss and a triplet-derived design) in a comparable scene: the demo camera
with that lens at f/4, one sphere light 6 degrees off-axis, 720p. Every render uses the same total
sample count N (2^20) unless said otherwise, so the per-path budget is the same. For each choice the
"full model" and the "reduced" render are timed (median wall of two seeds, warm: every compiled
configuration has had a warm-up render) and compared:

- **culling**: ``cull_threshold`` 0 (full) against 1e-3 (the default) and 1e-2; culled paths, the
  renderer's ``culled_energy_bound`` and the energy actually dropped (the culled paths' energy in
  the full render, relative to the brightest flare, the bound's unit);
- **wavelength strata**: production's 32 strata against preview's 8 at equal samples (time
  difference about 0; the error is the colour-noise difference), and **sample count**: preview
  (2^22) against production (2^26), extrapolated from the N-sample renders (time linear in samples,
  noise variance as 1/N): time and the RMSE of a preview against a production render;
- **polynomial degree from the pixel footprint**: ``method="auto"`` (preview degrees (3, 5) at a
  one-pixel tolerance) against ``"exact"``: render time without the path-system build (the build
  is its own column), paths that ended polynomial and at which degree;
- **field angle**: path systems of the 5 strongest ghost paths (``rank_ghost_paths``), degree 5,
  tolerance one pixel, ``cache=False``, built over the lights' field as ``render`` does
  (ceil((angle + 1) / 5) * 5 degrees) against the lens's full half field of view
  (``half_field_of_view_deg``): build seconds, validation p99 error and trusted fraction (no image);
- **occlusion**: the scene without geometry (the renderer skips the ray casts) against the same
  scene with a mesh that blocks nothing: ``far`` (a box 100 m away: every segment misses its bounding
  box and is answered without casting), rendered as shipped with no warm-up render of its own; and
  ``enclosing`` (two small triangles at opposite corners of a box around camera and lamp: every
  segment is cast with Embree and misses), after a warm-up render, so that the timing is the ray
  casts'. Same seeds as the scene without geometry, so the images must be identical.

The render step holds the ``Occluders`` as a static field hashed by identity; the renderer reuses
the loaded meshes while their files are unchanged (``jaxflare.rendering.effects.cached_occluders``),
so a scene with geometry compiles the step once, not on every render (``step_traces`` in the
records shows it), in part 1 as in part 2.

**Noise and error.** On the flare RGB ``result.image[..., :3]`` (no core), whole-image squared
norms, as ``bench_render.py``: two renders A, B of one configuration give sigma^2 = ||A - B||^2 / 2,
||mu||^2 = ||mean||^2 - sigma^2 / 2, relative RMSE sqrt(sigma^2 / ||mu||^2). A reduced render R_i
(seeds 2, 3) against the full model F_j (seeds 0, 1; independent samples): the raw relative RMSE is
sqrt(mean_i ||R_i - mean(F)||^2 / ||mu_F||^2), whose expectation is (bias^2 + sigma_R^2 +
sigma_F^2 / 2) / ||mu_F||^2, so the **bias estimate** (the error of the reduced model itself) is
sqrt(max(0, raw^2 - (sigma_F^2 / 2 + sigma_R^2) / ||mu_F||^2)); the ``noise floor`` column is the
subtracted term's square root, the scale below which a bias cannot be resolved. Comparisons with
the same seeds (auto against exact, occlusion) draw the same samples, so their difference is the
model error directly (``paired``): raw = bias = sqrt(mean_i ||R_i - F_i||^2 / ||mu_F||^2). ``auto``
is compared with independent seeds: it samples differently from ``exact`` (its pilot's sampling
tables are not kept), so same seeds do not give the same samples.

**Timing.** The median wall time of the renders of a configuration that did not trace the render
step (``step_traces``: ``equinox.debug.get_num_traces(jaxflare.rendering.render_step)`` before and
after): ``method="auto"`` can re-compile after the pilot when a path's exact-fallback capacity
differs from the warm-up's; such a render is not counted when the other seed's was warm (all
records, with ``step_traces``, are in the JSON).

``--quick``: 320x180, 2^15 ... 2^17 samples, only the 3 strongest ghost paths (``paths=``), the
Biotar only in part 2, 1 path for the field-angle builds (about 8 min on the loaded 2-core machine,
most of it compiling); writes into a new temporary folder (printed)
unless ``--out`` is given, never into ``benchmarks/results``.
"""

from __future__ import annotations

import collections
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
    load_average,
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
    usable_cpus,
    with_resolution,
)

CONVERGENCE_STEM = "sampling_convergence"
CHOICES_STEM = "model_choices"

FULL = {
    "resolution": (1280, 720), "convergence_samples": [2**19, 2**20, 2**21, 2**22], "choice_samples": 2**20,
    "seeds": [0, 1], "reduced_seeds": [2, 3], "warmup_samples": 2**16, "lenses": ["zeiss_biotar", "tronnier_heliar"],
    "off_axis_deg": 6.0, "f_number": 4.0, "field_paths": 5, "field_degree": 5, "paths": None,
    "convergence": True, "choices": True,
}
QUICK = dict(FULL, resolution=(320, 180), convergence_samples=[2**15, 2**16, 2**17], choice_samples=2**16,
             warmup_samples=2**13, field_paths=1, paths=3, lenses=["zeiss_biotar"])

MODES = {  # name: (sampling, method)
    "uniform": ("uniform", "exact"),
    "adaptive": ("adaptive", "exact"),
    "auto": ("adaptive", "auto"),
}
CONVERGENCE_FIELDS = [
    "scene", "mode", "sampling", "method", "samples_requested", "samples", "renders", "median_seconds", "render_seconds",
    "compile_seconds", "setup_seconds", "sensor_hit_rate", "relative_rmse", "relative_difference_from_adaptive_same_seed",
    "polynomial_paths", "exact_paths", "table_updates", "step_traces", "machine",
]
CHOICE_FIELDS = [
    "lens", "choice", "full", "reduced", "samples", "full_seconds", "reduced_seconds", "time_saved_seconds",
    "time_saved_percent", "full_render_seconds", "reduced_render_seconds", "relative_rmse_raw", "relative_bias_estimate",
    "noise_floor", "full_noise", "reduced_noise", "comparison", "build_seconds", "notes", "machine",
]


# --------------------------------------------------------------------------- scene inputs


def write_dirt_map(folder: Path, size: int = 256) -> Path:
    """A grey dirt map: a few dark blotches (transmission down to 0.15) and a faint smear; 1 = clean."""
    from PIL import Image

    yy, xx = np.mgrid[0:size, 0:size] / (size - 1) * 2.0 - 1.0
    transmission = np.ones((size, size))
    for cx, cy, radius, depth in ((-0.35, 0.25, 0.12, 0.85), (0.3, -0.2, 0.08, 0.7), (0.05, 0.55, 0.06, 0.6),
                                  (-0.1, -0.5, 0.15, 0.5), (0.55, 0.35, 0.05, 0.8)):
        transmission *= 1.0 - depth * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * radius**2))
    transmission *= 1.0 - 0.25 * np.exp(-((xx + yy) ** 2) / 0.02)  # a diagonal smear
    path = folder / "dirt.png"
    Image.fromarray(np.clip(np.round(transmission * 255), 0, 255).astype(np.uint8), mode="L").save(path)
    return path


def write_box(folder: Path, name: str, centre, extents) -> Path:
    import trimesh

    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_translation(centre)
    path = folder / f"{name}.obj"
    mesh.export(path)
    return path


def write_corner_triangles(folder: Path, low, high) -> Path:
    """Two small triangles at opposite corners of the box [low, high]: its bounding box holds every
    light-to-lens segment of the scene (all are cast), but nothing is hit."""
    import trimesh

    low, high = np.asarray(low, float), np.asarray(high, float)
    tri = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0]])
    vertices = np.concatenate([low + tri, high - tri])
    mesh = trimesh.Trimesh(vertices=vertices, faces=[[0, 1, 2], [3, 4, 5]], process=False)
    path = folder / "enclosing.obj"
    mesh.export(path)
    return path


def light_centre(scene) -> np.ndarray:
    return np.asarray(scene.lights[0].position_m, float)


def blocked_fraction(scene, mesh_file: Path, rays: int = 20000, seed: int = 0) -> float:
    """Fraction of light-to-front-lens segments the mesh blocks (uniform points on the sphere light,
    uniform points on the front clear aperture)."""
    from jaxflare.rendering.effects import load_occluders
    from jaxflare.scenes import camera_lens

    rng = np.random.default_rng(seed)
    light = scene.lights[0]
    direction = rng.normal(size=(rays, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    starts = light_centre(scene) + light.radius_m * direction
    camera = scene.camera
    radius = float(camera_lens(camera).semi_aperture_mm[0])
    r = radius * np.sqrt(rng.uniform(size=rays))
    phi = rng.uniform(0, 2 * np.pi, size=rays)
    lens_mm = np.stack([r * np.cos(phi), r * np.sin(phi), np.zeros(rays)], axis=1)
    ends = np.asarray(camera.position_m, float) + lens_mm @ camera.world_to_camera() / 1000.0  # R^T p
    occluders = load_occluders([mesh_file])
    return float(1.0 - np.mean(occluders.segment_visible(starts, ends)))


def with_geometry(scene, *files):
    import jaxflare

    return dataclasses.replace(scene, geometry=tuple(jaxflare.Geometry(file=str(f)) for f in files))


def with_settings(scene, **settings):
    return dataclasses.replace(scene, render=dataclasses.replace(scene.render, **settings))


def choice_scene(demo, lens: str, off_axis_deg: float, f_number: float, resolution):
    """The demo camera with ``lens`` at ``f_number`` and the demo lamp moved to ``off_axis_deg``
    (horizontally) at the same distance."""
    camera = dataclasses.replace(demo.camera, lens=lens, f_number=f_number, resolution=tuple(resolution))
    position = np.asarray(camera.position_m, float)
    distance = 20.0
    lamp = dataclasses.replace(demo.lights[0], position_m=(float(position[0] + distance * math.tan(math.radians(off_axis_deg))),
                                                           float(position[1]), float(position[2] - distance)))
    return dataclasses.replace(demo, camera=camera, lights=(lamp,), source=None)


def flare_energy(stats: dict) -> float:
    return float(sum(p["energy"] for p in stats["paths"] if p["path"] != "primary"))


def warm_median(records: list[dict], key: str = "wall_seconds") -> float:
    """Median over the records whose render did not trace (compile) the render step, if any did not:
    a render that compiled is not a warm render (its time is in the JSON all the same)."""
    warm = [r for r in records if not r.get("step_traces")]
    return median(warm or records, key)


# --------------------------------------------------------------------------- comparisons


def compare_independent(full: list[np.ndarray], reduced: list[np.ndarray]) -> dict:
    nf, nr = seed_noise(full), seed_noise(reduced)
    mean_f = np.mean([np.asarray(a, np.float64) for a in full], axis=0)
    raw2 = statistics.mean(sq_norm(np.asarray(r, np.float64) - mean_f) for r in reduced)
    mu2 = nf["mu2"]
    floor2 = nf["sigma2"] / len(full) + nr["sigma2"]
    return {"comparison": "independent seeds, noise subtracted", "relative_rmse_raw": relative(raw2, mu2),
            "relative_bias_estimate": relative(max(0.0, raw2 - floor2), mu2), "relative_bias2_signed": (raw2 - floor2) / mu2 if mu2 > 0 else float("nan"),
            "noise_floor": relative(floor2, mu2), "full_noise": nf["relative_rmse"], "reduced_noise": nr["relative_rmse"],
            "mu2": mu2}


def compare_paired(full: list[np.ndarray], reduced: list[np.ndarray]) -> dict:
    nf, nr = seed_noise(full), seed_noise(reduced)
    d2 = statistics.mean(sq_norm(np.asarray(r, np.float64) - np.asarray(f, np.float64)) for f, r in zip(full, reduced, strict=True))
    rel = relative(d2, nf["mu2"])
    max_abs = max(float(np.max(np.abs(np.asarray(r, np.float64) - np.asarray(f, np.float64)))) for f, r in zip(full, reduced, strict=True))
    return {"comparison": "paired (same seeds, same samples)", "relative_rmse_raw": rel, "relative_bias_estimate": rel,
            "relative_bias2_signed": rel**2, "noise_floor": 0.0, "full_noise": nf["relative_rmse"], "reduced_noise": nr["relative_rmse"],
            "mu2": nf["mu2"], "max_abs_pixel_difference": max_abs}


# --------------------------------------------------------------------------- the benchmark


class SamplingBench(GuardedSteps):
    def __init__(self, cfg: dict, out_dir: Path, machine: str, log, work: Path):
        import jaxflare

        self.cfg, self.out_dir, self.machine, self.log, self.work = cfg, out_dir, machine, log, work
        self.jaxflare = jaxflare
        self.demo = with_resolution(jaxflare.load_scene("demo"), cfg["resolution"])
        self.records: list[dict] = []
        self.convergence_rows: list[dict] = []
        self.choice_rows: list[dict] = []
        self.field_rows: list[dict] = []
        self.checks: dict = {}
        self.skipped: list[str] = []

    # ---- helpers
    def paths_for(self, scene):
        """``paths=`` of every render: None (all) in the full run, the strongest ghost paths in --quick."""
        if not self.cfg["paths"]:
            return None
        from jaxflare.optics import rank_ghost_paths
        from jaxflare.scenes import camera_lens

        return [p for p, _ in rank_ghost_paths(camera_lens(scene.camera))[: self.cfg["paths"]]]

    def render(self, scene, label, **kwargs):
        kwargs.setdefault("paths", self.paths_for(scene))
        record, flare, result = render_once(scene, self.log, label, **kwargs)
        stats = result.statistics
        record.update(case=label, culled_paths=stats["culled_paths"], culled_energy_bound=stats["culled_energy_bound"],
                      table_updates=stats["table_updates"], sampling=stats["sampling"], method=stats["settings"]["method"],
                      quality=stats["settings"]["quality"], wavelength_strata=stats["settings"]["wavelength_strata"],
                      cull_threshold=stats["settings"]["cull_threshold"], field_angle_deg=stats["field_angle_deg"],
                      flare_energy=flare_energy(stats))
        self.records.append(record)
        return record, flare, stats

    def renders(self, scene, label, seeds, **kwargs):
        records, images, stats = [], [], []
        for seed in seeds:
            record, flare, st = self.render(scene, f"{label} seed {seed}", seed=seed, **kwargs)
            records.append(record)
            images.append(flare)
            stats.append(st)
        return records, images, stats

    # ---- part 1: convergence
    def geometry_dirt_scene(self):
        demo = self.demo
        lamp = light_centre(demo)
        camera = np.asarray(demo.camera.position_m, float)
        z_plate = lamp[2] + 1.0  # 1 m in front of the lamp, towards the camera
        t = (z_plate - camera[2]) / (lamp[2] - camera[2])
        through = camera + t * (lamp - camera)  # the lamp's centre line at the plate
        # a plate whose right edge runs through the lamp's centre line: it hides the left half of the lamp
        plate = write_box(self.work, "plate", centre=(through[0] - 1.0, through[1], z_plate), extents=(2.0, 2.0, 0.02))
        dirt = write_dirt_map(self.work)
        scene = dataclasses.replace(with_geometry(demo, plate), camera=dataclasses.replace(demo.camera, dirt_map=str(dirt)))
        fraction = blocked_fraction(demo, plate)
        self.checks["geometry_dirt_scene"] = {"plate_obj": str(plate), "dirt_png": str(dirt), "plate_centre_m": [through[0] - 1.0, through[1], z_plate],
                                              "blocked_segment_fraction": fraction}
        self.log(f"  geometry-and-dirt scene: plate {plate.name} blocks {fraction:.1%} of the lamp-to-lens segments; dirt map {dirt.name}")
        if fraction < 0.05:
            self.log("  WARNING: the plate blocks almost nothing")
        return scene

    def convergence(self) -> None:
        cfg = self.cfg
        scenes = {"demo": self.demo, "geometry_dirt": self.geometry_dirt_scene()}
        self.log("\n-- convergence: warm-up (compile; auto: path-system build into the fresh cache, reported separately)")
        warm = {}
        for name, scene in scenes.items():
            record, _, _ = self.render(scene, f"warm-up {name} exact", samples=cfg["warmup_samples"], method="exact")
            warm[name] = record
            record, _, _ = self.render(scene, f"warm-up {name} auto (build)", samples=cfg["warmup_samples"], method="auto")
            self.checks.setdefault("auto_build", {})[name] = {"setup_seconds": record["setup_seconds"], "wall_seconds": record["wall_seconds"],
                                                             "compile_seconds": record["compile_seconds"]}
            self.log(f"  {name}: path-system set-up {record['setup_seconds']:.1f} s (build, or load if cached by the scene before)")
        drop = 1.0 - warm["geometry_dirt"]["flare_energy"] / warm["demo"]["flare_energy"] if warm["demo"]["flare_energy"] > 0 else float("nan")
        self.checks["geometry_dirt_scene"]["flare_energy_drop_vs_demo"] = drop
        self.log(f"  geometry-and-dirt scene: flare energy {drop:.1%} below the demo scene's (occlusion and dirt, warm-up renders)")
        for name, scene in scenes.items():
            adaptive_seed0 = {}
            for mode, (sampling, method) in MODES.items():
                s = with_settings(scene, sampling=sampling)
                self.log(f"\n-- convergence {name}, {mode} (sampling {sampling}, method {method}), seeds {cfg['seeds']}")
                for n in cfg["convergence_samples"]:
                    records, images, _ = self.renders(s, f"{name} {mode} 2^{math.log2(n):.0f}", cfg["seeds"], samples=n, method=method)
                    noise = seed_noise(images)
                    difference = float("nan")
                    if mode == "adaptive":
                        adaptive_seed0[n] = images[0]
                    elif mode == "auto" and n in adaptive_seed0:
                        ref = np.asarray(adaptive_seed0[n], np.float64)
                        difference = math.sqrt(sq_norm(np.asarray(images[0], np.float64) - ref) / max(sq_norm(ref), 1e-300))
                    row = {
                        "scene": name, "mode": mode, "sampling": sampling, "method": method, "samples_requested": n,
                        "samples": records[0]["samples"], "renders": len(records), "median_seconds": warm_median(records),
                        "render_seconds": warm_median(records, "render_seconds"), "compile_seconds": median(records, "compile_seconds"),
                        "setup_seconds": median(records, "setup_seconds"), "sensor_hit_rate": median(records, "sensor_hit_rate"),
                        "relative_rmse": noise["relative_rmse"], "relative_difference_from_adaptive_same_seed": difference,
                        "wall_seconds_all": [r["wall_seconds"] for r in records],
                        "polynomial_paths": records[0]["polynomial_paths"], "exact_paths": records[0]["exact_paths"],
                        "table_updates": records[0]["table_updates"], "step_traces": sum(r["step_traces"] for r in records),
                        "machine": self.machine,
                    }
                    self.convergence_rows.append(row)
                    self.log(f"    relative RMSE {noise['relative_rmse']:.4f}, median {row['median_seconds']:.2f} s, hit rate {row['sensor_hit_rate']:.4f}"
                             + (f", auto vs adaptive (same seed) {difference:.2e}" if math.isfinite(difference) else ""))
                del images

    # ---- part 2: model choices
    def choice_row(self, lens, choice, full_label, reduced_label, full_records, reduced_records, comparison: dict, *,
                   build_seconds=None, notes="", samples=None):
        t_full, t_red = warm_median(full_records), warm_median(reduced_records)
        row = {
            "lens": lens, "choice": choice, "full": full_label, "reduced": reduced_label,
            "samples": samples if samples is not None else reduced_records[0]["samples"],
            "full_seconds": t_full, "reduced_seconds": t_red, "time_saved_seconds": t_full - t_red,
            "time_saved_percent": 100.0 * (1.0 - t_red / t_full) if t_full > 0 else float("nan"),
            "full_render_seconds": warm_median(full_records, "render_seconds"), "reduced_render_seconds": warm_median(reduced_records, "render_seconds"),
            "relative_rmse_raw": comparison.get("relative_rmse_raw", float("nan")),
            "relative_bias_estimate": comparison.get("relative_bias_estimate", float("nan")),
            "noise_floor": comparison.get("noise_floor", float("nan")), "full_noise": comparison.get("full_noise", float("nan")),
            "reduced_noise": comparison.get("reduced_noise", float("nan")), "comparison": comparison.get("comparison", ""),
            "build_seconds": build_seconds, "notes": notes, "machine": self.machine,
            "detail": {k: v for k, v in comparison.items() if k not in ("comparison",)},
            "full_step_traces": sum(r["step_traces"] for r in full_records), "reduced_step_traces": sum(r["step_traces"] for r in reduced_records),
        }
        self.choice_rows.append(row)
        self.log(f"  => {choice}: {full_label} {t_full:.2f} s -> {reduced_label} {t_red:.2f} s ({row['time_saved_percent']:+.1f} % saved); "
                 f"relative RMSE raw {fmt(row['relative_rmse_raw'], '.2e')}, bias {fmt(row['relative_bias_estimate'], '.2e')} "
                 f"(noise floor {fmt(row['noise_floor'], '.2e')}){'; ' + notes if notes else ''}")
        return row

    def choices(self, lens: str) -> None:
        cfg = self.cfg
        n = cfg["choice_samples"]
        scene = choice_scene(self.demo, lens, cfg["off_axis_deg"], cfg["f_number"], cfg["resolution"])
        seeds_full, seeds_red = cfg["seeds"], cfg["reduced_seeds"]
        far = write_box(self.work, f"far_{lens}", centre=(100.0, 100.0, 100.0), extents=(1.0, 1.0, 1.0))
        lamp, cam = light_centre(scene), np.asarray(scene.camera.position_m, float)
        low = np.minimum(lamp, cam) - 5.0
        high = np.maximum(lamp, cam) + 5.0
        enclosing = write_corner_triangles(self.work, low, high)
        scene_far, scene_enc = with_geometry(scene, far), with_geometry(scene, enclosing)
        blocked = {"far": blocked_fraction(scene, far), "enclosing": blocked_fraction(scene, enclosing)}
        self.checks.setdefault("choices", {})[lens] = {"blocked_fraction": blocked, "light_position_m": lamp.tolist()}
        self.log(f"\n-- model choices, {lens} at f/{cfg['f_number']:g}, lamp {cfg['off_axis_deg']:g} deg off-axis, "
                 f"{'x'.join(map(str, cfg['resolution']))}, {n} samples; non-blocking meshes block {blocked['far']:.3%} / {blocked['enclosing']:.3%}")
        self.log("   warm-up (compiles each configuration; auto builds the path systems):")
        w = cfg["warmup_samples"]
        self.render(scene, f"warm-up {lens} exact", samples=w, method="exact")
        self.render(scene, f"warm-up {lens} production strata", samples=w, method="exact", quality="production")
        auto_warm, _, _ = self.render(scene, f"warm-up {lens} auto (build)", samples=w, method="auto")
        build = auto_warm["setup_seconds"]

        base_r, base_i, base_s = self.renders(scene, f"{lens} default", seeds_red, samples=n, method="exact")
        cull0_r, cull0_i, cull0_s = self.renders(with_settings(scene, cull_threshold=0.0), f"{lens} cull 0", seeds_full, samples=n, method="exact")
        cull2_r, cull2_i, cull2_s = self.renders(with_settings(scene, cull_threshold=1e-2), f"{lens} cull 1e-2", seeds_red, samples=n, method="exact")

        def cull_notes(stats_reduced):
            disabled = [tuple(p["path"]) for p in stats_reduced["paths"] if p["path"] != "primary" and not p["enabled"]]
            full_paths = [p for p in cull0_s[0]["paths"] if p["path"] != "primary"]
            brightest = max((p["energy"] for p in full_paths), default=0.0)
            total = sum(p["energy"] for p in full_paths)
            dropped = sum(p["energy"] for p in full_paths if tuple(p["path"]) in disabled)
            actual = dropped / brightest if brightest > 0 else float("nan")
            bound = stats_reduced["culled_energy_bound"]
            info = {"culled_paths": len(disabled), "of_paths": len(full_paths), "culled_energy_bound": bound,
                    "culled_energy_actual_vs_brightest": actual, "culled_energy_actual_vs_total": dropped / total if total > 0 else float("nan"),
                    "bound_holds": bool(actual <= bound * (1 + 1e-6) + 1e-12)}
            text = (f"{len(disabled)}/{len(full_paths)} paths culled; energy bound {bound:.2e}, actual {actual:.2e} of the brightest flare "
                    f"({info['culled_energy_actual_vs_total']:.2e} of all flares)" + ("" if info["bound_holds"] else " BOUND EXCEEDED"))
            return info, text

        for threshold, (rec, img, st) in (("1e-3", (base_r, base_i, base_s)), ("1e-2", (cull2_r, cull2_i, cull2_s))):
            info, text = cull_notes(st[0])
            row = self.choice_row(lens, f"culling {threshold}", "cull_threshold 0", f"cull_threshold {threshold}", cull0_r, rec,
                                  compare_independent(cull0_i, img), notes=text)
            row["detail"].update(info)
        del cull2_i

        s32_r, s32_i, _ = self.renders(scene, f"{lens} 32 strata", seeds_full, samples=n, method="exact", quality="production")
        strata = compare_independent(s32_i, base_i)
        self.choice_row(lens, "wavelength strata", "32 (production)", "8 (preview)", s32_r, base_r, strata, notes="equal samples")
        # quality sample counts, extrapolated from the N-sample renders
        levels = self.jaxflare.QUALITY_LEVELS
        n_prev, n_prod = levels["preview"].samples, levels["production"].samples
        drawn = base_r[0]["samples"]
        t_prev = median(base_r, "wall_seconds") * n_prev / n
        t_prod = median(s32_r, "wall_seconds") * n_prod / n
        sig_prev = seed_noise(base_i)["sigma2"] * n / n_prev
        sig_prod = seed_noise(s32_i)["sigma2"] * n / n_prod
        mu2 = strata["mu2"]
        bias2 = max(0.0, strata["relative_bias2_signed"]) * mu2
        extrap = {"comparison": "extrapolated from the N-sample renders (time x samples, variance / samples)",
                  "relative_rmse_raw": relative(sig_prev + sig_prod + bias2, mu2), "relative_bias_estimate": relative(sig_prev + bias2, mu2),
                  "noise_floor": float("nan"), "full_noise": relative(sig_prod, mu2), "reduced_noise": relative(sig_prev, mu2)}
        fake_full = [{"wall_seconds": t_prod, "render_seconds": median(s32_r, "render_seconds") * n_prod / n, "step_traces": 0}]
        fake_red = [{"wall_seconds": t_prev, "render_seconds": median(base_r, "render_seconds") * n_prev / n, "step_traces": 0, "samples": drawn * n_prev // n}]
        self.choice_row(lens, "quality samples", f"production ({n_prod})", f"preview ({n_prev})", fake_full, fake_red, extrap, samples=n_prev,
                        notes="extrapolated; bias column = preview's RMSE against the noise-free production image")
        del s32_i

        auto_r, auto_i, auto_s = self.renders(scene, f"{lens} auto", seeds_full, samples=n, method="auto")
        degrees = collections.Counter()
        for p in auto_s[0]["paths"]:
            degrees[(p["method"], p["polynomial_degree"])] += 1
        text = (f"{auto_r[0]['polynomial_paths']} paths polynomial, {auto_r[0]['exact_paths']} exact; "
                + ", ".join(f"{m} with degree-{d} system: {c}" for (m, d), c in sorted(degrees.items(), key=str))
                + f"; path-system set-up {build:.1f} s{' (cached by an earlier build)' if build < 5 else ''}")
        row = self.choice_row(lens, "polynomial (auto)", "exact", "auto", base_r, auto_r, compare_independent(base_i, auto_i), build_seconds=build, notes=text)
        row["detail"]["paths"] = [{k: p[k] for k in ("path", "method", "polynomial_degree", "polynomial_validation_trusted_fraction",
                                                    "polynomial_untrusted_sample_fraction", "exact_fallback_capacity")} for p in auto_s[0]["paths"]]
        del auto_i

        # as shipped, no warm-up: the first render with the mesh compiles the step (the renderer
        # reuses the loaded mesh afterwards, so a later one does not, unless the renderer changes)
        rec, img, _ = self.renders(scene_far, f"{lens} far mesh (as shipped)", seeds_red, samples=n, method="exact")
        traces = sum(r["step_traces"] for r in rec)
        compiles = "each mesh render re-compiles the step" if traces >= len(rec) else "the renderer reused the loaded mesh"
        self.choice_row(lens, "occlusion skip (far mesh)", "far mesh (as shipped)", "no geometry", rec, base_r, compare_paired(img, base_i),
                        notes=f"blocks {blocked['far']:.2%}; {compiles} (first batch "
                        f"{median(rec, 'compile_seconds'):.1f} s, {traces} traces in {len(rec)} renders); "
                        f"render loop {median(rec, 'render_seconds'):.2f} -> {median(base_r, 'render_seconds'):.2f} s")
        del img
        # one compile (the warm-up), then the timed renders measure the ray casts
        self.render(scene_enc, f"warm-up {lens} enclosing mesh", samples=w, method="exact")
        rec, img, _ = self.renders(scene_enc, f"{lens} enclosing mesh", seeds_red, samples=n, method="exact")
        traces = sum(r["step_traces"] for r in rec)
        self.choice_row(lens, "occlusion skip (enclosing mesh)", "enclosing mesh (cached load)", "no geometry", rec, base_r, compare_paired(img, base_i),
                        notes=f"blocks {blocked['enclosing']:.2%}; every segment cast (Embree), mesh loaded once; render loop "
                        f"{median(rec, 'render_seconds'):.2f} -> {median(base_r, 'render_seconds'):.2f} s"
                        + (f"; step traced {traces}x" if traces else ""))
        del img
        self.field_angle(lens, scene, base_s[0])

    def field_angle(self, lens_name: str, scene, stats) -> None:
        import jaxflare
        from jaxflare.optics import rank_ghost_paths
        from jaxflare.scenes import camera_lens, sensor_size_mm

        cfg = self.cfg
        render_lens = camera_lens(scene.camera)
        geometry_lens = camera_lens(scene.camera, with_iris=False, with_coatings=False)
        pitch = sensor_size_mm(scene.camera, render_lens)[0] / scene.camera.resolution[0]
        level = jaxflare.QUALITY_LEVELS[scene.render.quality]
        tolerance = level.tolerance_px * pitch
        lights = min(85.0, 5.0 * math.ceil((stats["field_angle_deg"] + 1.0) / 5.0))
        full = float(jaxflare.half_field_of_view_deg(geometry_lens))
        paths = [p for p, _ in rank_ghost_paths(render_lens)[: cfg["field_paths"]]]
        self.log(f"\n-- field angle, {lens_name}: degree {cfg['field_degree']} path systems of {paths}, tolerance {tolerance * 1e3:.1f} um "
                 f"(1 px); lights' field {stats['field_angle_deg']:.2f} deg -> domain {lights:g} deg, half field of view {full:.2f} deg")
        for angle in (lights, full):  # compiles the fit and validation code for this lens, degree and domain
            t0 = time.perf_counter()
            jaxflare.path_system(geometry_lens, paths[0], degree=cfg["field_degree"], max_field_angle_deg=angle, tolerance_mm=tolerance, cache=False, seed=7)
            self.log(f"  warm-up build at {angle:.1f} deg (seed 7, not counted): {time.perf_counter() - t0:.2f} s")
        results = {}
        for label, angle in (("full field", full), ("lights' field", lights)):
            reports = []
            for path in paths:
                t0 = time.perf_counter()
                system = jaxflare.path_system(geometry_lens, path, degree=cfg["field_degree"], max_field_angle_deg=angle, tolerance_mm=tolerance, cache=False)
                wall = time.perf_counter() - t0
                r = system.report
                reports.append({"path": list(path), "wall_seconds": wall, "build_seconds": r.build_seconds, "error_um_p99": r.error_um_p99,
                                "trusted_error_um_p99": r.trusted_error_um_p99, "trusted_fraction": r.trusted_fraction,
                                "valid_fraction": r.valid_fraction, "mask_mismatch": r.mask_mismatch})
                self.log(f"  {label:14s} {angle:5.1f} deg path {path}: {wall:6.2f} s, p99 error {r.error_um_p99 / (pitch * 1e3):7.3f} px, "
                         f"trusted {r.trusted_fraction:.3f}")
            results[label] = {"angle_deg": angle, "paths": reports, "seconds": sum(x["wall_seconds"] for x in reports),
                              "p99_px_median": statistics.median(x["error_um_p99"] for x in reports) / (pitch * 1e3),
                              "trusted_fraction_mean": statistics.mean(x["trusted_fraction"] for x in reports)}
        f, r = results["full field"], results["lights' field"]
        row = {"lens": lens_name, "choice": "field angle (path build)", "full": f"{full:.1f} deg (half FOV)", "reduced": f"{lights:g} deg (lights)",
               "samples": None, "full_seconds": f["seconds"], "reduced_seconds": r["seconds"], "time_saved_seconds": f["seconds"] - r["seconds"],
               "time_saved_percent": 100.0 * (1 - r["seconds"] / f["seconds"]) if f["seconds"] > 0 else float("nan"),
               "full_render_seconds": None, "reduced_render_seconds": None, "relative_rmse_raw": float("nan"), "relative_bias_estimate": float("nan"),
               "noise_floor": float("nan"), "full_noise": float("nan"), "reduced_noise": float("nan"),
               "comparison": f"build of {len(paths)} degree-{cfg['field_degree']} systems, cache off",
               "build_seconds": r["seconds"], "machine": self.machine,
               "notes": (f"p99 error {f['p99_px_median']:.3f} -> {r['p99_px_median']:.3f} px (median over paths), trusted fraction "
                         f"{f['trusted_fraction_mean']:.3f} -> {r['trusted_fraction_mean']:.3f}"),
               "detail": {"pixel_pitch_mm": pitch, "tolerance_mm": tolerance, **results}, "full_step_traces": 0, "reduced_step_traces": 0}
        self.choice_rows.append(row)
        self.log(f"  => field angle: {f['seconds']:.1f} s -> {r['seconds']:.1f} s ({row['time_saved_percent']:+.1f} % saved); {row['notes']}")

    def run(self) -> None:
        cache = tempfile.mkdtemp(prefix="jaxflare_bench_sampling_cache_")
        self.log(f"  JAXFLARE_CACHE_DIR={cache} (fresh; removed at the end)")
        try:
            with temporary_env("JAXFLARE_CACHE_DIR", cache):
                if self.cfg["convergence"]:
                    self.step("convergence", self.convergence)
                else:
                    self.skipped.append("convergence (--no-convergence)")
                if self.cfg["choices"]:
                    for lens in self.cfg["lenses"]:
                        self.step(f"model choices {lens}", self.choices, lens)
                else:
                    self.skipped.append("model choices (--no-choices)")
        finally:
            shutil.rmtree(cache, ignore_errors=True)


# --------------------------------------------------------------------------- outputs


def _title(meta: dict, what: str) -> str:
    m = meta["machine"]
    return (f"{what} ({meta['mode']}; {cpu_label(m)}, "
            f"jax {m.get('jax')} ({m.get('jax_backend')}), load {m.get('load_average_start')})")


def _convergence_chart(bench: SamplingBench, meta: dict):
    plt = pyplot()

    scenes = list(dict.fromkeys(r["scene"] for r in bench.convergence_rows))
    fig, axes = plt.subplots(1, max(1, len(scenes)), figsize=(6.2 * max(1, len(scenes)), 5.2), squeeze=False)
    labels = {"demo": "demo scene (Biotar f/2.8)", "geometry_dirt": "demo + occluding plate + dirt map"}
    styles = {"uniform": ("C0", "o"), "adaptive": ("C1", "s"), "auto": ("C2", "^")}
    for ax, scene in zip(axes[0], scenes, strict=False):
        for mode, (sampling, method) in MODES.items():
            pts = [r for r in bench.convergence_rows if r["scene"] == scene and r["mode"] == mode
                   and math.isfinite(r["relative_rmse"]) and r["median_seconds"] > 0]
            if not pts:
                continue
            colour, marker = styles[mode]
            ax.plot([p["median_seconds"] for p in pts], [p["relative_rmse"] for p in pts], marker + "-", color=colour,
                    label=f"{mode} (sampling {sampling}, method {method})")
            for p in pts:
                ax.annotate(f"2^{math.log2(p['samples_requested']):.0f}", (p["median_seconds"], p["relative_rmse"]),
                            textcoords="offset points", xytext=(4, 3), fontsize=7, color=colour)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
        ax.set_xlabel("wall time per render (warm) [s]")
        ax.set_ylabel("relative RMSE of the flare RGB (seed pairs)")
        ax.set_title(labels.get(scene, scene), fontsize=10)
        ax.legend(fontsize=8)
    fig.suptitle(_title(meta, "noise against render time per sampling mode"), fontsize=8)
    fig.tight_layout()
    return fig


def _choices_chart(bench: SamplingBench, meta: dict):
    plt = pyplot()

    rows = bench.choice_rows
    choices = list(dict.fromkeys(r["choice"] for r in rows))
    lenses = list(dict.fromkeys(r["lens"] for r in rows))
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(13.0, 5.6))
    width = 0.8 / max(1, len(lenses))
    x = np.arange(len(choices))
    floor = 1e-6
    for k, lens in enumerate(lenses):
        by = {r["choice"]: r for r in rows if r["lens"] == lens}
        saved = [by[c]["time_saved_percent"] if c in by and by[c]["time_saved_percent"] is not None else np.nan for c in choices]
        raw = [by[c]["relative_rmse_raw"] if c in by else np.nan for c in choices]
        bias = [by[c]["relative_bias_estimate"] if c in by else np.nan for c in choices]
        offset = (k - (len(lenses) - 1) / 2) * width
        ax1.bar(x + offset, saved, width, color=f"C{k}", label=lens)
        ax2.bar(x + offset, [max(v, floor) if math.isfinite(v) else np.nan for v in raw], width, color=f"C{k}", alpha=0.3,
                edgecolor=f"C{k}", label=f"{lens}: raw (incl. noise)")
        ax2.bar(x + offset, [max(v, floor) if math.isfinite(v) else np.nan for v in bias], width * 0.55, color=f"C{k}",
                label=f"{lens}: bias estimate (noise subtracted)")
        for xi, v in zip(x + offset, raw, strict=True):
            if not math.isfinite(v):
                ax2.annotate("n/a", (xi, floor), ha="center", va="bottom", fontsize=7, color=f"C{k}")
    for ax in (ax1, ax2):
        ax.set_xticks(x)
        ax.set_xticklabels(choices, rotation=30, ha="right", fontsize=8)
        ax.grid(True, axis="y", alpha=0.3)
    ax1.axhline(0, color="0.3", lw=0.8)
    ax1.set_ylabel("time saved by the reduced model [%]")
    ax1.legend(fontsize=8)
    ax2.set_yscale("log")
    ax2.set_ylim(bottom=floor)
    ax2.set_ylabel(f"relative RMSE against the full model (floor {floor:g})")
    ax2.legend(fontsize=7)
    fig.suptitle(_title(meta, "model no more than the scene needs: time saved and image error per choice"), fontsize=8)
    fig.tight_layout()
    return fig


def write_outputs(bench: SamplingBench, meta: dict, out_dir: Path, log) -> list[Path]:
    out = Outputs(out_dir, log)
    number_format = {"float_format": ".6g", "blank_nonfinite": True}
    if bench.convergence_rows:
        out.csv(f"{CONVERGENCE_STEM}.csv", bench.convergence_rows, CONVERGENCE_FIELDS, **number_format)
        out.json(f"{CONVERGENCE_STEM}.json", dict(meta, benchmark=CONVERGENCE_STEM, rows=bench.convergence_rows,
                                                  checks={k: v for k, v in bench.checks.items() if k != "choices"},
                                                  renders=[r for r in bench.records if not r["case"].startswith(tuple(bench.cfg["lenses"]))]))
        out.chart(f"{CONVERGENCE_STEM}.png", _convergence_chart, bench, meta)
    if bench.choice_rows:
        out.csv(f"{CHOICES_STEM}.csv", bench.choice_rows, CHOICE_FIELDS, **number_format)
        out.json(f"{CHOICES_STEM}.json", dict(meta, benchmark=CHOICES_STEM, rows=bench.choice_rows, checks=bench.checks.get("choices", {}),
                                              renders=bench.records))
        out.chart(f"{CHOICES_STEM}.png", _choices_chart, bench, meta)
    return out.written


def summary_text(bench: SamplingBench) -> str:
    lines = []
    if bench.convergence_rows:
        lines.append(f"{'scene':14s} {'mode':9s} {'samples':>9s} {'median s':>9s} {'hit rate':>8s} {'rel. RMSE':>9s} {'RMSE*sqrt(s)':>12s}  notes")
        for r in bench.convergence_rows:
            note = ""
            if math.isfinite(r["relative_difference_from_adaptive_same_seed"]):
                note = f"{r['polynomial_paths']} poly/{r['exact_paths']} exact; vs adaptive same seed {r['relative_difference_from_adaptive_same_seed']:.1e}"
            if r["step_traces"]:
                note += f" step traced x{r['step_traces']}"
            eff = r["relative_rmse"] * math.sqrt(r["median_seconds"]) if math.isfinite(r["relative_rmse"]) else float("nan")
            lines.append(f"{r['scene']:14s} {r['mode']:9s} {r['samples']:>9d} {fmt(r['median_seconds'], '9.2f')} {fmt(r['sensor_hit_rate'], '8.4f')} "
                         f"{fmt(r['relative_rmse'], '9.4f')} {fmt(eff, '12.4f')}  {note}")
        c = bench.checks
        if "auto_build" in c:
            lines.append("auto path-system set-up (warm-up): " + ", ".join(f"{k} {v['setup_seconds']:.1f} s" for k, v in c["auto_build"].items()))
        if "geometry_dirt_scene" in c:
            g = c["geometry_dirt_scene"]
            lines.append(f"geometry_dirt scene: plate blocks {g['blocked_segment_fraction']:.1%} of lamp-to-lens segments; flare energy "
                         f"{fmt(g.get('flare_energy_drop_vs_demo'), '.1%')} below the demo's")
        lines.append("")
    if bench.choice_rows:
        lines.append(f"{'lens':16s} {'choice':30s} {'full s':>8s} {'reduced s':>9s} {'saved %':>8s} {'RMSE raw':>9s} {'bias est.':>9s} {'floor':>8s}  notes")
        for r in bench.choice_rows:
            lines.append(f"{r['lens']:16s} {r['choice']:30s} {fmt(r['full_seconds'], '8.2f')} {fmt(r['reduced_seconds'], '9.2f')} "
                         f"{fmt(r['time_saved_percent'], '8.1f')} {fmt(r['relative_rmse_raw'], '9.2e')} {fmt(r['relative_bias_estimate'], '9.2e')} "
                         f"{fmt(r['noise_floor'], '8.1e')}  {r['notes']}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    parser = make_parser(__doc__, "smoke test: 320x180, 2^15-2^17 samples, the 3 strongest ghost paths, Biotar only; writes to a temporary folder")
    parser.add_argument("--no-convergence", action="store_true", help="skip part 1 (convergence charts)")
    parser.add_argument("--no-choices", action="store_true", help="skip part 2 (model-choice table)")
    parser.add_argument("--lenses", nargs="+", help="lenses of part 2 (default zeiss_biotar tronnier_heliar)")
    add_out_option(parser, quick_folder=True)
    args = parser.parse_args(argv)

    cfg = dict(QUICK if args.quick else FULL)
    cfg["convergence"] = cfg["convergence"] and not args.no_convergence
    cfg["choices"] = cfg["choices"] and not args.no_choices
    if args.lenses:
        cfg["lenses"] = list(args.lenses)
    out_dir = output_folder(args, "sampling")

    started = time.perf_counter()
    import jaxflare

    info, machine = announce("bench_sampling", args.quick, log)
    cpus = usable_cpus(info)
    log(f"  output folder: {out_dir}")
    work = Path(tempfile.mkdtemp(prefix="jaxflare_bench_sampling_inputs_"))
    try:
        bench = SamplingBench(cfg, out_dir, machine, log, work)
        bench.run()
        elapsed = time.perf_counter() - started
        meta = run_meta(
            None, args.quick, cfg, info, machine,
            quality_levels={k: dataclasses.asdict(v) for k, v in jaxflare.QUALITY_LEVELS.items()}, skipped=bench.skipped,
            elapsed_s=elapsed,
            method=(
                "wall = time.perf_counter around jaxflare.render after a warm-up render of each configuration; median of two seeds. "
                "Noise on image[..., :3] (no core): sigma^2 = ||A - B||^2 / 2, ||mu||^2 = ||mean||^2 - sigma^2 / 2, relative RMSE = "
                "sqrt(sigma^2 / ||mu||^2). Reduced vs full (independent seeds): raw^2 = mean_i ||R_i - mean(F)||^2 / ||mu_F||^2, "
                "bias^2 = raw^2 - (sigma_F^2 / 2 + sigma_R^2) / ||mu_F||^2; paired (same seeds): raw = bias = "
                "sqrt(mean_i ||R_i - F_i||^2 / ||mu_F||^2)."
            ),
        )
        if load_average() is not None and info["load_average_end"] > 0.25 * cpus:
            log(f"\n  WARNING: 1-minute load average at the end {info['load_average_end']:.2f} on {cpus} CPUs: other work ran alongside; timings are noisy")
        written = write_outputs(bench, meta, out_dir, log)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    log("\n" + summary_text(bench))
    for note in bench.skipped:
        log(f"skipped: {note}")
    log(f"\n{elapsed:.1f} s; wrote {shown_paths(written)}")
    return 0 if (bench.convergence_rows or bench.choice_rows) and not any("failed" in s for s in bench.skipped) else 1


if __name__ == "__main__":
    sys.exit(main())
