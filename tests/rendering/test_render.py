"""The flare renderer: closed-form radiometry, symmetry, iris shapes, linearity, determinism, EXR output.

Renders here are small (a few hundred pixels across, 10^5 - 10^6 samples) and use exact tracing
unless a test is about path systems, so the suite stays fast on a 2-core CPU.
"""

import math

import equinox as eqx
import numpy as np
import pytest

import jaxflare as jf
from jaxflare.colour import rgb_response_at, spectral_table


def make_scene(light=None, lights=None, render=None, **camera):
    """A small Biotar scene; ``render`` holds RenderSettings fields (``sampling="uniform"`` where a
    test needs the same samples whatever the light intensities: adaptive tables follow the energy)."""
    options = dict(lens="zeiss_biotar", f_number=8.0, resolution=(128, 96), look_at_m=(0.0, 0.0, -10.0))
    options.update(camera)
    if lights is None:
        lights = (light or jf.Light(kind="directional", direction=(0.05, 0.0, -1.0)),)
    return jf.Scene(camera=jf.Camera(**options), lights=tuple(lights), render=jf.RenderSettings(**(render or {})))


def centroid(image):
    luminance = image[..., :3].sum(axis=-1) if image.ndim == 3 else image
    rows, columns = np.indices(luminance.shape)
    total = luminance.sum()
    return (columns * luminance).sum() / total + 0.5, (rows * luminance).sum() / total + 0.5


def luminance(image, colour_space="ACEScg"):
    return image[..., :3] @ np.asarray(spectral_table(colour_space).luminance_weights)


def angular_harmonics(image, orders, centre=None):
    """|sum I r^2 exp(i m phi)| / sum I r^2 about the centre, for each order m."""
    value = image[..., :3].sum(axis=-1)
    height, width = value.shape
    cx, cy = centre if centre is not None else (width / 2, height / 2)
    rows, columns = np.indices(value.shape)
    dx, dy = columns + 0.5 - cx, rows + 0.5 - cy
    phi = np.arctan2(dy, dx)
    weight = value * (dx * dx + dy * dy)
    return {m: abs(np.sum(weight * np.exp(1j * m * phi))) / np.sum(weight) for m in orders}


def transmission_luminance(lens, path):
    """Luminance-weighted mean of a path's on-axis Fresnel factor for white light (ACEScg)."""
    table = spectral_table("ACEScg")
    grid = np.asarray(table.wavelength_nm)
    factor = np.asarray(jf.path_fresnel_factor(lens, path, grid))
    white = np.asarray(rgb_response_at(table, grid)) @ np.ones(3)
    weight = white @ np.asarray(table.luminance_weights)
    return float(np.sum(factor * weight) / np.sum(weight))


# --------------------------------------------------------------------------- radiometry


def test_sphere_light_core_obeys_the_camera_equation():
    """An extended light of radiance L images to pixels of value L T (camera equation E = pi L T / 4N^2)."""
    radiance = 50.0
    light = jf.Light(kind="sphere", position_m=(0.0, 0.0, -10.0), radius_m=0.25, intensity=radiance, rgb=(1.0, 1.0, 1.0))
    result = jf.render(make_scene(light), samples=2**21, method="exact", paths=[(5, 0)], seed=1)
    core = luminance(result.layers["core"])
    height, width = core.shape
    rows, columns = np.indices(core.shape)
    pitch = result.statistics["pixel_pitch_mm"]
    focal = jf.load_lens("zeiss_biotar").focal_length()
    image_radius_px = focal * 0.25 / 10.0 / pitch  # EFL x angular radius
    central = (columns + 0.5 - width / 2) ** 2 + (rows + 0.5 - height / 2) ** 2 < (0.7 * image_radius_px) ** 2
    expected = radiance * transmission_luminance(jf.load_lens("zeiss_biotar"), None)
    assert np.mean(core[central]) == pytest.approx(expected, rel=0.04)  # about 1000 samples: 2 % noise
    # and the whole image of the disc: area pi (f theta)^2 at that radiance
    assert core.sum() * pitch**2 == pytest.approx(expected * math.pi * (focal * 0.25 / 10.0) ** 2, rel=0.03)


