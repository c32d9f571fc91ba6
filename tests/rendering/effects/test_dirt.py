"""Front-lens dirt maps (jaxflare.rendering.effects._dirt): orientation, interpolation, gradients and file loading."""

import jax
import jax.numpy as jnp
import numpy as np
import OpenEXR
import pytest
from PIL import Image

from jaxflare.rendering.effects import dirt_transmission, load_dirt_map
from jaxflare.io import write_exr

R0 = 12.5  # front clear semi-aperture, mm


def _lens_xy(column, row, width, height, radius=R0):
    """Lens-frame (x, y) mm of continuous map coordinates (column right, row down, centres at +0.5)."""
    column = np.asarray(column, float)
    row = np.asarray(row, float)
    return np.stack([-radius + 2 * radius * column / width, radius - 2 * radius * row / height], axis=-1)


# ------------------------------------------------------------------------------ interpolation


def test_bilinear_is_exact_on_a_linear_ramp():
    height, width = 7, 11
    rows, columns = np.mgrid[0:height, 0:width]
    # value at pixel centre (i, j): linear in the centre's coordinates; 3 channels with different slopes
    ramp = np.stack([0.03 * columns + 0.05 * rows + 0.1, 0.08 * columns + 0.02, 0.9 - 0.1 * rows], axis=-1)
    rng = np.random.default_rng(0)
    column = rng.uniform(0.5, width - 0.5, 200)  # between the outermost centres: no clamping
    row = rng.uniform(0.5, height - 0.5, 200)
    got = np.asarray(dirt_transmission(jnp.asarray(ramp), jnp.asarray(_lens_xy(column, row, width, height)), R0))
    u, v = column - 0.5, row - 0.5
    expected = np.stack([0.03 * u + 0.05 * v + 0.1, 0.08 * u + 0.02, 0.9 - 0.1 * v], axis=-1)
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_pixel_centres_return_pixel_values_and_single_channel_broadcasts():
    height, width = 5, 6
    dirt = np.random.default_rng(1).uniform(size=(height, width, 1))
    rows, columns = np.mgrid[0:height, 0:width]
    xy = _lens_xy(columns.ravel() + 0.5, rows.ravel() + 0.5, width, height)
    got = np.asarray(dirt_transmission(jnp.asarray(dirt), jnp.asarray(xy), R0))
    assert got.shape == (height * width, 3)
    np.testing.assert_allclose(got, np.repeat(dirt.reshape(-1, 1), 3, axis=1), atol=1e-12)


def test_orientation_left_half_blocks_negative_x_and_top_rows_are_positive_y():
    left_dark = np.zeros((4, 4, 1))
    left_dark[:, 2:] = 1.0  # columns 0, 1 block (image left), columns 2, 3 transmit
    xy = jnp.asarray([[-0.75 * R0, 0.0], [-0.3 * R0, 0.4 * R0], [0.75 * R0, 0.0], [0.3 * R0, -0.6 * R0]])
    got = np.asarray(dirt_transmission(jnp.asarray(left_dark), xy, R0))
    np.testing.assert_allclose(got[:, 0], [0.0, 0.0, 1.0, 1.0], atol=1e-12)

    top_dark = np.ones((4, 4, 1))
    top_dark[:2] = 0.0  # rows 0, 1 (image top) block
    xy = jnp.asarray([[0.0, 0.75 * R0], [0.5 * R0, 0.3 * R0], [0.0, -0.75 * R0], [-0.5 * R0, -0.3 * R0]])
    got = np.asarray(dirt_transmission(jnp.asarray(top_dark), xy, R0))
    np.testing.assert_allclose(got[:, 0], [0.0, 0.0, 1.0, 1.0], atol=1e-12)

    # the boundary between the halves is at x = 0, halfway between the centres of columns 1 and 2
    np.testing.assert_allclose(np.asarray(dirt_transmission(jnp.asarray(left_dark), jnp.zeros((1, 2)), R0)), 0.5, atol=1e-12)


def test_outside_points_clamp_to_the_border():
    dirt = np.random.default_rng(2).uniform(size=(3, 5, 3))
    xy = jnp.asarray([[-3 * R0, 5 * R0], [10 * R0, -10 * R0], [-0.99 * R0, 0.99 * R0]])
    got = np.asarray(dirt_transmission(jnp.asarray(dirt), xy, R0))
    np.testing.assert_allclose(got[0], dirt[0, 0], atol=1e-12)  # far left, far up: top-left pixel
    np.testing.assert_allclose(got[1], dirt[-1, -1], atol=1e-12)  # far right, far down: bottom-right
    np.testing.assert_allclose(got[2], dirt[0, 0], atol=1e-12)  # within the outer half pixel: held


