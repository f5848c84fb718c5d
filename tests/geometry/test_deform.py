"""polarface.geometry.deform: expression blend shapes keep the mesh valid and move the right regions."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from polarface.geometry import (
    EXPRESSIONS,
    ExpressionConfig,
    ExpressionRig,
    dynamic_sequence_weights,
    flipped_faces,
    rasterize_uv,
    reposition,
    smooth_falloff,
)


@pytest.fixture(scope="module")
def rig(head):
    return ExpressionRig(head.mesh, head.landmarks)


def test_falloff_reference_values():
    np.testing.assert_allclose(
        smooth_falloff(np.array([0.0, 5.0, 10.0, 20.0]), 10.0), [1.0, 0.421875, 0.0, 0.0]
    )
    with pytest.raises(ValueError, match="radius"):
        smooth_falloff(np.zeros(1), 0.0)


def test_no_flipped_triangles_on_weight_grid(rig, head):
    for weights in itertools.product([0.0, 0.5, 1.0], repeat=3):
        vertices = rig.vertices(np.array(weights))
        assert not flipped_faces(head.mesh.vertices, vertices, head.mesh.faces).any(), weights
    for weights in dynamic_sequence_weights(30):
        rig.deform(weights)  # raises on a flip


def test_flip_detector_catches_inversion(head):
    vertices = head.mesh.vertices.copy()
    face = head.mesh.faces[0]
    vertices[face[0]], vertices[face[1]] = head.mesh.vertices[face[1]], head.mesh.vertices[face[0]]
    assert flipped_faces(head.mesh.vertices, vertices, head.mesh.faces)[0]


def test_regions_move_as_named(rig, head):
    rest = head.mesh.vertices
    brow = rig.vertices(np.array([1.0, 0, 0])) - rest
    assert brow[head.landmarks["brow_left"], 1] > 5.0 and brow[head.landmarks["chin"]].any() == 0
    smile = rig.vertices(np.array([0, 1.0, 0])) - rest
    assert smile[head.landmarks["mouth_left"], 0] > 3 and smile[head.landmarks["mouth_right"], 0] < -3
    assert smile[head.landmarks["mouth_left"], 1] > 3
    jaw = rig.vertices(np.array([0, 0, 1.0])) - rest
    assert jaw[head.landmarks["chin"], 1] < -5  # the chin drops
    assert np.abs(jaw[head.landmarks["forehead"]]).max() == 0
    # the back of the head never moves
    back = rest[:, 2] < -60
    for e in range(3):
        assert np.abs(rig.fields[e][back]).max() < 1e-9
    np.testing.assert_array_equal(rig.vertices(np.zeros(3)), rest)


def test_deformed_mesh_keeps_texture_coordinates(rig, head):
    raster = rasterize_uv(head.mesh, 64)
    deformed = rig.deform(np.array([0.5, 1.0, 0.7]))
    np.testing.assert_array_equal(deformed.uv, head.mesh.uv)
    moved = reposition(raster, deformed)
    assert np.array_equal(moved.mask, raster.mask)
    assert np.all(moved.texel_size_u[moved.mask] > 0)


def test_sequence_weights():
    weights = dynamic_sequence_weights(50)
    assert weights.shape == (50, len(EXPRESSIONS))
    assert weights.min() >= 0 and weights.max() <= 1 and weights.max() > 0.99
    np.testing.assert_allclose(weights[[0, -1]], 0, atol=1e-12)
    assert np.abs(np.diff(weights, axis=0)).max() < 0.2  # smooth at 50 frames
    with pytest.raises(ValueError, match="frame_count"):
        dynamic_sequence_weights(0)


def test_errors(rig, head):
    with pytest.raises(ValueError, match="weights"):
        rig.vertices(np.zeros(2))
    with pytest.raises(ValueError, match="weights"):
        rig.vertices(np.array([np.nan, 0, 0]))
    with pytest.raises(ValueError, match="landmarks"):
        ExpressionRig(head.mesh, {"brow_left": 0})
    strong = ExpressionRig(head.mesh, head.landmarks, ExpressionConfig(brow_lift=200.0, brow_radius=5.0))
    with pytest.raises(ValueError, match="flip"):
        strong.deform(np.array([1.0, 0, 0]))
