"""polarface.geometry.atlas: cylindrical atlas on a cylinder (reference UVs) and on the bundled head
(no two triangles share a texel on the face, texels map back to the surface)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from polarface.geometry import TriangleMesh, head_placement, load_head_asset, rasterize_uv
from polarface.geometry.atlas import CylindricalAtlasConfig, cylindrical_atlas

UP = np.array([0.0, -1.0, 0.0])
FRONT = np.array([0.0, 0.0, -1.0])
CENTRE = np.array([0.0, 0.0, 1000.0])


def _cylinder(radius=80.0, height=200.0, segments=64, rings=21, centre=CENTRE):
    """Closed-around open cylinder about the rig's up axis, CCW from outside; angle 0 faces -z."""
    theta = -math.pi + (np.arange(segments) + 0.5) * 2 * math.pi / segments
    h = np.linspace(-height / 2, height / 2, rings)
    tt, hh = np.meshgrid(theta, h)  # (rings, segments)
    # theta measured from front (-z) towards +x around the up axis (-y)
    verts = np.stack([radius * np.sin(tt), -hh, -radius * np.cos(tt)], axis=-1).reshape(-1, 3) + centre
    faces = []
    for i in range(rings - 1):
        for j in range(segments):
            a, b = i * segments + j, i * segments + (j + 1) % segments
            c, d = a + segments, b + segments
            faces += [[a, b, d], [a, d, c]]
    faces = np.asarray(faces)
    mesh = TriangleMesh.from_arrays(verts, faces, np.zeros((len(verts), 2)))
    return mesh, tt.reshape(-1), hh.reshape(-1)


def _strict_coverage(uv, faces, size):
    """Per-texel count of triangles containing the texel centre strictly (independent of the module)."""
    count = np.zeros((size, size), dtype=np.int32)
    px = uv[:, 0] * size - 0.5
    py = (1.0 - uv[:, 1]) * size - 0.5
    for tri in faces:
        x, y = px[tri], py[tri]
        cols = np.arange(max(int(np.ceil(x.min())), 0), min(int(np.floor(x.max())), size - 1) + 1)
        rows = np.arange(max(int(np.ceil(y.min())), 0), min(int(np.floor(y.max())), size - 1) + 1)
        if cols.size == 0 or rows.size == 0:
            continue
        cc, rr = np.meshgrid(cols, rows)
        edges = [
            (x[(k + 1) % 3] - x[k]) * (rr - y[k]) - (y[(k + 1) % 3] - y[k]) * (cc - x[k]) for k in range(3)
        ]
        inside = np.all([e > 1e-7 for e in edges], axis=0) | np.all([e < -1e-7 for e in edges], axis=0)
        count[rr[inside], cc[inside]] += 1
    return count


def test_cylinder_u_follows_angle_v_height_seam_at_back():
    mesh, theta, height = _cylinder()
    config = CylindricalAtlasConfig(resolution=256, padding_texels=3)
    atlas = cylindrical_atlas(mesh, UP, CENTRE, FRONT, config)
    # the seam column (one quad per ring band) is the only removal
    assert atlas.removed_faces == atlas.removed_seam_faces == 2 * 20
    seam_centroids = mesh.vertices[mesh.faces].mean(axis=1)[
        np.setdiff1d(np.arange(mesh.face_count), atlas.source_face)
    ]
    assert (seam_centroids[:, 2] > 1070).all() and (np.abs(seam_centroids[:, 0]) < 5).all()
    # reference UVs: equal mm per texel, u spans the angle range, v centred
    avail = 256 - 6
    t_lo, t_hi = theta.min(), theta.max()
    mm = (t_hi - t_lo) * 80.0 / avail
    u_ref = (3 + (theta - t_lo) / (t_hi - t_lo) * avail) / 256
    v_ref = (3 + 0.5 * (avail - 200.0 / mm) + (height + 100.0) / mm) / 256
    src = atlas.source_vertex
    np.testing.assert_allclose(atlas.mesh.uv[:, 0], u_ref[src], atol=1e-9)
    np.testing.assert_allclose(atlas.mesh.uv[:, 1], v_ref[src], atol=1e-9)
    np.testing.assert_allclose(atlas.reference_radius_mm, 80.0, rtol=1e-9)
    # orientation: front at u = 0.5, +x side to the right, top of the cylinder (up) at large v
    front = np.argmin(np.abs(theta[src]) + np.abs(height[src]))
    assert abs(atlas.mesh.uv[front, 0] - 0.5) < 0.01
    right = atlas.mesh.vertices[:, 0] > 40
    assert (atlas.mesh.uv[right, 0] > 0.5).all()
    # faces stay CCW with positive UV area; texel size (square texels at radius 80 mm)
    t = atlas.mesh.uv[atlas.mesh.faces]
    area = (t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1]) - (t[:, 2, 0] - t[:, 0, 0]) * (
        t[:, 1, 1] - t[:, 0, 1]
    )
    assert (area > 0).all()
    chord = 2 * math.sin(math.pi / 64) / (2 * math.pi / 64)  # flat facets are shorter than the arc
    assert atlas.texel_size_mm["median_v"] == pytest.approx(mm, rel=1e-6)
    assert atlas.texel_size_mm["median_u"] == pytest.approx(mm * chord, rel=1e-6)
    summary = atlas.to_json()
    assert summary["axis_direction"] == pytest.approx(list(UP)) and summary["removed_faces"] == 40


