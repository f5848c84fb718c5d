"""Optimisation of one patch: L-BFGS (the default), or RMSprop / Adam with their learning-rate schedule.

L-BFGS (``torch.optim.LBFGS``, strong-Wolfe line search; Nocedal & Wright, *Numerical Optimization*,
2nd ed., Sec. 7.2) is the default because it converges where the first-order methods stop short: the
lobe maps (alpha_s, rho_s, rho_ss, alpha_ss) lie in a long flat valley that RMSprop leaves where its
start put it, and eta, which the lobes' Fresnel polarization couples to them, then settles about 0.01 low
(the eta bias measured in docs/reconstruct.md, "Unbiased eta"). With fused samples on the CPU the
objective and its gradient come from numba
(:class:`polarface.inverse.polarimetric.step.FusedObjective`; RMSprop runs entirely there,
:func:`~polarface.inverse.polarimetric.step.optimise_patch_fused`); otherwise torch autograd drives
:meth:`polarface.inverse.polarimetric.problem.PatchProblem.loss`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import torch

from polarface.inverse.polarimetric.config import NO_LOBE_RAW, PolarimetricConfig
from polarface.inverse.polarimetric.problem import PatchProblem
from polarface.inverse.polarimetric.step import FusedObjective, optimise_patch_fused, pack_raw, unpack_raw

__all__ = ["learning_rate_schedule", "minimise_lbfgs", "optimise_patch"]


def _optimizer(params: list[torch.Tensor], config: PolarimetricConfig) -> torch.optim.Optimizer:
    if config.optimizer == "adam":
        return torch.optim.Adam(params, lr=config.lr)
    return torch.optim.RMSprop(params, lr=config.lr)


def learning_rate_schedule(config: PolarimetricConfig) -> list[float]:
    """Learning rate of each of the ``config.iterations`` steps: linear warm-up over ``config.warmup``
    steps times a cosine decay from ``config.lr`` to ``config.lr * config.lr_final_fraction``."""
    steps = int(config.iterations)
    learning_rates = []
    for step in range(steps):
        # RMSprop's first steps are ~10 lr (its running mean starts at 0): a short linear warm-up
        warm = min(1.0, (step + 1) / max(config.warmup, 1))
        fraction = warm * (
            config.lr_final_fraction
            + (1 - config.lr_final_fraction) * 0.5 * (1 + math.cos(math.pi * step / max(steps, 1)))
        )
        learning_rates.append(config.lr * fraction)
    return learning_rates


def optimise_patch(
    problem: PatchProblem,
    raw: dict[str, torch.Tensor],
    config: PolarimetricConfig,
    curve: list[float] | None = None,
    *,
    fused_steps: bool = True,
    variables: Sequence[str] | None = None,
) -> dict[str, torch.Tensor]:
    """Run the optimiser on one patch; returns detached raw variables.

    With fused samples on the CPU and RMSprop, the whole step runs in numba
    (:func:`polarface.inverse.polarimetric.step.optimise_patch_fused`, the same mathematics without the
    torch glue); otherwise torch autograd drives ``problem.loss``. ``variables`` (default: every key of
    ``raw``) names the optimised raw variables: only they are passed to ``problem.loss`` and returned
    (the per-frame fit's problem holds its fixed maps itself).
    """
    if config.lobes == "one" and "rho_ss" in raw:  # no second lobe, whatever the start
        raw = {**raw, "rho_ss": torch.full_like(raw["rho_ss"], NO_LOBE_RAW)}
    on_cpu = all(v.device.type == "cpu" for v in raw.values())
    fused = fused_steps and problem.fused is not None and on_cpu and variables is None
    frozen = {k: raw[k].detach() for k in config.frozen_variables if k in raw}
    names = [k for k in (list(raw) if variables is None else list(variables)) if k not in frozen]
    if fused and config.optimizer == "lbfgs":
        return _lbfgs_fused(problem, raw, config, curve)
    if fused and config.optimizer == "rmsprop":
        return optimise_patch_fused(problem, raw, config, learning_rate_schedule(config), curve)
    leaves = {k: raw[k].detach().clone().requires_grad_(True) for k in names}
    inputs = {**frozen, **leaves}

    def objective() -> torch.Tensor:
        total, _ = problem.loss(inputs)
        total.backward()
        return total

    if config.optimizer == "lbfgs":
        minimise_lbfgs(list(leaves.values()), objective, int(config.iterations), curve)
    else:
        optimizer = _optimizer(list(leaves.values()), config)
        for step, lr in enumerate(learning_rate_schedule(config)):
            for group in optimizer.param_groups:
                group["lr"] = lr
            optimizer.zero_grad(set_to_none=True)
            total = objective()
            optimizer.step()
            if curve is not None:
                if len(curve) <= step:
                    curve.append(0.0)
                curve[step] += float(total.detach())
    return {**frozen, **{k: v.detach() for k, v in leaves.items()}}


def minimise_lbfgs(
    leaves: list[torch.Tensor],
    objective: Callable[[], torch.Tensor],
    iterations: int,
    curve: list[float] | None = None,
) -> None:
    """Run ``iterations`` L-BFGS iterations (history 20, strong-Wolfe line search) on ``leaves`` in place.

    Args:
        leaves: tensors with ``requires_grad``; objective: returns the loss after filling every leaf's
            ``.grad`` (it is called with the gradients zeroed); curve: optional list,
            ``curve[k] +=`` the loss of the k-th objective evaluation (about 1.05 per iteration).
    """
    optimizer = torch.optim.LBFGS(
        leaves,
        lr=1.0,
        max_iter=int(iterations),
        max_eval=int(1.25 * int(iterations)) + 10,
        history_size=20,
        line_search_fn="strong_wolfe",
        tolerance_grad=1e-10,
        tolerance_change=1e-14,
    )
    evaluations = [0]

    def closure() -> torch.Tensor:
        optimizer.zero_grad(set_to_none=False)
        total = objective()
        if curve is not None:
            if len(curve) <= evaluations[0]:
                curve.append(0.0)
            curve[evaluations[0]] += float(total.detach())
        evaluations[0] += 1
        return total

    optimizer.step(closure)


def _lbfgs_fused(
    problem: PatchProblem, raw: dict[str, torch.Tensor], config: PolarimetricConfig, curve: list[float] | None
) -> dict[str, torch.Tensor]:
    """:func:`minimise_lbfgs` on the packed raw variables (float64) with the numba objective and gradient
    (:class:`~polarface.inverse.polarimetric.step.FusedObjective`, kernel in ``raw``'s float type)."""
    dtype = np.dtype(np.float32) if raw["eta"].dtype == torch.float32 else np.dtype(np.float64)
    fused_objective = FusedObjective(problem, config, dtype)
    packed = torch.from_numpy(pack_raw(raw).astype(np.float64)).requires_grad_(True)
    grad = np.zeros(tuple(packed.shape))

    def objective() -> torch.Tensor:
        total = fused_objective(packed.detach().numpy(), grad)
        packed.grad = torch.from_numpy(grad.copy())
        return torch.tensor(total, dtype=torch.float64)

    minimise_lbfgs([packed], objective, int(config.iterations), curve)
    return unpack_raw(packed.detach().numpy(), raw)
