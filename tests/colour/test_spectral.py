"""Spectral colour tables (jaxflare.colour._spectral): physics checks against colour-science.

The renderer averages per-wavelength contributions over a uniformly drawn wavelength, so most
checks evaluate that average either on a dense uniform grid (midpoint rule through the public
interpolation functions; the interpolants are piecewise linear, so this is accurate to ~1e-8) or by
Monte Carlo. Runs in float64 (conftest.py) unless stated.
"""

import colour
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflare.colour import _spectral as jc

SPACES = jc.COLOUR_SPACES
N_DENSE = 40_000


def _dense_wavelengths(table, n=N_DENSE):
    lo, hi = table.band_nm
    return lo + (np.arange(n) + 0.5) * (hi - lo) / n


def _band_mean_rgb(table, c, n=N_DENSE):
    """Uniform-wavelength average of K(lambda) @ c (dense midpoint rule)."""
    k = jc.rgb_response_at(table, _dense_wavelengths(table, n))
    return np.asarray(jnp.mean(k @ jnp.asarray(c), axis=0))


def _band_mean_spectrum(table, s_grid, n=N_DENSE):
    """Uniform-wavelength average of S(lambda) r(lambda), the product tabulated on the grid and
    interpolated linearly (as the renderer does)."""
    lam = _dense_wavelengths(table, n)
    product = s_grid[:, None] * np.asarray(table.spectrum_response)
    per_sample = jc.interpolate_on_grid(table.wavelength_nm, jnp.asarray(product), lam)
    return np.asarray(jnp.mean(per_sample, axis=0))


def _spectrum_of(table, c):
    """The emission spectrum implied by colour c on the grid: K(lambda) @ c = s(lambda) r(lambda)."""
    k = np.asarray(table.rgb_response)
    r = np.asarray(table.spectrum_response)
    w = np.asarray(table.luminance_weights)
    return (k @ np.asarray(c) @ w) / (r @ w)


def _d65_on(table):
    d65 = colour.SDS_ILLUMINANTS["D65"]
    return jc.normalise_spectrum(d65.wavelengths, d65.values, table)


# ----------------------------------------------------------------------------------------------
# names and construction


def test_colour_space_names():
    assert SPACES == ("ACEScg", "sRGB-linear")
    for alias in ("ACEScg", "acescg", "ACES-CG", "aces_cg"):
        assert jc.canonical_colour_space(alias) == "ACEScg"
    for alias in ("sRGB-linear", "srgb", "SRGB", "linear-srgb", "srgb-linear", "lin_srgb", "Linear sRGB"):
        assert jc.canonical_colour_space(alias) == "sRGB-linear"
    for bad in ("ACES2065-1", "rec2020", "", None):
        with pytest.raises(ValueError, match="ACEScg, sRGB-linear") as info:
            jc.canonical_colour_space(bad)
        assert repr(bad) in str(info.value)
    with pytest.raises(ValueError, match="'P3'.*ACEScg"):
        jc.spectral_table("P3")
    with pytest.raises(ValueError, match="valid names"):
        jc.display_matrix("XYZ")


def test_table_grid_and_cache():
    t = jc.spectral_table()
    assert t.colour_space == "ACEScg" and t.band_nm == (380.0, 780.0)
    np.testing.assert_array_equal(np.asarray(t.wavelength_nm), np.arange(380.0, 781.0, 5.0))
    assert t.rgb_response.shape == (81, 3, 3) and t.spectrum_response.shape == (81, 3)
    assert jc.spectral_table("acescg") is t  # cached on canonical arguments
    # A step that does not divide the band: both ends kept, step no larger than asked.
    g = np.asarray(jc.spectral_table("srgb", (400.0, 700.0), 7.0).wavelength_nm)
    assert g[0] == 400.0 and g[-1] == 700.0 and np.all(np.diff(g) <= 7.0 + 1e-12)
    with jax.enable_x64(False):
        t32 = jc.spectral_table()
        assert t32.rgb_response.dtype == jnp.float32
    assert t.rgb_response.dtype == jnp.float64


@pytest.mark.parametrize(
    "band", [(300.0, 780.0), (380.0, 800.0), (500.0, 500.0), (600.0, 500.0), (380.0, float("nan")), (400.0,)]
)
def test_bad_band(band):
    with pytest.raises(ValueError, match="band_nm"):
        jc.spectral_table("srgb", band)


@pytest.mark.parametrize("step", [0.0, -5.0, float("inf"), 500.0])
def test_bad_step(step):
    with pytest.raises(ValueError, match="step_nm"):
        jc.spectral_table("srgb", (380.0, 780.0), step)


