"""The array-valued lens (an ``equinox.Module`` pytree) and its construction from a prescription."""

from __future__ import annotations

import dataclasses
import math
import warnings

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from . import _paraxial
from ._glass import D_LINE_NM, Glass, UnknownGlassError, find_glass, model_glass
from ._prescription import (
    DEFAULT_COATING,
    F_NUMBER_RANGE,
    UNCOATED,
    CoatingSpec,
    LensFormatError,
    LensPrescription,
    MediumSpec,
    SurfaceSpec,
    check_blades,
    check_prescription,
)
from ._surface import SurfaceKind

STATED_INDEX_TOLERANCE = 0.002
"""Largest |n_d(catalog) - n_d(stated)| accepted silently for a named glass."""


class LensWarning(UserWarning):
    """Something about a lens was substituted or derived; the message says what."""


class Lens(eqx.Module):
    """A sequential lens as arrays, ready for jit-compiled tracing.

    Surfaces are indexed ``s = 0 .. num_surfaces - 1`` front to back; media ``m = 0 .. num_surfaces``
    where medium ``s`` lies in front of surface ``s`` (medium 0 is object-space air, the last one
    image-space air). Lengths in mm, wavelengths in nm. Build one with :func:`jaxflare.load_lens` or
    :func:`build_lens`; derive variants with :meth:`with_f_number`, :meth:`focused_at`,
    :meth:`with_aperture` and :meth:`at_zoom`.

    The paraxial methods (``focal_length`` and friends) evaluate in NumPy float64 and are meant
    for set-up and analysis, outside ``jit``.
    """

    curvature_per_mm: Float[Array, " S"]
    conic: Float[Array, " S"]
    aspheric_coefficients: Float[Array, "S K"]
    """Even-asphere coefficients A4, A6, ... per surface (zero-padded)."""
    surface_kind: Int[Array, " S"]
    """A :class:`~jaxflare.optics.SurfaceKind` per surface (0 rotationally symmetric, 1 cylindrical
    with power in x, 2 cylindrical with power in y)."""
    thickness_mm: Float[Array, " S"]
    """Axial gap after each surface (the last one reaches the prescription's sensor plane)."""
    semi_aperture_mm: Float[Array, " S"]
    sellmeier_b: Float[Array, "M 3"]
    sellmeier_c_um2: Float[Array, "M 3"]
    medium_is_air: Bool[Array, " M"]
    coating_indices: Float[Array, "S L"]
    coating_thicknesses_nm: Float[Array, "S L"]
    """Thin-film layers per surface in the order a forward ray meets them; zero thickness = none."""
    stop_radius_mm: Float[Array, ""]
    """Working radius of the aperture stop (circumradius of the iris polygon)."""
    aperture_rotation_rad: Float[Array, ""]
    sensor_z_mm: Float[Array, ""]
    """z of the sensor plane (z = 0 at the vertex of surface 0)."""

    stop_index: int = eqx.field(static=True)
    aperture_blades: int = eqx.field(static=True)
    interface_surfaces: tuple[int, ...] = eqx.field(static=True)
    has_aspheres: bool = eqx.field(static=True)
    zoom_position: int = eqx.field(static=True)
    prescription: LensPrescription = eqx.field(static=True)
    media: tuple[Glass | None, ...] = eqx.field(static=True)
    """Resolved medium behind each surface (None = air), for reports."""
    notes: tuple[str, ...] = eqx.field(static=True)
    """Substitutions and derivations made while building (also emitted as warnings)."""

    # ----------------------------------------------------------------- structure
    @property
    def name(self) -> str:
        return self.prescription.name

    @property
    def num_surfaces(self) -> int:
        return len(self.prescription.surfaces)

    @property
    def num_interfaces(self) -> int:
        """Surfaces where the refractive index changes (stop in air and dummies excluded)."""
        return len(self.interface_surfaces)

    @property
    def num_zoom_positions(self) -> int:
        return self.prescription.num_zoom_positions

    @property
    def vertex_z_mm(self) -> np.ndarray:
        thickness = np.asarray(self.thickness_mm, dtype=np.float64)
        return np.concatenate([[0.0], np.cumsum(thickness[:-1])])

    @property
    def max_stop_radius_mm(self) -> float:
        return float(self.semi_aperture_mm[self.stop_index])

    # ----------------------------------------------------------------- paraxial
    def refractive_indices(self, wavelength_nm: float = D_LINE_NM) -> np.ndarray:
        """Index of every medium (length num_surfaces + 1) at one wavelength, float64."""
        lam2 = (wavelength_nm * 1e-3) ** 2
        b = np.asarray(self.sellmeier_b, np.float64)
        c = np.asarray(self.sellmeier_c_um2, np.float64)
        n = np.sqrt(1.0 + np.sum(b * lam2 / (lam2 - c), axis=-1))
        return np.where(np.asarray(self.medium_is_air), 1.0, n)

    def _powers(self, wavelength_nm: float, plane: _paraxial.Plane) -> tuple[np.ndarray, np.ndarray]:
        if plane not in ("x", "y"):
            raise ValueError(f"plane must be 'x' or 'y', got {plane!r}")
        n = self.refractive_indices(wavelength_nm)
        kinds = np.asarray(self.surface_kind)
        curvature = np.asarray(self.curvature_per_mm, np.float64)
        no_power = kinds == (SurfaceKind.CYLINDRICAL_Y if plane == "x" else SurfaceKind.CYLINDRICAL_X)
        curvature = np.where(no_power, 0.0, curvature)
        return _paraxial.surface_powers(curvature, n[:-1], n[1:]), n

    def paraxial_system(self, wavelength_nm: float = D_LINE_NM, plane: _paraxial.Plane = "y") -> np.ndarray:
        """2x2 y-nu matrix from the first to the last vertex."""
        powers, n = self._powers(wavelength_nm, plane)
        return _paraxial.system_matrix(powers, np.asarray(self.thickness_mm, np.float64), n, 0, self.num_surfaces - 1)

    def focal_length(self, wavelength_nm: float = D_LINE_NM, plane: _paraxial.Plane = "y") -> float:
        """Effective focal length in mm (paraxial) at ``wavelength_nm`` in the ``plane`` meridian.

        The two planes differ only for anamorphic lenses with cylindrical surfaces.
        """
        return _paraxial.effective_focal_length(self.paraxial_system(wavelength_nm, plane))

    def back_focal_length(self, wavelength_nm: float = D_LINE_NM, plane: _paraxial.Plane = "y") -> float:
        """Distance in mm from the last vertex to the rear focal point."""
        return _paraxial.back_focal_distance(self.paraxial_system(wavelength_nm, plane))

    def entrance_pupil(self, wavelength_nm: float = D_LINE_NM, plane: _paraxial.Plane = "y") -> tuple[float, float]:
        """``(z_mm, radius_mm)`` of the entrance pupil at the current stop radius (z from vertex 0)."""
        powers, n = self._powers(wavelength_nm, plane)
        thickness = np.asarray(self.thickness_mm, np.float64)
        if self.stop_index == 0:
            return 0.0, float(self.stop_radius_mm)
        front = _paraxial.system_matrix(powers, thickness, n, 0, self.stop_index - 1)
        front = _paraxial.transfer_matrix(thickness[self.stop_index - 1], n[self.stop_index]) @ front
        z, magnification = _paraxial.entrance_pupil(front)
        return z, abs(magnification) * float(self.stop_radius_mm)

    def exit_pupil(self, wavelength_nm: float = D_LINE_NM, plane: _paraxial.Plane = "y") -> tuple[float, float]:
        """``(z_mm, radius_mm)`` of the exit pupil at the current stop radius (z from vertex 0)."""
        powers, n = self._powers(wavelength_nm, plane)
        thickness = np.asarray(self.thickness_mm, np.float64)
        back = _paraxial.system_matrix(powers, thickness, n, self.stop_index, self.num_surfaces - 1)
        z, magnification = _paraxial.stop_image(back)
        return float(self.vertex_z_mm[-1]) + z, abs(magnification) * float(self.stop_radius_mm)

    def f_number(self, wavelength_nm: float = D_LINE_NM, plane: _paraxial.Plane = "y") -> float:
        """Paraxial f-number for an object at infinity at the current stop radius: EFL / EP diameter."""
        _, radius = self.entrance_pupil(wavelength_nm, plane)
        return abs(self.focal_length(wavelength_nm, plane)) / (2.0 * radius)

    @property
    def widest_f_number(self) -> float:
        """f-number with the stop fully open (at its semi-aperture)."""
        return self.with_stop_radius(self.max_stop_radius_mm).f_number()

    def sensor_z_for_focus(self, focus_distance_mm: float = math.inf, wavelength_nm: float = D_LINE_NM) -> float:
        """z of the paraxial image plane for an axial object ``focus_distance_mm`` in front of vertex 0.

        Raises ``ValueError`` when the lens cannot focus there: an object at or inside the front
        focal point has no real image behind the lens (the message gives that distance).
        """
        if not focus_distance_mm > 0:
            raise ValueError(f"focus_distance_mm must be > 0 (or inf), got {focus_distance_mm}")
        system = self.paraxial_system(wavelength_nm)
        distance = _paraxial.image_distance(system, focus_distance_mm)
        if not (math.isfinite(distance) and distance > 0):
            (_, _), (c, d) = system
            front_focus = -d / c if c != 0 else math.inf  # the front focal point's distance in front of vertex 0
            limit = f" (objects must be farther than its front focal point, {front_focus / 1000.0:.4g} m in front of the lens)" if front_focus > 0 else ""
            raise ValueError(
                f"'{self.name}' cannot focus at {focus_distance_mm / 1000.0:g} m: the image would not lie behind the lens{limit}"
            )
        return float(self.vertex_z_mm[-1]) + distance

    # ----------------------------------------------------------------- variants
    def with_stop_radius(self, stop_radius_mm: float) -> "Lens":
        if not 0 < stop_radius_mm <= self.max_stop_radius_mm * (1 + 1e-9):
            raise ValueError(
                f"stop radius {stop_radius_mm:.4g} mm is outside (0, {self.max_stop_radius_mm:.4g}] mm, "
                f"the largest the stop of '{self.name}' allows"
            )
        return eqx.tree_at(lambda lens: lens.stop_radius_mm, self, jnp.asarray(stop_radius_mm, self.stop_radius_mm.dtype))

    def with_f_number(self, f_number: float) -> "Lens":
        """The same lens stopped to ``f_number`` (object at infinity); an error if faster than wide open."""
        if not (isinstance(f_number, (int, float)) and F_NUMBER_RANGE[0] <= f_number <= F_NUMBER_RANGE[1]):
            raise ValueError(f"f_number must be a number from {F_NUMBER_RANGE[0]:g} to {F_NUMBER_RANGE[1]:g}, got {f_number!r}")
        wide_open = self.widest_f_number
        if f_number < wide_open * (1 - 1e-6):
            raise ValueError(f"f/{f_number:g} is faster than '{self.name}' allows: its widest aperture is f/{wide_open:.3g}")
        radius = self.max_stop_radius_mm * wide_open / f_number
        return self.with_stop_radius(min(radius, self.max_stop_radius_mm))

    def with_aperture(self, blades: int | None = None, rotation_deg: float | None = None) -> "Lens":
        """Change the iris: ``blades`` >= 3 for a polygon, 0 for a circle; rotation in degrees."""
        lens = self
        if blades is not None:
            try:
                check_blades(blades, "with_aperture")
            except LensFormatError as error:
                raise ValueError(str(error)) from None
            lens = dataclasses.replace(lens, aperture_blades=blades)
        if rotation_deg is not None:
            lens = eqx.tree_at(lambda l: l.aperture_rotation_rad, lens, jnp.asarray(math.radians(rotation_deg), lens.aperture_rotation_rad.dtype))
        return lens

    def focused_at(self, focus_distance_mm: float, wavelength_nm: float = D_LINE_NM) -> "Lens":
        """Move the sensor to the paraxial image of an axial point ``focus_distance_mm`` in front of vertex 0."""
        z = self.sensor_z_for_focus(focus_distance_mm, wavelength_nm)
        return eqx.tree_at(lambda lens: lens.sensor_z_mm, self, jnp.asarray(z, self.sensor_z_mm.dtype))

    def at_zoom(self, zoom_position: int) -> "Lens":
        """The same lens at another zoom position (thicknesses from the prescription)."""
        lens = build_lens(self.prescription, zoom_position)
        return dataclasses.replace(
            lens,
            aperture_blades=self.aperture_blades,
            aperture_rotation_rad=self.aperture_rotation_rad,
        )

    def at_focal_length(self, focal_length_mm: float) -> "Lens":
        """The same lens zoomed to a paraxial effective focal length of ``focal_length_mm`` (d line).

        A zoom position ``k`` is the value ``u = k`` of a zoom parameter ``u`` in
        ``[0, num_zoom_positions - 1]``; between neighbouring positions every axial gap between
        surfaces (the zoom gaps) is interpolated linearly in ``u``, and ``u`` is solved by
        bisection on the EFL (float64, in the meridian of the prescription's stated focal
        lengths) to 1e-12 relative. At a zoom position's own EFL (within 1e-9 relative) the
        result is :meth:`at_zoom` of that position.

        As with :meth:`at_zoom`, the iris keeps its blades and rotation, its widest opening is
        limited to the stated f-number at the new focal length, and the sensor sits at the end of
        the last gap. If that gap changes with zoom (the prescription puts the sensor at each
        position's back focus), it is set to the paraxial back focal distance at ``u`` plus the
        prescription's small offset from it, interpolated linearly: linearly interpolated group
        spacings are not parfocal, and interpolating the last gap itself would leave the image
        defocused by millimetres between positions. A fixed last gap stays fixed.
        ``zoom_position`` of the result is the nearest zoom position.

        A prime lens (one zoom position) is returned unchanged if ``focal_length_mm`` is within
        1 % of its EFL. Raises ``ValueError`` outside the zoom range (or for a prime lens beyond 1 %).
        """
        target = float(focal_length_mm)
        if not (math.isfinite(target) and target > 0):
            raise ValueError(f"focal_length_mm must be a finite number > 0, got {focal_length_mm!r}")
        prescription = self.prescription
        plane = prescription.stated_focal_length_plane if prescription.stated_focal_length_plane in ("x", "y") else "y"
        count = prescription.num_zoom_positions
        if count <= 1:
            efl = abs(self.focal_length(plane=plane))
            if abs(target - efl) <= 0.01 * efl:
                return self
            raise ValueError(
                f"'{self.name}' has a fixed EFL of {efl:.4g} mm and {target:g} mm was requested: "
                "a prime lens cannot change focal length (only requests within 1 % of its EFL are accepted)"
            )

        table = np.array([s.thicknesses_mm for s in prescription.surfaces], dtype=np.float64)  # (S, zoom positions)
        powers, n = self._powers(D_LINE_NM, plane)

        def thickness_at(u: float) -> np.ndarray:
            k = min(math.floor(u), count - 2)
            fraction = u - k
            if fraction == 0.0:
                return table[:, k].copy()
            if fraction == 1.0:
                return table[:, k + 1].copy()
            mixed = (1.0 - fraction) * table[:, k] + fraction * table[:, k + 1]
            return np.where(table[:, k] == table[:, k + 1], table[:, k], mixed)  # fixed gaps stay bit-exact

        def efl_at(u: float) -> float:
            system = _paraxial.system_matrix(powers, thickness_at(u), n, 0, self.num_surfaces - 1)
            return abs(_paraxial.effective_focal_length(system))

        nodes = [efl_at(float(k)) for k in range(count)]
        shortest, longest = min(nodes), max(nodes)
        if not shortest * (1.0 - 1e-9) <= target <= longest * (1.0 + 1e-9):
            raise ValueError(
                f"{target:g} mm is outside the zoom range of '{self.name}': "
                f"{shortest:.4g} mm to {longest:.4g} mm (paraxial EFL at its {count} zoom positions)"
            )
        for k, efl in enumerate(nodes):
            if abs(efl - target) <= 1e-9 * efl:
                return self.at_zoom(k)

        u = math.nan
        for k in range(count - 1):
            a, b = nodes[k], nodes[k + 1]
            if min(a, b) <= target <= max(a, b):
                low, high, sign_low = float(k), float(k + 1), math.copysign(1.0, a - target)
                for _ in range(200):
                    u = 0.5 * (low + high)
                    error = efl_at(u) - target
                    if abs(error) <= 1e-12 * target or high - low <= 1e-15:
                        break
                    if math.copysign(1.0, error) == sign_low:
                        low = u
                    else:
                        high = u
                break

        thickness = thickness_at(u)
        if u != round(u) and np.any(table[-1] != table[-1, 0]):

            def back_focus_at(position: float) -> float:
                system = _paraxial.system_matrix(powers, thickness_at(position), n, 0, self.num_surfaces - 1)
                return _paraxial.back_focal_distance(system)

            k = min(math.floor(u), count - 2)
            offsets = [table[-1, j] - back_focus_at(float(j)) for j in (k, k + 1)]
            thickness[-1] = back_focus_at(u) + (k + 1 - u) * offsets[0] + (u - k) * offsets[1]
        fixed = dataclasses.replace(
            prescription,
            surfaces=tuple(dataclasses.replace(s, thicknesses_mm=(float(t),)) for s, t in zip(prescription.surfaces, thickness)),
            stated_focal_lengths_mm=(),
        )
        lens = build_lens(fixed, 0)
        where = f"at {target:g} mm (zoom parameter {u:.4f}):"
        return dataclasses.replace(
            lens,
            prescription=prescription,
            zoom_position=round(u),
            notes=tuple(note.replace("at zoom position 0:", where) for note in lens.notes),
            aperture_blades=self.aperture_blades,
            aperture_rotation_rad=self.aperture_rotation_rad,
        )

    def describe(self) -> str:
        """A short multi-line summary (name, source, EFL, f-number, interfaces, ghost paths)."""
        efl_y = self.focal_length()
        lines = [f"{self.name}", f"  source: {self.prescription.source or 'n/a'}"]
        efl = f"{efl_y:.2f} mm"
        efl_x = self.focal_length(plane="x")
        if abs(efl_x - efl_y) > 1e-6 * abs(efl_y):
            efl = f"{efl_y:.2f} mm (y), {efl_x:.2f} mm (x)"
        stated = self.prescription.stated_focal_length_mm
        lines.append(f"  EFL: {efl}" + (f"  (stated {stated:g} mm)" if stated else ""))
        lines.append(f"  f-number: f/{self.widest_f_number:.2f} wide open" + (f"  (stated f/{self.prescription.stated_f_number:g})" if self.prescription.stated_f_number else ""))
        n = self.num_interfaces
        lines.append(f"  surfaces: {self.num_surfaces}, interfaces: {n}, ghost paths: {n * (n - 1) // 2}")
        if self.num_zoom_positions > 1:
            lines.append(f"  zoom positions: {self.num_zoom_positions} (this is {self.zoom_position})")
        return "\n".join(lines)


