"""Plates (reference images) for fitting: reading EXR/PNG/TIFF, masks, weights and errors."""

import struct
import warnings
import zlib

import numpy as np
import pytest
from PIL import Image

from fitting._plate import Plate, PlateQuantisationWarning, load_plate, save_plate
from jaxflare.io import write_exr


def _ramp(height=4, width=5, scale=1.0):
    return (np.arange(height * width * 3, dtype=np.float64).reshape(height, width, 3) + 1) * scale


def _save16(path, values):
    Image.fromarray(np.asarray(values, dtype=np.uint16)).save(path)  # mode "I;16"


def _png16_rgb(path, values):
    """A 16-bit-per-channel RGB PNG (Pillow cannot write one), rows filtered with Sub and Paeth."""
    values = np.asarray(values, dtype=">u2")
    height, width, _ = values.shape
    rows = [values[i].tobytes() for i in range(height)]
    bpp = 6
    raw = b""
    for i, row in enumerate(rows):
        previous = rows[i - 1] if i else bytes(len(row))
        kind = 1 if i % 2 == 0 else 4
        out = bytearray()
        for k, byte in enumerate(row):
            a = row[k - bpp] if k >= bpp else 0
            b = previous[k]
            c = previous[k - bpp] if k >= bpp else 0
            if kind == 1:
                predictor = a
            else:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                predictor = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            out.append((byte - predictor) % 256)
        raw += bytes([kind]) + bytes(out)

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 16, 2, 0, 0, 0)
    with open(path, "wb") as handle:
        handle.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def _tiff16_rgb(path, values):
    """A minimal uncompressed little-endian 16-bit-per-channel RGB TIFF (Pillow cannot write one)."""
    values = np.asarray(values, dtype="<u2")
    height, width, _ = values.shape
    data = values.tobytes()
    entries = [(256, width), (257, height), (258, None), (259, 1), (262, 2), (273, None), (277, 3), (278, height)]
    entries.append((279, len(data)))
    ifd_offset = 8
    bits_offset = ifd_offset + 2 + 12 * len(entries) + 4
    data_offset = bits_offset + 6
    out = b"II*\x00" + struct.pack("<I", ifd_offset) + struct.pack("<H", len(entries))
    for tag, value in entries:
        if tag == 258:
            out += struct.pack("<HHII", tag, 3, 3, bits_offset)
        elif tag in (273, 279):
            out += struct.pack("<HHII", tag, 4, 1, data_offset if tag == 273 else value)
        else:
            out += struct.pack("<HHIHH", tag, 3, 1, value, 0)
    out += struct.pack("<I", 0) + struct.pack("<HHH", 16, 16, 16) + data
    with open(path, "wb") as handle:
        handle.write(out)


# ------------------------------------------------------------------------------------------------ EXR


def test_exr_default_layer_round_trip(tmp_path):
    rgb = _ramp(scale=0.01)
    save_plate(tmp_path / "p.exr", rgb)
    plate = load_plate(tmp_path / "p.exr")
    assert isinstance(plate, Plate)
    assert plate.rgb.dtype == np.float64 and plate.rgb.shape == (4, 5, 3)
    np.testing.assert_allclose(plate.rgb, rgb.astype(np.float32), rtol=0, atol=0)
    np.testing.assert_array_equal(plate.weight, np.ones((4, 5)))
    assert plate.source == str(tmp_path / "p.exr") and plate.layer == ""
    assert plate.size == (5, 4)
    assert not plate.rgb.flags.writeable


def test_exr_named_layer_and_single_layer(tmp_path):
    rgb = _ramp()
    write_exr(tmp_path / "two.exr", {"": np.zeros((4, 5, 3)), "flare": rgb}, pixel_type="float")
    plate = load_plate(tmp_path / "two.exr", layer="flare")
    np.testing.assert_array_equal(plate.rgb, rgb)
    assert plate.layer == "flare"
    assert np.all(load_plate(tmp_path / "two.exr").rgb == 0)  # the default layer
    save_plate(tmp_path / "one.exr", rgb, layer="beauty")
    only = load_plate(tmp_path / "one.exr")  # the only layer
    assert only.layer == "beauty"
    np.testing.assert_array_equal(only.rgb, rgb)
    with pytest.raises(ValueError, match="no layer 'nope'.*'beauty'"):
        load_plate(tmp_path / "one.exr", layer="nope")


