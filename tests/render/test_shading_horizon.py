"""Shadow rays only above the shading horizon (:func:`polarface.render.shading.lit_above_horizon`)."""

from __future__ import annotations

import numpy as np
import torch

from polarface.geometry.head_asset import load_head_asset
from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import rasterize_uv
from polarface.render.renderer import rig_lighting, shading_normals
from polarface.render.shading import lit_above_horizon
from polarface.render.subsurface import entering_flux, visible_entry_flux


def test_horizon_culling_changes_no_entry_flux(small_rig):
    """Every texel of the head, all modules: the culled visibility equals the shadow rays above the
    horizon, and the entry flux (the simulator's :func:`entering_flux`) is the same bits as with every
    ray cast."""
    asset = load_head_asset(texture_resolution=128)
    raster = rasterize_uv(asset.mesh, 128)
    caster = RayCaster(asset.mesh)
    shading = shading_normals(raster, np.zeros(raster.mask.shape))
    lights, intensity = rig_lighting(small_rig)
    # the head at the rig origin faces +z: put the lights around it at 1 m on both sides
    lights = np.concatenate([lights[:, :2], np.full((len(lights), 1), -1000.0)], axis=1)
    lights[::2, 2] *= -1.0
    mask = raster.mask
    points, normals, geometric = (
        np.asarray(a[mask], np.float64) for a in (raster.position, shading, raster.normal)
    )
    culled = lit_above_horizon(caster, points, geometric, normals, lights)
    every = caster.shadow_rays(points, geometric, lights)
    cosine = np.einsum("nc,nkc->nk", normals, lights[None] - points[:, None])
    above = cosine > 0
    assert 0.1 < above.mean() < 0.9  # some modules are below the horizon
    assert np.array_equal(culled[above], every[above])
    up = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    power = torch.full((len(lights), 1), float(intensity), dtype=torch.float64)
    eta = torch.full((len(points), 1), 1.4, dtype=torch.float64)
    flux = [
        visible_entry_flux(torch.from_numpy(normals), torch.from_numpy(points), up, lights, power, eta, v)
        for v in (culled, every)
    ]
    assert np.array_equal(flux[0].numpy().view(np.uint8), flux[1].numpy().view(np.uint8))
    assert float(flux[0].max()) > 0
    out = entering_flux(caster, raster, shading, np.full(mask.shape, 1.4), lights, float(intensity),
                        np.array([0.0, -1.0, 0.0]))
    assert np.array_equal(out[mask], flux[1][:, 0].numpy().astype(np.float32))
