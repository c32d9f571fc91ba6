"""The scene format document (jaxflare/scenes/FORMAT.md) stays true to the code: its TOML examples
load and build their lenses, its Python example builds the same scene, it mentions every key the
scene reader accepts (the hood, distortion and geometry tables' keys included) with the code's
defaults, and the file errors it quotes are the code's."""

import dataclasses
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

import jaxflare
from jaxflare.scenes import (
    CAMERA_KEYS,
    LIGHT_KEYS,
    Distortion,
    Geometry,
    Hood,
    RenderSettings,
    SceneError,
    camera_lens,
    scene_from_dict,
)

FORMAT_MD = Path(jaxflare.__file__).parent / "scenes" / "FORMAT.md"
TOML_BLOCK = re.compile(r"^```toml\n(.*?)^```", re.DOTALL | re.MULTILINE)
PYTHON_BLOCK = re.compile(r"^```python\n(.*?)^```", re.DOTALL | re.MULTILINE)
TABLE_KEYS = {"hood": Hood, "distortion": Distortion, "geometry": Geometry}
"""The sub-tables of a scene and the classes whose fields are their keys."""
A_LIGHT = {"kind": "point", "position_m": [1.0, 0.5, -10.0]}


def toml_blocks():
    return TOML_BLOCK.findall(FORMAT_MD.read_text(encoding="utf-8"))


def scene_blocks():
    return [block for block in toml_blocks() if re.search(r"^\[camera\]", block, re.MULTILINE)]


def camera_snippets():
    """Blocks with no table header: keys of a [camera] table (e.g. surface_coatings)."""
    return [block for block in toml_blocks() if not re.search(r"^\[", block, re.MULTILINE)]


def geometry_snippets():
    """Blocks whose only table headers are [[geometry]]."""
    return [block for block in toml_blocks() if set(re.findall(r"^(\[\[?[^\]]*\]\]?)", block, re.MULTILINE)) == {"[[geometry]]"}]


def section(heading: str) -> str:
    """The prose and tables of a section (code blocks left out, so their comments are not taken
    for headings), from its heading to the next heading of the same or a higher level."""
    text = re.sub(r"^```.*?^```\n", "", FORMAT_MD.read_text(encoding="utf-8"), flags=re.DOTALL | re.MULTILINE)
    level = heading.split(" ")[0]
    start = text.index(f"\n{heading}\n")
    following = re.search(rf"^#{{1,{len(level)}}} ", text[start + len(heading) + 2 :], re.MULTILINE)
    return text[start : start + len(heading) + 2 + following.start()] if following else text[start:]


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
    """Each [camera] snippet sets something, every key it sets reaches the camera (not ignored),
    and coatings it names change the lens that is built."""
    snippet = tomllib.loads(camera_snippets()[index])
    assert snippet
    scene = scene_from_dict({"camera": {"lens": "zeiss_biotar", **snippet}, "light": [A_LIGHT]})
    plain = scene_from_dict({"camera": {"lens": "zeiss_biotar"}, "light": [A_LIGHT]})
    for key in snippet:
        assert getattr(scene.camera, key) != getattr(plain.camera, key), key
    lens, plain_lens = camera_lens(scene.camera), camera_lens(plain.camera)
    if {"coating", "surface_coatings"} & set(snippet):
        assert not np.array_equal(np.asarray(lens.coating_thicknesses_nm), np.asarray(plain_lens.coating_thicknesses_nm))


def test_the_geometry_examples_load():
    assert geometry_snippets(), "FORMAT.md has no [[geometry]] example"
    for block in geometry_snippets():
        tables = tomllib.loads(block)["geometry"]
        scene = scene_from_dict({"camera": {"lens": "zeiss_biotar"}, "light": [A_LIGHT], "geometry": tables})
        assert len(scene.geometry) == len(tables) and all(isinstance(g, Geometry) for g in scene.geometry)


def test_the_minimal_example_is_minimal():
    """The first scene example uses only the required keys, so every default in it is the code's."""
    data = tomllib.loads(scene_blocks()[0])
    assert set(data) == {"camera", "light"} and set(data["camera"]) == {"lens"}


