"""The scene format document (jaxflare/scenes/FORMAT.md) stays true to the code: its TOML examples
load and build their lenses, and it mentions every key the scene reader accepts."""

import dataclasses
import re
import tomllib
from pathlib import Path

import pytest

import jaxflare
from jaxflare._scene import _CAMERA_KEYS, _LIGHT_KEYS, RenderSettings, camera_lens, scene_from_dict

FORMAT_MD = Path(jaxflare.__file__).parent / "scenes" / "FORMAT.md"
TOML_BLOCK = re.compile(r"^```toml\n(.*?)^```", re.DOTALL | re.MULTILINE)


def toml_blocks():
    return TOML_BLOCK.findall(FORMAT_MD.read_text(encoding="utf-8"))


def scene_blocks():
    return [block for block in toml_blocks() if re.search(r"^\[camera\]", block, re.MULTILINE)]


def camera_snippets():
    """Blocks with no table header: keys of a [camera] table (e.g. surface_coatings)."""
    return [block for block in toml_blocks() if not re.search(r"^\[", block, re.MULTILINE)]


def test_the_document_ships_with_the_package_and_has_examples():
    assert FORMAT_MD.is_file()
    assert len(scene_blocks()) >= 2  # the minimal and the complete example


@pytest.mark.parametrize("index", range(len(scene_blocks())))
def test_every_scene_example_loads_and_builds_its_lens(index):
    scene = scene_from_dict(tomllib.loads(scene_blocks()[index]))
    lens = camera_lens(scene.camera)
    assert lens.num_interfaces > 0 and scene.lights


@pytest.mark.parametrize("index", range(len(camera_snippets())))
def test_every_camera_snippet_loads_and_builds_its_lens(index):
    camera = {"lens": "zeiss_biotar", **tomllib.loads(camera_snippets()[index])}
    scene = scene_from_dict({"camera": camera, "light": [{"kind": "point", "position_m": [1.0, 0.5, -10.0]}]})
    camera_lens(scene.camera)


def test_the_minimal_example_is_minimal():
    """The first scene example uses only the required keys, so every default in it is the code's."""
    data = tomllib.loads(scene_blocks()[0])
    assert set(data) == {"camera", "light"} and set(data["camera"]) == {"lens"}


def test_the_complete_example_shows_every_key():
    text = scene_blocks()[1]
    for key in list(_CAMERA_KEYS) + list(_LIGHT_KEYS) + [f.name for f in dataclasses.fields(RenderSettings)]:
        assert re.search(rf"^\s*#?\s*{key}\s*=", text, re.MULTILINE), f"the complete example does not show {key!r}"


@pytest.mark.parametrize(
    "key",
    sorted(set(_CAMERA_KEYS) | set(_LIGHT_KEYS) | {f.name for f in dataclasses.fields(RenderSettings)}),
)
def test_every_key_is_documented(key):
    assert f"`{key}`" in FORMAT_MD.read_text(encoding="utf-8"), f"FORMAT.md does not document {key!r}"


def test_documented_defaults_match_the_code():
    text = FORMAT_MD.read_text(encoding="utf-8")
    for field in dataclasses.fields(RenderSettings):
        default = field.default
        if default is None:
            continue
        shown = f'"{default}"' if isinstance(default, str) else str(default).lower()
        row = re.search(rf"^\| `{field.name}` \|[^|]*\| `?{re.escape(shown)}`? \|", text, re.MULTILINE)
        assert row, f"the [render] table does not give {field.name}'s default {shown}"
    for preset, description in jaxflare.COATING_PRESETS.items():
        assert f'| `"{preset}"` | {description} |' in text
