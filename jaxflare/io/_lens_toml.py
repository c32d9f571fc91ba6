"""Reader and writer for the jaxflare lens format (TOML; documented in ``lenses/FORMAT.md``)."""

from __future__ import annotations

import dataclasses
import math
import os
import re
import tomllib
from collections.abc import Mapping
from typing import Any

from ..optics import (
    COATING_INDEX_RANGE,
    DEFAULT_COATING,
    F_NUMBER_RANGE,
    MAX_COATING_THICKNESS_NM,
    MAX_LENGTH_MM,
    MAX_SURFACES,
    SURFACE_KINDS,
    UNCOATED,
    CoatingLayerSpec,
    CoatingSpec,
    LensFormatError,
    LensPrescription,
    MediumSpec,
    SurfaceSpec,
    check_blades,
    check_prescription,
)
from ._text_input import read_text_file

_TOP_LEVEL_KEYS = {
    "name": "lens name (string)",
    "source": "where the prescription comes from (string)",
    "focal_length_mm": "stated focal length in mm (number, or a list for zooms)",
    "focal_length_plane": "meridian of the stated focal length, \"y\" (default) or \"x\"",
    "f_number": "stated f-number (number)",
    "entrance_pupil_diameter_mm": "stated entrance pupil diameter in mm, instead of an f-number (number)",
    "sensor_mm": "[width, height] in mm",
    "aperture_blades": "number of iris blades, 0 = circular",
    "aperture_rotation_deg": "iris rotation in degrees",
    "design_wavelength_nm": "wavelength of the stated focal length in nm",
    "notes": "free text",
    "glass_catalogs": "list of catalogs to search first for glass names",
    "surfaces": "list of surface rows",
}
_SURFACE_KEYS = {
    "radius": "signed radius in mm, 0 or \"flat\" for a plane",
    "thickness": "distance to the next vertex in mm (a list for zooms)",
    "medium": "\"air\" or a catalog glass name",
    "n_d": "refractive index at 587.56 nm",
    "v_d": "Abbe number",
    "semi_aperture": "clear semi-aperture in mm",
    "kind": "one of " + ", ".join(SURFACE_KINDS),
    "conic": "conic constant",
    "aspheric": "[A4, A6, ...] even-asphere coefficients",
    "coating": "\"default\", \"none\", \"MgF2\", {quarter_wave=..., wavelength_nm=...} or {layers=[[index, nm], ...]}",
    "stop": "true on the aperture stop",
    "label": "free text naming the surface",
}


def _surface_line_numbers(text: str) -> list[int]:
    """1-based line numbers of the rows of the ``surfaces`` array (one inline table per line)."""
    numbers: list[int] = []
    inside = False
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.split("#", 1)[0].strip()
        if not inside:
            if not re.match(r"surfaces\s*=\s*\[", stripped):
                continue
            inside = True
            stripped = stripped.split("[", 1)[1].strip()
        if stripped.startswith("{"):
            numbers.append(number)
        if stripped == "]":
            break
    return numbers


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


class _Where:
    """Builds ``file:line: surface k: `` prefixes for error messages."""

    def __init__(self, filename: str, line_numbers: list[int]):
        self.filename = filename
        self.line_numbers = line_numbers

    def surface(self, index: int) -> str:
        if index < len(self.line_numbers):
            return f"{self.filename}:{self.line_numbers[index]}: surface {index}"
        return f"{self.filename}: surface {index}"


