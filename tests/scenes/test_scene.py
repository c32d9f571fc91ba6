"""Scene files and objects: the demo scene, the TOML format, and errors that name the bad key."""

import math

import pytest

import jaxflare as jf
from jaxflare.scenes import camera_lens, demo_scene_path, scene_from_dict

BASE = {
    "camera": {"lens": "zeiss_biotar", "f_number": 4.0, "resolution": [64, 48], "look_at_m": [0.0, 0.0, -10.0]},
    "light": [{"kind": "point", "position_m": [0.5, 0.2, -10.0], "intensity": 3.0}],
}


def scene_with(section, key, value):
    data = {"camera": dict(BASE["camera"]), "light": [dict(BASE["light"][0])]}
    target = data["camera"] if section == "camera" else data["light"][0] if section == "light" else data.setdefault("render", {})
    if value is None:
        target.pop(key, None)
    else:
        target[key] = value
    return scene_from_dict(data, source="scene.toml")


def test_demo_scene_loads_and_matches_its_documented_settings():
    scene = jf.load_scene(demo_scene_path())
    assert scene.camera.lens == "zeiss_biotar" and scene.camera.f_number == 2.8 and scene.camera.aperture_blades == 6
    assert scene.lights[0].kind == "sphere" and scene.lights[0].temperature_k == 4200.0
    assert jf.load_scene("demo") == scene


def test_python_and_toml_scenes_are_the_same():
    from_toml = scene_from_dict(BASE)
    in_python = jf.Scene(
        camera=jf.Camera(lens="zeiss_biotar", f_number=4.0, resolution=(64, 48), look_at_m=(0.0, 0.0, -10.0)),
        lights=(jf.Light(kind="point", position_m=(0.5, 0.2, -10.0), intensity=3.0),),
    )
    assert from_toml == in_python


@pytest.mark.parametrize(
    "section, key, value, message",
    [
        ("camera", "lens", "no_such_lens", r"camera\.lens: no lens named 'no_such_lens'"),
        ("camera", "f_number", 0.7, r"camera\.f_number: f/0\.7 is faster than"),
        ("camera", "f_number", "fast", r"camera\.f_number: must be a number"),
        ("camera", "aperture_blades", 2, r"camera\.aperture_blades: must be 0 \(circular iris\) or at least 3"),
        ("camera", "resolution", [64], r"camera\.resolution: must be \[width, height\]"),
        ("camera", "coating", "gold", r"camera\.coating: must be one of .*'multilayer'"),
        ("camera", "f_numbr", 4.0, r"camera\.f_numbr: unknown key \(did you mean 'f_number'\?\)"),
        ("light", "intensity", -1.0, r"light\[0\]\.intensity: must be >= 0"),
        ("light", "colour", [1, 0, 0], r"light\[0\]\.colour: unknown key"),
        ("light", "position_m", [0.0, 0.0, 5.0], r"light\[0\]: is behind the camera"),
        ("light", "kind", "laser", r"light\[0\]\.kind: must be one of 'point', 'sphere', 'disk', 'directional'"),
        ("light", "rgb", [1.0, 0.5], r"light\[0\]\.rgb: must be a list of 3 numbers"),
        ("light", "temperature_k", 100.0, r"light\[0\]\.temperature_k: must be within 500-50000 K"),
        ("render", "quality", "ultra", r"render\.quality: must be one of 'preview', 'production'"),
        ("render", "colour_space", "XYZ", r"render\.colour_space"),
        ("render", "speed", 1, r"render\.speed: unknown key"),
        # issue 17: values beyond physical bounds or stated maxima, scalars where lists belong
        ("camera", "f_number", 0.1, r"camera\.f_number: must be >= 0\.5, got 0\.1"),
        ("camera", "focus_distance_m", 0.001, r"camera\.focus_distance_m: .* cannot focus at 0\.001 m: the image would not lie behind the lens"),
        ("camera", "aperture_blades", 1000, r"camera\.aperture_blades: must be at most 64, got 1,000"),
        ("camera", "aperture_blades", 100000, r"camera\.aperture_blades: must be at most 64"),
        ("camera", "surface_coatings", [{"surfaces": [1], "layers": [[0.5, 100.0]]}], r"layers\[0\]: must be \[index 1 \.\. 4, thickness_nm"),
        ("camera", "surface_coatings", 3, r"camera\.surface_coatings: must be a list of tables"),
        ("camera", "coating_tints", 3, r"camera\.coating_tints: must be a list of tables"),
        ("camera", "resolution", 64, r"camera\.resolution: must be \[width, height\]"),
        ("camera", "resolution", [16385, 100], r"camera\.resolution\[0\]: must be at most 16,384"),
        ("light", "intensity", 1e31, r"light\[0\]\.intensity: must be at most 1e\+30"),
        ("light", "intensity", 1e400, r"light\[0\]\.intensity: must be finite"),
        ("light", "spectrum", {"wavelengths_nm": 500, "values": 1}, r"light\[0\]\.spectrum\.wavelengths_nm: must be a list"),
        ("render", "samples", 2**63, r"render\.samples: must be at most 4,294,967,296"),
        ("render", "max_flare_layers", 10**6, r"render\.max_flare_layers: must be at most 256"),
    ],
)
def test_bad_scenes_name_the_key_and_what_is_valid(section, key, value, message):
    with pytest.raises(jf.SceneError, match=message):
        scene = scene_with(section, key, value)
        camera_lens(scene.camera)


