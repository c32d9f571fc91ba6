"""Finding and loading lenses: bundled names, our TOML format and Zemax ``.zmx`` files."""

from __future__ import annotations

import difflib
import os
from importlib import resources

from ..optics import LensPrescription
from ._lens_toml import read_lens_toml


def _bundled_directory():
    """The bundled lens folder: the installed ``jaxflare.lenses`` package data, or, when running
    from a source tree that is not installed, the repository's ``lenses/`` folder."""
    try:
        return resources.files("jaxflare.lenses")
    except ModuleNotFoundError:
        return resources.files("jaxflare").joinpath("..", "lenses")


def bundled_lens_names() -> list[str]:
    """Names of the lenses shipped with jaxflare (file stems in ``lenses/``)."""
    return sorted(entry.name[: -len(".toml")] for entry in _bundled_directory().iterdir() if entry.name.endswith(".toml"))


def read_prescription(source: str | os.PathLike) -> LensPrescription:
    """Read a prescription from a bundled lens name, a jaxflare ``.toml`` file or a Zemax ``.zmx`` file."""
    text = os.fspath(source)
    lower = text.lower()
    if lower.endswith(".zmx"):
        from ._zemax import read_zmx

        return read_zmx(text)
    if lower.endswith(".toml") or os.sep in text or os.path.exists(text):
        return read_lens_toml(text)
    names = bundled_lens_names()
    if text in names:
        with resources.as_file(_bundled_directory() / f"{text}.toml") as path:
            return read_lens_toml(path)
    close = difflib.get_close_matches(text, names, n=5, cutoff=0.3)
    hint = f" Did you mean: {', '.join(close)}?" if close else ""
    raise FileNotFoundError(
        f"no lens named {text!r}: not a file path and not a bundled lens.{hint} Bundled lenses: {', '.join(names)}"
    )


def load_lens(source: str | os.PathLike | LensPrescription, zoom_position: int = 0):
    """Load a lens: a bundled name (see :func:`bundled_lens_names`), a path to a jaxflare ``.toml``
    lens file, a Zemax ``.zmx`` path, or a :class:`LensPrescription`. Zooms start at position 0."""
    from ..optics import build_lens  # JAX: only when a lens is built

    prescription = source if isinstance(source, LensPrescription) else read_prescription(source)
    return build_lens(prescription, zoom_position)