def _number(
    value: Any, where: str, key: str, *, positive: bool = False, nonnegative: bool = False, maximum: float | None = None,
    minimum: float | None = None,
) -> float:
    if not _is_number(value):
        raise LensFormatError(f"{where}: '{key}' must be a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise LensFormatError(f"{where}: '{key}' must be finite, got {value!r}")
    if positive and number <= 0:
        raise LensFormatError(f"{where}: '{key}' must be > 0, got {number}")
    if nonnegative and number < 0:
        raise LensFormatError(f"{where}: '{key}' must be >= 0, got {number}")
    if minimum is not None and number < minimum:
        raise LensFormatError(f"{where}: '{key}' must be >= {minimum:g}, got {number:g}")
    if maximum is not None and number > maximum:
        raise LensFormatError(f"{where}: '{key}' must be <= {maximum:g}, got {number:g}")
    return number


def _parse_coating(value: Any, where: str) -> CoatingSpec | None:
    if isinstance(value, str):
        key = value.strip().lower()
        if key == "default":
            return None
        if key == "none":
            return UNCOATED
        if key == "mgf2":
            return DEFAULT_COATING
        raise LensFormatError(f"{where}: unknown coating {value!r}; valid: \"default\", \"none\", \"MgF2\" or a table")
    if isinstance(value, Mapping):
        unknown = set(value) - {"quarter_wave", "wavelength_nm", "layers", "name"}
        if unknown:
            raise LensFormatError(f"{where}: unknown coating keys {sorted(unknown)}; valid: quarter_wave, wavelength_nm, layers, name")
        name = str(value.get("name", ""))
        if "quarter_wave" in value:
            index = _number(value["quarter_wave"], where, "coating.quarter_wave", minimum=COATING_INDEX_RANGE[0], maximum=COATING_INDEX_RANGE[1])
            wavelength = _number(value.get("wavelength_nm", 550.0), where, "coating.wavelength_nm", minimum=100.0, maximum=20000.0)
            return CoatingSpec.quarter_wave(index, wavelength, name)
        if "layers" in value:
            if not isinstance(value["layers"], list):
                raise LensFormatError(f"{where}: coating 'layers' must be a list of [index, thickness_nm] pairs, got {value['layers']!r}")
            layers = []
            for k, layer in enumerate(value["layers"]):
                if not (isinstance(layer, list) and len(layer) == 2):
                    raise LensFormatError(f"{where}: coating layer {k} must be [index, thickness_nm], got {layer!r}")
                layers.append(
                    CoatingLayerSpec(
                        _number(layer[0], where, f"coating layer {k} index", minimum=COATING_INDEX_RANGE[0], maximum=COATING_INDEX_RANGE[1]),
                        _number(layer[1], where, f"coating layer {k} thickness_nm", nonnegative=True, maximum=MAX_COATING_THICKNESS_NM),
                    )
                )
            return CoatingSpec(tuple(layers), name)
        raise LensFormatError(f"{where}: a coating table needs 'quarter_wave' or 'layers'")
    raise LensFormatError(f"{where}: 'coating' must be a string or a table, got {value!r}")


def _parse_surface(row: Any, where: str) -> SurfaceSpec:
    if not isinstance(row, Mapping):
        raise LensFormatError(f"{where}: each surface must be a table {{radius = ..., ...}}, got {row!r}")
    unknown = set(row) - set(_SURFACE_KEYS)
    if unknown:
        valid = ", ".join(sorted(_SURFACE_KEYS))
        raise LensFormatError(f"{where}: unknown key(s) {sorted(unknown)}; valid keys: {valid}")
    for required in ("radius", "thickness", "semi_aperture"):
        if required not in row:
            raise LensFormatError(f"{where}: missing required key '{required}' ({_SURFACE_KEYS[required]})")

    radius_value = row["radius"]
    if isinstance(radius_value, str):
        if radius_value.strip().lower() not in ("flat", "inf", "infinity"):
            raise LensFormatError(f"{where}: 'radius' must be a number or \"flat\", got {radius_value!r}")
        radius = math.inf
    else:
        radius = _number(radius_value, where, "radius")
        if radius == 0.0:
            radius = math.inf
        elif abs(radius) < 1e-3:
            raise LensFormatError(f"{where}: 'radius' {radius:g} mm is too small for a lens surface (|radius| >= 0.001 mm, or 0 / \"flat\" for a plane)")

    thickness_value = row["thickness"]
    if isinstance(thickness_value, list):
        if not thickness_value:
            raise LensFormatError(f"{where}: 'thickness' list is empty")
        thicknesses = tuple(_number(t, where, "thickness", nonnegative=True, maximum=MAX_LENGTH_MM) for t in thickness_value)
    else:
        thicknesses = (_number(thickness_value, where, "thickness", nonnegative=True, maximum=MAX_LENGTH_MM),)

    semi = row["semi_aperture"]
    if isinstance(semi, str) and semi.strip().lower() in ("auto", "derive"):
        semi_aperture = math.nan
    else:
        semi_aperture = _number(semi, where, "semi_aperture", positive=True, maximum=MAX_LENGTH_MM)

    kind = row.get("kind", "spherical")
    if kind not in SURFACE_KINDS:
        raise LensFormatError(f"{where}: unknown kind {kind!r}; valid: {', '.join(SURFACE_KINDS)}")
    conic = _number(row.get("conic", 0.0), where, "conic", minimum=-1e4, maximum=1e4)
    aspheric = row.get("aspheric", [])
    if not isinstance(aspheric, list):
        raise LensFormatError(f"{where}: 'aspheric' must be a list [A4, A6, ...]")
    aspheric_coefficients = tuple(_number(a, where, "aspheric") for a in aspheric)
    while aspheric_coefficients and aspheric_coefficients[-1] == 0.0:
        aspheric_coefficients = aspheric_coefficients[:-1]

    if math.isfinite(radius) and math.isfinite(semi_aperture) and conic == 0.0 and not aspheric_coefficients:
        if semi_aperture > abs(radius):
            raise LensFormatError(
                f"{where}: semi_aperture {semi_aperture} mm is larger than the sphere allows (|radius| = {abs(radius)} mm)"
            )

    medium_name = row.get("medium", None)
    n_d = row.get("n_d", None)
    v_d = row.get("v_d", None)
    if (n_d is None) != (v_d is None) and medium_name in (None, "air"):
        raise LensFormatError(f"{where}: a model glass needs both 'n_d' and 'v_d'")
    n_d = None if n_d is None else _number(n_d, where, "n_d", minimum=1.0, maximum=4.0)
    v_d = None if v_d is None else _number(v_d, where, "v_d", positive=True, maximum=1000.0)
    if medium_name is not None and not isinstance(medium_name, str):
        raise LensFormatError(f"{where}: 'medium' must be a string, got {medium_name!r}")
    if medium_name is None or medium_name.strip().lower() == "air":
        if medium_name is not None and n_d is not None:
            raise LensFormatError(f"{where}: medium \"air\" cannot have n_d/v_d")
        medium = MediumSpec(n_d=n_d, v_d=v_d) if n_d is not None else MediumSpec()
    else:
        catalog, _, glass = medium_name.strip().rpartition(":")
        medium = MediumSpec(glass=glass.strip(), catalog=catalog.strip().upper() or None, n_d=n_d, v_d=v_d)

    coating = _parse_coating(row["coating"], where) if "coating" in row else None
    is_stop = row.get("stop", False)
    if not isinstance(is_stop, bool):
        raise LensFormatError(f"{where}: 'stop' must be true or false")
    label = str(row.get("label", "")) or where
    return SurfaceSpec(
        radius_mm=radius,
        thicknesses_mm=thicknesses,
        medium=medium,
        semi_aperture_mm=semi_aperture,
        kind=kind,
        conic=conic,
        aspheric_coefficients=aspheric_coefficients,
        coating=coating,
        is_stop=is_stop,
        label=label,
    )


def parse_lens_toml(text: str, filename: str = "<string>") -> LensPrescription:
    """Parse a lens description in the jaxflare TOML format (see ``lenses/FORMAT.md``)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise LensFormatError(f"{filename}: not valid TOML: {error}") from None
    unknown = set(data) - set(_TOP_LEVEL_KEYS)
    if unknown:
        raise LensFormatError(f"{filename}: unknown key(s) {sorted(unknown)}; valid keys: {', '.join(sorted(_TOP_LEVEL_KEYS))}")
    if "surfaces" not in data or not isinstance(data["surfaces"], list) or not data["surfaces"]:
        raise LensFormatError(f"{filename}: missing 'surfaces' (a non-empty list of surface rows)")
    if len(data["surfaces"]) > MAX_SURFACES:
        raise LensFormatError(f"{filename}: {len(data['surfaces'])} surfaces; a lens may have at most {MAX_SURFACES}")
    where = _Where(filename, _surface_line_numbers(text))
    surfaces = tuple(_parse_surface(row, where.surface(k)) for k, row in enumerate(data["surfaces"]))

    zoom_counts = {len(s.thicknesses_mm) for s in surfaces}
    num_zoom = max(zoom_counts)
    if len(zoom_counts) > 1:
        for k, s in enumerate(surfaces):
            if len(s.thicknesses_mm) not in (1, num_zoom):
                raise LensFormatError(
                    f"{where.surface(k)}: {len(s.thicknesses_mm)} thicknesses, but other surfaces give {num_zoom} zoom positions"
                )
        surfaces = tuple(
            dataclasses.replace(s, thicknesses_mm=s.thicknesses_mm * num_zoom) if len(s.thicknesses_mm) == 1 else s
            for s in surfaces
        )

    stops = [k for k, s in enumerate(surfaces) if s.is_stop]
    if len(stops) != 1:
        raise LensFormatError(f"{filename}: exactly one surface must have 'stop = true', found {len(stops)}")

    name = data.get("name", os.path.splitext(os.path.basename(filename))[0])
    for key in ("name", "source", "notes"):
        if key in data and not isinstance(data[key], str):
            raise LensFormatError(f"{filename}: '{key}' must be a string, got {data[key]!r}")
    focal = data.get("focal_length_mm")
    stated_focal_lengths: tuple[float, ...] = ()
    stated_focal: float | None = None
    if isinstance(focal, list):
        stated_focal_lengths = tuple(_number(f, filename, "focal_length_mm", positive=True) for f in focal)
        if len(stated_focal_lengths) != num_zoom:
            raise LensFormatError(f"{filename}: 'focal_length_mm' lists {len(stated_focal_lengths)} values for {num_zoom} zoom positions")
        stated_focal = stated_focal_lengths[0]
    elif focal is not None:
        stated_focal = _number(focal, filename, "focal_length_mm", positive=True)
    focal_plane = data.get("focal_length_plane", "y")
    if focal_plane not in ("x", "y"):
        raise LensFormatError(f"{filename}: 'focal_length_plane' must be \"x\" or \"y\", got {focal_plane!r}")
    f_number = data.get("f_number")
    f_number = None if f_number is None else _number(f_number, filename, "f_number", minimum=F_NUMBER_RANGE[0], maximum=F_NUMBER_RANGE[1])
    pupil = data.get("entrance_pupil_diameter_mm")
    pupil = None if pupil is None else _number(pupil, filename, "entrance_pupil_diameter_mm", positive=True, maximum=MAX_LENGTH_MM)
    sensor = data.get("sensor_mm", [36.0, 24.0])
    if not (isinstance(sensor, list) and len(sensor) == 2):
        raise LensFormatError(f"{filename}: 'sensor_mm' must be [width, height]")
    blades = check_blades(data.get("aperture_blades", 0), filename)
    catalogs = data.get("glass_catalogs", [])
    if not isinstance(catalogs, list) or not all(isinstance(c, str) for c in catalogs):
        raise LensFormatError(f"{filename}: 'glass_catalogs' must be a list of catalog names")
    prescription = LensPrescription(
        name=str(name),
        surfaces=surfaces,
        source=str(data.get("source", "")),
        stated_focal_length_mm=stated_focal,
        stated_focal_lengths_mm=stated_focal_lengths,
        stated_focal_length_plane=focal_plane,
        stated_f_number=f_number,
        entrance_pupil_diameter_mm=pupil,
        sensor_width_mm=_number(sensor[0], filename, "sensor_mm[0]", positive=True, maximum=1000.0),
        sensor_height_mm=_number(sensor[1], filename, "sensor_mm[1]", positive=True, maximum=1000.0),
        aperture_blades=blades,
        aperture_rotation_deg=_number(data.get("aperture_rotation_deg", 0.0), filename, "aperture_rotation_deg"),
        design_wavelength_nm=_number(data.get("design_wavelength_nm", 587.56), filename, "design_wavelength_nm", minimum=100.0, maximum=20000.0),
        notes=str(data.get("notes", "")),
        glass_catalogs=tuple(c.upper() for c in catalogs),
        path=filename,
    )
    check_prescription(prescription)
    return prescription


def read_lens_toml(path: str | os.PathLike) -> LensPrescription:
    """Read a lens file in the jaxflare TOML format."""
    path = os.fspath(path)
    return parse_lens_toml(read_text_file(path, "lens file", LensFormatError), path)


def _toml_number(value: float) -> str:
    return repr(float(value))


def lens_toml_text(prescription: LensPrescription) -> str:
    """Write a prescription back in the jaxflare TOML format (coatings and metadata included)."""

    def quote(text: str) -> str:
        return '"' + text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'

    lines = [f"name = {quote(prescription.name)}"]
    if prescription.source:
        lines.append(f"source = {quote(prescription.source)}")
    if prescription.stated_focal_lengths_mm:
        lines.append("focal_length_mm = [" + ", ".join(_toml_number(f) for f in prescription.stated_focal_lengths_mm) + "]")
    elif prescription.stated_focal_length_mm is not None:
        lines.append(f"focal_length_mm = {_toml_number(prescription.stated_focal_length_mm)}")
    if prescription.stated_focal_length_plane != "y":
        lines.append(f"focal_length_plane = {quote(prescription.stated_focal_length_plane)}")
    if prescription.stated_f_number is not None:
        lines.append(f"f_number = {_toml_number(prescription.stated_f_number)}")
    if prescription.entrance_pupil_diameter_mm is not None:
        lines.append(f"entrance_pupil_diameter_mm = {_toml_number(prescription.entrance_pupil_diameter_mm)}")
    lines.append(f"sensor_mm = [{_toml_number(prescription.sensor_width_mm)}, {_toml_number(prescription.sensor_height_mm)}]")
    lines.append(f"aperture_blades = {prescription.aperture_blades}")
    lines.append(f"aperture_rotation_deg = {_toml_number(prescription.aperture_rotation_deg)}")
    lines.append(f"design_wavelength_nm = {_toml_number(prescription.design_wavelength_nm)}")
    if prescription.glass_catalogs:
        lines.append("glass_catalogs = [" + ", ".join(quote(c) for c in prescription.glass_catalogs) + "]")
    if prescription.notes:
        lines.append(f"notes = {quote(prescription.notes)}")
    lines.append("")
    lines.append("surfaces = [")
    for surface in prescription.surfaces:
        radius = '"flat"' if math.isinf(surface.radius_mm) else _toml_number(surface.radius_mm)
        parts = [f"radius = {radius}"]
        if len(surface.thicknesses_mm) == 1:
            parts.append(f"thickness = {_toml_number(surface.thicknesses_mm[0])}")
        else:
            parts.append("thickness = [" + ", ".join(_toml_number(t) for t in surface.thicknesses_mm) + "]")
        medium = surface.medium
        if medium.glass is not None:
            parts.append(f"medium = {quote((medium.catalog + ':' if medium.catalog else '') + medium.glass)}")
        if medium.n_d is not None:
            parts.append(f"n_d = {_toml_number(medium.n_d)}, v_d = {_toml_number(medium.v_d)}")
        semi = '"auto"' if math.isnan(surface.semi_aperture_mm) else _toml_number(surface.semi_aperture_mm)
        parts.append(f"semi_aperture = {semi}")
        if surface.kind != "spherical":
            parts.append(f"kind = {quote(surface.kind)}")
        if surface.conic:
            parts.append(f"conic = {_toml_number(surface.conic)}")
        if surface.aspheric_coefficients:
            parts.append("aspheric = [" + ", ".join(_toml_number(a) for a in surface.aspheric_coefficients) + "]")
        if surface.coating is not None:
            layers = ", ".join(f"[{_toml_number(l.index)}, {_toml_number(l.thickness_nm)}]" for l in surface.coating.layers)
            name = f", name = {quote(surface.coating.name)}" if surface.coating.name else ""
            parts.append(f"coating = {{ layers = [{layers}]{name} }}")
        if surface.is_stop:
            parts.append("stop = true")
        lines.append("  { " + ", ".join(parts) + " },")
    lines.append("]")
    return "\n".join(lines) + "\n"
