"""polarface.geometry.uv_raster: rasterisation against analytic planes and spheres, sampling, reposition."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from polarface.geometry import (
    TriangleMesh,
    dilate_texture,
    rasterize_uv,
    reposition,
    rigid_transform,
    sample_texture,
    texel_uv,
    texels_to_world,
    uv_raster,
)


def test_plane_positions_and_texel_sizes(plane):
    raster = rasterize_uv(plane, (16, 32))
    assert raster.resolution == (16, 32) and raster.coverage == 1.0
    uv = texel_uv(16, 32)
    expected = np.stack([uv[..., 0] * 40.0, uv[..., 1] * 20.0, np.zeros((16, 32))], axis=-1)
    np.testing.assert_allclose(raster.position, expected, atol=1e-5)
    np.testing.assert_allclose(raster.texel_size_u, 40.0 / 32, rtol=1e-6)
    np.testing.assert_allclose(raster.texel_size_v, 20.0 / 16, rtol=1e-6)
    np.testing.assert_allclose(raster.tangent_u, np.broadcast_to([1, 0, 0], (16, 32, 3)), atol=1e-7)
    np.testing.assert_allclose(raster.tangent_v, np.broadcast_to([0, 1, 0], (16, 32, 3)), atol=1e-7)
    np.testing.assert_allclose(raster.normal, np.broadcast_to([0, 0, 1], (16, 32, 3)), atol=1e-7)
    # row 0 is the top of the atlas (v near 1 -> y near 20 mm)
    assert raster.position[0, 0, 1] > raster.position[-1, 0, 1]
    assert raster.position.dtype == np.float32 and raster.face_id.dtype == np.int64


def test_partial_coverage_triangle():
    mesh = TriangleMesh.from_arrays(
        [[0, 0, 0], [10, 0, 0], [0, 10, 0]], [[0, 1, 2]], [[0, 0], [1, 0], [0, 1]]
    )
    raster = rasterize_uv(mesh, 64)
    uv = texel_uv(64, 64)
    inside = uv.sum(-1) <= 1.0
    np.testing.assert_array_equal(raster.mask, inside)
    assert np.all(raster.face_id[~raster.mask] == -1)
    assert np.all(raster.position[~raster.mask] == 0)


def test_sphere_positions_and_texel_sizes(uv_sphere):
    height, width = 128, 256
    raster = rasterize_uv(uv_sphere, (height, width))
    m = raster.mask
    assert raster.coverage > 0.99  # only texels at the pole fans' corners are uncovered
    radius = np.linalg.norm(raster.position[m], axis=1)
    assert np.abs(radius - 50.0).max() < 0.05  # chord sag of a 128 x 64 tessellation
    uv = texel_uv(height, width)
    lat = (uv[..., 1] - 0.5) * np.pi
    lon = uv[..., 0] * 2 * np.pi
    expected = 50.0 * np.stack([np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon)], -1)
    assert np.abs(raster.position[m] - expected[m]).max() < 0.2
    # texel sizes: 2 pi r cos(lat) / W along u and pi r / H along v (chords of the facets: <1 % short);
    # next to the longitude seam the per-vertex average is one-sided (a few % off)
    band = m & (np.abs(lat) < np.radians(70))
    interior = band.copy()
    interior[:, [0, 1, 2, -3, -2, -1]] = False
    s_u_true = 2 * np.pi * 50.0 * np.cos(lat) / width
    np.testing.assert_allclose(raster.texel_size_u[interior], s_u_true[interior], rtol=0.01)
    np.testing.assert_allclose(raster.texel_size_u[band], s_u_true[band], rtol=0.05)
    np.testing.assert_allclose(raster.texel_size_v[band], np.pi * 50.0 / height, rtol=0.01)
    # normals radial, tangents along +lon and +lat
    radial = expected / 50.0
    assert np.einsum("tc,tc->t", raster.normal[m], radial[m]).min() > 0.999
    east = np.stack([np.cos(lon), np.zeros_like(lon), -np.sin(lon)], -1)
    assert np.einsum("tc,tc->t", raster.tangent_u[band], east[band]).min() > 0.99
    north = np.stack([-np.sin(lat) * np.sin(lon), np.cos(lat), -np.sin(lat) * np.cos(lon)], -1)
    assert np.einsum("tc,tc->t", raster.tangent_v[band], north[band]).min() > 0.99
    # total area covered by texels ~ sphere area
    area = (raster.texel_size_u * raster.texel_size_v)[m].sum()
    assert abs(area - 4 * np.pi * 2500) / (4 * np.pi * 2500) < 0.02


def test_reposition_and_texels_to_world(uv_sphere):
    raster = rasterize_uv(uv_sphere, 64)
    pose = rigid_transform(0.4, -0.3, 0.2, translation=(10, 20, -30))
    moved_mesh = uv_sphere.transformed(pose)
    moved = reposition(raster, moved_mesh)
    m = raster.mask
    expected = raster.position[m].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    np.testing.assert_allclose(moved.position[m], expected, atol=1e-3)
    np.testing.assert_allclose(moved.texel_size_u, raster.texel_size_u, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(
        moved.normal[m], raster.normal[m] @ pose[:3, :3].T.astype(np.float32), atol=1e-5
    )
    world = texels_to_world(raster, moved_mesh.vertices, moved_mesh.faces)
    np.testing.assert_allclose(world[m], expected, atol=1e-3)
    assert np.isnan(world[~m]).all()
    np.testing.assert_array_equal(moved.face_id, raster.face_id)
    with pytest.raises(ValueError, match="vertices"):
        texels_to_world(raster, np.zeros((3, 2)), moved_mesh.faces)


def test_head_atlas_coverage(head):
    raster = rasterize_uv(head.mesh, 256)
    assert 0.85 < raster.coverage < 0.97
    lo, hi = head.mesh.bounding_box()
    pts = raster.position[raster.mask]
    assert np.all(pts >= lo.astype(np.float32) - 1e-3) and np.all(pts <= hi.astype(np.float32) + 1e-3)
    assert np.all(raster.texel_size_u[raster.mask] > 0) and np.all(raster.texel_size_v[raster.mask] > 0)
    np.testing.assert_allclose(np.linalg.norm(raster.normal[raster.mask], axis=1), 1.0, atol=1e-5)


def test_batching_does_not_change_result(uv_sphere):
    uv_raster._COVERAGES.clear()  # both rasterised, not the second taken from the first
    a = rasterize_uv(uv_sphere, 64)
    uv_raster._COVERAGES.clear()
    b = rasterize_uv(uv_sphere, 64, batch_texels=257)
    np.testing.assert_array_equal(a.face_id, b.face_id)
    np.testing.assert_array_equal(a.barycentric, b.barycentric)


def test_coverage_is_shared_by_rasters_of_the_same_faces_and_uvs(uv_sphere, plane):
    """A posed or deformed copy of a mesh reuses the coverage (read-only, the same arrays); its geometry
    is its own and equals a fresh rasterisation's; other UVs or another resolution rasterise again."""
    uv_raster._COVERAGES.clear()
    first = rasterize_uv(uv_sphere, 64)
    bent = uv_sphere.with_vertices(uv_sphere.vertices * np.array([1.0, 1.3, 0.8]))
    shared = rasterize_uv(bent, 64)
    assert shared.face_id is first.face_id and shared.barycentric is first.barycentric
    assert not shared.face_id.flags.writeable and not shared.barycentric.flags.writeable
    uv_raster._COVERAGES.clear()
    fresh = rasterize_uv(bent, 64)
    for name in ("face_id", "barycentric", "mask", "position", "normal", "texel_size_u", "texel_size_v"):
        np.testing.assert_array_equal(getattr(shared, name), getattr(fresh, name))
    assert not np.array_equal(shared.position, first.position)
    assert rasterize_uv(bent, 32).face_id is not fresh.face_id  # another resolution
    flipped = TriangleMesh.from_arrays(uv_sphere.vertices, uv_sphere.faces, 1.0 - uv_sphere.uv)
    assert not np.array_equal(rasterize_uv(flipped, 64).face_id, fresh.face_id)  # other UVs
    rasterize_uv(plane, 16)
    assert len(uv_raster._COVERAGES) <= uv_raster._COVERAGE_ENTRIES


