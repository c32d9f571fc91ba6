"""Zemax OpticStudio ``.zmx`` import and export (``jaxflare.io._zemax``).

Everything here is plain Python on small texts: no tracing, no JAX arrays."""

from __future__ import annotations

import codecs
import dataclasses
import math
import os
import random
from pathlib import Path

import pytest

import jaxflare
from jaxflare.optics import (
    AIR,
    CoatingSpec,
    LensFormatError,
    LensPrescription,
    MediumSpec,
    SurfaceSpec,
)
from jaxflare.io import decode_zmx_bytes, parse_zmx, read_zmx, write_zmx, zmx_text

DATA = Path(__file__).resolve().parents[1] / "data" / "zmx"
FIXTURE = DATA / "double_gauss_50mm.zmx"
FIXTURE_UTF16 = DATA / "double_gauss_50mm_utf16.zmx"


# ----------------------------------------------------------------------------- helpers


def _same_value(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(_same_value(x, y) for x, y in zip(a, b))
    if dataclasses.is_dataclass(a) and dataclasses.is_dataclass(b):
        return type(a) is type(b) and all(_same_value(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))
    return a == b


def assert_same_prescription(actual: LensPrescription, expected: LensPrescription) -> None:
    """Field by field, exact (floats compared with ==, nan equal to nan), naming the first difference."""
    for field in dataclasses.fields(LensPrescription):
        if field.name == "surfaces":
            continue
        a, b = getattr(actual, field.name), getattr(expected, field.name)
        assert _same_value(a, b), f"{field.name}: {a!r} != {b!r}"
    assert len(actual.surfaces) == len(expected.surfaces), "number of surfaces"
    for k, (sa, sb) in enumerate(zip(actual.surfaces, expected.surfaces)):
        for field in dataclasses.fields(SurfaceSpec):
            a, b = getattr(sa, field.name), getattr(sb, field.name)
            assert _same_value(a, b), f"surface {k} {field.name}: {a!r} != {b!r}"


def zmx_representable(p: LensPrescription) -> LensPrescription:
    """What a .zmx file keeps of a prescription: per-glass catalogs move to GCAT, thin-film coatings
    are dropped, and the metadata that has no .zmx record takes its default."""
    catalogs = list(p.glass_catalogs)
    surfaces = []
    for s in p.surfaces:
        if s.medium.catalog and s.medium.catalog.upper() not in catalogs:
            catalogs.append(s.medium.catalog.upper())
        surfaces.append(dataclasses.replace(s, medium=dataclasses.replace(s.medium, catalog=None), coating=None))
    return dataclasses.replace(
        p,
        surfaces=tuple(surfaces),
        glass_catalogs=tuple(catalogs),
        source="",
        stated_focal_length_mm=None,
        stated_focal_lengths_mm=(),
        sensor_width_mm=36.0,
        sensor_height_mm=24.0,
        aperture_blades=0,
        aperture_rotation_deg=0.0,
        path="",
    )


def assert_round_trip(p: LensPrescription) -> LensPrescription:
    text = zmx_text(p)
    assert text.isascii()
    back = parse_zmx(text)
    assert_same_prescription(back, zmx_representable(p))
    # and a second trip changes nothing at all
    assert zmx_text(back) == zmx_text(zmx_representable(p))
    return back


def surf(radius, thickness, medium=AIR, semi=10.0, label="", **kwargs) -> SurfaceSpec:
    thicknesses = tuple(thickness) if isinstance(thickness, (tuple, list)) else (float(thickness),)
    return SurfaceSpec(radius_mm=float(radius), thicknesses_mm=thicknesses, medium=medium, semi_aperture_mm=semi, label=label, **kwargs)


# A minimal file in the layout OpticStudio writes; tests add or replace lines in it.
SINGLET = """\
VERS 190513 80 123457 L123457
MODE SEQ
NAME test singlet
UNIT MM X W X CM MR CPMM
FNUM 4 0
WAVM 1 0.5875618 1
PWAV 1
SURF 0
  TYPE STANDARD
  CURV 0.0 0 0 0 0 ""
  DISZ INFINITY
SURF 1
  STOP
  TYPE STANDARD
  CURV 0.02 0 0 0 0 ""
  DISZ 5
  GLAS N-BK7 0 0 1.5168 64.17 0 0 0 0 0 0
  DIAM 10 1 0 0 1 ""
SURF 2
  TYPE STANDARD
  CURV -0.005 0 0 0 0 ""
  DISZ 95
  DIAM 10 1 0 0 1 ""
SURF 3
  TYPE STANDARD
  CURV 0.0 0 0 0 0 ""
  DISZ 0
"""


def edit(text: str, after: str | None = None, insert: tuple[str, ...] = (), replace: dict[str, str] | None = None, append: tuple[str, ...] = ()) -> str:
    """Insert lines after the first line equal to ``after``, replace whole lines, append lines."""
    lines = text.splitlines()
    for old, new in (replace or {}).items():
        index = lines.index(old)
        lines[index : index + 1] = new.splitlines()
    if after is not None:
        index = lines.index(after)
        lines[index + 1 : index + 1] = list(insert)
    lines.extend(append)
    return "\n".join(lines) + "\n"


def line_of(text: str, line: str) -> int:
    return text.splitlines().index(line) + 1


# ----------------------------------------------------------------------------- hand-built lenses


def double_gauss() -> LensPrescription:
    """A 50 mm f/2 double Gauss: named glasses with and without stated n_d/V_d, a catalog on one
    glass, a model glass, a flat stop in air, coatings (which .zmx cannot hold)."""
    sk16 = MediumSpec(glass="N-SK16", n_d=1.62041, v_d=60.32)
    return LensPrescription(
        name="Double Gauss 50/2",
        surfaces=(
            surf(33.5, 4.6, sk16, 15.0, "L1 front", coating=CoatingSpec.quarter_wave(1.38, 550.0, "MgF2")),
            surf(128.0, 0.3, AIR, 14.5, "L1 back"),
            surf(19.8, 6.2, MediumSpec(glass="S-BSM81", catalog="OHARA", n_d=1.64, v_d=60.08), 13.0, "L2"),
            surf(52.0, 1.6, MediumSpec(glass="F5"), 11.5, "L3"),
            surf(13.4, 5.8, AIR, 9.6, "L3 back"),
            surf(math.inf, 5.4, AIR, 8.9, "iris", is_stop=True),
            surf(-15.6, 1.6, MediumSpec(glass="F5", catalog="SCHOTT"), 8.8, "L4"),
            surf(48.0, 6.0, MediumSpec(n_d=1.6935, v_d=53.2), 10.6, "L5 (model glass)"),
            surf(-21.2, 0.3, AIR, 11.0, "L5 back"),
            surf(95.0, 4.4, sk16, 12.4, "L6"),
            surf(-55.0, 37.6, AIR, 12.6, "L6 back"),
        ),
        source="hand-built for the tests",
        stated_focal_length_mm=50.0,
        stated_f_number=2.0,
        sensor_width_mm=24.0,
        sensor_height_mm=16.0,
        aperture_blades=6,
        notes="first line\nsecond line",
        glass_catalogs=("SCHOTT",),
    )


def stop_on_glass() -> LensPrescription:
    """A cemented doublet whose stop is its front (glass) surface, one glass without stated values."""
    return LensPrescription(
        name="doublet, stop on the first glass surface",
        surfaces=(
            surf(61.47, 6.0, MediumSpec(glass="N-BAK4", n_d=1.56883, v_d=55.98), 12.7, "front", is_stop=True),
            surf(-44.64, 2.5, MediumSpec(glass="SF5"), 12.7, "cement"),
            surf(-129.94, 93.9, AIR, 12.7, "back"),
        ),
        stated_f_number=4.0,
        design_wavelength_nm=546.07,
    )


def even_asphere() -> LensPrescription:
    """Even aspheres: a conic, interior zero coefficients, the full A4..A16 range, radii that are not
    short decimals (their curvatures do not give them back without help)."""
    awkward = 1.0 / 0.0123  # 81.30081300813008
    return LensPrescription(
        name="asphere test",
        surfaces=(
            surf(awkward, 3.2, MediumSpec(n_d=1.5311, v_d=55.8), 6.5, "molded asphere front", conic=-0.87, aspheric_coefficients=(1.25e-05, 0.0, -3.4e-09)),
            surf(-0.1 - 0.2, 1.1, AIR, 0.25, "tiny awkward radius", is_stop=True),
            surf(-17.345, 22.0, MediumSpec(glass="L-BAL42", n_d=1.58313, v_d=59.38), 6.0, "aspheric both", conic=0.5,
                 aspheric_coefficients=(-2.1e-05, 1.7e-07, -4.4e-10, 2.0e-12, -3.3e-15, 1.1e-17, -9.9e-21)),
            surf(-26.0000000001, 18.5, AIR, 6.2, "back"),
        ),
    )


def dummy_surfaces() -> LensPrescription:
    """Air-to-air dummy surfaces (they clip), missing semi-apertures, empty labels."""
    return LensPrescription(
        name="",
        surfaces=(
            surf(math.inf, 2.0, AIR, 20.0, "entrance baffle"),
            surf(40.0, 5.0, MediumSpec(glass="N-BK7"), math.nan, "no semi-aperture given"),
            surf(math.inf, 0.0, MediumSpec(glass="N-BK7"), 12.0, "dummy inside the glass"),  # (without an aperture it is dropped)
            surf(-40.0, 3.0, AIR, 14.0, "back"),
            surf(math.inf, 10.0, AIR, 7.0, "stop", is_stop=True),
            surf(math.inf, 25.0, AIR, 30.0, "flare cutter"),
        ),
    )


def zoom_3_positions() -> LensPrescription:
    def fixed(t):
        return (t, t, t)

    return LensPrescription(
        name="three-position zoom",
        surfaces=(
            surf(80.0, fixed(3.0), MediumSpec(glass="N-SF6"), 18.0, "G1"),
            surf(45.0, fixed(7.0), MediumSpec(glass="N-LAK9"), 18.0, "G1 cement"),
            surf(-300.0, (1.0, 14.5, 26.25), AIR, 18.0, "G1 back / zoom gap 1"),
            surf(-60.0, fixed(1.2), MediumSpec(glass="N-LAK9"), 9.0, "G2"),
            surf(22.0, (28.0, 15.0, 2.5), AIR, 9.0, "G2 back / zoom gap 2"),
            surf(math.inf, fixed(2.0), AIR, 7.5, "stop", is_stop=True),
            surf(30.0, fixed(4.0), MediumSpec(n_d=1.62, v_d=60.3), 8.0, "G3"),
            surf(-90.0, (40.0, 41.0, 42.125), AIR, 8.0, "G3 back / back focus"),
        ),
        stated_focal_lengths_mm=(35.0, 60.0, 105.0),
        stated_focal_length_mm=35.0,
        stated_f_number=3.5,
    )


def cylinders() -> LensPrescription:
    """An anamorphic attachment: cylinders with power in x and in y, one with a conic and aspherics."""
    return LensPrescription(
        name="anamorphic cylinders",
        surfaces=(
            surf(120.0, 4.0, MediumSpec(glass="N-BK7"), 20.0, "cyl x front", kind="cylindrical_x"),
            surf(math.inf, 10.0, AIR, 20.0, "plano"),
            surf(-85.5, 3.0, MediumSpec(glass="N-SF11"), 18.0, "cyl y", kind="cylindrical_y", conic=-0.3, aspheric_coefficients=(2e-06, 0.0, 5e-12)),
            surf(math.inf, 5.0, AIR, 18.0, "stop", is_stop=True),
            surf(-240.0, 60.0, AIR, 16.0, "cyl x back", kind="cylindrical_x"),
        ),
    )


# ----------------------------------------------------------------------------- the fixture


def test_fixture_double_gauss_reads_as_expected():
    p = read_zmx(FIXTURE)
    assert p.name == "Double Gauss 50 mm f/2 (jaxflare test fixture)"
    assert p.path == str(FIXTURE)
    assert p.glass_catalogs == ("SCHOTT", "OHARA")
    assert p.stated_f_number == 2.0
    assert p.design_wavelength_nm == 587.5618  # PWAV 2 -> WAVM 2
    assert p.notes.startswith("Hand-made fixture")
    assert p.num_zoom_positions == 1
    assert len(p.surfaces) == 11  # SURF 0 (object) and SURF 12 (image) dropped
    assert p.stop_surface_index == 5
    assert [s.radius_mm for s in p.surfaces] == [33.5, 128.0, 19.8, 52.0, 13.4, math.inf, -15.6, 48.0, -21.2, 95.0, -55.0]
    assert [s.thicknesses_mm[0] for s in p.surfaces] == [4.6, 0.3, 6.2, 1.6, 5.8, 5.4, 1.6, 6.0, 0.3, 4.4, 37.6]
    assert p.surfaces[-1].thicknesses_mm == (37.6,)  # the sensor distance
    # DIAM is a semi-diameter, MEMA the element's mechanical edge: a refracting surface clips at the
    # larger; the stop at its DIAM (8.9)
    assert [s.semi_aperture_mm for s in p.surfaces] == [15.0, 15.0, 13.0, 13.0, 13.0, 8.9, 11.0, 11.0, 11.0, 12.6, 12.6]
    # the model-glass columns beside a catalog glass are leftovers, not stated values
    assert p.surfaces[0].medium == MediumSpec(glass="N-SK16")
    assert p.surfaces[3].medium == MediumSpec(glass="F5")
    assert p.surfaces[7].medium == MediumSpec(n_d=1.6935, v_d=53.2)  # GLAS ___BLANK
    assert p.surfaces[1].medium.is_air
    assert p.surfaces[0].label == "L1 front [Zemax coating I.25]"
    assert p.surfaces[0].coating is None
    assert p.surfaces[1].label == "double_gauss_50mm.zmx:68: SURF 2 (surface 1)"
    assert all(s.kind == "spherical" and s.conic == 0.0 and s.aspheric_coefficients == () for s in p.surfaces)


def test_utf16_and_ascii_versions_give_the_same_prescription(tmp_path):
    ascii_bytes = FIXTURE.read_bytes()
    utf16_bytes = FIXTURE_UTF16.read_bytes()
    assert utf16_bytes.startswith(codecs.BOM_UTF16_LE) and ascii_bytes.isascii()
    assert decode_zmx_bytes(utf16_bytes).replace("\r\n", "\n") == decode_zmx_bytes(ascii_bytes)
    # same file name, so labels and source agree too
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    (tmp_path / "a" / "lens.zmx").write_bytes(ascii_bytes)
    (tmp_path / "b" / "lens.zmx").write_bytes(utf16_bytes)
    from_ascii = read_zmx(tmp_path / "a" / "lens.zmx")
    from_utf16 = read_zmx(tmp_path / "b" / "lens.zmx")
    assert_same_prescription(dataclasses.replace(from_utf16, path=""), dataclasses.replace(from_ascii, path=""))


@pytest.mark.parametrize(
    "encode",
    [
        lambda t: codecs.BOM_UTF16_BE + t.encode("utf-16-be"),
        lambda t: t.encode("utf-16-le"),  # no BOM: found by its NUL bytes
        lambda t: t.encode("utf-16-be"),
        lambda t: codecs.BOM_UTF8 + t.encode("utf-8"),
        lambda t: t.replace("\n", "\r\n").encode("cp1252"),
    ],
    ids=["utf16-be-bom", "utf16-le-nobom", "utf16-be-nobom", "utf8-bom", "cp1252-crlf"],
)
def test_other_encodings(encode):
    text = FIXTURE.read_text(encoding="ascii")
    expected = parse_zmx(text, "lens.zmx")
    assert_same_prescription(parse_zmx(decode_zmx_bytes(encode(text)), "lens.zmx"), expected)


def test_fixture_round_trips_through_zmx_text():
    p = dataclasses.replace(read_zmx(FIXTURE), path="", source="")
    back = parse_zmx(zmx_text(p))
    assert_same_prescription(back, p)


# ----------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("build", [double_gauss, stop_on_glass, even_asphere, dummy_surfaces, zoom_3_positions, cylinders])
def test_round_trip(build):
    assert_round_trip(build())


def test_round_trip_through_a_file(tmp_path):
    p = zoom_3_positions()
    path = tmp_path / "zoom.zmx"
    write_zmx(p, path)
    data = path.read_bytes()
    assert data.isascii() and b"\r\n" in data
    back = read_zmx(path)
    assert back.path == str(path)
    assert_same_prescription(dataclasses.replace(back, path="", source=""), zmx_representable(p))


def test_round_trip_keeps_arbitrary_radii_exactly():
    rng = random.Random(7)
    radii = [rng.uniform(3.0, 900.0) * rng.choice((-1, 1)) for _ in range(300)]
    surfaces = [surf(r, 1.0, AIR, 1.0, f"r{k}") for k, r in enumerate(radii)]
    surfaces[0] = dataclasses.replace(surfaces[0], is_stop=True)
    p = LensPrescription(name="radii", surfaces=tuple(surfaces))
    text = zmx_text(p)
    assert "NOTE jaxflare: radius SURF" in text  # some of these need the exact value recorded
    back = assert_round_trip(p)
    assert back.notes == ""


def test_zoom_is_written_as_mnum_and_thic_rows():
    text = zmx_text(zoom_3_positions())
    lines = text.splitlines()
    assert "MNUM 3 1" in lines
    thic = [line.split()[:4] for line in lines if line.startswith("THIC ")]
    assert thic == [
        ["THIC", "3", "1", "1.0"], ["THIC", "3", "2", "14.5"], ["THIC", "3", "3", "26.25"],
        ["THIC", "5", "1", "28.0"], ["THIC", "5", "2", "15.0"], ["THIC", "5", "3", "2.5"],
        ["THIC", "8", "1", "40.0"], ["THIC", "8", "2", "41.0"], ["THIC", "8", "3", "42.125"],
    ]


def test_export_layout():
    text = zmx_text(double_gauss())
    lines = text.splitlines()
    assert lines[:2] == ["VERS 221221 730 20120530 20120530", "MODE SEQ"]
    for expected in ("UNIT MM X W X CM MR CPMM", "FNUM 2.0 0", "GCAT SCHOTT OHARA", "WAVM 2 0.58756 1", "PWAV 2", "SURF 0", "  DISZ INFINITY", "SURF 12", "  GLAS F5 0 0 0 0 0 0 0 0 0 0", "  GLAS ___BLANK 1 0 1.6935 53.2 0 0 0 0 0 0", "  GLAS N-SK16 0 0 1.62041 60.32 0 0 0 0 0 0"):
        assert expected in lines, expected
    # the coating on surface 0 cannot be written; the file says so
    assert any(line.startswith("NOTE jaxflare: thin-film coatings") and "surface 0 (MgF2)" in line for line in lines)
    assert parse_zmx(text).notes == "first line\nsecond line"
    # the stop is a plain STANDARD surface with STOP
    stop = lines.index("SURF 6")
    assert lines[stop + 1] == "  STOP"
    assert zmx_text(dataclasses.replace(double_gauss(), stated_f_number=None)).count("\nFLOA\n") == 1


def test_export_of_aspheres_and_cylinders():
    text = zmx_text(cylinders())
    blocks = text.split("SURF ")
    assert "TYPE TOROIDAL" in blocks[2] and "PARM 1 120.0" in blocks[2] and "CURV 0.0" in blocks[2]
    assert "TYPE TOROIDAL" in blocks[4] and "PARM 1 0.0" in blocks[4] and "CONI -0.3" in blocks[4] and "PARM 3 2e-06" in blocks[4]
    text = zmx_text(even_asphere())
    assert "TYPE EVENASPH" in text and "  PARM 1 0.0\n  PARM 2 1.25e-05\n  PARM 3 0.0\n  PARM 4 -3.4e-09" in text


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda p: dataclasses.replace(p, surfaces=tuple(dataclasses.replace(s, is_stop=False) for s in p.surfaces)), "stop"),
        (lambda p: dataclasses.replace(p, surfaces=(dataclasses.replace(p.surfaces[0], kind="cylindrical_x", conic=-1.0),) + p.surfaces[1:]), "cylindrical_x"),
        (lambda p: dataclasses.replace(p, surfaces=(dataclasses.replace(p.surfaces[0], aspheric_coefficients=(1e-5,) * 8),) + p.surfaces[1:]), "EVENASPH"),
        (lambda p: dataclasses.replace(p, surfaces=(dataclasses.replace(p.surfaces[0], thicknesses_mm=(math.inf,)),) + p.surfaces[1:]), "thickness"),
        (lambda p: dataclasses.replace(p, surfaces=(dataclasses.replace(p.surfaces[0], medium=MediumSpec(glass="two words")),) + p.surfaces[1:]), "glass name"),
    ],
    ids=["no-stop", "aspheric-cylinder-x", "too-many-terms", "infinite-thickness", "glass-name-with-space"],
)
def test_export_refuses_what_zmx_cannot_hold(change, message):
    with pytest.raises(LensFormatError, match=message):
        zmx_text(change(stop_on_glass()))


