"""The mirror sphere's geometry (``polarface.capture.light_calibration``): the law of reflection at the
specular points, silhouette cones against the true sphere, the reflected rays through their light, and the
bundle adjustment recovering modules and centres exactly from exact highlights; bad input named."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.capture.light_calibration import (
    HighlightObservation,
    SilhouetteObservation,
    adjust_lights,
    highlight_spots,
    nearest_point,
    reflected_rays,
    silhouette_cone,
    silhouette_edge,
    specular_points,
    sphere_centre,
)
from polarface.capture.rig import paper_rig
from polarface.simulate.calibration_session import MirrorSphereTarget, render_mirror_sphere

RIG = paper_rig(width=320, height=256)
CAMERAS = [camera.pinhole() for camera in RIG.cameras]
RADIUS = 50.0
CENTRE = np.array([20.0, -10.0, 980.0])


def test_specular_points_obey_the_law_of_reflection():
    rng = np.random.default_rng(0)
    lights = rng.uniform(-150, 150, (20, 3)) * (1, 1, 0.2)
    eyes = np.concatenate([rng.uniform(-300, 300, (20, 2)), rng.uniform(-50, 50, (20, 1))], axis=1)
    centres = CENTRE + rng.uniform(-30, 30, (20, 3))
    points = specular_points(centres, RADIUS, eyes, lights)
    normals = (points - centres) / RADIUS
    np.testing.assert_allclose(np.linalg.norm(points - centres, axis=1), RADIUS)
    to_eye = (eyes - points) / np.linalg.norm(eyes - points, axis=1, keepdims=True)
    to_light = (lights - points) / np.linalg.norm(lights - points, axis=1, keepdims=True)
    # equal angles, and the three directions in one plane
    np.testing.assert_allclose(np.sum(normals * to_eye, 1), np.sum(normals * to_light, 1), atol=1e-12)
    np.testing.assert_allclose(np.einsum("ij,ij->i", normals, np.cross(to_eye, to_light)), 0.0, atol=1e-12)


def test_a_highlights_reflected_ray_passes_through_its_light():
    light = np.array([70.0, 70.0, 0.0])
    for camera in CAMERAS:
        point = specular_points(CENTRE[None], RADIUS, camera.center[None], light[None])
        pixel = camera.project(point)[0]
        hit_point, direction, hit = reflected_rays(camera, pixel, CENTRE, RADIUS)
        assert hit.all()
        np.testing.assert_allclose(hit_point, point, atol=1e-6)
        offset = light - hit_point[0]
        np.testing.assert_allclose(np.linalg.norm(np.cross(direction[0], offset)), 0.0, atol=1e-6)


def test_nearest_point_of_lines_through_a_point():
    rng = np.random.default_rng(1)
    target = np.array([1.0, -2.0, 3.0])
    directions = rng.normal(size=(6, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    origins = target + rng.uniform(-5, 5, (6, 1)) * directions
    np.testing.assert_allclose(nearest_point(origins, directions), target, atol=1e-12)


def test_silhouette_cones_give_the_sphere():
    target = MirrorSphereTarget(radius_mm=RADIUS)
    cones = []
    for camera in CAMERAS[:4]:
        edge = silhouette_edge(render_mirror_sphere(camera, CENTRE, target))
        axis, angle, rms = silhouette_cone(camera, edge)
        offset = CENTRE - camera.center
        truth = offset / np.linalg.norm(offset)
        focal = camera.K[0, 0]  # the errors in pixels: angles times the focal length
        assert np.arccos(min(axis @ truth, 1.0)) * focal < 0.05
        assert abs(angle - np.arcsin(RADIUS / np.linalg.norm(offset))) * focal < 0.05
        assert rms < 0.1  # the 4 x 4 antialiasing's coverage steps
        cones.append(SilhouetteObservation(0, camera, axis, angle, rms))
    assert np.linalg.norm(sphere_centre(cones, RADIUS) - CENTRE) < 0.3


def test_the_adjustment_recovers_modules_and_centres_from_exact_highlights():
    lights = np.array([[100.0, 3.0, -2.0], [-60.0, 75.0, 4.0], [5.0, -98.0, 1.0]])
    centres = np.array([[0.0, 0.0, 900.0], [40.0, 20.0, 1100.0], [-40.0, -20.0, 1000.0]])
    highlights, silhouettes = [], []
    for p, centre in enumerate(centres):
        for camera in CAMERAS:
            eyes = np.repeat(camera.center[None], 3, 0)
            points = specular_points(np.repeat(centre[None], 3, 0), RADIUS, eyes, lights)
            for k, pixel in enumerate(camera.project(points)[0]):
                highlights.append(HighlightObservation(p, k, camera, pixel))
            offset = centre - camera.center
            silhouettes.append(SilhouetteObservation(p, camera, offset / np.linalg.norm(offset),
                                                     float(np.arcsin(RADIUS / np.linalg.norm(offset))), 0.0))
    start = lights + np.array([[5.0, -4.0, 8.0], [-6.0, 3.0, -7.0], [4.0, 4.0, 9.0]])
    result = adjust_lights(highlights, silhouettes, RADIUS, start, centres + 1.0)
    np.testing.assert_allclose(result.positions_mm, lights, atol=1e-4)
    np.testing.assert_allclose(result.sphere_centres_mm, centres, atol=1e-5)
    assert result.highlight_rms_px < 1e-6 and list(result.highlights) == [len(CAMERAS) * 3] * 3
    with pytest.raises(ValueError, match="modules without: \\[1\\]"):
        adjust_lights([h for h in highlights if h.light != 1], silhouettes, RADIUS, start, centres)


def test_highlight_spots_find_centroids_and_saturation():
    image = np.zeros((40, 50))
    rows, cols = np.mgrid[0:40, 0:50]
    for u, v in ((10.3, 12.7), (35.6, 25.2)):
        image += np.exp(-((cols - u) ** 2 + (rows - v) ** 2) / (2 * 0.9**2))
    saturated = np.zeros(image.shape, bool)
    saturated[25, 35] = True
    spots = sorted(highlight_spots(image, saturated), key=lambda s: s.pixel[0])
    assert len(spots) == 2
    np.testing.assert_allclose(spots[0].pixel, (10.3, 12.7), atol=0.02)
    np.testing.assert_allclose(spots[1].pixel, (35.6, 25.2), atol=0.02)
    assert [s.saturated for s in spots] == [False, True]
    assert highlight_spots(np.zeros((5, 5))) == []


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="no bright disc"):
        silhouette_edge(np.full((30, 30), 0.1))
    cut = np.zeros((30, 30))
    cut[5:20, 24:] = 1.0  # a bright patch cut by the border: its edge leaves the image
    with pytest.raises(ValueError, match="not a closed curve"):
        silhouette_edge(cut)
    with pytest.raises(ValueError, match="'edge_px'"):
        silhouette_cone(CAMERAS[0], np.zeros((3, 2)))
