"""Finding and loading lenses: bundled names, our TOML format, Zemax ``.zmx`` files and the lens
data of other flare tools; explicit handling of the semi-apertures a file gives (or not) and of
glass names the catalogs lack."""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import math
import os
from collections.abc import Mapping
from importlib import resources

from ..optics import LensFormatError, LensPrescription, MediumSpec, check_prescription
from ._lens_formats import LENS_FORMATS, read_flaresim_lens, read_json_lens, read_openlensflare_xml, read_pbrt_dat
from ._lens_toml import read_lens_toml

SEMI_APERTURE_MODES = {
    "file": "as the file gives them (missing ones derived); a value larger than a spherical surface allows (|R|) is an error",
    "auto": "derived for every surface from the stop (the stated f-number, entrance pupil or stop size) and the marginal and chief rays",
    "diameter": "the file's aperture column holds diameters: halved",
    "clip": "as the file gives them, each clipped to 0.98 |R| where the sphere is smaller",
}
"""The ways :func:`read_prescription` / :func:`load_lens` treat a file's semi-apertures
(``semi_aperture=...``; ``jaxflare lens ... --semi-aperture MODE``). Every mode but ``"file"``
writes what it changed into the prescription's notes."""


def _bundled_directory():
    """The bundled lens folder: the installed ``jaxflare.lenses`` package data, or, when running
    from a source tree that is not installed, the repository's ``lenses/`` folder."""
    try:
        return resources.files("jaxflare.lenses")
    except ModuleNotFoundError:
        return resources.files("jaxflare").joinpath("..", "lenses")


def bundled_lens_names() -> list[str]:
    """Names of the lenses shipped with jaxflare (file stems in ``lenses/``)."""
    return sorted(entry.name[: -len(".toml")] for entry in _bundled_directory().iterdir() if entry.name.endswith(".toml"))


def _read_file(text: str) -> LensPrescription:
    """Read one lens file by its extension (``path#ID`` picks a lens of a lentil database)."""
    path, _, fragment = text.partition("#") if "#" in text and not os.path.exists(text) else (text, "", "")
    lower = path.lower()
    if lower.endswith(".zmx"):
        from ._zemax import read_zmx

        return read_zmx(path)
    if lower.endswith(".lens"):
        return read_flaresim_lens(path)
    if lower.endswith(".json"):
        return read_json_lens(path, fragment or None)
    if lower.endswith(".xml"):
        return read_openlensflare_xml(path)
    if lower.endswith(".dat"):
        return read_pbrt_dat(path)
    if fragment:
        raise LensFormatError(f"{text}: '#{fragment}' picks a lens of a lentil database (.json) only")
    return read_lens_toml(path)


def _is_file_path(text: str) -> bool:
    lower = text.lower().partition("#")[0]
    return lower.endswith((".toml", ".zmx", *LENS_FORMATS)) or os.sep in text or os.path.exists(text)


def apply_semi_aperture_mode(prescription: LensPrescription, mode: str) -> LensPrescription:
    """The prescription with its semi-apertures treated as ``mode`` says (see :data:`SEMI_APERTURE_MODES`)."""
    if mode not in SEMI_APERTURE_MODES:
        raise ValueError(f"semi_aperture must be one of {', '.join(repr(m) for m in SEMI_APERTURE_MODES)}, got {mode!r}")
    where = prescription.path or prescription.name
    surfaces = list(prescription.surfaces)
    notes = [prescription.notes] if prescription.notes else []

    def too_large(surface) -> bool:
        r = surface.radius_mm
        return math.isfinite(r) and surface.kind == "spherical" and surface.conic == 0.0 and not surface.aspheric_coefficients and surface.semi_aperture_mm > abs(r)

    if mode == "file":
        bad = [s for s in surfaces if math.isfinite(s.semi_aperture_mm) and too_large(s)]
        if bad:
            halved = sum(0.5 * s.semi_aperture_mm > abs(s.radius_mm) for s in bad)
            # labels of most readers name the file and line already; a Zemax comment label does not
            place = "" if os.path.basename(where or "") in bad[0].label else f"{where}: "
            raise LensFormatError(
                f"{place}{bad[0].label}: semi-aperture {bad[0].semi_aperture_mm:g} mm is larger than the sphere allows (|R| = {abs(bad[0].radius_mm):g} mm); "
                f"{len(bad)} of {len(surfaces)} surfaces exceed |R| ({halved} even when halved). If the column holds diameters use "
                "semi_aperture='diameter'; to derive every semi-aperture from the stop and the marginal and chief rays use "
                "semi_aperture='auto'; to clip them use 'clip' (command line: --semi-aperture MODE)"
            )
        return prescription
    if mode == "diameter":
        surfaces = [dataclasses.replace(s, semi_aperture_mm=0.5 * s.semi_aperture_mm) for s in surfaces]
        notes.append("semi_aperture='diameter': the file's aperture column read as diameters and halved")
    elif mode == "clip":
        clipped = []
        for k, s in enumerate(surfaces):
            if math.isfinite(s.semi_aperture_mm) and too_large(s):
                clipped.append(f"surface {k} ({s.semi_aperture_mm:g} -> {0.98 * abs(s.radius_mm):.4g} mm)")
                surfaces[k] = dataclasses.replace(s, semi_aperture_mm=0.98 * abs(s.radius_mm))
        notes.append(f"semi_aperture='clip': semi-apertures larger than the sphere allows clipped to 0.98 |R|: {', '.join(clipped) or 'none needed it'}")
    else:  # auto
        keep_stop = prescription.stated_f_number is None and prescription.entrance_pupil_diameter_mm is None
        surfaces = [s if (s.is_stop and keep_stop) else dataclasses.replace(s, semi_aperture_mm=math.nan) for s in surfaces]
        basis = "the stop's semi-aperture in the file" if keep_stop else "the stated f-number" if prescription.stated_f_number else "the stated entrance pupil"
        notes.append(f"semi_aperture='auto': every semi-aperture is derived from {basis} and the marginal and chief rays when the lens is built")
    return dataclasses.replace(prescription, surfaces=tuple(surfaces), notes="\n".join(notes))