# ----------------------------------------------------------------------------- import details


def test_singlet_basics():
    p = parse_zmx(SINGLET)
    assert p.name == "test singlet"
    assert p.stated_f_number == 4.0
    assert p.design_wavelength_nm == 587.5618
    assert [s.radius_mm for s in p.surfaces] == [50.0, -200.0]
    assert p.surfaces[0].medium == MediumSpec(glass="N-BK7")  # the model columns of a catalog glass are not read
    assert p.surfaces[0].is_stop and p.surfaces[1].thicknesses_mm == (95.0,)
    assert p.glass_catalogs == () and p.path == "" and p.source == ""
    assert p.surfaces[1].label == "<string>:19: SURF 2 (surface 1)"


def test_missing_or_zero_diam_gives_nan_and_clap_sets_the_aperture():
    text = SINGLET.replace('  DIAM 10 1 0 0 1 ""\n', "").replace("  DISZ 95\n", '  DISZ 95\n  DIAM 0 0 0 0 1 ""\n')
    p = parse_zmx(text)
    assert math.isnan(p.surfaces[0].semi_aperture_mm) and math.isnan(p.surfaces[1].semi_aperture_mm)
    text = edit(SINGLET, after="  DISZ 95", insert=("  CLAP 0 8.5 0", "  FLAP 0 10 0", "  OBSC 0 0 0"))
    assert parse_zmx(text).surfaces[1].semi_aperture_mm == 8.5


