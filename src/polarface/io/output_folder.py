"""One policy for every command that writes an output folder (or file), and a lock so two processes never
write one folder at once.

* A folder that holds something not written by this command is refused ("foreign"); an empty or absent
  folder is used. A folder is "this command's own" when it holds the marker :data:`MARKER`
  (``{"command": ..., "format": "polarface-output"}``, written atomically when the folder is created) or
  the command's own manifest (``owned(path)``, e.g. ``result.json`` of ``polarface reconstruct``).
* ``resume``: ``None`` for commands without a ``--resume`` flag (they continue or rewrite their own folder);
  ``False``/``True`` for commands that have one (their own non-empty folder needs ``--resume``).
* ``force``: the command writes into a temporary sibling ``.tmp-NAME-*``; only after it succeeds is the old
  folder swapped out and removed. On failure the old folder is untouched.
* The lock is the file ``.NAME.polarface.lock`` *beside* the output (``{"pid", "command", "path"}``, created
  with ``O_CREAT | O_EXCL``): beside, not inside, because some jobs require an empty folder, a file output
  cannot hold it, and ``--force`` swaps the folder. A lock whose pid no longer runs is stale and is taken
  over with a warning. A second process is refused at once with an error naming the first one's pid.
* An output at a URL (``memory://``, ``s3://``; :mod:`polarface.io.storage`) follows the same policy
  except that it is not locked (object storage has no exclusive create that every fsspec file system
  offers, and a pid means nothing on another machine: one writer per URL is the user's job) and that
  ``--force`` on a non-empty one is refused (a folder cannot be swapped in without a rename).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from polarface.io.atomic import write_json_atomic
from polarface.io.storage import PathOrUrl, StoragePath, UrlPath, remove_tree, storage_path

__all__ = ["MARKER", "OutputFolderError", "json_manifest", "lock_output", "output_file", "output_folder"]

LOGGER = logging.getLogger(__name__)

#: The marker file that makes a folder "this command's own".
MARKER = ".polarface-output.json"
_FORMAT = "polarface-output"
#: A lock file with no readable content older than this (seconds) is a crashed writer's: stale.
_UNREADABLE_STALE_S = 10.0


class OutputFolderError(ValueError):
    """The output folder (or file) cannot be used: foreign, busy, a file where a folder is expected."""


def json_manifest(name: str, **expected: object) -> Callable[[StoragePath], bool]:
    """Recognises a command's own folder: ``folder/name`` is a JSON object with the ``expected`` items."""

    def owned(folder: StoragePath) -> bool:
        try:
            data = json.loads((folder / name).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return False
        return isinstance(data, dict) and all(data.get(k) == v for k, v in expected.items())

    return owned


# ---- the lock ------------------------------------------------------------------------------------
def _lock_path(target: Path) -> Path:
    return target.parent / f".{target.name}.polarface.lock"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _read_lock(lock: Path) -> dict | None:
    try:
        data = json.loads(lock.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and isinstance(data.get("pid"), int) else None


def _try_create_lock(lock: Path, payload: bytes) -> bool:
    try:
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    try:
        os.write(fd, payload)
    finally:
        os.close(fd)
    return True


def _acquire(target: Path, command: str) -> Path:
    lock = _lock_path(target)
    lock.parent.mkdir(parents=True, exist_ok=True)
    payload = json.dumps({"pid": os.getpid(), "command": command, "path": str(target)}).encode()
    for _ in range(3):
        if _try_create_lock(lock, payload):
            return lock
        holder = _read_lock(lock)
        if holder is None:
            try:
                age = time.time() - lock.stat().st_mtime
            except FileNotFoundError:
                continue
            if age < _UNREADABLE_STALE_S:  # a writer between O_EXCL and write(): held
                raise OutputFolderError(f"output '{target}' is being written by another process ({lock})")
        elif holder["pid"] == os.getpid() or _pid_alive(holder["pid"]):
            raise OutputFolderError(
                f"output '{target}' is in use by 'polarface {holder.get('command')}' (pid {holder['pid']}); "
                f"wait for it to finish or stop it (lock file '{lock}')"
            )
        LOGGER.warning(
            "taking over the stale lock '%s' of pid %s (no longer running)",
            lock,
            holder["pid"] if holder else "?",
        )
        with contextlib.suppress(FileNotFoundError):
            lock.unlink()
    raise OutputFolderError(f"could not lock output '{target}' (lock file '{lock}' keeps reappearing)")


def _release(lock: Path) -> None:
    holder = _read_lock(lock)
    if holder is not None and holder["pid"] == os.getpid():
        with contextlib.suppress(FileNotFoundError):
            lock.unlink()


@contextlib.contextmanager
def lock_output(path: PathOrUrl, command: str) -> Iterator[StoragePath]:
    """Hold the lock of ``path`` (a folder or file) for the ``with`` body; yields ``Path(path)`` (a URL is
    yielded as a :class:`~polarface.io.storage.UrlPath`, unlocked: module docstring).

    Raises:
        OutputFolderError: another live process holds the lock (the message names its pid).
    """
    target = storage_path(path)
    if isinstance(target, UrlPath):
        yield target
        return
    missing = _missing_ancestors(target.parent)
    lock = _acquire(target, command)
    try:
        yield target
    finally:
        _release(lock)
        for folder in missing:  # the parents this call created, when nothing was written into them
            try:
                folder.rmdir()
            except OSError:
                break


def _missing_ancestors(folder: Path) -> list[Path]:
    """``folder`` and its ancestors that do not exist yet, deepest first."""
    missing = []
    while not folder.exists() and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    return missing


# ---- the folder policy ---------------------------------------------------------------------------
def _entries(folder: StoragePath) -> list[str]:
    return [p.name for p in folder.iterdir() if p.name != MARKER]


def _is_own(folder: StoragePath, command: str, owned: Callable[[StoragePath], bool] | None) -> bool:
    if json_manifest(MARKER, format=_FORMAT, command=command)(folder):
        return True
    return owned is not None and owned(folder)


def _check(target: StoragePath, command: str, resume: bool | None, force: bool, owned,
           replace_own: bool = True) -> bool:
    """Apply the policy; returns whether the command must write into a temporary sibling (``force``)."""
    if resume and force:
        raise OutputFolderError("arguments '--resume' and '--force' exclude each other")
    if target.exists() and not target.is_dir():
        raise OutputFolderError(f"output folder '{target}' is a file, not a folder; choose another --out")
    if not target.exists() or not _entries(target):
        return False
    if force and isinstance(target, UrlPath):
        raise OutputFolderError(
            f"argument '--force': output '{target}' is at a URL, where a folder cannot be swapped in "
            "(no rename); remove it first or choose another --out"
        )
    if force:
        return True
    if not _is_own(target, command, owned):
        raise OutputFolderError(
            f"output folder '{target}' is not empty and was not written by 'polarface {command}'; "
            "choose another --out or pass --force to replace it"
        )
    if resume is None and not replace_own:
        raise OutputFolderError(
            f"output folder '{target}' holds a previous 'polarface {command}' run; pass --force to "
            "replace it or choose another --out"
        )
    if resume is False:
        raise OutputFolderError(
            f"output folder '{target}' holds a previous 'polarface {command}' run; pass --resume to continue "
            "it or --force to replace it"
        )
    return False


def _write_marker(folder: StoragePath, command: str) -> None:
    if not (folder / MARKER).exists():
        write_json_atomic(folder / MARKER, {"format": _FORMAT, "command": command})


def _swap_in(tmp: Path, target: Path) -> None:
    """Replace ``target`` by the complete ``tmp``; the old folder is removed only after the rename."""
    old = target.with_name(f".old-{target.name}-{os.getpid()}")
    os.replace(target, old)
    try:
        os.replace(tmp, target)
    except OSError:
        os.replace(old, target)
        raise
    shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def output_folder(
    path: PathOrUrl,
    command: str,
    *,
    resume: bool | None = None,
    force: bool = False,
    owned: Callable[[StoragePath], bool] | None = None,
    marker: bool = True,
    replace_own: bool = True,
) -> Iterator[StoragePath]:
    """Lock ``path``, apply the policy (module docstring) and yield the folder the command writes into.

    Args:
        path: the output folder (``--out``): a local path or a URL (module docstring).
        command: the subcommand name (recorded in the marker and the lock).
        resume: ``--resume`` of commands that have it, else None (module docstring).
        force: ``--force``: replace the folder, swapping only after the ``with`` body succeeded.
        owned: recognises the command's own manifest (:func:`json_manifest`).
        marker: write :data:`MARKER` into a new folder (False for jobs that require an empty folder).
        replace_own: for a command without ``--resume``, write into its own non-empty folder (True) or
            refuse it unless ``force`` (False: outputs that are never silently overwritten, ``export``).

    Yields:
        ``path``, or with ``force`` on a non-empty folder a temporary sibling swapped in on success. A folder
        this call created is removed on failure when nothing but the marker is in it.

    Raises:
        OutputFolderError: a foreign folder, an own one without ``--resume``/``--force``, a file, busy, or
            ``force`` on a non-empty folder at a URL.
    """
    target = storage_path(path)
    with lock_output(target, command):
        if _check(target, command, resume, force, owned, replace_own):
            tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{target.name}-", dir=target.parent))
            try:
                if marker:
                    _write_marker(tmp, command)
                yield tmp
                _swap_in(tmp, target)
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
            return
        created = not target.exists()
        if marker:
            target.mkdir(parents=True, exist_ok=True)
            _write_marker(target, command)
        try:
            yield target
        except BaseException:
            if created and target.is_dir() and not _entries(target):
                remove_tree(target)
            raise


@contextlib.contextmanager
def output_file(
    path: str | os.PathLike[str],
    command: str,
    *,
    force: bool = False,
    owned: Callable[[Path], bool] | None = None,
) -> Iterator[Path]:
    """Lock the output file ``path`` and refuse to overwrite a file that ``owned`` does not recognise.

    Raises:
        OutputFolderError: ``path`` is a folder, a foreign file (without ``force``) or busy.
    """
    target = Path(path)
    with lock_output(target, command):
        if target.is_dir():
            raise OutputFolderError(f"output file '{target}' is a folder; choose another --out")
        if target.exists() and not force and not (owned is not None and owned(target)):
            raise OutputFolderError(
                f"output file '{target}' exists and was not written by 'polarface {command}'; "
                "choose another --out or pass --force to replace it"
            )
        yield target
