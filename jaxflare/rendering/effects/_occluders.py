"""Occlusion of light-to-lens connections: scene meshes (ray cast on the host) and lens hoods (JAX).

A flare sample connects a point on a light with a point on the front lens (see
:func:`jaxflare.rendering.sample_connections`). Anything between the two (a wall, a tree, a matte box)
blocks that sample: its weight gets a factor 0. Visibility is a fixed 0/1 factor per sample, so
fitting (gradients with respect to colours, powers and lens parameters that do not move the
blocking edge) works unchanged; the visibility itself has no useful gradient and none is taken.

:class:`Occluders` are triangle meshes (OBJ, PLY, STL, GLB/GLTF) in the **world frame, metres**,
ray cast on the CPU with trimesh (Intel Embree through ``embreex`` when installed).
:meth:`Occluders.segment_visible` answers in NumPy; :func:`segment_visibility` is the same query
as a ``jax.pure_callback``, usable inside ``jax.jit`` / ``eqx.filter_jit`` and ``vmap`` (its inputs
pass through ``stop_gradient``, so ``grad`` of a render never reaches the callback). The lens hood,
the other occluder, is in :mod:`._hood`.

Frames and units. World positions are metres (:mod:`jaxflare.scenes`). The lens frame is mm, x to
the right, y up, z along the optical axis towards the sensor, with the front lens vertex (the
camera's ``position_m``) at the origin; ``Camera.world_to_camera()`` is the rotation ``R`` taking
world vectors to lens-frame vectors, so a lens-frame point ``p_mm`` is at
``position_m + R.T @ p_mm / 1000`` in the world (:func:`lens_to_world`).

What counts as blocked. A segment from ``start`` to ``end`` is blocked when the *open* segment
crosses a triangle (either face: no back-face culling). Geometry that merely touches an end point
does not count: the ends are trimmed by ``rel_tol`` (default 1e-5) times the diagonal of the mesh's
bounding box, so a light lying on a wall or a lens point on a camera body is not self-blocked.
Segments shorter than twice that are visible, as are zero-length segments. Meshes need not be
closed or consistently oriented.

Precision. Embree works in float32. To keep that harmless every segment is first clipped, in
float64, to the mesh's bounding box (slightly enlarged); segments that miss the box are visible
without casting. The ray is cast from the clipped entry point, which lies at most a box diagonal
from the geometry, along a float64 unit direction, with its far limit (Embree's ``tfar``) set to the
clipped, trimmed segment length: any hit before it blocks. Points, limits and vertices are centred
on the box and divided by its diagonal in float64 before rounding to float32, so hits are resolved
to about 1e-7 of the mesh's size, a hundred times finer than the end trim. A directional light
passed as an end point 1e6 m away (or farther) therefore loses no precision, whichever end is far,
and casting from the lens towards the light or the reverse gives the same answer; so does a scene
placed far from the world origin. (The pure-NumPy fallback casts the same clipped rays with
trimesh's ``intersects_id`` and compares the first hit's float64 distance with the limit.)

Performance (measured on the 2-core development machine, with another job running: a
5120-triangle icosphere, 2e5 segments crossing its box, one thread): about 1.8 million segments/s
with Embree (embreex 4.4; the Embree query itself runs at ~20 million rays/s, the rest is the NumPy
clipping) and about 8,600 segments/s with trimesh's pure-NumPy intersector (rtree candidate
search), the fallback used, with an :class:`OcclusionWarning`, when embreex is not installed.
Segments are processed in chunks of :data:`CHUNK` so memory stays bounded whatever N.
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

SUPPORTED_EXTENSIONS = (".obj", ".ply", ".stl", ".glb", ".gltf")
"""Mesh file types :func:`load_occluders` reads (anything trimesh reads with these suffixes)."""

CHUNK = 1 << 17
"""Segments cast per batch (bounds the temporary arrays to a few tens of MB)."""

DEFAULT_REL_TOL = 1e-5
"""End-point trim, relative to the mesh's bounding-box diagonal (see the module docstring)."""

_BOX_MARGIN = 1e-3
"""Enlargement of the bounding box used for clipping, relative to its diagonal."""


