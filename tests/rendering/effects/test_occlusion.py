"""Occluders (scene meshes, ray cast with trimesh/Embree) and lens hoods: geometry against analytic
answers, file loading and its errors, the JAX callback under jit/vmap/grad."""

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")

from jaxflare.rendering.effects import (
    Occluders,
    embree_available,
    hood_visible,
    lens_to_world,
    load_occluders,
    segment_visibility,
)
from jaxflare.scenes import Camera, Hood


def rectangle(x0, x1, y0, y1, z):
    """Two triangles covering [x0, x1] x [y0, y1] in the plane z."""
    vertices = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=float)
    return trimesh.Trimesh(vertices, [[0, 1, 2], [0, 2, 3]], process=False)


def plate():
    """The square [0, 1] x [-0.5, 0.5] in the plane z = 0 (world metres)."""
    return rectangle(0.0, 1.0, -0.5, 0.5, 0.0)


def holed_box(half=1.0, hole=0.05):
    """The surface of the cube [-half, half]^3 with a square hole of half-size ``hole`` centred on
    the z axis in its front (z = -half) and back (z = +half) faces."""
    parts = []
    for z in (-half, half):
        parts += [
            rectangle(-half, -hole, -half, half, z),
            rectangle(hole, half, -half, half, z),
            rectangle(-hole, hole, hole, half, z),
            rectangle(-hole, hole, -half, -hole, z),
        ]
    side = rectangle(-half, half, -half, half, 0.0)
    for axis, sign in ((0, 1), (0, -1), (1, 1), (1, -1)):
        mesh = side.copy()
        # rotate the z = 0 square into the plane x = +-half (axis 0) or y = +-half (axis 1)
        rotation = trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0] if axis == 0 else [1, 0, 0])
        mesh.apply_transform(rotation)
        offset = np.zeros(3)
        offset[axis] = sign * half
        mesh.apply_translation(offset)
        parts.append(mesh)
    return trimesh.util.concatenate(parts)


@pytest.fixture(scope="module")
def plate_occluders():
    return Occluders.from_mesh(plate())


def test_plate_blocks_exactly_the_segments_it_covers(plate_occluders):
    # a bundle of parallel segments through z = 0 on a grid straddling the plate's edges
    x = np.linspace(-0.43, 1.43, 47)  # never exactly on x = 0 or 1
    y = np.linspace(-0.87, 0.87, 23)  # never on y = +-0.5
    gx, gy = np.meshgrid(x, y, indexing="ij")
    xy = np.stack([gx.ravel(), gy.ravel()], axis=-1)
    starts = np.concatenate([xy, np.full((len(xy), 1), -2.0)], axis=-1)
    ends = np.concatenate([xy, np.full((len(xy), 1), 3.0)], axis=-1)
    covered = (xy[:, 0] > 0) & (xy[:, 0] < 1) & (np.abs(xy[:, 1]) < 0.5)
    assert 0.2 < covered.mean() < 0.8
    np.testing.assert_array_equal(plate_occluders.segment_visible(starts, ends), ~covered)
    # the reverse direction, and (..., 3) batch shapes
    np.testing.assert_array_equal(plate_occluders.segment_visible(ends, starts), ~covered)
    batched = plate_occluders.segment_visible(starts.reshape(47, 23, 3), ends.reshape(47, 23, 3))
    assert batched.shape == (47, 23)
    np.testing.assert_array_equal(batched.ravel(), ~covered)
    # tilted segments: blocked where their crossing of z = 0 lies on the plate
    rng = np.random.default_rng(0)
    starts = rng.uniform([-0.5, -1, -2], [1.5, 1, -0.5], (4000, 3))
    ends = rng.uniform([-0.5, -1, 0.5], [1.5, 1, 2], (4000, 3))
    t = -starts[:, 2] / (ends[:, 2] - starts[:, 2])
    crossing = starts[:, :2] + t[:, None] * (ends[:, :2] - starts[:, :2])
    margin = np.minimum.reduce([np.abs(crossing[:, 0]), np.abs(crossing[:, 0] - 1), np.abs(np.abs(crossing[:, 1]) - 0.5)])
    keep = margin > 1e-6
    covered = (crossing[:, 0] > 0) & (crossing[:, 0] < 1) & (np.abs(crossing[:, 1]) < 0.5)
    np.testing.assert_array_equal(plate_occluders.segment_visible(starts, ends)[keep], ~covered[keep])


