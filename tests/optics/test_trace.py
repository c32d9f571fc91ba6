"""Exact tracer: closed-form cases, reversibility, masks, Fresnel throughput, finite gradients."""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from tests.helpers import lens_from_toml

import jaxflare
from jaxflare.optics import uncoated_reflectance

N_GLASS = 1.5  # model glasses are exact at the d line, so n(587.56 nm) = n_d
D_LINE = 587.56


def _parallel_rays(heights_mm, axis=1, z0=-10.0):
    heights = np.asarray(heights_mm, dtype=np.float64)
    origins = np.zeros((heights.size, 3))
    origins[:, axis] = heights
    origins[:, 2] = z0
    directions = np.tile([0.0, 0.0, 1.0], (heights.size, 1))
    return origins, directions


def _paraxial_axis_crossing(result) -> float:
    """Where two rays of angles a and 2a cross the axis, extrapolated to a -> 0 (aberrations grow
    as a^2, so the Richardson combination (4 z(a) - z(2a)) / 3 removes them)."""
    p, d = np.asarray(result.positions), np.asarray(result.directions)
    crossing = p[:, 2] - p[:, 1] * d[:, 2] / d[:, 1]
    return float((4 * crossing[0] - crossing[1]) / 3)


PLANO_CONVEX = """
name = "plano-convex"
surfaces = [
  { radius = 50.0, thickness = 5.0, n_d = 1.5, v_d = 60.0, semi_aperture = 20.0, stop = true, coating = "none" },
  { radius = "flat", thickness = 90.0, semi_aperture = 20.0, coating = "none" },
]
"""


def test_plano_convex_matches_closed_form_refraction():
    lens = lens_from_toml(PLANO_CONVEX)
    heights = np.array([0.5, 3.0, 8.0, 15.0, 19.0])
    result = jaxflare.trace(lens, *_parallel_rays(heights), D_LINE)
    assert bool(jnp.all(result.valid))
    radius, thickness, distance = 50.0, 5.0, 90.0
    theta = np.arcsin(heights / radius)  # incidence angle at the sphere
    theta_glass = np.arcsin(np.sin(theta) / N_GLASS)
    alpha = theta - theta_glass  # ray angle to the axis inside the glass
    z_hit = radius - np.sqrt(radius**2 - heights**2)
    y_flat = heights - (thickness - z_hit) * np.tan(alpha)
    alpha_out = np.arcsin(N_GLASS * np.sin(alpha))
    y_sensor = y_flat - distance * np.tan(alpha_out)
    np.testing.assert_allclose(np.asarray(result.positions[:, 1]), y_sensor, atol=1e-9)
    np.testing.assert_allclose(np.asarray(result.directions[:, 1]), -np.sin(alpha_out), atol=1e-12)
    np.testing.assert_allclose(np.asarray(result.positions[:, 2]), thickness + distance)


PLATE = """
name = "plate"
surfaces = [
  { radius = "flat", thickness = 12.0, n_d = 1.5, v_d = 60.0, semi_aperture = 40.0, stop = true },
  { radius = "flat", thickness = 30.0, semi_aperture = 40.0 },
]
"""


def test_plane_parallel_plate_lateral_shift():
    lens = lens_from_toml(PLATE)
    angles = np.radians([0.0, 5.0, 20.0, 35.0])
    origins = np.tile([0.0, 0.0, -10.0], (angles.size, 1))
    directions = np.stack([np.sin(angles), np.zeros_like(angles), np.cos(angles)], axis=1)
    result = jaxflare.trace(lens, origins, directions, D_LINE)
    inside = np.arcsin(np.sin(angles) / N_GLASS)
    expected_x = 10.0 * np.tan(angles) + 12.0 * np.tan(inside) + 30.0 * np.tan(angles)
    np.testing.assert_allclose(np.asarray(result.positions[:, 0]), expected_x, atol=1e-9)
    np.testing.assert_allclose(np.asarray(result.directions), directions, atol=1e-12)  # a plate does not deviate


BICONVEX = """
name = "biconvex"
surfaces = [
  { radius = "flat", thickness = 20.0, semi_aperture = 8.0, stop = true },
  { radius = 100.0, thickness = 2.0, n_d = 1.5, v_d = 60.0, semi_aperture = 20.0 },
  { radius = -100.0, thickness = 99.0, semi_aperture = 20.0 },
]
"""


