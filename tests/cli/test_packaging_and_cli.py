"""Packaging (lens files and glass data ship in the wheel) and the command line."""

import os
import subprocess
import sys
import zipfile

import pytest

import jaxflare
from jaxflare.cli import main

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_wheel_ships_lenses_and_glass_catalog(tmp_path):
    """A plain, non-editable install must find the bundled lenses: they are package data."""
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path), ROOT],
        check=True,
        capture_output=True,
    )
    (wheel,) = tmp_path.glob("jaxflare-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    for lens in jaxflare.bundled_lens_names():
        assert f"jaxflare/lenses/{lens}.toml" in names
    assert "jaxflare/optics/data/glass_catalog.csv" in names
    assert any(name.startswith("fitting/") for name in names)


def test_lens_list_and_info(capsys):
    assert main(["lens", "list"]) == 0
    listing = capsys.readouterr().out
    for name in jaxflare.bundled_lens_names():
        assert name in listing
    assert main(["lens", "info", "zeiss_biotar", "--top", "3"]) == 0
    info = capsys.readouterr().out
    assert "EFL: 99.9" in info and "ghost paths: 45" in info and "ranked by on-axis Fresnel factor" in info


def test_lens_info_unknown_lens_is_a_clear_error(capsys):
    assert main(["lens", "info", "zeiss_biotr"]) == 2
    assert "Did you mean: zeiss_biotar" in capsys.readouterr().err


def test_lens_plot_and_convert(tmp_path, capsys):
    png = tmp_path / "biotar.png"
    assert main(["lens", "plot", "zeiss_biotar", "-o", str(png), "--ghost", "5,2"]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    zmx = tmp_path / "biotar.zmx"
    assert main(["lens", "convert", "zeiss_biotar", str(zmx)]) == 0
    back = jaxflare.load_lens(str(zmx))
    assert back.focal_length() == pytest.approx(jaxflare.load_lens("zeiss_biotar").focal_length(), rel=1e-9)
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".tmp-")]  # atomic writes leave no temporaries


def test_demo_writes_cross_section(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--samples", "100000"]) == 0
    out = capsys.readouterr().out
    assert "Bundled lenses:" in out and "cross_section.png" in out
    assert (tmp_path / "cross_section.png").stat().st_size > 10_000
    assert (tmp_path / "demo.exr").exists() and (tmp_path / "demo.png").exists() and "demo.exr" in out
