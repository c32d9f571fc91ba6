"""The second half of the notebook runs (see tests/docs/test_notebooks.py, which runs the first half and
checks that every notebook is committed without outputs): a file of its own so that pytest-xdist's
``--dist loadfile`` runs it on the other worker."""

from pathlib import Path

import pytest
from tests.docs import test_notebooks as harness

SECOND_HALF = harness.NOTEBOOKS[1::2]


@pytest.mark.parametrize("path", SECOND_HALF, ids=[path.stem for path in SECOND_HALF])
def test_notebook_runs(path: Path, record_property):
    harness.run_notebook(path, record_property)
