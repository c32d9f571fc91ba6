"""Lens paths: the primary (image-forming) path and the two-reflection ghost paths, as event tables.

A *ghost path* ``(j, i)`` reflects at interface ``j``, travels back, reflects at interface ``i < j``
and goes on to the sensor (interfaces are the surfaces where the medium changes, numbered front to
back). A path is a fixed-length sequence of *events*: which surface, the direction of travel before
it, refract or reflect, and whether the event is active. Every path of a lens is padded to the same
length (``3 * num_surfaces``) so one compiled tracer serves them all.
"""

from __future__ import annotations

import enum

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Int

GhostPath = tuple[int, int]
"""A two-reflection path ``(j, i)``: first reflection at interface j, second at interface i < j."""


class EventAction(enum.IntEnum):
    """What a ray does at an event's surface."""

    REFRACT = 0
    REFLECT = 1


class EventColumn(enum.IntEnum):
    """The columns of the ``(E, 4)`` array :func:`path_events` returns."""

    SURFACE = 0
    TRAVEL = 1
    """+1 travelling towards the sensor before the event, -1 travelling back towards the object."""
    ACTION = 2
    """An :class:`EventAction`."""
    ACTIVE = 3
    """1 for the path's events, 0 for the padding after them."""


class EventTable(eqx.Module):
    """A path's events with named columns, each of shape ``(..., E)`` (a leading axis holds one
    path per ray or per stacked path)."""

    surface: Int[Array, "... E"]
    travel: Int[Array, "... E"]
    action: Int[Array, "... E"]
    active: Int[Array, "... E"]

    @classmethod
    def from_array(cls, events) -> EventTable:
        """From the ``(..., E, 4)`` array of :func:`path_events` (columns in :class:`EventColumn` order)."""
        if isinstance(events, np.ndarray):  # slice on the host: four device arrays, no device work
            return cls(*(jnp.asarray(np.ascontiguousarray(events[..., column])) for column in EventColumn))
        events = jnp.asarray(events)
        return cls(*(events[..., column] for column in EventColumn))

    def as_array(self) -> Array:
        return jnp.stack([self.surface, self.travel, self.action, self.active], axis=-1)


def ghost_paths(lens) -> list[GhostPath]:
    """Every two-reflection path ``(j, i)``: first reflection at interface j, second at i < j.

    Interfaces are numbered 0 .. ``lens.num_interfaces - 1``; there are N (N - 1) / 2 paths.
    """
    n = lens.num_interfaces
    return [(j, i) for j in range(1, n) for i in range(j)]


def check_ghost_path(lens, path: GhostPath | None) -> GhostPath | None:
    """``path`` as a pair of ints after checking it names a ghost path of ``lens`` (None: primary)."""
    if path is None:
        return None
    try:
        j, i = (int(k) for k in path)
    except (TypeError, ValueError):
        raise ValueError(f"path must be None (primary) or a pair (j, i) of interface indices, got {path!r}") from None
    n = lens.num_interfaces
    if not (0 <= i < j < n):
        raise ValueError(f"ghost path (j, i) needs 0 <= i < j < {n} (the interfaces of '{lens.name}'), got {path!r}")
    return j, i


def path_events(lens, path: GhostPath | None = None) -> np.ndarray:
    """The event table of a path: int32 array (3 * num_surfaces, 4) of
    ``(surface, direction +1/-1 before the event, REFRACT/REFLECT, active)`` rows."""
    path = check_ghost_path(lens, path)
    num = lens.num_surfaces
    refract, reflect = int(EventAction.REFRACT), int(EventAction.REFLECT)
    rows: list[tuple[int, int, int]] = []
    if path is None:
        rows = [(s, 1, refract) for s in range(num)]
    else:
        sj, si = lens.interface_surfaces[path[0]], lens.interface_surfaces[path[1]]
        rows += [(s, 1, refract) for s in range(sj)]
        rows.append((sj, 1, reflect))
        rows += [(s, -1, refract) for s in range(sj - 1, si, -1)]
        rows.append((si, -1, reflect))
        rows += [(s, 1, refract) for s in range(si + 1, num)]
    table = np.zeros((3 * num, 4), dtype=np.int32)
    table[:, EventColumn.TRAVEL] = 1
    table[: len(rows), :3] = rows
    table[: len(rows), EventColumn.ACTIVE] = 1
    return table


def event_table(lens, path: GhostPath | None = None) -> EventTable:
    """:func:`path_events` with named columns."""
    return EventTable.from_array(path_events(lens, path))


def stop_pass_count(events: np.ndarray, stop_index: int) -> int:
    """How often a path (its ``(E, 4)`` event array) crosses the aperture stop: 1 or 3."""
    return int(np.sum((events[:, EventColumn.SURFACE] == stop_index) & (events[:, EventColumn.ACTIVE] == 1)))


def active_event_count(events: np.ndarray) -> int:
    """The number of a path's events that are not padding."""
    return int(np.sum(np.asarray(events)[:, EventColumn.ACTIVE]))