def test_point_light_core_energy_matches_the_entrance_pupil():
    """sum(core) x pixel area = I T (f / d)^2 x 1e6: the flux a point light sends through the entrance pupil."""
    intensity, distance_m = 2.0, 10.0
    light = jf.Light(kind="point", position_m=(0.0, 0.0, -distance_m), intensity=intensity, rgb=(1.0, 1.0, 1.0))
    result = jf.render(make_scene(light), samples=2**19, method="exact", paths=[(5, 0)], seed=2)
    lens = jf.load_lens("zeiss_biotar").with_f_number(8.0)
    pitch = result.statistics["pixel_pitch_mm"]
    total = luminance(result.layers["core"]).sum() * pitch**2
    focal = lens.focal_length()
    z_pupil, _ = lens.entrance_pupil()
    expected = intensity * transmission_luminance(lens, None) * 1e6 * (focal / (distance_m * 1000.0 + z_pupil)) ** 2
    assert total == pytest.approx(expected, rel=0.03)


def test_layer_energy_is_linear_in_light_intensity():
    uniform = dict(sampling="uniform")
    scene = make_scene(jf.Light(kind="directional", direction=(0.08, 0.03, -1.0), intensity=1.0), render=uniform)
    brighter = make_scene(jf.Light(kind="directional", direction=(0.08, 0.03, -1.0), intensity=3.0), render=uniform)
    a = jf.render(scene, samples=2**17, method="exact", seed=3)
    b = jf.render(brighter, samples=2**17, method="exact", seed=3)
    assert a.layers.keys() == b.layers.keys()
    for name in a.layers:
        factor = 9.0 if name == "variance" else 3.0  # variance: float32 sums of squares, to 1e-4
        np.testing.assert_allclose(b.layers[name], factor * a.layers[name], rtol=1e-4 if name == "variance" else 1e-5, atol=1e-6 * b.layers[name].max())
    assert b.image[..., :3].sum() == pytest.approx(3.0 * a.image[..., :3].sum(), rel=1e-5)


def test_flare_multiplier_scales_flares_only_and_flag_removes_a_light():
    one = jf.Light(kind="directional", direction=(0.08, 0.0, -1.0), flare_intensity=2.0)
    off = jf.Light(kind="directional", direction=(-0.08, 0.0, -1.0), flare=False, intensity=100.0)
    with_off = jf.render(make_scene(lights=(one, off)), samples=2**16, method="exact", seed=4)
    alone = jf.render(make_scene(lights=(one,)), samples=2**16, method="exact", seed=4)
    np.testing.assert_allclose(with_off.image, alone.image, rtol=1e-6, atol=1e-9)
    with pytest.raises(jf.SceneError, match="no light has flare = true"):
        jf.render(make_scene(lights=(off,)), samples=2**10, method="exact")


# --------------------------------------------------------------------------- geometry


def _reference_centroid_px(lens, path, direction, pitch, width, height):
    """Throughput-weighted centroid of a ghost from a dense exact trace (independent of the sampler)."""
    direction = np.asarray(direction, float) / np.linalg.norm(direction)
    radius = float(lens.semi_aperture_mm[0]) * 1.2
    g = np.linspace(-radius, radius, 160)
    x, y = np.meshgrid(g, g)
    keep = x * x + y * y <= radius * radius
    origins = np.stack([x[keep], y[keep], np.zeros(keep.sum())], axis=-1) - 20.0 * direction
    directions = np.broadcast_to(direction, origins.shape)
    result = jf.trace(lens, origins, directions, 550.0, path)
    w = np.asarray(result.throughput) * np.asarray(result.valid)
    sx = np.sum(w * np.asarray(result.positions[:, 0])) / w.sum()
    sy = np.sum(w * np.asarray(result.positions[:, 1])) / w.sum()
    return -sx / pitch + width / 2, sy / pitch + height / 2


@pytest.mark.parametrize("angle_deg", [3.0, 6.0])
def test_ghost_lands_where_the_exact_tracer_puts_it(angle_deg):
    """Light to the right: the core moves right, and a ghost's centroid matches a dense exact trace."""
    lens = jf.load_lens("zeiss_biotar").with_f_number(8.0)
    path = (7, 4)
    toward = (math.sin(math.radians(angle_deg)), 0.0, -math.cos(math.radians(angle_deg)))
    scene = make_scene(jf.Light(kind="directional", direction=toward), resolution=(192, 128))
    result = jf.render(scene, samples=2**18, method="exact", paths=[path], seed=5)
    pitch = result.statistics["pixel_pitch_mm"]
    # the lens frame is the camera frame (x right, y up), the sensor image is inverted
    ghost_in_lens_frame = (-toward[0], -toward[1], -toward[2])
    expected = _reference_centroid_px(lens, path, ghost_in_lens_frame, pitch, 192, 128)
    got = centroid(result.layers["flare_07_04"])
    assert got == pytest.approx(expected, abs=1.0)
    core_x, core_y = centroid(result.layers["core"])
    assert core_x > 96 + 0.9 * 99.2 * math.tan(math.radians(angle_deg)) / pitch
    assert abs(core_y - 64) < 0.5


