"""Input and output: lens files (jaxflare TOML, Zemax .zmx), images (EXR, PNG, TIFF, JPEG),
previews, cross-section plots, and atomic writes (one file, or files that belong together:
:func:`atomic_output_group`).

Readers turn files into the plain data of :mod:`jaxflare.optics` (a :class:`~jaxflare.optics.
LensPrescription`) or NumPy arrays; writers never leave a half-written file (a temporary file
beside the target is renamed over it). Builds on :mod:`jaxflare.optics` and :mod:`jaxflare.colour`.

- Lenses: :func:`load_lens` (a bundled name, a ``.toml`` or a ``.zmx`` file, or another flare
  tool's lens file: flaresim ``.lens``, realflare/lentil ``.json``, OpenLensFlare ``.xml``, pbrt
  ``.dat``), :func:`read_prescription` (``semi_aperture=`` :data:`SEMI_APERTURE_MODES`,
  ``glass_aliases=``), :func:`read_lens_toml` / :func:`lens_toml_text`, :func:`read_zmx` /
  :func:`write_zmx` / :func:`zmx_text`, the importers ``read_flaresim_lens`` ... ``read_pbrt_dat``.
- Input files: :func:`read_input_bytes` / :func:`read_text_file` (regular files of at most
  :data:`MAX_INPUT_BYTES`, decoded with errors naming the line).
- Images: :func:`read_exr` / :func:`write_exr` (multi-layer, Nuke-style names),
  :func:`read_linear_image` (plates, masks, dirt maps), :func:`tone_map` / :func:`write_png`.
- Plots: :func:`plot_cross_section` / :func:`save_cross_section`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .._atomic import atomic_output_group, atomic_output_path, write_bytes_atomic, write_text_atomic
from ._lens_files import (
    SEMI_APERTURE_MODES,
    apply_glass_aliases,
    apply_semi_aperture_mode,
    bundled_lens_names,
    load_lens,
    read_prescription,
)
from ._lens_formats import (
    LENS_FORMATS,
    read_flaresim_lens,
    read_json_lens,
    read_lentil_json,
    read_openlensflare_xml,
    read_pbrt_dat,
    read_realflare_json,
)
from ._lens_toml import lens_toml_text, parse_lens_toml, read_lens_toml
from ._text_input import MAX_INPUT_BYTES, decode_text, read_input_bytes, read_text_file
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
    "PNG_SOFTWARE": "_preview",
    "REC709_LUMINANCE": "_preview",
    "is_jaxflare_png": "_preview",
    "tone_map": "_preview",
    "write_png": "_preview",
}

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs
    from ._exr import COMPRESSIONS, HALF_CLIPPED_ATTRIBUTE, HALF_MAX, read_exr, read_exr_channels, write_exr
    from ._images import EXR_EXTENSIONS, IMAGE_FORMATS, PILLOW_EXTENSIONS, LinearImage, read_linear_image
    from ._plot import plot_cross_section, save_cross_section
    from ._preview import PNG_SOFTWARE, REC709_LUMINANCE, is_jaxflare_png, tone_map, write_png


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
    "LENS_FORMATS",
    "MAX_INPUT_BYTES",
    "PILLOW_EXTENSIONS",
    "PNG_SOFTWARE",
    "REC709_LUMINANCE",
    "SEMI_APERTURE_MODES",
    "LinearImage",
    "apply_glass_aliases",
    "apply_semi_aperture_mode",
    "atomic_output_group",
    "atomic_output_path",
    "bundled_lens_names",
    "decode_text",
    "decode_zmx_bytes",
    "is_jaxflare_png",
    "lens_toml_text",
    "load_lens",
    "parse_lens_toml",
    "parse_zmx",
    "plot_cross_section",
    "read_exr",
    "read_exr_channels",
    "read_flaresim_lens",
    "read_input_bytes",
    "read_json_lens",
    "read_lens_toml",
    "read_lentil_json",
    "read_linear_image",
    "read_openlensflare_xml",
    "read_pbrt_dat",
    "read_prescription",
    "read_realflare_json",
    "read_text_file",
    "read_zmx",
    "save_cross_section",
    "tone_map",
    "write_bytes_atomic",
    "write_exr",
    "write_png",
    "write_text_atomic",
    "zmx_text",
]
