"""The one output-folder policy: own/foreign folders, --resume, --force, and the lock beside the output."""

import json
import logging
import os
import subprocess
import sys

import pytest

from polarface.io.output_folder import (
    MARKER,
    OutputFolderError,
    json_manifest,
    lock_output,
    output_file,
    output_folder,
)


def _lock(path):
    return path.parent / f".{path.name}.polarface.lock"


def test_new_folder_gets_marker_and_lock_is_released(tmp_path):
    out = tmp_path / "out"
    with output_folder(out, "stokes") as folder:
        assert folder == out
        assert json.loads((out / MARKER).read_text())["command"] == "stokes"
        assert json.loads(_lock(out).read_text())["pid"] == os.getpid()
        (folder / "a.txt").write_text("a")
    assert not _lock(out).exists()
    with output_folder(out, "stokes") as folder:  # its own folder: rewritten in place
        assert (folder / "a.txt").exists()


def test_foreign_folder_is_refused_and_untouched(tmp_path):
    out = tmp_path / "d"
    out.mkdir()
    (out / "notes.txt").write_text("x")
    with pytest.raises(OutputFolderError, match=r"not empty.*'polarface stokes'.*--force"):
        with output_folder(out, "stokes"):
            pass
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    with output_folder(tmp_path / "o", "stokes") as folder:
        (folder / "i0.exr").write_text("i")
    with pytest.raises(OutputFolderError, match="'polarface render'"):  # another command's folder is foreign
        with output_folder(tmp_path / "o", "render"):
            pass
    assert not list(tmp_path.glob(".*.polarface.lock"))


def test_file_as_folder_is_refused(tmp_path):
    path = tmp_path / "f"
    path.write_text("data")
    with pytest.raises(OutputFolderError, match="is a file"):
        with output_folder(path, "stokes"):
            pass
    assert path.read_text() == "data"


def test_resume_needs_own_folder(tmp_path):
    out = tmp_path / "r"
    out.mkdir()
    (out / "result.json").write_text(json.dumps({"format": "polarface-result"}))
    owned = json_manifest("result.json", format="polarface-result")
    with pytest.raises(OutputFolderError, match="--resume"):
        with output_folder(out, "reconstruct", resume=False, owned=owned, marker=False):
            pass
    with output_folder(out, "reconstruct", resume=True, owned=owned, marker=False) as folder:
        assert folder == out
    assert not (out / MARKER).exists()
    (out / "result.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(OutputFolderError, match="not written by"):
        with output_folder(out, "reconstruct", resume=True, owned=owned, marker=False):
            pass
    with pytest.raises(OutputFolderError, match="exclude"):
        with output_folder(out, "reconstruct", resume=True, force=True, owned=owned):
            pass


def test_force_replaces_only_after_success(tmp_path):
    out = tmp_path / "d"
    out.mkdir()
    (out / "notes.txt").write_text("x")
    with pytest.raises(RuntimeError):
        with output_folder(out, "stokes", force=True) as folder:
            assert folder != out and folder.parent == tmp_path
            (folder / "new.txt").write_text("n")
            raise RuntimeError("the run failed")
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    with output_folder(out, "stokes", force=True) as folder:
        (folder / "new.txt").write_text("n")
        assert (out / "notes.txt").exists()
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "new.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]


def test_failed_run_removes_only_an_empty_folder_it_created(tmp_path):
    with pytest.raises(ValueError):
        with output_folder(tmp_path / "new", "stokes"):
            raise ValueError("bad argument")
    assert not (tmp_path / "new").exists()
    with pytest.raises(KeyboardInterrupt):
        with output_folder(tmp_path / "partial", "simulate") as folder:
            (folder / "frame0.png").write_text("p")
            raise KeyboardInterrupt
    assert (tmp_path / "partial" / "frame0.png").exists()
    assert not _lock(tmp_path / "partial").exists()


def test_lock_held_by_a_live_process_is_refused_naming_its_pid(tmp_path):
    out = tmp_path / "busy"
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        _lock(out).write_text(json.dumps({"pid": holder.pid, "command": "simulate", "path": str(out)}))
        with pytest.raises(OutputFolderError, match=rf"in use by 'polarface simulate' \(pid {holder.pid}\)"):
            with output_folder(out, "simulate"):
                pass
        assert not out.exists()
    finally:
        holder.kill()
        holder.wait()


def test_stale_lock_is_taken_over_with_a_warning(tmp_path, caplog):
    out = tmp_path / "stale"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    _lock(out).write_text(json.dumps({"pid": dead.pid, "command": "simulate", "path": str(out)}))
    with caplog.at_level(logging.WARNING, logger="polarface.io.output_folder"):
        with output_folder(out, "simulate"):
            assert json.loads(_lock(out).read_text())["pid"] == os.getpid()
    assert "stale lock" in caplog.text and str(dead.pid) in caplog.text
    assert not _lock(out).exists()


def test_same_process_cannot_lock_twice(tmp_path):
    with lock_output(tmp_path / "x", "render"):
        with pytest.raises(OutputFolderError, match=f"pid {os.getpid()}"):
            with lock_output(tmp_path / "x", "render"):
                pass


def test_output_file_policy(tmp_path):
    target = tmp_path / "metrics.json"
    target.write_text("user data")
    with pytest.raises(OutputFolderError, match="exists and was not written"):
        with output_file(target, "evaluate", owned=lambda path: path.suffix == ".csv"):
            pass
    with output_file(target, "evaluate", force=True) as path:
        assert path == target
    with pytest.raises(OutputFolderError, match="is a folder"):
        with output_file(tmp_path, "evaluate"):
            pass
    assert target.read_text() == "user data"


def test_failed_run_leaves_no_created_parents(tmp_path):
    with pytest.raises(FileNotFoundError):
        with output_folder(tmp_path / "a" / "b" / "render", "render"):
            raise FileNotFoundError("RESULT 'missing' does not exist")
    assert list(tmp_path.iterdir()) == []
