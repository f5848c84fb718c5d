"""Tests of polarface.skin.sog: NNLS fits of skin profiles, delta blurs, energy conservation."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from polarface.skin.heterogeneous import fit_layer_shapes
from polarface.skin.layers import layer_optics
from polarface.skin.sog import (
    default_radial_grid,
    fit_sog,
    gaussian_2d,
    gaussian_blur,
    sog_blur,
    sog_profile,
    sog_variances,
)
from polarface.skin.spectral import default_wavelengths


def test_variances_and_gaussian_normalisation():
    v = sog_variances()
    assert v.shape == (9,) and v[0] == pytest.approx(1e-4) and v[8] == pytest.approx(1e-4 * 4**8)
    r = default_radial_grid(r_max_mm=30.0, count=20001)
    mass = torch.trapezoid(2 * math.pi * r * gaussian_2d(torch.tensor(0.5, dtype=torch.float64), r), r)
    assert float(mass) == pytest.approx(1.0, rel=1e-6)
    with pytest.raises(ValueError, match="variance_mm2"):
        gaussian_2d(0.0, 1.0)


def test_fit_recovers_exact_sum_of_gaussians():
    r = default_radial_grid()
    weights = torch.tensor([0.0, 0.3, 0.0, 0.1, 0.2, 0.0, 0.05, 0.0, 0.01], dtype=torch.float64)
    fit = fit_sog(r, sog_profile(weights, r))
    assert torch.allclose(fit.weights, weights, atol=1e-8)
    assert float(fit.relative_error) < 1e-8
    assert bool((fit.weights >= 0).all())


def test_fit_is_nonnegative_and_optimal_against_perturbation():
    r = default_radial_grid()
    profile = torch.exp(-r / 0.7) / r.clamp_min(0.05)  # not a SoG
    fit = fit_sog(r, profile)
    assert bool((fit.weights >= 0).all())
    quad = torch.zeros_like(r)
    dr = r.diff()
    quad[1:] += dr / 2
    quad[:-1] += dr / 2

    def objective(w):
        return float((((profile - sog_profile(w, r)) ** 2) * r * quad).sum())

    best = objective(fit.weights)
    g = torch.Generator().manual_seed(0)
    for _ in range(50):
        trial = (fit.weights + 1e-3 * torch.randn(9, generator=g, dtype=torch.float64)).clamp_min(0)
        assert objective(trial) >= best - 1e-12


def test_skin_profile_fits_are_accurate():
    wl = default_wavelengths()
    optics = layer_optics(torch.tensor(0.05, dtype=torch.float64), 0.05, 0.03, 0.05, wl)
    shapes = fit_layer_shapes(optics)
    errors = shapes.relative_error  # (5, 15)
    assert errors.shape == (5, 15)
    # Bound: 6 % relative L2 error per profile.
    assert float(errors.max()) < 0.06
    for w in shapes[:5]:
        assert torch.allclose(w.sum(-1), torch.ones(15, dtype=torch.float64))


def test_fit_weights_sum_close_to_profile_total():
    from polarface.skin.multipole import slab_profiles

    r = default_radial_grid()
    profile, _ = slab_profiles(r, 0.3, 4.0, math.inf, 1.4)
    fit = fit_sog(r, profile)
    assert float(fit.weights.sum()) == pytest.approx(float(fit.total), rel=0.02)


def test_fit_errors():
    r = default_radial_grid(count=50)
    with pytest.raises(ValueError, match="profile"):
        fit_sog(r, torch.ones(49, dtype=torch.float64))
    with pytest.raises(ValueError, match="increasing"):
        fit_sog(r.flip(0), torch.ones(50, dtype=torch.float64))
    with pytest.raises(ValueError, match="profile"):
        fit_sog(r, torch.full((50,), float("nan"), dtype=torch.float64))


@pytest.mark.parametrize("texel", [0.05, 0.2])
def test_blur_of_delta_equals_sum_of_gaussians(texel):
    size = 129
    image = torch.zeros(size, size, dtype=torch.float64)
    image[64, 64] = 1.0
    weights = torch.tensor([0.1, 0.1, 0.2, 0.2, 0.2, 0.1, 0.1, 0.0, 0.0], dtype=torch.float64)
    out = sog_blur(image, weights, texel)
    # Reference: each Gaussian integrated over the texel squares (separable erf product).
    coords = (torch.arange(size, dtype=torch.float64) - 64) * texel
    ref = torch.zeros_like(image)
    for w, v in zip(weights, sog_variances(), strict=True):
        s = math.sqrt(float(v)) * math.sqrt(2)
        one_d = 0.5 * (torch.erf((coords + texel / 2) / s) - torch.erf((coords - texel / 2) / s))
        ref += w * one_d[:, None] * one_d[None, :]
    assert torch.allclose(out, ref, atol=2e-4 * float(ref.max()))
    if texel > 0.1:
        return  # texel averaging differs from point samples by ~(texel/sigma)^2 in the tails
    # And in density form, away from the centre, it matches G(v, r) point samples.
    r = torch.sqrt(coords[:, None] ** 2 + coords[None, :] ** 2)
    density = sog_profile(weights, r.reshape(-1)).reshape(size, size) * texel**2
    far = r > 1.0
    assert torch.allclose(out[far], density[far], rtol=0.02, atol=1e-7)


@pytest.mark.parametrize("corner", [(0, 0), (36, 52), (0, 52)])
def test_blur_of_corner_delta_on_prime_sized_map(corner):
    """Maps whose padded size has large prime factors are transformed at a longer, fast length: the
    blur is still the kernel renormalised to its mass inside the map, with nothing wrapped around."""
    height, width, texel = 37, 53, 0.2
    image = torch.zeros(height, width, dtype=torch.float64)
    image[corner] = 1.0
    weights = torch.tensor([0.0, 0.0, 0.1, 0.1, 0.2, 0.2, 0.2, 0.1, 0.1], dtype=torch.float64)
    out = sog_blur(image, weights, texel)

    def one_d(offsets: torch.Tensor, variance: float) -> torch.Tensor:
        s = math.sqrt(2.0 * variance)
        return 0.5 * (torch.erf((offsets + 0.5) * texel / s) - torch.erf((offsets - 0.5) * texel / s))

    rows = torch.arange(height, dtype=torch.float64) - corner[0]
    cols = torch.arange(width, dtype=torch.float64) - corner[1]
    kernel = sum(w * one_d(rows, float(v))[:, None] * one_d(cols, float(v))[None, :]
                 for w, v in zip(weights, sog_variances(), strict=True))
    assert torch.allclose(out, kernel / kernel.sum(), rtol=1e-9, atol=1e-15)


@settings(max_examples=15, deadline=None)
@given(
    texel=st.floats(0.02, 0.5),
    variance=st.sampled_from([1e-4, 4e-3, 0.0256, 0.41, 6.5]),
    masked=st.booleans(),
)
def test_energy_conserved(texel, variance, masked):
    g = torch.Generator().manual_seed(1)
    image = torch.rand(2, 40, 48, dtype=torch.float64, generator=g)
    mask = (torch.rand(40, 48, generator=g) > 0.3).double() if masked else None
    expected = (image * (mask if mask is not None else 1)).sum((-2, -1))
    out = gaussian_blur(image, variance, texel, mask=mask)
    assert torch.allclose(out.sum((-2, -1)), expected, rtol=1e-10)
    weights = torch.softmax(torch.randn(2, 9, generator=g, dtype=torch.float64), -1)
    out = sog_blur(image, weights, texel, mask=mask)
    assert torch.allclose(out.sum((-2, -1)), expected, rtol=1e-9)
    if mask is not None:
        assert float(out[..., mask == 0].abs().max()) == 0.0


def test_stretch_map_blur():
    g = torch.Generator().manual_seed(2)
    image = torch.rand(30, 34, dtype=torch.float64, generator=g)
    ones = torch.ones(30, 34, 2, dtype=torch.float64)
    # Uniform stretch equals the global path.
    a = gaussian_blur(image, 0.01, 0.05, stretch=ones)
    b = gaussian_blur(image, 0.01, 0.05)
    assert torch.allclose(a, b, atol=1e-12)
    # Stretch 2 = texels twice as large = half the blur width in texels.
    c = gaussian_blur(image, 0.01, 0.05, stretch=2 * ones)
    d = gaussian_blur(image, 0.01, 0.1)
    assert torch.allclose(c, d, atol=1e-12)
    # Varying stretch conserves energy.
    stretch = 0.5 + torch.rand(30, 34, 2, dtype=torch.float64, generator=g)
    e = sog_blur(image, torch.full((9,), 1 / 9, dtype=torch.float64), 0.05, stretch=stretch)
    assert float(e.sum()) == pytest.approx(float(image.sum()), rel=1e-10)


def test_blur_shapes_dtype_and_errors():
    image = torch.rand(3, 2, 16, 16)
    out = sog_blur(image, torch.full((2, 9), 1 / 9), 0.1)
    assert out.shape == (3, 2, 16, 16) and out.dtype == torch.float32
    with pytest.raises(ValueError, match="texel_size_mm"):
        gaussian_blur(image, 0.1, 0.0)
    with pytest.raises(ValueError, match="variance_mm2"):
        gaussian_blur(image, -1.0, 0.1)
    with pytest.raises(ValueError, match="image"):
        gaussian_blur(torch.tensor([float("nan"), 1.0]).reshape(1, 2), 0.1, 0.1)
    with pytest.raises(ValueError, match="stretch"):
        gaussian_blur(image, 0.1, 0.1, stretch=torch.ones(16, 16))
    with pytest.raises(ValueError, match="weights"):
        sog_blur(image, -torch.ones(9), 0.1)


def test_gradcheck_blurs():
    image = torch.rand(1, 12, 10, dtype=torch.float64, requires_grad=True)
    weights = torch.rand(9, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x, w: sog_blur(x, w, 0.05), (image, weights))
    stretch = (0.5 + torch.rand(12, 10, 2, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x, s: gaussian_blur(x, 0.003, 0.05, stretch=s), (image, stretch))


@pytest.mark.slow
def test_blur_1024_timing():
    import time

    image = torch.rand(1024, 1024)
    weights = torch.full((9,), 1 / 9)
    sog_blur(image, weights, 0.1)
    start = time.perf_counter()
    sog_blur(image, weights, 0.1)
    assert time.perf_counter() - start < 3.0  # loose bound for shared CI machines
