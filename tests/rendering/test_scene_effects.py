"""Scene effects in renders: occluding geometry, front-lens dirt, a lens hood, and distortion."""

import math

import numpy as np
import pytest

import jaxflare as jf

trimesh = pytest.importorskip("trimesh")

PATHS = [(7, 4), (4, 2), (2, 0), (5, 0)]


def scene(light, geometry=(), sampling="uniform", **camera):
    options = dict(lens="zeiss_biotar", f_number=4.0, aperture_blades=0, resolution=(96, 64), look_at_m=(0.0, 0.0, -10.0))
    options.update(camera)
    return jf.Scene(camera=jf.Camera(**options), lights=(light,), geometry=tuple(geometry), render=jf.RenderSettings(sampling=sampling))


def plate(tmp_path, name, corners_xy, z):
    """A rectangle at world z spanning corners_xy = ((x0, y0), (x1, y1)), written as an OBJ."""
    (x0, y0), (x1, y1) = corners_xy
    vertices = [[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]]
    mesh = trimesh.Trimesh(vertices=vertices, faces=[[0, 1, 2], [0, 2, 3]])
    path = tmp_path / f"{name}.obj"
    mesh.export(path)
    return jf.Geometry(file=str(path))


def layer_energies(result):
    return {str(p["path"]): p["energy"] for p in result.statistics["paths"]}


def test_half_plane_occluder_removes_exactly_half_of_every_path_on_the_axis(tmp_path):
    """On the axis the lens is mirror-symmetric in y, so a plate hiding the lower half of the view
    removes exactly half of the light of every path (same samples with and without the plate)."""
    light = jf.Light(kind="directional", direction=(0.0, 0.0, -1.0))
    blocker = plate(tmp_path, "lower", ((-10.0, -10.0), (10.0, 0.0)), -1.0)
    free = jf.render(scene(light), samples=2**17, paths=PATHS, seed=1)
    blocked = jf.render(scene(light, [blocker]), samples=2**17, paths=PATHS, seed=1)
    for path, energy in layer_energies(free).items():
        assert layer_energies(blocked)[path] == pytest.approx(0.5 * energy, rel=0.05), path
    # the lower half of each ghost image is what is lost, not a uniform dimming
    core_free, core_blocked = free.layers["core"].sum(-1), blocked.layers["core"].sum(-1)
    assert core_blocked.sum() == pytest.approx(0.5 * core_free.sum(), rel=0.02)


def test_an_occluded_light_loses_its_whole_flare_and_only_its_own(tmp_path):
    hidden = jf.Light(kind="point", position_m=(0.5, 0.2, -8.0), intensity=10.0)
    box = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    box.apply_translation((0.5, 0.2, -8.0))
    path = tmp_path / "box.ply"
    box.export(path)
    result = jf.render(scene(hidden, [jf.Geometry(file=str(path))]), samples=2**15, paths=PATHS, seed=2)
    assert result.image[..., :3].sum() == 0 and result.layers["core"].sum() == 0
    visible = jf.render(scene(hidden, [plate(tmp_path, "elsewhere", ((5.0, 5.0), (6.0, 6.0)), -4.0)]), samples=2**15, paths=PATHS, seed=2)
    free = jf.render(scene(hidden), samples=2**15, paths=PATHS, seed=2)
    np.testing.assert_array_equal(visible.image, free.image)


def _front_entry_fraction(lens, path, direction, dirty):
    """Share of a ghost's transmitted flux that entered the front lens where ``dirty(x, y)``, from
    a dense exact trace (independent of the renderer's sampler)."""
    direction = np.asarray(direction, float) / np.linalg.norm(direction)
    radius = float(lens.semi_aperture_mm[0]) * 1.1
    g = np.linspace(-radius, radius, 220)
    x, y = np.meshgrid(g, g)
    keep = x * x + y * y <= radius * radius
    origins = np.stack([x[keep], y[keep], np.zeros(keep.sum())], axis=-1) - 5.0 * direction
    result = jf.trace(lens, origins, np.broadcast_to(direction, origins.shape), 550.0, path)
    sensor = np.asarray(result.positions)
    on_sensor = (np.abs(sensor[:, 0]) <= 18.0) & (np.abs(sensor[:, 1]) <= 12.0)  # the 36 x 24 mm frame
    weight = np.asarray(result.throughput) * np.asarray(result.valid) * on_sensor
    return float(weight[dirty(x[keep], y[keep])].sum() / weight.sum())