# --------------------------------------------------------------------- building


GLASS_SUFFIX_RULES: tuple[tuple[str, str], ...] = (
    ("_MOLD", ("a moulded (precision-moulding) version of the catalog glass; its index after moulding, "
               "typically 0.001-0.005 lower, is not modelled")),
    ("-MOLD", "a moulded version of the catalog glass; its lower index after moulding is not modelled"),
)
"""Spelling rules for glass names that catalogs lack: ``(suffix, meaning)``. A name ending in one
of them that is not in the catalogs is looked up without the suffix, and the substitution is
reported in the lens notes."""


def non_dispersive_glass(n_d: float) -> Glass:
    """A medium of index ``n_d`` at every wavelength (a source that gives no Abbe number)."""
    if not (isinstance(n_d, (int, float)) and 1.0 < n_d < 4.0):
        raise ValueError(f"n_d must be a number in (1, 4), got {n_d!r}")
    return Glass(
        name=f"MODEL_{float(n_d)!r}_nodispersion", catalog="MODEL", sellmeier_b=(n_d * n_d - 1.0, 0.0, 0.0), sellmeier_c_um2=(0.0, 0.0, 0.0),
        n_d=n_d, v_d=math.inf, status="model", source="model glass without dispersion (no Abbe number given)",
    )


