"""Reference images ("plates") for fitting a lens's coatings and dirt to a real flare.

What a plate is
---------------
A plate is the image a fit tries to reproduce: the flare of one light through the lens, as a
camera (or another renderer) recorded it, at exactly the scene's ``camera.resolution``. It is
held as a :class:`Plate`: ``rgb``, an ``(H, W, 3)`` float64 array of *linear* values, and
``weight``, an ``(H, W)`` float64 array saying how much each pixel counts in the fit.

Units
-----
The fit compares the plate with jaxflare's render pixel by pixel, so the plate must be in the same
units: the camera-equation radiance that :func:`jaxflare.render` writes (a synthetic plate saved
from a render with :func:`save_plate` is already in them). A photographic plate is in its own
exposure units: linearise it (a raw developed without a tone curve, or an EXR) and it differs from
the render by one overall factor, which the fit can absorb in the light's intensity parameter.
Anything that is not linear (a JPEG, an sRGB-encoded PNG) must be decoded first; for sRGB files
``load_plate(..., encoding="srgb")`` applies the inverse sRGB transfer function.

Files
-----
* OpenEXR (``.exr``, via :func:`jaxflare.io.read_linear_image`): any layer by name. With ``layer=None`` the
  default layer ``""`` is used, or the only layer if the file has just one; a file with several
  layers and no default one needs ``layer=``. RGB, RGBA (alpha dropped) or Y (grey, broadcast to
  RGB). Values are taken as they are (EXR is linear by convention).
* PNG and TIFF (``.png``, ``.tif``, ``.tiff``, via Pillow): 16-bit values are divided by 65535,
  8-bit ones by 255 (with a :class:`PlateQuantisationWarning`: 8 bits quantise a faint flare, often
  a few thousandths of the light's own image, to a handful of levels), single-channel float TIFFs
  are taken as they are. Grey images are broadcast to RGB, alpha is dropped. The values are treated
  as LINEAR unless ``encoding="srgb"``. (Pillow itself reads 16-bit-per-channel colour PNG and TIFF
  files as 8-bit; :func:`load_plate` recovers the low bytes, so all 16 bits are used.)

Masks and weights
-----------------
``mask`` (an image file, PNG/TIFF/EXR, or an array of the plate's ``(H, W)``) says which pixels the
fit uses: 1 = use the pixel, 0 = ignore it (e.g. where the plate shows picture content rather than
flare, a clipped light source, or a region with no flare), values in between weight the pixel
down. RGB masks are reduced to their Rec. 709 luminance; mask files are read as linear values
(no sRGB decoding) and must lie in ``[0, 1]``.

``noise_sigma`` (a scalar or an ``(H, W)`` array) is the per-pixel standard deviation of the
plate's noise, in the plate's units. The weight is ``mask / noise_sigma`` (``mask`` is 1 when not
given, ``noise_sigma`` 1 when not given), and the fit's residual is
``weight * (render - plate)``: with a noise model, residuals are in units of sigma.

Non-finite pixels (NaN, infinity) are an error, except under weight 0 (where the mask is 0): those
are allowed, and set to 0 in ``Plate.rgb``.
"""

from __future__ import annotations

import dataclasses
import os
import warnings

import numpy as np

from jaxflare.io import read_linear_image, write_exr

__all__ = ["PLATE_FORMATS", "Plate", "PlateQuantisationWarning", "load_plate", "save_plate"]

PLATE_FORMATS = "OpenEXR (.exr), 16-bit PNG (.png) or 16-bit TIFF (.tif, .tiff)"
"""The plate formats :func:`load_plate` reads, for messages (8-bit PNG/TIFF are read with a warning)."""

_PLATE_EXTENSIONS = (".exr", ".png", ".tif", ".tiff")
_MASK_FORMATS = "OpenEXR (.exr), PNG (.png) or TIFF (.tif, .tiff)"
_ENCODINGS = ("linear", "srgb")
_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 / sRGB primaries


