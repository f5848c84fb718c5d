"""Texture-space subsurface scattering of the simulator: energy and wavelength dependence."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from polarface.render.subsurface import SubsurfaceModel, texture_space_exitance
from polarface.skin.spectral import default_spectral_calibration


def _uniform_chromophores(shape, c_m=0.05, beta_m=0.05, c_h_in=0.03, c_h_out=0.05):
    return {
        name: np.full(shape, value, np.float32)
        for name, value in (("c_m", c_m), ("beta_m", beta_m), ("c_h_in", c_h_in), ("c_h_out", c_h_out))
    }


@pytest.fixture(scope="module")
def model(patch):
    _, raster = patch
    calibration = default_spectral_calibration()
    return SubsurfaceModel.build(
        _uniform_chromophores(raster.mask.shape), raster, calibration.wavelengths_nm
    ), calibration


def test_shapes_and_texel_size(model, patch):
    subsurface, _ = model
    _, raster = patch
    assert subsurface.totals.r_out_f.shape == (15, *raster.mask.shape)
    assert subsurface.shapes.r_out_f.shape == (15, 9)
    assert subsurface.texel_size_mm == pytest.approx(40.0 / 64, rel=1e-3)


def test_energy_conserved_and_bounded(model):
    subsurface, _ = model
    flux = np.zeros(subsurface.mask.shape, np.float32)
    flux[28:36, 28:36] = 1.0
    energy = torch.from_numpy(flux)[None].expand(15, -1, -1)
    from polarface.skin.heterogeneous import render_layered_subsurface

    spectral = render_layered_subsurface(
        energy,
        tuple(subsurface.totals),
        subsurface.shapes,
        subsurface.texel_size_mm,
        stretch=subsurface.stretch,
        mask=subsurface.mask,
    )
    r_out_f, t_out_f, r_out_b, t_out_b, r_in_f = (t[:, 32, 32] for t in subsurface.totals)
    r_bar = r_out_f + t_out_f * r_in_f * t_out_b / (1 - r_out_b * r_in_f)
    totals = spectral.sum(dim=(-2, -1))
    # Homogeneous skin: the exitance integrates to R_bar times the entering flux, never more.
    np.testing.assert_allclose(totals.numpy(), (r_bar * float(flux.sum())).numpy(), rtol=2e-3)
    assert bool((totals <= float(flux.sum()) + 1e-4).all())


def test_red_scatters_further_than_blue(model):
    subsurface, _ = model
    flux = np.zeros(subsurface.mask.shape, np.float32)
    flux[32, 32] = 1.0
    from polarface.skin.heterogeneous import render_layered_subsurface

    energy = torch.from_numpy(flux)[None].expand(15, -1, -1)
    spectral = render_layered_subsurface(
        energy,
        tuple(subsurface.totals),
        subsurface.shapes,
        subsurface.texel_size_mm,
        stretch=subsurface.stretch,
        mask=subsurface.mask,
    )
    rows, cols = torch.meshgrid(torch.arange(64.0), torch.arange(64.0), indexing="ij")
    r2 = ((rows - 32) ** 2 + (cols - 32) ** 2) * subsurface.texel_size_mm**2
    width = (spectral * r2).sum((-2, -1)) / spectral.sum((-2, -1))  # mean squared radius, mm^2
    assert float(width[-1]) > 1.5 * float(width[0])  # 700 nm vs 420 nm
    assert float(width[-1]) > float(width[7])  # 700 nm vs 560 nm


def test_channel_exitance_without_blur_is_local(model):
    subsurface, calibration = model
    flux = np.full(subsurface.mask.shape, 2.0, np.float32)
    blurred = texture_space_exitance(flux, subsurface, calibration, blur=True)
    local = texture_space_exitance(flux, subsurface, calibration, blur=False)
    assert blurred.shape == local.shape == (64, 64, 6)
    # Uniform light on homogeneous skin: the blur changes nothing away from the border.
    np.testing.assert_allclose(blurred[24:40, 24:40], local[24:40, 24:40], rtol=2e-3)
    assert (local > 0).all() and (local < 2.0).all()


def test_updated_equals_a_full_build(patch):
    """Recomputing the totals of the changed texels only gives the full build's model bit for bit."""
    _, raster = patch
    calibration = default_spectral_calibration()
    rng = np.random.default_rng(3)
    chromophores = {
        name: (value * (1.0 + 0.2 * rng.standard_normal(raster.mask.shape))).astype(np.float32)
        for name, value in (("c_m", 0.05), ("beta_m", 0.05), ("c_h_in", 0.03), ("c_h_out", 0.05))
    }
    base = SubsurfaceModel.build(chromophores, raster, calibration.wavelengths_nm)
    changed = np.zeros(raster.mask.shape, bool)
    changed[10:30, 20:50] = True
    changed &= raster.mask
    pressed_c_h_out = np.where(changed, 0.3 * chromophores["c_h_out"], chromophores["c_h_out"])
    pressed = {**chromophores, "c_h_out": pressed_c_h_out.astype(np.float32)}
    full = SubsurfaceModel.build(pressed, raster, calibration.wavelengths_nm, shapes=base.shapes)
    partial = base.updated(pressed, changed)
    for a, b in zip(full.totals, partial.totals, strict=True):
        assert torch.equal(a, b)
    assert not torch.equal(full.totals.r_out_f, base.totals.r_out_f)  # the change is seen
    assert base.updated(pressed, np.zeros_like(changed)) is base
