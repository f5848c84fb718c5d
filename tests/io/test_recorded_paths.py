"""Paths in a folder's records: relative inside the folder, absolute outside, resolved from anywhere."""

import os
import shutil
from pathlib import Path

import pytest

from polarface.io import record_path, recorded_input, resolve_recorded_path
from polarface.io.storage import UrlPath


def test_a_path_inside_the_folder_is_recorded_relative_to_it(tmp_path, monkeypatch):
    result = tmp_path / "runs" / "result"
    assert record_path(result, result / "geometry" / "poses.json") == "geometry/poses.json"
    assert record_path(result, result) == "."
    # given relative to the working directory, as a user types it on the command line
    monkeypatch.chdir(tmp_path)
    assert record_path(Path("runs/result"), Path("runs/result/geometry")) == "geometry"
    assert record_path("runs/result", "runs/result/../result/mesh.obj") == "mesh.obj"


def test_a_path_outside_the_folder_is_recorded_absolute(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert record_path("runs/result", "sim/static") == (tmp_path / "sim" / "static").as_posix()
    sibling = (tmp_path / "runs" / "result-2" / "mesh.obj").as_posix()
    assert record_path("runs/result", "runs/result-2/mesh.obj") == sibling
    assert record_path("runs/result", None) is None


def test_urls_are_recorded_relative_inside_a_folder_at_a_url_and_whole_otherwise(tmp_path):
    assert record_path("memory://bucket/result", "memory://bucket/result/maps/eta.exr") == "maps/eta.exr"
    assert record_path("memory://bucket/result", "memory://bucket/sim") == "memory://bucket/sim"
    assert record_path(tmp_path, "memory://bucket/sim") == "memory://bucket/sim"
    assert record_path("memory://bucket/result", tmp_path / "sim") == (tmp_path / "sim").as_posix()
    resolved = resolve_recorded_path("memory://bucket/result", "maps/eta.exr")
    assert isinstance(resolved, UrlPath) and str(resolved) == "memory://bucket/result/maps/eta.exr"


def test_a_moved_folder_resolves_its_records_from_any_working_directory(tmp_path, monkeypatch):
    folder = tmp_path / "a" / "result"
    (folder / "geometry").mkdir(parents=True)
    (folder / "geometry" / "poses.json").write_text("{}")
    value = record_path(folder, folder / "geometry" / "poses.json")
    moved = tmp_path / "b" / "renamed"
    moved.parent.mkdir()
    shutil.move(folder, moved)
    for cwd in (tmp_path, moved, moved / "geometry"):
        monkeypatch.chdir(cwd)
        path = resolve_recorded_path(os.path.relpath(moved, cwd), value)
        assert path.is_file() and path.resolve() == (moved / "geometry" / "poses.json").resolve()


def test_resolving_absolute_empty_and_malformed_values(tmp_path):
    assert resolve_recorded_path(tmp_path, str(tmp_path / "x")) == tmp_path / "x"
    assert resolve_recorded_path(tmp_path, None) is None and resolve_recorded_path(tmp_path, "") is None
    with pytest.raises(ValueError, match="recorded path must be a string; got 3"):
        resolve_recorded_path(tmp_path, 3)


def test_an_older_record_relative_to_the_run_s_working_directory_is_still_found(tmp_path, monkeypatch):
    """Records before relative paths held the path as typed: 'demo_out/result/geometry/poses.json'."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "demo_out" / "result" / "geometry").mkdir(parents=True)
    (tmp_path / "demo_out" / "result" / "geometry" / "poses.json").write_text("{}")
    path = resolve_recorded_path("demo_out/result", "demo_out/result/geometry/poses.json")
    assert path == tmp_path / "demo_out" / "result" / "geometry" / "poses.json"


def test_a_recorded_input_that_is_gone_names_the_record_the_path_and_the_option(tmp_path):
    (tmp_path / "sim").mkdir()
    value = record_path(tmp_path / "result", tmp_path / "sim")
    assert recorded_input(tmp_path / "result", value, record="result.json", key="stages.prepare.capture",
                          remedy="give its new place with --capture") == tmp_path / "sim"
    (tmp_path / "sim").rmdir()
    with pytest.raises(FileNotFoundError) as raised:
        recorded_input(tmp_path / "result", value, record="R/result.json", key="stages.prepare.capture",
                       remedy="give its new place with --capture")
    message = str(raised.value)
    assert "'R/result.json'" in message and "stages.prepare.capture" in message
    assert f"'{value}'" in message and "--capture" in message
    with pytest.raises(FileNotFoundError, match=r"records no stages\.prepare\.capture; give it with"):
        recorded_input(tmp_path, None, record="R/result.json", key="stages.prepare.capture",
                       remedy="give it with --capture")
