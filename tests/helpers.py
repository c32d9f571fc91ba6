"""Helpers shared by the tests: where things are, building a lens from TOML text, and the small
scene the grid-model fitting tests share."""

import dataclasses
from pathlib import Path

import jaxflare

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent
DATA = TESTS / "data"


def lens_from_toml(text: str, filename: str = "test.toml") -> jaxflare.Lens:
    return jaxflare.build_lens(jaxflare.parse_lens_toml(text, filename))


BIOTAR_TWO_LIGHTS = jaxflare.Scene(
    camera=jaxflare.Camera(lens="zeiss_biotar", f_number=4.0, resolution=(64, 48), look_at_m=(0.0, 0.0, -10.0)),
    lights=(
        jaxflare.Light(kind="directional", direction=(0.06, 0.03, -1.0)),
        jaxflare.Light(kind="directional", direction=(-0.04, 0.02, -1.0), rgb=(1.0, 0.8, 0.6)),
    ),
)
"""A Zeiss Biotar at f/4, 64 x 48 pixels, two distant lights (one warm): small enough to model fast."""


def with_tints(scene, tints):
    """``scene`` with interface ``k``'s coating tint ``tints[k]`` (RGB) for every row of ``tints``."""
    camera = dataclasses.replace(scene.camera, coating_tints=tuple((k, tuple(map(float, rgb))) for k, rgb in enumerate(tints)))
    return dataclasses.replace(scene, camera=camera)


def flare_only(scene):
    """The scene rendered as a fit models it: no core, no culling."""
    return dataclasses.replace(scene, render=dataclasses.replace(scene.render, core=False, cull_threshold=0.0))
