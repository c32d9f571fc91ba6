"""Spectral colour: wavelengths to RGB through the CIE 1931 observer (colour-science).

Tables over a uniform wavelength grid (:class:`SpectralTable`, :func:`spectral_table`) turn a
sample's wavelength and its light's RGB colour or spectrum into the RGB it adds to the image, in
ACEScg or linear sRGB; :func:`blackbody_spectrum` and :func:`normalise_spectrum` prepare spectral
lights; :func:`display_matrix` and :func:`srgb_encode` serve previews. Imports nothing else of
jaxflare.
"""

from ._spectral import (
    SpectralTable,
    blackbody_spectrum,
    canonical_colour_space,
    colour_space_chromaticities,
    display_matrix,
    grid_position,
    interpolate_on_grid,
    normalise_spectrum,
    rgb_response_at,
    spectral_table,
    spectrum_response_at,
    srgb_encode,
)

__all__ = [
    "SpectralTable",
    "blackbody_spectrum",
    "canonical_colour_space",
    "colour_space_chromaticities",
    "display_matrix",
    "grid_position",
    "interpolate_on_grid",
    "normalise_spectrum",
    "rgb_response_at",
    "spectral_table",
    "spectrum_response_at",
    "srgb_encode",
]
