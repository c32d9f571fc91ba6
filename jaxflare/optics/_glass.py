"""Optical glasses: one dispersion formula, a catalog of real glasses, and model glasses.

Every medium the tracer sees uses the same 3-term Sellmeier formula

    n(λ)² = 1 + Σᵢ Bᵢ λ² / (λ² − Cᵢ),    λ in micrometres, Cᵢ in µm²,

so a lens is just two ``(M, 3)`` arrays of coefficients (air is B = 0). A catalog glass carries the
coefficients of its manufacturer (or a fit to them, see below); a *model glass*, known only by its
n_d and Abbe number V_d, gets a single-pole Sellmeier term solved to reproduce both exactly.

Wavelengths are in nanometres at the API. The Fraunhofer lines used for n_d and V_d are
d = 587.56 nm, F = 486.13 nm and C = 656.27 nm (the catalog values 587.5618/486.1327/656.2725 nm
rounded as the rest of the project writes them; the difference moves n by less than 1e-7).

The data: ``jaxflare/optics/data/glass_catalog.csv``
----------------------------------------------------

One row per glass, columns ``catalog,name,B1,B2,B3,C1,C2,C3,n_d,v_d,status,source``:

- ``catalog``: SCHOTT, OHARA, HOYA, HIKARI, CDGM, SUMITA or MISC (crystals, fused silica,
  optical plastics, water). Rows are in catalog search order.
- ``B1..C3``: the Sellmeier coefficients above (C in µm²).
- ``n_d``, ``v_d``: the values the source states (for MISC rows computed from the formula).
- ``status``: ``current`` (preferred/standard in the source), ``inquiry`` (Schott "inquiry",
  Hoya/Ohara "special"), ``withdrawn`` (marked obsolete in the source), ``n/a`` (MISC).
- ``source``: the file the row came from (and the package it was found in); for converted rows
  also the source formula and the largest index error of the conversion.

Withdrawn glasses are kept on purpose: old patents and ``.zmx`` files name them, and an old name
(SF5, BK7, SK16, ...) must give the old glass, not its lead-free successor (N-SF5, N-BK7, N-SK16),
which has a different dispersion.

How the table was made (converted once; redo it like this)
-----------------------------------------------------------

Nothing here runs at import time and none of these packages is a dependency. In a throwaway
environment::

    python3 -m venv /tmp/glassenv
    /tmp/glassenv/bin/pip install pandas openpyxl xlrd scipy pyyaml json_tricks
    /tmp/glassenv/bin/pip download --no-deps opticalglass==1.1.1 optiland==0.6.3 \\
        krakenos==1.0.0.24 otk==0.1.2 -d /tmp/dl            # unzip each wheel
    /tmp/glassenv/bin/pip install --no-deps /tmp/dl/opticalglass-1.1.1-py3-none-any.whl

Sources, first one wins for a name within a catalog:

- SCHOTT: ``opticalglass/data/SCHOTT.xls`` (2018-06-01, Sellmeier as published); then
  ``otk/properties/agfs/schottzemax-20180601.agf`` (also gives the status of every glass); then
  ``KrakenOS/Cat/SCHOTT.AGF`` ("Preferred optical glasses 26th February 2008 plus B270 and
  obsolete glasses"), the source of the old lead/arsenic glasses (BK7, SK16, LAK9, SF8, ...).
- OHARA: ``opticalglass/data/OHARA.xlsx`` then ``KrakenOS/Cat/ohara.agf`` (2019-10-18, with
  obsolete glasses).
- HOYA: ``opticalglass/data/HOYA.xlsx`` then ``KrakenOS/Cat/HOYA20220711_include_obsolete.agf``.
- HIKARI: ``opticalglass/data/HIKARI.xlsx`` (2020-04-01) then
  ``otk/properties/agfs/NIKON-HIKARI_201911.AGF`` (with Hikari's old Schott-style names: BAF10,
  SF5, SK16, ...; Nikon's all-digit in-house names are skipped).
- CDGM: ``opticalglass/data/CDGM.xls`` then ``KrakenOS/Cat/cdgm.agf``.
- SUMITA: ``opticalglass/data/SUMITA.xlsx`` (2020-07-29) then
  ``otk/properties/agfs/sumita-opt-dl-data-20200511235805.agf`` (with the old names, SSK4, ...).
  Sumita's ``(M)`` rows are its molding versions.
- MISC: F_SILICA, SILICA, CAF2, PMMA, POLYSTYR, SAN, WATER from ``KrakenOS/Cat/misc.agf``
  (its ACRYLIC, POLYCARB and COC failed the conversion below); SAPPHIRE (ordinary ray, Malitson & Dodge), BAF2 (Malitson) and MGF2
  (ordinary ray, Dodge) from the refractiveindex.info database inside the optiland wheel
  (``optiland/database/data-nk/main/...``).

Spreadsheets were read with opticalglass's catalog classes (names without internal spaces:
OHARA.xlsx writes "S-BSL 7"), ``.agf`` files by their keywords (NM: name, formula, n_d, V_d,
status; CD: coefficients, possibly over several lines; LD: valid wavelength range). AGF status
0/1/4 is ``current``, 3 ``inquiry``, 2 ``withdrawn``; a spreadsheet glass takes its status from
the newest ``.agf`` of its maker that lists it. Rows already in 3-term Sellmeier form are copied.
Other formulas (Schott/Laurent power series of HOYA, CDGM, SUMITA and the old ``.agf`` entries,
Hikari's extended series, 4-term Sellmeier) were converted by fitting the 3-term form over
0.365-1.014 µm, or over the source's own narrower range (Hikari's old glasses: 0.4-0.7 µm):
linear least squares for B on a grid of poles C, Levenberg-Marquardt on all six, then a
minimax refinement (SLSQP). A conversion was kept only if its largest index error on a dense
grid was below 2e-5 (the ``source`` column records the range and the error) and every pole lies
outside 0.30-1.20 µm. 82 glasses failed that and are absent: mostly very dense flints whose
dispersion a 3-term Sellmeier cannot follow to 2e-5 down to 365 nm (HOYA E-FDS1/2/3, FDS18,
TAFD43; CDGM H-ZF52, H-ZF62, H-ZF88, H-LaF2; SUMITA K-PSFn1/2, ...); a lens file that names one
of them and states n_d and V_d falls back to a model glass. Every row then had to pass: the
Sellmeier n at the d line within 1e-4 of the stated n_d, V_d from the F and C lines within 0.3 of
the stated V_d, normal dispersion over 400-700 nm, and (for spreadsheet rows) agreement within
5e-5 with the catalog's own tabulated indices between 365 and 1014 nm (this dropped SUMITA SF18,
whose stated n_d is a typo, and SUMITA CAFK95).

Old names: SCHOTT's 2008 file has BK7, SK16, LAK9, K5, BAK1, LAK8, LAK21, SK5, SK4, SK15, LAF2,
SF8, KF9 and the lead flints (SF1, SF2, SF4, SF5, SF6, SF10, SF11, SF15, F2 are also in the 2018
data). For several crowns (BK7, K5, SK5, SK16, BAK1, LAK8, LAK9, LAK21) it gives the very
coefficients of the N- successor, which SCHOTT matched to the old glass; the lead flints differ
from their successors by 5e-5 (KF9, SF10) to 9e-4 (SF4) in index over 400-700 nm. Cross-checked
against Robb's 1983 fits of the SCHOTT catalogue (``robb1983_data_final.txt`` in opticalglass,
~2-6e-5 accurate): the old flints agree with it to that accuracy and the N- flints do not; for
SK16, SK5 and K5 both the old rows and the N- glasses differ from Robb's curves by 1-4e-4, so
those three are the least certain. BAF10 is not in any SCHOTT file found; the name
resolves to HOYA's (then Hikari's, Sumita's) BAF10 of the same optical position (670/472). SSK4
likewise resolves to SUMITA's SSK4 (SCHOTT lists only SSK4A).
"""

