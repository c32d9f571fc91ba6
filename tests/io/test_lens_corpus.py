"""Every real lens file in ``tests/data`` (sources and licences in ``tests/data/README.md``): it
loads, or is refused with a one-line message naming the file and line; where the source states a
focal length, the traced EFL agrees with it. Lens loading only: no tracing beyond the paraxial
methods, so the whole corpus takes a few seconds."""

from __future__ import annotations

import math
import re
import warnings

import pytest

import jaxflare
from tests.helpers import DATA

LENS_EXTENSIONS = (".zmx", ".lens", ".json", ".xml", ".dat")

# file (relative to tests/data) -> (load options, expected: "load" or a regex of the refusal, stated EFL tolerance)
EXPECTED = {
    "zmx/double_gauss_50mm.zmx": ({}, "load", None),
    "zmx/double_gauss_50mm_utf16.zmx": ({}, "load", None),
    "zmx/US05831776-1.zmx": ({}, "load", None),
    "zmx/US00583336-2-scaled.zmx": ({}, "load", None),
    "zmx/US08427765-1.ZMX": ({}, "load", None),  # L-TIM28_MOLD by the suffix rule
    "zmx/laikin_100deg_wide_angle.zmx": ({}, "load", None),
    "zmx/optiland_lens1_enpd.zmx": ({}, "load", None),
    "zmx/optiland_lens_floa.zmx": ({}, "load", None),
    "zmx/EP0770895A2-embodiment-1.zmx": ({}, "load", None),
    "zmx/HoO-V2C18Ex03.zmx": ({}, r"HoO-V2C18Ex03\.zmx:86: GLAS MIRROR: reflecting surfaces are not supported", None),
    "zmx/HoO-V2C18Ex66.zmx": ({}, r"HoO-V2C18Ex66\.zmx:83: TYPE COORDBRK: coordinate breaks", None),
    "lens/AF_Nikkor_85mm_F1.4D_IF.lens": ({"semi_aperture": "auto"}, "load", 0.01),
    "lens/Zeiss_50mm_F1.4_Planar_T.lens": ({"semi_aperture": "auto"}, "load", 0.01),
    "lens/Zeiss_100mm_F4.5_Tessar.lens": ({}, "load", 0.01),
    "lens/Anamorphic_Test_50mm_2x.lens": ({}, "load", None),  # synthetic; states "about 50 mm"
    "realflare/kodak_100mm.json": ({}, "load", 0.01),
    "realflare/leica_35mm_1_4.json": ({}, "load", 0.015),
    "realflare/tronnier_color_heliar.json": ({}, "load", 0.05),  # realflare's transcription is 4.2 % off its stated 105 mm
    "lentil/lenses_subset.json#0001": ({}, "load", 0.01),
    "lentil/lenses_subset.json#0004": ({}, "load", 0.01),
    "lentil/lenses_subset.json#0009": ({}, "load", 0.01),
    "lentil/lenses_subset.json#2004": ({}, "load", 0.02),  # anamorphic: x plane
    "openlensflare/heliar-tronnier.xml": ({}, "load", 0.01),
    "openlensflare/itoh-zoom-short.xml": ({}, "load", 0.01),
    "pbrt/tronnier_double_gauss.50mm.dat": ({}, "load", 0.01),
}


def corpus_files() -> list[str]:
    files = []
    for path in sorted(DATA.rglob("*")):
        if path.suffix.lower() in LENS_EXTENSIONS and path.is_file():
            relative = path.relative_to(DATA).as_posix()
            if path.suffix.lower() == ".json" and "lentil" in relative:
                files.extend(key for key in EXPECTED if key.startswith(relative + "#"))
            else:
                files.append(relative)
    return files


