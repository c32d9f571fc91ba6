"""Colours outside the output gamut: one rule for both estimators (jaxflare.rendering._gamut).

A pixel with a negative channel is desaturated towards the grey of its own luminance until its
lowest channel is zero; luminance and hue (the direction away from grey) are kept."""

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from jaxflare.colour import spectral_table, spectrum_response_at
from jaxflare.rendering import clip_to_gamut

WEIGHTS = np.asarray(spectral_table("ACEScg").luminance_weights, np.float64)

rgb_values = st.lists(st.floats(-2.0, 5.0, allow_nan=False), min_size=3, max_size=3)


@settings(max_examples=200, deadline=None)
@given(rgb_values)
@example([0.0, 6.812523360763264e-193, -3.761390846082325e-195])  # found in a CI run: hue check underflowed
def test_mapping_keeps_luminance_and_hue_and_leaves_no_negative_channel(rgb):
    rgb = np.asarray(rgb)
    mapped = clip_to_gamut(rgb, WEIGHTS)
    luminance = rgb @ WEIGHTS
    assert mapped.min() >= 0.0
    if rgb.min() >= 0:
        np.testing.assert_array_equal(mapped, rgb)  # inside the gamut: unchanged
    elif luminance <= 0:
        np.testing.assert_array_equal(mapped, 0.0)  # no light to keep
    else:
        np.testing.assert_allclose(mapped @ WEIGHTS, luminance, rtol=1e-9, atol=1e-12)
        assert np.isclose(mapped.min(), 0.0, atol=1e-12)  # just enough desaturation
        # the same hue: mapped - grey is a non-negative multiple (< 1) of rgb - grey
        # (in units of the largest departure from grey: squares of colours near 1e-190 underflow)
        unit = np.abs(rgb - luminance).max()
        away, mapped_away = (rgb - luminance) / unit, (mapped - luminance) / unit
        scale = (mapped_away @ away) / (away @ away)
        assert 0.0 <= scale <= 1.0
        np.testing.assert_allclose(mapped_away, scale * away, atol=1e-9)


def test_a_spectral_line_outside_the_gamut_becomes_the_most_saturated_colour_of_its_hue():
    # 500 nm in ACEScg has a negative red channel; mapped, it is on the gamut's red = 0 face
    table = spectral_table("ACEScg")
    line = np.asarray(spectrum_response_at(table, np.asarray([500.0]))[0], np.float64)
    assert line.min() < 0
    mapped = clip_to_gamut(line, WEIGHTS)
    assert mapped.min() == 0.0 and np.argmin(mapped) == np.argmin(line)
    np.testing.assert_allclose(mapped @ WEIGHTS, line @ WEIGHTS, rtol=1e-9)
