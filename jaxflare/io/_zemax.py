"""Zemax OpticStudio sequential ``.zmx`` import and export.

``.zmx`` is a line-oriented text file: a keyword of (usually) four capital letters and its
values. System records come first (``VERS``, ``MODE``, ``UNIT``, ``GCAT``, ``FNUM``/``ENPD``,
fields, wavelengths, ...), then one ``SURF n`` block per surface whose records are indented, then
the merit function, tolerance and multi-configuration (``MNUM`` + operand rows) sections.
OpticStudio writes UTF-16 (little-endian, with a BOM) by default; older versions and other
programs write ASCII / UTF-8. There is no current public specification. The reader sorts records
into three kinds:

* records it interprets (surface shapes, thicknesses, glasses, apertures, stop, units, system
  aperture, wavelengths, zoom configurations);
* records that cannot change the sequential geometry or the materials, skipped: display, report,
  ray-aiming, field, tolerance, merit-function, file-history and authoring records (``AUTH``,
  ``IWDP``, ``SSID``, ``LUID``, ``EERA``, ``STUD``, ``FCOM``, ``FSVY``, ``DBDT``, ``OEMA``, ...).
  Beyond the routine ones every file has (``_ROUTINE_SYSTEM_KEYWORDS``), the skipped keywords are
  listed in the prescription's ``notes``; so are keywords this reader does not know, with their
  lines, which are skipped too (OpticStudio's records that change the optics are all known here);
* constructs that change the optics but cannot be modelled (mirrors, coordinate breaks,
  tilts/decenters, obscurations and non-circular apertures, true toroids, gradient index,
  non-sequential parts, glass offsets, configuration operands other than thicknesses, thickness
  solves that would need a ray trace per zoom position, ...): a :class:`LensFormatError` naming
  the file, the line and the keyword, never dropped.

Apertures follow Zemax's own meaning. ``DIAM`` is a semi-diameter (often computed by
OpticStudio), and OpticStudio clips rays only where a surface has an aperture: ``CLAP`` (circular
aperture, its maximum radius) or ``FLAP`` (floating aperture, at the semi-diameter). In jaxflare
every semi-aperture clips, so:

* a surface with ``CLAP`` clips at its maximum radius, one with ``FLAP`` at its ``DIAM``;
* the stop's ``DIAM`` is the stop radius (OpticStudio sizes it from the system aperture);
* a refracting surface (the index changes) clips at the edge of its glass: the larger of its
  ``DIAM`` and its mechanical semi-diameter ``MEMA``;
* a dummy surface (the same medium on both sides, not the stop, no ``CLAP``/``FLAP``) has no
  effect on the rays at all, so it is dropped and its thickness added to the surface before
  (the notes list them);
* the system aperture is kept: ``FNUM`` as the stated f-number, ``ENPD`` as the entrance pupil
  diameter (:attr:`LensPrescription.entrance_pupil_diameter_mm`), ``FLOA`` as "the stop's own
  semi-diameter". Semi-apertures the file lacks are ``math.nan``, derived when the lens is built
  from that system aperture and the marginal and chief rays (reported in the lens notes).

Glass records: a model glass (``GLAS ___BLANK 1 0 nd vd ...`` or solve type 1) gives n_d and V_d;
a catalog glass gives its name only: the model columns OpticStudio keeps beside a catalog glass
are leftovers of an earlier model glass, not values the design states. A name the catalogs lack
is an error when the lens is built, unless it is mapped with ``glass_aliases`` (see
:func:`jaxflare.load_lens`) or a known suffix rule applies (``_MOLD``).

Conventions of the result are those of :mod:`jaxflare.optics._prescription` (millimetres, the object
surface ``SURF 0`` and the image surface dropped, the last thickness is the distance to the
sensor). The writer emits a plain ASCII file in the same record shapes (see :func:`zmx_text`).
"""

from __future__ import annotations

import codecs
import dataclasses
import math
import os
import re
from decimal import Decimal, InvalidOperation

from ..optics import AIR, LensFormatError, LensPrescription, MediumSpec, SurfaceSpec
from .._atomic import write_bytes_atomic
from ._text_input import check_text, read_input_bytes

__all__ = ["decode_zmx_bytes", "parse_zmx", "read_zmx", "write_zmx", "zmx_text"]

# ----------------------------------------------------------------------------- keyword tables

_UNIT_SCALE_TO_MM = {"MM": Decimal(1), "CM": Decimal(10), "IN": Decimal("25.4"), "INCH": Decimal("25.4"), "METER": Decimal(1000), "M": Decimal(1000)}

_SURFACE_TYPES = ("STANDARD", "EVENASPH", "TOROIDAL")

_ROUTINE_SYSTEM_KEYWORDS = frozenset(
    """
    VERS PFIL LANG ENVD GFAC RAIM PUSH SDMA OMMA FTYP ROPD HYPR PICB
    XFLN YFLN XFLD YFLD FWGN FWGT VDXN VDYN VCXN VCYN VANN ZVDX ZVDY ZVCX ZVCY ZVAN
    WWGT WWGN WAVN POLS GLRS GSTD NSCD COFN SUMM BLNK TOL DMFS PUPD
    MNCA MNEA MNCG MNEG MXCA MXEA MXCG MXEG RGLA TRAC TCMM EFFL
    """.split()
)
"""System records every OpticStudio file has that do not change the sequential optics: file
version, display/report flags, ray aiming, field definitions and vignetting factors, wavelength
weights, polarization, global reference surface, glass-substitution and default-merit-function
settings, non-sequential defaults, coating/scatter file names, notes on the merit function
(``BLNK``), tolerances (``TOL``). Skipped without a note. ``ENVD`` (temperature and pressure) is
accepted too: the glass models here are at 20 degC, 1 atm."""

_HARMLESS_SYSTEM_KEYWORDS = frozenset(
    """
    AUTH IWDP LUID EERA STUD FCOM FSVY DBDT
    """.split()
)
"""System records of newer OpticStudio versions (2020-2024) that do not change the sequential
optics: author, image-window and lens IDs, encircled-energy and student-edition settings, file
comments, the file-survey flag and the file's date and history (``DBDT``). Skipped and listed in
the notes."""

_HARMLESS_SURFACE_KEYWORDS = frozenset("FIMP HIDE MIRR SLAB POPS SCOL TCED VPAR VCON VDSZ PPAR PKUP SSID OEMA".split())
"""Surface records that do not change the optics: import flags, drawing (``HIDE``, ``SLAB``,
``SCOL``, ``MIRR`` = mirror *substrate* drawn for mirrors, present on every surface in files
OpticStudio writes; a reflecting surface is ``GLAS MIRROR``), physical-optics settings (``POPS``),
surface IDs (``SSID``), the edge-aperture drawing mode (``OEMA``), thermal expansion data (``TCED``;
nothing here is thermal), optimization variable flags (``V...``) and pickups of curvature /
parameters, whose resolved values are what ``CURV`` / ``PARM`` store."""

_ROUTINE_SURFACE_KEYWORDS = frozenset("FIMP HIDE MIRR SLAB POPS".split())
"""Surface records on every surface of an OpticStudio file: skipped without a note."""

_THICKNESS_SOLVES = frozenset("PZUP TCOM TOLE MAZH CAZH EDGE".split())
"""Thickness solves and pickups. ``DISZ`` stores the solved value of the active configuration, so
they are harmless in a one-configuration file; across zoom positions ``PZUP`` (pickup), ``TCOM``
(compensator) and ``TOLE`` (position) are evaluated, the ray-based ones are refused."""

