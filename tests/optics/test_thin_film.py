"""Physics checks for jaxflare.optics._thin_film (thin-film-coated Fresnel reflectance).

Compiling on the CPU dominates the run time, so most checks go through :func:`_rsp`, which feeds
every evaluation to one fixed-shape call (rows padded to a fixed batch, stacks padded with
zero-thickness layers, which are exact no-ops; that is itself checked on native shapes below).
Every check states its precision with ``jax.enable_x64`` (conftest.py turns float64 on globally).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflare.optics import (
    coated_reflectance,
    coated_reflectance_sp,
    schlick_reflectance,
    uncoated_reflectance,
)

_ROWS, _LAYERS = 64, 4


def _float():
    return jax.dtypes.canonicalize_dtype(np.float64)  # float64 under x64, else float32


def _rsp(n0, ns, cos, lam=550.0, nl=(), tl=()):
    """(R_s, R_p) as numpy arrays, broadcast like the library, via fixed-shape padded calls."""
    nl, tl = np.asarray(nl, float), np.asarray(tl, float)
    nl, tl = nl.reshape(nl.shape or (0,)), tl.reshape(tl.shape or (0,))
    shape = np.broadcast_shapes(*(np.shape(a) for a in (n0, ns, cos, lam)), nl.shape[:-1], tl.shape[:-1])
    size, n_layers = int(np.prod(shape)), nl.shape[-1]
    cols = [np.broadcast_to(np.asarray(a, float), shape).ravel() for a in (n0, ns, cos, lam)]
    lay = [np.broadcast_to(a, shape + (n_layers,)).reshape(size, n_layers) for a in (nl, tl)]
    lay = [np.pad(a, ((0, 0), (0, _LAYERS - n_layers)), constant_values=v) for a, v in zip(lay, (1.5, 0.0))]
    rows = -(-size // _ROWS) * _ROWS
    args = [np.pad(a, [(0, rows - size)] + [(0, 0)] * (a.ndim - 1), mode="edge") for a in cols + lay]
    out = [[], []]
    for k in range(0, rows, _ROWS):
        r_s, r_p = coated_reflectance_sp(*(jnp.asarray(a[k : k + _ROWS], _float()) for a in args))
        out[0].append(np.asarray(r_s))
        out[1].append(np.asarray(r_p))
    return tuple(np.concatenate(o)[:size].reshape(shape) for o in out)


def _r(*args, **kwargs):
    r_s, r_p = _rsp(*args, **kwargs)
    return 0.5 * (r_s + r_p)


# ---------------------------------------------------------------------------------------------
# Independent reference: recursive Airy summation of interface amplitude coefficients (numpy).


def _airy_rs_rp(n0, ns, cos0, lam, indices, thicknesses):
    """(R_s, R_p) by summing the multiple reflections in each layer, innermost layer first."""
    sin0 = np.sqrt(1.0 - cos0**2)
    media = [n0, *indices, ns]
    cos = [np.sqrt(1.0 - (n0 * sin0 / n) ** 2 + 0j) for n in media]  # principal root: Im >= 0

    def r_s(i, j):
        a, b = media[i] * cos[i], media[j] * cos[j]
        return (a - b) / (a + b)

    def r_p(i, j):
        a, b = media[j] * cos[i], media[i] * cos[j]
        return (a - b) / (a + b)

    out = []
    for r_ij in (r_s, r_p):
        r = r_ij(len(media) - 2, len(media) - 1)
        for j in range(len(indices), 0, -1):
            phase = np.exp(2j * (2 * np.pi / lam) * media[j] * cos[j] * thicknesses[j - 1])
            r = (r_ij(j - 1, j) + r * phase) / (1 + r_ij(j - 1, j) * r * phase)
        out.append(abs(r) ** 2)
    return tuple(out)


def _snell_cos(n_from, n_to, cos_from):
    return np.sqrt(1.0 - (n_from / n_to) ** 2 * (1.0 - np.asarray(cos_from) ** 2))


NO_LAYERS = np.zeros((0,))


def test_uncoated_normal_incidence():
    n1 = np.array([1.0, 1.5, 1.0, 1.6, 1.0])
    n2 = np.array([1.5, 1.0, 1.9, 1.6, 1.0])
    expected = ((n1 - n2) / (n1 + n2)) ** 2
    for x64, tol in [(False, 1e-6), (True, 1e-14)]:
        with jax.enable_x64(x64):
            r_s, r_p = _rsp(n1, n2, 1.0)
            np.testing.assert_allclose(r_s, expected, rtol=tol, atol=tol * 1e-2)
            np.testing.assert_allclose(r_p, expected, rtol=tol, atol=tol * 1e-2)
    # s and p agree at normal incidence with a coating too.
    with jax.enable_x64(True):
        r_s, r_p = _rsp(1.0, 1.7, 1.0, 550.0, [1.38, 2.1], [99.6, 65.5])
        np.testing.assert_allclose(r_s, r_p, rtol=1e-13)


def test_native_shapes_empty_stack_and_zero_thickness_noops():
    """Direct calls: L = 0, broadcasting, and padding layers (as _rsp adds them) as no-ops."""
    with jax.enable_x64(False):  # float32 tolerances below
        cos = np.linspace(0.0, 1.0, _ROWS)
        bare = coated_reflectance_sp(1.0, 1.62, jnp.asarray(cos), 500.0, NO_LAYERS, NO_LAYERS)
        assert bare[0].shape == bare[1].shape == (_ROWS,)
        r = uncoated_reflectance(jnp.ones((1, 1)), jnp.array([[1.62], [1.0], [1.9]]), jnp.asarray(cos))
        assert r.shape == (3, _ROWS)
        np.testing.assert_allclose(r[0], 0.5 * (bare[0] + bare[1]), rtol=1e-6)
        np.testing.assert_allclose(r[:, -1], [((1 - 1.62) / 2.62) ** 2, 0.0, (0.9 / 2.9) ** 2], rtol=1e-6)
        # _rsp pads to _LAYERS zero-thickness layers: the same as no stack at all (identity matrices;
        # a differently compiled graph may still round differently in the last place).
        np.testing.assert_allclose(bare, _rsp(1.0, 1.62, cos, 500.0), rtol=1e-6, atol=1e-8)
        zero = _rsp(1.0, 1.62, cos, 500.0, [2.0, 1.38, 1.9], [0.0, 0.0, 0.0])
        np.testing.assert_array_equal(zero, _rsp(1.0, 1.62, cos, 500.0))
        # Padding around a real layer (only shape-dependent rounding of sin/cos may differ); the
        # one-layer stack given per row, broadcast against the angles.
        one = coated_reflectance_sp(1.0, 1.62, jnp.asarray(cos), 500.0, jnp.full((_ROWS, 1), 1.38), jnp.full((_ROWS, 1), 99.0))
        pad = _rsp(1.0, 1.62, cos, 500.0, [2.0, 1.38, 1.9], [0.0, 99.0, 0.0])
        np.testing.assert_allclose(one, pad, rtol=1e-6, atol=1e-7)
        assert not np.allclose(one, bare)


def test_fresnel_textbook_and_brewster():
    with jax.enable_x64(True):
        for n1, n2, angles in [(1.0, 1.5, [5, 20, 45, 60, 80, 89]), (1.5, 1.0, [5, 20, 35, 41])]:
            ti = np.deg2rad(np.array(angles, float))
            tt = np.arcsin(n1 / n2 * np.sin(ti))
            rs_sin = (np.sin(ti - tt) / np.sin(ti + tt)) ** 2
            rp_tan = (np.tan(ti - tt) / np.tan(ti + tt)) ** 2
            ci, ct = np.cos(ti), np.cos(tt)
            rs_cos = ((n1 * ci - n2 * ct) / (n1 * ci + n2 * ct)) ** 2
            r_s, r_p = _rsp(n1, n2, ci)
            np.testing.assert_allclose(r_s, rs_sin, rtol=1e-10)
            np.testing.assert_allclose(r_s, rs_cos, rtol=1e-10)
            np.testing.assert_allclose(r_p, rp_tan, rtol=1e-9, atol=1e-15)
            # Brewster angle: tan(theta_B) = n2 / n1.
            r_s, r_p = _rsp(n1, n2, n1 / np.hypot(n1, n2))
            assert r_p < 1e-20 and r_s > 1e-3
    with jax.enable_x64(False):
        r_s, r_p = _rsp(1.0, 1.5, 1.0 / np.hypot(1.0, 1.5))
        assert r_p < 1e-7


def test_quarter_and_half_wave_layers():
    lam0, n0, n2 = 550.0, 1.0, 1.52
    n_ideal, n_mgf2 = np.sqrt(n0 * n2), 1.38
    mgf2_closed = ((n0 * n2 - n_mgf2**2) / (n0 * n2 + n_mgf2**2)) ** 2
    np.testing.assert_allclose(mgf2_closed, 0.0126, atol=1e-4)
    for x64, tol in [(False, 1e-5), (True, 1e-12)]:
        with jax.enable_x64(x64):
            # Ideal quarter wave: zero at the design wavelength only.
            r = _r(n0, n2, 1.0, [lam0, 450.0], [n_ideal], [lam0 / (4 * n_ideal)])
            assert r[0] < (1e-20 if x64 else 1e-9) and r[1] > 1e-4
            r = _r(n0, n2, 1.0, lam0, [n_mgf2], [lam0 / (4 * n_mgf2)])
            np.testing.assert_allclose(r, mgf2_closed, rtol=tol)
            # Half wave: an absentee layer at its design wavelength.
            nh = np.array([[1.38], [2.1]])
            r = _r(n0, n2, 1.0, lam0, nh, lam0 / (2 * nh))
            np.testing.assert_allclose(r, ((n0 - n2) / (n0 + n2)) ** 2, rtol=tol)


STACKS = [
    # n0, ns, cos0, lam, indices, thicknesses
    (1.0, 1.52, 0.7, 550.0, [1.38, 2.1], [99.6, 65.5]),
    (1.0, 1.75, 0.25, 480.0, [2.3, 1.46], [140.0, 230.0]),
    (1.6, 1.0, 0.95, 620.0, [1.38, 1.9], [120.0, 80.0]),
    (1.7, 1.5, 0.5, 550.0, [1.38, 2.0], [100.0, 70.0]),  # evanescent first layer: tunnelling
    (1.7, 1.3, 0.5, 550.0, [1.38, 2.0], [100.0, 70.0]),  # ... and TIR in the substrate
    (1.5, 1.5, 0.3, 450.0, [1.38, 1.45], [300.0, 40.0]),  # both layers evanescent
]


def test_two_layer_stacks_against_airy_summation():
    want = np.array([_airy_rs_rp(*stack) for stack in STACKS]).T
    cols = [np.array([stack[i] for stack in STACKS]) for i in range(6)]
    with jax.enable_x64(True):
        np.testing.assert_allclose(_rsp(*cols), want, rtol=1e-11, atol=1e-14)
    with jax.enable_x64(False):
        np.testing.assert_allclose(_rsp(*cols), want, rtol=2e-4, atol=2e-6)
    # Random three-layer stacks, oblique incidence.
    rng = np.random.default_rng(1)
    n0, ns = rng.uniform(1.0, 2.0, (2, 40))
    nl, tl = rng.uniform(1.3, 2.4, (40, 3)), rng.uniform(0.0, 250.0, (40, 3))
    cos, lam = rng.uniform(0.05, 1.0, 40), rng.uniform(400, 700, 40)
    want = np.array([_airy_rs_rp(*row) for row in zip(n0, ns, cos, lam, nl, tl)]).T
    with jax.enable_x64(True):
        np.testing.assert_allclose(_rsp(n0, ns, cos, lam, nl, tl), want, rtol=1e-10, atol=1e-13)


def test_reciprocity_reversed_stack():
    n_a, n_b = 1.0, 1.62
    nl, tl = np.array([1.38, 2.1, 1.46]), np.array([95.0, 60.0, 120.0])
    cos_a = np.array([1.0, 0.8, 0.45, 0.1, 0.0])
    with jax.enable_x64(True):
        from_a = _rsp(n_a, n_b, cos_a, 530.0, nl, tl)
        from_b = _rsp(n_b, n_a, _snell_cos(n_a, n_b, cos_a), 530.0, nl[::-1], tl[::-1])
        np.testing.assert_allclose(from_a, from_b, rtol=1e-11, atol=1e-15)


def test_total_internal_reflection():
    cos_crit = float(_snell_cos(1.0, 1.5, 0.0))  # glass -> air critical angle, cosine in glass
    cos = np.array([0.0, 0.2, 0.5, 0.7, 0.99 * cos_crit])
    stacks = [([1.38], [99.0]), ([2.1, 1.38], [65.0, 99.0]), ([1.0, 1.6], [40.0, 300.0])]
    for x64, tol in [(False, 1e-6), (True, 1e-14)]:
        with jax.enable_x64(x64):
            for r in _rsp(1.5, 1.0, cos):
                np.testing.assert_allclose(r, 1.0, atol=tol)
            for nl, tl in stacks:
                for r in _rsp(1.5, 1.0, cos, 550.0, nl, tl):
                    np.testing.assert_allclose(r, 1.0, atol=tol)
    assert _r(1.5, 1.0, 1.01 * cos_crit) < 0.99


def test_bounds_on_random_grid():
    rng = np.random.default_rng(0)
    shape = (16, 32)
    n0, ns = rng.uniform(1.0, 2.2, (2, *shape))
    cos = rng.uniform(0.0, 1.0, shape)
    cos[:, 0], cos[:, 1] = 0.0, 1.0
    lam = rng.uniform(380.0, 780.0, shape)
    nl = rng.uniform(1.2, 2.5, (*shape, 4))
    tl = rng.uniform(0.0, 400.0, (*shape, 4)) * (rng.uniform(size=(*shape, 4)) > 0.2)
    for x64, tol in [(False, 2e-6), (True, 1e-13)]:
        with jax.enable_x64(x64):
            for r in _rsp(n0, ns, cos, lam, nl, tl):
                assert r.shape == shape and np.all(np.isfinite(r))
                assert np.all(r >= -tol) and np.all(r <= 1 + tol)


@jax.jit
def _grads(n0, ns, cos, lam, nl, tl):
    """Gradients wrt (n0, ns, cos, nl, tl), under jit and vmap."""
    return jax.vmap(jax.grad(coated_reflectance, argnums=(0, 1, 2, 4, 5)))(n0, ns, cos, lam, nl, tl)


def _grads_padded(n0, ns, cos, lam, nl, tl):
    """:func:`_grads` on 1-D rows padded to the fixed shape (_ROWS, _LAYERS); numpy out."""
    size, n_layers = len(cos), nl.shape[-1]
    rows = [np.pad(np.asarray(a, float), (0, _ROWS - size), mode="edge") for a in (n0, ns, cos, lam)]
    nl, tl = (np.pad(a, ((0, _ROWS - size), (0, _LAYERS - n_layers)), constant_values=v) for a, v in ((nl, 1.5), (tl, 0.0)))
    grads = _grads(*(jnp.asarray(a, _float()) for a in (*rows, nl, tl)))
    return [np.asarray(g)[:size, ..., :n_layers] if g.ndim == 2 else np.asarray(g)[:size] for g in grads]


@pytest.mark.parametrize("x64", [False, True])
def test_gradients_finite_everywhere(x64):
    with jax.enable_x64(x64):
        dtype = _float()
        cos_crit = np.asarray(_snell_cos(1.0, 1.5, 0.0), dtype)  # glass -> air
        # (n_incident, n_substrate, cos): normal, grazing, TIR, index-matched, and at and one ulp
        # either side of the critical angle.
        points = [(1.0, 1.5, 1.0), (1.0, 1.5, 0.0), (1.5, 1.0, 0.0), (1.5, 1.0, 1.0), (1.5, 1.0, 0.4),
                  (1.5, 1.5, 0.0), (1.5, 1.5, 1.0), (1.5, 1.0, cos_crit),
                  (1.5, 1.0, np.nextafter(cos_crit, dtype.type(2))),
                  (1.5, 1.0, np.nextafter(cos_crit, dtype.type(0)))]  # fmt: skip
        stacks = [
            ([1.38, 2.1, 1.6, 1.5], [99.0, 0.0, 40.0, 0.0]),  # includes padding
            ([1.0, 1.5, 1.38, 1.5], [50.0, 80.0, 120.0, 900.0]),  # layers at their critical angle
            ([1.5, 1.38, 1.0, 2.0], [0.0, 0.0, 0.0, 0.0]),  # all padding
        ]
        rows = [(*p, 550.0, *s) for p in points for s in stacks]
        n0, ns, cos, lam, nl, tl = (np.array(col, dtype) for col in zip(*rows))
        r = _r(n0, ns, cos, lam, nl, tl)
        assert np.all(np.isfinite(r)) and np.all((r >= -1e-6) & (r <= 1 + 1e-6))
        for g in _grads_padded(n0, ns, cos, lam, nl, tl):  # the all-padding stack is L = 0
            assert np.all(np.isfinite(g))
        assert np.all(np.isfinite(jax.vmap(jax.grad(schlick_reflectance, 1), (None, 0))(0.04, cos)))
        if not x64:  # plain jax.grad (no jit, no vmap) of the bare interface
            grad = jax.grad(uncoated_reflectance, argnums=(0, 1, 2))
            for p in points:
                assert np.all(np.isfinite(grad(*(dtype.type(v) for v in p))))


def test_gradients_match_finite_differences():
    """Gradients in thickness, layer index and angle vs central differences (float64)."""
    with jax.enable_x64(True):
        cos = np.array([0.6, 0.2, 1.0])
        nl, tl = np.tile([1.38, 2.05], (3, 1)), np.tile([98.0, 61.0], (3, 1))
        _, _, g_c, g_n, g_t = _grads_padded(1.0 + 0 * cos, 1.62 + 0 * cos, cos, 510.0 + 0 * cos, nl, tl)
        h = 1e-4
        for i in range(2):
            e = np.zeros(2)
            e[i] = h
            fd_t = (_r(1.0, 1.62, cos, 510.0, nl, tl + e) - _r(1.0, 1.62, cos, 510.0, nl, tl - e)) / (2 * h)
            fd_n = (_r(1.0, 1.62, cos, 510.0, nl + e, tl) - _r(1.0, 1.62, cos, 510.0, nl - e, tl)) / (2 * h)
            np.testing.assert_allclose(g_t[:, i], fd_t, rtol=1e-6, atol=1e-11)
            np.testing.assert_allclose(g_n[:, i], fd_n, rtol=1e-6, atol=1e-11)
        fd_c = (_r(1.0, 1.62, cos + h, 510.0, nl, tl) - _r(1.0, 1.62, cos - h, 510.0, nl, tl)) / (2 * h)
        np.testing.assert_allclose(g_c[:2], fd_c[:2], rtol=1e-6, atol=1e-11)
        # One-sided at normal incidence.
        fd_c = (_r(1.0, 1.62, 1.0, 510.0, nl[0], tl[0]) - _r(1.0, 1.62, 1.0 - h, 510.0, nl[0], tl[0])) / h
        np.testing.assert_allclose(g_c[2], fd_c, rtol=1e-3)


def test_schlick():
    r = np.asarray(schlick_reflectance(0.04, np.linspace(0.0, 1.0, 11)))
    np.testing.assert_allclose(r[[0, -1]], [1.0, 0.04], rtol=1e-6)
    assert np.all(np.diff(r) < 0)
