"""Polynomial path systems: sensor-position error against throughput, next to the exact tracer.

Run:  python benchmarks/bench_polynomial.py [--quick] [--lenses NAME ...] [--degrees D ...] [--out DIR]

What is measured, per lens (Zeiss Biotar, Nikon 28-70 zoom at its wide position, Nikkor 180 mm
telephoto; add ``--lenses ... minolta_fisheye`` for the wide-angle stress case, about 5 more
minutes; ``--quick``: Biotar only, degrees 1, 3, 5, 2^12 error rays, 2^13-ray batches, 3 timed
calls, no zoom build) on the primary path and the 3 strongest ghost paths (``rank_ghost_paths``:
on-axis Fresnel factor), for each construction (``"fit"``, the label the results keep for
``construction="least-squares"``, and ``"taylor"``) and degree (1 to 7; ``"fit"`` also degree 9
on the Biotar's primary path, to see where the primary path gets under half a pixel; ``--degrees``
replaces all of these):

- **Build**: ``jaxflare.path_system(lens, path, degree=, construction=, cache=False)`` with the
  default validation; its wall time and ``system.report`` are recorded.
- **Error** on fresh rays, independent of the build's fit and validation samples: 2^15 rays
  crossing the system's entrance plane uniformly over the front clear aperture, directions uniform
  over the disk of direction sines up to the domain's largest field angle (the lens's half field of
  view), wavelengths uniform in 400-700 nm. The exact float64 trace (``jaxflare.trace`` of the lens
  widened to float64) is compared with the polynomial evaluated in float64 (``system.polynomial``
  of the system cast to float64, coefficients as built). "Raw" errors use a copy of the system with
  ``estimate_limit_mm = inf`` and an all-True ``trust_table`` (the polynomial answers every ray)
  and are taken over the rays valid in both: median, 99th percentile and maximum of the
  sensor-plane distance in micrometres and in pixels at 2K on a 36 mm sensor
  (1 px = 36000 / 2048 um = 17.58 um). Also: the trusted fraction and the error over rays the
  normal system trusts and answers valid, the coverage (exact-valid rays the trusted polynomial
  answers valid), the validity-mask agreement of the raw polynomial, and the p99 error of the raw
  polynomial evaluated in float32 (the render precision).
- **Throughput** in float32 (``jax.enable_x64(False)``, the system's and lens's arrays cast to
  float32): a batch of 2^16 rays (the error rays are its first 2^15), one untimed warm-up call
  (compilation), then the median of 5 timed calls each ending in ``block_until_ready`` of
  ``system.polynomial`` (no exact fallback) and of ``jaxflare.trace(lens, ..., path)`` (the exact
  point), in the same process on the same rays. The exact tracer is timed before and after each
  lens's polynomials and the median of all those calls is used. Rays/s = rays / median seconds;
  pooled path kinds (ghosts, all) use total rays / total time.
- **Boundary map**: for degrees 5 and 7 the error rays are binned by field angle (10 bins up to
  the domain's largest) and each bin gets the raw p99 error, the trusted fraction and the coverage,
  per construction and path kind (primary, ghosts).
- **Zoom, every ghost path**: the time of ``jaxflare.path_systems(zoom, paths, degree=5,
  cache=False)`` for all 351 ghost paths, per construction. A dry estimate (4 random paths) decides:
  above ``--zoom-budget`` seconds (default 360) a random sample of 40 paths is timed and the total
  extrapolated (stated as such in the output).

Summary: per lens, construction and path kind (primary, ghosts), the smallest degree whose raw p99
error over valid rays is below 0.5 px at 2K, and the speed-up over the exact tracer there.

Outputs (atomic writes) under ``benchmarks/results/``: ``polynomial_accuracy.{csv,json,png}`` and
``polynomial_field_map.{csv,png}`` (``*_quick.*`` with ``--quick`` unless ``--stem`` says otherwise).
"""

from __future__ import annotations

import math
import random
import statistics
import sys
import time
import traceback
import warnings
from pathlib import Path

import numpy as np

from _harness import (
    Outputs,
    add_out_option,
    add_stem_option,
    announce,
    blocked,
    cpu_label,
    log,
    make_parser,
    pyplot,
    run_meta,
    shown_paths,
    timed,
)

STEM = "polynomial_accuracy"
MAP_STEM = "polynomial_field_map"
SENSOR_WIDTH_UM = 36000.0
PIXELS_2K = 2048
PX_UM = SENSOR_WIDTH_UM / PIXELS_2K
HALF_PIXEL = 0.5
WAVELENGTH_RANGE_NM = (400.0, 700.0)
ZOOM = "nikon_afs_28_70_zoom"
CONSTRUCTIONS = {"fit": "least-squares", "taylor": "taylor"}
"""The benchmark's construction labels (in its CSV and JSON) -> ``path_system(construction=)``:
``"fit"`` is the former name of ``"least-squares"``."""

LENSES = {
    "zeiss_biotar": "Biotar 100/1.4",
    "nikon_afs_28_70_zoom": "Nikon 28-70 (wide)",
    "nikkor_180mm_f28_telephoto": "Nikkor 180/2.8",
    "minolta_fisheye": "Minolta fisheye",
}

