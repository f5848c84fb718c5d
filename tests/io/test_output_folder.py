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


# ---- staged outputs (issue 47: no partial output) ------------------------------------------------------
def test_staged_new_folder_appears_only_once_complete(tmp_path):
    out = tmp_path / "a" / "render"
    with pytest.raises(RuntimeError):
        with output_folder(out, "render", staged=True) as folder:
            assert folder != out and folder.parent == out.parent and not out.exists()
            (folder / "srgb.png").write_text("half")
            raise RuntimeError("the render failed")
    assert not out.exists() and list(tmp_path.iterdir()) == []  # no folder, no temporary, no parents
    with pytest.raises(KeyboardInterrupt):
        with output_folder(out, "render", staged=True) as folder:
            (folder / "srgb.png").write_text("half")
            raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []
    with output_folder(out, "render", staged=True) as folder:
        (folder / "srgb.png").write_text("whole")
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "srgb.png"]
    assert sorted(p.name for p in out.parent.iterdir()) == ["render"]
    assert out.stat().st_mode & 0o777 == 0o777 & ~_umask()  # as mkdir would make it, not mkdtemp's 0700


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_staged_own_folder_is_replaced_whole_or_left_as_it_was(tmp_path):
    out = tmp_path / "render"
    with output_folder(out, "render", staged=True) as folder:
        (folder / "old.png").write_text("1")
    with pytest.raises(ValueError):
        with output_folder(out, "render", staged=True) as folder:
            (folder / "new.png").write_text("2")
            raise ValueError("bad")
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "old.png"]
    with output_folder(out, "render", staged=True) as folder:
        (folder / "new.png").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "new.png"]  # no stale file of the old run
    user = tmp_path / "user"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    with pytest.raises(OutputFolderError, match="not written by 'polarface render'"):
        with output_folder(user, "render", staged=True):
            pass
    assert (user / "notes.txt").read_text() == "mine"


def test_staged_empty_folder_is_filled_on_success_only(tmp_path):
    out = tmp_path / "empty"
    out.mkdir()
    with pytest.raises(RuntimeError):
        with output_folder(out, "stokes", staged=True) as folder:
            (folder / "i0.exr").write_text("i")
            raise RuntimeError
    assert out.is_dir() and list(out.iterdir()) == []
    with output_folder(out, "stokes", staged=True) as folder:
        (folder / "i0.exr").write_text("i")
    assert (out / "i0.exr").read_text() == "i"


def test_resumable_commands_keep_what_they_wrote(tmp_path):
    """Not staged (the default): an interrupted run's files stay for the next run to continue."""
    with pytest.raises(KeyboardInterrupt):
        with output_folder(tmp_path / "sim", "simulate") as folder:
            (folder / "frame0.png").write_text("p")
            raise KeyboardInterrupt
    assert (tmp_path / "sim" / "frame0.png").exists()


# ---- outputs apart from inputs (issue 47: data lost) --------------------------------------------------
def _result(root):
    root.mkdir(parents=True)
    (root / "result.json").write_text("{}")
    return root


def test_output_that_is_contains_or_lies_inside_an_input_is_refused(tmp_path):
    result = _result(tmp_path / "result")
    inputs = {"RESULT": result}
    for out, relation in ((result, "is"), (tmp_path, "contains"), (result / "maps", "lies inside")):
        expected = rf"argument '--out': '{out}' {relation} the input RESULT"
        with pytest.raises(OutputFolderError, match=expected):
            with output_folder(out, "export", force=True, inputs=inputs):
                pass
    assert sorted(p.name for p in result.iterdir()) == ["result.json"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result"]
    with output_folder(tmp_path / "elsewhere", "export", inputs=inputs) as folder:
        assert folder == tmp_path / "elsewhere"


def test_an_inputs_reserved_sub_folder_is_allowed(tmp_path):
    result = _result(tmp_path / "result")
    reserved = (result / "exports",)
    for out in (result / "exports", result / "exports" / "mitsuba"):
        with output_folder(out, "export", staged=True, inputs={"RESULT": result}, reserved=reserved):
            pass
    with pytest.raises(OutputFolderError, match=r"lies inside the input RESULT .* \(or '.*exports'\)"):
        with output_folder(result / "render", "export", inputs={"RESULT": result}, reserved=reserved):
            pass


def test_inputs_are_compared_after_resolving_links_and_in_lists(tmp_path):
    result = _result(tmp_path / "result")
    (tmp_path / "link").symlink_to(result)
    with pytest.raises(OutputFolderError, match="is the input RESULT"):
        with output_folder(tmp_path / "link", "export", force=True, inputs={"RESULT": result}):
            pass
    raw = tmp_path / "raw" / "frame.png"
    raw.parent.mkdir()
    raw.write_bytes(b"png")
    with pytest.raises(OutputFolderError, match=r"argument '--figures': .* contains the input --images"):
        with output_folder(raw.parent, "stokes", force=True, argument="--figures",
                           inputs={"--images": [str(tmp_path / "other.png"), raw], "--rig": None}):
            pass
    assert raw.read_bytes() == b"png"


def test_output_file_is_never_an_input_nor_inside_one(tmp_path):
    result = _result(tmp_path / "result")
    for target in (result / "result.json", result / "metrics.json"):
        with pytest.raises(OutputFolderError, match="argument '--out'"):
            with output_file(target, "evaluate", force=True, inputs={"RESULT": result, "--gt": None}):
                pass
    assert sorted(p.name for p in result.iterdir()) == ["result.json"]
    with output_file(tmp_path / "metrics.json", "evaluate", inputs={"RESULT": result}) as path:
        assert path == tmp_path / "metrics.json"


def test_foreign_folder_without_force_option_does_not_suggest_it(tmp_path):
    paper = tmp_path / "paper"
    paper.mkdir()
    (paper / "geometry_error_mm.png").write_text("the user's figure")
    with pytest.raises(OutputFolderError, match=r"choose another --figures$"):
        with output_folder(paper, "evaluate", force=None, staged=True, argument="--figures"):
            pass
    assert (paper / "geometry_error_mm.png").read_text() == "the user's figure"
