"""Image-space lens distortion of flare samples (jaxflare.rendering.effects._distortion): Brown-Conrady and ST-maps."""

import jax
import jax.numpy as jnp
import numpy as np
import OpenEXR
import pytest

from jaxflare.rendering.effects import BrownConrady, distort, identity_st_map, load_st_map, st_map_distort
from jaxflare.io import write_exr

W, H = 64, 48
F = 55.0  # focal length in pixels


def opencv_distort(u, v, k1, k2, p1, p2, k3, fx, fy, cx, cy):
    """OpenCV's distortion (cv::projectPoints / initUndistortRectifyMap), transcribed in OpenCV's
    own convention: pixel coordinates (u, v) with pixel centres at integers, x right, y down."""
    x = (u - cx) / fx
    y = (v - cy) / fy
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return fx * xd + cx, fy * yd + cy


def _opencv_in_our_pixels(column, row, k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0):
    # our continuous coordinates have pixel centres at +0.5; OpenCV's at integers; centred principal point
    u, v = opencv_distort(column - 0.5, row - 0.5, k1, k2, p1, p2, k3, F, F, (W - 1) / 2, (H - 1) / 2)
    return u + 0.5, v + 0.5


def _random_points(seed, count=300):
    rng = np.random.default_rng(seed)
    return rng.uniform(0, W, count), rng.uniform(0, H, count)


# ------------------------------------------------------------------------------- Brown-Conrady


def test_zero_coefficients_are_the_identity():
    x, y = _random_points(0)
    xd, yd = distort(BrownConrady.create(focal_length_px=F), jnp.asarray(x), jnp.asarray(y), W, H)
    np.testing.assert_allclose(np.asarray(xd), x, atol=1e-12)
    np.testing.assert_allclose(np.asarray(yd), y, atol=1e-12)


def test_barrel_pulls_corners_in_and_keeps_the_centre():
    model = BrownConrady.create(k1=-0.2, focal_length_px=F)
    corners_x = jnp.asarray([0.0, W, 0.0, W])
    corners_y = jnp.asarray([0.0, 0.0, H, H])
    xd, yd = distort(model, corners_x, corners_y, W, H)
    before = np.hypot(np.asarray(corners_x) - W / 2, np.asarray(corners_y) - H / 2)
    after = np.hypot(np.asarray(xd) - W / 2, np.asarray(yd) - H / 2)
    assert np.all(after < before - 1.0)
    # radial: the direction from the centre is kept
    np.testing.assert_allclose((np.asarray(xd) - W / 2) / after, (np.asarray(corners_x) - W / 2) / before, atol=1e-12)
    cx, cy = distort(model, jnp.asarray(W / 2), jnp.asarray(H / 2), W, H)
    assert float(cx) == W / 2 and float(cy) == H / 2
    # pincushion pushes them out
    xd, yd = distort(BrownConrady.create(k1=0.2, focal_length_px=F), corners_x, corners_y, W, H)
    assert np.all(np.hypot(np.asarray(xd) - W / 2, np.asarray(yd) - H / 2) > before + 1.0)


def test_matches_opencv_formula_on_random_points():
    x, y = _random_points(1)
    coefficients = {"k1": -0.13, "k2": 0.045, "k3": -0.011, "p1": 0.0031, "p2": -0.0017}
    model = BrownConrady.create(**coefficients, focal_length_px=F)
    xd, yd = distort(model, jnp.asarray(x), jnp.asarray(y), W, H)
    ex, ey = _opencv_in_our_pixels(x, y, **coefficients)
    np.testing.assert_allclose(np.asarray(xd), ex, atol=1e-10)
    np.testing.assert_allclose(np.asarray(yd), ey, atol=1e-10)


@pytest.mark.parametrize("p1, p2", [(0.01, 0.0), (0.0, 0.01), (-0.02, 0.007)])
def test_tangential_terms_match_opencv(p1, p2):
    x, y = _random_points(2)
    xd, yd = distort(BrownConrady.create(p1=p1, p2=p2, focal_length_px=F), jnp.asarray(x), jnp.asarray(y), W, H)
    ex, ey = _opencv_in_our_pixels(x, y, p1=p1, p2=p2)
    np.testing.assert_allclose(np.asarray(xd), ex, atol=1e-10)
    np.testing.assert_allclose(np.asarray(yd), ey, atol=1e-10)


