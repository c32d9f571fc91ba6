"""Multi-layer EXR output (jaxflare.io._exr) and tone-mapped PNG previews (jaxflare.io._preview)."""

import json
import os

import matplotlib.image
import numpy as np
import OpenEXR
import pytest

from jaxflare.io import _exr
from jaxflare.io import HALF_CLIPPED_ATTRIBUTE, read_exr, write_exr
from jaxflare.io import tone_map, write_png

H, W = 6, 9


def _image(channels: int, seed: int = 0, scale: float = 10.0) -> np.ndarray:
    return (np.random.default_rng(seed).normal(size=(H, W, channels)) * scale).astype(np.float32)


def _layers() -> dict[str, np.ndarray]:
    return {"": _image(4, 0), "ghosts": _image(3, 1), "mask_1": _image(1, 2), "ghost-2": _image(3, 3)}


# --------------------------------------------------------------------------------------------- EXR


def test_round_trip_float_is_exact(tmp_path):
    layers = _layers()
    path = tmp_path / "out.exr"
    write_exr(path, layers, pixel_type="float")
    back, header = read_exr(path)
    assert list(back) == ["", "ghost-2", "ghosts", "mask_1"]  # default layer first, then by name
    for name, image in layers.items():
        assert back[name].dtype == np.float32
        assert back[name].shape == image.shape
        np.testing.assert_array_equal(back[name], image)
    assert header["compression"] == "zip"
    assert HALF_CLIPPED_ATTRIBUTE not in header


def test_round_trip_half_equals_float16_cast(tmp_path):
    layers = {name: image.astype(np.float64) * 1.001 for name, image in _layers().items()}
    path = tmp_path / "out.exr"
    write_exr(path, layers)  # half by default
    back, header = read_exr(path)
    for name, image in layers.items():
        assert back[name].dtype == np.float32
        np.testing.assert_array_equal(back[name], image.astype(np.float16).astype(np.float32))
    assert header[HALF_CLIPPED_ATTRIBUTE] == 0


def test_channel_names_follow_multilayer_convention(tmp_path):
    path = tmp_path / "out.exr"
    write_exr(path, _layers())
    names = set(OpenEXR.File(str(path), separate_channels=True).channels())
    assert names == {
        "R", "G", "B", "A",
        "ghosts.R", "ghosts.G", "ghosts.B",
        "ghost-2.R", "ghost-2.G", "ghost-2.B",
        "mask_1.Y",
    }  # fmt: skip


def test_single_channel_default_layer_is_y(tmp_path):
    path = tmp_path / "y.exr"
    image = _image(1)
    write_exr(path, {"": image}, pixel_type="float")
    assert set(OpenEXR.File(str(path), separate_channels=True).channels()) == {"Y"}
    back, _ = read_exr(path)
    np.testing.assert_array_equal(back[""], image)


def test_header_attributes_round_trip(tmp_path):
    path = tmp_path / "out.exr"
    lens = {"name": "zeiss_biotar", "surfaces": [1, 2, 3], "f": 58.0}
    header = {
        "jaxflare/lens": lens,
        "jaxflare/scene": "night street",
        "jaxflare/samples": 4096,
        "jaxflare/exposure": 0.5,
        "jaxflare/wavelengths_nm": [450.0, 550.0, 650.0],
        "jaxflare/seed": np.int64(7),
    }
    write_exr(path, {"": _image(3)}, header=header)
    _, back = read_exr(path)
    assert back["jaxflare/scene"] == "night street"
    assert back["jaxflare/samples"] == 4096 and isinstance(back["jaxflare/samples"], int)
    assert back["jaxflare/seed"] == 7
    assert back["jaxflare/exposure"] == 0.5
    assert json.loads(back["jaxflare/lens"]) == lens
    assert json.loads(back["jaxflare/wavelengths_nm"]) == [450.0, 550.0, 650.0]


