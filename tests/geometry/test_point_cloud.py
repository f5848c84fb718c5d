"""Oriented point clouds: construction checks, voxel merging, rigid transforms, files."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.geometry.point_cloud import PointCloud, VoxelAccumulator, load_point_cloud, save_point_cloud
from polarface.geometry.poses import rigid_transform


def _cloud(count: int = 200, seed: int = 0) -> PointCloud:
    rng = np.random.default_rng(seed)
    return PointCloud.from_arrays(
        rng.uniform(0, 10, (count, 3)), rng.normal(size=(count, 3)), rng.uniform(0, 1, count),
        rng.random((count, 3)),
    )


def test_from_arrays_normalises_and_defaults():
    cloud = PointCloud.from_arrays(np.zeros((3, 3)), [[0, 0, 2.0], [3.0, 0, 0], [0, 0, 0]])
    assert np.allclose(np.linalg.norm(cloud.normals[:2], axis=1), 1.0)
    assert np.all(cloud.confidence == 1) and np.all(cloud.colours == 0) and len(cloud) == 3
    assert len(PointCloud.empty()) == 0 and len(PointCloud.concatenate([PointCloud.empty()])) == 0


def test_voxel_downsample_is_the_confidence_weighted_mean():
    points = [[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [5.0, 5.0, 5.0]]
    cloud = PointCloud.from_arrays(points, [[0, 0, 1.0]] * 3, [0.25, 0.75, 0.5])
    merged = cloud.voxel_downsample(1.0)
    assert len(merged) == 2
    first = merged.points[np.argmin(merged.points[:, 0])]
    assert np.allclose(first, 0.25 * 0.1 + 0.75 * 0.3)  # weights 0.25 and 0.75
    assert sorted(merged.confidence.tolist()) == [0.5, 0.75]  # a voxel keeps its best confidence


def test_accumulated_clouds_merge_as_if_downsampled_at_once():
    """Clouds added one by one (voxels shared with the held ones, new ones before, between and after them)
    give the one-shot downsample of their concatenation: same voxels, means and best confidences."""
    clouds = [_cloud(400, seed) for seed in range(3)]
    clouds.append(PointCloud.from_arrays(clouds[0].points - 20.0, clouds[0].normals, clouds[0].confidence))
    clouds.append(PointCloud.from_arrays(clouds[1].points + 20.0, clouds[1].normals, clouds[1].confidence))
    grid = VoxelAccumulator(2.5)
    for cloud in clouds:
        grid.add(cloud)
        grid.add(PointCloud.empty())
    merged, once = grid.cloud(), PointCloud.concatenate(clouds).voxel_downsample(2.5)
    assert len(merged) == len(once) < sum(len(c) for c in clouds)
    order_merged, order_once = np.lexsort(merged.points.T), np.lexsort(once.points.T)
    for name in ("points", "normals", "confidence", "colours"):
        assert np.allclose(getattr(merged, name)[order_merged], getattr(once, name)[order_once], atol=1e-12)


def test_voxel_sums_are_numpy_bincounts_bit_for_bit():
    """The one-pass per-voxel sums equal ``np.bincount``'s (points' products with their weights added in
    point order) and ``np.maximum.at``'s best confidences, to the last bit; confidence 0 weighs 1e-6."""
    from polarface.geometry.point_cloud import _voxel_keys

    cloud = PointCloud.concatenate([_cloud(3000, 4), _cloud(500, 5)])
    confidence = cloud.confidence.copy()
    confidence[::7] = 0.0
    cloud = PointCloud(cloud.points, cloud.normals, confidence, cloud.colours)
    grid = VoxelAccumulator(2.5)  # ~55 points a voxel: sums that depend on the order of addition
    keys, total, sums, best = grid._reduce(cloud)
    unique, inverse = np.unique(_voxel_keys(cloud.points, 2.5), return_inverse=True)
    weight = np.maximum(confidence.astype(np.float64), 1e-6)
    values = np.concatenate([cloud.points, cloud.normals, cloud.colours.astype(np.float64)], axis=1)
    values *= weight[:, None]
    expected_best = np.zeros(len(unique), np.float32)
    np.maximum.at(expected_best, inverse, confidence)
    assert len(unique) < len(cloud)  # voxels shared by several points
    np.testing.assert_array_equal(keys, unique)
    np.testing.assert_array_equal(total, np.bincount(inverse, weights=weight))
    for c in range(9):
        np.testing.assert_array_equal(sums[:, c], np.bincount(inverse, weights=values[:, c]))
    assert best.dtype == np.float32 and total.dtype == sums.dtype == np.float64
    np.testing.assert_array_equal(best, expected_best)


def test_transformed_and_concatenate():
    cloud = _cloud()
    motion = rigid_transform(yaw=0.3, pitch=-0.1, translation=(1.0, 2.0, 3.0))
    moved = cloud.transformed(motion)
    assert np.allclose(moved.points, cloud.points @ motion[:3, :3].T + motion[:3, 3])
    assert np.allclose(moved.normals, cloud.normals @ motion[:3, :3].T)
    both = PointCloud.concatenate([cloud, moved])
    assert len(both) == 2 * len(cloud)
    assert np.allclose(both.select(np.arange(len(cloud))).points, cloud.points)


def test_files_round_trip_and_bad_input(tmp_path):
    cloud = _cloud()
    path = save_point_cloud(tmp_path / "c.npz", cloud)
    again = load_point_cloud(path)
    for name in ("points", "normals", "confidence", "colours"):
        assert np.array_equal(getattr(again, name), getattr(cloud, name))
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"bad\.npz"):
        load_point_cloud(tmp_path / "bad.npz")
    with pytest.raises(FileNotFoundError, match=r"nope\.npz"):
        load_point_cloud(tmp_path / "nope.npz")
    with pytest.raises(ValueError, match="normals"):
        PointCloud(np.zeros((2, 3)), np.zeros((3, 3)), np.ones(2, np.float32), np.zeros((2, 3), np.float32))
    with pytest.raises(ValueError, match="points"):
        PointCloud.from_arrays([[np.nan, 0, 0]], [[0, 0, 1.0]])
    with pytest.raises(ValueError, match="voxel_mm"):
        cloud.voxel_downsample(0.0)
    with pytest.raises(ValueError, match="transform"):
        cloud.transformed(np.diag([2.0, 1, 1, 1]))