def test_tangential_sign_convention_is_y_down():
    # OpenCV, y down: with p1 > 0 alone a point below the centre (larger row) moves further down,
    # y_d = y + 3 p1 y^2 on the vertical axis; a point above the centre moves down as well
    model = BrownConrady.create(p1=0.05, focal_length_px=F)
    below = H / 2 + 0.4 * F
    above = H / 2 - 0.4 * F
    xd, yd = distort(model, jnp.asarray([W / 2, W / 2]), jnp.asarray([below, above]), W, H)
    np.testing.assert_allclose(np.asarray(xd), W / 2, atol=1e-12)
    np.testing.assert_allclose(np.asarray(yd), [below + F * 3 * 0.05 * 0.16, above + F * 3 * 0.05 * 0.16], atol=1e-10)
    # p2 > 0 alone moves points on the horizontal axis to the right: x_d = x + 3 p2 x^2
    xd, yd = distort(BrownConrady.create(p2=0.05, focal_length_px=F), jnp.asarray(W / 2 - 0.4 * F), jnp.asarray(H / 2), W, H)
    np.testing.assert_allclose(float(xd), W / 2 - 0.4 * F + F * 3 * 0.05 * 0.16, atol=1e-10)
    np.testing.assert_allclose(float(yd), H / 2, atol=1e-12)


def test_jit_vmap_and_gradients():
    model = BrownConrady.create(k1=-0.1, k2=0.02, p1=0.001, focal_length_px=F)
    x, y = (jnp.asarray(a) for a in _random_points(3, 20))
    eager = distort(model, x, y, W, H)
    jitted = jax.jit(distort, static_argnums=(3, 4))(model, x, y, W, H)
    traced_size = jax.jit(distort)(model, x, y, jnp.asarray(W), jnp.asarray(H))
    for got in (jitted, traced_size):
        np.testing.assert_allclose(np.asarray(got[0]), np.asarray(eager[0]), atol=1e-12)
        np.testing.assert_allclose(np.asarray(got[1]), np.asarray(eager[1]), atol=1e-12)
    # d x_d / d k1 = f x r^2 (normalised x, r)
    grad = jax.grad(lambda m: distort(m, x[0], y[0], W, H)[0])(model)
    xn, yn = (float(x[0]) - W / 2) / F, (float(y[0]) - H / 2) / F
    np.testing.assert_allclose(float(grad.k1), F * xn * (xn * xn + yn * yn), rtol=1e-10)
    # Jacobian with respect to the position is finite and near 1 at the centre
    jac = jax.jacfwd(lambda p: jnp.stack(distort(model, p[0], p[1], W, H)))(jnp.asarray([W / 2, H / 2]))
    np.testing.assert_allclose(np.asarray(jac), np.eye(2), atol=1e-12)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"k1": float("nan"), "focal_length_px": F}, "k1 must be finite"),
        ({"p2": float("inf"), "focal_length_px": F}, "p2 must be finite"),
        ({"focal_length_px": 0.0}, "focal_length_px must be positive"),
        ({"focal_length_px": -5.0}, "focal_length_px must be positive"),
        ({"focal_length_px": float("inf")}, "focal_length_px must be finite"),
        ({"k2": "x", "focal_length_px": F}, "k2 must be a number"),
    ],
)
def test_create_validates(kwargs, match):
    with pytest.raises(ValueError, match=match):
        BrownConrady.create(**kwargs)


def test_focal_length_is_keyword_only_and_required():
    with pytest.raises(TypeError):
        BrownConrady.create(0.1)


# ------------------------------------------------------------------------------------- ST maps


def _everywhere(seed, count=400):
    """Random positions over the whole frame, its outer half pixels and exact edges included."""
    x, y = _random_points(seed, count)
    return np.concatenate([x, [0.0, W, 0.1, W - 0.1, 0.0]]), np.concatenate([y, [0.0, H, 0.2, H - 0.2, H]])


def test_identity_st_map_values():
    st = identity_st_map(4, 2)
    assert st.shape == (2, 4, 2) and st.dtype == np.float32
    np.testing.assert_allclose(st[0, :, 0], [0.125, 0.375, 0.625, 0.875])
    np.testing.assert_allclose(st[:, 0, 1], [0.75, 0.25])  # t from the bottom: row 0 (top) has t near 1


def test_identity_st_map_leaves_positions_unchanged():
    x, y = _everywhere(4)
    xd, yd = st_map_distort(jnp.asarray(identity_st_map(W, H)), jnp.asarray(x), jnp.asarray(y), W, H)
    np.testing.assert_allclose(np.asarray(xd), x, atol=1e-5)
    np.testing.assert_allclose(np.asarray(yd), y, atol=1e-5)
    # a coarser map covering the same frame is the identity too
    xd, yd = st_map_distort(jnp.asarray(identity_st_map(8, 5)), jnp.asarray(x), jnp.asarray(y), W, H)
    np.testing.assert_allclose(np.asarray(xd), x, atol=1e-5)
    np.testing.assert_allclose(np.asarray(yd), y, atol=1e-5)


