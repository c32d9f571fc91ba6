"""What a scene adds on top of the lens, loaded once per render: front-lens dirt, a lens hood,
occluding geometry and the main render's distortion."""

from __future__ import annotations

import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ...scenes import Hood, Scene, SceneError
from ._dirt import load_dirt_map
from ._distortion import AbstractDistortion, BrownConrady, STMap, load_st_map
from ._occluders import Occluders, load_occluders


class SceneEffects(eqx.Module):
    """The scene's effects as the render step reads them. Each is optional (None: skipped, no cost)."""

    dirt: Float[Array, "H W C"] | None = None
    """Transmission of the front element (:mod:`._dirt`)."""
    hood: Hood | None = None
    occluders: Occluders | None = eqx.field(static=True, default=None)
    """Meshes that block light on its way to the lens (ray cast on the host)."""
    camera_position_m: Float[Array, " 3"] | None = None
    camera_to_world: Float[Array, "3 3"] | None = None
    distortion: AbstractDistortion | None = None


_OCCLUDER_CACHE: dict = {}


def cached_occluders(files: list[str], transforms: list[np.ndarray]) -> Occluders:
    """Loaded meshes, reused while the files are unchanged: the render step is compiled for its
    occluders (a static field), so reloading them would recompile every render."""
    key = (tuple(files), tuple(t.tobytes() for t in transforms), tuple(os.stat(f).st_mtime_ns if os.path.exists(f) else None for f in files))
    if key not in _OCCLUDER_CACHE:
        if len(_OCCLUDER_CACHE) > 8:
            _OCCLUDER_CACHE.clear()
        _OCCLUDER_CACHE[key] = load_occluders(files, transforms=transforms)
    return _OCCLUDER_CACHE[key]


def scene_effects(scene: Scene, lens, pitch_mm: float) -> SceneEffects:
    """Dirt, hood, occluding geometry and distortion of a scene, loaded (errors name the key)."""
    camera = scene.camera
    effects = {}
    if camera.dirt_map is not None:
        try:
            effects["dirt"] = jnp.asarray(load_dirt_map(camera.dirt_map), jnp.float32)
        except (OSError, ValueError) as error:
            raise SceneError(f"camera.dirt_map: {error}") from None
    if camera.hood is not None:
        effects["hood"] = jax.tree.map(lambda size: jnp.asarray(size, jnp.float32), camera.hood)  # traced, not static
    if scene.geometry:
        transforms = []
        for mesh in scene.geometry:
            place = np.eye(4) if mesh.transform is None else np.asarray(mesh.transform, np.float64)
            transforms.append(place @ np.diag([mesh.scale, mesh.scale, mesh.scale, 1.0]))
        try:
            effects["occluders"] = cached_occluders([mesh.file for mesh in scene.geometry], transforms)
        except (OSError, ValueError) as error:
            raise SceneError(f"geometry: {error}") from None
        effects["camera_position_m"] = jnp.asarray(camera.position_m, jnp.float32)
        effects["camera_to_world"] = jnp.asarray(camera.world_to_camera().T, jnp.float32)
    if camera.distortion is not None:
        distortion = camera.distortion
        if distortion.st_map is not None:
            try:
                effects["distortion"] = STMap(jnp.asarray(load_st_map(distortion.st_map), jnp.float32))
            except (OSError, ValueError) as error:
                raise SceneError(f"camera.distortion.st_map: {error}") from None
        else:
            focal = distortion.focal_length_px or lens.focal_length() / pitch_mm
            effects["distortion"] = BrownConrady.create(
                k1=distortion.k1, k2=distortion.k2, k3=distortion.k3, p1=distortion.p1, p2=distortion.p2, focal_length_px=focal,
            )
    return SceneEffects(**effects)
