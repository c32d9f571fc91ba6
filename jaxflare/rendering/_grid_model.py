"""The grid estimator as a differentiable model of a scene's flare: coating tints, the dirt map and
light gains in, image out, with the grid itself (cells, sub-samples) fixed.

A plate fit changes only what scales each grid sub-sample's value (equation (2) of Pekkarinen &
Balzer 2019): the path's coating tint, the front-lens dirt transmission where the sub-sample
enters, and its light's colour. The grid's geometry -- which cells are drawn, how finely, where
their sub-samples land -- does not depend on them, so it is planned and traced once
(:func:`grid_flare_model`) and the model re-splats the fixed records for any parameters
(:meth:`GridFlareModel.image`). Unlike a Monte Carlo model it has no noise, so a least-squares fit
through it is not biased towards dimmer tints, and its gradients are exact derivatives of a smooth
function. With the dirt map fixed the flare is linear in the path tints and in the lights' RGB
gains, so :meth:`GridFlareModel.path_images` gives one image per path and gain basis once, and a
fit of coatings and lights needs only their weighted sums.

Light gains scale a light's RGB colour per channel (a spectral light's brightness by their mean),
as :func:`scaled_lights` does for the Monte Carlo records: the job colours are linear in that gain,
so the model keeps one colour table per light and input channel and sums them.

Thin-film coatings enter through each path's on-axis coated Fresnel factor (P, L), which scales
its jobs' colours per wavelength under the Schlick model: :meth:`GridFlareModel.path_fresnel`
computes it for other coating stacks (the characteristic-matrix model), and ``image(...,
path_fresnel=)`` recolours the jobs with it, so a fit of layer thicknesses and indices is exact
to the grid estimator (not an RGB approximation of the spectrum). The flare is linear in the
Fresnel factors, so :meth:`GridFlareModel.path_knot_images` makes one image per spectral knot (a
hat function of wavelength) and a fit takes weighted sums of those images instead of re-splatting;
coating spectra are smooth, so knots :data:`KNOT_STEP_NM` apart suffice (measured in
tests/fitting/test_thin_film.py against the re-splat).

Colour planes: the gain bases and the spectral knots change only the job colours, not where a
sub-sample lands, so their images are channels of one splat (job colours of 3 x planes channels):
every sub-sample's geometry, clipping and dirt lookup is computed once for all of them. Measured on
the two-light Biotar at 64 x 48 with the fit's fine grid (2-core Xeon VM, warm): the six per-light
colour images 5.8 s as six splats, 1.8 s as one; the 41 knot images of a preview grid 1.8-2.0 s
one knot per pass, 0.6-0.8 s with 8 or more per pass.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..optics import EventTable, on_axis_fresnel
from ..scenes import Scene, load_scene
from ._grid import SPLAT_GROUP_SUBSAMPLES, band_averaging, job_colours, job_table
from ._grid_plan import GridPlan, plan_grid, prepare_grid
from ._grid_splat import DirtCells, JobTable, RecordTable, compose_layers, empty_grid_accumulators, packed_shape, splat_subsamples
from ._lights import LightArrays
from ._quality import radiance_scale
from ._step import RenderSetup

__all__ = ["GridFlareModel", "grid_flare_model", "scaled_lights"]

KNOT_STEP_NM = 10.0
"""Spacing of the spectral knots of :meth:`GridFlareModel.path_knot_images`. Measured on a 64 x 48
Biotar with MgF2 coatings 0.85-1.2 times their design thickness: the knot sum differs from the
re-splat by 0.09-0.29 % RMSE at 10 nm, 0.6 % at 12.5 nm, 1.4 % at 20 nm, 2.3 % at 25 nm."""


def knot_hats(wavelength_nm: np.ndarray, step_nm: float = KNOT_STEP_NM) -> tuple[np.ndarray, np.ndarray]:
    """Knot indices into the spectral grid ``wavelength_nm`` (about ``step_nm`` apart, both ends
    included) and their hat functions on the grid (B, L): piecewise linear, a partition of unity,
    so a spectrum sampled at the knots is interpolated linearly between them."""
    count = wavelength_nm.shape[0]
    span = float(wavelength_nm[-1] - wavelength_nm[0])
    num = max(2, int(round(span / step_nm)) + 1)
    knots = np.unique(np.round(np.linspace(0, count - 1, num)).astype(int))
    hats = np.stack([np.interp(np.arange(count), knots, np.eye(knots.size)[b]) for b in range(knots.size)])
    return knots, hats


def scaled_lights(lights: LightArrays, gain: Float[Array, "NL 3"]) -> LightArrays:
    """Light arrays with each light's colour scaled by ``gain`` (NL, 3): RGB lights per channel,
    spectral lights (a spectrum or a temperature) by the mean of their three gains."""
    gain = jnp.asarray(gain).astype(lights.rgb.dtype)
    return eqx.tree_at(lambda l: (l.rgb, l.spectral_rgb), lights, (lights.rgb * gain, lights.spectral_rgb * jnp.mean(gain, axis=1)[:, None, None]))


def gain_basis(num_lights: int) -> np.ndarray:
    """The unit gains of light k's input channel c (index ``3 k + c``): (3 NL, NL, 3)."""
    basis = np.zeros((3 * num_lights, num_lights, 3))
    for k in range(num_lights):
        for c in range(3):
            basis[3 * k + c, k, c] = 1.0
    return basis