def test_thick_lens_focal_length_and_focus_agree_with_exact_trace():
    lens = lens_from_toml(BICONVEX)
    n, r1, r2, t = N_GLASS, 100.0, -100.0, 2.0
    power = (n - 1) * (1 / r1 - 1 / r2 + (n - 1) * t / (n * r1 * r2))  # lensmaker's equation, thick lens
    assert lens.focal_length() == pytest.approx(1 / power, rel=1e-12)
    assert lens.back_focal_length() == pytest.approx((1 / power) * (1 - (n - 1) * t / (n * r1)), rel=1e-12)
    # exact trace of near-axis rays from an axial point at 1 m: where they cross the axis
    distance = 1000.0
    sensor_z = lens.sensor_z_for_focus(distance)
    angles = np.array([1e-4, 2e-4])
    origins = np.tile([0.0, 0.0, -distance], (2, 1))
    directions = np.stack([np.zeros(2), np.sin(angles), np.cos(angles)], axis=1)
    result = jaxflare.trace(lens, origins, directions, D_LINE)
    assert _paraxial_axis_crossing(result) == pytest.approx(sensor_z, rel=1e-7)
    # Gaussian imaging between the principal planes of the thick lens
    f = 1 / power
    front_principal = 20.0 - f * (n - 1) * t / (n * r2)
    rear_principal = 22.0 - f * (n - 1) * t / (n * r1)
    image = 1 / (power - 1 / (distance + front_principal))
    assert sensor_z == pytest.approx(rear_principal + image, rel=1e-12)


def test_pupils_and_f_number_agree_with_exact_chief_rays():
    lens = lens_from_toml(BICONVEX)
    z_entrance, r_entrance = lens.entrance_pupil()
    assert (z_entrance, r_entrance) == (pytest.approx(0.0), pytest.approx(8.0))  # stop is the first surface
    assert lens.f_number() == pytest.approx(lens.focal_length() / 16.0)
    # exit pupil: chief rays through the stop centre, extrapolated back to the axis in image space
    z_exit, r_exit = lens.exit_pupil()
    angles = np.array([1e-4, 2e-4])
    origins = np.zeros((2, 3))
    directions = np.stack([np.zeros(2), np.sin(angles), np.cos(angles)], axis=1)
    result = jaxflare.trace(lens, origins, directions, D_LINE)
    assert _paraxial_axis_crossing(result) == pytest.approx(z_exit, rel=1e-7)
    # pupil magnification = chief-ray angular magnification inverse
    slope_in = np.tan(angles[0])
    slope_out = float(result.directions[0, 1] / result.directions[0, 2])
    assert r_exit == pytest.approx(8.0 * abs(slope_in / slope_out), rel=1e-6)


def test_f_number_sets_stop_radius(biotar):
    stopped = biotar.with_f_number(4.0)
    assert stopped.f_number() == pytest.approx(4.0, rel=1e-9)
    with pytest.raises(ValueError, match="faster than"):
        biotar.with_f_number(0.9)


def _reversed(prescription: jaxflare.LensPrescription, front_gap_mm: float) -> jaxflare.LensPrescription:
    """The same lens traversed from the sensor side: surfaces in reverse order, radii negated."""
    surfaces = prescription.surfaces
    count = len(surfaces)
    reversed_surfaces = []
    for k in range(count):
        original = surfaces[count - 1 - k]
        medium_after = surfaces[count - 2 - k].medium if k < count - 1 else jaxflare.MediumSpec()
        gap = surfaces[count - 2 - k].thicknesses_mm if k < count - 1 else (front_gap_mm,)
        reversed_surfaces.append(
            dataclasses.replace(original, radius_mm=-original.radius_mm, medium=medium_after, thicknesses_mm=gap)
        )
    return dataclasses.replace(prescription, surfaces=tuple(reversed_surfaces))


