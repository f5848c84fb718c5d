"""The per-frame (dynamic) polarimetric loss (paper supplement, "Dynamic Inverse Rendering Details"),
optimised per patch by :func:`polarface.inverse.polarimetric.dynamic.fit_dynamic_frame` over
``rho_s^t, rho_ss^t, rho_sss_bar^t`` (6 channels) and the displacement ``H^t`` (mm) of a frame, with the
refractive index and both roughnesses fixed from the static result:

    w_sss L_sss + w_s L_s + w_phi L_phi + L_reg~   (defaults 1, 1, 0.2)

with the static stage's data terms (:mod:`polarface.inverse.polarimetric.losses`; the fused kernel or
the torch reference, :mod:`polarface.inverse.polarimetric.engines`; the DoP term ``L_psi`` only
constrains eta and is left out) and the regulariser (:func:`dynamic_regularisers`, per atlas texel of
the patch; superscript 0 = the static maps)

    L_reg~ = 0.001 sum (H^t - H^0)^2 + 500 sum (Laplacian (H^t - H^0))^2
             + 1.0 sum (rho_s^t - rho_s^0)^2 + 1.0 sum (rho_ss^t - rho_ss^0)^2   (paper: 0.01 each)
             + 0.01 sum_texel W^t sum_c (rho_sss_bar^t - rho_sss_bar^0)^2,
    W^t = |mean_c rho_sss_bar^0 - mean_c rho_sss_bar^t|   (per texel, mean over the 6 channels).

Choices where the supplement says "similar to" the static terms: both H terms act on the *change*
``H^t - H^0`` from the static displacement (the skin's fine relief moves with the tracked surface;
the static stage pulls H towards 0, the base mesh): the temporal term on its square, the spatial term
on its 4-neighbour Laplacian (:func:`~polarface.inverse.polarimetric.losses.laplacian_penalty`). A
Laplacian of ``H^t`` itself would, at weight 500 against 0.001, flatten the static relief in every
frame, most where the data are weak: on the simulator's demo frame 0 with the true static maps as
``H^0`` it raised the median displacement error from 0.0023 mm to 0.0075 mm. ``W^t`` is
recomputed from the current estimate at every step and treated as a constant (no gradient flows
through it): it is 0 where the subsurface albedo has not changed, so a start at the static maps is
free to move, and it grows with the change, so the term acts as a soft ``|change|^3`` pull on large
deviations of the channels' mean. Like the static loss, the patch loss is divided by the number of
atlas texels of the patch (with its halo); where the frame's fit crops a patch to the texels its views
see (``DynamicConfig.seen_margin``), by those of the uncropped patch, so the objective keeps its scale:
RMSprop's steps depend on it through its ``eps`` (doubling the loss moved the demo frames' maps as much
as the crop did with its own count, docs/dynamic.md).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import torch

from polarface.inverse.polarimetric.config import PARAMETER_NAMES, maps_from_raw
from polarface.inverse.polarimetric.fused import fused_data_loss, pack_parameters
from polarface.inverse.polarimetric.losses import LossWeights, data_losses, laplacian_penalty
from polarface.inverse.polarimetric.model import render_samples
from polarface.inverse.polarimetric.problem import PatchProblem

__all__ = [
    "DYNAMIC_VARIABLES",
    "FIXED_VARIABLES",
    "DynamicPatchProblem",
    "DynamicWeights",
    "dynamic_regularisers",
]

#: The maps optimised per frame; the other :data:`PARAMETER_NAMES` (eta, alpha_s, alpha_ss) stay static.
DYNAMIC_VARIABLES = ("rho_s", "rho_ss", "rho_sss_bar", "displacement_mm")
#: The maps that stay static.
FIXED_VARIABLES = tuple(name for name in PARAMETER_NAMES if name not in DYNAMIC_VARIABLES)


@dataclasses.dataclass(frozen=True)
class DynamicWeights:
    """Loss weights of the per-frame fit (defaults: the paper's supplement, dynamic stage).

    Attributes:
        sss, s, phi: weights of the data terms ``L_sss, L_s, L_phi``.
        h_temporal: weight of ``sum (H^t - H^0)^2`` (mm^2); h_laplacian: of
            ``sum (Laplacian (H^t - H^0))^2`` (mm^2, per texel step).
        rho_s_temporal, rho_ss_temporal: of ``sum (rho^t - rho^0)^2`` of the two lobe albedos. Paper:
            0.01 each; default 1.0 (a weight's effect depends on the loss normalisation, here
            observations divided by their mean ``I_sss`` and summed over samples). Measured on the
            demo preset through the whole pipeline (stereo geometry, tracked meshes): at 0.01 the
            lobe albedos follow each frame's noise, rho_s changes by 3.3 % (median) from frame to
            frame where the truth is constant (target 2 %); at 1.0 by 0.3 % (frame 5: rho_s median
            relative error against the truth 37.4 % vs 38.8 % at 0.01, i.e. no accuracy lost).
        rho_sss_bar_temporal: of ``sum W^t sum_c (rho_sss_bar^t - rho_sss_bar^0)^2`` (module docstring).
    """

    sss: float = 1.0
    s: float = 1.0
    phi: float = 0.2
    h_temporal: float = 0.001
    h_laplacian: float = 500.0
    rho_s_temporal: float = 1.0
    rho_ss_temporal: float = 1.0
    rho_sss_bar_temporal: float = 0.01

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not (value >= 0.0 and value < float("inf")):
                raise ValueError(f"argument 'weights.{field.name}' must be finite and >= 0; got {value}")

    def data_weights(self) -> LossWeights:
        """The data-term weights as static :class:`LossWeights` (``psi = 0``; its regularisers unused)."""
        return LossWeights(psi=0.0, sss=self.sss, s=self.s, phi=self.phi)


def dynamic_regularisers(
    current: Mapping[str, torch.Tensor], reference: Mapping[str, torch.Tensor], mask: torch.Tensor
) -> dict[str, torch.Tensor]:
    """The unweighted regularisers of ``L_reg~`` (module docstring) over the valid texels of a patch.

    Args:
        current, reference: the frame's and the static maps, ``rho_s``, ``rho_ss``, ``displacement_mm``
            ``(h, w)`` and ``rho_sss_bar`` ``(h, w, 6)`` (mm for H); mask: ``(h, w)`` bool valid texels.

    Returns:
        ``h_temporal, h_laplacian, rho_s_temporal, rho_ss_temporal, rho_sss_bar_temporal`` scalar
        tensors. ``W^t`` of the last term is detached (a constant for the gradient).
    """
    weight = mask.to(current["rho_s"].dtype)
    height_change = current["displacement_mm"] - reference["displacement_mm"]
    if height_change.shape != mask.shape:
        raise ValueError(
            f"argument 'current' displacement_mm {tuple(height_change.shape)} must match 'mask' "
            f"{tuple(mask.shape)}"
        )
    squared = lambda name: (((current[name] - reference[name]) ** 2) * weight).sum()  # noqa: E731
    change = current["rho_sss_bar"] - reference["rho_sss_bar"]
    w_t = change.mean(dim=-1).abs().detach()
    return {
        "h_temporal": ((height_change * height_change) * weight).sum(),
        "h_laplacian": laplacian_penalty(height_change, mask),
        "rho_s_temporal": squared("rho_s"),
        "rho_ss_temporal": squared("rho_ss"),
        "rho_sss_bar_temporal": ((change * change).sum(-1) * w_t * weight).sum(),
    }


class DynamicPatchProblem:
    """The per-frame loss of one patch: the static :class:`PatchProblem`'s samples and normals-from-H,
    the fixed maps (eta, alpha_s, alpha_ss) and the static reference maps as constants.

    Args:
        problem: the patch's :class:`PatchProblem` (fused samples or a sample batch).
        fixed_raw: raw variables (``(h, w, 1)`` tensors) of ``eta, alpha_s, alpha_ss``.
        reference_raw: raw variables of the static ``rho_s, rho_ss, rho_sss_bar, displacement_mm``.
        weights: :class:`DynamicWeights`.
        texel_count: the loss's normaliser (atlas texels, module docstring); None: ``problem``'s own
            count (the atlas texels of its patch with the halo).
    """

    def __init__(
        self,
        problem: PatchProblem,
        fixed_raw: Mapping[str, torch.Tensor],
        reference_raw: Mapping[str, torch.Tensor],
        weights: DynamicWeights,
        texel_count: int | None = None,
    ) -> None:
        if texel_count is not None and (isinstance(texel_count, bool) or int(texel_count) < 1):
            raise ValueError(f"argument 'texel_count' must be None or an integer >= 1; got {texel_count!r}")
        self.problem = problem
        self.weights = weights
        self.texel_count = problem.texel_count if texel_count is None else int(texel_count)
        self.fixed_raw = {k: fixed_raw[k].detach() for k in FIXED_VARIABLES}
        with torch.no_grad():
            reference = self._maps(dict(reference_raw))
        self.reference = {k: reference[k] for k in DYNAMIC_VARIABLES}
        self.fixed = {k: reference[k] for k in FIXED_VARIABLES}

    def _maps(self, raw: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Physical maps ``(h, w)`` (``rho_sss_bar`` ``(h, w, 6)``) of the optimised raw variables."""
        maps = maps_from_raw({**self.fixed_raw, **raw}, self.problem.config)
        return {k: v if k == "rho_sss_bar" else v[..., 0] for k, v in maps.items()}

    def loss(self, raw: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """``(total, terms)``: the weighted loss per valid texel and the unweighted terms (``data``:
        the weighted data loss, then the :func:`dynamic_regularisers`)."""
        problem, wts = self.problem, self.weights
        maps = self._maps({k: raw[k] for k in DYNAMIC_VARIABLES})
        normal = problem.normals(maps["displacement_mm"])
        flat = lambda name: maps[name].reshape(normal.shape[0], -1)  # noqa: E731
        fixed = lambda name: self.fixed[name].reshape(-1)  # noqa: E731
        if problem.fused is not None:
            params = pack_parameters(
                normal, fixed("eta"), fixed("alpha_s"), fixed("alpha_ss"), flat("rho_s"), flat("rho_ss"),
                flat("rho_sss_bar"),
            )  # fmt: skip
            data = fused_data_loss(params, problem.fused, wts.data_weights(), problem.scale)
        else:
            batch = problem.batch
            texel = batch.texel
            prediction = render_samples(
                batch, normal[texel], fixed("eta")[texel], fixed("alpha_s")[texel], fixed("alpha_ss")[texel],
                flat("rho_s")[texel, 0], flat("rho_ss")[texel, 0],
                torch.gather(flat("rho_sss_bar")[texel], 1, batch.channels),
            )  # fmt: skip
            terms = data_losses(prediction, batch.observed, problem.scale)
            data = wts.sss * terms["sss"] + wts.s * terms["s"] + wts.phi * terms["phi"]
        reg = dynamic_regularisers(maps, self.reference, problem.mask)
        total = data + sum(getattr(wts, name) * value for name, value in reg.items())
        return total / max(self.texel_count, 1), {"data": data, **reg}
