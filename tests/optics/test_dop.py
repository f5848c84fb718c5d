"""Diffuse and specular DoP: closed forms vs Fresnel ratios, bounds, inverses, gradients, bad input."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from polarface.optics import (
    brewster_angle,
    diffuse_dop,
    fresnel_terms,
    max_diffuse_dop,
    specular_dop,
    zenith_from_diffuse_dop,
    zenith_from_specular_dop,
)

etas = st.floats(1.01, 2.5)
zeniths = st.floats(0.0, math.pi / 2)


def test_smoke_kinds():
    assert isinstance(diffuse_dop(1.5, 0.5), float)
    assert diffuse_dop(np.array([1.4, 1.5]), np.array([0.1, 0.2])).shape == (2,)
    assert specular_dop(torch.tensor([1.5], dtype=torch.float32), torch.zeros(4, 1)).shape == (4, 1)


def test_reference_values():
    assert diffuse_dop(1.5, 0.0) == 0.0 and specular_dop(1.5, 0.0) == 0.0
    assert specular_dop(1.5, math.atan(1.5)) == pytest.approx(1.0, abs=1e-12)
    assert specular_dop(1.5, math.pi / 2) == pytest.approx(0.0, abs=1e-12)
    n = 1.5
    assert max_diffuse_dop(n) == pytest.approx((n - 1 / n) ** 2 / (2 + 2 * n * n - (n + 1 / n) ** 2))
    # float32 pi/2 rounds above pi/2: accepted and clamped
    assert torch.isfinite(diffuse_dop(torch.tensor(1.5), torch.tensor(math.pi / 2, dtype=torch.float32)))


@settings(max_examples=60, deadline=None)
@given(etas, zeniths)
def test_dop_equals_fresnel_ratios_and_bounds(eta, theta):
    terms = fresnel_terms(math.cos(theta), eta)
    d = diffuse_dop(eta, theta)
    s = specular_dop(eta, theta)
    assert 0.0 <= d <= 1.0 and 0.0 <= s <= 1.0 + 1e-12
    if theta < math.pi / 2 - 1e-4:  # at grazing T+ -> 0 and the ratio is 0/0 numerically
        assert d == pytest.approx(abs(terms.t_minus / terms.t_plus), abs=1e-8)
    if terms.r_plus > 1e-12 and theta < math.pi / 2 - 1e-6:
        assert s == pytest.approx(terms.r_minus / terms.r_plus, abs=1e-9)


def test_diffuse_monotone():
    theta = torch.linspace(0, math.pi / 2, 1000, dtype=torch.float64)
    d = diffuse_dop(torch.tensor(1.44, dtype=torch.float64), theta)
    assert bool((d[1:] > d[:-1]).all())


@settings(max_examples=40, deadline=None)
@given(etas, st.floats(0.0, math.pi / 2 - 1e-3))
def test_inverse_diffuse_round_trip(eta, theta):
    dop = diffuse_dop(eta, theta)
    assert zenith_from_diffuse_dop(dop, eta) == pytest.approx(theta, abs=1e-6 if theta > 1e-3 else 1e-3)


@settings(max_examples=40, deadline=None)
@given(etas, st.floats(0.0, 1.0))
def test_inverse_specular_two_branches(eta, dop):
    below, above = zenith_from_specular_dop(dop, eta)
    brewster = brewster_angle(eta)
    assert 0.0 <= below <= brewster + 1e-9
    assert brewster - 1e-9 <= above <= math.pi / 2 + 1e-12
    assert specular_dop(eta, below) == pytest.approx(dop, abs=1e-7)
    assert specular_dop(eta, above) == pytest.approx(dop, abs=1e-7)


def test_inverse_clamp_above_max():
    eta = 1.4
    assert zenith_from_diffuse_dop(0.9, eta) == pytest.approx(math.pi / 2)
    assert zenith_from_diffuse_dop(max_diffuse_dop(eta), eta) == pytest.approx(math.pi / 2)


def test_inverse_float32():
    theta = torch.tensor([0.3, 0.8, 1.2], dtype=torch.float32)
    eta = torch.tensor(1.44, dtype=torch.float32)
    back = zenith_from_diffuse_dop(diffuse_dop(eta, theta), eta)
    assert back.dtype == torch.float32
    torch.testing.assert_close(back, theta, atol=2e-4, rtol=0)


def test_gradcheck():
    eta = (torch.rand(4, dtype=torch.float64) + 1.2).requires_grad_(True)
    theta = (torch.rand(4, dtype=torch.float64) * 1.4 + 0.05).requires_grad_(True)
    assert torch.autograd.gradcheck(diffuse_dop, (eta, theta))
    assert torch.autograd.gradcheck(specular_dop, (eta, theta))
    assert torch.autograd.gradcheck(max_diffuse_dop, (eta,))
    dop = torch.tensor([0.05, 0.1, 0.2, 0.25], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(zenith_from_diffuse_dop, (dop, eta))
    dop_s = torch.tensor([0.1, 0.4, 0.7, 0.9], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p, e: zenith_from_specular_dop(p, e), (dop_s, eta))


def test_inverse_gradient_matches_forward_slope():
    eta = torch.tensor(1.5, dtype=torch.float64)
    theta = torch.tensor(0.9, dtype=torch.float64, requires_grad=True)
    dop = diffuse_dop(eta, theta)
    (slope,) = torch.autograd.grad(dop, theta)
    dop_leaf = dop.detach().requires_grad_(True)
    (inverse_slope,) = torch.autograd.grad(zenith_from_diffuse_dop(dop_leaf, eta), dop_leaf)
    assert float(inverse_slope) == pytest.approx(1 / float(slope), rel=1e-6)


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda: diffuse_dop(1.0, 0.3), "eta"),
        (lambda: diffuse_dop(1.5, -0.1), "theta_o"),
        (lambda: diffuse_dop(1.5, 2.0), "theta_o"),
        (lambda: specular_dop(1.5, float("nan")), "theta"),
        (lambda: zenith_from_diffuse_dop(1.2, 1.5), "dop"),
        (lambda: zenith_from_specular_dop(-0.1, 1.5), "dop"),
        (lambda: zenith_from_diffuse_dop(np.zeros(2), np.full(3, 1.5)), "dop"),
    ],
)
def test_bad_input(call, name):
    with pytest.raises(ValueError, match=name):
        call()