def test_gradient_with_respect_to_the_map_is_the_bilinear_weights():
    height, width = 5, 6
    dirt = jnp.asarray(np.random.default_rng(3).uniform(size=(height, width, 1)))
    # continuous index (u, v) = (1.3, 2.6): between columns 1, 2 and rows 2, 3
    xy = jnp.asarray(_lens_xy([1.3 + 0.5], [2.6 + 0.5], width, height))
    grad = np.asarray(jax.grad(lambda d: dirt_transmission(d, xy, R0)[0, 0])(dirt))[..., 0]
    expected = np.zeros((height, width))
    expected[2, 1] = 0.7 * 0.4
    expected[2, 2] = 0.3 * 0.4
    expected[3, 1] = 0.7 * 0.6
    expected[3, 2] = 0.3 * 0.6
    np.testing.assert_allclose(grad, expected, atol=1e-12)


def test_jit_and_vmap():
    rng = np.random.default_rng(4)
    maps = jnp.asarray(rng.uniform(size=(3, 6, 8, 3)))
    xy = jnp.asarray(rng.uniform(-R0, R0, size=(10, 2)))
    eager = np.stack([np.asarray(dirt_transmission(m, xy, R0)) for m in maps])
    jitted = jax.jit(jax.vmap(dirt_transmission, in_axes=(0, None, None)))(maps, xy, jnp.asarray(R0))
    np.testing.assert_allclose(np.asarray(jitted), eager, atol=1e-12)


def test_bad_map_shapes_rejected():
    with pytest.raises(ValueError, match="2 x 2"):
        dirt_transmission(jnp.ones((1, 5, 1)), jnp.zeros((1, 2)), R0)
    with pytest.raises(ValueError, match=r"\(H, W, 1\) or \(H, W, 3\)"):
        dirt_transmission(jnp.ones((4, 4, 2)), jnp.zeros((1, 2)), R0)


# ------------------------------------------------------------------------------------- files