class GridFlareModel(eqx.Module):
    """A planned, traced grid render of a scene's flare paths (no core), re-splatted for any path
    tints, dirt map and light gains. Built by :func:`grid_flare_model`."""

    setup: RenderSetup
    table: RecordTable
    jobs: JobTable
    colour_bases: Float[Array, "K J M 3"]
    """Each job's sub-node colours for light gain basis ``K = 3 k + c`` (light k, input channel c
    at gain 1, every other gain 0); their sum is the colour at unit gains."""
    job_slot: Int[Array, " J"]
    """Each job's flare path (its layer in :meth:`path_images`)."""
    total: Int[Array, ""]
    first: Int[Array, " C"]
    chunks: Int[Array, ""]
    to_radiance: Float[Array, ""]
    """Splat units to pixel radiance (the camera equation), as the grid render applies."""
    events: EventTable
    """The flare paths' event columns (P, E), for :meth:`path_fresnel`."""
    base_fresnel: Float[Array, "P L"]
    """Each path's on-axis coated Fresnel factor with the scene's coatings (spectral grid)."""
    band_nm: Float[Array, " B"]
    band_averaging: Float[Array, "R B"]
    paths: tuple = eqx.field(static=True)
    """The flare paths (j, i), in the order of the path axes."""
    resolution: tuple[int, int] = eqx.field(static=True)
    num_lights: int = eqx.field(static=True)
    subsamples: int = eqx.field(static=True)
    quality: str = eqx.field(static=True)

    @property
    def num_paths(self) -> int:
        return len(self.paths)

    @property
    def layer_bytes(self) -> int:
        """Bytes of one layer of the splat's packed level images (float32 RGB)."""
        rows, columns = packed_shape(*self.resolution)
        return 4 * 3 * rows * columns

    @property
    def atlas_bytes(self) -> int:
        """Bytes of the blurred jobs' slots (:mod:`._grid_blur`; one copy per dirt cell of a run)."""
        return 0 if self.jobs.blur is None else 4 * 3 * self.jobs.blur.size

    def path_fresnel(self, coating_indices: Float[Array, "S L"], coating_thicknesses_nm: Float[Array, "S L"]) -> Float[Array, "P Lw"]:
        """Each flare path's on-axis coated Fresnel factor on the spectral grid for the lens with
        these coating arrays (as :attr:`jaxflare.Lens.coating_indices` and
        ``coating_thicknesses_nm``: layers in forward order, real indices, nm); differentiable."""
        lens = self.setup.lens
        dtype = lens.thickness_mm.dtype
        lens = eqx.tree_at(
            lambda l: (l.coating_indices, l.coating_thicknesses_nm), lens,
            (jnp.asarray(coating_indices).astype(dtype), jnp.asarray(coating_thicknesses_nm).astype(dtype)),
        )
        return on_axis_fresnel(lens, self.events, self.setup.spectral.wavelength_nm.astype(dtype))

    def _splat(self, path_tint, dirt, light_gain, per_path: bool, path_fresnel=None, dirt_cells: DirtCells | None = None, colour=None):
        """The splat's composed layers (Y, H, W, C): ``colour`` (J, M, C), when given, replaces
        the job colours that ``light_gain`` and ``path_fresnel`` make (C / 3 colour planes)."""
        setup = self.setup
        dtype = self.colour_bases.dtype
        gains = jnp.ones((self.num_lights, 3), dtype) if light_gain is None else jnp.asarray(light_gain).astype(dtype)
        if colour is not None:
            colour = jnp.asarray(colour).astype(dtype)
        elif path_fresnel is None:
            colour = jnp.einsum("k,kjmc->jmc", gains.reshape(-1), self.colour_bases)
        else:
            colour = self._fresnel_colours(jnp.asarray(path_fresnel), gains)
        jobs = dataclasses.replace(self.jobs, colour=colour, layer=self.job_slot if per_path else jnp.zeros_like(self.job_slot))
        if dirt_cells is not None:  # the one-hot maps of the run's cells stand for the dirt map
            effects = dataclasses.replace(setup.effects, dirt=None)
        else:
            effects = setup.effects if dirt is None else dataclasses.replace(setup.effects, dirt=jnp.asarray(dirt).astype(dtype))
        setup = dataclasses.replace(setup, path_tint=jnp.asarray(path_tint).astype(dtype), effects=effects)
        width, height = self.resolution
        layers = (self.num_paths if per_path else 1) * (1 if dirt_cells is None else dirt_cells.count)
        atlas = 1 if jobs.blur is None else jobs.blur.size * (1 if dirt_cells is None else dirt_cells.count)
        acc = empty_grid_accumulators(layers, self.num_paths, width, height, atlas, colour.shape[-1])
        acc = splat_subsamples(setup, jobs, self.table, acc, self.total, self.first, self.chunks, dirt_cells)
        return compose_layers(acc, jobs, width, height, 0 if dirt_cells is None else dirt_cells.count) * self.to_radiance

    def image(
        self, path_tint: Float[Array, "P 3"], dirt: Float[Array, "Hd Wd C"] | None = None, light_gain: Float[Array, "NL 3"] | None = None,
        path_fresnel: Float[Array, "P L"] | None = None,
    ):
        """The flare (every flare path summed, H x W x 3, pixel radiance) for these path tints
        (each path's coating colour, unit = the lens's own coatings), front-lens transmission map
        (None: the scene's own), light gains (None: 1) and paths' coated Fresnel factors (None: the
        scene's coatings; else from :meth:`path_fresnel`). Differentiable in all four; jit it."""
        if path_fresnel is not None and not self.setup.schlick:
            raise ValueError("path_fresnel needs the Schlick Fresnel model (render.fresnel = 'schlick'): with 'exact' the coatings act per traced vertex")
        return self._splat(path_tint, dirt, light_gain, per_path=False, path_fresnel=path_fresnel)[0]

    def per_path_image(self, dirt=None, light_gain=None, path_fresnel=None):
        """Each flare path's image (P, H, W, 3) at unit tint for this dirt map, light gains and
        Fresnel factors (None: the scene's); jitted, one compile per shape. The flare is linear in
        the dirt map (bilinear lookup), so images for one-hot maps are a basis of its dependence."""
        dtype = self.colour_bases.dtype
        gain = jnp.ones((self.num_lights, 3), dtype) if light_gain is None else jnp.asarray(light_gain, dtype)
        return _per_path_splat(self, path_fresnel, gain, None if dirt is None else jnp.asarray(dirt, dtype))

    def per_path_cell_images(self, dirt_shape: tuple[int, int], first: int, count: int, light_gain=None, *, per_light_colour: bool = False):
        """Each flare path's image (P, count, H, W, 3) at unit tint for the one-hot dirt maps
        (shape ``dirt_shape``: rows, columns; one channel) of cells ``first`` .. ``first + count
        - 1`` (row-major; cells past the map's last are black), in one pass over the sub-samples
        (each splatted with its four bilinear dirt weights); equal to :meth:`per_path_image` of
        each one-hot map. With ``per_light_colour`` (``light_gain`` then unused), one image per
        light-gain basis as in :meth:`path_images`, in the same pass: (P, count, K, H, W, 3).
        Jitted, one compile per map shape and ``count`` (``first`` is data)."""
        dtype = self.colour_bases.dtype
        gain = jnp.ones((self.num_lights, 3), dtype) if light_gain is None else jnp.asarray(light_gain, dtype)
        cells = DirtCells(shape=(int(dirt_shape[0]), int(dirt_shape[1])), first=jnp.asarray(first, jnp.int32), count=int(count))
        width, height = self.resolution
        if not per_light_colour:
            return _per_path_cells_splat(self, gain, cells, None).reshape(self.num_paths, cells.count, height, width, 3)
        planes = _per_path_cells_splat(self, gain, cells, self.gain_planes())  # (P count, H, W, 3 K)
        return jnp.moveaxis(planes.reshape(self.num_paths, cells.count, height, width, -1, 3), 4, 2)

    def knot_fresnels(self, step_nm: float = KNOT_STEP_NM):
        """The spectral knots (:func:`knot_hats`: indices into the spectral grid) and, per knot,
        every path's Fresnel factor replaced by the knot's hat function (P, L)."""
        knots, hats = knot_hats(np.asarray(self.setup.spectral.wavelength_nm), step_nm)
        dtype = self.colour_bases.dtype
        return knots, [jnp.broadcast_to(jnp.asarray(hat, dtype), self.base_fresnel.shape) for hat in hats]

    def path_knot_images(self, dirt=None, *, step_nm: float = KNOT_STEP_NM, per_light_colour: bool = False, knot_slice: slice = slice(None)):
        """Each flare path's image with its Fresnel factor replaced by the hat function of one
        spectral knot (:meth:`knot_fresnels`): (P, B, K, H, W, 3), ``K`` as in :meth:`path_images`,
        and the knots' indices into the spectral grid. The flare for Fresnel factors ``F`` (P, L)
        is close to ``sum_pb F[p, knot_b] sum_K g_K image_pbK`` (exact when ``F`` is linear
        between the knots). Every knot and gain basis is a colour plane of one pass over the
        sub-samples; ``knot_slice`` makes only some of the knots (a fit pools the knots' images in
        groups that fit in memory)."""
        knots, fresnels = self.knot_fresnels(step_nm)
        knots, fresnels = knots[knot_slice], fresnels[knot_slice]
        dtype = self.colour_bases.dtype
        gains = jnp.asarray(gain_basis(self.num_lights), dtype) if per_light_colour else jnp.ones((1, self.num_lights, 3), dtype)
        planes = _per_path_planes(self, jnp.stack(fresnels), gains, None if dirt is None else jnp.asarray(dirt, dtype))  # (P, H, W, 3 B K)
        paths, height, width, _ = planes.shape
        return jnp.moveaxis(planes.reshape(paths, height, width, len(fresnels), gains.shape[0], 3), (3, 4), (1, 2)), knots

    def fresnel_planes(self, path_fresnels: Float[Array, "B P L"], light_gains: Float[Array, "K NL 3"]) -> Float[Array, "J M C"]:
        """The job colours for each of ``B`` paths' Fresnel factors and ``K`` light gains (as
        ``image(..., light_gain=, path_fresnel=)`` makes them), as colour planes of one splat:
        (J, M, 3 B K), plane ``b K + k``."""
        planes = jax.vmap(lambda f: jax.vmap(lambda g: self._fresnel_colours(f, g))(light_gains))(path_fresnels)  # (B, K, J, M, 3)
        count = planes.shape[0] * planes.shape[1]
        return jnp.moveaxis(planes.reshape((count,) + planes.shape[2:]), 0, 2).reshape(planes.shape[2], planes.shape[3], -1)

    def _fresnel_colours(self, path_fresnel: Float[Array, "P L"], light_gain: Float[Array, "NL 3"]) -> Float[Array, "J M 3"]:
        """The job colours for paths' Fresnel factors and light gains (Schlick model)."""
        dtype = self.colour_bases.dtype
        gained = dataclasses.replace(self.setup, lights=scaled_lights(self.setup.lights, jnp.asarray(light_gain).astype(dtype)))
        return job_colours(gained, path_fresnel.astype(dtype), self.jobs.light, self.jobs.path, self.band_nm, self.band_averaging)

    def gain_planes(self) -> Float[Array, "J M C"]:
        """The job colours of every light-gain basis (:attr:`colour_bases`) as colour planes of one
        splat: (J, M, 3 K), plane ``K = 3 k + c`` (light k, input channel c)."""
        bases = self.colour_bases
        return jnp.moveaxis(bases, 0, 2).reshape(bases.shape[1], bases.shape[2], -1)

    def path_images(self, dirt=None, *, per_light_colour: bool = False):
        """Each flare path's image at unit tint: (P, K, H, W, 3) with ``K = 3 NL`` gain bases
        (light k, input channel c: ``3 k + c``) when ``per_light_colour``, else ``K = 1`` (unit
        gains). The flare for path tints ``t`` and gains ``g`` is ``sum_p t_p sum_K g_K image_pK``.
        The bases are colour planes of one pass over the sub-samples."""
        ones = jnp.ones((self.num_paths, 3), self.colour_bases.dtype)
        if not per_light_colour:
            return self._splat(ones, dirt, None, per_path=True)[:, None]
        planes = self._splat(ones, dirt, None, per_path=True, colour=self.gain_planes())  # (P, H, W, 3 K)
        return jnp.moveaxis(planes.reshape(planes.shape[:3] + (-1, 3)), 3, 1)