@pytest.mark.parametrize(
    "glas, medium",
    [
        ("GLAS ___BLANK 1 0 1.6425 48.0 0 0 0 0 0 0", MediumSpec(n_d=1.6425, v_d=48.0)),
        ("GLAS ___BLANK 1 0 1.9 0 0 0 0 0 0 0", MediumSpec(n_d=1.9, v_d=None)),  # V_d 0: no dispersion given
        ("GLAS ___BLANK 2 1 1.4890000000000001 57.399999999999999 0 0 0 0 0 0", MediumSpec(n_d=1.489, v_d=57.4)),  # picked up
        ("GLAS 1.5,60 1 0 1.5 60 0 0 0", MediumSpec(n_d=1.5, v_d=60.0)),  # solve type 1 = model, whatever the label
        ("GLAS N-SF6 0 0 1.5 40 0 0 0 0 0 0", MediumSpec(glass="N-SF6")),  # never-set defaults
        ("GLAS N-SF6 0 0 0 0 0 0 0 0 0 0", MediumSpec(glass="N-SF6")),
        ("GLAS N-SF6", MediumSpec(glass="N-SF6")),
        ("GLAS N-SF6 3 0 1.80518 25.36 0 0 0 0 0 0", MediumSpec(glass="N-SF6")),  # substitute: leftover model columns
        ("GLAS S-TIH11 4 0 1.78472 25.68 0 0 0 0 0 0", MediumSpec(glass="S-TIH11")),  # zero offset
        ("GLAS N-LASF55 0 0 1.5168 64.17 0 0 0 0 0 0", MediumSpec(glass="N-LASF55")),  # stale columns are no stated values
    ],
)
def test_glass_records(glas, medium):
    text = SINGLET.replace("GLAS N-BK7 0 0 1.5168 64.17 0 0 0 0 0 0", glas)
    assert parse_zmx(text).surfaces[0].medium == medium