from __future__ import annotations

import csv
import dataclasses
import difflib
import functools
import importlib.resources
import math
import re
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

D_LINE_NM = 587.56
"""Helium d line, nm: the wavelength of n_d."""
F_LINE_NM = 486.13
"""Hydrogen F line, nm (blue end of V_d)."""
C_LINE_NM = 656.27
"""Hydrogen C line, nm (red end of V_d)."""

MODEL_N_D_RANGE = (1.0, 2.5)
"""Open interval of n_d accepted by :func:`model_glass`."""
MODEL_V_D_RANGE = (10.0, 120.0)
"""Open interval of V_d accepted by :func:`model_glass`."""

_CATALOG_ALIASES = {"NIKON": "HIKARI", "NIKON-HIKARI": "HIKARI"}

_NOT_CONVERTIBLE = {
    # In the source files, but no 3-term Sellmeier form follows them to 2e-5 (module docstring).
    "HOYA": "E-FDS1-W E-FDS1 E-FDS2 E-FDS3 FDS16-W FDS18-W FDS18 FDS20-W NBF1 NBFD11 M-FDS2 MP-FDS2 "
    "MC-FDS2 M-FDS910 MP-FDS910-50 MC-FDS910-50 M-FDS1 MP-FDS1 ADF355 BAC5 BAFL6 FD11 FD13 FD14 "
    "FD19 FDS3 LACL4 LAFL4 LAFL5 TAC1 TAFD43 TAFD6",
    "HIKARI": "LAF11 LASF010",
    "CDGM": "H-BAK6 H-ZBAF1 H-ZF52 H-ZF52GT H-ZF52TT ZF52 H-ZF62 H-ZF71 H-ZF72A H-ZF88 H-LAF2 H-LaF3B "
    "H-LaF4GT H-LAF54 H-ZLaF90 D-ZF93 D-ZLAF52LA H-LAK59 H-LAF50A",
    "SUMITA": "K-PSFn2 K-PSFn214P K-VC89(M) K-PSFn173 K-PSFn173(M) K-PSFn214 K-PSFn214(M) K-PSFn215 CSK120 BAF3 SF10 SF10W",
    "MISC": "ACRYLIC COC POLYCARB",
}
_INCONSISTENT_SOURCE = {"SUMITA": "CAFK95 SF18"}  # stated n_d/V_d contradict the source's own formula


