"""Unwrap stores from texture-space maps: texel geometry by finite differences (against the UV rasterizer
of a mesh), the texel-grid mesh, one view's samples, and the store writer."""

from __future__ import annotations

import numpy as np
import pytest

from authors_fixtures import plane_maps
from polarface.geometry import TriangleMesh, rasterize_uv
from polarface.texture import (
    UnwrapStore,
    ViewSpec,
    grid_mesh,
    texel_geometry,
    texel_geometry_from_maps,
    texture_view_samples,
    write_texture_unwrap,
)


def test_plane_tangents_and_sizes_are_exact() -> None:
    vertex, normal = plane_maps(6, spacing_mm=2.0)
    normal[0, 0] = 0.0  # out of the mask
    geometry = texel_geometry_from_maps(vertex, normal)
    mask = geometry.mask
    assert mask.sum() == 35 and not mask[0, 0]
    np.testing.assert_allclose(geometry.tangent_u[mask], np.tile([1.0, 0.0, 0.0], (35, 1)), atol=1e-7)
    # +v is up the atlas (decreasing row); the rows run along +y, so dP/dv is -y
    np.testing.assert_allclose(geometry.tangent_v[mask], np.tile([0.0, -1.0, 0.0], (35, 1)), atol=1e-7)
    np.testing.assert_allclose(geometry.texel_size_u[mask], 2.0)
    np.testing.assert_allclose(geometry.texel_size_v[mask], 2.0)


def test_atlas_seams_are_not_differenced_across() -> None:
    vertex, normal = plane_maps(8, spacing_mm=1.0)
    vertex[:, 4:, 2] += 500.0  # the right half is another chart, far away in 3D
    geometry = texel_geometry_from_maps(vertex, normal)
    np.testing.assert_allclose(geometry.texel_size_u[geometry.mask], 1.0, atol=1e-6)


def _cylinder(rows: int = 48, cols: int = 96, radius: float = 80.0) -> TriangleMesh:
    angles = np.linspace(-1.0, 1.0, cols)
    heights = np.linspace(-60.0, 60.0, rows)
    a, h = np.meshgrid(angles, heights)
    vertices = np.stack([radius * np.sin(a), h, -radius * np.cos(a)], -1).reshape(-1, 3)
    uv = np.stack([(a - a.min()) / np.ptp(a), (h - h.min()) / np.ptp(h)], -1).reshape(-1, 2) * 0.9 + 0.05
    index = np.arange(rows * cols).reshape(rows, cols)
    q = (index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:])
    faces = np.concatenate([np.stack([q[0], q[1], q[2]], -1).reshape(-1, 3),
                            np.stack([q[1], q[3], q[2]], -1).reshape(-1, 3)])
    return TriangleMesh.from_arrays(vertices, faces, uv)


def test_matches_the_uv_rasterizer_of_a_mesh() -> None:
    reference = texel_geometry(rasterize_uv(_cylinder(), 64))
    geometry = texel_geometry_from_maps(reference.position, reference.normal)
    mask = reference.mask & geometry.mask
    assert (geometry.mask == reference.mask).all()
    for name in ("tangent_u", "tangent_v"):
        cosine = np.einsum("nc,nc->n", getattr(geometry, name)[mask], getattr(reference, name)[mask])
        assert np.degrees(np.arccos(np.clip(np.median(cosine), -1, 1))) < 0.5, name
    for name in ("texel_size_u", "texel_size_v"):
        ratio = getattr(geometry, name)[mask] / getattr(reference, name)[mask]
        assert np.median(np.abs(ratio - 1)) < 0.01, name


def test_grid_mesh_rasterizes_back_to_the_texel_positions() -> None:
    reference = texel_geometry(rasterize_uv(_cylinder(), 32))
    geometry = texel_geometry_from_maps(reference.position, reference.normal)
    mesh = grid_mesh(geometry)
    assert len(mesh.vertices) == geometry.mask.sum()
    again = rasterize_uv(mesh, 32)
    both = again.mask & geometry.mask
    assert both.sum() >= 0.8 * geometry.mask.sum()
    np.testing.assert_allclose(again.position[both], geometry.position[both], atol=1e-3)
    # faces are oriented along the normals (counter-clockwise from outside)
    facet = np.cross(*(mesh.vertices[mesh.faces[:, k]] - mesh.vertices[mesh.faces[:, 0]] for k in (1, 2)))
    assert (np.einsum("fc,fc->f", facet, mesh.normals[mesh.faces].sum(1)) > 0).all()


def test_view_samples_reference_values_and_validity() -> None:
    rng = np.random.default_rng(0)
    images = [rng.uniform(0.1, 1.0, (3, 4, 3)).astype(np.float32) for _ in range(4)]
    visibility = [np.ones((3, 4)) for _ in range(4)]
    visibility[2][0, 1] = 0.4  # not seen at 90 deg
    images[3][2, 3, 1] = np.nan  # a NaN at 135 deg
    mask = np.ones((3, 4), bool)
    mask[1, 1] = False
    gains = np.array([2.0, 1.0, 0.5])
    obs, valid = texture_view_samples(images, visibility, gains, mask)
    expected = np.ones((3, 4), bool)
    expected[0, 1] = expected[2, 3] = expected[1, 1] = False
    np.testing.assert_array_equal(valid, expected)
    i0, i45, i90, i135 = (image * gains for image in images)
    np.testing.assert_allclose(obs[1, 2, 0], 2 * i90[1, 2], rtol=1e-6)
    np.testing.assert_allclose(obs[1, 2, 1], i135[1, 2] - i45[1, 2], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(obs[1, 2, 2], i0[1, 2] - i90[1, 2], rtol=1e-5, atol=1e-7)
    assert (obs[~valid] == 0).all()
    with pytest.raises(ValueError, match="polarizer angles"):
        texture_view_samples(images[:3], visibility, gains, mask)


def _plane_view(frame: int) -> ViewSpec:
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    lights = tuple((100.0 * np.cos(a), 100.0 * np.sin(a), 0.0) for a in angles)
    return ViewSpec(frame, "cam1", (0, 1, 2), (0.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, -1.0, 0.0), lights,
                    ((1.25e5,) * 3,) * 8)


def test_store_writer_samples_lit_and_refuses_nothing_seen(tmp_path) -> None:
    vertex, normal = plane_maps(6)
    geometry = texel_geometry_from_maps(vertex, normal)
    views = [_plane_view(0), _plane_view(1)]
    obs = np.ones((6, 6, 3, 3), np.float32)
    calls = []

    def read(index):
        calls.append(index)
        return obs * (index + 1), geometry.mask.copy()

    store = write_texture_unwrap(tmp_path / "u.zarr", geometry, views, read, patch=4, progress=False)
    assert store.complete and calls == [0, 1] and not (tmp_path / "u.zarr.partial").exists()
    got, valid, lit = store.read(slice(None), slice(None))
    assert valid.all() and lit.all() and got[1, 0, 0, 0, 0] == 2.0
    assert UnwrapStore.open(tmp_path / "u.zarr").views == views
    # a finished store is returned as is
    write_texture_unwrap(tmp_path / "u.zarr", geometry, views, read, progress=False)
    assert calls == [0, 1]
    with pytest.raises(ValueError, match="no texel is seen"):
        write_texture_unwrap(tmp_path / "none.zarr", geometry, views, lambda i: (obs, np.zeros((6, 6), bool)),
                             progress=False)
    assert not (tmp_path / "none.zarr.partial").exists() and not (tmp_path / "none.zarr").exists()