def test_flares_follow_the_light_along_the_line_through_the_centre():
    """Every ghost of a rotationally symmetric lens lies on the line through the image centre and
    the source, and at small angles its offset grows linearly with the field angle."""
    offsets = {}
    for angle in (2.0, 4.0):
        s = math.sin(math.radians(angle))
        toward = (math.cos(math.radians(30)) * s, math.sin(math.radians(30)) * s, -1.0)
        scene = make_scene(jf.Light(kind="directional", direction=toward), resolution=(160, 160))
        result = jf.render(scene, samples=2**18, method="exact", paths=[(7, 4), (5, 0), (9, 7)], seed=6)
        core = np.subtract(centroid(result.layers["core"]), 80.0)
        assert core[0] > 0 and core[1] < 0  # light up and right of the view: image up and right (rows grow down)
        line = core / np.linalg.norm(core)
        for name in ("flare_07_04", "flare_05_00", "flare_09_07"):
            offset = np.subtract(centroid(result.layers[name]), 80.0)
            across = offset[0] * line[1] - offset[1] * line[0]
            assert abs(across) < 0.5 + 0.03 * np.linalg.norm(offset), (name, angle, offset, core)
            offsets[name, angle] = offset @ line
    for name in ("flare_07_04", "flare_05_00", "flare_09_07"):
        if abs(offsets[name, 4.0]) > 3:
            assert offsets[name, 4.0] / offsets[name, 2.0] == pytest.approx(2.0, rel=0.15), name


def test_on_axis_light_gives_a_radially_symmetric_flare():
    """On the axis with a round iris, the flare equals itself turned by 90 degrees and mirrored, up
    to Monte Carlo noise (measured as the difference between two seeds); off the axis it does not."""
    paths = [(4, 2), (7, 4), (2, 0)]

    def flare(direction, seed):
        scene = make_scene(jf.Light(kind="directional", direction=direction), aperture_blades=0, resolution=(128, 128), f_number=4.0)
        return jf.render(scene, samples=2**18, method="exact", seed=seed, paths=paths).image[..., :3].sum(axis=-1)

    a, b = flare((0.0, 0.0, -1.0), 21), flare((0.0, 0.0, -1.0), 22)
    noise = np.linalg.norm(a - b)
    assert np.linalg.norm(a - np.rot90(a)) < 1.25 * noise
    assert np.linalg.norm(a - a[:, ::-1]) < 1.25 * noise
    assert np.subtract(centroid(a[..., None].repeat(3, -1)), 64.0) == pytest.approx((0, 0), abs=0.6)
    skew = flare((0.02, 0.0, -1.0), 21)
    assert np.linalg.norm(skew - skew[:, ::-1]) > 2 * noise


@pytest.mark.parametrize("blades", [5, 6])
def test_iris_blades_shape_the_ghosts(blades):
    """Stopped down, a ghost is an image of the iris: a B-blade iris gives a B-fold ghost, a round
    iris a round one (angular harmonics of the ghost about the axis)."""
    light = jf.Light(kind="directional", direction=(0.0, 0.0, -1.0))
    harmonics = {}
    for count in (blades, 0):
        scene = make_scene(light, aperture_blades=count, resolution=(128, 128), f_number=8.0)
        ghost = jf.render(scene, samples=2**18, method="exact", seed=8, paths=[(4, 2)]).layers["flare_04_02"]
        harmonics[count] = angular_harmonics(ghost, range(2, 9))
    assert max(harmonics[blades], key=harmonics[blades].get) == blades, harmonics
    assert harmonics[blades][blades] > 4 * harmonics[0][blades], harmonics


# --------------------------------------------------------------------------- determinism, layers, output


def test_same_seed_same_image_and_other_seed_differs():
    scene = make_scene(jf.Light(kind="directional", direction=(0.05, 0.02, -1.0)))
    a = jf.render(scene, samples=2**16, method="exact", seed=11)
    b = jf.render(scene, samples=2**16, method="exact", seed=11)
    c = jf.render(scene, samples=2**16, method="exact", seed=12)
    np.testing.assert_array_equal(a.image, b.image)
    for name in a.layers:
        np.testing.assert_array_equal(a.layers[name], b.layers[name])
    assert not np.array_equal(a.image, c.image)


