"""Coating presets and custom stacks (jaxflare.optics._coatings), and Lens.at_focal_length.

Reflectances are checked with the characteristic-matrix code (jaxflare.optics._thin_film) at normal
incidence on the glass of a real surface of the Biotar, with the layer order the tracer uses: a
ray travelling forward meets the stored order, a backward ray the reversed one.

Zeiss Biotar surfaces (media: air, glass, air, glass, glass, air, air, glass, glass, air, glass, air):
0 air->glass, 1 glass->air (the same singlet as 0), 2 air->glass, 3 cemented, 4 glass->air,
5 stop (air on both sides), 6 air->glass, 7 cemented, 8 glass->air, 9 air->glass, 10 glass->air.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxflare
from jaxflare.optics import COATING_PRESETS, with_coating, with_coating_layers
from jaxflare.optics import coated_reflectance

BAND_NM = np.linspace(450.0, 650.0, 41)
WIDE_NM = np.linspace(400.0, 700.0, 61)
GHOST = (1, 0)  # reflect at interface 1 (surface 1, glass->air), then interface 0 (surface 0)


def reflectance_from_air(lens: jaxflare.Lens, surface: int, wavelengths_nm) -> np.ndarray:
    """On-axis reflectance of a glass-air surface for light arriving from its air side, with the
    stored layers in the order the tracer uses for that travel direction."""
    wavelengths_nm = np.atleast_1d(np.asarray(wavelengths_nm, np.float64))
    air = np.asarray(lens.medium_is_air)
    layers_n = np.asarray(lens.coating_indices[surface])
    layers_d = np.asarray(lens.coating_thicknesses_nm[surface])
    forward = bool(air[surface])  # air in front: a forward ray comes from the air side
    if not forward:
        layers_n, layers_d = layers_n[::-1], layers_d[::-1]
    glass_medium = surface + 1 if forward else surface
    n_glass = np.array([lens.refractive_indices(w)[glass_medium] for w in wavelengths_nm])
    return np.asarray(coated_reflectance(1.0, n_glass, 1.0, wavelengths_nm, layers_n, layers_d))


# ------------------------------------------------------------------ single-surface physics


def test_uncoated_surface_is_bare_fresnel(biotar):
    lens = with_coating(biotar, "uncoated")
    n = biotar.refractive_indices(550.0)[1]
    assert float(reflectance_from_air(lens, 0, 550.0)[0]) == pytest.approx(((n - 1) / (n + 1)) ** 2, rel=1e-12)
    assert np.all(np.asarray(lens.coating_thicknesses_nm) == 0.0)


def test_mgf2_is_lower_with_minimum_near_550nm(biotar):
    bare = reflectance_from_air(with_coating(biotar, "uncoated"), 0, WIDE_NM)
    mgf2 = reflectance_from_air(with_coating(biotar, "mgf2"), 0, WIDE_NM)
    assert np.all(mgf2 < bare)
    assert float(reflectance_from_air(with_coating(biotar, "mgf2"), 0, 550.0)[0]) < 0.25 * float(bare[0])
    assert abs(WIDE_NM[np.argmin(mgf2)] - 550.0) <= 10.0


def test_multilayer_is_broadband_below_half_a_percent(biotar):
    multilayer = reflectance_from_air(with_coating(biotar, "multilayer"), 0, BAND_NM)
    mgf2 = reflectance_from_air(with_coating(biotar, "mgf2"), 0, BAND_NM)
    assert np.mean(multilayer < 0.005) >= 0.9
    assert np.max(multilayer) < 0.006
    assert np.mean(multilayer) < 0.5 * np.mean(mgf2)
    # every glass-air surface of the lens, front and back, and on each glass
    coated = with_coating(biotar, "multilayer")
    air = np.asarray(biotar.medium_is_air)
    for surface in (s for s in range(biotar.num_surfaces) if air[s] != air[s + 1]):
        assert np.mean(reflectance_from_air(coated, surface, BAND_NM) < 0.005) >= 0.9, surface


def test_amber_reflects_red_and_blue_reflects_blue(biotar):
    def red_over_blue(preset):
        r450, r650 = reflectance_from_air(with_coating(biotar, preset), 0, [450.0, 650.0])
        return r650 / r450

    assert red_over_blue("amber") > 1.5  # warm residual reflection
    assert red_over_blue("blue") < 1 / 1.5  # blue-purple residual reflection
    assert 0.5 < red_over_blue("multilayer") < 2.0  # roughly neutral


def test_ghost_fresnel_factor_drops_tenfold_with_multilayer(biotar):
    wavelengths = jnp.asarray([450.0, 550.0, 650.0])
    coated = with_coating(biotar, "multilayer")  # all three share the (S, 3) arrays: one compilation
    for path in (GHOST, (9, 2)):
        bare = np.asarray(jaxflare.path_fresnel_factor(with_coating(coated, "uncoated"), path, wavelengths))
        mgf2 = np.asarray(jaxflare.path_fresnel_factor(with_coating(coated, "mgf2"), path, wavelengths))
        multilayer = np.asarray(jaxflare.path_fresnel_factor(coated, path, wavelengths))
        assert np.all(multilayer * 10 < bare), path
        assert np.all(multilayer < mgf2), path


# ------------------------------------------------------------------ layer order and arrays


def test_glass_to_air_surface_stores_the_stack_reversed(biotar):
    stack = [(1.38, 100.0), (2.10, 60.0), (1.70, 80.0)]  # from the air side inwards
    lens = with_coating_layers(biotar, [0, 1], stack)
    front_n, front_d = np.asarray(lens.coating_indices[0]), np.asarray(lens.coating_thicknesses_nm[0])
    back_n, back_d = np.asarray(lens.coating_indices[1]), np.asarray(lens.coating_thicknesses_nm[1])
    np.testing.assert_array_equal(front_n, [1.38, 2.10, 1.70])  # air->glass: forward order = from air
    np.testing.assert_array_equal(front_d, [100.0, 60.0, 80.0])
    np.testing.assert_array_equal(back_n, front_n[::-1])  # glass->air: reversed
    np.testing.assert_array_equal(back_d, front_d[::-1])
    # The presets too: surfaces 0 and 1 bound the same glass, so the matched stacks mirror each other.
    preset = with_coating(biotar, "multilayer")
    np.testing.assert_array_equal(np.asarray(preset.coating_indices[1]), np.asarray(preset.coating_indices[0])[::-1])
    assert float(preset.coating_indices[0, 0]) == 1.38 and float(preset.coating_indices[1, -1]) == 1.38


def test_front_and_back_surface_reflect_alike_from_the_air_side(biotar):
    stack = [(1.38, 100.0), (2.10, 60.0), (1.70, 80.0)]
    for lens in (with_coating_layers(biotar, [0, 1], stack), with_coating(biotar, "multilayer")):
        front = reflectance_from_air(lens, 0, BAND_NM)  # forward ray, stored order
        back = reflectance_from_air(lens, 1, BAND_NM)  # backward ray, reversed order
        np.testing.assert_allclose(back, front, rtol=1e-12, atol=1e-15)
    # the order matters: without the reversal the back surface would reflect differently
    lens = with_coating_layers(biotar, [0, 1], stack)
    n_glass = np.array([biotar.refractive_indices(w)[1] for w in BAND_NM])
    wrong = np.asarray(coated_reflectance(1.0, n_glass, 1.0, BAND_NM, lens.coating_indices[1], lens.coating_thicknesses_nm[1]))
    assert np.max(np.abs(wrong - reflectance_from_air(lens, 0, BAND_NM))) > 1e-3


def test_cemented_and_stop_surfaces(biotar):
    lens = with_coating(biotar, "multilayer")
    assert lens.coating_thicknesses_nm.shape == (biotar.num_surfaces, 3)
    assert lens.coating_indices.dtype == biotar.coating_indices.dtype
    assert lens.coating_thicknesses_nm.dtype == biotar.coating_thicknesses_nm.dtype
    for untouched in (3, 5, 7):  # cemented, stop, cemented
        assert np.all(np.asarray(lens.coating_thicknesses_nm[untouched]) == 0.0)
    explicit = with_coating(biotar, "mgf2", surfaces=[3])
    assert float(explicit.coating_thicknesses_nm[3, 0]) == pytest.approx(550.0 / (4 * 1.38))
    np.testing.assert_array_equal(np.asarray(explicit.coating_thicknesses_nm[0]), np.asarray(biotar.coating_thicknesses_nm[0]))
    with pytest.raises(ValueError, match="surface 5 .* stop or dummy"):
        with_coating(biotar, "mgf2", surfaces=[5])
    with pytest.raises(ValueError, match="surfaces 0 to 10"):
        with_coating(biotar, "mgf2", surfaces=[11])
    with pytest.raises(ValueError, match="surfaces 0 to 10"):
        with_coating_layers(biotar, [-1], [(1.38, 100.0)])
    with pytest.raises(ValueError) as error:
        with_coating(biotar, "gold")
    for name in COATING_PRESETS:
        assert repr(name) in str(error.value) or name in str(error.value)


def test_custom_layers_are_validated(biotar):
    with pytest.raises(ValueError, match="index"):
        with_coating_layers(biotar, [0], [(0.9, 100.0)])
    with pytest.raises(ValueError, match="thickness"):
        with_coating_layers(biotar, [0], [(1.38, -1.0)])
    with pytest.raises(ValueError, match="thickness"):
        with_coating_layers(biotar, [0], [(1.38, float("nan"))])
    bare = with_coating_layers(biotar, [0], [])
    assert np.all(np.asarray(bare.coating_thicknesses_nm[0]) == 0.0)


def test_padding_is_an_identity_and_lens_preset_restores(biotar):
    padded = with_coating(with_coating(biotar, "multilayer"), "mgf2")  # L = 3, two zero layers
    assert padded.coating_thicknesses_nm.shape[1] == 3
    wavelengths = jnp.asarray([450.0, 550.0, 650.0])
    np.testing.assert_allclose(
        np.asarray(jaxflare.path_fresnel_factor(padded, GHOST, wavelengths)),
        np.asarray(jaxflare.path_fresnel_factor(biotar, GHOST, wavelengths)),
        rtol=1e-12,
    )
    assert with_coating(biotar, "lens") is biotar
    restored = with_coating(with_coating(biotar, "uncoated"), "lens")
    np.testing.assert_array_equal(np.asarray(restored.coating_thicknesses_nm), np.asarray(biotar.coating_thicknesses_nm))
    np.testing.assert_array_equal(np.asarray(restored.coating_indices), np.asarray(biotar.coating_indices))


def test_fresnel_factor_is_differentiable_in_the_coating(biotar):
    lens = with_coating(biotar, "multilayer")

    def factor(thicknesses):
        return jaxflare.path_fresnel_factor(eqx.tree_at(lambda l: l.coating_thicknesses_nm, lens, thicknesses), GHOST, 480.0)

    grad = np.asarray(jax.grad(factor)(lens.coating_thicknesses_nm))
    assert np.all(np.isfinite(grad))
    assert np.any(grad[0] != 0.0) and np.any(grad[1] != 0.0)  # the two reflecting surfaces

    def factor_of_layer(thickness_nm):  # also through with_coating_layers itself (same array shapes)
        coated = with_coating_layers(lens, [0, 1], [(1.38, thickness_nm)])
        return jaxflare.path_fresnel_factor(coated, GHOST, 480.0)

    slope = float(jax.grad(factor_of_layer)(jnp.asarray(99.6)))
    step = 1e-3
    numeric = (float(factor_of_layer(99.6 + step)) - float(factor_of_layer(99.6 - step))) / (2 * step)
    assert slope != 0.0 and slope == pytest.approx(numeric, rel=1e-5)


# ------------------------------------------------------------------ Lens.at_focal_length


@pytest.fixture(scope="module")
def zoom() -> jaxflare.Lens:
    return jaxflare.load_lens("nikon_afs_28_70_zoom")


def test_at_focal_length_hits_the_requested_efl(zoom):
    efls = [zoom.at_zoom(k).focal_length() for k in range(zoom.num_zoom_positions)]
    for target in (efls[0], 28.9, 35.0, 50.0, 60.0, 70.0, efls[-1]):
        lens = zoom.at_focal_length(target)
        assert lens.focal_length() == pytest.approx(target, rel=1e-6)
        assert lens.widest_f_number == pytest.approx(zoom.prescription.stated_f_number, rel=1e-6)
        # the sensor stays at the paraxial focus between zoom positions
        assert float(lens.sensor_z_mm) == pytest.approx(lens.sensor_z_for_focus(), abs=5e-3)
        assert lens.aperture_blades == zoom.aperture_blades
        assert lens.num_zoom_positions == zoom.num_zoom_positions


def test_at_focal_length_at_a_zoom_position_is_at_zoom(zoom):
    for k in range(zoom.num_zoom_positions):
        reference = zoom.at_zoom(k)
        lens = zoom.at_focal_length(reference.focal_length())
        assert lens.zoom_position == k
        np.testing.assert_allclose(np.asarray(lens.thickness_mm), np.asarray(reference.thickness_mm), rtol=0, atol=1e-9)
        assert float(lens.sensor_z_mm) == pytest.approx(float(reference.sensor_z_mm), abs=1e-9)
        assert float(lens.stop_radius_mm) == pytest.approx(float(reference.stop_radius_mm), abs=1e-9)


def test_at_focal_length_interpolates_between_positions(zoom):
    a, b = zoom.at_zoom(0), zoom.at_zoom(1)
    lens = zoom.at_focal_length(40.0)
    inner = slice(0, zoom.num_surfaces - 1)  # every gap but the last (refocused) one
    low = np.minimum(np.asarray(a.thickness_mm), np.asarray(b.thickness_mm))[inner]
    high = np.maximum(np.asarray(a.thickness_mm), np.asarray(b.thickness_mm))[inner]
    assert np.all((low <= np.asarray(lens.thickness_mm)[inner]) & (np.asarray(lens.thickness_mm)[inner] <= high))
    kept = zoom.with_aperture(blades=7, rotation_deg=10.0).at_focal_length(40.0)
    assert kept.aperture_blades == 7 and float(kept.aperture_rotation_rad) == pytest.approx(np.radians(10.0))


def test_at_focal_length_errors(zoom, biotar):
    with pytest.raises(ValueError, match=r"24 mm is outside the zoom range of 'Nikon.*': 28\.9 mm to 70 mm"):
        zoom.at_focal_length(24.0)
    with pytest.raises(ValueError, match="outside the zoom range"):
        zoom.at_focal_length(85.0)
    efl = biotar.focal_length()
    assert biotar.at_focal_length(efl * 1.009) is biotar
    assert biotar.at_focal_length(100.0) is biotar
    with pytest.raises(ValueError, match=r"99\.91 mm.*prime lens cannot change focal length"):
        biotar.at_focal_length(efl * 1.02)
