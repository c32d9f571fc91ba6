"""Reading images as linear pixel values: one reader for plates, masks and dirt maps.

PNG, TIFF and JPEG through Pillow (8- and 16-bit integers divided by 255 and 65535, float TIFFs as
stored; 16-bit colour PNG/TIFF read in full, which Pillow alone narrows to 8 bits), and OpenEXR
through :func:`jaxflare.io.read_exr` (any layer by name). Grey images have one channel, colour
three; alpha is dropped. Values are returned as read: no transfer function is undone.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from ._exr import read_exr

PILLOW_EXTENSIONS = (".png", ".tif", ".tiff", ".jpg", ".jpeg")
EXR_EXTENSIONS = (".exr",)
IMAGE_FORMATS = "OpenEXR (.exr), PNG (.png), TIFF (.tif, .tiff) or JPEG (.jpg, .jpeg)"
# Pillow modes read as they are (after dropping alpha); any other mode is converted to RGB first.
_DIRECT_MODES = {"L", "LA", "RGB", "RGBA", "I", "I;16", "I;16B", "I;16L", "I;16N", "F"}


@dataclasses.dataclass(frozen=True)
class LinearImage:
    """An image as read: ``pixels`` (H, W, C) float64 with C in {1, 3}, the file, the EXR layer
    ("" for the default layer and non-EXR files), and the bit depth of an integer image (None for
    float images)."""

    pixels: np.ndarray
    path: str
    layer: str
    bits: int | None


def _format_error(what: str, path: str, reason: str, formats: str) -> ValueError:
    return ValueError(f"cannot read {what} {path!r}: {reason}; {what}s must be {formats}")


def _rawmode(tile_args: object) -> str | None:
    if isinstance(tile_args, str):
        return tile_args
    if isinstance(tile_args, tuple) and tile_args and isinstance(tile_args[0], str):
        return tile_args[0]
    return None


def _swap_endianness(tile_args: object) -> object:
    def swap(rawmode: str) -> str:
        return rawmode.replace(";16B", ";16#").replace(";16L", ";16B").replace(";16#", ";16L")

    if isinstance(tile_args, str):
        return swap(tile_args)
    return (swap(tile_args[0]), *tile_args[1:])  # type: ignore[index]


def _is_16bit_colour(image: object) -> bool:
    """Whether Pillow would narrow this image's 16-bit channels to 8 bits (colour PNG/TIFF)."""
    if image.mode not in ("RGB", "RGBA", "LA", "L"):  # type: ignore[attr-defined]
        return False
    rawmodes = [_rawmode(tile.args) for tile in image.tile]  # type: ignore[attr-defined]
    return any(rawmode is not None and ";16" in rawmode for rawmode in rawmodes)


def _read_16bit_colour(path: str) -> np.ndarray:
    """Read a 16-bit-per-channel colour PNG/TIFF in full. Pillow unpacks such files to 8 bits (the
    high byte of each value); decoding the same data a second time with the byte order swapped
    yields the low bytes, and the two make up the 16-bit values."""
    from PIL import Image

    halves = []
    for swapped in (False, True):
        with Image.open(path) as image:
            if swapped:
                image.tile = [tile._replace(args=_swap_endianness(tile.args)) for tile in image.tile]
            image.load()
            halves.append(np.asarray(image).astype(np.uint16))
    return (halves[0] << 8) | halves[1]