class OcclusionWarning(UserWarning):
    """Ray casting falls back to the slow pure-NumPy intersector (embreex is not installed)."""


def embree_available() -> bool:
    """Whether trimesh can ray cast with Embree (the ``embreex`` package imports)."""
    try:
        from trimesh.ray import has_embree
    except ImportError:  # pragma: no cover - trimesh missing altogether
        return False
    return bool(has_embree)


def _import_trimesh():
    try:
        import trimesh
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("occluder meshes need trimesh: pip install trimesh embreex rtree") from exc
    return trimesh


def _make_intersector(mesh):
    """trimesh's Embree intersector when embreex imports, else its pure-NumPy one (with a warning)."""
    import trimesh.ray

    if trimesh.ray.has_embree:
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        return RayMeshIntersector(mesh)
    warnings.warn(
        "embreex is not installed: occluder ray casting uses trimesh's pure-NumPy intersector, which is "
        "hundreds of times slower; install it with `pip install embreex rtree`",
        OcclusionWarning,
        stacklevel=3,
    )
    from trimesh.ray.ray_triangle import RayMeshIntersector

    return RayMeshIntersector(mesh)


@dataclasses.dataclass(frozen=True, eq=False)
class Occluders:
    """Scene geometry that blocks light on its way to the lens: one triangle mesh in world metres.

    Build with :func:`load_occluders` (files) or :meth:`from_mesh` (a ``trimesh.Trimesh`` made in
    Python). Not a JAX pytree: close over it, or keep it as a static field of an equinox Module
    (it hashes and compares by identity). Query with :meth:`segment_visible` (NumPy) or
    :func:`segment_visibility` (JAX).
    """

    mesh: object
    """The concatenated ``trimesh.Trimesh`` (world frame, metres)."""
    intersector: object
    """``trimesh.ray.ray_pyembree.RayMeshIntersector`` when embreex imports, else
    ``trimesh.ray.ray_triangle.RayMeshIntersector`` (the fallback casts with it; with Embree the
    segment queries use an embreex scene of their own, built on first use, for per-ray limits)."""
    sources: tuple[str, ...] = ()
    """The files (or ``"<mesh>"``) the geometry came from, for messages."""

    def __post_init__(self):
        bounds = np.asarray(self.mesh.bounds, dtype=np.float64)
        diagonal = float(np.linalg.norm(bounds[1] - bounds[0]))
        if not diagonal > 0.0:  # a single point or every vertex coincident: pick a 1 m scale
            diagonal = 1.0
        margin = _BOX_MARGIN * diagonal
        object.__setattr__(self, "_box", (bounds[0] - margin, bounds[1] + margin))
        object.__setattr__(self, "_diagonal", diagonal)
        object.__setattr__(self, "_plane_origins", np.asarray(self.mesh.triangles[:, 0, :], dtype=np.float64))
        object.__setattr__(self, "_plane_normals", np.asarray(self.mesh.face_normals, dtype=np.float64))
        object.__setattr__(self, "_centroids", np.asarray(self.mesh.triangles_center, dtype=np.float64))

    @classmethod
    def from_mesh(cls, mesh, name: str = "<mesh>") -> Occluders:
        """Occluders from a ``trimesh.Trimesh`` (or a ``trimesh.Scene``, flattened with its
        transforms) already in world metres. The mesh is copied."""
        trimesh = _import_trimesh()
        if isinstance(mesh, trimesh.Scene):
            mesh = _scene_to_mesh(mesh)
        if not isinstance(mesh, trimesh.Trimesh):
            raise TypeError(f"{name}: expected a trimesh.Trimesh or trimesh.Scene, got {type(mesh).__name__}")
        mesh = mesh.copy()
        _check_mesh(mesh, name)
        return cls(mesh=mesh, intersector=_make_intersector(mesh), sources=(name,))

    def _embree_scene(self):
        """The embreex scene of the mesh, centred on its box and scaled by its diagonal (built once)."""
        cached = getattr(self, "_embree", None)
        if cached is None:
            from embreex import mesh_construction, rtcore_scene

            centre = 0.5 * (self._box[0] + self._box[1])
            vertices = (np.asarray(self.mesh.vertices, dtype=np.float64) - centre) / self._diagonal
            scene = rtcore_scene.EmbreeScene()
            mesh_construction.TriangleMesh(
                scene=scene,
                vertices=np.ascontiguousarray(vertices, dtype=np.float32),
                indices=np.ascontiguousarray(self.mesh.faces, dtype=np.int32),
            )
            cached = (scene, centre)
            object.__setattr__(self, "_embree", cached)
        return cached

    @property
    def uses_embree(self) -> bool:
        return type(self.intersector).__module__.endswith("ray_pyembree")

    @property
    def num_triangles(self) -> int:
        return len(self.mesh.faces)

    def __repr__(self) -> str:
        backend = "embree" if self.uses_embree else "numpy"
        return f"Occluders({self.num_triangles} triangles, {backend}, sources={list(self.sources)})"

    def segment_visible(self, starts, ends, *, rel_tol: float = DEFAULT_REL_TOL) -> np.ndarray:
        """True where the open segment from ``starts`` to ``ends`` (world metres, shape (..., 3))
        crosses no triangle; shape (...). Touching geometry at an end point does not block (the
        ends are trimmed by ``rel_tol`` times the mesh's bounding-box diagonal); zero-length
        segments are visible. Raises ValueError for mismatched shapes or non-finite coordinates."""
        starts = np.asarray(starts, dtype=np.float64)
        ends = np.asarray(ends, dtype=np.float64)
        if starts.shape != ends.shape or starts.ndim < 1 or starts.shape[-1] != 3:
            raise ValueError(f"starts and ends must have the same shape (..., 3), got {starts.shape} and {ends.shape}")
        if not (np.all(np.isfinite(starts)) and np.all(np.isfinite(ends))):
            raise ValueError("segment end points must be finite (pass a far point, e.g. 1e6 m away, for a directional light)")
        if not (math.isfinite(rel_tol) and rel_tol >= 0.0):
            raise ValueError(f"rel_tol must be finite and >= 0, got {rel_tol!r}")
        return self._visible(starts, ends, rel_tol)

    def _visible(self, starts: np.ndarray, ends: np.ndarray, rel_tol: float) -> np.ndarray:
        shape = starts.shape[:-1]
        starts = starts.reshape(-1, 3)
        ends = ends.reshape(-1, 3)
        visible = np.ones(starts.shape[0], dtype=bool)
        for begin in range(0, starts.shape[0], CHUNK):
            stop = begin + CHUNK
            visible[begin:stop] = self._visible_chunk(starts[begin:stop], ends[begin:stop], rel_tol)
        return visible.reshape(shape)

    def _visible_chunk(self, starts: np.ndarray, ends: np.ndarray, rel_tol: float) -> np.ndarray:
        delta = ends - starts
        length = np.linalg.norm(delta, axis=-1)
        trim = rel_tol * self._diagonal
        usable = length > 2.0 * trim
        visible = np.ones(starts.shape[0], dtype=bool)
        if not np.any(usable):
            return visible
        index = np.flatnonzero(usable)
        start = starts[index]
        length = length[index]
        direction = delta[index] / length[:, None]

        # clip to the (enlarged) bounding box in float64: slab test
        low, high = self._box
        with np.errstate(divide="ignore", invalid="ignore"):
            t_low = (low - start) / direction
            t_high = (high - start) / direction
        t_near = np.minimum(t_low, t_high)
        t_far = np.maximum(t_low, t_high)
        parallel = direction == 0.0
        inside_slab = (start >= low) & (start <= high)
        t_near = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), t_near)
        t_far = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), t_far)
        t_enter = np.maximum(np.max(t_near, axis=-1), trim)
        t_exit = np.minimum(np.min(t_far, axis=-1), length - trim)
        cast = t_exit > t_enter
        if not np.any(cast):
            return visible
        index = index[cast]
        direction = direction[cast]
        origin = start[cast] + t_enter[cast, None] * direction
        reach = t_exit[cast] - t_enter[cast]

        if self.uses_embree:
            # Embree straight away, each ray limited to its reach (tfar): any hit blocks. Coordinates
            # are centred on the box and scaled by its diagonal in float64 before rounding to
            # float32, so origins (inside the box) and reaches (<= ~1.7) keep ~1e-7 relative precision,
            # far below the end trim.
            scene, centre = self._embree_scene()
            scaled = ((origin - centre) / self._diagonal).astype(np.float32)
            tfar = np.ascontiguousarray(reach / self._diagonal, dtype=np.float32)
            hit = scene.run(scaled, np.ascontiguousarray(direction, dtype=np.float32), dists=tfar)
            visible[index[np.asarray(hit) >= 0]] = False
            return visible

        # first hit of each ray (pure NumPy intersector), its distance recomputed in float64
        tri, ray = self.intersector.intersects_id(origin, direction, multiple_hits=False, return_locations=False)
        tri = np.asarray(tri, dtype=np.int64)
        ray = np.asarray(ray, dtype=np.int64)
        keep = tri >= 0
        tri, ray = tri[keep], ray[keep]
        if tri.size == 0:
            return visible
        normal = self._plane_normals[tri]
        denominator = np.sum(direction[ray] * normal, axis=-1)
        numerator = np.sum((self._plane_origins[tri] - origin[ray]) * normal, axis=-1)
        edge_on = np.abs(denominator) < 1e-12
        with np.errstate(divide="ignore", invalid="ignore"):
            t_hit = np.where(edge_on, 0.0, numerator / np.where(edge_on, 1.0, denominator))
        # a ray grazing a triangle edge-on (or a degenerate triangle): use the centroid's distance
        t_hit = np.where(edge_on, np.sum((self._centroids[tri] - origin[ray]) * direction[ray], axis=-1), t_hit)
        blocked = t_hit <= reach[ray]
        visible[index[ray[blocked]]] = False
        return visible


