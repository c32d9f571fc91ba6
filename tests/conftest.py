"""Shared fixtures. Validation runs in float64 (the project renders in float32, fits and validates
in float64); tests that check float32 behaviour switch it off locally with ``jax.enable_x64(False)``."""

import gc
import os

os.environ.setdefault("MPLBACKEND", "Agg")
# One persistent JAX compilation cache for the test run: the xdist workers, the notebook kernels and
# the CLI subprocesses (which inherit the environment) load what another process compiled, and a
# worker reloads from it what it compiled before clearing its in-memory caches (below).
_CACHE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), ".cache")
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", os.path.join(_CACHE, "jax"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")

import jax

jax.config.update("jax_enable_x64", True)

import pytest

import jaxflare


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    """Drop every compiled program after each test file. An xdist worker runs half the suite's
    files in one process; with all their programs kept, XLA's CPU compiler segfaulted late in a run
    twice (jaxlib 0.10.2, at 97 %: once compiling, once serialising an executable), and xdist's
    loadfile scheduler then hung until CI's limit. Programs compiled again load from the
    persistent cache above."""
    yield
    jax.clear_caches()
    gc.collect()


@pytest.fixture(scope="session")
def biotar() -> jaxflare.Lens:
    return jaxflare.load_lens("zeiss_biotar")
