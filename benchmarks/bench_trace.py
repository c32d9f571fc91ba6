"""Exact-trace throughput of jaxflare (rays per second), side by side with optiland.

Run:  python benchmarks/bench_trace.py [--quick] [--lenses NAME ...] [--no-optiland] [--no-former] [--out DIR]

For each bundled lens (Biotar, Angenieux double Gauss, Nikon 28-70 zoom; a missing one is skipped
with a note) and each batch size it times :func:`jaxflare.trace` on the primary path and on a sample
of ghost paths, and the total time to trace *every* ghost path of the lens. The same lens is rebuilt
in optiland (constant indices equal to jaxflare's at 587.56 nm, same radii, thicknesses and clear
apertures) and the same rays are traced through it for the primary path and one ghost path.

Timing: random rays (origins uniform over the front clear aperture at z = -5 mm, directions uniform
in tan-angle space within the lens's half field of view), one untimed warm-up call per compiled
shape (its wall time is recorded as the compile time), then the median of ``--repeats`` timed calls,
each ending in ``block_until_ready``. jaxflare runs in float32 (the default render precision);
optiland in its own default (float64, NumPy + Numba backend).

Outputs (atomic writes): ``benchmarks/results/trace_throughput.{csv,json,png}``
(``trace_throughput_quick.*`` in ``--quick`` mode unless ``--out``/``--stem`` say otherwise).
"""

from __future__ import annotations

import math
import os
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
    cpu_label,
    log,
    make_parser,
    pyplot,
    quick_stem,
    REPO,
    run_meta,
    shown_paths,
    timed,
)

STEM = "trace_throughput"
WAVELENGTH_NM = 587.56
START_Z_MM = -5.0

# (file stem, short label)
LENSES = [
    ("zeiss_biotar", "Biotar 100/1.4"),
    ("angenieux_double_gauss", "Angenieux DG 100/1.1"),
    ("nikon_afs_28_70_zoom", "Nikon 28-70 (wide)"),
]

FULL = dict(batches=[2**12, 2**14, 2**16, 2**18, 2**20], repeats=5, ghost_sample=10, ghost_repeats=5, all_ghost_rays=2**14,
            all_ghost_repeats=3, check_rays=2**14, slow_call_s=0.5, long_pass_s=30.0, lenses=[name for name, _ in LENSES])
QUICK = dict(batches=[2**10, 2**12], repeats=2, ghost_sample=3, ghost_repeats=2, all_ghost_rays=2**10, all_ghost_repeats=1,
             check_rays=1024, slow_call_s=0.5, long_pass_s=30.0, lenses=["zeiss_biotar"])

CSV_FIELDS = [
    "lens", "lens_label", "path_kind", "path", "batch_rays", "tool", "tool_version", "dtype", "median_s", "rays_per_s",
    "compile_s", "repeats", "valid_fraction", "num_paths", "num_surfaces", "machine",
]


# --------------------------------------------------------------------------- utilities


def ghost_sample(paths: list, count: int) -> list:
    """``count`` paths spread evenly over the list (deterministic)."""
    if len(paths) <= count:
        return list(paths)
    picks = np.unique(np.linspace(0, len(paths) - 1, count).round().astype(int))
    return [paths[k] for k in picks]


# --------------------------------------------------------------------------- rays


def half_field_rad(lens) -> float:
    p = lens.prescription
    return math.atan(0.5 * math.hypot(p.sensor_width_mm, p.sensor_height_mm) / abs(lens.focal_length()))


def front_sag_at_rim(lens) -> float:
    c = float(lens.curvature_per_mm[0])
    r = float(lens.semi_aperture_mm[0])
    k = float(lens.conic[0])
    arg = 1.0 - (1.0 + k) * c * c * r * r
    return c * r * r / (1.0 + math.sqrt(max(arg, 0.0)))


def make_rays(lens, count: int, seed: int, start_z: float) -> tuple[np.ndarray, np.ndarray]:
    """Float32 origins (uniform over the front clear aperture at ``start_z``) and unit directions
    (uniform over a disk in tan-angle space of radius tan(half field))."""
    rng = np.random.default_rng(seed)
    radius = float(lens.semi_aperture_mm[0])
    r = radius * np.sqrt(rng.random(count))
    phi = 2.0 * np.pi * rng.random(count)
    origins = np.stack([r * np.cos(phi), r * np.sin(phi), np.full(count, start_z)], axis=-1)
    t = math.tan(half_field_rad(lens)) * np.sqrt(rng.random(count))
    psi = 2.0 * np.pi * rng.random(count)
    directions = np.stack([t * np.cos(psi), t * np.sin(psi), np.ones(count)], axis=-1)
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    return origins.astype(np.float32), directions.astype(np.float32)


# --------------------------------------------------------------------------- jaxflare


