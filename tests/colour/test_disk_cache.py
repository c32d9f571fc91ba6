"""colour-science's numbers kept on disk (jaxflare.colour._disk_cache): a second process gets the
same tables without importing colour-science; a damaged entry or an unwritable folder only costs
time."""

import os
import subprocess
import sys

import numpy as np

from jaxflare.colour import _disk_cache, _spectral

from tests.helpers import ROOT

TABLES = """
import json, sys
import numpy as np
from jaxflare.colour import _spectral as s
t = s._build_tables("ACEScg", (380.0, 780.0), 5.0)
print(json.dumps({"colour_imported": "colour" in sys.modules, "chromaticities": s.colour_space_chromaticities("ACEScg"),
                  "display": s.display_matrix("ACEScg").tolist(), "rgb_response": np.asarray(t["rgb_response"]).ravel().tolist()}))
"""


def run_tables(cache_dir, **env):
    environment = {**os.environ, "JAXFLARE_CACHE_DIR": str(cache_dir), **env}
    out = subprocess.run([sys.executable, "-c", TABLES], cwd=ROOT, env=environment, capture_output=True, text=True, check=True, timeout=300)
    import json

    return json.loads(out.stdout.strip().splitlines()[-1])


def test_a_second_process_reads_the_tables_without_importing_colour_science(tmp_path):
    first = run_tables(tmp_path)
    assert first["colour_imported"]
    entries = sorted(p.name for p in (tmp_path / "colour").iterdir())
    assert any(name.startswith("build_tables-") for name in entries) and not any(name.endswith(".tmp") for name in entries)
    second = run_tables(tmp_path)
    assert not second["colour_imported"]
    for key in ("chromaticities", "display", "rgb_response"):
        assert second[key] == first[key], key  # bit for bit: float64 through .npz


def test_the_cached_tables_equal_colour_sciences(tmp_path, monkeypatch):
    monkeypatch.setenv("JAXFLARE_CACHE_DIR", str(tmp_path))
    built = _spectral._build_tables.__wrapped__.__wrapped__("sRGB-linear", (400.0, 700.0), 10.0)  # colour-science, no cache
    cached = _spectral._build_tables.__wrapped__("sRGB-linear", (400.0, 700.0), 10.0)  # computes and writes
    read = _spectral._build_tables.__wrapped__("sRGB-linear", (400.0, 700.0), 10.0)  # reads
    assert sorted(read) == sorted(built)
    for key in built:
        np.testing.assert_array_equal(read[key], built[key])
        np.testing.assert_array_equal(cached[key], built[key])


def test_a_damaged_entry_is_computed_again_an_unwritable_folder_skipped_and_the_cache_can_be_off(tmp_path, monkeypatch):
    calls = []

    @_disk_cache.persisted
    def matrices(scale: float):
        calls.append(scale)
        return np.eye(3) * scale, 2.5 * scale

    monkeypatch.setenv("JAXFLARE_CACHE_DIR", str(tmp_path))
    first = matrices(2.0)
    assert len(calls) == 1
    read = matrices(2.0)
    assert len(calls) == 1  # read from disk
    np.testing.assert_array_equal(read[0], first[0])
    assert read[1] == 5.0 and isinstance(read[1], float)
    (entry,) = (tmp_path / "colour").iterdir()
    entry.write_bytes(b"not a zip file")
    again = matrices(2.0)
    assert len(calls) == 2
    np.testing.assert_array_equal(again[0], first[0])
    assert matrices(2.0) is not None and len(calls) == 2  # rewritten whole
    blocked = tmp_path / "file"
    blocked.write_text("a file where the folder would be")
    monkeypatch.setenv("JAXFLARE_CACHE_DIR", str(blocked))
    np.testing.assert_array_equal(matrices(3.0)[0], np.eye(3) * 3.0)
    assert not any(p.suffix == ".tmp" for p in tmp_path.rglob("*"))
    monkeypatch.setenv("JAXFLARE_CACHE_DIR", str(tmp_path / "off"))
    monkeypatch.setenv("JAXFLARE_COLOUR_CACHE", "0")
    matrices(4.0), matrices(4.0)
    assert calls[-2:] == [4.0, 4.0] and not (tmp_path / "off").exists()