def _read_pillow(path: str, what: str, formats: str) -> tuple[np.ndarray, int | None]:
    """Pixels as (H, W, C) float64 in [0, 1] (or as stored for float images), alpha dropped, and the
    bit depth of an integer image (None for float images)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            sixteen_bit_colour = _is_16bit_colour(image)
            if not sixteen_bit_colour:
                image.load()
                if image.mode == "1":
                    image = image.convert("L")
                elif image.mode in ("P", "PA"):
                    image = image.convert("RGBA")
                elif image.mode not in _DIRECT_MODES:  # CMYK, YCbCr, LAB, RGBX, ...
                    image = image.convert("RGB")
                mode = image.mode
                pixels = np.asarray(image)
            else:
                mode = image.mode
        if sixteen_bit_colour:
            try:
                pixels = _read_16bit_colour(path)
            except (OSError, ValueError, KeyError, SyntaxError) as error:
                raise ValueError(
                    f"cannot read the 16-bit {mode} {what} {path!r} in full ({type(error).__name__}: {error}); "
                    "save it as an OpenEXR file instead"
                ) from None
    except (UnidentifiedImageError, OSError, SyntaxError) as error:
        raise _format_error(what, path, formats=formats, reason=f"not a readable image ({type(error).__name__}: {error})") from None
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if pixels.ndim != 3:
        raise _format_error(what, path, f"unexpected pixel array shape {pixels.shape} (mode {mode!r})", formats)
    if mode in ("LA", "RGBA"):
        pixels = pixels[..., :-1]
    if pixels.dtype == np.uint8:
        return pixels.astype(np.float64) / 255.0, 8
    if pixels.dtype.kind == "u" and pixels.dtype.itemsize == 2:
        return pixels.astype(np.float64) / 65535.0, 16
    if pixels.dtype.kind == "i":  # mode "I": Pillow's 32-bit container
        low, high = int(pixels.min()), int(pixels.max())
        if low < 0 or high > 65535:
            raise ValueError(
                f"{what} {path!r}: integer values span [{low}, {high}], beyond 16 bits; save it as a 16-bit image or an EXR"
            )
        return pixels.astype(np.float64) / 65535.0, 16
    if pixels.dtype.kind == "f":
        return pixels.astype(np.float64), None
    raise _format_error(what, path, f"unsupported pixel type {pixels.dtype} (mode {mode!r})", formats)


def _read_exr_layer(path: str, layer: str | None, what: str, formats: str) -> tuple[np.ndarray, str]:
    try:
        layers, _ = read_exr(path)
    except ValueError as error:
        raise _format_error(what, path, str(error), formats) from None
    listing = ", ".join(repr(name) for name in layers)
    if layer is None:
        if "" in layers:
            layer = ""
        elif len(layers) == 1:
            layer = next(iter(layers))
        else:
            raise ValueError(f"{what} {path!r} has several layers and no default one: {listing}; choose one with layer=...")
    elif layer not in layers:
        raise ValueError(f"{what} {path!r} has no layer {layer!r}; its layers are: {listing}")
    pixels = layers[layer]
    if pixels.shape[-1] == 4:
        pixels = pixels[..., :3]
    return pixels.astype(np.float64), layer


def read_linear_image(
    path: str | os.PathLike, *, what: str = "image", layer: str | None = None, extensions: tuple[str, ...] | None = None,
    formats: str = IMAGE_FORMATS,
) -> LinearImage:
    """Read an image file as linear values (see the module docstring).

    ``what`` names the file in messages ("plate", "dirt map", ...); ``layer`` picks an EXR layer
    (None: the default layer, else the only one); ``extensions`` limits the accepted file types
    (default: all), ``formats`` describes them in messages. Raises ``FileNotFoundError`` for a
    missing file and ``ValueError`` for an unsupported or unreadable one, a missing or ambiguous
    layer, or more than 3 colour channels.
    """
    extensions = tuple(PILLOW_EXTENSIONS + EXR_EXTENSIONS) if extensions is None else extensions
    path = os.fspath(path)
    if not os.path.isfile(path):
        if os.path.isdir(path):
            raise ValueError(f"{what} {path!r} is a directory, not an image file")
        if os.path.exists(path):
            raise ValueError(f"{what} {path!r} is not a regular file (a device, pipe or socket), so it is not read as an image")
        raise FileNotFoundError(f"no such {what} file: {path!r}")
    extension = os.path.splitext(path)[1].lower()
    if extension in extensions and extension in EXR_EXTENSIONS:
        pixels, layer = _read_exr_layer(path, layer, what, formats)
        return LinearImage(pixels, path, layer, None)
    if extension in extensions and extension in PILLOW_EXTENSIONS:
        if layer not in (None, ""):
            raise ValueError(f"{what} {path!r}: layer={layer!r} given, but only EXR files have layers")
        pixels, bits = _read_pillow(path, what, formats)
        if pixels.shape[-1] not in (1, 3):
            raise ValueError(f"{what} {path!r} has {pixels.shape[-1]} channels; expected 1 (grey) or 3 (RGB)")
        return LinearImage(pixels, path, "", bits)
    raise _format_error(what, path, f"unsupported extension {extension or '(none)'!r}", formats)
