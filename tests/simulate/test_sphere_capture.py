"""The synthetic sphere-cap mesh and maps used by tests and benchmarks."""

from __future__ import annotations

import numpy as np

from polarface.geometry.uv_raster import rasterize_uv
from polarface.simulate.sphere_capture import sphere_cap_mesh, sphere_maps


def test_sphere_cap_mesh_is_a_valid_uv_chart():
    mesh = sphere_cap_mesh(50.0, 60.0, segments=16)
    np.testing.assert_allclose(np.linalg.norm(mesh.vertices, axis=1), 50.0, rtol=1e-9)
    assert (mesh.face_normals()[:, 2] > 0).all()  # outward (towards +z) orientation
    raster = rasterize_uv(mesh, 16)
    assert raster.coverage > 0.4


def test_sphere_maps_ranges():
    mask = np.ones((8, 8), bool)
    maps = sphere_maps(8, mask)
    assert maps["rho_sss_bar"].shape == (8, 8, 6)
    assert (maps["eta"] > 1.3).all() and (maps["alpha_ss"] > maps["alpha_s"]).all()
    assert (maps["rho_sss_bar"] > 0).all() and (maps["rho_sss_bar"] < 1).all()
