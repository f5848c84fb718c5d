"""Per-texel Gauss-Newton uncertainty: Jacobian against finite differences, scaling laws, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from polarface.inverse.polarimetric import fit_diagnostics
from polarface.inverse.polarimetric.uncertainty import _sample_jacobian, _texel_covariance

from .test_model import _batch, _scene


def _one_texel(count: int = 24, noise: float = 0.02):
    """``count`` samples of one texel (texel index 0) with noisy observations around the model."""
    position, normal, centre, up, reference, lights, params = _scene(count)
    rng = np.random.default_rng(1)
    batch = _batch(position, centre, up, reference, lights)
    values = {k: torch.full((count,), float(params[k][0]), dtype=torch.float64)
              for k in ("eta", "alpha_s", "alpha_ss", "rho_s", "rho_ss")}
    values["rho3"] = torch.tensor(np.tile(params["rho_sss_bar"][0], (count, 1)))
    normal_t = torch.tensor(normal)
    clean, _ = _sample_jacobian(batch, normal_t, values, jacobian=False)  # residual vs zero obs = prediction
    observed = clean * (1.0 + noise * torch.tensor(rng.normal(size=clean.shape)))
    batch = batch.select(torch.arange(count))
    object.__setattr__(batch, "observed", observed)
    object.__setattr__(batch, "texel", torch.zeros(count, dtype=torch.long))
    return batch, normal_t, values


def test_jacobian_matches_finite_differences():
    batch, normal, values = _one_texel()
    _, jac = _sample_jacobian(batch, normal, values, jacobian=True)
    step = 1e-6
    for name, column in (("eta", 0), ("alpha_s", 1), ("rho_ss", 4)):
        plus = {**values, name: values[name] + step}
        minus = {**values, name: values[name] - step}
        numeric = (_sample_jacobian(batch, normal, plus, False)[0]
                   - _sample_jacobian(batch, normal, minus, False)[0]) / (2 * step)
        np.testing.assert_allclose(jac[..., column], numeric, rtol=1e-5, atol=1e-9 * numeric.abs().max())
    rho_plus = {**values, "rho3": values["rho3"] + torch.tensor([0.0, step, 0.0])}
    rho_minus = {**values, "rho3": values["rho3"] - torch.tensor([0.0, step, 0.0])}
    numeric = (_sample_jacobian(batch, normal, rho_plus, False)[0]
               - _sample_jacobian(batch, normal, rho_minus, False)[0]) / (2 * step)
    np.testing.assert_allclose(jac[..., 5 + 1], numeric, rtol=1e-5, atol=1e-12)  # channel 1's column


def test_std_scales_with_noise_and_with_the_number_of_samples():
    batch, normal, values = _one_texel()
    residual, jac = _sample_jacobian(batch, normal, values, jacobian=True)
    texel = batch.texel
    diag, _ = _texel_covariance(texel, residual, jac, 1, batch.channels)
    doubled, _ = _texel_covariance(texel, 2 * residual, jac, 1, batch.channels)
    np.testing.assert_allclose(doubled[:, :8].sqrt(), 2 * diag[:, :8].sqrt(), rtol=1e-9)  # std ~ noise
    repeat = 4
    many, _ = _texel_covariance(texel.repeat(repeat), residual.repeat(repeat, 1, 1),
                                jac.repeat(repeat, 1, 1, 1), 1, batch.channels.repeat(repeat, 1))
    n, p = 9 * batch.count, 7 + 3
    expected = np.sqrt((n - p) / (repeat * n - p))  # sigma^2 = chi2 / (n - p), J^T W J x repeat
    ratio = many[:, :8].sqrt() / diag[:, :8].sqrt()
    np.testing.assert_allclose(ratio, expected, rtol=1e-9)
    assert torch.isfinite(diag[0, :5]).all() and (diag[0, 0] > 0)


def test_bad_maps_are_named():
    class _Unwrap:
        resolution = (4, 4)

    with pytest.raises(ValueError, match="'eta'"):
        fit_diagnostics(_Unwrap(), {}, np.ones((4, 4), bool))
