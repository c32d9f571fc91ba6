"""Fitting flares to plates: recover coating colours, front-lens dirt and light gains from a
reference flare image with optimistix, through jaxflare's differentiable renderer.

    fitted = fitting.fit(scene, fitting.load_plate("plate.exr", expected_size=scene.camera.resolution))
    fitting.save_fit(fitted, "fitted.json")
    jaxflare.render(fitting.apply_fit(scene, "fitted.json"))
"""

from ._fit import DEFAULT_SOLVER, DIRT_PRIOR, PARAMETERS, SOLVERS, FitResult, FlareParameters, apply_fit, fit, save_fit
from ._forward import FixedSamples, fixed_samples, render_image
from ._plate import Plate, PlateQuantisationWarning, load_plate, save_plate

__all__ = [
    "DEFAULT_SOLVER",
    "DIRT_PRIOR",
    "PARAMETERS",
    "SOLVERS",
    "FitResult",
    "FixedSamples",
    "FlareParameters",
    "Plate",
    "PlateQuantisationWarning",
    "apply_fit",
    "fit",
    "fixed_samples",
    "load_plate",
    "render_image",
    "save_fit",
    "save_plate",
]