def test_dirt_darkens_the_ghosts_whose_light_crosses_it(tmp_path):
    """A dirt map opaque on the left of the front element (lens x < 0): each ghost loses the share
    of its light that entered there, which the exact tracer gives independently."""
    from PIL import Image

    pixels = np.full((64, 64), 255, np.uint8)
    pixels[:, :32] = 0  # columns grow with +x: the left half is x < 0
    path = tmp_path / "dirt.png"
    Image.fromarray(pixels).save(path)
    toward = (0.08, 0.0, -1.0)
    light = jf.Light(kind="directional", direction=toward)
    clean = jf.render(scene(light), samples=2**18, paths=PATHS, seed=3)
    dirty = jf.render(scene(light, dirt_map=str(path)), samples=2**18, paths=PATHS, seed=3)
    lens = jf.load_lens("zeiss_biotar").with_f_number(4.0).with_aperture(0)
    travel = (-toward[0], -toward[1], -toward[2])
    for path in PATHS + [None]:
        lost = _front_entry_fraction(lens, path, travel, lambda x, y: x < 0)
        key = "primary" if path is None else str(list(path))
        ratio = layer_energies(dirty)[key] / layer_energies(clean)[key]
        assert ratio == pytest.approx(1.0 - lost, abs=0.04), (path, lost)


def test_lens_hood_cuts_off_lights_outside_its_opening():
    """A circular hood of radius 14 mm at 300 mm passes the on-axis core (its rays lie within the
    12.5 mm entrance pupil at f/4) and blocks every ray of a light 10 degrees off the axis (they
    cross the hood plane at least 300 tan 10 - 37 = 15.9 mm from the axis)."""
    hood = jf.Hood(shape="circular", distance_mm=300.0, radius_mm=14.0)
    near = jf.Light(kind="directional", direction=(0.0, 0.0, -1.0))
    far = jf.Light(kind="directional", direction=(math.sin(math.radians(10)), 0.0, -math.cos(math.radians(10))))
    with_hood = jf.render(scene(near, hood=hood), samples=2**15, paths=PATHS, seed=4)
    without = jf.render(scene(near), samples=2**15, paths=PATHS, seed=4)
    np.testing.assert_array_equal(with_hood.layers["core"], without.layers["core"])
    blocked = jf.render(scene(far, hood=hood), samples=2**15, paths=PATHS, seed=4)
    assert blocked.image[..., :3].sum() == 0
    assert jf.render(scene(far), samples=2**15, paths=PATHS, seed=4).image[..., :3].sum() > 0


def test_distortion_moves_the_flare_with_its_source():
    """Barrel distortion of the main render pulls an off-axis source towards the centre, and its
    core with it, by the Brown-Conrady amount at the core's position."""
    light = jf.Light(kind="directional", direction=(0.12, 0.0, -1.0))
    plain = jf.render(scene(light), samples=2**15, paths=PATHS, seed=5)
    k1 = -0.2
    barrel = jf.render(scene(light, distortion=jf.Distortion(k1=k1)), samples=2**15, paths=PATHS, seed=5)

    def core_x(result):
        core = result.layers["core"].sum(-1)
        columns = np.indices(core.shape)[1] + 0.5
        return float((columns * core).sum() / core.sum())

    f_px = jf.load_lens("zeiss_biotar").focal_length() / plain.statistics["pixel_pitch_mm"]
    x = (core_x(plain) - 48.0) / f_px
    assert core_x(barrel) - 48.0 == pytest.approx(f_px * x * (1 + k1 * x * x), abs=0.1)


def test_renders_with_the_same_geometry_compile_once(tmp_path):
    import equinox as eqx

    traces = lambda: eqx.debug.get_num_traces(jf.rendering.render_step)  # noqa: E731
    light = jf.Light(kind="directional", direction=(0.05, 0.0, -1.0))
    mesh = plate(tmp_path, "far", ((5.0, 5.0), (6.0, 6.0)), -4.0)
    jf.render(scene(light, [mesh]), samples=2**13, paths=PATHS, seed=1)
    before = traces()
    assert before >= 1
    jf.render(scene(light, [mesh]), samples=2**13, paths=PATHS, seed=2)
    assert traces() == before