def test_reversibility_of_the_primary_path(biotar):
    rng = np.random.default_rng(1)
    count = 200
    origins = np.column_stack([rng.uniform(-15, 15, count), rng.uniform(-15, 15, count), np.full(count, -10.0)])
    angles = rng.uniform(-0.15, 0.15, (count, 2))
    directions = np.column_stack([np.sin(angles[:, 0]), np.sin(angles[:, 1]), np.ones(count)])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    forward = jaxflare.trace(biotar, origins, directions, 486.1)
    valid = np.asarray(forward.valid)
    assert valid.mean() > 0.5

    backward_lens = jaxflare.build_lens(_reversed(biotar.prescription, front_gap_mm=10.0))
    last_vertex = float(biotar.vertex_z_mm[-1])
    back_origins = np.asarray(forward.positions).copy()
    back_origins[:, 2] = last_vertex - back_origins[:, 2]
    back_directions = -np.asarray(forward.directions)
    back_directions[:, 2] *= -1
    backward = jaxflare.trace(backward_lens, back_origins[valid], back_directions[valid], 486.1)
    assert bool(jnp.all(backward.valid))
    np.testing.assert_allclose(np.asarray(backward.positions[:, :2]), origins[valid, :2], atol=1e-8)
    expected = -directions[valid]
    expected[:, 2] *= -1
    np.testing.assert_allclose(np.asarray(backward.directions), expected, atol=1e-10)


def test_ghost_path_count_and_numbering(biotar):
    paths = jaxflare.ghost_paths(biotar)
    n = biotar.num_interfaces
    assert n == 10  # 11 surfaces, the stop in air is not an interface
    assert len(paths) == n * (n - 1) // 2 == 45
    assert all(0 <= i < j < n for j, i in paths)
    assert len(set(paths)) == len(paths)
    for bad in [(3, 3), (2, 5), (n, 0), (1, -1), "ab"]:
        with pytest.raises(ValueError):
            jaxflare.trace(biotar, np.zeros((1, 3)), np.array([[0, 0, 1.0]]), 550.0, bad)


def test_ghost_stop_passes(biotar):
    stop_interface_gap = sum(1 for s in biotar.interface_surfaces if s < biotar.stop_index)  # interfaces before stop
    origins, directions = _parallel_rays([0.0, 2.0])
    straddling = (stop_interface_gap, stop_interface_gap - 1)  # j after the stop, i before: 3 passes
    assert jaxflare.trace(biotar, origins, directions, 550.0, straddling).stop_positions.shape == (2, 3, 3)
    assert jaxflare.trace(biotar, origins, directions, 550.0, (2, 1)).stop_positions.shape == (2, 1, 3)
    assert jaxflare.trace(biotar, origins, directions, 550.0).stop_positions.shape == (2, 1, 3)


def test_clear_aperture_and_iris_polygon_clip():
    lens = lens_from_toml(PLATE).with_stop_radius(10.0)
    hexagon = lens.with_aperture(blades=6, rotation_deg=0.0)
    radius = 9.5  # inside the circumcircle (10) but outside the apothem (8.66) between vertices
    vertex_ray = np.array([[radius, 0.0, -1.0]])
    edge_ray = np.array([[radius * math.cos(math.pi / 6), radius * math.sin(math.pi / 6), -1.0]])
    forward = np.array([[0.0, 0.0, 1.0]])
    assert bool(jaxflare.trace(lens, edge_ray, forward).valid[0])  # the circle lets it through
    assert bool(jaxflare.trace(hexagon, vertex_ray, forward).valid[0])
    assert not bool(jaxflare.trace(hexagon, edge_ray, forward).valid[0])
    rotated = hexagon.with_aperture(rotation_deg=30.0)
    assert bool(jaxflare.trace(rotated, edge_ray, forward).valid[0])
    assert not bool(jaxflare.trace(rotated, vertex_ray, forward).valid[0])
    outside = jaxflare.trace(lens, np.array([[0.0, 10.5, -1.0]]), forward)
    assert not bool(outside.valid[0]) and int(outside.lost_at_surface[0]) == 0


TIR_LENS = """
name = "tir"
surfaces = [
  { radius = "flat", thickness = 10.0, n_d = 1.8, v_d = 40.0, semi_aperture = 14.0, stop = true },
  { radius = -15.0, thickness = 30.0, semi_aperture = 14.0 },
]
"""


