"""Coarse-to-fine resampling of the chromophore fit's maps (:mod:`polarface.inverse.biophysical.fit`): the
mask-weighted coarse maps its multi-start search runs on, and their upsampling to the valid texels as the
full-resolution fit's start and prior."""

from __future__ import annotations

import torch
import torch.nn.functional as nnf

__all__ = ["downsample_masked", "upsample_masked", "upsampled_coarse"]


def downsample_masked(maps: torch.Tensor, mask: torch.Tensor, factor: int
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Mask-weighted area average ``(H, W, C)`` -> ``(H/f, W/f, C)`` and the coarse mask."""
    weight = mask.to(maps.dtype)[None, None]
    summed = nnf.avg_pool2d(
        (maps * mask.to(maps.dtype)[..., None]).permute(2, 0, 1)[None], factor, ceil_mode=True
    )
    coverage = nnf.avg_pool2d(weight, factor, ceil_mode=True)
    coarse = (summed / coverage.clamp_min(1e-12))[0].permute(1, 2, 0)
    return coarse, coverage[0, 0] > 0.25


def upsample_masked(
    maps: torch.Tensor, mask: torch.Tensor, shape: tuple[int, int], fill: torch.Tensor
) -> torch.Tensor:
    """Mask-normalised bilinear upsampling ``(h, w, C)`` -> ``(H, W, C)``; holes take ``fill``."""
    weight = mask.to(maps.dtype)[None, None]
    values = (maps * weight[0, 0][..., None]).permute(2, 0, 1)[None]
    up = nnf.interpolate(values, size=shape, mode="bilinear", align_corners=False)
    up_weight = nnf.interpolate(weight, size=shape, mode="bilinear", align_corners=False)
    out = (up / up_weight.clamp_min(1e-12))[0].permute(1, 2, 0)
    return torch.where(up_weight[0, 0][..., None] > 1e-6, out, fill.to(out))


def upsampled_coarse(coarse: torch.Tensor, coarse_mask: torch.Tensor, mask_b: torch.Tensor) -> torch.Tensor:
    """The coarse maps ``(h, w, 4)`` on ``coarse_mask`` ``(h, w)`` bool upsampled to the ``N`` texels of
    ``mask_b`` ``(H, W)`` bool: ``(N, 4)`` (holes: the coarse median), the full-resolution fit's start and
    prior."""
    median = coarse[coarse_mask].median(dim=0).values
    return upsample_masked(coarse, coarse_mask, tuple(mask_b.shape), median.float())[mask_b]
