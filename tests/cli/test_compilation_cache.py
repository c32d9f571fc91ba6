"""The CLI's persistent compilation cache: where it goes, how to turn it off, and that a folder
that cannot be written is skipped rather than an error."""

import os

import pytest

from jaxflare._compilation_cache import compilation_cache_dir, enable_compilation_cache


def test_cache_folder_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.delenv("JAXFLARE_COMPILATION_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert compilation_cache_dir() == tmp_path / "jaxflare" / "jax"
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "mine"))
    assert compilation_cache_dir() == tmp_path / "mine"
    monkeypatch.setenv("JAXFLARE_COMPILATION_CACHE", "0")
    assert compilation_cache_dir() is None and enable_compilation_cache() is None


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write anywhere")
def test_unwritable_cache_folder_is_skipped(monkeypatch, tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        monkeypatch.delenv("JAXFLARE_COMPILATION_CACHE", raising=False)
        monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(locked / "jax"))
        assert enable_compilation_cache() is None
    finally:
        locked.chmod(0o700)
