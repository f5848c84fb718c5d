"""The input fingerprint of a RESULT folder: what a ``--resume`` must find unchanged.

``result.json`` key ``fingerprint`` (``docs/result_folder.md``, "Resume fingerprint") records, when a
run starts, the identity of everything that changes the result: the capture (SHA-256 over its
``rig.json``, ``manifest.json`` and frame markers ``frames/*.json``, which hold the SHA-1 of every raw
frame; plus its path and frame count for the message), the mesh and poses files (SHA-256), the
texture resolution, the hold-out and every fit option. A resumed run recomputes it and
:func:`fingerprint_differences` names what differs.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from typing import Any

from polarface.capture.manifest import MANIFEST_JSON
from polarface.io.storage import PathOrUrl, StoragePath, UrlPath, storage_path

__all__ = [
    "RecordMismatchError",
    "capture_identity",
    "file_identity",
    "fingerprint_differences",
    "same_input",
]


class RecordMismatchError(ValueError):
    """A folder's record differs from what a rerun or a resume would record: ``message`` says which folder
    and what to do, ``details`` holds one line per differing key path (:func:`fingerprint_differences`);
    the CLI prints the message, then each detail on a line of its own."""

    def __init__(self, message: str, details: list[str]) -> None:
        super().__init__(f"{message}: {'; '.join(details)}")
        self.message = message
        self.details = list(details)


def _sha256_files(paths: list[StoragePath]) -> str:
    digest = hashlib.sha256()
    for path in paths:
        digest.update(path.name.encode() + b"\0")
        with path.open("rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def _absolute(path: StoragePath) -> str:
    """The informative ``path`` of an identity: absolute (or the URL), so that it means the same from any
    working directory (:func:`polarface.io.recorded_paths.record_path` of a path outside the folder)."""
    return str(path) if isinstance(path, UrlPath) else os.path.abspath(path)


def file_identity(path: PathOrUrl) -> dict[str, str]:
    """``{"path", "sha256"}`` of one file (the path is informative; only the hash is compared)."""
    path = storage_path(path)
    return {"path": _absolute(path), "sha256": _sha256_files([path])}


def capture_identity(capture: PathOrUrl) -> dict[str, Any]:
    """``{"path", "frames", "sha256"}`` of a capture store, local or at a URL (hash of rig, manifest and
    frame markers)."""
    root = storage_path(capture)
    markers = sorted((root / "frames").glob("[0-9]*.json"))
    files = [p for p in (root / "rig.json", root / MANIFEST_JSON) if p.is_file()] + markers
    return {"path": _absolute(root), "frames": len(markers), "sha256": _sha256_files(files)}


def same_input(recorded: Any, current: Mapping[str, Any]) -> bool:
    """Whether a recorded identity (:func:`file_identity`, :func:`capture_identity`) names the same content
    as ``current``: the hash (and frame count) only, so a moved, copied or renamed input still matches."""
    if not isinstance(recorded, Mapping):
        return False
    return all(recorded.get(key) == current.get(key) for key in ("sha256", "frames"))


#: Longest value shown in a difference line (longer ones are cut with "...").
_SHOWN_CHARS = 120
#: A key present on one side only.
_ABSENT = object()


def _shown(entry: Any) -> str:
    """One value of a difference line: an input identity as its path, frames and hash, else its JSON."""
    if entry is _ABSENT:
        return "(absent)"
    if isinstance(entry, Mapping) and "sha256" in entry:
        frames = f", {entry['frames']} frames" if "frames" in entry else ""
        return f"'{entry.get('path')}'{frames}, sha256 {str(entry['sha256'])[:12]}"
    text = json.dumps(entry, sort_keys=True)
    return text if len(text) <= _SHOWN_CHARS else text[:_SHOWN_CHARS - 3] + "..."


def fingerprint_differences(old: Mapping[str, Any], new: Mapping[str, Any], prefix: str = "") -> list[str]:
    """What differs between a recorded and a recomputed record, one line per differing key path.

    Nested objects are compared key by key (``options.weights.sss: recorded 1.0, now 2.0``); an input
    identity (an object with ``sha256``: :func:`file_identity`, :func:`capture_identity`) compares by
    hash only (:func:`same_input`: a moved capture still matches) and is one line; a key present on one
    side only reads ``(absent)`` on the other.

    Args:
        old: the recorded record (e.g. ``result.json``'s ``fingerprint``).
        new: the recomputed one.
        prefix: the key path of ``old`` and ``new`` within a larger record (``"config."``).
    """
    lines: list[str] = []
    for key in sorted(set(old) | set(new), key=str):
        was, now = old.get(key, _ABSENT), new.get(key, _ABSENT)
        if any(isinstance(v, Mapping) and "sha256" in v for v in (was, now)):
            differs = not same_input(was, now if isinstance(now, Mapping) else {})
        elif isinstance(was, Mapping) and isinstance(now, Mapping):
            lines.extend(fingerprint_differences(was, now, f"{prefix}{key}."))
            continue
        else:
            differs = was != now
        if differs:
            lines.append(f"{prefix}{key}: recorded {_shown(was)}, now {_shown(now)}")
    return lines
