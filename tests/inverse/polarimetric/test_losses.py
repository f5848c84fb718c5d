"""Losses and regularisers of the polarimetric stage: values, laws, errors, finite-difference gradients."""

from __future__ import annotations

import pytest
import torch

from polarface.inverse.polarimetric import (
    LossWeights,
    SamplePrediction,
    data_losses,
    laplacian_penalty,
    smoothness_penalty,
)


def _prediction(seed: int = 0, count: int = 6, requires_grad: bool = False):
    generator = torch.Generator().manual_seed(seed)
    values = [torch.rand(count, 3, generator=generator, dtype=torch.float64) for _ in range(4)]
    values[0] = values[0] + 0.5  # I_sss positive
    values[1] = values[1] - 0.5
    if requires_grad:
        values = [v.requires_grad_(True) for v in values]
    return values


def test_zero_residual_gives_zero_data_losses():
    i_sss, i_zeta, i_s, spec = _prediction()
    observed = torch.stack([i_sss, i_zeta, i_s], dim=1)
    losses = data_losses(SamplePrediction(i_sss, i_zeta, i_s, spec), observed, 0.7)
    assert set(losses) == {"sss", "s", "phi", "psi"}
    for value in losses.values():
        assert float(value) == pytest.approx(0.0, abs=1e-14)


def test_losses_are_positive_and_scale_invariant():
    i_sss, i_zeta, i_s, spec = _prediction()
    observed = torch.stack([i_sss * 1.1, i_zeta + 0.01, i_s - 0.02], dim=1)
    first = data_losses(SamplePrediction(i_sss, i_zeta, i_s, spec), observed, 0.5)
    k = 7.0
    second = data_losses(SamplePrediction(i_sss * k, i_zeta * k, i_s * k, spec * k), observed * k, 0.5 * k)
    for name in first:
        assert float(first[name]) > 0
        assert float(second[name]) == pytest.approx(float(first[name]), rel=1e-10)


@pytest.mark.parametrize("name", ["sss", "s", "phi", "psi"])
def test_data_loss_gradients_match_finite_differences(name):
    inputs = _prediction(seed=3, requires_grad=True)
    observed = torch.stack([p.detach() * 1.05 + 0.01 for p in inputs[:3]], dim=1)
    assert torch.autograd.gradcheck(lambda *a: data_losses(SamplePrediction(*a), observed, 0.6)[name], inputs)


def test_bad_scale():
    i_sss, i_zeta, i_s, spec = _prediction()
    with pytest.raises(ValueError, match="scale"):
        data_losses(
            SamplePrediction(i_sss, i_zeta, i_s, spec), torch.zeros(6, 3, 3, dtype=torch.float64), 0.0
        )


def test_smoothness_and_laplacian_laws():
    mask = torch.ones(7, 9, dtype=torch.bool)
    constant = torch.full((7, 9), 1.4, dtype=torch.float64)
    assert float(smoothness_penalty(constant, mask)) == pytest.approx(0.0, abs=1e-20)
    rows, cols = torch.meshgrid(torch.arange(7.0), torch.arange(9.0), indexing="ij")
    plane = (0.3 * rows - 0.2 * cols).double()
    assert float(laplacian_penalty(plane, mask)) == pytest.approx(0.0, abs=1e-10)
    bump = torch.zeros(7, 9, dtype=torch.float64)
    bump[3, 4] = 1.0
    assert float(laplacian_penalty(bump, mask)) == pytest.approx(16.0 + 4.0)
    assert float(smoothness_penalty(bump, mask)) > 0
    # invalid texels do not contribute
    assert float(laplacian_penalty(bump, torch.zeros_like(mask))) == 0.0


def test_regulariser_gradients():
    generator = torch.Generator().manual_seed(1)
    value = torch.rand(6, 6, generator=generator, dtype=torch.float64, requires_grad=True)
    mask = torch.ones(6, 6, dtype=torch.bool)
    mask[0, 0] = False
    assert torch.autograd.gradcheck(lambda v: smoothness_penalty(v, mask), (value,))
    assert torch.autograd.gradcheck(lambda v: laplacian_penalty(v, mask), (value,))


def test_regulariser_shape_errors_and_weights():
    with pytest.raises(ValueError, match="value"):
        smoothness_penalty(torch.zeros(3, 3), torch.ones(3, 4, dtype=torch.bool))
    with pytest.raises(ValueError, match="height"):
        laplacian_penalty(torch.zeros(3, 3), torch.ones(2, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"weights\.eta"):
        LossWeights(eta=-1.0)
    # the paper's data weights; the displacement map's regularisers in mm (docs/reconstruct.md)
    assert (LossWeights().psi, LossWeights().eta) == (0.002, 400.0)
    assert (LossWeights().h_temporal, LossWeights().h_laplacian) == (0.01, 10.0)
