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


def _scattered_height_gradient(values, mask, w_ht, lap_valid, lap_g, unit, slopes, stencil_u, stencil_v):
    """The height gradient as a pass that scatters each texel's terms to its neighbours (the order the
    gathered sums of ``_height_backward.height_gradient`` follow)."""
    rows, cols = values.shape
    g_h = np.zeros((rows, cols))
    for i in range(rows):
        for j in range(cols):
            if mask[i, j]:
                g_h[i, j] += 2.0 * w_ht * values[i, j]
            if lap_valid[i, j]:
                g = lap_g[i, j]
                g_h[i - 1, j] += g
                g_h[i + 1, j] += g
                g_h[i, j - 1] += g
                g_h[i, j + 1] += g
                g_h[i, j] -= 4.0 * g
            if unit[i, j, 3] != 0.0:
                g_du, g_dv = slopes[i, j]
                g_h[i, j] += stencil_u[1, i, j] * g_du + stencil_v[1, i, j] * g_dv
                if j < cols - 1:
                    g_h[i, j + 1] += stencil_u[0, i, j] * g_du
                if j > 0:
                    g_h[i, j - 1] += stencil_u[2, i, j] * g_du
                if i < rows - 1:
                    g_h[i + 1, j] += stencil_v[0, i, j] * g_dv
                if i > 0:
                    g_h[i - 1, j] += stencil_v[2, i, j] * g_dv
    return g_h


@pytest.mark.parametrize("shape", [(1, 1), (3, 4), (9, 13)])
def test_gathered_height_gradient_equals_the_scattered_sums_bit_for_bit(shape):
    from polarface.inverse.polarimetric._height_backward import height_gradient

    rng = np.random.default_rng(sum(shape))
    rows, cols = shape
    values = rng.normal(size=shape)
    mask = rng.random(shape) < 0.7
    lap_valid = np.zeros(shape, bool)
    lap_valid[1:-1, 1:-1] = rng.random((max(rows - 2, 0), max(cols - 2, 0))) < 0.8
    lap_g = np.where(lap_valid, 2.0 * 0.3 * rng.normal(size=shape), 0.0)
    unit = rng.normal(size=(*shape, 4))
    unit[..., 3] = np.where(rng.random(shape) < 0.2, 0.0, np.abs(unit[..., 3]) + 0.5)  # base normal kept
    slopes = np.where(unit[..., 3:] != 0.0, rng.normal(size=(*shape, 2)), 0.0)
    stencil_u = rng.normal(size=(3, *shape)).astype(np.float32)
    stencil_v = rng.normal(size=(3, *shape)).astype(np.float32)
    inputs = (values, mask, 0.7, lap_valid, lap_g, unit, slopes, stencil_u, stencil_v)
    gathered = height_gradient(*inputs)
    scattered = _scattered_height_gradient(*inputs)
    assert gathered.dtype == np.float64 and gathered.shape == shape
    np.testing.assert_array_equal(gathered, scattered)