@pytest.mark.parametrize("bad", [{"compression": "x"}, {"channels": "x"}, {HALF_CLIPPED_ATTRIBUTE: 1}, {"big": 2**40}])
def test_bad_header_attributes_rejected(tmp_path, bad):
    with pytest.raises(ValueError):
        write_exr(tmp_path / "out.exr", {"": _image(3)}, header=bad)
    assert not os.listdir(tmp_path)


def test_unsupported_header_type_rejected(tmp_path):
    with pytest.raises(TypeError, match="none"):
        write_exr(tmp_path / "out.exr", {"": _image(3)}, header={"none": None})


@pytest.mark.parametrize("pixel_type", ["half", "float"])
def test_non_contiguous_input_round_trips(tmp_path, pixel_type):
    # The bindings silently scramble strided arrays; write_exr must copy each channel contiguously.
    base = np.random.default_rng(5).normal(size=(W, H, 4)).astype(np.float32)
    transposed = base.transpose(1, 0, 2)  # (H, W, 4), not C-contiguous
    strided = np.random.default_rng(6).normal(size=(2 * H, W, 6)).astype(np.float32)[::2, :, 1:4]
    fortran = np.asfortranarray(_image(1, 7))
    assert not transposed.flags.c_contiguous and not strided.flags.c_contiguous and not fortran.flags.c_contiguous
    path = tmp_path / "out.exr"
    write_exr(path, {"": transposed, "strided": strided, "fortran": fortran}, pixel_type=pixel_type)
    back, _ = read_exr(path)
    dtype = np.float32 if pixel_type == "float" else np.float16
    np.testing.assert_array_equal(back[""], transposed.astype(dtype))
    np.testing.assert_array_equal(back["strided"], strided.astype(dtype))
    np.testing.assert_array_equal(back["fortran"], fortran.astype(dtype))