def test_layers_add_up_and_thresholds_split_them():
    scene = make_scene(jf.Light(kind="directional", direction=(0.05, 0.02, -1.0)))
    result = jf.render(scene, samples=2**17, method="exact", seed=13)
    flares = [name for name in result.layers if name not in ("core", "variance")]
    assert "flares_merged" in flares and len(flares) <= 13
    assert result.layers["variance"].shape == (96, 128, 1) and np.all(result.layers["variance"] >= 0)
    np.testing.assert_allclose(sum(result.layers[n] for n in flares), result.image[..., :3], rtol=1e-5, atol=1e-7)
    assert np.all(np.isfinite(result.image))
    # single-wavelength samples fall outside the RGB gamut (negative channels in noisy pixels: before
    # the gamut rule 5-20 % of the red and green values); every layer is mapped into it (_gamut)
    assert 0.0 < result.statistics["settings"]["out_of_gamut_fraction"] < 1.0
    for name, layer in result.layers.items():
        assert layer.min() >= 0.0, name
    energies = {tuple(p["path"]): p["energy"] for p in result.statistics["paths"] if p["path"] != "primary"}
    own = [tuple(layer["paths"][0]) for layer in result.statistics["layers"] if layer["layer"].startswith("flare_")]
    merged = [tuple(p) for layer in result.statistics["layers"] if layer["layer"] == "flares_merged" for p in layer["paths"]]
    assert min(energies[p] for p in own) >= 0.5 * max(energies[p] for p in merged)  # pilot-chosen, up to noise
    np.testing.assert_allclose(result.image[..., 3], np.clip(result.image[..., :3].max(axis=-1), 0, 1))


def test_sensor_hits_weighting_is_the_papers_normalisation():
    scene = make_scene(jf.Light(kind="directional", direction=(0.05, 0.02, -1.0)), render=dict(sampling="uniform"))
    ours = jf.render(scene, samples=2**16, method="exact", seed=14)
    paper = jf.render(jf.Scene(scene.camera, scene.lights, jf.RenderSettings(weights="sensor-hits", sampling="uniform")), samples=2**16, method="exact", seed=14)
    rate = ours.statistics["sensor_hit_rate"]
    assert 0 < rate < 0.5
    np.testing.assert_allclose(paper.image[..., :3], ours.image[..., :3] / rate, rtol=1e-4, atol=1e-7)


def test_exr_round_trip(tmp_path):
    scene = make_scene(jf.Light(kind="directional", direction=(0.05, 0.02, -1.0)))
    result = jf.render(scene, samples=2**17, method="exact", seed=15)
    path = result.write_exr(tmp_path / "flare.exr", pixel_type="float")
    layers, header = jf.read_exr(path)
    np.testing.assert_array_equal(layers[""], result.image)
    for name, value in result.layers.items():
        np.testing.assert_array_equal(layers[name], value)
    assert "zeiss_biotar" in header["jaxflare/lens"].lower() or "biotar" in header["jaxflare/lens"].lower()
    assert '"samples"' in header["jaxflare/statistics"]
    half_path = result.write_exr(tmp_path / "half.exr")
    half, _ = jf.read_exr(half_path)
    np.testing.assert_array_equal(half[""], result.image.astype(np.float16).astype(np.float32))
    # the variance layer stays float32 in a half file: in float16 a luminance squared underflows
    variance = result.layers["variance"]
    assert np.count_nonzero(variance) > 0 and np.count_nonzero(variance.astype(np.float16)) < np.count_nonzero(variance)
    np.testing.assert_array_equal(half["variance"], variance)
    # a compositor's reader (OpenImageIO) sees the declared colour space: ACEScg = AP1 primaries, ACES white
    oiio = pytest.importorskip("OpenImageIO")
    spec = oiio.ImageInput.open(str(half_path)).spec()
    ap1 = (0.713, 0.293, 0.165, 0.830, 0.128, 0.044, 0.32168, 0.33767)
    np.testing.assert_allclose(spec.getattribute("chromaticities"), ap1, atol=1e-6)
    assert spec.channelformat(spec.channelnames.index("variance.Y")) == oiio.FLOAT
    assert spec.channelformat(spec.channelnames.index("R")) == oiio.HALF
    png = result.write_png(tmp_path / "flare.png")
    import matplotlib.image

    assert matplotlib.image.imread(png).shape[:2] == (96, 128)


