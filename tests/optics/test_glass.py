"""The glass catalog: data checked against manufacturer datasheets, lookup rules, model glasses.

Runs in float64 (conftest enables x64), so index values are compared at the 1e-9 level where the
physics promises exactness.
"""

import importlib.resources
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflare.optics import (
    C_LINE_NM,
    D_LINE_NM,
    F_LINE_NM,
    Glass,
    UnknownGlassError,
    catalogs,
    find_glass,
    glass_names,
    model_glass,
    nearest_glass,
    sellmeier_index,
)

MAKERS = ("SCHOTT", "OHARA", "HOYA", "HIKARI", "CDGM", "SUMITA")

# Names that old patents and .zmx files use for withdrawn (mostly lead or arsenic) glasses. The lead
# flints differ measurably from their N- successors; for crowns such as BK7, K5 or LAK9 SCHOTT matched
# the successor to the old glass and its files give the same coefficients for both.
OLD_FLINTS = ("SF5", "SF15", "F2", "SF2", "SF1", "SF10", "SF11", "SF4", "SF6", "SF8", "KF9")
OLD_OTHERS = ("BK7", "SK16", "LAK9", "BAF10", "SK4", "K5", "BAK1", "SSK4", "LAF2", "LAK8", "LAK21", "SK15", "SK5")
OLD_NAMES = OLD_FLINTS + OLD_OTHERS


def n_at(glass: Glass, wavelength_nm) -> np.ndarray:
    return np.asarray(glass.index(np.asarray(wavelength_nm, dtype=np.float64)))


def abbe(glass: Glass) -> float:
    n_d, n_f, n_c = n_at(glass, [D_LINE_NM, F_LINE_NM, C_LINE_NM])
    return float((n_d - 1.0) / (n_f - n_c))


def all_glasses() -> list[Glass]:
    return [find_glass(f"{c}:{n}") for c in catalogs() for n in glass_names(c)]


# ------------------------------------------------------------------------------ data


@pytest.mark.parametrize(
    "name, n_d, v_d",
    [
        ("N-BK7", 1.5168, 64.17),  # SCHOTT datasheet
        ("SF5", 1.6727, 32.21),  # the old lead flint, not N-SF5
        ("F2", 1.6200, 36.37),
        ("N-SF6", 1.80518, 25.36),
        ("SF11", 1.78472, 25.76),  # N-SF11 is 25.68
        ("SK16", 1.62041, 60.33),  # withdrawn arsenic crown (2008 SCHOTT file)
        ("S-BSL7", 1.51633, 64.14),  # OHARA
        ("F_SILICA", 1.45846, 67.82),  # Malitson fused silica
    ],
)
def test_datasheet_values(name, n_d, v_d):
    glass = find_glass(name)
    assert float(n_at(glass, D_LINE_NM)) == pytest.approx(n_d, abs=1e-4)
    assert abbe(glass) == pytest.approx(v_d, abs=0.05)


def test_catalogs_present_with_many_glasses():
    assert catalogs()[0] == "SCHOTT"
    for maker in MAKERS:
        assert maker in catalogs()
        assert len(glass_names(maker)) > 50, maker
    assert {"F_SILICA", "CAF2", "SAPPHIRE"} <= set(glass_names("MISC"))


@pytest.mark.parametrize("name", OLD_NAMES)
def test_old_names_resolve_to_old_glasses(name):
    glass = find_glass(name)
    assert glass.name == name  # never silently the N- (lead-free) successor
    assert glass.catalog == {"BAF10": "HOYA", "SSK4": "SUMITA"}.get(name, "SCHOTT")
    try:
        successor = find_glass("N-" + name)
    except UnknownGlassError:
        return
    assert successor.name == "N-" + name and successor is not glass
    if name in OLD_FLINTS:
        wavelengths = np.linspace(400.0, 700.0, 31)
        assert np.max(np.abs(n_at(glass, wavelengths) - n_at(successor, wavelengths))) > 2e-5


def test_sf5_and_n_sf5_are_different_glasses():
    old, new = find_glass("SF5"), find_glass("N-SF5")
    assert (old.catalog, old.name, new.name) == ("SCHOTT", "SF5", "N-SF5")
    assert old.sellmeier_b != new.sellmeier_b
    wavelengths = np.linspace(400.0, 700.0, 31)
    assert np.max(np.abs(n_at(old, wavelengths) - n_at(new, wavelengths))) > 5e-5


