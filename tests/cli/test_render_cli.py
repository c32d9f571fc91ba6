"""``jaxflare render`` on the command line: outputs, summary and errors."""

import numpy as np

import jaxflare as jf
from jaxflare.cli import main

SCENE = """
[camera]
lens = "zeiss_biotar"
f_number = 5.6
aperture_blades = 5
resolution = [96, 64]
look_at_m = [0.0, 0.0, -10.0]

[[light]]
kind = "disk"
position_m = [0.4, 0.3, -10.0]
radius_m = 0.05
rgb = [1.0, 0.8, 0.6]
intensity = 100.0
"""


def test_render_command_writes_exr_and_png(tmp_path, capsys):
    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE)
    out = tmp_path / "out" / "flare.exr"
    assert main(["render", str(scene), "-o", str(out), "--png", "--seed", "3", "--samples", "40000"]) == 0
    printed = capsys.readouterr().out
    assert "sensor hit rate" in printed and "layers:" in printed and str(out) in printed
    layers, header = jf.read_exr(out)
    assert layers[""].shape == (64, 96, 4) and "core" in layers and "flares_merged" in layers
    assert '"seed": 3' in header["jaxflare/settings"]
    assert (tmp_path / "out" / "flare.png").exists()
    again = jf.render(jf.load_scene(scene), seed=3, samples=40000)
    np.testing.assert_array_equal(layers["core"], again.layers["core"].astype(np.float16).astype(np.float32))


def test_render_command_reports_bad_input(tmp_path, capsys):
    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE.replace("f_number = 5.6", "f_number = 0.5"))
    assert main(["render", str(scene), "-o", str(tmp_path / "x.exr")]) == 2
    error = capsys.readouterr().err
    assert "camera.f_number" in error and "faster than" in error
    assert not (tmp_path / "x.exr").exists()
    assert main(["render", str(tmp_path / "missing.toml"), "-o", str(tmp_path / "x.exr")]) == 2
    assert main(["render", str(scene), "-o", str(tmp_path / "x.png")]) == 2
