"""Tests of polarface.skin.multipole: closed-form totals vs integration, adding-doubling oracle."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import quad

from polarface.skin import multipole as mp
from polarface.skin.multipole import fresnel_diffuse_reflectance, slab_profiles, slab_totals

GRID = [
    (sa, ss, d, eta)
    for sa in (0.02, 0.5, 5.0)
    for ss in (1.0, 8.0)
    for d in (0.25, 1.0, math.inf)
    for eta in (1.0, 1.4)
]


@pytest.mark.parametrize(("sigma_a", "sigma_s_prime", "thickness", "eta"), GRID)
def test_closed_form_equals_numerical_integration(sigma_a, sigma_s_prime, thickness, eta):
    # Erratum (docs/conventions.md): 2 pi int P r dr = (alpha'/2) sign(z) exp(-sigma |z|).
    r_total, t_total = slab_totals(sigma_a, sigma_s_prime, thickness, eta, 1.0)

    def integrand(r: float, which: int) -> float:
        return 2 * math.pi * r * slab_profiles(r, sigma_a, sigma_s_prime, thickness, eta, 1.0)[which]

    r_num = quad(integrand, 0, math.inf, args=(0,), epsabs=0, epsrel=1e-11, limit=400)[0]
    assert r_total == pytest.approx(r_num, rel=1e-4)
    if math.isinf(thickness):
        assert t_total == 0.0
    else:
        t_num = quad(integrand, 0, math.inf, args=(1,), epsabs=0, epsrel=1e-11, limit=400)[0]
        assert t_total == pytest.approx(t_num, rel=1e-4, abs=1e-10)


def test_geometric_series_equals_pole_by_pole_sum():
    g = torch.Generator().manual_seed(3)
    n = 500
    sa = torch.rand(n, dtype=torch.float64, generator=g) * 20
    sa[:5] = 0.0
    ss = torch.rand(n, dtype=torch.float64, generator=g) * 20 + 0.5
    d = torch.rand(n, dtype=torch.float64, generator=g) * 2 + 0.05
    d[::7] = math.inf
    e1 = 1 + torch.rand(n, dtype=torch.float64, generator=g) * 0.6
    e2 = 0.8 + torch.rand(n, dtype=torch.float64, generator=g) * 0.8
    for poles in (0, 1, 4, 16):
        a = mp._explicit_totals(sa, ss, d, e1, e2, poles)
        b = mp.slab_totals_unchecked(sa, ss, d, e1, e2, poles)
        assert torch.allclose(a[0], b[0], atol=1e-13) and torch.allclose(a[1], b[1], atol=1e-13)


def test_dipole_matches_jensen_closed_form():
    # Jensen et al. 2001: Rd = (a'/2)(1 + exp(-4/3 A sqrt(3(1-a')))) exp(-sqrt(3(1-a'))).
    sa, ss, eta = 0.1, 2.0, 1.3
    albedo = ss / (sa + ss)
    f_dr = fresnel_diffuse_reflectance(eta)
    a = (1 + f_dr) / (1 - f_dr)
    root = math.sqrt(3 * (1 - albedo))
    expected = 0.5 * albedo * (1 + math.exp(-4 / 3 * a * root)) * math.exp(-root)
    assert slab_totals(sa, ss, math.inf, eta)[0] == pytest.approx(expected, rel=1e-12)


def test_pole_count_converges():
    r16 = slab_totals(0.05, 3.0, 0.5, 1.4, 1.0, n_poles=16)
    r40 = slab_totals(0.05, 3.0, 0.5, 1.4, 1.0, n_poles=40)
    assert r16[0] == pytest.approx(r40[0], rel=1e-6) and r16[1] == pytest.approx(r40[1], rel=1e-6)


def test_forward_backward_swaps_surfaces():
    rf, tf, rb, tb = mp.slab_totals_forward_backward(0.3, 5.0, 0.25, 1.4, 1.0)
    assert rb == pytest.approx(slab_totals(0.3, 5.0, 0.25, 1.0, 1.4)[0])
    assert rf != pytest.approx(rb)
    # Symmetric boundaries: forward == backward.
    rf, tf, rb, tb = mp.slab_totals_forward_backward(0.3, 5.0, 0.25, 1.3, 1.3)
    assert rf == pytest.approx(rb) and tf == pytest.approx(tb)


@settings(max_examples=40, deadline=None)
@given(
    sigma_a=st.floats(0.01, 50.0),
    sigma_s_prime=st.floats(0.5, 50.0),
    thickness=st.floats(0.2, 5.0),
    eta=st.floats(1.0, 1.6),
)
def test_energy_bounds_for_optically_thick_slabs(sigma_a, sigma_s_prime, thickness, eta):
    # Physics: with >= 2 transport mean free paths, R, T >= 0 and R + T <= albedo.
    if (sigma_a + sigma_s_prime) * thickness < 2.0:
        return
    r, t = slab_totals(sigma_a, sigma_s_prime, thickness, eta)
    assert r >= 0 and t >= -1e-12
    assert r + t <= sigma_s_prime / (sigma_a + sigma_s_prime) + 1e-9


def test_monotonic_in_absorption():
    sa = torch.linspace(0.01, 10, 50, dtype=torch.float64)
    r, t = slab_totals(sa, torch.tensor(4.0, dtype=torch.float64), 0.5, 1.4)
    assert bool((r.diff() < 0).all()) and bool((t.diff() < 0).all())


def test_shapes_broadcast_and_dtypes():
    sa = torch.rand(4, 1, dtype=torch.float32) + 0.1
    ss = torch.rand(1, 3, dtype=torch.float32) + 1
    thickness = torch.tensor([0.25, math.inf, 1.0], dtype=torch.float32)
    r, t = slab_totals(sa, ss, thickness, 1.4)
    assert r.shape == (4, 3) and r.dtype == torch.float32
    assert bool((t[:, 1] == 0).all())
    rr, _tt = slab_profiles(torch.linspace(0, 3, 7)[:, None], sa[0], ss[0], 0.25, 1.4)
    assert rr.shape == (7, 3) and rr.dtype == torch.float32
    out = slab_totals(np.array([0.1, 0.2]), 2.0, 0.5, 1.4)
    assert isinstance(out[0], np.ndarray)


def test_bad_input():
    with pytest.raises(ValueError, match="sigma_a"):
        slab_totals(-0.1, 1.0, 1.0, 1.4)
    with pytest.raises(ValueError, match="sigma_s_prime"):
        slab_totals(0.1, 0.0, 1.0, 1.4)
    with pytest.raises(ValueError, match="thickness_mm"):
        slab_totals(0.1, 1.0, 0.0, 1.4)
    with pytest.raises(ValueError, match="thickness_mm"):
        slab_totals(0.1, 1.0, float("nan"), 1.4)
    with pytest.raises(ValueError, match="eta"):
        slab_totals(0.1, 1.0, 1.0, -1.0)
    with pytest.raises(ValueError, match="sigma_a"):
        slab_totals(float("nan"), 1.0, 1.0, 1.4)
    with pytest.raises(ValueError, match="n_poles"):
        slab_totals(0.1, 1.0, 1.0, 1.4, n_poles=-1)
    with pytest.raises(ValueError, match="broadcast"):
        slab_totals(torch.ones(3), torch.ones(4), 1.0, 1.4)
    with pytest.raises(ValueError, match="r_mm"):
        slab_profiles(-1.0, 0.1, 1.0, 1.0, 1.4)


def test_gradcheck_totals_and_profiles():
    sa = torch.tensor([0.2, 1.5], dtype=torch.float64, requires_grad=True)
    ss = torch.tensor([3.0, 6.0], dtype=torch.float64, requires_grad=True)
    d = torch.tensor([0.3, 0.8], dtype=torch.float64, requires_grad=True)
    eta = torch.tensor([1.3, 1.45], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b, c, e: slab_totals(a, b, c, e, 1.0), (sa, ss, d, eta))
    r = torch.tensor([0.05, 0.7], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a, b: slab_profiles(r, a, b, 0.5, 1.4), (sa, ss))


def test_fresnel_diffuse_reflectance_values():
    # Egan & Hilgeman fit: ~0.44 for 1.3 (Jensen 2001 uses it), about 0 at index match.
    assert fresnel_diffuse_reflectance(1.3) == pytest.approx(0.4446, abs=1e-3)
    assert abs(fresnel_diffuse_reflectance(1.0)) < 3e-3
    with pytest.raises(ValueError, match="eta"):
        fresnel_diffuse_reflectance(0.0)