def test_exr_several_layers_without_a_name(tmp_path):
    write_exr(tmp_path / "p.exr", {"ghosts": _ramp(), "primary": _ramp(), "rgba": np.ones((4, 5, 4))})
    with pytest.raises(ValueError, match="several layers") as error:
        load_plate(tmp_path / "p.exr")
    for name in ("'ghosts'", "'primary'", "'rgba'"):
        assert name in str(error.value)
    rgba = load_plate(tmp_path / "p.exr", layer="rgba")
    np.testing.assert_array_equal(rgba.rgb, np.ones((4, 5, 3)))  # alpha dropped


def test_exr_y_layer_broadcast(tmp_path):
    grey = np.arange(20, dtype=np.float64).reshape(4, 5) / 8
    save_plate(tmp_path / "y.exr", grey)
    plate = load_plate(tmp_path / "y.exr")
    for channel in range(3):
        np.testing.assert_array_equal(plate.rgb[..., channel], grey)


# ------------------------------------------------------------------------------------------------ PNG / TIFF


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_16bit_grey_values(tmp_path, suffix):
    values = np.array([[0, 1000, 65535], [7, 30000, 123]])
    _save16(tmp_path / f"p{suffix}", values)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        plate = load_plate(tmp_path / f"p{suffix}")
    np.testing.assert_allclose(plate.rgb, np.repeat((values / 65535.0)[..., None], 3, axis=-1), rtol=1e-15)


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_16bit_rgb_keeps_all_bits(tmp_path, suffix):
    # Pillow alone would read these as 8-bit (the high bytes); load_plate recovers the low bytes too.
    values = (np.arange(3 * 4 * 3).reshape(3, 4, 3) * 1777 + 13) % 65536
    (_png16_rgb if suffix == ".png" else _tiff16_rgb)(tmp_path / f"rgb16{suffix}", values)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        plate = load_plate(tmp_path / f"rgb16{suffix}")
    np.testing.assert_allclose(plate.rgb * 65535.0, values, rtol=0, atol=1e-9)


def test_8bit_warns(tmp_path):
    values = np.array([[[0, 128, 255], [1, 2, 3]]], dtype=np.uint8)
    Image.fromarray(values).save(tmp_path / "p.png")
    with pytest.warns(PlateQuantisationWarning, match="8-bit"):
        plate = load_plate(tmp_path / "p.png")
    np.testing.assert_allclose(plate.rgb, values / 255.0)


