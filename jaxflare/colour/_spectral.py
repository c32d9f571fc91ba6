"""Spectral colour for a Monte Carlo renderer that samples one wavelength per ray.

Every ray carries one wavelength ``lambda`` drawn uniformly over a band (default 380-780 nm). The
tables here turn (light colour, wavelength) into that ray's linear RGB contribution in an output
colour space (``"ACEScg"`` or ``"sRGB-linear"``), such that averaging the contributions over
uniformly drawn wavelengths converges to the light's colour. The tables are built once, in float64
NumPy with colour-science, and used as constant JAX arrays; the per-sample work is a linear
interpolation on the wavelength grid and a 3x3 (or 3-vector) product, so it is linear and
differentiable in the light colour (and piecewise linear in the wavelength).

Method (RGB lights)
-------------------
A light of linear RGB colour ``c`` in the output space is first converted to linear sRGB
(``c_srgb = B c``; for ACEScg, whose white is the ACES white ~D60, with a Bradford chromatic
adaptation to D65). Its emission spectrum is

    E(lambda) = sum_k (c_srgb)_k b_k(lambda) D65(lambda),

where ``b_k`` are the spectral primaries of Mallett & Yuksel, "Spectral Primary Decomposition for
Rendering with sRGB Reflectance", EGSR 2019 (``colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019``:
three smooth, non-negative reflectances summing to 1 at every wavelength, so white (1, 1, 1) is
exactly the D65 spectrum) and ``D65`` is the CIE D65 spectral power distribution. The colour seen
at one wavelength is ``A cmf(lambda) E(lambda)``, with ``cmf`` the CIE 1931 2-degree colour matching
functions (``colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]``) and ``A`` the XYZ to output
RGB matrix, with a Bradford adaptation from D65 to the output space's white. Hence

    K(lambda) = r(lambda) e(lambda)^T              (a rank-one 3x3 matrix per wavelength),

where ``r(lambda) = kappa A cmf(lambda)`` is :attr:`SpectralTable.spectrum_response` and
``e(lambda)^T c`` is the (scaled) emission at ``lambda``. Finally ``K`` is renormalised,
``K <- K (mean K)^-1``, so that its band mean is *exactly* the identity: white stays white and
every colour is reproduced exactly by the Monte Carlo average. Before this correction the band
mean is already within about 3e-4 of the identity over 380-780 nm (below 2e-3 over 400-700 nm;
the residual comes from the fit of the Mallett basis, from linear interpolation and from truncating
the band), so the correction is small and the implied spectra remain the physical Mallett spectra.

Colours outside the sRGB gamut (possible in ACEScg) have negative sRGB weights, so their
intermediate spectrum ``e(lambda)^T c`` is negative at some wavelengths. The linear map ``K`` still
reproduces them exactly in the band mean, but individual samples can carry negative components.

Method (spectral lights)
------------------------
A light with spectral values ``S(lambda)`` on the table grid contributes ``S(lambda) r(lambda)`` per
sample; its output RGB is the band mean of that product. ``kappa`` is chosen so that the equal
energy spectrum ``S = 1`` has luminance 1. :func:`normalise_spectrum` and
:func:`blackbody_spectrum` rescale a spectrum so that its luminance is 1, the luminance of RGB
white (1, 1, 1), which makes spectral and RGB lights of the same nominal intensity equally bright.

Units and conventions
---------------------
- Wavelengths are vacuum wavelengths in nanometres.
- The grid spans the band including both ends, uniformly, with a step of at most ``step_nm``.
- "Band mean" means the mean over a uniformly distributed wavelength of the piecewise-linear
  interpolant used by :func:`rgb_response_at` / :func:`spectrum_response_at` (the trapezoid rule on
  the grid); for a spectral light, likewise of the product ``S(lambda) r(lambda)`` tabulated on
  the grid and interpolated linearly. Wavelengths outside the band clamp to its ends.
- Luminance is ``luminance_weights @ rgb``, the Y row of the output space's RGB to XYZ matrix
  (relative luminance, white = 1). The RGB to XYZ matrices are derived from colour-science's
  primaries and whitepoints (ACEScg: its published matrix; sRGB: Y row 0.21264, 0.71517, 0.07219,
  the unrounded form of the IEC 61966-2-1 matrix), so white maps exactly to white.
- Chromatic adaptation (ACEScg's white is the ACES white, x, y = 0.32168, 0.33767) is Bradford.
  For ACEScg, luminance is measured after adaptation, so a coloured spectral light normalised to
  luminance 1 has a CIE Y (relative to D65) that differs slightly from 1 (0.5% for 2700 K).
- Colour-science is imported lazily, only when a table is first built.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._disk_cache import persisted

__all__ = [
    "COLOUR_SPACES",
    "SpectralTable",
    "blackbody_spectrum",
    "canonical_colour_space",
    "display_matrix",
    "normalise_spectrum",
    "rgb_response_at",
    "spectral_table",
    "spectrum_response_at",
    "srgb_encode",
]

COLOUR_SPACES: tuple[str, ...] = ("ACEScg", "sRGB-linear")

# Aliases after lower-casing and removing spaces, "-", "_" and ".".
_ALIASES = {
    "acescg": "ACEScg",
    "acesap1": "ACEScg",
    "ap1": "ACEScg",
    "srgb": "sRGB-linear",
    "srgblinear": "sRGB-linear",
    "srgblin": "sRGB-linear",
    "linearsrgb": "sRGB-linear",
    "linsrgb": "sRGB-linear",
    "rec709": "sRGB-linear",
    "linearrec709": "sRGB-linear",
    "linrec709": "sRGB-linear",
}

# colour-science names of the output spaces (their linear RGB <-> XYZ matrices are used).
_COLOUR_SCIENCE_NAMES = {"ACEScg": "ACEScg", "sRGB-linear": "sRGB"}

_CMF_RANGE_NM = (380.0, 780.0)  # range of the Mallett basis (and D65 tabulation used here)
_MIN_STEP_NM = 0.1
_CAT = "Bradford"
_TEMPERATURE_RANGE_K = (500.0, 50000.0)


def canonical_colour_space(name: str) -> str:
    """Canonical output colour space name (one of :data:`COLOUR_SPACES`) for a case-insensitive alias."""
    if isinstance(name, str):
        key = name.strip().lower()
        for ch in " -_.":
            key = key.replace(ch, "")
        if key in _ALIASES:
            return _ALIASES[key]
    raise ValueError(
        f"unknown colour space {name!r}; valid names are {', '.join(COLOUR_SPACES)} "
        "(case-insensitive; aliases such as 'srgb', 'linear-srgb', 'lin_srgb', 'acescg' are accepted)"
    )


class SpectralTable(eqx.Module):
    """Per-wavelength colour tables on a uniform grid over ``band_nm``; see the module docstring.

    - ``wavelength_nm``: the grid (nm), both band ends included.
    - ``rgb_response``: ``K(lambda)``; an RGB light ``c`` (output space) contributes ``K(lambda) @ c``
      at a uniformly drawn ``lambda``; the band mean of ``K`` is exactly the identity.
    - ``spectrum_response``: ``r(lambda)``; a spectral light ``S`` contributes ``S(lambda) r(lambda)``.
    - ``luminance_weights``: relative luminance of each output primary (sums to 1).
    """

    wavelength_nm: Float[Array, " L"]
    rgb_response: Float[Array, "L 3 3"]
    spectrum_response: Float[Array, "L 3"]
    luminance_weights: Float[Array, " 3"]
    colour_space: str = eqx.field(static=True)
    band_nm: tuple[float, float] = eqx.field(static=True)


# ----------------------------------------------------------------------------------------------
# Table construction (NumPy float64, colour-science imported lazily)


def _validate_band(band_nm) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in band_nm)
    except (TypeError, ValueError):
        raise ValueError(f"band_nm must be a pair of wavelengths in nm, got {band_nm!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and _CMF_RANGE_NM[0] <= lo < hi <= _CMF_RANGE_NM[1]):
        raise ValueError(
            f"band_nm must satisfy {_CMF_RANGE_NM[0]:g} <= min < max <= {_CMF_RANGE_NM[1]:g} nm "
            f"(the range of the tabulated spectral data), got {band_nm!r}"
        )
    return lo, hi


def _validate_step(step_nm, lo: float, hi: float) -> float:
    try:
        step = float(step_nm)
    except (TypeError, ValueError):
        raise ValueError(f"step_nm must be a number of nm, got {step_nm!r}") from None
    if not (math.isfinite(step) and _MIN_STEP_NM <= step <= hi - lo):
        raise ValueError(f"step_nm must be between {_MIN_STEP_NM:g} nm and the band width {hi - lo:g} nm, got {step_nm!r}")
    return step


def _grid(lo: float, hi: float, step: float) -> np.ndarray:
    n_intervals = max(1, math.ceil((hi - lo) / step - 1e-9))
    return np.linspace(lo, hi, n_intervals + 1)


def _mean_weights(grid: np.ndarray) -> np.ndarray:
    """Weights ``w`` with ``w @ f`` = band mean of the piecewise-linear interpolant of ``f`` (trapezoid)."""
    d = np.diff(grid)
    w = np.zeros_like(grid)
    w[:-1] += d / 2
    w[1:] += d / 2
    return w / (grid[-1] - grid[0])


def colour_space_chromaticities(colour_space: str) -> tuple[float, float, float, float, float, float, float, float]:
    """CIE xy of the red, green and blue primaries and of the white point of an output colour
    space (colour-science's values): the eight numbers of an OpenEXR ``chromaticities`` attribute,
    in its order (red x, y, green x, y, blue x, y, white x, y). ACEScg: the AP1 primaries with the
    ACES white (about D60); linear sRGB: the Rec. 709 primaries with D65."""
    return tuple(float(v) for v in _chromaticities(canonical_colour_space(colour_space)))  # type: ignore[return-value]


@functools.cache
@persisted
def _chromaticities(colour_space: str) -> np.ndarray:
    import colour

    space = colour.RGB_COLOURSPACES[_COLOUR_SCIENCE_NAMES[colour_space]]
    return np.concatenate([np.asarray(space.primaries, dtype=np.float64).ravel(), np.asarray(space.whitepoint, np.float64)])


@functools.cache
@persisted
def _space_matrices(colour_space: str) -> tuple[np.ndarray, np.ndarray]:
    """``(RGB_to_XYZ, whitepoint XYZ)`` of an output space, float64.

    The matrix is the normalised primary matrix of colour-science's primaries and whitepoint (for
    ACEScg identical to its published matrix; for sRGB the unrounded form of the 4-digit IEC
    matrix), so that RGB white maps exactly to the whitepoint."""
    import colour

    space = colour.RGB_COLOURSPACES[_COLOUR_SCIENCE_NAMES[colour_space]]
    white_xy = np.asarray(space.whitepoint, dtype=np.float64)
    npm = colour.normalised_primary_matrix(np.asarray(space.primaries, dtype=np.float64), white_xy)
    return np.asarray(npm, dtype=np.float64), np.asarray(colour.xy_to_XYZ(white_xy), dtype=np.float64)


def _cat(white_from: np.ndarray, white_to: np.ndarray) -> np.ndarray:
    return _cat_matrix(tuple(float(v) for v in white_from), tuple(float(v) for v in white_to))


@functools.cache
@persisted
def _cat_matrix(white_from: tuple[float, float, float], white_to: tuple[float, float, float]) -> np.ndarray:
    import colour

    return np.asarray(colour.adaptation.matrix_chromatic_adaptation_VonKries(np.asarray(white_from), np.asarray(white_to), transform=_CAT))


@functools.cache
def _matrix_to_srgb(colour_space: str) -> np.ndarray:
    """Linear output space -> linear sRGB (D65), with a Bradford CAT when the whites differ."""
    m_out, w_out = _space_matrices(colour_space)
    m_srgb, w_srgb = _space_matrices("sRGB-linear")
    cat = np.eye(3) if np.allclose(w_out, w_srgb, rtol=0, atol=1e-12) else _cat(w_out, w_srgb)
    return np.linalg.inv(m_srgb) @ cat @ m_out


@functools.cache
def _xyz_d65_to_output(colour_space: str) -> np.ndarray:
    """XYZ (D65-relative) -> linear output RGB, with a Bradford CAT from D65 to the space's white."""
    m_out, w_out = _space_matrices(colour_space)
    _, w_d65 = _space_matrices("sRGB-linear")
    cat = np.eye(3) if np.allclose(w_out, w_d65, rtol=0, atol=1e-12) else _cat(w_d65, w_out)
    return np.linalg.inv(m_out) @ cat


