"""Texture-space re-render of one view of an unwrapped capture, from the renderer's stages.

The inverse stages compare observations with the image formation *on the texture atlas*: every texel
that a view sees (:class:`polarface.texture.UnwrapStore`) is one fragment (:class:`TexelFragments`;
the image-space counterpart is :class:`polarface.render.fragments.SurfaceFragments`), shaded by the
same physics as the camera renderer (:mod:`polarface.render.shading`, :mod:`polarface.optics`):

* **Entry**: :func:`polarface.render.subsurface.visible_entry_flux` — the flux entering the skin from
  every LED module whose shadow ray from the texel is free (the store's ``lit``), with the entry Fresnel
  transmission and its polarization in the LED polarizer frame of the rig's *reference* camera up
  (:attr:`polarface.texture.ViewSpec.reference_up`), as the simulator's texture-space entry flux.
* **Local subsurface model** (paper Sec. 5.2): the exitance is ``E = rho_sss_bar Phi`` per channel (no
  diffusion), and :func:`polarface.optics.subsurface_exit_stokes` turns it into Stokes radiance in the
  frame of the *view's own* camera up (zero where the shading normal faces away from the camera).
* **Specular and single scattering**: :func:`polarface.render.shading.lobe_stokes` (full Mueller
  matrices of :func:`polarface.optics.render_polarimetric`, per lit module, view camera up).

The observations are those of the unwrap store (``src/polarface/texture/unwrap_store.py``):
``I_sss = s0 - s1``, ``I_zeta = -s2``, ``I_s = s1`` per channel. Positions are those of the rest
mesh (model frame, mm): the displacement only turns the shading normal (:func:`texel_shading_normals`).
Radiance is in the light intensity unit per mm^2 per sr. Maps follow the ``SIM/ground_truth/maps``
conventions: ``eta, alpha_s, alpha_ss, rho_s, rho_ss, displacement_mm`` ``(Ht, Wt)`` and
``rho_sss_bar`` ``(Ht, Wt, 6)``, float.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from polarface._validation import trusted_inputs
from polarface.optics.image_formation import subsurface_exit_stokes
from polarface.render.fragments import FragmentRecord
from polarface.render.renderer import shading_normals as _raster_shading_normals
from polarface.render.shading import FragmentMaterial, lobe_stokes
from polarface.render.subsurface import visible_entry_flux
from polarface.results import POLARIMETRIC_MAPS, RHO_SSS_BAR
from polarface.texture import UnwrapStore, ViewSpec

__all__ = [
    "TexelFragments",
    "render_view_texture",
    "shade_texels",
    "texel_fragments",
    "texel_material",
    "texel_shading_normals",
    "texture_observations",
]

#: The parameter maps a texture-space render reads (``rho_sss_bar`` has 6 channels, the others one).
MAP_NAMES = (*POLARIMETRIC_MAPS, RHO_SSS_BAR)


@dataclasses.dataclass(frozen=True, eq=False)
class TexelFragments(FragmentRecord):
    """The atlas texels one view sees (``N`` fragments), read from an unwrap store.

    Attributes:
        row, col: ``(N,)`` int64 texel indices in the full atlas (row 0 = v 1,
            ``src/polarface/geometry/uv_raster.py``).
        position: ``(N, 3)`` float64 texel position on the rest mesh, model frame, mm.
        geometric_normal: ``(N, 3)`` float64 unit normal of the rest mesh (no displacement), model frame.
        lit: ``(N, K)`` bool, the shadow ray from the texel to LED module ``k`` is free.
        observed: ``(N, 3, 3)`` float32 observations ``[I_sss, I_zeta, I_s]`` x the view's channels
            (radiance, light intensity unit per mm^2 per sr).
    """

    row: np.ndarray
    col: np.ndarray
    position: np.ndarray
    geometric_normal: np.ndarray
    lit: np.ndarray
    observed: np.ndarray


def texel_fragments(
    unwrap: UnwrapStore, view_index: int, rows: slice = slice(None), cols: slice = slice(None)
) -> TexelFragments:
    """The fragments of view ``view_index`` in a texture region: texels inside the atlas and ``valid``
    for the view, in row-major order (unchecked ``view_index``: see :func:`render_view_texture`)."""
    geometry = unwrap.geometry(rows, cols)
    obs, valid, lit = unwrap.read(rows, cols, [view_index])
    r, c = np.nonzero(valid[0] & geometry.mask)
    return TexelFragments(
        row=(r + (rows.start or 0)).astype(np.int64),
        col=(c + (cols.start or 0)).astype(np.int64),
        position=geometry.position[r, c].astype(np.float64),
        geometric_normal=geometry.normal[r, c].astype(np.float64),
        lit=np.asarray(lit[0, r, c], bool),
        observed=obs[0, r, c],
    )


def texel_material(
    fragments: TexelFragments,
    maps: dict[str, np.ndarray],
    normal: np.ndarray,
    channels: tuple[int, ...],
) -> FragmentMaterial:
    """float64 :class:`FragmentMaterial` of the fragments from full-atlas ``maps`` and ``normal``.

    ``normal`` is the ``(Ht, Wt, 3)`` shading-normal map (model frame, used as given, not flipped);
    ``eta`` is clamped to ``>= 1 + 1e-6`` and the roughnesses to ``>= 1e-3`` (as the renderer); the
    lobe albedos are used as given. ``exitance`` holds the local-model albedo ``rho_sss_bar`` of the
    view's ``channels`` ``(N, 3)`` until :func:`shade_texels` replaces it with ``rho_sss_bar Phi``.
    """
    r, c = fragments.row, fragments.col
    t = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float64))  # noqa: E731
    column = lambda name, low: t(np.maximum(maps[name][r, c], low))[:, None]  # noqa: E731
    return FragmentMaterial(
        normal=t(normal[r, c]),
        geometric_normal=t(fragments.geometric_normal),
        eta=column("eta", 1.0 + 1e-6),
        alpha_s=column("alpha_s", 1e-3),
        alpha_ss=column("alpha_ss", 1e-3),
        rho_s=t(maps["rho_s"][r, c])[:, None],
        rho_ss=t(maps["rho_ss"][r, c])[:, None],
        exitance=t(maps["rho_sss_bar"][r, c][:, list(channels)]),
    )


def shade_texels(fragments: TexelFragments, material: FragmentMaterial, view: ViewSpec) -> torch.Tensor:
    """``(N, 3, 4)`` float64 Stokes radiance (view camera frame) of the fragments in the view's channels.

    ``material.exitance`` carries ``rho_sss_bar`` ``(N, 3)`` (:func:`texel_material`); the subsurface
    term is ``E = rho_sss_bar Phi`` with ``Phi`` entering under the reference up, leaving under the view
    up; the lobes are added per lit module (module docstring). Inputs are trusted (built here).
    """
    position = torch.from_numpy(fragments.position)
    centre = torch.tensor(view.camera_center, dtype=torch.float64)
    up = torch.tensor(view.camera_up, dtype=torch.float64)
    lights = np.asarray(view.light_positions, np.float64)
    intensity = torch.tensor(view.light_intensity, dtype=torch.float64)  # (K, 3)
    with trusted_inputs():
        flux = visible_entry_flux(
            material.normal,
            position,
            torch.tensor(view.reference_up, dtype=torch.float64),
            lights,
            intensity,
            material.eta,
            fragments.lit,
        )
        exitance = material.exitance * flux
        to_camera = centre - position
        facing = (material.normal * to_camera).sum(-1) > 0.0
        exit_stokes = subsurface_exit_stokes(material.normal, position, centre, up, material.eta)
        stokes = torch.where(facing[:, None, None], exitance[..., None] * exit_stokes, 0.0)
        shaded = dataclasses.replace(material, exitance=exitance)
        return lobe_stokes(shaded, position, centre, up, lights, fragments.lit, intensity, stokes)


def texture_observations(stokes: torch.Tensor) -> np.ndarray:
    """``(N, 3, C)`` float32 observations ``[I_sss, I_zeta, I_s] = [s0 - s1, -s2, s1]`` of Stokes
    ``(N, C, 4)`` (camera frame), the layout of the unwrap store's ``obs``."""
    s0, s1, s2 = stokes[..., 0], stokes[..., 1], stokes[..., 2]
    return torch.stack([s0 - s1, -s2, s1], dim=1).numpy().astype(np.float32)