def test_segments_short_of_or_behind_the_plate_or_touching_it_are_visible(plate_occluders):
    xy = np.array([[0.5, 0.0], [0.2, 0.3], [0.9, -0.4]])
    column = lambda z: np.full((3, 1), z)
    at = lambda z: np.concatenate([xy, column(z)], axis=-1)
    occ = plate_occluders
    assert occ.segment_visible(at(-2.0), at(-0.01)).all()  # ends before the plate
    assert occ.segment_visible(at(0.01), at(2.0)).all()  # starts behind it
    assert occ.segment_visible(at(-2.0), at(0.0)).all()  # ends on it: touching does not block
    assert occ.segment_visible(at(0.0), at(2.0)).all()  # starts on it
    assert not occ.segment_visible(at(-2.0), at(1e-3)).any()  # just through it: blocked
    assert occ.segment_visible(at(-1.0), at(-1.0)).all()  # zero length
    assert occ.segment_visible(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)
    with pytest.raises(ValueError, match="finite"):
        occ.segment_visible(at(-1.0), at(np.inf))
    with pytest.raises(ValueError, match="same shape"):
        occ.segment_visible(at(-1.0), at(1.0)[:2])


def test_segment_through_a_small_hole_in_a_box_is_visible_and_the_rest_are_blocked():
    occ = Occluders.from_mesh(holed_box(half=1.0, hole=0.05))
    # straight through both holes, tilted through both, and from outside to the box's centre
    starts = np.array([[0.0, 0.0, -5.0], [-0.01, 0.02, -5.0], [0.03, -0.03, -4.0]])
    ends = np.array([[0.0, 0.0, 5.0], [0.01, -0.02, 5.0], [0.0, 0.0, 0.0]])
    assert occ.segment_visible(starts, ends).all()
    # everything else crossing the box is blocked
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.9, 0.9, (500, 2))
    xy = xy[np.max(np.abs(xy), axis=-1) > 0.06]
    starts = np.concatenate([xy, np.full((len(xy), 1), -5.0)], axis=-1)
    ends = np.concatenate([xy, np.full((len(xy), 1), 5.0)], axis=-1)
    assert not occ.segment_visible(starts, ends).any()
    # from the centre out through a side wall, and from outside to the centre through the front hole
    # at an angle that makes it graze no wall
    assert not occ.segment_visible(np.zeros((1, 3)), np.array([[3.0, 0.1, 0.2]])).any()
    assert occ.segment_visible(np.array([[0.04, 0.0, -1.5]]), np.array([[0.0, 0.0, 0.5]])).all()


@pytest.mark.parametrize("far_end", ["start", "end"])
def test_directional_light_with_a_far_away_end_point(plate_occluders, far_end):
    rng = np.random.default_rng(2)
    lens = rng.uniform([-0.5, -1.0, 0.5], [1.5, 1.0, 2.0], (3000, 3))  # lens points behind the plate
    angle = np.radians(rng.uniform(-20, 20, (3000, 2)))
    towards_light = np.stack([np.tan(angle[:, 0]), np.tan(angle[:, 1]), -np.ones(3000)], axis=-1)
    towards_light /= np.linalg.norm(towards_light, axis=-1, keepdims=True)
    light = lens + 1e6 * towards_light
    crossing = lens[:, :2] + (-lens[:, 2] / towards_light[:, 2])[:, None] * towards_light[:, :2]
    margin = np.minimum.reduce([np.abs(crossing[:, 0]), np.abs(crossing[:, 0] - 1), np.abs(np.abs(crossing[:, 1]) - 0.5)])
    keep = margin > 1e-6
    covered = (crossing[:, 0] > 0) & (crossing[:, 0] < 1) & (np.abs(crossing[:, 1]) < 0.5)
    assert keep.mean() > 0.99 and 0.1 < covered.mean() < 0.9
    starts, ends = (light, lens) if far_end == "start" else (lens, light)
    np.testing.assert_array_equal(plate_occluders.segment_visible(starts, ends)[keep], ~covered[keep])
    # the same far from the world origin (a scene in large world coordinates)
    shift = np.array([3000.0, -200.0, 5000.0])
    moved = plate().apply_translation(shift)
    visible = Occluders.from_mesh(moved).segment_visible(starts + shift, ends + shift)
    np.testing.assert_array_equal(visible[keep], ~covered[keep])


def scene_mesh():
    """A plate and a tilted box, for the file round trips."""
    box = trimesh.creation.box(extents=[0.4, 0.3, 0.2])
    box.apply_transform(trimesh.transformations.rotation_matrix(0.3, [1, 1, 0]))
    box.apply_translation([-0.4, 0.2, 0.5])
    return trimesh.util.concatenate([plate(), box])


