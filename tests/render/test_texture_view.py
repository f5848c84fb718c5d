"""Texture-space re-render of a view (render/texture_view.py) on a tiny synthetic sphere capture."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from polarface.capture.store import CaptureStore
from polarface.geometry.mesh import load_mesh
from polarface.geometry.poses import load_poses
from polarface.optics.image_formation import render_polarimetric
from polarface.render.texture_view import (
    render_view_texture,
    shade_texels,
    texel_fragments,
    texel_material,
    texel_shading_normals,
    texture_observations,
)
from polarface.simulate.sphere_capture import SphereCaptureConfig, make_sphere_capture
from polarface.texture import UnwrapConfig, UnwrapStore, unwrap_capture


@pytest.fixture(scope="module")
def unwrapped(tmp_path_factory):
    root = tmp_path_factory.mktemp("sphere_texture_view")
    info = make_sphere_capture(root, SphereCaptureConfig(texture_resolution=16, frames=3))
    store = CaptureStore.open(info["capture"])
    mesh = load_mesh(info["ground_truth"] / "mesh_rest.obj")
    poses = load_poses(info["ground_truth"] / "static" / "poses.json")
    config = UnwrapConfig(texture_resolution=16, patch=8, holdout_every=3)
    unwrap = unwrap_capture(store, mesh, poses, root / "u.zarr", config, progress=False)
    return info, unwrap


def _tilted_reference_copy(unwrap: UnwrapStore, path) -> UnwrapStore:
    """A copy of ``unwrap`` whose views' reference up is tilted 35 deg about the viewing axis (the sphere
    rig's cameras share one up, which would hide a mix-up of the entry and exit polariser frames)."""
    shutil.copytree(unwrap.path, path)
    copy = UnwrapStore.open(path, mode="a")
    views = []
    for view in copy.root.attrs["views"]:
        up = np.asarray(view["camera_up"])
        axis = -np.asarray(view["camera_center"]) / np.linalg.norm(view["camera_center"])
        angle = np.radians(35.0)
        tilted = up * np.cos(angle) + np.cross(axis, up) * np.sin(angle)
        tilted += axis * (axis @ up) * (1 - np.cos(angle))  # Rodrigues' rotation
        views.append({**view, "reference_up": [float(v) for v in tilted]})
    copy.root.attrs["views"] = views
    return copy


def _perturbed_maps(maps: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The true maps with texel-wise noise on every parameter (eta, alphas, albedos, displacement)."""
    rng = np.random.default_rng(7)
    out = {}
    for name, value in maps.items():
        noise = rng.uniform(0.7, 1.3, value.shape)
        out[name] = (value * noise).astype(np.float32)
    out["eta"] = (1.2 + (maps["eta"] - 1.0) * rng.uniform(0.5, 2.0, maps["eta"].shape)).astype(np.float32)
    out["displacement_mm"] = (maps["displacement_mm"] + rng.normal(0, 0.02, maps["eta"].shape)).astype(
        np.float32
    )
    return out


def _reference_normals(unwrap: UnwrapStore, displacement_mm: np.ndarray) -> np.ndarray:
    """The shading normals straight from ``geometry.heights`` (float64 -> float32)."""
    from polarface.geometry.heights import normals_from_heights

    geometry = unwrap.geometry()
    t = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float64))  # noqa: E731
    with torch.no_grad():
        normal = normals_from_heights(
            t(displacement_mm),
            t(geometry.tangent_u),
            t(geometry.tangent_v),
            t(geometry.normal),
            t(geometry.texel_size_u),
            t(geometry.texel_size_v),
            torch.from_numpy(geometry.mask),
        )
    return normal.numpy().astype(np.float32)


def _reference_render(unwrap: UnwrapStore, maps: dict, view_index: int, normal: np.ndarray, patch: int):
    """Oracle: the inverse stage's per-sample forward model (``inverse.polarimetric.render_samples``, which
    its own tests hold to ``optics.render_polarimetric``) on the fit's sample batches of one view."""
    from polarface.inverse.polarimetric import build_patch_samples, render_samples

    height, width = unwrap.resolution
    observed = np.zeros((height, width, 3, 3), np.float32)
    predicted = np.zeros_like(observed)
    valid = np.zeros((height, width), bool)
    t = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float64))  # noqa: E731
    for rows, cols in unwrap.patches(patch):
        batch, geometry = build_patch_samples(
            unwrap, rows, cols, [view_index], unwrap.views, dtype=torch.float64
        )
        if batch is None:
            continue
        texel = batch.texel.numpy()
        r, c = texel // geometry.mask.shape[1] + rows.start, texel % geometry.mask.shape[1] + cols.start
        with torch.no_grad():
            prediction = render_samples(
                batch,
                t(normal[r, c]),
                t(np.maximum(maps["eta"][r, c], 1.0 + 1e-6)),
                t(np.maximum(maps["alpha_s"][r, c], 1e-3)),
                t(np.maximum(maps["alpha_ss"][r, c], 1e-3)),
                t(maps["rho_s"][r, c]),
                t(maps["rho_ss"][r, c]),
                t(np.take_along_axis(maps["rho_sss_bar"][r, c], batch.channels.numpy(), axis=1)),
            )
        predicted[r, c] = torch.stack([prediction.i_sss, prediction.i_zeta, prediction.i_s], dim=1).numpy()
        observed[r, c] = batch.observed.numpy()
        valid[r, c] = True
    return observed, predicted, valid