def _scene_to_mesh(scene):
    trimesh = _import_trimesh()
    meshes = [g for g in scene.dump(concatenate=False) if isinstance(g, trimesh.Trimesh)]
    if not meshes:
        return trimesh.Trimesh()
    return trimesh.util.concatenate(meshes) if len(meshes) > 1 else meshes[0]


def _check_mesh(mesh, name: str) -> None:
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise ValueError(f"{name}: the mesh is empty (no triangles)")
    if not np.all(np.isfinite(np.asarray(mesh.vertices, dtype=np.float64))):
        raise ValueError(f"{name}: the mesh has non-finite vertex coordinates")


def _load_one(path: str | os.PathLike):
    trimesh = _import_trimesh()
    name = os.fspath(path)
    if not os.path.exists(name):
        raise FileNotFoundError(f"occluder mesh file not found: {name}")
    if os.path.isdir(name):
        raise ValueError(f"{name}: is a directory, not a mesh file; supported: {', '.join(SUPPORTED_EXTENSIONS)}")
    extension = os.path.splitext(name)[1].lower()
    if extension not in SUPPORTED_EXTENSIONS:
        raise ValueError(f"{name}: unsupported mesh file type {extension or '(none)'!r}; supported: {', '.join(SUPPORTED_EXTENSIONS)}")
    try:
        loaded = trimesh.load(name, force="mesh", process=False)  # the file as written, for the checks
    except Exception as exc:  # trimesh raises many kinds for broken files
        raise ValueError(f"{name}: could not read the mesh ({type(exc).__name__}: {exc}); supported: {', '.join(SUPPORTED_EXTENSIONS)}") from exc
    if isinstance(loaded, trimesh.Scene):
        loaded = _scene_to_mesh(loaded)
    if not isinstance(loaded, trimesh.Trimesh):
        # e.g. a point cloud (PLY without faces)
        raise ValueError(f"{name}: the file holds no triangles ({type(loaded).__name__}); the mesh is empty")  # noqa: TRY004
    _check_mesh(loaded, name)
    return loaded


