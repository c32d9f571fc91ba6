"""Atomic outputs (jaxflare._atomic, re-exported by jaxflare.io): a reader never sees a half-written file, nor an EXR and
its PNG (or a fit's JSON and its render) from two different runs; nothing temporary is left."""

import os
from pathlib import Path

import pytest

from jaxflare.io import atomic_output_group, atomic_output_path


def temporaries(folder):
    return [name for name in os.listdir(folder) if name.startswith(".tmp-")]


def write_run(tmp_path, run, fail_after=None, stale=()):
    exr, png = tmp_path / "flare.exr", tmp_path / "flare.png"
    with atomic_output_group([exr, png], stale=stale) as (exr_tmp, png_tmp):
        with open(exr_tmp, "w") as handle:
            handle.write(f"exr of run {run}")
        if fail_after == "exr":
            raise KeyboardInterrupt  # Ctrl-C (or SIGTERM turned into an exception) between the two files
        with open(png_tmp, "w") as handle:
            handle.write(f"png of run {run}")
    return exr, png


def test_a_group_is_replaced_whole_or_not_at_all(tmp_path):
    exr, png = write_run(tmp_path, 1)
    assert (exr.read_text(), png.read_text()) == ("exr of run 1", "png of run 1")
    with pytest.raises(KeyboardInterrupt):
        write_run(tmp_path, 2, fail_after="exr")
    assert (exr.read_text(), png.read_text()) == ("exr of run 1", "png of run 1")  # not a mix
    assert temporaries(tmp_path) == []
    write_run(tmp_path, 3)
    assert (exr.read_text(), png.read_text()) == ("exr of run 3", "png of run 3")
    assert temporaries(tmp_path) == []


def test_stale_companions_of_an_earlier_run_are_removed(tmp_path):
    """A run without --png removes the PNG of an earlier run: it would not belong to the new EXR."""
    write_run(tmp_path, 1)
    with atomic_output_group([tmp_path / "flare.exr"], stale=(tmp_path / "flare.png",)) as (exr_tmp,):
        Path(exr_tmp).write_text("exr of run 2")
    assert (tmp_path / "flare.exr").read_text() == "exr of run 2" and not (tmp_path / "flare.png").exists()


def test_single_file_keeps_the_old_version_on_failure_and_its_permissions(tmp_path):
    target = tmp_path / "lens.toml"
    target.write_text("old")
    os.chmod(target, 0o640)
    with pytest.raises(ValueError), atomic_output_path(target) as temporary:
        with open(temporary, "w") as handle:
            handle.write("half")
        raise ValueError("writer failed")
    assert target.read_text() == "old" and temporaries(tmp_path) == []
    with atomic_output_path(target) as temporary, open(temporary, "w") as handle:
        handle.write("new")
    assert target.read_text() == "new" and (os.stat(target).st_mode & 0o777) == 0o640