def test_brightest_allowed_light_gives_a_finite_variance_and_writes(tmp_path):
    """Issue 17: a light of intensity 1e30 overflowed the float32 sums of squares, and the EXR
    write failed after the whole render. Now the image is 1e30 x the unit light's, the variance
    1e60 x (clipped to float32's range and counted, never Inf), and both pixel types write."""
    light = {"kind": "directional", "direction": (0.08, 0.03, -1.0)}
    unit = jf.render(make_scene(jf.Light(**light), render={"sampling": "uniform"}), samples=2**17, method="exact", seed=3)
    bright = jf.render(make_scene(jf.Light(**light, intensity=1e30), render={"sampling": "uniform"}), samples=2**17, method="exact", seed=3)
    np.testing.assert_allclose(bright.image[..., :3], 1e30 * unit.image[..., :3], rtol=1e-5, atol=1e-6 * 1e30 * unit.image.max())
    variance = bright.layers["variance"]
    assert np.all(np.isfinite(variance)) and variance.max() > 0
    exact = 1e60 * unit.layers["variance"].astype(np.float64)
    np.testing.assert_allclose(variance, np.minimum(exact, np.finfo(np.float32).max), rtol=1e-4)
    info = next(layer for layer in bright.statistics["layers"] if layer["layer"] == "variance")
    assert info["clipped_values"] == np.count_nonzero(exact > np.finfo(np.float32).max) > 0
    for pixel_type in ("half", "float"):
        layers, _ = jf.read_exr(bright.write_exr(tmp_path / f"bright_{pixel_type}.exr", pixel_type=pixel_type))
        assert all(np.all(np.isfinite(v)) for v in layers.values())
        np.testing.assert_array_equal(layers["variance"], variance)


def test_spectral_and_blackbody_lights_are_coloured():
    warm = jf.render(make_scene(jf.Light(kind="directional", direction=(0.05, 0.0, -1.0), temperature_k=2700.0)), samples=2**16, method="exact", seed=16)
    r, g, b = warm.layers["core"].reshape(-1, 3).sum(axis=0)
    assert r > g > b
    bluish = jf.Light(kind="directional", direction=(0.05, 0.0, -1.0), spectrum=((400.0, 480.0, 520.0, 700.0), (1.0, 1.0, 0.0, 0.0)))
    blue = jf.render(make_scene(bluish), samples=2**16, method="exact", seed=16)
    r, g, b = blue.layers["core"].reshape(-1, 3).sum(axis=0)
    assert b > r