def load_occluders(
    paths: Sequence[str | os.PathLike] | str | os.PathLike,
    *,
    transforms: Sequence[np.ndarray] | None = None,
    scale: float = 1.0,
) -> Occluders:
    """Load occluder meshes (OBJ, PLY, STL, GLB/GLTF) into one :class:`Occluders` in world metres.

    Each file's vertices ``v`` (file units) go to the world as ``T @ [scale * v, 1]``: ``scale``
    converts the file's unit to metres (0.01 for centimetres, 0.001 for millimetres) and the
    optional per-file 4x4 ``transforms`` (one per path, world metres) then place it. Scenes in a
    file (GLB/GLTF) are flattened with their node transforms.

    Raises FileNotFoundError for a missing file, ValueError (naming the file) for an unsupported or
    unreadable file, an empty mesh or non-finite vertices, and for bad ``transforms`` or ``scale``.
    """
    trimesh = _import_trimesh()
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    paths = list(paths)
    if not paths:
        raise ValueError("load_occluders needs at least one mesh file")
    if not (isinstance(scale, (int, float, np.floating, np.integer)) and math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive finite number (file unit in metres), got {scale!r}")
    if transforms is not None:
        transforms = list(transforms)
        if len(transforms) != len(paths):
            raise ValueError(f"transforms: got {len(transforms)} for {len(paths)} files (one 4x4 matrix per file)")
        checked = []
        for k, matrix in enumerate(transforms):
            matrix = np.asarray(matrix, dtype=np.float64)
            if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
                raise ValueError(f"transforms[{k}] (for {os.fspath(paths[k])}): must be a finite 4x4 matrix, got shape {matrix.shape}")
            checked.append(matrix)
        transforms = checked
    meshes = []
    for k, path in enumerate(paths):
        mesh = _load_one(path)
        if scale != 1.0:
            mesh.apply_scale(float(scale))
        if transforms is not None:
            mesh.apply_transform(transforms[k])
        _check_mesh(mesh, os.fspath(path))
        meshes.append(mesh)
    mesh = trimesh.util.concatenate(meshes) if len(meshes) > 1 else meshes[0]
    return Occluders(mesh=mesh, intersector=_make_intersector(mesh), sources=tuple(os.fspath(p) for p in paths))


# --------------------------------------------------------------------------- JAX interface


def segment_visibility(occluders: Occluders, starts: Array, ends: Array, *, rel_tol: float = DEFAULT_REL_TOL) -> Array:
    """:meth:`Occluders.segment_visible` as a JAX operation (shape (..., 3) -> bool (...)).

    Runs as a ``jax.pure_callback`` on the host, so it works under ``jit``/``eqx.filter_jit`` and
    ``vmap`` (``vmap_method="broadcast_all"``: one host call per batch). ``starts`` and ``ends``
    pass through ``stop_gradient``: the result is a constant 0/1 factor for differentiation.
    Non-finite segments count as visible here (the NumPy method raises instead).
    """
    if not isinstance(occluders, Occluders):
        raise TypeError(f"occluders must be a jaxflare Occluders, got {type(occluders).__name__}")
    starts = jax.lax.stop_gradient(jnp.asarray(starts))
    ends = jax.lax.stop_gradient(jnp.asarray(ends))
    if starts.shape != ends.shape or starts.ndim < 1 or starts.shape[-1] != 3:
        raise ValueError(f"starts and ends must have the same shape (..., 3), got {starts.shape} and {ends.shape}")

    def host(s, e):
        s = np.asarray(s, dtype=np.float64)
        e = np.asarray(e, dtype=np.float64)
        finite = np.all(np.isfinite(s), axis=-1) & np.all(np.isfinite(e), axis=-1)
        s = np.where(finite[..., None], s, 0.0)
        e = np.where(finite[..., None], e, 0.0)  # zero length: visible
        return occluders._visible(s, e, rel_tol)

    result = jax.ShapeDtypeStruct(starts.shape[:-1], jnp.bool_)
    return jax.pure_callback(host, result, starts, ends, vmap_method="broadcast_all")


def lens_to_world(points_mm: Array, world_to_camera: Array, position_m: Array) -> Array:
    """Lens-frame points (mm, (..., 3)) to world points (metres): ``position_m + R.T @ p / 1000``
    with ``R = Camera.world_to_camera()``. Works on NumPy and JAX arrays."""
    rotation = jnp.asarray(world_to_camera)
    return jnp.asarray(position_m) + (jnp.asarray(points_mm) / 1000.0) @ rotation
