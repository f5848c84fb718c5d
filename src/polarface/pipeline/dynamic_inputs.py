"""The dynamic stage's inputs, checked before anything is written: the dynamic capture store (or a
simulation folder's ``dynamic``), its frame selection (``--frames``),
its rig against the static one, that it is not the static capture, that its raw images are whole, and
the static RESULT the frames build on (:mod:`polarface.pipeline.dynamic`; rules in ``docs/dynamic.md``,
"Bad input")."""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from polarface.capture.store import CaptureStore
from polarface.io import storage_path
from polarface.io.recorded_paths import resolve_recorded_path
from polarface.io.storage import PathOrUrl, StoragePath, UrlPath
from polarface.pipeline.geometry_frames import check_stereo_pairs
from polarface.pipeline.reconstruct_inputs import check_capture_manifest, check_derived_store
from polarface.results import ResultFolder
from polarface.results.fingerprint import capture_identity, same_input

__all__ = [
    "check_dynamic_sequence",
    "check_raw_images_whole",
    "check_static_result",
    "open_dynamic_capture",
    "parse_frame_selection",
    "resolve_dynamic_capture",
    "selection_note",
]

#: The last 12 bytes of every PNG file: the empty ``IEND`` chunk (length 0, type, CRC).
_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"


def resolve_dynamic_capture(path: str | Path) -> Path:
    """The dynamic capture store of ``path``: a capture store, or a simulation folder (``SIM/dynamic``).

    Raises:
        FileNotFoundError: ``path`` does not exist. ValueError: it is not a capture store.
    """
    path = storage_path(path)
    if not path.exists():
        raise FileNotFoundError(f"dynamic capture '{path}' does not exist")
    if (path / "dynamic" / "manifest.json").is_file():
        path = path / "dynamic"
    if (path / "imported.json").is_file():  # an imported authors' session (pipeline.dynamic_imported)
        return path
    if not (path / "manifest.json").is_file():
        raise ValueError(f"dynamic capture '{path}' is not a capture store (no manifest.json) nor a "
                         "simulation folder (no dynamic/manifest.json)")
    return path


def _ranges(values: Sequence[int]) -> str:
    """``[0, 1, 2, 5]`` as ``'0-2,5'``."""
    parts: list[str] = []
    start = previous = None
    for value in sorted(set(values)):
        if previous is not None and value == previous + 1:
            previous = value
            continue
        if start is not None:
            parts.append(f"{start}-{previous}" if previous != start else f"{start}")
        start = previous = value
    if start is not None:
        parts.append(f"{start}-{previous}" if previous != start else f"{start}")
    return ",".join(parts)


def parse_frame_selection(spec: str | Iterable[int] | None, frames: Iterable[int]) -> list[int]:
    """Frames selected by ``spec`` among the capture's ``frames``, in the sequence's order.

    ``spec`` is ``"0-4,7"`` (frames and ascending ranges, in any order, repeats allowed), a list of
    indices, or None for all. The selection is a set: the frames are always tracked forward through the
    whole sequence and fitted in its order, whatever order ``spec`` lists them in.

    Raises:
        ValueError: a malformed spec, a descending range (``'4-0'``: write ``'0-4'``), an empty selection,
            or frames that are not in the capture (naming ``--frames``).
    """
    frames = [int(f) for f in frames]
    if spec is None:
        return frames
    present = set(frames)
    chosen: set[int] = set()
    unknown: list[str] = []

    def take(low: int, high: int) -> None:
        inside = [f for f in frames if low <= f <= high]
        chosen.update(inside)
        if high - low + 1 > len(inside):  # some are not in the capture: name them, compactly
            if high - low < 100_000:
                unknown.append(_ranges([v for v in range(low, high + 1) if v not in present]))
            else:  # a huge range: its ends that are not in the capture
                while low in present:
                    low += 1
                while high in present:
                    high -= 1
                unknown.append(f"{low}-{high}")

    if isinstance(spec, str):
        for part in (p.strip() for p in spec.split(",")):
            try:
                if "-" in part[1:]:
                    cut = part.index("-", 1)
                    low, high = int(part[:cut]), int(part[cut + 1:])
                else:
                    low = high = int(part)
            except ValueError:
                raise ValueError(
                    f"argument '--frames': {spec!r} is not a list of frames and ranges (e.g. '0-4,7')"
                ) from None
            if min(low, high) < 0:
                raise ValueError(f"argument '--frames': {part!r}: frame indices are >= 0")
            if low > high:
                raise ValueError(
                    f"argument '--frames': {part!r} is a descending range; frames are tracked forward "
                    f"through the whole sequence and fitted in its order: write '{high}-{low}'"
                )
            take(low, high)
    else:
        for value in spec:
            take(int(value), int(value))
    if unknown:
        raise ValueError(
            f"argument '--frames': frame(s) {','.join(unknown)} are not in the dynamic capture (its frames: "
            f"{_ranges(frames) or 'none'})"
        )
    if not chosen:
        raise ValueError(f"argument '--frames': {spec!r} selects no frame")
    return [f for f in frames if f in chosen]


