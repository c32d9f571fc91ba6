"""Radiometry of the lights the renderer samples, against closed forms.

Pixels hold camera-equation radiance (``E = pi L T / 4 N^2`` solved for L), so an extended light of
radiance L images to pixels of value L T, and the sum of a light's image times the pixel area is the
flux through the entrance pupil times ``4 N^2 / pi``. For a light of solid angle ``omega`` seen at
the axis that sum is ``L T f^2 omega_projected`` (``omega_projected`` = ``pi sin^2 theta`` for a
cone of half angle theta, ``A cos(alpha) / d^2`` for a small disk of area A tilted by alpha); for a
parallel beam of irradiance E it is ``E T f^2``. T is the lens's on-axis transmission for white light.
"""

import math

import numpy as np
import pytest

import jaxflare as jf
from jaxflare.colour import rgb_response_at, spectral_table

F_NUMBER = 8.0
PATHS = [(5, 0)]  # a ghost must be rendered; the core is what is measured


def scene(light):
    camera = jf.Camera(lens="zeiss_biotar", f_number=F_NUMBER, resolution=(96, 96), look_at_m=(0.0, 0.0, -10.0))
    return jf.Scene(camera=camera, lights=(light,))


def luminance(image):
    return image[..., :3] @ np.asarray(spectral_table("ACEScg").luminance_weights)


def transmission(lens):
    """Luminance-weighted on-axis transmission of the primary path for white light (ACEScg)."""
    table = spectral_table("ACEScg")
    grid = np.asarray(table.wavelength_nm)
    factor = np.asarray(jf.path_fresnel_factor(lens, None, grid))
    weight = (np.asarray(rgb_response_at(table, grid)) @ np.ones(3)) @ np.asarray(table.luminance_weights)
    return float(np.sum(factor * weight) / np.sum(weight))


@pytest.fixture(scope="module")
def lens():
    return jf.load_lens("zeiss_biotar").with_f_number(F_NUMBER)


def core_energy(result):
    """Sum of the core's luminance times the pixel area (mm^2)."""
    pitch = result.statistics["pixel_pitch_mm"]
    return float(luminance(result.layers["core"]).sum() * pitch**2)


def test_a_disk_facing_the_camera_sends_its_radiance_through_its_solid_angle(lens):
    radiance, radius_m, distance_m = 40.0, 0.2, 10.0
    light = jf.Light(kind="disk", position_m=(0.0, 0.0, -distance_m), radius_m=radius_m, intensity=radiance, rgb=(1.0, 1.0, 1.0))
    result = jf.render(scene(light), samples=2**19, method="exact", paths=PATHS, seed=5)
    z_pupil_m = lens.entrance_pupil()[0] / 1000.0  # the solid angle is seen from the entrance pupil
    expected = radiance * transmission(lens) * lens.focal_length() ** 2 * math.pi * radius_m**2 / (distance_m + z_pupil_m) ** 2
    assert core_energy(result) == pytest.approx(expected, rel=0.03)


def test_a_tilted_disk_is_foreshortened_by_the_cosine_of_its_tilt():
    """Tilted by 60 degrees away from the camera, a one-sided disk shows half its area (cos 60);
    turned away from the camera it sends nothing."""
    def light(normal):
        return jf.Light(kind="disk", position_m=(0.0, 0.0, -10.0), radius_m=0.2, intensity=40.0, rgb=(1.0, 1.0, 1.0), normal=normal)

    facing = core_energy(jf.render(scene(light((0.0, 0.0, 1.0))), samples=2**19, method="exact", paths=PATHS, seed=6))
    tilted = core_energy(jf.render(scene(light((math.sin(math.radians(60)), 0.0, 0.5))), samples=2**19, method="exact", paths=PATHS, seed=7))
    away = jf.render(scene(light((0.0, 0.0, -1.0))), samples=2**15, method="exact", paths=PATHS, seed=8)
    assert tilted / facing == pytest.approx(0.5, rel=0.04)
    assert away.layers["core"].sum() == 0 and away.image[..., :3].sum() == 0


def test_the_sun_disc_images_at_its_radiance_and_sends_l_pi_sin2_theta(lens):
    """A directional light with an angular radius (a sun's disc, here 2 degrees) of radiance L:
    flux L pi sin^2(theta) per unit pupil area, an image disc of radius f tan(theta) whose pixels
    are L T (the camera equation holds for the sun as for any extended source)."""
    radiance, theta_deg = 30.0, 2.0
    light = jf.Light(kind="directional", direction=(0.0, 0.0, -1.0), angular_radius_deg=theta_deg, intensity=radiance, rgb=(1.0, 1.0, 1.0))
    result = jf.render(scene(light), samples=2**19, method="exact", paths=PATHS, seed=9)
    focal, theta = lens.focal_length(), math.radians(theta_deg)
    expected = radiance * transmission(lens) * focal**2 * math.pi * math.sin(theta) ** 2
    assert core_energy(result) == pytest.approx(expected, rel=0.03)
    core = luminance(result.layers["core"])
    rows, columns = np.indices(core.shape)
    radius_px = focal * math.tan(theta) / result.statistics["pixel_pitch_mm"]
    central = (columns + 0.5 - 48) ** 2 + (rows + 0.5 - 48) ** 2 < (0.6 * radius_px) ** 2
    assert central.sum() > 50
    assert np.mean(core[central]) == pytest.approx(radiance * transmission(lens), rel=0.06)
    outside = (columns + 0.5 - 48) ** 2 + (rows + 0.5 - 48) ** 2 > (1.3 * radius_px) ** 2
    assert core[outside].sum() < 1e-3 * core.sum()


def test_a_parallel_beam_sends_its_irradiance_through_the_entrance_pupil(lens):
    """A beam of irradiance E (angular radius 0) puts E T A_pupil through the lens: with
    4 N^2 / pi A_pupil = f^2 the core sums to E T f^2."""
    irradiance = 3.0
    light = jf.Light(kind="directional", direction=(0.0, 0.0, -1.0), intensity=irradiance, rgb=(1.0, 1.0, 1.0))
    result = jf.render(scene(light), samples=2**18, method="exact", paths=PATHS, seed=10)
    expected = irradiance * transmission(lens) * lens.focal_length() ** 2
    assert core_energy(result) == pytest.approx(expected, rel=0.02)
    assert light.intensity_unit == "irradiance at the lens, W/m^2"