def test_total_internal_reflection_and_misses_are_masked_with_finite_gradients():
    lens = lens_from_toml(TIR_LENS)
    heights = np.array([2.0, 6.0, 10.0, 13.0])  # sin(i) = h / 15 > 1 / 1.8 beyond h = 8.3 mm: TIR
    origins, directions = _parallel_rays(heights)
    result = jaxflare.trace(lens, origins, directions, D_LINE)
    np.testing.assert_array_equal(np.asarray(result.valid), [True, True, False, False])
    np.testing.assert_array_equal(np.asarray(result.lost_at_surface), [-1, -1, 1, 1])
    wild = np.array([[0.0, 0.0, -5.0], [100.0, 0.0, -5.0], [0.0, 0.0, -5.0]])
    wild_dirs = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.999, 0.045]])
    missed = jaxflare.trace(lens, wild, wild_dirs, D_LINE)
    assert not bool(jnp.any(missed.valid))
    for value in (missed.positions, missed.directions, missed.throughput, result.positions):
        assert bool(jnp.all(jnp.isfinite(value)))

    def loss(curvatures, origins):
        changed = dataclasses.replace(lens, curvature_per_mm=curvatures)
        r = jaxflare.trace(changed, origins, np.vstack([directions, wild_dirs]), D_LINE)
        return jnp.sum(r.positions**2) + jnp.sum(r.directions) + jnp.sum(r.throughput)

    grads = jax.grad(loss, argnums=(0, 1))(lens.curvature_per_mm, jnp.asarray(np.vstack([origins, wild])))
    for grad in grads:
        assert bool(jnp.all(jnp.isfinite(grad)))


def test_gradients_through_clipped_ghost_rays_are_finite_and_match_finite_differences(biotar):
    rng = np.random.default_rng(3)
    origins = np.column_stack([rng.uniform(-40, 40, (64, 2)), np.full(64, -10.0)])  # many clipped
    directions = np.tile([0.05, -0.02, 1.0], (64, 1))
    path = (5, 2)

    def mean_y(origins):
        r = jaxflare.trace(biotar, origins, directions, 550.0, path)
        return jnp.sum(jnp.where(r.valid, r.positions[:, 1], 0.0))

    grad = jax.grad(mean_y)(jnp.asarray(origins))
    assert bool(jnp.all(jnp.isfinite(grad)))
    valid = np.asarray(jaxflare.trace(biotar, origins, directions, 550.0, path).valid)
    assert 0 < valid.sum() < valid.size
    k = int(np.flatnonzero(valid)[0])
    step = 1e-6
    bumped = origins.copy()
    bumped[k, 1] += step
    lowered = origins.copy()
    lowered[k, 1] -= step
    finite_difference = (mean_y(bumped) - mean_y(lowered)) / (2 * step)
    assert float(grad[k, 1]) == pytest.approx(float(finite_difference), rel=1e-5, abs=1e-8)


def test_uncoated_throughput_matches_fresnel_products():
    lens = lens_from_toml(PLANO_CONVEX)
    r = ((N_GLASS - 1) / (N_GLASS + 1)) ** 2
    np.testing.assert_allclose(float(jaxflare.path_fresnel_factor(lens, None, D_LINE)), (1 - r) ** 2, rtol=1e-12)
    np.testing.assert_allclose(float(jaxflare.path_fresnel_factor(lens, (1, 0), D_LINE)), (1 - r) ** 2 * r**2, rtol=1e-12)
    # oblique rays: transmittance from the exact angles at the plate
    plate = lens_from_toml(PLATE.replace("semi_aperture = 40.0, stop = true", "semi_aperture = 40.0, stop = true, coating = \"none\"").replace("semi_aperture = 40.0 }", "semi_aperture = 40.0, coating = \"none\" }"))
    angle = math.radians(30.0)
    result = jaxflare.trace(plate, np.array([[0.0, 0.0, -1.0]]), np.array([[math.sin(angle), 0.0, math.cos(angle)]]), D_LINE)
    inside = math.asin(math.sin(angle) / N_GLASS)
    r_front = float(uncoated_reflectance(1.0, N_GLASS, math.cos(angle)))
    r_back = float(uncoated_reflectance(N_GLASS, 1.0, math.cos(inside)))
    assert float(result.throughput[0]) == pytest.approx((1 - r_front) * (1 - r_back), rel=1e-12)


@pytest.mark.parametrize("name", ["zeiss_biotar", "tronnier_heliar"])
def test_on_axis_fresnel_is_the_traced_on_axis_throughput(name):
    """The closed-form on-axis factor (every surface met at its vertex at normal incidence) equals
    the throughput the exact tracer gives the on-axis ray, for every path and wavelength."""
    from jaxflare.optics import EventTable, on_axis_fresnel, path_events, trace_events

    lens = jaxflare.load_lens(name)
    paths = [None] + jaxflare.ghost_paths(lens)
    events = EventTable.from_array(np.stack([path_events(lens, path) for path in paths]))
    wavelengths = jnp.linspace(400.0, 700.0, 7)
    origins = jnp.zeros((7, 3)).at[:, 2].set(-1.0)
    directions = jnp.zeros((7, 3)).at[:, 2].set(1.0)
    traced = jax.vmap(lambda e: trace_events(lens, origins, directions, wavelengths, e, 1).throughput)(events)
    closed_form = on_axis_fresnel(lens, events, wavelengths)
    assert closed_form.shape == (len(paths), 7)
    np.testing.assert_allclose(np.asarray(closed_form), np.asarray(traced), rtol=1e-11)
    assert float(jnp.min(traced)) > 0.0  # every path's on-axis ray got through: the comparison is not vacuous


