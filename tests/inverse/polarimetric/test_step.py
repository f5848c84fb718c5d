"""The numba optimiser step (polarface.inverse.polarimetric.step) against the torch glue it replaces."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from polarface.inverse.polarimetric import LossWeights, PolarimetricConfig, benchmark_problem, optimise_patch


def _perturbed(raw: dict[str, torch.Tensor], seed: int) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    return {k: v + 0.3 * torch.randn(v.shape, generator=generator, dtype=v.dtype) for k, v in raw.items()}


@pytest.fixture(scope="module")
def patch():
    bench = benchmark_problem(side=10, frames=3, dtype=torch.float64)
    return bench.problems["fused"], _perturbed(bench.raw, 0)


@pytest.mark.parametrize(
    "weights",
    [
        LossWeights(),
        LossWeights(h_laplacian=0.0, eta=0.0, alpha_s=0.0, alpha_ss=0.0),
        LossWeights(sss=0.0, s=0.0),
    ],
    ids=["paper", "data-only", "regularisers-heavy"],
)
def test_numba_steps_follow_the_torch_trajectory(patch, weights):
    problem, raw = patch
    config = PolarimetricConfig(iterations=6, weights=weights)
    problem = dataclasses.replace(problem) if dataclasses.is_dataclass(problem) else problem
    problem.config = config
    curve_numba, curve_torch = [], []
    fast = optimise_patch(problem, raw, config, curve_numba)
    slow = optimise_patch(problem, raw, config, curve_torch, fused_steps=False)
    np.testing.assert_allclose(curve_numba, curve_torch, rtol=1e-9)
    for name in raw:
        torch.testing.assert_close(fast[name], slow[name], rtol=1e-7, atol=1e-9)
        assert fast[name].dtype == raw[name].dtype and fast[name].shape == raw[name].shape
    assert not torch.equal(fast["displacement_mm"], raw["displacement_mm"])  # the heights moved


def test_float32_steps_are_deterministic_and_lower_the_loss():
    bench = benchmark_problem(side=10, frames=3)
    problem, raw = bench.problems["fused"], _perturbed(bench.raw, 1)
    config = PolarimetricConfig(iterations=20)
    curve_a, curve_b = [], []
    first = optimise_patch(problem, raw, config, curve_a)
    second = optimise_patch(problem, raw, config, curve_b)
    assert curve_a[-1] < curve_a[0] and curve_a == curve_b
    for name in first:
        assert torch.equal(first[name], second[name])
