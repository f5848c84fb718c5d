"""Small analytic meshes for the geometry tests (no files from ../shared are read)."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.geometry import TriangleMesh


def make_plane(width_mm: float = 40.0, height_mm: float = 20.0) -> TriangleMesh:
    """Rectangle in z = 0 covering uv [0, 1]^2: u along +x (width), v along +y (height)."""
    vertices = [[0, 0, 0], [width_mm, 0, 0], [width_mm, height_mm, 0], [0, height_mm, 0]]
    return TriangleMesh.from_arrays(vertices, [[0, 1, 2], [0, 2, 3]], [[0, 0], [1, 0], [1, 1], [0, 1]])


def make_uv_sphere(radius: float = 50.0, n_lon: int = 128, n_lat: int = 64) -> TriangleMesh:
    """Latitude-longitude sphere with equirectangular UVs (u = lon / 2pi, v = (lat + pi/2) / pi).

    The longitude seam duplicates vertices (u = 0 and u = 1); the poles are fans. Outward normals.
    """
    lon = np.linspace(0.0, 2.0 * np.pi, n_lon + 1)
    lat = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 1)
    lon_g, lat_g = np.meshgrid(lon, lat)  # (n_lat + 1, n_lon + 1)
    x = radius * np.cos(lat_g) * np.sin(lon_g)
    y = radius * np.sin(lat_g)
    z = radius * np.cos(lat_g) * np.cos(lon_g)
    vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    uv = np.stack([lon_g / (2 * np.pi), (lat_g + np.pi / 2) / np.pi], axis=-1).reshape(-1, 2)
    idx = np.arange((n_lat + 1) * (n_lon + 1)).reshape(n_lat + 1, n_lon + 1)
    a, b = idx[:-1, :-1], idx[:-1, 1:]
    c, d = idx[1:, 1:], idx[1:, :-1]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    # drop the degenerate triangles at the poles (two corners on the pole)
    corners = vertices[faces]
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    faces = faces[area > 1e-9]
    mesh = TriangleMesh.from_arrays(vertices, faces, uv)
    # orient outwards
    if np.mean(np.einsum("fc,fc->f", mesh.face_normals(), vertices[faces].mean(1))) < 0:
        mesh = TriangleMesh.from_arrays(vertices, faces[:, ::-1], uv)
    return mesh


@pytest.fixture
def plane() -> TriangleMesh:
    return make_plane()


@pytest.fixture(scope="session")
def uv_sphere() -> TriangleMesh:
    return make_uv_sphere()


@pytest.fixture(scope="session")
def head():
    from polarface.geometry import load_head_asset

    return load_head_asset(256)


@pytest.fixture(scope="session")
def uv_sphere_factory():
    return make_uv_sphere
