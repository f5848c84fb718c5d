"""ResultFolder: round trips of every map kind, result.json updates, per-frame folders, errors, atomicity."""

from __future__ import annotations

import json

import numpy as np
import pytest

from polarface.io import read_exr, read_png, write_exr
from polarface.results import (
    CHROMOPHORE_MAPS,
    POLARIMETRIC_MAPS,
    RESULT_FORMAT,
    RHO_SSS_BAR,
    ResultFolder,
    default_channel_names,
    load_sog,
)

NAMES = ["B", "G", "R", "b", "g", "r"]
SHAPE = (12, 10)


def _maps(rng: np.random.Generator) -> dict[str, np.ndarray]:
    maps = {name: rng.uniform(0.1, 1.0, SHAPE) for name in POLARIMETRIC_MAPS}
    maps[RHO_SSS_BAR] = rng.uniform(0.0, 1.0, (*SHAPE, 6))
    return maps


def _mask() -> np.ndarray:
    mask = np.zeros(SHAPE, bool)
    mask[2:10, 1:8] = True
    return mask


def test_polarimetric_maps_round_trip(tmp_path):
    folder = ResultFolder(tmp_path / "result")
    folder.write_result_header(NAMES, SHAPE, 0.5)
    maps, mask = _maps(np.random.default_rng(1)), _mask()
    view_count = np.arange(np.prod(SHAPE)).reshape(SHAPE) % 7
    folder.write_polarimetric_maps(maps, mask, {"view_count": view_count})
    back = folder.read_maps(NAMES)
    for name in (*POLARIMETRIC_MAPS, RHO_SSS_BAR):
        assert back[name].dtype == np.float64
        np.testing.assert_array_equal(back[name], maps[name].astype(np.float32))
    assert np.array_equal(back["mask"], mask)
    assert set(read_exr(folder.map_path(RHO_SSS_BAR))) == set(NAMES)
    np.testing.assert_array_equal(folder.read_scalar_map("view_count"), view_count.astype(np.float32))
    for name in (*POLARIMETRIC_MAPS, "view_count", "rho_sss_bar_rgb"):
        assert folder.preview_path(name).is_file()
    # the channel order comes from the names asked for, not from the file
    swapped = folder.read_channel_map(RHO_SSS_BAR, NAMES[::-1])
    np.testing.assert_array_equal(swapped, maps[RHO_SSS_BAR][..., ::-1].astype(np.float32))


def test_channel_names_default_and_fallback(tmp_path):
    folder = ResultFolder(tmp_path)
    assert folder.channel_names() == default_channel_names() == [f"channel{i}" for i in range(6)]
    folder.write_channel_map(RHO_SSS_BAR, np.zeros((*SHAPE, 2), np.float32), ["x", "a"])
    assert folder.read_channel_map(RHO_SSS_BAR, ["q"], strict=False).shape == (*SHAPE, 2)
    with pytest.raises(ValueError, match=r"rho_sss_bar\.exr.*lacks channel"):
        folder.read_channel_map(RHO_SSS_BAR, ["q"])


def test_scalar_chromophore_mask_loss_sog_round_trip(tmp_path):
    folder = ResultFolder(tmp_path)
    rng = np.random.default_rng(2)
    for name in CHROMOPHORE_MAPS:
        values = rng.uniform(0.0, 0.2, SHAPE).astype(np.float32)
        folder.write_scalar_map(name, values)
        np.testing.assert_array_equal(folder.read_scalar_map(name), values)
    folder.write_mask(_mask(), "in_gamut")
    assert np.array_equal(folder.read_mask(SHAPE, "in_gamut"), _mask())
    assert read_png(folder.map_path("in_gamut", ".png")).max() == 255
    assert folder.read_loss_curve() is None
    folder.write_loss_curve([3.0, 2.0, 1.5])
    np.testing.assert_array_equal(folder.read_loss_curve(), [3.0, 2.0, 1.5])
    assert folder.read_sog() is None
    keys = ("r_out_f", "t_out_f", "r_out_b", "t_out_b", "r_in_f")
    layers = {k: np.full((3, 9), 1 / 9).tolist() for k in keys}
    folder.write_sog({"format": "polarface-sog", "version": 1, "layers": layers})
    shapes = load_sog(folder.map_path("sog", ".json"))
    assert shapes.r_in_f.shape == (3, 9)


def test_result_json_update_and_stage_records(tmp_path):
    folder = ResultFolder(tmp_path)
    assert folder.read_result() == {} and not folder.stage_complete("prepare")
    folder.write_result_header(NAMES, SHAPE, 0.25)
    data = folder.read_result()
    assert data["format"] == RESULT_FORMAT and data["version"] == 1 and data["stages"] == {}
    assert data["texture_resolution"] == list(SHAPE) and folder.channel_names() == NAMES
    folder.record_stage("prepare", {"views": 3})
    assert folder.stage_complete("prepare")
    assert folder.stage_record("prepare") == {"views": 3, "complete": True}
    folder.update_result(defaults={"format": "other", "extra": 1}, stage="biophysical", record={"a": 1})
    data = json.loads(folder.result_json_path.read_text())
    assert data["format"] == RESULT_FORMAT and data["extra"] == 1
    assert data["stages"] == {"prepare": {"views": 3, "complete": True}, "biophysical": {"a": 1}}
    assert not folder.stage_complete("biophysical")


