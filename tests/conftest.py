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
# XLA's CPU compiler, tuned for compile time: the suite compiles ~1500 programs and spent more than
# half its time in XLA's backend (1068 s of 1977 s of test time, 2-core VM). Without the MLIR fusion
# emitters (one MLIR context per kernel) and at LLVM optimisation level 1, a Biotar render step
# compiles in 1.6-1.9 s instead of 3.1-3.4 s, runs about as fast, and gives the same image to float32
# rounding (8e-6 of a 7.8 peak); the suite's backend compile fell to 477 s, its wall time from
# 874-1018 s to 661 s. Renders and fits outside the tests keep XLA's defaults (faster kernels).
# The notebook kernels and CLI subprocesses inherit these flags with the environment.
# XLA aborts the process on a flag it does not know, so only flags this jaxlib's binary names are set.
_XLA_TEST_FLAGS = ("--xla_cpu_use_fusion_emitters=false", "--xla_backend_optimization_level=1")


def _known_xla_flags(flags):
    import importlib.util
    import mmap
    from pathlib import Path

    spec = importlib.util.find_spec("jaxlib")
    folders = [Path(p) for p in (spec.submodule_search_locations or [])] if spec else []
    names = {f.split("=")[0].lstrip("-").encode() for f in flags}
    found = set()
    for library in (p for folder in folders for p in folder.glob("*.so") if p.stat().st_size > 2**24):
        with open(library, "rb") as handle, mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ) as data:
            found |= {name for name in names if data.find(name) >= 0}
    return [f for f in flags if f.split("=")[0].lstrip("-").encode() in found]


_flags = os.environ.get("XLA_FLAGS", "")
_added = [f for f in _known_xla_flags(_XLA_TEST_FLAGS) if f.split("=")[0] not in _flags]
os.environ["XLA_FLAGS"] = " ".join([_flags] * bool(_flags) + _added)

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