def test_default_mgf2_coating_suppresses_ghosts_near_its_design_wavelength(biotar):
    coated = jaxflare.path_fresnel_factor(biotar, (1, 0), jnp.array([450.0, 550.0, 650.0]))
    uncoated_prescription = dataclasses.replace(
        biotar.prescription,
        surfaces=tuple(dataclasses.replace(s, coating=jaxflare.CoatingSpec()) for s in biotar.prescription.surfaces),
    )
    uncoated = jaxflare.path_fresnel_factor(jaxflare.build_lens(uncoated_prescription), (1, 0), jnp.array([450.0, 550.0, 650.0]))
    assert bool(jnp.all(coated < 0.25 * uncoated))
    assert int(jnp.argmin(coated)) == 1  # quarter-wave at 550 nm reflects least there


def test_chromatic_dispersion_shortens_blue_focal_length(biotar):
    assert biotar.focal_length(450.0) < biotar.focal_length(587.56) < biotar.focal_length(650.0)


def test_float32_render_mode_stays_close_to_float64(biotar):
    origins, directions = _parallel_rays(np.linspace(-20, 20, 9))
    reference = jaxflare.trace(biotar, origins, directions, 550.0, (4, 1))
    with jax.enable_x64(False):
        lens32 = jaxflare.load_lens("zeiss_biotar")
        single = jaxflare.trace(lens32, origins.astype(np.float32), directions.astype(np.float32), 550.0, (4, 1))
        assert single.positions.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(single.valid), np.asarray(reference.valid))
    valid = np.asarray(reference.valid)
    np.testing.assert_allclose(np.asarray(single.positions)[valid], np.asarray(reference.positions)[valid], atol=2e-3)


def test_one_compilation_serves_every_ghost_path(biotar):
    origins, directions = _parallel_rays([1.0, 2.0])
    jaxflare.trace(biotar, origins, directions, 550.0, (1, 0))
    jaxflare.trace(biotar, origins, directions, 550.0, (5, 2))
    before = eqx.debug.get_num_traces(jaxflare.optics.trace_events.__wrapped__)
    assert before >= 1
    for path in jaxflare.ghost_paths(biotar):
        jaxflare.trace(biotar, origins, directions, 550.0, path)
    # paths with 1 and 3 stop passes both compiled above: no ghost path compiles again
    assert eqx.debug.get_num_traces(jaxflare.optics.trace_events.__wrapped__) == before


DEEP_MENISCUS = """
name = "deep sphere in a glass block"
surfaces = [
  { radius = 10.0, thickness = 15.0, n_d = 1.5, v_d = 60.0, semi_aperture = 9.5, coating = "none" },
  { radius = "flat", thickness = 30.0, semi_aperture = 20.0, stop = true, coating = "none" },
]
"""


def test_backward_ghost_ray_hits_the_vertex_sheet_ahead_not_the_far_sheet_behind():
    # Reflected at the flat back (z = 15), the ghost ray travels back to the R = 10 mm sphere. The
    # sphere's far sheet (z = 10 + sqrt(100 - h^2)) lies *behind* such a ray for h < 8.7 mm and is
    # the nearer root along the line; the hit must be the vertex sheet ahead (z = 10 - sqrt(...)).
    lens = lens_from_toml(DEEP_MENISCUS)
    heights = np.array([1.0, 3.0, 5.0])
    result = jaxflare.trace(lens, *_parallel_rays(heights), D_LINE, path=(1, 0), record_events=True)
    events = jaxflare.path_events(lens, (1, 0))
    back_at_front = int(np.flatnonzero((events[:, 0] == 0) & (events[:, 1] == -1))[0])
    hit = np.asarray(result.event_positions[back_at_front])
    rho = np.hypot(hit[:, 0], hit[:, 1])
    np.testing.assert_allclose(hit[:, 2], 10.0 - np.sqrt(100.0 - rho**2), atol=1e-9)  # on the vertex sheet
    assert np.all(hit[:, 2] < 15.0)  # ahead of the backward ray, which left z = 15
    assert bool(jnp.all(result.valid))


