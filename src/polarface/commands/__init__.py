"""Subcommands of the ``polarface`` CLI, one module each (discovered by :mod:`polarface.cli`).

A command module defines ``NAME`` (str), ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``. It parses arguments, calls the library, and writes a documented artifact.
A library job with several settings takes them as a frozen options dataclass, which the command
builds with :func:`options_from_args` from the arguments of the same names (argparse ``dest``).
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


def store_location(value: str):
    """argparse ``type`` of a capture store or RESULT argument: a local path or an fsspec URL
    (``file://``, ``memory://``, ``s3://bucket/key``; :func:`polarface.io.storage.storage_path`). A URL of
    an unknown protocol or a missing package is an argument error naming it."""
    from polarface.io.storage import storage_path

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