def _note(notes: list[str], text: str) -> None:
    notes.append(text)
    warnings.warn(text, LensWarning, stacklevel=5)


def _resolve_medium(medium: MediumSpec, surface: SurfaceSpec, prescription: LensPrescription, notes: list[str]) -> Glass | None:
    if medium.is_air:
        return None
    if medium.glass is None:
        try:
            if medium.v_d is None:
                glass = non_dispersive_glass(medium.n_d)
                _note(notes, f"{surface.label}: model glass n_d={medium.n_d} has no Abbe number given; it is used without dispersion")
                return glass
            return model_glass(medium.n_d, medium.v_d)
        except ValueError as error:
            raise LensFormatError(f"{surface.label}: {error}") from None
    catalogs = ((medium.catalog,) if medium.catalog else ()) + tuple(prescription.glass_catalogs)
    try:
        glass = find_glass(medium.glass, catalogs)
    except UnknownGlassError as error:
        for suffix, meaning in GLASS_SUFFIX_RULES:
            if medium.glass.upper().endswith(suffix) and len(medium.glass) > len(suffix):
                try:
                    glass = find_glass(medium.glass[: -len(suffix)], catalogs)
                except UnknownGlassError:
                    continue
                _note(notes, f"{surface.label}: glass {medium.glass!r} read as {glass.qualified_name}: the suffix {suffix} names {meaning}")
                break
        else:
            if medium.n_d is not None and medium.v_d is not None:
                _note(
                    notes,
                    f"{surface.label}: glass {medium.glass!r} is not in the catalogs; substituted a model glass "
                    f"with the stated n_d={medium.n_d}, V_d={medium.v_d}",
                )
                return model_glass(medium.n_d, medium.v_d)
            raise LensFormatError(
                f"{surface.label}: {error}. Map the name to a catalog glass with glass_aliases "
                f"(load_lens(..., glass_aliases={{{medium.glass!r}: 'CATALOG:NAME'}}), or --glass {medium.glass}=CATALOG:NAME on the command line)"
            ) from None
    if medium.n_d is not None and abs(glass.n_d - medium.n_d) > STATED_INDEX_TOLERANCE:
        _note(
            notes,
            f"{surface.label}: catalog glass {glass.catalog}:{glass.name} has n_d={glass.n_d:.5f}, "
            f"but the source states {medium.n_d}; using the catalog glass",
        )
    return glass


