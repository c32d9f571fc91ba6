"""JAX's persistent compilation cache for the command line.

A fresh ``jaxflare render`` process spends most of its first seconds compiling the tracer and the
render step; XLA programs compiled once are kept on disk and loaded by later processes (the JAX
cache is keyed by the program, the compile options and the JAX version, so a stale entry is never
used). The CLI turns it on; scripts and notebooks keep JAX's own default unless they set
``JAX_COMPILATION_CACHE_DIR`` themselves.

Where: ``$JAX_COMPILATION_CACHE_DIR`` when set (JAX reads it itself), else
``$XDG_CACHE_HOME/jaxflare/jax`` (``~/.cache/jaxflare/jax``). ``JAXFLARE_COMPILATION_CACHE=0`` turns
it off. A folder that cannot be created or written is skipped silently: the cache only saves time.
"""

from __future__ import annotations

import os
from pathlib import Path

from ._cache_dirs import switched_off

MIN_COMPILE_TIME_S = 0.0
"""Programs that compile faster than this are not written to the cache. Zero: a grid render
compiles some 80 small programs (host-side planning, table building) that each take well under
0.2 s but together 4-5 s of a fresh process (measured on a 64 x 48 grid render: 11.3 s with a
0.2 s threshold and a warm cache, 6.3 s with every program cached; the cache grew by 0.7 MB)."""


def compilation_cache_dir() -> Path | None:
    """The folder the CLI caches compiled programs in, or None when caching is off."""
    if switched_off("JAXFLARE_COMPILATION_CACHE"):
        return None
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return Path(os.environ["JAX_COMPILATION_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jaxflare" / "jax"


def enable_compilation_cache() -> Path | None:
    """Point JAX's persistent compilation cache at :func:`compilation_cache_dir` (when it can be
    written); returns the folder used, or None."""
    folder = compilation_cache_dir()
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if not os.access(folder, os.W_OK | os.X_OK):
            return None
    except OSError:
        return None
    import jax

    jax.config.update("jax_compilation_cache_dir", str(folder))
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_TIME_S)
    return folder