@eqx.filter_jit
def _per_path_splat(model: GridFlareModel, path_fresnel, light_gain, dirt):
    ones = jnp.ones((model.num_paths, 3), model.colour_bases.dtype)
    return model._splat(ones, dirt, light_gain, per_path=True, path_fresnel=path_fresnel)


@eqx.filter_jit
def _per_path_planes(model: GridFlareModel, path_fresnels, light_gains, dirt):
    ones = jnp.ones((model.num_paths, 3), model.colour_bases.dtype)
    return model._splat(ones, dirt, None, per_path=True, colour=model.fresnel_planes(path_fresnels, light_gains))


@eqx.filter_jit
def _per_path_cells_splat(model: GridFlareModel, light_gain, cells: DirtCells, colour):
    ones = jnp.ones((model.num_paths, 3), model.colour_bases.dtype)
    return model._splat(ones, None, light_gain, per_path=True, dirt_cells=cells, colour=colour)


def _model_scene(scene) -> Scene:
    """The scene as a model of its flare: no core (only flares are fitted), no culling (a fit may
    brighten a path its tints make dim)."""
    scene = scene if isinstance(scene, Scene) else load_scene(scene)
    return dataclasses.replace(scene, render=dataclasses.replace(scene.render, core=False, cull_threshold=0.0))


