"""polarface.io.storage: local paths and fsspec URLs, files put whole, clear errors for bad URLs."""

from __future__ import annotations

import importlib.util
import pickle
from pathlib import Path

import numpy as np
import pytest

from polarface.io import (
    UrlPath,
    atomic_path,
    image_header,
    is_url,
    local_copy,
    read_exr,
    read_json_object,
    read_png,
    storage_path,
    write_exr,
    write_json_atomic,
    write_png,
)
from polarface.io.storage import remove_tree
from storage_fixtures import memory_keys


def test_local_paths_and_file_urls_are_paths(tmp_path):
    assert storage_path(str(tmp_path)) == tmp_path
    assert storage_path(f"file://{tmp_path}/a") == tmp_path / "a"
    assert storage_path(tmp_path) is tmp_path
    assert not is_url("relative/dir") and not is_url(str(tmp_path)) and is_url("s3://b/k")


def test_url_path_names_and_joins(memory_url):
    root = storage_path(memory_url + "/")
    assert isinstance(root, UrlPath) and str(root) == memory_url
    child = root / "maps" / "eta.exr"
    assert str(child) == f"{memory_url}/maps/eta.exr"
    assert (child.name, child.stem, child.suffix) == ("eta.exr", "eta", ".exr")
    assert child.parent == root / "maps" and child.with_name("mask.png") == root / "maps" / "mask.png"
    assert child.relative_to(root).as_posix() == "maps/eta.exr"
    assert pickle.loads(pickle.dumps(child)) == child
    with pytest.raises(ValueError, match="absolute"):
        root / "/etc"


@pytest.mark.parametrize("scheme", ["memory", "file"])
def test_images_and_json_round_trip(scheme, memory_url, tmp_path):
    root = storage_path(memory_url if scheme == "memory" else f"file://{tmp_path}")
    values = np.linspace(-1, 3, 30, dtype=np.float32).reshape(5, 6)
    raw = (np.arange(30, dtype=np.uint16).reshape(5, 6) * 1000).astype(np.uint16)
    write_exr(root / "maps" / "eta.exr", {"Y": values})
    write_png(root / "raw.png", raw, bit_depth=16)
    write_json_atomic(root / "result.json", {"format": "x", "values": [1, 2]})
    np.testing.assert_array_equal(read_exr(root / "maps" / "eta.exr")["Y"], values)
    np.testing.assert_array_equal(read_png(root / "raw.png"), raw)
    assert image_header(root / "raw.png") == (6, 5, 1, 16)
    assert read_json_object(root / "result.json") == {"format": "x", "values": [1, 2]}
    assert sorted(p.name for p in root.iterdir()) == ["maps", "raw.png", "result.json"]
    assert [p.name for p in root.glob("*/*.exr")] == ["eta.exr"]
    with local_copy(root / "raw.png") as local:
        assert isinstance(local, Path) and local.read_bytes() == (root / "raw.png").read_bytes()
    remove_tree(root / "maps")
    assert not (root / "maps").exists() and (root / "raw.png").is_file()


def test_missing_files_are_named(memory_url):
    missing = storage_path(memory_url) / "nothing.exr"
    with pytest.raises(FileNotFoundError, match=r"nothing\.exr"):
        read_exr(missing)
    with pytest.raises(FileNotFoundError, match=memory_url):
        missing.read_bytes()


def test_unknown_protocol_names_the_url():
    with pytest.raises(ValueError, match=r"storage URL 'nosuchfs://bucket/x': unknown protocol"):
        storage_path("nosuchfs://bucket/x")


@pytest.mark.skipif(importlib.util.find_spec("s3fs") is not None, reason="s3fs is installed")
def test_missing_protocol_package_names_the_url_and_the_package():
    with pytest.raises(ValueError, match=r"'s3://bucket/capture' needs the package 's3fs'.*pip install s3fs"):
        storage_path("s3://bucket/capture")


# ---- atomicity: a write that fails half-way leaves nothing under the final key ---------------------
def test_a_writer_failing_mid_write_leaves_no_object(memory_url):
    target = storage_path(memory_url) / "maps" / "eta.exr"
    with pytest.raises(RuntimeError, match="killed"), atomic_path(target) as tmp:
        tmp.write_bytes(b"half of an EXR")
        raise RuntimeError("killed mid-write")
    assert not target.exists() and memory_keys(memory_url) == []


def test_an_interrupted_upload_keeps_the_old_object(memory_url, monkeypatch):
    target = storage_path(memory_url) / "result.json"
    write_json_atomic(target, {"version": 1})
    fs = target.fs
    original = fs.pipe_file

    def half_then_fail(path, value, **kwargs):
        original(path, value[: len(value) // 2], **kwargs)  # part of the object reaches the store
        raise ConnectionError("connection lost mid-upload")

    monkeypatch.setattr(fs, "pipe_file", half_then_fail)
    with pytest.raises(ConnectionError):
        write_json_atomic(target, {"version": 2, "padding": "x" * 100})
    monkeypatch.setattr(fs, "put_file", lambda local, path, **kwargs: half_then_fail(path, b"x" * 64))
    with pytest.raises(ConnectionError):  # a staged file (EXR) whose upload breaks off
        write_exr(target, {"Y": np.zeros((2, 2), np.float32)})
    monkeypatch.undo()
    monkeypatch.setattr(fs, "mv", lambda *a, **k: (_ for _ in ()).throw(OSError("mv failed")))
    with pytest.raises(OSError, match="mv failed"):
        write_exr(target.with_name("eta.exr"), {"Y": np.zeros((2, 2), np.float32)})
    monkeypatch.undo()
    assert read_json_object(target) == {"version": 1}
    assert memory_keys(memory_url) == ["result.json"]  # no temporary key left behind


def test_process_private_urls_are_recognised():
    """``memory://`` lives inside one process (issue 47: outputs that vanish): the CLI refuses it."""
    from polarface.io.storage import process_private, url_protocols

    assert url_protocols("simplecache::s3://bucket/key") == ("simplecache", "s3")
    assert url_protocols("relative/dir") == () and url_protocols(Path("/x")) == ()
    assert process_private("memory://cap") == "memory"
    assert process_private("simplecache::memory://cap") == "memory"
    assert process_private(storage_path("memory://cap")) == "memory"
    for value in ("s3://bucket/key", "file:///tmp/x", "/tmp/memory:", "memory:"):
        assert process_private(value) is None