def test_png_8_bit_grey_rgb_rgba_and_palette(tmp_path):
    grey = np.arange(12, dtype=np.uint8).reshape(3, 4) * 20
    Image.fromarray(grey).save(tmp_path / "grey.png")
    loaded = load_dirt_map(tmp_path / "grey.png")
    assert loaded.dtype == np.float32 and loaded.shape == (3, 4, 1)
    np.testing.assert_allclose(loaded[..., 0], grey / 255.0, rtol=1e-6)

    rgb = np.random.default_rng(5).integers(0, 256, size=(3, 4, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(tmp_path / "rgb.png")
    np.testing.assert_allclose(load_dirt_map(tmp_path / "rgb.png"), rgb / 255.0, rtol=1e-6)

    rgba = np.concatenate([rgb, np.full((3, 4, 1), 7, np.uint8)], axis=-1)
    Image.fromarray(rgba).save(tmp_path / "rgba.png")
    loaded = load_dirt_map(tmp_path / "rgba.png")
    assert loaded.shape == (3, 4, 3)  # alpha dropped
    np.testing.assert_allclose(loaded, rgb / 255.0, rtol=1e-6)

    Image.fromarray(rgb).quantize(colors=256, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE).save(
        tmp_path / "palette.png"
    )
    with Image.open(tmp_path / "palette.png") as image:
        assert image.mode == "P"
        expected = np.asarray(image.convert("RGB")) / 255.0
    np.testing.assert_allclose(load_dirt_map(tmp_path / "palette.png"), expected, rtol=1e-6)

    Image.fromarray(np.dstack([grey, np.full_like(grey, 9)])).save(tmp_path / "la.png")
    np.testing.assert_allclose(load_dirt_map(tmp_path / "la.png")[..., 0], grey / 255.0, rtol=1e-6)


def test_png_and_tiff_16_bit(tmp_path):
    values = np.array([[0, 1000, 30000], [40000, 65535, 12345]], dtype=np.uint16)
    for name in ("grey16.png", "grey16.tif"):
        Image.fromarray(values).save(tmp_path / name)
        loaded = load_dirt_map(tmp_path / name)
        assert loaded.shape == (2, 3, 1)
        np.testing.assert_allclose(loaded[..., 0], values / 65535.0, rtol=1e-6)
    # big-endian 16-bit (mode I;16B)
    Image.frombytes("I;16B", (3, 2), values.astype(">u2").tobytes()).save(tmp_path / "big.tif")
    np.testing.assert_allclose(load_dirt_map(tmp_path / "big.tif")[..., 0], values / 65535.0, rtol=1e-6)
    # 32-bit integer image (mode I) holding 16-bit values
    Image.fromarray(values.astype(np.int32)).save(tmp_path / "int.tif")
    np.testing.assert_allclose(load_dirt_map(tmp_path / "int.tif")[..., 0], values / 65535.0, rtol=1e-6)


def test_jpeg_loads_approximately(tmp_path):
    grey = np.full((8, 8), 128, np.uint8)
    Image.fromarray(grey).save(tmp_path / "dirt.jpg", quality=95)
    np.testing.assert_allclose(load_dirt_map(tmp_path / "dirt.jpg"), 128 / 255.0, atol=2 / 255)


def test_float_tiff_and_exr(tmp_path):
    values = np.random.default_rng(6).uniform(size=(4, 5)).astype(np.float32)
    Image.fromarray(values).save(tmp_path / "float.tif")
    np.testing.assert_array_equal(load_dirt_map(tmp_path / "float.tif")[..., 0], values)

    rgb = np.random.default_rng(7).uniform(size=(4, 5, 3)).astype(np.float32)
    write_exr(tmp_path / "rgb.exr", {"": rgb}, pixel_type="float")
    np.testing.assert_array_equal(load_dirt_map(tmp_path / "rgb.exr"), rgb)

    write_exr(tmp_path / "y.exr", {"": values[..., None]}, pixel_type="half")
    loaded = load_dirt_map(tmp_path / "y.exr")
    assert loaded.shape == (4, 5, 1)
    np.testing.assert_array_equal(loaded[..., 0], values.astype(np.float16).astype(np.float32))

    write_exr(tmp_path / "rgba.exr", {"": np.concatenate([rgb, np.ones((4, 5, 1), np.float32)], -1)}, pixel_type="float")
    np.testing.assert_array_equal(load_dirt_map(tmp_path / "rgba.exr"), rgb)


def test_missing_file(tmp_path):
    path = tmp_path / "nowhere.png"
    with pytest.raises(FileNotFoundError, match="nowhere.png"):
        load_dirt_map(path)


@pytest.mark.parametrize("name", ["garbage.png", "garbage.tif", "garbage.exr", "garbage.jpg"])
def test_garbage_files(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(b"this is not an image at all" * 10)
    with pytest.raises(ValueError, match=name) as info:
        load_dirt_map(path)
    assert "PNG" in str(info.value) and "OpenEXR" in str(info.value)


def test_unsupported_extension(tmp_path):
    path = tmp_path / "dirt.bmp"
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(path)
    with pytest.raises(ValueError, match="dirt.bmp") as info:
        load_dirt_map(path)
    assert "TIFF" in str(info.value)


def test_out_of_range_floats(tmp_path):
    rgb = np.full((3, 3, 3), 0.5, np.float32)
    rgb[1, 1, 2] = 1.75
    rgb[0, 2, 0] = -0.25
    write_exr(tmp_path / "bright.exr", {"": rgb}, pixel_type="float")
    with pytest.raises(ValueError, match="bright.exr") as info:
        load_dirt_map(tmp_path / "bright.exr")
    message = str(info.value)
    assert "-0.25" in message and "1.75" in message and "transmission in [0, 1]" in message


def test_non_finite_values(tmp_path):
    values = np.full((3, 3), 0.5, np.float32)
    values[1, 1] = np.nan
    Image.fromarray(values).save(tmp_path / "nan.tif")
    with pytest.raises(ValueError, match="nan.tif.*non-finite"):
        load_dirt_map(tmp_path / "nan.tif")
    # an EXR with an infinity (write_exr refuses to write one, so write it with the bindings)
    channel = np.full((3, 3), 0.5, np.float32)
    channel[0, 0] = np.inf
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"Y": channel}).write(str(tmp_path / "inf.exr"))
    with pytest.raises(ValueError, match="inf.exr.*non-finite"):
        load_dirt_map(tmp_path / "inf.exr")


def test_too_small(tmp_path):
    Image.fromarray(np.zeros((1, 5), np.uint8)).save(tmp_path / "thin.png")
    with pytest.raises(ValueError, match="thin.png.*at least 2 x 2"):
        load_dirt_map(tmp_path / "thin.png")


def test_cell_taps_reproduce_the_transmission_inside_and_beyond_the_map():
    """dirt_cell_taps gives the cells and weights through which dirt_transmission reads each point
    (inside, on the clamped border and far outside the map), for maps down to the smallest, 2 x 2."""
    from jaxflare.rendering.effects import dirt_cell_taps

    rng = np.random.default_rng(3)
    xy = jnp.asarray(rng.uniform(-14.0, 14.0, (400, 2)))  # a front radius of 10 mm: a fifth lie outside
    for shape in ((5, 7), (2, 9), (2, 2)):
        dirt = rng.uniform(0.1, 1.0, shape + (1,))
        expected = np.asarray(dirt_transmission(jnp.asarray(dirt), xy, 10.0))[:, 0]
        taps = dirt_cell_taps(shape, xy, 10.0)
        weights = np.stack([np.asarray(w) for _, w in taps])
        assert np.all(weights >= -1e-12) and np.allclose(weights.sum(axis=0), 1.0), shape
        assembled = sum(dirt.reshape(-1)[np.asarray(c)] * np.asarray(w) for c, w in taps)
        np.testing.assert_allclose(assembled, expected, rtol=1e-12, err_msg=str(shape))
