"""glTF 2.0 binary (``face.glb``) of a RESULT's static reconstruction: mesh and a PBR material.

What maps onto what, what is lost, units and axes: ``docs/export.md``, "glTF 2.0". In short:

* **Geometry**: ``mesh.obj`` (mm, model frame; one UV per vertex, seams already split) with POSITION,
  NORMAL, TANGENT, TEXCOORD_0 and triangle indices. Positions are scaled to metres in the vertex data
  (no node transform) and rotated into glTF's +y up / face towards +z when the mesh is in the rig world
  of a stereo reconstruction (y down, the face towards -z, ``docs/geometry.md``); a given mesh is in the
  head's model frame, already +y up / face +z. The 4x4 model (mm) -> glTF (m) matrix is in the node's
  ``extras.polarface.model_to_gltf``. UVs: polarface's v is up, glTF's v is down: ``v_gltf = 1 - v``;
  texture rows are stored as the maps' rows (row 0 = top = ``v_gltf`` 0).
* **Material** (``pbrMetallicRoughness``, ``metallicFactor`` 0): base colour = sRGB of the rig's linear
  RGB of ``rho_sss_bar`` (per colour the mean of its two half bands,
  :func:`polarface.render.linear_rgb_from_channels`); ``metallicRoughnessTexture`` G = ``sqrt(alpha_s)``
  (glTF's alpha = roughness^2); ``normalTexture`` = the displacement map's shading normals
  (:func:`polarface.render.shading_normals`) in the tangent frame the TANGENT attribute defines;
  ``KHR_materials_ior`` ior = median ``eta`` over the mask; ``KHR_materials_specular``: strength (A of
  ``specularTexture``) = ``min(rho_s, 1)``, colour (``specularColorTexture`` x ``specularColorFactor``)
  = ``rho_s F0(eta) / (F0(ior) min(rho_s, 1))``, so glTF's normal-incidence reflectance
  ``F0(ior) colour strength`` equals polarface's ``rho_s F0(eta)`` per texel.

Texels outside the mask take their nearest valid value (:func:`polarface.render.fill_empty_texels`) so
that bilinear lookups and mip-maps do not blend in empty texels.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from polarface.export.formats import ExportOptions
from polarface.export.gltf_glb import ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER, GlbBuilder
from polarface.export.source import ExportSource
from polarface.export.texture_images import fresnel_f0
from polarface.io import atomic_path, encode_png, record_path

__all__ = ["GLB_NAME", "LOST", "tangent_space_normals", "write_gltf"]

#: The file written into the format's folder.
GLB_NAME = "face.glb"
#: What the glTF material cannot carry (``record["lost"]``; ``docs/export.md``).
LOST = (
    "second (single-scattering) specular lobe rho_ss, alpha_ss",
    "per-texel eta (one ior: the median over the mask; the per-texel normal-incidence reflectance "
    "rho_s F0(eta) is kept in the specular colour, the Fresnel curve's shape is glTF's Schlick curve)",
    "specular reflectance above 1 at grazing angles (glTF's f90 = min(rho_s, 1))",
    "six-channel subsurface albedo rho_sss_bar (reduced to RGB: mean of the two half bands per colour)",
    "subsurface diffusion (chromophore maps, sum-of-Gaussians kernels: Lambertian base colour instead)",
    "Stokes vectors / polarisation (glTF shading is unpolarized)",
    "displacement as geometry (kept as a normal map only)",
    "dynamic frames (static result only)",
)

_SAMPLER = {"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}  # linear, mip-mapped
_MM_TO_M = 1e-3


def _model_rotation(source: ExportSource) -> tuple[np.ndarray, str]:
    """``(3, 3)`` rotation model frame -> glTF axes and a sentence saying why."""
    if source.folder.stereo_geometry():
        return np.diag([1.0, -1.0, -1.0]), (
            "stereo geometry: the model frame is the rig world of the reference frame (y down, the face "
            "towards -z), rotated 180 deg about x into glTF's +y up, face towards +z"
        )
    return np.eye(3), "given mesh: the model frame is +y up, the face towards +z (docs/geometry.md), kept"


def _vertex_tangents(mesh) -> np.ndarray:
    """``(N, 4)`` float64 glTF tangents of ``mesh`` (model frame): xyz the unit direction of dP/du
    orthogonalised against the vertex normal, w = +-1 so that ``cross(normal, xyz) w`` points along dP/dv
    (v up, the image's up: glTF's normal-map +Y). Per vertex: area-weighted mean of its faces'
    dP/du, dP/dv (seams split vertices, so charts never mix)."""
    corners, uvs = mesh.vertices[mesh.faces], mesh.uv[mesh.faces]
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    d1, d2 = uvs[:, 1] - uvs[:, 0], uvs[:, 2] - uvs[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    ok = np.abs(det) > 1e-15
    inverse = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)[:, None] * mesh.face_areas()[:, None]
    dp_du = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * inverse
    dp_dv = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * inverse
    sum_u = np.zeros_like(mesh.vertices)
    sum_v = np.zeros_like(mesh.vertices)
    for k in range(3):
        np.add.at(sum_u, mesh.faces[:, k], dp_du)
        np.add.at(sum_v, mesh.faces[:, k], dp_dv)
    normal = mesh.normals
    tangent = sum_u - (sum_u * normal).sum(1, keepdims=True) * normal
    length = np.linalg.norm(tangent, axis=1, keepdims=True)
    # vertices without a usable dP/du: any direction orthogonal to the normal
    helper = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    fallback = np.cross(normal, helper)
    fallback /= np.linalg.norm(fallback, axis=1, keepdims=True)
    tangent = np.where(length > 1e-12, tangent / np.maximum(length, 1e-300), fallback)
    handedness = np.where((np.cross(normal, tangent) * sum_v).sum(1) < 0.0, -1.0, 1.0)
    return np.concatenate([tangent, handedness[:, None]], axis=1)


def _unit(vectors: np.ndarray) -> np.ndarray:
    return vectors / np.maximum(np.linalg.norm(vectors, axis=-1, keepdims=True), 1e-300)


def tangent_space_normals(raster, mesh, tangents: np.ndarray, shading: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` float64 tangent-space normals (x along TANGENT, y along the bitangent, z along the
    normal; unit, z > 0) whose decoding by a glTF viewer gives ``shading`` back.

    A viewer interpolates the vertex tangent t, bitangent b = cross(n, t) w and normal n over the
    triangle, normalises them and shades with ``normalize(x t + y b + z n)``; we solve that 3x3 system
    per texel. Texels outside ``raster.mask`` (no triangle) hold (0, 0, 1).

    Args:
        raster: :class:`polarface.geometry.UVRaster` of ``mesh`` (face ids and barycentrics).
        mesh: the mesh (model frame). tangents: ``(N, 4)`` from :func:`_vertex_tangents`.
        shading: ``(H, W, 3)`` unit shading normals, model frame.
    """
    out = np.zeros((*raster.mask.shape, 3))
    out[..., 2] = 1.0
    rows, cols = np.nonzero(raster.mask)
    triangle = mesh.faces[raster.face_id[rows, cols]]
    weights = raster.barycentric[rows, cols].astype(np.float64)[..., None]
    bitangents = np.cross(mesh.normals, tangents[:, :3]) * tangents[:, 3:]
    tables = (tangents[:, :3], bitangents, mesh.normals)
    frame = [_unit((weights * table[triangle]).sum(1)) for table in tables]
    matrix = np.stack(frame, axis=-1)  # columns t, b, n
    target = shading[rows, cols]
    solvable = np.abs(np.linalg.det(matrix)) > 1e-6
    local = np.tile([0.0, 0.0, 1.0], (len(rows), 1))
    local[solvable] = np.linalg.solve(matrix[solvable], target[solvable][..., None])[..., 0]
    local[:, 2] = np.maximum(local[:, 2], 1e-3)
    out[rows, cols] = _unit(local)
    return out


