"""polarface.geometry.camera: OpenCV-convention pinhole camera, look_at, distortion, rays."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from polarface.capture.rig import paper_rig
from polarface.geometry import PinholeCamera, look_at, undistort_normalized

DIST = np.array([-0.21, 0.08, 0.0012, -0.0008, -0.015])


def make_camera(distortion=None):
    K = np.array([[1800.0, 0.0, 300.5], [0.0, 1795.0, 250.25], [0.0, 0.0, 1.0]])
    cam = PinholeCamera.look_at([300.0, 100.0, 900.0], [0.0, 0.0, 0.0], width=612, height=512, focal=1800.0)
    pose = cam.world_to_camera
    return PinholeCamera(K, pose, 612, 512, np.zeros(5) if distortion is None else distortion)


def test_look_at_hand_computed():
    cam = PinholeCamera.look_at([0, 0, 10.0], [0, 0, 0], [0, 1, 0], width=640, height=480, fov_y=math.pi / 2)
    expected = np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 10.0], [0, 0, 0, 1]])
    np.testing.assert_allclose(cam.world_to_camera, expected, atol=1e-12)
    np.testing.assert_allclose(cam.K, [[240, 0, 319.5], [0, 240, 239.5], [0, 0, 1]])
    np.testing.assert_allclose(cam.center, [0, 0, 10])
    np.testing.assert_allclose(cam.viewing_axis, [0, 0, -1])
    np.testing.assert_allclose(cam.up_vector, [0, 1, 0])
    pixels, depth = cam.project(np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]]))
    np.testing.assert_allclose(pixels, [[319.5, 239.5], [319.5 + 24.0, 239.5 - 24.0]])  # +y world = up
    np.testing.assert_allclose(depth, [10, 10])


def test_look_at_errors():
    with pytest.raises(ValueError, match="differ"):
        PinholeCamera.look_at([0, 0, 0], [0, 0, 0], width=10, height=10, focal=10)
    with pytest.raises(ValueError, match="parallel"):
        PinholeCamera.look_at([0, 5, 0], [0, 0, 0], [0, 1, 0], width=10, height=10, focal=10)
    with pytest.raises(ValueError, match="exactly one"):
        PinholeCamera.look_at([0, 0, 5], [0, 0, 0], width=10, height=10)
    with pytest.raises(ValueError, match="'K'"):
        PinholeCamera(np.eye(3) * -1, np.eye(4), 10, 10)
    with pytest.raises(ValueError, match="world_to_camera"):
        PinholeCamera(np.eye(3), np.diag([1.0, 1.0, -1.0, 1.0]), 10, 10)
    with pytest.raises(ValueError, match="distortion"):
        PinholeCamera(np.eye(3), np.eye(4), 10, 10, np.zeros(4))
    cam = make_camera()
    with pytest.raises(ValueError, match="points"):
        cam.project(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="NaN"):
        cam.project(np.full((1, 3), np.nan))


@pytest.mark.parametrize("distortion", [None, DIST])
def test_project_matches_opencv(distortion):
    cam = make_camera(distortion)
    rng = np.random.default_rng(1)
    points = rng.uniform(-80, 80, size=(200, 3))
    pixels, _ = cam.project(points)
    rvec, _ = cv2.Rodrigues(cam.world_to_camera[:3, :3])
    cv_pixels, _ = cv2.projectPoints(points, rvec, cam.world_to_camera[:3, 3], cam.K, cam.distortion)
    np.testing.assert_allclose(pixels, cv_pixels[:, 0], atol=1e-6)


@pytest.mark.parametrize("distortion", [None, DIST])
def test_unproject_and_rays_round_trip(distortion):
    cam = make_camera(distortion)
    rng = np.random.default_rng(2)
    points = rng.uniform(-60, 60, size=(300, 3))
    pixels, depth = cam.project(points)
    np.testing.assert_allclose(cam.unproject(pixels, depth), points, atol=1e-7)
    origins, directions = cam.pixel_rays(pixels)
    t = np.einsum("rc,rc->r", points - origins, directions)
    np.testing.assert_allclose(origins + t[:, None] * directions, points, atol=1e-7)
    grid_o, grid_d = cam.pixel_rays()
    assert grid_o.shape == (512, 612, 3) and grid_d.shape == (512, 612, 3)
    np.testing.assert_allclose(np.linalg.norm(grid_d, axis=-1), 1.0, atol=1e-12)


def test_distort_undistort_matches_opencv():
    cam = make_camera(DIST)
    rng = np.random.default_rng(3)
    pixels = rng.uniform([0, 0], [611, 511], size=(400, 2))
    ideal = cam.undistort_points(pixels)
    cv_ideal = cv2.undistortPoints(
        pixels[:, None],
        cam.K,
        cam.distortion,
        None,
        cam.K,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14),
    )[:, 0]
    np.testing.assert_allclose(ideal, cv_ideal, atol=1e-6)
    np.testing.assert_allclose(cam.distort_points(ideal), pixels, atol=1e-8)
    # zero distortion is the identity
    np.testing.assert_allclose(undistort_normalized(np.array([[0.1, -0.2]]), np.zeros(5)), [[0.1, -0.2]])


def test_dict_round_trip_and_behind_camera():
    cam = make_camera(DIST)
    again = PinholeCamera.from_dict(cam.to_dict())
    np.testing.assert_array_equal(again.K, cam.K)
    np.testing.assert_array_equal(again.distortion, cam.distortion)
    pixels, depth = cam.project(cam.center + 2 * (cam.center - np.zeros(3)))  # behind the camera
    assert depth < 0 and np.isnan(pixels).all()
    with pytest.raises(ValueError, match="lacks"):
        PinholeCamera.from_dict({"K": np.eye(3).tolist()})


def test_look_at_default_up_is_world_minus_y():
    pose = look_at([0.0, 0.0, 0.0], [0.0, 0.0, 10.0])
    np.testing.assert_allclose(pose, np.eye(4), atol=1e-12)
    cam = PinholeCamera.look_at([0.0, 0.0, 0.0], [0.0, 0.0, 10.0], width=8, height=6, focal=10.0)
    np.testing.assert_allclose(cam.world_to_camera, pose)
    np.testing.assert_allclose(cam.up_vector, [0.0, -1.0, 0.0])


def test_torch_interop_matches_numpy_frame():
    cam = PinholeCamera.look_at([300.0, 100.0, 900.0], [0.0, 0.0, 0.0], [0, 1, 0],
        width=16, height=12, focal=20
    )
    _, directions = cam.pixel_rays()
    rays = cam.ray_directions_tensor(torch.float64)
    assert rays.shape == (12, 16, 3)
    np.testing.assert_allclose(rays.numpy(), directions, atol=1e-12)
    np.testing.assert_allclose(cam.center_tensor(torch.float64).numpy(), cam.center, atol=1e-9)
    np.testing.assert_allclose(cam.up_tensor(torch.float64).numpy(), cam.up_vector, atol=1e-12)
    np.testing.assert_allclose(cam.forward_tensor(torch.float64).numpy(), cam.viewing_axis, atol=1e-12)
    assert cam.rotation_tensor().dtype == torch.float32


def test_centred_camera_and_rig_pinhole():
    cam = PinholeCamera.centred(4, 2, 100.0)
    np.testing.assert_allclose(cam.K[:2, 2], [1.5, 0.5])
    with pytest.raises(ValueError, match="focal"):
        PinholeCamera.centred(4, 4, -1.0)
    rig_camera = paper_rig(width=64, height=48).polarimetric_cameras()[0]
    pinhole = rig_camera.pinhole()
    np.testing.assert_allclose(pinhole.world_to_camera, rig_camera.pose)
    np.testing.assert_allclose(pinhole.center, rig_camera.centre_mm)
