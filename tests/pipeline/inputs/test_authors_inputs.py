"""``import-authors`` and bad input (issue 47's bad-input campaign): a bad ``cameras.txt`` / ``images.txt``
named with its line (was a pydantic dump), an unreadable, truncated or wrongly sized EXR refused before
anything is written (was a half-written import), one error line with ``--force`` too, a rerun into its own
folder with another session refused (was silently overwritten in part) while the same session resumes, and
a chunk deleted from an imported unwrap store refused by ``reconstruct`` (was fitted from zarr's fill
values)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from authors_fixtures import write_fake_session
from polarface.capture.authors_checks import exr_header
from polarface.cli import main
from polarface.io import write_exr
from polarface.pipeline import import_authors, resolve_reconstruct_inputs
from polarface.pipeline.inputs import ImportStoppedError, read_imported
from polarface.texture import UnwrapStore

RES = 8


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> tuple[Path, Path, Path]:
    """``(session, other session, its import)``: two static sessions of 2 frames, the first imported."""
    root = tmp_path_factory.mktemp("authors_inputs")
    session = write_fake_session(root / "a" / "5_Static" / "90", frames=2, resolution=RES)
    other = write_fake_session(root / "b" / "5_Static" / "90", frames=2, resolution=RES)
    (other / "images.txt").write_text((other / "images.txt").read_text().replace(" 0.0 0.899", " 0.5 0.899"))
    import_authors(session, root / "imported", progress=False)
    return session, other, root / "imported"


def _copy(source: Path, target: Path) -> Path:
    shutil.copytree(source, target)
    return target


def _cli(session: Path, out: Path, *extra: str) -> int:
    return main(["import-authors", str(session), "--out", str(out), "--no-progress", *extra])


def _error_line(capfd) -> str:
    captured = capfd.readouterr()
    lines = [line for line in (captured.err + captured.out).splitlines() if line.strip()]
    assert len(lines) == 1, lines
    assert lines[0].startswith("polarface import-authors: error:")
    return lines[0]


@pytest.mark.parametrize(
    ("name", "old", "new", "message"),
    [
        ("cameras.txt", "1 OPENCV 48 32 192.0", "1 OPENCV 48 32 -5.0", r"txt' line 3: camera 1 focal"),
        ("cameras.txt", "2 OPENCV 48 32 192.0", "2 OPENCV 48 32 nan", r"txt' line 4: camera 2 param"),
        ("cameras.txt", "2 OPENCV 48 32", "2 OPENCV 0 32", r"cameras\.txt' line 4: camera 2 size 0 x 32"),
        ("cameras.txt", "2 OPENCV 48", "1 OPENCV 48", r"txt' line 4: camera 1 is listed again \(line 3\)"),
        ("cameras.txt", "2 OPENCV 48 32 192.0", "2 OPENCV 48 32 abc", r"cameras\.txt' line 4: malformed"),
        ("images.txt", "1 0.99988", "1 0 0 0 0 X", r"images\.txt' line 4: malformed image line"),
        ("images.txt", "2 0.9998875695602899", "2 nan", r"images\.txt' line 6: image 2 quaternion and"),
    ],
    ids=["negative-focal", "nan", "zero-width", "camera-twice", "malformed-camera", "malformed-image",
         "nan-pose"],
)
def test_bad_colmap_file_names_the_file_and_line(sessions, tmp_path, capfd, name, old, new, message):
    session = _copy(sessions[0], tmp_path / "session")
    text = (session / name).read_text()
    assert old in text
    (session / name).write_text(text.replace(old, new, 1))
    assert _cli(session, tmp_path / "out") == 2
    line = _error_line(capfd)
    assert str(session / name) in line and "validation error" not in line
    assert re.search(message, line), line
    assert not (tmp_path / "out").exists()


def test_zero_quaternion_is_named(sessions, tmp_path, capfd):
    session = _copy(sessions[0], tmp_path / "session")
    lines = (session / "images.txt").read_text().splitlines()
    tokens = lines[3].split()
    lines[3] = " ".join([tokens[0], "0", "0", "0", "0", *tokens[5:]])
    (session / "images.txt").write_text("\n".join(lines) + "\n")
    assert _cli(session, tmp_path / "out") == 2
    assert "images.txt' line 4: image 1 has the zero quaternion" in _error_line(capfd)


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:-10])


def _garbage(path: Path) -> None:
    path.write_bytes(b"not an exr at all")


def _small(path: Path) -> None:
    write_exr(path, np.ones((4, 4, 3), np.float32))


def _two_channels(path: Path) -> None:
    write_exr(path, {"R": np.ones((RES, RES), np.float32), "G": np.ones((RES, RES), np.float32)})


@pytest.mark.parametrize(
    ("spoil", "message"),
    [(_truncate, "is truncated"), (_garbage, "is not an OpenEXR file"),
     (_small, "is 4x4 texels; the texture is 8x8"),
     (_two_channels, r"lacks channel\(s\) \['B'\]")],
    ids=["truncated", "garbage", "size", "channels"],
)
@pytest.mark.parametrize("force", [False, True], ids=["new", "force"])
def test_bad_exr_is_refused_before_anything_is_written(sessions, tmp_path, capfd, spoil, message, force):
    session, _, imported = sessions
    session = _copy(session, tmp_path / "session")
    bad = session / "texture" / "45" / "exr" / "img2_0001.exr"  # the last view's: found before any write
    spoil(bad)
    out = _copy(imported, tmp_path / "out") if force else tmp_path / "out"
    before = sorted(p.name for p in out.iterdir()) if force else None
    assert _cli(session, out, *(["--force"] if force else [])) == 2
    line = _error_line(capfd)
    assert str(bad) in line and re.search(message, line), line
    if force:  # the import that --force replaces is untouched
        assert sorted(p.name for p in out.iterdir()) == before and read_imported(out)["complete"]
    else:
        assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp-")]


def test_exr_header_finds_every_truncation(tmp_path):
    path = tmp_path / "map.exr"
    write_exr(path, np.random.default_rng(0).random((40, 24, 3)).astype(np.float32))
    header = exr_header(path)
    assert header.channels == ("B", "G", "R") and (header.height, header.width) == (40, 24)
    data = path.read_bytes()
    cut = tmp_path / "cut.exr"
    sizes = sorted({*range(0, 400), *range(400, len(data), 97), *range(len(data) - 100, len(data))})
    for size in sizes:  # the header, the offset table, every chunk and the end of the last one
        cut.write_bytes(data[:size])
        try:
            exr_header(cut)
        except ValueError as exc:
            assert "cut.exr" in str(exc)
        else:
            raise AssertionError(f"a file cut to {size} of {len(data)} bytes passed")


def test_pixels_that_fail_to_decode_leave_a_resumable_import(sessions, tmp_path, capfd):
    session, _, imported = sessions
    session = _copy(session, tmp_path / "session")
    bad = session / "texture" / "45" / "exr" / "img2_0001.exr"
    good = bad.read_bytes()
    damaged = bytearray(good)
    damaged[-60:-4] = bytes(56)  # the compressed pixels of the last chunk: the structure is intact
    bad.write_bytes(bytes(damaged))
    out = tmp_path / "out"
    with pytest.raises(ImportStoppedError, match=r"img2_0001\.exr"):
        import_authors(session, out, progress=False)
    shutil.rmtree(out)
    capfd.readouterr()
    assert _cli(session, out) == 2
    captured = capfd.readouterr()
    line = next(line for line in captured.err.splitlines()
                if line.startswith("polarface import-authors: error:"))
    assert str(bad) in line and "kept in" in line and "rerun the same command" in line
    record = json.loads((out / "imported.json").read_text())
    assert record["complete"] is False and (out / "unwrap.zarr.partial").is_dir()
    with pytest.raises(ValueError, match="interrupted"):
        read_imported(out)
    bad.write_bytes(good)  # the file replaced: the rerun resumes (the changed file was not imported yet)
    assert _cli(session, out) == 0
    capfd.readouterr()
    first = UnwrapStore.open(imported / "unwrap.zarr").read(slice(None), slice(None))
    second = UnwrapStore.open(out / "unwrap.zarr").read(slice(None), slice(None))
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a, b)


def test_pixels_that_fail_to_decode_are_one_error_line(sessions, tmp_path, capfd):
    session = _copy(sessions[0], tmp_path / "session")
    bad = session / "texture" / "45" / "exr" / "img2_0001.exr"
    damaged = bytearray(bad.read_bytes())
    damaged[-60:-4] = bytes(56)
    bad.write_bytes(bytes(damaged))
    capfd.readouterr()
    assert _cli(session, tmp_path / "out") == 2
    assert str(bad) in _error_line(capfd)


def test_rerun_with_another_session_is_refused_and_the_same_resumes(sessions, tmp_path, capfd):
    session, other, imported = sessions
    out = _copy(imported, tmp_path / "out")
    record = read_imported(out)
    assert _cli(other, out) == 2
    line = _error_line(capfd)
    assert "holds an import of another session" in line and "images.txt differs" in line and "--force" in line
    assert read_imported(out) == record  # untouched
    assert _cli(session, out) == 0  # the same session: the finished import is kept as it is
    assert json.loads(capfd.readouterr().out)["complete"] is True
    assert read_imported(out) == record
    # another frame list, and an image already imported that changed, are named too
    changed = _copy(session, tmp_path / "changed")
    write_exr(changed / "texture" / "0" / "exr" / "img1_0000.exr", np.ones((RES, RES, 3), np.float32))
    with pytest.raises(ValueError, match=r"texture/0/exr/img1_0000\.exr \(\d+ bytes; imported: \d+ bytes\)"):
        import_authors(changed, out, progress=False)
    longer = write_fake_session(tmp_path / "longer", frames=3, resolution=RES)
    with pytest.raises(ValueError, match=r"its frames are 2 \(0000\.\.0001\), the session's 3"):
        import_authors(longer, out, progress=False)
    assert _cli(other, out, "--force") == 0
    capfd.readouterr()
    assert read_imported(out)["inputs"]["text"]["images.txt"] != record["inputs"]["text"]["images.txt"]


def test_dynamic_rerun_with_another_session_is_refused(tmp_path):
    session = write_fake_session(tmp_path / "a", frames=2, resolution=RES, dynamic=True)
    other = write_fake_session(tmp_path / "b", frames=2, resolution=RES, dynamic=True)
    write_exr(other / "texture" / "tracked" / "vertex_0001.exr", np.zeros((RES, RES, 3), np.float32))
    import_authors(session, tmp_path / "dyn", progress=False)
    with pytest.raises(ValueError, match=r"tracked/vertex_0001\.exr"):
        import_authors(other, tmp_path / "dyn", progress=False)
    static = write_fake_session(tmp_path / "static", frames=2, resolution=RES)
    with pytest.raises(ValueError, match="holds a dynamic session, not a static one"):
        import_authors(static, tmp_path / "dyn", progress=False)


def test_deleted_unwrap_chunk_is_refused_before_reconstruct_writes(sessions, tmp_path, capfd):
    _, _, imported = sessions
    out = _copy(imported, tmp_path / "imported")
    chunk = out / "unwrap.zarr" / "obs" / "c" / "2" / "0" / "0" / "0" / "0"
    chunk.unlink()
    with pytest.raises(ValueError, match=r"'unwrap\.zarr/obs' view 2 holds 0 chunk file\(s\).*--force") \
            as info:
        read_imported(out, "static")
    assert "\n" not in str(info.value) and str(out) in str(info.value)
    with pytest.raises(ValueError, match="view 2"):
        resolve_reconstruct_inputs(out)
    assert main(["reconstruct", str(out), "--out", str(tmp_path / "result")]) == 2
    captured = capfd.readouterr()
    errors = [line for line in captured.err.splitlines() if "error" in line]
    assert len(errors) == 1 and "unwrap.zarr/obs' view 2" in errors[0]
    assert not (tmp_path / "result").exists()
    assert _cli(imported.parent / "a" / "5_Static" / "90", out) == 2  # a rerun does not hide it either
    assert "--force" in _error_line(capfd)


def test_deleted_chunk_of_a_dynamic_frame_is_named(tmp_path):
    session = write_fake_session(tmp_path / "a", frames=2, resolution=RES, dynamic=True)
    import_authors(session, tmp_path / "dyn", progress=False)
    store = tmp_path / "dyn" / "frames" / "0001" / "unwrap.zarr"
    next(p for p in sorted((store / "valid" / "c").rglob("*")) if p.is_file()).unlink()
    with pytest.raises(ValueError, match=r"frames/0001: 'unwrap\.zarr/valid' view \d+ holds"):
        read_imported(tmp_path / "dyn", "dynamic")


def test_info_describes_an_imported_session(sessions, tmp_path, capsys):
    _, _, imported = sessions
    assert main(["info", str(imported)]) == 0
    text = capsys.readouterr().out
    assert text.startswith(f"imported session {imported}") and "as the import wrote them" in text
    assert "static session (complete)" in text and "4 views, texture 8 x 8 texels" in text
    out = _copy(imported, tmp_path / "imported")
    (out / "unwrap.zarr" / "lit" / "c" / "0" / "0" / "0" / "0").unlink()
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["kind"] == "imported" and "'unwrap.zarr/lit' view 0" in info["stores"]
