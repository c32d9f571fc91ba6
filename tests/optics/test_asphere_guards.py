"""The tracer's guards hold on aspheres and wide-angle lenses: rays far outside the clear apertures
(where an even-asphere polynomial overflows float32) give finite stop positions, sensor positions
and gradients, while the rays that pass are traced as before (float32 against float64)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxflare
from jaxflare.optics import Vector, cast_floating, intersect
from tests.helpers import lens_from_toml

# A strong moulded asphere (f ~ 10 mm at f/1, like a Thorlabs AL1815 condenser) with terms up to
# A10, behind it a weak aspheric rear surface.
ASPHERE = """
name = "strong asphere"
f_number = 1.0
surfaces = [
  { radius = 8.0, thickness = 6.0, n_d = 1.77, v_d = 50.0, semi_aperture = 9.0, conic = -1.6, aspheric = [1.2e-4, -3.0e-6, 2.0e-8, -1.0e-10] },
  { radius = "flat", thickness = 0.5, semi_aperture = 9.0, stop = true },
  { radius = -40.0, thickness = 12.0, n_d = 1.5, v_d = 60.0, semi_aperture = 9.0, aspheric = [2.0e-5, 1e-7] },
  { radius = -60.0, thickness = 5.0, semi_aperture = 9.0 },
]
"""


def _rays(count: int, spread_mm: float, slope: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    origins = np.c_[rng.uniform(-spread_mm, spread_mm, (count, 2)), np.full(count, -5.0)]
    directions = np.c_[rng.uniform(-slope, slope, (count, 2)), np.ones(count)]
    return origins, directions


def _finite_everywhere(lens, origins, directions, path):
    def loss(o, l):
        r = jaxflare.trace(l, o, directions, 550.0, path)
        value = jnp.sum(jnp.where(r.valid[:, None], r.positions[:, :2], 0.0) ** 2) + jnp.sum(
            jnp.where(r.valid[:, None, None], r.stop_positions, 0.0)
        )
        return value, r

    # one jitted trace gives the rays and the gradient of the masked loss (op by op is 3x slower)
    (_, result), (grad_rays, grad_lens) = eqx.filter_jit(eqx.filter_value_and_grad(lambda args: loss(*args), has_aux=True))((origins, lens))
    for name in ("positions", "directions", "throughput", "stop_positions"):
        assert bool(jnp.all(jnp.isfinite(getattr(result, name)))), name
    assert bool(jnp.all(jnp.isfinite(grad_rays)))
    leaves = [x for x in jax.tree.leaves(grad_lens) if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating)]
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in leaves)
    return result


@pytest.mark.parametrize("path", [None, (2, 0)])
def test_asphere_rays_far_outside_stay_finite_in_float32(path):
    origins, directions = _rays(512, 40.0, 0.6)
    with jax.enable_x64(False):
        lens = cast_floating(lens_from_toml(ASPHERE), jnp.float32)
        result = _finite_everywhere(lens, jnp.asarray(origins, jnp.float32), jnp.asarray(directions, jnp.float32), path)
        assert 0 < int(result.valid.sum()) < 512  # some pass, most are outside the 9 mm apertures
        positions32, valid32 = np.asarray(result.positions, np.float64), np.asarray(result.valid)
    # the rays that pass are traced as in float64
    lens64 = lens_from_toml(ASPHERE)
    result64 = jaxflare.trace(lens64, jnp.asarray(origins), jnp.asarray(directions), 550.0, path)
    both = valid32 & np.asarray(result64.valid)
    assert both.sum() >= 0.95 * valid32.sum()
    np.testing.assert_allclose(positions32[both], np.asarray(result64.positions)[both], atol=2e-3)


def test_fisheye_grazing_rays_stay_finite():
    """The bundled fisheye, with rays up to 80 degrees off axis across the whole front element."""
    lens = jaxflare.load_lens("minolta_fisheye")
    semi = float(lens.semi_aperture_mm[0])
    origins, directions = _rays(256, 1.5 * semi, 5.7, seed=3)
    with jax.enable_x64(False):
        lens32 = cast_floating(lens, jnp.float32)
        _finite_everywhere(lens32, jnp.asarray(origins, jnp.float32), jnp.asarray(directions, jnp.float32), None)


def test_intersect_gives_a_missing_ray_its_own_origin():
    """A miss returns the ray's origin and a normal facing -z: finite whatever the polynomial does."""
    origin = Vector(*(jnp.array([v], jnp.float32) for v in (35.6, 0.93, -5.0)))
    direction = Vector(*(jnp.array([v], jnp.float32) for v in (-0.376, -0.162, 0.912)))
    coefficients = jnp.array([1.2e-4, -3.0e-6, 2.0e-8, -1.0e-10], jnp.float32)
    with jax.enable_x64(False):
        point, normal, hit = intersect(origin, direction, 0.0, jnp.float32(1 / 8), jnp.float32(-1.6), coefficients, jnp.int32(0), True)
    assert not bool(hit[0])
    np.testing.assert_array_equal(np.stack(point, axis=-1), np.stack(origin, axis=-1))
    np.testing.assert_array_equal(np.stack(normal, axis=-1), [[0.0, 0.0, -1.0]])


def test_asphere_hit_gradients_equal_finite_differences():
    """The Newton root's derivative (the implicit function theorem at the root, not the unrolled
    iterations) equals central finite differences of the traced sensor position in float64, with
    respect to the ray's height, the asphere's A4 and A6 coefficients and its conic constant."""
    lens = lens_from_toml(ASPHERE)
    origins, directions = _rays(64, 3.0, 0.02, seed=5)
    origins, directions = jnp.asarray(origins), jnp.asarray(directions)
    valid = np.asarray(jaxflare.trace(lens, origins, directions, 550.0).valid)
    assert valid.sum() >= 32
    weight = jnp.asarray(np.where(valid, 1.0, 0.0))

    def sensor(height, a4, a6, conic):
        moved = eqx.tree_at(
            lambda l: (l.aspheric_coefficients, l.conic), lens,
            (lens.aspheric_coefficients.at[0, 0].add(a4).at[0, 1].add(a6), lens.conic.at[0].add(conic)),
        )
        result = jaxflare.trace(moved, origins.at[:, 1].add(height), directions, 550.0)
        return jnp.sum(weight * (result.positions[:, 0] + 2.0 * result.positions[:, 1]))

    at = (0.0, 0.0, 0.0, 0.0)
    value_and_grad = jax.jit(jax.value_and_grad(sensor, argnums=(0, 1, 2, 3)))  # one program for both
    gradient = np.asarray(value_and_grad(*at)[1])
    value = lambda *args: float(value_and_grad(*args)[0])  # noqa: E731
    for k, step in enumerate((1e-4, 1e-9, 1e-11, 1e-5)):
        plus, minus = list(at), list(at)
        plus[k], minus[k] = step, -step
        finite = (value(*plus) - value(*minus)) / (2 * step)
        np.testing.assert_allclose(gradient[k], finite, rtol=1e-5, atol=1e-9 * abs(finite) + 1e-12)
        assert abs(finite) > 0, k
