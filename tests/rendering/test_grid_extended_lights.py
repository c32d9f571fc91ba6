"""Extended lights in the grid estimator: the light's disc drawn by convolving each path's image with
the disc's image (jaxflare/rendering/_grid_blur.py) instead of one disc point per sub-sample.

The convolution must be the same integral as sampling the disc (energies equal, images equal once
the sampled one's noise is smoothed away), without its noise, and the core of a sphere light must
be the even disc the camera equation predicts."""

import dataclasses
import math

import numpy as np
import pytest

import jaxflare as jf
from jaxflare import rendering
from jaxflare.rendering._grid_blur import disc_kernel

from .grid_cases import blur, luminance
from .test_render import make_scene, transmission_luminance


def kernel_covariance(kernel, border):
    rows, columns = np.indices(kernel.shape) - border
    moves = np.stack([columns.ravel(), rows.ravel()], axis=-1).astype(float)
    weight = kernel.ravel()
    mean = weight @ moves
    centred = moves - mean
    return mean, (centred * weight[:, None]).T @ centred


@pytest.mark.parametrize(
    "jacobian", [np.diag([6.0, 3.0]), np.array([[4.0, -3.0], [2.0, 5.0]]), np.array([[5.0, 5.0], [2.0, 2.0]])], ids=["axes", "sheared", "singular"],
)
def test_disc_kernel_is_the_unit_disc_moved_by_the_jacobian(jacobian):
    """A uniform unit disc has covariance I / 4, so its image under J has J J^T / 4 (plus a
    pixel's 1/12 from binning), centred on no move; a singular J (a move along a line) needs no
    inverse and puts the kernel on that line."""
    border = 8
    kernel = disc_kernel(jacobian, border)
    assert kernel.sum() == pytest.approx(1.0) and np.all(kernel >= 0)
    mean, covariance = kernel_covariance(kernel, border)
    np.testing.assert_allclose(mean, 0.0, atol=1e-3)
    np.testing.assert_allclose(covariance, jacobian @ jacobian.T / 4 + np.eye(2) / 12, atol=0.12)
    if abs(np.linalg.det(jacobian)) < 1e-9:  # every cell off the line's pixels is empty
        rows, columns = np.nonzero(kernel)
        direction = jacobian[:, 0] / np.linalg.norm(jacobian[:, 0])
        distance = np.abs((columns - border) * direction[1] - (rows - border) * direction[0])
        assert distance.max() < 1.0


def sphere_scene(position_m, radius_m=0.25, radiance=50.0, core=True):
    light = jf.Light(kind="sphere", position_m=position_m, radius_m=radius_m, intensity=radiance, rgb=(1.0, 1.0, 1.0))
    return make_scene(light, render=dict(core=core))


def test_sphere_light_core_by_convolution_is_an_even_disc_at_the_camera_equation():
    """The core of a sphere light of radiance L (as tests/rendering/test_render.py checks with
    Monte Carlo): pixels L T inside the image of the disc, zero beyond its rim, the flux of a
    disc of radius f theta, and the disc's inside even to 1 % (no sampling noise)."""
    radiance, radius_m, distance_m = 50.0, 0.25, 10.0
    result = rendering.render_grid(sphere_scene((0.0, 0.0, -distance_m), radius_m, radiance), paths=[(5, 0)], grid_error=1e-9)
    core = luminance(result.layers["core"])
    height, width = core.shape
    rows, columns = np.indices(core.shape)
    pitch = result.statistics["pixel_pitch_mm"]
    focal = jf.load_lens("zeiss_biotar").focal_length()
    radius_px = focal * radius_m / distance_m / pitch
    r = np.hypot(columns + 0.5 - width / 2, rows + 0.5 - height / 2)
    expected = radiance * transmission_luminance(jf.load_lens("zeiss_biotar"), None)
    central = core[r < 0.7 * radius_px]
    assert central.size > 100
    assert np.mean(central) == pytest.approx(expected, rel=0.02)
    assert np.std(central) < 0.01 * np.mean(central)
    assert core.sum() * pitch**2 == pytest.approx(expected * math.pi * (focal * radius_m / distance_m) ** 2, rel=0.02)
    # nothing beyond the rim: not even the FFT's rounding (1e-7 of the peak along its row and column)
    assert np.all(core[r > radius_px + 2.0] == 0.0)


@pytest.fixture(scope="module")
def off_axis_sphere():
    """A sphere light off axis, two strong ghosts: drawn by convolution, by sampling the disc, and
    with Monte Carlo (two seeds of 2^21 samples, uniform sampling)."""
    scene = sphere_scene((0.9, 0.5, -10.0), radius_m=0.12, core=False)
    paths = [(7, 4), (9, 7)]
    convolved = rendering.render_grid(scene, paths=paths, grid_error=1e-9)
    sampled = rendering.render_grid(scene, paths=paths, grid_error=1e-9, grid_options={"blur": False})
    uniform = dataclasses.replace(scene, render=dataclasses.replace(scene.render, sampling="uniform"))
    monte_carlo = [jf.render(uniform, seed=seed, samples=2**21, paths=paths, estimator="monte-carlo") for seed in range(2)]
    return convolved, sampled, monte_carlo


def test_convolved_disc_carries_the_sampled_disc_energy_per_path(off_axis_sphere):
    convolved, sampled, _ = off_axis_sphere
    assert convolved.statistics.paths[0].energy > 0
    for a, b in zip(convolved.statistics.paths, sampled.statistics.paths):
        assert a.energy == pytest.approx(b.energy, rel=0.01), (a.path, a.energy, b.energy)
    assert luminance(convolved.image).sum() == pytest.approx(luminance(sampled.image).sum(), rel=0.01)


def test_convolved_disc_is_closer_to_monte_carlo_than_the_sampled_disc(off_axis_sphere):
    """Pixel by pixel the convolved image is far closer to Monte Carlo than the sampled disc (whose
    noise dominates: measured 7 % against 26 % relative RMSE); smoothed, both agree with Monte Carlo
    to a few per cent (the convolution's one mean move per path is a first-order model: measured
    3.6 % after eight smoothing passes, where the sampled disc is at 3.5 %)."""
    convolved, sampled, monte_carlo = off_axis_sphere
    a, b = luminance(convolved.image), luminance(sampled.image)
    reference = np.mean([luminance(r.image) for r in monte_carlo], axis=0)

    def error(image, passes=0):
        smooth = (lambda x: blur(x, passes=passes)) if passes else (lambda x: x)
        return np.linalg.norm(smooth(image) - smooth(reference)) / np.linalg.norm(smooth(reference))

    assert error(a) < 0.5 * error(b)
    assert error(a, passes=8) < 0.06
