"""The dynamic stage's inputs, checked before anything is written: the dynamic capture store (or a
simulation folder's ``dynamic``), its frame selection (``--frames``), its rig against the static one,
that it is not the static capture, that its raw images are whole, and the static RESULT the frames build
on (:mod:`polarface.pipeline.dynamic`; rules in ``docs/dynamic.md``, "Bad input")."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from polarface.capture import (
    MANIFEST_JSON,
    CaptureStore,
    check_capture_manifest,
    check_derived_store,
    check_raw_images_whole,
    check_stereo_pairs,
)
from polarface.io import storage_path
from polarface.io.recorded_paths import resolve_recorded_path
from polarface.io.storage import PathOrUrl, StoragePath, UrlPath
from polarface.pipeline.inputs.folders import read_input_folder
from polarface.pipeline.inputs.frames import parse_frame_selection
from polarface.results import ResultFolder
from polarface.results.fingerprint import capture_identity, same_input

__all__ = [
    "check_dynamic_sequence",
    "check_static_result",
    "open_dynamic_capture",
    "resolve_dynamic_capture",
]

def resolve_dynamic_capture(path: PathOrUrl) -> StoragePath:
    """The dynamic capture store of ``path``: a capture store, a simulation folder (``SIM/dynamic``) or an
    imported dynamic session (:func:`~polarface.pipeline.inputs.folders.read_input_folder`).

    Raises:
        FileNotFoundError: ``path`` does not exist. ValueError: it is none of those, or a simulation
            without a dynamic sequence.
    """
    folder = read_input_folder(path, ("capture", "imported", "simulation"), argument="DYNAMIC")
    if folder.dynamic is None:
        raise ValueError(f"argument 'DYNAMIC': simulation folder '{folder.root}' holds no dynamic capture "
                         "store")
    return folder.dynamic


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
            f"'{store.root / MANIFEST_JSON}' records sequence {store.sequence!r}: a static capture, not a "
            "dynamic (expression) one; give the dynamic capture (a simulation's SIM/dynamic, or the frames "
            "ingested with 'polarface ingest RAW_DIR --rig RIG --out NEW --sequence dynamic')"
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
