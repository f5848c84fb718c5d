"""Polarimetric shading of surface fragments with the pBSSRDF image formation.

The last stage of the renderer (:mod:`polarface.render.renderer`). Per fragment
(:class:`polarface.render.fragments.SurfaceFragments`) the texture stack of the frame
(:class:`FrameTextures`: pBSSRDF parameters, shading normal, diffused subsurface exitance) is read
bilinearly at the fragment's ``uv`` (:func:`fragment_material`);
:func:`polarface.optics.subsurface_exit_stokes` applies the exit Fresnel transmission with its
polarization to the exitance, and
the specular and single-scattering lobes of :func:`polarface.optics.render_polarimetric` are added for
each LED module times its shadow-ray visibility (:func:`lobe_stokes`; the image formation is linear in
the lights), computing only the Stokes components the camera keeps. The physics itself lives in
:mod:`polarface.optics.image_formation` and :mod:`polarface.optics.lobes` (its compiled loops in
:mod:`polarface.render.lobe_kernel`).

Frames and units: world mm; Stokes vectors in the camera frame (``docs/conventions.md``); radiance in
LED intensity units per mm^2 per sr.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from scipy import ndimage

from polarface._validation import trusted_inputs
from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import sample_texture
from polarface.optics.lobes import ShadowTest
from polarface.optics.pbssrdf import SURFACE_PARAMETER_NAMES
from polarface.render.lobe_kernel import add_lobes_fused

__all__ = [
    "PARAMETER_ORDER",
    "FragmentMaterial",
    "FrameTextures",
    "facing_shading_normal",
    "fill_empty_texels",
    "fragment_material",
    "lit_above_horizon",
    "lobe_stokes",
    "module_intensities",
]

#: Order of the parameter channels stacked in :attr:`FrameTextures.stack`.
PARAMETER_ORDER = SURFACE_PARAMETER_NAMES
#: First channel of the shading normal and of the exitance in :attr:`FrameTextures.stack`.
NORMAL_CHANNEL = len(PARAMETER_ORDER)
EXITANCE_CHANNEL = NORMAL_CHANNEL + 3


def fill_empty_texels(texture: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Copy of ``texture`` ``(H, W[, C])`` whose texels outside ``mask`` take their nearest valid value.

    Keeps bilinear lookups near atlas seams from blending in empty (zero) texels.
    """
    if mask.all():
        return texture.copy()
    _, (rows, cols) = ndimage.distance_transform_edt(~mask, return_indices=True)
    return texture[rows, cols]


@dataclasses.dataclass(frozen=True, eq=False)
class FrameTextures:
    """Everything a camera needs per texel for one frame, as one stacked float32 tensor.

    Attributes:
        stack: ``(Ht, Wt, 5 + 3 + 6)``: the parameters in :data:`PARAMETER_ORDER`, the world-space
            unit shading normal of the posed frame (from the displacement map), and the six-channel
            diffused subsurface exitance (light intensity unit per mm^2) — empty texels filled.
    """

    stack: torch.Tensor

    @classmethod
    def build(
        cls,
        parameters: dict[str, np.ndarray],
        shading_normal: np.ndarray,
        exitance: np.ndarray,
        mask: np.ndarray,
    ) -> FrameTextures:
        """Stack and fill ``parameters`` (name -> ``(Ht, Wt)``), normals ``(Ht, Wt, 3)`` and the
        exitance ``(Ht, Wt, 6)``."""
        layers = [parameters[name][..., None] for name in PARAMETER_ORDER]
        stack = np.concatenate([*layers, shading_normal, exitance], axis=-1).astype(np.float32)
        return cls(torch.from_numpy(fill_empty_texels(stack, mask)))

    def without_subsurface(self) -> FrameTextures:
        """The same textures with the subsurface exitance zeroed: a camera then sees the surface
        reflection alone (the specular and single-scattering lobes), the specular image of a view."""
        stack = self.stack.clone()
        stack[..., len(PARAMETER_ORDER) + 3:] = 0.0
        return FrameTextures(stack)