def texel_shading_normals(unwrap: UnwrapStore, displacement_mm: np.ndarray) -> np.ndarray:
    """``(Ht, Wt, 3)`` float32 unit shading normals (model frame) of the rest mesh displaced by
    ``displacement_mm`` ``(Ht, Wt)`` (mm along the base normal); ValueError on a wrong shape."""
    geometry = unwrap.geometry()
    if np.shape(displacement_mm) != geometry.mask.shape:
        shape = np.shape(displacement_mm)
        raise ValueError(f"argument 'displacement_mm' must have shape {geometry.mask.shape}; got {shape}")
    with torch.no_grad():
        return _raster_shading_normals(geometry, displacement_mm).astype(np.float32)


def _check_inputs(unwrap: UnwrapStore, maps: dict[str, np.ndarray], view_index: int, normal) -> None:
    count = len(unwrap.views)
    if not 0 <= view_index < count:
        raise ValueError(f"argument 'view_index' must be in [0, {count}); got {view_index}")
    resolution = unwrap.resolution
    for name in MAP_NAMES:
        if name not in maps:
            raise ValueError(f"argument 'maps' lacks '{name}'")
        expected = (*resolution, 6) if name == "rho_sss_bar" else resolution
        shape = np.shape(maps[name])
        if shape != expected:
            raise ValueError(f"argument 'maps' entry '{name}' must have shape {expected}; got {shape}")
    if normal is not None and np.shape(normal) != (*resolution, 3):
        raise ValueError(f"argument 'normal' must have shape {(*resolution, 3)}; got {np.shape(normal)}")


