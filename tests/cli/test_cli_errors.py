"""Issue 17: every command-line failure is one line on stderr and a non-zero status, never a
traceback: bad files (a directory, /dev/zero, non-UTF-8 text), bad arguments (--seed 2^70,
--samples 2^63), Ctrl-C (130, also when something below swallows the interrupt) and SIGTERM (143,
no temporary file left). In-process ``main()`` where that tests the same thing; one subprocess
for the real signals (the lens commands do not import JAX, so it starts in about a second)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from jaxflare import cli
from jaxflare.cli import main
from tests.helpers import DATA

ROOT = Path(__file__).resolve().parents[2]


def one_line_error(capsys, *needles: str) -> str:
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert re.match(r"jaxflare( [a-z ]+)?: error: ", lines[0]), lines[0]  # argparse names the subcommand
    assert "Traceback" not in captured.err and "Traceback" not in captured.out
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def test_bad_lens_files_are_one_line_errors_naming_the_file(tmp_path, capsys):
    assert main(["lens", "info", "/dev/zero"]) == 2  # was read past 8 GiB
    one_line_error(capsys, "/dev/zero", "not a regular file")
    assert main(["lens", "info", str(tmp_path)]) == 2
    one_line_error(capsys, str(tmp_path), "is a directory")
    latin1 = tmp_path / "latin1.toml"  # (a .zmx may be ANSI: OpticStudio's older files are read as cp1252)
    latin1.write_bytes(b'name = "Caf\xe9 50"\nf_number = 2.0\n')
    assert main(["lens", "info", str(latin1)]) == 2
    one_line_error(capsys, "latin1.toml:1", "not UTF-8")
    huge = tmp_path / "many.toml"
    rows = "".join("  { radius = 50.0, thickness = 1.0, n_d = 1.5, v_d = 60.0, semi_aperture = 5.0 },\n" for _ in range(400))
    huge.write_text(f'name = "x"\nf_number = 4.0\nsurfaces = [\n{rows}]\n')
    assert main(["lens", "info", str(huge)]) == 2  # a 400-surface lens hung
    one_line_error(capsys, "many.toml", "at most 100")
    assert main(["lens", "convert", str(DATA / "zmx" / "double_gauss_50mm.zmx"), str(tmp_path / "x.txt")]) == 2
    one_line_error(capsys, "must end in .toml or .zmx")
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".tmp-")]


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["render", "demo", "-o", "x.exr", "--seed", str(2**70)], "--seed"),
        (["render", "demo", "-o", "x.exr", "--seed", "-1"], "--seed"),
        (["render", "demo", "-o", "x.exr", "--samples", str(2**63)], "--samples"),
        (["render", "demo", "-o", "x.exr", "--samples", "many"], "--samples"),
        (["lens", "info", "zeiss_biotar", "--glass", "nonsense"], "--glass"),
        (["fit", "plate.exr", "--scene", "demo", "-o", "fit.json", "--max-steps", "0"], "--max-steps"),
    ],
)
def test_bad_arguments_exit_2_with_one_line(argv, needle, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    one_line_error(capsys, needle)


def test_render_refuses_a_directory_as_scene_or_output_before_any_work(tmp_path, capsys):
    scene = tmp_path / "scene.toml"
    scene.write_text('[camera]\nlens = "zeiss_biotar"\n[[light]]\nkind = "directional"\ndirection = [0.0, 0.0, -1.0]\n')
    (tmp_path / "out.exr").mkdir()
    assert main(["render", str(scene), "-o", str(tmp_path / "out.exr")]) == 2
    one_line_error(capsys, "is a directory")
    assert main(["render", str(tmp_path), "-o", str(tmp_path / "flare.exr")]) == 2
    one_line_error(capsys, str(tmp_path), "directory")
    scene.write_bytes(b'[camera]\nlens = "zeiss_biotar" # \xff\n')
    assert main(["render", str(scene), "-o", str(tmp_path / "flare.exr")]) == 2
    one_line_error(capsys, "scene.toml:2", "UTF-8")
    scene.write_text('[camera]\nlens = "zeiss_biotar"\nsurface_coatings = 3\n[[light]]\nkind = "directional"\ndirection = [0.0, 0.0, -1.0]\n')
    assert main(["render", str(scene), "-o", str(tmp_path / "flare.exr")]) == 2  # was a TypeError traceback
    one_line_error(capsys, "camera.surface_coatings: must be a list")
    assert not (tmp_path / "flare.exr").exists()


def test_ctrl_c_exits_130_with_one_line_even_when_swallowed(monkeypatch, capsys):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_lens_info", interrupted)
    assert main(["lens", "info", "zeiss_biotar"]) == 130
    assert capsys.readouterr().err.strip() == "jaxflare: interrupted"

    def swallowed(*args, **kwargs):  # a library that catches KeyboardInterrupt and carries on
        try:
            os.kill(os.getpid(), signal.SIGINT)
        except KeyboardInterrupt:
            pass
        return "finished anyway"

    monkeypatch.setattr(cli, "_lens_info", swallowed)
    handler_before = signal.getsignal(signal.SIGINT)  # pytest-xdist workers run with SIGINT ignored
    assert main(["lens", "info", "zeiss_biotar"]) == 130  # two interrupted renders exited 0
    captured = capsys.readouterr()
    assert captured.err.strip() == "jaxflare: interrupted"
    assert signal.getsignal(signal.SIGINT) is handler_before  # handlers restored


def test_internal_errors_are_one_line_with_status_70(monkeypatch, capsys):
    def broken(*args, **kwargs):
        raise RuntimeError("something\nunexpected")

    monkeypatch.setattr(cli, "_lens_info", broken)
    monkeypatch.delenv("JAXFLARE_TRACEBACK", raising=False)
    assert main(["lens", "info", "zeiss_biotar"]) == 70
    err = capsys.readouterr().err.strip()
    assert err.startswith("jaxflare: internal error: RuntimeError: something unexpected") and "\n" not in err


# The child writes through the real atomic writer, announces it, and waits to be signalled.
CHILD = textwrap.dedent(
    """
    import sys, time
    import jaxflare.io
    from jaxflare import cli
    from jaxflare.io import atomic_output_path

    def slow_write(target, text):
        with atomic_output_path(target) as temporary:
            with open(temporary, "w") as handle:
                handle.write(text[: len(text) // 2])
            print("writing", flush=True)
            time.sleep(60)

    jaxflare.io.write_text_atomic = slow_write
    sys.exit(cli.main(["lens", "convert", sys.argv[1], sys.argv[2]]))
    """
)


@pytest.mark.parametrize("signum, status, line", [(signal.SIGTERM, 143, "jaxflare: terminated"), (signal.SIGINT, 130, "jaxflare: interrupted")])
def test_signal_while_writing_leaves_no_temporary_file(tmp_path, signum, status, line):
    target = tmp_path / "out" / "lens.toml"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(DATA / "zmx" / "double_gauss_50mm.zmx"), str(target)],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        assert child.stdout.readline().strip() == "writing"
        assert next(p.name for p in target.parent.iterdir()).startswith(".tmp-")  # the write is under way
        child.send_signal(signum)
        _, err = child.communicate(timeout=30)
    finally:
        child.kill()
    assert child.returncode == status
    assert err.strip().splitlines()[-1] == line and "Traceback" not in err
    assert list(target.parent.iterdir()) == []  # no temporary file, no half-written target


LAZY_CHILD = textwrap.dedent(
    """
    import contextlib, io, sys
    from jaxflare.cli import main
    with contextlib.redirect_stdout(io.StringIO()):
        try:
            main(["--help"])
        except SystemExit:
            pass
        assert main(["lens", "convert", sys.argv[1], sys.argv[2]]) == 0
    heavy = sorted(name for name in ("jax", "matplotlib", "OpenEXR", "equinox") if name in sys.modules)
    print(",".join(heavy) or "none")
    """
)


def test_help_and_lens_convert_do_not_import_jax(tmp_path):
    """--help took 2.2 s because every command imported JAX first."""
    result = subprocess.run(
        [sys.executable, "-c", LAZY_CHILD, str(DATA / "zmx" / "double_gauss_50mm.zmx"), str(tmp_path / "lens.toml")],
        cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True, text=True, timeout=120, check=False,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "none"
    assert (tmp_path / "lens.toml").read_text().startswith(("#", "name"))


@pytest.mark.parametrize("plate, needle", [("/dev/zero", "not a regular file"), (".", "is a directory"), ("missing.exr", "no such plate file")])
def test_bad_plates_are_one_line_errors(plate, needle, tmp_path, capsys):
    """The fit's plate: a device or a directory was reported as a missing file."""
    assert main(["fit", plate, "--scene", "demo", "-o", str(tmp_path / "fit.json")]) == 2
    one_line_error(capsys, needle)
    assert not list(tmp_path.iterdir())