class PlateQuantisationWarning(UserWarning):
    """An 8-bit plate: faint flare detail is quantised to steps of 1/255."""


@dataclasses.dataclass(frozen=True, eq=False)
class Plate:
    """A reference image for a fit.

    ``rgb``: ``(H, W, 3)`` float64 linear values, in the units jaxflare renders in (see the module
    docstring); finite everywhere. ``weight``: ``(H, W)`` float64, 0 where the pixel is masked out,
    else the per-pixel residual weight (1 by default, ``mask / noise_sigma`` in general); finite,
    non-negative and not all zero. ``source``: where the plate came from (a file path).
    ``layer``: the EXR layer read ("" for the default layer and for PNG/TIFF files).

    Both arrays are stored as read-only float64 copies.
    """

    rgb: np.ndarray
    weight: np.ndarray
    source: str = ""
    layer: str = ""

    def __post_init__(self) -> None:
        rgb = np.array(self.rgb, dtype=np.float64)
        weight = np.array(self.weight, dtype=np.float64)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] == 0 or rgb.shape[1] == 0:
            raise ValueError(f"Plate.rgb must have shape (H, W, 3), got {rgb.shape}")
        if weight.shape != rgb.shape[:2]:
            raise ValueError(f"Plate.weight must have shape (H, W) = {rgb.shape[:2]}, got {weight.shape}")
        if not np.all(np.isfinite(rgb)):
            raise ValueError("Plate.rgb has non-finite values")
        if not np.all(np.isfinite(weight)) or np.any(weight < 0):
            raise ValueError("Plate.weight must be finite and non-negative")
        if not np.any(weight > 0):
            raise ValueError("Plate.weight is zero everywhere: nothing to fit")
        rgb.setflags(write=False)
        weight.setflags(write=False)
        object.__setattr__(self, "rgb", rgb)
        object.__setattr__(self, "weight", weight)
        object.__setattr__(self, "source", str(self.source))
        object.__setattr__(self, "layer", str(self.layer))

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels, as in a scene's ``camera.resolution``."""
        return self.width, self.height


def _srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """The inverse sRGB transfer function (IEC 61966-2-1), extended to negative values by symmetry."""
    magnitude = np.abs(values)
    linear = np.where(magnitude <= 0.04045, magnitude / 12.92, ((magnitude + 0.055) / 1.055) ** 2.4)
    return np.sign(values) * linear


def _size_text(size: tuple[int, int]) -> str:
    return f"{size[0]} x {size[1]} (width x height)"


# --------------------------------------------------------------------------------------------------
# Masks and noise


def _mask_array(mask: str | os.PathLike | np.ndarray, shape: tuple[int, int], plate_path: str) -> np.ndarray:
    plate_size = (shape[1], shape[0])
    if isinstance(mask, (str, os.PathLike)):
        image = read_linear_image(mask, what="mask", extensions=_PLATE_EXTENSIONS, formats=_MASK_FORMATS)
        pixels, mask_path = image.pixels, image.path
        where = f"mask {mask_path!r}"
    else:
        pixels = np.asarray(mask)
        if pixels.dtype.kind not in "biuf":
            raise ValueError(f"mask: expected a numeric or boolean array, got dtype {pixels.dtype}")
        pixels = pixels.astype(np.float64)
        if pixels.ndim == 2:
            pixels = pixels[..., None]
        if pixels.ndim != 3 or pixels.shape[-1] not in (1, 3):
            raise ValueError(f"mask array must have shape (H, W), (H, W, 1) or (H, W, 3), got {pixels.shape}")
        where = "mask array"
    mask_size = (pixels.shape[1], pixels.shape[0])
    if mask_size != plate_size:
        raise ValueError(
            f"{where} is {_size_text(mask_size)} but plate {plate_path!r} is {_size_text(plate_size)}; "
            "the mask must match the plate"
        )
    if not np.all(np.isfinite(pixels)):
        count = int(np.size(pixels) - np.count_nonzero(np.isfinite(pixels)))
        raise ValueError(f"{where} has {count} non-finite (NaN or infinite) value(s)")
    values = pixels[..., 0] if pixels.shape[-1] == 1 else pixels @ _LUMINANCE
    low, high = float(values.min()), float(values.max())
    if low < -1e-9 or high > 1 + 1e-9:
        raise ValueError(f"{where}: values span [{low:.6g}, {high:.6g}], outside [0, 1] (1 = use the pixel, 0 = ignore it)")
    values = np.clip(values, 0.0, 1.0)
    if not np.any(values > 0):
        raise ValueError(f"empty mask: nothing to fit ({where} is 0 everywhere)")
    return values


