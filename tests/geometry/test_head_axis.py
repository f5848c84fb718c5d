"""polarface.geometry.head_axis: the head's vertical axis and a point on it from a revolving-chair pose
sequence (a tilted axis recovered, the fallback when the head does not turn, bad poses named)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from polarface.geometry.head_axis import head_axis_from_poses, head_axis_point_from_poses

UP = np.array([0.0, -1.0, 0.0])


def _yaw_sweep(axis, pivot, frames=41, pitch_deg=2.0, seed=0):
    rng = np.random.default_rng(seed)
    yaw = np.radians(np.linspace(-60, 60, frames))
    poses = np.tile(np.eye(4), (frames, 1, 1))
    for i, angle in enumerate(yaw):
        rot = Rotation.from_rotvec(angle * axis) * Rotation.from_euler(
            "x", rng.normal(0, pitch_deg), degrees=True
        )
        poses[i, :3, :3] = rot.as_matrix()
        poses[i, :3, 3] = pivot - rot.as_matrix() @ pivot
    return poses


def test_head_axis_from_poses_recovers_tilted_axis():
    axis = np.array([0.08, -1.0, 0.12])
    axis /= np.linalg.norm(axis)
    pivot = np.array([5.0, 20.0, 1110.0])
    estimate = head_axis_from_poses(_yaw_sweep(-axis, pivot))  # turning sign does not matter
    assert np.degrees(np.arccos(np.clip(estimate @ axis, -1, 1))) < 1.0
    exact = head_axis_from_poses(_yaw_sweep(axis, pivot, pitch_deg=0.0))
    np.testing.assert_allclose(exact, axis, atol=1e-9)
    point = head_axis_point_from_poses(_yaw_sweep(axis, pivot, pitch_deg=0.0), exact)
    off = (point - pivot) - ((point - pivot) @ axis) * axis
    assert np.linalg.norm(off) < 1e-6


def test_head_axis_falls_back_when_static():
    poses = np.tile(np.eye(4), (5, 1, 1))
    poses[:, :3, 3] = np.random.default_rng(1).normal(0, 2, (5, 3))
    poses[2, :3, :3] = Rotation.from_euler("y", 3.0, degrees=True).as_matrix()
    np.testing.assert_allclose(head_axis_from_poses(poses), UP)
    np.testing.assert_allclose(head_axis_from_poses(poses, default_axis=(0, -2, 0)), UP)
    with pytest.raises(ValueError, match="poses"):
        head_axis_point_from_poses(poses, UP)


def test_head_axis_bad_poses():
    with pytest.raises(ValueError, match="poses"):
        head_axis_from_poses(np.eye(4))
    bad = np.tile(np.eye(4), (3, 1, 1))
    bad[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match="poses"):
        head_axis_from_poses(bad)
    with pytest.raises(ValueError, match="default_axis"):
        head_axis_from_poses(np.tile(np.eye(4), (3, 1, 1)), default_axis=(0, 0, 0))