def test_shift_in_s_moves_samples_right():
    st = identity_st_map(W, H)
    st[..., 0] += 3.0 / W
    x, y = _everywhere(5)
    xd, yd = st_map_distort(jnp.asarray(st), jnp.asarray(x), jnp.asarray(y), W, H)
    np.testing.assert_allclose(np.asarray(xd), x + 3.0, atol=1e-5)
    np.testing.assert_allclose(np.asarray(yd), y, atol=1e-5)


def test_t_counts_from_the_bottom():
    st = identity_st_map(W, H)
    st[..., 1] += 0.1
    x, y = _everywhere(6)
    xd, yd = st_map_distort(jnp.asarray(st), jnp.asarray(x), jnp.asarray(y), W, H)
    np.testing.assert_allclose(np.asarray(xd), x, atol=1e-5)
    np.testing.assert_allclose(np.asarray(yd), y - 0.1 * H, atol=1e-5)  # up the image: smaller row


def test_st_map_reproduces_brown_conrady_inside_the_frame():
    model = BrownConrady.create(k1=-0.08, p1=0.002, focal_length_px=F)
    rows, columns = np.mgrid[0:H, 0:W] + 0.5
    xd, yd = distort(model, jnp.asarray(columns), jnp.asarray(rows), W, H)
    st = np.stack([np.asarray(xd) / W, 1 - np.asarray(yd) / H], axis=-1)
    x, y = np.array([10.5, 33.5, 40.5]), np.array([7.5, 20.5, 40.5])  # pixel centres: exact samples
    got = st_map_distort(jnp.asarray(st), jnp.asarray(x), jnp.asarray(y), W, H)
    want = distort(model, jnp.asarray(x), jnp.asarray(y), W, H)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-9)


def test_positions_outside_the_frame_clamp_and_jit_works():
    st = jnp.asarray(identity_st_map(W, H))
    x = jnp.asarray([-10.0, W + 10.0, W / 2])
    y = jnp.asarray([H / 2, H / 2, H + 50.0])
    xd, yd = jax.jit(st_map_distort, static_argnums=(3, 4))(st, x, y, W, H)
    np.testing.assert_allclose(np.asarray(xd), [0.0, W, W / 2], atol=1e-5)
    np.testing.assert_allclose(np.asarray(yd), [H / 2, H / 2, H], atol=1e-5)


def _write_raw_exr(path, channels):
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {name: np.ascontiguousarray(c, np.float32) for name, c in channels.items()}).write(str(path))


def test_load_st_map_round_trips(tmp_path):
    st = identity_st_map(W, H)
    st[..., 0] += 0.01
    write_exr(tmp_path / "rgb.exr", {"": np.dstack([st, np.zeros((H, W), np.float32)])}, pixel_type="float")
    loaded = load_st_map(tmp_path / "rgb.exr")
    assert loaded.shape == (H, W, 2) and loaded.dtype == np.float32
    np.testing.assert_array_equal(loaded, st)
    # R and G alone (no B), as many tools write ST-maps
    _write_raw_exr(tmp_path / "rg.exr", {"R": st[..., 0], "G": st[..., 1]})
    np.testing.assert_array_equal(load_st_map(tmp_path / "rg.exr"), st)


def test_load_st_map_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="absent.exr"):
        load_st_map(tmp_path / "absent.exr")
    (tmp_path / "garbage.exr").write_bytes(b"not an exr file" * 20)
    with pytest.raises(ValueError, match="garbage.exr"):
        load_st_map(tmp_path / "garbage.exr")
    write_exr(tmp_path / "grey.exr", {"": np.zeros((H, W, 1), np.float32)}, pixel_type="float")
    with pytest.raises(ValueError, match="grey.exr.*R or G"):
        load_st_map(tmp_path / "grey.exr")
    _write_raw_exr(tmp_path / "red.exr", {"R": np.zeros((H, W))})
    with pytest.raises(ValueError, match="red.exr.*no channel G"):
        load_st_map(tmp_path / "red.exr")
    bad = identity_st_map(W, H)
    bad[3, 4, 1] = np.nan
    _write_raw_exr(tmp_path / "nan.exr", {"R": bad[..., 0], "G": bad[..., 1]})
    with pytest.raises(ValueError, match="nan.exr.*non-finite"):
        load_st_map(tmp_path / "nan.exr")


def test_bad_st_map_shape_rejected():
    with pytest.raises(ValueError, match=r"\(H, W, 2\)"):
        st_map_distort(jnp.zeros((4, 4, 3)), jnp.zeros(1), jnp.zeros(1), W, H)
    with pytest.raises(ValueError, match="2 x 2"):
        identity_st_map(1, 4)
