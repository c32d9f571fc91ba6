"""The sets of lens paths a render batch samples, each traced by its own path tracer.

- :class:`AdaptivePathSet`: exactly traced paths sampled through one joint (light, path,
  front-lens cell) table (:mod:`._adaptive`): a batch mixes paths, each ray follows its own;
- :class:`UniformPathSet`: paths whose polynomial systems share one structure, ``rays_per_path``
  samples each, uniform over the front lens, evaluated together.

The render step iterates over the sets the same way whatever their tracer: each set draws its
connections, traces them, and makes their :class:`~._records.SampleRecords`. Adaptive sets of
one trace group (the planner puts the core and the flares of one lens in one) draw their cells
from their own tables, then connect, trace and record their samples together
(:func:`group_records`): a compiled render step holds one copy of that code, however many sets
there are (each copy cost seconds of compilation on a CPU).
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Int

from ..optics import AbstractPathTracer, ExactPathTracer
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

    @property
    def trace_group(self) -> int | None:
        """Sets of one group are connected, traced and recorded together (:func:`group_records`);
        None: on its own."""
        return None

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
    joint_trace_group: int | None = eqx.field(static=True, default=None)
    """Sets with the same group number are traced by one call; they must hold exact tracers of
    one lens with one Fresnel model (the planner's exact sets do)."""

    @property
    def table(self) -> SamplingTable:
        return self.sampling_table

    @property
    def trace_group(self) -> int | None:
        return self.joint_trace_group

    def draw_cells(self, key) -> tuple[Array, Array, Array, Array, Array, Array]:
        """This batch's (light, slot, unit-disc point, table entry, normalised weight) per sample,
        drawn from the table, and the key its connections are drawn with."""
        k_table, k_rays = jax.random.split(jax.random.fold_in(key, self.stream))
        light, slot, unit, index, weight = draw(self.sampling_table, k_table, self.samples)
        return light, slot, unit, index, weight / self.samples, k_rays

    def draw(self, setup, key):
        light, slot, unit, index, weight, k_rays = self.draw_cells(key)
        connections = sample_connections(
            setup.lights, setup.front, setup.spectral, k_rays, self.samples, setup.wavelength_strata, light=light, front_unit=unit,
        )
        return connections, slot, weight, index


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


def trace_groups(path_sets) -> list[list[int]]:
    """The sets' indices by trace group, in order of first appearance (a set without a group
    alone)."""
    groups: dict = {}
    for k, path_set in enumerate(path_sets):
        group = path_set.trace_group
        groups.setdefault(("alone", k) if group is None else ("group", group), []).append(k)
    return list(groups.values())


def group_records(setup, path_sets, key: Array) -> list[SampleRecords]:
    """One batch of adaptive sets of one trace group: each draws its cells from its own table
    (its own random stream); then the samples of all of them are connected to the lights (with
    the first set's connection key), traced by one :meth:`ExactPathTracer.joined` tracer and
    recorded together, and the records are split back into one per set, in order."""
    if not all(isinstance(s, AdaptivePathSet) and isinstance(s.tracer, ExactPathTracer) for s in path_sets):
        raise TypeError("a trace group holds adaptive sets of exact tracers only")
    cells = [s.draw_cells(key) for s in path_sets]
    offsets = np.cumsum([0] + [s.tracer.num_paths for s in path_sets])[:-1]
    bounds = np.cumsum([0] + [s.samples for s in path_sets])
    light, unit, index, weight = (jnp.concatenate([c[k] for c in cells]) for k in (0, 2, 3, 4))
    tracer_slot = jnp.concatenate([c[1] + int(offset) for c, offset in zip(cells, offsets)])
    path = jnp.concatenate([s.path_index[c[1]] for s, c in zip(path_sets, cells)])
    connections = sample_connections(
        setup.lights, setup.front, setup.spectral, cells[0][5], int(bounds[-1]), setup.wavelength_strata, light=light, front_unit=unit,
    )
    tracer = ExactPathTracer.joined([s.tracer for s in path_sets])
    traced = tracer.trace(connections.origins, connections.directions, connections.wavelength_nm, tracer_slot)
    records = sample_records(setup, connections, path, traced, weight, index)
    return [jax.tree.map(lambda x, low=int(low), high=int(high): x[low:high], records) for low, high in zip(bounds[:-1], bounds[1:])]