def _sigma_array(noise_sigma: float | np.ndarray, shape: tuple[int, int], mask: np.ndarray) -> np.ndarray:
    sigma = np.asarray(noise_sigma, dtype=np.float64)
    if sigma.ndim == 0:
        sigma = np.full(shape, float(sigma))
    elif sigma.shape != shape:
        raise ValueError(f"noise_sigma must be a scalar or an (H, W) = {shape} array matching the plate, got shape {sigma.shape}")
    used = mask > 0
    bad = used & ~(np.isfinite(sigma) & (sigma > 0))
    if np.any(bad):
        raise ValueError(
            f"noise_sigma must be finite and > 0 wherever the mask is non-zero; it is not at {int(np.count_nonzero(bad))} pixel(s)"
        )
    return sigma


# --------------------------------------------------------------------------------------------------
# Public API


def load_plate(
    path: str | os.PathLike,
    *,
    layer: str | None = None,
    mask: str | os.PathLike | np.ndarray | None = None,
    expected_size: tuple[int, int] | None = None,
    noise_sigma: float | np.ndarray | None = None,
    encoding: str = "linear",
) -> Plate:
    """Read a plate (a reference flare image) for a fit; see the module docstring.

    ``layer``: the EXR layer (``None``: the default layer "", else the only layer). ``mask``: an
    image file or an ``(H, W)`` (or ``(H, W, 1|3)``) array in ``[0, 1]``, 1 = use the pixel.
    ``expected_size``: ``(width, height)``, the scene's ``camera.resolution``; a plate of another
    size is an error. ``noise_sigma``: per-pixel noise standard deviation (scalar or ``(H, W)``);
    the weight becomes ``mask / noise_sigma``. ``encoding``: ``"linear"`` (values used as read) or
    ``"srgb"`` (the inverse sRGB transfer function is applied to the plate, not to the mask).

    Raises ``FileNotFoundError`` for a missing plate or mask file, and ``ValueError`` for an
    unreadable or unsupported file, a missing or ambiguous layer, a size mismatch, non-finite pixels
    where the weight is not 0, a bad or empty mask, or a non-positive ``noise_sigma``. An 8-bit
    PNG/TIFF plate gives a :class:`PlateQuantisationWarning`.
    """
    if encoding not in _ENCODINGS:
        raise ValueError(f"encoding must be one of {_ENCODINGS}, got {encoding!r}")
    if expected_size is not None:
        if (
            isinstance(expected_size, (str, bytes))
            or len(expected_size) != 2
            or not all(isinstance(v, (int, np.integer)) and v > 0 for v in expected_size)
        ):
            raise ValueError(f"expected_size must be (width, height) in pixels, got {expected_size!r}")
        expected_size = (int(expected_size[0]), int(expected_size[1]))

    image = read_linear_image(path, what="plate", layer=layer, extensions=_PLATE_EXTENSIONS, formats=PLATE_FORMATS)
    pixels, path, layer = image.pixels, image.path, image.layer
    if image.bits == 8:
        warnings.warn(
            f"plate {path!r} is an 8-bit image: faint flares (ghosts are often a few thousandths of the light's own "
            "image) are quantised to steps of 1/255; prefer a 16-bit PNG/TIFF or an EXR",
            PlateQuantisationWarning,
            stacklevel=2,
        )
    height, width = pixels.shape[:2]
    if expected_size is not None and (width, height) != expected_size:
        raise ValueError(
            f"plate {path!r} is {_size_text((width, height))} but the scene renders {_size_text(expected_size)}; "
            "the plate must match the scene's camera.resolution"
        )
    rgb = np.broadcast_to(pixels, (height, width, 3)).astype(np.float64)

    weight = np.ones((height, width)) if mask is None else _mask_array(mask, (height, width), path)
    finite = np.all(np.isfinite(rgb), axis=-1)
    bad = ~finite & (weight > 0)
    if np.any(bad):
        count = int(np.count_nonzero(bad))
        if mask is None:
            raise ValueError(
                f"plate {path!r} has {count} pixel(s) with non-finite (NaN or infinite) values; "
                "fix the file or mask them out (mask 0 there)"
            )
        raise ValueError(
            f"plate {path!r} has {count} pixel(s) with non-finite (NaN or infinite) values where the mask is non-zero; "
            "set the mask to 0 there"
        )
    rgb[~finite] = 0.0
    if encoding == "srgb":
        rgb = _srgb_to_linear(rgb)
    if noise_sigma is not None:
        sigma = _sigma_array(noise_sigma, (height, width), weight)
        used = weight > 0
        weight = np.where(used, weight / np.where(used, sigma, 1.0), 0.0)
    return Plate(rgb=rgb, weight=weight, source=path, layer=layer)


