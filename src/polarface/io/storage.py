"""Where a store lives: a local path, or an fsspec URL that a cluster can share.

The capture store, the unwrap store and the RESULT folder take either a local path or a URL
(``memory://...``, ``s3://bucket/key``, ``gs://...``, any protocol of `fsspec
<https://filesystem-spec.readthedocs.io>`_ that zarr v3 supports). :func:`storage_path` turns what the
user gave into one of two kinds:

* a :class:`pathlib.Path` for a local path or a ``file://`` / ``local://`` URL (today's code path:
  temporary name plus rename, ``polarface.io.atomic``);
* a :class:`UrlPath` for anything else: the part of ``pathlib.Path``'s API that the stores use, on the
  URL's fsspec file system. A file is always written whole: :meth:`UrlPath.write_bytes` puts the
  bytes under a temporary key ``.tmp-<stem>-<random><suffix>`` beside the target and then moves it
  (``fs.mv``; on object storage a server-side copy), so a reader or a retried unit never sees half a
  file under the final key. Writers that need a local file (OpenEXR, OpenCV, numpy) write to a local
  temporary file that is uploaded once it is complete (``polarface.io.atomic.atomic_path``); readers
  that need one get a local copy (:func:`local_copy`). zarr arrays are opened through zarr's own
  fsspec support (:func:`open_zarr_group`): a chunk is one object put, so a rewritten chunk replaces
  the old one whole.

Credentials and other options of a protocol come from fsspec's configuration (environment variables
``FSSPEC_<PROTOCOL>_<OPTION>``, e.g. ``FSSPEC_S3_ENDPOINT_URL``, or the protocol package's own, e.g.
``AWS_PROFILE`` for ``s3fs``), or from ``options`` in the Python API; prefer the configuration, which
every process and node reads the same way (some stages pass a location on as a string, which drops
``options``). A ``UrlPath`` pickles as its URL and options, so Ray tasks can receive it (``memory://``
is private to one process, though).

A URL of a file system that lives inside one process (:data:`PROCESS_PRIVATE_PROTOCOLS`: fsspec's
``memory://``) names nothing that another process can read: a command line refuses it
(:func:`process_private`; ``polarface.commands.store_location``), as an input (a fresh process holds
nothing there) and as an output (what it writes would vanish when it exits). The Python API takes it.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import posixpath
import re
import shutil
import tempfile
import uuid
from collections.abc import Iterator, Mapping
from pathlib import Path, PurePosixPath
from typing import Any, TypeAlias

__all__ = [
    "PROCESS_PRIVATE_PROTOCOLS",
    "PathOrUrl",
    "StoragePath",
    "UrlPath",
    "is_url",
    "local_copy",
    "open_zarr_group",
    "process_private",
    "read_head",
    "remove_tree",
    "storage_path",
    "url_protocols",
]

_URL = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]*(://|::)")

#: fsspec protocols whose files live inside one process (module docstring): a command line refuses them.
#: Tests that run a command in-process (``polarface.cli.main``) may empty it to use ``memory://`` as a
#: stand-in for object storage.
PROCESS_PRIVATE_PROTOCOLS: frozenset[str] = frozenset({"memory"})


def is_url(value: object) -> bool:
    """True for a string that starts with a protocol (``memory://``, ``s3://``, ``simplecache::...``)."""
    return isinstance(value, str) and _URL.match(value) is not None


def url_protocols(value: object) -> tuple[str, ...]:
    """The protocols a URL names, outermost first (``"simplecache::s3://b/k"`` -> ``("simplecache",
    "s3")``); ``()`` for a local path or a :class:`~pathlib.Path`."""
    text = value.url if isinstance(value, UrlPath) else value
    if not is_url(text):
        return ()
    return tuple(part.split("://", 1)[0].lower() for part in str(text).split("::") if part)


def process_private(value: object) -> str | None:
    """The protocol of :data:`PROCESS_PRIVATE_PROTOCOLS` that the URL ``value`` uses (a string or a
    :class:`UrlPath`), or None (a local path, a URL that other processes can read)."""
    return next((p for p in url_protocols(value) if p in PROCESS_PRIVATE_PROTOCOLS), None)


def _missing_package(url: str, exc: ImportError) -> ValueError:
    """The error for a URL whose protocol's package is not installed (names the URL and the package)."""
    from fsspec.registry import known_implementations

    protocol = url.split("://", 1)[0].split("::")[-1]
    module = known_implementations.get(protocol, {}).get("class", "").split(".")[0]
    if module and importlib.util.find_spec(module) is None:
        return ValueError(
            f"storage URL '{url}' needs the package '{module}', which is not installed "
            f"(pip install {module}): {exc}"
        )
    return ValueError(f"storage URL '{url}' needs a package that is not installed: {exc}")


def _filesystem(url: str, options: Mapping[str, Any]) -> tuple[Any, str]:
    """``(fsspec file system, path within it)`` of ``url``.

    Raises:
        ValueError: unknown protocol, or the protocol's package is missing (naming the URL).
    """
    import fsspec

    try:
        return fsspec.core.url_to_fs(url, **options)
    except ImportError as exc:
        raise _missing_package(url, exc) from exc
    except ValueError as exc:
        if "Protocol not known" not in str(exc):
            raise ValueError(f"storage URL '{url}': {exc}") from exc
        raise ValueError(
            f"storage URL '{url}': unknown protocol ({exc}); give a local path or a URL of an fsspec file "
            "system (file://, s3://, gs://, ...)"
        ) from exc


class UrlPath:
    """A file or folder named by an fsspec URL, with the part of ``pathlib.Path``'s API the stores use.

    Args:
        url: ``protocol://...``; trailing slashes are dropped.
        options: keyword arguments of the protocol's file system (credentials, endpoint).

    Raises:
        ValueError: an unknown protocol or a missing protocol package (naming the URL).
    """

    __slots__ = ("fs", "options", "path", "url")

    def __init__(self, url: str, options: Mapping[str, Any] | None = None) -> None:
        head, sep, tail = url.rpartition("://")
        self.url = f"{head}{sep}{tail.rstrip('/')}" if sep else url
        self.options = dict(options or {})
        self.fs, self.path = _filesystem(self.url, self.options)

    @classmethod
    def _child(cls, parent: UrlPath, url: str, path: str) -> UrlPath:
        child = cls.__new__(cls)
        child.url, child.options, child.fs, child.path = url, parent.options, parent.fs, path
        return child

    def __reduce__(self) -> tuple[Any, ...]:
        return (UrlPath, (self.url, self.options))

    # ---- names -------------------------------------------------------------------------------
    def __str__(self) -> str:
        return self.url

    def __repr__(self) -> str:
        return f"UrlPath({self.url!r})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, UrlPath) and (self.url, self.options) == (other.url, other.options)

    def __hash__(self) -> int:
        return hash(self.url)

    def __lt__(self, other: UrlPath) -> bool:
        return self.url < other.url

    def __truediv__(self, name: str | os.PathLike[str]) -> UrlPath:
        relative = PurePosixPath(os.fspath(name)).as_posix()
        if relative.startswith("/"):
            raise ValueError(f"cannot join the absolute path '{relative}' to the URL '{self.url}'")
        if relative in ("", "."):
            return self
        return UrlPath._child(self, f"{self.url}/{relative}", f"{self.path.rstrip('/')}/{relative}")

    def joinpath(self, *names: str | os.PathLike[str]) -> UrlPath:
        out = self
        for name in names:
            out = out / name
        return out

    @property
    def name(self) -> str:
        return posixpath.basename(self.path)

    @property
    def stem(self) -> str:
        return PurePosixPath(self.name).stem

    @property
    def suffix(self) -> str:
        return PurePosixPath(self.name).suffix

    @property
    def parent(self) -> UrlPath:
        """The enclosing folder (the URL itself at a protocol's root)."""
        head, sep, tail = self.url.rpartition("://")
        if "/" not in tail.strip("/"):
            return self
        return UrlPath._child(self, f"{head}{sep}{tail.rsplit('/', 1)[0]}", posixpath.dirname(self.path))

    def with_name(self, name: str) -> UrlPath:
        return self.parent / name

    def with_suffix(self, suffix: str) -> UrlPath:
        return self.with_name(self.stem + suffix)

    def relative_to(self, other: UrlPath) -> PurePosixPath:
        """The relative path from ``other`` to this one. Raises ValueError when it is not below ``other``."""
        if not self.url.startswith(other.url.rstrip("/") + "/"):
            raise ValueError(f"'{self.url}' is not below '{other.url}'")
        return PurePosixPath(self.url[len(other.url.rstrip("/")) + 1 :])

    def as_posix(self) -> str:
        return self.url

    def is_absolute(self) -> bool:
        return True

    # ---- queries -----------------------------------------------------------------------------
    def exists(self) -> bool:
        return bool(self.fs.exists(self.path))

    def is_file(self) -> bool:
        return bool(self.fs.isfile(self.path))

    def is_dir(self) -> bool:
        return bool(self.fs.isdir(self.path))

    def _children(self, names: list[str]) -> list[UrlPath]:
        base = self.path.rstrip("/")
        out = []
        for name in names:
            name = name.rstrip("/")
            if name != base and name.startswith(base + "/"):
                out.append(self / name[len(base) + 1 :])
        return sorted(out)

    def iterdir(self) -> Iterator[UrlPath]:
        """The entries of this folder (files and sub-folders); none when it does not exist."""
        try:
            names = self.fs.ls(self.path, detail=False)
        except FileNotFoundError:
            return iter([])
        return iter(self._children(list(names)))

    def glob(self, pattern: str) -> list[UrlPath]:
        """Entries below this folder matching ``pattern`` (fsspec's glob: ``*``, ``?``, ``[...]``, ``**``)."""
        return self._children(list(self.fs.glob(f"{self.path.rstrip('/')}/{pattern}")))

    # ---- reading -----------------------------------------------------------------------------
    def read_bytes(self) -> bytes:
        """The file's content. Raises FileNotFoundError naming the URL."""
        try:
            return bytes(self.fs.cat_file(self.path))
        except FileNotFoundError:
            raise FileNotFoundError(f"'{self.url}' does not exist") from None

    def read_text(self, encoding: str = "utf-8") -> str:
        return self.read_bytes().decode(encoding)

    def open(self, mode: str = "rb"):
        """A read-only file object (``rb`` or ``r``): writes go through :meth:`write_bytes`, whole."""
        if mode not in ("rb", "r"):
            raise ValueError(f"'{self.url}': open() reads only (mode 'rb' or 'r'); write with write_bytes()")
        try:
            handle = self.fs.open(self.path, "rb")
        except FileNotFoundError:
            raise FileNotFoundError(f"'{self.url}' does not exist") from None
        if mode == "r":
            import io

            return io.TextIOWrapper(handle, encoding="utf-8")
        return handle

    # ---- writing -----------------------------------------------------------------------------
    def _publish(self, put) -> None:
        """``put(temporary key)``, then move the temporary key onto this one; on an error nothing new
        appears under this key and the temporary key is removed."""
        temporary = f"{posixpath.dirname(self.path)}/.tmp-{self.stem}-{uuid.uuid4().hex[:12]}{self.suffix}"
        try:
            put(temporary)
            self.fs.mv(temporary, self.path)
        except BaseException:
            with contextlib.suppress(Exception):
                if self.fs.exists(temporary):
                    self.fs.rm_file(temporary)
            raise

    def write_bytes(self, data: bytes) -> int:
        """Put ``data`` under this key whole: to a temporary key beside it, then moved onto it. Returns
        the size."""
        self._publish(lambda temporary: self.fs.pipe_file(temporary, bytes(data)))
        return len(data)

    def upload(self, local: str | os.PathLike[str]) -> None:
        """Put the local file ``local`` under this key whole (streamed from disk; as :meth:`write_bytes`)."""
        self._publish(lambda temporary: self.fs.put_file(os.fspath(local), temporary))

    def write_text(self, text: str, encoding: str = "utf-8") -> int:
        return self.write_bytes(text.encode(encoding))

    def mkdir(self, parents: bool = True, exist_ok: bool = True) -> None:
        """Create the folder where the file system has folders (object stores have none: no-op)."""
        self.fs.makedirs(self.path, exist_ok=True)

    def unlink(self, missing_ok: bool = False) -> None:
        try:
            self.fs.rm_file(self.path)
        except FileNotFoundError:
            if not missing_ok:
                raise FileNotFoundError(f"'{self.url}' does not exist") from None


#: A local path or a URL: what :func:`storage_path` returns.
StoragePath: TypeAlias = Path | UrlPath
#: What the functions taking a store location accept: a path, a path string or a URL string, a UrlPath.
PathOrUrl: TypeAlias = str | os.PathLike[str] | UrlPath


def storage_path(value: PathOrUrl) -> StoragePath:
    """A local path or an fsspec URL as a :class:`~pathlib.Path` (local paths, ``file://`` URLs) or a
    :class:`UrlPath` (every other protocol).

    Raises:
        ValueError: a URL of an unknown protocol or of one whose package is missing (naming the URL).
        TypeError: ``value`` is neither a string nor a path.
    """
    if isinstance(value, UrlPath | Path):
        return value
    if is_url(value):
        url = UrlPath(value)
        from fsspec.implementations.local import LocalFileSystem

        return Path(url.path) if isinstance(url.fs, LocalFileSystem) else url
    return Path(value)


@contextlib.contextmanager
def local_copy(path: PathOrUrl) -> Iterator[Path]:
    """A local file holding ``path``'s content for the duration of the block: ``path`` itself when it is
    local, else a temporary download (same file name) removed afterwards.

    Raises:
        FileNotFoundError: ``path`` does not exist (naming it).
    """
    target = storage_path(path)
    if isinstance(target, Path):
        yield target
        return
    folder = Path(tempfile.mkdtemp(prefix="polarface-download-"))
    try:
        local = folder / (target.name or "file")
        local.write_bytes(target.read_bytes())
        yield local
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def read_head(path: PathOrUrl, size: int) -> bytes:
    """The first ``size`` bytes of a file (one ranged read on object storage). Raises FileNotFoundError."""
    target = storage_path(path)
    if isinstance(target, Path):
        with open(target, "rb") as handle:
            return handle.read(size)
    try:
        return bytes(target.fs.cat_file(target.path, start=0, end=size))
    except FileNotFoundError:
        raise FileNotFoundError(f"'{target}' does not exist") from None


def remove_tree(path: PathOrUrl) -> None:
    """Delete a folder (or file) and everything below it; nothing happens when it does not exist."""
    target = storage_path(path)
    if isinstance(target, Path):
        if target.is_dir():
            shutil.rmtree(target, ignore_errors=True)
        else:
            target.unlink(missing_ok=True)
    elif target.exists():
        target.fs.rm(target.path, recursive=True)


def open_zarr_group(path: PathOrUrl, mode: str):
    """``zarr.open_group`` on a local folder (zarr's LocalStore) or a URL (zarr's FsspecStore).

    Args:
        mode: zarr's ``r``, ``r+``, ``a``, ``w`` or ``w-``.
    """
    import zarr

    target = storage_path(path)
    if isinstance(target, Path):
        return zarr.open_group(str(target), mode=mode)
    return zarr.open_group(target.url, mode=mode, storage_options=target.options or None)
