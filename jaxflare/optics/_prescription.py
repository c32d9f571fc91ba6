"""Plain-Python lens prescriptions: what a lens file says, before any glass is resolved.

Both readers (our TOML lens format and Zemax ``.zmx``) produce a :class:`LensPrescription`;
:func:`jaxflare.build_lens` turns one into the array-valued :class:`jaxflare.Lens` that the
tracer uses. Keeping this layer free of JAX makes the readers and writers easy to test and lets a
``.zmx`` round trip compare prescriptions field by field.

Conventions (all lengths in millimetres):

- Surfaces are listed front (object side) to back (sensor side).
- ``radius_mm`` is the signed vertex radius of curvature, positive when the centre of curvature
  lies behind the vertex (towards the sensor); ``math.inf`` means flat.
- ``thicknesses_mm`` is the axial distance from this surface's vertex to the next one (for the
  last surface: to the sensor plane). A zoom lens has one entry per zoom position; a fixed lens
  has exactly one.
- ``medium`` is the medium *after* the surface (between it and the next surface).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

SurfaceKindName = Literal["spherical", "cylindrical_x", "cylindrical_y"]
"""Shape family of a surface.

``spherical`` is rotationally symmetric about the optical axis (sphere, flat, conic or even
asphere, depending on ``conic`` and ``aspheric_coefficients``). ``cylindrical_x`` has optical power
only in the x-z plane: its sag depends on x alone (the cylinder axis lies along y).
``cylindrical_y`` has power only in the y-z plane.
"""

SURFACE_KINDS: tuple[str, ...] = ("spherical", "cylindrical_x", "cylindrical_y")


class LensFormatError(ValueError):
    """A lens description is malformed; the message names the file, line or surface and why."""


@dataclasses.dataclass(frozen=True)
class MediumSpec:
    """The medium after a surface, as written in a lens file.

    Exactly one of three forms:

    - air: ``MediumSpec()`` (``glass`` is None and ``n_d`` is None),
    - a catalog glass: ``MediumSpec(glass="N-BK7")`` optionally with ``catalog="SCHOTT"``; if
      ``n_d``/``v_d`` are given too they are the values the source states and are used to check
      the catalog glass,
    - a model glass: ``MediumSpec(n_d=1.6424, v_d=48.0)`` (dispersion from n_d and the Abbe number).
    """

    glass: str | None = None
    catalog: str | None = None
    n_d: float | None = None
    v_d: float | None = None

    @property
    def is_air(self) -> bool:
        return self.glass is None and self.n_d is None

    def describe(self) -> str:
        if self.is_air:
            return "air"
        if self.glass is not None:
            name = f"{self.catalog}:{self.glass}" if self.catalog else self.glass
            return name
        return f"model glass n_d={self.n_d} V_d={self.v_d}"


AIR = MediumSpec()


@dataclasses.dataclass(frozen=True)
class CoatingLayerSpec:
    """One thin-film layer: refractive index (non-absorbing) and physical thickness in nm."""

    index: float
    thickness_nm: float


@dataclasses.dataclass(frozen=True)
class CoatingSpec:
    """A thin-film stack on a surface.

    ``layers`` are ordered as a ray travelling *forward* (towards the sensor) meets them.
    An empty tuple means an uncoated surface.
    """

    layers: tuple[CoatingLayerSpec, ...] = ()
    name: str = ""

    @staticmethod
    def quarter_wave(index: float = 1.38, design_wavelength_nm: float = 550.0, name: str = "") -> "CoatingSpec":
        """Single quarter-wave layer (default: MgF2, n = 1.38, at 550 nm)."""
        thickness = design_wavelength_nm / (4.0 * index)
        return CoatingSpec((CoatingLayerSpec(index, thickness),), name or f"quarter-wave n={index} @ {design_wavelength_nm} nm")


UNCOATED = CoatingSpec((), "uncoated")
DEFAULT_COATING = CoatingSpec.quarter_wave(1.38, 550.0, "MgF2 quarter-wave @ 550 nm")


@dataclasses.dataclass(frozen=True)
class SurfaceSpec:
    """One surface of a prescription, as written in a lens file (see module docstring)."""

    radius_mm: float
    thicknesses_mm: tuple[float, ...]
    medium: MediumSpec
    semi_aperture_mm: float
    """Clear semi-aperture in mm; ``math.nan`` when the source does not give one (it is then
    derived from the paraxial marginal and chief rays when the lens is built, with a warning)."""
    kind: SurfaceKindName = "spherical"
    conic: float = 0.0
    aspheric_coefficients: tuple[float, ...] = ()
    """Even-asphere coefficients A4, A6, A8, ... (sag terms A4 r^4 + A6 r^6 + ...), in mm^(1-2k)."""
    coating: CoatingSpec | None = None
    """None: the default (quarter-wave MgF2 on air-glass interfaces, nothing on cemented ones)."""
    is_stop: bool = False
    label: str = ""
    """Where the surface came from, for error messages (e.g. ``"biotar.toml surface 5"``)."""

    @property
    def curvature_per_mm(self) -> float:
        return 0.0 if math.isinf(self.radius_mm) else 1.0 / self.radius_mm

    @property
    def is_flat(self) -> bool:
        return math.isinf(self.radius_mm) and not self.aspheric_coefficients


@dataclasses.dataclass(frozen=True)
class LensPrescription:
    """A whole lens as written in a file: surfaces plus metadata.

    The object medium in front of surface 0 is air. The last surface's thickness is the distance
    to the sensor plane as the source states it.
    """

    name: str
    surfaces: tuple[SurfaceSpec, ...]
    source: str = ""
    stated_focal_length_mm: float | None = None
    """The focal length the source states (for a zoom: at zoom position 0)."""
    stated_focal_lengths_mm: tuple[float, ...] = ()
    """For zooms: the stated focal length at each zoom position (same order as thicknesses)."""
    stated_focal_length_plane: str = "y"
    """The meridian the stated focal length refers to: "y" (default) or "x" (anamorphics whose
    source states the squeezed axis's focal length)."""
    stated_f_number: float | None = None
    entrance_pupil_diameter_mm: float | None = None
    """The system aperture as an entrance pupil diameter (a Zemax file's ``ENPD``), when the source
    gives one instead of an f-number: the stop is opened no wider than that, and missing
    semi-apertures are derived from it."""
    sensor_width_mm: float = 36.0
    sensor_height_mm: float = 24.0
    aperture_blades: int = 0
    """Number of iris blades; 0 means a circular stop."""
    aperture_rotation_deg: float = 0.0
    design_wavelength_nm: float = 587.56
    notes: str = ""
    glass_catalogs: tuple[str, ...] = ()
    """Catalogs to search first for named glasses (a .zmx file's GCAT line), e.g. ("SCHOTT", "OHARA")."""
    path: str = ""
    """The file this prescription was read from (empty if built in code)."""

    @property
    def num_zoom_positions(self) -> int:
        return len(self.surfaces[0].thicknesses_mm) if self.surfaces else 0

    @property
    def stop_surface_index(self) -> int:
        stops = [k for k, s in enumerate(self.surfaces) if s.is_stop]
        if len(stops) != 1:
            raise LensFormatError(f"{self.path or self.name}: expected exactly one aperture stop, found {len(stops)}")
        return stops[0]


# --------------------------------------------------------------------------- physical bounds

MAX_SURFACES = 100
"""The most surfaces a lens may have (a 30-element zoom has about 60; ghost paths grow as the square)."""
MAX_LENGTH_MM = 1.0e5
"""Largest thickness, |radius| or semi-aperture accepted, in mm (100 m): beyond it a value is a typo."""
MIN_RADIUS_MM = 1.0e-3
"""Smallest |radius| accepted, in mm (a 1 um radius is no lens surface)."""
MAX_CONIC = 1.0e4
"""Largest |conic constant| accepted (real aspheres stay within a few hundred)."""
MAX_ASPHERIC_SAG_MM = 1.0e4
"""Largest |aspheric sag| accepted at a surface's semi-aperture (or at 1 mm where none is given)."""
F_NUMBER_RANGE = (0.5, 1000.0)
"""Stated and requested f-numbers: f/0.5 is the limit of a lens in air (numerical aperture 1)."""
COATING_INDEX_RANGE = (1.0, 4.0)
"""Refractive index of a thin-film coating layer (porous silica 1.2 .. titania 2.4, germanium 4)."""
MAX_COATING_THICKNESS_NM = 1.0e5
"""Thickest coating layer accepted, in nm (100 um: no longer a thin film)."""
MAX_APERTURE_BLADES = 64
"""The most iris blades accepted (real irises have up to about 20; more is a circle to the eye)."""
WAVELENGTH_RANGE_NM = (100.0, 20000.0)
"""Design wavelengths accepted, in nm."""


def check_blades(blades: object, where: str) -> int:
    """An iris blade count: 0 (circular) or 3 .. :data:`MAX_APERTURE_BLADES`."""
    if isinstance(blades, bool) or not isinstance(blades, int) or blades < 0 or blades in (1, 2) or blades > MAX_APERTURE_BLADES:
        raise LensFormatError(f"{where}: 'aperture_blades' must be 0 (circular) or an integer from 3 to {MAX_APERTURE_BLADES}, got {blades!r}")
    return blades


def _in_range(value: float, low: float, high: float) -> bool:
    return math.isfinite(value) and low <= value <= high


def check_prescription(prescription: LensPrescription) -> None:
    """Refuse values no lens can have, naming the surface (its label says file and line) and the
    valid range: lengths, radii, conics, aspheric sags, coating layers, the f-number, the entrance
    pupil, iris blades, the design wavelength and the number of surfaces. Raises
    :class:`LensFormatError`; NaN semi-apertures (to be derived) are allowed."""
    where = prescription.path or prescription.name or "lens"
    surfaces = prescription.surfaces
    if not surfaces:
        raise LensFormatError(f"{where}: the lens has no surfaces")
    if len(surfaces) > MAX_SURFACES:
        raise LensFormatError(f"{where}: {len(surfaces)} surfaces; a lens may have at most {MAX_SURFACES}")
    for k, surface in enumerate(surfaces):
        here = surface.label or f"{where}: surface {k}"
        for t in surface.thicknesses_mm:
            if not _in_range(t, 0.0, MAX_LENGTH_MM):
                raise LensFormatError(f"{here}: thickness {t} mm is outside the valid range 0 .. {MAX_LENGTH_MM:g} mm")
        radius = surface.radius_mm
        if math.isnan(radius) or (not math.isinf(radius) and not MIN_RADIUS_MM <= abs(radius) <= MAX_LENGTH_MM * 1e3):
            raise LensFormatError(f"{here}: radius {radius} mm is outside the valid range: {MIN_RADIUS_MM:g} <= |radius| <= {MAX_LENGTH_MM * 1e3:g} mm, or flat")
        semi = surface.semi_aperture_mm
        if not math.isnan(semi) and not (0.0 < semi <= MAX_LENGTH_MM and math.isfinite(semi)):
            raise LensFormatError(f"{here}: semi-aperture {semi} mm is outside the valid range (0, {MAX_LENGTH_MM:g}] mm")
        if not _in_range(surface.conic, -MAX_CONIC, MAX_CONIC):
            raise LensFormatError(f"{here}: conic constant {surface.conic} is outside the valid range -{MAX_CONIC:g} .. {MAX_CONIC:g}")
        if surface.aspheric_coefficients:
            rho2 = (semi if math.isfinite(semi) else 1.0) ** 2
            sag = 0.0
            for j, a in enumerate(surface.aspheric_coefficients):
                if not math.isfinite(a):
                    raise LensFormatError(f"{here}: aspheric coefficient A{2 * j + 4} = {a} is not finite")
                sag += abs(a) * rho2 ** (j + 2)
            if not sag <= MAX_ASPHERIC_SAG_MM:
                raise LensFormatError(
                    f"{here}: the aspheric terms add {sag:.3g} mm of sag at r = {math.sqrt(rho2):g} mm; more than {MAX_ASPHERIC_SAG_MM:g} mm "
                    "is no lens surface (are the coefficients in the right units, mm^(1-2k)?)"
                )
        if surface.coating is not None:
            for j, layer in enumerate(surface.coating.layers):
                if not _in_range(layer.index, *COATING_INDEX_RANGE):
                    raise LensFormatError(f"{here}: coating layer {j} index {layer.index} is outside the valid range {COATING_INDEX_RANGE[0]:g} .. {COATING_INDEX_RANGE[1]:g}")
                if not _in_range(layer.thickness_nm, 0.0, MAX_COATING_THICKNESS_NM):
                    raise LensFormatError(f"{here}: coating layer {j} thickness {layer.thickness_nm} nm is outside the valid range 0 .. {MAX_COATING_THICKNESS_NM:g} nm")
    if prescription.stated_f_number is not None and not _in_range(prescription.stated_f_number, *F_NUMBER_RANGE):
        raise LensFormatError(f"{where}: stated f-number {prescription.stated_f_number} is outside the valid range {F_NUMBER_RANGE[0]:g} .. {F_NUMBER_RANGE[1]:g}")
    epd = prescription.entrance_pupil_diameter_mm
    if epd is not None and not (math.isfinite(epd) and 0.0 < epd <= MAX_LENGTH_MM):
        raise LensFormatError(f"{where}: entrance pupil diameter {epd} mm is outside the valid range (0, {MAX_LENGTH_MM:g}] mm")
    check_blades(prescription.aperture_blades, where)
    if not _in_range(prescription.design_wavelength_nm, *WAVELENGTH_RANGE_NM):
        raise LensFormatError(f"{where}: design wavelength {prescription.design_wavelength_nm} nm is outside the valid range {WAVELENGTH_RANGE_NM[0]:g} .. {WAVELENGTH_RANGE_NM[1]:g} nm")
    for name in ("sensor_width_mm", "sensor_height_mm"):
        value = getattr(prescription, name)
        if not (math.isfinite(value) and 0.0 < value <= 1000.0):
            raise LensFormatError(f"{where}: {name} {value} is outside the valid range (0, 1000] mm")