def test_sample_texture_reference_values():
    texture = np.arange(12, dtype=np.float64).reshape(3, 4)  # rows top->bottom
    uv_centres = texel_uv(3, 4)
    np.testing.assert_allclose(sample_texture(texture, uv_centres), texture)  # exact at centres
    # halfway between the top-left two texels
    np.testing.assert_allclose(sample_texture(texture, np.array([[0.25, 1 - 0.5 / 3]])), [0.5])
    # clamp outside the atlas and at the borders
    np.testing.assert_allclose(sample_texture(texture, np.array([[0.0, 1.0], [1.0, 0.0]])), [0.0, 11.0])
    rgb = np.stack([texture, 2 * texture, 3 * texture], -1)
    out = sample_texture(rgb, np.array([[0.5, 0.5]]))
    assert out.shape == (1, 3)
    np.testing.assert_allclose(out[0], [5.5, 11.0, 16.5])


def test_sample_texture_torch_gradcheck_and_dtype():
    texture = torch.rand(5, 6, 2, dtype=torch.float64, requires_grad=True)
    uv = torch.tensor([[0.31, 0.47], [0.8, 0.15]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(sample_texture, (texture, uv))
    out32 = sample_texture(texture.detach().float(), uv.detach().float())
    assert out32.dtype == torch.float32 and out32.shape == (2, 2)


def test_sample_texture_row_gathers_equal_2d_indexing():
    """A contiguous texture is read by row gathers of its flattened texels, any other by 2-D indexing:
    the same values for any batch shape of ``uv``, and the same gradients."""
    rng = np.random.default_rng(0)
    texture = torch.from_numpy(rng.random((7, 5, 4)))
    strided = texture.permute(1, 0, 2).contiguous().permute(1, 0, 2)  # same values, not contiguous
    assert not strided.is_contiguous()
    uv = torch.from_numpy(rng.uniform(-0.1, 1.1, (3, 6, 2)))
    assert torch.equal(sample_texture(texture, uv), sample_texture(strided, uv))
    assert sample_texture(texture, uv).shape == (3, 6, 4)
    assert torch.equal(sample_texture(texture[..., 0], uv), sample_texture(strided[..., 0], uv))
    grads = []
    for tex in (texture, strided):
        tex = tex.clone().requires_grad_(True) if tex.is_contiguous() else tex.detach().requires_grad_(True)
        sample_texture(tex, uv).sum().backward()
        grads.append(tex.grad)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-12, atol=1e-12)


def test_sample_texture_errors():
    with pytest.raises(ValueError, match="texture"):
        sample_texture(np.zeros(4), np.zeros((1, 2)))
    with pytest.raises(ValueError, match="uv"):
        sample_texture(np.zeros((4, 4)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="uv"):
        sample_texture(np.zeros((4, 4)), np.array([[np.nan, 0.5]]))


def test_resolution_errors(plane):
    with pytest.raises(ValueError, match="resolution"):
        rasterize_uv(plane, 0)


def test_dilate_texture():
    mask = np.zeros((6, 6), dtype=bool)
    mask[2:4, 2:4] = True
    texture = np.where(mask, 5.0, -1.0)
    out = dilate_texture(texture, mask, texels=1)
    assert np.all(out[mask] == 5.0)
    ring = np.zeros_like(mask)
    ring[1:5, 1:5] = True
    assert np.all(out[ring] == 5.0) and np.all(out[~ring] == -1.0)  # farther texels untouched
    rgb = dilate_texture(np.stack([texture] * 3, -1).astype(np.float32), mask, texels=3)
    assert rgb.dtype == np.float32 and np.all(rgb == 5.0)
    np.testing.assert_array_equal(dilate_texture(texture, mask, texels=0), texture)
    with pytest.raises(ValueError, match="mask"):
        dilate_texture(texture, mask[:3])
    with pytest.raises(ValueError, match="texels"):
        dilate_texture(texture, mask, texels=-1)


def _shifted_sums_dilation(texture: np.ndarray, mask: np.ndarray, texels: int) -> np.ndarray:
    """Growth steps as sums of the eight shifted images of the whole map (what ``dilate_texture``
    computed before it grew only the texels next to the charts)."""
    values = np.where(mask[..., None], texture[..., None] if texture.ndim == 2 else texture, 0.0)
    filled = mask.copy()
    height, width = mask.shape
    for _ in range(texels):
        padded_v = np.pad(values * filled[..., None], ((1, 1), (1, 1), (0, 0)))
        padded_m = np.pad(filled.astype(np.float64), 1)
        total, count = np.zeros_like(values), np.zeros(mask.shape)
        for dy in (0, 1, 2):
            for dx in (0, 1, 2):
                if (dy, dx) != (1, 1):
                    total += padded_v[dy : dy + height, dx : dx + width]
                    count += padded_m[dy : dy + height, dx : dx + width]
        grow = ~filled & (count > 0)
        values[grow] = total[grow] / count[grow, None]
        filled |= grow
    out = np.where(filled[..., None], values, texture[..., None] if texture.ndim == 2 else texture)
    return out if texture.ndim == 3 else out[..., 0]


@pytest.mark.parametrize("channels, texels", [(None, 1), (3, 4), (6, 7)])
def test_dilate_texture_equals_the_shifted_image_sums_bit_for_bit(channels, texels):
    rng = np.random.default_rng(texels)
    mask = np.zeros((40, 33), dtype=bool)
    mask[3:20, 5:30] = rng.random((17, 25)) < 0.9  # a chart with holes, near the image's top border
    mask[28:38, 0:9] = True  # a chart touching the left border
    shape = mask.shape if channels is None else (*mask.shape, channels)
    texture = rng.normal(size=shape) * 1e3
    texture[rng.random(mask.shape) < 0.05] = np.nan  # outside the charts: kept where no growth reaches
    expected = _shifted_sums_dilation(texture, mask, texels)
    np.testing.assert_array_equal(dilate_texture(texture, mask, texels), expected)