_NONCIRCULAR_APERTURES = {
    "OBSC": "circular obscuration",
    "SQAP": "rectangular aperture",
    "SQOB": "rectangular obscuration",
    "ELAP": "elliptical aperture",
    "ELOB": "elliptical obscuration",
    "SPID": "spider",
    "UDAD": "user-defined aperture",
    "USAP": "user-defined aperture",
}

_SURFACE_KEYWORDS = (
    frozenset("TYPE CURV DISZ GLAS DIAM MEMA STOP CONI PARM XDAT YDAT COMM COAT CLAP FLAP OBDC SCBD GRIN".split())
    | _HARMLESS_SURFACE_KEYWORDS
    | _THICKNESS_SOLVES
    | frozenset(_NONCIRCULAR_APERTURES)
)

_HARMLESS_CONFIG_OPERANDS = frozenset("MOFF APER FVCX FVCY FVDX FVDY FVAN WAVE WLWT XFIE YFIE FLWT PRWV FLTP".split())
"""Multi-configuration operands that do not change the sequential optics: ``OFF`` rows (written
``MOFF``), the system aperture value, field vignetting factors, wavelengths and fields."""

_OPTICAL_CONFIG_OPERANDS = frozenset(
    """
    CRVT GLSS CONN PRAM SDIA MIND MABB MDPG IGNR TEMP PRES COTN PXDT PYDT XDAT YDAT
    CADX CADY CATX CATY CATZ CBDX CBDY CBTX CBTY CBTZ APMN APMX APDX APDY APTP NPAR NPOS
    """.split()
)
"""Multi-configuration operands that change the optics per configuration (curvature, glass,
conic, surface parameters, semi-diameter, model-glass data, ignored surfaces, environment,
coatings, tilts/decenters, apertures, non-sequential objects): refused."""

_INTERPRETED_SYSTEM_KEYWORDS = frozenset("SURF MODE UNIT NAME NOTE COMM GCAT FNUM ENPD OBNA FLOA ISNA WAVM WAVL PWAV MNUM THIC MOFF".split())

_NON_SEQUENTIAL_KEYWORDS = frozenset("NSOH NSOD NSOP NSCS NSOA NSOO NSOQ NSOS NSOU NSOV NSOW".split())

_KNOWN_SYSTEM_KEYWORDS = (
    _INTERPRETED_SYSTEM_KEYWORDS | _ROUTINE_SYSTEM_KEYWORDS | _HARMLESS_SYSTEM_KEYWORDS | _HARMLESS_CONFIG_OPERANDS
    | _OPTICAL_CONFIG_OPERANDS | _NON_SEQUENTIAL_KEYWORDS
) - {"COMM"}
"""System keywords: in a file whose surface records are not indented, one of these ends a SURF block."""

_WRITER_NOTE_PREFIX = "jaxflare:"
"""``NOTE`` lines starting with this are written by :func:`zmx_text` for its own reader (exact
radii, what was not exported); they are not added to ``notes`` on import."""

_RADIUS_HINT = re.compile(r"^jaxflare:\s+radius\s+SURF\s+(\d+)\s+(\S+)\s*$")
_STATED_GLASS_HINT = re.compile(r"^jaxflare:\s+stated\s+SURF\s+(\d+)\s+n_d\s+(\S+)\s+v_d\s+(\S+)\s*$")

# ----------------------------------------------------------------------------- decoding


def decode_zmx_bytes(data: bytes, filename: str = "<bytes>") -> str:
    """Decode the bytes of a ``.zmx`` file: UTF-16 with a BOM (LE or BE, OpticStudio's default),
    UTF-16 without a BOM (detected by its NUL bytes), UTF-8 with or without a BOM, and finally
    Windows-1252 for old 8-bit files. Text with control characters (a binary file) is a
    :class:`LensFormatError` naming the line."""
    return check_text(_decode_zmx(data, filename), filename, ".zmx file", LensFormatError)


def _decode_zmx(data: bytes, filename: str) -> str:
    try:
        if data.startswith(codecs.BOM_UTF8):
            return data[len(codecs.BOM_UTF8) :].decode("utf-8")
        if data.startswith(codecs.BOM_UTF16_LE):
            return data[2:].decode("utf-16-le")
        if data.startswith(codecs.BOM_UTF16_BE):
            return data[2:].decode("utf-16-be")
        sample = data[:4096]
        if b"\x00" in sample:
            odd_nuls = sample[1::2].count(0)
            even_nuls = sample[0::2].count(0)
            return data.decode("utf-16-le" if odd_nuls >= even_nuls else "utf-16-be")
    except UnicodeDecodeError as error:
        raise LensFormatError(f"{filename}: not a readable .zmx file (UTF-16 decoding failed: {error})") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return data.decode("cp1252", errors="replace")


# ----------------------------------------------------------------------------- reading


@dataclasses.dataclass
class _Rec:
    """One record: keyword (upper case), its value tokens, the raw text after the keyword, line."""

    keyword: str
    tokens: list[str]
    rest: str
    line: int


@dataclasses.dataclass
class _RawSurface:
    number: int
    line: int
    type: _Rec | None = None
    curv: _Rec | None = None
    disz: _Rec | None = None
    glas: _Rec | None = None
    diam: _Rec | None = None
    mema: _Rec | None = None
    clap: _Rec | None = None
    flap: _Rec | None = None
    coni: _Rec | None = None
    stop: _Rec | None = None
    comment: str | None = None
    coating: str | None = None
    parms: dict[int, _Rec] = dataclasses.field(default_factory=dict)
    xdat: dict[int, _Rec] = dataclasses.field(default_factory=dict)
    solves: list[_Rec] = dataclasses.field(default_factory=list)