def test_coating_tints_colour_their_paths():
    light = jf.Light(kind="directional", direction=(0.05, 0.02, -1.0))
    uniform = dict(sampling="uniform")
    plain = jf.render(make_scene(light, render=uniform), samples=2**16, method="exact", paths=[(7, 4), (5, 0)], seed=17)
    tinted = jf.render(make_scene(light, render=uniform, coating_tints=((7, (1.0, 0.5, 0.25)),)), samples=2**16, method="exact", paths=[(7, 4), (5, 0)], seed=17)
    # linear in the tint wherever the pixel is inside the gamut (a pixel with a zero channel was
    # desaturated into it, which is not linear: _gamut); those hold a small share of the light
    a, b = plain.layers["flare_07_04"], tinted.layers["flare_07_04"]
    inside = (a.min(axis=-1) > 0) & (b.min(axis=-1) > 0)
    assert a[inside].sum() > 0.9 * a.sum()
    np.testing.assert_allclose(b[inside], a[inside] * np.array([1.0, 0.5, 0.25]), rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(tinted.layers["flare_05_00"], plain.layers["flare_05_00"], rtol=1e-6)


def test_coating_preset_changes_ghost_energy():
    light = jf.Light(kind="directional", direction=(0.05, 0.02, -1.0))
    bare = jf.render(make_scene(light, coating="uncoated"), samples=2**16, method="exact", paths=[(7, 4)], seed=18)
    coated = jf.render(make_scene(light, coating="multilayer"), samples=2**16, method="exact", paths=[(7, 4)], seed=18)
    assert coated.image.sum() < 0.2 * bare.image.sum()


def test_polynomial_method_agrees_with_exact_tracing(tmp_path, monkeypatch):
    """At a resolution whose pixels the degree-5 systems meet, polynomial and exact renders agree
    to within their Monte Carlo noise (two seeds each: the methods draw different samples)."""
    monkeypatch.setenv("JAXFLARE_CACHE_DIR", str(tmp_path))
    light = jf.Light(kind="directional", direction=(0.03, 0.01, -1.0))
    scene = make_scene(light, f_number=4.0, resolution=(96, 64), render=dict(quality="production", samples=2**17))
    paths = [(4, 2)]
    exact = [jf.render(scene, samples=2**17, method="exact", paths=paths, seed=s) for s in (19, 20)]
    poly = [jf.render(scene, samples=2**17, method="polynomial", paths=paths, seed=19)]
    compiled = eqx.debug.get_num_traces(jf.rendering.render_step)
    poly.append(jf.render(scene, samples=2**17, method="polynomial", paths=paths, seed=20))
    # the exact-fallback capacities come from batches of a fixed seed: another seed, the same step
    assert eqx.debug.get_num_traces(jf.rendering.render_step) == compiled
    auto = jf.render(scene, samples=2**17, method="auto", paths=paths, seed=19)
    assert poly[0].statistics["polynomial_paths"] == 2 and poly[0].statistics["unevaluated_fraction"] < 0.01
    assert auto.statistics["polynomial_paths"] + auto.statistics["exact_paths"] == 2
    for name in ("flare_04_02", "core"):
        # luminance: the gamut rule (_gamut) keeps it, not the channel sum, and the two methods'
        # colour noise differs (here 44 % of the polynomial render's pixels were outside the gamut, 4 % of the exact one's)
        e = [luminance(r.layers[name]) for r in exact]
        p = [luminance(r.layers[name]) for r in poly]
        noise = abs(e[0].sum() - e[1].sum()) + abs(p[0].sum() - p[1].sum())
        assert abs((p[0] + p[1]).sum() - (e[0] + e[1]).sum()) < 3 * noise + 0.02 * (e[0] + e[1]).sum(), name
        spread = np.linalg.norm(np.subtract(centroid(e[0]), centroid(e[1]))) + np.linalg.norm(np.subtract(centroid(p[0]), centroid(p[1])))
        offset = np.linalg.norm(np.subtract(centroid(p[0] + p[1]), centroid(e[0] + e[1])))
        assert offset < 2 * spread + 0.3, name


def test_render_step_compiles_once_per_structure():
    """Renders of one structure (lens, paths, lights, resolution, layers) share one compiled step,
    whatever the light's direction and intensity, the f-number or the sample count; another
    structure (a second path) compiles its own."""
    traces = lambda: eqx.debug.get_num_traces(jf.rendering.render_step)  # noqa: E731
    scene = make_scene(jf.Light(kind="directional", direction=(0.05, 0.02, -1.0)))
    start = traces()
    jf.render(scene, samples=2**12, method="exact", paths=[(7, 4), (6, 1)], seed=1)
    before = traces()
    assert before >= start
    other = make_scene(jf.Light(kind="directional", direction=(-0.05, 0.04, -1.0), intensity=7.0), f_number=5.6)
    jf.render(other, samples=2**13, method="exact", paths=[(7, 4), (6, 1)], seed=2)
    assert traces() == before
    jf.render(other, samples=2**12, method="exact", paths=[(7, 4), (6, 1), (5, 0)], seed=2)
    assert traces() == before + 1  # the counter sees compilations: the test above cannot pass vacuously


def test_exact_fresnel_model_agrees_with_schlick_near_the_axis():
    """Near the axis the paper's Schlick estimate (on-axis coated factor x front-lens angle term)
    and the coated Fresnel product at every event agree; the primary image closely."""
    light = jf.Light(kind="directional", direction=(0.02, 0.0, -1.0))
    scene = make_scene(light)
    schlick = jf.render(scene, samples=2**17, method="exact", paths=[(7, 4), (4, 2)], seed=23)
    exact = jf.render(jf.Scene(scene.camera, scene.lights, jf.RenderSettings(fresnel="exact")), samples=2**17, method="exact", paths=[(7, 4), (4, 2)], seed=23)
    assert exact.layers["core"].sum() == pytest.approx(schlick.layers["core"].sum(), rel=0.01)
    for name in ("flare_07_04", "flare_04_02"):
        assert exact.layers[name].sum() == pytest.approx(schlick.layers[name].sum(), rel=0.25), name
