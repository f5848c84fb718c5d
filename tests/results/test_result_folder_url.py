"""A RESULT folder at an fsspec URL (memory://, file://): every artifact written there reads back as the
same bytes and arrays as a local folder's; an unrenderable URL is refused naming it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from disk_fixtures import plane_mesh
from polarface.capture.rig import paper_rig
from polarface.io import UrlPath, storage_path
from polarface.results import (
    CHROMOPHORE_MAPS,
    POLARIMETRIC_MAPS,
    RHO_SSS_BAR,
    ResultAppearance,
    ResultFolder,
)
from polarface.results.layout import SOG_LAYERS
from storage_fixtures import memory_keys

NAMES = ["B", "G", "R", "b", "g", "r"]
SHAPE = (12, 10)


def _write_result(root) -> ResultFolder:
    """A RESULT with every kind of artifact: header and stage records, polarimetric maps with previews
    and a diagnostic map, chromophore maps, sog.json, the loss curve, mesh, rig, one frame folder."""
    rng = np.random.default_rng(3)
    folder = ResultFolder(root)
    folder.write_result_header(NAMES, SHAPE, 0.5)
    mask = np.zeros(SHAPE, bool)
    mask[2:10, 1:8] = True
    maps = {name: rng.uniform(0.1, 1.0, SHAPE) for name in POLARIMETRIC_MAPS}
    maps[RHO_SSS_BAR] = rng.uniform(0.0, 1.0, (*SHAPE, 6))
    folder.write_polarimetric_maps(maps, mask, {"view_count": rng.integers(0, 9, SHAPE).astype(float)})
    for name in CHROMOPHORE_MAPS:
        folder.write_scalar_map(name, rng.uniform(0.0, 0.1, SHAPE).astype(np.float32))
    layers = {k: np.full((2, 9), 0.1).tolist() for k in SOG_LAYERS}
    folder.write_sog({"format": "polarface-sog", "layers": layers})
    folder.write_loss_curve([3.0, 2.0, 1.5])
    folder.write_mesh(plane_mesh(cells=2))
    paper_rig(width=32, height=24).save(folder.rig_path)
    folder.record_stage("polarimetric", {"texels": int(mask.sum())})
    frame = folder.frame(3)
    frame.write_scalar_map("eta", maps["eta"].astype(np.float32))
    frame.write_mask(mask)
    return folder


def _files(root) -> dict[str, bytes]:
    root = storage_path(root)
    if isinstance(root, UrlPath):
        return {key: (root / key).read_bytes() for key in memory_keys(str(root))}
    files = sorted(p for p in Path(root).rglob("*") if p.is_file())
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in files}


@pytest.fixture(scope="module")
def local_result(tmp_path_factory):
    return _write_result(tmp_path_factory.mktemp("result") / "RESULT")


@pytest.mark.parametrize("scheme", ["memory", "file"])
def test_a_result_at_a_url_round_trips(scheme, memory_url, tmp_path, local_result):
    url = f"{memory_url}/RESULT" if scheme == "memory" else f"file://{tmp_path}/RESULT"
    written = _write_result(url)
    assert isinstance(written.root, UrlPath) == (scheme == "memory")
    local_files = _files(local_result.root)
    assert _files(written.root) == local_files  # same keys, same bytes: nothing half-written, no temporaries
    assert any(name.startswith("previews/") for name in local_files)
    folder = ResultFolder(url)
    assert folder.read_result() == local_result.read_result()
    assert folder.channel_names() == NAMES and folder.stage_complete("polarimetric")
    expected, got = local_result.read_maps(NAMES), folder.read_maps(NAMES)
    assert sorted(got) == sorted(expected)
    for name, values in expected.items():
        np.testing.assert_array_equal(got[name], values)
    np.testing.assert_array_equal(folder.read_loss_curve(), [3.0, 2.0, 1.5])
    assert folder.read_sog() == local_result.read_sog()
    np.testing.assert_array_equal(folder.read_mesh().vertices, local_result.read_mesh().vertices)
    assert folder.read_rig() == local_result.read_rig()
    assert folder.frame_indices() == [3]
    np.testing.assert_array_equal(folder.frame(3).read_mask(), local_result.frame(3).read_mask())
    assert folder.frame(3).mesh_path == folder.root / "mesh.obj"  # a frame shares the sequence's mesh
    appearance = ResultAppearance.load(url)
    np.testing.assert_array_equal(appearance.maps["c_m"], local_result.read_scalar_map("c_m"))


def test_missing_maps_and_bad_urls_are_named(memory_url):
    folder = ResultFolder(f"{memory_url}/EMPTY")
    assert folder.read_result() == {} and folder.frame_indices() == []
    with pytest.raises(FileNotFoundError, match=f"'{memory_url}/EMPTY/maps/eta.exr' does not exist"):
        folder.read_scalar_map("eta")
    with pytest.raises(ValueError, match="storage URL 'nosuchfs://bucket/RESULT': unknown protocol"):
        ResultFolder("nosuchfs://bucket/RESULT")


def test_render_reads_and_writes_urls_like_local_folders(tmp_path, memory_url, capsys, monkeypatch):
    """``polarface render URL --out URL``: the images of the local RESULT's render. ``memory://`` stands in
    for object storage (the command line refuses it: it lives in one process only, so here it is allowed)."""
    monkeypatch.setattr("polarface.io.storage.PROCESS_PRIVATE_PROTOCOLS", frozenset())
    from disk_fixtures import write_plane_result
    from polarface.cli import main
    from storage_fixtures import upload_tree

    local = write_plane_result(tmp_path / "result", resolution=16)
    url = str(upload_tree(local, f"{memory_url}/result"))
    options = ["--no-mueller", "--no-strip", "--exposure", "1.0"]
    assert main(["render", str(local), "--out", str(tmp_path / "out"), *options]) == 0
    assert main(["render", url, "--out", f"{memory_url}/out", *options]) == 0
    expected, got = _files(tmp_path / "out"), _files(f"{memory_url}/out")
    assert "srgb_linear.exr" in expected and sorted(got) == sorted(expected)
    different = [name for name in expected if got[name] != expected[name]]
    assert different == ["render.json"]  # its "seconds" only
    assert json.loads(got["render.json"])["pixels"] == json.loads(expected["render.json"])["pixels"]
    capsys.readouterr()
    with pytest.raises(SystemExit):  # commands that write local folders refuse a URL as --out
        main(["reconstruct", url, "--out", f"{memory_url}/R"])
    assert "writes a local folder" in capsys.readouterr().err