def test_cylinder_fill_mode_and_hidden_inner_sheet():
    outer, _, _ = _cylinder(segments=48, rings=11)
    inner, _, _ = _cylinder(radius=60.0, height=60.0, segments=48, rings=4)
    keep = inner.vertices[inner.faces].mean(axis=1)[:, 2] < 960  # a front patch behind the outer wall
    vertices = np.concatenate([outer.vertices, inner.vertices])
    faces = np.concatenate([outer.faces, inner.faces[keep] + outer.vertex_count])
    mesh = TriangleMesh.from_arrays(vertices, faces, np.zeros((len(vertices), 2)))
    config = CylindricalAtlasConfig(resolution=128, padding_texels=0, equal_texel_size=False)
    atlas = cylindrical_atlas(mesh, UP, CENTRE, FRONT, config)
    assert atlas.removed_hidden_faces == int(keep.sum())  # the inner sheet loses to the outer wall
    assert (atlas.source_face < outer.face_count).all()
    assert atlas.mesh.uv.min(axis=0) == pytest.approx([0, 0]) and atlas.mesh.uv.max(axis=0) == pytest.approx(
        [1, 1]
    )


@pytest.fixture(scope="module")
def head_rig():
    asset = load_head_asset(texture_resolution=64)
    mesh = asset.mesh.transformed(head_placement())  # rig frame: y down, face towards -z
    return mesh, asset.landmarks


@pytest.mark.parametrize("resolution", [128, 256])
def test_head_atlas_bijective_on_face(head_rig, resolution):
    mesh, landmarks = head_rig
    config = CylindricalAtlasConfig(resolution=resolution)
    atlas = cylindrical_atlas(mesh, UP, None, FRONT, config)
    out = atlas.mesh
    assert out.uv.min() >= 0 and out.uv.max() <= 1
    t = out.uv[out.faces]
    area = (t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1]) - (t[:, 2, 0] - t[:, 0, 0]) * (
        t[:, 1, 1] - t[:, 0, 1]
    )
    assert (area > 0).all()
    assert (_strict_coverage(out.uv, out.faces, resolution) <= 1).all()
    # the face (chin to forehead, +-60 deg) is covered and its texels map back to the surface
    raster = rasterize_uv(out, resolution)
    c = atlas.axis_point
    d = raster.position.astype(np.float64) - c
    theta = np.degrees(np.arctan2(d[..., 0], -d[..., 2]))
    h = -d[..., 1]
    chin = -(mesh.vertices[landmarks["chin"], 1] - c[1])
    forehead = -(mesh.vertices[landmarks["forehead"], 1] - c[1])
    face = raster.mask & (np.abs(theta) <= 60) & (h >= chin) & (h <= forehead)
    assert face.sum() > 0.01 * resolution**2
    # cylindrical coordinates of each face texel's 3D position give back its own texel (<= 0.5 texel)
    (t_lo, t_hi), (h_lo, h_hi) = atlas.angle_range_rad, atlas.height_range_mm
    mm = max((t_hi - t_lo) * atlas.reference_radius_mm, h_hi - h_lo) / (
        resolution - 2 * config.padding_texels
    )
    rows, cols = np.nonzero(face)
    col_back = (out.uv[:, 0].min() * resolution - 0.5) + (
        np.radians(theta[face]) - t_lo
    ) * atlas.reference_radius_mm / mm
    row_back = (1 - out.uv[:, 1].min()) * resolution - 0.5 - (h[face] - h_lo) / mm
    assert np.abs(col_back - cols).max() < 0.5 and np.abs(row_back - rows).max() < 0.5
    # texel positions lie on the input surface (unsigned distance, Open3D)
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh.vertices.astype(np.float32), mesh.faces.astype(np.uint32))
    dist = scene.compute_distance(o3d.core.Tensor(raster.position[face])).numpy()
    assert dist.max() < 2e-3
    # the summary's texel size agrees with the raster's over the face
    sizes = np.sqrt(raster.texel_size_u * raster.texel_size_v)[raster.mask & (np.abs(theta) <= 60)]
    assert atlas.texel_size_mm["median"] == pytest.approx(np.median(sizes), rel=0.05)


