"""README.md stays true to the code.

- Every ```python block runs, in file order, in one namespace, in a fresh interpreter started in a
  temporary working directory (with its own path-system cache), as a reader would run them; a
  failure points at the README line. Some values the README states in its comments are checked.
- Every ``jaxflare ...`` line of the ```sh blocks parses with the command line's own parser (the
  subcommand, the options and their values exist) and names only options that the subcommand's
  ``--help`` lists; no command is run. Together the lines use every subcommand.
- Every ``jaxflare ...`` synopsis line of the ```text blocks names real options, and lists all
  of its subcommand's options (the README says it shows "all options").
- ``make`` targets exist, files the commands read from the repository exist, relative links and
  pictures point at files (and headings) that exist, and the ```toml examples load: lens files
  build and match their stated focal length and f-number, scene files load and build their lens,
  and the scene shown as the demo scene is the bundled demo scene.

The ```sh blocks must hold runnable command lines (a synopsis with [optional] parts goes in a
```text block).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import os
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

jaxflare = pytest.importorskip(
    "jaxflare", reason="the jaxflare package is not importable (run `make demo` or `pip install -e .`), so README.md cannot be checked"
)
from jaxflare.cli import build_parser, main

from tests.helpers import ROOT
README = ROOT / "README.md"


@dataclasses.dataclass(frozen=True)
class Block:
    language: str
    text: str
    line: int
    """README line number of the block's first line of code (1-based)."""


def code_blocks(path: Path = README) -> list[Block]:
    """The fenced code blocks of a Markdown file, indented ones (in list items) dedented."""
    blocks, current, indent, language, start = [], None, "", "", 0
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        stripped = line.strip()
        if current is None:
            if stripped.startswith("```"):
                current, indent, language, start = [], line[: len(line) - len(line.lstrip())], stripped[3:].strip(), number + 1
        elif stripped == "```":
            blocks.append(Block(language, "\n".join(current) + "\n", start))
            current = None
        else:
            current.append(line[len(indent) :] if line.startswith(indent) else line.lstrip())
    assert current is None, f"{path.name}: unterminated code block from line {start - 1}"
    return blocks


def command_lines(language: str) -> list[tuple[int, str]]:
    """(README line, command) of every line of the blocks of ``language``; continuations joined."""
    lines = []
    for block in code_blocks():
        if block.language != language:
            continue
        pending, first = "", 0
        for offset, line in enumerate(block.text.splitlines()):
            if not pending:
                first = block.line + offset
            if line.rstrip().endswith("\\"):
                pending += line.rstrip()[:-1] + " "
                continue
            command = (pending + line).strip()
            pending = ""
            if command and not command.startswith("#"):
                lines.append((first, command))
    return lines


def jaxflare_argv(command: str) -> list[str] | None:
    """The arguments after ``jaxflare`` (also ``.venv/bin/jaxflare``, ``python -m jaxflare``), or None."""
    words = shlex.split(command, comments=True)
    if words[:2] in (["python", "-m"], [".venv/bin/python", "-m"]) and words[2:3] == ["jaxflare"]:
        return words[3:]
    if words and words[0] in ("jaxflare", ".venv/bin/jaxflare"):
        return words[1:]
    return None


def subcommand_path(argv: list[str]) -> list[str]:
    return argv[:2] if argv[:1] == ["lens"] else argv[:1]


def leaf_subcommands(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()) -> dict[tuple[str, ...], argparse.ArgumentParser]:
    """Every runnable subcommand (``("lens", "info")``, ``("render",)``, ...) and its parser."""
    leaves = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                leaves.update(leaf_subcommands(sub, prefix + (name,)) or {prefix + (name,): sub})
    return leaves


