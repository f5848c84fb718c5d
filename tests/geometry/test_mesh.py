"""polarface.geometry.mesh: loading, saving, areas, normals, transforms, bad files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from polarface.geometry import (
    TriangleMesh,
    face_areas,
    load_mesh,
    rigid_transform,
    save_obj,
    save_ply,
    vertex_normals,
)
from polarface.geometry.head_asset import head_data_dir


def test_from_arrays_smoke_shapes(plane):
    assert plane.vertices.shape == (4, 3) and plane.vertices.dtype == np.float64
    assert plane.faces.dtype == np.int64 and plane.uv.shape == (4, 2) and plane.normals.shape == (4, 3)
    np.testing.assert_allclose(plane.normals, np.tile([0, 0, 1.0], (4, 1)))
    assert not plane.vertices.flags.writeable


def test_face_areas_and_bbox(plane):
    np.testing.assert_allclose(plane.face_areas(), [400.0, 400.0])
    np.testing.assert_allclose(face_areas(plane.vertices, plane.faces).sum(), 800.0)
    lo, hi = plane.bounding_box()
    np.testing.assert_allclose(lo, [0, 0, 0])
    np.testing.assert_allclose(hi, [40, 20, 0])


def test_sphere_area_and_normals_radial(uv_sphere):
    assert abs(uv_sphere.face_areas().sum() - 4 * math.pi * 50.0**2) / (4 * math.pi * 2500) < 2e-3
    radial = uv_sphere.vertices / np.linalg.norm(uv_sphere.vertices, axis=1, keepdims=True)
    cos = np.einsum("nc,nc->n", radial, uv_sphere.normals)
    assert cos.min() > 0.9995  # smooth across the UV seam too (welded accumulation)


def test_vertex_normals_area_weighted():
    # two faces sharing vertex 0: one large in z = 0 (area 50), one small tilted (area 0.5)
    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 1.0], [0, -1, 0]])
    f = np.array([[0, 1, 2], [0, 4, 3]])
    n = vertex_normals(v, f)
    big = np.array([0, 0, 1.0]) * 100.0
    small = np.cross(v[4] - v[0], v[3] - v[0])
    expected = (big + small) / np.linalg.norm(big + small)
    np.testing.assert_allclose(n[0], expected, atol=1e-12)


def test_transform_rigid(plane):
    matrix = rigid_transform(yaw=0.3, pitch=-0.2, roll=0.1, translation=(1, 2, 3))
    moved = plane.transformed(matrix)
    np.testing.assert_allclose(moved.vertices, plane.vertices @ matrix[:3, :3].T + matrix[:3, 3])
    np.testing.assert_allclose(moved.face_areas(), plane.face_areas())
    np.testing.assert_allclose(moved.normals, plane.normals @ matrix[:3, :3].T, atol=1e-12)
    with pytest.raises(ValueError, match="transform"):
        plane.transformed(np.diag([1.0, 1.0, -1.0, 1.0]))


@pytest.mark.parametrize("suffix", [".obj", ".ply"])
def test_save_load_round_trip(tmp_path, uv_sphere, suffix):
    path = tmp_path / f"sphere{suffix}"
    (save_obj if suffix == ".obj" else save_ply)(path, uv_sphere)
    loaded = load_mesh(path)
    assert loaded.face_count == uv_sphere.face_count
    # OBJ re-splits per (vertex, uv) pairs: compare per-corner data, order-independent of vertex numbering
    corners_a = np.concatenate([uv_sphere.vertices[uv_sphere.faces], uv_sphere.uv[uv_sphere.faces]], -1)
    corners_b = np.concatenate([loaded.vertices[loaded.faces], loaded.uv[loaded.faces]], -1)
    np.testing.assert_allclose(corners_b, corners_a, atol=1e-6)
    assert not list(tmp_path.glob(".tmp-*"))  # atomic write left nothing behind


def test_a_file_read_again_unchanged_is_not_parsed_again(tmp_path, uv_sphere):
    """load_mesh keeps the meshes it read: the same file, unchanged and with the same options, gives the
    same read-only mesh; a file replaced (as save_obj does, by renaming) or rewritten in place, or other
    options, read it again."""
    path = tmp_path / "sphere.obj"
    save_obj(path, uv_sphere)
    first = load_mesh(path)
    assert load_mesh(str(path)) is first
    assert not first.vertices.flags.writeable
    assert load_mesh(path, scale=2.0) is not first
    np.testing.assert_allclose(load_mesh(path, scale=2.0).vertices, 2.0 * first.vertices)
    save_obj(path, uv_sphere.with_vertices(uv_sphere.vertices + 1.0))
    moved = load_mesh(path)
    assert moved is not first
    np.testing.assert_allclose(moved.vertices, first.vertices + 1.0, atol=1e-6)
    # rewritten in place with text of the same length (times and size may not change): read again
    text = path.read_text()
    path.write_text(text.replace("v 1.", "v 3.", 1) if "v 1." in text else text.replace("v 2.", "v 4.", 1))
    assert load_mesh(path) is not moved


def test_obj_seams_are_split(tmp_path):
    text = "\n".join(
        [
            "v 0 0 0",
            "v 1 0 0",
            "v 1 1 0",
            "v 0 1 0",
            "vt 0 0",
            "vt 0.5 0",
            "vt 0.5 1",
            "vt 0 1",
            "vt 1 0",
            "vt 1 1",
            "f 1/1 2/2 3/3",
            "f 1/1 3/3 4/4",
            "f 2/5 3/6 4/4",  # vertices 2, 3 used with two UVs each
        ]
    )
    path = tmp_path / "seam.obj"
    path.write_text(text + "\n")
    mesh = load_mesh(path)
    assert mesh.vertex_count == 6
    for face_index, uv_expected in ((0, [[0, 0], [0.5, 0], [0.5, 1]]), (2, [[1, 0], [1, 1], [0, 1]])):
        np.testing.assert_allclose(mesh.uv[mesh.faces[face_index]], uv_expected)


@pytest.mark.parametrize(
    "variant",
    [
        lambda line: "  " + line,  # leading blanks: the line-by-line parser
        lambda line: line.replace(" ", "\t"),  # tabs: the line-by-line parser
        lambda line: " ".join(c + "/1" if "/" in c else c for c in line.split()) if line[0] == "f" else line,
    ],
    ids=["indented", "tabs", "normals"],
)
def test_obj_written_irregularly_loads_as_the_regular_file(tmp_path, uv_sphere, variant):
    """numpy's reader takes regular files, the line-by-line parser any other: the same mesh either way
    (``f v/vt/vn`` with normals, a repeated ``vt`` value: one vertex per distinct uv value)."""
    save_obj(tmp_path / "regular.obj", uv_sphere)
    lines = (tmp_path / "regular.obj").read_text().splitlines()
    keywords = ("v", "vt", "f")
    lines = [variant(line) if line.split() and line.split()[0] in keywords else line for line in lines]
    (tmp_path / "irregular.obj").write_text("\n".join(["vn 0 0 1", *lines]) + "\n")
    regular, irregular = load_mesh(tmp_path / "regular.obj"), load_mesh(tmp_path / "irregular.obj")
    for name in ("vertices", "faces", "uv", "normals"):
        assert np.array_equal(getattr(regular, name), getattr(irregular, name)), name


_OBJ_LINES = ["# header", "v 0.1 0.2 0.3", "v 1 0 0", "v 0 1 0", "v 1 1 0.5", "vt 0 0", "vt 1 0", "vt 0.5 1",
              "vn 0 0 1", "f 1/1 2/2 3/3", "f 2/2 4/3 3/1"]


@pytest.mark.parametrize(
    ("edit", "regular"),
    [
        (lambda lines: lines, True),
        (lambda lines: ["o a", *lines[1:3], lines[5], lines[9], "g b", *lines[3:5], "s off", *lines[6:8],
                        lines[10], "usemtl m"], True),  # groups, objects, interleaved blocks
        (lambda lines: ["", *lines, "  ", "#v 9 9 9"], True),  # blank lines, a comment that looks like a v
        (lambda lines: [line + " 1" if line.startswith(("v ", "vt ")) else line for line in lines], True),
        (lambda lines: [*lines, "f -1/-1 -2/-2 -3/-3", "vtx 1 2", "vn\t1 2 3"], True),  # relative indices
        (lambda lines: [*lines, "f 1/1 2/2 3/3 4/1"], False),  # a quad
        (lambda lines: [*lines, "vt\t0.1 0.2"], False),  # a keyword and a tab
        (lambda lines: [*lines, "f 1//1 2//2 3//3"], False),  # no texture coordinates
        (lambda lines: [*lines, "f 1/1/1 2/2/1 3/3/1"], False),  # two corner forms
        (lambda lines: [*lines, "v"], False),
    ],
)
def test_obj_regular_reader_equals_the_line_by_line_parser(edit, regular):
    """The grouped, numpy-read path returns the line-by-line parser's arrays for every file it takes, and
    None (the line-by-line parser then reads or refuses the file) for the irregular ones."""
    from polarface.geometry.obj_file import _obj_arrays_by_line, _obj_arrays_regular

    lines = edit(list(_OBJ_LINES))
    parsed = _obj_arrays_regular(lines)
    assert (parsed is not None) == regular
    if regular:
        for got, expected in zip(parsed, _obj_arrays_by_line(lines, Path("x.obj")), strict=True):
            assert got.dtype == expected.dtype and np.array_equal(got, expected)


def test_load_bundled_glb_v_convention():
    raw = trimesh.load(head_data_dir() / "LeePerrySmith.glb", process=False).to_geometry()
    mesh = load_mesh(head_data_dir() / "LeePerrySmith.glb")
    flipped = load_mesh(head_data_dir() / "LeePerrySmith.glb", flip_v=True, scale=2.0)
    assert mesh.vertex_count == 9279 and mesh.face_count == 17684
    np.testing.assert_allclose(mesh.uv, raw.visual.uv, atol=1e-7)  # trimesh's v-up conversion
    np.testing.assert_allclose(flipped.uv[:, 1], 1.0 - mesh.uv[:, 1], atol=1e-7)
    np.testing.assert_allclose(flipped.vertices, 2.0 * mesh.vertices)


def test_bad_files(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_mesh(tmp_path / "missing.obj")
    no_uv = tmp_path / "no_uv.obj"
    no_uv.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match=r"no_uv\.obj.*texture coordinates"):
        load_mesh(no_uv)
    quad = tmp_path / "quad.obj"
    quad.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1 4/1\n")
    with pytest.raises(ValueError, match=r"quad\.obj.*non-triangle"):
        load_mesh(quad)
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 nan\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1\n")
    with pytest.raises(ValueError, match=r"nan\.obj.*NaN"):
        load_mesh(nan)
    empty = tmp_path / "empty.obj"
    empty.write_text("vt 0 0\n")
    with pytest.raises(ValueError, match=r"empty\.obj"):
        load_mesh(empty)
    quad_ply = tmp_path / "quad.ply"
    quad_ply.write_text(
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "property float s\nproperty float t\nelement face 1\nproperty list uchar int vertex_indices\n"
        "end_header\n0 0 0 0 0\n1 0 0 1 0\n1 1 0 1 1\n0 1 0 0 1\n4 0 1 2 3\n"
    )
    with pytest.raises(ValueError, match=r"quad\.ply.*non-triangle"):
        load_mesh(quad_ply)
    plain_ply = tmp_path / "plain.ply"
    trimesh.creation.box().export(plain_ply)
    with pytest.raises(ValueError, match=r"plain\.ply.*texture coordinates"):
        load_mesh(plain_ply)
    garbage = tmp_path / "garbage.glb"
    garbage.write_bytes(b"not a glb at all")
    with pytest.raises(ValueError, match=r"garbage\.glb"):
        load_mesh(garbage)
    with pytest.raises(ValueError, match="unsupported"):
        (tmp_path / "x.stl").write_text("solid x\nendsolid x\n")
        load_mesh(tmp_path / "x.stl")


def test_from_arrays_errors():
    v = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    uv = [[0, 0], [1, 0], [0, 1]]
    with pytest.raises(ValueError, match="face indices"):
        TriangleMesh.from_arrays(v, [[0, 1, 3]], uv)
    with pytest.raises(ValueError, match="uv must lie"):
        TriangleMesh.from_arrays(v, [[0, 1, 2]], [[0, 0], [1.5, 0], [0, 1]])
    with pytest.raises(ValueError, match="uv must be"):
        TriangleMesh.from_arrays(v, [[0, 1, 2]], uv[:2])
    with pytest.raises(ValueError, match="vertices"):
        TriangleMesh.from_arrays(np.zeros((0, 3)), [[0, 1, 2]], np.zeros((0, 2)))