# ----------------------------------------------------------------------------------------------
# RGB lights


@pytest.mark.parametrize("space", SPACES)
@pytest.mark.parametrize("band", [(380.0, 780.0), (400.0, 700.0)])
def test_band_mean_reproduces_colour(space, band):
    t = jc.spectral_table(space, band)
    rng = np.random.default_rng(0)
    colours = np.concatenate([np.eye(3), np.ones((1, 3)), rng.uniform(0, 2, (4, 3)), [[0.3, -0.1, 1.5]]])
    k = jc.rgb_response_at(t, _dense_wavelengths(t))
    got = np.asarray(jnp.mean(k, axis=0)) @ colours.T
    np.testing.assert_allclose(got, colours.T, atol=1e-6)
    # The grid (trapezoid) mean is exactly the identity.
    w = jc._mean_weights(np.asarray(t.wavelength_nm))
    np.testing.assert_allclose(np.einsum("l,lij->ij", w, np.asarray(t.rgb_response)), np.eye(3), atol=1e-12)


@pytest.mark.parametrize("space", SPACES)
def test_monte_carlo_converges(space):
    t = jc.spectral_table(space)
    n = 200_000
    lam = jax.random.uniform(jax.random.key(1), (n,), minval=t.band_nm[0], maxval=t.band_nm[1])
    for c in (np.ones(3), np.array([1.0, 0.0, 0.0]), np.array([0.2, 0.7, 0.4])):
        samples = np.asarray(jc.rgb_response_at(t, lam) @ jnp.asarray(c))
        err = samples.mean(axis=0) - c
        sigma = samples.std(axis=0) / np.sqrt(n)
        assert np.all(np.abs(err) < 5 * sigma + 1e-9), (c, err, sigma)


@pytest.mark.parametrize("space", SPACES)
def test_physical_before_renormalisation(space):
    """The Mallett spectra seen through the CIE 1931 observer already give (nearly) the identity:
    the final renormalisation is a small correction, not what makes colours come out right."""
    raw = jc._build_tables(space, (380.0, 780.0), 5.0)["raw_mean"]
    np.testing.assert_allclose(raw, np.eye(3), atol=1e-3)


@pytest.mark.parametrize("space", SPACES)
def test_white_is_d65_and_response_is_rank_one(space):
    t = jc.spectral_table(space)
    np.testing.assert_allclose(_band_mean_rgb(t, np.ones(3)), np.ones(3), atol=1e-7)
    # Each wavelength contributes (emission value) x (observer response): K(lambda) has rank one,
    # with columns along r(lambda).
    k = np.asarray(t.rgb_response)
    r = np.asarray(t.spectrum_response)
    sv = np.linalg.svd(k, compute_uv=False)
    assert np.all(sv[:, 1] <= 1e-12 * sv[:, 0])
    kc = k @ np.array([0.3, 0.5, 0.9])
    cross = np.cross(kc, r)
    assert np.max(np.abs(cross)) <= 1e-12 * np.max(np.abs(kc)) * np.max(np.abs(r))
    # White light emits the D65 spectrum (the Mallett basis sums to 1), up to a constant.
    s_white = _spectrum_of(t, np.ones(3))
    d65 = colour.SDS_ILLUMINANTS["D65"]
    d65_grid = np.interp(np.asarray(t.wavelength_nm), d65.wavelengths, d65.values)
    ratio = s_white / d65_grid
    np.testing.assert_allclose(ratio / ratio.mean(), 1.0, rtol=2e-3)


def test_luminance_weights():
    for space in SPACES:
        w = np.asarray(jc.spectral_table(space).luminance_weights)
        assert abs(w.sum() - 1.0) < 1e-6
        # White (1, 1, 1) has luminance 1 and spectral luminance agrees with the weights.
        y = _band_mean_rgb(jc.spectral_table(space), np.ones(3)) @ w
        assert abs(y - 1.0) < 1e-6
    np.testing.assert_allclose(
        np.asarray(jc.spectral_table("ACEScg").luminance_weights),
        colour.models.RGB_COLOURSPACE_ACESCG.matrix_RGB_to_XYZ[1],
        rtol=1e-9,
    )
    # sRGB: the unrounded IEC 61966-2-1 weights (derived from the primaries and D65).
    np.testing.assert_allclose(np.asarray(jc.spectral_table("srgb").luminance_weights), [0.2126, 0.7152, 0.0722], atol=1e-4)