class _Reader:
    def __init__(self, text: str, filename: str):
        self.filename = filename
        self.lines = text.lstrip("\ufeff").splitlines()
        self.surfaces: list[_RawSurface] = []
        self.surfaces_closed = False
        self.unit: _Rec | None = None
        self.name = ""
        self.notes: list[str] = []
        self.radius_hints: dict[int, str] = {}
        self.stated_glass: dict[int, tuple[str, str]] = {}
        self.note_paragraph = ""
        """n_d and V_d that :func:`zmx_text` recorded for a catalog glass (``NOTE jaxflare: stated``)."""
        self.catalogs: list[str] = []
        self.f_number: float | None = None
        self.wavelengths: dict[int, _Rec] = {}
        self.legacy_wavelengths: _Rec | None = None
        self.primary_wavelength: _Rec | None = None
        self.mnum: _Rec | None = None
        self.thic_rows: list[_Rec] = []
        self.entrance_pupil: _Rec | None = None
        self.aperture_kind = "FNUM"
        self.skipped: dict[str, int] = {}
        """Skipped known-harmless keywords (beyond the routine ones) and how often."""
        self.unknown: dict[str, list[int]] = {}
        """Skipped unknown keywords and their lines."""

    # -- helpers

    def error(self, line: int, message: str) -> LensFormatError:
        return LensFormatError(f"{self.filename}:{line}: {message}")

    def number(self, rec: _Rec, index: int, what: str = "value", default: str | None = None) -> float:
        token = rec.tokens[index] if index < len(rec.tokens) else default
        if token is None:
            raise self.error(rec.line, f"{rec.keyword}: missing {what}")
        value = _parse_float(token)
        if value is None or not math.isfinite(value):
            raise self.error(rec.line, f"{rec.keyword}: {what} must be a finite number, got {token!r}")
        return value

    def integer(self, rec: _Rec, index: int, what: str) -> int:
        value = self.number(rec, index, what)
        if value != int(value):
            raise self.error(rec.line, f"{rec.keyword}: {what} must be an integer, got {rec.tokens[index]!r}")
        return int(value)

    def decimal(self, rec: _Rec, index: int, what: str) -> Decimal:
        self.number(rec, index, what)  # validates
        return _parse_decimal(rec.tokens[index])

    def all_zero(self, rec: _Rec) -> bool:
        values = [_parse_float(t) for t in rec.tokens if not t.startswith('"')]
        return all(v == 0.0 for v in values if v is not None) and all(v is not None for v in values)

    # -- pass 1: records

    def read(self) -> None:
        block_indented: bool | None = None  # the indentation of the current SURF block's records
        for lineno, raw in enumerate(self.lines, 1):
            stripped = raw.strip()
            if not stripped:
                continue
            parts = stripped.split(None, 1)
            keyword = parts[0].upper()
            rest = parts[1].strip() if len(parts) > 1 else ""
            rec = _Rec(keyword, rest.split(), rest, lineno)
            indented = raw[:1].isspace()
            in_block = bool(self.surfaces) and not self.surfaces_closed
            if in_block and keyword != "SURF":
                if block_indented is None and (indented or keyword in _SURFACE_KEYWORDS):
                    block_indented = indented
                # Files indent surface records (OpticStudio) or not (older files and other
                # writers), some mix both: a record belongs to the block if it is indented like
                # the block's first one, or is no system keyword in a block that is not indented.
                if indented or (block_indented is False and keyword not in _KNOWN_SYSTEM_KEYWORDS):
                    self.surface_record(rec)
                    continue
            if indented and keyword in _SURFACE_KEYWORDS and keyword != "SURF":
                raise self.error(lineno, f"{parts[0]}: surface record outside a SURF block")
            if self.surfaces and keyword != "SURF":
                self.surfaces_closed = True
            if keyword == "SURF":
                block_indented = None
            self.system_record(rec, parts[0])
        self.end_note_paragraph()

    def end_note_paragraph(self) -> None:
        text = self.note_paragraph.strip()
        if text:
            self.notes.append(text)
        self.note_paragraph = ""

    def skip(self, rec: _Rec, known: bool) -> None:
        if known:
            self.skipped[rec.keyword] = self.skipped.get(rec.keyword, 0) + 1
        else:
            self.unknown.setdefault(rec.keyword, []).append(rec.line)

    def system_record(self, rec: _Rec, written: str) -> None:
        kw = rec.keyword
        if kw == "SURF":
            if self.surfaces_closed:
                raise self.error(rec.line, "SURF: surface block after the surface list ended")
            number = self.integer(rec, 0, "surface number")
            if number != len(self.surfaces):
                raise self.error(rec.line, f"SURF: expected surface {len(self.surfaces)}, got {number}")
            self.surfaces.append(_RawSurface(number, rec.line))
        elif kw == "MODE":
            mode = rec.tokens[0].upper() if rec.tokens else ""
            if mode != "SEQ":
                raise self.error(rec.line, f"MODE {rec.rest}: only sequential systems (MODE SEQ) are supported")
        elif kw == "UNIT":
            if not rec.tokens or rec.tokens[0].upper() not in _UNIT_SCALE_TO_MM:
                raise self.error(rec.line, f"UNIT: unknown lens unit {rec.rest!r}; known: MM, CM, IN, METER")
            self.unit = rec
        elif kw == "NAME":
            self.name = _unquote(rec.rest)
        elif kw in ("NOTE", "COMM"):
            text = _unquote(rec.rest)
            hint = _RADIUS_HINT.match(text)
            stated = _STATED_GLASS_HINT.match(text)
            if hint:
                self.radius_hints[int(hint.group(1))] = hint.group(2)
            elif stated:
                self.stated_glass[int(stated.group(1))] = (stated.group(2), stated.group(3))
            elif kw == "NOTE" and re.fullmatch(r"[04](\s.*)?", rec.rest):
                # OpticStudio's notes: "NOTE 0 text" holds up to 200 characters of a paragraph,
                # "NOTE 4" ends the paragraph
                if rec.rest[0] == "0":
                    self.note_paragraph += rec.rest[2:]
                else:
                    self.end_note_paragraph()
            elif not text.startswith(_WRITER_NOTE_PREFIX):
                self.notes.append(text)
        elif kw == "GCAT":
            self.catalogs.extend(t.upper() for t in rec.tokens)
        elif kw == "FNUM":
            value = self.number(rec, 0, "f-number")
            flag = self.integer(rec, 1, "f-number type") if len(rec.tokens) > 1 else 0
            # 0: image-space F/#, 1: paraxial working F/#; equal for an object at infinity in air.
            self.f_number = value if value > 0 and flag in (0, 1) else None
        elif kw == "ENPD":
            self.f_number = None
            self.aperture_kind = "ENPD"
            self.entrance_pupil = rec
        elif kw == "FLOA":
            self.f_number, self.entrance_pupil, self.aperture_kind = None, None, "FLOA"
        elif kw == "ISNA":  # image-space numerical aperture: F/# = 1 / (2 NA) in air
            value = self.number(rec, 0, "numerical aperture")
            self.f_number = 1.0 / (2.0 * value) if 0.0 < value < 1.0 else None
            self.entrance_pupil, self.aperture_kind = None, "ISNA"
        elif kw == "OBNA":  # object-space NA: no meaning for an object at infinity
            self.f_number, self.entrance_pupil, self.aperture_kind = None, None, "OBNA"
        elif kw == "WAVM":
            self.wavelengths[self.integer(rec, 0, "wavelength number")] = rec
        elif kw == "WAVL":
            self.legacy_wavelengths = rec
        elif kw == "PWAV":
            self.primary_wavelength = rec
        elif kw == "MNUM":
            self.mnum = rec
        elif kw == "THIC":
            self.thic_rows.append(rec)
        elif kw == "MOFF":  # an OFF row of the multi-configuration editor
            named = [t.strip('"').upper() for t in rec.tokens if t.startswith('"') and t.strip('"')]
            for operand in named:
                if operand in _OPTICAL_CONFIG_OPERANDS or operand == "THIC":
                    raise self.error(rec.line, f"MOFF: configuration row names operand {operand!r}; this multi-configuration layout is not supported")
        elif kw in _OPTICAL_CONFIG_OPERANDS:
            raise self.error(rec.line, f"{written}: multi-configuration operand {kw} changes the optics per configuration; only THIC (thickness) is supported")
        elif kw in _ROUTINE_SYSTEM_KEYWORDS or kw in _HARMLESS_CONFIG_OPERANDS:
            pass
        elif kw in _HARMLESS_SYSTEM_KEYWORDS:
            self.skip(rec, known=True)
        elif kw in _NON_SEQUENTIAL_KEYWORDS:
            raise self.error(rec.line, f"{written}: non-sequential objects are not supported")
        elif kw in _SURFACE_KEYWORDS:
            raise self.error(rec.line, f"{written}: surface keyword outside a SURF block (surface records are indented)")
        elif self.surfaces_closed and self.mnum is None and re.fullmatch(r"[A-Z][A-Z0-9]{3}", kw):
            pass  # a merit-function operand row: evaluates the design, does not change it
        elif self.mnum is not None and re.fullmatch(r"[A-Z][A-Z0-9]{3}", kw):
            # a configuration operand row this reader does not know: it might change the optics
            raise self.error(rec.line, f"{written}: unknown multi-configuration operand {kw!r}; only THIC (thickness) rows are supported")
        elif re.fullmatch(r"[A-Z][A-Z0-9]{2,3}", kw):
            self.skip(rec, known=False)
        else:
            raise self.error(rec.line, f"{written[:20]!r}: not a .zmx record (a keyword of 3-4 capital letters)")

    def surface_record(self, rec: _Rec) -> None:
        surf = self.surfaces[-1]
        kw = rec.keyword
        if kw == "TYPE":
            surf.type = rec
            kind = rec.tokens[0].upper() if rec.tokens else ""
            if kind == "COORDBRK":
                raise self.error(rec.line, "TYPE COORDBRK: coordinate breaks (tilts/decenters) are not supported")
            if kind not in _SURFACE_TYPES:
                raise self.error(rec.line, f"TYPE {rec.rest}: unsupported surface type; supported: {', '.join(_SURFACE_TYPES)}")
        elif kw == "CURV":
            surf.curv = rec
        elif kw == "DISZ":
            surf.disz = rec
        elif kw == "GLAS":
            surf.glas = rec
        elif kw == "DIAM":
            surf.diam = rec
        elif kw == "MEMA":
            surf.mema = rec
        elif kw == "CONI":
            surf.coni = rec
        elif kw == "STOP":
            surf.stop = rec
        elif kw == "COMM":
            surf.comment = _unquote(rec.rest)
        elif kw == "COAT":
            surf.coating = rec.tokens[0] if rec.tokens else None
        elif kw in ("PARM", "XDAT", "YDAT"):
            if len(rec.tokens) < 2:
                raise self.error(rec.line, f"{kw}: expected a parameter number and a value")
            index = self.integer(rec, 0, "parameter number")
            self.number(rec, 1, f"{kw} {index} value")
            if kw == "YDAT":
                if self.number(rec, 1) != 0.0:
                    raise self.error(rec.line, f"YDAT {index}: extra data on a surface is not supported")
            else:
                (surf.parms if kw == "PARM" else surf.xdat)[index] = rec
        elif kw == "CLAP":
            if self.number(rec, 0, "minimum radius", default="0") != 0.0:
                raise self.error(rec.line, "CLAP: an annular aperture (non-zero minimum radius) is not supported")
            self.number(rec, 1, "maximum radius")
            surf.clap = rec
        elif kw == "FLAP":
            # a floating aperture clips at the semi-diameter (DIAM); only its minimum radius matters
            if rec.tokens and self.number(rec, 0, "minimum radius") != 0.0:
                raise self.error(rec.line, "FLAP: an annular aperture (non-zero minimum radius) is not supported")
            surf.flap = rec
        elif kw in _NONCIRCULAR_APERTURES:
            if not self.all_zero(rec):
                raise self.error(rec.line, f"{kw}: {_NONCIRCULAR_APERTURES[kw]} is not supported (only circular clear apertures)")
        elif kw == "OBDC":
            if not self.all_zero(rec):
                raise self.error(rec.line, "OBDC: decentered apertures are not supported")
        elif kw == "SCBD":
            if not self.all_zero(rec):
                raise self.error(rec.line, "SCBD: surface tilts/decenters are not supported")
        elif kw == "GRIN":
            raise self.error(rec.line, "GRIN: gradient-index media are not supported")
        elif kw in _THICKNESS_SOLVES:
            surf.solves.append(rec)
        elif kw in _ROUTINE_SURFACE_KEYWORDS:
            pass
        elif kw in _HARMLESS_SURFACE_KEYWORDS:
            self.skip(rec, known=True)
        elif re.fullmatch(r"[A-Z][A-Z0-9]{2,3}", kw):
            self.skip(rec, known=False)
        else:
            raise self.error(rec.line, f"{rec.keyword[:20]!r}: not a .zmx surface record (a keyword of 3-4 capital letters)")

    # -- pass 2: the prescription

    def scale(self) -> Decimal:
        return _UNIT_SCALE_TO_MM[self.unit.tokens[0].upper()] if self.unit else Decimal(1)

    def length(self, rec: _Rec, index: int, what: str) -> float:
        scale = self.scale()
        if scale == 1:
            return self.number(rec, index, what)
        return float(self.decimal(rec, index, what) * scale)

    def thickness(self, surf: _RawSurface) -> float:
        if surf.disz is None:
            return 0.0
        if surf.disz.tokens and surf.disz.tokens[0].upper() in ("INFINITY", "INF"):
            return math.inf
        return self.length(surf.disz, 0, "thickness")

    def medium(self, surf: _RawSurface) -> MediumSpec:
        rec = surf.glas
        if rec is None or not rec.tokens:
            return AIR
        name = rec.tokens[0]
        upper = name.upper()
        if upper == "MIRROR":
            raise self.error(rec.line, "GLAS MIRROR: reflecting surfaces are not supported")
        if upper == "AIR":
            return AIR
        code = self.integer(rec, 1, "glass solve type") if len(rec.tokens) > 1 else 0
        n_d = self.number(rec, 3, "n_d") if len(rec.tokens) > 3 else 0.0
        v_d = self.number(rec, 4, "V_d") if len(rec.tokens) > 4 else 0.0
        if code == 4:  # catalog glass with an index / Abbe offset: GLAS name 4 0 nd vd dpgf 0 0 0 dnd dvd
            offsets = [self.number(rec, k, "offset") for k in (9, 10) if len(rec.tokens) > k]
            if any(o != 0.0 for o in offsets):
                raise self.error(rec.line, f"GLAS {name}: glass offsets (solve type 4) are not supported")
        elif code not in (0, 1, 2, 3):
            raise self.error(rec.line, f"GLAS {name}: unknown glass solve type {code}")
        if upper == "___BLANK" or code == 1:  # a model glass: n_d, V_d (V_d = 0: no dispersion given)
            if abs(n_d - 1.0) <= 1e-3:  # "air" written as a model glass (some writers give air relative to vacuum)
                note = f"{os.path.basename(self.filename)}:{rec.line}: a model glass of n_d {n_d:g} is read as air"
                if note not in self.notes:
                    self.notes.append(note)
                return AIR
            if not 1.0 < n_d < 4.0:
                raise self.error(rec.line, f"GLAS {name}: a model glass needs 1 < n_d < 4, got {n_d}")
            return MediumSpec(n_d=n_d, v_d=v_d if v_d > 0.0 else None)
        # A catalog glass (fixed, picked up, substituted or with zero offsets): the model columns
        # beside it are what OpticStudio kept from an earlier model glass (or its defaults 1.5 /
        # 40), not values the design states, so only the name is read; values a jaxflare file
        # states are in its NOTE lines.
        stated = self.stated_glass.get(surf.number)
        if stated is not None:
            n_stated, v_stated = _parse_float(stated[0]), _parse_float(stated[1])
            if n_stated is not None and v_stated is not None and math.isfinite(n_stated) and math.isfinite(v_stated):
                return MediumSpec(glass=name, n_d=n_stated if n_stated > 0 else None, v_d=v_stated if v_stated > 0 else None)
        return MediumSpec(glass=name)

    def radius_from(self, rec: _Rec | None, number: int) -> float:
        """Signed radius in mm from ``CURV``: the shortest decimal whose reciprocal is the stored
        curvature (so a radius typed as 51.3 comes back as 51.3), or the exact radius that
        :func:`zmx_text` recorded in a ``NOTE jaxflare: radius`` line."""
        if rec is None:
            return math.inf
        curvature = self.number(rec, 0, "curvature")
        if curvature == 0.0:
            return math.inf
        hint = self.radius_hints.get(number)
        if hint is not None and self.scale() == 1:
            value = _parse_float(hint)
            if value is not None and math.isfinite(value) and value != 0.0 and 1.0 / value == curvature:
                return value
        radius = _radius_from_curvature(curvature)
        scale = self.scale()
        return radius if scale == 1 else float(Decimal(repr(radius)) * scale)

    def coefficient(self, rec: _Rec, power: int) -> float:
        """An aspheric coefficient of r**power, converted to mm**(1 - power)."""
        scale = self.scale()
        if scale == 1:
            return self.number(rec, 1, "coefficient")
        return float(self.decimal(rec, 1, "coefficient") * scale ** (1 - power))

    def shape(self, surf: _RawSurface) -> tuple[str, float, float, tuple[float, ...]]:
        """(kind, radius, conic, aspheric coefficients A4, A6, ...) of a surface block."""
        surface_type = surf.type.tokens[0].upper() if surf.type is not None and surf.type.tokens else "STANDARD"
        conic = self.number(surf.coni, 0, "conic") if surf.coni is not None else 0.0
        for index, rec in surf.xdat.items():
            is_zernike_count = surface_type == "TOROIDAL" and index == 1
            if (surface_type != "TOROIDAL" or is_zernike_count) and self.number(rec, 1) != 0.0:
                raise self.error(rec.line, f"XDAT {index}: extra data (Zernike / extended polynomial terms) is not supported")
        if surface_type == "STANDARD":
            for index, rec in sorted(surf.parms.items()):
                if self.number(rec, 1) != 0.0:
                    raise self.error(rec.line, f"PARM {index}: a STANDARD surface has no parameters, got a non-zero value")
            return "spherical", self.radius_from(surf.curv, surf.number), conic, ()
        if surface_type == "EVENASPH":
            coefficients: dict[int, float] = {}
            for index, rec in sorted(surf.parms.items()):
                value = self.number(rec, 1)
                if index == 1 and value != 0.0:
                    raise self.error(rec.line, "PARM 1: the r^2 term of an EVENASPH surface is not supported (only A4, A6, ...)")
                if index < 1 and value != 0.0:
                    raise self.error(rec.line, f"PARM {index}: unexpected parameter on an EVENASPH surface")
                if index >= 2:
                    coefficients[index] = self.coefficient(rec, 2 * index)
            return "spherical", self.radius_from(surf.curv, surf.number), conic, _trimmed(coefficients, first=2)
        # TOROIDAL: a y-z profile (CURV, CONI, PARM 2.. = y^2, y^4, ... terms) swept about an axis
        # parallel to y at the radius of rotation PARM 1 (0 = infinite: no power in x).
        rotation_rec = surf.parms.get(1)
        rotation = self.number(rotation_rec, 1) if rotation_rec is not None else 0.0
        curvature = self.number(surf.curv, 0, "curvature") if surf.curv is not None else 0.0
        terms: dict[int, float] = {}
        for index, rec in sorted(surf.parms.items()):
            value = self.number(rec, 1)
            if index == 2 and value != 0.0:
                raise self.error(rec.line, "PARM 2: the y^2 term of a TOROIDAL surface is not supported")
            if index >= 3:
                terms[index] = self.coefficient(rec, 2 * (index - 1))
        coefficients = _trimmed(terms, first=3)
        if rotation != 0.0:
            if curvature != 0.0:
                where = rotation_rec.line
                raise self.error(where, "PARM 1: a TOROIDAL surface with power in both x and y (a true toroid) is not supported; only cylinders")
            if conic != 0.0 or coefficients:
                raise self.error(rotation_rec.line, "PARM 1: a TOROIDAL cylinder with power in x cannot have a conic or aspheric y profile")
            scale = self.scale()
            radius = rotation if scale == 1 else float(self.decimal(rotation_rec, 1, "radius of rotation") * scale)
            return "cylindrical_x", radius, 0.0, ()
        return "cylindrical_y", self.radius_from(surf.curv, surf.number), conic, coefficients

    def build(self) -> LensPrescription:
        last_line = len(self.lines)
        if len(self.surfaces) < 3:
            raise self.error(last_line, f"expected an object surface, at least one lens surface and an image surface; found {len(self.surfaces)} SURF block(s)")
        obj, lens, image = self.surfaces[0], self.surfaces[1:-1], self.surfaces[-1]
        notes = list(self.notes)

        for surf, what in ((obj, "object"), (image, "image")):
            if surf.stop is not None:
                raise self.error(surf.stop.line, f"STOP: the aperture stop cannot be the {what} surface")
            kind, radius, _, coefficients = self.shape(surf)
            if what == "image" and (not math.isinf(radius) or coefficients or kind == "cylindrical_x"):
                raise self.error((surf.curv or surf.type or _Rec("SURF", [], "", surf.line)).line, "CURV: a curved image surface is not supported (the sensor is flat)")
        if self.medium(obj) != AIR:
            raise self.error(obj.glas.line, "GLAS: the object space must be air")
        object_distance = self.thickness(obj)
        if object_distance < 1e9:  # OpticStudio writes 1e10 for "at infinity" where INFINITY is not allowed
            notes.append(f"the .zmx object is at a finite distance ({object_distance:g} mm); jaxflare images from infinity")

        positions = self.configurations()
        base = [self.thickness(s) for s in self.surfaces]
        for surf, t in zip(lens, base[1:-1]):
            if math.isinf(t):
                raise self.error(surf.disz.line, "DISZ INFINITY: only the object and image surfaces may have an infinite thickness")
        per_config = self.thicknesses_per_configuration(base, positions, notes)

        stops = [s for s in lens if s.stop is not None]
        if not stops:
            raise self.error(last_line, "no surface is marked STOP (the aperture stop)")
        if len(stops) > 1:
            raise self.error(stops[1].stop.line, f"STOP: more than one aperture stop (SURF {stops[0].number} and SURF {stops[1].number})")

        basename = os.path.basename(self.filename)
        media = [self.medium(surf) for surf in lens]
        surfaces = []
        dropped: list[str] = []
        for k, surf in enumerate(lens):
            kind, radius, conic, coefficients = self.shape(surf)
            before = media[k - 1] if k > 0 else AIR
            dummy = media[k] == before and surf.stop is None and surf.clap is None and surf.flap is None
            thicknesses = tuple(per_config[surf.number])
            if dummy:
                # no index change and no aperture: the surface does nothing to the rays
                dropped.append(f"SURF {surf.number}")
                if surfaces:
                    previous = surfaces[-1]
                    merged = tuple(a + b for a, b in zip(previous.thicknesses_mm, thicknesses))
                    surfaces[-1] = dataclasses.replace(previous, thicknesses_mm=merged)
                else:
                    notes.append(f"the front dummy SURF {surf.number} was dropped: z = 0 is the vertex of the next surface, {sum(thicknesses[:1]):g} mm behind it")
                continue
            label = surf.comment if surf.comment else f"{basename}:{surf.line}: SURF {surf.number} (surface {len(surfaces)})"
            if surf.coating:
                label += f" [Zemax coating {surf.coating}]"
            surfaces.append(
                SurfaceSpec(
                    radius_mm=radius,
                    thicknesses_mm=thicknesses,
                    medium=media[k],
                    semi_aperture_mm=self.semi_aperture(surf, is_interface=media[k] != before),
                    kind=kind,
                    conic=conic,
                    aspheric_coefficients=coefficients,
                    coating=None,
                    is_stop=surf.stop is not None,
                    label=label,
                )
            )
        if dropped:
            notes.append(
                f"dummy surfaces dropped (the same medium on both sides, no CLAP/FLAP aperture, not the stop: they do not change the rays; "
                f"their thicknesses are added to the surface before): {', '.join(dropped)}"
            )
        if self.skipped:
            notes.append(
                "skipped records that do not change the sequential optics (besides the display, field and merit-function records "
                "every file has): " + ", ".join(sorted(self.skipped))
            )
        if self.unknown:
            listed = ", ".join(
                f"{kw} (line {lines[0]})" if len(lines) == 1 else f"{kw} ({len(lines)} records, first on line {lines[0]})"
                for kw, lines in sorted(self.unknown.items(), key=lambda item: item[1][0])
            )
            notes.append(f"skipped records this reader does not know (they are not among the records that change the optics): {listed}")
        stop_surface = next(s for s in surfaces if s.is_stop)
        if self.aperture_kind == "FLOA" and math.isnan(stop_surface.semi_aperture_mm):
            notes.append(
                f"FLOA: the system aperture floats with the stop's semi-diameter, but the stop ({stop_surface.label}) has no DIAM; "
                "the stop is sized from the other apertures when the lens is built"
            )
        if self.aperture_kind == "OBNA":
            notes.append("OBNA: an object-space numerical aperture has no meaning for an object at infinity; the stop's semi-diameter sets the aperture")

        if not self.name and self.filename != "<string>":
            name = os.path.splitext(basename)[0]
        else:
            name = self.name
        return LensPrescription(
            name=name,
            surfaces=tuple(surfaces),
            source="" if self.filename == "<string>" else f"Zemax OpticStudio file {basename}",
            stated_f_number=self.f_number,
            entrance_pupil_diameter_mm=self.entrance_pupil_diameter(),
            design_wavelength_nm=self.design_wavelength(),
            notes="\n".join(notes),
            glass_catalogs=tuple(self.catalogs),
        )

    def semi_aperture(self, surf: _RawSurface, is_interface: bool) -> float:
        """The clear semi-aperture jaxflare clips at, from Zemax's apertures (see the module docstring)."""
        if surf.clap is not None:
            return self.length(surf.clap, 1, "maximum radius")
        diam = math.nan
        if surf.diam is not None:
            diam = self.length(surf.diam, 0, "semi-diameter")
            if diam < 0:
                raise self.error(surf.diam.line, f"DIAM: negative semi-diameter {diam}")
        if surf.flap is not None or surf.stop is not None:
            return diam if diam > 0.0 else math.nan
        mema = self.length(surf.mema, 0, "mechanical semi-diameter") if surf.mema is not None else math.nan
        if mema > 0.0 and surf.curv is not None:
            # beyond the rim of a sphere (or of a conic with k > -1) the element's edge is the flat
            # annulus OpticStudio draws out to MEMA, not the refracting surface
            curvature = abs(self.number(surf.curv, 0, "curvature")) / float(self.scale())
            conic = self.number(surf.coni, 0, "conic") if surf.coni is not None else 0.0
            if curvature > 0.0 and conic > -1.0:
                mema = min(mema, 0.98 / (curvature * math.sqrt(1.0 + conic)))
        edge = max((v for v in (diam, mema) if v > 0.0), default=math.nan)  # the edge of the glass
        return edge if is_interface else math.nan

    def entrance_pupil_diameter(self) -> float | None:
        if self.entrance_pupil is None:
            return None
        value = self.length(self.entrance_pupil, 0, "entrance pupil diameter")
        if not value > 0.0:
            raise self.error(self.entrance_pupil.line, f"ENPD: the entrance pupil diameter must be > 0, got {value}")
        return value

    def design_wavelength(self) -> float:
        primary = self.integer(self.primary_wavelength, 0, "primary wavelength") if self.primary_wavelength else 1
        token = None
        if primary in self.wavelengths:
            rec = self.wavelengths[primary]
            self.number(rec, 1, "wavelength")
            token = rec.tokens[1]
        elif self.legacy_wavelengths is not None and 1 <= primary <= len(self.legacy_wavelengths.tokens):
            self.number(self.legacy_wavelengths, primary - 1, "wavelength")
            token = self.legacy_wavelengths.tokens[primary - 1]
        if token is None:
            return 587.56
        value_nm = float(_parse_decimal(token).scaleb(3))
        return value_nm if value_nm > 0 else 587.56

    def configurations(self) -> int:
        if self.mnum is None:
            if self.thic_rows:
                raise self.error(self.thic_rows[0].line, "THIC: configuration row without MNUM")
            return 1
        count = self.integer(self.mnum, 0, "number of configurations")
        if count < 1:
            raise self.error(self.mnum.line, f"MNUM: number of configurations must be >= 1, got {count}")
        return count

    def thicknesses_per_configuration(self, base: list[float], positions: int, notes: list[str]) -> list[list[float]]:
        last = len(self.surfaces) - 1
        scale = self.scale()
        values: dict[int, dict[int, float]] = {}
        lines: dict[int, int] = {}
        for rec in self.thic_rows:
            if len(rec.tokens) < 3:
                raise self.error(rec.line, "THIC: expected 'THIC surface configuration value ...'")
            surface = self.integer(rec, 0, "surface number")
            config = self.integer(rec, 1, "configuration number")
            if not 0 <= surface <= last:
                raise self.error(rec.line, f"THIC: surface {surface} does not exist (surfaces 0..{last})")
            if not 1 <= config <= positions:
                raise self.error(rec.line, f"THIC: configuration {config} is outside 1..{positions} (MNUM)")
            token = rec.tokens[2]
            if token.upper() in ("INFINITY", "INF"):
                if 0 < surface < last:
                    raise self.error(rec.line, f"THIC: infinite thickness on SURF {surface}")
                value = math.inf
            else:
                value = self.number(rec, 2, "thickness") if scale == 1 else float(self.decimal(rec, 2, "thickness") * scale)
            column = values.setdefault(surface, {})
            if config in column:
                raise self.error(rec.line, f"THIC: SURF {surface} configuration {config} is given twice")
            column[config] = value
            lines.setdefault(surface, rec.line)
        table = [[t] * positions for t in base]
        for surface, column in values.items():
            missing = [c for c in range(1, positions + 1) if c not in column]
            if missing:
                raise self.error(lines[surface], f"THIC: SURF {surface} has no value for configuration(s) {missing}")
            table[surface] = [column[c] for c in range(1, positions + 1)]
        if 0 in values and len(set(table[0])) > 1:
            notes.append("the .zmx configurations change the object distance (THIC on SURF 0); ignored")
        if positions > 1:
            for surf in self.surfaces[1:-1]:
                for rec in surf.solves:
                    table[surf.number] = self.solve(rec, surf.number, table, surf.number in values)
        return table

    def solve(self, rec: _Rec, surface: int, table: list[list[float]], has_operand: bool) -> list[float]:
        if has_operand:
            raise self.error(rec.line, f"{rec.keyword}: SURF {surface} has both a thickness solve and a THIC configuration operand")
        scale = self.scale()

        def length(index: int, what: str) -> float:
            return self.number(rec, index, what) if scale == 1 else float(self.decimal(rec, index, what) * scale)

        if rec.keyword in ("TCOM", "TOLE", "PZUP"):
            reference = self.integer(rec, 0, "reference surface")
            if not 1 <= reference < surface:
                raise self.error(rec.line, f"{rec.keyword}: reference surface {reference} must be a lens surface before SURF {surface}")
            if rec.keyword == "TCOM":  # compensator: t_ref + t_this = total
                total = length(1, "total")
                return [total - table[reference][c] for c in range(len(table[surface]))]
            if rec.keyword == "TOLE":  # position: t_ref + ... + t_this = total
                total = length(1, "total")
                return [total - sum(table[k][c] for k in range(reference, surface)) for c in range(len(table[surface]))]
            factor = self.number(rec, 1, "scale", default="1")  # PZUP from scale offset column
            offset = length(2, "offset") if len(rec.tokens) > 2 else 0.0
            if len(rec.tokens) > 3 and self.number(rec, 3, "column") != 0.0:
                raise self.error(rec.line, "PZUP: pickups from a column other than the thickness are not supported")
            return [factor * table[reference][c] + offset for c in range(len(table[surface]))]
        raise self.error(
            rec.line,
            f"{rec.keyword}: a ray-based thickness solve on SURF {surface} cannot be evaluated for each configuration; "
            "replace it by THIC configuration operands",
        )


