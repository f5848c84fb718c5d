"""``import-authors`` on a small synthetic session in the authors' layout: the imported unwrap store holds
the observations computed from the polarizer images, the views the session's cameras and poses; reruns
resume; reconstruct accepts the folder; the CLI refuses partial downloads naming the file."""

from __future__ import annotations

import json

import numpy as np
import pytest

from authors_fixtures import polarizer_stack, write_fake_session
from polarface.capture import paper_rig
from polarface.cli import main
from polarface.pipeline import import_authors, resolve_reconstruct_inputs
from polarface.pipeline.inputs import read_imported
from polarface.texture import UnwrapStore

RES = 8


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    root = tmp_path_factory.mktemp("authors")
    session = write_fake_session(root / "5_Static" / "90", frames=2, resolution=RES)
    record = import_authors(session, root / "imported", progress=False)
    return session, root / "imported", record


def test_record_and_files(imported) -> None:
    _, out, record = imported
    assert record["kind"] == "static" and record["frames"] == ["0000", "0001"] and record["complete"]
    assert record["texture_resolution"] == [RES, RES] and record["views"] == 4
    for name in ("rig.json", "mesh.obj", "poses.json", "unwrap.zarr"):
        assert (out / name).exists(), name
    assert read_imported(out, "static")["session"] == record["session"]
    with pytest.raises(ValueError, match="imported static session; a dynamic one"):
        read_imported(out, "dynamic")


def test_observations_are_the_polarizer_combinations(imported) -> None:
    _, out, _ = imported
    store = UnwrapStore.open(out / "unwrap.zarr")
    obs, valid, lit = store.read(slice(None), slice(None))
    assert valid.all() and lit.all()
    for index, view in enumerate(store.views):
        camera = int(view.camera_id[-1])
        i0, i45, i90, i135 = polarizer_stack(view.frame, camera, RES).astype(np.float64)
        expected = np.stack([2 * i90, i135 - i45, i0 - i90], axis=-2)
        np.testing.assert_allclose(obs[index], expected, rtol=1e-5, atol=1e-7)
        assert view.channels == ((0, 1, 2) if camera == 1 else (3, 4, 5))


def test_views_carry_the_session_cameras(imported) -> None:
    _, out, _ = imported
    store = UnwrapStore.open(out / "unwrap.zarr")
    centres = [c.centre_mm for c in paper_rig(width=48, height=32).polarimetric_cameras()]
    for view in store.views:  # identity ICP poses: model frame = world
        np.testing.assert_allclose(view.camera_center, centres[int(view.camera_id[-1]) - 1], atol=1e-9)
        assert not view.held_out


def test_rerun_resumes_and_keeps_the_store(imported, tmp_path) -> None:
    session, out, _ = imported
    target = tmp_path / "again"
    import_authors(session, target, progress=False)
    store = UnwrapStore.open(target / "unwrap.zarr", mode="a")
    store.root.attrs["done"] = [0]  # as if interrupted after the first view
    store.root.attrs["complete"] = False
    (target / "unwrap.zarr").rename(target / "unwrap.zarr.partial")
    record = json.loads((target / "imported.json").read_text())  # as an interrupted import leaves it
    (target / "imported.json").write_text(json.dumps({**record, "complete": False}))
    (target / "mesh.obj").unlink()
    import_authors(session, target, progress=False)
    first = UnwrapStore.open(out / "unwrap.zarr").read(slice(None), slice(None))
    second = UnwrapStore.open(target / "unwrap.zarr").read(slice(None), slice(None))
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a, b)


def test_reconstruct_inputs_of_an_imported_folder(imported) -> None:
    _, out, _ = imported
    inputs = resolve_reconstruct_inputs(out)
    assert inputs.mesh_path == out / "mesh.obj" and inputs.poses_path == out / "poses.json"
    assert inputs.texture_resolution == RES
    with pytest.raises(ValueError, match="own geometry"):
        resolve_reconstruct_inputs(out, geometry=out)


def test_dynamic_session_import(tmp_path) -> None:
    session = write_fake_session(tmp_path / "6_Dynamic_1" / "90", frames=2, resolution=RES, dynamic=True)
    record = import_authors(session, tmp_path / "dyn", progress=False)
    assert record["kind"] == "dynamic" and record["frames"] == ["0000", "0001"]
    store = UnwrapStore.open(tmp_path / "dyn" / "frames" / "0001" / "unwrap.zarr")
    assert [v.frame for v in store.views] == [1, 1] and store.complete
    assert (tmp_path / "dyn" / "frames" / "0001" / "mesh.obj").is_file()


def test_cli_imports_and_refuses_a_partial_download(tmp_path, capsys) -> None:
    session = write_fake_session(tmp_path / "s", frames=1, resolution=4)
    assert main(["import-authors", str(session), "--out", str(tmp_path / "ok"), "--no-progress"]) == 0
    assert json.loads(capsys.readouterr().out)["complete"] is True
    (session / "texture" / "135" / "exr" / "visible_img2_0000.exr").unlink()
    assert main(["import-authors", str(session), "--out", str(tmp_path / "bad"), "--no-progress"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and error[0].startswith("polarface import-authors: error:")
    assert "visible_img2_0000.exr" in error[0]
    assert not (tmp_path / "bad").exists()
