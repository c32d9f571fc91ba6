"""Fitting flares to plates: recover coating colours, front-lens dirt and light gains from a
reference flare image, or several plates of one lens, with optimistix, through jaxflare's
deterministic grid estimator (or its Monte Carlo renderer).

    fitted = fitting.fit(scene, fitting.load_plate("plate.exr", expected_size=scene.camera.resolution))
    fitting.save_fit(fitted, "fitted.json")
    jaxflare.render(fitting.apply_fit(scene, "fitted.json"))
"""

from ._fit import (
    DEFAULT_SOLVER,
    DIRT_MAX,
    DIRT_PRIOR,
    DIRT_PRIOR_WEIGHTS,
    MODELS,
    OBSERVABLE_STD,
    PARAMETERS,
    SOLVERS,
    TINT_PRIOR_WEIGHTS,
    FitResult,
    FlareParameters,
    apply_fit,
    block_resolution_plate,
    fit,
    save_fit,
)
from ._forward import FixedSamples, PathImages, fixed_samples, flare_render, path_image_model, path_images, render_image
from ._plate import Plate, PlateQuantisationWarning, load_plate, save_plate

__all__ = [
    "DEFAULT_SOLVER",
    "DIRT_MAX",
    "DIRT_PRIOR",
    "DIRT_PRIOR_WEIGHTS",
    "MODELS",
    "OBSERVABLE_STD",
    "PARAMETERS",
    "SOLVERS",
    "TINT_PRIOR_WEIGHTS",
    "FitResult",
    "FixedSamples",
    "FlareParameters",
    "PathImages",
    "Plate",
    "PlateQuantisationWarning",
    "apply_fit",
    "block_resolution_plate",
    "fit",
    "fixed_samples",
    "flare_render",
    "load_plate",
    "path_image_model",
    "path_images",
    "render_image",
    "save_fit",
    "save_plate",
]
