"""Shared fixtures. Validation runs in float64 (the project renders in float32, fits and validates
in float64); tests that check float32 behaviour switch it off locally with ``jax.enable_x64(False)``."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")
# No persistent JAX compilation cache in the test run (not in process, not in the CLI subprocesses,
# which inherit the environment): on jaxlib 0.10.2 serialising a CPU executable for the cache
# segfaulted a pytest-xdist worker in CI (in ``LoadedExecutable.serialize``), and the run then
# hung until CI's limit. The CLI's own cache is tested in tests/cli/test_compilation_cache.py.
os.environ.setdefault("JAXFLARE_COMPILATION_CACHE", "0")
os.environ.pop("JAX_COMPILATION_CACHE_DIR", None)

import jax

jax.config.update("jax_enable_x64", True)

import pytest

import jaxflare


@pytest.fixture(scope="session")
def biotar() -> jaxflare.Lens:
    return jaxflare.load_lens("zeiss_biotar")
