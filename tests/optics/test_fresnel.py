"""Fresnel scalars: reference values, R + T = 1, pypolar oracle, gradients, bad input."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from polarface.optics import (
    brewster_angle,
    fresnel_reflectance,
    fresnel_terms,
    fresnel_transmittance,
    fresnel_transmittance_exit,
)

cosines = st.floats(-1.0, 1.0, allow_nan=False)
etas = st.floats(1.0001, 3.0, allow_nan=False)


def test_smoke_kinds_and_dtypes():
    r_perp, r_par = fresnel_reflectance(0.5, 1.5)
    assert isinstance(r_perp, float) and isinstance(r_par, float)
    out = fresnel_reflectance(np.linspace(0, 1, 5), 1.4)
    assert isinstance(out[0], np.ndarray) and out[0].shape == (5,)
    t32 = fresnel_transmittance(torch.rand(3, 2, dtype=torch.float32), torch.tensor(1.5))
    assert t32[0].dtype == torch.float32 and t32[0].shape == (3, 2)


def test_broadcast_shapes():
    r_perp, _ = fresnel_reflectance(
        torch.rand(4, 1, dtype=torch.float64), torch.full((1, 3), 1.5, dtype=torch.float64)
    )
    assert r_perp.shape == (4, 3)


@pytest.mark.parametrize("eta", [1.33, 1.44, 1.5, 2.4])
def test_normal_incidence_reference(eta):
    r_perp, r_par = fresnel_reflectance(1.0, eta)
    expected = ((eta - 1) / (eta + 1)) ** 2
    assert r_perp == pytest.approx(expected, rel=1e-12)
    assert r_par == pytest.approx(expected, rel=1e-12)


def test_brewster_and_grazing():
    eta = 1.5
    theta_b = brewster_angle(eta)
    assert theta_b == pytest.approx(math.atan(1.5))
    _, r_par = fresnel_reflectance(math.cos(theta_b), eta)
    assert r_par == pytest.approx(0.0, abs=1e-15)
    r_perp, r_par = fresnel_reflectance(0.0, eta)
    assert r_perp == pytest.approx(1.0) and r_par == pytest.approx(1.0)
    # documented clamp: negative cosines behave as grazing
    assert fresnel_reflectance(-0.3, eta)[0] == pytest.approx(1.0)


def test_known_value_glass_45deg():
    # Hecht, Optics: n = 1.5 at 45 deg: R_s = 0.0920, R_p = 0.00847
    r_perp, r_par = fresnel_reflectance(math.cos(math.radians(45)), 1.5)
    assert r_perp == pytest.approx(0.0920, abs=5e-4)
    assert r_par == pytest.approx(0.00847, abs=5e-5)


@settings(max_examples=60, deadline=None)
@given(cosines, etas)
def test_energy_conservation(cos, eta):
    r_perp, r_par = fresnel_reflectance(cos, eta)
    t_perp, t_par = fresnel_transmittance(cos, eta)
    assert r_perp + t_perp == pytest.approx(1.0, abs=1e-12)
    assert r_par + t_par == pytest.approx(1.0, abs=1e-12)
    assert 0.0 <= r_par <= r_perp <= 1.0 + 1e-12
    terms = fresnel_terms(cos, eta)
    assert terms.t_plus == pytest.approx(1 - terms.r_plus, abs=1e-12)
    assert terms.t_minus == pytest.approx(-terms.r_minus, abs=1e-12)
    assert terms.r_cross <= terms.r_plus + 1e-12  # AM-GM
    assert terms.t_cross <= terms.t_plus + 1e-12


def test_exit_equals_transmittance_by_reciprocity():
    cos = torch.linspace(0, 1, 11, dtype=torch.float64)
    a = fresnel_transmittance(cos, 1.44)
    b = fresnel_transmittance_exit(cos, 1.44)
    torch.testing.assert_close(a[0], b[0])
    torch.testing.assert_close(a[1], b[1])


def test_reciprocity_against_internal_incidence():
    """Transmittance from inside at theta_t equals that from outside at theta_o (Stokes relations)."""
    import pypolar.fresnel as pf

    eta = 1.44
    theta_o = np.linspace(0.0, 1.5, 40)
    theta_t = np.arcsin(np.sin(theta_o) / eta)
    inside_perp = pf.T_per(1.0, theta_t, n_i=eta)
    inside_par = pf.T_par(1.0, theta_t, n_i=eta)
    t_perp, t_par = fresnel_transmittance_exit(np.cos(theta_o), eta)
    np.testing.assert_allclose(t_perp, inside_perp, atol=1e-10)
    np.testing.assert_allclose(t_par, inside_par, atol=1e-10)


def test_pypolar_oracle_powers():
    """Independent oracle: pypolar's Fresnel powers on 500 random angles and indices.

    Tolerance 1e-10 absolute (both float64); pypolar's T includes the n cos ratio, so T = 1 - R checks
    our energy-conserving convention too.
    """
    import pypolar.fresnel as pf

    rng = np.random.default_rng(3)
    theta = rng.uniform(0.0, math.pi / 2 - 1e-6, 500)
    eta = rng.uniform(1.05, 2.5, 500)
    r_perp, r_par = fresnel_reflectance(np.cos(theta), eta)
    t_perp, t_par = fresnel_transmittance(np.cos(theta), eta)
    ref = {
        "r_perp": np.array([pf.R_per(m, t) for m, t in zip(eta, theta)]),
        "r_par": np.array([pf.R_par(m, t) for m, t in zip(eta, theta)]),
        "t_perp": np.array([pf.T_per(m, t) for m, t in zip(eta, theta)]),
        "t_par": np.array([pf.T_par(m, t) for m, t in zip(eta, theta)]),
    }
    ours = {"r_perp": r_perp, "r_par": r_par, "t_perp": t_perp, "t_par": t_par}
    for key, value in ref.items():
        np.testing.assert_allclose(ours[key], value, atol=1e-10, err_msg=key)
    brewster = [pf.brewster(m) for m in eta[:20]]
    np.testing.assert_allclose(brewster_angle(eta[:20]), brewster, atol=1e-12)


@pytest.mark.parametrize("func", [fresnel_reflectance, fresnel_transmittance, fresnel_transmittance_exit])
def test_gradcheck(func):
    cos = torch.rand(6, dtype=torch.float64) * 0.98 + 0.01
    cos.requires_grad_(True)
    eta = (torch.rand(6, dtype=torch.float64) + 1.2).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda c, e: func(c, e), (cos, eta))


def test_gradcheck_terms_and_brewster_crossing():
    eta = torch.tensor([1.5], dtype=torch.float64, requires_grad=True)
    # angles around the Brewster angle (56.31 deg), away from the exact kink of r_cross
    cos = torch.cos(torch.deg2rad(torch.tensor([40.0, 55.0, 58.0, 80.0], dtype=torch.float64)))
    cos.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda c, e: tuple(fresnel_terms(c, e)), (cos, eta))
    assert torch.autograd.gradcheck(brewster_angle, (eta,))


def test_gradients_finite_at_grazing_and_normal():
    cos = torch.tensor([0.0, 1.0, -0.5], dtype=torch.float64, requires_grad=True)
    eta = torch.tensor(1.4, dtype=torch.float64, requires_grad=True)
    total = sum(t.sum() for t in fresnel_terms(cos, eta))
    total.backward()
    assert torch.isfinite(cos.grad).all() and torch.isfinite(eta.grad).all()


@pytest.mark.parametrize(
    ("cos", "eta", "name"),
    [
        (float("nan"), 1.5, "cos_theta_i"),
        (0.5, float("inf"), "eta"),
        (1.2, 1.5, "cos_theta_i"),
        (-1.01, 1.5, "cos_theta_i"),
        (0.5, 1.0, "eta"),
        (0.5, 0.8, "eta"),
    ],
)
def test_bad_input(cos, eta, name):
    with pytest.raises(ValueError, match=name):
        fresnel_reflectance(cos, eta)
    with pytest.raises(ValueError, match=name):
        fresnel_transmittance(cos, eta)


def test_mismatched_shapes_named():
    with pytest.raises(ValueError, match="cos_theta_i"):
        fresnel_reflectance(np.zeros(3), np.full(4, 1.5))
    with pytest.raises(ValueError, match="eta"):
        brewster_angle(1.0)
