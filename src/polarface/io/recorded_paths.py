"""Paths that a folder's records hold (``result.json``, ``geometry.json``, ``tracking.json``,
``imported.json``, ``export.json``, ...): one writer and one reader, so that every folder can be moved,
copied or renamed and still be read from any working directory.

* :func:`record_path` turns a path into what a record stores: a path **inside** the recording folder is
  stored relative to that folder, in POSIX form (``"geometry/poses.json"``); a path **outside** it (an
  input, such as the capture a RESULT was made from) is stored absolute, or as its URL.
* :func:`resolve_recorded_path` turns a stored value back into a path: a relative value is taken from the
  recording folder, wherever that folder now is and whatever the working directory.
* :func:`recorded_input` does the same for an input that must exist, and otherwise raises an error that
  names the record, the key, the recorded path and what to do (the option that points to the input's new
  place).

Records written before this rule (polarface 0.1 before issue 47) stored paths as given on the command
line, relative to the working directory of the run: a relative value that does not exist under the
folder but does from the working directory is still found.
"""

from __future__ import annotations

import os
from pathlib import Path, PurePosixPath

from polarface.io.storage import PathOrUrl, StoragePath, UrlPath, is_url, storage_path

__all__ = ["record_path", "recorded_input", "resolve_recorded_path"]


def _absolute(path: PathOrUrl) -> StoragePath:
    """``path`` as an absolute local path (``..`` collapsed, symlinks kept) or as a URL."""
    target = storage_path(path)
    return target if isinstance(target, UrlPath) else Path(os.path.abspath(target))


def record_path(folder: PathOrUrl, path: PathOrUrl | None) -> str | None:
    """What a record of ``folder`` stores for ``path`` (None stays None).

    Args:
        folder: the folder whose record holds the value (a RESULT, a GEOM folder, ``tracking/``, ...).
        path: the path to record, relative to the working directory or absolute, or a URL.

    Returns:
        The POSIX path relative to ``folder`` when ``path`` lies inside it (``"."`` for ``folder``
        itself), else the absolute path or the URL.
    """
    if path is None:
        return None
    target, root = _absolute(path), _absolute(folder)
    if isinstance(target, UrlPath):
        inside = isinstance(root, UrlPath) and target.url.startswith(root.url + "/")
        return target.url[len(root.url) + 1:] if inside else target.url
    if isinstance(root, UrlPath):
        return target.as_posix()
    try:
        return target.relative_to(root).as_posix() or "."
    except ValueError:
        return target.as_posix()


def resolve_recorded_path(folder: PathOrUrl, value: object) -> StoragePath | None:
    """The path that a record of ``folder`` stores as ``value`` (None for an absent or empty value).

    A URL or an absolute path is returned as it is; a relative path is taken from ``folder`` (or, for a
    record written before paths were stored relative to their folder, from the working directory when
    only that one exists: module docstring).

    Raises:
        ValueError: ``value`` is neither a string nor None (a malformed record).
    """
    if value is None or value == "":
        return None
    if not isinstance(value, str):
        raise ValueError(f"a recorded path must be a string; got {value!r}")
    if is_url(value):
        return storage_path(value)
    recorded = Path(value)
    if recorded.is_absolute():
        return recorded
    root = storage_path(folder)
    inside = root / PurePosixPath(value).as_posix()
    if isinstance(inside, Path) and not inside.exists() and recorded.exists():
        return recorded.absolute()  # an older record: relative to the working directory of its run
    return inside


def recorded_input(folder: PathOrUrl, value: object, *, record: str, key: str, remedy: str) -> StoragePath:
    """An input that a record of ``folder`` names and that must exist (a file or a folder).

    Args:
        folder: the folder whose record holds ``value``.
        value: the recorded value (:func:`record_path`).
        record: the record file, for the message (e.g. ``'RESULT/result.json'``).
        key: the key path in the record, for the message (e.g. ``stages.prepare.geometry``).
        remedy: what the user does about it, for the message: the option that points to the input's new
            place (``"give its new place with --gt"``), or how to do without it.

    Raises:
        FileNotFoundError: nothing is recorded, or the recorded path does not exist (naming the record,
            the key, the recorded path and ``remedy``).
    """
    path = resolve_recorded_path(folder, value)
    if path is None:
        raise FileNotFoundError(f"'{record}' records no {key}; {remedy}")
    if not path.exists():
        raise FileNotFoundError(
            f"'{record}' records {key} = '{value}', which does not exist (moved or deleted?); {remedy}"
        )
    return path