def test_per_frame_folders(tmp_path):
    sequence = ResultFolder(tmp_path)
    (tmp_path / "mesh.obj").write_text("# rest")
    frame = sequence.frame(3)
    assert frame.root == tmp_path / "frames" / "0003" and frame.sequence is sequence
    assert frame.rig_path == tmp_path / "rig.json" and frame.mesh_path == tmp_path / "mesh.obj"
    assert sequence.frame_indices() == []
    values = np.full(SHAPE, 0.5, np.float32)
    frame.write_scalar_map("displacement_mm", values)
    sequence.frame(12).record_stage("polarimetric", {"texels": 4})
    assert sequence.frame_indices() == [3, 12]
    np.testing.assert_array_equal(sequence.frame(3).read_scalar_map("displacement_mm"), values)
    assert not sequence.has_map("displacement_mm")
    assert sequence.frame(12).stage_complete("polarimetric") and not sequence.stage_complete("polarimetric")
    (frame.root / "mesh.obj").write_text("# deformed")
    assert frame.mesh_path == frame.root / "mesh.obj"
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="index"):
            sequence.frame(bad)
    with pytest.raises(ValueError, match="nest"):
        frame.frame(0)


def test_bad_input_errors_name_the_file(tmp_path):
    folder = ResultFolder(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"maps/eta\.exr"):
        folder.read_scalar_map("eta")
    with pytest.raises(FileNotFoundError, match=r"mask '.*mask\.png'"):
        folder.read_mask()
    write_exr(folder.map_path("eta"), {"R": np.zeros(SHAPE, np.float32)})
    with pytest.raises(ValueError, match=r"eta\.exr.*'Y'"):
        folder.read_scalar_map("eta")
    folder.write_mask(_mask())
    with pytest.raises(ValueError, match=r"mask '.*' is \(12, 10\), expected \(4, 4\)"):
        folder.read_mask((4, 4))
    folder.result_json_path.write_text("{not json")
    with pytest.raises(ValueError, match=r"result\.json' is not valid JSON"):
        folder.read_result()
    folder.result_json_path.write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"result\.json' must hold a JSON object"):
        folder.update_result({"x": 1})
    with pytest.raises(FileNotFoundError, match=r"mesh\.obj"):
        folder.read_mesh()


def test_failed_write_leaves_no_partial_file(tmp_path):
    folder = ResultFolder(tmp_path)
    folder.write_scalar_map("eta", np.ones(SHAPE, np.float32))
    with pytest.raises(ValueError):
        folder.write_channel_map(RHO_SSS_BAR, np.ones((*SHAPE, 2), np.float32), [])  # no channels
    with pytest.raises(ValueError, match=r"'maps' lacks \['alpha_s'"):
        folder.write_polarimetric_maps({"eta": np.full(SHAPE, np.nan)}, _mask())
    maps = _maps(np.random.default_rng(3))
    maps["rho_s"] = maps["rho_s"][:4]
    with pytest.raises(ValueError, match="rho_s"):
        folder.write_polarimetric_maps(maps, _mask())
    assert not folder.has_map(RHO_SSS_BAR)
    assert not [p for p in tmp_path.rglob(".tmp-*")]
    np.testing.assert_array_equal(folder.read_scalar_map("eta"), np.ones(SHAPE, np.float32))


def test_diagnostic_maps_must_be_registered_and_match_the_mask(tmp_path):
    folder = ResultFolder(tmp_path)
    maps = _maps(np.random.default_rng(4))
    with pytest.raises(ValueError, match="'dop_max' is not registered in DIAGNOSTIC_MAPS"):
        folder.write_polarimetric_maps(maps, _mask(), {"dop_max": np.zeros(SHAPE)})
    with pytest.raises(ValueError, match=r"'view_count' has shape \(2, 2\)"):
        folder.write_polarimetric_maps(maps, _mask(), {"view_count": np.zeros((2, 2))})
    assert not folder.has_map("eta")


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("format", "other"),
        ("version", 99),
        ("version", True),
        ("channel_names", ["r"]),
        ("channel_names", ["a", "a", "b", "c", "d", "e"]),
        ("texture_resolution", [-1, 0]),
        ("texture_resolution", [16]),
        ("stages", []),
    ],
)
def test_result_json_format_keys_are_validated(tmp_path, key, value):
    folder = ResultFolder(tmp_path)
    folder.write_result_header(NAMES, SHAPE, 0.5)
    data = json.loads(folder.result_json_path.read_text())
    data[key] = value
    folder.result_json_path.write_text(json.dumps(data))
    before = folder.result_json_path.read_bytes()
    with pytest.raises(ValueError, match=rf"result\.json': '{key}'"):
        folder.read_result()
    with pytest.raises(ValueError, match=rf"result\.json': '{key}'"):
        folder.update_result({"x": 1})
    assert folder.result_json_path.read_bytes() == before


def test_read_sog_names_the_file(tmp_path):
    folder = ResultFolder(tmp_path)
    assert folder.read_sog() is None
    folder.map_path("sog", ".json").parent.mkdir(parents=True)
    for text, match in (("", "not valid JSON"), ('{"layers": ', "not valid JSON"), ("[]", "JSON object")):
        folder.map_path("sog", ".json").write_text(text)
        with pytest.raises(ValueError, match=rf"sog\.json' .*{match}"):
            folder.read_sog()


def test_rest_placement_follows_where_the_geometry_came_from(tmp_path):
    from polarface.geometry.head_asset import head_placement

    folder = ResultFolder(tmp_path / "r")
    folder.write_result_header(["c0", "c1", "c2", "c3", "c4", "c5"], (8, 8), 1.0)
    folder.record_stage("prepare", {"geometry": None, "mesh": "given.obj"})
    assert not folder.stereo_geometry()
    assert np.allclose(folder.rest_placement(), head_placement())
    folder.record_stage("prepare", {"geometry": str(tmp_path / "r" / "geometry")})
    assert folder.stereo_geometry() and folder.frame(3).stereo_geometry()
    assert np.array_equal(folder.rest_placement(), np.eye(4))
