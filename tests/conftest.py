"""Shared fixtures. Validation runs in float64 (the project renders in float32, fits and validates
in float64); tests that check float32 behaviour switch it off locally with ``jax.enable_x64(False)``."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")

import jax

jax.config.update("jax_enable_x64", True)

import pytest

import jaxflare


@pytest.fixture(scope="session")
def biotar() -> jaxflare.Lens:
    return jaxflare.load_lens("zeiss_biotar")
