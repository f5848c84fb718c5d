"""Clusters of the diffuse albedo and per-cluster medians (``polarface.inverse.polarimetric.clusters``,
the ``hwang2022`` variant): planted albedo groups come back as the clusters, medians per cluster, bad
input named."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.inverse.polarimetric.clusters import albedo_clusters, cluster_values


def _planted(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three albedo groups (columns 0-9, 10-19, 20-29) with 1 % noise, the last rows outside the mask."""
    rng = np.random.default_rng(seed)
    truth = np.repeat(np.arange(3), 10)[None, :].repeat(20, axis=0)
    centres = np.array([[0.6, 0.5, 0.4, 0.35, 0.3, 0.25], [0.3] * 6, [0.8, 0.7, 0.2, 0.2, 0.1, 0.1]])
    albedo = centres[truth] + 0.01 * rng.standard_normal((20, 30, 6))
    mask = np.ones((20, 30), bool)
    mask[17:] = False
    return albedo, mask, truth


def test_planted_groups_are_the_clusters():
    albedo, mask, truth = _planted()
    labels = albedo_clusters(albedo, mask, 3, seed=1)
    assert labels.dtype == np.int32 and labels.shape == mask.shape
    for group in range(3):  # each planted group is one cluster, outside the mask too (nearest centre)
        assert len(np.unique(labels[truth == group])) == 1
    assert len(np.unique(labels)) == 3
    np.testing.assert_array_equal(albedo_clusters(albedo, mask, 3, seed=1), labels)  # deterministic


def test_cluster_values_are_medians_over_the_mask():
    _, mask, truth = _planted()
    values = np.arange(600, dtype=np.float64).reshape(20, 30)
    values[~mask] = 1e6  # outside the mask: not counted
    medians = cluster_values(values, truth.astype(np.int32), mask, 4)
    for group in range(3):
        assert medians[group] == pytest.approx(np.median(values[mask & (truth == group)]))
    assert medians[3] == pytest.approx(np.median(values[mask]))  # an empty cluster: the mask's median


def test_bad_input_is_named():
    albedo, mask, truth = _planted()
    with pytest.raises(ValueError, match="'rho_sss_bar'"):
        albedo_clusters(albedo[..., 0], mask, 3)
    with pytest.raises(ValueError, match="'count'"):
        albedo_clusters(albedo, np.zeros_like(mask), 3)
    with pytest.raises(ValueError, match="'values'"):
        cluster_values(albedo[..., 0][:5], truth, mask, 3)
    with pytest.raises(ValueError, match="'mask' has no texel"):
        cluster_values(albedo[..., 0], truth, np.zeros_like(mask), 3)