def random_segments(count, seed):
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.2, 1.5, (count, 3)) + [0, 0, -2.0], rng.uniform(-1.2, 1.5, (count, 3)) + [0, 0, 2.0]


def test_obj_ply_glb_files_load_with_the_same_visibility_and_transforms_and_scale(tmp_path):
    mesh = scene_mesh()
    starts, ends = random_segments(3000, 3)
    reference = Occluders.from_mesh(mesh).segment_visible(starts, ends)
    assert 0.1 < reference.mean() < 0.9
    for extension in ("obj", "ply", "glb", "stl"):
        path = tmp_path / f"scene.{extension}"
        mesh.export(path)
        occ = load_occluders([path])
        assert occ.num_triangles == len(mesh.faces) and str(path) in occ.sources
        np.testing.assert_array_equal(occ.segment_visible(starts, ends), reference, err_msg=extension)
    # a centimetre file, placed by a transform (world metres) after scaling
    centimetres = mesh.copy().apply_scale(100.0)
    centimetres.export(tmp_path / "cm.ply")
    rotation = trimesh.transformations.rotation_matrix(0.7, [0, 0, 1])
    placement = trimesh.transformations.translation_matrix([0.3, -0.2, 1.0]) @ rotation
    occ = load_occluders([tmp_path / "cm.ply"], transforms=[placement], scale=0.01)
    np.testing.assert_allclose(occ.mesh.bounds, mesh.copy().apply_transform(placement).bounds, atol=1e-9)
    moved = Occluders.from_mesh(mesh.copy().apply_transform(placement))
    np.testing.assert_array_equal(occ.segment_visible(starts, ends), moved.segment_visible(starts, ends))
    # two files concatenate: the union blocks what either blocks (the cm file scaled by its transform)
    to_metres = placement @ np.diag([0.01, 0.01, 0.01, 1.0])
    both = load_occluders([tmp_path / "scene.obj", tmp_path / "cm.ply"], transforms=[np.eye(4), to_metres])
    assert both.num_triangles == 2 * len(mesh.faces) and len(both.sources) == 2
    union = reference & moved.segment_visible(starts, ends)
    assert (union != reference).any()
    np.testing.assert_array_equal(both.segment_visible(starts, ends), union)


def test_bad_files_raise_naming_the_file(tmp_path):
    missing = tmp_path / "nowhere.obj"
    with pytest.raises(FileNotFoundError, match="nowhere.obj"):
        load_occluders([missing])
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing here\n")
    with pytest.raises(ValueError, match="empty.obj.*empty"):
        load_occluders([empty])
    garbage = tmp_path / "garbage.glb"
    garbage.write_bytes(b"\x00\xffnot a mesh at all" * 10)
    with pytest.raises(ValueError, match="garbage.glb.*supported: .obj"):
        load_occluders([garbage])
    unsupported = tmp_path / "mesh.xyz"
    unsupported.write_text("1 2 3\n")
    with pytest.raises(ValueError, match=r"mesh.xyz.*\.obj, \.ply, \.stl, \.glb, \.gltf"):
        load_occluders([unsupported])
    nan = plate()
    nan.vertices[0, 0] = np.nan
    nan.export(tmp_path / "nan.ply")
    with pytest.raises(ValueError, match="nan.ply.*non-finite"):
        load_occluders([tmp_path / "nan.ply"])
    plate().export(tmp_path / "ok.obj")
    with pytest.raises(ValueError, match="transforms"):
        load_occluders([tmp_path / "ok.obj"], transforms=[np.eye(3)])
    with pytest.raises(ValueError, match="scale"):
        load_occluders([tmp_path / "ok.obj"], scale=0.0)
    with pytest.raises(ValueError, match="empty"):
        Occluders.from_mesh(trimesh.Trimesh())


