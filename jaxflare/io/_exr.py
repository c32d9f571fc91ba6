"""Multi-layer OpenEXR files for compositors.

Layer layout
------------
An image is written as a single-part scanline EXR holding one or more *layers*, each an
``(H, W, C)`` array with ``C`` in {1, 3, 4}; all layers share ``H`` and ``W``. Channel names follow
the standard OpenEXR multi-layer convention that Nuke (and most compositors) split into layers:

* the default layer ``""`` is stored as ``R, G, B`` (+ ``A`` when ``C == 4``), or ``Y`` when ``C == 1``;
* any other layer ``name`` is stored as ``name.R, name.G, name.B`` (+ ``name.A``), or ``name.Y``.

Layer names may contain only letters, digits, ``_`` and ``-`` (a ``.`` would be taken for a further
level of nesting). The file itself keeps no layer order (OpenEXR sorts channels by name), so
:func:`read_exr` returns the default layer first and the others sorted by name.

Pixel types
-----------
``pixel_type="half"`` (float16, the compositing norm: half the size, ~3 significant digits, range
±65504) or ``"float"`` (float32). No NaN or infinity is ever written: a non-finite input value is a
``ValueError``. ``layer_pixel_types`` stores chosen layers otherwise (e.g. a float32 variance
layer in a half file: small values that float16 would flush to zero). For half, finite values beyond ±65504 (which float16 would turn into infinities) are
clipped to ±65504 and the number of clipped values is recorded in the integer header attribute
``jaxflare/half_clipped_values`` (written, possibly 0, on every half file). For float, values beyond
the float32 range are a ``ValueError``.

Header attributes
-----------------
Extra attributes are stored under the keys as given (e.g. ``"jaxflare/lens"``): ``str`` as string
attributes, ``int`` (and ``bool``, as 0/1) as 32-bit int attributes (values outside the int32 range
are a ``ValueError`` rather than silently wrapped), ``float`` as OpenEXR *float* attributes, i.e.
32-bit (about 7 significant digits; pass a string or put it in a dict for full precision), and
``dict``/``list``/``tuple`` values as JSON-encoded strings. :func:`read_exr` returns strings as
strings; JSON is not decoded automatically (``json.loads`` the attributes you know are JSON).

Colour
------
``chromaticities`` (the CIE xy of the red, green and blue primaries and the white point, eight
numbers) is written as OpenEXR's standard ``chromaticities`` attribute, which compositors
(Nuke, OpenImageIO, ...) read to know the pixels' colour space; ``white_luminance`` (cd/m^2 of
RGB 1, 1, 1) as ``whiteLuminance``, only when the pixels are in photometric units.

Why contiguous
--------------
The OpenEXR Python bindings (``OpenEXR.File``) read a numpy array's buffer as if it were C-contiguous
without checking, so a strided view such as ``image[..., 0]`` or a transposed array is written
scrambled, without any error. Every channel is therefore passed as a fresh
``np.ascontiguousarray(channel, dtype)``.

Files are written atomically (a temporary file beside the target, renamed over it on success), so an
error part-way never leaves a half-written or damaged target.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Mapping

import numpy as np
import OpenEXR

from .._atomic import atomic_output_path

__all__ = ["COMPRESSIONS", "HALF_CLIPPED_ATTRIBUTE", "HALF_MAX", "read_exr", "write_exr"]

HALF_MAX = 65504.0
HALF_CLIPPED_ATTRIBUTE = "jaxflare/half_clipped_values"

COMPRESSIONS: dict[str, OpenEXR.Compression] = {
    "none": OpenEXR.NO_COMPRESSION,
    "rle": OpenEXR.RLE_COMPRESSION,
    "zips": OpenEXR.ZIPS_COMPRESSION,
    "zip": OpenEXR.ZIP_COMPRESSION,
    "piz": OpenEXR.PIZ_COMPRESSION,
    "pxr24": OpenEXR.PXR24_COMPRESSION,
    "b44": OpenEXR.B44_COMPRESSION,
    "b44a": OpenEXR.B44A_COMPRESSION,
    "dwaa": OpenEXR.DWAA_COMPRESSION,
    "dwab": OpenEXR.DWAB_COMPRESSION,
}
_COMPRESSION_NAMES = {value: name for name, value in COMPRESSIONS.items()}

_PIXEL_TYPES = {"half": np.float16, "float": np.float32}
_CHANNELS_BY_COUNT = {1: ("Y",), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}
_LAYER_NAME = re.compile(r"[A-Za-z0-9_-]+")
_EXR_MAGIC = b"\x76\x2f\x31\x01"
_INT32 = (-(2**31), 2**31 - 1)
_FLOAT32_MAX = float(np.finfo(np.float32).max)
# Attributes OpenEXR manages itself (or that describe the layout): never taken from `header`.
_RESERVED_ATTRIBUTES = frozenset(
    {
        "channels",
        "compression",
        "dataWindow",
        "displayWindow",
        "lineOrder",
        "pixelAspectRatio",
        "screenWindowCenter",
        "screenWindowWidth",
        "type",
        "tiles",
        "name",
        "version",
        "chunkCount",
        "maxSamplesPerPixel",
        "chromaticities",
        "whiteLuminance",
        HALF_CLIPPED_ATTRIBUTE,
    }
)


def _channel_names(layer: str, count: int) -> tuple[str, ...]:
    prefix = f"{layer}." if layer else ""
    return tuple(prefix + suffix for suffix in _CHANNELS_BY_COUNT[count])


def _header_value(key: str, value: object) -> object:
    if isinstance(value, str):
        return value
    if isinstance(value, (bool, np.bool_)):
        return int(value)
    if isinstance(value, (int, np.integer)):
        if not _INT32[0] <= int(value) <= _INT32[1]:
            raise ValueError(
                f"header attribute {key!r}: int {value} is outside the 32-bit range of an EXR int attribute; pass it as a str"
            )
        return int(value)
    if isinstance(value, (float, np.floating)):
        if not np.isfinite(value):
            raise ValueError(f"header attribute {key!r} is not finite: {value}")
        return float(value)
    if isinstance(value, (dict, list, tuple)):
        try:
            return json.dumps(value, allow_nan=False, sort_keys=isinstance(value, dict))
        except (TypeError, ValueError) as error:
            raise ValueError(f"header attribute {key!r} cannot be JSON-encoded: {error}") from None
    raise TypeError(f"header attribute {key!r}: unsupported type {type(value).__name__} (use str, int, float, dict or list)")


def _prepare_header(header: Mapping[str, object] | None) -> dict[str, object]:
    prepared: dict[str, object] = {}
    for key, value in (header or {}).items():
        if not isinstance(key, str) or not key:
            raise ValueError(f"header attribute names must be non-empty strings, got {key!r}")
        if key in _RESERVED_ATTRIBUTES:
            raise ValueError(f"header attribute {key!r} is reserved (set by write_exr or OpenEXR)")
        prepared[key] = _header_value(key, value)
    return prepared


def _prepare_layers(
    layers: Mapping[str, np.ndarray], pixel_type: str, layer_pixel_types: Mapping[str, str] | None = None
) -> tuple[dict[str, np.ndarray], int]:
    """Validate the layers and return {channel name: contiguous 2-D array} and the half-clip count."""
    if not layers:
        raise ValueError("write_exr needs at least one layer")
    overrides: dict[str, str] = {}
    for name, kind in (layer_pixel_types or {}).items():
        if name not in layers:
            raise ValueError(f"layer_pixel_types names layer {name!r}, which is not among the layers {sorted(layers)}")
        if not isinstance(kind, str) or kind.lower() not in _PIXEL_TYPES:
            raise ValueError(f"layer_pixel_types[{name!r}] must be one of {sorted(_PIXEL_TYPES)}, got {kind!r}")
        overrides[name] = kind.lower()
    channels: dict[str, np.ndarray] = {}
    clipped_total = 0
    reference: tuple[str, tuple[int, int]] | None = None
    for name, image in layers.items():
        layer_type = overrides.get(name, pixel_type)
        dtype = _PIXEL_TYPES[layer_type]
        if not isinstance(name, str) or (name and not _LAYER_NAME.fullmatch(name)):
            raise ValueError(f"invalid layer name {name!r}: use letters, digits, '_' and '-' only ('' is the default layer)")
        array = np.asarray(image)
        if array.dtype.kind not in "fiu":
            raise ValueError(f"layer {name!r}: expected a real numeric array, got dtype {array.dtype}")
        if array.ndim != 3 or array.shape[2] not in _CHANNELS_BY_COUNT:
            raise ValueError(f"layer {name!r}: expected shape (H, W, C) with C in {{1, 3, 4}}, got {array.shape}")
        if array.shape[0] == 0 or array.shape[1] == 0:
            raise ValueError(f"layer {name!r}: empty image of shape {array.shape}")
        if reference is None:
            reference = (name, array.shape[:2])
        elif array.shape[:2] != reference[1]:
            raise ValueError(
                f"layer {name!r} has shape {array.shape} (H, W = {array.shape[:2]}) but layer {reference[0]!r} "
                f"has H, W = {reference[1]}; all layers must share H and W"
            )
        if array.dtype.kind in "iu":
            array = array.astype(np.float64)
        non_finite = int(np.count_nonzero(~np.isfinite(array)))
        if non_finite:
            raise ValueError(f"layer {name!r} has {non_finite} non-finite (NaN or Inf) value(s); EXR output must be finite")
        if layer_type == "half":
            too_big = np.abs(array) > HALF_MAX
            clipped = int(np.count_nonzero(too_big))
            if clipped:
                array = np.clip(array, -HALF_MAX, HALF_MAX)
                clipped_total += clipped
        elif array.dtype.itemsize > 4:
            overflow = int(np.count_nonzero(np.abs(array) > _FLOAT32_MAX))
            if overflow:
                raise ValueError(f"layer {name!r} has {overflow} value(s) beyond the float32 range (±{_FLOAT32_MAX:.4g})")
        for index, channel_name in enumerate(_channel_names(name, array.shape[2])):
            # Contiguous copy per channel: the bindings mis-write strided views silently.
            channels[channel_name] = np.ascontiguousarray(array[..., index], dtype=dtype)
    return channels, clipped_total


def write_exr(
    path: str | os.PathLike,
    layers: Mapping[str, np.ndarray],
    *,
    pixel_type: str = "half",
    compression: str = "zip",
    header: Mapping[str, object] | None = None,
    layer_pixel_types: Mapping[str, str] | None = None,
    chromaticities: tuple[float, ...] | None = None,
    white_luminance: float | None = None,
) -> None:
    """Write ``layers`` ({name: (H, W, C) array}) to a single-part scanline EXR at ``path``, atomically.

    See the module docstring for the channel naming, pixel types (``layer_pixel_types``: {layer:
    "half" or "float"} for layers stored unlike ``pixel_type``), header attribute encoding and
    the colour attributes (``chromaticities``: 8 numbers, red/green/blue/white x and y;
    ``white_luminance``). Everything is validated before anything touches the disk; an error
    while writing leaves an existing ``path`` untouched.
    """
    if not isinstance(pixel_type, str) or pixel_type.lower() not in _PIXEL_TYPES:
        raise ValueError(f"pixel_type must be one of {sorted(_PIXEL_TYPES)}, got {pixel_type!r}")
    pixel_type = pixel_type.lower()
    if not isinstance(compression, str) or compression.lower() not in COMPRESSIONS:
        raise ValueError(f"compression must be one of {', '.join(COMPRESSIONS)} (case-insensitive), got {compression!r}")
    attributes = _prepare_header(header)
    if chromaticities is not None:
        values = tuple(float(v) for v in chromaticities)
        if len(values) != 8 or not all(np.isfinite(v) and -1.0 < v < 2.0 for v in values):
            raise ValueError(f"chromaticities must be 8 finite CIE xy values (red, green, blue, white), got {chromaticities!r}")
        attributes["chromaticities"] = values
    if white_luminance is not None:
        if not (np.isfinite(white_luminance) and white_luminance > 0):
            raise ValueError(f"white_luminance must be a positive number (cd/m^2), got {white_luminance!r}")
        attributes["whiteLuminance"] = float(white_luminance)
    channels, clipped = _prepare_layers(layers, pixel_type, layer_pixel_types)
    if pixel_type == "half" or "half" in (layer_pixel_types or {}).values():
        attributes[HALF_CLIPPED_ATTRIBUTE] = clipped
    attributes["compression"] = COMPRESSIONS[compression.lower()]
    attributes["type"] = OpenEXR.scanlineimage
    with atomic_output_path(path) as temporary:
        OpenEXR.File(attributes, channels).write(temporary)


def _layer_and_suffix(channel_name: str) -> tuple[str, str]:
    layer, _, suffix = channel_name.rpartition(".")
    return layer, suffix


def read_exr_channels(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    """The float channels of a single-part EXR by their full names (e.g. ``"R"``, ``"ghost.G"``),
    and its header (``compression`` as its lower-case name). Raises ``FileNotFoundError`` for a
    missing file and ``ValueError`` for a file that is not a readable single-part EXR, or has
    subsampled or non-float channels."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"no such EXR file: {path!r}")
    if not os.path.isfile(path):
        raise ValueError(f"{path!r} is not an OpenEXR file (a directory, device, pipe or socket)")
    with open(path, "rb") as handle:
        magic = handle.read(4)
    if magic != _EXR_MAGIC:
        raise ValueError(f"{path!r} is not an OpenEXR file")
    try:
        exr = OpenEXR.File(path, separate_channels=True)
    except RuntimeError as error:  # what the bindings raise for a damaged file
        raise ValueError(f"cannot read OpenEXR file {path!r}: {error}") from None
    if not exr.parts:  # the bindings drop a part whose pixel data cannot be read (e.g. truncated)
        raise ValueError(f"cannot read the pixel data of OpenEXR file {path!r} (damaged or truncated?)")
    if len(exr.parts) != 1:
        raise ValueError(f"{path!r} has {len(exr.parts)} parts; read_exr reads single-part files only")
    channels: dict[str, np.ndarray] = {}
    for channel_name, channel in exr.channels().items():
        if channel.xSampling != 1 or channel.ySampling != 1:
            raise ValueError(f"{path!r}: channel {channel_name!r} is subsampled; not supported")
        pixels = channel.pixels
        if pixels.dtype.kind != "f":
            raise ValueError(f"{path!r}: channel {channel_name!r} has non-float pixels ({pixels.dtype})")
        channels[channel_name] = pixels
    attributes: dict[str, object] = {}
    for key, value in exr.header().items():
        if key == "channels":
            continue
        if key == "compression":
            value = _COMPRESSION_NAMES.get(value, str(value))
        attributes[key] = value
    return channels, attributes


