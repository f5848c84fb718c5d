"""The simulator's validation camera (``polarface.simulate.validation``): novel viewpoints around the
head, none of them a rig camera's, and a folder written once (its images and physics are checked by
``tests/evaluate/test_validation.py`` on the shared tiny simulation)."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest

from polarface.simulate.scene import SimulationConfig, SimulationScene
from polarface.simulate.validation import (
    VALIDATION_FOLDER,
    VALIDATION_JSON,
    validation_cameras,
    write_validation,
)


@pytest.fixture(scope="module")
def scene():
    return SimulationScene.build(SimulationConfig(preset="tiny"))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0)))


def test_cameras_surround_the_head_at_the_rig_distance_and_look_at_it(scene):
    cameras = validation_cameras(scene, 24)
    assert list(cameras) == [f"validation_{i:02d}" for i in range(24)]
    reference = scene.rig.polarimetric_cameras()[0].pinhole()
    centre = scene.asset.mesh.transformed(scene.placement).vertices.mean(axis=0)
    distance = np.linalg.norm(reference.center - centre)
    for camera in cameras.values():
        assert np.linalg.norm(camera.center - centre) == pytest.approx(distance, rel=1e-9)
        pixel, depth = camera.project(centre[None])
        np.testing.assert_allclose(pixel[0], [(camera.width - 1) / 2, (camera.height - 1) / 2], atol=1e-6)
        assert depth[0] > 0
        np.testing.assert_array_equal(camera.K, reference.K)
    # 8 azimuths over -75..75 deg and 3 elevations: the views are well apart, and none looks along a
    # polarimetric camera, beside which the LEDs sit: every view sees the head off the lights' axis
    directions = {k: c.center - centre for k, c in cameras.items()}
    assert min(_angle_deg(a, b) for a, b in itertools.combinations(directions.values(), 2)) > 10.0
    for camera in scene.rig.polarimetric_cameras():
        nearest = min(_angle_deg(camera.pinhole().center - centre, d) for d in directions.values())
        assert nearest > 5.0, camera.id
    # fewer than 9 views: one row at the middle elevation (8 deg over the plane through the head's centre
    # normal to the image's up direction, as seen from the polarimetric camera)
    axis = reference.center - centre
    up = reference.up_vector - axis * (reference.up_vector @ axis) / (axis @ axis)
    row = validation_cameras(scene, 4)
    elevations = [90.0 - _angle_deg(c.center - centre, up) for c in row.values()]
    np.testing.assert_allclose(elevations, 8.0, atol=1e-9)


def test_bad_view_counts_are_refused(scene):
    for views in (0, -1, 2.5, True):
        with pytest.raises(ValueError, match="argument 'views'"):
            validation_cameras(scene, views)


def test_the_folder_is_written_once(scene, tmp_path):
    index = write_validation(scene, tmp_path, 2)
    path = tmp_path / VALIDATION_FOLDER / VALIDATION_JSON
    assert json.loads(path.read_text()) == index and len(index["views"]) == 2
    images = [tmp_path / VALIDATION_FOLDER / view["file"] for view in index["views"]]
    stamps = [image.stat().st_mtime_ns for image in images]
    assert write_validation(scene, tmp_path, 2) == index
    assert [image.stat().st_mtime_ns for image in images] == stamps
    # other cameras: written again
    assert len(write_validation(scene, tmp_path, 3)["views"]) == 3
