"""Tests of polarface.inverse.biophysical.local_kernel: the fused CPU local model against the torch
formulas of polarface.inverse.biophysical.model (its reference), autograd, the table's clamp, the
thread count and bad values; its per-texel LM against the torch loop of
polarface.inverse.biophysical.local_fit."""

from __future__ import annotations

import numba
import pytest
import torch

from polarface.inverse.biophysical import TotalsTable, local_channel_albedo
from polarface.inverse.biophysical.local_fit import _BoundedProblem, _bounds, _fit_torch, _start_design
from polarface.inverse.biophysical.local_kernel import fused_local_albedo, fused_local_fit
from polarface.inverse.biophysical.model import _local_albedo_with_jacobian_torch


def _parameters(n: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    """``(n, 4)`` random parameters spanning the admissible ranges (c_m to 0.5, c_h to 0.32)."""
    g = torch.Generator().manual_seed(seed)
    scale = torch.tensor([0.5, 1.0, 0.32, 0.32], dtype=torch.float64)
    return (torch.rand(n, 4, generator=g, dtype=torch.float64) * scale).to(dtype)


def test_reference_values_equal_the_torch_formulas_in_float64(table, calibration):
    params = _parameters(2000, seed=1)
    rho, jac = fused_local_albedo(params, table, calibration.weights.double(), with_jacobian=True)
    rho_ref, jac_ref = _local_albedo_with_jacobian_torch(params, table, calibration.weights.double())
    assert rho.dtype == jac.dtype == torch.float64
    assert torch.allclose(rho, rho_ref, rtol=0, atol=1e-14)
    assert torch.allclose(jac, jac_ref, rtol=1e-12, atol=1e-12)
    value_only, none = fused_local_albedo(params, table, calibration.weights.double(), with_jacobian=False)
    assert none is None and torch.equal(value_only, rho)


def test_jacobian_matches_autograd_of_the_torch_model(table, calibration):
    """gradcheck-style: the kernel's analytic Jacobian against autograd through the torch path."""
    params = _parameters(30, seed=2) * 0.9 + 0.005
    weights = calibration.weights.double()
    _, jac = fused_local_albedo(params, table, weights, with_jacobian=True)
    autograd = torch.autograd.functional.jacobian(
        lambda p: local_channel_albedo(p, table, weights).sum(0), params
    ).permute(1, 0, 2)
    assert torch.allclose(jac, autograd, rtol=1e-10, atol=1e-10)


def test_albedo_is_a_reflectance_and_float32_keeps_its_dtype(table, calibration):
    """Energy: 0 <= rho < 1 over the admissible box; float32 in gives float32 out, close to float64."""
    params = _parameters(3000, seed=3)
    rho64, _ = fused_local_albedo(params, table, calibration.weights, with_jacobian=False)
    assert bool((rho64 >= 0).all()) and bool((rho64 < 1).all())
    rho32, jac32 = fused_local_albedo(params.float().reshape(30, 100, 4), table, calibration.weights, True)
    assert rho32.dtype == jac32.dtype == torch.float32
    assert rho32.shape == (30, 100, 6) and jac32.shape == (30, 100, 6, 4)
    assert torch.allclose(rho32.reshape(-1, 6).double(), rho64, atol=1e-6)


def test_clamped_absorptions_have_zero_slope(calibration):
    """The documented clamp: outside the table's range the totals are flat, as in the torch path."""
    table = TotalsTable(calibration.wavelengths_nm, sigma_a_range_mm=(0.5, 5.0), nodes=64)
    params = _parameters(500, seed=4)
    weights = calibration.weights.double()
    rho, jac = fused_local_albedo(params, table, weights, with_jacobian=True)
    rho_ref, jac_ref = _local_albedo_with_jacobian_torch(params, table, weights)
    assert torch.allclose(rho, rho_ref, atol=1e-14) and torch.allclose(jac, jac_ref, atol=1e-12)
    assert float(jac.abs().min()) == 0.0  # some absorptions fall outside (0.5, 5) mm^-1


def test_public_functions_dispatch_to_the_kernel_unless_a_graph_is_needed(table, calibration):
    params = _parameters(50, seed=5).float()
    weights = calibration.weights.float()
    fused, _ = fused_local_albedo(params, table, weights, with_jacobian=False)
    assert torch.equal(local_channel_albedo(params, table, weights), fused)
    graph = params.clone().requires_grad_(True)
    differentiable = local_channel_albedo(graph, table, weights)  # torch path, float32 arithmetic
    assert differentiable.requires_grad and torch.allclose(differentiable.detach(), fused, atol=2e-6)


def test_result_does_not_depend_on_the_thread_count(table, calibration):
    params = _parameters(4001, seed=6)
    previous = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = fused_local_albedo(params, table, calibration.weights, with_jacobian=True)
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        many = fused_local_albedo(params, table, calibration.weights, with_jacobian=True)
    finally:
        numba.set_num_threads(previous)
    assert torch.equal(one[0], many[0]) and torch.equal(one[1], many[1])


def test_bad_values_give_nan_rows_not_a_crash(table, calibration):
    """A NaN or infinite parameter poisons its own row only (the lookup index stays inside the table)."""
    params = _parameters(4, seed=7)
    params[1, 0] = float("nan")
    params[2, 3] = float("inf")
    rho, jac = fused_local_albedo(params, table, calibration.weights, with_jacobian=True)
    assert bool(torch.isnan(rho[1]).all()) and bool(torch.isnan(jac[1]).all())
    assert bool(torch.isfinite(rho[[0, 3]]).all()) and bool(torch.isfinite(jac[[0, 3]]).all())
    assert not bool(torch.isfinite(rho[2]).all())


# ------------------------------------------------------------------------------------ the per-texel LM
def _lm_inputs(table, weights, n: int, seed: int, prior: bool):
    """Rows of a multi-start fit: noisy model albedos as goals, the design starts, a prior pull."""
    truth = _parameters(n, seed) * 0.9 + 0.005
    g = torch.Generator().manual_seed(seed + 100)
    noise = 0.02 * torch.randn(n, 6, generator=g, dtype=torch.float64)
    goal = local_channel_albedo(truth, table, weights) * (1 + noise)
    design = _start_design(4, torch.float64, "cpu")
    x = design[:, None, :].expand(4, n, 4).reshape(-1, 4).clone()
    goal = goal.repeat(4, 1)
    weight = 1.0 / (goal + 0.02)
    anchor = truth.repeat(4, 1) if prior else x.clone()
    pull = torch.tensor([0.5, 0.2, 0.3, 0.4] if prior else [0.0] * 4, dtype=torch.float64)
    return x, goal, weight, anchor, pull, _bounds(torch.float64, "cpu")


@pytest.mark.parametrize("prior", [False, True], ids=["free", "prior"])
def test_lm_rows_follow_the_torch_loop(table, calibration, prior):
    """Reference: each row's numba LM takes the torch loop's steps (float64: same parameters and costs)."""
    weights = calibration.weights.double()
    x, goal, weight, anchor, pull, (low, high) = _lm_inputs(table, weights, 300, 11, prior)
    got, got_cost = fused_local_fit(x, goal, weight, anchor, pull, (low, high), 40, table, weights)
    problem = _BoundedProblem(table, weights, pull, low, high)
    want, want_cost = _fit_torch(problem, x, goal, weight, anchor, 40)
    assert got.dtype == got_cost.dtype == torch.float64
    assert torch.allclose(got, want, rtol=0, atol=1e-9)
    assert torch.allclose(got_cost, want_cost, rtol=1e-9, atol=1e-15)
    assert bool((got >= low).all()) and bool((got <= high).all())  # bounded


def test_lm_lowers_the_cost_and_does_not_depend_on_the_thread_count(table, calibration):
    weights = calibration.weights.double()
    x, goal, weight, anchor, pull, bounds = _lm_inputs(table, weights, 500, 12, False)
    start_cost = (((local_channel_albedo(x, table, weights) - goal) * weight) ** 2).sum(-1)
    previous = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = fused_local_fit(x, goal, weight, anchor, pull, bounds, 40, table, weights)
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        many = fused_local_fit(x, goal, weight, anchor, pull, bounds, 40, table, weights)
    finally:
        numba.set_num_threads(previous)
    assert torch.equal(one[0], many[0]) and torch.equal(one[1], many[1])
    assert bool((one[1] <= start_cost).all()) and float(one[1].median()) < 1e-3 * float(start_cost.median())


def test_lm_bad_target_poisons_its_row_only(table, calibration):
    weights = calibration.weights.double()
    x, goal, weight, anchor, pull, bounds = _lm_inputs(table, weights, 3, 13, False)
    goal[1, 2] = float("nan")
    params, cost = fused_local_fit(x, goal, weight, anchor, pull, bounds, 10, table, weights)
    assert not bool(torch.isfinite(cost[1])) and bool(torch.isfinite(cost[[0, 2]]).all())
    assert bool(torch.isfinite(params).all())  # a NaN cost never accepts a step: the start is kept