def grid_flare_model(
    scene, quality: str | None = "production", *, paths=None, grid_error: float | None = None, grid_options: dict | None = None,
) -> GridFlareModel:
    """Plan and trace ``scene``'s flare with the grid estimator (as :func:`jaxflare.render_grid`
    at ``quality``; ``paths``, ``grid_error`` and ``grid_options`` as for :func:`plan_grid`) and
    keep the records, so :meth:`GridFlareModel.image` re-splats them for other parameters. The
    grid is planned for the scene's own coatings, every flare path kept."""
    plan: GridPlan = plan_grid(_model_scene(scene), quality, 0, paths=paths, grid_error=grid_error, grid_options=grid_options)
    prepared = prepare_grid(plan).prepared
    if prepared is None:
        raise ValueError("the scene's flare paths put no light on the image: there is nothing to model")
    if prepared.more:
        raise ValueError(
            f"the grid of this scene draws {prepared.total:,} sub-samples, more than a flare model keeps in one table "
            f"({SPLAT_GROUP_SUBSAMPLES:,}): fit at a lower resolution or quality, or pass a larger grid_error"
        )
    setup = plan.setup
    num_lights = int(setup.lights.kind.shape[0])
    bases = []
    for gain in gain_basis(num_lights):
        gained = dataclasses.replace(setup, lights=scaled_lights(setup.lights, jnp.asarray(gain)))
        bases.append(job_table(gained, plan.jobs, plan.path_fresnel, plan.spectral.band_nm).colour)
    flare_paths = tuple(tuple(int(v) for v in p) for p in plan.paths)
    fine, averaging = band_averaging(plan.spectral.band_nm)
    return GridFlareModel(
        setup=dataclasses.replace(setup, path_tint=jnp.ones_like(setup.path_tint)),
        table=prepared.table, jobs=prepared.jobs, colour_bases=jnp.stack(bases), job_slot=prepared.jobs.path,
        total=jnp.asarray(prepared.total, jnp.int32), first=jnp.asarray(prepared.first, jnp.int32), chunks=jnp.asarray(prepared.chunks, jnp.int32),
        to_radiance=jnp.asarray(radiance_scale(plan.lens, plan.pixel_pitch_mm), jnp.float32),
        events=EventTable.from_array(np.stack(plan.events)), base_fresnel=jnp.asarray(plan.path_fresnel, jnp.float32),
        band_nm=jnp.asarray(fine, jnp.float32), band_averaging=jnp.asarray(averaging, jnp.float32),
        paths=flare_paths, resolution=tuple(plan.scene.camera.resolution), num_lights=num_lights, subsamples=int(prepared.total),
        quality=plan.quality_name,
    )