def _resample(sd_wavelengths, sd_values, grid: np.ndarray) -> np.ndarray:
    """Linear interpolation of tabulated spectral data (L0,) or (L0, K) onto ``grid``."""
    wl = np.asarray(sd_wavelengths, dtype=np.float64)
    v = np.asarray(sd_values, dtype=np.float64)
    if v.ndim == 1:
        return np.interp(grid, wl, v)
    return np.stack([np.interp(grid, wl, v[:, k]) for k in range(v.shape[1])], axis=-1)


@functools.cache
@persisted
def _build_tables(colour_space: str, band_nm: tuple[float, float], step_nm: float) -> dict[str, np.ndarray]:
    """All tables in float64 NumPy, plus diagnostics (``raw_mean``: band mean of K before renormalisation)."""
    import colour

    grid = _grid(band_nm[0], band_nm[1], step_nm)
    w = _mean_weights(grid)

    basis_msds = colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019
    basis = _resample(basis_msds.wavelengths, basis_msds.values, grid)  # (L, 3): red, green, blue
    d65_sd = colour.SDS_ILLUMINANTS["D65"]
    d65 = _resample(d65_sd.wavelengths, d65_sd.values, grid)  # (L,)
    cmfs_msds = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    cmfs = _resample(cmfs_msds.wavelengths, cmfs_msds.values, grid)  # (L, 3): x, y, z bar

    a = _xyz_d65_to_output(colour_space)
    b = _matrix_to_srgb(colour_space)
    m_out, _ = _space_matrices(colour_space)
    lum_w = m_out[1].copy()

    # r(lambda) = kappa A cmf(lambda), kappa: the equal-energy spectrum S = 1 has luminance 1.
    r = cmfs @ a.T  # (L, 3)
    r = r / (w @ (r @ lum_w))

    # e(lambda)^T c = emission of colour c at lambda, scaled so that white has luminance 1.
    e = (basis * d65[:, None]) @ b  # (L, 3): row e(lambda) acts on output-space RGB
    k_raw = r[:, :, None] * e[:, None, :]  # (L, 3, 3)
    white_lum = lum_w @ np.einsum("l,lij->ij", w, k_raw) @ np.ones(3)
    e = e / white_lum
    k_raw = k_raw / white_lum
    raw_mean = np.einsum("l,lij->ij", w, k_raw)
    correction = np.linalg.inv(raw_mean)
    k = k_raw @ correction

    return {
        "wavelength_nm": grid,
        "rgb_response": k,
        "spectrum_response": r,
        "luminance_weights": lum_w,
        "emission_row": e @ correction,  # (L, 3): K(lambda) = r(lambda) emission_row(lambda)^T
        "raw_mean": raw_mean,
    }