def read_exr(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    """Read an EXR written by :func:`write_exr` (or any single-part scanline/tiled EXR laid out the same way).

    Returns ``(layers, header)``: ``layers`` maps a layer name ("" for the unprefixed channels) to a
    float32 ``(H, W, C)`` array with channels ordered R, G, B[, A] (or Y alone), default layer first,
    the others sorted by name; ``header`` holds the file's attributes except ``channels``, with
    ``compression`` as its lower-case name (e.g. ``"zip"``) and custom attributes as stored (str,
    int, float). Raises ``FileNotFoundError`` for a missing file and ``ValueError`` for a file that
    is not an EXR or whose channels do not form R,G,B[,A] / Y layers.
    """
    channels, attributes = read_exr_channels(path)
    grouped: dict[str, dict[str, np.ndarray]] = {}
    for channel_name, pixels in channels.items():
        layer, suffix = _layer_and_suffix(channel_name)
        grouped.setdefault(layer, {})[suffix] = pixels
    layers: dict[str, np.ndarray] = {}
    for layer in sorted(grouped, key=lambda name: (name != "", name)):
        by_suffix = grouped[layer]
        order = next((names for names in _CHANNELS_BY_COUNT.values() if set(names) == set(by_suffix)), None)
        if order is None:
            raise ValueError(f"{os.fspath(path)!r}: layer {layer!r} has channels {sorted(by_suffix)}; expected R,G,B, R,G,B,A or Y")
        layers[layer] = np.stack([np.asarray(by_suffix[suffix], dtype=np.float32) for suffix in order], axis=-1)
    return layers, attributes
