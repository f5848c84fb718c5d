"""polarface.geometry.raycast kernels: the numba shadow-ray set-up and first-hit geometry give the bits of
the numpy formulation; indexed shadow rays; the value checks skipped inside ``trusted_inputs``."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from polarface._validation import trusted_inputs
from polarface.geometry import RayCaster, TriangleMesh
from polarface.geometry.raycast import _segment_rays

OFFSET = 1e-3


@pytest.fixture(scope="module")
def bumpy() -> RayCaster:
    """A displaced icosphere (radius ~50 mm, self-shadowing bumps) about an off-origin centre."""
    ico = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    direction = ico.vertices / np.linalg.norm(ico.vertices, axis=1, keepdims=True)
    bumps = 1.0 + 0.15 * np.sin(5 * direction[:, 0]) * np.cos(4 * direction[:, 1])
    vertices = direction * 50.0 * bumps[:, None] + np.array([10.0, -20.0, 700.0])
    mesh = TriangleMesh.from_arrays(vertices, ico.faces, np.zeros((len(vertices), 2)))
    return RayCaster(mesh, offset=OFFSET)


def numpy_segments(points, normals, lights, origin, scale):
    """The numpy formulation of the shadow segments: Embree's float32 rays and the float64 lengths."""
    count = len(lights)
    p, n = np.repeat(points, count, axis=0), np.repeat(normals, count, axis=0)
    target = np.tile(lights, (len(points), 1))
    side = np.sign(np.einsum("rc,rc->r", target - p, n))
    side[side == 0] = 1.0
    start = p + (OFFSET * side)[:, None] * n
    segment = target - start
    length = np.linalg.norm(segment, axis=1)
    direction = np.divide(segment, length[:, None], out=np.tile([0.0, 0.0, 1.0], (len(p), 1)),
                          where=(length > 0)[:, None])
    limit = np.maximum(length - 2.0 * OFFSET, 0.0)
    return ((start - origin) * scale).astype(np.float32), direction.astype(np.float32), limit


