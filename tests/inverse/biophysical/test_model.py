"""Tests of polarface.inverse.biophysical.model: tabulated totals, local and blurred albedo."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from polarface.inverse.biophysical import (
    TotalsTable,
    blurred_channel_albedo,
    check_parameter_maps,
    local_channel_albedo,
    local_channel_albedo_with_jacobian,
    median_shapes,
)
from polarface.skin.layers import subsurface_albedo
from polarface.skin.spectral import default_spectral_calibration


def _random_parameters(n: int, seed: int = 0, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    scale = torch.tensor([0.5, 1.0, 0.32, 0.32], dtype=dtype)
    return torch.rand(n, 4, generator=g, dtype=dtype) * scale


def test_smoke_shapes_dtypes(table, calibration):
    for dtype in (torch.float32, torch.float64):
        params = torch.full((3, 5, 4), 0.05, dtype=dtype)
        rho = local_channel_albedo(params, table, calibration.weights)
        assert rho.shape == (3, 5, 6) and rho.dtype == dtype
        assert table.total_reflectance(params).shape == (3, 5, calibration.wavelengths_nm.numel())


def test_table_matches_closed_form_totals(table, calibration):
    """Reference: the Hermite tables reproduce the closed-form multipole composition (skin.layers)."""
    params = _random_parameters(500)
    reference = subsurface_albedo(
        params[:, 0], params[:, 1], params[:, 2], params[:, 3], calibration.wavelengths_nm
    )
    got = table.total_reflectance(params)
    assert torch.allclose(got, reference, atol=1e-8, rtol=0)
    channels = local_channel_albedo(params, table, calibration.weights)
    assert torch.allclose(channels, calibration.integrate(reference), atol=1e-8)


def test_analytic_jacobian_matches_autograd(table, calibration):
    params = _random_parameters(40, seed=3) * 0.9 + 0.005
    weights = calibration.weights
    value, jac = local_channel_albedo_with_jacobian(params, table, weights)
    reference = torch.autograd.functional.jacobian(
        lambda p: local_channel_albedo(p, table, weights).sum(0), params
    )
    assert torch.allclose(value, local_channel_albedo(params, table, weights), atol=1e-12)
    assert torch.allclose(jac, reference.permute(1, 0, 2), atol=1e-9)


def test_gradcheck_local(table, calibration):
    params = (_random_parameters(4, seed=5) * 0.8 + 0.01).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: local_channel_albedo(p, table, calibration.weights), (params,))


def test_physics_more_melanin_darker_more_blood_redder(table, calibration):
    base = torch.tensor([0.05, 0.1, 0.03, 0.05], dtype=torch.float64)
    more_melanin = base.clone()
    more_melanin[0] = 0.2
    more_blood = base.clone()
    more_blood[3] = 0.2
    rho = local_channel_albedo(torch.stack([base, more_melanin, more_blood]), table, calibration.weights)
    assert bool((rho[1] < rho[0]).all())  # melanin absorbs at every channel
    names = list(calibration.channel_names)
    red, green = names.index("red_upper"), names.index("green_upper")
    assert rho[2, red] / rho[2, green] > rho[0, red] / rho[0, green]  # blood absorbs green more than red


@settings(max_examples=15, deadline=None)
@given(st.floats(0.0, 0.5), st.floats(0.0, 1.0), st.floats(0.0, 0.32), st.floats(0.0, 0.32))
def test_property_albedo_in_unit_interval(c_m, beta_m, c_h_in, c_h_out):
    table = TotalsTable(default_spectral_calibration().wavelengths_nm)
    params = torch.tensor([[c_m, beta_m, c_h_in, c_h_out]], dtype=torch.float64)
    r_bar = table.total_reflectance(params)
    assert bool(torch.isfinite(r_bar).all()) and bool((r_bar >= 0).all()) and bool((r_bar < 1).all())


def test_clamped_outside_table_is_finite(calibration):
    table = TotalsTable(calibration.wavelengths_nm, sigma_a_range_mm=(0.1, 1.0), nodes=64)
    sigma = torch.tensor([[1e-3] * 15, [50.0] * 15], dtype=torch.float64)
    totals = table.totals(sigma, sigma)
    assert all(bool(torch.isfinite(t).all()) for t in totals)
    _, slope = table._interpolate("outer", sigma, with_slope=True)
    assert float(slope.abs().max()) == 0.0  # documented clamp: flat outside the range


def test_errors(calibration):
    with pytest.raises(ValueError, match="wavelengths_nm"):
        TotalsTable(torch.zeros(2, 2))
    with pytest.raises(ValueError, match="sigma_a_range_mm"):
        TotalsTable(calibration.wavelengths_nm, sigma_a_range_mm=(1.0, 0.1))
    with pytest.raises(ValueError, match="c_m"):
        check_parameter_maps(torch.tensor([[0.9, 0.1, 0.1, 0.1]]))
    with pytest.raises(ValueError, match=r"\(\.\.\., 4\)"):
        check_parameter_maps(torch.zeros(3, 3))
    with pytest.raises(ValueError, match="NaN"):
        check_parameter_maps(torch.tensor([[float("nan"), 0.1, 0.1, 0.1]]))


def test_blurred_homogeneous_conserves_energy(table, calibration):
    """Homogeneous maps: the blurred albedo keeps the local albedo's energy and equals it inside."""
    params = torch.tensor([0.04, 0.1, 0.03, 0.06], dtype=torch.float64).expand(24, 24, 4).clone()
    mask = torch.ones(24, 24, dtype=torch.bool)
    shapes, _ = median_shapes(params, mask, table)
    blurred = blurred_channel_albedo(params, table, calibration.weights, shapes, 0.5, mask)
    local = local_channel_albedo(params, table, calibration.weights)
    assert blurred.shape == (24, 24, 6)
    assert torch.allclose(blurred.sum((0, 1)), local.sum((0, 1)), rtol=1e-6)
    assert torch.allclose(blurred[12, 12], local[12, 12], rtol=2e-2)


