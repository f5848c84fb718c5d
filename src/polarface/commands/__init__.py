"""Subcommands of the ``polarface`` CLI, one module each (discovered by :mod:`polarface.cli`).

A command module defines ``NAME`` (str), ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``. It parses arguments, calls the library, and writes a documented artifact.
"""
