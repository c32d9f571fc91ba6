"""The grid image converges as its grid is refined (measured error ratio against a finer grid);
an on-axis light through a round iris gives a rotationally symmetric grid flare and a B-blade iris
a B-fold one; lights that send rays past the lens or outside the frame give finite images."""

import numpy as np
import pytest

from .grid_cases import grid, luminance

FINE = (("min_cells", 64), ("max_cells", 64), ("spacing_px", 0.2), ("edge_side", 8))


def cells(n):
    return (("min_cells", n), ("max_cells", n), ("spacing_px", 0.2), ("edge_side", 8))


def test_grid_image_converges_as_the_grid_doubles():
    """Relative L2 error of the (7, 4) + (9, 7) image against a 64-cell grid, at 8, 16 and 32
    cells per side (the sub-sample spacing held fine, so the cells' bilinear maps are what
    changes): each doubling at least halves the error."""
    reference = luminance(grid(options=FINE).image)
    errors = [np.linalg.norm(luminance(grid(options=cells(n)).image) - reference) / np.linalg.norm(reference) for n in (8, 16, 32)]
    assert errors[0] > 2 * errors[1] > 4 * errors[2] > 0, errors


CENTRED = (("interleave", False),)


def symmetric_scene_image(blades, paths=((4, 2), (7, 4)), options=CENTRED):
    return luminance(grid(direction=(0.0, 0.0, -1.0), paths=paths, blades=blades, f_number=8.0, square=True, options=options).image)


def test_on_axis_round_iris_grid_flare_is_rotationally_symmetric():
    """With every sub-sample lattice centred in its cells, the grid of a symmetric scene is
    symmetric, and so is its image: to float rounding (measured about 1e-6)."""
    image = symmetric_scene_image(0)
    norm = np.linalg.norm(image)
    assert norm > 0
    for turned in (np.rot90(image), image[::-1], image[:, ::-1], image.T):
        assert np.linalg.norm(image - turned) < 1e-5 * norm


def angular_harmonics(image, orders):
    height, width = image.shape
    rows, columns = np.indices(image.shape)
    dx, dy = columns + 0.5 - width / 2, rows + 0.5 - height / 2
    phi = np.arctan2(dy, dx)
    weight = image * (dx * dx + dy * dy)
    return {m: abs(np.sum(weight * np.exp(1j * m * phi))) / np.sum(weight) for m in orders}


@pytest.mark.parametrize("blades", [5, 6])
def test_iris_blades_give_their_angular_harmonic(blades):
    shaped = angular_harmonics(symmetric_scene_image(blades, paths=((4, 2),)), range(2, 9))
    round_ = angular_harmonics(symmetric_scene_image(0, paths=((4, 2),)), range(2, 9))
    assert max(shaped, key=shaped.get) == blades, shaped
    assert shaped[blades] > 50 * round_[blades], (shaped, round_)


@pytest.mark.parametrize("direction", [(0.62, 0.0, -1.0), (0.3, 0.2, -1.0), (0.0, 0.0, -1.0)])
def test_no_nan_where_rays_clip_or_miss(direction):
    """Far off axis (32 degrees: most rays miss the lens or leave the frame), near the frame's
    corner and on the axis: every layer finite, no pixel below -1e-6 of its layer's peak."""
    result = grid(direction=direction, paths=((7, 4), (9, 7)))
    for name, layer in result.layers.items():
        assert np.all(np.isfinite(layer)), name
        assert layer.min() >= -1e-6 * max(layer.max(), 0.0), name
    assert np.all(np.isfinite(result.image))
