"""USD export read back through the USD Python API (usd-core): geometry per time code, st orientation,
time-varying texture paths, UsdValidation, bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdShade  # usd-core: a dependency of polarface (the export's reader here)

from polarface.export import ExportOptions, ExportSource, MissingMapError
from polarface.export.texture_images import tangent_space_normals
from polarface.geometry import rasterize_uv
from polarface.io import read_png
from polarface.pipeline import export_result
from polarface.render import encode_srgb, linear_rgb_from_channels


@pytest.fixture(scope="module")
def usd_export(tiny_export, tmp_path_factory):
    """``(RESULT, ExportSource, stage, export record)`` of the tiny result exported as USD."""
    _, result = tiny_export
    out = tmp_path_factory.mktemp("usd_export")
    summary = export_result(result, out, ExportOptions(formats=("usd",)))
    stage = Usd.Stage.Open(str(out / "usd" / summary["formats"]["usd"]["root"]))
    assert stage is not None
    return result, ExportSource.open(result), stage, summary["formats"]["usd"]


def test_stage_units_counts_and_time_codes(usd_export):
    _, source, stage, record = usd_export
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.001)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert stage.GetDefaultPrim().GetPath() == "/Face"
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/Mesh"))
    rest = source.mesh
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    assert len(counts) == rest.face_count and (counts == 3).all()
    np.testing.assert_array_equal(indices, rest.faces)
    assert mesh.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
    frames = list(source.frames)
    assert frames == [0, 1] and record["frames"] == frames
    assert list(mesh.GetPointsAttr().GetTimeSamples()) == [float(f) for f in frames]
    assert stage.GetStartTimeCode() == frames[0] and stage.GetEndTimeCode() == frames[-1]
    stamps = [source.timestamp_s(f) for f in frames]
    assert stage.GetTimeCodesPerSecond() == pytest.approx((frames[1] - frames[0]) / (stamps[1] - stamps[0]))


def test_points_equal_the_rest_and_tracked_meshes(usd_export):
    _, source, stage, _ = usd_export
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/Mesh"))
    samples = [(Usd.TimeCode.Default(), source.mesh)] + [
        (Usd.TimeCode(float(f)), source.frame(f).mesh) for f in source.frames
    ]
    for time, expected in samples:
        points = np.asarray(mesh.GetPointsAttr().Get(time), dtype=np.float64)
        np.testing.assert_allclose(points, expected.vertices, atol=1e-4)  # float32 mm
        extent = np.asarray(mesh.GetExtentAttr().Get(time))
        np.testing.assert_allclose(extent, [points.min(0), points.max(0)], atol=1e-6)
        normals = np.asarray(mesh.GetNormalsAttr().Get(time), dtype=np.float64)
        np.testing.assert_allclose(normals, expected.normals, atol=1e-5)
    first, second = (np.asarray(mesh.GetPointsAttr().Get(float(f))) for f in source.frames)
    assert np.abs(first - second).max() > 1e-3  # the frames differ: the test sees motion


def _usd_texel(image: np.ndarray, st: np.ndarray) -> np.ndarray:
    """Texel of ``image`` at ``st`` by USD's convention: (0, 0) is the image's bottom-left corner."""
    height, width = image.shape[:2]
    col = np.clip(np.floor(st[:, 0] * width).astype(int), 0, width - 1)
    row_from_bottom = np.clip(np.floor(st[:, 1] * height).astype(int), 0, height - 1)
    return image[height - 1 - row_from_bottom, col]


def test_st_maps_a_known_texel(usd_export):
    _, source, stage, _ = usd_export
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/Mesh"))
    st_primvar = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st_primvar.GetInterpolation() == UsdGeom.Tokens.vertex
    st = np.asarray(st_primvar.Get(), dtype=np.float64)
    # the exported albedo PNG read at st must be the sRGB of rho_sss_bar at the vertex's texel
    shader = UsdShade.Shader(stage.GetPrimAtPath("/Face/Looks/Skin/AlbedoTexture"))
    png = read_png(shader.GetInput("file").Get().resolvedPath).astype(np.float64) / 255.0
    expected_image = encode_srgb(np.clip(linear_rgb_from_channels(source.channel_map("rho_sss_bar"),
                                                                  source.rig), 0.0, 1.0))
    mask = source.mask
    height, width = mask.shape
    rows = np.clip(np.floor((1.0 - source.mesh.uv[:, 1]) * height).astype(int), 0, height - 1)
    cols = np.clip(np.floor(source.mesh.uv[:, 0] * width).astype(int), 0, width - 1)
    inside = mask[rows, cols]
    assert inside.sum() > 100
    got = _usd_texel(png, st[inside])
    expected = expected_image[rows[inside], cols[inside]]
    assert np.median(np.abs(got - expected)) < 1.5 / 255
    flipped = _usd_texel(png, np.stack([st[inside, 0], 1.0 - st[inside, 1]], -1))
    assert np.median(np.abs(flipped - expected)) > 5 * np.median(np.abs(got - expected)) + 1e-3


def test_texture_paths_resolve_and_vary_per_frame(usd_export):
    _, source, stage, _ = usd_export
    looks = "/Face/Looks/Skin"
    times = [Usd.TimeCode.Default()] + [Usd.TimeCode(float(f)) for f in source.frames]
    for name in ("AlbedoTexture", "NormalTexture", "OuterHaemoglobinTexture", "RoughnessTexture",
                 "SpecularTexture"):
        attribute = UsdShade.Shader(stage.GetPrimAtPath(f"{looks}/{name}")).GetInput("file").GetAttr()
        paths = [attribute.Get(t).resolvedPath for t in times]
        assert all(paths) and all(Path(p).is_file() for p in paths), (name, paths)
        if name in ("AlbedoTexture", "NormalTexture", "OuterHaemoglobinTexture"):
            assert len(set(paths)) == len(times), name  # a file per frame, static as the default
    # the C_h,out texture at each frame decodes (scale input) to that frame's map
    shader = UsdShade.Shader(stage.GetPrimAtPath(f"{looks}/OuterHaemoglobinTexture"))
    scale = shader.GetInput("scale").Get()[0]
    for frame in source.frames:
        frame_source = source.frame(frame)
        decoded = read_png(shader.GetInput("file").Get(float(frame)).resolvedPath) / 65535.0 * scale
        mask = frame_source.mask
        np.testing.assert_allclose(decoded[mask], frame_source.scalar_map("c_h_out")[mask], atol=1e-5)
    surface = UsdShade.Material(stage.GetPrimAtPath(looks)).ComputeSurfaceSource()[0]
    assert surface.GetIdAttr().Get() == "UsdPreviewSurface"
    bound = UsdShade.MaterialBindingAPI(stage.GetPrimAtPath("/Face/Mesh")).ComputeBoundMaterial()[0]
    assert bound.GetPath() == looks


def test_usd_validation_reports_no_error(usd_export):
    _, _, stage, _ = usd_export
    validation = pytest.importorskip("pxr.UsdValidation", reason="usd-core without UsdValidation")
    validators = validation.ValidationRegistry().GetOrLoadAllValidators()
    assert len(validators) > 10
    errors = validation.ValidationContext(validators).Validate(stage)
    serious = [e.GetMessage() for e in errors if e.GetType() == validation.ValidationErrorType.Error]
    assert serious == []


def test_tangent_space_normal_of_a_tilted_plane(tiny_export):
    _, result = tiny_export
    source = ExportSource.open(result)
    raster = rasterize_uv(source.mesh, source.mask.shape)
    slope = 0.02  # mm of height per texel column
    height = slope * np.arange(raster.mask.shape[1], dtype=np.float64)[None].repeat(raster.mask.shape[0], 0)
    normals = tangent_space_normals(height, source.mask, raster)
    mask = source.mask & raster.mask
    interior = mask & np.roll(mask, 1, 1) & np.roll(mask, -1, 1) & np.roll(mask, 1, 0) & np.roll(mask, -1, 0)
    s_u, s_v = raster.texel_size_u[interior], raster.texel_size_v[interior]
    expected = np.stack([-s_v * slope, np.zeros_like(s_u), s_u * s_v], -1)
    expected /= np.linalg.norm(expected, axis=-1, keepdims=True)
    np.testing.assert_allclose(normals[interior], expected, atol=1e-6)
    np.testing.assert_array_equal(normals[~mask], np.tile([0.0, 0.0, 1.0], ((~mask).sum(), 1)))


def test_a_result_without_a_frame_map_is_refused_by_name(tiny_export, tmp_path):
    _, result = tiny_export
    copy = tmp_path / "r"
    shutil.copytree(result, copy, ignore=shutil.ignore_patterns("unwrap.zarr", "checkpoints", "previews"))
    (copy / "frames" / "0001" / "maps" / "displacement_mm.exr").unlink()
    with pytest.raises(MissingMapError, match=r"'usd' needs .*frames/0001/maps/displacement_mm\.exr"):
        export_result(copy, tmp_path / "out", ExportOptions(formats=("usd",)))
    assert not (tmp_path / "out" / "usd").exists()


def test_a_static_result_has_no_time_samples(tiny_export, tmp_path):
    _, result = tiny_export
    from polarface.export.usd import write_usd

    source = ExportSource.open(result, frames=[])
    record = write_usd(source, tmp_path, ExportOptions(formats=("usd",)))
    stage = Usd.Stage.Open(str(tmp_path / record["root"]))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/Mesh"))
    assert list(mesh.GetPointsAttr().GetTimeSamples()) == []
    np.testing.assert_allclose(np.asarray(mesh.GetPointsAttr().Get()), source.mesh.vertices, atol=1e-3)
    for path in record["files"]:
        assert (tmp_path / path).is_file(), path