def render_view_texture(
    unwrap: UnwrapStore,
    maps: dict[str, np.ndarray],
    view_index: int,
    *,
    normal: np.ndarray | None = None,
    patch: int = 128,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observed and re-rendered observations of one view on the texture.

    Args:
        unwrap: the unwrapped capture; maps: parameter maps (module docstring); view_index: view to render;
        normal: optional precomputed :func:`texel_shading_normals` ``(Ht, Wt, 3)``; patch: texels per side
            processed at once (memory bound).

    Returns:
        ``observed (Ht, Wt, 3, 3)`` and ``predicted (Ht, Wt, 3, 3)`` float32 (``[I_sss, I_zeta, I_s]`` x
        the view's channels; zero where not visible) and ``valid (Ht, Wt)`` bool (atlas texels the view
        sees).

    Raises:
        ValueError: naming ``view_index``, ``maps`` (missing or mis-shaped map), ``displacement_mm`` or
            ``normal``.
    """
    _check_inputs(unwrap, maps, view_index, normal)
    view = unwrap.views[view_index]
    height, width = unwrap.resolution
    normal = texel_shading_normals(unwrap, maps["displacement_mm"]) if normal is None else normal
    observed = np.zeros((height, width, 3, 3), np.float32)
    predicted = np.zeros_like(observed)
    valid = np.zeros((height, width), bool)
    for rows, cols in unwrap.patches(patch):
        fragments = texel_fragments(unwrap, view_index, rows, cols)
        if fragments.count == 0:
            continue
        material = texel_material(fragments, maps, normal, view.channels)
        with torch.no_grad():
            stokes = shade_texels(fragments, material, view)
        r, c = fragments.row, fragments.col
        predicted[r, c] = texture_observations(stokes)
        observed[r, c] = fragments.observed
        valid[r, c] = True
    return observed, predicted, valid
