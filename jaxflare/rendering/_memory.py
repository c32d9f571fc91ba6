"""An up-front memory estimate of a render's images, so that a picture too large for the machine
is refused before the lens is traced rather than failing (or being killed) at the end."""

from __future__ import annotations

import os

from ..scenes import SceneError

HEADROOM = 0.8
"""The share of the available memory a render's images may take."""


def available_host_bytes() -> int | None:
    """Memory the operating system can give this process now (``MemAvailable``), or None."""
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def image_bytes(width: int, height: int, num_layers: int) -> tuple[int, int]:
    """(device, host) bytes of a render's images: on the device the float32 accumulators (every
    layer's RGB, two luminance images, one batch's luminance); on the host the float64 and
    float32 copies of the layers, the RGBA image and the standard-deviation layer."""
    pixels = int(width) * int(height)
    device = pixels * 4 * (3 * num_layers + 3)
    host = pixels * (3 * num_layers * (8 + 4) + 4 * 4 + 3 * 8 + 4)
    return device, host


def check_image_memory(width: int, height: int, num_layers: int) -> None:
    """Raise :class:`~jaxflare.scenes.SceneError` when the render's images would not fit in memory."""
    import jax

    device_bytes, host_bytes = image_bytes(width, height, num_layers)
    limits = []
    available = available_host_bytes()
    if available is not None:
        on_cpu = jax.default_backend() == "cpu"
        limits.append(("memory", available, host_bytes + (device_bytes if on_cpu else 0)))
    try:
        stats = jax.devices()[0].memory_stats() or {}
    except Exception:  # noqa: BLE001 - backends without memory statistics raise various errors
        stats = {}
    if jax.default_backend() != "cpu" and stats.get("bytes_limit"):
        limits.append(("accelerator memory", int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0)), device_bytes))
    for what, have, need in limits:
        if need > HEADROOM * have:
            raise SceneError(
                f"camera.resolution: {width} x {height} pixels with {num_layers} image layers needs about {need / 2**30:.1f} GiB of {what}, "
                f"and {have / 2**30:.1f} GiB is available: lower the resolution or render.max_flare_layers"
            )
