"""The export source: missing maps named before anything is written, frame selection checked."""

from __future__ import annotations

import shutil

import pytest

from polarface.export import EXPORT_FORMATS, ExportSource, MissingMapError


def test_every_format_finds_its_maps_in_a_full_result(tiny_export):
    _, result = tiny_export
    source = ExportSource.open(result)
    assert source.frames == (0, 1)
    for spec in EXPORT_FORMATS.values():
        source.require(spec.maps, spec.name, frames=spec.frames)


def test_a_missing_map_is_named(tiny_export, tmp_path):
    _, result = tiny_export
    copy = tmp_path / "r"
    shutil.copytree(result, copy, ignore=shutil.ignore_patterns("unwrap.zarr"))
    (copy / "maps" / "eta.exr").unlink()
    (copy / "frames" / "0001" / "maps" / "c_h_out.exr").unlink()
    source = ExportSource.open(copy)
    with pytest.raises(MissingMapError, match=r"'gltf' needs '.*maps/eta\.exr'"):
        source.require(EXPORT_FORMATS["gltf"].maps, "gltf")
    with pytest.raises(MissingMapError, match=r"frames/0001/maps/c_h_out\.exr"):
        source.require(EXPORT_FORMATS["usd"].maps, "usd")


def test_bad_frame_selection_and_folder(tiny_export, tmp_path):
    _, result = tiny_export
    with pytest.raises(ValueError, match=r"argument 'frames': \[5\]"):
        ExportSource.open(result, [0, 5])
    with pytest.raises(FileNotFoundError, match="not a RESULT folder"):
        ExportSource.open(tmp_path)
