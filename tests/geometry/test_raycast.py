"""polarface.geometry.raycast: Embree first hits against analytic spheres, shadow rays, errors."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from polarface.geometry import PinholeCamera, RayCaster, TriangleMesh, embree_available

RADIUS = 50.0


@pytest.fixture(scope="module")
def sphere() -> TriangleMesh:
    ico = trimesh.creation.icosphere(subdivisions=5, radius=RADIUS)
    uv = np.zeros((len(ico.vertices), 2))
    return TriangleMesh.from_arrays(ico.vertices, ico.faces, uv)


@pytest.fixture(scope="module")
def caster(sphere) -> RayCaster:
    return RayCaster(sphere)


def test_embree_backend_is_used(caster):
    assert embree_available()
    assert type(caster._scene.scene).__module__ == "embreex.rtcore_scene"


def test_camera_rays_hit_sphere_analytically(sphere, caster):
    cam = PinholeCamera.look_at([0, 0, 400.0], [0, 0, 0], width=96, height=80, fov_y=np.radians(20))
    origins, directions = cam.pixel_rays()
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    hits = caster.first_hits(origins, directions)
    # analytic ray-sphere intersection
    b = np.einsum("rc,rc->r", origins, directions)
    c = np.einsum("rc,rc->r", origins, origins) - RADIUS**2
    disc = b * b - c
    analytic_hit = disc > 0
    # rays grazing the silhouette may differ between the polyhedron and the sphere; the distance error
    # of a facet (sag ~ 0.012 mm) grows as 1 / cos(incidence), so compare where cos(incidence) > 0.3
    cos_incidence = np.sqrt(np.maximum(disc, 0)) / RADIUS
    grazing = cos_incidence < 0.06
    assert np.array_equal(hits.hit[~grazing], analytic_hit[~grazing])
    both = hits.hit & analytic_hit & (cos_incidence > 0.3)
    t_true = -b[both] - np.sqrt(disc[both])
    # a subdivision-5 icosphere deviates from the sphere by at most r (1 - cos(edge/2r)) ~ 0.03 mm
    assert np.abs(hits.distance[both] - t_true).max() < 0.06
    normal_true = (origins[both] + t_true[:, None] * directions[both]) / RADIUS
    shading = hits.shading_normal(sphere)[both]
    angle = np.degrees(np.arccos(np.clip(np.einsum("rc,rc->r", shading, normal_true), -1, 1)))
    assert angle.max() < 0.5
    face_angle = np.degrees(
        np.arccos(np.clip(np.einsum("rc,rc->r", hits.geometric_normal[both], normal_true), -1, 1))
    )
    assert face_angle.max() < 2.5
    # barycentrics reproduce the point, which lies on the triangle's plane
    corners = sphere.vertices[sphere.faces[hits.face_id[both]]]
    np.testing.assert_allclose(np.einsum("rk,rkc->rc", hits.barycentric[both], corners), hits.point[both])
    assert np.all(hits.barycentric[both] >= 0) and np.allclose(hits.barycentric[both].sum(1), 1)
    # misses
    assert np.all(hits.face_id[~hits.hit] == -1) and np.all(np.isinf(hits.distance[~hits.hit]))
    assert np.isnan(hits.point[~hits.hit]).all()


def test_from_inside_and_occlusion_distance(caster):
    origins = np.zeros((3, 3))
    directions = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]])
    hits = caster.first_hits(origins, directions)
    np.testing.assert_allclose(hits.distance, RADIUS, atol=0.06)
    blocked = caster.occluded(origins, directions, np.array([RADIUS - 1.0, RADIUS + 1.0, np.inf]))
    assert blocked.tolist() == [False, True, True]


def test_shadow_rays_self_intersection_and_blocking(sphere, caster):
    light = np.array([[0.0, 0.0, 1000.0]])
    points = sphere.vertices
    normals = sphere.normals
    lit = caster.shadow_rays(points, normals, light)
    assert lit.shape == (len(points), 1)
    # the light at 1 m sees the cap z > r^2 / 1000 = 2.5 mm (terminator of a point light)
    cos_light = np.einsum(
        "nc,nc->n", normals, (light - points) / np.linalg.norm(light - points, axis=1)[:, None]
    )
    facing = cos_light > 0.02
    back = cos_light < -0.02
    assert lit[facing, 0].all()  # no self-shadowing acne
    assert not lit[back, 0].any()
    # a light inside the sphere: every surface point sees it (segments stay inside)
    inside = caster.shadow_rays(points[:50], normals[:50], np.zeros((1, 3)))
    assert inside.all()
    # pairwise=False pairs point r with light r
    lights = np.tile([[0.0, 0.0, 1000.0]], (len(points), 1))
    paired = caster.shadow_rays(points, normals, lights, pairwise=False)
    np.testing.assert_array_equal(paired, lit[:, 0])


def test_occluder_between_plane_and_light():
    ground = trimesh.creation.box(extents=(100, 100, 1)).apply_translation((0, 0, -0.5))
    blocker = trimesh.creation.box(extents=(10, 10, 1)).apply_translation((0, 0, 20))
    scene = trimesh.util.concatenate([ground, blocker])
    mesh = TriangleMesh.from_arrays(scene.vertices, scene.faces, np.zeros((len(scene.vertices), 2)))
    rc = RayCaster(mesh)
    points = np.array([[0.0, 0, 0], [30.0, 0, 0]])
    normals = np.tile([0.0, 0, 1], (2, 1))
    lit = rc.shadow_rays(points, normals, np.array([[0.0, 0, 100.0], [0.0, 0, 10.0]]), pairwise=True)
    assert lit.tolist() == [[False, True], [True, True]]


def test_errors(caster):
    with pytest.raises(ValueError, match="origins"):
        caster.first_hits(np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="directions"):
        caster.first_hits(np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="unit"):
        caster.first_hits(np.zeros((1, 3)), np.array([[0, 0, 2.0]]))
    with pytest.raises(ValueError, match="finite"):
        caster.first_hits(np.full((1, 3), np.nan), np.array([[0, 0, 1.0]]))
    with pytest.raises(ValueError, match="max_distance"):
        caster.occluded(np.zeros((1, 3)), np.array([[0, 0, 1.0]]), -1.0)
    with pytest.raises(ValueError, match="pairwise"):
        caster.shadow_rays(np.zeros((2, 3)), np.tile([0, 0, 1.0], (2, 1)), np.zeros((3, 3)), pairwise=False)
    with pytest.raises(ValueError, match="offset"):
        RayCaster(caster.mesh, offset=0.0)
    assert caster.first_hits(np.zeros((0, 3)), np.zeros((0, 3))).hit.shape == (0,)


def test_missing_embree_fails_loudly(monkeypatch, sphere):
    import builtins

    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name.startswith("embreex"):
            raise ImportError("no embreex")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    with pytest.raises(ImportError, match="embreex"):
        RayCaster(sphere)
