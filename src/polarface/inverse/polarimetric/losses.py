"""Losses and regularisers of the static polarimetric stage (paper Sec. 5.2, supplement
"Polarimetric inverse rendering details"); pure torch, differentiable.

Data terms, summed over samples (texel x view; the visibility V^t is the sample list itself) on
observations divided by a global ``scale`` (mean observed ``I_sss``, so the paper's weights act on
images of unit mean):

* ``L_sss = sum (I^_sss - I_sss)^2``, with ``I^_sss`` the *exact* ``2 I90`` of the model
  (no ``I_sss = S rho T+T+`` shortcut bias);
* ``L_s = sum (I^_s - I_s)^2``, ``I^_s`` including the subsurface ``-S rho T-T+ xi`` term;
* ``L_phi = sum W_phi ((I^_zeta - I_zeta)^2 + (I^_xi - I_xi)^2)`` with ``W_phi = I_sss / scale`` (the
  normalised observed subsurface intensity) and ``I_xi = I_s - S kappa R+`` (the
  supplement writes ``I_zeta`` twice); with the model's own specular part subtracted from both
  sides, ``I^_xi - I_xi = I^_s - I_s``;
* ``L_psi``: the refractive-index (DoP) loss on the *signed* components of the diffuse DoP,
  ``(I_zeta / I_sss, I_xi / I_sss)`` observed vs predicted (the magnitude
  ``sqrt(a^2 + b^2)`` is biased upward by noise); ``I_sss`` is clamped below at 5 % of ``scale``.

Regularisers (per valid texel of the patch): ``H^2`` (temporal, i.e. towards the base mesh),
``(Laplacian H)^2`` (4-neighbour, texel units, mm), and ``(x - mean_5x5(x))^2`` for eta, alpha_s and
alpha_ss (mean over the valid texels of the 5 x 5 window).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from torch.nn import functional

from polarface.inverse.polarimetric.model import SamplePrediction

__all__ = ["LossWeights", "data_losses", "laplacian_penalty", "laplacian_support", "smoothness_penalty"]


@dataclasses.dataclass(frozen=True)
class LossWeights:
    """Loss weights of the static stage; defaults are the paper's (supplement, "Regularization loss"),
    except the displacement map's two.

    ``h_temporal`` weighs ``sum H^2`` and ``h_laplacian`` ``sum (Laplacian H)^2`` (H in mm, the
    Laplacian over 4-neighbour texel steps), against data losses in units of the observation scale.
    The paper gives 1 and 1000 without H's unit. In these units they hold H to a tenth of the true
    displacement's size (demo preset: median |H| 0.001 vs 0.010 mm), so the fitted H turned the normals by
    0.035 deg median and corrected none of the reference mesh's error. The defaults 0.01 and 10 were
    chosen on the demo preset (docs/reconstruct.md, "The displacement map's regularisers"): with stereo
    geometry (and L-BFGS) the normals went 2.37 -> 1.51 deg and rho_sss_bar 3.1 -> 2.0 %; with the
    true geometry every map improved (eta 0.0070 -> 0.0061) but the normals, 0.593 -> 0.605 deg.
    """

    psi: float = 0.002
    sss: float = 1.0
    s: float = 1.0
    phi: float = 1.0
    h_temporal: float = 0.01
    h_laplacian: float = 10.0
    alpha_s: float = 200.0
    alpha_ss: float = 200.0
    eta: float = 400.0

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not (value >= 0.0 and value < float("inf")):
                raise ValueError(f"argument 'weights.{field.name}' must be finite and >= 0; got {value}")


def data_losses(
    prediction: SamplePrediction, observed: torch.Tensor, scale: float
) -> dict[str, torch.Tensor]:
    """Unweighted data losses (sums over samples and channels).

    Args:
        prediction: model output for S samples, ``(S, 3)`` tensors.
        observed: ``(S, 3, 3)`` ``[I_sss, I_zeta, I_s]`` x channel.
        scale: observation scale (> 0), radiance.

    Returns:
        ``{"sss", "s", "phi", "psi"}`` scalar tensors.
    """
    if not scale > 0:
        raise ValueError(f"argument 'scale' must be > 0; got {scale}")
    inv = 1.0 / scale
    obs_sss, obs_zeta, obs_s = observed[:, 0], observed[:, 1], observed[:, 2]
    r_sss = (prediction.i_sss - obs_sss) * inv
    r_zeta = (prediction.i_zeta - obs_zeta) * inv
    r_s = (prediction.i_s - obs_s) * inv
    w_phi = (obs_sss * inv).clamp_min(0.0)
    floor = 0.05 * scale
    denom_obs = obs_sss.clamp_min(floor)
    denom_pred = prediction.i_sss.clamp_min(floor)
    xi_pred = prediction.i_s - prediction.specular_s1
    xi_obs = obs_s - prediction.specular_s1
    psi = (prediction.i_zeta / denom_pred - obs_zeta / denom_obs) ** 2 + (
        xi_pred / denom_pred - xi_obs / denom_obs
    ) ** 2
    return {
        "sss": (r_sss * r_sss).sum(),
        "s": (r_s * r_s).sum(),
        "phi": (w_phi * (r_zeta * r_zeta + r_s * r_s)).sum(),
        "psi": psi.sum(),
    }


def smoothness_penalty(value: torch.Tensor, mask: torch.Tensor, window: int = 5) -> torch.Tensor:
    """``sum_valid (x - mean_window(x))^2`` over a ``(h, w)`` map (mean over valid texels of the window)."""
    if value.shape != mask.shape or value.ndim != 2:
        raise ValueError(
            f"arguments 'value' {tuple(value.shape)} and 'mask' {tuple(mask.shape)} must be equal (h, w)"
        )
    weight = mask.to(value.dtype)[None, None]
    pad = window // 2
    total = functional.avg_pool2d(
        (value * mask)[None, None], window, stride=1, padding=pad, count_include_pad=True
    )
    count = functional.avg_pool2d(weight, window, stride=1, padding=pad, count_include_pad=True)
    mean = (total / count.clamp_min(1e-12))[0, 0]
    return (((value - mean) ** 2) * weight[0, 0]).sum()


def laplacian_penalty(height: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``sum (Laplacian H)^2`` (4-neighbour, per texel step) over texels whose 4 neighbours are valid."""
    if height.shape != mask.shape or height.ndim != 2:
        raise ValueError(
            f"arguments 'height' {tuple(height.shape)} and 'mask' {tuple(mask.shape)} must be equal (h, w)"
        )
    if min(height.shape) < 3:
        return height.sum() * 0.0
    centre = height[1:-1, 1:-1]
    lap = height[:-2, 1:-1] + height[2:, 1:-1] + height[1:-1, :-2] + height[1:-1, 2:] - 4.0 * centre
    return ((lap * lap) * laplacian_support(mask).to(height.dtype)).sum()


def laplacian_support(mask: torch.Tensor | np.ndarray) -> torch.Tensor | np.ndarray:
    """``(h - 2, w - 2)`` bool: interior texels whose 4 neighbours are all valid (where
    :func:`laplacian_penalty` counts); torch tensor or numpy array in, same kind out."""
    return mask[1:-1, 1:-1] & mask[:-2, 1:-1] & mask[2:, 1:-1] & mask[1:-1, :-2] & mask[1:-1, 2:]