def apply_glass_aliases(prescription: LensPrescription, aliases: Mapping[str, str]) -> LensPrescription:
    """The prescription with each glass named in ``aliases`` (case-insensitive) replaced by its
    target, ``"NAME"`` or ``"CATALOG:NAME"``; each replacement, and each alias the lens does not
    use, is written to the notes."""
    if not isinstance(aliases, Mapping):
        raise TypeError(f"glass_aliases must be a mapping {{name: 'CATALOG:NAME'}}, got {type(aliases).__name__}")
    table = {}
    for name, target in aliases.items():
        if not isinstance(name, str) or not isinstance(target, str) or not name.strip() or not target.strip():
            raise ValueError(f"glass_aliases: {name!r} -> {target!r}: both must be non-empty strings")
        table[name.strip().upper()] = target.strip()
    used, surfaces, notes = set(), [], [prescription.notes] if prescription.notes else []
    for k, s in enumerate(prescription.surfaces):
        glass = s.medium.glass
        if glass is not None and glass.upper() in table:
            target = table[glass.upper()]
            catalog, _, name = target.rpartition(":")
            used.add(glass.upper())
            surfaces.append(dataclasses.replace(s, medium=MediumSpec(glass=name, catalog=catalog.upper() or None, n_d=s.medium.n_d, v_d=s.medium.v_d)))
            notes.append(f"{s.label}: glass {glass!r} mapped to {target!r} (glass_aliases)")
        else:
            surfaces.append(s)
    unused = sorted(set(table) - used)
    if unused:
        notes.append(f"glass_aliases not used by this lens: {', '.join(unused)}")
    return dataclasses.replace(prescription, surfaces=tuple(surfaces), notes="\n".join(notes))


def read_prescription(
    source: str | os.PathLike, *, semi_aperture: str = "file", glass_aliases: Mapping[str, str] | None = None
) -> LensPrescription:
    """Read a prescription: a bundled lens name, a jaxflare ``.toml`` file, a Zemax ``.zmx``
    file, or the lens data of another flare tool (flaresim ``.lens``, realflare or lentil
    ``.json`` (``lenses.json#ID`` for one lens of a lentil database), OpenLensFlare ``.xml``, pbrt
    ``.dat``).

    ``semi_aperture`` says how the file's semi-apertures are taken (:data:`SEMI_APERTURE_MODES`:
    ``"file"``, ``"auto"``, ``"diameter"``, ``"clip"``); ``glass_aliases`` maps glass names the
    catalogs lack to catalog glasses (``{"L-TIM28_MOLD": "OHARA:L-TIM28"}``). Both are reported
    in the prescription's notes. Values no lens can have are a :class:`LensFormatError`.
    """
    text = os.fspath(source)
    if _is_file_path(text):
        prescription = _read_file(text)
    else:
        names = bundled_lens_names()
        if text not in names:
            close = difflib.get_close_matches(text, names, n=5, cutoff=0.3)
            hint = f" Did you mean: {', '.join(close)}?" if close else ""
            raise FileNotFoundError(
                f"no lens named {text!r}: not a file path and not a bundled lens.{hint} Bundled lenses: {', '.join(names)}. "
                f"Lens files: .toml, .zmx, {', '.join(LENS_FORMATS)}"
            )
        with resources.as_file(_bundled_directory() / f"{text}.toml") as path:
            prescription = read_lens_toml(path)
    with _naming_the_file(text if _is_file_path(text) else ""):
        if glass_aliases:
            prescription = apply_glass_aliases(prescription, glass_aliases)
        prescription = apply_semi_aperture_mode(prescription, semi_aperture)
        check_prescription(prescription)
    return prescription


@contextlib.contextmanager
def _naming_the_file(path: str):
    """Checks made after a file is read (apertures, glasses, the built lens) name a surface; a
    :class:`LensFormatError` from them names the file too."""
    try:
        yield
    except LensFormatError as error:
        message = str(error)
        if path and os.path.basename(path.split("#")[0]) not in message:  # messages may name the file by its base name
            raise LensFormatError(f"{path}: {message}") from None
        raise


def load_lens(
    source: str | os.PathLike | LensPrescription,
    zoom_position: int = 0,
    *,
    semi_aperture: str = "file",
    glass_aliases: Mapping[str, str] | None = None,
):
    """Load a lens: a bundled name (see :func:`bundled_lens_names`), a path to a jaxflare ``.toml``
    lens file, a Zemax ``.zmx`` file, another flare tool's lens file (see :func:`read_prescription`),
    or a :class:`LensPrescription`. Zooms start at position 0. ``semi_aperture`` and
    ``glass_aliases`` as for :func:`read_prescription` (applied to a prescription too)."""
    from ..optics import build_lens  # JAX: only when a lens is built

    if isinstance(source, LensPrescription):
        prescription = apply_glass_aliases(source, glass_aliases) if glass_aliases else source
        prescription = apply_semi_aperture_mode(prescription, semi_aperture)
    else:
        prescription = read_prescription(source, semi_aperture=semi_aperture, glass_aliases=glass_aliases)
    source_path = "" if isinstance(source, LensPrescription) else os.fspath(source)
    with _naming_the_file(source_path if _is_file_path(source_path) else ""):
        return build_lens(prescription, zoom_position)
