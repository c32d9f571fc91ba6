"""Thin-film coatings as fit parameters: every coated layer's thickness and index.

A fit of ``"thin-film"`` changes the layers of the lens's coating stacks (the scene's preset or
``surface_coatings``) instead of free RGB tints, so every colour it reports is one a real coating
makes: the characteristic-matrix model (:mod:`jaxflare.optics._thin_film`) gives each path's
coated Fresnel factor per wavelength (:meth:`jaxflare.rendering.GridFlareModel.path_fresnel`) and
the grid model recolours its jobs with it.

Bounds (by reparametrisation, as the other fit parameters): a layer's thickness stays within
:data:`THICKNESS_RANGE` times its start (a coater misses a design by tens of per cent, not by a
factor: the reflectance is periodic in the optical thickness, so a wider range only adds distant
minima) and its index within :data:`INDEX_SPREAD` of its start, inside :data:`INDEX_LIMITS` (the
spread of one deposited material: MgF2 films measure 1.37-1.39, mixtures vary more); a weak prior
pulls the index to its start, where thickness and index trade against each other.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxflare.colour import spectral_table
from jaxflare.optics import Lens, coated_reflectance

THICKNESS_RANGE = (0.5, 2.0)
"""A fitted layer's thickness, relative to its start (the scene's coating)."""
INDEX_SPREAD = 0.1
"""A fitted layer's index stays within this of its start."""
INDEX_LIMITS = (1.35, 2.45)
"""Indices of deposited coating materials: cryolite / MgF2 (1.35-1.38) to TiO2 (2.4)."""
INDEX_PRIOR_WEIGHT = 1e-4
"""Weight of the prior pulling a layer's index to its start (relative loss units, as the tints')."""


@dataclasses.dataclass(frozen=True)
class FilmLayers:
    """The coating layers a thin-film fit changes: every layer of positive thickness on an
    interface, as (surface, column) entries of the lens's coating arrays, with their starts and bounds."""

    surfaces: np.ndarray
    columns: np.ndarray
    thickness_nm: np.ndarray
    thickness_low_nm: np.ndarray
    thickness_high_nm: np.ndarray
    index: np.ndarray
    index_low: np.ndarray
    index_high: np.ndarray
    base_indices: np.ndarray
    """The lens's coating arrays (S, L) the fitted layers are written into."""
    base_thicknesses_nm: np.ndarray

    @property
    def size(self) -> int:
        return int(self.surfaces.size)


def film_layers(lens: Lens) -> FilmLayers:
    """The layers of ``lens``'s coatings a thin-film fit changes (ValueError when it has none)."""
    thickness = np.asarray(lens.coating_thicknesses_nm, np.float64)
    indices = np.asarray(lens.coating_indices, np.float64)
    interfaces = np.zeros(thickness.shape[0], bool)
    interfaces[list(lens.interface_surfaces)] = True
    surfaces, columns = np.nonzero((thickness > 0) & interfaces[:, None])
    if surfaces.size == 0:
        raise ValueError(
            f"params 'thin-film': the lens '{lens.name}' has no coating layers to fit; give the scene a coating "
            "(camera.coating = 'mgf2', 'multilayer', ... or camera.surface_coatings) as the start"
        )
    t0, n0 = thickness[surfaces, columns], indices[surfaces, columns]
    return FilmLayers(
        surfaces=surfaces, columns=columns, thickness_nm=t0, thickness_low_nm=THICKNESS_RANGE[0] * t0, thickness_high_nm=THICKNESS_RANGE[1] * t0,
        index=n0, index_low=np.maximum(n0 - INDEX_SPREAD, INDEX_LIMITS[0]), index_high=np.minimum(n0 + INDEX_SPREAD, INDEX_LIMITS[1]),
        base_indices=indices, base_thicknesses_nm=thickness,
    )


def _bounded(logits, low, high):
    return low + (high - low) * jax.nn.sigmoid(logits)


def _logits(values, low, high):
    x = np.clip((np.asarray(values, np.float64) - low) / np.maximum(high - low, 1e-300), 1e-6, 1 - 1e-6)
    return np.log(x) - np.log1p(-x)


