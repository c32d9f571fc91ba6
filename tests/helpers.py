"""Helpers shared by the tests: where things are, and building a lens from TOML text."""

from pathlib import Path

import jaxflare

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent
DATA = TESTS / "data"


def lens_from_toml(text: str, filename: str = "test.toml") -> jaxflare.Lens:
    return jaxflare.build_lens(jaxflare.parse_lens_toml(text, filename))
