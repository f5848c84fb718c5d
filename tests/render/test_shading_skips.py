"""Work the renderer skips changes nothing: shadow rays only above the shading horizon
(:func:`polarface.render.shading.lit_above_horizon`), ``s0`` alone for RGB cameras (:func:`lobe_stokes`),
and, in :func:`render_view`, the Stokes components the camera drops and the shadow rays towards modules
whose lobes are exactly 0."""

from __future__ import annotations

import numpy as np
import torch

from polarface.geometry.head_asset import load_head_asset
from polarface.geometry.raycast import RayCaster
from polarface.geometry.uv_raster import rasterize_uv, reposition
from polarface.optics import render_polarimetric, subsurface_exit_stokes
from polarface.render.fragments import cast_fragments
from polarface.render.renderer import analyzer_images, render_view, rig_lighting, shading_normals
from polarface.render.shading import (
    FragmentMaterial,
    FrameTextures,
    fragment_material,
    lit_above_horizon,
    lobe_stokes,
)
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
    power = torch.from_numpy(intensity[:, None].copy())
    eta = torch.full((len(points), 1), 1.4, dtype=torch.float64)
    flux = [
        visible_entry_flux(torch.from_numpy(normals), torch.from_numpy(points), up, lights, power, eta, v)
        for v in (culled, every)
    ]
    assert np.array_equal(flux[0].numpy().view(np.uint8), flux[1].numpy().view(np.uint8))
    assert float(flux[0].max()) > 0
    out = entering_flux(caster, raster, shading, np.full(mask.shape, 1.4), lights, intensity,
                        np.array([0.0, -1.0, 0.0]))
    assert np.array_equal(out[mask], flux[1][:, 0].numpy().astype(np.float32))


def test_lobe_stokes_s0_alone_is_the_full_vectors_s0():
    rng = np.random.default_rng(5)
    count = 500
    normal = torch.from_numpy(rng.normal(size=(count, 3)) + np.array([0.0, 0.0, -3.0])).float()
    normal = normal / normal.norm(dim=-1, keepdim=True)
    position = torch.from_numpy(rng.uniform(-50, 50, size=(count, 3)) + np.array([0.0, 0.0, 1000.0])).float()
    column = lambda low, high: torch.from_numpy(rng.uniform(low, high, size=(count, 1))).float()  # noqa: E731
    material = FragmentMaterial(normal, normal, column(1.3, 1.5), column(0.1, 0.5), column(0.2, 0.6),
                                column(0.0, 1.0), column(0.0, 1.0), column(0.0, 1.0).expand(count, 6))
    centre, up = torch.zeros(3), torch.tensor([0.0, -1.0, 0.0])
    lights = rng.uniform(-300, 300, size=(4, 3)) * np.array([1.0, 1.0, 0.0])
    visible = rng.random((count, 4)) < 0.7
    start = torch.from_numpy(rng.random((count, 6, 4))).float()
    full = lobe_stokes(material, position, centre, up, lights, visible, torch.ones(1, 1), start)
    s0 = lobe_stokes(material, position, centre, up, lights, visible, torch.ones(1, 1), start[..., :1])
    assert s0.shape == (count, 6, 1)
    assert torch.equal(s0[..., 0], full[..., 0])


