"""Read errors that name the file: the CLI's rule is one line naming the file at fault.

Most readers name their file (``read_exr``, ``read_json_object``, ``Rig.load``); some fail deep in a
parser with no file name (a truncated OBJ: numpy's "setting an array element with a sequence").
:func:`named_read` wraps such a read so that its error names the file.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

__all__ = ["named_read"]

_T = TypeVar("_T")


def named_read(path: object, read: Callable[[], _T]) -> _T:
    """``read()``; an error that does not name ``path`` becomes a ValueError ``cannot read 'PATH': ...``.

    Args:
        path: the file ``read`` reads (a path or URL; named as ``str(path)``).
        read: the reader.

    Raises:
        OSError: as ``read`` raised it (the CLI names its file, or its message does).
        ValueError: any other error of the parser (ValueError, IndexError, KeyError, TypeError,
            RuntimeError, UnicodeDecodeError), naming ``path``.
    """
    try:
        return read()
    except OSError:
        raise
    except (ValueError, IndexError, KeyError, TypeError, RuntimeError) as exc:
        if str(path) in str(exc):
            raise
        raise ValueError(f"cannot read '{path}': {exc}") from exc