class JaxflareBench:
    def __init__(self, lens):
        import jax

        import jaxflare

        self.jax = jax
        self.jaxflare = jaxflare
        self.lens = lens
        self.compile_s: dict = {}
        """Wall time of the first call of each compiled variant, keyed by (rays, stop passes)."""

    @staticmethod
    def compilations() -> int:
        """How often the exact-trace kernel has been traced (compiled) in this process."""
        import equinox as eqx

        from jaxflare.optics import trace_events

        return eqx.debug.get_num_traces(trace_events.__wrapped__)

    def variant(self, count: int, path) -> tuple:
        """The key of the compiled function a call uses: jaxflare compiles once per ray count and
        number of stop passes (1 for the primary path, 1 or 3 for ghosts); the path itself is data."""
        from jaxflare.optics import path_events, stop_pass_count

        return (count, stop_pass_count(path_events(self.lens, path), self.lens.stop_index))

    def put(self, origins: np.ndarray, directions: np.ndarray):
        jnp = self.jax.numpy
        return jnp.asarray(origins), jnp.asarray(directions)

    def call(self, origins, directions, path):
        result = self.jaxflare.trace(self.lens, origins, directions, WAVELENGTH_NM, path)
        return self.jax.block_until_ready(result)

    def call_former(self, origins, directions, path):
        """The same trace with the formulation jaxflare 0.1.0 shipped (tests/optics/reference_tracer.py)."""
        from jaxflare.optics import path_events, stop_pass_count

        jnp = self.jax.numpy
        events = path_events(self.lens, path)
        wavelength = jnp.full(origins.shape[0], WAVELENGTH_NM, origins.dtype)
        result = former_tracer()(self.lens, origins, directions, wavelength, jnp.asarray(events), stop_pass_count(events, self.lens.stop_index))
        return self.jax.block_until_ready(result)

    def warm(self, origins, directions, path) -> float:
        """Make sure the variant this call needs is compiled (an untimed first call if it is new);
        returns the wall time of the call that compiled it (recorded once per variant)."""
        key = self.variant(origins.shape[0], path)
        if key not in self.compile_s:
            before = self.compilations()
            t0 = time.perf_counter()
            self.call(origins, directions, path)
            elapsed = time.perf_counter() - t0
            self.compile_s[key] = elapsed if self.compilations() != before else 0.0
        return self.compile_s[key]