def _reference_view(caster, mesh, camera, textures, lights, intensity, channels, polarization):
    """The renderer's images the straightforward way: every shadow ray cast, the lobes of each module
    through ``render_polarimetric`` (all four Stokes components), summed times the visibility."""
    origins, directions = (a.reshape(-1, 3) for a in camera.pixel_rays())
    fragments = cast_fragments(caster, mesh, origins, directions)
    position = torch.from_numpy(fragments.position.astype(np.float32))
    centre = torch.from_numpy(camera.center.astype(np.float32))
    up = torch.from_numpy(camera.up_vector.astype(np.float32))
    material = fragment_material(textures, torch.from_numpy(fragments.uv.astype(np.float32)),
                                 torch.from_numpy(fragments.geometric_normal.astype(np.float32)), position,
                                 centre, channels)
    visible = caster.shadow_rays(fragments.position, fragments.geometric_normal, lights, pairwise=True)
    stokes = material.exitance[..., None] * subsurface_exit_stokes(material.normal, position, centre, up,
                                                                  material.eta)
    for k in range(len(lights)):
        images = render_polarimetric(
            material.normal, position, centre, up, torch.from_numpy(lights[k : k + 1].astype(np.float32)),
            torch.from_numpy(intensity[k : k + 1, None].astype(np.float32)), material.eta, material.alpha_s,
            material.alpha_ss, material.rho_s, material.rho_ss, 0.0,
            diffused_exitance=torch.zeros(fragments.count, 1),
        )
        stokes = stokes + torch.from_numpy(visible[:, k].astype(np.float32))[:, None, None] * images.stokes
    return fragments, analyzer_images(stokes, polarization), visible


def test_render_view_gives_the_full_paths_images(small_rig):
    """The head, turned to face the rig at 1 m: ``render_view`` (s0 alone for RGB, s0..s2 for the
    polarization camera, shadow rays only towards modules lighting a fragment from the front, the lobes
    in one compiled loop) gives the images of the full per-module path to float32 rounding, and some
    shadow rays are skipped.

    Rounding, per pixel: within 8 ulps of the pixel's intensity s0. Not a share of identical bits: the
    two paths evaluate the same expressions, but torch's vectorised kernels are chosen for the CPU and
    some are not correctly rounded (tests/render/test_lobe_kernel.py), so the share of equal pixels is
    the CPU's (82 % on an AMD EPYC without AVX-512, above 95 % on Intel with it). An analyzer image
    I_theta = (s0 + cos s1 + sin s2) / 2 sums terms of the size of s0, and I90 nearly cancels (its own
    relative error reaches 10 ulps where it is 0.3 % of the image's maximum), so its rounding is
    measured against s0, not against itself or the image's maximum (which would be loose on dim pixels).
    """
    asset = load_head_asset(texture_resolution=128)
    turn = np.diag([-1.0, 1.0, -1.0, 1.0])
    turn[2, 3] = 1000.0
    mesh = asset.mesh.transformed(turn)
    raster = reposition(rasterize_uv(asset.mesh, 128), mesh)
    rng = np.random.default_rng(0)
    maps = {name: rng.uniform(low, high, raster.mask.shape) for name, low, high in (
        ("eta", 1.35, 1.45), ("alpha_s", 0.2, 0.5), ("alpha_ss", 0.4, 0.9), ("rho_s", 0.5, 1.0),
        ("rho_ss", 0.1, 0.4))}
    textures = FrameTextures.build(maps, shading_normals(raster, np.zeros(raster.mask.shape)),
                                   rng.uniform(0.0, 1.0, (*raster.mask.shape, 6)), raster.mask)
    caster = RayCaster(mesh)
    lights, intensity = rig_lighting(small_rig)
    for camera, polarization, channels in ((small_rig.cameras[0], True, (0, 2, 4)),
                                           (small_rig.cameras[-1], False, tuple(range(6)))):
        pinhole = camera.pinhole()
        view = render_view(caster, mesh, pinhole, textures, lights, intensity, channels,
                           polarization=polarization, chunk_pixels=4000)
        fragments, expected, visible = _reference_view(caster, mesh, pinhole, textures, lights, intensity,
                                                       channels, polarization)
        assert fragments.count > 500 and not visible.all()
        pixel = np.unravel_index(fragments.pixel, view.mask.shape)
        assert set(view.images) == set(expected)
        # the pixel's intensity s0 (I0 + I90 for the polarization camera) is the scale of its rounding
        pixel_s0 = (expected["i0"] + expected["i90"]).numpy() if polarization else expected["s0"].numpy()
        for name, image in expected.items():
            got, image = view.images[name][pixel], image.numpy()
            error = np.abs(got.astype(np.float64) - image) / (np.finfo(np.float32).eps * pixel_s0)
            assert error.max() <= 8.0, (name, float(error.max()))  # measured: at most 2.6 ulps
