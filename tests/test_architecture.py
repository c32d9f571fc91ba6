"""The layout is a contract: stage packages import only downwards (import-linter), each package's
``__init__`` is its API, and no document a user reads (README, notebooks, format documents,
benchmarks) reaches into a private module."""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

import jaxflare

ROOT = Path(__file__).resolve().parents[1]
PRIVATE_IMPORT = re.compile(r"\b(?:from|import)\s+(?:jaxflare|fitting)(?:\.[A-Za-z0-9]+)*\._[A-Za-z]\w*|\bjaxflare(?:\.[a-z]+)*\._(?!_)[a-z]\w*\s*(?:\.|\(|import)")
STAGES = ("optics", "colour", "io", "polynomial", "scenes", "rendering")


def test_import_contracts_are_kept():
    """``lint-imports`` checks the contracts in pyproject.toml: layers (cli, fitting, rendering,
    scenes, polynomial, io, then optics and colour), private modules, no cycles."""
    lint = Path(sys.executable).with_name("lint-imports")
    result = subprocess.run([str(lint), "--config", str(ROOT / "pyproject.toml")], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "3 kept, 0 broken" in result.stdout


def test_the_layer_contract_would_catch_an_upward_import(tmp_path):
    """The contract is not vacuous: a copy of the package in which optics imports rendering breaks it."""
    import shutil

    copy = tmp_path / "src"
    shutil.copytree(ROOT / "jaxflare", copy / "jaxflare", ignore=shutil.ignore_patterns("__pycache__", "data", "*.md", "*.toml"))
    shutil.copytree(ROOT / "fitting", copy / "fitting", ignore=shutil.ignore_patterns("__pycache__"))
    with open(copy / "jaxflare" / "optics" / "_lens.py", "a") as handle:
        handle.write("\nfrom ..rendering import render  # an upward import\n")
    lint = Path(sys.executable).with_name("lint-imports")
    result = subprocess.run(
        [str(lint), "--config", str(ROOT / "pyproject.toml")], cwd=copy, capture_output=True, text=True, timeout=300,
        env={"PYTHONPATH": str(copy), "PATH": str(Path(sys.executable).parent)},
    )
    assert result.returncode != 0
    assert "jaxflare.optics._lens -> jaxflare.rendering" in result.stdout


def _documents():
    files = [ROOT / "README.md", ROOT / "lenses" / "FORMAT.md", ROOT / "jaxflare" / "scenes" / "FORMAT.md", ROOT / "benchmarks" / "README.md"]
    files += sorted((ROOT / "benchmarks").glob("*.py"))
    for path in files:
        yield path, path.read_text()
    for path in sorted((ROOT / "notebooks").glob("*.ipynb")):
        cells = json.loads(path.read_text())["cells"]
        yield path, "\n".join("".join(cell["source"]) for cell in cells if cell["cell_type"] == "code")


@pytest.mark.parametrize("path, text", list(_documents()), ids=lambda value: value.name if isinstance(value, Path) else "")
def test_documents_use_only_public_modules(path, text):
    offending = [line.strip() for line in text.splitlines() if PRIVATE_IMPORT.search(line)]
    assert not offending, f"{path.relative_to(ROOT)} uses private modules: {offending}"


def test_each_stage_exports_what_it_documents():
    """Every name in a stage's ``__all__`` exists, and the root re-exports the script-level names."""
    import importlib

    for stage in STAGES:
        module = importlib.import_module(f"jaxflare.{stage}")
        missing = [name for name in module.__all__ if not hasattr(module, name)]
        assert not missing, (stage, missing)
    for name in ("load_lens", "trace", "ghost_paths", "path_system", "load_scene", "render", "read_zmx", "write_zmx", "plot_cross_section", "rank_ghost_paths"):
        assert name in jaxflare.__all__ and callable(getattr(jaxflare, name)), name
    assert len(jaxflare.__all__) <= 25