def test_every_row_is_consistent_and_normally_dispersive():
    glasses = all_glasses()
    assert 1500 < len(glasses) < 5000
    b = np.array([g.sellmeier_b for g in glasses])
    c = np.array([g.sellmeier_c_um2 for g in glasses])
    wavelengths = np.linspace(400.0, 700.0, 61)
    n = np.asarray(sellmeier_index(b[None], c[None], wavelengths[:, None]))  # (W, G)
    assert np.all(np.isfinite(n))
    assert np.all(np.diff(n, axis=0) < 0), "index must fall with wavelength over 400-700 nm"
    n_d, n_f, n_c = np.asarray(sellmeier_index(b[None], c[None], np.array([D_LINE_NM, F_LINE_NM, C_LINE_NM])[:, None]))
    stated_n_d = np.array([g.n_d for g in glasses])
    stated_v_d = np.array([g.v_d for g in glasses])
    assert np.max(np.abs(n_d - stated_n_d)) < 1e-4
    assert np.max(np.abs((n_d - 1) / (n_f - n_c) - stated_v_d)) < 0.3
    assert {g.status for g in glasses} <= {"current", "inquiry", "withdrawn", "n/a"}
    assert all(g.source for g in glasses)


def test_catalog_file_is_package_data_and_small():
    resource = importlib.resources.files("jaxflare.optics") / "data" / "glass_catalog.csv"
    assert resource.is_file()
    assert len(resource.read_bytes()) < 1_000_000


# ------------------------------------------------------------------------------ lookup


def test_unknown_name_lists_near_matches():
    with pytest.raises(UnknownGlassError) as info:
        find_glass("N-BK8")
    error = info.value
    assert isinstance(error, KeyError) and isinstance(error, ValueError)
    message = str(error)
    assert message.startswith("unknown glass 'N-BK8'")  # readable, not KeyError's repr
    assert "SCHOTT:N-BK7" in error.suggestions and "N-BK7" in message
    assert len(error.suggestions) == 5
    assert "SCHOTT" in message and "SUMITA" in message  # the catalogs searched


def test_glasses_left_out_of_the_table_say_why():
    with pytest.raises(UnknownGlassError, match="HOYA lists it, but no 3-term Sellmeier form"):
        find_glass("E-FDS1")  # a dense flint no 3-term Sellmeier follows to 2e-5 over 365-1014 nm


def test_case_catalog_prefix_and_preference_order():
    assert find_glass("n-bk7").name == "N-BK7"
    assert find_glass("SF5").catalog == "SCHOTT"
    assert find_glass("SF5", ["HIKARI"]).catalog == "HIKARI"
    assert find_glass("SF5", ("sumita", "HIKARI")).catalog == "SUMITA"
    assert find_glass("hikari:sf5").qualified_name == "HIKARI:SF5"
    assert find_glass("N-BK7", ["OHARA"]).catalog == "SCHOTT"  # not in OHARA: falls through
    assert find_glass("N-BK7", ["INFRARED"]).catalog == "SCHOTT"  # unknown catalogs are ignored
    with pytest.raises(UnknownGlassError, match="OHARA"):
        find_glass("OHARA:N-BK7")  # a catalog prefix searches that catalog only
    with pytest.raises(UnknownGlassError, match="no catalog 'ACME'"):
        find_glass("ACME:N-BK7")


def test_spelling_variants_only_where_unambiguous():
    assert find_glass("NBK7").name == "N-BK7"
    assert find_glass("slah64").qualified_name == "OHARA:S-LAH64"
    assert find_glass("NSF5").name == "N-SF5"
    assert find_glass("SF5").name == "SF5"
    with pytest.raises(UnknownGlassError):
        find_glass("N-SF5X")


def test_glass_names_and_catalogs():
    assert "N-BK7" in glass_names("SCHOTT") and "N-BK7" in glass_names()
    assert "N-BK7" not in glass_names("OHARA")
    assert len(glass_names()) == len(set(glass_names()))
    with pytest.raises(ValueError, match="unknown glass catalog"):
        glass_names("ACME")


def test_nearest_glass():
    assert nearest_glass(1.5168, 64.17).name in ("N-BK7", "BK7")
    ohara = nearest_glass(1.5168, 64.17, ["OHARA"])
    assert ohara.catalog == "OHARA" and ohara.name in ("S-BSL7", "BSL7")
    best = min(
        (find_glass(f"OHARA:{n}") for n in glass_names("OHARA")),
        key=lambda g: (g.n_d - 1.5168) ** 2 + 1e-4 * (g.v_d - 64.17) ** 2,
    )
    assert ohara is best
    glass = nearest_glass(1.6727, 32.21, catalogs=("SCHOTT",))
    assert (glass.n_d, glass.v_d) == (1.6727, 32.21)
    with pytest.raises(ValueError):
        nearest_glass(1.5, 60.0, ["ACME"])


