"""Tests of polarface.skin.heterogeneous: layered texture-space rendering (Eq. simple_sss)."""

from __future__ import annotations

import pytest
import torch

from polarface.skin.heterogeneous import ProfileShapes, fit_layer_shapes, render_layered_subsurface
from polarface.skin.layers import compose_total_reflectance, layer_optics, layer_totals
from polarface.skin.spectral import default_wavelengths


@pytest.fixture(scope="module")
def shapes():
    wl = default_wavelengths()[[0, 7, 14]]
    optics = layer_optics(torch.tensor(0.05, dtype=torch.float64), 0.05, 0.03, 0.05, wl)
    return wl, fit_layer_shapes(optics)


def maps(wl, c_m, size=(24, 28)):
    optics = layer_optics(c_m, 0.05, 0.03, 0.05, wl)  # (H, W, L)
    totals = layer_totals(*optics)
    return [t.movedim(-1, 0) for t in totals]  # (L, H, W)


def test_homogeneous_interior_equals_r_bar(shapes):
    wl, s = shapes
    c_m = torch.full((40, 40), 0.05, dtype=torch.float64)
    totals = maps(wl, c_m)
    irradiance = torch.ones(40, 40, dtype=torch.float64)
    for n in (1, 3):
        out = render_layered_subsurface(irradiance, totals, s, 0.5, blurred_interreflections=n)
        r_bar = compose_total_reflectance(*[t[:, 0, 0] for t in totals])
        # Away from the borders (energy is re-concentrated there), the exitance equals R_bar E.
        centre = out[:, 18:22, 18:22]
        assert torch.allclose(centre, r_bar[:, None, None].expand_as(centre), rtol=1e-3)


def test_energy_balance_heterogeneous(shapes):
    wl, s = shapes
    g = torch.Generator().manual_seed(0)
    c_m = 0.02 + 0.2 * torch.rand(24, 28, dtype=torch.float64, generator=g)
    totals = maps(wl, c_m)
    irradiance = torch.rand(24, 28, dtype=torch.float64, generator=g)
    out = render_layered_subsurface(irradiance, totals, s, 0.1)
    # Heterogeneous: not local, but total exitance lies between the extreme local albedos x input.
    r_bar = compose_total_reflectance(*totals)
    total_in = irradiance.sum()
    assert bool((out.sum((-2, -1)) <= (r_bar.amax((-2, -1)) * total_in) * (1 + 1e-9)).all())
    assert bool((out.sum((-2, -1)) >= (r_bar.amin((-2, -1)) * total_in) * (1 - 1e-9)).all())
    assert out.shape == (3, 24, 28)


def test_blur_spreads_a_point_light(shapes):
    wl, s = shapes
    totals = maps(wl, torch.full((33, 33), 0.05, dtype=torch.float64))
    irradiance = torch.zeros(33, 33, dtype=torch.float64)
    irradiance[16, 16] = 1.0
    out = render_layered_subsurface(irradiance, totals, s, 0.1)
    # Red light travels further than blue (less absorption): more energy outside the centre texel.
    spread = 1 - out[:, 16, 16] / out.sum((-2, -1))
    assert float(spread[2]) > float(spread[0])
    r_bar = compose_total_reflectance(*[t[:, 0, 0] for t in totals])
    assert torch.allclose(out.sum((-2, -1)), r_bar, rtol=1e-3)


def test_mask_keeps_light_inside(shapes):
    wl, s = shapes
    totals = maps(wl, torch.full((20, 20), 0.05, dtype=torch.float64))
    mask = torch.zeros(20, 20, dtype=torch.float64)
    mask[4:16, 4:16] = 1
    out = render_layered_subsurface(torch.ones(20, 20, dtype=torch.float64), totals, s, 0.2, mask=mask)
    assert float(out[:, mask == 0].abs().max()) == 0.0


def test_errors(shapes):
    wl, s = shapes
    totals = maps(wl, torch.full((8, 8), 0.05, dtype=torch.float64))
    e = torch.ones(8, 8, dtype=torch.float64)
    with pytest.raises(ValueError, match="blurred_interreflections"):
        render_layered_subsurface(e, totals, s, 0.1, blurred_interreflections=0)
    bad = list(totals)
    bad[0] = bad[0] + 2
    with pytest.raises(ValueError, match="r_out_f"):
        render_layered_subsurface(e, bad, s, 0.1)
    with pytest.raises(ValueError, match="irradiance"):
        render_layered_subsurface(e * float("nan"), totals, s, 0.1)


def test_gradcheck():
    uniform = torch.full((3, 9), 1 / 9, dtype=torch.float64)
    s = ProfileShapes(uniform, uniform, uniform, uniform, uniform)
    g = torch.Generator().manual_seed(1)
    totals = [
        (0.1 + 0.3 * torch.rand(3, 6, 5, dtype=torch.float64, generator=g)).requires_grad_(True)
        for _ in range(5)
    ]
    e = torch.rand(6, 5, dtype=torch.float64, generator=g).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x, *t: render_layered_subsurface(x, t, s, 0.02), (e, *totals))
