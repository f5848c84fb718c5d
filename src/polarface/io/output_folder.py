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
* ``staged``: for commands whose output is all or nothing (``export``, ``render``, ``stokes``,
  ``skin-fit``, ``evaluate --figures``): a new folder, and the command's own folder it rewrites, are
  written into a temporary sibling too, renamed onto the output only once the command succeeded; a failed
  or interrupted run leaves no output behind (a new folder is not created, an own one is left as it
  was). Commands that continue their own folder after an interruption (``reconstruct --resume``,
  ``simulate``, ``ingest``, ``demo``) are not staged: what they finished is what they resume from.
* The lock is the file ``.NAME.polarface.lock`` *beside* the output (``{"pid", "command", "path"}``, created
  with ``O_CREAT | O_EXCL``): beside, not inside, because some jobs require an empty folder, a file output
  cannot hold it, and ``--force`` swaps the folder. A lock whose pid no longer runs is stale and is taken
  over with a warning. A second process is refused at once with an error naming the first one's pid.
* An output at a URL (``s3://``, ``gs://``; :mod:`polarface.io.storage`) follows the same policy
  except that it is not locked (object storage has no exclusive create that every fsspec file system
  offers, and a pid means nothing on another machine: one writer per URL is the user's job), that
  ``--force`` on a non-empty one is refused (a folder cannot be swapped in without a rename) and that
  ``staged`` writes a new one in place and removes it whole when the run fails.

**Outputs apart from inputs** (``inputs=``, :func:`check_apart`). A command never deletes what it did not
write, so an output folder (or file) must not be, contain or lie inside one of the command's inputs (the
RESULT that ``export`` reads, the ``--gt`` simulation of ``evaluate``, the raw frame of ``stokes``, ...):
``--force`` on such a folder would swap the input away, and a file written into an input folder would mix
a command's output into what another command owns. The one exception is a sub-folder that the input's
layout reserves for this command's outputs (``reserved=``), where the command reads nothing and which it
rewrites whole: ``RESULT/exports`` of ``export`` and ``RESULT/render`` of ``render`` (their defaults), and
anything below them. Paths are compared after resolving symbolic links (``os.path.realpath``); URLs by their
text, so a local path and a URL never overlap. A command that updates one of its inputs in place by design
(``calibrate`` and ``calibrate-polarization`` rewriting ``--rig``) does not list that input.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path

from polarface.io.atomic import write_json_atomic
from polarface.io.storage import PathOrUrl, StoragePath, UrlPath, remove_tree, storage_path

__all__ = [
    "MARKER",
    "OutputFolderError",
    "check_apart",
    "json_manifest",
    "lock_output",
    "output_file",
    "output_folder",
]

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


# ---- outputs apart from inputs -------------------------------------------------------------------
def _comparable(path: PathOrUrl) -> str:
    """``path`` as text to compare: the resolved absolute local path, or the URL without trailing ``/``."""
    target = storage_path(path)
    if isinstance(target, UrlPath):
        return target.url.rstrip("/")
    return os.path.realpath(target)


def _within(inner: str, outer: str) -> bool:
    """Whether ``inner`` is ``outer`` or lies below it (both :func:`_comparable`)."""
    return inner == outer or inner.startswith(outer.rstrip("/") + "/")


#: What a command reads, for :func:`check_apart`: a label naming the argument -> a path, several paths, or
#: None (skipped).
Inputs = Mapping[str, PathOrUrl | Sequence[PathOrUrl] | None]


def check_apart(
    out: PathOrUrl,
    inputs: Inputs,
    *,
    argument: str = "--out",
    reserved: Iterable[PathOrUrl] = (),
) -> None:
    """Refuse an output that is, contains or lies inside one of the command's inputs (module docstring).

    Args:
        out: the output folder or file, as the user gave it.
        inputs: what the command reads: a label naming the argument (``"RESULT"``, ``"--gt"``) -> its
            path (a folder or a file), a list of paths (``--images``), or None (skipped).
        argument: the output's option as the user types it (named in the error).
        reserved: sub-folders of an input reserved for this command's outputs (``RESULT/exports``):
            ``out`` may be one of them or lie below one.

    Raises:
        OutputFolderError: naming ``argument``, the output, the input's label and its path.
    """
    where = _comparable(out)
    allowed = [_comparable(path) for path in reserved]
    pairs = [(label, v) for label, values in inputs.items() if values is not None
             for v in (values if isinstance(values, list | tuple) else [values])]
    for label, value in pairs:
        source = _comparable(value)
        if _within(source, where):
            relation, advice = ("is", f"another {argument}") if source == where else \
                ("contains", f"an {argument} that does not hold it")  # fmt: skip
            raise OutputFolderError(
                f"argument '{argument}': '{out}' {relation} the input {label} '{value}', which this command "
                f"reads (a command never replaces or deletes its inputs); choose {advice}"
            )
        if _within(where, source) and not any(_within(where, path) for path in allowed):
            hint = f" (or {', '.join(repr(str(path)) for path in reserved)})" if allowed else ""
            raise OutputFolderError(
                f"argument '{argument}': '{out}' lies inside the input {label} '{value}', which this command "
                f"reads (its outputs do not go into its inputs); choose an {argument} outside it{hint}"
            )


# ---- the folder policy ---------------------------------------------------------------------------
def _entries(folder: StoragePath) -> list[str]:
    return [p.name for p in folder.iterdir() if p.name != MARKER]


def _is_own(folder: StoragePath, command: str, owned: Callable[[StoragePath], bool] | None) -> bool:
    if json_manifest(MARKER, format=_FORMAT, command=command)(folder):
        return True
    return owned is not None and owned(folder)


def _check(target: StoragePath, command: str, resume: bool | None, force: bool | None, owned,
           replace_own: bool = True, argument: str = "--out") -> bool:
    """Apply the policy; returns whether the command must write into a temporary sibling (``force``;
    None: the output has no ``--force``, which the errors then do not suggest)."""
    if resume and force:
        raise OutputFolderError("arguments '--resume' and '--force' exclude each other")
    if target.exists() and not target.is_dir():
        raise OutputFolderError(
            f"output folder '{target}' is a file, not a folder; choose another {argument}"
        )
    if not target.exists() or not _entries(target):
        return False
    if force and isinstance(target, UrlPath):
        raise OutputFolderError(
            f"argument '--force': output '{target}' is at a URL, where a folder cannot be swapped in "
            f"(no rename); remove it first or choose another {argument}"
        )
    if force:
        return True
    if not _is_own(target, command, owned):
        raise OutputFolderError(
            f"output folder '{target}' is not empty and was not written by 'polarface {command}'; "
            f"choose another {argument}" + (" or pass --force to replace it" if force is not None else "")
        )
    if resume is None and not replace_own:
        raise OutputFolderError(
            f"output folder '{target}' holds a previous 'polarface {command}' run; pass --force to "
            f"replace it or choose another {argument}"
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


def _publish_mode(folder: Path) -> None:
    """Give a folder made by ``mkdtemp`` (0700) the permissions a plain ``mkdir`` would have had."""
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(folder, 0o777 & ~mask)


def _swap_in(tmp: Path, target: Path) -> None:
    """Replace ``target`` by the complete ``tmp`` (``target`` absent: a rename); an old folder is removed
    only after the rename."""
    _publish_mode(tmp)
    if not target.exists():
        os.replace(tmp, target)
        return
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
    force: bool | None = False,
    owned: Callable[[StoragePath], bool] | None = None,
    marker: bool = True,
    replace_own: bool = True,
    staged: bool = False,
    inputs: Inputs | None = None,
    reserved: Iterable[PathOrUrl] = (),
    argument: str = "--out",
) -> Iterator[StoragePath]:
    """Lock ``path``, apply the policy (module docstring) and yield the folder the command writes into.

    Args:
        path: the output folder (``--out``): a local path or a URL (module docstring).
        command: the subcommand name (recorded in the marker and the lock).
        resume: ``--resume`` of commands that have it, else None (module docstring).
        force: ``--force``: replace the folder, swapping only after the ``with`` body succeeded; None: the
            command has no ``--force`` for this output (a foreign folder is refused without suggesting it).
        owned: recognises the command's own manifest (:func:`json_manifest`).
        marker: write :data:`MARKER` into a new folder (False for jobs that require an empty folder).
        replace_own: for a command without ``--resume``, write into its own non-empty folder (True) or
            refuse it unless ``force`` (False: outputs that are never silently overwritten, ``export``).
        staged: write a new (or own) folder into a temporary sibling renamed onto ``path`` on success
            (module docstring); False: write in place, so that an interrupted run can be continued.
        inputs: the command's inputs, label -> path (:func:`check_apart`), checked before anything else.
        reserved: sub-folders of an input where this output may lie (:func:`check_apart`).
        argument: the output's option as the user types it (named in the errors).

    Yields:
        ``path``, or a temporary sibling (``force`` on a non-empty folder, ``staged``) renamed onto ``path``
        on success. A folder this call created in place is removed on failure when nothing but the marker
        is in it (``staged`` at a URL: whatever is in it).

    Raises:
        OutputFolderError: an output that is, contains or lies inside an input, a foreign folder, an own one
            without ``--resume``/``--force``, a file, busy, or ``force`` on a non-empty folder at a URL.
    """
    target = storage_path(path)
    if inputs:
        check_apart(target, inputs, argument=argument, reserved=reserved)
    with lock_output(target, command):
        swap = _check(target, command, resume, force, owned, replace_own, argument)
        if swap or (staged and isinstance(target, Path)):
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
            if created and target.is_dir() and (staged or not _entries(target)):
                remove_tree(target)
            raise


@contextlib.contextmanager
def output_file(
    path: str | os.PathLike[str],
    command: str,
    *,
    force: bool = False,
    owned: Callable[[Path], bool] | None = None,
    inputs: Inputs | None = None,
    argument: str = "--out",
) -> Iterator[Path]:
    """Lock the output file ``path`` and refuse to overwrite a file that ``owned`` does not recognise.

    Args:
        inputs: the command's inputs, label -> path: ``path`` must not be one nor lie inside one
            (:func:`check_apart`). argument: the output's option as the user types it.

    Raises:
        OutputFolderError: ``path`` is or lies inside an input, is a folder, a foreign file (without
            ``force``) or busy.
    """
    target = Path(path)
    if inputs:
        check_apart(target, inputs, argument=argument)
    with lock_output(target, command):
        if target.is_dir():
            raise OutputFolderError(f"output file '{target}' is a folder; choose another {argument}")
        if target.exists() and not force and not (owned is not None and owned(target)):
            raise OutputFolderError(
                f"output file '{target}' exists and was not written by 'polarface {command}'; "
                f"choose another {argument} or pass --force to replace it"
            )
        yield target