def _unorm8(values: np.ndarray) -> np.ndarray:
    return np.round(np.clip(values, 0.0, 1.0) * 255.0).astype(np.uint8)


@dataclasses.dataclass(frozen=True)
class _Textures:
    """The material's images (uint8, ``(H, W, C)``, row 0 = top) and its scalar factors."""

    base_colour: np.ndarray
    metallic_roughness: np.ndarray
    normal: np.ndarray
    specular: np.ndarray
    specular_colour: np.ndarray
    specular_colour_factor: float
    ior: float


def _material_textures(source: ExportSource, raster, tangents: np.ndarray) -> _Textures:
    from polarface.render import encode_srgb, fill_empty_texels, linear_rgb_from_channels, shading_normals

    valid = source.mask & raster.mask
    if not valid.any():
        raise ValueError(
            f"glTF export: no texel of '{source.map_file('mask')}' lies on the UV atlas of "
            f"'{source.folder.mesh_path}' (mesh and maps do not belong together)"
        )
    fill = lambda m: fill_empty_texels(m, valid)  # noqa: E731
    eta, rho_s = source.scalar_map("eta"), source.scalar_map("rho_s")
    ior = float(np.median(eta[valid]))
    if not ior > 1.0:
        raise ValueError(f"glTF export: the median eta over the mask is {ior:.4g}; glTF's ior must exceed 1")
    linear = linear_rgb_from_channels(source.channel_map("rho_sss_bar"), source.rig)
    roughness = np.sqrt(np.clip(source.scalar_map("alpha_s"), 0.0, 1.0))
    strength = np.clip(rho_s, 0.0, 1.0)
    colour = np.maximum(rho_s, 0.0) * fresnel_f0(eta) / fresnel_f0(ior) / np.maximum(strength, 1e-6)
    colour = fill(np.where(strength > 0.0, colour, fresnel_f0(eta) / fresnel_f0(ior)))
    colour_factor = max(float(colour.max()), 1e-6)
    height = np.where(valid, source.scalar_map("displacement_mm"), 0.0)
    shading = shading_normals(dataclasses.replace(raster, mask=valid), height)
    normal = fill_empty_texels(tangent_space_normals(raster, source.mesh, tangents, shading), raster.mask)
    opaque, zero = np.ones(valid.shape), np.zeros(valid.shape)
    return _Textures(
        base_colour=_unorm8(encode_srgb(fill(linear))),
        metallic_roughness=_unorm8(np.stack([opaque, fill(roughness), zero], -1)),
        normal=_unorm8(0.5 * (normal + 1.0)),
        specular=_unorm8(np.stack([opaque, opaque, opaque, fill(strength)], -1)),
        specular_colour=_unorm8(np.repeat(encode_srgb(colour / colour_factor)[..., None], 3, -1)),
        specular_colour_factor=colour_factor,
        ior=ior,
    )