def spectral_table(
    colour_space: str = "ACEScg", band_nm: tuple[float, float] = (380.0, 780.0), step_nm: float = 5.0
) -> SpectralTable:
    """Spectral colour tables for ``colour_space`` over ``band_nm`` (nm) on a grid of step at most ``step_nm``.

    Built once per argument set (cached) in float64; the arrays are ``jnp.asarray`` of the float64
    tables, so they take JAX's default float dtype (float32 unless x64 is enabled)."""
    name = canonical_colour_space(colour_space)
    lo, hi = _validate_band(band_nm)
    step = _validate_step(step_nm, lo, hi)
    # The float dtype jnp.asarray gives float64 data now (x64 on or off) is part of the cache key.
    dtype = str(jnp.asarray(np.zeros((), np.float64)).dtype)
    return _spectral_table_cached(name, (lo, hi), step, dtype)


@functools.lru_cache(maxsize=32)
def _spectral_table_cached(colour_space: str, band_nm: tuple[float, float], step_nm: float, dtype: str) -> SpectralTable:
    del dtype  # cache key only
    t = _build_tables(colour_space, band_nm, step_nm)
    return SpectralTable(
        wavelength_nm=jnp.asarray(t["wavelength_nm"]),
        rgb_response=jnp.asarray(t["rgb_response"]),
        spectrum_response=jnp.asarray(t["spectrum_response"]),
        luminance_weights=jnp.asarray(t["luminance_weights"]),
        colour_space=colour_space,
        band_nm=band_nm,
    )


