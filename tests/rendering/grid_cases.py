"""Small scenes and cached renders shared by the grid estimator's tests (tests/rendering/test_grid_*.py).

Renders are cached per process (``functools.lru_cache``), so test files that ask for the same
scene share its render and its compilations. Images are tiny (64 x 48) and use a directional
(point-like) light unless a test is about extended lights.
"""

import functools

import numpy as np

import jaxflare as jf
from jaxflare import rendering
from jaxflare.colour import spectral_table

RESOLUTION = (64, 48)


def scene(lens="zeiss_biotar", direction=(0.04, 0.02, -1.0), blades=6, f_number=8.0, resolution=RESOLUTION, core=False, light=None, **render):
    light = light or jf.Light(kind="directional", direction=direction)
    camera = jf.Camera(lens=lens, f_number=f_number, aperture_blades=blades, resolution=resolution, look_at_m=(0.0, 0.0, -10.0))
    return jf.Scene(camera=camera, lights=(light,), render=jf.RenderSettings(core=core, **render))


@functools.cache
def grid(lens="zeiss_biotar", direction=(0.04, 0.02, -1.0), paths=((7, 4), (9, 7)), blades=6, f_number=8.0, options=(), square=False):
    """A grid render (``options``: GridQuality overrides as ((name, value), ...); ``square``: 64 x 64)."""
    s = scene(lens, direction, blades, f_number, resolution=(64, 64) if square else RESOLUTION)
    return rendering.render_grid(s, paths=list(paths), grid_error=1e-9, grid_options=dict(options))


@functools.cache
def monte_carlo(lens="zeiss_biotar", direction=(0.04, 0.02, -1.0), paths=((7, 4), (9, 7)), blades=6, f_number=8.0, seeds=5, samples=2**17):
    """Monte Carlo renders at ``seeds`` seeds (uniform sampling, so the seeds are independent and identically distributed)."""
    s = scene(lens, direction, blades, f_number, sampling="uniform")
    return tuple(jf.render(s, seed=seed, samples=samples, paths=list(paths), estimator="monte-carlo") for seed in range(seeds))


def blur(image, passes=2):
    """A small separable blur ([1, 2, 1] / 4, ``passes`` times, edges clamped)."""
    for _ in range(passes):
        for axis in (0, 1):
            padded = np.concatenate([np.take(image, [0], axis), image, np.take(image, [-1], axis)], axis)
            n = image.shape[axis]
            image = (np.take(padded, range(n), axis) + 2 * np.take(padded, range(1, n + 1), axis) + np.take(padded, range(2, n + 2), axis)) / 4
    return image


def luminance(image):
    return image[..., :3] @ np.asarray(spectral_table("ACEScg").luminance_weights)


def strongest_paths(lens_name, count=2):
    return tuple(path for path, _ in jf.rank_ghost_paths(jf.load_lens(lens_name))[:count])
