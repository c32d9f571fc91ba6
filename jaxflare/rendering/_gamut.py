"""Colours outside the output gamut, handled the same way by every estimator.

A single wavelength (a Monte Carlo sample) or a narrow band (a grid wavelength stratum) seen
through the CIE observer and mapped to the output space (ACEScg, Rec.709, ...) can have a negative
channel. Summed over the visible band such colours are inside the gamut, but a pixel lit by part
of the band (a colour fringe, or a pixel that received few Monte Carlo samples) can stay outside
it; a compositor adding such a layer to a plate would darken the plate there.

:func:`clip_to_gamut` moves each such pixel towards the grey of the same luminance until its
lowest channel is zero: luminance and hue kept, saturation reduced. A pixel whose luminance is not
positive becomes black. Both estimators apply it to every layer before the default layer is summed
from them, so no layer has a negative pixel.
"""

from __future__ import annotations

import numpy as np


def clip_to_gamut(rgb: np.ndarray, luminance_weights: np.ndarray) -> np.ndarray:
    """``rgb`` (..., 3) with every pixel that has a negative channel desaturated towards the grey
    of its own luminance just enough that its lowest channel is 0; pixels of luminance <= 0 become
    0. Pixels without a negative channel are unchanged (float64 result)."""
    rgb = np.array(rgb, np.float64)  # a copy: only the pixels outside the gamut are rewritten
    negative = lowest_channel(rgb) < 0
    if not negative.any():
        return rgb
    outside = rgb[negative]  # (K, 3): usually a small part of the layer
    luminance = outside @ np.asarray(luminance_weights, np.float64)
    lowest = lowest_channel(outside)
    movable = luminance > 0  # then luminance - lowest > 0
    scale = np.where(movable, luminance / np.where(movable, luminance - lowest, 1.0), 1.0)
    mapped = luminance[:, None] + scale[:, None] * (outside - luminance[:, None])
    rgb[negative] = np.where(movable[:, None], np.maximum(mapped, 0.0), 0.0)
    return rgb


def gamut_clipped_fraction(rgb: np.ndarray) -> float:
    """The fraction of pixels of ``rgb`` (..., 3) with a negative channel (before clipping)."""
    rgb = np.asarray(rgb)
    return float(np.mean(lowest_channel(rgb) < 0)) if rgb.size else 0.0


def lowest_channel(rgb: np.ndarray) -> np.ndarray:
    """The smallest of the three channels of ``rgb`` (..., 3), per pixel. Two elementwise minima:
    NumPy's reduction along a trailing axis of length 3 is about ten times slower (a 720p render's
    layers spent 0.5 s in it)."""
    return np.minimum(np.minimum(rgb[..., 0], rgb[..., 1]), rgb[..., 2])