FULL = {
    "lenses": ["zeiss_biotar", "nikon_afs_28_70_zoom", "nikkor_180mm_f28_telephoto"],
    "degrees": [1, 2, 3, 4, 5, 6, 7], "extra_fit_degrees": {"zeiss_biotar": [9]}, "constructions": ["fit", "taylor"], "ghosts": 3,
    "error_rays": 2**15, "timing_rays": 2**16, "repeats": 5, "map_degrees": [5, 7], "field_bins": 10,
    "zoom_build": True, "zoom_degree": 5, "zoom_dry": 4, "zoom_sample": 40, "zoom_budget_s": 360.0, "seed": 2024,
}
QUICK = dict(FULL, lenses=["zeiss_biotar"], degrees=[1, 3, 5], extra_fit_degrees={}, error_rays=2**12, timing_rays=2**13,
             repeats=3, map_degrees=[5], zoom_build=False)

CSV_FIELDS = [
    "lens", "lens_label", "zoom_position", "num_interfaces", "path_kind", "paths", "num_paths", "tool", "construction",
    "degree", "num_terms", "build_s", "error_rays", "valid_both", "err_um_median", "err_um_p99", "err_um_max",
    "err_px_median", "err_px_p99", "err_px_max", "err_f32_um_p99", "mask_agreement", "trusted_fraction", "coverage",
    "trusted_err_um_p99", "trusted_err_um_max", "trusted_err_px_p99", "report_err_um_p99_max", "timing_rays",
    "median_s", "rays_per_s", "speedup_vs_exact", "machine",
]
MAP_FIELDS = [
    "lens", "path_kind", "construction", "degree", "bin", "field_deg_low", "field_deg_high", "rays", "exact_valid",
    "valid_both", "err_um_p99", "err_px_p99", "err_um_median", "trusted_fraction", "coverage",
]


# --------------------------------------------------------------------------- helpers


def cast_floats(tree, dtype):
    """``tree`` with every floating-point array cast to ``dtype`` (call inside the matching x64 mode)."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    return jax.tree.map(lambda x: jnp.asarray(x, dtype) if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) else x, tree)


def stats_um(values: np.ndarray) -> tuple[float, float, float]:
    """(median, p99, max) of ``values``; NaN when empty."""
    if values.size == 0:
        return float("nan"), float("nan"), float("nan")
    return float(np.median(values)), float(np.percentile(values, 99)), float(values.max())


def path_label(path) -> str:
    return "primary" if path is None else f"({path[0]},{path[1]})"


def make_rays(domain, lens, count: int, seed: int):
    """Float64 rays from 4 mm before the entrance plane, crossing it uniformly over the front clear
    aperture, direction sines uniform over the disk up to the domain's largest field angle,
    wavelengths uniform in ``WAVELENGTH_RANGE_NM``. Also returns each ray's field angle (deg)."""
    rng = np.random.default_rng(seed)
    radius = float(lens.semi_aperture_mm[0])
    r, phi = radius * np.sqrt(rng.random(count)), 2 * np.pi * rng.random(count)
    sin_field = domain.sin_max_field * np.sqrt(rng.random(count))
    psi = 2 * np.pi * rng.random(count)
    directions = np.stack([sin_field * np.cos(psi), sin_field * np.sin(psi), np.sqrt(1 - sin_field**2)], -1)
    back = 4.0 / directions[:, 2]
    origins = np.stack([r * np.cos(phi), r * np.sin(phi), np.full(count, domain.entrance_z_mm)], -1) - back[:, None] * directions
    wavelength = rng.uniform(*WAVELENGTH_RANGE_NM, count)
    return origins, directions, wavelength, np.degrees(np.arcsin(sin_field))


# --------------------------------------------------------------------------- one lens


