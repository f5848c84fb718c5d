"""USD export (``polarface export --format usd``): the static result and the dynamic sequence as a stage.

Layout of the format's folder ``OUT`` (``docs/export.md``, section "USD")::

    face.usda                 root layer (text): stage metadata, /Face, the UsdPreviewSurface material
                              with its (time-varying) texture paths; sublayers the geometry layer
    face_geometry.usdc        binary layer: /Face/Mesh with points, normals and extents (default = the
                              static rest mesh, one time sample per dynamic frame), indices, st
    textures/*.png            static textures; textures/frames/<name>_NNNN.png per dynamic frame

Units and axes: stage units are the RESULT's mm (``metersPerUnit`` 0.001) in the model frame, ``upAxis``
Y (the bundled head's +y; ``docs/conventions.md``). Time: one time code per dynamic frame, equal to the
frame index; ``timeCodesPerSecond`` (and ``framesPerSecond``) come from the frames' capture timestamps
(a straight-line fit through them); the timestamps themselves are in the root layer's
``customLayerData``. Texture coordinates: polarface's UVs are v up with texture row 0 at ``v = 1``,
which is USD's ``st`` convention for UsdUVTexture (origin at the image's bottom-left), so ``st`` is the
mesh's UV unchanged (tests check a known texel).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from polarface.export.formats import ExportOptions
from polarface.export.source import ExportSource
from polarface.export.texture_images import (
    albedo_srgb_image,
    fill_outside_mask,
    normal_map_image,
    specular_f0,
)
from polarface.geometry import UVRaster, rasterize_uv, reposition
from polarface.io import record_path, write_png
from polarface.skin.layers import PARAMETER_RANGES

__all__ = ["USD_GEOMETRY_LAYER", "USD_ROOT_LAYER", "write_usd"]

#: The root layer (what to open) and the binary geometry layer it sublayers.
USD_ROOT_LAYER = "face.usda"
USD_GEOMETRY_LAYER = "face_geometry.usdc"
_TEXTURES = "textures"
_FRAME_TEXTURES = "textures/frames"
_FACE, _MESH, _MATERIAL = "/Face", "/Face/Mesh", "/Face/Looks/Skin"
#: The 16-bit C_h,out texture stores C_h,out / this (its admissible maximum); UsdUVTexture's ``scale``
#: gives the volume fraction back.
_C_H_OUT_SCALE = PARAMETER_RANGES["c_h_out"][1]
_DEFAULT_FPS = 30.0

LOST = [
    "polarization: UsdPreviewSurface has no Mueller calculus (pBSSRDF lobes become unpolarized)",
    "subsurface diffusion: rho_sss_bar is a Lambertian diffuseColor (no SoG blur; see the kernels format)",
    "single scattering (alpha_ss, rho_ss): no second specular lobe",
    "eta per texel: only in specularColor = rho_s F0(eta); the ior input is the masked median",
    "six spectral channels: diffuse colour is linear RGB of the half-band means, sRGB encoded",
    "chromophores other than C_h,out (c_m, beta_m, c_h_in): not carried",
    "per-frame alpha_s, rho_s, eta: roughness and specular stay the static result's",
]


@dataclasses.dataclass(frozen=True)
class _FrameData:
    """One time sample: vertices/normals ``(N, 3)`` float32 mm and its three texture paths (relative)."""

    vertices: np.ndarray
    normals: np.ndarray
    albedo: str
    normal: str
    c_h_out: str


def _scaled_16bit(values: np.ndarray, scale: float) -> np.ndarray:
    return np.clip(values / scale, 0.0, 1.0)


def _time_textures(source: ExportSource, raster: UVRaster, out: Path, folder: str, tag: str
                   ) -> dict[str, str]:
    """Write the albedo, normal and C_h,out textures of ``source`` as ``folder/<name><tag>.png``."""
    mask = source.mask
    names = {"albedo": "albedo_srgb", "normal": "normal_tangent", "c_h_out": "c_h_out"}
    paths = {key: f"{folder}/{name}{tag}.png" for key, name in names.items()}
    (out / folder).mkdir(parents=True, exist_ok=True)
    write_png(out / paths["albedo"], albedo_srgb_image(source.channel_map("rho_sss_bar"), mask, source.rig))
    write_png(out / paths["normal"], normal_map_image(source.scalar_map("displacement_mm"), mask, raster))
    c_h_out = fill_outside_mask(source.scalar_map("c_h_out"), mask)
    write_png(out / paths["c_h_out"], _scaled_16bit(c_h_out, _C_H_OUT_SCALE), bit_depth=16)
    return paths


def _static_textures(source: ExportSource, out: Path) -> dict[str, Any]:
    """Roughness and specular textures (static only) and the scalar ior; returns paths and scales."""
    mask = source.mask
    alpha = fill_outside_mask(np.clip(source.scalar_map("alpha_s"), 0.0, 1.0), mask)
    eta = fill_outside_mask(source.scalar_map("eta"), mask)
    f0 = specular_f0(fill_outside_mask(np.maximum(source.scalar_map("rho_s"), 0.0), mask), eta)
    f0_scale = float(f"{max(float(f0[mask].max()), 1e-6):.2g}") * 1.01
    paths = {"roughness": f"{_TEXTURES}/roughness.png", "specular": f"{_TEXTURES}/specular_f0.png"}
    write_png(out / paths["roughness"], np.sqrt(alpha), bit_depth=16)
    write_png(out / paths["specular"], np.repeat(_scaled_16bit(f0, f0_scale)[..., None], 3, -1), bit_depth=16)
    return {**paths, "specular_scale": f0_scale, "ior": float(np.median(source.scalar_map("eta")[mask]))}


def _frame_data(source: ExportSource, frame: int, rest, raster: UVRaster, out: Path) -> _FrameData:
    """Tracked mesh of ``frame`` (checked against the rest topology) and its textures."""
    frame_source = source.frame(frame)
    mesh = frame_source.mesh
    if not (np.array_equal(mesh.faces, rest.faces) and np.allclose(mesh.uv, rest.uv, atol=1e-6)):
        raise ValueError(
            f"'{frame_source.folder.mesh_path}' does not share the faces and UVs of the rest mesh "
            f"'{source.folder.mesh_path}' (a tracked frame must keep the topology)"
        )
    paths = _time_textures(frame_source, reposition(raster, mesh), out, _FRAME_TEXTURES, f"_{frame:04d}")
    return _FrameData(
        mesh.vertices.astype(np.float32), mesh.normals.astype(np.float32), **paths
    )


def _timing(source: ExportSource) -> dict[str, Any]:
    """Time codes (= frame indices), the rate fitted to the timestamps and its worst deviation (s)."""
    frames = list(source.frames)
    stamps = [source.timestamp_s(f) for f in frames]
    rate = _DEFAULT_FPS
    if len(frames) >= 2:
        slope = np.polyfit(np.asarray(frames, float), np.asarray(stamps, float), 1)[0]
        rate = float(f"{1.0 / slope:.6g}") if slope > 0 else _DEFAULT_FPS
    deviation = 0.0
    if frames:
        fitted = stamps[0] + (np.asarray(frames, float) - frames[0]) / rate
        deviation = float(np.max(np.abs(fitted - np.asarray(stamps))))
    return {
        "time_codes": {str(f): float(f) for f in frames},
        "timestamps_s": {str(f): float(t) for f, t in zip(frames, stamps, strict=True)},
        "time_codes_per_second": float(rate),
        "max_timing_deviation_s": deviation,
    }


def _vec3(values: np.ndarray):
    from pxr import Vt

    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(values, dtype=np.float32))


def _extent(vertices: np.ndarray):
    return _vec3(np.stack([vertices.min(axis=0), vertices.max(axis=0)]))


def _write_geometry_layer(path: Path, rest, frames: dict[int, _FrameData], rate: float) -> None:
    """``/Face/Mesh``: static values as defaults, one time sample per frame.

    The layer's ``timeCodesPerSecond`` must equal the root layer's: USD rescales the time samples of a
    sublayer whose rate differs (time codes would no longer be frame indices)."""
    from pxr import Sdf, Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(path))
    stage.SetTimeCodesPerSecond(rate)
    stage.SetFramesPerSecond(rate)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    face = UsdGeom.Xform.Define(stage, _FACE)
    stage.SetDefaultPrim(face.GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, _MESH)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)  # counter-clockwise from outside
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(rest.faces), 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(rest.faces.reshape(-1).astype(np.int32)))
    points, normals, extent = mesh.CreatePointsAttr(), mesh.CreateNormalsAttr(), mesh.CreateExtentAttr()
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    samples = [(Usd.TimeCode.Default(), rest.vertices, rest.normals)]
    samples += [(Usd.TimeCode(float(f)), d.vertices, d.normals) for f, d in frames.items()]
    for time, vertices, vertex_normals in samples:
        points.Set(_vec3(vertices), time)
        normals.Set(_vec3(vertex_normals), time)
        extent.Set(_extent(vertices), time)
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex
    )
    st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(rest.uv, dtype=np.float32)))
    stage.GetRootLayer().Save()


def _texture(stage, material_path: str, name: str, file: str, colour_space: str,
             scale: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0), bias: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)):
    """A UsdUVTexture shader reading ``file`` at the ``st`` primvar (``outputs:r``/``rgb`` declared)."""
    from pxr import Gf, Sdf, UsdShade

    shader = UsdShade.Shader.Define(stage, f"{material_path}/{name}")
    shader.CreateIdAttr("UsdUVTexture")
    shader.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(f"./{file}"))
    reader = UsdShade.Shader(stage.GetPrimAtPath(f"{material_path}/StReader"))
    shader.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
    shader.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(colour_space)
    shader.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
    shader.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("clamp")
    if scale != (1.0, 1.0, 1.0, 1.0):
        shader.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*scale))
    if bias != (0.0, 0.0, 0.0, 0.0):
        shader.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*bias))
    shader.CreateOutput("r", Sdf.ValueTypeNames.Float)
    shader.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    return shader


def _write_material(stage, static: dict[str, Any], textures: dict[str, str], frames: dict[int, _FrameData]):
    """``/Face/Looks/Skin``: UsdPreviewSurface fed by UsdUVTextures; per-frame textures time-sampled."""
    from pxr import Sdf, Usd, UsdGeom, UsdShade

    UsdGeom.Scope.Define(stage, _MATERIAL.rsplit("/", 1)[0])
    material = UsdShade.Material.Define(stage, _MATERIAL)
    surface = UsdShade.Shader.Define(stage, f"{_MATERIAL}/PreviewSurface")
    surface.CreateIdAttr("UsdPreviewSurface")
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    reader = UsdShade.Shader.Define(stage, f"{_MATERIAL}/StReader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")  # string in the Sdr definition
    reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    albedo = _texture(stage, _MATERIAL, "AlbedoTexture", textures["albedo"], "sRGB")
    normal = _texture(stage, _MATERIAL, "NormalTexture", textures["normal"], "raw",
                      scale=(2.0, 2.0, 2.0, 1.0), bias=(-1.0, -1.0, -1.0, 0.0))
    c_h_out = _texture(stage, _MATERIAL, "OuterHaemoglobinTexture", textures["c_h_out"], "raw",
                       scale=(_C_H_OUT_SCALE,) * 3 + (1.0,))
    roughness = _texture(stage, _MATERIAL, "RoughnessTexture", static["roughness"], "raw")
    specular = _texture(stage, _MATERIAL, "SpecularTexture", static["specular"], "raw",
                        scale=(static["specular_scale"],) * 3 + (1.0,))
    inputs = surface.CreateInput
    inputs("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(albedo.ConnectableAPI(), "rgb")
    inputs("normal", Sdf.ValueTypeNames.Normal3f).ConnectToSource(normal.ConnectableAPI(), "rgb")
    inputs("roughness", Sdf.ValueTypeNames.Float).ConnectToSource(roughness.ConnectableAPI(), "r")
    inputs("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(1)
    inputs("specularColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(specular.ConnectableAPI(), "rgb")
    inputs("ior", Sdf.ValueTypeNames.Float).Set(static["ior"])
    for key, shader in (("albedo", albedo), ("normal", normal), ("c_h_out", c_h_out)):
        attribute = shader.GetInput("file").GetAttr()
        for frame, data in frames.items():
            attribute.Set(Sdf.AssetPath(f"./{getattr(data, key)}"), Usd.TimeCode(float(frame)))
    return material


def _write_root_layer(path: Path, static: dict[str, Any], textures: dict[str, str],
                      frames: dict[int, _FrameData], timing: dict[str, Any], source: ExportSource) -> None:
    from pxr import Kind, Usd, UsdGeom, UsdShade

    stage = Usd.Stage.CreateNew(str(path))
    stage.GetRootLayer().subLayerPaths.append(f"./{USD_GEOMETRY_LAYER}")
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    face = UsdGeom.Xform.Define(stage, _FACE)
    Usd.ModelAPI(face).SetKind(Kind.Tokens.component)
    stage.SetDefaultPrim(face.GetPrim())
    material = _write_material(stage, static, textures, frames)
    mesh = stage.OverridePrim(_MESH)
    UsdShade.MaterialBindingAPI.Apply(mesh).Bind(material)
    stage.SetTimeCodesPerSecond(timing["time_codes_per_second"])
    stage.SetFramesPerSecond(timing["time_codes_per_second"])
    if frames:
        stage.SetStartTimeCode(float(min(frames)))
        stage.SetEndTimeCode(float(max(frames)))
    stage.GetRootLayer().customLayerData = {
        "polarface:result": record_path(path.parent, source.folder.root),
        "polarface:timestamps_s": {f"frame_{k}": v for k, v in timing["timestamps_s"].items()},
    }
    stage.GetRootLayer().Save()


def write_usd(source: ExportSource, out: Path, options: ExportOptions) -> dict[str, Any]:
    """Write the USD stage of the static result and ``source.frames`` into the empty folder ``out``.

    Args:
        source: the RESULT (maps checked by :data:`polarface.export.EXPORT_FORMATS`'s ``usd`` entry).
        out: the format's local folder (module docstring for its layout).
        options: the export options (the frame selection is already applied to ``source``).

    Returns:
        ``files`` (relative to ``out``), ``root`` (the layer to open), ``frames``, the timing
        (``time_codes``, ``timestamps_s``, ``time_codes_per_second``, ``max_timing_deviation_s``),
        ``ior`` and ``lost``.

    Raises:
        ValueError: a frame's tracked mesh does not share the rest mesh's faces and UVs (naming it).
    """
    out = Path(out)
    rest = source.mesh
    raster = rasterize_uv(rest, source.mask.shape)
    textures = _time_textures(source, raster, out, _TEXTURES, "")
    static = _static_textures(source, out)
    with concurrent.futures.ThreadPoolExecutor(max_workers=2) as pool:
        results = pool.map(lambda f: _frame_data(source, f, rest, raster, out), source.frames)
        frames = dict(zip(source.frames, results, strict=True))
    timing = _timing(source)
    _write_geometry_layer(out / USD_GEOMETRY_LAYER, rest, frames, timing["time_codes_per_second"])
    _write_root_layer(out / USD_ROOT_LAYER, static, textures, frames, timing, source)
    files = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    return {
        "files": files,
        "root": USD_ROOT_LAYER,
        "frames": list(source.frames),
        **timing,
        "ior": static["ior"],
        "lost": LOST,
    }
