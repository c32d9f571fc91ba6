"""Polynomial path systems: accuracy against the exact tracer, the swap contract with
:func:`jaxflare.trace`, detection of where each construction fails, gradients, the disk cache."""

import dataclasses
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxflare
from tests.helpers import lens_from_toml

FAST = dict(validation_rays=8192, cache=False)
RAYS = 2048
"""Rays per evaluation in most tests: one ray count means one compiled evaluator and tracer for
them (each distinct count compiles both again)."""


@functools.cache
def built(lens_name: str, path=None, degree: int = 5, construction: str = "least-squares", sparse_terms=None):
    """A system built with ``FAST`` options, once per module: several tests compare the same
    systems (building one takes seconds, a degree-7 one about 20)."""
    return jaxflare.path_system(jaxflare.load_lens(lens_name), path, degree=degree, construction=construction, sparse_terms=sparse_terms, **FAST)


def domain_rays(system, count, seed, field_scale=1.0, radius_scale=1.0, wavelength_nm=(420.0, 680.0)):
    """Rays from z = -5 mm crossing the system's entrance plane uniformly over the front aperture,
    at field angles up to ``field_scale`` times the domain's largest, random wavelengths."""
    rng = np.random.default_rng(seed)
    lens, domain = system.lens, system.domain
    radius = float(lens.semi_aperture_mm[0]) * radius_scale
    r, phi = radius * np.sqrt(rng.random(count)), 2 * np.pi * rng.random(count)
    sin_field = math.sin(math.radians(domain.max_field_angle_deg * field_scale)) * np.sqrt(rng.random(count))
    psi = 2 * np.pi * rng.random(count)
    directions = np.stack([sin_field * np.cos(psi), sin_field * np.sin(psi), np.sqrt(1 - sin_field**2)], -1)
    start = domain.entrance_z_mm - 4.0
    back = (domain.entrance_z_mm - start) / directions[:, 2]
    origins = np.stack([r * np.cos(phi), r * np.sin(phi), np.full(count, domain.entrance_z_mm)], -1) - back[:, None] * directions
    wavelength = rng.uniform(*wavelength_nm, count)
    return origins, directions, wavelength


def sensor_error_mm(a, b):
    return np.linalg.norm(np.asarray(a.positions)[:, :2] - np.asarray(b.positions)[:, :2], axis=-1)


@pytest.fixture(scope="module")
def primary7(biotar):
    return built("zeiss_biotar", None, 7)


def test_swap_contract_same_outputs_as_trace(biotar, primary7):
    origins, directions, wavelength = domain_rays(primary7, RAYS, seed=1)
    exact = jaxflare.trace(biotar, origins, directions, wavelength)
    poly = dataclasses.replace(primary7, fallback_fraction=1.0)(origins, directions, wavelength)
    for field in ("positions", "directions", "valid", "throughput", "lost_at_surface", "stop_positions"):
        assert getattr(poly, field).shape == getattr(exact, field).shape, field
    assert bool(jnp.all(poly.trusted))  # with a full exact fallback every ray is answered
    untrusted = ~np.asarray(primary7.polynomial(origins, directions, wavelength).trusted)
    np.testing.assert_array_equal(np.asarray(poly.valid)[untrusted], np.asarray(exact.valid)[untrusted])
    valid = np.asarray(poly.valid)
    np.testing.assert_allclose(np.asarray(poly.positions)[valid, 2], float(biotar.sensor_z_mm))
    assert np.all(np.isfinite(np.asarray(poly.positions))) and np.all(np.isfinite(np.asarray(poly.throughput)))


def test_trusted_rays_are_within_tolerance_and_masks_agree(biotar, primary7):
    origins, directions, wavelength = domain_rays(primary7, RAYS, seed=2)
    exact = jaxflare.trace(biotar, origins, directions, wavelength)
    poly = primary7.polynomial(origins, directions, wavelength)  # no fallback: the polynomial's own answers
    trusted = np.asarray(poly.trusted)
    both = trusted & np.asarray(poly.valid) & np.asarray(exact.valid)
    tolerance = primary7.report.tolerance_um * 1e-3
    error = sensor_error_mm(poly, exact)[both]
    assert trusted.mean() > 0.05  # at half a pixel, degree 7 covers the central part of the domain
    assert np.percentile(error, 99) <= tolerance
    assert error.max() <= 3 * tolerance
    # validity of trusted rays agrees with the exact trace except at the rims of apertures
    disagree = (np.asarray(poly.valid) != np.asarray(exact.valid)) & trusted
    assert disagree.mean() < 0.02
    # and the throughput (Fresnel product) follows the exact one
    np.testing.assert_allclose(np.asarray(poly.throughput)[both], np.asarray(exact.throughput)[both], atol=2e-3)