@pytest.mark.parametrize("case", ["true maps", "perturbed maps", "tilted reference up"])
def test_equals_the_inverse_per_sample_model(unwrapped, tmp_path, case):

    info, unwrap = unwrapped
    maps = info["maps"] if case == "true maps" else _perturbed_maps(info["maps"])
    if case == "tilted reference up":
        unwrap = _tilted_reference_copy(unwrap, tmp_path / "tilted.zarr")
    normal = texel_shading_normals(unwrap, maps["displacement_mm"])
    np.testing.assert_array_equal(normal, _reference_normals(unwrap, maps["displacement_mm"]))
    held = [i for i, v in enumerate(unwrap.views) if v.held_out]
    fitting = [i for i, v in enumerate(unwrap.views) if not v.held_out]
    assert held and fitting
    worst = 0.0
    for index in (held[0], fitting[0], fitting[-1]):
        observed, predicted, valid = render_view_texture(unwrap, maps, index, patch=8)
        want_observed, want_predicted, want_valid = _reference_render(unwrap, maps, index, normal, patch=8)
        np.testing.assert_array_equal(valid, want_valid)
        np.testing.assert_array_equal(observed, want_observed)
        assert valid.sum() > 20 and predicted.dtype == np.float32 and predicted.shape == (16, 16, 3, 3)
        assert not predicted[~valid].any()
        scale = np.abs(want_predicted[valid]).max(axis=0, keepdims=True)  # per observation x channel
        denominator = np.maximum(np.abs(want_predicted[valid]), 1e-6 * scale)
        relative = np.abs(predicted[valid] - want_predicted[valid]) / denominator
        worst = max(worst, float(relative.max()))
    print(f"max relative difference vs the inverse per-sample model ({case}): {worst:.3g}")
    assert worst < 1e-6


def _single_texel_case(unwrapped, lobes: bool):
    """Shading of view 0 and, for one texel lit by every module, optics.render_polarimetric of it."""
    info, unwrap = unwrapped
    maps = dict(info["maps"])
    if not lobes:
        maps["rho_s"] = np.zeros_like(maps["rho_s"])
        maps["rho_ss"] = np.zeros_like(maps["rho_ss"])
    view = unwrap.views[0]
    # the entry frame (reference up) and the exit frame (view up) coincide for the reference camera, so
    # the single-up image formation of polarface.optics applies unchanged
    np.testing.assert_allclose(view.reference_up, view.camera_up, atol=1e-12)
    fragments = texel_fragments(unwrap, 0)
    normal = texel_shading_normals(unwrap, maps["displacement_mm"])
    material = texel_material(fragments, maps, normal, view.channels)
    stokes = shade_texels(fragments, material, view)
    texel = int(np.nonzero(fragments.lit.all(axis=1))[0][0])
    one = slice(texel, texel + 1)
    images = render_polarimetric(
        material.normal[one],
        torch.from_numpy(fragments.position[one]),
        torch.tensor(view.camera_center, dtype=torch.float64),
        torch.tensor(view.camera_up, dtype=torch.float64),
        torch.tensor(view.light_positions, dtype=torch.float64),
        torch.tensor(view.light_intensity, dtype=torch.float64),
        material.eta[one],
        material.alpha_s[one],
        material.alpha_ss[one],
        material.rho_s[one],
        material.rho_ss[one],
        material.exitance[one],  # rho_sss_bar of the view's channels: the local model E = rho_sss_bar Phi
    )
    return stokes, texel, images


@pytest.mark.parametrize("lobes", [True, False])
def test_a_fully_lit_texel_matches_the_optics_image_formation(unwrapped, lobes):
    stokes, texel, images = _single_texel_case(unwrapped, lobes)
    np.testing.assert_allclose(stokes[texel].numpy(), images.stokes[0].numpy(), rtol=1e-10, atol=0)
    assert bool(images.specular.abs().max() > 0) == lobes


def test_lobe_free_texel_has_only_the_subsurface_polarization(unwrapped):
    stokes, texel, images = _single_texel_case(unwrapped, lobes=False)
    np.testing.assert_allclose(stokes[texel].numpy(), images.subsurface[0].numpy(), rtol=1e-10, atol=0)
    i_sss, i_zeta, i_s = texture_observations(stokes)[texel]
    assert np.all(i_sss > 0) and np.all(np.abs(i_s) < i_sss)
    # I_s = s1 = -E T-_o cos 2phi_o / pi and I_zeta = -s2 = E T-_o sin 2phi_o / pi: their ratio -cot 2phi_o
    # depends on the exit azimuth only, not on the channel's albedo
    ratio = i_s / i_zeta
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-5)


def test_bad_input_raises_naming_the_argument(unwrapped):
    info, unwrap = unwrapped
    maps = info["maps"]
    with pytest.raises(ValueError, match="view_index"):
        render_view_texture(unwrap, maps, len(unwrap.views))
    with pytest.raises(ValueError, match="view_index"):
        render_view_texture(unwrap, maps, -1)
    with pytest.raises(ValueError, match=r"maps.*rho_ss"):
        render_view_texture(unwrap, {k: v for k, v in maps.items() if k != "rho_ss"}, 0)
    with pytest.raises(ValueError, match=r"maps.*eta"):
        render_view_texture(unwrap, {**maps, "eta": maps["eta"][:8]}, 0)
    with pytest.raises(ValueError, match="displacement_mm"):
        texel_shading_normals(unwrap, np.zeros((8, 16), np.float32))
    with pytest.raises(ValueError, match="normal"):
        render_view_texture(unwrap, maps, 0, normal=np.zeros((16, 16), np.float32))