class UnknownGlassError(KeyError, ValueError):
    """A glass name is not in the catalogs searched.

    Both a ``KeyError`` (a failed lookup) and a ``ValueError`` (a bad value in a lens file). The
    message names the glass, the nearest names in the catalogs searched and those catalogs.

    Attributes:
        name: the name that was asked for.
        suggestions: up to five nearest names, as ``"CATALOG:NAME"``.
        catalogs_searched: the catalogs searched, in order.
    """

    def __init__(self, name: str, suggestions: Sequence[str] = (), catalogs_searched: Sequence[str] = (), reason: str = ""):
        super().__init__(name)
        self.name = name
        self.suggestions = tuple(suggestions)
        self.catalogs_searched = tuple(catalogs_searched)
        self.reason = reason

    def __str__(self) -> str:
        message = f"unknown glass {self.name!r}"
        if self.reason:
            message += f" ({self.reason})"
        if self.suggestions:
            message += "; nearest names: " + ", ".join(self.suggestions)
        if self.catalogs_searched:
            message += "; catalogs searched: " + ", ".join(self.catalogs_searched)
        return message


@dataclasses.dataclass(frozen=True)
class Glass:
    """One optical medium with 3-term Sellmeier dispersion.

    Attributes:
        name: the manufacturer's name (``"N-BK7"``) or ``"MODEL_<n_d>_<v_d>"`` for a model glass.
        catalog: ``"SCHOTT"``, ``"OHARA"``, ... ``"MISC"``, or ``"MODEL"``.
        sellmeier_b: B1, B2, B3 (dimensionless).
        sellmeier_c_um2: C1, C2, C3 in µm² (squares of the pole wavelengths).
        n_d: index at the d line (587.56 nm) as stated by the source.
        v_d: Abbe number (n_d − 1) / (n_F − n_C) as stated by the source.
        status: ``current``, ``inquiry``, ``withdrawn``, ``n/a`` or ``model``.
        source: where the data came from.
    """

    name: str
    catalog: str
    sellmeier_b: tuple[float, float, float]
    sellmeier_c_um2: tuple[float, float, float]
    n_d: float
    v_d: float
    status: str = ""
    source: str = ""

    def __post_init__(self) -> None:
        for field in ("sellmeier_b", "sellmeier_c_um2"):
            value = tuple(float(x) for x in getattr(self, field))
            if len(value) != 3:
                raise ValueError(f"{field} needs 3 coefficients, got {len(value)}")
            object.__setattr__(self, field, value)
        object.__setattr__(self, "n_d", float(self.n_d))
        object.__setattr__(self, "v_d", float(self.v_d))

    @property
    def qualified_name(self) -> str:
        """``"CATALOG:NAME"``, which :func:`find_glass` resolves back to this glass."""
        return f"{self.catalog}:{self.name}"

    def index(self, wavelength_nm: Any) -> jnp.ndarray:
        """Refractive index at ``wavelength_nm`` (nm; scalar or array, numpy or JAX)."""
        return sellmeier_index(self.sellmeier_b, self.sellmeier_c_um2, wavelength_nm)


