"""The white sphere's radiometry (``polarface.capture.radiometric_calibration``): a Lambertian sphere's
radiance against its closed form, the products of gain and intensity recovered exactly, the gauge that
splits them, and bad input named."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.capture.radiometric_calibration import channel_products, lambertian_sphere, split_products
from polarface.geometry.camera import PinholeCamera

CAMERA = PinholeCamera.look_at(np.zeros(3), np.array([0.0, 0.0, 1000.0]), width=96, height=80, focal=400.0)
CENTRE = np.array([0.0, 0.0, 1000.0])
RADIUS = 75.0


def test_the_radiance_is_lamberts_law():
    light = np.array([0.0, 0.0, 0.0])  # at the camera: the sphere's nearest point faces both
    centre_pixel = CAMERA.project(CENTRE)[0][None]
    radiance, lit, view = lambertian_sphere(CAMERA, CENTRE, RADIUS, light, centre_pixel)
    distance = 1000.0 - RADIUS
    assert radiance[0] == pytest.approx(1.0 / (np.pi * distance**2), rel=1e-9)
    assert lit[0] == pytest.approx(1.0) and view[0] == pytest.approx(1.0)
    # off the axis: radiance = cos / (pi d^2) at the sphere point each ray hits
    full, lit, view = lambertian_sphere(CAMERA, CENTRE, RADIUS, np.array([300.0, -200.0, 100.0]))
    assert full.shape == (80, 96) and (full >= 0).all()
    assert (full[view == 0] == 0).all() and (full[(view > 0) & (lit == 0)] == 0).all()  # missed, or unlit
    assert ((view > 0) & (lit == 0)).any() and ((view > 0) & (lit > 0)).any()  # the terminator is in view
    # the inverse square law: the light twice as far from the sphere's nearest point (z = 925 mm), 425 and
    # 850 mm, quarters the brightest pixel
    near, _, _ = lambertian_sphere(CAMERA, CENTRE, RADIUS, np.array([0.0, 0.0, 500.0]))
    far, _, _ = lambertian_sphere(CAMERA, CENTRE, RADIUS, np.array([0.0, 0.0, 75.0]))
    assert far.max() / near.max() == pytest.approx((425.0 / 850.0) ** 2, rel=0.02)


def test_products_are_recovered_and_split_by_the_gauge():
    rng = np.random.default_rng(0)
    predicted = rng.uniform(0.1, 1.0, (20, 30))
    truth = np.array([2.0, 3.5, 0.7])
    valid = np.ones((20, 30), bool)
    valid[:3] = False
    observed = predicted[..., None] * truth
    observed[:3] = 99.0  # invalid pixels are not counted
    products, rms = channel_products(observed, predicted, valid)
    np.testing.assert_allclose(products, truth, rtol=1e-12)
    np.testing.assert_allclose(rms, 0.0, atol=1e-12)
    table = rng.uniform(0.9, 1.1, (8, 6)) * rng.uniform(0.5, 2.0, 6)
    gains, intensities = split_products(table, np.full(6, 1e6))
    np.testing.assert_allclose(gains[None] * intensities, table)  # the products unchanged
    np.testing.assert_allclose(intensities.mean(axis=0), 1e6)  # the modules' mean at the nominal value
    with pytest.raises(ValueError, match="no pixel"):
        channel_products(observed, predicted, np.zeros_like(valid))