def test_gcat_is_captured_upper_case():
    text = edit(SINGLET, after="UNIT MM X W X CM MR CPMM", insert=("GCAT schott Ohara HOYA ",))
    assert parse_zmx(text).glass_catalogs == ("SCHOTT", "OHARA", "HOYA")


def test_inch_units_are_converted_to_mm():
    text = """\
MODE SEQ
UNIT IN X W X IN MR CPMM
ENPD 1
SURF 0
  DISZ INFINITY
SURF 1
  STOP
  TYPE EVENASPH
  CURV 0.5 0 0 0 0 ""
  PARM 1 0
  PARM 2 0.001
  PARM 3 -2e-5
  DISZ 0.25
  GLAS ___BLANK 1 0 1.5 60 0 0 0 0 0 0
  DIAM 0.5 1 0 0 1 ""
  CONI -1
SURF 2
  TYPE STANDARD
  CURV -0.125
  DISZ 3.5
  CLAP 0 0.45 0
SURF 3
  DISZ 0
"""
    p = parse_zmx(text)
    s0, s1 = p.surfaces
    assert s0.radius_mm == 50.8 and s1.radius_mm == -203.2
    assert s0.thicknesses_mm == (6.35,) and s1.thicknesses_mm == (88.9,)
    assert s0.semi_aperture_mm == 12.7 and s1.semi_aperture_mm == pytest.approx(11.43, rel=1e-15)
    assert s0.conic == -1.0
    # A4 r^4 in inch: 0.001 in^-3 = 0.001 / 25.4^3 mm^-3; A6: in^-5
    assert s0.aspheric_coefficients == pytest.approx((0.001 / 25.4**3, -2e-5 / 25.4**5), rel=1e-15)
    assert p.stated_f_number is None  # ENPD is not an f-number