def test_inputs_outside_the_domain_are_flagged_then_traced_exactly(biotar, primary7):
    origins, directions, wavelength = domain_rays(primary7, RAYS, seed=3, field_scale=1.6)
    field = np.degrees(np.arccos(directions[:, 2]))
    outside = field > primary7.domain.max_field_angle_deg
    assert outside.sum() > 400
    poly = primary7.polynomial(origins, directions, wavelength)
    assert not np.any(np.asarray(poly.trusted)[outside])
    assert not np.any(np.asarray(poly.valid)[outside])
    assert np.all(np.asarray(poly.lost_at_surface)[outside] == -2)
    # the exact fallback answers them (capacity: all of this small batch)
    system = dataclasses.replace(primary7, fallback_fraction=1.0)
    exact = jaxflare.trace(biotar, origins, directions, wavelength)
    result = system(origins, directions, wavelength)
    assert np.all(np.asarray(result.trusted))
    np.testing.assert_array_equal(np.asarray(result.valid)[outside], np.asarray(exact.valid)[outside])
    both = outside & np.asarray(exact.valid)
    np.testing.assert_allclose(np.asarray(result.positions)[both], np.asarray(exact.positions)[both], atol=1e-9)
    # a wavelength outside the band is untrusted too
    poly_uv = primary7.polynomial(origins[:8], directions[:8] * 0 + [0, 0, 1], 300.0)
    assert not np.any(np.asarray(poly_uv.trusted))


def test_overflowing_the_fallback_capacity_returns_invalid_untrusted_rays(primary7):
    origins, directions, wavelength = domain_rays(primary7, RAYS, seed=4, field_scale=3.0)
    result = primary7(origins, directions, wavelength)  # default capacity: 1/8 of the batch
    untrusted = ~np.asarray(result.trusted)
    assert untrusted.sum() > 0
    assert not np.any(np.asarray(result.valid)[untrusted])
    assert np.all(np.asarray(result.lost_at_surface)[untrusted] == -2)


def test_stopping_down_and_a_polygonal_iris_need_no_rebuild(biotar, primary7):
    stopped = biotar.with_f_number(4.0).with_aperture(blades=6, rotation_deg=10.0)
    system = primary7.with_lens(stopped)
    origins, directions, wavelength = domain_rays(system, RAYS, seed=5)
    exact = jaxflare.trace(stopped, origins, directions, wavelength)
    poly = system.polynomial(origins, directions, wavelength)
    trusted = np.asarray(poly.trusted)
    agree = np.asarray(poly.valid) == np.asarray(exact.valid)
    assert agree[trusted].mean() > 0.98
    assert np.asarray(exact.valid).mean() < 0.5 * np.asarray(jaxflare.trace(biotar, origins, directions, wavelength).valid).mean()


def test_error_falls_with_degree_over_the_domain_for_the_fit(biotar):
    p99 = [built("zeiss_biotar", None, d).report.error_um_p99 for d in (1, 3, 5, 7)]
    assert p99[0] > p99[1] > p99[2] > p99[3], p99


def test_taylor_converges_near_the_axis_but_not_at_the_rim_of_a_fast_lens(biotar):
    # The f/1.4 Biotar's series about the axis converges slowly, if at all, at the rim of the
    # front lens: over the whole domain degree 3 is no better than degree 1 (a measured failure,
    # which the error estimate and trust table must catch), while near the axis each degree helps.
    systems = {d: built("zeiss_biotar", None, d, "taylor") for d in (1, 3, 5)}
    near = domain_rays(systems[1], RAYS, seed=12, field_scale=0.2, radius_scale=0.2, wavelength_nm=(560.0, 600.0))
    exact = jaxflare.trace(biotar, *near)
    ok = np.asarray(exact.valid)
    errors = [np.percentile(sensor_error_mm(systems[d].polynomial(*near), exact)[ok], 99) for d in (1, 3, 5)]
    assert errors[0] > 4 * errors[1] > 16 * errors[2], errors
    assert systems[3].report.error_um_p99 > 0.5 * systems[1].report.error_um_p99
    assert systems[3].report.trusted_fraction < 0.5


