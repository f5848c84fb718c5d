"""Tests of polarface.inverse.biophysical: bounded LM, coarse-to-fine fit, blurred model, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as nnf

from polarface.inverse.biophysical import (
    BiophysicalConfig,
    blurred_channel_albedo,
    fit_biophysical,
    fit_local_parameters,
    gamut_distance,
    local_channel_albedo,
    median_shapes,
)
from polarface.skin.layers import PARAMETER_RANGES


def smooth_maps(size: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    y, x = torch.meshgrid(torch.linspace(0, 1, size), torch.linspace(0, 1, size), indexing="ij")
    params = torch.stack([0.03 + 0.05 * x, 0.05 + 0.1 * y, 0.02 + 0.03 * x * y, 0.02 + 0.1 * (1 - x) * y], -1)
    mask = torch.ones(size, size, dtype=torch.bool)
    mask[:3] = False
    return params, mask


def test_config_defaults_and_errors():
    config = BiophysicalConfig()
    assert config.albedo_model == "blurred" and config.constants.gamma == 0.75
    with pytest.raises(ValueError, match="albedo_model"):
        BiophysicalConfig(albedo_model="nope")
    with pytest.raises(ValueError, match="coarse_factor"):
        BiophysicalConfig(coarse_factor=0)
    with pytest.raises(ValueError, match="channel_floor"):
        BiophysicalConfig(channel_floor=0.0)
    assert config.gamut_tolerance == 0.05
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="gamut_tolerance"):
            BiophysicalConfig(gamut_tolerance=bad)
    BiophysicalConfig(gamut_tolerance=math.inf)  # disables the screen


def test_gamut_distance_values_shapes_and_gradient(setup):
    table, weights = setup
    params = torch.tensor([[0.05, 0.1, 0.03, 0.05], [0.2, 0.6, 0.1, 0.1]], dtype=torch.float64)
    model = local_channel_albedo(params, table, weights.double())
    assert gamut_distance(model, model).shape == (2,)
    assert float(gamut_distance(model, model).abs().max()) == 0.0
    brighter = model * 1.1  # 10 % brighter than the model in every channel
    expected = ((model - brighter) / (brighter + 0.02)).pow(2).mean(-1).sqrt()
    assert torch.allclose(gamut_distance(brighter, model), expected)
    assert bool((gamut_distance(brighter, model) > 0.05).all())  # beyond the default tolerance
    assert bool((gamut_distance(brighter, model) < 0.1).all())
    rho = brighter.clone().requires_grad_(True)
    model_leaf = model.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: gamut_distance(a, b), (rho, model_leaf))
    as_numpy = gamut_distance(brighter.numpy(), model.numpy())  # numpy in, numpy out
    assert isinstance(as_numpy, np.ndarray) and np.allclose(as_numpy, expected.numpy())
    assert gamut_distance(brighter.float(), model.float()).dtype == torch.float32
    assert gamut_distance(brighter, model[:1]).shape == (2,)  # broadcasting
    with pytest.raises(ValueError, match="broadcast"):
        gamut_distance(brighter, model[:, :3])
    with pytest.raises(ValueError, match="rho_sss_bar"):
        gamut_distance(-brighter, model)
    with pytest.raises(ValueError, match="model"):
        gamut_distance(brighter, model * float("nan"))
    with pytest.raises(ValueError, match="channel_floor"):
        gamut_distance(brighter, model, channel_floor=0.0)


@pytest.fixture(scope="module")
def blurred_with_outliers(setup):
    """Blurred (Eq. simple_sss) smooth skin with five out-of-gamut texels: a saturated 2x2 block
    (rho = 0.98, a polarimetric fit stuck at its bound) and one texel with reversed channel ratios."""
    table, weights = setup
    params, mask = smooth_maps()
    shapes, _ = median_shapes(params, mask, table)
    observed = blurred_channel_albedo(params, table, weights, shapes, 0.4, mask).clone()
    bad = torch.zeros(mask.shape, dtype=torch.bool)
    bad[15:17, 15:17] = True
    observed[15:17, 15:17] = 0.98
    bad[24, 8] = True
    observed[24, 8] = observed[24, 8].flip(-1)
    near = (nnf.max_pool2d(bad.float()[None, None], 9, 1, 4)[0, 0] > 0) & ~bad & mask
    fits = {
        tolerance: fit_biophysical(
            observed, mask, table, weights, 0.4, BiophysicalConfig(coarse_factor=4, gamut_tolerance=tolerance)
        )
        for tolerance in (0.05, math.inf)
    }
    return params, mask, bad, near, fits


def test_gamut_screen_flags_exactly_the_out_of_gamut_texels(blurred_with_outliers):
    _, mask, bad, _, fits = blurred_with_outliers
    screened, unscreened = fits[0.05], fits[math.inf]
    assert screened.in_gamut.shape == mask.shape and screened.in_gamut.dtype == torch.bool
    assert bool(((~screened.in_gamut & mask) == bad).all())
    assert not bool(screened.in_gamut[~mask].any())
    assert bool(unscreened.in_gamut[mask].all())  # inf disables the screen
    assert float(screened.gamut_distance[bad].min()) > 0.2
    assert float(screened.gamut_distance[mask & ~bad].max()) < 0.02
    # Reported numbers: all texels count; the floor is the inputs' own distance to the gamut.
    assert screened.residual_rmse_in_gamut < 0.01
    assert 0.1 < screened.gamut_floor_rmse < screened.residual_rmse
    assert unscreened.residual_rmse_in_gamut == pytest.approx(unscreened.residual_rmse)


def test_gamut_screen_keeps_outliers_out_of_their_neighbours_prior(blurred_with_outliers):
    """Without the screen the saturated texels bias the coarse maps that warm-start and regularise
    their neighbours (the default prior pulls beta_m and C_h_in towards them)."""
    params, mask, bad, near, fits = blurred_with_outliers
    errors = {k: (fit.parameters - params)[near].abs().median(0).values for k, fit in fits.items()}
    far = (fits[0.05].parameters - params)[mask & ~near & ~bad].abs().median(0).values
    assert float(errors[0.05][1]) < 0.5 * float(errors[math.inf][1])  # beta_m
    assert float(errors[0.05][2]) < 0.5 * float(errors[math.inf][2])  # C_h_in
    assert float(errors[0.05][0]) < 0.5 * float(errors[math.inf][0])  # C_m
    assert float(errors[0.05][1]) < 1.5 * float(far[1]) + 1e-3  # neighbours as good as the rest
    assert float(errors[0.05][2]) < 1.5 * float(far[2]) + 1e-3


def test_fit_local_parameters_recovers_random_skin(setup):
    table, weights = setup
    g = torch.Generator().manual_seed(1)
    truth = torch.stack(
        [
            0.01 + 0.2 * torch.rand(300, generator=g),
            0.02 + 0.5 * torch.rand(300, generator=g),
            0.005 + 0.1 * torch.rand(300, generator=g),
            0.005 + 0.2 * torch.rand(300, generator=g),
        ],
        -1,
    )
    rho = local_channel_albedo(truth, table, weights)
    fitted, cost = fit_local_parameters(rho, table, weights, starts=6, iterations=60)
    error = (fitted - truth).abs()
    assert float(error[:, 0].median()) < 1e-4 and float(error[:, 3].median()) < 1e-4
    assert float(error[:, 2].median()) < 1e-4 and float(error[:, 1].median()) < 1e-3
    assert cost.shape == (300,)
    for i, name in enumerate(("c_m", "beta_m", "c_h_in", "c_h_out")):  # inside the bounds
        low, high = PARAMETER_RANGES[name]
        assert bool((fitted[:, i] >= low).all()) and bool((fitted[:, i] <= high).all())


def test_fit_local_parameters_respects_bounds_for_unreachable_targets(setup):
    table, weights = setup
    rho = torch.full((4, 6), 0.97)  # whiter than any skin
    fitted, _ = fit_local_parameters(rho, table, weights, starts=2, iterations=20)
    low = torch.tensor([PARAMETER_RANGES[k][0] for k in ("c_m", "beta_m", "c_h_in", "c_h_out")])
    assert bool(torch.isfinite(fitted).all()) and bool((fitted >= low).all())


def test_fit_biophysical_local_model(setup):
    table, weights = setup
    params, mask = smooth_maps()
    rho = local_channel_albedo(params, table, weights) * mask[..., None]
    fit = fit_biophysical(
        rho,
        mask,
        table,
        weights,
        0.5,
        BiophysicalConfig(albedo_model="local", coarse_factor=4, prior_weight=(0.0,) * 4),
    )
    error = (fit.parameters - params)[mask].abs().median(0).values
    assert bool((error < torch.tensor([1e-4, 1e-3, 1e-4, 1e-4])).all())
    assert fit.residual_rmse < 1e-4
    assert fit.rendered.shape == (32, 32, 6) and fit.spectral.shape == (15, 32, 32)
    assert float(fit.parameters[~mask].abs().max()) == 0.0
    assert set(fit.timings_s) >= {"coarse_s", "fine_local_s", "gamut_s"}
    assert bool(fit.in_gamut[mask].all()) and fit.gamut_floor_rmse < 1e-4  # skin is in its own gamut
    assert fit.residual_rmse_in_gamut == pytest.approx(fit.residual_rmse)


@pytest.mark.slow
def test_fit_biophysical_blurred_model_undoes_the_blur(setup):
    """Input blurred by Eq. simple_sss: the blurred fine stage recovers the maps, the local one cannot."""
    table, weights = setup
    params, mask = smooth_maps()
    params[14:18, 14:18, 0] = 0.12  # a freckle, where blur matters
    shapes, _ = median_shapes(params, mask, table)
    observed = blurred_channel_albedo(params, table, weights, shapes, 0.4, mask)
    config = BiophysicalConfig(albedo_model="blurred", coarse_factor=4, prior_weight=(0.0,) * 4)
    fit = fit_biophysical(observed, mask, table, weights, 0.4, config)
    local = fit_biophysical(
        observed,
        mask,
        table,
        weights,
        0.4,
        BiophysicalConfig(albedo_model="local", coarse_factor=4, prior_weight=(0.0,) * 4),
    )
    error = (fit.parameters - params)[mask].abs()
    error_local = (local.parameters - params)[mask].abs()
    assert float(error[:, 0].median()) < 0.005 and float(error[:, 3].median()) < 0.01
    assert float(error[:, 2].median()) < 0.01 and float(error[:, 1].median()) < 0.03
    assert float(error[:, 0].max()) < float(error_local[:, 0].max())  # the freckle is sharper
    assert fit.residual_rmse < 0.01


def test_prior_reduces_noise_in_weak_parameters(setup):
    """1 % noise on rho_sss_bar: the pull towards the coarse maps shrinks the beta_m and C_h_in errors."""
    table, weights = setup
    params, mask = smooth_maps()
    rho = local_channel_albedo(params, table, weights)
    noisy = (rho * (1 + 0.01 * torch.randn(rho.shape, generator=torch.Generator().manual_seed(2)))).clamp(
        0, 1
    )
    errors = {}
    for prior in ((0.0, 0.0, 0.0, 0.0), (0.0, 1.0, 1.0, 0.0)):
        config = BiophysicalConfig(albedo_model="local", coarse_factor=4, prior_weight=prior)
        fit = fit_biophysical(noisy * mask[..., None], mask, table, weights, 0.5, config)
        errors[prior[1]] = (fit.parameters - params)[mask].abs().median(0).values
    assert float(errors[1.0][1]) < 0.7 * float(errors[0.0][1])
    assert float(errors[1.0][2]) < float(errors[0.0][2])
    with pytest.raises(ValueError, match="prior_weight"):
        BiophysicalConfig(prior_weight=(0.0, -1.0, 0.0, 0.0))


def test_fit_biophysical_bad_input(setup):
    table, weights = setup
    params, mask = smooth_maps(16)
    rho = local_channel_albedo(params, table, weights)
    with pytest.raises(ValueError, match="rho_sss_bar"):
        fit_biophysical(rho * 5.0, mask, table, weights, 0.5)
    with pytest.raises(ValueError, match="rho_sss_bar"):
        fit_biophysical(-rho, mask, table, weights, 0.5)
    bad = rho.clone()
    bad[5, 5, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        fit_biophysical(bad, mask, table, weights, 0.5)
    with pytest.raises(ValueError, match=r"\(H, W, 6\)"):
        fit_biophysical(rho[..., :3], mask, table, weights, 0.5)
    with pytest.raises(ValueError, match="mask"):
        fit_biophysical(rho, torch.zeros(16, 16, dtype=torch.bool), table, weights, 0.5)
    with pytest.raises(ValueError, match="mask"):
        fit_biophysical(rho, mask[:8], table, weights, 0.5)
    with pytest.raises(ValueError, match="texel_size_mm"):
        fit_biophysical(rho, mask, table, weights, 0.0)
