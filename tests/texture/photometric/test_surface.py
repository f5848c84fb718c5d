"""The photometric surface refinement (polarface.texture.photometric): the sweep finds a region pushed off
the truth, the gate keeps a surface that the images cannot resolve better unchanged, bad options and
inputs are refused naming the argument. The recovery itself at the demo preset's resolution (a pushed
forehead pulled back to 0.02 mm) is measured by ``benchmarks/bench_surface_refinement.py``: the tiny
preset's 256 x 212 px frames do not resolve 0.5 mm."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.capture import CaptureStore
from polarface.geometry import load_mesh, load_poses, rasterize_uv, rotation_from_euler
from polarface.texture.photometric import (
    SurfaceRefinementConfig,
    TexelGrid,
    ViewSampling,
    photo_consistency_volume,
    refine_surface,
)


@pytest.fixture(scope="module")
def truth(tiny_sim):
    """``(store, true rest mesh, {frame: true pose})`` of the tiny simulation's static sequence."""
    store = CaptureStore.open(tiny_sim / "static")
    mesh = load_mesh(tiny_sim / "ground_truth" / "mesh_rest.obj")
    poses = load_poses(tiny_sim / "ground_truth" / "static" / "poses.json")
    return store, mesh, {record.index: poses[record.index] for record in store.frames}


@pytest.mark.slow
def test_the_true_surface_is_kept_where_the_images_do_not_resolve_it(truth):
    store, mesh, poses = truth
    result = refine_surface(store, mesh, poses, resolution=256)
    assert not result.applied and "min_measured_fraction" in result.not_applied_reason
    assert result.mesh is mesh and not result.vertex_offset_mm.any()
    assert 0.0 < result.measured_fraction < 0.5
    record = result.to_json()
    assert record["applied"] is False and record["texels_measured"] == int(result.measured.sum())
    assert record["seconds"] > 0 and record["texels_seen"] >= record["texels_measured"]
    assert record["flagged_frames"] == [] and record["frames_used"] == len(poses)


@pytest.mark.slow
def test_a_forced_refinement_moves_a_pushed_region_back_and_keeps_topology(truth):
    store, mesh, poses = truth
    vertices = mesh.vertices
    forehead = vertices[np.argmax(vertices[:, 2] + 0.8 * vertices[:, 1])]
    distance = np.linalg.norm(vertices - forehead, axis=1)
    pushed = mesh.with_vertices(vertices + 0.5 * (distance < 30.0)[:, None] * mesh.normals)
    result = refine_surface(
        store, pushed, poses, SurfaceRefinementConfig(min_measured_fraction=0.0), resolution=256
    )
    assert result.applied and result.not_applied_reason is None
    np.testing.assert_array_equal(result.mesh.faces, pushed.faces)
    np.testing.assert_array_equal(result.mesh.uv, pushed.uv)
    core = distance < 20.0
    residual = np.einsum("ij,ij->i", result.mesh.vertices[core] - vertices[core], mesh.normals[core])
    assert abs(np.median(residual)) < 0.35, np.median(residual)  # moved back from 0.5 mm
    raster = rasterize_uv(pushed, result.offset_mm.shape[0])  # the sweep's texture: 1.5 x 256
    texels = raster.mask & (np.linalg.norm(raster.position - forehead, axis=-1) < 20.0) & result.measured
    assert np.median(result.offset_mm[texels]) < -0.15  # the sweep sees the push (its sign and size)


