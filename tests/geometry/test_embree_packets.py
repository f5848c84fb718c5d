"""polarface.geometry.embree_packets: coherent packets of shadow rays against embreex's one-ray queries."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from polarface.geometry import RayCaster, TriangleMesh
from polarface.geometry.embree_packets import PacketScene, packet_scene


@pytest.fixture(scope="module")
def head_like() -> TriangleMesh:
    """Two overlapping spheres and a box: concave regions, so shadow segments both pass and are blocked."""
    parts = [trimesh.creation.icosphere(subdivisions=4, radius=40.0),
             trimesh.creation.icosphere(subdivisions=3, radius=15.0).apply_translation([0.0, 0.0, 45.0]),
             trimesh.creation.box(extents=[20.0, 20.0, 20.0]).apply_translation([35.0, 0.0, 30.0])]
    mesh = trimesh.util.concatenate(parts)
    return TriangleMesh.from_arrays(mesh.vertices, mesh.faces, np.zeros((len(mesh.vertices), 2)))


def _embreex_blocked(caster: RayCaster, origins32, directions32, lengths32) -> np.ndarray:
    result = caster._scene.scene.run(origins32, directions32, dists=lengths32, query="OCCLUDED")
    return np.asarray(result) != -1


def _rays(caster: RayCaster, count: int, seed: int):
    """Random segments in the scene's float32 frame: from points on and around the surface towards points
    around it, lengths up to past the far end (and some of length 0)."""
    rng = np.random.default_rng(seed)
    start = caster.mesh.vertices[rng.integers(0, len(caster.mesh.vertices), count)]
    start = start + rng.normal(0.0, 2.0, (count, 3))
    end = rng.normal(0.0, 60.0, (count, 3))
    segment = end - start
    length = np.linalg.norm(segment, axis=1)
    wrap = caster._scene
    origins32 = ((start - wrap.origin) * wrap.scale).astype(np.float32)
    directions32 = (segment / length[:, None]).astype(np.float32)
    lengths32 = (length * rng.uniform(0.0, 1.3, count) * wrap.scale).astype(np.float32)
    lengths32[::97] = 0.0
    return origins32, directions32, lengths32


@pytest.mark.parametrize("count", [0, 1, 7, 8, 9, 20_001])
def test_packets_answer_as_embreex(head_like, count):
    caster = RayCaster(head_like)
    packets = caster._packet_scene()
    assert isinstance(packets, PacketScene)
    origins32, directions32, lengths32 = _rays(caster, count, seed=count)
    blocked = packets.occluded(origins32, directions32, lengths32)
    expected = _embreex_blocked(caster, origins32, directions32, lengths32)
    assert blocked.dtype == bool and blocked.shape == (count,)
    assert np.array_equal(blocked, expected)
    if count > 1000:  # the rays test both answers
        assert 0.1 < expected.mean() < 0.9


def test_shadow_rays_same_without_packets(head_like, monkeypatch):
    rng = np.random.default_rng(3)
    caster = RayCaster(head_like)
    origins = np.column_stack([rng.uniform(-60.0, 60.0, (2000, 2)), np.full(2000, 300.0)])
    hits = caster.first_hits(origins, np.tile([0.0, 0.0, -1.0], (2000, 1)))
    points, normals = hits.point[hits.hit], hits.geometric_normal[hits.hit]
    lights = np.array([[200.0, 0.0, 200.0], [-150.0, 50.0, 250.0], [0.0, 300.0, 50.0], [60.0, 0.0, 90.0]])
    lit = caster.shadow_rays(points, normals, lights)
    monkeypatch.setenv("POLARFACE_EMBREE_PACKETS", "0")
    plain = RayCaster(head_like)
    assert plain._packet_scene() is None
    assert np.array_equal(plain.shadow_rays(points, normals, lights), lit)
    assert 0.05 < lit.mean() < 0.95


def test_packet_scene_switched_off(monkeypatch, head_like):
    monkeypatch.setenv("POLARFACE_EMBREE_PACKETS", "0")
    assert packet_scene(np.zeros((3, 3), np.float32), np.array([[0, 1, 2]])) is None


def test_packet_scene_bad_rays(head_like):
    packets = RayCaster(head_like)._packet_scene()
    with pytest.raises(ValueError, match="'origins32' and 'directions32'"):
        packets.occluded(np.zeros((4, 3)), np.zeros((4, 2)), np.zeros(4))
    with pytest.raises(ValueError, match="'lengths32' must be \\(4,\\)"):
        packets.occluded(np.zeros((4, 3)), np.zeros((4, 3)), np.zeros(3))