def parse_zmx(text: str, filename: str = "<string>") -> LensPrescription:
    """Parse the text of a sequential Zemax ``.zmx`` file into a :class:`LensPrescription`.

    Lengths are converted to millimetres (``UNIT`` MM, CM, IN, METER). ``SURF 0`` (the object) and
    the last ``SURF`` (the image) are dropped; the last lens surface's ``DISZ`` is the distance to
    the sensor. Multi-configuration ``THIC`` operands become per-position ``thicknesses_mm``.
    Errors are :class:`LensFormatError` ``"file:line: KEYWORD: why"``.
    """
    reader = _Reader(text, filename)
    reader.read()
    return reader.build()


def read_zmx(path: str | os.PathLike) -> LensPrescription:
    """Read a sequential Zemax ``.zmx`` file (UTF-16 or ASCII/UTF-8) into a :class:`LensPrescription`."""
    filename = os.fspath(path)
    data = read_input_bytes(filename, ".zmx file", LensFormatError)
    prescription = parse_zmx(decode_zmx_bytes(data, filename), filename)
    return dataclasses.replace(prescription, path=filename)


# ----------------------------------------------------------------------------- writing

_F_LINE_UM = "0.4861327"
_C_LINE_UM = "0.6562725"
_MAX_EVENASPH_TERMS = 7  # PARM 2..8: A4 .. A16
_MAX_TOROIDAL_TERMS = 6  # PARM 3..8: y^4 .. y^14


