"""``jaxflare.path_system``: build, validate and cache the polynomial system of a lens path."""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._version import __version__
from .._cache_dirs import cache_root
from ..io import write_bytes_atomic
from ..optics import GhostPath, Lens, cast_floating, check_ghost_path, ghost_paths, half_field_of_view_deg
from ._basis import monomial_exponents
from ._constructions import AbstractConstruction, construction_from
from ._domain import DEFAULT_WAVELENGTH_RANGE_NM, PathDomain, make_domain, sample_variables
from ._least_squares import build_polynomial, sample_region
from ._system import PathSystem, PathSystemReport
from ._validate import validate

DEFAULT_DEGREE = 5
CACHE_FORMAT = 2


def _code_version() -> str:
    """The package version and a digest of the source of every module a path system depends on
    (the optics and polynomial packages): a cached system is rebuilt when any of them changes."""
    digest = hashlib.sha256()
    root = Path(__file__).resolve().parent.parent
    for package in ("optics", "polynomial"):
        for source in sorted((root / package).glob("*.py")):
            digest.update(source.read_bytes())
    return f"{__version__}-{CACHE_FORMAT}-{digest.hexdigest()[:16]}"


def _lens_key(lens: Lens) -> str:
    digest = hashlib.sha256()
    for leaf in jax.tree.leaves(lens):
        if eqx.is_array(leaf):
            digest.update(np.ascontiguousarray(np.asarray(leaf, np.float64 if jnp.issubdtype(leaf.dtype, jnp.floating) else np.int64)).tobytes())
    digest.update(repr((lens.stop_index, lens.aperture_blades, lens.interface_surfaces, lens.has_aspheres, lens.zoom_position)).encode())
    return digest.hexdigest()


def default_cache_dir() -> Path:
    """``$JAXFLARE_CACHE_DIR``, else ``$XDG_CACHE_HOME/jaxflare``, else ``~/.cache/jaxflare``."""
    return cache_root()