@pytest.mark.parametrize("unit, factor", [("MM", 1.0), ("CM", 10.0), ("METER", 1000.0)])
def test_other_units(unit, factor):
    text = SINGLET.replace("UNIT MM X W X CM MR CPMM", f"UNIT {unit} X W X CM MR CPMM")
    p = parse_zmx(text)
    assert p.surfaces[0].radius_mm == pytest.approx(50.0 * factor, rel=1e-15)
    assert p.surfaces[1].thicknesses_mm[0] == pytest.approx(95.0 * factor, rel=1e-15)


def test_even_asphere_coefficients_and_trailing_zeros():
    text = SINGLET.replace("  TYPE STANDARD\n  CURV 0.02", "  TYPE EVENASPH\n  CURV 0.02")
    text = edit(text, after="  CURV 0.02 0 0 0 0 \"\"", insert=("  PARM 1 0", "  PARM 2 1e-05", "  PARM 3 0", "  PARM 4 -2e-11", "  PARM 5 0", "  PARM 6 0", "  PARM 7 0", "  PARM 8 0"))
    assert parse_zmx(text).surfaces[0].aspheric_coefficients == (1e-05, 0.0, -2e-11)


def test_toroidal_cylinders():
    base = SINGLET.replace("  TYPE STANDARD\n  CURV 0.02", "  TYPE TOROIDAL\n  CURV 0.02")
    p = parse_zmx(edit(base, after='  CURV 0.02 0 0 0 0 ""', insert=("  PARM 1 0", "  PARM 2 0", "  PARM 3 1e-06", "  XDAT 1 0 0 0 1 0 0 \"\"", "  XDAT 2 100 0 0 1 0 0 \"\"")))
    assert (p.surfaces[0].kind, p.surfaces[0].radius_mm, p.surfaces[0].aspheric_coefficients) == ("cylindrical_y", 50.0, (1e-06,))
    flat_y = base.replace('  CURV 0.02 0 0 0 0 ""', '  CURV 0 0 0 0 0 ""\n  PARM 1 -75')
    p = parse_zmx(flat_y)
    assert (p.surfaces[0].kind, p.surfaces[0].radius_mm) == ("cylindrical_x", -75.0)