class LensBench:
    """The fresh rays, exact references and timings of one lens, and the measurements of each system."""

    def __init__(self, name: str, cfg: dict, log):
        import jax
        import jax.numpy as jnp

        import jaxflare
        from jaxflare import make_domain, rank_ghost_paths

        self.cfg, self.log, self.name = cfg, log, name
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            lens = jaxflare.load_lens(name)
        if lens.num_zoom_positions > 1:
            lens = lens.at_zoom(0)
        self.lens = cast_floats(lens, jnp.float32)
        self.label = LENSES.get(name, name)
        self.domain = make_domain(self.lens)
        ranked = rank_ghost_paths(self.lens)
        self.paths = [None] + [p for p, _ in ranked[: cfg["ghosts"]]]
        self.info = {
            "lens": name, "label": self.label, "name": lens.name, "zoom_position": lens.zoom_position,
            "num_surfaces": lens.num_surfaces, "num_interfaces": lens.num_interfaces,
            "num_ghost_paths": len(jaxflare.ghost_paths(lens)), "efl_mm": float(lens.focal_length()),
            "domain": {k: getattr(self.domain, k) for k in ("max_field_angle_deg", "entrance_z_mm", "entrance_radius_mm")},
            "paths": [path_label(p) for p in self.paths],
            "ghost_fresnel_factor": {path_label(p): f for p, f in ranked[: cfg["ghosts"]]},
        }
        origins, directions, wavelength, field = make_rays(self.domain, self.lens, cfg["timing_rays"], cfg["seed"])
        n = cfg["error_rays"]
        self.field_deg = field[:n]
        with jax.enable_x64(True):
            self.lens64 = cast_floats(self.lens, jnp.float64)
            self.rays64 = tuple(jnp.asarray(a[:n], jnp.float64) for a in (origins, directions, wavelength))
            self.exact64 = {}
            for p in self.paths:
                result = jaxflare.trace(self.lens64, *self.rays64, p)
                self.exact64[p] = (np.asarray(result.positions)[:, :2], np.asarray(result.valid))
        with jax.enable_x64(False):
            self.rays32 = tuple(jnp.asarray(a, jnp.float32) for a in (origins, directions, wavelength))
        self.exact_times = {p: [] for p in self.paths}
        self.exact_f32_err = {}
        self.time_exact()
        self.log(f"\n== {self.label}: '{lens.name}' (zoom position {lens.zoom_position}) | {lens.num_interfaces} interfaces, "
                 f"{self.info['num_ghost_paths']} ghost paths | field up to {self.domain.max_field_angle_deg:.1f} deg | paths "
                 f"{', '.join(self.info['paths'])}")
        for p in self.paths:
            self.log(f"  exact {path_label(p):9s} float32: {len(self.rays32[0]) / statistics.median(self.exact_times[p]) / 1e6:7.3f} "
                     f"Mrays/s, exact-valid {self.exact64[p][1].mean():.3f}, float32 p99 error {self.exact_f32_err[p]:.3f} um")

    def time_exact(self) -> None:
        import jax

        import jaxflare

        with jax.enable_x64(False):
            for p in self.paths:
                call = blocked(lambda p=p: jaxflare.trace(self.lens, *self.rays32, p))
                result = call()  # compiles on first use
                _, times, _ = timed(call, self.cfg["repeats"])
                self.exact_times[p] += times
                if p not in self.exact_f32_err:
                    self.exact_f32_err[p] = self._f32_error(p, result)

    def _f32_error(self, p, result) -> float:
        n = self.cfg["error_rays"]
        pos, valid = self.exact64[p]
        both = valid & np.asarray(result.valid)[:n]
        err = np.linalg.norm(np.asarray(result.positions, np.float64)[:n, :2] - pos, axis=-1)[both] * 1e3
        return stats_um(err)[1]

    def exact_rays_per_s(self, p) -> float:
        return len(self.rays32[0]) / statistics.median(self.exact_times[p])

    def measure(self, construction: str, degree: int, p) -> dict:
        """Build one system, measure its errors (float64) and throughput (float32)."""
        import equinox as eqx
        import jax
        import jax.numpy as jnp

        import jaxflare

        t0 = time.perf_counter()
        system = jaxflare.path_system(self.lens, p, degree=degree, construction=CONSTRUCTIONS[construction], cache=False)
        build_s = time.perf_counter() - t0
        pos, exact_valid = self.exact64[p]
        with jax.enable_x64(True):
            sys64 = cast_floats(system, jnp.float64)
            raw64 = eqx.tree_at(lambda s: (s.trust_table, s.estimate_limit_mm), sys64,
                                (jnp.ones_like(sys64.trust_table), jnp.asarray(jnp.inf, jnp.float64)))
            raw = raw64.polynomial(*self.rays64)
            raw_pos, raw_valid = np.asarray(raw.positions)[:, :2], np.asarray(raw.valid)
            normal = sys64.polynomial(*self.rays64)
            trusted, trusted_valid = np.asarray(normal.trusted), np.asarray(normal.valid)
        err = np.linalg.norm(raw_pos - pos, axis=-1) * 1e3
        both = raw_valid & exact_valid
        answered = trusted_valid & exact_valid
        with jax.enable_x64(False):
            sys32 = cast_floats(system, jnp.float32)
            call = blocked(lambda: sys32.polynomial(*self.rays32))
            call()  # compiles on first use of this structure
            median_s, _, _ = timed(call, self.cfg["repeats"])
            raw32 = eqx.tree_at(lambda s: (s.trust_table, s.estimate_limit_mm), sys32,
                                (jnp.ones_like(sys32.trust_table), jnp.asarray(jnp.inf, jnp.float32)))
            r32 = raw32.polynomial(*self.rays32)  # same compiled function: trust table and limit are data
        n = self.cfg["error_rays"]
        both32 = np.asarray(r32.valid)[:n] & exact_valid
        err32 = np.linalg.norm(np.asarray(r32.positions, np.float64)[:n, :2] - pos, axis=-1)[both32] * 1e3
        return {
            "path": p, "construction": construction, "degree": degree, "num_terms": system.num_terms, "build_s": build_s,
            "report": system.report.as_dict(), "err": err, "both": both, "exact_valid": exact_valid, "raw_valid": raw_valid,
            "trusted": trusted, "answered": answered, "err_f32_p99": stats_um(err32)[1], "median_s": median_s,
            "timing_rays": len(self.rays32[0]),
        }