def _check_maps(source: ExportSource) -> tuple[int, int]:
    shape = source.mask.shape
    for name in ("eta", "rho_s", "alpha_s", "displacement_mm"):
        if source.scalar_map(name).shape != shape:
            raise ValueError(
                f"glTF export: '{source.map_file(name)}' is {source.scalar_map(name).shape}, "
                f"the mask {shape}"
            )
    if source.channel_map("rho_sss_bar").shape[:2] != shape:
        raise ValueError(f"glTF export: '{source.map_file('rho_sss_bar')}' does not match the mask {shape}")
    return shape


def _material(textures: dict[str, int], t: _Textures) -> dict[str, Any]:
    return {
        "name": "polarface_skin",
        "pbrMetallicRoughness": {
            "baseColorTexture": {"index": textures["base_colour"]},
            "metallicFactor": 0.0,
            "roughnessFactor": 1.0,
            "metallicRoughnessTexture": {"index": textures["metallic_roughness"]},
        },
        "normalTexture": {"index": textures["normal"], "scale": 1.0},
        "extensions": {
            "KHR_materials_specular": {
                "specularFactor": 1.0,
                "specularTexture": {"index": textures["specular"]},
                "specularColorFactor": [t.specular_colour_factor] * 3,
                "specularColorTexture": {"index": textures["specular_colour"]},
            },
            "KHR_materials_ior": {"ior": t.ior},
        },
    }


