"""The dynamic metrics' computations on arrays (``polarface.evaluate.dynamic``): the
recovery fit on synthetic curves and the material points on a synthetic triangle (the pressed-patch
weight against the simulated sequence: ``tests/evaluate/test_dynamic_metrics.py``)."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.evaluate.dynamic import fit_recovery_time_constant, material_point_errors
from polarface.simulate import blood_flow_factor


def test_recovery_fit_finds_the_simulated_time_constant():
    times = np.arange(10) * 0.2  # the demo preset's sampling
    curve = 0.04 - 0.032 * (1.0 - blood_flow_factor(times))  # c = cs (1 - 0.8 (1 - f(t)))
    assert fit_recovery_time_constant(times, curve) == pytest.approx(2.0 / 3.0, rel=1e-4)
    noisy = curve + np.random.default_rng(0).normal(0.0, 2e-4, times.size)
    assert fit_recovery_time_constant(times, noisy) == pytest.approx(2.0 / 3.0, rel=0.1)
    assert fit_recovery_time_constant(times[:2], curve[:2]) is None


def test_material_points_ignore_untracked_and_distant_vertices():
    vertices = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0]])
    faces = np.array([[0, 1, 2]])
    points = np.array([[2.0, 2, 0], [3, 3, 0], [2, 2, 8.0]])  # the last is 8 mm off the surface
    truth = np.stack([vertices, vertices + np.array([0.0, 0.0, 1.0])])  # the triangle rises 1 mm
    tracked = np.stack([points, points + np.array([0.0, 0.0, 0.5])])  # tracking follows halfway
    confidence = np.array([[1, 1, 1], [1, 0, 1]], np.float32)
    errors = material_point_errors(tracked, confidence, truth, faces)
    assert errors[0] == pytest.approx([0.0, 0.0], abs=1e-5)
    assert errors[1] == pytest.approx([0.5], abs=1e-5)  # vertex 1 untracked, vertex 2 too far