@pytest.mark.parametrize("bad_value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("pixel_type", ["half", "float"])
def test_non_finite_rejected_naming_layer(tmp_path, bad_value, pixel_type):
    layers = _layers()
    layers["ghosts"][1, 2, 0] = bad_value
    layers["ghosts"][3, 4, 2] = bad_value
    with pytest.raises(ValueError, match=r"'ghosts'.* 2 non-finite"):
        write_exr(tmp_path / "out.exr", layers, pixel_type=pixel_type)
    assert not os.listdir(tmp_path)


def test_half_clipping_counted(tmp_path):
    image = np.zeros((H, W, 3))
    image[0, 0, 0] = 1e6
    image[1, 1, 1] = -70000.0
    image[2, 2, 2] = 65504.0  # representable: not clipped
    image[3, 3, 0] = 1e30
    other = np.zeros((H, W, 1))
    other[0, 0, 0] = 65505.0
    path = tmp_path / "out.exr"
    write_exr(path, {"": image, "other": other})
    back, header = read_exr(path)
    assert header[HALF_CLIPPED_ATTRIBUTE] == 4
    assert back[""][0, 0, 0] == 65504.0 and back[""][1, 1, 1] == -65504.0 and back[""][3, 3, 0] == 65504.0
    assert back[""][2, 2, 2] == 65504.0 and back["other"][0, 0, 0] == 65504.0
    assert all(np.isfinite(layer).all() for layer in back.values())


def test_float_overflow_rejected(tmp_path):
    image = np.zeros((H, W, 3))
    image[0, 0, 0] = 1e300
    with pytest.raises(ValueError, match="float32 range"):
        write_exr(tmp_path / "out.exr", {"": image}, pixel_type="float")


def test_shape_mismatch_rejected(tmp_path):
    with pytest.raises(ValueError, match=r"'b'.*\(6, 8, 3\).*'a'"):
        write_exr(tmp_path / "out.exr", {"a": np.zeros((6, 9, 3)), "b": np.zeros((6, 8, 3))})


@pytest.mark.parametrize(
    "layers",
    [
        {"": np.zeros((H, W, 2))},
        {"": np.zeros((H, W))},
        {"": np.zeros((0, W, 3))},
        {"": np.zeros((H, W, 3), dtype=complex)},
        {},
    ],
)
def test_bad_layer_shapes_rejected(tmp_path, layers):
    with pytest.raises(ValueError):
        write_exr(tmp_path / "out.exr", layers)


@pytest.mark.parametrize("name", ["a.b", "with space", "ümlaut", "x/y", "R:G"])
def test_bad_layer_names_rejected(tmp_path, name):
    with pytest.raises(ValueError, match="layer name"):
        write_exr(tmp_path / "out.exr", {name: np.zeros((H, W, 3))})


def test_bad_compression_and_pixel_type_rejected(tmp_path):
    with pytest.raises(ValueError, match="dwab"):
        write_exr(tmp_path / "out.exr", {"": _image(3)}, compression="lzw")
    with pytest.raises(ValueError, match="pixel_type"):
        write_exr(tmp_path / "out.exr", {"": _image(3)}, pixel_type="double")
    assert not os.listdir(tmp_path)


@pytest.mark.parametrize("compression", list(_exr.COMPRESSIONS))
@pytest.mark.parametrize("pixel_type", ["half", "float"])
def test_every_compression_readable(tmp_path, compression, pixel_type):
    # Smooth positive data, as lossy codecs expect of images; large enough for whole blocks.
    y, x = np.mgrid[0:32, 0:48] / 16.0
    image = np.stack([1.0 + np.sin(x), 1.0 + np.cos(y), 0.5 + 0.25 * x * y / 6.0], axis=-1).astype(np.float32)
    path = tmp_path / "out.exr"
    write_exr(path, {"": image, "ghost": image[..., :1] * 3.0}, pixel_type=pixel_type, compression=compression.upper())
    back, header = read_exr(path)
    assert header["compression"] == compression
    dtype = np.float16 if pixel_type == "half" else np.float32
    lossy = compression in {"b44", "b44a", "dwaa", "dwab"} or (compression == "pxr24" and pixel_type == "float")
    for name, expected in (("", image), ("ghost", image[..., :1] * 3.0)):
        expected = expected.astype(dtype).astype(np.float32)
        if lossy:
            np.testing.assert_allclose(back[name], expected, rtol=0.02, atol=0.02)
        else:
            np.testing.assert_array_equal(back[name], expected)


def test_error_while_writing_leaves_existing_target_untouched(tmp_path, monkeypatch):
    path = tmp_path / "out.exr"
    write_exr(path, _layers())
    before = path.read_bytes()

    class FailingFile:
        def __init__(self, header, channels):
            pass

        def write(self, temporary):
            with open(temporary, "wb") as handle:  # a half-written file, then a crash
                handle.write(b"\x76\x2f\x31\x01partial")
            raise RuntimeError("disk full")

    monkeypatch.setattr(_exr.OpenEXR, "File", FailingFile)
    with pytest.raises(RuntimeError, match="disk full"):
        write_exr(path, {"": _image(3, 9)})
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["out.exr"]


def test_invalid_second_layer_leaves_existing_target_untouched(tmp_path):
    path = tmp_path / "out.exr"
    write_exr(path, _layers())
    before = path.read_bytes()
    bad = _layers()
    bad["ghosts"][0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="ghosts"):
        write_exr(path, bad)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["out.exr"]


def test_read_missing_and_non_exr(tmp_path):
    missing = tmp_path / "missing.exr"
    with pytest.raises(FileNotFoundError, match="missing.exr"):
        read_exr(missing)
    text = tmp_path / "notes.exr"
    text.write_text("not an image")
    with pytest.raises(ValueError, match="notes.exr"):
        read_exr(text)
    truncated = tmp_path / "truncated.exr"
    write_exr(truncated, {"": np.ones((64, 64, 3))}, compression="none")
    data = truncated.read_bytes()
    for end in (40, len(data) // 2):  # inside the header; inside the pixel data
        truncated.write_bytes(data[:end])
        with pytest.raises(ValueError, match="truncated.exr"):
            read_exr(truncated)


def test_layer_pixel_types_keep_a_float_layer_in_a_half_file(tmp_path):
    """A variance (a luminance squared, ~1e-9) underflows to 0 in float16; a float32 layer in a
    half file keeps it exactly, and OpenEXR's own reader sees the two pixel types."""
    layers = {"": _image(4), "variance": np.full((H, W, 1), 3e-9, np.float32)}
    write_exr(tmp_path / "mixed.exr", layers, pixel_type="half", layer_pixel_types={"variance": "float"})
    back, header = read_exr(tmp_path / "mixed.exr")
    np.testing.assert_array_equal(back["variance"], layers["variance"])
    np.testing.assert_array_equal(back[""], layers[""].astype(np.float16).astype(np.float32))
    assert header[HALF_CLIPPED_ATTRIBUTE] == 0
    kinds = {name: channel.pixels.dtype for name, channel in OpenEXR.File(str(tmp_path / "mixed.exr"), separate_channels=True).channels().items()}
    assert kinds["variance.Y"] == np.float32 and kinds["R"] == np.float16
    write_exr(tmp_path / "all_half.exr", layers, pixel_type="half")
    assert not np.any(read_exr(tmp_path / "all_half.exr")[0]["variance"])  # what the override prevents
    for bad, match in (({"nope": "float"}, "not among the layers"), ({"variance": "double"}, "must be one of")):
        with pytest.raises(ValueError, match=match):
            write_exr(tmp_path / "bad.exr", layers, layer_pixel_types=bad)


def test_chromaticities_and_white_luminance_are_standard_attributes(tmp_path):
    """OpenEXR's own reader (and OpenImageIO, where installed) read the declared colour space."""
    from jaxflare.colour import colour_space_chromaticities

    rec709 = colour_space_chromaticities("srgb-linear")
    np.testing.assert_allclose(rec709, (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290), atol=1e-4)
    write_exr(tmp_path / "c.exr", {"": _image(3)}, chromaticities=rec709, white_luminance=100.0)
    header = OpenEXR.File(str(tmp_path / "c.exr")).header()
    np.testing.assert_allclose(header["chromaticities"], rec709, atol=1e-6)
    assert header["whiteLuminance"] == pytest.approx(100.0)
    for bad in ((0.64, 0.33), (float("nan"),) * 8):
        with pytest.raises(ValueError, match="chromaticities"):
            write_exr(tmp_path / "bad.exr", {"": _image(3)}, chromaticities=bad)
    with pytest.raises(ValueError, match="white_luminance"):
        write_exr(tmp_path / "bad.exr", {"": _image(3)}, white_luminance=-1.0)
    with pytest.raises(ValueError, match="reserved"):
        write_exr(tmp_path / "bad.exr", {"": _image(3)}, header={"chromaticities": "ACEScg"})
    assert not (tmp_path / "bad.exr").exists()


# ----------------------------------------------------------------------------------------- preview

ACESCG_TO_SRGB = np.array(
    [
        [1.70505, -0.62179, -0.08326],
        [-0.13026, 1.14080, -0.01055],
        [-0.02400, -0.12897, 1.15297],
    ]
)


def _srgb_8bit(linear: float) -> int:
    encoded = 12.92 * linear if linear <= 0.0031308 else 1.055 * linear ** (1 / 2.4) - 0.055
    return round(encoded * 255)


def test_tone_map_black_stays_black():
    for stops in (None, 0.0, 10.0):
        out = tone_map(np.zeros((H, W, 3)), exposure_stops=stops)
        assert out.dtype == np.uint8 and out.shape == (H, W, 3) and not out.any()


def test_tone_map_negative_clipped_and_nonfinite_rejected():
    image = np.full((H, W, 3), -1.0)
    assert not tone_map(image).any()
    image[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        tone_map(image)
    with pytest.raises(ValueError):
        tone_map(np.zeros((H, W, 4)))


def test_tone_map_monotonic_along_ramp():
    ramp = np.geomspace(1e-4, 1e4, 2000)
    image = np.zeros((3, ramp.size, 3))
    image[1] = ramp[:, None]
    for stops in (None, 0.0, -3.0):
        values = tone_map(image, exposure_stops=stops)[1].astype(int)
        assert np.all(np.diff(values, axis=0) >= 0)
        assert values[0, 0] < values[-1, 0]
        assert (values[:, 0] == values[:, 1]).all() and (values[:, 0] == values[:, 2]).all()  # grey stays grey
    assert not tone_map(image)[0].any()


def test_tone_map_fixed_exposure_values():
    image = np.array([[[1.0, 0.25, 0.0]]])
    out = tone_map(image, exposure_stops=0.0)
    assert out[0, 0].tolist() == [_srgb_8bit(0.5), _srgb_8bit(0.2), 0]
    out = tone_map(image, exposure_stops=2.0)
    assert out[0, 0].tolist() == [_srgb_8bit(0.8), _srgb_8bit(0.5), 0]


def test_tone_map_exposure_brightens():
    image = np.abs(np.random.default_rng(0).normal(size=(H, W, 3)))
    darker = tone_map(image, exposure_stops=0.0).astype(int)
    brighter = tone_map(image, exposure_stops=1.0).astype(int)
    assert np.all(brighter >= darker) and brighter.sum() > darker.sum()


def test_tone_map_auto_exposure_ignores_black_background():
    # A mostly black flare image: a few bright pixels must land near 0.8 after the curve.
    image = np.zeros((100, 100, 3))
    image[50, 50] = 1000.0
    image[10, 20] = 3000.0
    out = tone_map(image)
    assert out[10, 20].tolist() == [_srgb_8bit(0.8)] * 3
    assert 0 < out[50, 50, 0] < out[10, 20, 0]
    assert out[0, 0].tolist() == [0, 0, 0]
    # Scaling the input does not change the auto-exposed preview.
    np.testing.assert_array_equal(tone_map(image * 1e-6), out)


def test_tone_map_matrix_applied():
    permute = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # out = (G, B, R)
    red = np.zeros((1, 1, 3))
    red[..., 0] = 1.0
    assert tone_map(red, to_srgb_matrix=permute, exposure_stops=0.0)[0, 0].tolist() == [0, 0, _srgb_8bit(0.5)]

    # ACEScg -> linear sRGB: pure ACEScg red is more saturated than sRGB red (G, B negative, clipped);
    # an ACEScg red-yellow mixes into all three channels; white stays neutral.
    out = tone_map(red, to_srgb_matrix=ACESCG_TO_SRGB, exposure_stops=0.0)[0, 0]
    assert out.tolist() == [_srgb_8bit(1.70505 / 2.70505), 0, 0]
    mixed = np.array([[[1.0, 0.5, 0.2]]])
    srgb = ACESCG_TO_SRGB @ mixed[0, 0]
    out = tone_map(mixed, to_srgb_matrix=ACESCG_TO_SRGB, exposure_stops=0.0)[0, 0]
    assert out.tolist() == [_srgb_8bit(v / (1 + v)) for v in srgb]
    assert out.tolist() != tone_map(mixed, exposure_stops=0.0)[0, 0].tolist()
    white = tone_map(np.ones((1, 1, 3)), to_srgb_matrix=ACESCG_TO_SRGB, exposure_stops=0.0)[0, 0]
    assert max(white) - min(white) <= 1
    with pytest.raises(ValueError):
        tone_map(red, to_srgb_matrix=np.eye(4))


def test_write_png(tmp_path):
    rgb = np.abs(np.random.default_rng(1).normal(size=(H, W, 3)))
    image = tone_map(rgb)
    path = tmp_path / "preview.png"
    path.write_bytes(b"old")
    write_png(path, image)
    back = matplotlib.image.imread(path)
    assert back.shape[:2] == (H, W) and back.shape[2] in (3, 4)
    np.testing.assert_array_equal(np.round(back[..., :3] * 255).astype(np.uint8), image)
    assert os.listdir(tmp_path) == ["preview.png"]
    with pytest.raises(ValueError):
        write_png(path, image.astype(np.float32))
