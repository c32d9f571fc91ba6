"""The example notebooks in ``notebooks/``: committed without outputs, and they run top to bottom.

Every ``notebooks/*.ipynb`` is picked up, including notebooks added later. Each one is executed
with nbclient in a fresh ``python3`` kernel of this interpreter (jupyter_client starts a kernel
spec whose command is ``python`` with ``sys.executable``), with the notebook folder as its working
directory, as a user running it from a fresh clone would. The notebook is executed in memory:
nothing is written back. A failing cell fails the test with that cell's source and traceback.

Execution is split over two files (this one and ``test_notebooks_second_half.py``) so the two
pytest-xdist workers of ``make test`` share it. Run one notebook with
``pytest tests/docs/test_notebooks.py tests/docs/test_notebooks_second_half.py -k quick_start``; add ``-rP`` to see the
measured wall time of each notebook (also recorded as the ``wall_seconds`` property, e.g. in
``--junitxml`` reports).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
NOTEBOOK_DIR = REPO / "notebooks"
CELL_TIMEOUT_S = 600
KERNEL_NAME = "python3"

# Keep matplotlib, IPython, Jupyter and jaxflare caches inside the checkout (the Makefile exports the
# same for `make test`); set before nbclient / jupyter_client read them. The kernel inherits them.
_CACHE = REPO / ".cache"
for _name, _value in {
    "MPLCONFIGDIR": _CACHE / "matplotlib",
    "XDG_CACHE_HOME": _CACHE,
    "IPYTHONDIR": _CACHE / "ipython",
    "JUPYTER_CONFIG_DIR": _CACHE / "jupyter",
    "JUPYTER_DATA_DIR": _CACHE / "jupyter-data",
    "JUPYTER_RUNTIME_DIR": _CACHE / "jupyter-runtime",
    "MPLBACKEND": "Agg",
}.items():
    os.environ.setdefault(_name, str(_value))

nbformat = pytest.importorskip("nbformat", reason="notebook tests need the test extras: pip install -e '.[test]'")
nbclient = pytest.importorskip("nbclient", reason="notebook tests need the test extras: pip install -e '.[test]'")
pytest.importorskip("ipykernel", reason="notebook tests need the test extras: pip install -e '.[test]'")
errors = pytest.importorskip("nbclient.exceptions")


def notebook_paths() -> list[Path]:
    """Every notebook in ``notebooks/`` (tracked or not), and every one git tracks there."""
    found = set(NOTEBOOK_DIR.glob("*.ipynb"))
    try:
        tracked = subprocess.run(
            ["git", "ls-files", "-z", "--", "notebooks/*.ipynb"], cwd=REPO, capture_output=True, check=True, timeout=30
        ).stdout.decode()
        found |= {REPO / name for name in tracked.split("\0") if name}
    except (OSError, subprocess.SubprocessError):
        pass  # not a git checkout (e.g. an sdist): the folder listing is all there is
    return sorted(found)


NOTEBOOKS = notebook_paths()
IDS = [path.stem for path in NOTEBOOKS]
_ANSI = re.compile(r"\x1b\[[0-9;]*m")  # colour codes in IPython tracebacks


def _shown(path: Path) -> str:
    return str(path.relative_to(REPO)) if path.is_relative_to(REPO) else str(path)


def test_notebooks_exist():
    assert NOTEBOOKS, f"no notebooks found in {NOTEBOOK_DIR}"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=IDS)
def test_notebook_is_stripped(path: Path):
    """Committed notebooks carry no outputs and no execution counts (before committing: Jupyter's
    "Clear All Outputs" and save, or ``jupyter nbconvert --clear-output --inplace`` with nbconvert)."""
    assert path.is_file(), f"{_shown(path)} is tracked by git but missing from the working tree"
    notebook = nbformat.read(path, as_version=4)
    nbformat.validate(notebook)
    dirty = [
        f"cell {index}: {len(cell.get('outputs', []))} output(s), execution_count {cell.get('execution_count')!r}"
        for index, cell in enumerate(notebook.cells)
        if cell.cell_type == "code" and (cell.get("outputs") or cell.get("execution_count") is not None)
    ]
    assert not dirty, f"{_shown(path)} is not stripped:\n  " + "\n  ".join(dirty)


def test_kernel_is_this_interpreter():
    """The ``python3`` kernel the notebooks run in is this environment's Python (with jaxflare)."""
    notebook = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell("import sys, jaxflare; print(sys.executable)")])
    nbclient.NotebookClient(notebook, kernel_name=KERNEL_NAME, timeout=120).execute()
    printed = "".join(output.get("text", "") for output in notebook.cells[0].outputs).strip()
    assert Path(printed).resolve() == Path(sys.executable).resolve(), f"kernel runs {printed!r}, tests run {sys.executable!r}"


def _files_under(folder: Path) -> set[Path]:
    """Files a notebook might leave in its working directory (notebooks themselves are left out: a
    colleague may be adding one while the tests run)."""
    return {
        p
        for p in folder.rglob("*")
        if p.suffix != ".ipynb" and ".ipynb_checkpoints" not in p.parts and "__pycache__" not in p.parts
    }


FIRST_HALF = NOTEBOOKS[0::2]
"""Notebooks this file runs; the others run in tests/docs/test_notebooks_second_half.py, so that
``make test`` (pytest-xdist ``--dist loadfile``: one worker per file) runs the two halves at once."""


@pytest.mark.parametrize("path", FIRST_HALF, ids=[path.stem for path in FIRST_HALF])
def test_notebook_runs(path: Path, record_property):
    run_notebook(path, record_property)


def run_notebook(path: Path, record_property):
    """Execute the notebook top to bottom in a fresh kernel, working directory ``notebooks/``."""
    notebook = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(
        notebook,
        kernel_name=KERNEL_NAME,
        timeout=CELL_TIMEOUT_S,
        resources={"metadata": {"path": str(NOTEBOOK_DIR)}},
    )
    before = _files_under(NOTEBOOK_DIR)
    failure = None
    started = time.perf_counter()
    try:
        client.execute()
    except errors.CellExecutionError as error:  # its message holds the cell's source and the traceback
        failure = f"{path.name}: a cell raised\n{_ANSI.sub('', str(error))}"
    except (errors.CellTimeoutError, errors.DeadKernelError) as error:
        failure = f"{path.name}: {type(error).__name__}: {_ANSI.sub('', str(error))}"
    finally:
        seconds = time.perf_counter() - started
        record_property("wall_seconds", round(seconds, 1))
        print(f"{path.name}: executed in {seconds:.1f} s (wall)")
    if failure:
        pytest.fail(failure, pytrace=False)
    created = sorted(_shown(p) for p in _files_under(NOTEBOOK_DIR) - before)
    assert not created, f"{path.name} wrote into the repository (use tempfile): {created}"
