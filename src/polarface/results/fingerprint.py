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
from collections.abc import Mapping
from typing import Any

from polarface.io.storage import PathOrUrl, StoragePath, storage_path

__all__ = ["capture_identity", "file_identity", "fingerprint_differences"]


def _sha256_files(paths: list[StoragePath]) -> str:
    digest = hashlib.sha256()
    for path in paths:
        digest.update(path.name.encode() + b"\0")
        with path.open("rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def file_identity(path: PathOrUrl) -> dict[str, str]:
    """``{"path", "sha256"}`` of one file (the path is informative; only the hash is compared)."""
    path = storage_path(path)
    return {"path": str(path), "sha256": _sha256_files([path])}


def capture_identity(capture: PathOrUrl) -> dict[str, Any]:
    """``{"path", "frames", "sha256"}`` of a capture store, local or at a URL (hash of rig, manifest and
    frame markers)."""
    root = storage_path(capture)
    markers = sorted((root / "frames").glob("[0-9]*.json"))
    files = [p for p in (root / "rig.json", root / "manifest.json") if p.is_file()] + markers
    return {"path": str(root), "frames": len(markers), "sha256": _sha256_files(files)}


def _flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, Mapping):
        out: dict[str, Any] = {}
        for key, item in value.items():
            out.update(_flatten(item, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: value}


def _describe(entry: Any) -> str:
    if isinstance(entry, Mapping) and "sha256" in entry:
        frames = f", {entry['frames']} frames" if "frames" in entry else ""
        return f"'{entry.get('path')}'{frames}, sha256 {str(entry['sha256'])[:12]}"
    return json.dumps(entry)


def fingerprint_differences(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    """What differs between a recorded and a recomputed fingerprint, one phrase per item.

    Files (``capture``, ``mesh``, ``poses``) compare by hash only (a moved capture still matches);
    ``options`` compare field by field (nested fields as ``weights.sss``); other keys by value.
    """
    problems: list[str] = []
    for key in sorted(set(old) | set(new)):
        was, now = old.get(key), new.get(key)
        if key == "options":
            flat_old, flat_new = _flatten(was or {}), _flatten(now or {})
            for name in sorted(set(flat_old) | set(flat_new)):
                if flat_old.get(name) != flat_new.get(name):
                    problems.append(
                        f"option '{name}' was {json.dumps(flat_old.get(name))}, "
                        f"now {json.dumps(flat_new.get(name))}"
                    )
        elif isinstance(was, Mapping) and isinstance(now, Mapping) and "sha256" in was:
            if was.get("sha256") != now.get("sha256"):
                problems.append(f"the {key} differs: was {_describe(was)}, now {_describe(now)}")
        elif was != now:
            problems.append(f"'{key}' was {_describe(was)}, now {_describe(now)}")
    return problems
