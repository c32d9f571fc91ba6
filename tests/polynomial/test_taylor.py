"""Taylor expansion of the exact trace: convergence order against ``jaxflare.trace``, paraxial
first-order terms, cylindrical and aspheric surfaces, dispersion, and invalid on-axis rays."""

import functools

import equinox as eqx
import numpy as np
import pytest
from tests.helpers import lens_from_toml

import jaxflare
from jaxflare.polynomial import monomial_exponents, monomials_numpy
from jaxflare.polynomial import taylor_path_coefficients

D_LINE = 587.56
ENTRANCE_Z = -10.0
RAYS = 8

ASPHERIC = """
name = "aspheric doublet"
surfaces = [
  { radius = 40.0, thickness = 8.0, n_d = 1.69, v_d = 53, semi_aperture = 15.0, conic = -0.6, aspheric = [-3e-6, 2e-9, -1e-12] },
  { radius = -60.0, thickness = 5.0, semi_aperture = 15.0 },
  { radius = "flat", thickness = 5.0, semi_aperture = 10.0, stop = true },
  { radius = -30.0, thickness = 3.0, n_d = 1.75, v_d = 28.0, semi_aperture = 12.0, aspheric = [1e-5, -4e-8] },
  { radius = -45.0, thickness = 40.0, semi_aperture = 12.0 },
]
"""


@functools.lru_cache(maxsize=None)
def _lens(name):
    """A bundled lens or the aspheric test lens, built once (and compiled once) per session."""
    return lens_from_toml(ASPHERIC) if name == "aspheric" else jaxflare.load_lens(name)


def _domain(front_radius_mm, sin_max_field, center_nm=D_LINE, half_width_nm=100.0):
    return dict(
        entrance_z_mm=ENTRANCE_Z, front_radius_mm=front_radius_mm, sin_max_field=sin_max_field,
        wavelength_center_nm=center_nm, wavelength_half_width_nm=half_width_nm,
    )


def _exact(lens, path, variables, domain):
    """Exact trace of rays given by normalised (u, v, s, t, w); all must be valid. Padded with
    axial rays to a batch of RAYS, so that one compilation per lens serves every test."""
    radius, sine = domain["front_radius_mm"], domain["sin_max_field"]
    u, v, s, t, w = np.concatenate([variables, np.zeros((RAYS - len(variables), 5))]).T
    origins = np.stack([radius * u, radius * v, np.full_like(u, domain["entrance_z_mm"])], axis=1)
    directions = np.stack([sine * s, sine * t, np.sqrt(1.0 - sine**2 * (s**2 + t**2))], axis=1)
    wavelength = domain["wavelength_center_nm"] + domain["wavelength_half_width_nm"] * w
    result = jaxflare.trace(lens, origins, directions, wavelength, path, record_events=True)
    assert bool(np.all(result.valid)), np.asarray(result.lost_at_surface)
    count = len(variables)
    return {
        "sensor": np.asarray(result.positions)[:count, :2],
        "direction": np.asarray(result.directions)[:count, :2],
        "stop": np.moveaxis(np.asarray(result.stop_positions)[:count, :, :2], 1, 0),
        "events": np.asarray(result.event_positions)[:, :count, :2],
    }


def _evaluate(coefficients, variables, degree):
    return monomials_numpy(variables, monomial_exponents(degree)) @ np.moveaxis(coefficients, -1, -2)


def _sensor_errors(lens, path, degree, domain, scales, seed=0):
    """Largest sensor-position error (mm) of the Taylor polynomial at random inputs times each scale."""
    inputs = np.random.default_rng(seed).uniform(-1.0, 1.0, (RAYS, 5))
    coefficients = taylor_path_coefficients(lens, path, degree, **domain)["sensor"]
    errors = []
    for scale in scales:
        exact = _exact(lens, path, scale * inputs, domain)["sensor"]
        errors.append(np.abs(_evaluate(coefficients, scale * inputs, degree) - exact).max())
    return np.array(errors)


@pytest.mark.parametrize("path", [None, (3, 1)])
@pytest.mark.parametrize("degree", [2, 4, 6])
def test_error_falls_with_the_next_order(biotar, path, degree):
    # Even degrees: the leading omitted terms (degree d + 1, odd in u, v, s, t as a rotationally
    # symmetric lens demands) are large. After an odd degree the next even terms need odd powers of
    # w and are small (weak dispersion), so the error there falls nearly like eps^(d + 2).
    errors = _sensor_errors(biotar, path, degree, _domain(37.0, 0.25), scales=(0.1, 0.05))
    ratio = errors[0] / errors[1]
    assert 2 ** (degree + 1) / 2 < ratio < 2 ** (degree + 1) * 2, (errors, ratio)
    assert errors[1] < 0.02


