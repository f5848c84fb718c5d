"""A previous chromophore fit as the start of a new one (a dynamic frame started from the static result).

Paper main text, dynamic capture: over a short expression sequence the skin changes mainly in its
haemoglobin, and a frame's biophysical fit is regularised towards the static result. With a
:class:`BiophysicalStart`, :func:`polarface.inverse.biophysical.fit_biophysical` replaces its
coarse multi-start search by the previous maps:

* the local refinement and the blurred residual correction start from the previous parameters, and
  the prior of the full-resolution fit (``BiophysicalConfig.prior_weight``) pulls towards them
  instead of towards the upsampled coarse maps (a temporal instead of a spatial prior);
* the residual correction starts from the previous fit's fixed point: targets ``t = local(p_prev)``
  with parameters ``p_prev``, so an unchanged texel stays where the previous fit put it (its
  deblurred value) instead of being deblurred again from its blurred local fit;
* the SoG profile shapes are the previous ones when given (the layer optics of the median texel
  change little when only the haemoglobin does), so no shape is re-fitted.

The gamut screen is unchanged (its multi-start fit of suspect texels included), so an input that
no skin explains is detected as in a fit from scratch.
"""

from __future__ import annotations

import dataclasses

import torch

from polarface.inverse.biophysical.model import PARAMETER_ORDER, check_parameter_maps
from polarface.skin.heterogeneous import ProfileShapes

__all__ = ["BiophysicalStart", "start_parameters"]


@dataclasses.dataclass(frozen=True, eq=False)
class BiophysicalStart:
    """Maps of a previous fit on the same texture atlas.

    Attributes:
        parameters: ``(H, W, 4)`` volume fractions in ``PARAMETER_ORDER`` (float; values outside
            ``valid`` are ignored).
        valid: ``(H, W)`` bool, texels where ``parameters`` hold a fit.
        shapes: the previous fit's normalised SoG shapes (``(L, J)`` per layer), or None to fit them
            at the median texel as a fit from scratch does.
    """

    parameters: torch.Tensor
    valid: torch.Tensor
    shapes: ProfileShapes | None = None

    def __post_init__(self) -> None:
        params = torch.as_tensor(self.parameters)
        valid = torch.as_tensor(self.valid)
        if params.ndim != 3 or params.shape[-1] != len(PARAMETER_ORDER):
            raise ValueError(f"BiophysicalStart.parameters must be (H, W, 4); got {tuple(params.shape)}")
        if tuple(valid.shape) != tuple(params.shape[:2]) or valid.dtype != torch.bool:
            raise ValueError(
                f"BiophysicalStart.valid must be a bool (H, W) = {tuple(params.shape[:2])} map; got "
                f"{valid.dtype} {tuple(valid.shape)}"
            )
        if not bool(valid.any()):
            raise ValueError("BiophysicalStart.valid has no valid texel")
        check_parameter_maps(params[valid], "BiophysicalStart.parameters")


def start_parameters(start: BiophysicalStart, mask: torch.Tensor) -> torch.Tensor:
    """The start ``(N, 4)`` float32 of the ``N`` texels of ``mask`` ``(H, W)`` bool: the previous
    parameters where valid, the median of the valid ones elsewhere.

    Raises:
        ValueError: ``mask`` and ``start`` have different shapes (another atlas or resolution).
    """
    if tuple(mask.shape) != tuple(start.valid.shape):
        raise ValueError(
            f"the start's maps are {tuple(start.valid.shape)} texels but the input is "
            f"{tuple(mask.shape)}: a warm start needs the same texture atlas and resolution"
        )
    params = start.parameters.to(device=mask.device, dtype=torch.float32)
    valid = start.valid.to(mask.device)
    fill = params[valid].median(dim=0).values
    filled = torch.where(valid[..., None], params, fill)
    return filled[mask].contiguous()
