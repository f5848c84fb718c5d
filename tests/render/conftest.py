"""Fixtures of the simulator tests: a flat skin patch in front of the paper's rig."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.capture.rig import paper_rig
from polarface.geometry.mesh import TriangleMesh
from polarface.geometry.uv_raster import rasterize_uv


def flat_patch(size_mm: float = 40.0, distance_mm: float = 1000.0) -> TriangleMesh:
    """A square facing the polarimetric module (normal towards -z of the rig world), UVs over [0, 1]."""
    half = size_mm / 2
    vertices = np.array(
        [
            [-half, -half, distance_mm],
            [half, -half, distance_mm],
            [half, half, distance_mm],
            [-half, half, distance_mm],
        ]
    )
    # Rig world: y down. u along +x, v along -y (up in the image).
    uv = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]])
    faces = np.array([[0, 2, 1], [0, 3, 2]])
    return TriangleMesh.from_arrays(vertices, faces, uv, source="flat patch")


@pytest.fixture(scope="module")
def patch():
    mesh = flat_patch()
    raster = rasterize_uv(mesh, 64)
    return mesh, raster


@pytest.fixture(scope="module")
def small_rig():
    return paper_rig(width=128, height=96)