def surface_points(caster: RayCaster, count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    mesh = caster.mesh
    face = rng.integers(0, len(mesh.faces), count)
    weights = rng.dirichlet(np.ones(3), count)
    points = np.einsum("rk,rkc->rc", weights, mesh.vertices[mesh.faces[face]])
    return points, mesh.face_normals()[face]


@pytest.mark.parametrize("scale", [1.0, 0.37])
def test_segment_kernel_gives_the_numpy_bits(scale):
    rng = np.random.default_rng(3)
    points = rng.normal(size=(4000, 3)) * 100 + np.array([5.0, -30.0, 900.0])
    normals = rng.normal(size=(4000, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    lights = rng.normal(size=(6, 3)) * 500
    lights[0] = points[7]  # a zero-length segment: direction +z, limit 0
    origin = points.min(axis=0) - 3.0
    count = len(points) * len(lights)
    origins32, directions32 = np.empty((count, 3), np.float32), np.empty((count, 3), np.float32)
    limits = np.empty(count)
    unused = np.zeros(0, np.int64)
    _segment_rays(points, normals, lights, unused, unused, True, OFFSET, origin, scale, origins32,
                  directions32, limits)
    expected = numpy_segments(points, normals, lights, origin, scale)
    for got, want in zip((origins32, directions32, limits), expected, strict=True):
        assert got.tobytes() == want.tobytes()


def test_shadow_rays_equal_occlusion_of_the_numpy_rays(bumpy):
    points, normals = surface_points(bumpy, 3000)
    lights = np.array([[0.0, 0.0, 0.0], [400.0, -300.0, 500.0], [-350.0, 200.0, 650.0], [0.0, 0.0, 1400.0]])
    lit = bumpy.shadow_rays(points, normals, lights)
    wrap = bumpy._scene
    origins32, directions32, limit = numpy_segments(points, normals, lights, wrap.origin, wrap.scale)
    answer = wrap.scene.run(origins32, directions32, dists=np.minimum(limit, 1e30).astype(np.float32),
                            query="OCCLUDED")
    expected = ~((np.asarray(answer) != -1) & (limit > 0))
    assert 0.2 < lit.mean() < 0.9  # bumps and the back side shadow some pairs
    np.testing.assert_array_equal(lit.reshape(-1), expected)
    paired = bumpy.shadow_rays(points, normals, lights[np.arange(len(points)) % 4], pairwise=False)
    np.testing.assert_array_equal(paired, lit[np.arange(len(points)), np.arange(len(points)) % 4])


def test_indexed_shadow_rays(bumpy):
    points, normals = surface_points(bumpy, 500, seed=1)
    lights = np.array([[400.0, -300.0, 500.0], [-350.0, 200.0, 650.0], [0.0, 0.0, 1400.0]])
    every = bumpy.shadow_rays(points, normals, lights)
    rng = np.random.default_rng(2)
    rows, modules = rng.integers(0, 500, 900), rng.integers(0, 3, 900)
    np.testing.assert_array_equal(bumpy.shadow_rays_indexed(points, normals, lights, rows, modules),
                                  every[rows, modules])
    np.testing.assert_array_equal(bumpy.shadow_rays_indexed(points, normals, lights, rows, 2), every[rows, 2])
    assert bumpy.shadow_rays_indexed(points, normals, lights, np.zeros(0, np.int64), 0).shape == (0,)
    with pytest.raises(ValueError, match="'rows'"):
        bumpy.shadow_rays_indexed(points, normals, lights, rows.astype(float), 0)
    with pytest.raises(ValueError, match="'rows'"):
        bumpy.shadow_rays_indexed(points, normals, lights, np.array([0, 500]), 0)
    with pytest.raises(ValueError, match="'modules'"):
        bumpy.shadow_rays_indexed(points, normals, lights, rows, modules[:5])
    with pytest.raises(ValueError, match="'modules'"):
        bumpy.shadow_rays_indexed(points, normals, lights, rows, 3)
    with pytest.raises(ValueError, match="finite"):
        bumpy.shadow_rays_indexed(np.full_like(points, np.nan), normals, lights, rows, 0)


def test_first_hits_give_the_numpy_bits(bumpy):
    rng = np.random.default_rng(4)
    origins = np.tile([10.0, -20.0, 0.0], (5000, 1)) + rng.normal(size=(5000, 3))
    targets = np.array([10.0, -20.0, 700.0]) + rng.normal(size=(5000, 3)) * 40  # some miss
    directions = targets - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    hits = bumpy.first_hits(origins, directions)
    assert 0.2 < hits.hit.mean() < 1.0
    wrap = bumpy._scene
    result = wrap.scene.run(((origins - wrap.origin) * wrap.scale).astype(np.float32),
                            directions.astype(np.float32), output=1)
    face = np.asarray(result["primID"], np.int64)
    hit = face >= 0
    u, v = np.asarray(result["u"], np.float64), np.asarray(result["v"], np.float64)
    bary = np.clip(np.stack([1.0 - u - v, u, v], axis=1), 0.0, 1.0)
    bary /= np.maximum(bary.sum(axis=1, keepdims=True), 1e-300)
    bary[~hit] = 0.0
    tri = bumpy.mesh.faces[np.where(hit, face, 0)]
    vertices = bumpy.mesh.vertices
    point = bary[:, 0:1] * vertices[tri[:, 0]]
    point += bary[:, 1:2] * vertices[tri[:, 1]]
    point += bary[:, 2:3] * vertices[tri[:, 2]]
    distance = np.einsum("rc,rc->r", point - origins, directions)
    distance[~hit], point[~hit] = np.inf, np.nan
    np.testing.assert_array_equal(hits.face_id, face)
    for got, want in ((hits.barycentric, bary), (hits.point, point), (hits.distance, distance)):
        assert got.tobytes() == want.tobytes()


def test_trusted_inputs_skip_the_value_checks_only(bumpy):
    origins, long = np.zeros((1, 3)), np.array([[0.0, 0.0, 2.0]])
    with pytest.raises(ValueError, match="unit"):
        bumpy.first_hits(origins, long)
    with trusted_inputs():
        bumpy.first_hits(origins, long)  # the unit check is skipped; the shape checks are not
        with pytest.raises(ValueError, match="directions"):
            bumpy.first_hits(origins, np.zeros((2, 3)))
        with pytest.raises(ValueError, match="light_positions"):
            bumpy.shadow_rays(origins, long, np.zeros(3))