def pooled_row(bench: LensBench, kind: str, measures: list[dict], machine: str) -> dict:
    """One CSV row pooling the measurements of several paths (same construction and degree)."""
    err = np.concatenate([m["err"][m["both"]] for m in measures])
    trusted_err = np.concatenate([m["err"][m["answered"]] for m in measures])
    exact_valid = np.concatenate([m["exact_valid"] for m in measures])
    med, p99, mx = stats_um(err)
    _, t99, tmax = stats_um(trusted_err)
    rays = sum(m["timing_rays"] for m in measures)
    seconds = sum(m["median_s"] for m in measures)
    exact_seconds = sum(m["timing_rays"] / bench.exact_rays_per_s(m["path"]) for m in measures)
    return {
        "lens": bench.name, "lens_label": bench.label, "zoom_position": bench.info["zoom_position"],
        "num_interfaces": bench.info["num_interfaces"], "path_kind": kind,
        "paths": " ".join(path_label(m["path"]) for m in measures), "num_paths": len(measures), "tool": "polynomial",
        "construction": measures[0]["construction"], "degree": measures[0]["degree"], "num_terms": measures[0]["num_terms"],
        "build_s": sum(m["build_s"] for m in measures), "error_rays": sum(len(m["err"]) for m in measures),
        "valid_both": int(err.size), "err_um_median": med, "err_um_p99": p99, "err_um_max": mx,
        "err_px_median": med / PX_UM, "err_px_p99": p99 / PX_UM, "err_px_max": mx / PX_UM,
        "err_f32_um_p99": max(m["err_f32_p99"] for m in measures),
        "mask_agreement": float(np.mean(np.concatenate([m["raw_valid"] == m["exact_valid"] for m in measures]))),
        "trusted_fraction": float(np.mean(np.concatenate([m["trusted"] for m in measures]))),
        "coverage": float(np.sum([m["answered"].sum() for m in measures]) / max(1, exact_valid.sum())),
        "trusted_err_um_p99": t99, "trusted_err_um_max": tmax, "trusted_err_px_p99": t99 / PX_UM,
        "report_err_um_p99_max": max(m["report"]["error_um_p99"] for m in measures),
        "timing_rays": rays, "median_s": seconds, "rays_per_s": rays / seconds, "speedup_vs_exact": exact_seconds / seconds,
        "machine": machine,
    }


def exact_row(bench: LensBench, kind: str, paths: list, machine: str) -> dict:
    rays = len(bench.rays32[0]) * len(paths)
    seconds = sum(len(bench.rays32[0]) / bench.exact_rays_per_s(p) for p in paths)
    valid = np.concatenate([bench.exact64[p][1] for p in paths])
    return {
        "lens": bench.name, "lens_label": bench.label, "zoom_position": bench.info["zoom_position"],
        "num_interfaces": bench.info["num_interfaces"], "path_kind": kind, "paths": " ".join(path_label(p) for p in paths),
        "num_paths": len(paths), "tool": "exact", "construction": "exact", "degree": None, "build_s": 0.0,
        "error_rays": valid.size, "valid_both": int(valid.sum()), "err_um_median": 0.0, "err_um_p99": 0.0, "err_um_max": 0.0,
        "err_px_median": 0.0, "err_px_p99": 0.0, "err_px_max": 0.0,
        "err_f32_um_p99": max(bench.exact_f32_err[p] for p in paths), "mask_agreement": 1.0, "trusted_fraction": 1.0,
        "coverage": 1.0, "timing_rays": rays, "median_s": seconds, "rays_per_s": rays / seconds, "speedup_vs_exact": 1.0,
        "machine": machine,
    }


def field_map_rows(bench: LensBench, kind: str, measures: list[dict]) -> list[dict]:
    cfg = bench.cfg
    edges = np.linspace(0.0, bench.domain.max_field_angle_deg, cfg["field_bins"] + 1)
    which = np.clip(np.searchsorted(edges, bench.field_deg, side="right") - 1, 0, cfg["field_bins"] - 1)
    rows = []
    for b in range(cfg["field_bins"]):
        sel = which == b
        err = np.concatenate([m["err"][sel & m["both"]] for m in measures])
        exact_valid = sum(int((m["exact_valid"] & sel).sum()) for m in measures)
        med, p99, _ = stats_um(err)
        rows.append({
            "lens": bench.name, "path_kind": kind, "construction": measures[0]["construction"], "degree": measures[0]["degree"],
            "bin": b, "field_deg_low": edges[b], "field_deg_high": edges[b + 1], "rays": int(sel.sum()) * len(measures),
            "exact_valid": exact_valid, "valid_both": int(err.size), "err_um_p99": p99, "err_px_p99": p99 / PX_UM,
            "err_um_median": med,
            "trusted_fraction": float(np.mean(np.concatenate([m["trusted"][sel] for m in measures]))) if sel.any() else float("nan"),
            "coverage": sum(int((m["answered"] & sel).sum()) for m in measures) / exact_valid if exact_valid else float("nan"),
        })
    return rows