def selection_note(spec: str | Iterable[int] | None, selected: Sequence[int]) -> str | None:
    """What to tell the user about ``--frames spec`` whose frames are fitted as ``selected``
    (:func:`parse_frame_selection`): a note when ``spec`` lists them out of the sequence's order or more
    than once (they are fitted once, in the sequence's order), else None."""
    if spec is None:
        return None
    if isinstance(spec, str):
        firsts = [int(part.strip()[:part.strip().index("-", 1)]) if "-" in part.strip()[1:]
                  else int(part) for part in spec.split(",")]
    else:
        firsts = [int(value) for value in spec]
    if firsts == sorted(set(firsts)):
        return None
    return (f"--frames {spec if isinstance(spec, str) else firsts!r}: the frames are fitted once "
            f"each, in the sequence's order ({_ranges(selected)}); the tracking always runs forward "
            "through the whole sequence")


def check_static_result(folder: ResultFolder) -> None:
    """Raise ValueError (naming the folder and what is missing) unless ``folder`` holds a finished static
    result: rig, mesh, eta map and mask, polarimetric stage complete."""
    if folder.root.exists() and not folder.root.is_dir():
        raise ValueError(f"RESULT '{folder.root}' is a file, not a RESULT folder")
    required = (folder.rig_path, folder.mesh_path, folder.map_path("eta"), folder.map_path("mask", ".png"))
    missing = [path for path in required if not path.is_file()]
    if missing or not folder.stage_complete("polarimetric"):
        what = f"'{missing[0]}' is missing" if missing else "its polarimetric stage is not complete"
        raise ValueError(
            f"'{folder.root}' holds no static result ({what}); the dynamic stage needs one: run "
            "'polarface reconstruct STATIC_CAPTURE --out RESULT' first (or add '--dynamic' to it)"
        )


def _same_location(first: StoragePath | None, second: StoragePath | None) -> bool:
    """Whether two stores are one folder (symbolic links and ``..`` resolved; URLs compared as text)."""
    if first is None or second is None:
        return False
    if isinstance(first, UrlPath) or isinstance(second, UrlPath):
        return str(first).rstrip("/") == str(second).rstrip("/")
    try:
        return os.path.samefile(first, second)
    except OSError:
        return os.path.realpath(first) == os.path.realpath(second)


def check_dynamic_sequence(store: CaptureStore, *, static_capture: PathOrUrl | None = None,
                           result: ResultFolder | None = None) -> None:
    """Refuse a dynamic capture that is a static one (``docs/dynamic.md``, "Bad input").

    Refused: the static capture ``static_capture`` itself (the same folder, or a copy: the same
    :func:`polarface.results.fingerprint.capture_identity`); the static capture ``result`` was
    reconstructed from (its ``stages.prepare.capture`` folder, or ``fingerprint.capture``'s identity);
    and a store whose ``manifest.json`` records ``sequence: "static"`` (the simulator's ``SIM/static``,
    ``polarface ingest`` without ``--sequence dynamic``).

    Raises:
        ValueError: naming the store, and the RESULT or the manifest field that tells.
    """
    identity: dict[str, Any] | None = None
    if static_capture is not None:
        static_root = storage_path(static_capture)
        identity = capture_identity(store.root)
        if _same_location(store.root, static_root) or same_input(capture_identity(static_root), identity):
            raise ValueError(
                f"dynamic capture '{store.root}' is the static capture '{static_root}' itself; give the "
                "dynamic (expression) capture of the same rig (a simulation's SIM/dynamic, or a store "
                "ingested with 'polarface ingest ... --sequence dynamic')"
            )
    if result is not None:
        recorded = result.read_result()
        static_root = resolve_recorded_path(result.root, recorded.get("stages", {}).get("prepare", {})
                                            .get("capture"))
        fingerprint = recorded.get("fingerprint", {}).get("capture")
        if identity is None and fingerprint is not None:
            identity = capture_identity(store.root)
        if _same_location(store.root, static_root) or (fingerprint is not None
                                                       and same_input(fingerprint, identity or {})):
            raise ValueError(
                f"dynamic capture '{store.root}' is the static capture that '{result.root}' was "
                f"reconstructed from ('{result.result_json_path}': stages.prepare.capture / "
                "fingerprint.capture); give the dynamic (expression) capture of the same rig (a "
                "simulation's SIM/dynamic)"
            )
    if store.sequence != "dynamic":
        raise ValueError(
            f"'{store.root / 'manifest.json'}' records sequence {store.sequence!r}: a static capture, not a "
            "dynamic (expression) one; give the dynamic capture (a simulation's SIM/dynamic, or the frames "
            "ingested with 'polarface ingest RAW_DIR --rig RIG --out NEW --sequence dynamic')"
        )