def test_taylor_is_exact_near_the_axis_and_worse_than_the_fit_at_the_rim(biotar):
    taylor = built("zeiss_biotar", None, 5, "taylor")
    fit = built("zeiss_biotar", None, 5)
    near = domain_rays(taylor, RAYS, seed=6, field_scale=0.1, radius_scale=0.1, wavelength_nm=(575.0, 585.0))
    exact = jaxflare.trace(biotar, *near)
    ok = np.asarray(exact.valid)
    assert sensor_error_mm(taylor.polynomial(*near), exact)[ok].max() < 1e-4  # 0.1 um: the expansion point
    assert taylor.report.error_um_max > fit.report.error_um_max


def assert_wrong_answers_are_caught(system, lens, path=None, seed=7):
    """On fresh in-domain rays: the polynomial really is wrong over part of the domain, and at
    least 99 % of the rays where it is wrong by more than three tolerances are untrusted or
    invalid, while the trusted answers meet the tolerance."""
    origins, directions, wavelength = domain_rays(system, 8192, seed=seed)
    exact = jaxflare.trace(lens, origins, directions, wavelength, path)
    poly = system.polynomial(origins, directions, wavelength)
    raw = eqx.tree_at(lambda s: (s.estimate_limit_mm, s.trust_table), system, (jnp.inf, jnp.ones_like(system.trust_table)))
    raw_result = raw.polynomial(origins, directions, wavelength)
    tolerance = system.report.tolerance_um * 1e-3
    wrong = np.asarray(exact.valid & raw_result.valid) & (sensor_error_mm(raw_result, exact) > 3 * tolerance)
    assert wrong.sum() > 50
    caught = ~np.asarray(poly.trusted) | ~np.asarray(poly.valid)
    assert caught[wrong].mean() > 0.99
    answered = np.asarray(poly.valid & poly.trusted & exact.valid)
    if answered.sum() > 20:
        assert np.percentile(sensor_error_mm(poly, exact)[answered], 99) <= 1.5 * tolerance
    return poly


@pytest.mark.parametrize("construction", ["fit", "taylor"])
def test_wide_angle_lens_errors_are_flagged_not_trusted(construction):
    # The fisheye's 77 degree half field is far beyond what a degree-3 polynomial can follow.
    lens = jaxflare.load_lens("minolta_fisheye")
    system = jaxflare.path_system(lens, None, degree=3, construction=construction, **FAST)
    assert_wrong_answers_are_caught(system, lens)
    assert system.report.trusted_fraction < 0.5


@pytest.mark.parametrize("construction", ["fit", "taylor"])
def test_strongly_curved_ghost_path_errors_are_flagged(biotar, construction):
    # Ghost (5, 0) reflects off the front surface from inside: its sensor map bends so strongly
    # that at degree 5 the error is hundreds of micrometres over most of the domain.
    system = jaxflare.path_system(biotar, (5, 0), degree=5, construction=construction, **FAST)
    assert system.report.error_um_p99 > 10 * system.report.tolerance_um
    assert_wrong_answers_are_caught(system, biotar, (5, 0))


TIR_LENS = """
name = "strong back curve: total internal reflection beyond 6.7 mm"
surfaces = [
  { radius = "flat", thickness = 8.0, n_d = 1.8, v_d = 40.0, semi_aperture = 10.0, coating = "none" },
  { radius = -12.0, thickness = 4.0, semi_aperture = 10.0, coating = "none" },
  { radius = "flat", thickness = 12.0, semi_aperture = 9.0, stop = true },
]
"""


