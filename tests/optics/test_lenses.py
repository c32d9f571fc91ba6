"""Every bundled lens: its traced focal length against the one its source states, and sanity of
the prescription (source named, stop, sensor at focus, rays through the centre of the field)."""

import math

import numpy as np
import pytest

import jaxflare

EFL_TOLERANCE = 0.015
"""Relative tolerance on the traced EFL against the source's stated focal length.

Patents state focal lengths rounded to a few digits ("f = 100"), their radii are rounded to
0.01 mm and their indices to 4-5 digits, and most were designed with tabulated indices at the e or
d line rather than our catalog/model-glass Sellmeier data. Those effects together move the EFL by a
few tenths of a percent; 1.5 % still catches any transcription error that matters (a wrong radius
or thickness on a powered surface moves the EFL by several percent), which is the point of the check.
"""

EFL_TOLERANCE_EXCEPTIONS = {
    # US 6,310,731 states f = 31 mm for the squeezed (x) axis. Our paraxial x-plane EFL of the
    # public transcription is 31.49 mm (+1.6 %); lentil's own finite-ray value for the same data
    # is 30.41 mm (-1.9 %), so the stated value lies between two independent evaluations and no
    # single transcription error explains it. Kept at 2 % until the patent scan can be checked.
    "Schneider 2x anamorphic 31 mm (cylindrical front attachment + spherical prime)": 0.02,
}

NAMES = jaxflare.bundled_lens_names()


def test_enough_lenses_are_bundled():
    assert len(NAMES) >= 8
    for required in ("zeiss_biotar", "angenieux_double_gauss", "tronnier_heliar", "tronnier_double_gauss", "nikon_afs_28_70_zoom"):
        assert required in NAMES


@pytest.fixture(scope="module", params=NAMES)
def lens(request) -> jaxflare.Lens:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jaxflare.LensWarning)
        return jaxflare.load_lens(request.param)


def _stated_focal_lengths(lens):
    prescription = lens.prescription
    if prescription.stated_focal_lengths_mm:
        return prescription.stated_focal_lengths_mm
    return (prescription.stated_focal_length_mm,)


def test_source_and_metadata(lens):
    prescription = lens.prescription
    assert prescription.source, "every bundled lens names its source"
    assert prescription.stated_focal_length_mm is not None
    assert prescription.stated_f_number is not None
    assert 0 <= lens.stop_index < lens.num_surfaces


def test_traced_focal_length_matches_the_stated_one(lens):
    for zoom, stated in enumerate(_stated_focal_lengths(lens)):
        at_zoom = lens.at_zoom(zoom) if zoom else lens
        plane = lens.prescription.stated_focal_length_plane
        traced = at_zoom.focal_length(lens.prescription.design_wavelength_nm, plane)
        tolerance = EFL_TOLERANCE_EXCEPTIONS.get(lens.prescription.name, EFL_TOLERANCE)
        assert traced == pytest.approx(stated, rel=tolerance), f"{lens.name} zoom {zoom}: traced {traced:.3f} mm vs stated {stated} mm"


def _is_anamorphic(lens):
    return bool(np.any(np.asarray(lens.surface_kind) != 0))


def test_sensor_is_at_the_paraxial_focus(lens):
    for zoom in range(lens.num_zoom_positions):
        at_zoom = lens.at_zoom(zoom) if zoom else lens
        focus = at_zoom.sensor_z_for_focus(math.inf)
        assert float(at_zoom.sensor_z_mm) == pytest.approx(focus, abs=max(0.01 * abs(at_zoom.focal_length()), 0.5))


def test_widest_f_number_is_close_to_the_stated_one(lens):
    assert lens.widest_f_number == pytest.approx(lens.prescription.stated_f_number, rel=0.15)


def test_axial_bundle_passes_and_focuses(lens):
    """Rays over the central half of the entrance pupil reach the sensor near the axis."""
    z_pupil, r_pupil = lens.entrance_pupil()
    rho = np.linspace(-0.5, 0.5, 11) * r_pupil
    origins = np.column_stack([np.zeros_like(rho), rho, np.full_like(rho, -5.0)])
    directions = np.tile([0.0, 0.0, 1.0], (rho.size, 1))
    result = jaxflare.trace(lens, origins, directions, lens.prescription.design_wavelength_nm)
    assert bool(np.all(np.asarray(result.valid)))
    blur = np.max(np.abs(np.asarray(result.positions[:, :2])))
    assert blur < 0.01 * abs(lens.focal_length()) + 0.05, f"axial blur {blur:.3f} mm"


def test_ghost_path_count(lens):
    n = lens.num_interfaces
    assert len(jaxflare.ghost_paths(lens)) == n * (n - 1) // 2


def test_zoom_lens_has_27_interfaces_and_several_positions():
    zoom = jaxflare.load_lens("nikon_afs_28_70_zoom")
    assert zoom.num_interfaces == 27
    assert zoom.num_zoom_positions >= 3
    efls = [zoom.at_zoom(k).focal_length() for k in range(zoom.num_zoom_positions)]
    assert efls == sorted(efls) and efls[-1] / efls[0] > 2.0


def test_anamorphic_lens_has_different_focal_lengths_in_x_and_y():
    names = [name for name in NAMES if "anamorphic" in name]
    assert names
    lens = jaxflare.load_lens(names[0])
    assert _is_anamorphic(lens)
    ratio = lens.focal_length(plane="y") / lens.focal_length(plane="x")
    assert abs(math.log(ratio)) > math.log(1.2)  # a real squeeze, not a rounding difference
