"""Dense stereo of one pair against rendered scenes of known depth (a plane, a sphere)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.ndimage import map_coordinates

from polarface.geometry.camera import PinholeCamera, look_at
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.raycast import RayCaster
from polarface.geometry.stereo import StereoConfig, match_stereo_pair, rectify_pair

WIDTH, HEIGHT, FOCAL = 612, 512, 2448.0
TARGET = np.array([0.0, 0.0, 1000.0])


def _camera(x_mm: float, y_mm: float = 0.0) -> PinholeCamera:
    K = np.array([[FOCAL, 0, (WIDTH - 1) / 2], [0, FOCAL, (HEIGHT - 1) / 2], [0, 0, 1.0]])
    pose = look_at(np.array([x_mm, y_mm, 0.0]), TARGET, up=(0.0, -1.0, 0.0))
    return PinholeCamera(K, pose, WIDTH, HEIGHT)


def _texture(size: int = 512, seed: int = 0) -> np.ndarray:
    """A blurred random texture in [0.2, 1] (skin-like contrast at a few texels)."""
    import cv2

    noise = np.random.default_rng(seed).random((size, size)).astype(np.float32)
    blurred = cv2.GaussianBlur(noise, (0, 0), 1.5)
    blurred = (blurred - blurred.min()) / (blurred.max() - blurred.min())
    return 0.2 + 0.8 * blurred


def _render(mesh: TriangleMesh, camera: PinholeCamera, texture: np.ndarray) -> np.ndarray:
    """Linear image of a Lambertian textured ``mesh`` under a headlight, 12-bit scale, 0 = background."""
    origins, directions = (a.reshape(-1, 3) for a in camera.pixel_rays())
    hits = RayCaster(mesh).first_hits(origins, directions)
    image = np.zeros(len(directions))
    faces = mesh.faces[hits.face_id[hits.hit]]
    uv = (mesh.uv[faces] * hits.barycentric[hits.hit][:, :, None]).sum(1)
    size = texture.shape[0]
    u = np.clip(uv[:, 0] * (size - 1), 0, size - 1)
    v = np.clip((1 - uv[:, 1]) * (size - 1), 0, size - 1)
    values = map_coordinates(texture, [v, u], order=1)
    shade = np.clip(-(hits.shading_normal(mesh)[hits.hit] * directions[hits.hit]).sum(-1), 0, 1)
    image[hits.hit] = 3000.0 * values * shade
    return image.reshape(camera.height, camera.width)


def _plane(z_mm: float = 1000.0, half: float = 200.0) -> TriangleMesh:
    grid = np.linspace(-half, half, 41)
    x, y = np.meshgrid(grid, grid)
    vertices = np.stack([x.ravel(), y.ravel(), np.full(x.size, z_mm)], axis=1)
    uv = np.stack([(x.ravel() + half) / (2 * half), (y.ravel() + half) / (2 * half)], axis=1)
    faces = []
    for i in range(40):
        for j in range(40):
            a = i * 41 + j
            faces += [[a, a + 41, a + 1], [a + 1, a + 41, a + 42]]
    return TriangleMesh.from_arrays(vertices, np.array(faces), uv)


def _sphere(radius: float = 80.0) -> TriangleMesh:
    sphere = trimesh.creation.uv_sphere(radius=radius, count=[96, 96])
    vertices = np.asarray(sphere.vertices) + TARGET
    direction = np.asarray(sphere.vertices) / radius
    uv = np.stack([(np.arctan2(direction[:, 0], direction[:, 2]) / np.pi + 1) / 2,
                   np.arccos(np.clip(direction[:, 1], -1, 1)) / np.pi], axis=1)
    return TriangleMesh.from_arrays(vertices, np.asarray(sphere.faces), np.clip(uv, 0, 1))


@pytest.fixture(scope="module")
def pair() -> tuple[PinholeCamera, PinholeCamera]:
    return _camera(-50.0, 30.0), _camera(50.0, 30.0)


def test_plane_depth(pair):
    texture = _texture()
    mesh = _plane()
    images = [_render(mesh, camera, texture) for camera in pair]
    result = match_stereo_pair(*images, *pair, saturation=4095.0)
    error = np.abs(result.cloud.points[:, 2] - 1000.0)
    assert len(result.cloud) > 0.5 * WIDTH * HEIGHT
    # 1 px of disparity is 4.1 mm of depth here (Z^2 / (f B)). SGBM's sub-pixel parabola locks towards
    # whole pixels (measured: bias -0.52 mm = 0.13 px, median |error| 0.76 mm, p95 1.35 mm); a wrong
    # rectification or depth conversion errs by whole pixels (>= 4 mm).
    assert np.median(error) < 1.0 and np.percentile(error, 95) < 2.0
    angle = np.degrees(np.arccos(np.clip(-result.cloud.normals[:, 2], -1, 1)))
    assert np.median(angle) < 10.0
    assert 0 < result.cloud.confidence.mean() <= 1


def test_sphere_radius_and_normals(pair):
    texture = _texture(seed=1)
    mesh = _sphere()
    images = [_render(mesh, camera, texture) for camera in pair]
    result = match_stereo_pair(*images, *pair, saturation=4095.0)
    offset = result.cloud.points - TARGET
    radius = np.linalg.norm(offset, axis=1)
    assert len(result.cloud) > 20000
    assert abs(np.median(radius) - 80.0) < 0.3
    assert np.percentile(np.abs(radius - 80.0), 95) < 2.0
    outward = (result.cloud.normals * offset / radius[:, None]).sum(1)
    assert np.median(np.degrees(np.arccos(np.clip(outward, -1, 1)))) < 15.0


def test_swapped_pair_gives_the_same_cloud(pair):
    texture = _texture(seed=2)
    mesh = _plane(z_mm=950.0)
    images = [_render(mesh, camera, texture) for camera in pair]
    forward = match_stereo_pair(images[0], images[1], pair[0], pair[1])
    backward = match_stereo_pair(images[1], images[0], pair[1], pair[0])
    assert backward.rectification.swapped and not forward.rectification.swapped
    assert len(forward.cloud) == len(backward.cloud)
    assert np.allclose(forward.cloud.points, backward.cloud.points)


def test_saturation_and_highlight_make_no_outliers(pair):
    texture = _texture(seed=3)
    mesh = _plane()
    images = [_render(mesh, camera, texture) for camera in pair]
    rows, cols = slice(200, 260), slice(280, 340)
    images[0][rows, cols] = 4095.0  # saturated in the left view
    images[1][300:330, 150:200] *= 2.5  # a view-dependent highlight only the right camera sees
    result = match_stereo_pair(*images, *pair, saturation=4095.0)
    assert result.rejected["saturated"] > 60 * 60
    assert np.isnan(result.depth_mm).sum() > 0
    error = np.abs(result.cloud.points[:, 2] - 1000.0)
    assert error.max() < 8.0  # within two disparity pixels, no gross outlier
    assert np.percentile(error, 99) < 2.0


def test_background_gives_no_points(pair):
    image = np.zeros((HEIGHT, WIDTH))
    result = match_stereo_pair(image, image, *pair)
    assert len(result.cloud) == 0


def test_disparity_range_covers_the_depth_range(pair):
    rect = rectify_pair(*pair)
    low, count = rect.disparity_range((800.0, 1250.0))
    assert count % 16 == 0
    focal, offset = rect.projection_a[0, 0], rect.projection_b[0, 2] - rect.projection_a[0, 2]
    for depth in (800.0, 1000.0, 1250.0):
        disparity = focal * rect.baseline_mm / depth - offset
        assert low < disparity < low + count
    assert rect.baseline_mm == pytest.approx(100.0, rel=1e-6)


def test_bad_inputs(pair):
    image = np.ones((HEIGHT, WIDTH))
    with pytest.raises(ValueError, match="image_a"):
        match_stereo_pair(np.ones((HEIGHT, WIDTH + 4)), image, *pair)
    with pytest.raises(ValueError, match="image_b"):
        match_stereo_pair(image, np.full((HEIGHT, WIDTH), np.nan), *pair)
    with pytest.raises(ValueError, match="broken calibration"):
        match_stereo_pair(image, image, pair[0], pair[0])
    along_axis = _camera(0.0, 30.0)
    shifted = PinholeCamera(along_axis.K, along_axis.world_to_camera @ np.diag([1, 1, 1, 1.0]) + np.array(
        [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, -100.0], [0, 0, 0, 0]]), WIDTH, HEIGHT)
    with pytest.raises(ValueError, match="broken calibration"):
        match_stereo_pair(image, image, along_axis, shifted)
    with pytest.raises(ValueError, match="depth_range_mm"):
        StereoConfig(depth_range_mm=(1000.0, 900.0))
    with pytest.raises(ValueError, match="block_size"):
        StereoConfig(block_size=4)