@jax.jit
def sellmeier_index(sellmeier_b: Any, sellmeier_c_um2: Any, wavelength_nm: Any) -> jnp.ndarray:
    """Refractive index from the 3-term Sellmeier formula.

    n² = 1 + Σᵢ Bᵢ λ² / (λ² − Cᵢ), with λ = ``wavelength_nm`` / 1000 in µm and Cᵢ in µm².

    Args:
        sellmeier_b: B coefficients, shape ``(..., 3)``.
        sellmeier_c_um2: C coefficients in µm², shape ``(..., 3)``.
        wavelength_nm: wavelengths in nm; broadcast against the leading axes of the coefficients.

    Returns:
        The index, shape ``broadcast(wavelength_nm.shape, sellmeier_b.shape[:-1])``. Pure
        ``jax.numpy`` under ``jax.jit`` (compiled once per input shape): differentiable in all
        arguments and usable inside other jitted code; numpy arrays and Python floats work too.
        Zero coefficients give n = 1 (air).
    """
    b = jnp.asarray(sellmeier_b)
    c = jnp.asarray(sellmeier_c_um2)
    lam2 = jnp.square(jnp.asarray(wavelength_nm) * 1e-3)[..., None]
    return jnp.sqrt(1.0 + jnp.sum(b * lam2 / (lam2 - c), axis=-1))


# ------------------------------------------------------------------------- catalog table


class _Table:
    """The parsed CSV: glasses per catalog, indexed by upper-case name and by a loose key."""

    def __init__(self, glasses: list[Glass]):
        self.glasses = tuple(glasses)
        self.order: tuple[str, ...] = tuple(dict.fromkeys(g.catalog for g in glasses))
        self.by_name: dict[str, dict[str, Glass]] = {c: {} for c in self.order}
        self.by_key: dict[str, dict[str, list[Glass]]] = {c: {} for c in self.order}
        for g in glasses:
            self.by_name[g.catalog].setdefault(g.name.upper(), g)
            self.by_key[g.catalog].setdefault(_loose_key(g.name), []).append(g)
        self.n_d = np.array([g.n_d for g in glasses])
        self.v_d = np.array([g.v_d for g in glasses])
        self.catalog_of = np.array([g.catalog for g in glasses])


def _loose_key(name: str) -> str:
    """Spelling-insensitive key: upper case without hyphens, spaces, dots or underscores."""
    return re.sub(r"[\s\-_.]", "", name.upper())


@functools.cache
def _table() -> _Table:
    resource = importlib.resources.files("jaxflare.optics") / "data" / "glass_catalog.csv"
    with resource.open("r", encoding="utf-8", newline="") as f:
        glasses = [
            Glass(
                name=row["name"],
                catalog=row["catalog"],
                sellmeier_b=(float(row["B1"]), float(row["B2"]), float(row["B3"])),
                sellmeier_c_um2=(float(row["C1"]), float(row["C2"]), float(row["C3"])),
                n_d=float(row["n_d"]),
                v_d=float(row["v_d"]),
                status=row["status"],
                source=row["source"],
            )
            for row in csv.DictReader(f)
        ]
    return _Table(glasses)


def _canonical_catalog(name: str) -> str | None:
    key = str(name).strip().upper()
    key = _CATALOG_ALIASES.get(key, key)
    return key if key in _table().by_name else None


def catalogs() -> list[str]:
    """The catalogs in the table, in default search order (SCHOTT first, MISC last)."""
    return list(_table().order)


