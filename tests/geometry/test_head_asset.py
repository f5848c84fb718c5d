"""polarface.geometry.head_asset: scale, frame, UVs, maps and attribution of the bundled head."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.geometry import RayCaster, load_head_asset, pick_landmark, sample_texture, srgb_to_linear
from polarface.geometry.head_asset import head_data_dir


@pytest.fixture(scope="module")
def native():
    return load_head_asset()


def test_mesh_scale_and_frame(native):
    v = native.mesh.vertices
    assert native.mesh.vertex_count == 9279 and native.mesh.face_count == 17684
    # cranial breadth just above the ears (y 25..55 mm above the origin): 140-170 mm
    band = v[(v[:, 1] > 30) & (v[:, 1] < 55)]
    breadth = band[:, 0].max() - band[:, 0].min()
    assert 140 < breadth < 170
    # +y up: the top of the head is ~120 mm above the origin, shoulders far below
    assert 100 < v[:, 1].max() < 140 and v[:, 1].min() < -200
    # face towards +z: the nose tip is the front-most point near the midline, ~110 mm in front
    nose = native.landmark_position("nose_tip")
    assert abs(nose[0]) < 5 and 90 < nose[2] < 130
    # the origin lies inside the head (between the ears)
    caster = RayCaster(native.mesh)
    dirs = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0, 0, -1.0]])
    assert caster.first_hits(np.zeros((5, 3)), dirs).hit.all()


def test_uvs_and_normals(native):
    uv = native.mesh.uv
    assert uv.min() >= 0 and uv.max() <= 1
    assert np.allclose(np.linalg.norm(native.mesh.normals, axis=1), 1.0)
    # outward normals: the nose-tip normal points forwards
    assert native.mesh.normals[native.landmarks["nose_tip"]][2] > 0.8


def test_maps_shapes_ranges(native):
    assert native.albedo.shape == (1024, 1024, 3) and native.albedo.dtype == np.float32
    assert native.specular.shape == (1024, 1024, 1)
    assert native.normal_tangent.shape == (1024, 1024, 3)
    assert native.displacement.shape == (1024, 1024, 1)
    assert 0 <= native.albedo.min() and native.albedo.max() <= 1
    np.testing.assert_allclose(np.linalg.norm(native.normal_tangent, axis=-1), 1.0, atol=1e-5)
    assert np.median(native.normal_tangent[..., 2]) > 0.95  # mostly along the normal
    h = np.abs(native.displacement)
    assert 0.005 < np.median(h) < 0.05 and 0.1 < np.percentile(h, 99) < 0.5  # mm, pores to wrinkles


def test_uv_orientation_lips_redder_than_forehead(native):
    # sampling the albedo at the mesh's UVs (v up) must put the red lips at the mouth landmark
    lips = sample_texture(native.albedo, native.mesh.uv[[native.landmarks["mouth_center"]]])[0]
    brow = sample_texture(native.albedo, native.mesh.uv[[native.landmarks["forehead"]]])[0]
    assert lips[0] / lips[1] > 1.2 * brow[0] / brow[1]


def test_resampled_resolution():
    small = load_head_asset(128)
    assert small.albedo.shape == (128, 128, 3) and small.displacement.shape == (128, 128, 1)
    assert small.specular.shape == (128, 128, 1)
    with pytest.raises(ValueError, match="texture_resolution"):
        load_head_asset(0)


def test_srgb_reference_values():
    np.testing.assert_allclose(
        srgb_to_linear(np.array([0.0, 0.04045, 0.5, 1.0])), [0.0, 0.04045 / 12.92, 0.21404114, 1.0], rtol=1e-6
    )


def test_attribution_and_size():
    folder = head_data_dir()
    assert (folder / "LeePerrySmith_License.txt").is_file()
    text = (folder / "ATTRIBUTION.md").read_text()
    assert "CC BY 3.0" in text and "Lee Perry-Smith" in text
    from polarface.geometry.head_asset import ATTRIBUTION

    assert "CC BY 3.0" in ATTRIBUTION and "Lee Perry-Smith" in ATTRIBUTION
    total = sum(p.stat().st_size for p in folder.iterdir() if p.is_file())
    assert total < 4 * 1024 * 1024


def test_pick_landmark_errors(native):
    with pytest.raises(ValueError, match="front-facing"):
        pick_landmark(native.mesh, 1000.0, 1000.0)
    with pytest.raises(ValueError, match="unknown landmark"):
        native.landmark_position("elbow")


def test_displacement_consistent_with_scan_normal_map(native):
    """Cross-check sign, v-up convention and scale of H against the scan's own tangent-space normal map.

    On the face, slopes -dH/du / s_u and -dH/dv / s_v (band-passed like H) must correlate with the
    normal map's x and y components and regress on them with a slope near 1.
    """
    from scipy import ndimage

    from polarface.geometry import height_gradients, rasterize_uv

    raster = rasterize_uv(native.mesh, 1024)
    du, dv = height_gradients(native.displacement[..., 0].astype(np.float64), raster.mask)
    face = raster.mask & (raster.position[..., 2] > 40) & (np.abs(du) + np.abs(dv) > 0)
    slope_u = -du[face] / raster.texel_size_u[face]
    slope_v = -dv[face] / raster.texel_size_v[face]
    for slope, channel in ((slope_u, 0), (slope_v, 1)):
        component = native.normal_tangent[..., channel].astype(np.float64)
        band = (component - ndimage.gaussian_filter(component, 4.0))[face]
        assert np.corrcoef(slope, band)[0, 1] > 0.35
        gain = np.cov(slope, band)[0, 1] / slope.var()
        assert 0.6 < gain < 1.5
