"""polarface.capture.observations: I_sss / I_zeta / I_s / DoP / AoLP and the two-camera merge."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from polarface.capture.demosaic import PolarizationStack
from polarface.capture.observations import (
    OBSERVATION_NAMES,
    convergence_distance_mm,
    depth_from_mesh,
    merge_six_channels,
    observations_from_intensities,
    observations_from_stack,
    plane_homography,
    register_to_reference,
)
from polarface.capture.rig import paper_rig
from polarface.optics.stokes import intensities_from_stokes


def test_observations_reference_values():
    # co-polarized specular [1, 1, 0] plus unpolarized 0.4: I0 = 0.7, I90 = 0.2, I45 = I135 = 0.45
    obs = observations_from_intensities(0.7, 0.45, 0.2, 0.45)
    assert obs["i_sss"] == pytest.approx(0.4)
    assert obs["i_zeta"] == pytest.approx(0.0)
    assert obs["i_s"] == pytest.approx(0.5)
    assert obs["dop"] == pytest.approx(0.5 / 0.9)
    assert obs["aolp"] == pytest.approx(0.0)
    assert set(obs) == set(OBSERVATION_NAMES)


def test_observations_match_optics_stokes():
    from polarface.optics.stokes import aolp, linear_dop, stokes_from_intensities

    rng = np.random.default_rng(3)
    images = rng.uniform(0.05, 1.0, (4, 7, 5, 3))
    obs = observations_from_intensities(*images)
    stokes = stokes_from_intensities(*images)
    np.testing.assert_allclose(obs["dop"], linear_dop(stokes), rtol=1e-12)
    np.testing.assert_allclose(obs["aolp"], aolp(stokes), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(obs["i_s"], stokes[..., 1])
    np.testing.assert_allclose(obs["i_zeta"], -stokes[..., 2])


def test_observations_physics_of_image_formation():
    """Supplement Eq.: with s_o = [a + b, a - c xi... ] the observations isolate their terms."""
    rng = np.random.default_rng(0)
    kappa, sss, t_minus, phi = rng.uniform(0.1, 1, (4, 50))
    xi, zeta = np.cos(2 * phi), np.sin(2 * phi)
    stokes = np.stack([kappa + sss - t_minus * xi, kappa - t_minus * xi, -t_minus * zeta], -1)
    i0, i45, i90, i135 = np.moveaxis(intensities_from_stokes(stokes), -1, 0)
    obs = observations_from_intensities(i0, i45, i90, i135)
    np.testing.assert_allclose(obs["i_sss"], sss)  # 2 I90 = S rho T++
    np.testing.assert_allclose(obs["i_zeta"], t_minus * zeta)  # I135 - I45
    np.testing.assert_allclose(obs["i_s"], kappa - t_minus * xi)  # I0 - I90


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_observations_torch_dtype_shapes(dtype):
    images = [torch.rand(5, 6, 3, dtype=dtype) + 0.1 for _ in range(4)]
    obs = observations_from_intensities(*images)
    for value in obs.values():
        assert value.shape == (5, 6, 3) and value.dtype == dtype
    assert bool(((obs["aolp"] >= 0) & (obs["aolp"] < math.pi)).all())


def test_observations_gradcheck():
    images = tuple(torch.rand(3, 4, dtype=torch.float64, requires_grad=True) + 0.2 for _ in range(4))
    for key in ("i_sss", "i_zeta", "i_s", "dop", "aolp"):
        assert torch.autograd.gradcheck(lambda *x, k=key: observations_from_intensities(*x)[k], images)


def test_observations_errors():
    with pytest.raises(ValueError, match="i45"):
        observations_from_intensities(np.ones(3), np.array([np.nan, 1, 1]), np.ones(3), np.ones(3))
    with pytest.raises(ValueError):
        observations_from_intensities(np.ones(3), np.ones(2), np.ones(3), np.ones(3))


def test_observations_from_stack_blocks_and_mask():
    rng = np.random.default_rng(2)
    intensities = rng.uniform(0.1, 1, (4, 37, 11, 3)).astype(np.float32)
    saturated = np.zeros((37, 11), bool)
    saturated[3, 4] = True
    stack = PolarizationStack(intensities, saturated, np.zeros_like(saturated))
    obs = observations_from_stack(stack, rows_per_block=8)
    whole = observations_from_intensities(*intensities)
    for name in OBSERVATION_NAMES:
        np.testing.assert_allclose(getattr(obs, name), whole[name], rtol=1e-6, atol=1e-6)
    assert not obs.valid[3, 4] and obs.valid.sum() == 37 * 11 - 1


def _rig():
    return paper_rig(width=160, height=128)


def _scene(u, v):
    return np.stack([np.sin(u / 9.0) + 2, np.cos(v / 7.0) + 2, np.sin((u + v) / 11.0) + 2], -1).astype(
        np.float32
    )


def _render_plane(rig, camera_id, distance):
    """Image of a textured fronto-parallel (world z = distance) plane seen by a camera."""
    camera = rig.camera(camera_id)
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(camera.intrinsics).T
    rotation, centre = camera.pose[:3, :3], camera.centre_mm
    world_dirs = rays @ rotation
    t = (distance - centre[2]) / world_dirs[..., 2]
    points = centre + world_dirs * t[..., None]
    return _scene(points[..., 0] * 0.5, points[..., 1] * 0.5)


def test_homography_and_depth_registration_agree_on_a_plane():
    rig = _rig()
    ref, src = rig.camera("pol_upper"), rig.camera("pol_lower")
    distance = convergence_distance_mm(ref, src)
    assert distance == pytest.approx(math.hypot(1000.0, 30.0), rel=1e-6)
    homography = plane_homography(ref, src, distance)
    assert homography.shape == (3, 3)
    image = _render_plane(rig, "pol_lower", 1000.0)
    by_plane, ok_plane = register_to_reference(image, src, ref)
    depth = np.full((ref.height, ref.width), distance, dtype=np.float32)
    by_depth, ok_depth = register_to_reference(image, src, ref, depth_mm=depth)
    both = ok_plane & ok_depth
    assert both.mean() > 0.8
    np.testing.assert_allclose(by_plane[both], by_depth[both], atol=1e-3)


def test_merge_six_channels_recovers_reference_view():
    rig = _rig()
    ref = rig.camera("pol_upper")
    # the plane through the face centre, seen by both cameras: world z = 1000 is not fronto-parallel to
    # the verged reference camera, so use per-pixel depth of that plane
    v, u = np.mgrid[0 : ref.height, 0 : ref.width].astype(np.float64)
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(ref.intrinsics).T
    world_dirs = rays @ ref.pose[:3, :3]
    t = (1000.0 - ref.centre_mm[2]) / world_dirs[..., 2]
    depth = t  # z_cam of rays with unit z in the camera = ray parameter
    images = {cam: _render_plane(rig, cam, 1000.0) for cam in ("pol_upper", "pol_lower")}
    six, valid = merge_six_channels(images, rig, "pol_upper", depth_mm=depth)
    assert six.shape == (128, 160, 6) and valid.mean() > 0.8
    truth = images["pol_upper"]
    for colour, channel in rig.camera("pol_upper").colour_channels.items():
        np.testing.assert_allclose(six[..., channel], truth[..., "RGB".index(colour)])
    for colour, channel in rig.camera("pol_lower").colour_channels.items():
        error = np.abs(six[..., channel] - truth[..., "RGB".index(colour)])[valid]
        assert np.percentile(error, 99) < 0.003  # a 1 px misregistration would give ~0.05
    # masks travel with the images
    masks = {"pol_lower": np.zeros((128, 160), bool)}
    _, none_valid = merge_six_channels(images, rig, "pol_upper", depth_mm=depth, masks=masks)
    assert not none_valid.any()


def test_merge_errors():
    rig = _rig()
    image = np.zeros((128, 160, 3), np.float32)
    with pytest.raises(ValueError, match="reference"):
        merge_six_channels({"pol_lower": image}, rig, "pol_upper")
    with pytest.raises(ValueError, match=r"channels \[3, 4, 5\]"):
        merge_six_channels({"pol_upper": image}, rig, "pol_upper")
    with pytest.raises(ValueError, match="colour_channels"):
        merge_six_channels({"pol_upper": image, "stereo0_a": image}, rig, "pol_upper")
    with pytest.raises(ValueError, match="depth_mm"):
        register_to_reference(
            image, rig.camera("pol_lower"), rig.camera("pol_upper"), depth_mm=np.ones((4, 4))
        )
    with pytest.raises(ValueError, match="parallel"):
        convergence_distance_mm(rig.camera("pol_upper"), rig.camera("pol_upper"))


def test_depth_from_mesh_plane():
    import trimesh

    rig = paper_rig(width=32, height=32)
    camera = rig.camera("pol_upper")
    plane = trimesh.Trimesh(
        vertices=[[-500, -500, 1000], [500, -500, 1000], [500, 500, 1000], [-500, 500, 1000]],
        faces=[[0, 1, 2], [0, 2, 3]],
    )
    depth = depth_from_mesh(plane, camera)
    centre_ray_depth = depth[15:17, 15:17].mean()
    assert centre_ray_depth == pytest.approx(math.hypot(1000.0, 30.0), rel=1e-3)
    assert np.isfinite(depth).all()
