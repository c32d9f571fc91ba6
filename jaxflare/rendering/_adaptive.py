"""Adaptive sampling over lights, lens paths and front-lens cells (Pekkarinen & Balzer 2019, section 3).

The paper samples light paths and uniform front-lens cells with probabilities proportional to the
radiance each subset carries, ``p_s = p_lp x p_cell``, and weights samples by equation (1). Here
the subsets are the triples (light, path, cell) and their probabilities one joint table: that
also samples several lights by their flare contribution, which the paper lists as future work.

Cells are equal-area polar cells of the unit disc (rings x sectors); the renderer maps the unit
disc onto its per-sample front-lens disc (:class:`jaxflare.rendering._lights.FrontDisc`). Each sample's
weight is ``a_cell / q``: the cell's area fraction over the table probability, so every batch is an
unbiased estimate whatever the table, and the table can be re-learnt between batches from what
the render has seen. A defensive share of uniform probability keeps every triple reachable, so a
subset the pilot missed is still sampled (and the estimate stays unbiased).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

DEFAULT_RINGS = 8
DEFAULT_SECTORS = 16
UNIFORM_SHARE = 0.1
"""Fraction of the samples drawn uniformly over all (light, path, cell) triples."""


class SamplingTable(eqx.Module):
    """A joint distribution over (light, path, cell), flattened in that order."""

    probability: Float[Array, " K"]
    cumulative: Float[Array, " K"]
    num_lights: int = eqx.field(static=True)
    num_paths: int = eqx.field(static=True)
    rings: int = eqx.field(static=True)
    sectors: int = eqx.field(static=True)

    @property
    def num_cells(self) -> int:
        return self.rings * self.sectors


def uniform_table(num_lights: int, num_paths: int, rings: int = DEFAULT_RINGS, sectors: int = DEFAULT_SECTORS, light_probability=None) -> SamplingTable:
    """Uniform over paths and cells; over lights by ``light_probability`` (default uniform)."""
    light_probability = np.full(num_lights, 1.0 / num_lights) if light_probability is None else np.asarray(light_probability, np.float64)
    probability = np.repeat(light_probability / (num_paths * rings * sectors), num_paths * rings * sectors)
    return _table(probability, num_lights, num_paths, rings, sectors)


def _table(probability: np.ndarray, num_lights: int, num_paths: int, rings: int, sectors: int) -> SamplingTable:
    probability = np.asarray(probability, np.float64)
    cumulative = np.cumsum(probability / probability.sum()).astype(np.float32)
    cumulative[-1] = 1.0
    # the probabilities actually sampled: differences of the float32 cumulative table that
    # ``draw`` searches, so the weights 1/q are exact for the distribution drawn from
    actual = np.diff(cumulative.astype(np.float64), prepend=0.0)
    return SamplingTable(jnp.asarray(actual, jnp.float32), jnp.asarray(cumulative), num_lights, num_paths, rings, sectors)


def masked_table(previous: SamplingTable, energy: np.ndarray | None, mask: np.ndarray, uniform_share: float = UNIFORM_SHARE) -> SamplingTable:
    """A table proportional to the energy each triple carried (``energy``: importance-weighted sums
    over the samples seen so far, shape (K,)), mixed with ``uniform_share`` of uniform over the
    entries ``mask`` keeps; masked-out entries (culled paths) get probability 0. With ``energy``
    None the table stays uniform over paths and cells (the lights keep their probabilities)."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        return previous
    base = np.where(mask, np.asarray(uniform_table(previous.num_lights, previous.num_paths, previous.rings, previous.sectors).probability, np.float64), 0.0)
    base = base / base.sum()
    light_prior = np.asarray(previous.probability, np.float64).reshape(previous.num_lights, -1).sum(axis=1)
    base = base.reshape(previous.num_lights, -1) * light_prior[:, None] * previous.num_lights
    base = (base / base.sum()).ravel()
    if energy is None:
        return _table(base, previous.num_lights, previous.num_paths, previous.rings, previous.sectors)
    energy = np.where(mask, np.clip(np.nan_to_num(np.asarray(energy, np.float64)), 0.0, None), 0.0)
    if energy.sum() <= 0:
        return _table(base, previous.num_lights, previous.num_paths, previous.rings, previous.sectors)
    probability = (1.0 - uniform_share) * energy / energy.sum() + uniform_share * base
    return _table(probability, previous.num_lights, previous.num_paths, previous.rings, previous.sectors)


def draw(table: SamplingTable, key: Array, count: int, dtype=jnp.float32):
    """``count`` samples: light, path slot, a point on the unit disc uniform in the cell, the flat
    index of the triple and the weight ``a_cell / q`` (a_cell = 1 / cells)."""
    k_index, k_point = jax.random.split(key)
    u = jax.random.uniform(k_index, (count,), jnp.float32)
    index = jnp.clip(jnp.searchsorted(table.cumulative, u, side="right"), 0, table.probability.shape[0] - 1)
    cells = table.num_cells
    light = index // (table.num_paths * cells)
    path = (index // cells) % table.num_paths
    cell = index % cells
    ring = cell // table.sectors
    sector = cell % table.sectors
    v = jax.random.uniform(k_point, (count, 2), dtype)
    # equal-area rings: radius^2 uniform within [ring, ring + 1] / rings
    radius = jnp.sqrt((ring + v[:, 0]) / table.rings)
    angle = 2 * jnp.pi * (sector + v[:, 1]) / table.sectors
    unit = jnp.stack([radius * jnp.cos(angle), radius * jnp.sin(angle)], axis=-1)
    weight = (1.0 / cells) / table.probability[index].astype(dtype)
    return light, path, unit, index, weight