NEGATIVE_PIXEL_LIMIT = 0.5
"""A pixel under the mask more negative than this fraction of the plate's peak is not noise."""


def check_fittable(plate: Plate) -> None:
    """Refuse a plate no flare can match: black or negative everywhere its weight is non-zero, a
    negative total of light there, or a pixel far more negative than noise (a flare only adds
    light: a plate with a subtracted background or a sign error). Small negative values, such as
    a noisy dark background gives, are kept."""
    used = plate.weight > 0
    values = plate.rgb[used]
    where = f"plate {plate.source}" + (f" (layer {plate.layer!r})" if plate.layer else "")
    peak = float(values.max()) if values.size else 0.0
    if not peak > 0:
        raise ValueError(
            f"{where}: no light where its weight is non-zero (it is black{' or negative' if values.size and values.min() < 0 else ''} "
            "under the mask): there is no flare to fit; check the layer, the exposure or the mask"
        )
    total = values.sum(axis=0)
    if np.any(total <= 0):
        channel = "RGB"[int(np.argmin(total))]
        raise ValueError(
            f"{where}: the {channel} channel sums to {float(total.min()):.6g} under the mask; a flare only adds light, "
            "so a plate's light cannot be negative (was a background subtracted from it?)"
        )
    lowest = plate.rgb.min(axis=-1)
    worst = np.unravel_index(int(np.argmin(np.where(used, lowest, np.inf))), lowest.shape)
    if lowest[worst] < -NEGATIVE_PIXEL_LIMIT * peak:
        raise ValueError(
            f"{where}: pixel (x={worst[1]}, y={worst[0]}) is {float(lowest[worst]):.6g}, below -{NEGATIVE_PIXEL_LIMIT} x the plate's peak "
            f"{peak:.6g}; a flare only adds light and noise is not that negative: fix the plate or mask that pixel out"
        )


def save_plate(path: str | os.PathLike, rgb: np.ndarray, *, layer: str = "", pixel_type: str = "float") -> None:
    """Write ``rgb`` (``(H, W, 3)``, or ``(H, W)`` / ``(H, W, 1)`` grey, saved as a Y layer) to an
    EXR plate at ``path`` (float32 by default; ``pixel_type="half"`` for float16), in ``layer``
    ("" = the default layer). Values must be finite. For tests and synthetic plates; read it back
    with :func:`load_plate`."""
    array = np.asarray(rgb)
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3 or array.shape[-1] not in (1, 3):
        raise ValueError(f"save_plate expects an (H, W, 3) or (H, W) array, got shape {array.shape}")
    write_exr(path, {layer: array}, pixel_type=pixel_type)