def glass_names(catalog: str | None = None) -> list[str]:
    """Glass names of one catalog (table order), or of all catalogs (each name once) if None."""
    table = _table()
    if catalog is None:
        return list(dict.fromkeys(g.name for g in table.glasses))
    canonical = _canonical_catalog(catalog)
    if canonical is None:
        raise ValueError(f"unknown glass catalog {catalog!r}; known catalogs: {', '.join(table.order)}")
    return [g.name for g in table.by_name[canonical].values()]


def find_glass(name: str, catalogs: Sequence[str] = ()) -> Glass:
    """Look up a catalog glass by name (case-insensitive).

    Args:
        name: ``"N-BK7"``, or ``"CATALOG:NAME"`` (``"OHARA:S-BSL7"``) to search that catalog only.
        catalogs: catalogs to search first, in order; all other catalogs follow in the default
            order (:func:`catalogs`). Names that are not catalogs of the table (a ``.zmx`` GCAT line
            may list ones we do not ship) are ignored.

    Returns:
        The first glass of that name in search order. If no name matches exactly, spelling
        variants that differ only in hyphens, spaces, dots or underscores are accepted when they
        are unambiguous (``"NBK7"`` finds N-BK7, ``"SLAH64"`` finds S-LAH64). A prefix is never
        added or dropped: ``"SF5"`` is the old lead glass SF5, not its successor N-SF5.

    Raises:
        UnknownGlassError: the name is in none of the catalogs searched; the message lists the
            five nearest names.
    """
    table = _table()
    query = str(name).strip()
    if catalogs is None:
        catalogs = ()
    elif isinstance(catalogs, str):
        catalogs = (catalogs,)
    if ":" in query:
        catalog_part, _, query = query.partition(":")
        query = query.strip()
        canonical = _canonical_catalog(catalog_part)
        if canonical is None:
            raise UnknownGlassError(name, reason=f"no catalog {catalog_part.strip()!r}; known catalogs: {', '.join(table.order)}")
        order: tuple[str, ...] = (canonical,)
    else:
        preferred = [c for c in (_canonical_catalog(x) for x in catalogs) if c is not None]
        order = tuple(dict.fromkeys([*preferred, *table.order]))

    upper = query.upper()
    for catalog in order:
        glass = table.by_name[catalog].get(upper)
        if glass is not None:
            return glass
    key = _loose_key(query)
    for catalog in order:
        hits = table.by_key[catalog].get(key, [])
        if len(hits) == 1:
            return hits[0]
        if len(hits) > 1:
            raise UnknownGlassError(
                name,
                suggestions=[g.qualified_name for g in hits[:5]],
                catalogs_searched=order,
                reason="ambiguous spelling",
            )
    raise UnknownGlassError(
        name, suggestions=_nearest_names(upper, order), catalogs_searched=order, reason=_left_out_reason(upper, order)
    )


def _left_out_reason(upper: str, order: Sequence[str]) -> str:
    for catalog in order:
        if upper in _NOT_CONVERTIBLE.get(catalog, "").upper().split():
            return (
                f"{catalog} lists it, but no 3-term Sellmeier form follows its dispersion to 2e-5, so the "
                "catalog table leaves it out; give n_d and v_d to use a model glass"
            )
        if upper in _INCONSISTENT_SOURCE.get(catalog, "").upper().split():
            return f"{catalog} lists it, but with n_d/V_d that contradict its own formula, so the catalog table leaves it out"
    return ""


def _nearest_names(upper: str, order: Sequence[str], count: int = 5) -> list[str]:
    table = _table()
    first: dict[str, Glass] = {}
    for catalog in order:
        for key, glass in table.by_name[catalog].items():
            first.setdefault(key, glass)
    matches = difflib.get_close_matches(upper, list(first), n=count, cutoff=0.0)
    return [first[m].qualified_name for m in matches]


# ------------------------------------------------------------------------- model glasses


def _check_open_range(parameter: str, value: float, bounds: tuple[float, float]) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{parameter} must be a number in ({bounds[0]}, {bounds[1]}), got {value!r}") from None
    if not (bounds[0] < x < bounds[1]):
        raise ValueError(f"{parameter} must be in ({bounds[0]}, {bounds[1]}), got {value!r}")
    return x


