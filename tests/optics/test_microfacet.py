"""GGX D and Smith G: normalisation, limits, Mitsuba 3 oracle, gradients, bad input."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from polarface.optics import ggx_d, smith_g, smith_g1, smith_g1_over_cos


def test_smoke_shapes_kinds():
    assert isinstance(ggx_d(0.9, 0.3), float)
    assert ggx_d(np.linspace(0, 1, 7), 0.3).shape == (7,)
    out = smith_g(torch.rand(2, 3), torch.rand(1, 3), torch.tensor(0.5))
    assert out.shape == (2, 3) and out.dtype == torch.float32


@pytest.mark.parametrize("alpha", [0.05, 0.2, 0.45, 0.95])
def test_ggx_normalisation(alpha):
    """The projected microfacet area equals the macro area: int D(h) cos theta_h dw = 1."""
    # substitute u = cos^2 theta: int_0^1 D(u) du * pi (azimuth 2 pi, d cos = du / (2 sqrt u))
    theta = torch.linspace(0, math.pi / 2, 400001, dtype=torch.float64)
    integrand = (
        ggx_d(torch.cos(theta), torch.tensor(alpha, dtype=torch.float64))
        * torch.cos(theta)
        * torch.sin(theta)
    )
    integral = 2 * math.pi * torch.trapezoid(integrand, theta)
    assert float(integral) == pytest.approx(1.0, abs=2e-4)


def test_reference_values():
    alpha = 0.45
    assert ggx_d(1.0, alpha) == pytest.approx(1.0 / (math.pi * alpha**2))
    assert ggx_d(-0.1, alpha) == 0.0 and ggx_d(0.0, alpha) == 0.0
    assert smith_g1(1.0, alpha) == pytest.approx(1.0)
    assert smith_g1(0.0, alpha) == 0.0
    tan2 = (1 - 0.6**2) / 0.6**2
    assert smith_g1(0.6, alpha) == pytest.approx(2 / (1 + math.sqrt(1 + alpha**2 * tan2)))
    assert smith_g(0.6, 0.8, alpha) == pytest.approx(smith_g1(0.6, alpha) * smith_g1(0.8, alpha))
    assert smith_g1_over_cos(0.0, alpha) == pytest.approx(2 / alpha)


@settings(max_examples=60, deadline=None)
@given(st.floats(-1, 1), st.floats(-1, 1), st.floats(0.01, 2.0))
def test_g_bounds(cos_i, cos_o, alpha):
    g = smith_g(cos_i, cos_o, alpha)
    assert 0.0 <= g <= 1.0 + 1e-12
    assert ggx_d(cos_i, alpha) >= 0.0


def test_mitsuba_oracle_ggx(mi):
    """D and separable G against ``mi.MicrofacetDistribution(GGX)`` on 300 random configurations.

    Mitsuba evaluates in float32: relative tolerance 2e-5 on D, absolute 2e-6 on G.
    """
    rng = np.random.default_rng(2)
    worst_d = worst_g = 0.0
    for _ in range(300):
        alpha = float(rng.uniform(0.05, 1.0))
        dist = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, alpha, False)
        wi, wo = rng.normal(size=3), rng.normal(size=3)
        wi[2], wo[2] = abs(wi[2]) + 0.05, abs(wo[2]) + 0.05
        wi, wo = wi / np.linalg.norm(wi), wo / np.linalg.norm(wo)
        h = (wi + wo) / np.linalg.norm(wi + wo)
        d_ref = dist.eval(mi.Vector3f(h))
        g_ref = dist.G(mi.Vector3f(wi), mi.Vector3f(wo), mi.Vector3f(h))
        worst_d = max(worst_d, abs(ggx_d(float(h[2]), alpha) - d_ref) / d_ref)
        worst_g = max(worst_g, abs(smith_g(float(wi[2]), float(wo[2]), alpha) - g_ref))
    assert worst_d < 2e-5, worst_d
    assert worst_g < 2e-6, worst_g


def test_gradcheck():
    cos = (torch.rand(5, dtype=torch.float64) * 0.9 + 0.05).requires_grad_(True)
    cos2 = (torch.rand(5, dtype=torch.float64) * 0.9 + 0.05).requires_grad_(True)
    alpha = (torch.rand(5, dtype=torch.float64) + 0.1).requires_grad_(True)
    assert torch.autograd.gradcheck(ggx_d, (cos, alpha))
    assert torch.autograd.gradcheck(smith_g1, (cos, alpha))
    assert torch.autograd.gradcheck(smith_g1_over_cos, (cos, alpha))
    assert torch.autograd.gradcheck(smith_g, (cos, cos2, alpha))


def test_grazing_gradients_finite():
    cos = torch.tensor([0.0, 1.0, -0.2], dtype=torch.float64, requires_grad=True)
    alpha = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
    (
        ggx_d(cos, alpha).sum() + smith_g(cos, cos, alpha).sum() + smith_g1_over_cos(cos, alpha).sum()
    ).backward()
    assert torch.isfinite(cos.grad).all() and torch.isfinite(alpha.grad).all()


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda: ggx_d(1.1, 0.3), "cos_theta_h"),
        (lambda: ggx_d(0.5, 0.0), "alpha"),
        (lambda: ggx_d(0.5, -0.3), "alpha"),
        (lambda: ggx_d(float("nan"), 0.3), "cos_theta_h"),
        (lambda: smith_g(0.5, 2.0, 0.3), "cos_theta_o"),
        (lambda: smith_g(np.zeros(2), np.zeros(3), 0.3), "cos_theta_i"),
        (lambda: smith_g1(0.5, float("inf")), "alpha"),
    ],
)
def test_bad_input(call, name):
    with pytest.raises(ValueError, match=name):
        call()
