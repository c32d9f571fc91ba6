"""Tone-mapped 8-bit PNG previews of linear HDR renders.

A preview is for *looking* at a render (thumbnails, notebooks, reports); it is not for compositing.
It is display-referred, clipped, exposure-adjusted, rolled off and quantised to 8 bits, so it has
lost the scene-linear values. Composite from the EXR (:func:`jaxflare.io._exr.write_exr`) instead.

The pipeline of :func:`tone_map`, in order:

1. colour matrix: ``out = M @ rgb`` per pixel, ``M`` mapping the linear working space to linear
   sRGB / Rec.709 primaries (identity when not given);
2. negative values (out-of-gamut after the matrix, or ringing) are clipped to 0;
3. exposure: multiply by ``2 ** exposure_stops``, or, by default, by an automatic scale that maps
   the 99.9th percentile of the Rec.709 luminance of the *non-zero* pixels to 0.8 after the curve
   (flare renders are mostly black with a few very bright pixels, so percentiles over all pixels
   would be 0); an all-black image stays black;
4. highlight roll-off, per channel: ``x / (1 + x)`` (Reinhard). Per channel rather than on luminance
   so that nothing ever exceeds 1 and very bright, saturated cores desaturate towards white the way
   film and sensors do; it is smooth, monotonic and nearly linear for small ``x``;
5. the sRGB transfer function (``12.92 x`` below 0.0031308, else ``1.055 x^(1/2.4) - 0.055``);
6. rounding to 8 bits.
"""

from __future__ import annotations

import os

import numpy as np

from ..colour import srgb_encode
from .._atomic import atomic_output_path

__all__ = ["REC709_LUMINANCE", "tone_map", "write_png"]

REC709_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
_AUTO_PERCENTILE = 99.9
_AUTO_TARGET = 0.8  # value of the curve x / (1 + x) the percentile is mapped to
_AUTO_SCALED = _AUTO_TARGET / (1.0 - _AUTO_TARGET)  # the x with x / (1 + x) == _AUTO_TARGET


def _auto_scale(rgb: np.ndarray) -> float:
    luminance = rgb @ REC709_LUMINANCE
    lit = luminance[luminance > 0]
    if lit.size == 0:
        return 1.0
    reference = float(np.percentile(lit, _AUTO_PERCENTILE))
    return _AUTO_SCALED / reference


def tone_map(
    rgb: np.ndarray,
    *,
    to_srgb_matrix: np.ndarray | None = None,
    exposure_stops: float | None = None,
) -> np.ndarray:
    """Tone-map a linear ``(H, W, 3)`` image to an ``(H, W, 3)`` uint8 sRGB preview.

    ``to_srgb_matrix`` (3x3) takes the working space to linear sRGB primaries (``out = M @ rgb``);
    ``exposure_stops`` is an absolute exposure (scale ``2 ** exposure_stops``); ``None`` picks it
    automatically. See the module docstring for the steps. Raises ``ValueError`` for a wrong shape
    or non-finite input.
    """
    image = np.asarray(rgb)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"tone_map expects an (H, W, 3) array, got shape {image.shape}")
    if image.dtype.kind not in "fiu":
        raise ValueError(f"tone_map expects a real numeric array, got dtype {image.dtype}")
    image = image.astype(np.float64)
    non_finite = int(np.count_nonzero(~np.isfinite(image)))
    if non_finite:
        raise ValueError(f"tone_map input has {non_finite} non-finite (NaN or Inf) value(s)")
    if to_srgb_matrix is not None:
        matrix = np.asarray(to_srgb_matrix, dtype=np.float64)
        if matrix.shape != (3, 3) or not np.all(np.isfinite(matrix)):
            raise ValueError(f"to_srgb_matrix must be a finite 3x3 matrix, got shape {matrix.shape}")
        image = image @ matrix.T
    image = np.maximum(image, 0.0)

    if exposure_stops is None:
        scale = _auto_scale(image)
    else:
        stops = float(exposure_stops)
        if not np.isfinite(stops):
            raise ValueError(f"exposure_stops must be finite, got {exposure_stops!r}")
        with np.errstate(over="ignore"):
            scale = float(np.exp2(stops))

    with np.errstate(over="ignore", invalid="ignore"):
        # zeros stay zero even for an infinite scale (0 * inf would be NaN)
        exposed = np.where(image > 0.0, image * scale, 0.0)
        # x / (1 + x), with overflowed (infinite) values at the curve's limit 1
        rolled = np.where(np.isinf(exposed), 1.0, exposed / (1.0 + exposed))
    encoded = srgb_encode(rolled)  # clipped to [0, 1]
    return np.clip(np.round(encoded * 255.0), 0, 255).astype(np.uint8)


PNG_SOFTWARE = "jaxflare"
"""The PNG ``Software`` text of the previews :func:`write_png` writes (see :func:`is_jaxflare_png`)."""


def is_jaxflare_png(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a PNG preview written by :func:`write_png` (its ``Software`` text)."""
    try:
        from PIL import Image

        with Image.open(path) as image:
            return image.format == "PNG" and str(image.info.get("Software", "")).startswith(PNG_SOFTWARE)
    except (OSError, ValueError):
        return False


def write_png(path: str | os.PathLike, image_uint8: np.ndarray) -> None:
    """Write an ``(H, W, 3)`` uint8 image (e.g. from :func:`tone_map`) to ``path`` as PNG, atomically.

    matplotlib stores it as RGBA with an opaque alpha channel; the PNG's ``Software`` text is
    ``jaxflare`` (:func:`is_jaxflare_png`).
    """
    import matplotlib.image

    image = np.asarray(image_uint8)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"write_png expects an (H, W, 3) uint8 array, got shape {image.shape} and dtype {image.dtype}")
    with atomic_output_path(path) as temporary:
        matplotlib.image.imsave(temporary, np.ascontiguousarray(image), format="png", metadata={"Software": PNG_SOFTWARE})