def film_start_logits(layers: FilmLayers) -> np.ndarray:
    """Unconstrained start (2, F): thickness and index logits of the scene's coating."""
    return np.stack([
        _logits(layers.thickness_nm, layers.thickness_low_nm, layers.thickness_high_nm), _logits(layers.index, layers.index_low, layers.index_high),
    ])


def film_values(layers: FilmLayers, logits) -> tuple[jax.Array, jax.Array]:
    """Thicknesses (nm) and indices (F,) of the layers for unconstrained ``logits`` (2, F)."""
    thickness = _bounded(logits[0], jnp.asarray(layers.thickness_low_nm), jnp.asarray(layers.thickness_high_nm))
    index = _bounded(logits[1], jnp.asarray(layers.index_low), jnp.asarray(layers.index_high))
    return thickness, index


def film_arrays(layers: FilmLayers, thickness_nm, index) -> tuple[jax.Array, jax.Array]:
    """The lens's coating arrays (indices, thicknesses in nm; (S, L) each) with the fitted layers written in."""
    where = (jnp.asarray(layers.surfaces), jnp.asarray(layers.columns))
    indices = jnp.asarray(layers.base_indices).at[where].set(index)
    thicknesses = jnp.asarray(layers.base_thicknesses_nm).at[where].set(thickness_nm)
    return indices, thicknesses


def interface_reflectance(lens: Lens, indices, thicknesses_nm, wavelength_nm) -> jax.Array:
    """Normal-incidence reflectance (I, L) of each interface of ``lens`` with these coating arrays
    (the same from either side: the films do not absorb)."""
    wavelength_nm = jnp.asarray(wavelength_nm, jnp.float64)
    n = jnp.stack([jnp.asarray(lens.refractive_indices(w), jnp.float64) for w in np.asarray(wavelength_nm)], axis=1)  # (S+1, L)
    rows = []
    for s in lens.interface_surfaces:
        reflect = jax.vmap(lambda n1, n2, w: coated_reflectance(n1, n2, jnp.ones((), jnp.float64), w, indices[s], thicknesses_nm[s]))
        rows.append(reflect(n[s], n[s + 1], wavelength_nm))
    return jnp.stack(rows)


def equivalent_tints(lens: Lens, layers: FilmLayers, thickness_nm, index, colour_space: str = "ACEScg") -> np.ndarray:
    """Each interface's RGB tint (I, 3) equivalent to the fitted stack: its reflectance of an
    equal-energy white, per channel of ``colour_space``, over the scene coating's (1 where a
    surface's coating did not change). A reading of the physical result in the units of the
    ``"coatings"`` fit, not what the model renders with (that is spectral)."""
    table = spectral_table(colour_space)
    wavelengths = np.asarray(table.wavelength_nm, np.float64)
    response = np.clip(np.asarray(table.spectrum_response, np.float64), 0.0, None)  # (L, 3), its positive lobes
    with jax.enable_x64(True):
        fitted = np.asarray(interface_reflectance(lens, *film_arrays(layers, jnp.asarray(thickness_nm), jnp.asarray(index)), wavelengths))
        base = np.asarray(interface_reflectance(lens, jnp.asarray(layers.base_indices), jnp.asarray(layers.base_thicknesses_nm), wavelengths))
    return (fitted @ response) / np.maximum(base @ response, 1e-300)


def air_side_stacks(lens: Lens, layers: FilmLayers, thickness_nm, index) -> list[tuple[int, list[tuple[float, float]]]]:
    """The fitted stacks as ``(surface, [(index, thickness_nm), ...])`` from the air side inwards
    (the order of a scene's ``surface_coatings``), one per coated surface."""
    indices, thicknesses = (np.asarray(a, np.float64) for a in film_arrays(layers, jnp.asarray(thickness_nm), jnp.asarray(index)))
    air = np.asarray(lens.medium_is_air)
    stacks = []
    for s in sorted(set(int(v) for v in layers.surfaces)):
        stack = [(float(n), float(t)) for n, t in zip(indices[s], thicknesses[s]) if t > 0]
        if (not air[s]) and air[s + 1]:  # stored in the forward order: glass side first
            stack = stack[::-1]
        stacks.append((s, stack))
    return stacks
