"""The renderer: one image formation for the simulator, ``polarface render`` and the report.

Stages, each with a frozen-dataclass output whose fields document shape, dtype, units and frame (in the
manner of a rasterizer -> fragments -> shader pipeline):

1. :func:`cast_fragments` -> :class:`SurfaceFragments`: Embree ray casting of a view (hit mask, texel
   coordinates, world positions and normals).
2. :class:`SubsurfaceModel`, :func:`entering_flux`, :func:`texture_space_exitance`: texture-space
   subsurface transport (entry Fresnel under the rig's polarized LEDs, heterogeneous two-layer
   sum-of-Gaussians diffusion).
3. :func:`fragment_material`, :func:`lobe_stokes`: polarimetric shading of fragments with the image
   formation of :mod:`polarface.optics` (exit Fresnel, specular and single-scattering Mueller lobes).

:func:`render_view` composes them into a :class:`ViewRender`. The texture-space counterpart of stage 1
is :func:`texel_fragments` -> :class:`TexelFragments` (the texels a view of an unwrapped capture sees),
shaded by the same physics in :func:`render_view_texture` (the inverse stage's re-render of a view).
:func:`render_result_view` (:func:`result_scene`: the posed RESULT for any number of cameras) and
:func:`mueller_images` render a RESULT folder's maps, :func:`render_demo` the optics-only sphere.
"""

from polarface.render.colour import encode_srgb, linear_rgb_from_channels, linear_srgb_to_lab
from polarface.render.demo import DemoParameters, DemoRender, render_demo
from polarface.render.fragments import FragmentRecord, SurfaceFragments, cast_fragments
from polarface.render.relight import (
    ResultScene,
    apply_edits,
    mueller_images,
    parse_edits,
    render_result_view,
    result_scene,
)
from polarface.render.renderer import ViewRender, analyzer_images, render_view, rig_lighting, shading_normals
from polarface.render.result_views import RenderOptions, render_result_outputs
from polarface.render.scene import SphereGeometry, ring_light_positions, trace_sphere
from polarface.render.shading import (
    FragmentMaterial,
    FrameTextures,
    facing_shading_normal,
    fill_empty_texels,
    fragment_material,
    lit_above_horizon,
    lobe_stokes,
)
from polarface.render.subsurface import SubsurfaceModel, entering_flux, texture_space_exitance
from polarface.render.texture_view import (
    TexelFragments,
    render_view_texture,
    shade_texels,
    texel_fragments,
    texel_material,
    texel_shading_normals,
    texture_observations,
)

__all__ = [
    "DemoParameters",
    "DemoRender",
    "FragmentMaterial",
    "FragmentRecord",
    "FrameTextures",
    "RenderOptions",
    "ResultScene",
    "SphereGeometry",
    "SubsurfaceModel",
    "SurfaceFragments",
    "TexelFragments",
    "ViewRender",
    "analyzer_images",
    "apply_edits",
    "cast_fragments",
    "encode_srgb",
    "entering_flux",
    "facing_shading_normal",
    "fill_empty_texels",
    "fragment_material",
    "linear_rgb_from_channels",
    "linear_srgb_to_lab",
    "lit_above_horizon",
    "lobe_stokes",
    "mueller_images",
    "parse_edits",
    "render_demo",
    "render_result_outputs",
    "render_result_view",
    "render_view",
    "render_view_texture",
    "result_scene",
    "rig_lighting",
    "ring_light_positions",
    "shade_texels",
    "shading_normals",
    "texel_fragments",
    "texel_material",
    "texel_shading_normals",
    "texture_observations",
    "texture_space_exitance",
    "trace_sphere",
]