def _same_medium(a: Glass | None, b: Glass | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return (a.sellmeier_b, a.sellmeier_c_um2) == (b.sellmeier_b, b.sellmeier_c_um2)


def _default_coating(before: Glass | None, after: Glass | None, spec: CoatingSpec | None) -> CoatingSpec:
    if _same_medium(before, after):
        return UNCOATED  # a stop or dummy surface in one medium cannot reflect
    if spec is not None:
        return spec
    if before is None or after is None:
        return DEFAULT_COATING
    return UNCOATED  # cemented glass-glass interface


def build_lens(prescription: LensPrescription, zoom_position: int = 0) -> Lens:
    """Resolve glasses and coatings, derive missing apertures, and build the array-valued lens."""
    check_prescription(prescription)
    surfaces = prescription.surfaces
    num = len(surfaces)
    if isinstance(zoom_position, bool) or not isinstance(zoom_position, (int, np.integer)) or not 0 <= zoom_position < prescription.num_zoom_positions:
        raise ValueError(f"zoom_position must be in [0, {prescription.num_zoom_positions - 1}] for '{prescription.name}', got {zoom_position}")
    stop_index = prescription.stop_surface_index
    notes: list[str] = []
    media: list[Glass | None] = [None]
    for surface in surfaces:
        media.append(_resolve_medium(surface.medium, surface, prescription, notes))
    if media[-1] is not None:
        raise LensFormatError(f"{surfaces[-1].label}: the medium after the last surface (image space) must be air")
    coatings = [_default_coating(media[s], media[s + 1], surfaces[s].coating) for s in range(num)]
    interface_surfaces = tuple(s for s in range(num) if not _same_medium(media[s], media[s + 1]))
    if not interface_surfaces:
        raise LensFormatError(
            f"{prescription.path or prescription.name}: the lens has no refracting interface (air, or one medium, on both sides of "
            "every surface), so it forms no image; give a glass (medium or n_d/v_d) after the surfaces of its elements"
        )

    max_layers = max([1] + [len(c.layers) for c in coatings])
    coating_indices = np.ones((num, max_layers))
    coating_thicknesses = np.zeros((num, max_layers))
    for s, coating in enumerate(coatings):
        for k, layer in enumerate(coating.layers):
            coating_indices[s, k] = layer.index
            coating_thicknesses[s, k] = layer.thickness_nm

    max_aspheric = max([1] + [len(s.aspheric_coefficients) for s in surfaces])
    aspheric = np.zeros((num, max_aspheric))
    for s, surface in enumerate(surfaces):
        aspheric[s, : len(surface.aspheric_coefficients)] = surface.aspheric_coefficients

    sellmeier_b = np.zeros((num + 1, 3))
    sellmeier_c = np.zeros((num + 1, 3))
    for m, glass in enumerate(media):
        if glass is not None:
            sellmeier_b[m] = glass.sellmeier_b
            sellmeier_c[m] = glass.sellmeier_c_um2

    thickness = np.array([s.thicknesses_mm[zoom_position] for s in surfaces], dtype=np.float64)
    for s, t in enumerate(thickness):
        if t < 0:
            raise LensFormatError(f"{surfaces[s].label}: negative thickness {t} mm")
    semi_aperture = np.array([s.semi_aperture_mm for s in surfaces], dtype=np.float64)

    lens = Lens(
        curvature_per_mm=jnp.asarray([s.curvature_per_mm for s in surfaces]),
        conic=jnp.asarray([s.conic for s in surfaces]),
        aspheric_coefficients=jnp.asarray(aspheric),
        surface_kind=jnp.asarray([SurfaceKind.from_label(s.kind) for s in surfaces], dtype=jnp.int32),
        thickness_mm=jnp.asarray(thickness),
        semi_aperture_mm=jnp.asarray(semi_aperture),
        sellmeier_b=jnp.asarray(sellmeier_b),
        sellmeier_c_um2=jnp.asarray(sellmeier_c),
        medium_is_air=jnp.asarray([g is None for g in media]),
        coating_indices=jnp.asarray(coating_indices),
        coating_thicknesses_nm=jnp.asarray(coating_thicknesses),
        stop_radius_mm=jnp.asarray(semi_aperture[stop_index]),
        aperture_rotation_rad=jnp.asarray(math.radians(prescription.aperture_rotation_deg)),
        sensor_z_mm=jnp.asarray(float(np.sum(thickness))),
        stop_index=stop_index,
        aperture_blades=prescription.aperture_blades,
        interface_surfaces=interface_surfaces,
        has_aspheres=bool(np.any(aspheric != 0.0)),
        zoom_position=zoom_position,
        prescription=prescription,
        media=tuple(media[1:]),
        notes=(),
    )
    if np.any(np.isnan(semi_aperture)):
        lens = _derive_semi_apertures(lens, notes)
    lens = _limit_iris_to_stated_f_number(lens, notes)
    lens = _limit_iris_to_entrance_pupil(lens, notes)
    return dataclasses.replace(lens, notes=tuple(notes))


def _limit_iris_to_stated_f_number(lens: Lens, notes: list[str]) -> Lens:
    """Open the iris no wider than the lens's stated maximum aperture.

    A prescription's stop semi-aperture can allow a faster f-number than the product has: for a
    constant-aperture zoom the stop is sized for the slowest zoom position, and estimated stops are
    rounded up. The iris of the real lens stops at the stated f-number, so the stop's clear
    semi-aperture (the widest iris) is reduced to the radius that gives exactly that f-number at
    this zoom position (the paraxial f-number is inversely proportional to the stop radius).
    """
    stated = lens.prescription.stated_f_number
    if stated is None:
        return lens
    wide_open = lens.f_number()
    if not wide_open < stated * (1.0 - 1e-3):
        return lens
    radius = lens.max_stop_radius_mm * wide_open / stated
    notes.append(
        f"{lens.prescription.path or lens.name}: iris limited to the stated f/{stated:g} at zoom position {lens.zoom_position}: "
        f"stop semi-aperture {lens.max_stop_radius_mm:.3f} mm (f/{wide_open:.3g}) reduced to {radius:.3f} mm"
    )
    semi = lens.semi_aperture_mm.at[lens.stop_index].set(radius)
    lens = eqx.tree_at(lambda l: l.semi_aperture_mm, lens, semi)
    return eqx.tree_at(lambda l: l.stop_radius_mm, lens, semi[lens.stop_index])


def _limit_iris_to_entrance_pupil(lens: Lens, notes: list[str]) -> Lens:
    """Open the iris no wider than the entrance pupil diameter the source gives (Zemax ``ENPD``)."""
    diameter = lens.prescription.entrance_pupil_diameter_mm
    if diameter is None:
        return lens
    _, pupil_radius = lens.entrance_pupil()
    if not pupil_radius > 0.5 * diameter * (1.0 + 1e-3):
        return lens
    radius = lens.max_stop_radius_mm * 0.5 * diameter / pupil_radius
    notes.append(
        f"{lens.prescription.path or lens.name}: iris limited to the stated entrance pupil diameter {diameter:g} mm: "
        f"stop semi-aperture {lens.max_stop_radius_mm:.3f} mm reduced to {radius:.3f} mm"
    )
    semi = lens.semi_aperture_mm.at[lens.stop_index].set(radius)
    lens = eqx.tree_at(lambda l: l.semi_aperture_mm, lens, semi)
    return eqx.tree_at(lambda l: l.stop_radius_mm, lens, semi[lens.stop_index])


def _derive_semi_apertures(lens: Lens, notes: list[str]) -> Lens:
    """Fill missing clear semi-apertures from a paraxial marginal ray and a chief ray at the corner
    of the sensor, with a 5 % margin, capped below |R|.

    The marginal ray's entrance height comes from, in this order: the stated f-number, the stated
    entrance pupil diameter, the stop's own semi-aperture, or (when the stop has none) the largest
    axial beam that the surfaces with a semi-aperture let through.
    """
    prescription = lens.prescription
    where = prescription.path or prescription.name
    efl = lens.focal_length()
    if not (math.isfinite(efl) and efl != 0.0):
        raise LensFormatError(f"{where}: semi-apertures are missing and cannot be derived: the lens is afocal (no focal length)")
    half_field = math.atan(0.5 * math.hypot(prescription.sensor_width_mm, prescription.sensor_height_mm) / abs(efl))
    powers, n = lens._powers(D_LINE_NM, "y")
    thickness = np.asarray(lens.thickness_mm, np.float64)
    stop = lens.stop_index
    if stop > 0:
        front = _paraxial.system_matrix(powers, thickness, n, 0, stop - 1)
        front = _paraxial.transfer_matrix(thickness[stop - 1], n[stop]) @ front
    else:
        front = np.eye(2)
    (a, b), _ = front
    semi = np.asarray(lens.semi_aperture_mm, np.float64).copy()

    def heights(entrance: float) -> np.ndarray:
        rays = np.stack([np.array([entrance, 0.0]), np.array([-b / a * math.tan(half_field), math.tan(half_field)])], axis=1)
        out = np.zeros((lens.num_surfaces, 2))
        for s in range(lens.num_surfaces):
            if s > 0:
                rays = _paraxial.transfer_matrix(thickness[s - 1], n[s]) @ rays
            out[s] = np.abs(rays[0])
            rays = _paraxial.refraction_matrix(powers[s]) @ rays
        return out

    if prescription.stated_f_number is not None:
        entrance_radius = abs(efl) / (2.0 * prescription.stated_f_number)
        source = f"the stated f/{prescription.stated_f_number:g}"
    elif prescription.entrance_pupil_diameter_mm is not None:
        entrance_radius = 0.5 * prescription.entrance_pupil_diameter_mm
        source = f"the stated entrance pupil diameter {prescription.entrance_pupil_diameter_mm:g} mm"
    elif math.isfinite(semi[stop]) and a != 0.0:
        entrance_radius = semi[stop] / abs(a)
        source = f"the stop's semi-aperture {semi[stop]:.4g} mm"
    else:
        unit = heights(1.0)[:, 0]
        known = [s for s in range(lens.num_surfaces) if s != stop and math.isfinite(semi[s]) and unit[s] > 0]
        if not known or a == 0.0:
            missing = [prescription.surfaces[s].label or f"surface {s}" for s in range(lens.num_surfaces) if math.isnan(semi[s])]
            raise LensFormatError(
                f"{where}: semi-apertures are missing ({'; '.join(missing[:4])}{' ...' if len(missing) > 4 else ''}) and nothing defines "
                "the aperture to derive them from: state the f-number (f_number), give the stop a semi-aperture, or give the "
                "semi-apertures"
            )
        limiting = min(known, key=lambda s: semi[s] / unit[s])
        entrance_radius = semi[limiting] / unit[limiting]
        source = (
            f"the widest axial beam the given apertures pass (limited by {prescription.surfaces[limiting].label or f'surface {limiting}'}; "
            f"f/{abs(efl) / (2.0 * entrance_radius):.3g}), since neither an f-number nor a stop size is given"
        )
    ray_heights = heights(entrance_radius)
    derived = []
    for s, surface in enumerate(prescription.surfaces):
        if math.isnan(semi[s]):
            value = ray_heights[s, 0] if s == stop else 1.05 * (ray_heights[s, 0] + ray_heights[s, 1])
            if math.isfinite(surface.radius_mm):
                value = min(value, 0.98 * abs(surface.radius_mm))
            semi[s] = value
            derived.append(s)
    note = (
        f"{where}: semi-apertures of surfaces {derived} derived from paraxial marginal ({source}) and chief rays "
        f"({math.degrees(half_field):.1f} deg half field, the sensor corner) with a 5 % margin; not in the source"
    )
    notes.append(note)
    warnings.warn(note, LensWarning, stacklevel=3)
    semi_jnp = jnp.asarray(semi)
    lens = eqx.tree_at(lambda l: l.semi_aperture_mm, lens, semi_jnp)
    return eqx.tree_at(lambda l: l.stop_radius_mm, lens, semi_jnp[stop])