def former_tracer():
    """``reference_trace_events``: the exact tracer as jaxflare 0.1.0 formulated it, which the tests
    keep as the reference of today's tracer (loaded from its file, not imported as a package)."""
    import importlib.util

    global _FORMER
    if _FORMER is None:
        spec = importlib.util.spec_from_file_location("reference_tracer", REPO / "tests" / "optics" / "reference_tracer.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        _FORMER = module.reference_trace_events
    return _FORMER


_FORMER = None
FORMER = "jaxflare-0.1.0"
"""The tool name of the former formulation in the results."""


# --------------------------------------------------------------------------- optiland


class OptilandUnavailable(RuntimeError):
    pass


def import_optiland():
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import optiland
            import optiland.backend as be
            from optiland.materials import IdealMaterial
            from optiland.optic import Optic
            from optiland.rays import RealRays
    except Exception as error:  # ImportError, or a broken dependency
        raise OptilandUnavailable(f"import optiland failed: {type(error).__name__}: {error}") from None
    try:
        from importlib.metadata import version

        ver = version("optiland")
    except Exception:
        ver = getattr(optiland, "__version__", "unknown")
    if be.get_backend() != "numpy":
        be.set_backend("numpy")
    return dict(optiland=optiland, be=be, IdealMaterial=IdealMaterial, Optic=Optic, RealRays=RealRays, version=ver)


def optiland_unsupported_reason(lens) -> str | None:
    if bool(np.any(np.asarray(lens.surface_kind) != 0)):
        return "cylindrical surfaces (not mapped to optiland here)"
    if lens.has_aspheres:
        return "aspheric surfaces (not mapped to optiland here)"
    if lens.aperture_blades:
        return None  # the polygon iris is approximated by its circumcircle (noted in the output)
    return None


class OptilandBench:
    """The jaxflare lens rebuilt in optiland: object at infinity (surface 0), jaxflare surface s is
    optiland surface s + 1, the sensor is the image surface. Constant indices equal to jaxflare's
    at 587.56 nm; air is index 1 exactly (as in jaxflare)."""

    def __init__(self, lens, ol: dict):
        self.ol = ol
        self.lens = lens
        be, IdealMaterial, Optic = ol["be"], ol["IdealMaterial"], ol["Optic"]
        n = lens.refractive_indices(WAVELENGTH_NM)
        curvature = np.asarray(lens.curvature_per_mm, np.float64)
        # the float32 values jaxflare actually traces with, widened to float64
        thickness = np.asarray(lens.thickness_mm, np.float64)
        semi = np.asarray(lens.semi_aperture_mm, np.float64)
        conic = np.asarray(lens.conic, np.float64)
        stop_radius = float(lens.stop_radius_mm)
        optic = Optic()
        optic.surfaces.add(index=0, radius=be.inf, thickness=be.inf)
        for s in range(lens.num_surfaces):
            radius = be.inf if curvature[s] == 0 else 1.0 / curvature[s]
            aperture = 2.0 * (min(semi[s], stop_radius) if s == lens.stop_index else semi[s])
            optic.surfaces.add(
                index=s + 1,
                radius=radius,
                conic=float(conic[s]),
                thickness=float(thickness[s]),
                material=IdealMaterial(float(n[s + 1])),
                aperture=float(aperture),
                is_stop=(s == lens.stop_index),
            )
        optic.surfaces.add(index=lens.num_surfaces + 1)
        # object space: air with n = 1 exactly, like jaxflare (optiland's default 'air' is ideal n = 1 too)
        optic.set_aperture(aperture_type="EPD", value=2.0 * lens.entrance_pupil()[1])
        optic.fields.set_type(field_type="angle")
        optic.fields.add(y=0.0)
        optic.wavelengths.add(value=WAVELENGTH_NM * 1e-3, is_primary=True)
        self.optic = optic
        self.sequences: dict = {}

    def efl(self) -> float:
        return float(self.optic.paraxial.f2())

    def image_z(self) -> float:
        return float(np.asarray(self.optic.surfaces.positions).ravel()[-1])

    def ghost_sequence(self, path):
        """optiland sub-sequence for jaxflare ghost path (j, i) (same event order as jaxflare)."""
        if path in self.sequences:
            return self.sequences[path]
        lens = self.lens
        sj, si = lens.interface_surfaces[path[0]], lens.interface_surfaces[path[1]]
        steps: list = [s + 1 for s in range(sj)]
        steps.append((sj + 1, "reflect"))
        steps += [s + 1 for s in range(sj - 1, si, -1)]
        steps.append((si + 1, "reflect"))
        steps += [s + 1 for s in range(si + 1, lens.num_surfaces)]
        steps.append(lens.num_surfaces + 1)  # image surface
        seq = self.optic.add_sequence(f"ghost_{path[0]}_{path[1]}", steps)
        self.sequences[path] = seq
        return seq

    def make(self, origins: np.ndarray, directions: np.ndarray):
        """Fresh RealRays (optiland traces in place) from the same float32 rays, as float64."""
        o = origins.astype(np.float64)
        d = directions.astype(np.float64)
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        count = o.shape[0]
        return self.ol["RealRays"](
            o[:, 0].copy(), o[:, 1].copy(), o[:, 2].copy(), d[:, 0].copy(), d[:, 1].copy(), d[:, 2].copy(),
            np.ones(count), np.full(count, WAVELENGTH_NM * 1e-3),
        )

    def trace(self, rays, path=None):
        if path is None:
            # real-ray trace through the nominal sequence, skipping the object surface at infinity;
            # record=False: no per-surface snapshots (optiland's fastest way to get image-plane rays)
            return self.optic.surfaces.trace(rays, skip=1, record=False)
        return self.ghost_sequence(path).surfaces.trace(rays)

    @staticmethod
    def valid(rays) -> np.ndarray:
        x, y = np.asarray(rays.x), np.asarray(rays.y)
        return (np.asarray(rays.i) > 0) & np.isfinite(x) & np.isfinite(y)


# --------------------------------------------------------------------------- correctness


def correctness_check(jb: JaxflareBench, ob: OptilandBench, lens, count: int, seed: int, start_z: float, ghost_paths_to_check) -> dict:
    """Trace identical rays (the same float32 values) through both tools and compare the sensor-plane
    positions of the rays both call valid, the validity masks, and the paraxial EFL.

    Ghost paths are compared over all rays valid in both and over those landing on the sensor
    rectangle: ghost rays far off the sensor can leave the lens nearly parallel to it, where float32
    rounding is amplified by the long propagation to the sensor plane."""
    from collections import Counter

    origins, directions = make_rays(lens, count, seed, start_z)
    rays_j = jb.put(origins, directions)
    half_w = 0.5 * lens.prescription.sensor_width_mm
    half_h = 0.5 * lens.prescription.sensor_height_mm
    out: dict = {"rays": count, "tolerance_mm": 1e-3}
    out["efl_jaxflare_mm"] = float(lens.focal_length())
    out["efl_optiland_mm"] = ob.efl()
    out["efl_diff_mm"] = abs(out["efl_jaxflare_mm"] - out["efl_optiland_mm"])
    out["sensor_z_jaxflare_mm"] = float(lens.sensor_z_mm)
    out["image_z_optiland_mm"] = ob.image_z()
    calls = []
    for _ in range(2):  # the first optiland trace in a process includes Numba's JIT compilation
        t0 = time.perf_counter()
        with np.errstate(all="ignore"):
            ob.trace(ob.make(origins, directions), None)
        calls.append(time.perf_counter() - t0)
    out["optiland_first_call_s"] = calls[0]
    out["optiland_second_call_s"] = calls[1]
    out["paths"] = []
    for path in [None] + list(ghost_paths_to_check):
        jb.warm(*rays_j, path)
        jr = jb.call(*rays_j, path)
        jpos = np.asarray(jr.positions, np.float64)
        jvalid = np.asarray(jr.valid)
        lost = np.asarray(jr.lost_at_surface)
        with np.errstate(all="ignore"):
            orays = ob.trace(ob.make(origins, directions), path)
        ovalid = ob.valid(orays)
        opos = np.stack([np.asarray(orays.x), np.asarray(orays.y), np.asarray(orays.z)], axis=-1)
        both = jvalid & ovalid
        on_sensor = both & (np.abs(jpos[:, 0]) <= half_w) & (np.abs(jpos[:, 1]) <= half_h)
        only_o = ovalid & ~jvalid
        entry = {
            "path": "primary" if path is None else f"({path[0]},{path[1]})",
            "valid_jaxflare": int(jvalid.sum()),
            "valid_optiland": int(ovalid.sum()),
            "valid_both": int(both.sum()),
            "valid_only_jaxflare": int((jvalid & ~ovalid).sum()),
            "valid_only_optiland": int(only_o.sum()),
            "only_optiland_lost_at_surface_in_jaxflare": {str(k): v for k, v in sorted(Counter(lost[only_o].tolist()).items())},
            "on_sensor_both": int(on_sensor.sum()),
        }
        diff = np.linalg.norm(jpos[:, :2] - opos[:, :2], axis=-1)
        if both.any():
            entry["max_xy_diff_mm"] = float(diff[both].max())
            entry["median_xy_diff_mm"] = float(np.median(diff[both]))
            entry["max_sensor_z_diff_mm"] = float(np.max(np.abs(jpos[both, 2] - opos[both, 2])))
        if on_sensor.any():
            entry["max_xy_diff_on_sensor_mm"] = float(diff[on_sensor].max())
        key = "max_xy_diff_mm" if path is None else "max_xy_diff_on_sensor_mm"
        # None: no ray valid in both tools (and on the sensor, for ghosts): nothing to compare
        entry["positions_pass"] = bool(entry[key] < out["tolerance_mm"]) if key in entry else None
        entry["masks_agree"] = entry["valid_only_jaxflare"] == 0 and entry["valid_only_optiland"] == 0
        out["paths"].append(entry)
    out["primary"] = out["paths"][0]
    ghosts = out["paths"][1:]
    out["ghost_summary"] = {
        "paths_checked": len(ghosts),
        "paths_compared": sum(e["positions_pass"] is not None for e in ghosts),
        "rays_compared_on_sensor": sum(e["on_sensor_both"] for e in ghosts),
        "positions_pass_all": all(e["positions_pass"] is not False for e in ghosts),
        "max_xy_diff_on_sensor_mm": max((e.get("max_xy_diff_on_sensor_mm", 0.0) for e in ghosts), default=None),
        "max_xy_diff_all_valid_mm": max((e.get("max_xy_diff_mm", 0.0) for e in ghosts), default=None),
        "paths_with_mask_mismatch": [e["path"] for e in ghosts if not e["masks_agree"]],
        "rays_only_valid_in_optiland": sum(e["valid_only_optiland"] for e in ghosts),
        "rays_only_valid_in_jaxflare": sum(e["valid_only_jaxflare"] for e in ghosts),
        "rays_valid_in_either": sum(e["valid_jaxflare"] + e["valid_only_optiland"] for e in ghosts),
    }
    return out


def _verdict(ok) -> str:
    return "n/a (no rays to compare)" if ok is None else ("PASS" if ok else "FAIL")


def log_correctness(c: dict, log) -> None:
    log(f"  correctness vs optiland ({c['rays']} identical rays, tolerance {c['tolerance_mm']:g} mm): paraxial EFL "
        f"{c['efl_jaxflare_mm']:.5f} vs {c['efl_optiland_mm']:.5f} mm (diff {c['efl_diff_mm']:.1e}); optiland first trace "
        f"{c['optiland_first_call_s']:.2f} s, second {c['optiland_second_call_s']:.3f} s (Numba JIT on first use)")
    p = c["primary"]
    log(f"    primary: valid {p['valid_jaxflare']} / {p['valid_optiland']} (jaxflare / optiland), mask mismatches "
        f"{p['valid_only_jaxflare'] + p['valid_only_optiland']}; max |dxy| {p.get('max_xy_diff_mm', float('nan')):.2e} mm "
        f"(median {p.get('median_xy_diff_mm', float('nan')):.1e}) -> {_verdict(p['positions_pass'])}")
    g = c["ghost_summary"]
    if g["paths_checked"]:
        log(f"    {g['paths_checked']} ghost paths ({g['paths_compared']} with rays on the sensor in both, "
            f"{g['rays_compared_on_sensor']} rays): max |dxy| on the sensor {g['max_xy_diff_on_sensor_mm']:.2e} mm "
            f"-> {_verdict(g['positions_pass_all'])}; over all valid rays {g['max_xy_diff_all_valid_mm']:.2e} mm "
            f"(includes far-off-sensor grazing rays, float32)")
        if g["paths_with_mask_mismatch"]:
            log(f"    validity differs on paths {', '.join(g['paths_with_mask_mismatch'])}: {g['rays_only_valid_in_optiland']} rays "
                f"valid only in optiland, {g['rays_only_valid_in_jaxflare']} only in jaxflare (of {g['rays_valid_in_either']})")
            for e in c["paths"][1:]:
                if not e["masks_agree"]:
                    log(f"      {e['path']}: only optiland {e['valid_only_optiland']} (jaxflare lost them at surfaces "
                        f"{e['only_optiland_lost_at_surface_in_jaxflare']}), only jaxflare {e['valid_only_jaxflare']}")


# --------------------------------------------------------------------------- the benchmark


def bench_lens(name: str, label: str, cfg: dict, ol: dict | None, machine: str, log) -> tuple[list[dict], dict]:
    import jax
    import jaxflare

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        lens = jaxflare.load_lens(name)
    lens_info: dict = {"lens": name, "label": label, "name": lens.name, "num_surfaces": lens.num_surfaces,
                       "num_interfaces": lens.num_interfaces, "efl_mm": float(lens.focal_length()),
                       "half_field_deg": math.degrees(half_field_rad(lens)), "load_warnings": [str(w.message) for w in caught]}
    paths = jaxflare.ghost_paths(lens)
    lens_info["num_ghost_paths"] = len(paths)
    start_z = START_Z_MM
    sag = front_sag_at_rim(lens)
    if sag < start_z + 0.5:
        start_z = math.floor(sag - 1.0)
        lens_info["note_start_z"] = f"front surface rim sag {sag:.2f} mm lies before z = -5; rays start at z = {start_z} mm"
        log(f"  note: {lens_info['note_start_z']}")
    lens_info["start_z_mm"] = start_z
    log(f"\n== {label}: '{lens.name}' | {lens.num_surfaces} surfaces, {lens.num_interfaces} interfaces, "
        f"{len(paths)} ghost paths | EFL {lens_info['efl_mm']:.2f} mm, half field {lens_info['half_field_deg']:.1f} deg")

    rows: list[dict] = []
    jb = JaxflareBench(lens)
    sample = ghost_sample(paths, cfg["ghost_sample"])
    lens_info["ghost_sample"] = [list(p) for p in sample]

    def row(kind, path, batch, tool, version, dtype, med, compile_s, repeats, valid_fraction, num_paths, rays_total=None):
        rays = batch * num_paths if rays_total is None else rays_total
        r = {
            "lens": name, "lens_label": label, "path_kind": kind, "path": path, "batch_rays": batch, "tool": tool,
            "tool_version": version, "dtype": dtype, "median_s": med, "rays_per_s": rays / med if med > 0 else float("nan"),
            "compile_s": compile_s, "repeats": repeats, "valid_fraction": valid_fraction, "num_paths": num_paths,
            "num_surfaces": lens.num_surfaces, "machine": machine,
        }
        rows.append(r)
        return r

    # optiland set-up (and the comparison ghost path: the sampled path with the most valid rays)
    ob = None
    if ol is not None:
        reason = optiland_unsupported_reason(lens)
        if reason:
            lens_info["optiland_skipped"] = reason
            log(f"  optiland: skipped for this lens: {reason}")
        else:
            try:
                ob = OptilandBench(lens, ol)
            except Exception as error:
                lens_info["optiland_skipped"] = f"building the optic failed: {type(error).__name__}: {error}"
                log(f"  optiland: {lens_info['optiland_skipped']}")
                ob = None
            if ob is not None and lens.aperture_blades:
                lens_info["optiland_note"] = "polygonal iris approximated by its circumcircle in optiland"

    # the ghost path timed in optiland too: the sampled path with the most valid rays
    probe_o, probe_d = make_rays(lens, cfg["check_rays"], 99, start_z)
    probe = jb.put(probe_o, probe_d)
    fractions = {}
    for p in sample:
        jb.warm(*probe, p)
        fractions[p] = float(np.mean(np.asarray(jb.call(*probe, p).valid)))
    lens_info["ghost_sample_valid_fraction"] = {f"({p[0]},{p[1]})": f for p, f in fractions.items()}
    compare_path = max(sample, key=lambda p: fractions[p]) if sample else None
    lens_info["optiland_ghost_path"] = list(compare_path) if compare_path else None

    if ob is not None:
        try:
            lens_info["correctness"] = correctness_check(jb, ob, lens, cfg["check_rays"], 7, start_z, sample)
            log_correctness(lens_info["correctness"], log)
        except Exception as error:
            lens_info["correctness_error"] = f"{type(error).__name__}: {error}"
            log(f"  correctness check failed to run: {lens_info['correctness_error']}")
            traceback.print_exc()

    repeats = cfg["repeats"]
    jax_version = jax.__version__
    for batch in cfg["batches"]:
        origins_np, directions_np = make_rays(lens, batch, 1000 + batch, start_z)
        rays = jb.put(origins_np, directions_np)
        # primary
        compile_s = jb.warm(*rays, None)
        med, _, last = timed(lambda: jb.call(*rays, None), repeats)
        valid = float(np.mean(np.asarray(last.valid)))
        r = row("primary", "primary", batch, "jaxflare", jax_version, "float32", med, compile_s, repeats, valid, 1)
        log(f"  jaxflare primary    N={batch:>7d}: {med * 1e3:9.2f} ms {r['rays_per_s'] / 1e6:8.3f} Mrays/s  "
            f"(compile {compile_s:.2f} s, valid {valid:.2f})")
        # ghost sample: one compiled function per stop-pass count, the path is data. Every sampled
        # path runs the same compiled code on the same number of events, so when one call is slow
        # the per-path repeats drop (to keep the full run near 10 minutes): the median over the
        # sampled paths still rests on >= 10 timed calls.
        ghost_repeats = cfg["ghost_repeats"] if med < cfg["slow_call_s"] else max(1, min(cfg["ghost_repeats"], 1 if med > 4 * cfg["slow_call_s"] else 2))
        per_path_times, per_path_valid = [], []
        ghost_compile = sum({jb.variant(batch, p): jb.warm(*rays, p) for p in sample}.values())
        for p in sample:
            med_p, _, last = timed(lambda p=p: jb.call(*rays, p), ghost_repeats)
            v = float(np.mean(np.asarray(last.valid)))
            per_path_times.append(med_p)
            per_path_valid.append(v)
            if p == compare_path:
                row("ghost_path", f"({p[0]},{p[1]})", batch, "jaxflare", jax_version, "float32", med_p,
                    jb.compile_s[jb.variant(batch, p)], ghost_repeats, v, 1)
        lens_info.setdefault("ghost_path_median_s", {})[str(batch)] = {f"({p[0]},{p[1]})": t for p, t in zip(sample, per_path_times)}
        by_passes: dict = {}
        for p, t in zip(sample, per_path_times):
            by_passes.setdefault(jb.variant(batch, p)[1], []).append(t)
        lens_info.setdefault("ghost_median_s_by_stop_passes", {})[str(batch)] = {
            str(k): statistics.median(v) for k, v in sorted(by_passes.items())}
        if sample:
            med_g = statistics.median(per_path_times)
            r = row("ghost_median", f"median of {len(sample)}", batch, "jaxflare", jax_version, "float32", med_g, ghost_compile,
                    ghost_repeats, statistics.median(per_path_valid), 1)
            log(f"  jaxflare ghost      N={batch:>7d}: {med_g * 1e3:9.2f} ms {r['rays_per_s'] / 1e6:8.3f} Mrays/s  "
                f"(median over {len(sample)} paths, range {min(per_path_times) * 1e3:.1f}-{max(per_path_times) * 1e3:.1f} ms; "
                + ", ".join(f"{k} stop pass{'es' if k != 1 else ''}: {statistics.median(v) * 1e3:.1f} ms ({len(v)})"
                            for k, v in sorted(by_passes.items()))
                + f"; {ghost_repeats} call(s)/path; compile {ghost_compile:.2f} s)")
        # the former formulation, same rays, same calls
        if cfg.get("former", True):
            jb.call_former(*rays, None)
            med_f, _, last = timed(lambda: jb.call_former(*rays, None), repeats)
            r = row("primary", "primary", batch, FORMER, jax_version, "float32", med_f, float("nan"), repeats, float(np.mean(np.asarray(last.valid))), 1)
            log(f"  {FORMER} primary N={batch:>7d}: {med_f * 1e3:9.2f} ms {r['rays_per_s'] / 1e6:8.3f} Mrays/s")
            if sample:
                former_times = []
                for p in sample:
                    jb.call_former(*rays, p)
                    former_times.append(timed(lambda p=p: jb.call_former(*rays, p), ghost_repeats)[0])
                med_fg = statistics.median(former_times)
                r = row("ghost_median", f"median of {len(sample)}", batch, FORMER, jax_version, "float32", med_fg, float("nan"), ghost_repeats, float("nan"), 1)
                log(f"  {FORMER} ghost   N={batch:>7d}: {med_fg * 1e3:9.2f} ms {r['rays_per_s'] / 1e6:8.3f} Mrays/s (median over {len(sample)} paths)")
        # optiland, same rays
        if ob is not None:
            try:
                for kind, path in (("primary", None), ("ghost_path", compare_path)):
                    if kind == "ghost_path" and path is None:
                        continue
                    t0 = time.perf_counter()
                    with np.errstate(all="ignore"):
                        first = ob.trace(ob.make(origins_np, directions_np), path)
                    first_s = time.perf_counter() - t0
                    times = []
                    for _ in range(repeats):
                        fresh = ob.make(origins_np, directions_np)  # optiland traces in place: new rays, untimed
                        t0 = time.perf_counter()
                        with np.errstate(all="ignore"):
                            ob.trace(fresh, path)
                        times.append(time.perf_counter() - t0)
                    med_o = statistics.median(times)
                    valid_o = float(np.mean(ob.valid(first)))
                    compile_o = max(first_s - med_o, 0.0)
                    label_path = "primary" if path is None else f"({path[0]},{path[1]})"
                    r = row(kind, label_path, batch, "optiland", ol["version"], "float64", med_o, compile_o, repeats, valid_o, 1)
                    log(f"  optiland {'primary' if path is None else 'ghost ' + label_path:10s} N={batch:>7d}: {med_o * 1e3:9.2f} ms "
                        f"{r['rays_per_s'] / 1e6:8.3f} Mrays/s  (first call +{compile_o:.2f} s, valid {valid_o:.2f})")
            except Exception as error:
                lens_info["optiland_error"] = f"{type(error).__name__}: {error}"
                log(f"  optiland trace failed: {lens_info['optiland_error']}")
                traceback.print_exc()
                ob = None

    # every ghost path of the lens with a fixed ray count each: the loop a renderer runs
    count = cfg["all_ghost_rays"]
    origins_np, directions_np = make_rays(lens, count, 5, start_z)
    rays = jb.put(origins_np, directions_np)
    compile_s = sum({jb.variant(count, p): jb.warm(*rays, p) for p in paths}.values())

    def all_ghosts():
        results = [jaxflare.trace(lens, rays[0], rays[1], WAVELENGTH_NM, p) for p in paths]
        return jax.block_until_ready(results)

    # one untimed pass first when it is cheap (it also settles caches); fewer repeats when a pass is long
    estimate = None
    per_path = [r for r in rows if r["path_kind"] == "ghost_median" and r["batch_rays"] == count]
    if per_path:
        estimate = per_path[0]["median_s"] * len(paths)
    all_repeats = cfg["all_ghost_repeats"]
    if estimate is not None and estimate > cfg["long_pass_s"]:
        all_repeats = 1
        log(f"  (all-ghost pass estimated at {estimate:.0f} s: timing 1 pass)")
    elif estimate is not None and estimate < 0.2 * cfg["long_pass_s"]:
        all_ghosts()
    med, times, _ = timed(all_ghosts, all_repeats)
    r = row("all_ghosts", f"all {len(paths)}", count, "jaxflare", jax_version, "float32", med, compile_s, all_repeats,
            float("nan"), len(paths))
    lens_info["all_ghosts_s"] = med
    lens_info["all_ghosts_first_call_s"] = compile_s
    log(f"  jaxflare ALL {len(paths)} ghost paths x {count} rays: {med:.2f} s ({r['rays_per_s'] / 1e6:.3f} Mrays/s, "
        f"{med / len(paths) * 1e3:.1f} ms/path; median of {len(times)}; compile {compile_s:.2f} s)")
    if cfg.get("former", True):
        for p in {jb.variant(count, p): p for p in paths}.values():
            jb.call_former(*rays, p)  # compile each variant, untimed
        t0 = time.perf_counter()
        for p in paths:
            jb.call_former(*rays, p)
        former_s = time.perf_counter() - t0
        row("all_ghosts", f"all {len(paths)}", count, FORMER, jax_version, "float32", former_s, float("nan"), 1, float("nan"), len(paths))
        lens_info["all_ghosts_former_s"] = former_s
        log(f"  {FORMER} ALL {len(paths)} ghost paths x {count} rays: {former_s:.2f} s (1 pass): {former_s / med:.1f}x slower")
    return rows, lens_info


def summary_table(rows: list[dict], lens_infos: list[dict]) -> str:
    def best(tool, lens, kinds):
        cand = [r for r in rows if r["tool"] == tool and r["lens"] == lens and r["path_kind"] in kinds]
        return max(cand, key=lambda r: r["rays_per_s"]) if cand else None

    lines = []
    header = (f"{'lens':22s} {'path':22s} {'jaxflare rays/s':>16s} {'@N':>7s} {'optiland rays/s':>16s} {'@N':>7s} {'ratio':>7s} "
              f"{'former rays/s':>14s} {'speed-up':>9s}")
    lines += [header, "-" * len(header)]
    for info in lens_infos:
        lens = info["lens"]
        specs = [("primary", ("primary",), ("primary",))]
        gp = info.get("optiland_ghost_path")
        if gp:
            specs.append((f"ghost ({gp[0]},{gp[1]})", ("ghost_path",), ("ghost_path",)))
        specs.append((f"ghost median of {len(info.get('ghost_sample', []))}", ("ghost_median",), ()))
        specs.append((f"all {info['num_ghost_paths']} ghosts", ("all_ghosts",), ()))
        for title, jk, ok in specs:
            j = best("jaxflare", lens, jk)
            o = best("optiland", lens, ok) if ok else None
            if j is None:
                continue
            ratio = f"{j['rays_per_s'] / o['rays_per_s']:6.1f}x" if o else "    -"
            ostr = f"{o['rays_per_s']:16.3e} {o['batch_rays']:7d}" if o else f"{'-':>16s} {'':7s}"
            f = [r for r in rows if r["tool"] == FORMER and r["lens"] == lens and r["path_kind"] in jk and r["batch_rays"] == j["batch_rays"]]
            fstr = f"{f[0]['rays_per_s']:14.3e} {j['rays_per_s'] / f[0]['rays_per_s']:8.1f}x" if f else f"{'-':>14s} {'-':>9s}"
            lines.append(f"{info['label']:22s} {title:22s} {j['rays_per_s']:16.3e} {j['batch_rays']:7d} {ostr} {ratio:>7s} {fstr}")
    return "\n".join(lines)


def write_outputs(rows: list[dict], meta: dict, out_dir: Path, stem: str, log) -> list[Path]:
    out = Outputs(out_dir, log)
    out.csv(f"{stem}.csv", rows, CSV_FIELDS)
    out.json(f"{stem}.json", dict(meta, rows=rows))
    out.chart(f"{stem}.png", _chart, rows, meta)
    return out.written


def _chart(rows: list[dict], meta: dict):
    plt = pyplot()
    lenses = [info for info in meta["lenses"]]
    fig, axes = plt.subplots(1, max(len(lenses), 1), figsize=(max(5.2 * len(lenses), 7.5), 5.2), squeeze=False, sharey=True)
    styles = {
        ("jaxflare", "primary"): dict(color="C0", marker="o", ls="-"),
        ("jaxflare", "ghost_median"): dict(color="C0", marker="s", ls="--"),
        ("jaxflare", "ghost_path"): dict(color="C0", marker="^", ls=":"),
        ("optiland", "primary"): dict(color="C3", marker="o", ls="-"),
        ("optiland", "ghost_path"): dict(color="C3", marker="^", ls=":"),
        ("jaxflare", "all_ghosts"): dict(color="C2", marker="*", ls="none", ms=12),
        (FORMER, "primary"): dict(color="0.55", marker="o", ls="-"),
        (FORMER, "ghost_median"): dict(color="0.55", marker="s", ls="--"),
        (FORMER, "all_ghosts"): dict(color="0.55", marker="*", ls="none", ms=12),
    }
    names = {"primary": "primary", "ghost_median": "ghost (median over sampled paths)",
             "ghost_path": "ghost (the path compared with optiland)", "all_ghosts": "all ghost paths (total)"}
    handles: dict = {}
    for ax, info in zip(axes[0], lenses):
        for (tool, kind), style in styles.items():
            sel = sorted((r for r in rows if r["lens"] == info["lens"] and r["tool"] == tool and r["path_kind"] == kind),
                         key=lambda r: r["batch_rays"])
            if not sel:
                continue
            label = f"{tool} {names[kind]}"
            (line,) = ax.plot([r["batch_rays"] for r in sel], [r["rays_per_s"] for r in sel], label=label, **style)
            handles.setdefault(label, line)
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xlabel("rays per trace call (batch)")
        gp = info.get("optiland_ghost_path")
        ax.set_title(f"{info['label']} ({info['num_surfaces']} surfaces, {info['num_ghost_paths']} ghost paths)"
                     + (f"\ncompared ghost path ({gp[0]},{gp[1]})" if gp else ""), fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("rays / s")
    m = meta["machine"]
    fig.suptitle(f"Exact-trace throughput: jaxflare (float32; grey: the former formulation, {FORMER}) vs optiland "
                 f"{meta.get('optiland_version') or '(skipped)'} (float64)\n"
                 f"{cpu_label(m)}, jax {m.get('jax')}, "
                 f"load avg {m.get('load_average_start')}", fontsize=9)
    fig.legend(list(handles.values()), list(handles.keys()), loc="lower center", ncol=3, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.14, 1, 1))
    return fig


def main(argv: list[str] | None = None) -> int:
    parser = make_parser(__doc__, "smoke test: small batches, 2 repeats, one lens (< 60 s)")
    parser.add_argument("--lenses", nargs="+", help="lens file stems (default: Biotar, Angenieux, Nikon 28-70)")
    parser.add_argument("--batches", nargs="+", type=int, help="batch sizes (rays per call)")
    parser.add_argument("--repeats", type=int, help="timed repeats per measurement (median reported)")
    parser.add_argument("--ghost-repeats", type=int, help="timed repeats per sampled ghost path")
    parser.add_argument("--ghost-sample", type=int, help="number of ghost paths timed individually")
    parser.add_argument("--all-ghost-rays", type=int, help="rays per path for the all-ghost-paths total")
    parser.add_argument("--no-optiland", action="store_true", help="skip the optiland comparison")
    parser.add_argument("--no-former", action="store_true", help=f"skip the former formulation ({FORMER})")
    add_out_option(parser, quick_folder=False)
    add_stem_option(parser, "output file stem (default trace_throughput, or trace_throughput_quick with --quick)")
    args = parser.parse_args(argv)

    cfg = dict(QUICK if args.quick else FULL)
    if args.lenses:
        cfg["lenses"] = args.lenses
    if args.batches:
        cfg["batches"] = args.batches
    for key in ("repeats", "ghost_repeats", "ghost_sample", "all_ghost_rays"):
        if getattr(args, key):
            cfg[key] = getattr(args, key)
    cfg["former"] = not args.no_former
    stem = quick_stem(args, STEM)

    started = time.perf_counter()
    try:
        import jax
        import jaxflare
    except Exception as error:
        log(f"bench_trace: cannot import jaxflare/jax: {type(error).__name__}: {error}")
        return 1
    if jax.config.jax_enable_x64:
        log("WARNING: jax_enable_x64 is on; this benchmark is meant for float32 (the default render precision)")

    info, machine = announce("bench_trace", args.quick, log)
    log(f"  batches {cfg['batches']}, {cfg['repeats']} repeats (median), ghost sample {cfg['ghost_sample']} paths, "
        f"all-ghost pass {cfg['all_ghost_rays']} rays/path")

    ol = None
    optiland_status = "skipped (--no-optiland)"
    if not args.no_optiland:
        try:
            t0 = time.perf_counter()
            ol = import_optiland()
            optiland_status = f"optiland {ol['version']} (numpy backend), import {time.perf_counter() - t0:.1f} s"
            warnings.filterwarnings("ignore", module=r"numba\..*")
            warnings.filterwarnings("ignore", module=r"optiland\..*")
            try:
                from numba.core.errors import NumbaWarning

                warnings.filterwarnings("ignore", category=NumbaWarning)
            except Exception:
                pass
        except OptilandUnavailable as error:
            optiland_status = f"SKIPPED: {error}"
    log(f"  optiland comparison: {optiland_status}")

    available = set(jaxflare.bundled_lens_names())
    labels = dict(LENSES)
    rows: list[dict] = []
    lens_infos: list[dict] = []
    skipped: list[str] = []
    for name in cfg["lenses"]:
        if name not in available and not os.path.exists(name):
            note = f"lens '{name}' is not bundled (have: {', '.join(sorted(available))}); skipped"
            log(f"\nnote: {note}")
            skipped.append(note)
            continue
        try:
            lens_rows, lens_info = bench_lens(name, labels.get(name, name), cfg, ol, machine, log)
        except Exception as error:
            note = f"lens '{name}' failed: {type(error).__name__}: {error}"
            log(f"\nnote: {note}")
            traceback.print_exc()
            skipped.append(note)
            continue
        rows += lens_rows
        lens_infos.append(lens_info)

    elapsed = time.perf_counter() - started
    meta = run_meta(
        "trace_throughput", args.quick, cfg, info, machine,
        after_config={"wavelength_nm": WAVELENGTH_NM},
        optiland_version=ol["version"] if ol else None,
        optiland_status=optiland_status,
        skipped=skipped,
        lenses=lens_infos,
        elapsed_s=elapsed,
        method=(
            "median of `repeats` timed calls after one warm-up call per compiled shape (its wall time = compile_s for jaxflare; "
            "for optiland compile_s = first call - median, i.e. Numba JIT + caches); jax.block_until_ready on every call; "
            "rays/s = batch_rays * num_paths / median_s. jaxflare float32, optiland float64 NumPy backend with "
            "record=False for the primary path (ghost sequences always record)."
        ),
    )
    written = write_outputs(rows, meta, args.out, stem, log)
    log("\n" + summary_table(rows, lens_infos))
    if ol is None:
        log(f"\noptiland comparison {optiland_status}")
    for note in skipped:
        log(f"skipped: {note}")
    log(f"\nwrote {shown_paths(written)} in {elapsed:.1f} s")
    return 0 if rows else 1


if __name__ == "__main__":
    sys.exit(main())