def test_blurred_spreads_a_spot(table, calibration):
    """A dark freckle's contrast is reduced by the subsurface blur (physics: light crosses it)."""
    params = torch.tensor([0.04, 0.1, 0.03, 0.06], dtype=torch.float64).expand(32, 32, 4).clone()
    params[14:18, 14:18, 0] = 0.3
    mask = torch.ones(32, 32, dtype=torch.bool)
    shapes, _ = median_shapes(params, mask, table)
    blurred = blurred_channel_albedo(params, table, calibration.weights, shapes, 0.2, mask)
    local = local_channel_albedo(params, table, calibration.weights)
    contrast_local = local[2, 2] - local[16, 16]
    contrast_blurred = blurred[2, 2] - blurred[16, 16]
    assert bool((contrast_blurred < contrast_local).all()) and bool((contrast_blurred > 0).all())


def test_gradcheck_blurred(table, calibration):
    params = torch.tensor([0.04, 0.1, 0.03, 0.06], dtype=torch.float64).expand(6, 6, 4).clone()
    params = params + 0.01 * torch.rand(6, 6, 4, dtype=torch.float64)
    mask = torch.ones(6, 6, dtype=torch.bool)
    mask[0, 0] = False
    shapes, _ = median_shapes(params, mask, table)
    weights = calibration.weights
    params.requires_grad_(True)

    def f(p):
        return blurred_channel_albedo(p, table, weights, shapes, 0.05, mask)[..., 1]

    assert torch.autograd.gradcheck(f, (params,), atol=1e-6, rtol=1e-4)


def test_numpy_free_device_agnostic(table, calibration):
    """Runs on the parameters' device (CPU here) and accepts float32 weights with float64 params."""
    params = torch.full((2, 4), 0.05, dtype=torch.float64)
    rho = local_channel_albedo(params, table, calibration.weights.float())
    assert rho.dtype == torch.float64 and rho.device == params.device
    assert np.isfinite(rho.numpy()).all()


def _blurred_on_whole_map(params, table, weights, shapes, texel_size_mm, mask):
    """Independent reference: Eq. simple_sss on the whole map, totals of every texel masked to 0."""
    from polarface.skin.heterogeneous import render_layered_subsurface

    mask_t = mask.to(params.dtype)
    totals = tuple((m * mask_t[..., None]).permute(2, 0, 1) for m in table.layer_totals(params))
    light = mask_t[None].expand_as(totals[0])
    spectral = render_layered_subsurface(light, totals, shapes, texel_size_mm, mask=light)
    return spectral.permute(1, 2, 0) @ weights.to(spectral).T, spectral


def test_blurred_small_mask_in_large_map_equals_whole_map_render(table, calibration):
    """A mask in one corner of a large atlas (a frame seen by two cameras): rendering its bounding box
    alone gives the whole map's render (no light leaves the mask), 0 outside the mask."""
    g = torch.Generator().manual_seed(3)
    params = torch.tensor([0.04, 0.1, 0.03, 0.06], dtype=torch.float64).expand(64, 80, 4).clone()
    params = params + 0.02 * torch.rand(64, 80, 4, generator=g, dtype=torch.float64)
    mask = torch.zeros(64, 80, dtype=torch.bool)
    mask[5:40, 30:70] = True
    mask[20:25, 40:50] = False  # a hole
    shapes, _ = median_shapes(params, mask, table)
    channels, spectral = blurred_channel_albedo(
        params, table, calibration.weights, shapes, 0.25, mask, return_spectral=True
    )
    ref_channels, ref_spectral = _blurred_on_whole_map(params, table, calibration.weights, shapes, 0.25, mask)
    assert channels.shape == (64, 80, 6) and spectral.shape == (table.wavelengths_nm.numel(), 64, 80)
    assert torch.allclose(channels, ref_channels, atol=1e-12, rtol=1e-10)
    assert torch.allclose(spectral, ref_spectral, atol=1e-12, rtol=1e-10)
    assert float(channels[~mask].abs().max()) == 0.0
    # a box far narrower than the widest Gaussian (the FFT blur shortens its kernel to the box)
    tiny = torch.zeros(64, 80, dtype=torch.bool)
    tiny[30:33, 30:33] = True
    got = blurred_channel_albedo(params, table, calibration.weights, shapes, 0.05, tiny)
    expected, _ = _blurred_on_whole_map(params, table, calibration.weights, shapes, 0.05, tiny)
    assert torch.allclose(got, expected, atol=1e-12, rtol=1e-10)
