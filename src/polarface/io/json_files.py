"""Reading the JSON artifacts (``result.json``, ``simulation.json``, ``scene.json``, ``sog.json`` ...)."""

from __future__ import annotations

import json
from typing import Any

from polarface.io.storage import PathOrUrl, storage_path

__all__ = ["json_values", "read_json_object"]


def read_json_object(path: PathOrUrl) -> dict[str, Any]:
    """The JSON object in the UTF-8 file ``path`` (a local path or a URL).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file is not UTF-8 JSON, or holds something other than an object (one line naming
            the file).
    """
    path = storage_path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"'{path}' is not valid JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise ValueError(f"'{path}' must hold a JSON object; got {type(data).__name__}")
    return data


def json_values(value: Any) -> Any:
    """``value`` with every tuple turned into a list, recursively through dicts and lists: what it reads
    back as after a JSON round trip, so that recorded and current configurations compare equal."""
    if isinstance(value, dict):
        return {k: json_values(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_values(v) for v in value]
    return value
