"""The dynamic stage's inputs, checked before anything is written: the dynamic capture store (or a
simulation folder's ``dynamic``), its frame selection (``--frames``), its rig against the static one,
and the static RESULT the frames build on (:mod:`polarface.pipeline.dynamic`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from polarface.capture.store import CaptureStore
from polarface.io import storage_path
from polarface.pipeline.geometry_frames import check_stereo_pairs
from polarface.pipeline.reconstruct_inputs import check_capture_manifest
from polarface.results import ResultFolder

__all__ = ["check_static_result", "open_dynamic_capture", "parse_frame_selection", "resolve_dynamic_capture"]


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
        raise ValueError(f"'--dynamic {path}' is not a capture store (no manifest.json)")
    return path


def parse_frame_selection(spec: str | Sequence[int] | None, frames: Sequence[int]) -> list[int]:
    """Frames selected by ``spec`` (``"0-4,7"``, a list of indices, or None for all) among ``frames``.

    Raises:
        ValueError: a malformed spec, or a frame that is not in the capture (naming ``--frames``).
    """
    frames = [int(f) for f in frames]
    if spec is None:
        return frames
    chosen: set[int] = set()
    if isinstance(spec, str):
        for part in (p.strip() for p in spec.split(",")):
            try:
                if "-" in part[1:]:
                    low, high = part.split("-", 1) if not part.startswith("-") else ("", part)
                    chosen.update(range(int(low), int(high) + 1))
                else:
                    chosen.add(int(part))
            except ValueError:
                raise ValueError(
                    f"argument '--frames': {spec!r} is not a list of frames and ranges (e.g. '0-4,7')"
                ) from None
    else:
        chosen = {int(f) for f in spec}
    unknown = sorted(chosen - set(frames))
    if unknown:
        raise ValueError(f"argument '--frames': frame(s) {unknown} are not in the dynamic capture {frames}")
    return [f for f in frames if f in chosen]


def check_static_result(folder: ResultFolder) -> None:
    """Raise ValueError (naming the folder and what is missing) unless ``folder`` holds a finished static
    result: rig, mesh, eta map and mask, polarimetric stage complete."""
    required = (folder.rig_path, folder.mesh_path, folder.map_path("eta"), folder.map_path("mask", ".png"))
    missing = [path for path in required if not path.is_file()]
    if missing or not folder.stage_complete("polarimetric"):
        what = f"'{missing[0]}' is missing" if missing else "its polarimetric stage is not complete"
        raise ValueError(
            f"'{folder.root}' holds no static result ({what}); the dynamic stage needs one: run "
            "'polarface reconstruct STATIC_CAPTURE --out RESULT' first (or add '--dynamic' to it)"
        )


def open_dynamic_capture(capture: Path, rig, rig_path: Path,
                         frames: str | Sequence[int] | None = None) -> CaptureStore:
    """The dynamic capture store, checked: finished, its rig's geometry equal to ``rig`` (the static
    capture's, read from ``rig_path``; :meth:`polarface.capture.rig.Rig.geometry_differences`), stereo
    pairs that rectify, and ``frames`` among its frames (:func:`parse_frame_selection`).

    Raises:
        ValueError: naming the rig files and the differing fields, or the bad selection.
    """
    store = CaptureStore.open(capture)
    check_capture_manifest(store)
    differences = store.rig.geometry_differences(rig)
    if differences:
        more = f" (+{len(differences) - 6} more)" if len(differences) > 6 else ""
        raise ValueError(
            f"the rig of the dynamic capture '{store.root / 'rig.json'}' differs from the static one "
            f"'{rig_path}': {', '.join(differences[:6])}{more}; reconstruct captures of one rig"
        )
    check_stereo_pairs(store)
    parse_frame_selection(frames, [record.index for record in store.frames])
    return store
