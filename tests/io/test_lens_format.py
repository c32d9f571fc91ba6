"""The jaxflare TOML lens format: parsing, round trip, and clear errors for bad files."""

import dataclasses
import math

import pytest
from tests.helpers import lens_from_toml

import jaxflare

GOOD = """
name = "test doublet"
source = "made up"
focal_length_mm = 100.0
f_number = 4.0
aperture_blades = 6
surfaces = [
  { radius = 61.0, thickness = 6.0, medium = "N-BK7", semi_aperture = 13.0 },
  { radius = -45.0, thickness = 2.5, n_d = 1.6727, v_d = 32.2, semi_aperture = 13.0, coating = "none" },
  { radius = -130.0, thickness = 5.0, semi_aperture = 13.0, coating = { layers = [[1.38, 99.6], [2.1, 65.5]] } },
  { radius = "flat", thickness = 92.0, semi_aperture = 12.0, stop = true },
]
"""


def test_parse_good_file():
    prescription = jaxflare.parse_lens_toml(GOOD, "good.toml")
    assert prescription.name == "test doublet"
    assert prescription.aperture_blades == 6
    assert [s.is_stop for s in prescription.surfaces] == [False, False, False, True]
    assert math.isinf(prescription.surfaces[3].radius_mm)
    assert prescription.surfaces[0].medium.glass == "N-BK7"
    assert prescription.surfaces[1].medium.n_d == 1.6727
    assert len(prescription.surfaces[2].coating.layers) == 2
    lens = jaxflare.build_lens(prescription)
    assert lens.num_interfaces == 3  # the stop in air is not an interface
    assert lens.aperture_blades == 6


def test_round_trip_through_toml_text():
    prescription = jaxflare.parse_lens_toml(GOOD, "good.toml")
    again = jaxflare.parse_lens_toml(jaxflare.lens_toml_text(prescription), "good.toml")
    strip = lambda p: [dataclasses.replace(s, label="") for s in p.surfaces]  # noqa: E731
    assert strip(again) == strip(prescription)
    assert (again.name, again.stated_f_number, again.aperture_blades) == (prescription.name, 4.0, 6)


@pytest.mark.parametrize(
    "edit, message",
    [
        ((", semi_aperture = 13.0 },", " },"), r"bad\.toml:8: surface 0: missing required key 'semi_aperture'"),
        (("thickness = 6.0", "thickness = -6.0"), r"bad\.toml:8: surface 0: 'thickness' must be >= 0"),
        (("radius = 61.0, thickness = 6.0, medium = \"N-BK7\", semi_aperture = 13.0", "radius = 10.0, thickness = 6.0, medium = \"N-BK7\", semi_aperture = 13.0"), r"surface 0: semi_aperture 13.0 mm is larger than the sphere allows"),
        ((", stop = true", ""), r"bad\.toml: exactly one surface must have 'stop = true', found 0"),
        (("coating = \"none\"", "colour = \"none\""), r"bad\.toml:9: surface 1: unknown key\(s\) \['colour'\]"),
        (("f_number = 4.0", "f_number = 4.0\nfocal = 3"), r"unknown key\(s\) \['focal'\]"),
        (("radius = -45.0", "radius = \"steep\""), r"surface 1: 'radius' must be a number or \"flat\""),
        (("aperture_blades = 6", "aperture_blades = 2"), r"'aperture_blades' must be 0 \(circular\) or an integer from 3 to 64"),
        (("coating = \"none\"", "coating = \"gold\""), r"unknown coating 'gold'"),
        (("surfaces = [", "surfaces = [ oops"), r"bad\.toml: not valid TOML"),
    ],
)
def test_bad_files_name_file_surface_and_reason(edit, message):
    old, new = edit
    assert old in GOOD
    with pytest.raises(jaxflare.LensFormatError, match=message):
        jaxflare.parse_lens_toml(GOOD.replace(old, new, 1), "bad.toml")


def test_unknown_glass_names_surface_and_near_matches():
    with pytest.raises(jaxflare.LensFormatError, match=r"surface 0.*N-BK8.*N-BK7"):
        lens_from_toml(GOOD.replace("N-BK7", "N-BK8"), "bad.toml")


def test_unknown_glass_with_stated_values_is_an_explicit_substitution():
    text = GOOD.replace('medium = "N-BK7"', 'medium = "UNOBTAINIUM-7", n_d = 1.5168, v_d = 64.17')
    with pytest.warns(jaxflare.LensWarning, match="UNOBTAINIUM-7.*substituted a model glass"):
        lens = lens_from_toml(text)
    assert any("substituted" in note for note in lens.notes)
    assert lens.media[0].n_d == pytest.approx(1.5168)


def test_stated_index_mismatch_is_reported():
    text = GOOD.replace('medium = "N-BK7"', 'medium = "N-BK7", n_d = 1.60, v_d = 64.17')
    with pytest.warns(jaxflare.LensWarning, match="N-BK7 has n_d=1.516"):
        lens_from_toml(text)


def test_zoom_thickness_lists():
    text = GOOD.replace("thickness = 2.5", "thickness = [2.5, 3.5, 4.5]").replace("thickness = 92.0", "thickness = [92.0, 90.0, 88.0]")
    text = text.replace("focal_length_mm = 100.0", "focal_length_mm = [100.0, 101.0, 102.0]")
    prescription = jaxflare.parse_lens_toml(text, "zoom.toml")
    assert prescription.num_zoom_positions == 3
    assert prescription.surfaces[0].thicknesses_mm == (6.0, 6.0, 6.0)  # fixed gaps repeat
    lens = jaxflare.build_lens(prescription, 2)
    assert float(lens.thickness_mm[1]) == 4.5
    assert float(lens.at_zoom(1).thickness_mm[3]) == 90.0
    with pytest.raises(jaxflare.LensFormatError, match=r"2 thicknesses, but other surfaces give 3 zoom positions"):
        jaxflare.parse_lens_toml(text.replace("thickness = 6.0", "thickness = [6.0, 7.0]"), "zoom.toml")
    with pytest.raises(ValueError, match=r"zoom_position must be in \[0, 2\]"):
        jaxflare.build_lens(prescription, 3)


def test_missing_semi_apertures_are_derived_and_reported():
    text = GOOD.replace("semi_aperture = 13.0", 'semi_aperture = "auto"')
    with pytest.warns(jaxflare.LensWarning, match=r"semi-apertures of surfaces \[0, 1, 2\] derived"):
        lens = lens_from_toml(text)
    semi = [float(v) for v in lens.semi_aperture_mm]
    assert all(s > 0 for s in semi)
    # the derived apertures pass the stated f/4 marginal ray (entrance pupil radius = EFL / 8)
    assert semi[0] >= lens.focal_length() / 8.0


def test_load_lens_errors():
    with pytest.raises(FileNotFoundError, match=r"no lens named 'zeiss_biotr'.*Did you mean: zeiss_biotar"):
        jaxflare.load_lens("zeiss_biotr")
    with pytest.raises(FileNotFoundError, match=r"lens file not found: missing\.toml"):
        jaxflare.load_lens("missing.toml")


def test_lens_file_path_and_bundled_name_agree(tmp_path):
    path = tmp_path / "copy.toml"
    bundled = jaxflare.read_prescription("zeiss_biotar")
    path.write_text(jaxflare.lens_toml_text(bundled))
    assert jaxflare.load_lens(str(path)).focal_length() == pytest.approx(jaxflare.load_lens("zeiss_biotar").focal_length(), rel=1e-12)