def bench_lens(name: str, cfg: dict, machine: str, log) -> tuple[list[dict], list[dict], dict]:
    started = time.perf_counter()
    bench = LensBench(name, cfg, log)
    rows, map_rows, per_path = [], [], []
    degrees_by_construction = {
        c: sorted(set(cfg["degrees"]) | set(cfg["extra_fit_degrees"].get(name, []) if c == "fit" else set()))
        for c in cfg["constructions"]
    }
    measured: dict = {}
    extra = set(cfg["extra_fit_degrees"].get(name, [])) - set(cfg["degrees"])
    for construction, degrees in degrees_by_construction.items():
        for degree in degrees:
            t0 = time.perf_counter()
            ms = []
            # an extra (fit-only) degree is measured on the primary path only: it is there to find
            # where the primary path gets under half a pixel; the ghosts are far from it
            for p in bench.paths[:1] if degree in extra else bench.paths:
                m = bench.measure(construction, degree, p)
                ms.append(m)
                r = m["report"]
                per_path.append({
                    "lens": name, "path": path_label(p), "construction": construction, "degree": degree, "build_s": m["build_s"],
                    "num_terms": m["num_terms"], "valid_both": int(m["both"].sum()),
                    "err_um": dict(zip(("median", "p99", "max"), stats_um(m["err"][m["both"]]))),
                    "trusted_fraction": float(m["trusted"].mean()), "rays_per_s": m["timing_rays"] / m["median_s"],
                    "speedup_vs_exact": bench.exact_rays_per_s(p) and m["timing_rays"] / m["median_s"] / bench.exact_rays_per_s(p),
                    "report": {k: r[k] for k in ("error_um_median", "error_um_p99", "error_um_max", "trusted_fraction",
                                                 "mask_mismatch", "build_seconds", "estimate_limit_um", "clip_surfaces")},
                })
            measured[(construction, degree)] = ms
            kinds = [("primary", ms[:1]), ("ghosts", ms[1:]), ("all", ms if len(ms) > 1 else [])]
            pooled = {kind: pooled_row(bench, kind, sel, machine) for kind, sel in kinds if sel}
            rows += pooled.values()
            prim, ghosts = pooled["primary"], pooled.get("ghosts")
            log(f"  {construction:6s} deg {degree}: primary p99 {prim['err_px_p99']:8.3f} px (median {prim['err_px_median']:.3f}, "
                f"trusted {prim['trusted_fraction']:.2f}) {prim['rays_per_s'] / 1e6:7.2f} Mrays/s x{prim['speedup_vs_exact']:.1f}"
                + (f" | ghosts p99 {ghosts['err_px_p99']:9.3f} px, trusted {ghosts['trusted_fraction']:.2f}, "
                   f"x{ghosts['speedup_vs_exact']:.1f}" if ghosts else "")
                + f" | build {sum(m['build_s'] for m in ms):.1f} s ({time.perf_counter() - t0:.1f} s total)")
            if degree in cfg["map_degrees"]:
                for kind, sel in kinds[:2]:
                    if sel:
                        map_rows += field_map_rows(bench, kind, sel)
    bench.time_exact()  # the exact tracer again after the polynomials: the median covers both
    for kind, sel in (("primary", bench.paths[:1]), ("ghosts", bench.paths[1:]), ("all", bench.paths)):
        if sel:
            rows.append(exact_row(bench, kind, sel, machine))
    bench.info["exact_rays_per_s"] = {path_label(p): bench.exact_rays_per_s(p) for p in bench.paths}
    bench.info["exact_f32_err_um_p99"] = {path_label(p): bench.exact_f32_err[p] for p in bench.paths}
    bench.info["per_path"] = per_path
    bench.info["build_s_total"] = sum(e["build_s"] for e in per_path)
    bench.info["elapsed_s"] = time.perf_counter() - started
    log(f"  {bench.label}: {bench.info['elapsed_s']:.0f} s ({bench.info['build_s_total']:.0f} s building systems)")
    return rows, map_rows, bench.info


# --------------------------------------------------------------------------- summary


def summarise(rows: list[dict], cfg: dict) -> list[dict]:
    out = []
    for lens in dict.fromkeys(r["lens"] for r in rows):
        for construction in cfg["constructions"]:
            for kind in ("primary", "ghosts"):
                cand = sorted((r for r in rows if r["lens"] == lens and r["construction"] == construction and r["path_kind"] == kind),
                              key=lambda r: r["degree"])
                if not cand:
                    continue
                hit = next((r for r in cand if r["valid_both"] > 0 and r["err_px_p99"] < HALF_PIXEL), None)
                finite = [r for r in cand if r["valid_both"] > 0 and math.isfinite(r["err_px_p99"])]
                best = min(finite, key=lambda r: r["err_px_p99"]) if finite else None
                out.append({
                    "lens": lens, "construction": construction, "path_kind": kind,
                    "smallest_degree_under_half_px": hit["degree"] if hit else None,
                    "verdict": f"degree {hit['degree']}" if hit else f"none up to {cand[-1]['degree']}",
                    "p99_px_there": hit["err_px_p99"] if hit else None,
                    "speedup_vs_exact_there": hit["speedup_vs_exact"] if hit else None,
                    "rays_per_s_there": hit["rays_per_s"] if hit else None,
                    "trusted_fraction_there": hit["trusted_fraction"] if hit else None,
                    "best_p99_px": best["err_px_p99"] if best else None, "best_degree": best["degree"] if best else None,
                    "best_trusted_fraction": max(r["trusted_fraction"] for r in cand),
                })
    return out