def help_text(path: list[str]) -> str:
    """What ``jaxflare PATH --help`` prints."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), pytest.raises(SystemExit) as stopped:
        main([*path, "--help"])
    assert stopped.value.code == 0, f"`jaxflare {' '.join(path)} --help` failed: {err.getvalue()}"
    return out.getvalue()


def names_option(text: str, option: str) -> bool:
    return re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", text) is not None


SH_LINES = command_lines("sh")
JAXFLARE_LINES = [(line, command) for line, command in SH_LINES if jaxflare_argv(command) is not None]
SYNOPSES = [(line, command) for line, command in command_lines("text") if command.startswith("jaxflare ")]


# ---------------------------------------------------------------- the Python examples


def test_the_readme_has_python_examples_for_each_part_of_the_api():
    python = "\n".join(block.text for block in code_blocks() if block.language == "python")
    for call in ("jaxflare.trace(", "jaxflare.path_system(", "jf.render(", ".write_exr(", ".preview(",
                 "fitting.load_plate(", "fitting.fit(", "fitting.save_fit(", "fitting.apply_fit("):
        assert call in python, f"README.md: no Python example calls {call}"


RUNNER = r"""
import json, sys
blocks, readme, facts_file = json.load(open(sys.argv[1])), sys.argv[2], sys.argv[3]
namespace = {"__name__": "readme_examples"}
for line, text in blocks:
    # padded so that a traceback names the README line
    exec(compile("\n" * (line - 1) + text, readme, "exec"), namespace)