def test_head_atlas_removes_no_visible_face_surface(head_rig):
    from polarface.geometry import RayCaster

    mesh, landmarks = head_rig
    atlas = cylindrical_atlas(mesh, UP, None, FRONT, CylindricalAtlasConfig(resolution=256))
    c = atlas.axis_point
    band = tuple(-(mesh.vertices[landmarks[k], 1] - c[1]) for k in ("chin", "forehead"))
    removed = np.setdiff1d(np.arange(mesh.face_count), atlas.source_face)
    centroids = mesh.vertices[mesh.faces[removed]].mean(axis=1)
    d = centroids - c
    angle, height = np.arctan2(d[:, 0], -d[:, 2]), -d[:, 1]
    in_face = (np.abs(angle) <= math.radians(60)) & (height >= band[0]) & (height <= band[1])
    removed, centroids = removed[in_face], centroids[in_face]
    assert removed.size > 100  # eye sockets, mouth interior, nostrils
    dirs = centroids / np.linalg.norm(centroids, axis=1, keepdims=True)  # seen from a camera at the origin
    visible = RayCaster(mesh).first_hits(np.zeros_like(dirs), dirs).face_id == removed
    assert mesh.face_areas()[removed[visible]].sum() < 20.0  # mm^2 (of ~35 000 visible)
    # equal mm per texel: square texels on the face proper (chin to forehead)
    face_only = cylindrical_atlas(
        mesh, UP, c, FRONT, CylindricalAtlasConfig(resolution=256, face_height_mm=band)
    )
    assert 0.9 < face_only.texel_size_mm["median_anisotropy"] < 1.1
    assert face_only.texel_size_mm["p5"] < face_only.texel_size_mm["median"] < face_only.texel_size_mm["p95"]


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"axis_direction": (0, 0, 0)}, "axis_direction"),
        ({"axis_direction": (0, np.nan, 1)}, "axis_direction"),
        ({"front_direction": (0, 2, 0)}, "front_direction"),
        ({"front_direction": (0, 0)}, "front_direction"),
        ({"axis_point": (0, np.inf, 0)}, "axis_point"),
        ({"config": "fast"}, "config"),
    ],
)
def test_atlas_bad_arguments(kwargs, name):
    mesh, _, _ = _cylinder(segments=8, rings=3)
    with pytest.raises(ValueError, match=name):
        cylindrical_atlas(mesh, **kwargs)


def test_atlas_bad_config_and_mesh():
    with pytest.raises(ValueError, match="resolution"):
        CylindricalAtlasConfig(resolution=4)
    with pytest.raises(ValueError, match="padding_texels"):
        CylindricalAtlasConfig(resolution=16, padding_texels=7)
    with pytest.raises(ValueError, match="face_half_angle_deg"):
        CylindricalAtlasConfig(face_half_angle_deg=0)
    with pytest.raises(ValueError, match="face_height_mm"):
        CylindricalAtlasConfig(face_height_mm=(5, -5))
    with pytest.raises(ValueError, match="mesh"):
        cylindrical_atlas(np.zeros((3, 3)))
    # a mesh facing the axis everywhere (normals inwards) leaves nothing
    mesh, _, _ = _cylinder(segments=8, rings=3)
    inward = TriangleMesh.from_arrays(mesh.vertices, mesh.faces[:, ::-1], mesh.uv)
    with pytest.raises(ValueError, match="mesh"):
        cylindrical_atlas(inward, UP, CENTRE, FRONT)