def test_fnum_enpd_floa():
    assert parse_zmx(SINGLET.replace("FNUM 4 0", "FNUM 2.8 1")).stated_f_number == 2.8  # paraxial working F/#
    assert parse_zmx(SINGLET.replace("FNUM 4 0", "ENPD 20")).stated_f_number is None
    assert parse_zmx(SINGLET.replace("FNUM 4 0", "FLOA")).stated_f_number is None
    assert parse_zmx(SINGLET.replace("FNUM 4 0", "OBNA 0.1 0")).stated_f_number is None


def test_harmless_records_are_accepted():
    text = edit(
        SINGLET,
        after='  DIAM 10 1 0 0 1 ""',
        insert=("  MIRR 2 0", "  HIDE 0 0 0 0 0 0 0 0 0 0", "  SLAB 3", "  MEMA 10 0 0 0 1 \"\"", "  POPS 0 0 0 0 0 0 0 0 1 1 1 1 0 0 0 0",
                "  FIMP ", "  COAT AR", "  PARM 1 0", "  SCBD 0 0 0 0 0 0 0", "  OBDC 0 0", "  VDSZ 0 0", "  MAZH 0 0.7"),
        append=("BLNK Sequential merit function", "DMFS 0 0 0 0 0 0 0 0 0 0", "EFFL 0 2 0 0 0 0 0 0 0 0", "REAY 3 1 0 1 0 0 0 0 0 0",
                "TOL TOFF   0   0              0              0   0 0 0 0", "MNUM 1 1", 'MOFF   0   1 "" 0 0 0 1 1 0 0.0 "" 0'),
    )
    p = parse_zmx(text)
    assert p.surfaces[0].label.endswith("[Zemax coating AR]")
    assert len(p.surfaces) == 2


def test_finite_object_distance_is_noted():
    p = parse_zmx(SINGLET.replace("  DISZ INFINITY", "  DISZ 1000"))
    assert "finite distance (1000 mm)" in p.notes


def test_notes_and_name_fall_back_to_the_file_name(tmp_path):
    path = tmp_path / "Planar 50.zmx"
    path.write_text(SINGLET.replace("NAME test singlet", "NAME ").replace("MODE SEQ", "MODE SEQ\nNOTE a note"), encoding="utf-16")
    p = read_zmx(path)
    assert p.name == "Planar 50" and p.notes == "a note" and p.source == "Zemax OpticStudio file Planar 50.zmx"


# ----------------------------------------------------------------------------- zoom files


ZOOM = """\
VERS 221221 730 20120530 20120530
MODE SEQ
NAME zoom
UNIT MM X W X CM MR CPMM
FNUM 4 1
SURF 0
  DISZ INFINITY
SURF 1
  TYPE STANDARD
  CURV 0.01
  DISZ 4
  GLAS N-BK7 0 0 1.5168 64.17 0 0 0 0 0 0
SURF 2
  TYPE STANDARD
  CURV -0.01
  DISZ 10
SURF 3
  STOP
  TYPE STANDARD
  CURV 0
  DISZ 3
SURF 4
  TYPE STANDARD
  CURV 0.02
  DISZ 2
  GLAS N-SF5 0 0 1.67271 32.25 0 0 0 0 0 0
SURF 5
  TYPE STANDARD
  CURV 0
  DISZ 50
  TCOM 2 60
SURF 6
  TYPE STANDARD
  CURV 0
  DISZ 0
MNUM 3 1
THIC 0 1 1.0000000000E+10 0 0 0 1 1 1 0 0 "" 0
THIC 0 2 1.0000000000E+10 0 0 0 1 1 1 0 0 "" 0
THIC 0 3 1.0000000000E+10 0 0 0 1 1 1 0 0 "" 0
THIC 2 1 10 0 0 0 1 1 1 0 0 "" 0
THIC 2 2 20 0 0 0 1 1 1 0 0 "" 0
THIC 2 3 35.5 0 0 0 1 1 1 0 0 "" 0
APER 0 1 4 0 0 0 1 1 1 0 0 "" 0
APER 0 2 4.5 0 0 0 1 1 1 0 0 "" 0
APER 0 3 5.6 0 0 0 1 1 1 0 0 "" 0
FVCY 1 1 0 0 0 0 1 1 1 0 0 "" 0
FVDY 1 1 0 0 0 0 1 1 1 0 0 "" 0
"""


def test_opticstudio_style_zoom_with_a_compensator():
    p = parse_zmx(ZOOM)
    assert p.num_zoom_positions == 3
    assert [s.thicknesses_mm for s in p.surfaces] == [(4.0,) * 3, (10.0, 20.0, 35.5), (3.0,) * 3, (2.0,) * 3, (50.0, 40.0, 24.5)]
    assert p.stated_f_number == 4.0


@pytest.mark.parametrize(
    "line, keyword",
    [
        ('CRVT 1 2 0.011 0 0 0 1 1 1 0 0 "" 0', "CRVT"),
        ('GLSS 4 2 "N-SF6" 0 0 0 1 1 1 0 0 "" 0', "GLSS"),
        ('PRAM 1 2 0.1 1 0 0 1 1 1 0 0 "" 0', "PRAM"),
        ('ZZZZ 1 2 3 0 0 0 1 1 1 0 0 "" 0', "ZZZZ"),
        ('THIC 2 1 12 0 0 0 1 1 1 0 0 "" 0', "THIC"),  # given twice
        ('THIC 7 1 12 0 0 0 1 1 1 0 0 "" 0', "THIC"),  # no such surface
        ('THIC 3 4 12 0 0 0 1 1 1 0 0 "" 0', "THIC"),  # no such configuration
        ('MOFF 0 1 "THIC" 3 0 0 0', "MOFF"),
    ],
)
def test_zoom_errors_name_the_line(line, keyword):
    text = ZOOM + line + "\n"
    with pytest.raises(LensFormatError) as info:
        parse_zmx(text, "zoom.zmx")
    assert f"zoom.zmx:{line_of(text, line)}:" in str(info.value) and keyword in str(info.value)