def _raw_images_read(store: CaptureStore) -> list[str]:
    """Ids of the cameras whose raw images the dynamic stage reads: the stereo pairs' (stereo) and every
    camera that is not polarimetric (tracking); the polarimetric cameras are read from ``derived.zarr``."""
    ids = {camera.id for pair in store.rig.stereo_camera_pairs() for camera in pair}
    ids.update(camera.id for camera in store.rig.cameras if camera.role != "polarimetric")
    return sorted(ids)


def _tail(path: StoragePath, size: int) -> bytes:
    """The last ``size`` bytes of a file (fewer when it is shorter)."""
    if isinstance(path, UrlPath):
        return bytes(path.fs.cat_file(path.path, start=-size))
    with open(path, "rb") as handle:
        handle.seek(0, os.SEEK_END)
        handle.seek(max(handle.tell() - size, 0))
        return handle.read(size)


def check_raw_images_whole(store: CaptureStore, cameras: Sequence[str] | None = None) -> None:
    """Every raw PNG image of ``cameras`` (None: those the dynamic stage reads) in every frame of ``store``
    ends with PNG's end chunk: a truncated file (an interrupted copy or download) is found by one small
    read per file, before any work, rather than by the stereo or the tracking minutes later. Corruption
    that keeps a file's length is found where the file is decoded (an error naming it).

    Raises:
        ValueError: naming the store, the file, its frame and camera.
    """
    wanted = set(_raw_images_read(store) if cameras is None else cameras)
    for record in store.frames:
        for camera_id, relative in sorted(record.raw.items()):
            if camera_id not in wanted or not relative.lower().endswith(".png"):
                continue
            path = store.root / relative
            try:
                whole = _tail(path, len(_PNG_END)) == _PNG_END
            except FileNotFoundError:
                raise ValueError(f"capture store '{store.root}': raw image '{relative}' (frame "
                                 f"{record.index}, camera {camera_id}) is missing") from None
            if not whole:
                raise ValueError(
                    f"capture store '{store.root}': raw image '{relative}' (frame {record.index}, camera "
                    f"{camera_id}) is truncated (it does not end with PNG's IEND chunk); copy or ingest that "
                    "frame again"
                )


def open_dynamic_capture(capture: Path, rig, rig_path: Path, frames: str | Sequence[int] | None = None,
                         *, static_capture: PathOrUrl | None = None,
                         result: ResultFolder | None = None) -> CaptureStore:
    """The dynamic capture store, checked: finished, readable (``derived.zarr``'s first chunks), not the
    static capture (:func:`check_dynamic_sequence` with ``static_capture`` and ``result``), its rig's
    geometry equal to ``rig`` (the static capture's, read from ``rig_path``;
    :meth:`polarface.capture.rig.Rig.geometry_differences`), stereo pairs that rectify, ``frames`` among
    its frames (:func:`parse_frame_selection`) and whole raw images (:func:`check_raw_images_whole`).

    Raises:
        ValueError: naming the store, the rig files and the differing fields, the bad selection or the
            truncated file.
    """
    store = CaptureStore.open(capture)
    check_capture_manifest(store)
    check_dynamic_sequence(store, static_capture=static_capture, result=result)
    differences = store.rig.geometry_differences(rig)
    if differences:
        more = f" (+{len(differences) - 6} more)" if len(differences) > 6 else ""
        raise ValueError(
            f"the rig of the dynamic capture '{store.root / 'rig.json'}' differs from the static one "
            f"'{rig_path}': {', '.join(differences[:6])}{more}; reconstruct captures of one rig"
        )
    check_stereo_pairs(store)
    parse_frame_selection(frames, [record.index for record in store.frames])
    check_derived_store(store)
    check_raw_images_whole(store)
    return store