# ----------------------------------------------------------------------------------------------
# Per-sample lookups (JAX)


def grid_position(grid: Array, wavelength_nm: Array) -> tuple[Array, Array]:
    """Where wavelengths fall on a uniform wavelength grid: the node below (int, clamped to
    ``[0, L - 2]``) and the fraction of the way to the next node (wavelengths outside the grid are
    clamped onto its ends). The one grid interpolation of the package: spectral responses, lights'
    spectra and the paths' Fresnel tables all use it."""
    position = jnp.clip((wavelength_nm - grid[0]) / (grid[1] - grid[0]), 0, grid.shape[0] - 1)
    below = jnp.clip(jnp.floor(position).astype(jnp.int32), 0, grid.shape[0] - 2)
    return below, position - below


def interpolate_on_grid(grid: Array, table: Array, wavelength_nm: ArrayLike) -> Array:
    """Piecewise-linear interpolation of ``table`` (L, ...) over the uniform ``grid`` (L,) at
    ``wavelength_nm`` (any shape S; the result has shape S + table.shape[1:]), clamped."""
    below, fraction = grid_position(grid, jnp.asarray(wavelength_nm, dtype=grid.dtype))
    fraction = fraction.reshape(fraction.shape + (1,) * (table.ndim - 1))
    return table[below] * (1 - fraction) + table[below + 1] * fraction