def test_scene_errors_name_the_file(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text('[camera]\nlens = "zeiss_biotar"\n[[light]]\nkind = "point"\nposition_m = [0, 0, 3]\n')
    with pytest.raises(jf.SceneError, match=r"bad\.toml: light\[0\]: is behind the camera"):
        jf.load_scene(path)
    path.write_text("[camera\n")
    with pytest.raises(jf.SceneError, match="not valid TOML"):
        jf.load_scene(path)
    with pytest.raises(FileNotFoundError, match="missing.toml"):
        jf.load_scene(tmp_path / "missing.toml")


def test_camera_settings_act_on_the_lens_physically():
    camera = jf.Camera(lens="nikon_afs_28_70_zoom", focal_length_mm=50.0, f_number=5.6, aperture_blades=7, aperture_rotation_deg=10.0, focus_distance_m=3.0)
    lens = camera_lens(camera)
    assert lens.focal_length() == pytest.approx(50.0, rel=1e-5)
    assert lens.f_number() == pytest.approx(5.6, rel=1e-3)
    assert lens.aperture_blades == 7 and float(lens.aperture_rotation_rad) == pytest.approx(math.radians(10.0))
    infinity = camera_lens(jf.Camera(lens="nikon_afs_28_70_zoom", focal_length_mm=50.0))
    assert float(lens.sensor_z_mm) > float(infinity.sensor_z_mm)  # focusing closer moves the sensor back
    coated = camera_lens(jf.Camera(lens="zeiss_biotar", coating="uncoated"))
    assert float(coated.coating_thicknesses_nm.sum()) == 0.0


def test_camera_orientation():
    forward = jf.Camera(lens="zeiss_biotar", position_m=(1.0, 2.0, 3.0), look_at_m=(1.0, 2.0, -7.0)).world_to_camera()
    assert forward @ [0, 0, -1] == pytest.approx([0, 0, -1])  # the view direction is lens -z (light travels along +z)
    assert forward @ [1, 0, 0] == pytest.approx([1, 0, 0]) and forward @ [0, 1, 0] == pytest.approx([0, 1, 0])
    turned = jf.Camera(lens="zeiss_biotar", rotation_deg=(90.0, 0.0, 0.0)).world_to_camera()
    # yawed 90 degrees to the left, the camera looks down -x
    assert turned @ [-1, 0, 0] == pytest.approx([0, 0, -1], abs=1e-12)
