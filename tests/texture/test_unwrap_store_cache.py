"""The unwrap store's chunk cache (texture/unwrap_store.py): reads through the cache equal uncached reads
(regions straddling chunks, clipped at the texture's edge, view subsets in any order, the texel
geometry), a region read again decodes nothing, the decoded chunks held stay within the bound, and a
cache on a writable store is refused.

A synthetic sphere capture with a 24 x 24 atlas in 8-texel chunks (a 3 x 3 chunk grid).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from polarface.capture.store import CaptureStore
from polarface.geometry.mesh import load_mesh
from polarface.geometry.poses import load_poses
from polarface.simulate.sphere_capture import SphereCaptureConfig, make_sphere_capture
from polarface.texture import TexelGeometry, UnwrapConfig, UnwrapStore, unwrap_capture

RES, PATCH = 24, 8
REGIONS = [
    (slice(0, 24), slice(0, 24)),  # the whole texture
    (slice(4, 20), slice(3, 13)),  # a haloed patch: straddles 3 x 2 chunks
    (slice(8, 16), slice(8, 16)),  # one chunk exactly
    (slice(20, 30), slice(-4, None)),  # clipped at the edge, negative start
    (slice(5, 5), slice(0, 8)),  # empty
]


@pytest.fixture(scope="module")
def unwrap_path(tmp_path_factory):
    root = tmp_path_factory.mktemp("unwrap_cache")
    make_sphere_capture(root / "sim", SphereCaptureConfig(texture_resolution=RES, frames=3))
    unwrap_capture(
        CaptureStore.open(root / "sim" / "static"), load_mesh(root / "sim/ground_truth/mesh_rest.obj"),
        load_poses(root / "sim/ground_truth/static/poses.json"), root / "unwrap.zarr",
        UnwrapConfig(texture_resolution=RES, patch=PATCH), progress=False,
    )  # fmt: skip
    return root / "unwrap.zarr"


@pytest.mark.parametrize("views", [None, [0, 2, 5], [5, 1], []])
def test_cached_reads_equal_uncached_reads(unwrap_path, views):
    plain, cached = UnwrapStore.open(unwrap_path), UnwrapStore.open(unwrap_path, cache_bytes=1 << 30)
    for rows, cols in REGIONS * 2:  # the second time from the cache
        for got, expected in zip(cached.read(rows, cols, views), plain.read(rows, cols, views), strict=True):
            assert got.dtype == expected.dtype and got.shape == expected.shape
            assert np.array_equal(got, expected), (rows, cols, views)
        got_geometry, expected_geometry = cached.geometry(rows, cols), plain.geometry(rows, cols)
        for field in dataclasses.fields(TexelGeometry):
            assert np.array_equal(getattr(got_geometry, field.name), getattr(expected_geometry, field.name))


def test_a_region_read_again_decodes_nothing_and_the_cache_stays_within_its_bound(unwrap_path):
    cached = UnwrapStore.open(unwrap_path, cache_bytes=1 << 30)
    cached.read(slice(4, 14), slice(3, 13), [0, 1, 2])
    first = cached.cache_counts
    assert first["misses"] == 3 * 4 * 3 and first["hits"] == 0  # 3 arrays x 2 x 2 chunks x 3 views
    cached.read(slice(6, 14), slice(4, 12), [2, 0])  # inside the chunks already held
    assert cached.cache_counts["misses"] == first["misses"] and cached.cache_counts["bytes"] == first["bytes"]
    chunk_bytes = PATCH * PATCH * 9 * 4  # one obs chunk, the largest
    small = UnwrapStore.open(unwrap_path, cache_bytes=2 * chunk_bytes)
    plain = UnwrapStore.open(unwrap_path)
    for rows, cols in REGIONS:
        for got, expected in zip(small.read(rows, cols), plain.read(rows, cols), strict=True):
            assert np.array_equal(got, expected)
        assert 0 < small.cache_counts["bytes"] <= 2 * chunk_bytes
    assert UnwrapStore.open(unwrap_path).cache_counts == {"hits": 0, "misses": 0, "bytes": 0}


def test_a_cache_on_a_writable_store_is_refused(unwrap_path):
    with pytest.raises(ValueError, match="cache_bytes"):
        UnwrapStore.open(unwrap_path, mode="a", cache_bytes=1 << 20)


@pytest.mark.parametrize("cache_bytes", [0, 1 << 30])
@pytest.mark.parametrize("views", [None, [0, 2, 5], [5, 1]])
def test_reads_equal_zarrs_own_reads(unwrap_path, views, cache_bytes):
    """A local store's regions are decoded from its chunk files directly (io/zarr_chunks.py), with or
    without the cache: the same arrays as zarr's own reads, and the same view counts."""
    store = UnwrapStore.open(unwrap_path, cache_bytes=cache_bytes)
    assert store._assembled("obs") and store._array("lit")[1] is not None  # the direct path is taken
    chosen = np.arange(len(store.views)) if views is None else np.asarray(views)
    for rows, cols in REGIONS:
        for name, got in zip(("obs", "valid", "lit"), store.read(rows, cols, views), strict=True):
            expected = np.asarray(store.root[name].get_orthogonal_selection((chosen, rows, cols)))
            assert got.dtype == expected.dtype and np.array_equal(got, expected), (name, rows, cols)
        geometry = store.geometry(rows, cols)
        for field in dataclasses.fields(TexelGeometry):
            expected = np.asarray(store.root[f"texel/{field.name}"][rows, cols])
            assert np.array_equal(getattr(geometry, field.name), expected), field.name
    fitting = [i for i, view in enumerate(store.views) if not view.held_out]
    expected_count = np.asarray(store.root["valid"].get_orthogonal_selection((np.asarray(fitting),))).sum(0)
    assert np.array_equal(store.visible_count(), expected_count)


def test_a_view_written_directly_reads_back_through_zarr_and_bad_shapes_are_refused(unwrap_path, tmp_path):
    """create and write_view on a local store write each chunk straight to its file (io/zarr_chunks.py): a
    store written view by view from another store's arrays reads, through zarr, the same arrays."""
    source = UnwrapStore.open(unwrap_path)
    copy = UnwrapStore.create(tmp_path / "copy.zarr", source.geometry(), source.views, PATCH)
    assert copy._array("obs")[1] is not None  # the direct path is taken
    for index in range(len(source.views)):
        copy.write_view(index, *(array[0] for array in source.read(slice(None), slice(None), [index])))
    for name in ("obs", "valid", "lit"):
        assert np.array_equal(np.asarray(copy.root[name][...]), np.asarray(source.root[name][...])), name
    for field in dataclasses.fields(TexelGeometry):  # create writes the texel geometry's chunks directly
        name = f"texel/{field.name}"
        assert np.array_equal(np.asarray(copy.root[name][...]), np.asarray(source.root[name][...])), name
    obs, valid, lit = source.read(slice(None), slice(None), [0])
    with pytest.raises(ValueError, match="argument 'lit' must have shape"):
        copy.write_view(0, obs[0] + 1.0, valid[0], lit[0, :, :, :1])
    # nothing of the refused view is written: its obs are still the source's
    assert np.array_equal(np.asarray(copy.root["obs"][0]), np.asarray(source.root["obs"][0]))
