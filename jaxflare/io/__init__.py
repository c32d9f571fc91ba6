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

from ._atomic import atomic_output_path, write_bytes_atomic, write_text_atomic
from ._exr import COMPRESSIONS, HALF_CLIPPED_ATTRIBUTE, HALF_MAX, read_exr, read_exr_channels, write_exr
from ._images import EXR_EXTENSIONS, IMAGE_FORMATS, PILLOW_EXTENSIONS, LinearImage, read_linear_image
from ._lens_files import bundled_lens_names, load_lens, read_prescription
from ._lens_toml import lens_toml_text, parse_lens_toml, read_lens_toml
from ._plot import plot_cross_section, save_cross_section
from ._preview import REC709_LUMINANCE, tone_map, write_png
from ._zemax import decode_zmx_bytes, parse_zmx, read_zmx, write_zmx, zmx_text

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