def zmx_text(prescription: LensPrescription) -> str:
    """The prescription as the text of an ASCII sequential ``.zmx`` file (lines end in ``\\n``).

    Written: ``NAME``, ``NOTE`` (the notes), ``UNIT MM``, ``FNUM`` (image-space F/#) when the
    prescription states one (else ``FLOA``: the aperture floats with the stop's semi-diameter),
    ``GCAT`` (the catalogs of the prescription and of its named glasses), three fields at 0, 0.7 and 1
    of the sensor half-diagonal, the F, design and C wavelengths (the design wavelength primary), an
    object surface at infinity, one ``SURF`` per surface (``STANDARD``, ``EVENASPH`` for aspheres,
    ``TOROIDAL`` for cylinders) with ``STOP``, ``CURV``, ``PARM``, ``DISZ``, ``GLAS``, ``CONI``,
    ``DIAM`` with a ``CLAP`` circular aperture of the same radius (jaxflare's semi-apertures clip,
    which in Zemax takes an aperture) and the label as ``COMM``, the image surface, and ``MNUM``
    with ``THIC`` rows for the thicknesses that change between zoom positions. The system aperture
    is ``FNUM`` (a stated f-number), else ``ENPD`` (a stated entrance pupil), else ``FLOA``.

    Not representable, so not written: thin-film coatings (a ``NOTE`` lists what was dropped),
    per-glass catalogs (they go to ``GCAT``), the source, stated focal lengths, sensor size (only as
    the field heights), aperture blades and the file path. A radius whose curvature does not
    reproduce it exactly is recorded in a ``NOTE jaxflare: radius`` line that :func:`parse_zmx` uses.
    Degenerate values do not come back as written: a flat ``cylindrical_x`` surface reads back as a
    flat ``cylindrical_y`` one, a semi-aperture of 0 as ``math.nan``, a radius of ``-inf`` as ``inf``,
    and a dummy surface (the same medium on both sides, not the stop) without a semi-aperture is
    dropped on reading, its thickness added to the surface before.
    """
    surfaces = prescription.surfaces
    where = prescription.path or prescription.name or "prescription"
    if not surfaces:
        raise LensFormatError(f"{where}: the lens has no surfaces")
    positions = len(surfaces[0].thicknesses_mm)
    if positions < 1 or any(len(s.thicknesses_mm) != positions for s in surfaces):
        raise LensFormatError(f"{where}: every surface needs the same number (>= 1) of zoom-position thicknesses")
    prescription.stop_surface_index  # exactly one stop, or LensFormatError

    body: list[str] = []
    hints: list[str] = []
    dropped_coatings: list[str] = []
    catalogs = [c.upper() for c in prescription.glass_catalogs]
    for k, surface in enumerate(surfaces):
        number = k + 1
        here = f"{where}: surface {k}"
        body.extend(_surface_lines(surface, number, here, hints))
        if surface.medium.catalog and surface.medium.catalog.upper() not in catalogs:
            catalogs.append(surface.medium.catalog.upper())
        if surface.coating is not None:
            dropped_coatings.append(f"surface {k} ({surface.coating.name or f'{len(surface.coating.layers)} layers'})")

    lines = ["VERS 221221 730 20120530 20120530", "MODE SEQ", f"NAME {_ascii_line(prescription.name)}"]
    for note in prescription.notes.split("\n") if prescription.notes else ():
        lines.append(f"NOTE {_ascii_line(note)}".rstrip())
    if dropped_coatings:
        lines.append(f"NOTE {_WRITER_NOTE_PREFIX} thin-film coatings cannot be written to .zmx and were dropped: {', '.join(dropped_coatings)}")
    lines.extend(f"NOTE {hint}" for hint in hints)
    lines += ["PFIL 0 0 0", "LANG 0", "UNIT MM X W X CM MR CPMM"]
    f_number = prescription.stated_f_number
    if f_number is not None:
        if not (math.isfinite(f_number) and f_number > 0):
            raise LensFormatError(f"{where}: stated f-number must be a positive number, got {f_number}")
        lines.append(f"FNUM {_num(f_number)} 0")
    elif prescription.entrance_pupil_diameter_mm is not None:
        lines.append(f"ENPD {_num(prescription.entrance_pupil_diameter_mm)}")
    else:
        lines.append("FLOA")
    lines += ["ENVD 20 1 0", "GFAC 0 0"]
    if catalogs:
        for name in catalogs:
            if not re.fullmatch(r"\S+", name):
                raise LensFormatError(f"{where}: glass catalog name {name!r} cannot contain spaces in .zmx")
        lines.append("GCAT " + " ".join(catalogs))
    half_diagonal = math.hypot(prescription.sensor_width_mm, prescription.sensor_height_mm) / 2.0
    pad = ["0"] * 9
    lines += [
        "FTYP 2 0 3 3 0 0 0 3",
        "ROPD 2",
        "PICB 1",
        "XFLN " + " ".join(["0", "0", "0"] + pad),
        "YFLN " + " ".join(["0", _num(0.7 * half_diagonal), _num(half_diagonal)] + pad),
        "FWGN " + " ".join(["1"] * 12),
    ]
    lines += [f"{kw} " + " ".join(["0"] * 12) for kw in ("VDXN", "VDYN", "VCXN", "VCYN", "VANN")]
    design = prescription.design_wavelength_nm
    if not (math.isfinite(design) and design > 0):
        raise LensFormatError(f"{where}: design wavelength must be a positive number of nm, got {design}")
    lines += [
        f"WAVM 1 {_F_LINE_UM} 1",
        f"WAVM 2 {_decimal_text(Decimal(repr(float(design))).scaleb(-3))} 1",
        f"WAVM 3 {_C_LINE_UM} 1",
        "PWAV 2",
    ]
    lines += ["SURF 0", "  TYPE STANDARD", '  CURV 0.0 0 0 0 0 ""', "  DISZ INFINITY"]
    lines += body
    lines += [f"SURF {len(surfaces) + 1}", "  TYPE STANDARD", '  CURV 0.0 0 0 0 0 ""', "  DISZ 0"]
    lines.append(f"MNUM {positions} 1")
    for k, surface in enumerate(surfaces):
        if len(set(surface.thicknesses_mm)) > 1:
            for config, t in enumerate(surface.thicknesses_mm, 1):
                lines.append(f'THIC {k + 1} {config} {_num(t)} 0 0 0 1 1 1 0 0 "" 0')
    return "\n".join(lines) + "\n"


