"""Validation of ``result.json``'s format keys (``format``, ``version``, ``channel_names``,
``texture_resolution``) and ``stages``: every reader of a RESULT folder goes through it.

A key that is absent is accepted (a RESULT being built has none yet); a key that is present must hold
what :meth:`~polarface.results.ResultFolder.write_result_header` writes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from polarface.results import layout

__all__ = ["check_result_header"]


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def check_result_header(path: Path, data: dict[str, Any]) -> None:
    """Raise ValueError naming ``path`` and the key when a format key of ``data`` is malformed."""
    if "format" in data and data["format"] != layout.RESULT_FORMAT:
        raise ValueError(
            f"'{path}': 'format' is {data['format']!r}, expected {layout.RESULT_FORMAT!r} "
            "(not a RESULT folder)"
        )
    if "version" in data and (not _is_int(data["version"]) or data["version"] != layout.RESULT_VERSION):
        raise ValueError(
            f"'{path}': 'version' {data['version']!r} is not supported (this polarface reads version "
            f"{layout.RESULT_VERSION})"
        )
    if "channel_names" in data:
        names = data["channel_names"]
        if (
            not isinstance(names, list)
            or len(names) != 6
            or not all(isinstance(n, str) and n for n in names)
            or len(set(names)) != 6
        ):
            raise ValueError(f"'{path}': 'channel_names' must be 6 distinct non-empty names; got {names!r}")
    if "texture_resolution" in data:
        res = data["texture_resolution"]
        if not isinstance(res, list) or len(res) != 2 or not all(_is_int(v) and v >= 1 for v in res):
            raise ValueError(
                f"'{path}': 'texture_resolution' must be [height, width] with integers >= 1; got {res!r}"
            )
    if "stages" in data and not isinstance(data["stages"], dict):
        raise ValueError(f"'{path}': 'stages' must be a JSON object; got {type(data['stages']).__name__}")
