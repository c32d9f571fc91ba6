"""The sets of lens paths a render batch samples, each traced by its own path tracer.

- :class:`AdaptivePathSet`: exactly traced paths sampled through one joint (light, path,
  front-lens cell) table (:mod:`._adaptive`): a batch mixes paths, each ray follows its own;
- :class:`UniformPathSet`: paths whose polynomial systems share one structure, ``rays_per_path``
  samples each, uniform over the front lens, evaluated together.

The render step iterates over the sets the same way whatever their tracer: each set draws its
connections, traces them, and makes their :class:`~._records.SampleRecords`.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Int

from ..optics import AbstractPathTracer
from ._adaptive import SamplingTable, draw
from ._records import SampleRecords, sample_records
from ._sampling import Connections, sample_connections


class AbstractPathSet(eqx.Module):
    """Paths sampled and traced together in a render batch."""

    path_index: eqx.AbstractVar[Int[Array, " P"]]
    """Index of each of the set's paths in the render's path list."""
    tracer: eqx.AbstractVar[AbstractPathTracer]

    @property
    @abc.abstractmethod
    def table(self) -> SamplingTable | None:
        """The adaptive sampling table, or None for uniform sampling."""

    @abc.abstractmethod
    def draw(self, setup, key: Array) -> tuple[Connections, Array, Array, Array | None]:
        """This batch's connections, each ray's slot in the set, its normalised weight, and its
        entry of the sampling table (None without a table)."""

    def records(self, setup, key: Array) -> SampleRecords:
        """Draw, trace and record this set's samples of one batch."""
        connections, slot, weight, table_index = self.draw(setup, key)
        traced = self.tracer.trace(connections.origins, connections.directions, connections.wavelength_nm, slot)
        return sample_records(setup, connections, self.path_index[slot], traced, weight, table_index)


class AdaptivePathSet(AbstractPathSet):
    """Exactly traced paths sampled through one joint (light, path, cell) table; each sample's
    weight is ``a_cell / q`` over the batch size."""

    path_index: Int[Array, " P"]
    tracer: AbstractPathTracer
    sampling_table: SamplingTable
    samples: int = eqx.field(static=True)
    """Samples per batch."""
    stream: int = eqx.field(static=True)
    """Random stream of the set within a batch (its key is the batch key folded with this)."""

    @property
    def table(self) -> SamplingTable:
        return self.sampling_table

    def draw(self, setup, key):
        k_table, k_rays = jax.random.split(jax.random.fold_in(key, self.stream))
        light, slot, unit, index, weight = draw(self.sampling_table, k_table, self.samples)
        connections = sample_connections(
            setup.lights, setup.front, setup.spectral, k_rays, self.samples, setup.wavelength_strata, light=light, front_unit=unit,
        )
        return connections, slot, weight / self.samples, index


class UniformPathSet(AbstractPathSet):
    """Paths sampled uniformly, ``rays_per_path`` samples each, grouped by path (the layout
    :class:`~jaxflare.polynomial.PolynomialPathTracer` evaluates vmapped)."""

    path_index: Int[Array, " P"]
    tracer: AbstractPathTracer
    rays_per_path: int = eqx.field(static=True)

    @property
    def table(self) -> None:
        return None

    def draw(self, setup, key):
        n = self.rays_per_path
        keys = jax.vmap(lambda p: jax.random.fold_in(key, p))(self.path_index)
        connections = jax.vmap(lambda k: sample_connections(setup.lights, setup.front, setup.spectral, k, n, setup.wavelength_strata))(keys)
        connections = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), connections)
        slot = jnp.repeat(jnp.arange(self.path_index.shape[0]), n)
        return connections, slot, jnp.full(slot.shape, 1.0 / n, connections.flux.dtype), None