@pytest.mark.parametrize("space", SPACES)
def test_primary_spectra(space):
    t = jc.spectral_table(space)
    lam = np.asarray(t.wavelength_nm)
    to_out = np.linalg.inv(jc.display_matrix(space))  # sRGB primaries expressed in the output space
    long, short = lam > 600, lam < 500
    red, green, blue = (_spectrum_of(t, to_out[:, i]) for i in range(3))
    assert red[long].sum() > 3 * red[short].sum()
    assert blue[short].sum() > 3 * blue[long].sum()
    assert green[(lam > 500) & (lam < 600)].sum() > green[long].sum() + green[short].sum()
    # sRGB-gamut colours have non-negative (Mallett) spectra ...
    for c in (to_out[:, 0], to_out[:, 1], to_out[:, 2], to_out @ [0.9, 0.4, 0.1]):
        s = _spectrum_of(t, c)
        assert s.min() >= -1e-3 * s.max()
    # ... an ACEScg primary outside the sRGB gamut has a spectrum that is negative somewhere, yet
    # the band mean still reproduces it exactly.
    if space == "ACEScg":
        s = _spectrum_of(t, [0.0, 1.0, 0.0])
        assert s.min() < -1e-2 * s.max()
        np.testing.assert_allclose(_band_mean_rgb(t, [0.0, 1.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-7)


def test_gradient_is_the_linear_map():
    t = jc.spectral_table("ACEScg")
    lam = jnp.linspace(370.0, 790.0, 257)

    @jax.jit
    def f(c):
        return jnp.sum(jc.rgb_response_at(t, lam) @ c)

    c0 = jnp.array([0.4, 1.3, -0.2])
    g = jax.grad(f)(c0)
    expected = np.asarray(jc.rgb_response_at(t, lam)).sum(axis=(0, 1))
    assert np.all(np.isfinite(np.asarray(g)))
    np.testing.assert_allclose(np.asarray(g), expected, rtol=1e-12)
    np.testing.assert_allclose(float(f(2 * c0)), 2 * float(f(c0)), rtol=1e-12)  # linear in c
    # vmap over wavelengths agrees with the batched call; the wavelength gradient is finite.
    one = jax.vmap(lambda x: jc.rgb_response_at(t, x))(lam)
    np.testing.assert_allclose(np.asarray(one), np.asarray(jc.rgb_response_at(t, lam)), rtol=1e-14)
    dl = jax.grad(lambda x: jnp.sum(jc.spectrum_response_at(t, x)))(550.0)
    assert np.isfinite(float(dl))


def test_interpolation_and_clamping():
    t = jc.spectral_table("srgb")
    k = np.asarray(t.rgb_response)
    at = np.asarray(jc.rgb_response_at(t, [300.0, 380.0, 382.5, 780.0, 900.0]))
    np.testing.assert_allclose(at[0], k[0])
    np.testing.assert_allclose(at[1], k[0])
    np.testing.assert_allclose(at[2], 0.5 * (k[0] + k[1]))
    np.testing.assert_allclose(at[3], k[-1])
    np.testing.assert_allclose(at[4], k[-1])
    r = np.asarray(jc.spectrum_response_at(t, jnp.array([[555.0, 557.0]])))
    assert r.shape == (1, 2, 3)
    np.testing.assert_allclose(r[0, 1], 0.6 * np.asarray(t.spectrum_response)[35] + 0.4 * np.asarray(t.spectrum_response)[36])


# ----------------------------------------------------------------------------------------------
# spectral lights


@pytest.mark.parametrize("space", SPACES)
def test_d65_spectrum_is_white(space):
    t = jc.spectral_table(space)
    s = _d65_on(t)
    rgb = _band_mean_spectrum(t, s)
    np.testing.assert_allclose(rgb, np.ones(3), atol=1e-2)
    assert abs(rgb @ np.asarray(t.luminance_weights) - 1.0) < 1e-7
    # The equal-energy spectrum S = 1 has luminance 1 (the scale of spectrum_response).
    assert abs(_band_mean_spectrum(t, np.ones(t.wavelength_nm.shape[0])) @ np.asarray(t.luminance_weights) - 1.0) < 1e-7


def test_blackbody():
    t = jc.spectral_table("sRGB-linear")
    w = np.asarray(t.luminance_weights)
    warm = _band_mean_spectrum(t, jc.blackbody_spectrum(2700.0, t))
    cool = _band_mean_spectrum(t, jc.blackbody_spectrum(10000.0, t))
    assert warm[0] > warm[1] > warm[2] > 0
    assert cool[2] > cool[0]
    assert abs(warm @ w - 1.0) < 1e-7 and abs(cool @ w - 1.0) < 1e-7
    # Agrees with colour-science's own spectral integration (XYZ -> sRGB, luminance 1). The
    # reference integrates over 360-830 nm at 1 nm; the table stops at 380-780 nm with a 5 nm
    # linear interpolant, hence the 1% tolerance.
    for temperature, got in ((2700.0, warm), (10000.0, cool)):
        xyz = colour.sd_to_XYZ(colour.sd_blackbody(temperature), method="Integration")
        ref = np.linalg.inv(colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ) @ (xyz / xyz[1])
        np.testing.assert_allclose(got, ref, rtol=1e-2)
    # ACEScg: the same colour through the CATs (D65 -> ACES white -> D65 is the identity). Only the
    # scale differs: luminance is measured after adaptation to the ACES white, where the Y of a
    # non-white light is not its CIE Y (0.5% here).
    ta = jc.spectral_table("ACEScg")
    warm_a = _band_mean_spectrum(ta, jc.blackbody_spectrum(2700.0, ta))
    assert abs(warm_a @ np.asarray(ta.luminance_weights) - 1.0) < 1e-7
    as_srgb = jc.display_matrix("ACEScg") @ warm_a
    np.testing.assert_allclose(as_srgb / (as_srgb @ w), warm, rtol=1e-7)
    assert abs(as_srgb @ w - 1.0) < 1e-2


def test_normalise_spectrum_resampling():
    t = jc.spectral_table("srgb", (400.0, 700.0), 10.0)
    # A spectrum covering only part of the band is zero outside its samples.
    s = jc.normalise_spectrum([500.0, 600.0], [1.0, 1.0], t)
    lam = np.asarray(t.wavelength_nm)
    assert np.all(s[(lam < 500) | (lam > 600)] == 0) and np.all(s[(lam >= 500) & (lam <= 600)] > 0)
    assert s.dtype == np.float64 and s.shape == lam.shape
    # Scaling the input does not change the result.
    d65 = colour.SDS_ILLUMINANTS["D65"]
    np.testing.assert_allclose(jc.normalise_spectrum(d65.wavelengths, 7 * d65.values, t), _d65_on(t), rtol=1e-12)


@pytest.mark.parametrize(
    ("wavelengths", "values", "match"),
    [
        ([400.0, 500.0, 600.0], [1.0, 1.0], "same length"),
        ([500.0], [1.0], "at least 2"),
        ([400.0, 400.0, 600.0], [1.0, 1.0, 1.0], "increasing"),
        ([600.0, 500.0], [1.0, 1.0], "increasing"),
        ([400.0, 500.0], [1.0, -0.5], "non-negative"),
        ([400.0, 500.0], [1.0, float("nan")], "finite"),
        ([400.0, float("inf")], [1.0, 1.0], "finite"),
        ([800.0, 900.0], [1.0, 1.0], "zero luminance"),
        ([400.0, 700.0], [0.0, 0.0], "zero luminance"),
        ([[400.0, 700.0]], [[1.0, 1.0]], "1-D"),
    ],
)
def test_bad_spectra(wavelengths, values, match):
    with pytest.raises(ValueError, match=match):
        jc.normalise_spectrum(wavelengths, values, jc.spectral_table("srgb"))


@pytest.mark.parametrize("temperature", [100.0, 499.0, 60000.0, float("nan"), "hot"])
def test_bad_temperature(temperature):
    with pytest.raises(ValueError, match="temperature_k"):
        jc.blackbody_spectrum(temperature, jc.spectral_table("srgb"))


# ----------------------------------------------------------------------------------------------
# display


def test_display_matrix_and_encoding():
    np.testing.assert_allclose(jc.display_matrix("srgb"), np.eye(3), atol=1e-12)
    m = jc.display_matrix("ACEScg")
    np.testing.assert_allclose(m @ np.ones(3), np.ones(3), atol=1e-12)  # white to white (CAT)
    ref = colour.matrix_RGB_to_RGB(colour.RGB_COLOURSPACES["ACEScg"], colour.RGB_COLOURSPACES["sRGB"], "Bradford")
    np.testing.assert_allclose(m, ref, atol=1e-3)
    x = np.array([-1.0, 0.0, 0.002, 0.0031308, 0.18, 0.5, 1.0, 3.0])
    enc = jc.srgb_encode(x)
    np.testing.assert_allclose(enc, colour.cctf_encoding(np.clip(x, 0, 1), "sRGB"), atol=1e-12)
    assert enc[0] == 0.0 and abs(enc[-1] - 1.0) < 1e-15
    np.testing.assert_allclose(enc[3], 0.04045, atol=1e-6)


def test_import_is_lazy():
    import subprocess
    import sys

    code = "import sys, jaxflare.colour._spectral; assert 'colour' not in sys.modules, 'colour imported eagerly'"
    subprocess.run([sys.executable, "-c", code], check=True)
