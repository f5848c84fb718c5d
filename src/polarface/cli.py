"""The ``polarface`` command line: one subcommand per stage.

Every module in :mod:`polarface.commands` that defines ``NAME``, ``HELP``, ``add_arguments(parser)``
and ``run(args) -> int`` becomes a subcommand; stages add a module, never edit this file. A module may
define ``INTERRUPTED``: what Ctrl-C keeps and how to continue (``{out}`` is the output folder), or
``STAGED = True``: its output is written whole or not at all (``polarface.io.output_folder``, ``staged``).

Errors end in one line on stderr, never a traceback: ``polarface CMD: error: ...`` and exit code 2 for
bad input and failed reads/writes (ValueError, OSError: the path and the reason; an error that carries
``details``, such as a refused resume's differing keys
(:class:`polarface.results.fingerprint.RecordMismatchError`), prints them below it, one indented line
each), ``polarface CMD:
interrupted ...`` and exit code 130 for Ctrl-C, also while the commands are being loaded (``polarface:
interrupted ...``). Once the command has finished, the process's own exit (the interpreter tearing
down torch, numba, Embree: seconds on a busy machine) ignores Ctrl-C: Python restores the default
SIGINT action before that teardown, so a Ctrl-C there killed the process silently with status 130 after
a complete run (``polarface render``'s long teardown showed it). Only :func:`main` called as the
program (``argv`` None: the console script, ``python -m polarface.cli``) does so; a caller's process
keeps its handlers.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import pkgutil
import signal
import sys
from collections.abc import Sequence

import polarface
from polarface import commands

__all__ = ["build_parser", "main"]


def _command_modules() -> list:
    modules = []
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        if all(hasattr(module, attr) for attr in ("NAME", "HELP", "add_arguments", "run")):
            modules.append(module)
    return modules


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Adds "(default: X)" to an option's help unless the help names the default already or there is none."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if (
            not action.option_strings
            or action.default is None
            or action.default is False
            or action.default == []
            or "default" in text
        ):
            return text
        return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every discovered subcommand."""
    parser = argparse.ArgumentParser(
        prog="polarface",
        formatter_class=_HelpFormatter,
        description="Polarimetric BSSRDF acquisition of dynamic faces (Ha et al., ACM TOG 2024).",
    )
    parser.add_argument("--version", action="version", version=f"polarface {polarface.__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv: debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in _command_modules():
        command = sub.add_parser(
            module.NAME, help=module.HELP, description=module.__doc__, formatter_class=_HelpFormatter
        )
        module.add_arguments(command)
        command.set_defaults(_run=module.run, _interrupted=getattr(module, "INTERRUPTED", None),
                             _staged=bool(getattr(module, "STAGED", False)))
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``polarface`` console script; returns the process exit code.

    Args:
        argv: the arguments; None: ``sys.argv[1:]``, and this call is the program (module docstring).
    """
    try:
        return _main(argv)
    finally:
        if argv is None:  # the command is over: the interpreter's teardown is not interruptible
            with contextlib.suppress(ValueError):  # (not the main thread)
                signal.signal(signal.SIGINT, signal.SIG_IGN)


def _main(argv: Sequence[str] | None) -> int:
    try:
        parser = build_parser()  # imports every command module (torch, numba, ...): seconds
        args = parser.parse_args(argv)
    except KeyboardInterrupt:
        print("polarface: interrupted while loading the commands; nothing was run", file=sys.stderr)
        return 130
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose + 1, 2),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except (ValueError, OSError) as exc:
        details = list(getattr(exc, "details", None) or [])
        message = getattr(exc, "message", None) if details else None
        headline = " ".join(str(message).split()) if message else _one_line(exc)
        print(f"polarface {args.command}: error: {headline}", file=sys.stderr)
        for line in details:
            print(f"  {' '.join(str(line).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"polarface {args.command}: {_interrupted_line(args)}", file=sys.stderr)
        return 130


def _one_line(exc: BaseException) -> str:
    """The error as one line; an OSError with a path reads ``'PATH': reason``."""
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        paths = f"'{exc.filename}'" + (f" -> '{exc.filename2}'" if exc.filename2 is not None else "")
        text = f"{paths}: {exc.strerror}"
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(text.split())


def _exists(path: object) -> bool:
    """Whether a local path or URL exists (False when it cannot be told)."""
    from polarface.io.storage import storage_path

    try:
        return storage_path(path).exists()  # type: ignore[arg-type]
    except Exception:  # a message on Ctrl-C must not fail
        return False


def _interrupted_line(args: argparse.Namespace) -> str:
    """What Ctrl-C kept: the command's ``INTERRUPTED`` text with its output folder, if it has one."""
    out = getattr(args, "out", None) or getattr(args, "result", None)
    hint = getattr(args, "_interrupted", None)
    if getattr(args, "_staged", False):
        return "interrupted; nothing was written (the output is written whole or not at all; an existing " \
               "one is left as it was)"  # fmt: skip
    if out is not None and getattr(args, "force", False) and _exists(out):
        return f"interrupted; {out} left as it was (--force replaces it only after a complete run)"
    if hint and out is not None and _exists(out):
        return f"interrupted; {hint.format(out=out)}"
    return "interrupted"


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