def rgb_response_at(table: SpectralTable, wavelength_nm: ArrayLike) -> Float[Array, "N 3 3"]:
    """``K(lambda)`` at the given wavelengths (nm, shape ``(N,)`` or any shape ``S`` -> ``S + (3, 3)``).

    A light of output-space RGB ``c`` contributes ``rgb_response_at(table, lam) @ c`` at ``lam``."""
    return interpolate_on_grid(table.wavelength_nm, table.rgb_response, wavelength_nm)


def spectrum_response_at(table: SpectralTable, wavelength_nm: ArrayLike) -> Float[Array, "N 3"]:
    """``r(lambda)`` at the given wavelengths (nm, shape ``(N,)`` or any shape ``S`` -> ``S + (3,)``).

    A spectral light with value ``S`` at ``lam`` contributes ``S * spectrum_response_at(table, lam)``."""
    return interpolate_on_grid(table.wavelength_nm, table.spectrum_response, wavelength_nm)


# ----------------------------------------------------------------------------------------------
# Spectral lights (NumPy)


def _table_luminance(values_on_grid: np.ndarray, table: SpectralTable) -> float:
    grid = np.asarray(table.wavelength_nm, dtype=np.float64)
    y = np.asarray(table.spectrum_response, dtype=np.float64) @ np.asarray(table.luminance_weights, dtype=np.float64)
    return float(_mean_weights(grid) @ (values_on_grid * y))