def test_every_corpus_file_has_an_expectation():
    """A file added to tests/data must say what it should do."""
    assert sorted(corpus_files()) == sorted(EXPECTED)
    assert len(EXPECTED) >= 12


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_corpus_file(name):
    options, expected, tolerance = EXPECTED[name]
    source = str(DATA / name)
    if expected != "load":
        with pytest.raises(jaxflare.LensFormatError) as info:
            jaxflare.load_lens(source, **options)
        message = str(info.value)
        assert re.search(expected, message), message
        assert "\n" not in message
        return
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        lens = jaxflare.load_lens(source, **options)
    prescription = lens.prescription
    plane = prescription.stated_focal_length_plane
    efl = abs(lens.focal_length(plane=plane))
    assert math.isfinite(efl) and efl > 0
    assert lens.num_interfaces >= 2
    semi = [float(s) for s in lens.semi_aperture_mm]
    assert all(math.isfinite(s) and s > 0 for s in semi)
    for surface, s in zip(prescription.surfaces, semi):  # no clear aperture beyond a sphere's rim
        if math.isfinite(surface.radius_mm) and surface.conic == 0.0 and not surface.aspheric_coefficients:
            assert s <= abs(surface.radius_mm) * (1 + 1e-12), surface.label
    if tolerance is not None:
        stated = prescription.stated_focal_length_mm
        assert stated, f"{name} states no focal length"
        assert abs(efl - stated) <= tolerance * stated, f"{name}: EFL {efl:.3f} mm, stated {stated} mm"
    else:
        assert prescription.stated_focal_length_mm is None or "Anamorphic" in name


def test_opticstudio_records_are_skipped_and_listed():
    """The OpticStudio 2022 file: AUTH, IWDP, SSID, LUID, EERA are skipped and named in the notes;
    its OpticStudio NOTE paragraphs are read as text."""
    prescription = jaxflare.read_prescription(DATA / "zmx" / "laikin_100deg_wide_angle.zmx")
    skipped = next(line for line in prescription.notes.splitlines() if line.startswith("skipped records that do not change"))
    for keyword in ("AUTH", "IWDP", "SSID", "LUID", "EERA"):
        assert keyword in skipped
    assert prescription.notes.splitlines()[0] == "Notes..."