def test_zoom_thic_row_missing_a_configuration():
    text = ZOOM.replace('THIC 2 3 35.5 0 0 0 1 1 1 0 0 "" 0\n', "")
    with pytest.raises(LensFormatError, match=r"zoom.zmx:\d+: THIC: SURF 2 has no value for configuration\(s\) \[3\]"):
        parse_zmx(text, "zoom.zmx")


def test_ray_based_thickness_solve_in_a_zoom_is_refused():
    text = ZOOM.replace("  TCOM 2 60", "  MAZH 0 0")
    with pytest.raises(LensFormatError) as info:
        parse_zmx(text, "zoom.zmx")
    assert f"zoom.zmx:{line_of(text, '  MAZH 0 0')}: MAZH" in str(info.value)
    # in a one-configuration file the stored DISZ is the solved value
    one = text.split("MNUM")[0]
    assert parse_zmx(one).surfaces[-1].thicknesses_mm == (50.0,)


# ----------------------------------------------------------------------------- errors


SURFACE_ERRORS = [
    ("  TYPE COORDBRK", "COORDBRK", {"  TYPE STANDARD\n  CURV 0.02 0 0 0 0 \"\"": None}),
    ("  TYPE GRINSUR1", "GRINSUR1", None),
    ("  TYPE BICONICX", "BICONICX", None),
    ("  TYPE NONSEQCO", "NONSEQCO", None),
    ("  SCBD 0 0.5 0 0 0 0 0", "SCBD", None),
    ("  PARM 1 0.25", "PARM 1", None),
    ("  OBSC 0 5 0", "OBSC", None),
    ("  SQAP 10 10 0", "SQAP", None),
    ("  ELAP 10 8 0", "ELAP", None),
    ("  OBDC 0.5 0", "OBDC", None),
    ("  CLAP 2 10 0", "CLAP", None),
    ('  XDAT 1 5 0 0 1 0 0 ""', "XDAT", None),
]


@pytest.mark.parametrize("line, keyword, _", SURFACE_ERRORS, ids=[e[1] for e in SURFACE_ERRORS])
def test_unsupported_surface_constructs_name_line_and_keyword(line, keyword, _):
    text = edit(SINGLET, after="  DISZ 95", insert=(line,))
    with pytest.raises(LensFormatError) as info:
        parse_zmx(text, "bad.zmx")
    message = str(info.value)
    assert message.startswith(f"bad.zmx:{line_of(text, line)}:"), message
    assert keyword in message


@pytest.mark.parametrize(
    "old, new, keyword",
    [
        ("  GLAS N-BK7 0 0 1.5168 64.17 0 0 0 0 0 0", "  GLAS MIRROR 0 0 1.5 40 0 0 0 0 0 0", "MIRROR"),
        ("  GLAS N-BK7 0 0 1.5168 64.17 0 0 0 0 0 0", "  GLAS N-BK7 4 0 1.5168 64.17 0 0 0 0 0.001 0", "offset"),
        ("  GLAS N-BK7 0 0 1.5168 64.17 0 0 0 0 0 0", "  GLAS N-BK7 7 0 1.5168 64.17 0 0 0 0 0 0", "solve type"),
        ("  DISZ 5", "  DISZ infinity", "DISZ INFINITY"),
        ("  DISZ 95", "  DISZ Infinity", "DISZ INFINITY"),  # the sensor distance too
        ("  TYPE STANDARD\n  CURV 0.02 0 0 0 0 \"\"", "  TYPE EVENASPH\n  CURV 0.02 0 0 0 0 \"\"\n  PARM 1 0.001", "PARM 1"),
        ("  TYPE STANDARD\n  CURV 0.02 0 0 0 0 \"\"", "  TYPE TOROIDAL\n  CURV 0.02 0 0 0 0 \"\"\n  PARM 1 40", "PARM 1"),
        ("  TYPE STANDARD\n  CURV 0.02 0 0 0 0 \"\"", "  TYPE TOROIDAL\n  CURV 0.02 0 0 0 0 \"\"\n  PARM 2 0.001", "PARM 2"),
        ("MODE SEQ", "MODE NSC", "MODE"),
        ("UNIT MM X W X CM MR CPMM", "UNIT FT X W X CM MR CPMM", "UNIT"),
        ("FNUM 4 0", "  DISZ 4", "DISZ"),  # a surface record before any SURF
        ("  DISZ 0", "  DISZ 0\nNSOH STANDARD 0 0", "NSOH"),
    ],
    ids=["mirror", "glass-offset", "glass-solve", "infinite-middle", "infinite-sensor", "evenasph-r2", "toroid", "toroidal-y2",
         "mode-nsc", "unit", "stray-surface-record", "non-sequential"],
)
def test_unsupported_constructs_name_line_and_keyword(old, new, keyword):
    text = SINGLET.replace(old, new, 1)
    assert text != SINGLET
    bad_line = [line for line in new.splitlines() if line not in old.splitlines()][-1]
    with pytest.raises(LensFormatError) as info:
        parse_zmx(text, "bad.zmx")
    message = str(info.value)
    assert message.startswith(f"bad.zmx:{line_of(text, bad_line)}:"), message
    assert keyword in message


def test_unknown_keyword_after_the_surfaces_that_is_a_surface_keyword():
    text = SINGLET + "DIAM 5\n"
    with pytest.raises(LensFormatError, match=rf"bad.zmx:{line_of(text, 'DIAM 5')}: DIAM: surface keyword outside a SURF block"):
        parse_zmx(text, "bad.zmx")