def test_the_complete_example_shows_every_key():
    text = scene_blocks()[1]
    for key in list(CAMERA_KEYS) + list(LIGHT_KEYS) + [f.name for f in dataclasses.fields(RenderSettings)]:
        assert re.search(rf"^\s*#?\s*{key}\s*=", text, re.MULTILINE), f"the complete example does not show {key!r}"


def test_the_complete_example_shows_every_hood_distortion_and_geometry_key():
    text = scene_blocks()[1]
    assert re.search(r"^\[\[geometry\]\]", text, re.MULTILINE), "the complete example has no [[geometry]] table"
    for table, cls in TABLE_KEYS.items():
        for field in dataclasses.fields(cls):
            assert re.search(rf"\b{field.name}\s*=", text), f"the complete example does not show {table}.{field.name}"
    scene = scene_from_dict(tomllib.loads(text))
    assert scene.camera.dirt_map and isinstance(scene.camera.hood, Hood) and isinstance(scene.camera.distortion, Distortion)
    assert scene.geometry and scene.geometry[0].transform is not None


def test_the_python_example_builds_the_complete_example():
    """The Python equivalent (up to the render) builds the scene of the complete TOML example's
    camera, hood, distortion, dirt and geometry."""
    code = next(block for block in PYTHON_BLOCK.findall(FORMAT_MD.read_text(encoding="utf-8")) if "jf.Scene(" in block)
    namespace = {}
    exec(code.split("\nresult = ")[0], namespace)  # noqa: S102 - the document's own example
    built = namespace["scene"]
    toml = scene_from_dict(tomllib.loads(scene_blocks()[1]))
    for name in ("lens", "f_number", "resolution", "dirt_map", "hood", "distortion"):
        assert getattr(built.camera, name) == getattr(toml.camera, name), name
    assert built.geometry == toml.geometry


@pytest.mark.parametrize(
    "key",
    sorted(set(CAMERA_KEYS) | set(LIGHT_KEYS) | {f.name for f in dataclasses.fields(RenderSettings)}),
)
def test_every_key_is_documented(key):
    assert f"`{key}`" in FORMAT_MD.read_text(encoding="utf-8"), f"FORMAT.md does not document {key!r}"


@pytest.mark.parametrize(
    ("table", "key"), [(table, f.name) for table, cls in TABLE_KEYS.items() for f in dataclasses.fields(cls)]
)
def test_every_table_key_is_documented_with_its_default(table, key):
    """Each key of hood, distortion and [[geometry]] has a row in its section's table, giving the
    code's default where the code has one."""
    heading = "## `[[geometry]]`" if table == "geometry" else f"### `{table}`"
    text = section(heading)
    row = re.search(rf"^\| `{key}` \|([^|]*)\|([^|]*)\|([^|]*)\|", text, re.MULTILINE)
    assert row, f"the {table} section has no table row for {key!r}"
    field = next(f for f in dataclasses.fields(TABLE_KEYS[table]) if f.name == key)
    if field.default is dataclasses.MISSING:
        assert "required" in row.group(3), f"{table}.{key} is required"
    elif field.default is not None:
        default = field.default
        shown = f'`"{default}"`' if isinstance(default, str) else f"{default:g}"
        assert row.group(3).strip() == shown, f"{table}.{key}: the table gives {row.group(3).strip()!r}, the code {shown}"


@pytest.mark.parametrize(
    ("camera", "geometry"),
    [({"dirt_map": "dust.png"}, []), ({}, [{"file": "set/wall.obj"}])],
    ids=["dirt_map", "geometry"],
)
def test_the_documented_missing_file_errors_are_the_code_s(camera, geometry):
    """Missing files are reported when the render starts (the scene only records their paths);
    the messages FORMAT.md quotes are the ones the code gives."""
    from jaxflare.rendering import scene_effects

    source = "/shots/sh010/lamp.toml"
    assert not Path(source).parent.exists()
    scene = scene_from_dict(
        {"camera": {"lens": "zeiss_biotar", **camera}, "light": [A_LIGHT], "geometry": geometry}, source=source
    )
    with pytest.raises(SceneError) as error:
        scene_effects(scene, camera_lens(scene.camera), 0.01)
    assert f"jaxflare: error: {error.value}\n" in FORMAT_MD.read_text(encoding="utf-8")


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
