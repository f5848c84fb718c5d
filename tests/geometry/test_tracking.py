"""Mesh tracking by optical flow with anchor frames (polarface.geometry.tracking).

The synthetic scenes are rendered analytically: a plane at z = 500 mm carries a smooth random texture
in material coordinates; a frame's in-plane deformation moves the material, and a pixel's intensity is
the texture at the material point its ray meets (the deformation is inverted by fixed-point
iteration). Three cameras 100 mm apart, 600 px focal: 0.83 mm per pixel on the plane.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from polarface.geometry import PinholeCamera, TriangleMesh
from polarface.geometry.tracked_file import load_tracked, save_tracked
from polarface.geometry.tracking import (
    TrackedSequence,
    TrackingConfig,
    TrackingFrame,
    track_mesh,
)

PLANE_Z_MM = 500.0
MM_PER_PX = PLANE_Z_MM / 600.0


def _cameras() -> dict[str, PinholeCamera]:
    target = np.array([0.0, 0.0, PLANE_Z_MM])
    return {
        name: PinholeCamera.look_at(np.array([x, 0.0, 0.0]), target, width=200, height=160, focal=600.0)
        for name, x in (("left", -100.0), ("centre", 0.0), ("right", 100.0))
    }


def _grid_mesh(half_width: float, half_height: float, step: float) -> TriangleMesh:
    xs = np.arange(-half_width, half_width + 1e-9, step)
    ys = np.arange(-half_height, half_height + 1e-9, step)
    gx, gy = np.meshgrid(xs, ys)
    vertices = np.stack([gx, gy, np.full_like(gx, PLANE_Z_MM)], axis=-1).reshape(-1, 3)
    index = np.arange(gx.size).reshape(gx.shape)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, 1:], index[1:, :-1]
    # counter-clockwise seen from the cameras (normal towards -z)
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    uv = np.stack([(gx - gx.min()) / np.ptp(gx), (gy - gy.min()) / np.ptp(gy)], -1).reshape(-1, 2)
    mesh = TriangleMesh.from_arrays(vertices, faces, uv)
    assert mesh.normals[:, 2].max() < -0.99
    return mesh


class _Texture:
    """Smooth random texture on material coordinates (mm): sum of random plane waves, 5-15 mm periods."""

    def __init__(self, seed: int = 0):
        rng = np.random.default_rng(seed)
        angles = rng.uniform(0, np.pi, 40)
        periods = rng.uniform(5.0, 15.0, 40)
        self.k = np.stack([np.cos(angles), np.sin(angles)], -1) * (2 * np.pi / periods)[:, None]
        self.phase = rng.uniform(0, 2 * np.pi, 40)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        return 1.0 + 0.08 * np.cos(points @ self.k.T + self.phase).sum(-1)


def _displacement(points: np.ndarray, amplitude: float) -> np.ndarray:
    """Smooth in-plane displacement (mm) of material points ``(..., 2)`` scaled by ``amplitude``
    (strain at most ~0.04 per mm of amplitude)."""
    s, t = points[..., 0], points[..., 1]
    dx = np.sin(2 * np.pi * s / 150.0 + 0.3) * np.cos(2 * np.pi * t / 160.0)
    dy = 0.6 * np.cos(2 * np.pi * s / 170.0 + 0.5) * np.sin(2 * np.pi * t / 140.0 + 0.4)
    return amplitude * np.stack([dx, dy], -1)


def _render(camera: PinholeCamera, texture: _Texture, amplitude: float, noise: float,
            rng: np.random.Generator) -> np.ndarray:
    origins, directions = camera.pixel_rays()
    world = origins + directions * ((PLANE_Z_MM - origins[..., 2:]) / directions[..., 2:])
    material = world[..., :2].copy()
    for _ in range(30):  # x = s + d(s)  =>  s = x - d(s)
        material = world[..., :2] - _displacement(material, amplitude)
    image = texture(material) + noise * rng.standard_normal(material.shape[:2])
    return image.astype(np.float32)


def _plane_sequence(amplitudes, noise: float = 0.0, seed: int = 0, no_surface: tuple[int, ...] = ()):
    cameras = _cameras()
    texture = _Texture(seed)
    surface = _grid_mesh(120.0, 100.0, 4.0)
    reference = _grid_mesh(30.0, 20.0, 2.0)

    def load(index: int) -> TrackingFrame:
        rng = np.random.default_rng(1000 * seed + index)
        images = {c: _render(cam, texture, amplitudes[index], noise, rng) for c, cam in cameras.items()}
        return TrackingFrame(index, images, None if index in no_surface else surface)

    def truth(index: int) -> np.ndarray:
        rest = reference.vertices
        moved = rest[:, :2] + _displacement(rest[:, :2], amplitudes[index])
        return np.concatenate([moved, rest[:, 2:]], axis=1)

    return reference, cameras, load, truth


def _errors(tracked: TrackedSequence, truth) -> np.ndarray:
    return np.stack([np.linalg.norm(tracked.vertices[i] - truth(f), axis=1)
                     for i, f in enumerate(tracked.frames)])


def test_plane_with_known_smooth_deformation_is_tracked():
    amplitudes = [0.0, 0.6, 1.2, 1.8, 2.4, 3.0]  # mm, up to 3.6 px in the images
    reference, cameras, load, truth = _plane_sequence(amplitudes)
    tracked = track_mesh(reference, cameras, load, range(len(amplitudes)))
    errors = _errors(tracked, truth)
    motion = np.linalg.norm(truth(5) - truth(0), axis=1)
    assert np.median(motion) > 1.0  # the deformation is real
    # 0.1 px on the plane is 0.083 mm: median error below that, 90th percentile below 0.2 px
    assert np.median(errors[1:], axis=1).max() < 0.1 * MM_PER_PX
    assert np.percentile(errors[1:], 90, axis=1).max() < 0.2 * MM_PER_PX
    assert tracked.failed == {}
    assert (tracked.tracked_fraction() > 0.95).all()
    assert tracked.vertices.shape == (6, reference.vertex_count, 3)
    assert tracked.confidence.dtype == np.float32


def test_flows_on_image_crops_track_as_flows_on_whole_images():
    """The default crop margin is the whole of these small images; an 8 px margin (motion up to 3.6 px)
    computes the flows on 18 % of each image and tracks as well as the whole images."""
    amplitudes = [0.0, 1.2, 2.4, 3.0]
    reference, cameras, load, truth = _plane_sequence(amplitudes)
    whole = track_mesh(reference, cameras, load, range(4), TrackingConfig(flow_crop_margin_px=None))
    cropped = track_mesh(reference, cameras, load, range(4), TrackingConfig(flow_crop_margin_px=8.0))
    for tracked in (whole, cropped):
        errors = _errors(tracked, truth)
        assert np.median(errors[1:], axis=1).max() < 0.1 * MM_PER_PX
        assert (tracked.tracked_fraction() > 0.95).all()
    difference = np.linalg.norm(cropped.vertices - whole.vertices, axis=-1)
    assert np.median(difference) < 0.025 * MM_PER_PX  # measured 0.011 px
    assert cropped.anchors == whole.anchors


def test_rays_that_miss_a_hole_in_the_surface_still_track_the_vertices():
    """The frames' surfaces have a hole of 12 mm radius under the middle of the tracked patch (a stereo
    mesh's hole at saturated or specular pixels). The flowed rays that miss it still triangulate the
    vertices (``off_surface_rays``, default): tracked as well as elsewhere; dropping them leaves the
    middle untracked."""
    amplitudes = [0.0, 1.0, 2.0]
    reference, cameras, load, truth = _plane_sequence(amplitudes)
    full = load(0).surface
    centroids = full.vertices[full.faces].mean(axis=1)
    kept = np.linalg.norm(centroids[:, :2], axis=1) > 12.0
    holed = TriangleMesh.from_arrays(full.vertices, full.faces[kept], full.uv)

    def load_holed(index: int) -> TrackingFrame:
        frame = load(index)
        return dataclasses.replace(frame, surface=holed) if index > 0 else frame

    middle = np.linalg.norm(reference.vertices[:, :2], axis=1) < 8.0
    tracked = track_mesh(reference, cameras, load_holed, range(3))
    errors = _errors(tracked, truth)
    assert middle.sum() > 30 and (tracked.confidence[2][middle] > 0).mean() > 0.95
    assert np.median(errors[2][middle]) < 0.1 * MM_PER_PX
    dropped = track_mesh(reference, cameras, load_holed, range(3), TrackingConfig(off_surface_rays=False))
    assert (dropped.confidence[2][middle] > 0).mean() < 0.05


def test_snapping_puts_the_tracked_vertices_on_the_surface():
    """``snap_to_surface``: the tracked vertices are moved to the closest point of the frame's surface (the
    plane, whose depth ``truth`` keeps) before the smoothing, and still follow the deformation."""
    amplitudes = [0.0, 1.0, 2.0]
    reference, cameras, load, truth = _plane_sequence(amplitudes)
    lifted = dataclasses.replace(reference, vertices=reference.vertices + np.array([0.0, 0.0, 0.3]))
    tracked = track_mesh(lifted, cameras, load, range(3), TrackingConfig(snap_to_surface=True))
    seen = tracked.confidence[2] > 0
    assert seen.mean() > 0.9
    # the reference started 0.3 mm off the plane; snapped and smoothed, the tracked vertices lie on it
    assert np.abs(tracked.vertices[2][seen, 2] - truth(2)[seen, 2]).max() < 0.01
    along = np.linalg.norm(tracked.vertices[2][seen, :2] - truth(2)[seen, :2], axis=1)
    assert np.median(along) < 0.1 * MM_PER_PX


def test_anchor_frames_bound_the_drift_of_chaining():
    """The texture moves away and comes back (last frame = first) under per-frame image noise: chaining
    accumulates the flow noise, the anchor scheme tracks the returning frames directly from frame 0."""
    amplitudes = list(2.0 * np.sin(np.pi * np.arange(10) / 9.0))
    reference, cameras, load, truth = _plane_sequence(amplitudes, noise=0.04, seed=3)
    anchored = track_mesh(reference, cameras, load, range(10))
    chained = track_mesh(reference, cameras, load, range(10), TrackingConfig(anchor_similarity=None))
    last_anchored = np.median(_errors(anchored, truth)[-1])
    last_chained = np.median(_errors(chained, truth)[-1])
    assert chained.anchors == (0,)
    assert 9 in anchored.anchors
    assert last_chained > 2.0 * last_anchored
    # the returning frame sees only its own image noise: below 0.05 px on the plane
    assert last_anchored < 0.05 * MM_PER_PX


def test_frame_without_surface_fails_and_tracking_goes_on(tmp_path):
    amplitudes = [0.0, 0.5, 1.0, 1.5]
    reference, cameras, load, truth = _plane_sequence(amplitudes, no_surface=(2,))
    tracked = track_mesh(reference, cameras, load, range(4))
    assert set(tracked.failed) == {2} and "frame 2" in tracked.failed[2]
    assert (tracked.confidence[2] == 0).all()
    np.testing.assert_array_equal(tracked.vertices[2], tracked.vertices[1])
    assert np.median(_errors(tracked, truth)[3]) < 0.1 * MM_PER_PX
    summary = tracked.to_json()
    assert summary["failed"] == {"2": tracked.failed[2]} and summary["tracked_fraction"][2] == 0.0
    path = save_tracked(tmp_path / "tracking.npz", tracked)
    loaded = load_tracked(path)
    np.testing.assert_array_equal(loaded.vertices, tracked.vertices)
    np.testing.assert_array_equal(loaded.confidence, tracked.confidence)
    assert (loaded.frames, loaded.anchors, loaded.failed) == (tracked.frames, tracked.anchors, tracked.failed)


def test_bad_input_is_refused(tmp_path):
    reference, cameras, load, _ = _plane_sequence([0.0, 0.5])
    with pytest.raises(ValueError, match="frames"):
        track_mesh(reference, cameras, load, [])
    with pytest.raises(ValueError, match="cameras"):
        track_mesh(reference, {}, load, [0, 1])
    with pytest.raises(ValueError, match="unknown camera id 'nope'"):
        track_mesh(reference, {"centre": cameras["centre"]}, lambda i: TrackingFrame(
            i, {"nope": np.zeros((160, 200), np.float32)}, None), [0, 1])
    with pytest.raises(ValueError, match=r"camera 'centre' must have shape \(160, 200\)"):
        track_mesh(reference, cameras, lambda i: TrackingFrame(
            i, {"centre": np.zeros((10, 10), np.float32)}, None), [0, 1])
    with pytest.raises(ValueError, match="'images' is empty"):
        track_mesh(reference, cameras, lambda i: TrackingFrame(i, {}, None), [0, 1])
    with pytest.raises(ValueError, match="index 5"):
        track_mesh(reference, cameras, lambda i: dataclasses.replace(load(i), index=5), [0, 1])
    with pytest.raises(ValueError, match="anchor_similarity"):
        TrackingConfig(anchor_similarity=2.0)
    with pytest.raises(FileNotFoundError, match=r"missing\.npz"):
        load_tracked(tmp_path / "missing.npz")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"bad\.npz"):
        load_tracked(tmp_path / "bad.npz")


@pytest.fixture(scope="module")
def tiny_dynamic(tiny_sim):
    """The shared tiny simulation (tests/conftest.py; this module reads its dynamic sequence)."""
    return tiny_sim


def test_tiny_head_stays_put_under_changing_skin_colour(tiny_dynamic):
    """The tiny simulator's two dynamic frames have the same (neutral) shape but a different outer
    haemoglobin map and new sensor noise: the tracked head must not move although the images change."""
    from polarface.capture.store import CaptureStore
    from polarface.geometry import load_mesh

    store = CaptureStore.open(tiny_dynamic / "dynamic")
    rig_cameras = {camera.id: camera for camera in store.rig.cameras}
    meshes = [load_mesh(tiny_dynamic / "ground_truth/dynamic/meshes" / f"{i:06d}.ply") for i in (0, 1)]

    def image(index: int, camera_id: str) -> np.ndarray:
        if rig_cameras[camera_id].role == "polarimetric":
            return store.observation("i_sss", index, camera_id).mean(-1)
        raw = store.read_raw(index, camera_id).astype(np.float32)
        return raw.mean(-1) - rig_cameras[camera_id].black_level

    def load(index: int) -> TrackingFrame:
        return TrackingFrame(index, {c: image(index, c) for c in rig_cameras}, meshes[index])

    cameras = {c: camera.pinhole() for c, camera in rig_cameras.items()}
    # the surfaces here are the exact ground truth, so the surface term may be stiffer than the default
    # (tuned for ~0.3 mm noisy stereo surfaces): it fixes the depth of the coarse tiny-preset pixels
    tracked = track_mesh(meshes[0], cameras, load, [0, 1], TrackingConfig(surface_weight=0.1))
    errors = np.linalg.norm(tracked.vertices[1] - meshes[1].vertices, axis=1)
    seen = tracked.confidence[1] > 0
    assert tracked.failed == {} and seen.mean() > 0.3
    # a tenth of a pixel is ~0.1 mm at the tiny preset's resolution; the median must stay below it
    assert np.median(errors[seen]) < 0.05
    # the 90th percentile depends on the noise realisation, which float rounding of the render moves
    # (numpy's Poisson sampler draws a varying number of uniforms per pixel): 0.14-0.20 mm measured on
    # two CPUs and thread counts
    assert np.percentile(errors, 90) < 0.25
    print(f"tiny head: median {np.median(errors[seen]):.4f} mm, p90 {np.percentile(errors, 90):.4f} mm")


def _tiny_expression_tracking(weights, expression_config=None):
    """The tiny simulator head deformed by the expression rig with each of ``weights`` (one frame each,
    neutral first), rendered noise-free in every rig camera and tracked with the true deformed meshes
    as surfaces; returns ``(scene, meshes, tracked)``."""
    from polarface.geometry.deform import ExpressionConfig, ExpressionRig
    from polarface.simulate.pipeline import SimulationConfig, SimulationScene, render_frame

    scene = SimulationScene.build(SimulationConfig(preset="tiny", sequences=("dynamic",), noise=False))
    config = expression_config or ExpressionConfig()
    expressions = ExpressionRig(scene.asset.mesh, scene.asset.landmarks, config)
    meshes = [expressions.deform(np.array(w)).transformed(scene.placement) for w in weights]
    renders = [render_frame(scene, mesh, scene.maps, scene.subsurface) for mesh in meshes]

    def image(frame: int, camera) -> np.ndarray:
        images = renders[frame].views[camera.id].images
        return (2.0 * images["i90"] if camera.role == "polarimetric" else images["s0"]).mean(-1)

    def load(frame: int) -> TrackingFrame:
        return TrackingFrame(frame, {c.id: image(frame, c) for c in scene.rig.cameras}, meshes[frame])

    cameras = {c.id: c.pinhole() for c in scene.rig.cameras}
    frames = list(range(len(weights)))
    return scene, meshes, track_mesh(meshes[0], cameras, load, frames, TrackingConfig(surface_weight=0.1))


def test_tiny_head_smile_is_tracked():
    """A known deformation of the tiny simulator head: neutral, then a half and a full smile (mouth
    corners ~5 mm out, up and back, cheeks raised), rendered noise-free by the simulator in every rig
    camera; the surfaces are the true deformed meshes. The tracked vertices follow the truth."""
    _, meshes, tracked = _tiny_expression_tracking([(0.0, 0.0, 0.0), (0.0, 0.5, 0.0), (0.0, 1.0, 0.0)])
    motion = np.linalg.norm(meshes[2].vertices - meshes[0].vertices, axis=1)
    seen = tracked.confidence[2] > 0
    moving = seen & (motion > 1.0)
    assert tracked.failed == {} and moving.sum() > 50
    errors = np.linalg.norm(tracked.vertices[2] - meshes[2].vertices, axis=1)
    # the tiny preset's pixels are ~1 mm on the face: measured median 0.42 mm (9 % of the 4.75 mm median
    # motion; not tracking at all would leave 100 %), p90 1.05 mm
    print(f"smile: median motion {np.median(motion[moving]):.2f} mm, error median "
          f"{np.median(errors[moving]):.3f} mm, p90 {np.percentile(errors[moving], 90):.3f} mm")
    assert np.median(errors[moving]) < 0.6
    assert np.median(errors[moving]) < 0.15 * np.median(motion[moving])
    assert np.median(errors[seen & ~moving]) < 0.2


def test_tiny_head_jaw_opening_is_tracked_at_the_lips():
    """A known jaw opening of the tiny simulator head, 15 mm at the chin (7.6 degrees), in four equal
    steps, rendered noise-free; the lips (vertices within 15 mm of the mouth's centre that move more
    than 1 mm) are tracked. Issue 50 asks <= 1 mm at the lips; measured 1.07 mm median for a 6.5 mm
    median lip motion (0.42, 0.58, 0.87, 1.07 mm over the four steps: the flowed lip vertices lag the
    motion by ~4 % a step where the simulated jaw stretches the skin between the lips; the demo's
    612 x 512 cameras give 1.11 mm, so it is not the tiny preset's resolution). The bounds hold today's
    accuracy with some margin; without tracking the error would be the motion itself."""
    import math

    from polarface.geometry.deform import ExpressionConfig

    steps = (0.0, 0.25, 0.5, 0.75, 1.0)
    config = ExpressionConfig(jaw_angle=math.radians(7.6))
    scene, meshes, tracked = _tiny_expression_tracking([(0.0, 0.0, w) for w in steps], config)
    mouth = scene.asset.mesh.vertices[scene.asset.landmarks["mouth_center"]]
    near_mouth = np.linalg.norm(scene.asset.mesh.vertices - mouth, axis=1) < 15.0
    motion = np.linalg.norm(meshes[-1].vertices - meshes[0].vertices, axis=1)
    assert tracked.failed == {} and 14.0 < motion.max() < 16.0
    lips = near_mouth & (motion > 1.0)
    assert lips.sum() > 80
    errors = [np.linalg.norm(tracked.vertices[f] - meshes[f].vertices, axis=1)[lips] for f in (2, 4)]
    print(f"jaw: lip motion median {np.median(motion[lips]):.2f} mm; error median half-open "
          f"{np.median(errors[0]):.3f} mm, open {np.median(errors[1]):.3f} mm")
    assert np.median(errors[0]) < 0.8
    assert np.median(errors[1]) < 1.3
    assert np.median(errors[1]) < 0.2 * np.median(motion[lips])
