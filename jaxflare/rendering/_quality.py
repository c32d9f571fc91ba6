"""What a render spends: the quality levels and the renderer's fixed budgets."""

from __future__ import annotations

import dataclasses
import math


@dataclasses.dataclass(frozen=True)
class Quality:
    """What a quality level spends: total Monte Carlo samples (``rays_per_path`` per path and batch),
    wavelength strata per batch, the polynomial degree and the sensor-position tolerance (in pixels
    of the render) a path system must meet to be used instead of exact tracing."""

    samples: int
    wavelength_strata: int
    degrees: tuple[int, ...]
    """Polynomial degrees tried, lowest first: each path gets the lowest that meets the tolerance."""
    tolerance_px: float
    pilot_fraction: float = 1 / 16


QUALITY_LEVELS = {
    "preview": Quality(samples=2**22, wavelength_strata=8, degrees=(3, 5), tolerance_px=1.0),
    "production": Quality(samples=2**26, wavelength_strata=32, degrees=(5, 7), tolerance_px=0.5),
}
TRUSTED_FOR_DEGREE = 0.9
"""A degree meets the tolerance when this fraction of its validation rays is trusted."""
RAYS_PER_STEP = 2**17
"""Rays per batch (all paths together): bounds the memory of one step."""
FALLBACK_CAPACITIES = (0.125, 0.25, 0.5, 1.0)
"""Exact-fallback capacities (fractions of a batch) a polynomial path can get."""
AUTO_MAX_FALLBACK = 0.25
"""``method="auto"``: a path whose polynomial does not trust more than this fraction of the
scene's samples (measured in the pilot) is traced exactly instead: beyond it, polynomial plus
fallback costs about as much as exact tracing (measured against the former exact tracer,
jaxflare 0.1.0: degree-5 systems were 1.6-5.6x faster on CPU; the current tracer is 6-8x faster
than that one, and this threshold has not been re-measured against it)."""


def radiance_scale(lens, pitch_mm: float) -> float:
    """Pixel value per unit of splatted flux: the camera equation ``E = pi L / (4 N^2)`` solved for
    the scene radiance L, over the pixel area (N: the lens's working f-number)."""
    return 4.0 * lens.f_number() ** 2 / math.pi / (pitch_mm * pitch_mm)
