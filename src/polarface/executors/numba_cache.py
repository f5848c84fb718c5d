"""A numba cache folder per worker process.

numba's on-disk cache is not safe to fill from concurrent processes (numba issues 4807 and 10128; a
process of this project's tests segfaulted so). On a fresh install the worker processes of
``--executor processes`` would otherwise compile the same kernels into the same files at the same time.
Each worker therefore claims a folder of its own before it defines a kernel (the process pool's
initializer, :class:`polarface.executors.ProcessExecutor`).

The price: a worker whose folder is new compiles the kernels afresh, and numba's fresh and cached
parallel code differ in the last bits (docs/cluster.md, "The fused kernel from numba's cache
everywhere"), so the first run on new folders is not bit-identical to a local run that loaded the kernels
from the shared cache; later runs are. A crash outweighs last bits here. Ray workers keep the shared
cache: the Ray tests compare their maps bit for bit with the local executor's, and with folders of their
own those comparisons failed on the first run (measured on the dynamic stage).
"""

from __future__ import annotations

import os
import sys
import tempfile

__all__ = ["claim_numba_cache"]

#: The cache folder a worker holds (its lock file stays open, and so locked, for the process's life).
_CLAIMED: dict[str, object] = {}


def claim_numba_cache(base: str | os.PathLike | None = None, slots: int = 256) -> str | None:
    """Give this process a numba cache folder that no other running process uses; returns it.

    The folder is the first free slot ``BASE/worker-N`` (N < ``slots``), held by an exclusive lock on
    ``BASE/worker-N.lock`` until the process ends, so slots are reused by later runs (their kernels
    stay compiled) and never shared by two live processes. ``BASE``: ``base``, else
    ``$NUMBA_CACHE_DIR/polarface-workers`` when that is set, else ``polarface-numba-workers`` in the
    user's cache folder (``$XDG_CACHE_HOME`` or ``~/.cache``; the temporary folder when that is not
    writable). Must run before the process defines a cached kernel (a worker's initializer). None, and
    nothing changed, where file locks are unavailable (Windows) or every slot is taken.
    """
    if "folder" in _CLAIMED:
        return str(_CLAIMED["folder"])
    try:
        import fcntl
    except ImportError:
        return None
    for root in _cache_roots(base):
        try:
            os.makedirs(root, exist_ok=True)
        except OSError:
            continue
        for slot in range(int(slots)):
            folder = os.path.join(root, f"worker-{slot}")
            try:
                handle = open(folder + ".lock", "a")  # held open, and so locked, for the process's life
            except OSError:
                break  # not writable: the next root
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                handle.close()
                continue
            _CLAIMED.update(folder=folder, handle=handle)
            os.environ["NUMBA_CACHE_DIR"] = folder
            if "numba" in sys.modules:  # imported already: its configuration is read at each decoration
                sys.modules["numba"].config.CACHE_DIR = folder
            return folder
    return None


def _cache_roots(base: str | os.PathLike | None) -> list[str]:
    if base is not None:
        return [os.fspath(base)]
    if os.environ.get("NUMBA_CACHE_DIR"):
        return [os.path.join(os.environ["NUMBA_CACHE_DIR"], "polarface-workers")]
    user = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return [os.path.join(user, "polarface-numba-workers"),
            os.path.join(tempfile.gettempdir(), f"polarface-numba-workers-{os.getuid()}")]