def normalise_spectrum(wavelengths_nm: ArrayLike, values: ArrayLike, table: SpectralTable) -> np.ndarray:
    """Resample a spectrum onto ``table``'s grid and scale it to luminance 1 (float64, shape ``(L,)``).

    ``wavelengths_nm`` must be strictly increasing (at least 2 samples); the spectrum is linearly
    interpolated between them and zero outside. ``values`` must be finite and non-negative. The
    luminance is ``luminance_weights`` applied to the band mean of ``S(lambda) r(lambda)`` (the
    product tabulated on the grid, linearly interpolated: the trapezoid rule)."""
    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    if wl.ndim != 1 or v.ndim != 1:
        raise ValueError(f"wavelengths_nm and values must be 1-D, got shapes {wl.shape} and {v.shape}")
    if wl.shape != v.shape:
        raise ValueError(f"wavelengths_nm and values must have the same length, got {wl.size} and {v.size}")
    if wl.size < 2:
        raise ValueError(f"a spectrum needs at least 2 samples, got {wl.size}")
    if not np.all(np.isfinite(wl)):
        raise ValueError("wavelengths_nm must be finite")
    if not np.all(np.diff(wl) > 0):
        raise ValueError("wavelengths_nm must be strictly increasing")
    if not np.all(np.isfinite(v)):
        raise ValueError("spectrum values must be finite")
    if np.any(v < 0):
        raise ValueError(f"spectrum values must be non-negative, got minimum {v.min():g}")
    grid = np.asarray(table.wavelength_nm, dtype=np.float64)
    s = np.interp(grid, wl, v, left=0.0, right=0.0)
    lum = _table_luminance(s, table)
    if not lum > 1e-300:
        raise ValueError(
            f"the spectrum has zero luminance in the band {table.band_nm[0]:g}-{table.band_nm[1]:g} nm "
            f"(samples span {wl[0]:g}-{wl[-1]:g} nm)"
        )
    return s / lum


def blackbody_spectrum(temperature_k: float, table: SpectralTable) -> np.ndarray:
    """Planck spectrum at ``temperature_k`` (500-50000 K) on ``table``'s grid, scaled to luminance 1."""
    try:
        t = float(temperature_k)
    except (TypeError, ValueError):
        raise ValueError(f"temperature_k must be a number, got {temperature_k!r}") from None
    lo, hi = _TEMPERATURE_RANGE_K
    if not (math.isfinite(t) and lo <= t <= hi):
        raise ValueError(f"temperature_k must be between {lo:g} and {hi:g} K, got {temperature_k!r}")
    h, c, k = 6.62607015e-34, 299792458.0, 1.380649e-23
    grid = np.asarray(table.wavelength_nm, dtype=np.float64)
    lam = grid * 1e-9
    # Spectral radiance up to a constant; the overall scale is removed by the normalisation.
    x = h * c / (lam * k * t)
    radiance = (lam / 500e-9) ** -5 / np.expm1(x)
    return radiance / _table_luminance(radiance, table)


# ----------------------------------------------------------------------------------------------
# Display helpers (NumPy)


def display_matrix(colour_space: str) -> np.ndarray:
    """3x3 matrix from linear ``colour_space`` RGB to linear sRGB (D65; Bradford CAT), for previews."""
    return _matrix_to_srgb(canonical_colour_space(colour_space)).copy()


def srgb_encode(x: ArrayLike) -> np.ndarray:
    """sRGB transfer function (IEC 61966-2-1, piecewise) of linear values clipped to [0, 1]."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