def write_zmx(prescription: LensPrescription, path: str | os.PathLike) -> None:
    """Write :func:`zmx_text` to ``path`` (ASCII, CRLF line ends) atomically: a temporary file in
    the same directory is written, flushed and then renamed over ``path``."""
    write_bytes_atomic(path, zmx_text(prescription).replace("\n", "\r\n").encode("ascii"))


def _surface_lines(surface: SurfaceSpec, number: int, here: str, hints: list[str]) -> list[str]:
    for t in surface.thicknesses_mm:
        if not math.isfinite(t):
            raise LensFormatError(f"{here}: thickness must be finite, got {t}")
    if math.isnan(surface.radius_mm) or surface.radius_mm == 0.0:
        raise LensFormatError(f"{here}: radius must be non-zero (math.inf for flat), got {surface.radius_mm}")
    if not math.isfinite(surface.conic):
        raise LensFormatError(f"{here}: conic must be finite, got {surface.conic}")
    for a in surface.aspheric_coefficients:
        if not math.isfinite(a):
            raise LensFormatError(f"{here}: aspheric coefficients must be finite, got {a}")
    coefficients = list(surface.aspheric_coefficients)
    while coefficients and coefficients[-1] == 0.0:
        coefficients.pop()

    lines = [f"SURF {number}"]
    if surface.is_stop:
        lines.append("  STOP")
    radius = surface.radius_mm
    curvature = 0.0 if math.isinf(radius) else 1.0 / radius
    parms: list[tuple[int, float]] = []
    if surface.kind == "spherical":
        if coefficients:
            if len(coefficients) > _MAX_EVENASPH_TERMS:
                raise LensFormatError(f"{here}: EVENASPH holds at most {_MAX_EVENASPH_TERMS} coefficients (A4..A16), got {len(coefficients)}")
            lines.append("  TYPE EVENASPH")
            parms = [(1, 0.0)] + [(k + 2, a) for k, a in enumerate(coefficients)]
        else:
            lines.append("  TYPE STANDARD")
    elif surface.kind == "cylindrical_y":
        if len(coefficients) > _MAX_TOROIDAL_TERMS:
            raise LensFormatError(f"{here}: a TOROIDAL cylinder holds at most {_MAX_TOROIDAL_TERMS} coefficients (A4..A14), got {len(coefficients)}")
        lines.append("  TYPE TOROIDAL")
        parms = [(1, 0.0), (2, 0.0)] + [(k + 3, a) for k, a in enumerate(coefficients)]
    elif surface.kind == "cylindrical_x":
        if surface.conic != 0.0 or coefficients:
            raise LensFormatError(f"{here}: a cylindrical_x surface with a conic or aspheric terms cannot be written as a Zemax TOROIDAL surface")
        lines.append("  TYPE TOROIDAL")
        parms = [(1, 0.0 if math.isinf(radius) else radius)]
        curvature = 0.0
    else:
        raise LensFormatError(f"{here}: unknown surface kind {surface.kind!r}")
    if surface.label:
        lines.append(f"  COMM {_ascii_line(surface.label)}")
    lines.append(f'  CURV {_num(curvature)} 0 0 0 0 ""')
    if curvature != 0.0 and _radius_from_curvature(curvature) != radius:
        hints.append(f"{_WRITER_NOTE_PREFIX} radius SURF {number} {_num(radius)}")
    lines.extend(f"  PARM {index} {_num(value)}" for index, value in parms)
    lines.append(f"  DISZ {_num(surface.thicknesses_mm[0])}")
    medium = surface.medium
    if medium.glass is not None:
        if not re.fullmatch(r"[\x21-\x7e]+", medium.glass) or medium.glass.upper() in ("___BLANK", "MIRROR"):
            raise LensFormatError(f"{here}: glass name {medium.glass!r} cannot be written to .zmx")
        n_d = _num(_finite(medium.n_d, here, "n_d")) if medium.n_d is not None else "0"
        v_d = _num(_finite(medium.v_d, here, "v_d")) if medium.v_d is not None else "0"
        lines.append(f"  GLAS {medium.glass} 0 0 {n_d} {v_d} 0 0 0 0 0 0")
        if medium.n_d is not None or medium.v_d is not None:  # OpticStudio's reader ignores these columns; ours reads the NOTE
            hints.append(f"{_WRITER_NOTE_PREFIX} stated SURF {number} n_d {n_d} v_d {v_d}")
    elif medium.n_d is not None:
        n_d = _finite(medium.n_d, here, "n_d")
        if n_d <= 0:
            raise LensFormatError(f"{here}: model glass n_d must be > 0, got {n_d}")
        v_d = _num(_finite(medium.v_d, here, "v_d")) if medium.v_d is not None else "0"
        lines.append(f"  GLAS ___BLANK 1 0 {_num(n_d)} {v_d} 0 0 0 0 0 0")
    if surface.conic != 0.0 and surface.kind != "cylindrical_x":
        lines.append(f"  CONI {_num(surface.conic)}")
    semi = surface.semi_aperture_mm
    if not math.isnan(semi):
        if not (math.isfinite(semi) and semi >= 0):
            raise LensFormatError(f"{here}: semi-aperture must be a positive number or math.nan, got {semi}")
        lines.append(f'  DIAM {_num(semi)} 1 0 0 1 ""')
        lines.append(f"  CLAP 0 {_num(semi)} 0")  # jaxflare's semi-apertures clip: a circular aperture in Zemax
    return lines