@dataclasses.dataclass(frozen=True, eq=False)
class FragmentMaterial:
    """The material of ``N`` fragments, in the dtype of the shading (float32 or float64).

    Attributes:
        normal: ``(N, 3)`` unit shading normal, world frame, facing the camera
            (:func:`facing_shading_normal`).
        geometric_normal: ``(N, 3)`` unit geometric normal flipped towards the camera, world frame.
        eta: ``(N, 1)`` refractive index, at least ``1 + 1e-6``.
        alpha_s, alpha_ss: ``(N, 1)`` GGX roughness of the specular and single-scattering lobes, >= 1e-3.
        rho_s, rho_ss: ``(N, 1)`` lobe albedos, >= 0.
        exitance: ``(N, C)`` diffused subsurface exitance of the rendered channels (intensity per mm^2).
    """

    normal: torch.Tensor
    geometric_normal: torch.Tensor
    eta: torch.Tensor
    alpha_s: torch.Tensor
    alpha_ss: torch.Tensor
    rho_s: torch.Tensor
    rho_ss: torch.Tensor
    exitance: torch.Tensor


def facing_shading_normal(
    raw_normal: torch.Tensor, geometric: torch.Tensor, position: torch.Tensor, camera_center: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(shading normal, geometric normal)``, each ``(N, 3)`` unit, world frame, facing the camera.

    ``raw_normal`` (the bilinear read of the normal map, not unit) is normalised; where it tilts past
    the view direction (silhouettes: ``n . w_o <= 1e-3``) the geometric normal, flipped towards the
    camera, replaces it. ``position`` ``(N, 3)`` and ``camera_center`` ``(3,)`` in mm.
    """
    normal = raw_normal / raw_normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    to_camera = camera_center - position
    to_camera = to_camera / to_camera.norm(dim=-1, keepdim=True)
    facing = (normal * to_camera).sum(-1, keepdim=True)
    geometric = geometric * torch.where((geometric * to_camera).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    return torch.where(facing > 1e-3, normal, geometric), geometric


def fragment_material(
    textures: FrameTextures,
    uv: torch.Tensor,
    geometric_normal: torch.Tensor,
    position: torch.Tensor,
    camera_center: torch.Tensor,
    channels: tuple[int, ...],
    *,
    trusted: bool = True,
) -> FragmentMaterial:
    """Read ``textures`` at ``uv`` ``(N, 2)`` and build the fragments' material.

    The texture stack is read in float32 and cast to the dtype of ``position`` ``(N, 3)`` (mm).
    ``channels`` index the six exitance channels to render. ``trusted`` skips the value checks of the
    texture read (the stack is built and filled by :meth:`FrameTextures.build`).
    """
    if trusted:
        with trusted_inputs():
            sampled = sample_texture(textures.stack, uv)
    else:
        sampled = sample_texture(textures.stack, uv)
    sampled = sampled.to(position.dtype)
    normal, geometric = facing_shading_normal(
        sampled[:, NORMAL_CHANNEL : NORMAL_CHANNEL + 3], geometric_normal, position, camera_center
    )
    params = {name: sampled[:, i : i + 1] for i, name in enumerate(PARAMETER_ORDER)}
    exitance = sampled[:, torch.tensor([EXITANCE_CHANNEL + c for c in channels])]
    return FragmentMaterial(
        normal=normal,
        geometric_normal=geometric,
        eta=params["eta"].clamp_min(1.0 + 1e-6),
        alpha_s=params["alpha_s"].clamp_min(1e-3),
        alpha_ss=params["alpha_ss"].clamp_min(1e-3),
        rho_s=params["rho_s"].clamp_min(0.0),
        rho_ss=params["rho_ss"].clamp_min(0.0),
        exitance=exitance,
    )


def module_intensities(light_intensity: float | np.ndarray, modules: int,
                       dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """``(K, 1)`` radiant intensity of each of the ``modules`` LED modules, from one value for all or a
    ``(K,)`` array (:func:`polarface.render.rig_lighting`), spectrally flat: the LEDs' spectrum is the
    rig's ``led_spd`` (white-normalised channels).

    Raises:
        ValueError: an array of another length, or a negative or non-finite value.
    """
    values = np.asarray(light_intensity, dtype=np.float64)
    if values.ndim == 0:
        values = np.full(int(modules), float(values))
    if values.shape != (int(modules),) or not np.isfinite(values).all() or (values < 0).any():
        raise ValueError(f"argument 'light_intensity' must be one value or {modules} (one per module), "
                         f"finite and >= 0; got shape {values.shape}")
    return torch.from_numpy(values[:, None].copy()).to(dtype)


def lit_above_horizon(
    caster: RayCaster,
    points: np.ndarray,
    geometric_normal: np.ndarray,
    shading_normal: np.ndarray,
    light_positions: np.ndarray,
    *,
    margin: float = 1e-4,
) -> np.ndarray:
    """``(N, K)`` bool shadow-ray visibility of ``K`` LED modules from ``N`` surface points, as
    :meth:`RayCaster.shadow_rays`, with rays cast only towards the modules above the horizon of each
    point's shading normal.

    A module below it (``n_shading . w_i < -margin``, in float64) gets no ray and is reported unlit:
    what it would add is zero whatever its visibility — the entry flux of
    :func:`polarface.optics.subsurface_entry_flux` (``max(n . w_i, 0)``) and the specular and
    single-scattering lobes of :func:`lobe_stokes` (their front test ``n . w_i > 0``) — so the
    entering flux and the rendered Stokes are the same as with every ray cast. ``margin`` covers the
    float32 rounding of a cosine (~1e-7). Worth it where many modules are below the horizon (every
    texel of the head: about a third of the rays); a camera's fragments face its nearby modules.

    Args:
        caster: ray caster of the posed mesh; points: ``(N, 3)`` mm on it.
        geometric_normal: ``(N, 3)`` unit face normals (the side of the shadow rays' offset).
        shading_normal: ``(N, 3)`` unit shading normals (float32 or float64).
        light_positions: ``(K, 3)`` mm.
    """
    points = np.asarray(points, np.float64)
    lights = np.asarray(light_positions, np.float64)
    to_light = lights[None, :, :] - points[:, None, :]  # (N, K, 3)
    cosine = np.einsum("nc,nkc->nk", np.asarray(shading_normal, np.float64), to_light)
    above = cosine > -margin * np.linalg.norm(to_light, axis=-1)
    rows, modules = np.nonzero(above)
    visible = np.zeros(above.shape, bool)
    if rows.size:
        visible[rows, modules] = caster.shadow_rays_indexed(points, geometric_normal, lights, rows, modules)
    return visible


def lobe_stokes(
    material: FragmentMaterial,
    position: torch.Tensor,
    camera_center: torch.Tensor,
    camera_up: torch.Tensor,
    light_positions: np.ndarray,
    visible: np.ndarray | ShadowTest,
    intensity: torch.Tensor,
    stokes: torch.Tensor,
    *,
    light_stokes: torch.Tensor | None = None,
    skip_unlit: bool = True,
) -> torch.Tensor:
    """``stokes`` plus the specular and single-scattering Stokes ``(N, C, S)`` of every visible LED.

    :func:`polarface.optics.lobes.add_lobes` with the fragments' material, in compiled loops
    (:func:`polarface.render.lobe_kernel.add_lobes_fused`: its expressions, equal to it to float
    rounding): the lobes of :func:`polarface.optics.render_polarimetric`, light by light, with the view
    geometry computed once; only the ``S`` components of ``stokes`` are computed (``S = 1``: the first
    row of the Mueller chain, ``s0``, for an RGB camera).

    Args:
        material: the fragments' material; position: ``(N, 3)`` mm (float32 or float64: the dtype of
            the shading).
        camera_center: ``(3,)`` mm; camera_up: ``(3,)`` world up of the camera (Stokes frame).
        light_positions: ``(K, 3)`` float64 LED module positions, mm.
        visible: ``(N, K)`` bool shadow-ray visibility of each module; or a
            :data:`~polarface.optics.lobes.ShadowTest` called
            per module with the fragments that it lights from the front (``n . w_i > 0`` and
            ``n . w_o > 0`` with the shading normal, in the shading's dtype: elsewhere both lobes are
            exactly 0), so shadow rays whose answer cannot matter are never cast.
        intensity: ``(1, C)`` radiant intensity of every module (``(1, 1)`` broadcasts over channels),
            or ``(K, C)`` one row per module.
        stokes: ``(N, C, S)`` the Stokes to add to (e.g. the subsurface term), ``1 <= S <= 4``: the
            first ``S`` components are accumulated, each the same sum as in the full vector.
        light_stokes: ``(4,)`` or ``(K, 4)`` incident Stokes vector of the LEDs in their own frame
            (default: the image formation's default ``[1, 1, 0, 0]``).
        skip_unlit: skip modules that no fragment sees (they add zero).

    Raises:
        ValueError: shapes that do not match, a ``visible`` test answering the wrong shape, and (outside
            :func:`polarface._validation.trusted_inputs`) the value checks of ``render_polarimetric``.
    """
    return add_lobes_fused(
        stokes, material.normal, position, camera_center, camera_up, light_positions, intensity,
        material.eta, material.alpha_s, material.alpha_ss, material.rho_s, material.rho_ss, visible,
        light_stokes=light_stokes, skip_unlit=skip_unlit,
    )
