"""The simulator's camera rendering against the optics core on a flat skin patch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from polarface.geometry.camera import PinholeCamera
from polarface.geometry.raycast import RayCaster
from polarface.optics import fresnel_transmittance, render_polarimetric
from polarface.render.renderer import render_view
from polarface.render.shading import FrameTextures, fill_empty_texels
from polarface.render.subsurface import SubsurfaceModel, entering_flux, texture_space_exitance
from polarface.skin.spectral import default_spectral_calibration

PARAMS = {"eta": 1.44, "alpha_s": 0.4, "alpha_ss": 0.95, "rho_s": 0.5, "rho_ss": 0.2}


def _scene(patch, rig, rho_s=PARAMS["rho_s"], rho_ss=PARAMS["rho_ss"], subsurface=True):
    mesh, raster = patch
    shape = raster.mask.shape
    caster = RayCaster(mesh)
    calibration = default_spectral_calibration()
    chromophores = {
        k: np.full(shape, v, np.float32)
        for k, v in (("c_m", 0.05), ("beta_m", 0.05), ("c_h_in", 0.03), ("c_h_out", 0.05))
    }
    model = SubsurfaceModel.build(chromophores, raster, calibration.wavelengths_nm)
    params = {k: np.full(shape, v, np.float32) for k, v in PARAMS.items()}
    params["rho_s"][:] = rho_s
    params["rho_ss"][:] = rho_ss
    lights = np.array([light.position_mm for light in rig.lights])
    intensity = float(rig.lights[0].radiant_intensity)
    camera = PinholeCamera.from_dict(rig.cameras[0].model_dump())
    flux = entering_flux(caster, raster, raster.normal, params["eta"], lights, intensity, camera.up_vector)
    exitance = texture_space_exitance(flux, model, calibration, blur=False)
    if not subsurface:
        exitance[:] = 0.0
    textures = FrameTextures.build(params, raster.normal, exitance, raster.mask)
    channels = tuple(rig.cameras[0].colour_channels[c] for c in "RGB")
    view = render_view(caster, mesh, camera, textures, lights, intensity, channels)
    rho = np.asarray(calibration.integrate(model.totals_local_r_bar()[:, 32, 32]))
    return view, camera, lights, intensity, channels, rho


def test_fill_empty_texels():
    texture = np.zeros((4, 4))
    mask = np.zeros((4, 4), bool)
    mask[1, 1] = True
    texture[1, 1] = 3.0
    assert (fill_empty_texels(texture, mask) == 3.0).all()


def test_flat_patch_matches_direct_local_model(patch, small_rig):
    view, camera, lights, intensity, channels, rho = _scene(patch, small_rig)
    assert view.mask.sum() > 100
    origins, directions = camera.pixel_rays()
    hit = view.mask
    position = origins[hit] + view.depth[hit][:, None] * directions[hit]
    normal = np.tile([0.0, 0.0, -1.0], (hit.sum(), 1))
    direct = render_polarimetric(
        torch.from_numpy(normal),
        torch.from_numpy(position),
        torch.from_numpy(camera.center),
        torch.from_numpy(camera.up_vector),
        torch.from_numpy(lights),
        torch.full((len(lights), 3), intensity, dtype=torch.float64),
        PARAMS["eta"],
        PARAMS["alpha_s"],
        PARAMS["alpha_ss"],
        PARAMS["rho_s"],
        PARAMS["rho_ss"],
        torch.from_numpy(rho[list(channels)]).expand(hit.sum(), 3),
    )
    for name in ("i0", "i45", "i90", "i135"):
        expected = getattr(direct, name).numpy()
        np.testing.assert_allclose(view.images[name][hit], expected, rtol=2e-3, atol=1e-6 * expected.max())


def test_flat_patch_near_coaxial_closed_form(patch, small_rig):
    view, camera, lights, intensity, channels, rho = _scene(patch, small_rig, rho_s=0.0, rho_ss=0.0)
    row, col = camera.height // 2, camera.width // 2
    assert view.mask[row, col]
    # Paper Eq. I_sss: S (rho / pi) T+_i T+_o with the coaxial geometry of the image centre.
    origins, directions = camera.pixel_rays()
    point = origins[row, col] + view.depth[row, col] * directions[row, col]
    normal = np.array([0.0, 0.0, -1.0])
    to_lights = lights - point
    distance = np.linalg.norm(to_lights, axis=1)
    cos_i = (to_lights @ normal) / distance
    shading = intensity * cos_i / distance**2
    t_perp, t_par = fresnel_transmittance(cos_i, PARAMS["eta"])
    cos_o = float(-directions[row, col] @ normal)
    to_perp, to_par = fresnel_transmittance(cos_o, PARAMS["eta"])
    expected = (
        (shading * 0.5 * (t_perp + t_par)).sum() * rho[list(channels)] / np.pi * 0.5 * (to_perp + to_par)
    )
    i_sss = 2.0 * view.images["i90"][row, col]
    np.testing.assert_allclose(i_sss, expected, rtol=6e-3)  # the paper's shortcut at 5.72 deg


def test_cross_polarized_image_has_no_specular(patch, small_rig):
    view, *_ = _scene(patch, small_rig, subsurface=False)
    hit = view.mask
    i0, i90 = view.images["i0"][hit], view.images["i90"][hit]
    assert i0.max() > 0
    assert float(i90.max()) < 0.01 * float(i0.max())  # up to the near-coaxial leak


def test_diffuse_only_identity_i_sss_equals_two_i90(patch, small_rig):
    view, *_ = _scene(patch, small_rig, rho_s=0.0, rho_ss=0.0)
    hit = view.mask
    s0 = view.images["i0"][hit] + view.images["i90"][hit]
    i_sss = 2.0 * view.images["i90"][hit]
    np.testing.assert_allclose(i_sss, s0, rtol=6e-3)


def test_render_view_requires_matching_channels(patch, small_rig):
    mesh, _ = patch
    textures = FrameTextures(torch.zeros(64, 64, 14))
    camera = PinholeCamera.from_dict(small_rig.cameras[0].model_dump())
    with pytest.raises((IndexError, ValueError)):
        render_view(RayCaster(mesh), mesh, camera, textures, np.zeros((1, 3)), 1.0, (7,))
