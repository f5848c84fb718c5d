"""Checks of an authors' session before an import writes anything, and of an import's stores afterwards.

``polarface import-authors`` (:mod:`polarface.pipeline.inputs.authors`) reads hundreds of EXR images; a
truncated or wrongly sized one found halfway would leave a half-written import. Before anything is
written it therefore reads every EXR's header and offset table (not its pixels; about a millisecond a
file), :func:`check_session_files`:

* :func:`exr_header`: the size and channel names of an OpenEXR file, and, for a single-part scan-line
  file (what OpenCV and the OpenEXR binding write), that its offset table is complete and its last chunk
  ends inside the file: a truncated download or an unfinished write is refused naming the file, without
  OpenEXR's own messages on stderr;
* every observation image has channels R, G, B and the texture's size (that of ``vertex.exr`` or of the
  tracked maps), every visibility map a channel and that size.

:func:`session_fingerprint` is what identifies a session's content cheaply (its text files' SHA-1 and
every EXR's size; the EXR pixels are not hashed: hundreds of megabytes), so that a rerun into an import
folder can tell the same session (resume) from another one (refused).

:func:`store_inventory` counts the chunk files and bytes of a zarr folder per array and per index of the
array's first chunk axis (the view, for an unwrap store's ``obs``, ``valid`` and ``lit``);
:func:`inventory_problem` compares a folder against an inventory recorded when it was written. zarr reads a
missing chunk as its fill value, so a chunk deleted after the import would otherwise be fitted as
"nothing seen" (or zeros) without a word.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import struct
from collections.abc import Collection, Iterable, Mapping
from pathlib import Path
from typing import Any

from polarface.capture.authors_layout import AuthorsSession

__all__ = [
    "ExrHeader",
    "check_session_files",
    "exr_header",
    "inventory_problem",
    "session_differences",
    "session_fingerprint",
    "store_inventory",
]

_EXR_MAGIC = b"\x76\x2f\x31\x01"
_TILED, _DEEP, _MULTIPART = 0x200, 0x800, 0x1000
#: Scan lines per chunk of each compression (OpenEXR's ``Compression`` enum: NO, RLE, ZIPS, ZIP, PIZ,
#: PXR24, B44, B44A, DWAA, DWAB, HTJ2K256, HTJ2K32).
_LINES_PER_CHUNK = {0: 1, 1: 1, 2: 1, 3: 16, 4: 32, 5: 16, 6: 32, 7: 32, 8: 32, 9: 256, 10: 256, 11: 32}
_HEADER_LIMIT = 1 << 20  # a header longer than this is not one


@dataclasses.dataclass(frozen=True)
class ExrHeader:
    """Size (pixels) and channel names of an OpenEXR file."""

    width: int
    height: int
    channels: tuple[str, ...]


def _cstring(data: bytes, start: int, path: Path) -> tuple[str, int]:
    end = data.find(b"\0", start)
    if end < 0:
        raise ValueError(f"EXR file '{path}' is truncated (its header is cut off)")
    return data[start:end].decode("latin-1"), end + 1


def _channel_names(value: bytes) -> tuple[str, ...]:
    names, start = [], 0
    while start < len(value) and value[start] != 0:
        end = value.index(b"\0", start)
        names.append(value[start:end].decode("latin-1"))
        start = end + 1 + 16  # pixel type, pLinear + 3 reserved, x and y sampling
    return tuple(names)


def exr_header(path: str | os.PathLike[str]) -> ExrHeader:
    """The header of an OpenEXR file, checked to be whole (module docstring).

    Raises:
        FileNotFoundError: no such file. ValueError: not an OpenEXR file, a header or offset table cut
            off, or chunks that lie beyond the end of the file (naming the file).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"EXR file '{path}' does not exist")
    size = path.stat().st_size
    with path.open("rb") as handle:
        data = handle.read(min(size, _HEADER_LIMIT))
        if len(data) < 8 or data[:4] != _EXR_MAGIC:
            raise ValueError(f"'{path}' is not an OpenEXR file ({size} bytes; truncated or another format)")
        flags = struct.unpack_from("<I", data, 4)[0]
        if flags & (_DEEP | _MULTIPART):
            return _header_from_library(path)
        attributes: dict[str, bytes] = {}
        position = 8
        while True:
            if position >= len(data):
                raise ValueError(f"EXR file '{path}' is truncated (its header is cut off)")
            if data[position] == 0:
                position += 1
                break
            name, position = _cstring(data, position, path)
            _, position = _cstring(data, position, path)
            if position + 4 > len(data):
                raise ValueError(f"EXR file '{path}' is truncated (its header is cut off)")
            length = struct.unpack_from("<i", data, position)[0]
            position += 4
            if length < 0 or position + length > len(data):
                raise ValueError(f"EXR file '{path}' is truncated or damaged (attribute '{name}')")
            attributes[name] = data[position:position + length]
            position += length
        try:
            xmin, ymin, xmax, ymax = struct.unpack("<4i", attributes["dataWindow"])
            channels = _channel_names(attributes["channels"])
            compression = attributes["compression"][0]
        except (KeyError, struct.error, ValueError, IndexError):
            raise ValueError(
                f"EXR file '{path}' has a damaged header (dataWindow, channels or compression)") from None
        header = ExrHeader(xmax - xmin + 1, ymax - ymin + 1, channels)
        if flags & _TILED or compression not in _LINES_PER_CHUNK or header.width < 1 or header.height < 1:
            return header  # tiled or an unknown compression: the offset table is not checked
        count = -(-header.height // _LINES_PER_CHUNK[compression])
        handle.seek(position)
        table = handle.read(8 * count)
        if len(table) < 8 * count:
            raise ValueError(f"EXR file '{path}' is truncated (its offset table is cut off)")
        offsets = struct.unpack(f"<{count}Q", table)
        first_chunk = position + 8 * count
        if min(offsets) < first_chunk or max(offsets) + 8 > size:
            raise ValueError(f"EXR file '{path}' is truncated or incomplete (a chunk lies outside its "
                             f"{size} bytes)")
        handle.seek(max(offsets) + 4)
        length = struct.unpack("<i", handle.read(4))[0]
        if length < 0 or max(offsets) + 8 + length > size:
            raise ValueError(f"EXR file '{path}' is truncated (its last chunk ends at byte "
                             f"{max(offsets) + 8 + length}; the file has {size})")
    return header


def _header_from_library(path: Path) -> ExrHeader:
    """Size and channels of a deep or multi-part file through the OpenEXR binding (first part)."""
    import OpenEXR

    try:
        with OpenEXR.File(str(path), header_only=True) as exr:
            header = exr.header()
            (xmin, ymin), (xmax, ymax) = header["dataWindow"]
            names = tuple(getattr(c, "name", str(c)) for c in header.get("channels", ()))
    except Exception as exc:
        raise ValueError(f"cannot read EXR file '{path}': {' '.join(str(exc).split())}") from None
    return ExrHeader(int(xmax - xmin + 1), int(ymax - ymin + 1), names)


def _check_map(path: Path, shape: tuple[int, int] | None, rgb: bool) -> tuple[int, int]:
    header = exr_header(path)
    if rgb:
        missing = [c for c in "RGB" if c not in header.channels]
        if missing:
            raise ValueError(f"EXR '{path}' lacks channel(s) {missing} (has {sorted(header.channels)})")
    elif not header.channels:
        raise ValueError(f"visibility map '{path}' has no channel")
    if shape is not None and (header.height, header.width) != shape:
        raise ValueError(f"EXR '{path}' is {header.width}x{header.height} texels; the texture is "
                         f"{shape[1]}x{shape[0]}")
    return header.height, header.width


def check_session_files(session: AuthorsSession) -> tuple[int, int]:
    """Check every EXR an import reads (module docstring); returns the texture's ``(rows, cols)``.

    Raises:
        FileNotFoundError, ValueError: naming the first file that is missing, not an OpenEXR file,
            truncated, lacks its channels or has another size than the texture.
    """
    if session.dynamic:
        geometry = [path for pair in session.tracked_paths for path in pair]
    else:
        geometry = [session.texture_dir / "vertex.exr", session.texture_dir / "normal.exr"]
    shape = _check_map(geometry[0], None, rgb=True)
    for path in geometry[1:]:
        _check_map(path, shape, rgb=True)
    for key in sorted(session.observation_paths):
        image, visibility = session.observation_paths[key]
        _check_map(image, shape, rgb=True)
        _check_map(visibility, shape, rgb=False)
    return shape


def _session_files(session: AuthorsSession) -> Iterable[Path]:
    if session.dynamic:
        yield from (path for pair in session.tracked_paths for path in pair)
    else:
        yield session.texture_dir / "vertex.exr"
        yield session.texture_dir / "normal.exr"
    for key in sorted(session.observation_paths):
        yield from session.observation_paths[key]


def session_fingerprint(session: AuthorsSession) -> dict[str, Any]:
    """What identifies a session's content (module docstring): ``{"text": {name: sha1}, "files": {name:
    bytes}}``, names relative to the module folder (POSIX); ``icp-pose`` files only for a static session
    (the dynamic import does not read them)."""
    root = session.root
    text = [root / name for name in ("cameras.txt", "images.txt", "white_balance.txt")]
    if not session.dynamic:
        text += sorted(p for p in (root / "icp-pose").iterdir() if p.suffix == ".txt")
    return {
        "text": {p.relative_to(root).as_posix(): hashlib.sha1(p.read_bytes()).hexdigest() for p in text},
        "files": {p.relative_to(root).as_posix(): p.stat().st_size for p in _session_files(session)},
    }


def session_differences(recorded: Mapping[str, Any], current: Mapping[str, Any],
                            written: Collection[str]) -> list[str]:
    """What makes the session of fingerprint ``current`` another one than that of ``recorded``
    (:func:`session_fingerprint`), for an import that has already written what it read from the files
    ``written``: any text file (cameras, poses, white balance are in everything written), and the EXRs
    among ``written``; an EXR not read yet may have changed (a damaged file replaced)."""
    problems = []
    old_text, new_text = dict(recorded.get("text", {})), dict(current.get("text", {}))
    for name in sorted(set(old_text) | set(new_text)):
        if name not in new_text:
            problems.append(f"{name} is gone")
        elif name not in old_text:
            problems.append(f"{name} is new")
        elif old_text[name] != new_text[name]:
            problems.append(f"{name} differs")
    old_files, new_files = dict(recorded.get("files", {})), dict(current.get("files", {}))
    for name in sorted((set(old_files) | set(new_files)) & set(written)):
        if old_files.get(name) != new_files.get(name):
            was = f"{old_files[name]} bytes" if name in old_files else "absent"
            now = f"{new_files[name]} bytes" if name in new_files else "is gone"
            problems.append(f"{name} ({now}; imported: {was})")
    return problems


# ---- the chunk inventory of a written zarr folder ------------------------------------------------------
def _arrays(folder: Path) -> Iterable[Path]:
    """The array folders (a ``zarr.json`` beside a ``c`` chunk folder, or an array without chunks yet)."""
    for current, dirs, files in os.walk(folder):
        here = Path(current)
        if "zarr.json" in files and (here / "c").is_dir():
            dirs[:] = []
            yield here


def store_inventory(folder: str | os.PathLike[str]) -> dict[str, dict[str, list[int]]]:
    """``{array: {first chunk index: [chunk files, bytes]}}`` of the zarr folder (module docstring)."""
    folder = Path(folder)
    inventory: dict[str, dict[str, list[int]]] = {}
    for array in _arrays(folder):
        counts: dict[str, list[int]] = {}
        for current, _, files in os.walk(array / "c"):
            relative = Path(current).relative_to(array / "c").parts
            for name in files:
                first = relative[0] if relative else name
                entry = counts.setdefault(first, [0, 0])
                entry[0] += 1
                entry[1] += (Path(current) / name).stat().st_size
        ordered = sorted(counts.items(), key=lambda item: int(item[0]))
        inventory[array.relative_to(folder).as_posix()] = dict(ordered)
    return dict(sorted(inventory.items()))


def inventory_problem(folder: str | os.PathLike[str], recorded: Mapping[str, Mapping[str, list[int]]],
                      *, per_view: Iterable[str] = ("obs", "valid", "lit")) -> str | None:
    """How the zarr ``folder`` differs from its ``recorded`` inventory (:func:`store_inventory`), or None.

    ``per_view`` arrays name their first chunk index as a view, the others as a chunk row.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return f"'{folder}' is missing"
    found = store_inventory(folder)
    views = set(per_view)
    for array in sorted(set(recorded) | set(found)):
        written, now = dict(recorded.get(array, {})), found.get(array, {})
        for index in sorted(set(written) | set(now), key=int):
            before, after = list(written.get(index, [0, 0])), list(now.get(index, [0, 0]))
            if before == after:
                continue
            where = f"view {index}" if array in views else f"chunk row {index}"
            return (f"'{folder.name}/{array}' {where} holds {after[0]} chunk file(s) of {after[1]} bytes; "
                    f"the import wrote {before[0]} of {before[1]} bytes (a chunk deleted, added or changed)")
    return None