def write_gltf(source: ExportSource, out: Path, options: ExportOptions) -> dict[str, Any]:
    """Write ``out/face.glb``: the static result's mesh and material (module docstring).

    Args:
        source: the RESULT (static maps ``eta``, ``rho_s``, ``alpha_s``, ``displacement_mm``,
            ``rho_sss_bar``, ``mask``; ``mesh.obj`` with UVs; ``rig.json``).
        out: the format's (empty, local) folder.
        options: unused (the glTF export has no settings).

    Returns:
        ``files``, ``vertices``, ``triangles``, ``texture_size`` ``[H, W]``, ``ior``,
        ``specular_color_factor``, ``axes``, ``model_to_gltf`` (4x4, mm -> m), ``lost``.

    Raises:
        ValueError: maps of different sizes, a mask off the mesh's UV atlas, eta <= 1 (naming the file).
    """
    from polarface import __version__
    from polarface.geometry import rasterize_uv

    del options
    shape = _check_maps(source)
    mesh = source.mesh
    raster = rasterize_uv(mesh, shape)
    tangents = _vertex_tangents(mesh)
    images = _material_textures(source, raster, tangents)
    rotation, axes = _model_rotation(source)
    builder = GlbBuilder()
    positions = (mesh.vertices @ rotation.T) * _MM_TO_M
    uv = np.stack([mesh.uv[:, 0], 1.0 - mesh.uv[:, 1]], axis=1)
    tangent_out = np.concatenate([tangents[:, :3] @ rotation.T, tangents[:, 3:]], axis=1)
    index_type = np.uint16 if mesh.vertex_count < 65535 else np.uint32  # 65535: primitive restart
    attributes = {
        "POSITION": builder.add_accessor(positions.astype(np.float32), ARRAY_BUFFER, bounds=True),
        "NORMAL": builder.add_accessor((mesh.normals @ rotation.T).astype(np.float32), ARRAY_BUFFER),
        "TANGENT": builder.add_accessor(tangent_out.astype(np.float32), ARRAY_BUFFER),
        "TEXCOORD_0": builder.add_accessor(uv.astype(np.float32), ARRAY_BUFFER),
    }
    indices = builder.add_accessor(mesh.faces.reshape(-1).astype(index_type), ELEMENT_ARRAY_BUFFER)
    textures = {}
    for name in ("base_colour", "metallic_roughness", "normal", "specular", "specular_colour"):
        textures[name] = builder.add_image(encode_png(getattr(images, name)), "image/png", name)
    model_to_gltf = np.eye(4)
    model_to_gltf[:3, :3] = rotation * _MM_TO_M
    document = {
        "asset": {"version": "2.0", "generator": f"polarface {__version__} (polarface export --format gltf)"},
        "extensionsUsed": ["KHR_materials_ior", "KHR_materials_specular"],
        "scene": 0,
        "scenes": [{"name": "polarface", "nodes": [0]}],
        "nodes": [{"name": "face", "mesh": 0, "extras": {"polarface": {
            "model_to_gltf": model_to_gltf.tolist(), "axes": axes,
            "result": record_path(out, source.folder.root)}}}],
        "meshes": [{"name": "face", "primitives": [
            {"attributes": attributes, "indices": indices, "material": 0, "mode": 4}]}],
        "materials": [_material(textures, images)],
        "samplers": [_SAMPLER],
        "textures": [{"sampler": 0, "source": textures[name]} for name in textures],
    }
    out = Path(out)
    with atomic_path(out / GLB_NAME) as tmp:
        tmp.write_bytes(builder.encode(document))
    return {
        "files": [GLB_NAME],
        "vertices": mesh.vertex_count,
        "triangles": mesh.face_count,
        "texture_size": [int(shape[0]), int(shape[1])],
        "ior": images.ior,
        "specular_color_factor": images.specular_colour_factor,
        "axes": axes,
        "model_to_gltf": model_to_gltf.tolist(),
        "lost": list(LOST),
    }