def test_srgb_decoding(tmp_path):
    values = np.array([[0, 2000, 30000, 65535]])
    _save16(tmp_path / "p.png", values)
    plate = load_plate(tmp_path / "p.png", encoding="srgb")
    encoded = values / 65535.0
    expected = np.where(encoded <= 0.04045, encoded / 12.92, ((encoded + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(plate.rgb[..., 1], expected, rtol=1e-12)
    assert plate.rgb[0, 3, 0] == pytest.approx(1.0) and plate.rgb[0, 2, 0] < encoded[0, 2]
    with pytest.raises(ValueError, match="encoding"):
        load_plate(tmp_path / "p.png", encoding="gamma")


# ------------------------------------------------------------------------------------------------ errors


def test_size_mismatch_names_both_sizes(tmp_path):
    save_plate(tmp_path / "p.exr", _ramp())
    assert load_plate(tmp_path / "p.exr", expected_size=(5, 4)).size == (5, 4)
    with pytest.raises(ValueError, match="5 x 4.*640 x 480.*camera.resolution") as error:
        load_plate(tmp_path / "p.exr", expected_size=(640, 480))
    assert "p.exr" in str(error.value)


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.exr"):
        load_plate(tmp_path / "nope.exr")
    save_plate(tmp_path / "p.exr", _ramp())
    with pytest.raises(FileNotFoundError, match="no_mask.png"):
        load_plate(tmp_path / "p.exr", mask=tmp_path / "no_mask.png")


def test_nan_error_and_nan_under_zero_mask(tmp_path):
    rgb = _ramp()
    rgb[1, 2, 0] = np.nan
    rgb[3, 4, :] = np.nan
    rgb[0, 0, 1] = np.inf
    _write_exr_with_nan(tmp_path / "p.exr", rgb)
    with pytest.raises(ValueError, match=r"p\.exr.* 3 pixel"):
        load_plate(tmp_path / "p.exr")
    mask = np.ones((4, 5))
    mask[1, 2] = mask[3, 4] = mask[0, 0] = 0
    plate = load_plate(tmp_path / "p.exr", mask=mask)
    assert np.all(np.isfinite(plate.rgb))
    assert plate.rgb[1, 2, 0] == 0 and np.all(plate.rgb[3, 4] == 0)
    assert np.all(plate.rgb[1, 2] == 0)  # the whole non-finite pixel is zeroed
    assert plate.rgb[2, 2, 1] == rgb[2, 2, 1] and plate.weight[1, 2] == 0 and plate.weight[2, 2] == 1
    mask[0, 0] = 0.5
    with pytest.raises(ValueError, match="1 pixel.*mask is non-zero"):
        load_plate(tmp_path / "p.exr", mask=mask)


def _write_exr_with_nan(path, rgb):
    """write_exr refuses non-finite values: write the channels with the OpenEXR bindings directly."""
    import OpenEXR

    channels = {name: np.ascontiguousarray(rgb[..., k], dtype=np.float32) for k, name in enumerate("RGB")}
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels).write(str(path))


# ------------------------------------------------------------------------------------------------ masks and weights


def test_mask_from_png_and_array(tmp_path):
    save_plate(tmp_path / "p.exr", _ramp())
    mask8 = np.full((4, 5), 255, dtype=np.uint8)
    mask8[0] = 0
    mask8[1, 1] = 51
    Image.fromarray(mask8).save(tmp_path / "mask.png")
    plate = load_plate(tmp_path / "p.exr", mask=tmp_path / "mask.png")
    np.testing.assert_allclose(plate.weight, mask8 / 255.0)
    rgb_mask = np.repeat(mask8[..., None], 3, axis=-1)
    Image.fromarray(rgb_mask).save(tmp_path / "mask_rgb.png")
    np.testing.assert_allclose(load_plate(tmp_path / "p.exr", mask=tmp_path / "mask_rgb.png").weight, mask8 / 255.0)
    boolean = mask8 > 0
    np.testing.assert_array_equal(load_plate(tmp_path / "p.exr", mask=boolean).weight, boolean.astype(float))


def test_wrong_size_and_empty_and_out_of_range_masks(tmp_path):
    save_plate(tmp_path / "p.exr", _ramp())
    with pytest.raises(ValueError, match=r"6 x 3.*5 x 4"):
        load_plate(tmp_path / "p.exr", mask=np.ones((3, 6)))
    Image.fromarray(np.ones((3, 6), dtype=np.uint8) * 255).save(tmp_path / "m.png")
    with pytest.raises(ValueError, match=r"m\.png.*6 x 3.*5 x 4"):
        load_plate(tmp_path / "p.exr", mask=tmp_path / "m.png")
    with pytest.raises(ValueError, match="empty mask: nothing to fit"):
        load_plate(tmp_path / "p.exr", mask=np.zeros((4, 5)))
    with pytest.raises(ValueError, match=r"outside \[0, 1\]"):
        load_plate(tmp_path / "p.exr", mask=np.full((4, 5), 2.0))


def test_noise_sigma_weights(tmp_path):
    save_plate(tmp_path / "p.exr", _ramp())
    assert np.all(load_plate(tmp_path / "p.exr", noise_sigma=0.5).weight == 2.0)
    sigma = np.linspace(0.1, 2.0, 20).reshape(4, 5)
    mask = np.ones((4, 5))
    mask[0, :2] = 0
    plate = load_plate(tmp_path / "p.exr", mask=mask, noise_sigma=sigma)
    np.testing.assert_allclose(plate.weight, mask / sigma)
    sigma[0, 0] = 0.0  # masked out: allowed
    np.testing.assert_allclose(
        load_plate(tmp_path / "p.exr", mask=mask, noise_sigma=sigma).weight[0], [0, 0, *(1 / sigma[0, 2:])]
    )
    sigma[2, 2] = -1.0
    with pytest.raises(ValueError, match="noise_sigma.*> 0.*1 pixel"):
        load_plate(tmp_path / "p.exr", mask=mask, noise_sigma=sigma)
    with pytest.raises(ValueError, match="noise_sigma"):
        load_plate(tmp_path / "p.exr", noise_sigma=np.ones((2, 2)))