CROSSING_SURFACES = """
name = "surfaces that cross at 4.4 mm height"
surfaces = [
  { radius = 10.0, thickness = 1.0, n_d = 1.5, v_d = 60.0, semi_aperture = 9.0, stop = true },
  { radius = "flat", thickness = 40.0, semi_aperture = 20.0 },
]
"""


def test_a_surface_behind_the_ray_is_a_miss_not_a_backward_step():
    # The sphere's sag passes the flat back surface (z = 1) at h = sqrt(19) = 4.36 mm: beyond that
    # height a ray is already past the flat surface when it leaves the sphere. Stepping backwards
    # to it (t < 0) would be unphysical; the ray is lost at surface 1 instead.
    lens = lens_from_toml(CROSSING_SURFACES)
    result = jaxflare.trace(lens, *_parallel_rays(np.array([2.0, 4.0, 5.0, 7.0])), D_LINE)
    np.testing.assert_array_equal(np.asarray(result.valid), [True, True, False, False])
    np.testing.assert_array_equal(np.asarray(result.lost_at_surface), [-1, -1, 1, 1])


def test_per_ray_event_tables_match_one_path_at_a_time(biotar):
    """A batch in which every ray follows its own path (the renderer's adaptive batches) traces
    each ray exactly as a batch of that path alone does."""
    import numpy as np

    from jaxflare.optics import EventTable, trace_events

    paths = [None, (5, 0), (7, 4), (9, 7), (4, 2)]
    rng = np.random.default_rng(3)
    count = 400
    origins = np.concatenate([rng.uniform(-20, 20, (count, 2)), np.full((count, 1), -5.0)], axis=1)
    directions = np.concatenate([rng.normal(0, 0.05, (count, 2)), np.ones((count, 1))], axis=1)
    wavelength = rng.uniform(400, 700, count)
    which = rng.integers(0, len(paths), count)
    tables = np.stack([jaxflare.path_events(biotar, p) for p in paths])
    mixed = trace_events(biotar, jnp.asarray(origins), jnp.asarray(directions), jnp.asarray(wavelength), EventTable.from_array(tables[which]), 3)
    for k, path in enumerate(paths):
        rows = which == k
        alone = jaxflare.trace(biotar, origins[rows], directions[rows], wavelength[rows], path)
        np.testing.assert_array_equal(np.asarray(mixed.valid)[rows], np.asarray(alone.valid))
        np.testing.assert_allclose(np.asarray(mixed.positions)[rows], np.asarray(alone.positions), atol=1e-9)
        np.testing.assert_allclose(np.asarray(mixed.throughput)[rows], np.asarray(alone.throughput), rtol=1e-12, atol=1e-15)
        passes = alone.stop_positions.shape[1]
        np.testing.assert_allclose(np.asarray(mixed.stop_positions)[rows][:, :passes], np.asarray(alone.stop_positions), atol=1e-9)


def test_nearby_batch_sizes_share_one_compilation(biotar):
    """Batches are traced in size buckets (``ray_bucket``): 1000 and 1001 rays compile once (as
    do 1 and 2048), and the padding never shows in the result."""
    from jaxflare.optics._trace import ray_bucket

    assert ray_bucket(1000) == ray_bucket(1001) == ray_bucket(1) == ray_bucket(2048) == 2048
    assert ray_bucket(2049) == 4096 and ray_bucket(16385) == 32768
    origins, directions = _parallel_rays(np.linspace(-3.0, 3.0, 1001))
    first = jaxflare.trace(biotar, origins[:1000], directions[:1000], 550.0, (4, 1))
    before = eqx.debug.get_num_traces(jaxflare.optics.trace_events.__wrapped__)
    second = jaxflare.trace(biotar, origins, directions, 550.0, (4, 1))
    assert eqx.debug.get_num_traces(jaxflare.optics.trace_events.__wrapped__) == before
    assert second.positions.shape == (1001, 3) and first.positions.shape == (1000, 3)
    np.testing.assert_array_equal(np.asarray(second.valid[:1000]), np.asarray(first.valid))
    np.testing.assert_allclose(np.asarray(second.positions[:1000]), np.asarray(first.positions), atol=1e-12)
