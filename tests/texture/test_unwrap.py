"""Texture-space unwrapping of a synthetic capture (sphere cap with known maps)."""

from __future__ import annotations

import numpy as np
import pytest

from polarface.capture.store import CaptureStore
from polarface.geometry.camera import PinholeCamera
from polarface.geometry.mesh import TriangleMesh, load_mesh
from polarface.geometry.poses import load_poses
from polarface.geometry.raycast import RayCaster
from polarface.render import render_view_texture
from polarface.simulate.sphere_capture import SphereCaptureConfig, make_sphere_capture
from polarface.texture import UnwrapConfig, UnwrapStore, footprint_sees_surface, unwrap_capture


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("sphere")
    info = make_sphere_capture(root, SphereCaptureConfig(texture_resolution=16, frames=3))
    store = CaptureStore.open(info["capture"])
    mesh = load_mesh(info["ground_truth"] / "mesh_rest.obj")
    poses = load_poses(info["ground_truth"] / "static" / "poses.json")
    return info, store, mesh, poses, root


def test_unwrap_layout_and_observations_match_the_forward_model(capture):
    info, store, mesh, poses, root = capture
    unwrap = unwrap_capture(
        store, mesh, poses, root / "u.zarr", UnwrapConfig(texture_resolution=16, patch=8), progress=False
    )
    assert unwrap.complete and unwrap.resolution == (16, 16)
    assert len(unwrap.views) == 6 and {v.camera_id for v in unwrap.views} == {"pol_upper", "pol_lower"}
    obs, valid, lit = unwrap.read(slice(0, 16), slice(0, 16))
    assert obs.shape == (6, 16, 16, 3, 3) and valid.shape == (6, 16, 16) and lit.shape == (6, 16, 16, 8)
    assert valid.any() and np.isfinite(obs).all() and not valid[:, ~info["mask"]].any()
    assert unwrap.mean_i_sss() > 0
    # the stored observations agree with the forward model of the true maps (demosaicing error only)
    observed, predicted, seen = render_view_texture(unwrap, info["maps"], 0)
    assert seen.sum() > 20
    relative = np.abs(predicted[seen][:, 0] - observed[seen][:, 0]) / observed[seen][:, 0].mean()
    assert np.median(relative) < 0.03
    # reopening gives the same content; the store lists patches with atlas texels only
    again = UnwrapStore.open(root / "u.zarr")
    assert [v.to_dict() for v in again.views] == [v.to_dict() for v in unwrap.views]
    assert all(info["mask"][r, c].any() for r, c in again.patches(8))


def test_unwrap_rejects_bad_input_and_writes_nothing(capture):
    _info, store, mesh, poses, root = capture
    with pytest.raises(ValueError, match="poses"):
        unwrap_capture(store, mesh, poses[:2], root / "bad1.zarr", progress=False)
    assert not (root / "bad1.zarr").exists()
    away = poses.copy()
    away[:, :3, 3] = (0.0, 0.0, -5000.0)  # behind the cameras: nothing is visible
    with pytest.raises(ValueError, match="all-invisible"):
        unwrap_capture(
            store, mesh, away, root / "bad2.zarr", UnwrapConfig(texture_resolution=16), progress=False
        )
    assert not (root / "bad2.zarr").exists() and not (root / "bad2.zarr.partial").exists()


def test_unwrap_resumes_a_partial_store(capture):
    _info, store, mesh, poses, root = capture
    config = UnwrapConfig(texture_resolution=16, patch=8)
    full = unwrap_capture(store, mesh, poses, root / "full.zarr", config, progress=False)
    partial = unwrap_capture(store, mesh, poses, root / "part.zarr", config, progress=False)
    (root / "part.zarr").rename(root / "part.zarr.partial")
    writer = UnwrapStore.open(root / "part.zarr.partial", mode="a")
    writer.root.attrs["done"] = [0, 1]
    writer.root.attrs["complete"] = False
    writer.root["obs"][3] = 0.0
    resumed = unwrap_capture(store, mesh, poses, root / "part.zarr", config, progress=False)
    assert resumed.complete and partial is not None
    np.testing.assert_array_equal(
        resumed.read(slice(0, 16), slice(0, 16))[0], full.read(slice(0, 16), slice(0, 16))[0]
    )


def test_frames_in_threads_give_the_store_of_one_thread(capture, monkeypatch):
    """Frames sampled side by side (unwrap.VIEW_THREADS) write the same arrays and attributes."""
    import polarface.texture.unwrap as unwrap_module

    _info, store, mesh, poses, root = capture
    config = UnwrapConfig(texture_resolution=16, patch=8)
    stores = {}
    for threads in (1, 3):
        monkeypatch.setattr(unwrap_module, "VIEW_THREADS", threads)
        stores[threads] = unwrap_capture(store, mesh, poses, root / f"threads{threads}.zarr", config,
                                         progress=False)
    one, many = stores[1], stores[3]
    for name in ("obs", "valid", "lit"):
        np.testing.assert_array_equal(np.asarray(one.root[name][:]), np.asarray(many.root[name][:]))
    assert dict(one.root.attrs) == dict(many.root.attrs)
    assert list(many.root.attrs["stats"]) == [str(v) for v in range(len(many.views))]  # in view order


@pytest.mark.parametrize(
    "field,value",
    [
        ("texture_resolution", 4),
        ("patch", 2),
        ("cos_view_min", 1.5),
        ("holdout_every", 1),
        ("occlusion_tolerance_mm", 0.0),
        ("footprint_margin_px", -1),
        ("footprint_tolerance_mm", 0.0),
    ],
)
def test_config_errors(field, value):
    with pytest.raises(ValueError, match=field):
        UnwrapConfig(**{field: value})


