"""First-order optimisation of one patch: learning-rate schedule and the optimiser loop.

With fused samples on the CPU and RMSprop, the whole step runs in numba
(:func:`polarface.inverse.polarimetric.step.optimise_patch_fused`); otherwise torch autograd drives
:meth:`polarface.inverse.polarimetric.problem.PatchProblem.loss`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from polarface.inverse.polarimetric.config import PolarimetricConfig
from polarface.inverse.polarimetric.problem import PatchProblem
from polarface.inverse.polarimetric.step import optimise_patch_fused

__all__ = ["learning_rate_schedule", "optimise_patch"]


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
    learning_rates = learning_rate_schedule(config)
    on_cpu = all(v.device.type == "cpu" for v in raw.values())
    if fused_steps and problem.fused is not None and config.optimizer == "rmsprop" and on_cpu:
        return optimise_patch_fused(problem, raw, config, learning_rates, curve)
    names = list(raw) if variables is None else list(variables)
    leaves = {k: raw[k].detach().clone().requires_grad_(True) for k in names}
    optimizer = _optimizer(list(leaves.values()), config)
    for step, lr in enumerate(learning_rates):
        for group in optimizer.param_groups:
            group["lr"] = lr
        optimizer.zero_grad(set_to_none=True)
        total, _ = problem.loss(leaves)
        total.backward()
        optimizer.step()
        if curve is not None:
            if len(curve) <= step:
                curve.append(0.0)
            curve[step] += float(total.detach())
    return {k: v.detach() for k, v in leaves.items()}
