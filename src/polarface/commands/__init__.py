"""Subcommands of the ``polarface`` CLI, one module each (discovered by :mod:`polarface.cli`).

A command module defines ``NAME`` (str), ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``. It parses arguments, calls the library, and writes a documented artifact.
A library job with several settings takes them as a frozen options dataclass, which the command
builds with :func:`options_from_args` from the arguments of the same names (argparse ``dest``).

Every path argument has one of three ``type`` s, never ``pathlib.Path`` (which turns ``foo://cap`` into a
missing local path ``foo:/cap``): :func:`store_location` (a store, RESULT or output folder that may live at
a URL of a shared file system), :func:`local_folder` (an output folder of this machine) and
:func:`local_path` (a local input or output file or folder). All three refuse, naming the URL as typed, a
URL that no later process can read (``memory://``) and a URL they cannot take, with the reason.
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any, TypeVar

__all__ = [
    "add_executor_arguments",
    "add_force_argument",
    "executor_from_args",
    "local_folder",
    "local_path",
    "options_from_args",
    "store_location",
]

_Options = TypeVar("_Options")


def options_from_args(options_type: type[_Options], args: argparse.Namespace, **values: Any) -> _Options:
    """``options_type(**values)`` with every other field taken from the argument of the same name.

    Args:
        options_type: a dataclass; each of its fields not in ``values`` must be an attribute of ``args``.
        args: the parsed command line.
        values: fields set otherwise (renamed or converted arguments).
    """
    fields = (f.name for f in dataclasses.fields(options_type) if f.name not in values)  # type: ignore[arg-type]
    return options_type(**{name: getattr(args, name) for name in fields}, **values)


def _private_url_error(value: str, protocol: str, *, urls: bool = True) -> argparse.ArgumentTypeError:
    """The error for a URL of a file system private to one process (``memory://``)."""
    instead = "a local path or a URL of a shared file system (file://, s3://, gs://, ...)" if urls else \
        "a local path"  # fmt: skip
    return argparse.ArgumentTypeError(
        f"'{value}' is a URL of {protocol}://, a file system that lives inside one process: no other "
        f"process can read what a command writes there, nor a command what another wrote; give {instead}"
    )


def store_location(value: str):
    """argparse ``type`` of a capture store, RESULT or output folder that may live at a URL: a local path or
    an fsspec URL (``file://``, ``s3://bucket/key``; :func:`polarface.io.storage.storage_path`).

    One rule for every command: a URL of an unknown protocol or a missing package, and a URL that a later
    process cannot read (``memory://``: :func:`polarface.io.storage.process_private`), are argument errors
    naming the URL as typed."""
    from polarface.io.storage import process_private, storage_path

    protocol = process_private(value)
    if protocol is not None:
        raise _private_url_error(value, protocol)
    try:
        return storage_path(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def local_folder(value: str):
    """argparse ``type`` of an output folder that must be local (a shared file system path on a cluster):
    a path or a ``file://`` URL. Another URL is an argument error (rather than a local folder named
    ``s3:``)."""
    from pathlib import Path

    from polarface.io.storage import storage_path

    location = store_location(value)
    if not isinstance(location, Path):
        raise argparse.ArgumentTypeError(
            f"'{value}' is a URL; this command writes a local folder (on a cluster, a path of a shared "
            "file system); write it there and copy it, or give the URL to the commands that take one "
            "(docs/cluster.md, 'Storage')"
        )
    return storage_path(location)


def local_path(value: str):
    """argparse ``type`` of a local file or folder (an input such as ``rig.json``, or an output file): a
    path, or a ``file://`` URL. Any other URL is an argument error naming the URL as typed and why
    (``type=Path`` would turn ``foo://cap`` into a missing local path ``foo:/cap``)."""
    from pathlib import Path

    from fsspec.registry import known_implementations, registry

    from polarface.io.storage import is_url, process_private, url_protocols

    if not is_url(value):
        return Path(value)
    protocols = url_protocols(value)
    if protocols in (("file",), ("local",)):
        return store_location(value)
    private = process_private(value)
    if private is not None:
        raise _private_url_error(value, private, urls=False)
    unknown = [p for p in protocols if p not in known_implementations and p not in registry]
    reason = f"a URL of an unknown protocol '{unknown[0]}'" if unknown else "a URL"
    raise argparse.ArgumentTypeError(
        f"'{value}' is {reason}; this argument takes a local path (a file or folder of this machine)"
    )


def add_force_argument(parser: argparse.ArgumentParser, target: str = "the output folder") -> None:
    """``--force``: replace ``target`` even when this command did not write it; the new output is swapped
    in only once the run succeeds (``polarface.io.output_folder``)."""
    parser.add_argument(
        "--force", action="store_true", help=f"replace {target} (swapped in once the run succeeds)"
    )


def add_executor_arguments(parser: argparse.ArgumentParser, units: str = "units") -> None:
    """``--executor local|processes|ray``, ``--ray-address ADDR``, ``--workers N`` and
    ``--gpus-per-unit G``: how the command's ``units`` run (:mod:`polarface.executors`)."""
    parser.add_argument(
        "--executor", choices=("local", "processes", "ray"), default="local",
        help=f"run the {units} in this process (local, default), in worker processes of this machine "
        "(processes; --workers of them, default one per core) or as Ray tasks (ray; needs "
        "'pip install polarface[cluster]')",
    )
    parser.add_argument(
        "--ray-address", default=None, metavar="ADDR",
        help="Ray cluster to use with --executor ray (HOST:PORT, ray://HOST:PORT or auto; default: start "
        "a local Ray instance)",
    )
    parser.add_argument(
        "--workers", type=int, default=None,
        help=f"with --executor ray: {units} at once, and the CPUs of a local Ray instance (default: all); "
        "with --executor processes: worker processes (default: one per core)",
    )
    parser.add_argument(
        "--gpus-per-unit", type=float, default=None, metavar="G",
        help="with --executor ray: GPUs reserved by each Ray task (default 0; 1 on GPU workers, with "
        "--device auto)",
    )


def executor_from_args(args: argparse.Namespace):
    """The executor of :func:`add_executor_arguments`'s arguments, not started
    (:func:`polarface.executors.create_executor`)."""
    from polarface.executors import create_executor

    return create_executor(args.executor, address=args.ray_address, workers=args.workers,
                           gpus_per_unit=args.gpus_per_unit)