def test_nan_observations_raise(capture):
    from polarface.geometry.raycast import RayCaster
    from polarface.geometry.uv_raster import rasterize_uv
    from polarface.texture import sample_view, texel_geometry

    _info, store, mesh, poses, _root = capture
    geometry = texel_geometry(rasterize_uv(mesh, 16))
    camera = store.rig.polarimetric_cameras()[0]
    stack = store.stack(0, camera.id).copy()
    stack[:] = np.nan
    world = mesh.transformed(poses[0])
    lights = np.array([light.position_mm for light in store.rig.lights])
    with pytest.raises(ValueError, match="NaN"):
        sample_view(
            geometry,
            world,
            RayCaster(world),
            camera.pinhole(),
            poses[0],
            stack,
            np.zeros(stack.shape[1:3], bool),
            lights,
            UnwrapConfig(texture_resolution=16),
            "frame 0",
        )


def _plane(half_mm: float, z_mm: float) -> TriangleMesh:
    vertices = np.array(
        [
            [-half_mm, -half_mm, z_mm],
            [half_mm, -half_mm, z_mm],
            [half_mm, half_mm, z_mm],
            [-half_mm, half_mm, z_mm],
        ]
    )
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    return TriangleMesh.from_arrays(vertices, faces, uv=(vertices[:, :2] / (2 * half_mm) + 0.5))


def test_footprint_rejects_mixed_pixels_at_edges_and_occluders():
    """A 100 mm plane seen from 1 m (1 px ~ 1 mm): samples whose footprint crosses the plane's edge or
    the edge of a 20 mm occluder 100 mm in front are rejected; interior samples and inf tolerance pass."""
    plane = _plane(50.0, 0.0)
    occluder = _plane(10.0, 100.0)
    scene = TriangleMesh.from_arrays(
        np.concatenate([plane.vertices, occluder.vertices]),
        np.concatenate([plane.faces, occluder.faces + 4]),
        uv=np.concatenate([plane.uv, occluder.uv]),
    )
    camera = PinholeCamera.look_at([0.0, 0.0, 1000.0], [0.0, 0.0, 0.0], width=201, height=201, focal=1000.0)
    caster = RayCaster(scene)
    points = np.array(
        [[30.0, 30.0, 0.0], [49.8, 0.0, 0.0], [30.0, -49.5, 0.0], [0.0, 11.4, 0.0], [25.0, 0.0, 0.0]]
    )
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    pixels, _ = camera.project(points)
    ok = footprint_sees_surface(caster, camera, points, normals, pixels, 1, 3.0)
    assert ok.tolist() == [True, False, False, False, True]
    assert footprint_sees_surface(caster, camera, points, normals, pixels, 1, np.inf).all()
    # margin 0 checks only the 2 x 2 bilinear cell: a sample 2.4 px from the occluder's edge passes
    far = np.array([[0.0, 12.4, 0.0]])
    assert footprint_sees_surface(caster, camera, far, normals[:1], camera.project(far)[0], 0, 3.0).all()
    assert not footprint_sees_surface(caster, camera, far, normals[:1], camera.project(far)[0], 2, 3.0).any()
    assert footprint_sees_surface(caster, camera, points[:0], normals[:0], pixels[:0], 1, 3.0).shape == (0,)


def test_footprint_pixel_table_equals_numpy_unique():
    """The footprints' pixels and each entry's position among them, from the per-pixel table, are
    ``np.unique(..., return_inverse=True)``'s: overlapping footprints, pixels 0 and the last, one entry."""
    from polarface.texture.footprint import _unique_pixels

    rng = np.random.default_rng(3)
    width, height = 37, 23
    base = rng.integers(0, width * height - 10, size=(400, 1))
    cases = [base + np.arange(9)[None], np.array([[0, width * height - 1, 0]]), np.array([[5]])]
    for flat in cases:
        unique, inverse = _unique_pixels(flat, width * height)
        expected_unique, expected_inverse = np.unique(flat, return_inverse=True)
        assert np.array_equal(unique, expected_unique)
        assert np.array_equal(inverse, expected_inverse.reshape(flat.shape))
        assert np.array_equal(unique[inverse], flat)


def test_footprint_test_removes_boundary_samples_of_the_sphere_cap(capture):
    """On the sphere-cap capture the test drops some samples next to the cap's silhouette edge only."""
    _info, store, mesh, poses, root = capture
    counts = {}
    for name, tolerance in (("checked", 3.0), ("unchecked", np.inf)):
        config = UnwrapConfig(texture_resolution=16, patch=8, footprint_tolerance_mm=tolerance)
        unwrap = unwrap_capture(store, mesh, poses, root / f"fp_{name}.zarr", config, progress=False)
        counts[name] = unwrap.visible_count()
    assert (counts["checked"] <= counts["unchecked"]).all()
    assert counts["checked"].sum() < counts["unchecked"].sum()


def test_excluded_frames_are_left_out(capture):
    _info, store, mesh, poses, root = capture
    config = UnwrapConfig(texture_resolution=16, patch=8, excluded_frames=(1,))
    unwrap = unwrap_capture(store, mesh, poses, root / "excluded.zarr", config, progress=False)
    assert sorted({v.frame for v in unwrap.views}) == [0, 2] and len(unwrap.views) == 4
    with pytest.raises(ValueError, match="excluded_frames"):
        unwrap_capture(store, mesh, poses, root / "none.zarr",
                       UnwrapConfig(texture_resolution=16, excluded_frames=(0, 1, 2)), progress=False)
    assert not (root / "none.zarr").exists()