def summary_text(summary: list[dict], labels: dict) -> str:
    header = (f"{'lens':22s} {'construction':12s} {'paths':8s} {'smallest degree p99<0.5px':>26s} {'speed-up':>9s} "
              f"{'best p99 px (deg)':>18s} {'max trusted':>11s}")
    lines = [header, "-" * len(header)]
    for s in summary:
        speed = f"{s['speedup_vs_exact_there']:8.1f}x" if s["speedup_vs_exact_there"] else f"{'-':>9s}"
        best = f"{s['best_p99_px']:.3g} ({s['best_degree']})" if s["best_p99_px"] is not None else "-"
        lines.append(f"{labels.get(s['lens'], s['lens']):22s} {s['construction']:12s} {s['path_kind']:8s} {s['verdict']:>26s} "
                     f"{speed} {best:>18s} {s['best_trusted_fraction']:11.3f}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- zoom: every ghost path


def zoom_build_times(cfg: dict, log) -> dict:
    import jax.numpy as jnp

    import jaxflare

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        zoom = jaxflare.load_lens(ZOOM)
    zoom = cast_floats(zoom.at_zoom(0), jnp.float32)
    paths = jaxflare.ghost_paths(zoom)
    rng = random.Random(cfg["seed"])
    out = {"lens": ZOOM, "zoom_position": 0, "num_interfaces": zoom.num_interfaces, "num_ghost_paths": len(paths),
           "degree": cfg["zoom_degree"], "budget_s": cfg["zoom_budget_s"], "constructions": {}}
    log(f"\n== every ghost path of the zoom: {len(paths)} paths, degree {cfg['zoom_degree']}, cache=False")
    for construction in cfg["constructions"]:
        options = {"degree": cfg["zoom_degree"], "construction": CONSTRUCTIONS[construction], "cache": False}
        dry = rng.sample(paths, min(cfg["zoom_dry"], len(paths)))
        dry_times = []
        for p in dry:
            t0 = time.perf_counter()
            jaxflare.path_system(zoom, p, **options)
            dry_times.append(time.perf_counter() - t0)
        estimate = statistics.median(dry_times) * len(paths)
        entry = {"dry_paths": [list(p) for p in dry], "dry_seconds": dry_times, "dry_estimate_all_s": estimate}
        if estimate <= cfg["zoom_budget_s"]:
            chosen, entry["mode"] = None, "all paths timed"
        else:
            chosen = rng.sample(paths, min(cfg["zoom_sample"], len(paths)))
            entry["mode"] = f"random sample of {len(chosen)} paths timed, total extrapolated to {len(paths)}"
        built_paths = paths if chosen is None else chosen
        t0 = time.perf_counter()
        systems = jaxflare.path_systems(zoom, chosen, **options)
        seconds = time.perf_counter() - t0
        per_path = [s.report.build_seconds for s in systems.values()]
        entry.update(
            paths_built=len(systems), seconds=seconds, per_path_mean_s=seconds / len(systems),
            per_path_report_median_s=statistics.median(per_path), per_path_report_max_s=max(per_path),
            all_paths_s=seconds if chosen is None else seconds / len(systems) * len(paths),
            extrapolated=chosen is not None,
            sample_paths=None if chosen is None else [list(p) for p in built_paths],
            trusted_fraction_median=statistics.median(s.report.trusted_fraction for s in systems.values()),
        )
        out["constructions"][construction] = entry
        log(f"  {construction:6s}: dry estimate {estimate:.0f} s from {len(dry)} paths -> {entry['mode']}: "
            f"{len(systems)} systems in {seconds:.1f} s ({entry['per_path_mean_s']:.2f} s/path) -> all {len(paths)} paths "
            f"{'~' if chosen is not None else ''}{entry['all_paths_s']:.0f} s ({entry['all_paths_s'] / 60:.1f} min)"
            f"{' (EXTRAPOLATED)' if chosen is not None else ''}")
    return out


# --------------------------------------------------------------------------- outputs


STYLE = {
    ("fit", "primary"): {"color": "C0", "marker": "o", "ls": "-"},
    ("fit", "ghosts"): {"color": "C0", "marker": "s", "ls": "--", "mfc": "none"},
    ("taylor", "primary"): {"color": "C1", "marker": "^", "ls": "-"},
    ("taylor", "ghosts"): {"color": "C1", "marker": "v", "ls": "--", "mfc": "none"},
}


def _accuracy_chart(rows: list[dict], meta: dict):
    plt = pyplot()
    import matplotlib.ticker

    lenses = [info["lens"] for info in meta["lenses"]]
    labels = {info["lens"]: info["label"] for info in meta["lenses"]}
    width = max(5.0 * len(lenses), 9.0)
    fig, axes = plt.subplots(1, max(len(lenses), 1), figsize=(width, 5.8), squeeze=False)
    positive = [r["err_px_p99"] for r in rows if r["tool"] == "polynomial" and r["err_px_p99"] and r["err_px_p99"] > 0
                and math.isfinite(r["err_px_p99"])]
    floor = 10 ** math.floor(math.log10(min(positive + [HALF_PIXEL]) / 3))
    handles: dict = {}
    for ax, lens in zip(axes[0], lenses):
        for (construction, kind), style in STYLE.items():
            sel = sorted((r for r in rows if r["lens"] == lens and r["tool"] == "polynomial" and r["construction"] == construction
                          and r["path_kind"] == kind and r["valid_both"] > 0 and math.isfinite(r["err_px_p99"])),
                         key=lambda r: r["degree"])
            if not sel:
                continue
            label = f"{construction} ({'primary' if kind == 'primary' else 'strongest ghosts'})"
            xs = [r["rays_per_s"] / 1e6 for r in sel]
            ys = [max(r["err_px_p99"], floor) for r in sel]
            (line,) = ax.plot(xs, ys, label=label, **style)
            handles.setdefault(label, line)
            for x, y, r in zip(xs, ys, sel):
                ax.annotate(str(r["degree"]), (x, y), textcoords="offset points", xytext=(4, 3), fontsize=7, color=style["color"])
        for kind, marker_colour in (("primary", "k"), ("ghosts", "0.45")):
            ex = [r for r in rows if r["lens"] == lens and r["tool"] == "exact" and r["path_kind"] == kind]
            if ex:
                label = f"exact tracer ({'primary' if kind == 'primary' else 'ghosts'}; error 0, drawn at the floor)"
                (star,) = ax.plot([ex[0]["rays_per_s"] / 1e6], [floor], marker="*", ms=15, ls="none", color=marker_colour,
                                  label=label, clip_on=False, zorder=5)
                handles.setdefault(label, star)
                ax.annotate(f"exact {kind}", (ex[0]["rays_per_s"] / 1e6, floor), textcoords="offset points", xytext=(6, 6),
                            fontsize=7, color=marker_colour)
        line = ax.axhline(HALF_PIXEL, color="C3", lw=1, ls=":")
        handles.setdefault("0.5 px at 2K (36 mm sensor)", line)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylim(bottom=floor)
        ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("throughput, float32 [Mrays/s]")
        ax.set_title(labels.get(lens, lens), fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("p99 sensor-position error over valid rays [px at 2K]")
    m = meta["machine"]
    fig.suptitle("Polynomial path systems: p99 error vs throughput (numbers: degree); "
                 f"{meta['config']['error_rays']} fresh rays/path, batch {meta['config']['timing_rays']}\n"
                 f"{cpu_label(m)}, jax {m.get('jax')}", fontsize=9)
    fig.legend(list(handles.values()), list(handles.keys()), loc="lower center", ncol=3 if width > 9 else 2, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.16 if width <= 9 else 0.12, 1, 1))
    return fig


def _field_map_chart(map_rows: list[dict], meta: dict):
    plt = pyplot()

    lenses = [info["lens"] for info in meta["lenses"]]
    labels = {info["lens"]: info["label"] for info in meta["lenses"]}
    fig, axes = plt.subplots(2, max(len(lenses), 1), figsize=(max(5.0 * len(lenses), 8.0), 8.0), squeeze=False, sharex="col")
    colours = {("fit", 5): "C0", ("fit", 7): "C2", ("taylor", 5): "C1", ("taylor", 7): "C3"}
    handles: dict = {}
    for col, lens in enumerate(lenses):
        for key in dict.fromkeys((r["construction"], r["degree"], r["path_kind"]) for r in map_rows if r["lens"] == lens):
            construction, degree, kind = key
            sel = sorted((r for r in map_rows if r["lens"] == lens and (r["construction"], r["degree"], r["path_kind"]) == key),
                         key=lambda r: r["bin"])
            x = [0.5 * (r["field_deg_low"] + r["field_deg_high"]) for r in sel]
            style = {"color": colours.get((construction, degree), "C4"), "ls": "-" if kind == "primary" else "--",
                         "marker": "o" if kind == "primary" else "s", "ms": 3}
            label = f"{construction} deg {degree} {kind}"
            (line,) = axes[0][col].plot(x, [r["err_px_p99"] for r in sel], label=label, **style)
            axes[1][col].plot(x, [r["trusted_fraction"] for r in sel], **style)
            handles.setdefault(label, line)
        axes[0][col].axhline(HALF_PIXEL, color="k", lw=1, ls=":")
        axes[0][col].set_yscale("log")
        axes[0][col].set_title(labels.get(lens, lens), fontsize=10)
        axes[1][col].set_ylim(-0.02, 1.02)
        axes[1][col].set_xlabel("field angle [deg]")
        for ax in axes[:, col]:
            ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("raw p99 error [px at 2K]")
    axes[1][0].set_ylabel("trusted fraction of the rays")
    fig.suptitle("Where the polynomials hold: raw p99 error (over rays valid in both) and trusted fraction against "
                 "field angle\n(dotted: 0.5 px at 2K; coverage of exact-valid rays is in the CSV)", fontsize=10)
    fig.legend(list(handles.values()), list(handles.keys()), loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    return fig


def write_outputs(rows, map_rows, meta, out_dir: Path, stem: str, map_stem: str, log) -> list[Path]:
    out = Outputs(out_dir, log)
    out.csv(f"{stem}.csv", rows, CSV_FIELDS, float_format=".6g")
    out.csv(f"{map_stem}.csv", map_rows, MAP_FIELDS, float_format=".6g")
    out.json(f"{stem}.json", dict(meta, rows=rows, field_map=map_rows))
    out.chart(f"{stem}.png", _accuracy_chart, rows, meta)
    out.chart(f"{map_stem}.png", _field_map_chart, map_rows, meta)
    return out.written


# --------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    parser = make_parser(__doc__, "smoke test: Biotar only, degrees 1 3 5, fewer rays, no zoom build")
    parser.add_argument("--lenses", nargs="+", help=f"lens file stems (default: {' '.join(FULL['lenses'])})")
    parser.add_argument("--degrees", nargs="+", type=int, help="degrees for both constructions (default 1..7; replaces the extra fit degree 9)")
    parser.add_argument("--constructions", nargs="+", choices=list(CONSTRUCTIONS))
    parser.add_argument("--repeats", type=int, help="timed calls per measurement (median)")
    parser.add_argument("--zoom-sample", type=int, help="paths timed when building every zoom path is too long")
    parser.add_argument("--zoom-budget", type=float, help="seconds: above this dry estimate the zoom build is sampled")
    parser.add_argument("--no-zoom-build", action="store_true", help="skip timing the build of every zoom ghost path")
    add_out_option(parser, quick_folder=False)
    add_stem_option(parser, "output file stem (default polynomial_accuracy[_quick]; the field map adds _field_map)")
    args = parser.parse_args(argv)

    cfg = dict(FULL if not args.quick else QUICK)
    overrides = {"lenses": args.lenses, "constructions": args.constructions, "repeats": args.repeats,
                 "zoom_sample": args.zoom_sample, "zoom_budget_s": args.zoom_budget}
    cfg.update({key: value for key, value in overrides.items() if value is not None})
    if args.degrees:  # replaces the extra fit degrees too
        cfg["degrees"], cfg["extra_fit_degrees"] = sorted(set(args.degrees)), {}
    cfg["zoom_build"] = cfg["zoom_build"] and not args.no_zoom_build
    suffix = "_quick" if args.quick else ""
    stem = args.stem or STEM + suffix
    map_stem = f"{args.stem}_field_map" if args.stem else MAP_STEM + suffix

    started = time.perf_counter()
    import jax

    import jaxflare

    info, machine = announce("bench_polynomial", args.quick, log)
    log(f"  lenses {cfg['lenses']}, degrees {cfg['degrees']} (+fit {cfg['extra_fit_degrees']}), {cfg['error_rays']} error rays "
        f"and {cfg['timing_rays']}-ray batches per path, {cfg['repeats']} timed calls (median)")

    available = set(jaxflare.bundled_lens_names())
    rows, map_rows, lens_infos, skipped = [], [], [], []
    for name in cfg["lenses"]:
        if name not in available:
            skipped.append(f"lens '{name}' is not bundled; skipped")
            log(f"\nnote: {skipped[-1]}")
            continue
        try:
            lens_rows, lens_map, lens_info = bench_lens(name, cfg, machine, log)
        except Exception as error:
            skipped.append(f"lens '{name}' failed: {type(error).__name__}: {error}")
            log(f"\nnote: {skipped[-1]}")
            traceback.print_exc()
            continue
        rows += lens_rows
        map_rows += lens_map
        lens_infos.append(lens_info)

    zoom = None
    if cfg["zoom_build"]:
        try:
            zoom = zoom_build_times(cfg, log)
        except Exception as error:
            skipped.append(f"zoom build timing failed: {type(error).__name__}: {error}")
            log(f"\nnote: {skipped[-1]}")
            traceback.print_exc()
    summary = summarise(rows, cfg)
    elapsed = time.perf_counter() - started
    meta = run_meta(
        "polynomial_accuracy", args.quick, cfg, info, machine, jax_x64_default=bool(jax.config.jax_enable_x64),
        pixel_um=PX_UM, half_pixel_um=HALF_PIXEL * PX_UM, wavelength_range_nm=WAVELENGTH_RANGE_NM,
        summary=summary, zoom_build=zoom if zoom else "skipped", lenses=lens_infos, skipped=skipped,
        elapsed_s=elapsed,
        method=(
            "errors: float64 exact trace vs float64 evaluation of system.polynomial on fresh in-domain rays; raw = trust "
            "table all True and estimate limit inf, over rays valid in both; trusted = the normal system's trusted and valid "
            "rays; px = um / (36000/2048). Throughput: float32, median of `repeats` block_until_ready calls after a "
            "warm-up, same rays for system.polynomial (no exact fallback) and jaxflare.trace; pooled kinds = total rays / "
            "total time; speed-up = exact time / polynomial time on the same paths."
        ),
    )
    written = write_outputs(rows, map_rows, meta, args.out, stem, map_stem, log)
    labels = {i["lens"]: i["label"] for i in lens_infos}
    log("\nsmallest degree with p99 error over valid rays < 0.5 px at 2K (17.6 um/px), and speed-up over the exact tracer:")
    log(summary_text(summary, labels))
    if zoom:
        for c, e in zoom["constructions"].items():
            log(f"zoom ({zoom['num_ghost_paths']} ghost paths, degree {zoom['degree']}) {c}: {e['all_paths_s']:.0f} s "
                f"({e['all_paths_s'] / 60:.1f} min){' extrapolated from ' + str(e['paths_built']) + ' random paths' if e['extrapolated'] else ''}")
    log("".join(f"skipped: {note}\n" for note in skipped), end="")
    log(f"\n{elapsed:.1f} s; wrote {shown_paths(written)}")
    return 1 if not rows else 0


if __name__ == "__main__":
    sys.exit(main())
