"""Atomic file and directory writes: write to a temporary name in the same folder, then rename.

A crash leaves either the old file or no file, never a half-written one that a later run trusts. A file
named by a URL (:class:`polarface.io.storage.UrlPath`: object storage has no rename) is written to a
local temporary file and uploaded whole once it is complete (:meth:`UrlPath.write_bytes`).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from polarface.io.storage import PathOrUrl, StoragePath, UrlPath, storage_path

__all__ = ["atomic_directory", "atomic_path", "write_json_atomic"]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _publish_mode(path: Path, *, directory: bool) -> None:
    """Give a temporary file/folder the permissions a plain open()/mkdir() would have had.

    mkstemp and mkdtemp create private (0600/0700) entries; results are meant to be shared.
    """
    os.chmod(path, (0o777 if directory else 0o666) & ~_umask())


@contextlib.contextmanager
def _staged_upload(target: UrlPath) -> Iterator[Path]:
    """Yield a local temporary file; on success upload its content whole to ``target``."""
    fd, tmp_name = tempfile.mkstemp(prefix=f".tmp-{target.stem}-", suffix=target.suffix)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        target.upload(tmp)
    finally:
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_path(path: PathOrUrl) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    The temporary name keeps ``path``'s suffix (so writers that pick a format by suffix work) and
    starts with ``.tmp-`` so that readers can ignore it. On error the temporary file is removed. For a
    URL (``memory://``, ``s3://``; :func:`polarface.io.storage.storage_path`) the yielded path is a
    local temporary file whose content is put under the URL in one piece on success.
    """
    target = storage_path(path)
    if isinstance(target, UrlPath):
        with _staged_upload(target) as tmp:
            yield tmp
        return
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".tmp-{target.stem}-", suffix=target.suffix, dir=target.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        if tmp.exists():
            _publish_mode(tmp, directory=False)
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike[str], *, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary directory beside ``path``; on success move it to ``path``.

    If ``path`` exists and ``overwrite`` is True it is replaced (the old one is removed only after
    the new one is complete). On error the temporary directory is removed.

    Raises:
        ValueError: ``path`` is a URL other than ``file://`` (object storage cannot rename a folder).
    """
    target = storage_path(path)
    if isinstance(target, UrlPath):
        raise ValueError(f"'{target}': a folder can be replaced atomically only on a local file system")
    target.parent.mkdir(parents=True, exist_ok=True)
    if target.exists() and not overwrite:
        raise FileExistsError(f"output directory '{target}' exists (pass overwrite=True to replace it)")
    tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{target.name}-", dir=target.parent))
    try:
        yield tmp
        _publish_mode(tmp, directory=True)
        if target.exists():
            old = target.with_name(f".old-{target.name}-{os.getpid()}")
            os.replace(target, old)
            os.replace(tmp, target)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, target)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def write_json_atomic(path: PathOrUrl, payload: Any, *, indent: int = 2) -> StoragePath:
    """Write ``payload`` as JSON to ``path`` (a local path or a URL) atomically; returns the path."""
    target = storage_path(path)
    text = json.dumps(payload, indent=indent, sort_keys=False) + "\n"
    if isinstance(target, UrlPath):
        target.write_text(text)
        return target
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return target
