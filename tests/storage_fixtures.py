"""Stores at URLs for the tests (importable: ``tests`` is on pytest's ``pythonpath``): the keys below a
``memory://`` URL and copying a local folder to a URL. The fixture ``memory_url`` (a fresh, empty
folder of fsspec's in-memory file system per test) is in ``tests/conftest.py``."""

from __future__ import annotations

from pathlib import Path

from polarface.io.storage import UrlPath, storage_path

__all__ = ["memory_keys", "upload_tree"]


def memory_keys(url: str) -> list[str]:
    """Every key below ``url`` in the in-memory file system, relative to it (sorted)."""
    root = storage_path(url)
    assert isinstance(root, UrlPath)
    return sorted(path.relative_to(root).as_posix() for path in root.glob("**") if path.is_file())


def upload_tree(local: Path, url: str) -> UrlPath:
    """Copy every file below the local folder ``local`` to the same relative key below ``url``."""
    target = storage_path(url)
    assert isinstance(target, UrlPath)
    for path in sorted(Path(local).rglob("*")):
        if path.is_file():
            (target / path.relative_to(local).as_posix()).write_bytes(path.read_bytes())
    return target
