"""Photometric refinement of a reconstruction's geometry against its own observations (issue 49).

The stereo geometry (``docs/geometry.md``) is refined with the images the appearance fit reads:

* :func:`refine_surface` (``surface``): the reference surface moved along its normals to where the views
  of every frame agree (a texture-space plane sweep of the locally normalised images).

It samples the views in texture space (``views``: grey images, visibility, local normalisation) with the
options of :class:`ViewSampling`; the configurations live in ``config``.
"""

from polarface.texture.photometric.config import (
    ROLES,
    SurfaceRefinementConfig,
    ViewSampling,
)
from polarface.texture.photometric.surface import (
    PhotoConsistency,
    SurfaceRefinement,
    photo_consistency_volume,
    refine_surface,
)
from polarface.texture.photometric.views import TexelGrid

__all__ = [
    "ROLES",
    "PhotoConsistency",
    "SurfaceRefinement",
    "SurfaceRefinementConfig",
    "TexelGrid",
    "ViewSampling",
    "photo_consistency_volume",
    "refine_surface",
]
