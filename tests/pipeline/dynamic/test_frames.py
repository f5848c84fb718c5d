"""A dynamic frame's texels the tracking could not follow (polarface.pipeline.dynamic.frames): the
tracking's per-vertex confidence carried to the atlas and the flag it gives."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.geometry import TriangleMesh, rasterize_uv
from polarface.geometry.tracking import TrackingConfig, TrackingFrame, track_mesh
from polarface.pipeline.dynamic import DynamicStageConfig, texel_tracking_confidence


def _square() -> TriangleMesh:
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    return TriangleMesh.from_arrays(vertices, faces, vertices[:, :2].copy())


def test_a_texel_takes_the_smallest_confidence_of_its_triangle():
    mesh = _square()
    confidence = np.array([1.0, 0.8, 0.6, 0.0])
    texels = texel_tracking_confidence(mesh, confidence, (16, 16))
    raster = rasterize_uv(mesh, (16, 16))
    first = raster.mask & (raster.face_id == 0)
    second = raster.mask & (raster.face_id == 1)
    assert first.any() and second.any()
    assert np.all(texels[first] == np.float32(0.6)) and np.all(texels[second] == 0.0)
    assert texels.dtype == np.float32 and np.all(texels[~raster.mask] == 0.0)


def test_bad_confidence_and_threshold_are_refused():
    with pytest.raises(ValueError, match="confidence"):
        texel_tracking_confidence(_square(), np.ones(3), (8, 8))
    for value in (-0.1, 1.5, "0.1", True):
        with pytest.raises(ValueError, match="min_tracking_confidence"):
            DynamicStageConfig(min_tracking_confidence=value)


def test_an_untrackable_mouth_is_flagged_there_and_the_rest_of_the_face_is_kept():
    """The tiny simulator head, still, rendered noise-free three times; in the second frame every
    camera's pixels around the mouth are replaced by noise (an occluding hand, a tongue, a flow that
    cannot follow). The mouth's texels are flagged (confidence below the stage's default threshold) and
    the rest of the face is tracked in place and not flagged; the third, clean frame says which texels
    the cameras follow at all."""
    from polarface.simulate.pipeline import SimulationConfig, SimulationScene, render_frame

    scene = SimulationScene.build(SimulationConfig(preset="tiny", sequences=("dynamic",), noise=False))
    mesh = scene.asset.mesh.transformed(scene.placement)
    render = render_frame(scene, mesh, scene.maps, scene.subsurface)
    mouth = mesh.vertices[scene.asset.landmarks["mouth_center"]]
    rng = np.random.default_rng(0)

    def image(frame: int, camera) -> np.ndarray:
        images = render.views[camera.id].images
        picture = (2.0 * images["i90"] if camera.role == "polarimetric" else images["s0"]).mean(-1)
        if frame == 1:  # a disc of 15 mm about the mouth, as the camera sees it, is noise
            pinhole = camera.pinhole()
            centre = pinhole.project(mouth)[0]
            radius = np.linalg.norm(pinhole.project(mouth + 15.0 * pinhole.right_vector)[0] - centre)
            rows, cols = np.indices(picture.shape)
            disc = (cols - centre[0]) ** 2 + (rows - centre[1]) ** 2 < radius**2
            picture = np.where(disc, rng.uniform(0.0, 2.0 * picture.mean(), picture.shape), picture)
        return picture.astype(np.float32)

    def load(frame: int) -> TrackingFrame:
        return TrackingFrame(frame, {c.id: image(frame, c) for c in scene.rig.cameras}, mesh)

    cameras = {c.id: c.pinhole() for c in scene.rig.cameras}
    tracked = track_mesh(mesh, cameras, load, [0, 1, 2], TrackingConfig(surface_weight=0.1))
    assert tracked.failed == {}
    threshold = DynamicStageConfig().min_tracking_confidence
    rings = DynamicStageConfig().tracking_support_rings
    texels = texel_tracking_confidence(mesh, tracked.confidence[1], (256, 256), rings)
    raster = rasterize_uv(mesh, (256, 256))
    clean = texel_tracking_confidence(mesh, tracked.confidence[2], (256, 256), rings)
    seen = raster.mask & (clean >= threshold)
    distance = np.linalg.norm(raster.position - mouth, axis=-1)
    flagged = seen & (texels < threshold)
    near, face = seen & (distance < 8.0), seen & (distance > 40.0) & (distance < 90.0)
    print(f"flagged: {flagged[near].mean():.3f} near the mouth, {flagged[face].mean():.3f} on the face")
    errors = np.linalg.norm(tracked.vertices[1] - mesh.vertices, axis=1)
    kept = tracked.confidence[1] >= threshold
    near_vertices = kept & (np.linalg.norm(mesh.vertices - mouth, axis=1) < 8.0)
    print(f"kept vertices: median error {np.median(errors[kept]):.3f} mm; near the mouth "
          f"{np.round(errors[near_vertices], 2)} mm")
    assert near.sum() > 20 and flagged[near].mean() > 0.8
    assert flagged[face].mean() < 0.05
    assert np.median(errors[kept]) < 0.1