def test_merit_operands_and_unknown_records_are_skipped_and_listed():
    p = parse_zmx(SINGLET + "QSUM 1 2 3\n")
    assert len(p.surfaces) == 2 and "QSUM" not in p.notes  # a merit-function row after the surfaces
    # an unknown keyword elsewhere is skipped, and the notes name it with its line
    text = SINGLET.replace("PWAV 1", "PWAV 1\nQSUM 1 2 3\nFROB 4 0").replace("  DISZ 95", "  DISZ 95\n  FOOB 1 2")
    p = parse_zmx(text, "bad.zmx")
    assert [s.radius_mm for s in p.surfaces] == [50.0, -200.0]
    assert f"QSUM (line {line_of(text, 'QSUM 1 2 3')})" in p.notes and f"FROB (line {line_of(text, 'FROB 4 0')})" in p.notes
    assert f"FOOB (line {line_of(text, '  FOOB 1 2')})" in p.notes
    # after MNUM every row is a configuration operand: an unknown one may change the optics
    with pytest.raises(LensFormatError, match=r"bad.zmx:\d+: ZZZZ"):
        parse_zmx(SINGLET + "MNUM 1 1\nZZZZ 1 1\n", "bad.zmx")
    # a line that is no record at all
    with pytest.raises(LensFormatError, match=r"bad.zmx:8: '\?\?': not a .zmx record"):
        parse_zmx(SINGLET.replace("PWAV 1", "PWAV 1\n?? what"), "bad.zmx")


def test_stop_errors():
    no_stop = SINGLET.replace("  STOP\n", "")
    with pytest.raises(LensFormatError, match="no surface is marked STOP"):
        parse_zmx(no_stop)
    two = edit(SINGLET, after="SURF 2", insert=("  STOP",))
    with pytest.raises(LensFormatError, match=rf"<string>:{line_of(two, 'SURF 2') + 1}: STOP: more than one"):
        parse_zmx(two)
    on_object = edit(no_stop, after="SURF 0", insert=("  STOP",))
    with pytest.raises(LensFormatError, match=r"<string>:9: STOP: .*object"):
        parse_zmx(on_object)


def test_image_and_object_errors():
    curved_image = SINGLET.replace('SURF 3\n  TYPE STANDARD\n  CURV 0.0 0 0 0 0 ""', 'SURF 3\n  TYPE STANDARD\n  CURV -0.01 0 0 0 0 ""')
    curv_line = line_of(curved_image, '  CURV -0.01 0 0 0 0 ""')
    with pytest.raises(LensFormatError, match=rf"<string>:{curv_line}: CURV: a curved image"):
        parse_zmx(curved_image)
    object_in_glass = edit(SINGLET, after="  DISZ INFINITY", insert=("  GLAS WATER 0 0 1.333 55 0 0 0 0 0 0",))
    with pytest.raises(LensFormatError, match=r"<string>:12: GLAS: the object space must be air"):
        parse_zmx(object_in_glass)
    with pytest.raises(LensFormatError, match="at least one lens surface"):
        parse_zmx("MODE SEQ\nSURF 0\n  DISZ INFINITY\nSURF 1\n  DISZ 0\n")
    with pytest.raises(LensFormatError, match=r"<string>:\d+: SURF: expected surface 2, got 3"):
        parse_zmx(SINGLET.replace("SURF 2", "SURF 3", 1))


def test_unreadable_utf16():
    with pytest.raises(LensFormatError, match="bad.zmx"):
        decode_zmx_bytes(codecs.BOM_UTF16_LE + b"\x00\xd8A", "bad.zmx")


# ----------------------------------------------------------------------------- writing files


def test_write_zmx_is_atomic_and_overwrites(tmp_path):
    path = tmp_path / "lens.zmx"
    path.write_text("old contents\n")
    write_zmx(stop_on_glass(), path)
    assert read_zmx(path).name == "doublet, stop on the first glass surface"
    assert sorted(os.listdir(tmp_path)) == ["lens.zmx"]
    # a prescription that cannot be written leaves the old file and no temporary file behind
    before = path.read_bytes()
    broken = dataclasses.replace(stop_on_glass(), surfaces=tuple(dataclasses.replace(s, is_stop=False) for s in stop_on_glass().surfaces))
    with pytest.raises(LensFormatError):
        write_zmx(broken, path)
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["lens.zmx"]


def test_write_zmx_non_ascii_text_is_replaced(tmp_path):
    p = dataclasses.replace(stop_on_glass(), name="Objektiv f\u00fcr Tests \u2013 50 mm")
    path = tmp_path / "x.zmx"
    write_zmx(p, path)
    assert read_zmx(path).name == "Objektiv f?r Tests ? 50 mm"


def test_unknown_catalog_glass_is_an_error_naming_the_line_not_a_substitution(tmp_path):
    """Issue 17: an unknown N-LASF55 with leftover model columns became n_d 1.5168 with only a
    warning. The columns are no stated values: the load fails naming the file, line and glass,
    with near matches and the way to map it (glass_aliases); the alias then loads it."""
    path = tmp_path / "singlet.zmx"
    path.write_text(SINGLET.replace("GLAS N-BK7 0 0 1.5168 64.17 0 0 0 0 0 0", "GLAS N-LASF55 0 0 1.5168 64.17 0 0 0 0 0 0"))
    with pytest.raises(LensFormatError, match=r"^singlet\.zmx:\d+: SURF 1 \(surface 0\): unknown glass 'N-LASF55'.*glass_aliases") as info:
        jaxflare.load_lens(path)
    assert str(path) not in str(info.value)  # named once, not twice
    lens = jaxflare.load_lens(path, glass_aliases={"N-LASF55": "SCHOTT:N-LASF45"})
    assert lens.prescription.surfaces[0].medium.glass == "N-LASF45" and "N-LASF55" in lens.prescription.notes