# ----------------------------------------------------------------------------- numbers and text


def _parse_float(token: str) -> float | None:
    text = token.strip()
    if text.count(",") == 1 and "." not in text:
        text = text.replace(",", ".")  # a decimal comma from a localized writer
    try:
        return float(text)
    except ValueError:
        return None


def _parse_decimal(token: str) -> Decimal:
    text = token.strip()
    if text.count(",") == 1 and "." not in text:
        text = text.replace(",", ".")
    try:
        return Decimal(text)
    except InvalidOperation:  # pragma: no cover - validated by _parse_float first
        return Decimal(repr(float(text)))


def _radius_from_curvature(curvature: float) -> float:
    """The double with the fewest significant digits whose reciprocal is ``curvature`` (a stored
    curvature of 1/51.3 gives 51.3, not 51.300000000000004), or the plain reciprocal."""
    plain = 1.0 / curvature
    for digits in range(1, 18):
        candidate = float(f"{plain:.{digits}g}")
        if candidate != 0.0 and 1.0 / candidate == curvature:
            return candidate
    for direction in (math.inf, -math.inf):
        candidate = plain
        for _ in range(4):
            candidate = math.nextafter(candidate, direction)
            if 1.0 / candidate == curvature:
                return candidate
    return plain


def _trimmed(coefficients: dict[int, float], first: int) -> tuple[float, ...]:
    if not coefficients:
        return ()
    values = [coefficients.get(index, 0.0) for index in range(first, max(coefficients) + 1)]
    while values and values[-1] == 0.0:
        values.pop()
    return tuple(values)


def _num(value: float) -> str:
    """Shortest text that reads back as exactly ``value`` (Python's repr)."""
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"cannot write non-finite number {value}")
    return repr(value)


def _decimal_text(value: Decimal) -> str:
    text = format(value.normalize(), "f")
    return text if "." in text or "E" in text else text + ".0"


def _finite(value: float | None, here: str, what: str) -> float:
    if value is None or not math.isfinite(value):
        raise LensFormatError(f"{here}: {what} must be a finite number, got {value}")
    return float(value)


def _unquote(text: str) -> str:
    text = text.strip()
    if len(text) >= 2 and text[0] == text[-1] == '"':
        return text[1:-1]
    return text


def _ascii_line(text: str) -> str:
    """One line of printable ASCII (other characters become '?', line breaks spaces)."""
    flat = " ".join(str(text).splitlines())
    return flat.encode("ascii", "replace").decode("ascii")
