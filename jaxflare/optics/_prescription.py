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
