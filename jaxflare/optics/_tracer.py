"""One interface for tracing rays along lens paths, whatever the method.

:class:`AbstractPathTracer` is what the renderer and the fitting package call: rays in, a
:class:`~jaxflare.TraceResult` out. A tracer holds one or several paths (stacked); each ray says
which one it follows. Implementations are final: :class:`ExactPathTracer` here (the exact
sequential trace), and the polynomial tracer of :mod:`jaxflare.polynomial`.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Int

from ._lens import Lens
from ._paths import EventTable, GhostPath, active_event_count, check_ghost_path, path_events, stop_pass_count
from ._trace import TraceResult, ray_arguments, trace_events


class AbstractPathTracer(eqx.Module):
    """Traces rays along ``num_paths`` lens paths (stacked)."""

    @property
    @abc.abstractmethod
    def num_paths(self) -> int:
        """How many paths the tracer holds."""

    @abc.abstractmethod
    def trace(self, origins: Array, directions: Array, wavelength_nm: Array, slot: Int[Array, " N"] | None = None) -> TraceResult:
        """Trace (N, 3) ``origins`` and ``directions`` (mm, lens frame) at (N,) ``wavelength_nm``;
        ray ``n`` follows path ``slot[n]`` of the tracer (None: every ray the first path). See each
        implementation for how the rays must be laid out."""

    def __call__(self, origins: ArrayLike, directions: ArrayLike, wavelength_nm: ArrayLike = 587.56) -> TraceResult:
        """Trace rays along the tracer's only path, with the argument checks of :func:`jaxflare.trace`."""
        if self.num_paths != 1:
            raise ValueError(f"this tracer holds {self.num_paths} paths: call trace() with a slot per ray")
        return self.trace(*ray_arguments(origins, directions, wavelength_nm))


class ExactPathTracer(AbstractPathTracer):
    """The exact sequential trace (:func:`jaxflare.trace`) along one or several paths of a lens.

    Rays may come in any order: each follows the event table of its own ``slot``.
    """

    lens: Lens
    events: EventTable
    """Columns of shape (P, E): one row per path."""
    num_stop_passes: int = eqx.field(static=True, default=1)
    """Stop crossings recorded in ``stop_positions`` (at most the paths' own count)."""
    fresnel: bool = eqx.field(static=True, default=True)
    """Multiply the coated Fresnel factor of every event into the throughput (False: skip it, the
    throughput is 1 for every valid ray; the renderer's Schlick model needs no more)."""

    @classmethod
    def for_paths(
        cls, lens: Lens, paths: Sequence[GhostPath | None], num_stop_passes: int | None = None, *, fresnel: bool = True,
    ) -> ExactPathTracer:
        """A tracer for ``paths`` (None is the primary path) of ``lens``. ``num_stop_passes``
        defaults to the fewest stop crossings of any of them (so a primary path records its one).
        The event tables are cut after the longest path's last event: rays of several paths in one
        batch each skip their own padding by a mask, so padding no path needs is not traced."""
        tables = np.stack([path_events(lens, check_ghost_path(lens, path)) for path in paths])
        if num_stop_passes is None:
            num_stop_passes = min(stop_pass_count(table, lens.stop_index) for table in tables)
        longest = max(active_event_count(table) for table in tables)
        return cls(lens, EventTable.from_array(tables[:, :longest]), num_stop_passes, fresnel)

    @classmethod
    def joined(cls, tracers: Sequence[ExactPathTracer]) -> ExactPathTracer:
        """One tracer holding the paths of ``tracers`` in order (the first one's paths, then the
        second's, ...), so that rays of all of them are traced by one call: one tracer in a
        compiled program instead of one per set. The tracers must trace one lens (this one takes
        the first's) with one Fresnel model; event tables are padded to the longest with inactive
        events, and the fewest stop crossings any of them records are kept."""
        tracers = tuple(tracers)
        if not tracers:
            raise ValueError("joined: needs at least one tracer")
        if len({t.fresnel for t in tracers}) != 1:
            raise ValueError("joined: the tracers use different Fresnel models (fresnel=True and False)")
        if len({jax.tree.structure(t.lens) for t in tracers}) != 1:
            raise ValueError("joined: the tracers trace lenses of different structure")
        longest = max(int(t.events.surface.shape[1]) for t in tracers)
        padding = {"surface": 0, "travel": 1, "action": 0, "active": 0}  # as path_events pads

        def column(name):
            parts = []
            for t in tracers:
                values = getattr(t.events, name)
                parts.append(jnp.pad(values, ((0, 0), (0, longest - values.shape[1])), constant_values=padding[name]))
            return jnp.concatenate(parts)

        events = EventTable(**{name: column(name) for name in padding})
        return cls(tracers[0].lens, events, min(t.num_stop_passes for t in tracers), tracers[0].fresnel)

    @property
    def num_paths(self) -> int:
        return int(self.events.surface.shape[0])

    def trace(self, origins: Array, directions: Array, wavelength_nm: Array, slot: Int[Array, " N"] | None = None) -> TraceResult:
        if slot is None:
            events = jax.tree.map(lambda column: column[0], self.events)
            return trace_events(self.lens, origins, directions, wavelength_nm, events, self.num_stop_passes, False, self.fresnel)
        # A path per ray (rays of several paths mixed in one batch): the rays are traced in order of
        # their path's length, so that the tracer's chunks of rays skip the events none of their
        # rays needs, then put back in their own order.
        length = jnp.sum(self.events.active, axis=1)
        order = jnp.argsort(length[slot], stable=True)
        traced = trace_events(
            self.lens, origins[order], directions[order], wavelength_nm[order], self.events, self.num_stop_passes, False, self.fresnel,
            slot[order],
        )
        back = jnp.zeros_like(order).at[order].set(jnp.arange(order.shape[0], dtype=order.dtype))
        return jax.tree.map(lambda x: x[back], traced)

