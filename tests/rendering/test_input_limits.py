"""Issue 17: renders that cannot work are refused up front, with the key and the valid range,
instead of failing (or being killed) after the work: a picture too large for the memory, a seed
beyond JAX's 32-bit keys."""

import pytest

import jaxflare as jf
from jaxflare.rendering import _memory


def huge_scene(resolution=(16384, 16384)):
    return jf.Scene(
        camera=jf.Camera(lens="zeiss_biotar", f_number=8.0, resolution=resolution, look_at_m=(0.0, 0.0, -10.0)),
        lights=(jf.Light(kind="directional", direction=(0.05, 0.0, -1.0)),),
    )


def test_image_memory_estimate_counts_every_layer():
    """Device: float32 RGB per layer + 3 luminance images; host: float64 and float32 RGB per layer,
    the RGBA image, the float64 variance work and its float32 layer."""
    device, host = _memory.image_bytes(1000, 500, 14)
    assert device == 1000 * 500 * 4 * (3 * 14 + 3)
    assert host == 1000 * 500 * (3 * 14 * 12 + 16 + 24 + 4)
    assert _memory.image_bytes(16384, 16384, 14)[1] > 100 * 2**30  # the 16384^2 render of the issue


def test_huge_resolution_is_refused_before_tracing(monkeypatch):
    monkeypatch.setattr(_memory, "available_host_bytes", lambda: 8 * 2**30)
    with pytest.raises(jf.SceneError, match=r"camera\.resolution: 16384 x 16384 pixels .* GiB of memory, and 8\.0 GiB is available"):
        jf.render(huge_scene(), samples=2**16, method="exact")
    _memory.check_image_memory(640, 480, 14)  # an ordinary picture passes the same check


@pytest.mark.parametrize("seed", [2**70, -1, 2**32, 1.5, True])
def test_seed_beyond_32_bits_is_a_value_error(seed):
    with pytest.raises(ValueError, match=r"seed must be an integer from 0 to 4,294,967,295"):
        jf.render(huge_scene((64, 48)), seed=seed)