@pytest.mark.parametrize(
    ("make", "field"),
    [
        (lambda: SurfaceRefinementConfig(search_mm=0.0), "search_mm"),
        (lambda: SurfaceRefinementConfig(step_mm=float("nan")), "step_mm"),
        (lambda: SurfaceRefinementConfig(search_mm=0.1, step_mm=0.2), "step_mm"),
        (lambda: SurfaceRefinementConfig(smoothing_texels=-1.0), "smoothing_texels"),
        (lambda: SurfaceRefinementConfig(min_views=1), "min_views"),
        (lambda: SurfaceRefinementConfig(agreement_mm=0.0), "agreement_mm"),
        (lambda: SurfaceRefinementConfig(min_measured_fraction=1.5), "min_measured_fraction"),
        (lambda: SurfaceRefinementConfig(min_frame_score=-0.1), "min_frame_score"),
        (lambda: ViewSampling(patch_texels=4), "patch_texels"),
        (lambda: ViewSampling(scale=0.0), "scale"),
        (lambda: ViewSampling(cos_view_min=1.0), "cos_view_min"),
        (lambda: ViewSampling(roles=("thermal",)), "roles"),
        (lambda: ViewSampling(resolution=8), "resolution"),
        (lambda: ViewSampling(occlusion_tolerance_mm=-1.0), "occlusion_tolerance_mm"),
    ],
)
def test_bad_options_name_the_field(make, field):
    with pytest.raises(ValueError, match=field):
        make()


def test_the_sampling_is_finer_than_the_atlas_unless_set():
    assert ViewSampling().texture_size(512) == 768 and ViewSampling().texture_size(None) == 768
    assert ViewSampling(scale=1.0).texture_size(255) == 256  # even
    assert ViewSampling(resolution=300).texture_size(512) == 300


def test_offsets_are_symmetric_steps():
    offsets = SurfaceRefinementConfig(search_mm=0.3, step_mm=0.1).offsets
    np.testing.assert_allclose(offsets, [-0.3, -0.2, -0.1, 0.0, 0.1, 0.2, 0.3])
    assert SurfaceRefinementConfig().to_json()["sampling"]["roles"] == ["polarimetric", "stereo"]


def test_bad_frames_and_poses_are_refused(truth):
    store, mesh, _ = truth
    with pytest.raises(ValueError, match="frame_poses"):
        refine_surface(store, mesh, {}, resolution=64)
    with pytest.raises(ValueError, match="no frame 99"):
        refine_surface(store, mesh, {99: np.eye(4)}, resolution=64)
    skewed = np.eye(4)
    skewed[0, 1] = 0.5
    with pytest.raises(ValueError, match=r"frame_poses\[0\]"):
        refine_surface(store, mesh, {0: skewed}, resolution=64)


def _wrong(pose: np.ndarray, degrees: float, shift_mm: float) -> np.ndarray:
    """``pose`` turned by ``degrees`` about the rig's vertical axis through the model's origin and shifted
    sideways by ``shift_mm``."""
    wrong = pose.copy()
    wrong[:3, :3] = rotation_from_euler(np.deg2rad(degrees)) @ pose[:3, :3]
    wrong[0, 3] += shift_mm
    return wrong


@pytest.mark.slow
def test_a_frame_with_a_wildly_wrong_pose_is_flagged_and_not_used(truth):
    store, mesh, poses = truth
    bad = sorted(poses)[1]
    grid = TexelGrid.from_raster(rasterize_uv(mesh, 128))
    # The tiny preset's frames hardly resolve the skin's texture, so the views of even a 20 mm-wrong pose
    # still correlate through the shading (its score is ~0.6 of the others', at the demo's resolution
    # far less): the threshold is raised here to test the mechanism.
    config = SurfaceRefinementConfig(min_frame_score=0.85)
    wrong = {**poses, bad: _wrong(poses[bad], 10.0, 20.0)}
    flagged = photo_consistency_volume(store, mesh, wrong, grid, config)
    assert flagged.flagged_frames == (bad,), flagged.frame_scores
    good = [score for frame, score in flagged.frame_scores.items() if frame != bad]
    assert flagged.frame_scores[bad] < 0.85 * min(good)
    without = photo_consistency_volume(
        store, mesh, {f: p for f, p in poses.items() if f != bad}, grid, config
    )
    assert without.flagged_frames == ()
    np.testing.assert_array_equal(flagged.views, without.views)
    np.testing.assert_allclose(flagged.volume.sum(axis=0), without.volume.sum(axis=0), atol=1e-4)
