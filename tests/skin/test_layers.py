"""Tests of polarface.skin.layers: optical properties, totals, composition, physics direction."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from polarface.skin.layers import (
    PARAMETER_RANGES,
    SkinLayerConstants,
    compose_total_reflectance,
    layer_optics,
    layer_totals,
    subsurface_albedo,
)
from polarface.skin.multipole import slab_totals
from polarface.skin.spectral import default_spectral_calibration, default_wavelengths

WL = default_wavelengths()
# Supplement Table tb:res_params, forehead means of skin types I-IV: (C_m, beta_m, C_h_in, C_h_out).
FOREHEAD = {
    "I": (0.03243, 0.09607, 0.03691, 0.01701),
    "II": (0.05036, 0.04759, 0.02072, 0.08323),
    "III": (0.06155, 0.05304, 0.03622, 0.07337),
    "IV": (0.08909, 0.05291, 0.02654, 0.10450),
}


def albedo(c_m, beta_m, c_h_in, c_h_out, wl=WL):
    t = [torch.as_tensor(v, dtype=torch.float64) for v in (c_m, beta_m, c_h_in, c_h_out)]
    return subsurface_albedo(*t, wl)


def test_constants_defaults_and_validation():
    c = SkinLayerConstants()
    assert (c.outer_thickness_mm, c.eta_skin, c.gamma, c.inner_scattering_ratio) == (0.25, 1.4, 0.75, 0.5)
    with pytest.raises(ValueError, match="gamma"):
        SkinLayerConstants(gamma=1.5)
    with pytest.raises(ValueError, match="outer_thickness_mm"):
        SkinLayerConstants(outer_thickness_mm=math.inf)


def test_layer_optics_formula():
    o = layer_optics(0.1, 0.3, 0.05, 0.02, np.array([500.0]))
    from polarface.skin import chromophores as ch

    blood = 0.75 * ch.sigma_a_oxy_haemoglobin(500.0) + 0.25 * ch.sigma_a_deoxy_haemoglobin(500.0)
    mel = 0.3 * ch.sigma_a_eumelanin(500.0) + 0.7 * ch.sigma_a_pheomelanin(500.0)
    base = ch.sigma_a_baseline(500.0)
    assert o.sigma_a_out[0] == pytest.approx(0.1 * mel + 0.02 * blood + 0.88 * base)
    assert o.sigma_a_in[0] == pytest.approx(0.05 * blood + 0.95 * base)
    assert o.sigma_s_prime_in[0] == pytest.approx(0.5 * o.sigma_s_prime_out[0])


def test_shapes_maps_broadcast():
    c_m = torch.full((4, 5), 0.05)
    out = subsurface_albedo(c_m, 0.5, torch.full((1, 5), 0.03), 0.05, WL.float())
    assert out.shape == (4, 5, 15) and out.dtype == torch.float32
    optics = layer_optics(c_m, 0.5, 0.03, 0.05, WL.float())
    assert all(t.shape == (4, 5, 15) for t in optics)
    totals = layer_totals(*optics)
    assert all(t.shape == (4, 5, 15) for t in totals)


def test_composition_matches_layer_totals_and_geometric_series():
    o = layer_optics(0.05, 0.5, 0.04, 0.06, WL)
    t = layer_totals(*o)
    r_bar = compose_total_reflectance(*t)
    assert torch.allclose(r_bar, albedo(0.05, 0.5, 0.04, 0.06))
    series = t.r_out_f + sum(
        t.t_out_f * t.r_in_f * (t.r_out_b * t.r_in_f) ** n * t.t_out_b for n in range(200)
    )
    assert torch.allclose(r_bar, series, rtol=1e-10)
    # Layer totals come from the multipole with the documented boundaries.
    r_f, t_f = slab_totals(o.sigma_a_out, o.sigma_s_prime_out, 0.25, 1.4, 1.0)
    assert torch.allclose(t.r_out_f, r_f) and torch.allclose(t.t_out_f, t_f)
    r_in, _ = slab_totals(o.sigma_a_in, o.sigma_s_prime_in, math.inf, 1.0)
    assert torch.allclose(t.r_in_f, r_in)


def test_albedo_in_unit_interval_over_parameter_box():
    grid = torch.tensor(
        np.array(np.meshgrid(*[np.linspace(lo, hi, 4) for lo, hi in PARAMETER_RANGES.values()]))
        .reshape(4, -1)
        .T
    )
    out = albedo(grid[:, 0], grid[:, 1], grid[:, 2], grid[:, 3])
    assert bool((out > 0).all()) and bool((out < 1).all())


def test_more_melanin_lowers_blue():
    low, high = albedo(0.02, 0.5, 0.03, 0.03), albedo(0.2, 0.5, 0.03, 0.03)
    blue = WL <= 480
    assert bool((high[blue] < low[blue] * 0.8).all())
    assert bool((high < low).all())


def test_more_haemoglobin_deepens_q_band_dips():
    wl = torch.tensor([520.0, 540.0, 560.0, 575.0, 600.0], dtype=torch.float64)

    def dip(c_h):
        r = albedo(0.03, 0.5, c_h, c_h, wl)
        shoulder = 0.5 * (r[0] + r[2])  # 540 relative to its neighbours' mean; 575 relative to 560/600
        return float(shoulder - r[1]), float(0.5 * (r[2] + r[4]) - r[3])

    d1, d2 = dip(0.01), dip(0.1)
    assert d2[0] > d1[0] and d2[1] > d1[1]
    assert d2[0] > 0 and d2[1] > 0


def test_paper_skin_types_darken_from_I_to_IV():
    calibration = default_spectral_calibration()
    previous_mean, previous_channels = None, None
    for name in ("I", "II", "III", "IV"):
        r = albedo(*FOREHEAD[name])
        channels = calibration.integrate(r)
        if previous_mean is not None:
            assert float(r.mean()) < previous_mean, name
            # The blue channels darken monotonically too.
            assert float(channels[2]) < float(previous_channels[2]) and float(channels[5]) < float(
                previous_channels[5]
            )
        previous_mean, previous_channels = float(r.mean()), channels


def test_errors_name_arguments():
    with pytest.raises(ValueError, match="c_m"):
        albedo(-0.1, 0.5, 0.03, 0.03)
    with pytest.raises(ValueError, match="beta_m"):
        albedo(0.1, 1.5, 0.03, 0.03)
    with pytest.raises(ValueError, match="c_h_in"):
        albedo(0.1, 0.5, float("nan"), 0.03)
    with pytest.raises(ValueError, match="c_m \\+ c_h_out"):
        albedo(0.7, 0.5, 0.03, 0.6)
    with pytest.raises(ValueError, match="wavelengths_nm"):
        albedo(0.1, 0.5, 0.03, 0.03, torch.tensor([[500.0]], dtype=torch.float64))
    with pytest.raises(ValueError, match="broadcast"):
        subsurface_albedo(torch.ones(3) * 0.1, torch.ones(2) * 0.5, 0.03, 0.03, WL)
    with pytest.raises(ValueError, match="r_out_b"):
        compose_total_reflectance(0.1, 0.5, 1.0, 0.5, 1.0)


def test_gradcheck_subsurface_albedo():
    params = [torch.tensor([v], dtype=torch.float64, requires_grad=True) for v in (0.05, 0.4, 0.03, 0.06)]
    wl = torch.tensor([450.0, 560.0, 650.0], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a, b, c, d: subsurface_albedo(a, b, c, d, wl), params)


def test_numpy_in_numpy_out():
    out = subsurface_albedo(np.array([0.05, 0.1]), 0.5, 0.03, 0.03, WL.numpy())
    assert isinstance(out, np.ndarray) and out.shape == (2, 15)


def test_layer_totals_in_blocks_are_the_whole_arrays(monkeypatch):
    """Large inputs go through in blocks of the broadcast shape: the same values and gradients."""
    import polarface.skin.layers as layers

    rng = np.random.default_rng(5)
    texels = 1003  # blocks of 64 elements end inside rows of the (texels, L) broadcast shape
    params = [torch.tensor(rng.uniform(low, high, texels), requires_grad=True)
              for low, high in (PARAMETER_RANGES[name] for name in ("c_m", "beta_m", "c_h_in", "c_h_out"))]

    def totals_and_grads(block: int):
        monkeypatch.setattr(layers, "_TOTALS_BLOCK", block)
        optics = layer_optics(*params, WL)
        totals = layer_totals(*optics)
        grads = torch.autograd.grad(sum(t.sum() for t in totals), params)
        return [t.detach() for t in totals], grads

    whole, whole_grads = totals_and_grads(10**9)
    blocked, blocked_grads = totals_and_grads(64)
    assert whole[0].shape == (texels, WL.numel())
    for a, b in zip(whole + list(whole_grads), blocked + list(blocked_grads), strict=True):
        assert torch.equal(a, b)
