"""Importers for the lens data other flare tools ship, each producing a :class:`LensPrescription`.

Formats (front to sensor, lengths in mm, the medium given after each surface):

- **flaresim / PhotonsToPhotos** ``.lens``: ``name:`` and ``focal_length:`` lines, then after
  ``surfaces:`` one row ``radius thickness ior abbe semi_ap coating [type [radius_y]]`` per
  surface; ``stop`` (or ``STOP``) as the radius marks the aperture stop, ``0`` or ``inf`` a plane;
  ``coating`` is the number of anti-reflection layers (0 uncoated); ``type`` is ``sph``, ``cyl_x``
  (cylinder axis along x: power in y, jaxflare's ``cylindrical_y``), ``cyl_y`` (power in x,
  ``cylindrical_x``) or ``toric`` (not supported). The header comments of the converted
  PhotonsToPhotos files state the f-number (``f/1.4``), which is read. Most of those files hold
  *diameters* in the ``semi_ap`` column; the column is read as written, and
  ``semi_aperture="diameter"`` or ``"auto"`` (see :func:`jaxflare.load_lens`) says otherwise.
- **realflare** JSON (``resources/model/*/*.json``): ``lens_elements`` with ``radius`` (0 =
  plane), ``distance`` (thickness), ``refractive_index``, ``abbe_nr``, ``height`` (semi-aperture),
  and ``aperture_index`` (the stop element), ``focal_length``, ``fstop``.
- **lentil** JSON (``polynomial-optics/database/lenses.json``): a database of lenses by id; pick
  one with ``lenses.json#0001`` (or give a file that holds one entry). Elements come from
  ``optical-elements-patent`` (else ``-adjusted``): ``radius``, ``thickness`` (a number, or one
  per zoom position), ``material`` (``air``, ``iris`` for the stop, ``abbe`` or a glass name),
  ``ior``, ``abbe``, ``housing-radius`` (semi-aperture), ``lens-geometry`` (``spherical``,
  ``cyl-y`` = power in x, ``cyl-x`` = power in y; ``aspherical`` with an equation is not
  supported).
- **OpenLensFlare** XML (``<opticalSystem>``): ``<element>`` with ``type`` (``lensSpherical``,
  ``apertureStop``, ``sensor``; ``lensAspherical`` holds no coefficients and is refused),
  ``height`` (semi-aperture), ``thickness``, ``radius`` (0 = plane), ``refractiveIndex``,
  ``abbeNumber``, ``coatingLambda``/``coatingIor`` (a quarter-wave layer), and the system's
  ``fnumber``, ``effectiveFocalLength``, ``filmWidth``, ``filmHeight``.
- **pbrt** ``.dat`` (pbrt-v3/v4 ``RealisticCamera``): rows ``radius thickness ior aperture``
  where ``aperture`` is a *diameter* (halved here, by the format's definition), a radius of 0
  marks the stop and an index of 0 means air. pbrt focuses the film itself, so a last thickness
  of 0 is replaced by the paraxial back focal distance.

What a format leaves open is settled explicitly and written to the prescription's ``notes``:
a missing iris becomes the surface that limits the axial beam, an Abbe number of 0 a medium
without dispersion, a missing back focus the paraxial one. Anything that cannot be modelled is a
:class:`LensFormatError` naming the file, the line or element and what is wrong.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
from collections.abc import Mapping
from typing import Any
from xml.etree import ElementTree

from ..optics import AIR, UNCOATED, CoatingSpec, LensFormatError, LensPrescription, MediumSpec, SurfaceSpec
from ._first_order import limiting_surface, marginal_ray
from ._text_input import decode_text, read_input_bytes

__all__ = ["LENS_FORMATS", "read_flaresim_lens", "read_lentil_json", "read_openlensflare_xml", "read_pbrt_dat", "read_realflare_json"]

LENS_FORMATS = {
    ".lens": "flaresim / PhotonsToPhotos lens table",
    ".json": "realflare lens model or lentil lens database",
    ".xml": "OpenLensFlare optical system",
    ".dat": "pbrt RealisticCamera lens table",
}
"""File extensions of the importers here (besides jaxflare's ``.toml`` and Zemax ``.zmx``)."""

_F_NUMBER = re.compile(r"\bf\s*/\s*(\d+(?:\.\d+)?)", re.IGNORECASE)


# --------------------------------------------------------------------------- helpers


def _text(path: str, what: str) -> str:
    return decode_text(read_input_bytes(path, what, LensFormatError), path, what, LensFormatError)


def _number(value: Any, where: str, what: str, *, minimum: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise LensFormatError(f"{where}: {what} must be a number, got {value!r}")
    try:
        number = float(value)
    except ValueError:
        raise LensFormatError(f"{where}: {what} must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise LensFormatError(f"{where}: {what} must be finite, got {value!r}")
    if minimum is not None and number < minimum:
        raise LensFormatError(f"{where}: {what} must be >= {minimum:g}, got {number:g}")
    return number


def _medium(index: float, abbe: float | None, where: str, glass: str | None = None) -> MediumSpec:
    """Air for an index of 1 (or 0, pbrt's air), else a model glass (no dispersion without an Abbe
    number), or a named glass with the stated index and Abbe number to check it against."""
    if index == 0.0 or abs(index - 1.0) < 1e-6:
        return AIR
    if not 1.0 < index < 4.0:
        raise LensFormatError(f"{where}: refractive index {index:g} is outside the valid range 1 .. 4 (1 = air)")
    v_d = abbe if abbe is not None and abbe > 0.0 else None
    if glass:
        return MediumSpec(glass=glass, n_d=index, v_d=v_d)
    return MediumSpec(n_d=index, v_d=v_d)


def _radius(value: float) -> float:
    return math.inf if value == 0.0 else value


def _choose_stop(surfaces: list[SurfaceSpec], where: str, notes: list[str], why: str) -> list[SurfaceSpec]:
    """Mark as stop the surface that limits an axial beam (from the given semi-apertures and the
    media's d-line indices), and say so in ``notes``."""
    indices = [1.0 if s.medium.is_air else float(s.medium.n_d or 1.5) for s in surfaces]
    heights, _, _ = marginal_ray([s.curvature_per_mm for s in surfaces], [s.thicknesses_mm[0] for s in surfaces], indices)
    stop = limiting_surface(heights, [s.semi_aperture_mm for s in surfaces])
    if stop is None:
        raise LensFormatError(f"{where}: {why}, and without semi-apertures no surface can be chosen as the aperture stop")
    notes.append(f"{why}: the aperture stop is {surfaces[stop].label}, the surface that limits the axial beam (paraxial, d line)")
    return [s if k != stop else dataclasses.replace(s, is_stop=True) for k, s in enumerate(surfaces)]


def _f_number_in(text: str) -> float | None:
    match = _F_NUMBER.search(text)
    return float(match.group(1)) if match else None


# --------------------------------------------------------------------------- flaresim .lens


def read_flaresim_lens(path: str | os.PathLike) -> LensPrescription:
    """Read a flaresim / PhotonsToPhotos ``.lens`` file (see the module docstring)."""
    filename = os.fspath(path)
    base = os.path.basename(filename)
    text = _text(filename, ".lens file")
    name, focal, header, surfaces, notes = "", None, [], [], []
    in_surfaces = False
    f_number = None
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            if not in_surfaces:
                header.append(line.lstrip("# ").strip())
            continue
        where = f"{filename}:{lineno}"
        if not in_surfaces:
            key, sep, value = line.partition(":")
            key = key.strip().lower()
            if not sep:
                raise LensFormatError(f"{where}: expected 'name:', 'focal_length:' or 'surfaces:', got {line[:40]!r}")
            if key == "name":
                name = value.strip()
            elif key == "focal_length":
                focal = _number(value.strip(), where, "focal_length", minimum=0.0) or None
            elif key == "surfaces":
                in_surfaces = True
            else:
                notes.append(f"{base}:{lineno}: key {key!r} is not a flaresim key; skipped")
            continue
        tokens = line.split("#", 1)[0].split()
        if len(tokens) < 6:
            raise LensFormatError(f"{where}: a surface row needs radius thickness ior abbe semi_ap coating, got {len(tokens)} value(s)")
        label = f"{base}:{lineno}: surface {len(surfaces)}"
        is_stop = tokens[0].lower() == "stop"
        radius = math.inf if is_stop or tokens[0].lower() in ("inf", "infinity", "flat") else _radius(_number(tokens[0], where, "radius"))
        thickness = _number(tokens[1], where, "thickness", minimum=0.0)
        index = _number(tokens[2], where, "ior")
        abbe = _number(tokens[3], where, "abbe", minimum=0.0)
        semi = _number(tokens[4], where, "semi_ap", minimum=0.0)
        layers = tokens[5]
        if not re.fullmatch(r"\d+", layers):
            raise LensFormatError(f"{where}: coating must be a whole number of layers (0 = uncoated), got {layers!r}")
        kind = "spherical"
        if len(tokens) > 6:
            shape = tokens[6].lower()
            if shape in ("cyl_y", "cylinder_y"):
                kind = "cylindrical_x"  # cylinder axis along y: power in x
            elif shape in ("cyl_x", "cylinder_x"):
                kind = "cylindrical_y"
            elif shape == "toric":
                raise LensFormatError(f"{where}: a toric surface (power in x and y) is not supported; only spheres and cylinders")
            elif shape not in ("sph", "spherical"):
                raise LensFormatError(f"{where}: unknown surface type {tokens[6]!r}; valid: sph, cyl_x, cyl_y")
        coating = UNCOATED if int(layers) == 0 else CoatingSpec.quarter_wave(1.38, 550.0, f"flaresim {layers}-layer coating as MgF2 quarter-wave @ 550 nm")
        surfaces.append(
            SurfaceSpec(
                radius_mm=radius, thicknesses_mm=(thickness,), medium=_medium(index, abbe, where), semi_aperture_mm=semi if semi > 0 else math.nan,
                kind=kind, coating=coating, is_stop=is_stop, label=label,
            )
        )
    if not surfaces:
        raise LensFormatError(f"{filename}: no surface rows (expected a 'surfaces:' line followed by rows)")
    if any(s.coating is not UNCOATED for s in surfaces):
        notes.append("coating column: 0 = uncoated, 1 or more = one quarter-wave MgF2 layer at 550 nm (flaresim's single-layer model)")
    f_number = next((value for value in (_f_number_in(line) for line in header) if value), None)
    if f_number is not None:
        notes.append(f"f-number f/{f_number:g} read from the file's header comment")
    stops = [s for s in surfaces if s.is_stop]
    if len(stops) > 1:
        raise LensFormatError(f"{stops[1].label}: a second 'stop' row; a lens has one aperture stop")
    if not stops:
        surfaces = _choose_stop(surfaces, filename, notes, "the file has no 'stop' row")
    return LensPrescription(
        name=name or os.path.splitext(base)[0], surfaces=tuple(surfaces), source=f"flaresim .lens file {base}" + (f" ({header[0]})" if header else ""),
        stated_focal_length_mm=focal, stated_f_number=f_number, notes="\n".join(notes), path=filename,
    )


# --------------------------------------------------------------------------- realflare JSON


def _json(filename: str) -> Any:
    text = _text(filename, "JSON lens file")
    try:
        return json.loads(text)
    except json.JSONDecodeError as error:
        raise LensFormatError(f"{filename}:{error.lineno}: not valid JSON: {error.msg} (column {error.colno})") from None


def read_realflare_json(path: str | os.PathLike, data: Any = None) -> LensPrescription:
    """Read a realflare lens model (JSON with ``lens_elements``; see the module docstring)."""
    filename = os.fspath(path)
    base = os.path.basename(filename)
    data = _json(filename) if data is None else data
    elements = data.get("lens_elements") if isinstance(data, Mapping) else None
    if not isinstance(elements, list) or not elements:
        raise LensFormatError(f"{filename}: 'lens_elements' must be a non-empty list of elements")
    notes: list[str] = []
    stop_index = data.get("aperture_index")
    if stop_index is not None and (isinstance(stop_index, bool) or not isinstance(stop_index, int) or not 0 <= stop_index < len(elements)):
        raise LensFormatError(f"{filename}: 'aperture_index' must be an element index 0 .. {len(elements) - 1}, got {stop_index!r}")
    surfaces = []
    for k, element in enumerate(elements):
        where = f"{filename}: lens_elements[{k}]"
        if not isinstance(element, Mapping):
            raise LensFormatError(f"{where}: must be an object with radius, distance, refractive_index, abbe_nr, height")
        unknown = set(element) - {"radius", "distance", "refractive_index", "abbe_nr", "height", "coating", "name"}
        if unknown:
            notes.append(f"lens_elements[{k}]: keys {sorted(unknown)} are not realflare keys; skipped")
        for key in ("radius", "distance", "refractive_index"):
            if key not in element:
                raise LensFormatError(f"{where}: missing {key!r}")
        height = _number(element.get("height", 0.0), where, "height", minimum=0.0)
        surfaces.append(
            SurfaceSpec(
                radius_mm=_radius(_number(element["radius"], where, "radius")),
                thicknesses_mm=(_number(element["distance"], where, "distance", minimum=0.0),),
                medium=_medium(_number(element["refractive_index"], where, "refractive_index"), _number(element.get("abbe_nr") or 0.0, where, "abbe_nr"), where),
                semi_aperture_mm=height if height > 0 else math.nan,
                is_stop=k == stop_index,
                label=f"{base}: lens_elements[{k}]",
            )
        )
    if stop_index is None:
        surfaces = _choose_stop(surfaces, filename, notes, "the model has no 'aperture_index'")
    focal = data.get("focal_length")
    f_number = data.get("fstop")
    source = f"realflare lens model {base}" + (f", patent {data['patent_number']}" if data.get("patent_number") else "")
    return LensPrescription(
        name=str(data.get("name") or os.path.splitext(base)[0]), surfaces=tuple(surfaces), source=source,
        stated_focal_length_mm=_number(focal, filename, "focal_length", minimum=0.0) or None if focal is not None else None,
        stated_f_number=_number(f_number, filename, "fstop", minimum=0.0) or None if f_number is not None else None,
        notes="\n".join([str(data.get("notes") or "")] + notes).strip(), path=filename,
    )


# --------------------------------------------------------------------------- lentil JSON


def read_lentil_json(path: str | os.PathLike, lens_id: str | None = None, data: Any = None) -> LensPrescription:
    """Read one lens of a lentil lens database (``lenses.json``; ``lens_id`` picks the entry,
    needed when the file holds more than one)."""
    filename = os.fspath(path)
    base = os.path.basename(filename)
    data = _json(filename) if data is None else data
    if not isinstance(data, Mapping):
        raise LensFormatError(f"{filename}: a lentil lens database is an object of lenses by id")
    if any(key.startswith("optical-elements") for key in data):
        entry, lens_id = data, lens_id or os.path.splitext(base)[0]
    else:
        ids = sorted(key for key, value in data.items() if isinstance(value, Mapping))
        if lens_id is None:
            if len(ids) != 1:
                raise LensFormatError(f"{filename}: the database holds {len(ids)} lenses; pick one as {base}#ID, with ID one of {', '.join(ids[:30])}")
            lens_id = ids[0]
        if lens_id not in data or not isinstance(data[lens_id], Mapping):
            raise LensFormatError(f"{filename}: no lens {lens_id!r} in the database; ids: {', '.join(ids[:30])}")
        entry = data[lens_id]
    key = "optical-elements-patent" if entry.get("optical-elements-patent") else "optical-elements-adjusted"
    elements = entry.get(key)
    where_lens = f"{filename}#{lens_id}"
    if not isinstance(elements, list) or not elements:
        raise LensFormatError(f"{where_lens}: no 'optical-elements-patent' or 'optical-elements-adjusted' list")
    notes: list[str] = [f"elements from {key!r}"]
    surfaces = []
    zoom_positions = 1
    for k, element in enumerate(elements):
        where = f"{where_lens}: {key}[{k}]"
        if not isinstance(element, Mapping):
            raise LensFormatError(f"{where}: must be an object")
        for required in ("radius", "thickness", "material"):
            if required not in element:
                raise LensFormatError(f"{where}: missing {required!r}")
        material = str(element["material"])
        geometry = str(element.get("lens-geometry") or "spherical").lower()
        if element.get("aspherical-equation") not in (None, "", []):
            raise LensFormatError(f"{where}: aspherical equations are not supported")
        kind = {"spherical": "spherical", "cyl-y": "cylindrical_x", "cyl-x": "cylindrical_y"}.get(geometry)
        if kind is None:
            raise LensFormatError(f"{where}: lens-geometry {geometry!r} is not supported; valid: spherical, cyl-x, cyl-y")
        thickness = element["thickness"]
        if isinstance(thickness, list):
            if not thickness:
                raise LensFormatError(f"{where}: 'thickness' list is empty")
            thicknesses = tuple(_number(t, where, "thickness", minimum=0.0) for t in thickness)
            zoom_positions = max(zoom_positions, len(thicknesses))
        else:
            thicknesses = (_number(thickness, where, "thickness", minimum=0.0),)
        is_stop = material.lower() == "iris"
        if material.lower() in ("air", "iris"):
            medium = AIR
        else:
            if element.get("ior") is None:
                raise LensFormatError(f"{where}: material {material!r} needs 'ior'")
            index = _number(element["ior"], where, "ior")
            abbe = _number(element["abbe"], where, "abbe") if element.get("abbe") is not None else None
            medium = _medium(index, abbe, where, glass=None if material.lower() in ("abbe", "unknown", "") else material)
        semi = _number(element.get("housing-radius") or 0.0, where, "housing-radius", minimum=0.0)
        surfaces.append(
            SurfaceSpec(
                radius_mm=math.inf if is_stop else _radius(_number(element["radius"], where, "radius")), thicknesses_mm=thicknesses,
                medium=medium, semi_aperture_mm=semi if semi > 0 else math.nan, kind=kind if not is_stop else "spherical", is_stop=is_stop,
                label=f"{base}#{lens_id}: {key}[{k}]",
            )
        )
    if zoom_positions > 1:
        surfaces = [s if len(s.thicknesses_mm) != 1 else dataclasses.replace(s, thicknesses_mm=s.thicknesses_mm * zoom_positions) for s in surfaces]
        if any(len(s.thicknesses_mm) != zoom_positions for s in surfaces):
            raise LensFormatError(f"{where_lens}: thickness lists of different lengths (zoom positions)")
    if sum(s.is_stop for s in surfaces) > 1:
        raise LensFormatError(f"{where_lens}: more than one 'iris' element")
    if not any(s.is_stop for s in surfaces):
        surfaces = _choose_stop(surfaces, where_lens, notes, "the lens has no 'iris' element")
    focal = entry.get("focal-length-mm-patent") if key == "optical-elements-patent" else None
    kinds = {s.kind for s in surfaces} - {"spherical"}
    plane = "y"
    if len(kinds) == 1 and focal is not None:
        # an anamorphic: the stated focal length is the squeezed meridian's, the one with cylinder power
        plane = "x" if kinds == {"cylindrical_x"} else "y"
        notes.append(f"anamorphic (cylinders with power in {plane} only): the stated focal length is read as the {plane}-plane focal length")
    name = " ".join(str(entry.get(k)) for k in ("company", "product-name") if entry.get(k)) or f"lentil lens {lens_id}"
    source = f"lentil lens database {base}, lens {lens_id}" + (f", patent {entry['patent-number']}" if entry.get("patent-number") else "")
    if entry.get("notes"):
        notes.insert(0, str(entry["notes"]))
    return LensPrescription(
        name=name, surfaces=tuple(surfaces), source=source,
        stated_focal_length_mm=_number(focal, where_lens, "focal-length-mm-patent", minimum=0.0) or None if focal is not None else None,
        stated_focal_length_plane=plane, notes="\n".join(notes), path=filename,
    )


# --------------------------------------------------------------------------- OpenLensFlare XML


def read_openlensflare_xml(path: str | os.PathLike) -> LensPrescription:
    """Read an OpenLensFlare optical system (XML with ``<opticalSystem>``; see the module docstring)."""
    filename = os.fspath(path)
    base = os.path.basename(filename)
    text = _text(filename, "XML lens file")
    if "<!DOCTYPE" in text or "<!ENTITY" in text:
        raise LensFormatError(f"{filename}: XML with a DOCTYPE or entities is not read (an OpenLensFlare file has none)")
    try:
        root = ElementTree.fromstring(text)
    except ElementTree.ParseError as error:
        line = error.position[0] if getattr(error, "position", None) else "?"
        raise LensFormatError(f"{filename}:{line}: not valid XML: {error}") from None
    if root.tag != "opticalSystem":
        raise LensFormatError(f"{filename}: expected an <opticalSystem> document, got <{root.tag}>")

    def value(node, tag: str, where: str, default: float | None = None) -> float:
        child = node.find(tag)
        if child is None or child.text is None or not child.text.strip():
            if default is None:
                raise LensFormatError(f"{where}: missing <{tag}>")
            return default
        return _number(child.text.strip(), where, f"<{tag}>")

    elements = root.findall("./elements/element")
    if not elements:
        raise LensFormatError(f"{filename}: no <elements><element> entries")
    surfaces, notes = [], []
    for k, element in enumerate(elements):
        where = f"{filename}: element {k}"
        kind = (element.findtext("type") or "").strip()
        if kind == "sensor":
            if k != len(elements) - 1:
                notes.append(f"element {k} is the sensor; the {len(elements) - k - 1} element(s) after it are ignored")
            break
        if kind == "lensAspherical":
            raise LensFormatError(f"{where}: lensAspherical elements hold no aspheric coefficients in the file; not supported")
        if kind not in ("lensSpherical", "apertureStop"):
            raise LensFormatError(f"{where}: unknown element type {kind!r}; valid: lensSpherical, apertureStop, sensor")
        height = value(element, "height", where, 0.0)
        wavelength, coating_index = value(element, "coatingLambda", where, 0.0), value(element, "coatingIor", where, 0.0)
        coating = None
        if kind == "lensSpherical":
            coating = CoatingSpec.quarter_wave(coating_index, wavelength, f"quarter-wave n={coating_index:g} @ {wavelength:g} nm") if wavelength > 0 and coating_index > 0 else UNCOATED
        surfaces.append(
            SurfaceSpec(
                radius_mm=math.inf if kind == "apertureStop" else _radius(value(element, "radius", where)),
                thicknesses_mm=(value(element, "thickness", where),),
                medium=AIR if kind == "apertureStop" else _medium(value(element, "refractiveIndex", where), value(element, "abbeNumber", where, 0.0), where),
                semi_aperture_mm=height if height > 0 else math.nan, coating=coating, is_stop=kind == "apertureStop", label=f"{base}: element {k} ({kind})",
            )
        )
    else:
        notes.append("no sensor element: the sensor is at the end of the last thickness")
    if not surfaces:
        raise LensFormatError(f"{filename}: no lens elements before the sensor")
    for k, s in enumerate(surfaces):
        if s.thicknesses_mm[0] < 0:
            raise LensFormatError(f"{s.label}: negative thickness {s.thicknesses_mm[0]}")
    if sum(s.is_stop for s in surfaces) > 1:
        raise LensFormatError(f"{filename}: more than one apertureStop element")
    if not any(s.is_stop for s in surfaces):
        surfaces = _choose_stop(surfaces, filename, notes, "the system has no apertureStop element")

    def system(tag: str) -> float | None:
        node = root.find(tag)
        if node is None or not (node.text or "").strip():
            return None
        number = _number(node.text.strip(), filename, f"<{tag}>")
        return number if number > 0 else None

    width, height = system("filmWidth"), system("filmHeight")
    return LensPrescription(
        name=(root.findtext("name") or "").strip() or os.path.splitext(base)[0], surfaces=tuple(surfaces), source=f"OpenLensFlare optical system {base}",
        stated_focal_length_mm=system("effectiveFocalLength"), stated_f_number=system("fnumber"),
        sensor_width_mm=width or 36.0, sensor_height_mm=height or 24.0, notes="\n".join(notes), path=filename,
    )


# --------------------------------------------------------------------------- pbrt .dat


def read_pbrt_dat(path: str | os.PathLike) -> LensPrescription:
    """Read a pbrt ``RealisticCamera`` lens table (``.dat``; see the module docstring)."""
    filename = os.fspath(path)
    base = os.path.basename(filename)
    text = _text(filename, "pbrt lens file")
    header, rows = [], []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            header.append(line.lstrip("# ").strip().strip('"').strip())
            continue
        tokens = line.split()
        where = f"{filename}:{lineno}"
        if len(tokens) != 4:
            raise LensFormatError(f"{where}: a row is 'radius thickness ior aperture', got {len(tokens)} value(s)")
        rows.append((where, f"{base}:{lineno}: surface {len(rows)}", [_number(t, where, what) for t, what in zip(tokens, ("radius", "thickness", "ior", "aperture"))]))
    if not rows:
        raise LensFormatError(f"{filename}: no lens rows")
    notes = ["the aperture column is a diameter (pbrt's definition): semi-apertures are half of it"]
    surfaces = []
    for where, label, (radius, thickness, index, aperture) in rows:
        if thickness < 0 or aperture < 0:
            raise LensFormatError(f"{where}: thickness and aperture must be >= 0")
        is_stop = radius == 0.0
        surfaces.append(
            SurfaceSpec(
                radius_mm=_radius(radius), thicknesses_mm=(thickness,), medium=AIR if is_stop else _medium(index, None, where),
                semi_aperture_mm=0.5 * aperture if aperture > 0 else math.nan, is_stop=is_stop, label=label,
            )
        )
    if sum(s.is_stop for s in surfaces) > 1:
        raise LensFormatError(f"{filename}: more than one row with radius 0 (the stop)")
    if not any(s.is_stop for s in surfaces):
        surfaces = _choose_stop(surfaces, filename, notes, "no row has radius 0 (pbrt's stop)")
    if any(not s.medium.is_air for s in surfaces):
        notes.append("pbrt gives no dispersion: every glass has its index at all wavelengths")
    if surfaces[-1].thicknesses_mm[0] == 0.0:
        indices = [1.0 if s.medium.is_air else float(s.medium.n_d) for s in surfaces]
        _, _, back_focus = marginal_ray([s.curvature_per_mm for s in surfaces], [s.thicknesses_mm[0] for s in surfaces], indices)
        if not (math.isfinite(back_focus) and back_focus > 0):
            raise LensFormatError(f"{filename}: the last thickness is 0 (pbrt focuses the film) and the lens has no real back focus")
        surfaces[-1] = dataclasses.replace(surfaces[-1], thicknesses_mm=(back_focus,))
        notes.append(f"the last thickness is 0 (pbrt focuses the film itself): the sensor is put at the paraxial back focus, {back_focus:.4f} mm")
    focal_match = re.search(r"(\d+(?:\.\d+)?)\s*mm", base)
    focal = float(focal_match.group(1)) if focal_match else None
    if focal is not None:
        notes.append(f"stated focal length {focal:g} mm read from the file name")
    f_number = next((value for value in (_f_number_in(line) for line in header) if value), None)
    return LensPrescription(
        name=header[0] if header else os.path.splitext(base)[0], surfaces=tuple(surfaces), source=f"pbrt lens file {base}" + (f" ({'; '.join(header[1:3])})" if len(header) > 1 else ""),
        stated_focal_length_mm=focal, stated_f_number=f_number, notes="\n".join(notes), path=filename,
    )


def read_json_lens(path: str | os.PathLike, lens_id: str | None = None) -> LensPrescription:
    """A JSON lens file: a realflare model (``lens_elements``) or a lentil database entry."""
    filename = os.fspath(path)
    data = _json(filename)
    if isinstance(data, Mapping) and "lens_elements" in data:
        if lens_id is not None:
            raise LensFormatError(f"{filename}: a realflare model holds one lens; '#{lens_id}' picks nothing")
        return read_realflare_json(filename, data)
    if isinstance(data, Mapping) and (
        any(key.startswith("optical-elements") for key in data)
        or any(isinstance(v, Mapping) and any(k.startswith("optical-elements") for k in v) for v in data.values())
    ):
        return read_lentil_json(filename, lens_id, data)
    raise LensFormatError(f"{filename}: not a lens JSON jaxflare knows: expected a realflare model ('lens_elements') or a lentil database ('optical-elements-...')")