def test_stop_and_event_points_match_the_trace(biotar):
    path, degree, domain = (7, 2), 5, _domain(37.0, 0.25)
    events = jaxflare.path_events(biotar, path)
    rows = [0, int(np.sum(events[:, 3])) - 1]
    inputs = 0.05 * np.random.default_rng(1).uniform(-1.0, 1.0, (6, 5))
    series = taylor_path_coefficients(biotar, path, degree, record_event_rows=rows, **domain)
    exact = _exact(biotar, path, inputs, domain)
    assert series["stop"].shape[0] == 3  # the ghost crosses the stop forwards, backwards, forwards
    np.testing.assert_allclose(_evaluate(series["stop"], inputs, degree), exact["stop"], atol=1e-6)
    np.testing.assert_allclose(_evaluate(series["events"], inputs, degree), exact["events"][rows], atol=1e-6)
    np.testing.assert_allclose(_evaluate(series["direction"], inputs, degree), exact["direction"], atol=1e-8)


@pytest.mark.parametrize("name", ["zeiss_biotar", "schneider_anamorphic"])
def test_linear_terms_are_the_paraxial_ray_transfer_matrix(name):
    lens = _lens(name)
    radius, sine = 10.0, 0.1
    series = taylor_path_coefficients(lens, None, 3, **_domain(radius, sine))
    exponents = monomial_exponents(3)
    index = {var: int(np.flatnonzero((exponents == np.eye(5, dtype=int)[k]).all(axis=1))[0]) for k, var in enumerate("uvst")}
    after_last = float(lens.sensor_z_mm) - float(lens.vertex_z_mm[-1])
    for axis, (position, angle), plane in ((0, "us", "x"), (1, "vt", "y")):
        # (height, reduced angle): entrance plane -> vertex 0 -> last vertex -> sensor, all in air
        matrix = (
            np.array([[1.0, after_last], [0.0, 1.0]])
            @ lens.paraxial_system(D_LINE, plane)
            @ np.array([[1.0, -ENTRANCE_Z], [0.0, 1.0]])
        )
        linear_sensor = series["sensor"][axis, [index[position], index[angle]]]
        linear_direction = series["direction"][axis, [index[position], index[angle]]]
        np.testing.assert_allclose(linear_sensor, [radius * matrix[0, 0], sine * matrix[0, 1]], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(linear_direction, [radius * matrix[1, 0], sine * matrix[1, 1]], rtol=1e-9, atol=1e-12)
        other = [index[k] for k in "uvst" if k not in (position, angle)] + [5]  # index 5: w
        np.testing.assert_array_equal(series["sensor"][axis, other], 0.0)


def test_focused_at_infinity_the_image_height_is_efl_times_the_direction(biotar):
    lens = biotar.focused_at(np.inf)
    series = taylor_path_coefficients(lens, None, 1, **_domain(20.0, 0.1))
    # linear order: u, v, s, t, w at indices 1..5; a parallel bundle focuses to one point
    np.testing.assert_allclose(series["sensor"][1, 2], 0.0, atol=1e-9)
    np.testing.assert_allclose(series["sensor"][1, 4], 0.1 * lens.focal_length(), rtol=1e-9)


@pytest.mark.parametrize(
    "lens_source, path",
    [("schneider_anamorphic", None), ("schneider_anamorphic", (5, 1)), ("aspheric", None), ("aspheric", (2, 0))],
)
def test_cylindrical_and_aspheric_surfaces_converge(lens_source, path):
    lens = _lens(lens_source)
    domain = _domain(10.0, 0.15)
    for degree in (3, 7):
        errors = _sensor_errors(lens, path, degree, domain, scales=(0.1, 0.05))
        assert errors[0] / errors[1] > 2 ** (degree + 1) / 2, (degree, errors)
        assert errors[1] < 1e-5


def test_dispersion_series_reproduces_the_chromatic_shift(biotar):
    domain = _domain(37.0, 0.25, center_nm=550.0, half_width_nm=150.0)
    inputs = np.array([[0.1, -0.05, 0.1, 0.05, w] for w in (-0.5, 0.0, 0.5)])
    exact = _exact(biotar, None, inputs, domain)["sensor"]
    exact_shift = exact[[0, 2]] - exact[1]
    assert np.abs(exact_shift).max() > 5e-3  # lateral colour of this off-axis ray, in mm
    shift_errors = []
    for degree in (2, 4, 6):
        position = _evaluate(taylor_path_coefficients(biotar, None, degree, **domain)["sensor"], inputs, degree)
        shift_errors.append(np.abs(position[[0, 2]] - position[1] - exact_shift).max())
    assert shift_errors[0] > 3 * shift_errors[1] > 9 * shift_errors[2], shift_errors
    assert shift_errors[2] < 1e-3 * np.abs(exact_shift).max()


def test_an_invalid_on_axis_ray_is_an_error(biotar):
    # A negative gap puts surface 4 behind surface 3: the exact tracer loses even the axial ray
    # there. (Total internal reflection cannot stop the axial ray: it meets every surface normally.)
    crossed = eqx.tree_at(lambda lens: lens.thickness_mm, biotar, biotar.thickness_mm.at[3].set(-2.0))
    axial = jaxflare.trace(crossed, np.array([[0.0, 0.0, ENTRANCE_Z]]), np.array([[0.0, 0.0, 1.0]]), D_LINE, (8, 1))
    assert not bool(axial.valid[0]) and int(axial.lost_at_surface[0]) == 4
    with pytest.raises(ValueError, match=r"ghost path \(8, 1\).*surface 4"):
        taylor_path_coefficients(crossed, (8, 1), 3, **_domain(37.0, 0.25))