def test_jax_callback_matches_numpy_under_jit_vmap_and_grad(plate_occluders):
    occ = plate_occluders
    starts, ends = random_segments(2000, 4)
    expected = occ.segment_visible(starts, ends)
    jitted = jax.jit(lambda s, e: segment_visibility(occ, s, e))
    np.testing.assert_array_equal(np.asarray(jitted(jnp.asarray(starts), jnp.asarray(ends))), expected)
    with jax.enable_x64(False):  # float32 inputs, as the renderer uses
        got = jitted(jnp.asarray(starts, jnp.float32), jnp.asarray(ends, jnp.float32))
        assert got.dtype == jnp.bool_
        assert np.mean(np.asarray(got) == expected) > 0.999
    batched = jax.jit(jax.vmap(lambda s, e: segment_visibility(occ, s, e)))(starts.reshape(4, 500, 3), ends.reshape(4, 500, 3))
    np.testing.assert_array_equal(np.asarray(batched).ravel(), expected)

    # an equinox module holding the occluders as a static field, under eqx.filter_jit
    class Weighted(eqx.Module):
        occluders: Occluders = eqx.field(static=True)
        colour: jax.Array

        def __call__(self, s, e):
            return jnp.sum(self.colour * segment_visibility(self.occluders, s, e) * jnp.linalg.norm(e - s, axis=-1))

    model = Weighted(occ, jnp.asarray(2.0))
    value = eqx.filter_jit(Weighted.__call__)(model, starts, ends)
    np.testing.assert_allclose(value, 2.0 * np.sum(expected * np.linalg.norm(ends - starts, axis=-1)))
    grads = eqx.filter_jit(eqx.filter_grad(lambda m, s, e: m(s, e)))(model, starts, ends)
    np.testing.assert_allclose(grads.colour, np.sum(expected * np.linalg.norm(ends - starts, axis=-1)))
    # gradient with respect to the end points: the visibility is a constant factor
    grad_ends = jax.jit(jax.grad(lambda e: model(jnp.asarray(starts), e)))(jnp.asarray(ends))
    assert np.all(np.isfinite(grad_ends))
    direction = (ends - starts) / np.linalg.norm(ends - starts, axis=-1, keepdims=True)
    np.testing.assert_allclose(grad_ends, 2.0 * expected[:, None] * direction, atol=1e-12)
    # non-finite segments count as visible in the callback
    bad = jnp.asarray(ends).at[0].set(jnp.nan)
    assert bool(jitted(jnp.asarray(starts), bad)[0])


def test_embree_is_used_when_installed_and_throughput():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    occ = Occluders.from_mesh(sphere)
    if embree_available():
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        assert isinstance(occ.intersector, RayMeshIntersector) and occ.uses_embree
    else:
        pytest.skip("embreex is not installed")
    rng = np.random.default_rng(5)
    count = 100_000
    starts = rng.normal(size=(count, 3)) * 0.3 + [0, 0, -5]
    ends = rng.normal(size=(count, 3)) * 0.3 + [0, 0, 5]
    occ.segment_visible(starts[:100], ends[:100])  # build the BVH
    begin = time.perf_counter()
    visible = occ.segment_visible(starts, ends)
    elapsed = time.perf_counter() - begin
    # analytic: blocked iff the line passes within the (inscribed-radius-ish) sphere
    direction = (ends - starts) / np.linalg.norm(ends - starts, axis=-1, keepdims=True)
    closest = starts - np.sum(starts * direction, axis=-1, keepdims=True) * direction
    miss = np.linalg.norm(closest, axis=-1)
    inscribed = np.min(np.abs(np.sum(sphere.triangles_center * sphere.face_normals, axis=-1)))
    assert not visible[miss < inscribed - 1e-6].any() and visible[miss > 1.0 + 1e-6].all()
    print(f"\noccluder ray casting: {count / elapsed:,.0f} segments/s with embree, {len(sphere.faces)} triangles")


def test_without_embree_the_numpy_intersector_gives_the_same_answer_with_a_warning(monkeypatch):
    import trimesh.ray
    from trimesh.ray.ray_triangle import RayMeshIntersector

    from jaxflare.rendering.effects import OcclusionWarning

    mesh = scene_mesh()
    starts, ends = random_segments(400, 8)
    fast = Occluders.from_mesh(mesh).segment_visible(starts, ends)
    monkeypatch.setattr(trimesh.ray, "has_embree", False)
    with pytest.warns(OcclusionWarning, match="embreex"):
        slow = Occluders.from_mesh(mesh)
    assert isinstance(slow.intersector, RayMeshIntersector) and not slow.uses_embree
    np.testing.assert_array_equal(slow.segment_visible(starts, ends), fast)

def test_lens_to_world_inverts_the_camera_rotation():
    camera = Camera(lens="zeiss_biotar", position_m=(1.0, 2.0, 3.0), rotation_deg=(30.0, -10.0, 5.0))
    rotation = camera.world_to_camera()
    world = np.array([[4.0, -1.0, -7.0], [1.0, 2.0, 3.0]])
    lens_mm = (world - camera.position_m) @ rotation.T * 1000.0
    np.testing.assert_allclose(lens_to_world(lens_mm, rotation, camera.position_m), world, atol=1e-12)


