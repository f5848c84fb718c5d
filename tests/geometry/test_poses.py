"""polarface.geometry.poses: Euler rotations, rigidity, the static chair sequence, JSON/NPY I/O."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polarface.geometry import (
    StaticSequenceConfig,
    check_rigid,
    euler_from_rotation,
    invert_rigid,
    load_poses,
    rigid_transform,
    rotation_from_euler,
    save_poses,
    static_sequence_poses,
)

angles = st.floats(-3.0, 3.0)


@settings(max_examples=40, deadline=None)
@given(angles, st.floats(-1.5, 1.5), angles)
def test_rotation_is_orthonormal_and_euler_round_trips(yaw, pitch, roll):
    r = rotation_from_euler(yaw, pitch, roll)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(r) - 1.0) < 1e-12
    np.testing.assert_allclose(rotation_from_euler(*euler_from_rotation(r)), r, atol=1e-9)


def test_reference_directions():
    # positive yaw turns the face (+z) towards +x; positive pitch tilts it down (-y)
    np.testing.assert_allclose(rotation_from_euler(math.pi / 2) @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(rotation_from_euler(0, math.pi / 2) @ [0, 0, 1], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(rotation_from_euler(0, 0, math.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_rigid_transform_pivot_fixed_and_inverse():
    pivot = np.array([0.0, -30.0, -30.0])
    matrix = rigid_transform(0.7, 0.2, -0.1, translation=(5, 0, 0), pivot=pivot)
    np.testing.assert_allclose(
        matrix[:3, :3] @ pivot + matrix[:3, 3], pivot + np.array([5.0, 0, 0]), atol=1e-12
    )
    np.testing.assert_allclose(invert_rigid(matrix) @ matrix, np.eye(4), atol=1e-12)


def test_check_rigid_errors():
    with pytest.raises(ValueError, match=r"'T'.*shape"):
        check_rigid(np.eye(3), "T")
    with pytest.raises(ValueError, match="orthonormal"):
        check_rigid(np.diag([2.0, 1, 1, 1]))
    with pytest.raises(ValueError, match="determinant"):
        check_rigid(np.diag([1.0, 1, -1, 1]))
    bad_row = np.eye(4)
    bad_row[3, 0] = 1
    with pytest.raises(ValueError, match="last row"):
        check_rigid(bad_row)
    with pytest.raises(ValueError, match="NaN"):
        check_rigid(np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="yaw"):
        rotation_from_euler(float("nan"))


def test_static_sequence():
    config = StaticSequenceConfig(frame_count=41)
    poses = static_sequence_poses(config)
    assert poses.shape == (41, 4, 4)
    check_rigid(poses)
    yaws = np.array([euler_from_rotation(p[:3, :3])[0] for p in poses])
    pitches = np.array([euler_from_rotation(p[:3, :3])[1] for p in poses])
    np.testing.assert_allclose([yaws[0], yaws[-1]], [-math.radians(60), math.radians(60)], atol=1e-12)
    assert np.all(np.diff(yaws) > 0)  # monotonic sweep
    assert abs(yaws[20]) < 1e-12 and np.abs(pitches).max() <= math.radians(5) + 1e-12
    pivot = np.array(config.pivot)
    moved = poses[:, :3, :3] @ pivot + poses[:, :3, 3]
    np.testing.assert_allclose(moved, np.broadcast_to(pivot, moved.shape), atol=1e-9)
    assert static_sequence_poses(StaticSequenceConfig(frame_count=1)).shape == (1, 4, 4)
    with pytest.raises(ValueError, match="frame_count"):
        StaticSequenceConfig(frame_count=0)


@pytest.mark.parametrize("suffix", [".json", ".npy"])
def test_save_load_round_trip(tmp_path, suffix):
    poses = static_sequence_poses(StaticSequenceConfig(frame_count=5))
    path = save_poses(tmp_path / f"poses{suffix}", poses)
    np.testing.assert_allclose(load_poses(path), poses, atol=0 if suffix == ".npy" else 1e-15)
    if suffix == ".json":
        assert json.loads(path.read_text())["units"] == "mm"


def test_load_bad_files(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_poses(tmp_path / "none.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"units": "mm", "poses": [np.diag([1.0, 1, -1, 1]).tolist()]}))
    with pytest.raises(ValueError, match=r"bad\.json.*determinant"):
        load_poses(bad)
    garbled = tmp_path / "garbled.json"
    garbled.write_text("{not json")
    with pytest.raises(ValueError, match="garbled"):
        load_poses(garbled)
    metres = tmp_path / "metres.json"
    metres.write_text(json.dumps({"units": "m", "poses": [np.eye(4).tolist()]}))
    with pytest.raises(ValueError, match="units"):
        load_poses(metres)
    with pytest.raises(ValueError, match="suffix"):
        save_poses(tmp_path / "p.txt", np.eye(4))
