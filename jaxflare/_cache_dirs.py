"""Where jaxflare keeps its disk caches (path systems, colour-science's tables), and the switch
that turns one off. No heavy imports: the command line reads it before JAX is loaded."""

from __future__ import annotations

import os
from pathlib import Path

_OFF = {"0", "false", "no", "off"}


def cache_root() -> Path:
    """``$JAXFLARE_CACHE_DIR``, else ``$XDG_CACHE_HOME/jaxflare``, else ``~/.cache/jaxflare``."""
    if os.environ.get("JAXFLARE_CACHE_DIR"):
        return Path(os.environ["JAXFLARE_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jaxflare"


def switched_off(variable: str) -> bool:
    """Whether the environment variable ``variable`` turns a cache off (0, false, no or off)."""
    return os.environ.get(variable, "1").strip().lower() in _OFF
