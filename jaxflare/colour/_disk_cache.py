"""colour-science's numbers kept on disk, so that a render does not import colour-science.

Importing colour-science takes 1.5-2 s (colour 0.4 imports its plotting module, and with it
matplotlib and scipy's interpolation), a large part of what a fresh ``jaxflare render`` of a small
preview waits for. What jaxflare derives from it (the spectral tables, colour-space matrices,
chromaticities) is a few kilobytes of float64 numbers: :func:`persisted` computes each once with
colour-science and keeps it in ``<cache folder>/colour`` (the folder of the
path systems, :func:`jaxflare._cache_dirs.cache_root`: ``$JAXFLARE_CACHE_DIR``, else
``$XDG_CACHE_HOME/jaxflare``, else ``~/.cache/jaxflare``).

An entry is keyed by the function, its arguments, the installed colour-science version and the
bytes of the module that defines the function, so a new colour-science or a changed formula never
reads a stale entry. Entries are written atomically (a temporary file renamed into place); an entry
that cannot be read is computed again, a folder that cannot be written is skipped: the cache only
saves time. ``JAXFLARE_COLOUR_CACHE=0`` turns it off.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import importlib.metadata
import inspect
import io
from pathlib import Path

import numpy as np

from .._atomic import write_bytes_atomic
from .._cache_dirs import cache_root, switched_off

FORMAT = 1
"""Bumped when the file layout changes."""


def _cache_folder() -> Path | None:
    return None if switched_off("JAXFLARE_COLOUR_CACHE") else cache_root() / "colour"


@functools.cache
def _colour_science_version() -> str:
    try:
        return importlib.metadata.version("colour-science")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - a dependency of the package
        return "unknown"


@functools.cache
def _source_digest(source_file: str) -> str:
    return hashlib.sha256(Path(source_file).read_bytes()).hexdigest()[:16]


def _pack(value) -> dict[str, np.ndarray]:
    """A result as named arrays: a dict of arrays, a tuple of arrays or numbers, or one array."""
    if isinstance(value, dict):
        return {f"d-{key}": np.asarray(item) for key, item in value.items()}
    if isinstance(value, tuple):
        return {f"t-{index:03d}": np.asarray(item) for index, item in enumerate(value)}
    return {"a-": np.asarray(value)}


def _unpack(arrays: dict[str, np.ndarray]):
    keys = sorted(arrays)
    if keys and keys[0].startswith("d-"):
        return {key[2:]: arrays[key] for key in keys}
    if keys and keys[0].startswith("t-"):
        return tuple(arrays[key] if arrays[key].ndim else arrays[key].item() for key in keys)
    return arrays["a-"]


def persisted(function):
    """Keep ``function``'s results (NumPy arrays, or a dict or tuple of arrays and numbers) on disk,
    keyed by its arguments (their ``repr``), the colour-science version and its module's bytes."""
    source = inspect.getsourcefile(function)

    @functools.wraps(function)
    def cached(*args):
        folder = _cache_folder()
        if folder is None:
            return function(*args)
        key = repr((FORMAT, function.__module__, function.__qualname__, args, _colour_science_version(), _source_digest(source)))
        path = folder / f"{function.__name__.strip('_')}-{hashlib.sha256(key.encode()).hexdigest()[:24]}.npz"
        try:
            with np.load(path, allow_pickle=False) as stored:
                return _unpack({name: stored[name] for name in stored.files})
        except (OSError, ValueError, KeyError):
            pass  # absent or unreadable: compute it
        value = function(*args)
        buffer = io.BytesIO()
        np.savez(buffer, **_pack(value))
        with contextlib.suppress(OSError):  # an unwritable folder: the cache only saves time
            write_bytes_atomic(path, buffer.getvalue())
        return value

    return cached