import jaxflare
lens, result, scene = namespace["lens"], namespace["result"], namespace["scene"]
facts = dict(
    focal_length=lens.focal_length(wavelength_nm=587.56), num_interfaces=lens.num_interfaces,
    first_ghost_paths=[list(p) for p in jaxflare.ghost_paths(lens)[:3]], resolution=list(scene.camera.resolution),
    image_shape=list(result.image.shape), layer_shapes={k: list(v.shape) for k, v in result.layers.items()},
    preview_shape=list(namespace["preview"].shape), trusted_given=namespace["approx"].trusted is not None,
    systems=[list(k) for k in namespace["systems"]], fitted_tints=len(namespace["fitted_scene"].camera.coating_tints),
)
json.dump(facts, open(facts_file, "w"))
"""


def test_python_examples_run_in_order(tmp_path):
    """The blocks run in a fresh interpreter, as a reader would run them: float64 off (the test
    suite turns it on), nothing imported beforehand, a new working directory and path-system cache."""
    blocks = [[block.line, block.text] for block in code_blocks() if block.language == "python"]
    assert blocks, "README.md has no ```python blocks"
    (tmp_path / "blocks.json").write_text(json.dumps(blocks), encoding="utf-8")
    work = tmp_path / "work"
    work.mkdir()
    env = {**os.environ, "JAXFLARE_CACHE_DIR": str(tmp_path / "path-system-cache"), "MPLBACKEND": "Agg"}
    env.pop("JAX_ENABLE_X64", None)
    run = subprocess.run(
        [sys.executable, "-c", RUNNER, str(tmp_path / "blocks.json"), str(README), str(tmp_path / "facts.json")],
        check=False, cwd=work, env=env, capture_output=True, text=True, timeout=900,
    )
    if run.returncode != 0:
        pytest.fail(f"README.md's Python examples failed (the traceback names the README line):\n{run.stderr[-6000:]}")

    # what the README's comments and prose say about the results
    facts = json.loads((tmp_path / "facts.json").read_text(encoding="utf-8"))
    assert facts["focal_length"] == pytest.approx(99.91, abs=0.005)
    assert facts["num_interfaces"] == 10
    assert facts["first_ghost_paths"] == [[1, 0], [2, 0], [2, 1]]
    width, height = facts["resolution"]
    assert facts["image_shape"] == [height, width, 4]
    layers = facts["layer_shapes"]
    assert layers["core"] == [height, width, 3] and layers["variance"] == [height, width, 1]
    assert "flares_merged" in layers
    flares = [name for name in layers if name not in ("core", "flares_merged", "variance")]
    assert flares and all(re.fullmatch(r"flare_\d\d_\d\d", name) for name in flares)
    assert facts["preview_shape"] == [height, width, 3]
    for written in ("flare.exr", "flare.png", "fitted.json", "fitted_render.exr"):
        assert (work / written).is_file(), f"the README's examples should have written {written}"
    assert facts["trusted_given"] and facts["systems"] == [[4, 2]] and facts["fitted_tints"] > 0


# ---------------------------------------------------------------- the command lines


def test_the_sh_examples_use_every_subcommand():
    used = {tuple(subcommand_path(jaxflare_argv(command))) for _, command in JAXFLARE_LINES}
    missing = set(leaf_subcommands(build_parser())) - used
    assert not missing, f"README.md has no ```sh example of: {', '.join('jaxflare ' + ' '.join(m) for m in sorted(missing))}"


@pytest.mark.parametrize(("line", "command"), JAXFLARE_LINES, ids=[f"README.md:{line}" for line, _ in JAXFLARE_LINES])
def test_sh_command_parses_and_its_options_exist(line, command):
    argv = jaxflare_argv(command)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            build_parser().parse_args(argv)
        except SystemExit:
            pytest.fail(f"README.md:{line}: `{command}` is not a valid jaxflare command line: {err.getvalue().strip()}")
    path = subcommand_path(argv)
    text = help_text(path)
    for word in argv[len(path) :]:
        if word.startswith("-") and not re.fullmatch(r"-\d.*", word):
            option = word.split("=", 1)[0]
            assert names_option(text, option), f"README.md:{line}: `jaxflare {' '.join(path)} --help` does not list {option}"
    for word in argv[len(path) :]:  # files the command reads from the repository must be there
        if re.match(r"(jaxflare|tests|benchmarks|lenses/FORMAT)", word) and "/" in word:
            assert (ROOT / word).exists(), f"README.md:{line}: {word} does not exist"


@pytest.mark.parametrize(("line", "synopsis"), SYNOPSES, ids=[f"README.md:{line}" for line, _ in SYNOPSES])
def test_synopsis_lists_exactly_the_options_of_its_subcommand(line, synopsis):
    words = synopsis.split()[1:]
    path = subcommand_path(words)
    leaves = leaf_subcommands(build_parser())
    assert tuple(path) in leaves, f"README.md:{line}: no subcommand `jaxflare {' '.join(path)}`"
    named = set(re.findall(r"(?<![\w-])(--?[a-zA-Z][\w-]*)", " ".join(words[len(path) :])))
    text = help_text(path)
    for option in sorted(named):
        assert names_option(text, option), f"README.md:{line}: `jaxflare {' '.join(path)} --help` does not list {option}"
    options = {
        max(action.option_strings, key=len)
        for action in leaves[tuple(path)]._actions
        if action.option_strings and not isinstance(action, argparse._HelpAction)
    }
    spelled = {option for option in named} | {
        max(a.option_strings, key=len) for a in leaves[tuple(path)]._actions if set(a.option_strings) & named
    }
    missing = options - spelled
    assert not missing, f"README.md:{line}: the synopsis of `jaxflare {' '.join(path)}` leaves out {', '.join(sorted(missing))}"


def test_every_subcommand_has_a_synopsis():
    covered = {tuple(subcommand_path(synopsis.split()[1:])) for _, synopsis in SYNOPSES}
    missing = set(leaf_subcommands(build_parser())) - covered
    assert not missing, f"README.md: no synopsis (```text block) of: {', '.join(' '.join(m) for m in sorted(missing))}"


def test_make_targets_and_other_commands_exist():
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    for line, command in SH_LINES:
        words = shlex.split(command, comments=True)
        if words[:1] == ["make"]:
            for target in (w for w in words[1:] if not w.startswith("-") and "=" not in w):
                assert re.search(rf"^{re.escape(target)}:", makefile, re.MULTILINE), f"README.md:{line}: no Makefile target {target!r}"
        elif "pytest" in words:
            for word in words:
                if word.endswith(".py"):
                    assert (ROOT / word).is_file(), f"README.md:{line}: no test file {word}"


# ---------------------------------------------------------------- links and the file-format examples


def github_anchor(heading: str) -> str:
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_relative_links_and_pictures_exist():
    text = re.sub(r"^```.*?^```", "", README.read_text(encoding="utf-8"), flags=re.DOTALL | re.MULTILINE)
    links = re.findall(r"\]\(([^)\s]+)\)", text)
    assert links
    for link in links:
        if re.match(r"[a-z]+:", link):
            continue
        target, _, anchor = link.partition("#")
        path = ROOT / target if target else README
        assert path.exists(), f"README.md links to {target}, which does not exist"
        if anchor:
            headings = re.findall(r"^#+ (.*)$", path.read_text(encoding="utf-8"), re.MULTILINE)
            assert anchor in {github_anchor(h) for h in headings}, f"README.md links to {link}: no such heading"


def toml_blocks() -> list[Block]:
    return [block for block in code_blocks() if block.language == "toml"]


@pytest.mark.parametrize("block", toml_blocks(), ids=lambda b: f"README.md:{b.line}")
def test_toml_examples_load(block):
    data = tomllib.loads(block.text)
    if "camera" in data:
        from jaxflare.scenes import camera_lens, demo_scene_path, scene_from_dict

        scene = scene_from_dict(data)
        assert camera_lens(scene.camera).num_interfaces > 0
        with open(demo_scene_path(), "rb") as handle:
            assert data == tomllib.load(handle), f"README.md:{block.line}: the scene shown as the demo scene differs from jaxflare/scenes/demo.toml"
    else:
        assert "surfaces" in data, f"README.md:{block.line}: a ```toml block must be a lens file or a scene file"
        lens = jaxflare.build_lens(jaxflare.parse_lens_toml(block.text, "README.md"))
        assert lens.focal_length() == pytest.approx(data["focal_length_mm"], rel=0.015)
        assert lens.widest_f_number == pytest.approx(data["f_number"], rel=0.02)
        assert float(lens.sensor_z_mm) == pytest.approx(lens.sensor_z_for_focus(), abs=0.01 * abs(lens.focal_length()))


# ---------------------------------------------------------------- quoted signatures and names


def test_the_quoted_render_signature_matches_the_code():
    """The README quotes the full signature of jaxflare.render: same parameters, same kinds
    (positional or keyword-only), same defaults."""
    import ast
    import inspect

    text = re.sub(r"^```.*?^```", "", README.read_text(encoding="utf-8"), flags=re.DOTALL | re.MULTILINE)
    quoted = re.findall(r"`jf\.render\(([^`]*?)\)`", text, re.DOTALL)
    assert len(quoted) == 1, "README.md should quote the signature of jf.render once"
    tree = ast.parse(f"def f({' '.join(quoted[0].split())}): pass").body[0].args
    stated = {}
    positional = tree.posonlyargs + tree.args
    for arg, default in zip(positional, [None] * (len(positional) - len(tree.defaults)) + tree.defaults):
        stated[arg.arg] = ("positional", default)
    for arg, default in zip(tree.kwonlyargs, tree.kw_defaults):
        stated[arg.arg] = ("keyword", default)
    actual = inspect.signature(jaxflare.render).parameters
    assert list(stated) == list(actual), f"README.md: jf.render's parameters are {list(actual)}, the README says {list(stated)}"
    for parameter in actual.values():
        kind, default = stated[parameter.name]
        expected_kind = "keyword" if parameter.kind is inspect.Parameter.KEYWORD_ONLY else "positional"
        assert kind == expected_kind, f"README.md: jf.render: {parameter.name} is {expected_kind} in the code"
        if parameter.default is inspect.Parameter.empty:
            assert default is None, f"README.md: jf.render: {parameter.name} has no default in the code"
        else:
            value = ast.literal_eval(default)
            assert value == parameter.default, f"README.md: jf.render: {parameter.name} defaults to {parameter.default!r}, not {value!r}"


def resolve(dotted: str):
    """The object a dotted name of the README stands for (importing private submodules if needed)."""
    import importlib

    parts = dotted.split(".")
    target = importlib.import_module(parts[0])
    for k, part in enumerate(parts[1:], start=1):
        if not hasattr(target, part):
            target = importlib.import_module(".".join(parts[: k + 1]))
        else:
            target = getattr(target, part)
    return target


def test_every_api_name_the_readme_mentions_exists():
    """``jaxflare.X``, ``jf.X`` and ``fitting.X`` in the prose and the examples name real things."""
    text = README.read_text(encoding="utf-8")
    names = set(re.findall(r"(?<![\w./-])((?:jaxflare|jf|fitting)(?:\.[A-Za-z_]\w*)+)", text))
    assert len(names) > 20
    for name in sorted(names):
        dotted = re.sub(r"^jf\.", "jaxflare.", name)
        try:
            resolve(dotted)
        except (AttributeError, ModuleNotFoundError):
            pytest.fail(f"README.md mentions {name}, which does not exist")
