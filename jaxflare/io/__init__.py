"""Input and output: lens files (jaxflare TOML, Zemax .zmx), images (EXR, PNG, TIFF, JPEG),
previews, cross-section plots, and atomic writes.

Readers turn files into the plain data of :mod:`jaxflare.optics` (a :class:`~jaxflare.optics.
LensPrescription`) or NumPy arrays; writers never leave a half-written file (a temporary file
beside the target is renamed over it). Builds on :mod:`jaxflare.optics` and :mod:`jaxflare.colour`.

- Lenses: :func:`load_lens` (a bundled name, a ``.toml`` or a ``.zmx`` file), :func:`read_prescription`,
  :func:`read_lens_toml` / :func:`lens_toml_text`, :func:`read_zmx` / :func:`write_zmx` / :func:`zmx_text`.
- Images: :func:`read_exr` / :func:`write_exr` (multi-layer, Nuke-style names),
  :func:`read_linear_image` (plates, masks, dirt maps), :func:`tone_map` / :func:`write_png`.
- Plots: :func:`plot_cross_section` / :func:`save_cross_section`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ._atomic import atomic_output_path, write_bytes_atomic, write_text_atomic
from ._lens_files import bundled_lens_names, load_lens, read_prescription
from ._lens_toml import lens_toml_text, parse_lens_toml, read_lens_toml
from ._zemax import decode_zmx_bytes, parse_zmx, read_zmx, write_zmx, zmx_text

# Images, previews and plots need OpenEXR, Pillow or matplotlib (and plots JAX): loaded on first
# use (PEP 562), so that reading and converting lens files imports none of them.
_LAZY = {
    "COMPRESSIONS": "_exr",
    "HALF_CLIPPED_ATTRIBUTE": "_exr",
    "HALF_MAX": "_exr",
    "read_exr": "_exr",
    "read_exr_channels": "_exr",
    "write_exr": "_exr",
    "EXR_EXTENSIONS": "_images",
    "IMAGE_FORMATS": "_images",
    "PILLOW_EXTENSIONS": "_images",
    "LinearImage": "_images",
    "read_linear_image": "_images",
    "plot_cross_section": "_plot",
    "save_cross_section": "_plot",
    "REC709_LUMINANCE": "_preview",
    "tone_map": "_preview",
    "write_png": "_preview",
}

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs
    from ._exr import COMPRESSIONS, HALF_CLIPPED_ATTRIBUTE, HALF_MAX, read_exr, read_exr_channels, write_exr
    from ._images import EXR_EXTENSIONS, IMAGE_FORMATS, PILLOW_EXTENSIONS, LinearImage, read_linear_image
    from ._plot import plot_cross_section, save_cross_section
    from ._preview import REC709_LUMINANCE, tone_map, write_png


def _module(name: str):
    if name == "_exr":
        from . import _exr as module
    elif name == "_images":
        from . import _images as module
    elif name == "_plot":
        from . import _plot as module
    else:
        from . import _preview as module
    return module


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


__all__ = [
    "COMPRESSIONS",
    "EXR_EXTENSIONS",
    "HALF_CLIPPED_ATTRIBUTE",
    "HALF_MAX",
    "IMAGE_FORMATS",
    "PILLOW_EXTENSIONS",
    "REC709_LUMINANCE",
    "LinearImage",
    "atomic_output_path",
    "bundled_lens_names",
    "decode_zmx_bytes",
    "lens_toml_text",
    "load_lens",
    "parse_lens_toml",
    "parse_zmx",
    "plot_cross_section",
    "read_exr",
    "read_exr_channels",
    "read_lens_toml",
    "read_linear_image",
    "read_prescription",
    "read_zmx",
    "save_cross_section",
    "tone_map",
    "write_bytes_atomic",
    "write_exr",
    "write_png",
    "write_text_atomic",
    "zmx_text",
]
