"""Texture-space unwrapping: per texel geometry and per texel x view observations.

The inverse stages work on the UV atlas of a rest mesh (paper Sec. 5.1: "cylindrical texture mapping
so that all spatially-varying appearance parameters ... are modeled as textures"). Every polarimetric
camera of every frame is one *view* carrying three of the six spectral channels. :func:`unwrap_capture`
projects each texel into each view through the known geometry (mesh + rigid per-frame poses), decides
its visibility (ray-cast occlusion, n.v threshold, saturation and observation masks) and each LED
module's visibility (shadow rays), samples the observations bilinearly, and stores everything in a
zarr group chunked by texture patch (:class:`UnwrapStore`), one view at a time, so memory stays
bounded for any texture size and view count.
"""

from polarface.texture.footprint import footprint_sees_surface
from polarface.texture.texture_maps import (
    grid_mesh,
    texel_geometry_from_maps,
    texture_view_samples,
    write_texture_unwrap,
)
from polarface.texture.unwrap import UnwrapConfig, sample_view, unwrap_capture
from polarface.texture.unwrap_store import (
    TEXTURE_OBSERVATION_NAMES,
    TexelGeometry,
    UnwrapStore,
    texel_geometry,
)
from polarface.texture.views import ViewSpec, build_views

__all__ = [
    "TEXTURE_OBSERVATION_NAMES",
    "TexelGeometry",
    "UnwrapConfig",
    "UnwrapStore",
    "ViewSpec",
    "build_views",
    "footprint_sees_surface",
    "grid_mesh",
    "sample_view",
    "texel_geometry",
    "texel_geometry_from_maps",
    "texture_view_samples",
    "unwrap_capture",
    "write_texture_unwrap",
]