def test_system_apertures_of_real_files():
    """ENPD and FLOA: the files' own aperture definitions size the stop (no 'f_number is missing')."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        enpd = jaxflare.load_lens(DATA / "zmx" / "optiland_lens1_enpd.zmx")
        floa = jaxflare.load_lens(DATA / "zmx" / "optiland_lens_floa.zmx")
    assert enpd.prescription.entrance_pupil_diameter_mm == pytest.approx(8.333333969116211)
    assert 2 * enpd.entrance_pupil()[1] == pytest.approx(8.333333969116211, rel=1e-9)
    assert any("the stated entrance pupil diameter" in note for note in enpd.notes)
    assert floa.max_stop_radius_mm == 8.5  # the stop's DIAM
    assert any("the stop's semi-aperture 8.5 mm" in note for note in floa.notes)


def test_moulded_glass_suffix_and_aliases():
    path = DATA / "zmx" / "US08427765-1.ZMX"
    with pytest.warns(jaxflare.LensWarning, match=r"'L-TIM28_MOLD' read as OHARA:L-TIM28"):
        by_rule = jaxflare.load_lens(path)
    aliased = jaxflare.load_lens(path, glass_aliases={"l-tim28_mold": "OHARA:S-TIM28"})
    assert "mapped to 'OHARA:S-TIM28' (glass_aliases)" in aliased.prescription.notes
    glasses = {g.qualified_name for g in aliased.media if g is not None}
    assert "OHARA:S-TIM28" in glasses and "OHARA:L-TIM28" not in glasses
    assert {g.qualified_name for g in by_rule.media if g is not None} - glasses == {"OHARA:L-TIM28"}


def test_diameter_columns_need_an_explicit_choice():
    """A .lens file whose aperture column holds diameters is refused as it stands, with the
    options named; 'diameter' halves the column, 'auto' derives every aperture (both reported)."""
    path = DATA / "lens" / "AF_Nikkor_85mm_F1.4D_IF.lens"
    with pytest.raises(jaxflare.LensFormatError, match=r"AF_Nikkor_85mm_F1\.4D_IF\.lens:12: surface 0: semi-aperture 64\.62 mm is larger than the sphere allows.*'diameter'.*'auto'"):
        jaxflare.read_prescription(path)
    halved = jaxflare.read_prescription(path, semi_aperture="diameter")
    assert halved.surfaces[0].semi_aperture_mm == pytest.approx(32.31)
    assert "read as diameters and halved" in halved.notes
    auto = jaxflare.read_prescription(path, semi_aperture="auto")
    assert all(math.isnan(s.semi_aperture_mm) for s in auto.surfaces)
    with pytest.warns(jaxflare.LensWarning, match=r"derived from paraxial marginal \(the stated f/1\.4\)"):
        lens = jaxflare.load_lens(auto)
    assert lens.widest_f_number == pytest.approx(1.4, rel=1e-6)
    clipped = jaxflare.read_prescription(path, semi_aperture="clip")
    assert clipped.surfaces[0].semi_aperture_mm == pytest.approx(0.98 * 54.6447)
    with pytest.raises(ValueError, match=r"semi_aperture must be one of 'file', 'auto', 'diameter', 'clip'"):
        jaxflare.read_prescription(path, semi_aperture="guess")


def test_formats_without_an_iris_choose_the_limiting_surface(tmp_path):
    """A model without its iris: the stop becomes the surface that clips an axial beam first, which
    real rays confirm: just inside the entrance pupil they pass, just outside they are lost there."""
    import json

    import jax.numpy as jnp

    model = json.loads((DATA / "realflare" / "kodak_100mm.json").read_text())
    del model["aperture_index"]
    (tmp_path / "no_iris.json").write_text(json.dumps(model))
    prescription = jaxflare.read_prescription(tmp_path / "no_iris.json")
    chosen = prescription.stop_surface_index
    assert f"the model has no 'aperture_index': the aperture stop is {prescription.surfaces[chosen].label}" in prescription.notes
    lens = jaxflare.load_lens(prescription)
    _, pupil = lens.entrance_pupil()
    heights = jnp.array([0.98, 1.02]) * pupil
    origins = jnp.stack([jnp.zeros(2), heights, jnp.full(2, -1.0)], axis=-1)
    directions = jnp.tile(jnp.array([[0.0, 0.0, 1.0]]), (2, 1))
    result = jaxflare.trace(lens, origins, directions)
    assert bool(result.valid[0]) and not bool(result.valid[1])
    assert int(result.lost_at_surface[1]) == chosen


def test_pbrt_film_at_focus():
    prescription = jaxflare.read_prescription(DATA / "pbrt" / "tronnier_double_gauss.50mm.dat")
    assert prescription.surfaces[0].semi_aperture_mm == 12.6  # half the 25.2 diameter
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lens = jaxflare.load_lens(prescription)
    assert float(lens.sensor_z_mm) == pytest.approx(lens.sensor_z_for_focus(), abs=1e-9)
    assert "paraxial back focus" in prescription.notes


def test_converted_files_round_trip_through_toml(tmp_path):
    """Any importer's prescription converts to the TOML format and back, semi-apertures 'auto' kept."""
    from jaxflare.cli import main

    target = tmp_path / "nikkor.toml"
    assert main(["lens", "convert", str(DATA / "lens" / "AF_Nikkor_85mm_F1.4D_IF.lens"), str(target), "--semi-aperture", "auto"]) == 0
    text = target.read_text()
    assert text.count('semi_aperture = "auto"') == 18
    again = jaxflare.read_prescription(target)
    original = jaxflare.read_prescription(DATA / "lens" / "AF_Nikkor_85mm_F1.4D_IF.lens", semi_aperture="auto")
    assert [s.radius_mm for s in again.surfaces] == [s.radius_mm for s in original.surfaces]
    assert again.stated_f_number == 1.4 and again.stated_focal_length_mm == 85.0