def _single_pole(n_d: float, c_um2: float) -> tuple[float, float, float]:
    """(B, n_F, n_C) of n² = 1 + B λ²/(λ² − C) pinned to n(d) = n_d, in float64."""
    ld, lf, lc = ((x * 1e-3) ** 2 for x in (D_LINE_NM, F_LINE_NM, C_LINE_NM))
    b = (n_d * n_d - 1.0) * (ld - c_um2) / ld
    n_f = math.sqrt(1.0 + b * lf / (lf - c_um2))
    n_c = math.sqrt(1.0 + b * lc / (lc - c_um2))
    return b, n_f, n_c


def model_glass(n_d: float, v_d: float) -> Glass:
    """A glass known only by its index n_d and Abbe number V_d.

    It uses the same Sellmeier formula as the catalog glasses, with a single ultraviolet pole:
    n² = 1 + B₁ λ²/(λ² − C₁) (B₂ = B₃ = C₂ = C₃ = 0). For a pole C₁, B₁ is fixed by
    n(587.56 nm) = n_d; C₁ is then the root of (n_F − n_C)/(n_d − 1) = 1/V_d, which grows
    monotonically from 0 (C₁ = 0, no dispersion) as the pole moves towards the visible, found by
    bisection in float64 to the last bit. Both n_d and V_d are reproduced to ~1e-14.

    Args:
        n_d: index at 587.56 nm, in (1, 2.5).
        v_d: Abbe number, in (10, 120).

    Raises:
        ValueError: a value outside its range (the message names the parameter and the range).
    """
    n_d = _check_open_range("n_d", n_d, MODEL_N_D_RANGE)
    v_d = _check_open_range("v_d", v_d, MODEL_V_D_RANGE)
    target = 1.0 / v_d

    def excess(c_um2: float) -> float:
        _, n_f, n_c = _single_pole(n_d, c_um2)
        return (n_f - n_c) / (n_d - 1.0) - target

    # At C = 0 the excess is -1/V_d < 0; a pole at 0.2 µm² (447 nm) gives V_d < 3 for every n_d
    # in range, so the root is bracketed and, the excess being monotonic, unique.
    lo, hi = 0.0, 0.2
    while True:
        mid = 0.5 * (lo + hi)
        if mid <= lo or mid >= hi:
            break
        if excess(mid) < 0.0:
            lo = mid
        else:
            hi = mid
    c1 = lo if abs(excess(lo)) <= abs(excess(hi)) else hi
    b1, _, _ = _single_pole(n_d, c1)
    return Glass(
        name=f"MODEL_{n_d!r}_{v_d!r}",
        catalog="MODEL",
        sellmeier_b=(b1, 0.0, 0.0),
        sellmeier_c_um2=(c1, 0.0, 0.0),
        n_d=n_d,
        v_d=v_d,
        status="model",
        source="model glass: single-pole Sellmeier solved for n_d and V_d",
    )


def nearest_glass(n_d: float, v_d: float, catalogs: Sequence[str] = ()) -> Glass:
    """The catalog glass nearest to (n_d, V_d) by (Δn_d)² + 1e-4 (ΔV_d)².

    That is the Polynomial Optics toolkit's rule: one Abbe unit weighs like 0.01 in index.
    ``catalogs`` restricts the search (default: all catalogs, withdrawn glasses included); ties go
    to the earlier row in search order.

    Raises:
        ValueError: a name in ``catalogs`` is not a catalog of the table.
    """
    table = _table()
    if catalogs is None:
        catalogs = ()
    elif isinstance(catalogs, str):
        catalogs = (catalogs,)
    mask = np.ones(len(table.glasses), dtype=bool)
    if catalogs:
        wanted = []
        for c in catalogs:
            canonical = _canonical_catalog(c)
            if canonical is None:
                raise ValueError(f"unknown glass catalog {c!r}; known catalogs: {', '.join(table.order)}")
            wanted.append(canonical)
        mask = np.isin(table.catalog_of, wanted)
    distance = (table.n_d - float(n_d)) ** 2 + 1e-4 * (table.v_d - float(v_d)) ** 2
    distance = np.where(mask, distance, np.inf)
    return table.glasses[int(np.argmin(distance))]