# --------------------------------------------------------------------------- hood


def test_circular_hood_blocks_rays_whose_crossing_is_outside_its_radius():
    d, r = 60.0, 35.0
    hood = Hood.circular(distance_mm=d, radius_mm=r)
    rng = np.random.default_rng(6)
    origins = np.concatenate([rng.uniform(-20, 20, (20000, 2)), np.full((20000, 1), -2.0)], axis=-1)  # just in front of the lens
    slopes = np.tan(np.radians(rng.uniform(-40, 40, (20000, 2))))
    directions = np.concatenate([slopes, np.ones((20000, 1))], axis=-1)
    directions *= rng.uniform(0.5, 2.0, (20000, 1))  # need not be unit
    crossing = origins[:, :2] + (-d - origins[:, 2:3]) * slopes
    radius = np.linalg.norm(crossing, axis=-1)
    keep = np.abs(radius - r) > 1e-9
    visible = np.asarray(jax.jit(hood_visible)(hood, origins, directions))
    np.testing.assert_array_equal(visible[keep], (radius <= r)[keep])
    assert 0.2 < visible.mean() < 0.9
    # on axis through the lens vertex: blocked iff d tan(theta) > r
    theta = np.radians(np.linspace(0.5, 60, 120))
    on_axis = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=-1)
    blocked = ~np.asarray(hood_visible(hood, np.zeros_like(on_axis), on_axis))
    np.testing.assert_array_equal(blocked, d * np.tan(theta) > r)
    # rays not travelling towards the lens
    assert not np.asarray(hood_visible(hood, np.zeros((2, 3)), np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]))).any()


def test_rectangular_hood_blocks_outside_its_opening_and_validates():
    d, w, h = 80.0, 40.0, 22.5
    hood = Hood.rectangular(distance_mm=d, half_width_mm=w, half_height_mm=h)
    rng = np.random.default_rng(7)
    origins = np.concatenate([rng.uniform(-15, 15, (20000, 2)), np.zeros((20000, 1))], axis=-1)
    slopes = np.tan(np.radians(rng.uniform(-45, 45, (20000, 2))))
    directions = np.concatenate([slopes, np.ones((20000, 1))], axis=-1)
    crossing = origins[:, :2] - d * slopes
    keep = (np.abs(np.abs(crossing[:, 0]) - w) > 1e-9) & (np.abs(np.abs(crossing[:, 1]) - h) > 1e-9)
    inside = (np.abs(crossing[:, 0]) <= w) & (np.abs(crossing[:, 1]) <= h)
    visible = np.asarray(jax.jit(jax.vmap(hood_visible, in_axes=(None, 0, 0)))(hood, origins.reshape(4, -1, 3), directions.reshape(4, -1, 3)))
    np.testing.assert_array_equal(visible.ravel()[keep], inside[keep])
    # horizontal rays through the vertex: blocked iff d tan(theta) > w; vertical ones against h
    theta = np.radians(np.linspace(1, 50, 99))
    horizontal = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=-1)
    vertical = horizontal[:, [1, 0, 2]]
    np.testing.assert_array_equal(~np.asarray(hood_visible(hood, np.zeros_like(horizontal), horizontal)), d * np.tan(theta) > w)
    np.testing.assert_array_equal(~np.asarray(hood_visible(hood, np.zeros_like(vertical), vertical)), d * np.tan(theta) > h)
    # gradients flow through a render-like product without touching the hood
    grad = jax.grad(lambda c: jnp.sum(c * hood_visible(hood, origins, directions)))(1.0)
    assert float(grad) == visible.sum()

    with pytest.raises(ValueError, match="distance_mm"):
        Hood.circular(distance_mm=0.0, radius_mm=30.0)
    with pytest.raises(ValueError, match="radius_mm"):
        Hood.circular(distance_mm=50.0, radius_mm=float("nan"))
    with pytest.raises(ValueError, match="half_height_mm"):
        Hood.rectangular(distance_mm=50.0, half_width_mm=30.0, half_height_mm=-1.0)
    with pytest.raises(ValueError, match="half_width_mm"):
        Hood.rectangular(distance_mm=50.0, half_width_mm=np.inf, half_height_mm=10.0)
    with pytest.raises(ValueError, match="shape"):
        Hood("oval", 50.0, radius_mm=10.0)
    with pytest.raises(ValueError, match="radius_mm"):
        Hood("rectangular", 50.0, radius_mm=10.0, half_width_mm=1.0, half_height_mm=1.0)