def test_total_internal_reflection_is_not_silently_trusted():
    lens = lens_from_toml(TIR_LENS)
    system = jaxflare.path_system(lens, None, degree=5, max_field_angle_deg=5.0, **FAST)
    origins, directions, wavelength = domain_rays(system, 8192, seed=8)
    exact = jaxflare.trace(lens, origins, directions, wavelength)
    poly = system.polynomial(origins, directions, wavelength)
    # inside the glass, rays meet the back sphere beyond asin(1 / n) from its normal: lost to TIR
    lost_at_back = np.asarray(exact.lost_at_surface) == 1
    assert lost_at_back.sum() > 1000
    reported_valid = np.asarray(poly.valid) & np.asarray(poly.trusted)
    assert reported_valid[lost_at_back].mean() < 0.01


def test_gradients_match_the_exact_tracer(biotar, primary7):
    origins, directions, wavelength = domain_rays(primary7, 64, seed=9, field_scale=0.5, radius_scale=0.5)
    exact = jaxflare.trace(biotar, origins, directions, wavelength)
    poly = primary7.polynomial(origins, directions, wavelength)
    keep = np.flatnonzero(np.asarray(exact.valid & poly.valid & poly.trusted))[:8]
    o, d, w = jnp.asarray(origins[keep]), jnp.asarray(directions[keep]), jnp.asarray(wavelength[keep])
    c = biotar.curvature_per_mm[3]

    def with_curvature(curvature):
        return eqx.tree_at(lambda l: l.curvature_per_mm, biotar, biotar.curvature_per_mm.at[3].set(curvature))

    # Sensor x and y summed over the rays, as functions of the rays and of one lens curvature. The
    # polynomial is re-fitted for the perturbed lens (refit is differentiable); at the unperturbed
    # lens the refit equals the system, so one Jacobian gives both the ray and the lens gradients.
    def sensor_sums(trace_with):
        def sums(o, d, curvature):
            positions = trace_with(with_curvature(curvature), o, d).positions
            return jnp.stack([jnp.sum(positions[:, 0]), jnp.sum(positions[:, 1])])

        return jax.jit(jax.jacrev(sums, argnums=(0, 1, 2)))(o, d, c)  # one program, not an eager op-by-op compile

    exact_jac = sensor_sums(lambda lens, o, d: jaxflare.trace(lens, o, d, w))
    poly_jac = sensor_sums(lambda lens, o, d: jaxflare.refit(primary7, lens).polynomial(o, d, w))
    # focused at infinity, the sensor position hardly depends on the entrance position (only through
    # aberrations) and mostly on the direction (by the focal length): compare on that scale
    exact_grads, poly_grads = (exact_jac[0][0], exact_jac[1][0]), (poly_jac[0][0], poly_jac[1][0])
    scale = max(np.abs(np.asarray(g)).max() for g in exact_grads)
    for g_exact, g_poly in zip(exact_grads, poly_grads):
        np.testing.assert_allclose(np.asarray(g_poly), np.asarray(g_exact), atol=0.01 * scale)
    # with respect to the lens parameter (sensor y), against the derivative of the exact trace
    g_exact, g_poly = exact_jac[2][1], poly_jac[2][1]
    assert float(g_exact) != 0.0
    np.testing.assert_allclose(float(g_poly), float(g_exact), rtol=0.05)


def test_outputs_and_gradients_stay_finite_for_wild_inputs(primary7):
    rng = np.random.default_rng(10)
    origins = rng.normal(0, 50, (64, 3))
    directions = rng.normal(0, 1, (64, 3))  # some point backwards
    poly = primary7.polynomial(origins, directions, 550.0)
    for leaf in (poly.positions, poly.directions, poly.throughput, poly.stop_positions):
        assert np.all(np.isfinite(np.asarray(leaf)))
    grad = jax.grad(lambda o: jnp.sum(primary7(o, directions, 550.0).positions))(jnp.asarray(origins))
    assert np.all(np.isfinite(np.asarray(grad)))


