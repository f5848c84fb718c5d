"""Demo scene: pinhole rays, analytic sphere intersection, LED ring geometry, demo render."""

import math

import pytest
import torch

from polarface.geometry.camera import PinholeCamera
from polarface.render.demo import DemoParameters, render_demo
from polarface.render.scene import ring_light_positions, trace_sphere


def test_camera_rays_and_up():
    cam = PinholeCamera.centred(4, 2, 100.0)
    rays = cam.ray_directions_tensor(torch.float64)
    assert rays.shape == (2, 4, 3)
    torch.testing.assert_close(rays.norm(dim=-1), torch.ones(2, 4, dtype=torch.float64))
    assert rays[0, 0, 0] < 0 and rays[0, 0, 1] < 0  # top-left pixel looks left and up (y down)
    torch.testing.assert_close(cam.up_tensor(), torch.tensor([0.0, -1.0, 0.0]))
    with pytest.raises(ValueError, match="focal"):
        PinholeCamera.centred(4, 4, -1.0)


def test_sphere_intersection_analytic():
    cam = PinholeCamera.centred(128, 128, 800.0)
    geometry = trace_sphere(cam, (0.0, 0.0, 1000.0), 80.0, torch.float64)
    hit = geometry.mask
    points = geometry.position[hit]
    distance = (points - torch.tensor([0.0, 0.0, 1000.0], dtype=torch.float64)).norm(dim=-1)
    torch.testing.assert_close(distance, torch.full_like(distance, 80.0))
    torch.testing.assert_close(geometry.normal.norm(dim=-1), torch.ones(128, 128, dtype=torch.float64))
    # front side only: normals face the camera
    assert bool(((geometry.normal[hit] * points).sum(-1) < 0).all())
    # projected disc area: pi (f r / sqrt(d^2 - r^2))^2 pixels (tangent cone)
    radius_px = 800.0 * 80.0 / math.sqrt(1000.0**2 - 80.0**2)
    assert int(hit.sum()) == pytest.approx(math.pi * radius_px**2, rel=0.02)
    assert not bool(torch.isnan(geometry.normal).any())
    with pytest.raises(ValueError, match="radius_mm"):
        trace_sphere(cam, radius_mm=0.0)


def test_ring_lights_at_paper_angle():
    cam = PinholeCamera.centred(256, 256, 1400.0)
    lights = ring_light_positions(cam, 100.0, 8, dtype=torch.float64)
    assert lights.shape == (8, 3)
    torch.testing.assert_close(lights[:, :2].norm(dim=-1), torch.full((8,), 100.0, dtype=torch.float64))
    assert float(lights[:, 2].abs().max()) == 0.0
    subject = torch.tensor([0.0, 0.0, 1000.0], dtype=torch.float64)
    cos = ((lights - subject) @ -subject) / ((lights - subject).norm(dim=-1) * subject.norm())
    assert math.degrees(float(torch.acos(cos).mean())) == pytest.approx(5.71, abs=0.01)
    with pytest.raises(ValueError, match="count"):
        ring_light_positions(cam, count=0)


def test_render_demo_small():
    result = render_demo(DemoParameters(width=48, height=48, focal_px=1400.0 * 48 / 256))
    images = result.images
    assert images.i0.shape == (48, 48, 3)
    assert bool(torch.isfinite(images.stokes).all())
    assert float(images.i0[~result.geometry.mask].abs().max()) == 0.0
    lit = result.geometry.mask
    assert bool((images.i90[lit] > 0).all())
    with pytest.raises(ValueError, match="rho_sss_bar"):
        DemoParameters(rho_sss_bar=(0.5, 0.5))