# ------------------------------------------------------------------------------ model glass


@pytest.mark.parametrize(
    "n_d, v_d", list(itertools.product([1.01, 1.3, 1.5168, 1.7, 1.9, 2.2, 2.49], [10.5, 20.0, 35.0, 64.17, 90.0, 119.0]))
)
def test_model_glass_reproduces_n_d_and_v_d_exactly(n_d, v_d):
    glass = model_glass(n_d, v_d)
    assert glass.catalog == "MODEL" and glass.status == "model"
    assert glass.sellmeier_b[1:] == (0.0, 0.0) and glass.sellmeier_c_um2[1:] == (0.0, 0.0)
    assert 0.0 < glass.sellmeier_c_um2[0] < 0.1  # one pole in the ultraviolet
    assert abs(float(n_at(glass, D_LINE_NM)) - n_d) < 1e-9
    assert abs(abbe(glass) - v_d) < 1e-9


def test_model_glass_name_and_validation():
    assert model_glass(1.64238, 48.0).name == "MODEL_1.64238_48.0"
    for kwargs, parameter, bounds in [
        ({"n_d": 1.0, "v_d": 50.0}, "n_d", r"\(1\.0, 2\.5\)"),
        ({"n_d": 2.6, "v_d": 50.0}, "n_d", r"\(1\.0, 2\.5\)"),
        ({"n_d": 1.5, "v_d": 10.0}, "v_d", r"\(10\.0, 120\.0\)"),
        ({"n_d": 1.5, "v_d": float("nan")}, "v_d", r"\(10\.0, 120\.0\)"),
    ]:
        with pytest.raises(ValueError, match=parameter + ".*" + bounds):
            model_glass(**kwargs)


def test_model_glass_disperses_like_a_real_glass():
    real, model = find_glass("N-BK7"), model_glass(1.5168, 64.17)
    wavelengths = np.linspace(400.0, 700.0, 61)
    assert np.max(np.abs(n_at(real, wavelengths) - n_at(model, wavelengths))) < 2e-3
    assert np.all(np.diff(n_at(model, wavelengths)) < 0)


# ------------------------------------------------------------------------------ the formula in JAX


def test_sellmeier_index_is_jittable_differentiable_and_broadcasts():
    glass = find_glass("N-BK7")
    b, c = jnp.asarray(glass.sellmeier_b), jnp.asarray(glass.sellmeier_c_um2)
    slope = jax.grad(lambda w: sellmeier_index(b, c, w))(550.0)
    assert np.isfinite(slope) and slope < 0
    # finite-difference check of the slope (dn/dλ of N-BK7 at 550 nm is about -5e-5 per nm)
    h = 1e-3
    fd = (float(glass.index(550.0 + h)) - float(glass.index(550.0 - h))) / (2 * h)
    assert float(slope) == pytest.approx(fd, rel=1e-5)
    jitted = jax.jit(sellmeier_index)(b, c, 587.56)
    assert float(jitted) == pytest.approx(1.5168, abs=1e-4)
    lens_b = jnp.stack([jnp.zeros(3), b, jnp.asarray(find_glass("F2").sellmeier_b)])  # air, crown, flint
    lens_c = jnp.stack([jnp.zeros(3), c, jnp.asarray(find_glass("F2").sellmeier_c_um2)])
    n = sellmeier_index(lens_b[None], lens_c[None], jnp.array([450.0, 550.0, 650.0])[:, None])
    assert n.shape == (3, 3)
    np.testing.assert_allclose(np.asarray(n[:, 0]), 1.0)
    assert np.all(np.asarray(n[:, 2]) > np.asarray(n[:, 1]))
    # numpy inputs work too and agree with the method
    assert float(sellmeier_index(np.array(glass.sellmeier_b), np.array(glass.sellmeier_c_um2), np.float64(500.0))) == float(
        glass.index(500.0)
    )


def test_glass_is_hashable_and_coerces_coefficients():
    glass = Glass("X", "TEST", [1.0, 0.2, 1.0], [0.006, 0.02, 100.0], 1.5, 60.0)
    assert isinstance(glass.sellmeier_b, tuple) and hash(glass) == hash(
        Glass("X", "TEST", (1.0, 0.2, 1.0), (0.006, 0.02, 100.0), 1.5, 60.0)
    )
    assert find_glass("N-BK7") is find_glass("SCHOTT:N-BK7")
    with pytest.raises(ValueError, match="3 coefficients"):
        Glass("X", "TEST", (1.0, 0.2), (0.006, 0.02, 100.0), 1.5, 60.0)