def test_ghost_paths_of_a_lens_share_one_compiled_evaluator(biotar):
    one_pass = [p for p in jaxflare.ghost_paths(biotar) if int(np.sum(jaxflare.path_events(biotar, p)[:, 0] == biotar.stop_index)) == 1]
    a = dataclasses.replace(jaxflare.path_system(biotar, one_pass[0], degree=3, **FAST), fallback_fraction=1.0)
    b = dataclasses.replace(jaxflare.path_system(biotar, one_pass[-1], degree=3, **FAST), fallback_fraction=1.0)
    assert a.num_stop_passes == b.num_stop_passes
    origins, directions, wavelength = domain_rays(a, 128, seed=11)
    traces = lambda: eqx.debug.get_num_traces(jaxflare.polynomial.evaluate.__wrapped__)  # noqa: E731
    start = traces()
    a(origins, directions, wavelength)
    before = traces()
    assert before >= start  # a compiled (or reused) the evaluator
    result = b(origins, directions, wavelength)
    assert traces() == before
    exact = jaxflare.trace(biotar, origins, directions, wavelength, path=one_pass[-1])
    assert np.mean(np.asarray(result.valid) == np.asarray(exact.valid)) > 0.95  # it evaluated b's path


def test_sparse_fit_keeps_fewer_terms_at_similar_accuracy(biotar):
    dense = built("zeiss_biotar", None, 5)
    sparse = built("zeiss_biotar", None, 5, sparse_terms=30)
    assert sparse.num_terms < dense.num_terms
    assert sparse.report.error_um_p99 < 3 * dense.report.error_um_p99


def test_disk_cache_returns_the_same_system_and_keys_on_the_lens(biotar, tmp_path):
    first = jaxflare.path_system(biotar, (5, 0), degree=3, validation_rays=4096, cache=tmp_path)
    files = list(tmp_path.glob("path-*.npz"))
    assert len(files) == 1
    second = jaxflare.path_system(biotar, (5, 0), degree=3, validation_rays=4096, cache=tmp_path)
    np.testing.assert_array_equal(np.asarray(second.coefficients), np.asarray(first.coefficients))
    np.testing.assert_array_equal(np.asarray(second.trust_table), np.asarray(first.trust_table))
    assert second.report == first.report and second.clip_surfaces == first.clip_surfaces
    thicker = eqx.tree_at(lambda l: l.thickness_mm, biotar, biotar.thickness_mm.at[2].add(0.5))
    jaxflare.path_system(thicker, (5, 0), degree=3, validation_rays=4096, cache=tmp_path)
    assert len(list(tmp_path.glob("path-*.npz"))) == 2
    # a damaged entry is rebuilt, not trusted
    files[0].write_bytes(b"not an npz")
    again = jaxflare.path_system(biotar, (5, 0), degree=3, validation_rays=4096, cache=tmp_path)
    np.testing.assert_allclose(np.asarray(again.coefficients), np.asarray(first.coefficients))


@pytest.mark.parametrize(
    "options, message",
    [
        (dict(degree=0), "degree"),
        (dict(degree=12), "degree"),
        (dict(construction="spline"), "construction"),
        (dict(construction="taylor", sparse_terms=10), "sparse_terms"),
        (dict(max_field_angle_deg=95.0), "max_field_angle_deg"),
        (dict(wavelength_range_nm=(700.0, 400.0)), "wavelength_range_nm"),
        (dict(fallback="maybe"), "fallback"),
    ],
)
def test_bad_options_are_clear_errors(biotar, options, message):
    with pytest.raises(ValueError, match=message):
        jaxflare.path_system(biotar, None, cache=False, **options)


def test_bad_path_is_a_clear_error(biotar):
    with pytest.raises(ValueError, match="ghost path"):
        jaxflare.path_system(biotar, (2, 5), cache=False)


def test_field_of_view_follows_the_lens_not_the_pinhole_formula():
    fisheye = jaxflare.load_lens("minolta_fisheye")
    rectilinear = math.degrees(math.atan(0.5 * math.hypot(36, 24) / fisheye.focal_length()))
    assert jaxflare.half_field_of_view_deg(fisheye) > rectilinear + 15
    biotar = jaxflare.load_lens("zeiss_biotar")
    pinhole = math.degrees(math.atan(0.5 * math.hypot(36, 24) / biotar.focal_length()))
    assert jaxflare.half_field_of_view_deg(biotar) == pytest.approx(pinhole, abs=0.5)
