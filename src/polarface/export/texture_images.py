"""Texture images of a RESULT's maps for real-time material models (USD's UsdPreviewSurface, glTF PBR).

Every function takes maps in the RESULT's texture layout (``docs/geometry.md``: ``(H, W[, C])``, row 0
at ``v = 1``) and returns float64 images in [0, 1] ready for :func:`polarface.io.write_png`, in the same
layout (so a PNG row 0 is the top of the atlas, ``v = 1``). Texels outside the result mask carry no
estimate: colours are grown outwards from the mask for a few texels (bilinear lookups and mip-maps at
chart borders then never blend in junk) and the rest is filled with the masked texels' median; the
normal map is flat (tangent space ``(0, 0, 1)``) there. Mappings and their losses: ``docs/export.md``.
"""

from __future__ import annotations

import numpy as np
import torch

from polarface.geometry import UVRaster, dilate_texture, normals_from_heights
from polarface.render.colour import encode_srgb, linear_rgb_from_channels

__all__ = [
    "BORDER_TEXELS",
    "albedo_srgb_image",
    "fill_outside_mask",
    "fresnel_f0",
    "normal_map_image",
    "specular_f0",
    "tangent_space_normals",
]

#: Texels by which colours are grown outwards from the mask before the median fill.
BORDER_TEXELS = 4


def fill_outside_mask(values: np.ndarray, mask: np.ndarray, texels: int = BORDER_TEXELS) -> np.ndarray:
    """``values`` ``(H, W)`` or ``(H, W, C)`` grown ``texels`` texels out of ``mask`` (mean of valid
    8-neighbours, :func:`polarface.geometry.uv_raster.dilate_texture`), the rest set to the median of
    the masked texels; float64. A mask without a texel is refused (ValueError)."""
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        raise ValueError("argument 'mask' has no valid texel; nothing to export")
    values = np.asarray(values, dtype=np.float64)
    grown = dilate_texture(values, mask, texels)
    reached = dilate_texture(mask.astype(np.float64), mask, texels) > 0
    median = np.median(values[mask], axis=0)
    shaped = reached if values.ndim == 2 else reached[..., None]
    return np.where(shaped, grown, median)


def albedo_srgb_image(rho_sss_bar: np.ndarray, mask: np.ndarray, rig) -> np.ndarray:
    """``(H, W, 3)`` sRGB-encoded (IEC 61966-2-1) colour of the six-channel subsurface albedo.

    Linear RGB is the mean of each colour's two half bands (:func:`polarface.render.linear_rgb_from_channels`,
    the colour an unfiltered camera of ``rig`` sees), clipped to [0, 1], filled outside ``mask``.
    """
    linear = linear_rgb_from_channels(np.asarray(rho_sss_bar, dtype=np.float64), rig)
    return encode_srgb(fill_outside_mask(np.clip(linear, 0.0, 1.0), mask))


def tangent_space_normals(displacement_mm: np.ndarray, mask: np.ndarray, raster: UVRaster) -> np.ndarray:
    """``(H, W, 3)`` float64 unit normals of the displaced surface in the tangent frame ``(T, B, N)``.

    ``T`` and ``B`` are the unit directions of dP/du and dP/dv (``B`` = +v, up the atlas) and ``N`` the
    base normal, taken orthonormal: polarface's height-to-normal code
    (:func:`polarface.geometry.normals_from_heights`) evaluated in that frame, with the texel sizes
    ``s_u``, ``s_v`` (mm per texel) of ``raster``, gives ``normalize(-s_v dH/du, -s_u dH/dv, s_u s_v)``.
    Texels outside ``mask`` (and outside the raster) are ``(0, 0, 1)`` and are not used as neighbours.
    """
    height = torch.from_numpy(np.asarray(displacement_mm, dtype=np.float64))
    valid = np.asarray(mask, dtype=bool) & raster.mask
    shape = (*valid.shape, 3)

    def axis(index: int) -> torch.Tensor:
        frame = torch.zeros(shape, dtype=torch.float64)
        frame[..., index] = 1.0
        return frame

    normals = normals_from_heights(
        height,
        axis(0),
        axis(1),
        axis(2),
        torch.from_numpy(raster.texel_size_u.astype(np.float64)),
        torch.from_numpy(raster.texel_size_v.astype(np.float64)),
        torch.from_numpy(valid),
    )
    return normals.numpy()


def normal_map_image(displacement_mm: np.ndarray, mask: np.ndarray, raster: UVRaster) -> np.ndarray:
    """``(H, W, 3)`` tangent-space normal map encoded as ``0.5 n + 0.5`` (:func:`tangent_space_normals`)."""
    return 0.5 * tangent_space_normals(displacement_mm, mask, raster) + 0.5


def fresnel_f0(eta: np.ndarray | float) -> np.ndarray:
    """Normal-incidence Fresnel reflectance ``((eta - 1) / (eta + 1))^2`` of a dielectric (glTF's and
    UsdPreviewSurface's F0), float64."""
    eta = np.asarray(eta, dtype=np.float64)
    return ((eta - 1.0) / (eta + 1.0)) ** 2


def specular_f0(rho_s: np.ndarray, eta: np.ndarray) -> np.ndarray:
    """Specular reflectance at normal incidence ``rho_s ((eta - 1) / (eta + 1))^2`` (dimensionless).

    polarface's specular lobe is ``rho_s F(theta_d; eta) D G / (4 cos_i cos_o)`` (GGX ``D``, ``G``;
    :mod:`polarface.optics.pbssrdf`), so this is its albedo times Fresnel at ``theta_d = 0``.
    """
    return np.asarray(rho_s, dtype=np.float64) * fresnel_f0(eta)