def path_system(
    lens: Lens,
    path: GhostPath | None = None,
    *,
    degree: int = DEFAULT_DEGREE,
    construction: str | AbstractConstruction = "least-squares",
    max_field_angle_deg: float | None = None,
    wavelength_range_nm: tuple[float, float] = DEFAULT_WAVELENGTH_RANGE_NM,
    sparse_terms: int | None = None,
    max_clip_events: int = 4,
    fit_rays: int | None = None,
    validation_rays: int = 16384,
    tolerance_mm: float | None = None,
    max_mask_mismatch: float = 0.1,
    fallback: Literal["exact", "none"] = "exact",
    fallback_fraction: float = 0.125,
    cache: bool | str | os.PathLike = True,
    seed: int = 0,
) -> PathSystem:
    """Build (or load from the disk cache) the polynomial system of one path of ``lens``.

    Args:
        lens: the lens; its iris and clear apertures are the ones tested at call time.
        path: ``None`` for the primary path or a ghost path ``(j, i)`` as in :func:`jaxflare.trace`.
        degree: total degree of the polynomials (1 to 9).
        construction: ``"least-squares"`` (least squares on exact traces over the domain; the
            default: it is accurate across the whole domain; ``"fit"`` is its former name),
            ``"taylor"`` (expansion about the axis, 2012), or an
            :class:`~jaxflare.polynomial.AbstractConstruction`.
        max_field_angle_deg: largest angle between an incoming ray and the axis; default the lens's
            half field of view. Lights further off-axis need a wider domain.
        wavelength_range_nm: the band the system is built for (default the visible 380-780 nm).
        sparse_terms: keep at most this many terms per output (least squares only), chosen by the size
            of their contribution, and evaluate only the union of the kept terms.
        max_clip_events: clear apertures (besides the iris) tested per ray; the ones that clip the
            most rays are chosen; rays lost elsewhere show up as ``unmodelled_clip_fraction``.
        fit_rays: rays that get through the path to fit on (default 8 per term, at least 2048);
            sampling stops short of it after 2^15 candidates (4 batches), which bounds the
            build time of paths that few rays get through.
        validation_rays: exact traces used to measure the error and build the trust table: half
            uniform over the domain, half where the fit samples got through.
        tolerance_mm: sensor-position error a cell of the domain may have and still be trusted
            (default half a pixel of a 2048-pixel-wide image on the lens's sensor).
        max_mask_mismatch: fraction of a cell's rays whose validity may differ from the exact trace.
        fallback: ``"exact"`` re-traces untrusted rays exactly (up to ``fallback_fraction`` of each
            batch); ``"none"`` returns them invalid. Either way ``result.trusted`` marks them.
        cache: True for :func:`default_cache_dir`, a directory, or False for no cache.
        seed: seed of the fit and validation samples.
    """
    path = check_ghost_path(lens, path)
    if not (isinstance(degree, int) and 1 <= degree <= 9):
        raise ValueError(f"degree must be an integer from 1 to 9, got {degree!r}")
    construction = construction_from(construction, sparse_terms)
    if fallback not in ("exact", "none"):
        raise ValueError(f"fallback must be 'exact' or 'none', got {fallback!r}")
    if not 0 < fallback_fraction <= 1:
        raise ValueError(f"fallback_fraction must be in (0, 1], got {fallback_fraction}")
    domain = make_domain(lens, max_field_angle_deg, wavelength_range_nm)
    if tolerance_mm is None:
        tolerance_mm = 0.5 * lens.prescription.sensor_width_mm / 2048
    exponents = monomial_exponents(degree)
    if fit_rays is None:
        fit_rays = max(2048, 8 * len(exponents))
    settings = dict(
        path=path, degree=degree, construction=construction.name, domain=dataclasses.asdict(domain),
        sparse_terms=getattr(construction, "sparse_terms", None),
        max_clip_events=max_clip_events, fit_rays=fit_rays, validation_rays=validation_rays, tolerance_mm=tolerance_mm,
        max_mask_mismatch=max_mask_mismatch, seed=seed,
    )
    cache_file = None
    if cache:
        directory = default_cache_dir() if cache is True else Path(cache)
        key = hashlib.sha256((_lens_key(lens) + json.dumps(settings, sort_keys=True) + _code_version()).encode()).hexdigest()[:32]
        cache_file = directory / f"path-{key}.npz"
        if cache_file.exists():
            try:
                return load_cached(cache_file, lens, fallback, fallback_fraction)
            except (OSError, ValueError, KeyError):
                pass  # a damaged cache entry is rebuilt and overwritten
    start = time.perf_counter()
    with jax.enable_x64(True):
        lens64 = cast_floating(lens, jnp.float64)
        system, region = build_polynomial(lens64, path, domain, exponents, construction, max_clip_events, fit_rays, seed, tolerance_mm)
        # half uniform over the domain (every cell of the trust table), half where rays get through
        rng = np.random.default_rng(seed + 1)
        samples = sample_variables(validation_rays - validation_rays // 2, rng)
        samples = np.concatenate([samples, sample_region(region, validation_rays // 2, rng)])
        table, estimate_limit_mm, summary = validate(system, samples, tolerance_mm, max_mask_mismatch)
        system = eqx.tree_at(lambda s: (s.trust_table, s.estimate_limit_mm), system, (jnp.asarray(table), jnp.asarray(estimate_limit_mm)))
        arrays = {name: np.asarray(getattr(system, name)) for name in _ARRAY_FIELDS}
    report = PathSystemReport(
        construction=construction.name, degree=degree, num_terms=len(system.exponents), fit_rays=len(arrays["fit_variables"]),
        validation_rays=validation_rays, clip_surfaces=system.clip_surfaces, tolerance_um=tolerance_mm * 1e3,
        estimate_limit_um=estimate_limit_mm * 1e3, build_seconds=time.perf_counter() - start, **summary,
    )
    static = dict(
        path=path, degree=system.degree, construction=construction.name, exponents=system.exponents, domain=domain,
        num_stop_passes=system.num_stop_passes, clip_event_rows=system.clip_event_rows, clip_surfaces=system.clip_surfaces,
        report=report,
    )
    if cache_file is not None:
        save_cached(cache_file, arrays, static)
    return _assemble(lens, arrays, static, fallback, fallback_fraction)


_ARRAY_FIELDS = (
    "coefficients", "trust_table", "error_estimator", "estimate_limit_mm", "fit_variables", "path_blocked", "events",
    "clip_surface_index", "clip_active",
)


def _assemble(lens: Lens, arrays: dict, static: dict, fallback: str, fallback_fraction: float) -> PathSystem:
    """A path system on ``lens`` (its dtype: float32 to render) from NumPy arrays and static fields."""
    dtype = lens.curvature_per_mm.dtype
    fields = {name: jnp.asarray(value, dtype) if np.issubdtype(value.dtype, np.floating) else jnp.asarray(value) for name, value in arrays.items()}
    return PathSystem(lens=lens, **fields, **static, fallback=fallback, fallback_fraction=fallback_fraction)


def path_systems(lens: Lens, paths: Sequence[GhostPath | None] | None = None, **options) -> dict:
    """Path systems for several paths (default: every ghost path of ``lens``), keyed by path."""
    paths = ghost_paths(lens) if paths is None else list(paths)
    if options.get("max_field_angle_deg") is None:  # trace the field of view once, not once per path
        options["max_field_angle_deg"] = half_field_of_view_deg(lens)
    return {path: path_system(lens, path, **options) for path in paths}


# --------------------------------------------------------------------------- cache


def save_cached(file: Path, arrays: dict, static: dict) -> None:
    meta = dict(static, domain=dataclasses.asdict(static["domain"]), report=static["report"].as_dict())
    buffer = io.BytesIO()
    np.savez(buffer, meta=np.asarray(json.dumps(meta)), **arrays)
    try:
        write_bytes_atomic(file, buffer.getvalue())
    except OSError:
        pass  # an unwritable cache only costs a rebuild next time


def load_cached(file: Path, lens: Lens, fallback: str, fallback_fraction: float) -> PathSystem:
    with np.load(file, allow_pickle=False) as data:
        arrays = {name: data[name] for name in _ARRAY_FIELDS}
        meta = json.loads(str(data["meta"]))
    report = dict(meta["report"], clip_surfaces=tuple(meta["report"]["clip_surfaces"]))
    static = dict(
        path=tuple(meta["path"]) if meta["path"] is not None else None, degree=meta["degree"], construction=meta["construction"],
        exponents=tuple(tuple(e) for e in meta["exponents"]), domain=PathDomain(**meta["domain"]),
        num_stop_passes=meta["num_stop_passes"], clip_event_rows=tuple(meta["clip_event_rows"]),
        clip_surfaces=tuple(meta["clip_surfaces"]), report=PathSystemReport(**report),
    )
    return _assemble(lens, arrays, static, fallback, fallback_fraction)
