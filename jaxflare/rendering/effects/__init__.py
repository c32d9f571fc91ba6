"""What a scene adds on top of the lens: front-lens dirt, a lens hood, occluding geometry (trimesh
ray casts) and the main render's distortion (Brown-Conrady or an ST-map), each applied per sample."""

from ._bilinear import bilinear
from ._dirt import DIRT_FORMATS, dirt_cell_taps, dirt_transmission, load_dirt_map
from ._distortion import AbstractDistortion, BrownConrady, STMap, distort, identity_st_map, load_st_map, st_map_distort
from ._hood import hood_crossing, hood_inside, hood_visible
from ._occluders import SUPPORTED_EXTENSIONS, OcclusionWarning, Occluders, embree_available, lens_to_world, load_occluders, segment_visibility
from ._scene_effects import SceneEffects, cached_occluders, scene_effects

__all__ = [
    "DIRT_FORMATS",
    "SUPPORTED_EXTENSIONS",
    "AbstractDistortion",
    "BrownConrady",
    "OcclusionWarning",
    "Occluders",
    "STMap",
    "SceneEffects",
    "bilinear",
    "cached_occluders",
    "dirt_cell_taps",
    "dirt_transmission",
    "distort",
    "embree_available",
    "hood_crossing",
    "hood_inside",
    "hood_visible",
    "identity_st_map",
    "lens_to_world",
    "load_dirt_map",
    "load_occluders",
    "load_st_map",
    "scene_effects",
    "segment_visibility",
]
